"""Readers round 5: the CSV leftovers (leading '#' lines, Latin-1, markers in lines.csv) and the
other formats' no-data markers, repeated records and damaged files.  Every reading is compared
with the clean file's reading; refusals must name file, row and column."""

from __future__ import annotations

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
