"""Sensor models: the gravimeter's first-order lag solved exactly, GNSS noise.

The gravimeter model (SPEC §1, seed 001 eq. 4) is ``τ·ẏ + k·y = u(t)``.  When the
input ``u`` is a piecewise cubic (``scipy.interpolate.PPoly``) the solution is
exact: on each piece ``y(s) = p(s) + (y_i − p(0))·exp(−s/T)`` with ``T = τ/k`` and
the polynomial particular solution ``p = (u − T u' + T² u'' − T³ u''')/k``.  The
mean of ``y`` over any interval then follows from the ODE itself:
``∫_a^b y = (U(b) − U(a) − τ·(y(b) − y(a)))/k`` with ``U`` the antiderivative of
``u``.  No time-stepping error is involved.
"""

from __future__ import annotations

import numpy as np
from numba import njit
from scipy.interpolate import PPoly


@njit(cache=True)
def _recurrence(beta, c):  # y[i+1] = beta[i]*y[i] + c[i], y[0] given as c[-1]
    n = beta.size
    y = np.empty(n + 1)
    y[0] = c[n]
    for i in range(n):
        y[i + 1] = beta[i] * y[i] + c[i]
    return y


class LaggedResponse:
    """Exact response ``y`` of ``τ·ẏ + k·y = u`` to a piecewise-cubic input ``u``.

    Parameters
    ----------
    u_pp : PPoly
        Input (any unit), degree ≤ 3.
    tau_s : float
        Time constant τ (s); 0 gives ``y = u/k``.
    scale : float
        Scale k (dimensionless).

    Notes
    -----
    The initial value is the quasi-static ``u(x0)/k``; the start-up transient decays
    as ``exp(−t/T)``, so start the input well (≥ 10 T) before the first use.
    """

    def __init__(self, u_pp: PPoly, tau_s: float, scale: float):
        c = np.asarray(u_pp.c, dtype=float)
        if c.shape[0] > 4:
            raise ValueError("input must be at most cubic")
        if c.shape[0] < 4:
            c = np.vstack([np.zeros((4 - c.shape[0], c.shape[1])), c])
        self.x = np.asarray(u_pp.x, dtype=float)
        self.tau = float(tau_s)
        self.k = float(scale)
        self.u_pp = PPoly(c, self.x)
        self.U_pp = self.u_pp.antiderivative()
        if self.tau == 0.0:
            return
        T = self.tau / self.k
        self.T = T
        c0, c1, c2, c3 = c
        self.d = np.array([c0, c1 - 3 * T * c0, c2 - 2 * T * c1 + 6 * T * T * c0,
                           c3 - T * c2 + 2 * T * T * c1 - 6 * T ** 3 * c0]) / self.k
        h = np.diff(self.x)
        beta = np.exp(-h / T)
        d = self.d
        p_end = ((d[0] * h + d[1]) * h + d[2]) * h + d[3]
        rhs = np.empty(h.size + 1)
        rhs[:-1] = p_end - beta * d[3]
        rhs[-1] = c3[0] / self.k       # start from the quasi-static value u(x0)/k
        self.y_knots = _recurrence(beta, rhs)

    def y(self, t) -> np.ndarray:
        """Point values of the response at times ``t`` (inside the knot range)."""
        t = np.asarray(t, dtype=float)
        if self.tau == 0.0:
            return self.u_pp(t) / self.k
        i = np.clip(np.searchsorted(self.x, t, side="right") - 1, 0, self.x.size - 2)
        s = t - self.x[i]
        d = self.d[:, i]
        p = ((d[0] * s + d[1]) * s + d[2]) * s + d[3]
        return p + (self.y_knots[i] - d[3]) * np.exp(-s / self.T)

    def interval_means(self, edges) -> np.ndarray:
        """Mean of ``y`` over consecutive intervals ``[edges[j], edges[j+1]]``."""
        e = np.asarray(edges, dtype=float)
        U = self.U_pp(e)
        if self.tau == 0.0:
            return np.diff(U) / np.diff(e) / self.k
        Y = self.y(e)
        return (np.diff(U) - self.tau * np.diff(Y)) / (self.k * np.diff(e))


def interval_means_pp(pp: PPoly, edges) -> np.ndarray:
    """Exact mean of a piecewise polynomial over consecutive intervals of ``edges``."""
    e = np.asarray(edges, dtype=float)
    return np.diff(pp.antiderivative()(e)) / np.diff(e)


def quadratic_from_means(t_epochs, means) -> PPoly:
    """Smooth function whose mean over each (t_{k−1}, t_k] equals ``means[k]``.

    The derivative of the cubic spline through the cumulative integral, a C¹
    piecewise quadratic.  ``means[0]`` is used for the half-open interval before
    ``t_epochs[0]`` of the same length.

    Parameters
    ----------
    t_epochs : ndarray, shape (n,)
    means : ndarray, shape (n,)
    """
    from scipy.interpolate import CubicSpline

    t = np.asarray(t_epochs, dtype=float)
    m = np.asarray(means, dtype=float)
    dt0 = t[1] - t[0]
    tt = np.concatenate([[t[0] - dt0], t])
    G = np.concatenate([[0.0], np.cumsum(m * np.diff(tt))])
    cs = CubicSpline(tt, G, bc_type="not-a-knot")
    return PPoly(cs.c, cs.x).derivative()


def noise_episodes(t0: float, t1: float, rate_per_h: float, len_s, factor, rng):
    """Random noisy episodes: list of (start, end, std factor)."""
    n = rng.poisson(rate_per_h * (t1 - t0) / 3600.0) if rate_per_h > 0 else 0
    eps = []
    for _ in range(n):
        L = rng.uniform(*len_s)
        s = rng.uniform(t0, max(t0, t1 - L))
        eps.append((float(s), float(s + L), float(rng.uniform(*factor))))
    return eps


def sigma_factor(t, episodes) -> np.ndarray:
    """Std multiplier in force at times ``t`` (max over overlapping episodes, else 1)."""
    f = np.ones_like(np.asarray(t, dtype=float))
    for s, e, k in episodes:
        m = (t >= s) & (t < e)
        f[m] = np.maximum(f[m], k)
    return f
