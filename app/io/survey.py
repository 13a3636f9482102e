"""Read and validate a survey directory (SPEC §4, docs/CONTRACTS.md).

::

    <survey>/survey.toml
    <survey>/lines.csv                               (optional with XYZ Line/Tie blocks)
    <survey>/flights/<flight>/gravimeter.csv[.gz]    or gravimeter.xyz[.gz], a G file (gravimeter.g,
                                                     *.G, a G file *.dat), DGS AT1A/AT1M records (*.dat)
    <survey>/flights/<flight>/gnss.csv[.gz]          or gnss.xyz[.gz]
    <survey>/flights/<flight>/<name>.xyz[.gz]        one Geosoft XYZ file holding both (instead)

Formats: :mod:`app.io.tables` (CSV), :mod:`app.io.gfile`, :mod:`app.io.dgs`,
:mod:`app.io.xyz` (with the ``[columns]`` table of survey.toml).  ``.dat`` files
are told apart by their content (:func:`app.io.dgs.sniff_dat`), never by name
alone; each sensor must have exactly one file.

Rates are inferred from the time stamps (median interval); ``gravimeter.rate_hz``
and ``processing.gnss_rate_hz`` are only checks of them (0.5–100 Hz and
0.5–50 Hz are accepted when nothing is declared).

Without ``lines.csv`` the survey lines come from the XYZ blocks
(:func:`lines_from_blocks`): ``Line <id>`` → main, ``Tie <id>`` → tie, the
window from the block's first to last GNSS time; an id used twice needs a
lines.csv.

GNSS without ``vu``: ``vu`` is derived from ``h`` — per contiguous run (no
record gap longer than ``max(processing.max_gap_s, 1.5 × median step)``),
``V(t_k)`` is the derivative at ``t_k`` of the not-a-knot cubic spline through
``(t, h)``; the pipeline's ``(V_k − V_{k−1})/Δt`` is then exactly the spline's
mean vertical acceleration over ``(t_{k−1}, t_k]``.  Runs shorter than 4
samples are errors naming their rows.  ``Flight.vu_derived_from_h`` records it
(the pipeline reports it as a flight note).  ``ve``/``vn`` are left to the
pipeline, which derives them from the positions when absent.

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
from typing import NamedTuple

import numpy as np
import pandas as pd
from pydantic import ValidationError

from app.config import F_Z_UNIT_TO_MS2, SurveyConfig, check_name
from app.core.geodesy import (
    horizontal_velocity_misfit_ms,
    path_length_km,
    step_lengths_km,
    velocities_from_positions_ms,
    vertical_velocity_from_heights_ms,
)
from app.core.measurement import height_rate_ratio
from app.io.dgs import dat_hint, read_dgs, sniff_dat
from app.io.errors import InputError
from app.io.gfile import is_gfile_name, read_gfile
from app.io.tables import (
    check_file_size,
    check_finite,
    check_range,
    check_rate,
    check_time_increasing,
    drop_duplicate_rows,
    fill_short_nan_runs,
    gap_rows_in_windows,
    mark_no_data,
    median_rate_hz,
    no_data_mask,
    read_csv_table,
    true_runs,
)
from app.io.xyz import XyzTable, scan_xyz, xyz_table

__all__ = ["Flight", "Survey", "read_survey", "read_config", "read_lines", "read_gravimeter", "read_gnss",
           "survey_summary", "path_length_km", "LINE_KINDS"]

LINE_KINDS = ("main", "tie", "repeat")
GRAV_REQUIRED = ("time", "f_z")
GRAV_OPTIONAL = ("f_x", "f_y")
GNSS_REQUIRED = ("time", "lat", "lon", "h")
GNSS_OPTIONAL = ("vu", "ve", "vn", "sigma_v")  # vu derived from h when absent
#: plausible median |f_z| (m/s²) of a gravimeter file in m/s² with Z up
F_Z_PLAUSIBLE_MS2 = (7.0, 13.0)
#: other units a CSV f_z is recognised in by its median (×factor → m/s²): Gal, mGal, µm/s²
F_Z_UNITS = (("Gal (cm/s²)", 1e-2), ("mGal", 1e-5), ("µm/s²", 1e-6))
#: rates (Hz) accepted when none is declared (airborne and marine gravimeters; GNSS receivers)
GRAVIMETER_RATE_SANITY_HZ = (0.5, 100.0)
GNSS_RATE_SANITY_HZ = (0.5, 50.0)
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
    ``vu_derived_from_h``: True when the GNSS file had no ``vu`` and the column
    was derived from the heights (:func:`derive_vu_from_h`); the pipeline
    reports it.
    """

    name: str
    gravimeter: pd.DataFrame
    gnss: pd.DataFrame
    gravimeter_path: Path
    gnss_path: Path
    vu_derived_from_h: bool = False


@dataclass
class Survey:
    """A validated survey directory.

    ``lines``: DataFrame[line (str), flight (str), t_start, t_end (float s), kind, track (str or None)].
    """

    root: Path
    config: SurveyConfig
    lines: pd.DataFrame
    flights: dict[str, Flight] = field(default_factory=dict)
    #: what the readers changed or assumed while reading (saturated G-file messages dropped,
    #: DGS records without GPS sync, relative DGS readings …), for the report's warnings
    notes: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------- survey.toml


def _toml_key_row(text: str, loc: tuple) -> int | None:
    """Line number of ``key`` in table ``[section]`` of a TOML text (best effort).

    ``loc`` is a pydantic error location: ``(table,)`` points at the table's
    header, ``(table, key)`` or ``(table, subtable, key)`` at the key (or, when
    it is not written as a key, at the header ``[table.subtable]``).
    """
    def header_row(name: str) -> int | None:
        for i, line in enumerate(text.splitlines(), start=1):
            m = re.match(r"^\[\s*([^\]]+?)\s*\]", line.strip())
            if m and m.group(1).replace('"', "").replace(" ", "") == name:
                return i
        return None

    loc = tuple(str(x) for x in loc)
    if not loc:
        return None
    if len(loc) == 1:  # an unknown or bad table: point at its header
        return header_row(loc[0])
    section, key = ".".join(loc[:-1]), loc[-1]
    current = None
    for i, line in enumerate(text.splitlines(), start=1):
        st = line.strip()
        m = re.match(r"^\[\s*([^\]]+?)\s*\]", st)
        if m:
            current = m.group(1).replace('"', "").replace(" ", "")
            continue
        if current == section and re.match(rf'^"?{re.escape(key)}"?\s*=', st):
            return i
    return header_row(".".join(loc)) or header_row(section)


#: Largest survey.toml read (a real one is a few kB: names, the gravimeter and a few settings); it is
#: read whole and parsed in pure Python, so a bound on the upload alone would allow gigabytes.
MAX_CONFIG_BYTES = 1 << 20


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
    size = path.stat().st_size
    if size > MAX_CONFIG_BYTES:
        raise InputError(display, None, None, f"the file is {size / 2**20:.3g} MB; at most {MAX_CONFIG_BYTES >> 20} MB "
                                              "allowed (survey.toml holds names and settings: a few kB)")
    text = path.read_text(encoding="utf-8-sig", errors="replace")
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
#: The columns lines.csv must have (SPEC §4); ``track`` is optional.
LINES_COLUMNS = ("line", "flight", "t_start", "t_end", "kind")


def read_lines(path, display: str = "lines.csv") -> tuple[pd.DataFrame, np.ndarray]:
    """Read and check ``lines.csv`` (columns, numbers, kinds, t_end > t_start, unique ids).

    Returns
    -------
    lines : DataFrame[line, flight, t_start, t_end, kind, track]
    rows : ndarray of int
        File line number of each line.
    """
    df, rows = read_csv_table(path, display, LINES_COLUMNS, ("track",),
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
        bad = np.flatnonzero(no_data_mask(df[col].to_numpy()))
        if bad.size:
            i = int(bad[0])
            raise InputError(display, int(rows[i]), col, f"{float(df[col].iloc[i]):g} is a no-data marker, not a "
                             f"time: line {df['line'].iloc[i]} needs its {col.replace('_', ' ')} (s, the data files' "
                             "time scale)")
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
        t0, t1 = float(df["t_start"].iloc[i]), float(df["t_end"].iloc[i])
        msg = f"line {df['line'].iloc[i]} ends ({t1:.3f}) before it starts ({t0:.3f})"
        for period, what in ((86400.0, "seconds of day: the line crosses midnight"),
                             (604800.0, "GPS seconds of week: the line crosses the week's end")):
            if 0.0 < period - (t0 - t1) < 0.5 * period:   # a window across the clock's wrap
                msg += (f" — the time scale wrapped ({what}); the survey needs one monotonic scale: add "
                        f"{period:.0f} s to the times after the wrap, here and in the data files")
        raise InputError(display, int(rows[i]), "t_end", msg)
    dup = np.flatnonzero(df["line"].duplicated().to_numpy())
    if dup.size:
        i = int(dup[0])
        first = int(rows[np.flatnonzero((df["line"] == df["line"].iloc[i]).to_numpy())[0]])
        raise InputError(display, int(rows[i]), "line",
                         f"line id {df['line'].iloc[i]!r} is listed twice (first at row {first})")
    _check_overlaps(df, rows, display)
    if "track" in df:
        vals = [None if (v is None or v is pd.NA or (isinstance(v, float) and np.isnan(v)) or str(v).strip() == "")
                else str(v).strip() for v in df["track"].tolist()]
        df["track"] = pd.Series(vals, index=df.index, dtype=object)
    else:
        df["track"] = pd.Series([None] * len(df), dtype=object)
    df = df[["line", "flight", "t_start", "t_end", "kind", "track"]]
    return df, rows


def _check_overlaps(df: pd.DataFrame, rows: np.ndarray, display: str) -> None:
    """No two lines of one flight overlap in time: an aircraft flies one line at a time, and
    the shared epochs would be processed twice (a typo in a window, usually)."""
    for _, g in df.groupby("flight", sort=False):
        order = np.argsort(g["t_start"].to_numpy(), kind="stable")
        idx = g.index.to_numpy()[order]
        t0, t1 = df["t_start"].to_numpy()[idx], df["t_end"].to_numpy()[idx]
        ends = np.maximum.accumulate(t1)
        bad = np.flatnonzero(t0[1:] < ends[:-1])
        if bad.size:
            k = int(bad[0]) + 1
            prev = idx[int(np.flatnonzero(t1[:k] == ends[k - 1])[0])]
            i = idx[k]
            raise InputError(display, int(rows[i]), "t_start",
                             f"line {df['line'].iloc[i]} starts at {t0[k]:.3f}, before line {df['line'].iloc[prev]} "
                             f"(row {int(rows[prev])}) of the same flight ends at {ends[k - 1]:.3f}: the windows "
                             "overlap (one aircraft flies one line at a time)")


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
                   required: tuple, optional: tuple, holes: tuple = ()) -> tuple[pd.DataFrame, np.ndarray]:
    """Checks and short NaN runs of one flight file: every column's runs up to ``max_nan_run``
    interpolated, except ``holes``' — their rows are dropped (a hole of the record, which
    processing leaves missing), and a warning says how many.  Returns the table and its rows."""
    # an optional column left completely empty is treated as absent
    for c in optional:
        if c in df and df[c].isna().all():
            df = df.drop(columns=c)
    cols = [c for c in required + optional if c in df]
    check_finite(df, cols, rows, display)
    _check_ranges(df, rows, display)
    gone = np.zeros(len(df), bool)
    for c in holes:
        if c in df:
            gone |= df[c].isna().to_numpy()
    fill_short_nan_runs(df, cols, rows, display, max_nan_run)
    if gone.any():
        # A linear fill of f_z misses the aircraft's acceleration at that sample, which the GNSS
        # still sees: at 2 Hz one filled sample of a 0.5 m/s² turbulent record was 100+ mGal of
        # error along its line.  The measurement stage puts a sample back only where the record
        # shows a spline predicts it (an 18 Hz meter's; fill_gravimeter_samples).
        warnings.warn(f"{display}: {int(gone.sum())} missing value(s) of {', '.join(holes)} left as holes of the "
                      f"record (rows {', '.join(str(int(r)) for r in rows[gone][:5])}"
                      f"{', …' if gone.sum() > 5 else ''}), not interpolated here (the measurement puts a sample back "
                      "where the record predicts it: processing.gravimeter_fill_max_error_mgal)", stacklevel=2)
        df = df.loc[~gone].reset_index(drop=True)
        rows = np.asarray(rows)[~gone]
    check_time_increasing(df["time"].to_numpy(), rows, display)
    return df, rows


def _days_to_gnss(t: np.ndarray, gnss_time_range: tuple[float, float] | None) -> float:
    """Whole days (s) that best put the series ``t`` inside the GNSS time range (0 without one)."""
    if gnss_time_range is None:
        return 0.0
    mid_g = 0.5 * (t[0] + t[-1])
    mid_n = 0.5 * (gnss_time_range[0] + gnss_time_range[1])
    return 86400.0 * float(np.round((mid_n - mid_g) / 86400.0))


def finish_gravimeter(df: pd.DataFrame, rows: np.ndarray, display: str, config: SurveyConfig) -> pd.DataFrame:
    """Checks common to every gravimeter format: time order, rate, plausible f_z (m/s², up)."""
    p = config.processing
    t = df["time"].to_numpy()
    check_time_increasing(t, rows, display)
    check_rate(t, display, config.gravimeter.rate_hz, p.rate_tolerance, "gravimeter", "gravimeter.rate_hz",
               sanity_hz=GRAVIMETER_RATE_SANITY_HZ)
    med = float(np.median(df["f_z"].to_numpy()))
    lo, hi = F_Z_PLAUSIBLE_MS2
    if not (lo <= med <= hi):
        hint = (" (negative: the Z axis must point up)" if -hi <= med <= -lo else
                " (the values must be specific force in m/s², about +9.8 at rest)")
        raise InputError(display, None, "f_z", f"median f_z is {med:.6g} m/s², not plausible{hint}")
    return df


def read_gravimeter(path, display: str, config: SurveyConfig, time_offset_s: float | None = None,
                    gnss_time_range: tuple[float, float] | None = None,
                    kind: str | None = None) -> tuple[pd.DataFrame, np.ndarray]:
    """Read ``gravimeter.csv[.gz]``, a G file or DGS records; validate; return (DataFrame[time, f_z, (f_x, f_y)], rows).

    ``kind`` is ``"csv"``, ``"gfile"`` or ``"dgs"`` (None: from the name and,
    for ``.dat`` files, the content).  For a G file, ``time_offset_s`` maps UTC
    seconds of day onto the survey scale; for DGS records it is added to the
    GPS seconds of week (:mod:`app.io.dgs`).  When None it is the whole number
    of days that best puts the data inside ``gnss_time_range`` (no leap
    seconds: GNSS assumed on UTC for G files, on GPS time for DGS records; the
    pipeline's time-offset estimate, searched over ±60 s, finds and removes the
    rest — e.g. 18 s of GPS−UTC — and reports it).
    """
    path = Path(path)
    p = config.processing
    if kind is None:
        low = path.name.lower()
        if low.endswith(".dat") or low.endswith(".dat.gz"):
            kind = sniff_dat(path) or ("gfile" if is_gfile_name(path.name) else "dgs")
        elif is_gfile_name(path.name):
            kind = "gfile"
        else:
            kind = "csv"
    if kind in ("gfile", "dgs"):
        offset = 0.0 if time_offset_s is None else float(time_offset_s)
        check_file_size(path, display)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if kind == "gfile":
                g = read_gfile(path, time_offset_s=offset, max_nan_run=p.max_nan_run, display=display)
            else:
                g = read_dgs(path, time_offset_s=time_offset_s, rate_hz=config.gravimeter.rate_hz,
                             reading_offset_mgal=config.gravimeter.reading_offset_mgal,
                             max_nan_run=p.max_nan_run, display=display)
        for w in caught:
            warnings.warn(str(w.message), stacklevel=2)
        if time_offset_s is None:
            g["time"] = g["time"] + _days_to_gnss(g["time"].to_numpy(), gnss_time_range)
        rows = g["source_row"].to_numpy(dtype=np.int64)
        df = g[[c for c in ("time", "f_z", "f_x", "f_y") if c in g]].copy()
        df.attrs.update(g.attrs)
        if kind == "gfile":   # a G file's accelerations in Gal, mGal or µm/s², like a CSV's
            declared = config.columns.for_role("gravimeter").get("f_z_unit")
            _csv_force_units(df, display, declared, _unit_row(path) if declared else None)
        _check_ranges(df, rows, display)
    else:
        df, rows = read_csv_table(path, display, GRAV_REQUIRED, GRAV_OPTIONAL, min_rows=2)
        df, rows = drop_duplicate_rows(df, rows, display)
        mark_no_data(df, rows, display, GRAV_REQUIRED + GRAV_OPTIONAL)
        declared = config.columns.for_role("gravimeter").get("f_z_unit")
        _csv_force_units(df, display, declared, _unit_row(path) if declared else None)
        df, rows = _finish_series(df, rows, display, p.max_nan_run, GRAV_REQUIRED, GRAV_OPTIONAL, holes=("f_z",))
    return finish_gravimeter(df, rows, display, config), rows


def _unit_row(path: Path) -> int | None:
    """Line of ``f_z_unit`` in the survey.toml of the survey holding ``path``
    (``flights/<name>/<file>``), best effort."""
    toml = path.parent.parent.parent / "survey.toml"
    try:
        text = toml.read_text(encoding="utf-8-sig", errors="replace")
    except OSError:
        return None
    for loc in (("columns", "gravimeter", "f_z_unit"), ("columns", "f_z_unit")):
        row = _toml_key_row(text, loc)
        if row is not None and "f_z_unit" in text.splitlines()[row - 1]:
            return row
    return None


def _csv_force_units(df: pd.DataFrame, display: str, declared: str | None = None,
                     toml_row: int | None = None) -> None:
    """SPEC's gravimeter.csv has f_z in m/s²; a file in Gal, mGal or µm/s² is recognised by its
    median (≈ 9.8·10², 10⁵·9.8, 10⁶·9.8 — the ranges do not overlap) and converted in place,
    f_x/f_y with it, with a warning.  Anything else is left to the range checks (an error).
    ``declared``: survey.toml's ``[columns] f_z_unit`` (:data:`app.config.F_Z_UNIT_TO_MS2`),
    which the values must then agree with — an error naming it (``toml_row``: its line in
    survey.toml) when they do not —, converted without a warning.  ``df`` is
    :func:`read_csv_table`'s (float columns: bad cells are already errors)."""
    fz = df["f_z"].to_numpy(dtype=float)
    if not np.isfinite(fz).any():
        return
    med = float(np.nanmedian(fz))
    lo, hi = F_Z_PLAUSIBLE_MS2
    if declared is not None:
        factor = F_Z_UNIT_TO_MS2[declared]
        if not lo <= med * factor <= hi:
            seen = next((u for u, fac in (("m/s²", 1.0), *F_Z_UNITS) if lo <= med * fac <= hi), None)
            raise InputError("survey.toml", toml_row, "columns.f_z_unit",
                             f"f_z_unit = {declared!r}, but {display}'s median f_z is {med:.6g}, "
                             f"{med * factor:.6g} m/s² in that unit (about 9.8 expected)"
                             + (f"; the values look like {seen}" if seen else ""))
        _scale_force(df, factor)
        return
    for unit, factor in F_Z_UNITS:
        if lo <= med * factor <= hi:
            _scale_force(df, factor)
            warnings.warn(f"{display}: f_z read as {unit} (median {med:.6g}) and converted to m/s² "
                          f"(× {factor:g}); SPEC's gravimeter.csv is in m/s²", stacklevel=2)
            return


def _scale_force(df: pd.DataFrame, factor: float) -> None:
    """f_z, f_x and f_y (those present) times ``factor``, in place."""
    if factor != 1.0:
        for c in ("f_z", "f_x", "f_y"):
            if c in df:
                df[c] = df[c] * factor


def gnss_runs(t: np.ndarray, max_gap_s: float) -> list[tuple[int, int]]:
    """Index ranges ``[i0, i1)`` of the contiguous stretches of a GNSS record.

    A record gap is a step longer than ``max(max_gap_s, 1.5 × median step)``
    (the gaps a survey line may not contain; a coarse receiver's regular step
    is never a gap).
    """
    t = np.asarray(t, dtype=float)
    if t.size < 2:
        return [(0, int(t.size))]
    dt = np.diff(t)
    limit = max(float(max_gap_s), 1.5 * float(np.median(dt)))
    cut = np.flatnonzero(dt > limit) + 1
    edges = np.concatenate(([0], cut, [t.size]))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def derive_vu_from_h(df: pd.DataFrame, rows: np.ndarray, display: str, max_gap_s: float) -> np.ndarray:
    """``vu`` (m/s) from the heights of a GNSS table that has none.

    Per contiguous run (:func:`gnss_runs`), ``vu_k`` is the derivative at
    ``t_k`` of the not-a-knot cubic spline through ``(t, h)``
    (:func:`app.core.geodesy.vertical_velocity_from_heights_ms`), so that the
    pipeline's ``(V_k − V_{k−1})/Δt`` is the spline's mean vertical
    acceleration over each GNSS interval.  No spline crosses a record gap.

    Raises
    ------
    InputError
        A run shorter than 4 samples (names its rows, column ``h``).
    """
    t = df["time"].to_numpy(dtype=float)
    h = df["h"].to_numpy(dtype=float)
    vu = np.empty_like(t)
    for a, b in gnss_runs(t, max_gap_s):
        if b - a < 4:
            span = f"rows {int(rows[a])}–{int(rows[b - 1])}" if b - a > 1 else f"row {int(rows[a])}"
            raise InputError(display, int(rows[a]), "h",
                             f"no vu column, and the {b - a} GNSS sample(s) of {span} between record gaps are too "
                             f"few to derive vu from h (a cubic spline needs at least 4 samples per contiguous "
                             f"run): add a vu column or remove these rows")
        vu[a:b] = vertical_velocity_from_heights_ms(t[a:b], h[a:b])
    return vu


#: height change per metre of integrated vu (:func:`app.core.measurement.height_rate_ratio`) of a
#: file whose heights are in feet and velocities in m/s
FEET_PER_METRE = 1.0 / 0.3048


def check_vu_against_heights(df: pd.DataFrame, display: str, min_corr: float = 0.9) -> None:
    """``vu`` must be the rate of change of ``h`` (m/s, up); checked on the record's own heights.

    Where the record moves vertically enough to tell (:func:`app.core.measurement.height_rate_ratio`,
    height changes against ∫vu dt, correlation beyond ``min_corr`` in magnitude):
    ``vu`` running against the heights at the same rate (slope −1 ± 15 %) is a positive-down
    velocity (NED ``vd`` exported as ``vu``): its sign is flipped in place, with a warning;
    any other slope outside 0.7–1.4 is an ``InputError`` (column ``h``) naming it — feet
    (slope 3.28: h in ft, vu in m/s; 0.305: the reverse) or another unit.  Without enough
    vertical motion, or without the correlation, nothing is said."""
    b, corr, n = height_rate_ratio(df["time"].to_numpy(float), df["h"].to_numpy(float),
                                   df["vu"].to_numpy(float))
    if not (np.isfinite(b) and abs(corr) >= min_corr):
        return
    if 0.7 <= b <= 1.4:
        return
    what = f"the heights change {b:.4g} × the integral of vu (∫vu dt over {n} windows of ~2 s, " \
           f"correlation {corr:.3f})"
    if -1.15 <= b <= -0.85:
        df["vu"] = -df["vu"]
        warnings.warn(f"{display}: {what}: vu is positive down (a NED vd exported as vu?); its sign was flipped to make it "
                      "up, as SPEC's vu is (the aircraft's vertical acceleration would otherwise enter z twice "
                      "over)", stacklevel=2)
        return
    for ratio, hint in ((FEET_PER_METRE, "h looks like feet beside a vu in m/s"),
                        (1.0 / FEET_PER_METRE, "vu looks like ft/s beside an h in metres")):
        if abs(b / ratio - 1.0) < 0.05:
            raise InputError(display, None, "h", f"{what}: {hint}; SPEC's GNSS file has h in metres "
                             "(ellipsoidal) and vu in m/s, up — convert the column")
    raise InputError(display, None, "h", f"{what}; vu must be dh/dt (h in metres, vu in m/s, up): "
                     "a unit or sign of h or vu is not SPEC's")


def check_radian_positions(df: pd.DataFrame, display: str) -> None:
    """lat/lon in radians (every |lat| ≤ π/2, |lon| ≤ 2π: a point off West Africa in degrees) are
    told by the motion they give: with ``ve``/``vn``, positions that match the velocities when read
    as radians (:func:`app.core.geodesy.horizontal_velocity_misfit_ms` within a quarter of the
    speed) and not as degrees is an ``InputError`` (column ``lat``); without them a median speed
    under 5 m/s by the positions is a warning (normal gravity at the wrong latitude is thousands of
    mGal off, and a CRS chosen for the data does not see it)."""
    lat, lon = df["lat"].to_numpy(float), df["lon"].to_numpy(float)
    if len(df) < 10 or not (np.nanmax(np.abs(lat)) <= 0.5 * np.pi and np.nanmax(np.abs(lon)) <= 2.0 * np.pi):
        return
    t, h = df["time"].to_numpy(float), df["h"].to_numpy(float)
    if "ve" in df and "vn" in df:
        ve, vn = df["ve"].to_numpy(float), df["vn"].to_numpy(float)
        speed, as_deg, n = horizontal_velocity_misfit_ms(t, lat, lon, h, ve, vn)
        _, as_rad, _ = horizontal_velocity_misfit_ms(t, np.rad2deg(lat), np.rad2deg(lon), h, ve, vn)
        if n >= 10 and as_rad < 0.25 * speed < as_deg:
            raise InputError(display, None, "lat", f"read as degrees, the positions move {as_deg:.3g} m/s away from "
                             f"ve/vn (median, at {speed:.3g} m/s); read as radians {as_rad:.2g} m/s: lat and lon "
                             "look like radians; SPEC's GNSS file has them in degrees")
        return
    ve_p, vn_p = velocities_from_positions_ms(t, lat, lon, h)
    med = float(np.nanmedian(np.hypot(ve_p, vn_p)))
    if 0.0 < med < 5.0:
        warnings.warn(f"{display}: every lat is within ±π/2 and every lon within ±2π, and the positions move at a "
                      f"median {med:.2g} m/s: radians? SPEC's lat and lon are degrees (normal gravity, the Eötvös "
                      "correction and every distance would be wrong)", stacklevel=3)


def finish_gnss(df: pd.DataFrame, rows: np.ndarray, display: str, config: SurveyConfig) -> tuple[pd.DataFrame, bool]:
    """Validate a parsed GNSS table (any file format) and derive ``vu`` when absent.

    ``sigma_v`` is not used by the processing: with empty cells it is dropped (a warning),
    not refused as missing values.

    Returns
    -------
    (DataFrame[time, lat, lon, h, vu, (ve, vn, sigma_v)], vu_derived_from_h)
    """
    p = config.processing
    if "sigma_v" in df:
        miss = np.flatnonzero(df["sigma_v"].isna().to_numpy())
        if 0 < miss.size < len(df):   # (a column left wholly empty is dropped as absent, silently)
            df = df.drop(columns="sigma_v")
            warnings.warn(f"{display}: sigma_v has {miss.size} empty cell(s) (first at row {int(rows[miss[0]])}); "
                          f"the processing does not use it: column dropped", stacklevel=2)
    df, rows = _finish_series(df, rows, display, p.max_nan_run, GNSS_REQUIRED, GNSS_OPTIONAL)
    check_range(df, "lat", -90.0, 90.0, rows, display, "latitude")
    check_range(df, "lon", -180.0, 360.0, rows, display, "longitude")
    check_rate(df["time"].to_numpy(), display, p.gnss_rate_hz, p.rate_tolerance, "GNSS", "processing.gnss_rate_hz",
               sanity_hz=GNSS_RATE_SANITY_HZ)
    check_radian_positions(df, display)
    if p.geoid_height_m is not None:   # orthometric heights declared: made ellipsoidal (a constant N)
        df["h"] = df["h"] + float(p.geoid_height_m)
        warnings.warn(f"{display}: h taken as orthometric and made ellipsoidal by adding the declared geoid undulation "
                      f"{p.geoid_height_m:g} m (processing.geoid_height_m)", stacklevel=2)
    derived = "vu" not in df
    if derived:
        df.insert(4, "vu", derive_vu_from_h(df, rows, display, p.max_gap_s))
    else:
        check_vu_against_heights(df, display)
    cols = [c for c in ("time", "lat", "lon", "h", "vu", "ve", "vn", "sigma_v") if c in df]
    return df[cols].reset_index(drop=True), derived


def read_gnss(path, display: str, config: SurveyConfig) -> tuple[pd.DataFrame, np.ndarray]:
    """Read ``gnss.csv[.gz]``; validate; return (DataFrame[time, lat, lon, h, vu, (ve, vn, sigma_v)], rows).

    Without a ``vu`` column, ``vu`` is derived from ``h`` (:func:`derive_vu_from_h`)
    and ``df.attrs["vu_derived_from_h"]`` is True.
    """
    df, rows = read_csv_table(path, display, GNSS_REQUIRED, GNSS_OPTIONAL, min_rows=2)
    df, rows = drop_duplicate_rows(df, rows, display)
    mark_no_data(df, rows, display, GNSS_REQUIRED + GNSS_OPTIONAL)
    df, derived = finish_gnss(df, rows, display, config)
    df.attrs["vu_derived_from_h"] = derived
    return df, rows


def _rel(root: Path, p: Path) -> str:
    try:
        return p.relative_to(root).as_posix()
    except ValueError:
        return str(p)


def _is(name: str, *suffixes: str) -> bool:
    low = name.lower()
    return any(low.endswith(sfx) for sfx in suffixes)


@dataclass
class _Source:
    kind: str            # csv | gfile | dgs | xyz
    path: Path
    combined: bool = False


def flight_sources(d: Path, root: Path) -> dict[str, _Source]:
    """The gravimeter and GNSS files of a flight directory.

    gravimeter: ``gravimeter.csv[.gz]``, ``gravimeter.xyz[.gz]``, a G file
    (``gravimeter.g``, ``*.G``, or a ``*.dat`` whose content is a G file) or DGS
    records (a ``*.dat`` whose content is DGS records; :func:`app.io.dgs.sniff_dat`);
    GNSS: ``gnss.csv[.gz]``, ``gnss.xyz[.gz]``; and one ``<name>.xyz[.gz]``
    serves every sensor that has no file of its own (a combined file).

    Raises
    ------
    InputError
        Two candidates for one sensor, raw DGS strings, or a missing sensor.
    """
    files = sorted(p for p in d.iterdir() if p.is_file() and not p.name.startswith("."))
    grav: list[_Source] = []
    gnss: list[_Source] = []
    other_xyz: list[Path] = []
    unknown_dat: list[str] = []
    for f in files:
        low = f.name.lower()
        if low in ("gravimeter.csv", "gravimeter.csv.gz"):
            grav.append(_Source("csv", f))
        elif low in ("gnss.csv", "gnss.csv.gz"):
            gnss.append(_Source("csv", f))
        elif low in ("gravimeter.xyz", "gravimeter.xyz.gz"):
            grav.append(_Source("xyz", f))
        elif low in ("gnss.xyz", "gnss.xyz.gz"):
            gnss.append(_Source("xyz", f))
        elif _is(f.name, ".xyz", ".xyz.gz"):
            other_xyz.append(f)
        elif _is(f.name, ".dat", ".dat.gz"):
            what = sniff_dat(f)
            if what in ("gfile", "dgs"):
                grav.append(_Source(what, f))
            elif what == "dgs_raw":
                raise InputError(_rel(root, f), 1, None,
                                 "raw DGS serial strings ('$…': A/D counts before the meter's calibration) are not "
                                 "read: use the records the DGS logger writes")
            else:
                hint = dat_hint(f)
                unknown_dat.append(f"{f.name} ({hint})" if hint else f.name)
        elif low in ("gravimeter.g", "gravimeter.g.gz") or f.name.endswith((".G", ".G.gz")):
            grav.append(_Source("gfile", f))
    where = _rel(root, d) + "/"
    if len(other_xyz) > 1:
        raise InputError(where, None, None,
                         f"several XYZ files in one flight ({', '.join(p.name for p in other_xyz)}): use "
                         f"gravimeter.xyz and gnss.xyz, or one <name>.xyz holding both")
    if other_xyz:
        if grav and gnss:
            raise InputError(_rel(root, other_xyz[0]), None, None,
                             f"the flight already has its gravimeter file ({grav[0].path.name}) and GNSS file "
                             f"({gnss[0].path.name}): remove {other_xyz[0].name} or them")
        for lst in (grav, gnss):
            if not lst:
                lst.append(_Source("xyz", other_xyz[0], combined=True))
    for what, lst in (("gravimeter", grav), ("GNSS", gnss)):
        if len(lst) > 1:
            names = ", ".join(x.path.name for x in lst)
            raise InputError(where, None, None,
                             f"several {what} files in one flight ({names}): keep one per flight directory "
                             f"(merge split recordings into one file, or make each a flight of its own)")
    if not gnss:
        raise InputError(_rel(root, d / "gnss.csv"), None, None,
                         f"flight {d.name} has no gnss.csv (or gnss.csv.gz, gnss.xyz, or one <name>.xyz with both "
                         f"sensors)")
    if not grav:
        extra = (f"; {', '.join(unknown_dat)} is neither DGS records nor a G file" if unknown_dat else "")
        raise InputError(_rel(root, d / "gravimeter.csv"), None, None,
                         f"flight {d.name} has no gravimeter.csv (or .csv.gz, gravimeter.xyz, a G file: "
                         f"gravimeter.g, *.G, G*.dat, or DGS records *.dat){extra}")
    return {"gravimeter": grav[0], "gnss": gnss[0]}


def _xyz_role(src: _Source, role: str, root: Path, config: SurveyConfig, scans: dict) -> XyzTable:
    if src.path not in scans:
        scans[src.path] = scan_xyz(src.path, _rel(root, src.path))
    return xyz_table(scans[src.path], role, config.columns, combined=src.combined)


@dataclass
class _BlockSource:
    display: str
    table: XyzTable
    time: np.ndarray      # validated times of the table's rows


def lines_from_blocks(block_sources: dict[str, dict[str, _BlockSource]]) -> tuple[pd.DataFrame, list]:
    """Survey lines from the XYZ blocks of each flight (when there is no lines.csv).

    ``Line <id>`` → kind main, ``Tie <id>`` → kind tie, ``t_start``/``t_end`` =
    the block's first/last time in the flight's GNSS file (the gravimeter
    file's when the GNSS file has no such blocks); other blocks are not
    survey lines.  The gravimeter and GNSS files must list the same lines.

    Returns
    -------
    lines : DataFrame[line, flight, t_start, t_end, kind, track]
    origins : list of (file, row)
        Where each line was declared (its block header).
    """
    recs: list[dict] = []
    origins: list[tuple[str, int | None]] = []
    first_seen: dict[str, tuple[str, int | None]] = {}
    for flight, by_role in block_sources.items():
        def survey_blocks(bs: _BlockSource):
            return [b for b in bs.table.blocks if b.kind is not None]

        use = by_role.get("gnss") if "gnss" in by_role and survey_blocks(by_role["gnss"]) else by_role.get("gravimeter")
        if use is None or not survey_blocks(use):
            continue
        for other in by_role.values():
            if other is use or not survey_blocks(other):
                continue
            a = {(b.line_id, b.kind) for b in survey_blocks(use)}
            b_ = {(b.line_id, b.kind) for b in survey_blocks(other)}
            if a != b_:
                diff = sorted(a ^ b_)
                raise InputError(other.display, None, None,
                                 f"the Line/Tie blocks of {other.display} and {use.display} differ "
                                 f"({', '.join(f'{k} {i}' for i, k in diff[:5])}): both files must list the same "
                                 f"survey lines")
        for b in survey_blocks(use):
            t = use.time[b.start:b.stop]
            if t.size < 2:
                raise InputError(use.display, b.row, "line",
                                 f"{b.keyword.capitalize()} {b.line_id} has {t.size} sample(s): a survey line needs "
                                 f"at least 2")
            if b.line_id in first_seen:
                f0, r0 = first_seen[b.line_id]
                raise InputError(use.display, b.row, "line",
                                 f"line id {b.line_id!r} appears in two blocks (first in {f0} at row {r0}): a line "
                                 f"flown again (kind repeat) or split needs a lines.csv listing each part with its "
                                 f"own id (and track); otherwise give the blocks distinct ids")
            first_seen[b.line_id] = (use.display, b.row)
            recs.append({"line": b.line_id, "flight": flight, "t_start": float(t[0]), "t_end": float(t[-1]),
                         "kind": b.kind, "track": None})
            origins.append((use.display, b.row))
    lines = pd.DataFrame(recs, columns=["line", "flight", "t_start", "t_end", "kind", "track"])
    lines["track"] = pd.Series([None] * len(lines), dtype=object)
    return lines, origins


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
    lines = None
    origins: list[tuple[str, int | None]] = []
    if (root / "lines.csv").is_file():
        lines, line_rows = read_lines(root / "lines.csv")
        origins = [("lines.csv", int(r)) for r in line_rows]
    flight_dirs = _flight_dirs(root, lines, origins)
    flights: dict[str, Flight] = {}
    series: dict[str, _FlightSeries] = {}
    block_sources: dict[str, dict[str, _BlockSource]] = {}
    notes: list[str] = []
    used = set(lines["flight"]) if lines is not None else None
    for name, d in flight_dirs.items():
        failed = None
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                fs = _read_flight_series(name, d, root, config, block_sources)
            except InputError as exc:
                if used is None or name in used:
                    # raised below, after what the reader said before it (a no-data marker
                    # read as missing explains the "missing value" error that follows)
                    failed, fs = exc, None
                else:
                    # No line of lines.csv uses this flight: a folder holding only a GNSS file, or a
                    # ferry or test flight with broken data, must not stop the survey. Said, not hidden.
                    warnings.warn(f"flight {name} is not read (no line in lines.csv uses it): {exc}", stacklevel=2)
                    block_sources.pop(name, None)
                    fs = None
        for w in caught:
            warnings.warn(str(w.message), stacklevel=2)   # still on stderr for scripts
            if str(w.message) not in notes:
                notes.append(str(w.message))
        if failed is not None:
            raise failed
        if fs is None:
            continue
        series[name] = fs
        flights[name] = Flight(name=name, gravimeter=fs.grav, gnss=fs.gnss, gravimeter_path=fs.grav_path,
                               gnss_path=fs.gnss_path,
                               vu_derived_from_h=bool(fs.gnss.attrs.get("vu_derived_from_h", False)))
    if lines is None:
        lines, origins = lines_from_blocks(block_sources)
        missing = [f for f in flights if f not in block_sources or not (lines["flight"] == f).any()]
        if len(lines) == 0 or missing:
            which = f" (flight {', '.join(missing)} has none)" if missing and len(lines) else ""
            raise InputError("lines.csv", None, None,
                             f"file not found, and the survey lines cannot be taken from the flights' XYZ Line/Tie "
                             f"blocks{which}: add a lines.csv")
    for name, fs in series.items():
        _check_line_windows(name, fs, lines, origins, config.processing.max_gap_s, config.processing.max_nan_run)
    for n in [n for name, fs in series.items() for n in stuck_sensor_notes(name, fs, lines)] + \
            repeat_track_notes(lines, origins):
        warnings.warn(n, stacklevel=2)
        notes.append(n)
    return Survey(root=root, config=config, lines=lines, flights=flights, notes=notes)


def stuck_sensor_notes(name: str, fs, lines: pd.DataFrame, min_s: float = 5.0, min_samples: int = 10) -> list[str]:
    """Notes on runs of one unchanging f_z value inside flight ``name``'s line windows: in the air
    the vertical specific force varies by thousands of mGal from one second to the next, so a
    value repeated for ``min_s`` s and ``min_samples`` samples is a stuck or saturated sensor —
    those epochs are not a measurement (processing goes on: the analyst decides where to cut)."""
    t = fs.grav["time"].to_numpy(float)
    f = fs.grav["f_z"].to_numpy(float)
    out = []
    sel = lines.loc[lines["flight"] == name]
    for line, a, b in zip(sel["line"], sel["t_start"].to_numpy(float), sel["t_end"].to_numpy(float)):
        i0, i1 = np.searchsorted(t, a, side="left"), np.searchsorted(t, b, side="right")
        if i1 - i0 < min_samples:
            continue
        starts, steps = true_runs(np.diff(f[i0:i1]) == 0.0)   # runs of unchanged steps
        stops, n = starts + steps, steps + 1                    # last sample, samples per run
        dur = t[i0 + stops] - t[i0 + starts]
        k = np.flatnonzero((n >= min_samples) & (dur >= min_s))
        if not k.size:
            continue
        j = int(k[np.argmax(dur[k])])
        r0, r1 = i0 + int(starts[j]), i0 + int(stops[j])
        out.append(f"{fs.grav_disp}: f_z is constant ({f[r0]:.6g} m/s²) for {dur[j]:.1f} s, {int(n[j])} samples "
                   f"(rows {int(fs.grav_rows[r0])}–{int(fs.grav_rows[r1])}) inside line {line}"
                   + (f", and in {k.size - 1} more run(s) there" if k.size > 1 else "")
                   + ": a stuck or saturated sensor? Those epochs are not a measurement — cut the line there "
                   "in lines.csv (two windows)")
    return out


def repeat_track_notes(lines: pd.DataFrame, origins: list) -> list[str]:
    """Notes on repeat lines whose track lines.csv does not give: a repeat line is left out of
    the crossovers and only its track's other passes measure it (the repeat-line accuracy), so
    one without a track is grouped by its position in stage 2
    (:func:`app.pipeline.stages.lines.infer_repeat_tracks`) and its track's only pass gives no
    figure — each says why."""
    out = []
    rep = np.flatnonzero((lines["kind"] == "repeat").to_numpy())
    tracks: dict[str, list[int]] = {}
    for i in rep:
        tr = lines["track"].iloc[i]
        if tr is None:
            ofile, orow = origins[i]
            out.append(f"{ofile} row {orow}: line {lines['line'].iloc[i]} is kind repeat but has no track: it is "
                       f"left out of the crossovers (as repeat lines are) and compared with the passes it flies one "
                       f"track with by their positions (stage 2, the report's repeat_tracks_inferred), or with none "
                       f"— give every pass of one track the same track id to set it (or make it kind main)")
        else:
            tracks.setdefault(str(tr), []).append(int(i))
    for tr, idx in tracks.items():
        if len(idx) == 1:
            i = idx[0]
            ofile, orow = origins[i]
            out.append(f"{ofile} row {orow}: track {tr} has one pass (line {lines['line'].iloc[i]}): it is left out "
                       f"of the crossovers (as repeat lines are) and a repeat-line accuracy needs at least two "
                       f"passes — check the track ids (or make it kind main)")
    return out


def _flight_dirs(root: Path, lines: pd.DataFrame | None, origins: list) -> dict[str, Path]:
    """The flight directories under ``flights/`` (names checked); with a lines.csv, every line's
    flight must be one of them."""
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
    if lines is not None:
        bad = np.flatnonzero(~lines["flight"].isin(known).to_numpy())
        if bad.size:
            i = int(bad[0])
            have = ", ".join(sorted(known)) or "none"
            raise InputError("lines.csv", origins[i][1], "flight",
                             f"line {lines['line'].iloc[i]} refers to flight {lines['flight'].iloc[i]!r}, which has no "
                             f"directory under flights/ (flights found: {have})")
    return flight_dirs


class _FlightSeries(NamedTuple):
    """One flight's validated tables with the file row of each record, the files' display names
    (relative to the survey) and paths."""

    grav: pd.DataFrame
    grav_rows: np.ndarray
    grav_disp: str
    gnss: pd.DataFrame
    gnss_rows: np.ndarray
    gnss_disp: str
    grav_path: Path
    gnss_path: Path


def _read_flight_series(name: str, d: Path, root: Path, config: SurveyConfig,
                        block_sources: dict[str, dict[str, _BlockSource]]) -> _FlightSeries:
    """Read one flight's GNSS and gravimeter files (CSV, G file, DGS or XYZ); an XYZ file's
    Line/Tie blocks are recorded in ``block_sources[name]`` (the lines when there is no lines.csv)."""
    p = config.processing
    src = flight_sources(d, root)
    scans: dict = {}
    gsrc, nsrc = src["gravimeter"], src["gnss"]
    gnss_disp, grav_disp = _rel(root, nsrc.path), _rel(root, gsrc.path)
    if nsrc.kind == "xyz":
        tab = _xyz_role(nsrc, "gnss", root, config, scans)
        gnss, derived = finish_gnss(tab.df, tab.rows, gnss_disp, config)
        gnss.attrs["vu_derived_from_h"] = derived
        gnss_rows = tab.rows
        block_sources.setdefault(name, {})["gnss"] = _BlockSource(gnss_disp, tab, gnss["time"].to_numpy())
    else:
        gnss, gnss_rows = read_gnss(nsrc.path, gnss_disp, config)
    tn = gnss["time"].to_numpy()
    if gsrc.kind == "xyz":
        tab = _xyz_role(gsrc, "gravimeter", root, config, scans)
        grav, grav_rows = _finish_series(tab.df, tab.rows, grav_disp, p.max_nan_run, GRAV_REQUIRED, GRAV_OPTIONAL,
                                         holes=("f_z",))
        grav = finish_gravimeter(grav.reset_index(drop=True), grav_rows, grav_disp, config)
        block_sources.setdefault(name, {})["gravimeter"] = _BlockSource(grav_disp, tab, grav["time"].to_numpy())
    else:
        grav, grav_rows = read_gravimeter(gsrc.path, grav_disp, config,
                                          time_offset_s=config.gravimeter.time_offset_s,
                                          gnss_time_range=(float(tn[0]), float(tn[-1])), kind=gsrc.kind)
    return _FlightSeries(grav, grav_rows, grav_disp, gnss, gnss_rows, gnss_disp, gsrc.path, nsrc.path)


def _time_scale_name(t: float) -> str:
    """What a time stamp (s) of this size usually is."""
    for hi, what in ((86400.0 * 1.05, "seconds of day"), (604800.0 * 1.01, "GPS seconds of week"),
                     (1.6e9, "GPS seconds since 1980-01-06"), (2.2e9, "Unix time (seconds since 1970)")):
        if abs(t) < hi:
            return what
    return "not seconds (milliseconds?)"


def _check_one_time_scale(fs: _FlightSeries, ts: np.ndarray, te: np.ndarray) -> None:
    """The gravimeter and GNSS files of a flight must share one time scale: when their records do
    not even overlap, the error names the file that holds none of the flight's line windows
    (``ts``, ``te``; the gravimeter's when both or neither do), both ranges, what each scale
    looks like and the whole days (plus seconds) between them — rather than "a window outside
    the data", which blames lines.csv."""
    tg, tn = fs.grav["time"].to_numpy(float), fs.gnss["time"].to_numpy(float)
    if tg[-1] >= tn[0] and tn[-1] >= tg[0]:
        return
    holds_g = bool(np.any((ts >= tg[0]) & (te <= tg[-1])))
    holds_n = bool(np.any((ts >= tn[0]) & (te <= tn[-1])))
    odd_is_gnss = holds_g and not holds_n
    disp, rows, t = (fs.gnss_disp, fs.gnss_rows, tn) if odd_is_gnss else (fs.grav_disp, fs.grav_rows, tg)
    d = 0.5 * (tn[0] + tn[-1]) - 0.5 * (tg[0] + tg[-1])
    days = float(np.round(d / 86400.0))
    rest = d - 86400.0 * days
    between = (f"; they differ by {days:.0f} whole days{f' and {rest:+.0f} s' if abs(rest) >= 0.5 else ''}"
               if days != 0 and abs(rest) <= 120.0 else "")
    raise InputError(disp, int(rows[0]), "time",
                     f"the records of {fs.grav_disp} ({tg[0]:.3f}–{tg[-1]:.3f} s, like {_time_scale_name(tg[0])}) "
                     f"and {fs.gnss_disp} ({tn[0]:.3f}–{tn[-1]:.3f} s, like {_time_scale_name(tn[0])}) do not "
                     f"overlap: the two files are on different time scales{between}; put both, and the lines.csv "
                     f"windows, on one scale (the windows lie in "
                     f"{'neither file' if not (holds_g or holds_n) else (fs.grav_disp if holds_g else fs.gnss_disp)})")


def _check_line_windows(name: str, fs: _FlightSeries, lines: pd.DataFrame, origins: list, max_gap_s: float,
                        max_nan_run: int = 0) -> None:
    """Every line window of flight ``name`` lies within both files' data, holds at least two
    GNSS epochs (the epochs a line is estimated at: a window between two of them has none, and
    processing failed on it after the identification) and has no gap longer than ``max_gap_s``
    (processing.max_gap_s) inside it — in the gravimeter's record, nor longer than the
    ``max_nan_run`` missing samples tolerated there (left as holes, :func:`_finish_series`)."""
    tg = fs.grav["time"].to_numpy()
    tn = fs.gnss["time"].to_numpy()
    sel = np.flatnonzero((lines["flight"] == name).to_numpy())
    if not sel.size:
        return
    ts = lines["t_start"].to_numpy()[sel]
    te = lines["t_end"].to_numpy()[sel]
    _check_one_time_scale(fs, ts, te)
    for k, i in enumerate(sel):
        ofile, orow = origins[i]
        for t, disp in ((tg, fs.grav_disp), (tn, fs.gnss_disp)):
            if ts[k] < t[0] or te[k] > t[-1]:
                col, val = ("t_start", ts[k]) if ts[k] < t[0] else ("t_end", te[k])
                raise InputError(ofile, orow, col,
                                 f"line {lines['line'].iloc[i]} window {ts[k]:.3f}–{te[k]:.3f} s is outside "
                                 f"the data of {disp} ({t[0]:.3f}–{t[-1]:.3f} s): {col} = {val:.3f}")
    n_epochs = np.searchsorted(tn, te, side="right") - np.searchsorted(tn, ts, side="left")
    few = np.flatnonzero(n_epochs < 2)
    if few.size:
        k = int(few[0])
        ofile, orow = origins[sel[k]]
        raise InputError(ofile, orow, "t_end",
                         f"line {lines['line'].iloc[sel[k]]} window {ts[k]:.3f}–{te[k]:.3f} s "
                         f"({te[k] - ts[k]:.3g} s) holds {int(n_epochs[k])} epoch(s) of {fs.gnss_disp}: a line "
                         f"needs at least 2 (check t_start and t_end)")
    grav_gap_s = max_gap_s
    if max_nan_run > 0 and len(tg) > 1:
        grav_gap_s = max(max_gap_s, 1.01 * (max_nan_run + 1) * float(np.median(np.diff(tg))))
    for t, rows, disp, limit_s in ((tg, fs.grav_rows, fs.grav_disp, grav_gap_s),
                                   (tn, fs.gnss_rows, fs.gnss_disp, max_gap_s)):
        g = gap_rows_in_windows(t, ts, te, limit_s)
        hit = np.flatnonzero(g >= 0)
        if hit.size:
            k = int(hit[0])
            j = int(g[k])
            raise InputError(disp, int(rows[j]), "time",
                             f"gap of {t[j] - t[j - 1]:.3f} s before this row (from {t[j - 1]:.3f} to "
                             f"{t[j]:.3f} s) inside line {lines['line'].iloc[sel[k]]} "
                             f"({ts[k]:.3f}–{te[k]:.3f} s); at most {limit_s:g} s allowed "
                             f"(processing.max_gap_s): split the line at the gap in lines.csv (two windows), "
                             f"or raise max_gap_s — holes that cut a line into stretches of a few minutes "
                             f"hide the low frequencies the noise model is fitted on (docs/METHOD.md, gaps)")


# --------------------------------------------------------------------------- QC summary


def _window_stats(t: np.ndarray, a, b) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per window ``[a_k, b_k]`` (s) of the sorted stamps ``t``: median rate (Hz), largest step
    (s), sample count, and the index range ``[i0, i1)`` of its samples.

    The largest step includes the steps from the last sample before the window
    and to the first sample after it, so a hole at a window edge is seen.
    One pass of index arithmetic for all windows (a survey may list 20 000 lines).
    """
    a = np.atleast_1d(np.asarray(a, dtype=float))
    b = np.atleast_1d(np.asarray(b, dtype=float))
    i0, i1 = np.searchsorted(t, a, side="left"), np.searchsorted(t, b, side="right")
    steps = np.diff(t)
    lo, hi = np.maximum(i0 - 1, 0), np.minimum(i1 + 1, t.size) - 1   # steps[lo:hi] bound the window
    rate = np.full(a.size, np.nan)
    gap = np.full(a.size, np.nan)
    for k in range(a.size):
        if i1[k] - i0[k] >= 2:
            rate[k] = median_rate_hz(t[i0[k]:i1[k]])
        if hi[k] > lo[k]:
            gap[k] = steps[lo[k]:hi[k]].max()
    return rate, gap, (i1 - i0).astype(np.int64), i0, i1


def _window_lengths_km(cum_km: np.ndarray, i0: np.ndarray, i1: np.ndarray) -> np.ndarray:
    """Path length (km) through the positions ``[i0, i1)`` from the cumulative step lengths
    ``cum_km`` (0 first): 0 for fewer than two positions."""
    last = np.maximum(i1 - 1, i0)
    return np.where(i1 - i0 >= 2, cum_km[last] - cum_km[i0], 0.0)


_SUMMARY_COLUMNS = ["level", "flight", "line", "kind", "track", "t_start", "t_end", "duration_s",
                    "gravimeter_rate_hz", "gnss_rate_hz", "gravimeter_max_gap_s", "gnss_max_gap_s",
                    "n_gravimeter", "n_gnss", "length_km"]


def _summary_block(level: str, flight: str, a, b, tg, tn, cum_km, line=None, kind=None, track=None) -> pd.DataFrame:
    """Rows of :func:`survey_summary` for the windows ``[a, b]`` of one flight."""
    a = np.atleast_1d(np.asarray(a, dtype=float))
    b = np.atleast_1d(np.asarray(b, dtype=float))
    rg, gg, ng, _, _ = _window_stats(tg, a, b)
    rn, gn, nn, j0, j1 = _window_stats(tn, a, b)
    cols = {k: np.full(a.size, None, dtype=object) if v is None else np.asarray(v, dtype=object)
            for k, v in (("line", line), ("kind", kind), ("track", track))}
    return pd.DataFrame({"level": level, "flight": flight, **cols, "t_start": a, "t_end": b, "duration_s": b - a,
                         "gravimeter_rate_hz": rg, "gnss_rate_hz": rn, "gravimeter_max_gap_s": gg,
                         "gnss_max_gap_s": gn, "n_gravimeter": ng, "n_gnss": nn,
                         "length_km": _window_lengths_km(cum_km, j0, j1)}, columns=_SUMMARY_COLUMNS)


def survey_summary(survey: Survey) -> pd.DataFrame:
    """QC table, one row per flight (``level = "flight"``) then one per line (``level = "line"``).

    Columns: ``level, flight, line, kind, track, t_start, t_end, duration_s,
    gravimeter_rate_hz, gnss_rate_hz, gravimeter_max_gap_s, gnss_max_gap_s,
    n_gravimeter, n_gnss, length_km``.  Rates are from the median interval,
    gaps are the largest time step among the samples inside (and bounding)
    the window, ``length_km`` is the ellipsoidal path length of the GNSS
    positions within the window (at flight height), ``line``/``kind``/``track``
    are None on flight rows.  Each flight's stamps and step lengths are read
    once for all its lines.
    """
    flights, lines = [], []
    by_flight = {name: idx for name, idx in survey.lines.groupby("flight", sort=False).indices.items()}
    for name, fl in survey.flights.items():
        tg = fl.gravimeter["time"].to_numpy(dtype=float)
        tn = fl.gnss["time"].to_numpy(dtype=float)
        g = fl.gnss
        steps = step_lengths_km(g["lat"].to_numpy(), g["lon"].to_numpy(), g["h"].to_numpy())
        cum = np.concatenate([[0.0], np.cumsum(steps)])
        a, b = float(min(tg[0], tn[0])), float(max(tg[-1], tn[-1]))
        block = _summary_block("flight", name, a, b, tg, tn, cum)
        block["length_km"] = float(np.sum(steps))   # the whole track, as path_length_km sums it
        flights.append(block)
        if name in by_flight:
            ls = survey.lines.iloc[by_flight[name]]
            lines.append(_summary_block("line", name, ls["t_start"], ls["t_end"], tg, tn, cum,
                                        ls["line"].to_numpy(), ls["kind"].to_numpy(), ls["track"].to_numpy()))
    out = pd.concat(flights + lines, ignore_index=True) if flights else pd.DataFrame(columns=_SUMMARY_COLUMNS)
    # lines in the order lines.csv lists them (the blocks above are grouped by flight)
    listed = [np.asarray(by_flight[n]) for n in survey.flights if n in by_flight]
    if listed:
        order = np.concatenate([np.arange(len(flights)),
                                len(flights) + np.argsort(np.concatenate(listed), kind="stable")])
        out = out.iloc[order]
    out = out.reset_index(drop=True)
    for c in ("line", "kind", "track"):  # None (not NaN, which concatenating blocks may give) where empty
        out[c] = pd.Series([None if v is None or (isinstance(v, float) and np.isnan(v)) else v for v in out[c]],
                           index=out.index, dtype=object)
    return out
