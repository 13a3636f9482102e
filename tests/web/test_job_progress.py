"""The progress a real job reports: one plan of stages known up front, each EM run (one per anomaly
order) in its own share of the bar — the second run moves the bar on instead of holding it — the
stage named with its run, and a fraction that never decreases, from the pipeline's callback and as
the web's job record shows it."""

from __future__ import annotations

import time

import pytest

from .conftest import import_zip, make_tiny_survey, zip_dir

REAL = "app.pipeline.process:run_job"

pytestmark = [pytest.mark.slow]


def _record(fn, *args) -> list[tuple[str, float]]:
    seq: list[tuple[str, float]] = []
    fn(*args, progress=lambda stage, fraction, info=None: seq.append((stage, float(fraction))))
    return seq


def _non_decreasing(seq):
    bad = [(a, b) for a, b in zip(seq, seq[1:]) if b[1] < a[1]]
    assert not bad, bad[:5]


def test_process_progress_never_decreases_and_the_second_em_run_moves_it(tmp_path):
    from app.pipeline.process import filter_from, identify_survey, process_survey

    survey = make_tiny_survey(tmp_path / "tiny")
    seq = _record(process_survey, survey, tmp_path / "out")
    _non_decreasing(seq)
    assert seq[0] == ("ingest", 0.0) and seq[-1] == ("done", 1.0)
    # the tiny survey has too few crossovers to choose the order: m = 1 and m = 2 are both identified
    first = [f for s, f in seq if s.startswith("learning (m=1, run 1 of 2)")]
    second = [f for s, f in seq if s.startswith("learning (m=2, run 2 of 2)")]
    assert len(first) > 2 and len(second) > 2, sorted({s for s, _ in seq})
    assert min(second) > max(first)            # its own share, after the first run's
    assert second[-1] > second[0]              # moving while the second EM runs
    # the stages in their order, named as before (the run in brackets)
    names = [s.split(" (")[0] for s, _ in seq]
    order = list(dict.fromkeys(names))
    assert order == ["ingest", "measurement", "noise", "fir", "regularization", "learning", "recognition",
                     "nlmeans", "filtering", "level_check", "choice", "leveling", "gridding", "writing", "done"]

    # an identify job ends near the end of its own bar, a filter job starts near the start of its own
    ident = _record(identify_survey, survey, tmp_path / "ident")
    _non_decreasing(ident)
    assert [f for s, f in ident if s != "done"][-1] > 0.8
    filt = _record(filter_from, tmp_path / "ident", tmp_path / "filt")
    _non_decreasing(filt)
    assert [f for s, f in filt if s.startswith("nlmeans")][0] < 0.3


def test_a_real_jobs_progress_never_steps_back(make_client, tmp_path):
    client = make_client(pipeline_entry=REAL, poll_interval_s=0.05)
    sid = import_zip(client, zip_dir(make_tiny_survey(tmp_path / "tiny"))).json()["id"]
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    seen, t_end = [], time.monotonic() + 180
    while True:
        j = client.get(f"/api/jobs/{job['id']}").json()
        seen.append((j["stage"], j["progress"]))
        if j["status"] not in ("queued", "running"):
            break
        assert time.monotonic() < t_end, j
        time.sleep(0.02)
    assert j["status"] == "succeeded", j
    _non_decreasing(seen)
    assert seen[-1] == ("done", 1.0)
    assert len({p for _, p in seen}) > 4, seen      # watched while it ran, not only its end
