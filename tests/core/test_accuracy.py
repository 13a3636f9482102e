"""Tests of the accuracy measures against hand computations and simulations."""

import numpy as np
import pytest
from scipy.signal import lfilter

from app.core.accuracy import (
    GridAccuracy,
    crossover_rms,
    crossover_std_factor,
    grid_accuracy_in_hull,
    grid_rms_in_hull,
    internal_accuracy,
    line_demeaned,
    mean_error_vs_reference,
    noise_excess_p_value,
    points_in_hull,
    repeat_error_parts,
    repeat_line_accuracy,
    repeat_pass_noise_ratio,
    repeat_pass_noise_var,
    repeat_pass_std_scales,
    rms_vs_reference,
    std_calibration,
    track_axes,
)


def test_internal_accuracy_by_hand():
    # means (2, 3); deviations ±1 everywhere: Σ = 4, n (K-1) = 2 -> sqrt(2)
    assert internal_accuracy([[1.0, 2.0], [3.0, 4.0]]) == pytest.approx(np.sqrt(2.0))
    # K = 3 at one point: values 0, 3, 6 -> mean 3, Σ = 18, n(K-1) = 2 -> 3
    assert internal_accuracy([[0.0], [3.0], [6.0]]) == pytest.approx(3.0)
    with pytest.raises(ValueError):
        internal_accuracy([[1.0, 2.0]])


def _smooth_noise(rng, n, sigma, corr_samples):
    """AR(1)-filtered white noise scaled to std sigma (correlated over corr_samples)."""
    a = np.exp(-1.0 / corr_samples)
    x = lfilter([np.sqrt(1 - a * a)], [1, -a], rng.standard_normal(n + 5 * corr_samples))
    return sigma * x[5 * corr_samples:]


def test_repeat_line_accuracy_recovers_known_noise():
    rng = np.random.default_rng(0)
    sigma = 0.7
    def truth(s):
        return 15 * np.sin(s / 9.0) + 4 * np.cos(s / 2.3)

    es, ns, gs = [], [], []
    direction = np.array([np.cos(0.4), np.sin(0.4)])
    for k in range(6):
        # 100 km track, 10 m sampling, start offsets and directions differ, small cross-track wobble
        s = np.arange(-1.0 + 0.3 * k, 101.0 - 0.2 * k, 0.01)
        if k % 2:
            s = s[::-1]
        cross = 0.05 * np.sin(s / 7.0 + k)
        e = 500.0 + s * direction[0] - cross * direction[1]
        n = 7000.0 + s * direction[1] + cross * direction[0]
        es.append(e)
        ns.append(n)
        gs.append(truth(s) + _smooth_noise(rng, s.size, sigma, 100))   # noise correlated over 1 km
    res = repeat_line_accuracy(es, ns, gs, step_km=0.1)
    assert res.n_repeats == 6
    # same thing from a list of (e, n, dg) tuples; float() gives ε
    assert float(repeat_line_accuracy(list(zip(es, ns, gs)))) == res.epsilon_mgal
    assert res.along_km[-1] == pytest.approx(99.99 - 0.5, abs=0.12)   # common interval [0.5, 99.99]
    assert res.epsilon_mgal == pytest.approx(sigma, rel=0.1)
    # the mean of the repeats tracks the truth (the principal axis may point either way)
    fwd = rms_vs_reference(res.mean_mgal, truth(0.5 + res.along_km))
    bwd = rms_vs_reference(res.mean_mgal, truth(99.99 - res.along_km))
    assert min(fwd, bwd) < sigma


def test_repeat_line_errors():
    with pytest.raises(ValueError, match="at least 2"):
        repeat_line_accuracy([np.arange(3.0)], [np.zeros(3)], [np.zeros(3)])
    with pytest.raises(ValueError, match="common"):
        repeat_line_accuracy([np.arange(3.0), np.arange(3.0) + 10], [np.zeros(3)] * 2, [np.zeros(3)] * 2)


def test_crossover_rms_and_reference():
    assert crossover_rms([3.0, -4.0, np.nan]) == pytest.approx(np.sqrt(12.5))
    with pytest.raises(ValueError):
        crossover_rms([np.nan])
    assert rms_vs_reference([1.0, 2.0, np.nan], [0.0, 0.0, 5.0]) == pytest.approx(np.sqrt(2.5))


def test_std_calibration_gaussian():
    rng = np.random.default_rng(1)
    s = rng.uniform(0.5, 2.0, 200_000)
    e = rng.standard_normal(s.size) * s
    assert std_calibration(e, s, 2.0) == pytest.approx(0.9545, abs=0.003)
    assert std_calibration(e, s, 1.0) == pytest.approx(0.6827, abs=0.003)
    assert std_calibration(e, 2 * s, 1.0) == pytest.approx(0.9545, abs=0.003)


def test_grid_rms_inside_hull_of_lines():
    # lines on the border of the square [0, 10]²
    t = np.linspace(0, 10, 101)
    le = np.concatenate([t, t, np.zeros_like(t), np.full_like(t, 10.0)])
    ln = np.concatenate([np.zeros_like(t), np.full_like(t, 10.0), t, t])
    x = np.arange(-5.0, 15.5, 1.0)
    y = np.arange(-5.0, 15.5, 1.0)
    X, Y = np.meshgrid(x, y)
    inside = (X >= 0) & (X <= 10) & (Y >= 0) & (Y <= 10)
    est = np.where(inside, 1.0, 100.0)
    est[0, 0] = np.nan
    assert grid_rms_in_hull(x, y, est, np.zeros_like(est), le, ln) == pytest.approx(1.0)
    assert points_in_hull(5.0, 5.0, le, ln) and not points_in_hull(11.0, 5.0, le, ln)
    with pytest.raises(ValueError, match="shape"):
        grid_rms_in_hull(x, y, est[1:], est[1:], le, ln)


def test_crossover_std_factor_recovers_a_misstated_std():
    """Two crossing lines' errors with true std σ and correlation ρ; the stated std is
    off by a known factor: the crossover factor must undo it (simulation, known truth)."""
    rng = np.random.default_rng(7)
    n, rho = 4000, 0.25
    sigma = rng.uniform(1.0, 3.0, n)
    shared = rng.standard_normal(n) * np.sqrt(rho)
    ea = sigma * (shared + rng.standard_normal(n) * np.sqrt(1 - rho))
    eb = sigma * (shared + rng.standard_normal(n) * np.sqrt(1 - rho))
    for stated_over_true in (0.5, 1.6):
        stated = sigma * stated_over_true
        res = crossover_std_factor(ea - eb, 2 * stated ** 2, shared_fraction=rho, min_n_narrow=100,
                                   min_factor=0.1)
        assert res["factor"] == pytest.approx(1 / stated_over_true, rel=0.04)
    # with few crossovers it only widens; it never narrows below min_factor
    few = crossover_std_factor((ea - eb)[:40], 2 * (3 * sigma[:40]) ** 2, rho, min_n_narrow=100)
    assert few["factor"] == 1.0
    many = crossover_std_factor(ea - eb, 2 * (3 * sigma) ** 2, rho, min_n_narrow=100, min_factor=0.6)
    assert many["factor"] == 0.6
    assert crossover_std_factor(ea[:5] - eb[:5], np.ones(5), min_n=10) == {"n": 5}
    assert crossover_std_factor(ea[:1] - eb[:1], np.ones(1)) == {"n": 1}
    with pytest.raises(ValueError):
        crossover_std_factor(ea, np.ones(3))


def test_crossover_std_factor_with_few_crossovers_restores_coverage():
    """A small survey: 3 crossovers per trial, the lines' errors Gaussian with known std.
    A std stated at half the true one covers |e| < 2σ on 68 % of points (analytic:
    P(|N(0,1)| < 1)); widened by its own 3 crossovers it must cover ≥ 85 % on average (a factor from three
    differences scatters: 88 % here).
    A calibrated std (95.4 %) must stay below 99 % on average (widening by chance)."""
    from scipy.stats import norm

    rng = np.random.default_rng(11)
    rho, trials = 0.2, 4000
    cov = {}
    for stated_over_true in (0.5, 1.0):
        hits = []
        for _ in range(trials):
            shared = rng.standard_normal(3) * np.sqrt(rho)
            ea = shared + rng.standard_normal(3) * np.sqrt(1 - rho)
            eb = shared + rng.standard_normal(3) * np.sqrt(1 - rho)
            res = crossover_std_factor(ea - eb, np.full(3, 2 * stated_over_true ** 2), rho, min_factor=1.0)
            assert res["factor"] >= 1.0
            e = rng.standard_normal(200)  # errors elsewhere on the lines, same std
            hits.append(np.mean(np.abs(e) < 2 * stated_over_true * res["factor"]))
        cov[stated_over_true] = float(np.mean(hits))
    assert 2 * norm.cdf(1.0) - 1 == pytest.approx(0.683, abs=1e-3)
    assert cov[0.5] >= 0.85
    assert 2 * norm.cdf(2.0) - 1 <= cov[1.0] <= 0.99


def test_rms_vs_reference_per_line_mean_removed_by_hand():
    # line A errors 1, 3 (mean 2 -> ±1), line B errors -2, -2, NaN (mean -2 -> 0, 0, NaN)
    est = np.array([1.0, 3.0, 0.0, 0.0, np.nan])
    ref = np.array([0.0, 0.0, 2.0, 2.0, 0.0])
    line = np.array(["A", "A", "B", "B", "B"])
    assert rms_vs_reference(est, ref) == pytest.approx(np.sqrt((1 + 9 + 4 + 4) / 4))
    assert rms_vs_reference(est, ref, line=line) == pytest.approx(np.sqrt(2 / 4))
    np.testing.assert_allclose(line_demeaned(est - ref, line), [-1.0, 1.0, 0.0, 0.0, np.nan])
    # the line mean is taken over all the line's points, then `where` selects (first point of A, B)
    sel = np.array([True, False, True, False, False])
    assert rms_vs_reference(est, ref, where=sel) == pytest.approx(np.sqrt((1 + 4) / 2))
    assert rms_vs_reference(est, ref, line=line, where=sel) == pytest.approx(np.sqrt(1 / 2))
    assert mean_error_vs_reference(est, ref) == pytest.approx((1 + 3 - 2 - 2) / 4)
    assert mean_error_vs_reference(est, ref, where=sel) == pytest.approx(-0.5)
    # integer line ids work too; no selected finite pair is an error
    assert rms_vs_reference(est, ref, line=np.array([0, 0, 1, 1, 1])) == pytest.approx(np.sqrt(0.5))
    with pytest.raises(ValueError, match="common finite"):
        rms_vs_reference(est, ref, where=np.array([False] * 4 + [True]))
    with pytest.raises(ValueError, match="where"):
        rms_vs_reference(est, ref, where=np.ones(3, bool))


def test_std_calibration_by_hand():
    # |e| < 2σ: 0.5 < 2 yes, 3 < 2 no, 1.9 < 2 yes, 2 < 2 no (strict); the NaN pair is ignored
    assert std_calibration([0.5, -3.0, 1.9, 2.0, np.nan], [1.0, 1.0, 1.0, 1.0, 1.0]) == pytest.approx(0.5)
    assert std_calibration([0.5, -3.0], 2.0, k=1.0) == pytest.approx(0.5)   # σ broadcast


def test_grid_accuracy_in_hull_by_hand():
    # lines on the border of the square [0, 2]²; grid nodes -1..3 -> the 9 nodes 0..2 are inside
    t = np.linspace(0, 2, 21)
    le = np.concatenate([t, t, np.zeros_like(t), np.full_like(t, 2.0)])
    ln = np.concatenate([np.zeros_like(t), np.full_like(t, 2.0), t, t])
    x = y = np.arange(-1.0, 3.5, 1.0)
    X, Y = np.meshgrid(x, y)
    inside = (X >= 0) & (X <= 2) & (Y >= 0) & (Y <= 2)
    err = np.where(inside, 0.0, 50.0)
    err[inside] = [1, 1, 1, 1, 1, 1, 1, 3, 3]           # row by row
    err[1, 1] = np.nan                                  # one inside node lost: 8 cells left
    kept = np.array([1, 1, 1, 1, 1, 1, 3, 3], float)
    std = np.full(X.shape, 1.0)                         # |err| < 2: the six 1s
    res = grid_accuracy_in_hull(x, y, err, np.zeros_like(err), le, ln, std_mgal=std)
    assert res == GridAccuracy(cells=8, rms_mgal=pytest.approx(np.sqrt(np.mean(kept ** 2))),
                               rms_demeaned_mgal=pytest.approx(np.std(kept)), std_calibration=0.75)
    assert res.rms_mgal == pytest.approx(np.sqrt(24 / 8))
    assert grid_rms_in_hull(x, y, err, np.zeros_like(err), le, ln) == pytest.approx(res.rms_mgal)
    # no node inside: no error, None figures
    none = grid_accuracy_in_hull(x + 100.0, y, err, np.zeros_like(err), le, ln)
    assert none == GridAccuracy(cells=0, rms_mgal=None, rms_demeaned_mgal=None, std_calibration=None)


def test_points_in_hull_of_many_points_and_edges():
    rng = np.random.default_rng(4)
    e, n = rng.uniform(0, 10, 200_000), rng.uniform(0, 10, 200_000)
    e[:4], n[:4] = [0, 10, 10, 0], [0, 0, 10, 10]      # the square's corners are data points
    probe_e = np.array([5.0, 0.0, 10.0, 5.0, -0.01, 10.01, 5.0])
    probe_n = np.array([5.0, 5.0, 3.0, 10.0, 5.0, 5.0, -1.0])
    np.testing.assert_array_equal(points_in_hull(probe_e, probe_n, e, n),
                                  [True, True, True, True, False, False, False])


def test_repeat_line_accuracy_leaves_out_points_without_a_value():
    """Two repeats 1 mGal apart everywhere: ε = 1/√2 (analytic), whatever stretch of one of
    them is missing (NaN); a repeat missing everywhere leaves no common point."""
    from app.core.accuracy import repeat_line_accuracy

    e = np.linspace(0.0, 20.0, 401)
    a = np.sin(e)
    b = np.sin(e) + 1.0
    b[100:180] = np.nan
    res = repeat_line_accuracy([e, e[::-1]], [np.zeros(401)] * 2, [a, b[::-1]])
    assert float(res) == pytest.approx(1.0 / np.sqrt(2.0))
    assert res.n_points < 201 - 30
    with pytest.raises(ValueError):
        repeat_line_accuracy([e, e], [np.zeros(401)] * 2, [a, np.full(401, np.nan)])


def test_repeat_error_parts_recovers_the_noise_and_the_shared_smoothing_error():
    """Simulation with known parts: K repeats share a smoothing error b (what every pass's
    estimate smooths away) and carry their own noise; the less-smoothed estimate has the
    same truth plus other, larger noise of its own."""
    rng = np.random.default_rng(3)
    k, n = 6, 20000
    b = _smooth_noise(rng, n, 0.8, 50)              # shared: 0.64 mGal²
    x = np.array([b + _smooth_noise(rng, n, 1.2, 50) for _ in range(k)])   # noise 1.44 mGal²
    hi = np.array([_smooth_noise(rng, n, 2.0, 20) for _ in range(k)])      # the less-smoothed one's own noise
    parts = repeat_error_parts(x, x - hi)
    assert (parts.n_repeats, parts.n_points) == (k, n)
    assert parts.noise_var_mgal2 == pytest.approx(1.44, rel=0.1)
    # d = b + noise_x − noise_hi: the mean over repeats keeps b and 1/K of the noise, which
    # the repeats' scatter of d gives
    assert parts.smoothing_var_mgal2 == pytest.approx(0.64, rel=0.2)
    # the scale to a posterior: sqrt((1.44 + 0.64) / 1.04) = sqrt(2) by hand; never below 1
    assert parts.std_scale(1.04) == pytest.approx(np.sqrt((parts.noise_var_mgal2 + parts.smoothing_var_mgal2) / 1.04))
    assert parts.std_scale(1.04) == pytest.approx(np.sqrt(2.0), rel=0.12)
    assert parts.std_scale(100.0) == 1.0
    with pytest.raises(ValueError, match="positive"):
        parts.std_scale(0.0)
    # nothing shared: the smoothing part is about 0 (clipped at 0, never negative)
    none = repeat_error_parts(x - b, x - b - hi)
    assert 0.0 <= none.smoothing_var_mgal2 < 0.05


def test_smoothing_p_value_is_calibrated_under_no_shared_part_and_finds_one():
    """The F-test of a smoothing part: over 400 simulated tracks whose repeats share nothing
    (K = 4, 20 independent points), the one-sided p-value falls below 0.05 on 0.05 of them
    (binomial 3σ: 0.017–0.083) and is uniform (KS); with a shared part of half the noise's
    variance (F about 3 at 20 and 60 degrees of freedom) it falls below 0.05 on more than 0.8."""
    from scipy.stats import kstest

    rng = np.random.default_rng(8)
    k, n = 4, 20
    null = []
    for _ in range(400):
        d = rng.normal(0.0, 1.3, (k, n))
        null.append(repeat_error_parts(rng.normal(0.0, 1.0, (k, n)), d).smoothing_p_value(n))
    null = np.array(null)
    assert 0.017 <= np.mean(null < 0.05) <= 0.083
    assert kstest(null, "uniform").pvalue > 0.01
    found = [repeat_error_parts(rng.normal(0.0, 1.0, (k, n)),
                                rng.normal(0.0, 0.9, n) + rng.normal(0.0, 1.3, (k, n))).smoothing_p_value(n)
             for _ in range(200)]
    assert np.mean(np.array(found) < 0.05) > 0.8
    parts = repeat_error_parts(rng.normal(0.0, 1.0, (k, n)), rng.normal(0.0, 1.0, (k, n)))
    assert parts.mean_diff_sq_mgal2 - parts.mean_diff_noise_mgal2 == pytest.approx(
        parts.smoothing_var_mgal2) or parts.smoothing_var_mgal2 == 0.0
    with pytest.raises(ValueError, match="at least 1"):
        parts.smoothing_p_value(0.5)


def test_repeat_error_parts_errors():
    with pytest.raises(ValueError, match="same shape"):
        repeat_error_parts(np.zeros((1, 5)), np.zeros((1, 5)))
    with pytest.raises(ValueError, match="same shape"):
        repeat_error_parts(np.zeros((3, 5)), np.zeros((3, 4)))
    with pytest.raises(ValueError, match="finite"):
        repeat_error_parts(np.full((3, 5), np.nan), np.zeros((3, 5)))


def test_across_track_spread_of_repeat_passes():
    """Passes of one track flown both ways with 30 m of wander spread by ~0.06 km; a pass 2 km to
    the side of the others spreads them by 2 km, whatever the track's heading; one pass: 0."""
    from app.core.accuracy import across_track_spread_km

    rng = np.random.default_rng(3)
    s = np.linspace(0.0, 40.0, 401)
    heading = np.deg2rad(37.0)
    u, v = np.array([np.cos(heading), np.sin(heading)]), np.array([-np.sin(heading), np.cos(heading)])

    def pass_(offset_km, reverse=False):
        a = s[::-1] if reverse else s
        w = offset_km + 0.03 * rng.standard_normal(a.size)
        return 500.0 + a * u[0] + w * v[0], 7000.0 + a * u[1] + w * v[1]

    same = [pass_(0.0), pass_(0.0, True), pass_(0.0), pass_(0.0, True)]
    assert across_track_spread_km([p[0] for p in same], [p[1] for p in same]) < 0.01
    apart = same[:3] + [pass_(2.0, True)]
    assert abs(across_track_spread_km([p[0] for p in apart], [p[1] for p in apart]) - 2.0) < 0.01
    assert across_track_spread_km([same[0][0]], [same[0][1]]) == 0.0
    with pytest.raises(ValueError):
        across_track_spread_km([same[0][0], same[1][0]], [same[0][1]])


def test_passes_are_grouped_by_the_track_they_fly():
    """Four passes of one east-west track (alternate directions, 50 m apart, one a little
    shorter) are one group; a parallel line 2 km north, a north-south line through the track's
    middle, and the track's continuation beyond its end (collinear, no overlap) are each their
    own; the order of appearance sets the labels."""
    from app.core.accuracy import group_passes, same_track

    e = np.linspace(0.0, 40.0, 401)
    n0 = np.zeros_like(e)
    passes = [(e, n0), (e[::-1], n0 + 0.05), (e[20:], n0[20:] - 0.03), (e[::-1], n0 + 0.02),
              (e, n0 + 2.0),                                  # a parallel line 2 km away
              (np.full_like(e, 20.0), e - 20.0),              # a north-south line through the middle
              (e + 45.0, n0)]                                 # the continuation, collinear
    labels = group_passes([p[0] for p in passes], [p[1] for p in passes])
    assert labels.tolist() == [0, 0, 0, 0, 1, 2, 3]
    # a pass at 8 degrees to the track still flies it, one at 15 degrees does not
    for deg, same in ((8.0, True), (15.0, False)):
        a = np.radians(deg)
        x = np.linspace(-20.0, 20.0, 401)
        rot = (20.0 + x * np.cos(a), x * np.sin(a))
        assert same_track([e, rot[0]], [n0, rot[1]], max_spread_km=10.0) is same
    with pytest.raises(ValueError):
        same_track([e], [n0])


def test_each_repeats_own_noise_is_recovered():
    """Simulation with known parts: five repeats share a smoothing error and carry noise of
    their own with variances 1, 9, 0.25, 1 and 4 mGal² (a turbulent pass among calm ones).
    Each one's departure from the mean of the others gives its variance back within 10 %;
    their mean is the repeats' scatter ε² (internal accuracy squared), exactly."""
    rng = np.random.default_rng(21)
    n = 40000
    v_true = np.array([1.0, 9.0, 0.25, 1.0, 4.0])
    b = _smooth_noise(rng, n, 3.0, 50)          # shared by every repeat: cancels
    x = np.array([b + rng.normal(0.0, np.sqrt(v), n) for v in v_true])
    v = repeat_pass_noise_var(x)
    np.testing.assert_allclose(v, v_true, rtol=0.1)
    assert np.mean(v) == pytest.approx(internal_accuracy(x) ** 2, rel=1e-9)
    # two repeats cannot tell their noise apart: both get ε²
    two = repeat_pass_noise_var(x[:2])
    assert two[0] == two[1] == pytest.approx(internal_accuracy(x[:2]) ** 2, rel=1e-12)
    # by hand, three repeats at one point (2, 0, 0): departures from the others' mean 2, −1, −1
    # (squares 4, 1, 1); v_i + (v_j + v_k)/4 = (4, 1, 1) is solved by v = (4, 0, 0), whose
    # mean 4/3 is the unbiased variance of (2, 0, 0)
    np.testing.assert_allclose(repeat_pass_noise_var(np.array([[2.0], [0.0], [0.0]])), [4.0, 0.0, 0.0], atol=1e-12)
    # a repeat quieter than the others can come out below 0: clipped
    assert np.all(repeat_pass_noise_var(np.array([[0.0, 0.0], [3.0, -3.0], [-3.0, 3.0]])) >= 0.0)
    with pytest.raises(ValueError, match="K ≥ 2"):
        repeat_pass_noise_var(np.zeros((1, 4)))
    with pytest.raises(ValueError, match="finite"):
        repeat_pass_noise_var(np.array([[0.0, np.nan], [1.0, 2.0]]))


def test_noise_excess_p_value_is_calibrated_and_finds_excess_noise():
    """Four repeats at 20 independent points (60 degrees of freedom): with noise whose
    variance equals the posterior's, p < 0.1 on 0.1 of 1000 draws (binomial 3σ 0.07–0.13);
    with the noise 2× the posterior variance, on nearly all of them."""
    rng = np.random.default_rng(5)
    k, n = 4, 20
    dof = n * (k - 1)
    null = np.array([noise_excess_p_value(internal_accuracy(rng.normal(0.0, 1.5, (k, n))) ** 2, 2.25, dof)
                     for _ in range(1000)])
    assert 0.07 <= np.mean(null < 0.1) <= 0.13
    excess = np.array([noise_excess_p_value(internal_accuracy(rng.normal(0.0, 1.5 * np.sqrt(2), (k, n))) ** 2,
                                            2.25, dof) for _ in range(200)])
    assert np.mean(excess < 0.1) > 0.95
    assert noise_excess_p_value(2.25, 2.25, 1e6) == pytest.approx(0.5, abs=0.01)
    with pytest.raises(ValueError, match="positive"):
        noise_excess_p_value(1.0, 0.0, 10)
    with pytest.raises(ValueError, match="at least 1"):
        noise_excess_p_value(1.0, 1.0, 0.5)


def test_repeat_noise_ratio_is_not_ruled_by_the_line_ends():
    """Four repeats whose posterior (and noise) widens 10× over the last 5 % of the points, as
    at a line's end: the noise over the posterior, point by point, gives each repeat's ratio
    (1, 4, 1, 1 over 1.3) within 10 %, whether the posterior comes per repeat or once."""
    rng = np.random.default_rng(4)
    k, n = 4, 40000
    sd = np.ones(n)
    sd[-n // 20:] = 10.0
    post_var = 1.3 * sd ** 2                       # the posterior: noise 1 plus a smoothing part
    ratio_true = np.array([1.0, 4.0, 1.0, 1.0]) / 1.3
    b = rng.normal(0.0, 5.0, n)                    # shared: cancels
    x = np.array([b + rng.normal(0.0, 1.0, n) * sd * np.sqrt(r * 1.3) for r in ratio_true])
    np.testing.assert_allclose(repeat_pass_noise_ratio(x, post_var), ratio_true, rtol=0.1)
    np.testing.assert_allclose(repeat_pass_noise_ratio(x, np.tile(post_var, (k, 1))), ratio_true, rtol=0.1)
    with pytest.raises(ValueError, match="positive"):
        repeat_pass_noise_ratio(x, np.zeros(n))
    with pytest.raises(ValueError, match="one per common point"):
        repeat_pass_noise_ratio(x, post_var[:-1])


def test_repeat_pass_std_scales_by_hand():
    """max(track scale, sqrt(ρ + smoothing ratio)), never below 1: ρ = (0.25, 9, 1) alone gives
    (1, 3, 1); with a track scale 1.5 and a smoothing ratio 0.44: (1.5, sqrt(9.44), 1.5)."""
    np.testing.assert_allclose(repeat_pass_std_scales([0.25, 9.0, 1.0]), [1.0, 3.0, 1.0])
    np.testing.assert_allclose(repeat_pass_std_scales([0.25, 9.0, 1.0], 1.5, 0.44), [1.5, np.sqrt(9.44), 1.5])
    np.testing.assert_allclose(repeat_pass_std_scales([0.0, 0.0], 0.5), [1.0, 1.0])
    with pytest.raises(ValueError, match="≥ 0"):
        repeat_pass_std_scales([-1.0, 1.0])
    with pytest.raises(ValueError, match="≥ 0"):
        repeat_pass_std_scales([1.0, 1.0], smoothing_ratio=-0.1)


def test_repeat_pass_departures_by_hand():
    """Three repeats at two points: each one's departure from the other two's mean of the
    reference, over the mean posterior variance at each point (worked out by hand)."""
    from app.core.accuracy import repeat_pass_departures

    ref = np.array([[1.0, 2.0], [3.0, 2.0], [5.0, 8.0]])
    post = np.array([[1.0, 4.0], [1.0, 4.0], [1.0, 4.0]])
    # others' means: pass 0 (4, 5), pass 1 (3, 5), pass 2 (2, 2); variances 1 and 4
    expected = [((1 - 4) ** 2 / 1 + (2 - 5) ** 2 / 4) / 2, ((3 - 3) ** 2 + (2 - 5) ** 2 / 4) / 2,
                ((5 - 2) ** 2 + (8 - 2) ** 2 / 4) / 2]
    np.testing.assert_allclose(repeat_pass_departures(ref, ref, post), expected)
    np.testing.assert_allclose(repeat_pass_departures(ref, ref, np.array([1.0, 4.0])), expected)
    # another estimate of the same repeats against the reference as it was: pass 0 moved to 4, 5
    moved = ref.copy()
    moved[0] = [4.0, 5.0]
    assert repeat_pass_departures(moved, ref, post)[0] == 0.0
    with pytest.raises(ValueError):
        repeat_pass_departures(ref, ref, np.zeros(2))
    with pytest.raises(ValueError):
        repeat_pass_departures(ref[:1], ref[:1], post[:1])


def test_track_axes_of_passes_on_a_known_bearing():
    """Three passes along a bearing of 60° from grid north (one reversed, one offset 50 m
    across, one shorter with a NaN position): the axis is the leading eigenvector of the finite
    points' covariance (numpy's eigh), within 0.1° of the bearing (the offset pass tilts it), the
    across axis perpendicular to it, the centre the mean of the finite points."""
    u = np.array([np.sin(np.radians(60.0)), np.cos(np.radians(60.0))])
    v = np.array([u[1], -u[0]])
    s = np.linspace(0.0, 20.0, 41)
    p1 = np.outer(s, u) + [100.0, 200.0]
    p2 = np.outer(s[::-1], u) + [100.0, 200.0] + 0.05 * v
    p3 = np.outer(s[5:], u) + [100.0, 200.0]
    p3[3] = np.nan
    centre, along, across = track_axes([p1[:, 0], p2[:, 0], p3[:, 0]], [p1[:, 1], p2[:, 1], p3[:, 1]])
    pts = np.vstack([p1, p2, p3[np.isfinite(p3).all(axis=1)]])
    np.testing.assert_allclose(centre, pts.mean(axis=0), atol=1e-12)
    lead = np.linalg.eigh(np.cov((pts - pts.mean(axis=0)).T))[1][:, -1]
    assert abs(abs(float(along @ lead)) - 1.0) < 1e-12
    assert np.degrees(np.arccos(min(1.0, abs(float(along @ u))))) < 0.1
    assert abs(float(along @ across)) < 1e-12 and abs(np.linalg.norm(across) - 1.0) < 1e-12
