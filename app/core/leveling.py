"""Line leveling at crossovers (SPEC §3, seed 001 §5).

Two steps:

1. :func:`find_crossovers` finds every intersection of survey lines in projected
   coordinates (km) and interpolates the full-rate anomaly estimate and its
   standard deviation of both lines at the crossing.
2. :func:`level_lines` fits a polynomial drift in time per line (degree 0–2,
   time normalised per line to [-1, 1]) to the crossover differences by
   weighted least squares and reports the crossover RMS before and after.

:func:`common_level_std` says how far off the level leveling leaves common to every
flight can be (what crossovers cannot see).

The drift model of seed 001 is ``δf_T(t) = l_0 + l_1 t + … + l_p t^p`` per line.
Crossover differences only see differences of drifts, so the problem is
degenerate: at least a common constant (one per connected group of lines) and,
for ``degree >= 1`` on two families of straight parallel lines flown at
constant speed, every function that is linear along each line — ``1``, ``x``,
``y`` and the product ``u·v`` of the coordinates normal to the two line
directions — is unobservable (a 4-dimensional null space).  The
degeneracy is removed either by a reference line whose drift is fixed to zero
(the paper's choice; the remaining null space, e.g. the plane, is then removed
by the minimum-norm rule) or by the minimum-norm solution (truncated SVD of the
whitened design matrix).  Instead of one polynomial per line, the lines of one
flight may share one polynomial in time (``groups``), the alternative seed 001
mentions.

Units: coordinates km, times s, anomalies and drifts mGal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from app.core.gridding import single_thread_blas
from app.core.model_check import paired_decrease_p

KINDS = ("main", "tie", "repeat")
CROSSOVER_COLUMNS = ["line_a", "line_b", "easting_km", "northing_km", "time_a", "time_b",
                     "dg_a", "dg_b", "std_a", "std_b"]


@dataclass
class LineTrack:
    """One survey line at full (GNSS) rate.

    Attributes
    ----------
    easting_km, northing_km : ndarray, shape (n,)
        Projected position (km).
    time_s : ndarray, shape (n,)
        Strictly increasing time (s, survey time scale).
    dg_mgal : ndarray, shape (n,)
        Anomaly estimate (mGal).
    dg_std_mgal : ndarray, shape (n,)
        Its standard deviation (mGal); zeros if unknown.
    kind : str
        ``"main"``, ``"tie"`` or ``"repeat"``.
    """

    easting_km: np.ndarray
    northing_km: np.ndarray
    time_s: np.ndarray
    dg_mgal: np.ndarray
    dg_std_mgal: np.ndarray
    kind: str = "main"

    def __post_init__(self):
        self.easting_km = np.asarray(self.easting_km, dtype=float)
        self.northing_km = np.asarray(self.northing_km, dtype=float)
        self.time_s = np.asarray(self.time_s, dtype=float)
        self.dg_mgal = np.asarray(self.dg_mgal, dtype=float)
        if self.dg_std_mgal is None:
            self.dg_std_mgal = np.zeros_like(self.dg_mgal)
        self.dg_std_mgal = np.asarray(self.dg_std_mgal, dtype=float)
        n = self.time_s.shape
        for name in ("easting_km", "northing_km", "dg_mgal", "dg_std_mgal"):
            if getattr(self, name).shape != n:
                raise ValueError(f"LineTrack: {name} has shape {getattr(self, name).shape}, "
                                 f"time_s has {n}")
        if self.time_s.ndim != 1 or self.time_s.size < 2:
            raise ValueError("LineTrack: need 1-D arrays with at least 2 points")
        if not np.all(np.diff(self.time_s) > 0):
            raise ValueError("LineTrack: time_s must be strictly increasing")
        if self.kind not in KINDS:
            raise ValueError(f"LineTrack: kind must be one of {KINDS}, got {self.kind!r}")


def _decimate_indices(e_km, n_km, step_km):
    """Indices of a polyline keeping about one vertex per ``step_km`` (ends kept)."""
    d = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(e_km), np.diff(n_km)))])
    if d[-1] <= 0:
        return np.array([0, e_km.size - 1])
    bins = np.floor(d / step_km).astype(np.int64)
    first = np.flatnonzero(np.concatenate([[True], bins[1:] != bins[:-1]]))
    idx = np.union1d(first, [e_km.size - 1])
    return idx


def find_crossovers(lines: dict[str, LineTrack], *, include_repeat: bool = False,
                    decimate_km: float = 0.1) -> pd.DataFrame:
    """Every intersection between different survey lines.

    Tracks are decimated to polylines with ~``decimate_km`` vertices, candidate
    segment pairs are found with a KD-tree on segment midpoints (two segments of
    length ≤ L that intersect have midpoints closer than L), and the exact
    intersection is solved for all candidates at once.  At the crossing the time
    of each line is interpolated linearly along its decimated segment, and the
    full-rate ``dg`` and ``dg_std`` are interpolated at that time.

    Main–tie crossings are the usual ones; main–main and tie–tie pairs are
    included when they really intersect.  No crossing is reported inside a
    data gap (a decimated segment longer than ``max(3·decimate_km, 5×`` the
    line's median sample step``)``).  Repeat lines are excluded unless
    ``include_repeat``.

    Parameters
    ----------
    lines : dict of str to LineTrack
    include_repeat : bool
        Include lines of kind ``"repeat"``.
    decimate_km : float
        Vertex spacing of the decimated polylines (km).

    Returns
    -------
    DataFrame
        Columns ``line_a, line_b, easting_km, northing_km, time_a, time_b, dg_a,
        dg_b, std_a, std_b`` (km, s, mGal); one row per crossing.  ``line_a`` is
        the line of the higher-priority kind (main < tie < repeat), ties broken by
        id order.  Empty (with these columns) if nothing crosses.
    """
    if decimate_km <= 0:
        raise ValueError("decimate_km must be positive")
    names = [k for k, v in lines.items() if include_repeat or v.kind != "repeat"]
    empty = pd.DataFrame({c: pd.Series(dtype=object if c.startswith("line") else float)
                          for c in CROSSOVER_COLUMNS})
    segs = _line_segments(lines, names, decimate_km)
    if len(names) < 2 or segs.line.size == 0:
        return empty
    hits = _intersections(segs, _candidate_pairs(segs))
    if hits is None:
        return empty
    return _crossover_frame(lines, names, segs, hits)


class _Segments(NamedTuple):
    """The decimated polylines of all lines as one set of segments (global arrays)."""

    line: np.ndarray       # (S,) index into ``names`` of each segment's line
    i0: np.ndarray         # (S,) full-rate index of the segment's start vertex
    i1: np.ndarray         # (S,) and of its end vertex
    p0: np.ndarray         # (S, 2) start point (km)
    p1: np.ndarray         # (S, 2) end point (km)
    time: list             # per line: full-rate time_s
    dg: list               # per line: full-rate dg_mgal
    std: list              # per line: full-rate dg_std_mgal


def _line_segments(lines: dict[str, LineTrack], names: list[str], decimate_km: float) -> _Segments:
    """Decimated segments of every named line, without the segments that bridge a data gap
    (longer than ``max(3·decimate_km, 5×`` the line's median sample step``)``)."""
    seg_line, seg_i0, seg_i1 = [], [], []
    for li, name in enumerate(names):
        tr = lines[name]
        if not isinstance(tr, LineTrack):
            raise ValueError(f"line {name!r} is not a LineTrack")
        idx = _decimate_indices(tr.easting_km, tr.northing_km, decimate_km)
        # drop segments that bridge a data gap (no data to interpolate there)
        raw_step = np.hypot(np.diff(tr.easting_km), np.diff(tr.northing_km))
        gap_km = max(3.0 * decimate_km, 5.0 * float(np.median(raw_step)))
        seg_len = np.hypot(np.diff(tr.easting_km[idx]), np.diff(tr.northing_km[idx]))
        good = seg_len <= gap_km
        seg_line.append(np.full(int(good.sum()), li))
        seg_i0.append(idx[:-1][good])
        seg_i1.append(idx[1:][good])
    if names:
        seg_line, seg_i0, seg_i1 = np.concatenate(seg_line), np.concatenate(seg_i0), np.concatenate(seg_i1)
    else:
        seg_line = seg_i0 = seg_i1 = np.zeros(0, dtype=np.int64)
    p0 = np.empty((seg_line.size, 2))
    p1 = np.empty((seg_line.size, 2))
    for li, name in enumerate(names):
        m = seg_line == li
        p0[m, 0] = lines[name].easting_km[seg_i0[m]]
        p0[m, 1] = lines[name].northing_km[seg_i0[m]]
        p1[m, 0] = lines[name].easting_km[seg_i1[m]]
        p1[m, 1] = lines[name].northing_km[seg_i1[m]]
    return _Segments(seg_line, seg_i0, seg_i1, p0, p1, [lines[n].time_s for n in names],
                     [lines[n].dg_mgal for n in names], [lines[n].dg_std_mgal for n in names])


def _candidate_pairs(segs: _Segments) -> np.ndarray:
    """Pairs ``(i, j)`` of segments of different lines whose midpoints are closer than the
    longest segment (two segments of length ≤ L that intersect have midpoints closer than L)."""
    length = np.hypot(*(segs.p1 - segs.p0).T)
    mid = 0.5 * (segs.p0 + segs.p1)
    r = float(length.max()) * 1.0000001 + 1e-12
    pairs = cKDTree(mid).query_pairs(r, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    return pairs[segs.line[pairs[:, 0]] != segs.line[pairs[:, 1]]]


class _Hits(NamedTuple):
    """Segment pairs that intersect and where."""

    i: np.ndarray          # segment of the first line
    j: np.ndarray          # segment of the second line
    u: np.ndarray          # crossing parameter along segment i, in [0, 1]
    v: np.ndarray          # and along segment j
    easting_km: np.ndarray
    northing_km: np.ndarray


def _intersections(segs: _Segments, pairs: np.ndarray) -> _Hits | None:
    """Exact intersections ``p0i + u (p1i − p0i) = p0j + v (p1j − p0j)`` of the candidate pairs.

    Parameter intervals are half-open so a crossing on a shared vertex counts once; the last
    segment of a line is closed.  None when nothing intersects.
    """
    if pairs.size == 0:
        return None
    i, j = pairs[:, 0], pairs[:, 1]
    p0, p1 = segs.p0, segs.p1
    di = p1[i] - p0[i]
    dj = p1[j] - p0[j]
    w = p0[j] - p0[i]
    den = di[:, 0] * dj[:, 1] - di[:, 1] * dj[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (w[:, 0] * dj[:, 1] - w[:, 1] * dj[:, 0]) / den
        v = (w[:, 0] * di[:, 1] - w[:, 1] * di[:, 0]) / den
    last_i = (segs.i1[i] == np.array([segs.time[k].size - 1 for k in segs.line[i]]))
    last_j = (segs.i1[j] == np.array([segs.time[k].size - 1 for k in segs.line[j]]))
    ok = (np.abs(den) > 1e-15) & (u >= 0) & (v >= 0) & ((u < 1) | (last_i & (u <= 1))) \
        & ((v < 1) | (last_j & (v <= 1)))
    i, j, u, v = i[ok], j[ok], u[ok], v[ok]
    if i.size == 0:
        return None
    xe = p0[i, 0] + u * di[ok][:, 0]
    xn = p0[i, 1] + u * di[ok][:, 1]
    return _Hits(i, j, u, v, xe, xn)


class _LineValues(NamedTuple):
    """A line's time, anomaly and std at crossings."""

    time: np.ndarray
    dg: np.ndarray
    std: np.ndarray


def _values_at(segs: _Segments, seg: np.ndarray, par: np.ndarray) -> _LineValues:
    """Time interpolated linearly along each decimated segment at parameter ``par``, and the
    full-rate ``dg`` and ``dg_std`` interpolated at that time."""
    t = np.empty(seg.size)
    g = np.empty(seg.size)
    s = np.empty(seg.size)
    for k in np.unique(segs.line[seg]):
        m = segs.line[seg] == k
        time_s = segs.time[k]
        t0 = time_s[segs.i0[seg[m]]]
        t1 = time_s[segs.i1[seg[m]]]
        tk = t0 + par[m] * (t1 - t0)
        t[m] = tk
        g[m] = np.interp(tk, time_s, segs.dg[k])
        s[m] = np.interp(tk, time_s, segs.std[k])
    return _LineValues(t, g, s)


def _crossover_frame(lines: dict[str, LineTrack], names: list[str], segs: _Segments, hits: _Hits) -> pd.DataFrame:
    """The crossover table, ``line_a`` of the higher-priority kind (main < tie < repeat, ties
    broken by id order), sorted by ``line_a, line_b, time_a``."""
    ta, ga, sa = _values_at(segs, hits.i, hits.u)
    tb, gb, sb = _values_at(segs, hits.j, hits.v)
    la = np.array(names, dtype=object)[segs.line[hits.i]]
    lb = np.array(names, dtype=object)[segs.line[hits.j]]
    prio = {k: n for n, k in enumerate(KINDS)}
    ka = np.array([prio[lines[n].kind] for n in la])
    kb = np.array([prio[lines[n].kind] for n in lb])
    order_a = np.array([names.index(n) for n in la])
    order_b = np.array([names.index(n) for n in lb])
    swap = (kb < ka) | ((kb == ka) & (order_b < order_a))
    df = pd.DataFrame({
        "line_a": np.where(swap, lb, la), "line_b": np.where(swap, la, lb),
        "easting_km": hits.easting_km, "northing_km": hits.northing_km,
        "time_a": np.where(swap, tb, ta), "time_b": np.where(swap, ta, tb),
        "dg_a": np.where(swap, gb, ga), "dg_b": np.where(swap, ga, gb),
        "std_a": np.where(swap, sb, sa), "std_b": np.where(swap, sa, sb),
    })
    df["line_a"] = df["line_a"].astype(str)
    df["line_b"] = df["line_b"].astype(str)
    return df.sort_values(["line_a", "line_b", "time_a"]).reset_index(drop=True)


def _basis(tau, degree):
    """Power basis columns ``tau**0 .. tau**degree``, shape (n, degree+1)."""
    return np.vander(np.asarray(tau, dtype=float), degree + 1, increasing=True)


@dataclass
class LevelingResult:
    """Result of :func:`level_lines`.

    Attributes
    ----------
    coefs : dict of str to ndarray
        Drift polynomial coefficients per drift unit (mGal), power basis in the
        normalised time ``τ = 2 (t − t0)/(t1 − t0) − 1`` of the unit's time
        range.  A unit is a line, or a group of lines (e.g. a flight) when
        ``groups`` was given.  Units without crossings have no entry (their
        lines' correction is zero).
    degrees : dict of str to int
        Degree actually used per unit (reduced when it has too few crossings).
    time_ranges : dict of str to (float, float)
        ``(t0, t1)`` per unit (s).
    rms_before, rms_after : float
        Crossover RMS of ``dg_a − dg_b`` before and after leveling (mGal).
    diff_before, diff_after : ndarray, shape (len(crossovers),)
        Crossover differences before and after (mGal), row order of the input;
        NaN for crossovers that had a non-finite value (not used).
    reference : str or None
        The reference unit (zero drift), or None for the minimum-norm solution.
    unit_of : dict of str to str
        Drift unit of every line (the line itself without ``groups``).
    """

    coefs: dict
    degrees: dict
    time_ranges: dict
    rms_before: float
    rms_after: float
    diff_before: np.ndarray
    diff_after: np.ndarray
    reference: str | None = None
    sigma0_mgal: float = 0.0
    n_crossovers: int = 0
    unleveled_lines: list = field(default_factory=list)
    unit_of: dict = field(default_factory=dict)
    fit_ranges: dict = field(default_factory=dict)

    def correction(self, line: str, time_s) -> np.ndarray:
        """Drift of ``line`` at ``time_s`` (mGal): subtract it from the line's ``dg``.

        Lines whose drift unit had no crossing get zero.  The drift is not extrapolated:
        outside the time span of the unit's lines that have crossings (``fit_ranges``) it is
        held at the edge value (a slope fitted to two tie lines' crossings, carried an hour
        further, put 36 mGal on repeat lines that had no crossings of their own).
        """
        t = np.asarray(time_s, dtype=float)
        unit = self.unit_of.get(str(line), str(line))
        if unit not in self.coefs:
            return np.zeros_like(t)
        t0, t1 = self.time_ranges[unit]
        if unit in self.fit_ranges:
            t = np.clip(t, *self.fit_ranges[unit])
        tau = 2.0 * (t - t0) / (t1 - t0) - 1.0
        return _basis(tau.ravel(), self.degrees[unit]).dot(self.coefs[unit]).reshape(t.shape)

    def summary(self) -> dict:
        """JSON-able summary for ``report.json`` (mGal, s)."""
        return {
            "rms_before_mgal": self.rms_before, "rms_after_mgal": self.rms_after,
            "n_crossovers": self.n_crossovers, "reference": self.reference,
            "sigma0_mgal": self.sigma0_mgal,
            "degrees": dict(self.degrees),
            "coefs_mgal": {k: [float(c) for c in v] for k, v in self.coefs.items()},
            "time_ranges_s": {k: [float(a), float(b)] for k, (a, b) in self.time_ranges.items()},
            "crossing_time_ranges_s": {k: [float(a), float(b)] for k, (a, b) in self.fit_ranges.items()},
            "unleveled_lines": list(self.unleveled_lines),
        }

    def apply(self, line: str, time_s, dg_mgal) -> np.ndarray:
        """Leveled anomaly ``dg − correction(line, time)`` (mGal)."""
        return np.asarray(dg_mgal, dtype=float) - self.correction(line, time_s)


def cross_validated_leveling(crossovers: pd.DataFrame, line_time_ranges: dict, degree: int = 1,
                             groups: dict | None = None, **kwargs) -> dict:
    """Leave-one-line-out check of :func:`level_lines`: does the drift model predict
    crossovers it was not fitted to?

    For every line, the drift is fitted to the crossovers that do not involve it and applied
    to the ones that do (both lines' corrections); each crossover is so predicted twice, once
    per held-out line.  Crossover errors are correlated along lines, so an in-sample F-test
    finds "significant" drift in the smoothing errors themselves; a drift the held-out lines
    do not confirm is noise.

    Parameters
    ----------
    crossovers, line_time_ranges, degree, groups, **kwargs
        As for :func:`level_lines`.

    Returns
    -------
    dict
        ``rms_before_mgal`` (the crossovers used), ``rms_cv_mgal`` (held-out RMS after the
        drift correction), ``p_value`` (one-sided paired t-test that the held-out squared
        differences are lower after the correction) and ``n_folds``.
    """
    cx = crossovers.reset_index(drop=True)
    before = (cx["dg_a"] - cx["dg_b"]).to_numpy(float)
    la, lb = cx["line_a"].astype(str).to_numpy(), cx["line_b"].astype(str).to_numpy()
    sq, sq0, n_folds = [], [], 0
    for line in sorted(set(la) | set(lb)):
        held = (la == line) | (lb == line)
        if held.all() or not held.any():
            continue
        try:
            res = level_lines(cx[~held], line_time_ranges, degree=degree, groups=groups, **kwargs)
        except ValueError:
            continue
        rows = np.flatnonzero(held & np.isfinite(before))
        pred = np.array([res.correction(la[k], cx["time_a"].iloc[k]) - res.correction(lb[k], cx["time_b"].iloc[k])
                         for k in rows], float).ravel()
        sq.append((before[rows] - pred) ** 2)
        sq0.append(before[rows] ** 2)
        n_folds += 1
    ok = np.isfinite(before)
    if not sq:
        return {"rms_before_mgal": _rms(before[ok]), "rms_cv_mgal": float("nan"), "p_value": 1.0, "n_folds": 0}
    a, b = np.concatenate(sq0), np.concatenate(sq)
    # one-sided paired test of "leveling lowers the held-out squared differences"; each
    # crossover enters twice (once per held-out line), so the independent pairs are halved
    p = paired_decrease_p(a, b, n_eff=max(2, a.size // 2))
    return {"rms_before_mgal": _rms(before[ok]), "rms_cv_mgal": float(np.sqrt(np.mean(b))),
            "p_value": 1.0 if not np.isfinite(p) else p, "n_folds": n_folds}


def drift_free_differences(crossovers: pd.DataFrame, diffs_mgal, line_time_ranges: dict, degree: int = 1,
                           groups: dict | None = None, with_dof: bool = False):
    """Crossover differences with all that a drift of the leveling model explains removed.

    The least-squares residuals of :func:`level_lines`'s model — one polynomial of ``degree``
    in time per line, or per group of lines (``groups``: a flight) — fitted without weights to
    each column of ``diffs_mgal`` over the crossovers where every column is finite.  Two
    estimates of the same lines share the lines' drift and offsets exactly, so their drift-free
    differences compare what the estimates themselves get wrong: a flight offset of several
    mGal against estimate errors of one, left in, decides any comparison of the two at a few
    crossovers by chance.

    Parameters
    ----------
    crossovers : DataFrame
        :func:`find_crossovers`' table (``line_a``, ``line_b``, ``time_a``, ``time_b``).
    diffs_mgal : array_like, shape (n,) or (n, k)
        Differences at the table's rows (mGal), one column per estimate.
    line_time_ranges, degree, groups
        As for :func:`level_lines`.

    with_dof : bool
        Also return the residuals' degrees of freedom: the rows used less the rank of the
        drift model on them.

    Returns
    -------
    ndarray, or (ndarray, int) with ``with_dof``
        The residuals, the shape of ``diffs_mgal``; NaN on rows where a column is not finite.
    """
    d = np.asarray(diffs_mgal, dtype=float)
    one = d.ndim == 1
    d2 = d[:, None] if one else d
    if d2.ndim != 2 or d2.shape[0] != len(crossovers):
        raise ValueError(f"diffs_mgal has shape {d.shape} for {len(crossovers)} crossovers")
    ta = crossovers["time_a"].to_numpy(float)
    tb = crossovers["time_b"].to_numpy(float)
    keep = np.all(np.isfinite(d2), axis=1) & np.isfinite(ta) & np.isfinite(tb)
    out = np.full(d2.shape, np.nan)
    if keep.sum() < 2:
        res = out[:, 0] if one else out
        return (res, 0) if with_dof else res
    la = crossovers["line_a"].astype(str).to_numpy()[keep]
    lb = crossovers["line_b"].astype(str).to_numpy()[keep]
    obs = _Observations(la, lb, ta[keep], tb[keep], d2[keep, 0], np.ones(int(keep.sum())), keep, d2[:, 0])
    units = _drift_units(line_time_ranges, obs, groups)
    involved = sorted(set(units.unit_a) | set(units.unit_b))
    A = _design_matrix(units, obs, _column_layout(units, involved, degree, None))   # min-norm: the common constant
    y = d2[keep]
    coef, _, rank, _ = np.linalg.lstsq(A, y, rcond=None)
    out[keep] = y - A @ coef
    res = out[:, 0] if one else out
    return (res, int(keep.sum()) - int(rank)) if with_dof else res


def _rms(x):
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")


def level_lines(crossovers: pd.DataFrame, line_time_ranges: dict, degree: int = 1,
                reference: str | None = None, sigma0_mgal: float = 0.5,
                rcond: float = 1e-6, groups: dict | None = None,
                slope_scale: float = 0.01) -> LevelingResult:
    """Per-line polynomial drift in time from crossover differences.

    Model, per crossover k between lines a and b::

        dg_a(t_a) − dg_b(t_b) = d_a(t_a) − d_b(t_b) + noise,
        d_l(t) = Σ_j c_lj τ_l(t)^j,  τ_l = 2 (t − t0_l)/(t1_l − t0_l) − 1,

    solved by weighted least squares with weights ``1/(std_a² + std_b² + σ0²)``.

    Degeneracy: ``reference=None`` or ``"min-norm"`` gives the minimum-norm
    solution (truncated SVD of the whitened system, singular values below
    ``rcond·s_max`` dropped), which removes the common constant of every
    connected group of lines and any other unobservable combination (e.g. a
    survey-wide plane for degree ≥ 1).  The norm is weighted: coefficients of
    τ^j, j ≥ 1, count ``1/slope_scale`` times more than the constants, so along
    unobservable directions the solution prefers per-line offsets to in-line
    slopes (drift within one line is small; offsets between lines and flights
    are not).  With a plain norm (``slope_scale=1``) differing flight offsets
    leak into a survey-wide tilt (measured on the omolon-mini geometry: 9.7
    mGal line error with slope_scale=1 against 1.0 mGal with 0.01).  A line
    id fixes that line's drift to zero (seed 001); what remains unobservable
    is then removed by the weighted minimum-norm rule too.

    Crossovers with a non-finite value are ignored (their ``diff_after`` is
    NaN; ``n_crossovers`` counts the ones used).

    Over-fitting guard: with degree p a line needs more than p+1 crossings, so
    its degree is reduced to ``min(p, n_crossings − 2)`` (never below 0; a line
    with a single crossing gets a constant).  Lines absent from ``crossovers``
    get zero correction (they are reported in ``unleveled_lines``).

    Parameters
    ----------
    crossovers : DataFrame
        Output of :func:`find_crossovers` (columns ``line_a, line_b, time_a,
        time_b, dg_a, dg_b, std_a, std_b``).
    line_time_ranges : dict of str to (float, float)
        ``(t_start, t_end)`` of every line (s); defines the time normalisation.
    degree : int
        0, 1 or 2.
    reference : str or None
        None / ``"min-norm"`` or the id of the reference line.
    sigma0_mgal : float
        Extra crossover error (mGal) added in the weights (anomaly mismatch,
        unmodelled errors); must be > 0 if the stds can be zero.
    rcond : float
        Relative singular-value cut-off of the minimum-norm solve.
    slope_scale : float
        Relative scale of the τ^j (j ≥ 1) coefficients in the minimum norm
        (see above); 1 gives the plain minimum-norm solution.
    groups : dict of str to str, optional
        Line → group (e.g. flight).  Lines of one group share one drift
        polynomial in time over the group's time span (seed 001: "the trend
        common to all lines of a flight"); ``reference`` then names a group.
        Lines missing from the mapping are their own unit.

    Returns
    -------
    LevelingResult

    Raises
    ------
    ValueError
        No crossovers, bad degree, unknown reference line, a crossover line
        missing from ``line_time_ranges``, or zero weights.
    """
    _check_leveling_args(crossovers, degree, sigma0_mgal, slope_scale)
    obs = _crossover_observations(crossovers, sigma0_mgal)
    units = _drift_units(line_time_ranges, obs, groups)
    involved = sorted(set(units.unit_a) | set(units.unit_b))
    if reference is not None and reference != "min-norm" and str(reference) not in involved:
        raise ValueError(f"reference line/group {reference!r} has no crossovers")
    ref = None if reference in (None, "min-norm") else str(reference)
    layout = _column_layout(units, involved, degree, ref)
    A = _design_matrix(units, obs, layout)
    x = _weighted_min_norm(A, obs, layout, slope_scale, rcond)
    coefs = {}
    for n in involved:
        if n == ref:
            coefs[n] = np.zeros(layout.degrees[n] + 1)
        else:
            o = layout.offsets[n]
            coefs[n] = x[o:o + layout.degrees[n] + 1].copy()
    nx = obs.diff.size
    model = A.dot(x) if layout.ncol else np.zeros(nx)
    diff_after = np.full(obs.diff_all.size, np.nan)
    diff_after[obs.keep] = obs.diff - model
    unleveled = sorted(ln for ln, u in units.unit_of.items() if u not in involved)
    # the time span over which each drift is applied: the lines whose crossings determined it
    crossing_lines = set(obs.line_a) | set(obs.line_b)
    line_ranges = {str(k): v for k, v in line_time_ranges.items()}
    fit_ranges = {}
    for ln in sorted(crossing_lines):
        u = units.unit_of[ln]
        t0, t1 = (float(v) for v in line_ranges[ln])
        fit_ranges[u] = (min(t0, fit_ranges[u][0]), max(t1, fit_ranges[u][1])) if u in fit_ranges else (t0, t1)
    return LevelingResult(coefs=coefs, degrees=layout.degrees, time_ranges=units.ranges, unit_of=units.unit_of,
                          fit_ranges=fit_ranges,
                          rms_before=_rms(obs.diff), rms_after=_rms(diff_after),
                          diff_before=obs.diff_all, diff_after=diff_after, reference=ref,
                          sigma0_mgal=float(sigma0_mgal), n_crossovers=int(nx),
                          unleveled_lines=unleveled)


def _check_leveling_args(crossovers, degree: int, sigma0_mgal: float, slope_scale: float) -> None:
    """The argument checks of :func:`level_lines` that need no computation."""
    if degree not in (0, 1, 2):
        raise ValueError(f"degree must be 0, 1 or 2, got {degree}")
    if crossovers is None or len(crossovers) == 0:
        raise ValueError("no crossovers: lines cannot be leveled (no main/tie crossings found)")
    need = {"line_a", "line_b", "time_a", "time_b", "dg_a", "dg_b", "std_a", "std_b"}
    missing = need - set(crossovers.columns)
    if missing:
        raise ValueError(f"crossovers lack columns {sorted(missing)}")
    if sigma0_mgal < 0:
        raise ValueError("sigma0_mgal must be >= 0")
    if not slope_scale > 0:
        raise ValueError("slope_scale must be > 0")


class _Observations(NamedTuple):
    """The usable crossovers (finite difference, variance and times)."""

    line_a: np.ndarray     # line ids
    line_b: np.ndarray
    time_a: np.ndarray     # s
    time_b: np.ndarray
    diff: np.ndarray       # dg_a − dg_b (mGal)
    var: np.ndarray        # std_a² + std_b² + σ0² (mGal²)
    keep: np.ndarray       # (len(crossovers),) bool: which rows these are
    diff_all: np.ndarray   # dg_a − dg_b of every row (NaN kept)


def _crossover_observations(crossovers: pd.DataFrame, sigma0_mgal: float) -> _Observations:
    """Differences and their variances at the crossovers with finite values."""
    la = crossovers["line_a"].astype(str).to_numpy()
    lb = crossovers["line_b"].astype(str).to_numpy()
    ta = crossovers["time_a"].to_numpy(float)
    tb = crossovers["time_b"].to_numpy(float)
    diff = crossovers["dg_a"].to_numpy(float) - crossovers["dg_b"].to_numpy(float)
    var = (crossovers["std_a"].to_numpy(float) ** 2 + crossovers["std_b"].to_numpy(float) ** 2
           + sigma0_mgal ** 2)
    keep = np.isfinite(diff) & np.isfinite(var) & np.isfinite(ta) & np.isfinite(tb)
    if not np.any(keep):
        raise ValueError("no crossovers with finite values: lines cannot be leveled")
    diff_all = diff
    la, lb, ta, tb, diff, var = (a[keep] for a in (la, lb, ta, tb, diff, var))
    if np.any(var <= 0):
        raise ValueError("zero crossover variance: give sigma0_mgal > 0")
    return _Observations(la, lb, ta, tb, diff, var, keep, diff_all)


class _DriftUnits(NamedTuple):
    """Drift units (a line, or a group of lines sharing one polynomial) and their time spans."""

    unit_of: dict          # line -> unit
    ranges: dict           # unit -> (t0, t1) (s)
    unit_a: np.ndarray     # unit of each usable crossover's line_a
    unit_b: np.ndarray     # and of its line_b


def _drift_units(line_time_ranges: dict, obs: _Observations, groups: dict | None) -> _DriftUnits:
    """Every line's drift unit (``groups`` maps a line to its group; others are their own unit)
    and each unit's time span (the union of its lines'); the crossovers' lines must have one."""
    line_ranges = {str(k): (float(v[0]), float(v[1])) for k, v in line_time_ranges.items()}
    for name in sorted(set(obs.line_a) | set(obs.line_b)):
        if name not in line_ranges:
            raise ValueError(f"line {name!r} of the crossovers has no time range")
        if not line_ranges[name][1] > line_ranges[name][0]:
            raise ValueError(f"line {name!r}: time range must have t_end > t_start")
    grp = {str(k): str(v) for k, v in (groups or {}).items()}
    unit_of = {ln: grp.get(ln, ln) for ln in line_ranges}
    ranges = {}
    for ln, u in unit_of.items():
        t0, t1 = line_ranges[ln]
        ranges[u] = (min(t0, ranges[u][0]), max(t1, ranges[u][1])) if u in ranges else (t0, t1)
    return _DriftUnits(unit_of, ranges, np.array([unit_of[x] for x in obs.line_a], dtype=object),
                       np.array([unit_of[x] for x in obs.line_b], dtype=object))


class _ColumnLayout(NamedTuple):
    """Columns of the design matrix: ``degrees[u] + 1`` per unit from ``offsets[u]``; the
    reference unit has none (zero drift)."""

    ref: str | None
    degrees: dict          # unit -> degree used
    offsets: dict          # unit -> first column
    ncol: int


def _column_layout(units: _DriftUnits, involved: list, degree: int, ref: str | None) -> _ColumnLayout:
    """Degrees (reduced to ``n_crossings − 2``, never below 0) and column offsets per unit."""
    counts = pd.Series(np.concatenate([units.unit_a, units.unit_b])).value_counts()
    degrees = {n: int(max(0, min(degree, counts[n] - 2))) for n in involved}
    offsets, ncol = {}, 0
    for n in involved:
        if n == ref:
            continue
        offsets[n] = ncol
        ncol += degrees[n] + 1
    return _ColumnLayout(ref, degrees, offsets, ncol)


def _design_matrix(units: _DriftUnits, obs: _Observations, layout: _ColumnLayout) -> np.ndarray:
    """``A`` with ``A x = d_a(t_a) − d_b(t_b)`` at every usable crossover (power basis in each
    unit's normalised time); at least one column."""
    nx = obs.diff.size
    A = np.zeros((nx, max(layout.ncol, 1)))
    rows = np.arange(nx)
    for names, times, sign in ((units.unit_a, obs.time_a, 1.0), (units.unit_b, obs.time_b, -1.0)):
        for n in np.unique(names):
            if n == layout.ref:
                continue
            m = names == n
            t0, t1 = units.ranges[n]
            tau = 2.0 * (times[m] - t0) / (t1 - t0) - 1.0
            B = _basis(tau, layout.degrees[n])
            o = layout.offsets[n]
            A[rows[m], o:o + B.shape[1]] += sign * B
    return A


def _weighted_min_norm(A: np.ndarray, obs: _Observations, layout: _ColumnLayout, slope_scale: float,
                       rcond: float) -> np.ndarray:
    """Weighted least squares, minimum norm with the τ^j (j ≥ 1) columns scaled by
    ``slope_scale`` (truncated SVD, ``rcond``); zeros when there is no column."""
    if not layout.ncol:
        return np.zeros(1)
    w = 1.0 / np.sqrt(obs.var)
    # column scales of the weighted minimum norm: 1 for constants, slope_scale for τ^j, j ≥ 1
    scale = np.ones(max(layout.ncol, 1))
    for n, o in layout.offsets.items():
        scale[o + 1:o + layout.degrees[n] + 1] = slope_scale
    with single_thread_blas():  # small dense problem: threads only contend
        z, *_ = np.linalg.lstsq(A * w[:, None] * scale[None, :], obs.diff * w, rcond=rcond)
    return scale * z


def connected_groups(crossing_units) -> dict:
    """The connected groups of drift units that crossovers join.

    Parameters
    ----------
    crossing_units : iterable of (label, label)
        The two units of every crossover.

    Returns
    -------
    dict
        Each unit that crosses another (or itself) mapped to its group's label: the group's
        least unit by ``str`` (so the same for any order of the crossovers).
    """
    parent: dict = {}

    def find(x):
        parent.setdefault(x, x)
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for a, b in crossing_units:
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[max(ra, rb, key=str)] = min(ra, rb, key=str)
    return {k: find(k) for k in list(parent)}


def keep_mean_level(correction_mgal, unit, crossing_units, anchor=None) -> tuple[np.ndarray, list[float]]:
    """Drift corrections without the common level the crossovers cannot see.

    Crossover differences fix the drifts of connected drift units only up to one constant per
    connected group; the constant the solution's gauge leaves in (the weighted minimum norm of
    the coefficients, which is not the mean over the epochs once units have slopes and their
    lines sit unevenly in time) moves the group's mean level, which no crossover measured.
    Per group, the epoch-weighted mean correction over its epochs is subtracted, so leveling
    keeps each group's mean level; differences within a group — and so every crossover
    residual — are unchanged.

    Where a group holds epochs whose level is known absolutely (``anchor``: flights tied to a
    base reading) and others whose level is not (a flight without a tie keeps the gravimeter's
    reading offset, 100+ mGal), the mean over the anchored epochs alone is subtracted: the
    tied flights keep their absolute level on average and the untied ones are brought to it
    through the crossovers, instead of the reading offset being shared out over the whole map.

    Parameters
    ----------
    correction_mgal : array_like, shape (n,)
        Correction per epoch (mGal; subtracted from ``dg``).
    unit : array_like, shape (n,)
        Drift unit of each epoch's line (any hashable label).
    crossing_units : iterable of (label, label)
        The two units of every crossover used.
    anchor : array_like of bool, shape (n,), optional
        Epochs whose level is absolute (None: none is).

    Returns
    -------
    (ndarray, list of float)
        The corrections (shape (n,)) and the constant removed from each group (mGal).
    """
    c = np.array(correction_mgal, dtype=float)
    u = np.asarray(unit, dtype=object)
    if c.shape != u.shape or c.ndim != 1:
        raise ValueError(f"correction_mgal and unit must be 1-D of one length, got {c.shape} and {u.shape}")
    anc = np.zeros(c.shape, bool) if anchor is None else np.asarray(anchor, dtype=bool)
    if anc.shape != c.shape:
        raise ValueError(f"anchor must have the corrections' shape {c.shape}, got {anc.shape}")
    roots = connected_groups(crossing_units)
    removed = []
    for root in sorted(set(roots.values()), key=str):
        group = np.isin(u, np.array([k for k, r in roots.items() if r == root], dtype=object))
        sel = group & np.isfinite(c)
        if (sel & anc).any():
            sel &= anc
        if sel.any():
            shift = float(np.mean(c[sel]))
            c[group] -= shift
            removed.append(shift)
    return c, removed


@dataclass(frozen=True)
class CommonLevel:
    """Result of :func:`common_level_std` (mGal).

    Attributes
    ----------
    std_mgal : float
        Std of the level the drift units share, which crossovers cannot see: ``s/√n``.
    spread_mgal : float
        ``s``: the std of the units' own offsets (their noise taken out; ≥ 0).
    offsets_mgal : dict of str to float
        Each unit's offset from the units' mean, fitted to the crossovers between units.
    n_units, n_crossovers : int
        Units connected by crossovers, and the crossovers between different units used.
    """

    std_mgal: float
    spread_mgal: float
    offsets_mgal: dict
    n_units: int
    n_crossovers: int


def common_level_std(unit_a, unit_b, diff_mgal) -> CommonLevel | None:
    """The std of the level that leveling leaves common to every drift unit (a flight).

    Crossover differences see only differences of the units' drifts, so leveling fixes the
    flights relative to each other and leaves their mean offset where it is (without a base
    tie nothing else sees it).  Read the flights' offsets as exchangeable draws of one
    instrument's drift, std ``s`` about the truth: then their mean, the level leveling keeps,
    is off by ``s/√n`` (n units).  ``s`` is estimated from the crossovers between different
    units: one offset per unit by least squares (their sum zero), ``s² = Σ b_u²/(n − 1) −
    tr(Cov b)/n`` (the offsets' scatter less their estimation noise, from the residual
    variance of the fit), clipped at 0.

    Parameters
    ----------
    unit_a, unit_b : array_like of str, shape (k,)
        The drift unit (flight) of each crossover's two lines.
    diff_mgal : array_like, shape (k,)
        The crossover differences before leveling (line a − line b, mGal); non-finite ones and
        those within one unit are ignored.

    Returns
    -------
    CommonLevel or None
        None when fewer than two units are connected, or no more crossovers between units
        than offsets to fit.
    """
    ua = np.asarray(unit_a, dtype=object)
    ub = np.asarray(unit_b, dtype=object)
    d = np.asarray(diff_mgal, dtype=float)
    if not (ua.shape == ub.shape == d.shape) or d.ndim != 1:
        raise ValueError(f"unit_a, unit_b and diff_mgal must be 1-D of one length, got {ua.shape}, {ub.shape}, "
                         f"{d.shape}")
    sel = np.isfinite(d) & (ua != ub)
    units = sorted({str(u) for u in ua[sel]} | {str(u) for u in ub[sel]})
    n, k = len(units), int(sel.sum())
    if n < 2 or k <= n - 1:
        return None
    idx = {u: i for i, u in enumerate(units)}
    A = np.zeros((k + 1, n))
    rows = np.arange(k)
    A[rows, [idx[str(u)] for u in ua[sel]]] += 1.0
    A[rows, [idx[str(u)] for u in ub[sel]]] -= 1.0
    A[k, :] = 1.0                                     # the offsets' sum is zero
    y = np.concatenate([d[sel], [0.0]])
    b = np.linalg.lstsq(A, y, rcond=None)[0]
    resid = d[sel] - A[:k] @ b
    var_r = float(np.sum(resid ** 2) / max(1, k - (n - 1)))
    cov = var_r * np.linalg.pinv(A.T @ A)
    s2 = max(0.0, float(np.sum(b ** 2) / (n - 1) - np.trace(cov) / n))
    return CommonLevel(float(np.sqrt(s2 / n)), float(np.sqrt(s2)), {u: float(b[i]) for u, i in idx.items()}, n, k)


def crossover_table(crossovers: pd.DataFrame, result: LevelingResult) -> pd.DataFrame:
    """The ``crossovers.csv`` table of SPEC §5: ``line_a, line_b, easting_km,
    northing_km, diff_before_mgal, diff_after_mgal``."""
    if len(crossovers) != result.diff_before.size:
        raise ValueError("crossovers and leveling result have different lengths")
    return pd.DataFrame({
        "line_a": crossovers["line_a"].astype(str).to_numpy(),
        "line_b": crossovers["line_b"].astype(str).to_numpy(),
        "easting_km": crossovers["easting_km"].to_numpy(float),
        "northing_km": crossovers["northing_km"].to_numpy(float),
        "diff_before_mgal": result.diff_before,
        "diff_after_mgal": result.diff_after,
    })
