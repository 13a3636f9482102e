"""The gravimeter's response width (app.core.response) against analytic filters and simulated
accelerations with known widths."""

import numpy as np
import pytest
from scipy.signal import butter, sosfiltfilt

from app.core import response as resp

DT = 0.1


def _turbulence(n: int, rng, peak_hz: float = 0.4) -> np.ndarray:
    """Aircraft-like vertical acceleration (m/s², ~0.4 RMS): white noise band-passed at
    0.05–1.5 Hz around ``peak_hz``, plus a slow phugoid."""
    sos = butter(2, [0.05, 1.5], btype="band", fs=1.0 / DT, output="sos")
    a = sosfiltfilt(sos, rng.standard_normal(n))
    t = np.arange(n) * DT
    a = 0.4 * a / a.std() + 0.05 * np.sin(2 * np.pi * t / 60.0)
    return a


def _boxcar(x: np.ndarray, width_s: float) -> np.ndarray:
    """Centred running mean over ``width_s`` (an odd number of samples)."""
    k = int(round(width_s / DT)) | 1
    return np.convolve(np.pad(x, k, mode="reflect"), np.ones(k) / k, mode="same")[k:-k]


def test_gaussian_response_is_the_analytic_transfer_function():
    f = np.array([0.0, 0.1, 0.5, 1.0])
    c = 0.02
    np.testing.assert_allclose(resp.gaussian_response(f, c), np.exp(-c * (2 * np.pi * f) ** 2))


def test_smooth_response_attenuates_a_sinusoid_by_the_transfer_function():
    t = np.arange(20000) * DT
    c = 0.03
    for f_hz in (0.05, 0.3, 0.8):
        x = np.sin(2 * np.pi * f_hz * t)
        y = resp.smooth_response(x, DT, c)
        mid = slice(2000, -2000)
        gain = np.sqrt(2.0 * np.mean(y[mid] ** 2))
        assert gain == pytest.approx(np.exp(-c * (2 * np.pi * f_hz) ** 2), rel=2e-3)
        # zero phase: the output is in step with the input
        assert np.corrcoef(x[mid], y[mid])[0, 1] > 0.9999


def test_smooth_response_keeps_gaps_and_is_identity_at_zero_width():
    x = np.sin(np.arange(500) * 0.1)
    x[100:103] = np.nan
    y = resp.smooth_response(x, DT, 0.01)
    assert np.isnan(y[100:103]).all() and np.isfinite(np.delete(y, [100, 101, 102])).all()
    np.testing.assert_array_equal(resp.smooth_response(x, DT, 0.0), x)
    with pytest.raises(ValueError, match="≥ 0"):
        resp.smooth_response(x, DT, -0.01)


@pytest.mark.parametrize("noise_ms2", [0.0, 0.05])
def test_fit_recovers_a_gaussian_width_unbiased_by_the_gnss_noise(noise_ms2):
    rng = np.random.default_rng(1)
    a = _turbulence(40000, rng)
    c_true = 0.015
    g = resp.smooth_response(a, DT, c_true)                       # the gravimeter's reading
    gnss = a + noise_ms2 * rng.standard_normal(a.size)            # white GNSS error
    fit = resp.fit_response_width(g, gnss, DT, (0.01, 1.0))
    assert fit.c_s2 == pytest.approx(c_true, rel=0.03), fit
    assert fit.c_s2 > 3 * fit.se_s2
    assert fit.relative_improvement > 0.3


def test_fit_reads_two_boxcars_as_their_second_moment():
    # a 2 Hz platform's decimation filter: two boxcars of 0.5 s, H(ω) = 1 − (T²/12)·ω² + …; the
    # Gaussian of the same second moment is fitted, to within the shapes' difference above 0.5 Hz
    rng = np.random.default_rng(2)
    a = _turbulence(40000, rng)
    g = _boxcar(_boxcar(a, 0.5), 0.5)
    fit = resp.fit_response_width(g, a + 0.01 * rng.standard_normal(a.size), DT, (0.01, 0.8))
    assert fit.c_s2 == pytest.approx(0.5 ** 2 / 12, rel=0.15), fit
    assert fit.relative_improvement > 0.5


def test_matched_records_fit_no_width_whatever_the_gnss_noise():
    # the same interval means on both sides, the GNSS acceleration differenced from heights with
    # 1 cm of white error (2.5 m/s² RMS, blue): smoothing the GNSS side would lower the residual by
    # removing noise and read c ≈ 0.004 s² into a meter that has none; undoing the response on the
    # gravimeter's side reads none
    rng = np.random.default_rng(3)
    a = _turbulence(30000, rng)
    noise = np.diff(0.01 * rng.standard_normal(a.size + 2), 2) / DT ** 2
    fit = resp.fit_response_width(a, a + noise, DT, (0.01, 1.0))
    assert fit.c_s2 < 0.001 and fit.c_s2 < 3 * fit.se_s2, fit
    assert fit.relative_improvement < 0.01, fit


def test_fit_refuses_too_short_or_mismatched_records():
    with pytest.raises(ValueError, match="200"):
        resp.fit_response_width(np.zeros(100), np.zeros(100), DT, (0.01, 1.0))
    with pytest.raises(ValueError, match="same length"):
        resp.fit_response_width(np.zeros(300), np.zeros(301), DT, (0.01, 1.0))


def test_matching_change_stays_inside_each_stretch():
    # two stretches with a gap: each is filtered alone (a step at the gap would otherwise leak
    # across it), a stretch of 2 samples and the missing samples take no change
    t = np.concatenate([np.arange(300) * DT, 100.0 + np.arange(300) * DT, [200.0, 200.1]])
    acc = np.concatenate([np.sin(2 * np.pi * 0.7 * t[:300]), 5.0 + np.cos(2 * np.pi * 0.3 * t[300:600]), [9.0, 9.0]])
    acc[10] = np.nan
    runs = [(0, 300), (300, 600), (600, 602)]
    out = resp.matching_change(acc, t, 0.02, runs)
    first = acc[:300] - resp.smooth_response(acc[:300], DT, 0.02)
    np.testing.assert_allclose(out[:300], np.where(np.isfinite(first), first, 0.0), atol=1e-9)
    np.testing.assert_allclose(out[300:600], acc[300:600] - resp.smooth_response(acc[300:600], DT, 0.02), atol=1e-9)
    assert out[10] == 0.0 and np.all(out[600:] == 0.0)
    # away from the ends a sinusoid loses 1 − exp(−c·ω²) of itself
    mid = slice(100, 200)
    np.testing.assert_allclose(out[mid], (1 - np.exp(-0.02 * (2 * np.pi * 0.7) ** 2)) * acc[mid], atol=2e-3)
