"""Gridding of line data: least-squares collocation with error maps, and a spline.

SPEC §3 "Map", seed 001 §5: the anomaly at flight height on grid nodes by
least-squares collocation (LSC) with a covariance model of the anomaly and the
along-line error variances, computed in local neighbourhoods so it scales to
large surveys, with the posterior standard deviation of every node.

Estimators follow the verde style: ``fit`` on scattered data, then ``predict``
on points or ``grid`` on a regular grid.

Covariance model
    Second-order Gauss–Markov (Matérn ν = 3/2, positive definite in the
    plane): ``C(d) = σ² (1 + d/L) exp(−d/L)``, d in km.  ``σ²`` and ``L`` are
    estimated from the data: a plane (or the mean) is removed, the empirical
    covariance is binned by distance and the model fitted by weighted least
    squares (weights = pair counts, lags up to a quarter of the survey
    diagonal) with a non-positive constant offset that absorbs the bias of
    the trend removal.  The nugget is what the empirical variance at zero lag
    has beyond the model and the mean given error variance.

Thinning
    Data (GNSS rate, ~10 m spacing) are block-averaged on ``thin_km`` squares,
    separately per line for collocation (so a per-line error can be modelled),
    across lines for the spline.
    The error variance of a block mean is ``mean(std²)/n_eff`` with
    ``n_eff = clip(n · step / error_corr_km, 1, n)``: ``error_corr_km = 0`` treats
    errors as white (variance divided by n); a positive value is the
    along-line correlation length of the errors (smoothed estimates are
    correlated over km, so averaging does not reduce them much).
    Errors of different blocks are treated as independent.

Neighbourhoods
    Grid nodes are grouped in square blocks of ``block_km``; each block is solved
    with the ``max_points`` data nearest to its centre inside
    ``search_radius_km`` (+ the block half diagonal).  With ``max_points`` and
    ``search_radius_km`` large enough this is the global LSC solution.

Units: coordinates km, anomalies mGal, variances mGal².
"""

from __future__ import annotations

import contextlib

import numpy as np
from scipy.linalg import cho_factor, solve_triangular
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

# --------------------------------------------------------------------------- helpers

def single_thread_blas():
    """Limit BLAS to one thread for the many small local solves.

    Multi-threaded OpenBLAS on small (≤ 1000²) matrices on a loaded machine
    is 10–20× slower than one thread (measured: 10.7 s vs 0.66 s for the
    same grid).  Uses ``threadpoolctl`` when installed; otherwise a no-op.
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def gm2_covariance(d_km, variance_mgal2: float, length_km: float):
    """Second-order Gauss–Markov covariance ``σ² (1 + d/L) e^{−d/L}`` (mGal²).

    Parameters
    ----------
    d_km : array_like
        Distances (km), any shape.
    variance_mgal2 : float
        σ² (mGal²).
    length_km : float
        L (km); the correlation drops to 1/2 at d ≈ 1.68 L.
    """
    x = np.asarray(d_km, dtype=float) / length_km
    return variance_mgal2 * (1.0 + x) * np.exp(-x)


def _gm2_inplace(d_km, variance_mgal2, length_km):
    """:func:`gm2_covariance` overwriting the distance array (saves memory passes)."""
    d_km /= length_km
    e = np.exp(-d_km)
    d_km += 1.0
    d_km *= e
    d_km *= variance_mgal2
    return d_km


def _robust_cholesky(K, jitter):
    """Lower Cholesky factor of K; adds growing diagonal jitter if K is not numerically PD."""
    from numpy.linalg import LinAlgError

    for k in range(6):
        try:
            return cho_factor(K if k == 0 else K + np.eye(K.shape[0]) * jitter * 10.0 ** (2 * k),
                              lower=True, check_finite=False)[0]
        except LinAlgError:
            continue
    raise ValueError("collocation matrix is not positive definite (duplicate points with zero error?)")


def _check_xyz(easting_km, northing_km, values, std=None):
    e = np.asarray(easting_km, dtype=float).ravel()
    n = np.asarray(northing_km, dtype=float).ravel()
    v = np.asarray(values, dtype=float).ravel()
    if not (e.size == n.size == v.size):
        raise ValueError(f"easting_km, northing_km and dg_mgal must have the same size "
                         f"({e.size}, {n.size}, {v.size})")
    if std is None:
        s = np.zeros_like(v)
    else:
        s = np.broadcast_to(np.asarray(std, dtype=float).ravel(), v.shape).astype(float)
    ok = np.isfinite(e) & np.isfinite(n) & np.isfinite(v) & np.isfinite(s)
    if not np.any(ok):
        raise ValueError("no finite data to grid")
    if np.any(s[ok] < 0):
        raise ValueError("std_mgal must be non-negative")
    return e[ok], n[ok], v[ok], s[ok], ok


def _split_lines(e, n, line):
    """Integer line labels: given, or from jumps > 10× the median consecutive step."""
    if line is not None:
        _, lab = np.unique(np.asarray(line), return_inverse=True)
        return lab, None
    step = np.hypot(np.diff(e), np.diff(n))
    med = np.median(step) if step.size else 0.0
    jump = step > 10.0 * max(med, 1e-9)
    return np.concatenate([[0], np.cumsum(jump)]), med


def median_step_km(e, n, lab):
    """Median distance between consecutive points of the same line (km)."""
    same = lab[1:] == lab[:-1]
    step = np.hypot(np.diff(e), np.diff(n))[same]
    return float(np.median(step)) if step.size else 0.0


def block_thin(easting_km, northing_km, dg_mgal, std_mgal, thin_km: float,
               error_corr_km: float = 0.0, step_km: float | None = None):
    """Block means on ``thin_km`` squares.

    Returns
    -------
    (e, n, dg, std, count) : tuple of ndarray, shape (m,)
        Mean position, mean value, std of the mean (see module docstring for
        ``error_corr_km``) and the number of points per block.
    """
    return _block_thin(easting_km, northing_km, dg_mgal, std_mgal, thin_km, error_corr_km,
                       step_km, None)[:5]


def block_thin_lines(easting_km, northing_km, dg_mgal, std_mgal, line_label, thin_km: float,
                     error_corr_km: float = 0.0, step_km: float | None = None):
    """:func:`block_thin` separately per line (blocks never mix two lines).

    Returns
    -------
    (e, n, dg, std, count, label) : tuple of ndarray, shape (m,)
    """
    return _block_thin(easting_km, northing_km, dg_mgal, std_mgal, thin_km, error_corr_km,
                       step_km, line_label)


def _block_thin(easting_km, northing_km, dg_mgal, std_mgal, thin_km, error_corr_km, step_km, label):
    if thin_km <= 0:
        raise ValueError("thin_km must be positive")
    e, n, v, s = (np.asarray(a, dtype=float) for a in (easting_km, northing_km, dg_mgal, std_mgal))
    ix = np.floor((e - e.min()) / thin_km).astype(np.int64)
    iy = np.floor((n - n.min()) / thin_km).astype(np.int64)
    key = ix * (iy.max() + 1) + iy
    if label is not None:
        _, lab = np.unique(np.asarray(label), return_inverse=True)
        key = key * (lab.max() + 1) + lab
    _, first, inv, cnt = np.unique(key, return_index=True, return_inverse=True, return_counts=True)

    def mean(x):
        return np.bincount(inv, weights=x) / cnt

    var_mean = mean(s ** 2)
    if error_corr_km > 0:
        st = step_km if step_km is not None else thin_km
        n_eff = np.clip(cnt * st / error_corr_km, 1.0, cnt)
    else:
        n_eff = cnt.astype(float)
    out_lab = None if label is None else np.asarray(label)[first]
    return mean(e), mean(n), mean(v), np.sqrt(var_mean / n_eff), cnt, out_lab


def _trend_design(e, n, trend, origin):
    if trend == "plane":
        return np.column_stack([np.ones_like(e), e - origin[0], n - origin[1]])
    if trend == "mean":
        return np.ones((e.size, 1))
    return np.zeros((e.size, 0))


def empirical_covariance(easting_km, northing_km, residual_mgal, max_lag_km: float,
                         n_bins: int = 30, max_points: int = 4000, seed: int = 0,
                         line_label=None, line_var_mgal2: float = 0.0):
    """Isotropic empirical covariance binned by distance.

    Uses all pairs of a random subsample of at most ``max_points`` points within
    ``max_lag_km``.  With ``line_label`` and ``line_var_mgal2``, the known
    per-line error variance is subtracted from the products of same-line pairs
    and from the zero-lag variance, so the result estimates the anomaly's
    covariance.

    Returns
    -------
    lag_km : ndarray, shape (k,)
        Mean pair distance per non-empty bin (km).
    cov_mgal2 : ndarray, shape (k,)
        Mean product of residuals per bin (mGal²).
    count : ndarray, shape (k,)
        Pairs per bin.
    c0_mgal2 : float
        Empirical variance (zero lag) of the residuals.
    """
    e = np.asarray(easting_km, dtype=float)
    n = np.asarray(northing_km, dtype=float)
    r = np.asarray(residual_mgal, dtype=float)
    c0 = float(np.mean(r ** 2)) - line_var_mgal2
    lab = None if line_label is None else np.asarray(line_label)
    if e.size > max_points:
        idx = np.random.default_rng(seed).choice(e.size, max_points, replace=False)
        e, n, r = e[idx], n[idx], r[idx]
        lab = None if lab is None else lab[idx]
    pairs = cKDTree(np.column_stack([e, n])).query_pairs(max_lag_km, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0, dtype=int), c0
    d = np.hypot(e[pairs[:, 0]] - e[pairs[:, 1]], n[pairs[:, 0]] - n[pairs[:, 1]])
    prod = r[pairs[:, 0]] * r[pairs[:, 1]]
    if lab is not None and line_var_mgal2:
        prod = prod - line_var_mgal2 * (lab[pairs[:, 0]] == lab[pairs[:, 1]])
    b = np.minimum((d / max_lag_km * n_bins).astype(np.int64), n_bins - 1)
    cnt = np.bincount(b, minlength=n_bins)
    sd = np.bincount(b, weights=d, minlength=n_bins)
    sp = np.bincount(b, weights=prod, minlength=n_bins)
    ok = cnt > 0
    return sd[ok] / cnt[ok], sp[ok] / cnt[ok], cnt[ok], c0


def fit_gm2(lag_km, cov_mgal2, count, l_min_km: float, l_max_km: float, offset: bool = True):
    """Weighted least-squares fit of ``σ² (1 + d/L) e^{−d/L} + c`` to binned covariances.

    ``c ≤ 0`` (when ``offset``) absorbs the negative bias that removing the
    mean/trend puts into the empirical covariance of a finite area; without it
    L and σ² come out too small.  For a given L the fit is linear in (σ², c)
    (closed form); L is found by a grid search in log L refined by a bounded
    1-D search.  Weights are the pair counts.

    Returns
    -------
    (variance_mgal2, length_km, offset_mgal2) : tuple of float
    """
    d = np.asarray(lag_km, dtype=float)
    c = np.asarray(cov_mgal2, dtype=float)
    w = np.asarray(count, dtype=float)
    if d.size == 0:
        raise ValueError("no pairs to estimate the covariance from")
    sw = np.sqrt(w)

    def solve(log_l):
        g = gm2_covariance(d, 1.0, np.exp(log_l))
        if offset and d.size >= 3:
            X = np.column_stack([g, np.ones_like(g)])
            coef = np.linalg.lstsq(X * sw[:, None], c * sw, rcond=None)[0]
            if coef[1] <= 0 and coef[0] >= 0:
                return coef[0], coef[1], np.sum(w * (c - X.dot(coef)) ** 2)
        s2 = max(np.sum(w * g * c) / np.sum(w * g * g), 0.0)
        return s2, 0.0, np.sum(w * (c - s2 * g) ** 2)

    grid = np.linspace(np.log(l_min_km), np.log(l_max_km), 61)
    costs = [solve(x)[2] for x in grid]
    k = int(np.argmin(costs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)]
    best = grid[k]
    if hi > lo:
        res = minimize_scalar(lambda x: solve(x)[2], bounds=(lo, hi), method="bounded",
                              options={"xatol": 1e-4})
        if res.fun <= costs[k]:
            best = res.x
    s2, off, _ = solve(best)
    return float(s2), float(np.exp(best)), float(off)


def line_spacing_km(easting_km, northing_km, line_label, sample_km: float = 0.5,
                    max_points: int = 20000, seed: int = 0, coincident_km: float = 0.1) -> float:
    """Median distance from a line point to the nearest point of another line (km).

    Passes of one track (repeat lines: more than half of a line's points within
    ``coincident_km`` of one other line) count as one line, else a survey with a repeated
    track has a "spacing" of a few metres and every grid node is masked.

    Parameters
    ----------
    easting_km, northing_km : array_like, shape (n,)
        Line points (km).
    line_label : array_like, shape (n,)
        Line of each point.
    sample_km : float
        Lines are decimated to about one point per ``sample_km`` along their length.
    coincident_km : float
        Distance (km) below which a point lies on another line's track.

    Returns
    -------
    float
        NaN when there is a single line (or a single track).
    """
    e = np.asarray(easting_km, dtype=float)
    n = np.asarray(northing_km, dtype=float)
    lab = np.asarray(line_label)
    if np.unique(lab).size < 2:
        return float("nan")
    # decimate each line to ~sample_km by along-line distance bins
    keep = np.zeros(e.size, dtype=bool)
    for k in np.unique(lab):
        idx = np.flatnonzero(lab == k)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(e[idx]), np.diff(n[idx])))])
        b = np.floor(s / sample_km).astype(np.int64)
        keep[idx[np.concatenate([[True], b[1:] != b[:-1]])]] = True
    e, n = e[keep], n[keep]
    _, code = np.unique(lab[keep], return_inverse=True)
    tree = cKDTree(np.column_stack([e, n]))
    q = np.arange(e.size)
    if q.size > max_points:
        q = np.random.default_rng(seed).choice(q, max_points, replace=False)
    kk = min(e.size, 64)
    dist, nb = tree.query(np.column_stack([e[q], n[q]]), k=kk)
    dist, nb = np.atleast_2d(dist), np.atleast_2d(nb)
    track = _merge_coincident(code, q, dist, nb, coincident_km)
    other = track[nb] != track[q][:, None]
    best = np.where(other, dist, np.inf).min(axis=1)
    best = best[np.isfinite(best)]
    return float(np.median(best)) if best.size else float("nan")


def _merge_coincident(code, q, dist, nb, coincident_km: float) -> np.ndarray:
    """Track index of every point's line: lines that run along another (more than half of
    their sampled points within ``coincident_km`` of that line) share one index.

    ``code``: line index of every sampled point; ``q``: the query points; ``dist``/``nb``:
    their nearest neighbours' distances and indices."""
    n_lines = int(code.max()) + 1
    rows, cols = np.nonzero((dist < coincident_km) & (code[nb] != code[q][:, None]))
    # each (query point, other line) once, however many of that line's points are close
    pair = np.unique(rows.astype(np.int64) * n_lines + code[nb[rows, cols]])
    counts = np.zeros((n_lines, n_lines))
    np.add.at(counts, (code[q][pair // n_lines], pair % n_lines), 1.0)
    sampled = np.bincount(code[q], minlength=n_lines).astype(float)
    parent = np.arange(n_lines)

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    for a, b in zip(*np.nonzero(counts > 0.5 * np.maximum(sampled, 1.0)[:, None])):
        ra, rb = root(a), root(b)
        parent[max(ra, rb)] = min(ra, rb)
    return np.array([root(i) for i in range(n_lines)])[code]


def _grid_axes(region, spacing_km, e, n):
    if spacing_km <= 0:
        raise ValueError("spacing_km must be positive")
    if region is None:
        region = (float(e.min()), float(e.max()), float(n.min()), float(n.max()))
    w, east, s, north = (float(x) for x in region)
    if not (east >= w and north >= s):
        raise ValueError(f"region must be (west, east, south, north) with east ≥ west, north ≥ south: {region}")
    nx = int(np.floor((east - w) / spacing_km + 1e-9)) + 1
    ny = int(np.floor((north - s) / spacing_km + 1e-9)) + 1
    return w + spacing_km * np.arange(nx), s + spacing_km * np.arange(ny)


class _LineGridder:
    """Shared fit-time preparation: validation, line labels, thinning, mask distance."""

    def _prepare(self, easting_km, northing_km, dg_mgal, std_mgal, line, per_line=True):
        e, n, v, s, ok = _check_xyz(easting_km, northing_km, dg_mgal, std_mgal)
        lab_in = None if line is None else np.asarray(line).ravel()[ok]
        lab, _ = _split_lines(e, n, lab_in)
        step = median_step_km(e, n, lab)
        self.data_step_km_ = step
        te, tn, tv, ts, cnt, tlab = block_thin_lines(e, n, v, s, lab if per_line else np.zeros_like(lab),
                                                     self.thin_km, getattr(self, "error_corr_km", 0.0), step)
        self._lab = tlab
        self.n_data_ = int(e.size)
        self.n_thinned_ = int(te.size)
        self.line_spacing_km_ = line_spacing_km(e, n, lab)
        if self.mask_km is not None:
            if self.mask_km <= 0:
                raise ValueError("mask_km must be positive")
            self.mask_distance_km_ = float(self.mask_km)
        elif np.isfinite(self.line_spacing_km_):
            self.mask_distance_km_ = 1.5 * self.line_spacing_km_
        else:  # a single line: keep a narrow band around it
            self.mask_distance_km_ = 3.0 * self.thin_km
        self._mask_tree = cKDTree(np.column_stack([te, tn]))
        self.region_ = (float(e.min()), float(e.max()), float(n.min()), float(n.max()))
        return te, tn, tv, ts

    def _mask(self, pe, pn, mask_km=None):
        d, _ = self._mask_tree.query(np.column_stack([pe, pn]), k=1,
                                     distance_upper_bound=mask_km or self.mask_distance_km_)
        return np.isfinite(d)

    def grid(self, region=None, spacing_km: float = 1.0, mask_km: float | None = None):
        """Predict on a regular grid.

        Parameters
        ----------
        region : (west, east, south, north) in km, optional
            Defaults to the data bounding box.  Nodes start at west/south.
        spacing_km : float
        mask_km : float, optional
            Mask distance for this call (overrides the fitted
            ``mask_distance_km_``).

        Returns
        -------
        easting_km : ndarray, shape (nx,)
        northing_km : ndarray, shape (ny,)
        dg : ndarray, shape (ny, nx)
            Anomaly (mGal); NaN farther than the mask distance from any datum.
        dg_std : ndarray, shape (ny, nx)
            Standard deviation (mGal); NaN where masked.

        Raises
        ------
        ValueError
            Not fitted, bad region or spacing, or no node within the mask.
        """
        if not hasattr(self, "region_"):
            raise ValueError("call fit() before grid()")
        ge, gn = _grid_axes(region, spacing_km, *(np.array(self.region_[:2]), np.array(self.region_[2:])))
        if mask_km is not None and not mask_km > 0:
            raise ValueError("mask_km must be positive")
        E, N = np.meshgrid(ge, gn)
        inside = self._mask(E.ravel(), N.ravel(), mask_km)
        if not np.any(inside):
            raise ValueError("empty grid area: no grid node lies within "
                             f"{mask_km or self.mask_distance_km_:.3g} km of the data")
        dg = np.full(E.size, np.nan)
        sd = np.full(E.size, np.nan)
        dg[inside], sd[inside] = self._predict(E.ravel()[inside], N.ravel()[inside])
        return ge, gn, dg.reshape(E.shape), sd.reshape(E.shape)

    def predict(self, easting_km, northing_km, return_std: bool = False, masked: bool = False):
        """Predict at points (km). NaN outside the mask only if ``masked``."""
        if not hasattr(self, "region_"):
            raise ValueError("call fit() before predict()")
        pe = np.asarray(easting_km, dtype=float)
        pn = np.asarray(northing_km, dtype=float)
        shape = np.broadcast_shapes(pe.shape, pn.shape)
        pe, pn = (np.broadcast_to(a, shape).ravel() for a in (pe, pn))
        v, s = self._predict(pe, pn)
        if masked:
            m = ~self._mask(pe, pn)
            v[m] = np.nan
            s[m] = np.nan
        v, s = v.reshape(shape), s.reshape(shape)
        return (v, s) if return_std else v


class Collocation(_LineGridder):
    """Least-squares collocation in local neighbourhoods with posterior std.

    Parameters
    ----------
    variance_mgal2, length_km : float, optional
        Fix the GM2 covariance ``σ² (1 + d/L) e^{−d/L}``; estimated from the
        data when None.
    nugget_mgal2 : float, optional
        Extra white error variance added to every datum; estimated from the
        empirical covariance at zero lag when None.
    thin_km : float
        Block size of the thinning (km).
    error_corr_km : float
        Along-line correlation length of the data errors used to shrink the
        std of block means: ``n_eff = clip(n·step/error_corr_km, 1, n)``.
        0 means white errors (std / √n).  The default 1 km suits smoothed
        line estimates (a 0.5 km block mean keeps the points' std); set it to
        the smoother's correlation length.
    trend : {"plane", "mean", "none"}
        Deterministic part removed before covariance estimation and added back.
    block_km : float
        Side of the square blocks of nodes solved together (km).
    max_points : int
        Most data used per block (nearest to the block centre).
    search_radius_km : float, optional
        Data search radius beyond the block half-diagonal; 4 L when None.
    mask_km : float, optional
        Nodes farther than this from any datum are NaN; 1.5× the median line
        spacing when None.
    line_error_mgal2 : float
        Variance of an error constant along each line (leveling residual),
        shared by all data of one line: adds ``line_error_mgal2`` to the
        covariance of same-line pairs (and is removed from the empirical
        covariance before the model is fitted).  E.g. ``max(0, rms_after²/2 −
        mean std²)`` from the crossovers after leveling.
    seed : int
        Seed of the subsampling in the covariance estimation.

    Notes
    -----
    The posterior std is that of simple kriging around the fitted trend: it
    does not include the trend's own uncertainty, nor correlations of the
    errors between different thinning blocks (errors correlated along lines
    over several km make it optimistic; raise ``error_corr_km`` or the
    ``nugget_mgal2``).  Leveling residuals that are constant per line are not
    modelled either.

    Attributes (after ``fit``)
    --------------------------
    variance_mgal2_, length_km_, nugget_mgal2_ : float
        Covariance parameters in use.
    empirical_ : dict
        ``lag_km, cov_mgal2, count, c0_mgal2`` of the empirical covariance.
    trend_coef_ : ndarray
    line_spacing_km_, mask_distance_km_ : float
    n_data_, n_thinned_ : int
    """

    def __init__(self, variance_mgal2=None, length_km=None, nugget_mgal2=None, *,
                 thin_km: float = 0.5, error_corr_km: float = 1.0, trend: str = "plane",
                 block_km: float = 5.0, max_points: int = 400, search_radius_km=None,
                 mask_km=None, line_error_mgal2: float = 0.0, seed: int = 0):
        self.line_error_mgal2 = line_error_mgal2
        self.variance_mgal2 = variance_mgal2
        self.length_km = length_km
        self.nugget_mgal2 = nugget_mgal2
        self.thin_km = thin_km
        self.error_corr_km = error_corr_km
        self.trend = trend
        self.block_km = block_km
        self.max_points = max_points
        self.search_radius_km = search_radius_km
        self.mask_km = mask_km
        self.seed = seed

    def fit(self, easting_km, northing_km, dg_mgal, std_mgal=None, line=None):
        """Fit to scattered line data.

        Parameters
        ----------
        easting_km, northing_km, dg_mgal : array_like, shape (n,)
        std_mgal : array_like, shape (n,) or scalar, optional
            Standard deviation of each datum (mGal); zero when None.
        line : array_like, shape (n,), optional
            Line id of each datum (for the line spacing of the default mask);
            lines are split at jumps when None.

        Returns
        -------
        self
        """
        if self.trend not in ("plane", "mean", "none"):
            raise ValueError("trend must be 'plane', 'mean' or 'none'")
        if self.block_km <= 0 or self.max_points < 1:
            raise ValueError("block_km must be positive and max_points >= 1")
        for name in ("variance_mgal2", "length_km"):
            val = getattr(self, name)
            if val is not None and not val > 0:
                raise ValueError(f"{name} must be positive")
        if self.nugget_mgal2 is not None and self.nugget_mgal2 < 0:
            raise ValueError("nugget_mgal2 must be >= 0")
        te, tn, tv, ts = self._prepare(easting_km, northing_km, dg_mgal, std_mgal, line)
        self._origin = (float(np.mean(te)), float(np.mean(tn)))
        G = _trend_design(te, tn, self.trend, self._origin)
        if G.shape[1] and te.size > G.shape[1]:
            self.trend_coef_, *_ = np.linalg.lstsq(G, tv, rcond=None)
        elif G.shape[1]:
            self.trend_coef_ = np.zeros(G.shape[1])
            self.trend_coef_[0] = np.mean(tv)
        else:
            self.trend_coef_ = np.zeros(0)
        resid = tv - G.dot(self.trend_coef_)
        w, e_, s, n_ = self.region_
        extent = max(np.hypot(e_ - w, n_ - s), self.thin_km)
        max_lag = max(0.25 * extent, 4.0 * self.thin_km)
        if self.line_error_mgal2 < 0:
            raise ValueError("line_error_mgal2 must be >= 0")
        lag, cov, cnt, c0 = empirical_covariance(te, tn, resid, max_lag, seed=self.seed,
                                                 line_label=self._lab,
                                                 line_var_mgal2=float(self.line_error_mgal2))
        self.empirical_ = {"lag_km": lag, "cov_mgal2": cov, "count": cnt, "c0_mgal2": c0}
        if self.variance_mgal2 is None or self.length_km is None:
            if lag.size == 0:
                raise ValueError("too few data to estimate the covariance; give variance_mgal2 and length_km")
            if self.length_km is not None:
                L0 = np.log(float(self.length_km))
                var, length, off = fit_gm2(lag, cov, cnt, np.exp(L0), np.exp(L0))
            else:
                var, length, off = fit_gm2(lag, cov, cnt, 0.5 * self.thin_km, 2.0 * extent)
            if self.variance_mgal2 is not None:
                var = float(self.variance_mgal2)
        else:
            var, length, off = float(self.variance_mgal2), float(self.length_km), 0.0
        var = max(var, 1e-6 * c0, 1e-12)
        self.covariance_offset_mgal2_ = float(off)
        if self.nugget_mgal2 is None:
            # zero-lag excess of the empirical variance over the model (incl. its offset)
            nugget = max(0.0, c0 - (var + off) - float(np.mean(ts ** 2)))
        else:
            nugget = float(self.nugget_mgal2)
        self.variance_mgal2_ = float(var)
        self.length_km_ = float(length)
        self.nugget_mgal2_ = float(nugget)
        self._xy = np.column_stack([te, tn])
        self._resid = resid
        self._noise = ts ** 2 + nugget + 1e-10 * var
        self._tree = cKDTree(self._xy)
        return self

    def summary(self) -> dict:
        """JSON-able covariance model and data counts of the fit."""
        if not hasattr(self, "variance_mgal2_"):
            raise ValueError("call fit() first")
        return {"method": "collocation", "covariance": "gm2",
                "variance_mgal2": self.variance_mgal2_, "length_km": self.length_km_,
                "nugget_mgal2": self.nugget_mgal2_, "offset_mgal2": self.covariance_offset_mgal2_,
                "trend": self.trend, "trend_coef": [float(c) for c in self.trend_coef_],
                "line_error_mgal2": float(self.line_error_mgal2),
                "n_data": self.n_data_, "n_thinned": self.n_thinned_,
                "line_spacing_km": self.line_spacing_km_, "mask_km": self.mask_distance_km_}

    def _trend_at(self, pe, pn):
        G = _trend_design(pe, pn, self.trend, self._origin)
        return G.dot(self.trend_coef_) if G.shape[1] else np.zeros(pe.size)

    def _predict(self, pe, pn):
        var, L = self.variance_mgal2_, self.length_km_
        if pe.size == 0:
            return np.zeros(0), np.zeros(0)
        radius = (4.0 * L if self.search_radius_km is None else float(self.search_radius_km))
        half_diag = self.block_km / np.sqrt(2.0)
        k = min(self.max_points, self._xy.shape[0])
        out_v = np.empty(pe.size)
        out_s = np.empty(pe.size)
        bx = np.floor((pe - pe.min()) / self.block_km).astype(np.int64)
        by = np.floor((pn - pn.min()) / self.block_km).astype(np.int64)
        key = bx * (by.max() + 1) + by
        order = np.argsort(key, kind="stable")
        bounds = np.flatnonzero(np.diff(key[order])) + 1
        with single_thread_blas():
            self._solve_blocks(np.split(order, bounds), pe, pn, var, L, radius + half_diag, k,
                               out_v, out_s)
        return out_v + self._trend_at(pe, pn), out_s

    def _solve_blocks(self, groups, pe, pn, var, L, radius, k, out_v, out_s):
        for grp in groups:
            ce = 0.5 * (pe[grp].min() + pe[grp].max())
            cn = 0.5 * (pn[grp].min() + pn[grp].max())
            d, idx = self._tree.query([ce, cn], k=k, distance_upper_bound=radius)
            idx = np.atleast_1d(idx)[np.isfinite(np.atleast_1d(d))]
            if idx.size == 0:  # no data: prior
                out_v[grp] = 0.0
                out_s[grp] = np.sqrt(var)
                continue
            xy = self._xy[idx]
            K = _gm2_inplace(cdist(xy, xy), var, L)
            K.flat[::K.shape[0] + 1] += self._noise[idx]
            if self.line_error_mgal2 > 0:
                lab = self._lab[idx]
                K += self.line_error_mgal2 * (lab[:, None] == lab[None, :])
            Cdg = _gm2_inplace(cdist(xy, np.column_stack([pe[grp], pn[grp]])), var, L)
            c = _robust_cholesky(K, 1e-8 * var)
            A = solve_triangular(c, Cdg, lower=True, check_finite=False)
            b = solve_triangular(c, self._resid[idx], lower=True, check_finite=False)
            out_v[grp] = A.T.dot(b)
            out_s[grp] = np.sqrt(np.maximum(var - np.einsum("ij,ij->j", A, A), 0.0))


class Spline(_LineGridder):
    """Cubic (Clough–Tocher C¹) interpolation of block-averaged data.

    The simple alternative to :class:`Collocation` (seed 000 used a cubic
    spline).  ``dg_std`` of the grid is the linear interpolation of the block
    means' std: an indication, not a posterior std.  Outside the convex hull of
    the data the grid is NaN.

    Parameters
    ----------
    thin_km : float
        Block-averaging size (km) before interpolation.
    mask_km : float, optional
        As in :class:`Collocation`.
    """

    def __init__(self, *, thin_km: float = 0.5, mask_km=None):
        self.thin_km = thin_km
        self.mask_km = mask_km

    def fit(self, easting_km, northing_km, dg_mgal, std_mgal=None, line=None):
        """Fit to scattered line data (see :meth:`Collocation.fit`). Returns self."""
        from scipy.interpolate import CloughTocher2DInterpolator, LinearNDInterpolator
        from scipy.spatial import Delaunay

        te, tn, tv, ts = self._prepare(easting_km, northing_km, dg_mgal, std_mgal, line, per_line=False)
        if te.size < 3:
            raise ValueError("Spline needs at least 3 distinct data blocks")
        pts = np.column_stack([te, tn])
        try:
            tri = Delaunay(pts)  # one triangulation for both interpolants
            self._interp = CloughTocher2DInterpolator(tri, tv)
            self._interp_std = LinearNDInterpolator(tri, ts)
        except Exception as exc:  # collinear data (one straight line)
            raise ValueError(f"cannot triangulate the data (all on one straight line?): {exc}") from exc
        return self

    def _predict(self, pe, pn):
        q = np.column_stack([pe, pn])
        return np.asarray(self._interp(q), dtype=float), np.asarray(self._interp_std(q), dtype=float)


def cross_validated_std_factor(make_estimator, easting_km, northing_km, dg_mgal, std_mgal, line,
                               n_folds: int = 8, step_km: float = 1.0) -> dict:
    """Leave-line-out check of a gridder's posterior std: the factor to scale it by.

    For ``n_folds`` lines spread over the survey, the estimator is fitted without the
    line and predicts at that line's points (thinned to ``step_km``); the normalised
    residuals ``(prediction − data)/sqrt(σ_pred² + σ_data²)`` should have unit RMS if the
    std is right.  Held-out lines are farther from their neighbours than grid cells are
    from the lines, so this checks the covariance model where it is most stretched.

    Parameters
    ----------
    make_estimator : callable
        ``make_estimator() -> estimator`` with ``fit(e, n, dg, std, line=...)`` and
        ``predict(e, n, return_std=True)``.
    easting_km, northing_km, dg_mgal, std_mgal : ndarray, shape (n,)
    line : ndarray, shape (n,)
        Line label per point.
    n_folds : int
    step_km : float

    Returns
    -------
    dict
        ``factor`` (RMS of the normalised residuals, ≥ 0), ``n_points``, ``lines``.
    """
    e = np.asarray(easting_km, float)
    n = np.asarray(northing_km, float)
    v = np.asarray(dg_mgal, float)
    s = np.asarray(std_mgal, float)
    lab = np.asarray(line).astype(str)
    names = list(dict.fromkeys(lab))
    if len(names) < 3:
        raise ValueError("cross-validation needs at least 3 lines")
    folds = [names[i] for i in np.linspace(0, len(names) - 1, min(n_folds, len(names))).round().astype(int)]
    zs = []
    for name in dict.fromkeys(folds):
        held = lab == name
        idx = np.flatnonzero(held)
        de = np.diff(e[idx])
        dn = np.diff(n[idx])
        along = np.concatenate([[0.0], np.cumsum(np.hypot(de, dn))])
        pick = idx[np.unique(np.searchsorted(along, np.arange(0.0, along[-1], step_km)))]
        est = make_estimator()
        est.fit(e[~held], n[~held], v[~held], s[~held], line=lab[~held])
        pv, ps = est.predict(e[pick], n[pick], return_std=True)
        ok = np.isfinite(pv) & np.isfinite(ps)
        zs.append((pv[ok] - v[pick][ok]) / np.sqrt(ps[ok] ** 2 + s[pick][ok] ** 2))
    z = np.concatenate(zs) if zs else np.zeros(0)
    if z.size == 0:
        raise ValueError("no held-out point could be predicted")
    return {"factor": float(np.sqrt(np.mean(z ** 2))), "n_points": int(z.size), "lines": list(dict.fromkeys(folds))}


def line_std_floor(grid_easting_km, grid_northing_km, easting_km, northing_km, std_mgal, k: int = 8,
                   step: int = 10) -> np.ndarray:
    """Lower bound for a grid's std from the line estimates it is built from (mGal).

    Smoothed line estimates have errors correlated along the line over the smoother's
    resolution, so averaging neighbouring points does not beat them down by √N as the
    collocation's independent-error model assumes: a grid value cannot be more certain
    than the line estimates around it.  The bound at each node is the median posterior
    std of the ``k`` nearest line points (every ``step``-th point used).

    Parameters
    ----------
    grid_easting_km : ndarray, shape (nx,)
    grid_northing_km : ndarray, shape (ny,)
    easting_km, northing_km, std_mgal : ndarray, shape (n,)
        Line points and their posterior std.
    k, step : int

    Returns
    -------
    ndarray, shape (ny, nx)
    """
    from scipy.spatial import cKDTree

    e = np.asarray(easting_km, float)[::step]
    n = np.asarray(northing_km, float)[::step]
    s = np.asarray(std_mgal, float)[::step]
    ok = np.isfinite(e) & np.isfinite(n) & np.isfinite(s)
    if ok.sum() == 0:
        raise ValueError("no line points with a finite std")
    tree = cKDTree(np.column_stack([e[ok], n[ok]]))
    N, E = np.meshgrid(np.asarray(grid_northing_km, float), np.asarray(grid_easting_km, float), indexing="ij")
    kk = int(min(k, ok.sum()))
    _, idx = tree.query(np.column_stack([E.ravel(), N.ravel()]), k=kk)
    idx = np.asarray(idx).reshape(E.size, kk)
    return np.median(s[ok][idx], axis=1).reshape(N.shape)
