"""Passes of one repeat track must lie on one track: two parallel lines 2 km apart marked as one
track gave a repeat-line "internal accuracy" of 6 mGal with no word (found by fuzzing lines.csv).
The report now gives each track's across-track spread and warns above 0.5 km."""

import numpy as np
import pandas as pd

from app.pipeline.stages.outputs import REPEAT_MAX_SPREAD_KM, repeat_accuracy, repeat_track_warnings


def _pass(line, track, northing_km, reverse=False):
    e = np.linspace(0.0, 30.0, 301)
    e = e[::-1] if reverse else e
    dg = 10.0 * np.sin(e / 4.0) + 0.3 * northing_km * 10.0     # the anomaly changes across the track
    return pd.DataFrame({"line": line, "kind": "repeat", "track": track, "easting_km": e,
                         "northing_km": np.full(e.size, northing_km), "dg_mgal": dg, "dg_fir_mgal": dg,
                         "dg_stationary_mgal": dg})


def test_passes_apart_across_the_track_are_warned():
    table = pd.concat([_pass("R1a", "R1", 0.0), _pass("R1b", "R1", 2.0, True),
                       _pass("R2a", "R2", 5.0), _pass("R2b", "R2", 5.05, True), _pass("R2c", "R2", 4.98)],
                      ignore_index=True)
    rep = repeat_accuracy(table)
    assert abs(rep["R1"]["across_track_spread_km"] - 2.0) < 1e-9
    assert abs(rep["R2"]["across_track_spread_km"] - 0.07) < 1e-9
    assert rep["R1"]["internal_accuracy_mgal"]["dg_mgal"] > 1.0      # what it compared: different ground
    (w,) = repeat_track_warnings(rep)
    assert w.startswith("repeat track R1: its 2 passes lie 2.00 km apart") and f"{REPEAT_MAX_SPREAD_KM} km" in w


def test_passes_apart_are_left_out_of_the_noise_fit_and_the_std_sizing():
    """The same passes used as repeats: 0.05 km apart they feed the noise fit's pass
    differences and size the std (the level a decade low, so the passes' error is clearly above
    the posterior's); 2 km apart the track is left out of both (their scatter holds the
    anomaly's change across the track, not the noise) and the std keeps the level spread."""
    from types import SimpleNamespace

    from app.core.smoother import kalman_smooth
    from app.pipeline.stages.filtering import Filtered, PreparedLine
    from app.pipeline.stages.noise import repeat_tracks

    dt, T, R, speed, q = 0.5, 3000, 1.0, 60.0, 2e-5
    rng = np.random.default_rng(0)
    dg = np.cumsum(np.cumsum(rng.normal(size=T) * np.sqrt(q))) + 30.0
    s_km = np.arange(T) * dt * speed / 1000.0
    zs = []
    for k in range(4):
        o = slice(None) if k % 2 == 0 else slice(None, None, -1)
        r = rng.normal(size=T + 1) * np.sqrt(R)
        zs.append(dg[o] - 1000.0 * (r[1:] - r[:-1]) / dt)
    sms = [kalman_smooth(z, np.full(T, q / 10), np.full(T, R), dt, m=2) for z in zs]
    table = pd.DataFrame({"dg_mgal": np.concatenate([s.dg_mgal for s in sms]),
                          "dg_std_mgal": np.concatenate([s.dg_std_mgal for s in sms])})
    out = {}
    for apart_km in (0.05, 2.0):
        lines = [SimpleNamespace(kind="repeat", track="T1", t_s=np.arange(T) * dt + 10_000.0 * k,
                                 easting_km=500.0 + s_km[slice(None) if k % 2 == 0 else slice(None, None, -1)],
                                 northing_km=np.full(T, 7000.0 + apart_km * (k % 2)), speed_ms=speed)
                 for k in range(4)]
        out[apart_km] = len(repeat_tracks(lines))
        prepared = [PreparedLine(ln, np.zeros(T, int), np.zeros(T, int), z, slice(0, T), None, None, None)
                    for ln, z in zip(lines, zs)]
        f = Filtered(table.copy(), np.array([q / 10]), None, 1.0, prepared=prepared, r_lines=[np.full(T, R)] * 4,
                     n_r=1)
        f.level_spread_std(dt, 2, "bf", None, 10.0, repeat_min_samples=8.0, fir_period_s=100.0)
        out[f"track {apart_km}"] = f.std_repeat_tracks["T1"]
        out[f"factor {apart_km}"] = f.std_level_factor
    assert out[0.05] == 1 and out[2.0] == 0
    assert out["track 0.05"]["scale"] > 1.2 and out["factor 0.05"] is None
    far = out["track 2.0"]
    assert far["scale"] is None and abs(far["across_track_spread_km"] - 2.0) < 1e-9 and "not repeats" in far["reason"]
    assert out["factor 2.0"] == 10.0


def test_repeat_lines_without_a_track_are_compared_by_their_positions(tmp_path):
    """The 4-pass test line with lines.csv's track column left empty (a user's conversion that
    marks the passes kind repeat and nothing more): they were compared with no other pass — no
    repeat-line accuracy, no repeat checks or blend in stage 9.  Stage 2 now groups them by their
    positions as track auto-1 and says so; the report then gives the passes' accuracy and the
    repeat blend's evidence."""
    import json

    from app.pipeline.process import process_survey
    from app.simulate import simulate_survey

    survey = simulate_survey("testline-2hz", tmp_path / "survey", seed=1)
    lines = pd.read_csv(survey / "lines.csv")
    passes = sorted(lines.loc[lines["kind"] == "repeat", "line"].astype(str))
    assert len(passes) == 4 and lines["track"].notna().all()
    lines.drop(columns=["track"]).to_csv(survey / "lines.csv", index=False)
    report = process_survey(survey, tmp_path / "out")
    assert report["repeat_tracks_inferred"] == {"auto-1": passes}
    assert any("compared as track auto-1" in w for w in report["warnings"])
    rep = json.loads((tmp_path / "out" / "report.json").read_text())["repeat_lines"]
    assert list(rep) == ["auto-1"] and rep["auto-1"]["repeats"] == 4
    assert rep["auto-1"]["internal_accuracy_mgal"]["dg_mgal"] < rep["auto-1"]["internal_accuracy_mgal"]["dg_fir_mgal"]
    assert report["model_choice"]["repeat_blend"]["passes"] == 4
    out = pd.read_parquet(tmp_path / "out" / "lines.parquet", columns=["line", "kind"])
    assert set(out.loc[out["kind"] == "repeat", "line"].astype(str)) == set(passes)
