"""Exports read back by independent readers (xarray, rasterio, pandas, a DSAA parser)."""

import json
import os

import numpy as np
import pandas as pd
import pytest

from app.io import export
from app.io.export import (SURFER_BLANK, atomic_write, write_csv, write_grid_csv, write_grid_geotiff,
                           write_grid_netcdf, write_grid_surfer, write_json, write_parquet)

CRS = "EPSG:32657"


@pytest.fixture
def grid():
    e = 500.0 + 2.0 * np.arange(5)            # km, nx = 5
    n = 7000.0 + 2.0 * np.arange(4)           # km, ny = 4
    E, N = np.meshgrid(e, n)
    dg = 0.5 * (E - 500.0) - 3.0 * (N - 7000.0) + 10.0   # distinct values, row 0 south
    std = 0.1 + 0.01 * (E - 500.0)
    dg[3, 4] = np.nan
    std[3, 4] = np.nan
    return e, n, dg, std


def test_netcdf_roundtrip(tmp_path, grid):
    import xarray as xr
    from pyproj import CRS as PCRS

    e, n, dg, std = grid
    p = write_grid_netcdf(tmp_path / "grid.nc", e, n, dg, std, CRS)
    with xr.open_dataset(p, engine="netcdf4") as ds:
        np.testing.assert_array_equal(ds.easting_km.values, e)
        np.testing.assert_array_equal(ds.northing_km.values, n)
        np.testing.assert_allclose(ds.dg.values, dg, equal_nan=True)
        np.testing.assert_allclose(ds.dg_std.values, std, equal_nan=True)
        assert ds.dg.dims == ("northing_km", "easting_km")
        assert ds.easting_km.attrs["standard_name"] == "projection_x_coordinate"
        assert ds.northing_km.attrs["standard_name"] == "projection_y_coordinate"
        assert ds.easting_km.attrs["units"] == "km" and ds.dg.attrs["units"] == "mGal"
        assert ds.dg.attrs["grid_mapping"] == "crs"
        assert PCRS.from_wkt(ds.crs.attrs["crs_wkt"]).to_epsg() == 32657
        assert PCRS.from_wkt(ds.crs.attrs["spatial_ref"]).to_epsg() == 32657
        assert ds.crs.attrs["grid_mapping_name"] == "transverse_mercator"
        assert ds.attrs["Conventions"].startswith("CF-")


def test_geotiff_roundtrip(tmp_path, grid):
    import rasterio

    e, n, dg, std = grid
    p = write_grid_geotiff(tmp_path / "grid.tif", e, n, dg, std, CRS)
    with rasterio.open(p) as src:
        assert src.count == 2 and src.dtypes == ("float32", "float32")
        assert src.crs.to_epsg() == 32657
        t = src.transform
        assert (t.a, t.e) == pytest.approx((2000.0, -2000.0))
        assert (t.c, t.f) == pytest.approx((499_000.0, 7_007_000.0))   # west edge, north edge (m)
        b1, b2 = src.read(1), src.read(2)
        # row 0 is north; pixel centre of (row, col) = node coordinates
        x, y = src.xy(0, 0)
        assert (x, y) == pytest.approx((500_000.0, 7_006_000.0))
        np.testing.assert_allclose(b1, dg[::-1].astype(np.float32), equal_nan=True)
        np.testing.assert_allclose(b2, std[::-1].astype(np.float32), equal_nan=True)
        assert np.isnan(src.nodata)
        assert src.descriptions == ("dg_mgal", "dg_std_mgal")


def _read_dsaa(path):
    """Minimal Surfer 6 ASCII parser from the format description (Golden Software):
    'DSAA', nx ny, xlo xhi, ylo yhi, zlo zhi, then ny rows of nx values, first row = ylo."""
    tokens = open(path).read().split()
    assert tokens[0] == "DSAA"
    nx, ny = int(tokens[1]), int(tokens[2])
    xlo, xhi, ylo, yhi, zlo, zhi = map(float, tokens[3:9])
    z = np.array(tokens[9:], dtype=float)
    assert z.size == nx * ny
    z = z.reshape(ny, nx)
    z[z >= 1.7e38] = np.nan
    return np.linspace(xlo, xhi, nx), np.linspace(ylo, yhi, ny), z, (zlo, zhi)


def test_surfer_roundtrip(tmp_path, grid):
    e, n, dg, std = grid
    p = write_grid_surfer(tmp_path / "grid.grd", e, n, dg, std)
    x, y, z, (zlo, zhi) = _read_dsaa(p)
    np.testing.assert_allclose(x, e)
    np.testing.assert_allclose(y, n)
    np.testing.assert_allclose(z, dg, equal_nan=True)
    assert (zlo, zhi) == pytest.approx((np.nanmin(dg), np.nanmax(dg)))
    assert f"{SURFER_BLANK:g}" in open(p).read()
    *_, zs, _ = _read_dsaa(tmp_path / "grid_std.grd")
    np.testing.assert_allclose(zs, std, equal_nan=True)


def test_grid_csv_roundtrip(tmp_path, grid):
    e, n, dg, std = grid
    p = write_grid_csv(tmp_path / "grid.csv", e, n, dg, std)
    df = pd.read_csv(p)
    assert list(df.columns) == ["easting_km", "northing_km", "dg_mgal", "dg_std_mgal"]
    assert len(df) == e.size * n.size
    piv = df.pivot(index="northing_km", columns="easting_km", values="dg_mgal")
    np.testing.assert_allclose(piv.to_numpy(), dg, equal_nan=True)
    np.testing.assert_allclose(piv.index.to_numpy(), n)


def test_tables_and_json(tmp_path):
    df = pd.DataFrame({"line": ["L1", "L2"], "x": [1.5, np.nan], "k": np.array([1, 2], dtype=np.int64)})
    pd.testing.assert_frame_equal(pd.read_parquet(write_parquet(df, tmp_path / "a.parquet")), df)
    pd.testing.assert_frame_equal(pd.read_csv(write_csv(df, tmp_path / "a.csv")), df)
    obj = {"rms": np.float64(0.5), "n": np.int64(3), "arr": np.array([[1.0, np.nan]]),
           "nan": float("nan"), "ok": np.bool_(True), "path": tmp_path, 7: "key"}
    back = json.loads(open(write_json(obj, tmp_path / "r.json")).read())
    assert back == {"rms": 0.5, "n": 3, "arr": [[1.0, None]], "nan": None, "ok": True,
                    "path": str(tmp_path), "7": "key"}


def test_atomic_failure_keeps_old_file(tmp_path, grid, monkeypatch):
    target = tmp_path / "report.json"
    write_json({"v": 1}, target)
    old = target.read_bytes()

    class Bad:
        pass

    # the encoder has already streamed part of the document when it meets Bad()
    with pytest.raises(TypeError):
        write_json({"a": list(range(1000)), "z": Bad()}, target)
    assert target.read_bytes() == old
    assert os.listdir(tmp_path) == ["report.json"]

    def half_then_fail(tmp):
        with open(tmp, "w") as f:
            f.write("partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, half_then_fail)
    assert target.read_bytes() == old and os.listdir(tmp_path) == ["report.json"]

    # a failing rename also leaves the old grid and no temporary file
    e, n, dg, std = grid
    nc = tmp_path / "grid.nc"
    write_grid_netcdf(nc, e, n, dg, std, CRS)
    before = nc.read_bytes()
    monkeypatch.setattr(export.os, "replace", lambda *a: (_ for _ in ()).throw(OSError("boom")))
    with pytest.raises(OSError):
        write_grid_netcdf(nc, e, n, dg + 1, std, CRS)
    monkeypatch.undo()
    assert nc.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["grid.nc", "report.json"]


def test_grid_validation(tmp_path, grid):
    e, n, dg, std = grid
    with pytest.raises(ValueError, match="shape"):
        write_grid_netcdf(tmp_path / "g.nc", e, n, dg.T, std, CRS)
    with pytest.raises(ValueError, match="uniformly"):
        write_grid_geotiff(tmp_path / "g.tif", np.array([0.0, 1.0, 3.0, 4.0, 5.0]), n, dg, std, CRS)
    with pytest.raises(ValueError, match="CRS"):
        write_grid_geotiff(tmp_path / "g.tif", e, n, dg, std, "EPSG:999999")
    with pytest.raises(ValueError, match="no finite"):
        write_grid_surfer(tmp_path / "g.grd", e, n, np.full_like(dg, np.nan))
    assert not any(p.name.startswith("g.") for p in tmp_path.iterdir())
