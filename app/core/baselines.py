"""Baseline filters (SPEC §2 step 6 and seeds 002–004).

* :func:`fir_lowpass_mgal` — zero-phase windowed-sinc FIR low-pass ("FIR100s" of
  seed 004), with renormalised weights at line ends and around NaNs.
* :func:`stationary_smooth` — the seed-000 smoother with one (Q, R) pair.
* :func:`estimate_stationary_qr` — maximum-likelihood (Q, R) for one or several lines.
* :func:`random_walk_kf` — seed 003 scalar random-walk Kalman filter + RTS smoother,
  Q by maximum likelihood when not given.
* :func:`position_domain_filter` — seed 004 Kalman filter/RTS smoother with state
  ``(h, v_u, δg, δġ)``, GNSS height (or vertical velocity) as measurement and the
  corrected gravimeter reading as control input.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import optimize, signal
from scipy.linalg import expm

from app.core.smoother import (
    SmootherResult,
    _chol_solve_inplace,
    _mm,
    _mmT,
    kalman_loglik,
    kalman_smooth,
)
from app.core.statespace import MGAL_PER_CMS2, _check_dt, _check_m

_LOG_2PI = float(np.log(2.0 * np.pi))
MS2_PER_MGAL = 1e-5

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
            ei = np.zeros(n); ei[i] = h
            ej = np.zeros(n); ej[j] = h
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


# ---------------------------------------------------------------------------
# Seed 003: scalar random-walk Kalman filter / smoother
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RandomWalkResult:
    """Output of :func:`random_walk_kf` (same unit as the input series).

    Attributes
    ----------
    filtered, filtered_var : ndarray (N,)
        Filtered mean and variance (NaN before the first finite sample).
    smoothed, smoothed_var : ndarray (N,)
        RTS-smoothed mean and variance.
    Q, R : float
        Random-walk step variance and measurement noise variance used.
    loglik : float
        Innovations log-likelihood of the samples after the first finite one
        (exact diffuse initialisation).
    """

    filtered: np.ndarray
    filtered_var: np.ndarray
    smoothed: np.ndarray
    smoothed_var: np.ndarray
    Q: float
    R: float
    loglik: float


@njit(cache=True)
def _rw_filter(y, Q, R, k0, xf, Pf):
    """Scalar random walk; diffuse start at the first finite sample k0."""
    N = y.shape[0]
    ll = 0.0
    x = y[k0]
    P = R
    for k in range(k0):
        xf[k] = np.nan
        Pf[k] = np.nan
    xf[k0] = x
    Pf[k0] = P
    for k in range(k0 + 1, N):
        P = P + Q
        yk = y[k]
        if yk == yk:
            S = P + R
            nu = yk - x
            K = P / S
            x = x + K * nu
            P = (1.0 - K) * P  # = P R / S > 0
            ll -= 0.5 * (_LOG_2PI + np.log(S) + nu * nu / S)
        xf[k] = x
        Pf[k] = P
    return ll


@njit(cache=True)
def _rw_smooth(Q, k0, xf, Pf, xs, Ps):
    N = xf.shape[0]
    xs[N - 1] = xf[N - 1]
    Ps[N - 1] = Pf[N - 1]
    for k in range(N - 2, k0 - 1, -1):
        Pp = Pf[k] + Q
        G = Pf[k] / Pp
        xs[k] = xf[k] + G * (xs[k + 1] - xf[k])
        Ps[k] = Pf[k] + G * G * (Ps[k + 1] - Pp)
    for k in range(k0 - 1, -1, -1):  # before the first sample: backward random walk
        xs[k] = xs[k + 1]
        Ps[k] = Ps[k + 1] + Q


def random_walk_kf(series, R: float, Q: float | None = None,
                   Q_bounds: tuple[float, float] | None = None) -> RandomWalkResult:
    """Seed-003 scalar Kalman filter: ``x_k = x_{k−1} + w_k`` (Var Q), ``y_k = x_k + v_k`` (Var R).

    The filter starts diffuse: the first finite sample is taken as the state with
    variance R (this is the exact limit of an infinitely wide prior), and the
    likelihood counts the innovations of the later samples.  The RTS smoother gives the
    fixed-interval estimate.  NaN samples are skipped (prediction only).

    Parameters
    ----------
    series : array_like, shape (N,)
        The series (any unit), NaN = missing.
    R : float
        Measurement noise variance (unit²), > 0 (seed 003: from the sensor's datasheet).
    Q : float, optional
        Random-walk step variance (unit² per sample), > 0.  When None it is estimated by
        maximum likelihood: bounded scalar optimisation of the innovations log-likelihood
        over ``ln Q`` within ``Q_bounds`` (default ``(1e-10 R, 1e4 R)``).
    Q_bounds : (float, float), optional
        Search interval for Q.

    Returns
    -------
    RandomWalkResult
    """
    y = np.ascontiguousarray(np.asarray(series, dtype=float))
    if y.ndim != 1:
        raise ValueError(f"series must be 1-D, got shape {y.shape}")
    if np.any(np.isinf(y)):
        raise ValueError("series contains infinite values")
    fin = np.flatnonzero(np.isfinite(y))
    if fin.size < 3:
        raise ValueError("series needs at least 3 finite samples")
    R = float(R)
    if not (np.isfinite(R) and R > 0):
        raise ValueError(f"R must be > 0, got {R!r}")
    k0 = int(fin[0])
    N = y.size
    xf = np.empty(N); Pf = np.empty(N)
    if Q is None:
        lo, hi = Q_bounds if Q_bounds is not None else (1e-10 * R, 1e4 * R)
        if not (0 < lo < hi):
            raise ValueError("Q_bounds must satisfy 0 < low < high")
        res = optimize.minimize_scalar(lambda lq: -_rw_filter(y, float(np.exp(lq)), R, k0, xf, Pf),
                                       bounds=(np.log(lo), np.log(hi)), method="bounded",
                                       options=dict(xatol=1e-6))
        Q = float(np.exp(res.x))
    else:
        Q = float(Q)
        if not (np.isfinite(Q) and Q > 0):
            raise ValueError(f"Q must be > 0, got {Q!r}")
    ll = _rw_filter(y, Q, R, k0, xf, Pf)
    xs = np.empty(N); Ps = np.empty(N)
    _rw_smooth(Q, k0, xf, Pf, xs, Ps)
    return RandomWalkResult(filtered=xf, filtered_var=Pf, smoothed=xs, smoothed_var=Ps,
                            Q=Q, R=R, loglik=float(ll))


# ---------------------------------------------------------------------------
# Seed 004: position-domain Kalman filter with control input
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class PositionFilterResult:
    """Output of :func:`position_domain_filter`.

    Attributes
    ----------
    dg_mgal, dg_std_mgal : ndarray (N,)
        Smoothed anomaly and its posterior std (mGal).
    h_m, vu_ms : ndarray (N,)
        Smoothed height (m) and vertical velocity (m/s).
    R : float
        Measurement noise variance used (m² for height, (m/s)² for velocity).
    q_dg_mgal2_s3 : float
        Intensity of the white noise driving ``δġ`` (mGal²/s³).
    loglik : float
        Innovations log-likelihood of the forward filter.
    """

    dg_mgal: np.ndarray
    dg_std_mgal: np.ndarray
    h_m: np.ndarray
    vu_ms: np.ndarray
    R: float
    q_dg_mgal2_s3: float
    loglik: float


def _discretize(dt, qa, qg):
    """Φ, B (control), Qd for the continuous model, exact (Van Loan)."""
    F = np.zeros((4, 4))
    F[0, 1] = 1.0
    F[1, 2] = -MS2_PER_MGAL
    F[2, 3] = 1.0
    Qc = np.diag([0.0, qa, 0.0, qg])
    M = np.zeros((8, 8))
    M[:4, :4] = -F
    M[:4, 4:] = Qc
    M[4:, 4:] = F.T
    E = expm(M * dt)
    Phi = E[4:, 4:].T
    Qd = Phi @ E[:4, 4:]
    Qd = 0.5 * (Qd + Qd.T)
    Bc = np.array([0.5 * dt * dt, dt, 0.0, 0.0])
    return Phi, Bc, Qd


@njit(cache=True)
def _pos_kf_rts(Phi_t, B_t, Q_t, idx, u, H, y, R, x0, P0, xs_out, Ps_out):
    """Kalman filter (Joseph form, scalar measurement H·x + v) + RTS, dense small n."""
    N = y.shape[0]
    n = x0.shape[0]
    xf = np.empty((N, n)); Pf = np.empty((N, n, n))
    xp = np.empty((N, n)); Pp = np.empty((N, n, n))
    x = x0.copy(); P = P0.copy()
    T = np.empty((n, n)); T2 = np.empty((n, n))
    g = np.empty(n); K = np.empty(n); xt = np.empty(n)
    ll = 0.0
    for k in range(N):
        if k > 0:
            j = idx[k]
            Phi = Phi_t[j]
            for i in range(n):
                s = B_t[j, i] * u[k]
                for l in range(n):
                    s += Phi[i, l] * x[l]
                xt[i] = s
            x[:] = xt
            _mm(Phi, P, T)
            _mmT(T, Phi, P)
            for i in range(n):
                for l in range(n):
                    P[i, l] += Q_t[j, i, l]
        xp[k] = x
        Pp[k] = P
        yk = y[k]
        if yk == yk:
            S = R
            nu = yk
            for i in range(n):
                s = 0.0
                for l in range(n):
                    s += P[i, l] * H[l]
                g[i] = s
                nu -= H[i] * x[i]
            for i in range(n):
                S += H[i] * g[i]
            for i in range(n):
                K[i] = g[i] / S
                x[i] += K[i] * nu
            # Joseph: (I − K Hᵀ) P (I − K Hᵀ)ᵀ + R K Kᵀ
            for i in range(n):
                for l in range(n):
                    T[i, l] = (1.0 if i == l else 0.0) - K[i] * H[l]
            _mm(T, P, T2)
            _mmT(T2, T, P)
            for i in range(n):
                for l in range(n):
                    P[i, l] = 0.5 * (P[i, l] + P[l, i]) + R * K[i] * K[l]
            for i in range(n):
                for l in range(i + 1, n):
                    P[l, i] = P[i, l]
            ll -= 0.5 * (_LOG_2PI + np.log(S) + nu * nu / S)
        xf[k] = x
        Pf[k] = P
    xs = xf[N - 1].copy()
    Ps = Pf[N - 1].copy()
    xs_out[N - 1] = xs
    for i in range(n):
        Ps_out[N - 1, i] = Ps[i, i]
    Gt = np.empty((n, n)); G = np.empty((n, n)); D = np.empty((n, n))
    dx = np.empty(n)
    for k in range(N - 2, -1, -1):
        j = idx[k + 1]
        _mm(Phi_t[j], Pf[k], Gt)          # Pp_{k+1} Gᵀ = Φ P_k
        _chol_solve_inplace(Pp[k + 1], Gt)
        for i in range(n):
            for l in range(n):
                G[i, l] = Gt[l, i]
                D[i, l] = Ps[i, l] - Pp[k + 1, i, l]
            dx[i] = xs[i] - xp[k + 1, i]
        for i in range(n):
            s = xf[k, i]
            for l in range(n):
                s += G[i, l] * dx[l]
            xt[i] = s
        xs[:] = xt
        _mm(G, D, T)
        _mmT(T, G, T2)
        for i in range(n):
            for l in range(n):
                Ps[i, l] = Pf[k, i, l] + 0.5 * (T2[i, l] + T2[l, i])
        xs_out[k] = xs
        for i in range(n):
            Ps_out[k, i] = Ps[i, i]
    return ll


def position_domain_filter(t_s, h_gnss_m, f_corrected_ms2, *, measurement: str = "height",
                           vu_gnss_ms=None, R: float | None = None,
                           dg_cutoff_period_s: float = 100.0, q_dg_mgal2_s3: float | None = None,
                           q_acc_m2_s3: float = (5e-5) ** 2,
                           r_cutoff_period_s: float = 0.4) -> PositionFilterResult:
    """Seed-004 position-domain Kalman filter + RTS smoother.

    Model (continuous time, "up" positive)::

        ḣ = v_u
        v̇_u = u(t) − 1e-5·δg + w_a          (u = f − γ + E, m/s²; δg in mGal)
        d(δg)/dt = δġ,   d(δġ)/dt = w_g     (δg an integrated random walk)

    with white ``w_a`` (intensity ``q_acc_m2_s3``, gravimeter/model noise) and ``w_g``
    (intensity ``q_dg_mgal2_s3``).  Discretised exactly per step (Van Loan; the control
    is held constant over ``(t_{k−1}, t_k]`` and, following seed 004, the reading of the
    *current* epoch ``u_k`` drives ``x_k`` — pass the specific force averaged over that
    interval).  Measurement: GNSS height ``h_k`` (default, recommended by seed 004) or
    vertical velocity, with white noise of variance ``R``.  Fixed-interval RTS smoothing.

    Parameters
    ----------
    t_s : array_like, shape (N,)
        Epoch times (s), strictly increasing.
    h_gnss_m : array_like, shape (N,)
        GNSS ellipsoidal height (m); NaN = missing.
    f_corrected_ms2 : array_like, shape (N,)
        Corrected gravimeter reading ``f − γ + E`` (m/s²): vertical specific force minus
        normal gravity plus Eötvös, averaged over each GNSS interval.  Must be finite.
    measurement : {'height', 'velocity'}
        Which GNSS quantity is the measurement.
    vu_gnss_ms : array_like, optional
        GNSS vertical velocity (m/s), required for ``measurement='velocity'``.
    R : float, optional
        Measurement noise variance (m² or (m/s)²).  When None (seed 004's recipe): the
        variance of the high-pass part ``y − FIR(y)`` with a ``r_cutoff_period_s`` FIR
        low-pass, divided by the white-noise power fraction the high-pass keeps
        (``1 − 2h₀ + Σh²``).  Aircraft motion above the cut-off biases it upwards.
    dg_cutoff_period_s : float
        Used when ``q_dg_mgal2_s3`` is None: the intensity is set so that the Wiener
        cross-over of signal and noise spectra sits at this period,
        ``q_g = ω_c^(2p+4)·R·Δt·1e10`` (p = 2 for height, 1 for velocity).
    q_dg_mgal2_s3 : float, optional
        Intensity of ``w_g`` (mGal²/s³).
    q_acc_m2_s3 : float
        Intensity of ``w_a`` ((m/s²)²·s); default (5 mGal)²·s.
    r_cutoff_period_s : float
        Cut-off of the FIR used to estimate R.

    Returns
    -------
    PositionFilterResult
    """
    t = np.asarray(t_s, dtype=float)
    h = np.asarray(h_gnss_m, dtype=float)
    u = np.ascontiguousarray(np.asarray(f_corrected_ms2, dtype=float))
    N = t.size
    if t.ndim != 1 or h.shape != t.shape or u.shape != t.shape:
        raise ValueError("t_s, h_gnss_m and f_corrected_ms2 must be 1-D arrays of the same length")
    if N < 10:
        raise ValueError("need at least 10 epochs")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ValueError("t_s must be finite and strictly increasing")
    if not np.all(np.isfinite(u)):
        raise ValueError("f_corrected_ms2 must be finite at every epoch")
    if measurement == "height":
        y, Hrow, p = h, np.array([1.0, 0.0, 0.0, 0.0]), 2
    elif measurement == "velocity":
        if vu_gnss_ms is None:
            raise ValueError("measurement='velocity' needs vu_gnss_ms")
        y = np.asarray(vu_gnss_ms, dtype=float)
        if y.shape != t.shape:
            raise ValueError("vu_gnss_ms must have the length of t_s")
        Hrow, p = np.array([0.0, 1.0, 0.0, 0.0]), 1
    else:
        raise ValueError(f"measurement must be 'height' or 'velocity', got {measurement!r}")
    y = np.ascontiguousarray(y)
    if np.isfinite(y).sum() < 10:
        raise ValueError("need at least 10 finite measurements")
    dts = np.diff(t)
    dt_med = float(np.median(dts))
    if R is None:
        hk = fir_kernel(dt_med, r_cutoff_period_s, 2.0)
        hp = y - fir_lowpass_mgal(y, dt_med, r_cutoff_period_s, 2.0)
        c = max(hk.size // 2, 1)
        frac = 1.0 - 2.0 * hk[c] + np.sum(hk**2)
        R = float(np.nanvar(hp[c:-c] if N > 4 * c else hp) / frac)
    R = float(R)
    if not (np.isfinite(R) and R > 0):
        raise ValueError(f"R must be > 0, got {R!r}")
    if q_dg_mgal2_s3 is None:
        if not dg_cutoff_period_s > 0:
            raise ValueError("dg_cutoff_period_s must be > 0")
        wc = 2.0 * np.pi / dg_cutoff_period_s
        q_dg_mgal2_s3 = float(wc ** (2 * p + 4) * R * dt_med / MS2_PER_MGAL**2)
    qg = float(q_dg_mgal2_s3)
    if not (qg > 0 and q_acc_m2_s3 >= 0):
        raise ValueError("q_dg_mgal2_s3 must be > 0 and q_acc_m2_s3 ≥ 0")
    # discretisation tables per distinct step (rounded to 1 µs)
    keys = np.round(np.r_[dts[0], dts] * 1e6).astype(np.int64)
    uniq, idx = np.unique(keys, return_inverse=True)
    tabs = [_discretize(k * 1e-6, q_acc_m2_s3, qg) for k in uniq]
    Phi_t = np.ascontiguousarray(np.array([a for a, _, _ in tabs]))
    B_t = np.ascontiguousarray(np.array([b for _, b, _ in tabs]))
    Q_t = np.ascontiguousarray(np.array([q for _, _, q in tabs]))
    # prior: first measurement(s); δg diffuse-ish around 0
    fin = np.flatnonzero(np.isfinite(y))
    x0 = np.zeros(4)
    P0 = np.diag([1e4, 1e2, 1e6, 1e2])
    if measurement == "height":
        x0[0] = y[fin[0]]
        P0[0, 0] = R
        if fin.size > 1:
            x0[1] = (y[fin[1]] - y[fin[0]]) / (t[fin[1]] - t[fin[0]])
            P0[1, 1] = 4.0 * R / (t[fin[1]] - t[fin[0]]) ** 2 + 1.0
    else:
        x0[1] = y[fin[0]]
        P0[1, 1] = R
        x0[0] = 0.0
    xs = np.empty((N, 4))
    Pd = np.empty((N, 4))
    ll = _pos_kf_rts(Phi_t, B_t, Q_t, idx.astype(np.int64), u, Hrow, y, R, x0, P0, xs, Pd)
    return PositionFilterResult(dg_mgal=xs[:, 2], dg_std_mgal=np.sqrt(np.maximum(Pd[:, 2], 0.0)),
                                h_m=xs[:, 0], vu_ms=xs[:, 1], R=R, q_dg_mgal2_s3=qg, loglik=float(ll))
