"""Third hostile pass over the web server: each test is a case that was broken (a 500, a hang, a
request costing the server far more than its size) and the behaviour the fix gives."""

from __future__ import annotations

from pathlib import Path

import pytest

from .conftest import import_zip, make_tiny_survey, zip_dir, zip_with


@pytest.fixture(scope="module")
def tiny_src(tmp_path_factory) -> Path:
    return make_tiny_survey(tmp_path_factory.mktemp("third") / "tiny", name="tiny")


def test_unpaired_surrogates_in_json_are_4xx(client, tiny_src):
    """A JSON string may escape half of a UTF-16 pair (``"\\ud800"``); Python reads it as a lone
    surrogate that cannot be written as UTF-8, so the 422 echoing it, the survey.toml written with it
    and the database row all failed with a 500.  Every such request is a 4xx with a reason now, and
    nothing is stored."""
    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    before = client.get(f"/api/surveys/{sid}").json()
    s = b"\\ud800"
    cases = [("POST", "/api/surveys", b'{"name": "a' + s + b'"}'),
             ("POST", f"/api/surveys/{sid}/jobs", b'{"kind": "process", "params": {"x' + s + b'": 1}}'),
             ("POST", f"/api/surveys/{sid}/jobs", b'{"kind": "p' + s + b'"}'),
             ("POST", f"/api/surveys/{sid}/jobs", b'{"kind": "process", "params": {"em_tol": "' + s + b'"}}'),
             ("PATCH", f"/api/surveys/{sid}", b'{"survey": {"name": "' + s + b'"}}'),
             ("PATCH", f"/api/surveys/{sid}", b'{"survey": {"crs": "' + s + b'"}}'),
             ("PATCH", f"/api/surveys/{sid}", b'{"gravimeter": {"model": "GT' + s + b'"}}'),
             ("PATCH", f"/api/surveys/{sid}", b'{"gravimeter": {"tau_s": "' + s + b'"}}')]
    for method, url, body in cases:
        r = client.request(method, url, content=body, headers={"content-type": "application/json"})
        assert r.status_code == 422, (method, url, body, r.status_code, r.text[:300])
        assert r.json()["detail"], r.text
    assert [x["id"] for x in client.get("/api/surveys").json()] == [sid]
    after = client.get(f"/api/surveys/{sid}").json()
    assert after["settings"] == before["settings"] and after["last_job"] is None


def test_huge_survey_toml_refused_unread(client, tiny_src, monkeypatch):
    """survey.toml was read whole and parsed whatever its size: a 0.3 MB zip holding a 300 MB comment
    in it cost the server 800 MB and 10 s and was stored (and read again at every job submission).
    It is refused from its size, naming survey.toml, and nothing is stored.  What is guarded is
    that the TOML parser never sees more than MAX_CONFIG_BYTES (spied at ``tomllib.loads``, the
    parser survey.toml goes through), not how long the request took."""
    import tomllib

    from app.io.survey import MAX_CONFIG_BYTES

    real_loads = tomllib.loads
    parsed: list[int] = []

    def spy(text, *a, **kw):
        parsed.append(len(text))
        return real_loads(text, *a, **kw)

    monkeypatch.setattr(tomllib, "loads", spy)
    toml = (tiny_src / "survey.toml").read_bytes() + b"# " + b"x" * (MAX_CONFIG_BYTES + 10) + b"\n"
    r = import_zip(client, zip_with(tiny_src, {"survey.toml": toml}))
    assert r.status_code == 422, r.text[:300]
    d = r.json()["detail"]
    assert d["file"] == "survey.toml" and "MB" in d["message"], d
    assert not [n for n in parsed if n > MAX_CONFIG_BYTES], parsed
    assert client.get("/api/surveys").json() == []
    # a survey.toml just under the bound is read as before
    ok = (tiny_src / "survey.toml").read_bytes() + b"# " + b"x" * (MAX_CONFIG_BYTES - 1000) + b"\n"
    assert import_zip(client, zip_with(tiny_src, {"survey.toml": ok})).status_code == 201


def _many_lines(n: int) -> bytes:
    """lines.csv with ``n`` short lines inside the tiny survey's flight (1005–1395 s)."""
    step = 390.0 / n
    return ("line,flight,t_start,t_end,kind\n" + "".join(
        f"L{i},f1,{1005 + i * step:.6f},{1005 + (i + 0.9) * step:.6f},main\n" for i in range(n))).encode()


def test_survey_lines_bounded_in_zips_too(client, tiny_src, monkeypatch):
    """An uploaded lines file may list 100,000 lines, but a zip's lines.csv had no bound: 200,000 lines
    in a 2 MB zip took 27 s and 1.2 GB of the server and were stored (a million would take the
    server's memory).  A survey of more lines than an upload may list is refused (422 naming
    lines.csv) before its QC and database rows are built, and nothing is stored.  What is guarded
    is that the survey reader (which checks every line's window) and the QC are never run on it —
    spied at ``app.io.survey.read_survey`` and ``app.web.services.survey_qc`` — not how long the
    request took."""
    import app.io.survey as survey_io
    import app.web.services as services
    from app.web.services import MAX_LINES_ROWS

    calls: list[str] = []
    hostile = True

    def spy(name, real):
        def f(*a, **kw):
            calls.append(name)
            if hostile:   # fail now: the old code spent half a minute in them
                raise AssertionError(f"{name} ran on a survey of {MAX_LINES_ROWS + 1:,} lines")
            return real(*a, **kw)
        return f

    monkeypatch.setattr(survey_io, "read_survey", spy("read_survey", survey_io.read_survey))
    monkeypatch.setattr(services, "survey_qc", spy("survey_qc", services.survey_qc))
    r = import_zip(client, zip_with(tiny_src, {"lines.csv": _many_lines(MAX_LINES_ROWS + 1)}))
    assert r.status_code == 422, r.text[:300]
    d = r.json()["detail"]
    assert d["file"] == "lines.csv" and f"{MAX_LINES_ROWS + 1:,} lines" in d["message"], d
    assert calls == [], calls
    assert client.get("/api/surveys").json() == []
    # the spies see a survey within the bound: it is read and its QC built
    hostile = False
    assert import_zip(client, zip_with(tiny_src, {"lines.csv": _many_lines(5)})).status_code == 201
    assert calls == ["read_survey", "survey_qc"], calls


def test_survey_lines_bounded_across_flight_uploads(client, tiny_src, monkeypatch):
    """Each flight upload was bounded alone, so uploads one after another grew a survey without
    limit (every upload rebuilding every line's QC and rows); the survey's total is bounded."""
    import app.web.services as services

    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    monkeypatch.setattr(services, "MAX_SURVEY_LINES", 4)
    fdir = tiny_src / "flights" / "f1"
    files = {"gravimeter": ("g.csv", (fdir / "gravimeter.csv").read_bytes()),
             "gnss": ("n.csv", (fdir / "gnss.csv").read_bytes())}
    one = b"line,t_start,t_end,kind\nA1,1010,1140,main\n"
    two = b"line,t_start,t_end,kind\nA1,1010,1140,main\nA2,1150,1280,main\n"
    r = client.post(f"/api/surveys/{sid}/flights", files={**files, "lines": ("l.csv", two)}, data={"flight": "f2"})
    assert r.status_code == 422, r.text[:300]
    assert r.json()["detail"]["file"] == "lines.csv" and "5 lines" in r.json()["detail"]["message"]
    s = client.get(f"/api/surveys/{sid}").json()
    assert s["flights"] == ["f1"] and s["n_lines"] == 3
    r = client.post(f"/api/surveys/{sid}/flights", files={**files, "lines": ("l.csv", one)}, data={"flight": "f2"})
    assert r.status_code == 201 and r.json()["n_lines"] == 4, r.text[:300]


def test_crs_naming_a_server_file_refused_unopened(client, tiny_src, tmp_path):
    """A PROJ string may name grid files by path (``+nadgrids=/some/file``): PROJ opened whatever the
    CRS named while a PATCH (or an import) was validated, and on a FIFO — or ``/dev/stdin`` of a
    server started from a terminal — it blocked holding the GIL: the whole server froze for good.  A
    CRS whose grid, init or other file parameter is a path is refused (422 naming survey.crs) without
    being opened; grids by bare name from PROJ's own data and CRS names with '/' are accepted."""
    import os
    import subprocess
    import sys

    fifo = tmp_path / "grid.gsb"
    os.mkfifo(fifo)
    # in a process of its own: the old code never returns
    crs = f"+proj=utm +zone=57 +ellps=GRS80 +nadgrids={fifo}"
    check = f"from app.config import SurveySection\ntry:\n    SurveySection(crs={crs!r})\nexcept ValueError as e:\n    print(e)\n"
    try:
        out = subprocess.run([sys.executable, "-c", check], cwd=Path(__file__).resolve().parents[2],
                             capture_output=True, text=True, timeout=30).stdout
    except subprocess.TimeoutExpired:
        pytest.fail("validating a CRS naming a FIFO blocked")
    assert "names a file" in out, out

    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    for crs in ("+proj=utm +zone=57 +ellps=GRS80 +nadgrids=/etc/passwd",
                "+proj=utm +zone=57 +ellps=GRS80 +nadgrids=@/tmp/x.gsb,@null",
                "+proj=utm +zone=57 +ellps=GRS80 +geoidgrids=../x.gtx",
                "+proj=utm +zone=57 +ellps=GRS80 +towgs84=0,0,0 +init=/etc/passwd:1",
                "+proj=utm +zone=57 +ellps=GRS80 +nadgrids=C:\\x.gsb"):
        r = client.patch(f"/api/surveys/{sid}", json={"survey": {"crs": crs}})
        assert r.status_code == 422, (crs, r.text[:300])
        d = r.json()["detail"][0]
        assert d["loc"][-2:] == ["survey", "crs"] and "names a file" in d["msg"], d
    assert client.get(f"/api/surveys/{sid}").json()["settings"]["survey"]["crs"] == "EPSG:32657"
    for ok in ("WGS 84 / UTM zone 57N", "+proj=utm +zone=57 +ellps=GRS80 +nadgrids=@null"):
        r = client.patch(f"/api/surveys/{sid}", json={"survey": {"crs": ok}})
        assert r.status_code == 200 and r.json()["crs"] == ok, r.text[:300]


def test_profile_lowpass_cost_does_not_grow_with_its_width(client, tiny_src, monkeypatch):
    """The profile's z low-pass was a direct Gaussian convolution, whose cost is the line's samples ×
    the kernel's: a 1 h line of 100 Hz GNSS at z_lowpass_s = 600 (the allowed maximum) took 23 s of
    the server per request, any client could ask for it again with another width.  It costs about
    the same at any width now, and gives the same values.  What is guarded is the work, not the
    time: no direct convolution (``scipy.ndimage.gaussian_filter1d``, spied) uses a kernel wider
    than 513 taps — wider ones go by FFT; benchmarks/bench_web.py prints the request times."""
    import numpy as np
    import pandas as pd
    from scipy.ndimage import gaussian_filter1d

    from .conftest import wait_job

    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    assert wait_job(client, job["id"])["status"] == "succeeded"
    rid = client.get(f"/api/surveys/{sid}").json()["current_result_id"]
    rng = np.random.default_rng(1)

    def line(n: int, dt: float) -> pd.DataFrame:
        t = 1000.0 + dt * np.arange(n)
        return pd.DataFrame({"line": "X", "flight": "f1", "kind": "main", "time": t, "easting_km": 0.1 * (t - 1000.0),
                             "northing_km": 0.0, "z_mgal": np.cumsum(rng.normal(0, 1, n)) + rng.normal(0, 30, n),
                             "dg_mgal": 0.0, "dg_std_mgal": 1.0, "dg_stationary_mgal": 0.0, "dg_fir_mgal": 0.0,
                             "state": 0})

    groups = {"LONG": line(360_000, 0.01), "SHORT": line(5_000, 0.01), "TEN_HZ": line(3_000, 0.1)}
    client.app.state.cache.get(("lines", rid), lambda: {"groups": groups})   # the result's lines, as loaded
    import scipy.ndimage

    real_filter = scipy.ndimage.gaussian_filter1d
    direct: list[tuple[int, int]] = []      # (samples, kernel taps) of each direct convolution

    def spy(x, sigma, *a, truncate=4.0, **kw):
        taps = 2 * int(truncate * float(sigma) + 0.5) + 1
        direct.append((len(x), taps))
        if taps > 513:   # fail now: the old code's 360,000 × 152,883 convolution takes minutes
            raise AssertionError(f"direct Gaussian convolution of {len(x):,} samples × {taps:,} taps")
        return real_filter(x, sigma, *a, truncate=truncate, **kw)

    with monkeypatch.context() as m:
        m.setattr(scipy.ndimage, "gaussian_filter1d", spy)
        r = client.get(f"/api/surveys/{sid}/lines/LONG", params={"z_lowpass_s": 600, "max_points": 2000})
        assert r.status_code == 200, r.text[:300]
        r = client.get(f"/api/surveys/{sid}/lines/LONG", params={"z_lowpass_s": 1.0, "max_points": 2000})
        assert r.status_code == 200, r.text[:300]
    # the narrow width went the direct way (a kernel of 255 taps), the wide one did not
    assert direct == [(360_000, 2 * int(3.0 * 1.0 / (2.3548 * 0.01) + 0.5) + 1)], direct
    for name, width in (("SHORT", 600.0), ("SHORT", 30.0), ("TEN_HZ", 30.0), ("TEN_HZ", 0.5)):
        g = groups[name]
        p = client.get(f"/api/surveys/{sid}/lines/{name}", params={"z_lowpass_s": width, "max_points": 50000}).json()
        want = gaussian_filter1d(g["z_mgal"].to_numpy(), width / (2.3548 * 0.01 if name == "SHORT" else 2.3548 * 0.1),
                                 mode="nearest", truncate=3.0)
        np.testing.assert_allclose(p["z_lowpassed"], want, atol=2e-3, err_msg=f"{name} at {width} s")
