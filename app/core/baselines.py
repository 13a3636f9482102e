"""Baseline filters (SPEC §2 step 6 and seed 004's FIR).

* :func:`fir_lowpass_mgal` — zero-phase windowed-sinc FIR low-pass ("FIR100s" of
  seed 004), with renormalised weights at line ends and around NaNs.
* :func:`stationary_smooth` — the seed-000 smoother with one (Q, R) pair.
* :func:`estimate_stationary_qr` — maximum-likelihood (Q, R) for one or several lines.
* :func:`gaussian_lowpass` — the Gaussian low-pass of the line profiles' z.

The seed-003 random-walk filter and the seed-004 position-domain filter, which the
product never runs, are in :mod:`app.research.random_walk_kf` and
:mod:`app.research.position_domain`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize, signal

from app.core.smoother import SmootherResult, kalman_loglik, kalman_smooth
from app.core.statespace import MGAL_PER_CMS2, _check_dt, _check_m

# ---------------------------------------------------------------------------
# FIR low-pass
# ---------------------------------------------------------------------------


def fir_kernel(dt_s: float, cutoff_period_s: float = 100.0, length_periods: float = 2.0) -> np.ndarray:
    """Blackman-windowed sinc low-pass kernel with unit DC gain.

    Parameters
    ----------
    dt_s : float
        Sample step (s).
    cutoff_period_s : float
        Cut-off period ``1/f_c`` (s); the sinc is ``2 f_c Δt · sinc(2 f_c Δt n)``.
    length_periods : float
        Kernel length in cut-off periods; the number of taps is the odd number
        ``2·round(length_periods·cutoff_period_s/(2Δt)) + 1``.  The default 2 gives, for
        100 s at 10 Hz, 2001 taps (200 s) with −6 dB at 0.0101 Hz, gain 0.88 at 0.005 Hz
        and 0.011 at 0.02 Hz.

    Returns
    -------
    ndarray, shape (L,)
        Symmetric taps (zero phase when applied centred), summing to 1.
    """
    dt = _check_dt(dt_s)
    if not (np.isfinite(cutoff_period_s) and cutoff_period_s > 2.0 * dt):
        raise ValueError(f"cutoff_period_s must exceed two samples (2·dt = {2 * dt:g} s), got {cutoff_period_s!r}")
    if not (np.isfinite(length_periods) and length_periods > 0):
        raise ValueError("length_periods must be positive")
    half = max(int(round(length_periods * cutoff_period_s / (2.0 * dt))), 1)
    n = np.arange(-half, half + 1)
    fc = dt / cutoff_period_s  # cycles per sample
    h = np.sinc(2.0 * fc * n) * np.blackman(2 * half + 1)
    return h / h.sum()


def fir_lowpass_mgal(z_mgal, dt_s: float, cutoff_period_s: float = 100.0,
                     length_periods: float = 2.0) -> np.ndarray:
    """Zero-phase FIR low-pass of a line (seed 004 "FIR100s").

    The kernel is :func:`fir_kernel` (Blackman-windowed sinc, odd length ≈ 2 cut-off
    periods, unit DC gain), applied centred, so there is no phase shift.  At the ends of
    the line and around missing samples (NaN) the output is the weighted mean over the
    samples that exist: ``y_k = Σ_j h_j x_{k−j} w_{k−j} / Σ_j h_j w_{k−j}`` with ``w = 1``
    for finite samples and 0 otherwise (renormalised weights), so every epoch gets a
    value and a constant input is returned unchanged everywhere.  An epoch whose
    available weight ``Σ h_j w_{k−j}`` is below 0.05 (a gap much longer than the kernel)
    gets NaN.  FFT (overlap-add) convolution: O(N log L).

    Parameters
    ----------
    z_mgal : array_like, shape (N,)
        Input series (any unit; mGal in the pipeline); NaN = missing.
    dt_s : float
        Sample step (s).
    cutoff_period_s : float, default 100
        Cut-off period (s); the gain there is ≈ 0.5 (−6 dB).
    length_periods : float, default 2
        Kernel length in cut-off periods.

    Returns
    -------
    ndarray, shape (N,)
    """
    x = np.asarray(z_mgal, dtype=float)
    if x.ndim != 1:
        raise ValueError(f"z_mgal must be 1-D, got shape {x.shape}")
    if x.size == 0:
        raise ValueError("z_mgal is empty")
    if np.any(np.isinf(x)):
        raise ValueError("z_mgal contains infinite values")
    h = fir_kernel(dt_s, cutoff_period_s, length_periods)
    w = np.isfinite(x).astype(float)
    xw = np.where(w > 0, x, 0.0)
    num = signal.oaconvolve(xw, h, mode="same")
    den = signal.oaconvolve(w, h, mode="same")
    out = np.full(x.shape, np.nan)
    ok = den > 0.05
    out[ok] = num[ok] / den[ok]
    return out


# ---------------------------------------------------------------------------
# Stationary smoother and ML (Q, R)
# ---------------------------------------------------------------------------


def fir_gap_error_mgal(z_mgal, dt_s: float, cutoff_period_s: float = 100.0,
                       length_periods: float = 2.0, record_ends: bool = False) -> np.ndarray:
    """How far :func:`fir_lowpass_mgal` can be from the gap-free low-pass because of missing
    samples inside the record (mGal, per epoch).

    z holds the aircraft's accelerations as the gravimeter and the GNSS disagree on them
    (10³–10⁴ mGal per sample at 2 Hz), and their sum over the kernel telescopes to a velocity
    difference; a missing sample breaks that sum and its value is not predictable from its
    neighbours (a 2 Hz platform record: lag-1 correlation 0.46).  The renormalised low-pass
    then misses it by about ``Σ_j |h_j|·|z_{k−j}|`` over the missing samples: one missing
    sample of a simulated 2 Hz test line moved FIR 100 s by up to 150 mGal.  This bound is
    ``Σ_j σ_j |h_j| (1 − w_{k−j})`` over the interior missing samples (leading and trailing
    ones are the record's ends), with ``σ_j`` the robust std of z (1.4826 × MAD) over half a
    kernel either side of the hole (the whole record's where fewer than 10 values are there):
    a flight's ground time is quiet, its turbulent air is not.

    With ``record_ends`` the record's ends count as holes too, reaching half a kernel beyond
    it: the low-pass there has data on one side only.  A flight that starts and ends on the
    ground is quiet there and loses little; a record that starts in the air (GNSS exported
    line by line, a receiver started late) is not — the renormalised half kernel passes the
    aircraft's accelerations, and the first 25 s of such a simulated line were up to 166 mGal
    off.

    Parameters
    ----------
    z_mgal : ndarray, shape (N,)
        The series (NaN = missing).
    dt_s, cutoff_period_s, length_periods : float
        As for :func:`fir_lowpass_mgal`.

    Returns
    -------
    ndarray, shape (N,)
        The bound (mGal); 0 where no interior missing sample is under the kernel.
    """
    x = np.asarray(z_mgal, dtype=float)
    if x.ndim != 1:
        raise ValueError(f"z_mgal must be 1-D, got shape {x.shape}")
    fin = np.flatnonzero(np.isfinite(x))
    out = np.zeros(x.shape)
    if fin.size < 2:
        return out
    h = np.abs(fir_kernel(dt_s, cutoff_period_s, length_periods))
    w = h.size // 2
    if record_ends:
        padded = np.concatenate([np.full(w, np.nan), x, np.full(w, np.nan)])
        return _gap_error(padded, ~np.isfinite(padded), h, w)[w:w + x.size]
    gap = ~np.isfinite(x)
    gap[: fin[0]] = False
    gap[fin[-1] + 1:] = False
    if not gap.any():
        return out
    return _gap_error(x, gap, h, w)


def _gap_error(x, gap, h, w) -> np.ndarray:
    """:func:`fir_gap_error_mgal`'s bound for the holes ``gap`` of ``x`` (kernel ``|h|``,
    half-length ``w``)."""
    fin = np.flatnonzero(np.isfinite(x))
    gap = gap & ~np.isfinite(x)
    v = x[fin]
    sigma_all = 1.4826 * float(np.median(np.abs(v - np.median(v))))
    # each hole weighs with z's spread next to it (a flight's ground time is quiet, its air not)
    d = np.diff(np.concatenate([[0], gap.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    weight = gap.astype(float) * sigma_all
    if starts.size <= 10_000:
        for a, b in zip(starts, stops):
            near = np.concatenate([x[max(0, a - w):a], x[b:b + w]])
            near = near[np.isfinite(near)]
            if near.size >= 10:
                weight[a:b] = 1.4826 * float(np.median(np.abs(near - np.median(near))))
    r = signal.oaconvolve(weight, h, mode="same")
    return np.where(r > 1e-9 * h.max() * sigma_all, r, 0.0)   # FFT round-off is no weight


def gaussian_lowpass(x, dt_s: float, fwhm_s: float) -> np.ndarray:
    """``x`` low-passed by a Gaussian of full width at half maximum ``fwhm_s`` (s), samples
    ``dt_s`` (s) apart: ``scipy.ndimage.gaussian_filter1d`` (edges 'nearest', truncated at 3σ),
    a wide kernel by FFT with the same edge padding and truncation (the direct convolution costs
    samples × kernel).  NaNs take the mean of the rest; a Gaussian narrower than a fifth of a
    sample returns ``x`` as it is.  Used for the line profiles' z (smooth weights matter there:
    z holds the differenced GNSS velocity noise, which a boxcar only telescopes down).

    Parameters
    ----------
    x : array_like, shape (n,)
    dt_s, fwhm_s : float

    Returns
    -------
    ndarray, shape (n,)
    """
    from scipy.ndimage import gaussian_filter1d

    x = np.asarray(x, float)
    sigma = fwhm_s / (2.3548 * dt_s) if dt_s > 0 and np.isfinite(dt_s) else 0.0
    if sigma < 0.2 or x.size <= 2:
        return x
    xf = np.where(np.isfinite(x), x, np.nanmean(x))
    radius = int(3.0 * sigma + 0.5)
    if radius <= 256:
        return gaussian_filter1d(xf, sigma=sigma, mode="nearest", truncate=3.0)
    k = np.arange(-radius, radius + 1, dtype=float)
    kernel = np.exp(-0.5 * (k / sigma) ** 2)
    kernel /= kernel.sum()
    return signal.oaconvolve(np.pad(xf, radius, mode="edge"), kernel, mode="valid")


def stationary_smooth(z_mgal, Q_mgal2: float, R_cm2s2: float, dt_s: float, m: int = 2,
                      method: str = "bf") -> SmootherResult:
    """Seed-000 smoother with one constant (Q, R) pair (the stationary baseline).

    Parameters
    ----------
    z_mgal : array_like, shape (T,)
        Measurements (mGal), NaN = missing.
    Q_mgal2 : float
        Variance of ``∇^m δg`` (mGal² per GNSS step), > 0.
    R_cm2s2 : float
        GNSS velocity noise variance ((cm/s)²), > 0.
    dt_s, m, method
        As in :func:`app.core.smoother.kalman_smooth`.
    """
    if np.ndim(Q_mgal2) != 0 or np.ndim(R_cm2s2) != 0:
        raise ValueError("stationary_smooth takes scalar Q_mgal2 and R_cm2s2")
    return kalman_smooth(z_mgal, float(Q_mgal2), float(R_cm2s2), dt_s, m=m, method=method)


@dataclass(frozen=True)
class StationaryQR:
    """Maximum-likelihood (Q, R) of the stationary model.

    Attributes
    ----------
    Q_mgal2 : float
        Variance of ``∇^m δg`` (mGal² per GNSS step).
    R_cm2s2 : float
        GNSS velocity noise variance ((cm/s)²).
    loglik : float
        Total innovations log-likelihood over the lines at the optimum.
    se_log_Q, se_log_R : float
        Asymptotic standard errors of ``ln Q`` and ``ln R`` from the numerical Hessian of
        the log-likelihood (NaN if the Hessian is not negative definite, e.g. at a bound).
    n_evaluations : int
        Number of likelihood evaluations.
    """

    Q_mgal2: float
    R_cm2s2: float
    loglik: float
    se_log_Q: float
    se_log_R: float
    n_evaluations: int


def _as_lines(z) -> list[np.ndarray]:
    if isinstance(z, np.ndarray) and z.ndim == 1:
        return [z.astype(float)]
    if isinstance(z, np.ndarray) and z.ndim == 2:
        return [row.astype(float) for row in z]
    lines = [np.asarray(v, dtype=float) for v in z]
    if not lines:
        raise ValueError("no lines given")
    return lines


def _hessian_se(f, x, h=0.05):
    """Standard errors from the numerical Hessian of the log-likelihood f at x."""
    n = len(x)
    H = np.empty((n, n))
    f0 = f(x)
    for i in range(n):
        for j in range(i, n):
            ei = np.zeros(n)
            ei[i] = h
            ej = np.zeros(n)
            ej[j] = h
            if i == j:
                H[i, i] = (f(x + ei) - 2 * f0 + f(x - ei)) / h**2
            else:
                H[i, j] = H[j, i] = (f(x + ei + ej) - f(x + ei - ej) - f(x - ei + ej) + f(x - ei - ej)) / (4 * h * h)
    try:
        cov = np.linalg.inv(-H)
        d = np.diag(cov)
        return np.where(d > 0, np.sqrt(np.abs(d)), np.nan)
    except np.linalg.LinAlgError:
        return np.full(n, np.nan)


def estimate_stationary_qr(z_mgal, dt_s: float, m: int = 2,
                           Q_bounds_mgal2: tuple[float, float] = (1e-12, 1e4),
                           R_bounds_cm2s2: tuple[float, float] = (1e-4, 1e4)) -> StationaryQR:
    """Maximum-likelihood estimate of one (Q, R) pair for a line or several lines.

    The objective is the sum over lines of the Kalman-filter innovations
    log-likelihood (:func:`app.core.smoother.kalman_loglik`, default diffuse-ish prior
    per line).  ``R`` starts from the high-frequency variance, ``var(∇z) ≈ 6 (1000/Δt)² R``;
    ``Q`` from a coarse grid (one value per decade) at that ``R``; then bounded
    quasi-Newton (L-BFGS-B) on ``(ln Q, ln R)``.

    Parameters
    ----------
    z_mgal : array_like (T,), 2-D array (L, T) or sequence of 1-D arrays
        Measurements per line (mGal), NaN = missing.
    dt_s : float
        GNSS step (s).
    m : int
        Model order, 1..3.
    Q_bounds_mgal2, R_bounds_cm2s2 : (float, float)
        Search bounds.

    Returns
    -------
    StationaryQR
    """
    m = _check_m(m)
    dt = _check_dt(dt_s)
    lines = _as_lines(z_mgal)
    for i, ln in enumerate(lines):
        if ln.ndim != 1 or np.isfinite(ln).sum() < m + 2:
            raise ValueError(f"line {i}: need a 1-D array with at least {m + 2} finite values")
    lo = np.log([Q_bounds_mgal2[0], R_bounds_cm2s2[0]])
    hi = np.log([Q_bounds_mgal2[1], R_bounds_cm2s2[1]])
    if not np.all(lo < hi):
        raise ValueError("bounds must be (low, high) with 0 < low < high")
    c = MGAL_PER_CMS2 / dt
    d = np.concatenate([np.diff(ln) for ln in lines])
    d = d[np.isfinite(d)]
    mad = np.median(np.abs(d - np.median(d))) * 1.4826 if d.size else 1.0
    R0 = float(np.clip(mad**2 / (6.0 * c * c), *np.exp([lo[1], hi[1]])))
    count = [0]

    def ll(p):
        count[0] += 1
        q, r = np.exp(p)
        return sum(kalman_loglik(ln, q, r, dt, m=m) for ln in lines)

    grid = np.arange(np.ceil(lo[0] / np.log(10)), np.floor(hi[0] / np.log(10)) + 1) * np.log(10)
    vals = [ll(np.array([g, np.log(R0)])) for g in grid]
    p0 = np.array([grid[int(np.argmax(vals))], np.log(R0)])
    res = optimize.minimize(lambda p: -ll(p), p0, method="L-BFGS-B",
                            bounds=list(zip(lo, hi)), options=dict(eps=1e-4))
    p = res.x
    se = _hessian_se(ll, p)
    return StationaryQR(Q_mgal2=float(np.exp(p[0])), R_cm2s2=float(np.exp(p[1])),
                        loglik=float(-res.fun), se_log_Q=float(se[0]), se_log_R=float(se[1]),
                        n_evaluations=count[0])
