"""The analyst's workflow through the API: the report with its warnings and decisions, survey
metadata (PATCH), deleting a survey, flight names from lines.csv, and exports that open in place
(GDAL via rasterio, xarray, a Surfer parser, Geosoft XYZ)."""

from __future__ import annotations

import io

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
