"""In-flight gravimeter calibration and its accuracy planner (seed 001 §3–4).

Model
-----
Gravimeter (seed 001 eq. 4)::

    τ·ḟ' + k·f' = f_g + δf_T + δf,      f_g = f_3 − (α1+δ1)·f_y + (α2+δ2)·f_x

``f'`` the RAW gravimeter output (m/s², up), ``f_3`` the true vertical specific
force, ``f_x = f_z1``, ``f_y = f_z2`` the horizontal specific force (m/s²),
``α1, α2`` the platform levelling errors known from the INS (rad, optional),
``δ1, δ2`` the unknown gravimeter misalignments (rad), ``δf_T`` the drift and
``δf`` white instrument noise.

What ``z`` is for calibration
-----------------------------
``z`` is the SPEC §1 anomaly measurement formed with the **raw** interval mean
``f̄'_k`` (lag and scale *not* undone), in m/s²::

    z_k = f̄'_k − (V_k − V_{k−1})/Δt − γ_k + E_k

Since the SPEC anomaly is ``δg = f_3 − V̇ − γ + E``, eliminating ``f_3`` with the
gravimeter model gives, exactly (interval means on both sides)::

    z = −τ·ḟ' + (1 − k)·f' − δ1·f_y + δ2·f_x + α-terms + δg − δf_T − δf + r_GNSS
      = X_regᵀ c + δg + r,      c = (ḟ', f', −f_y, f_x),  X_reg = (−τ, 1−k, δ1, δ2)

i.e. seed 001 eq. (10) with the SPEC's ``c`` and the sign convention of eq. (4)
for ``δ1, δ2``; the paper's eq. (10) prints ``X = (τ, k, δ1, δ2)``, which is the
same regression up to the signs of the first two components.

The regression is done on the **deviation from a nominal model**
``(τ0, k0, δ1₀, δ2₀)`` (δ's default 0):
``y = z + τ0·ḟ' + (k0 − 1)·f' + (α1+δ1₀)·f_y − (α2+δ2₀)·f_x`` is regressed on
the columns ``(−ḟ', −f', −f_y, f_x)`` to give ``(τ − τ0, k − k0, δ1 − δ1₀,
δ2 − δ2₀)``.  For jointly
estimated parameters the result does not depend on the nominal values (the
model is linear); parameters *not* estimated are held at their nominal values.
``f'`` is ≈ 9.8 m/s²: its mean is confounded with the constant drift (and with
the anomaly's mean), so ``k`` comes only from the *variation* of ``f'`` in the
manoeuvres; an absolute scale needs a base tie, not in-flight calibration.

Estimator (seed 001 eqs. 13–14)
-------------------------------
Frequency-domain weighted least squares on the DFT of the record::

    [Σ_ω ĉ ĉ* Γ] X = Σ_ω ĉ ẑ* Γ,   Γ(ω) = 1/(S_δg(ω) + S_r(ω)),   D_XX = [Σ_ω ĉ ĉ* Γ]⁻¹

Spectra are two-sided densities in (m/s²)² per rad/s, ``∫ S dω = variance``
(seed 001 convention ``S(ω) = (1/2π) ∫ C(t) e^{−iωt} dt``); white noise of
level ``d`` has ``S = d/2π`` and per-sample variance ``d/Δt``:

* anomaly (first-order approximation model): ``S_δg = d_δg/(2π ω²)``,
  ``d_δg = 6·V0·σ²/r_c`` (a random walk, increment variance ``d_δg·Δt``);
* Doppler GNSS: ``S_r = ω²·d_V/2π + d_f/2π`` (``d_V`` in (m/s)²·s);
* phase GNSS: ``S_r = ω⁴·d_h/2π + d_f/2π`` (``d_h`` in m²·s).

With ``discrete=True`` (default) ``ω`` in these spectra is replaced by
``D(ω) = 2 sin(ωΔt/2)/Δt``, which makes them exact for the GNSS-rate model
(velocity first differences, height second differences, random-walk anomaly).

With the DFT normalisation used here, the sum over DFT bins equals the time
domain generalised least squares with a circulant noise covariance of
eigenvalues ``2π S(ω_j)/Δt``.  What makes that exact enough on a finite record:

* the DC bin is dropped (a constant drift / anomaly mean is estimated
  implicitly), and a polynomial drift of degree ``drift_degree ≥ 1`` is
  estimated jointly: the linear term also absorbs the end-to-end ramp of the
  random-walk anomaly, whose remainder (a Brownian bridge) has exactly
  uncorrelated DFT coefficients with spectrum ``d/(2π ω²)``;
* the wrap-around of the differenced GNSS noise (first sample uses ``V_{−1}``)
  is one (Doppler) or two (phase) unknown impulses at the start of the record,
  estimated jointly as nuisance parameters.

Planner (seed 001 eqs. 18–19)
-----------------------------
:func:`plan_calibration` evaluates the expected information matrix of eq. (18)
for a line-spectrum manoeuvre on the same DFT grid (the Fejér kernel of the
finite record), and also the asymptotic closed form ``D = 2π/(L·∫S_cΓ)``
(= ``π/T`` for the paper's record ``[−T, T]`` of length ``L = 2T``) and the
closed forms of Tables 1–2 as printed (``4π/T``).

Units: time s, accelerations m/s², angles rad; spectra inputs as named.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np

MGAL_MS2 = 1e-5            # 1 mGal in m/s²
G_E_MS2 = 9.7803            # seed 001 g_e (m/s²), for the turn rule ω* = g_e/V0

PARAM_NAMES = ("tau", "k", "d1", "d2")

# 7-point (6th-order) central first-derivative stencil.  Applied to GNSS-rate
# interval means f̄'_k it gives the interval mean of ḟ' (for a band-limited f',
# the derivative of the interval-mean sequence equals the interval mean of the
# derivative); relative error ≈ (ωΔt)⁶/140.
_STENCIL = np.array([-1.0 / 60, 3.0 / 20, -3.0 / 4, 0.0, 3.0 / 4, -3.0 / 20, 1.0 / 60])
_HALF = 3


@dataclass(frozen=True)
class CalibrationSpectra:
    """Noise and anomaly spectra for calibration (seed 001 §3–4).

    Parameters
    ----------
    d_f_mgal2_s : float
        Gravimeter white-noise level ``d_f`` (mGal²·s); ``S_δf = d_f/2π``.
        Per GNSS epoch the interval-mean noise variance is ``d_f/Δt``.
    d_dg_mgal2_s : float
        Anomaly level ``d = 6·V0·σ²/r_c`` (mGal²/s), ``S_δg = d/(2π ω²)``; see
        :func:`anomaly_level_mgal2_s`.
    gnss : {'doppler', 'phase'}
        Doppler: ``z`` from velocity differences, ``S_r = ω² d_V/2π + S_δf``;
        phase: ``z`` from height second differences, ``S_r = ω⁴ d_h/2π + S_δf``.
    d_v_m2_s : float
        GNSS vertical-velocity white-noise level ``d_V`` ((m/s)²·s); with a
        per-epoch variance ``R`` (cm/s)² at step Δt: ``d_V = R·1e-4·Δt``.
    d_h_m2_s : float
        GNSS height white-noise level ``d_h`` (m²·s).
    discrete : bool
        Use ``D(ω) = 2 sin(ωΔt/2)/Δt`` in place of ``ω`` (exact for the
        GNSS-rate difference model).  False: the paper's continuous forms.
    """

    d_f_mgal2_s: float
    d_dg_mgal2_s: float
    gnss: Literal["doppler", "phase"] = "doppler"
    d_v_m2_s: float = 0.0
    d_h_m2_s: float = 0.0
    discrete: bool = True

    def __post_init__(self):
        if self.gnss not in ("doppler", "phase"):
            raise ValueError(f"gnss must be 'doppler' or 'phase', got {self.gnss!r}")
        for name in ("d_f_mgal2_s", "d_dg_mgal2_s", "d_v_m2_s", "d_h_m2_s"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        gnss_level = self.d_v_m2_s if self.gnss == "doppler" else self.d_h_m2_s
        if self.d_f_mgal2_s == 0 and gnss_level == 0:
            raise ValueError("spectra: at least one of the gravimeter or GNSS noise levels must be > 0")

    @classmethod
    def from_epoch_variances(cls, dt_s: float, *, f_var_mgal2: float, dg_step_var_mgal2: float,
                             gnss: str = "doppler", r_cm2s2: float = 0.0, h_var_m2: float = 0.0,
                             discrete: bool = True) -> CalibrationSpectra:
        """Spectra from per-GNSS-epoch variances (the pipeline's units).

        Parameters
        ----------
        dt_s : float
            GNSS step Δt (s).
        f_var_mgal2 : float
            Variance of the gravimeter interval-mean noise per epoch (mGal²): ``d_f = var·Δt``.
        dg_step_var_mgal2 : float
            Variance of the anomaly's increment per epoch (random walk, the m = 1
            ``Q`` in mGal² per GNSS step): ``d_δg = var/Δt``.
        r_cm2s2 : float
            GNSS vertical-velocity noise variance per epoch ((cm/s)², SPEC's R):
            ``d_V = R·1e-4·Δt``.
        h_var_m2 : float
            GNSS height noise variance per epoch (m²): ``d_h = var·Δt``.
        """
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be > 0, got {dt_s}")
        return cls(d_f_mgal2_s=f_var_mgal2 * dt_s, d_dg_mgal2_s=dg_step_var_mgal2 / dt_s,
                   gnss=gnss, d_v_m2_s=r_cm2s2 * 1e-4 * dt_s, d_h_m2_s=h_var_m2 * dt_s,
                   discrete=discrete)

    def density_ms2(self, omega_rad_s, dt_s: float) -> np.ndarray:
        """Total two-sided density ``S_δg + S_r`` ((m/s²)² per rad/s); ``inf`` at ω = 0
        when ``d_dg > 0``.

        Parameters
        ----------
        omega_rad_s : array_like
            Angular frequencies (rad/s).
        dt_s : float
            GNSS step (s), used when ``discrete``.
        """
        w = np.abs(np.asarray(omega_rad_s, dtype=float))
        if self.discrete:
            w = 2.0 * np.sin(0.5 * w * dt_s) / dt_s
        d_dg = self.d_dg_mgal2_s * MGAL_MS2 ** 2
        d_f = self.d_f_mgal2_s * MGAL_MS2 ** 2
        with np.errstate(divide="ignore"):
            s = np.where(w > 0, d_dg / np.where(w > 0, w, 1.0) ** 2, np.inf if d_dg > 0 else 0.0)
        s = s + d_f
        if self.gnss == "doppler":
            s = s + w ** 2 * self.d_v_m2_s
        else:
            s = s + w ** 4 * self.d_h_m2_s
        return s / (2.0 * np.pi)


def anomaly_level_mgal2_s(speed_ms: float, six_sigma2_over_rc_mgal2_km: float) -> float:
    """Seed 001 anomaly level ``d = 6·V0·σ²/r_c`` (mGal²/s).

    Parameters
    ----------
    speed_ms : float
        Ground speed V0 (m/s).
    six_sigma2_over_rc_mgal2_km : float
        ``6σ²/r_c`` (mGal²/km); the paper's tables use 0.1.
    """
    return float(six_sigma2_over_rc_mgal2_km) * float(speed_ms) / 1000.0


@dataclass
class CalibrationResult:
    """Result of :func:`calibrate`.

    Attributes
    ----------
    names : tuple of str
        Estimated parameters, a subset of ``('tau', 'k', 'd1', 'd2')`` in that order.
    x : ndarray, shape (p,)
        Estimates (τ in s, k dimensionless, δ1, δ2 in rad), absolute values.
    std : ndarray, shape (p,)
        Standard errors, ``sqrt(diag(cov))``.
    cov : ndarray, shape (p, p)
        ``D_XX`` (eq. 14), marginal over the nuisance parameters.
    tau_s, k, d1_rad, d2_rad : float
        The full parameter set to use downstream (fixed ones at nominal).
    drift_ms2 : ndarray
        Polynomial drift coefficients (degree 1..p, in normalised time
        ``(t − t_mid)/duration``, m/s²) – the constant is not estimated.
    chi2_per_dof : float
        Weighted residual power per degree of freedom; ≈ 1 when the spectra
        describe the data.  ≫ 1: noise underestimated, ``std`` too small.
    n_samples : int
        Samples used (record minus 3 at each end for the derivative).
    """

    names: tuple
    x: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    tau_s: float
    k: float
    d1_rad: float
    d2_rad: float
    drift_ms2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    chi2_per_dof: float = float("nan")
    n_samples: int = 0

    def as_dict(self) -> dict:
        """JSON-ready summary."""
        return {
            "names": list(self.names),
            "x": [float(v) for v in self.x],
            "std": [float(v) for v in self.std],
            "cov": [[float(v) for v in row] for row in self.cov],
            "tau_s": self.tau_s, "k": self.k, "d1_rad": self.d1_rad, "d2_rad": self.d2_rad,
            "chi2_per_dof": self.chi2_per_dof, "n_samples": self.n_samples,
        }


def _as_1d(name, a, n=None):
    arr = np.asarray(a, dtype=float)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    if n is not None and arr.size != n:
        raise ValueError(f"{name} has {arr.size} samples, expected {n} (same as t_s)")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf (cut the segment to finite data)")
    return arr


def _check_params(params) -> tuple:
    names = tuple(params)
    if not names:
        raise ValueError("params must name at least one of 'tau', 'k', 'd1', 'd2'")
    bad = [p for p in names if p not in PARAM_NAMES]
    if bad:
        raise ValueError(f"unknown calibration parameter(s) {bad}; choose from {PARAM_NAMES}")
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate calibration parameters in {names}")
    return tuple(p for p in PARAM_NAMES if p in names)


def derivative_of_interval_means(f_ms2, dt_s: float) -> np.ndarray:
    """Interval mean of ḟ from the interval means of f (7-point stencil), m/s³.

    Parameters
    ----------
    f_ms2 : ndarray, shape (n,)
        Interval means on a uniform grid of step ``dt_s``.
    dt_s : float

    Returns
    -------
    ndarray, shape (n − 6,)
        Values at samples ``3 … n−4``.
    """
    f = np.asarray(f_ms2, dtype=float)
    if f.size < _STENCIL.size:
        raise ValueError(f"need at least {_STENCIL.size} samples for the derivative, got {f.size}")
    return np.convolve(f, _STENCIL[::-1], mode="valid") / dt_s


def _weights(n: int, dt_s: float, spectra: CalibrationSpectra, fmax_hz: float | None = None) -> np.ndarray:
    """rfft-bin weights so that (1/n)·Σ_bins w·Re(A B*) = Aᵀ Σ_circ⁻¹ B; DC excluded; bins above
    ``fmax_hz`` (when given) get no weight."""
    omega = 2.0 * np.pi * np.fft.rfftfreq(n, dt_s)
    s = spectra.density_ms2(omega, dt_s)
    lam = 2.0 * np.pi * s / dt_s               # circulant eigenvalues, (m/s²)² per sample
    w = np.zeros_like(omega)
    ok = (omega > 0) & np.isfinite(lam) & (lam > 0)
    w[ok] = 1.0 / lam[ok]
    mult = np.full(omega.shape, 2.0)
    mult[0] = 1.0
    if n % 2 == 0:
        mult[-1] = 1.0
    w = w * mult / n
    w[0] = 0.0                                  # DC: constant drift / anomaly mean
    if fmax_hz is not None:
        w[omega > 2.0 * np.pi * float(fmax_hz)] = 0.0
    return w


def calibrate(t_s, z_ms2, f_raw_ms2, f_x_ms2=None, f_y_ms2=None, *, spectra: CalibrationSpectra,
              params: Sequence[str] = PARAM_NAMES, tau0_s: float = 0.0, k0: float = 1.0,
              d1_0_rad: float = 0.0, d2_0_rad: float = 0.0, fdot_raw_ms3=None, alpha1_rad=None, alpha2_rad=None, drift_degree: int = 1,
              min_samples: int = 64, fmax_hz: float | None = None) -> CalibrationResult:
    """Estimate gravimeter lag, scale and misalignments from a manoeuvre segment.

    Frequency-domain weighted least squares (seed 001 eqs. 13–14); see the
    module docstring for the exact model and the definition of ``z``.

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        GNSS epochs (s), uniformly spaced (relative jitter ≤ 1e-3), no gaps.
    z_ms2 : ndarray, shape (n,)
        ``f̄'_k − (V_k − V_{k−1})/Δt − γ_k + E_k`` (m/s²) with the RAW interval
        mean ``f̄'`` (no lag/scale correction); e.g.
        ``1e-5 * anomaly_measurement_mgal(fbar_raw, t, vu, gamma, eotvos)``
        without its first (NaN) epoch.
    f_raw_ms2 : ndarray, shape (n,)
        RAW gravimeter interval means ``f̄'_k`` over ``(t_{k−1}, t_k]`` (m/s²).
    f_x_ms2, f_y_ms2 : ndarray, shape (n,), optional
        Horizontal specific force interval means (m/s²), ``f_z1`` and ``f_z2``;
        required when ``'d2'`` resp. ``'d1'`` is estimated, otherwise used
        (if given) with the nominal misalignment 0 — i.e. ignored.
    spectra : CalibrationSpectra
        Anomaly and noise spectra (Γ = 1/(S_δg + S_r)).
    params : sequence of str
        Parameters to estimate jointly, subset of ``('tau', 'k', 'd1', 'd2')``;
        the others are held at ``(tau0_s, k0, d1_0_rad, d2_0_rad)``.
    tau0_s, k0 : float
        Nominal τ (s) and k (e.g. from ``survey.toml``).
    d1_0_rad, d2_0_rad : float
        Nominal misalignments (rad), e.g. from an earlier calibration; default 0.
    fdot_raw_ms3 : ndarray, shape (n,), optional
        Interval means of ḟ' (``(f'(t_k) − f'(t_{k−1}))/Δt``), e.g. from the
        integrated gravimeter series.  Default: 7-point stencil on ``f_raw_ms2``.
    alpha1_rad, alpha2_rad : ndarray, shape (n,), optional
        Known INS levelling errors α1, α2 (rad); default 0.
    drift_degree : int
        Degree (≥ 1) of the polynomial drift estimated jointly (constant implicit).
    min_samples : int
        Smallest accepted record after trimming (samples).
    fmax_hz : float, optional
        Use only frequencies up to this (Hz): above it the GNSS-derived acceleration of a
        1–2 Hz receiver or of differenced heights no longer follows the aircraft's.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    ValueError
        Bad shapes / NaN / non-uniform time, a segment too short, or a
        singular normal matrix (a parameter not excited by the manoeuvres).
    """
    names = _check_params(params)
    rec = _calibration_record(t_s, z_ms2, f_raw_ms2, f_x_ms2, f_y_ms2, fdot_raw_ms3, alpha1_rad, alpha2_rad,
                              names=names, gnss=spectra.gnss, drift_degree=drift_degree, min_samples=min_samples,
                              nominal=(tau0_s, k0, d1_0_rad, d2_0_rad))
    y, A = _deviation_regression(rec, names, tau0_s, k0, d1_0_rad, d2_0_rad, drift_degree, spectra.gnss)
    w = _weights(rec.n, rec.dt, spectra, fmax_hz)
    Ah = np.fft.rfft(A, axis=1)
    yh = np.fft.rfft(y)
    M = np.real((Ah * w) @ Ah.conj().T)
    b = np.real((Ah * w) @ yh.conj())
    _check_excited(M, A, names)
    covfull = _normal_inverse(M, names)
    p = len(names)
    theta = covfull @ b
    resid = yh - theta @ Ah
    dof = rec.n - 1 - A.shape[0]
    chi2 = float(np.sum(w * np.abs(resid) ** 2)) / max(dof, 1)
    cov = covfull[:p, :p]
    cov = 0.5 * (cov + cov.T)
    nominal = {"tau": float(tau0_s), "k": float(k0), "d1": float(d1_0_rad), "d2": float(d2_0_rad)}
    full = dict(nominal)
    for i, name in enumerate(names):
        full[name] = nominal[name] + float(theta[i])
    x = np.array([full[nm] for nm in names])
    return CalibrationResult(names=names, x=x, std=np.sqrt(np.diag(cov)), cov=cov,
                             tau_s=full["tau"], k=full["k"], d1_rad=full["d1"],
                             d2_rad=full["d2"], drift_ms2=theta[p:p + drift_degree].copy(),
                             chi2_per_dof=chi2, n_samples=rec.n)


@dataclass
class _CalibrationRecord:
    """A checked calibration segment, trimmed by ``_HALF`` samples at each end (the stencil)."""

    t: np.ndarray          # epochs (s)
    z: np.ndarray          # anomaly measurement with the raw mean (m/s²)
    f: np.ndarray          # raw interval means f̄' (m/s²)
    fdot: np.ndarray       # interval means of ḟ' (m/s³)
    fx: np.ndarray         # horizontal specific force (m/s²), zeros when not given
    fy: np.ndarray
    a1: np.ndarray         # INS levelling errors (rad), zeros when not given
    a2: np.ndarray
    dt: float              # GNSS step (s)

    @property
    def n(self) -> int:
        return int(self.t.size)


def _calibration_record(t_s, z_ms2, f_raw_ms2, f_x_ms2, f_y_ms2, fdot_raw_ms3, alpha1_rad, alpha2_rad, *,
                        names: tuple, gnss: str, drift_degree: int, min_samples: int,
                        nominal: tuple) -> _CalibrationRecord:
    """The inputs of :func:`calibrate` checked (shapes, finite, uniform time, length, channels
    the parameters need, finite ``nominal`` (τ0, k0, δ1₀, δ2₀)) and trimmed to where the
    derivative of the interval means exists."""
    t = _as_1d("t_s", t_s)
    n_all = t.size
    z = _as_1d("z_ms2", z_ms2, n_all)
    f = _as_1d("f_raw_ms2", f_raw_ms2, n_all)
    if not isinstance(drift_degree, (int, np.integer)) or drift_degree < 1:
        raise ValueError(f"drift_degree must be an integer >= 1 (the linear term absorbs the "
                         f"random-walk anomaly's end ramp), got {drift_degree!r}")
    n_nuis_min = drift_degree + (1 if gnss == "doppler" else 2)
    need = max(int(min_samples), 2 * (len(names) + n_nuis_min)) + 2 * _HALF
    if n_all < need:
        raise ValueError(f"calibration segment too short: {n_all} samples, need at least {need} "
                         f"(min_samples={min_samples} after trimming {_HALF} at each end)")
    dts = np.diff(t)
    dt = float(np.median(dts))
    if not dt > 0 or np.max(np.abs(dts - dt)) > 1e-3 * dt:
        raise ValueError("t_s must be strictly increasing and uniformly spaced (no gaps); "
                         f"step range [{dts.min():.6g}, {dts.max():.6g}] s")
    fx = np.zeros(n_all) if f_x_ms2 is None else _as_1d("f_x_ms2", f_x_ms2, n_all)
    fy = np.zeros(n_all) if f_y_ms2 is None else _as_1d("f_y_ms2", f_y_ms2, n_all)
    if "d1" in names and f_y_ms2 is None:
        raise ValueError("estimating 'd1' needs f_y_ms2 (f_z2)")
    if "d2" in names and f_x_ms2 is None:
        raise ValueError("estimating 'd2' needs f_x_ms2 (f_z1)")
    a1 = np.zeros(n_all) if alpha1_rad is None else _as_1d("alpha1_rad", alpha1_rad, n_all)
    a2 = np.zeros(n_all) if alpha2_rad is None else _as_1d("alpha2_rad", alpha2_rad, n_all)
    if not all(np.isfinite(v) for v in nominal):
        raise ValueError("tau0_s, k0, d1_0_rad, d2_0_rad must be finite")
    sl = slice(_HALF, n_all - _HALF)
    if fdot_raw_ms3 is None:
        fdot = derivative_of_interval_means(f, dt)
    else:
        fdot = _as_1d("fdot_raw_ms3", fdot_raw_ms3, n_all)[sl]
    return _CalibrationRecord(t[sl], z[sl], f[sl], fdot, fx[sl], fy[sl], a1[sl], a2[sl], dt)


def _deviation_regression(rec: _CalibrationRecord, names: tuple, tau0_s: float, k0: float, d1_0_rad: float,
                          d2_0_rad: float, drift_degree: int, gnss: str):
    """``(y, A)``: ``y = z − (nominal-model terms)`` and the regressors, rows = the parameters'
    columns ``(−ḟ', −f', −f_y, f_x)`` in ``names`` order, the drift ``u^1..u^degree`` in
    normalised time, and one (Doppler) or two (phase) start impulses."""
    t, n = rec.t, rec.n
    fc = rec.f - rec.f.mean()                    # the mean goes to the (implicit) constant
    y = (rec.z + tau0_s * rec.fdot + (k0 - 1.0) * fc + (rec.a1 + d1_0_rad) * rec.fy
         - (rec.a2 + d2_0_rad) * rec.fx)
    cols = {"tau": -rec.fdot, "k": -fc, "d1": -rec.fy, "d2": rec.fx}
    A = [cols[name] for name in names]
    u = (t - 0.5 * (t[0] + t[-1])) / (t[-1] - t[0])
    for power in range(1, drift_degree + 1):
        A.append(u ** power)
    n_imp = 1 if gnss == "doppler" else 2
    for i in range(n_imp):
        e = np.zeros(n)
        e[i] = 1.0
        A.append(e)
    return y, np.array(A)                        # A: (m, n)


def _check_excited(M: np.ndarray, A: np.ndarray, names: tuple) -> None:
    """A parameter whose regressor has no variation (beyond rounding) carries no information."""
    p = len(names)
    diag = np.diag(M)[:p]
    spread = [float(np.std(A[i])) for i in range(p)]
    dead = [names[i] for i in range(p)
            if not diag[i] > 0 or not np.isfinite(diag[i]) or spread[i] <= 1e-10
            or spread[i] <= 1e-9 * float(np.max(np.abs(A[i])))]
    if dead:
        raise ValueError(f"parameter(s) {dead} not excited: their regressor has no variation "
                         "in the segment (no manoeuvre on that channel)")


def _normal_inverse(M: np.ndarray, names: tuple) -> np.ndarray:
    """``M⁻¹`` through the correlation matrix, refused when a column has no weight or the
    parameters cannot be separated (smallest eigenvalue of the correlation < 1e-10)."""
    p = len(names)
    s = np.sqrt(np.diag(M))
    if not np.all(s > 0):
        raise ValueError("singular normal matrix: a drift/nuisance regressor has no weight "
                         "(segment too short for the spectra?)")
    C = M / np.outer(s, s)
    ev, evec = np.linalg.eigh(C)
    if ev[0] < 1e-10:
        v = np.abs(evec[:p, 0])
        involved = [names[i] for i in np.argsort(-v, kind="stable") if v[i] > 0.2]
        cond = ev[-1] / max(ev[0], 1e-300)
        raise ValueError(f"singular normal matrix (condition {cond:.1e}): parameters {involved or list(names)} "
                         "cannot be separated by this segment's manoeuvres; estimate fewer parameters or "
                         "use a segment with independent manoeuvres on each channel")
    Ci = np.linalg.inv(C)
    return Ci / np.outer(s, s)


def corrected_specific_force_ms2(fbar_corrected_ms2, f_x_ms2, f_y_ms2, d1_rad: float,
                                 d2_rad: float, alpha1_rad=0.0, alpha2_rad=0.0) -> np.ndarray:
    """Vertical specific force ``f_3`` from the lag/scale-corrected gravimeter mean.

    ``f_3 = (τ ḟ' + k f') + (α1+δ1)·f_y − (α2+δ2)·f_x`` (drift and noise aside), where
    ``fbar_corrected_ms2 = τ ḟ' + k f'`` is e.g.
    ``app.core.gravimeter.interval_means(series, t, tau_s=res.tau_s, scale=res.k)``.

    Parameters
    ----------
    fbar_corrected_ms2, f_x_ms2, f_y_ms2 : ndarray, shape (n,)
        m/s².
    d1_rad, d2_rad : float
        Misalignments from :func:`calibrate` (rad).
    alpha1_rad, alpha2_rad : float or ndarray
        INS levelling errors (rad).

    Returns
    -------
    ndarray, shape (n,)
    """
    f = np.asarray(fbar_corrected_ms2, dtype=float)
    return (f + (np.asarray(alpha1_rad) + d1_rad) * np.asarray(f_y_ms2, dtype=float)
            - (np.asarray(alpha2_rad) + d2_rad) * np.asarray(f_x_ms2, dtype=float))


# --------------------------------------------------------------------------- planner

def _line_info(n: int, dt_s: float, w: np.ndarray, omega0: float) -> float:
    """(1/n)·Σ_bins w·E|Â|² / P for a random-phase sinusoid of power P at ω0."""
    omega = 2.0 * np.pi * np.fft.rfftfreq(n, dt_s)

    def fejer(x):
        # |Σ_{m<n} e^{−i x m Δt}|² = sin²(n x Δt/2)/sin²(x Δt/2)
        h = 0.5 * x * dt_s
        sh = np.sin(h)
        small = np.abs(sh) < 1e-12
        out = np.where(small, float(n) ** 2, np.sin(n * h) ** 2 / np.where(small, 1.0, sh) ** 2)
        return out

    e2 = 0.5 * (fejer(omega - omega0) + fejer(omega + omega0))   # E|Â|²/P
    return float(np.sum(w * e2))


def plan_calibration(duration_s: float, *, speed_ms: float | None = None,
                     omega_rad_s: float | None = None, omega_x_rad_s: float | None = None,
                     omega_y_rad_s: float | None = None, power_z_ms2sq: float = 3.0,
                     power_x_ms2sq: float = 3.0, power_y_ms2sq: float = 3.0,
                     power_z_is_input: bool = False, gnss: str = "doppler",
                     d_v_m2_s: float = 0.25e-4, d_h_m2_s: float = 4e-4, d_f_mgal2_s: float = 25.0,
                     six_sigma2_over_rc_mgal2_km: float = 0.1, d_dg_mgal2_s: float | None = None,
                     tau_s: float = 2.0, k: float = 1.0, params: Sequence[str] = PARAM_NAMES,
                     joint: bool = True, dt_s: float = 0.1, discrete: bool = True) -> dict:
    """Standard errors of in-flight calibration for a planned manoeuvre segment.

    Each channel is a sinusoid of random phase (line spectrum, seed 001 §4):
    vertical output ``f'`` at ``ω`` with power ``power_z`` (so ``ḟ'`` has power
    ``ω²·power_z``), horizontal ``f_x``, ``f_y`` at ``ω_x``, ``ω_y`` with their
    powers, mutually independent.  ``D_XX`` is the inverse of the expected
    information of eq. (18) on the record's DFT grid (Fejér kernel), i.e. what
    :func:`calibrate` reports for such a segment (nuisance drift/impulse terms
    neglected, they cost O(1/n)).

    Parameters
    ----------
    duration_s : float
        Record length L (s).
    speed_ms : float, optional
        V0 (m/s): gives ``ω = g_e/V0`` if ``omega_rad_s`` is None and the
        anomaly level ``d = 6 V0 σ²/r_c`` if ``d_dg_mgal2_s`` is None.
    omega_rad_s : float, optional
        Manoeuvre frequency ω* (rad/s) of the vertical channel.
    omega_x_rad_s, omega_y_rad_s : float, optional
        Frequencies of the horizontal channels (default ω*).  With all channels at
        one frequency the joint 4-parameter problem is degenerate per realisation
        (4 sinusoids of one frequency span a 2-D space); see ``degenerate_joint``.
    power_z_ms2sq, power_x_ms2sq, power_y_ms2sq : float
        Power (variance, (m/s²)²) of ``f'``, ``f_x``, ``f_y`` — the paper's A_c.
    power_z_is_input : bool
        If True ``power_z`` is the power of the true vertical acceleration; the
        output power is then ``power_z/(k² + τ²ω²)``.
    gnss : {'doppler', 'phase'}
    d_v_m2_s, d_h_m2_s, d_f_mgal2_s : float
        Noise levels (see :class:`CalibrationSpectra`); defaults are seed 001's
        ``(0.5 cm/s)²·s``, ``(2 cm)²·s``, ``(5 mGal)²·s``.
    six_sigma2_over_rc_mgal2_km : float
        Anomaly ``6σ²/r_c`` (mGal²/km), used with ``speed_ms``.
    d_dg_mgal2_s : float, optional
        Anomaly level d directly (mGal²/s).
    tau_s, k : float
        Nominal lag and scale (used by ``power_z_is_input`` and the printed k formula).
    params : sequence of str
        Parameters estimated.
    joint : bool
        ``std`` is the joint standard error (True) or one-at-a-time (False).
    dt_s : float
        GNSS step (s).
    discrete : bool
        Discrete-time spectra (as in :func:`calibrate`).

    Returns
    -------
    dict
        ``names``, ``std`` (joint or single, per ``joint``), ``std_joint``,
        ``std_single`` (others known), ``std_asymptotic_single`` (``2π/(L P Γ(ω))``,
        eq. 19 integrated, = ``π/T`` with ``L = 2T``), ``std_paper_formula_single``
        (Tables 1–2 closed forms as printed, ``4π/T`` with ``T = L``), ``cov``
        (joint ``D_XX``), ``omega_rad_s``, ``d_dg_mgal2_s``, ``degenerate_joint``.
    """
    names = _check_params(params)
    if not (np.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    if not (np.isfinite(dt_s) and 0 < dt_s < duration_s):
        raise ValueError(f"dt_s must be in (0, duration_s), got {dt_s}")
    if omega_rad_s is None:
        if speed_ms is None or not speed_ms > 0:
            raise ValueError("give omega_rad_s or a positive speed_ms (turn rule ω* = g_e/V0)")
        omega_rad_s = G_E_MS2 / speed_ms
    if d_dg_mgal2_s is None:
        if speed_ms is None or not speed_ms > 0:
            raise ValueError("give d_dg_mgal2_s or a positive speed_ms for d = 6 V0 σ²/r_c")
        d_dg_mgal2_s = anomaly_level_mgal2_s(speed_ms, six_sigma2_over_rc_mgal2_km)
    ch = _planned_channels(names, dt_s, omega_rad_s, omega_x_rad_s, omega_y_rad_s, power_z_ms2sq, power_x_ms2sq,
                           power_y_ms2sq, power_z_is_input, tau_s, k)
    spectra = CalibrationSpectra(d_f_mgal2_s=d_f_mgal2_s, d_dg_mgal2_s=d_dg_mgal2_s, gnss=gnss,
                                 d_v_m2_s=d_v_m2_s, d_h_m2_s=d_h_m2_s, discrete=discrete)
    M = _expected_information(names, ch, spectra, duration_s, dt_s)
    cov = np.linalg.inv(M)
    std_joint = np.sqrt(np.diag(cov))
    std_single = 1.0 / np.sqrt(np.diag(M))

    def gamma(om):
        return 1.0 / spectra.density_ms2(np.array([om]), dt_s)[0]

    std_asym = np.array([np.sqrt(2 * np.pi / (duration_s * ch.powers[nm] * gamma(ch.freqs[nm])))
                         for nm in names])
    std_printed = np.array([_printed_std(nm, ch, duration_s, gnss, d_v_m2_s, d_h_m2_s, d_f_mgal2_s, d_dg_mgal2_s,
                                         power_x_ms2sq, power_y_ms2sq, tau_s) for nm in names])
    shared = {}
    for nm in names:
        shared.setdefault(ch.freqs[nm], []).append(nm)
    # per realisation, one frequency line carries 2 degrees of freedom (sin, cos)
    degenerate = bool(joint and any(len(v) > 2 for v in shared.values()))
    return {
        "names": list(names),
        "std": std_joint if joint else std_single,
        "std_joint": std_joint,
        "std_single": std_single,
        "std_asymptotic_single": std_asym,
        "std_paper_formula_single": std_printed,
        "cov": cov,
        "omega_rad_s": ch.wz,
        "omega_x_rad_s": ch.wx,
        "omega_y_rad_s": ch.wy,
        "d_dg_mgal2_s": float(d_dg_mgal2_s),
        "degenerate_joint": degenerate,
    }


class _PlannedChannels(NamedTuple):
    """Manoeuvre line of each parameter's regressor in a planned segment."""

    wz: float              # vertical channel frequency (rad/s)
    wx: float              # f_x channel
    wy: float              # f_y channel
    pz: float              # power of the gravimeter output f' ((m/s²)²)
    powers: dict           # parameter -> power of its regressor
    freqs: dict            # parameter -> frequency of its regressor (rad/s)


def _planned_channels(names: tuple, dt_s: float, omega_rad_s: float, omega_x_rad_s, omega_y_rad_s,
                      power_z_ms2sq: float, power_x_ms2sq: float, power_y_ms2sq: float, power_z_is_input: bool,
                      tau_s: float, k: float) -> _PlannedChannels:
    """Frequencies (checked below Nyquist) and regressor powers: ``ḟ'`` has ``ω²`` times the power
    of ``f'``; with ``power_z_is_input`` the output power is ``power_z/(k² + τ²ω²)``."""
    wz = float(omega_rad_s)
    wx = wz if omega_x_rad_s is None else float(omega_x_rad_s)
    wy = wz if omega_y_rad_s is None else float(omega_y_rad_s)
    nyq = np.pi / dt_s
    for nm, om in (("omega", wz), ("omega_x", wx), ("omega_y", wy)):
        if not (0 < om < nyq):
            raise ValueError(f"{nm} must be in (0, π/dt) = (0, {nyq:.4g}) rad/s, got {om}")
    pz = float(power_z_ms2sq)
    if power_z_is_input:
        pz = pz / (k ** 2 + (tau_s * wz) ** 2)
    powers = {"tau": pz * wz ** 2, "k": pz, "d1": float(power_y_ms2sq), "d2": float(power_x_ms2sq)}
    freqs = {"tau": wz, "k": wz, "d1": wy, "d2": wx}
    for nm in names:
        if not powers[nm] > 0:
            raise ValueError(f"parameter {nm!r} has no manoeuvre power: the normal matrix is singular")
    return _PlannedChannels(wz, wx, wy, pz, powers, freqs)


def _expected_information(names: tuple, ch: _PlannedChannels, spectra: CalibrationSpectra, duration_s: float,
                          dt_s: float) -> np.ndarray:
    """Expected normal matrix of eq. (18) on the record's DFT grid (Fejér kernel).

    The cross terms vanish in expectation: ``ḟ'`` and ``f'`` are in quadrature
    (``Re E[ĉ_τ ĉ_k*] = 0``) and independent channels have zero cross-spectra, so it is diagonal.
    """
    n = int(round(duration_s / dt_s))
    w = _weights(n, dt_s, spectra)
    info_unit = {om: _line_info(n, dt_s, w, om) for om in set(ch.freqs[nm] for nm in names)}
    p = len(names)
    M = np.zeros((p, p))
    for i, nm in enumerate(names):
        M[i, i] = ch.powers[nm] * info_unit[ch.freqs[nm]]
    return M


def _printed_std(nm: str, ch: _PlannedChannels, duration_s: float, gnss: str, d_v_m2_s: float, d_h_m2_s: float,
                 d_f_mgal2_s: float, d_dg_mgal2_s: float, power_x_ms2sq: float, power_y_ms2sq: float,
                 tau_s: float) -> float:
    """Seed 001 Tables 1–2 closed form as printed (continuous ω, T = duration, A_c = power of
    each channel) for one parameter."""
    d = d_dg_mgal2_s * MGAL_MS2 ** 2
    d_f = d_f_mgal2_s * MGAL_MS2 ** 2
    T = duration_s
    om = ch.freqs[nm]
    num = (om ** 4 * d_v_m2_s if gnss == "doppler" else om ** 6 * d_h_m2_s) + om ** 2 * d_f + d
    a_c = {"tau": ch.pz, "k": ch.pz, "d1": power_y_ms2sq, "d2": power_x_ms2sq}[nm]
    den = T * a_c * om ** 2
    if nm == "tau":
        den = T * a_c * om ** 4
    elif nm == "k":
        den = den * (1 + tau_s ** 2 * om ** 2)
    return np.sqrt(2 * num / den)
