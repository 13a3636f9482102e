"""The paired tests of app.core.model_check against SciPy's ttest_rel and a simulation."""

import numpy as np
import pytest
from scipy import stats

from app.core.baselines import fir_kernel, fir_lowpass_mgal
from app.core.model_check import (
    blend_estimates,
    crossover_blend_weight,
    crossover_comparison,
    difference_nll,
    disagreement_ratio,
    fir_noise_bandwidth_hz,
    fir_noise_variance_mgal2,
    fir_smoothing_variance_mgal2,
    flattening_ratio,
    noise_overstated,
    paired_decrease_p,
    paired_rank_p,
    repeat_contrasts,
    smooth_error_bound_mgal2,
)


def test_paired_decrease_p_equals_scipy_one_sided_ttest_rel():
    rng = np.random.default_rng(3)
    before = rng.normal(5.0, 1.0, 40)
    after = before - rng.normal(0.3, 1.0, 40)
    ref = stats.ttest_rel(before, after, alternative="greater").pvalue
    np.testing.assert_allclose(paired_decrease_p(before, after), ref, rtol=1e-12)
    # with fewer independent pairs the same mean difference is less significant
    assert paired_decrease_p(before, after, n_eff=20) > ref
    assert np.isnan(paired_decrease_p([1.0], [0.0]))


def test_crossover_comparison_prefers_the_more_accurate_estimate():
    """Two estimates of 200 crossings: errors of 1 and 2 mGal (independent per line)."""
    rng = np.random.default_rng(0)
    good = rng.normal(0, 1.0, (200, 2))
    bad = rng.normal(0, 2.0, (200, 2))
    d_good, d_bad = good[:, 0] - good[:, 1], bad[:, 0] - bad[:, 1]
    c = crossover_comparison(d_bad, d_good)
    assert c.n == 200 and c.p_value < 1e-6
    np.testing.assert_allclose([c.rms_a_mgal, c.rms_b_mgal], [2 * np.sqrt(2), np.sqrt(2)], rtol=0.15)
    assert crossover_comparison(d_good, d_bad).p_value > 0.99


def test_crossover_blend_weight_finds_the_least_error_blend_of_correlated_estimates():
    """Two estimates of 20 000 crossings whose line errors share a part: e_a = c + u_a,
    e_b = c + u_b with std(c) = 1, std(u_a) = 2, std(u_b) = 1 (independent per line).  The
    least-variance blend w·e_a + (1 − w)·e_b has w = var(u_b) / (var(u_a) + var(u_b)) = 0.2
    (the shared part c is in both and the same in every blend); the weight is found from the
    crossover differences alone, and the blend's error is the analytic minimum."""
    rng = np.random.default_rng(11)
    n = 20_000
    c = rng.normal(0, 1.0, (n, 2))
    e_a = c + rng.normal(0, 2.0, (n, 2))
    e_b = c + rng.normal(0, 1.0, (n, 2))
    d_a, d_b = e_a[:, 0] - e_a[:, 1], e_b[:, 0] - e_b[:, 1]
    w = crossover_blend_weight(d_a, d_b)
    assert abs(w - 0.2) < 0.02
    blend = w * e_a + (1 - w) * e_b
    # var = 1 + w²·4 + (1 − w)²·1, minimum 1 + 0.8 at w = 0.2
    np.testing.assert_allclose(np.var(blend), 1.8, rtol=0.03)
    assert np.var(blend) < np.var(e_b) < np.var(e_a)
    # it is the argmin of the blend's crossover mean square (brute force over w)
    grid = np.linspace(0, 1, 2001)
    ms = [np.var(g * d_a + (1 - g) * d_b) for g in grid]
    assert abs(grid[int(np.argmin(ms))] - w) < 1e-3
    # symmetric: a's weight seen from b
    np.testing.assert_allclose(crossover_blend_weight(d_b, d_a), 1 - w, atol=1e-12)


def test_crossover_blend_weight_edges():
    """Clipped to [0, 1]; NaN pairs left out; equal differences give 0; too few give NaN."""
    rng = np.random.default_rng(2)
    d_b = rng.normal(0, 1.0, 500)
    # a = b + a large independent error, positively tied to b: the unclipped optimum is < 0
    d_a = 3.0 * d_b + rng.normal(0, 1.0, 500)
    assert crossover_blend_weight(d_a, d_b) == 0.0
    assert crossover_blend_weight(d_b, d_a) == 1.0
    assert crossover_blend_weight(d_b, d_b) == 0.0
    d_a2 = rng.normal(0, 1.0, 500)
    with_nan = d_a2.copy()
    with_nan[:7] = np.nan
    np.testing.assert_allclose(crossover_blend_weight(with_nan, d_b), crossover_blend_weight(d_a2[7:], d_b[7:]))
    assert np.isnan(crossover_blend_weight([1.0, 2.0], [0.0, 1.0]))
    with pytest.raises(ValueError, match="one length"):
        crossover_blend_weight(np.ones(4), np.ones(5))


def test_blend_estimates_is_the_mean_and_std_of_the_two_point_mixture():
    """Draws of the mixture (a + N(0, s²) with probability w, b + N(0, s²) otherwise): their
    mean and std per epoch are the blend and its std; NaN in a leaves b; bad weights raise."""
    rng = np.random.default_rng(5)
    a, b, s = np.array([3.0, -1.0, 10.0]), np.array([1.0, 2.0, 10.0]), np.array([0.5, 2.0, 1.0])
    w, n = 0.3, 400_000
    pick_a = rng.random((n, 3)) < w
    draws = np.where(pick_a, a, b) + rng.normal(0.0, 1.0, (n, 3)) * s
    est, std = blend_estimates(a, b, s, w)
    np.testing.assert_allclose(est, draws.mean(axis=0), atol=0.01)
    np.testing.assert_allclose(std, draws.std(axis=0), rtol=0.005)
    est2, std2 = blend_estimates(np.array([np.nan, 4.0, 1.0]), b, s, w)
    assert est2[0] == b[0] and std2[0] == s[0]
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="blend weight"):
            blend_estimates(a, b, s, bad)
    with pytest.raises(ValueError, match="one length"):
        blend_estimates(a, b[:2], s, w)


def test_disagreement_ratio_matches_its_analytic_value():
    """estimate = s + e_a, fir = s + e_f, independent: the ratio is
    sqrt((σ_a² + σ_f²) / (σ_s² + σ_f²)) (large-sample value); means do not matter."""
    rng = np.random.default_rng(5)
    n = 400_000
    s = rng.normal(0.0, 3.0, n)
    for sa, sf in ((1.0, 0.5), (4.0, 1.0), (2.0, 3.0)):
        est = 10.0 + s + rng.normal(0.0, sa, n)
        fir = -5.0 + s + rng.normal(0.0, sf, n)
        want = np.sqrt((sa ** 2 + sf ** 2) / (9.0 + sf ** 2))
        assert disagreement_ratio(est, fir) == pytest.approx(want, rel=0.01)
    assert np.isnan(disagreement_ratio(np.ones(5), np.ones(5)))
    assert np.isnan(disagreement_ratio(np.arange(20.0), np.ones(20)))
    with pytest.raises(ValueError, match="shape"):
        disagreement_ratio(np.ones(20), np.ones(21))


def test_paired_rank_p_matches_scipy_and_holds_its_level():
    """The signed-rank p against SciPy's wilcoxon, its false-alarm rate under the null
    (same distribution, 2000 draws of 30 pairs) and ties."""
    rng = np.random.default_rng(11)
    a, b = rng.normal(0, 2.0, 30), rng.normal(0, 1.0, 30)
    ref = stats.wilcoxon(np.abs(a) - np.abs(b), alternative="greater").pvalue
    np.testing.assert_allclose(paired_rank_p(np.abs(a), np.abs(b)), ref, rtol=1e-12)
    p0 = np.array([paired_rank_p(np.abs(rng.standard_t(3, 30)), np.abs(rng.standard_t(3, 30)))
                   for _ in range(2000)])
    # binomial 99.9 % band around 5 %: 0.034-0.068
    assert 0.034 < np.mean(p0 < 0.05) < 0.068
    assert paired_rank_p([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == 0.5
    assert np.isnan(paired_rank_p([1.0], [0.0]))


def test_crossover_comparison_rank_test_sees_through_one_wild_crossover():
    """An estimate with twice FIR's error at every crossover, one of its crossovers 60 mGal
    off: the squared differences' t-test loses its power (the outlier dominates their
    variance), the signed ranks do not.  Power over 500 simulated surveys of 30 crossovers."""
    rng = np.random.default_rng(2)
    hits_t = hits_rank = 0
    for _ in range(500):
        d_fir = rng.normal(0, 1.0, 30)
        d_est = rng.normal(0, 2.0, 30)
        d_est[0] = 60.0  # one wild crossover, in the estimate
        c = crossover_comparison(d_est, d_fir)
        hits_t += c.p_value < 0.05
        hits_rank += c.p_rank < 0.05
    assert hits_rank / 500 > 0.8
    assert hits_t / 500 < 0.2


def test_significantly_worse_takes_the_ranks_only_when_the_rms_agrees():
    """30 crossovers, the estimate's differences 1.5× FIR's at every crossing but FIR with two
    wild ±40 mGal crossovers: the ranks say the estimate is worse, its crossover RMS says it
    is better — not significantly worse.  Without them both agree — worse."""
    from app.core.model_check import significantly_worse

    rng = np.random.default_rng(4)
    base = rng.normal(0, 1.0, 30)
    d_est, d_fir = 1.5 * base, base.copy()
    d_fir[:2] = 40.0, -40.0
    c = crossover_comparison(d_est, d_fir)
    assert c.p_rank < 0.05 and c.rms_a_mgal < c.rms_b_mgal and c.p_value > 0.5
    assert not significantly_worse(c, 0.05)
    c2 = crossover_comparison(d_est, base)
    assert c2.p_rank < 0.05 and c2.rms_a_mgal > c2.rms_b_mgal
    assert significantly_worse(c2, 0.05)


def test_crossover_rms_is_the_demeaned_rms_of_the_finite_differences():
    """Hand-computed: differences 1, 3, NaN, 5 → mean 3, deviations −2, 0, 2 → RMS sqrt(8/3)."""
    from app.core.model_check import crossover_rms_mgal

    assert crossover_rms_mgal([1.0, 3.0, np.nan, 5.0]) == pytest.approx(np.sqrt(8.0 / 3.0))
    assert np.isnan(crossover_rms_mgal([np.nan]))


def test_smooth_error_bound_holds_for_a_conditional_mean():
    """x ~ N(0, 4), FIR = x + N(0, 1), data z = x + N(0, 16): the conditional mean
    x̂ = 4/20 z has Var x̂ = 0.8 and error variance 4·16/20 = 3.2 (analytic); the bound
    Var(FIR) − Var(x̂) = 5 − 0.8 = 4.2 lies above it.  A flat estimate's error is the anomaly:
    bound 5 ≥ 4.  Fewer than 10 finite epochs: NaN."""
    rng = np.random.default_rng(11)
    n = 400_000
    x = rng.normal(0.0, 2.0, n)
    fir = x + rng.normal(0.0, 1.0, n)
    xh = 0.2 * (x + rng.normal(0.0, 4.0, n))
    b = smooth_error_bound_mgal2(xh, fir)
    assert b == pytest.approx(4.2, rel=0.01)
    assert np.var(xh - x) == pytest.approx(3.2, rel=0.01) and np.var(xh - x) < b
    assert smooth_error_bound_mgal2(np.zeros(n), fir) == pytest.approx(5.0, rel=0.01)
    assert np.isnan(smooth_error_bound_mgal2(np.full(9, 1.0), np.arange(9.0)))


def _crossovers(rng, n, noise_var_a, noise_var_b, shared_var=0.0, offsets_var=0.0):
    """FIR crossover differences of two lines: independent noise, a shared smoothing error
    (cancels) and, optionally, line offsets (drift)."""
    shared = rng.normal(0.0, np.sqrt(shared_var), n) if shared_var else 0.0
    ea = shared + rng.normal(0.0, np.sqrt(noise_var_a), n) + rng.normal(0.0, np.sqrt(offsets_var), n)
    eb = shared + rng.normal(0.0, np.sqrt(noise_var_b), n)
    return ea - eb


def test_noise_overstated_holds_its_level_and_detects_a_3x_overstatement():
    """Differences of independent Gaussian noises: with the true noise predicted, the test
    says "over-stated" at its level α (binomial: ≤ 0.065 of 2000 at α = 0.05); with 3× the
    variance predicted it says so (≥ 95 % with 30 crossovers).  A shared error cancels in the
    differences and does not change that; line offsets only make the test more cautious."""
    rng = np.random.default_rng(11)
    n, va, vb, reps = 30, 4.0, 9.0, 2000
    pred = np.full(n, va + vb)
    fa = np.mean([noise_overstated(_crossovers(rng, n, va, vb, shared_var=25.0), pred).overstated
                  for _ in range(reps)])
    assert 0.035 < fa < 0.065
    hit = np.mean([noise_overstated(_crossovers(rng, n, va, vb, shared_var=25.0), 3.0 * pred).overstated
                   for _ in range(reps)])
    assert hit > 0.95
    hit_drift = np.mean([noise_overstated(_crossovers(rng, n, va, vb, offsets_var=13.0), 3.0 * pred).overstated
                         for _ in range(reps)])
    assert hit_drift < hit
    b = noise_overstated(_crossovers(rng, n, va, vb), pred)
    assert b.bound_mgal2 == pytest.approx(b.crossover_ms_mgal2 * n / stats.chi2.ppf(0.05, n))
    # too few crossovers: never
    assert not noise_overstated(np.array([0.1, -0.1, 0.2]), np.full(3, 1e6)).overstated
    with pytest.raises(ValueError):
        noise_overstated(np.zeros(5), np.zeros(4))


def test_fir_smoothing_variance_of_sinusoids_follows_the_kernel_response():
    """var(a − FIR(a)) of a sinusoid of amplitude A is A²/2 · |1 − H(f)|², H the FIR kernel's
    frequency response (computed here from its taps): nearly all of a 30 s period, nearly none
    of a 2000 s period, about half the amplitude near the 100 s cut-off."""
    dt, A = 0.1, 5.0
    t = np.arange(0, 6000.0, dt)
    h = fir_kernel(dt, 100.0)
    k = np.arange(h.size) - h.size // 2
    for period in (30.0, 100.0, 2000.0):
        f = 1.0 / period
        H = np.abs(np.sum(h * np.exp(-2j * np.pi * f * k * dt)))
        a = A * np.sin(2 * np.pi * t / period)
        inner = slice(h.size, -h.size)       # away from the renormalised ends
        assert np.var((a - fir_lowpass_mgal(a, dt, 100.0))[inner]) == pytest.approx(A ** 2 / 2 * (1 - H) ** 2,
                                                                                  rel=0.02, abs=1e-3)
    v = fir_smoothing_variance_mgal2(A * np.sin(2 * np.pi * t / 30.0), dt)
    assert v == pytest.approx(A ** 2 / 2, rel=0.02)
    assert np.isnan(fir_smoothing_variance_mgal2(np.full(10, np.nan), dt))


def test_repeat_contrasts_cancel_the_anomaly_and_keep_each_pass_offset():
    """Passes flown both ways over one anomaly, each with its own constant offset: the
    anomaly cancels and the contrasts are the Helmert contrasts of the offsets (analytic)."""
    s = np.linspace(0.0, 40_000.0, 801)
    anomaly = 20.0 * np.sin(s / 3000.0)
    offsets = np.array([1.0, -2.0, 0.5, 3.0])
    along = [s, s[::-1], s + 7.0, s[::-1] - 3.0]
    values = [np.interp(a, s, anomaly) + c for a, c in zip(along, offsets)]
    got = repeat_contrasts(along, values, 5000.0).reshape(3, -1)
    for k in (1, 2, 3):
        expect = (offsets[:k].sum() - k * offsets[k]) / np.sqrt(k * (k + 1))
        np.testing.assert_allclose(got[k - 1], expect, atol=0.02)   # linear interpolation of the sine
    values[2][100:110] = np.nan                                     # a gap drops its positions only
    assert repeat_contrasts(along, values, 5000.0).size == got.size - 3
    assert repeat_contrasts([s, s + 50_000.0], values[:2], 5000.0).size == 0   # no common interval
    with pytest.raises(ValueError):
        repeat_contrasts(along, values, 0.0)


@pytest.mark.parametrize("order", [0, 1, 2])
def test_repeat_contrasts_every_cutoff_period_hold_the_chi2_level(order):
    """Four 600 s passes whose FIR 100 s noise is white, f² or f⁴ z noise behind the filter
    (known variance): contrasts sampled every 100 s of flight keep noise_overstated near its
    level α = 0.05 (binomial band for 400 draws), and a 3x over-statement is seen ≥ 85 %."""
    rng = np.random.default_rng(5 + order)
    dt, n, v = 0.5, 1200, 100.0

    def fir_noise():
        x = np.diff(rng.standard_normal(n + 800 + order), order)
        return fir_lowpass_mgal(x, dt, 100.0)[400:-400]      # a stretch cut out of a flight

    var = np.mean([np.mean(fir_noise() ** 2) for _ in range(200)])
    s = np.arange(n) * dt * v
    fa = hit = 0
    for _ in range(400):
        c = repeat_contrasts([s, s[::-1], s, s[::-1]], [fir_noise() for _ in range(4)], 100.0 * v)
        fa += noise_overstated(c, np.full(c.size, var)).overstated
        hit += noise_overstated(c, np.full(c.size, 3.0 * var)).overstated
    assert c.size == 18
    assert 0.02 <= fa / 400 <= 0.085
    assert hit / 400 >= 0.85


def test_difference_nll_is_the_gaussian_log_density():
    rng = np.random.default_rng(2)
    d = rng.normal(0.0, 2.0, 50)
    v = rng.uniform(1.0, 5.0, 50)
    assert difference_nll(d, v) == pytest.approx(-np.mean(stats.norm.logpdf(d, scale=np.sqrt(v))))
    # the variance that explains the differences best is their mean square
    grid = np.geomspace(0.5, 20.0, 400)
    best = grid[np.argmin([difference_nll(d, np.full(50, g)) for g in grid])]
    assert best == pytest.approx(np.mean(d ** 2), rel=0.02)


def _fir_noise(rng, n_lines: int, n: int, dt_s: float, R_cm2s2: float = 1.0) -> np.ndarray:
    """FIR 100 s output of white-velocity noise (the paper's model), (n_lines, n), from
    records long enough that the kernel sees no edge."""
    pad = int(200 / dt_s)
    v = rng.normal(0.0, np.sqrt(R_cm2s2), (n_lines, n + 2 * pad + 1))
    z = np.diff(v, axis=1) * (1000.0 / dt_s)          # cm/s per step -> mGal
    return np.array([fir_lowpass_mgal(row, dt_s, 100.0)[pad:pad + n] for row in z])


def test_fir_noise_bandwidth_gives_the_sample_variance_scatter():
    """Over T seconds the FIR's noise holds ν = 2·B·T independent samples: the sample variance
    of a stretch scatters as χ²_ν/ν about the model's variance — its relative variance is 2/ν
    (measured on 3000 simulated stretches of 300 s and 1200 s)."""
    from app.core.noise_model import white_velocity

    dt = 0.5
    noise = white_velocity(dt)
    B = fir_noise_bandwidth_hz(noise, dt, 100.0)
    assert 0.005 < B < 0.02                            # of the order of the FIR's pass band
    rng = np.random.default_rng(11)
    for T in (300.0, 1200.0):
        x = _fir_noise(rng, 3000, int(T / dt), dt)
        s2 = x.var(axis=1)
        nu = 2 * B * T
        assert np.mean(s2) == pytest.approx(fir_noise_variance_mgal2(noise, 1.0, dt), rel=0.03)
        assert np.var(s2) / np.mean(s2) ** 2 == pytest.approx(2 / nu, rel=0.15)


def test_flattening_bound_holds_its_level_and_still_finds_a_flattened_estimate():
    """An estimate keeping 60 % of the anomaly's variance (not flattened by the 0.5 rule) on a
    300 s line, the anomaly 4-8x the FIR's noise variance: the point ratio, scattered by the
    FIR's noise over ~7 independent samples, calls it flattened on about a tenth of the lines
    (31 of 286 here); the bound at 95 % on at most 5 % (none here).  A collapsed estimate (1 % of the variance) on the same
    lines, and one keeping 10 % on 1500 s lines, are still called flattened (≥ 90 %)."""
    from app.core.noise_model import white_velocity

    dt = 0.5
    noise = white_velocity(dt)
    B = fir_noise_bandwidth_hz(noise, dt, 100.0)
    sigma2 = fir_noise_variance_mgal2(noise, 1.0, dt)
    rng = np.random.default_rng(5)
    for T, kept in ((300.0, 0.6), (300.0, 0.01), (1500.0, 0.1)):
        n, n_lines = int(T / dt), 400
        t = np.arange(n) * dt
        point = bound = tried = 0
        for x_noise in _fir_noise(rng, n_lines, n, dt):
            # an anomaly inside the FIR's pass band, 4-8x its noise variance
            per = rng.uniform(200, 500, 3)
            amp = np.sqrt(rng.uniform(4, 8) * sigma2 / 1.5)
            truth = sum(amp * np.sin(2 * np.pi * t / p_ + rng.uniform(0, 2 * np.pi)) for p_ in per)
            fir = fir_lowpass_mgal(truth, dt, 100.0) + x_noise
            est = np.sqrt(kept) * (truth - truth.mean())
            f = flattening_ratio(est, fir, sigma2, min_snr=2.0, independent_samples=2 * B * T)
            if not f.detectable:
                continue
            tried += 1
            point += f.ratio < 0.5
            bound += f.ratio_bound < 0.5
        assert tried > 0.6 * n_lines
        if kept == 0.6:
            assert point > 0.05 * tried               # the sampling scatter fools the point ratio
            assert bound <= 0.05 * tried
        else:
            assert bound >= 0.9 * tried


def test_flattening_ratio_without_samples_is_the_point_ratio():
    rng = np.random.default_rng(1)
    est, fir = rng.normal(0, 1, 500), rng.normal(0, 3, 500)
    f = flattening_ratio(est, fir, 1.0)
    assert f.ratio_bound == f.ratio == pytest.approx(np.var(est) / (np.var(fir) - 1.0))
    g = flattening_ratio(est, fir, 1.0, independent_samples=1e9)   # infinitely many: the bound is the ratio
    assert g.ratio_bound == pytest.approx(f.ratio, rel=1e-3)
    assert flattening_ratio(est, fir, 1.0, independent_samples=3).ratio_bound > f.ratio
    with pytest.raises(ValueError, match="confidence"):
        flattening_ratio(est, fir, 1.0, independent_samples=5, confidence=1.0)


def test_repeat_noise_variance_is_each_pass_own_and_blind_to_the_anomaly():
    """Four passes of one track: a common anomaly of 20 mGal std and white noise of 1, 2, 3 and
    6 mGal on the passes.  The three-cornered hat gives each pass's own noise variance (within
    the sampling error of 4000 points), the same to rounding when the anomaly is 100× larger
    (pass differences cancel it); two passes share their difference's variance equally."""
    from app.core.model_check import repeat_noise_variance_mgal2

    rng = np.random.default_rng(11)
    n = 4000
    anomaly = 20.0 * np.sin(np.linspace(0, 9 * np.pi, n)) + rng.normal(0, 5.0, n).cumsum() / 30
    sd = np.array([1.0, 2.0, 3.0, 6.0])
    noise = rng.normal(0.0, 1.0, (4, n)) * sd[:, None]
    est = repeat_noise_variance_mgal2(anomaly + noise)
    assert est == pytest.approx(sd ** 2, rel=0.15, abs=0.3)
    assert repeat_noise_variance_mgal2(100 * anomaly + noise) == pytest.approx(est, abs=1e-6)
    two = repeat_noise_variance_mgal2(anomaly + noise[:2])
    assert two == pytest.approx(np.full(2, np.var(noise[0] - noise[1]) / 2))
    assert np.isnan(repeat_noise_variance_mgal2((anomaly + noise)[:, :5])).all()
    with pytest.raises(ValueError):
        repeat_noise_variance_mgal2(anomaly[None, :])


def test_leave_one_out_msd_by_hand():
    """Three passes at two positions: each pass and reference about its mean, then the mean
    square difference from the other two passes' mean reference, computed by hand."""
    from app.core.model_check import leave_one_out_msd_mgal2

    v = np.array([[1.0, 3.0], [0.0, 4.0], [2.0, 2.0]])
    r = np.array([[0.0, 2.0], [5.0, 1.0], [1.0, 1.0]])
    # about their means: v -> [-1, 1], [-2, 2], [0, 0]; r -> [-1, 1], [2, -2], [0, 0]
    # other passes' mean of r: pass 0 -> [1, -1], pass 1 -> [-0.5, 0.5], pass 2 -> [0.5, -0.5]
    expected = [((-1 - 1) ** 2 + (1 + 1) ** 2) / 2, ((-2 + 0.5) ** 2 + (2 - 0.5) ** 2) / 2,
                ((0 - 0.5) ** 2 + (0 + 0.5) ** 2) / 2]
    assert leave_one_out_msd_mgal2(v, r) == pytest.approx(expected)
    # a position where any value is missing is left out everywhere
    vn = np.column_stack([v, [np.nan, 7.0, 7.0]])
    rn = np.column_stack([r, [9.0, 9.0, 9.0]])
    assert leave_one_out_msd_mgal2(vn, rn) == pytest.approx(expected)
    with pytest.raises(ValueError):
        leave_one_out_msd_mgal2(v[:1], r[:1])
    with pytest.raises(ValueError):
        leave_one_out_msd_mgal2(v, r[:, :1])


def test_leave_one_out_msd_differences_are_the_mean_square_error_differences():
    """Four passes of a common anomaly (30 mGal std); a reference with white noise of 8 mGal on
    each pass and no smoothing error; estimate a with 1 mGal of noise, estimate b with 2 mGal
    and a shared error (a bias of 1.5 mGal std the passes repeat).  The difference of the two
    estimates' figures is their difference in mean square error against the truth,
    1 − (4 + 2.25) mGal², though the reference's noise alone is 64/3 mGal² in each figure."""
    from app.core.model_check import leave_one_out_msd_mgal2

    rng = np.random.default_rng(5)
    k, n = 4, 50_000
    g = 30.0 * np.sin(np.linspace(0, 40 * np.pi, n))
    bias = 1.5 * np.sin(np.linspace(0, 97 * np.pi, n) + 0.3) * np.sqrt(2.0)
    ref = g + rng.normal(0.0, 8.0, (k, n))
    a = g + rng.normal(0.0, 1.0, (k, n))
    b = g + bias + rng.normal(0.0, 2.0, (k, n))
    d = leave_one_out_msd_mgal2(a, ref) - leave_one_out_msd_mgal2(b, ref)
    true = np.mean((a - g) ** 2, axis=1) - np.mean((b - g - np.mean(b - g, axis=1, keepdims=True)) ** 2, axis=1)
    assert np.mean(d) == pytest.approx(1.0 - 6.25, abs=0.3)
    assert d == pytest.approx(true, abs=0.4)
    assert leave_one_out_msd_mgal2(a, ref) == pytest.approx(1.0 + 64.0 / 3.0, rel=0.05)


def test_repeat_blend_weight_is_the_least_error_blend_of_independent_estimates():
    """Four passes; estimates a and b with independent errors of 2 and 1 mGal std (b's partly
    shared by the passes: a smoothing error), a reference with 8 mGal of noise.  The weight of
    b is the truth's least-error weight σ_a²/(σ_a² + σ_b²) = 0.8; swapped, 0.2; an estimate
    against itself, 0; one that would extrapolate beyond b, clipped at 1."""
    from app.core.model_check import repeat_blend_weight

    rng = np.random.default_rng(8)
    k, n = 4, 100_000
    g = 25.0 * np.sin(np.linspace(0, 60 * np.pi, n))
    ref = g + rng.normal(0.0, 8.0, (k, n))
    a = g + rng.normal(0.0, 2.0, (k, n))
    shared = 0.6 * np.sin(np.linspace(0, 173 * np.pi, n)) * np.sqrt(2.0)
    b = g + shared + rng.normal(0.0, 0.8, (k, n))
    assert repeat_blend_weight(a, b, ref) == pytest.approx(0.8, abs=0.02)
    # two tracks: the sums over both
    assert repeat_blend_weight([a[:, :n // 2], a[:2, n // 2:]], [b[:, :n // 2], b[:2, n // 2:]],
                               [ref[:, :n // 2], ref[:2, n // 2:]]) == pytest.approx(0.8, abs=0.03)
    assert repeat_blend_weight(b, a, ref) == pytest.approx(0.2, abs=0.02)
    assert repeat_blend_weight(a, a, ref) == 0.0
    # b's error half of a's, the same error: the least-error blend would extrapolate (w = 2)
    assert repeat_blend_weight(a, g + 0.5 * (a - g), ref) == 1.0
    with pytest.raises(ValueError):
        repeat_blend_weight(a[:1], b[:1], ref[:1])


def test_leave_one_out_msd_test_finds_the_better_estimate_and_is_calibrated():
    """Four passes of a shared anomaly, a reference with large independent noise per pass, and
    two estimates: with errors of variance 1 and 2 (block-correlated, 50 positions), a finds
    itself better (mean difference about −1, p < 0.05 in most draws); with equal errors the
    one-sided p falls below 0.1 in about a tenth of the draws (0.05–0.17 over 200)."""
    from app.core.model_check import leave_one_out_msd_test

    rng = np.random.default_rng(5)
    K, n, blk = 4, 1000, 50

    def smooth_noise(var):
        w = rng.normal(size=(K, n + blk)) * np.sqrt(var * blk)
        return np.array([np.convolve(x, np.ones(blk) / blk, mode="valid")[:n] for x in w])

    def draw(var_a, var_b):
        g = np.cumsum(rng.normal(size=n)) * 0.1
        ref = g + rng.normal(size=(K, n)) * 5.0
        return g + smooth_noise(var_a), g + smooth_noise(var_b), ref

    found, means = 0, []
    for _ in range(40):
        a, b, r = draw(1.0, 2.0)
        mean, p = leave_one_out_msd_test(a, b, r, blk)
        means.append(mean)
        found += p < 0.05
    assert found >= 30 and -1.3 < np.mean(means) < -0.7, (found, np.mean(means))
    ps = np.array([leave_one_out_msd_test(*draw(1.0, 1.0), blk)[1] for _ in range(200)])
    assert 0.05 < np.mean(ps < 0.1) < 0.17, np.mean(ps < 0.1)
    # lists of tracks, and the guards
    a, b, r = draw(1.0, 2.0)
    m2, p2 = leave_one_out_msd_test([a, a], [b, b], [r, r], blk)
    assert m2 == pytest.approx(leave_one_out_msd_test(a, b, r, blk)[0]) and p2 < 0.05
    assert np.isnan(leave_one_out_msd_test(a[:, :100], b[:, :100], r[:, :100], blk)[1])   # 2 blocks
    with pytest.raises(ValueError):
        leave_one_out_msd_test(a, b, r, 0)


def _test_line_draw(rng, k=4, n=40, shared_a=0.0, ref_noise=13.0):
    """Four passes of one track at n independent positions (a 40 km line holds about 40
    independent stretches of a 100 s low-pass): the anomaly g, an estimate a with
    a shared error (``shared_a`` × a smooth pattern, the same on every pass) and 0.5 mGal of
    pass noise, FIR b with 1.5 mGal of pass noise and a small shared rounding, and a reference
    whose pass noise (``ref_noise``) dwarfs both — a 2 Hz test line's 50 s low-pass of z."""
    x = np.linspace(0, 8 * np.pi, n)
    g = 10.0 * np.sin(x)
    a = g + shared_a * np.sin(3.1 * x) + rng.normal(0.0, 0.5, (k, n))
    b = g - 0.3 * np.sin(x) + rng.normal(0.0, 1.5, (k, n))
    ref = g + rng.normal(0.0, ref_noise, (k, n))
    return g, a, b, ref


def _blend_mse(a, b, g, w):
    """Mean square error of the blend (1 − w)·a + w·b against the anomaly g (mGal²)."""
    return float(np.mean(((1 - w) * a + w * b - g) ** 2))


def test_shrunk_repeat_blend_weight_against_simulated_truth():
    """Over 200 simulated test lines whose estimate is better than FIR (the truth's weight of
    FIR is 0), the passes' raw weight scatters over [0, 1] and its blend loses to the estimate
    alone; shrunk by its jackknife error it is 0 on most draws and its blend's mean square error
    is far closer to the estimate's.  Where the estimate carries a large shared error (4 mGal,
    the truth's weight near 1), the evidence stands out of its scatter and the shrunk weight
    stays near the raw one.  Fewer than 3 passes: no jackknife, the weight is not shrunk."""
    from app.core.model_check import repeat_blend_weight, shrunk_repeat_blend_weight

    rng = np.random.default_rng(47)
    raw, used, mse_raw, mse_used, mse_a = [], [], [], [], []
    for _ in range(200):
        g, a, b, ref = _test_line_draw(rng)
        s = shrunk_repeat_blend_weight(a, b, ref)
        assert s.raw == pytest.approx(repeat_blend_weight(a, b, ref))
        assert 0.0 <= s.weight <= s.raw and len(s.leave_one_out) == 4 and s.se >= 0
        assert s.weight == pytest.approx(s.raw * max(0.0, 1 - s.se ** 2 / s.raw ** 2) if s.raw > 0 else 0.0)
        raw.append(s.raw)
        used.append(s.weight)
        mse_raw.append(_blend_mse(a, b, g, s.raw))
        mse_used.append(_blend_mse(a, b, g, s.weight))
        mse_a.append(_blend_mse(a, b, g, 0.0))
    raw, used = np.array(raw), np.array(used)
    assert np.mean(raw > 0.2) > 0.25                 # the raw weight scatters
    assert np.mean(used == 0.0) > 0.7                # shrunk: mostly the estimate alone
    assert np.mean(mse_used) < 0.85 * np.mean(mse_raw)
    assert np.mean(mse_used) < 1.3 * np.mean(mse_a)
    # a large shared error in the estimate: FIR wins, and the weight survives the shrinkage
    kept = []
    for _ in range(50):
        g, a, b, ref = _test_line_draw(rng, shared_a=4.0)
        s = shrunk_repeat_blend_weight(a, b, ref)
        kept.append((s.raw, s.weight))
    kept = np.array(kept)
    assert np.median(kept[:, 0]) > 0.6 and np.median(kept[:, 1]) > 0.55
    assert np.median(kept[:, 1]) > 0.85 * np.median(kept[:, 0])
    # two passes: nothing to leave out
    g, a, b, ref = _test_line_draw(rng, k=2)
    s = shrunk_repeat_blend_weight(a, b, ref)
    assert s.weight == s.raw and np.isnan(s.se)


def test_crossover_excess_holds_its_level_and_sees_an_understated_std():
    """Differences drawn with the variance the std predicts (unequal from crossover to
    crossover): p < 0.05 on about 5 % of draws, the RMS ratio near 1.  Drawn with 1.5× that
    std at 30 crossovers: the excess is found on most draws.  Fewer degrees of freedom (a
    drift removed) are taken as given."""
    from app.core.model_check import crossover_excess

    rng = np.random.default_rng(21)
    n, draws = 30, 4000
    pv = rng.uniform(1.0, 3.0, n)             # σ_a² + σ_b² at each crossover (mGal²)
    p_null, p_alt, ratios = [], [], []
    for _ in range(draws):
        z = rng.normal(size=n)
        ex = crossover_excess(np.sqrt(pv.mean()) * z, pv)
        p_null.append(ex.p_value)
        ratios.append(ex.rms_ratio)
        p_alt.append(crossover_excess(1.5 * np.sqrt(pv.mean()) * z, pv).p_value)
    assert np.mean(np.array(p_null) < 0.05) == pytest.approx(0.05, abs=0.012)
    assert np.median(ratios) == pytest.approx(1.0, abs=0.03)
    assert np.mean(np.array(p_alt) < 0.05) > 0.9
    # the statistic is χ² with the given dof: Σd²/mean(pv)
    d = rng.normal(size=n)
    ex = crossover_excess(d, pv, dof=25)
    t = np.sum(d ** 2) / pv.mean()
    assert ex.dof == 25 and ex.p_value == pytest.approx(stats.chi2.sf(t, 25))
    assert ex.rms_ratio == pytest.approx(np.sqrt(t / 25))
    # NaN rows are left out; nothing usable gives NaN
    d[3] = np.nan
    assert crossover_excess(d, pv).n == n - 1
    assert np.isnan(crossover_excess(np.full(3, np.nan), np.ones(3)).p_value)
    with pytest.raises(ValueError, match="one shape"):
        crossover_excess(d, pv[:-1])


def test_crossover_level_scale_takes_the_least_mean_square_when_significant():
    """Three estimates at the same crossovers: scale 0.25's differences half the size of scale
    1's (taken, p small), scale 0.0625's rougher again; with every scale alike the best is
    taken only by chance (p large on most draws)."""
    from app.core.model_check import crossover_level_scale

    rng = np.random.default_rng(4)
    n = 40
    base = rng.normal(size=n)
    diffs = {1.0: 2.0 * base + 0.3 * rng.normal(size=n), 0.25: base, 0.0625: 1.5 * base + 0.3 * rng.normal(size=n)}
    res = crossover_level_scale(diffs)
    assert res.scale == 0.25 and res.p_value < 0.01
    assert res.rms_mgal[0.25] == pytest.approx(np.sqrt(np.mean(base ** 2)))
    ps = []
    for _ in range(400):
        alike = {s: rng.normal(size=n) for s in (1.0, 0.5, 0.25)}
        r = crossover_level_scale(alike)
        ps.append(1.0 if r.scale == 1.0 else r.p_value)
    assert np.mean(np.array(ps) < 0.05) < 0.12          # a best picked from three: some selection, no more
    # scale 1 best: kept, no test
    assert crossover_level_scale({1.0: base, 0.5: 2 * base}).scale == 1.0
    with pytest.raises(ValueError, match="scale 1"):
        crossover_level_scale({0.5: base})


def test_the_noise_floor_is_the_root_of_the_crossovers_ratio():
    """ratio(k) = √(A / (B + 2ᵏ)) falls through 1 at 2ᵏ = A − B (closed form): the search returns
    the bracket's upper end, within its final width above the root, at a ratio ≤ 1."""
    from app.core.model_check import crossover_noise_floor

    A, B = 40.0, 3.0
    fit = crossover_noise_floor(lambda k: np.sqrt(A / (B + 2.0 ** k)), log2_start=-10.0, log2_max=10.0, step=2.0,
                                refine=4)
    root = np.log2(A - B)
    assert fit.converged and fit.ratio <= 1.0
    assert root <= fit.log2_weight <= root + 2.0 / 2 ** 4 + 1e-12
    assert len(fit.evaluations) == int(np.ceil((root + 10.0) / 2.0)) + 1 + 4
    # no excess at the start: the start; an excess no floor removes: the largest, not converged
    assert crossover_noise_floor(lambda k: 0.9).log2_weight == -10.0
    stuck = crossover_noise_floor(lambda k: 2.0, log2_max=4.0)
    assert not stuck.converged and stuck.log2_weight == 4.0 and stuck.ratio == 2.0
    assert crossover_noise_floor(lambda k: np.nan).converged
    with pytest.raises(ValueError):
        crossover_noise_floor(lambda k: 1.0, step=0.0)
