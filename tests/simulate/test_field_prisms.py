"""The simulator's prism mountains (``mountain_bodies = "prisms"``): blocks instead of point
masses, an anomaly family the defaults were not tuned on."""

import harmonica as hm
import numpy as np
import pytest

from app.simulate.field import make_field
from app.simulate.presets import PRESETS


@pytest.fixture(scope="module")
def prism_field():
    cfg = PRESETS["tiny"].replace(mountain_bodies="prisms", mountain_std_mgal=25.0, plain_std_mgal=5.0,
                                  height_m=1500.0)
    return cfg, make_field(cfg, (-30.0, 30.0, -12.0, 12.0), 500.0, 6000.0, np.random.default_rng(4))


def test_prism_field_is_harmonica_of_the_recorded_bodies(prism_field):
    """At any point and height the field is harmonica's g_z of the recorded prisms and plain point
    masses less the plain offset; the bicubic grid at the nominal height agrees with it."""
    cfg, fld = prism_field
    src = fld.sources
    assert fld.info["mountain_bodies"] == "prisms" and src["prisms_m"].shape[1] == 6
    assert src["n_mountain"] == 0 and fld.info["n_mountain_sources"] == src["prisms_m"].shape[0] > 10
    rng = np.random.default_rng(0)
    e = 500.0 + rng.uniform(-25.0, 25.0, 60)
    n = 6000.0 + rng.uniform(-10.0, 10.0, 60)
    for h in (cfg.height_m, cfg.height_m + 300.0):
        coords = ((e - 500.0) * 1000.0, (n - 6000.0) * 1000.0, np.full(e.size, h))
        ref = (hm.prism_gravity(coords, src["prisms_m"], src["prism_density_kgm3"], field="g_z")
               + hm.point_gravity(coords, (src["x_m"], src["y_m"], src["z_m"]), src["mass_kg"], field="g_z")
               - src["offset_mgal"])
        np.testing.assert_allclose(fld.at(e, n, h), ref, atol=1e-6)
    g0 = fld.at(e, n, cfg.height_m)
    assert np.abs(fld(e, n) - g0).max() < 0.1
    assert np.abs(fld.at(e, n, cfg.height_m + 300.0) - g0).max() > 0.5     # the field decays upward


def test_prism_mountains_have_their_std_and_another_spectrum(prism_field):
    """The mountains' part is scaled to mountain_std_mgal over the ridge mask (the plain part adds
    a little); the extended blocks (0.5–4 km wide, up to 3 km thick) put less of that std into
    0.5 km gradients than point masses at the same depths: another anomaly family."""
    cfg, fld = prism_field
    X, Y = np.meshgrid(fld.easting_km, fld.northing_km)
    mnt = fld.terrain_mountain(X, Y)
    assert 20.0 < np.std(fld.dg_mgal[mnt]) < 30.0
    pts = make_field(cfg.replace(mountain_bodies="points"), (-30.0, 30.0, -12.0, 12.0), 500.0, 6000.0,
                     np.random.default_rng(4))

    def short_share(f):
        d = np.diff(f.dg_mgal, axis=1)[mnt[:, 1:]]        # east gradient over 0.5 km inside the ridges
        return np.std(d) / np.std(f.dg_mgal[mnt])

    assert short_share(fld) < 0.8 * short_share(pts)


def test_unknown_mountain_bodies_are_refused():
    cfg = PRESETS["tiny"].replace(mountain_bodies="prism")
    with pytest.raises(ValueError, match="mountain_bodies must be 'points' or 'prisms', got 'prism'"):
        make_field(cfg, (-30.0, 30.0, -12.0, 12.0), 500.0, 6000.0, np.random.default_rng(4))
