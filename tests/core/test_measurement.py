"""The measurement z_k of SPEC §1 against physical situations with a known answer."""

import numpy as np
import pytest
from scipy.integrate import cumulative_trapezoid as scipy_ct

from app.core import geodesy
from app.core import gravimeter as gm
from app.core.measurement import anomaly_measurement_mgal, cumulative_trapezoid, gnss_acceleration_ms2


def test_stationary_gravimeter_on_apron_gives_g_minus_gamma():
    lat, h = 65.4321, 220.0
    g_mgal = 982316.4                                   # absolute gravity at the parking place
    rate = 18.24
    n = int(600 * rate)
    stamps = np.round(1000.0 + (np.arange(n) + 0.5) / rate, 3)   # rounded centre stamps
    f = np.full(n, g_mgal * 1e-5)                       # at rest: f_z = g (m/s², up)
    series = gm.integrate_samples(stamps, f)
    t = np.arange(1010.0, 1590.0, 0.1)
    fbar = gm.interval_means(series, t, tau_s=2.0, scale=1.0)
    gamma = geodesy.normal_gravity_mgal(np.full(t.size, lat), np.full(t.size, h))
    e = geodesy.eotvos_mgal(lat, h, np.zeros(t.size), np.zeros(t.size))
    z = anomaly_measurement_mgal(fbar, t, np.zeros(t.size), gamma, e)
    assert np.isnan(z[0])
    np.testing.assert_allclose(z[1:], g_mgal - gamma[1:], atol=0.01)


def test_steady_climb_and_eotvos_cancel():
    # An aircraft flying east at constant speed and accelerating upward at 0.5 m/s²
    # over a place of anomaly 37 mGal: the gravimeter feels a + γ + δg − E.
    lat, h0, ve = 60.0, 3000.0, 100.0
    t = np.arange(0.0, 60.0, 0.1)
    a = 0.5
    vu = a * (t - 30.0)
    h = h0 + 0.5 * a * (t - 30.0) ** 2
    gamma = geodesy.normal_gravity_mgal(np.full(t.size, lat), h)
    E = geodesy.eotvos_mgal(lat, h, np.full(t.size, ve), np.zeros(t.size))
    dg = 37.0
    fbar = a + (gamma + dg - E) * 1e-5
    z = anomaly_measurement_mgal(fbar, t, vu, gamma, E)
    np.testing.assert_allclose(z[1:], dg, atol=1e-6)


def test_gnss_acceleration():
    t = np.array([0.0, 0.1, 0.3])
    v = np.array([1.0, 1.2, 1.0])
    np.testing.assert_allclose(gnss_acceleration_ms2(t, v)[1:], [2.0, -1.0])
    with pytest.raises(ValueError):
        gnss_acceleration_ms2(np.array([0.0, 0.0]), np.array([1.0, 1.0]))


def test_velocity_spikes_are_found_and_repaired_without_low_frequency_error():
    """GNSS velocity spikes (cycle slips) put ±A/Δt doublets into z.  The mask must find
    them without false alarms on Gaussian noise, including at a jump of the noise level,
    and the repair must leave the 100 s average of z as if the spikes had never been
    there (simulation with known truth)."""
    from scipy.ndimage import uniform_filter1d

    from app.core.measurement import repair_spikes, spike_mask

    rng = np.random.default_rng(3)
    n, dt = 400_000, 0.1
    sig = np.full(n + 1, 1.3)
    sig[150_000:160_000] *= 4.0                   # a noisy episode: not spikes
    v_clean = rng.standard_normal(n + 1) * sig / 100.0          # m/s
    anomaly = 20.0 * np.sin(np.arange(n) * dt / 300.0)
    z_clean = -1e5 * np.diff(v_clean) / dt + anomaly
    v = v_clean.copy()
    j = rng.choice(np.arange(1000, n - 1000), 200, replace=False)
    j = j[(j < 149_000) | (j > 161_000)]
    v[j] += rng.choice([-1.0, 1.0], j.size) * rng.uniform(0.15, 0.4, j.size)
    z = -1e5 * np.diff(v) / dt + anomaly
    hit = np.zeros(n, bool)
    hit[j - 1] = hit[j] = True                    # z_k = … − (V_{k+1} − V_k)/Δt in this indexing
    mask = spike_mask(z, dt)
    assert (mask & hit).sum() >= 0.99 * hit.sum()
    assert (mask & ~hit).sum() <= 5
    fixed = repair_spikes(z, mask)
    w = int(100 / dt)
    err_raw = uniform_filter1d(z - z_clean, w)
    err_fixed = uniform_filter1d(fixed - z_clean, w)
    assert np.sqrt(np.mean(err_raw ** 2)) > 5.0                  # spikes matter at 100 s (mGal)
    assert np.sqrt(np.mean(err_fixed ** 2)) < 0.15 * np.sqrt(np.mean(err_raw ** 2))
    # the repair never changes a run's sum (z's low frequencies)
    assert np.sum(fixed) == pytest.approx(np.sum(z), rel=1e-9, abs=1e-3)
    with pytest.raises(ValueError):
        repair_spikes(z, mask[:10])
    with pytest.raises(ValueError):
        spike_mask(np.ones((3, 3)), dt)


@pytest.mark.parametrize("rate_hz, turbulence_ms2", [(1.0, 0.3), (2.0, 0.45), (10.0, 0.3)])
def test_spikes_at_a_tenth_of_a_percent_are_found_in_turbulence(rate_hz, turbulence_ms2):
    """Issue 'Real surveys': spikes injected at 0.1 % of the epochs of a turbulent low-rate
    record are still found (≥ 90 %), with false alarms ≤ 0.1 % of the clean epochs.  The
    noise of z is the turbulence the gravimeter and GNSS see differently (an AR(2) acceleration
    mismatch of ``turbulence_ms2`` × 10 % RMS, coloured, plus white velocity noise); each spike
    is a GNSS velocity outlier (cycle slip) of 10–40 × the noise of z per epoch."""
    from scipy.signal import lfilter

    from app.core.measurement import spike_mask

    rng = np.random.default_rng(int(rate_hz * 10))
    dt = 1.0 / rate_hz
    n = int(6 * 3600 * rate_hz)
    # AR(2) resonance at ~0.15 Hz: the residual of turbulence in z (mGal)
    r, w = 0.9 ** dt, 2 * np.pi * 0.15 * dt
    acc = lfilter([1.0], [1.0, -2 * r * np.cos(w), r * r], rng.standard_normal(n))
    acc *= 0.1 * turbulence_ms2 * 1e5 / acc.std()
    v_noise = rng.standard_normal(n + 1) * 0.02                   # m/s
    z_clean = acc - 1e5 * np.diff(v_noise) / dt + 20.0 * np.sin(np.arange(n) * dt / 300.0)
    sz = np.std(z_clean)
    k = max(20, int(1e-3 * n))
    j = np.sort(rng.choice(np.arange(100, n - 100), k, replace=False))
    j = j[np.concatenate([[True], np.diff(j) > 5])]               # isolated spikes
    amp_ms = rng.choice([-1.0, 1.0], j.size) * rng.uniform(10, 40, j.size) * sz * dt / 1e5
    v = v_noise.copy()
    v[j] += amp_ms
    z = acc - 1e5 * np.diff(v) / dt + 20.0 * np.sin(np.arange(n) * dt / 300.0)
    hit = np.zeros(n, bool)
    hit[j - 1] = hit[j] = True
    mask = spike_mask(z, dt)
    found = np.mean(mask[j - 1] | mask[j])
    assert found >= 0.9, found
    assert (mask & ~hit).sum() <= 1e-3 * n
    assert spike_mask(z_clean, dt).mean() <= 1e-3                 # the clean record: false alarms only


def test_height_spikes_and_steps_are_removed_through_the_spline():
    """Heights-only GNSS: vu is the derivative of the spline through h, so a height spike
    (one bad epoch) or a step (a cycle slip: every later height off) reaches z as a pattern
    ringing over several epochs.  The flags cover only its core; replacing that core by its
    mean (the velocity-spike repair) leaves the tails unbalanced, an error at 100 s.  The
    height-outlier repair must recover the clean record's FIR 100 s low-pass and say what
    it removed."""
    from app.core.baselines import fir_lowpass_mgal
    from app.core.measurement import repair_height_outliers, repair_spikes

    rng = np.random.default_rng(3)
    dt = 0.5
    t = 5000.0 + np.arange(7200) * dt                     # one hour at 2 Hz
    h = 3000.0 + sum(a * np.sin(2 * np.pi * t / p + rng.uniform(0, 6.3))   # aircraft heave
                     for a, p in ((0.02, 3.0), (0.1, 7.0), (0.5, 19.0), (2.0, 60.0)))
    anomaly = 20.0 * np.sin(2 * np.pi * t / 900.0)         # mGal
    fbar = np.r_[np.nan, np.diff(geodesy.vertical_velocity_from_heights_ms(t, h)) / dt]
    fbar = fbar + (anomaly + rng.normal(0, 500.0, t.size)) * 1e-5   # gravimeter: motion + anomaly + noise
    zero = np.zeros(t.size)

    def z_of(heights):
        return anomaly_measurement_mgal(fbar, t, geodesy.vertical_velocity_from_heights_ms(t, heights), zero, zero)

    bad = h.copy()
    truth = {1500: ("spike", 0.25), 3100: ("spike", -0.15), 4777: ("step", 0.30), 6000: ("spike", 0.40)}
    for j, (kind, size) in truth.items():
        if kind == "spike":
            bad[j] += size
        else:
            bad[j:] += size
    z0, z1 = z_of(h)[1:], z_of(bad)[1:]
    tt = t[1:]
    # the detector flags the pattern's core, often not all of it (spike_mask's local scale
    # sees the ringing): flag the largest departure from the clean record and one neighbour
    mask = np.zeros(z1.size, bool)
    for j in truth:
        k = j - 1 - 4 + int(np.argmax(np.abs(z1 - z0)[j - 1 - 4:j - 1 + 5]))
        mask[k:k + 2] = True
    fixed, fixes = repair_height_outliers(z1, tt, mask)
    found = {f["epoch"] + 1: (f["kind"], f["size_m"]) for f in fixes}   # z index -> epoch of t
    assert set(found) == set(truth)
    for j, (kind, size) in truth.items():
        assert found[j][0] == kind and abs(found[j][1] - size) < 0.01

    def fir_err(z):
        return float(np.sqrt(np.mean((fir_lowpass_mgal(z, dt) - fir_lowpass_mgal(z0, dt))[300:-300] ** 2)))

    assert fir_err(fixed) < 0.05                                      # mGal
    assert fir_err(repair_spikes(z1, mask)) > 1.0                     # the run-mean repair's tails
    assert fir_err(z1) > 1.0                                          # the step, left in
    with pytest.raises(ValueError, match="same shape"):
        repair_height_outliers(z1, tt[:-1], mask)


def test_height_outliers_are_found_where_the_spike_mask_misses_them():
    """A 50 cm height spike reaches z through the spline as ~12 epochs of ±100 000 mGal: the
    spike mask's local scale rises with the pattern and misses it; the matched patterns
    find it, and on a clean record flag nothing."""
    from app.core.measurement import height_outlier_mask, spike_mask

    rng = np.random.default_rng(11)
    dt = 0.5
    t = np.arange(14400) * dt                               # two hours at 2 Hz
    h = 3000.0 + 0.5 * np.sin(2 * np.pi * t / 19.0) + 2.0 * np.sin(2 * np.pi * t / 60.0)
    fbar = np.r_[np.nan, np.diff(geodesy.vertical_velocity_from_heights_ms(t, h)) / dt]
    fbar = fbar + rng.normal(0, 18000.0, t.size) * 1e-5    # 18 000 mGal of noise: a turbulent 2 Hz record
    zero = np.zeros(t.size)

    def z_of(heights):
        return anomaly_measurement_mgal(fbar, t, geodesy.vertical_velocity_from_heights_ms(t, heights), zero, zero)

    clean = z_of(h)
    assert not height_outlier_mask(clean, t).any()
    bad = h.copy()
    where = np.arange(500, 14000, 1350)                      # ten spikes of ±50 cm
    bad[where] += 0.5 * np.where(np.arange(where.size) % 2, 1.0, -1.0)
    z = z_of(bad)
    found = np.flatnonzero(height_outlier_mask(z, t))
    assert all(np.min(np.abs(found - j)) <= 2 for j in where)
    assert np.sum(np.diff(found) > 3) + 1 == where.size            # one cluster per spike, no other
    assert spike_mask(z, dt).sum() < where.size              # what the spike mask alone finds
    with pytest.raises(ValueError, match="same shape"):
        height_outlier_mask(z, t[:-1])


def test_running_median_within_runs_is_a_median_of_each_runs_own_samples():
    """Against a brute-force median of each window, reflected at the run's ends (scipy's
    'reflect': d c b a | a b c d | d c b a) and never reaching across a gap."""
    from app.core.measurement import running_median_within_runs

    rng = np.random.default_rng(4)
    x = rng.standard_normal(60)
    valid = np.ones(60, bool)
    valid[[0, 20, 21, 22, 45]] = False
    x[~valid] = 1e9                                     # what the gaps hold must not matter
    got = running_median_within_runs(x, valid, 7)
    assert np.all(np.isnan(got[~valid]))
    d = np.diff(np.concatenate([[0], valid.astype(int), [0]]))
    for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
        run = x[a:b]
        ext = np.concatenate([run[::-1], run, run[::-1]])   # runs here are longer than 3
        for i in range(b - a):
            j = i + (b - a)
            assert got[a + i] == pytest.approx(np.median(ext[j - 3:j + 4]))
    with pytest.raises(ValueError, match="same shape"):
        running_median_within_runs(x, valid[:-1], 7)


def test_no_false_spikes_at_the_ends_of_a_records_runs():
    """A clean record cut into runs — a static reading on the apron, a short gap (the
    gravimeter starts later), the turbulent flight, a GNSS outage, the flight, the apron again
    — raises no flag: the robust scale is each run's own.  The scale's running median once
    counted the gaps' interpolated samples and the templates' zero fill, and reached from the
    quiet apron into the turbulent flight: generated clean surveys were flagged within 13
    epochs (spike mask) and 16–29 epochs (height templates) of the runs' ends, 0.13–0.19 % of
    a small heights-only survey's epochs.  Spikes a few epochs from a gap are still found."""
    from app.core.measurement import height_outlier_mask, spike_mask

    rng = np.random.default_rng(8)
    dt = 1.0
    t = np.arange(3000) * dt
    flying = (t >= 150) & (t < 2860)
    on = np.clip((t - 118) / 32, 0, 1) * np.clip((2875 - t) / 15, 0, 1)   # motion starts and stops in the gaps
    h = 3000.0 + on * (0.5 * np.sin(2 * np.pi * t / 7.0) + 2.0 * np.sin(2 * np.pi * t / 23.0))
    h = h + rng.normal(0, 0.005, t.size)
    fbar = np.r_[np.nan, np.diff(geodesy.vertical_velocity_from_heights_ms(t, h)) / dt]
    fbar = fbar + rng.normal(0, 50.0, t.size) * 1e-5
    for a, b in [(118, 150), (1500, 1530), (2860, 2875)]:   # apron | flight | outage | flight | apron
        fbar[a:b] = np.nan
    zero = np.zeros(t.size)
    z = anomaly_measurement_mgal(fbar, t, geodesy.vertical_velocity_from_heights_ms(t, h), zero, zero)
    assert not spike_mask(z, dt).any()
    assert not height_outlier_mask(z, t).any()
    # velocity spikes (doublets) 3, 6 and 40 epochs after a gap's end, and 4 before one
    zs = z.copy()
    size = 20 * np.nanstd(np.diff(z[flying]))
    where = [153, 1536, 190, 1495]
    for j in where:
        zs[j] += size
        zs[j + 1] -= size
    found = spike_mask(zs, dt)
    assert all(found[j] and found[j + 1] for j in where)
    near = np.zeros(t.size, bool)
    for j in where:
        near[j - 2:j + 4] = True
    assert not (found & ~near).any()                      # the doublets' partners, no other


def test_height_steps_found_and_sized_in_the_double_integral_of_z():
    """Heights-only GNSS at 2 Hz with 1 cm of white height noise (through the spline, z's noise
    rises as f⁴: thousands of mGal) and four cycle slips of 0.2–0.3 m.  In z's double integral
    a step of the heights is a step: the sizes come out within 3 cm, the mask flags each step
    once (within an epoch) and nothing on the clean record, and a repair sized from the double integral leaves the
    FIR 100 s low-pass within 2 mGal of the clean record's (the steps left in: over 10 mGal)."""
    from app.core.baselines import fir_lowpass_mgal
    from app.core.measurement import height_step_mask, height_step_sizes_m, repair_height_outliers

    rng = np.random.default_rng(5)
    dt = 0.5
    t = 1000.0 + np.arange(14400) * dt                      # two hours
    h = 3000.0 + sum(a * np.sin(2 * np.pi * t / p + rng.uniform(0, 6.3))
                     for a, p in ((0.1, 7.0), (0.5, 19.0), (2.0, 60.0)))
    fbar = np.r_[np.nan, np.diff(geodesy.vertical_velocity_from_heights_ms(t, h)) / dt]
    fbar = fbar + (15.0 * np.sin(2 * np.pi * t / 700.0) + rng.normal(0, 50.0, t.size)) * 1e-5
    noisy = h + rng.normal(0, 0.01, t.size)
    zero = np.zeros(t.size)

    def z_of(heights):
        return anomaly_measurement_mgal(fbar, t, geodesy.vertical_velocity_from_heights_ms(t, heights), zero, zero)

    clean = z_of(noisy)
    assert np.nanstd(clean) > 2000.0
    assert not height_step_mask(clean, t).any()
    steps = {2000: 0.2, 5500: -0.25, 9000: 0.3, 12500: -0.2}
    bad = noisy.copy()
    for j, size in steps.items():
        bad[j:] += size
    z = z_of(bad)
    sizes = height_step_sizes_m(z, t)
    for j, size in steps.items():
        assert abs(sizes[j] - size) < 0.03, (j, sizes[j], size)
    found = np.flatnonzero(height_step_mask(z, t))
    assert found.size == len(steps) and np.all(np.abs(found - np.array(sorted(steps))) <= 1), found
    fixed, fixes = repair_height_outliers(z, t, height_step_mask(z, t), step_sizes_m=sizes)
    assert [f["kind"] for f in fixes] == ["step"] * 4

    def fir_err(x):
        return float(np.max(np.abs((fir_lowpass_mgal(x[1:], dt) - fir_lowpass_mgal(clean[1:], dt))[300:-300])))

    assert fir_err(z) > 10.0
    assert fir_err(fixed) < 2.0
    with pytest.raises(ValueError, match="same shape"):
        height_step_sizes_m(z, t[:-1])


def _heave_1hz(seed: int):
    """Two hours of 1 Hz heights-only GNSS under heave with power up to 0.45 Hz (0.6 m/s² RMS of
    acceleration), a 20 Hz gravimeter measuring ḧ + γ + a 15 mGal anomaly (1 mGal white noise),
    heights with 7 mm white and 2.5 cm Gauss-Markov (60 s) error.  Returns the gravimeter
    series, the epochs, the measured heights and γ (E = 0)."""
    rng = np.random.default_rng(seed)
    comp = [(a, 2 * np.pi / p, rng.uniform(0, 6.3))
            for a, p in ((0.08, 2.2), (0.15, 3.0), (0.3, 5.0), (1.0, 20.0), (3.0, 60.0))]

    def vel(x):
        return sum(a * w * np.cos(w * x + ph) for a, w, ph in comp)

    g0 = 9.82
    tb = np.arange(0.0, 7300.0 + 1e-9, 0.05)                 # sample boundaries
    a, b = tb[:-1], tb[1:]
    f = ((vel(b) - vel(a)) / 0.05 + g0 + 15e-5 * np.sin(2 * np.pi * 0.5 * (a + b) / 700.0)
         + rng.normal(0, 1e-5, a.size))
    series = gm.integrate_samples(0.5 * (a + b), f, dejitter=False)
    t = 50.0 + np.arange(7200) * 1.0
    gm_err = np.zeros(t.size)
    phi = np.exp(-1.0 / 60.0)
    e = rng.normal(0, 0.025 * np.sqrt(1 - phi ** 2), t.size)
    for k in range(1, t.size):
        gm_err[k] = phi * gm_err[k - 1] + e[k]
    heights = (3000.0 + sum(a * np.sin(w * t + ph) for a, w, ph in comp)
               + rng.normal(0, 0.007, t.size) + gm_err)
    return series, t, heights, np.full(t.size, g0 * 1e5)


def test_height_steps_at_1hz_found_and_sized_in_the_gravimeter_double_integral():
    """At 1 Hz z's own double integral (a sum over the epochs) misses ∫∫f by half an epoch times
    the spline velocity's error, which under heave near the Nyquist frequency swamps a 0.2 m
    cycle slip: of four slips (0.2, −0.3, 0.5, −0.2 m) it finds one, the 0.5 m.  The gravimeter's
    double integral less the heights finds all four at their epochs, sizes them within 2.5 cm
    (the heights' 60 s error wanders: 0.3–1.4 cm here, up to 3 cm at other seeds), flags
    nothing on the clean record, and the repair leaves the FIR 100 s low-pass within 1.5 mGal
    of the clean record's (the slips left in: over 25 mGal)."""
    from app.core.baselines import fir_lowpass_mgal
    from app.core.measurement import (
        gravimeter_height_misfit_m,
        height_step_mask,
        height_step_sizes_m,
        repair_height_outliers,
    )

    series, t, heights, gamma = _heave_1hz(7)
    zero = np.zeros(t.size)
    fbar = gm.interval_means(series, t)
    ff = gm.double_integral_m(series, t)
    steps = {1500: 0.2, 3000: -0.3, 4500: 0.5, 6000: -0.2}
    bad = heights.copy()
    for j, size in steps.items():
        bad[j:] += size

    def z_of(hh):
        return anomaly_measurement_mgal(fbar, t, geodesy.vertical_velocity_from_heights_ms(t, hh), gamma, zero)

    clean, z = z_of(heights), z_of(bad)
    own = np.flatnonzero(height_step_mask(z, t))                         # z's own double integral
    assert sum(np.min(np.abs(own - j)) <= 1 for j in steps) <= 2, own
    sizes_clean = height_step_sizes_m(clean, t, misfit_m=gravimeter_height_misfit_m(t, ff, heights, gamma, zero))
    assert not height_step_mask(clean, t, sizes_m=sizes_clean).any()
    sizes = height_step_sizes_m(z, t, misfit_m=gravimeter_height_misfit_m(t, ff, bad, gamma, zero))
    found = np.flatnonzero(height_step_mask(z, t, sizes_m=sizes))
    np.testing.assert_array_equal(found, sorted(steps))
    for j, size in steps.items():
        assert abs(sizes[j] - size) < 0.025, (j, sizes[j], size)
    mask = height_step_mask(z, t, sizes_m=sizes)
    fixed, fixes = repair_height_outliers(z, t, mask, step_sizes_m=np.where(mask, sizes, np.nan))
    assert [(f["epoch"], f["kind"]) for f in fixes] == [(j, "step") for j in sorted(steps)]

    def fir_err(x):
        return float(np.max(np.abs((fir_lowpass_mgal(x[1:], 1.0) - fir_lowpass_mgal(clean[1:], 1.0))[300:-300])))

    assert fir_err(z) > 25.0
    assert fir_err(fixed) < 1.5
    with pytest.raises(ValueError, match="one shape"):
        gravimeter_height_misfit_m(t, ff[:-1], bad, gamma, zero)
    with pytest.raises(ValueError, match="shape of z_mgal"):
        height_step_sizes_m(z, t, misfit_m=ff[:-1])


def test_response_prediction_recovers_the_part_of_z_linear_in_the_acceleration():
    """z = (g ⋆ a) − a + 30 mGal + white noise of 200 mGal, with g a short response (a 3-tap
    lag): the prediction from a alone leaves the noise (its residual std within 5 % of 200 mGal,
    where z's own spread is ~thousands), and it exists where z is missing."""
    from app.core.measurement import response_prediction_mgal

    rng = np.random.default_rng(8)
    n = 20000
    a = rng.normal(0.0, 0.3, n)                            # m/s²
    g = np.array([0.2, 0.5, 0.3])                          # response: a_k spread over k, k−1, k−2
    resp = np.convolve(a, g)[:n]
    noise = rng.normal(0.0, 200.0, n)
    z = (resp - a) * 1e5 + 30.0 + noise
    z_holed = z.copy()
    z_holed[5000:5010] = np.nan
    pred = response_prediction_mgal(z_holed, a / 1.0, lags=5)
    ok = np.isfinite(pred) & np.isfinite(z_holed)
    assert np.std(z) > 10_000
    assert np.std(z[ok] - pred[ok]) == pytest.approx(200.0, rel=0.05)
    assert np.all(np.isfinite(pred[5000:5010]))
    np.testing.assert_allclose(pred[5000:5010], z[5000:5010] - noise[5000:5010], atol=50.0)


# --------------------------------------------------------------------------- band delay
def _motion(rng, t, dt):
    """Vertical acceleration (mGal): a phugoid, a second slow mode and AR(1) turbulence."""
    from scipy.signal import lfilter
    a = 15_000.0 * np.sin(2 * np.pi * t / 45.0) + 3_000.0 * np.sin(2 * np.pi * t / 28.0 + 1.0)
    return a + 300.0 * lfilter([1.0], [1.0, -0.98], rng.standard_normal(t.size))


def _z(rng, t, dt, delay_s, anomaly=None, vel_noise_cms=1.0):
    """z of a gravimeter late by delay_s: a(t − d) − (a(t) + e_a) + δg, with the GNSS's own
    acceleration error e_a (white velocity noise differenced) in both z and the regressor."""
    from app.core.measurement import gnss_acceleration_ms2
    a = _motion(rng, t, dt)
    v_err = rng.normal(0.0, vel_noise_cms / 100.0, t.size)
    e_a = np.nan_to_num(gnss_acceleration_ms2(t, v_err)) * 1e5
    dg = 5.0 * np.sin(2 * np.pi * t / 400.0) if anomaly is None else anomaly(a)
    z = np.interp(t - delay_s, t, a) - (a + e_a) + dg
    return z, a + e_a


def test_band_delay_recovers_a_known_delay_and_its_correction_removes_it():
    from app.core.measurement import band_delay_fit, delay_correction_mgal
    rng = np.random.default_rng(3)
    dt = 0.1
    t = np.arange(0.0, 7200.0, dt)
    z, a = _z(rng, t, dt, 0.02)
    fit = band_delay_fit([(t, z, a, np.ones(t.size, bool))], dt, (0.01, 0.05))
    assert abs(fit.delay_s - 0.02) < max(3 * fit.se_s, 1e-3)
    assert fit.t_stat > 20 and fit.n_independent == pytest.approx(2 * 0.04 * (7200 - 2 * 100), rel=0.01)  # the ends left out
    zc = z - delay_correction_mgal(t, a, fit.delay_s, 0.1)
    again = band_delay_fit([(t, zc, a, np.ones(t.size, bool))], dt, (0.01, 0.05))
    assert abs(again.t_stat) < 3
    assert again.band_rms_mgal == pytest.approx(fit.band_rms_corrected_mgal, rel=0.01)
    assert again.band_rms_mgal < 0.5 * fit.band_rms_mgal
    # above the low-pass z is left as it was (the broad-band offset fit's)
    from scipy.signal import butter, sosfiltfilt
    hp = butter(4, 0.3, btype="highpass", fs=1 / dt, output="sos")
    assert np.std(sosfiltfilt(hp, zc - z)) < 1e-3 * np.std(sosfiltfilt(hp, z))


def test_band_delay_null_is_calibrated_with_the_gnss_error_in_both_sides():
    """No delay: the t statistic (one independent sample per 1/(2B) s) behaves as N(0, 1),
    although the GNSS acceleration error is in z and in the regressor alike."""
    from app.core.measurement import band_delay_fit
    rng = np.random.default_rng(11)
    dt = 0.2
    t = np.arange(0.0, 3600.0, dt)
    ts = []
    for _ in range(150):
        z, a = _z(rng, t, dt, 0.0, vel_noise_cms=3.0)
        ts.append(band_delay_fit([(t, z, a, np.ones(t.size, bool))], dt, (0.01, 0.05)).t_stat)
    ts = np.abs(np.array(ts))
    assert np.mean(ts > 2.0) < 0.12          # N(0, 1): 4.6 %
    assert np.mean(ts > 4.0) < 0.02
    assert 0.5 < np.sqrt(np.mean(ts ** 2)) < 1.5


def test_band_delay_is_blind_to_an_anomaly_that_follows_the_flight_path():
    """A draped flight: the anomaly rises and falls with the aircraft (δg ∝ its band-passed
    acceleration); the jerk is in quadrature with it, so no delay is read into it."""
    from scipy.signal import butter, sosfiltfilt

    from app.core.measurement import band_delay_fit
    rng = np.random.default_rng(5)
    dt = 0.1
    t = np.arange(0.0, 7200.0, dt)
    sos = butter(4, (0.01, 0.05), btype="bandpass", fs=1 / dt, output="sos")
    z, a = _z(rng, t, dt, 0.0, anomaly=lambda acc: -2e-3 * sosfiltfilt(sos, acc))
    fit = band_delay_fit([(t, z, a, np.ones(t.size, bool))], dt, (0.01, 0.05))
    assert abs(fit.t_stat) < 4 and abs(fit.delay_s) < 1e-3


def test_band_delay_leaves_out_gaps_and_rejects_a_bad_band():
    from app.core.measurement import band_delay_fit
    rng = np.random.default_rng(2)
    dt = 0.1
    t = np.arange(0.0, 3600.0, dt)
    z, a = _z(rng, t, dt, 0.015)
    z[10_000:10_050] = np.nan                    # a gap: bridged for the filter, left out of the fit
    use = np.ones(t.size, bool)
    fit = band_delay_fit([(t, z, a, use)], dt, (0.01, 0.05))
    assert abs(fit.delay_s - 0.015) < max(3 * fit.se_s, 1e-3)
    assert fit.n_epochs < t.size - 2 * 1000       # the gap's margins and the record's ends are out
    short = band_delay_fit([(t[:3000], z[:3000], a[:3000], use[:3000])], dt, (0.01, 0.05))
    assert np.isnan(short.delay_s)                # 300 s, less than 10/(f2 − f1)
    with pytest.raises(ValueError, match="Nyquist"):
        band_delay_fit([(t, z, a, use)], dt, (0.01, 6.0))


def test_band_delay_pools_records_logged_at_different_rates():
    """Two flights of one instrument, GNSS at 10 Hz and at 5 Hz: each is filtered on its own
    step, and the pooled delay and its independent samples count both."""
    from app.core.measurement import band_delay_fit
    rng = np.random.default_rng(7)
    segs, dur = [], 0.0
    for dt in (0.1, 0.2):
        t = np.arange(0.0, 3600.0, dt)
        z, a = _z(rng, t, dt, 0.02)
        segs.append((t, z, a, np.ones(t.size, bool)))
        dur += 3600.0 - 2 * 100.0
    fit = band_delay_fit(segs, None, (0.01, 0.05))
    assert abs(fit.delay_s - 0.02) < max(3 * fit.se_s, 1e-3)
    assert fit.n_independent == pytest.approx(2 * 0.04 * dur, rel=0.01)
    with pytest.raises(ValueError, match="0 < f1 < f2"):
        band_delay_fit(segs, None, (0.05, 0.01))


def test_cumulative_trapezoid_against_scipy():
    """The running trapezoid integral on uneven stamps equals SciPy's (a peer implementation)."""
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.05, 0.15, 500))
    y = np.sin(t) + 0.1 * rng.standard_normal(t.size)
    np.testing.assert_allclose(cumulative_trapezoid(y, t), scipy_ct(y, t, initial=0.0), rtol=1e-12, atol=1e-12)


def test_delay_heterogeneity_is_cochrans_chi2():
    """Two estimates: χ² is (d₁ − d₂)²/(se₁² + se₂²) on one degree of freedom, whose tail is
    erfc(√(χ²/2)); equal estimates agree perfectly; what is not finite is left out."""
    import math

    from app.core.measurement import delay_heterogeneity

    h = delay_heterogeneity([0.010, 0.040], [0.010, 0.020])
    chi2 = 0.030 ** 2 / (0.010 ** 2 + 0.020 ** 2)
    assert h["dof"] == 1 and h["chi2"] == pytest.approx(chi2)
    assert h["p_value"] == pytest.approx(math.erfc(math.sqrt(chi2 / 2.0)))
    assert h["mean_s"] == pytest.approx((0.010 / 1e-4 + 0.040 / 4e-4) / (1 / 1e-4 + 1 / 4e-4))
    same = delay_heterogeneity([0.02, 0.02, 0.02], [0.001, 0.005, 0.01])
    assert same["chi2"] == pytest.approx(0.0, abs=1e-20) and same["p_value"] == pytest.approx(1.0) and same["dof"] == 2
    nan = delay_heterogeneity([0.02, np.nan, 0.03], [0.01, 0.01, np.nan])
    assert nan["dof"] == 0 and np.isnan(nan["p_value"])
    with pytest.raises(ValueError):
        delay_heterogeneity([0.0, 0.1], [0.1])
