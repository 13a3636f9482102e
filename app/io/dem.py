"""DEM (terrain model) reader and writer: a GeoTIFF (GDAL's GTiff driver only) in any CRS,
reprojected and resampled onto a regular grid in the survey's projected CRS.

``read_dem(path, crs, bounds_m=None, spacing_m=None, ...) -> app.core.terrain.Dem``

* the raster's CRS is required (``InputError`` column ``crs`` otherwise); the target CRS is the
  survey's (``survey.toml`` ``[survey] crs``, or the UTM zone the reader chose);
* band 1 holds heights in metres; the raster's nodata value and non-finite values become NaN;
* the target grid: ``bounds_m = (west, east, south, north)`` in the target CRS (metres), enlarged
  by ``margin_m`` (give the lines' extent and the terrain radius), or the raster's own footprint;
  ``spacing_m`` or, by default, the raster's resolution at its centre (metres); cell centres on
  multiples of the spacing;
* resampling ``"bilinear"`` (default), ``"cubic"``, ``"nearest"`` or ``"average"`` (use it when
  the target spacing is much coarser than the raster) through ``rasterio.warp.reproject``;
* ``height_offset_m`` is added to every height (e.g. a mean geoid undulation, to bring an
  orthometric DEM to the ellipsoidal heights of the GNSS);
* ``require_bounds_m``: an area (the survey lines' extent) that must be fully covered: a cell
  without data there is an ``InputError`` naming the raster pixel (row = 1-based pixel row,
  column ``band 1``, and the pixel column and target coordinates in the message).

Errors are ``app.io.errors.InputError(file, row, column, message)``: unreadable file, no CRS,
no bands, heights outside −12 000 … 9 000 m (the first offending pixel), a target grid over
``MAX_DEM_CELLS``, no overlap with the requested bounds, missing data under the survey.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import rasterio
import rasterio.windows
from pyproj import Transformer
from rasterio.crs import CRS
from rasterio.errors import RasterioIOError
from rasterio.transform import from_origin
from rasterio.warp import Resampling, calculate_default_transform, reproject, transform_bounds

from app.core.terrain import Dem
from app.io.errors import InputError

#: largest target grid (cells); 25 million float64 cells = 200 MB
MAX_DEM_CELLS = 25_000_000
HEIGHT_RANGE_M = (-12000.0, 9000.0)
_RESAMPLING = ("bilinear", "cubic", "nearest", "average")


def _display(path, display):
    return display if display is not None else str(path)


#: The first bytes of a TIFF or BigTIFF file, either byte order.
_TIFF_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


def _open_raster(path, name: str):
    """The GeoTIFF at ``path`` opened with rasterio's GTiff driver only; an :class:`InputError`
    naming the file when it is not a TIFF or GDAL cannot read it.

    Only GeoTIFF: GDAL would otherwise open any of its formats, and some of them are references,
    not data — a VRT (a few lines of XML) named ``dem.tif`` can point at any raster on the
    machine or at a URL (``/vsicurl/``), so a survey uploaded to the server could make it read
    its own files or fetch from its network.  A GeoTIFF's only side files are its own overviews
    and masks, beside it."""
    try:
        with open(Path(path), "rb") as fh:
            head = fh.read(4)
    except OSError as exc:
        raise InputError(name, None, None, f"cannot read the file: {exc}") from None
    if head not in _TIFF_MAGIC:
        raise InputError(name, None, None, "not a GeoTIFF (the file does not start as a TIFF does); convert the "
                                           "terrain model to GeoTIFF, e.g. gdal_translate -of GTiff")
    try:
        return rasterio.open(Path(path), driver="GTiff")
    except (RasterioIOError, OSError) as exc:
        raise InputError(name, None, None, f"not a GeoTIFF GDAL can read: {exc}") from None


def read_dem(path, crs: str, bounds_m=None, spacing_m: float | None = None, margin_m: float = 0.0,
             resampling: str = "bilinear", height_offset_m: float = 0.0, require_bounds_m=None,
             display: str | None = None) -> Dem:
    """Read a DEM raster and resample it to the survey's projected CRS (module docstring).

    Returns
    -------
    app.core.terrain.Dem
        Cell-centre axes (m, increasing), heights (ny, nx) in metres, NaN without data;
        ``info`` = source CRS, size and resolution, target spacing, resampling, offset,
        fraction of cells with data.
    """
    name = _display(path, display)
    if resampling not in _RESAMPLING:
        raise InputError(name, None, "resampling", f"resampling must be one of {', '.join(_RESAMPLING)}, "
                                                   f"not {resampling!r}")
    dst_crs = _target_crs(crs, name)
    src = _open_raster(path, name)
    with src:
        data = _read_heights(src, name)
        grid = _target_grid(src, dst_crs, crs, bounds_m, spacing_m, margin_m, name)
        x, y, spacing_m = grid.x, grid.y, grid.spacing_m
        dst = np.full((y.size, x.size), np.nan)
        dst_tr = from_origin(x[0] - spacing_m / 2, y[-1] + spacing_m / 2, spacing_m, spacing_m)
        src_nan = np.where(np.isfinite(data), data, np.nan)
        reproject(source=src_nan, destination=dst, src_transform=src.transform, src_crs=src.crs,
                  src_nodata=np.nan, dst_transform=dst_tr, dst_crs=dst_crs, dst_nodata=np.nan,
                  resampling=getattr(Resampling, resampling))
        heights = dst[::-1] + float(height_offset_m)       # north-up rows → increasing northing
        info = {"source_crs": src.crs.to_string(), "source_shape": [src.height, src.width],
                "source_resolution": [abs(src.transform.a), abs(src.transform.e)],
                "spacing_m": spacing_m, "resampling": resampling, "height_offset_m": float(height_offset_m),
                "valid_fraction": float(np.isfinite(heights).mean()), "file": name}
        if require_bounds_m is not None:
            _check_coverage(src, dst_crs, crs, x, y, heights, spacing_m, require_bounds_m, name)
    return Dem(x, y, heights, crs=str(crs), info=info)


def _target_crs(crs: str, name: str) -> CRS:
    """The survey's CRS, which must be projected (metres)."""
    try:
        dst_crs = CRS.from_user_input(crs)
    except Exception as exc:  # noqa: BLE001 - pyproj/rasterio raise several types
        raise InputError(name, None, "crs", f"unknown target CRS {crs!r}: {exc}") from None
    if not dst_crs.is_projected:
        raise InputError(name, None, "crs", f"the target CRS {crs!r} is not projected (metres needed)")
    return dst_crs


def _read_heights(src, name: str) -> np.ndarray:
    """Band 1 in metres, nodata and non-finite values as NaN; the raster must have a CRS, some
    data and heights within ``HEIGHT_RANGE_M`` (the first offending pixel is named)."""
    if src.count < 1:
        raise InputError(name, None, "band 1", "the raster has no bands")
    if src.crs is None:
        raise InputError(name, None, "crs", "the DEM has no coordinate reference system; "
                                            "write one into the GeoTIFF (e.g. gdal_edit.py -a_srs)")
    data = src.read(1, masked=True).astype(float).filled(np.nan)
    data[~np.isfinite(data)] = np.nan
    bad = np.isfinite(data) & ((data < HEIGHT_RANGE_M[0]) | (data > HEIGHT_RANGE_M[1]))
    if bad.any():
        r, c = (int(v) for v in np.argwhere(bad)[0])
        raise InputError(name, r + 1, "band 1",
                         f"height {data[r, c]:.6g} m at pixel row {r + 1}, column {c + 1} is outside "
                         f"{HEIGHT_RANGE_M[0]:g} … {HEIGHT_RANGE_M[1]:g} m (heights must be metres)")
    if not np.isfinite(data).any():
        raise InputError(name, None, "band 1", "the DEM holds no data (every pixel is nodata)")
    return data


class _TargetGrid(NamedTuple):
    """Cell-centre axes of the target grid (m, on multiples of the spacing) and the spacing."""

    x: np.ndarray
    y: np.ndarray
    spacing_m: float


def _target_grid(src, dst_crs, crs: str, bounds_m, spacing_m: float | None, margin_m: float,
                 name: str) -> _TargetGrid:
    """The target grid: ``bounds_m`` (or the raster's footprint less half a cell) plus
    ``margin_m``, ``spacing_m`` (or the raster's resolution at its centre); it must overlap the
    raster and have between 2 × 2 and ``MAX_DEM_CELLS`` cells."""
    src_bounds = transform_bounds(src.crs, dst_crs, *src.bounds, densify_pts=21)  # (w, s, e, n)
    if spacing_m is None:
        tr, _, _ = calculate_default_transform(src.crs, dst_crs, src.width, src.height, *src.bounds)
        spacing_m = float(np.sqrt(abs(tr.a * tr.e)))
    spacing_m = float(spacing_m)
    if not np.isfinite(spacing_m) or spacing_m <= 0:
        raise InputError(name, None, "spacing_m", f"DEM spacing must be a positive number of metres, "
                                                  f"not {spacing_m}")
    if bounds_m is None:
        # the footprint less half a cell: cell centres of an aligned raster stay where they are
        w, s_, e, n = (src_bounds[0] + spacing_m / 2, src_bounds[1] + spacing_m / 2,
                       src_bounds[2] - spacing_m / 2, src_bounds[3] - spacing_m / 2)
    else:
        w, e, s_, n = (float(v) for v in bounds_m)
    w, e, s_, n = w - margin_m, e + margin_m, s_ - margin_m, n + margin_m
    # overlap with the raster's footprint
    if e <= src_bounds[0] or w >= src_bounds[2] or n <= src_bounds[1] or s_ >= src_bounds[3]:
        raise InputError(name, None, None,
                         f"the DEM (covering {src_bounds[0]:.0f}…{src_bounds[2]:.0f} E, "
                         f"{src_bounds[1]:.0f}…{src_bounds[3]:.0f} N in {crs}) does not overlap the "
                         f"survey area {w:.0f}…{e:.0f} E, {s_:.0f}…{n:.0f} N")
    # cell centres on multiples of the spacing
    x = np.arange(np.floor(w / spacing_m), np.ceil(e / spacing_m) + 1) * spacing_m
    y = np.arange(np.floor(s_ / spacing_m), np.ceil(n / spacing_m) + 1) * spacing_m
    if x.size * y.size > MAX_DEM_CELLS:
        raise InputError(name, None, "spacing_m",
                         f"the DEM grid would have {x.size} × {y.size} cells (> {MAX_DEM_CELLS:,}); "
                         f"choose a coarser spacing than {spacing_m:g} m or a smaller area")
    if x.size < 2 or y.size < 2:
        raise InputError(name, None, "spacing_m", f"spacing {spacing_m:g} m leaves fewer than 2 × 2 cells")
    return _TargetGrid(x, y, spacing_m)


def _check_coverage(src, dst_crs, crs: str, x, y, heights, spacing_m: float, require_bounds_m, name: str) -> None:
    """Every cell within one spacing of ``require_bounds_m`` has a height; the first hole is
    named by its raster pixel and target coordinates."""
    rw, re_, rs, rn = (float(v) for v in require_bounds_m)
    X, Y = np.meshgrid(x, y)
    inside = (X >= rw - spacing_m) & (X <= re_ + spacing_m) & (Y >= rs - spacing_m) & (Y <= rn + spacing_m)
    hole = inside & ~np.isfinite(heights)
    if not hole.any():
        return
    j, i = (int(v) for v in np.argwhere(hole)[0])
    xs, ys = Transformer.from_crs(dst_crs, src.crs, always_xy=True).transform(x[i], y[j])
    col, row = ~src.transform @ (xs, ys)
    row_i, col_i = int(np.floor(row)), int(np.floor(col))
    where = (f"pixel row {row_i + 1}, column {col_i + 1}"
             if 0 <= row_i < src.height and 0 <= col_i < src.width else "outside the raster")
    raise InputError(name, row_i + 1 if 0 <= row_i < src.height else None, "band 1",
                     f"no terrain height under the survey at {x[i]:.0f} E, {y[j]:.0f} N "
                     f"({crs}; {where}); {int(hole.sum())} cells of the survey area lack data")


def check_dem(path, crs: str, require_bounds_m=None, max_cells: int = MAX_DEM_CELLS,
              display: str | None = None) -> dict:
    """Validate a DEM as it arrives (an upload), cheaply and in bounded memory: a GeoTIFF GDAL reads,
    with a CRS and at least one band, at most ``max_cells`` pixels, band 1 read in blocks of rows with
    some data and every height within ``HEIGHT_RANGE_M`` (the first offending pixel named, as
    :func:`read_dem` does), and a footprint (in ``crs``) that contains ``require_bounds_m = (west,
    east, south, north)`` (m; the survey lines' extent).  Holes inside the footprint are left to
    :func:`read_dem`'s coverage check at processing time.

    Returns the raster's description: ``source_crs``, ``shape`` [rows, columns], ``resolution``,
    ``footprint_m`` (west, east, south, north in ``crs``), ``valid_fraction``, ``height_range_m``.
    Raises ``InputError(display, row, column, message)``."""
    name = _display(path, display)
    dst_crs = _target_crs(crs, name)
    src = _open_raster(path, name)
    with src:
        if src.count < 1:
            raise InputError(name, None, "band 1", "the raster has no bands")
        if src.crs is None:
            raise InputError(name, None, "crs", "the DEM has no coordinate reference system; "
                                                "write one into the GeoTIFF (e.g. gdal_edit.py -a_srs)")
        if src.width * src.height > max_cells:
            raise InputError(name, None, None, f"the DEM has {src.height} × {src.width} pixels (> {max_cells:,}); "
                                               "crop it to the survey area plus the terrain radius or resample it")
        n_valid, lo, hi = 0, np.inf, -np.inf
        step = max(1, (1 << 22) // max(1, src.width))          # ~4 M pixels per read
        try:
            for r0 in range(0, src.height, step):
                win = rasterio.windows.Window(0, r0, src.width, min(step, src.height - r0))
                data = src.read(1, window=win, masked=True).astype(float).filled(np.nan)
                data[~np.isfinite(data)] = np.nan
                bad = np.isfinite(data) & ((data < HEIGHT_RANGE_M[0]) | (data > HEIGHT_RANGE_M[1]))
                if bad.any():
                    r, c = (int(v) for v in np.argwhere(bad)[0])
                    raise InputError(name, r0 + r + 1, "band 1",
                                     f"height {data[r, c]:.6g} m at pixel row {r0 + r + 1}, column {c + 1} is outside "
                                     f"{HEIGHT_RANGE_M[0]:g} … {HEIGHT_RANGE_M[1]:g} m (heights must be metres)")
                ok = np.isfinite(data)
                if ok.any():
                    n_valid += int(ok.sum())
                    lo, hi = min(lo, float(data[ok].min())), max(hi, float(data[ok].max()))
        except RasterioIOError as exc:
            raise InputError(name, None, "band 1", f"the raster's data cannot be read (damaged file?): {exc}") from None
        if n_valid == 0:
            raise InputError(name, None, "band 1", "the DEM holds no data (every pixel is nodata)")
        try:
            w, s_, e, n = transform_bounds(src.crs, dst_crs, *src.bounds, densify_pts=21)
        except Exception as exc:  # noqa: BLE001 - PROJ errors come in several types
            raise InputError(name, None, "crs", f"the DEM's CRS cannot be transformed to {crs}: {exc}") from None
        if require_bounds_m is not None:
            rw, re_, rs, rn = (float(v) for v in require_bounds_m)
            if rw < w or re_ > e or rs < s_ or rn > n:
                raise InputError(name, None, None,
                                 f"the DEM (covering {w:.0f}…{e:.0f} E, {s_:.0f}…{n:.0f} N in {crs}) does not cover "
                                 f"the survey lines ({rw:.0f}…{re_:.0f} E, {rs:.0f}…{rn:.0f} N)")
        return {"source_crs": src.crs.to_string(), "shape": [src.height, src.width],
                "resolution": [abs(src.transform.a), abs(src.transform.e)],
                "footprint_m": [float(w), float(e), float(s_), float(n)],
                "valid_fraction": n_valid / float(src.width * src.height), "height_range_m": [lo, hi]}


def write_dem(path, dem: Dem, dtype: str = "float32", nodata: float = -32768.0) -> Path:
    """Write a :class:`~app.core.terrain.Dem` as a single-band GeoTIFF (north-up, its CRS,
    NaN → ``nodata``).  Written to a temporary name and renamed (atomic)."""
    path = Path(path)
    dx, dy = dem.spacing_m
    w, _, _, n = dem.bounds_m
    tr = from_origin(w, n, dx, dy)
    arr = dem.height_m[::-1].astype(dtype)
    arr = np.where(np.isfinite(arr), arr, nodata).astype(dtype)
    tmp = path.with_name(f".{path.name}.partial")
    with rasterio.open(tmp, "w", driver="GTiff", width=arr.shape[1], height=arr.shape[0], count=1,
                       dtype=dtype, crs=dem.crs, transform=tr, nodata=nodata, compress="deflate") as dst:
        dst.write(arr, 1)
    os.replace(tmp, path)
    return path
