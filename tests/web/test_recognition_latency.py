"""Interactive re-smoothing stays fast on a 74-line survey (SPEC §2 step 4: well under a second)."""

from __future__ import annotations

import importlib.util
import json
import time
from pathlib import Path

from app.web.db import Job, Result, Survey

ROOT = Path(__file__).resolve().parents[2]


def _bench_module():
    spec = importlib.util.spec_from_file_location("bench_web", ROOT / "benchmarks" / "bench_web.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_recognition_resmoothing_latency_74_lines(client):
    rec = _bench_module().synthetic_recognition(74)
    app = client.app
    d = Path(app.state.settings.data_dir) / "surveys" / "bench" / "results" / "job-1"
    d.mkdir(parents=True)
    rec.to_parquet(d / "recognition.parquet", index=False)
    (d / "identification.json").write_text(json.dumps({"states": [{"index": 0, "Q": 0.04, "R": 1.7},
                                                                  {"index": 1, "Q": 0.35, "R": 1.7}]}))
    with app.state.Session() as db:
        s = Survey(name="bench")
        db.add(s)
        db.flush()
        j = Job(survey_id=s.id, kind="process", status="succeeded", progress=1.0, params={}, em_iterations=[])
        db.add(j)
        db.flush()
        r = Result(survey_id=s.id, job_id=j.id, dir=str(d), report={})
        db.add(r)
        db.flush()
        s.current_result_id = r.id
        db.commit()
        sid = s.id
    first = client.get(f"/api/surveys/{sid}/recognition").json()
    assert first["n_points"] == len(rec) > 7000
    worst = 0.0
    prev = None
    for h, rho in [(1.4, 5), (0.5, 10), (0.0, 15), (3.0, 2), (1.0, 8)]:
        t0 = time.perf_counter()
        r = client.get(f"/api/surveys/{sid}/recognition", params={"h": h, "rho": rho, "coords": False})
        worst = max(worst, time.perf_counter() - t0)
        assert r.status_code == 200 and len(r.json()["state"]) == len(rec)
        assert r.json()["state"] != prev
        prev = r.json()["state"]
    assert worst < 0.3, f"re-smoothing took {1000 * worst:.0f} ms for {len(rec)} points"
