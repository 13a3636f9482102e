"""The anomaly measurement z_k (SPEC §1).

``z_k = f̄_k − (V_k − V_{k−1})/Δt − γ(φ_k, h_k) + E_k``

with ``f̄_k`` the gravimeter's specific force (lag and scale undone) averaged
over ``(t_{k−1}, t_k]``, ``V`` the GNSS vertical velocity (up), ``γ`` normal
gravity and ``E`` the Eötvös correction (positive flying east).  A gravimeter
at rest at a point of gravity g gives ``z = g − γ``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal, stats
from scipy.ndimage import maximum_filter1d, median_filter, uniform_filter1d

from app.core.epochs import run_bounds
from app.core.geodesy import MGAL_PER_MS2, vertical_velocity_from_heights_ms
from app.core.gravimeter import fill_nan


def gnss_acceleration_ms2(t_s, vu_ms) -> np.ndarray:
    """Mean vertical acceleration over each GNSS interval, ``(V_k − V_{k−1})/Δt_k`` (m/s²).

    Parameters
    ----------
    t_s, vu_ms : ndarray, shape (n,)

    Returns
    -------
    ndarray, shape (n,)
        First element NaN.
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(vu_ms, dtype=float)
    if t.shape != v.shape:
        raise ValueError("t_s and vu_ms must have the same shape")
    out = np.full(t.shape, np.nan)
    if t.size > 1:
        dt = np.diff(t)
        if np.any(dt <= 0):
            raise ValueError("GNSS epochs must be strictly increasing")
        out[1:] = np.diff(v) / dt
    return out


def cumulative_trapezoid(y, t_s) -> np.ndarray:
    """``∫ y dt`` from the first epoch to each (trapezoid rule), 0 at the first, shape (n,);
    units of y × s.  NaN propagates from where y has one."""
    y = np.asarray(y, dtype=float)
    return np.concatenate([[0.0], np.cumsum(0.5 * (y[1:] + y[:-1]) * np.diff(np.asarray(t_s, dtype=float)))])


def height_velocity_misfit_m(t_s, h_m, vu_ms) -> np.ndarray:
    """What the GNSS heights and vertical velocities of one stretch disagree on:
    ``d_k = h_k − h_0 − ∫_{t_0}^{t_k} vu dt`` (trapezoid rule), in m.

    The aircraft's motion cancels (``vu`` is ``dh/dt``), so ``d`` holds the two
    measurements' errors only: the height error, plus the *integral* of the velocity
    error.  Below ~0.02 Hz the integral dominates (a 1 cm/s white velocity error at 10 Hz
    wanders ~5 cm in 100 s, while height errors are a few cm), so ``d``'s spectrum shows
    the velocity error in the band where z cannot show it — there the anomaly is larger.

    Parameters
    ----------
    t_s, h_m, vu_ms : ndarray, shape (n,)
        NaN-free stretch, times strictly increasing (s, m, m/s).

    Returns
    -------
    ndarray, shape (n,)
        ``d`` (m), 0 at the first epoch.
    """
    t = np.asarray(t_s, dtype=float)
    h = np.asarray(h_m, dtype=float)
    v = np.asarray(vu_ms, dtype=float)
    if not (t.shape == h.shape == v.shape) or t.ndim != 1:
        raise ValueError("t_s, h_m and vu_ms must be 1-D arrays of one shape")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(h)) and np.all(np.isfinite(v))):
        raise ValueError("the stretch must be NaN-free")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        raise ValueError("GNSS epochs must be strictly increasing")
    return h - h[0] - cumulative_trapezoid(v, t)


def height_rate_ratio(t_s, h_m, vu_ms, window_s: float = 2.0,
                      min_rms_m: float = 0.1) -> tuple[float, float, int]:
    """How the GNSS heights move against the integral of the GNSS vertical velocity.

    Over consecutive windows of about ``window_s`` the height change ``Δh`` and the
    velocity's integral ``ΔI = ∫ vu dt`` (trapezoid rule) are the same motion when ``vu``
    is ``dh/dt``: the least-squares slope ``b = Σ Δh·ΔI / Σ ΔI²`` is 1 and the two are
    correlated almost perfectly wherever the aircraft moves vertically (climbs, descents,
    turbulence: metres, beside centimetres of GNSS error).  ``b ≈ −1`` says ``vu`` is
    positive *down* (a NED ``vd`` exported as ``vu``); ``b ≈ 3.281`` heights in feet beside
    a velocity in m/s, ``b ≈ 0.3048`` the reverse.  Windows that hold a record gap (a span
    over 1.5 × their nominal length) or a NaN are skipped.

    Parameters
    ----------
    t_s, h_m, vu_ms : ndarray, shape (n,)
        One GNSS record: times strictly increasing (s), heights (m, or whatever unit the
        file has), vertical velocity (m/s as the file says, up).
    window_s : float
        Window length (s).
    min_rms_m : float
        Below this RMS of ``ΔI`` (m) the record moves too little vertically to tell.

    Returns
    -------
    (float, float, int)
        ``b`` (dimensionless: height unit per metre of integrated velocity), the correlation
        coefficient of ``Δh`` and ``ΔI``, and the number of windows used; ``b`` and the
        correlation are NaN when fewer than 10 windows are usable or the motion is below
        ``min_rms_m``.
    """
    t = np.asarray(t_s, dtype=float)
    h = np.asarray(h_m, dtype=float)
    v = np.asarray(vu_ms, dtype=float)
    if not (t.shape == h.shape == v.shape) or t.ndim != 1:
        raise ValueError("t_s, h_m and vu_ms must be 1-D arrays of one shape")
    nan = (float("nan"), float("nan"), 0)
    if t.size < 4:
        return nan
    step = float(np.median(np.diff(t)))
    n = max(1, int(round(window_s / step)))
    integral = cumulative_trapezoid(v, t)
    i0 = np.arange(0, t.size - n, n)
    i1 = i0 + n
    dh = h[i1] - h[i0]
    di = integral[i1] - integral[i0]
    ok = (t[i1] - t[i0] <= 1.5 * n * step) & np.isfinite(dh) & np.isfinite(di)
    dh, di = dh[ok], di[ok]
    if dh.size < 10 or not np.sqrt(np.mean(di ** 2)) >= min_rms_m:
        return nan
    b = float(np.sum(dh * di) / np.sum(di ** 2))
    corr = float(np.corrcoef(dh, di)[0, 1])
    return b, corr, int(dh.size)


def anomaly_measurement_mgal(fbar_ms2, t_s, vu_ms, gamma_mgal, eotvos_mgal) -> np.ndarray:
    """Free-air anomaly measurement ``z_k`` at every GNSS epoch (mGal).

    Parameters
    ----------
    fbar_ms2 : ndarray, shape (n,)
        Gravimeter specific force (up, lag/scale undone) averaged over
        ``(t_{k−1}, t_k]`` (m/s²); NaN where unavailable.
    t_s : ndarray, shape (n,)
        GNSS epoch times (s).
    vu_ms : ndarray, shape (n,)
        GNSS vertical velocity (m/s, up).
    gamma_mgal : ndarray, shape (n,)
        Normal gravity at each epoch (mGal).
    eotvos_mgal : ndarray, shape (n,)
        Eötvös correction at each epoch (mGal).

    Returns
    -------
    ndarray, shape (n,)
        ``z`` in mGal; the first epoch is NaN (no previous velocity).
    """
    f = np.asarray(fbar_ms2, dtype=float)
    acc = gnss_acceleration_ms2(t_s, vu_ms)
    g = np.asarray(gamma_mgal, dtype=float)
    e = np.asarray(eotvos_mgal, dtype=float)
    if not (f.shape == acc.shape == g.shape == e.shape):
        raise ValueError("all inputs of anomaly_measurement_mgal must have the same shape")
    return (f - acc) * MGAL_PER_MS2 - g + e


def running_median_within_runs(x, valid, size: int) -> np.ndarray:
    """Centred running median of ``x`` over ``size`` samples, taken within each run of
    consecutive ``valid`` samples only (reflected at the run's ends); NaN outside the runs.

    A robust scale must not count what is not data: the spike detectors' scale once ran over
    a gap's interpolated samples (zero residual) or a window's zero fill, and near every gap
    it collapsed, so the first and last epochs of each run were flagged (generated clean
    surveys: every flag of the small layouts within 13 epochs of a run's end).

    Parameters
    ----------
    x : ndarray, shape (n,)
    valid : ndarray of bool, shape (n,)
    size : int
        Window length (samples, made odd).

    Returns
    -------
    ndarray, shape (n,)
    """
    x = np.asarray(x, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    if x.shape != valid.shape or x.ndim != 1:
        raise ValueError("x and valid must be one-dimensional and of the same shape")
    out = np.full(x.shape, np.nan)
    for a, b in run_bounds(valid):
        out[a:b] = median_filter(x[a:b], size=max(1, int(size)) | 1, mode="reflect")
    return out


def spike_mask(z_mgal, dt_s: float, threshold: float = 6.0, neighbour_s: float = 0.5,
               scale_s: tuple[float, float] = (5.0, 30.0)) -> np.ndarray:
    """Epochs of z hit by isolated outliers (GNSS velocity or height spikes, cycle slips,
    gravimeter glitches).

    A spike of size A in one GNSS velocity ``V_j`` puts a doublet ``+A/Δt, −A/Δt`` into
    ``z_j, z_{j+1}`` (a height spike a triplet); a gravimeter glitch one sample.  Each
    epoch's residual from the mean of its neighbours (``±max(2, neighbour_s/Δt)`` samples,
    itself excluded) is compared with the local robust scale (1.4826 × running median of
    |residual|); an epoch beyond ``threshold`` scales is flagged, and so is a neighbour
    beyond half of it (the doublet's partner).  The scale is the larger of a short-window
    one (follows the noise level when it jumps at a noisy episode) and a long-window one.

    The neighbour mean, not a running median, is the reference: at 1–2 Hz the noise of z
    is dominated by turbulence at a few samples per period, and the residual from a
    3-sample median is exactly zero on every monotone triple, so its median — the scale —
    collapses and a third of a clean record was flagged.  Gaussian noise is flagged at 6
    scales with probability ~10⁻⁸ per epoch.

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
        The measurement (mGal); NaN is never flagged.
    dt_s : float
        GNSS step (s).
    threshold : float
        Flag level in robust standard deviations.
    neighbour_s : float
        Half-width (s) of the neighbourhood whose mean is the reference (at least 2 samples).
    scale_s : (float, float)
        Short and long windows (s) of the robust scale.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    z = np.asarray(z_mgal, dtype=float)
    if z.ndim != 1:
        raise ValueError("z_mgal must be one-dimensional")
    if not dt_s > 0 or not threshold > 0:
        raise ValueError("dt_s and threshold must be positive")
    ok = np.isfinite(z)
    mask = np.zeros(z.shape, bool)
    if ok.sum() < 16:
        return mask
    zi = np.interp(np.arange(z.size), np.flatnonzero(ok), z[ok]) if not ok.all() else z
    h = max(2, int(round(neighbour_s / dt_s)))
    w = 2 * h + 1
    local = (uniform_filter1d(zi, w, mode="reflect") * w - zi) / (w - 1)
    ar = np.abs(zi - local)
    scale = 1.4826 * np.maximum(*(running_median_within_runs(ar, ok, max(2 * w + 1, int(round(s / dt_s)) | 1))
                                  for s in scale_s))
    scale = np.where(ok, np.maximum(scale, 1e-12 + 1e-9 * np.nanmedian(scale)), np.inf)
    big = ar > threshold * scale
    half = ar > 0.5 * threshold * scale
    partner = np.zeros_like(big)
    partner[1:] |= big[:-1]
    partner[:-1] |= big[1:]
    mask = (big | (partner & half)) & ok
    return mask


def repair_spikes(z_mgal, mask) -> np.ndarray:
    """Remove flagged outliers from z without disturbing its low frequencies.

    z is a difference of velocities, so the sum of z over a run of epochs telescopes to
    the velocity change across the run: a velocity spike adds ``+A/Δt`` and ``−A/Δt``
    that cancel in the sum.  Each flagged run, widened by one epoch on either side, is
    replaced by its own mean: the sum is kept exactly (the low frequencies — everything
    the anomaly lives in — are untouched) and the doublet is gone.  Dropping or
    interpolating epochs instead would change the sum: an error of ~A/n in every
    n-epoch average, tens of mGal for one spike.

    Where ``vu`` was derived from the heights a flag is a height spike or step seen
    through the spline, which rings over several epochs: use
    :func:`repair_height_outliers` there (replacing only the flagged core by its mean
    leaves the ringing's tails unbalanced: 10 spikes of 20 cm in a 2 Hz heights-only
    record put 3.5 mGal RMS into the FIR 100 s column that way).

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
    mask : ndarray of bool, shape (n,)
        From :func:`spike_mask`.

    Returns
    -------
    ndarray, shape (n,)
        Repaired copy of z (NaN stays NaN).
    """
    z = np.array(z_mgal, dtype=float)
    mk = np.asarray(mask, dtype=bool)
    if mk.shape != z.shape:
        raise ValueError("mask and z_mgal must have the same shape")
    if not mk.any():
        return z
    wide = mk.copy()
    wide[1:] |= mk[:-1]
    wide[:-1] |= mk[1:]
    d = np.diff(np.concatenate([[0], wide.astype(np.int8), [0]]))
    for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
        seg = z[a:b]
        ok = np.isfinite(seg)
        if ok.any():
            seg[ok] = seg[ok].mean()
    return z


def height_outlier_templates_mgal(t_s, j: int, half_width: int = 16):
    """z's response (mGal per metre) to a unit spike and to a unit step in the heights at
    epoch ``j``, where ``vu`` is the derivative of the not-a-knot spline through h
    (:func:`app.core.geodesy.vertical_velocity_from_heights_ms`).

    The spline is taken over ``±half_width`` epochs of the contiguous stretch around ``j``
    (steps above 1.5 × the median step end it): the spline's response to one value decays
    by about ``2 − √3`` per knot, so the window's own ends barely reach ``j`` — against the
    whole record's spline, ±8 epochs left 1.4·10⁻³ of the peak (0.26 mGal RMS at 100 s for a
    25 cm spike), ±16 epochs 4·10⁻⁸.  ``dz_k = −(dV_k − dV_{k−1})/Δt_k`` (SPEC §1).

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        GNSS times (s), increasing.
    j : int
        The epoch of the spike (h_j alone is off) or of the step's first offset epoch
        (h_k is off for every k ≥ j).
    half_width : int
        Epochs on either side of ``j`` over which the spline is formed (≥ 2).

    Returns
    -------
    (idx, spike, step) : ndarray of int, shape (w,), and two ndarrays of shape (w,)
        The epochs of z that the outlier reaches and the two templates there (mGal per m).
        Empty when the stretch around ``j`` has fewer than 4 epochs.
    """
    t = np.asarray(t_s, dtype=float)
    n = t.size
    if not 0 <= j < n:
        raise ValueError(f"epoch {j} outside 0..{n - 1}")
    if half_width < 2:
        raise ValueError("half_width must be at least 2")
    dt = np.diff(t)
    gap = dt > 1.5 * float(np.median(dt)) if dt.size else np.zeros(0, bool)
    a = j
    while a > 0 and j - a < half_width and not gap[a - 1]:
        a -= 1
    b = j + 1
    while b < n and b - 1 - j < half_width and not gap[b - 1]:
        b += 1
    if b - a < 4:
        return np.zeros(0, int), np.zeros(0), np.zeros(0)
    out = []
    for e in (np.eye(b - a)[j - a], (np.arange(a, b) >= j).astype(float)):
        dv = vertical_velocity_from_heights_ms(t[a:b], e)          # the pipeline's own vu from h
        out.append(-gnss_acceleration_ms2(t[a:b], dv)[1:] * MGAL_PER_MS2)
    return np.arange(a + 1, b), out[0], out[1]


def repair_height_outliers(z_mgal, t_s, mask, half_width: int = 16, search: int = 2, step_sizes_m=None):
    """Remove height spikes and steps from z where ``vu`` was derived from the heights.

    A flagged cluster of epochs (flags at most ``search`` + 1 apart) is explained by the
    best of two outliers in h — a spike (one height off) or a step (every later height
    off, a cycle slip) — at an epoch within ``search`` of the cluster: for each candidate
    the size (m) is fitted by least squares to z over the template's epochs together with
    a constant (:func:`height_outlier_templates_mgal`), and the candidate that leaves the
    smallest residual is subtracted.  Unlike replacing the flagged epochs by their mean
    (:func:`repair_spikes`), this removes the spline's ringing around them too and keeps
    what the rest of z has in the window — the noise's own sum and first moment, which a
    low-pass turns into mGal.

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
    t_s : ndarray, shape (n,)
        GNSS times (s).
    mask : ndarray of bool, shape (n,)
        From :func:`spike_mask`.
    half_width, search : int
        Template half-width and the candidate epochs searched on either side (epochs).
    step_sizes_m : ndarray, shape (n,), optional
        Where finite, :func:`height_step_sizes_m` at epochs where only z's double integral saw a
        step (:func:`height_step_mask`): a cluster reaching such an epoch is that step, at the
        epoch of the largest size and of that size — the templates' fit to z, which z's blue
        noise scatters, called such steps spikes of 0.10–0.17 m (generated 2 Hz test lines,
        0.2–0.3 m steps, 11–17 mGal left in the 100 s low-pass).

    Returns
    -------
    (z, fixes) : ndarray, shape (n,), and list of dict
        The repaired copy of z (NaN stays NaN) and per cluster ``{"epoch", "kind"
        ('spike' or 'step'), "size_m"}``; a cluster whose window holds NaN or no
        template is left as it is (``kind`` None).
    """
    z = np.array(z_mgal, dtype=float)
    t = np.asarray(t_s, dtype=float)
    mk = np.asarray(mask, dtype=bool)
    if mk.shape != z.shape or t.shape != z.shape:
        raise ValueError("z_mgal, t_s and mask must have the same shape")
    flags = np.flatnonzero(mk)
    fixes: list[dict] = []
    if flags.size == 0:
        return z, fixes
    clusters = np.split(flags, np.flatnonzero(np.diff(flags) > search + 1) + 1)
    sizes = np.full(z.size, np.nan) if step_sizes_m is None else np.asarray(step_sizes_m, dtype=float)
    for cl in clusters:
        cand = np.arange(max(0, cl[0] - search), min(z.size, cl[-1] + search + 1))
        seen = cand[np.isfinite(sizes[cand])]
        if seen.size:   # a step its double integral saw and sized
            j = int(seen[np.argmax(np.abs(sizes[seen]))])
            idx, _spike, step = height_outlier_templates_mgal(t, j, half_width)
            if idx.size and np.all(np.isfinite(z[idx])):
                size = float(sizes[j])
                z[idx] -= size * step
                fixes.append({"epoch": j, "kind": "step", "size_m": size})
                continue
        best = None
        for j in range(max(0, cl[0] - search), min(z.size, cl[-1] + search + 1)):
            idx, spike, step = height_outlier_templates_mgal(t, j, half_width)
            if idx.size == 0 or not np.all(np.isfinite(z[idx])):
                continue
            y = z[idx]
            for kind, tpl in (("spike", spike), ("step", step)):
                X = np.column_stack([tpl, np.ones_like(tpl)])
                coef, *_ = np.linalg.lstsq(X, y, rcond=None)
                ss = float(np.sum((y - X @ coef) ** 2))
                # residual per epoch: windows shortened by a gap compare fairly
                score = ss / idx.size
                if best is None or score < best[0]:
                    best = (score, j, kind, float(coef[0]), idx, tpl)
        if best is None:
            fixes.append({"epoch": int(cl[0]), "kind": None, "size_m": None})
            continue
        _, j, kind, size, idx, tpl = best
        z[idx] -= size * tpl
        fixes.append({"epoch": int(j), "kind": kind, "size_m": size})
    return z, fixes


def height_outlier_mask(z_mgal, t_s, threshold: float = 6.0, half_width: int = 16,
                        scale_s: tuple[float, float] = (10.0, 60.0), search: int = 2) -> np.ndarray:
    """Epochs of z hit by a height spike or step, where ``vu`` was derived from the heights.

    Through the spline such an outlier is a pattern of ~12 epochs, not an isolated value:
    :func:`spike_mask`'s local scale, taken over a window the pattern fills, rises with it
    (ten 50 cm spikes in a 2 Hz heights-only record: none flagged).  Here z is correlated with
    the two patterns (:func:`height_outlier_templates_mgal` on the median step), giving at
    each epoch the least-squares size of a spike and of a step there; an epoch is flagged
    where either size exceeds ``threshold`` robust scales of its own series (1.4826 × the
    running median of its magnitude, the larger of the two windows ``scale_s``) and is the
    largest within ±``search`` epochs.  Only epochs whose whole window is finite are tested.
    The patterns sum to zero, so z's level does not matter.

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
    t_s : ndarray, shape (n,)
        GNSS times (s), increasing.
    threshold : float
        Flag level in robust scales.
    half_width, search : int
        Pattern half-width and local-maximum neighbourhood (epochs).
    scale_s : (float, float)
        Windows (s) of the robust scale.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    z = np.asarray(z_mgal, dtype=float)
    t = np.asarray(t_s, dtype=float)
    if z.ndim != 1 or t.shape != z.shape:
        raise ValueError("z_mgal and t_s must be one-dimensional and of the same shape")
    if not threshold > 0:
        raise ValueError("threshold must be positive")
    mask = np.zeros(z.shape, bool)
    if z.size < 4 * half_width + 2:
        return mask
    dt = float(np.median(np.diff(t)))
    idx, spike, step = height_outlier_templates_mgal(np.arange(2 * half_width + 1) * dt, half_width, half_width)
    off = idx - half_width                                   # z epochs relative to the outlier's
    ok = np.isfinite(z)
    zi = np.where(ok, z, 0.0)
    n = z.size

    def shifted(x, o, fill):
        """x[j + o] at every j (``fill`` beyond the ends)."""
        y = np.full(n, fill, dtype=x.dtype)
        if o >= 0:
            y[:n - o] = x[o:]
        else:
            y[-o:] = x[:n + o]
        return y

    full = np.ones(n, bool)
    for o in off:
        full &= shifted(ok, int(o), False)
    for tpl in (spike, step):
        w = tpl / np.sum(tpl ** 2)
        size = np.zeros(n)                                   # least-squares size at each epoch (m)
        for o, wk in zip(off, w):
            size += wk * shifted(zi, int(o), 0.0)
        a = np.where(full, np.abs(size), 0.0)
        scale = 1.4826 * np.maximum(*(running_median_within_runs(a, full, max(3, int(round(s / dt))) | 1)
                                      for s in scale_s))
        scale = np.where(full, np.maximum(scale, 1e-12 + 1e-9 * float(np.nanmedian(scale))), np.inf)
        big = a > threshold * scale
        mask |= big & (a >= maximum_filter1d(a, 2 * search + 1)) & full
    return mask


def gravimeter_height_misfit_m(t_s, gravimeter_m, h_m, gamma_mgal, eotvos_mgal) -> np.ndarray:
    """``S = ∫∫ (f_g − γ + E) dt² − h`` at the GNSS epochs (m): the gravimeter's double
    integral less the GNSS heights, the limit of z's double integral without its sampling.

    The aircraft's motion cancels, so ``S`` is the twice-integrated anomaly, drift and
    initial velocity (smooth) plus the heights' error, the gravimeter's noise twice
    integrated and the lag's and scale's errors (``Δτ·vu``, ``Δk·h``).  A step of the
    heights (a cycle slip) is a step of ``S``.  ``γ − E`` is integrated by the trapezoid rule
    (smooth at the epochs' spacing).

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        GNSS times (s), increasing.
    gravimeter_m : ndarray, shape (n,)
        ``∫∫ f_g dt²`` at the epochs (m; :func:`app.core.gravimeter.double_integral_m`), NaN
        where unknown.
    h_m, gamma_mgal, eotvos_mgal : ndarray, shape (n,)
        GNSS heights (m), normal gravity and Eötvös correction (mGal).

    Returns
    -------
    ndarray, shape (n,)
        ``S`` (m, up to a constant); NaN where an input is.
    """
    t = np.asarray(t_s, dtype=float)
    ff = np.asarray(gravimeter_m, dtype=float)
    h = np.asarray(h_m, dtype=float)
    c = (np.asarray(gamma_mgal, dtype=float) - np.asarray(eotvos_mgal, dtype=float)) / MGAL_PER_MS2
    if t.ndim != 1 or not (t.shape == ff.shape == h.shape == c.shape):
        raise ValueError("all inputs of gravimeter_height_misfit_m must be 1-D and of one shape")
    if t.size < 2:
        return ff - h
    c = fill_nan(c) if np.isfinite(c).any() else c
    c2 = cumulative_trapezoid(cumulative_trapezoid(c, t), t)
    return ff - c2 - h


def height_step_sizes_m(z_mgal, t_s, window_s: float = 10.0, misfit_m=None) -> np.ndarray:
    """Least-squares size (m) of a step in the heights at each epoch, seen in the double integral
    of z, where ``vu`` was derived from the heights.

    z = f − ḧ − γ + …, so S = ∫∫ z dt² is the gravimeter's double integral less h, plus a
    smooth part (the anomaly, drift and γ twice integrated).  A step of the heights at epoch j
    (h_k off by s for every k ≥ j: a cycle slip) is a step of −s in S, whatever the spline did
    to z around it.  Integrating twice whitens z's noise, which rises as f⁴ below ~0.3 Hz on a
    turbulent record (docs: the real 2 Hz line), where the matched templates of
    :func:`height_outlier_mask` meet it at its largest.  Over ±``window_s`` (at least 4 epochs)
    around each epoch S is fitted by a quadratic plus a step between j − 1 and j; the step's
    coefficient, sign reversed, is the size.  Each contiguous finite run of z is integrated on
    its own; epochs whose window leaves the run are NaN.

    Given ``misfit_m`` (:func:`gravimeter_height_misfit_m`, S formed from the gravimeter's own
    samples), that is fitted instead, on the same runs.  Summing z over 1 s epochs misses the
    double integral by half an epoch times the spline velocity's error: on generated 1 Hz
    heights-only flights the sizes' robust scale on the lines was 4–7 cm from z, 1 cm from
    the gravimeter (0.7–0.8 cm against 5 Hz GNSS, 1.5 cm on the 2 Hz test lines, whose
    gravimeter samples at 2 Hz).

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
    t_s : ndarray, shape (n,)
        GNSS times (s), increasing.
    window_s : float
        Half-width of the fit (s).
    misfit_m : ndarray, shape (n,), optional
        S at the epochs (m); NaN where unknown.

    Returns
    -------
    ndarray, shape (n,)
        Step size at each epoch (m, positive: the heights stepped up); NaN where not fitted.
    """
    z = np.asarray(z_mgal, dtype=float)
    t = np.asarray(t_s, dtype=float)
    if z.ndim != 1 or t.shape != z.shape:
        raise ValueError("z_mgal and t_s must be one-dimensional and of the same shape")
    out = np.full(z.shape, np.nan)
    if z.size < 9:
        return out
    dt = float(np.median(np.diff(t)))
    w = max(4, int(round(window_s / dt)))
    k = np.arange(-w, w + 1, dtype=float)
    design = np.column_stack([np.ones_like(k), k, k ** 2, (k >= 0).astype(float)])
    row = np.linalg.pinv(design)[3]
    ok = np.isfinite(z)
    if misfit_m is not None:
        misfit = np.asarray(misfit_m, dtype=float)
        if misfit.shape != z.shape:
            raise ValueError("misfit_m must have the shape of z_mgal")
        ok &= np.isfinite(misfit)
    edges = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)):
        if b - a < 2 * w + 1:
            continue
        if misfit_m is None:
            s2 = np.cumsum(np.cumsum(z[a:b] / MGAL_PER_MS2) * dt) * dt        # m
        else:
            s2 = misfit[a:b] - misfit[a]
        out[a + w:b - w] = -(np.lib.stride_tricks.sliding_window_view(s2, 2 * w + 1) @ row)
    return out


def height_step_mask(z_mgal, t_s, threshold: float = 8.0, window_s: float = 10.0,
                     scale_s: float = 120.0, sizes_m=None) -> np.ndarray:
    """Epochs where the heights step, from :func:`height_step_sizes_m`.

    An epoch is flagged where the size exceeds ``threshold`` robust scales (1.4826 × the
    running median of the sizes' magnitude over ``scale_s``) and is the largest within the
    fit's half-width (a large step's fit leaves side lobes at ±``window_s``).  Generated
    heights-only surveys (1, 2 and 5 Hz, seeds 1–3, every flight), sizes from z's own double
    integral: on the lines clean records reach 4.5 scales (8.8 once, outside the lines at
    1 Hz); steps of 0.2–0.5 m reach 6–60 at 2–5 Hz, 3–32 at 1 Hz.  Sizes from the gravimeter's
    double integral (``misfit_m`` of :func:`height_step_sizes_m`; 1 Hz seeds 1–9 too): clean
    records reach 5.7 scales anywhere in a flight, a 0.2 m step 13–25 (scales of 1.0–1.5 cm).

    Parameters
    ----------
    z_mgal, t_s : ndarray, shape (n,)
    threshold : float
        Flag level in robust scales.
    window_s, scale_s : float
        The fit's half-width and the scale's window (s).
    sizes_m : ndarray, shape (n,), optional
        :func:`height_step_sizes_m` of z at ``window_s``, when already computed.

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    if not threshold > 0:
        raise ValueError("threshold must be positive")
    t = np.asarray(t_s, dtype=float)
    size = np.abs(height_step_sizes_m(z_mgal, t, window_s) if sizes_m is None else np.asarray(sizes_m, float))
    mask = np.zeros(size.shape, bool)
    fin = np.isfinite(size)
    if not fin.any():
        return mask
    dt = float(np.median(np.diff(t)))
    filled = np.where(fin, size, np.median(size[fin]))
    scale = 1.4826 * median_filter(filled, size=max(3, int(scale_s / dt) | 1), mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(fin & (scale > 0), filled / scale, 0.0)
    w = max(4, int(round(window_s / dt)))
    return (r >= threshold) & (r >= maximum_filter1d(r, 2 * w + 1))


def response_prediction_mgal(z_mgal, a_ms2, lags: int = 5) -> np.ndarray:
    """z predicted from the GNSS vertical acceleration alone (mGal, shape (n,)).

    z holds the aircraft's accelerations as the gravimeter and the GNSS disagree on them (the
    two instruments' responses differ): a part of z linear in the acceleration.  It is fitted by
    least squares, ``z_k ≈ c₀ + Σ_{l=−L..L} c_l a_{k+l}``, over the epochs where z and every lag
    are finite, and returned at every epoch whose lags are finite (NaN elsewhere).  Where z is
    missing (a hole in the gravimeter record) the prediction stands in for it, off by the part
    of z the acceleration does not explain (the 2 Hz test line: 4,700 of 13,800 mGal RMS).

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
        The measurement (NaN = missing).
    a_ms2 : ndarray, shape (n,)
        GNSS vertical acceleration (:func:`gnss_acceleration_ms2`).
    lags : int
        L (epochs each side).
    """
    z = np.asarray(z_mgal, dtype=float)
    a = np.asarray(a_ms2, dtype=float) * 1e5
    if z.shape != a.shape or z.ndim != 1:
        raise ValueError("z_mgal and a_ms2 must be 1-D of the same shape")
    n, L = z.size, int(lags)
    out = np.full(n, np.nan)
    if n <= 2 * L + 2:
        return out
    k = np.arange(L, n - L)
    X = np.column_stack([a[k + l] for l in range(-L, L + 1)] + [np.ones(k.size)])
    rows = np.all(np.isfinite(X), axis=1)
    fit = rows & np.isfinite(z[k])
    if fit.sum() < 10 * X.shape[1]:
        return out
    c, *_ = np.linalg.lstsq(X[fit], z[k][fit], rcond=None)
    out[k[rows]] = X[rows] @ c
    return out


@dataclass(frozen=True)
class BandDelay:
    """Result of :func:`band_delay_fit`.

    Attributes
    ----------
    delay_s : float
        The gravimeter's residual delay behind the GNSS at the band's frequencies (s; positive:
        the gravimeter late), ``z_band ≈ −delay_s · ȧ_band``.
    se_s : float
        Its standard error (s), from ``n_independent`` independent samples of the residual.
    t_stat : float
        ``delay_s / se_s``.
    n_independent : float
        ``2·B·T``: B the band's width (Hz), T the duration fitted (s).
    band_rms_mgal, band_rms_corrected_mgal : float
        RMS of z in the band before and after the delay is taken out (mGal).
    n_epochs : int
        Epochs fitted.
    """

    delay_s: float
    se_s: float
    t_stat: float
    n_independent: float
    band_rms_mgal: float
    band_rms_corrected_mgal: float
    n_epochs: int


def band_delay_fit(segments, dt_s: float | None, band_hz: tuple[float, float],
                   gap_margin_s: float = 100.0) -> BandDelay:
    """The timing error left between z and the GNSS acceleration at the anomaly's edge.

    A time offset or lag fitted over a broad band (where the aircraft's turbulence rules) is
    that band's best single delay; an instrument whose response is not a pure lag and shift
    (an anti-alias filter, a platform's loop) keeps a residual delay at the lowest frequencies
    of the motion, and the phugoid (periods of 20–90 s, 10⁴ mGal of vertical acceleration)
    turns a few milliseconds of it into tens of mGal in z just above the FIR cut-off.  A
    gravimeter late by d puts ``a(t − d) − a(t) ≈ −d·ȧ(t)`` into z, so d is the least-squares
    coefficient of z's band on the GNSS jerk's band, ``d = −Σ z_b ȧ_b / Σ ȧ_b²``.  The jerk is
    in quadrature with the acceleration, so an anomaly that follows the flight path (a draped
    flight: the anomaly and the acceleration both follow the terrain) does not bias it.

    Parameters
    ----------
    segments : sequence of (t_s, z_mgal, a_mgal, usable)
        Records on a uniform step each (one per flight, or per run of a flight): epoch times
        (s), z (mGal, NaN where missing), the GNSS vertical acceleration (mGal, NaN where
        missing) and the epochs that may be fitted (bool; the lines).  Each record is
        band-passed whole (zero-phase Butterworth of order 4, NaNs bridged linearly); epochs
        within ``gap_margin_s`` of a bridged NaN or of the record's ends are left out.
    dt_s : float or None
        The records' time step (s); None: each record's own (the median step of its times —
        flights logged at different rates).
    band_hz : (float, float)
        The band fitted (Hz), ``0 < f1 < f2 <`` Nyquist (a record whose own Nyquist frequency
        is not above f2 is left out).
    gap_margin_s : float
        Margin (s) left out around gaps and ends.

    Returns
    -------
    BandDelay
        NaN figures when fewer than ``10/(f2 − f1)`` s are usable.
    """
    f1, f2 = (float(x) for x in band_hz)
    if dt_s is not None:
        if not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be positive, got {dt_s!r}")
        if not 0 < f1 < f2 < 0.5 / dt_s:
            raise ValueError(f"band {band_hz} must satisfy 0 < f1 < f2 < Nyquist ({0.5 / dt_s:g} Hz)")
    elif not 0 < f1 < f2:
        raise ValueError(f"band {band_hz} must satisfy 0 < f1 < f2")
    zs, js, duration = [], [], 0.0
    for t, z, a, usable in segments:
        t, z, a = (np.asarray(x, dtype=float) for x in (t, z, a))
        use = np.asarray(usable, dtype=bool).copy()
        if not (t.shape == z.shape == a.shape == use.shape) or t.ndim != 1:
            raise ValueError("each segment's t_s, z_mgal, a_mgal and usable must be 1-D of one length")
        step = float(dt_s) if dt_s is not None else (float(np.median(np.diff(t))) if t.size > 1 else float("nan"))
        if not (np.isfinite(step) and step > 0 and f2 < 0.5 / step):
            continue
        margin = int(round(gap_margin_s / step))
        if t.size <= 2 * margin + 12 or np.isfinite(z).sum() < 2 or np.isfinite(a).sum() < 2:
            continue
        bad = ~(np.isfinite(z) & np.isfinite(a))
        if bad.any():
            use &= np.convolve(bad.astype(float), np.ones(2 * margin + 1), mode="same") == 0
        use[:margin] = use[-margin:] = False
        if not use.any():
            continue
        sos = signal.butter(4, (f1, f2), btype="bandpass", fs=1.0 / step, output="sos")
        zb = signal.sosfiltfilt(sos, fill_nan(z) - np.nanmean(z))   # a uniform record: by index is by time
        ab = signal.sosfiltfilt(sos, fill_nan(a) - np.nanmean(a))
        zs.append(zb[use])
        js.append(np.gradient(ab, step)[use])
        duration += float(use.sum()) * step
    n = int(sum(x.size for x in zs))
    nan = BandDelay(*(float("nan"),) * 6, n)
    if duration < 10.0 / (f2 - f1):
        return nan
    zb, jb = np.concatenate(zs), np.concatenate(js)
    sjj = float(np.dot(jb, jb))
    if not sjj > 0:
        return nan
    c = float(np.dot(zb, jb) / sjj)
    res = zb - c * jb
    n_ind = 2.0 * (f2 - f1) * duration
    se = float(np.sqrt(np.mean(res ** 2) / (np.mean(jb ** 2) * n_ind)))
    return BandDelay(-c, se, -c / se if se > 0 else float("nan"), n_ind,
                     float(np.sqrt(np.mean(zb ** 2))), float(np.sqrt(np.mean(res ** 2))), n)


def delay_heterogeneity(delays_s, se_s) -> dict:
    """Do several independent estimates of one delay disagree by more than their errors?

    Cochran's test: with the inverse-variance mean ``d̄ = Σ wᵢdᵢ / Σ wᵢ`` (``wᵢ = 1/seᵢ²``),
    ``χ² = Σ wᵢ(dᵢ − d̄)²`` has k − 1 degrees of freedom when the k estimates share one true
    value.  Estimates that are not finite (a flight too short to fit) are left out.

    Parameters
    ----------
    delays_s, se_s : array_like, shape (k,)
        The estimates and their standard errors (s; any unit, the same for both).

    Returns
    -------
    dict
        ``mean_s`` (d̄), ``chi2``, ``dof`` (k − 1 over the usable estimates) and ``p_value``
        (``P(χ²_dof ≥ chi2)``); with fewer than two usable estimates ``dof`` is 0 and the
        figures NaN.
    """
    d = np.asarray(delays_s, dtype=float)
    se = np.asarray(se_s, dtype=float)
    if d.shape != se.shape or d.ndim != 1:
        raise ValueError("delays_s and se_s must be 1-D of one length")
    ok = np.isfinite(d) & np.isfinite(se) & (se > 0)
    if ok.sum() < 2:
        return {"mean_s": float("nan"), "chi2": float("nan"), "dof": 0, "p_value": float("nan")}
    w = 1.0 / se[ok] ** 2
    mean = float(np.sum(w * d[ok]) / np.sum(w))
    chi2 = float(np.sum(w * (d[ok] - mean) ** 2))
    dof = int(ok.sum()) - 1
    return {"mean_s": mean, "chi2": chi2, "dof": dof, "p_value": float(stats.chi2.sf(chi2, dof))}


def delay_correction_mgal(t_s, a_mgal, delay_s: float, lowpass_hz: float) -> np.ndarray:
    """What a residual delay d puts into z below ``lowpass_hz``: ``−d·ȧ`` of the GNSS
    acceleration low-passed (zero-phase Butterworth of order 4), mGal, shape (n,).  Subtracted
    from z it takes the delay out there and leaves z above ``lowpass_hz`` (the broad-band
    offset fit's) as it was.  NaN where ``a_mgal`` is."""
    t = np.asarray(t_s, dtype=float)
    a = np.asarray(a_mgal, dtype=float)
    if t.shape != a.shape or t.ndim != 1:
        raise ValueError("t_s and a_mgal must be 1-D of one length")
    dt = float(np.median(np.diff(t))) if t.size > 1 else float("nan")
    if not (np.isfinite(dt) and dt > 0 and 0 < lowpass_hz < 0.5 / dt):
        raise ValueError(f"lowpass_hz {lowpass_hz!r} must lie below the Nyquist frequency of a uniform record")
    if t.size < 13 or not np.isfinite(a).any():
        return np.where(np.isfinite(a), 0.0, np.nan)
    sos = signal.butter(4, lowpass_hz, btype="lowpass", fs=1.0 / dt, output="sos")
    al = signal.sosfiltfilt(sos, fill_nan(a))   # a uniform record: by index is by time
    out = -float(delay_s) * np.gradient(al, t)
    out[~np.isfinite(a)] = np.nan
    return out
