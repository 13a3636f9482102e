"""Seed-002 two-filter smoother: equal to the generic RTS smoother (both optimal)."""

import numpy as np
import pytest

from app.core.smoother import rts_smooth
from app.core.statespace import build_model, process_covariance
from app.research.two_filter import two_filter_smooth


def test_two_filter_equals_rts_generic_model():
    """TFS and RTS are both optimal: equal on a model with measurement noise (invertible A)."""
    rng = np.random.default_rng(3)
    T = 300
    A = np.array([[1.0, 1.0], [0.0, 0.98]])
    Q = np.diag([1e-3, 1e-4])
    C = np.array([[1.0, 0.0]])
    Rm = np.array([[0.5]])
    x = np.zeros(2)
    z = np.empty(T)
    for k in range(T):
        x = A @ x + rng.multivariate_normal(np.zeros(2), Q)
        z[k] = x[0] + rng.normal(0, np.sqrt(0.5))
    z[100:110] = np.nan
    x0, P0 = np.zeros(2), np.diag([10.0, 1.0])
    u = np.zeros((T, 2))
    u[:, 1] = 0.001
    xs_r, Ps_r, ll_r = rts_smooth(A, Q, C, Rm, z, x0, P0, u=u)
    xs_t, Ps_t, ll_t = two_filter_smooth(A, Q, C, Rm, z, x0, P0, u=u)
    np.testing.assert_allclose(xs_t, xs_r, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(Ps_t, Ps_r, rtol=1e-8, atol=1e-12)
    assert ll_t == ll_r


def test_two_filter_rejects_zero_measurement_noise():
    A, _, C = build_model(1, 0.1)
    with pytest.raises(ValueError, match="positive definite"):
        two_filter_smooth(A, process_covariance(1, 1.0, 1.0), C, np.zeros((1, 1)), np.zeros(10),
                          np.zeros(3), np.eye(3))


def test_seed002_sphere_tfs_equals_rts():
    """Seed 002 buried sphere (R 400 m, top 100 m, Δρ 0.15 g/cm³, 4000 m at 4 m, noise 20 mGal²),
    the seed's state model with the analytic gradient as known input: TFS = RTS."""
    G = 6.674e-11
    M = 4.0 / 3.0 * np.pi * 400.0**3 * 150.0
    D = 500.0
    x = np.arange(0.0, 4000.0 + 1e-9, 4.0)
    dx = x - 2000.0
    g = G * M * D / (dx**2 + D**2) ** 1.5 * 1e5
    assert g.max() == pytest.approx(1.0735, abs=1e-3)  # G M / D² in mGal
    grad = -3.0 * G * M * D * dx / (dx**2 + D**2) ** 2.5 * 1e5
    rng = np.random.default_rng(0)
    z = g + rng.normal(0, np.sqrt(20.0), x.size)
    u = np.zeros((x.size, 1))
    u[1:, 0] = 4.0 * grad[:-1]
    args = (np.array([[1.0]]), np.array([[1e-4]]), np.array([[1.0]]), np.array([[20.0]]), z,
            np.array([z[0]]), np.array([[20.0]]))
    xt, Pt, _ = two_filter_smooth(*args, u=u)
    xr, Pr, _ = rts_smooth(*args, u=u)
    np.testing.assert_allclose(xt, xr, rtol=0, atol=1e-6)
    np.testing.assert_allclose(Pt, Pr, rtol=1e-6)
    # the smoother is near the one-offset floor sqrt(20/1001) = 0.14 mGal, far below the noise
    assert np.sqrt(np.mean((xr[:, 0] - g) ** 2)) < 0.5
