"""A line window that reaches into a turn is named in a warning (lines.csv t_start/t_end).

The track is analytic: 600 s east at 100 m/s, then a 180° turn at 3°/s (60 s), at 10 Hz.
"""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest

from app.core.geodesy import heading_departures
from app.pipeline.stages.lines import turn_warnings

DT = 0.1


def _track(turn_s=60.0, rate_deg_s=3.0):
    t = np.arange(0.0, 600.0 + turn_s, DT)
    heading = np.deg2rad(90.0 + rate_deg_s * np.clip(t - 600.0, 0.0, None))   # from north, clockwise
    return t, 100.0 * np.sin(heading), 100.0 * np.cos(heading)


def test_departures_of_a_turn_at_the_end():
    t, ve, vn = _track()
    d = heading_departures(t, ve, vn, max_deg=30.0)
    # the turn's unit vectors (600 samples, their sum at most 600·2/π) move the line's heading by at
    # most atan(382/6000) = 3.6°: the turn is 30° off after 10 ± 1.2 s, so 50 ± 1.2 s are off (± a GNSS
    # step: the record ends at 659.9 s), up to 180 − 3.6°
    assert 48.8 - DT <= d["seconds"] <= 51.2 + DT
    assert 180.0 - 3.65 - 0.3 <= d["max_deg"] <= 180.0   # the last epoch has turned 179.7°; atan(382/6000) = 3.64°
    assert 608.8 <= d["first_s"] <= 611.2 + DT and d["last_s"] == pytest.approx(t[-1])
    straight = heading_departures(t[t < 600.0], ve[t < 600.0], vn[t < 600.0])
    assert straight["seconds"] == 0.0 and straight["max_deg"] < 1e-6


def _line(t, name="M1"):
    return SimpleNamespace(line=name, flight="F1", t_s=t, sl=slice(0, t.size))


def test_turn_in_the_window_is_warned_and_a_straight_line_is_not():
    t, ve, vn = _track()
    flights = {"F1": SimpleNamespace(ve_ms=ve, vn_ms=vn)}
    (w,) = turn_warnings([_line(t)], flights)
    assert re.match(r"line M1 \(flight F1\): (49|50|51) s of its window", w)
    assert "(at its end)" in w and "more than 30° off the line's heading (up to 17" in w
    n = int(600.0 / DT)
    assert turn_warnings([_line(t[:n])], {"F1": SimpleNamespace(ve_ms=ve[:n], vn_ms=vn[:n])}) == []
    # a gentle 4 s swing past 30° (a gust, a correction) is not a turn
    t2, ve2, vn2 = _track(turn_s=14.0)
    assert turn_warnings([_line(t2)], {"F1": SimpleNamespace(ve_ms=ve2, vn_ms=vn2)}) == []
