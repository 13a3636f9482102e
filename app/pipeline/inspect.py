"""``aerograv inspect``: a QC table per flight and line (rates, gaps, duration, length, lag)."""

from __future__ import annotations

import numpy as np
import pandas as pd


def inspect_survey(survey_dir) -> pd.DataFrame:
    """QC table: one row per line (and its flight's sensor rates), with the estimated
    gravimeter–GNSS time offset of the flight (cross-correlation of accelerations)."""
    from app.core import gravimeter as gm
    from app.io.survey import read_survey, survey_summary

    survey = read_survey(survey_dir)
    table = survey_summary(survey)
    cfg = survey.config
    lags = {}
    for name, fl in survey.flights.items():
        try:
            series = gm.integrate_samples(fl.gravimeter["time"].to_numpy(float), fl.gravimeter["f_z"].to_numpy(float))
            off, corr = gm.estimate_time_offset_s(series, fl.gnss["time"].to_numpy(float),
                                                  fl.gnss["vu"].to_numpy(float), cfg.gravimeter.tau_s,
                                                  cfg.gravimeter.scale, cfg.processing.max_time_offset_s)
            lags[name] = (round(off, 4), round(corr, 3))
        except ValueError:
            lags[name] = (np.nan, np.nan)
    table["lag_s"] = table["flight"].map(lambda f: lags.get(str(f), (np.nan, np.nan))[0])
    table["lag_corr"] = table["flight"].map(lambda f: lags.get(str(f), (np.nan, np.nan))[1])
    return table
