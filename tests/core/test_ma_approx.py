"""Tests for app.core.ma_approx: analytic decimated autocovariance and Monte-Carlo truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import comb

from app.core.ma_approx import (
    autocovariance,
    fit_ma_component,
    fit_ma_model,
    ma_autocovariance,
    model_vs_true_spectrum,
    spectral_factor,
)
from app.core.regularize import design_regularization, regularize_line

DT = 0.1


@pytest.fixture(scope="module", params=["decimated", "full"])
def design(request):
    return design_regularization(DT, 100.0, difference_grid=request.param)


def _analytic_gammas(design, m):
    """Decimated autocovariances per unit Q and R, built here from first principles."""
    h = design.taps
    n = design.n
    if design.difference_grid == "decimated":
        # ∇_n^m (h*z) = h * (1 + B + … + B^{n−1})^m * ∇^m z
        gq = h.copy()
        for _ in range(m):
            gq = np.convolve(gq, np.ones(n))
    else:
        gq = h.copy()
    nab = np.array([(-1) ** i * comb(m + 1, i, exact=True) for i in range(m + 2)], float)
    gr = 1000.0 / DT * np.convolve(gq, nab)

    def acov(g):
        J = (g.size - 1) // n
        return np.array([np.dot(g[: g.size - j * n], g[j * n:]) for j in range(J + 1)])

    return acov(gq), acov(gr)


def _rel_l2(a, b):
    size = max(a.size, b.size)
    A = np.zeros(size)
    B = np.zeros(size)
    A[: a.size] = a
    B[: b.size] = b
    w = np.full(size, np.sqrt(2.0))
    w[0] = 1
    return np.linalg.norm(w * (A - B)) / np.linalg.norm(w * B)


@pytest.mark.parametrize("m", [1, 2])
def test_model_autocovariance_matches_analytic(design, m):
    model = fit_ma_model(design, m)
    gq, gr = _analytic_gammas(design, m)
    maxlag = max(gq.size, gr.size) + 3
    aq = autocovariance(model, 1.0, 0.0, maxlag)
    ar = autocovariance(model, 0.0, 1.0, maxlag)
    assert _rel_l2(aq, gq) < 0.01
    assert _rel_l2(ar, gr) < 0.01
    assert np.max(np.abs(aq[: gq.size] - gq)) < 0.01 * gq[0]
    assert np.max(np.abs(ar[: gr.size] - gr)) < 0.01 * gr[0]
    # reported misfits are the measured ones
    assert model.misfit_q == pytest.approx(_rel_l2(aq, gq), rel=1e-6, abs=1e-12)
    assert model.misfit_r == pytest.approx(_rel_l2(ar, gr), rel=1e-6, abs=1e-12)
    # coefficients as plain arrays, sizes and p consistent, p small
    assert model.c.shape == (model.K + 1,) and model.d.shape == (model.L + 1,)
    assert model.p == max(model.K, model.L) <= 10
    assert model.dt_dec_s == pytest.approx(10.0)


@pytest.mark.parametrize("m", [1, 2])
def test_full_order_is_exact_factor(design, m):
    gq, gr = _analytic_gammas(design, m)
    model = fit_ma_model(design, m, K=gq.size - 1, L=gr.size - 1)
    np.testing.assert_allclose(ma_autocovariance(model.c), gq, rtol=1e-6, atol=1e-9 * gq[0])
    np.testing.assert_allclose(ma_autocovariance(model.d), gr, rtol=1e-5, atol=1e-9 * gr[0])


def test_order_criterion_is_minimal(design):
    m = 2
    model = fit_ma_model(design, m)
    assert model.misfit_q < 0.01 and model.band_error_q < 0.05
    assert model.misfit_r < 0.01 and model.band_error_r < 0.05
    if model.K > 0:
        lower = fit_ma_model(design, m, K=model.K - 1, L=model.L)
        assert lower.misfit_q >= 0.01 or lower.band_error_q >= 0.05
    if model.L > 0:
        lower = fit_ma_model(design, m, K=model.K, L=model.L - 1)
        assert lower.misfit_r >= 0.01 or lower.band_error_r >= 0.05
    looser = fit_ma_model(design, m, tol=0.05, band_tol=10.0)
    assert looser.K <= model.K and looser.L <= model.L
    assert looser.misfit_q < 0.05 and looser.misfit_r < 0.05


def _spec_from_acov(gamma, w):
    j = np.arange(1, gamma.size)
    return gamma[0] + 2 * np.cos(np.outer(w, j)) @ gamma[1:]


def _spec_from_coef(b, w):
    return np.abs(np.exp(-1j * np.outer(w, np.arange(b.size))) @ b) ** 2


def test_band_error_measured_independently():
    design = design_regularization(DT, 100.0)
    w = np.linspace(1e-4, np.pi - 1e-4, 4001)
    for m in (1, 2):
        model = fit_ma_model(design, m)
        gq, gr = _analytic_gammas(design, m)
        for gamma, b, reported in ((gq, model.c, model.band_error_q), (gr, model.d, model.band_error_r)):
            st = _spec_from_acov(gamma, w)
            sm = _spec_from_coef(b, w)
            err = np.max(np.abs(sm - st) / (st + 0.01 * st.max()))
            assert err < 0.05
            assert err == pytest.approx(reported, rel=0.1, abs=2e-3)


@pytest.mark.parametrize("m, Q0", [(1, 0.04), (1, 0.35), (2, 1e-6), (2, 1e-5)])
def test_whittle_bias_of_q_and_r_is_small(m, Q0):
    """Fitness for learning: the asymptotic (Whittle) ML estimate of (Q, R) within the
    MA-model family, for data with the exact decimated spectrum, is within 1 % of truth."""
    from scipy.optimize import minimize

    design = design_regularization(DT, 100.0)
    model = fit_ma_model(design, m)
    R0 = 1.68
    gq, gr = _analytic_gammas(design, m)
    w = (np.arange(2000) + 0.5) * np.pi / 2000
    s_true = Q0 * _spec_from_acov(gq, w) + R0 * _spec_from_acov(gr, w)
    sc, sd = _spec_from_coef(model.c, w), _spec_from_coef(model.d, w)

    def whittle(th):
        s = np.exp(th[0]) * sc + np.exp(th[1]) * sd
        return np.mean(np.log(s) + s_true / s)

    res = minimize(whittle, [np.log(Q0) + 0.3, np.log(R0) - 0.3], method="Nelder-Mead",
                   options=dict(xatol=1e-9, fatol=1e-15, maxiter=5000))
    Q, R = np.exp(res.x)
    assert abs(Q / Q0 - 1) < 0.01
    assert abs(R / R0 - 1) < 0.01


def test_override_orders_and_validation(design):
    model = fit_ma_model(design, 1, K=2, L=3)
    assert model.c.shape == (3,) and model.d.shape == (4,) and model.p == 3
    with pytest.raises(ValueError, match="order"):
        fit_ma_model(design, 1, K=-1)
    with pytest.raises(ValueError, match="m must"):
        fit_ma_model(design, 0)
    with pytest.raises(ValueError, match="maxlag"):
        autocovariance(model, 1.0, 1.0, -1)


def _simulate_x(design, m, Q, R, component, n_lines, line_len, rng):
    """Full-rate simulation → regularize_line; returns the list of decimated lines."""
    out = []
    for _ in range(n_lines):
        if component == "q":
            dg = rng.normal(scale=np.sqrt(Q), size=line_len)
            for _ in range(m):
                dg = np.cumsum(dg)
            z = dg
        else:
            r = rng.normal(scale=np.sqrt(R), size=line_len + 1)  # cm/s
            z = -1000.0 * np.diff(r) / DT
        x, _ = regularize_line(z, m, design)
        out.append(x)
    return out


def _pooled_acov(lines, maxlag):
    num = np.zeros(maxlag + 1)
    cnt = np.zeros(maxlag + 1)
    for x in lines:
        for j in range(maxlag + 1):
            num[j] += np.dot(x[: x.size - j], x[j:])
            cnt[j] += x.size - j
    return num / cnt, cnt


@pytest.mark.parametrize("m", [1, 2])
@pytest.mark.parametrize("component", ["q", "r"])
def test_monte_carlo_autocovariance(m, component):
    design = design_regularization(DT, 100.0)
    model = fit_ma_model(design, m)
    Q, R = (0.04, 0.0) if component == "q" else (0.0, 1.7)
    rng = np.random.default_rng(1000 * m + (component == "r"))
    lines = _simulate_x(design, m, Q, R, component, n_lines=120, line_len=50_000, rng=rng)
    maxlag = model.p + 3
    est, cnt = _pooled_acov(lines, maxlag)
    # exact target (analytic), and the model's
    gq, gr = _analytic_gammas(design, m)
    gamma = Q * gq if component == "q" else R * gr
    g = np.zeros(maxlag + 40)
    g[: gamma.size] = gamma
    model_acov = autocovariance(model, Q, R, maxlag)
    # Bartlett's large-sample standard error of the lag-j sample autocovariance
    # (zero-mean Gaussian): Var ≈ (1/N) Σ_v (γ_v² + γ_{v+j} γ_{v−j})
    gg = np.concatenate([g[:0:-1], g])  # lags −(len−1)..len−1
    c0 = g.size - 1
    se = np.array([
        np.sqrt(sum(gg[c0 + v] ** 2 + gg[c0 + v + j] * gg[c0 + v - j]
                    for v in range(-(g.size - 1 - j), g.size - j)) / cnt[j])
        for j in range(maxlag + 1)
    ])
    assert np.all(np.abs(est - g[: maxlag + 1]) < 5 * se)  # the simulation agrees with theory
    misfit = model.misfit_q if component == "q" else model.misfit_r
    allowance = misfit * np.linalg.norm(gamma) * np.sqrt(2)
    assert np.all(np.abs(est - model_acov) < 5 * se + allowance)
    # and the sampling error is small enough for this to be a real check
    assert 5 * se[0] < 0.05 * g[0]


def test_spectrum_fold_sum_vs_model(design):
    m = 1
    model = fit_ma_model(design, m)
    T = design.dt_dec_s
    f = (np.arange(256) + 0.5) / 256 * (0.5 / T)  # midpoints on (0, 1/2T)
    spec = model_vs_true_spectrum(model, design, f)
    gq, gr = _analytic_gammas(design, m)
    for name, gamma, mis in (("q", gq, model.misfit_q), ("r", gr, model.misfit_r)):
        true = spec[f"true_{name}"]
        mod = spec[f"model_{name}"]
        # Parseval: the aliased fold-sum integrates to the analytic decimated variance
        var = 2 * np.sum(true) * (0.5 / T) / f.size
        assert var == pytest.approx(gamma[0], rel=1e-3)
        # and matches the trig polynomial of the analytic autocovariance
        j = np.arange(1, gamma.size)
        trig = T * (gamma[0] + 2 * np.cos(2 * np.pi * np.outer(f, j) * T) @ gamma[1:])
        np.testing.assert_allclose(true, trig, rtol=1e-6, atol=1e-9 * trig.max())
        # relative L2 spectral misfit equals the reported one (Parseval)
        rel = np.linalg.norm(mod - true) / np.linalg.norm(true)
        assert rel == pytest.approx(mis, rel=0.05, abs=1e-6)


def test_long_ill_conditioned_autocovariance_still_fits():
    """A 1 500-lag autocovariance (an MA(3) plus a 10⁻⁹ decaying tail, like a height-noise
    component differenced m + 2 times): the roots of its degree-3 000 polynomial are lost to
    round-off (they used to give a white start), the cepstrum factors it — the MA(3) itself
    comes back — and the least-squares fit recovers the MA(3) within the 1 % misfit (it used
    to raise from least_squares)."""
    b = np.array([1.0, 0.5, -0.3, 0.1])
    J = 1500
    g = np.zeros(J + 1)
    a = ma_autocovariance(b)
    g[:a.size] = a
    g += 1e-9 * 0.995 ** np.arange(J + 1) * np.cos(0.01 * np.arange(J + 1))
    start = spectral_factor(g)
    assert np.all(np.isfinite(start))
    np.testing.assert_allclose(start[:4], b, atol=1e-6)
    c, k, f, be = fit_ma_component(g)
    assert k <= 4 and f < 0.01 and np.all(np.isfinite(c))
    np.testing.assert_allclose(ma_autocovariance(c)[:4], a, atol=1e-3)


def test_long_autocovariance_factored_exactly_and_as_scipy_does():
    """A long autocovariance (J = 1 000: an MA(3) padded with zero lags, and a slowly
    decaying AR(1)-like spectrum through a first difference, which puts a zero at ω = 0)
    is factored by the cepstrum: the MA(3) comes back as its own minimum-phase factor
    (its roots lie inside the unit circle), and the differenced one agrees with SciPy's
    homomorphic minimum-phase filter of the symmetric sequence (``signal.minimum_phase``),
    whose magnitude response is the square root of the spectrum."""
    from scipy import signal

    b = np.array([1.0, 0.5, -0.3, 0.1])
    assert np.all(np.abs(np.roots(b)) < 1.0)        # minimum phase
    J = 1000
    g = np.zeros(J + 1)
    g[:b.size] = ma_autocovariance(b)
    f = spectral_factor(g)
    np.testing.assert_allclose(f[:b.size], b, atol=1e-10)
    assert np.max(np.abs(f[b.size:])) < 1e-10
    # AR(1) with φ = 0.995 (a slow Gauss–Markov error), then a first difference
    h = np.convolve(0.995 ** np.arange(4000), [1.0, -1.0])
    g2 = np.array([h[: h.size - j] @ h[j:] for j in range(J + 1)])
    f2 = spectral_factor(g2)
    a2 = ma_autocovariance(f2)
    assert np.linalg.norm(a2 - g2) / np.linalg.norm(g2) < 1e-5
    peer = signal.minimum_phase(np.concatenate([g2[:0:-1], g2]), method="homomorphic", n_fft=1 << 16)
    assert peer.size == J + 1
    np.testing.assert_allclose(f2[:50], peer[:50], atol=1e-3 * abs(peer[0]))
