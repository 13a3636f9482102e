"""Geosoft XYZ line-data files: reader and writer (SPEC §4 tables in XYZ form).

Format (as written by Oasis montaj "Export XYZ" and read by its "Import Geosoft XYZ")
-----------------------------------------------------------------------------------
Plain text, one sample per line, fields separated by blanks (spaces or tabs)::

    / Aerograv survey tiny, flight F01                 <- comment
    //flight 12                                        <- directive (recorded, not used)
    / TIME       FZ                 FX    FY           <- column header: the last '/'
    Random 1                                              line before the first data row,
    11743.059    9.8123456789012    0.1   *               when it has one name per field
    ...
    Line 1010                                          <- block header: keyword + line id
    12793.012    9.81077            0.2   0.1
    Tie 2010
    ...

* ``/`` starts a comment line; ``//`` lines are directives (``//flight``,
  ``//date``: Oasis montaj applies them to the lines that follow) — they are
  kept in :attr:`XyzScan.directives` but do not change the data.
* The column header is the last ``/`` line before the first data row, if it
  holds exactly as many words as that row has fields; otherwise the file has
  no header and columns are mapped by number (``[columns]`` in survey.toml).
  (So a header-less file must not end its leading comments with a line of
  exactly that many words.)
* Block headers start with a line-type keyword (any case) and the line id:
  ``Line``, ``Tie``, ``Base``, ``Test``, ``Trend``, ``Special``, ``Random`` — the
  seven line types of a Geosoft database (``DB_LINE_TYPE_NORMAL, BASE, TIE,
  TEST, TREND, SPECIAL, RANDOM`` in the GX API; the letters L, B, T, S, R, P, D
  of Oasis montaj line names such as ``T110.2:16`` = tie 110, version 2,
  flight 16).  The id is the rest of the header line, as written.  An Oasis montaj
  line name alone on a line (``L1010.1``, ``T2010``) is a block header too.
* Instead of block headers a ``line`` column may carry the line of every row
  (mapped as ``line`` in ``[columns]``, or a header column named ``line`` in a
  file without block headers): Oasis montaj line names (``L1010``,
  ``T2010``, …: the letter is the type, the rest the id) or plain numbers
  (normal lines); ``*`` marks rows on no line.  Consecutive rows with the same
  value form a block.
* Missing values: ``*`` (Oasis montaj's dummy in text) and any number ≤
  −0.9·10³² (the GX API's double dummy ``GS_R8DM = −1.0E32``; ``GS_R8MN =
  −0.9E32`` is the smallest valid value).  Missing values then follow the
  survey's NaN policy (``processing.max_nan_run``), like blank CSV cells.  The no-data
  markers of a CSV (``app.io.tables.mark_no_data``: −9999, −999.99, any magnitude ≥ 10³⁰ —
  so ``+1E32`` too —, f_z exactly 0 …) are missing values as well, with a warning; rows
  repeated exactly are dropped (``drop_duplicate_rows``); a last row with fewer fields (the
  file cut while written) is dropped with a warning.  Text that is not UTF-8 (``/ Höhe`` saved
  by a Windows program) is read as cp1252/Latin-1 with a warning.

Sources: Seequent Oasis montaj help ("Geosoft XYZ file format",
"Import Geosoft XYZ", "Select/Deselect Type": line types and the
``TYPE number.version:flight`` naming); the GX API constants
(GeosoftInc/gxpy ``geosoft/gxapi``: ``DB_LINE_TYPE_*``, ``GS_R8DM``); public
readers of the format: PyGMI ``vector/iodefs.py`` (``get_GXYZ``: ``/`` comments,
the last leading ``/`` line as the header, blocks split on ``line``/``tie``,
``*`` as NaN) and the geoWhizz airborne-gravity XYZ reader (``/`` header records,
``LINE``/``TIE`` blocks, ``*`` dummies).

What Aerograv makes of it
-------------------------
* Blocks ``Line <id>`` are survey lines of kind ``main``, ``Tie <id>`` of kind
  ``tie``.  ``Base``, ``Test``, ``Trend``, ``Special`` and ``Random`` blocks (and
  rows before the first block header) are data of the flight but not survey
  lines: parking-place readings fit ``Base``, test/calibration lines ``Test``,
  turns and transits ``Random`` (the writer puts everything off the survey
  lines in ``Random`` blocks).
* The time column follows SPEC §1: one monotonic time scale across the whole
  file, whatever the blocks; a time that does not increase is an error naming
  the row, exactly as in a CSV file.
* ``f_z`` (and ``f_x``, ``f_y``) are converted to m/s² from ``f_z_unit``
  (``"m/s2"``, ``"mGal"``, ``"um/s2"``); without it the unit is inferred from the
  median magnitude of f_z: 7–13 → m/s², 7·10⁵–1.3·10⁶ → mGal, 7·10⁶–1.3·10⁷ →
  µm/s²; anything else is an error asking for ``f_z_unit``.
* Every problem raises :class:`app.io.errors.InputError` with the file, the
  1-based line number in the file and the SPEC column name (``f_z``, ``h`` …);
  the message names the file's own column label.

The survey reader (:mod:`app.io.survey`) decides where the files are and how
the lines come from the blocks; this module only reads and writes files.
"""

from __future__ import annotations

import gzip
import io
import math
import os
import re
import shutil
import tempfile
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from app.config import F_Z_UNIT_TO_MS2, ColumnsSection
from app.io.errors import InputError
from app.io.tables import clock_time_hint, drop_duplicate_rows, mark_no_data, read_text

__all__ = ["XyzScan", "XyzBlock", "XyzTable", "scan_xyz", "xyz_table", "infer_f_z_unit",
           "write_xyz", "write_flight_xyz", "write_survey_xyz", "BLOCK_KEYWORDS", "LINE_KIND_OF_KEYWORD",
           "GEOSOFT_DUMMY_BELOW", "XYZ_ROLES"]

#: block keywords (lower case) → Geosoft line type letter
BLOCK_KEYWORDS = {"line": "L", "tie": "T", "base": "B", "test": "S", "trend": "R", "special": "P", "random": "D"}
_LETTER_KEYWORD = {v: k for k, v in BLOCK_KEYWORDS.items()}
#: which block keywords are survey lines, and of what kind
LINE_KIND_OF_KEYWORD = {"line": "main", "tie": "tie"}
#: numbers at or below this are Geosoft dummies (GS_R8MN = -0.9E32; the dummy itself is -1.0E32)
GEOSOFT_DUMMY_BELOW = -0.9e32
#: plausible median |f_z| per unit (f_z ≈ +9.8 m/s² at rest)
F_Z_UNIT_RANGES = {"m/s2": (7.0, 13.0), "mGal": (7e5, 1.3e6), "um/s2": (7e6, 1.3e7)}

#: the SPEC columns of each table read from an XYZ file
XYZ_ROLES = {
    "gravimeter": {"required": ("time", "f_z"), "optional": ("f_x", "f_y")},
    "gnss": {"required": ("time", "lat", "lon", "h"), "optional": ("vu", "ve", "vn", "sigma_v")},
}

_GEOSOFT_LINE_NAME = re.compile(r"^([LTBSRPD])\s*(\d+(?:\.\d+)?(?::\S+)?)$")
_NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")


@dataclass
class XyzBlock:
    """A block of consecutive data rows.

    ``keyword``: ``line``, ``tie``, ``base``, ``test``, ``trend``, ``special``,
    ``random``, or None for rows before the first block header (or rows on no
    line, with a line column).  ``start``/``stop``: data-row indices
    ``[start, stop)``; ``row``: file line number of the block header (of the
    block's first row with a line column).
    """

    keyword: str | None
    line_id: str | None
    row: int | None
    start: int
    stop: int

    @property
    def kind(self) -> str | None:
        """Survey-line kind (``main``/``tie``) or None for other blocks."""
        return LINE_KIND_OF_KEYWORD.get(self.keyword or "")


@dataclass
class XyzScan:
    """A scanned XYZ file: data rows located, blocks and header found, nothing parsed yet."""

    display: str
    data_lines: list[str]
    rows: np.ndarray                 # file line number of each data row
    n_fields: int
    names: list[str] | None          # column header (None: none found)
    header_row: int | None
    blocks: list[XyzBlock]
    directives: list[tuple[int, str]] = field(default_factory=list)
    _cache: dict = field(default_factory=dict, repr=False)

    def label(self, j: int) -> str:
        """The file's name of column ``j`` (0-based), or ``#j+1`` without a header."""
        return self.names[j] if self.names else f"#{j + 1}"


@dataclass
class XyzTable:
    """One SPEC table (gravimeter or GNSS) taken from an XYZ file.

    ``df``: SPEC columns (f_z etc. already in m/s²); ``rows``: file line number
    of each row; ``blocks``: the file's blocks re-indexed to rows of ``df``;
    ``f_z_unit``: the unit the file used (gravimeter only); ``labels``: SPEC
    column → the file's column label.
    """

    df: pd.DataFrame
    rows: np.ndarray
    blocks: list[XyzBlock]
    labels: dict[str, str]
    f_z_unit: str | None = None


# --------------------------------------------------------------------------- reading


def _read_text(path: Path, display: str) -> str:
    if not path.is_file():
        raise InputError(display, None, None, "file not found")
    return read_text(path, display)


def _keep_rows(blocks: list[XyzBlock], keep: np.ndarray) -> None:
    """Re-index ``blocks`` (in place) to the rows ``keep`` leaves."""
    pos = np.concatenate(([0], np.cumsum(keep)))
    for b in blocks:
        b.start, b.stop = int(pos[b.start]), int(pos[b.stop])


def scan_xyz(path, display: str | None = None) -> XyzScan:
    """Locate comments, directives, the header, block headers and data rows of an XYZ file.

    Raises
    ------
    InputError
        Empty file, a block header without an id, a data row whose number of
        fields differs from the first data row's, a header-like first data row.
    """
    path = Path(path)
    display = str(path) if display is None else display
    text = _read_text(path, display)
    lines = text.split("\n")
    data_idx: list[int] = []
    heads: list[tuple[str, str, int, int]] = []  # keyword, id, file row, data index
    directives: list[tuple[int, str]] = []
    last_comment: tuple[int, str] | None = None
    numeric_start = set("0123456789-+.*")
    for i, raw in enumerate(lines):
        s = raw.strip()
        if not s:
            continue
        c = s[0]
        if c in numeric_start:
            data_idx.append(i)
            continue
        if c == "/":
            if s.startswith("//"):
                directives.append((i + 1, s[2:].strip()))
            elif not data_idx:
                last_comment = (i + 1, s[1:])
            continue
        tok = s.split(None, 1)
        kw = tok[0].lower()
        bare = _GEOSOFT_LINE_NAME.match(s) if len(tok) == 1 else None
        if bare:   # an Oasis montaj line name alone (L1010.1, T2010): type letter and number
            heads.append((_LETTER_KEYWORD[bare.group(1)], bare.group(2), i + 1, len(data_idx)))
            continue
        if kw in BLOCK_KEYWORDS:
            if len(tok) < 2 or not tok[1].strip():
                raise InputError(display, i + 1, None, f"block header {tok[0]!r} without a line number")
            heads.append((kw, tok[1].strip(), i + 1, len(data_idx)))
            continue
        data_idx.append(i)  # a data row starting with text (e.g. a date or NaN): its fields are checked later
    if not data_idx:
        raise InputError(display, None, None, "the file has no data rows")
    rows = np.asarray(data_idx, dtype=np.int64) + 1
    data_lines = [lines[i] for i in data_idx]
    counts = np.fromiter((len(ln.split()) for ln in data_lines), dtype=np.int64, count=len(data_lines))
    n_fields = int(counts[0])
    if len(counts) > 2 and counts[-1] < n_fields and not (counts[:-1] != n_fields).any():
        # the recording stopped (or the file was copied while written) in the middle of the last row
        warnings.warn(f"{display}: the last row (row {int(rows[-1])}) has {int(counts[-1])} of the {n_fields} "
                      "fields: cut short when the file ended, dropped", stacklevel=3)
        data_lines, rows, counts = data_lines[:-1], rows[:-1], counts[:-1]
    bad = np.flatnonzero(counts != n_fields)
    if bad.size:
        k = int(bad[0])
        raise InputError(display, int(rows[k]), None,
                         f"this row has {int(counts[k])} fields, the first data row (row {int(rows[0])}) has "
                         f"{n_fields}: every row needs a value (or '*') in every column")
    first = data_lines[0].split()
    if all(not _NUMBER.match(f) and f != "*" for f in first) and any(c.isalpha() for c in data_lines[0]):
        raise InputError(display, int(rows[0]), None,
                         "this row looks like column names: write them on a comment line starting with '/' "
                         "just before the data (/ TIME FZ …)")
    names = header_row = None
    if last_comment is not None:
        toks = last_comment[1].split()
        if len(toks) == n_fields:
            names, header_row = toks, last_comment[0]
    blocks: list[XyzBlock] = []
    n = len(data_lines)
    if heads and heads[0][3] > 0:
        blocks.append(XyzBlock(None, None, None, 0, heads[0][3]))
    for k, (kw, lid, row, start) in enumerate(heads):
        stop = heads[k + 1][3] if k + 1 < len(heads) else n
        blocks.append(XyzBlock(kw, lid, row, start, stop))
    if not heads:
        blocks.append(XyzBlock(None, None, None, 0, n))
    return XyzScan(display, data_lines, rows, n_fields, names, header_row, blocks, directives)


def _parse_columns(scan: XyzScan, cols: list[int], fields: dict[int, str], text_cols: tuple[int, ...] = ()) -> dict:
    """Parse columns (0-based) of the data rows: float64 (dummies → NaN) or text; cached per scan."""
    need = [j for j in cols if j not in scan._cache]
    if need:
        num = [j for j in need if j not in text_cols]
        dtype = {j: (str if j in text_cols else np.float64) for j in need}
        buf = io.StringIO("\n".join(scan.data_lines))
        try:
            df = pd.read_csv(buf, sep=r"\s+", header=None, names=list(range(scan.n_fields)), usecols=need,
                             dtype=dtype, na_values=["*"], keep_default_na=False, engine="c")
        except ValueError:
            buf.seek(0)
            raw = pd.read_csv(buf, sep=r"\s+", header=None, names=list(range(scan.n_fields)), usecols=num,
                              dtype=str, keep_default_na=False, engine="c")
            best = None
            for j in num:
                s = raw[j]
                bad = np.flatnonzero(pd.to_numeric(s, errors="coerce").isna().to_numpy() & (s != "*").to_numpy())
                if bad.size and (best is None or (bad[0], j) < best[:2]):
                    best = (int(bad[0]), j, str(s.iloc[bad[0]]))
            if best is None:
                raise InputError(scan.display, None, None, "cannot parse the data rows") from None
            i, j, val = best
            fld = fields.get(j, scan.label(j))
            raise InputError(scan.display, int(scan.rows[i]), fld,
                             f"not a number: {val!r} (file column {scan.label(j)!r}){clock_time_hint(fld, val)}") from None
        for j in need:
            v = df[j].to_numpy()
            if j not in text_cols:
                v = v.astype(np.float64, copy=True)
                v[v <= GEOSOFT_DUMMY_BELOW] = np.nan
            scan._cache[j] = v
    return {j: scan._cache[j] for j in cols}


def _resolve(scan: XyzScan, fld: str, ref, role: str, explicit: bool) -> int | None:
    """0-based column index of SPEC field ``fld`` (None when absent and not mapped)."""
    where = f"[columns] {fld}" if explicit else None
    if isinstance(ref, int):
        if ref > scan.n_fields:
            raise InputError(scan.display, int(scan.rows[0]), fld,
                             f"{where} = {ref}, but the file has {scan.n_fields} columns")
        return ref - 1
    name = ref if ref is not None else fld
    if scan.names is None:
        if explicit:
            raise InputError(scan.display, None, fld,
                             f"{where} = {ref!r} names a column, but the file has no column header (a '/' comment "
                             f"line with the {scan.n_fields} column names just before the data): write one, or map "
                             f"the column by its number ({fld} = 3)")
        return None
    hits = [j for j, nm in enumerate(scan.names) if nm.lower() == name.lower()]
    if len(hits) > 1:
        raise InputError(scan.display, scan.header_row, fld,
                         f"the header names {len(hits)} columns {name!r} (columns {', '.join(str(h + 1) for h in hits)}): "
                         f"map {fld} by number in [columns]")
    if not hits:
        if explicit:
            have = ", ".join(scan.names)
            raise InputError(scan.display, scan.header_row, fld,
                             f"{where} = {ref!r}, but the file has no such column (columns found: {have})")
        return None
    return hits[0]


def infer_f_z_unit(median_abs: float) -> str | None:
    """The f_z unit whose plausible range holds the median |f_z|, or None."""
    for unit, (lo, hi) in F_Z_UNIT_RANGES.items():
        if lo <= median_abs <= hi:
            return unit
    return None


def _line_blocks(scan: XyzScan, values: np.ndarray, fld_label: str) -> list[XyzBlock]:
    """Blocks from a line column: runs of equal values; '*' or empty → no line."""
    out: list[XyzBlock] = []
    vals = [None if (v is None or (isinstance(v, float) and math.isnan(v)) or str(v).strip() in ("", "*"))
            else str(v).strip() for v in values]
    start = 0
    n = len(vals)
    for i in range(1, n + 1):
        if i < n and vals[i] == vals[start]:
            continue
        v = vals[start]
        if v is None:
            out.append(XyzBlock(None, None, int(scan.rows[start]), start, i))
        else:
            m = _GEOSOFT_LINE_NAME.match(v)
            if m:
                out.append(XyzBlock(_LETTER_KEYWORD[m.group(1)], m.group(2), int(scan.rows[start]), start, i))
            elif _NUMBER.match(v):
                out.append(XyzBlock("line", v, int(scan.rows[start]), start, i))
            else:
                raise InputError(scan.display, int(scan.rows[start]), "line",
                                 f"line value {v!r} (file column {fld_label!r}) is neither an Oasis montaj line name "
                                 f"(a type letter L, T, B, S, R, P or D, then the number: L1010, T2010) nor a "
                                 f"number; use '*' for rows on no survey line")
        start = i
    return out


def xyz_table(scan: XyzScan, role: str, columns: ColumnsSection | None, *, combined: bool = False) -> XyzTable:
    """Take the SPEC table of ``role`` (``"gravimeter"`` or ``"gnss"``) out of a scanned XYZ file.

    Parameters
    ----------
    scan : XyzScan
    role : {"gravimeter", "gnss"}
    columns : ColumnsSection or None
        The ``[columns]`` mapping (None: every field under its own name).
    combined : bool
        The file holds both tables: a row belongs to ``role`` when at least
        one of the role's data columns (not ``time``) has a value; rows where
        all of them are missing are the other sensor's samples.

    Returns
    -------
    XyzTable
        Not yet validated (missing values, time order, rates: app.io.survey).
    """
    spec = XYZ_ROLES[role]
    cmap = (columns or ColumnsSection()).for_role(role)
    idx: dict[str, int] = {}
    for fld in spec["required"] + spec["optional"]:
        j = _resolve(scan, fld, cmap.get(fld), role, fld in cmap)
        if j is None:
            if fld in spec["required"]:
                have = ", ".join(scan.names) if scan.names else f"no header; {scan.n_fields} columns"
                raise InputError(scan.display, scan.header_row, fld,
                                 f"required column '{fld}' is missing (columns found: {have}); map it in survey.toml "
                                 f"[columns] ({fld} = \"NAME\" or its number)")
            continue
        idx[fld] = j
    fields_of = {j: f for f, j in idx.items()}
    vals = _parse_columns(scan, list(idx.values()), fields_of)
    df = pd.DataFrame({f: vals[j] for f, j in idx.items()})
    rows = scan.rows
    # blocks: from the line column when there is one, else from the block headers
    line_ref = cmap.get("line")
    j_line = _resolve(scan, "line", line_ref, role, "line" in cmap)
    has_heads = any(b.keyword is not None for b in scan.blocks)
    if j_line is not None and (line_ref is not None or not has_heads):
        if has_heads:
            raise InputError(scan.display, scan.blocks[-1].row, "line",
                             "the file has both block headers (Line/Tie …) and a line column ([columns] line): "
                             "use one of them")
        lv = _parse_columns(scan, [j_line], {j_line: "line"}, text_cols=(j_line,))[j_line]
        blocks = _line_blocks(scan, lv, scan.label(j_line))
    else:
        blocks = [XyzBlock(b.keyword, b.line_id, b.row, b.start, b.stop) for b in scan.blocks]
    # as in a CSV: rows repeated exactly dropped, no-data markers (−9999, +1e32 …) made missing
    keep = ~df.duplicated().to_numpy()
    df, rows = drop_duplicate_rows(df, rows, scan.display)
    if not keep.all():
        _keep_rows(blocks, keep)
    mark_no_data(df, rows, scan.display, list(idx))
    if combined:
        data_cols = [f for f in idx if f != "time"]
        mask = ~np.all(np.isnan(df[data_cols].to_numpy(dtype=float)), axis=1)
        if not mask.all():
            _keep_rows(blocks, mask)
            df = df.loc[mask].reset_index(drop=True)
            rows = rows[mask]
    unit = None
    if role == "gravimeter":
        unit = cmap.get("f_z_unit")
        fz = df["f_z"].to_numpy(dtype=float)
        if unit is None:
            med = float(np.nanmedian(np.abs(fz))) if np.isfinite(fz).any() else float("nan")
            unit = infer_f_z_unit(med)
            if unit is None:
                raise InputError(scan.display, None, "f_z",
                                 f"cannot tell the unit of f_z (file column {scan.label(idx['f_z'])!r}) from its values "
                                 f"(median |f_z| = {med:.6g}; expected about 9.8 for m/s², 980000 for mGal, 9.8e6 for "
                                 f"µm/s²): set f_z_unit in survey.toml [columns] to 'm/s2', 'mGal' or 'um/s2' "
                                 f"(relative readings need an absolute offset first)")
        k = F_Z_UNIT_TO_MS2[unit]
        if k != 1.0:
            for c in ("f_z", "f_x", "f_y"):
                if c in df:
                    df[c] = df[c].to_numpy(dtype=float) * k
    labels = {f: scan.label(j) for f, j in idx.items()}
    return XyzTable(df, np.asarray(rows, dtype=np.int64), blocks, labels, unit)


# --------------------------------------------------------------------------- writing


def _fmt_block(df: pd.DataFrame) -> str:
    """Rows as text: shortest round-trip repr of every float, '*' for missing values."""
    if len(df) == 0:
        return ""
    return df.to_csv(sep=" ", header=False, index=False, na_rep="*", lineterminator="\n")


def write_xyz(path, table: pd.DataFrame, names: dict[str, str], segments: list[tuple[str, str, int, int]],
              comments: tuple[str, ...] = ()) -> Path:
    """Write one XYZ file.

    Parameters
    ----------
    path : path-like
        Destination (``.gz`` → gzip).
    table : DataFrame
        The rows, in order; NaN is written as ``*``.
    names : dict
        ``{column of table: name in the file header}``, in file column order.
    segments : list of (keyword, id, i0, i1)
        Consecutive row ranges ``[i0, i1)`` covering the table, each written
        after a block header ``<Keyword> <id>``.
    comments : tuple of str
        ``/`` comment lines written before the header.
    """
    path = Path(path)
    cols = list(names)
    out = [f"/ {c}" for c in comments]
    out.append("/ " + " ".join(names[c] for c in cols))
    text = "\n".join(out) + "\n"
    body = [text]
    sub = table[cols]
    for kw, lid, i0, i1 in segments:
        body.append(f"{kw.capitalize()} {lid}\n")
        body.append(_fmt_block(sub.iloc[i0:i1]))
    data = "".join(body)
    if path.name.lower().endswith(".gz"):
        with gzip.open(path, "wt", encoding="utf-8", newline="\n") as fh:
            fh.write(data)
    else:
        path.write_text(data, encoding="utf-8", newline="\n")
    return path


def line_segments(t: np.ndarray, lines: pd.DataFrame) -> list[tuple[str, str, int, int]]:
    """Blocks of a time series: each survey line's window ``[t_start, t_end]`` a ``Line``/``Tie``
    block (repeat lines are ``Line`` blocks too), the stretches between them ``Random`` blocks.

    Raises
    ------
    ValueError
        Overlapping line windows.
    """
    t = np.asarray(t, dtype=float)
    ln = lines.sort_values("t_start", kind="stable")
    segs: list[tuple[str, str, int, int]] = []
    pos = 0
    k = 0
    prev_end = -np.inf
    for r in ln.itertuples(index=False):
        if r.t_start <= prev_end:
            raise ValueError(f"line {r.line} overlaps the previous line of its flight in time")
        prev_end = r.t_end
        i0 = int(np.searchsorted(t, r.t_start, side="left"))
        i1 = int(np.searchsorted(t, r.t_end, side="right"))
        if i0 > pos:
            k += 1
            segs.append(("random", str(k), pos, i0))
        segs.append(("tie" if r.kind == "tie" else "line", str(r.line), i0, i1))
        pos = i1
    if pos < t.size or not segs:
        k += 1
        segs.append(("random", str(k), pos, t.size))
    return segs


#: file header names written by :func:`write_flight_xyz` (Oasis montaj style channel names)
XYZ_WRITE_NAMES = {"time": "TIME", "f_z": "FZ", "f_x": "FX", "f_y": "FY", "lat": "LAT", "lon": "LON", "h": "HGT",
                   "vu": "VU", "ve": "VE", "vn": "VN", "sigma_v": "SIGMA_V"}


def _same_rate(ta: np.ndarray, tb: np.ndarray, rel: float = 1e-3) -> bool:
    from app.io.tables import median_rate_hz

    ra, rb = median_rate_hz(ta), median_rate_hz(tb)
    return bool(np.isfinite(ra) and np.isfinite(rb) and abs(ra - rb) <= rel * max(ra, rb))


def write_flight_xyz(flight_dir, name: str, gravimeter: pd.DataFrame, gnss: pd.DataFrame, lines: pd.DataFrame,
                     combined: bool = False, names: dict[str, str] | None = None) -> list[Path]:
    """Write one flight's gravimeter and GNSS tables as XYZ files with line blocks.

    Parameters
    ----------
    flight_dir : path-like
        ``flights/<flight>/`` (created).
    name : str
        The flight name (used in comments and the combined file name).
    gravimeter, gnss : DataFrame
        SPEC tables (gravimeter in m/s²).
    lines : DataFrame
        The flight's survey lines (``line, t_start, t_end, kind``).
    combined : bool
        One ``<name>.xyz`` holding both tables when their rates are equal (rows
        on the union of the time stamps, ``*`` in the columns of the sensor
        without a sample at that time); otherwise, or when False,
        ``gravimeter.xyz`` and ``gnss.xyz``.
    names : dict, optional
        SPEC column → name in the file header (default :data:`XYZ_WRITE_NAMES`).

    Returns
    -------
    list of Path
        The files written.
    """
    names = XYZ_WRITE_NAMES if names is None else names
    d = Path(flight_dir)
    d.mkdir(parents=True, exist_ok=True)
    tg = gravimeter["time"].to_numpy(dtype=float)
    tn = gnss["time"].to_numpy(dtype=float)
    gcols = [c for c in ("time", "f_z", "f_x", "f_y") if c in gravimeter]
    ncols = [c for c in ("time", "lat", "lon", "h", "vu", "ve", "vn", "sigma_v") if c in gnss]
    if combined and _same_rate(tg, tn):
        both = pd.merge(gravimeter[gcols], gnss[ncols], on="time", how="outer", sort=True)
        p = write_xyz(d / f"{name}.xyz", both, {c: names[c] for c in gcols + ncols[1:]},
                      line_segments(both["time"].to_numpy(), lines),
                      comments=(f"Aerograv flight {name}: gravimeter (m/s2) and GNSS",))
        return [p]
    pg = write_xyz(d / "gravimeter.xyz", gravimeter, {c: names[c] for c in gcols},
                   line_segments(tg, lines), comments=(f"Aerograv flight {name}: gravimeter, specific force in m/s2",))
    pn = write_xyz(d / "gnss.xyz", gnss, {c: names[c] for c in ncols}, line_segments(tn, lines),
                   comments=(f"Aerograv flight {name}: GNSS",))
    return [pg, pn]


def _columns_toml(mapped: dict[str, str]) -> str:
    out = ["[columns]", 'f_z_unit = "m/s2"']
    out += [f'{k} = "{v}"' for k, v in mapped.items()]
    return "\n".join(out) + "\n"


def write_survey_xyz(src_survey_dir, dst_dir, combined: bool = False, keep_lines_csv: bool = True) -> Path:
    """Convert a survey directory (SPEC-CSV, G files …) into the same survey in XYZ form.

    Every flight's tables (as :func:`app.io.survey.read_survey` reads them)
    are written by :func:`write_flight_xyz` with ``Line``/``Tie`` blocks for the
    survey-line windows and ``Random`` blocks for the rest of the record;
    numbers are written with the shortest repr that round-trips, so reading
    the result gives bit-identical tables.  ``survey.toml`` is copied with a
    ``[columns]`` table appended; ``lines.csv`` is copied unless
    ``keep_lines_csv`` is False — but always when the survey has repeat lines
    (their kind and track cannot be told from blocks).  A ``vu`` column that
    the reader derived from ``h`` is not written (the XYZ survey derives it
    again).  The destination is written in a temporary sibling directory and
    renamed into place.

    Returns
    -------
    Path
        The destination directory.
    """
    from app.io.survey import read_survey

    src = Path(src_survey_dir)
    survey = read_survey(src)
    toml_text = (src / "survey.toml").read_text(encoding="utf-8-sig")
    if "columns" in tomllib.loads(toml_text):
        raise ValueError(f"{src / 'survey.toml'} already has a [columns] table: convert a SPEC-CSV survey")
    tables = {name: (fl.gravimeter, fl.gnss.drop(columns="vu") if fl.vu_derived_from_h else fl.gnss)
              for name, fl in survey.flights.items()}
    # a column every flight has is written under its Oasis-style name and mapped in [columns]; one that
    # only some flights have keeps its SPEC name in upper case (found without a mapping)
    common = set.intersection(*(set(g.columns) | set(n.columns) for g, n in tables.values()))
    names = {c: (XYZ_WRITE_NAMES[c] if c in common else c.upper()) for c in XYZ_WRITE_NAMES}
    mapped = {c: names[c] for c in XYZ_WRITE_NAMES if c in common}
    out = Path(dst_dir).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        os.chmod(tmp, 0o755)
        body = toml_text if toml_text.endswith("\n") or not toml_text else toml_text + "\n"
        (tmp / "survey.toml").write_text(body + "\n" + _columns_toml(mapped), encoding="utf-8")
        lines = survey.lines
        if keep_lines_csv or (lines["kind"] == "repeat").any():
            shutil.copyfile(src / "lines.csv", tmp / "lines.csv")
        for name, (grav, gnss) in tables.items():
            write_flight_xyz(tmp / "flights" / name, name, grav, gnss, lines[lines["flight"] == name],
                             combined=combined, names=names)
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.replace(out, old / "x")
            shutil.rmtree(old, ignore_errors=True)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
