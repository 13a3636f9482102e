"""Stage 9, model choice: which estimate becomes ``dg_mgal``, decided from the data alone.

1. **Anomaly order.**  When ``processing.m`` is not set and the survey has at least
   ``choice_min_crossovers`` crossovers, the orders m = 1 and m = 2 are both identified and
   filtered; SPEC's default m = 2 is used unless m = 1's estimates agree significantly better
   at the crossovers (one-sided p < ``order_choice_p`` by a paired t-test on the squared
   differences or a signed-rank test on their magnitudes, as in step 4).  Two crossing lines' errors are
   nearly independent (different directions, flights, times), so the mean square crossover
   difference estimates the sum of the two lines' mean square errors — distortion included,
   which repeat passes cannot see — except the part of the error the two lines share: an
   estimate that misses an anomaly misses it on both lines at the crossing.  A small
   difference either way therefore says nothing about the error against the truth
   (omolon: m = 2 had the lower crossover RMS, 3.45 vs 3.51 mGal, p = 0.22, and the larger
   error against truth, 2.49 vs 2.34 mGal, when both used the full-rate refined levels).
   Without enough crossovers the SPEC default m = 2 is used.  Where m = 1 is not
   significantly better, the estimate is the blend ``w·(m = 1) + (1 − w)·(m = 2)`` whose
   crossover differences have the least mean square (``order_blend``;
   :func:`app.core.model_check.crossover_blend_weight`), on the differences less what a drift
   of the leveling model explains (:func:`app.core.leveling.drift_free_differences`: both
   orders carry the same flight offsets and drift, several mGal against their own errors of
   one, and left in they set the weight by chance): read as above, the combination of
   the two orders with the least unshared error — it takes what each order gets right (m = 1
   the sharp anomalies m = 2's smoother prior rounds off, m = 2 the noise m = 1 lets through)
   where the crossovers see it, and is m = 2 alone (w = 0) where they see no gain.  The
   levels, the state map and the std are m = 2's; the variance adds the blend's share of the
   two orders' difference, ``w(1 − w)·(m₁ − m₂)²`` (the law of total variance over the two
   orders with weights w, 1 − w, each order's own variance taken as m = 2's).
2. **Flattened lines.**  An estimate whose along-line variance is far below the anomaly
   variance the FIR 100 s estimate shows beyond its own noise
   (:func:`app.core.model_check.flattening_ratio` < ``flatten_min_ratio`` against the least
   anomaly variance FIR shows at 95 % over the line's ``2·B·T`` independent samples of its
   noise — a short line's FIR can carry far more noise than predicted by chance) failed to detect
   the anomaly: that line takes the stationary estimate, or FIR if that is flattened too or
   differs from FIR by more than FIR's own along-line std (step 3's disagreement test: on a
   line with a noise episode the stationary estimate, blind to the episode, had 66 mGal of
   error against FIR's 27).  On a pass of a repeat track the sister passes measure FIR's
   noise without a model (:func:`repeat_fir_noise_mgal2`); where that is significantly above
   the model's and the check fails against it, the verdict read noise as anomaly and the
   adaptive estimate stays (:func:`_repeats_veto`).  Where stage 8's crossover level check
   lowered the levels (noise in the anomaly band the model does not know), FIR's noise as FIR's
   own crossovers measure it plays that part on every line (:func:`fir_crossover_noise`).  Where FIR shows no anomaly beyond its noise the check cannot run;
   a line whose estimate also varies by less than its own posterior std is reported as not
   resolving the anomaly (``resolved``), and when that holds for at least half of the lines a
   warning says so — the estimate is then close to a smooth trend, right or flattened.  Such
   a line's std is widened to the error a smooth estimate can have: Var(FIR) − Var(estimate)
   (``std_unresolved_bound``; :func:`_bound_std`), and so is every line FIR cannot judge
   alone when the lines' median flattening ratio is below ``flatten_min_ratio`` (the survey
   flattened as a whole: :func:`_bound_flattened_survey`).
3. **Noisy estimate.**  The converse of step 2, survey-wide: when the lines' median ratio of
   the estimate's along-line variance to the anomaly variance FIR shows beyond its noise
   exceeds ``noisy_max_ratio`` (3), the estimate carries several times more variance than
   the anomaly has in FIR's band.  At flight height the anomaly has little variance at periods
   below 100 s, so the excess is noise the model let through (a level or a noise model gone
   wrong): every line takes FIR.  Over 59 simulated surveys (13 regimes × 2 seeds, three
   presets, 16 unseen and 14 random geometries) the median was 0.15–1.45; a 60th — three
   12 km lines, two ties, a 1 Hz platform gravimeter — gave 8.2 with an error of 20.3 mGal
   against FIR's 8.1 (its 6 crossovers: p = 0.08 in step 4, not significant).
   The same step also takes FIR when the median over those lines of RMS(estimate − FIR)
   exceeds FIR's own along-line std (``noisy_max_disagreement``, 1): that says the estimate's error exceeds the
   anomaly (:func:`app.core.model_check.disagreement_ratio`), and unlike the variance ratio
   it needs no noise model — the variance ratio is fooled when the fitted model puts too
   little noise in FIR's band, as a tiny heights-only survey's "white height" fit does.
4. **FIR guard.**  With at least ``fir_guard_min_crossovers`` crossovers (the paired test's
   p-value accounts for how few there are: a 4-line survey's 8 crossovers can still show an
   estimate ruined by a wrong noise model), when the chosen estimate disagrees
   significantly more at the crossovers than FIR 100 s does (one-sided p < ``fir_guard_p`` by
   a paired t-test on the squared differences, or by a signed-rank test on their magnitudes
   when the crossover RMS points the same way — a few wild crossovers blind the first:
   :func:`app.core.model_check.significantly_worse`), every line takes FIR.

4b. **Repeat blend** (:func:`repeat_blend`).  Where the crossovers are too few for step 4 (a
   test-line survey) and a repeat track has at least ``repeat_blend_min_passes`` passes, every
   line takes the blend of the estimate and FIR 100 s whose passes agree best with the other
   passes' light low-pass of z (the passes share the anomaly, not the noise).

4d. **Small survey** (:func:`small_survey_blend`).  Where neither 4 nor 4b could judge the
   estimate and its one anomaly level was learned from fewer than ``min_points_adaptive``
   decimated points, every line takes ``(1 − w)·estimate + w·FIR 100 s``,
   ``w = small_survey_fir_weight``: a hedge towards the model-free estimate where the model is
   least reliable and nothing can check it.

Between 3 and 4, **3b. FIR resolving nothing** (:func:`longer_lowpass`): after step 3, when
FIR's own crossovers show at least as much error as its lines vary, the same low-pass at the
longer ``fir_long_periods_s`` is tried and the shortest that varies by more than its crossovers'
error (else the one with the least) replaces FIR on every line.

After 4 and 4b, **4c. The estimate resolving nothing** (:func:`unresolved_check`): when the
estimate kept so far (adaptive, mixed, or FIR by the guard) shows at its own crossovers at least
as much error as its lines vary, step 3b's longer low-pass is tried against its crossover error.

Every decision is returned with its evidence (the report's ``model_choice`` section).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from app.core.accuracy import REPEAT_MAX_SPREAD_KM, across_track_spread_km, repeat_line_accuracy
from app.core.baselines import fir_lowpass_mgal
from app.core.leveling import drift_free_differences, find_crossovers
from app.core.model_check import (
    blend_estimates,
    crossover_blend_weight,
    crossover_comparison,
    crossover_excess,
    crossover_rms_mgal,
    disagreement_ratio,
    fir_noise_bandwidth_hz,
    fir_noise_variance_mgal2,
    fir_smoothing_variance_mgal2,
    flattening_ratio,
    leave_one_out_msd_mgal2,
    repeat_blend_weight,
    repeat_noise_variance_mgal2,
    shrunk_repeat_blend_weight,
    significantly_worse,
    smooth_error_bound_mgal2,
)
from app.pipeline.stages.leveling import STD_FLOOR, flight_of_line, tracks
from app.pipeline.stages.lines import line_crossovers


@dataclass
class Candidate:
    """One identified and filtered order: the identification, its state map, its filter."""

    ident: object
    smap: object
    filtered: object


@dataclass
class ModelChoice:
    """Result of :func:`choose_model`.

    Attributes
    ----------
    m : int
        The order whose outputs are used.
    table : DataFrame
        The line table with ``dg_mgal``/``dg_unleveled_mgal``/``dg_std_mgal`` from the chosen
        estimate of every line.
    report : dict
        The evidence: per-order crossover RMS and test, per-line estimate and flattening
        ratio, the FIR guard.
    """

    m: int
    table: pd.DataFrame
    report: dict


def _crossover_table(table: pd.DataFrame, col: str, include_repeat: bool) -> pd.DataFrame:
    """The crossovers of the table's lines carrying ``col`` (empty when there are none)."""
    try:
        return find_crossovers(tracks(table, col), include_repeat=include_repeat)
    except ValueError:
        return pd.DataFrame()


def crossover_differences(table: pd.DataFrame, col: str, include_repeat: bool) -> np.ndarray:
    """Differences of ``col`` at the crossovers of the table's lines (line_a − line_b)."""
    cx = _crossover_table(table, col, include_repeat)
    if len(cx) == 0:
        return np.zeros(0)
    return (cx["dg_a"] - cx["dg_b"]).to_numpy(float)


def _drift_free(table: pd.DataFrame, cx: pd.DataFrame, diffs: list[np.ndarray], p, with_dof: bool = False):
    """``diffs`` (each order's differences at the crossovers ``cx`` of ``table``'s lines, in
    the same order) with what a drift of the leveling model explains removed
    (:func:`app.core.leveling.drift_free_differences`: ``leveling_degree``, one polynomial per
    flight with ``leveling_per_flight``); None when that cannot be done.  With ``with_dof``,
    ``(differences, degrees of freedom)``."""
    if len(cx) == 0 or any(d.size != len(cx) for d in diffs):
        return None
    ranges = {str(ln): (float(g["time"].min()), float(g["time"].max())) for ln, g in table.groupby("line", sort=False)}
    groups = flight_of_line(table) if p.leveling_per_flight and "flight" in table else None
    try:
        out, dof = drift_free_differences(cx, np.column_stack(diffs), ranges, p.leveling_degree, groups,
                                          with_dof=True)
    except ValueError:
        return None
    cols = [out[:, k] for k in range(out.shape[1])]
    return (cols, dof) if with_dof else cols


def count_crossovers(lines: list, include_repeat: bool) -> int:
    """Crossovers between the survey lines (geometry only), as leveling will find them."""
    return int(len(line_crossovers(lines, include_repeat)))


def choose_order(candidates: dict, p) -> tuple[int, dict]:
    """Step 1 of the module docstring."""
    orders = sorted(candidates)
    if p.m is not None:
        return int(p.m), {"criterion": "fixed (processing.m)", "m": int(p.m)}
    if len(orders) == 1:
        return orders[0], {"criterion": f"default: fewer than {p.choice_min_crossovers} crossovers to tell the "
                                        "orders apart", "m": orders[0]}
    tables = {m: _crossover_table(candidates[m].filtered.table, "dg_unleveled_mgal", p.leveling_include_repeat)
              for m in orders}
    diffs = {m: (cx["dg_a"] - cx["dg_b"]).to_numpy(float) if len(cx) else np.zeros(0) for m, cx in tables.items()}
    if min(d.size for d in diffs.values()) < p.choice_min_crossovers:
        n = min(d.size for d in diffs.values())
        return 2, {"criterion": f"default: {n} crossovers (< {p.choice_min_crossovers}) cannot tell the orders apart",
                   "m": 2}
    rms = {m: crossover_rms_mgal(d) for m, d in diffs.items()}
    lo, hi = orders[0], orders[-1]
    cmp = crossover_comparison(diffs[hi], diffs[lo])
    # SPEC's default order stands unless the other one is significantly better at the
    # crossovers: the crossovers cannot see the error two crossing lines share (the anomaly a
    # smoother estimate misses at the crossing is missed on both lines), so a small
    # difference either way says nothing about the error against the truth
    # (by the mean square or by the ranks, as for the FIR guard: a few wild crossovers of the
    # default order blind the t-test — unseen seed 88: 48.5 against 11.3 mGal, t p = 0.09)
    best = lo if significantly_worse(cmp, p.order_choice_p) else hi
    rep = {"criterion": f"crossover RMS: m = {hi} (SPEC's default) unless m = {lo} agrees significantly "
                        f"better at the crossovers (one-sided p < {p.order_choice_p} by the squared "
                        "differences' t-test, or the signed ranks of their magnitudes with the RMS agreeing)",
           "crossover_rms_mgal": {str(m): rms[m] for m in orders}, "n_crossovers": cmp.n,
           f"p_m{hi}_worse_than_m{lo}": cmp.p_value, f"p_rank_m{hi}_worse_than_m{lo}": cmp.p_rank, "m": best}
    if best == hi and p.order_blend:
        # neither order shown better: the blend the crossovers find least in error (module docstring)
        # on the crossover differences less what the leveling's drift explains: the orders
        # share the lines' drift and offsets exactly, and left in (several mGal against
        # estimate errors of one) they decide the weight by chance (generated survey 185:
        # w = 1 and 1.31x FIR; drift removed w = 0.23)
        free = _drift_free(candidates[hi].filtered.table, tables[hi], [diffs[lo], diffs[hi]], p)
        da, db = free if free is not None else (diffs[lo], diffs[hi])
        w = crossover_blend_weight(da, db)
        if np.isfinite(w) and w > 0.0:
            rep["blend"] = {"m": lo, "weight": w, "crossover_rms_mgal": crossover_rms_mgal(
                w * diffs[lo] + (1.0 - w) * diffs[hi]), "drift_removed": free is not None}
        rep["criterion"] += (f"; else the blend w·(m = {lo}) + (1 − w)·(m = {hi}) with the least crossover mean "
                             "square once what the leveling's drift explains is removed (w = 0: m = 2 alone)")
    return best, rep


def _use(table: pd.DataFrame, rows, values, std) -> None:
    """Another estimate on ``rows`` — where it has a value: where it has none (FIR left out
    near missing samples, :func:`app.pipeline.stages.filtering.fir_baseline`) the estimate
    stays as it was."""
    values = np.asarray(values, dtype=float)
    ok = np.isfinite(values)
    rows = np.asarray(rows)[ok]
    values = values[ok]
    std = np.broadcast_to(np.asarray(std, dtype=float), ok.shape)[ok]
    table.loc[rows, "dg_mgal"] = values
    table.loc[rows, "dg_unleveled_mgal"] = values
    table.loc[rows, "dg_std_mgal"] = std
    if STD_FLOOR in table:  # the adaptive estimate's floor does not hold for another estimate
        table.loc[rows, STD_FLOOR] = np.nan


def repeat_passes(table: pd.DataFrame) -> list[list[tuple[str, pd.DataFrame]]]:
    """The passes of every repeat track in the line table: per track, ``[(line, rows)]`` in
    table order.  Tracks with one pass or passes more than ``REPEAT_MAX_SPREAD_KM`` apart
    across the track (not repeats of one track) are left out."""
    out = []
    if "track" not in table or "kind" not in table:
        return out
    rep = table[(table["kind"] == "repeat") & table["track"].notna()]
    for _, g in rep.groupby("track", sort=False):
        passes = [(str(line), gg) for line, gg in g.groupby("line", sort=False)]
        if len(passes) < 2:
            continue
        if across_track_spread_km([gg["easting_km"].to_numpy() for _, gg in passes],
                                  [gg["northing_km"].to_numpy() for _, gg in passes]) > REPEAT_MAX_SPREAD_KM:
            continue
        out.append(passes)
    return out


def repeat_fir_noise_mgal2(table: pd.DataFrame) -> dict[str, float]:
    """FIR's noise variance (mGal²) on every pass of a repeat track, measured by the passes
    (:func:`app.core.model_check.repeat_noise_variance_mgal2` on FIR 100 s at common positions
    every 0.1 km): {line: mGal²}.  Tracks with one pass, passes more than
    ``REPEAT_MAX_SPREAD_KM`` apart or no common stretch are left out."""
    out: dict[str, float] = {}
    for passes in repeat_passes(table):
        e = [gg["easting_km"].to_numpy() for _, gg in passes]
        n = [gg["northing_km"].to_numpy() for _, gg in passes]
        try:
            acc = repeat_line_accuracy(e, n, [gg["dg_fir_mgal"].to_numpy() for _, gg in passes])
        except ValueError:   # no common stretch where every pass has FIR
            continue
        for (line, _), v in zip(passes, repeat_noise_variance_mgal2(acc.values_mgal)):
            if np.isfinite(v):
                out[line] = float(v)
    return out


def fir_crossover_noise(table: pd.DataFrame, noise, dt_s: float, p) -> dict:
    """FIR's error as its crossovers measure it, against the noise model's FIR noise.

    The drift-free crossover differences of ``dg_fir_mgal``
    (:func:`app.core.leveling.drift_free_differences`) against the sum of the two lines' FIR
    noise variances the noise model predicts (:func:`app.core.model_check.crossover_excess`).
    ``factor`` is the ratio squared when the excess is significant (p < ``crossover_level_p``),
    else 1: the factor by which the model under-states FIR's noise (FIR's own smoothing error at
    the crossings adds to it, so it is an upper bound)."""
    cx = _crossover_table(table, "dg_fir_mgal", p.leveling_include_repeat)
    if len(cx) < p.crossover_level_min_crossovers:
        return {"n_crossovers": int(len(cx)), "factor": 1.0}
    level = {str(ln): fir_noise_variance_mgal2(noise, float(np.nanmean(g["R_cm2s2"])), dt_s, p.fir_cutoff_period_s)
             for ln, g in table.groupby("line", sort=False)}
    pv = np.array([level.get(str(a), np.nan) + level.get(str(b), np.nan) for a, b in zip(cx["line_a"], cx["line_b"])])
    free = _drift_free(table, cx, [(cx["dg_a"] - cx["dg_b"]).to_numpy(float)], p, with_dof=True)
    if free is None:
        return {"n_crossovers": int(len(cx)), "factor": 1.0}
    ex = crossover_excess(free[0][0], pv, free[1])
    sig = bool(ex.rms_ratio > 1.0 and ex.p_value < p.crossover_level_p)
    return {"n_crossovers": int(len(cx)), "rms_ratio": ex.rms_ratio, "p_excess": ex.p_value,
            "factor": float(ex.rms_ratio ** 2) if sig else 1.0}


def _line_flattening(g: pd.DataFrame, noise, dt_s: float, p, bandwidth_hz: float):
    """One line's flattening check (:func:`app.core.model_check.flattening_ratio` of
    ``dg_unleveled_mgal`` against ``dg_fir_mgal``): FIR's noise variance the model predicts at
    the line's mean R (mGal²), its independent samples along the line, and the result."""
    fir_var = fir_noise_variance_mgal2(noise, float(np.nanmean(g["R_cm2s2"])), dt_s, p.fir_cutoff_period_s)
    # independent samples of FIR's noise along the line: a short line's FIR can carry
    # twice the predicted noise variance by chance, which would read as a flattened anomaly
    nu = 2.0 * bandwidth_hz * len(g) * dt_s
    return fir_var, nu, flattening_ratio(g["dg_unleveled_mgal"], g["dg_fir_mgal"], fir_var, independent_samples=nu)


def resolved_anomaly(table: pd.DataFrame, noise, dt_s: float, p) -> dict:
    """How much of the anomaly FIR 100 s shows beyond its noise the estimate keeps, over the lines
    where FIR shows it (``detectable``): ``n_lines``, ``n_detectable`` and the median of their
    flattening ratios (the estimate's along-line variance over FIR's beyond its noise; NaN
    without such a line)."""
    bandwidth_hz = fir_noise_bandwidth_hz(noise, dt_s, p.fir_cutoff_period_s)
    ratios, n = [], 0
    for _, g in table.groupby("line", sort=False):
        n += 1
        fl = _line_flattening(g, noise, dt_s, p, bandwidth_hz)[2]
        if fl.detectable and np.isfinite(fl.ratio):
            ratios.append(float(fl.ratio))
    return {"n_lines": n, "n_detectable": len(ratios),
            "median_flattening_ratio": float(np.median(ratios)) if ratios else float("nan")}


def check_lines(table: pd.DataFrame, noise, dt_s: float, p, warnings: list, fir_noise_factor: float = 1.0) -> dict:
    """Step 2 (in place): flattened lines take the stationary or the FIR estimate.  With
    ``fir_noise_factor`` > 1 (FIR's noise as its crossovers measure it over the model's,
    :func:`fir_crossover_noise`; used where the crossover level check lowered the levels) a
    verdict that no longer holds against FIR's noise so measured is overturned, as a repeat
    track's passes overturn it (:func:`_repeats_veto`)."""
    out = {}
    bandwidth_hz = fir_noise_bandwidth_hz(noise, dt_s, p.fir_cutoff_period_s)
    repeat_noise = repeat_fir_noise_mgal2(table)
    for line, g in table.groupby("line", sort=False):
        fir_var, nu, fl = _line_flattening(g, noise, dt_s, p, bandwidth_hz)
        measured, source = repeat_noise.get(str(line)), "its repeat passes"
        if fir_noise_factor > 1.0 and not (measured is not None and measured >= fir_var * fir_noise_factor):
            measured, source = fir_var * fir_noise_factor, "the survey's crossovers"
        est_std = float(np.nanstd(g["dg_unleveled_mgal"]))
        post_std = float(np.sqrt(np.nanmean(np.square(g["dg_std_mgal"]))))
        rec = {"estimate": "adaptive", "flattening_ratio": fl.ratio, "flattening_ratio_bound": fl.ratio_bound,
               "fir_signal_var_mgal2": fl.signal_var_mgal2, "fir_noise_std_mgal": float(np.sqrt(fir_var)),
               "fir_noise_samples": fl.independent_samples, "detectable": fl.detectable,
               "estimate_std_mgal": est_std, "posterior_std_mgal": post_std,
               "resolved": bool(fl.detectable or est_std >= post_std)}
        if not rec["resolved"] and p.std_unresolved_bound:
            _bound_std(table, g, rec)
        if (fl.detectable and fl.ratio_bound < p.flatten_min_ratio
                and not _repeats_veto(g, fir_var, measured, nu, p, rec, warnings, source)):
            st = flattening_ratio(g["dg_stationary_mgal"], g["dg_fir_mgal"], fir_var, independent_samples=nu)
            # the stationary estimate must not be flattened either, nor pass noise: an error
            # beyond the anomaly's own spread (a noise episode the stationary level ignores)
            st_dis = disagreement_ratio(g["dg_stationary_mgal"].to_numpy(), g["dg_fir_mgal"].to_numpy())
            rec["stationary_disagreement"] = st_dis
            st_noisy = bool(np.isfinite(st_dis) and st_dis > p.noisy_max_disagreement)
            why = ""
            if st.ratio_bound >= p.flatten_min_ratio and not st_noisy:
                _use(table, g.index, g["dg_stationary_mgal"].to_numpy(), g["dg_std_mgal"].to_numpy())
                rec["estimate"] = "stationary"
            else:
                _use(table, g.index, g["dg_fir_mgal"].to_numpy(), np.full(len(g), np.sqrt(fir_var)))
                rec["estimate"] = "FIR"
                why = (f" (the stationary one differs from FIR by {st_dis:.2f}x FIR's std: it passes noise)"
                       if st_noisy else " (the stationary one is flattened too)")
            warnings.append(f"line {line}: the adaptive estimate is flattened (variance {fl.ratio:.2f} of the "
                            f"anomaly variance FIR shows beyond its noise, {fl.ratio_bound:.2f} of the least it can "
                            f"show over {nu:.0f} independent samples of its noise): {rec['estimate']} estimate "
                            f"used{why}")
        out[str(line)] = rec
    if p.std_unresolved_bound:
        _bound_flattened_survey(table, out, p.flatten_min_ratio, warnings)
    _warn_unresolved(out, warnings)
    return out


def _repeats_veto(g: pd.DataFrame, fir_var: float, measured: float | None, nu: float, p, rec: dict,
                  warnings: list, source: str = "its repeat passes") -> bool:
    """Whether a repeat pass's sister passes overturn its flattening verdict (in place: ``rec``
    and ``warnings`` say so).

    The verdict reads FIR's variance beyond the noise model's as anomaly.  Where the passes
    measure FIR's noise on this pass (:func:`repeat_fir_noise_mgal2`) significantly above the
    model's (one-sided 95 % over its ν samples: by chance alone the measure is up to twice the
    model's on a short pass) and the check no longer holds against that noise, the "anomaly"
    was noise the model's level misses — a noise episode of slowly varying GNSS error — and
    the adaptive estimate stays.  Generated survey 116: a pass in a ×9 noise episode, whose
    sound estimate (11.9 mGal from the truth) was swapped for the stationary one (69)."""
    if measured is None or not np.isfinite(measured):
        return False
    nu_eff = max(float(nu), 2.0) if np.isfinite(nu) else 2.0
    if not measured > fir_var * stats.chi2.ppf(0.95, nu_eff) / nu_eff:
        return False
    fl = flattening_ratio(g["dg_unleveled_mgal"], g["dg_fir_mgal"], measured, independent_samples=nu)
    if fl.detectable and fl.ratio_bound < p.flatten_min_ratio:
        return False
    key = "fir_noise_std_repeats_mgal" if source == "its repeat passes" else "fir_noise_std_crossovers_mgal"
    rec["flattening_vetoed"] = {key: float(np.sqrt(measured)),
                                "flattening_ratio_bound": fl.ratio_bound, "detectable": fl.detectable}
    warnings.append(f"line {g['line'].iloc[0]}: the adaptive estimate looked flattened against FIR, but "
                    f"{source} measure FIR's noise on it at {np.sqrt(measured):.1f} mGal (the noise model: "
                    f"{np.sqrt(fir_var):.1f}): what FIR shows beyond the model's noise is noise, the adaptive "
                    "estimate kept")
    return True


def _bound_flattened_survey(table: pd.DataFrame, lines: dict, min_ratio: float, warnings: list) -> None:
    """Where the survey's estimate is flattened as a whole but no line on its own shows it.

    A line's flattening check needs FIR to show anomaly variance beyond its noise
    (``detectable``); on a noisy survey none does, each line's ratio is too uncertain alone,
    and the std of an estimate that keeps a fraction of the anomaly stays its own
    posterior's.  The median over the lines of the flattening ratio is far steadier: below
    ``min_ratio`` (``flatten_min_ratio``) the estimate keeps less than that share of the
    anomaly variance FIR shows on most lines.  Then every adaptive line that is not
    detectable takes the std floor of an unresolved line (:func:`_bound_std`: the error a
    smooth estimate can have, ``Var(FIR) − Var(estimate)``); the estimate is unchanged.
    Held-out surveys of ``bench_unseen.py`` (1701, 1703, 1705: a low, draped flight over
    shallow sources in heavy turbulence, the estimate keeping 0.12–0.26 of the truth's
    variance): 2σ coverage 0.85 → 0.93, 0.75 → 1.00, 0.78 → 1.00."""
    ratios = [r["flattening_ratio"] for r in lines.values()
              if r.get("flattening_ratio") is not None and np.isfinite(r["flattening_ratio"])]
    if len(ratios) < 3:   # a median of one or two lines' ratios is that line's chance
        return
    med = float(np.median(ratios))
    if not med < min_ratio:
        return
    widened = []
    for line, g in table.groupby("line", sort=False):
        rec = lines.get(str(line))
        if rec is None or rec["detectable"] or not rec["resolved"] or rec["estimate"] != "adaptive":
            continue
        _bound_std(table, g, rec)
        if "std_bound_factor" in rec:
            rec["survey_flattened"] = True
            widened.append(str(line))
    if widened:
        warnings.append(f"the estimate keeps a median {med:.2f} of the anomaly variance FIR shows beyond its noise "
                        f"over {len(ratios)} lines (< {min_ratio:g}: flattened as a whole, though no line shows it "
                        f"alone): the std of {len(widened)} lines widened to the error a smooth estimate can have")


def _bound_std(table: pd.DataFrame, g: pd.DataFrame, rec: dict) -> None:
    """An unresolved line's std floor (in place, column :data:`STD_FLOOR`): the error a smooth
    estimate can have.

    :func:`app.core.model_check.smooth_error_bound_mgal2` (``Var(FIR) − Var(x̂)``) needs no
    noise model — the fitted one may over- or under-state FIR's noise, which is why the line
    is unresolved.  When the bound exceeds the mean posterior variance, the std scaled up to it, keeping its shape in time, becomes the line's floor
    (``std_bound_factor`` in the report).  It is applied after the crossover check of the
    std, which judges the model's own std: a floor counted there lowered the other lines'
    widening (unseen seed 83: 2σ coverage 0.97 → 0.83)."""
    bound = smooth_error_bound_mgal2(g["dg_unleveled_mgal"].to_numpy(), g["dg_fir_mgal"].to_numpy())
    post = rec["posterior_std_mgal"] ** 2
    if np.isfinite(bound) and post > 0 and bound > post:
        f = float(np.sqrt(bound / post))
        if STD_FLOOR not in table:
            table[STD_FLOOR] = np.nan
        table.loc[g.index, STD_FLOOR] = g["dg_std_mgal"].to_numpy() * f
        rec["std_bound_factor"] = f


def _warn_unresolved(lines: dict, warnings: list) -> None:
    """One warning when at least half of the lines do not resolve the anomaly: FIR 100 s shows
    no anomaly variance beyond 4× its predicted noise (the flattening check cannot run) and the
    estimate varies along the line by less than its own posterior std.  Such an estimate is
    close to a smooth trend — maybe right (the anomaly below the noise at 100 s), maybe
    flattened — and nothing in the data can tell which (unseen seed 89: along-line variance
    0.09 of the truth's, no warning before)."""
    bad = [ln for ln, r in lines.items() if not r["resolved"]]
    if not lines or 2 * len(bad) < len(lines):
        return
    est = float(np.median([lines[ln]["estimate_std_mgal"] for ln in bad]))
    post = float(np.median([lines[ln]["posterior_std_mgal"] for ln in bad]))
    names = ", ".join(bad[:8]) + (", …" if len(bad) > 8 else "")
    wide = [lines[ln]["std_bound_factor"] for ln in bad if "std_bound_factor" in lines[ln]]
    warnings.append(f"{len(bad)} of {len(lines)} lines do not resolve the anomaly beyond the noise ({names}): FIR 100 s "
                    "shows no anomaly variance beyond its predicted noise and the estimate varies along the line by "
                    f"less than its own std (median {est:.2f} vs {post:.2f} mGal) — it is close to a smooth trend, "
                    "which the data cannot tell from a flattened anomaly"
                    + (f"; the std of {len(wide)} of them widened to the anomaly variance FIR allows "
                       f"(median ×{np.median(wide):.2f})" if wide else ""))


def median_line_spread_mgal(table: pd.DataFrame, values_mgal) -> float:
    """Median over the table's lines of the along-line std of ``values_mgal`` (one value per
    row, in row order; NaNs ignored), mGal."""
    v = np.asarray(values_mgal, dtype=float)
    return float(np.nanmedian([float(np.nanstd(v[pos])) for pos in table.groupby("line", sort=False).indices.values()]))


def _fir_std_by_line(table: pd.DataFrame, noise, dt_s: float, p, floor_mgal: float = 0.0,
                     smoothing: bool = False) -> tuple[dict, dict]:
    """FIR 100 s's std on every line (mGal): its noise under the fitted model, at least
    ``floor_mgal``; with ``smoothing`` also the anomaly FIR clips as the adaptive estimate a
    sees it, var(a − FIR(a)).  Returns ``(std, clipped)``, the second that variance per line
    (mGal²; empty without ``smoothing``)."""
    std, clipped = {}, {}
    for line, g in table.groupby("line", sort=False):
        s = max(np.sqrt(fir_noise_variance_mgal2(noise, float(np.nanmean(g["R_cm2s2"])), dt_s,
                                                 p.fir_cutoff_period_s)), floor_mgal)
        if smoothing:
            clipped[line] = c = fir_smoothing_variance_mgal2(g["dg_unleveled_mgal"].to_numpy(), dt_s,
                                                             p.fir_cutoff_period_s)
            if np.isfinite(c) and c > 0:
                s = np.sqrt(s ** 2 + c)
        std[line] = float(s)
    return std, clipped


def _use_fir(table: pd.DataFrame, noise, dt_s: float, p, floor_mgal: float = 0.0, smoothing: bool = False) -> dict:
    """Every line takes FIR 100 s with its std from :func:`_fir_std_by_line`; returns the
    clipped anomaly's variance per line (empty without ``smoothing``)."""
    std, clipped = _fir_std_by_line(table, noise, dt_s, p, floor_mgal, smoothing)
    for line, g in table.groupby("line", sort=False):
        _use(table, g.index, g["dg_fir_mgal"].to_numpy(), np.full(len(g), std[line]))
    return clipped


def noisy_check(table: pd.DataFrame, lines: dict, noise, dt_s: float, p, warnings: list,
                fir_at=None) -> dict:
    """Step 3 (in place): an estimate with several times the anomaly variance FIR shows is
    noise; so is one that differs from FIR by more than FIR's whole along-line std
    (:func:`app.core.model_check.disagreement_ratio`, no noise model needed beyond which lines
    FIR resolves).  ``fir_at(period_s)``: the low-pass of z at another period on the table's
    rows, for :func:`longer_lowpass` where FIR itself resolves nothing."""
    # on the lines where FIR resolves the anomaly beyond its noise, as for the variance ratio: where
    # FIR is mostly noise the ratio tends to 1 whatever the estimate's error (a 0.13×-FIR estimate
    # gave 0.97), and the sampling scatter of FIR's noise variance decides which side it falls
    dis = [disagreement_ratio(g["dg_unleveled_mgal"].to_numpy(), g["dg_fir_mgal"].to_numpy())
           for line, g in table.groupby("line", sort=False) if lines.get(str(line), {}).get("detectable")]
    dis = np.array([d for d in dis if np.isfinite(d)], float)
    rep: dict = {"max_ratio": p.noisy_max_ratio, "max_disagreement": p.noisy_max_disagreement}
    if dis.size:
        rep["median_disagreement"] = float(np.median(dis))
    ratios = np.array([r["flattening_ratio"] for r in lines.values() if r.get("detectable")], float)
    ratios = ratios[np.isfinite(ratios)]
    if ratios.size:
        rep.update(median_variance_ratio=float(np.median(ratios)), n_lines=int(ratios.size))
    by_variance = ratios.size > 0 and rep["median_variance_ratio"] > p.noisy_max_ratio
    by_disagreement = dis.size > 0 and rep["median_disagreement"] > p.noisy_max_disagreement
    rep["applied"] = bool(by_variance or by_disagreement)
    if not (ratios.size or dis.size):
        rep["reason"] = "no line to compare with FIR"
    if rep["applied"]:
        # an estimate that passes noise means the fitted model misjudges the noise, in FIR's band
        # too, so its FIR noise std means little (a tiny heights-only survey: 2σ coverage 0.07).
        # Two scales need no model: FIR's own along-line spread (where the estimate was rejected
        # the anomaly FIR leaves out is of that order) and its crossovers' share.  The crossovers
        # see only the error two crossing lines do not share, and the anomaly FIR clips is shared
        # (the same place): on a 4-line heights-only layout they gave 1.2 mGal against an error
        # of 12 (2σ coverage 0.13).  So the floor is the larger of the two (a NaN one ignored).
        spread = median_line_spread_mgal(table, table["dg_fir_mgal"].to_numpy())
        d_fir = crossover_differences(table, "dg_fir_mgal", p.leveling_include_repeat)
        floor = spread
        if d_fir.size >= 4:
            rep["fir_crossover_std_mgal"] = float(crossover_rms_mgal(d_fir) / np.sqrt(2.0))
            floor = float(np.fmax(spread, rep["fir_crossover_std_mgal"]))
        rep["fir_spread_mgal"] = spread
        _use_fir(table, noise, dt_s, p, floor)
        rep["fir_std_floor_mgal"] = floor
        why = (f"has {rep['median_variance_ratio']:.1f}x the along-line variance of the anomaly FIR 100 s shows "
               f"beyond its noise (median of {ratios.size} lines)" if by_variance else
               f"differs from FIR 100 s by {rep['median_disagreement']:.2f}x FIR's along-line std (median of "
               f"{dis.size} lines): its error would exceed the anomaly")
        warnings.append(f"the adaptive estimate {why}: it passes noise, FIR used")
        if fir_at is not None and p.fir_long_periods_s and "fir_crossover_std_mgal" in rep:
            rep["long_lowpass"] = longer_lowpass(table, fir_at, spread, rep["fir_crossover_std_mgal"], p, warnings)
    return rep


#: the longest low-pass period step 3b tries, in units of the lines' median duration (about
#: twice: a 40 km line at 100 m/s, 399.9 s by its samples, keeps 800 s)
LONG_LOWPASS_LINE_FACTOR = 2.1


def longer_lowpass(table: pd.DataFrame, fir_at, fir_spread_mgal: float, fir_crossover_std_mgal: float, p,
                   warnings: list, what: str | None = None) -> dict:
    """Step 3b (in place): where FIR resolves no anomaly, a longer low-pass.

    When the error FIR's crossovers show (RMS of the differences over √2: the part two crossing
    lines do not share) is at least FIR's whole along-line spread (the median of its lines'
    std), the anomaly FIR 100 s keeps is lost in its noise — aliased motion on a 1–2 Hz
    record that the noise model cannot see, so every model-based estimate passes it too.  The
    same low-pass of z over each whole flight is then tried at the longer ``fir_long_periods_s``
    (``fir_at(period_s)``) — those at most :data:`LONG_LOWPASS_LINE_FACTOR` (about twice) the
    lines' median duration, a longer one
    taking a line's level from outside it —, and the shortest one whose lines vary by more than
    its crossovers' error is used on every line: the least smoothing that resolves something
    beyond its noise.
    Where none does, the one with the least crossover RMS (the longest, as a rule).  Not the
    least crossover RMS in general: the crossovers cannot see the anomaly a low-pass clips (the
    same at both ends of a crossing), so they favour the longest period (generated 44: 800 s,
    1.7 → 12.4 mGal).  And only where that period's crossover error is at most
    ``fir_long_max_error_ratio`` of FIR's: the lines' levels (drift, offsets, not leveled yet)
    also make crossover error, and a longer low-pass keeps them.  Its std adds the two errors it has in
    quadrature: the noise its crossovers show and the anomaly it clips.  The data cannot size
    the latter (the estimate it replaces varied along its lines by no more than its noise), so
    it is taken as large as that variation may hide: the larger of the replaced estimate's
    along-line spread and the low-pass's own.  The low-pass's spread alone (the old rule) is
    what an 800 s low-pass keeps, 2-10 mGal against the 15-19 it clipped on unseen 1914 and
    1938 (2σ coverage 0.85 and 0.67; 0.98 by this rule).  ``what``: the estimate whose spread
    and crossover error are given when it is not FIR 100 s (step 4c), named in the warning.
    Returns the evidence."""
    rep: dict = {"fir_crossover_std_mgal": fir_crossover_std_mgal, "fir_spread_mgal": fir_spread_mgal,
                 "applied": False}
    if not fir_crossover_std_mgal >= fir_spread_mgal:
        rep["reason"] = "FIR's crossovers show less error than its along-line spread: it resolves the anomaly"
        return rep
    # a low-pass much longer than the lines takes their level from outside them (turns, other
    # lines): on 40 s lines (4 km at 100 m/s) the 400 s one was 21–40 mGal off every line, the
    # same on all, so neither the crossovers nor its std saw it (FIR 100 s: 4.9 mGal)
    g = table.groupby("line", sort=False)["time"]
    line_s = float(np.median((g.max() - g.min()).to_numpy()))
    rep["median_line_s"] = line_s
    periods = [float(x) for x in p.fir_long_periods_s if x > p.fir_cutoff_period_s]
    longest = LONG_LOWPASS_LINE_FACTOR * line_s
    if not any(x <= longest for x in periods):
        rep["reason"] = (f"the lines ({line_s:.0f} s, median) are shorter than half of every longer low-pass: it "
                         "would take their level from outside them")
        return rep
    tried = {}
    for period in sorted(x for x in periods if x <= longest):
        col = np.asarray(fir_at(period), dtype=float)
        d = crossover_differences(table.assign(_lp=col), "_lp", p.leveling_include_repeat)
        d = d[np.isfinite(d)]
        if d.size < 4:
            continue
        spread = median_line_spread_mgal(table, col)
        tried[period] = (crossover_rms_mgal(d) / np.sqrt(2.0), spread, col)
    rep["tried"] = {f"{k:g}": {"crossover_std_mgal": v[0], "spread_mgal": v[1]} for k, v in tried.items()}
    if not tried:
        rep["reason"] = "too few crossovers with a longer low-pass"
        return rep
    resolving = [k for k, v in tried.items() if v[1] > v[0]]
    best = resolving[0] if resolving else min(tried, key=lambda k: tried[k][0])
    xstd, spread, col = tried[best]
    if xstd > p.fir_long_max_error_ratio * fir_crossover_std_mgal:
        # what FIR's crossovers show is mostly the lines' levels (drift, offsets: leveling comes
        # later), which a longer low-pass keeps, not noise in the band it removes (layout 193: 200 s
        # keeps 0.8 of FIR's crossover error and is 1.4x FIR's error against the truth)
        rep.update(period_s=best, reason=f"the {best:g} s low-pass keeps {xstd / fir_crossover_std_mgal:.2f} of "
                   f"{what or 'FIR'}'s crossover error (> {p.fir_long_max_error_ratio:g}): "
                   + ("no less error where lines cross" if what else "the lines' levels, not noise it removes"))
        return rep
    std = float(np.hypot(xstd, max(spread, fir_spread_mgal)))   # the clipped anomaly: see above
    for pos in table.groupby("line", sort=False).indices.values():   # positions: col is in row order
        _use(table, table.index[pos], col[pos], std)
    rep.update(applied=True, period_s=best, resolves=bool(resolving), std_mgal=std)
    who = what or f"FIR {p.fir_cutoff_period_s:g} s"
    warnings.append(f"{who} resolves no anomaly{'' if what else ' either'} (its crossovers show "
                    f"{fir_crossover_std_mgal:.1f} mGal of error against an along-line spread of "
                    f"{fir_spread_mgal:.1f}): the {best:g} s low-pass is used on every line ("
                    + (f"the shortest that varies by more than its crossovers' error, {xstd:.1f} mGal" if resolving
                       else f"none of {', '.join(f'{k:g}' for k in tried)} s resolves anything beyond its "
                            f"crossovers' error; this one has the least, {xstd:.1f} mGal")
                    + f"); only anomalies longer than ~{best:g} s of flight are resolved "
                    + ("(model_choice.unresolved_check)" if what else "(model_choice.noisy_check.long_lowpass)"))
    return rep


def unresolved_check(table: pd.DataFrame, chosen: str, p, warnings: list, fir_at=None) -> dict:
    """Step 4c (in place): the estimate chosen so far resolves nothing beyond its noise.

    When its own crossovers show at least as much error as its lines vary (RMS of the
    differences over √2 against the median of the lines' std, as in step 3b) its variation
    is the noise two crossing lines do not share, not anomaly: the model let through noise
    that neither its noise fit nor the checks before saw (foreign 817: a 2 Hz point-sampled
    platform on Doppler velocities, crossovers 65 mGal RMS for an anomaly of 12 mGal std).
    Step 3b's longer low-pass is then tried against this estimate's crossover error, under
    the same rules (the shortest period that resolves something, at most half the crossover
    error, no longer than about twice the lines)."""
    rep: dict = {"applied": False}
    if fir_at is None or not p.fir_long_periods_s:
        return {**rep, "reason": "off"}
    d = crossover_differences(table, "dg_unleveled_mgal", p.leveling_include_repeat)
    d = d[np.isfinite(d)]
    if d.size < p.fir_guard_min_crossovers:
        return {**rep, "reason": f"{d.size} crossovers (< {p.fir_guard_min_crossovers})"}
    xstd = float(crossover_rms_mgal(d) / np.sqrt(2.0))
    spread = median_line_spread_mgal(table, table["dg_unleveled_mgal"].to_numpy())
    rep.update(crossover_std_mgal=xstd, spread_mgal=spread, n_crossovers=int(d.size))
    if not xstd >= spread:
        return {**rep, "reason": "its crossovers show less error than its along-line spread: it resolves the anomaly"}
    long = longer_lowpass(table, fir_at, spread, xstd, p, warnings, what=f"the {chosen} estimate")
    rep.update(applied=bool(long["applied"]), long_lowpass=long)
    return rep


def fir_guard(table: pd.DataFrame, noise, dt_s: float, p, warnings: list) -> dict:
    """Step 4 (in place)."""
    d_est = crossover_differences(table, "dg_unleveled_mgal", p.leveling_include_repeat)
    if d_est.size < p.fir_guard_min_crossovers:
        return {"applied": False, "reason": f"{d_est.size} crossovers (< {p.fir_guard_min_crossovers})"}
    d_fir = crossover_differences(table, "dg_fir_mgal", p.leveling_include_repeat)
    cmp = crossover_comparison(d_est, d_fir)
    # by the mean square (t-test) or by the ranks of the magnitudes when the RMS agrees: a few
    # wild crossovers make the squared differences' t-test blind (unseen seed 88: crossover RMS
    # 48.5 against FIR's 21.9, p = 0.10, ranks p = 0.002; 2.0x FIR's error against the truth)
    # FIR's crossovers understate its error (the anomaly it clips is shared by the two crossing
    # lines), a bias of the test that many crossovers make "significant": there a stricter level
    level = p.fir_guard_p_many if cmp.n >= p.fir_guard_many_crossovers else p.fir_guard_p
    rep = {"n_crossovers": cmp.n, "crossover_rms_mgal": cmp.rms_a_mgal, "crossover_rms_fir_mgal": cmp.rms_b_mgal,
           "p_value": cmp.p_value, "p_rank": cmp.p_rank, "p_level": level,
           "applied": significantly_worse(cmp, level)}
    if rep["applied"]:
        # the FIR's std: its noise under the fitted model, but never below what its crossovers
        # show (each line's share of the crossover difference) — the guard fired because the
        # fitted model misjudged the data
        _guarded_fir(table, noise, dt_s, p, cmp.rms_b_mgal / np.sqrt(2.0), rep)
        warnings.append(f"the adaptive estimate disagrees more at the crossovers than FIR 100 s "
                        f"({cmp.rms_a_mgal:.2f} vs {cmp.rms_b_mgal:.2f} mGal RMS, p = {cmp.p_value:.3g}; by the ranks "
                        f"of the differences' magnitudes p = {cmp.p_rank:.3g}): FIR used")
    return rep


def _guarded_fir(table: pd.DataFrame, noise, dt_s: float, p, floor_mgal: float, rep: dict) -> None:
    """A guard's switch to FIR (in place): every line takes FIR 100 s with its std at least
    ``floor_mgal`` (what the guard measured of FIR's error), plus (``fir_guard_smoothing_std``)
    the anomaly FIR clips as the adaptive estimate sees it — an error two crossing lines share,
    which the crossovers cannot show (unseen seed 50: 2σ coverage 0.78 -> 0.91)."""
    clipped = _use_fir(table, noise, dt_s, p, floor_mgal, p.fir_guard_smoothing_std)
    rep["fir_std_floor_mgal"] = float(floor_mgal)
    if clipped:
        rep["fir_smoothing_std_mgal"] = float(np.nanmedian(np.sqrt(np.fmax(list(clipped.values()), 0.0))))


def _track_values(passes: list, dt_s: float, period_s: float, length_periods: float, smoother_ref: bool = False):
    """One track's estimate, FIR 100 s and reference, each (passes, common positions) at the
    positions every pass has all three (:func:`app.core.accuracy.repeat_line_accuracy`); None
    without a common stretch.  The reference: the pass smoothed lightly (column
    ``dg_repeat_reference_mgal``, :meth:`app.pipeline.stages.filtering.Filtered.repeat_reference`)
    with ``smoother_ref``, else FIR of z at ``period_s`` with a kernel of ``length_periods`` periods."""
    e = [g["easting_km"].to_numpy() for _, g in passes]
    n = [g["northing_km"].to_numpy() for _, g in passes]
    cols = []
    for _, g in passes:
        est, fir = g["dg_unleveled_mgal"].to_numpy(float), g["dg_fir_mgal"].to_numpy(float)
        ref = (g["dg_repeat_reference_mgal"].to_numpy(float) if smoother_ref else
               fir_lowpass_mgal(g["z_mgal"].to_numpy(float), dt_s, period_s, length_periods))
        ok = np.isfinite(est) & np.isfinite(fir) & np.isfinite(ref)  # the same positions for all three
        cols.append([np.where(ok, v, np.nan) for v in (est, fir, ref)])
    try:
        return [np.asarray(repeat_line_accuracy(e, n, [c[k] for c in cols]).values_mgal) for k in range(3)]
    except ValueError:
        return None


def repeat_blend(table: pd.DataFrame, noise, dt_s: float, p, warnings: list) -> dict:
    """Step 4b (in place): where the crossovers are too few for step 4 (a test-line survey) and
    repeat tracks have at least ``repeat_blend_min_passes`` passes, every line takes the blend
    ``(1 − w)·estimate + w·FIR 100 s`` whose passes agree best with the other passes' light
    low-pass of z (:func:`app.core.model_check.repeat_blend_weight`; FIR of z at
    ``repeat_blend_reference_period_s`` with a kernel of ``repeat_blend_reference_periods``
    periods: sharp, so that it rounds off little of the anomaly; its noise, independent
    between passes, only adds scatter).  The passes share the anomaly and not the noise, so
    this is the blend with the least error against the truth as far as the passes can tell —
    the test line's counterpart of the crossovers.  Its std is that of the two-point mixture:
    ``(1 − w)·σ² + w·σ_FIR² + w(1 − w)·(estimate − FIR)²``, σ_FIR at least the noise the
    passes measure on FIR (three-cornered hat).  A significance test over 4 passes has little
    power (a jackknife over the passes gives t ≈ 1.6 where the estimate is 1.2-1.3x FIR's
    error); the blend needs none — it loses little where w is off (module docstring)."""
    tracks = [t for t in repeat_passes(table) if len(t) >= p.repeat_blend_min_passes]
    if not tracks:
        return {"applied": False, "reason": f"no repeat track of {p.repeat_blend_min_passes} passes or more"}
    def values(smoother_ref: bool) -> list:
        return [v for v in (_track_values(t, dt_s, p.repeat_blend_reference_period_s,
                                          p.repeat_blend_reference_periods, smoother_ref) for t in tracks)
                if v is not None]

    smoother_ref = p.repeat_blend_reference == "smoother" and "dg_repeat_reference_mgal" in table
    vals = values(smoother_ref)
    if smoother_ref and not vals:   # the filtering stage smoothed none of these passes: the low-pass of z
        smoother_ref, vals = False, values(False)
    reference = (f"estimate at {p.repeat_blend_reference_q_factor:g} x Q(t)" if smoother_ref else
                 f"{p.repeat_blend_reference_period_s:g} s low-pass of z")
    if not vals:
        return {"applied": False, "reason": "no common stretch of the passes"}
    est, fir, ref = ([v[k] for v in vals] for k in range(3))
    # one weight for the survey, over every track; shrunk by its scatter over the passes
    shrunk = shrunk_repeat_blend_weight(est, fir, ref) if p.repeat_blend_shrink else None
    w = shrunk.weight if shrunk is not None else repeat_blend_weight(est, fir, ref)
    msd = [float(np.nanmean(np.concatenate([leave_one_out_msd_mgal2(x, r) for x, r in zip(xs, ref)])))
           for xs in (est, fir, [(1 - w) * e + w * f for e, f in zip(est, fir)])]
    rep = {"weight_fir": w, "passes": int(sum(x.shape[0] for x in est)), "tracks": len(vals),
           "reference": reference,
           **({"reference_q_factor": p.repeat_blend_reference_q_factor} if smoother_ref else
              {"reference_period_s": p.repeat_blend_reference_period_s}),
           "msd_estimate_mgal2": msd[0], "msd_fir_mgal2": msd[1], "msd_blend_mgal2": msd[2], "applied": w > 0}
    if shrunk is not None:
        rep.update(weight_raw=shrunk.raw, weight_se=shrunk.se, weight_leave_one_out=list(shrunk.leave_one_out))
        if shrunk.raw > 0 and w < shrunk.raw:
            rep["reason"] = (f"the passes' weight {shrunk.raw:.2f} scatters by {shrunk.se:.2f} over the passes "
                             f"(jackknife): shrunk to {w:.2f}")
    if not rep["applied"]:
        return rep
    measured = [v for v in repeat_fir_noise_mgal2(table).values() if v > 0]
    rep["fir_std_floor_mgal"] = float(np.sqrt(np.mean(measured))) if measured else 0.0
    _blend_with_fir(table, noise, dt_s, p, w, rep["fir_std_floor_mgal"])
    shrunk_note = (f" (the passes' own weight {shrunk.raw:.2f}, shrunk by its jackknife error {shrunk.se:.2f})"
                   if shrunk is not None and w < shrunk.raw else "")
    warnings.append(f"test line: the repeat passes agree best with the other passes' "
                    f"{reference} when {w:.2f}{shrunk_note} of FIR 100 s is "
                    f"blended into "
                    f"the adaptive estimate ({rep['passes']} passes; mean square {msd[0]:.2f} adaptive, {msd[1]:.2f} FIR, "
                    f"{msd[2]:.2f} blend, mGal², the reference's noise included): that blend used")
    return rep


def _blend_with_fir(table: pd.DataFrame, noise, dt_s: float, p, w: float, floor_mgal: float = 0.0) -> None:
    """Every line takes ``(1 − w)·estimate + w·FIR 100 s`` (in place).  The std is the two-point
    mixture's (:func:`app.core.model_check.blend_estimates`) around the mean variance
    ``(1 − w)σ² + w·σ_FIR²``, with FIR's std from :func:`_fir_std_by_line` (at least
    ``floor_mgal``; with ``fir_guard_smoothing_std`` the anomaly FIR clips counted).  Where FIR has
    no value the estimate stays, with its own std."""
    fir_std = _fir_std_by_line(table, noise, dt_s, p, floor_mgal, p.fir_guard_smoothing_std)[0]
    for line, g in table.groupby("line", sort=False):
        sa = g["dg_std_mgal"].to_numpy(float)
        mix = np.sqrt((1 - w) * sa ** 2 + w * fir_std[line] ** 2)
        fir_v = g["dg_fir_mgal"].to_numpy(float)
        blended, std = blend_estimates(fir_v, g["dg_unleveled_mgal"].to_numpy(float), mix, w)
        _use(table, g.index, blended, np.where(np.isfinite(fir_v), std, sa))


def small_survey_blend(table: pd.DataFrame, noise, dt_s: float, p, n_points: int, n_q: int, warnings: list) -> dict:
    """Step 4d (in place): a share of FIR 100 s where nothing can judge the estimate.

    Called where neither the crossovers (step 4) nor the repeat passes (step 4b) judged the
    estimate.  When its one anomaly level was learned from fewer than ``min_points_adaptive``
    decimated points (``n_q`` None: chosen, not set), the level, the noise model and the
    transitions are the least reliable of any survey and no check in the data can catch a wrong
    one, so the estimate is hedged towards the model-free FIR 100 s: every line takes
    ``(1 − w)·estimate + w·FIR`` with ``w = small_survey_fir_weight`` (:func:`_blend_with_fir`).
    On 19 random layouts of that kind (``bench_unseen.py --geometry``, 3200–3299) the shares
    0.1–0.3 lowered the mean error (adaptive / FIR 0.890 → 0.871 at 0.3; the pooled least-error
    share 0.33); on the 14 of 100 held out (3300–3399) 0.948 → 0.921, the worst 1.45 → 1.26,
    better on 7 and worse on 7 — a layout the model suits loses (0.53 → 0.64).  Report:
    ``applied``, ``weight_fir``, ``n_points``, ``reason``."""
    w = float(p.small_survey_fir_weight)
    rep: dict = {"applied": False, "weight_fir": w, "n_points": int(n_points)}
    if not w > 0:
        rep["reason"] = "off (small_survey_fir_weight = 0)"
        return rep
    if p.n_q is not None or n_q != 1 or n_points >= p.min_points_adaptive:
        rep["reason"] = ("n_q set: the number of levels was not chosen from the points" if p.n_q is not None else
                         f"not a small survey: {n_q} anomaly level(s) from {n_points} decimated points "
                         f"(the blend needs one level from < {p.min_points_adaptive})")
        return rep
    _blend_with_fir(table, noise, dt_s, p, w)
    rep["applied"] = True
    rep["reason"] = (f"no crossovers or repeat passes to judge an anomaly level learned from {n_points} decimated "
                     f"points (< {p.min_points_adaptive})")
    warnings.append(f"small survey: nothing in the data can judge the estimate (fewer than "
                    f"{p.fir_guard_min_crossovers} crossovers, no repeat track of {p.repeat_blend_min_passes} passes) "
                    f"and its one anomaly level comes from {n_points} decimated points: {w:g} of FIR 100 s "
                    "blended into it (small_survey_fir_weight)")
    return rep


def stationary_check(table: pd.DataFrame, p, warnings: list) -> dict:
    """The stationary baseline column is only shown, never used for ``dg_mgal``; where its one
    full-rate ML level runs away (tiny surveys: the level absorbs noise the model misses) it
    passes noise, and the report says so by the disagreement with FIR of the noisy check
    (:func:`app.core.model_check.disagreement_ratio`, median over the lines)."""
    if "dg_stationary_mgal" not in table or not table["dg_stationary_mgal"].notna().any():
        return {"reason": "no stationary column"}
    dis = np.array([disagreement_ratio(g["dg_stationary_mgal"].to_numpy(), g["dg_fir_mgal"].to_numpy())
                    for _, g in table.groupby("line", sort=False)], float)
    dis = dis[np.isfinite(dis)]
    if not dis.size:
        return {"reason": "no line to compare with FIR"}
    rep = {"median_disagreement": float(np.median(dis)), "max_disagreement": p.noisy_max_disagreement}
    rep["passes_noise"] = bool(rep["median_disagreement"] > p.noisy_max_disagreement)
    if rep["passes_noise"]:
        warnings.append(f"the stationary baseline (dg_stationary_mgal) differs from FIR 100 s by "
                        f"{rep['median_disagreement']:.1f}x FIR's along-line std (median of {dis.size} lines): its "
                        "one full-rate ML level likely passes noise; the column is kept as computed, for comparison only")
    return rep


def choose_model(candidates: dict, noise, dt_s: float, p, warnings: list, order=None, fir_at=None) -> ModelChoice:
    """Stage 9 over the filtered candidates ``{m: Candidate}`` (``order``: the result of
    :func:`choose_order` when already made; ``fir_at``: as in :func:`noisy_check`)."""
    m, order_rep = order if order is not None else choose_order(candidates, p)
    # shallow: with pandas' copy-on-write (pandas >= 3) the writes below copy only the columns
    # they change, and the candidates are not read after the choice (a deep copy took ~1 s on omolon)
    table = candidates[m].filtered.table.copy(deep=False)
    fir_x = None
    if (getattr(candidates[m].filtered, "crossover_check", None) or {}).get("applied"):
        # the levels were lowered for noise the model does not know: FIR's noise is more than it says too
        fir_x = fir_crossover_noise(table, noise, dt_s, p)
    lines = (check_lines(table, noise, dt_s, p, warnings, (fir_x or {}).get("factor", 1.0))
             if p.flatten_check else {})
    noisy = (noisy_check(table, lines, noise, dt_s, p, warnings, fir_at) if p.flatten_check
             else {"applied": False, "reason": "off"})
    if noisy["applied"]:
        guard = {"applied": False, "reason": "FIR already used (noisy estimate)"}
    else:
        guard = fir_guard(table, noise, dt_s, p, warnings) if p.fir_guard else {"applied": False, "reason": "off"}
    if noisy["applied"] or guard.get("applied"):
        repeats = {"applied": False, "reason": "FIR already used"}
    elif "p_value" in guard:
        repeats = {"applied": False, "reason": "the crossovers judged (step 4)"}
    else:
        repeats = (repeat_blend(table, noise, dt_s, p, warnings) if p.repeat_blend
                   else {"applied": False, "reason": "off"})
    n_q = len(candidates[m].ident.learned.em.Q)
    n_points = int(candidates[m].ident.n_points)
    if noisy["applied"] or guard.get("applied") or "p_value" in guard or "weight_fir" in repeats:
        small = {"applied": False, "reason": "judged by the data (steps 3, 4 or 4b)"}
    else:
        small = small_survey_blend(table, noise, dt_s, p, n_points, n_q, warnings)
    used = {r["estimate"] for r in lines.values()} or {"adaptive"}
    chosen = ("FIR" if guard.get("applied") or noisy["applied"] or repeats.get("weight_fir") == 1.0 else
              "blend with FIR" if repeats["applied"] or small["applied"] else
              ("adaptive" if used == {"adaptive"} else "mixed"))
    if noisy["applied"]:   # FIR taken there, and step 3b judged it on the same figures
        unresolved = {"applied": False, "reason": "FIR judged by step 3b (noisy estimate)"}
    else:
        unresolved = unresolved_check(table, chosen, p, warnings, fir_at)
        if unresolved["applied"]:
            chosen = "FIR"
    why = ("two anomaly levels (Markov-switching Q)" if n_q > 1 else
           f"one anomaly level: {n_points} decimated points "
           f"(< {p.min_points_adaptive}) cannot tell two apart" if p.n_q is None else "n_q = 1 set")
    if chosen == "FIR":   # the low-pass's period: FIR's, or the longer one of step 3b or 4c
        long = next((r for r in (noisy.get("long_lowpass"), unresolved.get("long_lowpass"))
                     if (r or {}).get("applied")), None)
        rep_period = {"fir_period_s": float(long["period_s"] if long else p.fir_cutoff_period_s)}
    else:
        rep_period = {}
    rep = {"chosen": chosen, **rep_period, "m": m, "order": order_rep, "anomaly_levels": n_q,
           "anomaly_levels_reason": why,
           "lines": lines, "noisy_check": noisy, "fir_guard": guard, "repeat_blend": repeats,
           "small_survey_blend": small, "unresolved_check": unresolved,
           "stationary_check": stationary_check(table, p, warnings)}
    if fir_x is not None:
        rep["fir_crossover_noise"] = fir_x
    return ModelChoice(m, table, rep)
