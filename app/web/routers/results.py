"""Results of the survey's current (last successful) job: lines, profiles, the
recognition map with interactive NL-means re-smoothing, the grid and exports."""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
from fastapi import APIRouter, Depends, HTTPException, Query
from fastapi.responses import FileResponse
from sqlalchemy.orm import Session

from app.core.baselines import gaussian_lowpass
from app.core.nlmeans import RecognitionMap
from app.jsonsafe import finite_float, float_list, int_list, to_jsonable
from app.pipeline.stages.recognition import Recognition, state_map

from ..db import Result, Survey
from ..deps import get_cache, get_db, get_store, get_survey_or_404, get_views
from ..repeat import track_members, track_passes
from ..schemas import (
    GridOut,
    LineOut,
    ProfileOut,
    RecognitionOut,
    RepeatTrackOut,
    RepeatTracksOut,
    ReportOut,
)
from ..services import has_dem
from ..store import ResultCache, Store

router = APIRouter(prefix="/api/surveys", tags=["results"])

EXPORTS = {
    "geotiff": ("grid.tif", "image/tiff"),
    "netcdf": ("grid.nc", "application/x-netcdf"),
    "surfer": ("grid.grd", "text/plain"),
    "csv": ("grid.csv", "text/csv"),
    "parquet": ("lines.parquet", "application/vnd.apache.parquet"),
    "xyz": ("lines.xyz", "text/plain"),
    "crossovers": ("crossovers.csv", "text/csv"),
    "report": ("report.json", "application/json"),
}


def _clean(a, nd: int = 3) -> list:
    """Array → JSON list, rounded, NaN/inf → null (:func:`app.jsonsafe.float_list`)."""
    return float_list(a, nd)


_ints = int_list


def current_result(s: Survey, db: Session) -> Result:
    if s.current_result_id is None:
        raise HTTPException(404, f"survey {s.id} has no results yet: run a 'process' job")
    r = db.get(Result, s.current_result_id)
    if r is None or not Path(r.dir).is_dir():
        raise HTTPException(404, f"the results of survey {s.id} are missing on disk")
    return r


# ---------------------------------------------------------------- loaders (cached)
def _result_file(r: Result, name: str) -> Path:
    """A file of a result, or 404 naming what is missing (an ``identify`` result has no line
    estimates or grid until a ``filter`` job runs)."""
    p = Path(r.dir) / name
    if not p.exists():
        if (Path(r.dir) / "identified").is_dir() and not (Path(r.dir) / "lines.parquet").exists():
            raise HTTPException(404, f"the current result is an identification: {name} comes with a filter "
                                     "(apply h, ρ) or process job")
        why = _grid_missing_reason(r) if name.startswith("grid") else None
        raise HTTPException(404, why or f"{name} is not among the stored results")
    return p


def _grid_missing_reason(r: Result) -> str | None:
    """Why a processed result has no grid, from its report's warnings (a test line: the lines
    span less than two grid cells), or None."""
    try:
        rep = json.loads((Path(r.dir) / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    for w in rep.get("warnings", []) or []:
        if "grid files not written" in str(w):
            return f"this result has no grid: {w}"
    return None


def _load_lines(r: Result) -> dict[str, Any]:
    df = pd.read_parquet(_result_file(r, "lines.parquet"))
    df["line"] = df["line"].astype(str)
    groups = {k: g.sort_values("time").reset_index(drop=True) for k, g in df.groupby("line", sort=False)}
    return {"groups": groups}


def _load_identification(r: Result) -> dict:
    p = Path(r.dir) / "identification.json"
    return json.loads(p.read_text()) if p.exists() else {}


def _load_recognition(r: Result) -> dict[str, Any]:
    """The state map's raw posteriors (``recognition_raw.parquet``, before NL-means) as the
    pipeline's :class:`~app.pipeline.stages.recognition.Recognition`, the stored smoothed map
    and its (h, ρ), and the neighbour structure (built once per result)."""
    out = Path(r.dir)
    ident = _load_identification(r)
    stored = pd.read_parquet(out / "recognition.parquet")
    pcols = sorted([c for c in stored.columns if c.startswith("p_")], key=lambda c: int(c[2:]))
    states = ident.get("states") or []
    raw_path = out / "recognition_raw.parquet"
    if raw_path.exists():
        raw = pd.read_parquet(raw_path)
        n_q, n_r = int(raw["n_q"].iloc[0]), int(raw["n_r"].iloc[0])
        rec = Recognition(raw.drop(columns=["n_q", "n_r"]), n_q, n_r)
    else:  # a result without raw posteriors (older runs): its smoothed map stands in for them
        n_r = max(1, len({s_["R"] for s_ in states})) if states else 1
        n_q = max(1, len(pcols) // n_r)
        rec = Recognition(stored, n_q, n_r)
    t = rec.table
    rmap = RecognitionMap(t["easting_km"].to_numpy(float), t["northing_km"].to_numpy(float), max_rho_km=15.0)
    nl = ident.get("nlmeans", {})
    coords = {"easting_km": _clean(t["easting_km"], 3), "northing_km": _clean(t["northing_km"], 3),
              "line": t["line"].astype(str).tolist(), "state_raw": t["state_raw"].astype(int).tolist(),
              "time": _clean(t["time"], 2) if "time" in t else None}
    return {"recognition": rec, "map": rmap, "stored_state": stored["state_smoothed"].to_numpy(int),
            "stored_pmax": stored[pcols].to_numpy(float).max(axis=1) if pcols else np.ones(len(stored)),
            "h": nl.get("h_per_km"), "rho": nl.get("rho_km"), "mode": nl.get("mode", "soft"),
            "states": states, "coords": coords, "n": len(t), "n_states": rec.n_states}


def smoothed_map(views: ResultCache, r: Result, rec: dict[str, Any], h: float, rho: float,
                 mode: str) -> dict[str, np.ndarray]:
    """``{state, p_max}`` of the result's recognition map smoothed at (h, ρ, mode) by the pipeline's
    :func:`state_map`, kept in ``views`` by (result id, result folder, h, ρ, mode): NL-means runs once
    per setting among the last ones asked for (concurrent identical requests wait for the first one),
    and a new result — a new id and folder — never gets another's map."""
    def build() -> dict[str, np.ndarray]:
        smap = state_map(rec["recognition"], h, rho, mode, rmap=rec["map"])
        return {"state": np.asarray(smap.states).astype(np.int32), "p_max": np.asarray(smap.probs.max(axis=1))}
    return views.get(("recognition_view", r.id, r.dir, float(h), float(rho), mode), build)


# ---------------------------------------------------------------- endpoints
@router.get("/{survey_id}/lines", response_model=list[LineOut])
def list_lines(s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
               cache: ResultCache = Depends(get_cache)) -> list[LineOut]:
    """Survey lines with QC and, once processed, statistics of the final anomaly (mGal)."""
    groups: dict = {}
    if s.current_result_id is not None:
        try:
            r = current_result(s, db)
            groups = cache.get(("lines", r.id), lambda: _load_lines(r))["groups"]
        except HTTPException:
            groups = {}
    out = []
    for l in s.lines:
        stats = None
        g = groups.get(l.line)
        if g is not None and len(g):
            dg = g["dg_mgal"].to_numpy(float)
            stats = {"n": int(len(g)), "dg_mean_mgal": _clean([np.nanmean(dg)])[0],
                     "dg_std_mgal": _clean([np.nanstd(dg)])[0], "dg_min_mgal": _clean([np.nanmin(dg)])[0],
                     "dg_max_mgal": _clean([np.nanmax(dg)])[0],
                     "sigma_mean_mgal": _clean([np.nanmean(g["dg_std_mgal"])])[0] if "dg_std_mgal" in g else None}
        out.append(LineOut(id=l.id, line=l.line, flight=l.flight, kind=l.kind, t_start=l.t_start, t_end=l.t_end,
                           qc=l.qc or {}, stats=stats))
    return out


#: ProfileOut field ← lines.parquet product column (app.pipeline.stages.outputs.PRODUCT_COLUMNS and h)
PROFILE_PRODUCTS = {"height_m": "h", "atm_corr": "atm_corr_mgal", "dg_flight": "dg_flight_mgal",
                    "dg_flight_std": "dg_flight_std_mgal", "dg_datum": "dg_datum_mgal",
                    "dg_datum_std": "dg_datum_std_mgal", "datum_height_m": "datum_height_m",
                    "terrain": "terrain_mgal", "terrain_height_m": "terrain_height_m",
                    "dg_bouguer": "dg_bouguer_mgal"}


@router.get("/{survey_id}/lines/{line:path}", response_model=ProfileOut)
def line_profile(line: str, max_points: int = Query(2000, ge=50, le=50000, description="decimate to about this many points"),
                 z_lowpass_s: float = Query(30.0, ge=0, le=600, description="Gaussian low-pass of z, full width at half maximum (s)"),
                 s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
                 cache: ResultCache = Depends(get_cache)) -> ProfileOut:
    """Profile series of one line: z low-passed, final δg ± σ, stationary, FIR, state (decimated), and
    the product columns the result has (flight height, atmospheric correction, δg at flight height and
    at the datum, terrain effect, Bouguer anomaly; null when absent)."""
    r = current_result(s, db)
    groups = cache.get(("lines", r.id), lambda: _load_lines(r))["groups"]
    g = groups.get(line)
    if g is None:
        shown = line if len(line) <= 100 else line[:100] + '…'
        raise HTTPException(404, f"line {shown!r} not in the results of survey {s.id}")
    n = len(g)
    t = g["time"].to_numpy(float)
    e, nn = g["easting_km"].to_numpy(float), g["northing_km"].to_numpy(float)
    dist = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(e), np.diff(nn)))])
    dt = float(np.median(np.diff(t))) if n > 1 else 0.1
    z = gaussian_lowpass(g["z_mgal"].to_numpy(float), dt, z_lowpass_s)
    step = max(1, math.ceil(n / max_points))
    sl = slice(None, None, step)

    def col(name):
        return _clean(g[name].to_numpy(float)[sl]) if name in g else [None] * len(t[sl])

    return ProfileOut(
        survey_id=s.id, line=line, flight=str(g["flight"].iloc[0]) if "flight" in g else "",
        kind=str(g["kind"].iloc[0]) if "kind" in g else "", n_total=n, step=step, z_lowpass_s=z_lowpass_s,
        time=_clean(t[sl], 2), distance_km=_clean(dist[sl], 4), z_lowpassed=_clean(z[sl]),
        dg=col("dg_mgal"), dg_std=col("dg_std_mgal"), dg_stationary=col("dg_stationary_mgal"),
        dg_fir=col("dg_fir_mgal"), dg_unleveled=col("dg_unleveled_mgal"),
        state=_ints(g["state"].to_numpy()[sl]) if "state" in g else [None] * len(t[sl]),
        **{k: _clean(g[c].to_numpy(float)[sl]) for k, c in PROFILE_PRODUCTS.items() if c in g},
    )


def _repeat_tracks(s: Survey, r: Result, cache: ResultCache) -> tuple[dict, dict, dict]:
    """(lines.parquet groups, report.json, {track: [line, …]}) of the current result."""
    groups = cache.get(("lines", r.id), lambda: _load_lines(r))["groups"]
    rep = cache.get(("report", r.id), lambda: _load_report(r))["report"]
    members = track_members([(l.line, l.kind, (l.qc or {}).get("track")) for l in s.lines], rep, set(groups))
    return groups, rep, members


@router.get("/{survey_id}/repeat-tracks", response_model=RepeatTracksOut)
def repeat_tracks(s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
                  cache: ResultCache = Depends(get_cache)) -> RepeatTracksOut:
    """The repeat tracks of the current result with two or more passes, their lines and the
    internal accuracy report.json gives them."""
    r = current_result(s, db)
    _, rep, members = _repeat_tracks(s, r, cache)
    acc = rep.get("repeat_lines") if isinstance(rep.get("repeat_lines"), dict) else {}
    return RepeatTracksOut(survey_id=s.id, result_id=r.id, tracks=[
        {"track": t, "lines": m, "internal_accuracy_mgal": (acc.get(t) or {}).get("internal_accuracy_mgal")}
        for t, m in members.items()])


@router.get("/{survey_id}/repeat-tracks/{track:path}", response_model=RepeatTrackOut)
def repeat_track(track: str, max_points: int = Query(1500, ge=50, le=50000, description="decimate each pass to "
                                                     "about this many points"),
                 s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
                 cache: ResultCache = Depends(get_cache)) -> RepeatTrackOut:
    """Every pass of a repeat track on one along-track axis (distance along the track's principal
    direction from one origin, so passes flown the other way overlay), with δg ± σ, stationary and
    FIR per pass and the track's repeatability figures from report.json."""
    r = current_result(s, db)
    groups, rep, members = _repeat_tracks(s, r, cache)
    if track not in members:
        shown = track if len(track) <= 100 else track[:100] + '…'
        raise HTTPException(404, f"no repeat track {shown!r} with two or more passes in the results of survey {s.id}")
    body = track_passes(track, members[track], groups, rep, max_points)
    return RepeatTrackOut(survey_id=s.id, result_id=r.id, **body)


@router.get("/{survey_id}/recognition", response_model=RecognitionOut, response_model_exclude_none=True)
def recognition(h: float | None = Query(None, ge=0, le=100, description="NL-means weight decay h (1/km); "
                                        "without h and ρ: the current result's stored map"),
                rho: float | None = Query(None, ge=0, le=15, description="NL-means radius ρ (km), at most 15"),
                mode: Literal["hard", "soft"] | None = Query(None, description="smooth hard labels or probabilities"),
                coords: bool = Query(True, description="include positions, lines and raw states"),
                s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
                cache: ResultCache = Depends(get_cache), views: ResultCache = Depends(get_views)) -> RecognitionOut:
    """The recognition state map at (h, ρ): the raw posteriors smoothed by NL-means and the
    state chosen at every point by the pipeline's own function
    (:func:`app.pipeline.stages.recognition.state_map`) — the map a ``filter`` job with these
    values uses.  Without h and ρ: the current result's map, with the (h, ρ) it was made with.
    The last maps asked for are kept (:func:`smoothed_map`): a repeated setting is not smoothed again."""
    t0 = time.perf_counter()
    r = current_result(s, db)
    rec = cache.get(("recognition", r.id), lambda: _load_recognition(r))
    if h is None and rho is None and mode is None and rec["h"] is not None:
        h, rho, mode = float(rec["h"]), float(rec["rho"]), rec["mode"]
        state, pmax = rec["stored_state"], rec["stored_pmax"]
    else:
        h = 0.5 if h is None else h
        rho = 10.0 if rho is None else rho
        mode = mode or "soft"
        view = smoothed_map(views, r, rec, h, rho, mode)
        state, pmax = view["state"], view["p_max"]
    body = {"survey_id": s.id, "result_id": r.id, "h": h, "rho": rho, "mode": mode, "n_states": rec["n_states"],
            "states": rec["states"], "n_points": rec["n"], "smoother": "app.pipeline.stages.recognition.state_map",
            "state": np.asarray(state).astype(int).tolist(), "p_max": _clean(pmax, 3)}
    if coords:
        body.update(rec["coords"])
    body["elapsed_ms"] = round(1000 * (time.perf_counter() - t0), 2)
    return RecognitionOut(**body)


_finite = finite_float


def _load_report(r: Result) -> dict[str, Any]:
    """report.json (the database copy when the file is missing), identification.json's summary and
    the per-line adaptive − FIR differences."""
    p = Path(r.dir) / "report.json"
    try:
        rep = json.loads(p.read_text(encoding="utf-8")) if p.exists() else (r.report or {})
    except (OSError, ValueError):
        rep = r.report or {}
    if not isinstance(rep, dict):
        rep = {"report": rep}
    ident = _load_identification(r)
    em = ident.get("em") or {}
    iters = em.get("iterations") or []
    identification = {k: ident[k] for k in ("states", "transition", "lines_skipped", "lines_learned", "m", "units")
                      if k in ident}
    identification["em"] = {"selection": em.get("selection"), "model": em.get("model"),
                            "converged": em.get("converged"), "loglik": em.get("loglik"),
                            "n_iterations": len(iters), "final": iters[-1] if iters else None}
    diffs = []
    lp = Path(r.dir) / "lines.parquet"
    if lp.exists():
        import pyarrow.parquet as pq
        have = set(pq.read_schema(lp).names)
        # both estimates before leveling: the difference is then filtering alone
        a = "dg_unleveled_mgal" if "dg_unleveled_mgal" in have else "dg_mgal"
        cols = [c for c in ("line", "flight", "kind", "time", a, "dg_fir_mgal") if c in have]
        if "dg_fir_mgal" in have and a in have:
            df = pd.read_parquet(lp, columns=cols)
            df["line"] = df["line"].astype(str)
            df["_d"] = df[a].to_numpy(float) - df["dg_fir_mgal"].to_numpy(float)
            for line, g in df.groupby("line", sort=False):
                d = g["_d"].to_numpy()
                d = d[np.isfinite(d)]
                diffs.append({"line": str(line), "flight": str(g["flight"].iloc[0]) if "flight" in g else "",
                              "kind": str(g["kind"].iloc[0]) if "kind" in g else "", "n": int(d.size),
                              "rms_mgal": _finite(np.sqrt(np.mean(d ** 2))) if d.size else None,
                              "mean_mgal": _finite(np.mean(d)) if d.size else None,
                              "std_mgal": _finite(np.std(d)) if d.size else None})
    crossovers = []
    cx = Path(r.dir) / "crossovers.csv"
    if cx.exists():
        c = pd.read_csv(cx, dtype={"line_a": str, "line_b": str})
        for col in c.columns:
            if c[col].dtype.kind == "f":
                c[col] = c[col].round(4)
        crossovers = to_jsonable(c)
    warnings = [str(w) for w in rep.get("warnings") or []] if isinstance(rep.get("warnings"), list) else []
    xo = rep.get("crossovers") if isinstance(rep.get("crossovers"), dict) else {}
    return {"warnings": warnings, "leveled": xo.get("status") == "leveled", "leveling_status": xo.get("status"),
            "absolute_base_tie": not any(w.startswith("no absolute base tie") for w in warnings),
            "adaptive_minus_fir": diffs, "crossovers": crossovers, "identification": identification, "report": rep}


@router.get("/{survey_id}/report", response_model=ReportOut,
            responses={404: {"description": "no such survey, or no result yet"}})
def report(s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
           cache: ResultCache = Depends(get_cache)) -> ReportOut:
    """The current result's report: every warning and automatic decision (base ties, time offsets, lag
    check, spike repair, leveling F-test, crossovers, noise model, model order, identification, repeat
    lines), with the per-line RMS of adaptive − FIR computed from lines.parquet."""
    r = current_result(s, db)
    body = cache.get(("report", r.id), lambda: _load_report(r))
    return ReportOut(survey_id=s.id, result_id=r.id, job_id=r.job_id, **body)


# ---------------------------------------------------------------- product grids
PRODUCTS = ("free_air", "bouguer")
HEIGHTS = ("flight", "datum")
GRID_EXT = {"geotiff": ".tif", "netcdf": ".nc", "surfer": ".grd", "csv": ".csv"}


def _datum_of(r: Result) -> dict | None:
    """report.json ``products.datum`` when the result was continued to a datum, else None."""
    prods = (r.report or {}).get("products")
    datum = prods.get("datum") if isinstance(prods, dict) else None
    return datum if isinstance(datum, dict) and datum.get("datum") in ("constant", "draped") else None


def _no_dem_reason(s: Survey, r: Result) -> str:
    prods = (r.report or {}).get("products")
    terrain = prods.get("terrain") if isinstance(prods, dict) else None
    used = isinstance(terrain, dict) and terrain.get("dem")
    if not used and not has_dem(s):
        return (f"survey {s.id} has no DEM (dem.tif): the Bouguer anomaly needs a terrain model; add one "
                f"(PUT /api/surveys/{s.id}/dem, or dem.tif beside survey.toml in an imported zip) and process again")
    if not used:
        return "the current result was computed without the survey's DEM (added since): process the survey again"
    return "the current result has no Bouguer grid (the terrain correction ran, the gridding did not: see the warnings)"


def grid_files(s: Survey, r: Result) -> tuple[dict[tuple[str, str], str | None], dict[str, str]]:
    """The grid file stem of every (product, height) of a result (None when there is none) and why
    the missing ones are missing (``'<product>@<height>'``).

    Without a datum ``grid.*`` and ``grid_bouguer.*`` are at flight height; with one ``grid.*`` and
    ``grid_bouguer.*`` are at the datum and ``grid_flight.*`` is the free-air grid at flight height
    (the Bouguer anomaly exists at the datum only: the terrain effect was evaluated there)."""
    d = Path(r.dir)
    there = {stem: (d / f"{stem}.nc").exists() for stem in ("grid", "grid_bouguer", "grid_flight")}
    datum = _datum_of(r)
    if datum is None:
        want = {("free_air", "flight"): "grid", ("bouguer", "flight"): "grid_bouguer",
                ("free_air", "datum"): None, ("bouguer", "datum"): None}
    else:
        want = {("free_air", "datum"): "grid", ("bouguer", "datum"): "grid_bouguer",
                ("free_air", "flight"): "grid_flight", ("bouguer", "flight"): None}
    files, why = {}, {}
    for (product, height), stem in want.items():
        files[(product, height)] = stem if stem is not None and there[stem] else None
        if files[(product, height)] is not None:
            continue
        key = f"{product}@{height}"
        if datum is None and height == "datum":
            why[key] = ("no datum was used (processing.datum = 'flight'): the values are at flight height; set "
                        "datum = 'constant' or 'draped' and process again to continue them to a common datum")
        elif product == "bouguer" and not there["grid_bouguer"]:
            why[key] = _no_dem_reason(s, r)
        elif product == "bouguer":
            why[key] = ("with a datum the Bouguer anomaly is given at the datum only (the terrain effect is "
                        "evaluated there); its line values at flight height are not computed")
        elif stem == "grid_flight":
            why[key] = "the current result has no flight-height grid (grid_flight.nc): process the survey again"
        else:
            why[key] = f"{stem}.nc is not among the stored results"
    return files, why


def _grid_stem(s: Survey, r: Result, product: str, height: str | None) -> tuple[str, str]:
    """(file stem, height) of the grid asked for; 404 naming why when the result has none.  Without
    ``height``: the height the result's values are given at (the datum when one was used)."""
    height = height or ("datum" if _datum_of(r) is not None else "flight")
    files, why = grid_files(s, r)
    stem = files[(product, height)]
    if stem is None:
        if not (Path(r.dir) / "grid.nc").exists():
            _result_file(r, "grid.nc")          # an identification or a result without grid: that message
        raise HTTPException(404, f"no {product.replace('_', '-')} grid at {height} height: {why[f'{product}@{height}']}")
    return stem, height


def _load_grid(r: Result, stem: str = "grid") -> dict[str, Any]:
    import xarray as xr
    with xr.open_dataset(_result_file(r, f"{stem}.nc")) as ds:
        ds = ds.load()
    dg = ds["dg"]
    ydim, xdim = dg.dims[-2], dg.dims[-1]
    # grid.nc: x/y in the CRS's unit with easting_km/northing_km beside them (older results: km only)
    e = ds["easting_km"].values if "easting_km" in ds.coords else ds[xdim].values / 1000.0
    n = ds["northing_km"].values if "northing_km" in ds.coords else ds[ydim].values / 1000.0
    out = {"easting_km": _clean(e, 4), "northing_km": _clean(n, 4),
           "dg": [_clean(row, 3) for row in dg.values],
           "dg_std": [_clean(row, 3) for row in ds["dg_std"].values] if "dg_std" in ds else None,
           "crs": ds.attrs.get("crs") or (ds["crs"].attrs.get("crs_wkt") if "crs" in ds else None)}
    lines_path = Path(r.dir) / "lines.parquet"
    tracks = []
    if lines_path.exists():
        df = pd.read_parquet(lines_path, columns=["line", "kind", "easting_km", "northing_km", "time"])
        for name, g in df.groupby("line", sort=False):
            g = g.sort_values("time")
            step = max(1, len(g) // 200)
            tracks.append({"line": str(name), "kind": str(g["kind"].iloc[0]),
                           "easting_km": _clean(g["easting_km"].to_numpy()[::step], 3),
                           "northing_km": _clean(g["northing_km"].to_numpy()[::step], 3)})
    out["lines"] = tracks
    cx = Path(r.dir) / "crossovers.csv"
    if cx.exists():
        out["crossovers"] = to_jsonable(pd.read_csv(cx))
    else:
        out["crossovers"] = []
    return out


@router.get("/{survey_id}/grid", response_model=GridOut,
            responses={404: {"description": "no such survey, no result yet, or no grid of this product and "
                                            "height (the detail says why, e.g. the survey has no DEM)"}})
def grid(product: Literal["free_air", "bouguer"] = Query("free_air", description="free_air (δg) or bouguer "
                                                           "(δg − terrain effect of the survey's DEM)"),
         height: Literal["flight", "datum"] | None = Query(None, description="flight (the flight height) or datum "
                                                           "(continued to processing.datum); default: the "
                                                           "height the result's values are given at"),
         s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
         cache: ResultCache = Depends(get_cache)) -> GridOut:
    """Anomaly grid (free-air δg or the Bouguer anomaly, at flight height or at the datum) and its
    posterior σ (mGal) with lines and crossovers for overlays; ``available``/``unavailable`` say
    which other grids the result has and why the others are missing."""
    r = current_result(s, db)
    stem, height = _grid_stem(s, r, product, height)
    g = cache.get((stem, r.id), lambda: _load_grid(r, stem))   # (name, result id): dropped with the survey
    files, why = grid_files(s, r)
    available = {pr: {h: files[(pr, h)] is not None for h in HEIGHTS} for pr in PRODUCTS}
    return GridOut(survey_id=s.id, result_id=r.id, **g, report=r.report or {}, product=product, height=height,
                   datum=_datum_of(r), available=available, unavailable=why)


def _lines_xyz(s: Survey, r: Result, store: Store) -> Path:
    """``lines.xyz`` of a result (Geosoft XYZ line data), written beside lines.parquet on first use
    (404 naming lines.parquet when the result has none).

    Concurrent first requests: the file is written atomically (``write_lines_xyz`` writes a
    temporary file in the result folder and renames it into place), so no request — in this
    process or another sharing the data directory — ever serves a part of it; and it is written
    once, under the survey's lock (:meth:`Store.survey_lock`, which also keeps a prune from
    removing the result folder meanwhile): the other requests wait and serve it, instead of
    each reading the whole lines.parquet and writing a copy of its own."""
    from app.io.export import write_lines_xyz

    p = Path(r.dir) / "lines.xyz"
    if p.exists():
        return p
    src = _result_file(r, "lines.parquet")
    with store.survey_lock(s.id):
        if not p.exists():
            crs = (r.report or {}).get("crs") or s.crs
            write_lines_xyz(p, pd.read_parquet(src), crs,
                            comments=(f"Aerograv line data: survey {s.name[:100]!r}, result {r.id}",))
    return p


@router.get("/{survey_id}/export")
def export(format: Literal["geotiff", "netcdf", "surfer", "csv", "parquet", "xyz", "crossovers", "report"] = Query(
               ..., description="geotiff, netcdf, surfer (grids: x/y in metres of the CRS), csv (grid), "
               "parquet or xyz (line data with every product column; xyz = Geosoft XYZ with X/Y in metres), "
               "crossovers, report"),
           product: Literal["free_air", "bouguer"] = Query("free_air", description="grids: free_air or bouguer"),
           height: Literal["flight", "datum"] | None = Query(None, description="grids: flight or datum (default: "
                                                             "the height the result's values are given at)"),
           s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
           store: Store = Depends(get_store)):
    """Download a stored output of the current result (grids: the product and height asked for,
    404 naming why when the result has none)."""
    r = current_result(s, db)
    fname, media = EXPORTS[format]
    if format in GRID_EXT and (product != "free_air" or height is not None):
        fname = _grid_stem(s, r, product, height)[0] + GRID_EXT[format]
    p = _lines_xyz(s, r, store) if format == "xyz" else _result_file(r, fname)
    safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in s.name)
    return FileResponse(p, media_type=media, filename=f"{safe}_{fname}")
