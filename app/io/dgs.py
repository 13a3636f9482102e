"""Reader of Dynamic Gravity Systems AT1A / AT1M gravimeter records (``*.dat``).

Layout
------
One record per line, comma-separated, no header (a first line of names is
skipped), in the order the DGS logger writes them and DGS's own processing
code reads them (DynamicGravitySystems/DGP ``read_at1a``; ``GravityTypes.AT1A``)::

    0 gravity      meter reading, mGal, arbitrary offset (see below)
    1 long_accel   long(itudinal) platform accelerometer
    2 cross_accel  cross platform accelerometer
    3 beam         beam position (V, −5…+5 between the stops)
    4 temp         sensor temperature (°C)
    5 status       status word (integer bit field, bit 0 first)
    6 pressure     sensor pressure
    7 etemp        electronics temperature (°C)
    8 gps_week     GPS week              ┐ present once the meter is synchronised
    9 gps_sow      GPS seconds of week   ┘ to GPS (10 fields)
    10 (a 1 Hz counter some loggers append; ignored)

so a file has 8, 10 or 11 fields per line.  Example (from DGP's tests)::

    10061.171360,-0.026226,-0.094891,-0.093803,62.253987,21061,39.690004,52.263138,1959,219697.800

Status bits (DGS AT1M data description; DGP ``_extract_bits``): 0 clamp,
1 unclamp, 2 GPS synchronised, 3 feedback on, 6 A/D locked, 7 command received,
8–9 platform nav mode, 11 sensor com fail, 12 valid GPS NMEA, 13–15 A/D, long,
cross saturation, 16 on line.  Only bit 2 is used here: a record whose GPS time
is not synchronised (bit 2 clear, or GPS week 0) carries no valid time stamp
and is dropped with a warning (``df.attrs["unsynced_records"]``), as DGS's own
processing does.  The raw serial strings (``$UW,…``, ``$AT1M_…``: A/D counts
before the meter's calibration) are not read: export the logger's records.

Time
----
``t = (gps_week − week₀)·604800 + gps_sow + time_offset_s`` with ``week₀`` the
week of the first synchronised record: GPS seconds of that week, continuous
across a week rollover.  The survey's GNSS times must be on the same scale;
``time_offset_s`` (``[gravimeter]`` of survey.toml) maps it onto another one
(e.g. ``week₀·604800`` for seconds since the GPS epoch, ``−day·86400`` for GPS
seconds of day, a known filter delay).  When it is None, the survey reader
adds the whole number of days that best puts the records inside the GNSS time
range (as for G files: GPS seconds of week or since the epoch, or seconds of
day, all match; a GNSS on UTC keeps the leap seconds, which the pipeline's
gravimeter–GNSS time-offset estimate, searched over ±``max_time_offset_s`` = 60 s,
finds and removes: −18.05 s on the sample survey, its result unchanged).  Records without the GPS fields
(8 per line) have no time of their own: the survey needs ``gravimeter.rate_hz``
and ``gravimeter.time_offset_s`` (the survey time of the first record), and the
records are taken as contiguous at that rate.

Gravity
-------
``gravity`` is the meter's filtered reading in mGal with an arbitrary
instrument offset (DGS calls it "uncorrected gravity, mGal"; its level is set
by a reading at a base of known gravity).  The pipeline needs a specific force
≈ +9.8 m/s², so ``f_z = (gravity + offset)·1e-5`` m/s² with ``offset`` =
``gravimeter.reading_offset_mgal`` when declared; otherwise 0 when the readings
already look absolute (median 7·10⁵–1.3·10⁶ mGal), else the nominal
:data:`NOMINAL_OFFSET_MGAL` = 978000 mGal (≈ normal gravity at the equator),
with a warning: the base tie to ``base_gravity_mgal`` at the parking-place
readings then fixes the level (a constant error of f_z is a constant error of
z, which the tie removes).  The offset used is in ``df.attrs``.

Damaged records (as in a CSV, :mod:`app.io.tables`): a record repeated exactly is dropped; a
no-data marker (−9999, 99999999, ±1e32 …) in ``gravity``, or a run of exact zeros between
readings more than ``GRAVITY_ZERO_DROPOUT_MGAL`` (100 mGal) from 0, is a missing reading — a
hole of the record —, with a warning.

``long_accel`` and ``cross_accel`` are returned but not turned into ``f_x``,
``f_y``: their units are not documented consistently (the AT1M data
description gives Gal for the long and mGal for the cross accelerometer) and
they are along and across the platform heading, not east and north.
"""

from __future__ import annotations

import gzip
import io
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from app.io.errors import InputError
from app.io.gfile import MIN_FIELDS as GFILE_MIN_FIELDS
from app.io.tables import (
    check_finite,
    check_time_increasing,
    drop_duplicate_rows,
    fill_short_nan_runs,
    mark_no_data,
    read_text,
)

__all__ = ["read_dgs", "sniff_dat", "dat_hint", "DGS_FIELDS", "NOMINAL_OFFSET_MGAL", "GPS_SYNC_BIT", "SECONDS_PER_WEEK"]

DGS_FIELDS = ("gravity", "long_accel", "cross_accel", "beam", "temp", "status", "pressure", "etemp",
              "gps_week", "gps_sow", "hz1_counter")
DGS_FIELD_COUNTS = (8, 10, 11)
GPS_SYNC_BIT = 2
SECONDS_PER_WEEK = 604800.0
#: mGal added to relative DGS readings when no reading_offset_mgal is declared
NOMINAL_OFFSET_MGAL = 978000.0
#: median readings (mGal) taken as already absolute
ABSOLUTE_READING_MGAL = (7e5, 1.3e6)
#: a run of exact zeros in ``gravity`` between readings farther than this from 0 (mGal) is a dropout
GRAVITY_ZERO_DROPOUT_MGAL = 100.0
_PHYSICAL = ("gravity", "long_accel", "cross_accel", "beam", "temp", "pressure", "etemp")


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _open_text(path: Path):
    if path.name.lower().endswith(".gz"):
        return gzip.open(path, "rt", encoding="utf-8-sig", errors="replace", newline="")
    return open(path, encoding="utf-8-sig", errors="replace", newline="")


_SNIFF_LINE_CHARS = 1 << 16
_SNIFF_MAX_LINES = 1000


def _first_lines(path, n: int) -> list[str]:
    """The first ``n`` non-blank lines of a text file, stripped ([] when unreadable), each cut at
    ``_SNIFF_LINE_CHARS`` and at most ``_SNIFF_MAX_LINES`` lines looked at: a sniff reads a few
    lines, never a whole file (a gzip expanding to one endless line would have been read whole)."""
    lines: list[str] = []
    try:
        with _open_text(Path(path)) as fh:
            for _ in range(_SNIFF_MAX_LINES):
                raw = fh.readline(_SNIFF_LINE_CHARS)
                if not raw:
                    break
                if raw.strip():
                    lines.append(raw.strip())
                    if len(lines) >= n:
                        break
    except (OSError, EOFError, UnicodeDecodeError):
        return []
    return lines


def _fields(s: str) -> list[str]:
    return [f.strip() for f in s.split(",")] if "," in s else s.split()


def dat_hint(path) -> str:
    """Why a ``.dat`` file that :func:`sniff_dat` does not recognise is neither: for comma-separated
    numeric records, their number of fields against DGS's 8, 10 or 11 ("" otherwise)."""
    lines = _first_lines(path, 3)
    data = [s for s in lines if all(_is_number(f) for f in _fields(s))]
    if not data or "," not in data[0]:
        return ""
    n = len(_fields(data[0]))
    return (f"comma-separated numeric records of {n} fields; DGS AT1A/AT1M records have 8 (gravity, long_accel, "
            "cross_accel, beam, temp, status, pressure, Etemp), 10 (+ GPS week, seconds) or 11 (+ a counter): "
            "export those fields in that order")


def sniff_dat(path, n_lines: int = 5) -> str | None:
    """What a ``.dat`` file holds, from its first lines.

    Returns
    -------
    ``"dgs"``
        DGS AT1A/AT1M records: comma-separated, 8, 10 or 11 numeric fields
        (after an optional line of names).
    ``"dgs_raw"``
        DGS raw serial strings (a line starting with ``$``).
    ``"gfile"``
        A GT-1A/GT-2A G file: a header line, then messages of at least 16 fields.
    None
        Anything else (or an unreadable file).
    """
    lines = _first_lines(path, n_lines + 1)
    if not lines:
        return None
    if lines[0].startswith("$"):
        return "dgs_raw"
    header = not all(_is_number(f) for f in _fields(lines[0]))
    data = lines[1:] if header else lines
    if not data:
        return None
    f = _fields(data[0])
    if "," in data[0] and len(f) in DGS_FIELD_COUNTS and all(_is_number(x) for x in f):
        if all(len(_fields(s)) == len(f) for s in data):
            return "dgs"
    if header and len(f) >= GFILE_MIN_FIELDS and all(_is_number(x) for x in f[:4]):
        return "gfile"
    return None


def _read_records(path: Path, display: str) -> tuple[pd.DataFrame, np.ndarray]:
    text = read_text(path, display)
    all_lines = text.split("\n")
    idx = [i for i, s in enumerate(all_lines) if s.strip()]
    if not idx:
        raise InputError(display, None, None, "the file is empty")
    first = [f.strip() for f in all_lines[idx[0]].split(",")]
    if all_lines[idx[0]].lstrip().startswith("$"):
        raise InputError(display, idx[0] + 1, None,
                         "raw DGS serial strings ('$…': A/D counts before the meter's calibration) are not read: "
                         "use the records the DGS logger writes (gravity, long_accel, cross_accel, beam, temp, status, "
                         "pressure, Etemp, GPS week, GPS seconds)")
    if not all(_is_number(f) for f in first):
        idx = idx[1:]  # a line of names
    if len(idx) < 2:
        raise InputError(display, None, None, f"the file has {len(idx)} record(s); at least 2 needed")
    data_lines = [all_lines[i] for i in idx]
    rows = np.asarray(idx, dtype=np.int64) + 1
    counts = np.fromiter((s.count(",") + 1 for s in data_lines), dtype=np.int64, count=len(data_lines))
    n = int(counts[0])
    if n not in DGS_FIELD_COUNTS:
        raise InputError(display, int(rows[0]), None,
                         f"a DGS record has 8 fields (gravity, long_accel, cross_accel, beam, temp, status, pressure, "
                         f"Etemp), 10 with GPS week and seconds, or 11 with a counter; this one has {n}")
    if counts[-1] < n and len(data_lines) > 2 and not (counts[:-1] != n).any():
        # the logger stopped (or the file was copied while written) in the middle of the last record
        warnings.warn(f"{display}: the last record (row {int(rows[-1])}) has {int(counts[-1])} of the {n} fields: "
                      "cut short when the recording stopped, dropped", stacklevel=3)
        data_lines, rows, counts = data_lines[:-1], rows[:-1], counts[:-1]
    bad = np.flatnonzero(counts != n)
    if bad.size:
        k = int(bad[0])
        raise InputError(display, int(rows[k]), None,
                         f"this record has {int(counts[k])} fields, the first (row {int(rows[0])}) has {n}")
    names = list(DGS_FIELDS[:n])
    buf = io.StringIO("\n".join(data_lines))
    try:
        df = pd.read_csv(buf, header=None, names=names, dtype=np.float64, skipinitialspace=True,
                         skip_blank_lines=False, engine="c")
    except ValueError:
        buf.seek(0)
        raw = pd.read_csv(buf, header=None, names=names, dtype=str, skipinitialspace=True, keep_default_na=False,
                          engine="c")
        for col in names:
            s = raw[col].str.strip()
            badc = np.flatnonzero(pd.to_numeric(s, errors="coerce").isna().to_numpy() & (s != "").to_numpy())
            if badc.size:
                raise InputError(display, int(rows[badc[0]]), col, f"not a number: {s.iloc[badc[0]]!r}") from None
        raise InputError(display, None, None, "cannot parse the records") from None
    return df, rows


def _status_words(df: pd.DataFrame, rows: np.ndarray, display: str) -> np.ndarray:
    """The status words as int64 (each must be a non-negative integer)."""
    status = df["status"].to_numpy()
    if np.any(status != np.round(status)) or np.any(status < 0):
        i = int(np.flatnonzero((status != np.round(status)) | (status < 0))[0])
        raise InputError(display, int(rows[i]), "status", f"the status word must be a non-negative integer, "
                                                           f"got {status[i]!r}")
    return status.astype(np.int64)


class _TimedRecords(NamedTuple):
    """Records synchronised to GPS time, with their survey times."""

    df: pd.DataFrame
    rows: np.ndarray
    status: np.ndarray
    time: np.ndarray
    n_unsynced: int        # records dropped (not synchronised)


def _gps_timed_records(df: pd.DataFrame, rows: np.ndarray, status: np.ndarray, display: str,
                       time_offset_s: float | None) -> _TimedRecords:
    """Drop the records not synchronised to GPS time (status bit 2 clear or GPS week 0; a warning),
    and time the others: GPS seconds since the first record's week + ``time_offset_s``."""
    week = df["gps_week"].to_numpy()
    synced = ((status >> GPS_SYNC_BIT) & 1).astype(bool) & (week > 0)
    n_unsynced = int((~synced).sum())
    if n_unsynced:
        first = int(rows[np.flatnonzero(~synced)[0]])
        if n_unsynced == len(df):
            raise InputError(display, first, "status",
                             "no record is synchronised to GPS time (status bit 2 clear or GPS week 0): the "
                             "records have no valid time stamps")
        warnings.warn(f"{display}: {n_unsynced} record(s) not synchronised to GPS time (status bit 2 clear or "
                      f"GPS week 0) dropped (first at row {first})", stacklevel=3)
        df = df.loc[synced].reset_index(drop=True)
        rows = rows[synced]
        status = status[synced]
        week = week[synced]
    off = 0.0 if time_offset_s is None else float(time_offset_s)
    t = (week - week[0]) * SECONDS_PER_WEEK + df["gps_sow"].to_numpy() + off
    check_time_increasing(t, rows, display, column="gps_sow")
    return _TimedRecords(df, rows, status, t, n_unsynced)


def _reading_offset(g: np.ndarray, reading_offset_mgal: float | None, display: str) -> tuple[float, str]:
    """mGal added to the readings and why: declared, none for absolute readings, else the nominal
    offset (with a warning)."""
    if reading_offset_mgal is not None:
        return float(reading_offset_mgal), "declared"
    if ABSOLUTE_READING_MGAL[0] <= float(np.median(g)) <= ABSOLUTE_READING_MGAL[1]:
        return 0.0, "absolute"
    warnings.warn(f"{display}: relative DGS gravity readings (median {float(np.median(g)):.1f} mGal): the nominal "
                  f"{NOMINAL_OFFSET_MGAL:.0f} mGal added (declare gravimeter.reading_offset_mgal, or tie the level "
                  f"with base_gravity_mgal)", stacklevel=3)
    return NOMINAL_OFFSET_MGAL, "nominal"


def read_dgs(path, *, time_offset_s: float | None = 0.0, rate_hz: float | None = None,
             reading_offset_mgal: float | None = None, max_nan_run: int = 0,
             display: str | None = None) -> pd.DataFrame:
    """Read DGS AT1A/AT1M records into the gravimeter table (see the module docstring).

    Parameters
    ----------
    path : path-like
        The ``.dat`` file (``.gz`` allowed).
    time_offset_s : float or None
        Seconds added to the GPS seconds of week of the first record's week;
        for records without GPS fields, the survey time of the first record
        (required then).  None is 0 for records with GPS time.
    rate_hz : float, optional
        Record rate (Hz); required only for records without GPS fields.
    reading_offset_mgal : float, optional
        mGal added to ``gravity`` before the conversion to m/s² (None: see the
        module docstring).
    max_nan_run : int
        Longest run of empty fields interpolated (``gravity`` … ``Etemp``,
        ``gps_sow``); ``status`` and ``gps_week`` must always be present.
    display : str, optional
        File name used in error messages.

    Returns
    -------
    DataFrame
        ``time`` (s), ``f_z`` (m/s²), ``gravity_mgal``, ``long_accel``,
        ``cross_accel``, ``beam``, ``temp``, ``status`` (int), ``pressure``,
        ``etemp``, (``gps_week``, ``gps_sow``), ``source_row``.
        ``attrs``: ``reading_offset_mgal``, ``reading_offset_source``
        (``"declared"``, ``"absolute"``, ``"nominal"``), ``unsynced_records``.
    """
    path = Path(path)
    display = str(path) if display is None else display
    if not path.is_file():
        raise InputError(display, None, None, "file not found")
    df, rows = _read_records(path, display)
    df, rows = drop_duplicate_rows(df, rows, display)   # a record logged twice
    # as in a CSV: a no-data marker (−9999, ±1e32 …) in gravity, or a run of exact zeros between
    # readings farther than GRAVITY_ZERO_DROPOUT_MGAL from 0, is a missing value (a hole), with a warning
    mark_no_data(df, rows, display, ["gravity"], zero_dropout=(), zero_runs={"gravity": GRAVITY_ZERO_DROPOUT_MGAL})
    has_gps = "gps_sow" in df
    num = [c for c in df.columns if c != "hz1_counter"]
    check_finite(df, num, rows, display)
    for col in ("status",) + (("gps_week",) if has_gps else ()):
        miss = np.flatnonzero(np.isnan(df[col].to_numpy()))
        if miss.size:
            raise InputError(display, int(rows[miss[0]]), col, f"missing {col} (it cannot be interpolated)")
    # a missing gravity is a hole of the record, not a value to interpolate (a linear fill misses the
    # aircraft's acceleration at that record, which the GNSS still sees): filled here for the checks
    # below, its records dropped at the end
    hole_rows = rows[np.isnan(df["gravity"].to_numpy())]
    fill_short_nan_runs(df, [c for c in _PHYSICAL + ("gps_sow",) if c in df], rows, display, max_nan_run,
                        time_col=None)
    status = _status_words(df, rows, display)
    n_unsynced = 0
    if has_gps:
        timed = _gps_timed_records(df, rows, status, display, time_offset_s)
        df, rows, status, t, n_unsynced = timed.df, timed.rows, timed.status, timed.time, timed.n_unsynced
    else:
        if rate_hz is None or time_offset_s is None:
            raise InputError(display, None, None,
                             "the DGS records carry no GPS time (8 fields): declare gravimeter.rate_hz (the record "
                             "rate) and gravimeter.time_offset_s (the survey time of the first record) in survey.toml")
        t = float(time_offset_s) + np.arange(len(df)) / float(rate_hz)
    g = df["gravity"].to_numpy()
    offset, source = _reading_offset(g, reading_offset_mgal, display)
    out = {"time": t, "f_z": (g + offset) * 1e-5, "gravity_mgal": g}
    for c in ("long_accel", "cross_accel", "beam", "temp"):
        out[c] = df[c].to_numpy()
    out["status"] = status
    out["pressure"] = df["pressure"].to_numpy()
    out["etemp"] = df["etemp"].to_numpy()
    if has_gps:
        out["gps_week"] = df["gps_week"].to_numpy().astype(np.int64)
        out["gps_sow"] = df["gps_sow"].to_numpy()
    out["source_row"] = rows
    res = pd.DataFrame(out)
    if hole_rows.size:
        res = res.loc[~np.isin(rows, hole_rows)].reset_index(drop=True)
        warnings.warn(f"{display}: {hole_rows.size} missing gravity value(s) left as holes of the record (rows "
                      f"{', '.join(str(int(r)) for r in hole_rows[:5])}{', …' if hole_rows.size > 5 else ''}), "
                      "not interpolated here (the measurement puts a sample back where the record predicts it: "
                      "processing.gravimeter_fill_max_error_mgal)", stacklevel=2)
    res.attrs.update(reading_offset_mgal=offset, reading_offset_source=source, unsynced_records=n_unsynced)
    return res
