"""The gravimeter's clock against the GNSS's: a drift and jumps, from windowed time offsets.

SPEC §4 puts every file of a survey on one time scale.  A logger whose clock runs free (a
few to a hundred ppm off the GNSS's) or is set again in flight (a jump) breaks that, and a
single time offset per flight cannot mend it: 20 ppm over a two-hour flight misaligns the
ends by 70 ms, and a 0.2 s jump halfway misaligns half the flight by 0.2 s, so the aircraft's
jerk enters z (white-30 of ``benchmarks/bench_regimes.py``: 3.68 mGal from the truth clean,
4.35 with a 20 ppm drift, 5.29 with a 0.2 s jump, 25.5 with a 1 s jump — FIR 100 s 4.3).

The time offset is estimated on windows along the flight
(:func:`app.core.gravimeter.fit_time_offset`); :func:`fit_clock` explains those offsets by a
constant, a linear drift and steps, each term kept only when the windows' own scatter says it
is real (a forward-selection F-test) and it moves the clock by more than a set amount;
:func:`clock_offset_s` evaluates the result and :func:`retime_stamps_s` puts the gravimeter's
stamps on the GNSS's scale.  Pure functions on arrays; times in s, offsets in s with the sign
of :class:`app.core.gravimeter.TimeOffsetFit` (gravimeter stamp + offset = GNSS time).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from app.core.epochs import run_bounds

#: Fewest windows on each side of a step (one window off by chance must not make two steps).
MIN_SEGMENT_WINDOWS = 2


@dataclass(frozen=True)
class ClockModel:
    """The gravimeter clock's offset from the GNSS's along a flight (:func:`fit_clock`).

    Attributes
    ----------
    offset_s : float
        Offset at ``t_ref_s`` before any step (s).
    drift_s_per_s : float
        Rate of the offset (s per s; 1e-6 is 1 ppm); 0 when no drift was kept.
    t_ref_s : float
        Reference time of the drift (s, the windows' weighted mean time).
    steps : tuple of (float, float)
        ``(time_s, size_s)`` of each step: the offset changes by ``size_s`` after ``time_s``
        (a forward jump of the gravimeter's clock by J seconds is a step of −J).
    terms : list of dict
        Each kept term in the order selected, with its F-test p-value and size.
    """

    offset_s: float
    drift_s_per_s: float = 0.0
    t_ref_s: float = 0.0
    steps: tuple = ()
    terms: list = field(default_factory=list)

    @property
    def changes(self) -> bool:
        """True when the clock drifts or jumps (more than a constant offset)."""
        return bool(self.drift_s_per_s != 0.0 or self.steps)


def _wls(X: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted least squares: coefficients and the weighted residual sum of squares."""
    sw = np.sqrt(w)
    beta, *_ = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)
    r = (y - X @ beta) * sw
    return beta, float(r @ r)


def fit_clock(t_s, offset_s, se_s, step_times_s=(), p_level: float = 1e-3, min_change_s: float = 0.02,
              max_steps: int = 3) -> ClockModel:
    """A constant offset, a linear drift and steps fitted to windowed time offsets.

    Terms are added by forward selection: the drift or a step at one of ``step_times_s``,
    whichever lowers the weighted residual sum of squares most, kept when its partial F-test
    (against the windows' own scatter about the larger model, so under-stated standard errors
    do not make false steps) gives p < ``p_level`` (a step: ``p_level`` over the number of
    candidate times, the best of which it is) and it moves the clock by at least
    ``min_change_s`` (the drift over the windows' span, a step by its size).  A step leaves at
    least :data:`MIN_SEGMENT_WINDOWS` windows on either side of it and of every other step.

    Parameters
    ----------
    t_s, offset_s, se_s : array_like, shape (n,)
        Window centres (s, increasing), their offsets (s) and standard errors (s, > 0).
    step_times_s : array_like
        Where a step may be (s): the gaps of the gravimeter's record, where a clock set
        forward or back in flight shows (none: drift only).
    p_level : float
        Significance of each term.
    min_change_s : float
        Smallest clock change (s) worth a term.
    max_steps : int
        Most steps.

    Returns
    -------
    ClockModel
        A constant only when no term passes.

    Raises
    ------
    ValueError
        Arrays of different lengths or empty, non-finite values, t not increasing or se not positive.
    """
    t = np.asarray(t_s, dtype=float)
    y = np.asarray(offset_s, dtype=float)
    se = np.asarray(se_s, dtype=float)
    if not (t.shape == y.shape == se.shape and t.ndim == 1):
        raise ValueError("t_s, offset_s and se_s must be 1-D arrays of one length")
    if t.size == 0:
        raise ValueError("no window")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y)) and np.all(np.isfinite(se))):
        raise ValueError("t_s, offset_s and se_s must be finite")
    if np.any(se <= 0):
        raise ValueError("se_s must be positive")
    if np.any(np.diff(t) <= 0):
        raise ValueError("t_s must be strictly increasing")
    n = t.size
    # weights from the standard errors, floored at half their median: one window's tiny se
    # must not carry the fit
    w = 1.0 / np.maximum(se, 0.5 * float(np.median(se))) ** 2
    t_ref = float(np.sum(w * t) / np.sum(w))
    span = float(t[-1] - t[0])
    cols = [np.ones(n)]
    kinds: list = [("offset", None)]
    beta, rss = _wls(np.column_stack(cols), y, w)
    terms: list = []
    steps_at = sorted({float(x) for x in np.asarray(step_times_s, dtype=float).ravel() if np.isfinite(x)})

    def room(tau: float) -> bool:   # enough windows on both sides of tau and of every step taken
        edges = [tau] + [x for kind, x in kinds if kind == "step"]
        bounds = [-np.inf] + sorted(edges) + [np.inf]
        return all(np.sum((t > a) & (t < b)) >= MIN_SEGMENT_WINDOWS for a, b in zip(bounds[:-1], bounds[1:]))

    while n - (len(cols) + 1) >= 2:
        k = len(cols)
        cands = [] if ("drift", None) in kinds else [(("drift", None), t - t_ref)]
        if sum(kind == "step" for kind, _ in kinds) < max_steps:
            cands += [(("step", x), (t > x).astype(float)) for x in steps_at
                      if ("step", x) not in kinds and room(x)]
        best = None
        for kind, col in cands:
            b, r = _wls(np.column_stack(cols + [col]), y, w)
            if best is None or r < best[2]:
                best = (kind, col, r, b)
        if best is None:
            break
        kind, col, r_new, b_new = best
        dof = n - (k + 1)
        p_val = float(stats.f.sf((rss - r_new) / (r_new / dof), 1, dof)) if r_new > 0 else 0.0
        size = float(b_new[-1]) * (span if kind[0] == "drift" else 1.0)
        # a step is the best of every candidate gap: its level shared among them (Bonferroni)
        level = p_level / max(1, len(steps_at)) if kind[0] == "step" else p_level
        if not (p_val < level and abs(size) >= min_change_s):
            break
        cols.append(col)
        kinds.append(kind)
        beta, rss = b_new, r_new
        terms.append({"term": kind[0], "p_value": p_val, "change_s": size,
                      **({"time_s": kind[1]} if kind[0] == "step" else {})})
    drift = next((float(b) for (kind, _), b in zip(kinds, beta) if kind == "drift"), 0.0)
    steps = tuple(sorted((float(x), float(b)) for (kind, x), b in zip(kinds, beta) if kind == "step"))
    return ClockModel(float(beta[0]), drift, t_ref, steps, terms)


def snap_step_s(size_s: float, gap_s: float, sample_step_s: float, tol_s: float) -> float | None:
    """A step of the clock (offset change ``size_s``, s) at a gap of ``gap_s`` (s) in a record
    sampled every ``sample_step_s`` (s), snapped to the instrument's sampling.

    Where only the logger's clock was set (the sensor kept sampling), the true time across the
    gap is a whole number n ≥ 1 of sample steps, so the jump is exactly ``gap − n·step``; the
    windows' estimate is a few ms off, and that error left on half a flight cost 3 % on white-30
    with 10 ms stamps.  Returns the snapped step (s, the sign of ``size_s``), or None where no n
    puts it within ``tol_s`` of the estimate (the sensor restarted: its phase is new)."""
    if not (sample_step_s > 0 and tol_s >= 0):
        raise ValueError("sample_step_s must be positive and tol_s non-negative")
    jump = -float(size_s)
    n = round((float(gap_s) - jump) / sample_step_s)
    if n < 1:
        return None
    snapped = float(gap_s) - n * sample_step_s
    return -snapped if abs(snapped - jump) <= tol_s else None


def refit_drift(model: ClockModel, t_s, offset_s, se_s) -> ClockModel:
    """``model``'s constant and drift refitted by weighted least squares with its steps held
    as they are (e.g. snapped to the instrument's sampling after :func:`fit_clock`): the fitted
    steps had taken part of the drift.  ``t_s`` on the steps' time scale; arrays as for
    :func:`fit_clock`."""
    t = np.asarray(t_s, dtype=float)
    y = np.asarray(offset_s, dtype=float)
    se = np.asarray(se_s, dtype=float)
    for t_step, size in model.steps:
        y = y - np.where(t >= t_step, size, 0.0)
    w = 1.0 / np.maximum(se, 0.5 * float(np.median(se))) ** 2
    t_ref = float(np.sum(w * t) / np.sum(w))
    beta, _ = _wls(np.column_stack([np.ones(t.size), t - t_ref]), y, w)
    return ClockModel(float(beta[0]), float(beta[1]), t_ref, model.steps, model.terms)


def clock_windows(t_s, moving, window_s: float, min_epochs: int = 200) -> list[tuple[int, int]]:
    """Index ranges ``[a, b)`` of the epochs ``t_s`` (s) the clock is tracked on: each run of
    ``moving`` epochs without a gap (:func:`app.core.epochs.run_bounds`) cut into equal windows of
    at least ``window_s`` (s), those of fewer than ``min_epochs`` epochs left out."""
    t = np.asarray(t_s, dtype=float)
    out = []
    for a, b in run_bounds(moving, t):
        n_w = int((t[b - 1] - t[a]) // window_s)
        if n_w < 1:
            continue
        edges = np.linspace(a, b, n_w + 1).round().astype(int)
        out += [(int(x), int(y)) for x, y in zip(edges[:-1], edges[1:]) if y - x >= min_epochs]
    return out


def _whole_steps(excess_s, step_s: float) -> np.ndarray:
    """Whether each gap excess (s) is a whole number of sample steps ``step_s`` (s), within 5 % of
    a step or 2 ms: samples lost, as a rule."""
    e = np.asarray(excess_s, dtype=float)
    return np.abs(e / step_s - np.round(e / step_s)) * step_s <= max(0.05 * step_s, 0.002)


def step_candidates(clock_t_s, min_excess_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where a record's clock may have been set: the gaps of its sample times ``clock_t_s`` (s;
    dejittered, dropped samples put back) longer than the median step by ``min_excess_s`` at
    least.  Returns the middle of each gap (s: a step put there is clear of the stamps' jitter),
    its excess over the step (s), and whether that excess is a whole number of steps (within 5 %
    of a step or 2 ms) — samples lost, as a rule, which leaves a window across it sound; a clock
    set forward by a whole number of steps looks the same, so such a gap stays a candidate."""
    t = np.asarray(clock_t_s, dtype=float)
    step = float(np.median(np.diff(t)))
    excess = np.diff(t) - step
    j = np.flatnonzero(excess >= min_excess_s)
    return 0.5 * (t[j] + t[j + 1]), excess[j], _whole_steps(excess[j], step)


def _gap_of_step(x: float, size: float, t_s, gap_t_s, gap_excess_s, sample_step_s: float, tol_s: float) -> int:
    """Which gap holds a step fitted at ``x`` (s) of ``size`` (s): the windows ``t_s`` cannot tell
    apart the gaps between the same two of them (a record losing samples every few minutes has
    several), so the one the jump fits is taken — where it snaps to the sampling
    (:func:`snap_step_s`), else where its excess is not whole steps and holds the jump, else the
    fitted one."""
    t = np.asarray(t_s, dtype=float)
    g = np.asarray(gap_t_s, dtype=float)
    same = np.flatnonzero(np.searchsorted(t, g) == np.searchsorted(t, x))
    fitted = int(np.argmin(np.abs(g - x)))
    if same.size <= 1:
        return fitted
    e = np.asarray(gap_excess_s, dtype=float)[same]
    snapped = [snap_step_s(size, x + sample_step_s, sample_step_s, tol_s) for x in e]
    snaps = [(abs(sn - size), int(j)) for j, sn in zip(same, snapped) if sn is not None]
    if snaps:
        return min(snaps)[1]
    fits = ~_whole_steps(e, sample_step_s) & (-size <= e + tol_s)
    return int(same[fits][np.argmin(np.abs(e[fits] + size))]) if fits.any() else fitted


def fit_clock_at_gaps(t_s, offset_s, se_s, gaps: tuple, sample_step_s: float, shift_s: float = 0.0,
                      p_level: float = 1e-3, min_change_s: float = 0.02) -> tuple[ClockModel, list]:
    """:func:`fit_clock` with steps only at a record's gaps, snapped to its sampling.

    A clock set forward by J leaves a gap of at least J: a larger fitted step there is not the
    clock's, and the fit is repeated without that gap.  Each step is then snapped
    (:func:`snap_step_s`, within 3 standard errors of the windows or a quarter step) and the
    drift refitted under snapped steps (:func:`refit_drift`: the fitted steps had taken part of it).

    Parameters
    ----------
    t_s, offset_s, se_s : array_like, shape (n,)
        The windows (as :func:`fit_clock`), on the GNSS's time scale.
    gaps : (ndarray, ndarray)
        :func:`step_candidates` of the record: gap middles (s, on the record's scale) and excesses (s).
    sample_step_s : float
        The record's sampling step (s).
    shift_s : float
        Record time + ``shift_s`` = the windows' time scale (the flight's offset, s).

    Returns
    -------
    (ClockModel, list of dict)
        The model on the record's time scale, and per step its evidence (``time_s``, ``size_s``,
        ``fitted_size_s``, ``gap_s``, ``snapped_to_clock``).
    """
    wt, wo, wse = (np.asarray(a, dtype=float) for a in (t_s, offset_s, se_s))
    gap_at, gap_excess = (np.asarray(a, dtype=float) for a in gaps)
    tol = max(3.0 * float(np.median(wse)), 0.5 * sample_step_s)
    allowed = np.ones(gap_at.size, bool)
    for _ in range(4):
        model = fit_clock(wt, wo, wse, gap_at[allowed] + shift_s, p_level, min_change_s)
        near = [int(np.argmin(np.abs(gap_at + shift_s - x))) for x, _ in model.steps]
        bad = [i for i, (_, size) in zip(near, model.steps) if -size > gap_excess[i] + tol]
        if not bad:
            break
        allowed[bad] = False
    snap_tol = max(3.0 * float(np.median(wse)), 0.25 * sample_step_s)
    steps, evidence = [], []
    for x, size in model.steps:
        i = _gap_of_step(x, size, wt, gap_at + shift_s, gap_excess, sample_step_s, snap_tol)
        gap = float(gap_excess[i] + sample_step_s)
        snapped = snap_step_s(size, gap, sample_step_s, snap_tol)
        steps.append((float(gap_at[i]), size if snapped is None else snapped))
        evidence.append({"time_s": float(gap_at[i]), "size_s": steps[-1][1], "fitted_size_s": size, "gap_s": gap,
                         "snapped_to_clock": snapped is not None})
    model = ClockModel(model.offset_s, model.drift_s_per_s, model.t_ref_s, tuple(steps), model.terms)
    if model.drift_s_per_s and any(e["snapped_to_clock"] for e in evidence):
        model = refit_drift(model, wt - shift_s, wo, wse)
    return model, evidence


def clock_offset_s(model: ClockModel, t_s) -> np.ndarray:
    """The model's offset (s, gravimeter stamp + offset = GNSS time) at times ``t_s`` (s)."""
    t = np.asarray(t_s, dtype=float)
    out = model.offset_s + model.drift_s_per_s * (t - model.t_ref_s)
    for t_step, size in model.steps:
        out = out + np.where(t >= t_step, size, 0.0)
    return out


def retime_stamps_s(stamps_s, model: ClockModel, reference_s: float) -> np.ndarray:
    """The gravimeter's stamps put on the GNSS's scale, less the model's offset at
    ``reference_s`` (s): ``stamp + offset(stamp) − offset(reference)``, so that what remains is
    one constant offset, left to the flight's time-offset estimate.  Steps are evaluated on
    the stamps, so a step placed in a gap of the record closes it."""
    s = np.asarray(stamps_s, dtype=float)
    return s + clock_offset_s(model, s) - float(clock_offset_s(model, np.array([reference_s]))[0])
