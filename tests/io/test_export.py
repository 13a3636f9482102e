"""Exports read back by independent readers (xarray, rasterio, pandas, a DSAA parser)."""

import json
import os

import numpy as np
import pandas as pd
import pytest

from app.io import export
from app.io.export import (
    SURFER_BLANK,
    atomic_write,
    write_csv,
    write_grid_csv,
    write_grid_geotiff,
    write_grid_netcdf,
    write_grid_surfer,
    write_json,
    write_parquet,
)

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
        np.testing.assert_array_equal(ds.x.values, e * 1000.0)   # metres of the UTM CRS
        np.testing.assert_array_equal(ds.y.values, n * 1000.0)
        # the pipeline's km stay readable (app.pipeline.evaluate.grid_accuracy reads them)
        np.testing.assert_array_equal(ds.easting_km.values, e)
        np.testing.assert_array_equal(ds.northing_km.values, n)
        np.testing.assert_allclose(ds.dg.values, dg, equal_nan=True)
        np.testing.assert_allclose(ds.dg_std.values, std, equal_nan=True)
        assert ds.dg.dims == ("y", "x")
        assert ds.x.attrs["standard_name"] == "projection_x_coordinate"
        assert ds.y.attrs["standard_name"] == "projection_y_coordinate"
        assert ds.x.attrs["units"] == "m" and ds.y.attrs["units"] == "m" and ds.dg.attrs["units"] == "mGal"
        assert ds.easting_km.attrs["units"] == "km" and "standard_name" not in ds.easting_km.attrs
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
        assert src.descriptions == ("dg", "dg_std")
        assert src.units == ("mGal", "mGal")
        assert src.tags(1)["units"] == "mGal" and src.tags(2)["units"] == "mGal"
        assert "standard deviation" in src.tags(2)["long_name"]


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
    np.testing.assert_allclose(x, e * 1000.0)   # metres of the projected CRS
    np.testing.assert_allclose(y, n * 1000.0)
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


def test_grid_files_agree_in_gdal_and_xarray_with_lines_in_metres(tmp_path):
    """The three grid files of one map, read back by GDAL (rasterio) and xarray, cover the same
    place in metres of the CRS, and that place is where the lines are (UTM 57N, ~515–576 km E)."""
    import rasterio
    import xarray as xr
    from pyproj import Transformer

    from app.core.geodesy import project_km

    lon = np.linspace(159.2, 160.3, 200)
    lat = np.linspace(64.05, 64.25, 200)
    le, ln = project_km(lon, lat, CRS)                       # the lines, km (pipeline convention)
    lx, ly = Transformer.from_crs("EPSG:4326", CRS, always_xy=True).transform(lon, lat)   # metres
    e = np.arange(np.floor(le.min()), np.ceil(le.max()) + 0.5, 1.0)
    n = np.arange(np.floor(ln.min()), np.ceil(ln.max()) + 0.5, 1.0)
    E, N = np.meshgrid(e, n)
    dg = np.sin(E / 7.0) + N / 1000.0
    std = np.full_like(dg, 0.5)
    write_grid_netcdf(tmp_path / "grid.nc", e, n, dg, std, CRS)
    write_grid_geotiff(tmp_path / "grid.tif", e, n, dg, std, CRS)
    write_grid_surfer(tmp_path / "grid.grd", e, n, dg, std)
    half = 500.0   # half a 1 km cell, m

    with rasterio.open(tmp_path / "grid.tif") as t:
        tif = t.bounds
        assert t.crs.to_epsg() == 32657
    with rasterio.open(f'NETCDF:"{tmp_path / "grid.nc"}":dg') as c:   # GDAL's netCDF driver
        nc_gdal = c.bounds
        assert c.crs is not None and c.crs.to_epsg() == 32657
        assert c.width == e.size and c.height == n.size
        np.testing.assert_allclose(c.read(1)[::-1] if c.transform.e < 0 else c.read(1), dg, rtol=1e-6)
    with xr.open_dataset(tmp_path / "grid.nc") as ds:
        nc_xr = (float(ds.x.min()) - half, float(ds.y.min()) - half, float(ds.x.max()) + half, float(ds.y.max()) + half)
    x, y, _, _ = _read_dsaa(tmp_path / "grid.grd")
    grd = (x[0] - half, y[0] - half, x[-1] + half, y[-1] + half)
    for b in (nc_gdal, nc_xr, grd):
        np.testing.assert_allclose(tuple(b), tuple(tif), atol=1e-3)
    # the map is where the lines are, in metres (not at 515–576 m)
    assert tif[0] <= lx.min() and lx.max() <= tif[2] and tif[1] <= ly.min() and ly.max() <= tif[3]
    assert lx.min() - tif[0] <= 1500.0 and tif[2] - lx.max() <= 1500.0   # floor/ceil to whole km + half a cell
    assert 500_000 < tif[0] < 600_000 and 7_000_000 < tif[1] < 7_200_000


def test_crs_unit():
    assert export.crs_unit("EPSG:32657") == ("m", 1.0)
    name, factor = export.crs_unit("EPSG:2227")   # California zone 3, US survey feet
    assert name == "US_survey_foot" and factor == pytest.approx(0.3048006096)


def test_lines_xyz_roundtrip(tmp_path):
    from app.io.xyz import scan_xyz

    t = np.arange(0.0, 5.0, 1.0)
    df = pd.concat([pd.DataFrame({"line": name, "flight": "F01", "kind": kind, "time": t0 + t,
                                  "lat": 64.0, "lon": 160.0, "h": 1000.0,
                                  "easting_km": 520.0 + t, "northing_km": 7100.0 + k,
                                  "z_mgal": 1.0, "dg_mgal": 2.5 + t, "dg_std_mgal": 0.4,
                                  "dg_unleveled_mgal": 2.5, "dg_stationary_mgal": np.nan, "dg_fir_mgal": 2.0,
                                  "state": 1, "Q_mgal2": 0.3, "R_cm2s2": 1.5})
                    for k, (name, kind, t0) in enumerate([("T1", "tie", 100.0), ("L1", "main", 0.0)])])
    p = export.write_lines_xyz(tmp_path / "lines.xyz", df, CRS, comments=("Aerograv line data",))
    scan = scan_xyz(p)
    assert scan.names[:3] == ["X", "Y", "TIME"] and "DG" in scan.names and "DG_FIR" in scan.names
    assert [(b.keyword, b.line_id) for b in scan.blocks] == [("line", "L1"), ("tie", "T1")]   # in time order
    first = scan.data_lines[0].split()
    assert float(first[0]) == 520_000.0 and float(first[1]) == 7_101_000.0    # metres
    assert scan.data_lines[0].split()[scan.names.index("DG_STAT")] == "*"
    text = p.read_text()
    assert "EPSG:32657" in text and "(m)" in text
