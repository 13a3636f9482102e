"""Offsets and drifts of repeat passes fitted to their differences (app.core.repeat_leveling),
against simulated passes with known offsets, drifts and errors."""

import numpy as np
import pytest

from app.core.repeat_leveling import drift_p_value, fit_repeat_levels


def _passes(rng, K=4, n=400, gap_s=900.0, step_s=1.6, flights=None):
    """K passes of one track (n common positions) flown in alternating directions, ``gap_s``
    apart; returns (times (K, n) s, anomaly (n,) mGal)."""
    s = np.arange(n) * step_s
    t = np.array([1000.0 + k * gap_s + (s if k % 2 == 0 else s[::-1]) for k in range(K)])
    g = np.cumsum(rng.normal(0, 0.5, n))
    return t, g


def test_noise_free_offsets_and_drift_are_recovered_and_the_mean_level_kept():
    rng = np.random.default_rng(0)
    t, g = _passes(rng)
    off = np.array([0.5, -1.0, 2.0, 0.3])          # mGal
    rate = 1.5                                     # mGal/h
    drift = rate * (t - 2500.0) / 3600.0
    x = g + off[:, None] + drift
    fit = fit_repeat_levels(x, t, degree=1, block=20)
    corr = np.array([fit.correction(k, t[k]) for k in range(4)])
    assert fit.drift_mgal[0, 0] == pytest.approx(rate, abs=1e-9)
    # what is left is the anomaly plus one level common to every pass
    left = x - corr
    assert np.ptp(left - g) == pytest.approx(0.0, abs=1e-9)
    # ... and that level is the passes' mean level before (the corrections average to zero)
    assert corr.mean() == pytest.approx(0.0, abs=1e-12)
    assert (left - g).mean() == pytest.approx((x - g).mean(), abs=1e-9)
    assert fit.p_value == 0.0 and fit.rms_after_mgal == pytest.approx(0.0, abs=1e-9)


def test_two_flights_get_their_own_drift():
    rng = np.random.default_rng(1)
    t, g = _passes(rng, K=6)
    flights = ["A", "A", "A", "B", "B", "B"]
    t[3:] += 20000.0                                # flight B flown later
    rates = {"A": 2.0, "B": -3.0}
    t_mean = {f: t[[i for i, ff in enumerate(flights) if ff == f]].mean() for f in rates}
    drift = np.array([rates[f] * (tk - t_mean[f]) / 3600.0 for f, tk in zip(flights, t)])
    x = g + drift + np.array([0, 0, 0, 4.0, 4.0, 4.0])[:, None]   # flight B also 4 mGal off
    fit = fit_repeat_levels(x, t, flights, degree=1, block=20)
    assert fit.drift_mgal[:, 0] == pytest.approx([2.0, -3.0], abs=1e-9)
    left = x - np.array([fit.correction(k, t[k]) for k in range(6)])
    assert np.ptp(left - g) == pytest.approx(0.0, abs=1e-9)


def test_f_test_false_alarms_at_its_level_without_offsets():
    """Block errors independent and no offsets or drift: p uniform, so p < α about α of the time."""
    rng = np.random.default_rng(2)
    t, g = _passes(rng, n=200)
    ps = []
    for _ in range(600):
        x = g + rng.normal(0, 0.4, (4, 20)).repeat(10, axis=1)   # one error per block of 10 positions
        ps.append(fit_repeat_levels(x, t, degree=1, block=10).p_value)
    ps = np.array(ps)
    assert 0.025 < np.mean(ps < 0.05) < 0.08
    assert np.mean(ps < 0.01) < 0.025


def test_offsets_above_the_noise_are_found_within_their_error():
    rng = np.random.default_rng(3)
    t, g = _passes(rng)
    off = np.array([-1.0, 0.8, 0.0, 0.2])
    errs = []
    for _ in range(50):
        x = g + off[:, None] + rng.normal(0, 0.3, (4, 40)).repeat(10, axis=1)
        fit = fit_repeat_levels(x, t, degree=0, block=10)
        assert fit.p_value < 1e-6
        errs.append(fit.offsets_mgal - (off - off.mean()))
    # each offset from 40 blocks of σ 0.3 against the mean of 4 passes: σ ≈ 0.3·sqrt(3/4)/sqrt(40)
    assert np.std(errs) == pytest.approx(0.3 * np.sqrt(0.75 / 40), rel=0.25)
    assert abs(np.mean(errs)) < 0.02


def test_bad_input_is_refused():
    t = np.tile(np.arange(100.0), (3, 1))
    x = np.zeros((3, 100))
    with pytest.raises(ValueError, match="one shape"):
        fit_repeat_levels(x[:, :50], t)
    with pytest.raises(ValueError, match="K ≥ 2"):
        fit_repeat_levels(x[:1], t[:1])
    with pytest.raises(ValueError, match="degree"):
        fit_repeat_levels(x, t, degree=3)
    with pytest.raises(ValueError, match="finite"):
        fit_repeat_levels(np.where(t > 50, np.nan, x), t)
    with pytest.raises(ValueError, match="degrees of freedom"):
        fit_repeat_levels(x, t, degree=1, block=50)
    with pytest.raises(ValueError, match="flights"):
        fit_repeat_levels(x, t, ["A", "B"])


def test_blocks_weighted_by_the_passes_variance():
    """A pass whose ends are noisy (a turn, a run-in): weighted by the inverse variance the
    offsets come from the quiet middle, unweighted the ends' errors pull them."""
    rng = np.random.default_rng(4)
    t, g = _passes(rng)
    off = np.array([0.6, -0.6, 0.3, -0.3])
    sd = np.full((4, 400), 0.1)
    sd[:, :60] = sd[:, -60:] = 3.0
    errs_w, errs_u = [], []
    for _ in range(40):
        x = g + off[:, None] + rng.normal(0, 1.0, (4, 400)) * sd
        for errs, std in ((errs_w, sd), (errs_u, None)):
            fit = fit_repeat_levels(x, t, degree=0, block=10, std_mgal=std)
            errs.append(fit.offsets_mgal - (off - off.mean()))
    assert np.sqrt(np.mean(np.square(errs_w))) < 0.3 * np.sqrt(np.mean(np.square(errs_u)))
    with pytest.raises(ValueError, match="std_mgal"):
        fit_repeat_levels(x, t, degree=0, block=10, std_mgal=np.zeros_like(x))


def test_the_drift_is_not_extrapolated_beyond_a_pass_s_common_points():
    rng = np.random.default_rng(5)
    t, g = _passes(rng)
    x = g + 2.0 * (t - t.mean()) / 3600.0
    fit = fit_repeat_levels(x, t, degree=1, block=20)
    lo, hi = t[0].min(), t[0].max()
    inside = fit.correction(0, np.array([lo, hi]))
    # an hour past the pass's end its correction is still that at the end
    assert fit.correction(0, np.array([lo - 3600.0, hi + 3600.0])) == pytest.approx(inside, abs=1e-12)
    assert abs(inside[1] - inside[0]) == pytest.approx(2.0 * (hi - lo) / 3600.0, rel=1e-9)


def test_passes_flown_one_way_get_no_drift_they_cannot_show():
    """Four passes flown the same way at the same speed: a drift in time is, along the track,
    only offsets between them.  The drift column is dropped (not traded against huge offsets),
    and the offsets still come out."""
    rng = np.random.default_rng(6)
    s = np.arange(300) * 1.6
    t = np.array([1000.0 + k * 900.0 + s for k in range(4)])      # every pass the same way
    g = np.cumsum(rng.normal(0, 0.5, 300))
    off = np.array([0.5, -1.0, 2.0, 0.3])
    x = g + off[:, None] + 2.0 * (t - t.mean()) / 3600.0 + rng.normal(0, 0.2, (4, 300))
    fit = fit_repeat_levels(x, t, degree=1, block=10)
    assert fit.drift_mgal[0, 0] == 0.0 and fit.n_parameters == 3
    corr = np.array([fit.correction(k, t[k]) for k in range(4)])
    assert np.max(np.abs(corr)) < 3.0
    left = x - corr - g
    assert np.ptp(left.mean(axis=1)) < 0.1


def test_the_drift_s_partial_test_is_calibrated_and_finds_a_real_drift():
    """Offsets but no drift, independent block errors: the drift's p is uniform (p < 0.05 about
    5 % of the time); a drift of 3 mGal/h on passes flown back and forth: p tiny; passes flown
    one way: no drift term to test (None)."""
    rng = np.random.default_rng(7)
    t, g = _passes(rng, n=200)
    off = np.array([0.5, -0.5, 1.0, -1.0])[:, None]
    ps = []
    for _ in range(400):
        x = g + off + rng.normal(0, 0.4, (4, 20)).repeat(10, axis=1)
        ps.append(drift_p_value(fit_repeat_levels(x, t, degree=0, block=10), fit_repeat_levels(x, t, degree=1, block=10)))
    assert 0.025 < np.mean(np.array(ps) < 0.05) < 0.085
    # with a drift: its estimate unbiased (its std here ~1.8 mGal/h: 5 min passes), and one of
    # 15 mGal/h (8 of those stds) found every time
    rates, ps = [], []
    for _ in range(50):
        x = g + off + 15.0 * (t - t.mean()) / 3600.0 + rng.normal(0, 0.4, (4, 20)).repeat(10, axis=1)
        drifted = fit_repeat_levels(x, t, degree=1, block=10)
        rates.append(drifted.drift_mgal[0, 0])
        ps.append(drift_p_value(fit_repeat_levels(x, t, degree=0, block=10), drifted))
    assert np.mean(rates) == pytest.approx(15.0, abs=3 * np.std(rates) / np.sqrt(50))
    assert max(ps) < 1e-3
    one_way = np.array([1000.0 + k * 900.0 + np.arange(200) * 1.6 for k in range(4)])
    assert drift_p_value(fit_repeat_levels(x, one_way, degree=0, block=10),
                         fit_repeat_levels(x, one_way, degree=1, block=10)) is None
    with pytest.raises(ValueError, match="same passes"):
        drift_p_value(fit_repeat_levels(x, t, degree=0, block=10), fit_repeat_levels(x, t, degree=1, block=20))
