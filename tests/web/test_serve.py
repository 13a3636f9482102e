"""`aerograv serve --bootstrap`: import a survey directory into an empty store and process it."""

from __future__ import annotations

import time

from app.web.serve import bootstrap_store

from .conftest import wait_job


def test_bootstrap_imports_and_processes_once(client, tiny_survey):
    job_id = bootstrap_store(client.app, tiny_survey)
    assert job_id is not None
    surveys = client.get("/api/surveys").json()
    assert len(surveys) == 1 and surveys[0]["name"] == "tiny" and surveys[0]["flights"] == ["f1"]
    j = wait_job(client, job_id)
    assert j["status"] == "succeeded", j
    # the finished job's recognition map is pre-loaded for the first slider move
    rid = client.get(f"/api/surveys/{surveys[0]['id']}").json()["current_result_id"]
    t_end = time.monotonic() + 10
    while ("recognition", rid) not in client.app.state.cache._d and time.monotonic() < t_end:
        time.sleep(0.1)
    assert ("recognition", rid) in client.app.state.cache._d
    # not empty any more: a second bootstrap does nothing
    assert bootstrap_store(client.app, tiny_survey) is None
    assert len(client.get("/api/surveys").json()) == 1
