"""Shared table helpers checked against brute-force references."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from app.io.errors import InputError
from app.io.tables import MAX_COLUMNS, check_time_increasing, fill_short_nan_runs, gap_rows_in_windows, read_csv_table


def brute_gaps(t, a, b, max_gap):
    for i in range(len(t) - 1):
        if t[i + 1] - t[i] > max_gap and t[i + 1] > a and t[i] < b:
            return i + 1
    return -1


def test_gap_rows_in_windows_matches_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(20):
        dt = rng.choice([0.1, 0.1, 0.1, 0.1, 2.5], size=400)
        t = np.cumsum(dt)
        a = rng.uniform(0, t[-1], 50)
        b = a + rng.uniform(0.01, 20.0, 50)
        got = gap_rows_in_windows(t, a, b, 1.0)
        ref = [brute_gaps(t, x, y, 1.0) for x, y in zip(a, b)]
        assert got.tolist() == ref


def test_scattered_stamps_do_not_turn_an_allowed_step_into_a_gap():
    """2 Hz stamps, one missing epoch (a 1 s step) with max_gap_s = 1: a step 20 ms longer (a
    logger's scatter, within 5 % of the 0.5 s median) is no gap; 30 ms longer is."""
    t = 0.5 * np.arange(100.0)
    for extra, gap in ((0.0, False), (0.02, False), (0.03, True)):
        tt = np.concatenate([t[:50], t[51:] + extra])
        got = gap_rows_in_windows(tt, np.array([0.0]), np.array([49.0]), 1.0)
        assert (got[0] == 50) == gap, extra


def test_fill_short_nan_runs_linear_in_time():
    t = np.array([0.0, 1.0, 3.0, 4.0, 10.0])
    v = np.array([0.0, np.nan, np.nan, 8.0, 20.0])  # true line v = 2 t
    df = pd.DataFrame({"time": t, "v": v})
    fill_short_nan_runs(df, ["time", "v"], np.arange(2, 7), "x.csv", max_nan_run=2)
    np.testing.assert_allclose(df["v"], 2 * t)
    df = pd.DataFrame({"time": t, "v": v})
    with pytest.raises(InputError) as ei:
        fill_short_nan_runs(df, ["time", "v"], np.arange(2, 7), "x.csv", max_nan_run=1)
    assert (ei.value.row, ei.value.column) == (3, "v")


def test_time_check_rows():
    with pytest.raises(InputError) as ei:
        check_time_increasing(np.array([0.0, 1.0, 2.0, 1.5]), np.array([2, 3, 4, 5]), "f")
    assert ei.value.row == 5


def test_header_case_blank_lines_and_parse_error(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text(" Time ,F_Z,extra\n1,9.8,x\n\n3,9.8,y\n\n\n")
    df, rows = read_csv_table(p, "a.csv", ("time", "f_z"))
    assert rows.tolist() == [2, 3, 4]  # the inner blank line is a row of missing values, trailing ones dropped
    assert np.isnan(df["time"].iloc[1])
    p.write_text('time,f_z\n1,9.8\n2,9.8\n3,9.8\n4,"9,8"\n')
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "a.csv", ("time", "f_z"))
    assert (ei.value.row, ei.value.column) == (5, "f_z") and "'9,8'" in str(ei.value)
    p.write_text("time,f_z\n1,9.8\n2,9.8\n3,9.8\n4,9.8,7\n")
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "a.csv", ("time", "f_z"))
    assert ei.value.row == 5


def test_surplus_field_message_names_the_row(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text("time,f_z,extra\n1,9.8,a\n2,9,81,b\n3,9.8,c\n")  # decimal comma on line 3
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "a.csv", ("time", "f_z"))
    assert ei.value.row == 3 and "more fields" in str(ei.value)


def test_surplus_field_row_is_reported(tmp_path):
    p = tmp_path / "a.csv"
    for text, row in (("time,f_z,extra\n1,9.8,a\n2,9,81,b\n3,9.8,c\n", 3),  # decimal comma on line 3
                      ("time,f_z\n1,9,8\n2,9.8\n", 2)):
        p.write_text(text)
        with pytest.raises(InputError) as ei:
            read_csv_table(p, "a.csv", ("time", "f_z"))
        assert ei.value.row == row, str(ei.value)


def test_median_rate_not_biased_by_rounded_stamps():
    from app.io.tables import median_rate_hz

    t = np.round(1000.0 + np.arange(5000) / 18.24, 3)  # stamps rounded to 1 ms
    assert median_rate_hz(t) == pytest.approx(18.24, rel=2e-3)
    assert 1.0 / np.median(np.diff(t)) == pytest.approx(18.18, rel=1e-3)  # what a plain median gives


def test_other_separators_and_unnamed_gzip_say_so(tmp_path):
    """Semicolons and tabs are read (the header says which, csv_dialect); a separator the
    reader does not take (bars) is refused at the header, naming it."""
    p = tmp_path / "a.csv"
    p.write_text("time|f_z\n1|9.8\n")
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "a.csv", ("time", "f_z"))
    assert ei.value.row == 1 and "bars" in str(ei.value) and "commas" in str(ei.value)
    import gzip

    p.write_bytes(gzip.compress(b"time,f_z\n1,9.8\n2,9.8\n"))
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "a.csv", ("time", "f_z"))
    assert "gzip" in str(ei.value) and "a.csv.gz" in str(ei.value)


def test_too_many_columns_is_refused_at_the_header(tmp_path):
    """Every column is tokenized, so a table of 100 000 columns took 26 s for 1.3 MB: past
    MAX_COLUMNS the header line is refused (row 1) before the data are read; at the limit the
    table reads."""
    p = tmp_path / "wide.csv"
    extra = [f"c{i}" for i in range(MAX_COLUMNS - 2)]
    p.write_text(",".join(["time", "f_z"] + extra) + "\n" + ",".join(["1", "9.8"] + ["0"] * len(extra)) + "\n")
    df, _ = read_csv_table(p, "wide.csv", ("time", "f_z"))
    assert df["f_z"].tolist() == [9.8]
    p.write_text(",".join(["time", "f_z"] + extra + ["one_more"]) + "\n"
                 + ",".join(["1", "9.8"] + ["0"] * (len(extra) + 1)) + "\n")
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "wide.csv", ("time", "f_z"))
    assert (ei.value.file, ei.value.row) == ("wide.csv", 1) and f"{MAX_COLUMNS + 1:,} columns" in str(ei.value)


def test_chunked_reading_keeps_values_and_finds_a_stray_separator_late(tmp_path, monkeypatch):
    """A wide table is tokenized a chunk of rows at a time, only the wanted columns kept (a 234 kB
    gzip of 999 columns had cost the server 1.1 GB parsed whole): the values and row numbers are
    those of a whole-file read, and a decimal comma in a later chunk is still found on its row."""
    import app.io.tables as tables

    monkeypatch.setattr(tables, "CHUNK_CELLS", 50)   # 1000 rows per chunk (the floor)
    rng = np.random.default_rng(0)
    n = 3500
    df = pd.DataFrame({"time": np.arange(n) * 0.1, "f_z": 9.8 + rng.standard_normal(n)})
    for i in range(40):
        df[f"x{i}"] = "a"
    p = tmp_path / "w.csv"
    df.to_csv(p, index=False)
    got, rows = read_csv_table(p, "w.csv", ["time", "f_z"])
    np.testing.assert_array_equal(got["f_z"].to_numpy(), pd.read_csv(p)["f_z"].to_numpy())
    np.testing.assert_array_equal(rows, np.arange(2, n + 2))
    lines = p.read_text().splitlines()
    lines[2600] = lines[2600].replace(",a,", ",9,81,", 1)        # file row 2601, in the third chunk
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "w.csv", ["time", "f_z"])
    assert ei.value.row == 2601 and "more fields than the header" in str(ei.value)


def test_gzip_bomb_refused_before_parsing(tmp_path, monkeypatch):
    """Under a size limit a .csv.gz is measured by streaming it (constant memory) before the parser
    sees a byte: a 2.6 MB gzip inflating to 1 GB had cost the server 640 MB refused by the parser."""
    import gzip

    import app.io.tables as tables

    p = tmp_path / "g.csv.gz"
    with gzip.open(p, "wb") as fh:
        fh.write(b"time,f_z\n" + b"1.0,9.8\n" * 300_000)        # 2.4 MB inflated
    calls = []
    monkeypatch.setattr(tables.pd, "read_csv", lambda *a, **k: calls.append(1) or pd.DataFrame())
    with tables.table_limits(max_bytes=1 << 20), pytest.raises(InputError, match="expands to more than"):
        read_csv_table(p, "g.csv.gz", ["time", "f_z"])
    assert calls == []


@pytest.mark.parametrize("name", ["gravimeter.g.gz", "F1.xyz.gz", "rec.dat.gz"])
def test_text_formats_gzip_capped_at_the_limit(tmp_path, name):
    """G files, XYZ and DGS records are read whole as text: under a size limit a .gz that expands
    past it is refused after reading at most the limit (a 3 kB gzip inflating to 3 MB against 1 MB),
    and one within it reads back exactly; the format sniff reads a few capped pieces of one endless
    line."""
    import gzip

    import app.io.tables as tables
    from app.io.dgs import _first_lines

    p = tmp_path / name
    body = b"0" * (3 << 20)                       # one line, no newline: 3 MB
    with gzip.open(p, "wb") as fh:
        fh.write(body)
    with tables.table_limits(max_bytes=1 << 20), pytest.raises(InputError, match="expands to more than"):
        tables.read_text(p, name)
    with tables.table_limits(max_bytes=4 << 20):
        assert tables.read_text(p, name) == body.decode()
    first = _first_lines(p, 5)                    # five pieces of 64 kB, not the 3 MB line
    assert len(first) == 5 and all(len(x) == 1 << 16 for x in first)


def test_not_utf8_byte_past_the_sniffed_head_read_as_cp1252(tmp_path):
    """A cp1252 '°' in a remark column at row 6001, past the 64 kB the dialect sniff reads: the
    table comes out as the UTF-8 one, with a warning naming that row (it was refused with "'utf-8'
    codec can't decode", no row)."""
    t = np.arange(8000) * 0.5
    rows = [f"{x:.1f},9.81{i % 7},ok" for i, x in enumerate(t)]
    rows[5999] = rows[5999].replace(",ok", ",12\u00b0 turn")
    clean, latin = tmp_path / "clean.csv", tmp_path / "latin.csv"
    clean.write_text("time,f_z,remark\n" + "\n".join(r.replace("\u00b0", "") for r in rows) + "\n", encoding="utf-8")
    latin.write_bytes(("time,f_z,remark\n" + "\n".join(rows) + "\n").encode("cp1252"))
    assert latin.read_bytes().index(b"\xb0") > 1 << 16
    with pytest.warns(UserWarning, match=r"not UTF-8 \(a byte at row 6001"):
        got, got_rows = read_csv_table(latin, "latin.csv", ["time", "f_z"])
    want, want_rows = read_csv_table(clean, "clean.csv", ["time", "f_z"])
    pd.testing.assert_frame_equal(got, want)
    np.testing.assert_array_equal(got_rows, want_rows)
