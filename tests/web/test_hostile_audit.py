"""Second hostile pass over the REST surface: each test is a case that was broken (a 500, a hang, a
silently ignored request) and the behaviour the fix gives."""

from __future__ import annotations

import io
from pathlib import Path

import pytest

from .conftest import import_zip, make_tiny_survey, zip_dir


@pytest.fixture(scope="module")
def tiny_src(tmp_path_factory) -> Path:
    return make_tiny_survey(tmp_path_factory.mktemp("audit") / "tiny", name="tiny")


def _flight_files(src: Path, lines: bytes) -> dict:
    fdir = src / "flights" / "f1"
    return {"gravimeter": ("gravimeter.csv", (fdir / "gravimeter.csv").read_bytes()),
            "gnss": ("gnss.csv", (fdir / "gnss.csv").read_bytes()),
            "lines": ("lines.csv", lines)}


def test_wide_lines_upload_refused_before_parsing(client, tiny_src, monkeypatch):
    """A 2 MB lines.csv with 300,000 columns kept the request busy for minutes (pandas parsing and
    concatenating the frame); it is refused from its header and the survey is unchanged.  What is
    guarded is that pandas never parses it (spied at ``pandas.read_csv``, the parser the upload
    went through), not how long the request took (a wall-clock bound, flaky on a busy machine)."""
    import pandas as pd

    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    before = client.get(f"/api/surveys/{sid}").json()
    n = 300_000
    wide = (",".join(["line", "t_start", "t_end", "kind"] + [f"c{i}" for i in range(n)]) + "\n"
            + ",".join(["X1", "1010", "1140", "main"] + ["1"] * n) + "\n").encode()
    real_read_csv = pd.read_csv
    parsed: list[int] = []

    def spy(src, *a, **kw):
        if isinstance(src, io.BytesIO) and src.getvalue() == wide:
            parsed.append(len(wide))
            raise AssertionError("the wide lines file was given to pandas")   # fail now, not in minutes
        return real_read_csv(src, *a, **kw)

    monkeypatch.setattr(pd, "read_csv", spy)
    r = client.post(f"/api/surveys/{sid}/flights", files=_flight_files(tiny_src, wide), data={"flight": "w"})
    assert r.status_code == 422, r.text[:300]
    d = r.json()["detail"]
    assert (d["file"], d["row"]) == ("lines.csv", 1) and f"{n + 4:,} columns" in d["message"], d
    assert parsed == [], "the wide lines file was given to pandas"
    after = client.get(f"/api/surveys/{sid}").json()
    assert after["flights"] == before["flights"] == ["f1"] and after["n_lines"] == before["n_lines"]
    # a quoted header whose commas are inside one name is one column per name, and passes
    quoted = b'line,t_start,t_end,kind,"' + b",".join([b"x"] * 200) + b'"\nX1,1010,1140,main,1\n'
    r = client.post(f"/api/surveys/{sid}/flights", files=_flight_files(tiny_src, quoted), data={"flight": "q"})
    assert r.status_code == 201, r.text[:300]


def test_patch_numbers_must_be_json_numbers(client, tiny_src):
    """PATCH stored ``scale = true`` as 1.0 and ``tau_s = "3"`` as 3.0 (pydantic's lax mode), where the
    jobs endpoint refuses the same values; both are a 422 naming the field now, and nothing changes."""
    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    before = client.get(f"/api/surveys/{sid}").json()["settings"]
    for body, field in (({"gravimeter": {"scale": True}}, "scale"), ({"gravimeter": {"tau_s": "3"}}, "tau_s"),
                        ({"gravimeter": {"base_gravity_mgal": False}}, "base_gravity_mgal")):
        r = client.patch(f"/api/surveys/{sid}", json=body)
        assert r.status_code == 422, (body, r.text)
        assert r.json()["detail"][0]["loc"][-2:] == ["gravimeter", field], r.json()
    assert client.get(f"/api/surveys/{sid}").json()["settings"] == before
    # integers and floats are still numbers
    r = client.patch(f"/api/surveys/{sid}", json={"gravimeter": {"tau_s": 3, "scale": 1.02}})
    assert r.status_code == 200, r.text
    assert r.json()["settings"]["gravimeter"]["tau_s"] == 3.0 and r.json()["settings"]["gravimeter"]["scale"] == 1.02


def test_job_request_with_unknown_keys_refused(client, tiny_src):
    """``{"kind": "process", "parameters": {...}}`` (a misspelt ``params``) started a job with the
    defaults, silently; unknown top-level keys are a 422 naming the key, and no job is queued."""
    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "parameters": {"grid_spacing_km": 0.5}})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["body", "parameters"], r.json()
    assert client.get(f"/api/surveys/{sid}/jobs").json() == []


def _many_entries_zip(src: Path, n: int) -> bytes:
    import io
    import zipfile
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for p in sorted(src.rglob("*")):
            if p.is_file():
                zf.write(p, "s/" + p.relative_to(src).as_posix())
        for i in range(n):
            zf.writestr(zipfile.ZipInfo(f"j/{i}"), b"")
    return buf.getvalue()


def _set_declared_entries(data: bytes, n: int) -> bytes:
    """The end-of-central-directory record's entry counts set to ``n`` (a lying table of contents)."""
    import struct
    b = bytearray(data)
    k = b.rfind(b"PK\x05\x06")
    struct.pack_into("<HH", b, k + 8, n, n)
    return bytes(b)


def test_zip_table_of_contents_bounded_before_it_is_read(client, tiny_src, monkeypatch):
    """ZipFile reads the whole central directory and builds an object per entry before the entry
    count was checked: 500,000 empty entries in a 40 MB zip cost 270 MB and 5 s.  The count is now
    checked from the directory's headers first (also when the end record's count lies), and a
    directory larger than MAX_ZIP_DIRECTORY is refused from the end record alone."""
    import zipfile

    import app.web.store as store_mod

    spy_calls = []
    real = zipfile.ZipFile.infolist
    monkeypatch.setattr(zipfile.ZipFile, "infolist", lambda self: spy_calls.append(1) or real(self))
    data = _many_entries_zip(tiny_src, 10_001)
    for what, blob in (("declared", data), ("lying", _set_declared_entries(data, 5))):
        r = import_zip(client, blob)
        assert r.status_code == 422, (what, r.text[:300])
        d = r.json()["detail"]
        assert d["file"] == "upload" and "10,000 allowed" in d["message"], (what, d)
    assert spy_calls == []                      # refused before ZipFile built its entry list
    monkeypatch.setattr(store_mod, "MAX_ZIP_DIRECTORY", 4096)
    r = import_zip(client, _many_entries_zip(tiny_src, 200))
    assert r.status_code == 422 and "table of contents" in r.json()["detail"]["message"], r.text[:300]
    assert client.get("/api/surveys").json() == []
    # a zip within the limits still imports (the file position was restored for ZipFile)
    monkeypatch.setattr(store_mod, "MAX_ZIP_DIRECTORY", 16 << 20)
    r = import_zip(client, _many_entries_zip(tiny_src, 50))
    assert r.status_code == 201, r.text[:300]


def test_large_lines_upload_refused_unread(client, tiny_src, monkeypatch):
    """An uploaded lines.csv was read whole and parsed in memory (a 57 MB file of 10,000 long rows
    cost 340 MB): past MAX_LINES_BYTES it is refused from its size, with nothing stored."""
    import app.web.services as services

    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    monkeypatch.setattr(services, "MAX_LINES_BYTES", 4096)
    monkeypatch.setattr("app.web.routers.surveys.MAX_LINES_BYTES", 4096)
    parsed = []
    real_read_csv = services.pd.read_csv
    monkeypatch.setattr(services.pd, "read_csv", lambda *a, **k: parsed.append(1) or real_read_csv(*a, **k))
    big = b"line,t_start,t_end,kind\n" + b"".join(b"L%d%s,1010,1140,main\n" % (i, b"x" * 90) for i in range(60))
    assert len(big) > 4096
    r = client.post(f"/api/surveys/{sid}/flights", files=_flight_files(tiny_src, big), data={"flight": "big"})
    assert r.status_code == 422, r.text[:300]
    d = r.json()["detail"]
    assert d["file"] == "lines.csv" and "larger than" in d["message"], d
    assert parsed == [] and client.get(f"/api/surveys/{sid}").json()["flights"] == ["f1"]
    small = b"line,t_start,t_end,kind\nX1,1010,1140,main\n"
    r = client.post(f"/api/surveys/{sid}/flights", files=_flight_files(tiny_src, small), data={"flight": "small"})
    assert r.status_code == 201 and r.json()["flights"] == ["f1", "small"], r.text[:300]


def test_wrong_method_on_an_api_path_is_405_with_its_methods(client):
    """The frontend's static mount at / answered API paths whose method did not match: HEAD on an
    existing survey was a 404, and every 405 said "Allow: GET, HEAD" (also for POST-only paths).
    API paths are the router's now: 405 listing the methods of the path, JSON 404 for unknown ones."""
    sid = client.post("/api/surveys", json={"name": "m"}).json()["id"]
    cases = [("HEAD", f"/api/surveys/{sid}", {"GET", "PATCH", "DELETE"}),
             ("DELETE", f"/api/surveys/{sid}/qc", {"GET"}),
             ("PATCH", "/api/jobs/1/cancel", {"POST"}),
             ("PUT", f"/api/surveys/{sid}/flights", {"POST"}),
             ("POST", "/api/health", {"GET"})]
    for method, path, allowed in cases:
        r = client.request(method, path)
        assert r.status_code == 405, (method, path, r.status_code)
        assert set(r.headers["allow"].split(", ")) == allowed, (method, path, r.headers["allow"])
        assert r.headers["x-frame-options"] == "DENY"
        if method != "HEAD":
            assert method in r.json()["detail"], r.json()
    r = client.get("/api/no-such-thing")
    assert r.status_code == 404 and r.json() == {"detail": "Not Found"}
    assert client.get(f"/api/surveys/{sid}").status_code == 200    # the survey is still there
    assert client.get("/").status_code == 200 and "<html" in client.get("/").text.lower()


def test_survey_listing_does_not_load_every_line(client, tiny_src):
    """GET /api/surveys and /api/surveys/{id} loaded each survey's Line rows (QC and map track) to
    count them: 1.5 s per listing for a survey of 20,000 lines.  The count comes from the database."""
    from sqlalchemy import event

    from app.web.db import Line

    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    loaded = []

    def on_load(target, _ctx):
        loaded.append(target.line)

    event.listen(Line, "load", on_load)
    try:
        listing = client.get("/api/surveys").json()
        one = client.get(f"/api/surveys/{sid}").json()
    finally:
        event.remove(Line, "load", on_load)
    assert loaded == []
    assert listing[0]["n_lines"] == one["n_lines"] == len(client.get(f"/api/surveys/{sid}/lines").json()) == 3


def test_line_qc_of_many_lines_matches_a_direct_computation(tmp_path, monkeypatch):
    """The QC of every line masked the whole flight and projected its track in its own call (20,000
    lines: 46 s under the survey's lock); the samples are now found by bisection and a flight's
    tracks projected at once.  Each line's mean height and map track equal a direct computation."""
    import numpy as np
    import pandas as pd

    import app.core.geodesy as geodesy
    from app.io.survey import read_survey
    from app.web.store import survey_qc

    root = make_tiny_survey(tmp_path / "s")
    n = 400
    t0 = 1000.5 + np.arange(n) * 399.0 / n
    pd.DataFrame({"line": [f"L{i}" for i in range(n)], "flight": "f1", "t_start": t0,
                  "t_end": t0 + 399.0 / n - 1e-3, "kind": "main"}).to_csv(root / "lines.csv", index=False)
    survey = read_survey(root)
    calls = []
    real = geodesy.project_km
    monkeypatch.setattr(geodesy, "project_km", lambda *a, **k: calls.append(1) or real(*a, **k))
    _flights, lines = survey_qc(survey, track_points=5)
    assert len(calls) == 1 and len(lines) == n
    g = survey.flights["f1"].gnss
    for ln in lines:
        m = ((g["time"] >= ln["t_start"]) & (g["time"] <= ln["t_end"])).to_numpy()
        assert ln["qc"]["mean_h_m"] == pytest.approx(float(g["h"][m].mean()), rel=1e-12)
        step = max(1, int(m.sum()) // 5)
        e, nn = real(g["lon"][m].to_numpy()[::step], g["lat"][m].to_numpy()[::step], "EPSG:32657")
        assert ln["map_track"]["easting_km"] == pytest.approx(np.round(e, 3).tolist(), abs=1e-9), ln["line"]
        assert ln["map_track"]["northing_km"] == pytest.approx(np.round(nn, 3).tolist(), abs=1e-9)
        assert ln["map_track"]["crs"] == "EPSG:32657"


def test_zip_file_names_with_control_characters_refused(client, tiny_src):
    """A flight folder with a newline was refused, but a file in it named ``x\\ny.csv`` was stored in
    the snapshot; file names are checked like flight names (422 naming the entry), nothing stored."""
    import io
    import zipfile

    for bad in ("x\ny.csv", "gnss\u202e.csv", "a\tb.dat"):
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as zf:
            for p in sorted(tiny_src.rglob("*")):
                if p.is_file():
                    zf.write(p, "s/" + p.relative_to(tiny_src).as_posix())
            zf.writestr("s/flights/f1/" + bad, b"a")
        r = import_zip(client, buf.getvalue())
        assert r.status_code == 422, (bad, r.text[:300])
        d = r.json()["detail"]
        assert d["file"] == "s/flights/f1/" + bad and "control character" in d["message"], d
    assert client.get("/api/surveys").json() == []
    assert list((Path(client.app.state.settings.data_dir) / "tmp").iterdir()) == []
