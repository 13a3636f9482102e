"""Recognition: Viterbi and posteriors against brute-force enumeration and simulation."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from app.core.mjls_em import fit_em, sample_ma_mixture
from app.core.recognition import loglikelihood, posteriors, recognize_lines, viterbi


# ----------------------------------------------------------------- independent reference
def _window_noise_states(path, k, p):
    """States of the noises entering x_k under the documented one-switch rule.

    Returns a function n -> state for absolute noise index n (n may be < 0).
    Written from the definition (not from the implementation): the window
    s_{k-p..k} (pre-sample states = s_0) is reduced to its most recent switch.
    """
    s = lambda n: path[max(n, 0)]  # noqa: E731
    b = s(k)
    run = 0
    while run < p + 1 and s(k - run) == b:
        run += 1
    if run >= p + 1:
        return lambda n: b
    a = s(k - run)
    return lambda n: b if n > k - run else a


def _cond_logpdf(x, k, p, c, d, Qs, Rs, path, n_r):
    """log p(x_k | x_{k-m..k-1}) with m = min(k, p), from an explicit covariance."""
    m = min(k, p)
    st = _window_noise_states(path, k, p)
    K, L = len(c) - 1, len(d) - 1
    idx = np.arange(k - m, k + 1)
    noise = np.arange(k - m - max(K, L), k + 1)
    Cm = np.array([[c[t - n] if 0 <= t - n <= K else 0.0 for n in noise] for t in idx])
    Dm = np.array([[d[t - n] if 0 <= t - n <= L else 0.0 for n in noise] for t in idx])
    qv = np.array([Qs[st(n) // n_r] for n in noise])
    rv = np.array([Rs[st(n) % n_r] for n in noise])
    cov = Cm @ np.diag(qv) @ Cm.T + Dm @ np.diag(rv) @ Dm.T
    full = multivariate_normal(np.zeros(m + 1), cov).logpdf(x[idx])
    if m == 0:
        return full
    past = multivariate_normal(np.zeros(m), cov[:m, :m]).logpdf(x[idx[:-1]])
    return full - past


def _brute(x, c, d, Qs, Rs, a, pi):
    n_r = len(Rs)
    N = len(Qs) * n_r
    p = max(len(c), len(d)) - 1
    T = len(x)
    paths = list(itertools.product(range(N), repeat=T))
    logj = np.empty(len(paths))
    for ip, path in enumerate(paths):
        lp = np.log(pi[path[0]]) + sum(np.log(a[path[k - 1], path[k]]) for k in range(1, T))
        lp += sum(_cond_logpdf(x, k, p, c, d, Qs, Rs, path, n_r) for k in range(T))
        logj[ip] = lp
    mx = logj.max()
    total = mx + np.log(np.exp(logj - mx).sum())
    w = np.exp(logj - total)
    post = np.zeros((T, N))
    for ip, path in enumerate(paths):
        post[np.arange(T), list(path)] += w[ip]
    return total, post, np.array(paths[int(np.argmax(logj))])


@pytest.mark.parametrize(
    "c,d,Qs,Rs,T",
    [
        ([1.0, 0.6, 0.2], [0.4, -0.4], [0.05, 0.8], [1.0], 7),
        ([1.0, 0.5], [0.3, -0.6, 0.3], [0.1, 1.0], [0.5, 3.0], 5),
        ([1.0], [0.0], [0.2, 2.0], [1.0], 6),
    ],
)
def test_against_brute_force(c, d, Qs, Rs, T):
    rng = np.random.default_rng(7)
    N = len(Qs) * len(Rs)
    a = np.full((N, N), 0.3 / (N - 1))
    np.fill_diagonal(a, 0.7)
    pi = rng.dirichlet(np.ones(N))
    x = rng.standard_normal(T) * 1.2
    total, post, best = _brute(x, np.array(c), np.array(d), Qs, Rs, a, pi)
    assert loglikelihood(x, c, d, Qs, Rs, a, pi) == pytest.approx(total, rel=1e-10, abs=1e-10)
    np.testing.assert_allclose(posteriors(x, c, d, Qs, Rs, a, pi), post, atol=1e-10)
    np.testing.assert_array_equal(viterbi(x, c, d, Qs, Rs, a, pi), best)


def test_stationary_loglik_equals_gaussian_conditionals():
    """N = 1: the likelihood is the product of exact windowed Gaussian conditionals."""
    rng = np.random.default_rng(3)
    c = np.array([2.0, 3.0, 2.0]) * 0.5
    d = np.array([0.05, -0.1, 0.05])
    x = rng.standard_normal(40)
    Q, R = 0.3, 4.0
    p = 2
    ref = 0.0
    Cfull = np.zeros((40, 42))
    Dfull = np.zeros((40, 42))
    for k in range(40):
        Cfull[k, k: k + 3] = c[::-1]
        Dfull[k, k: k + 3] = d[::-1]
    cov = Q * Cfull @ Cfull.T + R * Dfull @ Dfull.T
    for k in range(40):
        m = min(k, p)
        sl = slice(k - m, k + 1)
        ref += multivariate_normal(np.zeros(m + 1), cov[sl, sl]).logpdf(x[sl])
        if m:
            ref -= multivariate_normal(np.zeros(m), cov[k - m:k, k - m:k]).logpdf(x[k - m:k])
    got = loglikelihood(x, c, d, [Q], [R], np.ones((1, 1)), [1.0])
    assert got == pytest.approx(ref, rel=1e-10)


def _simulate(rng, c, d, Qs, Rs, a, T, W):
    return sample_ma_mixture(rng, c, d, Qs, Rs, a, T, W)


def test_viterbi_accuracy_on_simulated_data():
    rng = np.random.default_rng(11)
    c = 4.0 * np.hanning(7)[1:-1]
    d = 0.1 * np.array([1.0, -3.0, 3.0, -1.0])
    a = np.array([[0.9876, 0.0124], [0.0303, 0.9697]])
    Qs, Rs = [0.0414, 0.3533], [1.68]
    xs, ss = _simulate(rng, c, d, Qs, Rs, a, 200, 15)
    truth = np.concatenate(ss)
    states, probs = recognize_lines(xs, c, d, Qs, Rs, a, [0.7, 0.3])
    acc = np.mean(np.concatenate(states) == truth)
    chance = max(np.mean(truth == 0), np.mean(truth == 1))
    assert acc > 0.9 and acc > chance + 0.15
    allp = np.concatenate(probs)
    np.testing.assert_allclose(allp.sum(1), 1.0, atol=1e-12)
    acc_post = np.mean(np.argmax(allp, 1) == truth)
    assert acc_post > 0.9


def test_em_then_recognition_single_line_initial_is_posterior():
    rng = np.random.default_rng(5)
    c = np.array([1.0, 0.5])
    d = np.array([0.2, -0.2])
    a = np.array([[0.97, 0.03], [0.05, 0.95]])
    xs, _ = _simulate(rng, c, d, [0.05, 1.0], [1.0], a, 300, 1)
    res = fit_em(xs, c, d, max_iter=200, tol=1e-10)
    post0 = posteriors(xs[0], c, d, res.Q, res.R, res.transition, res.initial[0])[0]
    np.testing.assert_allclose(res.initial[0], post0, atol=1e-3)


def test_validation():
    a = np.array([[0.9, 0.1], [0.1, 0.9]])
    with pytest.raises(ValueError, match="NaN"):
        viterbi(np.array([1.0, np.nan, 2.0]), [1.0], [0.5], [1.0, 2.0], [1.0], a, [0.5, 0.5])
    with pytest.raises(ValueError, match="stochastic"):
        viterbi(np.ones(5), [1.0], [0.5], [1.0, 2.0], [1.0], a * 2, [0.5, 0.5])
    with pytest.raises(ValueError, match="probability"):
        posteriors(np.ones(5), [1.0], [0.5], [1.0, 2.0], [1.0], a, [0.5, 0.6])


def test_extra_loglik_zero_is_neutral_and_strong_evidence_wins():
    from app.core.recognition import state_evidence
    rng = np.random.default_rng(7)
    c, d = [1.0, 0.5], [0.8, -0.8]
    x = rng.standard_normal(80)
    Q, R, a, pi = [0.2, 2.0], [1.0], np.array([[0.95, 0.05], [0.1, 0.9]]), np.array([0.5, 0.5])
    base = posteriors(x, c, d, Q, R, a, pi)
    np.testing.assert_allclose(posteriors(x, c, d, Q, R, a, pi, np.zeros((80, 2))), base, atol=1e-12)
    ev = state_evidence(x, c, d, Q, R)
    assert ev.shape == (80, 2) and np.all(ev[:, 0] == 0)
    push = np.zeros((80, 2))
    push[:, 1] = 50.0
    assert np.all(viterbi(x, c, d, Q, R, a, pi, push) == 1)
    # a (K+1, 1) block coefficient is the same model as the 1-D one
    np.testing.assert_allclose(posteriors(x, np.array(c)[:, None], np.array(d)[:, None], Q, R, a, pi), base,
                               atol=1e-10)
