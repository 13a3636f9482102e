"""The gravimeter's clock tracked against the GNSS's along a flight (stage 1,
app.pipeline.stages.measurement.gravimeter_clock): a logger clock running 40 ppm fast and
set 0.3 s forward halfway misaligns z by the aircraft's jerk, which one time offset per
flight cannot mend.  Simulation with known truth: the drift and the jump are found and sized,
the stamps re-timed and the anomaly is the clean survey's; the clean survey's clock is left
alone."""

import shutil

import numpy as np
import pandas as pd

from tests.pipeline.test_gaps import _rms

DRIFT = 40e-6      # the logger's clock runs 40 ppm fast
JUMP_S = 0.3       # and is set 0.3 s forward halfway


def test_a_drifting_clock_set_forward_in_flight_is_retimed(tmp_path):
    from app.pipeline.process import process_survey
    from app.simulate import simulate_survey

    survey = simulate_survey("omolon-mini", tmp_path / "s", seed=8, n_main=6, n_tie=2, n_repeat=0,
                             n_flights=1, sigma_vu_cms=0.5)
    clean_rep = process_survey(survey, tmp_path / "clean")
    clock = clean_rep["time_offsets"]["F01"]["clock"]
    assert not clock["applied"] and len(clock["windows"]) >= 5 and clock["reason"] == "one offset fits every window"

    bad = tmp_path / "b"
    shutil.copytree(survey, bad)
    path = next((bad / "flights" / "F01").glob("gravimeter.csv*"))
    d = pd.read_csv(path)
    t = d["time"].to_numpy(float)
    mid = t[0] + 0.5 * (t[-1] - t[0])
    d["time"] = np.round(t + DRIFT * (t - t[0]) + np.where(t > mid, JUMP_S, 0.0), 6)
    d.to_csv(path, index=False)
    rep = process_survey(bad, tmp_path / "bad")
    clock = rep["time_offsets"]["F01"]["clock"]
    assert clock["applied"], clock
    # the offset (GNSS − stamp) drifts by −40 ppm and steps by −0.3 s at the record's gap
    assert abs(clock["drift_ppm"] + 40.0) < 4.0
    (step,) = clock["steps"]
    assert abs(step["size_s"] + JUMP_S) < 0.01 and abs(step["time_s"] - mid) < 1.0
    assert any("clock runs +" in w and "ppm fast" in w and "s forward at" in w for w in rep["warnings"])
    clean, fixed = _rms(tmp_path / "clean", survey), _rms(tmp_path / "bad", survey)
    assert fixed < 1.05 * clean, (fixed, clean)

    # the same record with the tracking off: one offset for the flight, far from the clean anomaly
    process_survey(bad, tmp_path / "off", {"clock_track": False})
    assert _rms(tmp_path / "off", survey) > 1.3 * clean
