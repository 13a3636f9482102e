"""Stage 8, the anomaly levels checked at the crossovers (``crossover_level_check``).

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
(MEASUREMENTS.md, session 57).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.leveling import drift_free_differences
from app.core.model_check import crossover_excess, crossover_level_scale
from app.pipeline.stages.lines import line_crossovers


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


def _excess(filtered, c: _Crossings, p) -> tuple[dict, np.ndarray | None]:
    """The excess test of one order: its report entries and its drift-free differences."""
    lines = [pr.line for pr in filtered.prepared]
    a, b = _at(c, lines, _line_columns(filtered, "dg_unleveled_mgal"))
    sa, sb = _at(c, lines, _line_columns(filtered, "dg_std_mgal"))
    try:
        free, dof = drift_free_differences(c.cx, a - b, c.ranges, p.leveling_degree, c.groups, with_dof=True)
    except ValueError as exc:
        return {"reason": f"no drift-free differences: {exc}"}, None
    ex = crossover_excess(free, sa ** 2 + sb ** 2, dof)
    return {"dof": ex.dof, "rms_ratio": ex.rms_ratio, "p_excess": ex.p_value,
            "excess": bool(ex.rms_ratio > 1.0 and ex.p_value < p.crossover_level_p)}, free


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


def check_levels_at_crossovers(filtered_by_m: dict, dt_s: float, noise, p, warnings: list) -> None:
    """The check of the module docstring on every order's :class:`~app.pipeline.stages.filtering.Filtered`
    (in place: levels scaled and lines smoothed again where it applies; each order's report in
    ``crossover_check``, a warning per order scaled).  With ``crossover_level_check`` off (the
    default) only the excess test runs, and is reported."""
    items = [(m, f) for m, f in sorted(filtered_by_m.items()) if f.prepared and f.r_lines is not None]
    c = _crossings(items[0][1], p) if items else None
    if c is None:
        for _, f in items:
            f.crossover_check = {"applied": False, "reason": f"fewer than {p.crossover_level_min_crossovers} crossovers"}
        return
    tests = {m: _excess(f, c, p) for m, f in items}
    found = [m for m, (rep, _) in tests.items() if rep.get("excess")]
    for m, f in items:
        rep, free = tests[m]
        rep = {"n_crossovers": int(len(c.cx)), **rep}
        if not p.crossover_level_check:
            f.crossover_check = {**rep, "applied": False, "reason": "crossover_level_check off (the default): reported only"}
            continue
        if not found or free is None or (m not in found and not p.crossover_level_all_orders):
            f.crossover_check = {**rep, "applied": False, "reason": rep.get("reason") or (
                f"the crossovers show {rep['rms_ratio']:.2f}x the error the posterior std predicts "
                f"(p = {rep['p_excess']:.2g}): no excess at p < {p.crossover_level_p:g}")}
            continue
        rep["excess_in_orders"] = found
        rep.update(_scan(f, c, free, lambda s, f=f, m=m: f.smoothed_at(s, dt_s, m, p.smoother, noise,
                                                                          p.q_from_posteriors), p))
        f.crossover_check = rep
        if rep["applied"]:
            f.scale_levels(rep["factor"], dt_s, m, p.smoother, noise, p.q_from_posteriors)
            src = m if m in found else found[0]
            ex = tests[src][0]
            warnings.append(f"anomaly levels x {rep['factor']:.3g} (m = {m}): the crossovers of m = {src} show "
                            f"{ex['rms_ratio']:.2f}x the error its posterior std predicts (p = {ex['p_excess']:.2g}), "
                            f"noise in the anomaly band the noise model does not know; {rep['reason']}")
