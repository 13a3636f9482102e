"""Terrain and Bouguer corrections (app.core.terrain) against harmonica's prism forward model."""

from __future__ import annotations

import harmonica as hm
import numpy as np
import pytest

from app.core.terrain import (
    Dem,
    simple_bouguer_mgal,
    terrain_clearance_m,
    terrain_effect_along_lines_mgal,
    terrain_effect_mgal,
)


def _dem(nx=48, ny=36, step=250.0, seed=0, below=True):
    rng = np.random.default_rng(seed)
    x = 1000.0 + step * np.arange(nx)
    y = -2000.0 + step * np.arange(ny)
    X, Y = np.meshgrid(x, y)
    h = (400 + 300 * np.sin(X / 1700.0) * np.cos(Y / 2300.0) + 60 * rng.standard_normal(X.shape))
    if below:
        h[:4, :5] = -50.0 - 20 * rng.random((4, 5))      # a basin below the reference
    h[10, 7] = np.nan                                      # a missing cell: no mass
    return Dem(x, y, h, crs="EPSG:32657")


def _harmonica(dem, obs, density=2670.0, radius=None):
    """Reference: harmonica.prism_layer over the DEM (missing cells at the reference), prism_gravity."""
    surf = np.where(np.isfinite(dem.height_m), dem.height_m, 0.0)
    dens = np.where(surf >= 0, density, -density)
    layer = hm.prism_layer((dem.easting_m, dem.northing_m), surf, 0.0, properties={"density": dens})
    if radius is None:
        return layer.prism_layer.gravity(obs, field="g_z")
    E, N = np.meshgrid(dem.easting_m, dem.northing_m)
    dx, dy = dem.spacing_m
    out = []
    for e, n, u in zip(*obs):
        m = np.hypot(E - e, N - n).ravel() <= radius
        prisms = np.column_stack([E.ravel() - dx / 2, E.ravel() + dx / 2, N.ravel() - dy / 2, N.ravel() + dy / 2,
                                  np.minimum(surf, 0).ravel(), np.maximum(surf, 0).ravel()])[m]
        out.append(hm.prism_gravity(([e], [n], [u]), prisms, dens.ravel()[m], field="g_z")[0])
    return np.array(out)


def test_prism_effect_equals_harmonica_forward_model():
    dem = _dem()
    rng = np.random.default_rng(1)
    e = rng.uniform(dem.bounds_m[0] - 2000, dem.bounds_m[1] + 2000, 60)
    n = rng.uniform(dem.bounds_m[2] - 2000, dem.bounds_m[3] + 2000, 60)
    h = rng.uniform(900.0, 3000.0, 60)
    obs = (e, n, h)
    got = terrain_effect_mgal(e, n, h, dem)
    ref = _harmonica(dem, obs)
    assert np.max(np.abs(got - ref)) < 1e-6, np.max(np.abs(got - ref))
    assert np.ptp(ref) > 5.0                                   # a non-trivial field
    # with a radius: only the prisms whose centres are within it
    got_r = terrain_effect_mgal(e[:15], n[:15], h[:15], dem, radius_m=3000.0)
    ref_r = _harmonica(dem, (e[:15], n[:15], h[:15]), radius=3000.0)
    assert np.max(np.abs(got_r - ref_r)) < 1e-6
    # the Dem.prisms() view is harmonica's set too (missing cell and zero thickness dropped)
    pr, dens = dem.prisms()
    np.testing.assert_allclose(hm.prism_gravity(obs, pr, dens, field="g_z"), ref, atol=1e-6, rtol=0)


def test_far_zone_blocks_small_error_and_shape():
    dem = _dem(nx=96, ny=80, step=200.0, below=False)
    rng = np.random.default_rng(2)
    e = rng.uniform(dem.easting_m[20], dem.easting_m[-20], 40)
    n = rng.uniform(dem.northing_m[20], dem.northing_m[-20], 40)
    h = np.full(40, 1500.0)
    exact = terrain_effect_mgal(e, n, h, dem, radius_m=15000.0)
    approx = terrain_effect_mgal(e, n, h, dem, radius_m=15000.0, near_radius_m=4000.0, block_factor=4)
    # white 60 m cell-to-cell roughness is the worst case for mean-thickness blocks (measured 0.031)
    assert np.max(np.abs(approx - exact)) < 0.04, np.max(np.abs(approx - exact))
    g2 = terrain_effect_mgal(e.reshape(5, 8), n.reshape(5, 8), 1500.0, dem)
    assert g2.shape == (5, 8)


def test_slab_and_plateau():
    assert simple_bouguer_mgal(1.0) == pytest.approx(0.04193 * 2.67, rel=5e-4)   # the textbook 0.04193ρ mGal/m
    assert simple_bouguer_mgal(-10.0, 1000.0) == pytest.approx(-0.4193, rel=5e-4)
    # a wide flat plateau 500 m high: at its centre, 100 m above it, the prisms within 30 km give
    # the vertical cylinder of radius 30 km (the slab less its part beyond 30 km)
    x = np.arange(-35000.0, 35001.0, 250.0)
    dem = Dem(x, x, np.full((x.size, x.size), 500.0))
    g = terrain_effect_mgal(0.0, 0.0, 600.0, dem, radius_m=30000.0)
    R, H, z = 30000.0, 500.0, 600.0
    # vertical cylinder of radius R from 0 to H, point on the axis at height z above its base
    cyl = 2 * np.pi * 6.6743e-11 * 2670 * (H + np.hypot(R, z - H) - np.hypot(R, z)) * 1e5
    assert g == pytest.approx(cyl, abs=0.01)                   # staircase edge of the disc
    assert terrain_clearance_m(0.0, 0.0, 600.0, dem) == pytest.approx(100.0)


def test_along_lines_interpolation():
    dem = _dem(nx=80, ny=40, step=250.0, below=False)
    t = np.arange(0.0, 180.0, 0.1)
    e = dem.easting_m[5] + 100.0 * t
    n = np.full(t.size, dem.northing_m[20])
    h = 1200.0 + 50 * np.sin(t / 20)
    lab = np.where(t < 90, "L1", "L2")
    got, info = terrain_effect_along_lines_mgal(e, n, h, lab, dem, radius_m=None, near_radius_m=None)
    sub = slice(3, None, 37)
    exact = terrain_effect_mgal(e[sub], n[sub], h[sub], dem)
    assert np.max(np.abs(got[sub] - exact)) < 0.01, np.max(np.abs(got[sub] - exact))
    assert info["eval_points"] < t.size / 5 and set(info["eval_spacing_m"]) == {"L1", "L2"}
