"""GT-1A/GT-2A "G" file reader: synthetic files built from known values."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from app.io.errors import InputError
from app.io.gfile import is_gfile_name, read_gfile
from app.io.survey import read_survey

MSG_HZ = 9.12  # two half-interval samples per message → 18.24 Hz
T_MSG = 1.0 / MSG_HZ


def hhmmss(sod):
    sod = np.asarray(sod, dtype=float) % 86400.0
    hh = np.floor(sod / 3600.0)
    mm = np.floor((sod - 3600.0 * hh) / 60.0)
    ss = sod - 3600.0 * hh - 60.0 * mm
    return hh * 10000.0 + mm * 100.0 + ss


def make_messages(n, t0_sod, seed=0, n_cc=3):
    """Message table with known values; message k's interval ends at t0 + (k+1)·T (true times)."""
    rng = np.random.default_rng(seed)
    t_end = t0_sod + (np.arange(n) + 1) * T_MSG
    whole = np.floor(t_end)
    sub = np.round(t_end - whole, 4)  # sub-second field (s), hhmmss carries whole seconds
    m = {
        "message_id": np.arange(n) + 100,
        "t_pow": 5000.0 + np.arange(n) * T_MSG,
        "utc": hhmmss(whole),
        "sub": sub,
    }
    for name, base in (("fz", 9.81), ("cz", 9.80), ("x", 0.0), ("y", 0.0)):
        m[name + "1"] = base + 0.01 * rng.standard_normal(n)
        m[name + "2"] = base + 0.01 * rng.standard_normal(n)
    m["temp"] = 0.5 + 0.01 * rng.standard_normal(n)
    for i in range(n_cc):
        m[f"cc{i}"] = rng.standard_normal(n)
    m["pm"] = 1e-3 * rng.standard_normal(n)
    m["sat"] = np.zeros(n, dtype=int)
    return pd.DataFrame(m), t_end


def write_g(path: Path, msgs: pd.DataFrame, sep=" ", scale=1.0):
    """Write messages as a G file; accelerations divided by ``scale`` (file units)."""
    out = ["GT-1A G file  id  t_pow  utc  sub  fz1 fz2 cz1 cz2 x1 x2 y1 y2 temp cc... pm sat chk"]
    cc = [c for c in msgs.columns if c.startswith("cc")]
    for r in msgs.itertuples(index=False):
        d = r._asdict()
        acc = [d[k] / scale for k in ("fz1", "fz2", "cz1", "cz2", "x1", "x2", "y1", "y2")]
        f = ([f"{d['message_id']:d}", f"{d['t_pow']:.4f}", f"{d['utc']:09.2f}", f"{d['sub']:.4f}"]
             + [repr(float(a)) for a in acc] + [repr(float(d["temp"]))] + [repr(float(d[c])) for c in cc]
             + [repr(float(d["pm"])), f"{d['sat']:d}", f"{(d['message_id'] * 7) % 256:02X}"])
        out.append(sep.join(f))
    path.write_text("\n".join(out) + "\n")


def interleave(a, b):
    out = np.empty(2 * len(a))
    out[0::2], out[1::2] = a, b
    return out


def test_reader_reproduces_values_and_centres(tmp_path):
    msgs, t_end = make_messages(200, t0_sod=3600.0 * 5 + 17.3)
    p = tmp_path / "flight.G"
    write_g(p, msgs)
    df = read_gfile(p)
    assert len(df) == 400
    np.testing.assert_allclose(df["f_z"], interleave(msgs["fz1"], msgs["fz2"]), rtol=0, atol=1e-14)
    np.testing.assert_allclose(df["f_z_coarse"], interleave(msgs["cz1"], msgs["cz2"]), rtol=0, atol=1e-14)
    np.testing.assert_allclose(df["f_x"], interleave(msgs["x1"], msgs["x2"]), rtol=0, atol=1e-14)
    np.testing.assert_allclose(df["f_y"], interleave(msgs["y1"], msgs["y2"]), rtol=0, atol=1e-14)
    np.testing.assert_allclose(df["cc_3"], np.repeat(msgs["cc2"], 2), rtol=0, atol=1e-14)
    np.testing.assert_allclose(df["temperature"], np.repeat(msgs["temp"], 2), rtol=0, atol=1e-14)
    # the true half-interval centres: interval k is (t_end_k − T, t_end_k]
    centres = interleave(t_end - 0.75 * T_MSG, t_end - 0.25 * T_MSG)
    np.testing.assert_allclose(df["time"], centres, rtol=0, atol=2e-4)  # sub-second rounded to 1e-4 s
    assert df["source_row"].tolist()[:4] == [2, 2, 3, 3]
    assert df["half"].tolist()[:4] == [1, 2, 1, 2]
    assert not df["saturated"].any()
    rate = 1.0 / np.median(np.diff(df["time"]))
    assert rate == pytest.approx(18.24, rel=1e-3)


def test_comma_separated_no_cross_coupling_scale_and_offset(tmp_path):
    msgs, t_end = make_messages(50, t0_sod=100.0, n_cc=0)
    p = tmp_path / "G0001.dat"
    write_g(p, msgs, sep=", ", scale=1e-5)  # file in mGal-like units (1e-5 m/s²)
    df = read_gfile(p, scale_to_ms2=1e-5, time_offset_s=3 * 86400.0 + 18.0)
    np.testing.assert_allclose(df["f_z"], interleave(msgs["fz1"], msgs["fz2"]), rtol=1e-12)
    assert not any(c.startswith("cc_") for c in df.columns)
    centres = interleave(t_end - 0.75 * T_MSG, t_end - 0.25 * T_MSG) + 3 * 86400.0 + 18.0
    np.testing.assert_allclose(df["time"], centres, rtol=0, atol=2e-4)


def test_stamp_start(tmp_path):
    msgs, t_end = make_messages(30, t0_sod=1000.0)
    p = tmp_path / "gravimeter.g"
    write_g(p, msgs)
    df = read_gfile(p, stamp="start")
    centres = interleave(t_end + 0.25 * T_MSG, t_end + 0.75 * T_MSG)
    np.testing.assert_allclose(df["time"], centres, rtol=0, atol=2e-4)


def test_midnight_rollover(tmp_path):
    msgs, t_end = make_messages(100, t0_sod=86400.0 - 5.0)
    p = tmp_path / "x.G"
    write_g(p, msgs)
    assert msgs["utc"].iloc[-1] < msgs["utc"].iloc[0]  # the file really crosses 00:00
    df = read_gfile(p)
    centres = interleave(t_end - 0.75 * T_MSG, t_end - 0.25 * T_MSG)
    np.testing.assert_allclose(df["time"], centres, rtol=0, atol=2e-4)


def test_saturation_policies(tmp_path):
    msgs, _ = make_messages(40, t0_sod=500.0)
    msgs.loc[[10, 11], "sat"] = 1
    p = tmp_path / "s.G"
    write_g(p, msgs)
    with pytest.warns(UserWarning, match="2 saturated"):
        df = read_gfile(p)
    assert len(df) == 2 * 38 and df.attrs["saturated_messages"] == 2
    assert 12 not in set(df["source_row"]) and 13 not in set(df["source_row"])
    flagged = read_gfile(p, on_saturation="flag")
    assert len(flagged) == 80 and flagged["saturated"].sum() == 4
    with pytest.raises(InputError) as ei:
        read_gfile(p, on_saturation="error", display="s.G")
    assert (ei.value.file, ei.value.row, ei.value.column) == ("s.G", 12, "saturation")


def test_missing_z_sample_left_as_a_hole(tmp_path):
    """A missing fine-Z half-sample (``max_nan_run`` tolerating it) is a hole of the record, not a
    value to interpolate: that half-sample is dropped with a warning naming its row; the other
    half of the message and every other sample keep their values and times."""
    msgs, _ = make_messages(40, t0_sod=500.0)
    fz = interleave(msgs["fz1"].to_numpy(), msgs["fz2"].to_numpy())
    msgs.loc[10, "fz1"] = np.nan
    p = tmp_path / "s.G"
    write_g(p, msgs)
    with pytest.warns(UserWarning, match=r"1 missing fine Z sample\(s\) left as holes of the record \(first at row 12\)"):
        df = read_gfile(p, max_nan_run=1)
    keep = np.arange(80) != 20
    assert len(df) == 79
    np.testing.assert_allclose(df["f_z"].to_numpy(), fz[keep], rtol=0, atol=1e-12)
    assert df.loc[df["source_row"] == 12, "half"].tolist() == [2]
    assert np.all(np.diff(df["time"].to_numpy()) > 0)


def test_non_numeric_and_backwards(tmp_path):
    msgs, _ = make_messages(20, t0_sod=500.0)
    p = tmp_path / "a.G"
    write_g(p, msgs)
    lines = p.read_text().splitlines()
    f = lines[6].split(" ")
    f[8] = "1.2.3"  # x_1
    lines[6] = " ".join(f)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as ei:
        read_gfile(p)
    assert (ei.value.row, ei.value.column) == (7, "x_1") and "'1.2.3'" in str(ei.value)

    msgs2 = msgs.copy()
    msgs2.loc[8, ["utc", "sub"]] = msgs2.loc[6, ["utc", "sub"]].to_numpy()
    write_g(p, msgs2)
    with pytest.raises(InputError) as ei:
        read_gfile(p)
    assert (ei.value.row, ei.value.column) == (10, "utc_hhmmss")


def test_too_few_fields(tmp_path):
    p = tmp_path / "b.G"
    p.write_text("header\n1 2 3 4 5\n")
    with pytest.raises(InputError) as ei:
        read_gfile(p)
    assert ei.value.row == 2


def test_names():
    assert is_gfile_name("gravimeter.g") and is_gfile_name("F12.G") and is_gfile_name("G0001.dat")
    assert not is_gfile_name("gnss.csv") and not is_gfile_name("data.dat")


DAY_S = 4 * 86400.0   # GNSS in GPS seconds of week, day 4


def _g_survey(root, msgs):
    """A one-flight survey whose gravimeter is the G file of ``msgs`` (5 min from 01:00 UTC)
    and whose GNSS is in GPS seconds of week; returns its directory."""
    d = root / "flights" / "F1"
    d.mkdir(parents=True)
    write_g(d / "F1.G", msgs)
    tn = np.round(DAY_S + 3600.0 + np.arange(3000) / 10.0, 2)
    pd.DataFrame({"time": tn, "lat": 60.0, "lon": 150.0 + 1e-5 * np.arange(3000), "h": 2000.0, "vu": 0.0}).to_csv(
        d / "gnss.csv", index=False)
    pd.DataFrame([{"line": "L1", "flight": "F1", "t_start": DAY_S + 3650.0, "t_end": DAY_S + 3850.0,
                   "kind": "main"}]).to_csv(root / "lines.csv", index=False)
    (root / "survey.toml").write_text('[survey]\nname = "g"\n')
    return root


def test_g_file_in_survey(tmp_path):
    """A flight with a G file instead of gravimeter.csv; GNSS in GPS seconds of week (day 4)."""
    day = DAY_S
    msgs, t_end = make_messages(int(300 * MSG_HZ), t0_sod=3600.0)
    s = read_survey(_g_survey(tmp_path / "s", msgs))
    g = s.flights["F1"].gravimeter
    assert list(g.columns) == ["time", "f_z", "f_x", "f_y"]
    assert s.flights["F1"].gravimeter_path.name == "F1.G"
    centres = interleave(t_end - 0.75 * T_MSG, t_end - 0.25 * T_MSG) + day  # day offset inferred from GNSS
    np.testing.assert_allclose(g["time"], centres, rtol=0, atol=2e-4)


def test_dropped_saturated_messages_reach_the_survey_notes(tmp_path):
    """What a reader drops is said where the report can show it (Survey.notes → report warnings)."""
    msgs, _ = make_messages(int(300 * MSG_HZ), t0_sod=3600.0)
    msgs.loc[[100, 101, 102], "sat"] = 1
    root = _g_survey(tmp_path / "s", msgs)
    with pytest.warns(UserWarning, match="3 saturated"):
        s = read_survey(root)
    assert len(s.notes) == 1 and "3 saturated message(s) dropped" in s.notes[0] and "F1.G" in s.notes[0]
    assert len(s.flights["F1"].gravimeter) == 2 * (int(300 * MSG_HZ) - 3)


def test_two_g_files_in_a_flight_is_an_error(tmp_path):
    day = 4 * 86400.0
    msgs, _ = make_messages(200, t0_sod=3600.0)
    d = tmp_path / "s" / "flights" / "F1"
    d.mkdir(parents=True)
    write_g(d / "A.G", msgs)
    write_g(d / "G2.dat", msgs)
    tn = np.round(day + 3600.0 + np.arange(300) / 10.0, 2)
    pd.DataFrame({"time": tn, "lat": 60.0, "lon": 150.0, "h": 2000.0, "vu": 0.0}).to_csv(d / "gnss.csv", index=False)
    pd.DataFrame([{"line": "L1", "flight": "F1", "t_start": day + 3605.0, "t_end": day + 3615.0, "kind": "main"}]).to_csv(
        tmp_path / "s" / "lines.csv", index=False)
    (tmp_path / "s" / "survey.toml").write_text("")
    with pytest.raises(InputError) as ei:
        read_survey(tmp_path / "s")
    assert ei.value.file == "flights/F1/" and "A.G" in str(ei.value) and "G2.dat" in str(ei.value)


@pytest.mark.parametrize("keep", [9, 17])   # cut inside the x channel (its value cut too), or before the checksum
def test_last_message_cut_short_is_dropped_with_a_warning(tmp_path, keep):
    msgs, t_end = make_messages(50, t0_sod=3600.0 * 5)
    p = tmp_path / "flight.G"
    write_g(p, msgs)
    lines = p.read_text().rstrip("\n").split("\n")
    fields = lines[-1].split(" ")
    lines[-1] = " ".join(fields[:keep - 1] + [fields[keep - 1][:3]])    # the logger stopped mid-field
    p.write_text("\n".join(lines))
    with pytest.warns(UserWarning, match=r"the last message \(row 51\) is cut short \(no checksum\): dropped"):
        df = read_gfile(p)
    assert len(df) == 2 * 49
    np.testing.assert_allclose(df["f_z"], interleave(msgs["fz1"][:49], msgs["fz2"][:49]), rtol=0, atol=1e-14)


def test_a_short_message_inside_the_file_is_still_an_error(tmp_path):
    msgs, _ = make_messages(50, t0_sod=3600.0 * 5)
    p = tmp_path / "flight.G"
    write_g(p, msgs)
    lines = p.read_text().split("\n")
    lines[20] = " ".join(lines[20].split(" ")[:10])
    p.write_text("\n".join(lines))
    with pytest.raises(InputError) as exc:
        read_gfile(p)
    assert exc.value.row == 21


def test_subsecond_field_in_milliseconds_is_recognised(tmp_path):
    msgs, t_end = make_messages(200, t0_sod=3600.0 * 5 + 17.3)
    msgs["sub"] = np.round(msgs["sub"] * 1000.0)           # the logger writes whole milliseconds
    p = tmp_path / "flight.G"
    write_g(p, msgs)
    with pytest.warns(UserWarning, match="the sub-second field reaches 9[0-9][0-9]: read as milliseconds"):
        df = read_gfile(p)
    centres = interleave(t_end - 0.75 * T_MSG, t_end - 0.25 * T_MSG)
    np.testing.assert_allclose(df["time"], centres, rtol=0, atol=1e-3)   # whole ms: ±0.5 ms, ±0.25 ms more at centres


def test_subsecond_field_beyond_microseconds_is_refused(tmp_path):
    msgs, _ = make_messages(20, t0_sod=3600.0 * 5)
    msgs["sub"] = 2e6
    p = tmp_path / "flight.G"
    write_g(p, msgs)
    with pytest.raises(InputError) as exc:
        read_gfile(p)
    assert exc.value.column == "sub_second"


def test_g_file_in_mgal_is_converted_like_a_csv(tmp_path):
    msgs, _ = make_messages(200, t0_sod=3600.0 * 5 + 17.3)
    root = tmp_path / "s"
    d = root / "flights" / "F1"
    d.mkdir(parents=True)
    write_g(d / "flight.G", msgs, scale=1e-5)                   # accelerations written in mGal
    df_si = read_gfile(d / "flight.G", scale_to_ms2=1e-5)
    t = df_si["time"].to_numpy()
    pd.DataFrame({"time": np.round(np.arange(t[0] - 1, t[-1] + 1, 0.1), 2), "lat": 62.0, "lon": 158.0, "h": 3000.0,
                  "vu": 0.0}).to_csv(d / "gnss.csv", index=False)
    (root / "lines.csv").write_text(f"line,flight,t_start,t_end,kind\nL1,F1,{t[5]:.2f},{t[-5]:.2f},main\n")
    (root / "survey.toml").write_text('[survey]\nname = "g"\n[gravimeter]\ntime_offset_s = 0.0\n')
    with pytest.warns(UserWarning, match=r"f_z read as mGal \(median 98[0-9]{4}"):
        s = read_survey(root)
    np.testing.assert_allclose(s.flights["F1"].gravimeter["f_z"], interleave(msgs["fz1"], msgs["fz2"]), rtol=1e-12)


@pytest.mark.parametrize("lost", [[60], [60, 61, 62]])
def test_message_after_lost_ones_keeps_its_own_interval(tmp_path, lost):
    msgs, t_end = make_messages(200, t0_sod=3600.0 * 5 + 17.3)
    keep = np.setdiff1d(np.arange(200), lost)
    p = tmp_path / "flight.G"
    write_g(p, msgs.iloc[keep])
    df = read_gfile(p)
    centres = interleave(t_end[keep] - 0.75 * T_MSG, t_end[keep] - 0.25 * T_MSG)
    np.testing.assert_allclose(df["time"], centres, rtol=0, atol=2e-4)   # sub-second rounded to 1e-4 s
