"""A gravimeter sampled slower than the GNSS (1 Hz interval means beside 10 Hz GNSS): the aircraft's
acceleration cancelled at the gravimeter's own sample boundaries (simulations with known truth,
stage 1 only).

Plain interval means interpolate the gravimeter's integral inside each 1 s sample, where only the
GNSS knows how the aircraft moved: with heavy turbulence that interpolation error is the largest
error in z.  Cancelling the motion at the boundaries removes it but samples the GNSS velocity error
at 1 Hz, folding its high frequencies into the anomaly band — which wins depends on the GNSS, so the
measurement stage compares z's band RMS on the lines and keeps the quieter one.
"""

import numpy as np
import pandas as pd
import pytest

from app.core.baselines import fir_lowpass_mgal
from app.io.survey import read_survey
from app.pipeline.stages import measurement as ms


def _survey(tmp_path_factory, name, **kw):
    from app.simulate import simulate_survey

    kw = {"main_length_km": 60.0, **kw}
    return simulate_survey("tiny", tmp_path_factory.mktemp(name) / "survey", seed=5,
                           gravimeter_model="AIRGrav", gravimeter_rate_hz=1.0, gravimeter_sampling="mean",
                           tau_true_s=0.0, tau_declared_s=0.0, time_offset_s=0.0, gravimeter_clock="aligned",
                           gnss_rate_hz=10.0, turbulence_spectrum="peaked",
                           turbulence_slopes=(3.0, 8.0), turbulence_rms_ms2=(0.3, 0.5), **kw)


def _errors_below(path, period_s: float = 100.0):
    """RMS (mGal) of the FIR ``period_s`` low-pass of z − truth (the FIR baseline's error, a period
    in from the line ends) on the lines, for the plain and the compensated means, and the stage's
    choice per flight."""
    s = read_survey(path)
    truth = pd.read_parquet(path / "truth" / "lines.parquet")
    out = {"plain": [], "compensated": [], "applied": []}
    measured = ms.measure(s).flights
    for name, flight in s.flights.items():
        m = measured[name]
        rec = m.time_offset["motion_compensation"]
        out["applied"].append(rec["applied"])
        tr = truth[truth["flight"] == name]
        idx = np.searchsorted(m.t_s, tr["time"].to_numpy(float))
        t, vu = m.t_s, m.vu_ms
        series = ms.gm.integrate_samples(flight.gravimeter["time"].to_numpy(float),
                                         flight.gravimeter["f_z"].to_numpy(float))
        off = m.time_offset.get("offset_s", 0.0) if m.time_offset.get("applied") else 0.0
        for key, fbar in (("plain", ms.gm.interval_means(series, t, time_offset_s=off)),
                          ("compensated", ms.gm.motion_compensated_means(series, t, vu, time_offset_s=off))):
            z = ms.anomaly_measurement_mgal(fbar, t, vu, m.gamma_mgal, m.eotvos_mgal)[idx]
            e = pd.Series(z - tr["dg_true_mgal"].to_numpy()).groupby(tr["line"].to_numpy())
            dt = float(np.median(np.diff(t)))
            k = int(round(period_s / dt))
            for _, x in e:
                if x.size < 3 * k:
                    continue
                lo = fir_lowpass_mgal(x.to_numpy(), dt, period_s)[k:-k]
                out[key].append(lo[np.isfinite(lo)] - np.nanmean(lo))
    return {k: (float(np.sqrt(np.mean(np.concatenate(v) ** 2))) if k != "applied" else v) for k, v in out.items()}


def test_compensation_used_where_it_removes_the_motion(tmp_path_factory):
    # carrier-phase velocities (0.5 mm/s at 10 Hz) and turbulence up to 1 Hz: sampled at 1 Hz
    # the velocities add less than the motion inside a second
    r = _errors_below(_survey(tmp_path_factory, "velocity", sigma_vu_cms=0.05, turbulence_peak_hz=0.6))
    # the motion inside a second dominates the plain means' error; the compensated are better
    # in the anomaly band and the stage chose them on every flight
    assert r["compensated"] < 0.7 * r["plain"], r
    assert all(r["applied"]), r          # 4 lines of ~1000 s: enough to compare the two (≥ 1000 s)


@pytest.mark.parametrize("gnss", [dict(sigma_vu_cms=1.3),
                                  dict(gnss_velocity=False, sigma_h_m=0.007, h_colored_m=0.025, h_colored_tau_s=60.0)],
                         ids=["velocity-13mm", "heights"])
def test_compensation_refused_where_it_folds_the_gnss_error_in(tmp_path_factory, gnss):
    # velocities with 1.3 cm/s of white noise at 10 Hz, or heights only (the velocity derived from
    # them is blue noise up to 5 Hz): sampled at 1 Hz, their error outweighs the motion's
    r = _errors_below(_survey(tmp_path_factory, "gnss", turbulence_peak_hz=0.4, **gnss))
    assert r["compensated"] > r["plain"], r
    assert not any(r["applied"]), r


@pytest.mark.parametrize("gnss,better", [(dict(sigma_vu_cms=0.05, turbulence_peak_hz=0.6), "compensated"),
                                         (dict(gnss_velocity=False, sigma_h_m=0.007, h_colored_m=0.025,
                                               h_colored_tau_s=60.0, turbulence_peak_hz=0.4), "plain")],
                         ids=["velocity", "heights"])
def test_short_lines_still_choose_by_the_data(tmp_path_factory, gnss, better):
    # four 25 km lines (250 s): no stretch of 300 s for the usual comparison's 100 s edges, so it
    # used to keep the plain means whatever they cost; the short-line comparison (50 s edges, over
    # >= 500 s of lines) takes the compensated means only where they are clearly quieter
    path = _survey(tmp_path_factory, "short", **{**gnss, "main_length_km": 25.0})
    r = _errors_below(path, period_s=30.0)    # the error against the truth below 30 s periods
    s = read_survey(path)
    rec = ms.measure(s).flights["F01"].time_offset["motion_compensation"]
    assert rec["n_epochs"] == 0, rec          # the usual comparison had nothing to go on
    assert rec["survey_short_lines"]["used"] == (better == "compensated"), rec
    worse = "plain" if better == "compensated" else "compensated"
    assert r[better] < r[worse], r
    assert all(r["applied"]) == (better == "compensated"), r
