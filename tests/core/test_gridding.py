"""Tests of the gridding estimators against simulated fields with known covariance."""

import numpy as np
import pytest

from app.core.gridding import (
    Collocation,
    Spline,
    block_thin,
    empirical_covariance,
    fit_gm2,
    gm2_covariance,
    line_spacing_km,
)

VAR, LEN = 25.0, 3.0          # mGal², km of the simulated field


def _simulate(seed, noise=1.0, spacing=2.0, step=0.25, nlines=8, length=24.0, grid_step=1.0):
    """GM2 random field sampled jointly on lines and on grid nodes (exact, by Cholesky)."""
    rng = np.random.default_rng(seed)
    e_l, n_l, lab = [], [], []
    for k in range(nlines):
        x = np.arange(0.0, length + 1e-9, step)
        e_l.append(x)
        n_l.append(np.full_like(x, k * spacing))
        lab.append(np.full(x.size, f"M{k}"))
    for j in range(3):  # ties
        y = np.arange(0.0, (nlines - 1) * spacing + 1e-9, step)
        e_l.append(np.full_like(y, 2.0 + j * 10.0))
        n_l.append(y)
        lab.append(np.full(y.size, f"T{j}"))
    e = np.concatenate(e_l)
    n = np.concatenate(n_l)
    lab = np.concatenate(lab)
    ge = np.arange(0.0, length + 1e-9, grid_step)
    gn = np.arange(0.0, (nlines - 1) * spacing + 1e-9, grid_step)
    GE, GN = np.meshgrid(ge, gn)
    xe = np.concatenate([e, GE.ravel()])
    xn = np.concatenate([n, GN.ravel()])
    C = gm2_covariance(np.hypot(xe[:, None] - xe[None], xn[:, None] - xn[None]), VAR, LEN)
    Lc = np.linalg.cholesky(C + 1e-8 * np.eye(xe.size))
    f = Lc @ rng.standard_normal(xe.size) + 100.0 + 0.4 * xe - 0.2 * xn
    obs = f[:e.size] + noise * rng.standard_normal(e.size)
    truth = f[e.size:].reshape(GE.shape)
    return e, n, obs, lab, ge, gn, truth


def test_gm2_covariance_shape_and_fit_recovers_parameters():
    d = np.linspace(0, 20, 50)
    c = gm2_covariance(d, 4.0, 2.0)
    assert c[0] == pytest.approx(4.0)
    # half-value distance of (1+x)e^-x is x = 1.678...
    assert gm2_covariance(1.6783469900166608 * 2.0, 4.0, 2.0) == pytest.approx(2.0, rel=1e-9)
    var, length, off = fit_gm2(d[1:], c[1:], np.ones(49), 0.1, 50.0)
    assert var == pytest.approx(4.0, rel=1e-4) and length == pytest.approx(2.0, rel=1e-4)
    assert off == pytest.approx(0.0, abs=1e-6)
    # a negative offset (bias of the mean removal) is separated from the model
    var, length, off = fit_gm2(d[1:], c[1:] - 0.7, np.ones(49), 0.1, 50.0)
    assert (var, length, off) == pytest.approx((4.0, 2.0, -0.7), rel=1e-4)


def test_block_thin_means_and_white_error_reduction():
    e = np.array([0.1, 0.2, 0.3, 1.1, 1.2])
    n = np.zeros(5)
    v = np.array([1.0, 2.0, 3.0, 10.0, 20.0])
    s = np.full(5, 2.0)
    te, tn, tv, ts, cnt = block_thin(e, n, v, s, thin_km=1.0)
    np.testing.assert_allclose(tv, [2.0, 15.0])
    np.testing.assert_allclose(ts, [2.0 / np.sqrt(3), 2.0 / np.sqrt(2)])
    # fully correlated errors (correlation length ≫ block): no reduction
    *_, ts2, _ = block_thin(e, n, v, s, thin_km=1.0, error_corr_km=100.0, step_km=0.1)
    np.testing.assert_allclose(ts2, [2.0, 2.0])


def test_collocation_on_simulated_field_accuracy_and_calibration():
    errs, stds, rms_rel = [], [], []
    est = []
    for seed in range(3):
        # 14 lines 1.5 km apart, 40 km long, 1 mGal white noise every 0.5 km
        e, n, obs, lab, ge, gn, truth = _simulate(seed, spacing=1.5, step=0.5, nlines=14, length=40.0)
        col = Collocation(thin_km=0.5, error_corr_km=0.0).fit(e, n, obs, np.full(e.size, 1.0), line=lab)
        est.append((col.variance_mgal2_, col.length_km_, col.nugget_mgal2_))
        x, y, dg, sd = col.grid(region=(0, 40, 0, 19.5), spacing_km=1.0)
        np.testing.assert_allclose(x, ge)
        np.testing.assert_allclose(y, gn)
        m = np.isfinite(dg)
        assert m.mean() > 0.9
        err = dg[m] - truth[m]
        errs.append(err)
        stds.append(sd[m])
        rms_rel.append(np.sqrt(np.mean(err ** 2)) / np.sqrt(VAR))
    err = np.concatenate(errs)
    std = np.concatenate(stds)
    frac = np.mean(np.abs(err) < 2 * std)
    print("estimates", est, "rms/sigma", rms_rel, "frac2sigma", frac)
    assert np.mean(rms_rel) < 0.2             # lines 1.5 km apart, L = 3 km
    assert 0.88 <= frac <= 0.99               # ≈ 95 %
    # the error std predicted matches the realised RMS within 30 %
    assert np.sqrt(np.mean(err ** 2)) == pytest.approx(np.sqrt(np.mean(std ** 2)), rel=0.3)
    v, L, _ = np.median(np.array(est), axis=0)
    assert 0.4 * VAR < v < 2.5 * VAR
    assert 0.5 * LEN < L < 2.0 * LEN


def test_local_collocation_equals_global_dense_solve():
    rng = np.random.default_rng(7)
    e = rng.uniform(0, 10, 150)
    n = rng.uniform(0, 8, 150)
    v = np.sin(e / 2) * 5 + n + rng.normal(0, 0.5, e.size)
    s = rng.uniform(0.2, 1.0, e.size)
    var, L, nug = 9.0, 2.0, 0.1
    pe = rng.uniform(-1, 11, 40)
    pn = rng.uniform(-1, 9, 40)
    col = Collocation(var, L, nug, thin_km=1e-4, max_points=10_000, search_radius_km=1e3,
                      block_km=3.0, mask_km=100.0).fit(e, n, v, s)
    got, got_s = col.predict(pe, pn, return_std=True)
    # dense global LSC written out independently
    G = np.column_stack([np.ones_like(e), e - e.mean(), n - n.mean()])
    beta = np.linalg.lstsq(G, v, rcond=None)[0]
    r = v - G @ beta
    def cov(d):
        return var * (1 + d / L) * np.exp(-d / L)

    K = cov(np.hypot(e[:, None] - e, n[:, None] - n)) + np.diag(s ** 2 + nug)
    k = cov(np.hypot(pe[:, None] - e, pn[:, None] - n))
    want = k @ np.linalg.solve(K, r) + np.column_stack([np.ones_like(pe), pe - e.mean(), pn - n.mean()]) @ beta
    want_s = np.sqrt(var - np.einsum("ij,ji->i", k, np.linalg.solve(K, k.T)))
    np.testing.assert_allclose(got, want, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(got_s, want_s, rtol=1e-6, atol=1e-7)
    # the default local neighbourhood (nearest 60 points) stays close to the global solution
    loc = Collocation(var, L, nug, thin_km=1e-4, max_points=60, block_km=2.0,
                      mask_km=100.0).fit(e, n, v, s)
    lv = loc.predict(pe, pn)
    assert np.max(np.abs(lv - want)) < 0.1 * np.sqrt(var)


def test_mask_and_errors():
    e, n, obs, lab, *_ = _simulate(0, nlines=4, length=10.0)
    col = Collocation(thin_km=0.5).fit(e, n, obs, 1.0, line=lab)
    assert col.line_spacing_km_ == pytest.approx(2.0, rel=0.05)
    assert col.mask_distance_km_ == pytest.approx(3.0, rel=0.05)
    summ = col.summary()
    assert summ["length_km"] == col.length_km_ and summ["mask_km"] == col.mask_distance_km_
    x, y, dg, sd = col.grid(region=(-10, 20, 0, 6), spacing_km=1.0)
    far = x < -3.1
    assert np.all(np.isnan(dg[:, far])) and np.all(np.isnan(sd[:, far]))
    assert np.all(np.isfinite(dg[:, (x >= 0) & (x <= 10)]))
    with pytest.raises(ValueError, match="empty grid area"):
        col.grid(region=(100, 110, 100, 110))
    # a per-call mask distance
    x2, _, dg2, _ = col.grid(region=(-10, 20, 0, 6), spacing_km=1.0, mask_km=8.0)
    assert np.all(np.isfinite(dg2[:, x2 >= -7.9])) and np.all(np.isnan(dg2[:, x2 < -8.1]))
    with pytest.raises(ValueError, match="no finite data"):
        Collocation().fit([], [], [])
    with pytest.raises(ValueError, match="no finite data"):
        Spline().fit([np.nan], [1.0], [1.0])
    with pytest.raises(ValueError, match="fit"):
        Collocation().grid()


def test_spline_reproduces_smooth_field():
    e, n, obs, lab, ge, gn, _ = _simulate(0, noise=0.0, nlines=6)
    def f(x, y):
        return 3 * np.sin(x / 4.0) + 0.5 * y

    obs = f(e, n)
    sp = Spline(thin_km=0.25).fit(e, n, obs, 0.1, line=lab)
    x, y, dg, sd = sp.grid(spacing_km=1.0)
    X, Y = np.meshgrid(x, y)
    m = np.isfinite(dg)
    assert m.mean() > 0.8
    assert np.sqrt(np.mean((dg[m] - f(X, Y)[m]) ** 2)) < 0.1


def test_line_spacing_counts_repeat_passes_as_one_track():
    """Passes of one track (a repeat line flown 4x, 20 m apart) are one line for the spacing:
    three lines 2 km apart plus the repeat track 1 km off the last one give the median of
    the points' nearest-other-track distances, computed here by hand."""
    x = np.linspace(0, 20, 201)
    mains = [(x, np.full(x.size, y)) for y in (0.0, 2.0, 4.0)]
    passes = [(x, np.full(x.size, 5.0 + 0.02 * k)) for k in range(4)]
    e = np.concatenate([a for a, _ in mains + passes])
    n = np.concatenate([b for _, b in mains + passes])
    lab = np.repeat(["M1", "M2", "M3", "R-1", "R-2", "R-3", "R-4"], x.size)
    # per sampled point: M1 2, M2 2, M3 1 (to the track), each pass 1 (to M3, 1 + 0.02k):
    # 4 of 7 equal-length lines sit ~1 km from another track, so the median is ~1 km
    assert line_spacing_km(e, n, lab) == pytest.approx(1.0, abs=0.07)
    # without the passes merged every pass point would have a neighbour 20 m away
    assert line_spacing_km(e, n, lab, coincident_km=0.001) == pytest.approx(0.02, abs=1e-6)
    # a single track flown four times has no spacing (as a single line)
    rep = np.isin(lab, ["R-1", "R-2", "R-3", "R-4"])
    assert np.isnan(line_spacing_km(e[rep], n[rep], lab[rep]))
    # crossing lines are not merged: a tie across the three mains keeps the 2 km spacing
    et = np.concatenate([e[:3 * x.size], np.full(41, 10.0)])
    nt = np.concatenate([n[:3 * x.size], np.linspace(0, 4, 41)])
    lt = np.concatenate([lab[:3 * x.size], np.full(41, "T1")])
    assert line_spacing_km(et, nt, lt) == pytest.approx(2.0, abs=0.01)


def test_line_spacing_and_empirical_covariance():
    e = np.concatenate([np.linspace(0, 10, 101)] * 3)
    n = np.repeat([0.0, 1.5, 3.0], 101)
    lab = np.repeat([0, 1, 2], 101)
    assert line_spacing_km(e, n, lab) == pytest.approx(1.5)
    assert np.isnan(line_spacing_km(e[:101], n[:101], lab[:101]))
    # white residuals: zero covariance at every lag, c0 = variance
    r = np.random.default_rng(0).normal(0, 2.0, e.size)
    lag, cov, cnt, c0 = empirical_covariance(e, n, r, 5.0)
    assert c0 == pytest.approx(4.0, rel=0.2)
    assert np.sum(cnt * cov) / np.sum(cnt) == pytest.approx(0.0, abs=0.2)


def test_collocation_with_along_line_correlated_errors_is_not_overconfident():
    """10 Hz-like data (50 m) with 1 mGal errors correlated over ~1 km on a
    deterministic field (a sum of Gaussian bumps, not the model's covariance)."""
    from scipy.ndimage import uniform_filter1d

    rng = np.random.default_rng(0)
    ce, cn = rng.uniform(-5, 35, 60), rng.uniform(-5, 25, 60)
    w, a = rng.uniform(2, 8, 60), rng.normal(0, 15, 60)

    def truth(x, y):
        return np.sum(a * np.exp(-((x[..., None] - ce) ** 2 + (y[..., None] - cn) ** 2) / (2 * w ** 2)), axis=-1)

    x = np.arange(0, 30.0001, 0.05)
    e = np.concatenate([x] * 21)
    n = np.repeat(np.arange(21.0), x.size)
    lab = np.repeat(np.arange(21), x.size)
    noise = uniform_filter1d(rng.standard_normal(e.size), 20) * np.sqrt(20)   # std ≈ 1 mGal
    col = Collocation(error_corr_km=1.0).fit(e, n, truth(e, n) + noise, 1.0, line=lab)
    ge, gn, g, s = col.grid(region=(0, 30, 0, 20))
    GE, GN = np.meshgrid(ge, gn)
    err = g - truth(GE, GN)
    assert np.sqrt(np.nanmean(err ** 2)) < 1.0
    assert np.nanmean(np.abs(err) < 2 * s) >= 0.9


def test_collocation_survives_coincident_points_with_zero_error():
    # the same positions repeated with different values and zero std (merged by the thinning)
    e = np.array([0.0, 0.0, 1.0, 1.0, 2.0, 3.0])
    n = np.zeros(6)
    v = np.array([1.0, 1.2, 2.0, 2.1, 3.0, 4.0])
    col = Collocation(4.0, 1.0, 0.0, thin_km=1e-6, trend="none", mask_km=10.0).fit(e, n, v, 0.0)
    got = col.predict(np.array([0.5, 2.0]), np.zeros(2))
    assert np.all(np.isfinite(got))
    assert got[1] == pytest.approx(3.0, abs=1e-3)            # interpolates a datum with zero error


def test_robust_cholesky_on_singular_matrix():
    from app.core.gridding import _robust_cholesky

    x = np.array([0.0, 1e-9, 1.0])
    K = gm2_covariance(np.abs(x[:, None] - x[None]), 1.0, 1.0)
    K[0, 1] = K[1, 0] = K[0, 0] = K[1, 1] = 1.0                # exactly singular
    c = _robust_cholesky(K, 1e-8)
    L = np.tril(c)
    assert np.max(np.abs(L @ L.T - K)) < 1e-3


def test_collocation_with_per_line_offsets():
    """Leveling residuals (a constant error per line, σ = 1.5 mGal) are modelled
    by ``line_error_mgal2``: the std stays calibrated and the offsets are
    partly separated from the field."""
    res = {0.0: [], 2.25: []}
    for seed in range(2):
        e, n, obs, lab, ge, gn, truth = _simulate(seed, noise=0.5, spacing=1.5, step=0.5, nlines=14, length=40.0)
        rng = np.random.default_rng(100 + seed)
        off = {k: rng.normal(0, 1.5) for k in np.unique(lab)}
        obs = obs + np.array([off[k] for k in lab])
        for le in res:
            col = Collocation(error_corr_km=0.0, line_error_mgal2=le).fit(e, n, obs, 0.5, line=lab)
            _, _, dg, sd = col.grid(region=(0, 40, 0, 19.5))
            err = (dg - truth)[np.isfinite(dg)]
            res[le].append((np.sqrt(np.mean(err ** 2)), np.mean(np.abs(err) < 2 * sd[np.isfinite(dg)])))
    with_line = np.array(res[2.25])
    without = np.array(res[0.0])
    assert np.all(with_line[:, 1] >= 0.88)                  # calibrated
    assert np.all(without[:, 1] < 0.8)                      # ignoring the line errors is overconfident
    assert with_line[:, 0].mean() < without[:, 0].mean()


def test_cross_validated_std_factor_near_one_for_a_correct_model():
    """Leave-line-out normalised residuals have unit RMS when the model matches the field,
    and a grossly over-confident data std shows up as a factor well above 1."""
    from app.core.gridding import cross_validated_std_factor

    e, n, obs, lab, *_ = _simulate(11, noise=1.0, nlines=8)
    std = np.full(e.size, 1.0)
    make = lambda: Collocation(error_corr_km=0.0)  # noqa: E731  white errors, as simulated
    good = cross_validated_std_factor(make, e, n, obs, std, lab, n_folds=6)
    assert 0.7 < good["factor"] < 1.4
    # per-line offsets of 6 mGal that the stated 1 mGal std does not admit
    names, inv = np.unique(lab, return_inverse=True)
    obs_bad = obs + np.random.default_rng(2).normal(0, 6.0, names.size)[inv]
    bad = cross_validated_std_factor(make, e, n, obs_bad, std, lab, n_folds=6)
    assert bad["factor"] > 1.5 * good["factor"]
    with pytest.raises(ValueError):
        cross_validated_std_factor(make, e[:10], n[:10], obs[:10], std[:10], lab[:10])


def test_line_std_floor_is_the_local_line_std():
    from app.core.gridding import line_std_floor

    e = np.concatenate([np.linspace(0, 20, 201), np.linspace(0, 20, 201)])
    n = np.concatenate([np.zeros(201), np.full(201, 10.0)])
    s = np.concatenate([np.full(201, 1.0), np.full(201, 3.0)])
    f = line_std_floor(np.array([5.0, 15.0]), np.array([0.0, 10.0]), e, n, s, k=8, step=1)
    np.testing.assert_allclose(f, [[1.0, 1.0], [3.0, 3.0]])
    with pytest.raises(ValueError):
        line_std_floor(np.array([0.0]), np.array([0.0]), e, n, np.full(e.size, np.nan))
