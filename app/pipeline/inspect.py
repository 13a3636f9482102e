"""``aerograv inspect``: a QC table per flight and line (rates, gaps, duration, length, lag).

:func:`inspect_table` is the survey QC of both the command line and the web application (the
browser's QC tab shows its figures), so the two never disagree.
"""

from __future__ import annotations

import numpy as np
import pandas as pd


def _time_offsets(survey) -> dict[str, tuple[float, float]]:
    """Per flight: the estimated gravimeter–GNSS time offset (s) and its correlation (NaN, NaN when
    it cannot be estimated)."""
    from app.core import gravimeter as gm
    from app.pipeline.stages.measurement import gravimeter_record

    cfg = survey.config
    lags = {}
    for name, fl in survey.flights.items():
        try:
            # the record as the measurement forms z from it (stamps on the clock, drops put back)
            series = gravimeter_record(fl.gravimeter, cfg.processing, []).series
            off, corr = gm.estimate_time_offset_s(series, fl.gnss["time"].to_numpy(float),
                                                  fl.gnss["vu"].to_numpy(float), cfg.gravimeter.tau_s,
                                                  cfg.gravimeter.scale, cfg.processing.max_time_offset_s)
            lags[name] = (round(off, 4), round(corr, 3))
        except ValueError:
            lags[name] = (np.nan, np.nan)
    return lags


def inspect_table(survey, time_offsets: bool = True) -> pd.DataFrame:
    """QC table of a read survey (:func:`app.io.survey.survey_summary`: one row per flight, then
    one per line, with rates from the median interval, the largest gaps, durations and ellipsoidal
    path lengths).  With ``time_offsets`` also ``lag_s`` and ``lag_corr``: each flight's
    gravimeter–GNSS time offset by cross-correlation of accelerations (seconds of computation per
    flight)."""
    from app.io.survey import survey_summary

    table = survey_summary(survey)
    if time_offsets:
        lags = _time_offsets(survey)
        table["lag_s"] = table["flight"].map(lambda f: lags.get(str(f), (np.nan, np.nan))[0])
        table["lag_corr"] = table["flight"].map(lambda f: lags.get(str(f), (np.nan, np.nan))[1])
    return table


def inspect_survey(survey_dir) -> pd.DataFrame:
    """QC table: one row per line (and its flight's sensor rates), with the estimated
    gravimeter–GNSS time offset of the flight (cross-correlation of accelerations)."""
    from app.io.survey import read_survey

    return inspect_table(read_survey(survey_dir))
