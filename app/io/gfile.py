"""Reader of the GT-1A / GT-2A ASCII "G" sensor file (SPEC §4).

Layout (one header line, then one message per line, fields separated by
blanks or commas)::

    0  message id
    1  time since power-on (s)
    2  UTC time of the message, hhmmss.ss
    3  sub-second (s, see ``subsecond_scale``)
    4  fine Z acceleration, first half-interval      5  … second half-interval
    6  coarse Z, first                                7  coarse Z, second
    8  X, first                                       9  X, second
    10 Y, first                                      11 Y, second
    12 normalized temperature
    13 … n−4   cross-coupling terms (any number, ≥ 0)
    n−3  proof-mass displacement
    n−2  saturation flag (0 = fine, anything else = saturated)
    n−1  checksum (kept as text, not verified: the algorithm is not documented)

Time construction
-----------------
``t_msg = hh·3600 + mm·60 + ss.ss + subsecond_scale·sub_second + time_offset_s``:
UTC seconds of day, unwrapped across midnight (a step back by more than half a
day adds 86 400 s), then mapped onto the survey time scale by
``time_offset_s`` (e.g. ``day_of_week·86400 + (GPS − UTC leap seconds)`` for GPS
seconds of week).  Put the fraction of the second in exactly one of the two
fields (hhmmss.ss or sub-second): the reader adds them.

Each message carries two values per channel, each the average over one half of
the message interval.  With ``stamp="end"`` (default) the message time is the
end of its interval, so with ``Δ_k = t_k − t_{k−1}`` the two samples are stamped
at the half-interval centres ``t_k − 0.75·Δ_k`` and ``t_k − 0.25·Δ_k``; with
``stamp="start"`` the interval is ``[t_k, t_{k+1})`` and the centres are
``t_k + 0.25·Δ_{k+1}`` and ``t_k + 0.75·Δ_{k+1}``.  The actual stamps are used
(never a median step), except for the one message at the edge that has no
neighbour, which uses the median interval.

Units: accelerations are multiplied by ``scale_to_ms2`` (default 1.0: the
file is in m/s², Z up, ≈ +9.8 at rest).

Damaged records (as in a CSV, :mod:`app.io.tables`): a message repeated exactly is dropped; a
no-data marker (−9999, ±1e32 …) in the Z, X or Y fields of the channel read, or a Z field
exactly 0 (a dropout: specific force is 0 only in free fall), is a missing value — a hole of
the record in Z —, with a warning; bytes that are not UTF-8 are read as cp1252 (a warning), so
garbage in a line is "not a number" at its row; a truncated ``.gz`` is an :class:`InputError`.

Saturation: ``on_saturation="drop"`` (default) removes both samples of a
saturated message, warns (``warnings.warn``) and records the count in
``df.attrs["saturated_messages"]``; the gap it leaves is then judged by the
survey's gap check like any other gap.  ``"flag"`` keeps them with
``saturated = True``; ``"error"`` raises :class:`InputError` at the first
saturated line (column ``saturation``).
"""

from __future__ import annotations

import io
import re
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from app.io.errors import InputError
from app.io.tables import (
    check_finite,
    check_time_increasing,
    drop_duplicate_rows,
    fill_short_nan_runs,
    mark_no_data,
    parser_error_row,
    read_text,
)

__all__ = ["read_gfile", "gfile_columns", "is_gfile_name"]

_HEAD = ["message_id", "time_since_power_on_s", "utc_hhmmss", "sub_second",
         "fine_z_1", "fine_z_2", "coarse_z_1", "coarse_z_2", "x_1", "x_2", "y_1", "y_2", "temperature"]
_TAIL = ["proof_mass_displacement", "saturation", "checksum"]
MIN_FIELDS = len(_HEAD) + len(_TAIL)


def gfile_columns(n_fields: int) -> list[str]:
    """Names of the fields of a G-file line with ``n_fields`` fields (cross-coupling ``cc_1…``)."""
    if n_fields < MIN_FIELDS:
        raise ValueError(f"a G-file line has at least {MIN_FIELDS} fields, got {n_fields}")
    n_cc = n_fields - MIN_FIELDS
    return _HEAD + [f"cc_{i + 1}" for i in range(n_cc)] + _TAIL


def is_gfile_name(name: str) -> bool:
    """File names recognised as G files in a flight directory: ``gravimeter.g``, ``*.G``, ``G*.dat``
    (each also gzip-compressed, ``.gz``)."""
    name = name[:-3] if name.lower().endswith(".gz") else name
    low = name.lower()
    return (low == "gravimeter.g" or name.endswith(".G")
            or (name[:1] in "Gg" and low.endswith(".dat")))


def _read_raw(path: Path, display: str) -> tuple[pd.DataFrame, np.ndarray]:
    text = read_text(path, display)   # a truncated gzip, bytes that are not UTF-8: said here
    lines = text.split("\n")
    first = next((ln for ln in lines[1:] if ln.strip()), None)
    if first is None:
        raise InputError(display, None, None, "the G file has no data lines after the header")
    comma = "," in first
    fields = [f for f in (first.split(",") if comma else first.split()) if f.strip() != ""]
    if len(fields) < MIN_FIELDS:
        raise InputError(display, 2, None,
                         f"a G-file message has at least {MIN_FIELDS} fields (id, times, 8 acceleration values, "
                         f"temperature, proof mass, saturation, checksum); the first data line has {len(fields)}")
    names = gfile_columns(len(fields))
    dtype = {c: np.float64 for c in names}
    dtype["checksum"] = str
    kw = dict(sep=",", skipinitialspace=True) if comma else dict(sep=r"\s+")
    try:
        df = pd.read_csv(io.StringIO(text), header=None, skiprows=1, names=names, dtype=dtype,
                         skip_blank_lines=False, engine="c", low_memory=False, **kw)
    except pd.errors.ParserError as exc:
        row = parser_error_row(exc)
        line = lines[row - 1].strip() if row and row <= len(lines) else ""
        saw = re.search(r"saw (\d+)", str(exc))
        raise InputError(display, row, None,
                         f"this message has {saw.group(1) if saw else 'another number of'} fields, the first has "
                         f"{len(fields)}: …{line[-80:]!r}") from None
    except ValueError:
        raw = pd.read_csv(io.StringIO(text), header=None, skiprows=1, names=names, dtype=str,
                          skip_blank_lines=False, engine="c", low_memory=False, **kw)
        for col in names[:-1]:
            s = raw[col]
            num = pd.to_numeric(s.str.strip(), errors="coerce")
            bad = np.flatnonzero(num.isna().to_numpy() & s.notna().to_numpy())
            if bad.size:
                raise InputError(display, int(bad[0]) + 2, col, f"not a number: {s.iloc[bad[0]]!r}") from None
        raise
    n = len(df)
    if n:
        empty = df.drop(columns="checksum").isna().all(axis=1).to_numpy()
        nz = np.flatnonzero(~empty)
        n = int(nz[-1]) + 1 if nz.size else 0
        df = df.iloc[:n].reset_index(drop=True)
    if n > 2 and pd.isna(df["checksum"].iloc[-1]) and df["checksum"].iloc[:-1].notna().all():
        # the logger stopped (or the file was copied while written) in the middle of the last message: its
        # last fields are missing and the one before them may be cut too
        warnings.warn(f"{display}: the last message (row {n + 1}) is cut short (no checksum): dropped", stacklevel=3)
        n -= 1
        df = df.iloc[:n]
    if n < 2:
        raise InputError(display, None, None, f"the G file has {n} message(s); at least 2 needed")
    return df, np.arange(2, n + 2, dtype=np.int64)


def _seconds_of_day(hhmmss: np.ndarray, rows: np.ndarray, display: str) -> np.ndarray:
    v = np.asarray(hhmmss, dtype=float)
    hh = np.floor(v / 10000.0)
    mm = np.floor((v - hh * 10000.0) / 100.0)
    ss = v - hh * 10000.0 - mm * 100.0
    bad = np.flatnonzero(~((v >= 0) & (hh < 24) & (mm < 60) & (ss < 61)))
    if bad.size:
        i = int(bad[0])
        raise InputError(display, int(rows[i]), "utc_hhmmss", f"not a UTC time hhmmss.ss: {v[i]!r}")
    return hh * 3600.0 + mm * 60.0 + ss


def subsecond_unit_s(sub: np.ndarray) -> float:
    """Seconds per unit of a G file's sub-second field, from its values: a fraction of a second in
    seconds is below 1; values up to 999 are milliseconds, up to 999 999 microseconds (1.0, 1e-3 or
    1e-6; NaN when larger or negative)."""
    v = np.asarray(sub, dtype=float)
    v = v[np.isfinite(v)]
    if not v.size:
        return 1.0
    lo, hi = float(v.min()), float(v.max())
    if lo < 0:
        return float("nan")
    for limit, unit in ((1.0, 1.0), (1000.0, 1e-3), (1e6, 1e-6)):
        if hi < limit:
            return unit
    return float("nan")


def _message_times(df: pd.DataFrame, rows: np.ndarray, display: str, subsecond_scale: float,
                   time_offset_s: float) -> np.ndarray:
    """Message times on the survey scale (s): UTC seconds of day + sub-second field, carried over
    UTC midnight, + ``time_offset_s``; checked strictly increasing."""
    sod = _seconds_of_day(df["utc_hhmmss"].to_numpy(), rows, display)
    t = sod + subsecond_scale * df["sub_second"].to_numpy()
    back = np.diff(t) < -43200.0  # UTC midnight
    if back.any():
        t = t + 86400.0 * np.concatenate(([0.0], np.cumsum(back)))
    t = t + float(time_offset_s)
    check_time_increasing(t, rows, display, column="utc_hhmmss")
    return t


def _half_interval_centres(t: np.ndarray, stamp: str) -> tuple[np.ndarray, np.ndarray]:
    """Centres of the two half-intervals of every message, ``(t1, t2)``, when the message time
    marks the end (``stamp="end"``) or the start of its interval; the first (last) interval
    takes the median step, and so does an interval beside a gap (a step over 1.5 × the median:
    messages missing there, the interval itself one message long — taking the gap for it put the
    two samples of the message after a lost one up to a whole interval early)."""
    dt = np.diff(t)
    med = float(np.median(dt))
    dt = np.where(dt > 1.5 * med, med, dt)
    if stamp == "end":
        span = np.concatenate(([med], dt))
        return t - 0.75 * span, t - 0.25 * span
    span = np.concatenate((dt, [med]))
    return t + 0.25 * span, t + 0.75 * span


def _half_sample_columns(df: pd.DataFrame, rows: np.ndarray, t1: np.ndarray, t2: np.ndarray, sat: np.ndarray,
                         z_channel: str, scale_to_ms2: float) -> dict:
    """Columns of the output: the two half-interval samples of every message interleaved, the
    per-message fields repeated on both."""
    n = len(df)
    other = "coarse" if z_channel == "fine" else "fine"

    def inter(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        out = np.empty(2 * n)
        out[0::2] = a
        out[1::2] = b
        return out

    def chan(prefix: str) -> np.ndarray:
        return inter(df[f"{prefix}_1"].to_numpy(), df[f"{prefix}_2"].to_numpy()) * scale_to_ms2

    def rep(a) -> np.ndarray:
        return np.repeat(np.asarray(a), 2)

    out = {
        "time": inter(t1, t2),
        "f_z": chan(f"{z_channel}_z"),
        "f_x": chan("x"),
        "f_y": chan("y"),
        f"f_z_{other}": chan(f"{other}_z"),
        "temperature": rep(df["temperature"].to_numpy()),
    }
    for c in df.columns:
        if c.startswith("cc_"):
            out[c] = rep(df[c].to_numpy())
    out["proof_mass_displacement"] = rep(df["proof_mass_displacement"].to_numpy())
    out["saturated"] = rep(sat)
    out["message_id"] = rep(df["message_id"].to_numpy())
    out["half"] = np.tile(np.array([1, 2], dtype=np.int8), n)
    out["source_row"] = rep(rows)
    return out


def read_gfile(path, *, time_offset_s: float = 0.0, scale_to_ms2: float = 1.0,
               subsecond_scale: float | None = None, stamp: str = "end", z_channel: str = "fine",
               on_saturation: str = "drop", max_nan_run: int = 0,
               display: str | None = None) -> pd.DataFrame:
    """Read a GT-1A/GT-2A ASCII "G" file into one row per half-interval sample.

    See the module docstring for the layout, the time construction and the
    saturation policy.

    Parameters
    ----------
    path : path-like
        The G file (may be gzip-compressed, ``.gz``).
    time_offset_s : float
        Added to UTC seconds of day to reach the survey time scale (s).
    scale_to_ms2 : float
        Multiplier turning file acceleration units into m/s² (1.0: already m/s²).
    subsecond_scale : float, optional
        Multiplier turning the sub-second field into seconds (1e-3 for ms).  None: from the
        field's values (:func:`subsecond_unit_s`: below 1 → s, below 1000 → ms, below 10⁶ → µs),
        with a warning when not seconds.
    stamp : {"end", "start"}
        Whether the message time marks the end or the start of its interval.
    z_channel : {"fine", "coarse"}
        Which Z channel becomes ``f_z`` (the other is kept as ``f_z_fine`` /
        ``f_z_coarse``).
    on_saturation : {"drop", "flag", "error"}
    max_nan_run : int
        Longest run of missing values interpolated (longer → InputError).
    display : str, optional
        File name used in error messages (default: ``str(path)``).

    Returns
    -------
    DataFrame, 2·n_messages rows (fewer if saturated messages were dropped)
        ``time`` (s, survey scale), ``f_z``, ``f_x``, ``f_y`` (m/s²),
        ``f_z_coarse`` or ``f_z_fine``, ``temperature``, ``cc_1…``,
        ``proof_mass_displacement``, ``saturated`` (bool), ``message_id``,
        ``half`` (1 or 2), ``source_row`` (line number in the file, header = 1).
    """
    path = Path(path)
    display = str(path) if display is None else display
    if stamp not in ("end", "start"):
        raise ValueError("stamp must be 'end' or 'start'")
    if z_channel not in ("fine", "coarse"):
        raise ValueError("z_channel must be 'fine' or 'coarse'")
    if on_saturation not in ("drop", "flag", "error"):
        raise ValueError("on_saturation must be 'drop', 'flag' or 'error'")
    if not path.is_file():
        raise InputError(display, None, None, "file not found")
    df, rows = _read_raw(path, display)
    df, rows = drop_duplicate_rows(df, rows, display)   # a message logged twice
    # as in a CSV: no-data markers (−9999, ±1e32 …) and a Z field exactly 0 (a dropout) in the
    # channels that become f_z, f_x, f_y are missing values, with a warning
    z = (f"{z_channel}_z_1", f"{z_channel}_z_2")
    mark_no_data(df, rows, display, list(z) + ["x_1", "x_2", "y_1", "y_2"], zero_dropout=z, zero_runs={})
    num_cols = [c for c in df.columns if c != "checksum"]
    check_finite(df, num_cols, rows, display)
    # a missing Z sample is a hole of the record (a linear fill misses the aircraft's acceleration
    # there, which the GNSS still sees): filled for the checks, the half-sample dropped below
    hole = np.empty(2 * len(df), bool)
    hole[0::2] = np.isnan(df[f"{z_channel}_z_1"].to_numpy())
    hole[1::2] = np.isnan(df[f"{z_channel}_z_2"].to_numpy())
    fill_short_nan_runs(df, num_cols, rows, display, max_nan_run, time_col=None)

    if subsecond_scale is None:
        subsecond_scale = subsecond_unit_s(df["sub_second"].to_numpy())
        if not np.isfinite(subsecond_scale):
            raise InputError(display, None, "sub_second", "the sub-second field holds values that are neither "
                             "seconds (< 1), milliseconds (< 1000) nor microseconds (< 10⁶) of the second")
        if subsecond_scale != 1.0:
            warnings.warn(f"{display}: the sub-second field reaches {np.nanmax(df['sub_second'].to_numpy()):g}: "
                          f"read as {'milliseconds' if subsecond_scale == 1e-3 else 'microseconds'}",
                          stacklevel=2)
    t = _message_times(df, rows, display, subsecond_scale, time_offset_s)
    t1, t2 = _half_interval_centres(t, stamp)
    sat = df["saturation"].to_numpy() != 0
    if sat.any() and on_saturation == "error":
        i = int(np.flatnonzero(sat)[0])
        raise InputError(display, int(rows[i]), "saturation",
                         "the gravimeter reports saturation in this message (use on_saturation='drop' to skip such messages)")
    out = _half_sample_columns(df, rows, t1, t2, sat, z_channel, scale_to_ms2)
    res = pd.DataFrame(out)
    if hole.any():
        warnings.warn(f"{display}: {int(hole.sum())} missing {z_channel} Z sample(s) left as holes of the record "
                      f"(first at row {int(res['source_row'].to_numpy()[hole][0])}), not interpolated here (the measurement puts "
                      "a sample back where the record predicts it: processing.gravimeter_fill_max_error_mgal)",
                      stacklevel=2)
        res = res.loc[~hole].reset_index(drop=True)
    n_sat = int(sat.sum())
    res.attrs["saturated_messages"] = n_sat
    if n_sat and on_saturation == "drop":
        first = int(rows[np.flatnonzero(sat)[0]])
        warnings.warn(f"{display}: {n_sat} saturated message(s) dropped (first at row {first})", stacklevel=2)
        res = res.loc[~res["saturated"].to_numpy()].reset_index(drop=True)
        res.attrs["saturated_messages"] = n_sat
    return res
