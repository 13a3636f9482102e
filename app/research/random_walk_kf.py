"""Seed-003 experiment: scalar random-walk Kalman filter and RTS smoother.

Research only (the product never runs it): ``x_k = x_{k−1} + w_k`` (Var Q),
``y_k = x_k + v_k`` (Var R), diffuse start, Q by maximum likelihood when not given
(:func:`random_walk_kf`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import optimize

_LOG_2PI = float(np.log(2.0 * np.pi))


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
    xf = np.empty(N)
    Pf = np.empty(N)
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
    xs = np.empty(N)
    Ps = np.empty(N)
    _rw_smooth(Q, k0, xf, Pf, xs, Ps)
    return RandomWalkResult(filtered=xf, filtered_var=Pf, smoothed=xs, smoothed_var=Ps,
                            Q=Q, R=R, loglik=float(ll))
