"""Stage 11, gridding (SPEC §3): the map at flight height by local least-squares collocation
with a posterior std grid (or the cubic-spline alternative).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from app.core.gridding import Collocation, Spline, cross_validated_std_factor, line_std_floor


def grid_table(table: pd.DataFrame, p, warnings: list, crossover_rms_mgal: float | None = None,
          grid_cv: dict | None = None):
    grid_cv = {} if grid_cv is None else grid_cv
    try:
        # what the crossovers still disagree by, beyond the lines' own posterior std, is an
        # error shared along each line (leveling residual): model it as such in the grid's std
        # The smoother's errors are correlated along a line over the smoother's own
        # resolution (several km), far longer than the thinning step: a share of their
        # variance (grid_line_error_fraction) can be carried as an error shared along each
        # line — it widens the std towards calibration (mini 0.92 → 0.97 of cells within 2σ)
        # but costs grid RMS (kalgoorlie 3.41 → 3.73 mGal), so it is off by default.
        line_err = p.grid_line_error_fraction * float(np.mean(table["dg_std_mgal"] ** 2))
        if crossover_rms_mgal is not None and np.isfinite(crossover_rms_mgal):
            line_err = max(line_err, crossover_rms_mgal ** 2 / 2.0 - float(np.mean(table["dg_std_mgal"] ** 2)))
        est = (Collocation(error_corr_km=p.grid_error_corr_km, line_error_mgal2=line_err)
               if p.gridding == "collocation" else Spline())
        kw = {} if p.grid_mask_km is None else {"mask_km": p.grid_mask_km}
        est.fit(table["easting_km"].to_numpy(), table["northing_km"].to_numpy(),
                table["dg_mgal"].to_numpy(), table["dg_std_mgal"].to_numpy(), line=table["line"].to_numpy())
        g = est.grid(spacing_km=p.grid_spacing_km, **kw)
        if len(g[0]) < 2 or len(g[1]) < 2 or not np.isfinite(g[2]).any():
            raise ValueError("the lines span less than two grid cells in one direction: no map to grid "
                             "(grid files not written)")
        if p.gridding == "collocation" and p.grid_std_line_floor:
            floor = line_std_floor(g[0], g[1], table["easting_km"].to_numpy(), table["northing_km"].to_numpy(),
                                   table["dg_std_mgal"].to_numpy())
            g = (g[0], g[1], g[2], np.where(np.isfinite(g[3]), np.maximum(g[3], floor), g[3]))
        if p.gridding == "collocation" and p.grid_std_cross_validate:
            main = table["kind"].to_numpy() != "repeat"
            try:
                cv = cross_validated_std_factor(
                    lambda: Collocation(error_corr_km=p.grid_error_corr_km, line_error_mgal2=line_err),
                    table["easting_km"].to_numpy()[main], table["northing_km"].to_numpy()[main],
                    table["dg_mgal"].to_numpy()[main], table["dg_std_mgal"].to_numpy()[main],
                    table["line"].to_numpy()[main])
                grid_cv.update(cv)
                if cv["factor"] > 1.0:   # only ever widen: a too-small std is the dangerous error
                    g = (g[0], g[1], g[2], g[3] * cv["factor"])
            except ValueError as exc:
                warnings.append(f"grid std cross-validation skipped: {exc}")
        return g
    except ValueError as exc:
        warnings.append(f"gridding: {exc}")
        return None


@dataclass
class Gridded:
    """Result of :func:`grid_survey`: coordinates (km), ``dg`` and ``dg_std`` (mGal, shape
    (ny, nx)) and the std cross-validation evidence (empty when not run)."""

    easting_km: np.ndarray
    northing_km: np.ndarray
    dg_mgal: np.ndarray
    dg_std_mgal: np.ndarray
    cross_validation: dict


def grid_survey(table: pd.DataFrame, p, warnings: list, crossover_rms_mgal: float | None) -> Gridded | None:
    """Stage 11 on the leveled line table; None (with a warning) when there is no map to grid."""
    cv: dict = {}
    g = grid_table(table, p, warnings, crossover_rms_mgal, cv)
    if g is None:
        return None
    return Gridded(np.asarray(g[0]), np.asarray(g[1]), np.asarray(g[2]), np.asarray(g[3]), cv)
