"""Realistic simulator regimes (docs/SIMULATOR.md): the 2 Hz test line, platform gravimeter sampling,
heights-only GNSS, draped flight, deterministic auxiliary streams, the original presets unchanged.

Checks against independent things: the real line's noise table (/work/shared/notes/
real-line-noise-spectrum.md), app.core.geodesy applied to the written files, harmonica's point-mass
forward model, numerical quadrature, the bundled sample survey.
"""

from __future__ import annotations

import gzip
import io
import json
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.integrate import quad
from scipy.interpolate import CubicSpline, PPoly
from scipy.signal import welch

from app.core.geodesy import eotvos_mgal, normal_gravity_mgal, radii_of_curvature_m
from app.simulate import PRESETS, simulate_survey
from app.simulate.sensors import LaggedResponse, LaggedResponseN, boxcar_pp, fir_gain, fir_pp

REPO = Path(__file__).resolve().parents[2]
NOISE_OFF = dict(grav_noise_mgal_rthz=0.0, drift_rate_mgal_h=(0.0, 0.0), drift_offset_std_mgal=0.0,
                 drift_rw_mgal_rth=0.0, sigma_vu_cms=0.0, sigma_vh_cms=0.0, sigma_pos_m=0.0,
                 sigma_h_m=0.0, horizontal_noise_ms2=0.0)
MINI_SMALL = dict(n_main=2, main_length_km=20.0, n_tie=1, n_repeat=0, n_flights=1, grid_margin_km=4.0)

#: the real 2 Hz test line: band RMS of z per pass (mGal), Welch periodogram of each pass
REAL_BANDS = {
    (0.02, 0.05): (60, 44, 63, 81),
    (0.05, 0.1): (533, 609, 552, 578),
    (0.1, 0.2): (2681, 2207, 2898, 2231),
    (0.2, 0.5): (38102, 35026, 34605, 34397),
    (0.5, 1.0): (10703, 10393, 9586, 10403),
}
REAL_STD = {"f_z": (64145, 61837, 64458, 59972), "hdd": (74094, 70215, 71098, 67265),
            "z": (40872, 36800, 34624, 33530)}


def _read(p: Path, name: str, flight: str) -> pd.DataFrame:
    f = p / "flights" / flight / f"{name}.csv"
    return pd.read_csv(f if f.exists() else f.with_suffix(".csv.gz"))


# ---------------------------------------------------------------- the 2 Hz test line

@pytest.fixture(scope="module")
def testline(tmp_path_factory):
    return simulate_survey("testline-2hz", tmp_path_factory.mktemp("sim") / "testline", seed=1)


def _testline_z(p: Path) -> dict[str, dict]:
    """Per pass, from the files only: z = f_z − ḧ − γ + E at the GNSS epochs (the gravimeter's point
    samples share the 2 Hz stamps), ḧ the second central difference of the heights, the Eötvös
    velocities from central differences of the positions; and the residual z − dg_true."""
    model = tomllib.loads((p / "survey.toml").read_text())["survey"]["normal_gravity"]
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    out = {}
    for fl in truth.flight.unique():
        g, n = _read(p, "gravimeter", fl), _read(p, "gnss", fl)
        t = n.time.to_numpy()
        dt = 0.5
        lat, lon, h = n.lat.to_numpy(), n.lon.to_numpy(), n.h.to_numpy()
        c = slice(1, -1)
        hdd = (h[2:] - 2 * h[1:-1] + h[:-2]) / dt ** 2
        r_m, r_n = radii_of_curvature_m(lat[c])
        ve = np.deg2rad(lon[2:] - lon[:-2]) / (2 * dt) * (r_n + h[c]) * np.cos(np.deg2rad(lat[c]))
        vn = np.deg2rad(lat[2:] - lat[:-2]) / (2 * dt) * (r_m + h[c])
        key = np.round(t[c], 3)
        fz = pd.Series(g.f_z.to_numpy(), index=np.round(g.time.to_numpy(), 3)).reindex(key).to_numpy()
        z = (fz - hdd) * 1e5 - normal_gravity_mgal(lat[c], h[c], model) + eotvos_mgal(lat[c], h[c], ve, vn)
        frame = pd.DataFrame({"f_z": fz * 1e5, "hdd": hdd * 1e5, "z": z}, index=key)
        for line, d in truth[truth.flight == fl].groupby("line"):
            sel = frame.reindex(np.round(d.time.to_numpy(), 3))
            assert sel.notna().all().all(), line
            out[line] = {"f_z": sel.f_z.to_numpy(), "hdd": sel.hdd.to_numpy(), "z": sel.z.to_numpy(),
                         "res": sel.z.to_numpy() - d.dg_true_mgal.to_numpy()}
    return out


def _band_rms(x: np.ndarray, fs: float = 2.0) -> dict:
    f, P = welch(x - x.mean(), fs=fs, nperseg=512, window="hann", detrend="constant")
    df = f[1] - f[0]
    return {b: float(np.sqrt(P[(f >= b[0]) & (f < b[1])].sum() * df)) for b in REAL_BANDS}


def test_testline_residual_spectrum_matches_real_line(testline):
    """Band RMS (Welch, per pass) of the z residual within a factor 3 of the real line in every band
    0.02–1 Hz, per pass and on average; f_z, ḧ and z of the size the real line shows."""
    passes = _testline_z(Path(testline))
    assert sorted(passes) == ["R1-1", "R1-2", "R1-3", "R1-4"]
    bands = {line: _band_rms(d["res"]) for line, d in passes.items()}
    for b, real in REAL_BANDS.items():
        sim = np.array([bands[line][b] for line in passes])
        ratio = sim / np.mean(real)
        assert np.all((ratio > 1 / 3) & (ratio < 3)), (b, sim.round(1), real)
        assert 1 / 2 < sim.mean() / np.mean(real) < 2, (b, sim.round(1), real)
    # the noise wall: the residual's band RMS grows by > 2 orders of magnitude from 0.02-0.05 to 0.2-0.5 Hz
    assert all(bands[ln][(0.2, 0.5)] > 100 * bands[ln][(0.02, 0.05)] for ln in passes)
    for key, real in REAL_STD.items():
        sim = np.array([np.std(d[key]) for d in passes.values()])
        assert np.all(np.abs(np.log(sim / np.mean(real))) < np.log(1.6)), (key, sim.round(0), real)
    # the mismatch: residual ≈ half the aircraft acceleration (real line 0.47-0.55)
    frac = np.array([np.std(d["z"]) / np.std(d["hdd"]) for d in passes.values()])
    assert np.all((frac > 0.35) & (frac < 0.65)), frac


def test_testline_geometry_and_files(testline):
    p = Path(testline)
    cfg = PRESETS["testline-2hz"]
    lines = pd.read_csv(p / "lines.csv")
    assert list(lines.kind) == ["repeat"] * 4 and set(lines.track) == {"R1"} and lines.flight.nunique() == 1
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    assert set(truth.terrain) == {"plain"} and truth.R_true_cm2s2.isna().all()
    headings, speeds = [], []
    for line, d in truth.groupby("line", sort=True):
        e = d.easting_km.to_numpy()
        assert abs(abs(e[-1] - e[0]) - 40.0) < 0.1 and np.ptp(d.northing_km) < 1e-6   # one 40 km track
        headings.append(np.sign(e[-1] - e[0]))
        speeds.append(np.abs(np.diff(e)).mean() * 1000.0 / 0.5)
        # draped 330 ± 45 m (+ the turbulence's metre-level motion)
        assert 280 < d.h_true_m.min() < 290 and 370 < d.h_true_m.max() < 380, line
        # anomaly: along-line std 8.5 mGal, hardly any power at wavelengths < 6 km
        dg = d.dg_true_mgal.to_numpy() - d.dg_true_mgal.mean()
        assert abs(np.std(dg) - 8.5) < 0.2
        k = np.fft.rfftfreq(dg.size, speeds[-1] * 0.5 / 1000.0)
        P = np.abs(np.fft.rfft(dg * np.hanning(dg.size))) ** 2
        assert P[k > 1 / 6.0].sum() < 0.01 * P[1:].sum()
    assert headings == [1, -1, 1, -1]                               # alternating directions
    assert min(speeds) > 54.9 and max(speeds) < 66.1 and max(speeds) - min(speeds) > 10
    for fl in lines.flight.unique():
        g, n = _read(p, "gravimeter", fl), _read(p, "gnss", fl)
        assert list(n.columns) == ["time", "lat", "lon", "h"]     # heights only, apron included
        assert list(g.columns) == ["time", "f_z", "f_x", "f_y"]
        for df in (g, n):                                         # stamps on exact multiples of 0.5 s
            assert np.array_equal(df.time * 2, np.round(df.time * 2))
            assert np.median(np.diff(df.time)) == 0.5
    toml = tomllib.loads((p / "survey.toml").read_text())
    assert toml["gravimeter"]["tau_s"] == 0.0 and toml["gravimeter"]["rate_hz"] == 2.0
    tj = json.loads((p / "truth" / "truth.json").read_text())
    assert tj["tau_s"] == cfg.tau_true_s == 0.25 and tj["tau_declared_s"] == 0.0
    reg = tj["regime"]
    assert reg["gravimeter"]["sampling"] == "point" and reg["gravimeter"]["internal_filter"]["boxcars"] == 2
    assert reg["gnss"]["velocity_columns"] is False and reg["drape"]["amp_m"] == 45.0


def test_heights_only_gnss_writes_four_columns(tmp_path):
    p = simulate_survey("heights-only-5hz", tmp_path / "h", seed=4, **MINI_SMALL)
    with gzip.open(p / "flights" / "F01" / "gnss.csv.gz", "rt") as fh:
        assert fh.readline().strip() == "time,lat,lon,h"
    n = _read(p, "gnss", "F01")
    assert np.allclose(np.diff(n.time)[np.diff(n.time) < 1], 0.2)
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    # the height error: 7 mm white + 2.5 cm Gauss-Markov (60 s) around the true height
    err = n.set_index(np.round(n.time, 3)).h.reindex(np.round(truth.time, 3)).to_numpy() - truth.h_true_m.to_numpy()
    assert 0.012 < np.std(err) < 0.045
    d = np.diff(err)                                       # white part dominates epoch-to-epoch changes
    assert 0.007 * np.sqrt(2) * 0.8 < np.std(d) < 0.007 * np.sqrt(2) * 1.3


def test_writer_rejects_missing_requested_column(tmp_path):
    from app.io.survey_writer import write_survey
    g = pd.DataFrame({"time": [0.0, 0.5], "f_z": [9.8, 9.8]})
    n = pd.DataFrame({"time": [0.0, 0.5], "lat": [0.0, 0.0], "lon": [0.0, 0.0], "h": [1.0, 1.0]})
    lines = pd.DataFrame({"line": ["L1"], "flight": ["F01"], "t_start": [0.0], "t_end": [0.5], "kind": ["main"]})
    with pytest.raises(ValueError, match="vu"):
        write_survey(tmp_path / "x", {"survey": {"name": "x"}}, lines, {"F01": (g, n)},
                     gnss_columns=["time", "lat", "lon", "h", "vu"])
    out = write_survey(tmp_path / "y", {"survey": {"name": "y"}}, lines, {"F01": (g, n.assign(vu=0.0))},
                       gnss_columns=["time", "lat", "lon", "h"])
    assert (out / "flights" / "F01" / "gnss.csv").read_text().splitlines()[0] == "time,lat,lon,h"


# ---------------------------------------------------------------- platform gravimeter sampling

def test_fir_and_lag_against_quadrature():
    """The exact FIR (boxcar cascade) and the lag of any degree against numerical integration and
    the analytic response of a sinusoid."""
    rng = np.random.default_rng(0)
    x = np.arange(0.0, 60.0, 0.01)
    cs = CubicSpline(x, np.cumsum(rng.standard_normal(x.size)) * 0.01)
    pp = PPoly(cs.c, cs.x)
    W = 0.5
    b1 = boxcar_pp(pp, W)
    b2 = fir_pp(pp, 2, W)
    for t in (20.0, 20.004, 33.3333, 41.005):
        brk = x[(x > t - W) & (x < t + W)]
        m1 = quad(pp, t - W / 2, t + W / 2, points=brk[np.abs(brk - t) < W / 2], limit=200)[0] / W
        assert abs(b1(t) - m1) < 1e-12
        # two boxcars = triangular window of half-width W
        m2 = quad(lambda s, t=t: pp(s) * (1 - abs(s - t) / W) / W, t - W, t + W, points=np.r_[brk, t], limit=400,
                  epsabs=1e-14)[0]
        assert abs(b2(t) - m2) < 1e-10
    # sinusoid: gain sinc(fW)^n, zero phase; then the lag, analytic
    w = 2 * np.pi * 0.4
    cs = CubicSpline(x, np.sin(w * x))
    f2 = fir_pp(PPoly(cs.c, cs.x), 2, W)
    t = np.linspace(30.0, 55.0, 301)
    g = fir_gain(0.4, 2, W)
    assert np.max(np.abs(f2(t) - g * np.sin(w * t))) < 1e-9
    tau, k = 0.25, 1.0002
    lr = LaggedResponseN(f2, tau, k)
    exact = g * (k * np.sin(w * t) - tau * w * np.cos(w * t)) / (k ** 2 + tau ** 2 * w ** 2)
    assert np.max(np.abs(lr.y(t) - exact)) < 1e-9
    # on cubic input it is the original solver
    old = LaggedResponse(PPoly(cs.c, cs.x), tau, k)
    new = LaggedResponseN(PPoly(cs.c, cs.x), tau, k)
    assert np.max(np.abs(old.y(t) - new.y(t))) < 1e-12
    assert np.max(np.abs(old.interval_means(t) - new.interval_means(t))) < 1e-12


@pytest.fixture(scope="module")
def platform_point(tmp_path_factory):
    """10 Hz point samples behind the sinc² filter (two boxcars of 0.1 s), no lag, no noise, no
    anomaly, draped (so the true height is in truth/ at full precision)."""
    out = tmp_path_factory.mktemp("sim") / "pp"
    return simulate_survey("platform-10hz-point", out, seed=7, scale_true=1.0, mountain_std_mgal=0.0,
                           plain_std_mgal=0.0, drape_amp_m=50.0, **NOISE_OFF, **MINI_SMALL)


def test_point_samples_are_filtered_acceleration_at_the_stamps(platform_point):
    """Independent evaluation: two boxcars of width W applied to the vertical acceleration ḧ equal
    the second difference of the true height with step W, ``(h(t+W) − 2h(t) + h(t−W))/W²``; with the
    anomaly off the sample at stamp t is that plus γ − E at t."""
    p = Path(platform_point)
    model = tomllib.loads((p / "survey.toml").read_text())["survey"]["normal_gravity"]
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    g = _read(p, "gravimeter", "F01")
    n = _read(p, "gnss", "F01")
    n = n.set_index(np.round(n.time.to_numpy(), 3))
    assert np.array_equal(g.time * 10, np.round(g.time * 10))      # exact multiples of 0.1 s
    fz = pd.Series(g.f_z.to_numpy(), index=np.round(g.time, 3))
    W = PRESETS["platform-10hz-point"].gravimeter_fir_width_s
    assert W == 0.1
    errs, teeth = [], []
    for _, d in truth.groupby("line"):
        h = d.h_true_m.to_numpy()
        t = np.round(d.time.to_numpy(), 3)[1:-1]
        filt = (h[2:] - 2 * h[1:-1] + h[:-2]) / W ** 2
        nn = n.reindex(t)
        lat, hh = nn.lat.to_numpy(), h[1:-1]
        slow = normal_gravity_mgal(lat, hh, model) - eotvos_mgal(lat, hh, nn.ve.to_numpy(), nn.vn.to_numpy())
        got = fz.reindex(t).to_numpy() * 1e5
        errs.append(got - (filt * 1e5 + slow))
        # the unfiltered acceleration (finer differences of the exact height: a(t) within ~1 mGal) differs
        h_fine = CubicSpline(d.time.to_numpy(), h)
        teeth.append(got - (h_fine(t, 2) * 1e5 + slow))
    err = np.concatenate(errs)
    assert np.abs(err).max() < 0.02, np.abs(err).max()
    assert np.std(np.concatenate(teeth)) > 50.0


def test_platform_mean_samples_on_exact_multiples(tmp_path):
    p = simulate_survey("platform-1hz", tmp_path / "p1", seed=2, **MINI_SMALL)
    g = _read(p, "gravimeter", "F01")
    assert np.array_equal(g.time, np.round(g.time)) and np.median(np.diff(g.time)) == 1.0
    tj = json.loads((p / "truth" / "truth.json").read_text())
    assert tj["regime"]["gravimeter"]["sampling"] == "mean" and "internal_filter" not in tj["regime"]["gravimeter"]
    assert tj["tau_s"] == tj["tau_declared_s"] == 0.0
    assert 9.7 < g.f_z.median() < 9.9


# ---------------------------------------------------------------- draped flight

@pytest.fixture(scope="module")
def draped(tmp_path_factory):
    return simulate_survey("draped", tmp_path_factory.mktemp("sim") / "draped", seed=5, **MINI_SMALL)


def test_draped_truth_is_harmonica_at_the_actual_height(draped):
    """dg_true (interval mean = value at the interval midpoint) equals harmonica's point-mass forward
    model of the recorded sources at the actual position and height; the nominal-height grid does
    not (the drape moves the aircraft ±50 m through the field's vertical gradient)."""
    import harmonica as hm
    import xarray as xr
    from scipy.interpolate import RegularGridInterpolator

    p = Path(draped)
    tj = json.loads((p / "truth" / "truth.json").read_text())
    src = tj["field"]["sources"]
    e0, n0 = tj["survey_centre_km"]
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    h0 = PRESETS["draped"].height_m
    grid = xr.open_dataset(p / "truth" / "grid.nc")
    rgi = RegularGridInterpolator((grid.northing_km.values, grid.easting_km.values), grid.dg.values, method="cubic")
    assert grid.attrs["height_m"] == h0
    # draped: over the line windows the height spans 3000 ± 50 m (+ the turbulence's metre-level motion)
    assert -56.0 < truth.h_true_m.min() - h0 < -44.0 and 44.0 < truth.h_true_m.max() - h0 < 56.0
    for line, d in truth.groupby("line"):
        assert np.ptp(d.h_true_m) > 20.0, line
        idx = np.linspace(1, len(d) - 1, 25).astype(int)                    # a few points per line
        def mid(c, d=d, idx=idx):
            return 0.5 * (d[c].to_numpy()[idx - 1] + d[c].to_numpy()[idx])

        e, n, h = mid("easting_km"), mid("northing_km"), mid("h_true_m")
        g = hm.point_gravity(((e - e0) * 1000.0, (n - n0) * 1000.0, h), (src["x_m"], src["y_m"], src["z_m"]),
                             src["mass_kg"], field="g_z") - src["offset_mgal"]
        assert np.abs(g - d.dg_true_mgal.to_numpy()[idx]).max() < 0.001, line
        # at the nominal height the bicubic grid agrees with the sources to < 0.05 mGal ...
        g0 = hm.point_gravity(((e - e0) * 1000.0, (n - n0) * 1000.0, np.full(e.size, h0)),
                              (src["x_m"], src["y_m"], src["z_m"]), src["mass_kg"], field="g_z") - src["offset_mgal"]
        assert np.abs(rgi(np.column_stack([n, e])) - g0).max() < 0.05, line
    # ... but ignoring the drape would be wrong by much more
    mid_pts = truth.iloc[1:]
    off = np.abs(rgi(mid_pts[["northing_km", "easting_km"]].to_numpy()) - mid_pts.dg_true_mgal.to_numpy())
    assert off.max() > 0.5


def test_draped_motion_is_in_the_files(draped):
    """The GNSS heights and vertical velocities follow the drape."""
    p = Path(draped)
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    n = _read(p, "gnss", "F01")
    n = n.set_index(np.round(n.time.to_numpy(), 3))
    d = truth[truth.line == truth.line.iloc[0]]
    h = n.h.reindex(np.round(d.time, 3)).to_numpy()
    assert np.abs(h - d.h_true_m.to_numpy()).max() < 0.2                     # 3 cm white noise
    assert np.ptp(d.h_true_m) > 20.0
    # the true vertical velocity is the derivative of the true (draped) height; the file's vu is it + noise
    dh = np.gradient(d.h_true_m.to_numpy(), 0.1)[1:-1]
    assert np.abs(d.vu_true_ms.to_numpy()[1:-1] - dh).max() < 0.01
    vu = n.vu.reindex(np.round(d.time, 3)).to_numpy()[1:-1]
    assert np.std(vu - dh) < 0.05 and np.std(vu) > 0.5


def test_repeat_passes_at_their_own_heights(tmp_path):
    """``repeat_height_offsets_m``: each repeat pass flies its offset above the other lines (here
    without a drape), the GNSS heights follow, and dg_true is the sources' field at that height."""
    import harmonica as hm

    p = simulate_survey("tiny", tmp_path / "rh", seed=2, **{**MINI_SMALL, "n_repeat": 2, "repeat_length_km": 10.0},
                        repeat_height_offsets_m=(-300.0, 250.0))
    tj = json.loads((p / "truth" / "truth.json").read_text())
    assert tj["regime"]["repeat_heights"]["offsets_m"] == [-300.0, 250.0]
    src, (e0, n0) = tj["field"]["sources"], tj["survey_centre_km"]
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    h0 = PRESETS["tiny"].height_m
    mean_h = truth.groupby("line").h_true_m.mean() - h0
    assert abs(mean_h["R1-1"] + 300.0) < 10 and abs(mean_h["R1-2"] - 250.0) < 10
    assert mean_h.drop(["R1-1", "R1-2"]).abs().max() < 10
    n = _read(p, "gnss", "F01")
    n = n.set_index(np.round(n.time.to_numpy(), 3))
    for line, d in truth.groupby("line"):
        assert np.abs(n.h.reindex(np.round(d.time, 3)).to_numpy() - d.h_true_m.to_numpy()).max() < 0.2, line
        idx = np.linspace(1, len(d) - 1, 15).astype(int)
        mid = lambda c: 0.5 * (d[c].to_numpy()[idx - 1] + d[c].to_numpy()[idx])  # noqa: E731, B023
        g = hm.point_gravity(((mid("easting_km") - e0) * 1000.0, (mid("northing_km") - n0) * 1000.0, mid("h_true_m")),
                             (src["x_m"], src["y_m"], src["z_m"]), src["mass_kg"], field="g_z") - src["offset_mgal"]
        assert np.abs(g - d.dg_true_mgal.to_numpy()[idx]).max() < 0.001, line


# ---------------------------------------------------------------- determinism and the original presets

def test_auxiliary_streams_do_not_depend_on_pythonhashseed(tmp_path):
    """Coloured and position-derived GNSS velocity errors (and the coloured height error) come from
    SeedSequence([seed, tag, flight]): the same seed gives the same files in processes with different
    string-hash randomisation."""
    code = ("import sys; from app.simulate import simulate_survey; "
            "simulate_survey('tiny', sys.argv[1], seed=21, n_main=1, n_tie=0, main_length_km=6.0, "
            "grid_margin_km=3.0, apron_s=60.0, vu_colored_cms=1.0, vu_from_position_m=0.01, h_colored_m=0.02)")
    outs = []
    for hs in ("1", "2"):
        out = tmp_path / f"s{hs}"
        env = {**os.environ, "PYTHONHASHSEED": hs}
        subprocess.run([sys.executable, "-c", code, str(out)], check=True, env=env, cwd=REPO, timeout=120)
        outs.append(out)
    a, b = (o / "flights" / "F01" / "gnss.csv" for o in outs)
    assert a.read_bytes() == b.read_bytes()
    ref = simulate_survey("tiny", tmp_path / "ref", seed=21, n_main=1, n_tie=0, main_length_km=6.0,
                          grid_margin_km=3.0, apron_s=60.0)
    assert (ref / "flights" / "F01" / "gnss.csv").read_bytes() != a.read_bytes()     # the options act


def test_omolon_mini_sample_reproduced_byte_for_byte(tmp_path):
    """The bundled sample is omolon-mini seed 1: the new options leave it unchanged (data files byte for
    byte after decompression; truth.json up to the config keys added since; parquet tables value for
    value, their metadata naming the writer's library versions)."""
    import xarray as xr

    sample = REPO / "sample_surveys" / "omolon-mini"
    if not sample.exists():
        pytest.skip("no bundled sample")
    p = simulate_survey("omolon-mini", tmp_path / "om", seed=1)
    files = sorted(q.relative_to(sample) for q in sample.rglob("*") if q.is_file())
    assert files == sorted(q.relative_to(p) for q in p.rglob("*") if q.is_file())
    for r in files:
        a, b = (sample / r).read_bytes(), (p / r).read_bytes()
        if r.suffix == ".gz":
            a, b = gzip.decompress(a), gzip.decompress(b)
        if r.name == "truth.json":
            ja, jb = json.loads(a), json.loads(b)
            for k in set(jb["config"]) - set(ja["config"]):
                jb["config"].pop(k)
            assert ja == jb
        elif r.suffix == ".nc":
            assert xr.open_dataset(sample / r).identical(xr.open_dataset(p / r))
        elif a != b and ".csv" in r.suffixes:
            # the same numbers up to the last printed digit: the FFT and BLAS round-off of another
            # machine or numpy may move a handful of 8-decimal values by one unit (30 of 85 406 rows)
            ta, tb = pd.read_csv(io.BytesIO(a)), pd.read_csv(io.BytesIO(b))
            assert list(ta.columns) == list(tb.columns) and len(ta) == len(tb), r
            for c in ta.columns:
                np.testing.assert_allclose(tb[c].to_numpy(float), ta[c].to_numpy(float), rtol=0, atol=1.01e-8,
                                           err_msg=f"{r}: {c}")
        elif r.suffix == ".parquet":
            # a parquet file carries its writer's versions (pandas, pyarrow) in its metadata: a clean
            # install with a newer pandas changed those bytes, not the table
            pd.testing.assert_frame_equal(pd.read_parquet(io.BytesIO(a)), pd.read_parquet(io.BytesIO(b)),
                                          check_exact=True, obj=str(r))
        else:
            assert a == b, r


def test_cli_lists_every_preset():
    out = subprocess.run([sys.executable, "-m", "app.cli", "simulate", "--help"], capture_output=True, text=True,
                         cwd=REPO, timeout=60)
    assert out.returncode == 0
    help_text = " ".join(out.stdout.split())
    for name in PRESETS:
        assert name in help_text, name
