"""Repeat tracks of a result for the browser: which lines are passes of one track, and every pass
on one along-track coordinate so that passes flown in opposite directions overlay.

The along-track coordinate of a track is the projection of its passes' positions (easting,
northing, km) on the track's principal direction (:func:`app.core.accuracy.track_axes`),
oriented so that the first pass in time flies towards increasing distance, with its origin at the smallest projection of any pass: every pass is on the same axis
from the same origin, and a pass flown the other way runs from the far end back to 0.
Presentation only: nothing here changes an estimate.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from app.core.accuracy import track_axes
from app.jsonsafe import finite_float, float_list

#: estimate key of report.json ``repeat_lines.<track>.internal_accuracy_mgal`` ← lines.parquet column
ESTIMATE_COLUMNS = {"dg_mgal": "dg_mgal", "dg_stationary_mgal": "dg_stationary_mgal", "dg_fir_mgal": "dg_fir_mgal"}


def track_members(lines: list[tuple[str, str, str | None]], report: dict, present: set[str]) -> dict[str, list[str]]:
    """``{track: [line, …]}`` of the repeat tracks with two or more passes in the result.

    ``lines``: (line, kind, track of lines.csv) of the survey; ``report``: report.json, whose
    ``repeat_tracks_inferred`` names the tracks the pipeline gave repeat lines without one;
    ``present``: the lines the result has.  Lines keep lines.csv's order."""
    out: dict[str, list[str]] = {}
    for line, kind, track in lines:
        if kind == "repeat" and track not in (None, "") and line in present:
            out.setdefault(str(track), []).append(line)
    inferred = report.get("repeat_tracks_inferred") if isinstance(report, dict) else None
    for track, members in (inferred or {}).items():
        if str(track) not in out and isinstance(members, list):
            out[str(track)] = [str(m) for m in members if str(m) in present]
    return {t: m for t, m in out.items() if len(m) >= 2}


def track_axis(passes: dict[str, pd.DataFrame]) -> dict[str, float]:
    """The along-track axis of a track's passes (each a lines.parquet group sorted by time):
    its origin (km), unit direction, azimuth (degrees clockwise from grid north) and length (km)."""
    es = [g["easting_km"].to_numpy(float) for g in passes.values()]
    ns = [g["northing_km"].to_numpy(float) for g in passes.values()]
    (ce, cn), (ue, un), _ = (tuple(float(x) for x in v) for v in track_axes(es, ns))
    e, n = np.concatenate(es), np.concatenate(ns)
    ok = np.isfinite(e) & np.isfinite(n)
    e, n = e[ok], n[ok]
    first = min(passes.values(), key=lambda g: float(g["time"].iloc[0]))
    fe, fn = first["easting_km"].to_numpy(float), first["northing_km"].to_numpy(float)
    fok = np.isfinite(fe) & np.isfinite(fn)
    if fok.sum() >= 2 and (fe[fok][-1] - fe[fok][0]) * ue + (fn[fok][-1] - fn[fok][0]) * un < 0:
        ue, un = -ue, -un
    s = (e - ce) * ue + (n - cn) * un
    s0 = float(s.min())
    return {"origin_easting_km": ce + s0 * ue, "origin_northing_km": cn + s0 * un, "unit_easting": ue,
            "unit_northing": un, "azimuth_deg": math.degrees(math.atan2(ue, un)) % 360.0,
            "length_km": float(s.max() - s0)}


def _pass(line: str, g: pd.DataFrame, axis: dict[str, float], max_points: int) -> dict[str, Any]:
    de = g["easting_km"].to_numpy(float) - axis["origin_easting_km"]
    dn = g["northing_km"].to_numpy(float) - axis["origin_northing_km"]
    along = de * axis["unit_easting"] + dn * axis["unit_northing"]
    across = -de * axis["unit_northing"] + dn * axis["unit_easting"]
    fin = np.isfinite(along)
    forward = bool(fin.sum() < 2 or along[fin][-1] >= along[fin][0])
    step = max(1, math.ceil(len(g) / max_points))
    sl = slice(None, None, step)

    def col(name: str) -> list | None:
        return float_list(g[name].to_numpy(float)[sl], 3) if name in g else None

    return {"line": line, "flight": str(g["flight"].iloc[0]) if "flight" in g else "",
            "direction": "forward" if forward else "reverse", "n_total": int(len(g)), "step": step,
            "t_start": finite_float(g["time"].iloc[0]), "t_end": finite_float(g["time"].iloc[-1]),
            "across_rms_m": finite_float(1000.0 * np.sqrt(np.nanmean(across ** 2))) if fin.any() else None,
            "time": float_list(g["time"].to_numpy(float)[sl], 2), "along_km": float_list(along[sl], 4),
            "dg": col("dg_mgal"), "dg_std": col("dg_std_mgal"), "dg_stationary": col("dg_stationary_mgal"),
            "dg_fir": col("dg_fir_mgal"),
            "sigma_mean_mgal": finite_float(np.nanmean(g["dg_std_mgal"])) if "dg_std_mgal" in g else None}


def track_passes(track: str, members: list[str], groups: dict[str, pd.DataFrame], report: dict,
                 max_points: int) -> dict[str, Any]:
    """Every pass of ``track`` on the track's axis (:func:`track_axis`), in time order, with the
    track's repeatability figures from report.json (``repeat_lines.<track>``, and the std check of
    ``level_refinement.std_repeat_tracks.<track>`` when there is one)."""
    passes = {ln: groups[ln] for ln in sorted(members, key=lambda x: float(groups[x]["time"].iloc[0]))}
    axis = track_axis(passes)
    return {"track": track, "axis": axis, "passes": [_pass(ln, g, axis, max_points) for ln, g in passes.items()],
            "repeatability": _section(report, "repeat_lines", track),
            "std_check": _section(report, "level_refinement", "std_repeat_tracks", track)}


def _section(report: dict, *keys: str) -> dict | None:
    """``report[k1][k2]…`` when every step is a dict, else None."""
    v: Any = report
    for k in keys:
        v = v.get(k) if isinstance(v, dict) else None
    return v if isinstance(v, dict) else None
