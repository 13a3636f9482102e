"""The measurement z_k of SPEC §1 against physical situations with a known answer."""

import numpy as np
import pytest

from app.core import geodesy
from app.core import gravimeter as gm
from app.core.measurement import anomaly_measurement_mgal, gnss_acceleration_ms2


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
