"""Fourth hostile pass over the web server: each test is a case that was broken (a request costing
the server far more than its size, a server path in an error, work without an end) and the
behaviour the fix gives."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from app.web.main import MAX_FORM_PARTS, PartCounter

from .conftest import import_zip, make_tiny_survey, wait_job, zip_dir, zip_with


@pytest.fixture(scope="module")
def tiny_src(tmp_path_factory) -> Path:
    return make_tiny_survey(tmp_path_factory.mktemp("fourth") / "tiny", name="tiny")


def _nothing_stored(client) -> None:
    d = Path(client.app.state.settings.data_dir)
    assert client.get("/api/surveys").json() == []
    assert sorted((d / "surveys").glob("*/input/*")) == [] and list((d / "tmp").iterdir()) == []


def _multipart(parts: list[tuple[str, str | None, bytes]], boundary: str = "b0undary") -> tuple[bytes, dict]:
    """A multipart/form-data body of (field, file name or None, content) parts."""
    out = io.BytesIO()
    for name, filename, data in parts:
        disp = f'form-data; name="{name}"' + (f'; filename="{filename}"' if filename else "")
        out.write(f"--{boundary}\r\nContent-Disposition: {disp}\r\n\r\n".encode() + data + b"\r\n")
    out.write(f"--{boundary}--\r\n".encode())
    return out.getvalue(), {"content-type": f"multipart/form-data; boundary={boundary}"}


def test_json_bodies_limited_apart_from_uploads(make_client, tiny_src):
    """Every body was allowed the upload limit (500 MB): a 105 MB JSON array sent as a survey's name
    took the server from 280 to 1180 MB (parsed into Python objects ~9 times its size) and left it at
    780 MB.  A request that is not an upload (JSON, or a form sent to an endpoint that takes no
    files) is limited to AEROGRAV_MAX_JSON_KB — declared or streamed — with a 413 naming it, while
    uploads keep their own limit."""
    client = make_client(max_json_kb=16)
    assert client.app.state.settings.max_json_bytes == 16 * 1024
    big = b'{"name": [' + b"0," * 20_000 + b'0]}'
    r = client.post("/api/surveys", content=big, headers={"content-type": "application/json"})
    assert r.status_code == 413 and "AEROGRAV_MAX_JSON_KB" in r.json()["detail"], r.text[:300]

    def streamed():
        for _ in range(40):
            yield b" " * 1024

    r = client.post("/api/surveys", content=streamed(), headers={"content-type": "application/json"})
    assert r.status_code == 413 and "AEROGRAV_MAX_JSON_KB" in r.json()["detail"], r.text[:300]
    body, headers = _multipart([("name", None, b"x" * 40_000)])        # a form where JSON is taken
    assert client.post("/api/surveys", content=body, headers=headers).status_code == 413
    r = client.post("/api/surveys/import", content=b"file=" + b"x" * 40_000,   # not multipart: not an upload
                    headers={"content-type": "application/x-www-form-urlencoded"})
    assert r.status_code == 413 and "AEROGRAV_MAX_JSON_KB" in r.json()["detail"]
    _nothing_stored(client)

    data = zip_dir(tiny_src)
    assert len(data) > 16 * 1024
    r = import_zip(client, data)                                          # an upload: the upload limit
    assert r.status_code == 201, r.text[:300]
    sid = r.json()["id"]
    r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": {"em_max_iter": 5}})
    assert r.status_code == 201, r.text[:300]                             # small JSON: as before
    r = client.patch(f"/api/surveys/{sid}", json={"survey": {"name": "renamed"}})
    assert r.status_code in (200, 409), r.text[:300]


def test_upload_form_with_many_small_parts_refused(client, tiny_src):
    """The form parser keeps a file part under 1 MB in memory (a larger one goes to disk): 150 parts
    of 1 MB raised the server's peak memory by 150 MB where one 150 MB file cost 1 MB, and the
    upload limit allowed 500 such parts.  An upload form has at most MAX_FORM_PARTS parts (400
    naming them, counted while the body streams in); the real ones pass."""
    body, headers = _multipart([(f"f{i}", f"a{i}.bin", b"x" * 1000) for i in range(MAX_FORM_PARTS + 5)])
    for path in ("/api/surveys/import", "/api/surveys/1/flights"):
        r = client.post(path, content=body, headers=headers)
        assert r.status_code == 400 and "parts" in r.json()["detail"], (path, r.text[:300])
    _nothing_stored(client)

    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    f = tiny_src / "flights" / "f1"
    lines = (tiny_src / "lines.csv").read_bytes()
    body, headers = _multipart([("gravimeter", "g.csv", (f / "gravimeter.csv").read_bytes()),
                                ("gnss", "n.csv", (f / "gnss.csv").read_bytes()), ("lines", "l.csv", lines),
                                ("flight", None, b"f1")])
    r = client.post(f"/api/surveys/{sid}/flights", content=body, headers=headers)
    assert r.status_code == 201, r.text[:300]


@pytest.mark.parametrize("chunk", [1, 3, 7, 1000])
def test_part_counter_across_chunk_edges(chunk):
    body, _ = _multipart([("a", "a.bin", b"--b0undar"), ("b", None, b"1"), ("c", "c.bin", b"")])
    pc = PartCounter(b"b0undary")
    n = 0
    for i in range(0, len(body), chunk):
        n = pc.feed(body[i:i + chunk])
    assert n == 3


def test_errors_do_not_show_server_paths(make_client, tiny_src):
    """GDAL names the file it cannot read by its path: a DEM that starts as a TIFF but is not one
    was refused with "'/…/data/tmp/<uuid>/survey/dem.tif' not recognized as being in a supported
    file format" — the server's data directory and layout.  Errors name the file by its place in
    the survey (dem.tif, flights/f1/gnss.csv), for uploads and failed jobs alike."""
    client = make_client()
    root = str(client.app.state.settings.data_dir)
    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    r = client.put(f"/api/surveys/{sid}/dem", files={"dem": ("dem.tif", b"II*\x00" + b"\x00" * 100)})
    assert r.status_code == 422 and r.json()["detail"]["file"] == "dem.tif", r.text[:300]
    assert root not in r.text and "dem.tif" in r.json()["detail"]["message"], r.text[:400]
    r = import_zip(client, zip_with(tiny_src, {"dem.tif": b"II*\x00" + b"\x00" * 100}))
    assert r.status_code == 422 and root not in r.text, r.text[:400]

    failing = make_client(data_dir=Path(root).parent / "failing", pipeline_entry="tests.web.fake_pipeline:failing_survey")
    sid = import_zip(failing, zip_dir(tiny_src)).json()["id"]
    job = wait_job(failing, failing.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()["id"])
    assert job["status"] == "failed", job
    err = job["error"]
    assert str(Path(root).parent / "failing") not in err, err
    assert err.startswith("file flights/f1/gnss.csv, row 3") and "'dem.tif'" in err and "grid.nc" in err, err


def test_jobs_stopped_after_their_time_limit(make_client, tiny_src, monkeypatch):
    """No job had an end but its own: parameters within their bounds can make a large survey's job run
    for many hours, and a job on each of a few surveys held every worker slot meanwhile (the others'
    jobs waiting without end).  A job running longer than AEROGRAV_JOB_TIMEOUT_S is marked failed
    saying so, its worker stopped, its half-written folder removed and its slot given to the next
    job; the survey keeps its current result."""
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "5")          # a fake job of about a minute
    client = make_client(job_timeout_s=0.3, max_jobs=1, poll_interval_s=0.05)
    jobs = client.app.state.jobs
    a = import_zip(client, zip_dir(tiny_src)).json()["id"]
    b = import_zip(client, zip_dir(tiny_src)).json()["id"]
    ja = client.post(f"/api/surveys/{a}/jobs", json={"kind": "process"}).json()["id"]
    jb = client.post(f"/api/surveys/{b}/jobs", json={"kind": "process"}).json()["id"]
    assert jobs.waiting() == [jb]
    first = wait_job(client, ja, timeout=10)
    assert first["status"] == "failed" and "AEROGRAV_JOB_TIMEOUT_S" in first["error"], first
    assert wait_job(client, jb, timeout=10)["status"] == "failed"      # started once the slot freed, then stopped
    assert jobs.waiting() == [] and jobs.worker_pid(ja) is None
    for sid in (a, b):
        assert client.get(f"/api/surveys/{sid}").json()["current_result_id"] is None
    d = Path(client.app.state.settings.data_dir)
    assert list(d.glob("surveys/*/results/*.partial")) == []


def test_number_of_surveys_bounded(make_client, tiny_src):
    """An empty survey costs no disk, so the store's limit never stopped them: 2000 POST /api/surveys
    took 7 s and made every survey listing take 1.1 s (linear: 100 000 would take a minute each).
    Beyond AEROGRAV_MAX_SURVEYS a new survey or an import is a 507 naming the setting, nothing
    stored; a deleted survey makes room again."""
    client = make_client(max_surveys=2)
    ids = [client.post("/api/surveys", json={"name": f"s{i}"}).json()["id"] for i in range(2)]
    r = client.post("/api/surveys", json={"name": "one too many"})
    assert r.status_code == 507 and "AEROGRAV_MAX_SURVEYS" in r.json()["detail"], r.text[:300]
    r = import_zip(client, zip_dir(tiny_src))
    assert r.status_code == 507 and "AEROGRAV_MAX_SURVEYS" in r.json()["detail"], r.text[:300]
    assert [s["id"] for s in client.get("/api/surveys").json()] == ids
    d = Path(client.app.state.settings.data_dir)
    assert sorted(d.glob("surveys/*/input/*")) == [] and list((d / "tmp").iterdir()) == []
    assert client.delete(f"/api/surveys/{ids[0]}").status_code == 204
    assert import_zip(client, zip_dir(tiny_src)).status_code == 201
