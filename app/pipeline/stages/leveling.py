"""Stage 10, leveling (SPEC §3): crossovers of main and tie lines, one drift polynomial per
flight fitted to them, applied only when an F-test says the crossovers support it and
without moving the map's mean level (the crossovers cannot see it); the crossovers also
check the lines' posterior std.  Without an absolute base tie the leveled map's common level
is as uncertain as the flights' offsets say (:func:`add_common_level_std`, after gridding).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pandas as pd
from scipy.stats import f as f_dist

from app.core.accuracy import REPEAT_MAX_SPREAD_KM, across_track_spread_km, crossover_std_factor, repeat_line_accuracy
from app.core.leveling import (
    LineTrack,
    common_level_std,
    connected_groups,
    cross_validated_leveling,
    find_crossovers,
    keep_mean_level,
    level_lines,
)
from app.core.repeat_leveling import drift_p_value, fit_repeat_levels

#: Per-epoch lower bound of ``dg_std_mgal`` that stage 9 sets on lines that do not resolve the
#: anomaly (:func:`app.pipeline.stages.choice.check_lines`); :func:`level_survey` applies it
#: after the crossover check of the std and drops the column.
STD_FLOOR = "dg_std_floor_mgal"


def tracks(table: pd.DataFrame, col: str):
    """One :class:`app.core.leveling.LineTrack` per line of the table, carrying column ``col``."""
    tracks = {}
    for line, g in table.groupby("line", sort=False):
        tracks[str(line)] = LineTrack(g["easting_km"].to_numpy(), g["northing_km"].to_numpy(),
                                      g["time"].to_numpy(), g[col].to_numpy(), g["dg_std_mgal"].to_numpy(),
                                      str(g["kind"].iloc[0]))
    return tracks


class _TestedDrift(NamedTuple):
    """A drift polynomial fitted to the crossovers and tested: the fit, the crossover differences
    before and after it (mGal), which are finite, their predicted variance (mGal²), the report
    entries, and why it is refused (None: accepted)."""

    res: object
    before: np.ndarray
    after: np.ndarray
    ok: np.ndarray
    pred_var: np.ndarray
    rep: dict
    reason: str | None


def _tested_drift(cx: pd.DataFrame, ranges: dict, groups: dict | None, degree: int, p, tied: bool) -> _TestedDrift:
    """Fit a drift of ``degree`` per unit (flight, or line without ``groups``) to the crossovers
    and test it: an F-test against no correction, then the leave-one-line-out check (at
    ``leveling_cv_significance``, or ``leveling_cv_significance_untied`` where a flight has no
    absolute base tie).  Raises ValueError when the drift cannot be fitted."""
    res = level_lines(cx, ranges, degree=degree, groups=groups)
    before = (cx["dg_a"] - cx["dg_b"]).to_numpy(float)
    after = np.asarray(res.diff_after, float)
    # Is the drift model supported by the crossovers at all?  F-test of the drift
    # parameters against "no correction": after base ties the crossover differences are
    # mostly the lines' own errors, and fitting them only adds noise to the lines.
    ok = np.isfinite(before) & np.isfinite(after)
    pred_var = (cx["std_a"] ** 2 + cx["std_b"] ** 2).to_numpy(float)
    lines_x = set(cx["line_a"].astype(str)) | set(cx["line_b"].astype(str))
    units = {groups[l] for l in lines_x} if groups else lines_x
    k = max(1, (len(units) - 1) * (degree + 1))
    n = int(ok.sum())
    ssr0 = float(np.sum(before[ok] ** 2))
    ssr1 = float(np.sum(after[ok] ** 2))
    p_value = 0.0
    if n > k + 1 and ssr1 > 0:
        F = ((ssr0 - ssr1) / k) / (ssr1 / (n - k))
        p_value = float(f_dist.sf(F, k, n - k))
    rep = {"degree": degree, "per_flight": bool(p.leveling_per_flight), "n_crossovers": int(len(cx)),
           "rms_before_mgal": float(res.rms_before), "n_drift_parameters": k, "p_value": p_value}
    reason = None
    if p_value > p.leveling_significance:
        reason = ("the drift model is not significant at the crossovers "
                  f"(F-test p = {p_value:.3g} > {p.leveling_significance})")
    elif p.leveling_cross_validate:
        # crossover errors are correlated along lines: the F-test can call smoothing errors a
        # drift; the drift must also predict the crossovers of lines left out of its fit
        cv = cross_validated_leveling(cx, ranges, degree=degree, groups=groups)
        sig = p.leveling_cv_significance if tied else p.leveling_cv_significance_untied
        rep["cross_validation"] = {**cv, "significance": sig, "absolute_base_tie": bool(tied)}
        if not (cv["rms_cv_mgal"] < cv["rms_before_mgal"] and cv["p_value"] < sig):
            reason = (f"the drift does not predict held-out lines' crossovers significantly (leave-one-line-out "
                      f"RMS {cv['rms_cv_mgal']:.3g} mGal against {cv['rms_before_mgal']:.3g} without leveling, "
                      f"p = {cv['p_value']:.3g}, needs < {sig}"
                      + ("" if tied else ": a flight without an absolute base tie keeps its reading offset") + ")")
    return _TestedDrift(res, before, after, ok, pred_var, rep, reason)


def _drift_or_offsets(cx: pd.DataFrame, ranges: dict, groups: dict | None, p, tied: bool) -> _TestedDrift:
    """The drift of ``leveling_degree``; where it is refused, one offset per unit (degree 0)
    under the same tests (``leveling_offset_fallback``), which has half the parameters: the
    refused drift's evidence stays in the report (``refused_drift``)."""
    drift = _tested_drift(cx, ranges, groups, p.leveling_degree, p, tied)
    if drift.reason is None or p.leveling_degree == 0 or not p.leveling_offset_fallback:
        return drift
    offsets = _tested_drift(cx, ranges, groups, 0, p, tied)
    if offsets.reason is not None:
        return drift
    offsets.rep["refused_drift"] = {**{k: drift.rep[k] for k in ("degree", "n_drift_parameters", "p_value")},
                                    **({"cross_validation": drift.rep["cross_validation"]}
                                       if "cross_validation" in drift.rep else {}),
                                    "status": f"not leveled: {drift.reason}"}
    return offsets


def level_lines_table(table: pd.DataFrame, p, warnings: list, tied: bool = True,
                      tied_flights=None) -> tuple[pd.DataFrame, dict]:
    """Crossovers and leveling; on failure keep the unleveled estimate and say why.

    ``tied``: every flight was tied to an absolute base reading (stage 1), which removed its
    reading offset.  Where one was not, that flight keeps its own offset, so the flights
    differ in level for certain: the held-out check of the drift is then at
    ``leveling_cv_significance_untied`` instead of ``leveling_cv_significance``.  A drift
    refused is followed by one offset per flight under the same tests
    (:func:`_drift_or_offsets`).  ``tied_flights``: the flights with an absolute tie; where
    only some are, leveling keeps their mean level (not the map's) and the report's
    ``untied_flights`` says where each other flight's level came from."""
    cols = ["line_a", "line_b", "easting_km", "northing_km", "diff_before_mgal", "diff_after_mgal"]
    try:
        cx = find_crossovers(tracks(table, "dg_unleveled_mgal"), include_repeat=p.leveling_include_repeat)
    except ValueError as exc:
        warnings.append(f"crossovers: {exc}")
        return pd.DataFrame(columns=cols), {"status": f"not leveled: {exc}"}
    if len(cx) == 0:
        warnings.append("no crossovers between lines: leveling skipped")
        rep = {"status": "not leveled: no crossovers"}
        if p.leveling_repeat_tracks:
            rep["repeat_tracks"] = level_repeat_tracks(table, p, warnings, tied, tied_flights)
        return pd.DataFrame(columns=cols), rep
    heights = crossover_heights(table, cx, p.leveling_max_height_difference_m, warnings)
    ranges = {str(l): (float(g["time"].min()), float(g["time"].max()))
              for l, g in table.groupby("line", sort=False)}
    try:
        groups = None
        if p.leveling_per_flight:
            groups = flight_of_line(table)
        fit = _drift_or_offsets(cx, ranges, groups, p, tied)
    except ValueError as exc:
        warnings.append(f"leveling: {exc}")
        cx = cx.assign(diff_before_mgal=cx["dg_a"] - cx["dg_b"], diff_after_mgal=cx["dg_a"] - cx["dg_b"])
        return cx[cols], {"status": f"not leveled: {exc}"}
    res, before, after, rep = fit.res, fit.before, fit.after, fit.rep
    if heights is not None:
        rep["height_difference_m"] = heights
    corr, removed, unit, pairs = _corrections(table, cx, res, fit.ok, tied_flights)
    untied = untied_flights_report(table, unit, pairs, tied_flights, fit.reason is None, warnings)
    if untied is not None:
        rep["untied_flights"] = untied
    if fit.reason is not None:
        rep.update(status=f"not leveled: {fit.reason}",
                   rms_after_mgal=float(res.rms_before), rms_after_if_leveled_mgal=float(res.rms_after))
        # what the refused drift would have subtracted, per drift unit (a flight), on average:
        # evidence for the analyst, not a warning — on simulated surveys with base ties the
        # refused drifts reach 2–7 mGal from the crossovers' own correlated errors (unseen 1664:
        # 6.9), as large as the real flight offsets the generator without base ties leaves (4–5)
        rep["if_leveled_mean_correction_mgal"] = _mean_by_unit(corr, unit)
        keep = _not_lone(table, cx, untied)
        rep["std_check"] = std_check(before[keep], fit.pred_var[keep], p)
        cx = cx.assign(diff_before_mgal=before, diff_after_mgal=before)
        return cx[cols], rep
    table["dg_mgal"] = table["dg_unleveled_mgal"].to_numpy() - corr
    cx = cx.assign(diff_before_mgal=before, diff_after_mgal=after)
    rep.update(status="leveled", rms_after_mgal=float(res.rms_after), mean_level_removed_mgal=removed)
    common = common_level_std([res.unit_of.get(str(a), str(a)) for a in cx["line_a"]],
                              [res.unit_of.get(str(b), str(b)) for b in cx["line_b"]], before)
    if common is not None:
        rep["common_level"] = {"std_mgal": common.std_mgal, "spread_mgal": common.spread_mgal,
                               "offsets_mgal": common.offsets_mgal, "n_units": common.n_units,
                               "n_crossovers": common.n_crossovers}
    keep = _not_lone(table, cx, untied)
    rep["std_check"] = std_check(after[keep], fit.pred_var[keep], p)
    return cx[cols], rep


def _repeat_passes(table: pd.DataFrame) -> dict:
    """``{track: [pass rows, …]}`` of the table's repeat tracks with two passes or more (each
    pass a line's rows in time order)."""
    if "track" not in table or not (table["kind"] == "repeat").any():
        return {}
    rep = table[table["kind"] == "repeat"]
    out = {}
    for track, g in rep.groupby("track", sort=False):
        passes = [gg.sort_values("time") for _, gg in g.groupby("line", sort=False)]
        if len(passes) >= 2:
            out[str(track)] = passes
    return out


def _pass_levels(passes: list, p, alpha: float):
    """Fit and test the passes' offsets and drifts (:func:`app.core.repeat_leveling.fit_repeat_levels`)
    on ``dg_unleveled_mgal`` at their common points: blocks of ``leveling_repeat_block_s`` at the
    passes' median ground speed, weighted by the inverse of the passes' variance
    (``dg_std_mgal``): one offset per pass, with each flight's drift of ``leveling_degree``
    where it explains the differences beyond the offsets (partial F-test p below
    ``leveling_repeat_drift_significance``); the whole tested against no correction at
    ``leveling_repeat_significance`` (a drift refused there, the offsets alone,
    ``leveling_offset_fallback``).  Returns (fit, block_km, reason, the drift's p or None):
    reason None = accepted.  Raises ValueError when the passes have no common stretch, no
    ground speed or too few blocks."""
    geo = [(g["easting_km"].to_numpy(float), g["northing_km"].to_numpy(float)) for g in passes]
    dg = [g["dg_unleveled_mgal"].to_numpy(float) for g in passes]
    tm = [np.where(np.isfinite(d), g["time"].to_numpy(float), np.nan) for g, d in zip(passes, dg)]
    step_km = 0.1
    sd = [np.where(np.isfinite(d), g["dg_std_mgal"].to_numpy(float), np.nan) for g, d in zip(passes, dg)]

    def common(cols):
        return np.asarray(repeat_line_accuracy([(e, n, c) for (e, n), c in zip(geo, cols)], step_km=step_km).values_mgal)

    vals, times, std = common(dg), common(tm), common(sd)
    if std.shape != vals.shape or not np.all(np.isfinite(std) & (std > 0)):
        std = None   # a std missing where the estimate is not: equal weights
    speeds = []
    for (e, n), g in zip(geo, passes):
        dt = np.diff(g["time"].to_numpy(float))
        ds = np.hypot(np.diff(e), np.diff(n))
        ok = (dt > 0) & np.isfinite(ds)
        if ok.any():
            speeds.append(np.median(ds[ok] / dt[ok]))
    block_km = float(p.leveling_repeat_block_s * np.median(speeds)) if speeds else float("nan")
    if not np.isfinite(block_km) or block_km <= 0:
        raise ValueError("the passes' ground speed is unknown")
    block = max(1, int(round(block_km / step_km)))
    flights = [str(g["flight"].iloc[0]) for g in passes]
    offsets = fit_repeat_levels(vals, times, flights, degree=0, block=block, std_mgal=std)
    fit, drift_p = offsets, None
    try:
        drifted = (fit_repeat_levels(vals, times, flights, degree=p.leveling_degree, block=block, std_mgal=std)
                   if p.leveling_degree > 0 else None)
    except ValueError:   # too few blocks for the drift's parameters: the offsets alone
        drifted = None
    if drifted is not None:
        drift_p = drift_p_value(offsets, drifted)
        # the drift only where the passes show it beyond their offsets: a drift they can hardly
        # tell from their offsets (passes flown one way) would be fitted to their errors
        if drift_p is not None and drift_p < p.leveling_repeat_drift_significance:
            fit = drifted
        if fit.p_value > alpha and fit is drifted and p.leveling_offset_fallback and offsets.p_value <= alpha:
            fit = offsets
    reason = None if fit.p_value <= alpha else (
        f"the passes' offsets and drift are not significant (F-test p = {fit.p_value:.3g} > {alpha})")
    return fit, block * step_km, reason, drift_p


def level_repeat_tracks(table: pd.DataFrame, p, warnings: list, tied: bool = False, tied_flights=None) -> dict:
    """A survey without crossovers: level each repeat track's passes against each other (in
    place, ``dg_mgal`` = ``dg_unleveled_mgal`` − the pass's correction where accepted).

    The passes' differences from their mean at common points show each pass's offset (a tare,
    its flight's reading offset) and, where they can show it, each flight's drift in time
    (:func:`_pass_levels`).  Applied where the F-test on their block means has p ≤
    ``leveling_repeat_significance_untied`` (default 1: always, the p reported) when a flight
    of the passes has no absolute base tie (``tied``, ``tied_flights`` as in
    :func:`level_lines_table`), ≤ ``leveling_repeat_significance`` (0.05) when all are tied;
    corrections above three times the passes' largest difference are refused.  The passes'
    mean level is kept (without a base tie it stays the gravimeter's reading offset).  Left
    alone: tracks whose passes lie more than ``REPEAT_MAX_SPREAD_KM`` apart across the track,
    or whose median heights differ by more than ``leveling_max_height_difference_m`` (the
    anomaly differs between them) unless the values were continued to a datum.  Returns the
    report's ``crossovers.repeat_tracks``: per track the passes, status, whether tied, the
    F-tests, the fitted offsets and drifts, each pass's mean correction (what was subtracted on
    average) and the block length."""
    out = {}
    for track, passes in _repeat_passes(table).items():
        names = [str(g["line"].iloc[0]) for g in passes]
        entry = {"passes": names}
        out[track] = entry
        spread = across_track_spread_km([g["easting_km"].to_numpy(float) for g in passes],
                                        [g["northing_km"].to_numpy(float) for g in passes])
        heights = [float(np.median(h[np.isfinite(h)])) for h in (g["h"].to_numpy(float) for g in passes)
                   if np.isfinite(h).any()] if "h" in table else []
        if spread > REPEAT_MAX_SPREAD_KM:
            entry["status"] = f"not leveled: the passes lie {spread:.2f} km apart across the track"
            continue
        if heights and "dg_flight_mgal" not in table and max(heights) - min(heights) > p.leveling_max_height_difference_m:
            entry["status"] = (f"not leveled: the passes were flown {max(heights) - min(heights):.0f} m apart in height "
                               "(the anomaly differs between them)")
            continue
        flights = {str(g["flight"].iloc[0]) for g in passes}
        track_tied = tied or (tied_flights is not None and flights <= {str(f) for f in tied_flights})
        alpha = p.leveling_repeat_significance if track_tied else p.leveling_repeat_significance_untied
        entry["absolute_base_tie"] = bool(track_tied)
        try:
            fit, block_km, reason, drift_p = _pass_levels(passes, p, alpha)
        except ValueError as exc:
            entry["status"] = f"not leveled: {exc}"
            continue
        entry.update(degree=int(fit.drift_mgal.shape[1]), p_value=fit.p_value, drift_p_value=drift_p, block_km=block_km,
                     n_blocks=fit.n_blocks, n_parameters=fit.n_parameters,
                     rms_before_mgal=fit.rms_before_mgal, rms_after_mgal=fit.rms_after_mgal,
                     offsets_mgal=dict(zip(names, map(float, fit.offsets_mgal))),
                     drift_mgal_per_h={str(g["flight"].iloc[0]): [float(b) for b in fit.drift_mgal[fit.flight_of_pass[k]]]
                                       for k, g in enumerate(passes)})
        if reason is not None:
            entry["status"] = f"not leveled: {reason}"
            continue
        corrs = [fit.correction(k, g["time"].to_numpy(float)) for k, g in enumerate(passes)]
        largest = max(float(np.nanmax(np.abs(c))) for c in corrs)
        if largest > 3.0 * fit.max_difference_mgal + 0.1:
            # a correction can only take out what the passes' differences show
            entry["status"] = (f"not leveled: its corrections (up to {largest:.3g} mGal) exceed what the passes' "
                               f"differences show (up to {fit.max_difference_mgal:.3g} mGal)")
            warnings.append(f"repeat track {track}: its passes were not leveled against each other — "
                            + entry["status"][len("not leveled: "):])
            continue
        means = {}
        for k, (g, corr) in enumerate(zip(passes, corrs)):
            table.loc[g.index, "dg_mgal"] = g["dg_unleveled_mgal"].to_numpy(float) - corr
            means[names[k]] = float(np.mean(corr))
        entry.update(status="leveled", mean_correction_mgal=means)
        lo, hi = min(means.values()), max(means.values())
        drift = ", ".join(f"{b:+.2f}" for b in fit.drift_mgal.ravel())
        warnings.append(f"repeat track {track}: no crossovers, so its {len(passes)} passes were leveled against each "
                        f"other (mean corrections {lo:+.2f} to {hi:+.2f} mGal" + (f", drift {drift} mGal/h" if drift else "")
                        + f"; F-test p = {fit.p_value:.2g}, their differences {fit.rms_before_mgal:.2f} → "
                        f"{fit.rms_after_mgal:.2f} mGal RMS over {block_km:.1f} km blocks); their mean level is kept")
    return out


def flight_of_line(table: pd.DataFrame) -> dict[str, str]:
    """``{line: flight}`` of the line table (each line is flown in one flight)."""
    return {str(ln): str(g["flight"].iloc[0]) for ln, g in table.groupby("line", sort=False)}


def _not_lone(table: pd.DataFrame, cx: pd.DataFrame, untied: dict | None) -> np.ndarray:
    """Crossovers the std check may use, shape (n,) bool: not those of an untied flight leveling
    left unconnected (``untied`` maps it to None) — their difference holds that flight's
    reading offset, not the lines' errors the std is about."""
    lone = {f for f, src in (untied or {}).items() if src is None}
    if not lone:
        return np.ones(len(cx), bool)
    flight_of = flight_of_line(table)
    a = np.array([flight_of.get(str(x)) in lone for x in cx["line_a"]], bool)
    b = np.array([flight_of.get(str(x)) in lone for x in cx["line_b"]], bool)
    return ~(a | b)


def _corrections(table: pd.DataFrame, cx: pd.DataFrame, res, ok: np.ndarray, tied_flights=None):
    """The drift corrections of ``res`` at every epoch of the table (mGal, subtracted from dg),
    with each connected group's mean level kept (the crossovers see differences only) — the
    mean over its flights in ``tied_flights`` where it has any (:func:`keep_mean_level`) —,
    the constants removed, every epoch's drift unit and the crossing unit pairs."""
    corr = np.zeros(len(table))
    for line, g in table.groupby("line", sort=False):
        corr[g.index.to_numpy()] = res.correction(str(line), g["time"].to_numpy())
    unit = table["line"].astype(str).map(lambda ln: res.unit_of.get(ln, ln)).to_numpy(object)
    pairs = [(res.unit_of.get(a, a), res.unit_of.get(b, b))
             for a, b, ok_k in zip(cx["line_a"].astype(str), cx["line_b"].astype(str), ok) if ok_k]
    anchor = None if not tied_flights else table["flight"].astype(str).isin(list(tied_flights)).to_numpy()
    corr, removed = keep_mean_level(corr, unit, pairs, anchor)
    return corr, removed, unit, pairs


def crossover_heights(table: pd.DataFrame, cx: pd.DataFrame, max_difference_m: float, warnings: list) -> dict | None:
    """How far apart in height the two lines of each crossover were flown (m; the report's
    ``crossovers.height_difference_m``: median and largest), with a warning beyond
    ``max_difference_m``: at flight height the anomaly itself differs with height (its vertical
    gradient; a 10 km anomaly of 20 mGal changes by ~4 mGal over 300 m), which the crossovers
    show and leveling takes for drift — unless the map was continued to a common datum first
    (``dg_flight_mgal`` present: the crossovers are then at the datum).  None without heights."""
    if "h" not in table or "dg_flight_mgal" in table or not len(cx):
        return None
    h_at = {}
    for line, g in table.groupby("line", sort=False):
        h_at[str(line)] = (g["time"].to_numpy(float), g["h"].to_numpy(float))
    diff = []
    for a, b, ta, tb in zip(cx["line_a"].astype(str), cx["line_b"].astype(str), cx["time_a"], cx["time_b"]):
        if a in h_at and b in h_at:
            diff.append(abs(np.interp(ta, *h_at[a]) - np.interp(tb, *h_at[b])))
    d = np.asarray(diff, float)
    d = d[np.isfinite(d)]
    if not d.size:
        return None
    out = {"median_m": float(np.median(d)), "max_m": float(np.max(d)), "n_over": int(np.sum(d > max_difference_m)),
           "limit_m": float(max_difference_m)}
    if out["n_over"]:
        warnings.append(f"{out['n_over']} of {d.size} crossovers compare lines flown up to {out['max_m']:.0f} m apart in "
                        f"height (median {out['median_m']:.0f} m): the anomaly itself differs with height there, "
                        "which leveling takes for drift — continue the lines to a common datum first "
                        "(processing.datum = 'constant' or 'draped')")
    return out


def untied_flights_report(table: pd.DataFrame, unit: np.ndarray, pairs: list, tied_flights, leveled: bool,
                          warnings: list) -> dict | None:
    """Where some flights are tied to an absolute base reading and others are not: for each
    untied flight, the tied flights its level was taken from through the crossovers (leveling
    applied and connecting them), or None — then its level carries the gravimeter's reading
    error, and a warning says so.  None when every flight or none is tied."""
    flights = table["flight"].astype(str).to_numpy()
    names = list(pd.unique(flights))
    tied = [f for f in names if f in set(tied_flights or ())]
    if not tied or len(tied) == len(names):
        return None
    roots = connected_groups(pairs) if leveled else {}
    root_of_flight: dict = {}
    for f, u in zip(flights, unit):
        if u in roots:
            root_of_flight.setdefault(f, set()).add(roots[u])
    out = {}
    for f in names:
        if f in tied:
            continue
        mine = root_of_flight.get(f, set())
        src = sorted(t for t in tied if mine & root_of_flight.get(t, set()))
        out[f] = src or None
        if src:
            warnings.append(f"flight {f} has no absolute base tie: its level was taken from its crossovers with "
                            f"the tied flight(s) {', '.join(src)}")
        else:
            warnings.append(f"flight {f} has no absolute base tie and leveling does not connect it to a tied "
                            "flight: its level carries the gravimeter's reading error (scale × g, easily 100+ mGal)")
    return out


def _mean_by_unit(corr: np.ndarray, unit: np.ndarray) -> dict:
    """Mean correction (mGal) over each drift unit's epochs."""
    return {str(u): float(np.mean(corr[unit == u])) for u in pd.unique(unit)}


def std_check(diff_mgal, pred_var_mgal2, p) -> dict:
    """Crossover differences against the lines' posterior std: an independent check of
    ``dg_std_mgal``."""
    return crossover_std_factor(diff_mgal, pred_var_mgal2, p.std_crossover_shared_fraction,
                                p.std_crossover_min_n, p.std_crossover_min_factor,
                                min_n=p.std_crossover_min_n_widen)


@dataclass
class Leveled:
    """Result of :func:`level_survey`: the crossover table (SPEC §5 ``crossovers.csv``) and
    the report's ``crossovers`` section (status, F-test, RMS before/after, std check)."""

    crossovers: pd.DataFrame
    report: dict


def reading_error_std_mgal(base_ties: dict) -> float | None:
    """The size of the gravimeter's reading error as the absolute base ties measured it (mGal):
    the RMS over every static period of every flight tied to a known base gravity; None when
    no flight is so tied.  A flight without such a tie keeps an error of about that size."""
    errs = [per["reading_error_mgal"] for b in base_ties.values() if b.get("applied") and b.get("absolute")
            for per in b.get("static_periods", []) if np.isfinite(per.get("reading_error_mgal", np.nan))]
    return float(np.sqrt(np.mean(np.square(errs)))) if errs else None


def widen_unconnected_flights(table: pd.DataFrame, rep: dict, level_std_mgal: float | None, warnings: list) -> None:
    """An untied flight that leveling did not connect to a tied one (``rep["untied_flights"]``
    maps it to None) keeps its gravimeter reading error: add ``level_std_mgal`` (the tied flights'
    reading error, :func:`reading_error_std_mgal`) to its epochs' ``dg_std_mgal`` in quadrature
    (in place; report ``untied_level_std_mgal``)."""
    lone = [f for f, src in (rep.get("untied_flights") or {}).items() if src is None]
    if not lone or level_std_mgal is None:
        return
    sel = table["flight"].astype(str).isin(lone).to_numpy()
    table.loc[sel, "dg_std_mgal"] = np.sqrt(table.loc[sel, "dg_std_mgal"].to_numpy(float) ** 2 + level_std_mgal ** 2)
    rep["untied_level_std_mgal"] = {f: level_std_mgal for f in lone}
    warnings.append(f"dg_std_mgal of flight(s) {', '.join(lone)} includes their unknown reading error, taken as the "
                    f"size the tied flights' base readings showed: {level_std_mgal:.1f} mGal")


def level_survey(table: pd.DataFrame, p, warnings: list, tied: bool = True, tied_flights=None,
                 reading_error_mgal: float | None = None) -> Leveled:
    """Stage 10 on the line table (in place: ``dg_mgal`` leveled, ``dg_std_mgal`` rescaled by
    the crossover check of the std); ``tied`` and ``tied_flights`` as in
    :func:`level_lines_table`; ``reading_error_mgal`` (:func:`reading_error_std_mgal`) is added
    to the std of an untied flight leveling leaves unconnected."""
    crossovers, rep = level_lines_table(table, p, warnings, tied, tied_flights)
    sc = rep.get("std_check", {})
    if p.std_crossover_check and "factor" in sc and sc["factor"] != 1.0:
        # The crossovers are an independent check of dg_std (core.accuracy.crossover_std_factor).
        # Model misfit shows up in both directions: coloured GNSS noise the model does not see
        # (std too small), an anomaly smoother than the random-walk model (too large).
        table["dg_std_mgal"] = table["dg_std_mgal"] * sc["factor"]
        sc["applied_factor"] = sc["factor"]
    if STD_FLOOR in table:  # stage 9's floor on lines that do not resolve the anomaly
        table["dg_std_mgal"] = np.fmax(table["dg_std_mgal"].to_numpy(), table.pop(STD_FLOOR).to_numpy())
    widen_unconnected_flights(table, rep, reading_error_mgal, warnings)
    return Leveled(crossovers, rep)


#: the std columns the common level's std is added to (besides the grids')
_STD_COLUMNS = ("dg_std_mgal", "dg_flight_std_mgal", "dg_datum_std_mgal")


def add_common_level_std(table: pd.DataFrame, grids, report: dict, tied: bool, p, warnings: list) -> None:
    """Where leveling fixed the flights relative to each other and no absolute base tie fixes
    their common level (``tied`` False), add that level's std (the report's
    ``crossovers.common_level``, :func:`app.core.leveling.common_level_std`) to every epoch's
    std and every grid's, in quadrature (in place; ``std_common_level``).  After gridding: the
    level is one number for the whole map, so it must not weigh the lines against each other
    there.  The report's ``common_level`` says whether it was applied."""
    common = report.get("common_level")
    if common is None:
        return
    if not p.std_common_level or tied:
        common["applied"] = False
        common["reason"] = "off" if not p.std_common_level else "an absolute base tie fixes the level"
        return
    var = float(common["std_mgal"]) ** 2
    common["applied"] = True
    if not var > 0:
        return
    for col in _STD_COLUMNS:
        if col in table:
            table[col] = np.sqrt(table[col].to_numpy(float) ** 2 + var)
    for g in grids:
        if g is not None:
            g.dg_std_mgal = np.sqrt(np.asarray(g.dg_std_mgal, float) ** 2 + var)
    warnings.append(f"no absolute base tie: leveling fixed the {common['n_units']} flights relative to each other "
                    f"(their offsets spread by {common['spread_mgal']:.2f} mGal at the crossovers), and their common "
                    f"level is uncertain by about {common['std_mgal']:.2f} mGal; dg_std_mgal and the grid std include it")
