"""The in-flight lag check applies a τ only where it makes z better in the band the smoother
works in (simulations with known truth; stage 1 only, no smoother).

Over 321 simulated surveys the τ-only calibration moved τ by more than 0.05 s on 10, every
time with survey.toml's τ the true one: it absorbs the difference between the records'
response (interval means, heights differentiated twice) and a first-order lag near the top
of its band.  On random layout 177 of ``benchmarks/bench_unseen.py --geometry`` (a GT-1A
with its true τ = 2.0 s declared, 2 Hz GNSS heights, 4.4 km up) it found 2.093 s, and with it
the estimate's error was 1.75x the FIR 100 s low-pass's (1.08x with τ = 2.0).  That τ raises
z's RMS at 0.02–0.05 Hz by 41 %; a real lag error lowers it (declared 2.0, true 2.15 s: −36 %).
"""

import numpy as np
import pytest

from app.io.survey import read_survey
from app.pipeline.parallel import thread_count
from app.pipeline.stages.measurement import check_lag, check_lag_with_search, each_flight, lag_band_check
from app.simulate import simulate_survey

LAYOUT_177 = dict(n_main=8, main_length_km=25.0, main_spacing_km=4.0, n_tie=0, n_flights=1, n_repeat=4,
                  speed_ms=112.0, height_m=4358.0, crs="EPSG:32657", normal_gravity="Helmert1901",
                  gnss_rate_hz=2.0, wind_ms=16.6, episode_rate_per_h=2.1, mountain_std_mgal=18.9,
                  plain_std_mgal=8.0, gnss_velocity=False, sigma_h_m=0.005, h_colored_m=0.03)


def test_in_flight_lag_that_worsens_z_is_not_applied(tmp_path):
    """Layout 177's flight has three short gravimeter holes; fitted across them the in-flight τ
    was 2.093 s.  Fitted away from them it is the true 2.0 (within lag_check_s), so nothing
    moves; and the τ the holes gave is still rejected by the band check (z's band RMS rises)."""
    survey_dir = simulate_survey("omolon-mini", tmp_path / "s", seed=177, **LAYOUT_177)
    survey = read_survey(survey_dir)
    assert survey.config.gravimeter.tau_s == 2.0                   # declared = true
    warnings = []
    tau, info = check_lag(survey, survey.config, warnings)
    est = float(np.median(info["estimated_tau_s"]))
    assert abs(est - 2.0) < 0.02 and tau is None and info["applied"] is False
    band = lag_band_check(list(survey.flights.values()), survey.config, 2.093)
    assert band["band_rms_estimated_mgal"] > 1.2 * band["band_rms_declared_mgal"]
    assert not any("gravimeter lag" in w for w in warnings)


def test_small_real_lag_error_is_still_applied(tmp_path):
    survey_dir = simulate_survey("tiny", tmp_path / "s", seed=7, tau_true_s=2.15)
    survey = read_survey(survey_dir)
    warnings = []
    tau, info = check_lag(survey, survey.config, warnings)
    assert info["applied"] and abs(tau - 2.15) < 0.02
    assert info["band_rms_improvement"] > 0.2
    assert any("gravimeter lag" in w for w in warnings)


def test_lag_error_below_lag_check_s_applied_when_the_band_confirms(tmp_path):
    """A lag error of 0.04 s (declared 2.04, true 2.0): below ``lag_check_s`` (0.05 s), once
    kept without a look; the band check now decides, and the true τ lowers z's band RMS."""
    survey_dir = simulate_survey("tiny", tmp_path / "s", seed=7, tau_true_s=2.0, tau_declared_s=2.04)
    survey = read_survey(survey_dir)
    assert survey.config.gravimeter.tau_s == 2.04
    warnings = []
    tau, info = check_lag(survey, survey.config, warnings)
    # tiny's one short flight holds too little motion in the band for the band fit to reach 5
    # standard errors (Δτ ≈ −0.04 ± 0.01 s): the wideband τ, confirmed by the band check
    assert not info["band_fit"]["applied"]
    assert info["applied"] and abs(tau - 2.0) < 0.015
    assert info["band_rms_improvement"] > 0.03
    # without the band fit, the same
    wide = survey.config.processing.model_copy(update={"lag_band_fit": False})
    tau_w, info_w = check_lag(survey, survey.config.model_copy(update={"processing": wide}), [])
    assert info_w["applied"] and "band_fit" not in info_w and tau_w == tau
    # the old rule (no band check below lag_check_s) kept the declared τ
    old = wide.model_copy(update={"lag_check_min_change_s": 0.05})
    tau_old, info_old = check_lag(survey, survey.config.model_copy(update={"processing": old}), [])
    assert tau_old is None and info_old["applied"] is False


PHUGOID = dict(phugoid_amp_m=7.0, phugoid_period_s=(30.0, 40.0), gnss_rate_hz=2.0, gnss_velocity=False,
               sigma_h_m=0.005, h_colored_m=0.03)


def test_band_fitted_lag_under_a_phugoid(tmp_path):
    """A 30–40 s phugoid of 7 m (0.2 m/s², 20 000 mGal in the band just above FIR's cutoff) and
    a GT-1A declared 2.07 s, true 2.0088 s: each 0.01 s of lag error leaves ~40 mGal of the
    aircraft's jerk in z where the anomaly is estimated.  The band fit (z regressed on ∂z/∂τ at
    0.02–0.05 Hz, iterated with the time offset re-fitted) finds τ within 2 ms and takes z's band
    RMS down by two thirds; with the declared τ true it moves nothing."""
    survey_dir = simulate_survey("tiny", tmp_path / "s", seed=7, tau_true_s=2.0088, tau_declared_s=2.07, **PHUGOID)
    survey = read_survey(survey_dir)
    warnings = []
    tau, info = check_lag(survey, survey.config, warnings)
    assert info["from_band_fit"] and info["applied"] and abs(tau - 2.0088) < 0.002, info
    first = info["iterations"][0]
    assert abs(first["dtau_s"]) > 10 * first["se_s"]
    assert info["band_rms_improvement"] > 0.5
    assert any("in the band where the anomaly is estimated" in w for w in warnings)

    survey_dir = simulate_survey("tiny", tmp_path / "t", seed=7, tau_true_s=2.0, tau_declared_s=2.0, **PHUGOID)
    survey = read_survey(survey_dir)
    tau, info = check_lag(survey, survey.config, [])
    assert tau is None and not info["band_fit"]["applied"]
    assert abs(info["band_fit"]["iterations"][0]["dtau_s"]) < 0.002


PLATFORM_10HZ = dict(gravimeter_model="AIRGrav", gravimeter_rate_hz=10.0, gravimeter_sampling="point",
                     tau_declared_s=0.0, time_offset_s=0.0, gravimeter_clock="aligned", gnss_rate_hz=1.0,
                     turbulence_spectrum="peaked", turbulence_peak_hz=0.6, turbulence_slopes=(3.0, 8.0),
                     turbulence_rms_ms2=(0.3, 0.4), sigma_vu_cms=0.2)


def test_offsets_are_not_read_as_a_lag_when_switched_off(tmp_path):
    survey_dir = simulate_survey("tiny", tmp_path / "s", seed=11, tau_true_s=0.1, **PLATFORM_10HZ)
    survey = read_survey(survey_dir, {"lag_from_time_offsets": False})
    tau, info = check_lag(survey, survey.config, [])
    assert tau is None and (info is None or "offset_as_lag" not in info)


def test_undeclared_lag_taken_for_a_time_offset_is_declared_as_a_lag(tmp_path):
    """A platform meter with an undeclared 0.1 s lag on 1 Hz GNSS: below 0.2 Hz, where the offset
    is fitted, a lag is a delay, so the time offset took it (−0.097 s here, −0.08 to −0.09 s on
    a generated survey) and the τ-only calibration, fitted after it, found none (−0.006 s).
    Read as a lag, the offset lowers z's band RMS (8 %: the lag's damping of the turbulence,
    averaged on the 1 s GNSS intervals, folds into the band), and τ ≈ 0.1 s is used.  (On 2 Hz
    GNSS the two agree within 0.1 % and the offset stays.)  On by default."""
    survey_dir = simulate_survey("tiny", tmp_path / "s", seed=11, tau_true_s=0.1, **PLATFORM_10HZ)
    survey = read_survey(survey_dir)
    warnings = []
    tau, info = check_lag(survey, survey.config, warnings)
    assert info["from_time_offsets"] and info["applied"], info
    assert abs(tau - 0.1) < 0.015 and info["band_rms_improvement"] > 0.05
    assert any("as a lag" in w for w in warnings)


def test_offsets_are_not_read_as_a_lag_when_the_gravimeter_is_slower_than_the_gnss(tmp_path, monkeypatch):
    """A 2 Hz point-sampled platform meter with the same undeclared 0.1 s lag on 10 Hz GNSS (5 GNSS
    steps per sample, by the stamps; the 10 Hz meter on 1 Hz GNSS is not slow): the offsets are
    not tried as a lag (on two generated surveys like it the lag, right as it was,
    made the estimate worse: z takes the slow record between its samples)."""
    from app.pipeline.stages.measurement import _slow_gravimeter

    slow = {**PLATFORM_10HZ, "gravimeter_rate_hz": 2.0, "gnss_rate_hz": 10.0}
    survey_dir = simulate_survey("tiny", tmp_path / "s", seed=11, tau_true_s=0.1, **slow)
    survey = read_survey(survey_dir)
    ratio = survey.config.processing.slow_gravimeter_min_ratio
    assert all(_slow_gravimeter(f, ratio) for f in survey.flights.values())
    tau, info = check_lag(survey, survey.config, [])
    assert not (info or {}).get("from_time_offsets") and "offset_as_lag" not in (info or {})
    fast = read_survey(simulate_survey("tiny", tmp_path / "f", seed=11, tau_true_s=0.1, **PLATFORM_10HZ))
    assert not any(_slow_gravimeter(f, ratio) for f in fast.flights.values())
    # without the rate rule the slow meter's offsets would be tried as a lag
    import app.pipeline.stages.measurement as ms

    monkeypatch.setattr(ms, "_slow_gravimeter", lambda flight, ratio: False)
    _, tried = check_lag(survey, survey.config, [])
    assert tried.get("from_time_offsets") or "offset_as_lag" in tried, tried


def test_a_real_shift_of_the_stamps_stays_an_offset(tmp_path):
    """The same meter with no lag but its stamps 0.1 s late: the offset is a shift, and as a
    lag it would damp the acceleration wrongly — the band check keeps it an offset."""
    survey_dir = simulate_survey("tiny", tmp_path / "s", seed=11, tau_true_s=0.0,
                                 **{**PLATFORM_10HZ, "time_offset_s": 0.1})
    survey = read_survey(survey_dir, {"lag_from_time_offsets": True})
    tau, info = check_lag(survey, survey.config, [])
    assert tau is None
    lag = info["offset_as_lag"]                 # tried (the offset looks like a lag) and refused
    assert not lag["applied"] and abs(lag["estimated_tau_s"][0] - 0.1) < 0.015, info
    assert lag["band_rms_improvement"] < -0.1   # as a lag, z's band RMS rises (+36 %)


def test_band_fit_confirms_a_small_wideband_lag_only_when_they_agree():
    """The rule of ``_band_confirms`` on the figures of the generated surveys it was measured on:
    9 (declared 1.59 s, wideband 1.568, band fit −0.0200 ± 0.0055 s: true 1.5695) is confirmed;
    32 (declared 0, wideband 0.039, band +0.0417 ± 0.0229: 1.8 standard errors; true 0), 55
    (wideband 0.020, band +0.0072 ± 0.0035: 3.8 standard errors apart; true 0) and a band fit the
    other way are not."""
    from app.config import ProcessingParams
    from app.pipeline.stages.measurement import _band_confirms

    p = ProcessingParams()

    def band(tau0, d, se):
        return {"declared_tau_s": tau0, "iterations": [{"tau_s": tau0, "dtau_s": d, "se_s": se}]}

    assert _band_confirms(band(1.59, -0.0200, 0.0055), 1.568, p)
    assert not _band_confirms(band(0.0, 0.0417, 0.0229), 0.039, p)
    assert not _band_confirms(band(0.0, 0.0072, 0.0035), 0.0204, p)
    assert not _band_confirms(band(1.59, +0.0200, 0.0055), 1.568, p)
    assert not _band_confirms(None, 1.568, p) and not _band_confirms(band(1.59, float("nan"), 0.01), 1.568, p)


def test_flights_lags_compared_on_one_scale(tmp_path, foreign_sim):
    """Generated survey 237 (independent generator): a 1 Hz interval-mean platform meter on 10 Hz
    GNSS heights, 3 flights, a 0.261 s lag that survey.toml does not declare.  Measured at τ = 0,
    two flights' time offsets took the lag for a shift of the stamps (≈ −0.25 s, applied) and
    their τ fits found almost nothing; the third flight's offset was not applied and its τ fit
    found the lag.  As they come the τ fits disagree by 0.26 s; each minus its applied offset,
    they agree within 0.02 s, and their median lies within 0.01 s of the truth.  Without this
    reading the band fit pools the three and stops half-way (0.225 s; the estimate was 1.36×
    FIR's error, 0.56× with this τ)."""
    fs = foreign_sim
    cfg = fs.draw_config(237)
    truth = cfg["tau_true_s"] + cfg["residual_lag_s"]
    survey_dir = fs.simulate(cfg, tmp_path / "s")
    survey = read_survey(survey_dir)
    warnings = []
    tau, info = check_lag(survey, survey.config, warnings)
    assert info["from_one_scale"] and info["applied"], info
    assert abs(tau - truth) < 0.01
    offsets = np.asarray(info["time_offsets_s"])
    assert np.any(offsets < -0.2) and np.any(offsets == 0.0)       # the case: some offsets took the lag
    assert np.ptp(info["estimated_tau_s"]) > 0.2 and np.ptp(info["flight_lags_s"]) < 0.05
    assert info["band_rms_improvement"] >= survey.config.processing.lag_one_scale_min_improvement
    assert any("once each one's time offset" in w for w in warnings)

    off = read_survey(survey_dir, {"lag_one_scale": False})
    tau_off, _ = check_lag(off, off.config, [])
    assert tau_off is None or abs(tau_off - truth) > 0.03


def test_a_real_shift_of_a_slow_meters_stamps_stays_an_offset(tmp_path):
    """A 2 Hz point-sampled meter on 10 Hz GNSS (slower than its GNSS, so the offsets-as-a-lag
    path does not run) with no lag and its stamps 0.1 s late: the offset is applied, and on one
    scale the flight's lag would be 0.1 s — but as a lag it leaves z's band RMS as it was, and
    the offset stays an offset."""
    slow = {**PLATFORM_10HZ, "gravimeter_rate_hz": 2.0, "gnss_rate_hz": 10.0, "time_offset_s": 0.1}
    survey_dir = simulate_survey("tiny", tmp_path / "s", seed=11, tau_true_s=0.0, **slow)
    survey = read_survey(survey_dir)
    tau, info = check_lag(survey, survey.config, [])
    assert tau is None
    one = info["one_scale"]                     # tried (an applied offset of 0.1 s) and refused
    assert not one["applied"] and abs(one["flight_lags_s"][0] - 0.1) < 0.01, one
    assert one["band_rms_improvement"] < survey.config.processing.lag_one_scale_min_improvement


def test_a_flight_that_cannot_be_measured_at_the_one_scale_lag_leaves_tau_alone(tmp_path, monkeypatch):
    """The one-scale lag's band check measures every flight again at the new τ; if one cannot be
    measured there (a hole its lag inversion cannot cross), stage 1 keeps survey.toml's τ and
    says why instead of stopping the run."""
    import app.pipeline.stages.measurement as ms

    slow = {**PLATFORM_10HZ, "gravimeter_rate_hz": 2.0, "gnss_rate_hz": 10.0, "time_offset_s": 0.1}
    survey = read_survey(simulate_survey("tiny", tmp_path / "s", seed=11, tau_true_s=0.0, **slow))

    def fails(*args, **kwargs):
        raise ValueError("flight F01: no airborne segment")

    monkeypatch.setattr(ms, "lag_band_check", fails)
    tau, info = check_lag(survey, survey.config, [])
    assert tau is None
    one = info["one_scale"]
    assert not one["applied"] and "could not be measured at τ = 0.100 s" in one["reason"], one


def test_a_lag_far_from_the_declared_one_is_found_by_the_band_minimum(tmp_path, monkeypatch):
    """A GT-1A (true τ = 2.0 s) declared 0 or 1 s: the in-flight checks, linear about the τ they
    start from and sharing the lag with the time offset, stop short (1.43 / 1.10 s on the sample
    survey); the search for the least RMS of z at 0.02–0.05 Hz finds the truth, beyond the first
    interval for 1 s (its minimum on the edge moves the interval on)."""
    for declared in (0.0, 1.0):
        survey = read_survey(simulate_survey("omolon-mini", tmp_path / f"s{declared:g}", seed=11,
                                             tau_declared_s=declared))
        assert survey.config.gravimeter.tau_s == declared
        first, _ = check_lag(survey, survey.config, [])
        assert first is not None and abs(first - 2.0) > 0.3, first       # found only in part
        warnings: list = []
        tau, info = check_lag_with_search(survey, survey.config, warnings)
        assert abs(tau - 2.0) < 0.03, (declared, tau)
        s = info["band_search"]
        assert s["applied"] and s["band_rms_mgal"] < 0.5 * s["band_rms_check_mgal"]
        assert any("is least at τ" in w for w in warnings), warnings
        if declared == 0.0:
            # the flights are measured on the line threads: another thread count, the same search
            monkeypatch.setenv("AEROGRAV_THREADS", "1" if thread_count() > 1 else "2")
            again = check_lag_with_search(survey, survey.config, [])
            monkeypatch.delenv("AEROGRAV_THREADS")
            assert again == (tau, info)


def test_each_flight_keeps_the_order_and_raises_as_the_loop_would(monkeypatch):
    """The flights measured on threads: results in the flights' order whatever finishes first,
    and the first failing flight's error (in order) raised, as the plain loop raises it."""
    import time

    monkeypatch.setenv("AEROGRAV_THREADS", "3")

    def slow_first(x):
        time.sleep(0.05 * (3 - x))          # the first item finishes last
        if x in (1, 2):
            raise ValueError(f"flight {x}")
        return 10 * x

    assert each_flight(lambda x: slow_first(x) if x == 0 else 10 * x, [0, 1, 2]) == [0, 10, 20]
    with pytest.raises(ValueError, match="flight 1"):
        each_flight(slow_first, [0, 1, 2])
