"""A height-type AR corner fitted inside the noise fit's band is moved below the data
(simulation with known truth).

Random layout 410 of ``benchmarks/bench_unseen.py --geometry``: five 40 km lines 4 km up at
105 m/s, no crossings, GNSS velocities at 5 Hz with white errors, a 1 Hz platform gravimeter.
z's true noise rises as f² up to 0.06 Hz and faster above (the 1 Hz record against 5 Hz
epochs).  The BIC chose a coloured height error with its corner at 0.044 Hz — above twice the
anomaly/noise crossover, where the corner rule did not look — so the model's noise fell as f⁴
below 0.044 Hz, 20x under the truth at 0.01 Hz, and the smoother let it through as anomaly:
1.82x the FIR 100 s error.  With the corner moved below the data, 0.87x."""

import numpy as np
import pandas as pd

from app.core.accuracy import rms_vs_reference
from app.pipeline.evaluate import merge_truth
from app.pipeline.process import process_survey

LAYOUT_410 = dict(n_main=5, main_length_km=40.0, main_spacing_km=2.0, n_tie=0, n_flights=1, n_repeat=0,
                  speed_ms=104.9, height_m=4037.5, crs="EPSG:32612", normal_gravity="WGS84", gnss_rate_hz=5.0,
                  wind_ms=4.4, episode_rate_per_h=0.31, mountain_std_mgal=14.3, plain_std_mgal=6.58,
                  gravimeter_model="AIRGrav", tau_true_s=0.0, tau_declared_s=0.0, gravimeter_clock="aligned",
                  gravimeter_rate_hz=1.0)


def test_height_corner_inside_the_fitted_band_is_moved_below_the_data(tmp_path):
    from app.simulate import simulate_survey

    survey = simulate_survey("omolon-mini", tmp_path / "survey", seed=410, **LAYOUT_410)
    out = tmp_path / "out"
    # the plain interval means, whose error above 0.06 Hz the corner was fitted to: since session 51
    # the short lines' comparison cancels the motion here instead (no corner then; 4.28 against
    # FIR's 6.05 mGal, the plain means' estimate 4.63)
    nm = process_survey(survey, out, {"slow_gravimeter_min_ratio": None})["noise_model"]
    f_low = nm["max_corner_hz"]                   # set when corners were moved: the lowest fitted frequency
    assert nm["hidden_corners_hz"] and f_low is not None
    corners = [(1.0 - c["phi"]) / (2.0 * np.pi * nm["dt_s"]) for c in nm["components"] if c["phi"] > 0]
    assert all(k <= f_low * (1 + 1e-9) for k in corners), (corners, f_low)

    m = merge_truth(pd.read_parquet(out / "lines.parquet"), pd.read_parquet(survey / "truth" / "lines.parquet"))
    core = m[(m["along_km"] >= 10.0) & (m["along_km"] <= m.groupby("line")["along_km"].transform("max") - 10.0)]
    rms = {c: rms_vs_reference(core[c], core["dg_true_mgal"], line=core["line"]) for c in ("dg_mgal", "dg_fir_mgal")}
    assert rms["dg_mgal"] < rms["dg_fir_mgal"], rms
