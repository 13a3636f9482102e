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
from scipy.ndimage import median_filter


def uniform_epochs(t_s, max_step_s: float, tolerance: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """The record's epochs with the missing ones of its clock put back.

    A step ``Δt`` that is ``m ≥ 2`` times the median step ``δ`` (within ``tolerance·δ``), with
    ``m·δ`` at most ``max_step_s`` (+0.1 %), gets ``m − 1`` epochs at ``t + jΔt/m``.  Longer steps (record
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
    # the nominal step (m clock steps) must be allowed; stamps scattered about the clock, or a
    # clock a few ppm off its nominal rate, must not make it longer
    fill = (m >= 2) & (np.abs(dt - m * med) <= tolerance * med) & (m * med <= max_step_s * (1.0 + 1e-3))
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
    ok_all = np.isfinite(v)
    # every inserted epoch lies between two recorded ones: linear first, the run's spline below
    out[ins] = np.interp(tn[ins], t[ok_all], v[ok_all]) if ok_all.sum() >= 2 else np.nan
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


def fill_error_mgal(t_s, y, n_missing: int, kernel, derivative: bool, n_trials: int = 40,
                    half_window: int = 24, *, acceleration: bool = False) -> float:
    """How far a spline fill of ``n_missing`` consecutive epochs moves a low-pass of the
    vertical acceleration, measured on the record itself (mGal, RMS over trials).

    At ``n_trials`` evenly spaced places where the record is uniform, ``n_missing`` epochs are
    taken out of a window of ``half_window`` epochs either side and the not-a-knot cubic spline
    through the rest gives the vertical velocity — ``y``'s derivative for heights
    (``derivative=True``), ``y`` itself for a velocity column — at every epoch of the window,
    as :func:`fill_at` and the heights' derivative would.  Against the same spline without the
    hole, the acceleration ``ΔV/Δt`` differs only around it, and its sum there is zero (the
    velocities at the window's recorded ends hardly move); what the low-pass ``kernel`` (taps
    on the record's step) makes of that difference is what the fill costs.  The bridge misses
    the aircraft's motion inside the hole: 2–6 s holes at 10 Hz in turbulence moved FIR 100 s by
    24–146 mGal, single missing epochs of a 2 Hz record by far less than 1 mGal.

    With ``acceleration`` the record is an acceleration itself (m/s²: a gravimeter's samples)
    and the fill's change of the acceleration is the spline's miss at the missing samples.

    Parameters
    ----------
    t_s, y : array_like, shape (n,)
        The record (s; m for heights, m/s for a velocity, m/s² with ``acceleration``).
    n_missing : int
        Epochs missing in a row (≥ 1).
    kernel : ndarray
        Low-pass taps on the record's step (e.g. :func:`app.core.baselines.fir_kernel`).
    derivative : bool
        ``y`` is a height: the velocity is the spline's derivative.
    n_trials, half_window : int
    acceleration : bool
        ``y`` is the acceleration (``derivative`` is then ignored).

    Returns
    -------
    float
        RMS over the trials of the largest low-pass change (mGal); NaN when the record has no
        uniform stretch long enough.
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(y, dtype=float)
    h = np.asarray(kernel, dtype=float)
    m, w = int(n_missing), int(half_window)
    if m < 1:
        raise ValueError(f"n_missing must be ≥ 1, got {n_missing!r}")
    span = 2 * w + m
    if t.size < span + 2:
        return float("nan")
    dt = np.diff(t)
    med = float(np.median(dt))
    good = (np.abs(dt - med) < 0.1 * med) & np.isfinite(v[1:]) & np.isfinite(v[:-1])
    # windows [i, i + span) whose steps are all on the clock
    ok_run = np.convolve(good.astype(float), np.ones(span - 1), mode="valid") >= span - 1 - 1e-9
    starts = np.flatnonzero(ok_run)
    if starts.size == 0:
        return float("nan")
    picks = starts[np.unique(np.linspace(0, starts.size - 1, min(n_trials, starts.size)).astype(int))]
    worst = []
    for i in picks:
        tw, vw = t[i:i + span] - t[i], v[i:i + span]
        keep = np.ones(span, bool)
        keep[w:w + m] = False
        holed = CubicSpline(tw[keep], vw[keep], bc_type="not-a-knot")
        if acceleration:                                     # the samples themselves, mGal
            worst.append(float(np.max(np.abs(np.convolve((holed(tw) - vw) * 1e5, h)))))
            continue
        full = CubicSpline(tw, vw, bc_type="not-a-knot")
        if derivative:
            va, vb = holed(tw, 1), full(tw, 1)
        else:
            va, vb = holed(tw), full(tw)
        d = np.diff(va - vb) / np.diff(tw) * 1e5            # acceleration difference, mGal
        worst.append(float(np.max(np.abs(np.convolve(d, h)))))
    return float(np.sqrt(np.mean(np.square(worst))))


def positions_follow_stamps(t_s, lat_deg, lon_deg, min_speed_ms: float = 20.0,
                            earth_radius_m: float = 6_371_000.0) -> tuple[float, int]:
    """Do the positions move with the stamps?  The correlation of the horizontal distance
    between consecutive epochs with their stamp intervals, each less its local median (31
    epochs), over the epochs where the aircraft moves faster than ``min_speed_ms``.

    A receiver samples on its own uniform clock; stamps a logger wrote scatter about it while the
    positions stay where the clock put them, so the distances do not follow the intervals
    (correlation ≈ 0).  Sampling that is truly irregular moves the aircraft in proportion to each
    interval (correlation ≈ 1).  At 100 m/s a stamp error of 5 ms is 0.5 m of distance, against
    1–2 cm of GNSS position noise: the test is sharp wherever the aircraft flies.

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        Stamps (s), increasing.
    lat_deg, lon_deg : ndarray, shape (n,)
        Positions (degrees).
    min_speed_ms : float
        Epochs slower than this (parked, taxiing) carry no information and are left out.

    Returns
    -------
    (float, int)
        The correlation (NaN when undefined) and the number of epoch intervals it used.
    """
    t, lat, lon = (np.asarray(a, dtype=float) for a in (t_s, lat_deg, lon_deg))
    if not (t.shape == lat.shape == lon.shape) or t.ndim != 1:
        raise ValueError("t_s, lat_deg and lon_deg must be one-dimensional and of one length")
    if t.size < 40:
        return float("nan"), 0
    dt = np.diff(t)
    phi = np.radians(0.5 * (lat[1:] + lat[:-1]))
    dlon = (np.diff(lon) + 180.0) % 360.0 - 180.0
    d = earth_radius_m * np.hypot(np.radians(np.diff(lat)), np.radians(dlon) * np.cos(phi))
    ok = np.isfinite(d) & (dt > 0)
    moving = ok & (d > min_speed_ms * np.where(dt > 0, dt, np.nan))
    if moving.sum() < 30:
        return float("nan"), int(moving.sum())
    rd = d - median_filter(np.where(ok, d, 0.0), size=31, mode="nearest")
    rt = dt - median_filter(dt, size=31, mode="nearest")
    a, b = rd[moving], rt[moving]
    if not np.std(b) > 0:
        return float("nan"), int(moving.sum())      # uniform stamps: nothing to judge
    if not np.std(a) > 0:
        return 0.0, int(moving.sum())               # distances exactly even while the stamps scatter
    return float(np.corrcoef(a, b)[0, 1]), int(moving.sum())


def run_bounds(ok, t_s=None, max_step_factor: float = 1.5) -> list[tuple[int, int]]:
    """``(start, stop)`` of the runs of consecutive ``ok`` epochs, also broken where the time
    step exceeds ``max_step_factor`` × the median step (``t_s`` given: epochs absent from the
    record, a turn or a ferry not recorded).

    Parameters
    ----------
    ok : ndarray of bool, shape (n,)
    t_s : ndarray, shape (n,), optional
        Epoch times (s), increasing.

    Returns
    -------
    list of (int, int)
    """
    ok = np.asarray(ok, dtype=bool)
    if ok.ndim != 1:
        raise ValueError("ok must be one-dimensional")
    brk = np.zeros(ok.size, bool)               # a run may not continue into epoch i
    if t_s is not None and ok.size > 1:
        t = np.asarray(t_s, dtype=float)
        if t.shape != ok.shape:
            raise ValueError(f"t_s has shape {t.shape}, ok {ok.shape}")
        step = np.diff(t)
        brk[1:] = step > max_step_factor * np.median(step)
    cont = np.zeros(ok.size, bool)               # epoch i continues the run of epoch i − 1
    cont[1:] = ok[1:] & ok[:-1] & ~brk[1:]
    starts = np.flatnonzero(ok & ~cont)
    ends = np.flatnonzero(ok & ~np.r_[cont[1:], False]) + 1
    return list(zip(starts.tolist(), ends.tolist()))
