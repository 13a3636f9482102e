"""GNSS heights and velocities both in feet agree with each other, so no check of the GNSS file sees
them; the gravimeter does: its acceleration is 0.3048 × the GNSS's.  Uses the simulator's tiny
survey (the truth: every file in SI units) with its GNSS h and vu multiplied by 1/0.3048."""

from __future__ import annotations

import shutil
import warnings

import pandas as pd
import pytest

from app.io.errors import InputError
from app.io.survey import read_survey
from app.pipeline.stages.measurement import measure_flight

FT = 0.3048


def _feet_copy(src, dst, drop_vu=False):
    shutil.copytree(src, dst)
    for p in (dst / "flights").glob("*/gnss.csv*"):
        g = pd.read_csv(p)
        g["h"] = g["h"] / FT
        g["vu"] = g["vu"] / FT
        if drop_vu:
            g = g.drop(columns=["vu", "ve", "vn", "sigma_v"], errors="ignore")
        g.to_csv(p, index=False)
    return dst


def _measure(root):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = read_survey(root)
    name = sorted(s.flights)[0]
    return name, measure_flight(s.flights[name], s.config, compensation=False)


def test_si_survey_has_unit_gain(tiny_survey):
    _, m = _measure(tiny_survey)
    assert m.time_offset["gain"] == pytest.approx(1.0, abs=0.1)
    assert not [n for n in m.notes if "× the GNSS's" in n]


@pytest.mark.parametrize("drop_vu", [False, True])
def test_gnss_in_feet_is_refused(tiny_survey, tmp_path, drop_vu):
    root = _feet_copy(tiny_survey, tmp_path / "feet", drop_vu)
    with pytest.raises(InputError) as exc:
        _measure(root)
    e = exc.value
    assert e.column == "h" and e.file.startswith("flights/") and e.file.split("/")[-1].startswith("gnss.csv")
    assert "the GNSS heights look like feet" in e.message
    gain = float(e.message.split("acceleration is ")[1].split(" ×")[0])
    assert gain == pytest.approx(FT, rel=0.03)
