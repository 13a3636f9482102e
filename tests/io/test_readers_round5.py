"""Readers round 5: the CSV leftovers (leading '#' lines, Latin-1, markers in lines.csv) and the
other formats' no-data markers, repeated records and damaged files.  Every reading is compared
with the clean file's reading; refusals must name file, row and column."""

from __future__ import annotations

import gzip

import pytest

from app.io.errors import InputError
from app.io.tables import read_csv_table
from tests.io.test_converter_dialects import _read_quiet, _rewrite, _same_tables
from tests.io.test_io_survey import expect_error, make_tables, write_survey


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    lines, tabs = make_tables()
    root = write_survey(tmp_path_factory.mktemp("clean") / "s", lines, tabs)
    return root, lines, tabs, _read_quiet(root)[0]


def _bad_row(text: str, k: int, col: int, value: str) -> str:
    lines = text.split("\n")
    f = lines[k].split(",")
    f[col] = value
    lines[k] = ",".join(f)
    return "\n".join(lines)


# ----------------------------------------------------------------------------- CSV leftovers


def test_leading_hash_lines_are_skipped(clean, tmp_path):
    _, lines, tabs, ref = clean
    root = write_survey(tmp_path / "s", lines, tabs)
    for name in ("gravimeter.csv", "gnss.csv"):
        _rewrite(root, name, lambda t: ("# exported by X\n#  units: SI\n" + t).encode())
    (root / "lines.csv").write_text("# lines of the survey\n" + (root / "lines.csv").read_text())
    _same_tables(ref, _read_quiet(root)[0])


def test_leading_hash_lines_keep_the_files_row_numbers(tmp_path):
    p = tmp_path / "g.csv"
    body = "time,f_z\n" + "".join(f"{k}.0,9.81\n" for k in range(10))
    p.write_text("# one\n# two\n" + _bad_row(body, 6, 1, "x"))
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "g.csv", ("time", "f_z"))
    assert (ei.value.row, ei.value.column) == (9, "f_z")   # line 9 of the file, as an editor shows it
    p.write_text("# one\n" + body)
    df, rows = read_csv_table(p, "g.csv", ("time", "f_z"))
    assert rows[0] == 3 and rows[-1] == 12 and df["time"].tolist() == [float(k) for k in range(10)]
    p.write_text("# one\n" + body.replace("time,f_z", "time,f_z [mGal]"))
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "g.csv", ("time", "f_z"))
    assert ei.value.row == 2


def test_a_commented_out_header_says_so(tmp_path):
    p = tmp_path / "g.csv"
    p.write_text("#time,f_z\n1.0,9.81\n2.0,9.81\n")
    with pytest.raises(InputError, match="remove the '#'") as ei:
        read_csv_table(p, "g.csv", ("time", "f_z"))
    assert (ei.value.row, ei.value.column) == (2, "time")


def test_latin1_file_is_read_with_a_warning(clean, tmp_path):
    _, lines, tabs, ref = clean
    root = write_survey(tmp_path / "s", lines, tabs)
    _rewrite(root, "gnss.csv", lambda t: ("# Höhe über NN\n" + t.replace(",lat,", ",lat [°],", 1)).encode("latin-1"))
    _rewrite(root, "gravimeter.csv", lambda t: ("# 5 µs\n" + t).encode("cp1252"))
    s, msgs = _read_quiet(root)
    _same_tables(ref, s)
    assert sum("not UTF-8" in m and "row 1" in m for m in msgs) == 2


def test_no_data_marker_as_a_line_time_is_named(clean, tmp_path):
    _, lines, tabs, _ = clean
    root = write_survey(tmp_path / "s", lines, tabs)
    text = (root / "lines.csv").read_text()
    col = text.split("\n")[0].split(",").index("t_start")
    (root / "lines.csv").write_text(_bad_row(text, 2, col, "-9999"))
    e = expect_error(root, "lines.csv", 3, "t_start", match="no-data marker")
    assert "-9999" in str(e)


# ----------------------------------------------------------------------------- Geosoft XYZ

NAN_RUN = {"max_nan_run": 3}   # a missing value of another column is interpolated
_G, _N = "flights/F1/gravimeter.xyz", "flights/F1/gnss.xyz"


def _set_cells(text: str, cells, value: str) -> str:
    """``value`` in field ``col`` of the ``k``-th data row (0-based) for each ``(k, col)``."""
    lines = text.split("\n")
    data = [i for i, ln in enumerate(lines) if ln[:1].isdigit()]
    for k, col in cells:
        f = lines[data[k]].split()
        f[col] = value
        lines[data[k]] = "  ".join(f)
    return "\n".join(lines)


def _xyz(root, gfn=None, nfn=None, toml=None):
    from tests.io.test_xyz import make_xyz_survey

    kw = {"toml": toml} if toml else {}
    make_xyz_survey(root, **kw)
    for rel, fn in ((_G, gfn), (_N, nfn)):
        if fn:
            (root / rel).write_bytes(fn((root / rel).read_text()))
    return root


XYZ_CELLS = {"g": [(300, 1)], "n": [(301, 1), (303, 2), (305, 3), (307, 4)]}


@pytest.mark.parametrize("marker", ["-1e32", "1e32", "-1.0E+32", "-9999", "-999.99"])
def test_xyz_dummies_and_markers_are_missing_values(tmp_path, marker):
    """Geosoft's dummies and the CSV markers in every column read as '*' does (+1e32, −9999 were
    refused as out of range, −999 in vu was read as a velocity)."""
    def edit(v):
        return (lambda t: _set_cells(t, XYZ_CELLS["g"], v).encode(), lambda t: _set_cells(t, XYZ_CELLS["n"], v).encode())
    ref = _read_quiet(_xyz(tmp_path / "star", *edit("*")), NAN_RUN)[0]
    s, msgs = _read_quiet(_xyz(tmp_path / "m", *edit(marker)), NAN_RUN)
    _same_tables(ref, s)
    assert len(s.flights["F1"].gravimeter) == 1199   # the f_z hole
    if marker not in ("-1e32", "-1.0E+32"):
        assert any("no-data markers" in m and "first at row 305" in m for m in msgs)


def test_xyz_repeated_rows_cut_last_row_and_bare_line_names(tmp_path):
    ref = _read_quiet(_xyz(tmp_path / "ref"))[0]

    def dup_and_rename(t: str) -> bytes:
        lines = t.split("\n")
        k = lines.index("Line 1001") + 5
        lines.insert(k, lines[k])
        return "\n".join(lines).replace("Line 1001", "L1001").replace("TIE 2001", "T2001").encode()

    s, msgs = _read_quiet(_xyz(tmp_path / "d", dup_and_rename, dup_and_rename))
    _same_tables(ref, s)
    assert sum("repeating an earlier row exactly" in m for m in msgs) == 2

    cut_ref = _read_quiet(_xyz(tmp_path / "c0", lambda t: t.rstrip("\n").rsplit("\n", 1)[0].encode() + b"\n"))[0]
    s, msgs = _read_quiet(_xyz(tmp_path / "c", lambda t: t.rstrip("\n").rsplit("  ", 1)[0].encode() + b"\n"))
    _same_tables(cut_ref, s)
    assert any("last row (row 1207)" in m and "cut short" in m for m in msgs)


def test_xyz_latin1_header_and_clock_times(tmp_path):
    toml = '[survey]\nname = "x"\n[columns]\nh = "Höhe"\n'

    def hoehe(enc):
        return lambda t: ("/ Höhe über NN\n" + t.replace("/ time  lat  lon  h  vu", "/ time  lat  lon  Höhe  vu")).encode(enc)

    ref = _read_quiet(_xyz(tmp_path / "u", nfn=hoehe("utf-8"), toml=toml))[0]
    s, msgs = _read_quiet(_xyz(tmp_path / "l", nfn=hoehe("latin-1"), toml=toml))
    _same_tables(ref, s)
    assert any("not UTF-8" in m and "row 1" in m for m in msgs)
    root = _xyz(tmp_path / "c", nfn=lambda t: _set_cells(t, [(0, 0)], "03:33:20.00").encode())
    expect_error(root, _N, 4, "time", match="clock time")


# ----------------------------------------------------------------------------- G files, DGS records


def _g_root(root, edit=None, gz=None):
    from tests.io.test_gfile import MSG_HZ, _g_survey, make_messages

    msgs, _ = make_messages(int(300 * MSG_HZ), t0_sod=3600.0)
    _g_survey(root, msgs)
    p = root / "flights/F1/F1.G"
    if edit:
        p.write_text(edit(p.read_text()))
    if gz:
        (root / "flights/F1/F1.G.gz").write_bytes(gz(gzip.compress(p.read_bytes())))
        p.unlink()
    return root


def _field(text: str, k: int, j: int, value: str, sep: str = " ") -> str:
    lines = text.split("\n")
    f = lines[k].split(sep)
    f[j] = value
    lines[k] = sep.join(f)
    return "\n".join(lines)


def _dup_line(text: str, k: int) -> str:
    lines = text.split("\n")
    lines.insert(k, lines[k])
    return "\n".join(lines)


def _dgs_root(root, edit=None):
    from tests.io.test_dgs import _dgs_survey

    _dgs_survey(root, False, toml='[survey]\nname = "d"\n[gravimeter]\nreading_offset_mgal = 970000.0\n')
    p = root / "flights/F1/AT1A_0042.dat"
    if edit:
        p.write_text(edit(p.read_text()))
    return root


#: format → (survey maker, line index and field of the reading, separator, a missing reading, its column)
READING = {"g": (_g_root, 301, 4, " ", "nan", "fine_z_1"), "dgs": (_dgs_root, 500, 0, ",", "", "gravity")}


@pytest.mark.parametrize("fmt, marker", [("g", "-9999"), ("g", "-999.99"), ("g", "1e32"), ("g", "0"),
                                         ("dgs", "-9999"), ("dgs", "99999999"), ("dgs", "1e32"), ("dgs", "0.000000")])
def test_markers_and_zeros_in_the_reading_are_holes(tmp_path, fmt, marker):
    """A marker or a 0 in a G file's fine Z field or a DGS gravity reading reads as a missing one
    does (a hole): 0 had been read as a value (G: a 980 000 mGal spike; DGS: a relative reading
    plus the offset, plausible), −9999 too (DGS) or refused as out of range (G)."""
    make, k, j, sep, missing, col = READING[fmt]
    ref = _read_quiet(make(tmp_path / "nan", lambda t: _field(t, k, j, missing, sep)), NAN_RUN)[0]
    s, msgs = _read_quiet(make(tmp_path / "m", lambda t: _field(t, k, j, marker, sep)), NAN_RUN)
    _same_tables(ref, s)
    assert any("no-data markers" in m and col in m and f"row {k + 1}" in m for m in msgs)


@pytest.mark.parametrize("fmt", ["g", "dgs"])
def test_a_repeated_message_or_record_is_dropped(tmp_path, fmt):
    make = READING[fmt][0]
    ref = _read_quiet(make(tmp_path / "ref"))[0]
    s, msgs = _read_quiet(make(tmp_path / "dup", lambda t: _dup_line(t, 400)))
    _same_tables(ref, s)
    assert any("repeating an earlier row exactly" in m and "row 401" in m for m in msgs)


def test_g_file_garbage_and_gzip(tmp_path):
    ref = _read_quiet(_g_root(tmp_path / "ref"))[0]
    _same_tables(ref, _read_quiet(_g_root(tmp_path / "gz", gz=lambda b: b))[0])   # F1.G.gz is found
    root = _g_root(tmp_path / "cut", gz=lambda b: b[: len(b) // 2])
    expect_error(root, "flights/F1/F1.G.gz", None, None, match="cannot read the file")
    root = _g_root(tmp_path / "bytes")
    p = root / "flights/F1/F1.G"
    raw = p.read_bytes().split(b"\n")
    raw[20] = b"\xff\xfe garbage \xe9"
    p.write_bytes(b"\n".join(raw))
    expect_error(root, "flights/F1/F1.G", 21, "message_id", match="not a number")
