"""Leveling removes a simulated per-flight drift (no parking-place readings to tie to)."""

import json

import numpy as np
import pandas as pd

from app.pipeline.evaluate import merge_truth


def test_leveling_removes_injected_flight_drift(tmp_path):
    from app.pipeline.process import process_survey
    from app.simulate import simulate_survey

    survey = simulate_survey("omolon-mini", tmp_path / "s", seed=7, apron_s=0,
                             drift_rate_mgal_h=(20.0, 60.0), drift_offset_std_mgal=40.0)
    out = tmp_path / "out"
    report = process_survey(survey, out)
    cx = report["crossovers"]
    assert cx["status"] == "leveled"
    # the drift dominates the crossover differences before leveling; afterwards only the
    # line estimates' own errors remain
    assert cx["rms_after_mgal"] <= cx["rms_before_mgal"] / 3.0
    lines = pd.read_parquet(out / "lines.parquet")
    truth = pd.read_parquet(survey / "truth" / "lines.parquet")
    m = merge_truth(lines, truth)
    # the absolute level is unobservable without base readings: compare after removing the
    # survey-wide mean error
    rms = {}
    for col in ("dg_mgal", "dg_unleveled_mgal"):
        e = m[col] - m["dg_true_mgal"]
        rms[col] = float(np.sqrt(np.mean((e - e.mean()) ** 2)))
    assert rms["dg_mgal"] < 0.8 * rms["dg_unleveled_mgal"]
    cxt = pd.read_csv(out / "crossovers.csv")
    assert np.sqrt(np.mean(cxt["diff_after_mgal"] ** 2)) < np.sqrt(np.mean(cxt["diff_before_mgal"] ** 2))
    assert json.loads((out / "report.json").read_text())["base_ties"]
