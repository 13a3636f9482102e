"""Gravimeter model: sample times, interval means on the GNSS grid, lag/scale inversion, time offset.

The instrument model (seed 001 eq. 4) is ``τ·ḟ' + k·f' = f_g + δf_T + δf``: the
output ``f'`` is the true specific force ``f_g`` seen through a first-order
(aperiodic) filter of time constant ``τ`` and scale ``k``.  Each output sample
is the instrument's output averaged over its sampling interval and stamped at
the interval's centre (SPEC §4).

Everything here works through the cumulative integral ``F(t) = ∫ f' dt``:

* ``F`` is known exactly at the sample-interval boundaries (sum of sample value
  × interval length), so interval means over any other partition (the GNSS
  intervals ``(t_{k−1}, t_k]``) follow from a smooth (cubic-spline) interpolant
  of ``F`` — exact for polynomial ``f'`` up to degree 2, and free of the
  aliasing that piecewise-constant or linear resampling of the 18.24 Hz series
  would put into the anomaly band;
* the lag/scale inversion is then exact and needs no numerical derivative of
  the noisy samples: the mean of ``f_g = τ·ḟ' + k·f'`` over ``(t_{k−1}, t_k]``
  is ``[τ·(f'(t_k) − f'(t_{k−1})) + k·(F(t_k) − F(t_{k−1}))] / Δt_k`` with
  ``f' = F'`` from the same spline.

Units: times in s, specific force in m/s².
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import butter, savgol_filter, sosfilt, sosfilt_zi

from app.core.geodesy import vertical_velocity_from_heights_ms

#: Stamp deviation (s) from a uniform clock that a millisecond rounding explains; the default
#: bound of :func:`dejitter_times_s` is the larger of this and 5 % of the step.
ROUNDING_JITTER_S = 1.5e-3


def _clock_fits(t: np.ndarray, window: int):
    """Per segment without gaps (steps within ±50 % of the median), the local straight-line
    fit of the stamps (Savitzky–Golay, degree 1, ``window`` samples): ``(a, b, fit)``."""
    n = t.size
    dt = np.diff(t)
    med = np.median(dt)
    if not med > 0:
        raise ValueError("time stamps must be strictly increasing")
    breaks = np.flatnonzero(np.abs(dt - med) > 0.5 * med) + 1
    edges = np.concatenate([[0], breaks, [n]])
    for a, b in zip(edges[:-1], edges[1:]):
        if b - a >= 7:
            yield a, b, _line_fit(t[a:b], window)


def _line_fit(seg: np.ndarray, window: int) -> np.ndarray:
    """The local straight-line fit of a segment's stamps (Savitzky–Golay, degree 1, ``window``
    samples or the segment, odd); ≥ 7 stamps."""
    w = min(int(window) | 1, seg.size if seg.size % 2 == 1 else seg.size - 1)
    rel = seg - seg[0]   # relative to the segment start: full float precision
    return savgol_filter(rel, w, 1, mode="interp") + seg[0]


def _robust_scale(x: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(x - np.median(x)))) if x.size else 0.0


def stamp_scatter_s(t_s, window: int = 401) -> tuple[float, float]:
    """How far sample stamps scatter about a uniform clock (the local straight-line fit of
    :func:`dejitter_times_s`), whether or not they are put back on it.

    Returns
    -------
    (float, float)
        The robust scale (1.4826 × MAD, s) and the largest deviation (s), over the segments
        long enough to fit; (0, 0) for fewer than 3 stamps.
    """
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1:
        raise ValueError("t_s must be one-dimensional")
    if t.size < 3:
        return 0.0, 0.0
    dev = [t[a:b] - fit for a, b, fit in _clock_fits(t, window)]
    if not dev:
        return 0.0, 0.0
    d = np.concatenate(dev)
    return _robust_scale(d), float(np.max(np.abs(d)))


def stamp_quantum_s(t_s) -> float:
    """The rounding step of a file's time stamps (s): the largest of 1, 2 and 5 × 10⁻ᵏ s
    (0.1 ms to 0.5 s) of which every stamp is a whole multiple, within 1e-5 of the step
    (the stamps' float representation); 0 when none is.

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        Time stamps (s).
    """
    t = np.asarray(t_s, dtype=float)
    t = t[np.isfinite(t)]
    if t.size < 3:
        return 0.0
    rel = t - np.floor(t[0])      # small numbers: whole seconds change no multiple
    for q in (0.5, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 0.001, 5e-4, 2e-4, 1e-4):
        k = rel / q
        if np.all(np.abs(k - np.round(k)) < 1e-5):   # float round-off of the stamps (relative, small)
            return q
    return 0.0


def dejitter_times_s(t_s, max_jitter_s: float | None = None, window: int = 401) -> np.ndarray:
    """Remove the rounding jitter of sample time stamps of a uniformly clocked instrument.

    The file's stamps are rounded (e.g. to 1 ms), so consecutive intervals are
    not exactly equal although the instrument clock is.  Within each segment
    without gaps (steps within ±50 % of the median), the stamps are replaced by
    a local straight-line fit (Savitzky–Golay, degree 1, ``window`` samples),
    which follows slow clock-rate changes but averages the rounding out.  A
    segment is left untouched when its stamps' scatter about the fit — the robust
    scale 1.4826 × MAD of the deviations — exceeds ``max_jitter_s``, or when any stamp
    is a quarter of a step or more from the fit (real irregular sampling is not "jitter").

    The default bound is the larger of 1.5 ms (a millisecond rounding) and 5 % of the
    median step: a logging computer's stamps on a 2 Hz record scatter by several
    milliseconds while the instrument's clock is uniform, and integrating the samples over
    the stamped intervals then multiplies the aircraft's acceleration by the stamps'
    relative error — on the simulated 2 Hz test line, ±5 ms of stamp jitter put 26 mGal
    into the FIR 100 s estimate (1.9 without).  The scale, not the largest deviation, is
    compared: over 40 000 stamps a 1 ms normal scatter rounded to 1 ms reaches 4 ms
    somewhere, and leaving such a 10 Hz GNSS record on its stamps gave 31 mGal of error
    against 3.3.  Steps alternating 0.45/0.55 s (a scale of 5 % × 1.48) stay as stamped.

    Stamps rounded to a coarser step q (:func:`stamp_quantum_s`: every stamp a whole
    multiple of 1, 2 or 5 × 10⁻ᵏ s) scatter uniformly by ±q/2 about the clock, a robust
    scale of 0.37 q — 3.7 ms for stamps to 0.01 s, above 5 % of an 18.24 Hz step (2.7 ms).
    By default a segment whose largest deviation is within q/2 + 1.5 ms (and a quarter step), with at
    least 30 % of them within q/4 (rounding spreads them evenly; alternating steps put them at
    ±q/2), is that rounding and goes back on the clock: left on such stamps the sample survey's error was
    4.02 mGal against 3.30.

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        Strictly increasing sample time stamps (s).
    max_jitter_s : float, optional
        Largest robust scale of the deviations from a uniform clock accepted as stamp
        jitter (s); default ``max(1.5e-3, 0.05 × median step)``.
    window : int
        Fit window in samples (odd).

    Returns
    -------
    ndarray, shape (n,)
        De-jittered time stamps (s).
    """
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1:
        raise ValueError("t_s must be one-dimensional")
    n = t.size
    if n < 3:
        return t.copy()
    med = float(np.median(np.diff(t)))
    if not med > 0:
        raise ValueError("time stamps must be strictly increasing")
    half_q = 0.0
    if max_jitter_s is None:
        max_jitter_s = max(ROUNDING_JITTER_S, 0.05 * med)
        half_q = 0.5 * stamp_quantum_s(t)
    out = t.copy()
    for a, b, fit in _clock_fits(t, window):
        dev = t[a:b] - fit
        if _on_clock(dev, med, max_jitter_s, half_q):
            out[a:b] = fit
            continue
        glitches = _isolated_glitches(dev, half_q, max_jitter_s)
        if glitches is not None and _on_clock(dev[~glitches], med, max_jitter_s, half_q):
            seg = t[a:b].copy()
            seg[glitches] = fit[glitches]      # the wrong stamps out of the clock's fit
            out[a:b] = _line_fit(seg, window)
    # the fit must keep the stamps increasing
    if np.any(np.diff(out) <= 0):
        return t.copy()
    return out


def _on_clock(dev: np.ndarray, med: float, max_jitter_s: float, half_q: float) -> bool:
    """Whether a segment's deviations from its clock fit (s) are stamp jitter
    (:func:`dejitter_times_s`): a robust scale within ``max_jitter_s``, or the rounding of the
    stamps to a step 2·``half_q`` — within q/2 (and a millisecond rounding's slack: the clock
    and its fit are not exact), spread over that range as rounding spreads them (not two
    values ±q/2: alternating steps) — and none a quarter step ``med`` or more off."""
    largest = np.max(np.abs(dev))
    rounding = (half_q > 0 and largest <= half_q + ROUNDING_JITTER_S
                and np.mean(np.abs(dev) < 0.5 * half_q) >= 0.3)
    return bool((_robust_scale(dev) <= max_jitter_s or rounding) and largest < 0.25 * med)


#: Most stamps of a segment that may be glitches (a share; at least one)
MAX_GLITCH_SHARE = 1e-3


def _isolated_glitches(dev: np.ndarray, half_q: float, max_jitter_s: float) -> np.ndarray | None:
    """The stamps of a segment that a logger's hiccup put off the clock, or None.

    A stamp far off the clock fit (beyond ``max_jitter_s`` and the rounding's reach, q/2 +
    1.5 ms — six robust scales of the deviations for stamps rounded to no step) while its
    neighbours are on it is a wrong stamp, not a sample taken off the instrument's clock: an
    instrument that sampled irregularly shows it on many stamps.
    Up to :data:`MAX_GLITCH_SHARE` of a segment's stamps, none adjacent to another; left on
    their stamps they kept the whole segment there (three 20 ms glitches a flight in stamps
    rounded to 10 ms: 3.76 mGal against 3.68 on seed 30's white regime)."""
    bound = max(max_jitter_s, half_q + ROUNDING_JITTER_S if half_q > 0 else 6.0 * _robust_scale(dev))
    far = np.abs(dev) > bound
    n = int(far.sum())
    if n == 0 or n > max(1, int(MAX_GLITCH_SHARE * dev.size)) or np.any(far[1:] & far[:-1]):
        return None
    return far


def sample_boundaries_s(t_s) -> np.ndarray:
    """Boundaries of the averaging intervals of centre-stamped samples (s).

    Interior boundaries are midpoints of consecutive stamps; the outer two are
    extrapolated by half the neighbouring interval.

    Parameters
    ----------
    t_s : ndarray, shape (n,)

    Returns
    -------
    ndarray, shape (n + 1,)
    """
    t = np.asarray(t_s, dtype=float)
    if t.size < 2:
        raise ValueError("need at least two gravimeter samples")
    mid = 0.5 * (t[1:] + t[:-1])
    return np.concatenate([[t[0] - (mid[0] - t[0])], mid, [t[-1] + (t[-1] - mid[-1])]])


@dataclass(frozen=True)
class IntegratedSeries:
    """Cumulative integral of a centre-stamped interval-mean series.

    Attributes
    ----------
    spline : CubicSpline
        ``F(t)`` in (m/s²)·s through the interval boundaries; ``F'`` ≈ f'(t).
    t_first_s, t_last_s : float
        Time span covered by the samples (outer boundaries).
    """

    spline: CubicSpline
    t_first_s: float
    t_last_s: float

    def integral(self, t_s):
        """F(t): ∫ f' dt from the first boundary (m/s²·s)."""
        return self.spline(np.asarray(t_s, dtype=float))

    def value(self, t_s):
        """f'(t) = F'(t): smooth point value of the series (m/s²)."""
        return self.spline(np.asarray(t_s, dtype=float), 1)

    @cached_property
    def double_integral(self):
        """∫F dt (m/s²·s²) as a piecewise polynomial, made once: :func:`double_integral_m` is
        called for every trial offset of every time-offset fit of a heights-only flight."""
        return self.spline.antiderivative()

    @property
    def step_s(self) -> float:
        """Median sampling interval (s) of the series (its boundaries' spacing)."""
        return float(np.median(np.diff(self.spline.x)))


def integrate_samples(t_s, f, dejitter: bool = True) -> IntegratedSeries:
    """Build the cumulative-integral interpolant of an interval-mean series.

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        Centre time stamps (s), strictly increasing.
    f : ndarray, shape (n,)
        Sample values (interval means), e.g. specific force in m/s².
    dejitter : bool
        Apply :func:`dejitter_times_s` to the stamps first.

    Returns
    -------
    IntegratedSeries
    """
    t = np.asarray(t_s, dtype=float)
    y = np.asarray(f, dtype=float)
    if t.shape != y.shape or t.ndim != 1:
        raise ValueError("t_s and f must be 1-D arrays of the same length")
    if not np.all(np.isfinite(y)):
        raise ValueError("gravimeter samples contain NaN or inf")
    if np.any(np.diff(t) <= 0):
        raise ValueError("gravimeter time stamps must be strictly increasing")
    if dejitter:
        t = dejitter_times_s(t)
    b = sample_boundaries_s(t)
    # Remove the mean level before accumulating to keep F well conditioned.
    level = float(np.mean(y))
    F = np.concatenate([[0.0], np.cumsum((y - level) * np.diff(b))])
    t0 = b[0]
    inner = CubicSpline(b - t0, F, bc_type="not-a-knot")
    # Re-express with the level added back: F_total(t) = F(t) + level·(t − t0).
    c = inner.c.copy()
    c[-2] += level          # linear coefficient of each piece gets + level
    c[-1] += level * (b[:-1] - t0)  # constant term: level·(x_i − t0)
    spline = CubicSpline.construct_fast(c, b, extrapolate=False)
    return IntegratedSeries(spline=spline, t_first_s=float(b[0]), t_last_s=float(b[-1]))


def _check_response(tau_s: float, scale: float) -> None:
    """The lag (s, ≥ 0) and scale (> 0) of the instrument's response, checked at the edge."""
    if tau_s < 0:
        raise ValueError(f"tau_s must be >= 0, got {tau_s}")
    if not scale > 0:
        raise ValueError(f"scale must be > 0, got {scale}")


def interval_means(series: IntegratedSeries, t_epochs_s, tau_s: float = 0.0, scale: float = 1.0,
                   time_offset_s: float = 0.0) -> np.ndarray:
    """Mean of ``f_g = τ·ḟ' + k·f'`` over each GNSS interval ``(t_{k−1}, t_k]`` (m/s²).

    With ``tau_s = 0`` and ``scale = 1`` this is the plain interval mean of the
    series.  The first epoch (no previous epoch) and epochs outside the
    gravimeter's time span are NaN.

    Parameters
    ----------
    series : IntegratedSeries
        From :func:`integrate_samples`.
    t_epochs_s : ndarray, shape (n,)
        GNSS epoch times (s), strictly increasing.
    tau_s : float
        Lag time constant τ of the instrument (s), ≥ 0.
    scale : float
        Scale k (dimensionless), > 0.
    time_offset_s : float
        Added to the gravimeter's time scale to align it with GNSS time: the
        gravimeter sample stamped ``t`` belongs to GNSS time ``t + offset``.

    Returns
    -------
    ndarray, shape (n,)
    """
    _check_response(tau_s, scale)
    t = np.asarray(t_epochs_s, dtype=float) - float(time_offset_s)
    inside = (t >= series.t_first_s) & (t <= series.t_last_s)
    tc = np.clip(t, series.t_first_s, series.t_last_s)
    F = series.integral(tc)
    out = np.full(t.shape, np.nan)
    if t.size < 2:
        return out
    dt = np.diff(t)
    mean = scale * np.diff(F) / dt
    if tau_s > 0:
        fv = series.value(tc)
        mean = mean + tau_s * np.diff(fv) / dt
    ok = inside[1:] & inside[:-1]
    out[1:] = np.where(ok, mean, np.nan)
    return out


def double_integral_m(series: IntegratedSeries, t_epochs_s, tau_s: float = 0.0, scale: float = 1.0,
                      time_offset_s: float = 0.0) -> np.ndarray:
    """``∫∫ f_g dt²`` from the series' first boundary to each epoch (m), ``f_g = τ·ḟ' + k·f'``.

    The integral of ``f_g`` is ``G = k·F + τ·f'`` (:func:`interval_means` differences it on
    the GNSS intervals); its integral is ``k·∫F dt + τ·F``, evaluated exactly on the piecewise
    cubic ``F``.  Sampled at the GNSS epochs it does not depend on how the aircraft moved
    between them, which the double integral of the interval means (a sum over the epochs)
    does: at 1 Hz that sum misses by half an interval times the error of the spline's
    velocity, several cm under turbulence.

    Parameters
    ----------
    series : IntegratedSeries
    t_epochs_s : ndarray, shape (n,)
        GNSS epoch times (s).
    tau_s, scale, time_offset_s : float
        As in :func:`interval_means`.

    Returns
    -------
    ndarray, shape (n,)
        NaN outside the gravimeter's span.
    """
    _check_response(tau_s, scale)
    t = np.asarray(t_epochs_s, dtype=float) - float(time_offset_s)
    inside = (t >= series.t_first_s) & (t <= series.t_last_s)
    tc = np.clip(t, series.t_first_s, series.t_last_s)
    out = scale * series.double_integral(tc) + tau_s * series.integral(tc)
    return np.where(inside, out, np.nan)


def motion_compensated_means(series: IntegratedSeries, t_epochs_s, vu_ms, tau_s: float = 0.0,
                             scale: float = 1.0, time_offset_s: float = 0.0) -> np.ndarray:
    """Interval means of ``f_g`` on the GNSS intervals for a gravimeter sampled **slower** than the
    GNSS (m/s²), formed so that the aircraft's acceleration cancels before any interpolation.

    :func:`interval_means` interpolates ``F = ∫ f' dt`` between the sample boundaries; when those
    are farther apart than the GNSS epochs the spline cannot know how the aircraft's acceleration
    (0.1–0.5 m/s² at 0.2–2 Hz) moved ``F`` inside a sample interval, and that interpolation error,
    differenced on the GNSS intervals, is a velocity-like error of its own in ``z`` (on a 1 Hz
    interval-mean record beside 10 Hz GNSS it was larger than the GNSS's velocity error).  Here
    the difference ``D(t) = G(t) − V(t)`` — ``G = k·F + τ·f'`` the integral of ``f_g``, ``V`` the
    GNSS vertical velocity — is formed where ``G`` is known exactly, at the sample boundaries
    (``V`` there from the cubic spline through the GNSS velocities, which resolve the motion), and
    only ``D`` (the integral of ``γ + δg − E`` and of the errors: smooth) is interpolated to the
    epochs.  The returned means are ``ΔD/Δt + ΔV/Δt`` on ``(t_{k−1}, t_k]``, so that
    :func:`app.core.measurement.anomaly_measurement_mgal`, which subtracts ``ΔV/Δt``, gets
    ``z = ΔD/Δt − γ + E``.

    Parameters
    ----------
    series : IntegratedSeries
    t_epochs_s : ndarray, shape (n,)
        GNSS epoch times (s), strictly increasing.
    vu_ms : ndarray, shape (n,)
        GNSS vertical velocity (m/s, up) at the epochs; NaN epochs are left out of its spline.
    tau_s, scale, time_offset_s : float
        As in :func:`interval_means`.

    Returns
    -------
    ndarray, shape (n,)
        NaN at the first epoch and outside the gravimeter's span (as :func:`interval_means`).
    """
    _check_response(tau_s, scale)
    t = np.asarray(t_epochs_s, dtype=float)
    v = np.asarray(vu_ms, dtype=float)
    if t.shape != v.shape or t.ndim != 1:
        raise ValueError("t_epochs_s and vu_ms must be 1-D arrays of the same length")
    out = np.full(t.shape, np.nan)
    ok_v = np.isfinite(v)
    if t.size < 2 or ok_v.sum() < 4:
        return out
    b = series.spline.x                               # sample boundaries, gravimeter time
    bg = b + float(time_offset_s)                     # … in GNSS time
    tv = t[ok_v]
    use = (bg >= tv[0]) & (bg <= tv[-1])
    if use.sum() < 4:
        return out
    G = scale * series.integral(b[use])
    if tau_s > 0:
        G = G + tau_s * series.value(b[use])
    D = G - CubicSpline(tv, v[ok_v])(bg[use])
    te = t - float(time_offset_s)
    # the outermost GNSS epochs may lie up to one sample interval beyond the boundaries used:
    # D (smooth) is extrapolated that far
    reach = series.step_s
    inside = ((t >= bg[use][0] - reach) & (t <= bg[use][-1] + reach)
              & (te >= series.t_first_s) & (te <= series.t_last_s))
    Dt = CubicSpline(bg[use], D)(np.clip(t, bg[use][0] - reach, bg[use][-1] + reach))
    dt = np.diff(t)
    mean = (np.diff(Dt) + np.diff(v)) / dt
    ok = inside[1:] & inside[:-1]
    out[1:] = np.where(ok, mean, np.nan)
    return out


def height_matched_means(series: IntegratedSeries, t_epochs_s, runs, tau_s: float = 0.0, scale: float = 1.0,
                         time_offset_s: float = 0.0) -> np.ndarray:
    """Means of ``f_g`` on the GNSS intervals as GNSS **heights** see the motion (m/s²), for a record
    whose vertical velocity was derived from its heights.

    Where the GNSS has heights only, ``V`` is the derivative of the not-a-knot cubic spline through
    the heights of each contiguous run (:func:`app.core.geodesy.vertical_velocity_from_heights_ms`),
    and ``(V_k − V_{k−1})/Δt`` is the mean acceleration of that spline, not of the aircraft: at
    1–2 Hz the heights are point samples of a motion with power up to ~1 Hz (turbulence), which the
    spline cannot follow, and :func:`interval_means` — the aircraft's true mean acceleration —
    then differs from it by far more than the anomaly.  Here the gravimeter's double integral
    ``∫∫ f_g dt²`` (:func:`double_integral_m`, exact at the epochs) is sampled at the same epochs
    and put through the same spline operator, so the aircraft's motion, which both the heights and
    the double integral contain in full, cancels in ``z`` however coarsely the epochs sample it.
    What is left is the twice-integrated anomaly (smooth, so the spline keeps it) and the errors.

    Per run of ``runs`` (index ranges ``[a, b)``, the GNSS's contiguous stretches as the heights'
    spline used them) and, within a run, per stretch where the double integral is known (the
    gravimeter's span and holes); elsewhere, and at each stretch's first epoch, the values of
    :func:`interval_means`.  A stretch's best quadratic is taken out before the spline and its
    exact mean added back (the spline reproduces cubics), so the ~10⁷ m of ``½·g·t²`` does not
    cost precision.

    Parameters
    ----------
    series : IntegratedSeries
    t_epochs_s : ndarray, shape (n,)
        GNSS epoch times (s), strictly increasing.
    runs : sequence of (int, int)
        Contiguous GNSS runs over which the heights' spline was formed.
    tau_s, scale, time_offset_s : float
        As in :func:`interval_means`.

    Returns
    -------
    ndarray, shape (n,)
        NaN at the first epoch and outside the gravimeter's span (as :func:`interval_means`).
    """
    t = np.asarray(t_epochs_s, dtype=float)
    out = interval_means(series, t, tau_s, scale, time_offset_s=time_offset_s)
    G = double_integral_m(series, t, tau_s, scale, time_offset_s=time_offset_s)
    for a, b in runs:
        ok = np.isfinite(G[a:b])
        d = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
        for s0, s1 in zip(np.flatnonzero(d == 1) + a, np.flatnonzero(d == -1) + a):
            if s1 - s0 < 4:
                continue
            x = t[s0:s1] - t[s0]
            span = max(float(x[-1]), 1e-9)
            c = np.polyfit(x / span, G[s0:s1], 2)            # c[0]·(x/span)² + …: mean acceleration 2·c[0]/span²
            v = vertical_velocity_from_heights_ms(t[s0:s1], G[s0:s1] - np.polyval(c, x / span))
            out[s0 + 1:s1] = np.diff(v) / np.diff(x) + 2.0 * c[0] / span ** 2
    return out


def apply_first_order_lag(t_s, f, tau_s: float, scale: float = 1.0, f0=None) -> np.ndarray:
    """Pass a finely, uniformly sampled signal through ``τ·ẏ + k·y = f``.

    Exact for an input that is linear between samples.  A forward model for
    the simulator and the tests (the pipeline inverts it in :func:`interval_means`).

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        Uniformly spaced sample times (s), step fine compared with τ.
    f : ndarray, shape (n,)
        Input signal.
    tau_s : float
        Time constant (s); 0 returns ``f / k``.
    scale : float
        k, > 0.
    f0 : float, optional
        Initial output; the steady state ``f[0]/k`` when None.

    Returns
    -------
    ndarray, shape (n,)
    """
    from scipy.signal import lfilter

    t = np.asarray(t_s, dtype=float)
    u = np.asarray(f, dtype=float)
    if tau_s <= 0:
        return u / scale
    h = np.diff(t)
    if h.size == 0:
        return u / scale
    step = float(np.mean(h))
    if np.max(np.abs(h - step)) > 1e-9 * max(1.0, abs(t[-1])):
        raise ValueError("apply_first_order_lag needs uniformly spaced samples")
    a = scale / tau_s
    e = np.exp(-a * step)
    # Exact discretisation for piecewise-linear input (first-order hold):
    # y[i+1] = e·y[i] + b0·u[i+1] + b1·u[i]
    b0 = (1.0 - (1.0 - e) / (a * step)) / scale
    b1 = ((1.0 - e) / (a * step) - e) / scale
    y0 = u[0] / scale if f0 is None else float(f0)
    zi = np.array([e * y0 + b1 * u[0]])
    y_rest, _ = lfilter([b0, b1], [1.0, -e], u[1:], zi=zi)
    return np.concatenate([[y0], y_rest])


@dataclass(frozen=True)
class TimeOffsetFit:
    """Result of :func:`fit_time_offset`.

    Attributes
    ----------
    offset_s : float
        Gravimeter stamp + offset = GNSS time (s).
    correlation : float
        Correlation of the aligned band-passed accelerations.
    se_s : float
        Standard error of the offset (s), from the curvature of the residual variance and
        the band's effective number of independent samples ``2·B·T``.
    cost_zero, cost_min : float
        Mean square band-passed residual (m²/s⁴) with no offset and at the estimate.
    gain : float
        How many m/s² of the aligned band-passed gravimeter specific force one m/s² of GNSS
        acceleration is: the inverse of the least-squares slope of the GNSS acceleration on the
        gravimeter's, whose band holds far less noise (dimensionless, ≈ 1: both are the aircraft's
        acceleration; 0.3048 at every frequency when the GNSS heights and velocities are in feet;
        a lag declared wrong lowers it too, by frequency: τ 2 s declared 0 gave 0.35–0.38).
    gain_low, gain_low_correlation : float
        The same gain, and the correlation, in :data:`GAIN_LOW_BAND_HZ`, where a lag mismatch of a
        few seconds hardly moves the amplitude (τ 2 s declared 0: 0.98–1.02; GNSS in feet: 0.30–0.33);
        noisier (clean surveys 0.99–1.26, heights-only records in feet down to correlation 0.14).
    """

    offset_s: float
    correlation: float
    se_s: float
    cost_zero: float
    cost_min: float
    gain: float = float("nan")
    gain_low: float = float("nan")
    gain_low_correlation: float = float("nan")

    @property
    def relative_improvement(self) -> float:
        """Share of the band-passed residual variance the offset removes."""
        return float((self.cost_zero - self.cost_min) / self.cost_zero) if self.cost_zero > 0 else 0.0


def estimate_time_offset_s(series: IntegratedSeries, t_epochs_s, vu_ms, tau_s: float = 0.0,
                           scale: float = 1.0, max_offset_s: float = 2.0,
                           band_hz: tuple[float, float] = (0.01, 1.0)) -> tuple[float, float]:
    """``(offset_s, correlation)`` of :func:`fit_time_offset` (same arguments)."""
    fit = fit_time_offset(series, t_epochs_s, vu_ms, tau_s, scale, max_offset_s, band_hz)
    return fit.offset_s, fit.correlation


def fit_time_offset(series: IntegratedSeries, t_epochs_s, vu_ms, tau_s: float = 0.0,
                    scale: float = 1.0, max_offset_s: float = 2.0,
                    band_hz: tuple[float, float] = (0.01, 1.0), height_runs=None,
                    center_s: float = 0.0) -> TimeOffsetFit:
    """Time offset between gravimeter and GNSS by cross-correlation of accelerations.

    The gravimeter's interval-mean specific force and the GNSS acceleration
    ``(V_k − V_{k−1})/Δt`` share the aircraft's vertical acceleration, which is
    10⁴ times the anomaly.  Both are band-passed (``band_hz``); a coarse search
    of the cross-correlation over whole GNSS steps is refined to sub-millisecond
    by minimising the band-passed residual variance over the offset.

    Parameters
    ----------
    series : IntegratedSeries
    t_epochs_s, vu_ms : ndarray, shape (n,)
        GNSS epochs (s) and vertical velocity (m/s).
    tau_s, scale : float
        Instrument lag and scale used for the interval means.
    max_offset_s : float
        Search range ±max_offset_s.
    band_hz : (float, float)
        Pass band for the comparison (Hz).
    height_runs : sequence of (int, int), optional
        When ``vu_ms`` was derived from heights: the runs of its spline, and the gravimeter's
        side is :func:`height_matched_means` (the motion seen as the heights see it).
    center_s : float
        The search is ``center_s ± max_offset_s`` (s): a window of a flight searched about the
        flight's own offset (:mod:`app.core.clock`).

    Returns
    -------
    TimeOffsetFit
        ``offset_s`` to pass as ``time_offset_s`` to :func:`interval_means`
        (gravimeter stamp + offset = GNSS time), the correlation coefficient
        of the aligned band-passed signals, its standard error and the residual
        variances with and without it.
    """
    from scipy.optimize import minimize_scalar

    t = np.asarray(t_epochs_s, dtype=float)
    v = np.asarray(vu_ms, dtype=float)
    if t.size < 200:
        raise ValueError("need at least 200 GNSS epochs to estimate the time offset")
    dt = float(np.median(np.diff(t)))
    fs = 1.0 / dt
    lo, hi = band_hz
    hi = min(hi, 0.45 * fs)
    band = band_filter(float(lo), float(hi), fs)
    acc = np.full(t.shape, np.nan)
    acc[1:] = np.diff(v) / np.diff(t)
    # at most an eighth of the record either way, so the compared stretch keeps 3/4 of it
    max_offset_s = min(float(max_offset_s), 0.125 * (t[-1] - t[0]))
    margin = int(np.ceil((max_offset_s + abs(float(center_s))) / dt)) + 2
    sl = slice(margin, t.size - margin)
    acc_bp = filtfilt_band(band, fill_nan(acc))[sl]

    def grav_bp(offset):
        f = gnss_side_means(series, t, tau_s, scale, offset, height_runs)
        return filtfilt_band(band, fill_nan(f))[sl]

    g0 = grav_bp(float(center_s))
    # shifting the gravimeter by +offset moves its features later: g(t − offset)
    best = float(center_s) + _coarse_lag(g0, acc_bp, int(np.ceil(max_offset_s / dt))) * dt

    def cost(offset):
        r = grav_bp(offset) - acc_bp
        return float(np.mean(r * r))

    res = minimize_scalar(cost, bounds=(best - 1.5 * dt, best + 1.5 * dt), method="bounded",
                          options={"xatol": 1e-4})
    off = float(res.x)
    g = grav_bp(off)
    corr = float(np.corrcoef(g, acc_bp)[0, 1])
    # the GNSS acceleration carries the noise (differenced velocities or heights), the gravimeter's
    # band-passed force hardly any: regress the former on the latter, so its noise does not bias
    gain = float(np.sum(g * g) / np.sum(g * acc_bp))
    gain_low, gain_low_corr = _low_band_gain(series, t, acc, (tau_s, scale, off), fs, sl, height_runs)
    c_min = cost(off)
    # curvature of the residual variance by a central difference (a tenth of a GNSS step)
    h = 0.1 * dt
    curv = (cost(off + h) - 2.0 * c_min + cost(off - h)) / (h * h)
    n_eff = max(2.0 * (hi - lo) * (t[sl][-1] - t[sl][0]), 1.0)
    se = float(np.sqrt(2.0 * c_min / (n_eff * curv))) if curv > 0 else float("inf")
    return TimeOffsetFit(off, corr, se, cost(0.0), c_min, gain, gain_low, gain_low_corr)


#: band (Hz) of :attr:`TimeOffsetFit.gain_low`: the aircraft's slow vertical accelerations (phugoid,
#: height holds), where a lag mismatch of a few seconds changes the gravimeter's amplitude by under ~20 %
GAIN_LOW_BAND_HZ = (0.01, 0.05)


def gnss_side_means(series: IntegratedSeries, t, tau_s: float, scale: float, offset: float,
                    height_runs=None) -> np.ndarray:
    """The gravimeter's means on the GNSS intervals (m/s²) as the GNSS sees the motion: the exact
    :func:`interval_means`, or :func:`height_matched_means` over ``height_runs`` when the GNSS
    vu came from its heights."""
    if height_runs is None:
        return interval_means(series, t, tau_s, scale, time_offset_s=offset)
    return height_matched_means(series, t, height_runs, tau_s, scale, time_offset_s=offset)


def _low_band_gain(series: IntegratedSeries, t: np.ndarray, acc: np.ndarray, response: tuple, fs: float,
                   sl: slice, height_runs=None) -> tuple[float, float]:
    """Gain and correlation of the gravimeter's interval means (``response`` = τ s, scale, time
    offset s) against the GNSS acceleration ``acc`` (m/s², per epoch ``t``) in :data:`GAIN_LOW_BAND_HZ`,
    over the epochs ``sl``; the gain is ``Σ g² / Σ g·a`` (the GNSS side regressed on the
    gravimeter's: its noise does not bias it), two periods of the band's low edge left out at both
    ends (the filters' transients).  NaNs when the band is above the GNSS's Nyquist or the record
    shorter than eight such periods."""
    lo, hi = GAIN_LOW_BAND_HZ
    if not hi < 0.45 * fs:
        return float("nan"), float("nan")
    band = band_filter(float(lo), float(hi), float(fs))
    tau_s, scale, off = response
    g = filtfilt_band(band, fill_nan(gnss_side_means(series, t, tau_s, scale, off, height_runs)))[sl]
    a = filtfilt_band(band, fill_nan(acc))[sl]
    edge = int(round(2.0 / lo * fs))   # two periods of the band's low edge: the filters' end transients
    if g.size < 4 * edge:
        return float("nan"), float("nan")
    g, a = g[edge:-edge], a[edge:-edge]
    den = float(np.sum(g * a))
    if not den > 0:
        return float("nan"), float(np.corrcoef(g, a)[0, 1])
    return float(np.sum(g * g) / den), float(np.corrcoef(g, a)[0, 1])


@lru_cache(maxsize=64)
def band_filter(lo_hz: float, hi_hz: float, fs_hz: float) -> tuple[np.ndarray, np.ndarray, int]:
    """A 4th-order Butterworth band-pass ``[lo_hz, hi_hz]`` at ``fs_hz`` (second-order sections),
    its steady-state initial conditions (``sosfilt_zi``) and the odd-extension length SciPy's
    ``sosfiltfilt`` pads with: made once per band and rate, shared (never modified) — the time-offset fit
    filters the same band hundreds of times per flight (:func:`filtfilt_band`)."""
    sos = butter(4, [lo_hz, hi_hz], btype="band", fs=fs_hz, output="sos")
    zi = sosfilt_zi(sos)
    ntaps = 2 * sos.shape[0] + 1 - min(int((sos[:, 2] == 0).sum()), int((sos[:, 5] == 0).sum()))
    zi.setflags(write=False)   # (SciPy's sosfilt needs a writable sos: not to be modified either)
    return sos, zi, 3 * ntaps


def filtfilt_band(band: tuple[np.ndarray, np.ndarray, int], x) -> np.ndarray:
    """Zero-phase filtering of the 1-D ``x`` by ``band`` (:func:`band_filter`): the same
    operations as ``scipy.signal.sosfiltfilt(sos, x)`` with its default odd padding (the
    result is identical), without designing the filter and solving for its initial
    conditions on every call."""
    sos, zi, edge = band
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or x.shape[0] <= edge:
        raise ValueError(f"The length of the input vector x must be greater than padlen, which is {edge}.")
    ext = np.concatenate((2 * x[0:1] - x[edge:0:-1], x, 2 * x[-1:] - x[-2:-(edge + 2):-1]))
    y, _ = sosfilt(sos, ext, zi=zi * ext[0:1])
    y, _ = sosfilt(sos, y[::-1], zi=zi * y[-1:])
    return y[::-1][edge:-edge]


def fill_nan(x):
    """Linear interpolation over non-finite samples by index (edges: nearest value).

    Raises ValueError when no sample is finite."""
    x = np.asarray(x, dtype=float).copy()
    bad = ~np.isfinite(x)
    if bad.all():
        raise ValueError("no finite value to interpolate from")
    if bad.any():
        idx = np.arange(x.size)
        x[bad] = np.interp(idx[bad], idx[~bad], x[~bad])
    return x


def _coarse_lag(g, a, nlag: int) -> int:
    """The shift (samples, |lag| ≤ nlag) of ``g`` later that correlates best with ``a``:
    the FFT cross-correlation, each lag's sum divided by its overlap (a ±60 s search at
    20 Hz is 2 400 lags)."""
    from scipy.signal import correlate, correlation_lags

    g = g - g.mean()
    a = a - a.mean()
    c = correlate(a, g, mode="full", method="fft")
    lags = correlation_lags(a.size, g.size, mode="full")
    keep = np.abs(lags) <= nlag
    c, lags = c[keep], lags[keep]
    return int(lags[int(np.argmax(c / (a.size - np.abs(lags))))])
