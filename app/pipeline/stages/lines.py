"""Stage 2, lines: the survey lines of ``lines.csv`` cut out of their flights' measurement,
with positions in the survey's projected CRS (``survey.crs`` or the data's UTM zone).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from app.config import SurveyConfig
from app.core import geodesy
from app.core.accuracy import group_passes
from app.core.epochs import run_bounds
from app.core.leveling import LineTrack, find_crossovers
from app.pipeline.stages.measurement import FlightMeasurement


@dataclass
@dataclass
class LineData:
    """One survey line on the GNSS epochs inside its window."""

    line: str
    flight: str
    kind: str
    track: str | None
    sl: slice                      # slice of the flight arrays
    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    h_m: np.ndarray
    easting_km: np.ndarray
    northing_km: np.ndarray
    z_mgal: np.ndarray
    speed_ms: float


def survey_crs(cfg: SurveyConfig, flights: dict[str, FlightMeasurement]) -> str:
    """The projected CRS: ``survey.crs`` or the UTM zone of the data."""
    if cfg.survey.crs:
        return cfg.survey.crs
    lon = np.concatenate([m.lon_deg[:: max(1, m.lon_deg.size // 1000)] for m in flights.values()])
    lat = np.concatenate([m.lat_deg[:: max(1, m.lat_deg.size // 1000)] for m in flights.values()])
    return geodesy.utm_crs_for(lon, lat)


def cut_lines(lines: pd.DataFrame, flights: dict[str, FlightMeasurement], crs: str) -> list[LineData]:
    """Cut every line of ``lines.csv`` out of its flight's measurement."""
    out = []
    for row in lines.itertuples(index=False):
        m = flights[str(row.flight)]
        i0 = int(np.searchsorted(m.t_s, row.t_start, side="left"))
        i1 = int(np.searchsorted(m.t_s, row.t_end, side="right"))
        sl = slice(i0, i1)
        e, n = geodesy.project_km(m.lon_deg[sl], m.lat_deg[sl], crs)
        z = m.z_mgal[sl].copy()
        speed = float(np.nanmedian(np.hypot(m.ve_ms[sl], m.vn_ms[sl]))) if i1 > i0 else float("nan")
        track = getattr(row, "track", None)
        if track is not None and (isinstance(track, float) and np.isnan(track)):
            track = None
        out.append(LineData(str(row.line), str(row.flight), str(row.kind),
                            None if track is None else str(track), sl, m.t_s[sl], m.lat_deg[sl],
                            m.lon_deg[sl], m.h_m[sl], np.asarray(e), np.asarray(n), z, speed))
    return out


def finite_segments(z) -> list[tuple[int, int]]:
    """(start, stop) index pairs of the runs of finite values of z."""
    return run_bounds(np.isfinite(np.asarray(z, float)))


def check_grid_size(lines, p) -> None:
    """Refuse, before the heavy stages, a grid over the lines' extent with more than
    ``app.config.MAX_GRID_CELLS`` nodes."""
    from app.config import check_grid_cells
    from app.io.errors import InputError

    e = np.concatenate([ln.easting_km for ln in lines] or [np.zeros(1)])
    n = np.concatenate([ln.northing_km for ln in lines] or [np.zeros(1)])
    e, n = e[np.isfinite(e)], n[np.isfinite(n)]
    if e.size and n.size:
        try:
            check_grid_cells(float(np.ptp(e)), float(np.ptp(n)), p.grid_spacing_km)
        except ValueError as exc:
            raise InputError(None, None, "processing.grid_spacing_km", str(exc)) from None


def infer_repeat_tracks(lines: list[LineData]) -> dict[str, list[str]]:
    """Repeat lines that ``lines.csv`` gives no track (in place): grouped by their positions
    (:func:`app.core.accuracy.group_passes`, in time order: one track, parallel or not, within
    ``REPEAT_MAX_SPREAD_KM`` across it and overlapping along it) and every group of two passes
    or more given the track ``auto-1``, ``auto-2``, … — so that its passes are compared (the
    repeat-line accuracy, the repeat checks and blend of stage 9) as they would be with a track
    id.  A pass that flies no other pass's track keeps none.  Returns ``{track: [line, …]}``."""
    free = sorted((ln for ln in lines if ln.kind == "repeat" and ln.track is None),
                  key=lambda ln: float(ln.t_s[0]) if ln.t_s.size else 0.0)
    if len(free) < 2:
        return {}
    taken = {ln.track for ln in lines if ln.track is not None}
    labels = group_passes([ln.easting_km for ln in free], [ln.northing_km for ln in free])
    out, k = {}, 0
    for g in range(int(labels.max()) + 1):
        members = [ln for ln, lab in zip(free, labels) if lab == g]
        if len(members) < 2:
            continue
        k += 1
        while f"auto-{k}" in taken:
            k += 1
        for ln in members:
            ln.track = f"auto-{k}"
        out[f"auto-{k}"] = [ln.line for ln in members]
    return out


#: relative distance error of a declared CRS at the survey beyond which a warning says so
#: (on the equator a UTM zone's edge: 0.001; two zones away 0.022)
MAX_CRS_SCALE_ERROR = 0.01


@dataclass
class SurveyLines:
    """Result of :func:`survey_lines`: the CRS, every line (in ``lines.csv`` order), the
    tracks given to repeat lines that had none (:func:`infer_repeat_tracks`) and warnings."""

    crs: str
    lines: list
    inferred_tracks: dict
    warnings: list = field(default_factory=list)


def crs_warning(crs: str, lines: list) -> str | None:
    """A warning when the CRS distorts distances at the survey's centre by more than
    :data:`MAX_CRS_SCALE_ERROR` (:func:`app.core.geodesy.scale_error`): line lengths, the
    NL-means distance ρ, grid spacing and every product in km are off by that much."""
    lon = np.concatenate([ln.lon_deg for ln in lines if ln.lon_deg.size])
    lat = np.concatenate([ln.lat_deg for ln in lines if ln.lat_deg.size])
    if not lon.size:
        return None
    err = geodesy.scale_error(*geodesy.mean_position_deg(lon, lat), crs)
    if abs(err) <= MAX_CRS_SCALE_ERROR:
        return None
    return (f"the CRS {crs} stretches distances at the survey by {100 * err:+.1f} % (it is meant for another "
            f"region; the survey's own UTM zone is {geodesy.utm_crs_for(lon, lat)}): line lengths, the grid spacing, "
            "nlmeans_rho_km and the products' distances are off by that much")


#: a line epoch whose heading departs from its line's by more than this (degrees) is off the line
TURN_DEPARTURE_DEG = 30.0
#: off-line seconds in a window beyond which a warning names the line (a few gusts are not a turn)
TURN_MIN_S = 5.0


def turn_warnings(lines: list[LineData], flights: dict[str, FlightMeasurement]) -> list[str]:
    """A warning per line whose window holds more than :data:`TURN_MIN_S` s flown more than
    :data:`TURN_DEPARTURE_DEG` off the line's heading (:func:`app.core.geodesy.heading_departures`):
    a turn inside the window (lines.csv's t_start/t_end reaching into the turn), where a
    stabilised platform is not level and the anomaly is not measured on the line."""
    out = []
    for ln in lines:
        m = flights[ln.flight]
        d = geodesy.heading_departures(ln.t_s, m.ve_ms[ln.sl], m.vn_ms[ln.sl], TURN_DEPARTURE_DEG)
        if d["seconds"] > TURN_MIN_S:
            where = ("at its start" if d["last_s"] - ln.t_s[0] < 0.5 * (ln.t_s[-1] - ln.t_s[0]) else
                     "at its end" if d["first_s"] - ln.t_s[0] > 0.5 * (ln.t_s[-1] - ln.t_s[0]) else "inside it")
            out.append(f"line {ln.line} (flight {ln.flight}): {d['seconds']:.0f} s of its window, "
                       f"{d['first_s']:.1f}–{d['last_s']:.1f} s ({where}), are flown more than "
                       f"{TURN_DEPARTURE_DEG:g}° off the line's heading (up to {d['max_deg']:.0f}°): a turn inside "
                       "the line window? A turn's platform and Eötvös errors enter dg and the crossovers; check "
                       "t_start/t_end in lines.csv")
    return out


def survey_lines(survey, measurement) -> SurveyLines:
    """Stage 2 on a survey and its :class:`~app.pipeline.stages.measurement.Measurement`."""
    crs = survey_crs(survey.config, measurement.flights)
    lines = cut_lines(survey.lines, measurement.flights, crs)
    check_grid_size(lines, survey.config.processing)
    warn = crs_warning(crs, lines) if survey.config.survey.crs else None
    return SurveyLines(crs, lines, infer_repeat_tracks(lines),
                       ([warn] if warn else []) + turn_warnings(lines, measurement.flights))


def line_crossovers(lines: list[LineData], include_repeat: bool, values=None, std_mgal: float = 0.0) -> pd.DataFrame:
    """Crossovers between the survey lines, as leveling will find them
    (:func:`app.core.leveling.find_crossovers`), carrying ``values(line)`` — an array on the
    line's epochs (zeros when None) — and a constant ``std_mgal``; an empty frame when there
    are none or the geometry gives none."""
    tr = {ln.line: LineTrack(ln.easting_km, ln.northing_km, ln.t_s,
                             np.zeros(ln.t_s.size) if values is None else values(ln),
                             np.full(ln.t_s.size, float(std_mgal)), ln.kind)
          for ln in lines if ln.t_s.size >= 2}
    try:
        return find_crossovers(tr, include_repeat=include_repeat) if len(tr) > 1 else pd.DataFrame()
    except ValueError:
        return pd.DataFrame()
