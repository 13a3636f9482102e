"""Stage 8 at the crossovers: the excess test (always, reported), and two options that act on
it — a noise floor (``crossover_noise_floor``) or the anomaly levels lowered
(``crossover_level_check``); both off by default.

**The noise floor.**  Where an order's crossovers show significantly more error than its
posterior std predicts (the excess test below), the noise model under-states the noise in the
anomaly band.  A white-z component (scaled by R(t), like every component) is added to that
order's noise model, the least — found by bisection in log₂ of its weight — at which the
crossovers no longer show a significant excess, and every line of the order is smoothed again
with it: where the floor exceeds the fitted noise (the low frequencies, under a noise that
rises steeply) the smoother leans more on the anomaly model, and the std widens by the noise it
now knows.  It is not added where the estimate is already smoother than the anomaly FIR 100 s
shows beyond its noise (median flattening ratio below ``crossover_noise_floor_min_flattening``
over the lines where FIR shows it, or fewer than 3 such lines): such an excess is not noise read
as anomaly.  **Why off:** on the independent generator's point-sampled meters where it was
designed it took 5 of 8 surveys 5–13 % closer to the truth and none further, but on held-out
draws of both generators it lost on 7 of the 9 surveys where it applied (by up to 5 %) and
gained on none: an excess at the crossovers does not say by itself that more smoothing helps
(MEASUREMENTS.md, session 58).

**The levels checked** (an option, off by default; what follows).

The posterior std of an estimate is the noise model's own account of the error it leaves. Two
crossing lines' errors are nearly independent, so their crossover differences measure that
error without the model.  When the crossovers of an order's estimate show significantly more
error than its std predicts (:func:`app.core.model_check.crossover_excess`, on the differences
less what a drift of the leveling model explains), the noise in the anomaly band is more than
the noise model knows — a point-sampled platform meter's aliased turbulence, white in
acceleration, sits under the anomaly where a single line's spectrum cannot tell it apart — and
the likelihood has read it as anomaly: the levels are too high.  Every order's lines are then
smoothed again with every anomaly level × 2⁻ᵏ (k = 1 … log₂(1 / ``crossover_level_min_scale``)),
and where the scale whose crossovers agree best agrees significantly better than the levels as fitted
(:func:`app.core.model_check.crossover_level_scale`), the order's levels move half-way (in
log) to it: the crossovers cannot see the error two crossing lines share, so their best
over-smooths — taken whole it lost on 4 of 10 generated surveys where the check fired, half-way
on 3 by less (MEASUREMENTS.md, session 57).  Only an order whose own crossovers show the excess
is scanned (``crossover_level_all_orders`` false): the excess is the noise model's, but scanning
every order when one shows it gained more on average and lost on 4 of 18 surveys, against 1.

Without an excess the crossovers are not asked: they cannot see the error two crossing lines
share (an anomaly both round off alike), so heavier smoothing always looks better at the
crossings than it is, and a scale picked by them alone lost on held-out surveys
(MEASUREMENTS.md, session 57).  With the noise floor on, the check tests the lines as smoothed
with it: where the floor was added the excess is no longer significant, and nothing is scanned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from app.core.leveling import drift_free_differences
from app.core.model_check import crossover_excess, crossover_level_scale, crossover_noise_floor
from app.core.noise_model import white_velocity, with_white_floor
from app.pipeline.stages.choice import resolved_anomaly
from app.pipeline.stages.lines import line_crossovers

#: Fewest lines on which FIR 100 s must show the anomaly beyond its noise for the crossover noise
#: floor (a median of the flattening ratios over fewer says little).
FLOOR_MIN_DETECTABLE = 3


@dataclass
class _Crossings:
    """The survey's crossovers as the check uses them: the table (``line_a``, ``line_b``,
    ``time_a``, ``time_b``), each line's time range and drift unit (its flight, or None: one
    per line), and each crossover's line positions ``(index, time)`` on either side."""

    cx: object
    ranges: dict
    groups: dict | None
    sides: tuple


def _crossings(filtered, p) -> _Crossings | None:
    """The crossovers of the filtered lines; None when fewer than ``crossover_level_min_crossovers``."""
    lines = [pr.line for pr in filtered.prepared]
    cx = line_crossovers(lines, p.leveling_include_repeat)
    if len(cx) < p.crossover_level_min_crossovers:
        return None
    index = {str(ln.line): i for i, ln in enumerate(lines)}
    sides = tuple((np.array([index[str(x)] for x in cx[f"line_{s}"]]), cx[f"time_{s}"].to_numpy(float))
                  for s in ("a", "b"))
    return _Crossings(cx, {str(ln.line): (float(ln.t_s.min()), float(ln.t_s.max())) for ln in lines},
                      {str(ln.line): str(ln.flight) for ln in lines} if p.leveling_per_flight else None, sides)


def _at(c: _Crossings, lines: list, per_line: list) -> np.ndarray:
    """The per-line arrays (on each line's epochs) at the crossovers (linear in time): the
    values of line a and of line b, shape (n,) each."""
    out = []
    for idx, t in c.sides:
        out.append(np.array([np.interp(tt, lines[i].t_s, per_line[i]) for i, tt in zip(idx, t)]))
    return out[0], out[1]


def _line_columns(filtered, col: str) -> list:
    """Column ``col`` of the filtered table split per prepared line (the table's line order)."""
    out, off = [], 0
    v = filtered.table[col].to_numpy(float)
    for pr in filtered.prepared:
        n = pr.inner.stop - pr.inner.start
        out.append(v[off:off + n])
        off += n
    return out


def _excess(filtered, c: _Crossings, p, per_line: tuple | None = None) -> tuple[dict, np.ndarray | None]:
    """The excess test of one order: its report entries and its drift-free differences.
    ``per_line``: (estimates, stds) per line to test instead of the order's table."""
    lines = [pr.line for pr in filtered.prepared]
    est, std = per_line or (_line_columns(filtered, "dg_unleveled_mgal"), _line_columns(filtered, "dg_std_mgal"))
    a, b = _at(c, lines, est)
    sa, sb = _at(c, lines, std)
    try:
        free, dof = drift_free_differences(c.cx, a - b, c.ranges, p.leveling_degree, c.groups, with_dof=True)
    except ValueError as exc:
        return {"reason": f"no drift-free differences: {exc}"}, None
    ex = crossover_excess(free, sa ** 2 + sb ** 2, dof)
    return {"dof": ex.dof, "rms_ratio": ex.rms_ratio, "p_excess": ex.p_value,
            "excess": bool(ex.rms_ratio > 1.0 and ex.p_value < p.crossover_level_p)}, free


def _noise_floor(filtered, c: _Crossings, excess: dict, noise, dt_s: float, m: int, p) -> tuple[dict, object]:
    """The least white noise floor at which order m's crossovers no longer show a significant excess
    over its std (:func:`app.core.model_check.crossover_noise_floor` on the RMS ratio over its
    critical value at ``crossover_level_p``): its report and the noise model with it."""
    base = noise if noise is not None else white_velocity(dt_s)
    # the search's unit: the fitted model's PSD per sample at half FIR's cutoff frequency (R = 1)
    ref = float(base.psd(np.array([0.5 / p.fir_cutoff_period_s]))[0] / base.dt_s)
    tests = {}

    def over_critical(k: float) -> float:
        per_line = filtered.smoothed_with(with_white_floor(base, ref * 2.0 ** k), dt_s, m, p.smoother,
                                          p.q_from_posteriors)
        rep = tests[k] = _excess(filtered, c, p, tuple(zip(*per_line)))[0]
        if "rms_ratio" not in rep:
            return float("nan")
        return float(rep["rms_ratio"] / np.sqrt(stats.chi2.isf(p.crossover_level_p, rep["dof"]) / rep["dof"]))

    fit = crossover_noise_floor(over_critical, log2_start=-10.0, log2_max=10.0)
    w, at = ref * 2.0 ** fit.log2_weight, tests[fit.log2_weight]
    rep = {"applied": True, "weight_mgal2": w, "reference_mgal2": ref, "log2_of_reference": fit.log2_weight,
           "rms_ratio_before": excess["rms_ratio"], "p_excess_before": excess["p_excess"],
           "rms_ratio": at.get("rms_ratio"), "p_excess": at.get("p_excess"),
           "converged": fit.converged, "evaluations": len(fit.evaluations), "dt_s": float(dt_s),
           "floor_std_mgal_at_typical_R": float(np.sqrt(w * np.median(np.concatenate(filtered.r_lines)))),
           "reason": (f"the crossovers show {excess['rms_ratio']:.2f}x the error the posterior std predicts "
                      f"(p = {excess['p_excess']:.2g}): a white noise floor of {w:.3g} mGal² per sample and unit R "
                      f"({2.0 ** fit.log2_weight:.3g}x the noise model's PSD at {2 * p.fir_cutoff_period_s:g} s) "
                      f"added, the least at which they no longer show a significant excess ({at.get('rms_ratio', 0):.2f}x, "
                      f"p = {at.get('p_excess', 0):.2g})" + ("" if fit.converged else " (the search's largest)"))}
    return rep, with_white_floor(base, w)


def _scan(filtered, c: _Crossings, free: np.ndarray, smooth, p) -> dict:
    """The scan of one order (``smooth(factor)`` → per-line estimates): its report entries."""
    lines = [pr.line for pr in filtered.prepared]
    rows = np.isfinite(free)
    diffs = {1.0: free[rows]}
    best_ms, since_best = float(np.mean(free[rows] ** 2)), 0
    for k in range(1, int(round(np.log2(1.0 / p.crossover_level_min_scale))) + 1):
        s = 2.0 ** -k
        a, b = _at(c, lines, smooth(s))
        d = np.where(rows, a - b, np.nan)
        diffs[s] = drift_free_differences(c.cx, d, c.ranges, p.leveling_degree, c.groups)[rows]
        ms = float(np.mean(diffs[s] ** 2))
        best_ms, since_best = (ms, 0) if ms < best_ms else (best_ms, since_best + 1)
        if since_best >= 2:   # two scales past the least mean square
            break
    choice = crossover_level_scale(diffs)
    rep = {"scan_rms_mgal": {f"{s:g}": r for s, r in choice.rms_mgal.items()}, "best_scale": choice.scale,
           "p_decrease": choice.p_value}
    if choice.scale == 1.0:
        return {**rep, "applied": False, "reason": "no lower level agrees better at the crossovers"}
    if not choice.p_value < p.crossover_level_p:
        return {**rep, "applied": False,
                "reason": (f"the best lower level (x {choice.scale:g}) agrees better at the crossovers only by "
                           f"chance (p = {choice.p_value:.2g} ≥ {p.crossover_level_p:g})")}
    # half-way (in log) to the crossovers' best: they cannot see the error two crossing lines share,
    # so their least mean square lies below the truth's best (held out: the full way lost on 4 of 10)
    rms, factor = choice.rms_mgal, float(np.sqrt(choice.scale))
    return {**rep, "applied": True, "factor": factor,
            "reason": (f"the crossovers agree best at the levels x {choice.scale:g} ({rms[1.0]:.2f} → "
                       f"{rms[choice.scale]:.2f} mGal RMS, drift removed; p = {choice.p_value:.2g}): levels x "
                       f"{factor:.3g}, half-way (their best over-smooths: they cannot see the error the lines share)")}


def _no_excess(rep: dict, p) -> str:
    """Why an order's excess test (:func:`_excess`, report ``rep``) leaves it alone."""
    return rep.get("reason") or (f"the crossovers show {rep['rms_ratio']:.2f}x the error the posterior std predicts "
                                 f"(p = {rep['p_excess']:.2g}): no excess at p < {p.crossover_level_p:g}")


def _add_noise_floor(f, c: _Crossings, rep: dict, noise, dt_s: float, m: int, p, warnings: list) -> None:
    """Order m's noise floor (module docstring), in place: :attr:`Filtered.noise_floor` set to
    its report, and where it is added the order's lines smoothed again with it and a warning.
    ``rep``: the order's excess test (:func:`_excess`)."""
    if not rep.get("excess"):
        f.noise_floor = {"applied": False, "reason": _no_excess(rep, p)}
        return
    kept = resolved_anomaly(f.table, noise if noise is not None else white_velocity(dt_s), dt_s, p)
    if not (kept["n_detectable"] >= FLOOR_MIN_DETECTABLE
            and kept["median_flattening_ratio"] >= p.crossover_noise_floor_min_flattening):
        why = (f"FIR 100 s shows the anomaly beyond its noise on only {kept['n_detectable']} of "
               f"{kept['n_lines']} lines (fewer than {FLOOR_MIN_DETECTABLE}): nothing shows the estimate "
               "passing noise as anomaly" if kept["n_detectable"] < FLOOR_MIN_DETECTABLE else
               f"the estimate keeps {kept['median_flattening_ratio']:.2f} of the anomaly FIR 100 s shows "
               f"beyond its noise (median over {kept['n_detectable']} lines, below "
               f"{p.crossover_noise_floor_min_flattening:g}): already smoother than that, it is not passing "
               "noise as anomaly")
        f.noise_floor = {"applied": False, "rms_ratio_before": rep["rms_ratio"], "p_excess_before": rep["p_excess"],
                         "anomaly_kept": kept,
                         "reason": (f"the crossovers show {rep['rms_ratio']:.2f}x the error the posterior std "
                                    f"predicts (p = {rep['p_excess']:.2g}), but {why}: no floor")}
        return
    floor, with_floor = _noise_floor(f, c, rep, noise, dt_s, m, p)
    floor["anomaly_kept"] = kept
    f.add_noise_floor(floor, with_floor, dt_s, m, p.smoother, p.q_from_posteriors)
    warnings.append(f"noise floor (m = {m}): {floor['reason']}; the lines smoothed again with it: noise in the "
                    "anomaly band a line's spectrum cannot see (a point-sampled meter's aliased motion)")


def check_levels_at_crossovers(filtered_by_m: dict, dt_s: float, noise, p, warnings: list) -> None:
    """The excess test of the module docstring on every order's
    :class:`~app.pipeline.stages.filtering.Filtered`, and the options that act on it (in place):
    with ``crossover_noise_floor`` the floor (each order's report in ``noise_floor``), then with
    ``crossover_level_check`` the levels check on the lines as they stand (levels scaled and lines
    smoothed again where it applies; each order's report in ``crossover_check``); a warning per
    order changed.  With both off (the default) only the excess test runs, and is reported."""
    items = [(m, f) for m, f in sorted(filtered_by_m.items()) if f.prepared and f.r_lines is not None]
    c = _crossings(items[0][1], p) if items else None
    if c is None:
        for _, f in items:
            f.crossover_check = {"applied": False, "reason": f"fewer than {p.crossover_level_min_crossovers} crossovers"}
            if p.crossover_noise_floor:
                f.noise_floor = dict(f.crossover_check)
        return
    tests = {m: _excess(f, c, p) for m, f in items}
    found = [m for m, (rep, _) in tests.items() if rep.get("excess")]
    if p.crossover_noise_floor:
        for m, f in items:
            _add_noise_floor(f, c, tests[m][0], noise, dt_s, m, p, warnings)
        # the level check below tests the lines as smoothed now
        tests = {m: _excess(f, c, p) for m, f in items}
        found = [m for m, (rep, _) in tests.items() if rep.get("excess")]
    for m, f in items:
        rep, free = tests[m]
        rep = {"n_crossovers": int(len(c.cx)), **rep}
        if not p.crossover_level_check:
            f.crossover_check = {**rep, "applied": False, "reason": "crossover_level_check off (the default): reported only"}
            continue
        if not found or free is None or (m not in found and not p.crossover_level_all_orders):
            f.crossover_check = {**rep, "applied": False, "reason": _no_excess(rep, p)}
            continue
        rep["excess_in_orders"] = found
        rep.update(_scan(f, c, free, lambda s, f=f, m=m: f.smoothed_at(s, dt_s, m, p.smoother, f.noise_for(noise),
                                                                          p.q_from_posteriors), p))
        f.crossover_check = rep
        if rep["applied"]:
            f.scale_levels(rep["factor"], dt_s, m, p.smoother, f.noise_for(noise), p.q_from_posteriors)
            src = m if m in found else found[0]
            ex = tests[src][0]
            warnings.append(f"anomaly levels x {rep['factor']:.3g} (m = {m}): the crossovers of m = {src} show "
                            f"{ex['rms_ratio']:.2f}x the error its posterior std predicts (p = {ex['p_excess']:.2g}), "
                            f"noise in the anomaly band the noise model does not know; {rep['reason']}")
