"""Recognition of the Markov state path (SPEC §2 step 3; seed 000 §4.3).

Uses the same one-switch window emission model as :mod:`app.core.mjls_em`
(see its module docstring).  The super-state path is a one-to-one function of
the chain path (the window at ``k = 0`` is constant), so the Viterbi path over
super-states is the MAP chain path under that model.
"""

from __future__ import annotations

import numpy as np

from app.core.mjls_em import WindowModel, _layout, emission_loglik, forward_backward, single_thread_blas


def _prepare(x, c, d, Q, R, transition, initial, extra_loglik=None):
    x = np.asarray(x, dtype=float)
    if x.ndim != 1 or x.size == 0:
        raise ValueError("x must be a non-empty 1-D array")
    if not np.all(np.isfinite(x)):
        raise ValueError("x contains NaN or infinite values")
    Q = np.atleast_1d(np.asarray(Q, float))
    R = np.atleast_1d(np.asarray(R, float))
    if Q.ndim != 1 or R.ndim != 1 or np.any(~(Q > 0)) or np.any(~(R > 0)):
        raise ValueError("Q and R must be 1-D arrays of positive variances")
    N = Q.size * R.size
    a = np.asarray(transition, float)
    pi = np.asarray(initial, float).reshape(-1)
    if a.shape != (N, N) or np.any(a < 0) or not np.allclose(a.sum(1), 1.0, atol=1e-6):
        raise ValueError(f"transition must be a ({N},{N}) stochastic matrix")
    if pi.shape != (N,) or np.any(pi < 0) or not np.isclose(pi.sum(), 1.0, atol=1e-6):
        raise ValueError(f"initial must be a probability vector of length {N}")
    model = WindowModel(np.atleast_1d(np.asarray(c, float)), np.atleast_1d(np.asarray(d, float)),
                        Q.size, R.size)
    data = _layout([x], model.p)
    logb = emission_loglik(model, data, Q, R)[0]  # (T, U)
    if extra_loglik is not None:
        e = np.asarray(extra_loglik, dtype=float)
        if e.shape != (x.size, N) or not np.all(np.isfinite(e)):
            raise ValueError(f"extra_loglik must be a finite ({x.size}, {N}) array")
        logb = logb + e[:, model.chain.cur]
    return model, data, logb, a, pi


def state_evidence(x, c, d, Q, R) -> np.ndarray:
    """Per-point log-evidence of each state, shape (T, N), relative to state 0.

    Column ``i`` is ``log p(x_k | window past, window constant in state i)``
    minus the same for state 0: the local evidence a point carries about its
    state, without the chain prior.  Summed with distance weights over the
    points of *neighbouring* lines (:meth:`app.core.nlmeans.RecognitionMap.neighbour_sum`)
    it is the ``extra_loglik`` of :func:`recognize_lines` (cross-line evidence
    pooling).
    """
    Q = np.atleast_1d(np.asarray(Q, float))
    R = np.atleast_1d(np.asarray(R, float))
    N = Q.size * R.size
    a = np.eye(N)
    model, _, logb, _, _ = _prepare(x, c, d, Q, R, a, np.full(N, 1.0 / N))
    ev = logb[:, model.chain.const_index]
    return ev - ev[:, :1]


def viterbi(x, c, d, Q, R, transition, initial, extra_loglik=None) -> np.ndarray:
    """MAP state path of one line by dynamic programming.

    Parameters
    ----------
    x : (T,) decimated sequence of the line.
    c, d : MA coefficients (K+1,), (L+1,).
    Q : (N1,) mGal²;  R : (N2,) (cm/s)².
    transition : (N, N);  initial : (N,) probabilities of ``s_0`` for this line.
    extra_loglik : (T, N), optional
        Additional log-evidence of each state at each point (e.g. pooled from
        neighbouring lines, see :func:`state_evidence`), added to the emissions.

    Returns
    -------
    ndarray of int, shape (T,)
        States ``i*N2 + j`` maximising ``P(S | X, Θ)``.
    """
    model, _, logb, a, pi = _prepare(x, c, d, Q, R, transition, initial, extra_loglik)
    ch = model.chain
    with np.errstate(divide="ignore"):
        logA = np.log(ch.transition(a))
        init = np.full(ch.n_super, -np.inf)
        init[ch.const_index] = np.log(pi)
    T, U = logb.shape
    back = np.empty((T, U), dtype=np.int64)
    delta = init + logb[0]
    for k in range(1, T):
        cand = delta[:, None] + logA  # (U_from, U_to)
        back[k] = np.argmax(cand, axis=0)
        delta = cand[back[k], np.arange(U)] + logb[k]
    path = np.empty(T, dtype=np.int64)
    path[-1] = int(np.argmax(delta))
    for k in range(T - 1, 0, -1):
        path[k - 1] = back[k, path[k]]
    return ch.cur[path]


def posteriors(x, c, d, Q, R, transition, initial, extra_loglik=None) -> np.ndarray:
    """Posterior state probabilities ``P(s_k = i | X, Θ)`` of one line, shape (T, N).

    Same arguments as :func:`viterbi`; rows sum to 1.
    """
    model, data, logb, a, pi = _prepare(x, c, d, Q, R, transition, initial, extra_loglik)
    ch = model.chain
    init_super = np.zeros((1, ch.n_super))
    init_super[0, ch.const_index] = pi
    gamma, _, _ = forward_backward(logb[None], data.valid, ch.transition(a), init_super)
    return gamma[0] @ ch.onehot()


def recognize_lines(x_list, c, d, Q, R, transition, initial, extra_loglik=None):
    """Viterbi paths and posteriors for several lines.

    ``initial`` is (W, N) (one row per line) or (N,) shared; ``extra_loglik``
    an optional list of (T_w, N) additional log-evidence per line (see
    :func:`viterbi`).  Returns ``(states_list, posteriors_list)``.
    """
    pis = np.asarray(initial, float)
    if pis.ndim == 1:
        pis = np.broadcast_to(pis, (len(x_list), pis.size))
    if pis.shape[0] != len(x_list):
        raise ValueError("initial must have one row per line")
    states, probs = [], []
    with single_thread_blas():
        for w, x in enumerate(x_list):
            try:
                ex = None if extra_loglik is None else extra_loglik[w]
                states.append(viterbi(x, c, d, Q, R, transition, pis[w], ex))
                probs.append(posteriors(x, c, d, Q, R, transition, pis[w], ex))
            except ValueError as exc:
                raise ValueError(f"line {w}: {exc}") from None
    return states, probs


def loglikelihood(x, c, d, Q, R, transition, initial) -> float:
    """Log-likelihood ``log p(X | Θ)`` of one line under the window model.

    Same arguments as :func:`viterbi`.  Summed over lines this is the EM
    objective of :func:`app.core.mjls_em.fit_em` (useful e.g. to compare MA
    orders or ``m`` by BIC).
    """
    model, data, logb, a, pi = _prepare(x, c, d, Q, R, transition, initial)
    ch = model.chain
    init_super = np.zeros((1, ch.n_super))
    init_super[0, ch.const_index] = pi
    _, _, ll = forward_backward(logb[None], data.valid, ch.transition(a), init_super)
    return float(ll[0])


def level_shares(probs, n_r: int) -> np.ndarray:
    """Share of the points each anomaly level holds under a map's posteriors.

    Parameters
    ----------
    probs : array_like, shape (T, N)
        State probabilities of T decimated points, N = n_q·n_r states ordered ``i·n_r + j``
        (anomaly level i, GNSS noise level j); each row sums to 1.
    n_r : int
        Number of GNSS noise levels.

    Returns
    -------
    ndarray, shape (n_q,)
        The mean over the points of each anomaly level's posterior mass (sums to 1).
    """
    P = np.asarray(probs, dtype=float)
    if P.ndim != 2 or P.shape[0] == 0:
        raise ValueError(f"probs must be a non-empty (T, N) array, got shape {P.shape}")
    if int(n_r) < 1 or P.shape[1] % int(n_r):
        raise ValueError(f"{P.shape[1]} states are not a whole number of levels of n_r = {n_r}")
    if not np.all(np.isfinite(P)) or np.any(P < 0):
        raise ValueError("probs must be finite and non-negative")
    mass = P.reshape(P.shape[0], -1, int(n_r)).sum(axis=2)
    return mass.mean(axis=0) / max(float(mass.sum(axis=1).mean()), np.finfo(float).tiny)


def stationary_distribution(a) -> np.ndarray:
    """Stationary distribution of a Markov chain.

    Parameters
    ----------
    a : array_like, shape (N, N)
        Transition matrix (rows sum to 1).

    Returns
    -------
    ndarray, shape (N,)
        The left eigenvector of ``a`` for eigenvalue 1, normalised to sum to 1: the long-run
        share of the steps in each state (of the steps from the start the eigensolver's
        eigenvector stands for when the chain has several closed classes, e.g. two absorbing
        states: the long-run shares then depend on where the chain starts).
    """
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] == 0:
        raise ValueError(f"a must be a square (N, N) matrix, got shape {a.shape}")
    if not np.all(np.isfinite(a)) or np.any(a < 0) or not np.allclose(a.sum(1), 1.0, atol=1e-6):
        raise ValueError("a must be a stochastic matrix (non-negative, rows summing to 1)")
    w, v = np.linalg.eig(a.T)
    k = int(np.argmin(np.abs(w - 1.0)))
    pi = np.abs(np.real(v[:, k]))
    return pi / pi.sum()


def last_supported_iteration(transitions, n_r: int, min_share: float) -> int | None:
    """The last EM iteration whose chain still gave every anomaly level ``min_share`` of the steps.

    Parameters
    ----------
    transitions : sequence of array_like, each (N, N)
        The transition matrix of each EM iteration (the records' ``transition``), N = n_q·n_r
        states ordered ``i·n_r + j``.
    n_r : int
        Number of GNSS noise levels.
    min_share : float
        Least long-run share (0–1, the chain's :func:`stationary_distribution` summed over the
        noise levels) a level must hold to count as learned from a part of the data.

    Returns
    -------
    int or None
        Index into ``transitions``; None when no iteration had every level at ``min_share``.
    """
    if len(transitions) == 0:
        raise ValueError("no transition matrices")
    if not 0.0 <= float(min_share) <= 1.0:
        raise ValueError(f"min_share must be within [0, 1], got {min_share}")
    ok = [k for k, a in enumerate(transitions)
          if np.all(level_shares(stationary_distribution(a)[None], n_r) >= min_share)]
    return ok[-1] if ok else None
