"""Passes of one repeat track must lie on one track: two parallel lines 2 km apart marked as one
track gave a repeat-line "internal accuracy" of 6 mGal with no word (found by fuzzing lines.csv).
The report now gives each track's across-track spread and warns above 0.5 km."""

import numpy as np
import pandas as pd

from app.pipeline.stages.outputs import REPEAT_MAX_SPREAD_KM, repeat_accuracy, repeat_track_warnings


def _pass(line, track, northing_km, reverse=False):
    e = np.linspace(0.0, 30.0, 301)
    e = e[::-1] if reverse else e
    dg = 10.0 * np.sin(e / 4.0) + 0.3 * northing_km * 10.0     # the anomaly changes across the track
    return pd.DataFrame({"line": line, "kind": "repeat", "track": track, "easting_km": e,
                         "northing_km": np.full(e.size, northing_km), "dg_mgal": dg, "dg_fir_mgal": dg,
                         "dg_stationary_mgal": dg})


def test_passes_apart_across_the_track_are_warned():
    table = pd.concat([_pass("R1a", "R1", 0.0), _pass("R1b", "R1", 2.0, True),
                       _pass("R2a", "R2", 5.0), _pass("R2b", "R2", 5.05, True), _pass("R2c", "R2", 4.98)],
                      ignore_index=True)
    rep = repeat_accuracy(table)
    assert abs(rep["R1"]["across_track_spread_km"] - 2.0) < 1e-9
    assert abs(rep["R2"]["across_track_spread_km"] - 0.07) < 1e-9
    assert rep["R1"]["internal_accuracy_mgal"]["dg_mgal"] > 1.0      # what it compared: different ground
    (w,) = repeat_track_warnings(rep)
    assert w.startswith("repeat track R1: its 2 passes lie 2.00 km apart") and f"{REPEAT_MAX_SPREAD_KM} km" in w
