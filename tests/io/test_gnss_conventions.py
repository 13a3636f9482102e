"""GNSS files whose vu is not SPEC's (m/s, up, = dh/dt): told from the file's own heights.

The truth is analytic: heights ``h = 3000 + A sin(ω τ)`` and the velocity ``A ω cos(ω τ)``; the
exports tried are the ones receivers' software writes — a NED ``vd`` (positive down) in the vu
column, heights in feet beside a velocity in m/s, a velocity in ft/s beside heights in metres.
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.core.measurement import height_rate_ratio
from app.io.errors import InputError
from app.io.survey import read_survey
from tests.io.test_io_survey import T0, make_tables, write_survey

A_M, OMEGA = 5.0, 2 * np.pi / 20.0   # a 20 s phugoid of ±5 m
FT = 0.3048                           # m per international foot


def _survey(tmp_path, h_factor=1.0, vu_factor=1.0):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    x = gnss["time"].to_numpy() - T0
    gnss = gnss.copy()
    gnss["h"] = (3000.0 + A_M * np.sin(OMEGA * x)) * h_factor
    gnss["vu"] = A_M * OMEGA * np.cos(OMEGA * x) * vu_factor
    return write_survey(tmp_path / "s", lines, {"F1": (grav, gnss)}), x


def test_ratio_of_heights_to_integrated_velocity():
    t = np.arange(0.0, 600.0, 0.1)
    h = 3000.0 + A_M * np.sin(OMEGA * t)
    v = A_M * OMEGA * np.cos(OMEGA * t)
    b, corr, n = height_rate_ratio(t, h, v)
    assert n == 299                                    # 2 s windows: 20 GNSS steps each
    assert b == pytest.approx(1.0, abs=1e-3) and corr > 0.999
    assert height_rate_ratio(t, h, -v)[0] == pytest.approx(-1.0, abs=1e-3)
    assert height_rate_ratio(t, h / FT, v)[0] == pytest.approx(1 / FT, rel=1e-3)
    # a level flight with centimetric velocity noise moves too little to tell
    rng = np.random.default_rng(0)
    b, corr, _ = height_rate_ratio(t, 3000.0 + 0 * t, 0.01 * rng.standard_normal(t.size))
    assert np.isnan(b) and np.isnan(corr)


def test_consistent_velocity_is_kept(tmp_path):
    root, x = _survey(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = read_survey(root)
    np.testing.assert_allclose(s.flights["F1"].gnss["vu"].to_numpy(), A_M * OMEGA * np.cos(OMEGA * x), atol=1e-12)
    assert not [w for w in caught if "integral of vu" in str(w.message)]


def test_positive_down_velocity_is_flipped_with_a_warning(tmp_path):
    root, x = _survey(tmp_path, vu_factor=-1.0)
    with pytest.warns(UserWarning, match="vu is positive down"):
        s = read_survey(root)
    np.testing.assert_allclose(s.flights["F1"].gnss["vu"].to_numpy(), A_M * OMEGA * np.cos(OMEGA * x), atol=1e-12)
    assert any("flights/F1/gnss.csv: the heights change -1 × the integral of vu" in n for n in s.notes)


@pytest.mark.parametrize("h_factor, vu_factor, says", [(1 / FT, 1.0, "h looks like feet beside a vu in m/s"),
                                                        (1.0, 1 / FT, "vu looks like ft/s beside an h in metres"),
                                                        (1.0, 2.0, "a unit or sign of h or vu is not SPEC's")])
def test_other_units_are_refused(tmp_path, h_factor, vu_factor, says):
    root, _ = _survey(tmp_path, h_factor=h_factor, vu_factor=vu_factor)
    with pytest.raises(InputError) as exc:
        read_survey(root)
    e = exc.value
    assert (e.file, e.column) == ("flights/F1/gnss.csv", "h")
    assert says in e.message
    assert f"{h_factor / vu_factor:.4g} × the integral of vu" in e.message


def _radian_survey(tmp_path, keep_velocities):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    gnss = gnss.copy()
    gnss["lat"], gnss["lon"] = np.deg2rad(gnss["lat"]), np.deg2rad(gnss["lon"])
    if not keep_velocities:
        gnss = gnss.drop(columns=["ve", "vn"])
    return write_survey(tmp_path / "s", lines, {"F1": (grav, gnss)})


def test_radians_with_velocities_are_refused(tmp_path):
    with pytest.raises(InputError) as exc:
        read_survey(_radian_survey(tmp_path, True))
    assert (exc.value.file, exc.value.column) == ("flights/F1/gnss.csv", "lat")
    assert "lat and lon look like radians" in exc.value.message


def test_radians_without_velocities_are_warned(tmp_path):
    # 100 m/s east at 62°N read as degrees at 1.082°N: 100·(π/180)·(R_N(1.08°) + h)·cos 1.082° / (6 394 000·cos 62°)
    # = 1.7453 · 6 380 014 / 3 001 804 = 3.71 m/s
    with pytest.warns(UserWarning, match=r"the positions move at a median 3\.7 m/s: radians\?"):
        read_survey(_radian_survey(tmp_path, False))


def test_declared_geoid_height_makes_orthometric_heights_ellipsoidal(tmp_path):
    """Heights written above the geoid (h − N): with ``geoid_height_m = N`` they are read back as
    the ellipsoidal heights of the clean file, to the last digit the CSV keeps, with a warning."""
    d = tmp_path / "s"
    shutil.copytree(Path(__file__).resolve().parents[2] / "sample_surveys" / "omolon-mini", d)
    gnss = d / "flights" / "F01" / "gnss.csv.gz"
    g = pd.read_csv(gnss)
    clean = g["h"].to_numpy()
    g["h"] = g["h"] - 31.25
    g.to_csv(gnss, index=False)
    with pytest.warns(UserWarning, match="made ellipsoidal by adding the declared geoid undulation 31.25 m"):
        s = read_survey(d, {"geoid_height_m": 31.25})
    np.testing.assert_allclose(s.flights["F01"].gnss["h"].to_numpy(), clean, atol=1e-6)
    assert np.max(np.abs(read_survey(d).flights["F01"].gnss["h"].to_numpy() - clean)) > 31.0   # undeclared: as written
