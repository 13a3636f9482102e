"""app.pipeline.evaluate: its figures are app.core.accuracy's; empty selections read NaN."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from app.pipeline.evaluate import evaluate, line_accuracy


def _frames(seed=0, n=400):
    rng = np.random.default_rng(seed)
    rows, truth = [], []
    for k, line in enumerate(("A", "B", "C")):
        t = 100.0 * k + np.arange(n) * 0.1
        e = np.linspace(0.0, 40.0, n)                                   # 40 km lines
        true = 10 * np.sin(e / 5.0) + k
        terrain = np.where(e < 20.0, "mountain", "plain")
        err = rng.normal(0.5 * k, 1.0, n)
        rows.append(pd.DataFrame({"line": line, "flight": "F1", "kind": "main", "time": t, "easting_km": e,
                                  "northing_km": 2.0 * k, "dg_mgal": true + err, "dg_unleveled_mgal": true + 2 * err,
                                  "dg_stationary_mgal": true + err, "dg_fir_mgal": true - err,
                                  "dg_std_mgal": np.full(n, 1.0)}))
        truth.append(pd.DataFrame({"line": line, "time": t, "dg_true_mgal": true, "terrain": terrain}))
    return pd.concat(rows, ignore_index=True), pd.concat(truth, ignore_index=True)


def test_line_accuracy_figures():
    lines, truth = _frames()
    res = line_accuracy(lines, truth, edge_km=5.0)
    core = lines.assign(terrain=truth["terrain"], true=truth["dg_true_mgal"])
    core = core[(core["easting_km"] >= 5.0) & (core["easting_km"] <= 35.0)]
    assert res["epochs"] == len(core)
    err = core["dg_mgal"] - core["true"]
    assert res["dg_mgal"]["all"] == pytest.approx(np.sqrt(np.mean(err ** 2)), rel=1e-12)
    dem = err - err.groupby(core["line"]).transform("mean")
    assert res["dg_mgal"]["all_line_demeaned"] == pytest.approx(np.sqrt(np.mean(dem ** 2)), rel=1e-12)
    plain = (core["terrain"] == "plain").to_numpy()
    assert res["dg_mgal"]["plain"] == pytest.approx(np.sqrt(np.mean(err[plain] ** 2)), rel=1e-12)
    assert res["dg_mgal"]["plain_line_demeaned"] == pytest.approx(np.sqrt(np.mean(dem[plain] ** 2)), rel=1e-12)
    assert res["std_calibration_dg_mgal"] == pytest.approx(np.mean(np.abs(err) < 2.0), rel=1e-12)
    assert res["bias_dg_mgal"] == pytest.approx(err.mean(), rel=1e-12)


def test_line_accuracy_empty_selection_is_nan():
    lines, truth = _frames()
    plain_t = truth["terrain"] == "plain"
    lines.loc[plain_t.to_numpy(), "dg_fir_mgal"] = np.nan        # no FIR value on the plain
    lines["dg_stationary_mgal"] = np.nan                         # no stationary value at all
    res = line_accuracy(lines, truth, edge_km=5.0)
    assert math.isnan(res["dg_fir_mgal"]["plain"]) and math.isnan(res["dg_fir_mgal"]["plain_line_demeaned"])
    assert np.isfinite(res["dg_fir_mgal"]["mountain"])
    assert all(math.isnan(v) for v in res["dg_stationary_mgal"].values())


def test_evaluate_processed_tiny_survey(tiny_survey, tiny_processed):
    out, _, _ = tiny_processed
    res = evaluate(tiny_survey, out)
    assert set(res["grid"]) == {"cells", "rms_mgal", "rms_demeaned_mgal", "std_calibration"}
    assert res["grid"]["cells"] > 0 and 0 < res["grid"]["rms_mgal"] < 10
    assert 0 < res["lines"]["dg_mgal"]["all"] < 10 and 0.5 < res["lines"]["std_calibration_dg_mgal"] <= 1
