"""The stages run one by one from stored intermediate results give the one-shot run's
outputs exactly (app.pipeline.stages.storage), and the storage refuses what is not data."""

import json

import numpy as np
import pandas as pd
import pytest

from app.pipeline.stages import storage


def _tables_equal(a, b):
    for name in ("lines.parquet", "recognition.parquet"):
        pd.testing.assert_frame_equal(pd.read_parquet(a / name), pd.read_parquet(b / name), check_exact=True)
    pd.testing.assert_frame_equal(pd.read_csv(a / "crossovers.csv"), pd.read_csv(b / "crossovers.csv"),
                                  check_exact=True)
    assert json.loads((a / "identification.json").read_text()) == json.loads((b / "identification.json").read_text())
    import xarray as xr

    ga, gb = xr.open_dataset(a / "grid.nc"), xr.open_dataset(b / "grid.nc")
    np.testing.assert_array_equal(ga["dg"].values, gb["dg"].values)
    ga.close()
    gb.close()


def test_stages_from_stored_results_equal_the_one_shot_run(tmp_path, tiny_survey):
    from app.io.survey import read_survey
    from app.pipeline import runs
    from app.pipeline.process import process_survey
    from app.pipeline.stages.measurement import measure

    one = tmp_path / "one"
    rep_one = process_survey(tiny_survey, one)
    # identify, store, load in a fresh object graph, filter
    survey = read_survey(tiny_survey)
    idf = runs.run_identify(survey, runs.Tracker(None))
    runs.save_identified(idf, tmp_path / "store")
    loaded = runs.load_identified(tmp_path / "store")
    assert loaded is not idf and loaded.identifications.keys() == idf.identifications.keys()
    two = tmp_path / "two"
    rep_two = runs.run_filter(loaded, two, runs.Tracker(None))
    _tables_equal(one, two)
    # the noise family's crossover check is process_survey's (a second run, when due): not due here
    assert rep_one["noise_model"].pop("crossover_check")["applied"] is False
    for k in ("crossovers", "identification", "model_choice", "noise_model", "repeat_lines", "warnings"):
        assert json.loads(json.dumps(rep_one[k], default=float)) == json.loads(json.dumps(rep_two[k], default=float)), k
    # a single stage's result round-trips too (arrays, nested dataclasses, dicts, slices)
    meas = measure(survey)
    storage.save(meas, tmp_path / "meas")
    back = storage.load(tmp_path / "meas")
    for name, fm in meas.flights.items():
        np.testing.assert_array_equal(back.flights[name].z_mgal, fm.z_mgal)
        assert back.flights[name].time_offset == fm.time_offset
    assert back.base_ties == json.loads(json.dumps(meas.base_ties))


def test_storage_refuses_classes_outside_the_pipeline(tmp_path):
    from dataclasses import dataclass

    @dataclass
    class Foreign:
        x: int

    with pytest.raises(TypeError):
        storage.save(Foreign(1), tmp_path / "x")
    storage.save({"a": np.arange(3), "s": slice(1, 5), "t": (1, "b"), "f": float("nan")}, tmp_path / "ok")
    state = json.loads((tmp_path / "ok" / "state.json").read_text())
    state["value"] = {"__dataclass__": "subprocess:Popen", "fields": {}, "extra": {}}
    (tmp_path / "ok" / "state.json").write_text(json.dumps(state))
    with pytest.raises(ValueError, match="outside the allowed modules"):
        storage.load(tmp_path / "ok")


def test_static_segments_found_in_velocities_differenced_from_noisy_positions():
    """Parked 300 s, then a 60 s take-off roll to 60 m/s: 20 Hz positions with 2 cm noise,
    velocities differenced from them (0.6 m/s of noise per epoch, as a heights-only GNSS
    file gives).  The parking is found (within its 10 s trims), the roll is not static."""
    from app.pipeline.stages.measurement import static_segments

    rng = np.random.default_rng(7)
    dt = 0.05
    t = np.arange(0.0, 600.0, dt)
    speed = np.clip((t - 300.0) / 60.0, 0.0, 1.0) * 60.0           # m/s along east
    east = np.cumsum(speed) * dt + rng.normal(0.0, 0.02, t.size)
    north = rng.normal(0.0, 0.02, t.size)
    up = 200.0 + rng.normal(0.0, 0.02, t.size)
    ve, vn, vu = (np.gradient(x, dt) for x in (east, north, up))
    assert static_segments(t, ve, vn, vu, smooth_s=0.0) == []      # epoch by epoch: never still for 60 s
    segs = static_segments(t, ve, vn, vu)
    assert len(segs) == 1
    a, b = segs[0]
    assert t[a] == pytest.approx(10.0, abs=3.0) and 285.0 < t[b - 1] <= 300.0


def test_gnss_stamp_jitter_is_undone_but_a_drifting_receiver_clock_is_kept():
    """Heights on a cubic trajectory (the not-a-knot spline's derivative is then exact):
    stamps scattered by ±2 ms, uncorrelated, go back on the clock and vu derived from the heights
    is derived again there (= the trajectory's derivative); a ±0.5 ms sawtooth (a receiver clock
    that drifts and jumps 1 ms, stamping its true epochs) is kept as it is."""
    from app.pipeline.stages.measurement import dejitter_gnss

    rng = np.random.default_rng(4)
    t = 1000.0 + 0.5 * np.arange(2000)
    x = t - 1000.0

    def heights(tt):
        xx = tt - 1000.0
        return 500.0 + 0.5 * xx - 1e-4 * xx ** 2 + 1e-8 * xx ** 3

    stamps = t + rng.uniform(-0.002, 0.002, t.size)
    gn = pd.DataFrame({"time": stamps, "lat": 60.0, "lon": 20.0, "h": heights(t), "vu": np.nan})
    notes: list = []
    out, info = dejitter_gnss(gn, 1.0, True, notes)
    assert info["gnss_stamps_dejittered"] and abs(info["gnss_stamp_jitter_lag1"]) < 0.2
    # back on the clock: steps equal within 50 µs (they scattered by ±4 ms), the clock's phase,
    # averaged out of the scatter, within 0.5 ms
    assert np.ptp(np.diff(out["time"])) < 5e-5 and np.max(np.abs(out["time"] - t)) < 5e-4
    np.testing.assert_allclose(out["vu"], 0.5 - 2e-4 * x + 3e-8 * x ** 2, atol=2e-4)
    assert any("put back on the clock" in n for n in notes)
    c = ((t - t[0]) * 1e-5) % 1e-3 - 5e-4
    gn = pd.DataFrame({"time": t + c, "lat": 60.0, "lon": 20.0, "h": heights(t + c), "vu": 0.0})
    out, info = dejitter_gnss(gn, 1.0, True, [])
    assert not info["gnss_stamps_dejittered"] and info["gnss_stamp_jitter_lag1"] > 0.9
    assert out is gn


def test_a_declared_crs_far_from_the_survey_is_said():
    """Lines at 159° E on the equator: their own UTM zone (57) is silent, a CRS six zones west
    stretches distances by 24 % and a warning names it and the survey's zone."""
    from types import SimpleNamespace

    from app.pipeline.stages.lines import crs_warning

    lon = np.linspace(158.8, 159.2, 50)
    lines = [SimpleNamespace(lon_deg=lon, lat_deg=np.zeros(50))]
    assert crs_warning("EPSG:32657", lines) is None
    w = crs_warning("EPSG:32651", lines)
    assert w is not None and "+23." in w and "EPSG:32657" in w


def _flight_at(times, t0: float = 1000.0):
    """A 10 Hz GNSS table flying east at 100 m/s (60° N), its positions and heights taken at
    ``times``; heights on a cubic as above."""
    x = np.asarray(times) - t0
    lon = 20.0 + np.degrees(100.0 * x / (6_371_000.0 * np.cos(np.radians(60.0))))
    return pd.DataFrame({"time": times, "lat": 60.0, "lon": lon,
                         "h": 500.0 + 0.5 * x - 1e-4 * x ** 2 + 1e-8 * x ** 3, "vu": np.nan})


def test_stamps_scattering_past_the_jitter_bound_follow_the_positions():
    """±20 ms stamps at 10 Hz (20 % of a step, above the 5 % the stamps alone may scatter): where
    the positions stayed on the receiver's clock (they do not move with the stamps) the epochs go
    back on it — within 2 ms of the true clock, where they were 20 ms off; where the positions
    were truly taken at those irregular times, the stamps are kept as they are."""
    from app.core.epochs import positions_follow_stamps
    from app.pipeline.stages.measurement import dejitter_gnss

    rng = np.random.default_rng(11)
    t = 1000.0 + 0.1 * np.arange(6000)
    stamps = t + rng.uniform(-0.02, 0.02, t.size)
    on_clock = _flight_at(t).assign(time=stamps)          # a logger's stamps on the receiver's epochs
    assert abs(positions_follow_stamps(stamps, on_clock["lat"], on_clock["lon"])[0]) < 0.1
    notes: list = []
    out, info = dejitter_gnss(on_clock, 1.0, True, notes)
    assert info["gnss_stamps_dejittered"] and info["gnss_stamp_positions_corr"] < 0.1
    assert np.max(np.abs(out["time"] - t)) < 2e-3 and np.max(np.abs(stamps - t)) > 0.019
    assert any("do not move with them" in n for n in notes)
    irregular = _flight_at(stamps)                          # positions really taken at the stamps
    assert positions_follow_stamps(stamps, irregular["lat"], irregular["lon"])[0] > 0.95
    notes = []
    out, info = dejitter_gnss(irregular, 1.0, True, notes)
    assert not info["gnss_stamps_dejittered"] and out is irregular
    assert any("move with the stamps" in n for n in notes)
    parked = _flight_at(np.full(t.size, 1000.0)).assign(time=stamps)   # no motion: no verdict
    assert np.isnan(positions_follow_stamps(stamps, parked["lat"], parked["lon"])[0])
