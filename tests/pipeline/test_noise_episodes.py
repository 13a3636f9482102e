"""The report's noise episodes (stages.noise.noise_episodes): by hand on a constructed table,
and against the simulator's drawn GNSS noise episodes."""

import json

import numpy as np
import pandas as pd
import pytest

from app.pipeline.stages.noise import noise_episodes


def _line(name, t0, n, r, std, speed_kms=0.1, flight="F01"):
    t = t0 + np.arange(n, dtype=float)             # 1 Hz
    return pd.DataFrame({"line": name, "flight": flight, "time": t, "easting_km": speed_kms * (t - t0),
                         "northing_km": 0.0, "R_cm2s2": r, "dg_std_mgal": std})


def test_episodes_by_hand():
    n = 600
    r_a = np.full(n, 1.0)
    r_a[100:220] = 20.0                            # 120 s at 20× (the median stays 1)
    r_a[300:320] = 20.0                            # 20 s: shorter than the 30 s listed
    std_a = np.where(r_a > 1, 5.0, 2.0)
    table = pd.concat([_line("A", 0.0, n, r_a, std_a),
                       _line("B", 1000.0, n, np.full(n, 1.0), np.full(n, 2.0), flight="F02")], ignore_index=True)
    rep, warns = noise_episodes(table, 4.0, 30.0, 10.0)
    assert rep["typical_R_cm2s2"] == pytest.approx(1.0)
    assert rep["threshold_R_cm2s2"] == pytest.approx(4.0)
    assert rep["lines"] == ["A"]
    (ep,) = rep["episodes"]
    assert (ep["line"], ep["flight"]) == ("A", "F01")
    assert (ep["t_start_s"], ep["t_end_s"], ep["duration_s"]) == (100.0, 219.0, 119.0)
    assert ep["along_start_km"] == pytest.approx(10.0) and ep["along_end_km"] == pytest.approx(21.9)
    assert ep["R_peak_over_typical"] == pytest.approx(20.0) and ep["R_mean_over_typical"] == pytest.approx(20.0)
    assert ep["std_mean_mgal"] == pytest.approx(5.0)
    # the line's std outside its listed episodes: the short one's 20 epochs at 5 among 480 at 2
    assert ep["std_line_quiet_mgal"] == pytest.approx(2.0)
    assert rep["epoch_fraction"] == pytest.approx(120 / 1200)
    assert len(warns) == 1 and "A 10–22 km" in warns[0] and "20×" in warns[0]
    # the two stretches of A as one when the 80 s gap between them is bridged
    rep, _ = noise_episodes(table, 4.0, 30.0, 81.0)
    assert [(e["t_start_s"], e["t_end_s"]) for e in rep["episodes"]] == [(100.0, 319.0)]
    # none above 25×: nothing listed, no warning
    rep, warns = noise_episodes(table, 25.0, 30.0, 10.0)
    assert rep["episodes"] == [] and warns == []


def test_no_levels_no_episodes():
    table = _line("A", 0.0, 100, np.full(100, np.nan), np.full(100, 1.0))
    rep, warns = noise_episodes(table, 4.0, 30.0, 10.0)
    assert rep["typical_R_cm2s2"] is None and rep["episodes"] == [] and warns == []
    rep, warns = noise_episodes(table.drop(columns="R_cm2s2"), 4.0, 30.0, 10.0)   # no level column at all
    assert rep["typical_R_cm2s2"] is None and rep["episodes"] == [] and warns == []


def test_episodes_are_where_the_simulator_drew_them(tmp_path):
    # the tiny preset with GNSS noise episodes (velocity std ×3–5, R ×9–25) every 10 min on
    # average: every listed episode overlaps a drawn one (within the 60 s window of the band
    # level), and every drawn one that covers ≥ 60 s of a line is listed
    from app.pipeline.process import process_survey
    from app.simulate import simulate_survey

    survey = simulate_survey("tiny", tmp_path / "survey", seed=5, episode_rate_per_h=6.0)
    rep = process_survey(survey, tmp_path / "out")
    drawn = [(e["t_start"], e["t_end"]) for f in json.loads((survey / "truth" / "truth.json").read_text())["flights"].values()
             for e in f["gnss_noisy_episodes"]]
    listed = rep["noise_episodes"]["episodes"]
    assert listed, "no episode listed"
    for e in listed:
        assert any(e["t_start_s"] < b + 30.0 and e["t_end_s"] > a - 30.0 for a, b in drawn), e
    lines = pd.read_parquet(tmp_path / "out" / "lines.parquet").groupby("line")["time"].agg(["min", "max"])
    for a, b in drawn:
        for line, (t0, t1) in lines.iterrows():
            if min(b, t1) - max(a, t0) >= 60.0:
                assert any(e["line"] == line and e["t_start_s"] < b and e["t_end_s"] > a for e in listed), (line, a, b)
    assert any("noise episodes" in w for w in rep["warnings"])
