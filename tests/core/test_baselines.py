"""Tests of the baseline filters against analytic responses, a peer library and simulations."""

import numpy as np
import pytest

from app.core.baselines import (
    estimate_stationary_qr,
    fir_kernel,
    fir_lowpass_mgal,
    stationary_smooth,
)
from app.core.smoother import kalman_smooth

DT = 0.1


def _fit_sin(t, y, f):
    """Least-squares amplitude and phase of y ≈ a sin(2πft) + b cos(2πft) + c."""
    X = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t), np.ones_like(t)])
    a, b, _ = np.linalg.lstsq(X, y, rcond=None)[0]
    return np.hypot(a, b), np.arctan2(b, a)


# --------------------------------------------------------------------------- FIR


def test_fir_unit_dc_gain_everywhere_including_edges_and_gaps():
    x = np.full(20_000, 37.5)
    x[5000:5300] = np.nan
    x[:3] = np.nan
    y = fir_lowpass_mgal(x, DT)
    assert np.all(np.isfinite(y))
    np.testing.assert_allclose(y, 37.5, rtol=1e-12)
    assert fir_kernel(DT).sum() == pytest.approx(1.0, abs=1e-14)


def test_fir_minus_6db_near_cutoff_and_passband():
    t = np.arange(0, 6000, DT)
    inner = slice(3000, -3000)
    amp_c, _ = _fit_sin(t[inner], fir_lowpass_mgal(np.sin(2 * np.pi * 0.01 * t), DT)[inner], 0.01)
    assert 20 * np.log10(amp_c) == pytest.approx(-6.02, abs=0.5)
    amp_s, _ = _fit_sin(t[inner], fir_lowpass_mgal(np.sin(2 * np.pi * 0.03 * t), DT)[inner], 0.03)
    assert amp_s < 1e-3  # stop band
    amp_p, _ = _fit_sin(t[inner], fir_lowpass_mgal(np.sin(2 * np.pi * 0.002 * t), DT)[inner], 0.002)
    assert amp_p == pytest.approx(1.0, abs=0.03)


def test_fir_zero_phase():
    """A passband sinusoid keeps its phase (no time shift) and gets the DTFT gain."""
    t = np.arange(0, 5000, DT)
    f, ph = 1 / 400.0, 0.7
    y = fir_lowpass_mgal(3.0 * np.sin(2 * np.pi * f * t + ph), DT)
    inner = slice(2000, -2000)
    amp, phase = _fit_sin(t[inner], y[inner], f)
    h = fir_kernel(DT)
    n = np.arange(h.size) - h.size // 2
    gain = np.sum(h * np.cos(2 * np.pi * f * n * DT))
    assert phase == pytest.approx(ph, abs=1e-6)
    assert amp == pytest.approx(3.0 * gain, rel=1e-6)


def test_fir_long_input_and_bad_input():
    rng = np.random.default_rng(0)
    y = fir_lowpass_mgal(rng.normal(size=1_500_000), DT)
    assert y.shape == (1_500_000,) and np.all(np.isfinite(y))
    # white noise variance reduced by Σh²
    assert np.var(y[10_000:-10_000]) == pytest.approx(np.sum(fir_kernel(DT) ** 2), rel=0.15)
    with pytest.raises(ValueError):
        fir_lowpass_mgal(np.ones(100), 0.0)
    with pytest.raises(ValueError):
        fir_lowpass_mgal(np.ones(100), DT, cutoff_period_s=0.1)
    with pytest.raises(ValueError):
        fir_lowpass_mgal(np.ones((3, 3)), DT)


# --------------------------------------------------------------- stationary, ML


def _simulate(rng, T, m, Q, R, dt=DT):
    q = rng.normal(size=T) * np.sqrt(Q)
    dg = q.copy()
    for _ in range(m):
        dg = np.cumsum(dg)
    r = rng.normal(size=T + 1) * np.sqrt(R)
    return dg - 1000.0 * np.diff(r) / dt, dg


def test_stationary_smooth_is_constant_qr_smoother():
    rng = np.random.default_rng(1)
    z, dg = _simulate(rng, 3000, 2, 1e-2, 2.0)
    a = stationary_smooth(z, 1e-2, 2.0, DT, m=2)
    b = kalman_smooth(z, np.full(3000, 1e-2), np.full(3000, 2.0), DT, m=2)
    np.testing.assert_array_equal(a.dg_mgal, b.dg_mgal)
    with pytest.raises(ValueError):
        stationary_smooth(z, np.full(3000, 1e-2), 2.0, DT)


def test_estimate_stationary_qr_recovers_truth():
    rng = np.random.default_rng(5)
    Q, R = 1e-2, 2.0
    lines = [_simulate(rng, 10_000, 2, Q, R)[0] for _ in range(3)]
    est = estimate_stationary_qr(lines, DT, m=2)
    assert 0 < est.se_log_Q < 0.3 and 0 < est.se_log_R < 0.05
    assert abs(np.log(est.Q_mgal2 / Q)) < 4 * est.se_log_Q
    assert abs(np.log(est.R_cm2s2 / R)) < 4 * est.se_log_R
    with pytest.raises(ValueError):
        estimate_stationary_qr([np.ones(2)], DT, m=2)


def test_fir_gap_error_is_the_scale_of_what_a_missing_sample_moves():
    """White z of std σ with one sample missing: over many draws the RMS of the renormalised
    low-pass's departure from the gap-free one is within 15 % of the bound σ·|h_j| near the
    gap, and the bound is zero beyond the kernel; the record's own ends are not gaps."""
    from app.core.baselines import fir_gap_error_mgal, fir_kernel

    rng = np.random.default_rng(3)
    dt, n, j = 0.5, 1200, 600
    sigma = 5000.0
    dev = []
    for _ in range(400):
        z = rng.normal(0.0, sigma, n)
        full = fir_lowpass_mgal(z, dt, 100.0)
        z[j] = np.nan
        dev.append(fir_lowpass_mgal(z, dt, 100.0) - full)
    rms = np.sqrt(np.mean(np.square(dev), axis=0))
    z[j] = np.nan
    bound = fir_gap_error_mgal(z, dt, 100.0)
    half = fir_kernel(dt, 100.0).size // 2
    near = np.arange(j - 20, j + 21)                      # where the kernel weight is large
    np.testing.assert_allclose(rms[near], bound[near], rtol=0.15)
    assert np.all(bound[: j - half - 1] == 0) and np.all(bound[j + half + 2:] == 0)
    z_ends = rng.normal(0.0, sigma, n)
    z_ends[:30] = np.nan
    z_ends[-30:] = np.nan
    assert not fir_gap_error_mgal(z_ends, dt, 100.0).any()


def test_fir_gap_error_at_a_record_end_in_the_air():
    """A record cut out of turbulent air (white z, σ = 5000 mGal): near its ends the
    renormalised low-pass departs from the low-pass of the uncut record, and the bound with
    ``record_ends`` covers that departure (RMS over many draws) and vanishes half a kernel in;
    without ``record_ends`` the ends are not holes."""
    from app.core.baselines import fir_gap_error_mgal, fir_kernel

    rng = np.random.default_rng(7)
    dt, n = 0.5, 1200
    half = fir_kernel(dt, 100.0).size // 2
    dev = []
    for _ in range(300):
        z = rng.normal(0.0, 5000.0, n + 2 * half)
        full = fir_lowpass_mgal(z, dt, 100.0)[half:half + n]
        dev.append(fir_lowpass_mgal(z[half:half + n], dt, 100.0) - full)
    rms = np.sqrt(np.mean(np.square(dev), axis=0))
    bound = fir_gap_error_mgal(z[half:half + n], dt, 100.0, record_ends=True)
    assert rms[0] > 100.0                                   # the effect is real: ~10² mGal
    big = rms[:half] > 1.0                                  # what fir_baseline cares about
    assert np.all(bound[:half][big] >= 0.95 * rms[:half][big])  # is covered
    assert np.all(bound[half + 1:n - half - 1] == 0)
    assert not fir_gap_error_mgal(z[half:half + n], dt, 100.0).any()
    # a flight that starts on quiet ground (σ = 50 mGal) weighs its start with the ground's spread
    zq = np.concatenate([rng.normal(0, 50.0, 600), rng.normal(0, 5000.0, 600)])
    bq = fir_gap_error_mgal(zq, dt, 100.0, record_ends=True)
    assert bq[0] < 50.0 and bq[-1] > 1000.0


def test_fir_gap_error_weighs_a_hole_with_the_spread_next_to_it():
    """A record that is quiet for 70 % of its length (ground time, σ = 50 mGal) and turbulent
    after (σ = 5000): a hole in the turbulent part is weighed with 5000 (the bound at the hole
    is 5000·|h_0| within 10 %), not with the whole record's MAD, which the quiet part sets."""
    from app.core.baselines import fir_gap_error_mgal, fir_kernel

    rng = np.random.default_rng(5)
    dt = 0.5
    z = np.concatenate([rng.normal(0, 50.0, 2800), rng.normal(0, 5000.0, 1200)])
    z[3400] = np.nan
    h0 = abs(fir_kernel(dt, 100.0)).max()
    bound = fir_gap_error_mgal(z, dt, 100.0)
    assert bound[3400] == pytest.approx(5000.0 * h0, rel=0.1)


def test_gaussian_lowpass_matches_scipy_at_any_width():
    """The profiles' Gaussian low-pass against scipy's gaussian_filter1d (the peer), on both of its
    paths: narrow kernels call it, wide ones (> 256 samples of radius) convolve by FFT with the
    same 'nearest' edges and 3σ truncation; NaNs take the mean; sub-sample widths change nothing."""
    from scipy.ndimage import gaussian_filter1d

    from app.core.baselines import gaussian_lowpass

    rng = np.random.default_rng(4)
    x = np.cumsum(rng.normal(0, 1, 20_000)) + rng.normal(0, 30, 20_000)
    for dt, fwhm in ((0.1, 30.0), (0.01, 600.0), (0.1, 600.0)):
        sigma = fwhm / (2.3548 * dt)
        ref = gaussian_filter1d(x, sigma=sigma, mode="nearest", truncate=3.0)
        np.testing.assert_allclose(gaussian_lowpass(x, dt, fwhm), ref, rtol=0, atol=1e-9 * np.abs(x).max())
    y = x.copy()
    y[100:110] = np.nan
    ref = gaussian_filter1d(np.where(np.isfinite(y), y, np.nanmean(y)), sigma=30.0 / (2.3548 * 0.1),
                            mode="nearest", truncate=3.0)
    np.testing.assert_allclose(gaussian_lowpass(y, 0.1, 30.0), ref)
    np.testing.assert_array_equal(gaussian_lowpass(x, 0.1, 0.01), x)
