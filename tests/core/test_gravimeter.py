"""Gravimeter interval means, lag/scale inversion and time offset against analytic signals."""

import numpy as np
import pytest

from app.core import gravimeter as gm

RATE = 18.24
T_GRAV = 1.0 / RATE


def _grav_samples(t0, t1, fbar_fn, round_ms=True, offset=0.0):
    """Centre-stamped interval means of a signal whose interval mean is ``fbar_fn(a, b)``."""
    n = int((t1 - t0) / T_GRAV)
    a = t0 + np.arange(n) * T_GRAV
    b = a + T_GRAV
    vals = fbar_fn(a, b)
    stamps = 0.5 * (a + b) - offset
    if round_ms:
        stamps = np.round(stamps, 3)
    return stamps, vals


def _poly_mean(coefs):
    # interval mean of sum c_j t^j over (a, b)
    def f(a, b):
        a = np.asarray(a, float)
        b = np.asarray(b, float)
        s = 0.0
        for j, c in enumerate(coefs):
            s = s + c * (b ** (j + 1) - a ** (j + 1)) / (j + 1)
        return s / (b - a)
    return f


@pytest.mark.parametrize("coefs", [[9.8], [9.8, 1e-3], [9.81, -2e-3, 3e-6]])
def test_interval_means_exact_for_polynomials(coefs):
    # exact centres (no rounding) → cumulative integral exact at the boundaries
    stamps, vals = _grav_samples(0.0, 60.0, _poly_mean(coefs), round_ms=False)
    series = gm.integrate_samples(stamps, vals)
    t = np.arange(1.0, 58.0, 0.1)
    got = gm.interval_means(series, t)
    want = _poly_mean(coefs)(t[:-1], t[1:])
    np.testing.assert_allclose(got[1:], want, rtol=0, atol=1e-9)
    assert np.isnan(got[0])


def test_dejitter_recovers_uniform_clock():
    n = 20000
    true = 1000.0 + (np.arange(n) + 0.5) * T_GRAV
    rounded = np.round(true, 3)
    fixed = gm.dejitter_times_s(rounded)
    assert np.max(np.abs(rounded - true)) > 4e-4
    assert np.max(np.abs(fixed[300:-300] - true[300:-300])) < 3e-5
    # a real gap is left alone and does not corrupt the rest
    gapped = np.concatenate([rounded[:5000], rounded[6000:]])
    fixed2 = gm.dejitter_times_s(gapped)
    assert np.all(np.diff(fixed2) > 0)
    assert fixed2[5000] == pytest.approx(true[6000], abs=1e-3)


def test_dejitter_takes_logging_jitter_but_not_irregular_sampling():
    """A 2 Hz record stamped by a logging computer (±5 ms around a uniform clock) is put back
    on the clock; a record that really alternates 0.45/0.55 s steps is not touched."""
    rng = np.random.default_rng(4)
    n = 7200
    true = 5000.0 + np.arange(n) * 0.5
    stamped = np.round(true + rng.uniform(-0.005, 0.005, n), 3)
    fixed = gm.dejitter_times_s(stamped)
    assert np.max(np.abs(stamped - true)) > 4e-3
    assert np.max(np.abs(fixed[300:-300] - true[300:-300])) < 1e-3
    irregular = 5000.0 + np.cumsum(np.where(np.arange(n) % 2, 0.55, 0.45))
    np.testing.assert_array_equal(gm.dejitter_times_s(irregular), irregular)
    # an explicit bound still rules
    np.testing.assert_array_equal(gm.dejitter_times_s(stamped, max_jitter_s=1.5e-3), stamped)


def test_dejitter_puts_isolated_stamp_glitches_back_on_the_clock():
    """A logger's hiccup: five stamps 20 ms late among 40 000 of an 18.24 Hz record stamped to
    1 ms or to 10 ms.  Each glitch is beyond a quarter step of the rounding's reach, which kept
    the whole segment on its stamps (±5 ms of rounding at 10 ms); the glitches are wrong stamps
    of a uniform clock, and the record goes back on the clock, glitches included."""
    rng = np.random.default_rng(3)
    n = 40000
    true = 1000.0 + (np.arange(n) + 0.5) * T_GRAV
    for decimals in (3, 2):
        stamped = np.round(true, decimals)
        idx = rng.choice(np.arange(500, n - 500), 5, replace=False)
        stamped[idx] = np.round(stamped[idx] + 0.02, decimals)
        fixed = gm.dejitter_times_s(stamped)
        assert np.max(np.abs(fixed[300:-300] - true[300:-300])) < 2e-4, decimals
        np.testing.assert_allclose(fixed[idx], true[idx], atol=2e-4)


def test_dejitter_takes_stamps_rounded_to_a_coarse_step():
    """18.24 Hz stamps rounded to 0.01 s scatter uniformly by ±5 ms about the clock (a robust
    scale of 3.7 ms, above 5 % of the 54.8 ms step): every stamp is a multiple of 0.01 s and
    none is more than 5 ms off, which is that rounding, so they go back on the clock (the
    sample survey so stamped: 4.02 mGal from the truth on the stamps, 3.29 on the clock; 3.30
    as simulated).  A record really alternating 0.45/0.55 s steps, all multiples of 0.05 s
    (deviations ±25 ms, the quantum's half, but never near zero), is not touched."""
    true = 400000.0 + (np.arange(30000) + 0.5) * T_GRAV
    for q in (0.01, 0.02):
        rounded = np.round(true / q) * q
        assert gm.stamp_quantum_s(rounded) == q
        assert gm.stamp_scatter_s(rounded)[0] > 0.05 * T_GRAV
        fixed = gm.dejitter_times_s(rounded)
        assert np.max(np.abs(fixed[300:-300] - true[300:-300])) < 5e-4
    assert gm.stamp_quantum_s(true) == 0.0
    n = 7200
    irregular = np.round(5000.0 + np.cumsum(np.where(np.arange(n) % 2, 0.55, 0.45)), 2)
    assert gm.stamp_quantum_s(irregular) == 0.05
    np.testing.assert_array_equal(gm.dejitter_times_s(irregular), irregular)


def test_dejitter_judges_the_scatter_not_its_largest_value():
    """10 Hz stamps with a 1 ms normal scatter rounded to 1 ms: over 40 000 stamps the largest
    deviation reaches 4 ms (beyond the old largest-deviation bound of 2.5 ms), the robust scale
    is 1 ms — jitter, put back on the clock — and :func:`stamp_scatter_s` reports it either way."""
    rng = np.random.default_rng(11)
    n = 40_000
    true = 20_000.0 + np.arange(n) * 0.1
    stamped = np.round(true + rng.normal(0.0, 1e-3, n), 3)
    assert np.max(np.abs(stamped - true)) > 3.5e-3
    fixed = gm.dejitter_times_s(stamped)
    assert np.max(np.abs(fixed[300:-300] - true[300:-300])) < 2e-4
    scale, largest = gm.stamp_scatter_s(stamped)
    assert 1e-3 <= scale <= 1.6e-3 and largest > 3.5e-3   # whole milliseconds: the MAD is 1 ms
    # a scatter well beyond jitter (10 % of the step) is kept, and still measured
    wild = true + rng.normal(0.0, 0.01, n)
    np.testing.assert_array_equal(gm.dejitter_times_s(wild), wild)
    assert gm.stamp_scatter_s(wild)[0] == pytest.approx(0.01, rel=0.1)


def _sin_lagged(amps, omegas, phases, tau, k):
    """Specific force f(t) = 9.8 + Σ A sin(ωt+φ) through τ·ẏ + k·y = f (steady state)."""
    def f_true_mean(a, b):
        s = 9.8 * np.ones_like(a)
        for A, w, p in zip(amps, omegas, phases):
            s = s + A * (np.cos(w * a + p) - np.cos(w * b + p)) / (w * (b - a))
        return s

    def lagged_mean(a, b):
        s = 9.8 / k * np.ones_like(a)
        for A, w, p in zip(amps, omegas, phases):
            g = A / np.hypot(k, w * tau)
            ph = p - np.arctan2(w * tau, k)
            s = s + g * (np.cos(w * a + ph) - np.cos(w * b + ph)) / (w * (b - a))
        return s
    return f_true_mean, lagged_mean


def _moving_average(x, n):
    c = np.convolve(x, np.ones(n) / n, mode="valid")
    return c


@pytest.mark.parametrize("tau,k", [(0.0, 1.0), (2.0, 1.0003)])
def test_double_integral_exact_for_polynomials(tau, k):
    """f' = c0 + c1·t + c2·t² sampled as interval means from t = 0: ∫∫ f_g dt² = k·∫F + τ·F
    with F = c0·t + c1·t²/2 + c2·t³/3 (by hand), to a µm; NaN outside the samples' span."""
    c0, c1, c2 = 9.81, -2e-3, 3e-6
    stamps, vals = _grav_samples(0.0, 60.0, _poly_mean([c0, c1, c2]), round_ms=False)
    series = gm.integrate_samples(stamps, vals, dejitter=False)
    t = np.arange(1.0, 58.0, 1.0)
    F = c0 * t + c1 * t ** 2 / 2 + c2 * t ** 3 / 3
    want = k * (c0 * t ** 2 / 2 + c1 * t ** 3 / 6 + c2 * t ** 4 / 12) + tau * F
    np.testing.assert_allclose(gm.double_integral_m(series, t, tau, k), want, rtol=0, atol=1e-6)
    # a gravimeter stamped 0.5 s early: its sample at t belongs to GNSS time t + 0.5
    late = gm.double_integral_m(series, t + 0.5, tau, k, time_offset_s=0.5)
    np.testing.assert_allclose(late, want, rtol=0, atol=1e-6)
    assert np.isnan(gm.double_integral_m(series, np.array([-1.0, 61.0]))).all()


def test_lag_and_scale_inversion_recovers_signal():
    rng = np.random.default_rng(3)
    freqs = np.array([0.003, 0.011, 0.05, 0.13, 0.31, 0.7, 1.3])
    amps = np.array([2e-4, 1e-4, 0.3, 0.5, 0.4, 0.2, 0.05])  # m/s²: anomaly-like + aircraft motion
    omegas = 2 * np.pi * freqs
    phases = rng.uniform(0, 2 * np.pi, freqs.size)
    tau, k = 2.0, 1.0003
    f_true_mean, lagged_mean = _sin_lagged(amps, omegas, phases, tau, k)
    stamps, vals = _grav_samples(0.0, 1500.0, lagged_mean)
    series = gm.integrate_samples(stamps, vals)
    t = np.arange(5.0, 1495.0, 0.1)
    got = gm.interval_means(series, t, tau_s=tau, scale=k)[1:]
    want = f_true_mean(t[:-1], t[1:])
    err_mgal = (got - want) * 1e5
    lp = _moving_average(err_mgal, 1000)          # 100 s low-pass
    assert np.sqrt(np.mean(lp ** 2)) < 0.1
    # without undoing the lag the error is enormous (aircraft accelerations)
    raw = gm.interval_means(series, t)[1:]
    assert np.sqrt(np.mean(((raw - want) * 1e5) ** 2)) > 1e4


def test_first_order_lag_forward_model_matches_analytic():
    t = np.arange(0.0, 30.0, 0.002)
    tau, k, w = 2.0, 1.0, 0.7
    y = gm.apply_first_order_lag(t, np.sin(w * t), tau, k, f0=0.0)
    ya = (np.sin(w * t) - w * tau * np.cos(w * t)) / (1 + (w * tau) ** 2) + w * tau / (1 + (w * tau) ** 2) * np.exp(-t / tau)
    np.testing.assert_allclose(y, ya, atol=1e-7)


def test_time_offset_recovered_to_10ms():
    rng = np.random.default_rng(7)
    freqs = rng.uniform(0.03, 0.8, 12)
    amps = rng.uniform(0.05, 0.4, 12)
    omegas = 2 * np.pi * freqs
    phases = rng.uniform(0, 2 * np.pi, 12)
    tau = 2.0
    f_true_mean, lagged_mean = _sin_lagged(amps, omegas, phases, tau, 1.0)
    offset = 0.137
    stamps, vals = _grav_samples(0.0, 900.0, lagged_mean, offset=offset)
    vals = vals + rng.normal(0, 2e-4, vals.size)  # sensor noise 20 mGal per sample
    series = gm.integrate_samples(stamps, vals)
    t = np.arange(10.0, 880.0, 0.1)
    # GNSS vertical velocity: integral of the acceleration (9.8 removed) + 1.5 cm/s noise
    v = np.zeros_like(t)
    for A, w, p in zip(amps, omegas, phases):
        v += -A / w * np.cos(w * t + p)
    v += rng.normal(0, 0.015, t.size)
    est, corr = gm.estimate_time_offset_s(series, t, v, tau_s=tau)
    assert abs(est - offset) < 0.010
    assert corr > 0.9


@pytest.mark.parametrize("offset", [18.0, -17.0])
def test_leap_second_offset_found_in_a_60_s_search(offset):
    """Gravimeter stamped in UTC, GNSS in GPS time (18 s apart; 17 s before 2017): the
    offset is found to 10 ms by the ±60 s search; a ±2 s one cannot reach it."""
    rng = np.random.default_rng(11)
    freqs = rng.uniform(0.03, 0.8, 40)   # broadband accelerations: no periodic false peak
    amps = rng.uniform(0.02, 0.2, 40)
    omegas, phases = 2 * np.pi * freqs, rng.uniform(0, 2 * np.pi, 40)
    tau = 2.0
    _, lagged_mean = _sin_lagged(amps, omegas, phases, tau, 1.0)
    stamps, vals = _grav_samples(0.0, 1300.0, lagged_mean, offset=offset)
    series = gm.integrate_samples(stamps, vals + rng.normal(0, 2e-4, vals.size))
    t = np.arange(100.0, 1200.0, 0.1)
    v = sum(-A / w * np.cos(w * t + p) for A, w, p in zip(amps, omegas, phases)) + rng.normal(0, 0.015, t.size)
    fit = gm.fit_time_offset(series, t, v, tau_s=tau, max_offset_s=60.0)
    assert abs(fit.offset_s - offset) < 0.010 and fit.correlation > 0.9
    narrow = gm.fit_time_offset(series, t, v, tau_s=tau, max_offset_s=2.0)
    assert abs(narrow.offset_s - offset) > 10.0 and narrow.correlation < 0.6


def test_bad_inputs():
    with pytest.raises(ValueError, match="increasing"):
        gm.integrate_samples(np.array([0.0, 1.0, 1.0]), np.ones(3))
    with pytest.raises(ValueError, match="NaN"):
        gm.integrate_samples(np.array([0.0, 1.0, 2.0]), np.array([1.0, np.nan, 1.0]))
    s = gm.integrate_samples(np.arange(100) * T_GRAV, np.ones(100))
    with pytest.raises(ValueError, match="tau_s"):
        gm.interval_means(s, np.arange(10) * 0.1, tau_s=-1.0)


def _turbulent(t):
    """Vertical acceleration (m/s²) of sinusoids at 0.23–1.7 Hz, its velocity and its exact
    integral of the velocity (analytic)."""
    f = np.array([0.23, 0.41, 0.67, 0.93, 1.31, 1.7])
    amp = np.array([0.15, 0.2, 0.15, 0.1, 0.08, 0.05])
    ph = np.array([0.3, 1.1, 2.0, 0.7, 2.9, 1.6])
    w = 2 * np.pi * f
    t = np.asarray(t, float)[..., None]
    a = np.sum(amp * np.sin(w * t + ph), -1)
    v = np.sum(-amp / w * np.cos(w * t + ph), -1)          # ∫ a dt
    return a, v


@pytest.mark.parametrize("offset", [0.0, 0.137])
def test_motion_compensated_means_cancel_motion_of_a_slow_gravimeter(offset):
    # a 1 Hz interval-mean gravimeter reading u = a(t) + g0 + c·t beside 10 Hz GNSS velocities:
    # f_g − ΔV/Δt on the GNSS intervals must be the mean of g0 + c·t, which plain interpolation of
    # F between the 1 s boundaries cannot give (it does not know the motion inside a second)
    g0, c = 9.8, 2e-5
    a_edges = 100.0 + np.arange(600)
    b_edges = a_edges + 1.0
    vals = ((_turbulent(b_edges)[1] - _turbulent(a_edges)[1])
            + g0 + c * 0.5 * (a_edges + b_edges)) / 1.0
    stamps = 0.5 * (a_edges + b_edges) - offset          # gravimeter clock behind GNSS time by offset
    series = gm.integrate_samples(stamps, vals)
    t = np.arange(110.0, 690.0, 0.1)
    vu = _turbulent(t)[1]
    want = g0 + c * 0.5 * (t[1:] + t[:-1])
    mc = gm.motion_compensated_means(series, t, vu, time_offset_s=offset)
    z_mc = mc[1:] - np.diff(vu) / np.diff(t)
    z_plain = gm.interval_means(series, t, time_offset_s=offset)[1:] - np.diff(vu) / np.diff(t)
    err_mc = np.sqrt(np.mean((z_mc - want) ** 2)) * 1e5       # mGal
    err_plain = np.sqrt(np.mean((z_plain - want) ** 2)) * 1e5
    assert np.isnan(mc[0])
    assert err_plain > 1000.0                                 # the motion inside a second: thousands of mGal
    assert err_mc < 0.01                                      # left: the GNSS velocity spline error
    # the anomaly band (below 0.02 Hz, a 50 s mean): within 0.001 mGal
    k = 500
    lo = np.convolve(z_mc - want, np.ones(k) / k, "valid") * 1e5
    assert np.max(np.abs(lo)) < 0.001


def test_motion_compensated_means_with_lag_and_scale():
    # τ·ẏ + k·y = u with u = g0 (constant) + motion: y's integral is known in closed form only for
    # the constant, so check the constant part with no motion: f_g's mean is g0 on every interval
    g0, tau, k = 9.8, 0.5, 1.02
    a_edges = np.arange(300.0)
    stamps = a_edges + 0.5
    vals = np.full(stamps.size, g0 / k)                        # steady output
    series = gm.integrate_samples(stamps, vals)
    t = np.arange(5.0, 290.0, 0.2)
    mc = gm.motion_compensated_means(series, t, np.zeros_like(t), tau_s=tau, scale=k)
    assert np.isnan(mc[0]) and np.all(np.isfinite(mc[1:]))
    assert np.allclose(mc[1:], g0, atol=1e-9)
    with pytest.raises(ValueError):
        gm.motion_compensated_means(series, t, np.zeros(3))


def _broadband_flight(seed, tau_true, lo_hz=0.01):
    """(series, t, v): a gravimeter with lag ``tau_true`` and the GNSS velocity (5 cm/s noise) of
    broadband vertical accelerations from ``lo_hz`` to 0.8 Hz."""
    rng = np.random.default_rng(seed)
    freqs = rng.uniform(lo_hz, 0.8, 40)
    amps = rng.uniform(0.02, 0.2, 40)
    omegas, phases = 2 * np.pi * freqs, rng.uniform(0, 2 * np.pi, 40)
    _, lagged_mean = _sin_lagged(amps, omegas, phases, tau_true, 1.0)
    stamps, vals = _grav_samples(0.0, 1300.0, lagged_mean, offset=0.0)
    series = gm.integrate_samples(stamps, vals + rng.normal(0, 2e-4, vals.size))
    t = np.arange(100.0, 1200.0, 0.1)
    v = sum(-A / w * np.cos(w * t + p) for A, w, p in zip(amps, omegas, phases)) + rng.normal(0, 0.05, t.size)
    return series, t, v


@pytest.mark.parametrize("gnss_unit_m", [1.0, 0.3048])
def test_time_offset_gain_is_the_gnss_unit(gnss_unit_m):
    """The fit's gain is how many m/s² of gravimeter acceleration one GNSS unit is: 1 for a GNSS
    in metres, 0.3048 for one whose velocities are in feet per second — even with 5 cm/s of
    velocity noise (what a regression on the noisy GNSS side would bias low) — in the whole band
    and in the low one."""
    series, t, v = _broadband_flight(5, 2.0)
    fit = gm.fit_time_offset(series, t, v / gnss_unit_m, tau_s=2.0, max_offset_s=5.0)
    assert fit.gain == pytest.approx(gnss_unit_m, rel=0.01)
    assert fit.gain_low == pytest.approx(gnss_unit_m, rel=0.05) and fit.gain_low_correlation > 0.9


def test_a_lag_declared_wrong_lowers_the_gain_but_hardly_the_low_band_one():
    """τ = 3 s undeclared (tau_s = 0): the gravimeter's amplitude is 1/|1 + iωτ| of the aircraft's —
    0.47 at 0.1 Hz, 0.07 at 0.8 Hz, but 0.73–0.98 at 0.01–0.05 Hz."""
    series, t, v = _broadband_flight(6, 3.0)
    fit = gm.fit_time_offset(series, t, v, tau_s=0.0, max_offset_s=5.0)
    assert fit.gain < 0.7
    assert 0.7 < fit.gain_low < 1.05


#: a phugoid and height-hold band (0.03–0.17 Hz) and turbulence the 1–2 Hz heights cannot follow (0.23–1.7 Hz)
_MOTION_HZ = np.array([0.031, 0.07, 0.12, 0.17, 0.23, 0.41, 0.67, 0.93, 1.31, 1.7])
_MOTION_AMP = np.array([0.05, 0.08, 0.1, 0.1, 0.15, 0.2, 0.15, 0.1, 0.08, 0.05])     # m/s²
_MOTION_PH = np.array([0.9, 2.2, 0.1, 1.4, 0.3, 1.1, 2.0, 0.7, 2.9, 1.6])


def _motion(t):
    """Vertical velocity (m/s) and height (m) of the sinusoids' acceleration (analytic)."""
    w = 2 * np.pi * _MOTION_HZ
    t = np.asarray(t, float)[..., None]
    v = np.sum(-_MOTION_AMP / w * np.cos(w * t + _MOTION_PH), -1)
    h = np.sum(-_MOTION_AMP / w ** 2 * np.sin(w * t + _MOTION_PH), -1)
    return v, h


def _fast_meter(g0, c, offset=0.0, t0=100.0, t1=700.0):
    """An 18.24 Hz interval-mean gravimeter reading the motion + g0 + c·t, its clock behind GNSS
    time by ``offset`` (s)."""
    a_edges = t0 + np.arange(int((t1 - t0) * RATE)) * T_GRAV
    b_edges = a_edges + T_GRAV
    vals = (_motion(b_edges)[0] - _motion(a_edges)[0]) / T_GRAV + g0 + c * 0.5 * (a_edges + b_edges)
    return gm.integrate_samples(0.5 * (a_edges + b_edges) - offset, vals)


@pytest.mark.parametrize("rate_hz", [1.0, 2.0])
def test_height_matched_means_cancel_motion_the_heights_cannot_follow(rate_hz):
    # 1–2 Hz GNSS heights (point samples) of a motion with power up to 1.7 Hz: the spline through
    # them has its own acceleration, thousands of mGal from the aircraft's, which the gravimeter's
    # exact interval means follow; put through the same spline, the gravimeter's double integral
    # leaves g0 + c·t (the spline keeps a linear trend) and the 18 Hz spline's interpolation of
    # the motion at the epochs (a few hundredths of a mGal, white)
    from app.core.geodesy import vertical_velocity_from_heights_ms

    g0, c = 9.8, 2e-5
    series = _fast_meter(g0, c)
    t = np.arange(110.0, 690.0, 1.0 / rate_hz)
    vu = vertical_velocity_from_heights_ms(t, _motion(t)[1])
    acc = np.diff(vu) / np.diff(t)
    want = g0 + c * 0.5 * (t[1:] + t[:-1])
    hm = gm.height_matched_means(series, t, [(0, t.size)])
    err_hm = np.sqrt(np.mean((hm[1:] - acc - want) ** 2)) * 1e5            # mGal
    err_plain = np.sqrt(np.mean((gm.interval_means(series, t)[1:] - acc - want) ** 2)) * 1e5
    assert np.isnan(hm[0])
    assert err_plain > 1000.0
    assert err_hm < 0.2
    k = int(50 * rate_hz)                                         # the anomaly band: a 50 s mean
    lo = np.convolve(hm[1:] - acc - want, np.ones(k) / k, "valid") * 1e5
    assert np.max(np.abs(lo)) < 0.01
    # two runs (a record gap between them): each keeps its own spline, the gap's interval the plain mean
    cut = t.size // 2
    t2 = np.concatenate([t[:cut], t[cut + 5:]])
    vu2 = np.concatenate([vertical_velocity_from_heights_ms(t2[:cut], _motion(t2[:cut])[1]),
                          vertical_velocity_from_heights_ms(t2[cut:], _motion(t2[cut:])[1])])
    hm2 = gm.height_matched_means(series, t2, [(0, cut), (cut, t2.size)])
    z2 = hm2[1:] - np.diff(vu2) / np.diff(t2) - (g0 + c * 0.5 * (t2[1:] + t2[:-1]))
    inside = np.ones(t2.size - 1, bool)
    inside[cut - 1] = False                                      # the interval across the gap
    assert np.max(np.abs(z2[inside])) * 1e5 < 1.0
    assert hm2[cut] == gm.interval_means(series, t2)[cut]


def test_height_matched_means_outside_the_gravimeter_span_and_with_lag():
    series = _fast_meter(9.8, 0.0)
    t = np.arange(90.0, 720.0, 1.0)                              # beyond the record on both sides
    hm = gm.height_matched_means(series, t, [(0, t.size)])
    assert np.array_equal(np.isnan(hm), np.isnan(gm.interval_means(series, t)))
    # a steady output through a lag and a scale: f_g's mean is g0 on every interval
    stamps = np.arange(0.5, 300.0, T_GRAV)
    steady = gm.integrate_samples(stamps, np.full(stamps.size, 9.8 / 1.02))
    tt = np.arange(5.0, 290.0, 1.0)
    hm_s = gm.height_matched_means(steady, tt, [(0, tt.size)], tau_s=0.5, scale=1.02)
    assert np.isnan(hm_s[0]) and np.allclose(hm_s[1:], 9.8, atol=1e-9)


def test_time_offset_of_heights_only_gnss_found_through_the_heights_spline():
    # 1 Hz heights of the motion, the gravimeter 0.137 s behind: as the heights see the motion
    # (height_runs), the offset comes out right; the exact means against the spline's acceleration
    # fit the turbulence the heights alias into the band instead
    from app.core.geodesy import vertical_velocity_from_heights_ms

    offset = 0.137
    series = _fast_meter(9.8, 0.0, offset=offset, t0=0.0, t1=1000.0)
    t = np.arange(20.0, 980.0, 1.0)
    vu = vertical_velocity_from_heights_ms(t, _motion(t)[1])
    fit = gm.fit_time_offset(series, t, vu, max_offset_s=3.0, band_hz=(0.01, 0.2), height_runs=[(0, t.size)])
    plain = gm.fit_time_offset(series, t, vu, max_offset_s=3.0, band_hz=(0.01, 0.2))
    assert abs(fit.offset_s - offset) < 0.005
    assert fit.correlation > 0.99
    assert abs(plain.offset_s - offset) > 5 * abs(fit.offset_s - offset)


@pytest.mark.parametrize("fs_hz, band_hz, n", [(10.0, (0.01, 1.0), 5000), (2.0, (0.01, 0.9), 700),
                                                (1.0, (0.01, 0.05), 300), (20.0, (0.05, 2.0), 60000)])
def test_filtfilt_band_is_scipys_sosfiltfilt(fs_hz, band_hz, n):
    """The cached band-pass of the time-offset fit gives SciPy's ``sosfiltfilt`` of the same
    Butterworth design bit for bit (a random walk, a trend and a step), and refuses a record no
    longer than SciPy's padding as SciPy does."""
    from scipy.signal import butter, sosfiltfilt

    from app.core.gravimeter import band_filter, filtfilt_band

    rng = np.random.default_rng(n)
    x = rng.normal(size=n).cumsum() + 0.01 * np.arange(n) + np.where(np.arange(n) > n // 3, 5.0, 0.0)
    ref = sosfiltfilt(butter(4, list(band_hz), btype="band", fs=fs_hz, output="sos"), x)
    got = filtfilt_band(band_filter(*band_hz, fs_hz), x)
    np.testing.assert_array_equal(got, ref)
    assert band_filter(*band_hz, fs_hz) is band_filter(*band_hz, fs_hz)   # designed once
    short = np.zeros(band_filter(*band_hz, fs_hz)[2])
    with pytest.raises(ValueError, match="padlen"):
        sosfiltfilt(butter(4, list(band_hz), btype="band", fs=fs_hz, output="sos"), short)
    with pytest.raises(ValueError, match="padlen"):
        filtfilt_band(band_filter(*band_hz, fs_hz), short)
