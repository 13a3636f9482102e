"""Geophysical products through the API (issue part 5): the DEM with the survey (zip import, PUT /
DELETE /dem, checked as it arrives), grids by product (free-air / Bouguer) and height (flight / datum)
with a 404 that says why, line profiles with the product columns, exports of each product.

The test pipeline (``tests.web.fake_pipeline``) writes the products the real one names (Bouguer
with a dem.tif, the datum columns and grid_flight.* with a datum); the browser test and
tests/pipeline run the real products."""

from __future__ import annotations

import io
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from .conftest import import_zip, make_dem, make_tiny_survey, wait_job, zip_dir


@pytest.fixture(scope="module")
def dem_survey(tmp_path_factory) -> Path:
    root = make_tiny_survey(tmp_path_factory.mktemp("dem") / "tinydem", name="tinydem")
    make_dem(root / "dem.tif")
    return root


def _process(client, sid, **params) -> dict:
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": params}).json()
    j = wait_job(client, job["id"])
    assert j["status"] == "succeeded", j
    return j


def _grid(client, sid, **params):
    return client.get(f"/api/surveys/{sid}/grid", params=params)


# ---------------------------------------------------------------- DEM with the survey
def test_zip_import_keeps_the_dem(client, dem_survey, make_client):
    r = import_zip(client, zip_dir(dem_survey), "tinydem.zip")
    assert r.status_code == 201, r.text
    s = r.json()
    assert s["has_dem"] is True
    snap = Path(client.app.state.store.survey_dir(s["id"])) / "input"
    (inp,) = list(snap.iterdir())
    assert (inp / "dem.tif").read_bytes() == (dem_survey / "dem.tif").read_bytes()
    # without one: has_dem false; other files beside survey.toml are still not stored
    other = dem_survey.parent / "nodem"
    shutil.copytree(dem_survey, other)
    (other / "dem.tif").rename(other / "notes.tif")
    s2 = import_zip(client, zip_dir(other), "nodem.zip").json()
    assert s2["has_dem"] is False
    (inp2,) = list((Path(client.app.state.store.survey_dir(s2["id"])) / "input").iterdir())
    assert not (inp2 / "notes.tif").exists()


@pytest.mark.parametrize("case, column, words", [
    ("garbage", None, "not a GeoTIFF"),
    ("no_crs", "crs", "no coordinate reference system"),
    ("elsewhere", None, "does not cover the survey lines"),
    ("feet", "band 1", "outside"),
])
def test_unusable_dem_is_rejected_naming_the_file(client, dem_survey, tmp_path, case, column, words):
    import rasterio

    root = tmp_path / case
    shutil.copytree(dem_survey, root)
    dem = root / "dem.tif"
    if case == "garbage":
        dem.write_bytes(b"II*\x00" + np.random.default_rng(0).bytes(5000))
    elif case == "no_crs":
        with rasterio.open(dem) as src:
            prof, data = src.profile, src.read(1)
        prof.pop("crs")
        dem.unlink()
        with rasterio.open(dem, "w", **prof) as dst:
            dst.write(data, 1)
    elif case == "elsewhere":
        make_dem(dem, shift_m=(200_000.0, 0.0))
    else:   # heights in feet of a high plateau: 30 000 > 9 000 m
        with rasterio.open(dem, "r+") as dst:
            dst.write(dst.read(1) * 75.0, 1)
    r = import_zip(client, zip_dir(root), f"{case}.zip")
    assert r.status_code == 422, r.text
    d = r.json()["detail"]
    assert d["file"] == "dem.tif" and d["column"] == column and words in d["message"], d
    assert client.get("/api/surveys").json() == []            # nothing stored


def test_put_and_delete_dem(client, tiny_zip, tmp_path):
    sid = import_zip(client, tiny_zip).json()["id"]
    _process(client, sid)
    r = _grid(client, sid, product="bouguer")
    assert r.status_code == 404 and "has no DEM (dem.tif)" in r.json()["detail"]
    assert client.get(f"/api/surveys/{sid}/export", params={"format": "geotiff", "product": "bouguer"}).status_code == 404
    bad = client.put(f"/api/surveys/{sid}/dem", files={"dem": ("dem.tif", b"not a tiff", "image/tiff")})
    assert bad.status_code == 422 and bad.json()["detail"]["file"] == "dem.tif"
    assert client.get(f"/api/surveys/{sid}").json()["has_dem"] is False
    dem = make_dem(tmp_path / "dem.tif")
    r = client.put(f"/api/surveys/{sid}/dem", files={"dem": ("srtm_57.tif", dem.read_bytes(), "image/tiff")})
    assert r.status_code == 200, r.text
    assert r.json()["has_dem"] is True and r.json()["result_outdated"] is True
    r = _grid(client, sid, product="bouguer")
    assert r.status_code == 404 and "computed without the survey's DEM (added since)" in r.json()["detail"]
    _process(client, sid)
    assert _grid(client, sid, product="bouguer").status_code == 200
    r = client.delete(f"/api/surveys/{sid}/dem")
    assert r.status_code == 200 and r.json()["has_dem"] is False and r.json()["result_outdated"] is True
    # a survey without data has no DEM to take
    empty = client.post("/api/surveys", json={"name": "empty"}).json()["id"]
    r = client.put(f"/api/surveys/{empty}/dem", files={"dem": ("dem.tif", dem.read_bytes(), "image/tiff")})
    assert r.status_code == 409


def test_dem_upload_respects_the_size_limit(make_client, tiny_zip, tmp_path):
    c = make_client(max_upload_mb=5.0, max_uncompressed_mb=1.0)
    sid = import_zip(c, tiny_zip).json()["id"]
    r = c.put(f"/api/surveys/{sid}/dem", files={"dem": ("dem.tif", b"\0" * 1_100_000, "image/tiff")})
    assert r.status_code == 413 and "dem.tif is larger than" in r.json()["detail"]


# ---------------------------------------------------------------- grids, profiles, exports by product
def test_bouguer_grid_profiles_and_exports(client, dem_survey, tmp_path):
    import rasterio
    import xarray as xr

    from app.io.xyz import scan_xyz

    sid = import_zip(client, zip_dir(dem_survey), "tinydem.zip").json()["id"]
    _process(client, sid)
    fa, bg = _grid(client, sid).json(), _grid(client, sid, product="bouguer").json()
    assert fa["product"] == "free_air" and bg["product"] == "bouguer" and fa["height"] == bg["height"] == "flight"
    assert fa["datum"] is None
    assert bg["available"] == {"free_air": {"flight": True, "datum": False}, "bouguer": {"flight": True, "datum": False}}
    assert "no datum was used" in bg["unavailable"]["bouguer@datum"]
    a, b = np.array(fa["dg"], dtype=float), np.array(bg["dg"], dtype=float)
    assert a.shape == b.shape and np.nanmax(np.abs(a - b)) > 1.0
    assert _grid(client, sid, product="bouguer", height="datum").status_code == 404
    assert _grid(client, sid, product="terrain").status_code == 422

    # profiles carry the product columns present
    p = client.get(f"/api/surveys/{sid}/lines/L1").json()
    for k in ("dg_bouguer", "terrain", "terrain_height_m", "atm_corr", "height_m"):
        assert p[k] is not None and len(p[k]) == len(p["dg"]), k
    assert p["dg_datum"] is None and p["dg_flight"] is None
    np.testing.assert_allclose(np.array(p["dg"]) - np.array(p["terrain"]), p["dg_bouguer"], atol=2e-3)

    # exports: the Bouguer grid in every grid format, line data with the product columns
    names = {}
    for fmt in ("geotiff", "netcdf", "surfer", "csv"):
        r = client.get(f"/api/surveys/{sid}/export", params={"format": fmt, "product": "bouguer"})
        assert r.status_code == 200, (fmt, r.text)
        names[fmt] = r.headers["content-disposition"]
        (tmp_path / f"b.{fmt}").write_bytes(r.content)
    assert all("grid_bouguer." in v for v in names.values()), names
    with rasterio.open(tmp_path / "b.geotiff") as t:
        assert t.crs.to_epsg() == 32657
        np.testing.assert_allclose(t.read(1)[::-1], b, atol=1e-3)
    with xr.open_dataset(tmp_path / "b.netcdf") as ds:
        np.testing.assert_allclose(ds["dg"].values, b, atol=1e-3)
    csv = pd.read_csv(tmp_path / "b.csv")
    assert np.nanmax(np.abs(np.sort(csv["dg_mgal"].dropna().to_numpy()) - np.sort(b[np.isfinite(b)]))) < 1e-3
    lines = pd.read_parquet(io.BytesIO(client.get(f"/api/surveys/{sid}/export", params={"format": "parquet"}).content))
    assert {"dg_bouguer_mgal", "terrain_mgal", "terrain_height_m", "atm_corr_mgal"} <= set(lines.columns)
    xyz = tmp_path / "lines.xyz"
    xyz.write_bytes(client.get(f"/api/surveys/{sid}/export", params={"format": "xyz"}).content)
    labels = scan_xyz(xyz).names
    assert {"DG_BOUGUER", "TERRAIN", "TERRAIN_HGT", "ATM_CORR"} <= set(labels), labels
    # the free-air default is unchanged
    r = client.get(f"/api/surveys/{sid}/export", params={"format": "geotiff"})
    assert 'grid.tif' in r.headers["content-disposition"] and "bouguer" not in r.headers["content-disposition"]


def test_datum_grids_at_flight_height_and_at_the_datum(client, dem_survey):
    sid = import_zip(client, zip_dir(dem_survey), "tinydem.zip").json()["id"]
    _process(client, sid, datum="constant", datum_height_m=1100.0)
    g = _grid(client, sid).json()
    assert g["height"] == "datum" and g["datum"]["datum"] == "constant"
    assert g["available"] == {"free_air": {"flight": True, "datum": True}, "bouguer": {"flight": False, "datum": True}}
    assert "at the datum only" in g["unavailable"]["bouguer@flight"]
    fl = _grid(client, sid, height="flight").json()
    assert fl["height"] == "flight" and np.nanmax(np.abs(np.array(fl["dg"], float) - np.array(g["dg"], float))) > 0.5
    r = _grid(client, sid, product="bouguer", height="flight")
    assert r.status_code == 404 and "at the datum only" in r.json()["detail"]
    assert _grid(client, sid, product="bouguer").json()["height"] == "datum"
    r = client.get(f"/api/surveys/{sid}/export", params={"format": "netcdf", "height": "flight"})
    assert r.status_code == 200 and "grid_flight.nc" in r.headers["content-disposition"]
    p = client.get(f"/api/surveys/{sid}/lines/L2").json()
    for k in ("dg_flight", "dg_flight_std", "dg_datum", "dg_datum_std", "datum_height_m", "dg_bouguer"):
        assert p[k] is not None and len(p[k]) == len(p["dg"]), k
    # the flight-height grid of a result without a datum is grid.nc; the datum one does not exist
    sid2 = import_zip(client, zip_dir(dem_survey), "tinydem.zip").json()["id"]
    _process(client, sid2)
    assert _grid(client, sid2, height="flight").json()["height"] == "flight"
    r = _grid(client, sid2, height="datum")
    assert r.status_code == 404 and "no datum was used" in r.json()["detail"]
