"""Stage 1's residual timing at the anomaly's edge (``check_band_delay``).

Simulation with known truth: two flights of one instrument whose gravimeter is late by a
known delay against the GNSS (a phugoid and a slower mode of 10⁴ mGal, white GNSS velocity
noise); z must come out with that delay taken out below the low-pass, untouched where there is
none, and the report must say which and why.
"""

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from app.config import ProcessingParams
from app.core.measurement import band_delay_fit, gnss_acceleration_ms2
from app.pipeline.stages.measurement import check_band_delay

DT_S = 0.1


def _velocity(t):
    """Vertical velocity (m/s) of a phugoid of 45 s and a mode of 28 s (0.15 and 0.03 m/s²)."""
    w1, w2 = 2 * np.pi / 45.0, 2 * np.pi / 28.0
    return -0.15 / w1 * np.cos(w1 * t) - 0.03 / w2 * np.cos(w2 * t + 1.0)


def _flight(rng, t0, delay_s, n=40_000):
    t = t0 + np.arange(n) * DT_S
    vu = _velocity(t) + rng.normal(0.0, 0.005, n)
    late = 1e5 * (_velocity(t - delay_s) - _velocity(t - delay_s - DT_S)) / DT_S   # the gravimeter's means
    z = late - 1e5 * gnss_acceleration_ms2(t, vu) + 4.0 * np.sin(2 * np.pi * t / 500.0)
    return SimpleNamespace(t_s=t, vu_ms=vu, ve_ms=np.full(n, 80.0), vn_ms=np.zeros(n), z_mgal=z)


def _survey(delay_s, seed=4, delay2_s=None):
    rng = np.random.default_rng(seed)
    flights = {"F1": _flight(rng, 1000.0, delay_s),
               "F2": _flight(rng, 90_000.0, delay_s if delay2_s is None else delay2_s)}
    lines = pd.DataFrame({"flight": ["F1", "F1", "F2", "F2"],
                          "t_start": [1300.0, 2800.0, 90_300.0, 91_800.0],
                          "t_end": [2500.0, 4600.0, 91_500.0, 94_600.0]})
    return flights, lines


def _refit(flights, lines, only=None):
    segs = []
    for name, m in flights.items():
        if only is not None and name != only:
            continue
        use = np.zeros(m.t_s.size, bool)
        for a, b in lines.loc[lines["flight"] == name, ["t_start", "t_end"]].to_numpy(float):
            use |= (m.t_s >= a) & (m.t_s <= b)
        segs.append((m.t_s, m.z_mgal, 1e5 * gnss_acceleration_ms2(m.t_s, m.vu_ms), use))
    return band_delay_fit(segs, DT_S, (0.01, 0.05))


@pytest.mark.parametrize("delay_s, word", [(0.02, "late"), (-0.02, "early")])
def test_a_late_or_early_gravimeter_is_put_right_below_the_low_pass(delay_s, word):
    flights, lines = _survey(delay_s)
    before = {k: m.z_mgal.copy() for k, m in flights.items()}
    warnings = []
    rec = check_band_delay(flights, lines, ProcessingParams(), warnings)
    assert rec["applied"] and rec["delay_s"] == pytest.approx(delay_s, abs=max(3 * rec["se_s"], 1e-3))
    assert rec["band_hz"] == [0.01, 0.05] and rec["lowpass_hz"] == pytest.approx(0.1)
    assert rec["band_rms_corrected_mgal"] < 0.5 * rec["band_rms_mgal"]
    assert any("band_delay" in w and f" ms {word} against the GNSS" in w for w in warnings)
    after = _refit(flights, lines)
    assert abs(after.t_stat) < 3                         # nothing left to take out
    for k, m in flights.items():                         # the change is the delay's, below 0.1 Hz
        d = m.z_mgal - before[k]
        ok = np.isfinite(d)
        assert np.nanstd(d[ok]) < 1e5 * 0.02 * 0.2      # |−d·ȧ| ≤ d · 0.15 m/s² · 2π/45 s⁻¹ · …
        assert np.nanstd(d[ok]) > 10.0


def test_no_delay_no_change_and_the_reason_said():
    flights, lines = _survey(0.0, seed=9)
    before = {k: m.z_mgal.copy() for k, m in flights.items()}
    warnings = []
    rec = check_band_delay(flights, lines, ProcessingParams(), warnings)
    assert not rec["applied"] and "standard errors" in rec["reason"] and abs(rec["t_stat"]) < 4
    for k, m in flights.items():
        np.testing.assert_array_equal(m.z_mgal, before[k])
    assert not warnings


def test_off_and_too_short():
    flights, lines = _survey(0.02)
    assert check_band_delay(flights, lines, ProcessingParams(band_delay_check=False), []) is None
    short = pd.DataFrame({"flight": ["F1"], "t_start": [1300.0], "t_end": [1400.0]})
    rec = check_band_delay(flights, short, ProcessingParams(), [])
    assert not rec["applied"] and "too few" in rec["reason"]


def test_flights_left_different_delays_are_put_right_each_apart():
    """The time offsets are applied per flight, so each can be left its own delay: F1 on time,
    F2 30 ms late.  The pooled delay (about half of F2's) would move F1 by what F2 needs; the
    flights disagree (Cochran's χ²), so F2 alone is put right and F1 is untouched."""
    flights, lines = _survey(0.0, seed=5, delay2_s=0.03)
    pooled = _refit(flights, lines)
    assert 0.005 < pooled.delay_s < 0.025 and abs(pooled.t_stat) > 4     # what one delay would take out
    before = {k: m.z_mgal.copy() for k, m in flights.items()}
    warnings = []
    rec = check_band_delay(flights, lines, ProcessingParams(), warnings)
    assert rec["applied"] and rec["per_flight"] and rec["heterogeneity"]["p_value"] < 1e-3
    assert rec["flights"]["F2"]["delay_s"] == pytest.approx(0.03, abs=max(3 * rec["flights"]["F2"]["se_s"], 1e-3))
    assert abs(rec["flights"]["F1"]["t_stat"]) < 4
    np.testing.assert_array_equal(flights["F1"].z_mgal, before["F1"])
    assert abs(_refit(flights, lines, only="F2").t_stat) < 3                 # nothing left on F2
    assert "F2 (+" in rec["reason"] and "F1 (" not in rec["reason"]
    assert any("disagree" in w for w in warnings)
    # flights that agree keep the one pooled delay (the case above), and the report says they agree
    flights, lines = _survey(0.02)
    rec = check_band_delay(flights, lines, ProcessingParams(), [])
    assert "per_flight" not in rec and rec["heterogeneity"]["p_value"] > 1e-3 and rec["heterogeneity"]["dof"] == 1
