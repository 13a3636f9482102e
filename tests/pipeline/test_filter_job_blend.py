"""The ``filter`` job after a run that blended the two anomaly orders (stage 9 step 1): it
filters both orders again (each refinement warm-started from the levels that run found) and
blends them, so at the same h, ρ it gives the ``process`` run's estimate — not m = 2 alone."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

SAMPLE = Path(__file__).resolve().parents[2] / "sample_surveys" / "omolon-mini"


def test_filter_job_after_a_blended_run_reproduces_it(tmp_path):
    from app.pipeline.process import filter_from, process_survey

    first = process_survey(SAMPLE, tmp_path / "process", keep_identification=True)
    blend = first["model_choice"]["order"].get("blend")
    assert blend is not None and 0.0 < blend["weight"] < 1.0   # the sample's crossovers blend (w ≈ 0.19)
    # the roughest level is filtered at no less than twice the full-rate likelihood's
    # (rough_level_factor); the report keeps the levels before that, which a filter job starts
    # from (raised there again, not twice over)
    rough = first["level_refinement"]["rough_level"]
    assert rough["used_mgal2"] == pytest.approx(max(rough["lifted_mgal2"], 2 * rough["full_rate_ml_mgal2"]))
    assert first["level_refinement"]["Q_mgal2"][-1] == pytest.approx(rough["lifted_mgal2"])
    q_col = pd.read_parquet(tmp_path / "process" / "lines.parquet")["Q_mgal2"].to_numpy()
    assert q_col.max() <= rough["used_mgal2"] * (1 + 1e-9)
    again = filter_from(tmp_path / "process", tmp_path / "filter")
    assert again["level_refinement"]["rough_level"]["used_mgal2"] == pytest.approx(rough["used_mgal2"], rel=0.05)
    # the warm-started refinements end near the cold ones: the same blend to a few thousandths
    assert abs(again["model_choice"]["order"]["blend"]["weight"] - blend["weight"]) < 0.02
    a = pd.read_parquet(tmp_path / "process" / "lines.parquet")
    b = pd.read_parquet(tmp_path / "filter" / "lines.parquet")
    for col in ("dg_mgal", "dg_std_mgal"):
        assert np.sqrt(np.mean((a[col] - b[col]) ** 2)) < 0.02   # mGal; the blend moved it by ~0.5
    # the stationary baseline has no states, so other h, ρ leave it where the run put it: its
    # level is the run's (not fitted again), the column the same but for R's map-dependent scale
    other = filter_from(tmp_path / "process", tmp_path / "filter2",
                        {"nlmeans_h_per_km": 1.0, "nlmeans_rho_km": 6.0})
    assert other["level_refinement"]["Q_stationary_mgal2"] == first["level_refinement"]["Q_stationary_mgal2"]
    c = pd.read_parquet(tmp_path / "filter2" / "lines.parquet")
    assert np.sqrt(np.mean((a["dg_stationary_mgal"] - c["dg_stationary_mgal"]) ** 2)) < 0.05
    assert np.sqrt(np.mean((a["dg_mgal"] - c["dg_mgal"]) ** 2)) > 0.05   # while the estimate moved
    # and the same job again into its own folder (its identification already linked there)
    filter_from(tmp_path / "process", tmp_path / "filter2", {"nlmeans_h_per_km": 1.0, "nlmeans_rho_km": 6.0})
    assert pd.read_parquet(tmp_path / "filter2" / "lines.parquet")["dg_mgal"].equals(c["dg_mgal"])


def test_filter_job_after_a_zero_weight_run_blends_as_process_would(tmp_path, monkeypatch):
    """A run whose crossovers gave the blend weight 0 (m = 2 alone): at other h, ρ the weight may
    be other, so the filter job filters both orders and blends them as ``process`` would — here
    at the run's own h, ρ, with the weight no longer forced to 0, it must find the sample's blend."""
    import app.pipeline.stages.choice as choice
    from app.pipeline.process import filter_from, process_survey

    real = choice.crossover_blend_weight
    monkeypatch.setattr(choice, "crossover_blend_weight", lambda a, b: 0.0)
    first = process_survey(SAMPLE, tmp_path / "process", keep_identification=True)
    assert first["model_choice"]["m"] == 2 and "blend" not in first["model_choice"]["order"]
    assert set(first["model_choice"]["order"]["Q_mgal2_by_order"]) == {"1", "2"}
    monkeypatch.setattr(choice, "crossover_blend_weight", real)
    again = filter_from(tmp_path / "process", tmp_path / "filter")
    blend = again["model_choice"]["order"].get("blend")
    assert blend is not None and 0.1 < blend["weight"] < 0.7   # the sample's w ≈ 0.19 (0.41 before session 32 removed the drift)
    a = pd.read_parquet(tmp_path / "process" / "lines.parquet")
    b = pd.read_parquet(tmp_path / "filter" / "lines.parquet")
    assert np.sqrt(np.mean((a["dg_mgal"] - b["dg_mgal"]) ** 2)) > 0.1   # the blend moved it (~0.5 mGal)
