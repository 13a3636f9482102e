"""Read and validate a survey directory (SPEC §4, docs/CONTRACTS.md).

::

    <survey>/survey.toml
    <survey>/lines.csv
    <survey>/flights/<flight>/gravimeter.csv[.gz]   (or gravimeter.g, *.G, G*.dat)
    <survey>/flights/<flight>/gnss.csv[.gz]

Every problem raises :class:`app.io.errors.InputError` naming the file (relative
to the survey directory, POSIX separators), the 1-based line number in the file
(header = 1) and the column.
"""

from __future__ import annotations

import re
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from pydantic import ValidationError

from app.config import SurveyConfig, check_name
from app.core.geodesy import radii_of_curvature_m
from app.io.errors import InputError
from app.io.gfile import is_gfile_name, read_gfile
from app.io.tables import (check_file_size, check_finite, check_range, check_rate, check_time_increasing,
                           fill_short_nan_runs, gap_rows_in_windows, median_rate_hz, read_csv_table)

__all__ = ["Flight", "Survey", "read_survey", "read_config", "read_lines", "read_gravimeter", "read_gnss",
           "survey_summary", "path_length_km", "LINE_KINDS"]

LINE_KINDS = ("main", "tie", "repeat")
GRAV_REQUIRED = ("time", "f_z")
GRAV_OPTIONAL = ("f_x", "f_y")
GNSS_REQUIRED = ("time", "lat", "lon", "h", "vu")
GNSS_OPTIONAL = ("ve", "vn", "sigma_v")
#: plausible median |f_z| (m/s²) of a gravimeter file in m/s² with Z up
F_Z_PLAUSIBLE_MS2 = (7.0, 13.0)
#: every value must lie in these ranges (wider than any flight: a value outside is a unit or file
#: error, reported with its row before it can overflow the processing)
VALUE_RANGES = {"time": (-1e10, 1e10, "time (s)"), "f_z": (-100.0, 100.0, "specific force (m/s²)"),
                "f_x": (-100.0, 100.0, "specific force (m/s²)"), "f_y": (-100.0, 100.0, "specific force (m/s²)"),
                "h": (-1000.0, 100_000.0, "ellipsoidal height (m)"), "vu": (-1000.0, 1000.0, "velocity (m/s)"),
                "ve": (-1000.0, 1000.0, "velocity (m/s)"), "vn": (-1000.0, 1000.0, "velocity (m/s)"),
                "sigma_v": (0.0, 1000.0, "velocity std (m/s)")}


@dataclass
class Flight:
    """One flight: gravimeter and GNSS tables on the survey time scale.

    ``gravimeter``: DataFrame[time, f_z, (f_x, f_y)] (s, m/s²).
    ``gnss``: DataFrame[time, lat, lon, h, vu, (ve, vn, sigma_v)] (s, deg, m, m/s).
    """

    name: str
    gravimeter: pd.DataFrame
    gnss: pd.DataFrame
    gravimeter_path: Path
    gnss_path: Path


@dataclass
class Survey:
    """A validated survey directory.

    ``lines``: DataFrame[line (str), flight (str), t_start, t_end (float s), kind, track (str or None)].
    """

    root: Path
    config: SurveyConfig
    lines: pd.DataFrame
    flights: dict[str, Flight] = field(default_factory=dict)


# --------------------------------------------------------------------------- survey.toml


def _toml_key_row(text: str, loc: tuple) -> int | None:
    """Line number of ``key`` in table ``[section]`` of a TOML text (best effort)."""
    if len(loc) == 1:  # an unknown or bad table: point at its header
        for i, line in enumerate(text.splitlines(), start=1):
            if re.match(rf"^\[\s*\"?{re.escape(str(loc[0]))}\"?\s*\]", line.strip()):
                return i
        return None
    if len(loc) < 2:
        return None
    section, key = str(loc[0]), str(loc[1])
    current = None
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        m = re.match(r"^\[\s*([^\]]+?)\s*\]", s)
        if m:
            current = m.group(1).strip().strip('"')
            continue
        if current == section and re.match(rf'^"?{re.escape(key)}"?\s*=', s):
            return i
    return None


def read_config(path, overrides: dict | None = None, display: str = "survey.toml") -> SurveyConfig:
    """Parse ``survey.toml`` into :class:`SurveyConfig`, ``overrides`` merged over ``[processing]``.

    Raises
    ------
    InputError
        TOML syntax error (with its line), or a validation error naming the
        key as ``section.key`` (file ``survey.toml``, or ``overrides`` when the
        bad value came from the overrides).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(display, None, None, "file not found (every survey needs a survey.toml)")
    text = path.read_text(encoding="utf-8", errors="replace")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"line (\d+)", str(exc))
        raise InputError(display, int(m.group(1)) if m else None, None, f"not valid TOML: {exc}") from None
    except RecursionError:
        raise InputError(display, None, None, "not valid TOML: nested too deeply") from None
    overrides = dict(overrides or {})
    if overrides:
        proc = data.get("processing", {})
        if not isinstance(proc, dict):
            raise InputError(display, None, "processing", "[processing] must be a table")
        data["processing"] = {**proc, **overrides}
    try:
        return SurveyConfig.model_validate(data)
    except ValidationError as exc:
        e = exc.errors()[0]
        loc = tuple(e.get("loc", ()))
        key = ".".join(str(x) for x in loc) or None
        value = _short(e.get("input"))
        msg = e.get("msg", "invalid value")
        if e.get("type") == "extra_forbidden":
            msg = "unknown setting"
        if len(loc) >= 2 and loc[0] == "processing" and loc[1] in overrides:
            raise InputError("overrides", None, key, f"{msg} (got {value!r})") from None
        detail = f"{msg} (got {value!r})" if e.get("type") != "extra_forbidden" else msg
        raise InputError(display, _toml_key_row(text, loc), key, detail) from None


class _Short:
    """A value shown in an error message, its repr cut to ~80 characters."""

    def __init__(self, v):
        self.r = repr(v)

    def __repr__(self) -> str:
        return self.r if len(self.r) <= 80 else f"{self.r[:60]}… ({len(self.r)} characters)"


def _short(v):
    return v if isinstance(v, (int, float, bool, type(None))) else _Short(v)


# --------------------------------------------------------------------------- lines.csv


def read_lines(path, display: str = "lines.csv") -> tuple[pd.DataFrame, np.ndarray]:
    """Read and check ``lines.csv`` (columns, numbers, kinds, t_end > t_start, unique ids).

    Returns
    -------
    lines : DataFrame[line, flight, t_start, t_end, kind, track]
    rows : ndarray of int
        File line number of each line.
    """
    df, rows = read_csv_table(path, display, ("line", "flight", "t_start", "t_end", "kind"), ("track",),
                              str_cols=("line", "flight", "kind", "track"), min_rows=1)
    # blank lines inside lines.csv are harmless: drop them
    keep = ~df.isna().all(axis=1).to_numpy()
    df, rows = df.loc[keep].reset_index(drop=True), rows[keep]
    if len(df) == 0:
        raise InputError(display, None, None, "no survey lines listed")
    for col in ("line", "flight", "kind"):
        s = df[col].fillna("").astype(str).str.strip()
        bad = np.flatnonzero((s == "").to_numpy())
        if bad.size:
            raise InputError(display, int(rows[bad[0]]), col, f"empty {col}")
        df[col] = s
    for col in ("line", "flight", "track"):
        if col in df:
            _check_names(df[col], rows, display, col)
    check_finite(df, ("t_start", "t_end"), rows, display)
    for col in ("t_start", "t_end"):
        bad = np.flatnonzero(np.isnan(df[col].to_numpy()))
        if bad.size:
            raise InputError(display, int(rows[bad[0]]), col, "missing time")
    kind = df["kind"].str.lower()
    bad = np.flatnonzero(~kind.isin(LINE_KINDS).to_numpy())
    if bad.size:
        i = int(bad[0])
        raise InputError(display, int(rows[i]), "kind",
                         f"unknown line kind {df['kind'].iloc[i]!r} (expected one of: {', '.join(LINE_KINDS)})")
    df["kind"] = kind
    bad = np.flatnonzero(~(df["t_end"].to_numpy() > df["t_start"].to_numpy()))
    if bad.size:
        i = int(bad[0])
        raise InputError(display, int(rows[i]), "t_end",
                         f"line {df['line'].iloc[i]} ends ({df['t_end'].iloc[i]!r}) before it starts "
                         f"({df['t_start'].iloc[i]!r})")
    dup = np.flatnonzero(df["line"].duplicated().to_numpy())
    if dup.size:
        i = int(dup[0])
        first = int(rows[np.flatnonzero((df["line"] == df["line"].iloc[i]).to_numpy())[0]])
        raise InputError(display, int(rows[i]), "line",
                         f"line id {df['line'].iloc[i]!r} is listed twice (first at row {first})")
    if "track" in df:
        vals = [None if (v is None or v is pd.NA or (isinstance(v, float) and np.isnan(v)) or str(v).strip() == "")
                else str(v).strip() for v in df["track"].tolist()]
        df["track"] = pd.Series(vals, index=df.index, dtype=object)
    else:
        df["track"] = pd.Series([None] * len(df), dtype=object)
    df = df[["line", "flight", "t_start", "t_end", "kind", "track"]]
    return df, rows


def _check_names(col: pd.Series, rows: np.ndarray, display: str, what: str) -> None:
    """Ids shown in the browser and used in URLs: app.config.check_name, row by row."""
    for i, v in enumerate(col.tolist()):
        if isinstance(v, str) and v != "":
            try:
                check_name(v, f"{what} id")
            except ValueError as exc:
                raise InputError(display, int(rows[i]), what, f"{exc}: {_short(v)!r}") from None


def _check_ranges(df: pd.DataFrame, rows: np.ndarray, display: str) -> None:
    """Every finite value within VALUE_RANGES; the error names the first row outside."""
    for col, (lo, hi, what) in VALUE_RANGES.items():
        if col in df:
            v = df[col].to_numpy(dtype=float)
            bad = np.flatnonzero(np.isfinite(v) & ((v < lo) | (v > hi)))
            if bad.size:
                i = int(bad[0])
                raise InputError(display, int(rows[i]), col, f"{what} {v[i]:.6g} is outside [{lo:g}, {hi:g}]")


# --------------------------------------------------------------------------- flight files


def _finish_series(df: pd.DataFrame, rows: np.ndarray, display: str, max_nan_run: int,
                   required: tuple, optional: tuple) -> pd.DataFrame:
    # an optional column left completely empty is treated as absent
    for c in optional:
        if c in df and df[c].isna().all():
            df = df.drop(columns=c)
    cols = [c for c in required + optional if c in df]
    check_finite(df, cols, rows, display)
    _check_ranges(df, rows, display)
    fill_short_nan_runs(df, cols, rows, display, max_nan_run)
    check_time_increasing(df["time"].to_numpy(), rows, display)
    return df


def read_gravimeter(path, display: str, config: SurveyConfig, time_offset_s: float | None = None,
                    gnss_time_range: tuple[float, float] | None = None) -> tuple[pd.DataFrame, np.ndarray]:
    """Read ``gravimeter.csv[.gz]`` or a G file; validate; return (DataFrame[time, f_z, (f_x, f_y)], rows).

    For a G file, ``time_offset_s`` maps UTC seconds of day onto the survey
    scale; when None it is the whole number of days that best puts the G
    data inside ``gnss_time_range`` (no leap seconds: GNSS assumed on UTC, or
    the pipeline's lag estimate absorbs the rest; see the report).
    """
    path = Path(path)
    p = config.processing
    if is_gfile_name(path.name):
        offset = 0.0 if time_offset_s is None else float(time_offset_s)
        check_file_size(path, display)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            g = read_gfile(path, time_offset_s=offset, max_nan_run=p.max_nan_run, display=display)
        for w in caught:
            warnings.warn(str(w.message), stacklevel=2)
        if time_offset_s is None and gnss_time_range is not None:
            mid_g = 0.5 * (g["time"].iloc[0] + g["time"].iloc[-1])
            mid_n = 0.5 * (gnss_time_range[0] + gnss_time_range[1])
            days = np.round((mid_n - mid_g) / 86400.0)
            g["time"] = g["time"] + 86400.0 * days
        rows = g["source_row"].to_numpy(dtype=np.int64)
        df = g[["time", "f_z", "f_x", "f_y"]].copy()
        _check_ranges(df, rows, display)
    else:
        df, rows = read_csv_table(path, display, GRAV_REQUIRED, GRAV_OPTIONAL, min_rows=2)
        df = _finish_series(df, rows, display, p.max_nan_run, GRAV_REQUIRED, GRAV_OPTIONAL)
    t = df["time"].to_numpy()
    check_time_increasing(t, rows, display)
    check_rate(t, display, config.gravimeter.rate_hz, p.rate_tolerance, "gravimeter", "gravimeter.rate_hz")
    med = float(np.median(df["f_z"].to_numpy()))
    lo, hi = F_Z_PLAUSIBLE_MS2
    if not (lo <= med <= hi):
        hint = (" (negative: the Z axis must point up)" if -hi <= med <= -lo else
                " (the values must be specific force in m/s², about +9.8 at rest)")
        raise InputError(display, None, "f_z", f"median f_z is {med:.6g} m/s², not plausible{hint}")
    return df, rows


def read_gnss(path, display: str, config: SurveyConfig) -> tuple[pd.DataFrame, np.ndarray]:
    """Read ``gnss.csv[.gz]``; validate; return (DataFrame[time, lat, lon, h, vu, (ve, vn, sigma_v)], rows)."""
    p = config.processing
    df, rows = read_csv_table(path, display, GNSS_REQUIRED, GNSS_OPTIONAL, min_rows=2)
    df = _finish_series(df, rows, display, p.max_nan_run, GNSS_REQUIRED, GNSS_OPTIONAL)
    check_range(df, "lat", -90.0, 90.0, rows, display, "latitude")
    check_range(df, "lon", -180.0, 360.0, rows, display, "longitude")
    check_rate(df["time"].to_numpy(), display, p.gnss_rate_hz, p.rate_tolerance, "GNSS", "processing.gnss_rate_hz")
    return df, rows


def _find_file(d: Path, stem: str) -> Path | None:
    for name in (f"{stem}.csv", f"{stem}.csv.gz"):
        if (d / name).is_file():
            return d / name
    return None


def _find_gfile(d: Path, root: Path) -> Path | None:
    cands = sorted(p for p in d.iterdir() if p.is_file() and is_gfile_name(p.name))
    if len(cands) > 1:
        names = ", ".join(p.name for p in cands)
        raise InputError(_rel(root, d) + "/", None, None,
                         f"several gravimeter G files in one flight ({names}): keep one per flight directory "
                         f"(merge split recordings into one file, or make each a flight of its own)")
    return cands[0] if cands else None


def _rel(root: Path, p: Path) -> str:
    try:
        return p.relative_to(root).as_posix()
    except ValueError:
        return str(p)


# --------------------------------------------------------------------------- survey


def read_survey(path, overrides: dict | None = None) -> Survey:
    """Read and validate a survey directory (SPEC §4).

    Parameters
    ----------
    path : path-like
        The survey directory.
    overrides : dict, optional
        ``ProcessingParams`` fields merged over ``[processing]`` of survey.toml.

    Returns
    -------
    Survey

    Raises
    ------
    InputError
        On the first problem found, naming file (relative to ``path``), row and column.
    """
    root = Path(path)
    if not root.is_dir():
        raise InputError(str(root), None, None, "survey directory not found")
    config = read_config(root / "survey.toml", overrides)
    p = config.processing
    lines, line_rows = read_lines(root / "lines.csv")

    fdir = root / "flights"
    if not fdir.is_dir():
        raise InputError("flights/", None, None, "the survey has no flights/ directory")
    flight_dirs = {d.name: d for d in sorted(fdir.iterdir()) if d.is_dir() and not d.name.startswith(".")}
    for name in flight_dirs:
        try:
            check_name(name, "flight name")
        except ValueError as exc:
            raise InputError(f"flights/{_short(name)!r}/", None, None, str(exc)) from None
    known = set(flight_dirs)
    bad = np.flatnonzero(~lines["flight"].isin(known).to_numpy())
    if bad.size:
        i = int(bad[0])
        have = ", ".join(sorted(known)) or "none"
        raise InputError("lines.csv", int(line_rows[i]), "flight",
                         f"line {lines['line'].iloc[i]} refers to flight {lines['flight'].iloc[i]!r}, which has no "
                         f"directory under flights/ (flights found: {have})")

    flights: dict[str, Flight] = {}
    for name, d in flight_dirs.items():
        gnss_path = _find_file(d, "gnss")
        if gnss_path is None:
            raise InputError(_rel(root, d / "gnss.csv"), None, None, f"flight {name} has no gnss.csv (or gnss.csv.gz)")
        grav_path = _find_file(d, "gravimeter") or _find_gfile(d, root)
        if grav_path is None:
            raise InputError(_rel(root, d / "gravimeter.csv"), None, None,
                             f"flight {name} has no gravimeter.csv (or .csv.gz, or a G file: gravimeter.g, *.G, G*.dat)")
        gnss_disp, grav_disp = _rel(root, gnss_path), _rel(root, grav_path)
        gnss, gnss_rows = read_gnss(gnss_path, gnss_disp, config)
        tn = gnss["time"].to_numpy()
        offset = getattr(config.gravimeter, "time_offset_s", None)
        grav, grav_rows = read_gravimeter(grav_path, grav_disp, config, time_offset_s=offset,
                                          gnss_time_range=(float(tn[0]), float(tn[-1])))
        tg = grav["time"].to_numpy()

        sel = np.flatnonzero((lines["flight"] == name).to_numpy())
        if sel.size:
            ts = lines["t_start"].to_numpy()[sel]
            te = lines["t_end"].to_numpy()[sel]
            for k, i in enumerate(sel):
                for t, disp in ((tg, grav_disp), (tn, gnss_disp)):
                    if ts[k] < t[0] or te[k] > t[-1]:
                        col, val = ("t_start", ts[k]) if ts[k] < t[0] else ("t_end", te[k])
                        raise InputError("lines.csv", int(line_rows[i]), col,
                                         f"line {lines['line'].iloc[i]} window {ts[k]:.3f}–{te[k]:.3f} s is outside "
                                         f"the data of {disp} ({t[0]:.3f}–{t[-1]:.3f} s): {col} = {val:.3f}")
            for t, rows, disp in ((tg, grav_rows, grav_disp), (tn, gnss_rows, gnss_disp)):
                g = gap_rows_in_windows(t, ts, te, p.max_gap_s)
                hit = np.flatnonzero(g >= 0)
                if hit.size:
                    k = int(hit[0])
                    j = int(g[k])
                    raise InputError(disp, int(rows[j]), "time",
                                     f"gap of {t[j] - t[j - 1]:.3f} s before this row (from {t[j - 1]:.3f} to "
                                     f"{t[j]:.3f} s) inside line {lines['line'].iloc[sel[k]]} "
                                     f"({ts[k]:.3f}–{te[k]:.3f} s); at most {p.max_gap_s:g} s allowed "
                                     f"(processing.max_gap_s)")
        flights[name] = Flight(name=name, gravimeter=grav, gnss=gnss, gravimeter_path=grav_path, gnss_path=gnss_path)
    return Survey(root=root, config=config, lines=lines, flights=flights)


# --------------------------------------------------------------------------- QC summary


def path_length_km(lat_deg, lon_deg, h_m=None) -> float:
    """Length of a track through consecutive positions, on the WGS84 ellipsoid (km).

    Each step uses the radii of curvature at the mid-latitude (and mid-height):
    ``ds² = ((R_M+h)·Δφ)² + ((R_N+h)·cos φ·Δλ)²`` — exact to second order for
    the short steps of 1–20 Hz GNSS.
    """
    lat = np.asarray(lat_deg, dtype=float)
    lon = np.asarray(lon_deg, dtype=float)
    if lat.shape != lon.shape:
        raise ValueError("lat_deg and lon_deg must have the same shape")
    if lat.size < 2:
        return 0.0
    h = np.zeros_like(lat) if h_m is None else np.asarray(h_m, dtype=float)
    phi = np.deg2rad(lat)
    lam = np.unwrap(np.deg2rad(lon))
    phim = 0.5 * (phi[1:] + phi[:-1])
    hm = 0.5 * (h[1:] + h[:-1])
    r_m, r_n = radii_of_curvature_m(np.rad2deg(phim))
    dn = (r_m + hm) * np.diff(phi)
    de = (r_n + hm) * np.cos(phim) * np.diff(lam)
    return float(np.sum(np.hypot(dn, de)) / 1000.0)


def _window_stats(t: np.ndarray, a: float, b: float) -> tuple[float, float, int]:
    """(median rate Hz, largest step s, sample count) of the samples of ``t`` in [a, b].

    The largest step includes the steps from the last sample before the window
    and to the first sample after it, so a hole at a window edge is seen.
    """
    i0, i1 = np.searchsorted(t, a, side="left"), np.searchsorted(t, b, side="right")
    seg = t[i0:i1]
    around = t[max(i0 - 1, 0):min(i1 + 1, t.size)]
    steps = np.diff(around)
    return median_rate_hz(seg), (float(steps.max()) if steps.size else float("nan")), int(seg.size)


def survey_summary(survey: Survey) -> pd.DataFrame:
    """QC table, one row per flight (``level = "flight"``) then one per line (``level = "line"``).

    Columns: ``level, flight, line, kind, track, t_start, t_end, duration_s,
    gravimeter_rate_hz, gnss_rate_hz, gravimeter_max_gap_s, gnss_max_gap_s,
    n_gravimeter, n_gnss, length_km``.  Rates are from the median interval,
    gaps are the largest time step among the samples inside (and bounding)
    the window, ``length_km`` is the ellipsoidal path length of the GNSS
    positions within the window (at flight height), ``line``/``kind``/``track``
    are None on flight rows.
    """
    rows = []
    for name, fl in survey.flights.items():
        tg = fl.gravimeter["time"].to_numpy()
        tn = fl.gnss["time"].to_numpy()
        a, b = float(min(tg[0], tn[0])), float(max(tg[-1], tn[-1]))
        rg, gg, ng = _window_stats(tg, a, b)
        rn, gn, nn = _window_stats(tn, a, b)
        g = fl.gnss
        rows.append(dict(level="flight", flight=name, line=None, kind=None, track=None, t_start=a, t_end=b,
                         duration_s=b - a, gravimeter_rate_hz=rg, gnss_rate_hz=rn, gravimeter_max_gap_s=gg,
                         gnss_max_gap_s=gn, n_gravimeter=ng, n_gnss=nn,
                         length_km=path_length_km(g["lat"].to_numpy(), g["lon"].to_numpy(), g["h"].to_numpy())))
    for ln in survey.lines.itertuples(index=False):
        fl = survey.flights[ln.flight]
        tg = fl.gravimeter["time"].to_numpy()
        tn = fl.gnss["time"].to_numpy()
        a, b = float(ln.t_start), float(ln.t_end)
        rg, gg, ng = _window_stats(tg, a, b)
        rn, gn, nn = _window_stats(tn, a, b)
        i0, i1 = np.searchsorted(tn, a, side="left"), np.searchsorted(tn, b, side="right")
        g = fl.gnss.iloc[i0:i1]
        rows.append(dict(level="line", flight=ln.flight, line=ln.line, kind=ln.kind, track=ln.track, t_start=a,
                         t_end=b, duration_s=b - a, gravimeter_rate_hz=rg, gnss_rate_hz=rn,
                         gravimeter_max_gap_s=gg, gnss_max_gap_s=gn, n_gravimeter=ng, n_gnss=nn,
                         length_km=path_length_km(g["lat"].to_numpy(), g["lon"].to_numpy(), g["h"].to_numpy())))
    out = pd.DataFrame(rows, columns=["level", "flight", "line", "kind", "track", "t_start", "t_end", "duration_s",
                                      "gravimeter_rate_hz", "gnss_rate_hz", "gravimeter_max_gap_s",
                                      "gnss_max_gap_s", "n_gravimeter", "n_gnss", "length_km"])
    for c in ("line", "kind", "track"):  # keep None (not NaN) on flight rows
        out[c] = pd.Series([r[c] for r in rows], index=out.index, dtype=object)
    return out
