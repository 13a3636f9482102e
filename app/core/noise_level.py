"""Local GNSS velocity-noise level R(t) from the high-frequency content of z.

Above ~0.5 Hz the measurement ``z_k = δg_k − 1000·(r_k − r_{k−1})/Δt`` is pure noise
(the anomaly at flight height has no power there), so the local variance of the
second difference of z measures the GNSS noise level directly, at full rate and with
thousands of samples per kilometre — far more precisely than a noise state recognised
on the decimated grid.  For white r of variance R (cm/s)²,
``∇z_k = −1000·(r_k − 2r_{k−1} + r_{k−2})/Δt`` has variance ``6·10⁶·R/Δt²``.

Other white errors (gravimeter sensor noise) are lumped into the same effective R,
which is what the smoother needs.  A global factor between this effective level and
the in-band level (coloured GNSS noise) is estimated later from the EM on the
regularized band.

:func:`band_noise_variance_cm2s2` measures the same equivalent-white level in a band
just above the anomaly's (default 0.1–0.5 Hz) instead of near the Nyquist frequency:
GNSS velocities differenced from positions have far less noise there than near the
Nyquist frequency, and the smoother works at low frequency.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.ndimage import uniform_filter1d

from app.core.epochs import run_bounds


def _check_series(z_mgal, dt_s: float, min_epochs: int) -> np.ndarray:
    z = np.asarray(z_mgal, dtype=float)
    if z.ndim != 1:
        raise ValueError("z_mgal must be one-dimensional")
    if not dt_s > 0:
        raise ValueError("dt_s must be positive")
    if z.size < min_epochs:
        raise ValueError(f"need at least {min_epochs} epochs to estimate the noise level")
    return z


def _windowed_mean_square(y, ok, w: int) -> np.ndarray:
    """Centred running mean of y² over the epochs where ``ok`` (window of w epochs,
    reflected at the ends); NaN-free: gaps take the median level."""
    num = uniform_filter1d(np.where(ok, y * y, 0.0), w, mode="reflect")
    den = uniform_filter1d(ok.astype(float), w, mode="reflect")
    var = np.where(den > 0.2, num / np.maximum(den, 1e-12), np.nan)
    if not np.isfinite(var).any():
        raise ValueError("no finite values to estimate the noise level from")
    return np.where(np.isfinite(var), var, np.nanmedian(var))


def local_noise_variance_cm2s2(z_mgal, dt_s: float, window_s: float = 20.0,
                               floor_cm2s2: float = 1e-4) -> np.ndarray:
    """Local R(t) in (cm/s)² at every epoch.

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
        The measurement (mGal); NaN allowed (ignored).
    dt_s : float
        GNSS step (s).
    window_s : float
        Length of the centred averaging window (s).
    floor_cm2s2 : float
        Lower bound of the returned values.

    Returns
    -------
    ndarray, shape (n,)
    """
    z = _check_series(z_mgal, dt_s, 8)
    dz = np.diff(z)
    var = _windowed_mean_square(dz, np.isfinite(dz), max(3, int(round(window_s / dt_s))))
    r = var * dt_s * dt_s / 6.0e6
    r = np.concatenate([[r[0]], r])
    return np.maximum(r, floor_cm2s2)


def white_band_gain(dt_s: float, band_hz: tuple[float, float], order: int = 4) -> float:
    """Variance (mGal²) of z's band-passed GNSS noise per unit white R ((cm/s)²).

    Parameters
    ----------
    dt_s : float
        GNSS step (s).
    band_hz : (float, float)
        Pass band (Hz).
    order : int
        Butterworth order (of each pass of the zero-phase filter).

    Notes
    -----

    For white r of variance R, ``n_k = −1000·(r_k − r_{k−1})/Δt`` has the two-sided PSD
    ``(1000/Δt)²·R·Δt·4 sin²(πfΔt)``; the zero-phase Butterworth band-pass of
    :func:`band_noise_variance_cm2s2` multiplies it by ``|H(f)|⁴``.
    """
    from scipy.signal import butter, sosfreqz

    sos = butter(order, band_hz, btype="bandpass", fs=1.0 / dt_s, output="sos")
    f, h = sosfreqz(sos, worN=1 << 16, fs=1.0 / dt_s)
    s = (1.0e3 / dt_s) ** 2 * dt_s * 4.0 * np.sin(np.pi * f * dt_s) ** 2 * np.abs(h) ** 4
    return float(2.0 * np.trapezoid(s, f))


#: Periods of the band's lower edge at either end of a run left out of its mean square (the
#: band-pass's transient there; `band_noise_variance_cm2s2`).
EDGE_CYCLES = 0.5


def band_noise_variance_cm2s2(z_mgal, dt_s: float, band_hz: tuple[float, float] = (0.1, 0.5),
                              window_s: float = 60.0, floor_cm2s2: float = 1e-4,
                              regressor_mgal=None, lags: int = 5, t_s=None) -> np.ndarray:
    """Local R(t) in (cm/s)² from z's content just above the anomaly's band.

    The high-frequency estimate of :func:`local_noise_variance_cm2s2` sees the GNSS noise
    near the Nyquist frequency; when that noise is not white (velocities differenced
    from positions: less power at low frequency; Gauss–Markov errors: more), its level
    there says little about the level where the smoother separates anomaly from noise.
    Here z is band-passed (zero-phase Butterworth, ``band_hz``), squared, averaged over
    ``window_s`` and divided by the band's gain for white R (:func:`white_band_gain`):
    the *equivalent white* R just above the anomaly band.

    With ``regressor_mgal`` (the gravimeter's specific force) the band-passed z first loses
    its least-squares fit on the band-passed regressor at lags ``−lags…lags``: the part of z
    linear in the aircraft's acceleration, where the gravimeter's and the GNSS's responses
    differ (an internal filter, interval means against point samples, a residual lag or
    scale).  That part follows the turbulence, its gain falls as f² below the band, and it
    is not the noise the smoother must weigh in the anomaly band.  The regressor holds no GNSS
    noise, so the fit cannot take GNSS noise away.

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
        The measurement (mGal); NaN ignored.  Each run of finite epochs (:func:`run_bounds`)
        is band-passed on its own: interpolated across a gap, a record whose noise is
        10⁴ mGal puts a ramp from one noise value to the next into the band, and R(t) came
        out 7× (a 0.5 s hole at 10 Hz) to 150× (30 s) too large within 15 s of it.  A run
        shorter than ``2 / band_hz[0]`` has no level of its own (its neighbours' within the
        window, else the record's median) unless no run is that long.
    dt_s : float
        GNSS step (s).
    band_hz : (float, float)
        Pass band (Hz); must lie below the Nyquist frequency.
    window_s : float
        Length of the centred averaging window (s).
    floor_cm2s2 : float
        Lower bound of the returned values.
    regressor_mgal : ndarray, shape (n,), optional
        The gravimeter's specific force at the same epochs (mGal; NaN allowed).
    lags : int
        Lags each side of the fit (epochs).
    t_s : ndarray, shape (n,), optional
        Epoch times (s): a jump of the clock also ends a run.

    Returns
    -------
    ndarray, shape (n,)
    """
    from scipy.signal import butter

    z = _check_series(z_mgal, dt_s, 64)
    f1, f2 = float(band_hz[0]), float(band_hz[1])
    if not 0 < f1 < f2 < 0.5 / dt_s:
        raise ValueError(f"band_hz must satisfy 0 < f1 < f2 < Nyquist ({0.5 / dt_s} Hz), got {band_hz}")
    ok = np.isfinite(z)
    if not ok.any():
        raise ValueError("no finite measurements to estimate the noise level from")
    sos = butter(4, (f1, f2), btype="bandpass", fs=1.0 / dt_s, output="sos")
    padlen = int(round(4.0 / (f1 * dt_s)))
    runs = run_bounds(ok, t_s)
    runs = [(a, b) for a, b in runs if (b - a) * dt_s >= 2.0 / f1] or runs   # none so long: every run
    y = _band_pass_runs(z, runs, sos, padlen)
    if regressor_mgal is not None:
        y = y - _band_regression(y, np.isfinite(y), regressor_mgal, sos, padlen, lags, runs)
    inner = np.isfinite(y)
    edge = int(round(EDGE_CYCLES / (f1 * dt_s)))
    for a, b in runs:                            # the filter's transient at a run's ends
        inner[a:min(b, a + edge)] = inner[max(a, b - edge):b] = False
    use = inner if inner.any() else np.isfinite(y)
    w = max(3, int(round(window_s / dt_s)))
    var = np.full(z.size, np.nan)
    for a, b in run_bounds(np.ones(z.size, bool), t_s):   # averaged across holes, not clock jumps
        if use[a:b].any():
            var[a:b] = _windowed_mean_square(y[a:b], use[a:b], w)
    var = np.where(np.isfinite(var), var, np.nanmedian(var))
    return np.maximum(var / white_band_gain(dt_s, (f1, f2)), floor_cm2s2)


def _band_pass_runs(x: np.ndarray, runs, sos, padlen: int) -> np.ndarray:
    """``sos`` (zero phase, even padding) applied to each run of ``x`` on its own, its mean
    removed (NaN inside a run interpolated over); NaN outside the runs."""
    from scipy.signal import sosfiltfilt

    y = np.full(x.size, np.nan)
    for a, b in runs:
        u = x[a:b]
        fin = np.isfinite(u)
        if fin.sum() < 2:
            continue
        if not fin.all():
            u = np.interp(np.arange(u.size), np.flatnonzero(fin), u[fin])
        y[a:b] = sosfiltfilt(sos, u - np.mean(u), padtype="even", padlen=min(u.size - 1, padlen))
    return y


def _band_regression(y, ok, regressor_mgal, sos, padlen: int, lags: int, runs) -> np.ndarray:
    """The part of the band-passed ``y`` linear in the regressor band-passed over the same
    ``runs`` at lags ±L (least squares over the epochs where ``ok``, the regressor and every
    lag are finite); zeros when too few epochs."""
    x = np.asarray(regressor_mgal, dtype=float)
    if x.shape != y.shape:
        raise ValueError(f"regressor_mgal has shape {x.shape}, z_mgal {y.shape}")
    fin = np.isfinite(x)
    n, L = y.size, int(lags)
    if fin.sum() < 10 * (2 * L + 1) or n <= 2 * L + 2:
        return np.zeros(n)
    xb = _band_pass_runs(x, runs, sos, padlen)
    k = np.arange(L, n - L)
    X = np.column_stack([xb[k + lag] for lag in range(-L, L + 1)])
    use = ok[k] & fin[k] & np.all(np.isfinite(X), axis=1)
    if use.sum() < 10 * X.shape[1]:
        return np.zeros(n)
    c, *_ = np.linalg.lstsq(X[use], y[k][use], rcond=None)
    out = np.zeros(n)
    whole = np.all(np.isfinite(X), axis=1)
    out[k[whole]] = X[whole] @ c
    return out


def _band_passed(z: np.ndarray, dt_s: float, sos: np.ndarray, edge: int,
                 order: int | None = None) -> tuple[np.ndarray, int]:
    """``sos`` (zero phase) applied to a stretch of z directly, through its integral and
    through its double integral (each with a polynomial of its order removed, the result
    differentiated back; see :func:`band_rms_mgal`): of the three, the one with the least
    power inside ``edge`` samples of the ends, shape of z, and its integration order (0–2).
    Ringing from the ends only adds power, and the way in with the smoothest ends is the one
    with the least.  ``order`` forces one way in (the same linear filter for a second series)."""
    from scipy.signal import sosfiltfilt

    x = np.arange(z.size) * dt_s
    u = z - np.mean(z)
    best, best_ss, best_k = None, np.inf, 0
    for k in range(3 if order is None else order + 1):
        if k:
            u = np.cumsum(u) * dt_s
            u = u - np.polyval(np.polyfit(x, u, k), x)
        if order is not None and k != order:
            continue
        y = sosfiltfilt(sos, u)
        for _ in range(k):
            y = np.gradient(y, dt_s)
        ss = float(np.sum(y[edge:z.size - edge] ** 2))
        if ss < best_ss:
            best, best_ss, best_k = y, ss, k
    return best, best_k


def band_rms_mgal(z_mgal, dt_s: float, band_hz: tuple[float, float], usable=None,
                  edge_s: float = 100.0) -> tuple[float, int]:
    """RMS of z in a frequency band, over the contiguous usable stretches of a record.

    Each stretch of consecutive usable, finite epochs is band-passed on its own (zero-phase
    Butterworth of order 4) and ``edge_s`` is left out at both of its ends, where the filter
    has no data on one side; stretches shorter than ``3 * edge_s`` are skipped.  Used to
    compare two versions of the same record (e.g. z with two gravimeter lags): the
    difference is then deterministic, not a sampling effect.

    z's noise is mostly blue (a velocity error differenced: PSD ∝ f²; heights differenced
    twice: ∝ f⁴), and a stretch of blue noise cut out of a record carries its cut-off ends
    as low-frequency content that a narrow band-pass rings with for hundreds of seconds —
    band-passing z itself put 40× the true band RMS of white-velocity noise into the
    result (and 10⁴× for heights' noise), so a version of z with more noise far above the
    band looked worse in it.  The stretch's integral and double integral are band-passed
    too and differentiated back (the same linear filter, with smoother ends; but a strong
    red part — the anomaly — rings from the integrals' ends instead), and of the three the
    least band power is taken: ringing only adds.

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
        The measurement on a uniform time step (mGal).
    dt_s : float
        Time step (s).
    band_hz : (float, float)
        Pass band (Hz), ``0 < f1 < f2 <`` Nyquist.
    usable : ndarray of bool, shape (n,), optional
        Epochs that may be used (e.g. airborne); all by default.
    edge_s : float
        Time left out at each end of every stretch (s).

    Returns
    -------
    (float, int)
        The band RMS (mGal; NaN when no stretch is long enough) and the number of epochs
        it is taken over.
    """
    from scipy.signal import butter

    z = _check_series(z_mgal, dt_s, 1)
    f1, f2 = float(band_hz[0]), float(band_hz[1])
    if not 0 < f1 < f2 < 0.5 / dt_s:
        raise ValueError(f"band_hz must satisfy 0 < f1 < f2 < Nyquist ({0.5 / dt_s} Hz), got {band_hz}")
    ok = np.isfinite(z) if usable is None else np.isfinite(z) & np.asarray(usable, dtype=bool)
    if ok.shape != z.shape:
        raise ValueError(f"usable has shape {ok.shape}, z_mgal {z.shape}")
    edge = int(round(edge_s / dt_s))
    d = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    sos = butter(4, (f1, f2), btype="bandpass", fs=1.0 / dt_s, output="sos")
    total, n = 0.0, 0
    for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
        if b - a < max(3 * edge, 16):
            continue
        y = _band_passed(z[a:b], dt_s, sos, edge)[0][edge:b - a - edge]
        total += float(np.sum(y * y))
        n += y.size
    return (float(np.sqrt(total / n)) if n else float("nan")), n


class BandFit(NamedTuple):
    """Least-squares fit ``y ≈ −c·x`` of two records inside one frequency band
    (:func:`band_fit_coefficient`)."""

    coef: float              #: c, in y's unit per x's unit: ``y + c·x`` has the least band power
    se: float                #: its standard error (the band's few independent samples counted)
    rms_before_mgal: float   #: band RMS of y
    rms_after_mgal: float    #: band RMS of ``y + c·x``
    n_epochs: int            #: epochs the fit is taken over
    dof: float               #: independent samples in the band, ``2·(f2 − f1)·T``


def band_fit_coefficient(y_mgal, x, dt_s: float, band_hz: tuple[float, float], usable=None,
                         edge_s: float = 100.0) -> BandFit:
    """How much of a known regressor ``x`` a record ``y`` holds inside a frequency band.

    Both records go through the same linear filter, stretch by stretch (as in
    :func:`band_rms_mgal`: zero-phase Butterworth band-pass, entered directly or through the
    stretch's first or second integral — whichever leaves y the least power, the same way for
    x — and ``edge_s`` left out at both ends), and ``c = −Σ y_b x_b / Σ x_b²``.  The standard
    error counts the band's independent samples, ``ν = 2·(f2 − f1)·T`` over the total duration
    ``T`` of the stretches, not the epochs: ``se² = mean(r²)/mean(x_b²)/ν`` with ``r = y_b + c·x_b``.

    Used with ``y = z`` and ``x = ∂z/∂τ`` (the gravimeter's jerk): the lag that leaves the
    aircraft's motion out of z where the anomaly is estimated.

    Parameters
    ----------
    y_mgal, x : ndarray, shape (n,)
        The record (mGal) and the regressor (any unit) on the same uniform time step.
    dt_s : float
        Time step (s).
    band_hz : (float, float)
        Pass band (Hz), ``0 < f1 < f2 <`` Nyquist.
    usable : ndarray of bool, shape (n,), optional
        Epochs that may be used (both records finite there as well).
    edge_s : float
        Time left out at each end of every stretch (s).

    Returns
    -------
    BandFit
        NaN coefficient and error when no stretch is long enough or x has no band power.
    """
    from scipy.signal import butter

    y = _check_series(y_mgal, dt_s, 1)
    xr = np.asarray(x, dtype=float)
    if xr.shape != y.shape:
        raise ValueError(f"x has shape {xr.shape}, y_mgal {y.shape}")
    f1, f2 = float(band_hz[0]), float(band_hz[1])
    if not 0 < f1 < f2 < 0.5 / dt_s:
        raise ValueError(f"band_hz must satisfy 0 < f1 < f2 < Nyquist ({0.5 / dt_s} Hz), got {band_hz}")
    ok = np.isfinite(y) & np.isfinite(xr)
    if usable is not None:
        u = np.asarray(usable, dtype=bool)
        if u.shape != y.shape:
            raise ValueError(f"usable has shape {u.shape}, y_mgal {y.shape}")
        ok &= u
    edge = int(round(edge_s / dt_s))
    d = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    sos = butter(4, (f1, f2), btype="bandpass", fs=1.0 / dt_s, output="sos")
    syy = sxy = sxx = 0.0
    n = 0
    for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
        if b - a < max(3 * edge, 16):
            continue
        yb, k = _band_passed(y[a:b], dt_s, sos, edge)
        xb, _ = _band_passed(xr[a:b], dt_s, sos, edge, order=k)
        yb, xb = yb[edge:b - a - edge], xb[edge:b - a - edge]
        syy += float(yb @ yb)
        sxy += float(yb @ xb)
        sxx += float(xb @ xb)
        n += yb.size
    nan = float("nan")
    if not n or not sxx > 0:
        return BandFit(nan, nan, float(np.sqrt(syy / n)) if n else nan, nan, n, 0.0)
    c = -sxy / sxx
    ss_after = max(syy - sxy * sxy / sxx, 0.0)
    dof = 2.0 * (f2 - f1) * n * dt_s
    se = float(np.sqrt(ss_after / sxx / max(dof - 1.0, 1.0)))
    return BandFit(float(c), se, float(np.sqrt(syy / n)), float(np.sqrt(ss_after / n)), n, float(dof))



class Run(NamedTuple):
    """One stretch of :func:`elevated_runs`: samples ``start`` … ``stop − 1``."""

    start: int
    stop: int


def elevated_runs(values, t_s, threshold: float, min_duration_s: float = 0.0,
                  bridge_s: float = 0.0) -> list[Run]:
    """Stretches of a series above a threshold (the noise episodes of a line's R(t)).

    A stretch is a maximal run of consecutive samples with ``values > threshold``; two
    stretches whose gap (from the last sample of one to the first of the next) is at most
    ``bridge_s`` are one stretch; a stretch is kept when it lasts at least ``min_duration_s``,
    its duration being ``t[stop − 1] − t[start]`` plus the median sample step (one sample
    lasts one step).  NaN values are never above the threshold.

    Parameters
    ----------
    values : ndarray, shape (n,)
        The series (any unit, e.g. R(t) in (cm/s)²).
    t_s : ndarray, shape (n,)
        Sample times (s), finite and strictly increasing.
    threshold : float
        Level (the unit of ``values``).
    min_duration_s, bridge_s : float
        Shortest stretch kept, longest gap bridged (s, ≥ 0).

    Returns
    -------
    list of Run
        In time order, not overlapping.
    """
    v = np.asarray(values, dtype=float)
    t = np.asarray(t_s, dtype=float)
    if v.ndim != 1 or t.shape != v.shape:
        raise ValueError(f"values and t_s must be one-dimensional of one length, got {v.shape} and {t.shape}")
    if not np.all(np.isfinite(t)) or (t.size > 1 and not np.all(np.diff(t) > 0)):
        raise ValueError("t_s must be finite and strictly increasing")
    if not np.isfinite(threshold):
        raise ValueError(f"threshold must be finite, got {threshold}")
    if not (min_duration_s >= 0 and bridge_s >= 0):
        raise ValueError("min_duration_s and bridge_s must be >= 0")
    if v.size == 0:
        return []
    step = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    above = np.concatenate([[False], np.nan_to_num(v, nan=-np.inf) > threshold, [False]])
    edges = np.flatnonzero(np.diff(above.astype(np.int8)))
    starts, stops = edges[0::2], edges[1::2]
    runs: list[list[int]] = []
    for a, b in zip(starts, stops):
        if runs and t[a] - t[runs[-1][1] - 1] <= bridge_s:
            runs[-1][1] = int(b)
        else:
            runs.append([int(a), int(b)])
    return [Run(a, b) for a, b in runs if t[b - 1] - t[a] + step >= min_duration_s]
