"""Heights-only GNSS on small surveys: the noise shape below the fitted band (simulations with
known truth).

First: the height family the heights-only rule prefers keeps no AR corner inside the fitted band.

The survey is the random layout 117 of ``benchmarks/bench_unseen.py --geometry``: two 40 km
lines and two ties, 2 Hz GNSS heights with a 3 cm, 30 s Gauss–Markov error (its z error rises
as f² from 0.005 Hz up), 66 decimated points, so one anomaly level.  The BIC chose white
velocity; the heights-only rule put the coloured height family in its place, and that
family's corner landed at 0.04 Hz, inside the band and above twice the anomaly/noise
crossover, where the corner rule did not look.  Below it the model's noise fell as f⁴ while
the truth's keeps falling as f²: the smoother let the noise through as anomaly, 1.5x the RMS
of the FIR 100 s low-pass.  With the corner moved below the data the estimate is level with
FIR (0.99x).

Second: where velocity + height fits best it is used, not the margin's simpler choice.  Layout
167 (three 40 km lines at 129 m/s, 20 Hz heights with the same error, no crossings): the
simplest family within the BIC margin was a coloured height with its corner at 0.079 Hz,
1.67x FIR; velocity + height, 5.5 lower in BIC, carries the f² down and gives 0.75x.

Third: on short lines "below the data" can still be the anomaly band.  Layout 489 (fourteen
12 km lines at 74 m/s, 2 Hz heights with the 3 cm, 30 s error): the spectra start at 0.054 Hz,
and the preferred coloured height put its corner at 0.034 Hz — below the data, above the band
where FIR and the smoother cut (1.44x FIR).  A GNSS height error correlated over ≥ 20 s has its
corner at ≤ 0.008 Hz; held there, 0.82x."""

import numpy as np
import pandas as pd

from app.core.accuracy import rms_vs_reference
from app.pipeline.evaluate import merge_truth
from app.pipeline.process import process_survey

LAYOUT_117 = dict(n_main=2, main_length_km=40.0, main_spacing_km=2.0, n_tie=2, n_flights=1, n_repeat=0,
                  speed_ms=75.3, height_m=2165.0, crs="EPSG:32657", normal_gravity="Helmert1901",
                  gnss_rate_hz=2.0, wind_ms=0.07, episode_rate_per_h=3.46, mountain_std_mgal=22.1,
                  plain_std_mgal=4.9, gnss_velocity=False, sigma_h_m=0.005, h_colored_m=0.03)


LAYOUT_167 = dict(n_main=3, main_length_km=40.0, main_spacing_km=8.0, n_tie=0, n_flights=1, n_repeat=0,
                  speed_ms=128.7, height_m=2799.0, crs="EPSG:32657", normal_gravity="WGS84", gnss_rate_hz=20.0,
                  wind_ms=9.73, episode_rate_per_h=0.58, mountain_std_mgal=37.7, plain_std_mgal=10.0,
                  gnss_velocity=False, sigma_h_m=0.005, h_colored_m=0.03)


LAYOUT_489 = dict(n_main=14, main_length_km=12.0, main_spacing_km=4.0, n_tie=0, n_flights=2, n_repeat=0,
                  speed_ms=73.5, height_m=2274.0, crs="EPSG:32657", normal_gravity="WGS84", gnss_rate_hz=2.0,
                  wind_ms=19.0, episode_rate_per_h=3.47, mountain_std_mgal=9.29, plain_std_mgal=8.82,
                  gnss_velocity=False, sigma_h_m=0.005, h_colored_m=0.03)


def _line_rms(survey, out, edge_fraction: float | None = None) -> dict:
    """Line-demeaned RMS against the truth of the estimate and FIR, 10 km in from the line ends
    (or ``edge_fraction`` of each line's length, as the benchmarks score 12 km lines)."""
    m = merge_truth(pd.read_parquet(out / "lines.parquet"), pd.read_parquet(survey / "truth" / "lines.parquet"))
    length = m.groupby("line")["along_km"].transform("max")
    edge = 10.0 if edge_fraction is None else edge_fraction * length
    core = m[(m["along_km"] >= edge) & (m["along_km"] <= length - edge)]
    return {c: rms_vs_reference(core[c], core["dg_true_mgal"], line=core["line"]) for c in ("dg_mgal", "dg_fir_mgal")}


def test_preferred_height_family_keeps_no_corner_in_the_data(tmp_path):
    from app.simulate import simulate_survey

    survey = simulate_survey("omolon-mini", tmp_path / "survey", seed=117, **LAYOUT_117)
    out = tmp_path / "out"
    report = process_survey(survey, out)
    nm = report["noise_model"]
    assert nm["height_family_preferred"] == "white velocity"
    f_low = nm["max_corner_hz"]                     # the corners' bound: the lowest fitted frequency
    assert f_low is not None and nm["hidden_corners_hz"]
    corners = [(1.0 - c["phi"]) / (2.0 * np.pi * nm["dt_s"]) for c in nm["components"] if c["phi"] > 0]
    assert all(k <= f_low * (1 + 1e-9) for k in corners), (corners, f_low)

    rms = _line_rms(survey, out)
    assert rms["dg_mgal"] <= 1.1 * rms["dg_fir_mgal"], rms   # 1.53x with the corner at 0.04 Hz


def test_velocity_and_height_is_used_where_it_fits_best(tmp_path):
    from app.simulate import simulate_survey

    survey = simulate_survey("omolon-mini", tmp_path / "survey", seed=167, **LAYOUT_167)
    out = tmp_path / "out"
    report = process_survey(survey, out)
    nm = report["noise_model"]
    best = min(nm["candidates"], key=lambda c: c["bic"])
    assert best["family"] == "velocity + height" and nm["family"] == "velocity + height"
    assert nm["best_fit_replaced"] is not None
    rms = _line_rms(survey, out)
    assert rms["dg_mgal"] <= 0.9 * rms["dg_fir_mgal"], rms   # 1.67x with the margin's coloured height


def test_preferred_height_corner_stays_below_what_gnss_heights_allow(tmp_path):
    from app.config import ProcessingParams
    from app.simulate import simulate_survey

    survey = simulate_survey("omolon-mini", tmp_path / "survey", seed=489, **LAYOUT_489)
    out = tmp_path / "out"
    nm = process_survey(survey, out)["noise_model"]
    assert nm["height_family_preferred"] == "white velocity"
    f_cap = 1.0 / (2.0 * np.pi * ProcessingParams().noise_height_tau_min_s)
    assert nm["max_corner_hz"] is not None and nm["max_corner_hz"] <= f_cap * (1 + 1e-6)
    corners = [(1.0 - c["phi"]) / (2.0 * np.pi * nm["dt_s"]) for c in nm["components"] if c["phi"] > 0]
    assert all(k <= f_cap * (1 + 1e-6) for k in corners), corners
    rms = _line_rms(survey, out, edge_fraction=0.2)      # 12 km lines: a fifth left out at each end
    assert rms["dg_mgal"] < rms["dg_fir_mgal"], rms
