"""Accuracy measures of a survey (SPEC §3 "Accuracy", seeds 001 and 004).

- crossover RMS of the differences at line intersections;
- repeat-line internal accuracy ``ε = sqrt(Σ_i Σ_j (g_ij − ḡ_j)² / (n (K−1)))``
  over K repeats of one track at n common points; which passes fly one track
  (:func:`same_track`, :func:`group_passes`); the parts of an estimate's error the repeats
  show (:func:`repeat_error_parts`), each repeat's own noise (:func:`repeat_pass_noise_var`, over its posterior:
  :func:`repeat_pass_noise_ratio`), whether it exceeds a posterior std
  (:func:`noise_excess_p_value`) and each repeat's std factor (:func:`repeat_pass_std_scales`);
- RMS (optionally with each line's mean removed) and mean error against a reference,
  std calibration (fraction of errors within k σ);
- grid RMS (and demeaned RMS, std calibration) against a true grid inside the convex
  hull of the lines.

All values in mGal, coordinates in km.  Pure functions on numpy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, Delaunay
from scipy.stats import chi2
from scipy.stats import f as f_dist


def crossover_rms(diff_mgal) -> float:
    """RMS of crossover differences (mGal); NaNs ignored.

    The error of one line value is ``crossover_rms / √2`` if both lines are
    equally accurate and independent.

    Raises
    ------
    ValueError
        No finite difference.
    """
    d = np.asarray(diff_mgal, dtype=float).ravel()
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise ValueError("no crossover differences")
    return float(np.sqrt(np.mean(d ** 2)))


def internal_accuracy(values_mgal) -> float:
    """Repeat-line internal accuracy from values at common points.

    ``ε = sqrt(Σ_i Σ_j (g_ij − ḡ_j)² / (n (K−1)))`` with i over the K repeats and
    j over the n common points, ``ḡ_j`` the mean of the repeats at point j.

    Parameters
    ----------
    values_mgal : array_like, shape (K, n)
        K ≥ 2 repeats at n ≥ 1 common points.

    Returns
    -------
    float
        ε (mGal): the std of one repeat's error.
    """
    g = np.asarray(values_mgal, dtype=float)
    if g.ndim != 2 or g.shape[0] < 2 or g.shape[1] < 1:
        raise ValueError(f"need an array of shape (K ≥ 2, n ≥ 1), got {g.shape}")
    if not np.all(np.isfinite(g)):
        raise ValueError("repeat values must be finite")
    k, n = g.shape
    return float(np.sqrt(np.sum((g - g.mean(axis=0)) ** 2) / (n * (k - 1))))


@dataclass(frozen=True)
class RepeatErrorParts:
    """Result of :func:`repeat_error_parts` (mGal², per repeat).

    Attributes
    ----------
    noise_var_mgal2 : float
        Variance of one repeat's error that differs between repeats (ε²): the noise part.
    smoothing_var_mgal2 : float
        Mean square of the repeats' common difference from the less-smoothed estimate, its
        own noise taken out (≥ 0): the smoothing part, which repeats share.
    n_points : int
    n_repeats : int
    mean_diff_sq_mgal2 : float
        ``mean_j(d̄_j²)``: the repeats' mean difference squared, its noise not taken out.
    mean_diff_noise_mgal2 : float
        ``mean_j(s_j²)/K``: the part of it the difference's noise explains.
    """

    noise_var_mgal2: float
    smoothing_var_mgal2: float
    n_points: int
    n_repeats: int
    mean_diff_sq_mgal2: float = float("nan")
    mean_diff_noise_mgal2: float = float("nan")

    def smoothing_p_value(self, n_independent: float) -> float:
        """One-sided p-value of a smoothing part above 0: the probability that the difference's
        noise alone gives a ratio ``F = mean(d̄²) / (mean(s²)/K)`` at least as large.  With the
        track's ``n_independent`` independent stretches (its length over the length one
        independent value spans, ≥ 1; the points along a track are strongly correlated), F
        follows Fisher's F(ν, ν(K − 1)), ν = ``n_independent``: ``K·d̄²`` and ``s²`` are
        independent estimates of the same noise variance (with 1 and K − 1 degrees of freedom
        per stretch) when the repeats share nothing but the anomaly."""
        nu = float(n_independent)
        if not nu >= 1.0:
            raise ValueError(f"n_independent must be at least 1, got {n_independent!r}")
        if not self.mean_diff_noise_mgal2 > 0:
            return 0.0 if self.mean_diff_sq_mgal2 > 0 else 1.0
        ratio = self.mean_diff_sq_mgal2 / self.mean_diff_noise_mgal2
        return float(f_dist.sf(ratio, nu, nu * (self.n_repeats - 1)))

    def std_scale(self, posterior_var_mgal2: float) -> float:
        """Factor ≥ 1 that widens a posterior std (mean variance ``posterior_var_mgal2``,
        mGal², at the same points) to the error the repeats show,
        ``max(1, sqrt((noise + smoothing) / posterior))``.  Never below 1: the measure is
        noisy and misses what the less-smoothed estimate also smooths away."""
        if not posterior_var_mgal2 > 0:
            raise ValueError(f"posterior variance must be positive, got {posterior_var_mgal2!r}")
        return max(1.0, float(np.sqrt((self.noise_var_mgal2 + self.smoothing_var_mgal2) / posterior_var_mgal2)))


def repeat_pass_noise_var(values_mgal) -> np.ndarray:
    """Each repeat's own noise variance, from its departures from the mean of the others.

    K repeats of one track share the anomaly and the detail of it the estimate smooths away;
    their noise differs from repeat to repeat, and not only by chance: a pass flown through a
    turbulent stretch carries more.  The departure of repeat i from the mean of the others,
    ``r_i = x_i − mean_{j≠i} x_j``, has the shared part cancelled and
    ``E[r_i²] = v_i + Σ_{j≠i} v_j / (K − 1)²`` (``v_j`` the repeats' noise variances, their
    noise independent).  The K equations, each ``r_i²`` averaged over the common points, give
    ``v`` (clipped at 0); their mean is the scatter ``ε²`` of :func:`internal_accuracy`
    (the noise part of :func:`repeat_error_parts`).  Two repeats cannot tell their noise apart:
    both get ``ε²``.

    Parameters
    ----------
    values_mgal : array_like, shape (K, n)
        K ≥ 2 repeats at n ≥ 1 common points (mGal), finite.

    Returns
    -------
    ndarray, shape (K,)
        The repeats' noise variances (mGal²).
    """
    g = np.asarray(values_mgal, dtype=float)
    if g.ndim != 2 or g.shape[0] < 2 or g.shape[1] < 1:
        raise ValueError(f"need an array of shape (K ≥ 2, n ≥ 1), got {g.shape}")
    if not np.all(np.isfinite(g)):
        raise ValueError("repeat values must be finite")
    k = g.shape[0]
    others = (g.sum(axis=0) - g) / (k - 1)
    a = np.mean((g - others) ** 2, axis=1)
    if k == 2:
        return np.full(2, float(a.mean()) / 2.0)
    m = np.eye(k) + (np.ones((k, k)) - np.eye(k)) / (k - 1) ** 2
    return np.maximum(np.linalg.solve(m, a), 0.0)


def _mean_posterior_var(posterior_var_mgal2, points: tuple) -> np.ndarray:
    """The repeats' mean posterior variance at each common point (mGal²): the (K, n) array's
    mean over the repeats, or the (n,) array itself; every value positive."""
    post = np.asarray(posterior_var_mgal2, dtype=float)
    scale = post.mean(axis=0) if post.ndim == 2 else post
    if scale.shape != tuple(points) or not np.all(scale > 0):
        raise ValueError(f"posterior variances must be positive, one per common point ({tuple(points)}), got "
                         f"shape {post.shape}")
    return scale


def repeat_pass_noise_ratio(values_mgal, posterior_var_mgal2) -> np.ndarray:
    """Each repeat's own noise variance over the posterior variance, point by point.

    :func:`repeat_pass_noise_var` of the repeats divided at every common point by the root
    of the repeats' mean posterior variance there: the posterior widens at a line's ends and
    holes, where every estimate departs more, and a plain mean square would let those few
    points rule.  A ratio above 1 says the repeat carries more noise than its posterior holds.

    Parameters
    ----------
    values_mgal : array_like, shape (K, n)
        K ≥ 2 repeats at n common points (mGal), finite.
    posterior_var_mgal2 : array_like, shape (K, n) or (n,)
        Their posterior variances at the same points (mGal², > 0).

    Returns
    -------
    ndarray, shape (K,)
        Dimensionless.
    """
    g = np.asarray(values_mgal, dtype=float)
    return repeat_pass_noise_var(g / np.sqrt(_mean_posterior_var(posterior_var_mgal2, g.shape[-1:])))


def repeat_pass_departures(values_mgal, reference_mgal, posterior_var_mgal2) -> np.ndarray:
    """Each repeat's mean square departure from the mean of the *other* repeats of a reference.

    ``mean_x ((v_j(x) − r̄₋ⱼ(x))² / s(x))`` with ``r̄₋ⱼ`` the mean of the reference over the
    repeats other than j and ``s`` the repeats' mean posterior variance at each point, so that
    the line ends, where every estimate departs more, do not rule.  With the reference the
    values themselves it is how far each repeat stands from the others; with another estimate
    of the same repeats as the values, how far that one would stand from them as they were.

    Parameters
    ----------
    values_mgal, reference_mgal : array_like, shape (K, n)
        K ≥ 2 repeats at n common points (mGal), finite.
    posterior_var_mgal2 : array_like, shape (K, n) or (n,)
        Posterior variances at the same points (mGal², > 0).

    Returns
    -------
    ndarray, shape (K,)
        Dimensionless.
    """
    v = np.asarray(values_mgal, dtype=float)
    r = np.asarray(reference_mgal, dtype=float)
    if r.ndim != 2 or r.shape[0] < 2 or v.shape != r.shape:
        raise ValueError(f"values and reference must both be (K >= 2, n), got {v.shape} and {r.shape}")
    scale = _mean_posterior_var(posterior_var_mgal2, r.shape[1:])
    others = (r.sum(axis=0)[None, :] - r) / (r.shape[0] - 1)
    return np.mean((v - others) ** 2 / scale[None, :], axis=1)


def repeat_pass_std_scales(noise_ratio, track_scale: float = 1.0, smoothing_ratio: float = 0.0) -> np.ndarray:
    """Each repeat's std factor: ``max(track_scale, sqrt(ρ_i + smoothing_ratio))``, at least 1.

    ``ρ_i`` is the repeat's noise over its posterior (:func:`repeat_pass_noise_ratio`),
    ``smoothing_ratio`` the repeats' shared smoothing part over the mean posterior variance
    (0 where it is not measured) and ``track_scale`` the one factor of the whole track
    (:meth:`RepeatErrorParts.std_scale`; 1 where there is none): a repeat is widened beyond the
    track's factor only by noise of its own, never narrowed below it (its share rests on a
    K-th of the track's stretches).

    Parameters
    ----------
    noise_ratio : array_like, shape (K,)
        Dimensionless, ≥ 0.
    track_scale, smoothing_ratio : float
        Dimensionless, ≥ 0.

    Returns
    -------
    ndarray, shape (K,)
    """
    r = np.asarray(noise_ratio, dtype=float)
    if r.ndim != 1 or not np.all(r >= 0):
        raise ValueError(f"noise ratios must be a 1-D array of values ≥ 0, got {r!r}")
    if not (track_scale >= 0 and smoothing_ratio >= 0):
        raise ValueError(f"track_scale and smoothing_ratio must be ≥ 0, got {track_scale!r}, {smoothing_ratio!r}")
    return np.maximum(max(1.0, float(track_scale)), np.sqrt(r + float(smoothing_ratio)))


def noise_excess_p_value(noise_var_mgal2: float, posterior_var_mgal2: float, dof: float) -> float:
    """One-sided p-value of a noise variance measured above a posterior variance.

    The repeats' scatter ``ε²`` (``dof`` degrees of freedom: independent stretches times
    K − 1) is a scaled χ² when the error is Gaussian; under the hypothesis that the noise
    part is no larger than the whole posterior variance, ``dof·ε²/σ²`` is at most χ²(dof),
    so a small p says the posterior std misses noise the repeats show.

    Parameters
    ----------
    noise_var_mgal2, posterior_var_mgal2 : float
        The repeats' noise variance and the mean posterior variance at the same points (mGal²,
        the latter > 0).
    dof : float
        Degrees of freedom of the scatter (≥ 1).
    """
    if not posterior_var_mgal2 > 0:
        raise ValueError(f"posterior variance must be positive, got {posterior_var_mgal2!r}")
    if not dof >= 1.0:
        raise ValueError(f"dof must be at least 1, got {dof!r}")
    return float(chi2.sf(dof * float(noise_var_mgal2) / float(posterior_var_mgal2), dof))


def repeat_error_parts(values_mgal, diff_mgal) -> RepeatErrorParts:
    """The two parts of an estimate's error that K repeats of one track show.

    The noise part differs from repeat to repeat: its variance is the repeats' scatter
    ``ε²`` (:func:`internal_accuracy`).  The smoothing part (the anomaly's detail the
    estimate smooths away) is the same in every repeat and cancels in their scatter; the
    difference ``d`` from a less-smoothed estimate of the same data carries it, plus noise
    that again differs from repeat to repeat.  Averaged over the repeats, ``d̄`` keeps the
    smoothing part and 1/K of that noise, whose variance the scatter of ``d`` gives:
    ``S = mean_j(d̄_j²) − mean_j(s_j²)/K`` (``s_j²`` the unbiased variance over the repeats
    at point j), clipped at 0.  ``S`` misses what the less-smoothed estimate also smooths
    away.

    Parameters
    ----------
    values_mgal, diff_mgal : array_like, shape (K, n)
        K ≥ 2 repeats at n ≥ 1 common points of the estimate and of its difference from a
        less-smoothed one (mGal), finite.

    Returns
    -------
    RepeatErrorParts
    """
    g = np.asarray(values_mgal, dtype=float)
    d = np.asarray(diff_mgal, dtype=float)
    if g.ndim != 2 or g.shape[0] < 2 or g.shape[1] < 1 or d.shape != g.shape:
        raise ValueError(f"need two arrays of the same shape (K ≥ 2, n ≥ 1), got {g.shape} and {d.shape}")
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(d))):
        raise ValueError("repeat values must be finite")
    k, n = g.shape
    noise = float(np.mean(np.var(g, axis=0, ddof=1)))
    mean_sq = float(np.mean(d.mean(axis=0) ** 2))
    of_noise = float(np.mean(np.var(d, axis=0, ddof=1)) / k)
    return RepeatErrorParts(noise, max(0.0, mean_sq - of_noise), n, k, mean_sq, of_noise)


@dataclass
class RepeatAccuracy:
    """Result of :func:`repeat_line_accuracy`.

    Attributes
    ----------
    epsilon_mgal : float
        Internal accuracy ε (mGal).
    along_km : ndarray, shape (n,)
        Common along-track positions (km, along the track's principal axis).
    values_mgal : ndarray, shape (K, n)
        The repeats interpolated on ``along_km``.
    mean_mgal : ndarray, shape (n,)
        Mean of the repeats.
    """

    epsilon_mgal: float
    along_km: np.ndarray
    values_mgal: np.ndarray
    mean_mgal: np.ndarray

    def __float__(self) -> float:
        return float(self.epsilon_mgal)

    @property
    def n_points(self) -> int:
        return int(self.along_km.size)

    @property
    def n_repeats(self) -> int:
        return int(self.values_mgal.shape[0])


def track_axes(easting_km, northing_km) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The principal axes of the passes of one track: the centre of all their finite points and
    the unit vectors along and across the direction of largest spread (km, in the CRS's easting /
    northing; the along vector's sign is arbitrary).

    Parameters
    ----------
    easting_km, northing_km : sequence of K array_like
        One array per pass (km).

    Returns
    -------
    (centre, along, across) : ndarray, shape (2,) each
    """
    allp = np.column_stack([np.concatenate([np.asarray(a, dtype=float).ravel() for a in easting_km]),
                            np.concatenate([np.asarray(a, dtype=float).ravel() for a in northing_km])])
    allp = allp[np.all(np.isfinite(allp), axis=1)]
    if len(allp) < 2:
        raise ValueError("a track needs at least 2 finite positions for its axis")
    centre = allp.mean(axis=0)
    _, _, vt = np.linalg.svd(allp - centre, full_matrices=False)
    return centre, vt[0], vt[1]


def repeat_line_accuracy(easting_km, northing_km=None, dg_mgal=None, step_km: float = 0.1) -> RepeatAccuracy:
    """Internal accuracy of K repeats of one track.

    Every repeat is projected on the principal axis of all the repeats' points
    (so repeats flown in opposite directions line up), sorted along it and
    linearly interpolated onto common positions every ``step_km`` over the
    interval all repeats cover; positions where a repeat has no value (NaN) are
    left out.

    Parameters
    ----------
    easting_km, northing_km, dg_mgal : sequence of K array_like
        One array per repeat (km, km, mGal).  Alternatively pass one sequence
        of K ``(easting_km, northing_km, dg_mgal)`` tuples as the first
        argument and leave the others None.
    step_km : float
        Spacing of the common points (km).

    Returns
    -------
    RepeatAccuracy
        ``float(result)`` is ε in mGal.

    Raises
    ------
    ValueError
        Fewer than 2 repeats, mismatched lengths, or no common interval.
    """
    if step_km <= 0:
        raise ValueError("step_km must be positive")
    if northing_km is None and dg_mgal is None:
        try:
            easting_km, northing_km, dg_mgal = zip(*easting_km)
        except (TypeError, ValueError) as exc:
            raise ValueError("pass (easting, northing, dg) per repeat or three sequences") from exc
    es = [np.asarray(a, dtype=float).ravel() for a in easting_km]
    ns = [np.asarray(a, dtype=float).ravel() for a in northing_km]
    gs = [np.asarray(a, dtype=float).ravel() for a in dg_mgal]
    if not (len(es) == len(ns) == len(gs)) or len(es) < 2:
        raise ValueError("need at least 2 repeats with easting, northing and dg each")
    for k, (e, n, g) in enumerate(zip(es, ns, gs)):
        if not (e.size == n.size == g.size) or e.size < 2:
            raise ValueError(f"repeat {k}: arrays must have the same size ≥ 2")
    centre, axis, _ = track_axes(es, ns)
    along = []
    for e, n in zip(es, ns):
        along.append((e - centre[0]) * axis[0] + (n - centre[1]) * axis[1])
    lo = max(a.min() for a in along)
    hi = min(a.max() for a in along)
    if not hi > lo:
        raise ValueError("the repeats have no common along-track interval")
    pos = np.arange(lo, hi + 1e-12, step_km)
    vals = np.empty((len(gs), pos.size))
    for k, (a, g) in enumerate(zip(along, gs)):
        o = np.argsort(a, kind="stable")
        vals[k] = np.interp(pos, a[o], g[o])
    keep = np.all(np.isfinite(vals), axis=0)   # a repeat without a value there (NaN) leaves the point out
    if not keep.any():
        raise ValueError("no common point where every repeat has a value")
    pos, vals = pos[keep], vals[:, keep]
    return RepeatAccuracy(internal_accuracy(vals), pos - lo, vals, vals.mean(axis=0))


#: passes of one repeat track farther apart across it than this (km) are not repeats: they are
#: kept out of every use of the track (noise fit, model checks, std sizing) and warned about
REPEAT_MAX_SPREAD_KM = 0.5


def across_track_spread_km(easting_km, northing_km) -> float:
    """How far apart K passes of one track lie across it (km): the range of the passes' median
    positions across the principal axis of all their points.  Repeats flown on one track lie
    within some 100 m of each other; passes kilometres apart are not repeats, and their
    :func:`repeat_line_accuracy` compares different ground.

    Parameters
    ----------
    easting_km, northing_km : sequence of K array_like
        One array per pass (km).

    Returns
    -------
    float
        0 for fewer than two passes.
    """
    es = [np.asarray(a, dtype=float).ravel() for a in easting_km]
    ns = [np.asarray(a, dtype=float).ravel() for a in northing_km]
    if len(es) != len(ns) or any(e.size != n.size for e, n in zip(es, ns)):
        raise ValueError("one easting and one northing array of the same size per pass")
    if len(es) < 2:
        return 0.0
    centre, _, cross = track_axes(es, ns)
    across = [np.nanmedian((e - centre[0]) * cross[0] + (n - centre[1]) * cross[1]) for e, n in zip(es, ns)]
    return float(np.nanmax(across) - np.nanmin(across))


def _pass_axis(e: np.ndarray, n: np.ndarray) -> np.ndarray | None:
    """Unit vector along a pass's principal axis (None with fewer than 2 finite points)."""
    ok = np.isfinite(e) & np.isfinite(n)
    if ok.sum() < 2:
        return None
    pts = np.column_stack([e[ok] - e[ok].mean(), n[ok] - n[ok].mean()])
    return np.linalg.svd(pts, full_matrices=False)[2][0]


def same_track(easting_km, northing_km, max_spread_km: float = REPEAT_MAX_SPREAD_KM,
               max_angle_deg: float = 10.0, min_overlap: float = 0.5) -> bool:
    """Whether two passes fly one track: parallel or anti-parallel within ``max_angle_deg``,
    within ``max_spread_km`` of each other across it (:func:`across_track_spread_km`), and
    overlapping along it by at least ``min_overlap`` of the shorter pass.

    Parameters
    ----------
    easting_km, northing_km : sequence of 2 array_like
        The two passes' positions (km).

    Returns
    -------
    bool
    """
    es = [np.asarray(a, dtype=float).ravel() for a in easting_km]
    ns = [np.asarray(a, dtype=float).ravel() for a in northing_km]
    if len(es) != 2 or len(ns) != 2:
        raise ValueError("same_track compares two passes")
    axes = [_pass_axis(e, n) for e, n in zip(es, ns)]
    if axes[0] is None or axes[1] is None:
        return False
    if abs(float(axes[0] @ axes[1])) < np.cos(np.radians(max_angle_deg)):
        return False
    if across_track_spread_km(es, ns) > max_spread_km:
        return False
    ax = axes[0]
    spans = []
    for e, n in zip(es, ns):
        a = e * ax[0] + n * ax[1]
        spans.append((float(np.nanmin(a)), float(np.nanmax(a))))
    overlap = min(spans[0][1], spans[1][1]) - max(spans[0][0], spans[1][0])
    shorter = min(s1 - s0 for s0, s1 in spans)
    return bool(shorter > 0 and overlap >= min_overlap * shorter)


def group_passes(easting_km, northing_km, **same_track_kw) -> np.ndarray:
    """Group passes into tracks: each pass joins the first group whose first pass it shares a
    track with (:func:`same_track`), else starts a group.

    Parameters
    ----------
    easting_km, northing_km : sequence of K array_like
        One array per pass (km), in the order to group them (e.g. time).
    **same_track_kw
        Passed to :func:`same_track`.

    Returns
    -------
    ndarray of int, shape (K,)
        The group of each pass, 0, 1, … in order of first appearance.
    """
    if len(easting_km) != len(northing_km):
        raise ValueError("one easting and one northing array per pass")
    labels = np.full(len(easting_km), -1, dtype=int)
    heads: list[int] = []
    for i in range(len(easting_km)):
        for g, h in enumerate(heads):
            if same_track([easting_km[h], easting_km[i]], [northing_km[h], northing_km[i]], **same_track_kw):
                labels[i] = g
                break
        else:
            labels[i] = len(heads)
            heads.append(i)
    return labels


def _error_vs_reference(estimate_mgal, reference_mgal) -> np.ndarray:
    """``estimate − reference`` (NaN where either is not finite), shapes checked."""
    a = np.asarray(estimate_mgal, dtype=float)
    b = np.asarray(reference_mgal, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(a) & np.isfinite(b), a - b, np.nan)


def _selected(values: np.ndarray, where) -> np.ndarray:
    """``values[where]`` (all of them when ``where`` is None), shape checked."""
    if where is None:
        return values
    w = np.asarray(where, dtype=bool)
    if w.shape != values.shape:
        raise ValueError(f"where has shape {w.shape}, the values {values.shape}")
    return values[w]


def line_demeaned(error_mgal, line) -> np.ndarray:
    """``error`` with each line's mean removed (the mean over the line's finite values).

    This is the part of an error that a constant per line (leveling, a base tie) cannot
    remove.  Non-finite values stay NaN; a line without finite values stays NaN.

    Parameters
    ----------
    error_mgal : array_like, shape (n,)
    line : array_like, shape (n,)
        Line id of every value (any hashable, sortable type: str, int).

    Returns
    -------
    ndarray, shape (n,)
    """
    e = np.asarray(error_mgal, dtype=float)
    ids = np.asarray(line)
    if e.ndim != 1 or ids.shape != e.shape:
        raise ValueError(f"error and line must be 1-D of the same length, got {e.shape} and {ids.shape}")
    _, inv = np.unique(ids, return_inverse=True)
    inv = inv.ravel()
    ok = np.isfinite(e)
    total = np.bincount(inv[ok], weights=e[ok], minlength=inv.max(initial=-1) + 1)
    count = np.bincount(inv[ok], minlength=total.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count
    out = e - mean[inv]
    out[~ok] = np.nan
    return out


def rms_vs_reference(estimate_mgal, reference_mgal, *, line=None, where=None) -> float:
    """RMS of ``estimate − reference`` over the points where both are finite (mGal).

    Parameters
    ----------
    estimate_mgal, reference_mgal : array_like, same shape
    line : array_like, optional
        Line id per point (1-D inputs): each line's mean error is removed first
        (:func:`line_demeaned`; the mean over all the line's points given, before
        ``where``), the RMS of what leveling and base ties cannot see.
    where : array_like of bool, optional
        Points counted in the RMS (e.g. one terrain class); default all.

    Returns
    -------
    float

    Raises
    ------
    ValueError
        Shapes differ, or no selected point has both values finite.
    """
    d = _error_vs_reference(estimate_mgal, reference_mgal)
    if line is not None:
        d = line_demeaned(d, line)
    d = _selected(d, where)
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise ValueError("no common finite values")
    return float(np.sqrt(np.mean(d ** 2)))


def mean_error_vs_reference(estimate_mgal, reference_mgal, *, where=None) -> float:
    """Mean of ``estimate − reference`` over the points where both are finite (mGal): the bias.

    ``where`` selects the points as in :func:`rms_vs_reference`.

    Raises
    ------
    ValueError
        Shapes differ, or no selected point has both values finite.
    """
    d = _selected(_error_vs_reference(estimate_mgal, reference_mgal), where)
    d = d[np.isfinite(d)]
    if d.size == 0:
        raise ValueError("no common finite values")
    return float(np.mean(d))


def std_calibration(error_mgal, std_mgal, k: float = 2.0) -> float:
    """Fraction of errors within ``k`` standard deviations, ``mean(|err| < k σ)``.

    For Gaussian errors with a correct σ: 0.683 (k=1), 0.954 (k=2), 0.997 (k=3).
    Points where either input is not finite are ignored.
    """
    e = np.asarray(error_mgal, dtype=float)
    s = np.asarray(std_mgal, dtype=float)
    e, s = np.broadcast_arrays(e, s)
    ok = np.isfinite(e) & np.isfinite(s)
    if not np.any(ok):
        raise ValueError("no finite error/std pairs")
    return float(np.mean(np.abs(e[ok]) < k * s[ok]))


def crossover_std_factor(diff_mgal, pred_var_mgal2, shared_fraction: float = 0.2, min_n_narrow: int = 20,
                         min_factor: float = 0.75, max_factor: float = 20.0, min_n: int = 2) -> dict:
    """Scale factor for the lines' posterior std from the crossover differences.

    At a crossing the difference of two lines' estimates has variance
    ``σ_a² + σ_b² − 2ρσ_aσ_b``; with the two errors sharing a fraction ρ of their
    variance (``shared_fraction``: the anomaly both leave unresolved at that place)
    that is ``(1 − ρ)(σ_a² + σ_b²)`` for σ_a ≈ σ_b.  The factor that makes the stated
    std agree with the crossovers is therefore
    ``sqrt(mean(diff²) / mean(σ_a² + σ_b²)) / sqrt(1 − ρ)``.

    Below ``min_n_narrow`` crossovers the factor only widens (≥ 1).  Errors are
    correlated along lines, so a few tens of crossovers scatter by a factor of two:
    the factor never narrows below ``min_factor``.  From ``min_n`` crossovers on it
    widens: a small survey's std has nothing else to check it, and when it is half the
    error even two or three crossovers say so (on the small random layouts of
    ``benchmarks/bench_unseen.py --geometry`` with 2–9 crossovers, 2σ coverage
    0.65–0.85 → 0.80–1.00; a calibrated one, 0.955, went to 1.00: a factor from a few
    differences scatters, and widening by chance costs less than the few percent
    coverage can still rise).

    Parameters
    ----------
    diff_mgal : array_like, shape (n,)
        Crossover differences (mGal).
    pred_var_mgal2 : array_like, shape (n,)
        ``σ_a² + σ_b²`` at each crossover (mGal²).
    shared_fraction : float
        ρ in [0, 1).

    Returns
    -------
    dict
        ``n`` (usable crossovers), and when n ≥ ``min_n`` ``rms_ratio`` (the raw ratio)
        and ``factor`` (to multiply the std by).
    """
    d = np.asarray(diff_mgal, dtype=float)
    v = np.asarray(pred_var_mgal2, dtype=float)
    if d.shape != v.shape:
        raise ValueError(f"diff_mgal and pred_var_mgal2 differ in shape: {d.shape} vs {v.shape}")
    if not 0 <= shared_fraction < 1:
        raise ValueError("shared_fraction must lie in [0, 1)")
    ok = np.isfinite(d) & np.isfinite(v) & (v > 0)
    n = int(ok.sum())
    if n < max(1, min_n):
        return {"n": n}
    ratio = float(np.sqrt(np.mean(d[ok] ** 2) / np.mean(v[ok])))
    factor = ratio / np.sqrt(1.0 - shared_fraction)
    if n < min_n_narrow:
        factor = max(factor, 1.0)
    return {"n": n, "rms_ratio": ratio, "factor": float(np.clip(factor, min_factor, max_factor))}


def points_in_hull(point_e_km, point_n_km, hull_e_km, hull_n_km) -> np.ndarray:
    """Boolean mask of the points inside the convex hull of the hull points.

    The hull is triangulated from its vertices only (``ConvexHull`` first), so millions
    of line points cost about as little as a few thousand; points on the hull's edges
    count as inside.

    Parameters
    ----------
    point_e_km, point_n_km : array_like, broadcastable
        The points to test (km).
    hull_e_km, hull_n_km : array_like
        Points whose convex hull is the region (any shape, flattened; non-finite dropped).

    Returns
    -------
    ndarray of bool, the broadcast shape of the points
    """
    hull_pts = np.column_stack([np.asarray(hull_e_km, float).ravel(),
                                np.asarray(hull_n_km, float).ravel()])
    hull_pts = hull_pts[np.all(np.isfinite(hull_pts), axis=1)]
    if hull_pts.shape[0] < 3:
        raise ValueError("need at least 3 points for a convex hull")
    pe = np.asarray(point_e_km, dtype=float)
    pn = np.asarray(point_n_km, dtype=float)
    pe, pn = np.broadcast_arrays(pe, pn)
    tri = Delaunay(hull_pts[ConvexHull(hull_pts).vertices])
    return (tri.find_simplex(np.column_stack([pe.ravel(), pn.ravel()])) >= 0).reshape(pe.shape)


@dataclass(frozen=True)
class GridAccuracy:
    """Result of :func:`grid_accuracy_in_hull` (mGal); the figures are None when ``cells`` is 0.

    Attributes
    ----------
    cells : int
        Grid nodes inside the lines' convex hull where both grids are finite.
    rms_mgal : float or None
        RMS of ``dg − true`` over those nodes.
    rms_demeaned_mgal : float or None
        The same with the mean error removed (the std of the error).
    std_calibration : float or None
        Fraction of those nodes with ``|dg − true| < k σ`` (:func:`std_calibration`),
        when a std grid was given.
    """

    cells: int
    rms_mgal: float | None
    rms_demeaned_mgal: float | None
    std_calibration: float | None = None


def _grid_error_in_hull(easting_km, northing_km, dg_mgal, true_dg_mgal, line_easting_km, line_northing_km):
    """``(dg − true)`` on the grid and the mask of nodes inside the hull with both finite."""
    e = np.asarray(easting_km, dtype=float)
    n = np.asarray(northing_km, dtype=float)
    g = np.asarray(dg_mgal, dtype=float)
    t = np.asarray(true_dg_mgal, dtype=float)
    if g.shape != (n.size, e.size) or t.shape != g.shape:
        raise ValueError(f"grids must have shape (ny, nx) = {(n.size, e.size)}; got {g.shape}, {t.shape}")
    E, N = np.meshgrid(e, n)
    inside = points_in_hull(E, N, line_easting_km, line_northing_km)
    return g - t, inside & np.isfinite(g) & np.isfinite(t)


def grid_accuracy_in_hull(easting_km, northing_km, dg_mgal, true_dg_mgal, line_easting_km,
                          line_northing_km, std_mgal=None, k: float = 2.0) -> GridAccuracy:
    """Accuracy of a grid against a true grid over the nodes inside the lines' convex hull.

    Parameters
    ----------
    easting_km : ndarray, shape (nx,)
    northing_km : ndarray, shape (ny,)
    dg_mgal, true_dg_mgal : ndarray, shape (ny, nx)
        The estimated and the true grid (the true one sampled at the same nodes).
    line_easting_km, line_northing_km : array_like
        Coordinates of the line points (any shape, flattened).
    std_mgal : ndarray, shape (ny, nx), optional
        Posterior std grid, for the calibration figure.
    k : float
        Calibration multiple of σ.

    Returns
    -------
    GridAccuracy
        ``cells = 0`` and None figures when no node qualifies (no error raised).
    """
    err, ok = _grid_error_in_hull(easting_km, northing_km, dg_mgal, true_dg_mgal, line_easting_km,
                                  line_northing_km)
    d = err[ok]
    if d.size == 0:
        return GridAccuracy(cells=0, rms_mgal=None, rms_demeaned_mgal=None, std_calibration=None)
    cal = None
    if std_mgal is not None:
        s = np.asarray(std_mgal, dtype=float)
        if s.shape != err.shape:
            raise ValueError(f"std_mgal has shape {s.shape}, the grid {err.shape}")
        cal = std_calibration(d, s[ok], k)
    return GridAccuracy(cells=int(d.size), rms_mgal=float(np.sqrt(np.mean(d ** 2))),
                        rms_demeaned_mgal=float(np.std(d)), std_calibration=cal)


def grid_rms_in_hull(easting_km, northing_km, dg_mgal, true_dg_mgal, line_easting_km,
                     line_northing_km) -> float:
    """RMS of ``dg − true`` over grid nodes inside the convex hull of the lines.

    Parameters
    ----------
    easting_km : ndarray, shape (nx,)
    northing_km : ndarray, shape (ny,)
    dg_mgal, true_dg_mgal : ndarray, shape (ny, nx)
    line_easting_km, line_northing_km : array_like
        Coordinates of the line points (any shape, flattened).

    Returns
    -------
    float
        RMS (mGal) over nodes inside the hull where both grids are finite.
    """
    err, ok = _grid_error_in_hull(easting_km, northing_km, dg_mgal, true_dg_mgal, line_easting_km,
                                  line_northing_km)
    d = err[ok]
    if d.size == 0:
        raise ValueError("no grid node inside the convex hull of the lines")
    return float(np.sqrt(np.mean(d ** 2)))
