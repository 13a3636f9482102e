"""A repeat track's passes on one along-track axis (app.web.repeat), on passes laid out here: the
distance along the track is the distance from the first pass's start point, whichever way a pass
flies and wherever the passes wander across the track; tracks come from lines.csv or, for repeat
lines without one, from report.json's repeat_tracks_inferred."""

from __future__ import annotations

import numpy as np
import pandas as pd

from app.web.repeat import track_members, track_passes


def _pass(line, t0, s_km, offset_km, az_deg, start=(500.0, 7000.0)):
    """A pass at distances ``s_km`` along azimuth ``az_deg`` from ``start``, ``offset_km`` to its right."""
    a = np.radians(az_deg)
    u, v = np.array([np.sin(a), np.cos(a)]), np.array([np.cos(a), -np.sin(a)])
    e = start[0] + s_km * u[0] + offset_km * v[0]
    n = start[1] + s_km * u[1] + offset_km * v[1]
    return pd.DataFrame({"line": line, "flight": "F1", "kind": "repeat", "time": t0 + np.arange(s_km.size) * 0.5,
                         "easting_km": e, "northing_km": n, "dg_mgal": np.sin(s_km), "dg_std_mgal": 0.5,
                         "dg_stationary_mgal": np.sin(s_km) + 0.1, "dg_fir_mgal": np.sin(s_km) - 0.1})


def test_passes_flown_both_ways_share_one_axis():
    s = np.linspace(0.0, 30.0, 301)
    rng = np.random.default_rng(3)
    groups = {"P1": _pass("P1", 1000.0, s, rng.normal(0, 0.02, s.size), 60.0),
              "P2": _pass("P2", 2000.0, s[::-1][:-20], rng.normal(0, 0.02, s.size - 20), 60.0),   # back, stops 2 km short
              "P3": _pass("P3", 3000.0, s[10:], 0.05 + rng.normal(0, 0.02, s.size - 10), 60.0)}   # starts 1 km in
    out = track_passes("T", ["P3", "P2", "P1"], groups, {"repeat_lines": {"T": {"repeats": 3}}}, max_points=5000)
    assert [p["line"] for p in out["passes"]] == ["P1", "P2", "P3"]                 # in time order
    assert abs(out["axis"]["azimuth_deg"] - 60.0) < 0.2 and abs(out["axis"]["length_km"] - 30.0) < 0.1
    assert [p["direction"] for p in out["passes"]] == ["forward", "reverse", "forward"]
    for p, want in zip(out["passes"], (s, s[::-1][:-20], s[10:])):
        # along-track distance = distance from the first pass's start, to the wander across the track
        np.testing.assert_allclose(p["along_km"], want, atol=0.01)
    # P3 flies 50 m right of the others: the axis runs through the passes' mean, 50 m × its share of the points
    mean_offset_m = 50.0 * (s.size - 10) / (3 * s.size - 30)
    assert abs(out["passes"][2]["across_rms_m"] - np.hypot(50.0 - mean_offset_m, 20.0)) < 3.0
    assert out["repeatability"] == {"repeats": 3} and out["std_check"] is None
    np.testing.assert_allclose(out["passes"][1]["dg_fir"], np.round(np.sin(s[::-1][:-20]) - 0.1, 3))


def test_track_members_from_lines_csv_then_inferred():
    lines = [("A1", "repeat", "A"), ("A2", "repeat", "A"), ("M1", "main", None), ("X1", "repeat", None),
             ("X2", "repeat", None), ("B1", "repeat", "B")]
    present = {"A1", "A2", "M1", "X1", "X2", "B1"}
    got = track_members(lines, {"repeat_tracks_inferred": {"auto-1": ["X1", "X2"]}}, present)
    assert got == {"A": ["A1", "A2"], "auto-1": ["X1", "X2"]}                        # B has one pass: none
    assert track_members(lines, {}, present - {"A2"}) == {}
