"""Markov-jump anomaly (seed 000): spatially coherent state map, along-line random walk.

The state (0 = low Q "plain", 1 = high Q "mountain") is a thresholded smooth Gaussian
random field over the survey area, so neighbouring lines see the same state
pattern.  Its smoothness is chosen so that along east–west lines, sampled on a
1 km grid, the transition probabilities are near the targets ``a11``, ``a22``.
Along each line the anomaly follows ``∇δg_k = q_k`` (m = 1), ``Var q_k = Q(state)``
in mGal² per GNSS step, the state held constant on blocks of 100 epochs (1 km).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import RegularGridInterpolator
from scipy.ndimage import gaussian_filter


@dataclass
class StateMap:
    """Smooth field ``s`` on a km grid (relative to the survey centre); state = s > thr."""

    x_km: np.ndarray
    y_km: np.ndarray
    field: np.ndarray       # (ny, nx)
    threshold: float
    sigma_km: float

    def __post_init__(self):
        self._interp = RegularGridInterpolator((self.y_km, self.x_km), self.field,
                                               bounds_error=False, fill_value=None)

    def state(self, x_km, y_km) -> np.ndarray:
        """State index (0 or 1) at relative coordinates (km)."""
        x = np.asarray(x_km, float)
        y = np.asarray(y_km, float)
        v = self._interp(np.column_stack([y.ravel(), x.ravel()])).reshape(np.broadcast(x, y).shape)
        return (v > self.threshold).astype(np.int64)


def transition_counts(paths) -> np.ndarray:
    """2×2 counts of i→j transitions over a list of integer state sequences."""
    C = np.zeros((2, 2))
    for p in paths:
        p = np.asarray(p, dtype=np.int64)
        if p.size > 1:
            np.add.at(C, (p[:-1], p[1:]), 1.0)
    return C


def empirical_transition(paths) -> np.ndarray:
    """Row-normalised transition matrix of the sequences (rows with no data: identity)."""
    C = transition_counts(paths)
    P = np.eye(2)
    for i in range(2):
        if C[i].sum() > 0:
            P[i] = C[i] / C[i].sum()
    return P


def make_state_map(extent_km, a11: float, a22: float, rng, step_km: float = 1.0,
                   rows_y_km=None, row_x_km=None, n_draws: int = 6) -> StateMap:
    """Thresholded smooth random field whose along-x switching matches (a11, a22).

    Parameters
    ----------
    extent_km : (xmin, xmax, ymin, ymax)
        Area relative to the survey centre (km), a margin is added.
    a11, a22 : float
        Target probabilities of staying in state 0 / state 1 per ``step_km``.
    rows_y_km : array_like, optional
        Northings of the east–west lines; the fit (threshold and smoothness) is done on
        these rows, between ``row_x_km = (x0, x1)``, so the realised line statistics are close
        to the targets.  Default: every grid row of the extent.
    n_draws : int
        Independent white-noise draws tried; the best (draw, smoothness) pair is kept.
    """
    xmin, xmax, ymin, ymax = extent_km
    m = 60.0
    x = np.arange(xmin - m, xmax + m + step_km, step_km)
    y = np.arange(ymin - m, ymax + m + step_km, step_km)
    p1 = (1 - a11) / ((1 - a11) + (1 - a22))     # stationary probability of state 1
    if rows_y_km is None:
        iy = np.nonzero((y >= ymin) & (y <= ymax))[0]
    else:
        iy = np.unique(np.clip(np.round((np.asarray(rows_y_km) - y[0]) / step_km).astype(int), 0, y.size - 1))
    x0, x1 = (xmin, xmax) if row_x_km is None else row_x_km
    ix = np.nonzero((x >= x0) & (x <= x1))[0]
    best = None
    for _ in range(n_draws):
        white = rng.standard_normal((y.size, x.size))
        for sig in np.geomspace(3.0, 40.0, 16):
            f = gaussian_filter(white, sig / step_km, mode="wrap")
            rows = f[np.ix_(iy, ix)]
            thr = float(np.quantile(rows, 1.0 - p1))
            P = empirical_transition(list((rows > thr).astype(np.int64)))
            err = abs(np.log(max(1 - P[0, 0], 1e-6)) - np.log(1 - a11)) + \
                abs(np.log(max(1 - P[1, 1], 1e-6)) - np.log(1 - a22))
            if best is None or err < best[0]:
                best = (err, sig, f, thr)
    _, sig, f, thr = best
    return StateMap(x, y, f, thr, float(sig))


def markov_line(n_epochs: int, states_blocks: np.ndarray, block: int, Q_mgal2, dg0_mgal: float, rng):
    """Random walk ``δg_k = δg_{k−1} + q_k`` with ``Var q_k = Q[state_k]``.

    Parameters
    ----------
    n_epochs : int
        Number of GNSS epochs on the line window.
    states_blocks : ndarray of int, shape (ceil(n_epochs / block),)
        State of each block of ``block`` epochs.
    Q_mgal2 : sequence of float
        Q of each state (mGal² per GNSS step).
    dg0_mgal : float
        Value at the first epoch.

    Returns
    -------
    dg_mgal, state, Q : ndarray, shape (n_epochs,)
    """
    state = np.repeat(np.asarray(states_blocks, dtype=np.int64), block)[:n_epochs]
    Q = np.asarray(Q_mgal2, dtype=float)[state]
    q = rng.standard_normal(n_epochs) * np.sqrt(Q)
    q[0] = 0.0
    return dg0_mgal + np.cumsum(q), state, Q
