"""The gravimeter's response relative to the GNSS acceleration: a zero-phase smoothing width
fitted from the data.

A gravimeter that outputs point samples behind a decimation filter (a stabilised-platform
meter's sinc² of two one-period boxcars, an anti-alias Gaussian) reads the aircraft's
acceleration smoothed, while the GNSS acceleration ``(V_k − V_{k−1})/Δt`` is a mean over one
GNSS step.  The two then differ by ``(1 − H(ω))·a(ω)``; at low frequency any such symmetric
filter is ``H(ω) ≈ 1 − c·ω²`` (``c`` is half the filter's variance in s²: two boxcars of
``T`` s give ``c = T²/12``), and ``c·ä̈`` of 0.3–0.5 m/s² turbulence is hundreds to thousands of
mGal of z at 0.05–0.5 Hz, which the noise model must then absorb.  Smoothing the GNSS
acceleration by the zero-phase Gaussian ``exp(−c·ω²)`` with ``c`` fitted to the band-passed
residual takes most of it out.  Pure functions on numpy arrays; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.signal import butter, sosfiltfilt

from app.core.gravimeter import fill_nan

__all__ = ["gaussian_response", "smooth_response", "matching_change", "ResponseWidthFit", "fit_response_width"]


def gaussian_response(f_hz, c_s2: float) -> np.ndarray:
    """Transfer function ``exp(−c·ω²)`` of the zero-phase Gaussian (ω = 2πf rad/s).

    Parameters
    ----------
    f_hz : array_like
        Frequencies (Hz).
    c_s2 : float
        Width ``c`` (s², ≥ 0): the Gaussian impulse response's variance is ``2c`` s².
    """
    w = 2.0 * np.pi * np.asarray(f_hz, dtype=float)
    return np.exp(-float(c_s2) * w * w)


def _padded_spectrum(x: np.ndarray, pad: int) -> tuple[np.ndarray, int]:
    """rfft of ``x`` mirrored by ``pad`` samples at both ends (no wrap-around at the edges)."""
    pad = int(min(pad, x.size - 1))
    xp = np.concatenate([x[pad:0:-1], x, x[-2:-pad - 2:-1]]) if pad > 0 else x
    return np.fft.rfft(xp), pad


def smooth_response(x, dt_s: float, c_s2: float) -> np.ndarray:
    """``x`` (uniformly sampled every ``dt_s`` s, shape (n,)) through the zero-phase Gaussian
    :func:`gaussian_response` of width ``c_s2`` (s²), by FFT with the record mirrored at its ends.
    Non-finite samples are bridged linearly for the filter and stay non-finite in the result;
    ``c_s2 = 0`` returns a copy.  Exact in the frequency domain, not
    :func:`app.core.baselines.gaussian_lowpass`'s sampled kernel: the widths here are a fraction
    of a sample to two samples (0.4 of a 2 Hz step), where a sampled kernel's transfer function is
    not the ``exp(−c·ω²)`` the width was fitted for."""
    x = np.asarray(x, dtype=float)
    if x.ndim != 1:
        raise ValueError("smooth_response needs a 1-D series")
    if not (np.isfinite(c_s2) and c_s2 >= 0.0):
        raise ValueError(f"response width must be finite and ≥ 0 s², got {c_s2!r}")
    if not (np.isfinite(dt_s) and dt_s > 0.0):
        raise ValueError(f"sample step must be finite and > 0 s, got {dt_s!r}")
    bad = ~np.isfinite(x)
    if c_s2 == 0.0 or x.size < 3 or bad.all():
        return x.copy()
    y = fill_nan(x)
    # the Gaussian's impulse response has σ = √(2c) s: 8σ of mirror leaves nothing to wrap around
    pad = int(np.ceil(8.0 * np.sqrt(2.0 * c_s2) / dt_s)) + 1
    spec, pad = _padded_spectrum(y, pad)
    n = y.size + 2 * pad
    out = np.fft.irfft(spec * gaussian_response(np.fft.rfftfreq(n, dt_s), c_s2), n)[pad:pad + y.size]
    out[bad] = np.nan
    return out


def matching_change(acc, t_s, c_s2: float, runs) -> np.ndarray:
    """``acc − G_c·acc`` (the units of ``acc``, shape (n,)): what replacing a record's acceleration
    by its :func:`smooth_response` of width ``c_s2`` (s²) takes away, the filter applied per
    contiguous stretch ``runs`` (index ranges ``[i0, i1)``, each on its own median step ``t_s``
    in s; none reaches across a gap); 0 where ``acc`` is missing and on stretches under 3 samples."""
    acc = np.asarray(acc, dtype=float)
    t = np.asarray(t_s, dtype=float)
    if acc.shape != t.shape or acc.ndim != 1:
        raise ValueError("acc and t_s must be 1-D arrays of the same length")
    out = np.zeros_like(acc)
    for i0, i1 in runs:
        if i1 - i0 < 3:
            continue
        seg = acc[i0:i1]
        d = seg - smooth_response(seg, float(np.median(np.diff(t[i0:i1]))), c_s2)
        out[i0:i1] = np.where(np.isfinite(d), d, 0.0)
    return out


@dataclass(frozen=True)
class ResponseWidthFit:
    """Result of :func:`fit_response_width`.

    Attributes
    ----------
    c_s2 : float
        Width ``c`` (s²) of the Gaussian ``exp(−c·ω²)`` that, applied to the GNSS acceleration,
        best matches the gravimeter's in the band (0 when no smoothing helps).
    se_s2 : float
        Its standard error (s²), from the curvature of the residual variance and the band's
        effective number of independent samples ``2·B·T`` (inf where the curvature is not positive).
    cost_zero, cost_min : float
        Mean square band-passed residual ``g/H_c − a`` (m²/s⁴) at c = 0 and at ``c_s2``.
    """

    c_s2: float
    se_s2: float
    cost_zero: float
    cost_min: float

    @property
    def relative_improvement(self) -> float:
        """Share of the band-passed residual variance the smoothing removes."""
        return float((self.cost_zero - self.cost_min) / self.cost_zero) if self.cost_zero > 0 else 0.0


def fit_response_width(g_ms2, acc_ms2, dt_s: float, band_hz: tuple[float, float],
                       max_c_s2: float = 1.0) -> ResponseWidthFit:
    """The Gaussian width ``c`` (s²) that best turns the GNSS acceleration into the gravimeter's.

    Both series are band-passed (4th-order Butterworth, zero phase, ``band_hz``), where the
    aircraft's acceleration dominates both and the anomaly is negligible; the residual
    ``g/H_c − a`` (``H_c = exp(−c·ω²)``) is evaluated in the frequency domain (Parseval) and its
    mean square minimised over ``0 ≤ c ≤ max_c_s2``.  The GNSS side ``a`` carries the noise, the
    gravimeter's hardly any, so undoing the response on the gravimeter's side leaves the noise
    a constant of the residual and the minimum unbiased by it.

    Parameters
    ----------
    g_ms2 : array_like, shape (n,)
        The gravimeter's specific force on the GNSS intervals (m/s², time offset and lag undone).
    acc_ms2 : array_like, shape (n,)
        The GNSS vertical acceleration on the same intervals (m/s²).
    dt_s : float
        GNSS step (s).
    band_hz : (float, float)
        Pass band of the comparison (Hz); its top is held below 0.45 of the sample rate.
    max_c_s2 : float
        Upper end of the search (s²), held to ``4/ω_top²`` (``exp(c·ω²) ≤ e⁴`` at the band's top).

    Returns
    -------
    ResponseWidthFit
    """
    g = np.asarray(g_ms2, dtype=float)
    a = np.asarray(acc_ms2, dtype=float)
    if g.shape != a.shape or g.ndim != 1:
        raise ValueError("g_ms2 and acc_ms2 must be 1-D series of the same length")
    if g.size < 200:
        raise ValueError("need at least 200 epochs to fit the response width")
    ok = np.isfinite(g) & np.isfinite(a)
    if ok.sum() < 200:
        raise ValueError("need at least 200 epochs with both accelerations to fit the response width")
    fs = 1.0 / float(dt_s)
    lo, hi = float(band_hz[0]), min(float(band_hz[1]), 0.45 * fs)
    if not 0.0 < lo < hi:
        raise ValueError(f"empty comparison band {band_hz!r} at a {fs:g} Hz sample rate")
    sos = butter(4, [lo, hi], btype="band", fs=fs, output="sos")
    gb = sosfiltfilt(sos, fill_nan(np.where(ok, g, np.nan)))     # both bridged where either is missing
    ab = sosfiltfilt(sos, fill_nan(np.where(ok, a, np.nan)))
    f = np.fft.rfftfreq(g.size, dt_s)
    # the band's bins only (outside it the band-pass left little of either, and undoing the
    # response there would amplify that little by exp(c·ω²)); interior bins count twice
    # (one-sided spectrum), and the band's top bounds the search: exp(c·ω²) ≤ e⁴ there
    inband = (f >= lo) & (f <= hi)
    G, A = np.fft.rfft(gb)[inband], np.fft.rfft(ab)[inband]
    f = f[inband]
    wt = 2.0
    norm = float(g.size) ** 2
    max_c_s2 = min(float(max_c_s2), 4.0 / (2.0 * np.pi * hi) ** 2)

    def cost(c):
        # the gravimeter's side undone (G/H_c), not the GNSS side smoothed (H_c·A): the GNSS
        # acceleration's own noise (differenced velocities or heights, white to blue) is then a
        # constant of the residual, where smoothing it would lower the residual by removing
        # noise and read a width into a meter that has none (5 Hz heights: 0.004-0.006 s²)
        r = G / gaussian_response(f, c) - A
        return float(np.sum(wt * (r.real ** 2 + r.imag ** 2)) / norm)

    res = minimize_scalar(cost, bounds=(0.0, float(max_c_s2)), method="bounded", options={"xatol": 1e-6})
    c = float(res.x)
    c0, cmin = cost(0.0), cost(c)
    if cmin > c0:
        c, cmin = 0.0, c0
    h = max(1e-4, 0.05 * c)
    if c >= h:      # central second difference; forward at the search's lower end
        curv = (cost(c + h) - 2.0 * cmin + cost(c - h)) / (h * h)
    else:
        curv = (cost(c + 2.0 * h) - 2.0 * cost(c + h) + cmin) / (h * h)
    n_eff = max(2.0 * (hi - lo) * g.size * float(dt_s), 1.0)
    se = float(np.sqrt(2.0 * cmin / (n_eff * curv))) if curv > 0 else float("inf")
    return ResponseWidthFit(c, se, c0, cmin)
