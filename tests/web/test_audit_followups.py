"""Follow-ups of the attacker audit: invisible-only names, warnings of an upload shown to the client,
the recognition view cached, the /tracks and /qc listings paginated."""

from __future__ import annotations

from pathlib import Path

import pytest

from .conftest import import_zip, make_tiny_survey, zip_dir


@pytest.fixture(scope="module")
def tiny_src(tmp_path_factory) -> Path:
    return make_tiny_survey(tmp_path_factory.mktemp("followups") / "tiny", name="tiny")


# ---------------------------------------------------------------- 1. names with nothing visible
@pytest.mark.parametrize("name", ["\u200b", "\u2060\ufeff", "\u0301\u0308", "\u3000"])
def test_invisible_survey_name_refused_naming_the_field(client, name):
    r = client.post("/api/surveys", json={"name": name})
    assert r.status_code == 422, r.text
    err = r.json()["detail"][0]
    assert err["loc"][-1] == "name"
    assert "visible" in err["msg"] or "empty" in err["msg"]
    assert client.get("/api/surveys").json() == []


def test_names_in_other_scripts_accepted(client):
    for name in ("Съёмка Камчатка", "航空重力測量", "Café Müller-Øst"):
        r = client.post("/api/surveys", json={"name": name})
        assert r.status_code == 201, r.text
        assert r.json()["name"] == name


def test_patch_invisible_model_refused(client, tiny_src):
    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    r = client.patch(f"/api/surveys/{sid}", json={"gravimeter": {"model": "\u200b\u2060"}})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["gravimeter", "model"]
    r = client.patch(f"/api/surveys/{sid}", json={"survey": {"name": "\ufeff"}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["survey", "name"]
    assert client.get(f"/api/surveys/{sid}").json()["settings"]["gravimeter"]["model"] == "GT-1A"


# ---------------------------------------------------------------- 2. an upload's warnings reach the client
GARBAGE = {"gravimeter": ("g.csv", b"\x00\x01garbage\xff", "text/csv"),
           "gnss": ("n.csv", b"nonsense,,\n1,2\n", "text/csv")}


def test_unused_garbage_flight_upload_says_so(client, tiny_src):
    imp = import_zip(client, zip_dir(tiny_src))
    assert imp.status_code == 201 and imp.json()["warnings"] == []
    sid = imp.json()["id"]
    r = client.post(f"/api/surveys/{sid}/flights", data={"flight": "junk"}, files=GARBAGE)
    assert r.status_code == 201, r.text
    body = r.json()
    assert any(w.startswith("flight junk is not read") and "flights/junk/gnss.csv" in w for w in body["warnings"])
    data_dir = str(client.app.state.settings.data_dir)
    assert not any(data_dir in w or "/tmp" in w for w in body["warnings"])    # no server path
    assert body["flights"] == ["f1"]             # stored, left out of the survey: what the warning says
    # a plain GET carries no warnings field (the upload's answer does)
    assert "warnings" not in client.get(f"/api/surveys/{sid}").json()
    ok = client.post(f"/api/surveys/{sid}/flights", data={"flight": "f1"}, files={
        "gravimeter": ("g.csv", (tiny_src / "flights/f1/gravimeter.csv").read_bytes(), "text/csv"),
        "gnss": ("n.csv", (tiny_src / "flights/f1/gnss.csv").read_bytes(), "text/csv")})
    assert ok.status_code == 201
    assert any("flight junk" in w for w in ok.json()["warnings"])   # still there: every flight's warnings


def test_import_with_unused_garbage_flight_says_so(client, tiny_src):
    from .conftest import zip_with
    data = zip_with(tiny_src, {"flights/ferry/gravimeter.csv": b"not,a\nfile", "flights/ferry/gnss.csv": b"\xff\xfe"})
    r = import_zip(client, data)
    assert r.status_code == 201, r.text
    assert any(w.startswith("flight ferry is not read") for w in r.json()["warnings"])


def test_reader_notes_bounded_and_relative(tmp_path):
    from types import SimpleNamespace

    from app.web.services import MAX_UPLOAD_WARNINGS, reader_notes
    root = tmp_path / "staging" / "survey"
    root.mkdir(parents=True)
    notes = [f"file {root}/flights/f{i}/gnss.csv: odd" for i in range(MAX_UPLOAD_WARNINGS + 5)] + ["x" * 5000]
    out = reader_notes(SimpleNamespace(notes=notes), root)
    assert len(out) == MAX_UPLOAD_WARNINGS + 1 and out[0] == "file flights/f0/gnss.csv: odd"
    assert out[-1].startswith("… and 6 more warnings")
    assert reader_notes(SimpleNamespace(notes=["y" * 5000]), root)[0].endswith("(5,000 characters)")
    assert reader_notes(object(), root) == []


# ---------------------------------------------------------------- 3. the re-smoothed recognition map kept
def _bench():
    import importlib.util
    spec = importlib.util.spec_from_file_location("bench_web", Path(__file__).resolve().parents[2] / "benchmarks"
                                                  / "bench_web.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture
def counted_state_map(monkeypatch):
    """Count (and slow down a little) the calls of the pipeline's NL-means map by the endpoint."""
    import time

    from app.web.routers import results

    calls = []
    real = results.state_map

    def counting(*a, **kw):
        calls.append(a[1:4])
        time.sleep(0.05)
        return real(*a, **kw)
    monkeypatch.setattr(results, "state_map", counting)
    return calls


def test_recognition_repeat_request_not_recomputed(client, counted_state_map):
    from concurrent.futures import ThreadPoolExecutor
    bench = _bench()
    sid = bench.store_recognition_result(client.app, bench.synthetic_recognition(8), "rec")
    url = f"/api/surveys/{sid}/recognition"
    a = client.get(url, params={"h": 0.7, "rho": 5, "coords": False}).json()
    b = client.get(url, params={"h": 0.70, "rho": 5.0, "coords": False}).json()
    assert len(counted_state_map) == 1
    assert a["state"] == b["state"] and a["p_max"] == b["p_max"]
    client.get(url, params={"h": 0.7, "rho": 5, "mode": "hard", "coords": False})
    client.get(url, params={"h": 0.9, "rho": 5, "coords": False})
    assert len(counted_state_map) == 3                  # another mode or h: smoothed
    with ThreadPoolExecutor(4) as ex:                   # concurrent identical requests: once
        outs = list(ex.map(lambda _: client.get(url, params={"h": 2.0, "rho": 3, "coords": False}), range(4)))
    assert all(o.status_code == 200 for o in outs) and len(counted_state_map) == 4
    assert len({tuple(o.json()["state"]) for o in outs}) == 1


def test_recognition_new_result_not_served_stale(client, counted_state_map):
    from app.web.db import Job, Result, Survey
    bench = _bench()
    rec = bench.synthetic_recognition(8)
    sid = bench.store_recognition_result(client.app, rec, "rec")
    url = f"/api/surveys/{sid}/recognition"
    params = {"h": 0.5, "rho": 4, "coords": False}
    first = client.get(url, params=params).json()
    flipped = rec.copy()
    flipped["p_0"], flipped["p_1"] = rec["p_1"], rec["p_0"]
    flipped["state_raw"] = flipped["state_smoothed"] = 1 - rec["state_raw"]
    with client.app.state.Session() as db:            # a new result of the same survey, as a job gives one
        s = db.get(Survey, sid)
        j = Job(survey_id=sid, kind="process", status="succeeded", progress=1.0, params={}, em_iterations=[])
        db.add(j)
        db.flush()
        d = Path(client.app.state.settings.data_dir) / "surveys" / str(sid) / "results" / f"job-{j.id}"
        d.mkdir(parents=True)
        flipped.to_parquet(d / "recognition.parquet", index=False)
        (d / "identification.json").write_text((Path(db.get(Result, s.current_result_id).dir)
                                                / "identification.json").read_text())
        r = Result(survey_id=sid, job_id=j.id, dir=str(d), report={})
        db.add(r)
        db.flush()
        s.current_result_id = r.id
        db.commit()
    second = client.get(url, params=params).json()
    assert second["result_id"] != first["result_id"] and len(counted_state_map) == 2
    assert second["state"] == [1 - x for x in first["state"]]
    # deleting the survey drops its maps (ids may be reused)
    assert client.delete(f"/api/surveys/{sid}").status_code == 204
    assert not [k for k in client.app.state.views._d if k[1] in (first["result_id"], second["result_id"])]


def test_recognition_views_memory_bounded():
    import numpy as np

    from app.web.store import ResultCache
    views = ResultCache(size=3, max_bytes=10_000)
    for i in range(10):      # 6000 bytes each: one fits
        views.get(("recognition_view", i), lambda: {"state": np.zeros(500, np.int32), "p_max": np.zeros(500)})
    assert list(views._d) == [("recognition_view", 9)]
    for i in range(10):      # 1200 bytes each: the last three
        views.get(("recognition_view", i), lambda: {"state": np.zeros(100, np.int32), "p_max": np.zeros(100)})
    assert list(views._d) == [("recognition_view", i) for i in (7, 8, 9)]


# ---------------------------------------------------------------- 4. /tracks and /qc paginated
@pytest.mark.parametrize("what", ["qc", "tracks"])
def test_line_listings_paginated(client, tiny_src, what):
    from app.web.services import LINES_PAGE_DEFAULT, LINES_PAGE_MAX
    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    url = f"/api/surveys/{sid}/{what}"
    full = client.get(url).json()                       # today's clients: every line, as before
    assert [l["line"] for l in full["lines"]] == ["L1", "L2", "T1"]
    assert (full["lines_total"], full["offset"], full["limit"]) == (3, 0, LINES_PAGE_DEFAULT)
    page = client.get(url, params={"offset": 1, "limit": 1}).json()
    assert [l["line"] for l in page["lines"]] == ["L2"] and page["lines_total"] == 3
    assert page["lines"][0] == full["lines"][1]
    assert [l["line"] for l in client.get(url, params={"offset": 2, "limit": 5}).json()["lines"]] == ["T1"]
    assert client.get(url, params={"offset": 3}).json()["lines"] == []
    count = client.get(url, params={"limit": 0}).json()
    assert count["lines"] == [] and count["lines_total"] == 3
    if what == "qc":
        assert [f["name"] for f in page["flights"]] == ["f1"]      # flights are not paged
    else:
        assert page["crs"] == full["crs"] == "EPSG:32657"
    assert client.get(url, params={"limit": LINES_PAGE_MAX}).status_code == 200
    for bad in ({"offset": -1}, {"limit": -1}, {"limit": "nan"}, {"offset": "NaN"}, {"limit": "inf"},
                {"limit": LINES_PAGE_MAX + 1}, {"offset": 10**30}, {"offset": "1e3"}, {"limit": ""}):
        r = client.get(url, params=bad)
        assert r.status_code == 422, (bad, r.text)
        assert r.json()["detail"][0]["loc"] == ["query", next(iter(bad))]
