"""The analyst's smoothing strength (``anomaly_level_scale``, METHOD stage 8): every anomaly level
the smoother uses is multiplied by the scale; the levels as fitted stay in the report (a filter
job's warm start), and the estimate is the Kalman smoother's under the scaled Q(t) — which
passes more of z the larger the level (its gain S/(S + N) grows with the anomaly's power at
every frequency)."""

import json

import numpy as np
import pandas as pd
import pytest

from app.core.noise_model import NoiseModel
from app.core.smoother import kalman_smooth
from app.io.errors import InputError

SCALE = 8.0


@pytest.fixture(scope="module")
def scaled(tiny_survey, tmp_path_factory):
    from app.pipeline.process import process_survey

    out = tmp_path_factory.mktemp("tiny_scaled")
    report = process_survey(tiny_survey, out, {"anomaly_level_scale": SCALE})
    return out, report


def _adaptive_lines(report) -> set:
    return {ln for ln, v in report["model_choice"].get("lines", {}).items() if v.get("estimate") == "adaptive"}


def test_levels_are_the_fitted_ones_times_the_scale(tiny_processed, scaled):
    (base_out, base_rep, _), (out, rep) = tiny_processed, scaled
    assert rep["level_refinement"]["anomaly_level_scale"] == SCALE
    assert base_rep["level_refinement"]["anomaly_level_scale"] == 1.0
    # the levels as fitted (the report's, a filter job's warm start) do not depend on the scale
    np.testing.assert_allclose(rep["level_refinement"]["Q_mgal2"], base_rep["level_refinement"]["Q_mgal2"],
                               rtol=1e-12)
    a, b = pd.read_parquet(base_out / "lines.parquet"), pd.read_parquet(out / "lines.parquet")
    np.testing.assert_allclose(b["Q_mgal2"].to_numpy(), SCALE * a["Q_mgal2"].to_numpy(), rtol=1e-9)


def test_the_estimate_is_the_smoother_under_the_scaled_level_and_passes_more(tiny_processed, scaled):
    (base_out, base_rep, _), (out, rep) = tiny_processed, scaled
    nm = rep["noise_model"]
    noise = NoiseModel.from_description(nm)
    a, b = pd.read_parquet(base_out / "lines.parquet"), pd.read_parquet(out / "lines.parquet")
    both = _adaptive_lines(rep) & _adaptive_lines(base_rep)
    assert len(both) >= 4
    checked = 0
    for line in sorted(both):
        ga, gb = a[a["line"] == line].sort_values("time"), b[b["line"] == line].sort_values("time")
        n = len(gb)
        if n < 2000:   # the 100 s tie lines: the run-in margins beyond their ends reach their middle
            continue
        inner = slice(n // 4, 3 * n // 4)   # away from the ends, where the run-in margins matter
        plain = kalman_smooth(gb["z_mgal"].to_numpy(), gb["Q_mgal2"].to_numpy(), gb["R_cm2s2"].to_numpy(),
                              nm["dt_s"], m=int(rep["model_choice"]["m"]), noise=noise).dg_mgal
        est = gb["dg_unleveled_mgal"].to_numpy()
        spread = float(np.std(est[inner]))
        assert np.sqrt(np.mean((est[inner] - plain[inner]) ** 2)) < 0.05 * spread, line
        # a larger level passes more of z: the estimate varies more about its smooth trend
        da = np.diff(ga["dg_unleveled_mgal"].to_numpy()[inner], 2)
        db = np.diff(est[inner], 2)
        assert np.std(db) > 1.2 * np.std(da), line   # measured 1.7× at a scale of 8
        checked += 1
    assert checked >= 4   # the four 30 km main lines


def test_bad_scale_is_refused_naming_the_field(tiny_survey, tmp_path):
    from app.pipeline.process import process_survey

    with pytest.raises(InputError, match="anomaly_level_scale"):
        process_survey(tiny_survey, tmp_path / "out", {"anomaly_level_scale": 0.0})
    assert not (tmp_path / "out" / "lines.parquet").exists()


def test_a_filter_job_takes_the_scale_from_its_parameters(tiny_survey, tmp_path):
    """The web application's filter job (from the stored identification) applies the scale given
    to it and starts from the levels as fitted, not from a scaled run's; a setting it is not
    given is the one the filter job before it was given, else the identification's
    (``filter_from``), and the earlier result's stored settings are left as they were."""
    from app.pipeline.process import run_job

    first = tmp_path / "process"
    base = run_job(tiny_survey, first, {"anomaly_level_scale": 2.0}, kind="process")
    assert base["level_refinement"]["anomaly_level_scale"] == 2.0
    second = tmp_path / "filter"
    rep = run_job(tiny_survey, second, {"anomaly_level_scale": 0.25}, kind="filter", previous_dir=first)
    assert rep["level_refinement"]["anomaly_level_scale"] == 0.25
    np.testing.assert_allclose(rep["level_refinement"]["Q_mgal2"], base["level_refinement"]["Q_mgal2"], rtol=1e-6)
    a, b = pd.read_parquet(first / "lines.parquet"), pd.read_parquet(second / "lines.parquet")
    np.testing.assert_allclose(b["Q_mgal2"].to_numpy(), 0.125 * a["Q_mgal2"].to_numpy(), rtol=1e-6)
    # a filter job given only h and ρ (the recognition view's) keeps the earlier filter job's scale
    third = tmp_path / "again"
    rep3 = run_job(tiny_survey, third, {"nlmeans_h_per_km": 0.6, "nlmeans_rho_km": 10.0}, kind="filter",
                   previous_dir=second)
    assert rep3["level_refinement"]["anomaly_level_scale"] == 0.25
    assert rep3["filter_settings"]["carried"] == {"anomaly_level_scale": 0.25}
    np.testing.assert_allclose(rep3["level_refinement"]["Q_mgal2"], base["level_refinement"]["Q_mgal2"], rtol=1e-6)
    # ... and the result it started from still holds its own settings
    stored = json.loads((second / "identified" / "filter_settings.json").read_text())
    assert stored == {"anomaly_level_scale": 0.25}
    again = json.loads((third / "identified" / "filter_settings.json").read_text())
    assert again == {"anomaly_level_scale": 0.25, "nlmeans_h_per_km": 0.6, "nlmeans_rho_km": 10.0}
