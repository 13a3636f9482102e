"""Tests for app.core.regularize against scipy.signal.freqz, FFTs and analytic inputs."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal
from scipy.special import comb

from app.core.regularize import (
    aliased_power_fraction,
    component_filters,
    design_regularization,
    difference,
    filter_response,
    measure_filter,
    regularize_line,
)


@pytest.fixture(scope="module")
def seed_design():
    return design_regularization(0.1, 100.0)


def _freqz_db(taps, f, fs):
    _, h = signal.freqz(taps, worN=f, fs=fs)
    return 20 * np.log10(np.abs(h))


def test_seed_defaults(seed_design):
    d = seed_design
    assert d.n == 100
    assert d.stop_hz == pytest.approx(0.05)
    assert d.cutoff_hz == pytest.approx(0.0237)
    assert d.width_hz == pytest.approx(2 * (0.05 - 0.0237))
    assert d.dt_dec_s == pytest.approx(10.0)
    h = d.taps
    assert h.size % 2 == 1
    np.testing.assert_allclose(h, h[::-1], atol=0)
    assert h.sum() == pytest.approx(1.0, abs=1e-12)
    # -6 dB (gain 0.5) at the cut-off, as for any window-method design
    assert abs(filter_response(d, d.cutoff_hz).real - 0.5) < 0.01


@pytest.mark.parametrize("att", [60.0, 80.0])
def test_stopband_attenuation_freqz(att):
    d = design_regularization(0.1, 100.0, attenuation_db=att)
    f = np.linspace(d.stop_hz, 5.0, 200_001)
    db = _freqz_db(d.taps, f, 10.0)
    assert db.max() <= -att
    assert measure_filter(d).stopband_attenuation_db >= att


def test_passband_ripple_freqz():
    # a design with a genuine pass band: edge at 0.035 - 0.015 = 0.02 Hz
    d = design_regularization(0.1, 100.0, cutoff_hz=0.035, attenuation_db=60.0)
    assert d.pass_hz == pytest.approx(0.02)
    f = np.linspace(0.0, d.pass_hz, 20_001)
    ripple_db = np.abs(_freqz_db(d.taps, f, 10.0)).max()
    delta = 10 ** (-60 / 20)
    assert ripple_db <= 20 * np.log10(1 + 2 * delta)  # Kaiser: pass ripple ≈ stop ripple δ
    assert measure_filter(d).passband_ripple_db == pytest.approx(ripple_db, rel=0.05)
    att = -_freqz_db(d.taps, np.linspace(d.stop_hz, 5.0, 100_001), 10.0).max()
    assert att >= 60.0


def test_filter_response_matches_fft(seed_design):
    d = seed_design
    nfft = 1 << 16
    H = np.fft.rfft(d.taps, nfft)
    f = np.fft.rfftfreq(nfft, d.dt_s)
    delay = (d.ntaps - 1) / 2
    ref = H * np.exp(2j * np.pi * f * delay * d.dt_s)
    sel = slice(0, 2000)
    np.testing.assert_allclose(filter_response(d, f[sel]), ref[sel], atol=1e-12)
    assert filter_response(d, 0.0).real == pytest.approx(1.0, abs=1e-12)


def test_overrides_and_validation():
    d = design_regularization(0.2, None, n=25, cutoff_hz=0.05)
    assert d.n == 25 and d.stop_hz == pytest.approx(0.1) and d.cutoff_hz == 0.05
    d2 = design_regularization(0.1, 50.0, step_km=0.5)
    assert d2.n == 100
    with pytest.raises(ValueError, match="dt_s"):
        design_regularization(-0.1, 100.0)
    with pytest.raises(ValueError, match="speed_ms"):
        design_regularization(0.1, 0.0)
    with pytest.raises(ValueError, match="speed_ms"):
        design_regularization(0.1, None)
    with pytest.raises(ValueError, match="cutoff_hz"):
        design_regularization(0.1, 100.0, cutoff_hz=0.06)
    with pytest.raises(ValueError, match="n must"):
        design_regularization(0.1, 100.0, n=1)
    with pytest.raises(ValueError, match="attenuation_db"):
        design_regularization(0.1, 100.0, attenuation_db=10)
    with pytest.raises(ValueError, match="step_km"):
        design_regularization(0.1, 100.0, step_km=0.0)
    with pytest.raises(ValueError, match="difference_grid"):
        design_regularization(0.1, 100.0, difference_grid="middle")


@pytest.mark.parametrize("m", [1, 2, 3])
def test_difference_matches_binomial(m):
    rng = np.random.default_rng(m)
    z = rng.normal(size=50)
    coef = np.array([(-1) ** i * comb(m, i, exact=True) for i in range(m + 1)], float)
    np.testing.assert_allclose(difference(z, m), np.convolve(z, coef, mode="valid"), atol=1e-12)
    q = rng.normal(size=200)
    s = q.copy()
    for _ in range(m):
        s = np.cumsum(s)
    np.testing.assert_allclose(difference(s, m), q[m:], atol=1e-9)


@pytest.mark.parametrize("grid", ["decimated", "full"])
@pytest.mark.parametrize("m", [1, 2])
def test_output_length_and_no_nan(grid, m):
    d = design_regularization(0.1, 100.0, difference_grid=grid)
    L, n = d.ntaps, d.n
    for N in (L + m * n, L + m * n + 57, 5000, 12_345):
        z = np.random.default_rng(N).normal(size=N)
        x, idx = regularize_line(z, m, d)
        if grid == "full":
            expected = (N - m - L) // n + 1
        else:
            expected = (N - L) // n + 1 - m
        assert x.size == idx.size == expected
        assert np.all(np.isfinite(x))
        assert np.all(np.diff(idx) == n)
        assert idx.min() >= 0 and idx.max() < N


def test_idx_is_window_centre_quadratic_input(seed_design):
    # z_k = k² (no noise): for the decimated grid and m = 1,
    # x'_k = y(c) − y(c − n) = 2 n (c − n/2) exactly (symmetric unit-gain taps),
    # and c − n/2 is the centre of the effective window.
    d = seed_design
    k = np.arange(6000, dtype=float)
    x, idx = regularize_line(k**2, 1, d)
    np.testing.assert_allclose(x / (2 * d.n), idx, atol=1e-6)
    # full grid, m = 1: x = ∇z = 2k − 1, whose centre is k − 1/2
    dfull = design_regularization(0.1, 100.0, difference_grid="full")
    x2, idx2 = regularize_line(k**2, 1, dfull)
    np.testing.assert_allclose(np.floor(x2 / 2 + 1e-9), idx2, atol=0)


def test_sinusoid_gain_and_phase(seed_design):
    # z = sin(2π f t): decimated-grid output x'_k = |H(f)|·(1 − e^{−iωnΔt})-filtered sinusoid
    d = seed_design
    f0 = 0.01
    t = np.arange(20_000) * d.dt_s
    z = np.sin(2 * np.pi * f0 * t)
    x, idx = regularize_line(z, 1, d)
    H = filter_response(d, f0).real
    # centred y at window centre c, then ∇_n: sin(ω c) − sin(ω (c − nΔt)) = 2 sin(ω nΔt/2) cos(ω (c − nΔt/2))
    tc = idx * d.dt_s
    w = 2 * np.pi * f0
    ref = H * 2 * np.sin(w * d.n * d.dt_s / 2) * np.cos(w * tc)
    np.testing.assert_allclose(x, ref, atol=1e-9)


def test_line_errors(seed_design):
    d = seed_design
    need = d.ntaps + 2 * d.n
    with pytest.raises(ValueError, match=f"at least {need}"):
        regularize_line(np.zeros(need - 1), 2, d)
    z = np.zeros(5000)
    z[1234] = np.nan
    with pytest.raises(ValueError, match="1234"):
        regularize_line(z, 1, d)
    with pytest.raises(ValueError, match="m must"):
        regularize_line(np.zeros(5000), 0, d)


def test_aliasing_fraction_independent_fft(seed_design):
    d = seed_design
    for m in (1, 2):
        _, g_r = component_filters(d, m)
        nfft = 1 << 18
        P = np.abs(np.fft.rfft(g_r, nfft)) ** 2
        f = np.fft.rfftfreq(nfft, d.dt_s)
        ref = P[f >= d.stop_hz].sum() / P.sum()
        got = aliased_power_fraction(g_r, d.dt_s, d.n, np.ones_like)
        assert got == pytest.approx(ref, rel=0.02, abs=1e-6)
        # the default (difference on the decimated grid) keeps aliasing below 1 %
        assert measure_filter(d, m).aliased_fraction < 0.01


def test_full_grid_difference_aliases_gnss_noise():
    # documents why difference_grid defaults to "decimated": with ∇^m at full rate the
    # f^{2(m+1)} GNSS spectrum leaks through the 60 dB Kaiser side-lobes and dominates.
    d = design_regularization(0.1, 100.0, difference_grid="full")
    dt = d.dt_s
    for m in (1, 2):
        def psd(f, m=m):
            return (2 * np.sin(np.pi * f * dt)) ** (2 * (m + 1))

        frac = aliased_power_fraction(d.taps, dt, d.n, psd)
        assert frac > 0.5
        assert measure_filter(d, m).aliased_fraction == pytest.approx(frac, rel=0.02)
