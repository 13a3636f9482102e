"""EM learning for the mixture of moving averages with Markov jumps (SPEC §2 step 2).

Model (seed 000 §4, eq. 14), per line ``w`` on the decimated grid::

    x_k = Σ_{l≤K} c_l q_{k−l} + Σ_{l≤L} d_l r_{k−l}

``q``, ``r`` independent white Gaussian, ``Var q_k = Q(s_k)`` (mGal²),
``Var r_k = R(s_k)`` ((cm/s)²); ``s_k`` a Markov chain over ``N = N1·N2`` states,
state ``i*N2 + j`` ↔ pair ``(Q_i, R_j)``; transition ``a_ij`` shared by all lines,
initial probabilities ``π(w)`` per line.

Emission model (the approximation used here)
--------------------------------------------
Let ``p = max(K, L)``.  The emission of time ``k`` is the exact Gaussian
conditional ``p(x_k | x_{k−m..k−1}, window)`` with ``m = min(k, p)``, computed
from the joint covariance of ``(x_{k−m}, …, x_k)``.  That covariance depends on
the states of all noises that enter the window.  The *window state* is the path
``s_{k−p..k}`` **restricted to at most one switch**: it is represented by the
pair (state before the last switch ``a``, current state ``b``) and the run length
``ℓ`` of ``b`` (``1..p``), or by "constant ``b``" when ``b`` has lasted ``p+1``
steps or more.  Noises at indices ``> k−ℓ`` take ``b``; all older noises
(including those older than the window) take ``a``.  This makes the window
state an exact Markov chain on ``N + N(N−1)p`` super-states (it is a function of
the true path: a path with two switches inside one window is represented by its
most recent switch), so the model is a proper HMM over super-states and EM on it
is monotone.  For ``p = 0`` it is an ordinary HMM with zero-mean Gaussian
emissions of variance ``c0²Q + d0²R``.

Initial probabilities ``π_i(w) = P(s_0 = i)``; the states before the first
sample are taken equal to ``s_0`` (the window at ``k = 0`` is "constant").

The EM objective reported (``objective``/``loglik``) is the log of this
likelihood, ``Σ_w log p(X(w) | Θ)``; EM never decreases it (the Q/R M-step
accepts only steps that increase the expected complete-data log-likelihood).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize

_LOG2PI = float(np.log(2.0 * np.pi))
# A generalized EM (Dempster, Laird & Rubin 1977, §3): the variance M-step takes at most this
# many warm-started L-BFGS iterations and is kept only when it raises the expected complete-data
# log-likelihood, which is all EM's monotonicity needs.  Solving each M-step to the end (100)
# spent ~16 objective evaluations per EM iteration on steps the next E-step moves anyway:
# learning 91 -> 48 s summed over 42 simulated surveys (21 -> 9 s on one with a 12-term noise
# MA); RMS within ±1 % on 29 of them, the others moved by reaching another EM end point or
# order choice (-11 % to +3 %; benchmarks/bench_regimes.py, bench_unseen.py).
_MSTEP_MAXITER = 5
# The variance M-step evaluates its objective only on the (window class, super-state) pairs whose
# posterior weight exceeds this fraction of the total; the rest change the per-sample objective
# by less than that.  With a long noise MA most pairs carry none: a class below p holds only
# the first samples of each line, and most switch positions are never visited (held-out layout
# 515, a 20-term MA: 2604 of 5124 pairs exactly zero, ~1100 above 1e-12; that EM 48.7 -> 17.6 s).
_MSTEP_MIN_WEIGHT = 1e-12


def single_thread_blas():
    """Context limiting BLAS to one thread (if ``threadpoolctl`` is importable).

    The E- and M-steps are thousands of tiny matrix products; a multi-threaded
    OpenBLAS on a loaded machine makes them 5–10× slower.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


# --------------------------------------------------------------------------- chain
@dataclass(frozen=True)
class WindowChain:
    """Super-state chain of window paths with at most one switch.

    Attributes
    ----------
    n_states : int
        Number of chain states N.
    p : int
        Window radius (MA order).
    cur, first, run : ndarray of int, shape (U,)
        Current state ``b``, first state of the window ``a`` (``= b`` for a
        constant window) and run length ``ℓ`` of ``b`` (``p + 1`` = constant).
    succ : ndarray of int, shape (U, N)
        Super-state reached when the next chain state is ``c``.
    const_index : ndarray of int, shape (N,)
        Super-state index of the constant window of each state (``= arange(N)``).
    """

    n_states: int
    p: int
    cur: np.ndarray
    first: np.ndarray
    run: np.ndarray
    succ: np.ndarray
    const_index: np.ndarray

    @property
    def n_super(self) -> int:
        return int(self.cur.size)

    def transition(self, a: np.ndarray) -> np.ndarray:
        """Super-state transition matrix (U, U) from the chain's ``a`` (N, N)."""
        U = self.n_super
        A = np.zeros((U, U))
        for u in range(U):
            for c in range(self.n_states):
                A[u, self.succ[u, c]] += a[self.cur[u], c]
        return A

    def onehot(self) -> np.ndarray:
        """(U, N) indicator of the current state of each super-state."""
        M = np.zeros((self.n_super, self.n_states))
        M[np.arange(self.n_super), self.cur] = 1.0
        return M


def build_chain(n_states: int, p: int) -> WindowChain:
    """Enumerate the super-states: constants first (index = state), then switches."""
    cur, first, run = [], [], []
    for b in range(n_states):
        cur.append(b), first.append(b), run.append(p + 1)
    index = {}
    for a in range(n_states):
        for b in range(n_states):
            if a == b:
                continue
            for ell in range(1, p + 1):
                index[(a, b, ell)] = len(cur)
                cur.append(b), first.append(a), run.append(ell)
    U = len(cur)
    succ = np.empty((U, n_states), dtype=np.int64)
    for u in range(U):
        b, ell = cur[u], run[u]
        for c in range(n_states):
            if c == b:
                if ell >= p:  # run reaches p+1: window constant
                    succ[u, c] = b
                else:
                    succ[u, c] = index[(first[u], b, ell + 1)]
            else:
                succ[u, c] = c if p == 0 else index[(b, c, 1)]
    return WindowChain(n_states, p, np.array(cur), np.array(first), np.array(run), succ,
                       np.arange(n_states))


# --------------------------------------------------------------------------- covariance basis
def _window_covariance(BQ, BR, pad, Q, R) -> np.ndarray:
    """``Σ = Σ_i Q_i BQ[..., i] + Σ_j R_j BR[..., j] + pad`` over (class, pair) axes."""
    return np.einsum("muixy,i->muxy", BQ, Q) + np.einsum("mujxy,j->muxy", BR, R) + pad


def _as_block(coef) -> np.ndarray:
    """Coefficients as a (K+1, r) array: column ``i`` multiplies the ``i``-th of ``r``
    independent unit sub-noises of each step (``r = 1`` for a scalar MA)."""
    coef = np.asarray(coef, dtype=float)
    return coef[:, None] if coef.ndim == 1 else coef


def _gram_split(coef: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Partial Gram matrices of one MA component over padded windows.

    Returns ``Gb, Ga`` of shape (p+1, p+2, p+1, p+1): for window class ``m``
    (``m`` past values available) and run length ``ℓ`` (1..p+1; index 0 unused),
    the contribution of the noises with relative index ``j > −ℓ`` (``Gb``) and
    ``j ≤ −ℓ`` (``Ga``) to ``Cov(x_{k−p+t}, x_{k−p+t'})`` per unit variance.
    Padding positions (``t < p − m``) are zero.
    """
    coef = _as_block(coef)
    K = coef.shape[0] - 1
    js = np.arange(-p - K, 1)  # relative noise indices that reach the window
    t = np.arange(p + 1)
    lag = t[:, None] - p - js[None, :]  # (p+1, J): coefficient index
    g = np.where(((lag >= 0) & (lag <= K))[..., None], coef[np.clip(lag, 0, K)], 0.0)  # (p+1, J, r)
    Gb = np.zeros((p + 1, p + 2, p + 1, p + 1))
    Ga = np.zeros_like(Gb)
    for m in range(p + 1):
        gm = g * (t >= p - m)[:, None, None]
        for ell in range(1, p + 2):
            bmask = js > -ell
            gb = gm[:, bmask].reshape(p + 1, -1)
            ga = gm[:, ~bmask].reshape(p + 1, -1)
            Gb[m, ell] = gb @ gb.T
            Ga[m, ell] = ga @ ga.T
    return Gb, Ga


@dataclass
class WindowModel:
    """Covariance structure of the switching MA model on padded windows.

    ``Σ[m, u] = Σ_i Q_i BQ[m, u, i] + Σ_j R_j BR[m, u, j] + pad[m]`` with shapes
    (p+1, U, p+1, p+1); ``pad[m]`` is the identity on the ``p − m`` leading
    (unavailable) positions so padded windows keep a regular covariance.
    """

    c: np.ndarray
    d: np.ndarray
    n_q: int
    n_r: int
    chain: WindowChain = field(init=False)
    p: int = field(init=False)
    BQ: np.ndarray = field(init=False)
    BR: np.ndarray = field(init=False)
    pad: np.ndarray = field(init=False)

    def __post_init__(self):
        self.c = np.asarray(self.c, dtype=float)
        self.d = np.asarray(self.d, dtype=float)
        self.p = max(self.c.shape[0], self.d.shape[0]) - 1
        p = self.p
        N = self.n_q * self.n_r
        self.chain = build_chain(N, p)
        ch = self.chain
        U = ch.n_super
        Gbc, Gac = _gram_split(self.c, p)
        Gbd, Gad = _gram_split(self.d, p)
        qi_b, qi_a = ch.cur // self.n_r, ch.first // self.n_r
        rj_b, rj_a = ch.cur % self.n_r, ch.first % self.n_r
        self.BQ = np.zeros((p + 1, U, self.n_q, p + 1, p + 1))
        self.BR = np.zeros((p + 1, U, self.n_r, p + 1, p + 1))
        for u in range(U):
            ell = ch.run[u]
            self.BQ[:, u, qi_b[u]] += Gbc[:, ell]
            self.BQ[:, u, qi_a[u]] += Gac[:, ell]
            self.BR[:, u, rj_b[u]] += Gbd[:, ell]
            self.BR[:, u, rj_a[u]] += Gad[:, ell]
        t = np.arange(p + 1)
        self.pad = np.stack([np.diag((t < p - m).astype(float)) for m in range(p + 1)])

    def covariance(self, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Window covariances Σ, shape (p+1, U, p+1, p+1)."""
        return _window_covariance(self.BQ, self.BR, self.pad[:, None], Q, R)

    def subset(self, mask: np.ndarray) -> WindowSubset:
        """The window covariances of the (class, super-state) pairs selected by ``mask``
        (bool, shape (p+1, U)), laid out as one class of K pairs (see :class:`WindowSubset`)."""
        mask = np.asarray(mask, bool)
        if mask.shape != self.BQ.shape[:2]:
            raise ValueError(f"mask must have shape {self.BQ.shape[:2]}, got {mask.shape}")
        m_idx = np.nonzero(mask)[0]
        return WindowSubset(self.n_q, self.p, self.BQ[mask][None], self.BR[mask][None],
                            self.pad[m_idx][None])

    def conditional(self, Q, R) -> tuple[np.ndarray, np.ndarray]:
        """Regression of ``x_k`` on its window past: ``beta`` (p+1, U, p), ``var`` (p+1, U)."""
        S = self.covariance(np.asarray(Q, float), np.asarray(R, float))
        p = self.p
        if p == 0:
            return np.zeros(S.shape[:2] + (0,)), S[..., 0, 0].copy()
        Spp = S[..., :p, :p]
        s = S[..., :p, p]
        try:
            beta = np.linalg.solve(Spp, s[..., None])[..., 0]
        except np.linalg.LinAlgError as exc:
            raise FloatingPointError("window covariance is singular") from exc
        var = S[..., p, p] - np.einsum("mux,mux->mu", s, beta)
        return beta, var


@dataclass
class WindowSubset:
    """Some (class, super-state) pairs of a :class:`WindowModel`, shaped as a single class of
    K pairs: ``BQ`` (1, K, n_q, p+1, p+1), ``BR`` (1, K, n_r, p+1, p+1), ``pad`` (1, K, p+1, p+1).
    Enough for the variance M-step (:func:`_qr_objective`), which sums over pairs."""

    n_q: int
    p: int
    BQ: np.ndarray
    BR: np.ndarray
    pad: np.ndarray

    def covariance(self, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Window covariances Σ of the selected pairs, shape (1, K, p+1, p+1)."""
        return _window_covariance(self.BQ, self.BR, self.pad, Q, R)


# --------------------------------------------------------------------------- data layout
@dataclass
class _Data:
    x: np.ndarray        # (W, T) zero padded
    valid: np.ndarray    # (W, T) bool
    Y: np.ndarray        # (W, T, p+1) windows x_{k-p..k}, zero for missing
    lengths: np.ndarray  # (W,)
    YY: np.ndarray | None = None  # (W, T, (p+1)^2) outer products, zero where padded


def _layout(x_list: Sequence[np.ndarray], p: int) -> _Data:
    W = len(x_list)
    lengths = np.array([len(x) for x in x_list])
    T = int(lengths.max())
    x = np.zeros((W, T))
    valid = np.zeros((W, T), dtype=bool)
    for w, xw in enumerate(x_list):
        x[w, : len(xw)] = xw
        valid[w, : len(xw)] = True
    xp = np.concatenate([np.zeros((W, p)), x], axis=1)
    Y = np.lib.stride_tricks.sliding_window_view(xp, p + 1, axis=1)[:, :T].copy()
    YY = (Y[..., :, None] * Y[..., None, :]).reshape(W, T, -1) * valid[..., None]
    return _Data(x, valid, Y, lengths, YY)


def emission_loglik(model: WindowModel, data: _Data, Q, R) -> np.ndarray:
    """log p(x_k | window past, super-state), shape (W, T, U); 0 where padded."""
    beta, var = model.conditional(Q, R)
    if np.any(~np.isfinite(var)) or np.any(var <= 0):
        raise FloatingPointError("window covariance not positive definite")
    p = model.p
    W, T = data.x.shape
    U = model.chain.n_super
    logb = np.empty((W, T, U))
    for k in range(min(p, T)):
        mu = data.Y[:, k, :p] @ beta[k].T  # (W, U)
        r = data.x[:, k, None] - mu
        logb[:, k] = -0.5 * (_LOG2PI + np.log(var[k]) + r * r / var[k])
    if T > p:
        mu = data.Y[:, p:, :p] @ beta[p].T  # (W, T-p, U)
        r = data.x[:, p:, None] - mu
        logb[:, p:] = -0.5 * (_LOG2PI + np.log(var[p]) + r * r / var[p])
    logb[~data.valid] = 0.0
    return logb


# --------------------------------------------------------------------------- forward-backward
def forward_backward(logb: np.ndarray, valid: np.ndarray, A: np.ndarray, init_super: np.ndarray):
    """Scaled forward–backward over super-states, batched over lines.

    Parameters
    ----------
    logb : (W, T, U) emission log-densities (0 at padded positions).
    valid : (W, T) bool mask of real samples (a prefix of each row).
    A : (U, U) super-state transition matrix.
    init_super : (W, U) distribution of the super-state at k = 0.

    Returns
    -------
    gamma : (W, T, U) posterior super-state probabilities.
    xi : (U, U) expected super-state transition counts summed over lines and time.
    loglik : (W,) log-likelihood of each line.
    """
    W, T, U = logb.shape
    alpha = np.empty((W, T, U))
    logc = np.empty((W, T))
    with np.errstate(divide="ignore"):
        pred = init_super
        for k in range(T):
            if k > 0:
                pred = alpha[:, k - 1] @ A
            lp = np.log(pred) + logb[:, k]
            mx = lp.max(axis=1)
            a = np.exp(lp - mx[:, None])
            s = a.sum(axis=1)
            alpha[:, k] = a / s[:, None]
            logc[:, k] = mx + np.log(s)
    loglik = np.where(valid, logc, 0.0).sum(axis=1)
    eb = np.exp(np.minimum(logb - logc[..., None], 700.0))  # (W, T, U)
    beta = np.empty((W, T, U))
    beta[:, T - 1] = 1.0
    for k in range(T - 2, -1, -1):
        beta[:, k] = (eb[:, k + 1] * beta[:, k + 1]) @ A.T
    gamma = alpha * beta
    gamma /= gamma.sum(axis=2, keepdims=True)
    if T > 1:
        pair = valid[:, 1:]
        lhs = (alpha[:, :-1] * pair[..., None]).reshape(-1, U)
        rhs = (eb[:, 1:] * beta[:, 1:]).reshape(-1, U)
        xi = A * (lhs.T @ rhs)
    else:
        xi = np.zeros((U, U))
    return gamma, xi, loglik


# --------------------------------------------------------------------------- M-step for Q, R
def _spd_inverse_from_cholesky(L: np.ndarray) -> np.ndarray:
    """Inverse of SPD matrices from their lower Cholesky factors, batched (..., n, n).

    Row-wise forward substitution vectorised over the batch (n steps), then
    ``Σ⁻¹ = L⁻ᵀ L⁻¹``; much cheaper than ``np.linalg.inv`` for many small matrices.
    """
    n = L.shape[-1]
    X = np.zeros_like(L)
    eye = np.eye(n)
    for i in range(n):
        row = eye[i] - (L[..., i:i + 1, :i] @ X[..., :i, :])[..., 0, :] if i else eye[0]
        X[..., i, :] = row / L[..., i, i, None]
    return np.swapaxes(X, -1, -2) @ X


def _qr_objective(theta, model: WindowModel | WindowSubset, S: np.ndarray, n: np.ndarray):
    """Expected emission log-likelihood and its gradient in log-variances.

    ``S`` (p+1, U, p+1, p+1) weighted window scatter, ``n`` (p+1, U) weights — or, with a
    :class:`WindowSubset` of K pairs, (1, K, p+1, p+1) and (1, K).
    Returns (value, grad) of the *negative* objective (for minimisation).
    """
    nq = model.n_q
    Q = np.exp(theta[:nq])
    R = np.exp(theta[nq:])
    p = model.p
    Sig = model.covariance(Q, R)
    try:
        L = np.linalg.cholesky(Sig)
    except np.linalg.LinAlgError:
        return np.inf, np.zeros_like(theta)
    diag = np.diagonal(L, axis1=-2, axis2=-1)
    if np.any(~(diag > 0)):
        return np.inf, np.zeros_like(theta)
    logdet = 2.0 * np.log(diag).sum(-1)
    Sinv = _spd_inverse_from_cholesky(L)
    SiS = Sinv @ S
    val = -0.5 * (n * logdet + np.trace(SiS, axis1=-2, axis2=-1))
    G = -0.5 * (n[..., None, None] * Sinv - SiS @ Sinv)
    if p > 0:
        # past block by the Schur complement of the full inverse:
        # Σ_pp⁻¹ = A − b bᵀ / c,  log det Σ_pp = log det Σ + log c
        c_ll = Sinv[..., p, p]
        b = Sinv[..., :p, p]
        Pinv = Sinv[..., :p, :p] - b[..., :, None] * b[..., None, :] / c_ll[..., None, None]
        logdetp = logdet + np.log(c_ll)
        PiS = Pinv @ S[..., :p, :p]
        val = val + 0.5 * (n * logdetp + np.trace(PiS, axis1=-2, axis2=-1))
        G[..., :p, :p] += 0.5 * (n[..., None, None] * Pinv - PiS @ Pinv)
    f = float(val.sum()) - 0.5 * _LOG2PI * float(n.sum())
    gQ = np.einsum("muxy,muixy->i", G, model.BQ) * Q
    gR = np.einsum("muxy,mujxy->j", G, model.BR) * R
    if not np.isfinite(f):
        return np.inf, np.zeros_like(theta)
    return -f, -np.concatenate([gQ, gR])


def _window_stats(data: _Data, gamma: np.ndarray, p: int):
    """Weighted scatter S (p+1, U, p+1, p+1) and weights n (p+1, U)."""
    W, T, U = gamma.shape
    g = gamma * data.valid[..., None]
    YY = data.YY
    S = np.zeros((p + 1, U, (p + 1) ** 2))
    n = np.zeros((p + 1, U))
    for k in range(min(p, T)):
        S[k] = g[:, k].T @ YY[:, k]
        n[k] = g[:, k].sum(0)
    if T > p:
        S[p] = g[:, p:].reshape(-1, U).T @ YY[:, p:].reshape(-1, (p + 1) ** 2)
        n[p] = g[:, p:].reshape(-1, U).sum(0)
    return S.reshape(p + 1, U, p + 1, p + 1), n


# --------------------------------------------------------------------------- initialisation
def _autocov_basis(coef: np.ndarray, p: int) -> np.ndarray:
    coef = _as_block(coef)
    full = np.zeros((p + 1, coef.shape[1]))
    full[: coef.shape[0]] = coef
    return np.array([np.sum(full[: p + 1 - l] * full[l:]) for l in range(p + 1)])


def initial_variances(x_list, c, d, n_q: int, n_r: int, chunk: int | None = None):
    """Data-driven starting values for Q (n_q,) and R (n_r,).

    Method of moments: the autocovariance of ``x`` at lags 0..p is
    ``Q·ρ_c(l) + R·ρ_d(l)``; it is fitted by least squares on the pooled data
    (stationary levels) and on chunks of ``chunk`` points (local levels).  Levels
    are spread over the 10–90 % quantiles of the chunk estimates (at least a
    factor 3 between extreme Q levels and 1.5 between extreme R levels).
    """
    c = np.asarray(c, float)
    d = np.asarray(d, float)
    p = max(c.shape[0], d.shape[0]) - 1
    rc, rd = _autocov_basis(c, p), _autocov_basis(d, p)
    chunk = chunk or max(20, 3 * (p + 1))
    has_c, has_d = np.any(rc != 0), np.any(rd != 0)

    def fit(acov):
        cols = [v for v, h in ((rc, has_c), (rd, has_d)) if h]
        Amat = np.stack(cols, axis=1)
        sol = np.linalg.lstsq(Amat, acov.T, rcond=None)[0]
        out = np.full((2,) + sol.shape[1:], np.nan)
        i = 0
        if has_c:
            out[0] = sol[i]
            i += 1
        if has_d:
            out[1] = sol[i]
        return out

    def acov_of(seg):
        m = seg.size
        return np.array([seg[: m - l] @ seg[l:] / m for l in range(p + 1)])

    pooled = np.zeros(p + 1)
    ntot = 0
    local = []
    for x in x_list:
        x = np.asarray(x, float)
        pooled += acov_of(x) * x.size
        ntot += x.size
        for s in range(0, x.size - chunk + 1, chunk):
            local.append(acov_of(x[s: s + chunk]))
    pooled /= ntot
    var0 = max(pooled[0], 1e-300)
    Q0, R0 = fit(pooled)
    # fall back when one component is absent or the moment fit is not positive
    if not has_c:
        Q0 = 1.0
    if not has_d:
        R0 = 1.0
    if has_c and not (Q0 > 0):
        Q0 = 0.5 * var0 / max(rc[0], 1e-300)
    if has_d and not (R0 > 0):
        R0 = 0.5 * var0 / max(rd[0], 1e-300)

    def levels(center, est, n, min_ratio):
        if n == 1:
            return np.array([center])
        est = est[np.isfinite(est) & (est > 0)] if est is not None else np.array([])
        if est.size >= 4:
            lo, hi = np.quantile(est, [0.1, 0.9])
            lo, hi = max(lo, 0.05 * center), min(hi, 20 * center)
        else:
            lo, hi = center, center
        if not (hi > lo) or hi / lo < min_ratio:
            g = np.sqrt(max(lo * hi, 1e-300))
            lo, hi = g / np.sqrt(min_ratio), g * np.sqrt(min_ratio)
        return np.geomspace(lo, hi, n)

    if local:
        est = fit(np.array(local))
        Qs, Rs = est[0], est[1]
    else:
        Qs = Rs = None
    Q = levels(Q0, Qs if has_c else None, n_q, 3.0)
    R = levels(R0, Rs if has_d else None, n_r, 1.5)
    return Q, R


# --------------------------------------------------------------------------- EM driver
@dataclass
class EMResult:
    """Result of :func:`fit_em`.

    Attributes
    ----------
    Q : (N1,) anomaly-noise variances, mGal², ascending.
    R : (N2,) GNSS-noise variances, (cm/s)², ascending.
    transition : (N, N) transition matrix ``a_ij`` (rows sum to 1), states ``i*N2+j``.
    initial : (W, N) initial probabilities per used line.
    loglik : float, final log-likelihood (the objective) of all used lines.
    iterations : list of dict ``{iteration, Q, R, objective, transition}``.
    converged : bool.
    line_index : indices (into the input list) of the lines used.
    warnings : messages about dropped lines.
    p : MA radius ``max(K, L)``.
    """

    Q: np.ndarray
    R: np.ndarray
    transition: np.ndarray
    initial: np.ndarray
    loglik: float
    iterations: list
    converged: bool
    line_index: list
    warnings: list
    p: int

    @property
    def n_states(self) -> int:
        return self.Q.size * self.R.size


def _validate_lines(x_list, p):
    if isinstance(x_list, np.ndarray) and x_list.ndim == 1:
        x_list = [x_list]
    out, idx, warns = [], [], []
    for w, x in enumerate(x_list):
        x = np.asarray(x, dtype=float)
        if x.ndim != 1:
            raise ValueError(f"line {w}: x must be one-dimensional, got shape {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"line {w}: x contains NaN or infinite values")
        if x.size < p + 2:
            warns.append(f"line {w} dropped: {x.size} points < p + 2 = {p + 2}")
            continue
        out.append(x)
        idx.append(w)
    if not out:
        raise ValueError(f"no line has at least p + 2 = {p + 2} points")
    return out, idx, warns


def _validate_coefs(c, d):
    c = np.atleast_1d(np.asarray(c, dtype=float))
    d = np.atleast_1d(np.asarray(d, dtype=float))
    for name, v in (("c", c), ("d", d)):
        if v.ndim not in (1, 2) or v.size == 0 or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a non-empty finite 1-D (or 2-D block) array")
    if not np.any(c) and not np.any(d):
        raise ValueError("c and d are both zero")
    return c, d


def _extra_super(extra_loglik, line_index, data: _Data, ch: WindowChain) -> np.ndarray:
    """(W, T, U) additive log-evidence from per-line (T_w, N) arrays (by current state)."""
    W, T = data.x.shape
    out = np.zeros((W, T, ch.n_super))
    for row, w in enumerate(line_index):
        e = np.asarray(extra_loglik[w], dtype=float)
        n = int(data.lengths[row])
        if e.shape != (n, ch.n_states) or not np.all(np.isfinite(e)):
            raise ValueError(f"extra_loglik[{w}] must be a finite ({n}, {ch.n_states}) array")
        out[row, :n] = e[:, ch.cur]
    return out


def _sort_states(Q, R, transition, initial, n_r):
    oq, orr = np.argsort(Q, kind="stable"), np.argsort(R, kind="stable")
    perm = (oq[:, None] * n_r + orr[None, :]).ravel()  # new index -> old index
    return Q[oq], R[orr], transition[np.ix_(perm, perm)], initial[:, perm]


def fit_em(x_list, c, d, n_q: int = 2, n_r: int = 1, Q_init=None, R_init=None,
           transition_init=None, max_iter: int = 60, tol: float = 1e-6,
           callback: Callable[[dict], None] | None = None,
           shared_initial: bool = False, initial_init=None, extra_loglik=None) -> EMResult:
    """Maximum-likelihood Θ = {Q_i, R_j, a_ij, π_i(w)} by EM over all lines.

    Parameters
    ----------
    x_list : sequence of 1-D arrays
        Decimated regularized sequences ``x(w)``, one per line (a single 1-D
        array is taken as one line).  Lines shorter than ``p + 2`` are dropped
        (listed in ``warnings``); NaN/inf raises ValueError naming the line.
    c, d : array_like, shapes (K+1,), (L+1,)
        MA coefficients of the anomaly and GNSS components (scaled so Q is in
        mGal² per GNSS step and R in (cm/s)², see CONTRACTS).
    n_q, n_r : int
        Number of Q levels N1 and R levels N2; N = N1·N2 states ``i*N2 + j``.
    Q_init, R_init : array_like, optional
        Starting variances (N1,), (N2,); data-driven (:func:`initial_variances`)
        when None.
    transition_init : (N, N), optional
        Starting transition matrix; default 0.95 on the diagonal, rest uniform.
    max_iter : int
        Maximum number of EM iterations.
    tol : float
        Stop when ``(ℓ_new − ℓ_old) / |ℓ_old| < tol`` for the log-likelihood ℓ.
    callback : callable, optional
        Called with each iteration record as soon as it exists.
    shared_initial : bool
        One π for all lines (mean of the lines' posteriors of ``s_0``) instead of
        one per line.  With a single line π(w) equals that line's posterior of s_0.
    initial_init : (N,) or (W, N), optional
        Starting π; uniform when None.
    extra_loglik : sequence of (T_w, N) arrays, optional
        Additional log-evidence of each state per point of each input line,
        added to the emissions of the E-step (off by default; pooling neighbour
        lines' evidence here was measured to bias Q_2 by −30 % on the markov
        preset, so the pipeline should use it in recognition only).

    ``c`` and ``d`` may also be (K+1, r) block coefficients: column ``i``
    multiplies the ``i``-th of ``r`` independent unit sub-noises of each step
    (the exact decimated representation of a full-rate filter is such a block MA).

    Returns
    -------
    EMResult
        States sorted so Q (then R) ascend (records of the iteration table too).  Record ``iteration = 0`` holds the
        initial values; record ``i`` the values after the i-th M-step, with
        ``objective`` = log-likelihood at those values.

    Notes
    -----
    The emission model is the one-switch window model described in the module
    docstring.  π(w) is the posterior of ``s_0`` on line ``w`` (at the previous
    iterate); with a single line π therefore equals that line's posterior and
    carries no prior information.  A Q level may collapse towards 0 when the
    data do not support it (e.g. variability that is really in R): compare
    ``loglik`` across (n_q, n_r) choices.  ``a_ij`` and ``π(w)`` are updated in closed form; ``Q``, ``R``
    by L-BFGS on log-variances of the expected complete-data log-likelihood,
    warm-started at the current values, at most ``_MSTEP_MAXITER`` (5) iterations
    per EM iteration and accepted only when it increases (a generalized EM: still
    monotone, the fixed points are EM's).
    BLAS is limited to one thread during the fit (see :func:`single_thread_blas`).
    """
    with single_thread_blas():
        return _fit_em(x_list, c, d, n_q, n_r, Q_init, R_init, transition_init, max_iter, tol,
                       callback, shared_initial, initial_init, extra_loglik)


def _fit_em(x_list, c, d, n_q, n_r, Q_init, R_init, transition_init, max_iter, tol,
            callback, shared_initial, initial_init, extra_loglik=None) -> EMResult:
    c, d = _validate_coefs(c, d)
    if int(n_q) < 1 or int(n_r) < 1:
        raise ValueError("n_q and n_r must be >= 1")
    n_q, n_r = int(n_q), int(n_r)
    N = n_q * n_r
    if max_iter < 0:
        raise ValueError("max_iter must be >= 0")
    if not tol >= 0:
        raise ValueError("tol must be >= 0")
    model = WindowModel(c, d, n_q, n_r)
    p = model.p
    lines, line_index, warns = _validate_lines(x_list, p)
    W = len(lines)
    data = _layout(lines, p)
    ch = model.chain
    extra = None
    if extra_loglik is not None:
        extra = _extra_super(extra_loglik, line_index, data, ch)

    Q0, R0 = initial_variances(lines, c, d, n_q, n_r)
    Q = Q0 if Q_init is None else np.asarray(Q_init, float).reshape(-1)
    R = R0 if R_init is None else np.asarray(R_init, float).reshape(-1)
    if Q.shape != (n_q,) or R.shape != (n_r,):
        raise ValueError(f"Q_init must have shape ({n_q},) and R_init ({n_r},)")
    if np.any(~(Q > 0)) or np.any(~(R > 0)) or not np.all(np.isfinite(np.r_[Q, R])):
        raise ValueError("initial variances must be positive and finite")
    if transition_init is None:
        a = np.full((N, N), 0.05 / max(N - 1, 1))
        np.fill_diagonal(a, 0.95 if N > 1 else 1.0)
    else:
        a = np.array(transition_init, float)
        if a.shape != (N, N) or np.any(a < 0) or not np.allclose(a.sum(1), 1.0, atol=1e-8):
            raise ValueError(f"transition_init must be a ({N},{N}) stochastic matrix")
    if initial_init is None:
        pi = np.full((W, N), 1.0 / N)
    else:
        pi = np.broadcast_to(np.asarray(initial_init, float), (W, N)).copy()
        if np.any(pi < 0) or not np.allclose(pi.sum(1), 1.0, atol=1e-8):
            raise ValueError("initial_init rows must be probability vectors")

    M1 = ch.onehot()
    theta = np.log(np.r_[Q, R])
    records: list[dict] = []
    prev = None
    converged = False

    def estep(Q, R, a, pi):
        logb = emission_loglik(model, data, Q, R)
        if extra is not None:
            logb = logb + extra
        init_super = np.zeros((W, ch.n_super))
        init_super[:, ch.const_index] = pi
        gamma, xi, ll = forward_backward(logb, data.valid, ch.transition(a), init_super)
        return gamma, xi, float(ll.sum())

    it = 0
    while True:
        try:
            gamma, xi, ll = estep(Q, R, a, pi)
        except FloatingPointError as exc:  # only possible at the start: steps are guarded
            raise ValueError(f"cannot evaluate the likelihood at the initial values: {exc} "
                             "(check c, d and the initial variances)") from None
        Qs_, Rs_, as_, _ = _sort_states(Q, R, a, pi, n_r)
        rec = {"iteration": it, "Q": Qs_.tolist(), "R": Rs_.tolist(), "objective": ll,
               "transition": as_.tolist()}
        records.append(rec)
        if callback is not None:
            callback(rec)
        if prev is not None and (ll - prev) <= tol * abs(prev):
            converged = True
            break
        if it >= max_iter:
            break
        prev = ll
        # --- M-step: chain
        counts = M1.T @ xi @ M1
        rows = counts.sum(1)
        a = a.copy()
        ok = rows > 0
        a[ok] = counts[ok] / rows[ok, None]
        g0 = gamma[:, 0, :][:, ch.const_index]
        g0 = g0 / g0.sum(1, keepdims=True)
        pi = np.repeat(g0.mean(0, keepdims=True), W, 0) if shared_initial else g0
        # --- M-step: variances
        S, n = _window_stats(data, gamma, p)
        scale = 1.0 / max(float(n.sum()), 1.0)  # objective per sample: O(1) gradients
        S, n = S * scale, n * scale
        keep = n > _MSTEP_MIN_WEIGHT * float(n.sum())
        sub, S, n = model.subset(keep), S[keep][None], n[keep][None]
        f0, _ = _qr_objective(theta, sub, S, n)
        res = minimize(_qr_objective, theta, args=(sub, S, n), jac=True, method="L-BFGS-B",
                       bounds=[(t - 25.0, t + 25.0) for t in theta],
                       options={"maxiter": _MSTEP_MAXITER, "ftol": 1e-12, "gtol": 1e-8})
        if np.all(np.isfinite(res.x)) and res.fun < f0:
            theta = res.x
        Q, R = np.exp(theta[:n_q]), np.exp(theta[n_q:])
        it += 1

    Qs, Rs, as_, pis = _sort_states(Q, R, a, pi, n_r)
    return EMResult(Qs, Rs, as_, pis, ll, records, converged, line_index, warns, p)


def sample_ma_mixture(rng, c, d, Q, R, transition, T: int, W: int):
    """Draw W lines of length T from the mixture of moving averages with Markov jumps.

    ``x_k = Σ c_l q_{k−l} + Σ d_l r_{k−l}`` with Var q = Q[s // n_r], Var r = R[s % n_r],
    the chain started from its stationary distribution; noises before the first sample
    take the first state.  The generative counterpart of :func:`fit_em` (tests, benchmarks).

    Returns
    -------
    (xs, states) : list of ndarray (T,), list of ndarray of int (T,)
    """
    c, d = np.asarray(c, float), np.asarray(d, float)
    Q, R = np.atleast_1d(np.asarray(Q, float)), np.atleast_1d(np.asarray(R, float))
    a = np.asarray(transition, float)
    p = max(len(c), len(d)) - 1
    N, n_r = Q.size * R.size, R.size
    w, v = np.linalg.eig(a.T)
    stat = np.abs(np.real(v[:, np.argmin(np.abs(w - 1.0))]))
    stat /= stat.sum()
    xs, ss = [], []
    for _ in range(W):
        s = np.empty(T, int)
        s[0] = rng.choice(N, p=stat)
        for k in range(1, T):
            s[k] = rng.choice(N, p=a[s[k - 1]])
        sf = np.r_[np.full(p, s[0]), s]
        q = rng.standard_normal(T + p) * np.sqrt(Q[sf // n_r])
        r = rng.standard_normal(T + p) * np.sqrt(R[sf % n_r])
        xs.append(np.convolve(q, c)[p: p + T] + np.convolve(r, d)[p: p + T])
        ss.append(s)
    return xs, ss
