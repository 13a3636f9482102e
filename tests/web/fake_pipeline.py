"""TEST FIXTURE ONLY: a stand-in for ``app.pipeline.process.process_survey``.

It validates the survey with the real ``read_survey`` and writes SPEC §5-shaped
outputs quickly and deterministically, reporting progress and EM iterations like
the real pipeline.  Used for the web tests that exercise job mechanics (kill,
cancel, concurrency, restart, Dask) where the science does not matter.  The delay
between progress reports comes from ``AEROGRAV_FAKE_DELAY_S`` (default 0.05 s).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd

N_STATES = 2


def _motion_compensation(i: int) -> dict:
    """Flight ``i``'s ``time_offsets.motion_compensation``: a 1 Hz gravimeter beside 10 Hz GNSS, the
    first flight's motion cancelled.  With ``AEROGRAV_FAKE_SHORT_LINES`` set, the lines were too
    short for the usual comparison (no figures) and the short-line one decided."""
    rec = {"applied": i == 0, "gravimeter_step_s": 1.0, "gnss_step_s": 0.1, "band_hz": [0.01, 0.02],
           "band_rms_plain_mgal": 16.8, "band_rms_compensated_mgal": 11.9 if i == 0 else 17.9,
           "n_epochs": 4000, "reason": "…"}
    if os.environ.get("AEROGRAV_FAKE_SHORT_LINES"):
        rec.update({"band_rms_plain_mgal": None, "band_rms_compensated_mgal": None, "n_epochs": 0,
                    "short_lines": {"edge_s": 50.0, "band_rms_plain_mgal": 31.8,
                                    "band_rms_compensated_mgal": 12.0 if i == 0 else 35.0, "n_epochs": 7840},
                    "survey_short_lines": {"band_rms_plain_mgal": 31.8, "band_rms_compensated_mgal": 12.0,
                                           "used": True}})
    return rec


def fake_report(df: pd.DataFrame, base_gravity_mgal: float | None = None, crs: str = "EPSG:32657") -> dict:
    """A report.json shaped like the real pipeline's (app.pipeline.process._report and what
    process_survey adds), with the decisions an analyst must see: no absolute base tie (unless
    ``base_gravity_mgal``), leveling rejected by the F-test, repeat-line accuracy where the adaptive
    estimate is the least repeatable, plus a ``model_choice`` and a section the browser does not
    know (shown generically)."""
    flights = sorted(df["flight"].astype(str).unique())
    warnings = [f"flight {flights[0]}: 3 epochs of z (0.019 %) repaired as spikes (> 6 local robust std from "
                "the neighbours' mean)"]
    if base_gravity_mgal is None:
        warnings.append("no absolute base tie (no base_gravity_mgal in survey.toml): the level of dg carries the "
                        "gravimeter's reading error (scale × g, easily 100+ mGal); differences along and between "
                        "lines are reliable, absolute values are not")
    return {
        "survey": "fake", "crs": crs, "fake": True,
        "counts": {"flights": len(flights), "lines": int(df["line"].nunique()), "epochs": int(len(df)),
                   "decimated_points": int(len(df) // 10), "crossovers": 1},
        "time_offsets": {f: {"offset_s": -0.0503, "correlation": 0.9957, "applied": i == 0, "estimated": True,
                             "se_s": 0.0003, "residual_reduction": 0.70 if i == 0 else 0.004,
                             "band_hz": [0.01, 0.4],
                             "reason": "significant and improves the fit" if i == 0 else
                             "improves the fit by less than 1 %",
                             # the stamps: the first flight's scattered like a logger's, the others a drifting clock
                             "gravimeter_stamp_jitter_ms": 0.0, "gnss_stamp_jitter_ms": 1.9 if i == 0 else 0.74,
                             "gnss_stamps_dejittered": i == 0, "gnss_stamp_jitter_lag1": -0.03 if i == 0 else 0.97,
                             # a 1 Hz gravimeter beside 10 Hz GNSS: the first flight's motion cancelled
                             "motion_compensation": _motion_compensation(i),
                             # the gravimeter's clock (white-30's figures): the first flight's logger ran 18.6
                             # ppm fast and was set 0.2 s forward, re-timed; the others kept one offset
                             "clock": ({"applied": True, "drift_ppm": -18.6, "residual_reduction": 0.96,
                                        "steps": [{"time_s": 13880.65, "size_s": -0.197, "gap_s": 0.255}],
                                        "windows": [{"t_s": 12000.0 + 300 * k} for k in range(14)]} if i == 0 else
                                       {"applied": False, "reason": "one offset fits every window",
                                        "windows": [{"t_s": 12000.0 + 300 * k} for k in range(12)]}),
                             # a 2 Hz platform's decimation filter read from the data (seed-20 figures)
                             "response_width": {"estimated": True, "c_s2": 0.0136 + 0.0001 * i, "se_s2": 0.00011,
                                                "band_hz": [0.01, 0.8], "residual_reduction": 0.651,
                                                "applied": True, "reason": "significant and improves the fit",
                                                "c_applied_s2": 0.0136 + 0.0001 * i}}
                         for i, f in enumerate(flights)},
        "response_width": {"c_s2": 0.01357, "se_s2": 6e-05, "residual_reduction": 0.728, "applied": True,
                           "flights": len(flights),
                           "reason": f"pooled over {len(flights)} flight(s): c = 0.0136 ± 6e-05 s², removing 72.8 % "
                                     "of the residual"},
        "gnss_filled_epochs": {f: (2 if i == 0 else 0) for i, f in enumerate(flights)},
        "gravimeter_filled_samples": {f: (7 if i == 0 else 0) for i, f in enumerate(flights)},
        "spike_repair": {f: {"threshold": 6.0, "flagged": 3, "epochs": int((df["flight"] == f).sum()),
                             "applied": True, "fraction": 0.00019,
                             # the last flight as a heights-only one: flags removed as height outliers
                             **({"repair": "height outliers", "height_outliers": [
                                 {"time": 1234.5, "kind": "spike", "size_m": 0.2},
                                 {"time": 1300.0, "kind": "step", "size_m": -0.05}]} if i == len(flights) - 1 else {})}
                         for i, f in enumerate(flights)},
        "crossovers": {"degree": 1, "per_flight": True, "n_crossovers": 1, "rms_before_mgal": 1.2,
                       "n_drift_parameters": 4, "p_value": 0.004,
                       "cross_validation": {"rms_before_mgal": 1.2, "rms_cv_mgal": 1.31, "p_value": 0.83,
                                            "n_folds": 2},
                       "status": "not leveled: the drift does not predict held-out lines' crossovers "
                                 "significantly (leave-one-line-out RMS 1.31 mGal against 1.2 without "
                                 "leveling, p = 0.83, needs < 0.01)",
                       "rms_after_mgal": 1.2, "rms_after_if_leveled_mgal": 0.1,
                       "std_check": {"n": 1, "rms_ratio": 0.57, "factor": 1.0},
                       # (only a leveled survey has it; here to show how the page renders it)
                       "common_level": {"std_mgal": 2.5, "spread_mgal": 4.33, "n_units": 3, "n_crossovers": 12,
                                        "offsets_mgal": {"F01": 3.0, "F02": -1.0, "F03": -2.0}, "applied": True},
                       # (only a survey without crossovers has it; here to show how the page renders it)
                       "repeat_tracks": {"R1": {"passes": ["R1-1", "R1-2", "R1-3"], "status": "leveled", "p_value": 0.0021,
                                                "degree": 1, "block_km": 3.0, "n_blocks": 13, "n_parameters": 3,
                                                "rms_before_mgal": 1.16, "rms_after_mgal": 0.62,
                                                "offsets_mgal": {"R1-1": 0.4, "R1-2": -0.1, "R1-3": -0.3},
                                                "drift_mgal_per_h": {"F01": [1.5]},
                                                "mean_correction_mgal": {"R1-1": 0.81, "R1-2": -0.12, "R1-3": -0.69}}}},
        "identification": {"Q_mgal2": [0.041, 0.353], "R_cm2s2": [1.679], "transition": [[0.98, 0.02], [0.03, 0.97]],
                           # a level its EM emptied, filtered with its value of an earlier iteration
                           "level_support": {"Q_mgal2": [0.041, 0.353], "share_em": [0.99, 0.01],
                                             "share_map": [0.46, 0.54], "map_from_m": 1, "em_converged": False,
                                             "unsupported": [1],
                                             "backoff": {"Q_em_mgal2": [0.041, 0.353], "Q_used_mgal2": [0.041, 0.062],
                                                         "iteration": 14, "share_at_iteration": [0.978, 0.022],
                                                         "reason": "levels [1] held < 0.02 of the points"}}},
        "timings_s": {"ingest": 0.1, "learning": 0.2},
        "noise_episodes": {"factor": 4.0, "min_duration_s": 30.0, "bridge_s": 10.0, "typical_R_cm2s2": 0.55,
                           "threshold_R_cm2s2": 2.2, "lines": [str(df["line"].iloc[0])], "epoch_fraction": 0.09,
                           "episodes": [{"line": str(df["line"].iloc[0]), "flight": flights[0], "t_start_s": 1020.0,
                                         "t_end_s": 1246.5, "duration_s": 226.5, "along_start_km": 0.5,
                                         "along_end_km": 1.8,
                                         "R_peak_over_typical": 18.8, "R_mean_over_typical": 13.7,
                                         "std_mean_mgal": 7.75, "std_line_quiet_mgal": 3.78}]},
        "warnings": warnings,
        "repeat_lines": {"R1": {"repeats": 3, "internal_accuracy_mgal": {
            "dg_mgal": 3.73, "dg_unleveled_mgal": 4.02, "dg_fir_mgal": 2.10, "dg_stationary_mgal": 1.17}}},
        "grid": {"nx": 10, "ny": 5, "valid_cells": 49},
        "base_ties": {f: {"static_periods": [], "applied": base_gravity_mgal is not None,
                          "absolute": base_gravity_mgal is not None,
                          **({"drift_mgal_per_h": -1.36} if base_gravity_mgal is not None else {})} for f in flights},
        "model_order": {"m": 1, "loglik": {"1": -758411.8, "2": -758515.9}, "Q_stationary_mgal2": {"1": 0.82, "2": 1.6e-5}},
        "noise_model": {"family": "white velocity", "dt_s": 0.1,
                        # a family the spectra chose at the margin, replaced at the crossovers
                        "crossover_check": {"family": "coloured height", "alternative": "white velocity",
                                            "bic_gap": 10.9, "n_crossovers": 30, "applied": True,
                                            "crossovers_compared": 30, "p_value": 0.0229, "p_rank": 0.00174,
                                            "p_level": 0.05, "crossover_rms_mgal": {"coloured height": 7.06,
                                                                                    "white velocity": 5.87},
                                            "reason": "coloured height beats white velocity by only 10.9 BIC units"},
                        "components": [{"order": 1, "phi": 0.0, "weight_mgal2": 1e8, "label": "velocity white"}],
                        "fit": "Whittle, prewhitened multitaper", "level_band_hz": [0.1, 0.5], "level_scale": 1.0,
                        "candidates": [{"family": "white velocity", "nll": 12512.1, "n_params": 2, "bic": 25038.0},
                                       {"family": "Gauss-Markov velocity", "nll": 12511.9, "n_params": 4,
                                        "bic": 25052.4}],
                        "n_bins": 1198, "fit_fmax_hz": 0.2, "m": 2, "anomaly_rolloff_s": 148.9,
                        "family_check": {"chosen": "Gauss-Markov velocity", "alternative": "white velocity",
                                         "applied": True, "n": 21, "predicted_ms_mgal2": 9.01, "bound_mgal2": 5.32,
                                         "reason": "Gauss-Markov velocity predicts 9.01 mGal² of FIR noise ...: "
                                                   "white velocity used"},
                        # as stage 3 writes it when the heights' bound refitted the noise (unseen 783's figures)
                        "velocity_bound": {"applied": True, "z_to_misfit": 0.972, "check_band_hz": [0.02, 0.05],
                                           "n_segments": 3, "groups": 9, "f_hz": [0.0011, 0.008],
                                           "max_model_to_misfit": 15.03, "refitted": True,
                                           "max_model_to_misfit_after": 2.691,
                                           # unseen 1100's figures: the moved corner refuted by the heights
                                           "cautious_shape": {"model_to_misfit": 2.691, "unmoved_model_to_misfit": 1.202,
                                                              "p_value": 0.0035, "unmoved_p_value": 0.67,
                                                              "alpha": 0.05, "refuted": True}}},
        "band_delay": {"band_hz": [0.01, 0.05], "lowpass_hz": 0.1, "min_t": 4.0, "applied": True,
                       "delay_s": 0.0181, "se_s": 0.00034, "t_stat": 52.7, "n_independent": 541.0,
                       "band_rms_mgal": 59.64, "band_rms_corrected_mgal": 24.08, "n_epochs": 67600,
                       "flights": {"F01": {"delay_s": 0.0180, "se_s": 0.0006, "t_stat": 30.0, "n_epochs": 22000},
                                   "F02": {"delay_s": 0.0183, "se_s": 0.0005, "t_stat": 36.6, "n_epochs": 24000},
                                   "F03": {"delay_s": 0.0179, "se_s": 0.0007, "t_stat": 25.6, "n_epochs": 21600}},
                       "heterogeneity": {"mean_s": 0.01812, "chi2": 0.23, "dof": 2, "p_value": 0.89, "p_limit": 0.001},
                       "reason": "the gravimeter is 18.1 ms late against the GNSS at 0.01–0.05 Hz (52.7 standard "
                                 "errors) after the time offset and lag: taken out of z below 0.1 Hz"},
        "lag_check": {"declared_tau_s": 2.0, "estimated_tau_s": [1.9995, 1.9990, 1.9992], "applied": False,
                      "offset_as_lag": {"applied": False, "from_time_offsets": True,
                                        "reason": "the flights' time offsets read as a lag (τ = 2.050 s) change z's "
                                                  "RMS at 0.02–0.05 Hz by +0.6 %: kept as offsets"},
                      "band_fit": {"applied": False, "from_band_fit": True, "declared_tau_s": 2.0,
                                   "iterations": [{"tau_s": 2.0, "dtau_s": -0.0004, "se_s": 0.0011}],
                                   "reason": "survey.toml's τ fits the band: Δτ -0.0004 s within 3 standard "
                                             "errors (0.0011 s)"}},
        # as the real stage 9 writes it when the FIR guard fired (unseen seed 88's figures)
        "model_choice": {"chosen": "FIR", "m": 2, "noisy_check": {"applied": False},
                         # unseen 1301's order choice: m = 1 not significantly better, the blend
                         "order": {"crossover_rms_mgal": {"1": 4.80, "2": 4.58}, "n_crossovers": 30,
                                   "p_m2_worse_than_m1": 0.677, "m": 2,
                                   "blend": {"m": 1, "weight": 0.2956, "crossover_rms_mgal": 4.534,
                                             "drift_removed": True}},
                         "fir_guard": {"n_crossovers": 30, "crossover_rms_mgal": 48.5, "crossover_rms_fir_mgal": 21.9,
                                       "p_value": 0.104, "p_rank": 0.002, "applied": True}},
        "future_section": {"note": "<b>not markup</b>", "value": 1},
    }


def write_outputs(out: Path, lines_df: pd.DataFrame, crs: str = "EPSG:32657", seed: int = 0,
                  base_gravity_mgal: float | None = None, dem: bool = False, datum: str = "flight") -> dict:
    """Write lines.parquet, recognition.parquet, identification.json, crossovers.csv, grid.* and
    report.json from a frame with ``line, flight, kind, time, lat, lon, h, easting_km, northing_km``.
    Products as the real pipeline names them: always ``atm_corr_mgal``; with ``dem`` the terrain
    columns and ``grid_bouguer.*``; with a ``datum`` other than "flight" the datum columns and
    ``grid_flight.*`` (the values are made up: shapes and names are what matters here)."""
    rng = np.random.default_rng(seed)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    df = lines_df.copy()
    e, n = df["easting_km"].to_numpy(), df["northing_km"].to_numpy()
    truth = 20 * np.sin(e / 7.0) * np.cos(n / 9.0) + 0.5 * e
    state = (np.sin(e / 5.0) > 0.3).astype(int)
    df["z_mgal"] = truth + rng.normal(0, 50, len(df))
    df["dg_mgal"] = truth + rng.normal(0, 0.3, len(df))
    df["dg_std_mgal"] = 0.5 + 0.3 * state
    df["dg_unleveled_mgal"] = df["dg_mgal"] + 1.0
    df["dg_stationary_mgal"] = truth + rng.normal(0, 0.6, len(df))
    df["dg_fir_mgal"] = truth + rng.normal(0, 1.0, len(df))
    df["state"] = state
    df["Q_mgal2"] = np.where(state == 1, 0.35, 0.04)
    df["R_cm2s2"] = 1.7
    df["atm_corr_mgal"] = 0.78
    products = {"atmospheric_correction": {"applied": True, "mean_mgal": 0.78},
                "datum": {"datum": "flight height (no continuation)"}, "terrain": {"dem": None}}
    if datum != "flight":
        df["dg_flight_mgal"] = df["dg_mgal"] + 0.05 * (df["h"] - 1000.0)
        df["dg_flight_std_mgal"] = df["dg_std_mgal"]
        df["dg_datum_mgal"] = df["dg_mgal"]
        df["dg_datum_std_mgal"] = df["dg_std_mgal"] * 1.1
        df["datum_height_m"] = 1100.0
        products["datum"] = {"datum": datum, "height_m": {"mean": 1100.0, "min": 1100.0, "max": 1100.0}}
    if dem:
        df["terrain_mgal"] = 0.1119 * (300.0 + 50.0 * np.sin(e / 3.0))
        df["terrain_height_m"] = 300.0 + 50.0 * np.sin(e / 3.0)
        df["dg_bouguer_mgal"] = df["dg_mgal"] - df["terrain_mgal"]
        products["terrain"] = {"dem": "dem.tif", "density_kgm3": 2670.0, "radius_m": 20000.0}
    products["grids"] = {"free_air": "grid", "bouguer": "grid_bouguer" if dem else None,
                         "free_air_flight_height": "grid_flight" if datum != "flight" else None}
    df.to_parquet(out / "lines.parquet", index=False)

    # decimated recognition points: every 10th epoch (AEROGRAV_FAKE_DECIMATE; 100 = ~1 km, as the pipeline)
    stride = int(os.environ.get("AEROGRAV_FAKE_DECIMATE", "10"))
    rec = df.groupby("line", sort=False).nth(slice(None, None, stride)).reset_index(drop=True)
    p1 = 1 / (1 + np.exp(-3 * np.sin(rec["easting_km"].to_numpy() / 5.0) + 0.9)) * 0.8 + rng.uniform(0, 0.2, len(rec))
    p1 = np.clip(p1, 0, 1)
    recog = pd.DataFrame({"line": rec["line"], "time": rec["time"], "easting_km": rec["easting_km"],
                          "northing_km": rec["northing_km"], "x": rng.normal(0, 1, len(rec)),
                          "state_raw": (p1 > 0.5).astype(int), "state_smoothed": (p1 > 0.5).astype(int),
                          "p_0": 1 - p1, "p_1": p1})
    recog.to_parquet(out / "recognition.parquet", index=False)

    ident = {"em": {"iterations": [{"iteration": i, "Q": [0.1, 1.0], "R": [10.0], "objective": -100.0 + i,
                                    "transition": [[0.98, 0.02], [0.03, 0.97]]} for i in range(3)],
                    "converged": True, "loglik": -98.0, "model": "2x1",
                    "selection": {"criterion": "bic", "chosen": "2x1", "candidates": [
                        {"model": "2x1", "n_q": 2, "n_r": 1, "loglik": -98.0, "n_params": 8, "bic": 240.5,
                         "iterations": 3},
                        {"model": "2x2", "n_q": 2, "n_r": 2, "loglik": -97.0, "n_params": 20, "bic": 262.1,
                         "iterations": 3}]}},
             "transition": [[0.98, 0.02], [0.03, 0.97]], "initial": {},
             "states": [{"index": 0, "Q": 0.041, "R": 1.679}, {"index": 1, "Q": 0.353, "R": 1.679}]}
    (out / "identification.json").write_text(json.dumps(ident))

    pd.DataFrame({"line_a": ["L1"], "line_b": ["T1"], "easting_km": [float(np.mean(e))],
                  "northing_km": [float(np.mean(n))], "diff_before_mgal": [1.2],
                  "diff_after_mgal": [0.1]}).to_csv(out / "crossovers.csv", index=False)

    xs = np.arange(np.floor(e.min()), np.ceil(e.max()) + 1, 1.0)
    ys = np.arange(np.floor(n.min()) - 1, np.ceil(n.max()) + 2, 1.0)
    X, Y = np.meshgrid(xs, ys)
    G = 20 * np.sin(X / 7.0) * np.cos(Y / 9.0) + 0.5 * X
    S = 0.5 + 0.1 * np.abs(Y - Y.mean())
    G[0, 0] = np.nan
    # the grid files through the real writers (the export conventions are part of what the web tests check)
    from app.io import export
    export.write_grid_netcdf(out / "grid.nc", xs, ys, G, S, crs)
    export.write_grid_geotiff(out / "grid.tif", xs, ys, G, S, crs)
    export.write_grid_surfer(out / "grid.grd", xs, ys, G, S)
    export.write_grid_csv(out / "grid.csv", xs, ys, G, S)
    extra = {}
    if dem:                           # Bouguer: the free-air grid less a smooth "terrain effect"
        extra["grid_bouguer"] = (G - 0.1119 * (300.0 + 50.0 * np.sin(X / 3.0)) + 20.0, S * 1.02)
    if datum != "flight":             # at flight height: the free-air grid plus a tilt
        extra["grid_flight"] = (G + 2.0 * (Y - Y.mean()), S * 0.95)
    for stem, (gg, ss) in extra.items():
        export.write_grid_netcdf(out / f"{stem}.nc", xs, ys, gg, ss, crs)
        export.write_grid_geotiff(out / f"{stem}.tif", xs, ys, gg, ss, crs)
        export.write_grid_surfer(out / f"{stem}.grd", xs, ys, gg, ss)
        export.write_grid_csv(out / f"{stem}.csv", xs, ys, gg, ss)
    report = fake_report(df, base_gravity_mgal, crs)
    report["products"] = products
    report["threads_env"] = os.environ.get("AEROGRAV_THREADS")  # what the job process was given
    (out / "report.json").write_text(json.dumps(report))
    return report


def process_survey(survey_dir, out_dir, overrides=None, progress=None, kind="process", previous_dir=None) -> dict:
    """A stand-in pipeline for the web tests: every job kind runs like "process"."""
    from app.io.survey import read_survey

    delay = float(os.environ.get("AEROGRAV_FAKE_DELAY_S", "0.05"))
    cb = progress or (lambda *a, **k: None)
    cb("ingest", 0.05, None)
    survey = read_survey(survey_dir, overrides)
    frames = []
    for row in survey.lines.itertuples(index=False):
        g = survey.flights[row.flight].gnss
        m = (g["time"] >= row.t_start) & (g["time"] <= row.t_end)
        d = g.loc[m, ["time", "lat", "lon", "h"]].copy()
        d.insert(0, "kind", row.kind)
        d.insert(0, "flight", row.flight)
        d.insert(0, "line", str(row.line))
        frames.append(d)
    df = pd.concat(frames, ignore_index=True)
    lat0 = df["lat"].mean()
    df["easting_km"] = (df["lon"] - df["lon"].min()) * 111.32 * np.cos(np.deg2rad(lat0))
    df["northing_km"] = (df["lat"] - df["lat"].min()) * 110.57
    for i in range(3):
        time.sleep(delay)
        cb("identification", 0.2 + 0.15 * i, {"em_iteration": {
            "iteration": i, "Q": [0.1 / (i + 1), 1.0 / (i + 1)], "R": [10.0 / (i + 1)], "objective": -100.0 + i,
            "transition": [[0.98, 0.02], [0.03, 0.97]]}})
    for k in range(10):
        time.sleep(delay)
        cb("filtering", 0.7 + 0.02 * k, None)
    cb("outputs", 0.95, None)
    (Path(out_dir) / "identified").mkdir(parents=True, exist_ok=True)  # a later filter job may start from here
    return write_outputs(out_dir, df, crs=survey.config.survey.crs or "EPSG:32657",
                         base_gravity_mgal=survey.config.gravimeter.base_gravity_mgal,
                         dem=(Path(survey_dir) / "dem.tif").is_file(), datum=survey.config.processing.datum)


def failing_survey(survey_dir, out_dir, overrides=None, progress=None, kind="process", previous_dir=None) -> dict:
    """A pipeline that fails as a reader or GDAL may: its error names files by their absolute paths."""
    from app.io.errors import InputError

    raise InputError(str(Path(survey_dir) / "flights" / "f1" / "gnss.csv"), 3, "time",
                     f"not a number; see also '{Path(survey_dir) / 'dem.tif'}' and {Path(out_dir) / 'grid.nc'}")
