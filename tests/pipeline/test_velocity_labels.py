"""A GNSS file whose ve/vn columns are swapped or sign-flipped is read the way its own positions
say, with a note (a vn sign alone changes no correction: Harlan's Eötvös term has vn²).  The track
is analytic: 600 s due east at 100 m/s (vn = 0: on such lines a swap and a swap-with-vn-negated look
alike), then a full 360° turn at 3°/s, at 10 Hz and 62°N; positions are the velocities integrated
with the WGS84 radii of curvature."""

from __future__ import annotations

import numpy as np
import pytest

from app.core.geodesy import radii_of_curvature_m, velocity_relabelling
from app.pipeline.stages.measurement import checked_horizontal_velocities

DT, V, LAT0, H = 0.1, 100.0, 62.0, 3000.0


def _track():
    t = np.arange(0.0, 720.0, DT)
    heading = np.deg2rad(90.0 + 3.0 * np.clip(t - 600.0, 0.0, None))
    ve, vn = V * np.sin(heading), V * np.cos(heading)
    lat = np.empty_like(t)
    lon = np.empty_like(t)
    lat[0], lon[0] = LAT0, 150.0
    for k in range(1, t.size):          # midpoint rule, the radii at the previous latitude
        r_m, r_n = radii_of_curvature_m(lat[k - 1])
        vn_mid, ve_mid = 0.5 * (vn[k] + vn[k - 1]), 0.5 * (ve[k] + ve[k - 1])
        lat[k] = lat[k - 1] + np.rad2deg(vn_mid * DT / (r_m + H))
        lon[k] = lon[k - 1] + np.rad2deg(ve_mid * DT / ((r_n + H) * np.cos(np.deg2rad(lat[k - 1]))))
    return t, lat, lon, np.full(t.size, H), ve, vn


@pytest.mark.parametrize("label, make", [("ve and vn swapped", lambda ve, vn: (vn, ve)),
                                         ("ve negated", lambda ve, vn: (-ve, vn)),
                                         ("ve and vn negated", lambda ve, vn: (-ve, -vn))])
def test_mislabelled_velocities_are_read_as_the_positions_say(label, make):
    t, lat, lon, h, ve, vn = _track()
    notes = []
    got_e, got_n = checked_horizontal_velocities(t, lat, lon, h, *make(ve, vn), notes)
    np.testing.assert_allclose(got_e, ve, atol=1e-12)
    np.testing.assert_allclose(got_n, vn, atol=1e-12)
    (note,) = notes
    assert f"with {label} they agree to" in note


def test_right_velocities_are_kept_silently_and_the_turn_decides():
    t, lat, lon, h, ve, vn = _track()
    notes = []
    got = checked_horizontal_velocities(t, lat, lon, h, ve, vn, notes)
    assert got[0] is ve and got[1] is vn and notes == []
    # swapped on the east line only, (vn, ve) and (vn, −ve) are both (100, 0): the turn's 120 s
    # (a sixth of the epochs, |difference| up to 2·100 m/s) set the runner-up's mean misfit far above
    label, _, _, best, runner_up = velocity_relabelling(t, lat, lon, h, vn, ve)
    assert label == "ve and vn swapped" and best < 1.0 and runner_up > 10.0
