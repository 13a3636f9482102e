"""Checks of an estimate against the data alone (no truth): is it flattened, is it
consistent at the crossovers?

The adaptive smoother is optimal when its model fits; these checks catch the cases
where it does not, so that the pipeline can fall back to a simpler estimate and say
why (``app.pipeline`` model choice).

* :func:`fir_noise_variance_mgal2` — variance of the FIR 100 s estimate's error due to
  the noise, from the fitted noise model: what the FIR passes of the noise.
* :func:`noise_overstated` — the FIR estimate's crossover differences bound the noise it
  passes from above (the noise of two crossing lines is independent): a noise model that
  predicts significantly more FIR noise than the crossovers allow over-states it.
* :func:`flattening_ratio` — along-line variance of an estimate against the anomaly
  variance the FIR estimate shows beyond its own noise.  A Kalman smoother whose anomaly
  level collapsed draws a straight line: its variance falls far below what the data
  support.  This is a failure to detect, not a result.
* :func:`crossover_comparison` — paired comparison of two estimates' crossover
  differences: two crossing lines' errors are nearly independent (different directions,
  flights, times), so the mean square difference estimates the sum of their mean square
  errors, and the difference between two estimators of it is their difference in accuracy.
  Two tests: a paired t-test on the squared differences (the mean square) and a
  Wilcoxon signed-rank test on their magnitudes (:func:`paired_rank_p`), which one wild
  crossover cannot mask.
* :func:`crossover_excess` — do the crossovers show more error than the lines' posterior std
  says?  The std is the noise model's word on the noise it leaves; an excess is noise in the
  anomaly band the model does not know.  :func:`crossover_level_scale` — then, of a scan of
  lower anomaly levels, the one whose crossovers agree best, if significantly better;
  :func:`crossover_noise_floor` — or the least white noise floor added to the noise model at
  which they agree with the std.
* :func:`crossover_blend_weight` — the weight of the blend of two estimates whose
  crossover differences have the least mean square: by the same reading of the
  crossovers, the blend with the least error two crossing lines do not share;
  :func:`blend_estimates` — that blend and its std.
* :func:`leave_one_out_msd_mgal2` — on a repeat track, each pass of an estimate against the
  other passes' mean of a lightly smoothed reference: the passes share the anomaly and not
  the noise, so the difference of two estimates' figures is the difference of their mean
  square errors (the test-line survey's counterpart of the crossovers);
  :func:`repeat_blend_weight` — the blend of two estimates with the least such figure, and
  :func:`shrunk_repeat_blend_weight` — that weight shrunk by its jackknife error over the passes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from app.core.baselines import fir_kernel, fir_lowpass_mgal


def fir_noise_variance_mgal2(noise, level: float, dt_s: float, cutoff_period_s: float = 100.0) -> float:
    """Variance (mGal²) of the noise of z after the FIR low-pass of :mod:`app.core.baselines`.

    Parameters
    ----------
    noise : app.core.noise_model.NoiseModel
        Shape of the error of z (a level R multiplies it).
    level : float
        Level R of the stretch (the model's unit, e.g. (cm/s)² of equivalent white velocity noise).
    dt_s : float
        GNSS step (s).
    cutoff_period_s : float
        The FIR's cut-off period (s).
    """
    f, s = _fir_noise_psd(noise, level, dt_s, cutoff_period_s)
    return float(2.0 * np.trapezoid(s, f))


def _fir_noise_psd(noise, level: float, dt_s: float, cutoff_period_s: float):
    """Frequencies (Hz, ≥ 0) and the two-sided PSD (mGal²/Hz) of z's noise at level R after
    the FIR low-pass: ``|H(f)|²·S(f)``."""
    h = fir_kernel(dt_s, cutoff_period_s)
    nfft = 1 << int(np.ceil(np.log2(max(8 * h.size, 1 << 14))))
    f = np.fft.rfftfreq(nfft, dt_s)
    return f, np.abs(np.fft.rfft(h, nfft)) ** 2 * noise.psd(f, level)


@dataclass(frozen=True)
class NoiseBound:
    """Result of :func:`noise_overstated`.

    Attributes
    ----------
    n : int
        Crossovers used.
    crossover_ms_mgal2 : float
        Mean square of the FIR estimate's crossover differences.
    predicted_ms_mgal2 : float
        Mean of the predicted ``σ_a² + σ_b²`` (the noise of the two lines' FIR estimates).
    bound_mgal2 : float
        One-sided upper confidence bound of the true mean square difference.
    overstated : bool
        ``predicted_ms_mgal2 > bound_mgal2``.
    lower_bound_mgal2 : float
        One-sided lower confidence bound (same level) of the true mean square difference.
    understated : bool
        ``predicted_ms_mgal2 < lower_bound_mgal2``: the model predicts significantly less FIR
        noise than the differences show (only meaningful where nothing but noise differs).
    """

    n: int
    crossover_ms_mgal2: float
    predicted_ms_mgal2: float
    bound_mgal2: float
    overstated: bool
    lower_bound_mgal2: float = float("nan")
    understated: bool = False


def noise_overstated(diff_mgal, pred_var_mgal2, alpha: float = 0.05, min_n: int = 4) -> NoiseBound:
    """Does a noise model predict more FIR noise than the crossovers allow?

    At a crossover the difference of the two lines' FIR estimates is ``e_a − e_b``; the noise
    parts of ``e_a`` and ``e_b`` are independent (other line, other time), so
    ``E(d²) ≥ σ_a² + σ_b²`` whatever else the errors hold (the smoothing error they share
    cancels and only lowers ``E(d²)`` towards the noise).  With ``d`` Gaussian, ``Σd²/E(d²)``
    is χ² with n degrees of freedom, so ``n·mean(d²)/χ²_α(n)`` bounds ``E(d²)`` from above
    with confidence ``1 − α``; a mean prediction above that bound over-states the noise.
    Line offsets (drift) in the differences only widen the bound: the test is one-sided.

    Parameters
    ----------
    diff_mgal : array_like, shape (n,)
        FIR crossover differences (mGal).
    pred_var_mgal2 : array_like, shape (n,)
        Predicted ``σ_a² + σ_b²`` at each crossover (mGal²).
    alpha : float
        One-sided level.
    min_n : int
        Fewer usable crossovers: never over-stated.

    Returns
    -------
    NoiseBound
    """
    d = np.asarray(diff_mgal, dtype=float)
    v = np.asarray(pred_var_mgal2, dtype=float)
    if d.shape != v.shape:
        raise ValueError(f"diff_mgal and pred_var_mgal2 differ in shape: {d.shape} vs {v.shape}")
    if not 0 < alpha < 0.5:
        raise ValueError("alpha must lie in (0, 0.5)")
    ok = np.isfinite(d) & np.isfinite(v) & (v >= 0)
    n = int(ok.sum())
    if n < max(1, min_n):
        return NoiseBound(n, float("nan"), float("nan"), float("nan"), False)
    ms = float(np.mean(d[ok] ** 2))
    pred = float(np.mean(v[ok]))
    bound = ms * n / float(stats.chi2.ppf(alpha, n))
    lower = ms * n / float(stats.chi2.ppf(1.0 - alpha, n))
    return NoiseBound(n, ms, pred, bound, bool(pred > bound), lower, bool(pred < lower))


def difference_nll(diff_mgal, pred_var_mgal2) -> float:
    """Mean negative log-likelihood per difference of zero-mean Gaussian differences with the
    predicted variances: ``½·mean(d²/v + ln 2πv)``.  Of two noise models, the one with the
    lower value explains the FIR differences (crossovers, repeat contrasts) better.

    Parameters
    ----------
    diff_mgal, pred_var_mgal2 : array_like, shape (n,)
        Differences (mGal) and their predicted variances (mGal², > 0).
    """
    d = np.asarray(diff_mgal, dtype=float)
    v = np.asarray(pred_var_mgal2, dtype=float)
    if d.shape != v.shape:
        raise ValueError(f"diff_mgal and pred_var_mgal2 differ in shape: {d.shape} vs {v.shape}")
    ok = np.isfinite(d) & np.isfinite(v) & (v > 0)
    if not ok.any():
        return float("nan")
    return float(0.5 * np.mean(d[ok] ** 2 / v[ok] + np.log(2.0 * np.pi * v[ok])))


def repeat_contrasts(along_m, values_mgal, step_m: float) -> np.ndarray:
    """Orthonormal contrasts of K passes of a repeat track at common along-track positions.

    Each pass is sorted along the track and linearly interpolated at positions every
    ``step_m`` over the interval all passes cover; positions where a pass is not finite are
    dropped.  At each position the K values give the K − 1 Helmert contrasts
    ``(g_1 + … + g_k − k·g_{k+1}) / √(k(k+1))``: the common part (the anomaly) cancels, and
    when the passes' errors are independent with one variance σ², the contrasts are
    independent with variance σ² — so they enter :func:`noise_overstated` with a predicted
    variance of σ² each, beside crossover differences (predicted ``σ_a² + σ_b²``).  Whatever
    else differs between passes (drift, flight height) only adds to them.

    Positions along a low-passed estimate are correlated; with ``step_m`` one period of the
    low-pass cut-off (100 s of flight behind FIR 100 s) the χ² test holds its level for white,
    f² and f⁴ noise behind that filter (half a period does not: 2.5–3.3 % false alarms at
    α = 0.01, 8–13 % at 0.05).

    Parameters
    ----------
    along_m : sequence of K array_like
        Along-track positions of each pass's epochs (m), in either direction.
    values_mgal : sequence of K array_like
        Each pass's values (mGal), same shapes.
    step_m : float
        Spacing of the common positions (m).

    Returns
    -------
    ndarray
        The contrasts (mGal), (K − 1) per usable position; empty with fewer than two passes
        or no common interval.
    """
    if not (np.isfinite(step_m) and step_m > 0):
        raise ValueError(f"step_m must be positive, got {step_m!r}")
    if len(along_m) != len(values_mgal):
        raise ValueError(f"{len(along_m)} position arrays for {len(values_mgal)} value arrays")
    passes = []
    for k, (s, v) in enumerate(zip(along_m, values_mgal)):
        s = np.asarray(s, dtype=float)
        v = np.asarray(v, dtype=float)
        if s.shape != v.shape or s.ndim != 1:
            raise ValueError(f"pass {k}: positions and values differ in shape: {s.shape} vs {v.shape}")
        ok = np.isfinite(s)
        o = np.argsort(s[ok], kind="stable")
        if o.size < 2:
            return np.zeros(0)
        passes.append((s[ok][o], v[ok][o]))
    if len(passes) < 2:
        return np.zeros(0)
    lo = max(p[0][0] for p in passes)
    hi = min(p[0][-1] for p in passes)
    if not hi > lo:
        return np.zeros(0)
    grid = np.arange(lo, hi + 1e-9, step_m)
    g = np.array([np.interp(grid, *p) for p in passes])      # a NaN spoils only its neighbours
    g = g[:, np.all(np.isfinite(g), axis=0)]
    kk = np.arange(1, len(passes))[:, None]
    cum = np.cumsum(g, axis=0)[:-1]                            # g_1 + … + g_k
    return ((cum - kk * g[1:]) / np.sqrt(kk * (kk + 1))).ravel()


@dataclass(frozen=True)
class Flattening:
    """Result of :func:`flattening_ratio`.

    Attributes
    ----------
    ratio : float
        ``var(estimate) / (var(FIR) − FIR noise variance)``; NaN when the FIR shows no
        anomaly beyond its noise (nothing to detect).
    signal_var_mgal2 : float
        Anomaly variance the FIR estimate shows beyond its noise.
    detectable : bool
        The FIR's anomaly variance exceeds ``min_snr`` × its noise variance.
    ratio_bound : float
        ``var(estimate)`` against the *least* anomaly variance the FIR shows at the
        confidence level, given how few independent samples of its noise the stretch holds
        (inf when that least variance is not positive: nothing shows the estimate
        flattened); equal to ``ratio`` without ``independent_samples``.
    independent_samples : float
        The independent samples of the FIR's noise the stretch holds (NaN when not given).
    """

    ratio: float
    signal_var_mgal2: float
    detectable: bool
    ratio_bound: float = float("nan")
    independent_samples: float = float("nan")


def fir_noise_bandwidth_hz(noise, dt_s: float, cutoff_period_s: float = 100.0) -> float:
    """Equivalent bandwidth (Hz, one-sided) of the noise of z after the FIR low-pass,
    ``(∫S df)² / ∫S² df`` with ``S`` the noise's spectrum through the FIR: a stretch of
    ``T`` seconds holds ``2·B·T`` independent samples of that noise (band-limited white noise
    of bandwidth ``B``: exactly ``2·B·T``).  The level R scales ``S`` and cancels.

    Parameters
    ----------
    noise : app.core.noise_model.NoiseModel
    dt_s : float
        GNSS step (s).
    cutoff_period_s : float
        The FIR's cut-off period (s).
    """
    f, s = _fir_noise_psd(noise, 1.0, dt_s, cutoff_period_s)
    den = float(np.trapezoid(s * s, f))
    return float(np.trapezoid(s, f) ** 2 / den) if den > 0 else float("nan")


def flattening_ratio(estimate_mgal, fir_mgal, fir_noise_var_mgal2: float, min_snr: float = 4.0,
                     independent_samples: float | None = None, confidence: float = 0.95) -> Flattening:
    """Along-line variance of ``estimate_mgal`` against the anomaly variance in ``fir_mgal``.

    Parameters
    ----------
    estimate_mgal, fir_mgal : ndarray, shape (n,)
        The estimate to check and the FIR 100 s estimate on the same epochs (NaN ignored).
    fir_noise_var_mgal2 : float
        :func:`fir_noise_variance_mgal2` for the stretch.
    min_snr : float
        The check applies only where the FIR's anomaly variance exceeds this × its noise.
    independent_samples : float, optional
        Independent samples ν of the FIR's noise along the stretch (``2·B·T``,
        :func:`fir_noise_bandwidth_hz`).  The noise variance the FIR actually carries over the
        stretch scatters as ``σ²·χ²_ν/ν`` about the model's σ², and its covariance with the
        anomaly by ``±sqrt(var_a·σ²/ν)``: a line of three FIR periods (ν ≈ 6) can carry twice
        the predicted noise variance, which then reads as anomaly the estimate missed.
        ``ratio_bound`` sets the estimate's variance against the least anomaly variance
        consistent with the FIR at ``confidence`` (one-sided): the anomaly variance less the
        two deviations at that level combined as independent errors,
        ``hypot(σ²·(χ²_conf(ν)/ν − 1), 2·z_conf·sqrt(var_a·σ²/ν))``.
    confidence : float
        One-sided confidence of that bound.
    """
    e = np.asarray(estimate_mgal, dtype=float)
    f = np.asarray(fir_mgal, dtype=float)
    if not 0.5 <= confidence < 1:
        raise ValueError(f"confidence must be in [0.5, 1), got {confidence}")
    ok = np.isfinite(e) & np.isfinite(f)
    if ok.sum() < 10:
        return Flattening(float("nan"), float("nan"), False)
    var_f, var_e = float(np.var(f[ok])), float(np.var(e[ok]))
    sig = var_f - fir_noise_var_mgal2
    detectable = sig > min_snr * fir_noise_var_mgal2 and sig > 0
    ratio = float(var_e / sig) if sig > 0 else float("nan")
    if independent_samples is None or not np.isfinite(independent_samples):
        return Flattening(ratio, sig, bool(detectable), ratio)
    nu = max(float(independent_samples), 2.0)
    # the two one-sided deviations at the confidence level, combined as independent errors
    # (the line's mean costs the FIR's noise little: it has little power at the lowest frequencies)
    noise_dev = fir_noise_var_mgal2 * (float(stats.chi2.ppf(confidence, nu)) / nu - 1.0)
    cross_dev = 2.0 * float(stats.norm.ppf(confidence)) * np.sqrt(max(sig, 0.0) * fir_noise_var_mgal2 / nu)
    sig_lo = sig - float(np.hypot(noise_dev, cross_dev))
    bound = float(var_e / sig_lo) if sig_lo > 0 else float("inf")
    return Flattening(ratio, sig, bool(detectable), bound, nu)


def fir_smoothing_variance_mgal2(estimate_mgal, dt_s: float, cutoff_period_s: float = 100.0) -> float:
    """Variance (mGal²) of what the FIR low-pass removes from an estimate along a line:
    ``var(a − FIR(a))``.

    Where the estimate ``a`` resolves anomaly above the FIR's cut-off, this is the FIR
    estimate's smoothing error — the anomaly it clips, an error two crossing lines largely
    share, so the FIR's crossover differences cannot show it.  Whatever noise ``a`` carries
    above the cut-off adds to it: as an addition to the FIR's error variance it errs on the
    wide side.

    Parameters
    ----------
    estimate_mgal : array_like, shape (n,)
        The estimate along one line (mGal); NaN = missing.
    dt_s : float
        Step (s).
    cutoff_period_s : float
        The FIR's cut-off period (s), as in :func:`app.core.baselines.fir_lowpass_mgal`.
    """
    a = np.asarray(estimate_mgal, dtype=float)
    if a.ndim != 1:
        raise ValueError(f"estimate_mgal must be 1-D, got shape {a.shape}")
    if not np.isfinite(a).any():
        return float("nan")
    return float(np.nanvar(a - fir_lowpass_mgal(a, dt_s, cutoff_period_s)))


def smooth_error_bound_mgal2(estimate_mgal, fir_mgal) -> float:
    """Along-line error variance a smooth estimate can have: ``Var(fir) − Var(estimate)`` (mGal²).

    With ``x̂`` the conditional mean of the anomaly ``x`` given the data,
    ``Var(x̂ − x) = Var x − Var x̂``; the FIR 100 s estimate ``x + e_f`` (noise independent of
    the anomaly) has ``Var x + Var e_f ≥ Var x``.  So the difference bounds the estimate's
    error variance from above, with no noise model — the bound used where an estimate does
    not resolve the anomaly and its posterior std says nothing about its error.

    Parameters
    ----------
    estimate_mgal, fir_mgal : ndarray, shape (n,)
        The estimate and FIR 100 s on the same epochs (mGal; NaN ignored).

    Returns
    -------
    float
        mGal² (may be negative: the estimate varies more than FIR); NaN with fewer than 10
        common finite epochs.
    """
    e = np.asarray(estimate_mgal, dtype=float)
    f = np.asarray(fir_mgal, dtype=float)
    ok = np.isfinite(e) & np.isfinite(f)
    if ok.sum() < 10:
        return float("nan")
    return float(np.var(f[ok]) - np.var(e[ok]))


def repeat_noise_variance_mgal2(values_mgal, min_points: int = 10) -> np.ndarray:
    """Each pass's noise variance (mGal²) from K ≥ 2 passes of one repeat track.

    At common along-track positions every pass holds the same anomaly and its own noise,
    independent between passes flown at different times, so the difference of passes j and k
    holds their noise alone: ``D_jk = var(v_j − v_k) = σ_j² + σ_k²``.  The K variances are the
    least-squares solution of those K(K − 1)/2 equations (the "three-cornered hat" of clock
    comparisons; K = 3: ``σ_1² = (D_12 + D_13 − D_23)/2``); with K = 2 the two passes share
    ``D_12`` equally.  No noise model enters — the model's level misses noise below its band (a
    GNSS noise episode of slowly varying error), the passes do not — and no anomaly: a
    covariance with the other passes would carry the anomaly times the noise, by chance
    several times the noise variance itself under a strong anomaly.  Whatever else differs
    between the passes (drift, a different height) counts as noise here.

    Parameters
    ----------
    values_mgal : array_like, shape (K, n)
        The passes' values at n common positions (mGal, finite;
        :func:`app.core.accuracy.repeat_line_accuracy` ``.values_mgal``).
    min_points : int
        Fewer common positions than this give NaN.

    Returns
    -------
    ndarray, shape (K,)
        mGal² (may come out negative by chance where one pass is much quieter than the others).
    """
    v = np.asarray(values_mgal, dtype=float)
    if v.ndim != 2 or v.shape[0] < 2:
        raise ValueError(f"values_mgal must be (K >= 2, n), got shape {v.shape}")
    k = v.shape[0]
    if v.shape[1] < min_points or not np.isfinite(v).all():
        return np.full(k, np.nan)
    j, i = np.triu_indices(k, 1)
    d = np.var(v[j] - v[i], axis=1)
    if k == 2:
        return np.full(2, d[0] / 2.0)
    design = np.zeros((d.size, k))
    design[np.arange(d.size), j] = 1.0
    design[np.arange(d.size), i] = 1.0
    return np.linalg.lstsq(design, d, rcond=None)[0]


def _passes_and_others(values_mgal: list, reference_mgal):
    """Estimates and a reference on one repeat track, shape (K ≥ 2, n) each, at the positions
    where all are finite and every pass about its mean: ``([values, …], others)`` with
    ``others[j]`` the mean reference of the passes other than j; None with fewer than 2 such
    positions."""
    vs = [np.asarray(v, dtype=float) for v in values_mgal]
    r = np.asarray(reference_mgal, dtype=float)
    if r.ndim != 2 or r.shape[0] < 2 or any(v.shape != r.shape for v in vs):
        raise ValueError(f"estimates and reference must all be (K >= 2, n), got "
                         f"{', '.join(str(v.shape) for v in vs)} and {r.shape}")
    ok = np.isfinite(r).all(axis=0)
    for v in vs:
        ok &= np.isfinite(v).all(axis=0)
    if ok.sum() < 2:
        return None
    vs = [v[:, ok] - v[:, ok].mean(axis=1, keepdims=True) for v in vs]
    r = r[:, ok] - r[:, ok].mean(axis=1, keepdims=True)
    return vs, (r.sum(axis=0, keepdims=True) - r) / (r.shape[0] - 1)


def leave_one_out_msd_mgal2(values_mgal, reference_mgal) -> np.ndarray:
    """Each pass's mean square difference (mGal²) from the other passes' mean reference.

    At common along-track positions pass j of an estimate holds ``v_j = g + e_j`` (the anomaly
    g, its error e_j) and the reference ``r_k = g + b + ν_k`` (b its smoothing error, shared;
    ν_k its noise, independent between passes flown at different times).  Against the mean
    ``r̄₋ⱼ`` of the other passes, ``E[(v_j − r̄₋ⱼ)²] = E[e_j²] − 2E[e_j b] + E[(b + ν̄₋ⱼ)²]``:
    the last term is the same for every estimate compared on the same pass, so the difference
    of two estimates' figures estimates the difference of their mean square errors against the
    truth, up to ``2E[(e_a − e_b) b]`` — small when the reference is a light low-pass of the
    measurement (b small) while its noise, however large, only adds scatter.  No noise model
    and no anomaly model enter.  Each pass's values and reference are taken about their mean
    (a pass's level is the leveling's business, as in the crossovers).

    Parameters
    ----------
    values_mgal, reference_mgal : array_like, shape (K, n)
        The estimate and the reference on K ≥ 2 passes at n common positions (mGal;
        :func:`app.core.accuracy.repeat_line_accuracy` ``.values_mgal``).  Positions where any
        value is not finite are left out.

    Returns
    -------
    ndarray, shape (K,)
        mGal²; NaN when fewer than 2 positions are complete.
    """
    got = _passes_and_others([values_mgal], reference_mgal)
    if got is None:
        return np.full(np.shape(values_mgal)[0], np.nan)
    (v,), others = got
    return np.mean((v - others) ** 2, axis=1)


def leave_one_out_msd_test(a_mgal, b_mgal, reference_mgal, block: int) -> tuple[float, float]:
    """Whether estimate a agrees with the other passes' reference better than b does.

    The difference of the two estimates' :func:`leave_one_out_msd_mgal2` figures, position by
    position and averaged over the passes (the passes' figures share the reference's noise, so
    they are not independent), is cut into blocks of ``block`` positions (about one
    independent stretch each); a one-sided t-test over the block means asks whether the mean
    difference is below 0.

    Parameters
    ----------
    a_mgal, b_mgal, reference_mgal : array_like, shape (K, n), or lists of them (one per track)
        Two estimates and the reference on K ≥ 2 passes at n common positions (mGal).
    block : int
        Positions per block (≥ 1).

    Returns
    -------
    (float, float)
        The mean difference a − b (mGal²) and the one-sided p-value (NaN with fewer than 3
        blocks).
    """
    if int(block) < 1:
        raise ValueError(f"block must be >= 1, got {block!r}")
    tracks = (zip(a_mgal, b_mgal, reference_mgal) if isinstance(a_mgal, (list, tuple))
              else [(a_mgal, b_mgal, reference_mgal)])
    means, total, count = [], 0.0, 0
    for a, b, r in tracks:
        got = _passes_and_others([a, b], r)
        if got is None:
            continue
        (a, b), others = got
        d = np.mean((a - others) ** 2 - (b - others) ** 2, axis=0)
        total += float(d.sum())
        count += d.size
        nb = d.size // int(block)
        if nb:
            means.extend(d[:nb * int(block)].reshape(nb, int(block)).mean(axis=1))
    if not count:
        return float("nan"), float("nan")
    mean = total / count
    m = np.asarray(means)
    if m.size < 3 or not np.std(m, ddof=1) > 0:
        return mean, float("nan")
    t = float(np.mean(m) / (np.std(m, ddof=1) / np.sqrt(m.size)))
    return mean, float(stats.t.cdf(t, m.size - 1))


def repeat_blend_weight(a_mgal, b_mgal, reference_mgal) -> float:
    """The weight w of the blend ``(1 − w)·a + w·b`` of two estimates on repeat tracks whose
    :func:`leave_one_out_msd_mgal2` summed over the passes is least, clipped to [0, 1].

    The figure is quadratic in w with its minimum at
    ``w = Σ (a_j − r̄₋ⱼ)(a_j − b_j) / Σ (a_j − b_j)²`` (sums over tracks, passes and positions,
    every pass and reference about its mean, r̄₋ⱼ over the other passes of the same track).
    The reference's noise is independent of pass j's estimates, so in expectation the
    numerator is ``E[e_a(e_a − e_b)]`` and the weight is the one that minimises the blend's
    mean square error against the truth (two estimates with independent errors of variances
    σ_a², σ_b²: ``σ_a²/(σ_a² + σ_b²)``), up to the reference's smoothing error as in
    :func:`leave_one_out_msd_mgal2`.

    Parameters
    ----------
    a_mgal, b_mgal, reference_mgal : array_like, shape (K, n), or lists of them (one per track)
        The two estimates and the reference on K ≥ 2 passes at n common positions (mGal).
        Positions where any value of a track is not finite are left out.

    Returns
    -------
    float
        w in [0, 1]; 0 when the two estimates do not differ (or no track has 2 complete positions).
    """
    tracks = (zip(a_mgal, b_mgal, reference_mgal) if isinstance(a_mgal, (list, tuple))
              else [(a_mgal, b_mgal, reference_mgal)])
    num = den = 0.0
    for a, b, r in tracks:
        got = _passes_and_others([a, b], r)
        if got is None:
            continue
        (a, b), others = got
        num += float(np.sum((a - others) * (a - b)))
        den += float(np.sum((a - b) ** 2))
    return float(np.clip(num / den, 0.0, 1.0)) if den > 0 else 0.0


@dataclass(frozen=True)
class ShrunkWeight:
    """Result of :func:`shrunk_repeat_blend_weight`.

    Attributes
    ----------
    weight : float
        The weight used, in [0, 1]: ``raw`` shrunk towards 0 by its jackknife error.
    raw : float
        :func:`repeat_blend_weight` of all the passes.
    se : float
        Its jackknife standard error over the passes (NaN with fewer than 3 passes on every track).
    leave_one_out : tuple of float
        The weight with each pass left out (tracks in order, passes in order).
    """

    weight: float
    raw: float
    se: float
    leave_one_out: tuple


def shrunk_repeat_blend_weight(a_mgal, b_mgal, reference_mgal) -> ShrunkWeight:
    """:func:`repeat_blend_weight` shrunk towards 0 by its own sampling error over the passes.

    The weight is a ratio of sums over a handful of passes against a reference whose noise is
    far larger than the difference it measures (a 2 Hz test line: the other passes' 50 s
    low-pass of z carries ~13 mGal RMS of noise against 1–2 mGal between the two estimates),
    so one test line's weight scatters over most of [0, 1].  Its jackknife over the passes
    (each pass left out in turn, the others' references re-formed without it) gives the
    standard error ``se``, and the positive-part James–Stein factor
    ``w = ŵ · max(0, 1 − se²/ŵ²)`` keeps a weight only as far as it stands out of its own
    scatter: 0 (the first estimate alone) when ``ŵ ≤ se``.  A track of 2 passes has no
    jackknife (one pass left has no reference); with no track of 3 or more the weight is not
    shrunk.

    Parameters
    ----------
    a_mgal, b_mgal, reference_mgal : array_like, shape (K, n), or lists of them (one per track)
        As in :func:`repeat_blend_weight`.

    Returns
    -------
    ShrunkWeight
    """
    tracks = ([np.asarray(x, float) for x in a_mgal], [np.asarray(x, float) for x in b_mgal],
              [np.asarray(x, float) for x in reference_mgal]) if isinstance(a_mgal, (list, tuple)) else \
        ([np.asarray(a_mgal, float)], [np.asarray(b_mgal, float)], [np.asarray(reference_mgal, float)])
    a, b, r = tracks
    raw = repeat_blend_weight(a, b, r)
    loo = []
    for t, (at, bt, rt) in enumerate(zip(a, b, r)):
        if at.shape[0] < 3:
            continue
        for i in range(at.shape[0]):
            keep = [j for j in range(at.shape[0]) if j != i]
            loo.append(repeat_blend_weight(a[:t] + [at[keep]] + a[t + 1:], b[:t] + [bt[keep]] + b[t + 1:],
                                           r[:t] + [rt[keep]] + r[t + 1:]))
    if len(loo) < 3:
        return ShrunkWeight(raw, raw, float("nan"), tuple(loo))
    w = np.asarray(loo)
    se = float(np.sqrt((w.size - 1) / w.size * np.sum((w - w.mean()) ** 2)))
    used = raw * max(0.0, 1.0 - se ** 2 / raw ** 2) if raw > 0 else 0.0
    return ShrunkWeight(float(used), float(raw), se, tuple(float(x) for x in loo))


def disagreement_ratio(estimate_mgal, fir_mgal) -> float:
    """RMS of ``estimate − fir`` over the std of ``fir``, both with their means removed.

    With ``estimate = s + e_a`` and ``fir = s + e_f`` (s the anomaly, errors independent of
    it), ``RMS(estimate − fir)² = var(e_a) + var(e_f) − 2 cov(e_a, e_f)`` and
    ``std(fir)² = var(s) + var(e_f)``; a ratio above 1 therefore means
    ``var(e_a) > var(s) + 2 cov(e_a, e_f)`` — with errors that go the same way (both filters
    pass the same noise of z and miss the same peaks) the estimate's error exceeds the
    anomaly itself, whatever noise model made it.  Unlike :func:`flattening_ratio` this needs
    no model of the FIR's noise.

    Parameters
    ----------
    estimate_mgal, fir_mgal : ndarray, shape (n,)
        The estimate and the FIR 100 s estimate on the same epochs (mGal; NaN ignored).

    Returns
    -------
    float
        The ratio; NaN with fewer than 10 common finite epochs or a constant FIR.
    """
    e = np.asarray(estimate_mgal, dtype=float)
    f = np.asarray(fir_mgal, dtype=float)
    if e.shape != f.shape:
        raise ValueError(f"estimate_mgal and fir_mgal differ in shape: {e.shape} vs {f.shape}")
    ok = np.isfinite(e) & np.isfinite(f)
    if ok.sum() < 10:
        return float("nan")
    d = (e[ok] - e[ok].mean()) - (f[ok] - f[ok].mean())
    sd = float(np.std(f[ok]))
    return float(np.sqrt(np.mean(d ** 2)) / sd) if sd > 0 else float("nan")


@dataclass(frozen=True)
class CrossoverComparison:
    """Result of :func:`crossover_comparison`.

    Attributes
    ----------
    n : int
        Crossovers used.
    rms_a_mgal, rms_b_mgal : float
        RMS of each estimate's crossover differences (after removing their mean).
    p_value : float
        One-sided p of "a is less accurate than b" (paired t-test on the squared differences).
    p_rank : float
        The same by the signed ranks of ``|a| − |b|`` (:func:`paired_rank_p`).  The squared
        differences are heavy-tailed: one crossover of 220 mGal made a t-test miss an
        estimate whose crossover RMS was 2.2× FIR's (p = 0.10; by the ranks 0.002).
    """

    n: int
    rms_a_mgal: float
    rms_b_mgal: float
    p_value: float
    p_rank: float = float("nan")


def crossover_comparison(diff_a_mgal, diff_b_mgal) -> CrossoverComparison:
    """Compare two estimates through their crossover differences (module docstring).

    The differences' mean (a level offset that leveling removes) is taken out of each.
    """
    a = np.asarray(diff_a_mgal, dtype=float)
    b = np.asarray(diff_b_mgal, dtype=float)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok] - np.mean(a[ok]) if ok.any() else a[ok], b[ok] - np.mean(b[ok]) if ok.any() else b[ok]
    n = int(a.size)
    if n < 3:
        return CrossoverComparison(n, float("nan"), float("nan"), float("nan"))
    p = paired_decrease_p(a ** 2, b ** 2)
    return CrossoverComparison(n, float(np.sqrt(np.mean(a ** 2))), float(np.sqrt(np.mean(b ** 2))), p,
                               paired_rank_p(np.abs(a), np.abs(b)))


def crossover_rms_mgal(diff_mgal) -> float:
    """RMS of the finite crossover differences after removing their mean (a level offset
    that leveling removes), mGal; NaN when there are none."""
    d = np.asarray(diff_mgal, dtype=float)
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean((d - d.mean()) ** 2))) if d.size else float("nan")


def significantly_worse(cmp: CrossoverComparison, p_level: float) -> bool:
    """Is estimate a significantly less accurate than b at the crossovers?

    Yes when the paired t-test on the squared differences says so (``p_value < p_level``),
    or when the signed ranks say so (``p_rank < p_level``) *and* a's crossover RMS is the
    larger: the ranks see a typical difference, the accuracy that matters is the mean
    square, so a rank result against the RMS is not taken (a layout whose estimate had
    4.8 against FIR's 5.4 mGal crossover RMS, ranks p = 0.03, had 0.83× FIR's error).

    Parameters
    ----------
    cmp : CrossoverComparison
        :func:`crossover_comparison` of a against b.
    p_level : float
        One-sided significance level of each test.
    """
    if cmp.p_value < p_level:
        return True
    return bool(cmp.p_rank < p_level and cmp.rms_a_mgal > cmp.rms_b_mgal)


def crossover_blend_weight(diff_a_mgal, diff_b_mgal) -> float:
    """Weight w of estimate a in the blend ``w·a + (1 − w)·b`` whose crossover differences
    have the least mean square, clipped to [0, 1].

    The blend's differences at the crossovers are ``w·d_a + (1 − w)·d_b`` (the crossings are
    the same points of the same lines), a quadratic in w with its minimum at
    ``w = (S_bb − S_ab) / (S_aa + S_bb − 2·S_ab)``, ``S`` the mean products of the
    differences after removing each one's mean (a level offset that leveling removes, as in
    :func:`crossover_comparison`).  Read as there — a crossover difference is the sum of two
    nearly independent line errors —, ``S_aa`` and ``S_bb`` are twice each estimate's mean
    square error and ``S_ab`` twice their covariance, and w is the linear combination with
    the least error (the minimum-variance weight of two correlated estimators), blind like
    every crossover measure to the error the crossing lines share.

    Parameters
    ----------
    diff_a_mgal, diff_b_mgal : array_like, shape (n,)
        The two estimates' differences at the same crossovers (mGal); pairs with a NaN are
        left out.

    Returns
    -------
    float
        w in [0, 1]; NaN with fewer than 3 finite pairs; 0 when the two sets of differences
        are equal (nothing to blend).
    """
    a = np.asarray(diff_a_mgal, dtype=float)
    b = np.asarray(diff_b_mgal, dtype=float)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"diff_a_mgal and diff_b_mgal must be 1-D of one length, got {a.shape} and {b.shape}")
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 3:
        return float("nan")
    a = a[ok] - a[ok].mean()
    b = b[ok] - b[ok].mean()
    s_aa, s_bb, s_ab = float(np.mean(a * a)), float(np.mean(b * b)), float(np.mean(a * b))
    den = s_aa + s_bb - 2.0 * s_ab   # = mean((a − b)²) ≥ 0
    if den <= 1e-12 * max(s_aa + s_bb, 1e-300):
        return 0.0
    return float(np.clip((s_bb - s_ab) / den, 0.0, 1.0))


def blend_estimates(a_mgal, b_mgal, std_b_mgal, weight_a: float) -> tuple[np.ndarray, np.ndarray]:
    """The blend ``w·a + (1 − w)·b`` of two estimates and its std.

    The std is that of the two-point mixture — a with probability w, b with 1 − w, each with
    b's std — by the law of total variance: ``sqrt(std_b² + w(1 − w)·(a − b)²)``.  Where a has
    no value (NaN) the blend is b with b's std.

    Parameters
    ----------
    a_mgal, b_mgal, std_b_mgal : array_like, shape (n,)
        The two estimates and b's posterior std (mGal).
    weight_a : float
        w in [0, 1] (e.g. :func:`crossover_blend_weight`).

    Returns
    -------
    (ndarray, ndarray)
        The blended estimate and its std, shape (n,), mGal.
    """
    a = np.asarray(a_mgal, dtype=float)
    b = np.asarray(b_mgal, dtype=float)
    sb = np.asarray(std_b_mgal, dtype=float)
    if not (a.shape == b.shape == sb.shape) or a.ndim != 1:
        raise ValueError(f"a_mgal, b_mgal and std_b_mgal must be 1-D of one length, got {a.shape}, {b.shape}, "
                         f"{sb.shape}")
    w = float(weight_a)
    if not 0.0 <= w <= 1.0:
        raise ValueError(f"blend weight must be in [0, 1], got {w}")
    d = np.where(np.isfinite(a), a - b, 0.0)
    return b + w * d, np.sqrt(sb ** 2 + w * (1.0 - w) * d ** 2)


def paired_rank_p(before, after) -> float:
    """One-sided Wilcoxon signed-rank test that ``after`` is lower than ``before``.

    Distribution-free: a few very large pairs (a heavy-tailed crossover error) weigh by
    their rank, not their size, so they neither make nor mask the result.

    Parameters
    ----------
    before, after : array_like, shape (n,)
        Paired values (e.g. crossover differences' magnitudes, mGal).

    Returns
    -------
    float
        p-value of "``before − after`` tends to be positive" (0.5 when every pair is tied;
        NaN below 2 pairs).
    """
    d = np.asarray(before, dtype=float) - np.asarray(after, dtype=float)
    d = d[np.isfinite(d)]
    if d.size < 2:
        return float("nan")
    if not np.any(d != 0):
        return 0.5
    return float(stats.wilcoxon(d, alternative="greater").pvalue)


def paired_decrease_p(before, after, n_eff: int | None = None) -> float:
    """One-sided paired t-test that ``after`` is lower than ``before`` on average.

    Parameters
    ----------
    before, after : array_like, shape (n,)
        Paired values (e.g. squared crossover differences, mGal²).
    n_eff : int, optional
        Independent pairs, when the n pairs are not (default n).

    Returns
    -------
    float
        p-value of ``mean(before − after) > 0`` (0.5 when every difference is equal).
    """
    d = np.asarray(before, dtype=float) - np.asarray(after, dtype=float)
    n = int(d.size if n_eff is None else n_eff)
    if d.size < 2 or n < 2:
        return float("nan")
    sd = float(np.std(d, ddof=1))
    if sd == 0:
        return 0.5
    return float(stats.t.sf(float(np.mean(d)) / (sd / np.sqrt(n)), n - 1))


@dataclass(frozen=True)
class CrossoverExcess:
    """Result of :func:`crossover_excess`.

    Attributes
    ----------
    n : int
        Crossovers used (finite difference and predicted variance).
    dof : float
        Degrees of freedom of the differences (n less the drift parameters removed).
    rms_ratio : float
        ``sqrt((Σ d² / dof) / mean(σ_a² + σ_b²))``: 1 when the crossovers show the error the
        std predicts (NaN without usable crossovers).
    p_value : float
        One-sided p of "the crossovers show more error than predicted": ``χ²_dof`` survival of
        ``Σ d² / mean(σ_a² + σ_b²)``.
    """

    n: int
    dof: float
    rms_ratio: float
    p_value: float


def crossover_excess(diff_mgal, pred_var_mgal2, dof: float | None = None) -> CrossoverExcess:
    """Do the crossover differences exceed what the lines' posterior std predicts?

    Two crossing lines' errors are nearly independent, so a difference has variance up to
    ``σ_a² + σ_b²`` (less the part of the error the lines share: the test is conservative).
    Under that variance ``Σ d² / mean(σ_a² + σ_b²)`` is about ``χ²`` with ``dof`` degrees of
    freedom (the differences' count less the parameters of a drift removed from them,
    :func:`app.core.leveling.drift_free_differences`).

    Parameters
    ----------
    diff_mgal : array_like, shape (n,)
        Crossover differences (mGal), a drift removed or not.
    pred_var_mgal2 : array_like, shape (n,)
        ``σ_a² + σ_b²`` at each crossover (mGal²).
    dof : float, optional
        Degrees of freedom (default: the usable differences' count).

    Returns
    -------
    CrossoverExcess
    """
    d = np.asarray(diff_mgal, dtype=float)
    v = np.asarray(pred_var_mgal2, dtype=float)
    if d.shape != v.shape or d.ndim != 1:
        raise ValueError(f"diff_mgal and pred_var_mgal2 must be 1-D of one shape, got {d.shape} and {v.shape}")
    ok = np.isfinite(d) & np.isfinite(v) & (v > 0)
    n = int(ok.sum())
    k = float(n if dof is None else min(float(dof), n))
    if n == 0 or not k > 0:
        return CrossoverExcess(n, k, float("nan"), float("nan"))
    t = float(np.sum(d[ok] ** 2) / np.mean(v[ok]))
    return CrossoverExcess(n, k, float(np.sqrt(t / k)), float(stats.chi2.sf(t, k)))


@dataclass(frozen=True)
class NoiseFloorFit:
    """Result of :func:`crossover_noise_floor`.

    Attributes
    ----------
    log2_weight : float
        log₂ of the floor's weight in the caller's unit: the least at which the crossovers show
        no more error than the std predicts (the search's upper bracket end).
    ratio : float
        The crossovers' RMS ratio there (≤ 1 when ``converged``).
    evaluations : dict
        ``{log2_weight: ratio}`` of every step of the search.
    converged : bool
        False when even ``log2_max`` left an excess (the floor is then ``log2_max``'s).
    """

    log2_weight: float
    ratio: float
    evaluations: dict
    converged: bool


def crossover_noise_floor(ratio_at, log2_start: float = -10.0, log2_max: float = 10.0, step: float = 2.0,
                          refine: int = 4) -> NoiseFloorFit:
    """The least white noise floor at which the crossovers agree with the posterior std.

    ``ratio_at(k)`` is the crossovers' RMS ratio (:attr:`CrossoverExcess.rms_ratio`) of the
    estimate smoothed with a floor of weight 2ᵏ (in the caller's unit) added to the noise
    model, over a threshold: 1 for the method-of-moments floor, or the ratio's critical value
    at a test level for the least floor at which the excess is no longer significant.  A floor
    both smooths more and widens the std, so the ratio falls as it rises; the root of
    ``ratio_at = 1`` is bracketed from ``log2_start`` up in steps of ``step`` and narrowed by
    ``refine`` bisections, and the bracket's upper end (``ratio_at ≤ 1``) is returned: the
    least floor the crossovers demand.

    Parameters
    ----------
    ratio_at : callable
        ``float → float`` (NaN is taken as "no excess").
    log2_start, log2_max, step : float
        The bracket's search in log₂ of the weight.
    refine : int
        Bisections of the bracket (its width ends at ``step / 2**refine``).

    Returns
    -------
    NoiseFloorFit
    """
    if not (step > 0 and log2_max >= log2_start and refine >= 0):
        raise ValueError(f"need step > 0, log2_max >= log2_start, refine >= 0; got {step}, {log2_start}, "
                         f"{log2_max}, {refine}")
    ev = {}

    def at(k: float) -> float:
        r = float(ratio_at(float(k)))
        ev[float(k)] = r
        return r

    lo, k = None, float(log2_start)
    while not at(k) <= 1.0 and not np.isnan(ev[k]):
        if k >= log2_max:
            return NoiseFloorFit(k, ev[k], ev, False)
        lo, k = k, min(k + step, float(log2_max))
    hi = k
    if lo is not None:
        for _ in range(refine):
            mid = 0.5 * (lo + hi)
            if at(mid) <= 1.0 or np.isnan(ev[mid]):
                hi = mid
            else:
                lo = mid
    return NoiseFloorFit(hi, ev[hi], ev, True)


@dataclass(frozen=True)
class CrossoverLevelScale:
    """Result of :func:`crossover_level_scale`.

    Attributes
    ----------
    scale : float
        The scale whose differences have the least mean square (1: none lower).
    p_value : float
        One-sided p of "its crossovers agree better than at scale 1" (paired t-test on the
        squared differences, :func:`paired_decrease_p`; NaN when the best is 1).
    rms_mgal : dict
        ``{scale: RMS of its differences}`` over the crossovers every scale has (mGal).
    """

    scale: float
    p_value: float
    rms_mgal: dict


def crossover_level_scale(diffs_by_scale: dict) -> CrossoverLevelScale:
    """Of estimates at several anomaly-level scales, the one whose crossover differences have
    the least mean square, and whether it agrees significantly better than scale 1.

    Parameters
    ----------
    diffs_by_scale : dict
        ``{scale: differences (mGal, shape (n,))}`` at the same n crossovers; must hold 1.0.

    Returns
    -------
    CrossoverLevelScale
    """
    if 1.0 not in diffs_by_scale:
        raise ValueError("diffs_by_scale must hold the estimate at scale 1")
    scales = sorted(diffs_by_scale)
    D = np.column_stack([np.asarray(diffs_by_scale[s], dtype=float) for s in scales])
    if D.ndim != 2:
        raise ValueError("every scale's differences must be 1-D of one length")
    D = D[np.all(np.isfinite(D), axis=1)]
    if D.shape[0] < 2:
        return CrossoverLevelScale(1.0, float("nan"), {})
    ms = np.mean(D ** 2, axis=0)
    rms = {float(s): float(np.sqrt(m)) for s, m in zip(scales, ms)}
    best = scales[int(np.argmin(ms))]
    if best == 1.0:
        return CrossoverLevelScale(1.0, float("nan"), rms)
    p = paired_decrease_p(D[:, scales.index(1.0)] ** 2, D[:, scales.index(best)] ** 2)
    return CrossoverLevelScale(float(best), p, rms)
