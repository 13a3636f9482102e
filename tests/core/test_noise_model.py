"""Coloured error of z (app.core.noise_model) and the smoother that carries it.

Independent references: closed-form spectra (the transfer function of each component),
pykalman on the same state-space model, simulation with known truth, and the seed-000
white-velocity model (which the white component must reproduce exactly).
"""

import numpy as np
import pytest

from app.core.noise_level import band_noise_variance_cm2s2
from app.core.noise_model import (
    NoiseComponent,
    NoiseModel,
    fit_noise_model,
    multitaper_psd,
    white_velocity,
    with_white_floor,
)
from app.core.smoother import coloured_model, kalman_loglik, kalman_smooth


def _simulate_component(rng, n, c: NoiseComponent, level=1.0):
    e = rng.standard_normal(n + 3) * np.sqrt(c.weight * level)
    u = np.empty_like(e)
    acc = 0.0
    for i, v in enumerate(e):
        acc = c.phi * acc + v
        u[i] = acc
    for _ in range(c.order):
        u = np.diff(u)
    return u[-n:]


def test_white_velocity_psd_is_the_seed_000_noise():
    """The white component at (1000/Δt)² per (cm/s)² has the PSD of −1000·∇r/Δt."""
    dt, R = 0.1, 1.7
    f = np.linspace(0.001, 4.9, 50)
    expected = dt * (1000.0 / dt) ** 2 * R * (2.0 * np.sin(np.pi * f * dt)) ** 2
    np.testing.assert_allclose(white_velocity(dt, R).psd(f), expected, rtol=1e-12)


@pytest.mark.parametrize("comp", [NoiseComponent(1, 0.9, 3.0), NoiseComponent(2, 0.0, 2.0),
                                  NoiseComponent(2, 0.7, 1.0), NoiseComponent(0, 0.0, 5.0)])
def test_component_psd_matches_simulation(comp):
    """Welch estimate of a simulated component against the model PSD (closed form)."""
    from scipy.signal import welch

    rng = np.random.default_rng(4)
    dt = 0.5
    x = _simulate_component(rng, 400_000, comp)
    f, p = welch(x, fs=1.0 / dt, nperseg=4096, return_onesided=True)
    sel = (f > 0.01) & (f < 0.9)
    model = NoiseModel((comp,), dt, "test").psd(f[sel]) * 2.0  # one-sided
    ratio = (p[sel] / model)[: 30 * (sel.sum() // 30)].reshape(30, -1).mean(axis=1)  # 30 bands
    np.testing.assert_allclose(ratio, 1.0, atol=0.06)


def test_block_has_the_spectrum_of_the_model():
    """The state-space block (F, W, h) has transfer function h(z)·(I − F z⁻¹)⁻¹: its PSD
    equals NoiseModel.psd (two independent derivations)."""
    dt = 0.5
    nm = NoiseModel((NoiseComponent(1, 0.8, 2.0), NoiseComponent(2, 0.3, 5.0), NoiseComponent(0, 0.0, 1.0)),
                    dt, "mix")
    F, W, h = nm.block()
    f = np.linspace(0.01, 0.99, 30)
    out = []
    for fk in f:
        zinv = np.exp(-2j * np.pi * fk * dt)
        G = h @ np.linalg.inv(np.eye(F.shape[0]) - F * zinv)
        out.append(dt * np.real(G @ W @ G.conj()))
    np.testing.assert_allclose(out, nm.psd(f), rtol=1e-10)


def test_normalized_level_is_the_band_estimator():
    """A normalised model at level R has band power equal to white velocity noise of R, so
    the band estimator of app.core.noise_level reads R off simulated coloured noise."""
    rng = np.random.default_rng(8)
    dt = 0.2
    comp = NoiseComponent(2, 0.5, 1.0)
    nm = NoiseModel((comp,), dt, "h").normalized((0.1, 0.5))
    assert nm.equivalent_white_R((0.1, 0.5)) == pytest.approx(1.0, rel=1e-9)
    R = 3.0
    x = _simulate_component(rng, 200_000, nm.components[0], level=R)
    est = np.median(band_noise_variance_cm2s2(x, dt, (0.1, 0.5)))
    assert est == pytest.approx(R, rel=0.08)


def test_multitaper_resolves_the_anomaly_band_under_a_steep_noise_wall():
    """10 orders of magnitude between 0.01 and 0.4 Hz: the prewhitened estimate at 0.01–0.03 Hz
    must follow the true PSD (an unprewhitened taper leaks the wall into it)."""
    rng = np.random.default_rng(2)
    dt = 0.5
    comp = NoiseComponent(2, 0.0, 4e9)       # heights-only GNSS at 2 Hz: f⁴
    x = _simulate_component(rng, 8000, comp)
    spec = multitaper_psd(x, dt, 0.2)
    sel = (spec.f_hz > 0.01) & (spec.f_hz < 0.03)
    true = NoiseModel((comp,), dt, "h").psd(spec.f_hz[sel])
    ratio = np.exp(np.mean(np.log(spec.psd[sel] / true)))
    assert 0.7 < ratio < 1.4


def test_multitaper_of_a_short_stretch_is_unbiased():
    """A 92 s line at 20 Hz is too short for the default anti-alias filter (~100 s with the
    decimation); the widened transition must still give the true spectrum of white velocity
    noise (f², steep enough that aliasing or leakage would show) — pooled over 60 stretches —
    and a stretch too short for any filter is refused."""
    dt = 0.05
    comp = NoiseComponent(1, 0.0, 1e6)
    ratios = []
    for seed in range(60):
        x = _simulate_component(np.random.default_rng(seed), 1840, comp)
        spec = multitaper_psd(x, dt, 0.2)
        ratios.append(spec.psd / NoiseModel((comp,), dt, "v").psd(spec.f_hz))
    ratios = np.concatenate(ratios)
    assert ratios.size >= 60 * 3
    assert 0.85 < np.mean(ratios) < 1.2
    with pytest.raises(ValueError, match="too short"):
        multitaper_psd(_simulate_component(np.random.default_rng(0), 300, comp), dt, 0.2)


def test_fit_recovers_white_velocity_noise_and_chooses_it():
    rng = np.random.default_rng(11)
    dt, R = 0.1, 1.69
    segs = []
    for _ in range(8):
        n = 10_000
        dg = np.cumsum(np.cumsum(rng.normal(0, 1e-3, n)))
        r = rng.normal(0, np.sqrt(R), n + 1)
        segs.append(dg - 1000.0 * np.diff(r) / dt)
    fit = fit_noise_model(segs, dt)
    assert fit.model.family == "white velocity"
    w = fit.model.components[0].weight
    assert w == pytest.approx((1000.0 / dt) ** 2 * R, rel=0.06)


def _anomaly_plus(rng, comps, n_seg=6, n=3000):
    """Segments of z: an m = 2 random anomaly plus the given noise components."""
    segs = []
    for _ in range(n_seg):
        dg = np.cumsum(np.cumsum(rng.normal(0, 1e-2, n)))
        segs.append(dg + sum(_simulate_component(rng, n, c) for c in comps))
    return segs


@pytest.mark.parametrize("comp,family", [(NoiseComponent(2, 0.0, 1e9), "white height"),
                                         (NoiseComponent(1, 0.95, 1e6), "Gauss-Markov velocity")])
def test_fit_chooses_the_family_of_the_data(comp, family):
    """The family of the data is found, with its parameters.  A bare white height is the fit
    kept beside the nesting family the fit uses (the next test), so it is read there."""
    fit = fit_noise_model(_anomaly_plus(np.random.default_rng(5), [comp]), 0.5)
    model = fit.model
    if family == "white height":
        assert model.family == "velocity + height" and model.info["white_height_nested"]
        model = fit.unmoved.model
    assert model.family == family
    got = model.components[0]
    assert got.weight == pytest.approx(comp.weight, rel=0.15)
    assert got.phi == pytest.approx(comp.phi, abs=0.02)


def test_bare_white_height_gets_the_random_walk_part_the_spectra_show():
    """White height noise dominating the fitted band plus a random-walk height part (f² in z)
    that only shows below 0.02 Hz, where the anomaly is: the BIC margin alone keeps the bare
    white height, which puts 4x too little noise at 0.005 Hz; the nesting family's fitted
    random-walk level gives the true noise there within a factor 2."""
    dt = 0.5
    wh, rw = NoiseComponent(2, 0.0, 1e9), NoiseComponent(1, 0.0, 8e5)
    fit = fit_noise_model(_anomaly_plus(np.random.default_rng(8), [wh, rw]), dt)
    assert fit.model.family == "velocity + height" and fit.model.info["white_height_nested"]
    assert fit.unmoved is not None and fit.unmoved.model.family == "white height"
    f = np.array([0.005])
    true = NoiseModel((wh, rw), dt, "truth").psd(f)[0]
    assert fit.unmoved.model.psd(f)[0] < 0.3 * true
    assert 0.5 * true < fit.model.psd(f)[0] < 2.0 * true


def _pykalman_model(pykalman, nm: NoiseModel, m: int, Q: float, R: float, obs_var: float, x0, P0):
    """pykalman's filter for the anomaly of order m = 2 (δg_k, δg_{k−1}) beside the noise block of
    ``nm`` at level R, with white observation noise of variance ``obs_var`` (mGal²)."""
    F, W, h = nm.block()
    n = m + nm.n_states
    A = np.zeros((n, n))
    A[0, :2] = [2.0, -1.0]
    A[1, 0] = 1.0
    A[m:, m:] = F
    Wm = np.zeros((n, n))
    Wm[0, 0] = Q
    Wm[m:, m:] = R * W
    C = np.zeros((1, n))
    C[0, 0] = 1.0
    C[0, m:] = h
    return pykalman.KalmanFilter(transition_matrices=A, observation_matrices=C, transition_covariance=Wm,
                                 observation_covariance=np.full((1, 1), float(obs_var)), initial_state_mean=x0,
                                 initial_state_covariance=P0)


def test_coloured_smoother_matches_pykalman():
    """Same state-space model, same prior: pykalman's smoother and likelihood."""
    pykalman = pytest.importorskip("pykalman")
    rng = np.random.default_rng(3)
    dt, T, m = 1.0, 300, 2
    nm = NoiseModel((NoiseComponent(1, 0.6, 0.5), NoiseComponent(2, 0.0, 0.2)), dt, "mix")
    Q, R = 0.05, 1.0
    dg = np.cumsum(np.cumsum(rng.normal(0, np.sqrt(Q), T))) + 10.0
    z = dg + _simulate_component(rng, T, nm.components[0]) + _simulate_component(rng, T, nm.components[1])
    z[40] = np.nan
    n = m + nm.n_states
    x0 = np.zeros(n)
    x0[:m] = np.nanmean(z[:20])
    P0 = np.eye(n) * 100.0
    P0[m:, m:] = nm.stationary_covariance(R)
    res_bf = kalman_smooth(z, Q, R, dt, m=m, noise=nm, x0=x0, P0=P0)
    res_rts = kalman_smooth(z, Q, R, dt, m=m, noise=nm, x0=x0, P0=P0, method="rts")
    kf = _pykalman_model(pykalman, nm, m, Q, R, 0.0, x0, P0)
    zm = np.ma.masked_invalid(z)
    means, covs = kf.smooth(zm)
    for res in (res_bf, res_rts):
        np.testing.assert_allclose(res.dg_mgal, means[:, 0], rtol=0, atol=1e-7 * np.abs(means[:, 0]).max())
        np.testing.assert_allclose(res.dg_std_mgal ** 2, covs[:, 0, 0], rtol=1e-6)
    assert kalman_loglik(z, Q, R, dt, m=m, noise=nm, x0=x0, P0=P0) == pytest.approx(kf.loglikelihood(zm), rel=1e-8)


def test_white_velocity_model_takes_the_seed_000_path():
    rng = np.random.default_rng(0)
    dt, T = 0.1, 2000
    z = np.cumsum(np.cumsum(rng.normal(0, 0.01, T))) + rng.normal(0, 100, T)
    a = kalman_smooth(z, 1e-4, 2.0, dt, m=2, noise=white_velocity(dt, 3.0))
    b = kalman_smooth(z, 1e-4, 6.0, dt, m=2)
    np.testing.assert_array_equal(a.dg_mgal, b.dg_mgal)
    # and the generic block code gives the same numbers for the same model
    A, Wa, Wb, c = coloured_model(2, white_velocity(dt))
    assert A.shape == (4, 4) and c.tolist() == [1.0, 0.0, 1.0, -1.0]


def test_coloured_noise_smoother_beats_the_white_model_on_height_noise():
    """Heights-only GNSS at 2 Hz (f⁴ error): a white-velocity model sized to the high band
    flattens the anomaly; the coloured model recovers it (simulation with known truth)."""
    rng = np.random.default_rng(21)
    dt, n = 0.5, 6000
    t = np.arange(n) * dt
    truth = 8.0 * np.sin(2 * np.pi * t / 600.0) + 4.0 * np.sin(2 * np.pi * t / 250.0 + 1.0)
    comp = NoiseComponent(2, 0.0, 2e9)
    z = truth + _simulate_component(rng, n, comp)
    fit = fit_noise_model([z], dt)
    assert fit.model.family in ("white height", "coloured height", "velocity + height")
    nm = fit.model
    from scipy.optimize import minimize_scalar

    best = minimize_scalar(lambda lq: -kalman_loglik(z, np.exp(lq), 1.0, dt, m=2, noise=nm),
                           bounds=(-25, 3), method="bounded")
    est = kalman_smooth(z, np.exp(best.x), 1.0, dt, m=2, noise=nm).dg_mgal
    core = slice(400, n - 400)
    rms = np.sqrt(np.mean((est - truth)[core] ** 2))
    r_white = np.median(band_noise_variance_cm2s2(z, dt, (0.1, 0.4)))
    best_w = minimize_scalar(lambda lq: -kalman_loglik(z, np.exp(lq), r_white, dt, m=2),
                             bounds=(-30, 3), method="bounded")
    est_w = kalman_smooth(z, np.exp(best_w.x), r_white, dt, m=2).dg_mgal
    rms_w = np.sqrt(np.mean((est_w - truth)[core] ** 2))
    assert rms < 1.5 and rms < 0.3 * rms_w
    assert np.var(est[core]) > 0.8 * np.var(truth[core])


def test_multitaper_leaves_bins_on_a_97_s_stretch_at_2_hz():
    """At 2 Hz the sharpest anti-alias filter takes 79 s of a 97 s stretch, and the 18 s left
    have a taper bandwidth above fmax: no bin (a layout of 12 km lines at 117 m/s was refused).
    With ``need_bins`` the next filter is taken, and its spectrum of white velocity noise is the
    true one (pooled over 60 stretches); the noise fit then runs on such lines."""
    dt = 0.5
    comp = NoiseComponent(1, 0.0, 1e6)
    rng = np.random.default_rng(7)
    x = _simulate_component(rng, 194, comp)
    assert multitaper_psd(x, dt, 0.2).f_hz.size == 0
    ratios = []
    for _ in range(60):
        spec = multitaper_psd(_simulate_component(rng, 194, comp), dt, 0.2, need_bins=True)
        assert spec.f_hz.size > 0 and spec.f_hz.max() <= 0.2
        ratios.append(spec.psd / NoiseModel((comp,), dt, "v").psd(spec.f_hz))
    assert 0.8 < np.mean(np.concatenate(ratios)) < 1.25
    fit = fit_noise_model([_simulate_component(rng, 194, comp) for _ in range(6)], dt, m=2, fmax_hz=0.2,
                          min_duration_s=60.0)
    assert fit.model.components


def test_pass_differences_keep_both_sides_of_a_hole():
    """Without holes pass_differences is pass_difference; with a hole (NaN) in one pass it
    returns the stretches on either side, equal to the hole-free difference away from the
    hole's edges (the not-a-knot spline of each run differs from the whole pass's only near its
    ends), where pass_difference returns nothing."""
    from app.core.noise_model import pass_difference, pass_differences

    rng = np.random.default_rng(9)
    dt, n = 0.5, 1200
    s = 50.0 * np.arange(n)                    # 100 m/s
    za, zb = rng.normal(0.0, 1.0, n), rng.normal(0.0, 1.0, n)
    for lp in (1.0, 0.3):                      # no low-pass (≥ 0.45 fs) and a low-pass
        whole = pass_difference(s, za, s[::-1], zb[::-1], dt, lp)
        got = pass_differences(s, za, s[::-1], zb[::-1], dt, lp)
        assert len(got) == 1
        np.testing.assert_array_equal(got[0].d_mgal, whole.d_mgal)
    holed = za.copy()
    holed[500:510] = np.nan
    assert pass_difference(s, holed, s, zb, dt, 1.0) is None
    parts = pass_differences(s, holed, s, zb, dt, 1.0)
    assert len(parts) == 2
    clean = pass_difference(s, za, s, zb, dt, 1.0).d_mgal
    assert parts[0].d_mgal.size + parts[1].d_mgal.size < clean.size
    np.testing.assert_allclose(parts[0].d_mgal[:480], clean[:480], atol=1e-9)
    np.testing.assert_allclose(parts[1].d_mgal[-(clean.size - 530):], clean[530:], atol=1e-9)
    short = za.copy()
    short[40:] = np.nan                        # nothing long enough on one pass
    assert pass_differences(s, short, s, zb, dt, 1.0) == []


def test_whittle_cached_spectra_are_the_component_spectra():
    """The Whittle likelihood's cached e^{-2πiν} give the closed form of an AR(1) differenced
    j times, w·(2 − 2 cos 2πν)^j / (1 − 2φ cos 2πν + φ²), for every order, white and AR(1), on
    z's bins (ν = f·dt·r1) and on pass-difference bins (r2) — and exactly the numbers of
    _component_psd_per_sample (the same arithmetic, so the fit is unchanged)."""
    from app.core.noise_model import _component_psd_per_sample, _Spectra, _Whittle

    f = np.linspace(0.003, 0.2, 157)
    n = f.size
    sp = _Spectra(f, np.ones(n), np.ones(n), np.ones(n), np.full(n, 0.5), np.full(n, 2.0), np.ones(n), 1)
    w = _Whittle(sp, 0.5, np.random.default_rng(0), 1, False)
    for order in (0, 1, 2):
        for phi in (0.0, 0.3, 0.97):
            c = NoiseComponent(order, phi, 123.0)
            for v, r in ((1, sp.r1), (2, sp.r2)):
                cos = np.cos(2 * np.pi * w.nu * r)
                closed = 123.0 * (2 - 2 * cos) ** order / (1 - 2 * phi * cos + phi ** 2)
                np.testing.assert_allclose(w._component_psd(v, c), closed, rtol=1e-9)
                assert np.array_equal(w._component_psd(v, c), _component_psd_per_sample(w.nu * r, c))


def _random_theta(rng, spec) -> tuple[list, list]:
    """A random θ of family ``spec`` (Q = 10⁻³; log w ~ N(−2, 1); logit φ ~ N(0.5, 1)) and its
    components as (order, φ, w) written out independently of the code's unpacking."""
    from app.core.noise_model import PHI_MAX

    theta = [np.log(1e-3)]
    comps = []
    for order, free_phi in spec:
        lw = rng.normal(-2.0, 1.0)
        theta.append(lw)
        phi = 0.0
        if free_phi:
            lg = rng.normal(0.5, 1.0)
            theta.append(lg)
            phi = PHI_MAX / (1.0 + np.exp(-lg))
        comps.append((order, phi, np.exp(lw)))
    return theta, comps


def test_whittle_likelihood_is_the_closed_form():
    """The Whittle negative log-likelihood the fit minimises, Σ wt·(log S + I/S), against S
    written out from the closed forms: on line bins the anomaly dt·Q/(2 − 2cos 2πν)^m plus each
    component dt·w(2 − 2cos)^j/(1 − 2φcos + φ²)/r1 at ν·r1; on pass-difference bins the
    components of both passes, at ν·r1 and ν·r2, no anomaly; θ = (log Q, log w, logit φ …), and
    with one element more the anomaly's roll-off exp(−β f); a θ beyond ±200 is refused (1e300)."""
    from app.core.noise_model import FAMILIES, ROLLOFF_MAX_S, _rolloff_logit, _Spectra, _Whittle, rolloff_s

    rng = np.random.default_rng(3)
    f = np.linspace(0.004, 0.2, 120)
    n = f.size
    is_line = (np.arange(n) % 3 != 0).astype(float)
    sp = _Spectra(f, rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 1.5, n), is_line, rng.uniform(0.8, 1.2, n),
                  rng.uniform(0.8, 1.2, n), 1.0 - is_line, 2)
    dt = 0.5
    w = _Whittle(sp, dt, np.random.default_rng(0), 1, True)
    for _, spec in FAMILIES:
        for m in (1, 2):
            theta, comps = _random_theta(rng, spec)
            nu = f * dt
            S = is_line * dt * 1e-3 / (2 - 2 * np.cos(2 * np.pi * nu)) ** m
            for order, phi, wt in comps:
                for r, on in ((sp.r1, 1.0), (sp.r2, 1.0 - is_line)):
                    cos = np.cos(2 * np.pi * nu * r)
                    S = S + on * dt * wt * (2 - 2 * cos) ** order / (1 - 2 * phi * cos + phi ** 2) / r
            expect = np.sum(w.wt * (np.log(S) + sp.psd / S))
            assert w.nll(np.array(theta), spec, m) == pytest.approx(expect, rel=1e-10)
            # one element more is the anomaly's roll-off: β = ROLLOFF_MAX_S·logistic(t), the
            # anomaly's term times exp(−β f)
            t = rng.normal(-3.0, 1.0)
            beta = ROLLOFF_MAX_S / (1.0 + np.exp(-t))
            S_ro = S + is_line * dt * 1e-3 / (2 - 2 * np.cos(2 * np.pi * nu)) ** m * (np.exp(-beta * f) - 1.0)
            expect_ro = np.sum(w.wt * (np.log(S_ro) + sp.psd / S_ro))
            assert w.nll(np.array(theta + [t]), spec, m) == pytest.approx(expect_ro, rel=1e-10)
    assert w.nll(np.array([250.0, 0.0]), ((1, False),), 2) == 1e300
    # the start of a β: the logistic's inverse
    assert rolloff_s([_rolloff_logit(150.0)]) == pytest.approx(150.0, rel=1e-12)



def test_whittle_misfit_bound_term_is_the_closed_form():
    """With a misfit bound the likelihood adds, per group g, weight·(log T + B/T) with
    B = slack·psd and T = max(B, Sb), Sb the model's velocity error in z there — each
    component's dt·w(2 − 2cos 2πν)^j/(1 − 2φcos + φ²) at ν = f·dt, no anomaly: the compiled
    kernel against that written out, and against the numpy reference on random θ of every
    family (with and without the roll-off element)."""
    from app.core.noise_model import FAMILIES, VelocityBound, _Spectra, _Whittle

    rng = np.random.default_rng(11)
    f = np.linspace(0.004, 0.2, 90)
    n = f.size
    sp = _Spectra(f, rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 1.5, n), np.ones(n), np.ones(n), np.ones(n),
                  np.zeros(n), 0)
    fb = np.geomspace(0.002, 0.05, 12)
    bound = VelocityBound(fb, rng.uniform(0.1, 3.0, fb.size), rng.uniform(2.0, 9.0, fb.size),
                          rng.uniform(1.0, 1.5, fb.size), 4)
    dt = 0.5
    w = _Whittle(sp, dt, np.random.default_rng(0), 1, False, bound)
    for _, spec in FAMILIES:
        theta, comps = _random_theta(rng, spec)
        nu = f * dt
        S = dt * 1e-3 / (2 - 2 * np.cos(2 * np.pi * nu)) ** 2
        cb = np.cos(2 * np.pi * fb * dt)
        Sb = np.zeros(fb.size)
        for order, phi, wt in comps:
            cos = np.cos(2 * np.pi * nu)
            S = S + dt * wt * (2 - 2 * cos) ** order / (1 - 2 * phi * cos + phi ** 2)
            Sb = Sb + dt * wt * (2 - 2 * cb) ** order / (1 - 2 * phi * cb + phi ** 2)
        B = bound.slack * bound.psd
        T = np.maximum(B, Sb)
        expect = np.sum(w.wt * (np.log(S) + sp.psd / S)) + np.sum(bound.weight * (np.log(T) + B / T))
        assert w.nll(np.array(theta), spec, 2) == pytest.approx(expect, rel=1e-10)
        for _ in range(20):
            th = np.array(theta) + rng.normal(0.0, 2.0, len(theta))
            if rng.random() < 0.5:
                th = np.append(th, rng.normal(0.0, 2.0))
            assert w.nll(th, spec, 2) == pytest.approx(w.nll_numpy(th, spec, 2), rel=1e-12)


class _StableArgsortNumpy:
    """numpy with a stable ``argsort``: SciPy's Nelder–Mead sorts its simplex with numpy's
    default argsort, whose order among equal values depends on the CPU's SIMD sort (ties of
    1e300 where θ leaves the likelihood's domain); the compiled search sorts stably."""

    def __getattr__(self, name):
        return getattr(np, name)

    @staticmethod
    def argsort(a, *args, **kwargs):
        return np.argsort(a, kind="stable")


def test_compiled_nelder_mead_is_scipys(monkeypatch):
    """The fit's Nelder–Mead (numba, with the likelihood inside) against SciPy's
    ``minimize(method="Nelder-Mead")`` on the same likelihood, with a stable sort on both
    sides: the same point, value and number of evaluations on every family, from starts near
    and far (some vertices outside the domain, 1e300), and over a subset of θ (the roll-off
    screen: Q and β free, the rest held)."""
    import scipy.optimize._optimize as scipy_optimize

    from app.core.noise_model import FAMILIES, _rolloff_logit, _Spectra, _Whittle

    monkeypatch.setattr(scipy_optimize, "np", _StableArgsortNumpy())
    rng = np.random.default_rng(5)
    f = np.linspace(0.004, 0.2, 150)
    n = f.size
    is_line = (np.arange(n) % 4 != 0).astype(float)
    sp = _Spectra(f, rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 1.5, n), is_line, np.ones(n), rng.uniform(0.8, 1.2, n),
                  1.0 - is_line, 2)
    w = _Whittle(sp, 0.5, np.random.default_rng(0), 1, True)
    checked = 0
    for _, spec in FAMILIES:
        for far in (False, True):
            x0 = np.array(w.random_starts(spec)[0]) + (rng.normal(0.0, 150.0, 1 + len(spec) + sum(f for _, f in spec))
                                                       if far else 0.0)
            for template, pos in ((None, None), (np.append(x0, 0.0), np.array([0, x0.size]))):
                start = x0 if template is None else np.array([x0[0], _rolloff_logit(60.0)])
                a = w.minimize(start, spec, 2, 400 * start.size, template, pos)
                b = w.nelder_mead_scipy(start, spec, 2, 400 * start.size, template, pos)
                assert np.array_equal(a.x, b.x) and a.fun == b.fun and a.nfev == b.nfev
                checked += 1
    assert checked == 4 * len(FAMILIES)

# --- the GNSS height–velocity misfit as a bound on the velocity error (velocity_bound) ---

def _ar1(rng, n, phi, sd):
    """AR(1) of stationary std ``sd`` (m/s)."""
    e = rng.normal(0.0, sd * np.sqrt(1.0 - phi ** 2), n)
    out = np.empty(n)
    acc = rng.normal(0.0, sd)
    for i in range(n):
        acc = phi * acc + e[i]
        out[i] = acc
    return out


def _velocity_model(dt, phi, sd_gm, sd_white):
    """The velocity error as z sees it, closed form: AR(1) + white velocity components."""
    to_z = (1e5 / dt) ** 2     # (m/s)² per step → mGal² (z = −Δr/Δt in mGal)
    comps = [NoiseComponent(1, 0.0, sd_white ** 2 * to_z)]
    if sd_gm > 0:
        comps.insert(0, NoiseComponent(1, phi, sd_gm ** 2 * (1.0 - phi ** 2) * to_z))
    return NoiseModel(tuple(comps), dt, "truth")


def _flight_with_gm_velocity(seed, dt, tau_s, sd_gm, sd_white, sd_h, n_line=3750, n_lines=13):
    """Thirteen lines of z: an anomaly whose spectrum falls exponentially (sources below the
    flight height, 28 mGal) minus a white + Gauss–Markov (``tau_s``) velocity error differenced
    once, and the misfit of the flight's heights (white error ``sd_h`` m) and velocities.
    Returns (z per line, misfit, the velocity error's closed-form model in z)."""
    from app.core.measurement import height_velocity_misfit_m

    rng = np.random.default_rng(seed)
    phi = float(np.exp(-dt / tau_s))
    n = n_line * n_lines
    r = _ar1(rng, n, phi, sd_gm) + rng.normal(0.0, sd_white, n)
    d = height_velocity_misfit_m(np.arange(n) * dt, rng.normal(0.0, sd_h, n), r)
    f = np.fft.rfftfreq(n_line, dt)
    zs = []
    for k in range(n_lines):
        x = np.fft.irfft(np.exp(-f / 0.006) * (f > 0) * (rng.normal(size=f.size) + 1j * rng.normal(size=f.size)), n_line)
        rr = r[k * n_line:(k + 1) * n_line]
        zs.append(28.0 * x / x.std() - np.diff(np.concatenate([[rr[0]], rr])) / dt * 1e5)
    return zs, d, _velocity_model(dt, phi, sd_gm, sd_white)


@pytest.mark.parametrize("sd_gm", [0.0, 0.005])
def test_velocity_bound_is_the_velocity_error_in_z(sd_gm):
    """The misfit h − ∫vu of exact heights and velocities with a known error: its spectrum,
    carried to z, is the velocity component's closed-form PSD (white, and Gauss–Markov
    with a 15 s correlation time, whose corner lies inside the band)."""
    from app.core.measurement import height_velocity_misfit_m
    from app.core.noise_model import velocity_bound

    rng = np.random.default_rng(21)
    dt, n, phi = 0.2, 20_000, float(np.exp(-0.2 / 15.0))
    t = np.arange(n) * dt
    h = 3000.0 + 3.0 * np.sin(2 * np.pi * t / 60.0) + 0.5 * np.sin(2 * np.pi * 0.2 * t)
    v = 3.0 * 2 * np.pi / 60.0 * np.cos(2 * np.pi * t / 60.0) + 0.5 * 2 * np.pi * 0.2 * np.cos(2 * np.pi * 0.2 * t)
    segs = []
    for _ in range(8):
        r = (_ar1(rng, n, phi, sd_gm) if sd_gm else 0.0) + rng.normal(0.0, 0.012, n)
        segs.append(height_velocity_misfit_m(t, h, v + r))
    b = velocity_bound(segs, dt, fmax_hz=0.01, n_groups=12)
    ratio = b.psd / _velocity_model(dt, phi, sd_gm, 0.012).psd(b.f_hz)
    assert b.f_hz.min() < 0.0015 and b.f_hz.max() <= 0.01
    assert np.exp(np.mean(np.log(ratio))) == pytest.approx(1.0, abs=0.12)
    assert np.all((ratio > 0.6) & (ratio < 1.6))


def test_misfit_cancels_the_motion_and_integrates_a_bias():
    """Analytic: exact heights and velocities of a manoeuvring aircraft leave d ≈ 0 (the
    trapezoid rule's error only); a velocity bias b leaves d = −b·(t − t₀)."""
    from app.core.measurement import height_velocity_misfit_m

    dt = 0.1
    t = 100.0 + np.arange(6000) * dt
    w = 2 * np.pi / 40.0
    h = 2000.0 + 20.0 * np.sin(w * t)
    v = 20.0 * w * np.cos(w * t)
    d = height_velocity_misfit_m(t, h, v)
    assert np.max(np.abs(d)) < 20.0 * (w * dt) ** 2 / 6.0
    np.testing.assert_allclose(height_velocity_misfit_m(t, h, v + 0.03) - d, -0.03 * (t - t[0]), atol=1e-9)
    with pytest.raises(ValueError):
        height_velocity_misfit_m(t, h, np.where(t > 200.0, np.nan, v))


def test_a_slack_velocity_bound_leaves_the_fit_as_it_was():
    """A bound far above the model adds a constant to the likelihood: the same fit."""
    from app.core.noise_model import VelocityBound

    segs = _anomaly_plus(np.random.default_rng(5), [NoiseComponent(1, 0.95, 1e6)])
    f = np.geomspace(0.002, 0.05, 10)
    loose = VelocityBound(f, np.full(10, 1e12), np.full(10, 50.0), np.full(10, 1.2), 1)
    a = fit_noise_model(segs, 0.5)
    b = fit_noise_model(segs, 0.5, bound=loose)
    assert a.model.family == b.model.family
    for ca, cb in zip(a.model.components, b.model.components):
        assert cb.weight == pytest.approx(ca.weight, rel=1e-4)
        assert cb.phi == pytest.approx(ca.phi, abs=1e-5)
    info = b.model.info["velocity_bound"]
    assert info["applied"] and info["max_model_to_misfit"] < 1e-3 and info["z_to_misfit"] < 1e-3


def test_a_bound_far_below_z_noise_is_not_applied():
    """Where z's noise above the anomaly band is many times what the GNSS misfit shows, the
    GNSS does not make it (a gravimeter's sampling error, its own noise): the bound is left
    out, the fit is the one without it, and the report says why."""
    from app.core.noise_model import VelocityBound

    segs = _anomaly_plus(np.random.default_rng(5), [NoiseComponent(1, 0.95, 1e6)])
    f = np.geomspace(0.002, 0.05, 10)
    tight = VelocityBound(f, np.full(10, 1e-3), np.full(10, 50.0), np.full(10, 1.2), 1)
    a = fit_noise_model(segs, 0.5)
    b = fit_noise_model(segs, 0.5, bound=tight)
    info = b.model.info["velocity_bound"]
    assert not info["applied"] and info["z_to_misfit"] > 2.0 and "not the GNSS alone" in info["reason"]
    assert [(c.order, c.phi, c.weight) for c in a.model.components] == \
           [(c.order, c.phi, c.weight) for c in b.model.components]


def test_the_bound_stops_the_noise_fit_taking_the_anomaly_for_velocity_error():
    """Simulation with truth (unseen survey 783's failure): an anomaly whose spectrum falls
    exponentially (sources below a 3 km flight height, 28 mGal) over a white + Gauss–Markov
    velocity error (15 s).  The spectra of z alone let a Gauss–Markov velocity with its corner
    far below the truth's explain the anomaly band: the model puts 2–3× the true noise there,
    and the smoother would flatten the anomaly.  The misfit of the same flight's heights and
    velocities (5 cm height error) keeps it within 1.6× of the truth."""
    from app.core.noise_model import velocity_bound

    dt = 0.2
    zs, d, truth = _flight_with_gm_velocity(1, dt, 15.0, 0.005, 0.0128, 0.03)
    band = np.array([0.002, 0.004])
    free = fit_noise_model(zs, dt).model.psd(band) / truth.psd(band)
    bounded = fit_noise_model(zs, dt, bound=velocity_bound([d], dt)).model.psd(band) / truth.psd(band)
    assert np.all(free > 2.0)
    assert np.all(bounded < 1.6) and np.all(bounded > 0.6)


def test_bound_p_value_is_a_chi2_test_of_the_model():
    """Group estimates drawn as S·χ²_ν/ν from a known velocity error: the true model is refuted
    (p < 0.05) in about 5 % of draws at most (Bonferroni is conservative), a model 4× too high
    in nearly all of them."""
    from app.core.noise_model import VelocityBound, bound_p_value

    rng = np.random.default_rng(3)
    truth = _velocity_model(0.2, float(np.exp(-0.2 / 10.0)), 0.004, 0.008)
    f = np.geomspace(0.001, 0.01, 9)
    w = np.linspace(3.0, 40.0, 9)            # few degrees of freedom at the lowest groups
    p_true, p_high = [], []
    for _ in range(400):
        psd = truth.psd(f) * rng.chisquare(2 * w) / (2 * w)
        b = VelocityBound(f, psd, w, np.ones(9), 1)
        p_true.append(bound_p_value(truth, b))
        p_high.append(bound_p_value(truth.scaled(4.0), b))
    assert np.mean(np.array(p_true) < 0.05) <= 0.06
    assert np.mean(np.array(p_high) < 0.05) >= 0.9


def test_the_heights_refute_a_corner_moved_below_the_data():
    """Simulation with truth (unseen survey 1100's failure): a Gauss–Markov velocity error
    (8.5 s, corner 0.019 Hz) beside a white one, under an anomaly that hides the corner.  The
    spectra of z alone fit the corner inside the band, and the corner is moved below the data
    (the cautious side where nothing else sees the noise): the model then puts 2–6× the true
    noise at 0.002–0.008 Hz and the smoother would flatten the anomaly.  The misfit of the same
    flight's heights and velocities refutes the moved shape (χ² test) and keeps the fitted
    one, within 1.5× of the truth."""
    from app.core.noise_model import velocity_bound

    dt = 0.2
    zs, d, truth = _flight_with_gm_velocity(2, dt, 8.5, 0.004, 0.0075, 0.02)
    band = np.array([0.002, 0.004, 0.008])
    free = fit_noise_model(zs, dt)
    assert free.model.info["hidden_corners_hz"]          # the corner was moved below the data
    assert np.all(free.model.psd(band) / truth.psd(band) > 2.0)
    fit = fit_noise_model(zs, dt, bound=velocity_bound([d], dt))
    shape = fit.model.info["velocity_bound"]["cautious_shape"]
    assert shape["refuted"] and shape["p_value"] < 0.05 <= shape["unmoved_p_value"]
    assert shape["model_to_misfit"] > 2.0                 # the moved shape, refitted under the bound
    assert not fit.model.info["hidden_corners_hz"] and fit.unmoved is None
    ratio = fit.model.psd(band) / truth.psd(band)
    assert np.all((ratio > 0.67) & (ratio < 1.5))


def _rolled_off_anomaly(rng, n, dt, A, beta_s):
    """A stationary anomaly whose two-sided PSD is A·f⁻⁴·exp(−β f) (mGal²/Hz): a field seen
    from above its sources (β = 4π d / v), shaped from white noise in the frequency domain."""
    f = np.fft.rfftfreq(n, dt)
    S = np.zeros_like(f)
    S[1:] = A * f[1:] ** -4.0 * np.exp(-beta_s * f[1:])
    X = (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) * np.sqrt(S * n / (2.0 * dt))
    return np.fft.irfft(X, n)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_anomaly_roll_off_keeps_the_noise_above_the_crossover(seed):
    """White + Gauss–Markov velocity noise (τ 10 s at 2 Hz) under an anomaly that falls as
    exp(−β f), β = 150 s (1.2 km below the aircraft at 100 m/s), crossing the noise near
    0.03 Hz.  With the random walk alone as the anomaly's spectrum the fit takes the noise
    just above the crossover for anomaly: a bare Gauss–Markov velocity with 0.2–0.55× the true
    noise at 0.01–0.03 Hz.  With β free it finds β within 10 %, the family of the data, and
    the noise at 0.02–0.05 Hz within 0.8–1.6× the truth's."""
    dt = 0.5
    comps = (NoiseComponent(1, 0.0, 2e5), NoiseComponent(1, 0.95, 2e4))
    truth = NoiseModel(comps, dt, "truth")
    rng = np.random.default_rng(seed)
    segs = [_rolled_off_anomaly(rng, 4000, dt, 0.1, 150.0) + sum(_simulate_component(rng, 4000, c) for c in comps)
            for _ in range(8)]
    f = np.array([0.02, 0.03, 0.05])
    plain = fit_noise_model(segs, dt, anomaly_rolloff=False)
    assert plain.rolloff_s == 0.0
    assert np.all(plain.model.psd(f[:2]) < 0.55 * truth.psd(f[:2]))
    fit = fit_noise_model(segs, dt)
    assert fit.rolloff_s == pytest.approx(150.0, rel=0.1)
    assert fit.model.info["anomaly_rolloff_s"] == fit.rolloff_s
    assert fit.model.family == "white + Gauss-Markov velocity"
    ratio = fit.model.psd(f) / truth.psd(f)
    assert np.all((ratio > 0.8) & (ratio < 1.6)), ratio


def test_no_roll_off_where_the_data_do_not_ask_for_one():
    """An anomaly that is the random walk itself (no roll-off): the fit with β free keeps
    β = 0 (one parameter more must lower the BIC by more than the margin)."""
    fit = fit_noise_model(_anomaly_plus(np.random.default_rng(5), [NoiseComponent(1, 0.95, 1e6)]), 0.5)
    assert fit.rolloff_s == 0.0
    assert all(c["rolloff_s"] == 0.0 for c in fit.candidates)


def test_a_reported_model_is_read_back_as_the_same_model():
    """``NoiseModel.from_description`` of a report's ``noise_model`` (after the JSON round trip
    report.json makes) has the model's spectrum and state-space block."""
    import json

    m = NoiseModel((NoiseComponent(1, 0.0, 3.0e5), NoiseComponent(2, 0.97, 12.5)), 0.1, "velocity + height",
                   info={"bic": 1.0})
    back = NoiseModel.from_description(json.loads(json.dumps(m.describe())))
    f = np.linspace(0.001, 4.9, 200)
    np.testing.assert_array_equal(back.psd(f), m.psd(f))
    for a, b in zip(back.block(), m.block()):
        np.testing.assert_array_equal(a, b)
    assert (back.family, back.dt_s) == (m.family, m.dt_s)


def test_a_white_floor_adds_its_weight_to_the_psd_at_every_frequency():
    """A white-z floor of w per sample has the two-sided PSD w·Δt (closed form); an existing
    white-z component is raised instead of a second one added."""
    dt, w = 0.5, 37.0
    f = np.linspace(0.001, 0.99, 40)
    base = NoiseModel((NoiseComponent(1, 0.8, 3.0), NoiseComponent(2, 0.0, 1.0)), dt, "mix")
    floor = with_white_floor(base, w)
    np.testing.assert_allclose(floor.psd(f), base.psd(f) + w * dt, rtol=1e-12)
    assert floor.family == "mix" and floor.info["white_floor_mgal2"] == w and floor.n_states == base.n_states + 1
    again = with_white_floor(floor, 3.0)
    assert len(again.components) == len(floor.components) and again.components[-1].weight == pytest.approx(w + 3.0)
    with pytest.raises(ValueError, match="weight_mgal2"):
        with_white_floor(base, -1.0)


def test_the_smoother_with_a_floor_is_pykalman_with_that_measurement_noise():
    """A white-z component at level R is measurement noise of variance R·w: the smoother with
    the floor in its state matches pykalman with the base model and that observation noise."""
    pykalman = pytest.importorskip("pykalman")
    rng = np.random.default_rng(11)
    dt, T, m, Q, R, w = 1.0, 300, 2, 0.05, 1.3, 4.0
    base = NoiseModel((NoiseComponent(1, 0.6, 0.5),), dt, "gm")
    nm = with_white_floor(base, w)
    dg = np.cumsum(np.cumsum(rng.normal(0, np.sqrt(Q), T))) + 10.0
    z = dg + _simulate_component(rng, T, base.components[0], R) + rng.normal(0, np.sqrt(R * w), T)
    n, nb = m + nm.n_states, m + base.n_states
    x0 = np.zeros(n)
    x0[:m] = np.nanmean(z[:20])
    P0 = np.eye(n) * 100.0
    P0[m:, m:] = nm.stationary_covariance(R)
    res = kalman_smooth(z, Q, R, dt, m=m, noise=nm, x0=x0, P0=P0)
    kf = _pykalman_model(pykalman, base, m, Q, R, R * w, x0[:nb], P0[:nb, :nb])
    means, covs = kf.smooth(z)
    np.testing.assert_allclose(res.dg_mgal, means[:, 0], rtol=0, atol=1e-7 * np.abs(means[:, 0]).max())
    np.testing.assert_allclose(res.dg_std_mgal ** 2, covs[:, 0, 0], rtol=1e-6)
