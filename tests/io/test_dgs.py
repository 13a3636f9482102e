"""DGS AT1A/AT1M records: small hand-written files in the logger's column order."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.io.dgs import NOMINAL_OFFSET_MGAL, read_dgs, sniff_dat
from app.io.errors import InputError
from app.io.survey import read_survey

# the record of DGP's test data: gravity, long, cross, beam, temp, status, pressure, Etemp, week, sow
EXAMPLE = "10061.171360,-0.026226,-0.094891,-0.093803,62.253987,21061,39.690004,52.263138,1959,219697.800"
SYNCED = 21061            # bit 2 (GPS sync) set
UNSYNCED = SYNCED - 4     # bit 2 clear
WEEK = 1959
HZ = 10.0


def records(n, sow0=219697.8, gravity0=10061.17136, week=WEEK, status=SYNCED, gps=True, counter=False):
    """(text lines, gravity mGal, sow) of n records at 10 Hz."""
    k = np.arange(n)
    sow = np.round(sow0 + k / HZ, 1)
    grav = np.round(gravity0 + 0.5 * np.sin(k / 13.0), 6)
    out = []
    for i in range(n):
        f = [f"{grav[i]:.6f}", "-0.026226", "-0.094891", "-0.093803", "62.253987", str(status), "39.690004",
             "52.263138"]
        if gps:
            f += [str(week), f"{sow[i]:.3f}"]
        if counter:
            f += [str(i)]
        out.append(",".join(f))
    return out, grav, sow


def write(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def test_example_record_and_time(tmp_path):
    p = write(tmp_path / "a.dat", [EXAMPLE, EXAMPLE.replace("219697.800", "219697.900")])
    with pytest.warns(UserWarning, match="nominal"):
        df = read_dgs(p)
    assert df["time"].tolist() == [219697.8, 219697.9]
    assert df["gravity_mgal"].iloc[0] == 10061.17136
    assert df["f_z"].iloc[0] == pytest.approx((10061.17136 + 978000.0) * 1e-5, rel=1e-15)
    assert df["long_accel"].iloc[0] == -0.026226 and df["cross_accel"].iloc[0] == -0.094891
    assert df["status"].iloc[0] == 21061 and df["gps_week"].iloc[0] == 1959
    assert df.attrs["reading_offset_source"] == "nominal" and df.attrs["reading_offset_mgal"] == NOMINAL_OFFSET_MGAL
    assert df["source_row"].tolist() == [1, 2]


def test_offsets_declared_absolute_and_counter_field(tmp_path):
    lines, grav, _ = records(20, counter=True)
    p = write(tmp_path / "a.dat", lines)
    df = read_dgs(p, reading_offset_mgal=971234.5)
    np.testing.assert_allclose(df["f_z"], (grav + 971234.5) * 1e-5, rtol=1e-15)
    assert df.attrs["reading_offset_source"] == "declared"
    lines, grav, _ = records(20, gravity0=981234.25)  # a logger that already adds g0: absolute-looking
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        df = read_dgs(write(tmp_path / "b.dat", lines))
    np.testing.assert_allclose(df["f_z"], grav * 1e-5, rtol=1e-15)
    assert df.attrs["reading_offset_source"] == "absolute"


def test_week_rollover_and_time_offset(tmp_path):
    a, _, _ = records(3, sow0=604799.7)
    b, _, _ = records(3, sow0=0.0, week=WEEK + 1)
    df = read_dgs(write(tmp_path / "a.dat", a + b), reading_offset_mgal=0.0, time_offset_s=-4 * 86400.0)
    np.testing.assert_allclose(df["time"], np.array([604799.7, 604799.8, 604799.9, 604800.0, 604800.1, 604800.2])
                               - 4 * 86400.0, rtol=0, atol=1e-9)


def test_unsynchronised_records_dropped_with_warning(tmp_path):
    a, _, _ = records(5, status=UNSYNCED, sow0=100.0)
    b, grav, sow = records(10, sow0=100.5)
    with pytest.warns(UserWarning, match="5 record"):
        df = read_dgs(write(tmp_path / "a.dat", a + b), reading_offset_mgal=0.0)
    assert df.attrs["unsynced_records"] == 5
    np.testing.assert_array_equal(df["time"], sow)
    assert df["source_row"].tolist() == list(range(6, 16))
    with pytest.raises(InputError) as ei:
        read_dgs(write(tmp_path / "b.dat", a), reading_offset_mgal=0.0)
    assert ei.value.column == "status" and ei.value.row == 1


def test_records_without_gps_time(tmp_path):
    lines, grav, _ = records(30, gps=False)
    p = write(tmp_path / "a.dat", ["gravity,long,cross,beam,temp,status,pressure,Etemp"] + lines)  # a line of names
    with pytest.raises(InputError) as ei:
        read_dgs(p, time_offset_s=None, rate_hz=HZ, reading_offset_mgal=0.0)
    assert "rate_hz" in str(ei.value) and "time_offset_s" in str(ei.value)
    df = read_dgs(p, time_offset_s=5000.0, rate_hz=HZ, reading_offset_mgal=0.0)
    np.testing.assert_allclose(df["time"], 5000.0 + np.arange(30) / HZ, rtol=0, atol=1e-12)
    assert df["source_row"].iloc[0] == 2 and "gps_sow" not in df


@pytest.mark.parametrize("gps", [True, False])
def test_missing_gravity_left_as_a_hole(tmp_path, gps):
    """A missing gravity value (with ``max_nan_run`` tolerating it) is a hole of the record, not a
    value to interpolate: its record is dropped with a warning naming the row, and every other
    record keeps its own time — from its GPS stamp, or from the record count without one."""
    lines, grav, sow = records(30, gps=gps)
    f = lines[10].split(",")
    f[0] = ""
    lines[10] = ",".join(f)
    p = write(tmp_path / "a.dat", lines)
    kw = {} if gps else {"time_offset_s": 5000.0, "rate_hz": HZ}
    with pytest.warns(UserWarning, match=r"1 missing gravity value\(s\) left as holes of the record \(rows 11\)"):
        df = read_dgs(p, reading_offset_mgal=0.0, max_nan_run=1, **kw)
    keep = np.arange(30) != 10
    t = sow if gps else 5000.0 + np.arange(30) / HZ
    np.testing.assert_allclose(df["time"], t[keep], rtol=0, atol=1e-9)
    np.testing.assert_allclose(df["gravity_mgal"], grav[keep], rtol=0, atol=1e-12)
    assert 11 not in df["source_row"].tolist() and len(df) == 29


@pytest.mark.parametrize("edit, row, column, match", [
    (lambda ls: ls.__setitem__(6, ls[6].replace("62.253987", "62.25x")), 7, "temp", "'62.25x'"),
    (lambda ls: ls.__setitem__(3, ls[3] + ",1"), 4, None, "11 fields"),
    (lambda ls: ls.__setitem__(8, ls[8].replace("219698.600", "219698.000")), 9, "gps_sow", "backwards"),
    (lambda ls: ls.__setitem__(2, ls[2].replace(",21061,", ",21061.5,")), 3, "status", "integer"),
    (lambda ls: ls.__setitem__(4, ls[4].replace("-0.026226", "")), 5, "long_accel", "missing"),
])
def test_errors_name_row_and_column(tmp_path, edit, row, column, match):
    lines, _, _ = records(12)
    edit(lines)
    with pytest.raises(InputError) as ei:
        read_dgs(write(tmp_path / "a.dat", lines), reading_offset_mgal=0.0)
    e = ei.value
    assert (e.row, e.column) == (row, column), str(e)
    assert match in str(e)


def test_raw_serial_strings_refused(tmp_path):
    p = write(tmp_path / "raw.dat", ["$UW,81242,-1948,557,4807924,307,872,204,6978,7541,-70,305,266,4903912,"
                                     "0.000000,0.000000,0.0000,0.0000,00000000001646"] * 3)
    assert sniff_dat(p) == "dgs_raw"
    with pytest.raises(InputError, match="raw DGS"):
        read_dgs(p)


def test_sniffing_tells_dgs_from_g_files(tmp_path):
    from tests.io.test_gfile import make_messages, write_g

    lines, _, _ = records(5)
    assert sniff_dat(write(tmp_path / "G0001.dat", lines)) == "dgs"  # a G-file-like name, DGS content
    msgs, _ = make_messages(10, t0_sod=3600.0)
    write_g(tmp_path / "flight.dat", msgs)
    assert sniff_dat(tmp_path / "flight.dat") == "gfile"
    write_g(tmp_path / "g2.dat", msgs, sep=",")
    assert sniff_dat(tmp_path / "g2.dat") == "gfile"
    assert sniff_dat(write(tmp_path / "notes.dat", ["flight notes", "engine start 10:02"])) is None


def _dgs_survey(root: Path, gnss_epoch: bool, dat_name="AT1A_0042.dat", toml='[survey]\nname = "d"\n'):
    """A flight of DGS records (GPS seconds of week) and GNSS at 10 Hz, on GPS seconds of week or
    (gnss_epoch) GPS seconds since 1980-01-06."""
    d = root / "flights" / "F1"
    d.mkdir(parents=True)
    lines, grav, sow = records(3000)
    write(d / dat_name, lines)
    shift = WEEK * 604800.0 if gnss_epoch else 0.0
    tn = sow + shift
    pd.DataFrame({"time": tn, "lat": 10.0, "lon": 20.0 + 1e-5 * np.arange(tn.size), "h": 1000.0, "vu": 0.0}).to_csv(
        d / "gnss.csv", index=False)
    pd.DataFrame([{"line": "L1", "flight": "F1", "t_start": tn[100], "t_end": tn[2900], "kind": "main"}]).to_csv(
        root / "lines.csv", index=False)
    (root / "survey.toml").write_text(toml)
    return grav, sow, shift


@pytest.mark.parametrize("gnss_epoch", [False, True])
def test_dgs_flight_in_survey(tmp_path, gnss_epoch):
    grav, sow, shift = _dgs_survey(tmp_path / "s", gnss_epoch,
                                   toml='[survey]\nname = "d"\n[gravimeter]\nreading_offset_mgal = 970000.0\n')
    s = read_survey(tmp_path / "s")
    fl = s.flights["F1"]
    assert fl.gravimeter_path.name == "AT1A_0042.dat"
    assert list(fl.gravimeter.columns) == ["time", "f_z"]
    np.testing.assert_allclose(fl.gravimeter["time"], sow + shift, rtol=0, atol=1e-6)  # whole days inferred
    np.testing.assert_allclose(fl.gravimeter["f_z"], (grav + 970000.0) * 1e-5, rtol=1e-15)


def test_dgs_in_a_g_named_file_and_declared_offset(tmp_path):
    grav, sow, _ = _dgs_survey(tmp_path / "s", False, dat_name="G0001.dat",
                               toml='[gravimeter]\ntime_offset_s = 0.0\nrate_hz = 10.0\n')
    with pytest.warns(UserWarning, match="nominal"):
        s = read_survey(tmp_path / "s")
    np.testing.assert_array_equal(s.flights["F1"].gravimeter["time"], sow)
    np.testing.assert_allclose(s.flights["F1"].gravimeter["f_z"], (grav + 978000.0) * 1e-5, rtol=1e-15)


def test_unrecognised_dat_is_named_in_the_error(tmp_path):
    d = tmp_path / "s" / "flights" / "F1"
    d.mkdir(parents=True)
    write(d / "meter.dat", ["something else", "1 2 3"])
    pd.DataFrame({"time": [0.0, 0.1], "lat": 1.0, "lon": 1.0, "h": 1.0, "vu": 0.0}).to_csv(d / "gnss.csv", index=False)
    (tmp_path / "s" / "lines.csv").write_text("line,flight,t_start,t_end,kind\nL,F1,0,0.1,main\n")
    (tmp_path / "s" / "survey.toml").write_text("")
    with pytest.raises(InputError) as ei:
        read_survey(tmp_path / "s")
    assert ei.value.file == "flights/F1/gravimeter.csv" and "meter.dat" in str(ei.value)


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # constant vu: no lag correlation
def test_inspect_works_on_dgs_and_xyz_surveys(tmp_path):
    from app.pipeline.inspect import inspect_survey
    from tests.io.test_xyz import make_xyz_survey

    _dgs_survey(tmp_path / "d", True, toml='[gravimeter]\nreading_offset_mgal = 970000.0\n')
    q = inspect_survey(tmp_path / "d")
    assert q["level"].tolist() == ["flight", "line"]
    assert q.loc[0, "gravimeter_rate_hz"] == pytest.approx(10.0) and q.loc[0, "gnss_rate_hz"] == pytest.approx(10.0)
    root, *_ = make_xyz_survey(tmp_path / "x")
    q = inspect_survey(root)
    assert q.loc[q["level"] == "line", "line"].tolist() == ["1001", "2001"]
    assert {"lag_s", "lag_corr", "length_km"} <= set(q.columns)


def test_records_without_gps_time_in_a_survey_need_rate_and_offset(tmp_path):
    d = tmp_path / "s" / "flights" / "F1"
    d.mkdir(parents=True)
    lines, grav, _ = records(600, gps=False)
    write(d / "meter.dat", lines)
    tn = 7000.0 + np.arange(600) / HZ
    pd.DataFrame({"time": tn, "lat": 1.0, "lon": 1.0 + 1e-5 * np.arange(600), "h": 1.0, "vu": 0.0}).to_csv(
        d / "gnss.csv", index=False)
    (tmp_path / "s" / "lines.csv").write_text("line,flight,t_start,t_end,kind\nL,F1,7010,7050,main\n")
    (tmp_path / "s" / "survey.toml").write_text("[gravimeter]\nreading_offset_mgal = 970000.0\n")
    with pytest.raises(InputError) as ei:
        read_survey(tmp_path / "s")
    assert ei.value.file == "flights/F1/meter.dat" and "gravimeter.rate_hz" in str(ei.value)
    (tmp_path / "s" / "survey.toml").write_text("[gravimeter]\nreading_offset_mgal = 970000.0\nrate_hz = 10.0\n"
                                                "time_offset_s = 7000.0\n")
    g = read_survey(tmp_path / "s").flights["F1"].gravimeter
    np.testing.assert_allclose(g["time"], tn, rtol=0, atol=1e-9)


def test_last_record_cut_short_is_dropped_with_a_warning(tmp_path):
    lines, grav, sow = records(30)
    lines[-1] = lines[-1][: len(lines[-1]) // 2]          # the logger stopped mid-record
    p = write(tmp_path / "a.dat", lines)
    with pytest.warns(UserWarning, match=r"the last record \(row 30\) has 5 of the 10 fields: cut short"):
        df = read_dgs(p, reading_offset_mgal=978000.0)
    assert df["time"].tolist() == sow[:29].tolist()
    np.testing.assert_allclose(df["gravity_mgal"], grav[:29], rtol=0, atol=0)


def test_a_short_record_inside_the_file_is_still_an_error(tmp_path):
    lines, _, _ = records(30)
    lines[10] = lines[10][: len(lines[10]) // 2]
    with pytest.raises(InputError, match="this record has 5 fields, the first"):
        read_dgs(write(tmp_path / "a.dat", lines))


def test_records_with_extra_fields_are_refused_saying_how_many(tmp_path):
    root = tmp_path / "s"
    _dgs_survey(root, gnss_epoch=False)
    p = root / "flights" / "F1" / "AT1A_0042.dat"
    p.write_text("".join(s + ",0.5,1\n" for s in p.read_text().splitlines()))   # a newer logger's two more fields
    with pytest.raises(InputError) as ei:
        read_survey(root)
    assert ei.value.file == "flights/F1/gravimeter.csv"
    assert "AT1A_0042.dat (comma-separated numeric records of 12 fields; DGS AT1A/AT1M records have 8" in str(ei.value)
