"""read_survey: a valid tiny survey built here, then one test per bad-input case."""

from __future__ import annotations

import gzip
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.io.errors import InputError
from app.io.survey import path_length_km, read_survey, survey_summary

T0 = 4 * 86400.0  # GPS seconds of week, Thursday 00:00
GRAV_HZ = 18.24
GNSS_HZ = 10.0
SPEED_MS = 100.0
LAT0, LON0 = 62.0, 158.0

TOML = """\
[survey]
name = "tiny"
normal_gravity = "WGS84"

[gravimeter]
model = "GT-1A"
tau_s = 2.0
scale = 1.0

[processing]
max_gap_s = 1.0
"""


def make_tables(flights=("F1",), duration_s=600.0, seed=0):
    """Known-truth tables: a flight flying east at 100 m/s, gravimeter at 18.24 Hz, GNSS at 10 Hz."""
    rng = np.random.default_rng(seed)
    tabs = {}
    lines = []
    for k, f in enumerate(flights):
        t0 = T0 + 1000.0 * k
        n_g = int(duration_s * GRAV_HZ)
        tg = np.round(t0 + np.arange(n_g) / GRAV_HZ, 4)
        grav = pd.DataFrame({"time": tg, "f_z": 9.81 + 1e-3 * rng.standard_normal(n_g),
                             "f_x": 1e-3 * rng.standard_normal(n_g), "f_y": 1e-3 * rng.standard_normal(n_g),
                             "temperature_c": 40.0})
        n_n = int(duration_s * GNSS_HZ)
        tn = np.round(t0 + np.arange(n_n) / GNSS_HZ, 2)
        # east along the parallel: dλ = v dt / ((R_N + h) cos φ); the exact length is checked with pyproj later
        lon = LON0 + np.rad2deg(SPEED_MS * (tn - t0) / (6_394_000.0 * np.cos(np.deg2rad(LAT0))))
        gnss = pd.DataFrame({"time": tn, "lat": LAT0, "lon": lon, "h": 3000.0 + 0.0 * tn, "vu": 0.01 * rng.standard_normal(n_n),
                             "ve": SPEED_MS, "vn": 0.0, "n_sats": 9})
        tabs[f] = (grav, gnss)
        lines += [
            {"line": f"0{k}01", "flight": f, "t_start": t0 + 20.0, "t_end": t0 + 280.0, "kind": "main", "track": ""},
            {"line": f"0{k}02", "flight": f, "t_start": t0 + 300.0, "t_end": t0 + 450.0, "kind": "tie", "track": ""},
            {"line": f"0{k}03", "flight": f, "t_start": t0 + 460.0, "t_end": t0 + 590.0, "kind": "repeat", "track": "A"},
        ]
    return pd.DataFrame(lines), tabs


def write_survey(root: Path, lines: pd.DataFrame, tabs: dict, toml: str = TOML, gz: bool = False) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "survey.toml").write_text(toml)
    lines.to_csv(root / "lines.csv", index=False)
    for f, (grav, gnss) in tabs.items():
        d = root / "flights" / f
        d.mkdir(parents=True, exist_ok=True)
        ext = ".csv.gz" if gz else ".csv"
        if grav is not None:
            grav.to_csv(d / f"gravimeter{ext}", index=False)
        gnss.to_csv(d / f"gnss{ext}", index=False)
    return root


@pytest.fixture
def survey_dir(tmp_path):
    lines, tabs = make_tables()
    return write_survey(tmp_path / "s", lines, tabs), lines, tabs


def edit_cell(path: Path, row: int, column: str, text: str) -> None:
    """Replace one cell of a CSV as a text editor would (row = file line number, header = 1)."""
    ls = path.read_text().splitlines()
    header = ls[0].split(",")
    cells = ls[row - 1].split(",")
    cells[header.index(column)] = text
    ls[row - 1] = ",".join(cells)
    path.write_text("\n".join(ls) + "\n")


def expect_error(root, file, row, column, overrides=None, match=None):
    with pytest.raises(InputError) as ei:
        read_survey(root, overrides)
    err = ei.value
    assert (err.file, err.row, err.column) == (file, row, column), str(err)
    s = str(err)
    assert file in s
    if row is not None:
        assert f"row {row}" in s
    if column is not None:
        assert f"'{column}'" in s
    if match is not None:
        assert match in s, s
    return err


# ------------------------------------------------------------------ valid input


def test_valid_survey_roundtrip(survey_dir):
    root, lines, tabs = survey_dir
    s = read_survey(root)
    assert s.root == root
    assert s.config.survey.name == "tiny"
    assert list(s.lines.columns) == ["line", "flight", "t_start", "t_end", "kind", "track"]
    assert s.lines["line"].tolist() == ["0001", "0002", "0003"]  # read as str, leading zeros kept
    assert s.lines["track"].tolist() == [None, None, "A"]
    assert s.lines["kind"].tolist() == ["main", "tie", "repeat"]
    fl = s.flights["F1"]
    grav, gnss = tabs["F1"]
    assert list(fl.gravimeter.columns) == ["time", "f_z", "f_x", "f_y"]  # extra column ignored
    assert list(fl.gnss.columns) == ["time", "lat", "lon", "h", "vu", "ve", "vn"]
    assert fl.gravimeter["time"].dtype == np.float64
    np.testing.assert_array_equal(fl.gravimeter["time"].to_numpy(), grav["time"].to_numpy())
    np.testing.assert_allclose(fl.gravimeter["f_z"].to_numpy(), grav["f_z"].to_numpy(), rtol=0, atol=1e-15)
    np.testing.assert_allclose(fl.gnss["lon"].to_numpy(), gnss["lon"].to_numpy(), rtol=0, atol=1e-12)
    assert fl.gravimeter_path == root / "flights/F1/gravimeter.csv"
    assert fl.gnss_path == root / "flights/F1/gnss.csv"


def test_byte_order_marks_accepted(survey_dir):
    """Windows editors (Notepad) save UTF-8 with a byte-order mark: survey.toml, lines.csv and
    the tables read as without it (the TOML parser refused the mark at line 1, column 1)."""
    root, lines, tabs = survey_dir
    ref = read_survey(root)
    for rel in ("survey.toml", "lines.csv", "flights/F1/gnss.csv", "flights/F1/gravimeter.csv"):
        path = root / rel
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    s = read_survey(root)
    assert s.config == ref.config
    pd.testing.assert_frame_equal(s.lines, ref.lines)
    pd.testing.assert_frame_equal(s.flights["F1"].gnss, ref.flights["F1"].gnss)
    pd.testing.assert_frame_equal(s.flights["F1"].gravimeter, ref.flights["F1"].gravimeter)


def test_gz_accepted(tmp_path):
    lines, tabs = make_tables()
    root = write_survey(tmp_path / "s", lines, tabs, gz=True)
    s = read_survey(root)
    assert s.flights["F1"].gnss_path.name == "gnss.csv.gz"
    assert s.flights["F1"].gravimeter_path.name == "gravimeter.csv.gz"
    np.testing.assert_array_equal(s.flights["F1"].gnss["time"].to_numpy(), tabs["F1"][1]["time"].to_numpy())


def test_optional_columns_absent_and_blank_track(tmp_path):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    tabs["F1"] = (grav[["time", "f_z"]], gnss[["time", "lat", "lon", "h", "vu"]])
    root = write_survey(tmp_path / "s", lines.drop(columns="track"), tabs)
    s = read_survey(root)
    assert list(s.flights["F1"].gravimeter.columns) == ["time", "f_z"]
    assert list(s.flights["F1"].gnss.columns) == ["time", "lat", "lon", "h", "vu"]
    assert s.lines["track"].tolist() == [None, None, None]


def test_overrides_applied(survey_dir):
    root, *_ = survey_dir
    s = read_survey(root, {"max_gap_s": 2.5, "n_q": 3})
    assert s.config.processing.max_gap_s == 2.5
    assert s.config.processing.n_q == 3
    assert s.config.gravimeter.tau_s == 2.0  # untouched
    with pytest.raises(InputError) as ei:
        read_survey(root, {"max_gap_s": -1})
    assert ei.value.file == "overrides" and ei.value.column == "processing.max_gap_s"
    with pytest.raises(InputError) as ei:
        read_survey(root, {"no_such_param": 1})
    assert ei.value.column == "processing.no_such_param"


def test_override_relaxes_gap(tmp_path):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    gnss = gnss.drop(index=range(1000, 1015)).reset_index(drop=True)  # 1.6 s hole inside line 0001
    tabs["F1"] = (grav, gnss)
    root = write_survey(tmp_path / "s", lines, tabs)
    err = expect_error(root, "flights/F1/gnss.csv", 1002, "time", match="gap of 1.600 s")
    assert "split the line at the gap in lines.csv" in str(err) and "processing.max_gap_s" in str(err)
    s = read_survey(root, {"max_gap_s": 2.0})
    assert len(s.flights["F1"].gnss) == len(gnss)


def test_bad_survey_toml_names_key_and_row(survey_dir):
    root, *_ = survey_dir
    (root / "survey.toml").write_text(TOML.replace("tau_s = 2.0", "tau_s = -3"))
    expect_error(root, "survey.toml", 7, "gravimeter.tau_s", match="-3")
    (root / "survey.toml").write_text(TOML.replace("scale = 1.0", "scale = 1.0\ncolour = 'red'"))
    expect_error(root, "survey.toml", 9, "gravimeter.colour", match="unknown setting")
    (root / "survey.toml").write_text(TOML.replace('name = "tiny"', 'name = tiny'))
    err = expect_error(root, "survey.toml", 2, None)
    assert "TOML" in str(err)


# ------------------------------------------------------------------ data files


def test_missing_required_column(survey_dir):
    root, lines, tabs = survey_dir
    tabs["F1"][1].drop(columns="h").to_csv(root / "flights/F1/gnss.csv", index=False)
    expect_error(root, "flights/F1/gnss.csv", 1, "h", match="missing")


def test_missing_column_in_lines(survey_dir):
    root, lines, tabs = survey_dir
    lines.drop(columns="kind").to_csv(root / "lines.csv", index=False)
    expect_error(root, "lines.csv", 1, "kind")


def test_non_numeric_cell(survey_dir):
    root, *_ = survey_dir
    edit_cell(root / "flights/F1/gravimeter.csv", 57, "f_z", "9.8x1")
    expect_error(root, "flights/F1/gravimeter.csv", 57, "f_z", match="'9.8x1'")


def test_non_numeric_cell_gz(tmp_path):
    lines, tabs = make_tables()
    root = write_survey(tmp_path / "s", lines, tabs, gz=True)
    p = root / "flights/F1/gnss.csv.gz"
    text = gzip.decompress(p.read_bytes()).decode().splitlines()
    cells = text[99].split(",")
    cells[3] = "abc"  # h
    text[99] = ",".join(cells)
    p.write_bytes(gzip.compress(("\n".join(text) + "\n").encode()))
    expect_error(root, "flights/F1/gnss.csv.gz", 100, "h", match="'abc'")


def test_non_numeric_time_in_lines(survey_dir):
    root, lines, _ = survey_dir
    edit_cell(root / "lines.csv", 3, "t_start", "noon")
    expect_error(root, "lines.csv", 3, "t_start", match="'noon'")


def test_nan_default_is_error(survey_dir):
    root, *_ = survey_dir
    edit_cell(root / "flights/F1/gnss.csv", 40, "vu", "")
    expect_error(root, "flights/F1/gnss.csv", 40, "vu", match="missing")


def test_sigma_v_with_missing_cells_does_not_refuse_the_survey(tmp_path):
    """sigma_v (optional) is not used by the processing: a receiver that leaves it empty on some
    epochs (no solution quality there) refused the whole survey as 'missing value'.  The column
    is dropped with a note naming its first empty row; the data are read."""
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    gnss = gnss.assign(sigma_v=0.02)
    gnss.loc[100:105, "sigma_v"] = np.nan   # rows 102-107
    tabs["F1"] = (grav, gnss)
    root = write_survey(tmp_path / "s", lines, tabs)
    with pytest.warns(UserWarning, match="sigma_v"):
        s = read_survey(root)
    assert "sigma_v" not in s.flights["F1"].gnss
    assert [n for n in s.notes if "flights/F1/gnss.csv" in n and "row 102" in n and "sigma_v" in n], s.notes
    edit_cell(root / "flights/F1/gnss.csv", 40, "vu", "")   # a column the processing uses: still an error
    expect_error(root, "flights/F1/gnss.csv", 40, "vu", match="missing")


def test_nan_runs_interpolated_or_rejected(tmp_path):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    truth = gnss["h"].to_numpy().copy()
    gnss = gnss.copy()
    gnss["h"] = 3000.0 + 0.5 * (gnss["time"] - T0)  # linear: interpolation must restore it exactly
    truth = gnss["h"].to_numpy().copy()
    gnss.loc[200:202, "h"] = np.nan  # run of 3, rows 202-204
    tabs["F1"] = (grav, gnss)
    root = write_survey(tmp_path / "s", lines, tabs)
    s = read_survey(root, {"max_nan_run": 3})
    np.testing.assert_allclose(s.flights["F1"].gnss["h"].to_numpy(), truth, rtol=0, atol=1e-9)
    err = expect_error(root, "flights/F1/gnss.csv", 202, "h", overrides={"max_nan_run": 2})
    assert "3 consecutive missing values" in str(err)


def test_missing_f_z_left_as_a_hole_not_interpolated(tmp_path):
    """A missing f_z is a hole in the record, not a value to draw a line through: a linear fill
    misses the aircraft's acceleration at that sample (the GNSS still sees it), which on a
    turbulent 2 Hz test line was 100+ mGal of error along the line.  Its rows are dropped with a
    warning naming them; every other value is the file's; a hole of ``max_nan_run`` samples is
    allowed inside a line even where it is longer than ``max_gap_s``."""
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    grav = grav.copy()
    grav.loc[1000:1002, "f_z"] = np.nan          # rows 1002-1004, inside line 0001 (3/18.24 s)
    tabs["F1"] = (grav, gnss)
    root = write_survey(tmp_path / "s", lines, tabs)
    with pytest.warns(UserWarning, match=r"3 missing value\(s\) of f_z left as holes of the record \(rows 1002, 1003, 1004\)"):
        s = read_survey(root, {"max_nan_run": 3, "max_gap_s": 0.1})
    got = s.flights["F1"].gravimeter
    keep = np.ones(len(grav), bool)
    keep[1000:1003] = False
    np.testing.assert_array_equal(got["time"].to_numpy(), grav["time"].to_numpy()[keep])
    np.testing.assert_allclose(got["f_z"].to_numpy(), grav["f_z"].to_numpy()[keep], rtol=0, atol=1e-15)
    # the same hole from deleted rows is a gap longer than max_gap_s
    tabs["F1"] = (grav.dropna().reset_index(drop=True), gnss)
    root = write_survey(tmp_path / "t", lines, tabs)
    expect_error(root, "flights/F1/gravimeter.csv", 1002, "time", overrides={"max_gap_s": 0.1}, match="gap of")


def test_nan_in_time_interpolated(tmp_path):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    truth = grav["time"].to_numpy().copy()
    grav = grav.copy()
    grav.loc[500, "time"] = np.nan
    tabs["F1"] = (grav, gnss)
    root = write_survey(tmp_path / "s", lines, tabs)
    s = read_survey(root, {"max_nan_run": 1})
    assert abs(s.flights["F1"].gravimeter["time"].iloc[500] - truth[500]) < 1e-4


def test_time_duplicated(survey_dir):
    root, _, tabs = survey_dir
    g = tabs["F1"][0].copy()
    g.loc[300, "time"] = g.loc[299, "time"]
    g.to_csv(root / "flights/F1/gravimeter.csv", index=False)
    expect_error(root, "flights/F1/gravimeter.csv", 302, "time", match="repeated")


def test_time_backwards(survey_dir):
    root, _, tabs = survey_dir
    n = tabs["F1"][1].copy()
    n.loc[[700, 701], "time"] = n.loc[[701, 700], "time"].to_numpy()
    n.to_csv(root / "flights/F1/gnss.csv", index=False)
    expect_error(root, "flights/F1/gnss.csv", 703, "time", match="backwards")


@pytest.mark.parametrize("period_s, what", [(86400.0, "crosses midnight"), (604800.0, "week's end")])
def test_time_of_day_wrap_says_so(survey_dir, period_s, what):
    """Times in seconds of day (or GPS seconds of week) wrap when a flight crosses midnight:
    SPEC wants one monotonic scale, so it is an error, and the message says what happened
    and how to put it right; a shuffled record gets no such hint."""
    root, _, tabs = survey_dir
    n = tabs["F1"][1].copy()
    t = n["time"].to_numpy()
    n["time"] = np.where(np.arange(t.size) >= 700, t - t[699] - 0.05, t + period_s - t[699] - 0.15)
    n.to_csv(root / "flights/F1/gnss.csv", index=False, float_format="%.10g")
    err = expect_error(root, "flights/F1/gnss.csv", 702, "time", match="wrapped")
    assert what in str(err) and f"add {period_s:.0f} s" in str(err)
    # with the record's 10 minute gap at the wrap (the files held 86250 then 450)
    n["time"] = np.where(np.arange(t.size) >= 700, t - t[699] + 600.0, t + period_s - t[699] - 0.15)
    n.to_csv(root / "flights/F1/gnss.csv", index=False, float_format="%.10g")
    assert what in str(expect_error(root, "flights/F1/gnss.csv", 702, "time", match="wrapped"))
    n = tabs["F1"][1].copy()
    n.loc[[700, 701], "time"] = n.loc[[701, 700], "time"].to_numpy()
    n.to_csv(root / "flights/F1/gnss.csv", index=False)
    assert "wrapped" not in str(expect_error(root, "flights/F1/gnss.csv", 703, "time", match="backwards"))


def test_gap_inside_line_is_error_outside_is_fine(tmp_path):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    tg = grav["time"].to_numpy()
    # 3 s hole at t0+5..8 (before the first line: on the ground) — fine
    hole_out = (tg > T0 + 5) & (tg < T0 + 8)
    # 2 s hole inside line 0002 (t0+300..450)
    hole_in = (tg > T0 + 350) & (tg < T0 + 352)
    g_out = grav.loc[~hole_out].reset_index(drop=True)
    root = write_survey(tmp_path / "ok", lines, {"F1": (g_out, gnss)})
    read_survey(root)  # no error
    g_in = grav.loc[~(hole_out | hole_in)].reset_index(drop=True)
    root = write_survey(tmp_path / "bad", lines, {"F1": (g_in, gnss)})
    after = int(np.flatnonzero(g_in["time"].to_numpy() > T0 + 352)[0])
    err = expect_error(root, "flights/F1/gravimeter.csv", after + 2, "time", match="line 0002")
    assert "max_gap_s" in str(err)


def test_gap_straddling_line_start(tmp_path):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    tn = gnss["time"].to_numpy()
    hole = (tn > T0 + 19.0) & (tn < T0 + 21.0)  # line 0001 starts at t0+20, inside the hole
    g2 = gnss.loc[~hole].reset_index(drop=True)
    root = write_survey(tmp_path / "s", lines, {"F1": (grav, g2)})
    after = int(np.flatnonzero(g2["time"].to_numpy() >= T0 + 21.0)[0])
    expect_error(root, "flights/F1/gnss.csv", after + 2, "time")


def test_line_window_outside_data(survey_dir):
    root, lines, tabs = survey_dir
    l2 = lines.copy()
    l2.loc[0, "t_start"] = T0 - 50.0
    l2.to_csv(root / "lines.csv", index=False)
    expect_error(root, "lines.csv", 2, "t_start", match="outside")
    # GNSS ends earlier than the gravimeter: the end of the last line falls outside GNSS only
    lines.to_csv(root / "lines.csv", index=False)
    gnss = tabs["F1"][1]
    gnss.loc[gnss["time"] < T0 + 585].to_csv(root / "flights/F1/gnss.csv", index=False)
    err = expect_error(root, "lines.csv", 4, "t_end")
    assert "gnss.csv" in str(err)


def test_line_window_between_two_gnss_epochs(survey_dir):
    """A window holding no GNSS epoch (shorter than the epochs' spacing) is refused at reading
    with its row: before, it passed the checks and processing failed after the identification
    (IndexError in the filtering stage)."""
    root, lines, tabs = survey_dir
    t = tabs["F1"][1]["time"].to_numpy()
    l2 = lines.copy()
    l2.loc[1, "t_start"], l2.loc[1, "t_end"] = t[100] + 0.25 * (t[101] - t[100]), t[100] + 0.75 * (t[101] - t[100])
    l2.to_csv(root / "lines.csv", index=False)
    expect_error(root, "lines.csv", 3, "t_end", match="holds 0 epoch")
    # two epochs are a line (short lines are left out of the identification, not refused)
    l2.loc[1, "t_start"], l2.loc[1, "t_end"] = t[100], t[101]
    l2.to_csv(root / "lines.csv", index=False)
    read_survey(root)


def test_stuck_gravimeter_inside_a_line_is_said():
    """A gravimeter whose f_z stops changing in the air (stuck or saturated) is not a measurement:
    processing went on and the crossovers grew from 4 to 226 mGal with no word of the sensor.  A
    run of one value for ≥ 5 s inside a line is now a note naming the file's rows; a 2 s run, or
    one outside every line (parked), is not."""
    import warnings as w

    def notes_for(first: int, n: int):
        lines, tabs = make_tables()
        grav = tabs["F1"][0]
        grav.loc[first:first + n - 1, "f_z"] = 9.80123
        with w.catch_warnings():
            w.simplefilter("ignore")
            return [x for x in read_survey(write_survey(Path(tmp) / f"s{first}-{n}", lines, tabs)).notes
                    if "constant" in x]

    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        start = int(100 * GRAV_HZ)                       # 100 s after the flight starts: line 0001
        (note,) = notes_for(start, int(8 * GRAV_HZ))
        assert "flights/F1/gravimeter.csv" in note and "inside line 0001" in note, note
        assert f"rows {start + 2}–{start + int(8 * GRAV_HZ) + 1}" in note, note   # header = row 1
        assert notes_for(start, int(2 * GRAV_HZ)) == []
        assert notes_for(int(5 * GRAV_HZ), int(8 * GRAV_HZ)) == []   # before the first line (20 s)


def test_unknown_flight(survey_dir):
    root, lines, _ = survey_dir
    l2 = lines.copy()
    l2.loc[2, "flight"] = "F9"
    l2.to_csv(root / "lines.csv", index=False)
    expect_error(root, "lines.csv", 4, "flight", match="'F9'")


def test_t_end_not_after_t_start(survey_dir):
    root, lines, _ = survey_dir
    l2 = lines.copy()
    l2.loc[1, "t_end"] = l2.loc[1, "t_start"]
    l2.to_csv(root / "lines.csv", index=False)
    expect_error(root, "lines.csv", 3, "t_end")


def test_t_end_before_t_start_across_midnight_says_so(survey_dir):
    root, lines, _ = survey_dir
    l2 = lines.copy()
    l2.loc[2, "t_start"] = 86_300.0
    l2.loc[2, "t_end"] = 100.0
    l2.to_csv(root / "lines.csv", index=False)
    err = expect_error(root, "lines.csv", 4, "t_end", match="ends (100.000) before it starts (86300.000)")
    assert "midnight" in str(err) and "np.float64" not in str(err)


def test_overlapping_windows_of_one_flight(survey_dir):
    # a typo: 0002 starts 50 s before 0001 ends — the shared epochs would be processed twice
    root, lines, _ = survey_dir
    l2 = lines.copy()
    l2.loc[1, "t_start"] = l2.loc[0, "t_end"] - 50.0
    l2.to_csv(root / "lines.csv", index=False)
    err = expect_error(root, "lines.csv", 3, "t_start", match="overlap")
    assert "0001" in str(err) and "row 2" in str(err)
    # touching windows are fine
    l2.loc[1, "t_start"] = l2.loc[0, "t_end"]
    l2.to_csv(root / "lines.csv", index=False)
    read_survey(root)


def test_unknown_kind(survey_dir):
    root, lines, _ = survey_dir
    l2 = lines.copy()
    l2.loc[0, "kind"] = "diagonal"
    l2.to_csv(root / "lines.csv", index=False)
    expect_error(root, "lines.csv", 2, "kind", match="'diagonal'")


def test_duplicate_line_id(survey_dir):
    root, lines, _ = survey_dir
    l2 = lines.copy()
    l2.loc[2, "line"] = l2.loc[0, "line"]
    l2.to_csv(root / "lines.csv", index=False)
    expect_error(root, "lines.csv", 4, "line", match="twice")



def test_repeat_line_without_track_or_second_pass_is_said(survey_dir):
    """A repeat line is left out of the crossovers and compared only with the other passes of
    its track: without a track (or as its track's only pass) it silently gave no repeat-line
    accuracy.  Said in the notes (→ the report's warnings) with lines.csv's row."""
    root, lines, _ = survey_dir
    s = read_survey(root)    # the fixture's line 0003 is track A's only pass
    assert [n for n in s.notes if "track A" in n and "0003" in n and "row 4" in n and "one pass" in n], s.notes
    l2 = lines.copy()
    l2.loc[2, "track"] = ""
    l2.to_csv(root / "lines.csv", index=False)
    s = read_survey(root)
    assert [n for n in s.notes if "0003" in n and "row 4" in n and "no track" in n], s.notes
    l2.loc[1, ["kind", "track"]] = ["repeat", "A"]   # 0002 and 0003: two passes of A
    l2.loc[2, "track"] = "A"
    l2.to_csv(root / "lines.csv", index=False)
    assert not [n for n in read_survey(root).notes if "track" in n]

def test_gravimeter_rate_inferred_declared_is_a_check(tmp_path):
    """No rate in survey.toml: a 2 Hz and a 10 Hz gravimeter are read; a declared rate is checked."""
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    for hz in (2.0, 10.0):
        t = np.round(T0 + np.arange(int(600 * hz)) / hz, 3)
        g = pd.DataFrame({"time": t, "f_z": 9.81})
        root = write_survey(tmp_path / f"s{hz:g}", lines, {"F1": (g, gnss)})
        s = read_survey(root)
        assert s.config.gravimeter.rate_hz is None
        q = survey_summary(s)
        assert q.loc[q["level"] == "flight", "gravimeter_rate_hz"].iloc[0] == pytest.approx(hz, rel=1e-9)
    # declaring a different rate makes the 10 Hz file an error naming the declared rate and the setting
    toml = TOML.replace("scale = 1.0", "scale = 1.0\nrate_hz = 18.24")
    (root / "survey.toml").write_text(toml)
    err = expect_error(root, "flights/F1/gravimeter.csv", None, "time", match="18.24")
    assert "gravimeter.rate_hz" in str(err) and "10 Hz" in str(err)
    # the declared, correct rate is accepted
    (root / "survey.toml").write_text(TOML.replace("scale = 1.0", "scale = 1.0\nrate_hz = 10.0"))
    read_survey(root)


@pytest.mark.parametrize("hz, ok", [(0.5, True), (100.0, True), (0.4, False), (125.0, False)])
def test_gravimeter_rate_sanity_range_when_undeclared(tmp_path, hz, ok):
    lines, tabs = make_tables()
    n = int(700 * hz)
    t = T0 - 50.0 + np.arange(n) / hz  # covers every line window (t0+20 … t0+590)
    g = pd.DataFrame({"time": t, "f_z": 9.81})
    root = write_survey(tmp_path / "s", lines, {"F1": (g, tabs["F1"][1])})
    if ok:
        read_survey(root, {"max_gap_s": 3.0})
    else:
        expect_error(root, "flights/F1/gravimeter.csv", None, "time", overrides={"max_gap_s": 3.0},
                     match="outside the plausible 0.5–100 Hz")


@pytest.mark.parametrize("hz, ok", [(1.0, True), (50.0, True), (0.25, False), (64.0, False)])
def test_gnss_rate_sanity_range_when_undeclared(tmp_path, hz, ok):
    lines, tabs = make_tables()
    n = int(700 * hz)
    t = T0 - 50.0 + np.arange(n) / hz
    nav = pd.DataFrame({"time": t, "lat": LAT0, "lon": LON0 + 1e-6 * np.arange(n), "h": 3000.0, "vu": 0.0})
    root = write_survey(tmp_path / "s", lines, {"F1": (tabs["F1"][0], nav)})
    if ok:
        read_survey(root, {"max_gap_s": 5.0})
    else:
        expect_error(root, "flights/F1/gnss.csv", None, "time", overrides={"max_gap_s": 5.0},
                     match="outside the plausible 0.5–50 Hz")


def test_gnss_rate(survey_dir):
    root, *_ = survey_dir
    read_survey(root, {"gnss_rate_hz": 10.0})
    expect_error(root, "flights/F1/gnss.csv", None, "time", overrides={"gnss_rate_hz": 5.0}, match="5 Hz")


def test_gnss_rate_sanity_when_undeclared(survey_dir):
    root, _, tabs = survey_dir
    gnss = tabs["F1"][1].copy()
    gnss["time"] = T0 * 1000.0 + (gnss["time"] - T0) * 1000.0  # milliseconds by mistake
    gnss.to_csv(root / "flights/F1/gnss.csv", index=False)
    expect_error(root, "flights/F1/gnss.csv", None, "time", match="plausible")


def test_latitude_out_of_range(survey_dir):
    root, *_ = survey_dir
    edit_cell(root / "flights/F1/gnss.csv", 11, "lat", "162.0")
    expect_error(root, "flights/F1/gnss.csv", 11, "lat", match="162")
    edit_cell(root / "flights/F1/gnss.csv", 11, "lat", "62.0")
    edit_cell(root / "flights/F1/gnss.csv", 4000, "lon", "-200.5")
    expect_error(root, "flights/F1/gnss.csv", 4000, "lon", match="-200.5")


def test_f_z_units_checked(survey_dir):
    root, _, tabs = survey_dir
    g = tabs["F1"][0].copy()
    g["f_z"] = -g["f_z"]
    g.to_csv(root / "flights/F1/gravimeter.csv", index=False)
    expect_error(root, "flights/F1/gravimeter.csv", None, "f_z", match="up")



def test_declared_f_z_unit_applies_to_gravimeter_csv(survey_dir):
    """survey.toml's ``[columns] f_z_unit`` is honoured for gravimeter.csv: a file in mGal
    declared as mGal reads as the same m/s² values as the file in m/s² (no inference
    warning); declared as m/s² it is refused, naming the key, its row and what the values
    look like."""
    import warnings

    root, _, tabs = survey_dir
    ref = read_survey(root).flights["F1"].gravimeter["f_z"].to_numpy()
    g = tabs["F1"][0].copy()
    g["f_z"] = g["f_z"] * 1e5
    g.to_csv(root / "flights/F1/gravimeter.csv", index=False)
    toml = (root / "survey.toml").read_text()
    (root / "survey.toml").write_text(toml + '\n[columns]\nf_z_unit = "mGal"\n')
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = read_survey(root).flights["F1"].gravimeter["f_z"].to_numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-12)
    assert not any("read as" in str(w.message) for w in caught)
    (root / "survey.toml").write_text(toml + '\n[columns]\nf_z_unit = "m/s2"\n')
    row = len(toml.splitlines()) + 3
    expect_error(root, "survey.toml", row, "columns.f_z_unit", match="look like mGal")

def test_missing_gnss_file(survey_dir):
    root, *_ = survey_dir
    (root / "flights/F1/gnss.csv").unlink()
    expect_error(root, "flights/F1/gnss.csv", None, None)


def test_unreadable_flight_no_line_uses_is_skipped_and_said(tmp_path):
    """A flight folder no line of lines.csv uses (a ferry flight with only its GNSS file, or
    broken data) does not stop the survey: it is left out with a warning naming it and the
    problem. The same folder used by a line is still refused, naming the file."""
    lines, tabs = make_tables(flights=("F1", "F2"))
    grav2, gnss2 = tabs["F2"]
    tabs["F2"] = (None, gnss2)                       # F2: only gnss.csv
    root = write_survey(tmp_path / "s", lines[lines["flight"] == "F1"], tabs)
    with pytest.warns(UserWarning, match=r"flight F2 is not read \(no line in lines.csv uses it\).*gravimeter"):
        s = read_survey(root)
    assert set(s.flights) == {"F1"}
    assert any("flight F2 is not read" in n for n in s.notes)
    pd.testing.assert_frame_equal(s.flights["F1"].gnss[["time", "h"]].reset_index(drop=True),
                                  tabs["F1"][1][["time", "h"]].reset_index(drop=True), check_dtype=False)
    # a complete flight no line uses is still read (it may be the calibration flight)
    tabs["F2"] = (grav2, gnss2)
    root2 = write_survey(tmp_path / "s2", lines[lines["flight"] == "F1"], tabs)
    assert set(read_survey(root2).flights) == {"F1", "F2"}
    # used by a line: refused, naming the missing file
    (root2 / "flights/F2/gravimeter.csv").unlink()
    lines.to_csv(root2 / "lines.csv", index=False)
    expect_error(root2, "flights/F2/gravimeter.csv", None, None)


def test_two_flights_and_summary(tmp_path):
    from pyproj import Geod

    lines, tabs = make_tables(flights=("F1", "F2"))
    root = write_survey(tmp_path / "s", lines, tabs)
    s = read_survey(root)
    assert set(s.flights) == {"F1", "F2"}
    q = survey_summary(s)
    assert (q["level"] == "flight").sum() == 2 and (q["level"] == "line").sum() == 6
    ln = q[q["level"] == "line"].set_index("line")
    np.testing.assert_allclose(ln["gravimeter_rate_hz"], GRAV_HZ, rtol=2e-4)
    assert q.loc[q["level"] == "flight", "line"].tolist() == [None, None]
    np.testing.assert_allclose(ln["gnss_rate_hz"], GNSS_HZ, rtol=1e-6)
    np.testing.assert_allclose(ln.loc["0001", "duration_s"], 260.0)
    assert ln.loc["0001", "gnss_max_gap_s"] == pytest.approx(0.1, abs=1e-6)
    # length against pyproj's geodesic on the ellipsoid (at h = 0) scaled to 3000 m height
    gnss = tabs["F1"][1]
    w = gnss[(gnss["time"] >= T0 + 20) & (gnss["time"] <= T0 + 280)]
    geod = Geod(ellps="WGS84")
    ref_km = geod.line_length(w["lon"].to_numpy(), w["lat"].to_numpy()) / 1000.0
    from app.core.geodesy import radii_of_curvature_m
    r_m, r_n = radii_of_curvature_m(LAT0)
    ref_km *= (r_n + 3000.0) / r_n  # east-west track: radius of the parallel grows with height
    assert ln.loc["0001", "length_km"] == pytest.approx(ref_km, rel=1e-6)
    # and against the flown speed: 100 m/s × 260 s with the rough radius used to build the track
    assert ln.loc["0001", "length_km"] == pytest.approx(26.0, rel=2e-3)


def test_summary_of_many_interleaved_lines(tmp_path):
    """200 short lines of two flights listed alternately: every line row is its own window's
    figures (pyproj's geodesic for the length, the stamps for counts, rates and gaps), in the
    order lines.csv lists them."""
    from pyproj import Geod

    _, tabs = make_tables(flights=("F1", "F2"))
    rows = []
    for i in range(100):
        for k, f in enumerate(("F1", "F2")):
            a = T0 + 1000.0 * k + 5.0 + 5.8 * i
            rows.append({"line": f"L{k}{i:03d}", "flight": f, "t_start": a, "t_end": a + 5.0 + 0.37 * (i % 3),
                         "kind": "main", "track": ""})
    lines = pd.DataFrame(rows)
    root = write_survey(tmp_path / "s", lines, tabs)
    q = survey_summary(read_survey(root))
    ln = q[q["level"] == "line"]
    assert ln["line"].tolist() == lines["line"].tolist()
    geod = Geod(ellps="WGS84")
    from app.core.geodesy import radii_of_curvature_m
    r_m, r_n = radii_of_curvature_m(LAT0)
    for row in list(ln.itertuples())[::17]:
        grav, gnss = tabs[row.flight]
        w = gnss[(gnss["time"] >= row.t_start) & (gnss["time"] <= row.t_end)]
        ref_km = geod.line_length(w["lon"].to_numpy(), w["lat"].to_numpy()) / 1000.0 * (r_n + 3000.0) / r_n
        assert row.length_km == pytest.approx(ref_km, rel=1e-6)
        assert row.n_gnss == len(w)
        assert row.n_gravimeter == int(((grav["time"] >= row.t_start) & (grav["time"] <= row.t_end)).sum())
        assert row.gnss_rate_hz == pytest.approx(GNSS_HZ, rel=1e-6)
        assert row.gravimeter_rate_hz == pytest.approx(GRAV_HZ, rel=2e-4)
        assert row.gnss_max_gap_s == pytest.approx(0.1, abs=1e-6)


def test_summary_of_a_survey_without_lines(survey_dir):
    """Flights stored before their lines (the web allows it): one row per flight, none per line."""
    root, *_ = survey_dir
    s = read_survey(root)
    s.lines = s.lines.iloc[:0]
    q = survey_summary(s)
    assert q["level"].tolist() == ["flight"] and q["line"].tolist() == [None]
    assert q["n_gnss"].iloc[0] == len(s.flights["F1"].gnss)


def test_path_length_meridian_against_pyproj():
    from pyproj import Geod

    lat = np.linspace(50.0, 51.0, 2001)
    lon = np.full_like(lat, 10.0)
    ref = Geod(ellps="WGS84").inv(10.0, 50.0, 10.0, 51.0)[2] / 1000.0
    assert path_length_km(lat, lon) == pytest.approx(ref, rel=1e-8)


# ------------------------------------------------------------------ large files


def test_one_million_rows_round_trip(tmp_path):
    """A flight of 10⁶ gravimeter rows (15 h at 18.24 Hz) is read whole and unchanged
    (the reading time is printed by benchmarks/bench_pipeline.py as the ingest stage)."""
    n = 1_000_000
    t = np.round(T0 + np.arange(n) / GRAV_HZ, 4)
    rng = np.random.default_rng(1)
    g = pd.DataFrame({"time": t, "f_z": 9.81 + 1e-3 * rng.standard_normal(n),
                      "f_x": 1e-3 * rng.standard_normal(n), "f_y": 1e-3 * rng.standard_normal(n)})
    m = int(t[-1] - T0) * 10
    tn = np.round(T0 + np.arange(m) / 10.0, 2)
    nav = pd.DataFrame({"time": tn, "lat": LAT0, "lon": LON0 + 1e-5 * np.arange(m), "h": 3000.0, "vu": 0.0})
    lines = pd.DataFrame([{"line": "1", "flight": "F1", "t_start": T0 + 100, "t_end": t[-1] - 100, "kind": "main"}])
    import pyarrow as pa
    import pyarrow.csv as pacsv

    root = write_survey(tmp_path / "s", lines, {"F1": (g.iloc[:10], nav.iloc[:10])})
    for df, name in ((g, "gravimeter.csv"), (nav, "gnss.csv")):  # fast writer (pandas to_csv takes ~10 s)
        pacsv.write_csv(pa.Table.from_pandas(df, preserve_index=False), root / "flights/F1" / name)
    s = read_survey(root)
    got = s.flights["F1"].gravimeter
    assert len(got) == n and len(s.flights["F1"].gnss) == m
    np.testing.assert_allclose(got["f_z"].to_numpy(), g["f_z"].to_numpy(), rtol=1e-15)
    np.testing.assert_allclose(got["time"].to_numpy(), t, rtol=0, atol=1e-9)


def test_unknown_toml_table(survey_dir):
    root, *_ = survey_dir
    (root / "survey.toml").write_text(TOML + "\n[plotting]\ncolour = 1\n")
    expect_error(root, "survey.toml", 13, "plotting", match="unknown")


def test_unusable_crs_in_survey_toml_is_named(survey_dir):
    # parses as a projected CRS, fails on every point: refused while reading, not mid-processing
    root, *_ = survey_dir
    p = root / "survey.toml"
    p.write_text(p.read_text().replace('name = "tiny"\n', 'name = "tiny"\ncrs = "+proj=merc +k=1e-10 +type=crs"\n'))
    err = expect_error(root, "survey.toml", 3, "survey.crs", match="the CRS cannot be used: projecting a point fails")
    assert "ProjError" not in str(err)


def test_crs_as_words_or_wkt_refused_with_the_epsg_code(survey_dir):
    """A UTM zone in words PROJ cannot read, and a WKT longer than the 200 characters allowed,
    are refused naming the EPSG code to write instead — the code PROJ itself identifies."""
    from pyproj import CRS

    root, *_ = survey_dir
    p = root / "survey.toml"
    text = p.read_text()
    p.write_text(text.replace('name = "tiny"\n', 'name = "tiny"\ncrs = "UTM 57N"\n'))
    expect_error(root, "survey.toml", 3, "survey.crs", match="EPSG:32657")
    wkt = CRS.from_epsg(32757).to_wkt()    # a TOML literal string keeps WKT's double quotes
    p.write_text(text.replace('name = "tiny"\n', f"name = \"tiny\"\ncrs = '{wkt}'\n"))
    expect_error(root, "survey.toml", 3, "survey.crs", match="it is EPSG:32757")


def test_repeated_rows_dropped_same_series(survey_dir):
    """A record written twice, and two files joined where they overlap (50 rows again), read as
    the clean file — every repeat is the same time with the same values — with a warning; a
    repeated time with another value is still refused (which one is right is not in the file)."""
    root, _, tabs = survey_dir
    g, gn = tabs["F1"][0], tabs["F1"][1]
    clean = read_survey(root).flights["F1"]
    twice = pd.concat([g.iloc[:301], g.iloc[300:]], ignore_index=True)              # row 300 twice
    joined = pd.concat([gn.iloc[:400], gn.iloc[350:]], ignore_index=True)           # 50 rows overlap
    twice.to_csv(root / "flights/F1/gravimeter.csv", index=False)
    joined.to_csv(root / "flights/F1/gnss.csv", index=False)
    with pytest.warns(UserWarning, match="repeating an earlier row exactly") as rec:
        s = read_survey(root).flights["F1"]
    msgs = " ".join(str(w.message) for w in rec)
    assert "gravimeter.csv: 1 row(s)" in msgs and "gnss.csv: 50 row(s)" in msgs
    pd.testing.assert_frame_equal(s.gravimeter.reset_index(drop=True), clean.gravimeter.reset_index(drop=True))
    pd.testing.assert_frame_equal(s.gnss.reset_index(drop=True), clean.gnss.reset_index(drop=True))
    other = twice.copy()
    other.loc[301, "f_z"] += 1e-4
    other.to_csv(root / "flights/F1/gravimeter.csv", index=False)
    expect_error(root, "flights/F1/gravimeter.csv", 303, "time", match="repeated")
