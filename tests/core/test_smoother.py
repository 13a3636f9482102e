"""Tests of the seed-000 Kalman smoother and the generic smoothers.

Independent references: pykalman (peer library), the generic numpy RTS and the
model itself (simulated data with known truth).  The two-filter/RTS identity (seed 002)
is tested in tests/research/test_two_filter.py.
"""

import numpy as np
import pytest

from app.core.smoother import (
    SmootherResult,
    kalman_loglik,
    kalman_smooth,
    level_spread_std_mgal,
    mixture_std_mgal,
    rts_smooth,
    smooth_many,
)
from app.core.statespace import build_model, process_covariance


def _simulate(rng, T, m, Q, R, dt):
    """Draw (z, δg) from the model with per-epoch Q, R (arrays of length T)."""
    q = rng.normal(size=T) * np.sqrt(Q)
    dg = q.copy()
    for _ in range(m):
        dg = np.cumsum(dg)
    dg += 50.0
    r = rng.normal(size=T + 1) * np.sqrt(np.r_[R[0], R])
    z = dg - 1000.0 * (r[1:] - r[:-1]) / dt
    return z, dg


def _prior(m, R0, mean=0.0, var=1e4):
    n = m + 2
    x0 = np.zeros(n)
    x0[:m] = mean
    P0 = np.diag([var] * m + [R0, R0])
    return x0, P0


@pytest.mark.parametrize("m", [1, 2, 3])
def test_matches_pykalman_stationary(m):
    pykalman = pytest.importorskip("pykalman")
    # Well-conditioned parameters: the peer (pinv-based, no Joseph form) loses up to
    # 1e-4 relative accuracy in the variances at dt = 0.1 s, R = 2 (see the exact-arithmetic
    # test below for that regime).
    rng = np.random.default_rng(10 + m)
    dt, T, Q, R = 1.0, 400, 1.0, 0.01
    z, _ = _simulate(rng, T, m, np.full(T, Q), np.full(T, R), dt)
    z[57] = np.nan
    A, _, C = build_model(m, dt)
    x0, P0 = _prior(m, R, mean=float(np.nanmean(z[:50])))
    kf = pykalman.KalmanFilter(
        transition_matrices=A, observation_matrices=C,
        transition_covariance=process_covariance(m, Q, R), observation_covariance=np.zeros((1, 1)),
        initial_state_mean=x0, initial_state_covariance=P0)
    zm = np.ma.masked_invalid(z)
    means, covs = kf.smooth(zm)
    fmeans, _ = kf.filter(zm)
    for method in ("bf", "rts"):
        res = kalman_smooth(z, Q, R, dt, m=m, method=method, x0=x0, P0=P0)
        np.testing.assert_allclose(res.dg_mgal, means[:, 0], rtol=1e-8, atol=1e-8 * np.abs(means[:, 0]).max())
        np.testing.assert_allclose(res.dg_std_mgal ** 2, covs[:, 0, 0], rtol=1e-8)
        np.testing.assert_allclose(res.filtered_mgal, fmeans[:, 0], rtol=1e-8, atol=1e-8 * np.abs(means[:, 0]).max())
    assert kalman_loglik(z, Q, R, dt, m=m, x0=x0, P0=P0) == pytest.approx(kf.loglikelihood(zm), rel=1e-9)


def test_bf_equals_rts_time_varying_with_gaps():
    rng = np.random.default_rng(1)
    dt, T, m = 0.1, 6000, 2
    k = np.arange(T)
    Q = np.where((k // 700) % 2 == 0, 1e-5, 1e-2)
    R = np.where((k // 1100) % 3 == 0, 4.0, 1.0)
    z, _ = _simulate(rng, T, m, Q, R, dt)
    z[1000:1040] = np.nan
    z[5] = np.nan
    x0, P0 = _prior(m, R[0], mean=float(np.nanmean(z[:50])))
    bf = kalman_smooth(z, Q, R, dt, m=m, method="bf", x0=x0, P0=P0)
    rts = kalman_smooth(z, Q, R, dt, m=m, method="rts", x0=x0, P0=P0)
    scale = np.abs(rts.dg_mgal).max()
    np.testing.assert_allclose(bf.dg_mgal, rts.dg_mgal, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(bf.dg_std_mgal, rts.dg_std_mgal, rtol=1e-8)
    np.testing.assert_array_equal(bf.filtered_mgal, rts.filtered_mgal)
    assert bf.loglik == rts.loglik
    # and both equal the generic numpy RTS on the same model and prior
    A, _, C = build_model(m, dt)
    W = np.array([process_covariance(m, q, r) for q, r in zip(Q[:800], R[:800])])
    x0, P0 = _prior(m, R[0], mean=float(np.nanmean(z[:50])))
    xs, Ps, ll = rts_smooth(A, W, C, np.zeros((1, 1)), z[:800], x0, P0)
    ref = kalman_smooth(z[:800], Q[:800], R[:800], dt, m=m, x0=x0, P0=P0)
    np.testing.assert_allclose(ref.dg_mgal, xs[:, 0], rtol=0, atol=1e-8 * np.abs(xs[:, 0]).max())
    np.testing.assert_allclose(ref.dg_std_mgal ** 2, Ps[:, 0, 0], rtol=1e-6)  # peer in unscaled units
    assert ref.loglik == pytest.approx(ll, rel=1e-10)


def _exact_rts(A, c, z, Q, Rs, m, x0, P0, prec=50):
    """RTS smoother in 50-digit decimal arithmetic (model with C = c, W = diag(Q at 0, Rs at m))."""
    from decimal import Decimal, getcontext

    getcontext().prec = prec
    D = lambda v: Decimal(float(v))  # noqa: E731
    n = len(x0)

    def mm(a, b):
        return [[sum((a[i][k] * b[k][j] for k in range(len(b))), Decimal(0)) for j in range(len(b[0]))]
                for i in range(len(a))]

    def tr(a):
        return [list(r) for r in zip(*a)]

    def lin(a, b, s=1):
        return [[a[i][j] + s * b[i][j] for j in range(len(a[0]))] for i in range(len(a))]

    def inv(a):
        M = [row[:] + [Decimal(int(i == j)) for j in range(n)] for i, row in enumerate(a)]
        for col in range(n):
            p = max(range(col, n), key=lambda r: abs(M[r][col]))
            M[col], M[p] = M[p], M[col]
            pv = M[col][col]
            M[col] = [v / pv for v in M[col]]
            for r in range(n):
                if r != col:
                    f = M[r][col]
                    M[r] = [M[r][j] - f * M[col][j] for j in range(2 * n)]
        return [row[n:] for row in M]

    Am = [[D(v) for v in row] for row in A]
    Cm = [[D(v) for v in c]]
    x = [[D(v)] for v in x0]
    P = [[D(v) for v in row] for row in P0]
    xf, Pf, xp, Pp = [], [], [], []
    for k in range(len(z)):
        if k > 0:
            x = mm(Am, x)
            P = mm(mm(Am, P), tr(Am))
            P[0][0] += D(Q[k])
            P[m][m] += D(Rs[k])
        xp.append(x)
        Pp.append(P)
        if np.isfinite(z[k]):
            S = mm(mm(Cm, P), tr(Cm))[0][0]
            K = [[v[0] / S] for v in mm(P, tr(Cm))]
            nu = D(z[k]) - mm(Cm, x)[0][0]
            x = [[x[i][0] + K[i][0] * nu] for i in range(n)]
            P = lin(P, [[K[i][0] * S * K[j][0] for j in range(n)] for i in range(n)], -1)
        xf.append(x)
        Pf.append(P)
    xs, Ps = xf[-1], Pf[-1]
    mean, var = [xs[0][0]], [Ps[0][0]]
    for k in range(len(z) - 2, -1, -1):
        G = mm(mm(Pf[k], tr(Am)), inv(Pp[k + 1]))
        xs = lin(xf[k], mm(G, lin(xs, xp[k + 1], -1)))
        Ps = lin(Pf[k], mm(mm(G, lin(Ps, Pp[k + 1], -1)), tr(G)))
        mean.append(xs[0][0])
        var.append(Ps[0][0])
    return np.array([float(v) for v in mean[::-1]]), np.array([float(v) for v in var[::-1]])


@pytest.mark.parametrize("m", [1, 2, 3])
def test_exact_arithmetic_reference(m):
    """Both smoothers against a 50-digit RTS on a realistic, time-varying line start
    (dt = 0.1 s, R = 1–4 (cm/s)², default diffuse-ish prior, a gap)."""
    rng = np.random.default_rng(100 + m)
    dt, T = 0.1, 160
    k = np.arange(T)
    Q = np.where(k < 80, 1e-4, 1e-2)
    R = np.where(k % 50 < 25, 1.0, 4.0)
    z, _ = _simulate(rng, T, m, Q, R, dt)
    z[30:33] = np.nan
    c = 1000.0 / dt
    A, _, C = build_model(m, dt)
    x0 = np.zeros(m + 2)
    x0[:m] = np.nanmean(z)
    P0 = np.diag([1e6] * m + [R[0], R[0]])
    P0s = P0.copy()
    P0s[m:, m:] *= c * c
    mean, var = _exact_rts(A, C[0] / np.r_[np.ones(m), c, c], z, Q, R * c * c, m, x0, P0s)
    for method, tol in (("bf", 1e-8), ("rts", 1e-8)):
        res = kalman_smooth(z, Q, R, dt, m=m, method=method, x0=x0, P0=P0)
        np.testing.assert_allclose(res.dg_mgal, mean, rtol=0, atol=1e-9 * np.abs(mean).max())
        np.testing.assert_allclose(res.dg_std_mgal, np.sqrt(var), rtol=tol)


def test_posterior_std_calibrated_on_simulation():
    """|error| < 2σ for 93–97 % of epochs on data drawn from the model (switching Q, R)."""
    rng = np.random.default_rng(2024)
    dt, m, T, L = 0.1, 2, 20000, 10
    zs, truth, Qs, Rs = [], [], [], []
    for _ in range(L):
        seg_q = rng.integers(0, 2, size=T // 2000 + 1)
        seg_r = rng.integers(0, 2, size=T // 3000 + 1)
        k = np.arange(T)
        Q = np.array([1e-2, 1.0])[seg_q[k // 2000]]
        R = np.array([1.0, 4.0])[seg_r[k // 3000]]
        z, dg = _simulate(rng, T, m, Q, R, dt)
        zs.append(z)
        truth.append(dg)
        Qs.append(Q)
        Rs.append(R)
    res = smooth_many(zs, Qs, Rs, dt, m=m)
    assert len(res) == L and all(isinstance(r, SmootherResult) for r in res)
    err = np.concatenate([r.dg_mgal - t for r, t in zip(res, truth)])
    sd = np.concatenate([r.dg_std_mgal for r in res])
    frac = np.mean(np.abs(err) < 2.0 * sd)
    assert 0.93 <= frac <= 0.97, frac
    # normalised errors have unit variance
    assert np.sqrt(np.mean((err / sd) ** 2)) == pytest.approx(1.0, abs=0.1)


def test_no_negative_variance_extreme_ratios_200k():
    rng = np.random.default_rng(7)
    dt, m, T = 0.1, 2, 200_000
    k = np.arange(T)
    Q = np.array([1e-9, 1e-6, 1e-2, 10.0])[(k // 5000) % 4]
    R = np.array([0.01, 100.0, 1.0])[(k // 7000) % 3]
    z, dg = _simulate(rng, T, m, Q, R, dt)
    z[50_000:50_500] = np.nan
    bf = kalman_smooth(z, Q, R, dt, m=m, method="bf")
    assert np.all(np.isfinite(bf.dg_std_mgal)) and np.all(bf.dg_std_mgal > 0)
    rts = kalman_smooth(z, Q, R, dt, m=m, method="rts")
    # Posterior std spans 0.3 .. 1e3 mGal against a measurement noise of up to 1.4e5 mGal.
    np.testing.assert_allclose(bf.dg_std_mgal, rts.dg_std_mgal, rtol=1e-7)
    e = (bf.dg_mgal - dg) / bf.dg_std_mgal
    assert np.sqrt(np.mean(e**2)) == pytest.approx(1.0, abs=0.15)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(Q_mgal2=0.0), "Q_mgal2"),
        (dict(Q_mgal2=-1.0), "Q_mgal2"),
        (dict(R_cm2s2=0.0), "R_cm2s2"),
        (dict(R_cm2s2=np.r_[np.ones(19), -1.0]), "R_cm2s2"),
        (dict(Q_mgal2=np.ones(19)), "length"),
        (dict(R_cm2s2=np.full(20, np.nan)), "R_cm2s2"),
        (dict(m=0), "m"),
        (dict(m=4), "m"),
        (dict(method="ukf"), "method"),
        (dict(dt_s=0.0), "dt_s"),
        (dict(z_mgal=np.ones(3)), "too short"),
        (dict(z_mgal=np.r_[np.ones(3), np.full(17, np.nan)]), "too short"),
        (dict(z_mgal=np.ones((4, 5))), "1-D"),
    ],
)
def test_bad_input(kwargs, match):
    args = dict(z_mgal=np.ones(20), Q_mgal2=1e-3, R_cm2s2=1.0, dt_s=0.1, m=2, method="bf")
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        kalman_smooth(**args)


def test_smooth_many_length_mismatch():
    with pytest.raises(ValueError):
        smooth_many([np.ones(20), np.ones(30)], [1e-3], 1.0, 0.1)


def test_two_component_anomaly_matches_pykalman():
    """δg = s + u with ∇²s = q (Q) and a random walk ∇u = w (Q_rw, switching along the
    line): the numba BF/RTS equal pykalman's smoother on the same 4-state model
    (δg, slope of s, ρ_k, ρ_{k−1}), means, variances and log-likelihood."""
    pykalman = pytest.importorskip("pykalman")
    rng = np.random.default_rng(5)
    dt, T, Q, R = 1.0, 400, 0.01, 0.01
    c = 1000.0 / dt
    q_rw = np.where((np.arange(T) // 100) % 2 == 1, 0.5, 0.0)       # rough stretches: a random walk
    s = np.cumsum(np.cumsum(rng.normal(size=T) * np.sqrt(Q)))
    u = np.cumsum(rng.normal(size=T) * np.sqrt(q_rw))
    r = rng.normal(size=T + 1) * np.sqrt(R)
    z = 30.0 + s + u - c * (r[1:] - r[:-1])
    z[123] = np.nan
    A = np.array([[1.0, 1.0, 0, 0], [0, 1.0, 0, 0], [0, 0, 0, 0], [0, 0, 1.0, 0]])
    Cm = np.array([[1.0, 0, -1.0, 1.0]])
    W = np.zeros((T - 1, 4, 4))
    W[:, :2, :2] = Q
    W[:, 0, 0] += q_rw[1:]
    W[:, 2, 2] = R * c * c
    x_int = np.array([float(np.nanmean(z[:20])), 0.0, 0.0, 0.0])
    P_int = np.diag([1e4, 1.0, R * c * c, R * c * c])
    kf = pykalman.KalmanFilter(transition_matrices=A, observation_matrices=Cm, transition_covariance=W,
                               observation_covariance=np.zeros((1, 1)), initial_state_mean=x_int,
                               initial_state_covariance=P_int)
    zm = np.ma.masked_invalid(z)
    means, covs = kf.smooth(zm)
    # the same prior in the model's basis (δg_k, δg_{k−1}, r_k, r_{k−1}): internal = Tm · model
    Tm = np.array([[1.0, 0, 0, 0], [1.0, -1.0, 0, 0], [0, 0, c, 0], [0, 0, 0, c]])
    Ti = np.linalg.inv(Tm)
    x0, P0 = Ti @ x_int, Ti @ P_int @ Ti.T
    for method in ("bf", "rts"):
        res = kalman_smooth(z, Q, R, dt, m=2, method=method, x0=x0, P0=P0, Q_rw_mgal2=q_rw)
        np.testing.assert_allclose(res.dg_mgal, means[:, 0], rtol=1e-7, atol=1e-7 * np.abs(means[:, 0]).max())
        np.testing.assert_allclose(res.dg_std_mgal ** 2, covs[:, 0, 0], rtol=1e-6)
    ll = kalman_loglik(z, Q, R, dt, m=2, x0=x0, P0=P0, Q_rw_mgal2=q_rw)
    assert ll == pytest.approx(kf.loglikelihood(zm), rel=1e-8)
    # no random-walk part: exactly the plain m = 2 model
    a = kalman_smooth(z, Q, R, dt, m=2, x0=x0, P0=P0, Q_rw_mgal2=0.0)
    b = kalman_smooth(z, Q, R, dt, m=2, x0=x0, P0=P0)
    np.testing.assert_array_equal(a.dg_mgal, b.dg_mgal)
    with pytest.raises(ValueError, match="m ≥ 2"):
        kalman_smooth(z, Q, R, dt, m=1, Q_rw_mgal2=q_rw)
    with pytest.raises(ValueError, match="Q_rw_mgal2"):
        kalman_smooth(z, Q, R, dt, m=2, Q_rw_mgal2=-q_rw - 1)


def test_mixture_std_matches_sampled_mixture():
    """The RMS deviation about a centre of a two-component Gaussian mixture, per epoch, against
    200 000 draws from that mixture (independent of the formula); bad shapes are refused."""
    rng = np.random.default_rng(5)
    mu = np.array([[0.0, 3.0, -2.0], [4.0, 3.0, 5.0]])
    sd = np.array([[1.0, 2.0, 0.5], [3.0, 0.5, 1.0]])
    w = np.array([[0.3, 0.9, 0.5], [0.7, 0.1, 0.5]])
    c = np.array([1.0, 3.0, 0.0])
    n = 200_000
    for j in range(3):
        k = rng.random(n) < w[1, j]
        x = np.where(k, rng.normal(mu[1, j], sd[1, j], n), rng.normal(mu[0, j], sd[0, j], n))
        assert mixture_std_mgal(c, mu, sd, w)[j] == pytest.approx(np.sqrt(np.mean((x - c[j]) ** 2)), rel=0.01)
    # one certain component: its own std and offset
    one = mixture_std_mgal(c, mu, sd, np.array([[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]))
    assert np.allclose(one, np.sqrt(sd[0] ** 2 + (mu[0] - c) ** 2))
    with pytest.raises(ValueError, match="shapes"):
        mixture_std_mgal(c[:2], mu, sd, w)
    with pytest.raises(ValueError, match="sum to zero"):
        mixture_std_mgal(c, mu, sd, np.zeros_like(w))


def test_level_spread_std_covers_a_level_a_decade_off():
    """Simulation with known truth (the model's own anomaly, white velocity noise): smoothed
    at a level 10x too low, the posterior std covers the error on about half the epochs; with
    the spread of the estimates at Q/10 and 10 Q added it covers ≥ 85 %, and at the right
    level it widens the std only a little (coverage ≤ 0.99).  The mean is the smoother's at Q;
    factor 1 is the plain smoother."""
    dt, T, Q_true, R = 0.1, 20000, 1e-7, 1.0
    cov = {"low": [[], []], "right": [[], []]}
    for seed in range(3):
        z, dg = _simulate(np.random.default_rng(seed), T, 2, np.full(T, Q_true), np.full(T, R), dt)
        for key, Q in (("low", Q_true / 10), ("right", Q_true)):
            plain = kalman_smooth(z, np.full(T, Q), np.full(T, R), dt, m=2)
            wide = level_spread_std_mgal(z, np.full(T, Q), np.full(T, R), dt, 10.0, m=2)
            np.testing.assert_array_equal(wide.dg_mgal, plain.dg_mgal)
            inner = slice(1000, T - 1000)
            e = np.abs(plain.dg_mgal - dg)[inner]
            cov[key][0].append(np.mean(e < 2 * plain.dg_std_mgal[inner]))
            cov[key][1].append(np.mean(e < 2 * wide.dg_std_mgal[inner]))
    assert np.mean(cov["low"][0]) < 0.7 and np.mean(cov["low"][1]) > 0.85
    assert 0.9 < np.mean(cov["right"][0]) and np.mean(cov["right"][1]) < 0.99
    same = level_spread_std_mgal(z, np.full(T, Q_true), np.full(T, R), dt, 1.0, m=2)
    np.testing.assert_array_equal(same.dg_std_mgal, kalman_smooth(z, np.full(T, Q_true), np.full(T, R), dt,
                                                                   m=2).dg_std_mgal)
    with pytest.raises(ValueError, match="factor"):
        level_spread_std_mgal(z, np.full(T, Q_true), np.full(T, R), dt, 0.5)
