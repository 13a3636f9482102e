"""Seed-004 experiment: position-domain Kalman filter + RTS smoother with control input.

Research only (the product never runs it; its FIR 100 s baseline is
:func:`app.core.baselines.fir_lowpass_mgal`).  State ``(h, v_u, δg, δġ)``, GNSS height
(or vertical velocity) as the measurement and the corrected gravimeter reading as the
control input (:func:`position_domain_filter`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from scipy.linalg import expm

from app.core.baselines import fir_kernel, fir_lowpass_mgal
from app.core.smoother import _chol_solve_inplace, _mm, _mmT

_LOG_2PI = float(np.log(2.0 * np.pi))
MS2_PER_MGAL = 1e-5


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


class _Discrete(NamedTuple):
    """One step of the discretised model: transition, control vector and process noise."""

    Phi: np.ndarray
    B: np.ndarray
    Qd: np.ndarray


def _discretize(dt, qa, qg) -> _Discrete:
    """Φ, B (control), Qd for the continuous model, exact (Van Loan).

    Parameters
    ----------
    dt : float
        Step (s).
    qa, qg : float
        Intensities of the white noises driving ``v_u`` ((m/s²)²·s) and ``δġ`` (mGal²/s³).

    Returns
    -------
    _Discrete
    """
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
    return _Discrete(Phi, Bc, Qd)


@njit(cache=True)
def _pos_kf(Phi_t, B_t, Q_t, idx, u, H, y, R, x0, P0, xf, Pf, xp, Pp):
    """Kalman filter (Joseph form, scalar measurement H·x + v), dense small n: fills the filtered
    ``xf, Pf`` and predicted ``xp, Pp`` states and returns the log-likelihood."""
    N = y.shape[0]
    n = x0.shape[0]
    x = x0.copy()
    P = P0.copy()
    T = np.empty((n, n))
    T2 = np.empty((n, n))
    g = np.empty(n)
    K = np.empty(n)
    xt = np.empty(n)
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
    return ll


@njit(cache=True)
def _pos_rts(Phi_t, idx, xf, Pf, xp, Pp, xs_out, Ps_out):
    """RTS backward pass over :func:`_pos_kf`'s states: smoothed means into ``xs_out`` and the
    diagonal of the smoothed covariances into ``Ps_out``."""
    N, n = xf.shape
    T = np.empty((n, n))
    T2 = np.empty((n, n))
    xt = np.empty(n)
    xs = xf[N - 1].copy()
    Ps = Pf[N - 1].copy()
    xs_out[N - 1] = xs
    for i in range(n):
        Ps_out[N - 1, i] = Ps[i, i]
    Gt = np.empty((n, n))
    G = np.empty((n, n))
    D = np.empty((n, n))
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


def _pos_kf_rts(Phi_t, B_t, Q_t, idx, u, H, y, R, x0, P0, xs_out, Ps_out):
    """Kalman filter + RTS (:func:`_pos_kf` then :func:`_pos_rts`); returns the log-likelihood."""
    N, n = y.shape[0], x0.shape[0]
    xf = np.empty((N, n))
    Pf = np.empty((N, n, n))
    xp = np.empty((N, n))
    Pp = np.empty((N, n, n))
    ll = _pos_kf(Phi_t, B_t, Q_t, idx, u, H, y, R, x0, P0, xf, Pf, xp, Pp)
    _pos_rts(Phi_t, idx, xf, Pf, xp, Pp, xs_out, Ps_out)
    return ll


class _Measurement(NamedTuple):
    """The GNSS measurement the filter uses."""

    y: np.ndarray       # measured series (m or m/s), NaN = missing
    H: np.ndarray       # measurement row over the state (h, v_u, δg, δġ)
    order: int          # p of the Wiener cross-over rule: 2 for height, 1 for velocity


def _measurement(measurement: str, h, vu_gnss_ms, t) -> _Measurement:
    """The measured series and its row ``H`` for ``measurement`` ('height' or 'velocity')."""
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
    return _Measurement(y, Hrow, p)


def _check_inputs(t, h, u) -> None:
    """Shapes and values of the epoch times, heights and control input."""
    if t.ndim != 1 or h.shape != t.shape or u.shape != t.shape:
        raise ValueError("t_s, h_gnss_m and f_corrected_ms2 must be 1-D arrays of the same length")
    if t.size < 10:
        raise ValueError("need at least 10 epochs")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ValueError("t_s must be finite and strictly increasing")
    if not np.all(np.isfinite(u)):
        raise ValueError("f_corrected_ms2 must be finite at every epoch")


def _white_noise_variance(y, dt_s: float, cutoff_period_s: float) -> float:
    """Seed 004's R: variance of ``y − FIR(y)`` over the white-noise power the high-pass keeps.

    The FIR is :func:`app.core.baselines.fir_lowpass_mgal` with a ``cutoff_period_s``
    cut-off; its ends (half a kernel) are left out when the series is long enough.
    """
    hk = fir_kernel(dt_s, cutoff_period_s, 2.0)
    hp = y - fir_lowpass_mgal(y, dt_s, cutoff_period_s, 2.0)
    c = max(hk.size // 2, 1)
    frac = 1.0 - 2.0 * hk[c] + np.sum(hk**2)
    return float(np.nanvar(hp[c:-c] if y.size > 4 * c else hp) / frac)


class _StepTables(NamedTuple):
    """Discretised model per distinct step, and the table row of every epoch."""

    Phi: np.ndarray     # (S, 4, 4)
    B: np.ndarray       # (S, 4)
    Q: np.ndarray       # (S, 4, 4)
    idx: np.ndarray     # (N,) int64: row of the step ending at each epoch (epoch 0: the first step)


def _step_tables(dts, q_acc_m2_s3: float, q_dg_mgal2_s3: float) -> _StepTables:
    """Discretisation tables per distinct step (steps rounded to 1 µs)."""
    keys = np.round(np.r_[dts[0], dts] * 1e6).astype(np.int64)
    uniq, idx = np.unique(keys, return_inverse=True)
    tabs = [_discretize(k * 1e-6, q_acc_m2_s3, q_dg_mgal2_s3) for k in uniq]
    Phi_t = np.ascontiguousarray(np.array([a for a, _, _ in tabs]))
    B_t = np.ascontiguousarray(np.array([b for _, b, _ in tabs]))
    Q_t = np.ascontiguousarray(np.array([q for _, _, q in tabs]))
    return _StepTables(Phi_t, B_t, Q_t, idx.astype(np.int64))


def _prior(measurement: str, y, t, R: float):
    """Prior ``(x0, P0)`` from the first measurement(s); δg diffuse-ish around 0."""
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
    return x0, P0


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
    _check_inputs(t, h, u)
    N = t.size
    meas = _measurement(measurement, h, vu_gnss_ms, t)
    dts = np.diff(t)
    dt_med = float(np.median(dts))
    if R is None:
        R = _white_noise_variance(meas.y, dt_med, r_cutoff_period_s)
    R = float(R)
    if not (np.isfinite(R) and R > 0):
        raise ValueError(f"R must be > 0, got {R!r}")
    if q_dg_mgal2_s3 is None:
        if not dg_cutoff_period_s > 0:
            raise ValueError("dg_cutoff_period_s must be > 0")
        wc = 2.0 * np.pi / dg_cutoff_period_s
        q_dg_mgal2_s3 = float(wc ** (2 * meas.order + 4) * R * dt_med / MS2_PER_MGAL**2)
    qg = float(q_dg_mgal2_s3)
    if not (qg > 0 and q_acc_m2_s3 >= 0):
        raise ValueError("q_dg_mgal2_s3 must be > 0 and q_acc_m2_s3 ≥ 0")
    tab = _step_tables(dts, q_acc_m2_s3, qg)
    x0, P0 = _prior(measurement, meas.y, t, R)
    xs = np.empty((N, 4))
    Pd = np.empty((N, 4))
    ll = _pos_kf_rts(tab.Phi, tab.B, tab.Q, tab.idx, u, meas.H, meas.y, R, x0, P0, xs, Pd)
    return PositionFilterResult(dg_mgal=xs[:, 2], dg_std_mgal=np.sqrt(np.maximum(Pd[:, 2], 0.0)),
                                h_m=xs[:, 0], vu_ms=xs[:, 1], R=R, q_dg_mgal2_s3=qg, loglik=float(ll))
