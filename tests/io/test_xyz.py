"""Geosoft XYZ surveys: the simulator's CSV survey converted to XYZ must read and process
identically; hand-written files check the format's features and every error case."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.io.errors import InputError
from app.io.survey import read_survey, survey_summary
from app.io.xyz import scan_xyz, write_survey_xyz

SIM = dict(seed=1, n_main=2, main_length_km=20.0)


def assert_same_survey(a, b):
    """Identical flight tables (bit for bit) and identical lines."""
    assert list(a.flights) == list(b.flights)
    for name in a.flights:
        for tab in ("gravimeter", "gnss"):
            x, y = getattr(a.flights[name], tab), getattr(b.flights[name], tab)
            assert list(x.columns) == list(y.columns), (name, tab)
            for c in x.columns:
                np.testing.assert_array_equal(x[c].to_numpy(), y[c].to_numpy(), err_msg=f"{name} {tab} {c}")
        assert a.flights[name].vu_derived_from_h == b.flights[name].vu_derived_from_h
    cols = ["line", "flight", "t_start", "t_end", "kind"]
    pd.testing.assert_frame_equal(a.lines[cols].reset_index(drop=True), b.lines[cols].reset_index(drop=True),
                                  check_exact=True, check_dtype=False)
    assert a.lines["track"].tolist() == b.lines["track"].tolist()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from app.simulate import simulate_survey

    return simulate_survey("tiny", tmp_path_factory.mktemp("sim") / "tiny", **SIM)


@pytest.fixture(scope="module")
def tiny_10hz(tmp_path_factory):
    """The gravimeter at 10 Hz like the GNSS (but on its own time stamps): one combined file."""
    from app.simulate import simulate_survey

    return simulate_survey("tiny", tmp_path_factory.mktemp("sim10") / "tiny10", gravimeter_rate_hz=10.0, **SIM)


def _process(survey_dir, out_dir) -> pd.DataFrame:
    from app.pipeline.process import process_survey

    process_survey(survey_dir, out_dir)
    return pd.read_parquet(Path(out_dir) / "lines.parquet")


# ------------------------------------------------------------------ acceptance: CSV → XYZ → same survey


def test_separate_files_with_lines_csv(tiny, tmp_path):
    dst = write_survey_xyz(tiny, tmp_path / "x", combined=False, keep_lines_csv=True)
    fd = dst / "flights" / "F01"
    assert sorted(p.name for p in fd.iterdir()) == ["gnss.xyz", "gravimeter.xyz"]
    assert (dst / "lines.csv").is_file()
    a, b = read_survey(tiny), read_survey(dst)
    assert_same_survey(a, b)
    assert b.flights["F01"].gravimeter_path.name == "gravimeter.xyz"
    assert b.config.columns.f_z == "FZ" and b.config.columns.f_z_unit == "m/s2"
    # QC of the XYZ survey is the CSV survey's
    pd.testing.assert_frame_equal(survey_summary(a), survey_summary(b))


def test_byte_order_marks_accepted(tiny, tmp_path):
    """XYZ files and survey.toml saved with a UTF-8 byte-order mark read as without it."""
    dst = write_survey_xyz(tiny, tmp_path / "x", combined=False, keep_lines_csv=False)
    ref = read_survey(dst)
    for path in [dst / "survey.toml", *(dst / "flights" / "F01").iterdir()]:
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert_same_survey(ref, read_survey(dst))


def test_lines_from_blocks_and_processing_identical(tiny, tmp_path):
    """No lines.csv: the Line/Tie blocks give the same lines; the pipeline gives the same lines.parquet."""
    dst = write_survey_xyz(tiny, tmp_path / "x", combined=False, keep_lines_csv=False)
    assert not (dst / "lines.csv").exists()
    a, b = read_survey(tiny), read_survey(dst)
    assert_same_survey(a, b)
    assert b.lines["kind"].tolist() == ["main", "main", "tie", "tie"]
    pa = _process(tiny, tmp_path / "out_csv")
    pb = _process(dst, tmp_path / "out_xyz")
    pd.testing.assert_frame_equal(pa, pb, check_exact=True)
    assert np.isfinite(pa["dg_mgal"]).all()


def test_combined_file_and_processing_identical(tiny_10hz, tmp_path):
    dst = write_survey_xyz(tiny_10hz, tmp_path / "x", combined=True, keep_lines_csv=False)
    fd = dst / "flights" / "F01"
    assert [p.name for p in fd.iterdir()] == ["F01.xyz"]
    text = (fd / "F01.xyz").read_text()
    assert " * " in text  # gravimeter and GNSS samples on their own stamps: dummies in the other's columns
    a, b = read_survey(tiny_10hz), read_survey(dst)
    assert_same_survey(a, b)
    assert b.flights["F01"].gravimeter_path == b.flights["F01"].gnss_path == fd / "F01.xyz"
    pd.testing.assert_frame_equal(_process(tiny_10hz, tmp_path / "o1"), _process(dst, tmp_path / "o2"),
                                  check_exact=True)


def test_combined_requested_with_unequal_rates_writes_separate_files(tiny, tmp_path):
    dst = write_survey_xyz(tiny, tmp_path / "x", combined=True, keep_lines_csv=True)
    assert sorted(p.name for p in (dst / "flights" / "F01").iterdir()) == ["gnss.xyz", "gravimeter.xyz"]


def test_repeat_lines_keep_lines_csv(tmp_path):
    from tests.io.test_io_survey import make_tables, write_survey

    lines, tabs = make_tables()  # has a repeat line
    src = write_survey(tmp_path / "s", lines, tabs)
    dst = write_survey_xyz(src, tmp_path / "x", keep_lines_csv=False)
    assert (dst / "lines.csv").is_file()
    assert_same_survey(read_survey(src), read_survey(dst))


# ------------------------------------------------------------------ hand-written files

T0 = 345600.0  # GPS seconds of week
HZ = 10.0
N = 1200       # 120 s
TOML = '[survey]\nname = "x"\n'


def _tables(n=N):
    t = np.round(T0 + np.arange(n) / HZ, 1)
    k = np.arange(n)
    grav = pd.DataFrame({"time": t, "f_z": 9.81 + 1e-4 * np.sin(k / 7.0)})
    gnss = pd.DataFrame({"time": t, "lat": 62.0, "lon": 158.0 + 1e-5 * k, "h": 3000.0 + 0.01 * k,
                         "vu": 0.1 + 0.0 * k})
    return grav, gnss


def _fmt(v) -> str:
    return "*" if isinstance(v, float) and np.isnan(v) else repr(float(v))


def xyz_text(df: pd.DataFrame, names: list[str] | None, blocks: list[tuple[str, int, int]],
             pre=("/ a hand-written test file",)):
    out = list(pre)
    if names is not None:
        out.append("/ " + "  ".join(names))
    for head, i0, i1 in blocks:
        if head:
            out.append(head)
        for r in df.iloc[i0:i1].itertuples(index=False):
            out.append("  ".join(_fmt(v) for v in r))
    return "\n".join(out) + "\n"


BLOCKS = [("Random 1", 0, 200), ("Line 1001", 200, 500), ("random 2", 500, 600), ("TIE 2001", 600, 900),
          ("Base 9", 900, N)]


def make_xyz_survey(root: Path, toml=TOML, grav_text=None, gnss_text=None, lines_csv=None):
    grav, gnss = _tables()
    d = root / "flights" / "F1"
    d.mkdir(parents=True, exist_ok=True)
    (root / "survey.toml").write_text(toml)
    (d / "gravimeter.xyz").write_text(grav_text if grav_text is not None
                                      else xyz_text(grav, ["TIME", "F_Z"], BLOCKS))
    (d / "gnss.xyz").write_text(gnss_text if gnss_text is not None
                                else xyz_text(gnss, ["time", "lat", "lon", "h", "vu"], BLOCKS))
    if lines_csv is not None:
        (root / "lines.csv").write_text(lines_csv)
    return root, grav, gnss


def row_of(text: str, needle: str) -> int:
    return text.splitlines().index(needle) + 1


def expect(root, file, row, column, match=None, overrides=None):
    with pytest.raises(InputError) as ei:
        read_survey(root, overrides)
    e = ei.value
    assert (e.file, e.row, e.column) == (file, row, column), str(e)
    if match is not None:
        assert match in str(e), str(e)
    return e


def test_blocks_header_names_and_lines(tmp_path):
    root, grav, gnss = make_xyz_survey(tmp_path / "s")
    s = read_survey(root)
    fl = s.flights["F1"]
    np.testing.assert_array_equal(fl.gravimeter["f_z"].to_numpy(), grav["f_z"].to_numpy())
    np.testing.assert_array_equal(fl.gnss["time"].to_numpy(), gnss["time"].to_numpy())
    assert s.lines["line"].tolist() == ["1001", "2001"]
    assert s.lines["kind"].tolist() == ["main", "tie"]
    t = gnss["time"].to_numpy()
    assert s.lines["t_start"].tolist() == [t[200], t[600]] and s.lines["t_end"].tolist() == [t[499], t[899]]
    sc = scan_xyz(root / "flights/F1/gnss.xyz")
    assert sc.names == ["time", "lat", "lon", "h", "vu"] and sc.header_row == 2
    assert [b.keyword for b in sc.blocks] == ["random", "line", "random", "tie", "base"]


def test_dummies_comments_directives_and_mapping_by_number(tmp_path):
    grav, gnss = _tables()
    g = grav.copy()
    g.loc[300, "f_z"] = np.nan          # written as '*'
    txt = xyz_text(g, None, BLOCKS, pre=("/ no header line: columns mapped by number", "//flight 12",
                                          "//date 2024/05/02"))
    txt = txt.replace(repr(float(grav["f_z"].iloc[301])), "-1.0E32", 1)  # the Geosoft double dummy
    toml = TOML + '\n[columns.gravimeter]\ntime = 1\nf_z = 2\n'
    root, *_ = make_xyz_survey(tmp_path / "s", toml=toml, grav_text=txt)
    r300 = row_of(txt, f"{float(g['time'].iloc[300])!r}  *")
    expect(root, "flights/F1/gravimeter.xyz", r300, "f_z", match="2 consecutive missing values")
    with pytest.warns(UserWarning, match="2 missing value"):
        s = read_survey(root, {"max_nan_run": 2})
    # dummies of f_z are holes of the record (not interpolated): rows 300 and 301 are gone
    got = s.flights["F1"].gravimeter
    np.testing.assert_array_equal(got["time"].to_numpy(), np.delete(grav["time"].to_numpy(), [300, 301]))
    np.testing.assert_allclose(got["f_z"].to_numpy()[299:301], grav["f_z"].to_numpy()[[299, 302]], rtol=0, atol=1e-15)
    assert scan_xyz(root / "flights/F1/gravimeter.xyz").directives == [(2, "flight 12"), (3, "date 2024/05/02")]


def test_line_column_instead_of_blocks(tmp_path):
    grav, gnss = _tables()
    lab = np.array(["*"] * N, dtype=object)
    lab[200:500] = "L1001"
    lab[600:900] = "T2001"
    lab[950:1000] = "R5"           # a trend line: data, not a survey line
    out = ["/ TIME LAT LON H VU LINE"]
    for r, v in zip(gnss.itertuples(index=False), lab):
        out.append(" ".join(_fmt(x) for x in r) + f" {v}")
    root, *_ = make_xyz_survey(tmp_path / "s", gnss_text="\n".join(out) + "\n",
                               grav_text=xyz_text(grav, ["TIME", "F_Z"], [("", 0, N)]),
                               toml=TOML + '\n[columns.gnss]\nh = "H"\nline = "LINE"\n')
    s = read_survey(root)
    assert s.lines["line"].tolist() == ["1001", "2001"] and s.lines["kind"].tolist() == ["main", "tie"]
    t = gnss["time"].to_numpy()
    assert s.lines["t_end"].tolist() == [t[499], t[899]]


def test_f_z_units_inferred_and_declared(tmp_path):
    grav, gnss = _tables()
    g = grav.copy()
    g["f_z"] = grav["f_z"] * 1e5  # mGal
    root, *_ = make_xyz_survey(tmp_path / "a", grav_text=xyz_text(g, ["TIME", "F_Z"], BLOCKS))
    s = read_survey(root)
    np.testing.assert_allclose(s.flights["F1"].gravimeter["f_z"], g["f_z"] * 1e-5, rtol=1e-15)
    g["f_z"] = grav["f_z"] * 1e6  # µm/s², declared
    root, *_ = make_xyz_survey(tmp_path / "b", grav_text=xyz_text(g, ["TIME", "F_Z"], BLOCKS),
                               toml=TOML + '\n[columns]\nf_z_unit = "um/s2"\n')
    np.testing.assert_allclose(read_survey(root).flights["F1"].gravimeter["f_z"], grav["f_z"], rtol=1e-15)


def test_gzipped_and_lines_csv_wins(tmp_path):
    import gzip

    root, grav, gnss = make_xyz_survey(tmp_path / "s", lines_csv=(
        "line,flight,t_start,t_end,kind,track\nA,F1,345620.0,345640.0,repeat,t1\nB,F1,345660.0,345680.0,repeat,t1\n"))
    p = root / "flights/F1/gnss.xyz"
    (root / "flights/F1/gnss.xyz.gz").write_bytes(gzip.compress(p.read_bytes()))
    p.unlink()
    s = read_survey(root)
    assert s.lines["line"].tolist() == ["A", "B"] and s.lines["track"].tolist() == ["t1", "t1"]
    assert s.flights["F1"].gnss_path.name == "gnss.xyz.gz"


# ------------------------------------------------------------------ errors


def test_error_bad_number_names_row_and_column(tmp_path):
    grav, gnss = _tables()
    txt = xyz_text(gnss, ["TIME", "LAT", "LON", "HGT", "VU"], BLOCKS)
    lines = txt.splitlines()
    r = row_of(txt, "Line 1001") + 10
    cells = lines[r - 1].split("  ")
    cells[3] = "3000.1O"
    lines[r - 1] = "  ".join(cells)
    root, *_ = make_xyz_survey(tmp_path / "s", gnss_text="\n".join(lines) + "\n",
                               toml=TOML + '\n[columns]\nh = "HGT"\n')
    e = expect(root, "flights/F1/gnss.xyz", r, "h", match="'3000.1O'")
    assert "HGT" in e.message


def test_error_time_not_increasing_across_blocks(tmp_path):
    grav, gnss = _tables()
    g = gnss.copy()
    # the Tie block was pasted with times that go back into the Line block's
    g.loc[600:899, "time"] = g.loc[600:899, "time"] - 50.0
    txt = xyz_text(g, ["time", "lat", "lon", "h", "vu"], BLOCKS)
    root, *_ = make_xyz_survey(tmp_path / "s", gnss_text=txt)
    first_tie = row_of(txt, "TIE 2001") + 1
    expect(root, "flights/F1/gnss.xyz", first_tie, "time", match="backwards")


def test_error_unknown_mapped_column(tmp_path):
    root, *_ = make_xyz_survey(tmp_path / "s", toml=TOML + '\n[columns.gravimeter]\nf_z = "GRAV"\n')
    e = expect(root, "flights/F1/gravimeter.xyz", 2, "f_z", match="'GRAV'")
    assert "TIME, F_Z" in e.message


def test_error_mapped_name_without_header(tmp_path):
    grav, _ = _tables()
    root, *_ = make_xyz_survey(tmp_path / "s", grav_text=xyz_text(grav, None, BLOCKS),
                               toml=TOML + '\n[columns.gravimeter]\ntime = "TIME"\nf_z = 2\n')
    expect(root, "flights/F1/gravimeter.xyz", None, "time", match="no column header")


def test_error_missing_required_column(tmp_path):
    _, gnss = _tables()
    txt = xyz_text(gnss.drop(columns="h"), ["time", "lat", "lon", "vu"], BLOCKS)
    root, *_ = make_xyz_survey(tmp_path / "s", gnss_text=txt)
    expect(root, "flights/F1/gnss.xyz", 2, "h", match="required column 'h' is missing")


def test_error_f_z_unit_ambiguous(tmp_path):
    grav, _ = _tables()
    g = grav.copy()
    g["f_z"] = 9810.0 + g["f_z"]  # a relative reading or Gal·1000? nobody can tell
    root, *_ = make_xyz_survey(tmp_path / "s", grav_text=xyz_text(g, ["TIME", "F_Z"], BLOCKS))
    e = expect(root, "flights/F1/gravimeter.xyz", None, "f_z", match="f_z_unit")
    assert "'F_Z'" in e.message and "mGal" in e.message


def test_error_declared_unit_wrong(tmp_path):
    root, *_ = make_xyz_survey(tmp_path / "s", toml=TOML + '\n[columns]\nf_z_unit = "mGal"\n')
    expect(root, "flights/F1/gravimeter.xyz", None, "f_z", match="not plausible")


def test_error_repeat_line_id_without_lines_csv(tmp_path):
    blocks = [("Line 1001", 0, 300), ("Random 1", 300, 400), ("Line 1001", 400, 700), ("Tie 2001", 700, N)]
    grav, gnss = _tables()
    txt = xyz_text(gnss, ["time", "lat", "lon", "h", "vu"], blocks)
    root, *_ = make_xyz_survey(tmp_path / "s", gnss_text=txt, grav_text=xyz_text(grav, ["TIME", "F_Z"], blocks))
    second = [i + 1 for i, ln in enumerate(txt.splitlines()) if ln == "Line 1001"][1]
    e = expect(root, "flights/F1/gnss.xyz", second, "line", match="lines.csv")
    assert "row 3" in e.message  # where the id was first seen


def test_error_blocks_differ_between_files(tmp_path):
    grav, _ = _tables()
    blocks = [b if b[0] != "TIE 2001" else ("Tie 2002", b[1], b[2]) for b in BLOCKS]
    root, *_ = make_xyz_survey(tmp_path / "s", grav_text=xyz_text(grav, ["TIME", "F_Z"], blocks))
    expect(root, "flights/F1/gravimeter.xyz", None, None, match="2002")


def test_error_field_count(tmp_path):
    _, gnss = _tables()
    txt = xyz_text(gnss, ["time", "lat", "lon", "h", "vu"], BLOCKS)
    lines = txt.splitlines()
    r = row_of(txt, "random 2") + 3
    lines[r - 1] = lines[r - 1] + "  7.0"
    root, *_ = make_xyz_survey(tmp_path / "s", gnss_text="\n".join(lines) + "\n")
    expect(root, "flights/F1/gnss.xyz", r, None, match="6 fields")


def test_error_columns_table_in_survey_toml(tmp_path):
    toml = TOML + '\n[columns]\ntime = "T"\n\n[columns.gnss]\nf_z = "FZ"\n'
    root, *_ = make_xyz_survey(tmp_path / "s", toml=toml)
    expect(root, "survey.toml", 8, "columns.gnss.f_z", match="unknown setting")
    root, *_ = make_xyz_survey(tmp_path / "t", toml=TOML + '\n[columns]\nf_z = "A"\nf_x = "a"\n')
    expect(root, "survey.toml", 4, "columns", match="same column")


def test_error_no_lines_anywhere(tmp_path):
    grav, gnss = _tables()
    one = [("", 0, N)]
    root, *_ = make_xyz_survey(tmp_path / "s", grav_text=xyz_text(grav, ["TIME", "F_Z"], one),
                               gnss_text=xyz_text(gnss, ["time", "lat", "lon", "h", "vu"], one))
    expect(root, "lines.csv", None, None, match="Line/Tie")


def test_gnss_xyz_without_vu_derives_it(tmp_path):
    _, gnss = _tables()
    txt = xyz_text(gnss.drop(columns="vu"), ["time", "lat", "lon", "h"], BLOCKS)
    root, *_ = make_xyz_survey(tmp_path / "s", gnss_text=txt)
    fl = read_survey(root).flights["F1"]
    assert fl.vu_derived_from_h
    np.testing.assert_allclose(fl.gnss["vu"], 0.01 * HZ, rtol=0, atol=1e-9)  # h rises 1 cm per 0.1 s
