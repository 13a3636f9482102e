"""DEM reader (app.io.dem): reprojection from a geographic GeoTIFF, round trip, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from app.core.geodesy import project_km
from app.core.terrain import Dem
from app.io.dem import read_dem, write_dem
from app.io.errors import InputError

CRS = "EPSG:32657"


def _surface(e_m, n_m):
    return 600.0 + 250.0 * np.sin(e_m / 7000.0) * np.cos(n_m / 9000.0)


def _geotiff(path, data, transform, crs="EPSG:4326", nodata=None, dtype="float64"):
    with rasterio.open(path, "w", driver="GTiff", width=data.shape[1], height=data.shape[0], count=1,
                       dtype=dtype, crs=crs, transform=transform, nodata=nodata) as dst:
        dst.write(data.astype(dtype), 1)
    return path


def _geographic_dem(tmp_path, **kw):
    # 0.002° × 0.001° pixels (~90 m × 110 m at 65.5° N) around 160 E, 65.5 N
    lon = 159.7 + 0.002 * (np.arange(300) + 0.5)
    lat = 65.62 - 0.001 * (np.arange(240) + 0.5)
    LON, LAT = np.meshgrid(lon, lat)
    e, n = project_km(LON, LAT, CRS)
    data = _surface(e * 1000, n * 1000)
    return _geotiff(tmp_path / "dem.tif", data, from_origin(159.7, 65.62, 0.002, 0.001), **kw), data


def test_geographic_dem_reprojected_to_utm(tmp_path):
    path, _ = _geographic_dem(tmp_path)
    e0, n0 = (float(v) * 1000 for v in project_km(160.0, 65.5, CRS))
    bounds = (e0 - 5000, e0 + 5000, n0 - 4000, n0 + 4000)
    dem = read_dem(path, CRS, bounds_m=bounds, spacing_m=200.0, margin_m=1000.0, require_bounds_m=bounds)
    assert dem.spacing_m == (200.0, 200.0) and dem.crs == CRS
    assert dem.easting_m[0] <= bounds[0] - 1000 and dem.northing_m[-1] >= bounds[3] + 1000
    E, N = np.meshgrid(dem.easting_m, dem.northing_m)
    err = dem.height_m - _surface(E, N)
    assert np.nanmax(np.abs(err)) < 0.5, np.nanmax(np.abs(err))     # bilinear on a ~100 m raster
    assert dem.info["source_crs"] == "EPSG:4326" and dem.info["valid_fraction"] == 1.0
    # default spacing: the raster's resolution in metres; default bounds: its footprint
    full = read_dem(path, CRS)
    assert 80 < full.spacing_m[0] < 120
    off = read_dem(path, CRS, bounds_m=bounds, spacing_m=200.0, height_offset_m=12.5)
    np.testing.assert_allclose(off.height_m - 12.5, read_dem(path, CRS, bounds_m=bounds, spacing_m=200.0).height_m)


def test_write_read_round_trip(tmp_path):
    x = 500000.0 + 250.0 * np.arange(40)
    y = 7260000.0 + 250.0 * np.arange(30)
    X, Y = np.meshgrid(x, y)
    h = _surface(X, Y)
    h[3, 4] = np.nan
    dem = Dem(x, y, h, crs=CRS)
    p = write_dem(tmp_path / "dem.tif", dem)
    back = read_dem(p, CRS, bounds_m=(x[0], x[-1], y[0], y[-1]), spacing_m=250.0, resampling="nearest")
    np.testing.assert_array_equal(back.easting_m, x)
    np.testing.assert_array_equal(back.northing_m, y)
    np.testing.assert_allclose(back.height_m, h.astype(np.float32), equal_nan=True)


def test_bad_input(tmp_path):
    (tmp_path / "junk.tif").write_text("not a raster")
    with pytest.raises(InputError, match="not a GeoTIFF"):
        read_dem(tmp_path / "junk.tif", CRS)
    # a GDAL VRT named dem.tif, pointing at a raster elsewhere on the machine: refused, never read
    elsewhere = _geotiff(tmp_path / "elsewhere.tif", np.full((10, 10), 100.0),
                         from_origin(500000, 7270000, 100, 100), crs=CRS)
    (tmp_path / "dem.tif").write_text(
        f'<VRTDataset rasterXSize="10" rasterYSize="10"><VRTRasterBand dataType="Float64" band="1">'
        f'<SimpleSource><SourceFilename relativeToVRT="0">{elsewhere}</SourceFilename><SourceBand>1</SourceBand>'
        f'</SimpleSource></VRTRasterBand></VRTDataset>')
    with pytest.raises(InputError, match="not a GeoTIFF"):
        read_dem(tmp_path / "dem.tif", CRS)
    # no CRS
    data = np.full((10, 10), 100.0)
    p = _geotiff(tmp_path / "nocrs.tif", data, from_origin(500000, 7270000, 100, 100), crs=None)
    with pytest.raises(InputError) as ei:
        read_dem(p, CRS)
    assert ei.value.column == "crs"
    # heights in feet × 100 or garbage: the first offending pixel
    data[6, 3] = 30000.0
    p = _geotiff(tmp_path / "bad.tif", data, from_origin(500000, 7270000, 100, 100), crs=CRS)
    with pytest.raises(InputError) as ei:
        read_dem(p, CRS)
    assert ei.value.row == 7 and ei.value.column == "band 1" and "column 4" in str(ei.value)
    # a hole (nodata) under the survey lines, named by its pixel
    data = np.full((20, 20), 100.0)
    data[10, 10] = -9999.0          # centre 500550 E, 7269450 N
    p = _geotiff(tmp_path / "hole.tif", data, from_origin(499500, 7270500, 100, 100), crs=CRS, nodata=-9999.0)
    area = (500000.0, 501000.0, 7269000.0, 7270000.0)
    with pytest.raises(InputError) as ei:
        read_dem(p, CRS, bounds_m=area, spacing_m=100.0, require_bounds_m=area)
    assert ei.value.row == 11 and "column 11" in str(ei.value) and "no terrain height" in str(ei.value)
    ok = read_dem(p, CRS, bounds_m=area, spacing_m=100.0)          # holes allowed outside a required area
    assert np.isnan(ok.height_m).sum() == 1
    # no overlap, grid too large, geographic target
    with pytest.raises(InputError, match="does not overlap"):
        read_dem(p, CRS, bounds_m=(0.0, 1000.0, 0.0, 1000.0))
    with pytest.raises(InputError) as ei:
        read_dem(p, CRS, bounds_m=(0.0, 1e6, 7e6, 8e6), spacing_m=10.0)
    assert ei.value.column == "spacing_m"
    with pytest.raises(InputError, match="not projected"):
        read_dem(p, "EPSG:4326")


def test_check_dem_as_it_arrives(tmp_path):
    """check_dem (uploads): the raster's description, coverage of the lines' extent, the pixel cap,
    heights out of range named by their pixel, nodata-only rasters."""
    from app.io.dem import check_dem

    path, data = _geographic_dem(tmp_path)
    info = check_dem(path, CRS, display="dem.tif")
    assert info["shape"] == [240, 300] and info["source_crs"] == "EPSG:4326" and info["valid_fraction"] == 1.0
    assert info["height_range_m"][0] == pytest.approx(data.min()) and info["height_range_m"][1] == pytest.approx(data.max())
    w, e, s, n = info["footprint_m"]
    check_dem(path, CRS, require_bounds_m=(w + 1000, e - 1000, s + 1000, n - 1000))
    with pytest.raises(InputError, match="does not cover the survey lines") as exc:
        check_dem(path, CRS, require_bounds_m=(w + 1000, e + 1000, s + 1000, n - 1000), display="dem.tif")
    assert exc.value.file == "dem.tif"
    with pytest.raises(InputError, match=r"240 × 300 pixels \(> 1,000\)"):
        check_dem(path, CRS, max_cells=1000)
    bad = data.copy()
    bad[117, 42] = 12000.0
    p2 = _geotiff(tmp_path / "high.tif", bad, from_origin(159.7, 65.62, 0.002, 0.001))
    with pytest.raises(InputError, match="pixel row 118, column 43") as exc:
        check_dem(p2, CRS)
    assert exc.value.row == 118 and exc.value.column == "band 1"
    p3 = _geotiff(tmp_path / "empty.tif", np.full((5, 5), -9999.0), from_origin(159.7, 65.62, 0.002, 0.001), nodata=-9999.0)
    with pytest.raises(InputError, match="holds no data"):
        check_dem(p3, CRS)
