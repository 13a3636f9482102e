"""What converters write (Excel, scripts, other packages): read as SPEC's file where the file
leaves no doubt, refused naming file, row and column where it does (round 4 of the input review).

Every reading is compared with the same tables written as SPEC's CSV."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

from app.io.errors import InputError
from app.io.survey import read_survey
from app.io.tables import check_range, check_time_increasing, read_csv_table
from tests.io.test_io_survey import expect_error, make_tables, write_survey


def _read_quiet(root, overrides=None):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        s = read_survey(root, overrides)
    return s, [str(w.message) for w in caught]


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    lines, tabs = make_tables()
    root = write_survey(tmp_path_factory.mktemp("clean") / "s", lines, tabs)
    return root, lines, tabs, _read_quiet(root)[0]


def _same_tables(a, b):
    for f in a.flights:
        pd.testing.assert_frame_equal(a.flights[f].gravimeter, b.flights[f].gravimeter, check_exact=True)
        pd.testing.assert_frame_equal(a.flights[f].gnss, b.flights[f].gnss, check_exact=True)
    pd.testing.assert_frame_equal(a.lines, b.lines, check_exact=True)


def _rewrite(root, name, fn):
    p = root / "flights" / "F1" / name
    p.write_bytes(fn(p.read_text()))


def _semicolon_decimal_comma(text: str) -> bytes:
    return "\n".join(line.replace(",", ";").replace(".", ",") for line in text.split("\n")).encode()


@pytest.mark.parametrize("dialect", ["utf16", "semicolon_decimal_comma", "tab", "units_in_header", "crlf_bom"])
def test_dialects_read_as_the_spec_file(clean, tmp_path, dialect):
    """UTF-16 (Excel's "Unicode text"), semicolons with decimal commas (a European Excel), tabs,
    SPEC units written after the names, CRLF with a UTF-8 BOM: the same numbers as SPEC's CSV."""
    _, lines, tabs, ref = clean
    root = write_survey(tmp_path / "s", lines, tabs)
    fn = {"utf16": lambda t: t.encode("utf-16"),
          "semicolon_decimal_comma": _semicolon_decimal_comma,
          "tab": lambda t: t.replace(",", "\t").encode(),
          "units_in_header": lambda t: t.replace("time,", "Time [s],", 1).replace(",f_z,", ",f_z(m/s^2),", 1)
          .replace(",h,", ",h [m],", 1).replace(",vu,", ", VU (m/s) ,", 1).encode(),
          "crlf_bom": lambda t: ("\ufeff" + t.replace("\n", "\r\n")).encode()}[dialect]
    for name in ("gravimeter.csv", "gnss.csv"):
        _rewrite(root, name, fn)
    (root / "lines.csv").write_bytes(fn((root / "lines.csv").read_text()))
    _same_tables(ref, _read_quiet(root)[0])


def test_decimal_commas_and_points_in_one_file_refused(tmp_path):
    p = tmp_path / "g.csv"
    p.write_text("time;f_z\n1,0;9,81\n2,0;9.81\n")
    with pytest.raises(InputError) as ei:
        read_csv_table(p, "g.csv", ("time", "f_z"))
    assert ei.value.row == 3 and "'9.81'" in str(ei.value) and "decimal commas" in str(ei.value)


def test_a_unit_in_the_header_that_is_not_spec_is_refused(clean, tmp_path):
    _, lines, tabs, _ = clean
    root = write_survey(tmp_path / "s", lines, tabs)
    _rewrite(root, "gnss.csv", lambda t: t.replace(",h,", ",h [ft],", 1).encode())
    expect_error(root, "flights/F1/gnss.csv", 1, "h", match="'ft'")


@pytest.mark.parametrize("column,marker,sensor", [("vu", "-999.99", "gnss"), ("h", "-9999", "gnss"),
                                                  ("ve", "-999.99", "gnss"), ("f_z", "1e30", "gravimeter"),
                                                  ("f_z", "0", "gravimeter"), ("h", "0", "gnss")])
def test_no_data_markers_are_missing_values(clean, tmp_path, column, marker, sensor):
    """-999.99 in vu, ve (inside their ±1000 m/s range) and h were read as numbers: 1.7, 1.8 and
    0.2 mGal RMS on the sample survey, silent; f_z = 0 (a dropout) 580 mGal. A marker is a missing
    value: refused by default naming its row (the reader's warning said first), read like an
    empty cell when processing.max_nan_run allows."""
    _, lines, tabs, ref = clean
    root = write_survey(tmp_path / "s", lines, tabs)
    row = 1000
    path = root / "flights" / "F1" / f"{sensor}.csv"
    ls = path.read_text().split("\n")
    head = ls[0].split(",")
    cells = ls[row - 1].split(",")
    cells[head.index(column)] = marker
    ls[row - 1] = ",".join(cells)
    path.write_text("\n".join(ls))
    with pytest.warns(UserWarning, match=f"{column}: 1 × .*first at row {row}"):
        expect_error(root, f"flights/F1/{sensor}.csv", row, column, match="missing value")
    got, said = _read_quiet(root, {"max_nan_run": 1})
    a, b = getattr(ref.flights["F1"], sensor), getattr(got.flights["F1"], sensor)
    if column == "f_z":   # a hole of the record: the row is left out, the others as read
        pd.testing.assert_frame_equal(a.drop(index=row - 2).reset_index(drop=True), b, check_exact=True)
    else:
        t = a["time"].to_numpy()
        want = np.interp(t[row - 2], t[[row - 3, row - 1]], a[column].to_numpy()[[row - 3, row - 1]])
        assert b[column].iloc[row - 2] == pytest.approx(want, rel=1e-12)
        pd.testing.assert_frame_equal(a.drop(index=row - 2), b.drop(index=row - 2), check_exact=True)


def test_zeros_that_are_values_are_kept(tmp_path):
    """Exact zeros of vu, and of h among heights close to 0 (a ship), are numbers."""
    p = tmp_path / "gnss.csv"
    pd.DataFrame({"time": [0.0, 0.1, 0.2, 0.3], "lat": 62.0, "lon": 158.0, "h": [0.4, 0.0, -0.3, 0.1],
                  "vu": [0.0, 0.0, 0.1, 0.0]}).to_csv(p, index=False)
    df, rows = read_csv_table(p, "gnss.csv", ("time", "lat", "lon", "h", "vu"))
    from app.io.tables import mark_no_data

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = mark_no_data(df.copy(), rows, "gnss.csv", ("time", "lat", "lon", "h", "vu"))
    pd.testing.assert_frame_equal(out, df, check_exact=True)


def test_gnss_dropout_row_of_zeros_is_missing(clean, tmp_path):
    """A logger's dropout written as 0 in lat, lon, h and vu (read before as a jump to 0°, 0°: a
    300 000 km² grid was asked for)."""
    _, lines, tabs, _ = clean
    gnss = tabs["F1"][1].copy()
    gnss.loc[999:1001, ["lat", "lon", "h", "vu", "ve"]] = 0.0
    root = write_survey(tmp_path / "s", lines, {"F1": (tabs["F1"][0], gnss)})
    with pytest.warns(UserWarning, match="vu: 3 × 0 \\(a dropout\\)"):
        expect_error(root, "flights/F1/gnss.csv", 1001, "lat", match="3 consecutive missing values")


@pytest.mark.parametrize("shift_days,scale", [(16100, "GPS seconds since 1980"), (19757, "Unix time")])
def test_files_on_two_time_scales_are_named(clean, tmp_path, shift_days, scale):
    """GNSS time in GPS seconds since 1980 or Unix time beside a gravimeter in seconds of week:
    refused naming the GNSS file (the lines.csv windows lie in the gravimeter's) and the days."""
    _, lines, tabs, _ = clean
    gnss = tabs["F1"][1].copy()
    gnss["time"] = gnss["time"] + 86400.0 * shift_days
    root = write_survey(tmp_path / "s", lines, {"F1": (tabs["F1"][0], gnss)})
    expect_error(root, "flights/F1/gnss.csv", 2, "time", match=f"differ by {shift_days} whole days")
    with pytest.raises(InputError, match=scale):
        read_survey(root)


def test_rounded_stamps_say_so():
    t = np.round(np.arange(200) / 18.24, 1)
    with pytest.raises(InputError, match="too few decimals") as ei:
        check_time_increasing(t, np.arange(2, 202), "g.csv")
    assert ei.value.row == 2 + int(np.flatnonzero(np.diff(t) == 0)[0]) + 1
    with pytest.raises(InputError) as ei:   # one duplicated stamp is just that
        check_time_increasing(np.array([0.0, 0.1, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]), np.arange(2, 10), "g.csv")
    assert "decimals" not in str(ei.value)


@pytest.mark.parametrize("cell,hint", [('"11,923.5"', "thousands separator"), ('"11923,5"', "decimal comma"),
                                       ("time", "header line inside the data"),
                                       ("2024-02-04T03:18:43", "date and time")])
def test_converter_cells_get_a_hint(tmp_path, cell, hint):
    p = tmp_path / "g.csv"
    p.write_text(f"time,f_z\n1.0,9.81\n{cell},9.81\n3.0,9.81\n")
    with pytest.raises(InputError, match=hint) as ei:
        read_csv_table(p, "g.csv", ("time", "f_z"))
    assert (ei.value.row, ei.value.column) == (3, "time")


def test_ddmm_latitude_says_so():
    df = pd.DataFrame({"lat": [65.5, 6530.19652]})
    with pytest.raises(InputError, match="DDMM") as ei:
        check_range(df, "lat", -90.0, 90.0, np.array([2, 3]), "gnss.csv", "latitude")
    assert ei.value.row == 3 and "6530.19652 is outside" in str(ei.value)
    assert "swapped" not in str(ei.value)     # no lon column to tell


def test_swapped_lat_lon_says_so():
    """A GNSS file east of 90° with lat and lon swapped: the latitude is out of range and
    the longitude column within ±90° everywhere — the error says they may be swapped; a
    latitude out of range with longitudes beyond ±90° does not."""
    df = pd.DataFrame({"lat": [158.91, 158.92], "lon": [65.50, 65.51]})
    with pytest.raises(InputError, match="swapped") as ei:
        check_range(df, "lat", -90.0, 90.0, np.array([2, 3]), "gnss.csv", "latitude")
    assert (ei.value.row, ei.value.column) == (2, "lat")
    df = pd.DataFrame({"lat": [65.5, 158.92], "lon": [158.9, 158.91]})
    with pytest.raises(InputError) as ei:
        check_range(df, "lat", -90.0, 90.0, np.array([2, 3]), "gnss.csv", "latitude")
    assert "swapped" not in str(ei.value) and ei.value.row == 3


def test_a_clock_set_back_in_flight_says_so():
    """An 18.24 Hz record whose logger clock was set back 0.3 s at sample 120: the times step back
    and go on at the record's step.  The error names the row and says how much to add to it and
    every later row (0.3 s less one step back, plus that step: the shift that joins the two
    parts); a record shuffled (a single row out of place) gets no such advice."""
    step = 1 / 18.24
    t = np.arange(300) * step
    t[120:] -= 0.3
    with pytest.raises(InputError, match="clock looks set back by about 0.300 s") as ei:
        check_time_increasing(t, np.arange(2, 302), "g.csv")
    assert ei.value.row == 2 + 120 and "add 0.300 s to this row's time and every later one" in str(ei.value)
    t = np.arange(300) * step
    t[150], t[151] = t[151], t[150]
    with pytest.raises(InputError) as ei:
        check_time_increasing(t, np.arange(2, 302), "g.csv")
    assert "set back" not in str(ei.value)
