"""Exports of grids and tables (SPEC §5): netCDF, GeoTIFF, Surfer, CSV, Parquet, JSON.

Grid layout everywhere: ``easting_km`` shape (nx,), ``northing_km`` shape (ny,),
both increasing and uniformly spaced for raster formats, values shape (ny, nx)
with row 0 at the southernmost northing; the coordinates are the node (cell
centre) positions in km of the projected CRS; masked nodes are NaN.

Every writer is atomic: it writes to a temporary file in the destination
directory and renames it over the destination with :func:`os.replace`, so a
failure half-way leaves any previous file intact and no partial file behind.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import json
import math
import os
import uuid
from pathlib import Path

import numpy as np

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


def write_grid_netcdf(path, easting_km, northing_km, dg, dg_std, crs, attrs: dict | None = None) -> Path:
    """CF-1.8 netCDF grid: variables ``dg``, ``dg_std`` (mGal) on ``northing_km``, ``easting_km``.

    Coordinates carry ``units = "km"`` and ``standard_name =
    projection_x_coordinate / projection_y_coordinate``; a scalar ``crs``
    grid-mapping variable carries the CF projection attributes from pyproj
    plus ``crs_wkt`` and ``spatial_ref`` (the WKT); the data variables name it
    in ``grid_mapping``.  Missing nodes are NaN (``_FillValue`` NaN).

    Parameters
    ----------
    path : str or Path
    easting_km : ndarray, shape (nx,)
    northing_km : ndarray, shape (ny,)
    dg, dg_std : ndarray, shape (ny, nx)
        Anomaly and its std (mGal); ``dg_std`` may be None.
    crs : str or pyproj.CRS
        Projected CRS of the coordinates.
    attrs : dict, optional
        Extra global attributes.
    """
    import xarray as xr

    e, n, g, s = _check_grid(easting_km, northing_km, dg, dg_std)
    c = _crs(crs)
    wkt = c.to_wkt()
    crs_attrs = {k: v for k, v in c.to_cf().items() if v is not None}
    crs_attrs.update(crs_wkt=wkt, spatial_ref=wkt)
    crs_attrs = {k: (json.dumps(v) if isinstance(v, (dict, list)) else v) for k, v in crs_attrs.items()}
    data_vars = {
        "dg": (("northing_km", "easting_km"), g, {
            "units": "mGal", "long_name": "gravity anomaly (free-air disturbance) at flight height",
            "grid_mapping": "crs"}),
        "crs": ((), np.int32(0), crs_attrs),
    }
    if s is not None:
        data_vars["dg_std"] = (("northing_km", "easting_km"), s, {
            "units": "mGal", "long_name": "standard deviation of dg", "grid_mapping": "crs"})
    ds = xr.Dataset(
        data_vars,
        coords={
            "easting_km": ("easting_km", e, {"units": "km", "standard_name": "projection_x_coordinate",
                                              "long_name": "easting", "axis": "X"}),
            "northing_km": ("northing_km", n, {"units": "km", "standard_name": "projection_y_coordinate",
                                                "long_name": "northing", "axis": "Y"}),
        },
        attrs={"Conventions": "CF-1.8", "title": "Aerograv anomaly grid", "crs": c.to_string(),
               **(attrs or {})},
    )
    enc = {v: {"_FillValue": np.nan, "dtype": "float64"} for v in ("dg", "dg_std") if v in ds}
    enc["easting_km"] = {"_FillValue": None}
    enc["northing_km"] = {"_FillValue": None}
    return atomic_write(path, lambda tmp: ds.to_netcdf(tmp, engine="netcdf4", encoding=enc))


def write_grid_geotiff(path, easting_km, northing_km, dg, dg_std, crs) -> Path:
    """GeoTIFF with 2 float32 bands (1: dg, 2: dg_std, mGal), nodata NaN.

    North-up: row 0 is the northernmost row; the affine transform is in metres
    of ``crs`` with the node coordinates at pixel centres.  ``dg_std`` None
    writes a band of NaN.
    """
    import rasterio
    from rasterio.crs import CRS as RioCRS
    from affine import Affine

    e, n, g, s = _check_grid(easting_km, northing_km, dg, dg_std, uniform=True)
    if s is None:
        s = np.full_like(g, np.nan)
    c = _crs(crs)
    dx_m = (e[-1] - e[0]) / (e.size - 1) * 1000.0
    dy_m = (n[-1] - n[0]) / (n.size - 1) * 1000.0
    transform = Affine(dx_m, 0.0, e[0] * 1000.0 - dx_m / 2, 0.0, -dy_m, n[-1] * 1000.0 + dy_m / 2)
    profile = dict(driver="GTiff", width=e.size, height=n.size, count=2, dtype="float32",
                   crs=RioCRS.from_wkt(c.to_wkt()), transform=transform, nodata=np.nan)

    def _write(tmp):
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(g[::-1].astype(np.float32), 1)
            dst.write(s[::-1].astype(np.float32), 2)
            dst.set_band_description(1, "dg_mgal")
            dst.set_band_description(2, "dg_std_mgal")
            dst.update_tags(units="mGal")

    return atomic_write(path, _write)


def surfer_text(easting_km, northing_km, values) -> str:
    """Surfer 6 ASCII grid text ("DSAA"), blanks 1.70141e38, rows south to north."""
    e, n, g, _ = _check_grid(easting_km, northing_km, values)
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
    """Surfer 6 ASCII grid ("DSAA") of ``dg`` (mGal), coordinates in km.

    Header ``DSAA / nx ny / xlo xhi / ylo yhi / zlo zhi``, then ny rows of nx
    values from south to north; blanks (NaN) as 1.70141e38.  A Surfer file
    holds one variable: if ``dg_std`` is given it goes to ``<stem>_std<suffix>``
    beside ``path``.  ``crs`` is not stored (the format has no place for it).
    """
    path = Path(path)
    text = surfer_text(easting_km, northing_km, dg)
    text_std = None
    if dg_std is not None and np.any(np.isfinite(dg_std)):
        text_std = surfer_text(easting_km, northing_km, dg_std)
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


# --------------------------------------------------------------------------- tables

def write_csv(df, path) -> Path:
    """``df.to_csv(index=False)``, atomically."""
    return atomic_write(path, lambda tmp: df.to_csv(tmp, index=False))


def write_parquet(df, path) -> Path:
    """``df.to_parquet(index=False)`` (pyarrow), atomically."""
    return atomic_write(path, lambda tmp: df.to_parquet(tmp, index=False, engine="pyarrow"))


def to_jsonable(obj):
    """Convert numpy/pandas/dataclass/Path values into plain JSON types.

    Non-finite floats become ``None`` (JSON has no NaN).  Raises TypeError for
    anything else it cannot convert.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, np.integer)) and not isinstance(obj, np.bool_):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return [to_jsonable(v) for v in obj.tolist()] if obj.ndim else to_jsonable(obj.item())
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (_dt.datetime, _dt.date)):
        return obj.isoformat()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    try:
        import pandas as pd

        if isinstance(obj, pd.DataFrame):
            return to_jsonable(obj.to_dict(orient="records"))
        if isinstance(obj, pd.Series):
            return to_jsonable(obj.tolist())
        if isinstance(obj, pd.Timestamp):
            return obj.isoformat()
    except ImportError:  # pragma: no cover
        pass
    if hasattr(obj, "model_dump"):  # pydantic
        return to_jsonable(obj.model_dump())
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def write_json(obj, path, indent: int | None = 2) -> Path:
    """JSON (numpy-aware, NaN → null, strict), atomically."""
    def _w(tmp):
        with open(tmp, "w", encoding="utf-8") as f:
            for chunk in json.JSONEncoder(indent=indent, allow_nan=False, ensure_ascii=False,
                                          default=to_jsonable).iterencode(_prefilter(obj)):
                f.write(chunk)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
    return atomic_write(path, _w)


def _prefilter(obj):
    """Replace non-finite floats (which ``default`` never sees) by None, lazily."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k if isinstance(k, str) else str(k): _prefilter(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_prefilter(v) for v in obj]
    return obj
