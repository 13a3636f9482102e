"""Moving-average approximation on the decimated grid (seed 000 eq. 13–14).

After :func:`app.core.regularize.regularize_line`, each component of the
decimated ``x`` is an exactly known finite moving average of the *full-rate*
white noises (``q`` in mGal per GNSS step, ``r`` in cm/s), with impulse response
``g`` from :func:`app.core.regularize.component_filters`.  Its exact decimated
autocovariance per unit variance is ``γ_j = Σ_i g_i g_{i+jn}``, zero for
``|j| > J = ⌊(len(g) − 1)/n⌋``.  We approximate it by a short MA driven by
decimated white noises of the *same* variances Q and R::

    x(τ_k) = Σ_{l=0..K} c_l q'(τ_{k−l}) + Σ_{l=0..L} d_l r'(τ_{k−l}),
    Var q' = Q (mGal², full-rate meaning),  Var r' = R ((cm/s)²),

so all scaling lives in ``c`` (dimensionless) and ``d`` (mGal per cm/s), and
nothing depends on Q or R.

Fit: least squares in the spectral domain,
``min_c ∫_{−π}^{π} (|C(e^{iω})|² − S(ω))² dω`` with ``S(ω) = Σ_j γ_j e^{−iωj}``;
by Parseval this equals ``2π Σ_{j∈ℤ} (Σ_l c_l c_{l+j} − γ_j)²``, which is what is
minimised (exactly, no frequency grid).  The start point is the minimum-phase
spectral factor (Fejér–Riesz) truncated to the order; for order ≥ J the factor is exact.
It comes from the roots of the autocovariance polynomial for short autocovariances
(J ≤ 64) and from the cepstrum of the spectrum otherwise (:func:`spectral_factor`):
the roots of a degree-2J polynomial cost O(J³) and are lost to round-off for the long
autocovariances a slowly decaying noise component gives (J ≈ 130–900: 2.4 s per call at
J = 908, and a white start instead of the factor).

Order criterion (per component, overridable): the smallest order that meets
both

* relative spectral misfit ``‖|C|² − S‖₂ / ‖S‖₂ < tol`` (default 1 %; L2 over ω,
  equal to the two-sided L2 norm of the autocovariance error), and
* band error ``max_ω ||C|² − S| / (S + 10^{−floor_db/10}·max S) < band_tol``
  (default 5 % with ``floor_db = 20``): the model is within 5 % of the true
  spectrum wherever that is within 20 dB of its peak,

capped at ``max_order`` (default 20; if the cap is reached the criterion is not
met and the reported misfits say by how much — this happens only for very
narrow transition bands, e.g. ``cutoff_hz`` ≥ 0.9·ω_stop).  The L2 criterion alone is not enough:
for m = 2 it accepts L = 6, whose error near the decimated Nyquist biases the
maximum-likelihood Q by −9 % (Q = 1e-5) to −38 % (Q = 1e-6); the band criterion
takes L = 7 and the bias falls below 0.3 % (asymptotic Whittle estimate).
Only second-order statistics matter: the coefficients are a minimum-phase-like
factor, their sign and phase carry no meaning.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize, signal

from app.core.regularize import RegularizationDesign, component_filters

DEFAULT_TOL = 0.01
DEFAULT_BAND_TOL = 0.05
DEFAULT_FLOOR_DB = 20.0
_N_FREQ = 1024
DEFAULT_MAX_ORDER = 20


@dataclass(frozen=True)
class MAModel:
    """Decimated mixture-of-MA model ``x_k = Σ c_l q_{k−l} + Σ d_l r_{k−l}``.

    Attributes
    ----------
    c : ndarray, shape (K+1,)
        Anomaly coefficients (dimensionless: Var q' = Q, mGal² per GNSS step).
    d : ndarray, shape (L+1,)
        GNSS-noise coefficients, mGal per (cm/s) (Var r' = R, (cm/s)²).
    K, L : int
        MA orders; ``p = max(K, L)`` is the correlation radius.
    dt_dec_s : float
        Decimated step, s.
    m : int
        Difference order the model was built for.
    misfit_q, misfit_r : float
        Relative L2 spectral misfit of each component (0.01 = 1 %).
    band_error_q, band_error_r : float
        Max relative spectral error where the component is within ``floor_db``
        of its peak (see module docstring).
    """

    c: np.ndarray
    d: np.ndarray
    K: int
    L: int
    p: int
    dt_dec_s: float
    m: int
    misfit_q: float
    misfit_r: float
    band_error_q: float = float("nan")
    band_error_r: float = float("nan")


def decimated_autocovariance(g: np.ndarray, n: int) -> np.ndarray:
    """Exact autocovariance of ``y[kn]``, ``y = g * w`` with unit white ``w``.

    Returns
    -------
    ndarray, shape (J+1,)
        ``γ_j = Σ_i g_i g_{i+jn}`` for ``j = 0..J``, ``J = ⌊(len(g) − 1)/n⌋``.
    """
    g = np.asarray(g, dtype=float)
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise ValueError(f"n must be an integer ≥ 1, got {n!r}")
    n = int(n)
    J = (g.size - 1) // n
    return np.array([np.dot(g[: g.size - j * n], g[j * n:]) for j in range(J + 1)])


def ma_autocovariance(coef: np.ndarray, maxlag: int | None = None) -> np.ndarray:
    """Autocovariance ``Σ_l b_l b_{l+j}``, ``j = 0..maxlag`` (default len−1), unit noise."""
    b = np.asarray(coef, dtype=float)
    full = np.correlate(b, b, mode="full")[b.size - 1:]
    if maxlag is None:
        return full
    out = np.zeros(int(maxlag) + 1)
    k = min(out.size, full.size)
    out[:k] = full[:k]
    return out


def _weights(n: int) -> np.ndarray:
    w = np.full(n, np.sqrt(2.0))
    w[0] = 1.0
    return w


def _misfit(acov_model: np.ndarray, gamma: np.ndarray) -> float:
    size = max(acov_model.size, gamma.size)
    a = np.zeros(size)
    a[:acov_model.size] = acov_model
    g = np.zeros(size)
    g[:gamma.size] = gamma
    w = _weights(size)
    return float(np.linalg.norm(w * (a - g)) / np.linalg.norm(w * g))


_ROOTS_MAX_LAG = 64     # longest autocovariance factored from its polynomial's roots
_FACTOR_EXACT = 1e-6    # a roots factor this close (relative L2 misfit) is kept as exact


def _roots_factor(gamma: np.ndarray) -> np.ndarray | None:
    """The minimum-phase factor from the J innermost roots of ``Σ_{|j|≤J} γ_|j| z^{J+j}``
    (reciprocal pairs), scaled to ``gamma`` by least squares; None when the roots are lost."""
    J = gamma.size - 1
    poly = np.concatenate([gamma[:0:-1], gamma])
    with np.errstate(all="ignore"):
        roots = np.roots(poly)
        roots = roots[np.argsort(np.abs(roots), kind="stable")][:J]
        b = np.real(np.poly(roots))
        out = _scaled(b, gamma)
    return out if np.all(np.isfinite(out)) else None


def _cepstral_factor(gamma: np.ndarray) -> np.ndarray:
    """The minimum-phase factor by the cepstrum (Kolmogorov's homomorphic method): the
    spectrum ``S(ω) = γ_0 + 2 Σ γ_j cos jω`` on an FFT grid of at least 16(J + 1) points
    (floored at 10⁻¹⁵ of its peak, where a differencing puts a zero), its log's cepstrum
    folded onto the causal lags, exponentiated back and truncated to J + 1 lags, then
    scaled to ``gamma`` by least squares.  O(J log J)."""
    J = gamma.size - 1
    n = 1 << int(np.ceil(np.log2(max(256, 16 * (J + 1)))))
    sym = np.zeros(n)
    sym[0] = gamma[0]
    sym[1:J + 1] = gamma[1:]
    sym[n - J:] = gamma[:0:-1]
    spec = np.fft.rfft(sym).real
    top = float(spec.max())
    if not top > 0:
        out = np.zeros(J + 1)
        out[0] = np.sqrt(max(gamma[0], 0.0))
        return out
    ceps = np.fft.irfft(np.log(np.maximum(spec, 1e-15 * top)), n)
    fold = np.zeros(n)
    fold[0], fold[n // 2] = ceps[0] / 2.0, ceps[n // 2] / 2.0
    fold[1:n // 2] = ceps[1:n // 2]
    b = np.fft.irfft(np.exp(np.fft.rfft(fold)), n)[:J + 1]
    return _scaled(b, gamma)


def _scaled(b: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """``b`` times the least-squares scale of its autocovariance onto ``gamma``."""
    with np.errstate(all="ignore"):
        a = ma_autocovariance(b)
        s2 = float(a @ gamma) / float(a @ a)
        return b * np.sqrt(max(s2, 0.0))


def spectral_factor(gamma: np.ndarray) -> np.ndarray:
    """Minimum-phase MA factor ``b`` (len J+1) with ``Σ_l b_l b_{l+j} ≈ γ_j``.

    For J ≤ 64, from the roots of ``Σ_{|j|≤J} γ_|j| z^{J+j}`` inside the unit circle, kept
    when its autocovariance misfit is below 10⁻⁶; otherwise (and always for longer
    autocovariances) the cepstral factor, or the roots' where that fits better.  The roots
    of a long autocovariance's polynomial are lost to round-off (a height-noise component
    differenced m + 2 times spans many decades); the cepstrum needs no roots.

    Parameters
    ----------
    gamma : ndarray, shape (J+1,)
        Autocovariance at lags 0..J (γ_0 > 0; a nonnegative spectrum).

    Returns
    -------
    ndarray, shape (J+1,)
        The factor, finite.
    """
    gamma = np.asarray(gamma, dtype=float)
    J = gamma.size - 1
    if J == 0:
        return np.array([np.sqrt(max(gamma[0], 0.0))])
    by_roots = _roots_factor(gamma) if J <= _ROOTS_MAX_LAG else None
    roots_misfit = _misfit(ma_autocovariance(by_roots), gamma) if by_roots is not None else np.inf
    if roots_misfit < _FACTOR_EXACT:
        return by_roots
    by_ceps = _cepstral_factor(gamma)
    if by_roots is not None and (not np.all(np.isfinite(by_ceps))
                                 or roots_misfit <= _misfit(ma_autocovariance(by_ceps), gamma)):
        return by_roots
    if not np.all(np.isfinite(by_ceps)):  # the white factor, a start only
        by_ceps = np.zeros(J + 1)
        by_ceps[0] = np.sqrt(max(gamma[0], 0.0))
    return by_ceps


def _fit_order(gamma: np.ndarray, order: int, b_full: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares MA(order) fit of the autocovariance ``gamma`` (two-sided L2)."""
    J = gamma.size - 1
    scale = np.sqrt(gamma[0])
    gn = gamma / gamma[0]
    nres = max(J, order) + 1
    gpad = np.zeros(nres)
    gpad[:gn.size] = gn
    w = _weights(nres)

    def resid(c):
        return w * (ma_autocovariance(c, nres - 1) - gpad)

    jj = np.arange(nres)[:, None]
    ll = np.arange(order + 1)[None, :]
    up, down = ll + jj, ll - jj
    up_ok, down_ok = up <= order, down >= 0
    up_i, down_i = np.minimum(up, order), np.maximum(down, 0)

    def jac(c):  # ∂(Σ_i c_i c_{i+j})/∂c_l = c_{l+j} + c_{l−j}
        Jm = np.where(up_ok, c[up_i], 0.0) + np.where(down_ok, c[down_i], 0.0)
        return w[:, None] * Jm

    b = b_full / scale
    starts = []
    c0 = np.zeros(order + 1)
    k = min(order + 1, b.size)
    c0[:k] = b[:k]
    starts.append(c0)
    if order < J:  # second start: factor of the Bartlett-tapered, truncated autocovariance
        taper = 1.0 - np.arange(order + 1) / (order + 1)
        starts.append(spectral_factor(gn[:order + 1] * taper))
    starts = [s for s in starts if np.all(np.isfinite(s))] or [np.eye(order + 1)[0]]
    best = None
    for s in starts:
        if order >= J:
            c = s
        else:
            c = optimize.least_squares(resid, s, jac=jac, method="lm", xtol=1e-14, ftol=1e-14,
                                       gtol=1e-14, max_nfev=2000).x
        f = _misfit(ma_autocovariance(c), gn)
        if best is None or f < best[1]:
            best = (c, f)
    c, f = best
    if c[0] < 0:  # sign convention: leading coefficient positive
        c = -c
    return c * scale, f


def _band_error(acov_model: np.ndarray, gamma: np.ndarray, floor_db: float) -> float:
    """max |S_model − S_true| / (S_true + floor·max S_true) on a uniform grid of (0, π)."""
    size = max(acov_model.size, gamma.size)
    a = np.zeros(size)
    a[:acov_model.size] = acov_model
    g = np.zeros(size)
    g[:gamma.size] = gamma
    w = (np.arange(_N_FREQ) + 0.5) * np.pi / _N_FREQ
    cosm = np.cos(np.outer(w, np.arange(1, size)))
    s_true = g[0] + 2.0 * cosm @ g[1:]
    s_mod = a[0] + 2.0 * cosm @ a[1:]
    floor = 10.0 ** (-floor_db / 10.0) * s_true.max()
    return float(np.max(np.abs(s_mod - s_true) / (np.maximum(s_true, 0.0) + floor)))


def fit_ma_component(
    gamma: np.ndarray, order: int | None = None, tol: float = DEFAULT_TOL,
    max_order: int = DEFAULT_MAX_ORDER, band_tol: float = DEFAULT_BAND_TOL,
    floor_db: float = DEFAULT_FLOOR_DB,
) -> tuple[np.ndarray, int, float, float]:
    """Fit one component's decimated autocovariance ``gamma`` (shape (J+1,)).

    Returns ``(coef, order, misfit, band_error)``; with ``order=None`` the smallest
    order meeting ``misfit < tol`` and ``band_error < band_tol`` (module docstring),
    at most ``max_order``; the exact factor (order J) meets both.
    """
    gamma = np.asarray(gamma, dtype=float)
    if gamma.ndim != 1 or gamma.size == 0 or not np.all(np.isfinite(gamma)) or gamma[0] <= 0:
        raise ValueError("gamma must be a finite 1-D autocovariance with gamma[0] > 0")
    J = gamma.size - 1
    b_full = spectral_factor(gamma)
    if order is not None:
        if isinstance(order, bool) or int(order) != order or order < 0:
            raise ValueError(f"MA order must be an integer ≥ 0, got {order!r}")
        c, f = _fit_order(gamma, int(order), b_full)
        return c, int(order), f, _band_error(ma_autocovariance(c), gamma, floor_db)
    if not (0 < tol < 1):
        raise ValueError(f"tol must be in (0, 1), got {tol}")
    if not (0 < band_tol):
        raise ValueError(f"band_tol must be positive, got {band_tol}")
    if isinstance(max_order, bool) or int(max_order) != max_order or max_order < 0:
        raise ValueError(f"max_order must be an integer ≥ 0, got {max_order!r}")
    for k in range(0, min(J, int(max_order)) + 1):
        c, f = _fit_order(gamma, k, b_full)
        be = _band_error(ma_autocovariance(c), gamma, floor_db)
        if f < tol and be < band_tol:
            break
    return c, k, f, be


def noise_filters(design: RegularizationDesign, m: int, noise=None) -> list[np.ndarray]:
    """Full-rate impulse responses from each noise innovation to the pre-decimation ``x``.

    ``noise`` None (or a white-velocity model at 1 (cm/s)²): the single ``g_r`` of
    :func:`app.core.regularize.component_filters`.  A coloured
    :class:`app.core.noise_model.NoiseModel`: one filter per component,
    ``g_q ∗ ∇^m ∗ (√w_c · AR_c ∗ ∇^{j_c})`` — the component's innovation (variance R·w_c)
    through its own shaping and the regularization; the decimated autocovariances of
    the components add.
    """
    g_q, g_r = component_filters(design, m)
    if noise is None:
        return [g_r]
    d_m = np.array([1.0])
    for _ in range(int(m)):
        d_m = np.convolve(d_m, [1.0, -1.0])
    base = np.convolve(g_q, d_m)
    return [np.convolve(base, h) for h in noise.impulse_responses()]


def fit_ma_model(
    design: RegularizationDesign, m: int, K: int | None = None, L: int | None = None,
    tol: float = DEFAULT_TOL, max_order: int = DEFAULT_MAX_ORDER,
    band_tol: float = DEFAULT_BAND_TOL, floor_db: float = DEFAULT_FLOOR_DB, noise=None,
) -> MAModel:
    """Fit the decimated MA model for difference order ``m``.

    Parameters
    ----------
    design : RegularizationDesign
    m : int ≥ 1
    K, L : int, optional
        MA orders of the anomaly / GNSS components; chosen by the criterion of
        the module docstring when None.
    tol : float
        Relative L2 spectral misfit threshold (0.01 = 1 %).
    max_order : int
    band_tol, floor_db : float
        Band-error threshold and the dB range below the peak it applies to.
    noise : app.core.noise_model.NoiseModel, optional
        The error of z (normalised: a level R in (cm/s)² of equivalent white velocity
        noise); ``d`` then describes that coloured error on the decimated grid
        (:func:`noise_filters`).  None: white velocity noise (seed 000).

    Returns
    -------
    MAModel
        Independent of Q and R.  Seed settings (10 Hz, 100 m/s, 60 dB,
        difference on the decimated grid): m = 1 → K = 5, L = 6; m = 2 → K = 5,
        L = 7.
    """
    if isinstance(m, bool) or int(m) != m or m < 1:
        raise ValueError(f"m must be an integer ≥ 1, got {m!r}")
    m = int(m)
    g_q, _ = component_filters(design, m)
    gam_q = decimated_autocovariance(g_q, design.n)
    gams = [decimated_autocovariance(g, design.n) for g in noise_filters(design, m, noise)]
    gam_r = np.zeros(max(g.size for g in gams))
    for g in gams:
        gam_r[:g.size] += g
    c, K, fq, bq = fit_ma_component(gam_q, K, tol, max_order, band_tol, floor_db)
    d, L, fr, br = fit_ma_component(gam_r, L, tol, max_order, band_tol, floor_db)
    return MAModel(c=c, d=d, K=K, L=L, p=max(K, L), dt_dec_s=design.dt_dec_s, m=m,
                   misfit_q=fq, misfit_r=fr, band_error_q=bq, band_error_r=br)


def autocovariance(model: MAModel, Q, R, maxlag: int) -> np.ndarray:
    """Autocovariance of the MA model, lags ``0..maxlag``.

    Parameters
    ----------
    Q : float — mGal² per GNSS step.  R : float — (cm/s)².

    Returns
    -------
    ndarray, shape (maxlag+1,), mGal².
    """
    if int(maxlag) != maxlag or maxlag < 0:
        raise ValueError(f"maxlag must be an integer ≥ 0, got {maxlag!r}")
    return float(Q) * ma_autocovariance(model.c, int(maxlag)) + float(R) * ma_autocovariance(model.d, int(maxlag))


def _psd_from_coef(b: np.ndarray, f_hz: np.ndarray, T: float) -> np.ndarray:
    l = np.arange(b.size)
    C = np.exp(-2j * np.pi * np.outer(f_hz, l) * T) @ b
    return T * np.abs(C) ** 2


def model_vs_true_spectrum(model: MAModel, design: RegularizationDesign, f_hz, noise=None) -> dict:
    """Two-sided PSDs on the decimated grid per unit Q and per unit R.

    The true spectrum is the aliased sum ``Σ_{k=0}^{n−1} Δt·|G(f − k/T)|²`` of the
    full-rate component filter (``T = nΔt``), independent of the autocovariance
    path used by the fit; the model spectrum is ``T·|C(e^{−2πifT})|²``.  Both
    integrate over (−1/2T, 1/2T) to the decimated variance.

    Returns
    -------
    dict with ``f_hz``, ``true_q``, ``model_q`` (mGal²/Hz per mGal²) and
    ``true_r``, ``model_r`` (mGal²/Hz per (cm/s)²), arrays of the shape of ``f_hz``.
    """
    f = np.atleast_1d(np.asarray(f_hz, dtype=float))
    T = design.dt_dec_s
    dt = design.dt_s
    g_q, _ = component_filters(design, model.m)
    out = {"f_hz": f}
    fk = (f[None, :] - np.arange(design.n)[:, None] / T).ravel()
    for name, gs, b in (("q", [g_q], model.c), ("r", noise_filters(design, model.m, noise), model.d)):
        true = np.zeros(f.size)
        for g in gs:
            _, G = signal.freqz(g, worN=fk, fs=1.0 / dt)
            true += dt * (np.abs(G) ** 2).reshape(design.n, f.size).sum(axis=0)
        out[f"true_{name}"] = true
        out[f"model_{name}"] = _psd_from_coef(b, f, T)
    return out
