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


def test_an_undeclared_lag_is_not_taken_for_feet(tmp_path):
    """τ = 3 s undeclared (tau_s = 0): 1/|1 + iωτ| lowers the gravimeter's acceleration to about 0.3 of
    the GNSS's over 0.01–1 Hz — like feet — but not below 0.05 Hz (≥ 0.73 there): no refusal."""
    from app.simulate import simulate_survey

    root = simulate_survey("tiny", tmp_path / "lag", seed=3, tau_true_s=3.0, tau_declared_s=0.0)
    _, m = _measure(root)
    assert abs(m.time_offset["gain"] / FT - 1) < 0.1       # over the whole band it looks like feet
    assert m.time_offset["gain_low"] > 0.73 and m.time_offset["gain_low_correlation"] > 0.5


def test_feet_with_an_undeclared_lag_is_refused(tmp_path):
    from app.simulate import simulate_survey

    src = simulate_survey("tiny", tmp_path / "lag", seed=3, tau_true_s=3.0, tau_declared_s=0.0)
    root = _feet_copy(src, tmp_path / "feet")
    with pytest.raises(InputError, match="the GNSS heights look like feet"):
        _measure(root)
