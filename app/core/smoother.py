"""Non-stationary Kalman filtering and fixed-interval smoothing (SPEC §2 step 5).

Two groups of functions:

* The seed-000 anomaly model (see :mod:`app.core.statespace`) with per-epoch
  ``Q_k`` (mGal² per GNSS step) and ``R_k`` ((cm/s)²):
  :func:`kalman_smooth` (one line), :func:`smooth_many` (many lines),
  :func:`kalman_loglik` (filter only, for likelihood fits).  The epoch loops are
  numba-compiled and use the sparse structure of ``A`` (a companion block plus a
  shift), so a step costs O(n²) with n = m + 2.

  - ``method='bf'`` (default): Kalman filter + modified Bryson–Frazier smoother
    (Bierman 1973).  The backward pass propagates the adjoint ``λ̂`` and its
    information matrix ``Λ̂``; it needs no inverse of ``A`` (which is singular
    here) nor of the predicted covariance.  Only row 0 of the filtered
    covariance is stored per epoch (memory O(n·T)).
  - ``method='rts'``: Kalman filter + Rauch–Tung–Striebel smoother.  The gain
    ``G_k = P_k Aᵀ (P⁻_{k+1})⁻¹`` is obtained by a Cholesky solve (the
    predicted covariance of this model is positive definite because Q, R > 0).

  Numerics: internally the state is carried in an equivalent, better conditioned
  basis ``(δg_k, ∇δg_k, …, ∇^{m−1}δg_k, ρ_k, ρ_{k−1})`` with ``ρ = 1000·r/Δt``
  (mGal): the shifted copies ``δg_{k−j}`` of the paper's state are nearly equal for
  smooth anomalies, so their covariance is ill-conditioned, while the differences
  have their own scales (in this basis ``A``'s δg block is the upper-triangular
  all-ones "Pascal" matrix, q enters every difference, and ``C`` is unchanged).
  This is a change of coordinates only: results are those of the model of
  :mod:`app.core.statespace` (it cut the disagreement of BF and RTS variances from
  1e-7 to 1e-9).  The filtered covariance is updated in Joseph form
  ``P = (I − K C) P⁻ (I − K C)ᵀ`` (no measurement-noise term; the congruence is
  evaluated as two rank-one corrections) and symmetrised every step.

  Initial state ("diffuse-ish" start, used when ``x0``/``P0`` are not given):
  ``δg_0`` ~ N(mean of the finite measurements of the first 100 s of the line
  (at least ``m + 2`` samples), (1000 mGal)²); the differences ``∇^j δg_0``
  (j = 1..m−1) ~ N(0, (1 mGal per step^j)²); ``r_0``, ``r_{−1}`` ~ N(0, R_0); all
  independent.  ``x0``/``P0``, when given, are in the model's basis
  (:mod:`app.core.statespace`: δg in mGal, r in cm/s) and are the prior of ``y_0``
  *before* the measurement ``z_0`` is used (no prediction step at k = 0).

* Generic linear-Gaussian models ``x_k = A x_{k−1} + u_k + w_k``,
  ``z_k = C x_k + v_k``: :func:`kalman_filter`, :func:`rts_smooth` (plain numpy,
  meant for small problems and as the reference the tests compare with; the seed-002
  two-filter smoother built on them is in :mod:`app.research.two_filter`).

References: Bierman, G. J. (1973), "Fixed interval smoothing with discrete
measurements", Int. J. Control 18(1); Rauch, Tung & Striebel (1965), AIAA J.
3(8).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from math import comb
from typing import NamedTuple

import numpy as np
from numba import njit

from app.core.statespace import MGAL_PER_CMS2, _check_dt, _check_m

_LOG_2PI = float(np.log(2.0 * np.pi))
#: Std (mGal) of each δg component of the default diffuse-ish prior.
PRIOR_DG_STD_MGAL = 1000.0
#: Std (mGal per step^j) of the j-th backward difference (j = 1..m−1) in the default prior.
PRIOR_DIFF_STD_MGAL = 1.0
#: Seconds of data averaged for the default prior mean of δg.
PRIOR_MEAN_WINDOW_S = 100.0


@dataclass(frozen=True)
class SmootherResult:
    """Output of :func:`kalman_smooth` for one line.

    Attributes
    ----------
    dg_mgal : ndarray, shape (T,)
        Smoothed anomaly ``E[δg_k | z_0..z_{T−1}]`` (mGal).
    dg_std_mgal : ndarray, shape (T,)
        Posterior standard deviation of ``δg_k`` (mGal).
    loglik : float
        Log-likelihood ``log p(z | Q, R)`` of the finite measurements (innovations
        form, natural log), including the prior of ``y_0``.
    filtered_mgal : ndarray, shape (T,)
        Filtered anomaly ``E[δg_k | z_0..z_k]`` (mGal).
    innovations : ndarray, shape (T,) or None
        Standardised innovations ``ν_k/√s_k`` of the filter (NaN at missing epochs; None
        with ``method='rts'``): white with unit variance when the model fits.
    """

    dg_mgal: np.ndarray
    dg_std_mgal: np.ndarray
    loglik: float
    filtered_mgal: np.ndarray
    innovations: np.ndarray | None = None


# ---------------------------------------------------------------------------
# numba kernels for the seed-000 model (state scaled: ρ = 1000 r / Δt in mGal)
# C = e_0 − e_m + e_{m+1}
# ---------------------------------------------------------------------------


@njit(cache=True, nogil=True, inline="always")
def _cdot(v, m):
    return v[0] - v[m] + v[m + 1]


@njit(cache=True, nogil=True)
def _predict(m, x, P, xp, Pp, T, Qk, Q0k, Rk):
    """xp = A x ; Pp = A P Aᵀ + W_k in the difference basis.

    δg block: A[i, l] = 1 for i ≤ l < m (suffix sums); A[m+1, m] = 1; row m zero.
    W_k = Q_k·b bᵀ (b = 1 on the δg block) + Q0_k e_0 e_0ᵀ + R_k e_m e_mᵀ (Q0: the
    random-walk part of the two-component model).  T is scratch (n×n)."""
    n = m + 2
    s = 0.0
    for i in range(m - 1, -1, -1):
        s += x[i]
        xp[i] = s
    xp[m] = 0.0
    xp[m + 1] = x[m]
    # T = A P (row suffix sums)
    for col in range(n):
        s = 0.0
        for i in range(m - 1, -1, -1):
            s += P[i, col]
            T[i, col] = s
        T[m, col] = 0.0
        T[m + 1, col] = P[m, col]
    # Pp = T Aᵀ (column suffix sums)
    for row in range(n):
        s = 0.0
        for j in range(m - 1, -1, -1):
            s += T[row, j]
            Pp[row, j] = s
        Pp[row, m] = 0.0
        Pp[row, m + 1] = T[row, m]
    for i in range(m):
        for j in range(m):
            Pp[i, j] += Qk
    Pp[0, 0] += Q0k
    Pp[m, m] += Rk


@njit(cache=True, nogil=True)
def _update(m, xp, Pp, zk, x, P, K, g, h):
    """Measurement update with C = e0 − e_m + e_{m+1}, no measurement noise.

    Joseph form P = (I − K cᵀ) Pp (I − K cᵀ)ᵀ.  Returns (nu, s)."""
    n = m + 2
    for i in range(n):
        g[i] = Pp[i, 0] - Pp[i, m] + Pp[i, m + 1]
    s = g[0] - g[m] + g[m + 1]
    for i in range(n):
        K[i] = g[i] / s
    nu = zk - _cdot(xp, m)
    for i in range(n):
        x[i] = xp[i] + K[i] * nu
    # M = (I − K cᵀ) Pp = Pp − K gᵀ      (cᵀ Pp = gᵀ by symmetry)
    for i in range(n):
        for j in range(n):
            P[i, j] = Pp[i, j] - K[i] * g[j]
    # P = M (I − c Kᵀ) = M − (M c) Kᵀ
    for i in range(n):
        h[i] = P[i, 0] - P[i, m] + P[i, m + 1]
    for i in range(n):
        for j in range(n):
            P[i, j] -= h[i] * K[j]
    for i in range(n):
        for j in range(i + 1, n):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v
    return nu, s


@njit(cache=True, nogil=True)
def _filter_state(x0, P0):
    """Working arrays of :func:`_filter_step`: x, P, xp, Pp (from the prior) and scratch."""
    n = x0.shape[0]
    return (x0.copy(), P0.copy(), x0.copy(), P0.copy(), np.empty((n, n)), np.zeros(n), np.empty(n),
            np.empty(n))


@njit(cache=True, nogil=True)
def _filter_step(m, k, zk, Qk, Q0k, Rk, x, P, xp, Pp, T, K, g, h):
    """One Kalman filter step in place: predict (k > 0; at k = 0 ``xp``/``Pp`` hold the
    prior), then update with ``zk`` or, when it is missing (NaN), carry the prediction.

    Returns (log-likelihood increment, innovation ν, its variance s); s = 0 when missing."""
    n = m + 2
    if k > 0:
        _predict(m, x, P, xp, Pp, T, Qk, Q0k, Rk)
    if zk == zk:  # finite
        nu, s = _update(m, xp, Pp, zk, x, P, K, g, h)
        return -0.5 * (_LOG_2PI + np.log(s) + nu * nu / s), nu, s
    for i in range(n):
        x[i] = xp[i]
        for j in range(n):
            P[i, j] = Pp[i, j]
    return 0.0, 0.0, 0.0


@njit(cache=True, nogil=True)
def _forward_bf(z, Qs, Q0s, Rs, m, x0, P0, xf0, prow, Kst, nust, sinv):
    """Kalman filter storing what the modified Bryson–Frazier pass needs."""
    n = m + 2
    N = z.shape[0]
    x, P, xp, Pp, T, K, g, h = _filter_state(x0, P0)
    ll = 0.0
    for k in range(N):
        dll, nu, s = _filter_step(m, k, z[k], Qs[k], Q0s[k], Rs[k], x, P, xp, Pp, T, K, g, h)
        ll += dll
        for i in range(n):
            Kst[k, i] = K[i] if s > 0.0 else 0.0
        nust[k] = nu
        sinv[k] = 1.0 / s if s > 0.0 else 0.0
        xf0[k] = x[0]
        for j in range(n):
            prow[k, j] = P[0, j]
    return ll


@njit(cache=True, nogil=True)
def _backward_bf(m, xf0, prow, Kst, nust, sinv, out_mean, out_var):
    """Modified Bryson–Frazier backward pass (no inverses).

    λ̂_{N−1} = 0, Λ̂_{N−1} = 0;  x_{k|N} = x_{k|k} − P_{k|k} λ̂_k,
    P_{k|N} = P_{k|k} − P_{k|k} Λ̂_k P_{k|k};
    λ̃_k = −c ν_k/s_k + Ĉ_kᵀ λ̂_k,  Λ̃_k = c cᵀ/s_k + Ĉ_kᵀ Λ̂_k Ĉ_k,  Ĉ_k = I − K_k cᵀ;
    λ̂_{k−1} = Aᵀ λ̃_k,  Λ̂_{k−1} = Aᵀ Λ̃_k A.
    """
    n = m + 2
    N = xf0.shape[0]
    lam = np.zeros(n)
    Lam = np.zeros((n, n))
    lt = np.empty(n)
    Lt = np.empty((n, n))
    T = np.empty((n, n))
    u = np.empty(n)
    c = np.zeros(n)
    c[0] = 1.0
    c[m] = -1.0
    c[m + 1] = 1.0
    for k in range(N - 1, -1, -1):
        # smoothed δg and its variance
        s1 = 0.0
        s2 = 0.0
        for i in range(n):
            pi = prow[k, i]
            s1 += pi * lam[i]
            t = 0.0
            for j in range(n):
                t += Lam[i, j] * prow[k, j]
            s2 += pi * t
        out_mean[k] = xf0[k] - s1
        out_var[k] = prow[k, 0] - s2
        if k == 0:
            break
        si = sinv[k]
        if si > 0.0:
            # u = Λ̂ K, β = Kᵀ u, γ = Kᵀ λ̂
            beta = 0.0
            gam = 0.0
            for i in range(n):
                t = 0.0
                for j in range(n):
                    t += Lam[i, j] * Kst[k, j]
                u[i] = t
            for i in range(n):
                beta += Kst[k, i] * u[i]
                gam += Kst[k, i] * lam[i]
            for i in range(n):
                lt[i] = lam[i] - c[i] * (gam + nust[k] * si)
            # Λ̃ = Ĉᵀ (Λ̂ Ĉ) + c cᵀ/s as an explicit congruence: N = Λ̂ − u cᵀ; Λ̃ = N − c (Kᵀ N)
            for i in range(n):
                for j in range(n):
                    Lt[i, j] = Lam[i, j] - u[i] * c[j]
            for j in range(n):
                t = 0.0
                for i in range(n):
                    t += Kst[k, i] * Lt[i, j]
                u[j] = t
            for i in range(n):
                for j in range(n):
                    Lt[i, j] -= c[i] * u[j]
            for i in range(n):
                for j in range(i, n):
                    v = 0.5 * (Lt[i, j] + Lt[j, i]) + si * c[i] * c[j]
                    Lt[i, j] = v
                    Lt[j, i] = v
        else:
            for i in range(n):
                lt[i] = lam[i]
                for j in range(n):
                    Lt[i, j] = Lam[i, j]
        # λ̂ = Aᵀ λ̃ : (Aᵀv)[j] = Σ_{i≤j} v_i (j < m); v_{m+1} (j = m); 0 (j = m+1)
        s = 0.0
        for j in range(m):
            s += lt[j]
            lam[j] = s
        lam[m] = lt[m + 1]
        lam[m + 1] = 0.0
        # T = Aᵀ Λ̃ (columns), Λ̂ = T A = (Aᵀ Tᵀ)ᵀ (rows)
        for col in range(n):
            s = 0.0
            for j in range(m):
                s += Lt[j, col]
                T[j, col] = s
            T[m, col] = Lt[m + 1, col]
            T[m + 1, col] = 0.0
        for row in range(n):
            s = 0.0
            for j in range(m):
                s += T[row, j]
                Lam[row, j] = s
            Lam[row, m] = T[row, m + 1]
            Lam[row, m + 1] = 0.0


@njit(cache=True, nogil=True)
def _smooth_bf(z, Qs, Q0s, Rs, m, x0, P0, out_mean, out_var, out_filt, out_innov):
    N = z.shape[0]
    n = m + 2
    prow = np.empty((N, n))
    Kst = np.empty((N, n))
    nust = np.empty(N)
    sinv = np.empty(N)
    ll = _forward_bf(z, Qs, Q0s, Rs, m, x0, P0, out_filt, prow, Kst, nust, sinv)
    _backward_bf(m, out_filt, prow, Kst, nust, sinv, out_mean, out_var)
    for k in range(N):
        out_innov[k] = nust[k] * np.sqrt(sinv[k]) if sinv[k] > 0.0 else np.nan
    return ll


@njit(cache=True, nogil=True)
def _loglik_only(z, Qs, Q0s, Rs, m, x0, P0):
    N = z.shape[0]
    x, P, xp, Pp, T, K, g, h = _filter_state(x0, P0)
    ll = 0.0
    for k in range(N):
        ll += _filter_step(m, k, z[k], Qs[k], Q0s[k], Rs[k], x, P, xp, Pp, T, K, g, h)[0]
    return ll


@njit(cache=True, nogil=True)
def _mm(A, B, out):
    """out = A B."""
    n, k = A.shape
    p = B.shape[1]
    for i in range(n):
        for j in range(p):
            s = 0.0
            for l in range(k):
                s += A[i, l] * B[l, j]
            out[i, j] = s


@njit(cache=True, nogil=True)
def _mmT(A, B, out):
    """out = A Bᵀ."""
    n, k = A.shape
    p = B.shape[0]
    for i in range(n):
        for j in range(p):
            s = 0.0
            for l in range(k):
                s += A[i, l] * B[j, l]
            out[i, j] = s


@njit(cache=True, nogil=True)
def _chol_solve_inplace(S, Bm):
    """Solve S X = Bm for symmetric positive definite S (n×n), Bm (n×p) overwritten."""
    n = S.shape[0]
    L = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            s = S[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if s <= 0.0:
                    s = 1e-300
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    p = Bm.shape[1]
    for c in range(p):
        for i in range(n):
            s = Bm[i, c]
            for k in range(i):
                s -= L[i, k] * Bm[k, c]
            Bm[i, c] = s / L[i, i]
        for i in range(n - 1, -1, -1):
            s = Bm[i, c]
            for k in range(i + 1, n):
                s -= L[k, i] * Bm[k, c]
            Bm[i, c] = s / L[i, i]


@njit(cache=True, nogil=True)
def _smooth_rts(z, Qs, Q0s, Rs, m, x0, P0, out_mean, out_var, out_filt):
    n = m + 2
    N = z.shape[0]
    xs = np.empty((N, n))
    Ps = np.empty((N, n, n))
    xps = np.empty((N, n))
    Pps = np.empty((N, n, n))
    x, P, xp, Pp, T, K, g, h = _filter_state(x0, P0)
    ll = 0.0
    for k in range(N):
        ll += _filter_step(m, k, z[k], Qs[k], Q0s[k], Rs[k], x, P, xp, Pp, T, K, g, h)[0]
        xs[k] = x
        Ps[k] = P
        xps[k] = xp
        Pps[k] = Pp
        out_filt[k] = x[0]
    # backward
    xsm = xs[N - 1].copy()
    Psm = Ps[N - 1].copy()
    out_mean[N - 1] = xsm[0]
    out_var[N - 1] = Psm[0, 0]
    AP = np.empty((n, n))
    G = np.empty((n, n))
    dx = np.empty(n)
    D = np.empty((n, n))
    GD = np.empty((n, n))
    xtmp = np.empty(n)
    for k in range(N - 2, -1, -1):
        # AP = A P_k  (= (P_k Aᵀ)ᵀ);  solve P⁻_{k+1} Gᵀ = A P_k
        Pk = Ps[k]
        for col in range(n):
            s = 0.0
            for i in range(m - 1, -1, -1):
                s += Pk[i, col]
                AP[i, col] = s
            AP[m, col] = 0.0
            AP[m + 1, col] = Pk[m, col]
        _chol_solve_inplace(Pps[k + 1], AP)  # AP now holds Gᵀ
        for i in range(n):
            for j in range(n):
                G[i, j] = AP[j, i]
        for i in range(n):
            dx[i] = xsm[i] - xps[k + 1, i]
            for j in range(n):
                D[i, j] = Psm[i, j] - Pps[k + 1, i, j]
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += G[i, j] * dx[j]
            xtmp[i] = xs[k, i] + s
        _mm(G, D, GD)
        _mmT(GD, G, Psm)
        for i in range(n):
            for j in range(n):
                Psm[i, j] += Pk[i, j]
        for i in range(n):
            for j in range(i + 1, n):
                v = 0.5 * (Psm[i, j] + Psm[j, i])
                Psm[i, j] = v
                Psm[j, i] = v
        for i in range(n):
            xsm[i] = xtmp[i]
        out_mean[k] = xsm[0]
        out_var[k] = Psm[0, 0]
    return ll


# ---------------------------------------------------------------------------
# Input validation and the public entry points
# ---------------------------------------------------------------------------


def _per_epoch(name: str, v, N: int, allow_zero: bool = False) -> np.ndarray:
    arr = np.asarray(v, dtype=float)
    if arr.ndim == 0:
        arr = np.full(N, float(arr))
    elif arr.ndim != 1:
        raise ValueError(f"{name} must be a scalar or a 1-D array, got shape {arr.shape}")
    elif arr.shape[0] != N:
        raise ValueError(f"{name} has length {arr.shape[0]} but z has length {N}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    if np.any(arr < 0.0) or (not allow_zero and np.any(arr == 0.0)):
        raise ValueError(f"{name} must be {'≥' if allow_zero else '>'} 0 at every epoch (min {arr.min():g})")
    return np.ascontiguousarray(arr)


def _to_internal(m: int, scale: float) -> np.ndarray:
    """Matrix taking the model state (δg_k … δg_{k−m+1}, r_k, r_{k−1}) [mGal, cm/s] to the
    internal one (δg_k, ∇δg_k, …, ∇^{m−1}δg_k, ρ_k, ρ_{k−1}) [mGal], ρ = 1000 r/Δt."""
    n = m + 2
    T = np.zeros((n, n))
    for j in range(m):
        for i in range(j + 1):
            T[j, i] = (-1.0) ** i * comb(j, i)
    T[m, m] = scale
    T[m + 1, m + 1] = scale
    return T


def _prepare(z_mgal, Q_mgal2, R_cm2s2, dt_s, m, x0, P0, Q_rw_mgal2=None):
    m = _check_m(m)
    dt = _check_dt(dt_s)
    z = np.ascontiguousarray(np.asarray(z_mgal, dtype=float))
    if z.ndim != 1:
        raise ValueError(f"z_mgal must be 1-D, got shape {z.shape}")
    if np.any(np.isinf(z)):
        raise ValueError("z_mgal contains infinite values (use NaN for missing epochs)")
    N = z.shape[0]
    finite = np.isfinite(z)
    nfin = int(finite.sum())
    if N < m + 2 or nfin < m + 2:
        raise ValueError(
            f"line too short for m={m}: need at least {m + 2} finite epochs, "
            f"got {nfin} finite of {N}")
    Q = _per_epoch("Q_mgal2", Q_mgal2, N)
    R = _per_epoch("R_cm2s2", R_cm2s2, N)
    if Q_rw_mgal2 is None:
        Q0 = np.zeros(N)
    else:
        if m < 2:
            raise ValueError("Q_rw_mgal2 (a random-walk part beside ∇^m δg = q) needs m ≥ 2")
        Q0 = _per_epoch("Q_rw_mgal2", Q_rw_mgal2, N, allow_zero=True)
    scale = MGAL_PER_CMS2 / dt
    Rs = R * (scale * scale)  # variance of ρ = 1000 r/Δt (mGal²)
    n = m + 2
    if x0 is None:
        nwin = max(int(round(PRIOR_MEAN_WINDOW_S / dt)), m + 2)
        idx = np.flatnonzero(finite)
        sel = idx[idx < nwin]
        if sel.size < m + 2:
            sel = idx[: m + 2]
        mean0 = float(np.mean(z[sel]))
        x0v = np.zeros(n)
        x0v[0] = mean0
    else:
        x0u = np.asarray(x0, dtype=float).reshape(-1)
        if x0u.shape != (n,):
            raise ValueError(f"x0 must have shape ({n},), got {np.shape(x0)}")
        x0v = _to_internal(m, scale) @ x0u
    if P0 is None:
        P0v = np.zeros((n, n))
        P0v[0, 0] = PRIOR_DG_STD_MGAL ** 2
        for i in range(1, m):
            P0v[i, i] = PRIOR_DIFF_STD_MGAL ** 2
        P0v[m, m] = Rs[0]
        P0v[m + 1, m + 1] = Rs[0]
    else:
        P0u = np.asarray(P0, dtype=float)
        if P0u.shape != (n, n):
            raise ValueError(f"P0 must have shape ({n}, {n}), got {P0u.shape}")
        if not np.allclose(P0u, P0u.T) or np.any(np.linalg.eigvalsh(P0u) < -1e-12 * np.abs(P0u).max()):
            raise ValueError("P0 must be symmetric positive semi-definite")
        Tm = _to_internal(m, scale)
        P0v = Tm @ P0u @ Tm.T
        P0v = 0.5 * (P0v + P0v.T)
    if not np.all(np.isfinite(x0v)) or not np.all(np.isfinite(P0v)):
        raise ValueError("x0 / P0 must be finite")
    return m, z, Q, Q0, Rs, np.ascontiguousarray(x0v), np.ascontiguousarray(P0v)


def kalman_smooth(z_mgal, Q_mgal2, R_cm2s2, dt_s, m: int = 2, method: str = "bf",
                  x0=None, P0=None, Q_rw_mgal2=None, noise=None) -> SmootherResult:
    """Fixed-interval smoothing of one line under the seed-000 model.

    Parameters
    ----------
    z_mgal : array_like, shape (T,)
        Anomaly measurements ``z_k`` (mGal); NaN = no measurement at that epoch.
    Q_mgal2 : float or array_like, shape (T,)
        Variance of ``q_k = ∇^m δg_k`` (mGal² per GNSS step), > 0.  ``Q[0]`` is unused
        (the prior covers epoch 0).
    R_cm2s2 : float or array_like, shape (T,)
        Variance of the GNSS vertical-velocity error ``r_k`` ((cm/s)²), > 0.
    dt_s : float
        GNSS step Δt (s).
    m : int, default 2
        Order of the anomaly model, 1..3.
    method : {'bf', 'rts'}
        Modified Bryson–Frazier (default, no matrix inverse) or Rauch–Tung–Striebel.
    x0, P0 : array_like, optional
        Prior mean (m+2,) and covariance (m+2, m+2) of ``y_0`` in model units
        (δg in mGal, r in cm/s).  Default: the diffuse-ish prior described in the
        module docstring.
    Q_rw_mgal2 : float or array_like, shape (T,), optional
        Two-component anomaly (m ≥ 2 only): ``δg = s + u`` with ``∇^m s = q`` (variance
        ``Q_mgal2``) and a random walk ``∇u = w`` of variance ``Q_rw_mgal2`` (mGal² per
        step, ≥ 0).  With 0 it is the plain order-m model; with a large random-walk part
        and a tiny Q it behaves like m = 1 while the smooth part keeps its slope.
        Internally the second state component is then the smooth part's slope.
    noise : app.core.noise_model.NoiseModel, optional
        The error of z as a coloured process; ``R_cm2s2`` is then the level multiplying
        every component's innovation variance (for a model normalised with
        :meth:`~app.core.noise_model.NoiseModel.normalized`: the equivalent white velocity
        noise, (cm/s)²).  None or a white-velocity model: the seed-000 model above (fast
        path).  Otherwise the state is ``(δg_k … δg_{k−m+1}, b_k)`` with the model's noise
        block ``b`` (``x0``/``P0`` in that basis) and the loops are dense.

    Returns
    -------
    SmootherResult

    Raises
    ------
    ValueError
        Bad ``m``, ``dt_s``, ``method``; Q or R ≤ 0 or non-finite; length mismatch;
        fewer than ``m + 2`` finite measurements.
    """
    if method not in ("bf", "rts"):
        raise ValueError(f"method must be 'bf' or 'rts', got {method!r}")
    white = _white_level(noise, dt_s)
    if white is None:
        if Q_rw_mgal2 is not None:
            raise ValueError("Q_rw_mgal2 is only available with white velocity noise")
        return _smooth_coloured(z_mgal, Q_mgal2, R_cm2s2, dt_s, m, noise, method, x0, P0)
    R_cm2s2 = np.asarray(R_cm2s2, dtype=float) * white if white != 1.0 else R_cm2s2
    m, z, Q, Q0, Rs, x0v, P0v = _prepare(z_mgal, Q_mgal2, R_cm2s2, dt_s, m, x0, P0, Q_rw_mgal2)
    N = z.shape[0]
    mean = np.empty(N)
    var = np.empty(N)
    filt = np.empty(N)
    if method == "bf":
        innov = np.empty(N)
        ll = _smooth_bf(z, Q, Q0, Rs, m, x0v, P0v, mean, var, filt, innov)
        return _finish(mean, var, ll, filt, innov)
    ll = _smooth_rts(z, Q, Q0, Rs, m, x0v, P0v, mean, var, filt)
    return _finish(mean, var, ll, filt)


def kalman_loglik(z_mgal, Q_mgal2, R_cm2s2, dt_s, m: int = 2, x0=None, P0=None,
                  Q_rw_mgal2=None, noise=None) -> float:
    """Innovations log-likelihood of one line (Kalman filter only; same prior as
    :func:`kalman_smooth`).  Units, ``noise`` and validation as in :func:`kalman_smooth`."""
    white = _white_level(noise, dt_s)
    if white is None:
        if Q_rw_mgal2 is not None:
            raise ValueError("Q_rw_mgal2 is only available with white velocity noise")
        z, Q, R, A, Wa, Wb, c, x0v, P0v = _prepare_coloured(z_mgal, Q_mgal2, R_cm2s2, dt_s, m, noise, x0, P0)
        e1, e2, e3 = np.empty(1), np.empty((1, 1)), np.empty((1, 1, 1))
        return float(_gen_filter(z, Q, R, A, Wa, Wb, c, x0v, P0v, 0, e2, e3, e2, e3, e2, e1, e1, e2, e1))
    R_cm2s2 = np.asarray(R_cm2s2, dtype=float) * white if white != 1.0 else R_cm2s2
    m, z, Q, Q0, Rs, x0v, P0v = _prepare(z_mgal, Q_mgal2, R_cm2s2, dt_s, m, x0, P0, Q_rw_mgal2)
    return float(_loglik_only(z, Q, Q0, Rs, m, x0v, P0v))


def smooth_many(z_lines: Sequence, Q_lines, R_lines, dt_s, m: int = 2,
                method: str = "bf") -> list[SmootherResult]:
    """Smooth many lines independently (each with its own default prior).

    Parameters
    ----------
    z_lines : sequence of array_like
        One measurement array per line (mGal).
    Q_lines, R_lines : sequence (one entry per line) of float or array_like, or a single float
        Per-line Q (mGal² per step) and R ((cm/s)²), scalar or per-epoch.
    dt_s, m, method
        As in :func:`kalman_smooth`.

    Returns
    -------
    list of SmootherResult, in the order of ``z_lines``.
    """
    L = len(z_lines)

    def _expand(v, name):
        if np.ndim(v) == 0:
            return [v] * L
        if len(v) != L:
            raise ValueError(f"{name} has {len(v)} entries but there are {L} lines")
        return list(v)

    Qs = _expand(Q_lines, "Q_lines")
    Rs = _expand(R_lines, "R_lines")
    return [kalman_smooth(z, q, r, dt_s, m=m, method=method)
            for z, q, r in zip(z_lines, Qs, Rs)]


# ---------------------------------------------------------------------------
# Coloured GNSS/motion error (app.core.noise_model): generic block state
# ---------------------------------------------------------------------------
#
# State (δg_k, ∇δg_k, …, ∇^{m−1}δg_k, b_k) with the anomaly block in the difference basis
# of the fast path (A_a upper-triangular ones, q entering every difference) and the
# noise block b_k = F b_{k−1} + e_k, Cov e_k = R_k·W (NoiseModel.block()); z_k = δg_k + hᵀb_k.
# The loops are dense (n ≤ m + 6), O(n³) per step.


@njit(cache=True, nogil=True)
def _gen_predict(A, x, P, Qk, Rk, Wa, Wb, xp, Pp, T):
    n = A.shape[0]
    for i in range(n):
        s = 0.0
        for l in range(n):
            s += A[i, l] * x[l]
        xp[i] = s
    _mm(A, P, T)
    _mmT(T, A, Pp)
    for i in range(n):
        for j in range(n):
            Pp[i, j] += Qk * Wa[i, j] + Rk * Wb[i, j]


@njit(cache=True, nogil=True)
def _gen_filter(z, Qs, Rs, A, Wa, Wb, c, x0, P0, store, xf, Pf, xpa, Ppa, Kst, nust, sinv, prow, xf0):
    """Kalman filter; with store = 1 keeps (K, ν, 1/s, P row 0, x0) for Bryson–Frazier,
    with store = 2 keeps full filtered/predicted moments for RTS; returns the log-likelihood."""
    N = z.shape[0]
    n = A.shape[0]
    x = x0.copy()
    P = P0.copy()
    xp = x0.copy()
    Pp = P0.copy()
    T = np.empty((n, n))
    g = np.empty(n)
    K = np.empty(n)
    ll = 0.0
    for k in range(N):
        if k > 0:
            _gen_predict(A, x, P, Qs[k], Rs[k], Wa, Wb, xp, Pp, T)
        zk = z[k]
        s = 0.0
        nu = 0.0
        if zk == zk:
            for i in range(n):
                t = 0.0
                for l in range(n):
                    t += Pp[i, l] * c[l]
                g[i] = t
            pred = 0.0
            for i in range(n):
                s += c[i] * g[i]
                pred += c[i] * xp[i]
            nu = zk - pred
            for i in range(n):
                K[i] = g[i] / s
                x[i] = xp[i] + K[i] * nu
            # Joseph form without measurement noise: (I − K cᵀ) Pp (I − K cᵀ)ᵀ
            for i in range(n):
                for j in range(n):
                    P[i, j] = Pp[i, j] - K[i] * g[j]
            for i in range(n):
                t = 0.0
                for l in range(n):
                    t += P[i, l] * c[l]
                T[0, i] = t
            for i in range(n):
                for j in range(n):
                    P[i, j] -= T[0, i] * K[j]
            for i in range(n):
                for j in range(i + 1, n):
                    v = 0.5 * (P[i, j] + P[j, i])
                    P[i, j] = v
                    P[j, i] = v
            ll += -0.5 * (_LOG_2PI + np.log(s) + nu * nu / s)
        else:
            for i in range(n):
                x[i] = xp[i]
                for j in range(n):
                    P[i, j] = Pp[i, j]
        if store == 1:
            for i in range(n):
                Kst[k, i] = K[i] if s > 0.0 else 0.0
                prow[k, i] = P[0, i]
            nust[k] = nu
            sinv[k] = 1.0 / s if s > 0.0 else 0.0
            xf0[k] = x[0]
        elif store == 2:
            for i in range(n):
                xf[k, i] = x[i]
                xpa[k, i] = xp[i]
                for j in range(n):
                    Pf[k, i, j] = P[i, j]
                    Ppa[k, i, j] = Pp[i, j]
            xf0[k] = x[0]
    return ll


@njit(cache=True, nogil=True)
def _gen_backward_bf(A, c, xf0, prow, Kst, nust, sinv, out_mean, out_var):
    """Modified Bryson–Frazier pass for a dense A (same recursions as :func:`_backward_bf`)."""
    n = A.shape[0]
    N = xf0.shape[0]
    lam = np.zeros(n)
    Lam = np.zeros((n, n))
    lt = np.empty(n)
    Lt = np.empty((n, n))
    u = np.empty(n)
    M = np.empty((n, n))
    for k in range(N - 1, -1, -1):
        s1 = 0.0
        s2 = 0.0
        for i in range(n):
            pi = prow[k, i]
            s1 += pi * lam[i]
            t = 0.0
            for j in range(n):
                t += Lam[i, j] * prow[k, j]
            s2 += pi * t
        out_mean[k] = xf0[k] - s1
        out_var[k] = prow[k, 0] - s2
        if k == 0:
            break
        si = sinv[k]
        if si > 0.0:
            gam = 0.0
            for i in range(n):
                gam += Kst[k, i] * lam[i]
            for i in range(n):
                lt[i] = lam[i] - c[i] * (gam + nust[k] * si)
            for i in range(n):
                t = 0.0
                for j in range(n):
                    t += Lam[i, j] * Kst[k, j]
                u[i] = t
            for i in range(n):
                for j in range(n):
                    Lt[i, j] = Lam[i, j] - u[i] * c[j]
            for j in range(n):
                t = 0.0
                for i in range(n):
                    t += Kst[k, i] * Lt[i, j]
                u[j] = t
            for i in range(n):
                for j in range(n):
                    Lt[i, j] -= c[i] * u[j]
            for i in range(n):
                for j in range(i, n):
                    v = 0.5 * (Lt[i, j] + Lt[j, i]) + si * c[i] * c[j]
                    Lt[i, j] = v
                    Lt[j, i] = v
        else:
            for i in range(n):
                lt[i] = lam[i]
                for j in range(n):
                    Lt[i, j] = Lam[i, j]
        for j in range(n):
            s = 0.0
            for i in range(n):
                s += A[i, j] * lt[i]
            lam[j] = s
        _mm(Lt, A, M)
        for i in range(n):
            for j in range(n):
                s = 0.0
                for l in range(n):
                    s += A[l, i] * M[l, j]
                Lam[i, j] = s


@njit(cache=True, nogil=True)
def _gen_backward_rts(A, xf, Pf, xpa, Ppa, out_mean, out_var):
    N, n = xf.shape
    xsm = xf[N - 1].copy()
    Psm = Pf[N - 1].copy()
    out_mean[N - 1] = xsm[0]
    out_var[N - 1] = Psm[0, 0]
    AP = np.empty((n, n))
    G = np.empty((n, n))
    D = np.empty((n, n))
    GD = np.empty((n, n))
    dx = np.empty(n)
    xtmp = np.empty(n)
    for k in range(N - 2, -1, -1):
        _mm(A, Pf[k], AP)
        S = Ppa[k + 1].copy()
        _chol_solve_inplace(S, AP)  # AP ← (P⁻_{k+1})⁻¹ A P_k = Gᵀ
        for i in range(n):
            for j in range(n):
                G[i, j] = AP[j, i]
        for i in range(n):
            dx[i] = xsm[i] - xpa[k + 1, i]
            for j in range(n):
                D[i, j] = Psm[i, j] - Ppa[k + 1, i, j]
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += G[i, j] * dx[j]
            xtmp[i] = xf[k, i] + s
        _mm(G, D, GD)
        _mmT(GD, G, Psm)
        for i in range(n):
            for j in range(n):
                Psm[i, j] += Pf[k, i, j]
        for i in range(n):
            for j in range(i + 1, n):
                v = 0.5 * (Psm[i, j] + Psm[j, i])
                Psm[i, j] = v
                Psm[j, i] = v
        for i in range(n):
            xsm[i] = xtmp[i]
        out_mean[k] = xsm[0]
        out_var[k] = Psm[0, 0]


def coloured_model(m: int, noise) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Internal matrices ``A, W_a, W_b, c`` of the anomaly ⊕ noise-block model.

    ``A`` (n×n, n = m + s): anomaly block upper-triangular ones (difference basis), noise
    block ``F``; ``W_a``: ones on the anomaly block (``Q_k·W_a``); ``W_b``: the noise
    block's ``W`` (``R_k·W_b``); ``c``: measurement row ``(1, 0…0, h)``."""
    F, W, h = noise.block()
    s = F.shape[0]
    n = m + s
    A = np.zeros((n, n))
    Wa = np.zeros((n, n))
    Wb = np.zeros((n, n))
    c = np.zeros(n)
    for i in range(m):
        A[i, i:m] = 1.0
    Wa[:m, :m] = 1.0
    A[m:, m:] = F
    Wb[m:, m:] = W
    c[0] = 1.0
    c[m:] = h
    return A, Wa, Wb, c


def _prepare_coloured(z_mgal, Q_mgal2, R_cm2s2, dt_s, m, noise, x0, P0):
    m = _check_m(m)
    dt = _check_dt(dt_s)
    if abs(float(noise.dt_s) - dt) > 1e-9 * dt:
        raise ValueError(f"the noise model is for steps of {noise.dt_s:g} s, the data have {dt:g} s")
    z = np.ascontiguousarray(np.asarray(z_mgal, dtype=float))
    if z.ndim != 1:
        raise ValueError(f"z_mgal must be 1-D, got shape {z.shape}")
    if np.any(np.isinf(z)):
        raise ValueError("z_mgal contains infinite values (use NaN for missing epochs)")
    N = z.shape[0]
    finite = np.isfinite(z)
    nfin = int(finite.sum())
    if N < m + 2 or nfin < m + 2:
        raise ValueError(f"line too short for m={m}: need at least {m + 2} finite epochs, got {nfin} finite of {N}")
    Q = _per_epoch("Q_mgal2", Q_mgal2, N)
    R = _per_epoch("R_cm2s2", R_cm2s2, N)
    A, Wa, Wb, c = coloured_model(m, noise)
    n = A.shape[0]
    Tm = np.eye(n)
    Tm[:m, :m] = _to_internal(m, 1.0)[:m, :m]
    if x0 is None:
        nwin = max(int(round(PRIOR_MEAN_WINDOW_S / dt)), m + 2)
        idx = np.flatnonzero(finite)
        sel = idx[idx < nwin]
        if sel.size < m + 2:
            sel = idx[: m + 2]
        x0v = np.zeros(n)
        x0v[0] = float(np.mean(z[sel]))
    else:
        x0u = np.asarray(x0, dtype=float).reshape(-1)
        if x0u.shape != (n,):
            raise ValueError(f"x0 must have shape ({n},), got {np.shape(x0)}")
        x0v = Tm @ x0u
    if P0 is None:
        P0v = np.zeros((n, n))
        P0v[0, 0] = PRIOR_DG_STD_MGAL ** 2
        for i in range(1, m):
            P0v[i, i] = PRIOR_DIFF_STD_MGAL ** 2
        P0v[m:, m:] = noise.stationary_covariance(R[0])
    else:
        P0u = np.asarray(P0, dtype=float)
        if P0u.shape != (n, n):
            raise ValueError(f"P0 must have shape ({n}, {n}), got {P0u.shape}")
        if not np.allclose(P0u, P0u.T) or np.any(np.linalg.eigvalsh(P0u) < -1e-12 * np.abs(P0u).max()):
            raise ValueError("P0 must be symmetric positive semi-definite")
        P0v = Tm @ P0u @ Tm.T
        P0v = 0.5 * (P0v + P0v.T)
    return z, Q, R, A, Wa, Wb, c, np.ascontiguousarray(x0v), np.ascontiguousarray(P0v)


def _smooth_coloured(z_mgal, Q_mgal2, R_cm2s2, dt_s, m, noise, method, x0, P0) -> SmootherResult:
    z, Q, R, A, Wa, Wb, c, x0v, P0v = _prepare_coloured(z_mgal, Q_mgal2, R_cm2s2, dt_s, m, noise, x0, P0)
    N, n = z.shape[0], A.shape[0]
    mean = np.empty(N)
    var = np.empty(N)
    filt = np.empty(N)
    if method == "bf":
        Kst = np.empty((N, n))
        prow = np.empty((N, n))
        nust = np.empty(N)
        sinv = np.empty(N)
        e2 = np.empty((1, 1))
        e3 = np.empty((1, 1, 1))
        ll = _gen_filter(z, Q, R, A, Wa, Wb, c, x0v, P0v, 1, e2, e3, e2, e3, Kst, nust, sinv, prow, filt)
        _gen_backward_bf(A, c, filt, prow, Kst, nust, sinv, mean, var)
        innov = np.where(sinv > 0.0, nust * np.sqrt(np.maximum(sinv, 0.0)), np.nan)
        return _finish(mean, var, ll, filt, innov)
    else:
        xf = np.empty((N, n))
        Pf = np.empty((N, n, n))
        xpa = np.empty((N, n))
        Ppa = np.empty((N, n, n))
        e1 = np.empty(1)
        e2 = np.empty((1, 1))
        ll = _gen_filter(z, Q, R, A, Wa, Wb, c, x0v, P0v, 2, xf, Pf, xpa, Ppa, e2, e1, e1, e2, filt)
        _gen_backward_rts(A, xf, Pf, xpa, Ppa, mean, var)
    return _finish(mean, var, ll, filt)


def _finish(mean, var, ll, filt, innov=None) -> SmootherResult:
    if np.any(var < 0.0):
        # Only round-off can produce this; report rather than hide it.
        neg = var.min()
        if neg < -1e-9 * max(1.0, float(np.max(np.abs(var)))):
            raise FloatingPointError(f"negative posterior variance {neg:g} (numerical breakdown)")
        var = np.maximum(var, 0.0)
    return SmootherResult(dg_mgal=mean, dg_std_mgal=np.sqrt(var), loglik=float(ll), filtered_mgal=filt,
                          innovations=innov)


def _white_level(noise, dt_s) -> float | None:
    """R multiplier that turns a white-velocity NoiseModel into the fast path's R (or None)."""
    if noise is None:
        return 1.0
    if not noise.is_white_velocity:
        return None
    w = next(c.weight for c in noise.components if c.weight > 0)
    return w / (MGAL_PER_CMS2 / float(dt_s)) ** 2


# ---------------------------------------------------------------------------
# Generic linear-Gaussian models (numpy; small problems)
# ---------------------------------------------------------------------------


class GenericModel(NamedTuple):
    """Checked inputs of the generic smoothers (:func:`generic_model_inputs`).

    Attributes
    ----------
    A : ndarray, shape (n, n)
    Q : ndarray, shape (T, n, n)
        Process noise covariance per step (broadcast when one was given).
    C : ndarray, shape (p, n)
    R : ndarray, shape (T, p, p)
        Measurement noise covariance per epoch.
    z : ndarray, shape (T, p)
    x0 : ndarray, shape (n,)
    P0 : ndarray, shape (n, n)
    u : ndarray, shape (T, n)
        Known input (zeros when none was given).
    """

    A: np.ndarray
    Q: np.ndarray
    C: np.ndarray
    R: np.ndarray
    z: np.ndarray
    x0: np.ndarray
    P0: np.ndarray
    u: np.ndarray


def generic_model_inputs(A, Qmat, C, Rmeas, z, x0, P0, u) -> GenericModel:
    """Check and shape the arguments of :func:`kalman_filter` (see there).

    Raises
    ------
    ValueError
        Non-square ``A``, ``C`` with the wrong number of columns, ``z`` not (T, p),
        fewer than 2 epochs, covariances or ``u`` of the wrong shape.
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    n = A.shape[0]
    if A.shape != (n, n):
        raise ValueError(f"A must be square, got {A.shape}")
    C = np.atleast_2d(np.asarray(C, dtype=float))
    p = C.shape[0]
    if C.shape[1] != n:
        raise ValueError(f"C must have {n} columns, got {C.shape}")
    z = np.asarray(z, dtype=float)
    if z.ndim == 1:
        z = z[:, None]
    if z.ndim != 2 or z.shape[1] != p:
        raise ValueError(f"z must have shape (T, {p}), got {np.shape(z)}")
    N = z.shape[0]
    if N < 2:
        raise ValueError("need at least 2 epochs")

    def _cov_seq(M, name, d):
        M = np.asarray(M, dtype=float)
        if M.ndim == 0 and d == 1:
            M = M.reshape(1, 1)
        elif M.ndim == 1 and d == 1 and M.shape[0] == N:
            M = M.reshape(N, 1, 1)
        if M.ndim == 2:
            M = np.broadcast_to(M, (N, d, d))
        if M.shape != (N, d, d):
            raise ValueError(f"{name} must be ({d},{d}) or ({N},{d},{d}), got {M.shape}")
        return M

    Qm = _cov_seq(Qmat, "Qmat", n)
    Rm = _cov_seq(Rmeas, "Rmeas", p)
    x0 = np.asarray(x0, dtype=float).reshape(n)
    P0 = np.asarray(P0, dtype=float).reshape(n, n)
    if u is None:
        u = np.zeros((N, n))
    else:
        u = np.asarray(u, dtype=float)
        if u.ndim == 1 and n == 1:
            u = u[:, None]
        if u.shape != (N, n):
            raise ValueError(f"u must have shape ({N}, {n}), got {u.shape}")
    return GenericModel(A, Qm, C, Rm, z, x0, P0, u)


class FilteredStates(NamedTuple):
    """Result of :func:`kalman_filter` (unpacks as ``xf, Pf, xp, Pp, loglik``).

    Attributes
    ----------
    xf : ndarray, shape (T, n)
        Filtered means.
    Pf : ndarray, shape (T, n, n)
        Filtered covariances.
    xp : ndarray, shape (T, n)
        Predicted means (``xp[0] = x0``).
    Pp : ndarray, shape (T, n, n)
        Predicted covariances (``Pp[0] = P0``).
    loglik : float
        Innovations log-likelihood.
    """

    xf: np.ndarray
    Pf: np.ndarray
    xp: np.ndarray
    Pp: np.ndarray
    loglik: float


class SmoothedStates(NamedTuple):
    """Result of :func:`rts_smooth` (unpacks as ``xs, Ps, loglik``).

    Attributes
    ----------
    xs : ndarray, shape (T, n)
        Smoothed means.
    Ps : ndarray, shape (T, n, n)
        Smoothed covariances.
    loglik : float
        Innovations log-likelihood of the forward filter.
    """

    xs: np.ndarray
    Ps: np.ndarray
    loglik: float


def kalman_filter(A, Qmat, C, Rmeas, z, x0, P0, u=None) -> FilteredStates:
    """Kalman filter for ``x_k = A x_{k−1} + u_k + w_k``, ``z_k = C x_k + v_k``.

    Parameters
    ----------
    A : (n, n); Qmat : (n, n) or (T, n, n); C : (p, n); Rmeas : (p, p) or (T, p, p)
    z : (T,) or (T, p), NaN rows = no measurement
    x0, P0 : prior of x_0 before z_0 (no prediction at k = 0)
    u : (T, n), optional known input (u_0 unused)

    Returns
    -------
    FilteredStates
        ``xf (T, n), Pf (T, n, n), xp (T, n), Pp (T, n, n), loglik (float)``.
        The update uses the Joseph form.
    """
    A, Qm, C, Rm, z, x0, P0, u = generic_model_inputs(A, Qmat, C, Rmeas, z, x0, P0, u)
    N, n = z.shape[0], A.shape[0]
    xf = np.empty((N, n))
    Pf = np.empty((N, n, n))
    xp = np.empty((N, n))
    Pp = np.empty((N, n, n))
    x, P = x0.copy(), P0.copy()
    ll = 0.0
    I = np.eye(n)
    for k in range(N):
        if k > 0:
            x = A @ x + u[k]
            P = A @ P @ A.T + Qm[k]
        xp[k], Pp[k] = x, P
        if np.all(np.isfinite(z[k])):
            S = C @ P @ C.T + Rm[k]
            Kt = np.linalg.solve(S, C @ P)  # Kᵀ
            K = Kt.T
            nu = z[k] - C @ x
            x = x + K @ nu
            IKC = I - K @ C
            P = IKC @ P @ IKC.T + K @ Rm[k] @ K.T
            P = 0.5 * (P + P.T)
            sign, logdet = np.linalg.slogdet(S)
            ll -= 0.5 * (len(nu) * _LOG_2PI + logdet + nu @ np.linalg.solve(S, nu))
        xf[k], Pf[k] = x, P
    return FilteredStates(xf, Pf, xp, Pp, float(ll))


def rts_smooth(A, Qmat, C, Rmeas, z, x0, P0, u=None) -> SmoothedStates:
    """Rauch–Tung–Striebel fixed-interval smoother for a generic linear-Gaussian model.

    Same arguments as :func:`kalman_filter`.  The gain ``G = P_k Aᵀ (P⁻_{k+1})⁻¹`` uses a
    least-squares solve (pseudo-inverse if the predicted covariance is singular).

    Returns
    -------
    SmoothedStates
        ``xs (T, n), Ps (T, n, n), loglik (float)``.
    """
    A = np.atleast_2d(np.asarray(A, dtype=float))
    xf, Pf, xp, Pp, ll = kalman_filter(A, Qmat, C, Rmeas, z, x0, P0, u)
    N = xf.shape[0]
    xs = xf.copy()
    Ps = Pf.copy()
    for k in range(N - 2, -1, -1):
        Gt = np.linalg.lstsq(Pp[k + 1], A @ Pf[k], rcond=None)[0]
        G = Gt.T
        xs[k] = xf[k] + G @ (xs[k + 1] - xp[k + 1])
        Pk = Pf[k] + G @ (Ps[k + 1] - Pp[k + 1]) @ G.T
        Ps[k] = 0.5 * (Pk + Pk.T)
    return SmoothedStates(xs, Ps, ll)


def mixture_std_mgal(center_mgal, means_mgal, stds_mgal, weights) -> np.ndarray:
    """Root mean square deviation from ``center_mgal`` of a mixture of Gaussians (law of total
    variance): ``sqrt(Σ_k w_k (σ_k² + (μ_k − c)²))`` per epoch.

    Parameters
    ----------
    center_mgal : array_like, shape (n,)
        The estimate the spread is measured about (mGal).
    means_mgal, stds_mgal : array_like, shape (K, n)
        Each component's posterior mean and std (mGal).
    weights : array_like, shape (K, n)
        Component probabilities at each epoch (non-negative; normalised here).

    Returns
    -------
    ndarray, shape (n,)
        mGal.
    """
    c = np.asarray(center_mgal, dtype=float)
    mu = np.atleast_2d(np.asarray(means_mgal, dtype=float))
    sd = np.atleast_2d(np.asarray(stds_mgal, dtype=float))
    w = np.atleast_2d(np.asarray(weights, dtype=float))
    if not (mu.shape == sd.shape == w.shape and mu.shape[1:] == c.shape):
        raise ValueError(f"shapes differ: center {c.shape}, means {mu.shape}, stds {sd.shape}, weights {w.shape}")
    if np.any(w < 0) or np.any(sd < 0):
        raise ValueError("weights and stds must be non-negative")
    tot = w.sum(axis=0)
    if np.any(tot <= 0):
        raise ValueError("the weights of some epoch sum to zero")
    return np.sqrt(np.sum(w * (sd ** 2 + (mu - c) ** 2), axis=0) / tot)


def level_spread_std_mgal(z_mgal, Q_mgal2, R_cm2s2, dt_s, factor: float, m: int = 2, method: str = "bf",
                          noise=None) -> SmootherResult:
    """Smoother at ``Q_mgal2`` whose std also carries an uncertain anomaly level.

    Where the data cannot fix the level ``Q`` better than a factor ``factor`` either way,
    the estimate at ``Q`` may be off by as much as it differs from the estimates at
    ``Q/factor`` and ``factor·Q``.  The returned std adds the larger of those two
    differences in quadrature to the posterior std at ``Q``:
    ``sqrt(σ_Q² + max((x_{Q/f} − x_Q)², (x_{f·Q} − x_Q)²))`` per epoch; the mean is ``x_Q``.

    Parameters
    ----------
    z_mgal, Q_mgal2, R_cm2s2, dt_s, m, method, noise
        As in :func:`kalman_smooth` (``Q_mgal2`` may vary along the line; it is scaled as a
        whole).
    factor : float
        ≥ 1; 1 gives :func:`kalman_smooth` unchanged.

    Returns
    -------
    SmootherResult
        ``dg_mgal`` at ``Q``; ``dg_std_mgal`` widened as above (mGal), shape (T,).
    """
    f = float(factor)
    if not np.isfinite(f) or f < 1.0:
        raise ValueError(f"factor must be a finite number ≥ 1, got {factor!r}")
    Q = np.asarray(Q_mgal2, dtype=float)
    mid = kalman_smooth(z_mgal, Q, R_cm2s2, dt_s, m=m, method=method, noise=noise)
    if f == 1.0:
        return mid
    x = np.asarray(mid.dg_mgal)
    d2 = np.zeros_like(x)
    for q in (Q / f, Q * f):
        other = np.asarray(kalman_smooth(z_mgal, q, R_cm2s2, dt_s, m=m, method=method, noise=noise).dg_mgal)
        d2 = np.maximum(d2, (other - x) ** 2)
    return replace(mid, dg_std_mgal=np.sqrt(np.asarray(mid.dg_std_mgal) ** 2 + d2))
