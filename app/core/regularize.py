"""Regularization of the anomaly measurement (SPEC §2 step 1, seed 000 §4.1).

Model at full rate (GNSS step ``Δt``), in mGal with ``r`` in cm/s::

    z_k = δg_k − 1000·(r_k − r_{k−1})/Δt,     ∇^m δg_k = q_k,
    x_k = ∇^m z_k = q_k − 1000·∇^{m+1} r_k / Δt.

Regularization low-passes ``x`` with a Kaiser-window FIR (cut-off ``ω_s``, stop
``ω_stop = ω_s + ω_p/2``) and decimates by ``n`` so that the new Nyquist
``1/(2nΔt)`` equals ``ω_stop``.

Where the difference is taken
-----------------------------
Two mathematically equivalent-in-spirit orders are offered through
``RegularizationDesign.difference_grid``:

``"full"``
    The literal seed order: ``∇^m`` at full rate, Kaiser low-pass, keep every
    n-th sample.  The GNSS component of ``∇^m z`` has a spectrum growing like
    ``f^{2(m+1)}`` up to the full-rate Nyquist, and the Kaiser window's
    side-lobes only fall like ``1/f``; with a 60 dB design and the seed
    settings, 96 % (m = 1) and > 99.999 % (m = 2) of the decimated GNSS power
    is aliased high-frequency noise, which buries the anomaly.
``"decimated"`` (default)
    Low-pass and decimate ``z`` itself, then take ``∇^m`` on the decimated
    grid.  Since ``1 − B^n = (1 − B)(1 + B + … + B^{n−1})`` this is exactly the
    seed pipeline (``∇^m`` at full rate, low-pass, decimate) with the Kaiser
    low-pass multiplied by ``m`` moving sums of length ``n`` (a CIC-like
    anti-alias factor with zeros at every frequency that folds onto DC).  The
    aliased fraction of the GNSS component drops to 0.13 % (m = 1) and 0.21 %
    (m = 2) for the seed
    settings.  ``q`` keeps its full-rate meaning either way; ``x`` on the
    decimated grid is ``∇_n^m`` of the low-passed anomaly measurement.

Either way every component of the decimated ``x`` is an exactly known finite
moving average of the full-rate white noises ``q`` and ``r``
(:func:`component_filters`), which ``app.core.ma_approx`` approximates by a
short MA on the decimated grid.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from math import comb
from typing import Literal

import numpy as np
from scipy import signal

#: Seed 000 example: ω_s = 0.0237 Hz for ω_stop = 0.05 Hz.
SEED_CUTOFF_TO_STOP = 0.0237 / 0.05
#: mGal per (cm/s)/s: 1 cm/s per second = 0.01 m/s² = 1000 mGal.
MGAL_PER_CMS_PER_S = 1000.0

DifferenceGrid = Literal["decimated", "full"]


@dataclass(frozen=True)
class RegularizationDesign:
    """Kaiser low-pass + decimation design.

    Attributes
    ----------
    n : int
        Decimation factor (decimated step ``n·dt_s``).
    dt_s : float
        Full-rate (GNSS) step, s.
    cutoff_hz : float
        ``ω_s``: nominal cut-off (−6 dB point, centre of the transition band), Hz.
    stop_hz : float
        ``ω_stop = ω_s + ω_p/2`` = new Nyquist ``1/(2 n dt_s)``, Hz.
    width_hz : float
        ``ω_p``: transition band width, Hz.
    attenuation_db : float
        Required stop-band attenuation, dB (verified on the designed taps).
    taps : ndarray, shape (ntaps,)
        Odd length, symmetric, unit DC gain.
    beta : float
        Kaiser window parameter.
    difference_grid : {"decimated", "full"}
        Where ``∇^m`` is taken (see module docstring).
    """

    n: int
    dt_s: float
    cutoff_hz: float
    stop_hz: float
    width_hz: float
    attenuation_db: float
    taps: np.ndarray
    beta: float
    difference_grid: DifferenceGrid = "decimated"

    @property
    def fs_hz(self) -> float:
        """Full sampling rate, Hz."""
        return 1.0 / self.dt_s

    @property
    def dt_dec_s(self) -> float:
        """Decimated step ``n·dt_s``, s."""
        return self.n * self.dt_s

    @property
    def pass_hz(self) -> float:
        """Pass-band edge ``ω_s − ω_p/2`` (Hz); ≤ 0 means no flat pass band.

        With the seed ratio ω_s/ω_stop = 0.474 the transition band reaches DC:
        the filter is a smooth low-pass (−6 dB at ω_s, ≥ A dB down from ω_stop);
        its shape is absorbed by the MA approximation.
        """
        return self.cutoff_hz - 0.5 * self.width_hz

    @property
    def ntaps(self) -> int:
        return int(self.taps.size)


@dataclass(frozen=True)
class FilterMetrics:
    """Measured properties of a design (see :func:`measure_filter`)."""

    passband_ripple_db: float
    stopband_attenuation_db: float
    aliased_fraction: float | None


def _check_pos(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def _stopband_attenuation_db(taps: np.ndarray, stop_hz: float, fs_hz: float) -> float:
    """Minimum attenuation (dB) of ``taps`` over [stop_hz, fs/2] on a dense grid."""
    # dense FFT grid (≥ 32 points per side-lobe width fs/ntaps) over the whole band …
    nfft = 1 << int(np.ceil(np.log2(max(8192, 32 * taps.size))))
    H = np.abs(np.fft.rfft(taps, nfft))
    f = np.fft.rfftfreq(nfft, 1.0 / fs_hz)
    peak = np.max(H[f >= stop_hz]) if np.any(f >= stop_hz) else 0.0
    # … and an extra-fine grid over the first side-lobes, where the maximum sits
    f2 = np.linspace(stop_hz, min(fs_hz / 2.0, stop_hz + 8.0 * fs_hz / taps.size), 4096)
    _, h2 = signal.freqz(taps, worN=f2, fs=fs_hz)
    peak = max(peak, float(np.max(np.abs(h2))))
    return float(-20.0 * np.log10(max(peak, 1e-300)))


def design_regularization(
    dt_s: float,
    speed_ms: float | None,
    step_km: float = 1.0,
    n: int | None = None,
    cutoff_hz: float | None = None,
    attenuation_db: float = 60.0,
    difference_grid: DifferenceGrid = "decimated",
) -> RegularizationDesign:
    """Design the Kaiser low-pass and the decimation factor.

    Parameters
    ----------
    dt_s : float
        Full-rate (GNSS) step, s (0.1 at 10 Hz).
    speed_ms : float or None
        Typical ground speed, m/s; only used to choose ``n`` (may be None when
        ``n`` is given).
    step_km : float
        Wanted decimated step along the line, km (default 1).
    n : int, optional
        Decimation factor; default ``round(step_km·1000/(speed_ms·dt_s))``.
    cutoff_hz : float, optional
        ``ω_s`` (Hz); default ``0.474·ω_stop`` (seed ratio 0.0237/0.05).
    attenuation_db : float
        Stop-band attenuation (dB) required from ``ω_stop = 1/(2 n dt_s)`` on.
        Checked on the designed taps; the Kaiser order is raised until met.
    difference_grid : {"decimated", "full"}
        Where ``∇^m`` is taken by :func:`regularize_line` (module docstring).

    Returns
    -------
    RegularizationDesign

    Raises
    ------
    ValueError
        Naming the offending parameter.
    """
    dt_s = _check_pos("dt_s", dt_s)
    attenuation_db = _check_pos("attenuation_db", attenuation_db)
    if attenuation_db < 21.0:
        raise ValueError(f"attenuation_db must be ≥ 21 dB for a Kaiser design, got {attenuation_db}")
    if difference_grid not in ("decimated", "full"):
        raise ValueError(f"difference_grid must be 'decimated' or 'full', got {difference_grid!r}")
    if n is None:
        step_km = _check_pos("step_km", step_km)
        if speed_ms is None:
            raise ValueError("speed_ms is required when n is not given")
        speed_ms = _check_pos("speed_ms", speed_ms)
        n = int(round(step_km * 1000.0 / (speed_ms * dt_s)))
        if n < 2:
            raise ValueError(
                f"step_km={step_km} at speed_ms={speed_ms}, dt_s={dt_s} gives n={n}; need n ≥ 2")
    else:
        if isinstance(n, bool) or int(n) != n or int(n) < 2:
            raise ValueError(f"n must be an integer ≥ 2, got {n!r}")
        n = int(n)
    fs = 1.0 / dt_s
    stop_hz = 1.0 / (2.0 * n * dt_s)
    if cutoff_hz is None:
        cutoff_hz = SEED_CUTOFF_TO_STOP * stop_hz
    else:
        cutoff_hz = _check_pos("cutoff_hz", cutoff_hz)
        if cutoff_hz >= stop_hz:
            raise ValueError(
                f"cutoff_hz={cutoff_hz} must be below the stop frequency 1/(2·n·dt_s)={stop_hz:g} Hz")
    width_hz = 2.0 * (stop_hz - cutoff_hz)
    if width_hz / (fs / 2.0) >= 1.0:
        raise ValueError(f"transition width {width_hz:g} Hz is wider than the Nyquist band; lower n")

    target = attenuation_db
    for _ in range(20):
        ntaps, beta = signal.kaiserord(target, width_hz / (fs / 2.0))
        ntaps = int(ntaps) | 1  # odd length → type-I linear phase, integer delay
        taps = signal.firwin(ntaps, cutoff_hz, window=("kaiser", beta), fs=fs, scale=False)
        taps = taps / taps.sum()  # unit DC gain
        taps = 0.5 * (taps + taps[::-1])  # exact symmetry
        measured = _stopband_attenuation_db(taps, stop_hz, fs)
        if measured >= attenuation_db:
            break
        target += attenuation_db - measured + 0.25
    else:  # pragma: no cover - kaiser designs converge in a couple of steps
        raise ValueError(f"could not reach attenuation_db={attenuation_db} (got {measured:.1f} dB)")
    return RegularizationDesign(
        n=n, dt_s=dt_s, cutoff_hz=float(cutoff_hz), stop_hz=float(stop_hz),
        width_hz=float(width_hz), attenuation_db=float(attenuation_db),
        taps=taps, beta=float(beta), difference_grid=difference_grid,
    )


def difference(z: np.ndarray, m: int) -> np.ndarray:
    """Backward difference ``∇^m z_k = Σ_i (−1)^i C(m,i) z_{k−i}``.

    Parameters
    ----------
    z : ndarray, shape (N,)
    m : int ≥ 0

    Returns
    -------
    ndarray, shape (N − m,)
        Element ``j`` is ``∇^m z`` at index ``j + m`` of ``z``.
    """
    z = np.asarray(z, dtype=float)
    if isinstance(m, bool) or int(m) != m or m < 0:
        raise ValueError(f"m must be an integer ≥ 0, got {m!r}")
    if z.ndim != 1:
        raise ValueError(f"z must be 1-D, got shape {z.shape}")
    if z.size <= m:
        raise ValueError(f"need more than m={m} samples to difference, got {z.size}")
    return np.diff(z, n=int(m)) if m > 0 else z.copy()


def difference_coefficients(m: int) -> np.ndarray:
    """Coefficients of ``(1 − B)^m``: ``[(−1)^i C(m, i)]``, shape (m+1,)."""
    return np.array([(-1) ** i * comb(m, i) for i in range(m + 1)], dtype=float)


def min_line_samples(design: RegularizationDesign, m: int) -> int:
    """Fewest full-rate samples a line needs for one decimated output."""
    if design.difference_grid == "decimated":
        return design.ntaps + m * design.n
    return design.ntaps + m


def regularize_line(z_mgal: np.ndarray, m: int, design: RegularizationDesign):
    """Difference, low-pass and decimate one line ("valid" mode, no edge padding).

    Parameters
    ----------
    z_mgal : ndarray, shape (N,)
        Anomaly measurement at full rate, mGal (uniform step ``design.dt_s``).
    m : int ≥ 1
        Order of the difference operator.
    design : RegularizationDesign

    Returns
    -------
    x_dec : ndarray, shape (M,)
        Regularized measurement on the decimated grid, mGal.
        ``difference_grid="full"``: ``M = ⌊(N − m − ntaps)/n⌋ + 1``;
        ``"decimated"``: ``M = ⌊(N − ntaps)/n⌋ + 1 − m``.
    idx : ndarray of int, shape (M,)
        Full-rate index (into ``z_mgal``) at the centre of the whole window of
        ``z`` each output depends on; consecutive entries differ by ``n``.

    Raises
    ------
    ValueError
        NaN/inf in ``z_mgal`` or a line shorter than :func:`min_line_samples`.
    """
    z = np.asarray(z_mgal, dtype=float)
    if z.ndim != 1:
        raise ValueError(f"z_mgal must be 1-D, got shape {z.shape}")
    if isinstance(m, bool) or int(m) != m or m < 1:
        raise ValueError(f"m must be an integer ≥ 1, got {m!r}")
    m = int(m)
    bad = ~np.isfinite(z)
    if bad.any():
        raise ValueError(
            f"z_mgal contains {int(bad.sum())} NaN/inf values (first at index {int(np.argmax(bad))});"
            " fill or split the line before regularization")
    need = min_line_samples(design, m)
    if z.size < need:
        raise ValueError(
            f"line too short for regularization: {z.size} samples, at least {need} needed "
            f"(filter of {design.ntaps} taps, n={design.n}, m={m}, difference_grid={design.difference_grid!r})")
    h = design.taps
    L, n = h.size, design.n
    if design.difference_grid == "full":
        x = difference(z, m)
        win = np.lib.stride_tricks.sliding_window_view(x, L)[::n]
        x_dec = win @ h[::-1]
        k = np.arange(x_dec.size)
        # effective window on z: [k n, k n + L − 1 + m]
        idx = (2 * k * n + L - 1 + m) // 2
    else:
        win = np.lib.stride_tricks.sliding_window_view(z, L)[::n]
        y = win @ h[::-1]
        x_dec = difference(y, m)
        k = np.arange(m, y.size)
        # effective window on z: [(k − m) n, k n + L − 1]
        idx = (2 * k * n - m * n + L - 1) // 2
    return x_dec, idx.astype(np.int64)


def component_filters(design: RegularizationDesign, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Full-rate impulse responses from the white noises to the pre-decimation ``x``.

    The decimated output of :func:`regularize_line` is
    ``x_dec[k] = Σ_i g_q[i] q[s_k − i] + Σ_i g_r[i] r[s_k − i]`` (up to the sign of
    the ``r`` part), with ``q`` in mGal (per GNSS step) and ``r`` in cm/s.

    Returns
    -------
    g_q : ndarray — mGal per mGal.
    g_r : ndarray — mGal per (cm/s); includes ``1000/Δt`` and ``∇^{m+1}``.
    """
    if isinstance(m, bool) or int(m) != m or m < 1:
        raise ValueError(f"m must be an integer ≥ 1, got {m!r}")
    g_q = np.asarray(design.taps, dtype=float)
    if design.difference_grid == "decimated":
        box = np.ones(design.n)
        for _ in range(int(m)):
            g_q = np.convolve(g_q, box)
    g_r = (MGAL_PER_CMS_PER_S / design.dt_s) * np.convolve(g_q, difference_coefficients(int(m) + 1))
    return g_q, g_r


def filter_response(design: RegularizationDesign, f_hz) -> np.ndarray:
    """Complex frequency response of the Kaiser taps at ``f_hz`` (Hz), shape of ``f_hz``.

    Linear phase removed (the taps are applied centred), so the values are real up
    to rounding.
    """
    f = np.asarray(f_hz, dtype=float)
    _, h = signal.freqz(design.taps, worN=f.ravel(), fs=design.fs_hz)
    delay = (design.ntaps - 1) / 2.0
    h = h * np.exp(2j * np.pi * f.ravel() * delay * design.dt_s)
    return h.reshape(f.shape)


def x_component_psd(f_hz, dt_s: float, m: int, component: Literal["q", "r"]) -> np.ndarray:
    """Two-sided PSD of one component of ``x = ∇^m z`` at full rate, per unit Q or R.

    ``q``: ``dt_s`` (white, variance 1 mGal² per step);
    ``r``: ``dt_s·(1000/dt_s)²·(2 sin(π f dt_s))^{2(m+1)}`` (mGal²/Hz per (cm/s)²).
    """
    f = np.asarray(f_hz, dtype=float)
    if component == "q":
        return np.full_like(f, dt_s)
    if component == "r":
        return dt_s * (MGAL_PER_CMS_PER_S / dt_s) ** 2 * (2.0 * np.sin(np.pi * f * dt_s)) ** (2 * (m + 1))
    raise ValueError(f"component must be 'q' or 'r', got {component!r}")


def aliased_power_fraction(
    taps: np.ndarray, dt_s: float, n: int, input_psd: Callable[[np.ndarray], np.ndarray],
    n_grid: int = 1 << 16,
) -> float:
    """Fraction of the filtered power that lies above the new Nyquist ``1/(2 n dt_s)``.

    All of it folds into the decimated band, so this is the aliased share of the
    decimated signal's variance: ``∫_{f_N'}^{fs/2} |H|² S df / ∫_0^{fs/2} |H|² S df``.

    Parameters
    ----------
    taps : ndarray — FIR applied before decimation.
    dt_s : float — full-rate step, s.
    n : int — decimation factor.
    input_psd : callable ``S(f_hz) -> ndarray`` — PSD of the filter input (any scale).
    """
    fs = 1.0 / dt_s
    f_dec = fs / (2.0 * n)
    f = np.linspace(0.0, fs / 2.0, int(n_grid) + 1)
    _, h = signal.freqz(np.asarray(taps, float), worN=f, fs=fs)
    p = np.abs(h) ** 2 * np.asarray(input_psd(f), dtype=float)
    total = np.trapezoid(p, f)
    hi = f >= f_dec
    # include the partial cell at f_dec exactly
    fa = np.concatenate([[f_dec], f[hi]])
    _, ha = signal.freqz(np.asarray(taps, float), worN=fa, fs=fs)
    pa = np.abs(ha) ** 2 * np.asarray(input_psd(fa), dtype=float)
    return float(np.trapezoid(pa, fa) / total)


def measure_filter(design: RegularizationDesign, m: int | None = None) -> FilterMetrics:
    """Measure pass-band ripple, stop-band attenuation and aliasing of a design.

    Parameters
    ----------
    design : RegularizationDesign
    m : int, optional
        When given, the aliased power fraction is computed for the GNSS (``r``)
        component of ``x`` through the effective filter of :func:`component_filters`
        (the worst case; the ``q`` component aliases far less).

    Returns
    -------
    FilterMetrics
        ``passband_ripple_db``: max |20 log10 |H|| over [0, pass_hz] (DC only when
        ``pass_hz ≤ 0``); ``stopband_attenuation_db``: min −20 log10 |H| over
        [ω_stop, fs/2]; ``aliased_fraction``: as above, or None without ``m``.
    """
    fs = design.fs_hz
    f_pass = np.linspace(0.0, max(design.pass_hz, 0.0), 2048)
    _, hp = signal.freqz(design.taps, worN=f_pass, fs=fs)
    ripple = float(np.max(np.abs(20.0 * np.log10(np.abs(hp)))))
    att = _stopband_attenuation_db(design.taps, design.stop_hz, fs)
    alias = None
    if m is not None:
        _, g_r = component_filters(design, m)
        alias = aliased_power_fraction(g_r, design.dt_s, design.n, lambda f: np.ones_like(f))
    return FilterMetrics(passband_ripple_db=ripple, stopband_attenuation_db=att, aliased_fraction=alias)
