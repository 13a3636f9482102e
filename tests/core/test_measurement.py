"""The measurement z_k of SPEC §1 against physical situations with a known answer."""

import numpy as np
import pytest

from app.core import geodesy
from app.core import gravimeter as gm
from app.core.measurement import anomaly_measurement_mgal, gnss_acceleration_ms2


def test_stationary_gravimeter_on_apron_gives_g_minus_gamma():
    lat, lon, h = 65.4321, 160.05, 220.0
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
