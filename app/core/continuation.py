"""Continuation of line anomalies to a common datum by equivalent sources, with posterior std.

Model
    The anomaly (mGal) at the block-averaged line points is ``d = μ + J c + e``: ``μ`` the
    weighted mean (a constant is harmonic and continues unchanged), ``J`` the Green's
    functions ``1/r`` of point sources (harmonica's ``EquivalentSources`` kernel, coordinates
    in metres, planar), ``e ~ N(0, ν² diag(σ²))`` with ``σ`` the std of each block mean and
    ``ν`` a noise scale.  The coefficients are scaled per column (``J̃ = J S⁻¹``, ``S`` the
    column standard deviations, as verde's ``least_squares`` does) with the prior
    ``S c ~ N(0, I/α)``; ``α`` (= harmonica's ``damping``) and ``ν`` are chosen by maximising
    the marginal likelihood (type-II maximum likelihood, closed form through one
    eigendecomposition of ``J̃ᵀWJ̃``).  The posterior of ``c`` is Gaussian, so the prediction
    at any point and height has mean ``μ + g̃ᵀc̃`` and variance ``g̃ᵀ(J̃ᵀWJ̃/ν² + αI)⁻¹g̃``
    (+ the variance of ``μ``): the **posterior std of the linear fit**.

    ``method="exact"`` solves this globally (the default up to ``max_exact_sources``
    sources).  ``method="gb"`` (larger surveys) fits the mean with harmonica's
    ``EquivalentSourcesGB`` (gradient boosting over overlapping windows, the same sources,
    weights ``1/(ν²σ²)`` and ``damping = α`` from an exact fit on a sub-area) and computes
    the std by the same closed form on local windows (each prediction tile with the data
    and sources within ``std_window_m`` of it): a local posterior that equals the global
    one when the window spans a few source depths (tests/core/test_continuation.py checks
    it against the global posterior and against truth).

Data
    Dense along-line data (10 Hz ≈ 10 m) are averaged per line over ``block_m`` of track
    (:func:`block_average_lines`).  The errors of smoothed line estimates are correlated
    along the line over ``error_corr_m`` (km), so each block counts as ``block_m /
    error_corr_m`` of an independent datum: its variance is the mean epoch variance ×
    ``error_corr_m / block_m`` (information-equivalent weighting).  Without it the fit
    treats correlated errors as independent and its posterior std is over-confident.

Sources
    One source under each block-median of the data on ``source_spacing_m`` squares
    (harmonica's block-averaged sources, Soler & Uieda 2021), at ``depth_m`` below its data
    point (relative depth).  Default ``depth_m = depth_factor × line spacing`` with
    ``depth_factor = 1`` and ``source_spacing_m`` = half the line spacing (measured on
    simulated draped surveys: docs/METHOD-products.md).

Units: metres for coordinates and heights (``easting_m = 1000·easting_km``), mGal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_factor, cho_solve, eigh
from scipy.optimize import minimize, minimize_scalar
from scipy.spatial import cKDTree

from app.core.gridding import line_spacing_km, single_thread_blas

#: above this many sources ``method="auto"`` switches from the exact global solve to "gb"
MAX_EXACT_SOURCES = 4000
#: sources of the central sub-area whose exact fit gives α (and ν) for method "gb"
HYPER_SOURCES = 1500


# --------------------------------------------------------------------------- data thinning

def block_average_lines(easting_m, northing_m, height_m, dg_mgal, std_mgal, line, block_m: float = 500.0,
                        error_corr_m: float | None = None) -> dict:
    """Per-line block means over ``block_m`` of along-track distance.

    Parameters
    ----------
    easting_m, northing_m, height_m, dg_mgal, std_mgal : array_like, shape (n,)
        Epochs in time order within each line; NaN values of ``dg`` or ``std`` are dropped.
    line : array_like, shape (n,)
        Line label of each epoch.
    block_m : float
        Block length along the track (m).
    error_corr_m : float or None
        Along-line correlation length of the errors; None: ``block_m`` (block std = rms std).

    Returns
    -------
    dict of ndarray, shape (m,)
        ``easting_m, northing_m, height_m, dg_mgal, std_mgal, count, line``.
    """
    e, n, h, v, s = (np.asarray(a, dtype=float) for a in (easting_m, northing_m, height_m, dg_mgal, std_mgal))
    lab = np.asarray(line)
    ok = np.isfinite(e) & np.isfinite(n) & np.isfinite(h) & np.isfinite(v) & np.isfinite(s)
    corr = block_m if error_corr_m is None else float(error_corr_m)
    out = {k: [] for k in ("easting_m", "northing_m", "height_m", "dg_mgal", "std_mgal", "count", "line")}
    _, inv = np.unique(lab, return_inverse=True)
    for k in np.unique(inv):
        idx = np.flatnonzero((inv == k) & ok)
        if idx.size == 0:
            continue
        ds = np.hypot(np.diff(e[idx]), np.diff(n[idx]))
        sdist = np.concatenate([[0.0], np.cumsum(ds)])
        b = np.floor(sdist / block_m).astype(np.int64)
        _, bi, cnt = np.unique(b, return_inverse=True, return_counts=True)

        def mean(x, bi=bi, idx=idx, cnt=cnt):
            return np.bincount(bi, weights=x[idx]) / cnt

        step = float(np.median(ds)) if ds.size else block_m
        n_eff = np.clip(cnt * step / corr, 1.0, cnt) if corr > 0 else cnt.astype(float)
        # errors correlated beyond one block: each block carries block/corr of an independent
        # datum (information-equivalent weighting, so the fit's posterior is not over-confident)
        n_eff = n_eff * min(1.0, block_m / corr) if corr > 0 else n_eff
        out["easting_m"].append(mean(e))
        out["northing_m"].append(mean(n))
        out["height_m"].append(mean(h))
        out["dg_mgal"].append(mean(v))
        out["std_mgal"].append(np.sqrt(mean(s ** 2) / n_eff))
        out["count"].append(cnt)
        out["line"].append(np.full(cnt.size, lab[idx[0]], dtype=object))
    return {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in out.items()}


def line_spacing_m(easting_m, northing_m, line) -> float:
    """Median distance from a line point to the nearest point of another line (m)."""
    return 1000.0 * line_spacing_km(np.asarray(easting_m) / 1000.0, np.asarray(northing_m) / 1000.0, line)


def block_sources(easting_m, northing_m, height_m, spacing_m: float, depth_m: float):
    """Sources under the block medians of the data positions on ``spacing_m`` squares,
    ``depth_m`` below the median height (harmonica's block-averaged source layout)."""
    import verde as vd  # heavy (~1.3 s with xarray): only when a continuation is fitted

    red = vd.BlockReduce(np.median, spacing=spacing_m, drop_coords=False)
    (se, sn, su), _ = red.filter((np.asarray(easting_m), np.asarray(northing_m), np.asarray(height_m)),
                                 np.zeros(np.size(easting_m)))
    return np.asarray(se, float), np.asarray(sn, float), np.asarray(su, float) - depth_m


# --------------------------------------------------------------------------- Bayesian solve

def _greens(e, n, u, src, parallel=True):
    """Jacobian (n_points, n_sources) of the 1/r point sources (harmonica's kernel)."""
    import harmonica as hm  # heavy (~1.4 s with verde/xarray): only when a continuation is fitted

    eqs = hm.EquivalentSources(parallel=parallel)
    return eqs.jacobian((np.asarray(e, float), np.asarray(n, float), np.asarray(u, float)), src)


@dataclass
class _Posterior:
    """Eigen-form of the posterior for one set of sources and data (all in the scaled basis)."""

    scale: np.ndarray        # column scales S (n_sources,)
    evec: np.ndarray         # V (M, M)
    lam0: np.ndarray         # eigenvalues of J̃ᵀ W0 J̃ (W0 = diag(1/σ²))
    b0: np.ndarray           # Vᵀ J̃ᵀ W0 d (rotated)
    dWd0: float
    logdet_sigma0: float
    n: int

    def log_evidence(self, log_alpha: float, log_nu: float) -> float:
        a, nu2 = np.exp(log_alpha), np.exp(2 * log_nu)
        lam = self.lam0 / nu2
        b = self.b0 / nu2
        quad = self.dWd0 / nu2 - np.sum(b * b / (lam + a))
        logdet = self.logdet_sigma0 + self.n * np.log(nu2) + np.sum(np.log1p(lam / a))
        return -0.5 * (quad + logdet + self.n * np.log(2 * np.pi))

    def coefs(self, alpha: float, nu: float) -> np.ndarray:
        nu2 = nu * nu
        ct = self.evec @ ((self.b0 / nu2) / (self.lam0 / nu2 + alpha))
        return ct / self.scale

    def var(self, g: np.ndarray, alpha: float, nu: float) -> np.ndarray:
        """Prediction variances for Green's rows ``g`` (P, M) in the unscaled basis."""
        gt = (g / self.scale) @ self.evec
        return np.sum(gt * gt / (self.lam0 / (nu * nu) + alpha), axis=1)


def _posterior(jac: np.ndarray, d: np.ndarray, sigma: np.ndarray) -> _Posterior:
    scale = jac.std(axis=0)
    scale[scale <= 0] = 1.0
    jt = jac / scale
    w = 1.0 / sigma ** 2
    jw = jt * w[:, None]
    B = jt.T @ jw
    lam, V = eigh(B, overwrite_a=True, check_finite=False)
    lam = np.clip(lam, 0.0, None)
    b = V.T @ (jw.T @ d)
    return _Posterior(scale, V, lam, b, float(np.sum(w * d * d)), float(np.sum(np.log(sigma ** 2))), d.size)


def _optimise(post: _Posterior, fit_noise_scale: bool):
    """Maximise the evidence over log α (and log ν): a coarse grid, then Nelder–Mead."""
    grid_a = np.linspace(np.log(1e-8), np.log(1e4), 25)
    grid_n = np.linspace(np.log(0.3), np.log(3.0), 9) if fit_noise_scale else np.array([0.0])
    best = max((post.log_evidence(a, v), a, v) for a in grid_a for v in grid_n)
    if fit_noise_scale:
        res = minimize(lambda x: -post.log_evidence(x[0], x[1]), x0=[best[1], best[2]], method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-4})
        la, ln = res.x
    else:
        res = minimize(lambda x: -post.log_evidence(x[0], 0.0), x0=[best[1]], method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-4})
        la, ln = res.x[0], 0.0
    return float(np.exp(la)), float(np.exp(ln)), float(post.log_evidence(la, ln))


# --------------------------------------------------------------------------- the model

@dataclass
class EquivalentSourceModel:
    """A fitted continuation: ``predict(e, n, h)`` and ``predict_std(e, n, h)`` (m in, mGal out)."""

    method: str
    sources: tuple                      # (easting_m, northing_m, upward_m) of the sources
    coefs: np.ndarray
    mean_mgal: float
    mean_var: float
    damping: float                      # α (harmonica's damping in verde's scaled basis)
    noise_scale: float                  # ν: the data stds were multiplied by this
    depth_m: float
    data: dict                          # the block-averaged data used
    info: dict = field(default_factory=dict)
    _post: _Posterior | None = None
    _local: dict | None = None

    def predict(self, easting_m, northing_m, height_m, chunk: int = 20000) -> np.ndarray:
        """Continued anomaly (mGal) at points and heights (any broadcastable shapes)."""
        import harmonica as hm  # heavy (~1.4 s with verde/xarray): only when a continuation is used

        e, n, h = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (easting_m, northing_m, height_m)))
        shape = e.shape
        e, n, h = e.ravel(), n.ravel(), h.ravel()
        eqs = hm.EquivalentSources()
        eqs.points_ = tuple(np.asarray(v, float) for v in self.sources)
        eqs.coefs_ = self.coefs
        out = np.empty(e.size)
        for i in range(0, e.size, chunk):
            sl = slice(i, i + chunk)
            out[sl] = eqs.predict((e[sl], n[sl], h[sl]))
        return (out + self.mean_mgal).reshape(shape)

    def predict_std(self, easting_m, northing_m, height_m, chunk: int = 2000) -> np.ndarray:
        """Posterior std (mGal) of the continued anomaly at points and heights."""
        e, n, h = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (easting_m, northing_m, height_m)))
        shape = e.shape
        e, n, h = e.ravel(), n.ravel(), h.ravel()
        var = np.empty(e.size)
        if self.method == "exact":
            for i in range(0, e.size, chunk):
                sl = slice(i, i + chunk)
                g = _greens(e[sl], n[sl], h[sl], self.sources)
                var[sl] = self._post.var(g, self.damping, self.noise_scale)
        else:
            with single_thread_blas():
                var = _local_variance(self, e, n, h)
        return np.sqrt(var + self.mean_var).reshape(shape)


def _local_variance(model: EquivalentSourceModel, e, n, h) -> np.ndarray:
    """Posterior variance from local windows (method "gb"): tiles of ``tile_m``; each solved with
    the data and sources within ``std_window_m`` of the tile, the global α and ν."""
    loc = model._local
    tile, win = loc["tile_m"], loc["window_m"]
    d = model.data
    de, dn, du, ds = d["easting_m"], d["northing_m"], d["height_m"], d["std_mgal"] * model.noise_scale
    se, sn, su = model.sources
    dtree = cKDTree(np.column_stack([de, dn]))
    stree = cKDTree(np.column_stack([se, sn]))
    ix = np.floor(e / tile).astype(np.int64)
    iy = np.floor(n / tile).astype(np.int64)
    keys, inv = np.unique(np.column_stack([ix, iy]), axis=0, return_inverse=True)
    inv = inv.ravel()
    var = np.empty(e.size)
    cache = {}
    for t, (kx, ky) in enumerate(keys):
        cx, cy = (kx + 0.5) * tile, (ky + 0.5) * tile
        r = win + tile / np.sqrt(2.0)
        di = np.asarray(dtree.query_ball_point([cx, cy], r), dtype=np.int64)
        si = np.asarray(stree.query_ball_point([cx, cy], r), dtype=np.int64)
        pts = np.flatnonzero(inv == t)
        if di.size == 0 or si.size == 0:
            var[pts] = np.nan
            continue
        jac = _greens(de[di], dn[di], du[di], (se[si], sn[si], su[si]))
        # same scaling convention as the global fit (scales of the full Jacobian columns)
        scale = loc["scale"][si]
        jt = jac / scale
        w = 1.0 / ds[di] ** 2
        A = jt.T @ (jt * w[:, None]) + model.damping * np.eye(si.size)
        cf = cho_factor(A, lower=True, check_finite=False)
        g = _greens(e[pts], n[pts], h[pts], (se[si], sn[si], su[si])) / scale
        var[pts] = np.sum(g * cho_solve(cf, g.T, check_finite=False).T, axis=1)
        cache[t] = si.size
    return var


def fit_equivalent_sources(easting_m, northing_m, height_m, dg_mgal, std_mgal, line=None, *,
                           block_m: float = 500.0, error_corr_m: float | None = 2000.0,
                           depth_m: float | None = None, depth_factor: float = 1.0,
                           source_spacing_m: float | None = None, damping: float | None = None,
                           noise_scale: float | None = 1.0, method: str = "auto",
                           max_exact_sources: int = MAX_EXACT_SOURCES, window_m: float | None = None,
                           std_window_m: float | None = None, random_state: int = 0) -> EquivalentSourceModel:
    """Fit equivalent sources to line estimates weighted by their posterior std.

    Parameters
    ----------
    easting_m, northing_m, height_m : array_like, shape (n,)
        Epoch positions (m, projected CRS) and heights (m, the same vertical reference as the
        datum), in time order within each line.
    dg_mgal, std_mgal : array_like, shape (n,)
        Line estimates and their posterior std (mGal).
    line : array_like, shape (n,), optional
        Line labels (None: the points are already thinned; no block averaging).
    block_m, error_corr_m
        Along-line block averaging (:func:`block_average_lines`); ``error_corr_m`` is the
        along-line correlation length of the line errors (default 2 km): blocks are weighted
        as ``block_m / error_corr_m`` independent data, which calibrates the posterior std
        (z-score of the continued anomaly vs truth 0.95 with the true 3 km, 1.1 with 2 km).
    depth_m, depth_factor
        Source depth below the data (m); None: ``depth_factor ×`` the line spacing.
    source_spacing_m
        Block size for the source layout (m); None: half the line spacing.
    damping, noise_scale
        α and ν (module docstring); None: by maximum marginal likelihood.  Default: α by
        marginal likelihood, ν = 1 (the line stds are trusted; with along-line correlated
        errors the evidence attributes part of the error to signal and fits ν ≈ 0.2–0.5,
        which makes the posterior std over-confident by 2–4×: docs/METHOD-products.md).
    method : {"auto", "exact", "gb"}
        "auto": "exact" up to ``max_exact_sources`` sources, else "gb".
    window_m
        Window size of ``EquivalentSourcesGB`` (None: 10 × the line spacing, at most half the
        survey's smaller side).
    std_window_m
        Half-size of the local std windows for "gb" (None: 4 × depth + tile).

    Returns
    -------
    EquivalentSourceModel
    """
    d = _continuation_data(easting_m, northing_m, height_m, dg_mgal, std_mgal, line, block_m, error_corr_m)
    e, n, h, v, s = d["easting_m"], d["northing_m"], d["height_m"], d["dg_mgal"], d["std_mgal"]
    spacing = line_spacing_m(e, n, d["line"]) if line is not None else np.nan
    if not np.isfinite(spacing):
        dist, _ = cKDTree(np.column_stack([e, n])).query(np.column_stack([e, n]), k=2)
        spacing = float(np.median(dist[:, 1])) * 4.0
    depth = float(depth_m) if depth_m is not None else depth_factor * spacing
    src_sp = float(source_spacing_m) if source_spacing_m is not None else 0.5 * spacing
    sources = block_sources(e, n, h, src_sp, depth)
    m_src = sources[0].size
    if method == "auto":
        method = "exact" if m_src <= max_exact_sources else "gb"
    if method not in ("exact", "gb"):
        raise ValueError(f"unknown method {method!r}")
    w = 1.0 / s ** 2
    mu = float(np.sum(w * v) / np.sum(w))
    info = {"n_data": int(e.size), "n_sources": int(m_src), "line_spacing_m": float(spacing),
            "source_spacing_m": src_sp, "block_m": block_m}
    fit = _Fit(d, sources, v - mu, mu, float(np.sum(w)), depth, spacing, info)
    if method == "exact":
        return _fit_exact(fit, damping, noise_scale)
    return _fit_gb(fit, damping, noise_scale, max_exact_sources, window_m, std_window_m, random_state)


def _continuation_data(easting_m, northing_m, height_m, dg_mgal, std_mgal, line, block_m: float,
                       error_corr_m: float | None) -> dict:
    """The data of a fit: block means per line (:func:`block_average_lines`), or the points as
    given when ``line`` is None; at least 10 of them, every std positive."""
    if line is not None:
        d = block_average_lines(easting_m, northing_m, height_m, dg_mgal, std_mgal, line, block_m, error_corr_m)
    else:
        d = {"easting_m": np.asarray(easting_m, float), "northing_m": np.asarray(northing_m, float),
             "height_m": np.asarray(height_m, float), "dg_mgal": np.asarray(dg_mgal, float),
             "std_mgal": np.asarray(std_mgal, float), "count": np.ones(np.size(easting_m), int),
             "line": np.zeros(np.size(easting_m), dtype=object)}
    if d["easting_m"].size < 10:
        raise ValueError(f"continuation needs at least 10 data blocks, got {d['easting_m'].size}")
    if np.any(d["std_mgal"] <= 0):
        raise ValueError("every std must be positive")
    return d


@dataclass
class _Fit:
    """What both solvers share: the data, the sources and the weighted mean taken out."""

    data: dict             # block-averaged data (easting_m, northing_m, height_m, dg_mgal, std_mgal, …)
    sources: tuple         # (easting_m, northing_m, upward_m)
    residual: np.ndarray   # dg − mean (mGal)
    mean_mgal: float       # weighted mean μ
    sum_weights: float     # Σ 1/σ² (the variance of μ is ν²/Σw)
    depth_m: float
    spacing_m: float       # line spacing (or its stand-in)
    info: dict


def _fit_exact(fit: _Fit, damping, noise_scale) -> EquivalentSourceModel:
    """Global solve: the posterior in eigen-form, α (and ν) by maximum evidence unless given."""
    d = fit.data
    jac = _greens(d["easting_m"], d["northing_m"], d["height_m"], fit.sources)
    post = _posterior(jac, fit.residual, d["std_mgal"])
    del jac
    if damping is None:
        a, nu, ev = _optimise(post, noise_scale is None)
        if noise_scale is not None:
            nu = float(noise_scale)
            a, _, ev = _optimise_alpha_only(post, nu)
    else:
        a = float(damping)
        nu = float(noise_scale) if noise_scale is not None else 1.0
        ev = post.log_evidence(np.log(a), np.log(nu))
    coefs = post.coefs(a, nu)
    fit.info.update(log_evidence=ev)
    return EquivalentSourceModel("exact", fit.sources, coefs, fit.mean_mgal, float(nu * nu / fit.sum_weights), a, nu,
                                 fit.depth_m, d, fit.info, _post=post)


def _gb_hyperparameters(fit: _Fit, damping, noise_scale, max_exact_sources: int) -> tuple[float, float]:
    """``(α, ν)`` for method "gb": the given ones, else from an exact fit on the sub-area around the
    centre (≤ ``min(max_exact_sources, HYPER_SOURCES)`` sources), recorded in ``info``."""
    a, nu = damping, noise_scale
    if a is None or nu is None:
        d, sources = fit.data, fit.sources
        e, n, h, s, r = d["easting_m"], d["northing_m"], d["height_m"], d["std_mgal"], fit.residual
        ce, cn = np.median(e), np.median(n)
        order = np.argsort(np.hypot(sources[0] - ce, sources[1] - cn), kind="stable")   # a grid has ties
        keep_s = order[:min(max_exact_sources, HYPER_SOURCES)]
        rad = np.hypot(sources[0][keep_s] - ce, sources[1][keep_s] - cn).max()
        keep_d = np.hypot(e - ce, n - cn) <= rad
        sub = tuple(x[keep_s] for x in sources)
        post_sub = _posterior(_greens(e[keep_d], n[keep_d], h[keep_d], sub), r[keep_d], s[keep_d])
        if nu is not None:
            a_fit, _, _ = _optimise_alpha_only(post_sub, float(nu))
        else:
            a_fit, nu_fit, _ = _optimise(post_sub, True)
            nu = nu_fit
        a = a_fit if a is None else a
        fit.info["hyper_subarea"] = {"n_sources": int(keep_s.size), "n_data": int(keep_d.sum()),
                                     "radius_m": float(rad)}
    return float(a), float(nu)


def _jacobian_column_scales(e, n, h, sources) -> np.ndarray:
    """Std of every column of the full Jacobian, in chunks of sources (memory: n_data × chunk);
    1 for a column without variation."""
    m_src = sources[0].size
    scale = np.empty(m_src)
    step = max(1, int(2e7 // max(e.size, 1)))
    for i in range(0, m_src, step):
        sl = slice(i, i + step)
        scale[i:i + step] = _greens(e, n, h, tuple(x[sl] for x in sources)).std(axis=0)
    scale[scale <= 0] = 1.0
    return scale


def _fit_gb(fit: _Fit, damping, noise_scale, max_exact_sources: int, window_m, std_window_m,
            random_state: int) -> EquivalentSourceModel:
    """Gradient-boosted mean (harmonica's ``EquivalentSourcesGB``), std from local windows."""
    import harmonica as hm  # heavy (~1.4 s with verde/xarray): only when a continuation is fitted

    d = fit.data
    e, n, h, s = d["easting_m"], d["northing_m"], d["height_m"], d["std_mgal"]
    a, nu = _gb_hyperparameters(fit, damping, noise_scale, max_exact_sources)
    if window_m is None:
        win = min(10.0 * fit.spacing_m, 0.5 * min(np.ptp(e), np.ptp(n)))
    else:
        win = float(window_m)
    gb = hm.EquivalentSourcesGB(damping=a, points=fit.sources, window_size=win, random_state=random_state)
    gb.fit((e, n, h), fit.residual, weights=1.0 / (nu * s) ** 2)
    scale = _jacobian_column_scales(e, n, h, fit.sources)
    tile = max(2.0 * fit.spacing_m, 2000.0)
    std_win = float(std_window_m) if std_window_m is not None else 4.0 * fit.depth_m + tile
    fit.info.update(window_m=win, std_tile_m=tile, std_window_m=std_win,
                    gb_rmse_first_last=[float(gb.rmse_per_iteration_[0]), float(gb.rmse_per_iteration_[-1])])
    return EquivalentSourceModel("gb", fit.sources, np.asarray(gb.coefs_, float), fit.mean_mgal,
                                 float(nu * nu / fit.sum_weights), a, nu, fit.depth_m, d, fit.info,
                                 _local={"tile_m": tile, "window_m": std_win, "scale": scale})


def _optimise_alpha_only(post: _Posterior, nu: float):
    ln = np.log(nu)
    grid = np.linspace(np.log(1e-8), np.log(1e4), 25)
    vals = [post.log_evidence(x, ln) for x in grid]
    i = int(np.argmax(vals))
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
    res = minimize_scalar(lambda x: -post.log_evidence(x, ln), bounds=(lo, hi), method="bounded")
    return float(np.exp(res.x)), nu, float(-res.fun)


def draped_datum_height_m(easting_m, northing_m, line_easting_m, line_northing_m, line_height_m,
                          smoothing_m: float = 2000.0) -> np.ndarray:
    """A smooth draped datum surface at arbitrary points: the Gaussian-weighted mean
    (``smoothing_m`` standard deviation) of the flight heights, from the nearest 64 line points.

    Useful for ``datum = "draped"``: predict the anomaly at ``(e, n, draped_datum_height_m(e, n, …))``.
    """
    le, ln, lh = (np.asarray(v, dtype=float).ravel() for v in (line_easting_m, line_northing_m, line_height_m))
    e, n = np.broadcast_arrays(np.asarray(easting_m, float), np.asarray(northing_m, float))
    tree = cKDTree(np.column_stack([le, ln]))
    k = min(64, le.size)
    dist, idx = tree.query(np.column_stack([e.ravel(), n.ravel()]), k=k)
    dist, idx = dist.reshape(-1, k), idx.reshape(-1, k)
    w = np.exp(-0.5 * (dist / smoothing_m) ** 2) + 1e-300
    return (np.sum(w * lh[idx], axis=1) / np.sum(w, axis=1)).reshape(e.shape)
