"""The smoothest level the lift-only refinement raised above the stationary model's level is
brought down to it (``refine_lift_max_stationary``), on a simulated survey with truth where the
lift happens: unseen draw 1413 of ``benchmarks/bench_unseen.py`` with prism mountains (1 Hz
point-sampled platform gravimeter, 5 Hz GNSS with Gauss–Markov velocity noise, noise episodes
up to 8×). The full-rate likelihood lifts the smooth level of both orders hundreds of times above
the EM's, far above the stationary level (m = 1: 0.033 → 13.4 mGal², stationary 0.86): without
the cap m = 1 is chosen and the survey is 1.12× FIR; with it, 0.77× (session 19).  With the
time offset fitted where a 1 Hz record carries the aircraft's acceleration (session 24) the lift
still happens, but no longer costs: the cap is checked to engage and not to hurt."""

import numpy as np
import pandas as pd

OVERRIDES = {
    "gnss_rate_hz": 5.0, "sigma_vu_cms": 1.1228777485744559, "vu_colored_cms": 0.9360677134631188,
    "vu_colored_tau_s": 11.258358336322893, "gravimeter_model": "AIRGrav", "tau_true_s": 0.0,
    "tau_declared_s": 0.0, "gravimeter_clock": "aligned", "gravimeter_rate_hz": 1.0,
    "gravimeter_sampling": "point", "gravimeter_fir_boxcars": 2, "gravimeter_fir_width_s": 1.0,
    "drape_amp_m": 53.503397234007856, "drift_rate_mgal_h": (0.2, 1.3387889641456725),
    "speed_ms": 97.00546727834374, "mountain_std_mgal": 34.75551652307483,
    "plain_std_mgal": 7.729472812147594, "mountain_sources_per_km2": 0.3808247419127811,
    "episode_rate_per_h": 3.0528232749954327, "episode_factor": (2.0, 7.914937656337093),
    "height_m": 676.4459466172049, "main_spacing_km": 2.0978776655747526,
    "grav_noise_mgal_rthz": 1.4353610348716244, "wind_ms": 3.5304874818184113, "mountain_bodies": "prisms",
}


def _rms_vs_truth(out, survey, col):
    from app.pipeline.evaluate import merge_truth

    m = merge_truth(pd.read_parquet(out / "lines.parquet"), pd.read_parquet(survey / "truth" / "lines.parquet"))
    m = m[m["dg_true_mgal"].notna()]
    e = m[col] - m["dg_true_mgal"]
    e = e - e.groupby(m["line"]).transform("mean")      # what leveling cannot see
    return float(np.sqrt(np.mean(e ** 2)))


def test_a_smooth_level_lifted_above_the_stationary_one_is_capped(tmp_path):
    from app.io.survey import read_survey
    from app.pipeline.runs import Tracker, run_filter, run_identify
    from app.simulate import simulate_survey

    survey = tmp_path / "survey"
    simulate_survey("omolon-mini", survey, seed=1413, **OVERRIDES)
    # the lift happens on z as measured before session 53: with the meter's two 1 s boxcars matched
    # (c = 0.051 s², 40 % of the acceleration residual) the full-rate likelihood no longer lifts the
    # smooth level here (and the estimate is 13.9 instead of 14.1 mGal, FIR 18.5), so the cap is
    # exercised on the unmatched z
    s = read_survey(survey)
    s.config = s.config.model_copy(update={"processing": s.config.processing.model_copy(
        update={"match_response": False})})
    idf = run_identify(s, Tracker(None))
    capped = run_filter(idf, tmp_path / "capped", Tracker(None))
    lift = capped["level_refinement"]["smooth_lift_capped"]
    # the lift is large (7.6× the EM's level with numpy 2.4 / scipy 1.17, 9× with numpy 2.3: the
    # simulated survey's draw differs between them) and above the stationary level, which caps it
    assert lift is not None and lift["lifted_mgal2"] > 5 * lift["used_mgal2"]
    assert lift["lifted_mgal2"] > lift["stationary_mgal2"]
    assert lift["used_mgal2"] == max(lift["stationary_mgal2"], lift["em_mgal2"])   # never below the EM's
    assert lift["stationary_mgal2"] == capped["level_refinement"]["Q_stationary_mgal2"]
    idf.config["processing"]["refine_lift_max_stationary"] = False
    lifted = run_filter(idf, tmp_path / "lifted", Tracker(None))
    assert lifted["level_refinement"]["smooth_lift_capped"] is None
    err_capped = _rms_vs_truth(tmp_path / "capped", survey, "dg_mgal")
    err_lifted = _rms_vs_truth(tmp_path / "lifted", survey, "dg_mgal")
    err_fir = _rms_vs_truth(tmp_path / "capped", survey, "dg_fir_mgal")
    # session 19: 14.0 against 21.2 mGal (FIR 19.6).  Since session 24 the time offset of this
    # 1 Hz record is fitted below 0.4 Hz (its 0.05 s offset found on every flight) and the
    # lifted estimate no longer passes the noise it did (14.0 against 14.0): the cap costs
    # nothing where the lift is harmless
    assert err_capped <= 1.02 * err_lifted
    assert err_capped < 0.8 * err_fir
