"""Simulated topography: a DEM of prisms of known density, its gravity, and a terrain-following drape.

The terrain (``topo_amp_m > 0``) is a sum of ``topo_components`` plane waves (random directions and
phases, wavelengths uniform in ``topo_wavelength_km``) scaled to span ``topo_base_m ± topo_amp_m``
over the DEM, on a regular grid of ``topo_spacing_m`` in the survey CRS covering the flight paths
plus ``topo_margin_km``.  Heights are rounded to float32 (what ``dem.tif`` stores), so the
prisms of the file and of the truth are the same.  Each cell is a right rectangular prism from
0 m (the reference) to its height with density ``topo_density_kgm3``.

Its gravity (``terrain_mgal`` in truth/lines.parquet) is ``app.core.terrain.terrain_effect_mgal``
of **every** prism (no radius, no far-zone blocks: exact), at the interval midpoint positions and
heights; evaluated every ``round(gnss_rate_hz)`` epochs (≈ 1 s, ~100 m) and interpolated by a cubic
spline in time (interpolation error < 0.005 mGal at ≥ 150 m clearance, checked by
tests/simulate/test_topography.py).

Terrain-following flight (``topo_clearance_m > 0``): the aircraft flies ``topo_clearance_m`` above
the terrain smoothed by a Gaussian of ``topo_drape_smooth_km`` (the flight cannot follow short
hills), raised where needed so that the clearance above the real terrain under the line windows
is at least ``topo_clearance_m / 2``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class TerrainDrape:
    """Drape surface (m above ``height_m``) that follows the smoothed terrain: the interface of
    :class:`app.simulate.motion.Drape` (callable on metres from the survey centre, ``info()``)."""

    spline: object            # RectBivariateSpline over (y_rel_m, x_rel_m) of the smoothed terrain
    clearance_m: float
    lift_m: float
    height_m: float

    def __call__(self, x_m, y_m) -> np.ndarray:
        x = np.asarray(x_m, dtype=float)
        y = np.asarray(y_m, dtype=float)
        return self.spline.ev(y, x) + self.clearance_m + self.lift_m - self.height_m

    def info(self) -> dict:
        return {"kind": "terrain-following", "clearance_m": self.clearance_m, "lift_m": self.lift_m,
                "formula": "flight height = smoothed terrain + clearance_m + lift_m (+ turbulence/phugoid)"}


@dataclass
class Topography:
    dem: object               # app.core.terrain.Dem, absolute projected metres
    density_kgm3: float
    info: dict
    drape: TerrainDrape | None

    def effect_mgal(self, easting_km, northing_km, height_m) -> np.ndarray:
        """Exact gravity of every prism (mGal, downward positive) at absolute km positions."""
        from app.core.terrain import terrain_effect_mgal

        return terrain_effect_mgal(np.asarray(easting_km) * 1000.0, np.asarray(northing_km) * 1000.0,
                                   height_m, self.dem, self.density_kgm3)

    def effect_along(self, t, easting_km, northing_km, height_m, every: int) -> np.ndarray:
        """:meth:`effect_mgal` at every ``every``-th epoch (and the last), cubic spline in time between."""
        from scipy.interpolate import CubicSpline

        t = np.asarray(t, dtype=float)
        idx = np.unique(np.r_[np.arange(0, t.size, max(1, every)), t.size - 1])
        h = np.broadcast_to(np.asarray(height_m, dtype=float), t.shape)
        v = self.effect_mgal(np.asarray(easting_km)[idx], np.asarray(northing_km)[idx], h[idx])
        if idx.size < 4:
            return np.interp(t, t[idx], v)
        return CubicSpline(t[idx], v)(t)


def make_topography(cfg, extent_km, e0_km: float, n0_km: float, lines, rng) -> Topography:
    """The topography of ``cfg`` over the flight extent (relative km) plus ``topo_margin_km``."""
    from scipy.interpolate import RectBivariateSpline
    from scipy.ndimage import gaussian_filter

    from app.core.terrain import Dem

    xmin, xmax, ymin, ymax = extent_km
    m = cfg.topo_margin_km * 1000.0
    sp = float(cfg.topo_spacing_m)
    # cell centres on absolute multiples of the spacing (as app.io.dem.read_dem lays its grids),
    # x, y relative to the survey centre
    ex, ny_ = e0_km * 1000.0, n0_km * 1000.0
    x = np.arange(np.floor((ex + xmin * 1000 - m) / sp), np.ceil((ex + xmax * 1000 + m) / sp) + 1) * sp - ex
    y = np.arange(np.floor((ny_ + ymin * 1000 - m) / sp), np.ceil((ny_ + ymax * 1000 + m) / sp) + 1) * sp - ny_
    n = int(cfg.topo_components)
    lam = rng.uniform(*cfg.topo_wavelength_km, n) * 1000.0
    th = rng.uniform(0.0, np.pi, n)
    ph = rng.uniform(0.0, 2 * np.pi, n)
    amp = lam / lam.max()               # longer waves carry more relief (red spectrum)
    k = 2 * np.pi / lam
    X, Y = np.meshgrid(x, y)
    z = np.zeros(X.shape)
    for a, kk, t, p in zip(amp, k, th, ph):
        z += a * np.cos(kk * np.sin(t) * X + kk * np.cos(t) * Y + p)
    z = (z - 0.5 * (z.max() + z.min())) / (0.5 * np.ptp(z)) * cfg.topo_amp_m + cfg.topo_base_m
    z = z.astype(np.float32).astype(float)
    dem = Dem(np.round(x + ex, 6), np.round(y + ny_, 6), z, crs=cfg.crs)
    info = {"file": "dem.tif", "density_kgm3": cfg.topo_density_kgm3, "reference_m": 0.0,
            "spacing_m": sp, "shape": list(z.shape), "base_m": cfg.topo_base_m, "amp_m": cfg.topo_amp_m,
            "height_range_m": [float(z.min()), float(z.max())],
            "wavelength_km": (lam / 1000).tolist(), "direction_deg": np.rad2deg(th).tolist(),
            "phase_rad": ph.tolist(), "relative_amplitude": amp.tolist(),
            "terrain_mgal": ("g_z (downward) of every DEM cell as a prism from 0 m to its height, density "
                             "density_kgm3, at the interval midpoint position and height; included in "
                             "dg_true_mgal")}
    drape = None
    if cfg.topo_clearance_m > 0:
        s_cells = cfg.topo_drape_smooth_km * 1000.0 / sp
        zs = gaussian_filter(z, s_cells, mode="nearest")
        spl = RectBivariateSpline(y, x, zs, kx=3, ky=3)
        # lift so that the clearance above the real terrain under the lines is ≥ half the nominal
        pts = []
        for ln in lines:
            a, b = np.array(ln.start_km) * 1000.0, np.array(ln.end_km) * 1000.0
            q = max(2, int(np.hypot(*(b - a)) / 50.0) + 1)
            pts.append(a + np.linspace(0.0, 1.0, q)[:, None] * (b - a))
        P = np.concatenate(pts)
        real = RectBivariateSpline(y, x, z, kx=1, ky=1).ev(P[:, 1], P[:, 0])
        lift = max(0.0, float(np.max(real - spl.ev(P[:, 1], P[:, 0]))) - 0.5 * cfg.topo_clearance_m)
        drape = TerrainDrape(spl, float(cfg.topo_clearance_m), lift, float(cfg.height_m))
        info["drape"] = {**drape.info(), "smooth_km": cfg.topo_drape_smooth_km}
    return Topography(dem, float(cfg.topo_density_kgm3), info, drape)
