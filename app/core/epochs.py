"""Missing epochs of a uniformly clocked record: found on its clock and filled.

A GNSS receiver logs at a fixed rate; a record that lost an epoch or two (a dropped
message, a solution that failed) has one step that is a whole multiple of the others.  The
measurement ``z_k = f̄_k − (V_k − V_{k−1})/Δt_k − …`` is then one sample over a longer
interval, and every stage after it works on the uniform grid: the FIR low-pass and the
smoother see one sample standing for two.  Left out (NaN), it is worse: z holds the
aircraft's accelerations (10⁴ mGal), whose sum over any window telescopes to a velocity
difference, and dropping one sample breaks that sum — the FIR 100 s estimate moves by
``h_j·z_j`` ≈ 150 mGal (the simulated 2 Hz test line, one missing GNSS epoch).

:func:`uniform_epochs` puts the missing epochs back on the clock and :func:`fill_at` gives
every column a value there from a cubic spline through the record.  For the vertical
velocity the sum of ``(V_k − V_{k−1})`` over the filled interval is ``V`` at its two ends,
which the record itself gives, so what the FIR sees of the interval is unchanged by the fill.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline


def uniform_epochs(t_s, max_step_s: float, tolerance: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """The record's epochs with the missing ones of its clock put back.

    A step ``Δt`` that is ``m ≥ 2`` times the median step ``δ`` (within ``tolerance·δ``) and
    at most ``max_step_s`` long gets ``m − 1`` epochs at ``t + jΔt/m``.  Longer steps (record
    gaps) and steps off the clock are left as they are.

    Parameters
    ----------
    t_s : array_like, shape (n,)
        Strictly increasing epochs (s).
    max_step_s : float
        Longest step filled (s).
    tolerance : float
        Largest deviation of a step from a whole number of median steps, as a fraction of
        the median step.

    Returns
    -------
    t_new : ndarray, shape (n + n_inserted,)
        The epochs, the inserted ones among them in order.
    inserted : ndarray of bool, shape (n + n_inserted,)
        True at the inserted epochs.
    """
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1:
        raise ValueError("t_s must be one-dimensional")
    if t.size < 3:
        return t.copy(), np.zeros(t.size, bool)
    dt = np.diff(t)
    if np.any(dt <= 0):
        raise ValueError("epochs must be strictly increasing")
    med = float(np.median(dt))
    m = np.rint(dt / med).astype(int)
    fill = (m >= 2) & (np.abs(dt - m * med) <= tolerance * med) & (dt <= max_step_s)
    if not fill.any():
        return t.copy(), np.zeros(t.size, bool)
    parts, flags = [], []
    last = 0
    for k in np.flatnonzero(fill):
        parts.append(t[last:k + 1])
        flags.append(np.zeros(k + 1 - last, bool))
        extra = t[k] + dt[k] * np.arange(1, m[k]) / m[k]
        parts.append(extra)
        flags.append(np.ones(extra.size, bool))
        last = k + 1
    parts.append(t[last:])
    flags.append(np.zeros(t.size - last, bool))
    return np.concatenate(parts), np.concatenate(flags)


def fill_at(t_s, y, t_new, inserted, runs=None) -> np.ndarray:
    """``y`` on ``t_new``: the record's values at its own epochs, the not-a-knot cubic spline
    through them at the inserted ones (per run: no spline crosses a record gap).

    Parameters
    ----------
    t_s, y : array_like, shape (n,)
        The record (s; any unit).  NaN values are left out of the spline.
    t_new, inserted : ndarray, shape (N,)
        :func:`uniform_epochs`' result for ``t_s``.
    runs : list of (int, int), optional
        Index ranges ``[a, b)`` of ``t_s`` without record gaps; default one run.

    Returns
    -------
    ndarray, shape (N,)
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(y, dtype=float)
    tn = np.asarray(t_new, dtype=float)
    ins = np.asarray(inserted, dtype=bool)
    if t.shape != v.shape or tn.shape != ins.shape or int((~ins).sum()) != t.size:
        raise ValueError("t_s, y and the kept epochs of t_new must agree in size")
    out = np.empty(tn.size)
    out[~ins] = v
    if not ins.any():
        return out
    for a, b in (runs or [(0, t.size)]):
        lo, hi = t[a], t[b - 1]
        sel = ins & (tn > lo) & (tn < hi)
        if not sel.any():
            continue
        ok = np.isfinite(v[a:b])
        x = t[a:b][ok] - lo
        if x.size >= 4:
            out[sel] = CubicSpline(x, v[a:b][ok], bc_type="not-a-knot")(tn[sel] - lo)
        elif x.size >= 2:
            out[sel] = np.interp(tn[sel] - lo, x, v[a:b][ok])
        else:
            out[sel] = np.nan
    return out
