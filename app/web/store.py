"""File side of the store: survey input snapshots, atomic imports, QC, cached results.

Layout under the data directory::

    surveys/<survey_id>/input/<uuid>/          an immutable, validated input snapshot
    surveys/<survey_id>/results/job-<job_id>/  the outputs of one job (SPEC §5)
    tmp/                                       staging (same filesystem: renames are atomic)

New files are staged in ``tmp/``, validated with ``read_survey`` and only then renamed
into place; the database pointer (``Survey.input_dir``) is switched afterwards in one
transaction.  A rejected upload leaves nothing behind.
"""

from __future__ import annotations

import os
import re
import threading
import uuid
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable

import numpy as np

from app.io.errors import InputError

SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,99}$")


class Store:
    def __init__(self, data_dir: Path):
        self.root = Path(data_dir).resolve()
        self.tmp = self.root / "tmp"
        self.tmp.mkdir(parents=True, exist_ok=True)
        (self.root / "surveys").mkdir(parents=True, exist_ok=True)

    def staging_dir(self) -> Path:
        d = self.tmp / uuid.uuid4().hex
        d.mkdir(parents=True)
        return d

    def survey_dir(self, survey_id: int) -> Path:
        return self.root / "surveys" / str(survey_id)

    def new_input_dir(self, survey_id: int) -> Path:
        d = self.survey_dir(survey_id) / "input"
        d.mkdir(parents=True, exist_ok=True)
        return d / uuid.uuid4().hex

    def job_out_dir(self, survey_id: int, job_id: int) -> Path:
        d = self.survey_dir(survey_id) / "results"
        d.mkdir(parents=True, exist_ok=True)
        return d / f"job-{job_id}"

    def commit_dir(self, staged: Path, final: Path) -> Path:
        final.parent.mkdir(parents=True, exist_ok=True)
        os.replace(staged, final)
        return final


def relativize(err: InputError, root: Path) -> InputError:
    """Report file names relative to the survey directory, not the staging path."""
    if err.file:
        try:
            rel = Path(err.file).resolve().relative_to(Path(root).resolve())
            err = InputError(rel.as_posix(), err.row, err.column, err.message)
        except ValueError:
            pass
    return err


def extract_survey_zip(fileobj, dest: Path, max_bytes: int | None = None) -> Path:
    """Extract a zip safely into ``dest`` (no absolute or '..' paths, bounded uncompressed size);
    return the survey root (possibly nested one level)."""
    try:
        zf = zipfile.ZipFile(fileobj)
    except zipfile.BadZipFile:
        raise InputError("upload", None, None, "not a zip archive")
    with zf:
        total = sum(i.file_size for i in zf.infolist())
        if max_bytes is not None and total > max_bytes:
            raise InputError("upload", None, None, f"the archive expands to {total / 2**20:.0f} MB, more than the "
                             f"{max_bytes / 2**20:.0f} MB allowed")
        for info in zf.infolist():
            name = info.filename
            if name.startswith("__MACOSX/") or name.endswith(".DS_Store"):
                continue
            p = Path(name)
            if p.is_absolute() or ".." in p.parts:
                raise InputError(name, None, None, "unsafe path in the zip archive")
            zf.extract(info, dest)
    if (dest / "survey.toml").is_file():
        return dest
    subdirs = [d for d in dest.iterdir() if d.is_dir() and d.name != "__MACOSX"]
    candidates = [d for d in subdirs if (d / "survey.toml").is_file()]
    if len(candidates) == 1:
        return candidates[0]
    raise InputError("survey.toml", None, None,
                     "the zip must contain a survey directory: survey.toml at the top level or in one folder")


def _gaps(t: np.ndarray) -> tuple[float, float]:
    """(mean sampling interval, longest interval); the mean, not the median: time stamps are
    rounded, so the median step of an 18.24 Hz file reads as 0.055 s (18.18 Hz)."""
    if t.size < 2:
        return float("nan"), float("nan")
    dt = np.diff(t)
    return float((t[-1] - t[0]) / (t.size - 1)), float(dt.max())


def _length_km(lat: np.ndarray, lon: np.ndarray) -> float:
    if lat.size < 2:
        return 0.0
    phi = np.deg2rad(lat)
    dy = np.diff(phi) * 6371.0
    dx = np.diff(np.deg2rad(lon)) * 6371.0 * np.cos(0.5 * (phi[1:] + phi[:-1]))
    return float(np.hypot(dx, dy).sum())


def _round_list(a, nd: int = 3) -> list:
    a = np.round(np.asarray(a, float), nd)
    return [None if not np.isfinite(v) else float(v) for v in a]


def _f(x: float, nd: int = 4) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def survey_qc(survey, track_points: int = 150) -> tuple[dict[str, dict], list[dict]]:
    """Per-flight and per-line QC from a validated ``Survey`` (rates, gaps, duration, length),
    plus each line's decimated track in the survey CRS (km) for the line map."""
    from app.core.geodesy import project_km, utm_crs_for

    crs = getattr(getattr(getattr(survey, "config", None), "survey", None), "crs", None)
    if not crs:
        g0 = next(iter(survey.flights.values())).gnss if survey.flights else None
        crs = utm_crs_for(g0["lon"], g0["lat"]) if g0 is not None and len(g0) else "EPSG:4326"
    flights: dict[str, dict] = {}
    for name, fl in survey.flights.items():
        tg = np.asarray(fl.gravimeter["time"], float)
        tn = np.asarray(fl.gnss["time"], float)
        mg, xg = _gaps(tg)
        mn, xn = _gaps(tn)
        flights[str(name)] = {
            "gravimeter_samples": int(tg.size), "gnss_samples": int(tn.size),
            "gravimeter_rate_hz": _f(1.0 / mg if mg else np.nan, 3), "gnss_rate_hz": _f(1.0 / mn if mn else np.nan, 3),
            "gravimeter_max_gap_s": _f(xg, 3), "gnss_max_gap_s": _f(xn, 3),
            "t_start": _f(min(tg.min(), tn.min()), 3) if tg.size and tn.size else None,
            "t_end": _f(max(tg.max(), tn.max()), 3) if tg.size and tn.size else None,
            "duration_s": _f(max(tg.max(), tn.max()) - min(tg.min(), tn.min()), 2) if tg.size and tn.size else None,
            "length_km": _f(_length_km(np.asarray(fl.gnss["lat"], float), np.asarray(fl.gnss["lon"], float)), 2),
        }
    lines: list[dict] = []
    for row in survey.lines.itertuples(index=False):
        fl = survey.flights.get(row.flight)
        q: dict[str, Any] = {"duration_s": _f(row.t_end - row.t_start, 2)}
        map_track: dict = {}
        if fl is not None:
            g = fl.gnss
            m = (g["time"] >= row.t_start) & (g["time"] <= row.t_end)
            tn = np.asarray(g["time"][m], float)
            med, mx = _gaps(tn)
            tg = np.asarray(fl.gravimeter["time"], float)
            tg = tg[(tg >= row.t_start) & (tg <= row.t_end)]
            gmed, gmx = _gaps(tg)
            length = _length_km(np.asarray(g["lat"][m], float), np.asarray(g["lon"][m], float))
            step = max(1, int(m.sum()) // track_points)
            try:
                e, n = project_km(g["lon"][m].to_numpy()[::step], g["lat"][m].to_numpy()[::step], crs)
                map_track = {"easting_km": _round_list(e), "northing_km": _round_list(n), "crs": crs}
            except Exception:  # pragma: no cover - bad CRS string: no map, QC still shown
                map_track = {}
            q.update({
                "gnss_samples": int(tn.size), "gnss_rate_hz": _f(1.0 / med if med else np.nan, 3),
                "gnss_max_gap_s": _f(mx, 3), "gravimeter_samples": int(tg.size),
                "gravimeter_rate_hz": _f(1.0 / gmed if gmed else np.nan, 3), "gravimeter_max_gap_s": _f(gmx, 3),
                "length_km": _f(length, 2),
                "speed_ms": _f(1000.0 * length / (row.t_end - row.t_start) if row.t_end > row.t_start else np.nan, 1),
                "mean_h_m": _f(float(np.mean(g["h"][m])) if tn.size else np.nan, 1),
            })
        track = getattr(row, "track", None)
        lines.append({"line": str(row.line), "flight": str(row.flight), "kind": str(row.kind),
                      "track": None if track is None or (isinstance(track, float) and np.isnan(track)) else str(track),
                      "t_start": float(row.t_start), "t_end": float(row.t_end), "qc": q, "map_track": map_track})
    return flights, lines


class ResultCache:
    """Small LRU of loaded result objects (DataFrames, grids, recognition maps) per key."""

    def __init__(self, size: int = 16):
        self.size = size
        self._d: OrderedDict = OrderedDict()
        self._lock = threading.Lock()
        self._key_locks: dict[Any, threading.Lock] = {}

    def get(self, key, build: Callable[[], Any]):
        with self._lock:
            if key in self._d:
                self._d.move_to_end(key)
                return self._d[key]
            kl = self._key_locks.setdefault(key, threading.Lock())
        with kl:  # build once even under concurrent requests
            with self._lock:
                if key in self._d:
                    return self._d[key]
            val = build()
            with self._lock:
                self._d[key] = val
                while len(self._d) > self.size:
                    self._d.popitem(last=False)
                self._key_locks.pop(key, None)
            return val
