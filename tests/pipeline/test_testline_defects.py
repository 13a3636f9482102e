"""The 4-pass test line (simulation with known truth: ``testline-2hz``, one 40 km line flown
four times, a 2 Hz platform gravimeter, 0.4 m/s² turbulence, GNSS heights only) with a defect
real records have: the gravimeter's stamps scattered by ±5 ms about its uniform clock (a
logging computer's time).

The stamps are put back on the clock (``dejitter_times_s``), but what is left changed the
noise spectrum enough that the fit chose a coloured velocity error, whose flat acceleration
noise, carried down into the anomaly band, flattened the estimate: 0.53 of the truth's
along-line variance, 1.4x the FIR 100 s error, and nothing said so (the flattening check
used the same over-stated FIR noise).  The passes' FIR differences show 1.7 mGal of FIR noise
where that model predicted 3.0: the family check falls back on velocity + height, and the
issue's acceptance for the test line holds again — RMS and pass-to-pass repeatability at most
FIR's, along-line variance at least 0.8 of the truth's.
"""

import json

import numpy as np
import pandas as pd

from app.pipeline.evaluate import merge_truth
from app.pipeline.process import process_survey


def _jitter_gravimeter_stamps(survey, jitter_s: float, seed: int = 7) -> None:
    rng = np.random.default_rng(seed)
    for f in sorted((survey / "flights").glob("*/gravimeter.csv")):
        g = pd.read_csv(f)
        g["time"] = g["time"] + rng.uniform(-jitter_s, jitter_s, len(g))
        g.to_csv(f, index=False, float_format="%.10g")


def test_testline_with_stamp_jitter_is_not_flattened(tmp_path):
    from app.simulate import simulate_survey

    survey = simulate_survey("testline-2hz", tmp_path / "survey", seed=1)
    _jitter_gravimeter_stamps(survey, 0.005)
    out = tmp_path / "out"
    report = process_survey(survey, out)
    # Whether the fit itself lands on the coloured velocity error is a close call of its
    # optimiser (numpy 2.4 / scipy 1.17 find the coloured velocity's φ near 0, nested in
    # velocity + height, which wins outright); where it does, the family check must replace it.
    fc = report["noise_model"].get("family_check")
    if fc is not None:
        assert fc["applied"] and fc["predicted_ms_mgal2"] > fc["bound_mgal2"]
    assert report["noise_model"]["family"] == "velocity + height"

    m = merge_truth(pd.read_parquet(out / "lines.parquet"), pd.read_parquet(survey / "truth" / "lines.parquet"))
    err = {c: m[c] - m["dg_true_mgal"] for c in ("dg_mgal", "dg_fir_mgal")}
    rms = {c: float(np.sqrt(np.mean((e - e.groupby(m["line"]).transform("mean")) ** 2))) for c, e in err.items()}
    assert rms["dg_mgal"] <= rms["dg_fir_mgal"]
    est = m["dg_mgal"] - m.groupby("line")["dg_mgal"].transform("mean")
    true = m["dg_true_mgal"] - m.groupby("line")["dg_true_mgal"].transform("mean")
    assert np.var(est) >= 0.8 * np.var(true)
    rep = json.loads((out / "report.json").read_text())["repeat_lines"]
    acc = next(iter(rep.values()))["internal_accuracy_mgal"]
    assert acc["dg_mgal"] <= acc["dg_fir_mgal"]
    # no crossovers: the passes judged the estimate against FIR (stage 9 step 4b), all four
    rb = report["model_choice"]["repeat_blend"]
    assert rb["passes"] == 4 and 0.0 <= rb["weight_fir"] <= 1.0 and "crossovers" in report["model_choice"]["fir_guard"]["reason"]
    # against the other passes smoothed at 300 x Q(t) (the default reference)
    assert rb["reference"] == "estimate at 300 x Q(t)" and rb["reference_q_factor"] == 300


def test_testline_with_a_missing_gnss_epoch_and_gravimeter_sample(tmp_path):
    """GNSS stamps scattered by ±2 ms about the receiver's clock (a logger's time), one GNSS
    epoch and one gravimeter sample missing inside lines (both allowed by the default
    ``max_gap_s`` at 2 Hz).  The scattered stamps alone took the lines from 1.47 to 3.03 mGal
    (FIR 1.92 → 3.45, 2σ coverage 0.89): they are put back on the clock.  Before: the interval over the missing GNSS epoch was left
    out of z and the FIR 100 s low-pass renormalised across it, missing that sample's share of
    the aircraft's accelerations (±10⁴ mGal): 22.7 mGal RMS on the lines; the missing
    gravimeter sample did the same (37.6 mGal), and the model choice, comparing with the broken
    FIR, put it into dg.  Now the GNSS epoch is put back on the receiver's clock (spline) and
    FIR is left out where the gravimeter's missing sample can move it by more than 1 mGal."""
    from app.simulate import simulate_survey

    survey = simulate_survey("testline-2hz", tmp_path / "survey", seed=1)
    rng = np.random.default_rng(11)
    for name, t0 in (("gnss", 13100.0), ("gravimeter", 14300.0)):
        path = survey / "flights" / "F01" / f"{name}.csv"
        d = pd.read_csv(path)
        d = d.drop(index=int((d["time"] - t0).abs().idxmin()))
        if name == "gnss":
            d["time"] = d["time"] + rng.uniform(-0.002, 0.002, len(d))
        d.to_csv(path, index=False, float_format="%.10g")
    out = tmp_path / "out"
    report = process_survey(survey, out)
    assert report["gnss_filled_epochs"] == {"F01": 1}
    assert report["time_offsets"]["F01"]["gnss_stamps_dejittered"]
    assert any("FIR 100 s left out" in w for w in report["warnings"])
    lines = pd.read_parquet(out / "lines.parquet")
    # the noise fit's bridge, with its limit: the gravimeter's hole (one missing sample, as z's
    # epochs) is bridged exactly when the flight's limit allows it.  Since the undeclared 0.23 s
    # lag is taken (lag_from_time_offsets) the de-lagged z is less predictable from the GNSS
    # acceleration and the limit falls below the hole (3 against 31 epochs without the lag)
    hb = report["noise_model"]["holes_bridged"]["F01"]
    bad = lines["z_mgal"].isna().to_numpy()
    assert 0 < bad.sum() <= 20
    assert hb["epochs_bridged"] == (bad.sum() if bad.sum() <= hb["max_hole_epochs"] else 0)
    near = (lines["time"] > 14300.0 - 60) & (lines["time"] < 14300.0 + 60)
    assert lines.loc[near, "dg_fir_mgal"].isna().all() and lines["dg_fir_mgal"].notna().mean() > 0.5
    assert lines["dg_mgal"].notna().all()
    m = merge_truth(lines, pd.read_parquet(survey / "truth" / "lines.parquet"))
    e = m["dg_mgal"] - m["dg_true_mgal"]
    rms = float(np.sqrt(np.mean((e - e.groupby(m["line"]).transform("mean")) ** 2)))
    ef = (m["dg_fir_mgal"] - m["dg_true_mgal"]).dropna()
    rms_fir = float(np.sqrt(np.mean((ef - ef.groupby(m["line"]).transform("mean")) ** 2)))
    assert rms < 2.5 and rms <= 1.05 * rms_fir, (rms, rms_fir)      # gap-free: 1.47 and 1.92


def test_testline_std_covers_the_error_the_passes_share(tmp_path):
    """Seed 3 of the test line: the four passes share about 1.3 mGal of error (the anomaly's
    smoothing, the same on every pass), which their scatter cannot show.  Sizing the std by the
    passes (the repeat-track rule) covered |error| < 2σ on 0.75 of the epochs against truth;
    where the shared part measured from the passes is lost in their noise the track keeps the
    levels' spread (``std_repeat_tracks[...].scale`` null, with the reason) and covers ≥ 0.85."""
    from app.simulate import simulate_survey

    survey = simulate_survey("testline-2hz", tmp_path / "survey", seed=3)
    out = tmp_path / "out"
    report = process_survey(survey, out)
    tracks = report["level_refinement"]["std_repeat_tracks"]
    (fig,) = tracks.values()
    assert fig["scale"] is None and "lost in the passes' noise" in fig["reason"]
    m = merge_truth(pd.read_parquet(out / "lines.parquet"), pd.read_parquet(survey / "truth" / "lines.parquet"))
    err = (m["dg_mgal"] - m["dg_true_mgal"]).abs()
    inside = float(np.mean(err < 2.0 * m["dg_std_mgal"]))
    assert inside >= 0.85, inside
    # and the std is not so wide that it says nothing: the error reaches past 1σ somewhere
    assert float(np.mean(err < m["dg_std_mgal"])) < 0.95
