"""The error of the measurement z as a coloured process: model, spectrum, fit.

Seed 000 takes the error of ``z_k`` to be white GNSS vertical-velocity noise differenced
once, ``−1000·(r_k − r_{k−1})/Δt``: its power rises as f² from zero frequency.  Real
flights are not like that.  Heights-only GNSS (vertical acceleration from differenced
positions) gives an error rising as f⁴; a Gauss–Markov velocity error flattens above its
corner frequency; the mismatch between the gravimeter's response and the GNSS-derived
acceleration under turbulence adds a steep band of its own (a real 2 Hz test line:
power rising as f⁴–f⁵ from 0.01 to 0.3 Hz).  A smoother that assumes the f² shape and
sizes it to the high band over-states the noise in the anomaly band by orders of
magnitude and draws a straight line.

Model
-----
The error is a sum of independent components.  Component ``c`` is an AR(1) process
``u_k = φ_c u_{k−1} + e_k`` (``Var e_k = R_k·w_c``) differenced ``j_c`` times::

    n_k = Σ_c (1 − B)^{j_c} u_{c,k}

* ``j = 1, φ = 0``: white velocity noise (the paper's model; ``w = (1000/Δt)²`` per
  (cm/s)²);
* ``j = 1, 0 < φ < 1``: Gauss–Markov velocity noise (flat above its corner);
* ``j = 2, φ = 0``: white position (height) noise differenced twice (f⁴);
* ``j = 2, 0 < φ < 1``: coloured height noise (f⁴ below the corner, f² above);
* ``j = 0``: an error white in z itself (gravimeter noise).

Each component is a small linear state-space block (states ``u_k … u_{k−j}``), so the
whole model stays a linear Gaussian state-space model and the Kalman smoother treats
it exactly (:mod:`app.core.smoother`).  ``R_k`` is a dimensionless-per-unit level in
time: the models used by the pipeline are *normalised* so that ``R_k`` is the
**equivalent white velocity noise** ((cm/s)²) — the white-velocity level with the same
power in a reference band (:meth:`NoiseModel.normalized`).  For the white-velocity
model this is exactly the paper's R.

Fit
---
:func:`fit_noise_model` maximises the Whittle likelihood of the multitaper spectra of
the lines' z (prewhitened by a steep low-pass so that the 10⁸ dynamic range of the
turbulence band cannot leak into the anomaly band, :func:`multitaper_psd`) over a
few physically meaningful families of components plus a stationary ``∇^m δg = q``
anomaly (a nuisance here), and chooses the family by BIC.  The fit uses frequencies
from just above zero to ``fmax_hz`` — where the noise's shape decides how the smoother
separates anomaly from noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from math import comb

import numpy as np
from numba import njit
from scipy import optimize, signal
from scipy.stats import chi2

#: mGal per (cm/s per s): 1 cm/s² = 1000 mGal.
MGAL_PER_CMS_PER_S = 1000.0
#: Largest AR(1) coefficient of a component (a correlation time of 1000 steps).
PHI_MAX = 0.999
#: Largest roll-off time (s) of the anomaly's spectrum in the noise fit (``exp(−β f)``):
#: β = 4π d / v for sources d below the aircraft at ground speed v — 10 km at 50 m/s.
ROLLOFF_MAX_S = 2500.0


@dataclass(frozen=True)
class NoiseComponent:
    """One component: an AR(1) process differenced ``order`` times.

    Attributes
    ----------
    order : int
        Number of differences j ∈ {0, 1, 2}.
    phi : float
        AR(1) coefficient, 0 ≤ φ ≤ ``PHI_MAX`` (0: white).
    weight : float
        Variance of the AR(1) innovation per unit level ``R`` (mGal²).
    """

    order: int
    phi: float
    weight: float

    def __post_init__(self):
        if self.order not in (0, 1, 2):
            raise ValueError(f"component order must be 0, 1 or 2, got {self.order!r}")
        if not (0.0 <= float(self.phi) <= PHI_MAX):
            raise ValueError(f"component phi must be in [0, {PHI_MAX}], got {self.phi!r}")
        if not (np.isfinite(self.weight) and self.weight >= 0.0):
            raise ValueError(f"component weight must be finite and ≥ 0, got {self.weight!r}")

    @property
    def label(self) -> str:
        base = {0: "white z", 1: "velocity", 2: "height"}[self.order]
        return f"{base} {'white' if self.phi == 0 else f'AR(1) φ={self.phi:.4g}'}"


@dataclass(frozen=True)
class NoiseModel:
    """Error of z as a sum of :class:`NoiseComponent` (module docstring), at step ``dt_s``.

    A level ``R_k`` multiplies every component's innovation variance at epoch k.
    """

    components: tuple
    dt_s: float
    family: str = "white velocity"
    info: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        if not self.components:
            raise ValueError("a noise model needs at least one component")
        if not (np.isfinite(self.dt_s) and self.dt_s > 0):
            raise ValueError(f"dt_s must be positive, got {self.dt_s!r}")
        if not any(c.weight > 0 for c in self.components):
            raise ValueError("every component of the noise model has zero weight")

    # ------------------------------------------------------------------ shape
    @property
    def is_white_velocity(self) -> bool:
        """True for the paper's model (one white velocity component): the smoother's fast path."""
        live = [c for c in self.components if c.weight > 0]
        return len(live) == 1 and live[0].order == 1 and live[0].phi == 0.0

    @property
    def n_states(self) -> int:
        return sum(c.order + 1 for c in self.components)

    def psd(self, f_hz, level: float = 1.0) -> np.ndarray:
        """Two-sided PSD of the error of z (mGal²/Hz) at level ``R = level``."""
        f = np.asarray(f_hz, dtype=float)
        return level * self.dt_s * sum(_component_psd_per_sample(f * self.dt_s, c) for c in self.components)

    def block(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """State-space block ``b_k = F b_{k−1} + e_k``, ``Cov e_k = R_k·W``, error ``= hᵀ b_k``.

        Returns
        -------
        F, W : ndarray, shape (s, s);  h : ndarray, shape (s,)
            ``s = Σ (j_c + 1)``; states of component c are ``u_k, u_{k−1}, …, u_{k−j}``.
        """
        s = self.n_states
        F = np.zeros((s, s))
        W = np.zeros((s, s))
        h = np.zeros(s)
        o = 0
        for c in self.components:
            F[o, o] = c.phi
            for i in range(1, c.order + 1):
                F[o + i, o + i - 1] = 1.0
            W[o, o] = c.weight
            for i in range(c.order + 1):
                h[o + i] = (-1.0) ** i * comb(c.order, i)
            o += c.order + 1
        return F, W, h

    def stationary_covariance(self, level: float = 1.0) -> np.ndarray:
        """Stationary covariance of the block's states at a constant level (prior of a line)."""
        from scipy.linalg import solve_discrete_lyapunov

        F, W, _ = self.block()
        P = solve_discrete_lyapunov(F, level * W)
        return 0.5 * (P + P.T)

    # ------------------------------------------------------------------ scale
    def scaled(self, factor: float) -> NoiseModel:
        """The same shape with every weight multiplied by ``factor``."""
        if not (np.isfinite(factor) and factor > 0):
            raise ValueError(f"scale factor must be positive, got {factor!r}")
        comps = tuple(replace(c, weight=c.weight * float(factor)) for c in self.components)
        return replace(self, components=comps)

    def band_power(self, band_hz: tuple[float, float], order: int = 4) -> float:
        """Variance (mGal²) of the error after the zero-phase Butterworth band-pass that
        :func:`app.core.noise_level.band_noise_variance_cm2s2` applies (``|H|⁴``), at R = 1."""
        f1, f2 = _check_band(band_hz, self.dt_s)
        sos = signal.butter(order, (f1, f2), btype="bandpass", fs=1.0 / self.dt_s, output="sos")
        f, h = signal.sosfreqz(sos, worN=1 << 16, fs=1.0 / self.dt_s)
        return float(2.0 * np.trapezoid(self.psd(f) * np.abs(h) ** 4, f))

    def equivalent_white_R(self, band_hz: tuple[float, float]) -> float:
        """The white-velocity level R ((cm/s)²) with the same band power as this model at R = 1."""
        return self.band_power(band_hz) / white_velocity(self.dt_s).band_power(band_hz)

    def normalized(self, band_hz: tuple[float, float]) -> NoiseModel:
        """This shape scaled so that a level R means R (cm/s)² of equivalent white velocity
        noise in ``band_hz`` (the band the local level R(t) is measured in)."""
        return self.scaled(1.0 / self.equivalent_white_R(band_hz))

    # ------------------------------------------------------------------ regularization
    def impulse_responses(self, tol: float = 1e-9, max_len: int = 200_000) -> list[np.ndarray]:
        """Impulse response of each component from its innovation (unit variance per unit R
        ... scaled by √weight) to the error of z, truncated where φ^L < tol."""
        out = []
        for c in self.components:
            if c.weight <= 0:
                continue
            if c.phi > 0:
                L = int(min(max_len, np.ceil(np.log(tol) / np.log(c.phi)) + 1))
                ar = c.phi ** np.arange(L)
            else:
                ar = np.ones(1)
            d = np.array([(-1.0) ** i * comb(c.order, i) for i in range(c.order + 1)])
            out.append(np.sqrt(c.weight) * np.convolve(ar, d))
        return out

    def describe(self) -> dict:
        """Plain-data description (JSON-able) for reports."""
        return {"family": self.family, "dt_s": self.dt_s,
                "components": [{"order": c.order, "phi": c.phi, "weight_mgal2": c.weight, "label": c.label}
                               for c in self.components], **self.info}

    @classmethod
    def from_description(cls, d: dict) -> NoiseModel:
        """The model a :meth:`describe` dictionary (a report's ``noise_model``) stands for: its
        family, step and components (the fit's other entries are not needed to use it)."""
        return cls(tuple(NoiseComponent(int(c["order"]), float(c["phi"]), float(c["weight_mgal2"]))
                         for c in d["components"]), float(d["dt_s"]), str(d.get("family", "white velocity")))


def white_velocity(dt_s: float, R_cm2s2: float = 1.0) -> NoiseModel:
    """The paper's model: white vertical-velocity noise of variance R, differenced once."""
    w = (MGAL_PER_CMS_PER_S / float(dt_s)) ** 2 * float(R_cm2s2)
    return NoiseModel((NoiseComponent(1, 0.0, w),), float(dt_s), "white velocity")


def with_white_floor(model: NoiseModel, weight_mgal2: float) -> NoiseModel:
    """``model`` with a white-z component added: a noise floor of ``weight_mgal2`` per sample.

    A point-sampled platform meter's aliased motion is white in z down into the anomaly band,
    where the steeper GNSS and motion components a line's spectrum is fitted to hide it; the
    crossovers see it (:func:`app.core.model_check.crossover_noise_floor`).

    Parameters
    ----------
    model : NoiseModel
        The fitted shape.
    weight_mgal2 : float
        Variance of the floor per sample and unit level R (mGal²); a white-z component of
        ``model`` (order 0, φ = 0) is raised by it instead of a second one being added.

    Returns
    -------
    NoiseModel
        Same step and family (``info['white_floor_mgal2']`` says the floor).
    """
    w = float(weight_mgal2)
    if not (np.isfinite(w) and w >= 0.0):
        raise ValueError(f"weight_mgal2 must be finite and >= 0, got {weight_mgal2!r}")
    comps = list(model.components)
    for i, c in enumerate(comps):
        if c.order == 0 and c.phi == 0.0:
            comps[i] = replace(c, weight=c.weight + w)
            break
    else:
        comps.append(NoiseComponent(0, 0.0, w))
    return replace(model, components=tuple(comps), info={**model.info, "white_floor_mgal2": w})


def _component_psd_per_sample(nu, c: NoiseComponent) -> np.ndarray:
    """PSD per cycle/sample (variance = ∫_{−1/2}^{1/2}) of one component at R = 1."""
    e = np.exp(-2j * np.pi * np.asarray(nu, dtype=float))
    return _component_psd_at(e, np.abs(1.0 - e) ** (2 * c.order) if c.order else 1.0, c)


def _component_psd_at(e: np.ndarray, num, c: NoiseComponent) -> np.ndarray:
    """:func:`_component_psd_per_sample` from ``e = e^{-2πiν}`` and ``num = |1 − e|^{2j}``
    (1 for j = 0), which a fit evaluating many components on the same bins computes once."""
    return c.weight * num / np.abs(1.0 - c.phi * e) ** 2


def anomaly_psd(f_hz, Q_mgal2: float, m: int, dt_s: float, rolloff_s: float = 0.0) -> np.ndarray:
    """Two-sided PSD (mGal²/Hz) of the anomaly ``∇^m δg = q``, ``Var q = Q`` per step,
    times ``exp(−rolloff_s · f)``: a field observed at a height d above its sources falls as
    ``exp(−4π d k)`` in wavenumber k, i.e. ``exp(−β f)`` with ``β = 4π d / v`` (s) along a
    track flown at speed v."""
    f = np.asarray(f_hz, dtype=float)
    nu = f * dt_s
    d = np.abs(1.0 - np.exp(-2j * np.pi * nu)) ** (2 * m)
    with np.errstate(divide="ignore"):
        return dt_s * Q_mgal2 / d * np.exp(-float(rolloff_s) * f)


def rolloff_s(theta) -> float:
    """The anomaly's roll-off time β (s) held in the last element of a fit's θ
    (``ROLLOFF_MAX_S`` times a logistic: 0 ≤ β < ``ROLLOFF_MAX_S``)."""
    return float(ROLLOFF_MAX_S / (1.0 + np.exp(-float(theta[-1]))))


def _rolloff_logit(beta_s: float) -> float:
    """The θ element that holds β (s): the inverse of :func:`rolloff_s`."""
    return float(np.log(beta_s / (ROLLOFF_MAX_S - beta_s)))


def _n_base(spec) -> int:
    """Length of a family's θ without the roll-off: log Q, then per component log w and, with
    a free φ, its logit.  A θ one longer carries β (:func:`rolloff_s`)."""
    return 1 + sum(1 + int(bool(free_phi)) for _, free_phi in spec)


def _check_band(band_hz, dt_s):
    f1, f2 = float(band_hz[0]), float(band_hz[1])
    if not 0 < f1 < f2 < 0.5 / dt_s:
        raise ValueError(f"band must satisfy 0 < f1 < f2 < Nyquist ({0.5 / dt_s:g} Hz), got {band_hz}")
    return f1, f2


# --------------------------------------------------------------------------- spectra
@dataclass(frozen=True)
class Spectrum:
    """Multitaper PSD of one stretch of z.

    Attributes
    ----------
    f_hz : ndarray, shape (F,)
        Frequencies (Hz), from ``1.5 × bandwidth`` to ``fmax_hz``.
    psd : ndarray, shape (F,)
        Two-sided PSD estimate (mGal²/Hz) of z, corrected for the prewhitening filter.
    bandwidth_hz : float
        Half-bandwidth W of the tapers (resolution).
    dof : float
        Degrees of freedom of each estimate (2 per taper).
    duration_s : float
    """

    f_hz: np.ndarray
    psd: np.ndarray
    bandwidth_hz: float
    dof: float
    duration_s: float


def _ar_least_squares(y: np.ndarray, p: int) -> np.ndarray:
    """Prediction-error filter ``(1, −a_1, …, −a_p)`` of an AR(p) fitted by least squares
    (covariance method); falls back to lower orders if the system is singular."""
    for order in range(p, 0, -1):
        if y.size <= 4 * order:
            continue
        X = np.column_stack([y[order - i - 1: y.size - i - 1] for i in range(order)])
        coef, *_ = np.linalg.lstsq(X, y[order:], rcond=None)
        if np.all(np.isfinite(coef)):
            return np.concatenate([[1.0], -coef])
    return np.ones(1)


def multitaper_psd(z_mgal, dt_s: float, fmax_hz: float, nw: float = 3.0, n_tapers: int | None = None,
                   attenuation_db: float = 110.0, ar_order: int = 6, need_bins: bool = False) -> Spectrum:
    """Prewhitened multitaper PSD of one NaN-free stretch of z up to ``fmax_hz``.

    The error of z spans ~10 orders of magnitude between the anomaly band and the
    turbulence band; any taper leaks that much.  So z is first low-passed (Kaiser FIR,
    pass band to 1.25·fmax, stop band from 1.7·fmax with ``attenuation_db``; from 2.2 or
    3·fmax when the stretch is too short for that filter) and decimated as far as that
    allows; a straight line is removed; an AR(``ar_order``) prediction-error filter fitted
    by least squares whitens what is left (still 5–8 decades inside the pass
    band); DPSS tapers (``nw``, ``n_tapers`` = 2·nw − 1 by default) give the residual's
    spectrum, which is divided by the gains of both filters.

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
        NaN-free stretch (mGal).
    dt_s : float
        Step (s).
    fmax_hz : float
        Highest frequency wanted (Hz), below 0.5/(1.7·dt_s)... clipped to 0.8 Nyquist.
    need_bins : bool
        Take the sharpest filter that also leaves bins below ``fmax_hz`` (the taper bandwidth
        of what is left after the filter); by default the sharpest the stretch is long enough
        for, whose spectrum can then be empty (a 97 s stretch at 2 Hz keeps 18 s).

    Returns
    -------
    Spectrum
    """
    from scipy.signal.windows import dpss

    z = np.asarray(z_mgal, dtype=float)
    if z.ndim != 1 or not np.all(np.isfinite(z)):
        raise ValueError("z_mgal must be a NaN-free 1-D stretch")
    fs = 1.0 / dt_s
    fmax = min(float(fmax_hz), 0.8 * 0.5 * fs)
    # Anti-alias low-pass before decimating by q.  Its length is set by the transition width in
    # Hz (110 dB over 0.45·fmax = 0.09 Hz takes ~80 s whatever the rate), so a stretch too short
    # for it gets a wider transition (2.2·fmax: ~40 s; 3·fmax: ~20 s).  The pass band
    # (≤ 1.25·fmax) is the same, and every frequency that folds onto [0, fmax] after the
    # decimation lies above the stop band (fs/q − fmax ≥ 2·f_stop − fmax ≥ f_stop).
    f_pass = 1.25 * fmax
    for stop_ratio in (1.7, 2.2, 3.0):
        f_stop = stop_ratio * fmax
        if f_stop < 0.5 * fs:
            ntap, beta = signal.kaiserord(attenuation_db, (f_stop - f_pass) / (0.5 * fs))
            ntap |= 1
            h = signal.firwin(ntap, 0.5 * (f_pass + f_stop), window=("kaiser", beta), fs=fs)
            q = max(1, int(np.floor(fs / (2.0 * f_stop))))
        else:
            h = np.ones(1)
            q = 1
        n_e = (z.size - h.size + 1) // q - ar_order
        if z.size >= h.size + 16 * q and (not need_bins or (n_e > 0 and 1.5 * nw / (n_e * q * dt_s) < fmax)):
            break
    else:
        raise ValueError(f"stretch of {z.size} samples too short for a spectrum up to {fmax:g} Hz")
    y = np.convolve(z, h, mode="valid")[::q]
    t = np.arange(y.size)
    y = y - np.polyval(np.polyfit(t, y, 1), t)
    # AR prewhitening (least squares, order ar_order): the residual's spectrum is nearly flat,
    # so the tapers' leakage no longer matters; the AR's gain is divided out afterwards
    a = _ar_least_squares(y, ar_order)
    e = np.convolve(y, a, mode="valid")
    N = e.size
    K = int(n_tapers) if n_tapers else max(1, int(2 * nw - 1))
    tapers = np.atleast_2d(dpss(N, nw, K))
    X = np.fft.rfft(tapers * e[None, :], axis=1)
    s = np.mean(np.abs(X) ** 2, axis=0)                 # per decimated sample
    fd = np.fft.rfftfreq(N, q * dt_s)                   # Hz
    _, H = signal.freqz(h, worN=fd, fs=fs)
    _, Ha = signal.freqz(a, worN=fd, fs=1.0 / (q * dt_s))
    psd = s * (q * dt_s) / np.maximum(np.abs(H) ** 2 * np.abs(Ha) ** 2, 1e-300)
    W = nw / (N * q * dt_s)
    sel = (fd >= 1.5 * W) & (fd <= fmax)
    return Spectrum(fd[sel], psd[sel], float(W), float(2 * K), float(N * q * dt_s))


@dataclass(frozen=True)
class VelocityBound:
    """The spectrum of what GNSS heights and velocities disagree on
    (:func:`app.core.measurement.height_velocity_misfit_m`), carried to z's units: an upper
    bound on the GNSS velocity error in z at low frequencies (:func:`velocity_bound`).

    Attributes
    ----------
    f_hz : ndarray, shape (G,)
        Group frequencies (Hz, log-spaced groups, weighted geometric mean).
    psd : ndarray, shape (G,)
        Two-sided PSD (mGal²/Hz) of the misfit differenced as z differences the velocity.
    weight : ndarray, shape (G,)
        Whittle weight of each group (one χ² of 2K dof per resolution cell, summed).
    slack : ndarray, shape (G,)
        The group's ``quantile`` of χ²_ν/ν (ν = 2·weight, its degrees of freedom): the bound
        binds from ``slack × psd`` on, so a group whose estimate fell low by chance does not
        pull the model down (with the estimate itself the fit stated the low-band noise of a
        simulated Gauss–Markov velocity error at half its value).
    n_segments : int
    """

    f_hz: np.ndarray
    psd: np.ndarray
    weight: np.ndarray
    slack: np.ndarray
    n_segments: int


def velocity_bound(d_segments_m, dt_s: float, fmax_hz: float = 0.05, nw: float = 3.0,
                   n_groups: int = 16, quantile: float = 0.9) -> VelocityBound | None:
    """Multitaper spectrum of the height–velocity misfit ``d`` (m, NaN-free stretches at
    step ``dt_s``) expressed as the error it bounds in z.

    z holds the velocity error differenced once, ``(r_k − r_{k−1})/Δt``; ``d`` holds its
    trapezoid integral plus the height error, so the velocity part of z's error has the PSD
    ``S_Δd · |1 − e^{−2πiν}|² / (Δt⁴ cos²(πν))`` with ``Δd`` the first difference of ``d``
    (ν = fΔt; ``d`` in mGal·s²).  The height error only adds: the result bounds the velocity
    error in z from above, tightly where the integral dominates (low frequencies).  ``Δd`` is
    white for a white velocity error, so its DPSS spectrum has no leakage from the random
    walk's power near zero frequency (``d`` itself biased the lowest bins up by 1.6×); its
    mean is removed (a constant velocity bias is no error of z).  Estimates from ``1.5 W``
    (W = nw/duration) to
    ``fmax_hz`` are pooled in ``n_groups`` log-spaced groups (weights summed, PSD
    weight-averaged).  Returns None when no stretch leaves a bin.
    """
    from scipy.signal.windows import dpss
    from scipy.stats import chi2

    K = max(1, int(2 * nw - 1))
    fs, ws, ps = [], [], []
    n_seg = 0
    for d in d_segments_m:
        d = np.asarray(d, dtype=float) * 1e5          # m → mGal·s²
        if d.ndim != 1 or d.size < 64 or not np.all(np.isfinite(d)):
            continue
        # differenced once, d is white for a white velocity error: no leakage from the
        # random walk's power at the lowest frequencies into the bins above them
        x = np.diff(d)
        x = x - x.mean()
        N = x.size
        X = np.fft.rfft(np.atleast_2d(dpss(N, nw, K)) * x[None, :], axis=1)
        f = np.fft.rfftfreq(N, dt_s)
        W = nw / (N * dt_s)
        sel = (f >= 1.5 * W) & (f <= fmax_hz)
        if not sel.any():
            continue
        nu = f[sel] * dt_s
        gain = np.abs(1.0 - np.exp(-2j * np.pi * nu)) ** 2 / (dt_s ** 4 * np.cos(np.pi * nu) ** 2)
        fs.append(f[sel])
        ps.append(np.mean(np.abs(X[:, sel]) ** 2, axis=0) * dt_s * gain)
        ws.append(np.full(int(sel.sum()), 0.5 * 2 * K / (2.0 * nw)))
        n_seg += 1
    if not fs:
        return None
    fg, pg, Wg = _log_groups(np.concatenate(fs), np.concatenate(ps), np.concatenate(ws), n_groups)
    nu = 2.0 * Wg
    return VelocityBound(fg, pg, Wg, chi2.ppf(quantile, nu) / nu, n_seg)


# --------------------------------------------------------------------------- fit
#: Candidate families: (name, [(order, phi free?)]).
#: BIC units a richer noise family must gain over a simpler one to be chosen (:func:`fit_noise_model`)
BIC_MARGIN = 10.0

FAMILIES: tuple = (
    ("white velocity", ((1, False),)),
    ("Gauss-Markov velocity", ((1, True),)),
    ("white height", ((2, False),)),
    ("coloured height", ((2, True),)),
    ("white + Gauss-Markov velocity", ((1, False), (1, True))),
    ("velocity + height", ((1, False), (2, False))),
    ("white velocity + coloured height", ((1, False), (2, True))),
    ("white + coloured height", ((2, False), (2, True))),
    ("coloured velocity + height", ((1, True), (2, True))),
)


@dataclass(frozen=True)
class PassDifference:
    """Difference of two passes of a repeat track, ``z_a − z_b``, on a common along-track
    grid in steps of ``v̄·Δt`` (v̄ the pair's mean ground speed).

    Attributes
    ----------
    d_mgal : ndarray, shape (n,)
        NaN-free difference (mGal).
    speed_ratios : (float, float)
        ``v_a/v̄``, ``v_b/v̄``: a pass flown faster sees the same noise stretched in distance.
    """

    d_mgal: np.ndarray
    speed_ratios: tuple


def pass_difference(s_a_m, z_a, s_b_m, z_b, dt_s: float, lowpass_hz: float) -> PassDifference | None:
    """``z_a − z_b`` on a common along-track grid (module :class:`PassDifference`).

    Each pass is low-passed (zero-phase Butterworth, order 8, at ``lowpass_hz``) in its own
    time, then interpolated (cubic) onto the overlap of the two passes' along-track
    positions ``s`` (m) at spacing ``v̄·Δt``.  Returns None when the passes do not overlap
    for at least 64 steps or a pass has missing values in the overlap.
    """
    from scipy.interpolate import CubicSpline
    from scipy.signal import butter, sosfiltfilt

    out = []
    speeds = []
    for s, z in ((s_a_m, z_a), (s_b_m, z_b)):
        s = np.asarray(s, dtype=float)
        z = np.asarray(z, dtype=float)
        if s.size < 64 or not np.all(np.isfinite(z)) or not np.all(np.isfinite(s)):
            return None
        if s[-1] < s[0]:
            s, z = s[::-1], z[::-1]
        if np.any(np.diff(s) <= 0):
            return None
        fs = 1.0 / dt_s
        if lowpass_hz < 0.45 * fs:
            sos = butter(8, lowpass_hz, fs=fs, output="sos")
            z = sosfiltfilt(sos, z - np.mean(z)) + np.mean(z)
        out.append((s, z))
        speeds.append((s[-1] - s[0]) / ((s.size - 1) * dt_s))
    v_bar = 0.5 * (speeds[0] + speeds[1])
    lo = max(out[0][0][0], out[1][0][0])
    hi = min(out[0][0][-1], out[1][0][-1])
    n = int(np.floor((hi - lo) / (v_bar * dt_s)))
    if n < 64:
        return None
    grid = lo + np.arange(n) * v_bar * dt_s
    za = CubicSpline(*out[0])(grid)
    zb = CubicSpline(*out[1])(grid)
    return PassDifference(za - zb, (speeds[0] / v_bar, speeds[1] / v_bar))


def pass_differences(s_a_m, z_a, s_b_m, z_b, dt_s: float, lowpass_hz: float,
                     min_steps: int = 64) -> list[PassDifference]:
    """:func:`pass_difference` for passes with missing values (NaN): each finite run of a pass
    (at least ``min_steps`` samples) is low-passed and interpolated on its own, and the
    difference is returned as its finite stretches of at least ``min_steps`` grid steps.  A
    pass with one hole (a gravimeter dropout) then still gives its pair's noise spectrum on
    either side of it, where :func:`pass_difference` gives nothing; without holes the result
    is :func:`pass_difference`'s.

    Returns
    -------
    list of PassDifference
        Possibly empty (no overlap, positions not increasing, nothing long enough).
    """
    from scipy.interpolate import CubicSpline
    from scipy.signal import butter, sosfiltfilt

    pieces, speeds, extent = [], [], []
    fs = 1.0 / dt_s
    sos = butter(8, lowpass_hz, fs=fs, output="sos") if lowpass_hz < 0.45 * fs else None
    for s, z in ((s_a_m, z_a), (s_b_m, z_b)):
        s = np.asarray(s, dtype=float)
        z = np.asarray(z, dtype=float)
        if s.size < min_steps or not np.all(np.isfinite(s)):
            return []
        if s[-1] < s[0]:
            s, z = s[::-1], z[::-1]
        if np.any(np.diff(s) <= 0):
            return []
        runs = []
        ok = np.concatenate([[False], np.isfinite(z), [False]])
        starts = np.flatnonzero(ok[1:] & ~ok[:-1])
        ends = np.flatnonzero(~ok[1:] & ok[:-1])
        for a, b in zip(starts, ends):
            if b - a < min_steps:
                continue
            zz = z[a:b]
            if sos is not None:
                zz = sosfiltfilt(sos, zz - np.mean(zz)) + np.mean(zz)
            runs.append(CubicSpline(s[a:b], zz))
        pieces.append(runs)
        speeds.append((s[-1] - s[0]) / ((s.size - 1) * dt_s))
        extent.append((s[0], s[-1]))
    v_bar = 0.5 * (speeds[0] + speeds[1])
    lo = max(extent[0][0], extent[1][0])
    hi = min(extent[0][1], extent[1][1])
    n = int(np.floor((hi - lo) / (v_bar * dt_s)))
    if n < min_steps:
        return []
    grid = lo + np.arange(n) * v_bar * dt_s
    vals = []
    for runs in pieces:
        v = np.full(n, np.nan)
        for sp in runs:
            inside = (grid >= sp.x[0]) & (grid <= sp.x[-1])
            v[inside] = sp(grid[inside])
        vals.append(v)
    d = vals[0] - vals[1]
    ok = np.concatenate([[False], np.isfinite(d), [False]])
    starts = np.flatnonzero(ok[1:] & ~ok[:-1])
    ends = np.flatnonzero(~ok[1:] & ok[:-1])
    ratios = (speeds[0] / v_bar, speeds[1] / v_bar)
    return [PassDifference(d[a:b], ratios) for a, b in zip(starts, ends) if b - a >= min_steps]


@dataclass
class NoiseFit:
    """Result of :func:`fit_noise_model`.

    Attributes
    ----------
    model : NoiseModel
        The chosen family's model at R = 1 (absolute weights: the survey's mean level).
    Q_mgal2 : float
        Stationary anomaly level of the fit, mGal² per step (at order ``m``).
    m : int
        Anomaly order with the largest likelihood in the fitted band (1, 2 or 3).
    candidates : list of dict
        Every family tried: name, negative log-likelihood, parameters, BIC.
    n_bins : int
        Spectral estimates used.
    fmax_hz : float
    """

    model: NoiseModel
    Q_mgal2: float
    m: int
    candidates: list
    n_bins: int
    fmax_hz: float
    rolloff_s: float = 0.0
    """β (s) of the anomaly's spectrum ``exp(−β f)`` in the fit (:func:`anomaly_psd`)."""
    unmoved: NoiseFit | None = None
    """The fit before a decision that puts more noise below the fitted band than the spectra
    show — AR corners moved below the data (``hidden_corners_hz``), or a bare white height given
    its random-walk part (``white_height_nested``) — for the crossovers to check; else None."""


def _unpack(theta, spec, phi_min: float = 0.0):
    Q = float(np.exp(theta[0]))
    comps, k = [], 1
    for order, free_phi in spec:
        w = float(np.exp(theta[k]))
        k += 1
        phi = 0.0
        if free_phi:
            phi = float(phi_min + (PHI_MAX - phi_min) / (1.0 + np.exp(-theta[k])))
            k += 1
        comps.append(NoiseComponent(order, phi, w))
    return Q, comps


def knee_hz(phi: float, dt_s: float) -> float:
    """Corner frequency (Hz) of an AR(1) component, ``(1 − φ)/(2π Δt)``."""
    return float((1.0 - phi) / (2.0 * np.pi * dt_s))


def fit_noise_model(z_segments, dt_s: float, m: int = 2, fmax_hz: float = 0.2,
                    families=FAMILIES, nw: float = 3.0, min_duration_s: float = 120.0,
                    n_starts: int = 4, seed: int = 0, bic_margin: float = BIC_MARGIN,
                    differences=(), octave_weights: bool = False,
                    knee_max_fraction: float | None = None, hidden_knees: bool = True,
                    prefer_height: bool = False, height_tau_min_s: float = 20.0,
                    bound: VelocityBound | None = None, bound_fmax_hz: float = 0.01,
                    bound_check_band_hz: tuple = (0.02, 0.05), bound_max_excess: float = 1.25,
                    anomaly_rolloff: bool = True) -> NoiseFit:
    """Fit the error of z by the Whittle likelihood of prewhitened multitaper spectra.

    Model of z's spectrum: ``S(f) = S_anomaly(f; Q, m, β) + Σ_c S_c(f)``; each family of
    :data:`FAMILIES` is fitted (weights, AR coefficients, Q and the anomaly's roll-off β by
    Nelder–Mead from ``n_starts`` seeded starts); the simplest family whose BIC is within ``bic_margin`` of
    the smallest is chosen (a richer shape needs strong evidence).  Each
    multitaper estimate has ``dof`` degrees of freedom and neighbours within the
    bandwidth are correlated; the likelihood counts ``dof/2 · (1/(2·nw))`` per bin, i.e.
    one χ² of ``2K`` dof per resolution cell.

    Parameters
    ----------
    z_segments : sequence of ndarray
        NaN-free stretches of z (mGal), e.g. the finite runs of every line.
    dt_s : float
        Step (s).
    m : int
        Order of the anomaly model while the families are compared; the chosen family is
        then refitted with m = 1, 2, 3 and the best order is returned.
    fmax_hz : float
        Highest frequency fitted (Hz).
    families : sequence of (name, spec)
    min_duration_s : float
        Stretches shorter than this are skipped.
    knee_max_fraction : float, optional
        Corners of the AR(1) components at most this × the lowest fitted frequency.
    hidden_knees : bool
        Move corners that fall between the lowest fitted frequency and twice the
        anomaly/noise crossover below the data and refit (see the code comment); so too
        any corner inside the fitted band of a height family ``prefer_height`` put in place
        of the velocity family the BIC chose.
    prefer_height : bool
        The error is known to come from GNSS heights (no velocity in the file): when the
        family chosen is a pure *velocity* family, the simplest height family within
        ``bic_margin`` of the best replaces it, if there is one.  The spectra cannot tell a
        white-velocity error (a random-walk height error, unbounded — not what GNSS heights
        do) from a coloured height error whose corner lies in the anomaly band, yet the two
        put very different noise there.  A chosen family with a height component is kept:
        the data have already said the error is partly a height error.
    height_tau_min_s : float
        Shortest correlation time (s) of a GNSS height error (multipath, troposphere and
        satellite geometry change over tens of seconds to minutes).  The corner of a height
        family ``prefer_height`` put in place is kept at or below ``1/(2π·height_tau_min_s)``
        (0.008 Hz for 20 s) as well as below the lowest fitted frequency: on short lines the
        spectra start at 0.03–0.06 Hz, and a corner guessed between there and the anomaly
        band took the noise out of it (random layout 489, 12 km lines at 74 m/s: corner
        0.034 Hz, 1.44x the FIR 100 s error; at 0.008 Hz, 0.82x).
    differences : sequence of PassDifference
        Differences of two passes of one repeat track on a common along-track grid: the
        anomaly cancels, so their spectra show the noise alone — also where it hides under
        the anomaly in a single line (the band where the smoother must cut).  They enter the
        likelihood with the noise-only model (each pass at its own speed).
    bound : VelocityBound, optional
        The height–velocity misfit's spectrum (:func:`velocity_bound`): an upper bound on the
        velocity error in z where the anomaly hides it.  Each group enters the likelihood with
        a free non-negative height error of its own, profiled out, so it binds only where the
        model puts more error than the misfit shows (``_Whittle._bound_nll``).  Corners are
        still moved below the data (``hidden_knees``), the cautious side, and the refit too
        is fitted under the bound; where the moved shape is refuted by the misfit (a χ² test,
        :func:`bound_p_value`) and the shape as fitted is not, the fitted shape is kept
        (:func:`_cautious_shape_under_bound`: z alone cannot see the noise below its band,
        the heights can).  Only its groups up to ``bound_fmax_hz`` enter; and only when
        the GNSS accounts for z's noise just above the anomaly band: the median ratio of z's
        line spectra to the misfit's over ``bound_check_band_hz`` at most ``bound_max_excess``
        (:func:`_bound_applies`: the misfit holds the velocity error plus the height error, so
        where the GNSS makes z's noise, z exceeds it only by the estimates' scatter; a 1 Hz
        interval-mean gravimeter's sampling error puts 13–28× the misfit into z there, and the
        bound would have removed it).  The families are fitted without the bound first, and
        again under it only where that fit exceeds it (``velocity_bound.refitted``): a slack
        bound changes no number.

    anomaly_rolloff : bool
        The anomaly's spectrum as the random walk times ``exp(−β f)``, β free where it lowers a
        family's BIC by more than ``bic_margin`` (``_Whittle.with_rolloff``); False: β = 0.

    Returns
    -------
    NoiseFit

    Raises
    ------
    ValueError
        No stretch long enough.
    """
    spectra = _collect_spectra(z_segments, differences, dt_s, fmax_hz, nw, min_duration_s)
    opts = dict(dt_s=dt_s, seed=seed, n_starts=n_starts, octave_weights=octave_weights, families=families, m=m,
                bic_margin=bic_margin, prefer_height=prefer_height, hidden_knees=hidden_knees,
                knee_max_fraction=knee_max_fraction, height_tau_min_s=height_tau_min_s, fmax_hz=fmax_hz,
                rolloff=anomaly_rolloff)
    fit = _fit_families(spectra, None, **opts)
    if bound is None:
        return fit
    check = _bound_applies(spectra, bound, bound_check_band_hz, bound_max_excess)
    keep = bound.f_hz <= bound_fmax_hz
    if check["applied"] and keep.any():
        bound = replace(bound, f_hz=bound.f_hz[keep], psd=bound.psd[keep], weight=bound.weight[keep],
                        slack=bound.slack[keep])
        over = _model_to_bound(fit.model, bound)
        check.update(n_segments=bound.n_segments, groups=int(bound.f_hz.size),
                     f_hz=[float(bound.f_hz.min()), float(bound.f_hz.max())], max_model_to_misfit=over,
                     refitted=bool(over > 1.0))
        if over > 1.0:
            # the fit without the bound puts more velocity error below bound_fmax_hz than the
            # heights and velocities disagree by: fitted again under it.  Where it is slack the
            # fit is the one without it (the same numbers: a bound's excursions would move the
            # Nelder–Mead searches to other local optima for nothing)
            fit = _fit_families(spectra, bound, **opts)
            check["max_model_to_misfit_after"] = _model_to_bound(fit.model, bound)
        fit = _cautious_shape_under_bound(fit, bound, check)
    fit.model.info["velocity_bound"] = check
    return fit


def _cautious_shape_under_bound(fit: NoiseFit, bound: VelocityBound, check: dict, alpha: float = 0.05) -> NoiseFit:
    """The heights' verdict on the cautious shape.  Moving a corner below the data (or giving
    a bare white height its random-walk part) puts more noise below the fitted band than the
    spectra of z show, because z alone cannot tell that noise from the anomaly.  The
    height–velocity misfit can: where the bound applies, the cautious model is refuted by it
    (:func:`bound_p_value` < ``alpha``) and the fit as it was (``unmoved``) is not, the unmoved
    fit is used (``check["cautious_shape"]``)."""
    if fit.unmoved is None:
        return fit
    p_moved, p_kept = bound_p_value(fit.model, bound), bound_p_value(fit.unmoved.model, bound)
    refuted = bool(p_moved < alpha <= p_kept)
    check["cautious_shape"] = {"model_to_misfit": _model_to_bound(fit.model, bound),
                               "unmoved_model_to_misfit": _model_to_bound(fit.unmoved.model, bound),
                               "p_value": p_moved, "unmoved_p_value": p_kept, "alpha": alpha, "refuted": refuted}
    if refuted:
        return replace(fit.unmoved, unmoved=None)
    return fit


def bound_p_value(model: NoiseModel, bound: VelocityBound) -> float:
    """How probable the misfit's spectrum is if the model's velocity error were all it held:
    each group's estimate is ``S·χ²_ν/ν`` (ν its degrees of freedom) with ``S ≥`` the model's
    PSD (the misfit adds the height error), so a group far below the model refutes it.  The
    smallest lower-tail probability over the G groups, times G (Bonferroni; capped at 1)."""
    nu = 2.0 * np.asarray(bound.weight, float)
    lower = chi2.cdf(nu * bound.psd / model.psd(bound.f_hz), nu)
    return float(min(1.0, bound.f_hz.size * np.min(lower)))


def _model_to_bound(model: NoiseModel, bound: VelocityBound) -> float:
    """The largest ratio of a model's velocity error in z to the bound (``slack × psd``)."""
    return float(np.max(model.psd(bound.f_hz) / (bound.slack * bound.psd)))


def _fit_families(spectra, bound, *, dt_s, seed, n_starts, octave_weights, families, m, bic_margin,
                  prefer_height, hidden_knees, knee_max_fraction, height_tau_min_s, fmax_hz, rolloff) -> NoiseFit:
    """The body of :func:`fit_noise_model` on collected spectra, under ``bound`` (or none)."""
    prob = _Whittle(spectra, dt_s, np.random.default_rng(seed), n_starts, octave_weights, bound, rolloff)
    f_low = float(np.min(spectra.f_hz))
    if knee_max_fraction is not None:
        prob.phi_min = float(np.clip(1.0 - 2.0 * np.pi * dt_s * knee_max_fraction * f_low, 0.0, PHI_MAX - 1e-6))
    chosen = prob.select(families, m, bic_margin, prefer_height)
    # A bare white height was replaced by the family that nests it (_Whittle.select); the bare
    # fit is kept beside (``unmoved``), as for moved corners below: where the added random-walk
    # part over-states the noise, crossovers can say so (app.core.model_check).
    unmoved = (_finished_fit(prob, prob.white_height_bare, m, spectra, [], fmax_hz)
               if prob.white_height_bare is not None else None)
    if prob.best_fit_over is not None:
        # velocity + height, the best fit, in place of the margin's choice on heights-only GNSS:
        # that choice is kept beside, for the crossovers to restore where the f² part over-states
        # the FIR noise they allow
        unmoved = _finished_fit(prob, prob.best_fit_over, m, spectra, [], fmax_hz)
    hidden = prob.hidden_corners(chosen, m) if hidden_knees else []
    fitted = None
    preferred = hidden_knees and prob.height_replaced is not None and prob.best_fit_over is None
    # where corners are moved to: below the data, and for a preferred height family (its
    # corner is not the data's) also below what a GNSS height error's correlation allows
    f_move = min(f_low, 1.0 / (2.0 * np.pi * height_tau_min_s)) if preferred else f_low
    if preferred and not hidden:
        # The heights-only rule preferred this height family to the velocity family the BIC
        # chose, so its corner is not the data's: the corner-free f² shape fitted as well.
        # Inside the fitted band such a corner still takes the f² slope away below it, and
        # where it was placed — after the order refit too, above twice the crossover — is
        # chance (a 4-line heights-only layout: corner 0.04 Hz, 1.45x FIR; moved, 0.99x).  It
        # is moved below the data like the corners above — and below 1/(2π·height_tau_min_s),
        # since on short lines "below the data" can still be the anomaly band (0.03–0.06 Hz).
        fitted = _finished_fit(prob, chosen, m, spectra, [], fmax_hz)
        hidden = [knee_hz(c.phi, dt_s) for c in fitted.model.components
                  if c.phi > 0 and knee_hz(c.phi, dt_s) > f_move]
    phi_low = float(np.clip(1.0 - 2.0 * np.pi * dt_s * f_move, 0.0, PHI_MAX - 1e-6))
    if hidden and prob.phi_min < phi_low:
        # An AR corner lowers the noise below it.  Placed above the lowest fitted frequency but
        # below twice the anomaly/noise crossover, it was decided where the anomaly hides the
        # noise — and a corner guessed too high lets noise through as anomaly.  Such corners are
        # moved below the data (the noise keeps its slope down to the lowest frequency) and the
        # families are fitted again.  The fit as it was is kept beside (``unmoved``): where the
        # move over-states the noise, crossovers can say so (app.core.model_check).
        unmoved = fitted if fitted is not None else _finished_fit(prob, chosen, m, spectra, [], fmax_hz)
        prob.phi_min = phi_low
        chosen = prob.select(families, m, bic_margin, prefer_height)
    return replace(_finished_fit(prob, chosen, m, spectra, hidden, fmax_hz), unmoved=unmoved)


def _bound_applies(spectra, bound: VelocityBound, band_hz, max_excess: float) -> dict:
    """Whether the GNSS misfit bounds z's noise: the median ratio of z's line spectra to the
    misfit's PSD over ``band_hz`` (above the anomaly band, where z's spectrum is its noise), at
    most ``max_excess``.  Where it is larger, something other than the GNSS velocity error
    (the gravimeter's sampling or response, its own noise) makes z's noise there, and may
    below the band too: the bound, which sees only the GNSS, does not apply."""
    line = spectra.is_line > 0
    f, p = spectra.f_hz[line], spectra.psd[line]
    sel = (f >= band_hz[0]) & (f <= band_hz[1]) & (f >= bound.f_hz.min()) & (f <= bound.f_hz.max())
    if not sel.any():
        return {"applied": False, "reason": f"no spectrum of z and of the misfit over {band_hz[0]:g}-{band_hz[1]:g} Hz "
                                            "to compare"}
    ratio = float(np.median(p[sel] / np.exp(np.interp(np.log(f[sel]), np.log(bound.f_hz), np.log(bound.psd)))))
    out = {"applied": bool(ratio <= max_excess), "z_to_misfit": ratio,
           "check_band_hz": [float(band_hz[0]), float(band_hz[1])]}
    if not out["applied"]:
        out["reason"] = (f"z's noise is {ratio:.1f}x the GNSS misfit's over {band_hz[0]:g}-{band_hz[1]:g} Hz "
                         f"(> {max_excess:g}): not the GNSS alone, so the misfit does not bound it")
    return out


def _finished_fit(prob, chosen: dict, m: int, spectra, hidden: list, fmax_hz: float) -> NoiseFit:
    """The chosen family refitted over the orders m = 1, 2, 3 and packed as a :class:`NoiseFit`."""
    dt_s = prob.dt_s
    orders = prob.orders(chosen, m)
    m_best = min(orders, key=lambda mm: orders[mm][0])
    Q_best, comps_best = _unpack(orders[m_best][1], chosen["_spec"], prob.phi_min)
    model = NoiseModel(tuple(comps_best), float(dt_s), chosen["family"],
                       info={"fit": "Whittle, prewhitened multitaper", "fmax_hz": float(fmax_hz),
                             "n_bins": int(spectra.f_hz.size), "n_difference_bins": spectra.n_diff_bins,
                             "n_pass_differences": spectra.n_differences, "m": int(m_best),
                             "hidden_corners_hz": hidden,
                             # the velocity family the heights-only rule replaced (None: not applied)
                             "height_family_preferred": prob.height_replaced,
                             # a bare white height replaced by the family that nests it
                             "white_height_nested": chosen is prob.white_height_nest,
                             # heights only: the margin's choice velocity + height (best BIC) replaced
                             "best_fit_replaced": (prob.best_fit_over["family"]
                                                   if prob.best_fit_over is not None else None),
                             "max_corner_hz": knee_hz(prob.phi_min, dt_s) if prob.phi_min > 0 else None,
                             "velocity_bound": None,   # fit_noise_model
                             "nll_by_m": {str(k): float(v[0]) for k, v in orders.items()},
                             # the anomaly's spectrum in the fit: exp(−β f) on the random walk
                             "anomaly_rolloff_s": prob.rolloff_of(orders[m_best][1], chosen["_spec"])})
    cands = [{k: v for k, v in c.items() if not k.startswith("_")} for c in prob.candidates]
    return NoiseFit(model, float(Q_best), int(m_best), cands, int(spectra.f_hz.size), float(fmax_hz),
                    rolloff_s=prob.rolloff_of(orders[m_best][1], chosen["_spec"]))


@dataclass
class _Spectra:
    """Every spectral estimate of the fit, concatenated: frequency, PSD, weight, and for each
    bin whether it belongs to a line (anomaly + noise) or a pass difference (noise of two
    passes, each at its own speed ratio r1, r2)."""

    f_hz: np.ndarray
    psd: np.ndarray
    weight: np.ndarray
    is_line: np.ndarray
    r1: np.ndarray
    r2: np.ndarray
    is_diff: np.ndarray
    n_differences: int

    @property
    def n_diff_bins(self) -> int:
        return int(np.sum(self.is_diff > 0))


def _collect_spectra(z_segments, differences, dt_s, fmax_hz, nw, min_duration_s) -> _Spectra:
    items = []   # (Spectrum, is_difference, speed ratios)
    for z in z_segments:
        z = np.asarray(z, dtype=float)
        if z.size * dt_s >= min_duration_s:
            try:
                items.append((multitaper_psd(z, dt_s, fmax_hz, nw=nw), False, (1.0, 1.0)))
            except ValueError:
                pass
    for d in differences:
        if d.d_mgal.size * dt_s >= min_duration_s:
            try:
                items.append((multitaper_psd(d.d_mgal, dt_s, fmax_hz, nw=nw), True,
                              tuple(float(r) for r in d.speed_ratios)))
            except ValueError:
                pass
    items = [it for it in items if it[0].f_hz.size > 0]
    if not any(not diff for _, diff, _ in items):
        # no stretch left a bin after the sharpest anti-alias filter it is long enough for (the
        # lines of a 12 km layout at 117 m/s and 2 Hz: refused): the wider transitions instead
        for z in z_segments:
            z = np.asarray(z, dtype=float)
            if z.size * dt_s >= min_duration_s:
                try:
                    items.append((multitaper_psd(z, dt_s, fmax_hz, nw=nw, need_bins=True), False, (1.0, 1.0)))
                except ValueError:
                    pass
    if not any(not diff for _, diff, _ in items):
        raise ValueError(f"no stretch of z of at least {min_duration_s:g} s to fit the noise model on")

    def cat(fn):
        return np.concatenate([np.full(sp.f_hz.size, fn(sp, diff, r)) for sp, diff, r in items])

    return _aggregate(_Spectra(np.concatenate([sp.f_hz for sp, _, _ in items]), np.concatenate([sp.psd for sp, _, _ in items]),
                    cat(lambda sp, diff, r: 0.5 * sp.dof / (2.0 * nw)), cat(lambda sp, diff, r: 0.0 if diff else 1.0),
                    cat(lambda sp, diff, r: r[0]), cat(lambda sp, diff, r: r[1]),
                    cat(lambda sp, diff, r: 1.0 if diff else 0.0), int(sum(diff for _, diff, _ in items))))


def _log_groups(f, psd, w, n_groups: int):
    """Spectral estimates pooled in ``n_groups`` log-spaced frequency groups: each non-empty
    group's weighted geometric-mean frequency, weighted-mean PSD and summed weight."""
    edges = np.geomspace(f.min(), f.max() * (1 + 1e-9), n_groups + 1)
    g = np.clip(np.searchsorted(edges, f, side="right") - 1, 0, n_groups - 1)
    W = np.bincount(g, w, n_groups)
    keep = W > 0
    fg = np.exp(np.bincount(g, w * np.log(f), n_groups)[keep] / W[keep])
    pg = np.bincount(g, w * psd, n_groups)[keep] / W[keep]
    return fg, pg, W[keep]


def _aggregate(sp: _Spectra, n_groups: int = 400) -> _Spectra:
    """The lines' estimates pooled in ``n_groups`` log-spaced frequency groups.

    Within a group the model spectrum hardly changes, so Σ w(log S + I/S) over its bins equals
    W(log S(f̄) + Ī/S(f̄)) with W = Σw and Ī the weighted mean: the likelihood is the same and
    a large survey's fit costs as little as a small one's.  Pass differences are kept as they
    are (their speed ratios differ)."""
    line = sp.is_line > 0
    if line.sum() <= 2 * n_groups:
        return sp
    fg, Ig, Wk = _log_groups(sp.f_hz[line], sp.psd[line], sp.weight[line], n_groups)
    k = int(Wk.size)
    d = ~line

    def cat(a, b):
        return np.concatenate([a, b])

    return _Spectra(cat(fg, sp.f_hz[d]), cat(Ig, sp.psd[d]), cat(Wk, sp.weight[d]), cat(np.ones(k), sp.is_line[d]),
                    cat(np.ones(k), sp.r1[d]), cat(np.ones(k), sp.r2[d]), cat(np.zeros(k), sp.is_diff[d]),
                    sp.n_differences)


@njit(cache=True, nogil=True, error_model="numpy")
def _ar_gain(phi: float, er: float, ei: float) -> float:
    """``|1 − φ e|²`` for ``e = er + i·ei`` (as ``np.abs(1 − φe) ** 2``)."""
    a = math.hypot(1.0 - phi * er, -phi * ei)
    return a * a


@njit(cache=True, nogil=True, error_model="numpy")
def _whittle_nll_kernel(th, n_base, d_anom, line_bins, f_hz, dt, orders, free_phi, phi_min, phi_max,
                        rolloff_max, num1, e1r, e1i, r1, num2, e2r, e2i, r2, diff_dt, wt, psd_obs,
                        bnum, ebr, ebi, b_ib, b_weight):
    """The weighted Whittle negative log-likelihood of :meth:`_Whittle.nll` (its docstring
    gives θ), compiled: the fit evaluates it ~10⁵ times on a few hundred bins, where numpy's
    per-call overhead was most of a survey's noise stage.  Arrays: per bin of the spectra
    (``d_anom`` = |1 − e|^{2m}, ``line_bins`` 1/0, ``num1``/``num2`` rows |1 − e|^{2j} for
    j = 0, 1, 2 of the two scalings, their ``e`` as real/imaginary parts, ``r1``, ``r2``,
    ``diff_dt``, the weights and the observed PSD); ``num2`` with no columns when there are
    no pass differences; ``bnum`` with no columns when there is no misfit bound (else its
    rows, ``e``, ``slack × psd`` and weights)."""
    n = th.size
    big = 0.0
    for i in range(n):
        if abs(th[i]) > big:
            big = abs(th[i])
    if big > 200.0:
        return 1e300
    nb = f_hz.size
    q = math.exp(th[0])
    S = np.empty(nb)
    for i in range(nb):
        S[i] = dt * q / d_anom[i] if line_bins[i] else 0.0
    if n > n_base:
        beta = rolloff_max / (1.0 + math.exp(-th[n - 1]))
        for i in range(nb):
            S[i] = S[i] * math.exp(-beta * f_hz[i])
    has2 = num2.shape[1] > 0
    hasb = bnum.shape[1] > 0
    Sb = np.zeros(bnum.shape[1])
    k = 1
    for c in range(orders.size):
        w = math.exp(th[k])
        k += 1
        phi = 0.0
        if free_phi[c]:
            phi = phi_min + (phi_max - phi_min) / (1.0 + math.exp(-th[k]))
            k += 1
        j = orders[c]
        if hasb:
            for i in range(Sb.size):
                pb = w * bnum[j, i] if j else w
                if phi != 0.0:
                    pb = pb / _ar_gain(phi, ebr[i], ebi[i])
                Sb[i] = Sb[i] + dt * pb
        for i in range(nb):
            p1 = w * num1[j, i] if j else w * 1.0
            if phi != 0.0:
                p1 = p1 / _ar_gain(phi, e1r[i], e1i[i])
            S[i] = S[i] + dt * p1 / r1[i]
            if has2:
                p2 = w * num2[j, i] if j else w * 1.0
                if phi != 0.0:
                    p2 = p2 / _ar_gain(phi, e2r[i], e2i[i])
                S[i] = S[i] + diff_dt[i] * p2 / r2[i]
    out = 0.0
    for i in range(nb):
        if not (S[i] > 0.0 and S[i] < np.inf):
            return 1e300
    for i in range(nb):
        out += wt[i] * (math.log(S[i]) + psd_obs[i] / S[i])
    if hasb:
        for i in range(Sb.size):
            if not (math.isfinite(Sb[i]) and Sb[i] >= 0.0):
                return 1e300
        for i in range(Sb.size):
            top = max(Sb[i], b_ib[i])
            out += b_weight[i] * (math.log(top) + b_ib[i] / top)
    return out


@njit(cache=True, nogil=True)
def _argsort_small(v):
    """Stable insertion argsort (numpy's for arrays of at most 16 elements)."""
    n = v.size
    ind = np.arange(n)
    for i in range(1, n):
        vi = ind[i]
        j = i
        while j > 0 and v[vi] < v[ind[j - 1]]:
            ind[j] = ind[j - 1]
            j -= 1
        ind[j] = vi
    return ind


@njit(cache=True, nogil=True, error_model="numpy")
def _nll_at(x, th, pos, kargs) -> float:
    """:func:`_whittle_nll_kernel` with θ's elements ``pos`` set to ``x`` (``th`` is updated)."""
    for i in range(x.size):
        th[pos[i]] = x[i]
    return _whittle_nll_kernel(th, *kargs)


@njit(cache=True, nogil=True)
def _converged(sim, fsim, xatol: float, fatol: float) -> bool:
    """SciPy's test: every vertex within ``xatol`` of the best, every value within ``fatol``."""
    dx = 0.0
    df = 0.0
    for j in range(1, sim.shape[0]):
        df = max(df, abs(fsim[0] - fsim[j]))
        for i in range(sim.shape[1]):
            dx = max(dx, abs(sim[j, i] - sim[0, i]))
    return dx <= xatol and df <= fatol


@njit(cache=True, nogil=True, error_model="numpy")
def _nelder_mead_kernel(x0, template, pos, maxiter, xatol, fatol, kargs):
    """Nelder–Mead minimisation of :func:`_whittle_nll_kernel` (its arguments after θ packed
    in ``kargs``) over the elements ``pos`` of θ, the others held at ``template``'s: step for
    step SciPy's ``_minimize_neldermead`` with its defaults (ρ = 1, χ = 2, ψ = σ = 0.5; the
    initial simplex x0 with one coordinate ×1.05, or 0.00025 where it is 0; no bounds, no limit
    on evaluations), whose Python loop cost more than the likelihood itself — but the simplex
    sorted stably (:func:`_argsort_small`).  Returns (x, f, iterations, evaluations)."""
    N = x0.size
    th = template.copy()
    sim = np.empty((N + 1, N))
    sim[0] = x0
    for k in range(N):
        sim[k + 1] = x0
        sim[k + 1, k] = (1 + 0.05) * x0[k] if x0[k] != 0 else 0.00025
    fsim = np.empty(N + 1)
    for k in range(N + 1):
        fsim[k] = _nll_at(sim[k], th, pos, kargs)
    nfev = N + 1
    ind = _argsort_small(fsim)
    sim, fsim = sim[ind], fsim[ind]
    xbar = np.empty(N)
    iterations = 1
    while iterations < maxiter and not _converged(sim, fsim, xatol, fatol):
        for i in range(N):   # numpy's add.reduce over the rows: in order
            acc = sim[0, i]
            for j in range(1, N):
                acc = acc + sim[j, i]
            xbar[i] = acc / N
        xr = 2 * xbar - 1 * sim[N]
        fxr = _nll_at(xr, th, pos, kargs)
        nfev += 1
        doshrink = False
        if fxr < fsim[0]:
            xe = 3 * xbar - 2 * sim[N]
            fxe = _nll_at(xe, th, pos, kargs)
            nfev += 1
            if fxe < fxr:
                sim[N], fsim[N] = xe, fxe
            else:
                sim[N], fsim[N] = xr, fxr
        elif fxr < fsim[N - 1]:
            sim[N], fsim[N] = xr, fxr
        else:
            outside = fxr < fsim[N]
            xc = 1.5 * xbar - 0.5 * sim[N] if outside else (1 - 0.5) * xbar + 0.5 * sim[N]
            fxc = _nll_at(xc, th, pos, kargs)
            nfev += 1
            if (fxc <= fxr) if outside else (fxc < fsim[N]):
                sim[N], fsim[N] = xc, fxc
            else:
                doshrink = True
        if doshrink:
            for j in range(1, N + 1):
                sim[j] = sim[0] + 0.5 * (sim[j] - sim[0])
                fsim[j] = _nll_at(sim[j], th, pos, kargs)
                nfev += 1
        iterations += 1
        ind = _argsort_small(fsim)
        sim, fsim = sim[ind], fsim[ind]
    return sim[0].copy(), fsim.min(), iterations, nfev


class _Whittle:
    """The Whittle likelihood of the spectra under (anomaly order m, family spec, θ) and its
    minimisation (Nelder–Mead from random and nested starts)."""

    def __init__(self, sp: _Spectra, dt_s: float, rng, n_starts: int, octave_weights: bool,
                 bound: VelocityBound | None = None, rolloff: bool = True):
        self.sp, self.dt_s, self.rng, self.n_starts = sp, float(dt_s), rng, int(n_starts)
        # the anomaly's spectrum rolls off as exp(−β f) with β free (the last element of θ,
        # :func:`rolloff_s`); without it the random-walk nuisance keeps the f^{−2m} slope up
        # to the noise band and takes noise just above the crossover as anomaly
        self.rolloff = bool(rolloff)
        # the height–velocity misfit's spectrum (velocity_bound): the noise model may not put
        # more velocity error there than the misfit shows (nll)
        self.bound = bound
        if bound is not None:
            eb = np.exp(-2j * np.pi * bound.f_hz * float(dt_s))
            self._bound_e = eb
            self._bound_num = {j: np.abs(1.0 - eb) ** (2 * j) for j in (1, 2)}
        self.wt = sp.weight
        if octave_weights:
            # every octave counts as much as the octave at the lowest frequency: the high band,
            # where bins are many and the shape matters least to the smoother, must not decide
            # the shape at the crossover
            self.wt = self.wt * np.minimum(1.0, 2.0 * float(np.min(sp.f_hz)) / sp.f_hz)
        self.n_eff = float(self.wt.sum())
        self.nu = sp.f_hz * dt_s
        self.d_anom = {mm: np.abs(1.0 - np.exp(-2j * np.pi * self.nu)) ** (2 * mm) for mm in (1, 2, 3)}
        # the bins' e^{-2πiν} of both scalings and their |1 − e|^{2j}, computed once: the
        # Nelder–Mead searches evaluate the components' spectra tens of thousands of times
        # (the same arithmetic as _component_psd_per_sample, so the same numbers)
        self._e = {1: np.exp(-2j * np.pi * np.asarray(self.nu * sp.r1, dtype=float))}
        if sp.n_differences:
            self._e[2] = np.exp(-2j * np.pi * np.asarray(self.nu * sp.r2, dtype=float))
        self._num = {(v, j): np.abs(1.0 - e) ** (2 * j) for v, e in self._e.items() for j in (1, 2)}
        self._variants = (1, 2) if sp.n_differences else (1,)
        self._line_bins = sp.is_line > 0
        self._diff_dt = sp.is_diff * self.dt_s
        self.level = float(np.median(sp.psd / dt_s))
        self.phi_min = 0.0
        # set by select(): the velocity family the heights-only rule replaced, and a bare white
        # height with the candidate that replaced it (_no_bare_white_height)
        self.height_replaced = self.white_height_bare = self.white_height_nest = None
        self.best_fit_over = None
        self.candidates: list = []
        self._kernel_spec: dict = {}
        self._kernel_arrays = self._arrays_for_kernel()
        self._f_hz = np.ascontiguousarray(sp.f_hz, dtype=float)
        self._line_bins = np.ascontiguousarray(self._line_bins)
        self.d_anom = {mm: np.ascontiguousarray(d) for mm, d in self.d_anom.items()}

    def _arrays_for_kernel(self) -> tuple:
        """The bins' arrays of :func:`_whittle_nll_kernel`, in its order: the two scalings'
        |1 − e|^{2j} (rows j = 0, 1, 2), e, r and the pass differences' Δt; the weights and
        the observed PSD; the misfit bound's rows, e, ``slack × psd`` and weights (no columns
        where there are no pass differences or no bound)."""
        def rows(num, n):
            return np.vstack([np.ones(n), num[1], num[2]])

        nb = self.sp.f_hz.size
        e1 = self._e[1]
        one = rows({j: self._num[(1, j)] for j in (1, 2)}, nb)
        if self.sp.n_differences:
            e2 = self._e[2]
            two = rows({j: self._num[(2, j)] for j in (1, 2)}, nb)
            r2 = np.asarray(self.sp.r2, dtype=float)
        else:
            e2, two, r2 = np.zeros(0, complex), np.zeros((3, 0)), np.zeros(0)
        if self.bound is not None:
            b = self.bound
            eb, bn = self._bound_e, rows(self._bound_num, b.f_hz.size)
            ib, bw = np.asarray(b.slack * b.psd, dtype=float), np.asarray(b.weight, dtype=float)
        else:
            eb, bn, ib, bw = np.zeros(0, complex), np.zeros((3, 0)), np.zeros(0), np.zeros(0)
        # C-contiguous float64 throughout: one compiled specialisation of the kernels (numba
        # compiles, ~11 s, and caches one per array layout)
        arrays = (one, e1.real, e1.imag, self.sp.r1, two, e2.real, e2.imag, r2, self._diff_dt, self.wt, self.sp.psd,
                  bn, eb.real, eb.imag, ib, bw)
        return tuple(np.ascontiguousarray(a, dtype=float) for a in arrays)

    def nll(self, theta, spec, mm) -> float:
        """The weighted Whittle negative log-likelihood at θ (log Q, then per component log w
        and, with a free φ, its logit; one more element carries the roll-off β).  Evaluated
        tens of thousands of times per fit: :func:`_whittle_nll_kernel` (the arithmetic of
        :func:`_unpack` and :func:`_component_psd_at`, term by term), :meth:`nll_numpy` the
        same in numpy."""
        ks = self._spec_arrays(spec)
        return float(_whittle_nll_kernel(np.asarray(theta, dtype=float), ks[2], self.d_anom[mm], self._line_bins,
                                         self._f_hz, self.dt_s, ks[0], ks[1], self.phi_min, PHI_MAX,
                                         ROLLOFF_MAX_S, *self._kernel_arrays))

    def _spec_arrays(self, spec) -> tuple:
        """A family's component orders, free-φ flags and θ length without the roll-off, for
        the kernels (cached per family)."""
        ks = self._kernel_spec.get(spec)
        if ks is None:
            ks = self._kernel_spec[spec] = (np.array([int(o) for o, _ in spec], dtype=np.int64),
                                            np.array([bool(f) for _, f in spec], dtype=np.bool_), _n_base(spec))
        return ks

    def nll_numpy(self, theta, spec, mm) -> float:
        """:meth:`nll` in numpy (the reference its compiled kernel is tested against)."""
        th = np.asarray(theta, dtype=float)
        if np.abs(th).max() > 200:
            return 1e300
        ex = np.exp(th)
        sp, dt, pm = self.sp, self.dt_s, self.phi_min
        with np.errstate(divide="ignore"):
            S = np.where(self._line_bins, dt * float(ex[0]) / self.d_anom[mm], 0.0)
        if th.size > _n_base(spec):
            S = S * np.exp(-rolloff_s(th) * sp.f_hz)
        k = 1
        Sb = 0.0
        for order, free_phi in spec:
            w = float(ex[k])
            k += 1
            phi = 0.0
            if free_phi:
                phi = float(pm + (PHI_MAX - pm) / (1.0 + np.exp(-th[k])))
                k += 1
            if self.bound is not None:
                pb = w * self._bound_num[order] if order else np.full(self.bound.f_hz.size, w)
                if phi != 0.0:
                    pb = pb / np.abs(1.0 - phi * self._bound_e) ** 2
                Sb = Sb + dt * pb
            for variant in self._variants:
                psd = w * self._num[(variant, order)] if order else w * 1.0
                if phi != 0.0:
                    psd = psd / np.abs(1.0 - phi * self._e[variant]) ** 2
                S = S + (dt * psd / sp.r1 if variant == 1 else self._diff_dt * psd / sp.r2)
        if not (S.min() > 0 and S.max() < np.inf):
            return 1e300
        out = float(np.sum(self.wt * (np.log(S) + sp.psd / S)))
        if self.bound is not None:
            out += self._bound_nll(Sb)
        return out

    def _bound_nll(self, Sb) -> float:
        """The misfit spectrum's term: its PSD is the velocity error in z plus a height error
        ≥ 0 of unknown size in every group; profiled out, a group where the model is below the
        misfit adds a constant, one where it is above adds the Whittle term at the model — an
        upper bound that binds only where the model puts more velocity error than the heights
        and velocities disagree by."""
        b = self.bound
        Sb = np.asarray(Sb, dtype=float)
        if Sb.ndim == 0 or not (np.all(np.isfinite(Sb)) and Sb.min() >= 0):
            return 1e300
        ib = b.slack * b.psd
        top = np.maximum(Sb, ib)
        return float(np.sum(b.weight * (np.log(top) + ib / top)))

    def _component_psd(self, variant: int, c: NoiseComponent) -> np.ndarray:
        """:func:`_component_psd_per_sample` at the bins of scaling ``variant`` (1: z's
        spectra, 2: pass differences), from the cached e^{-2πiν}."""
        return _component_psd_at(self._e[variant], self._num[(variant, c.order)] if c.order else 1.0, c)

    def fit(self, spec, mm, starts):
        best = None
        for th0 in starts:
            x0 = np.array(th0, float)
            res = self.minimize(x0, spec, mm, 400 * len(th0))
            if best is None or res.fun < best.fun:
                best = res
        return best

    def minimize(self, x0, spec, mm, maxiter: int, template=None, pos=None) -> optimize.OptimizeResult:
        """Nelder–Mead on :meth:`nll` (xatol 1e-5, fatol 1e-6) over θ, or over the elements
        ``pos`` of θ with the others at ``template``'s: :func:`_nelder_mead_kernel`, SciPy's
        algorithm compiled with the likelihood (``nelder_mead_scipy`` is the reference)."""
        x0 = np.asarray(x0, dtype=float)
        if template is None:
            template, pos = x0, np.arange(x0.size)
        ks = self._spec_arrays(spec)
        kargs = (ks[2], self.d_anom[mm], self._line_bins, self._f_hz, self.dt_s, ks[0], ks[1], self.phi_min,
                 PHI_MAX, ROLLOFF_MAX_S, *self._kernel_arrays)
        x, f, nit, nfev = _nelder_mead_kernel(x0, np.asarray(template, dtype=float), np.asarray(pos, dtype=np.int64),
                                              int(maxiter), 1e-5, 1e-6, kargs)
        return optimize.OptimizeResult(x=x, fun=float(f), nit=int(nit), nfev=int(nfev))

    def nelder_mead_scipy(self, x0, spec, mm, maxiter: int, template=None, pos=None) -> optimize.OptimizeResult:
        """:meth:`minimize` by ``scipy.optimize.minimize`` (the reference it is tested against)."""
        x0 = np.asarray(x0, dtype=float)
        if template is None:
            template, pos = x0, np.arange(x0.size)
        th = np.array(template, dtype=float)
        idx = np.asarray(pos, dtype=np.int64)

        def f(x):
            th[idx] = x
            return self.nll(th, spec, mm)

        return optimize.minimize(f, x0, method="Nelder-Mead", options={"maxiter": maxiter, "xatol": 1e-5, "fatol": 1e-6})

    def random_starts(self, spec) -> list:
        out = []
        for _ in range(self.n_starts):
            th0 = [np.log(1e-3) + self.rng.normal(0, 2)]
            for order, free_phi in spec:
                # start each component near the median level of the spectrum
                th0.append(np.log(self.level) - 3.0 * order + self.rng.normal(0, 2))
                if free_phi:
                    th0.append(self.rng.normal(1.0, 2.0))
            out.append(th0)
        return out

    def warm_starts(self, spec) -> list:
        """Starts from the families fitted so far: their components mapped onto this family's
        (same order; a missing component starts negligible, a missing φ at 0), so a richer
        family never ends worse than a simpler one it contains."""
        out = []
        for c in self.candidates:
            Q, comps = _unpack(c["_theta"], c["_spec"], self.phi_min)
            pool = list(comps)
            th = [np.log(Q)]
            for order, free_phi in spec:
                match = next((x for x in pool if x.order == order), None)
                if match is not None:
                    pool.remove(match)
                    th.append(np.log(max(match.weight, 1e-300)))
                    phi = match.phi
                else:
                    th.append(np.log(self.level) - 3.0 * order - 12.0)
                    phi = 0.0
                if free_phi:
                    u = (max(phi, self.phi_min) - self.phi_min) / (PHI_MAX - self.phi_min)
                    th.append(float(np.log(max(u, 1e-6) / max(1.0 - u, 1e-9))))
            if not pool:  # every fitted component was placed: a nested start
                out.append(th)
        return out

    def select(self, families, m: int, bic_margin: float, prefer_height: bool = False) -> dict:
        """Fit every family; the simplest within ``bic_margin`` of the best BIC.  A richer shape
        must be strongly supported (ΔBIC > 10), because its behaviour below the noise-dominated
        band — where the data cannot check it — decides how the smoother separates anomaly
        from noise.  ``prefer_height``: a pure velocity choice gives way to the simplest
        height-only family within the margin, when there is one (:func:`fit_noise_model`);
        and when velocity + height has the best BIC it is used: with heights only, the
        margin's simpler choice is not the cautious one below the band."""
        self.candidates = []
        for name, spec in families:
            best = self.fit(spec, m, self.random_starts(spec) + self.warm_starts(spec))
            gain = None
            if self.rolloff:
                best, gain = self.with_rolloff(best, spec, m, bic_margin)
            Q, comps = _unpack(best.x, spec, self.phi_min)
            k = len(best.x)
            self.candidates.append({
                "family": name, "nll": float(best.fun), "n_params": k,
                "bic": float(2.0 * best.fun + k * np.log(max(self.n_eff, 2.0))), "Q_mgal2": Q,
                # β and the BIC's gain from it (the screen's gain where the refit was not tried)
                "rolloff_s": self.rolloff_of(best.x, spec), "rolloff_bic_gain": gain,
                "components": [{"order": c.order, "phi": c.phi, "weight_mgal2": c.weight} for c in comps],
                "_theta": best.x, "_spec": spec})
        best_bic = min(c["bic"] for c in self.candidates)
        near = [c for c in sorted(self.candidates, key=lambda c: c["n_params"]) if c["bic"] <= best_bic + bic_margin]
        self.height_replaced = self.best_fit_over = None
        chosen = near[0]
        if prefer_height and all(order == 1 for order, _ in chosen["_spec"]):
            heights = [c for c in near if all(order == 2 for order, _ in c["_spec"])]
            if heights:
                self.height_replaced = chosen["family"]
                chosen = heights[0]
        chosen = self._no_bare_white_height(chosen)
        top = min(self.candidates, key=lambda c: c["bic"])
        if prefer_height and top["family"] == "velocity + height" and chosen["family"] != top["family"]:
            # Heights only: the margin's simpler choice puts less noise below the band than
            # velocity + height (the f² of a correlated height error carried down), which fits best.
            self.best_fit_over = chosen
            return top
        return chosen

    def _no_bare_white_height(self, chosen: dict) -> dict:
        """A bare white height error is replaced by the family that nests it, white height plus a
        random-walk height part (``velocity + height``), whenever that fits at least as well.

        Of all the families, white height puts the least noise below the fitted band: its
        acceleration spectrum falls as f⁴ all the way down.  GNSS height errors are correlated
        over tens of seconds to minutes (multipath, troposphere, orbits), and that part shows
        in z as an f² slope that the anomaly hides at the frequencies where it matters; when
        the fitted band is dominated by the white part, the BIC margin cannot see it and the
        simplest family would call the anomaly band noise-free.  The nesting family fits the
        level of the f² part (zero where the data say so), so the spectra decide it, not the
        choice of family."""
        self.white_height_bare = self.white_height_nest = None
        if chosen["family"] != "white height":
            return chosen
        nest = [c for c in self.candidates if c["family"] == "velocity + height"]
        if nest and nest[0]["nll"] <= chosen["nll"] + 1e-6 * abs(chosen["nll"]):
            self.white_height_bare, self.white_height_nest = chosen, nest[0]
            return nest[0]
        return chosen

    def hidden_corners(self, chosen: dict, m: int) -> list:
        """Corners (Hz) of the chosen family's AR components that lie between the lowest fitted
        frequency and twice the anomaly/noise crossover, and those of its *height* components
        (order 2) anywhere inside the fitted band.

        Below a height corner the model's z noise falls as f⁴.  A GNSS height error correlated
        over 20–120 s has its corner below the data; one fitted inside the band is the shape of
        something else (a response mismatch rising above 0.06 Hz, the anomaly's tail), and it
        takes the noise out of the band just above the anomaly: random layout 410 (white
        velocity errors, a 1 Hz platform gravimeter) had a coloured height with its corner at
        0.044 Hz, above twice the anomaly/noise crossover, and the estimate let noise through at 1.82x the FIR
        100 s error; moved, 0.87x."""
        Qc, comps = _unpack(chosen["_theta"], chosen["_spec"], self.phi_min)
        f_low = float(np.min(self.sp.f_hz))
        fg = np.geomspace(f_low, float(np.max(self.sp.f_hz)), 400)
        sn = NoiseModel(tuple(comps), self.dt_s, "x").psd(fg)
        above = np.flatnonzero(anomaly_psd(fg, Qc, m, self.dt_s, self.rolloff_of(chosen["_theta"], chosen["_spec"]))
                               >= sn)
        f_x = float(fg[above[-1]]) if above.size else f_low
        f_high = float(np.max(self.sp.f_hz))
        return [k for k, c in ((knee_hz(c.phi, self.dt_s), c) for c in comps if c.phi > 0)
                if f_low < k and (k < 2.0 * f_x or (c.order == 2 and k < f_high))]

    @staticmethod
    def rolloff_of(theta, spec) -> float:
        """β (s) of a fit's θ; 0 where the fit has no roll-off."""
        return rolloff_s(theta) if len(theta) > _n_base(spec) else 0.0

    def with_rolloff(self, best, spec, m: int, bic_margin: float):
        """The family refitted with the anomaly's roll-off β free, from its fit without it (β
        from 0 to 300 s); kept where it lowers the BIC by more than ``bic_margin`` (one
        parameter more must be strongly supported, like a richer family).

        A field seen from a height d above its sources falls as ``exp(−4π d k)`` in
        wavenumber, faster than any power law, so the random walk's ``f^{−2m}`` fitted where
        the anomaly rules over-states it just above the crossover, and the noise fitted beside
        it comes out too low there — where the smoother must cut (an anomaly falling as
        e^{−150 f} over Gauss–Markov velocity noise: 0.2–0.55× the true noise at 0.01–0.03 Hz
        without β, the right family and 0.94–1.4× with it)."""
        penalty = float(np.log(max(self.n_eff, 2.0)))
        # a screen first: Q and β alone, the noise as fitted; where that lowers the BIC at all
        # the whole family is refitted with β (most surveys need no roll-off: one cheap search)
        rest = np.asarray(best.x[1:], dtype=float)
        template = np.concatenate([[best.x[0]], rest, [0.0]])
        pos = np.array([0, template.size - 1])
        screen = None
        for b in (10.0, 60.0, 300.0):
            r = self.minimize(np.array([best.x[0], _rolloff_logit(b)]), spec, m, 400, template, pos)
            if screen is None or r.fun < screen.fun:
                screen = r
        if 2.0 * (best.fun - screen.fun) <= penalty:
            return best, float(2.0 * (best.fun - screen.fun) - penalty)
        starts = [np.append(best.x, _rolloff_logit(b)) for b in (1e-3, 10.0, 60.0, 300.0)]
        starts.append(np.concatenate([[screen.x[0]], rest, [screen.x[1]]]))
        res = self.fit(spec, m, starts)
        gain = float(2.0 * (best.fun - res.fun) - penalty)
        return (res if gain > bic_margin else best), gain

    def orders(self, chosen: dict, m: int) -> dict:
        """The chosen family refitted with m = 1, 2, 3 (from the m solution; equal parameter
        counts): {m: (negative log-likelihood, θ)}."""
        out = {m: (chosen["nll"], chosen["_theta"])}
        for mm in (1, 2, 3):
            if mm not in out:
                th = chosen["_theta"]
                starts = [th] + [np.concatenate([[th[0] + d], th[1:]]) for d in (-4.0, 4.0)]
                res = self.fit(chosen["_spec"], mm, starts)
                out[mm] = (float(res.fun), res.x)
        return out
