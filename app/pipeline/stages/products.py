"""Stage 9b, geophysical products (after the model choice, before leveling): the atmospheric
correction, the continuation to a common datum by equivalent sources, and the terrain
(complete Bouguer) correction from the survey's DEM.

* **Atmospheric correction** (``atmospheric_correction``, default off): the IAG/USSA76
  ``δg_atm(h)`` (:mod:`app.core.atmosphere`), written per epoch as ``atm_corr_mgal`` and, when
  switched on, added to every estimate column.  Off by default because SPEC §1 defines the
  measurement (and so ``dg_mgal``) without it: on a survey whose gravity has no atmosphere
  term the correction is a +0.8 mGal bias (2σ coverage of the posterior std 0.95 → 0.86 on the
  quiet regime).
* **Datum** (``datum``: ``"flight"`` default = no continuation, ``"constant"`` at
  ``datum_height_m`` (default the mean flight height), ``"draped"``: a smooth surface through the
  flight heights): equivalent sources fitted to the line estimates with their posterior std
  (:mod:`app.core.continuation`); per epoch ``dg_datum_mgal``, ``dg_datum_std_mgal``,
  ``datum_height_m``.  ``dg_mgal`` and ``dg_std_mgal`` then carry the continued values (leveling and
  gridding work on them); ``dg_flight_mgal`` and ``dg_flight_std_mgal`` keep the estimate at flight
  height (gridded as ``grid_flight.*``: :func:`flight_height_table`).
* **Terrain** (when the survey directory holds ``dem.tif``): the prisms of the DEM within
  ``terrain_radius_m`` at ``bouguer_density_kgm3`` (:mod:`app.core.terrain`); per epoch
  ``terrain_mgal``, ``terrain_height_m``, ``dg_bouguer_mgal = dg − terrain``; a Bouguer grid beside
  the free-air one.

Every decision and figure is returned for ``report.json`` (``products``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from app.core.atmosphere import atmospheric_correction_mgal
from app.core.continuation import draped_datum_height_m, fit_equivalent_sources
from app.core.terrain import terrain_effect_along_lines_mgal

#: estimate columns shifted by the atmospheric correction
ESTIMATE_COLUMNS = ("dg_mgal", "dg_unleveled_mgal", "dg_stationary_mgal", "dg_fir_mgal")


@dataclass
class Products:
    """Result of :func:`apply_products`: what was done and its figures (``report.json``)."""

    report: dict


def atmosphere(table: pd.DataFrame, p) -> dict:
    """The atmospheric correction added to every estimate (in place)."""
    corr = atmospheric_correction_mgal(table["h"].to_numpy(float))
    table["atm_corr_mgal"] = corr
    rep = {"applied": bool(p.atmospheric_correction), "model": "IAG / US Standard Atmosphere 1976",
           "mean_mgal": float(np.nanmean(corr)), "min_mgal": float(np.nanmin(corr)), "max_mgal": float(np.nanmax(corr))}
    if not p.atmospheric_correction:
        rep["note"] = ("not applied (default): dg_mgal is SPEC §1's free-air disturbance; add atm_corr_mgal for "
                       "the atmosphere-corrected anomaly contractors deliver, or set atmospheric_correction = true")
        return rep
    for c in ESTIMATE_COLUMNS:
        table[c] = table[c] + corr
    return rep


def continue_to_datum(table: pd.DataFrame, p, warnings: list) -> dict:
    """Equivalent-source continuation of the line estimates to the datum (in place)."""
    if p.datum == "flight":
        return {"datum": "flight height (no continuation)"}
    e = table["easting_km"].to_numpy(float) * 1000.0
    n = table["northing_km"].to_numpy(float) * 1000.0
    h = table["h"].to_numpy(float)
    ok = np.isfinite(table["dg_mgal"].to_numpy(float)) & np.isfinite(h)
    try:
        model = fit_equivalent_sources(e[ok], n[ok], h[ok], table["dg_mgal"].to_numpy(float)[ok],
                                       np.maximum(table["dg_std_mgal"].to_numpy(float)[ok], 1e-3),
                                       table["line"].to_numpy()[ok])
    except ValueError as exc:
        warnings.append(f"datum: continuation not possible ({exc}); values stay at flight height")
        return {"datum": "flight height (continuation failed)", "error": str(exc)}
    if p.datum == "constant":
        hd = np.full(e.size, float(p.datum_height_m) if p.datum_height_m is not None else float(np.nanmean(h)))
    else:
        hd = draped_datum_height_m(e, n, e[ok], n[ok], h[ok], smoothing_m=p.datum_smoothing_m)
    table["dg_flight_mgal"] = table["dg_mgal"]
    table["dg_flight_std_mgal"] = table["dg_std_mgal"]
    table["dg_datum_mgal"] = model.predict(e, n, hd)
    table["dg_datum_std_mgal"] = model.predict_std(e, n, hd)
    table["datum_height_m"] = hd
    # leveling and gridding work on the continued values
    table["dg_mgal"] = table["dg_datum_mgal"]
    table["dg_unleveled_mgal"] = table["dg_datum_mgal"]
    table["dg_std_mgal"] = table["dg_datum_std_mgal"]
    return {"datum": p.datum, "height_m": {"mean": float(np.mean(hd)), "min": float(np.min(hd)),
                                           "max": float(np.max(hd))},
            "equivalent_sources": {k: (float(v) if isinstance(v, (int, float, np.floating)) else v)
                                   for k, v in {**model.info, "damping": model.damping, "depth_m": model.depth_m,
                                                "method": model.method}.items()
                                   if isinstance(v, (int, float, str, np.floating))}}


def terrain(table: pd.DataFrame, dem_path: Path | None, crs: str, p, warnings: list) -> dict:
    """Terrain effect of the DEM's prisms and the complete Bouguer anomaly (in place)."""
    if dem_path is None or not Path(dem_path).exists():
        return {"dem": None}
    from app.io.dem import read_dem

    e = table["easting_km"].to_numpy(float) * 1000.0
    n = table["northing_km"].to_numpy(float) * 1000.0
    # the terrain effect where the free-air values are: at the datum when one is set
    h = table["datum_height_m" if "datum_height_m" in table else "h"].to_numpy(float)
    bounds = (float(np.nanmin(e)), float(np.nanmax(e)), float(np.nanmin(n)), float(np.nanmax(n)))
    dem = read_dem(dem_path, crs, bounds_m=bounds, spacing_m=p.dem_spacing_m, margin_m=p.terrain_radius_m,
                   height_offset_m=p.dem_height_offset_m, require_bounds_m=bounds, display="dem.tif")
    order = np.lexsort((table["time"].to_numpy(), table["line"].astype(str).to_numpy()))
    eff = np.empty(e.size)
    eff_o, info = terrain_effect_along_lines_mgal(e[order], n[order], h[order], table["line"].astype(str).to_numpy()[order],
                                                  dem, density_kgm3=p.bouguer_density_kgm3, radius_m=p.terrain_radius_m,
                                                  near_radius_m=p.terrain_near_radius_m)
    eff[order] = eff_o
    table["terrain_mgal"] = eff
    table["terrain_height_m"] = dem.sample(e, n)
    table["dg_bouguer_mgal"] = table["dg_mgal"] - eff
    return {"dem": "dem.tif", "density_kgm3": p.bouguer_density_kgm3, "radius_m": p.terrain_radius_m,
            "dem_spacing_m": [float(s) for s in np.atleast_1d(dem.spacing_m)], "terrain_mgal": {"mean": float(np.nanmean(eff)),
                                                                    "min": float(np.nanmin(eff)),
                                                                    "max": float(np.nanmax(eff))},
            "min_clearance_m": float(info.get("min_clearance_m", np.nan)) if info.get("min_clearance_m") is not None
            else None}


def apply_products(table: pd.DataFrame, survey_dir: Path | None, crs: str, p, warnings: list) -> Products:
    """Stage 9b on the chosen line table (in place)."""
    rep = {"atmospheric_correction": atmosphere(table, p)}
    rep["datum"] = continue_to_datum(table, p, warnings)
    dem = Path(survey_dir) / "dem.tif" if survey_dir is not None else None
    rep["terrain"] = terrain(table, dem, crs, p, warnings)
    return Products(rep)


def refresh_bouguer(table: pd.DataFrame) -> None:
    """After leveling: the Bouguer anomaly follows the leveled free-air estimate."""
    if "terrain_mgal" in table:
        table["dg_bouguer_mgal"] = table["dg_mgal"] - table["terrain_mgal"]


def flight_height_table(table: pd.DataFrame) -> pd.DataFrame | None:
    """When the values were continued to a datum: the line table with ``dg_mgal``/``dg_std_mgal`` at
    flight height (``dg_flight_mgal`` plus the leveling correction found at the datum — the drift is
    the instrument's, not the height's — and ``dg_flight_std_mgal``), for the flight-height grid;
    None otherwise."""
    if "dg_flight_mgal" not in table:
        return None
    leveling = table["dg_mgal"] - table["dg_unleveled_mgal"]
    std = table["dg_flight_std_mgal"] if "dg_flight_std_mgal" in table else table["dg_std_mgal"]
    return table.assign(dg_mgal=table["dg_flight_mgal"] + leveling, dg_std_mgal=std)
