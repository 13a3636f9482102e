"""Exports of grids and tables (SPEC §5): netCDF, GeoTIFF, Surfer, CSV, Parquet, JSON.

Grid layout of the writers' arguments: ``easting_km`` shape (nx,), ``northing_km``
shape (ny,), both increasing and uniformly spaced for raster formats, values shape
(ny, nx) with row 0 at the southernmost northing; the coordinates are the node (cell
centre) positions of the projected CRS in thousands of its unit (km for the metre CRSs
of the pipeline, ``app.core.geodesy.project_km``); masked nodes are NaN.

The files carry coordinates in the CRS's own unit (metres for UTM), so GIS software
puts the map where it is: netCDF ``x``/``y`` (CF ``projection_x/y_coordinate``, with
``easting_km``/``northing_km`` kept beside them as auxiliary coordinates), Surfer's
header, the GeoTIFF transform and the XYZ line data's ``X``/``Y``.  The unit comes from
the CRS's axis information (:func:`crs_unit`).

Every writer is atomic: it writes to a temporary file in the destination
directory and renames it over the destination with :func:`os.replace`, so a
failure half-way leaves any previous file intact and no partial file behind.
"""

from __future__ import annotations

import contextlib
import json
import os
import uuid
from pathlib import Path

import numpy as np

from app.jsonsafe import encoder, finite_tree

#: Blank value of Surfer grids.
SURFER_BLANK = 1.70141e38


# --------------------------------------------------------------------------- atomicity

@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path next to ``path``; on success rename it to ``path``.

    The temporary name keeps the suffix (some libraries pick the format from
    it).  On any exception the temporary file is removed and the exception
    re-raised; the destination is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.tmp{path.suffix}")
    try:
        yield tmp
        if not tmp.exists():
            raise OSError(f"writer produced no file for {path}")
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def atomic_write(path, write_fn) -> Path:
    """Call ``write_fn(tmp_path)`` and move the result atomically to ``path``."""
    with atomic_path(path) as tmp:
        write_fn(tmp)
    return Path(path)


# --------------------------------------------------------------------------- grids

def _check_grid(easting_km, northing_km, dg, dg_std=None, uniform=False):
    e = np.asarray(easting_km, dtype=float)
    n = np.asarray(northing_km, dtype=float)
    g = np.asarray(dg, dtype=float)
    if e.ndim != 1 or n.ndim != 1 or e.size < 1 or n.size < 1:
        raise ValueError("easting_km and northing_km must be non-empty 1-D arrays")
    if g.shape != (n.size, e.size):
        raise ValueError(f"dg must have shape (ny, nx) = {(n.size, e.size)}, got {g.shape}")
    s = None
    if dg_std is not None:
        s = np.asarray(dg_std, dtype=float)
        if s.shape != g.shape:
            raise ValueError(f"dg_std must have shape {g.shape}, got {s.shape}")
    for name, a in (("easting_km", e), ("northing_km", n)):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} must be finite")
        if a.size > 1 and not np.all(np.diff(a) > 0):
            raise ValueError(f"{name} must be strictly increasing")
        if uniform:
            if a.size < 2:
                raise ValueError(f"{name}: a raster needs at least 2 nodes per axis")
            d = np.diff(a)
            if not np.allclose(d, d[0], rtol=1e-6, atol=1e-9):
                raise ValueError(f"{name} must be uniformly spaced")
    return e, n, g, s


def _crs(crs):
    from pyproj import CRS

    if crs is None:
        raise ValueError("a CRS is required (e.g. 'EPSG:32657')")
    try:
        return CRS.from_user_input(crs)
    except Exception as exc:
        raise ValueError(f"unknown CRS {crs!r}: {exc}") from exc


#: CF/UDUNITS names of the linear units pyproj reports
_UNIT_NAMES = {"metre": "m", "meter": "m", "kilometre": "km", "foot": "ft", "US survey foot": "US_survey_foot",
               "foot_us": "US_survey_foot"}


def crs_unit(crs) -> tuple[str, float]:
    """(unit name for files, the unit's size in metres, or radians for angles) of the CRS's first
    axis: ``("m", 1.0)`` for UTM.  Grids and lines are laid out in a projected CRS (the web
    application refuses others); whatever the CRS, coordinates are written in its own unit."""
    c = _crs(crs)
    ax = c.axis_info[0] if c.axis_info else None
    if ax is None:
        return "m", 1.0
    name = ax.unit_name or "metre"
    return _UNIT_NAMES.get(name, name.replace(" ", "_")), float(ax.unit_conversion_factor or 1.0)


def to_crs_units(km):
    """Coordinates from the pipeline's km (thousands of the CRS unit, ``project_km``) to the CRS's
    unit."""
    return np.asarray(km, dtype=float) * 1000.0


def write_grid_netcdf(path, easting_km, northing_km, dg, dg_std, crs, attrs: dict | None = None) -> Path:
    """CF-1.8 netCDF grid: variables ``dg``, ``dg_std`` (mGal) on ``y``, ``x``.

    ``x``/``y`` are the node coordinates in the CRS's unit (metres for UTM), ``units`` from the
    CRS's axis information, ``standard_name = projection_x_coordinate /
    projection_y_coordinate``; ``easting_km``/``northing_km`` stay beside them as auxiliary
    coordinates (km) for readers of the pipeline's convention.  A scalar ``crs`` grid-mapping
    variable carries the CF projection attributes from pyproj plus ``crs_wkt`` and
    ``spatial_ref`` (the WKT); the data variables name it in ``grid_mapping``.  Missing nodes are
    NaN (``_FillValue`` NaN).  GDAL and QGIS read it in place (``NETCDF:"grid.nc":dg``).

    Parameters
    ----------
    path : str or Path
    easting_km : ndarray, shape (nx,)
    northing_km : ndarray, shape (ny,)
        Node coordinates in thousands of the CRS unit (km for a metre CRS).
    dg, dg_std : ndarray, shape (ny, nx)
        Anomaly and its std (mGal); ``dg_std`` may be None.
    crs : str or pyproj.CRS
        Projected CRS of the coordinates.
    attrs : dict, optional
        Extra global attributes.
    """
    import netCDF4  # directly: xarray's writer imports dask.array (~0.5 s of a 7 s run)

    e, n, g, s = _check_grid(easting_km, northing_km, dg, dg_std)
    c = _crs(crs)
    unit, _ = crs_unit(c)
    wkt = c.to_wkt()
    crs_attrs = {k: v for k, v in c.to_cf().items() if v is not None}
    crs_attrs.update(crs_wkt=wkt, spatial_ref=wkt)
    crs_attrs = {k: (json.dumps(v) if isinstance(v, (dict, list)) else v) for k, v in crs_attrs.items()}
    km = "km" if unit == "m" else f"1000 {unit}"
    coords = (("x", to_crs_units(e), {"units": unit, "standard_name": "projection_x_coordinate",
                                      "long_name": "easting", "axis": "X"}),
              ("y", to_crs_units(n), {"units": unit, "standard_name": "projection_y_coordinate",
                                      "long_name": "northing", "axis": "Y"}))
    aux = (("easting_km", "x", e, {"units": km, "long_name": "easting (x / 1000)"}),
           ("northing_km", "y", n, {"units": km, "long_name": "northing (y / 1000)"}))
    grids = [("dg", g, "gravity anomaly (free-air disturbance) at flight height")]
    if s is not None:
        grids.append(("dg_std", s, "standard deviation of dg"))

    def write(tmp):
        with netCDF4.Dataset(tmp, "w", format="NETCDF4") as ds:
            ds.setncatts({"Conventions": "CF-1.8", "title": "Aerograv anomaly grid", "crs": c.to_string(),
                          **(attrs or {})})
            ds.createDimension("y", n.size)
            ds.createDimension("x", e.size)
            for name, values, at in coords:
                v = ds.createVariable(name, "f8", (name,))
                v.setncatts(at)
                v[:] = values
            for name, dim, values, at in aux:
                v = ds.createVariable(name, "f8", (dim,))
                v.setncatts(at)
                v[:] = values
            v = ds.createVariable("crs", "i4", ())
            v.setncatts(crs_attrs)
            v.assignValue(0)
            for name, values, long_name in grids:
                v = ds.createVariable(name, "f8", ("y", "x"), fill_value=np.nan)
                v.setncatts({"units": "mGal", "long_name": long_name, "grid_mapping": "crs",
                             "coordinates": "easting_km northing_km"})
                v.set_auto_mask(False)   # NaN is the missing value itself, written as it is
                v[:] = values

    return atomic_write(path, write)


#: GeoTIFF bands: (description, long name)
GEOTIFF_BANDS = (("dg", "gravity anomaly (free-air disturbance) at flight height"),
                 ("dg_std", "standard deviation of dg"))


def write_grid_geotiff(path, easting_km, northing_km, dg, dg_std, crs) -> Path:
    """GeoTIFF with 2 float32 bands (1: dg, 2: dg_std, mGal), nodata NaN.

    North-up: row 0 is the northernmost row; the affine transform is in the CRS's unit
    (metres for UTM) with the node coordinates at pixel centres.  ``dg_std`` None
    writes a band of NaN.  Band descriptions ``dg`` and ``dg_std``, band unit ``mGal``
    (GDAL's unit type) and band tags ``units``, ``long_name``.
    """
    import rasterio
    from affine import Affine
    from rasterio.crs import CRS as RioCRS

    e, n, g, s = _check_grid(easting_km, northing_km, dg, dg_std, uniform=True)
    if s is None:
        s = np.full_like(g, np.nan)
    c = _crs(crs)
    x, y = to_crs_units(e), to_crs_units(n)
    dx_m = (x[-1] - x[0]) / (x.size - 1)
    dy_m = (y[-1] - y[0]) / (y.size - 1)
    transform = Affine(dx_m, 0.0, x[0] - dx_m / 2, 0.0, -dy_m, y[-1] + dy_m / 2)
    profile = dict(driver="GTiff", width=e.size, height=n.size, count=2, dtype="float32",
                   crs=RioCRS.from_wkt(c.to_wkt()), transform=transform, nodata=np.nan)

    def _write(tmp):
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(g[::-1].astype(np.float32), 1)
            dst.write(s[::-1].astype(np.float32), 2)
            for band, (name, long_name) in enumerate(GEOTIFF_BANDS, start=1):
                dst.set_band_description(band, name)
                dst.set_band_unit(band, "mGal")
                dst.update_tags(band, units="mGal", long_name=long_name)
            dst.update_tags(units="mGal", TIFFTAG_SOFTWARE="aerograv")

    return atomic_write(path, _write)


def surfer_text(x, y, values) -> str:
    """Surfer 6 ASCII grid text ("DSAA"), blanks 1.70141e38, rows south to north; the node
    coordinates ``x``, ``y`` written as given."""
    e, n, g, _ = _check_grid(x, y, values)
    ok = np.isfinite(g)
    if not np.any(ok):
        raise ValueError("grid has no finite value to write")
    lines = ["DSAA", f"{e.size} {n.size}", f"{e[0]:.10g} {e[-1]:.10g}", f"{n[0]:.10g} {n[-1]:.10g}",
             f"{g[ok].min():.10g} {g[ok].max():.10g}"]
    z = np.where(ok, g, SURFER_BLANK)
    for row in z:  # row 0 = southernmost (ylo)
        lines.append(" ".join(f"{v:.10g}" for v in row))
    return "\n".join(lines) + "\n"


def _write_text(path, text: str) -> Path:
    def _w(tmp):
        with open(tmp, "w", encoding="ascii", newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
    return atomic_write(path, _w)


def write_grid_surfer(path, easting_km, northing_km, dg, dg_std=None, crs=None) -> Path:
    """Surfer 6 ASCII grid ("DSAA") of ``dg`` (mGal), coordinates in the CRS's unit (metres).

    Header ``DSAA / nx ny / xlo xhi / ylo yhi / zlo zhi``, then ny rows of nx
    values from south to north; blanks (NaN) as 1.70141e38.  A Surfer file
    holds one variable: if ``dg_std`` is given it goes to ``<stem>_std<suffix>``
    beside ``path``.  The format has no place for the CRS, so the node coordinates are
    written in the unit of the projected CRS the pipeline uses (``easting_km`` × 1000: metres
    for UTM), which is how Surfer, QGIS and GDAL expect them; ``crs`` is not stored.
    """
    path = Path(path)
    e, n = to_crs_units(easting_km), to_crs_units(northing_km)
    text = surfer_text(e, n, dg)
    text_std = None
    if dg_std is not None and np.any(np.isfinite(dg_std)):
        text_std = surfer_text(e, n, dg_std)
    _write_text(path, text)
    if text_std is not None:
        _write_text(path.with_name(f"{path.stem}_std{path.suffix}"), text_std)
    return path


def grid_to_frame(easting_km, northing_km, dg, dg_std=None):
    """Long table ``easting_km, northing_km, dg_mgal, dg_std_mgal``, south-to-north rows."""
    import pandas as pd

    e, n, g, s = _check_grid(easting_km, northing_km, dg, dg_std)
    E, N = np.meshgrid(e, n)
    return pd.DataFrame({"easting_km": E.ravel(), "northing_km": N.ravel(), "dg_mgal": g.ravel(),
                         "dg_std_mgal": (s if s is not None else np.full_like(g, np.nan)).ravel()})


def write_grid_csv(path, easting_km, northing_km, dg, dg_std=None, crs=None) -> Path:
    """CSV with one row per node: ``easting_km, northing_km, dg_mgal, dg_std_mgal``.

    Masked nodes are written with empty values.  ``crs`` is not stored.
    """
    return write_csv(grid_to_frame(easting_km, northing_km, dg, dg_std), path)


# --------------------------------------------------------------------------- line data

#: lines.parquet columns → Geosoft XYZ channel names (Oasis montaj style), in file order
XYZ_LINE_CHANNELS = {"x": "X", "y": "Y", "time": "TIME", "lat": "LAT", "lon": "LON", "h": "HGT",
                     "z_mgal": "Z_MGAL", "dg_mgal": "DG", "dg_std_mgal": "DG_STD",
                     "dg_unleveled_mgal": "DG_UNLEV", "dg_stationary_mgal": "DG_STAT", "dg_fir_mgal": "DG_FIR",
                     "state": "STATE", "Q_mgal2": "Q_MGAL2", "R_cm2s2": "R_CM2S2",
                     # geophysical products (app.pipeline.stages.products), when present
                     "atm_corr_mgal": "ATM_CORR", "dg_flight_mgal": "DG_FLIGHT", "dg_flight_std_mgal": "DG_FLIGHT_STD",
                     "dg_datum_mgal": "DG_DATUM", "dg_datum_std_mgal": "DG_DATUM_STD", "datum_height_m": "DATUM_HGT",
                     "terrain_mgal": "TERRAIN", "terrain_height_m": "TERRAIN_HGT", "dg_bouguer_mgal": "DG_BOUGUER"}


def write_lines_xyz(path, lines, crs=None, comments: tuple[str, ...] = ()) -> Path:
    """Line data (a ``lines.parquet`` frame) as a Geosoft XYZ file, atomically.

    One block per survey line in time order, headed ``Line <id>`` (main and repeat lines) or
    ``Tie <id>``; channels ``X``, ``Y`` (the projected coordinates in the CRS's unit: metres for
    UTM), ``TIME``, ``LAT``, ``LON``, ``HGT``, then the anomalies in mGal (``DG`` is the final
    estimate), ``STATE``, ``Q_MGAL2``, ``R_CM2S2`` and the products ``ATM_CORR``, ``DG_FLIGHT``,
    ``DG_FLIGHT_STD``, ``DG_DATUM``, ``DG_DATUM_STD``, ``DATUM_HGT`` (m), ``TERRAIN``, ``TERRAIN_HGT`` (m),
    ``DG_BOUGUER`` (those present in ``lines``); missing values ``*``.  ``app.io.xyz.scan_xyz`` reads it back (the survey readers do not take it as a
    flight: it holds no gravimeter record).
    """
    from app.io.xyz import write_xyz

    df = lines.copy()
    df["line"] = df["line"].astype(str)
    df["x"] = to_crs_units(df["easting_km"])
    df["y"] = to_crs_units(df["northing_km"])
    order = df.groupby("line", sort=False)["time"].transform("min")
    df = df.assign(_t0=order).sort_values(["_t0", "line", "time"], kind="stable").reset_index(drop=True)
    names = {c: XYZ_LINE_CHANNELS[c] for c in XYZ_LINE_CHANNELS if c in df.columns}
    segments = []
    start = 0
    ids = df["line"].to_numpy()
    kinds = df["kind"].astype(str).to_numpy() if "kind" in df else np.full(len(df), "main")
    for i in range(1, len(df) + 1):
        if i == len(df) or ids[i] != ids[start]:
            segments.append(("tie" if kinds[start] == "tie" else "line", ids[start], start, i))
            start = i
    head = list(comments)
    if crs is not None:
        unit, _ = crs_unit(crs)
        hgt = ", ".join(v for k, v in names.items() if k in ("h", "datum_height_m", "terrain_height_m")) or "HGT"
        head.append(f"X, Y: {_crs(crs).to_string()} ({unit}); anomalies mGal; TIME s; {hgt} m")
    return atomic_write(path, lambda tmp: write_xyz(tmp, df, names, segments, comments=tuple(head)))


# --------------------------------------------------------------------------- tables

def write_csv(df, path) -> Path:
    """``df.to_csv(index=False)``, atomically."""
    return atomic_write(path, lambda tmp: df.to_csv(tmp, index=False))


def write_parquet(df, path) -> Path:
    """``df.to_parquet(index=False)`` (pyarrow), atomically."""
    return atomic_write(path, lambda tmp: df.to_parquet(tmp, index=False, engine="pyarrow"))


def write_json(obj, path, indent: int | None = 2) -> Path:
    """JSON (numpy-aware, NaN → null, strict), atomically."""
    def _w(tmp):
        with open(tmp, "w", encoding="utf-8") as f:
            for chunk in encoder(indent).iterencode(finite_tree(obj)):
                f.write(chunk)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
    return atomic_write(path, _w)
