"""A GNSS file on UTC beside a gravimeter on GPS time (18 s apart) is aligned by the time-offset
search, and the note says so.  The simulator's tiny survey with its GNSS times moved 18 s back."""

from __future__ import annotations

import json
import shutil
import warnings

import pandas as pd
import pytest

from app.io.survey import read_survey
from app.pipeline.stages.measurement import measure_flight


def _measure(root):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = read_survey(root)
    name = sorted(s.flights)[0]
    return measure_flight(s.flights[name], s.config, compensation=False)


def test_gnss_on_utc_is_aligned_and_named(tiny_survey, tmp_path):
    root = tmp_path / "utc"
    shutil.copytree(tiny_survey, root)
    for p in (root / "flights").glob("*/gnss.csv*"):
        g = pd.read_csv(p)
        g["time"] -= 18.0
        g.to_csv(p, index=False)
    clean = _measure(tiny_survey)
    m = _measure(root)
    # truth.json: gravimeter stamp = true interval centre + time_offset_s, and the pipeline's offset is
    # what the gravimeter's stamps need added to reach GNSS time: here − time_offset_s − 18 s
    truth = json.loads((tiny_survey / "truth" / "truth.json").read_text())
    expected = -float(truth.get("time_offset_s", 0.0)) - 18.0
    assert m.time_offset["applied"]
    assert m.time_offset["offset_s"] == pytest.approx(expected, abs=0.01)
    (note,) = [n for n in m.notes if n.startswith("time offset -1")]
    assert "s applied" in note and "GPS − UTC leap seconds" in note
    assert not [n for n in clean.notes if "clocks differ" in n]
