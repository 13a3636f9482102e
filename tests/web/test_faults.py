"""Faults and robustness: killed workers, cancel, restart, concurrency, Dask."""

from __future__ import annotations

import datetime as dt
import os
import signal
import time
from pathlib import Path

import pandas as pd
import pytest

from .conftest import import_zip, wait_job


def _wait_running(client, job_id, timeout=60.0) -> dict:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        j = client.get(f"/api/jobs/{job_id}").json()
        if j["status"] == "running" and j["em_iterations"]:
            return j
        assert j["status"] in ("queued", "running"), j
        time.sleep(0.05)
    raise AssertionError("job never got running")


def _run_ok(client, sid) -> dict:
    j = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    j = wait_job(client, j["id"])
    assert j["status"] == "succeeded", j
    return j


def test_killed_worker_fails_job_and_keeps_previous_results(client, tiny_zip, monkeypatch):
    sid = import_zip(client, tiny_zip).json()["id"]
    _run_ok(client, sid)
    before = client.get(f"/api/surveys/{sid}").json()
    grid_before = client.get(f"/api/surveys/{sid}/grid").json()["dg"]

    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "2")
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    _wait_running(client, job["id"])
    pid = client.app.state.jobs.worker_pid(job["id"])
    assert pid and pid != os.getpid()
    os.kill(pid, signal.SIGKILL)
    j = wait_job(client, job["id"], timeout=20)
    assert j["status"] == "failed" and "SIGKILL" in j["error"], j
    after = client.get(f"/api/surveys/{sid}").json()
    assert after["current_result_id"] == before["current_result_id"]
    assert after["flights"] == before["flights"] and after["n_lines"] == before["n_lines"]
    assert client.get(f"/api/surveys/{sid}/grid").json()["dg"] == grid_before
    out = Path(client.app.state.settings.data_dir) / "surveys" / str(sid) / "results"
    assert not list(out.glob("*.partial"))  # the half-written output was removed
    # the survey can be processed again
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "0.01")
    again = _run_ok(client, sid)
    assert client.get(f"/api/surveys/{sid}").json()["current_result_id"] != before["current_result_id"]
    assert again["id"] != job["id"]


def test_cancel_running_job(client, tiny_zip, monkeypatch):
    sid = import_zip(client, tiny_zip).json()["id"]
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "2")
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "identify"}).json()
    # a second job on the same survey is refused while the first is active
    assert client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).status_code == 409
    _wait_running(client, job["id"])
    r = client.post(f"/api/jobs/{job['id']}/cancel")
    assert r.status_code == 200 and r.json()["status"] == "cancelled"
    time.sleep(0.5)
    j = client.get(f"/api/jobs/{job['id']}").json()
    assert j["status"] == "cancelled" and j["error"] is None
    assert client.get(f"/api/surveys/{sid}").json()["current_result_id"] is None


def test_cancelled_rerun_keeps_the_result_and_says_whose_it_is(client, tiny_zip, monkeypatch):
    """A processed survey whose next job was cancelled: ``last_job`` is the cancelled job, the result
    stays current and ``result_job_id`` names the job that computed it (the survey list said
    "cancelled" from ``last_job`` alone, as if the survey had no result)."""
    sid = import_zip(client, tiny_zip).json()["id"]
    assert client.get(f"/api/surveys/{sid}").json()["result_job_id"] is None
    done = _run_ok(client, sid)
    before = client.get(f"/api/surveys/{sid}").json()
    assert before["result_job_id"] == done["id"] and before["last_job"]["id"] == done["id"]
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "2")
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    _wait_running(client, job["id"])
    assert client.post(f"/api/jobs/{job['id']}/cancel").json()["status"] == "cancelled"
    after = client.get(f"/api/surveys/{sid}").json()
    assert after["last_job"]["id"] == job["id"] and after["last_job"]["status"] == "cancelled"
    assert after["current_result_id"] == before["current_result_id"]
    assert after["result_job_id"] == done["id"]
    listed = {s["id"]: s for s in client.get("/api/surveys").json()}[sid]
    assert listed["result_job_id"] == done["id"] and listed["last_job"]["status"] == "cancelled"


def test_restart_keeps_everything_and_fails_running_jobs(make_client, tiny_zip, monkeypatch):
    c1 = make_client()
    sid = import_zip(c1, tiny_zip).json()["id"]
    done = _run_ok(c1, sid)
    sid2 = import_zip(c1, tiny_zip).json()["id"]
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "2")
    running = c1.post(f"/api/surveys/{sid2}/jobs", json={"kind": "process"}).json()
    _wait_running(c1, running["id"])

    c2 = make_client()  # a new server on the same data directory
    assert [s["id"] for s in c2.get("/api/surveys").json()] == [sid, sid2]
    assert c2.get(f"/api/jobs/{done['id']}").json()["status"] == "succeeded"
    j = c2.get(f"/api/jobs/{running['id']}").json()
    assert j["status"] == "failed" and j["error"] == "server restarted"
    assert c2.get(f"/api/surveys/{sid}/qc").json()["lines"]
    assert c2.get(f"/api/surveys/{sid}/grid").status_code == 200
    assert c2.get(f"/api/surveys/{sid}/lines/L1").json()["n_total"] > 0
    # the orphaned worker of the old server can no longer switch the survey's results
    c1.app.state.jobs.shutdown()
    assert c2.get(f"/api/surveys/{sid2}").json()["current_result_id"] is None


def test_two_jobs_on_two_surveys_run_concurrently(client, tiny_zip, monkeypatch):
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "0.3")
    a = import_zip(client, tiny_zip).json()["id"]
    b = import_zip(client, tiny_zip).json()["id"]
    ja = client.post(f"/api/surveys/{a}/jobs", json={"kind": "process"}).json()
    jb = client.post(f"/api/surveys/{b}/jobs", json={"kind": "process"}).json()
    ra, rb = wait_job(client, ja["id"], 90), wait_job(client, jb["id"], 90)
    assert ra["status"] == rb["status"] == "succeeded"
    t = {k: (dt.datetime.fromisoformat(j["started_at"]), dt.datetime.fromisoformat(j["finished_at"]))
         for k, j in (("a", ra), ("b", rb))}
    assert t["a"][0] < t["b"][1] and t["b"][0] < t["a"][1], t  # the running intervals overlap
    assert client.get(f"/api/surveys/{a}").json()["current_result_id"] != client.get(f"/api/surveys/{b}").json()["current_result_id"]


def test_dask_cluster_gives_same_results_as_local_pool(make_client, tiny_zip, tmp_path):
    distributed = pytest.importorskip("distributed")
    local = make_client(data_dir=tmp_path / "local")
    sid = import_zip(local, tiny_zip).json()["id"]
    _run_ok(local, sid)
    with distributed.LocalCluster(n_workers=1, processes=False, threads_per_worker=1, host="127.0.0.1", protocol="tcp://",
                                  dashboard_address=None) as cluster:
        dc = make_client(data_dir=tmp_path / "dask", dask_scheduler=cluster.scheduler_address)
        sid_d = import_zip(dc, tiny_zip).json()["id"]
        job = dc.post(f"/api/surveys/{sid_d}/jobs", json={"kind": "process"}).json()
        assert job["backend"] == "dask"
        j = wait_job(dc, job["id"], 60)
        assert j["status"] == "succeeded", j
        assert len(j["em_iterations"]) == 3
        assert dc.get(f"/api/surveys/{sid_d}/grid").json()["dg"] == local.get(f"/api/surveys/{sid}/grid").json()["dg"]
        a = local.get(f"/api/surveys/{sid}/export", params={"format": "parquet"}).content
        b = dc.get(f"/api/surveys/{sid_d}/export", params={"format": "parquet"}).content
        import io
        pd.testing.assert_frame_equal(pd.read_parquet(io.BytesIO(a)), pd.read_parquet(io.BytesIO(b)))
