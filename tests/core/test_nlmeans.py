"""NL-means smoothing of the recognition map: hand-computed weights, limits, denoising."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.nlmeans import RecognitionMap


def _three_points():
    # points on a line at 0, 1, 3 km
    return RecognitionMap([0.0, 1.0, 3.0], [0.0, 0.0, 0.0], max_rho_km=10.0)


def test_hard_hand_computed():
    rm = _three_points()
    probs, labels = rm.smooth(np.array([0, 1, 1]), h_per_km=1.0, rho_km=2.0, mode="hard")
    e1, e2 = np.exp(-1.0), np.exp(-2.0)
    expected = np.array([
        [1.0, e1] / (1.0 + e1),                  # point 0: itself + point 1 (d=1); point 2 at 3 km excluded
        [e1, 1.0 + e2] / (1.0 + e1 + e2),        # point 1: point 0 (d=1), itself, point 2 (d=2)
        [0.0, e2 + 1.0] / (e2 + 1.0),            # point 2: point 1 (d=2), itself
    ])
    np.testing.assert_allclose(probs, expected, rtol=1e-12)
    np.testing.assert_array_equal(labels, [0, 1, 1])


def test_hard_flips_isolated_label():
    rm = RecognitionMap([0.0, 1.0, 2.0], [0.0, 0.0, 0.0], max_rho_km=5.0)
    probs, labels = rm.smooth([1, 0, 1], h_per_km=0.1, rho_km=1.5, mode="hard")
    w = np.exp(-0.1)
    np.testing.assert_allclose(probs[1], [1.0, 2 * w] / (1.0 + 2 * w))
    np.testing.assert_array_equal(labels, [1, 1, 1])


def test_soft_hand_computed_and_differs_from_hard():
    rm = _three_points()
    P = np.array([[0.9, 0.1], [0.45, 0.55], [0.2, 0.8]])
    h, rho = 0.5, 2.5
    probs, labels = rm.smooth(P, h_per_km=h, rho_km=rho, mode="soft")
    D = np.abs(np.subtract.outer([0.0, 1.0, 3.0], [0.0, 1.0, 3.0]))
    Wm = np.where(D <= rho, np.exp(-h * D), 0.0)
    expected = Wm @ P / Wm.sum(1, keepdims=True)
    np.testing.assert_allclose(probs, expected, rtol=1e-12)
    np.testing.assert_array_equal(labels, np.argmax(expected, 1))
    hard, _ = rm.smooth(P, h_per_km=h, rho_km=rho, mode="hard")
    onehot = np.eye(2)[np.argmax(P, 1)]
    np.testing.assert_allclose(hard, Wm @ onehot / Wm.sum(1, keepdims=True), rtol=1e-12)
    assert not np.allclose(hard, probs)


def test_rho_zero_returns_input():
    rng = np.random.default_rng(0)
    e, n = rng.uniform(0, 20, 300), rng.uniform(0, 20, 300)
    rm = RecognitionMap(e, n, max_rho_km=5.0)
    labels = rng.integers(0, 3, 300)
    probs, out = rm.smooth(labels, h_per_km=1.4, rho_km=0.0, mode="hard", n_states=3)
    np.testing.assert_array_equal(out, labels)
    np.testing.assert_array_equal(probs, np.eye(3)[labels])
    P = rng.dirichlet(np.ones(3), size=300)
    probs, out = rm.smooth(P, h_per_km=1.4, rho_km=0.0, mode="soft")
    np.testing.assert_allclose(probs, P, rtol=1e-12)


def test_brute_force_random_map():
    rng = np.random.default_rng(1)
    e, n = rng.uniform(0, 10, 200), rng.uniform(0, 10, 200)
    rm = RecognitionMap(e, n, max_rho_km=4.0)
    P = rng.dirichlet(np.ones(2), size=200)
    h, rho = 0.7, 2.2
    D = np.hypot(np.subtract.outer(e, e), np.subtract.outer(n, n))
    Wm = np.where(D <= rho, np.exp(-h * D), 0.0)
    probs, _ = rm.smooth(P, h_per_km=h, rho_km=rho, mode="soft")
    np.testing.assert_allclose(probs, Wm @ P / Wm.sum(1, keepdims=True), rtol=1e-10)
    # h = 0: plain average over the neighbourhood
    probs0, _ = rm.smooth(P, h_per_km=0.0, rho_km=rho, mode="soft")
    W0 = (D <= rho).astype(float)
    np.testing.assert_allclose(probs0, W0 @ P / W0.sum(1, keepdims=True), rtol=1e-10)


def test_spatially_coherent_map_gets_more_accurate():
    rng = np.random.default_rng(2)
    # 30 lines 2 km apart, points every 1 km; a "mountain" disc of radius 12 km
    e, n = np.meshgrid(np.arange(0.0, 80.0, 1.0), np.arange(0.0, 60.0, 2.0))
    e, n = e.ravel(), n.ravel()
    truth = (np.hypot(e - 40, n - 30) < 12).astype(int)
    flip = rng.random(e.size) < 0.25
    noisy = np.where(flip, 1 - truth, truth)
    rm = RecognitionMap(e, n)
    # (at h = 1.4/km on a 1 km grid the point's own weight is about half the total,
    # too little smoothing for 25 % flips; h = 0.5/km is used here)
    _, smoothed = rm.smooth(noisy, h_per_km=0.5, rho_km=5.0, mode="hard")
    acc_before = np.mean(noisy == truth)
    acc_after = np.mean(smoothed == truth)
    assert acc_before == pytest.approx(0.75, abs=0.02)
    assert acc_after > 0.95
    # soft mode with informative but noisy posteriors also improves
    p1 = np.clip(truth + rng.normal(0, 0.45, e.size), 0.0, 1.0)
    P = np.column_stack([1 - p1, p1])
    _, soft = rm.smooth(P, h_per_km=0.5, rho_km=5.0, mode="soft")
    assert np.mean(soft == truth) > np.mean(np.argmax(P, 1) == truth) + 0.1


def test_validation():
    rm = _three_points()
    with pytest.raises(ValueError, match="h_per_km"):
        rm.smooth([0, 1, 1], h_per_km=-1.0, rho_km=1.0, mode="hard")
    with pytest.raises(ValueError, match="rho_km"):
        rm.smooth([0, 1, 1], h_per_km=1.0, rho_km=11.0, mode="hard")
    with pytest.raises(ValueError, match="rho_km"):
        rm.smooth([0, 1, 1], h_per_km=1.0, rho_km=-0.1, mode="hard")
    with pytest.raises(ValueError, match="shape"):
        rm.smooth([0, 1], h_per_km=1.0, rho_km=1.0, mode="hard")
    with pytest.raises(ValueError, match="mode"):
        rm.smooth([0, 1, 1], h_per_km=1.0, rho_km=1.0, mode="median")
    with pytest.raises(ValueError):
        RecognitionMap([0.0, np.nan], [0.0, 1.0])
    with pytest.raises(ValueError):
        rm.smooth(np.array([[0.5, 0.5], [np.nan, 1.0], [0.0, 1.0]]), 1.0, 1.0, mode="soft")


def test_neighbour_sum_excludes_own_group_and_matches_brute_force():
    rng = np.random.default_rng(3)
    e, n = rng.uniform(0, 10, 60), rng.uniform(0, 10, 60)
    g = rng.integers(0, 4, 60)
    v = rng.standard_normal((60, 2))
    rm = RecognitionMap(e, n, max_rho_km=6.0)
    got = rm.neighbour_sum(v, 0.7, 4.0, groups=g)
    d = np.hypot(e[:, None] - e[None, :], n[:, None] - n[None, :])
    w = np.where((d <= 4.0) & (g[:, None] != g[None, :]), np.exp(-0.7 * d), 0.0)
    np.testing.assert_allclose(got, w @ v, rtol=1e-12, atol=1e-12)
