"""Tests of the seed-000 state-space matrices against the model equations."""

import numpy as np
import pytest

from app.core.statespace import ar_coefficients, build_model, process_covariance


@pytest.mark.parametrize("m", [1, 2, 3])
def test_state_recursion_reproduces_model(m):
    """Simulate ∇^m δg = q and z = δg − 1000 ∇r/Δt directly, then check y_k = A y_{k−1} + B e_k
    and z_k = C y_k."""
    rng = np.random.default_rng(m)
    dt = 0.1
    T = 50
    q = rng.normal(size=T)
    r = rng.normal(size=T + 1)  # r_{-1} .. r_{T-1}
    dg = q.copy()
    for _ in range(m):
        dg = np.cumsum(dg)  # δg_k with δg_{<0} = 0, so ∇^m δg = q exactly
    z = dg - 1000.0 * (r[1:] - r[:-1]) / dt
    A, B, C = build_model(m, dt)
    n = m + 2
    assert A.shape == (n, n) and B.shape == (n, 2) and C.shape == (1, n)

    def y(k):
        past = [dg[k - j] if k - j >= 0 else 0.0 for j in range(m)]
        return np.array(past + [r[k + 1], r[k]])

    for k in range(1, T):
        np.testing.assert_allclose(A @ y(k - 1) + B @ np.array([q[k], r[k + 1]]), y(k), atol=1e-9)
        np.testing.assert_allclose(C @ y(k), [z[k]], rtol=1e-12, atol=1e-9)


def test_binomial_coefficients_and_singularity():
    np.testing.assert_array_equal(ar_coefficients(1), [1.0])
    np.testing.assert_array_equal(ar_coefficients(2), [2.0, -1.0])
    np.testing.assert_array_equal(ar_coefficients(3), [3.0, -3.0, 1.0])
    for m in (1, 2, 3):
        A, _, C = build_model(m, 0.1)
        assert np.linalg.matrix_rank(A) < m + 2
        np.testing.assert_allclose(C[0, m:], [-10000.0, 10000.0])


def test_process_covariance_is_B_diag_Bt():
    for m in (1, 2, 3):
        _, B, _ = build_model(m, 0.2)
        np.testing.assert_array_equal(process_covariance(m, 0.3, 2.0), B @ np.diag([0.3, 2.0]) @ B.T)


@pytest.mark.parametrize("m", [0, 4, -1, 2.0, "2", True])
def test_bad_m(m):
    with pytest.raises(ValueError):
        build_model(m, 0.1)


@pytest.mark.parametrize("dt", [0.0, -0.1, np.nan, np.inf])
def test_bad_dt(dt):
    with pytest.raises(ValueError):
        build_model(2, dt)
