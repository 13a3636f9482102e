"""Seed-003 scalar random-walk Kalman filter: maximum likelihood, a peer library, bad input."""

import numpy as np
import pytest

from app.research.random_walk_kf import random_walk_kf


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
