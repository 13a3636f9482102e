"""Stage 12, outputs (SPEC §5): ``identification.json``, ``report.json`` and the files.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from app.core import accuracy
from app.core.accuracy import REPEAT_MAX_SPREAD_KM
from app.core.ma_approx import model_vs_true_spectrum


def identification_json(ident, noise, smap, dt_s: float) -> dict:
    """``identification.json`` (SPEC §5) of one identification and the map its filter used."""
    reg, learned = ident.regularized, ident.learned
    em = learned.em
    d, ma = reg.design, reg.ma
    n_r = len(em.R)
    sel = learned.selection
    states = [{"index": i * n_r + j, "Q": float(em.Q[i]), "R": float(em.R[j])}
              for i in range(len(em.Q)) for j in range(n_r)]
    f = np.linspace(0, 0.5 / (d.n * d.dt_s), 64)
    try:
        spec = {k: np.asarray(v).tolist() for k, v in model_vs_true_spectrum(
            ma, d, f, noise=None if noise.is_white_velocity else noise).items()}
    except Exception as exc:  # the fit display must never break processing
        spec = {"error": str(exc)}
    return {
        "m": ident.m,
        "dt_s": dt_s,
        "units": {"Q": "mGal^2 per GNSS step (dt_s)", "R": "(cm/s)^2 of equivalent white velocity noise"},
        "regularization": {"n": int(d.n), "cutoff_hz": float(d.cutoff_hz), "stop_hz": float(d.stop_hz),
                           "width_hz": float(d.width_hz), "attenuation_db": float(d.attenuation_db),
                           "n_taps": int(len(d.taps)), "decimated_step_s": float(d.n * d.dt_s),
                           "difference_grid": d.difference_grid, "beta": float(d.beta)},
        "ma": {"K": int(ma.K), "L": int(ma.L), "p": int(ma.p), "c": np.asarray(ma.c).tolist(),
               "d": np.asarray(ma.d).tolist(), "misfit_q": float(ma.misfit_q), "misfit_r": float(ma.misfit_r),
               "band_error_q": float(ma.band_error_q), "band_error_r": float(ma.band_error_r),
               "spectrum": spec},
        "em": {"iterations": [em_record(r) for r in em.iterations],
               "converged": bool(getattr(em, "converged", True)),
               "loglik": float(getattr(em, "loglik", np.nan)), "model": sel.get("chosen"),
               "selection": sel},
        "transition": np.asarray(em.transition).tolist(),
        "initial": {ln.line: np.asarray(pi).tolist() for ln, pi in zip(reg.lines, learned.initial)},
        "states": states,
        "lines_learned": [ln.line for ln, k in zip(reg.lines, learned.learn_mask) if k],
        "lines_skipped": reg.skipped,
        "nlmeans": {"h_per_km": smap.h_per_km, "rho_km": smap.rho_km, "mode": smap.mode},
    }


def em_record(r: dict) -> dict:
    """One row of the EM iteration table as plain JSON numbers."""
    return {"iteration": int(r["iteration"]), "Q": [float(v) for v in r["Q"]], "R": [float(v) for v in r["R"]],
            "objective": float(r["objective"]),
            "transition": [[float(v) for v in row] for row in r.get("transition", [])]}


def build_report(survey_name: str, crs: str, table: pd.DataFrame, flights: dict, leveled, ident, grid,
                 warnings: list) -> dict:
    """``report.json`` (SPEC §5): counts, every automatic decision with its evidence, accuracy
    figures the data alone give (crossovers, repeat lines), warnings.  The caller adds the
    sections of the other stages (noise model, model choice, base ties, timings …)."""
    em = ident.learned.em
    backoff = getattr(ident, "level_backoff", None)
    rep = {
        "survey": survey_name,
        "crs": crs,
        "counts": {"flights": len(flights), "lines": int(table["line"].nunique()),
                   "epochs": int(len(table)), "decimated_points": int(ident.n_points),
                   "crossovers": int(len(leveled.crossovers))},
        "time_offsets": {n: {"offset_s": m.time_offset_s, "correlation": m.time_offset_corr,
                             "applied": m.time_offset_applied, **m.time_offset} for n, m in flights.items()},
        "spike_repair": {n: m.despike for n, m in flights.items()},
        "gnss_filled_epochs": {n: int(m.gnss_filled) for n, m in flights.items()},
        "gravimeter_filled_samples": {n: int(getattr(m, "gravimeter_filled", 0)) for n, m in flights.items()},
        "crossovers": leveled.report,
        # the EM's levels (a level it emptied is filtered with an earlier iteration's: level_support.backoff)
        "identification": {"Q_mgal2": np.asarray(em.Q if backoff is None else backoff["Q_em_mgal2"]).tolist(),
                           "R_cm2s2": np.asarray(em.R).tolist(),
                           "transition": np.asarray(em.transition).tolist()},
        "warnings": warnings,
    }
    rep["repeat_lines"] = repeat_accuracy(table)
    warnings.extend(repeat_track_warnings(rep["repeat_lines"]))
    if grid is not None:
        rep["grid"] = {"nx": int(len(grid.easting_km)), "ny": int(len(grid.northing_km)),
                       "valid_cells": int(np.isfinite(grid.dg_mgal).sum())}
    return rep


def repeat_accuracy(table: pd.DataFrame) -> dict:
    """Internal accuracy of the repeat tracks (SPEC §3) for the adaptive estimate (leveled and
    not: the baselines are not leveled), FIR and stationary estimates."""
    rep = table[table["kind"] == "repeat"]
    out = {}
    if rep.empty or "track" not in rep:
        return out
    for track, g in rep.groupby("track"):
        groups = [gg for _, gg in g.groupby("line", sort=False)]
        if len(groups) < 2:
            continue
        res = {}
        for col in [c for c in ("dg_mgal", "dg_unleveled_mgal", "dg_fir_mgal", "dg_stationary_mgal") if c in g]:
            try:
                res[col] = float(accuracy.repeat_line_accuracy(
                    [(gg["easting_km"].to_numpy(), gg["northing_km"].to_numpy(), gg[col].to_numpy())
                     for gg in groups]))
            except (ValueError, AttributeError, TypeError) as exc:
                res[col] = f"n/a: {exc}"
        spread = accuracy.across_track_spread_km([gg["easting_km"].to_numpy() for gg in groups],
                                                 [gg["northing_km"].to_numpy() for gg in groups])
        out[str(track)] = {"repeats": len(groups), "internal_accuracy_mgal": res, "across_track_spread_km": spread}
    return out


def repeat_track_warnings(repeat_lines: dict) -> list[str]:
    """Warnings for the tracks of :func:`repeat_accuracy` whose passes lie more than
    ``REPEAT_MAX_SPREAD_KM`` apart across the track."""
    return [f"repeat track {t}: its {r['repeats']} passes lie {r['across_track_spread_km']:.2f} km apart across "
            f"the track (more than {REPEAT_MAX_SPREAD_KM} km) — not repeats of one track? Its internal accuracy "
            "compares different ground (check the track column of lines.csv); the noise fit, the model checks "
            "and the std sizing left the track out"
            for t, r in repeat_lines.items() if r.get("across_track_spread_km", 0.0) > REPEAT_MAX_SPREAD_KM]


LINE_COLUMNS = ["line", "flight", "kind", "time", "lat", "lon", "h", "easting_km", "northing_km", "z_mgal",
                "dg_mgal", "dg_std_mgal", "dg_unleveled_mgal", "dg_stationary_mgal", "dg_fir_mgal", "state",
                "Q_mgal2", "R_cm2s2"]


#: product columns written after SPEC §5's when present (app.pipeline.stages.products)
PRODUCT_COLUMNS = ["atm_corr_mgal", "dg_flight_mgal", "dg_flight_std_mgal", "dg_datum_mgal", "dg_datum_std_mgal", "datum_height_m",
                   "terrain_mgal", "terrain_height_m", "dg_bouguer_mgal"]


def write_outputs(out, table: pd.DataFrame, recognition: pd.DataFrame, crossovers: pd.DataFrame,
                  identification: dict, grid, crs: str, grid_bouguer=None, grid_flight=None) -> None:
    """The files of SPEC §5 except ``report.json`` (each written atomically); with a Bouguer grid
    also ``grid_bouguer.{nc,tif,grd,csv}``, with a flight-height grid (the values were continued to a
    datum) ``grid_flight.{nc,tif,grd,csv}``."""
    from pathlib import Path

    from app.io import export

    out = Path(out)
    export.write_parquet(table[LINE_COLUMNS + [c for c in PRODUCT_COLUMNS if c in table]], out / "lines.parquet")
    export.write_parquet(recognition, out / "recognition.parquet")
    export.write_csv(crossovers, out / "crossovers.csv")
    export.write_json(identification, out / "identification.json")
    for name, gr in (("grid", grid), ("grid_bouguer", grid_bouguer), ("grid_flight", grid_flight)):
        if gr is not None:
            e, n, g, gs = gr.easting_km, gr.northing_km, gr.dg_mgal, gr.dg_std_mgal
            export.write_grid_netcdf(out / f"{name}.nc", e, n, g, gs, crs)
            export.write_grid_geotiff(out / f"{name}.tif", e, n, g, gs, crs)
            export.write_grid_surfer(out / f"{name}.grd", e, n, g, gs)
            export.write_grid_csv(out / f"{name}.csv", e, n, g, gs)
