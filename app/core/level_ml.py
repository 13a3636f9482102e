"""Full-rate maximum likelihood of the state levels Q_i, R_j given the recognised states.

The EM of seed 000 learns Θ on the regularized, decimated process, where the anomaly
is a few per cent of the variance; a smooth state's Q_i is then poorly determined and
can collapse towards 0, which makes the smoother fit straight lines through long
plains.  Once the state path is known (recognition + NL-means), the exact likelihood
of the full-rate measurements under the state-space model of SPEC §2 is available
from the Kalman filter (prediction-error decomposition), and the few level values
can be re-estimated by maximising it.  This is the same model and the same
criterion (maximum likelihood) evaluated without the regularization's approximations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from app.core.smoother import kalman_loglik


@dataclass
class LevelFit:
    """Result of :func:`refine_levels`.

    Attributes
    ----------
    Q_mgal2 : ndarray, shape (n_q,)
    R_cm2s2 : ndarray, shape (n_r,)
    loglik_start, loglik : float
        Log-likelihood of the subset at the start values and at the optimum.
    n_epochs : int
        Epochs used.
    n_evaluations : int
    """

    Q_mgal2: np.ndarray
    R_cm2s2: np.ndarray
    loglik_start: float
    loglik: float
    n_epochs: int
    n_evaluations: int


def select_subset(lengths, states_per_line, n_states: int, max_epochs: int, seed: int = 0) -> list[int]:
    """Choose lines (indices) totalling at most ``max_epochs`` epochs, covering every
    state that occurs (lines rich in rare states first — states of equal occupancy by index,
    whatever the CPU's sort —, then at random)."""
    rng = np.random.default_rng(seed)
    order = list(rng.permutation(len(lengths)))
    occ = np.array([np.bincount(np.asarray(s, int), minlength=n_states)[:n_states] for s in states_per_line])
    chosen, total, covered = [], 0, np.zeros(n_states)
    # first pass: for each state, the line with most epochs in it
    for k in np.argsort(occ.sum(axis=0), kind="stable"):   # ties by state index, on every CPU
        if occ[:, k].sum() == 0:
            continue
        i = int(np.argmax(occ[:, k]))
        if i not in chosen and total + lengths[i] <= max_epochs:
            chosen.append(i)
            total += lengths[i]
            covered += occ[i]
    for i in order:
        if i in chosen:
            continue
        if total + lengths[i] > max_epochs:
            continue
        chosen.append(int(i))
        total += lengths[i]
    return sorted(chosen) if chosen else [int(np.argmin(lengths))]


def refine_levels(z_lines, state_lines, Q_mgal2, R_cm2s2, dt_s: float, m: int,
                  max_epochs: int = 300_000, max_evaluations: int | None = None,
                  log_bounds: float = 6.0, r_base_lines=None, fit_r: bool = True, noise=None,
                  simplex_step: float = 1.0, map_lines=map) -> LevelFit:
    """Maximise the full-rate Kalman likelihood over the level values.

    Parameters
    ----------
    z_lines : sequence of ndarray
        Measurements per line (mGal, GNSS rate; NaN = missing).
    state_lines : sequence of ndarray of int
        State per epoch, index ``i_q * n_r + j_r``.
    Q_mgal2, R_cm2s2 : array_like, shapes (n_q,), (n_r,)
        Start values (from EM).
    dt_s : float
        GNSS step (s).
    m : int
        Order of the anomaly model.
    max_epochs : int
        Cap on the epochs used (a subset of lines covering every state).
    max_evaluations : int, optional
        Cap on likelihood evaluations (default 40 per parameter).
    log_bounds : float
        Levels stay within ``exp(±log_bounds)`` of their start values.
    r_base_lines : sequence of ndarray, optional
        Per-epoch noise levels (cm/s)² (e.g. :func:`app.core.noise_level.local_noise_variance_cm2s2`).
        When given, ``R(t) = α·r_base(t)`` and the single factor α replaces the R_j levels
        (returned as ``R_cm2s2 = [α]``).
    fit_r : bool
        Estimate the noise levels (or α) too; False keeps them at their start values and
        fits the Q levels only (the noise level then comes from elsewhere, e.g. the EM on
        the regularized band, which is robust to coloured GNSS noise).
    noise : app.core.noise_model.NoiseModel, optional
        Shape of the error of z (the levels R multiply it); None: white velocity noise.
    simplex_step : float
        Size (in log units) of the initial Nelder–Mead simplex: 1 from EM's levels, smaller
        when the start values are already a refinement's (a filter run with new h, ρ).
    map_lines : callable, default :func:`map`
        ``map_lines(f, indices)`` evaluates the lines' log-likelihoods, in order (e.g. a thread
        pool's ``map``: the Kalman kernels release the GIL); the sum is taken in line order, so
        the result does not depend on it.

    Returns
    -------
    LevelFit
    """
    Q0 = np.asarray(Q_mgal2, float)
    R0 = np.asarray(R_cm2s2, float)
    if np.any(~(Q0 > 0)) or np.any(~(R0 > 0)):
        raise ValueError("start levels must be positive")
    n_q, n_r = Q0.size, R0.size
    n_states = n_q * n_r
    lengths = [len(z) for z in z_lines]
    if len(lengths) != len(state_lines):
        raise ValueError("z_lines and state_lines differ in length")
    sub = select_subset(lengths, state_lines, n_states, max_epochs)
    zs = [np.asarray(z_lines[i], float) for i in sub]
    ss = [np.asarray(state_lines[i], int) for i in sub]
    rb = None if r_base_lines is None else [np.asarray(r_base_lines[i], float) for i in sub]
    present = np.zeros(n_states, bool)
    for s in ss:
        present[np.unique(s)] = True
    q_free = [i for i in range(n_q) if present[i * n_r:(i + 1) * n_r].any()]
    if rb is None:
        r_free = [j for j in range(n_r) if present[j::n_r].any()]
    else:
        R0 = np.array([1.0])
        r_free = [0]
    if not fit_r:
        r_free = []
    # A level collapsed towards 0 sits on a flat part of the likelihood (log scale):
    # start it at 1e-3 of the largest level so the search can see its effect.
    Q0 = np.maximum(Q0, 1e-3 * Q0.max())
    th0 = np.log(np.concatenate([Q0[q_free], R0[r_free]]))
    Q_lo = np.log(Q0.copy())
    R_lo = np.log(R0.copy())

    def unpack(th):
        lq, lr = Q_lo.copy(), R_lo.copy()
        lq[q_free] = th[:len(q_free)]
        lr[r_free] = th[len(q_free):]
        return np.exp(lq), np.exp(lr)

    def nll(th):
        if np.any(np.abs(th - th0) > log_bounds):
            return 1e300
        Q, R = unpack(th)

        def line_loglik(k):
            s = ss[k]
            r = R[s % n_r] if rb is None else R[0] * rb[k]
            return kalman_loglik(zs[k], Q[s // n_r], r, dt_s, m=m, noise=noise)

        total = 0.0
        for ll in map_lines(line_loglik, range(len(zs))):   # in line order: the same sum whatever the map
            total += ll
        return -total

    f0 = nll(th0)
    cap = max_evaluations or 40 * th0.size
    simplex = np.vstack([th0] + [th0 + np.eye(th0.size)[k] * simplex_step for k in range(th0.size)])
    res = minimize(nll, th0, method="Nelder-Mead",
                   options={"maxfev": cap, "xatol": 0.02, "fatol": 0.5, "initial_simplex": simplex})
    th = res.x if res.fun <= f0 else th0
    Q, R = unpack(th)
    return LevelFit(Q, R, -f0, -min(res.fun, f0), int(sum(len(z) for z in zs)), int(res.nfev) + 1)


def lift_levels(Q_ml_mgal2, Q_em_mgal2, unlearned=()) -> np.ndarray:
    """The lift-only refinement's levels: each full-rate likelihood level raised to the EM's.

    The EM's level is a floor against a likelihood level that collapsed.  A level the EM never
    learned (``unlearned``: taken back from its first iterations, where the value is the
    initialisation's) is no floor: that level keeps the likelihood's value, held at least at
    the level below it so the levels still ascend.

    Parameters
    ----------
    Q_ml_mgal2, Q_em_mgal2 : array_like, shape (n_q,)
        The likelihood's and the EM's levels (mGal² per step, ascending as the EM's).
    unlearned : sequence of int
        Indices of the levels the EM did not learn.

    Returns
    -------
    ndarray, shape (n_q,)
        The levels to use (mGal² per step).
    """
    q_ml = np.asarray(Q_ml_mgal2, dtype=float).reshape(-1)
    floor = np.array(Q_em_mgal2, dtype=float).reshape(-1)
    if q_ml.shape != floor.shape:
        raise ValueError(f"Q_ml_mgal2 has shape {q_ml.shape}, Q_em_mgal2 {floor.shape}")
    bad = sorted(int(i) for i in unlearned)
    floor[bad] = 0.0
    q = np.maximum(q_ml, floor)
    for i in bad:
        if i > 0:
            q[i] = max(q[i], q[i - 1])
    return q


def cap_lifted_smooth_level(Q_used_mgal2, Q_em_mgal2, Q_stationary_mgal2: float):
    """The smoothest anomaly level after a lift-only refinement, never above the one-level model's.

    A refinement that may only raise the EM's levels (a guard against a collapsed level) can
    lift the smoothest level above the level the full-rate likelihood gives the whole survey
    as one (the stationary model's): the smooth part of a survey rougher than the whole,
    which is the likelihood answering a noise level misjudged on part of the survey, not the
    anomaly.  That level is brought down to the stationary one, never below the EM's own.

    Parameters
    ----------
    Q_used_mgal2 : array_like, shape (n_q,)
        The levels after the lift-only refinement (ascending as the EM's).
    Q_em_mgal2 : array_like, shape (n_q,)
        The EM's levels.
    Q_stationary_mgal2 : float
        The stationary model's full-rate level.

    Returns
    -------
    (ndarray, bool)
        The levels to use and whether the smoothest one was capped.  With one level (the
        stationary model itself, at the survey's own noise levels) nothing changes.
    """
    q = np.array(Q_used_mgal2, dtype=float).reshape(-1)
    em = np.asarray(Q_em_mgal2, dtype=float).reshape(-1)
    if q.shape != em.shape:
        raise ValueError(f"Q_used_mgal2 has shape {q.shape}, Q_em_mgal2 {em.shape}")
    if q.size < 2 or not (np.isfinite(Q_stationary_mgal2) and Q_stationary_mgal2 > 0) or q[0] <= em[0]:
        return q, False
    cap = max(float(Q_stationary_mgal2), float(em[0]))
    if q[0] <= cap:
        return q, False
    q[0] = cap
    return q, True


def raise_rough_level(Q_lifted_mgal2, Q_full_rate_ml_mgal2, factor: float):
    """The roughest of two or more anomaly levels at least ``factor`` times its full-rate
    likelihood level (METHOD stage 8, "The rough level at least twice the likelihood's").

    The likelihood fits a level where the data say most, below the smoother's cutoff; the RMS
    error needs the anomaly's power at the cutoff, and where the anomaly's spectrum falls slower
    there than the m = 2 prior's ω⁻⁴ the likelihood's level over-smooths it (an
    Ornstein–Uhlenbeck anomaly wants 4.5–90× it).  A lifted level already above the bound (an EM
    level learned from the roughest few points) is kept.

    Parameters
    ----------
    Q_lifted_mgal2 : array_like, shape (n_q,)
        The levels after the lift-only refinement and the smooth level's cap (ascending).
    Q_full_rate_ml_mgal2 : array_like, shape (n_q,)
        The full-rate likelihood's own levels.
    factor : float
        The bound's factor (≥ 1; 1 leaves the levels as they are).

    Returns
    -------
    (ndarray, bool)
        The levels to use and whether the roughest one was raised.  With one level nothing is
        rougher than the rest, and nothing changes.
    """
    q = np.array(Q_lifted_mgal2, dtype=float).reshape(-1)
    ml = np.asarray(Q_full_rate_ml_mgal2, dtype=float).reshape(-1)
    if q.shape != ml.shape:
        raise ValueError(f"Q_lifted_mgal2 has shape {q.shape}, Q_full_rate_ml_mgal2 {ml.shape}")
    if not factor >= 1.0:
        raise ValueError(f"factor must be >= 1, got {factor}")
    bound = float(factor) * float(ml[-1])
    if q.size < 2 or not np.isfinite(bound) or q[-1] >= bound:
        return q, False
    q[-1] = bound
    return q, True


@dataclass
class OrderChoice:
    """Result of :func:`select_order`: the chosen m and, per candidate, the
    maximised log-likelihood and its stationary Q (mGal² per step)."""

    m: int
    loglik: dict
    Q_mgal2: dict


def select_order(z_lines, r_lines, dt_s: float, candidates=(1, 2), max_epochs: int = 200_000,
                 seed: int = 0, noise=None) -> OrderChoice:
    """Choose the order m of the anomaly model ``∇^m δg = q`` by maximum likelihood.

    For each candidate m, a stationary anomaly model (one Q) with the given per-epoch
    noise levels is fitted by maximising the full-rate Kalman likelihood over Q on a
    subset of lines; the m with the largest maximised likelihood wins (every candidate
    has the same number of free parameters, so this is also the BIC choice).

    Parameters
    ----------
    z_lines, r_lines : sequence of ndarray
        Measurements (mGal) and noise levels ((cm/s)²) per line.
    dt_s : float
    candidates : tuple of int
        Orders to compare (subset of 1..3).
    max_epochs : int
        Cap on the epochs used.
    noise : app.core.noise_model.NoiseModel, optional
        Shape of the error of z; None: white velocity noise.
    """
    from scipy.optimize import minimize_scalar

    if not candidates or any(m not in (1, 2, 3) for m in candidates):
        raise ValueError("candidates must be a non-empty subset of (1, 2, 3)")
    lengths = [len(z) for z in z_lines]
    rng = np.random.default_rng(seed)
    chosen, total = [], 0
    for i in rng.permutation(len(lengths)):
        if total + lengths[i] > max_epochs and chosen:
            continue
        chosen.append(int(i))
        total += lengths[i]
    zs = [np.asarray(z_lines[i], float) for i in chosen]
    rs = [np.asarray(r_lines[i], float) for i in chosen]
    ll, qs = {}, {}
    for m in candidates:
        def nll(lq, m=m):
            return -sum(kalman_loglik(z, np.exp(lq), r, dt_s, m=m, noise=noise) for z, r in zip(zs, rs))

        res = minimize_scalar(nll, bounds=(-30.0, 3.0), method="bounded", options={"xatol": 0.05})
        ll[m] = float(-res.fun)
        qs[m] = float(np.exp(res.x))
    best = max(ll, key=ll.get)
    return OrderChoice(best, ll, qs)
