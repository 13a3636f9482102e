"""Simulated topography (topo-* presets): dem.tif, terrain truth, terrain-following flight, and the
Bouguer anomaly of a topography-only survey."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from app.core.terrain import (
    simple_bouguer_mgal,
    terrain_clearance_m,
    terrain_effect_along_lines_mgal,
    terrain_effect_mgal,
)
from app.io.dem import read_dem
from app.simulate import PRESETS, simulate_survey

SMALL = dict(n_main=2, main_length_km=20.0, n_tie=1, n_repeat=0, topo_spacing_m=500.0, topo_margin_km=6.0,
             grid_margin_km=4.0)


@pytest.fixture(scope="module")
def topo_only(tmp_path_factory):
    return simulate_survey("topo-only", tmp_path_factory.mktemp("sim") / "topo", seed=2, **SMALL)


def _line_errors(truth, sd=1.5, corr_s=30.0, seed=0):
    rng = np.random.default_rng(seed)
    err = np.empty(len(truth))
    for _, idx in truth.groupby("line").indices.items():
        a = np.exp(-0.1 / corr_s)
        w = rng.standard_normal(idx.size) * sd
        x = np.empty(idx.size)
        x[0] = w[0]
        for i in range(1, idx.size):
            x[i] = a * x[i - 1] + np.sqrt(1 - a * a) * w[i]
        err[idx] = x
    return err


def test_dem_and_terrain_truth(topo_only):
    p = topo_only
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    info = json.loads((p / "truth" / "truth.json").read_text())
    topo = info["topography"]
    assert topo["density_kgm3"] == 2670.0 and topo["file"] == "dem.tif"
    dem = read_dem(p / "dem.tif", PRESETS["topo-only"].crs, resampling="nearest")
    assert dem.spacing_m == (500.0, 500.0) and list(dem.height_m.shape) == topo["shape"]
    # topography only: the anomaly is the terrain's gravity
    np.testing.assert_array_equal(truth.dg_true_mgal, truth.terrain_mgal)
    assert truth.terrain_mgal.std() > 5.0
    # the truth is the exact prism sum of the file's DEM at the GNSS interval midpoints (evaluated
    # every 1 s, cubic spline in time between)
    k = np.arange(7, len(truth), 97)
    k = k[(truth.line.to_numpy()[k] == truth.line.to_numpy()[k - 1])]
    mid = lambda c: 0.5 * (truth[c].to_numpy()[k] + truth[c].to_numpy()[k - 1])       # noqa: E731
    direct = terrain_effect_mgal(mid("easting_km") * 1000, mid("northing_km") * 1000, mid("h_true_m"), dem)
    assert np.max(np.abs(direct - truth.terrain_mgal.to_numpy()[k])) < 0.005
    # terrain-following: the aircraft stays between half the clearance and ~1.5x above the real terrain
    c = terrain_clearance_m(truth.easting_km * 1000, truth.northing_km * 1000, truth.h_true_m, dem)
    assert np.nanmin(c) > 180.0 and np.nanmax(c) < 700.0
    assert np.ptp(truth.h_true_m) > 150.0


def test_bouguer_of_topography_only_survey_is_flat(topo_only):
    p = topo_only
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    dem = read_dem(p / "dem.tif", PRESETS["topo-only"].crs, resampling="nearest")
    err = _line_errors(truth)
    est = truth.dg_true_mgal.to_numpy() + err                      # a line estimate with correlated noise
    e, n, h = truth.easting_km * 1000, truth.northing_km * 1000, truth.h_true_m
    eff, info = terrain_effect_along_lines_mgal(e, n, h, truth.line.to_numpy(), dem, radius_m=None)
    bouguer = est - eff
    noise = np.std(err)
    assert np.std(bouguer) <= 1.1 * noise, (np.std(bouguer), noise)
    assert abs(np.mean(bouguer - err)) < 0.05
    assert np.std(est) > 5 * noise                                 # the free-air map is far from flat
    assert info["eval_points"] < len(truth) / 5
    # the slab leaves most of the terrain signal at this clearance: the prisms are needed
    slab = est - simple_bouguer_mgal(dem.sample(e, n))
    assert np.std(slab) > 2 * np.std(bouguer)
