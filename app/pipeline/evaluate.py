"""Score processed outputs against a simulated survey's ``truth/`` (the simulator's contract).

Used by the tests, the benchmarks and ``aerograv evaluate``; never by processing itself.
Metrics: RMS vs truth of the adaptive, stationary and FIR estimates per terrain class
(first and last ``edge_km`` of each line excluded), std calibration (fraction of epochs
with |error| < 2σ), recognition accuracy (raw and smoothed), grid RMS inside the lines'
convex hull and the grid std calibration.  The accuracy figures are those of
:mod:`app.core.accuracy`; a selection without finite values reads NaN.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd

from app.core import accuracy

ESTIMATES = ("dg_mgal", "dg_unleveled_mgal", "dg_stationary_mgal", "dg_fir_mgal")


def _along_km(g: pd.DataFrame) -> np.ndarray:
    de = np.diff(g["easting_km"].to_numpy())
    dn = np.diff(g["northing_km"].to_numpy())
    return np.concatenate([[0.0], np.cumsum(np.hypot(de, dn))])


def merge_truth(lines: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Join processed epochs with truth epochs by line and time (nearest, 1 ms)."""
    out = []
    truth = truth.copy()
    truth["line"] = truth["line"].astype(str)
    lines = lines.copy()
    lines["line"] = lines["line"].astype(str)
    for line, g in lines.groupby("line", sort=False):
        t = truth[truth["line"] == line].sort_values("time")
        if t.empty:
            continue
        m = pd.merge_asof(g.sort_values("time"), t.drop(columns=[c for c in ("line", "flight", "kind", "easting_km",
                                                                             "northing_km") if c in t]),
                          on="time", direction="nearest", tolerance=1e-3)
        m["along_km"] = _along_km(m)
        out.append(m)
    return pd.concat(out, ignore_index=True)


def _has_pairs(est, true, where=None) -> bool:
    """Whether the selection holds a point where both the estimate and the truth are finite (the
    accuracy functions raise otherwise; evaluate reports NaN)."""
    ok = np.isfinite(np.asarray(est, float)) & np.isfinite(np.asarray(true, float))
    return bool((ok if where is None else ok & np.asarray(where, bool)).any())


def _rms_or_nan(est, true, *, line=None, where=None) -> float:
    """:func:`app.core.accuracy.rms_vs_reference`, NaN when the selection has no finite pair."""
    if not _has_pairs(est, true, where):
        return float("nan")
    return accuracy.rms_vs_reference(est, true, line=line, where=where)


def line_accuracy(lines: pd.DataFrame, truth: pd.DataFrame, edge_km: float = 10.0) -> dict:
    """RMS vs truth per terrain for each estimate, and std calibration (:mod:`app.core.accuracy`)."""
    m = merge_truth(lines, truth)
    L = m.groupby("line")["along_km"].transform("max")
    core = m[(m["along_km"] >= edge_km) & (m["along_km"] <= L - edge_km) & m["dg_true_mgal"].notna()]
    res: dict = {"epochs": int(len(core))}
    true = core["dg_true_mgal"].to_numpy(float)
    line = core["line"].to_numpy()
    for col in ESTIMATES:
        if col not in core:
            continue
        est = core[col].to_numpy(float)
        d = {"all": _rms_or_nan(est, true),
             # the same with each line's mean error removed (what leveling/base ties cannot see)
             "all_line_demeaned": _rms_or_nan(est, true, line=line)}
        for terr in ("mountain", "plain"):
            sel = (core["terrain"] == terr).to_numpy()
            if sel.any():
                d[terr] = _rms_or_nan(est, true, where=sel)
                d[f"{terr}_line_demeaned"] = _rms_or_nan(est, true, line=line, where=sel)
        res[col] = d
    std = core["dg_std_mgal"].to_numpy(float)
    for col in ("dg_mgal", "dg_unleveled_mgal"):
        err = core[col].to_numpy(float) - true
        res[f"std_calibration_{col}"] = (accuracy.std_calibration(err, std, 2.0) if _has_pairs(err, std)
                                         else float("nan"))
    dg = core["dg_mgal"].to_numpy(float)
    res["bias_dg_mgal"] = accuracy.mean_error_vs_reference(dg, true) if _has_pairs(dg, true) else float("nan")
    return res


def recognition_accuracy(rec: pd.DataFrame, truth: pd.DataFrame, n_r: int = 1) -> dict:
    """Fraction of decimated points whose anomaly-intensity class is right.

    The truth class is ``state_true // n_r`` mapped to 0 (smooth) / 1 (rough)."""
    tr = truth.copy()
    tr["line"] = tr["line"].astype(str)
    rec = rec.copy()
    rec["line"] = rec["line"].astype(str)
    parts = []
    for line, g in rec.groupby("line", sort=False):
        t = tr[tr["line"] == line].sort_values("time")
        if t.empty:
            continue
        parts.append(pd.merge_asof(g.sort_values("time"), t[["time", "state_true"]], on="time",
                                   direction="nearest", tolerance=1.0))
    m = pd.concat(parts, ignore_index=True).dropna(subset=["state_true"])
    truth_cls = (m["state_true"].astype(int) // 1).to_numpy()
    out = {"points": int(len(m))}
    for col in ("state_raw", "state_smoothed"):
        cls = (m[col].to_numpy() // n_r)
        cls = (cls > 0).astype(int) if truth_cls.max() <= 1 else cls
        out[col] = float(np.mean(cls == truth_cls))
    return out


def grid_accuracy(out_dir: Path, truth_dir: Path) -> dict:
    """Grid RMS and std calibration inside the lines' convex hull
    (:func:`app.core.accuracy.grid_accuracy_in_hull`) against the true grid interpolated to the
    nodes: ``{cells, rms_mgal, rms_demeaned_mgal, std_calibration}`` (None figures without cells)."""
    import xarray as xr
    from scipy.interpolate import RegularGridInterpolator

    with xr.open_dataset(out_dir / "grid.nc") as g, xr.open_dataset(truth_dir / "grid.nc") as t:
        e = g["easting_km"].values
        n = g["northing_km"].values
        dg = g["dg"].values
        std = g["dg_std"].values
        interp = RegularGridInterpolator((t["northing_km"].values, t["easting_km"].values), t["dg"].values,
                                         bounds_error=False, fill_value=np.nan)
    N, E = np.meshgrid(n, e, indexing="ij")
    true = interp(np.column_stack([N.ravel(), E.ravel()])).reshape(N.shape)
    lines = pd.read_parquet(out_dir / "lines.parquet", columns=["easting_km", "northing_km"])
    return dataclasses.asdict(accuracy.grid_accuracy_in_hull(e, n, dg, true, lines["easting_km"].to_numpy(),
                                                             lines["northing_km"].to_numpy(), std_mgal=std))


def evaluate(survey_dir, out_dir, edge_km: float = 10.0) -> dict:
    """All metrics for a processed simulated survey."""
    survey_dir, out_dir = Path(survey_dir), Path(out_dir)
    truth_dir = survey_dir / "truth"
    truth = pd.read_parquet(truth_dir / "lines.parquet")
    lines = pd.read_parquet(out_dir / "lines.parquet")
    ident = json.loads((out_dir / "identification.json").read_text())
    n_r = len({s["R"] for s in ident["states"]})
    res = {"lines": line_accuracy(lines, truth, edge_km)}
    res["recognition"] = recognition_accuracy(pd.read_parquet(out_dir / "recognition.parquet"), truth, n_r)
    if (out_dir / "grid.nc").exists() and (truth_dir / "grid.nc").exists():
        res["grid"] = grid_accuracy(out_dir, truth_dir)
    rep = json.loads((out_dir / "report.json").read_text())
    res["crossovers"] = rep.get("crossovers")
    res["repeat_lines"] = rep.get("repeat_lines")
    res["identification"] = rep.get("identification")
    tj = truth_dir / "truth.json"
    if tj.exists():
        res["truth"] = {k: v for k, v in json.loads(tj.read_text()).items()
                        if k in ("Q_true_mgal2", "R_true_cm2s2", "transition_empirical", "Q", "R", "transition")}
    return res
