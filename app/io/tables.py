"""Shared helpers to read and validate the numeric tables of a survey (SPEC §4).

Everything here raises :class:`app.io.errors.InputError` with the file, the
1-based line number in the file (header = line 1) and the column.

Row bookkeeping: readers return, beside the data, an integer array ``rows`` with
the file line number of every data row, so that checks done after parsing
(NaN runs, time order, gaps, ranges) can point at the line an analyst opens in
an editor.  Blank lines are kept while parsing (``skip_blank_lines=False``) so
that the numbering stays exact; blank lines at the end of a file are dropped,
blank lines inside it count as missing values.

Size limits: inside :func:`table_limits` (the web application's reader) every table file is
refused when it is larger than ``max_bytes`` (decompressed, counted while reading a
``.csv.gz``; checked on the file size before parsing a plain file) or has more than
``max_rows`` data rows, so one file can never make the reader buffer more than that.
"""

from __future__ import annotations

import codecs
import contextlib
import gzip
import io
import re
import warnings
import zlib
from collections.abc import Iterable, Sequence
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from app.io.errors import InputError

__all__ = [
    "read_csv_table",
    "csv_dialect",
    "locate_bad_cell",
    "check_finite",
    "fill_short_nan_runs",
    "true_runs",
    "check_time_increasing",
    "median_rate_hz",
    "check_rate",
    "check_range",
    "gap_rows_in_windows",
    "parser_error_row",
    "table_limits",
    "check_file_size",
    "mark_no_data",
    "drop_duplicate_rows",
    "no_data_mask",
    "read_text",
    "clock_time_hint",
]


#: Most columns a CSV table may have (all are tokenized; see :func:`read_csv_table`).
MAX_COLUMNS = 1000


@dataclass(frozen=True)
class _Limits:
    max_bytes: int | None = None
    max_rows: int | None = None


_NO_LIMITS = _Limits()  # frozen: safe as the ContextVar's shared default
_LIMITS: ContextVar[_Limits] = ContextVar("aerograv_table_limits", default=_NO_LIMITS)


@contextlib.contextmanager
def table_limits(max_bytes: int | None = None, max_rows: int | None = None):
    """Within this context, a table file larger than ``max_bytes`` (decompressed) or with more
    than ``max_rows`` data rows is an :class:`InputError` (raised before or while reading)."""
    tok = _LIMITS.set(_Limits(max_bytes, max_rows))
    try:
        yield
    finally:
        _LIMITS.reset(tok)


def _mb(n: int) -> str:
    return f"{n / 2**20:.3g} MB"


def check_file_size(path: Path, display: str) -> None:
    """Refuse a plain file larger than the current ``max_bytes`` before reading it."""
    lim = _LIMITS.get().max_bytes
    if lim is not None and not str(path).endswith(".gz"):
        size = Path(path).stat().st_size
        if size > lim:
            raise InputError(display, None, None, f"the file is {_mb(size)}, more than the {_mb(lim)} allowed "
                                                  "per file")


class _TooLarge(Exception):
    pass


class _LimitedReader(io.RawIOBase):
    """A decompressing reader that stops with :class:`_TooLarge` after ``limit`` bytes."""

    def __init__(self, raw, limit: int):
        self._raw, self._left = raw, limit

    def readable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        n = self._raw.readinto(b)
        self._left -= n
        if self._left < 0:
            raise _TooLarge()
        return n

    def close(self) -> None:
        self._raw.close()
        super().close()


@contextlib.contextmanager
def _source(path: Path, display: str):
    """``(source, read_csv keywords)`` for ``path``: the path itself, or a size-limited
    decompressing stream for a ``.csv.gz`` when a limit is in force."""
    lim = _LIMITS.get().max_bytes
    if lim is None or not str(path).endswith(".gz"):
        yield path, {}
        return
    # Counted first, in constant memory: parsing holds several times the bytes it has read, so a
    # small gzip bomb refused only when the parser reached the limit had cost the server 640 MB
    # (a 2.6 MB upload against a 200 MB limit)
    with gzip.open(path, "rb") as fh:
        left = lim
        while chunk := fh.read(1 << 20):
            left -= len(chunk)
            if left < 0:
                raise InputError(display, None, None, f"the file expands to more than the {_mb(lim)} allowed "
                                                      "per file")
    with _LimitedReader(gzip.open(path, "rb"), lim) as fh, io.BufferedReader(fh, 1 << 20) as buf:
        try:
            yield buf, {"compression": None}
        except _TooLarge:
            raise InputError(display, None, None, f"the file expands to more than the {_mb(lim)} allowed "
                                                  "per file") from None


def parser_error_row(exc: Exception) -> int | None:
    """Line number in a pandas tokenizer error ("Expected 5 fields in line 7, saw 6")."""
    m = re.search(r"line (\d+)", str(exc))
    return int(m.group(1)) if m else None


#: byte-order marks and the encoding each announces (a BOM is unambiguous: Excel's "Unicode text"
#: is UTF-16 with one, "CSV UTF-8" is UTF-8 with one)
_BOMS = ((b"\xef\xbb\xbf", "utf-8-sig"), (b"\xff\xfe", "utf-16"), (b"\xfe\xff", "utf-16"))
#: a cell that is a number written with a decimal point, or with a decimal comma
_DOT_NUMBER = re.compile(r'\s*"?[-+]?\d*\.\d+([eE][-+]?\d+)?"?\s*')
_COMMA_NUMBER = re.compile(r'\s*"?[-+]?\d+,\d+([eE][-+]?\d+)?"?\s*')
#: data lines looked at to decide a decimal comma
_SNIFF_LINES = 200


def _head_text(path: Path, n_bytes: int) -> tuple[str, str, bytes]:
    """``(encoding, text, bytes)`` of the first ``n_bytes`` bytes (decompressed) of ``path``: the
    encoding from a byte-order mark, else UTF-8 when the bytes are UTF-8, else cp1252 (Latin-1
    where cp1252 leaves a byte undefined); the text decoded leniently."""
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "rb") as fh:
        raw = fh.read(n_bytes)
    enc = next((e for bom, e in _BOMS if raw.startswith(bom)), None) or _single_byte_encoding(raw, cut=True)
    if enc == "utf-16" and len(raw) % 2:
        raw = raw[:-1]
    return enc, raw.decode(enc, errors="replace"), raw


def _single_byte_encoding(raw: bytes, cut: bool = False) -> str:
    """``"utf-8"`` when ``raw`` is UTF-8 (``cut``: it may end inside a character), else
    ``"cp1252"`` (Windows' Western code page, a superset of Latin-1's printable characters), or
    ``"latin-1"`` when a byte is one cp1252 leaves undefined.  Binary bytes (a NUL, gzip's
    magic number) stay ``"utf-8"``: no code page makes them text, and the read says what they are."""
    if raw[:2] == b"\x1f\x8b" or b"\x00" in raw:
        return "utf-8"
    try:
        raw.decode("utf-8")
        return "utf-8"
    except UnicodeDecodeError as exc:
        if cut and exc.start >= len(raw) - 3 and exc.reason == "unexpected end of data":
            return "utf-8"
    try:
        raw.decode("cp1252")
        return "cp1252"
    except UnicodeDecodeError:
        return "latin-1"


def _first_bad_utf8_row(raw: bytes) -> int:
    """1-based line number of the first byte that is not UTF-8 (``raw`` is not UTF-8)."""
    try:
        raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        return raw.count(b"\n", 0, exc.start) + 1
    return 0


def warn_not_utf8(display: str, enc: str, row: int, stacklevel: int = 3) -> None:
    """The one warning for a text file read in a single-byte code page (not UTF-8, no BOM)."""
    warnings.warn(f"{display}: not UTF-8 (a byte at row {row} is not a UTF-8 character) and no byte-order mark: "
                  f"read as {'Windows-1252' if enc == 'cp1252' else 'Latin-1'} (° and µ in names and comments "
                  "come out right; save the file as UTF-8 to say so)", stacklevel=stacklevel)


def read_text(path: Path, display: str) -> str:
    """A whole text file (``.gz`` decompressed): UTF-8 or UTF-16 by its byte-order mark, UTF-8
    without one — or, when its bytes are not UTF-8, cp1252/Latin-1 with a warning
    (:func:`warn_not_utf8`).  Unreadable (a truncated gzip …), or a ``.gz`` that expands past the
    per-file limit in force (:func:`table_limits`) → :class:`InputError`."""
    check_file_size(path, display)
    lim = _LIMITS.get().max_bytes
    try:
        if str(path).lower().endswith(".gz"):
            with gzip.open(path, "rb") as fh:
                # at most the limit decompressed (a gzip bomb of a G file or XYZ read whole had no cap)
                raw = fh.read() if lim is None else fh.read(lim + 1)
        else:
            raw = Path(path).read_bytes()
    except (OSError, EOFError, zlib.error) as exc:
        raise InputError(display, None, None, f"cannot read the file: {exc}") from None
    if lim is not None and len(raw) > lim:
        raise InputError(display, None, None, f"the file expands to more than the {_mb(lim)} allowed per file")
    for bom, enc in _BOMS:
        if raw.startswith(bom):
            return raw.decode(enc, errors="replace").lstrip("\ufeff")
    enc = _single_byte_encoding(raw)
    if enc != "utf-8":
        warn_not_utf8(display, enc, _first_bad_utf8_row(raw), stacklevel=3)
    return raw.decode(enc)


def csv_dialect(path: Path, display: str) -> dict:
    """The ``pandas.read_csv`` keywords a table file is written in (SPEC: UTF-8, commas, points).

    Inferred only where the file leaves no doubt: the encoding from a byte-order mark
    (UTF-16 with one, as Excel's "Unicode text" writes it), or cp1252/Latin-1 with a warning when
    the first 64 kB are not UTF-8 (``°`` or ``µ`` saved by a Windows program); leading lines
    starting with ``#`` skipped (``skiprows``: the row numbers stay the file's); the separator
    from the header line — ``;`` or a tab when it has no comma; with such a separator, a decimal comma when the
    first data lines write numbers with commas (``9,81234``) and none with a point.  Both in
    one file is refused.

    Returns
    -------
    dict
        ``encoding``, ``skiprows``, ``sep`` and ``decimal`` (absent when the file is SPEC's).

    Raises
    ------
    InputError
        Decimal commas and decimal points in one file whose separator is not a comma.
    """
    try:
        enc, text, raw = _head_text(path, 1 << 16)
    except (OSError, EOFError, zlib.error):
        return {}   # the read says what is wrong
    lines = text.lstrip("\ufeff").splitlines()
    kw: dict = {"encoding": enc} if enc != "utf-8" else {}
    if enc in ("cp1252", "latin-1"):
        warn_not_utf8(display, enc, _first_bad_utf8_row(raw), stacklevel=4)
    # leading comment lines ('# written by …'): skipped, the file's own row numbers kept
    n_comments = next((i for i, line in enumerate(lines) if not line.lstrip().startswith("#")), len(lines))
    if n_comments:
        kw["skiprows"] = n_comments
        lines = lines[n_comments:]
    head = lines[0] if lines else ""
    sep = next((c for c in (";", "\t") if "," not in head and c in head), ",")
    if sep == ",":
        return kw
    kw["sep"] = sep
    first: dict[str, tuple[int, str]] = {}
    for i, line in enumerate(lines[1:1 + _SNIFF_LINES], start=2 + n_comments):
        for cell in line.split(sep):
            for what, pat in (("comma", _COMMA_NUMBER), ("point", _DOT_NUMBER)):
                if what not in first and pat.fullmatch(cell):
                    first[what] = (i, cell.strip())
    if "comma" in first and "point" in first:
        (rc, vc), (rp, vp) = first["comma"], first["point"]
        raise InputError(display, max(rc, rp), None,
                         f"the columns are separated by {'semicolons' if sep == ';' else 'tabs'} and the numbers "
                         f"are written with decimal commas ({vc!r}, row {rc}) and with decimal points ({vp!r}, "
                         f"row {rp}): write every number one way")
    if "comma" in first:
        kw["decimal"] = ","
    return kw


def _too_wide(path: Path, sep: str = ",", skiprows: int = 0) -> int:
    """Fields of the header line (after ``skiprows`` comment lines), counted on its raw bytes (pandas takes seconds to even read
    a header of 100 000 fields); at most ``MAX_COLUMNS`` kB of it are read (decompressed).
    (UTF-16: the separator's byte once per separator, the line cut at the first newline byte.)"""
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "rb") as fh:
        for _ in range(skiprows):
            fh.readline(MAX_COLUMNS * 1024)
        line = fh.readline(MAX_COLUMNS * 1024)
    return line.count(sep.encode()) + 1


def _header(path: Path, display: str, **kw) -> list[str]:
    try:
        n_fields = _too_wide(path, kw.get("sep", ","), kw.get("skiprows", 0))
    except (OSError, EOFError, zlib.error):
        n_fields = 0   # the read below says what is wrong
    if n_fields > MAX_COLUMNS:
        # every column is tokenized (a stray separator must not be hidden): a header of 100 000
        # fields made a 1.3 MB file take 26 s to parse
        raise InputError(display, 1 + kw.get("skiprows", 0), None, f"{n_fields:,} columns in the header line: more than the "
                                           f"{MAX_COLUMNS:,} a table may have")
    try:
        with _source(path, display) as (src, skw):
            head = pd.read_csv(src, nrows=0, **skw, **kw)
    except pd.errors.EmptyDataError:
        raise InputError(display, None, None, "the file is empty (expected a header line with column names)") from None
    except (OSError, UnicodeDecodeError, EOFError, zlib.error) as exc:
        if _is_gzip(path) and not str(path).endswith(".gz"):
            raise InputError(display, None, None, "the file is gzip-compressed but not named .gz: rename it to "
                                                  f"{path.name}.gz (or decompress it)") from None
        raise InputError(display, None, None, f"cannot read the file: {exc}") from None
    except pd.errors.ParserError as exc:
        raise InputError(display, 1 + kw.get("skiprows", 0), None, f"cannot read the header line: {exc}") from None
    return [str(c) for c in head.columns]


def _is_gzip(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(2) == b"\x1f\x8b"
    except OSError:
        return False


def _separator_hint(names: list[str], last_comment: str = "", col: str = "") -> str:
    """A hint when the header came out as one field holding another separator, or when the
    missing column ``col`` is named on the leading ``#`` line above the header (skipped as a comment)."""
    if col and re.search(rf"\b{re.escape(col)}\b", last_comment.lower()):
        return (f"; the column names are on a comment line ({last_comment.strip()[:80]!r}), and leading lines "
                "starting with '#' are skipped: remove the '#' before the names")
    if len(names) == 1:
        for sep, what in ((";", "semicolons"), ("\t", "tabs"), ("|", "bars"), (" ", "blanks")):
            if sep in names[0].strip():
                return f"; the header is one field separated by {what}: columns must be separated by commas"
    return ""


def _last_comment(path: Path, head_row: int) -> str:
    """The leading ``#`` line just above the header ("" when there is none)."""
    if head_row < 2:
        return ""
    try:
        lines = _head_text(path, 1 << 16)[1].lstrip("\ufeff").splitlines()
    except (OSError, EOFError, zlib.error):
        return ""
    return lines[head_row - 2].lstrip().lstrip("#") if len(lines) >= head_row - 1 else ""


def _bad_cell_hint(col: str, val: str) -> str:
    """Why a cell that is not a number may look the way it does (a converter's habits)."""
    v = val.strip()
    if v.lower() == col or v.lower() == "time":
        return " — a header line inside the data (files joined one after the other?): remove it"
    if re.fullmatch(r"[-+]?\d{1,3}(,\d{3})+(\.\d+)?", v):
        return " — a thousands separator? Write numbers without grouping"
    if re.fullmatch(r"[-+]?\d+,\d+", v):
        return (" — a decimal comma? With commas between the columns numbers need decimal points "
                "(or separate the columns by semicolons)")
    if re.fullmatch(r"\d{4}-\d{2}-\d{2}[T ].*", v):
        return (" — a date and time: times are float seconds on the survey's one time scale (the data "
                "files' own, e.g. GPS seconds of week), not date strings")
    return ""



def locate_bad_cell(path: Path, display: str, usecols: Sequence[str], float_cols: Iterable[str],
                    rename: dict[str, str], **read_kw) -> InputError | None:
    """Find the first cell of ``float_cols`` that is not a number (slow path, only after a failure).

    Re-reads the file as text and returns an :class:`InputError` for the first
    offending cell (smallest line number; left-most column on ties), or None.
    """
    best: tuple[int, int, str, str] | None = None
    offset = int(read_kw.get("skiprows", 0))
    # in chunks: the text of a whole large file as Python strings would take ~10x its size
    with _source(path, display) as (src, skw), \
            pd.read_csv(src, usecols=list(usecols), dtype=str, skip_blank_lines=False, chunksize=200_000,
                        **skw, **read_kw) as reader:   # closed when the first bad chunk ends the loop
        for raw in reader:
            raw = raw.rename(columns=rename)
            for j, col in enumerate(float_cols):
                s = raw[col]
                txt = s.str.strip()
                num = pd.to_numeric(txt.str.replace(",", ".", regex=False) if read_kw.get("decimal") == "," else txt,
                                    errors="coerce")
                bad = np.flatnonzero(num.isna().to_numpy() & s.notna().to_numpy()
                                     & (s.fillna("").str.strip() != "").to_numpy())
                if bad.size:
                    cand = (offset + int(bad[0]) + 2, j, col, str(s.iloc[bad[0]]))
                    if best is None or cand[:2] < best[:2]:
                        best = cand
            if best is not None:
                break
            offset += len(raw)
    if best is None:
        return None
    row, _, col, val = best
    hint = clock_time_hint(col, val) or _bad_cell_hint(col, val)
    return InputError(display, row, col, f"not a number: {val!r}{hint}")


def clock_time_hint(col: str, val: str) -> str:
    """The hint for a time column holding a clock time (``hh:mm:ss[.ss]``), "" otherwise."""
    if col in ("time", "t_start", "t_end") and re.fullmatch(r"\s*\d{1,2}:\d{2}(:\d{2}(\.\d*)?)?\s*", val):
        return (" — a clock time (hh:mm:ss): times are float seconds on the survey's one time scale (the data "
                "files' own, e.g. GPS seconds of week), not clock strings")
    return ""


#: cells tokenized at a time by :func:`_read_all_columns` (at most 200 000 rows)
CHUNK_CELLS = 2_000_000


def _read_all_columns(path: Path, dtype: dict, display: str, n_columns: int = 1, **dialect) -> pd.DataFrame:
    # All columns are tokenized (with ``usecols`` pandas would silently drop surplus fields on a
    # line, hiding a stray separator, "9,81"), a chunk of rows at a time, and only the columns in
    # ``dtype`` kept: the others never all sit in memory (a 234 kB gzip of 999 columns had cost
    # 1.1 GB parsed whole).
    max_rows = _LIMITS.get().max_rows
    keep = list(dtype)
    with _source(path, display) as (src, skw):
        parts = [c[keep] for c in pd.read_csv(src, dtype=dtype, skip_blank_lines=False, engine="c", index_col=False,
                                              nrows=None if max_rows is None else max_rows + 1,
                                              chunksize=max(1000, min(200_000, CHUNK_CELLS // max(1, n_columns))),
                                              **skw, **dialect)]
    df = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame({c: pd.Series(dtype=float) for c in keep})
    if max_rows is not None and len(df) > max_rows:
        raise InputError(display, max_rows + 2 + dialect.get("skiprows", 0), None,
                         f"more than the {max_rows:,} data rows allowed per file")
    return df


#: the SPEC unit of each column, and how a header may write it after its name (``h [m]``,
#: ``f_z(m/s^2)``), compared lower-case without blanks, ``^``, ``*`` or ``.``, ``²`` as 2
SPEC_UNITS = {
    **{c: ("s", {"s", "sec", "secs", "second", "seconds"}) for c in ("time", "t_start", "t_end")},
    **{c: ("m/s²", {"m/s2", "ms-2", "m/s/s"}) for c in ("f_z", "f_x", "f_y")},
    **{c: ("degrees", {"deg", "degree", "degrees", "°", "decdeg", "dd"}) for c in ("lat", "lon")},
    "h": ("m", {"m", "metre", "metres", "meter", "meters"}),
    **{c: ("m/s", {"m/s", "ms-1"}) for c in ("vu", "ve", "vn", "sigma_v")},
}
_UNIT_IN_NAME = re.compile(r"(.+?)\s*[\[(]\s*(.*?)\s*[\])]")


def _unit_key(unit: str) -> str:
    u = unit.lower().replace("²", "2")
    for ch in " ^*.":
        u = u.replace(ch, "")
    return u


def _column_lookup(names: Sequence[str], wanted: Sequence[str], display: str, header_row: int = 1) -> dict[str, str]:
    """Lower-case SPEC name → the header's own label, for the columns in ``wanted``.

    A label matches after stripping blanks and lower-casing; one that writes a unit after the
    name (``h [m]``, ``f_z (m/s^2)``) matches when no label is the bare name and the unit is
    SPEC's (:data:`SPEC_UNITS`) — any other unit is an error naming it (a unit in the header is
    read, never assumed away).
    """
    lookup: dict[str, str] = {}
    for n in names:
        lookup.setdefault(n.strip().lower(), n)
    for n in names:
        m = _UNIT_IN_NAME.fullmatch(n.strip().lower())
        if not m or m.group(1) not in wanted or m.group(1) in lookup:
            continue
        col, unit = m.group(1), m.group(2)
        spec, accepted = SPEC_UNITS.get(col, (None, set()))
        if _unit_key(unit) not in accepted:
            raise InputError(display, header_row, col, f"column {n.strip()!r} gives {col} in {unit!r}; SPEC's {col} is in "
                                              f"{spec or 'its own unit'}: convert the column to {spec or 'that unit'} "
                                              f"(the unit in the header is read, never assumed)")
        lookup[col] = n
    return lookup


def _first_bad_utf8_row_streamed(path: Path) -> tuple[int, bytes]:
    """(1-based line, the 64 kB around it) of a file's first byte that is not UTF-8, read in
    chunks (``.gz`` decompressed) — (0, b"") when every byte is UTF-8."""
    opener = gzip.open if str(path).endswith(".gz") else open
    dec = codecs.getincrementaldecoder("utf-8")()
    lines = 0
    with opener(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            try:
                dec.decode(chunk)
            except UnicodeDecodeError as exc:
                return lines + chunk.count(b"\n", 0, max(0, exc.start)) + 1, chunk[max(0, exc.start - 32768):
                                                                                exc.start + 32768]
            lines += chunk.count(b"\n")
    return 0, b""


def _single_byte_dialect(path: Path, display: str, dialect: dict, exc: UnicodeDecodeError) -> dict:
    """The dialect with cp1252 (or Latin-1) as its encoding, and the warning naming the first row
    that is not UTF-8 (:func:`warn_not_utf8`), when the UTF-8 read failed on a byte past what
    :func:`csv_dialect` looked at.  A file that announced its encoding (a BOM), or whose bad byte
    no code page makes text, is refused naming the row."""
    row, around = _first_bad_utf8_row_streamed(path)
    enc = _single_byte_encoding(around, cut=True) if around else "utf-8"
    if dialect.get("encoding", "utf-8") not in ("utf-8", "utf-8-sig") or enc == "utf-8":
        raise InputError(display, row or None, None, f"cannot read the file: {exc}") from None
    warn_not_utf8(display, enc, row, stacklevel=5)
    return {**dialect, "encoding": enc}


def read_csv_table(path: Path | str, display: str, required: Sequence[str],
                   optional: Sequence[str] = (), str_cols: Sequence[str] = (),
                   min_rows: int = 1) -> tuple[pd.DataFrame, np.ndarray]:
    """Read a CSV (``.csv`` or ``.csv.gz``) keeping only the named columns.

    Column names are matched after stripping blanks and lower-casing, a label with a unit
    after the name (``h [m]``) when the unit is SPEC's (:func:`_column_lookup`); extra
    columns are ignored (not even parsed).  The encoding, separator and decimal mark are
    SPEC's (UTF-8, comma, point) unless the file itself says otherwise (:func:`csv_dialect`).  Numeric columns are parsed by the
    pandas C engine straight to float64; only when that fails is the file
    re-read as text to locate the offending cell.

    Parameters
    ----------
    path : path-like
        The file.
    display : str
        Name used in error messages (e.g. ``"flights/F1/gnss.csv"``).
    required, optional : sequence of str
        Column names (lower case).  Missing required → error at row 1.
        Optional columns are kept when present.
    str_cols : sequence of str
        Columns (among required/optional) read as text; all others are float64.
    min_rows : int
        Fewer data rows → error.

    Returns
    -------
    df : DataFrame
        Columns ``required`` then the present ``optional`` ones, default RangeIndex.
    rows : ndarray of int, shape (len(df),)
        File line number of each row (header = 1).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(display, None, None, "file not found")
    check_file_size(path, display)
    dialect = csv_dialect(path, display)
    names = _header(path, display, **dialect)
    head_row = 1 + dialect.get("skiprows", 0)   # leading '#' lines skipped: the file's own numbering kept
    lookup = _column_lookup(names, list(required) + list(optional), display, head_row)
    for col in required:
        if col not in lookup:
            have = ", ".join(repr(n) for n in names) or "none"
            raise InputError(display, head_row, col, f"required column '{col}' is missing (columns found: "
                                                     f"{have})" + _separator_hint(names, _last_comment(path, head_row), col))
    wanted = list(required) + [c for c in optional if c in lookup]
    usecols = [lookup[c] for c in wanted]
    rename = {lookup[c]: c for c in wanted}
    float_cols = [c for c in wanted if c not in str_cols]
    dtype = {lookup[c]: (str if c in str_cols else np.float64) for c in wanted}
    try:
        with warnings.catch_warnings():
            # the first data line having more fields than the header only warns: make it an error
            warnings.simplefilter("error", pd.errors.ParserWarning)
            try:
                df = _read_all_columns(path, dtype, display, len(names), **dialect)
            except UnicodeDecodeError as exc:
                # a byte that is not UTF-8 past the first 64 kB csv_dialect looked at (a ° in a remark)
                dialect = _single_byte_dialect(path, display, dialect, exc)
                df = _read_all_columns(path, dtype, display, len(names), **dialect)
    except InputError:
        raise
    except pd.errors.ParserWarning:
        raise InputError(display, head_row + 1, None, f"this line has more fields than the header ({len(names)}): "
                                           f"a stray separator or a decimal comma?") from None
    except pd.errors.ParserError as exc:
        raise InputError(display, parser_error_row(exc), None,
                         f"this line has more fields than the header ({len(names)}): a stray separator "
                         f"or a decimal comma? ({exc})") from None
    except ValueError as exc:
        try:
            err = locate_bad_cell(path, display, usecols, float_cols, rename, **dialect)
        except InputError:
            raise
        except Exception:  # noqa: BLE001 - the first error is the one reported
            err = None
        if err is not None:
            raise err from None
        raise InputError(display, None, None, f"cannot parse the file: {exc}") from None
    except (OSError, EOFError, zlib.error) as exc:
        raise InputError(display, None, None, f"cannot read the file: {exc}") from None
    df = df.rename(columns=rename)[wanted]
    # drop blank lines at the end of the file
    n = len(df)
    if n:
        empty = df.isna().all(axis=1).to_numpy()
        if empty[-1]:
            nz = np.flatnonzero(~empty)
            n = int(nz[-1]) + 1 if nz.size else 0
            df = df.iloc[:n]
    rows = np.arange(head_row + 1, n + head_row + 1, dtype=np.int64)
    if n < min_rows:
        raise InputError(display, None, None,
                         f"the file has {n} data row(s); at least {min_rows} needed")
    return df.reset_index(drop=True), rows


def check_finite(df: pd.DataFrame, columns: Sequence[str], rows: np.ndarray, display: str) -> None:
    """Reject ±inf cells (NaN is handled by :func:`fill_short_nan_runs`)."""
    best = None
    for j, col in enumerate(columns):
        bad = np.flatnonzero(np.isinf(df[col].to_numpy()))
        if bad.size and (best is None or (bad[0], j) < best[:2]):
            best = (int(bad[0]), j, col)
    if best is not None:
        i, _, col = best
        raise InputError(display, int(rows[i]), col, f"not a finite number: {df[col].iloc[i]!r}")


def true_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start indices and lengths of the runs of True in a boolean vector."""
    m = np.concatenate(([False], mask, [False])).astype(np.int8)
    d = np.diff(m)
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)
    return starts, ends - starts


def fill_short_nan_runs(df: pd.DataFrame, columns: Sequence[str], rows: np.ndarray, display: str,
                        max_nan_run: int, time_col: str | None = "time") -> pd.DataFrame:
    """Interpolate runs of missing values up to ``max_nan_run`` long; longer runs are errors.

    The time column (if among ``columns``) is interpolated linearly in the
    sample index; every other column linearly in time (in the sample index when
    there is no time column).  Runs touching the start or end of the file are
    filled with the nearest value.  The error names the first line of the
    earliest run that is too long.

    Returns
    -------
    DataFrame
        ``df`` itself, modified in place where values were filled.
    """
    worst = None
    for j, col in enumerate(columns):
        v = df[col].to_numpy()
        mask = np.isnan(v)
        if not mask.any():
            continue
        starts, lengths = true_runs(mask)
        too_long = np.flatnonzero(lengths > max_nan_run)
        if too_long.size:
            k = too_long[0]
            cand = (int(starts[k]), j, col, int(lengths[k]))
            if worst is None or cand[:2] < worst[:2]:
                worst = cand
    if worst is not None:
        i, _, col, length = worst
        what = "missing value" if length == 1 else f"{length} consecutive missing values starting here"
        allowed = ("no missing values are allowed" if max_nan_run == 0
                   else f"at most {max_nan_run} in a row are interpolated")
        raise InputError(display, int(rows[i]), col,
                         f"{what} ({allowed}; processing.max_nan_run)")
    idx = np.arange(len(df), dtype=float)
    ordered = list(columns)
    if time_col in ordered:
        ordered.remove(time_col)
        ordered.insert(0, time_col)
    for col in ordered:
        v = df[col].to_numpy(dtype=float)
        mask = np.isnan(v)
        if not mask.any():
            continue
        x = idx if (time_col is None or col == time_col or time_col not in df) else df[time_col].to_numpy(dtype=float)
        v = v.copy()
        v[mask] = np.interp(x[mask], x[~mask], v[~mask])
        df[col] = v
    return df


def check_time_increasing(t: np.ndarray, rows: np.ndarray, display: str, column: str = "time") -> None:
    """Times must increase strictly; the error names the row where order breaks."""
    dt = np.diff(t)
    bad = np.flatnonzero(~(dt > 0))
    if bad.size:
        i = int(bad[0]) + 1
        if dt[i - 1] == 0:
            msg = f"time {float(t[i]):.6f} is repeated (same as the previous row)"
            n_rep = int(np.count_nonzero(dt == 0))
            if n_rep >= max(3, 0.05 * dt.size):
                # stamps rounded coarser than the sampling interval (18 Hz written to 0.1 s)
                step = float(np.median(dt[dt > 0])) if np.any(dt > 0) else float("nan")
                msg += (f" — {n_rep:,} of the {dt.size + 1:,} stamps repeat the one before: the times are written "
                        f"with too few decimals for the sampling (distinct stamps {step:.3g} s apart); export "
                        f"the time column with more decimals")
        else:
            msg = f"time goes backwards: {float(t[i]):.6f} after {float(t[i - 1]):.6f}"
            back = float(t[i - 1] - t[i])
            for period, what in ((86400.0, "seconds of day: the flight crosses midnight"),
                                 (604800.0, "GPS seconds of week: the flight crosses the week's end")):
                # the clock wrapped (a record's gap at the wrap included: a turn's 10 minutes
                # without data), not a shuffled record
                if 0.0 < period - back <= 3600.0:
                    msg += (f" — the time scale wrapped ({what}); the survey needs one monotonic scale: "
                            f"add {period:.0f} s to this row's time and every later one (and to the "
                            f"lines.csv windows after the wrap)")
                    break
            else:
                msg += _set_back_hint(dt, i, back)
        raise InputError(display, int(rows[i]), column, msg)


def _set_back_hint(dt: np.ndarray, i: int, back_s: float) -> str:
    """The words for a clock set back in flight: the times step back by under a minute at row
    ``i`` and go on at the record's own step after it (a logger re-synchronised; a clock set
    forward is a gap, which the measurement re-times itself — METHOD stage 1); "" otherwise."""
    good = dt[dt > 0]
    if not (0.0 < back_s < 60.0) or good.size < 10:
        return ""
    step = float(np.median(good))
    after = dt[i:i + 20]
    if after.size < 5 or not np.all(np.abs(after - step) <= 0.25 * step):
        return ""
    shift = back_s + step
    return (f" — the times go on at the record's {step:.3g} s step after this row: the clock looks set back by "
            f"about {shift:.3f} s in flight; the survey needs one time scale — add {shift:.3f} s to this row's time "
            "and every later one (the measurement then re-times the gravimeter's clock against the GNSS's)")


def median_rate_hz(t: np.ndarray, span: int = 10) -> float:
    """Sampling rate from the median interval (Hz); NaN with fewer than 2 samples.

    The median is taken over ``span``-sample intervals divided by ``span``
    (when there are enough samples): robust to gaps like a plain median, but
    not biased by time stamps rounded to a few decimals (18.24 Hz stamped to
    1 ms would otherwise read as 1/0.055 = 18.18 Hz).
    """
    t = np.asarray(t, dtype=float)
    if t.size < 2:
        return float("nan")
    k = span if t.size > 2 * span else 1
    return float(k / np.median(t[k:] - t[:-k]))


def check_rate(t: np.ndarray, display: str, declared_hz: float | None, tolerance: float,
               what: str, setting: str, sanity_hz: tuple[float, float] = (1.0, 100.0)) -> float:
    """Compare the median rate with the declared one (or a sanity range when None).

    The rate is always inferred from the time stamps (:func:`median_rate_hz`);
    a declared rate is only a check of it (relative ``tolerance``).

    Returns
    -------
    float
        The median rate (Hz).
    """
    rate = median_rate_hz(t)
    if declared_hz is not None:
        if not abs(rate - declared_hz) <= tolerance * declared_hz:
            raise InputError(display, None, "time",
                             f"the {what} samples come at {rate:.4g} Hz (median interval), but {declared_hz:g} Hz "
                             f"is declared ({setting}; tolerance ±{tolerance:.0%}). Check the time column units "
                             f"or the declared rate.")
    elif not (sanity_hz[0] * (1 - 1e-9) <= rate <= sanity_hz[1] * (1 + 1e-9)):  # rounding of the stamps
        raise InputError(display, None, "time",
                         f"the {what} samples come at {rate:.4g} Hz (median interval), outside the plausible "
                         f"{sanity_hz[0]:g}–{sanity_hz[1]:g} Hz. Check the time column units (seconds expected) "
                         f"or declare the rate ({setting}).")
    return rate


def check_range(df: pd.DataFrame, column: str, lo: float, hi: float, rows: np.ndarray, display: str,
                what: str) -> None:
    """Values of ``column`` must lie in [lo, hi]; the error names the first row outside."""
    v = df[column].to_numpy()
    bad = np.flatnonzero(~((v >= lo) & (v <= hi)))
    if bad.size:
        i = int(bad[0])
        x = float(v[i])
        hint = ""
        if (column == "lat" and 100.0 <= abs(x) < 9100.0 or column == "lon" and 360.0 < abs(x) < 18100.0) \
                and abs(x) % 100.0 < 60.0:
            hint = (" — degrees and minutes run together (DDMM.mmmm, as NMEA writes them)? SPEC's lat and lon are "
                    "decimal degrees")
        if column == "lat" and "lon" in df and abs(x) <= 180.0 and np.all(np.abs(df["lon"].to_numpy()) <= 90.0):
            hint += (" — or lat and lon swapped (the lon column is within ±90° everywhere)? Swap the columns "
                     "(in an XYZ file, survey.toml's [columns] names them)")
        raise InputError(display, int(rows[i]), column, f"{what} {x!r} is outside [{lo:g}, {hi:g}]{hint}")


def gap_rows_in_windows(t: np.ndarray, t_start: np.ndarray, t_end: np.ndarray,
                        max_gap_s: float) -> np.ndarray:
    """Index of the first sample after a too-long gap inside each window (−1 if none).

    A gap (t_i, t_{i+1}) counts for window [a, b] when it overlaps it:
    ``t_{i+1} > a`` and ``t_i < b``.  A step counts as a gap when it exceeds ``max_gap_s`` by
    more than 5 % of the median step: stamps scattered about the clock (a logger's time, up to
    2.5 % of the step) do not turn an allowed step into a refused one.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Strictly increasing times (s).
    t_start, t_end : ndarray, shape (m,)
        Windows (s).
    max_gap_s : float

    Returns
    -------
    ndarray of int, shape (m,)
        For each window, the index ``i+1`` of the sample closing the first gap
        longer than ``max_gap_s`` that overlaps the window, or −1.
    """
    t = np.asarray(t, dtype=float)
    dt = np.diff(t)
    slack = 0.05 * float(np.median(dt)) if dt.size else 0.0
    big = np.flatnonzero(dt > max_gap_s + slack)  # gap between big[k] and big[k]+1
    out = np.full(len(t_start), -1, dtype=np.int64)
    if big.size == 0:
        return out
    after = t[big + 1]
    before = t[big]
    for w, (a, b) in enumerate(zip(np.asarray(t_start, float), np.asarray(t_end, float))):
        k = np.searchsorted(after, a, side="right")  # first gap ending after a
        if k < big.size and before[k] < b:
            out[w] = big[k] + 1
    return out


#: numbers converters and loggers write for "no data": never a value of a flight record's columns
#: (every one is outside what an aircraft's position, velocity or specific force can be, in SPEC's
#: units and in the f_z units recognised); any magnitude ≥ 1e30 is one too (Geosoft's ±1e32 …)
NO_DATA_MARKERS = (-999.0, -999.99, -999.999, -9999.0, -9999.99, -99999.0, -99999.99, -999999.0,
                   9999999.0, 99999999.0)
NO_DATA_BELOW_ABS = 1e30
#: a run of exact zeros in ``h`` is a logger's dropout when the heights bordering it are all
#: farther than this from 0 (m): no aircraft or ship moves that far in one sample
ZERO_DROPOUT_H_M = 50.0


def _zero_runs_bordered(v: np.ndarray, far: float) -> np.ndarray:
    """Mask of the runs of exact zeros in ``v`` whose bordering values (one side at a file end)
    are all farther than ``far`` from 0."""
    out = np.zeros(v.size, bool)
    starts, lengths = true_runs(v == 0.0)
    for a, n in zip(starts, lengths):
        border = [v[i] for i in (a - 1, a + n) if 0 <= i < v.size]
        if border and all(np.isfinite(b) and abs(b) > far for b in border):
            out[a:a + n] = True
    return out


def no_data_mask(v: np.ndarray) -> np.ndarray:
    """Where ``v`` holds a no-data marker (:data:`NO_DATA_MARKERS`, or a magnitude ≥ 1e30)."""
    v = np.asarray(v, dtype=float)
    return np.isin(v, NO_DATA_MARKERS) | (np.abs(v) >= NO_DATA_BELOW_ABS)


def mark_no_data(df: pd.DataFrame, rows: np.ndarray, display: str, columns: Sequence[str],
                 zero_dropout: Sequence[str] = ("f_z",),
                 zero_runs: dict[str, float] | None = None) -> pd.DataFrame:
    """Cells holding a no-data marker made missing (NaN), in place, with a warning naming them.

    Markers: the numbers of :data:`NO_DATA_MARKERS` and any magnitude ≥ 1e30, in every column
    of ``columns`` but ``time``; a logger's dropout written as zeros: ``f_z`` exactly 0 (specific
    force is 0 only in free fall), ``lat`` and ``lon`` both exactly 0 on a row, a run of exact
    zeros in ``h`` bordered by heights more than :data:`ZERO_DROPOUT_H_M` from 0 — and, on those
    rows, the other columns' exact zeros.  Other formats name their own columns: ``zero_dropout``
    (exactly 0 is a dropout; default ``f_z``) and ``zero_runs`` (column → the distance from 0
    its neighbours must have for a run of zeros to be a dropout; default ``{"h": 50}``).  What follows is the missing-value rule
    (``processing.max_nan_run``: refused, or interpolated, or a hole of f_z): a marker is never
    read as a number.

    Returns
    -------
    DataFrame
        ``df`` itself.
    """
    cols = [c for c in columns if c in df and c != "time"]
    found: list[str] = []
    dropout = np.zeros(len(df), bool)
    for c in zero_dropout:
        if c in df:
            dropout |= df[c].to_numpy(float) == 0.0
    if "lat" in df and "lon" in df:
        dropout |= (df["lat"].to_numpy(float) == 0.0) & (df["lon"].to_numpy(float) == 0.0)
    for c, far in ({"h": ZERO_DROPOUT_H_M} if zero_runs is None else zero_runs).items():
        if c in df:
            dropout |= _zero_runs_bordered(df[c].to_numpy(float), far)
    for c in cols:
        v = df[c].to_numpy(float)
        marker = no_data_mask(v)
        zero = dropout & (v == 0.0)
        for mask, what in ((marker, None), (zero, "0 (a dropout)")):
            if mask.any():
                i = int(np.flatnonzero(mask)[0])
                found.append(f"{c}: {int(mask.sum())} × {what or f'{v[i]:g}'} (first at row {int(rows[i])})")
        if marker.any() or zero.any():
            v = v.copy()
            v[marker | zero] = np.nan
            df[c] = v
    if found:
        warnings.warn(f"{display}: no-data markers read as missing values — {'; '.join(found)}", stacklevel=3)
    return df


def drop_duplicate_rows(df: pd.DataFrame, rows: np.ndarray, display: str) -> tuple[pd.DataFrame, np.ndarray]:
    """Rows that repeat an earlier row exactly — the same time and the same value in every
    column read — dropped, with a warning naming how many and the first (file row numbers).

    A logger that wrote a record twice, or two files joined where they overlap, repeat whole
    rows; a repeat carries nothing new, so dropping it loses nothing.  A time repeated with
    *other* values is still refused (:func:`check_time_increasing`): which one is right is not
    in the file.

    Returns
    -------
    (DataFrame, ndarray)
        The table and its file row numbers without the repeats (``df`` itself when there are none).
    """
    dup = df.duplicated(keep="first").to_numpy()
    if not dup.any():
        return df, rows
    rows = np.asarray(rows)
    n = int(dup.sum())
    warnings.warn(f"{display}: {n} row(s) repeating an earlier row exactly (time and every value) dropped — "
                  f"the first at row {int(rows[dup][0])}, repeating row "
                  f"{int(rows[np.flatnonzero(df.duplicated(keep=False).to_numpy() & ~dup)[0]])}", stacklevel=3)
    return df.loc[~dup].reset_index(drop=True), rows[~dup]
