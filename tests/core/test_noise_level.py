"""Local GNSS noise level estimators against noise of known spectrum."""

import numpy as np
import pytest
from scipy.signal import butter, sosfreqz

from app.core.noise_level import (
    band_fit_coefficient,
    band_noise_variance_cm2s2,
    band_rms_mgal,
    local_noise_variance_cm2s2,
    white_band_gain,
)

DT = 0.1


def _z_noise(v_cms):
    """z noise (mGal) of a GNSS vertical-velocity error series (cm/s)."""
    return -1000.0 * np.diff(v_cms) / DT


def test_white_gain_matches_parseval():
    # the band gain equals the variance of band-passed white-velocity noise (Monte Carlo)
    from scipy.signal import sosfiltfilt

    rng = np.random.default_rng(0)
    z = _z_noise(rng.standard_normal(400_001))
    sos = butter(4, (0.1, 0.5), btype="bandpass", fs=1 / DT, output="sos")
    y = sosfiltfilt(sos, z)[5000:-5000]
    assert np.var(y) == pytest.approx(white_band_gain(DT, (0.1, 0.5)), rel=0.03)


def test_band_level_of_white_noise_with_an_episode():
    rng = np.random.default_rng(1)
    n = 60_000
    sig = np.full(n + 1, 1.3)
    sig[20_000:26_000] *= 4.0                      # a 600 s noisy episode
    est = band_noise_variance_cm2s2(_z_noise(rng.standard_normal(n + 1) * sig), DT)
    assert np.median(est[2000:18_000]) == pytest.approx(1.69, rel=0.08)
    assert np.median(est[21_000:25_000]) == pytest.approx(16 * 1.69, rel=0.08)
    # no edge blow-up (the average is reflected at the ends, not padded with the edge value)
    assert np.max(est[:300]) < 2.5 * 1.69 and np.max(est[-300:]) < 2.5 * 1.69


@pytest.mark.parametrize("gap_s", [0.5, 2.0, 30.0])
def test_band_level_is_not_raised_next_to_a_gap(gap_s):
    """White velocity noise of known level (1.69 (cm/s)²) with a hole in z every 500 s: each
    run is band-passed on its own, so within 15 s of a hole R(t) stays near the level.
    Interpolated across the hole, the ramp from one noise value of z (±10⁴ mGal) to the next
    lay in the band: 7× (0.5 s) to 150× (30 s) the level there."""
    rng = np.random.default_rng(7)
    n = 60_000
    z = _z_noise(rng.standard_normal(n + 1) * 1.3)
    g = max(1, int(round(gap_s / DT)))
    starts = np.arange(3000, n - 3000, 5000)
    for s in starts:
        z[s:s + g] = np.nan
    est = band_noise_variance_cm2s2(z, DT)
    dist = np.min(np.abs(np.arange(n)[:, None] - np.r_[starts, starts + g][None, :]), axis=1) * DT
    near = np.isfinite(z) & (dist < 15.0)
    assert np.median(est[near]) == pytest.approx(1.69, rel=0.25)
    assert np.quantile(est[near], 0.9) < 2.0 * 1.69
    assert np.median(est[np.isfinite(z) & (dist > 60.0)]) == pytest.approx(1.69, rel=0.08)


def test_band_level_runs_end_where_the_clock_jumps():
    """A quiet static record (the apron, 0.1 cm/s) and then, ten minutes later on the clock
    but next in the file, a loud flight (3 cm/s): given the times, the apron's level is its
    own; without them the band-pass runs across the jump and the flight's noise leaks in."""
    rng = np.random.default_rng(9)
    quiet = _z_noise(rng.standard_normal(1201) * 0.1)       # 120 s
    loud = _z_noise(rng.standard_normal(6001) * 3.0)        # 600 s
    z = np.r_[quiet, loud]
    t = np.r_[np.arange(1200) * DT, 720.0 + np.arange(6000) * DT]
    apron = slice(0, 1200)
    own = band_noise_variance_cm2s2(z, DT, t_s=t)[apron]
    assert np.median(own) == pytest.approx(0.01, rel=0.3) and np.max(own) < 2 * 0.01
    assert np.max(band_noise_variance_cm2s2(z, DT)[apron]) > 100 * 0.01


def test_band_level_of_position_derived_velocity_noise():
    # velocities differenced from white positions (std σ_p): power ∝ sin²(πfΔt), i.e.
    # far less at low frequency; the band estimate must be the analytic band average,
    # far below the Nyquist-dominated high-frequency estimate
    rng = np.random.default_rng(2)
    sig_p_cm = 0.2
    e = rng.standard_normal(200_002) * sig_p_cm
    v = np.diff(e) / DT
    z = _z_noise(v)
    band = (0.1, 0.5)
    sos = butter(4, band, btype="bandpass", fs=1 / DT, output="sos")
    f, h = sosfreqz(sos, worN=1 << 16, fs=1 / DT)
    s2 = 4 * np.sin(np.pi * f * DT) ** 2
    w = (1000 / DT) ** 2 * DT * s2 * np.abs(h) ** 4
    expected = np.trapezoid(w * sig_p_cm ** 2 * s2 / DT ** 2, f) / np.trapezoid(w, f)
    est = band_noise_variance_cm2s2(z, DT, band)
    assert np.mean(est[3000:-3000]) == pytest.approx(expected, rel=0.05)
    hf = local_noise_variance_cm2s2(z, DT)
    assert np.median(hf) > 5 * np.median(est)


def _turbulence_mgal(rng, n, rms_mgal=30_000.0, peak_hz=0.3):
    """Peaked turbulence acceleration (mGal): white noise through a resonant AR(2)."""
    from scipy.signal import lfilter

    r, w = 0.995, 2 * np.pi * peak_hz * DT
    a = lfilter([1.0], [1.0, -2 * r * np.cos(w), r * r], rng.standard_normal(n + 2000))[2000:]
    return a / np.std(a) * rms_mgal


def _boxcars(x, width_s, count):
    """A gravimeter's internal filter: ``count`` centred boxcars of ``width_s``."""
    k = int(round(width_s / DT)) | 1
    for _ in range(count):
        x = np.convolve(x, np.ones(k) / k, mode="same")
    return x


def test_band_level_less_the_response_mismatch():
    # z = f_z − ḧ: the gravimeter's filter (two 0.5 s boxcars) passes 0.3 Hz turbulence at
    # 0.93, so 7 % of 30,000 mGal stays in z — far above the GNSS noise (R = 1.69 (cm/s)²)
    # and swinging with the turbulence, not the GNSS.  The band level less the part linear in
    # f_z is the GNSS noise's again, turbulence episode or not.
    rng = np.random.default_rng(3)
    n = 60_000
    acc = _turbulence_mgal(rng, n)
    acc[30_000:] *= 3.0                                      # a rough half
    f_z = _boxcars(acc, 0.5, 2)
    z = f_z - acc + _z_noise(rng.standard_normal(n + 1) * 1.3)
    plain = band_noise_variance_cm2s2(z, DT)
    unmixed = band_noise_variance_cm2s2(z, DT, regressor_mgal=f_z)
    assert np.median(plain[2000:28_000]) > 5 * 1.69          # the mismatch dominates...
    assert np.median(plain[32_000:-2000]) > 5 * np.median(plain[2000:28_000])  # ...and follows the turbulence
    assert np.median(unmixed[2000:28_000]) == pytest.approx(1.69, rel=0.1)
    assert np.median(unmixed[32_000:-2000]) == pytest.approx(1.69, rel=0.1)
    # with no mismatch (f_z follows the aircraft exactly) the regression takes nothing away
    z0 = acc * 0.0 + _z_noise(rng.standard_normal(n + 1) * 1.3)
    both = band_noise_variance_cm2s2(z0, DT), band_noise_variance_cm2s2(z0, DT, regressor_mgal=acc)
    assert np.median(both[1]) == pytest.approx(np.median(both[0]), rel=0.02)
    with pytest.raises(ValueError, match="regressor"):
        band_noise_variance_cm2s2(z, DT, regressor_mgal=f_z[:-1])


def test_band_level_bad_input():
    with pytest.raises(ValueError):
        band_noise_variance_cm2s2(np.ones(10), DT)
    with pytest.raises(ValueError):
        band_noise_variance_cm2s2(np.ones(1000), DT, band_hz=(0.3, 6.0))
    with pytest.raises(ValueError):
        band_noise_variance_cm2s2(np.full(1000, np.nan), DT)


def test_band_rms_of_a_sine_in_band_and_out():
    """A sine inside the band keeps its RMS A/√2, sines outside it (and a gap) do not count."""
    t = np.arange(0.0, 3600.0, 0.5)
    z = 3.0 * np.sin(2 * np.pi * 0.03 * t) + 50.0 * np.sin(2 * np.pi * 0.002 * t) + 10.0 * np.sin(2 * np.pi * 0.3 * t)
    rms, n = band_rms_mgal(z, 0.5, (0.02, 0.05))
    assert rms == pytest.approx(3.0 / np.sqrt(2.0), rel=2e-3) and n == t.size - 2 * 200
    usable = np.ones(t.size, bool)
    usable[3000:3100] = False                                  # two stretches, each trimmed at both ends
    z[3050] = np.nan
    rms2, n2 = band_rms_mgal(z, 0.5, (0.02, 0.05), usable=usable)
    assert rms2 == pytest.approx(3.0 / np.sqrt(2.0), rel=5e-3) and n2 == t.size - 100 - 4 * 200
    assert np.isnan(band_rms_mgal(z[:400], 0.5, (0.02, 0.05))[0])          # shorter than 3 × 100 s
    with pytest.raises(ValueError, match="band_hz"):
        band_rms_mgal(z, 0.5, (0.02, 1.5))


@pytest.mark.parametrize("order", [0, 1, 2])
def test_band_rms_of_blue_noise(order):
    """White noise differenced ``order`` times (a velocity error differenced: 1; heights: 2) has
    the analytic band RMS √(∫ 2Δt·(2 sin πfΔt)^{2·order}/Δt^{2·order} df) — ringing from the ends of
    the stretches (noise far above the band) must not enter it."""
    dt = 0.1
    band = (0.02, 0.05)
    rng = np.random.default_rng(7)
    w = rng.standard_normal(36_000 + order)
    z = np.diff(w, order) / dt ** order if order else w
    f = np.linspace(*band, 2001)
    psd = 2 * dt * (2 * np.sin(np.pi * f * dt)) ** (2 * order) / dt ** (2 * order)
    want = np.sqrt(np.trapezoid(psd, f))
    usable = np.ones(z.size, bool)
    usable[::4000] = False                                     # 9 stretches of 400 s
    rms, n = band_rms_mgal(z, dt, band, usable=usable)
    # the zero-phase Butterworth's squared response passes ≈ 0.85 of a flat band's power
    assert rms == pytest.approx(want, rel=0.2)


def _jerk_and_noise(rng, n, dt, order):
    """A band-limited 'jerk' x (a random phugoid-like process, 0.01–0.1 Hz) and white noise
    differenced ``order`` times (blue, like z's GNSS noise)."""
    from scipy.signal import sosfiltfilt
    sos = butter(2, (0.01, 0.1), btype="bandpass", fs=1 / dt, output="sos")
    x = sosfiltfilt(sos, rng.standard_normal(n)) * 300.0
    w = rng.standard_normal(n + order) * 5.0
    e = np.diff(w, order) / dt ** order if order else w
    return x, e


@pytest.mark.parametrize("order", [0, 1, 2])
def test_band_fit_recovers_a_known_coefficient_with_a_calibrated_error(order):
    """``y = a − c·x + e`` (a an out-of-band 'anomaly', e blue noise): the band fit recovers c,
    and over 60 records its standard error matches the scatter of the estimates (the band's
    independent samples counted, not the epochs)."""
    dt, n, band, c_true = 0.5, 7200, (0.02, 0.05), 0.06
    rng = np.random.default_rng(11 + order)
    t = np.arange(n) * dt
    zs = []
    for _ in range(60):
        x, e = _jerk_and_noise(rng, n, dt, order)
        y = 40.0 * np.sin(2 * np.pi * 0.002 * t + rng.uniform(0, 6.3)) - c_true * x + e
        fit = band_fit_coefficient(y, x, dt, band)
        assert fit.n_epochs == n - 2 * 200 and fit.dof == pytest.approx(2 * 0.03 * fit.n_epochs * dt)
        assert fit.rms_after_mgal < fit.rms_before_mgal
        zs.append((fit.coef - c_true) / fit.se)
    zs = np.asarray(zs)
    assert abs(zs.mean()) < 0.5                       # unbiased
    assert 0.7 < zs.std() < 1.4                       # the error is the estimates' real scatter


def test_band_fit_of_unrelated_records_and_bad_input():
    """A regressor with nothing in common with y gives c within its error of 0; a regressor
    with no band power gives NaN; shapes and bands are checked."""
    dt, n = 0.5, 7200
    rng = np.random.default_rng(3)
    x, e = _jerk_and_noise(rng, n, dt, 1)
    fit = band_fit_coefficient(e, x, dt, (0.02, 0.05))
    assert abs(fit.coef) < 3 * fit.se and fit.rms_after_mgal == pytest.approx(fit.rms_before_mgal, rel=0.02)
    flat = band_fit_coefficient(e, np.ones(n), dt, (0.02, 0.05))
    assert np.isnan(flat.coef) and flat.n_epochs > 0
    with pytest.raises(ValueError, match="shape"):
        band_fit_coefficient(e, x[:-1], dt, (0.02, 0.05))
    with pytest.raises(ValueError, match="band_hz"):
        band_fit_coefficient(e, x, dt, (0.02, 1.5))



def test_elevated_runs_by_hand():
    from app.core.noise_level import Run, elevated_runs

    t = np.arange(20.0) * 0.5                       # 2 Hz
    v = np.zeros(20)
    v[2:5] = 5.0                                    # 1.0–2.0 s: three samples, 1.5 s
    v[6:8] = 5.0                                    # 3.0–3.5 s: gap 1.0 s after the first
    v[15] = 9.0                                     # one sample, 0.5 s
    v[10] = np.nan                                  # NaN is never above
    assert elevated_runs(v, t, 1.0) == [Run(2, 5), Run(6, 8), Run(15, 16)]
    assert elevated_runs(v, t, 1.0, bridge_s=1.0) == [Run(2, 8), Run(15, 16)]
    assert elevated_runs(v, t, 1.0, bridge_s=0.99) == [Run(2, 5), Run(6, 8), Run(15, 16)]
    assert elevated_runs(v, t, 1.0, min_duration_s=1.5) == [Run(2, 5)]
    assert elevated_runs(v, t, 1.0, min_duration_s=1.51) == []
    assert elevated_runs(v, t, 1.0, min_duration_s=2.0, bridge_s=1.0) == [Run(2, 8)]
    assert elevated_runs(v, t, 6.0) == [Run(15, 16)]
    assert elevated_runs(np.full(4, 2.0), np.arange(4.0), 1.0) == [Run(0, 4)]   # to both ends
    assert elevated_runs(np.zeros(0), np.zeros(0), 1.0) == []


def test_elevated_runs_rejects_bad_input():
    from app.core.noise_level import elevated_runs

    with pytest.raises(ValueError, match="increasing"):
        elevated_runs(np.zeros(3), np.array([0.0, 2.0, 1.0]), 1.0)
    with pytest.raises(ValueError, match="one length"):
        elevated_runs(np.zeros(3), np.arange(4.0), 1.0)
    with pytest.raises(ValueError, match="threshold"):
        elevated_runs(np.zeros(3), np.arange(3.0), np.nan)
    with pytest.raises(ValueError, match=">= 0"):
        elevated_runs(np.zeros(3), np.arange(3.0), 1.0, min_duration_s=-1.0)


def test_band_level_episode_is_found_where_it_was_drawn():
    # white velocity noise with a ×4 std episode (R ×16) at 2000–2600 s: the band level R(t)
    # above 4× its median marks that stretch, to within the 60 s averaging window
    from app.core.noise_level import elevated_runs

    rng = np.random.default_rng(7)
    n = 60_000
    sig = np.full(n + 1, 1.0)
    sig[20_000:26_000] *= 4.0
    r = band_noise_variance_cm2s2(_z_noise(rng.standard_normal(n + 1) * sig), DT)
    t = np.arange(n) * DT
    runs = elevated_runs(r, t, 4.0 * np.median(r), min_duration_s=30.0, bridge_s=10.0)
    assert len(runs) == 1
    assert abs(t[runs[0].start] - 2000.0) < 30.0 and abs(t[runs[0].stop - 1] - 2600.0) < 30.0
