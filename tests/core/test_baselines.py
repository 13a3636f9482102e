"""Tests of the baseline filters against analytic responses, a peer library and simulations."""

import numpy as np
import pytest

from app.core.baselines import (
    estimate_stationary_qr,
    fir_kernel,
    fir_lowpass_mgal,
    position_domain_filter,
    random_walk_kf,
    stationary_smooth,
)
from app.core.smoother import kalman_smooth

DT = 0.1


def _fit_sin(t, y, f):
    """Least-squares amplitude and phase of y ≈ a sin(2πft) + b cos(2πft) + c."""
    X = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t), np.ones_like(t)])
    a, b, _ = np.linalg.lstsq(X, y, rcond=None)[0]
    return np.hypot(a, b), np.arctan2(b, a)


# --------------------------------------------------------------------------- FIR


def test_fir_unit_dc_gain_everywhere_including_edges_and_gaps():
    x = np.full(20_000, 37.5)
    x[5000:5300] = np.nan
    x[:3] = np.nan
    y = fir_lowpass_mgal(x, DT)
    assert np.all(np.isfinite(y))
    np.testing.assert_allclose(y, 37.5, rtol=1e-12)
    assert fir_kernel(DT).sum() == pytest.approx(1.0, abs=1e-14)


def test_fir_minus_6db_near_cutoff_and_passband():
    t = np.arange(0, 6000, DT)
    inner = slice(3000, -3000)
    amp_c, _ = _fit_sin(t[inner], fir_lowpass_mgal(np.sin(2 * np.pi * 0.01 * t), DT)[inner], 0.01)
    assert 20 * np.log10(amp_c) == pytest.approx(-6.02, abs=0.5)
    amp_s, _ = _fit_sin(t[inner], fir_lowpass_mgal(np.sin(2 * np.pi * 0.03 * t), DT)[inner], 0.03)
    assert amp_s < 1e-3  # stop band
    amp_p, _ = _fit_sin(t[inner], fir_lowpass_mgal(np.sin(2 * np.pi * 0.002 * t), DT)[inner], 0.002)
    assert amp_p == pytest.approx(1.0, abs=0.03)


def test_fir_zero_phase():
    """A passband sinusoid keeps its phase (no time shift) and gets the DTFT gain."""
    t = np.arange(0, 5000, DT)
    f, ph = 1 / 400.0, 0.7
    y = fir_lowpass_mgal(3.0 * np.sin(2 * np.pi * f * t + ph), DT)
    inner = slice(2000, -2000)
    amp, phase = _fit_sin(t[inner], y[inner], f)
    h = fir_kernel(DT)
    n = np.arange(h.size) - h.size // 2
    gain = np.sum(h * np.cos(2 * np.pi * f * n * DT))
    assert phase == pytest.approx(ph, abs=1e-6)
    assert amp == pytest.approx(3.0 * gain, rel=1e-6)


def test_fir_long_input_and_bad_input():
    rng = np.random.default_rng(0)
    y = fir_lowpass_mgal(rng.normal(size=1_500_000), DT)
    assert y.shape == (1_500_000,) and np.all(np.isfinite(y))
    # white noise variance reduced by Σh²
    assert np.var(y[10_000:-10_000]) == pytest.approx(np.sum(fir_kernel(DT) ** 2), rel=0.15)
    with pytest.raises(ValueError):
        fir_lowpass_mgal(np.ones(100), 0.0)
    with pytest.raises(ValueError):
        fir_lowpass_mgal(np.ones(100), DT, cutoff_period_s=0.1)
    with pytest.raises(ValueError):
        fir_lowpass_mgal(np.ones((3, 3)), DT)


# --------------------------------------------------------------- stationary, ML


def _simulate(rng, T, m, Q, R, dt=DT):
    q = rng.normal(size=T) * np.sqrt(Q)
    dg = q.copy()
    for _ in range(m):
        dg = np.cumsum(dg)
    r = rng.normal(size=T + 1) * np.sqrt(R)
    return dg - 1000.0 * np.diff(r) / dt, dg


def test_stationary_smooth_is_constant_qr_smoother():
    rng = np.random.default_rng(1)
    z, dg = _simulate(rng, 3000, 2, 1e-2, 2.0)
    a = stationary_smooth(z, 1e-2, 2.0, DT, m=2)
    b = kalman_smooth(z, np.full(3000, 1e-2), np.full(3000, 2.0), DT, m=2)
    np.testing.assert_array_equal(a.dg_mgal, b.dg_mgal)
    with pytest.raises(ValueError):
        stationary_smooth(z, np.full(3000, 1e-2), 2.0, DT)


def test_estimate_stationary_qr_recovers_truth():
    rng = np.random.default_rng(5)
    Q, R = 1e-2, 2.0
    lines = [_simulate(rng, 10_000, 2, Q, R)[0] for _ in range(3)]
    est = estimate_stationary_qr(lines, DT, m=2)
    assert 0 < est.se_log_Q < 0.3 and 0 < est.se_log_R < 0.05
    assert abs(np.log(est.Q_mgal2 / Q)) < 4 * est.se_log_Q
    assert abs(np.log(est.R_cm2s2 / R)) < 4 * est.se_log_R
    with pytest.raises(ValueError):
        estimate_stationary_qr([np.ones(2)], DT, m=2)


# ------------------------------------------------------------ random walk (003)


def test_random_walk_ml_q_within_sampling_error():
    rng = np.random.default_rng(11)
    Q, R, N = 0.01, 1.0, 20_000
    x = np.cumsum(rng.normal(0, np.sqrt(Q), N))
    y = x + rng.normal(0, np.sqrt(R), N)
    res = random_walk_kf(y, R)
    # sampling error from the curvature of the log-likelihood in ln Q
    h = 0.05
    ll = [random_walk_kf(y, R, Q=res.Q * np.exp(d)).loglik for d in (-h, 0.0, h)]
    curv = (ll[0] - 2 * ll[1] + ll[2]) / h**2
    assert curv < 0
    se = 1 / np.sqrt(-curv)
    assert se < 0.2
    assert abs(np.log(res.Q / Q)) < 4 * se
    assert ll[1] >= max(ll[0], ll[2])  # it is a maximum


def test_random_walk_matches_pykalman():
    pykalman = pytest.importorskip("pykalman")
    rng = np.random.default_rng(2)
    Q, R = 0.05, 2.0
    y = np.cumsum(rng.normal(0, np.sqrt(Q), 500)) + rng.normal(0, np.sqrt(R), 500)
    y[100:105] = np.nan
    res = random_walk_kf(y, R, Q=Q)
    # diffuse start == pykalman started at x_1 with prior N(y_0, R + Q)
    kf = pykalman.KalmanFilter(transition_matrices=[[1.0]], observation_matrices=[[1.0]],
                               transition_covariance=[[Q]], observation_covariance=[[R]],
                               initial_state_mean=[y[0]], initial_state_covariance=[[R + Q]])
    ym = np.ma.masked_invalid(y[1:])
    m, P = kf.smooth(ym)
    np.testing.assert_allclose(res.smoothed[1:], m[:, 0], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.smoothed_var[1:], P[:, 0, 0], rtol=1e-10)
    assert res.loglik == pytest.approx(kf.loglikelihood(ym), rel=1e-10)


def test_random_walk_bad_input():
    with pytest.raises(ValueError):
        random_walk_kf(np.ones(10), R=0.0)
    with pytest.raises(ValueError):
        random_walk_kf(np.ones(10), R=1.0, Q=-1.0)
    with pytest.raises(ValueError):
        random_walk_kf(np.array([1.0, np.nan]), R=1.0)


# ------------------------------------------------------- position domain (004)


def _flight(rng, T_s=3000.0, sigma_h=0.02, sigma_v=0.01):
    t = np.arange(0, T_s + DT / 2, DT)
    dg = 20 * np.sin(2 * np.pi * t / 700) + 8 * np.cos(2 * np.pi * t / 1300 + 1.0)
    k = 25
    w = 2 * np.pi / rng.uniform(4, 80, k)
    amp = rng.uniform(0.02, 0.15, k)
    ph = rng.uniform(0, 2 * np.pi, k)

    def v(tt):
        return np.sum(-amp[:, None] / w[:, None] * np.cos(w[:, None] * tt + ph[:, None]), 0)

    def h(tt):
        return np.sum(-amp[:, None] / w[:, None] ** 2 * np.sin(w[:, None] * tt + ph[:, None]), 0)

    abar = (v(t) - v(t - DT)) / DT  # aircraft acceleration averaged over each interval
    u = abar + 1e-5 * dg + rng.normal(0, 5e-5 / np.sqrt(DT), t.size)  # f − γ + E (m/s²)
    h_m = 1500.0 + h(t) + rng.normal(0, sigma_h, t.size)
    vu = v(t) + rng.normal(0, sigma_v, t.size)
    return t, dg, u, h_m, vu


def test_position_domain_filter_recovers_known_anomaly():
    rng = np.random.default_rng(3)
    t, dg, u, h_m, vu = _flight(rng)
    res = position_domain_filter(t, h_m, u)
    inner = slice(3000, -3000)
    err = res.dg_mgal - dg
    assert np.sqrt(np.mean(err[inner] ** 2)) < 1.0  # mGal, signal amplitude ~28 mGal
    assert res.R == pytest.approx(0.02**2, rel=0.1)  # R from the high-pass part
    assert np.all(res.dg_std_mgal > 0)
    h_gap = h_m.copy()
    h_gap[12_000:12_050] = np.nan  # a 5 s GNSS outage: prediction only
    resg = position_domain_filter(t, h_gap, u, R=res.R)
    assert np.sqrt(np.mean((resg.dg_mgal - dg)[inner] ** 2)) < 1.0
    assert np.all(np.isfinite(resg.dg_mgal))
    resv = position_domain_filter(t, h_m, u, measurement="velocity", vu_gnss_ms=vu)
    assert np.sqrt(np.mean((resv.dg_mgal - dg)[inner] ** 2)) < 3.0
    assert resv.R == pytest.approx(0.01**2, rel=0.1)


def test_position_domain_filter_bad_input():
    t = np.arange(100) * DT
    with pytest.raises(ValueError):
        position_domain_filter(t, np.zeros(99), np.zeros(100))
    with pytest.raises(ValueError):
        position_domain_filter(t[::-1], np.zeros(100), np.zeros(100))
    with pytest.raises(ValueError):
        position_domain_filter(t, np.zeros(100), np.zeros(100), measurement="velocity")
    with pytest.raises(ValueError):
        position_domain_filter(t, np.zeros(100), np.zeros(100), R=-1.0)
