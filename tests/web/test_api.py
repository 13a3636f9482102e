"""REST API through TestClient: surveys, uploads, errors, jobs and result views."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from .conftest import import_zip, make_tiny_survey, wait_job, zip_dir


def _stored_surveys(client) -> list[Path]:
    root = Path(client.app.state.settings.data_dir) / "surveys"
    return [p for p in root.iterdir()] if root.exists() else []


def _tmp_left(client) -> list[Path]:
    return list((Path(client.app.state.settings.data_dir) / "tmp").iterdir())


def test_create_list_get_survey(client):
    r = client.post("/api/surveys", json={"name": "Omolon block A"})
    assert r.status_code == 201, r.text
    s = r.json()
    assert s["id"] and s["name"] == "Omolon block A" and s["flights"] == [] and not s["has_input"]
    assert [x["id"] for x in client.get("/api/surveys").json()] == [s["id"]]
    assert client.get(f"/api/surveys/{s['id']}").json()["name"] == "Omolon block A"
    assert client.get("/api/surveys/999").status_code == 404
    assert client.post("/api/surveys", json={"name": ""}).status_code == 422
    # no data yet: a job cannot start, no results
    assert client.post(f"/api/surveys/{s['id']}/jobs", json={"kind": "process"}).status_code == 409
    assert client.get(f"/api/surveys/{s['id']}/grid").status_code == 404


@pytest.mark.parametrize("nested", [True, False])
def test_import_zip_and_qc(client, tiny_survey, nested):
    r = import_zip(client, zip_dir(tiny_survey, nested=nested))
    assert r.status_code == 201, r.text
    s = r.json()
    assert s["name"] == "tiny" and s["flights"] == ["f1"] and s["n_lines"] == 3 and s["crs"] == "EPSG:32657"
    qc = client.get(f"/api/surveys/{s['id']}/qc").json()
    f = qc["flights"][0]
    assert f["name"] == "f1"
    assert f["qc"]["gnss_rate_hz"] == pytest.approx(10.0, rel=1e-3)
    assert f["qc"]["gravimeter_rate_hz"] == pytest.approx(18.24, rel=1e-2)
    l1 = next(l for l in qc["lines"] if l["line"] == "L1")
    assert l1["qc"]["duration_s"] == pytest.approx(130.0)
    # 130 s east at ~0.018°/10 s × cos 62° → about 12.3 km
    assert 10 < l1["qc"]["length_km"] < 15
    assert l1["qc"]["gnss_max_gap_s"] == pytest.approx(0.1, abs=1e-3)
    lines = client.get(f"/api/surveys/{s['id']}/lines").json()
    assert [l["line"] for l in lines] == ["L1", "L2", "T1"] and lines[0]["stats"] is None
    assert not _tmp_left(client)


def test_malformed_csv_is_422_with_location_and_nothing_stored(client, tmp_path):
    root = make_tiny_survey(tmp_path / "bad")
    p = root / "flights" / "f1" / "gnss.csv"
    rows = p.read_text().splitlines()
    parts = rows[5].split(",")
    parts[4] = "abc"  # vu on line 6 of the file
    rows[5] = ",".join(parts)
    p.write_text("\n".join(rows) + "\n")
    r = import_zip(client, zip_dir(root))
    assert r.status_code == 422, r.text
    d = r.json()["detail"]
    assert d["file"] == "flights/f1/gnss.csv"
    assert d["row"] == 6 and d["column"] == "vu" and d["message"]
    assert client.get("/api/surveys").json() == []
    assert _stored_surveys(client) == [] and not _tmp_left(client)


def test_not_a_zip_and_missing_toml(client, tmp_path):
    r = import_zip(client, b"this is not a zip")
    assert r.status_code == 422 and "zip" in r.json()["detail"]["message"]
    buf = io.BytesIO()
    import zipfile
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("readme.txt", "hello")
    r = import_zip(client, buf.getvalue())
    assert r.status_code == 422 and r.json()["detail"]["file"] == "survey.toml"
    assert client.get("/api/surveys").json() == [] and not _tmp_left(client)


def test_upload_over_limit_is_413(make_client, tiny_zip):
    client = make_client(max_upload_mb=0.05)
    assert len(tiny_zip) > 0.05 * 1024 * 1024
    r = import_zip(client, tiny_zip)
    assert r.status_code == 413
    assert "limit" in r.json()["detail"] and "MB" in r.json()["detail"]
    assert client.get("/api/surveys").json() == [] and _stored_surveys(client) == []


def test_zip_bomb_refused(make_client):
    client = make_client(max_upload_mb=0.05)
    buf = io.BytesIO()
    import zipfile
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("s/survey.toml", "[survey]\n")
        zf.writestr("s/flights/f1/gnss.csv", b"0" * (2 * 1024 * 1024))  # 2 MB of zeros, ~2 kB compressed
    assert len(buf.getvalue()) < 0.05 * 1024 * 1024
    r = import_zip(client, buf.getvalue())
    assert r.status_code == 422 and "expands to" in r.json()["detail"]["message"]
    assert client.get("/api/surveys").json() == [] and not _tmp_left(client)


def test_upload_over_limit_streamed_without_length(make_client):
    client = make_client(max_upload_mb=0.01)

    def gen():
        for _ in range(40):
            yield b"x" * 1024

    r = client.post("/api/surveys/import", content=gen(),
                    headers={"content-type": "multipart/form-data; boundary=abc"})
    assert r.status_code == 413


def test_token_required_on_mutations(make_client, tiny_zip):
    client = make_client(token="s3cret")
    assert client.post("/api/surveys", json={"name": "x"}).status_code == 401
    assert client.post("/api/surveys", json={"name": "x"},
                       headers={"Authorization": "Bearer wrong"}).status_code == 401
    assert import_zip(client, tiny_zip).status_code == 401
    assert client.get("/api/surveys").status_code == 200  # reading is open
    assert client.post("/api/surveys", json={"name": "x"},
                       headers={"Authorization": "Bearer s3cret"}).status_code == 201
    assert client.post("/api/surveys", json={"name": "y"}, headers={"X-Aerograv-Token": "s3cret"}).status_code == 201
    assert [s["name"] for s in client.get("/api/surveys").json()] == ["x", "y"]


def test_flight_upload(client, tmp_path):
    src = make_tiny_survey(tmp_path / "src")
    sid = client.post("/api/surveys", json={"name": "uploads"}).json()["id"]
    fdir = src / "flights" / "f1"
    lines = pd.read_csv(src / "lines.csv").drop(columns=["flight"])
    files = {"gravimeter": ("gravimeter.csv", (fdir / "gravimeter.csv").read_bytes(), "text/csv"),
             "gnss": ("gnss.csv", (fdir / "gnss.csv").read_bytes(), "text/csv"),
             "lines": ("lines.csv", lines.to_csv(index=False).encode(), "text/csv")}
    r = client.post(f"/api/surveys/{sid}/flights", files=files, data={"flight": "F07"})
    assert r.status_code == 201, r.text
    assert r.json()["flights"] == ["F07"] and r.json()["n_lines"] == 3
    before = client.get(f"/api/surveys/{sid}").json()

    # a broken second flight: the survey keeps its first flight, nothing half-written
    bad = (fdir / "gnss.csv").read_text().splitlines()
    # line 11 takes line 10's time with another value (an exact repeat would be dropped as one)
    f = bad[9].split(",")
    f[-1] = repr(float(f[-1]) + 0.5)
    bad[10] = ",".join(f)
    files2 = {"gravimeter": ("gravimeter.csv", (fdir / "gravimeter.csv").read_bytes(), "text/csv"),
              "gnss": ("gnss.csv", ("\n".join(bad) + "\n").encode(), "text/csv"),
              "lines": ("lines.csv", lines.assign(line=lambda d: d.line + "b").to_csv(index=False).encode(), "text/csv")}
    r = client.post(f"/api/surveys/{sid}/flights", files=files2, data={"flight": "F08"})
    assert r.status_code == 422, r.text
    d = r.json()["detail"]
    assert d["file"] == "flights/F08/gnss.csv" and d["row"] == 11 and d["column"] == "time"
    after = client.get(f"/api/surveys/{sid}").json()
    assert after["flights"] == ["F07"] and after["n_lines"] == before["n_lines"]
    assert not _tmp_left(client)
    assert client.post(f"/api/surveys/{sid}/flights", files=files, data={"flight": "../x"}).status_code == 422


def test_params_schema_and_invalid_params(client, tiny_zip):
    sch = client.get("/api/params/schema").json()
    assert sch["defaults"]["nlmeans_h_per_km"] == 0.5
    assert "description" in sch["schema"]["properties"]["m"]
    sid = import_zip(client, tiny_zip).json()["id"]
    r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": {"m": 7}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["m"]
    r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": {"no_such": 1}})
    assert r.status_code == 422
    r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "dance"})
    assert r.status_code == 422
    r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": {"noise_band_hz": [0.5, 0.1]}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["noise_band_hz"]
    assert sch["defaults"]["noise_band_hz"] == [0.1, 0.5]
    assert client.get(f"/api/surveys/{sid}/jobs").json() == []


def test_process_job_and_result_views(client, tiny_zip):
    sid = import_zip(client, tiny_zip).json()["id"]
    assert client.get(f"/api/surveys/{sid}/recognition").status_code == 404
    r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": {"em_max_iter": 5}})
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["status"] in ("queued", "running") and job["params"] == {"em_max_iter": 5}
    j = wait_job(client, job["id"])
    assert j["status"] == "succeeded", j
    assert j["progress"] == 1.0 and [e["iteration"] for e in j["em_iterations"]] == [0, 1, 2]
    assert j["em_iterations"][0]["transition"] == [[0.98, 0.02], [0.03, 0.97]]
    assert client.get(f"/api/surveys/{sid}/jobs").json()[0]["id"] == job["id"]
    assert client.post(f"/api/jobs/{job['id']}/cancel").status_code == 409
    assert client.get("/api/jobs/12345").status_code == 404
    s = client.get(f"/api/surveys/{sid}").json()
    assert s["current_result_id"] and s["last_job"]["status"] == "succeeded"

    lines = client.get(f"/api/surveys/{sid}/lines").json()
    assert lines[0]["stats"]["n"] > 1000
    prof = client.get(f"/api/surveys/{sid}/lines/L1", params={"max_points": 300}).json()
    assert prof["n_total"] == 1301 and prof["step"] == 5 and len(prof["dg"]) == len(prof["time"]) == 261
    assert prof["distance_km"][0] == 0 and 10 < prof["distance_km"][-1] < 15
    assert set(prof["state"]) <= {0, 1}
    # z is low-passed: far less scatter than the raw 50 mGal noise
    assert np.std(np.diff(prof["z_lowpassed"])) < 10
    assert client.get(f"/api/surveys/{sid}/lines/NOPE").status_code == 404

    rec = client.get(f"/api/surveys/{sid}/recognition", params={"h": 1.4, "rho": 5}).json()
    n = rec["n_points"]
    assert n == len(rec["state"]) == len(rec["easting_km"]) == len(rec["state_raw"]) and rec["n_states"] == 2
    rec0 = client.get(f"/api/surveys/{sid}/recognition", params={"h": 0, "rho": 0, "coords": False}).json()
    assert "easting_km" not in rec0
    assert rec0["state"] == rec["state_raw"]  # ρ = 0: every point keeps its own state
    rec_wide = client.get(f"/api/surveys/{sid}/recognition", params={"h": 0.0, "rho": 15, "coords": False}).json()

    def changes(states):
        return int(np.sum(np.diff(states) != 0))

    assert changes(rec_wide["state"]) < changes(rec0["state"])  # wide averaging smooths the map
    assert client.get(f"/api/surveys/{sid}/recognition", params={"rho": 50}).status_code == 422

    g = client.get(f"/api/surveys/{sid}/grid").json()
    assert len(g["dg"]) == len(g["northing_km"]) and len(g["dg"][0]) == len(g["easting_km"])
    assert g["dg"][0][0] is None and g["dg_std"] is not None and g["crs"] == "EPSG:32657"
    assert {t["line"] for t in g["lines"]} == {"L1", "L2", "T1"} and g["crossovers"][0]["line_a"] == "L1"

    for fmt, magic in [("geotiff", b"II*\x00"), ("netcdf", b"\x89HDF"), ("surfer", b"DSAA"), ("csv", b"easting_km"),
                       ("parquet", b"PAR1")]:
        r = client.get(f"/api/surveys/{sid}/export", params={"format": fmt})
        assert r.status_code == 200, (fmt, r.text)
        assert r.content.startswith(magic) or (fmt == "netcdf" and r.content[:3] == b"CDF"), fmt
        assert "attachment" in r.headers["content-disposition"]
    assert client.get(f"/api/surveys/{sid}/export", params={"format": "xls"}).status_code == 422


def test_concurrent_jobs_share_the_cpus(make_client, tiny_survey, tmp_path, monkeypatch):
    """Each local job process gets its share of the server's CPUs for the per-line loops
    (AEROGRAV_THREADS = CPUs // jobs running, at least 1), so concurrent jobs do not
    oversubscribe the cores; a server-wide AEROGRAV_THREADS is left to every job."""
    from app.pipeline.parallel import thread_count

    monkeypatch.delenv("AEROGRAV_THREADS", raising=False)
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "0.3")  # the first job still runs when the second starts
    cpus = thread_count()
    c = make_client()
    first = import_zip(c, zip_dir(tiny_survey), name="a.zip").json()["id"]
    second = import_zip(c, zip_dir(tiny_survey), name="b.zip").json()["id"]
    jobs = [c.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()["id"] for sid in (first, second)]
    assert [wait_job(c, j)["status"] for j in jobs] == ["succeeded", "succeeded"]
    given = [c.get(f"/api/surveys/{sid}/report").json()["report"]["threads_env"] for sid in (first, second)]
    assert given == [str(cpus), str(max(1, cpus // 2))]

    monkeypatch.setenv("AEROGRAV_THREADS", "3")
    jid = c.post(f"/api/surveys/{first}/jobs", json={"kind": "process"}).json()["id"]
    assert wait_job(c, jid)["status"] == "succeeded"
    assert c.get(f"/api/surveys/{first}/report").json()["report"]["threads_env"] == "3"


def test_local_jobs_beyond_max_jobs_wait_queued(make_client, tiny_survey, monkeypatch):
    """Every job is a process of its own, so surveys started at once could take the machine's
    memory: beyond AEROGRAV_MAX_JOBS the jobs wait, queued, and start oldest first as slots
    free; a waiting job can be cancelled and then never starts."""
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "0.1")  # ~1.5 s per job
    c = make_client(max_jobs=1)
    sids = [import_zip(c, zip_dir(tiny_survey), name=f"{k}.zip").json()["id"] for k in range(3)]
    jobs = [c.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()["id"] for sid in sids]
    manager = c.app.state.jobs
    assert manager.waiting() == jobs[1:]  # one slot: the others wait, in order
    waiting = [c.get(f"/api/jobs/{j}").json() for j in jobs[1:]]
    assert [w["status"] for w in waiting] == ["queued", "queued"]
    assert all(w["stage"].startswith("waiting for a free worker") for w in waiting)
    assert c.post(f"/api/jobs/{jobs[2]}/cancel").status_code == 200
    assert manager.waiting() == jobs[1:2]
    done = [wait_job(c, j) for j in jobs[:2]]
    assert [d["status"] for d in done] == ["succeeded", "succeeded"]
    # the second started only after the first had finished
    assert done[1]["started_at"] >= done[0]["finished_at"]
    j3 = c.get(f"/api/jobs/{jobs[2]}").json()
    assert j3["status"] == "cancelled" and j3["started_at"] is None
    assert manager.waiting() == []


def test_frontend_and_docs_served(client):
    r = client.get("/")
    assert r.status_code == 200 and "<script type=\"module\"" in r.text
    assert client.get("/vendor/plotly.min.js").status_code == 200
    assert client.get("/js/api.js").status_code == 200
    docs = client.get("/docs")
    assert docs.status_code == 200 and "/docs-static/swagger-ui-bundle.js" in docs.text
    assert "http" not in docs.text and "<script>" not in docs.text   # no CDN, no inline script
    csp = docs.headers["content-security-policy"]
    assert "script-src 'self';" in csp and "unsafe-inline" not in csp.split("script-src")[1].split(";")[0]
    assert "cdn" not in csp and "https:" not in csp
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css", "redoc.standalone.js", "swagger-init.js"):
        r = client.get(f"/docs-static/{asset}")
        assert r.status_code == 200 and len(r.content) > 100, asset
    assert client.get("/docs-static/..%2Fcore.py").status_code == 404
    redoc = client.get("/redoc")
    assert redoc.status_code == 200 and "/docs-static/redoc.standalone.js" in redoc.text and "googleapis" not in redoc.text
    assert "/api/surveys/{survey_id}/recognition" in client.get("/openapi.json").json()["paths"]


def test_tracks_for_line_map(client, tiny_zip):
    sid = import_zip(client, tiny_zip).json()["id"]
    t = client.get(f"/api/surveys/{sid}/tracks").json()
    assert t["crs"] == "EPSG:32657" and [l["line"] for l in t["lines"]] == ["L1", "L2", "T1"]
    l1 = t["lines"][0]
    assert 50 <= len(l1["easting_km"]) == len(l1["northing_km"]) <= 400
    # flying east ~13 km along the line, in UTM km
    assert 10 < l1["easting_km"][-1] - l1["easting_km"][0] < 15
    assert abs(l1["northing_km"][-1] - l1["northing_km"][0]) < 1.0
    assert client.get(f"/api/surveys/{sid}/qc").json()["lines"][0]["qc"]["track"] is None
