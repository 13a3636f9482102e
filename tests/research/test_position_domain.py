"""Seed-004 position-domain Kalman filter on a simulated flight with a known anomaly."""

import numpy as np
import pytest

from app.research.position_domain import position_domain_filter

DT = 0.1


def _flight(rng, T_s=3000.0, sigma_h=0.02, sigma_v=0.01):
    t = np.arange(0, T_s + DT / 2, DT)
    dg = 20 * np.sin(2 * np.pi * t / 700) + 8 * np.cos(2 * np.pi * t / 1300 + 1.0)
    k = 25
    w = 2 * np.pi / rng.uniform(4, 80, k)
    amp = rng.uniform(0.02, 0.15, k)
    ph = rng.uniform(0, 2 * np.pi, k)

    def v(tt):
        return np.sum(-amp[:, None] / w[:, None] * np.cos(w[:, None] * tt + ph[:, None]), 0)

    def h(tt):
        return np.sum(-amp[:, None] / w[:, None] ** 2 * np.sin(w[:, None] * tt + ph[:, None]), 0)

    abar = (v(t) - v(t - DT)) / DT  # aircraft acceleration averaged over each interval
    u = abar + 1e-5 * dg + rng.normal(0, 5e-5 / np.sqrt(DT), t.size)  # f − γ + E (m/s²)
    h_m = 1500.0 + h(t) + rng.normal(0, sigma_h, t.size)
    vu = v(t) + rng.normal(0, sigma_v, t.size)
    return t, dg, u, h_m, vu


def test_position_domain_filter_recovers_known_anomaly():
    rng = np.random.default_rng(3)
    t, dg, u, h_m, vu = _flight(rng)
    res = position_domain_filter(t, h_m, u)
    inner = slice(3000, -3000)
    err = res.dg_mgal - dg
    assert np.sqrt(np.mean(err[inner] ** 2)) < 1.0  # mGal, signal amplitude ~28 mGal
    assert res.R == pytest.approx(0.02**2, rel=0.1)  # R from the high-pass part
    assert np.all(res.dg_std_mgal > 0)
    h_gap = h_m.copy()
    h_gap[12_000:12_050] = np.nan  # a 5 s GNSS outage: prediction only
    resg = position_domain_filter(t, h_gap, u, R=res.R)
    assert np.sqrt(np.mean((resg.dg_mgal - dg)[inner] ** 2)) < 1.0
    assert np.all(np.isfinite(resg.dg_mgal))
    resv = position_domain_filter(t, h_m, u, measurement="velocity", vu_gnss_ms=vu)
    assert np.sqrt(np.mean((resv.dg_mgal - dg)[inner] ** 2)) < 3.0
    assert resv.R == pytest.approx(0.01**2, rel=0.1)


def test_position_domain_filter_bad_input():
    t = np.arange(100) * DT
    with pytest.raises(ValueError):
        position_domain_filter(t, np.zeros(99), np.zeros(100))
    with pytest.raises(ValueError):
        position_domain_filter(t[::-1], np.zeros(100), np.zeros(100))
    with pytest.raises(ValueError):
        position_domain_filter(t, np.zeros(100), np.zeros(100), measurement="velocity")
    with pytest.raises(ValueError):
        position_domain_filter(t, np.zeros(100), np.zeros(100), R=-1.0)
