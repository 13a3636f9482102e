"""Terrain and Bouguer corrections: simple Bouguer slab and the topography's gravity by prisms.

Conventions
    Coordinates are metres in the survey's projected CRS (``easting_m = 1000·easting_km``),
    heights metres in one vertical reference shared by the DEM and the observations
    (ellipsoidal heights for the aircraft: give the DEM on the ellipsoid, e.g. by adding
    the geoid undulation when it is orthometric; ``app.io.dem.read_dem(height_offset_m=…)``).
    Gravity in mGal, ``g_z`` **downward positive** (a mass excess below the point gives a
    positive value), as harmonica's ``prism_gravity(field="g_z")``.  Densities kg/m³.

Products
    * ``simple_bouguer_mgal(H, ρ) = 2πGρH`` — the infinite slab of the terrain height
      ``H`` under the point (0.1119 mGal/m at 2670 kg/m³).
    * ``terrain_effect_mgal(e, n, h, dem, ρ, radius)`` — the *complete* topographic
      effect: ``g_z`` at the observation point of the DEM's prisms between the reference
      level (default 0 m) and the terrain surface, density ``ρ`` above the reference and
      ``−ρ`` below it (a mass deficit relative to the reference), summed over the prisms
      whose centres lie within ``radius_m`` (horizontal distance) of the point.
    * the Bouguer anomaly is ``dg_bouguer = dg − terrain_effect`` (complete) or
      ``dg − simple_bouguer`` (slab); the classical terrain correction
      ``TC = simple_bouguer − terrain_effect`` (the slab's excess over the real topography).

Exactness and cost
    With ``near_radius_m=None`` every DEM cell within the radius is a right rectangular
    prism evaluated with choclo's closed form (the kernel of harmonica's
    ``prism_gravity``): identical to ``harmonica.prism_gravity`` on the prisms of
    ``harmonica.prism_layer(dem)`` to rounding (tests: < 1e-6 mGal).  Cost ≈ 150 ns per
    (point, prism) on this 2-core machine.  For production the far zone is coarsened:
    beyond ``near_radius_m`` each block of ``block_factor × block_factor`` cells is one
    prism of the block's mean thickness (same mass, same footprint); the decision is made
    per block on the distance to the block centre.  Along lines the effect is evaluated
    every ``eval_spacing_m`` of track and interpolated by a cubic spline in along-track
    distance (:func:`terrain_effect_along_lines_mgal`).  Errors of both approximations
    on the simulated topography are in docs/METHOD-products.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

#: Newtonian constant of gravitation (m³ kg⁻¹ s⁻²), as harmonica/choclo use.
G_SI = 6.6743e-11
BOUGUER_DENSITY_KGM3 = 2670.0


# --------------------------------------------------------------------------- DEM container

@dataclass
class Dem:
    """A regular DEM in the survey's projected CRS.

    ``easting_m`` (nx,) and ``northing_m`` (ny,) are the **cell centres**, strictly
    increasing with constant steps; ``height_m`` (ny, nx), NaN where there are no data.
    """

    easting_m: np.ndarray
    northing_m: np.ndarray
    height_m: np.ndarray
    crs: str | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        self.easting_m = np.asarray(self.easting_m, dtype=float)
        self.northing_m = np.asarray(self.northing_m, dtype=float)
        self.height_m = np.asarray(self.height_m, dtype=float)
        ny, nx = self.height_m.shape
        if self.easting_m.shape != (nx,) or self.northing_m.shape != (ny,) or nx < 2 or ny < 2:
            raise ValueError(f"DEM axes {self.easting_m.shape}, {self.northing_m.shape} do not match heights "
                             f"{self.height_m.shape} (need at least 2 × 2 cells)")
        for name, ax in (("easting", self.easting_m), ("northing", self.northing_m)):
            d = np.diff(ax)
            if np.any(d <= 0) or np.ptp(d) > 1e-6 * abs(d[0]):
                raise ValueError(f"DEM {name} centres must increase with a constant step")

    @property
    def spacing_m(self) -> tuple[float, float]:
        """(east, north) cell size (m)."""
        return float(self.easting_m[1] - self.easting_m[0]), float(self.northing_m[1] - self.northing_m[0])

    @property
    def bounds_m(self) -> tuple[float, float, float, float]:
        """Outer edges (west, east, south, north) of the cells (m)."""
        dx, dy = self.spacing_m
        return (self.easting_m[0] - dx / 2, self.easting_m[-1] + dx / 2,
                self.northing_m[0] - dy / 2, self.northing_m[-1] + dy / 2)

    def sample(self, easting_m, northing_m) -> np.ndarray:
        """Terrain height (m) at points by bilinear interpolation between cell centres
        (NaN outside the centres' hull or next to a missing cell)."""
        from scipy.interpolate import RegularGridInterpolator

        e = np.asarray(easting_m, dtype=float)
        n = np.asarray(northing_m, dtype=float)
        f = RegularGridInterpolator((self.northing_m, self.easting_m), self.height_m, method="linear",
                                    bounds_error=False, fill_value=np.nan)
        return f(np.stack([n.ravel(), e.ravel()], axis=-1)).reshape(np.broadcast(e, n).shape)

    def prisms(self, density_kgm3: float = BOUGUER_DENSITY_KGM3, reference_m: float = 0.0):
        """The DEM as prisms: ``(prisms (m, 6) [w, e, s, n, bottom, top], density (m,))``, one per
        cell with data and non-zero thickness, in row-major order; density ``ρ`` above the
        reference, ``−ρ`` below.  Equal to ``harmonica.prism_layer`` boundaries."""
        dx, dy = self.spacing_m
        E, N = np.meshgrid(self.easting_m, self.northing_m)
        h = self.height_m
        ok = np.isfinite(h) & (h != reference_m)
        top = np.maximum(h, reference_m)[ok]
        bot = np.minimum(h, reference_m)[ok]
        pr = np.column_stack([E[ok] - dx / 2, E[ok] + dx / 2, N[ok] - dy / 2, N[ok] + dy / 2, bot, top])
        dens = np.where(h[ok] > reference_m, density_kgm3, -density_kgm3)
        return pr, dens


# --------------------------------------------------------------------------- slab

def simple_bouguer_mgal(terrain_height_m, density_kgm3: float = BOUGUER_DENSITY_KGM3):
    """Infinite Bouguer slab ``2πGρH`` (mGal) of the terrain height ``H`` (m) under the point.

    Subtracted from the free-air anomaly: ``dg_simple_bouguer = dg − simple_bouguer_mgal(H)``.
    Negative for ``H < 0``.  Independent of the observation height (infinite slab).
    """
    return 2.0 * np.pi * G_SI * density_kgm3 * np.asarray(terrain_height_m, dtype=float) * 1e5


def terrain_clearance_m(easting_m, northing_m, height_m, dem: Dem) -> np.ndarray:
    """Height of the observation above the terrain under it (m): ``h − dem.sample(e, n)``."""
    return np.asarray(height_m, dtype=float) - dem.sample(easting_m, northing_m)


# --------------------------------------------------------------------------- prism kernel

def _kernel():
    from choclo.prism import gravity_u

    @njit(parallel=True, cache=False)
    def run(e, n, u, x0, y0, dx, dy, thick, ref, rho, k, cthick, radius, near, out):
        ny, nx = thick.shape
        nby, nbx = cthick.shape
        bx_w, by_w = k * dx, k * dy
        half_diag = 0.5 * np.hypot(bx_w, by_w)
        for p in prange(e.size):
            ep, np_, up = e[p], n[p], u[p]
            acc = 0.0
            # blocks whose footprint can reach within the radius
            b0x = max(0, int(np.floor((ep - radius - (x0 - dx / 2)) / bx_w)))
            b1x = min(nbx - 1, int(np.floor((ep + radius - (x0 - dx / 2)) / bx_w)))
            b0y = max(0, int(np.floor((np_ - radius - (y0 - dy / 2)) / by_w)))
            b1y = min(nby - 1, int(np.floor((np_ + radius - (y0 - dy / 2)) / by_w)))
            for by in range(b0y, b1y + 1):
                j0 = by * k
                j1 = min(ny, j0 + k)
                for bx in range(b0x, b1x + 1):
                    i0 = bx * k
                    i1 = min(nx, i0 + k)
                    # block footprint and centre
                    w = x0 + (i0 - 0.5) * dx
                    ea = x0 + (i1 - 0.5) * dx
                    s = y0 + (j0 - 0.5) * dy
                    no = y0 + (j1 - 0.5) * dy
                    dc = np.hypot(0.5 * (w + ea) - ep, 0.5 * (s + no) - np_)
                    if dc > radius + half_diag:
                        continue
                    if dc > near:
                        if dc <= radius:
                            t = cthick[by, bx]
                            if t > 0.0:
                                acc += gravity_u(ep, np_, up, w, ea, s, no, ref, ref + t, rho)
                            elif t < 0.0:
                                acc += gravity_u(ep, np_, up, w, ea, s, no, ref + t, ref, -rho)
                        continue
                    for j in range(j0, j1):
                        yc = y0 + j * dy
                        for i in range(i0, i1):
                            t = thick[j, i]
                            if t == 0.0:
                                continue
                            xc = x0 + i * dx
                            if np.hypot(xc - ep, yc - np_) > radius:
                                continue
                            if t > 0.0:
                                acc += gravity_u(ep, np_, up, xc - dx / 2, xc + dx / 2, yc - dy / 2, yc + dy / 2,
                                                 ref, ref + t, rho)
                            else:
                                acc += gravity_u(ep, np_, up, xc - dx / 2, xc + dx / 2, yc - dy / 2, yc + dy / 2,
                                                 ref + t, ref, -rho)
            out[p] = -acc * 1e5
    return run


_KERNEL = None


def _get_kernel():
    global _KERNEL
    if _KERNEL is None:
        _KERNEL = _kernel()
    return _KERNEL


def _block_thickness(thick: np.ndarray, k: int) -> np.ndarray:
    """Mean signed thickness of each k × k block (cells beyond the edge count as absent)."""
    ny, nx = thick.shape
    nby, nbx = -(-ny // k), -(-nx // k)
    pad = np.zeros((nby * k, nbx * k))
    cnt = np.zeros_like(pad)
    pad[:ny, :nx] = thick
    cnt[:ny, :nx] = 1.0
    s = pad.reshape(nby, k, nbx, k).sum(axis=(1, 3))
    c = cnt.reshape(nby, k, nbx, k).sum(axis=(1, 3))
    # the coarse prism spans the block's real cells: keep the mass (mean over real cells)
    return s / np.maximum(c, 1.0)


def terrain_effect_mgal(easting_m, northing_m, height_m, dem: Dem,
                        density_kgm3: float = BOUGUER_DENSITY_KGM3, radius_m: float | None = None,
                        reference_m: float = 0.0, near_radius_m: float | None = None,
                        block_factor: int = 4) -> np.ndarray:
    """Gravity effect ``g_z`` (mGal, downward positive) of the topography at the points.

    Parameters
    ----------
    easting_m, northing_m, height_m : array_like
        Observation points (m; same shape).  Must lie above the terrain.
    dem : Dem
        Terrain in the same CRS and vertical reference.  NaN cells carry no mass.
    density_kgm3 : float
        Density of the topography (default 2670 kg/m³); cells below ``reference_m`` get
        ``−density`` (mass deficit).
    radius_m : float or None
        Only prisms (blocks) whose centre is within this horizontal distance count;
        None: every cell of the DEM.
    reference_m : float
        Bottom (or top, below it) of the prisms: the Bouguer reference level.
    near_radius_m : float or None
        None: exact (every cell a prism).  Otherwise blocks of ``block_factor²`` cells whose
        centre is farther than this are replaced by one prism of their mean thickness.
    block_factor : int
        Cells per block side for the far zone (≥ 1).

    Returns
    -------
    ndarray
        Same shape as the inputs.
    """
    e = np.asarray(easting_m, dtype=float)
    n = np.asarray(northing_m, dtype=float)
    h = np.asarray(height_m, dtype=float)
    shape = np.broadcast(e, n, h).shape
    e, n, h = (np.ascontiguousarray(np.broadcast_to(v, shape).ravel()) for v in (e, n, h))
    k = int(block_factor) if near_radius_m is not None else 1
    if k < 1:
        raise ValueError("block_factor must be ≥ 1")
    thick = np.where(np.isfinite(dem.height_m), dem.height_m - reference_m, 0.0)
    cthick = _block_thickness(thick, k)
    dx, dy = dem.spacing_m
    radius = 1e12 if radius_m is None else min(float(radius_m), 1e12)
    near = np.inf if near_radius_m is None else float(near_radius_m)
    out = np.zeros(e.size)
    if e.size:
        _get_kernel()(e, n, h, float(dem.easting_m[0]), float(dem.northing_m[0]), dx, dy,
                      np.ascontiguousarray(thick), float(reference_m), float(density_kgm3), k,
                      np.ascontiguousarray(cthick), radius, near, out)
    return out.reshape(shape)


def terrain_effect_along_lines_mgal(easting_m, northing_m, height_m, line, dem: Dem,
                                    density_kgm3: float = BOUGUER_DENSITY_KGM3,
                                    radius_m: float | None = 20000.0, reference_m: float = 0.0,
                                    near_radius_m: float | None = 5000.0, block_factor: int = 4,
                                    eval_spacing_m: float | None = None) -> tuple[np.ndarray, dict]:
    """Terrain effect (mGal) at every epoch of survey lines, evaluated on decimated points.

    Per line (consecutive epochs with one label, in time order) the effect and its vertical
    gradient (finite difference over 10 m) are computed (:func:`terrain_effect_mgal`) at points
    every ``eval_spacing_m`` of along-track distance (and at both ends); at every epoch
    ``effect = S[v](s) + S[∂v/∂h](s)·(h − S[h](s))`` with ``S`` the cubic spline in along-track
    distance ``s`` through the evaluation points (the aircraft's metre-level height jitter between
    them goes through the gradient).  Cost: two evaluations per point.  ``eval_spacing_m=None`` chooses half the smallest terrain clearance on the
    line, clipped to 25–500 m (the effect varies on the scale of the clearance).

    Returns
    -------
    (effect_mgal, info)
        ``info``: ``{"eval_points", "epochs", "eval_spacing_m" (per line), "radius_m",
        "near_radius_m", "block_factor", "density_kgm3", "min_clearance_m"}``.
    """
    from scipy.interpolate import CubicSpline

    e = np.asarray(easting_m, dtype=float)
    n = np.asarray(northing_m, dtype=float)
    h = np.asarray(height_m, dtype=float)
    lab = np.asarray(line)
    out = np.full(e.size, np.nan)
    idx_all, spans = [], []
    spacing_used = {}
    clear = terrain_clearance_m(e, n, h, dem)
    start = 0
    for stop in list(np.flatnonzero(lab[1:] != lab[:-1]) + 1) + [e.size]:
        sl = np.arange(start, stop)
        start = stop
        if sl.size == 0:
            continue
        s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(e[sl]), np.diff(n[sl])))])
        c = np.nanmin(clear[sl]) if np.isfinite(clear[sl]).any() else 500.0
        step = float(np.clip(0.5 * c, 25.0, 500.0)) if eval_spacing_m is None else float(eval_spacing_m)
        spacing_used[str(lab[sl[0]])] = step
        if s[-1] <= step or sl.size < 4:
            sel = sl
        else:
            targets = np.linspace(0.0, s[-1], int(np.ceil(s[-1] / step)) + 1)
            j = np.unique(np.clip(np.searchsorted(s, targets), 0, sl.size - 1))
            sel = sl[j]
        idx_all.append(sel)
        spans.append((sl, s, np.searchsorted(sl, sel)))
    if idx_all:
        sel = np.concatenate(idx_all)
        args = (dem, density_kgm3, radius_m, reference_m, near_radius_m, block_factor)
        val = terrain_effect_mgal(e[sel], n[sel], h[sel], *args)
        # vertical gradient at the evaluation points (finite difference over 10 m): the aircraft's
        # metre-level height jitter between them is applied through it
        grad = (terrain_effect_mgal(e[sel], n[sel], h[sel] + 10.0, *args) - val) / 10.0
        pos = 0
        for sl, s, j in spans:
            v, gz, hj = val[pos:pos + j.size], grad[pos:pos + j.size], h[sl][j]
            pos += j.size
            if j.size == sl.size:
                out[sl] = v
            elif j.size >= 2:
                sj, keep = np.unique(s[j], return_index=True)

                def f(y, sj=sj, keep=keep, s=s):
                    if sj.size >= 3:
                        return CubicSpline(sj, y[keep], bc_type="not-a-knot")(s)
                    return np.interp(s, sj, y[keep])

                out[sl] = f(v) + f(gz) * (h[sl] - f(hj))
            else:
                out[sl] = v[0] + gz[0] * (h[sl] - hj[0])
    info = {"eval_points": int(sum(x.size for x in idx_all)), "epochs": int(e.size),
            "eval_spacing_m": spacing_used, "radius_m": radius_m, "near_radius_m": near_radius_m,
            "block_factor": block_factor, "density_kgm3": density_kgm3,
            "min_clearance_m": float(np.nanmin(clear)) if np.isfinite(clear).any() else None}
    return out, info
