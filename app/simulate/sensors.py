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


# ---------------------------------------------------------------- platform gravimeter (new regimes)
#
# A platform gravimeter (AIRGrav class) delivers f_z at 1–10 Hz after an internal digital low-pass
# (anti-alias) filter that the processing does not know.  It is modelled as a linear-phase FIR whose
# group delay the instrument removes from its time stamps, i.e. a zero-phase filter: ``n`` cascaded
# moving averages (boxcars) of width ``W`` s (n = 2: a triangular window of base 2W,
# H(f) = sinc(f·W)^n).  Everything below is exact for piecewise-polynomial inputs.


def taylor_shift(c: np.ndarray, delta) -> np.ndarray:
    """Coefficients (highest power first, one column per piece) of ``p(s + delta)`` given those of
    ``p(s)`` (repeated synthetic division; exact up to rounding)."""
    a = np.array(c, dtype=float, copy=True)
    K = a.shape[0] - 1
    d = np.broadcast_to(np.asarray(delta, dtype=float), a.shape[1:])
    for k in range(K):
        for j in range(1, K + 1 - k):
            a[j] += d * a[j - 1]
    return a


def boxcar_pp(pp: PPoly, width_s: float, merge_s: float = 1e-7) -> PPoly:
    """Exact centred moving average ``M(t) = (1/W)·∫_{t−W/2}^{t+W/2} u`` of a piecewise polynomial.

    The result is a piecewise polynomial one degree higher, defined on ``[x0 + W/2, x_end − W/2]``,
    with breakpoints at the input's breakpoints shifted by ±W/2 (near-coincident ones merged).  Each
    new piece is built from the antiderivative's pieces re-centred by a Taylor shift, so only one
    level of antiderivative is involved (no cancellation of large accumulated integrals).
    """
    W = float(width_s)
    if W <= 0:
        raise ValueError("boxcar width must be positive")
    F = pp.antiderivative()
    x = F.x
    half = 0.5 * W
    lo, hi = x[0] + half, x[-1] - half
    if hi <= lo:
        raise ValueError("input too short for the boxcar")
    cand = np.concatenate([x - half, x + half, [lo, hi]])
    cand = np.sort(cand[(cand >= lo) & (cand <= hi)])
    keep = np.concatenate([[True], np.diff(cand) > merge_s])
    b = cand[keep]
    b[-1] = hi
    mid = 0.5 * (b[:-1] + b[1:])
    iu = np.clip(np.searchsorted(x, mid + half, side="right") - 1, 0, x.size - 2)
    il = np.clip(np.searchsorted(x, mid - half, side="right") - 1, 0, x.size - 2)
    cu = taylor_shift(F.c[:, iu], b[:-1] + half - x[iu])
    cl = taylor_shift(F.c[:, il], b[:-1] - half - x[il])
    return PPoly((cu - cl) / W, b)


def fir_pp(pp: PPoly, n_boxcars: int, width_s: float) -> PPoly:
    """The zero-phase FIR of ``n_boxcars`` cascaded boxcars of ``width_s`` applied exactly."""
    out = pp
    for _ in range(int(n_boxcars)):
        out = boxcar_pp(out, width_s)
    return out


def fir_gain(f, n_boxcars: int, width_s: float) -> np.ndarray:
    """Frequency response of :func:`fir_pp` (real: zero phase), ``sinc(f·W)^n``."""
    return np.sinc(np.asarray(f, dtype=float) * width_s) ** int(n_boxcars)


class LaggedResponseN:
    """Exact response of ``τ·ẏ + k·y = u`` to a piecewise polynomial ``u`` of any degree.

    Same method as :class:`LaggedResponse` (which is kept unchanged for the original presets):
    on each piece ``y(s) = p(s) + (y_i − p(0))·exp(−s/T)``, ``T = τ/k``,
    ``p = Σ_j (−T)^j u^{(j)} / k``; interval means from the ODE, ``∫y = (∫u − τ·Δy)/k``.
    """

    def __init__(self, u_pp: PPoly, tau_s: float, scale: float):
        self.u_pp = u_pp
        self.x = np.asarray(u_pp.x, dtype=float)
        self.tau = float(tau_s)
        self.k = float(scale)
        self.U_pp = u_pp.antiderivative()
        if self.tau == 0.0:
            return
        T = self.tau / self.k
        self.T = T
        c = np.asarray(u_pp.c, dtype=float)
        K = c.shape[0] - 1
        d = c.copy()
        der = c
        for j in range(1, K + 1):
            kk = der.shape[0] - 1
            der = der[:-1] * np.arange(kk, 0, -1)[:, None]
            d[-der.shape[0]:] += (-T) ** j * der
        d /= self.k
        self.d = d
        h = np.diff(self.x)
        beta = np.exp(-h / T)
        p_end = d[0].copy()
        for row in d[1:]:
            p_end = p_end * h + row
        rhs = np.empty(h.size + 1)
        rhs[:-1] = p_end - beta * d[-1]
        rhs[-1] = c[-1, 0] / self.k       # quasi-static start u(x0)/k
        self.y_knots = _recurrence(beta, rhs)

    def y(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        if self.tau == 0.0:
            return self.u_pp(t) / self.k
        i = np.clip(np.searchsorted(self.x, t, side="right") - 1, 0, self.x.size - 2)
        s = t - self.x[i]
        d = self.d[:, i]
        p = d[0].copy()
        for row in d[1:]:
            p = p * s + row
        return p + (self.y_knots[i] - d[-1]) * np.exp(-s / self.T)

    def interval_means(self, edges) -> np.ndarray:
        e = np.asarray(edges, dtype=float)
        U = self.U_pp(e)
        if self.tau == 0.0:
            return np.diff(U) / np.diff(e) / self.k
        return (np.diff(U) - self.tau * np.diff(self.y(e))) / (self.k * np.diff(e))


def gauss_markov(t, sigma: float, tau_s: float, rng) -> np.ndarray:
    """Stationary first-order Gauss–Markov sequence (std ``sigma``, correlation ``exp(−|Δt|/τ)``)
    at times ``t``; zeros when ``sigma <= 0``."""
    t = np.asarray(t, dtype=float)
    if sigma <= 0 or t.size == 0:
        return np.zeros(t.size)
    dt = np.diff(t, prepend=t[0])
    a = np.exp(-dt / tau_s)
    w = rng.standard_normal(t.size) * sigma
    return _ar1(a, np.sqrt(1.0 - a ** 2) * w, w[0])


@njit(cache=True)
def _ar1(a, e, x0):
    out = np.empty(a.size)
    out[0] = x0
    for i in range(1, a.size):
        out[i] = a[i] * out[i - 1] + e[i]
    return out
