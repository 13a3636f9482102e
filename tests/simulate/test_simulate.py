"""Survey simulator: file format, physical consistency (z = δg), Markov statistics.

Checks against independent things: analytic ODE solutions, app.core.geodesy applied to the
written files, sampling statistics of the known truth.
"""

from __future__ import annotations

import gzip
import json
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.interpolate import CubicSpline, PPoly, RegularGridInterpolator

from app.core.geodesy import eotvos_mgal, normal_gravity_mgal
from app.simulate import PRESETS, SimConfig, simulate_survey
from app.simulate.sensors import LaggedResponse, quadratic_from_means

NOISE_OFF = dict(grav_noise_mgal_rthz=0.0, drift_rate_mgal_h=(0.0, 0.0), drift_offset_std_mgal=0.0,
                 drift_rw_mgal_rth=0.0, sigma_vu_cms=0.0, sigma_vh_cms=0.0, sigma_pos_m=0.0,
                 sigma_h_m=0.0, horizontal_noise_ms2=0.0)
SMALL = dict(n_main=2, main_length_km=20.0, n_tie=1, grid_margin_km=4.0)


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """Noise-free, lag-free tiny survey (turbulence and turns still on)."""
    out = tmp_path_factory.mktemp("sim") / "clean"
    return simulate_survey("tiny", out, seed=3, tau_true_s=0.0, scale_true=1.0, time_offset_s=0.0,
                           **NOISE_OFF, **SMALL)


@pytest.fixture(scope="module")
def lagged(tmp_path_factory):
    """Noise-free, with lag, scale error and time offset."""
    out = tmp_path_factory.mktemp("sim") / "lagged"
    return simulate_survey("tiny", out, seed=4, tau_true_s=2.0, scale_true=1.0 + 2e-4,
                           time_offset_s=0.05, **NOISE_OFF, **SMALL)


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "noisy"
    return simulate_survey("tiny", out, seed=5, episode_rate_per_h=6.0, **SMALL)


# ---------------------------------------------------------------- exact lag solver

def test_lag_matches_analytic_sinusoid():
    tau, k, w = 2.0, 1.0002, 2 * np.pi * 0.3
    x = np.arange(0.0, 60.0, 0.01)
    cs = CubicSpline(x, np.sin(w * x))
    lr = LaggedResponse(PPoly(cs.c, cs.x), tau, k)
    t = np.linspace(40.0, 59.0, 777)          # start-up transient exp(−t/T) gone
    exact = (k * np.sin(w * t) - tau * w * np.cos(w * t)) / (k ** 2 + tau ** 2 * w ** 2)
    assert np.max(np.abs(lr.y(t) - exact)) < 1e-8
    # interval means against the integral of the analytic solution
    e = np.linspace(40.0, 59.0, 500)
    Y = (-k * np.cos(w * e) / w - tau * np.sin(w * e)) / (k ** 2 + tau ** 2 * w ** 2)
    assert np.max(np.abs(lr.interval_means(e) - np.diff(Y) / np.diff(e))) < 1e-8


def test_lag_zero_tau_is_scaled_input():
    x = np.linspace(0, 10, 101)
    cs = CubicSpline(x, x ** 2)
    lr = LaggedResponse(PPoly(cs.c, cs.x), 0.0, 2.0)
    e = np.array([1.0, 3.0, 7.5])
    assert np.allclose(lr.interval_means(e), np.diff(e ** 3 / 3) / np.diff(e) / 2.0)


def test_quadratic_from_means_has_exact_interval_means():
    rng = np.random.default_rng(0)
    t = 100.0 + np.arange(200) * 0.1
    m = np.cumsum(rng.standard_normal(200))
    pp = quadratic_from_means(t, m)
    got = np.diff(pp.antiderivative()(t)) / np.diff(t)
    assert np.max(np.abs(got - m[1:])) < 1e-9


# ---------------------------------------------------------------- file format

def _read(p: Path, name: str, flight: str) -> pd.DataFrame:
    f = p / "flights" / flight / f"{name}.csv"
    return pd.read_csv(f if f.exists() else f.with_suffix(".csv.gz"))


def _blocks(df: pd.DataFrame, max_gap_s: float = 1.0) -> list[pd.DataFrame]:
    """The file's contiguous recordings (apron before, airborne, apron after), split at gaps."""
    cut = np.flatnonzero(np.diff(df.time.to_numpy()) > max_gap_s) + 1
    return [df.iloc[a:b].reset_index(drop=True) for a, b in zip(np.r_[0, cut], np.r_[cut, len(df)])]


def _airborne(df: pd.DataFrame) -> pd.DataFrame:
    return max(_blocks(df), key=len)


def test_directory_has_spec_columns(noisy):
    p = Path(noisy)
    cfg = tomllib.loads((p / "survey.toml").read_text())
    assert cfg["survey"]["crs"] == "EPSG:32657" and cfg["survey"]["normal_gravity"] == "WGS84"
    assert cfg["gravimeter"]["tau_s"] == 2.0 and cfg["gravimeter"]["scale"] == 1.0
    lines = pd.read_csv(p / "lines.csv")
    assert list(lines.columns) == ["line", "flight", "t_start", "t_end", "kind", "track"]
    assert set(lines.kind) == {"main", "tie"}
    for fl, grp in lines.groupby("flight"):
        g = _read(p, "gravimeter", fl)
        n = _read(p, "gnss", fl)
        assert list(g.columns) == ["time", "f_z", "f_x", "f_y"]
        assert list(n.columns) == ["time", "lat", "lon", "h", "vu", "ve", "vn", "sigma_v"]
        assert np.all(np.diff(g.time) > 0) and np.all(np.diff(n.time) > 0)
        # GNSS on exact multiples of 0.1 s; gravimeter stamps rounded to 1 ms and not uniform
        assert np.allclose(n.time * 10, np.round(n.time * 10), atol=1e-6)
        assert np.allclose(g.time * 1000, np.round(g.time * 1000), atol=1e-5)
        assert len(np.unique(np.round(np.diff(g.time), 3))) >= 2
        assert 9.7 < g.f_z.median() < 9.9                 # up positive, ≈ +g at rest
        assert len(_blocks(g)) == len(_blocks(n)) == 3    # apron, airborne, apron
        for b in _blocks(g):
            assert abs((len(b) - 1) / (b.time.iloc[-1] - b.time.iloc[0]) - 18.24) < 0.01
        # line windows inside the airborne part of both files, with margin for filters
        g, n = _airborne(g), _airborne(n)
        assert grp.t_start.min() > g.time.iloc[0] + 20 and grp.t_end.max() < g.time.iloc[-1] - 5
        assert grp.t_start.min() >= n.time.iloc[0] and grp.t_end.max() <= n.time.iloc[-1]
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    for c in ["line", "flight", "kind", "time", "easting_km", "northing_km", "dg_true_mgal", "terrain",
              "state_true", "Q_true_mgal2", "R_true_cm2s2"]:
        assert c in truth.columns
    assert set(truth.terrain) <= {"mountain", "plain"}
    import xarray as xr
    grid = xr.open_dataset(p / "truth" / "grid.nc")
    assert grid["dg"].dims == ("northing_km", "easting_km") and grid.attrs["crs"] == "EPSG:32657"
    assert np.diff(grid.easting_km.values).max() <= 0.5 + 1e-9
    tj = json.loads((p / "truth" / "truth.json").read_text())
    assert tj["tau_s"] == 2.0 and tj["scale"] == PRESETS["tiny"].scale_true


def test_compressed_output_and_atomic_replace(tmp_path):
    out = tmp_path / "s"
    out.mkdir()
    (out / "stale.txt").write_text("old")
    simulate_survey("tiny", out, seed=1, compress=True, n_main=1, n_tie=0, main_length_km=8.0,
                    grid_margin_km=3.0)
    assert not (out / "stale.txt").exists()
    f = out / "flights" / "F01" / "gnss.csv.gz"
    with gzip.open(f, "rt") as fh:
        assert fh.readline().strip() == "time,lat,lon,h,vu,ve,vn,sigma_v"
    assert not [q for q in tmp_path.iterdir() if q.name.startswith(".")]


def test_unknown_override_rejected(tmp_path):
    with pytest.raises(TypeError):
        simulate_survey("tiny", tmp_path / "x", no_such_parameter=1)
    assert isinstance(PRESETS["omolon"], SimConfig)
    om = PRESETS["omolon"]
    assert om.n_main + om.n_tie == 74 and om.n_tie == 17 and om.n_flights == 12


# ---------------------------------------------------------------- physics: z = δg

def _z_from_files(p: Path, flight: str, tau: float, k: float, offset: float):
    """z per GNSS epoch from the written files with app.core.geodesy.

    f̄ over (t_{k−1}, t_k]: samples are interval means, so the cumulative integral is exact at the
    sample edges (recovered from a linear fit of the stamps), then a cubic spline of it; the lag
    is undone exactly on the interval: f̄ = τ·Δf'/Δt + k·mean(f').
    """
    g = _airborne(_read(p, "gravimeter", flight))
    n = _airborne(_read(p, "gnss", flight))
    model = tomllib.loads((p / "survey.toml").read_text())["survey"]["normal_gravity"]
    j = np.arange(len(g))
    a1, a0 = np.polyfit(j, g.time.to_numpy() - offset, 1)
    edges = a0 - a1 / 2 + a1 * np.arange(len(g) + 1)
    F = CubicSpline(edges, np.concatenate([[0.0], np.cumsum(g.f_z.to_numpy() * np.diff(edges))]))
    tk = n.time.to_numpy()
    dt = np.diff(tk)
    fbar = (tau * np.diff(F(tk, 1)) + k * np.diff(F(tk))) / dt
    dv = np.diff(n.vu.to_numpy()) / dt
    lat, h = n.lat.to_numpy()[1:], n.h.to_numpy()[1:]
    z = (fbar - dv) * 1e5 - normal_gravity_mgal(lat, h, model) \
        + eotvos_mgal(lat, h, n.ve.to_numpy()[1:], n.vn.to_numpy()[1:])
    return pd.Series(z, index=np.round(tk[1:], 1))


def _line_errors(p: Path, tau, k, offset, kernel):
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    zs = {fl: _z_from_files(p, fl, tau, k, offset) for fl in truth.flight.unique()}
    out = {}
    for line, d in truth[truth.kind == "main"].groupby("line"):
        err = zs[d.flight.iloc[0]].reindex(np.round(d.time.to_numpy(), 1)).to_numpy() - d.dg_true_mgal.to_numpy()
        assert np.isfinite(err).all()
        out[line] = (np.std(err), np.convolve(err, kernel, "valid"))
    return out


def test_z_equals_true_anomaly_without_lag(clean):
    errs = _line_errors(Path(clean), 0.0, 1.0, 0.0, np.ones(1000) / 1000.0)   # 100 s moving average
    for line, (raw, ma) in errs.items():
        assert raw > 0.1                     # the motion is there (not a trivial pass)
        assert np.max(np.abs(ma)) < 0.05, line


def test_z_equals_true_anomaly_with_lag_scale_offset(lagged):
    tj = json.loads((Path(lagged) / "truth" / "truth.json").read_text())
    w = np.blackman(1001)
    errs = _line_errors(Path(lagged), tj["tau_s"], tj["scale"], tj["time_offset_s"], w / w.sum())
    for line, (_, ma) in errs.items():
        assert np.max(np.abs(ma)) < 0.02, line
    # ignoring the scale error costs (k−1)·f ≈ 196 mGal: the test can fail
    errs_bad = _line_errors(Path(lagged), tj["tau_s"], 1.0, tj["time_offset_s"], w / w.sum())
    assert all(np.abs(ma).max() > 100 for _, ma in errs_bad.values())


def test_z_equals_true_anomaly_kalgoorlie_helmert(tmp_path):
    """Southern hemisphere, Helmert 1901 normal gravity, slower aircraft."""
    p = simulate_survey("kalgoorlie", tmp_path / "k", seed=6, tau_true_s=0.0, scale_true=1.0, time_offset_s=0.0,
                        n_main=2, n_tie=0, n_repeat=0, n_flights=1, main_length_km=15.0, grid_margin_km=4.0,
                        **NOISE_OFF)
    assert tomllib.loads((p / "survey.toml").read_text())["survey"]["normal_gravity"] == "Helmert1901"
    w = np.blackman(1001)
    errs = _line_errors(Path(p), 0.0, 1.0, 0.0, w / w.sum())
    assert len(errs) == 2
    for line, (_, ma) in errs.items():
        assert np.max(np.abs(ma)) < 0.02, line


def test_same_seed_same_survey(tmp_path):
    kw = dict(n_main=1, n_tie=0, main_length_km=6.0, grid_margin_km=3.0)
    calls = []
    a = simulate_survey("tiny", tmp_path / "a", seed=11, progress=lambda s, f, i: calls.append((s, f)), **kw)
    b = simulate_survey("tiny", tmp_path / "b", seed=11, **kw)
    c = simulate_survey("tiny", tmp_path / "c", seed=12, **kw)
    fa, fb, fc = (q / "flights" / "F01" / "gravimeter.csv" for q in (a, b, c))
    assert fa.read_bytes() == fb.read_bytes() != fc.read_bytes()
    assert calls[0][1] == 0.0 and calls[-1] == ("done", 1.0)
    assert all(0.0 <= f <= 1.0 for _, f in calls) and [f for _, f in calls] == sorted(f for _, f in calls)


def test_eotvos_alternates_and_motion_is_realistic(clean):
    p = Path(clean)
    n = _read(p, "gnss", "F01")
    lines = pd.read_csv(p / "lines.csv")
    for _, ln in lines[lines.kind == "main"].iterrows():
        s = n[(n.time >= ln.t_start) & (n.time <= ln.t_end)]
        E = eotvos_mgal(s.lat, s.h, s.ve, s.vn)
        assert 400 < abs(E.mean()) < 900
        assert np.ptp(np.hypot(s.ve, s.vn)) < 0.2          # straight, constant speed on the window
        a = np.diff(s.vu) / 0.1
        assert 0.05 < np.std(a) < 1.5
        assert np.ptp(s.h) < 40
    es = [np.sign(eotvos_mgal(*n[(n.time >= r.t_start) & (n.time <= r.t_end)][["lat", "h", "ve", "vn"]].T.values).mean())
          for _, r in lines[lines.kind == "main"].iterrows()]
    assert es[0] != es[1]


def test_truth_follows_grid_interpolant(clean):
    import xarray as xr
    p = Path(clean)
    grid = xr.open_dataset(p / "truth" / "grid.nc")
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    rgi = RegularGridInterpolator((grid.northing_km.values, grid.easting_km.values), grid.dg.values, method="cubic")
    # truth is the interval mean ≈ value at the interval midpoint (5 m back along the track)
    d = truth[truth.line == "M001"]
    ve = np.gradient(d.easting_km.to_numpy(), 0.1)
    vn = np.gradient(d.northing_km.to_numpy(), 0.1)
    pts = np.column_stack([d.northing_km - 0.05 * vn, d.easting_km - 0.05 * ve])
    assert np.max(np.abs(rgi(pts) - d.dg_true_mgal.to_numpy())) < 0.05
    assert d.dg_true_mgal.std() > 1.0


def test_gnss_noise_matches_recorded_R(noisy):
    p = Path(noisy)
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    n = _read(p, "gnss", "F01").set_index(np.round(_read(p, "gnss", "F01").time, 1))
    d = truth.set_index(np.round(truth.time, 1))
    r_cm = (n.vu.reindex(d.index).to_numpy() - d.vu_true_ms.to_numpy()) * 100.0
    for R in np.unique(np.round(d.R_true_cm2s2, 6)):
        m = np.isclose(d.R_true_cm2s2.to_numpy(), R)
        if m.sum() < 500:
            continue
        v = np.var(r_cm[m])
        assert abs(v / R - 1) < 5 * np.sqrt(2 / m.sum()) + 0.02, (R, v)


# ---------------------------------------------------------------- Markov preset

@pytest.fixture(scope="module")
def markov(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "markov"
    return simulate_survey("markov", out, seed=2, n_main=8, main_length_km=100.0, n_flights=2)


def test_markov_statistics(markov):
    p = Path(markov)
    assert tomllib.loads((p / "survey.toml").read_text())["processing"]["m"] == 1
    tj = json.loads((p / "truth" / "truth.json").read_text())["markov"]
    assert tj["Q_mgal2"] == [0.0414, 0.3533] and tj["R_cm2s2"] == [pytest.approx(1.6787)]
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    assert truth.line.nunique() == 8 and truth.groupby("line").size().min() >= 10000
    counts = np.zeros((2, 2))
    for s in (0, 1):
        d = np.concatenate([np.diff(g.dg_true_mgal.to_numpy())[g.state_true.to_numpy()[1:] == s]
                            for _, g in truth.groupby("line")])
        assert d.size > 2000
        Q = tj["Q_mgal2"][s]
        assert abs(d.var() / Q - 1) < 5 * np.sqrt(2 / d.size), (s, d.var())
        assert np.allclose(truth.Q_true_mgal2[truth.state_true == s], Q)
    for _, g in truth.groupby("line"):
        st = g.state_true.to_numpy()
        blocks = st[::100]
        assert all(len(np.unique(st[i:i + 100])) == 1 for i in range(0, st.size - 1, 100))
        np.add.at(counts, (blocks[:-1], blocks[1:]), 1)
    P = counts / counts.sum(axis=1, keepdims=True)
    assert np.allclose(P, tj["transition_empirical"], atol=1e-12)
    # spatially coherent: neighbouring lines mostly share the state at the same easting
    agree = []
    lines = sorted(truth.line.unique())
    for a, b in zip(lines[:-1], lines[1:]):
        A, B = truth[truth.line == a], truth[truth.line == b]
        sb = np.interp(A.easting_km, np.sort(B.easting_km), B.state_true.to_numpy()[np.argsort(B.easting_km)])
        agree.append(np.mean(np.round(sb) == A.state_true.to_numpy()))
    assert np.mean(agree) > 0.85
    # GNSS noise R = 1.6787 (cm/s)² without episodes
    n = pd.concat([_read(p, "gnss", f) for f in truth.flight.unique()])
    r = (n.set_index(np.round(n.time, 1)).vu.reindex(np.round(truth.time, 1)).to_numpy()
         - truth.vu_true_ms.to_numpy()) * 100
    assert abs(np.var(r) / 1.6787 - 1) < 0.03


def test_noisy_survey_error_budget(noisy):
    """With noise on, a 100 s FIR of z (true τ, k, offset) is within a few mGal of δg + drift.

    Expected from white GNSS velocity noise σ = 1.3 cm/s alone: ≈ 2 mGal (∫(2πf)² S_r over
    |f| < 0.01 Hz); the scale error ignored would give ≈ −196 mGal.
    """
    from scipy.signal import filtfilt, firwin

    p = Path(noisy)
    tj = json.loads((p / "truth" / "truth.json").read_text())
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    z = _z_from_files(p, "F01", tj["tau_s"], tj["scale"], tj["time_offset_s"])
    g = _airborne(_read(p, "gravimeter", "F01"))
    z = z[(z.index > g.time.iloc[0] + 1) & (z.index < g.time.iloc[-1] - 1)]
    b = firwin(2001, 1 / 100, fs=10, window="blackman")
    zf = pd.Series(filtfilt(b, [1.0], z.to_numpy()), index=z.index)
    for line, d in truth[truth.kind == "main"].groupby("line"):
        err = zf.reindex(np.round(d.time, 1)).to_numpy() - d.dg_true_mgal.to_numpy() - d.drift_mgal.to_numpy()
        assert abs(err.mean()) < 3.0 and 0.5 < err.std() < 12.0, (line, err.mean(), err.std())


# ---------------------------------------------------------------- parking-place (base) readings

@pytest.fixture(scope="module")
def drifty(tmp_path_factory):
    """No sensor noise, a strong drift (30 mGal/h + random walk), lag, scale error, time offset."""
    out = tmp_path_factory.mktemp("sim") / "drifty"
    kw = {**NOISE_OFF, "drift_rate_mgal_h": (30.0, 30.0), "drift_offset_std_mgal": 5.0,
          "drift_rw_mgal_rth": 0.3}
    return simulate_survey("tiny", out, seed=8, tau_true_s=2.0, scale_true=1.0 + 2e-4, time_offset_s=0.05,
                           **kw, **SMALL)


def _static_readings(p: Path, flight: str, model: str):
    """Per static block, from the files only: (block mid time, mean f_z·1e5 − γ, mean γ) (mGal)."""
    g, n = _read(p, "gravimeter", flight), _read(p, "gnss", flight)
    out = []
    for gb, nb in zip(_blocks(g), _blocks(n)):
        still = (np.hypot(nb.ve, nb.vn) < 0.5).all() and (np.abs(nb.vu) < 0.5).all()
        if not still:
            continue
        gam = float(np.mean(normal_gravity_mgal(nb.lat.to_numpy(), nb.h.to_numpy(), model)))
        out.append((float(gb.time.mean()), float(gb.f_z.mean() * 1e5 - gam), gam))
    return out


def test_static_segments_at_both_ends_of_each_flight(noisy):
    p = Path(noisy)
    cfg = PRESETS["tiny"]
    toml = tomllib.loads((p / "survey.toml").read_text())
    tj = json.loads((p / "truth" / "truth.json").read_text())
    g_base = toml["gravimeter"]["base_gravity_mgal"]
    assert g_base == tj["base_gravity_mgal"] == tj["airport"]["g_base_mgal"]
    ap = tj["airport"]
    gam_ap = normal_gravity_mgal(ap["lat_deg"], ap["h_m"], toml["survey"]["normal_gravity"])
    assert abs(g_base - gam_ap - cfg.airport_anomaly_mgal) < 0.01
    lines = pd.read_csv(p / "lines.csv")
    for fl, grp in lines.groupby("flight"):
        gbs = _blocks(_read(p, "gravimeter", fl))
        nbs = _blocks(_read(p, "gnss", fl))
        assert len(gbs) == len(nbs) == 3
        for i in (0, 2):
            nb, gb = nbs[i], gbs[i]
            assert abs(nb.time.iloc[-1] - nb.time.iloc[0] - cfg.apron_s) < 0.05
            assert np.abs(nb[["ve", "vn", "vu"]].to_numpy()).max() < 0.1           # standing still
            assert abs(nb.ve.std() * 100 - cfg.sigma_vh_cms) < 0.1 and abs(nb.vu.std() * 100 - cfg.sigma_vu_cms) < 0.15
            assert abs(nb.lat - ap["lat_deg"]).max() < 2e-6 and abs(nb.lon - ap["lon_deg"]).max() < 5e-6
            assert 0.005 < np.std((nb.lat - ap["lat_deg"]) * 111e3) < 0.05         # cm-level noise
            assert abs(nb.h.mean() - ap["h_m"]) < 0.01
            # gravimeter intervals inside the static GNSS span (none straddles a gap)
            off = tj["time_offset_s"]
            half = 0.5 / cfg.gravimeter_rate_hz
            assert gb.time.iloc[0] - off - half >= nb.time.iloc[0] - 2e-3
            assert gb.time.iloc[-1] - off + half <= nb.time.iloc[-1] + 2e-3
            assert (len(gb) + 1) / cfg.gravimeter_rate_hz > cfg.apron_s - 1.0
            assert gb.f_x.abs().max() < 0.1 and gb.f_y.abs().max() < 0.1
        # before / after every line window, separated by an unrecorded gap
        assert nbs[0].time.iloc[-1] + 100 < nbs[1].time.iloc[0] and gbs[0].time.iloc[-1] + 100 < gbs[1].time.iloc[0]
        assert nbs[1].time.iloc[-1] + 100 < nbs[2].time.iloc[0] and gbs[1].time.iloc[-1] + 100 < gbs[2].time.iloc[0]
        assert nbs[1].time.iloc[0] <= grp.t_start.min() and grp.t_end.max() <= nbs[1].time.iloc[-1]
        # one continuous instrument clock: the static samples sit on the airborne sampling lattice
        a1, a0 = np.polyfit(np.arange(len(gbs[1])), gbs[1].time.to_numpy(), 1)
        for i in (0, 2):
            j = (gbs[i].time.to_numpy() - a0) / a1
            assert np.abs(j - np.round(j)).max() < 0.03
        assert [a["segment"] for a in tj["flights"][fl]["apron"]] == ["before", "after"]
    truth = pd.read_parquet(p / "truth" / "lines.parquet")     # line epochs only
    assert truth.groupby("line").time.agg(["min", "max"]).reset_index().merge(lines, on="line").eval(
        "min >= t_start - 1e-6 and max <= t_end + 1e-6").all()


@pytest.mark.parametrize("which", ["noisy", "drifty"])
def test_static_reading_is_base_gravity_plus_reading_error(which, request):
    """At rest, from the files: mean(f_z − γ) = g_base − γ + reading error, the error being the scale
    and the drift known from truth.json (τ·ḟ' + k·f' = g + drift), ≈ −196 mGal + drift."""
    p = Path(request.getfixturevalue(which))
    tj = json.loads((p / "truth" / "truth.json").read_text())
    model = tomllib.loads((p / "survey.toml").read_text())["survey"]["normal_gravity"]
    g_base, k = tj["base_gravity_mgal"], tj["scale"]
    tol = 0.01 if which == "drifty" else 0.15       # white noise 0.5 mGal/√Hz over 300 s: σ ≈ 0.03 mGal
    for fl, fi in tj["flights"].items():
        st = _static_readings(p, fl, model)
        assert len(st) == 2
        for (tm, meas, gam), ap in zip(st, fi["apron"]):
            assert ap["t_start"] < tm < ap["t_end"]
            # the lag delays the drift by τ/k: the interval mean of τ·ḟ' + k·f' = g + drift is exact
            T = ap["gravimeter_t_end"] - ap["gravimeter_t_start"]
            lag = tj["tau_s"] * (ap["drift_end_mgal"] - ap["drift_start_mgal"]) / (k * T)
            err = (g_base + ap["drift_mean_mgal"] - lag) / k - g_base
            assert abs(meas - (g_base - gam + err)) < tol, (fl, ap["segment"], meas - (g_base - gam + err))
            assert -200 < err - ap["drift_mean_mgal"] < -192   # the scale error: the test has teeth


def test_drift_continuous_across_gap(drifty):
    """The drift keeps running through the unrecorded taxi/climb: the static readings (files) and the
    airborne truth lie on the same offset + rate·(t − t0) line, up to the random walk."""
    p = Path(drifty)
    tj = json.loads((p / "truth" / "truth.json").read_text())
    model = tomllib.loads((p / "survey.toml").read_text())["survey"]["normal_gravity"]
    g_base, k = tj["base_gravity_mgal"], tj["scale"]
    truth = pd.read_parquet(p / "truth" / "lines.parquet")
    rw = tj["config"]["drift_rw_mgal_rth"]
    for fl, fi in tj["flights"].items():
        def lin(t, fi=fi):
            return fi["drift_offset_mgal"] + fi["drift_rate_mgal_h"] * (t - fi["t0"]) / 3600.0

        st = _static_readings(p, fl, model)
        d_static = [k * (meas + gam) - g_base for _, meas, gam in st]     # drift seen at rest (files)
        for (tm, _, _), d in zip(st, d_static):
            assert abs(d - lin(tm)) < 5 * rw * np.sqrt(abs(tm - fi["t0"]) / 3600.0 + 0.05), (fl, tm, d, lin(tm))
        # the two readings span the gaps: their difference is the rate times the elapsed time
        dt_h = (st[1][0] - st[0][0]) / 3600.0
        assert dt_h > 2 * tj["config"]["apron_gap_s"] / 3600.0
        assert abs((d_static[1] - d_static[0]) - fi["drift_rate_mgal_h"] * dt_h) < 5 * rw * np.sqrt(dt_h)
        # frozen during the gaps would be off by rate·gap = 5 mGal; reset would be off by more
        assert abs(fi["drift_rate_mgal_h"]) * tj["config"]["apron_gap_s"] / 3600.0 > 10 * rw * np.sqrt(dt_h)
        # airborne truth on the same line; the truth drift is continuous at the apron ends
        d = truth[truth.flight == fl]
        assert np.abs(d.drift_mgal - lin(d.time)).max() < 5 * rw * np.sqrt((d.time.max() - fi["t0"]) / 3600.0 + 0.05)
        b, a = fi["apron"]
        assert abs(b["drift_end_mgal"] - lin(b["gravimeter_t_end"])) < 5 * rw * np.sqrt(0.5)
        assert abs(a["drift_start_mgal"] - lin(a["gravimeter_t_start"])) < 5 * rw * np.sqrt(0.5)


def test_apron_off_and_airborne_data_unchanged(tmp_path):
    """apron_s = 0 disables the static segments; the airborne data do not depend on them."""
    kw = dict(n_main=1, n_tie=0, main_length_km=6.0, grid_margin_km=3.0)
    a = simulate_survey("tiny", tmp_path / "a", seed=13, **kw)
    b = simulate_survey("tiny", tmp_path / "b", seed=13, apron_s=0.0, **kw)
    assert "base_gravity_mgal" not in tomllib.loads((b / "survey.toml").read_text())["gravimeter"]
    assert json.loads((b / "truth" / "truth.json").read_text())["flights"]["F01"]["apron"] == []
    for name in ("gravimeter", "gnss"):
        fa, fb = _read(a, name, "F01"), _read(b, name, "F01")
        assert len(_blocks(fb)) == 1 and len(_blocks(fa)) == 3
        pd.testing.assert_frame_equal(_airborne(fa), fb)
    pd.testing.assert_frame_equal(pd.read_parquet(a / "truth" / "lines.parquet"),
                                  pd.read_parquet(b / "truth" / "lines.parquet"))


def test_coloured_gnss_velocity_noise_option(tmp_path):
    """`vu_colored_cms` adds a Gauss–Markov velocity error of the stated std and correlation
    time on top of the white noise (for testing the pipeline on non-white GNSS noise)."""
    import numpy as np

    from app.simulate.presets import PRESETS
    from app.simulate.run import _colored_noise

    cfg = PRESETS["tiny"].__class__(**{**PRESETS["tiny"].__dict__, "vu_colored_cms": 2.0, "vu_colored_tau_s": 5.0})
    t = np.arange(0.0, 20000.0, 0.1)
    x = _colored_noise(t, cfg) * 100.0   # cm/s
    assert np.std(x) == pytest.approx(2.0, rel=0.05)
    lag = 50                             # 5 s = τ
    r = np.corrcoef(x[:-lag], x[lag:])[0, 1]
    assert r == pytest.approx(np.exp(-1.0), abs=0.05)
    cfg0 = PRESETS["tiny"]
    assert np.all(_colored_noise(t, cfg0) == 0.0)
