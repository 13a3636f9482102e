"""Leveling of repeat passes of one track against each other (stage 10 without crossovers).

A survey with no crossing lines (a test line flown K times) has no crossovers to level, but
its passes overlap along their whole length: at every common position ``s`` pass ``i`` reads
``x_i(s) = g(s) + c_i + d_f(t_i(s)) + e_i(s)`` — the same anomaly ``g``, the pass's own
offset ``c_i`` (a tare, the reading offset of its flight), the drift ``d_f`` of its flight
``f`` in time (a polynomial without constant term) and its error ``e_i``.  The anomaly drops
out of each pass's difference from the passes' mean,

    r_i(s) = x_i(s) − mean_j x_j(s) = (c_i − c̄) + d_f(i)(t_i(s)) − mean_j d_f(j)(t_j(s)) + …,

so offsets and drifts are a linear regression on those differences.  Passes flown in
alternating directions see a drift in time as along-track trends of opposite signs, which
the anomaly cannot mimic.  Only the differences are seen: the corrections average to zero over
the common points (the passes' mean level is kept, whatever fixed it — a base tie or nothing).

The differences' errors are correlated along the track (each pass is a smoothed estimate),
so the regression is fitted to their means over blocks of about ``block`` common positions
(every position in one block), which are close to independent when a block is longer than
the error's correlation length, and an F-test says whether the model explains more than those
errors (``(K − 1)`` independent differences per block: each block's ``K`` differences sum to
zero); :func:`drift_p_value` says whether a drift explains more than the offsets alone.

Units: anomalies, offsets and drifts mGal; times s (drift polynomials in hours about each
flight's mean time).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.stats import f as f_dist


class RepeatLevels(NamedTuple):
    """Offsets and drifts of K passes of one track fitted to their differences.

    Attributes
    ----------
    offsets_mgal : ndarray, shape (K,)
        Each pass's constant offset, chosen so that the corrections average to zero over the
        passes' common points (their mean level is kept).
    drift_mgal : ndarray, shape (F, degree)
        Each flight's drift coefficients of ``((t − t_ref) / 3600)^k``, k = 1 … degree
        (mGal per hour^k); shape (F, 0) for degree 0.  A coefficient the passes cannot tell
        from their offsets (all flown one way at one speed: ``IDENTIFIABLE_SHARE``) is 0 and
        not counted in ``n_parameters``.
    t_ref_s : ndarray, shape (F,)
        Each flight's reference time (s): the mean time of its passes' common points.
    flight_of_pass : ndarray, shape (K,)
        Index into the flight axis of each pass.
    p_value : float
        F-test of the fitted model against no correction on the block means.
    rms_before_mgal, rms_after_mgal : float
        RMS of the block means of the passes' differences from their mean, before and after
        the correction (weighted as fitted).
    n_blocks : int
        Blocks per pass.
    n_parameters : int
        Offsets (K − 1) plus drift coefficients.
    t_span_s : ndarray, shape (K, 2)
        Each pass's first and last time at the common points (s): its drift is held at its
        value there beyond them (not extrapolated).
    max_difference_mgal : float
        The largest difference of a pass from the passes' mean at a common point (mGal): what
        a correction could at most have to take out.
    """

    offsets_mgal: np.ndarray
    drift_mgal: np.ndarray
    t_ref_s: np.ndarray
    flight_of_pass: np.ndarray
    p_value: float
    rms_before_mgal: float
    rms_after_mgal: float
    n_blocks: int
    n_parameters: int
    t_span_s: np.ndarray
    max_difference_mgal: float

    def correction(self, k: int, time_s) -> np.ndarray:
        """The correction (mGal, to subtract) of pass ``k`` at times ``time_s`` (s), any shape;
        outside the times of its common points the drift keeps its value at the nearer end."""
        t = np.clip(np.asarray(time_s, dtype=float), *self.t_span_s[k])
        f = int(self.flight_of_pass[k])
        hours = (t - self.t_ref_s[f]) / 3600.0
        out = np.full(t.shape, float(self.offsets_mgal[k]))
        for j, b in enumerate(self.drift_mgal[f], start=1):
            out = out + b * hours ** j
        return out


def _block_means(a: np.ndarray, block: int) -> np.ndarray:
    """Means over ``n // block`` consecutive blocks of ``block`` or ``block + 1`` columns of ``a``
    (K, n) covering every column → (K, n // block)."""
    nb = max(1, a.shape[1] // block)
    edges = np.linspace(0, a.shape[1], nb + 1).round().astype(int)
    return np.add.reduceat(a, edges[:-1], axis=1) / np.diff(edges)


#: a drift column must keep at least this share of its (weighted) norm once the columns before it
#: (the offsets, lower-degree drifts) are projected out: passes flown the same way at the same
#: speed see a drift in time only as offsets between them, and a near-copy of the offsets'
#: columns makes the fit trade huge offsets against a huge drift (a layout's 4 same-way passes:
#: offsets of 10⁷ mGal, their sum right at the common points' blocks and 10⁶ mGal off elsewhere)
IDENTIFIABLE_SHARE = 0.05


def _identifiable(col: np.ndarray, before: list, sw: np.ndarray) -> bool:
    """Whether ``col`` (K, nb) keeps ``IDENTIFIABLE_SHARE`` of its weighted norm outside the span
    of the columns ``before`` (weights ``sw``, the square roots of the rows' weights)."""
    v = col.ravel() * sw
    norm = np.linalg.norm(v)
    if not norm > 0:
        return False
    if before:
        B = np.column_stack([c.ravel() for c in before]) * sw[:, None]
        v = v - B @ np.linalg.lstsq(B, v, rcond=None)[0]
    return bool(np.linalg.norm(v) >= IDENTIFIABLE_SHARE * norm)


def fit_repeat_levels(values_mgal, times_s, flight_of_pass=None, degree: int = 1,
                      block: int = 30, std_mgal=None) -> RepeatLevels:
    """Fit each pass's offset and each flight's drift to the passes' differences.

    Parameters
    ----------
    values_mgal : array_like, shape (K, n)
        The K passes' anomaly estimates at n common positions along the track (mGal; e.g.
        :func:`app.core.accuracy.repeat_line_accuracy`'s ``values_mgal``), finite.
    times_s : array_like, shape (K, n)
        The time each pass was at each common position (s).
    flight_of_pass : sequence of K hashables, optional
        The flight of each pass (default: all one flight); each flight gets its own drift.
    degree : int
        Degree of the drift polynomial in time (0: offsets only, 1 or 2).
    block : int
        Common positions per block (the differences are fitted as block means; ``n // block``
        blocks of ``block`` or ``block + 1`` positions cover all n).
    std_mgal : array_like, shape (K, n), optional
        The passes' posterior std at the common positions (mGal): each block is weighted by
        the inverse of the passes' mean variance there, so the lines' ends and holes, where
        each pass's error is larger and its own, weigh less.  Default: equal weights.

    Returns
    -------
    RepeatLevels

    Raises
    ------
    ValueError
        Fewer than 2 passes, shapes that differ, non-finite values, a degree outside 0–2, or
        too few blocks to test the model (fewer than 2 residual degrees of freedom).
    """
    x = np.asarray(values_mgal, dtype=float)
    t = np.asarray(times_s, dtype=float)
    if x.ndim != 2 or x.shape[0] < 2 or x.shape != t.shape:
        raise ValueError(f"values and times must be (K ≥ 2, n) of one shape, got {x.shape} and {t.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(t))):
        raise ValueError("values and times must be finite")
    if degree not in (0, 1, 2):
        raise ValueError(f"degree must be 0, 1 or 2, got {degree!r}")
    if int(block) < 1:
        raise ValueError(f"block must be ≥ 1 position, got {block!r}")
    K = x.shape[0]
    flights = [0] * K if flight_of_pass is None else list(flight_of_pass)
    if len(flights) != K:
        raise ValueError(f"{len(flights)} flights for {K} passes")
    names = list(dict.fromkeys(flights))
    fidx = np.array([names.index(f) for f in flights], dtype=int)
    t_ref = np.array([t[fidx == f].mean() for f in range(len(names))])
    r = _block_means(x - x.mean(axis=0), int(block))
    nb = r.shape[1]
    if std_mgal is None:
        w = np.ones(nb)
    else:
        sd = np.asarray(std_mgal, dtype=float)
        if sd.shape != x.shape or not np.all(np.isfinite(sd)) or np.any(sd <= 0):
            raise ValueError(f"std_mgal must be positive and finite of shape {x.shape}")
        w = 1.0 / _block_means(sd ** 2, int(block)).mean(axis=0)
        w = w / w.mean()
    cols = []
    for i in range(K - 1):   # offsets, the last pass's the negative sum of the others
        c = np.zeros((K, nb))
        c[i], c[K - 1] = 1.0, -1.0
        cols.append(c)
    w_rows = np.sqrt(np.broadcast_to(w, (K, nb))).ravel()
    for f in range(len(names)):
        for j in range(1, degree + 1):
            basis = np.where((fidx == f)[:, None], ((t - t_ref[f]) / 3600.0) ** j, 0.0)
            b = _block_means(basis - basis.mean(axis=0), int(block))
            cols.append(b if _identifiable(b, [c for c in cols if c is not None], w_rows) else None)
    used = [c for c in cols if c is not None]
    n_par = len(used)
    n_obs = (K - 1) * nb    # each block's K differences sum to zero
    if n_obs - n_par < 2:
        raise ValueError(f"{nb} blocks of {block} positions over {K} passes leave {n_obs - n_par} degrees of "
                         f"freedom for {n_par} parameters (need ≥ 2)")
    sw = w_rows   # weighted least squares by block
    A = np.column_stack([c.ravel() for c in used]) * sw[:, None]
    y = r.ravel() * sw
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    resid = y - A @ coef
    ssr0, ssr1 = float(y @ y), float(resid @ resid)
    if ssr1 > 0:
        F = ((ssr0 - ssr1) / n_par) / (ssr1 / (n_obs - n_par))
        p = float(f_dist.sf(F, n_par, n_obs - n_par))
    else:
        p = 0.0 if ssr0 > 0 else 1.0
    offsets = np.append(coef[:K - 1], -np.sum(coef[:K - 1]))
    drift = np.zeros((len(names), degree))
    k = K - 1
    for f in range(len(names)):
        for j in range(degree):
            if cols[K - 1 + f * degree + j] is not None:
                drift[f, j] = coef[k]
                k += 1
    levels = RepeatLevels(offsets, drift, t_ref, fidx, p, float(np.sqrt(ssr0 / y.size)),
                          float(np.sqrt(ssr1 / y.size)), int(nb), int(n_par),
                          np.column_stack([t.min(axis=1), t.max(axis=1)]),
                          float(np.max(np.abs(x - x.mean(axis=0)))))
    # the differences cannot see a level common to every pass: keep the passes' mean level
    mean = float(np.mean([levels.correction(i, t[i]) for i in range(K)]))
    return levels._replace(offsets_mgal=offsets - mean)


def drift_p_value(offsets: RepeatLevels, drifted: RepeatLevels) -> float | None:
    """Partial F-test of the drift terms beyond the passes' offsets.

    Parameters
    ----------
    offsets, drifted : RepeatLevels
        :func:`fit_repeat_levels` of the same values, times, weights and blocks with
        ``degree = 0`` and with the drift.

    Returns
    -------
    float or None
        One-sided p of the residual sum of squares the drift terms remove, against the
        drifted fit's residual variance; None when no drift term could be fitted (none
        identifiable, or no degrees of freedom left).

    Raises
    ------
    ValueError
        When the two fits are not of the same passes and blocks.
    """
    K = offsets.offsets_mgal.size
    if drifted.offsets_mgal.size != K or drifted.n_blocks != offsets.n_blocks:
        raise ValueError("the two fits must be of the same passes and blocks")
    k = drifted.n_parameters - offsets.n_parameters
    dof = drifted.n_blocks * (K - 1) - drifted.n_parameters
    if k <= 0 or dof <= 0:
        return None
    n = drifted.n_blocks * K     # both RMS are over the K × blocks weighted block means
    ssr0, ssr1 = offsets.rms_after_mgal ** 2 * n, drifted.rms_after_mgal ** 2 * n
    if not ssr1 > 0:
        return 0.0
    return float(f_dist.sf(((ssr0 - ssr1) / k) / (ssr1 / dof), k, dof))
