"""The analyst's workflow through the API: the report with its warnings and decisions, survey
metadata (PATCH), deleting a survey, flight names from lines.csv, and exports that open in place
(GDAL via rasterio, xarray, a Surfer parser, Geosoft XYZ)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from .conftest import import_zip, wait_job


def _processed(client, tiny_zip) -> int:
    sid = import_zip(client, tiny_zip).json()["id"]
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    assert wait_job(client, job["id"])["status"] == "succeeded"
    return sid


def _read_dsaa(raw: bytes):
    tok = raw.decode().split()
    assert tok[0] == "DSAA"
    nx, ny = int(tok[1]), int(tok[2])
    xlo, xhi, ylo, yhi = map(float, tok[3:7])
    return nx, ny, (xlo, ylo, xhi, yhi)


def test_exports_in_metres_agree_with_each_other_and_the_lines(client, tiny_zip, tmp_path):
    import rasterio
    import xarray as xr

    from app.io.xyz import scan_xyz

    sid = _processed(client, tiny_zip)
    files = {}
    for fmt, name in [("geotiff", "grid.tif"), ("netcdf", "grid.nc"), ("surfer", "grid.grd"),
                      ("parquet", "lines.parquet"), ("xyz", "lines.xyz")]:
        r = client.get(f"/api/surveys/{sid}/export", params={"format": fmt})
        assert r.status_code == 200, (fmt, r.text)
        files[fmt] = tmp_path / name
        files[fmt].write_bytes(r.content)
    lines = pd.read_parquet(files["parquet"])
    lx, ly = lines["easting_km"].to_numpy() * 1000, lines["northing_km"].to_numpy() * 1000

    with rasterio.open(files["geotiff"]) as t:
        tif, res = t.bounds, t.res
        assert t.crs.to_epsg() == 32657 and t.descriptions == ("dg", "dg_std") and t.units == ("mGal", "mGal")
    with rasterio.open(f'NETCDF:"{files["netcdf"]}":dg') as c:
        gdal_nc = c.bounds
        assert c.crs.to_epsg() == 32657
    with xr.open_dataset(files["netcdf"]) as ds:
        assert ds.x.attrs["units"] == "m" and ds.x.attrs["standard_name"] == "projection_x_coordinate"
        assert ds.y.attrs["standard_name"] == "projection_y_coordinate" and ds.dg.attrs["grid_mapping"] == "crs"
        assert "crs_wkt" in ds.crs.attrs and "spatial_ref" in ds.crs.attrs
        hx, hy = res[0] / 2, res[1] / 2
        xr_nc = (float(ds.x[0]) - hx, float(ds.y[0]) - hy, float(ds.x[-1]) + hx, float(ds.y[-1]) + hy)
    nx, ny, (xlo, ylo, xhi, yhi) = _read_dsaa(files["surfer"].read_bytes())
    grd = (xlo - hx, ylo - hy, xhi + hx, yhi + hy)
    for b in (gdal_nc, xr_nc, grd):
        np.testing.assert_allclose(tuple(b), tuple(tif), atol=1e-3)
    # the lines lie inside the map, in metres, and the map does not reach far beyond them
    assert tif[0] <= lx.min() and lx.max() <= tif[2] and tif[1] <= ly.min() and ly.max() <= tif[3]
    assert max(lx.min() - tif[0], tif[2] - lx.max()) <= 2 * res[0]

    scan = scan_xyz(files["xyz"])
    assert [b.line_id for b in scan.blocks] == ["L1", "L2", "T1"] and scan.blocks[-1].keyword == "tie"
    x = np.array([float(r.split()[0]) for r in scan.data_lines])
    np.testing.assert_allclose(np.sort(x), np.sort(lx), rtol=1e-9)
    assert client.get(f"/api/surveys/{sid}/export", params={"format": "xyz"}).content == files["xyz"].read_bytes()


def test_report_with_warnings_decisions_and_adaptive_minus_fir(client, tiny_zip):
    sid = import_zip(client, tiny_zip).json()["id"]
    assert client.get(f"/api/surveys/{sid}/report").status_code == 404          # no result yet
    assert client.get("/api/surveys/9999/report").status_code == 404            # no survey
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    assert wait_job(client, job["id"])["status"] == "succeeded"
    r = client.get(f"/api/surveys/{sid}/report")
    assert r.status_code == 200, r.text
    rep = r.json()
    assert rep["job_id"] == job["id"] and rep["result_id"] == client.get(f"/api/surveys/{sid}").json()["current_result_id"]
    assert any(w.startswith("no absolute base tie") for w in rep["warnings"]) and not rep["absolute_base_tie"]
    assert rep["leveled"] is False and rep["leveling_status"].startswith("not leveled")
    assert rep["report"]["repeat_lines"]["R1"]["internal_accuracy_mgal"]["dg_mgal"] == 3.73
    assert "model_choice" in rep["report"] and "future_section" in rep["report"]
    ident = rep["identification"]
    assert [s["index"] for s in ident["states"]] == [0, 1] and len(ident["transition"]) == 2
    assert ident["em"]["n_iterations"] == 3 and ident["em"]["final"]["iteration"] == 2
    assert ident["em"]["selection"]["chosen"] == "2x1"
    # adaptive − FIR per line, from lines.parquet (both before leveling)
    lines = pd.read_parquet(io.BytesIO(client.get(f"/api/surveys/{sid}/export", params={"format": "parquet"}).content))
    g = lines[lines["line"] == "L1"]
    d = g["dg_unleveled_mgal"] - g["dg_fir_mgal"]
    l1 = next(x for x in rep["adaptive_minus_fir"] if x["line"] == "L1")
    assert l1["n"] == len(g) and l1["kind"] == "main" and l1["flight"] == "f1"
    assert l1["rms_mgal"] == pytest.approx(float(np.sqrt(np.mean(d ** 2))))
    assert l1["mean_mgal"] == pytest.approx(float(d.mean())) and l1["std_mgal"] == pytest.approx(float(d.std(ddof=0)))
    assert [x["line"] for x in rep["adaptive_minus_fir"]] == ["L1", "L2", "T1"]
    assert rep["crossovers"][0]["line_a"] == "L1" and rep["crossovers"][0]["diff_before_mgal"] == 1.2
    assert "/api/surveys/{survey_id}/report" in client.get("/openapi.json").json()["paths"]


def test_patch_survey_settings(client, tiny_zip):
    sid = import_zip(client, tiny_zip).json()["id"]
    s0 = client.get(f"/api/surveys/{sid}").json()
    assert s0["settings"]["gravimeter"] == {"model": "GT-1A", "tau_s": 0.0, "scale": 1.0, "rate_hz": None,
                                            "base_gravity_mgal": None}
    assert s0["settings"]["survey"]["crs"] == "EPSG:32657"
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    wait_job(client, job["id"])
    assert client.get(f"/api/surveys/{sid}").json()["result_outdated"] is False
    r = client.patch(f"/api/surveys/{sid}", json={"survey": {"name": "Block A", "crs": "EPSG:32658"},
                                                  "gravimeter": {"base_gravity_mgal": 982316.4, "tau_s": 2.0,
                                                                 "model": "GT-2A", "rate_hz": 18.24}})
    assert r.status_code == 200, r.text
    s1 = r.json()
    assert s1["name"] == "Block A" and s1["crs"] == "EPSG:32658" and s1["result_outdated"] is True
    assert s1["settings"]["gravimeter"] == {"model": "GT-2A", "tau_s": 2.0, "scale": 1.0, "rate_hz": 18.24,
                                            "base_gravity_mgal": 982316.4}
    # stored as a new input snapshot: the survey.toml the pipeline reads says so, the old snapshot is intact
    import tomllib

    from app.web.db import Survey
    with client.app.state.Session() as db:
        new_dir = db.get(Survey, sid).input_dir
    toml = tomllib.loads((Path(new_dir) / "survey.toml").read_text())
    assert toml["survey"]["name"] == "Block A" and toml["gravimeter"]["base_gravity_mgal"] == 982316.4
    # the line map follows the new CRS (tracks reprojected into zone 58)
    t = client.get(f"/api/surveys/{sid}/tracks").json()
    assert t["crs"] == "EPSG:32658" and t["lines"][0]["easting_km"][0] < 400
    # null removes an optional field (rate inferred again, no base tie)
    r = client.patch(f"/api/surveys/{sid}", json={"gravimeter": {"rate_hz": None, "base_gravity_mgal": None}})
    assert r.status_code == 200 and r.json()["settings"]["gravimeter"]["rate_hz"] is None
    assert r.json()["settings"]["gravimeter"]["base_gravity_mgal"] is None and r.json()["name"] == "Block A"
    # a job now reads the changed survey.toml (the test pipeline says whether a base tie was made)
    r = client.patch(f"/api/surveys/{sid}", json={"gravimeter": {"base_gravity_mgal": 982000.0}})
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    assert wait_job(client, job["id"])["status"] == "succeeded"
    assert client.get(f"/api/surveys/{sid}/report").json()["absolute_base_tie"] is True
    assert client.get(f"/api/surveys/{sid}").json()["result_outdated"] is False


@pytest.mark.parametrize("body, loc", [
    ({"gravimeter": {"tau_s": -1}}, ["gravimeter", "tau_s"]),
    ({"gravimeter": {"base_gravity_mgal": 5.0}}, ["gravimeter", "base_gravity_mgal"]),
    ({"gravimeter": {"scale": 0}}, ["gravimeter", "scale"]),
    ({"survey": {"normal_gravity": "flat"}}, ["survey", "normal_gravity"]),
    ({"survey": {"name": "a/b"}}, ["survey", "name"]),
    ({"survey": {"name": None}}, ["survey", "name"]),
    ({"survey": {"crs": "EPSG:4326"}}, ["survey", "crs"]),
    ({"survey": {"crs": "not a crs"}}, ["survey", "crs"]),
    ({"gravimeter": {"rate_hz": 50.0}}, None),      # the reader: the declared rate disagrees with the data
    ({"gravimeter": {"colour": "red"}}, ["body", "gravimeter", "colour"]),
])
def test_patch_survey_422_names_the_field(client, tiny_zip, body, loc):
    sid = import_zip(client, tiny_zip).json()["id"]
    before = client.get(f"/api/surveys/{sid}").json()
    r = client.patch(f"/api/surveys/{sid}", json=body)
    assert r.status_code == 422, r.text
    d = r.json()["detail"]
    if loc is None:
        assert d["file"] == "flights/f1/gravimeter.csv" and "gravimeter.rate_hz" in d["message"], d
    else:
        assert d[0]["loc"] == loc, d
    assert client.get(f"/api/surveys/{sid}").json() == before   # nothing changed


def test_patch_and_delete_need_the_token_404_and_409(make_client, tiny_zip):
    client = make_client(token="s3cret")
    auth = {"Authorization": "Bearer s3cret"}
    sid = import_zip(client, tiny_zip, headers=auth).json()["id"]
    assert client.patch(f"/api/surveys/{sid}", json={"survey": {"name": "x"}}).status_code == 401
    assert client.delete(f"/api/surveys/{sid}").status_code == 401
    assert client.patch(f"/api/surveys/{sid}", json={"survey": {"name": "x"}},
                        headers={"Authorization": "Bearer wrong"}).status_code == 401
    assert client.get(f"/api/surveys/{sid}").json()["name"] == "tiny"
    assert client.patch("/api/surveys/9999", json={"survey": {"name": "x"}}, headers=auth).status_code == 404
    assert client.delete("/api/surveys/9999", headers=auth).status_code == 404
    # an empty survey takes a new name, but no other field until it has data
    empty = client.post("/api/surveys", json={"name": "empty"}, headers=auth).json()["id"]
    r = client.patch(f"/api/surveys/{empty}", json={"survey": {"name": "renamed"}}, headers=auth)
    assert r.status_code == 200 and r.json()["name"] == "renamed"
    assert client.patch(f"/api/surveys/{empty}", json={"gravimeter": {"tau_s": 1}}, headers=auth).status_code == 409
    # a cross-site browser request is refused even with no token set is covered by test_hostile; here:
    # the same-origin rule applies to PATCH and DELETE too
    open_client = make_client(data_dir=Path(client.app.state.settings.data_dir).parent / "open")
    oid = open_client.post("/api/surveys", json={"name": "o"}).json()["id"]
    assert open_client.delete(f"/api/surveys/{oid}", headers={"Sec-Fetch-Site": "cross-site"}).status_code == 403
    assert open_client.patch(f"/api/surveys/{oid}", json={"survey": {"name": "p"}},
                             headers={"Origin": "https://evil.example"}).status_code == 403


def test_delete_survey_removes_rows_files_and_refuses_while_a_job_runs(make_client, tiny_zip, monkeypatch):
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "0.3")
    client = make_client()
    sid = import_zip(client, tiny_zip).json()["id"]
    other = import_zip(client, tiny_zip).json()["id"]
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    r = client.delete(f"/api/surveys/{sid}")
    assert r.status_code == 409 and "job" in r.json()["detail"]
    assert wait_job(client, job["id"])["status"] == "succeeded"
    assert client.get(f"/api/surveys/{sid}/grid").status_code == 200
    sdir = Path(client.app.state.settings.data_dir) / "surveys" / str(sid)
    assert sdir.is_dir()
    assert client.delete(f"/api/surveys/{sid}").status_code == 204
    assert client.get(f"/api/surveys/{sid}").status_code == 404
    assert client.get(f"/api/jobs/{job['id']}").status_code == 404
    assert [s["id"] for s in client.get("/api/surveys").json()] == [other]
    assert not sdir.exists() and not list((Path(client.app.state.settings.data_dir) / "tmp").iterdir())
    assert client.delete(f"/api/surveys/{sid}").status_code == 404
    # a survey created afterwards (ids may be reused) shows nothing of the deleted one
    new = import_zip(client, tiny_zip).json()["id"]
    assert client.get(f"/api/surveys/{new}/grid").status_code == 404


def test_flight_name_defaults_to_the_lines_csv_flight(client, tmp_path):
    from .conftest import make_tiny_survey

    src = make_tiny_survey(tmp_path / "src")
    fdir = src / "flights" / "f1"

    def upload(sid, lines_text, **data):
        files = {"gravimeter": ("gravimeter.csv", (fdir / "gravimeter.csv").read_bytes(), "text/csv"),
                 "gnss": ("gnss.csv", (fdir / "gnss.csv").read_bytes(), "text/csv")}
        if lines_text is not None:
            files["lines"] = ("lines.csv", lines_text.encode(), "text/csv")
        return client.post(f"/api/surveys/{sid}/flights", files=files, data=data)

    one = "line,flight,t_start,t_end,kind\nL1,F01,1010,1140,main\nL2,F01,1150,1280,main\n"
    sid = client.post("/api/surveys", json={"name": "a"}).json()["id"]
    r = upload(sid, one)
    assert r.status_code == 201, r.text
    assert r.json()["flights"] == ["F01"]
    assert {l["flight"] for l in client.get(f"/api/surveys/{sid}/qc").json()["lines"]} == {"F01"}
    # the form's name still wins; two flights in lines.csv or none: today's default
    sid2 = client.post("/api/surveys", json={"name": "b"}).json()["id"]
    assert upload(sid2, one, flight="F07").json()["flights"] == ["F07"]   # its lines become F07's
    assert {l["flight"] for l in client.get(f"/api/surveys/{sid2}/qc").json()["lines"]} == {"F07"}
    sid3 = client.post("/api/surveys", json={"name": "c"}).json()["id"]
    r = upload(sid3, "line,t_start,t_end,kind\nL1,1010,1140,main\n")
    assert r.status_code == 201, r.text
    assert r.json()["flights"] == ["flight1"]


def test_unnamed_flight_never_replaces_a_stored_one_and_ids_are_not_reused(client, tmp_path):
    """An unnamed upload takes a name no stored flight has (flight2 exists: flight3); a deleted
    survey's id is not handed to the next one, so a retried DELETE cannot remove it; a lines file
    of a million rows is refused before it is parsed."""
    from .conftest import make_tiny_survey

    src = make_tiny_survey(tmp_path / "src")
    fdir = src / "flights" / "f1"
    files = lambda lines_text: {  # noqa: E731
        "gravimeter": ("gravimeter.csv", (fdir / "gravimeter.csv").read_bytes(), "text/csv"),
        "gnss": ("gnss.csv", (fdir / "gnss.csv").read_bytes(), "text/csv"),
        "lines": ("lines.csv", lines_text.encode(), "text/csv")}
    sid = client.post("/api/surveys", json={"name": "two flights"}).json()["id"]
    r = client.post(f"/api/surveys/{sid}/flights", data={"flight": "flight2"},
                    files=files("line,t_start,t_end,kind\nA1,1010,1140,main\n"))
    assert r.status_code == 201, r.text
    r = client.post(f"/api/surveys/{sid}/flights", files=files("line,t_start,t_end,kind\nB1,1010,1140,main\n"))
    assert r.status_code == 201, r.text
    assert r.json()["flights"] == ["flight2", "flight3"]
    assert {l["line"] for l in client.get(f"/api/surveys/{sid}/lines").json()} == {"A1", "B1"}
    big = "line,t_start,t_end,kind\n" + "X,1010,1140,main\n" * 100_050
    r = client.post(f"/api/surveys/{sid}/flights", data={"flight": "f9"}, files=files(big))
    assert r.status_code == 422 and "lines.csv" in r.text and "100,000" in r.text
    assert client.get(f"/api/surveys/{sid}").json()["flights"] == ["flight2", "flight3"]
    # ids
    last = client.post("/api/surveys", json={"name": "doomed"}).json()["id"]
    assert client.delete(f"/api/surveys/{last}").status_code == 204
    new = client.post("/api/surveys", json={"name": "bob"}).json()["id"]
    assert new != last
    assert client.delete(f"/api/surveys/{last}").status_code == 404      # the retry
    assert client.get(f"/api/surveys/{new}").status_code == 200


def test_patch_refuses_a_crs_that_cannot_project(client, tiny_zip):
    # parses as a projected CRS, but every point fails to project (k must be > 0)
    sid = import_zip(client, tiny_zip).json()["id"]
    r = client.patch(f"/api/surveys/{sid}", json={"survey": {"crs": "+proj=merc +lon_0=158 +k=1e-10 +type=crs"}})
    assert r.status_code == 422 and "crs" in r.text, r.text
    assert client.get(f"/api/surveys/{sid}").json()["settings"]["survey"]["crs"] == "EPSG:32657"
    assert client.patch(f"/api/surveys/{sid}", json={"survey": {"crs": "EPSG:32658"}}).status_code == 200


def test_gzip_upload_strict_job_params_and_bidi_names(client, tmp_path):
    """A gzip-compressed flight upload is stored as .csv.gz and read (the client's file name is
    not used); job parameters of the wrong JSON type are a 422, not converted; a survey name
    with a right-to-left override is refused."""
    import gzip

    from .conftest import make_tiny_survey

    src = make_tiny_survey(tmp_path / "src")
    fdir = src / "flights" / "f1"
    sid = client.post("/api/surveys", json={"name": "gz"}).json()["id"]
    r = client.post(f"/api/surveys/{sid}/flights", data={"flight": "f1"},
                    files={"gravimeter": ("g", gzip.compress((fdir / "gravimeter.csv").read_bytes()), "application/gzip"),
                           "gnss": ("n", (fdir / "gnss.csv").read_bytes(), "text/csv"),
                           "lines": ("l", (src / "lines.csv").read_bytes(), "text/csv")})
    assert r.status_code == 201, r.text
    for bad in ({"m": True}, {"m": "2"}, {"em_max_iter": True}, {"order_blend": "yes"}):
        r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": bad})
        assert r.status_code == 422, (bad, r.text)
    r = client.post("/api/surveys", json={"name": "report\u202etxt.exe"})
    assert r.status_code == 422 and "control character" in r.text


def test_file_part_without_a_name_is_a_plain_422(client, tiny_zip):
    """A file part sent with filename="" reaches the endpoint as text: the 422 says a file is
    expected and does not echo the bytes."""
    r = import_zip(client, tiny_zip, "")
    assert r.status_code == 422
    d = r.json()["detail"][0]
    assert "file upload is expected" in d["msg"] and "input" not in d and "UploadFile" not in r.text


def test_gravimeter_model_refuses_control_characters(client, tiny_zip):
    """The instrument's model is free text shown in the page and the report: a slash is fine,
    a newline or a text-direction override is a 422 naming the field, and nothing is stored."""
    sid = import_zip(client, tiny_zip).json()["id"]
    r = client.patch(f"/api/surveys/{sid}", json={"gravimeter": {"model": "GT-1A/2A"}})
    assert r.status_code == 200, r.text
    for bad in ("GT-1A\nrm -rf", "GT\u202e2A"):
        r = client.patch(f"/api/surveys/{sid}", json={"gravimeter": {"model": bad}})
        assert r.status_code == 422 and "control character" in r.text and "model" in r.text, r.text
    assert client.get(f"/api/surveys/{sid}").json()["settings"]["gravimeter"]["model"] == "GT-1A/2A"


def test_flight_upload_with_a_lines_file_of_no_lines_is_refused(client, tmp_path):
    """A lines file of garbage bytes (read as a header without rows) or with a header only used
    to add the flight with no lines beside the stored ones: a 422 naming lines.csv, and the
    survey keeps what it had."""
    from .conftest import make_tiny_survey

    src = make_tiny_survey(tmp_path / "src")
    fdir = src / "flights" / "f1"
    sid = client.post("/api/surveys", json={"name": "nolines"}).json()["id"]
    files = {"gravimeter": ("g", (fdir / "gravimeter.csv").read_bytes(), "text/csv"),
             "gnss": ("n", (fdir / "gnss.csv").read_bytes(), "text/csv")}
    r = client.post(f"/api/surveys/{sid}/flights", data={"flight": "f1"},
                    files={**files, "lines": ("l", (src / "lines.csv").read_bytes(), "text/csv")})
    assert r.status_code == 201, r.text
    before = client.get(f"/api/surveys/{sid}").json()
    header = (src / "lines.csv").read_text().splitlines()[0].encode()
    for raw, row in ((b"\x07\x03 zq#%!junk" * 40, 1), (header + b"\n", 2)):
        r = client.post(f"/api/surveys/{sid}/flights", data={"flight": "f2"},
                        files={**files, "lines": ("l", raw, "text/csv")})
        assert r.status_code == 422, r.text
        assert "lines.csv" in r.text and f'"row":{row}' in r.text.replace(" ", ""), r.text
    after = client.get(f"/api/surveys/{sid}").json()
    assert after["flights"] == before["flights"] and len(after["flights"]) == 1, after["flights"]
