"""EM learning of the switching MA mixture: peer check, monotonicity, recovery, validation."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from app.core.mjls_em import fit_em, sample_ma_mixture


def _simulate(rng, c, d, Qs, Rs, a, T, W):
    """Draw lines from the model (pre-sample noise states = s_0)."""
    return sample_ma_mixture(rng, c, d, Qs, Rs, a, T, W)


# ----------------------------------------------------------------- peer check: hmmlearn
@pytest.mark.parametrize("shared", [False, True])
def test_order_zero_equals_hmmlearn(shared):
    hmm = pytest.importorskip("hmmlearn.hmm")
    rng = np.random.default_rng(0)
    a_true = np.array([[0.95, 0.05], [0.1, 0.9]])
    W = 3 if shared else 1
    xs, _ = _simulate(rng, [1.0], [0.0], [0.3, 3.0], [1.0], a_true, 400, W)
    Q0 = np.array([0.5, 2.0])
    a0 = np.array([[0.8, 0.2], [0.3, 0.7]])
    pi0 = np.array([0.5, 0.5])
    n_iter = 12
    res = fit_em(xs, [1.0], [0.0], n_q=2, n_r=1, Q_init=Q0, R_init=[1.0], transition_init=a0,
                 initial_init=pi0, max_iter=n_iter, tol=0.0, shared_initial=shared)
    # hmmlearn 0.3.3 accumulates stats['post'] only when 'm' is in params, so the
    # means are "fitted" under a prior pinning them at 0 (weight 1e12: |mean| ~ 1e-12).
    m = hmm.GaussianHMM(n_components=2, covariance_type="diag", params="stmc", init_params="",
                        n_iter=n_iter, tol=-np.inf, covars_prior=0.0, covars_weight=1.0,
                        means_prior=0.0, means_weight=1e12)
    m.startprob_ = pi0
    m.transmat_ = a0
    m.means_ = np.zeros((2, 1))
    m.covars_ = Q0[:, None]
    X = np.concatenate(xs)[:, None]
    m.fit(X, lengths=[len(x) for x in xs])
    cov = m._covars_[:, 0]
    order = np.argsort(cov)
    assert np.max(np.abs(m.means_)) < 1e-9
    np.testing.assert_allclose(res.Q, cov[order], rtol=1e-3)
    np.testing.assert_allclose(res.transition, m.transmat_[np.ix_(order, order)], rtol=1e-3)
    np.testing.assert_allclose(res.initial[0], m.startprob_[order], atol=1e-3)
    assert len(res.iterations) == n_iter + 1
    # log-likelihood at the final parameters agrees too
    assert res.loglik == pytest.approx(m.score(X, lengths=[len(x) for x in xs]), rel=1e-6)


# ----------------------------------------------------------------- monotonicity
@pytest.mark.parametrize("n_q,n_r,seed", [(2, 1, 1), (2, 1, 2), (2, 2, 3), (2, 2, 4), (3, 1, 5)])
def test_objective_never_decreases(n_q, n_r, seed):
    rng = np.random.default_rng(seed)
    N = n_q * n_r
    a = np.full((N, N), 0.08 / (N - 1))
    np.fill_diagonal(a, 0.92)
    c = rng.uniform(0.2, 1.0, size=rng.integers(1, 4))
    d = rng.normal(size=rng.integers(1, 4)) * 0.3
    Qs = np.sort(rng.uniform(0.02, 1.0, n_q))
    Rs = np.sort(rng.uniform(0.5, 5.0, n_r))
    xs, _ = _simulate(rng, c, d, Qs, Rs, a, 60, 5)
    res = fit_em(xs, c, d, n_q=n_q, n_r=n_r, max_iter=15, tol=0.0)
    obj = np.array([r["objective"] for r in res.iterations])
    assert np.all(np.diff(obj) >= -1e-9 * np.abs(obj[:-1]))
    assert obj[-1] > obj[0]


def test_stationary_data_with_two_states_is_safe():
    """Over-parametrised model (N = 2 on stationary data): no failure, monotone, finite."""
    rng = np.random.default_rng(8)
    c, d = np.array([1.0, 0.6]), np.array([0.4, -0.4])
    xs, _ = _simulate(rng, c, d, [0.3], [2.0], np.ones((1, 1)), 80, 6)
    res = fit_em(xs, c, d, n_q=2, n_r=1, max_iter=30, tol=0.0)
    obj = np.array([r["objective"] for r in res.iterations])
    assert np.all(np.diff(obj) >= -1e-9 * np.abs(obj[:-1]))
    assert np.all(np.isfinite(res.Q)) and np.all(res.Q > 0) and np.all(np.isfinite(res.transition))
    # stationary fit for comparison: the 2-state likelihood is at least as high
    one = fit_em(xs, c, d, n_q=1, n_r=1, max_iter=60, tol=1e-10)
    assert one.Q[0] == pytest.approx(0.3, rel=0.25) and one.R[0] == pytest.approx(2.0, rel=0.25)
    assert res.loglik >= one.loglik - 1e-6 * abs(one.loglik)


# ----------------------------------------------------------------- parameter recovery
def test_recovery_two_states_realistic_ma():
    rng = np.random.default_rng(2024)
    c = 10.0 * np.hanning(9)[1:-1]          # smooth anomaly kernel, K = 6
    d = 0.05 * np.array([1.0, -3.0, 3.0, -1.0])  # differenced GNSS noise, L = 3
    a = np.array([[0.9876, 0.0124], [0.0303, 0.9697]])
    Q_true, R_true = np.array([0.0414, 0.3533]), np.array([1.68])
    xs, _ = _simulate(rng, c, d, Q_true, R_true, a, 150, 60)
    seen = []
    res = fit_em(xs, c, d, n_q=2, n_r=1, callback=seen.append)
    assert res.converged
    np.testing.assert_allclose(res.Q, Q_true, rtol=0.15)
    np.testing.assert_allclose(res.R, R_true, rtol=0.15)
    np.testing.assert_allclose(np.diag(res.transition), np.diag(a), atol=0.01)
    assert res.initial.shape == (60, 2)
    np.testing.assert_allclose(res.initial.sum(1), 1.0)
    assert seen == res.iterations and seen[0]["iteration"] == 0
    assert set(seen[0]) == {"iteration", "Q", "R", "objective", "transition"}


def test_recovery_two_by_two():
    rng = np.random.default_rng(77)
    a = np.full((4, 4), 0.01)
    np.fill_diagonal(a, 0.97)
    c = np.array([0.3, 0.6, 0.8, 0.6, 0.3])
    d = 0.3 * np.array([1.0, -2.0, 1.0])
    Q_true, R_true = np.array([0.05, 0.5]), np.array([1.0, 5.0])
    xs, ss = _simulate(rng, c, d, Q_true, R_true, a, 100, 60)
    res = fit_em(xs, c, d, n_q=2, n_r=2)
    np.testing.assert_allclose(res.Q, Q_true, rtol=0.15)
    np.testing.assert_allclose(res.R, R_true, rtol=0.15)
    np.testing.assert_allclose(np.diag(res.transition), np.diag(a), atol=0.02)


def test_state_order_is_canonical():
    """EM is permutation-equivariant: starting from swapped levels gives the same sorted result."""
    rng = np.random.default_rng(9)
    a = np.array([[0.95, 0.05], [0.08, 0.92]])
    c, d = np.array([1.0, 0.7]), np.array([0.3, -0.3])
    xs, _ = _simulate(rng, c, d, [0.05, 0.8], [1.0], a, 80, 8)
    r1 = fit_em(xs, c, d, Q_init=[0.1, 1.0], R_init=[2.0], transition_init=[[0.9, 0.1], [0.2, 0.8]],
                max_iter=10, tol=0.0)
    r2 = fit_em(xs, c, d, Q_init=[1.0, 0.1], R_init=[2.0], transition_init=[[0.8, 0.2], [0.1, 0.9]],
                max_iter=10, tol=0.0)
    np.testing.assert_allclose(r1.Q, r2.Q, rtol=1e-5)
    np.testing.assert_allclose(r1.transition, r2.transition, atol=1e-6)
    np.testing.assert_allclose(r1.initial, r2.initial, atol=1e-6)
    assert r1.Q[0] < r1.Q[1]
    assert r2.iterations[0]["Q"] == [0.1, 1.0]  # records are sorted too
    np.testing.assert_allclose(r2.iterations[0]["transition"], [[0.9, 0.1], [0.2, 0.8]])


# ----------------------------------------------------------------- validation
def test_validation_and_short_lines():
    rng = np.random.default_rng(1)
    c, d = np.array([1.0, 0.5, 0.2]), np.array([0.3])
    good = [rng.standard_normal(50) for _ in range(3)]
    with pytest.raises(ValueError, match="line 1"):
        fit_em([good[0], np.r_[good[1][:10], np.nan, good[1][10:]]], c, d)
    res = fit_em([good[0], np.ones(3), good[1]], c, d, max_iter=3)
    assert res.line_index == [0, 2]
    assert len(res.warnings) == 1 and "line 1" in res.warnings[0]
    assert res.initial.shape == (2, 2)
    with pytest.raises(ValueError, match="p \\+ 2"):
        fit_em([np.ones(3), np.ones(2)], c, d)
    with pytest.raises(ValueError):
        fit_em(good, c, d, Q_init=[1.0])
    with pytest.raises(ValueError):
        fit_em(good, c, d, transition_init=[[0.5, 0.6], [0.5, 0.5]])
    with pytest.raises(ValueError):
        fit_em(good, [np.nan], d)


def test_data_driven_initialisation_is_sensible():
    rng = np.random.default_rng(4)
    a = np.array([[0.98, 0.02], [0.04, 0.96]])
    c, d = np.array([1.0, 0.8, 0.4]), np.array([0.2, -0.4, 0.2])
    xs, _ = _simulate(rng, c, d, [0.05, 0.6], [2.0], a, 100, 20)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = fit_em(xs, c, d, max_iter=0)
    Q0 = np.array(res.iterations[0]["Q"])
    R0 = res.iterations[0]["R"][0]
    assert 0.005 < Q0[0] < Q0[1] < 3.0
    assert 0.5 < R0 < 8.0


def test_mstep_gradient_matches_finite_differences():
    from app.core.mjls_em import WindowModel, _layout, _qr_objective, _window_stats

    rng = np.random.default_rng(12)
    c, d = np.array([2.0, 1.0, 0.5]), np.array([0.1, -0.2])
    model = WindowModel(c, d, 2, 2)
    xs = [rng.standard_normal(30) for _ in range(3)]
    data = _layout(xs, model.p)
    gamma = rng.dirichlet(np.ones(model.chain.n_super), size=(3, 30))
    S, n = _window_stats(data, gamma, model.p)
    theta = np.log([0.05, 0.4, 1.0, 3.0])
    f, g = _qr_objective(theta, model, S, n)
    eps = 1e-6
    num = np.array([(_qr_objective(theta + eps * e, model, S, n)[0]
                     - _qr_objective(theta - eps * e, model, S, n)[0]) / (2 * eps) for e in np.eye(4)])
    np.testing.assert_allclose(g, num, rtol=1e-5, atol=1e-6 * abs(f))


def test_mstep_on_weighted_pairs_only_equals_full_objective():
    """The M-step evaluates only the (class, super-state) pairs that carry weight; pairs of
    zero weight contribute nothing, so value and gradient must equal the full sum's."""
    from app.core.mjls_em import WindowModel, _layout, _qr_objective, _window_stats

    rng = np.random.default_rng(5)
    c, d = np.array([2.0, 1.0, 0.5, 0.2]), np.array([0.1, -0.2, 0.05])
    model = WindowModel(c, d, 2, 2)
    xs = [rng.standard_normal(n) for n in (25, 40, 31)]
    data = _layout(xs, model.p)
    U = model.chain.n_super
    gamma = rng.dirichlet(np.ones(U), size=(3, 40))
    gamma[..., rng.random(U) < 0.5] = 0.0          # half the super-states never visited
    gamma /= gamma.sum(-1, keepdims=True)
    S, n = _window_stats(data, gamma, model.p)
    keep = n > 0
    assert 0 < keep.sum() < keep.size
    theta = np.log([0.05, 0.4, 1.0, 3.0])
    f_full, g_full = _qr_objective(theta, model, S, n)
    f_sub, g_sub = _qr_objective(theta, model.subset(keep), S[keep][None], n[keep][None])
    np.testing.assert_allclose(f_sub, f_full, rtol=1e-12)
    np.testing.assert_allclose(g_sub, g_full, rtol=1e-10, atol=1e-12 * abs(f_full))
    # a wrong selection (one weighted pair left out) is seen
    drop = keep.copy()
    drop[np.argwhere(keep)[0][0], np.argwhere(keep)[0][1]] = False
    f_bad, _ = _qr_objective(theta, model.subset(drop), S[drop][None], n[drop][None])
    assert abs(f_bad - f_full) > 1e-6 * abs(f_full)
    with pytest.raises(ValueError, match="mask must have shape"):
        model.subset(keep[:, :-1])
