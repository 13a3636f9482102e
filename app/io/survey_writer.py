"""Write a survey directory (SPEC §4) and the simulator's ``truth/`` folder.

Everything is written into a temporary sibling directory which is renamed into
place at the end, so a reader never sees a half-written survey.  An existing
directory at the destination is replaced only after the new one is complete.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

#: decimals written per column (resolution well below the simulated noise)
GRAV_DECIMALS = {"time": 3, "f_z": 8, "f_x": 4, "f_y": 4}
GNSS_DECIMALS = {"time": 3, "lat": 8, "lon": 8, "h": 3, "vu": 5, "ve": 3, "vn": 3, "sigma_v": 4}
GRAV_COLUMNS = ["time", "f_z", "f_x", "f_y"]
GNSS_COLUMNS = ["time", "lat", "lon", "h", "vu", "ve", "vn", "sigma_v"]
#: heights-only GNSS (no velocity): what a receiver without Doppler velocities delivers
GNSS_HEIGHTS_ONLY_COLUMNS = ["time", "lat", "lon", "h"]
LINES_COLUMNS = ["line", "flight", "t_start", "t_end", "kind", "track"]


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if not math.isfinite(v):
            raise ValueError("TOML cannot hold non-finite floats")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dumps_toml(doc: dict) -> str:
    """Minimal TOML writer for ``{table: {key: scalar | list | {subtable}}}`` documents (a nested
    dict is written as ``[table.sub]`` after the table's own keys); None values are left out."""
    out: list[str] = []

    def key(k: str) -> str:
        k = str(k)
        return k if k.replace("_", "").replace("-", "").isalnum() and k.isascii() else json.dumps(k)

    def table(path: list[str], body: dict) -> None:
        out.append("[" + ".".join(key(p) for p in path) + "]")
        for k, v in body.items():
            if v is None or isinstance(v, dict):
                continue
            out.append(f"{key(k)} = {_toml_value(v)}")
        out.append("")
        for k, v in body.items():
            if isinstance(v, dict):
                table(path + [k], v)

    for name, body in doc.items():
        table([name], body)
    return "\n".join(out)


def _round(df: pd.DataFrame, decimals: dict) -> pd.DataFrame:
    df = df.copy()
    for c, d in decimals.items():
        if c in df:
            df[c] = np.round(df[c].to_numpy(dtype=float), d)
    return df


def _columns(df: pd.DataFrame, wanted, spec: list[str], flight: str, what: str) -> list[str]:
    if wanted is None:
        return [c for c in spec if c in df]
    missing = [c for c in wanted if c not in df]
    if missing:
        raise ValueError(f"flight {flight}: {what} frame lacks column(s) {', '.join(missing)}")
    return list(wanted)


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_survey(out_dir, survey_toml: dict, lines: pd.DataFrame, flights: dict,
                 truth_lines: pd.DataFrame | None = None, truth_grid=None,
                 truth_json: dict | None = None, compress: bool = False,
                 gravimeter_columns=None, gnss_columns=None, dem=None) -> Path:
    """Write a complete survey directory atomically.

    Parameters
    ----------
    out_dir : path
        Destination directory (replaced if it exists).
    survey_toml : dict
        ``{"survey": {...}, "gravimeter": {...}, "processing": {...}}``.
    lines : DataFrame
        Columns ``line, flight, t_start, t_end, kind, track``.
    flights : dict
        ``{flight_name: (gravimeter_df, gnss_df)}`` with SPEC §4 columns
        (gravimeter ``time, f_z, f_x, f_y``; GNSS ``time, lat, lon, h, vu, ve, vn, sigma_v``).
    truth_lines, truth_grid, truth_json
        Written to ``truth/lines.parquet``, ``truth/grid.nc`` (xarray Dataset),
        ``truth/truth.json`` when given.
    compress : bool
        Write ``gravimeter.csv.gz`` / ``gnss.csv.gz``.
    gravimeter_columns, gnss_columns : list of str, optional
        The columns to write, in this order (e.g. :data:`GNSS_HEIGHTS_ONLY_COLUMNS` for a GNSS
        file without velocities); every listed column must be in each frame (``ValueError``
        otherwise).  Default: the SPEC §4 columns present in each frame.
    dem : app.core.terrain.Dem, optional
        Written as ``dem.tif`` (GeoTIFF, float32, the DEM's CRS) in the survey directory.

    Returns
    -------
    Path
        The destination directory.
    """
    out = Path(out_dir).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        os.chmod(tmp, 0o755)
        (tmp / "survey.toml").write_text(dumps_toml(survey_toml), encoding="utf-8")
        lc = lines.copy()
        if "track" not in lc:
            lc["track"] = None
        lc = lc[LINES_COLUMNS]
        lc.to_csv(tmp / "lines.csv", index=False, float_format="%.2f")
        if dem is not None:
            from app.io.dem import write_dem
            write_dem(tmp / "dem.tif", dem)
        ext = ".csv.gz" if compress else ".csv"
        comp = {"method": "gzip", "compresslevel": 6, "mtime": 0} if compress else None
        for name, (grav, gnss) in flights.items():
            d = tmp / "flights" / name
            d.mkdir(parents=True)
            g = _round(grav[_columns(grav, gravimeter_columns, GRAV_COLUMNS, name, "gravimeter")], GRAV_DECIMALS)
            g.to_csv(d / f"gravimeter{ext}", index=False, compression=comp)
            n = _round(gnss[_columns(gnss, gnss_columns, GNSS_COLUMNS, name, "gnss")], GNSS_DECIMALS)
            n.to_csv(d / f"gnss{ext}", index=False, compression=comp)
        if truth_lines is not None or truth_grid is not None or truth_json is not None:
            td = tmp / "truth"
            td.mkdir()
            if truth_lines is not None:
                truth_lines.to_parquet(td / "lines.parquet", index=False, compression="zstd",
                                       compression_level=9)
            if truth_grid is not None:
                enc = {v: {"zlib": True, "complevel": 4} for v in truth_grid.data_vars}
                truth_grid.to_netcdf(td / "grid.nc", engine="netcdf4", encoding=enc)
            if truth_json is not None:
                (td / "truth.json").write_text(json.dumps(truth_json, indent=1, default=_json_default),
                                               encoding="utf-8")
        old = None
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.replace(out, old / "x")
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
