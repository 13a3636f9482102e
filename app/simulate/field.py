"""Anomaly field at flight height: harmonica point masses on a grid, bicubic interpolant.

Two parts: a "mountainous" part (many shallow sources, inside ridge bands, short
wavelengths) and a "plain" part (sparse deep sources everywhere, smooth).  The
gravity disturbance δg (mGal, positive for a mass excess) is harmonica's
``g_z`` (downward component) of the sources, evaluated on a regular grid at the
flight height and interpolated with a bicubic spline.

For draped flight (the height varies along the lines) the same field is evaluated
exactly at any point and height from the scaled sources (:meth:`AnomalyField.at`):
``δg = Σ_mountain g_z + Σ_plain g_z − offset`` with the masses already scaled to the
target standard deviations and ``offset`` the plain part's mean on the nominal grid
(so ``at(x, y, height_m)`` equals the grid values).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import RectBivariateSpline


@dataclass
class Ridges:
    """Mountain mask: union of straight bands (km relative to the survey centre)."""

    x_km: np.ndarray        # a point on each ridge axis
    y_km: np.ndarray
    angle_rad: np.ndarray   # axis direction, from north, clockwise
    half_width_km: np.ndarray

    def contains(self, x_km, y_km) -> np.ndarray:
        """Boolean mask, same shape as the broadcast inputs."""
        x = np.asarray(x_km, dtype=float)
        y = np.asarray(y_km, dtype=float)
        inside = np.zeros(np.broadcast(x, y).shape, dtype=bool)
        for xc, yc, a, w in zip(self.x_km, self.y_km, self.angle_rad, self.half_width_km):
            # distance from the axis through (xc, yc) with direction (sin a, cos a)
            d = np.abs((x - xc) * np.cos(a) - (y - yc) * np.sin(a))
            inside |= d < w
        return inside


def make_ridges(width_km: float, rng) -> Ridges:
    """Ridge bands crossing the east–west lines, about 35 % of the area."""
    n = max(1, int(round(width_km / 70.0)))
    cell = width_km / n
    xs = -width_km / 2 + (np.arange(n) + 0.5) * cell + rng.uniform(-0.15, 0.15, n) * cell
    ang = np.deg2rad(rng.uniform(-25.0, 25.0, n))
    w = np.clip(0.18 * cell, 3.0, 15.0) * rng.uniform(0.85, 1.15, n)
    return Ridges(xs, np.zeros(n), ang, w)


@dataclass
class AnomalyField:
    """Gridded δg at flight height and its bicubic interpolant (coordinates in km, absolute CRS)."""

    easting_km: np.ndarray      # (nx,)
    northing_km: np.ndarray     # (ny,)
    dg_mgal: np.ndarray         # (ny, nx)
    e0_km: float                # survey centre in the CRS
    n0_km: float
    ridges: Ridges
    info: dict
    sources: dict | None = None  # {"x_m", "y_m", "z_m", "mass_kg"} (relative to the centre, scaled), "offset_mgal"

    def __post_init__(self):
        self._spl = RectBivariateSpline(self.northing_km, self.easting_km, self.dg_mgal, kx=3, ky=3)

    def __call__(self, easting_km, northing_km) -> np.ndarray:
        """δg (mGal) at absolute projected coordinates (km)."""
        return self._spl.ev(np.asarray(northing_km, float), np.asarray(easting_km, float))

    def at(self, easting_km, northing_km, height_m) -> np.ndarray:
        """δg (mGal) at absolute projected coordinates (km) and heights (m), straight from the sources."""
        import harmonica as hm

        e = np.asarray(easting_km, dtype=float)
        n = np.asarray(northing_km, dtype=float)
        h = np.broadcast_to(np.asarray(height_m, dtype=float), e.shape)
        src = self.sources
        coords = ((e.ravel() - self.e0_km) * 1000.0, (n.ravel() - self.n0_km) * 1000.0, h.ravel())
        g = hm.point_gravity(coords, (src["x_m"], src["y_m"], src["z_m"]), src["mass_kg"], field="g_z",
                             parallel=True)
        if "prisms_m" in src:
            g = g + _prism_gz(coords, {"bounds_m": src["prisms_m"], "density_kgm3": src["prism_density_kgm3"]})
        return (g - src["offset_mgal"]).reshape(e.shape)

    def terrain_mountain(self, easting_km, northing_km) -> np.ndarray:
        return self.ridges.contains(np.asarray(easting_km) - self.e0_km, np.asarray(northing_km) - self.n0_km)


def make_field(cfg, extent_km, e0_km: float, n0_km: float, rng, line_pts_km=None) -> AnomalyField:
    """Forward-model the anomaly on a grid covering ``extent_km`` plus a margin.

    Parameters
    ----------
    extent_km : (xmin, xmax, ymin, ymax)
        Extent of the flight paths relative to the survey centre (km).
    e0_km, n0_km : float
        Survey centre in the projected CRS (km).
    line_pts_km : (x, y) arrays, optional
        Points on the line windows (relative km); with ``cfg.field_std_over == "lines"`` the target
        standard deviations (and the plain part's zero mean) hold along these points at the nominal
        height instead of over the grid.
    """
    import harmonica as hm

    xmin, xmax, ymin, ymax = extent_km
    m = cfg.grid_margin_km
    sp = cfg.grid_spacing_km
    xg = np.arange(np.floor((xmin - m) / sp) * sp, xmax + m + sp, sp)
    yg = np.arange(np.floor((ymin - m) / sp) * sp, ymax + m + sp, sp)
    X, Y = np.meshgrid(xg, yg)
    ridges = make_ridges(xmax - xmin, rng)
    if cfg.mountain_sources_per_km2 <= 0:
        # no mountain sources: no mountain terrain either (the ridges are still drawn, so the random
        # stream and everything after it are as with mountains)
        ridges = Ridges(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    obs = (X.ravel() * 1000.0, Y.ravel() * 1000.0, np.full(X.size, cfg.height_m))
    # a little beyond the grid so edges are not source-free
    sx0, sx1, sy0, sy1 = xg[0] - 5, xg[-1] + 5, yg[0] - 5, yg[-1] + 5
    area = (sx1 - sx0) * (sy1 - sy0)
    # mountains: shallow sources inside the ridge bands (cfg.mountain_depth_m below a 500 m surface)
    n_try = int(cfg.mountain_sources_per_km2 * area)
    px = rng.uniform(sx0, sx1, n_try)
    py = rng.uniform(sy0, sy1, n_try)
    keep = ridges.contains(px, py)
    px, py = px[keep], py[keep]
    prisms = None
    bodies = getattr(cfg, "mountain_bodies", "points")
    if bodies not in ("points", "prisms"):
        raise ValueError(f"mountain_bodies must be 'points' or 'prisms', got {bodies!r}")
    if bodies == "prisms":
        prisms = _mountain_prisms(cfg, px, py, rng)
        px = py = pz = mass = np.zeros(0)
        g_m = _prism_gz(obs, prisms)
    else:
        pz = 500.0 - rng.uniform(*cfg.mountain_depth_m, px.size)
        mass = rng.standard_normal(px.size) * 1e10
        g_m = np.zeros(X.size)
        if px.size:
            g_m = hm.point_gravity(obs, (px * 1000.0, py * 1000.0, pz), mass, field="g_z", parallel=True)
    mask_grid = ridges.contains(X, Y).ravel()
    along = getattr(cfg, "field_std_over", "grid") == "lines"
    if along:
        if line_pts_km is None:
            raise ValueError('field_std_over = "lines" needs the line points')
        lx, ly = (np.asarray(v, dtype=float) for v in line_pts_km)
        lobs = (lx * 1000.0, ly * 1000.0, np.full(lx.size, cfg.height_m))
        lmask = ridges.contains(lx, ly)
        if prisms is not None:
            g_ml = _prism_gz(lobs, prisms)
        else:
            g_ml = (hm.point_gravity(lobs, (px * 1000.0, py * 1000.0, pz), mass, field="g_z", parallel=True)
                    if px.size else np.zeros(lx.size))
        s = np.std(g_ml[lmask]) if lmask.any() else np.std(g_ml)
    else:
        s = np.std(g_m[mask_grid]) if mask_grid.any() else np.std(g_m)
    f_m = (cfg.mountain_std_mgal / s) if s > 0 else 1.0
    g_m = g_m * (cfg.mountain_std_mgal / s) if s > 0 else g_m
    # plain: sparse deep sources everywhere
    n_p = max(8, int(cfg.plain_sources_per_km2 * area))
    qx = rng.uniform(sx0 - 20, sx1 + 20, n_p)
    qy = rng.uniform(sy0 - 20, sy1 + 20, n_p)
    qz = -rng.uniform(*cfg.plain_depth_m, n_p)
    mass_p = rng.standard_normal(n_p) * 1e12
    g_p = hm.point_gravity(obs, (qx * 1000.0, qy * 1000.0, qz), mass_p, field="g_z", parallel=True)
    if along:
        g_pl = hm.point_gravity(lobs, (qx * 1000.0, qy * 1000.0, qz), mass_p, field="g_z", parallel=True)
        mu_p, f_p = np.mean(g_pl), cfg.plain_std_mgal / np.std(g_pl)
        g_p = (g_p - mu_p) * f_p
    else:
        mu_p, f_p = np.mean(g_p), cfg.plain_std_mgal / np.std(g_p)
        g_p = (g_p - np.mean(g_p)) * (cfg.plain_std_mgal / np.std(g_p))
    dg = (g_m + g_p).reshape(X.shape)
    sources = {"x_m": np.concatenate([px, qx]) * 1000.0, "y_m": np.concatenate([py, qy]) * 1000.0,
               "z_m": np.concatenate([pz, qz]), "mass_kg": np.concatenate([mass * f_m, mass_p * f_p]),
               "offset_mgal": float(mu_p * f_p), "n_mountain": int(px.size)}
    if prisms is not None:
        sources["prisms_m"] = prisms["bounds_m"]
        sources["prism_density_kgm3"] = prisms["density_kgm3"] * f_m
    info = {"n_mountain_sources": int(px.size if prisms is None else prisms["bounds_m"].shape[0]),
            **({} if prisms is None else {"mountain_bodies": "prisms"}), "n_plain_sources": int(n_p),
            "mountain_fraction_of_grid": float(mask_grid.mean()),
            "ridges": [{"x_km": float(a), "y_km": float(b), "angle_deg": float(np.rad2deg(c)),
                        "half_width_km": float(d)} for a, b, c, d in
                       zip(ridges.x_km, ridges.y_km, ridges.angle_rad, ridges.half_width_km)]}
    return AnomalyField(xg + e0_km, yg + n0_km, dg, e0_km, n0_km, ridges, info, sources)


def _mountain_prisms(cfg, px_km, py_km, rng) -> dict:
    """Right rectangular prisms in place of the mountains' point masses (``mountain_bodies =
    "prisms"``): blocks with vertical sides — fault blocks, intrusions, basins —, another
    anomaly family than point masses (extended bodies: at 1.5 km flight height less of the
    std lies in 0.5 km gradients than with point masses at the same depths).  One
    prism per four point-source draws (``px_km``, ``py_km``: the draws inside the ridges, km),
    each ``prism_size_km`` wide in east and north, its top ``mountain_depth_m`` below a 500 m
    surface scaled by 0.5 (the top of a body, not its centre), ``prism_thickness_m`` thick,
    density contrast ±100–400 kg/m³ (scaled to the mountains' std afterwards).

    Returns
    -------
    dict
        ``bounds_m``: shape (n, 6), west, east, south, north, bottom, top (m, relative to the
        survey centre, heights up); ``density_kgm3``: shape (n,).
    """
    keep = np.arange(0, np.asarray(px_km).size, 4)
    x, y = np.asarray(px_km)[keep] * 1000.0, np.asarray(py_km)[keep] * 1000.0
    n = x.size
    wx = rng.uniform(*cfg.prism_size_km, n) * 1000.0
    wy = rng.uniform(*cfg.prism_size_km, n) * 1000.0
    top = 500.0 - 0.5 * rng.uniform(*cfg.mountain_depth_m, n)
    bottom = top - rng.uniform(*cfg.prism_thickness_m, n)
    rho = rng.choice([-1.0, 1.0], n) * rng.uniform(100.0, 400.0, n)
    bounds = np.column_stack([x - wx / 2, x + wx / 2, y - wy / 2, y + wy / 2, bottom, top])
    return {"bounds_m": bounds, "density_kgm3": rho}


def _prism_gz(coords, prisms: dict) -> np.ndarray:
    """harmonica's ``g_z`` (mGal) of the prisms at the points ``coords`` (x, y, height in m)."""
    import harmonica as hm

    n = np.asarray(coords[0]).size
    if prisms["bounds_m"].shape[0] == 0:
        return np.zeros(n)
    return hm.prism_gravity(coords, prisms["bounds_m"], prisms["density_kgm3"], field="g_z", parallel=True)
