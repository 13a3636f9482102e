"""An independent ("foreign") airborne-gravimetry survey generator, written without
``app.simulate``: other stochastic models for the anomaly, the aircraft, the GNSS and the
gravimeter, so that the product can be scored on surveys it was not developed on.

    python benchmarks/foreign_sim.py OUT_DIR [--seed N] [--clean] [--set key=value ...]

Writes a SPEC §4 survey directory (``survey.toml``, ``lines.csv``, ``flights/<F>/gravimeter.csv.gz``,
``flights/<F>/gnss.csv.gz``) and ``truth/`` (``lines.parquet``, ``truth.json`` and, for
constant-height surveys, ``grid.nc``).

Physics and conventions (SPEC §1, "up" positive, SI in the files):

* The aircraft's vertical acceleration ``a(t)`` is the primitive: piecewise linear between the
  nodes of a 100 Hz "fine" grid.  Vertical velocity and height are its exact first and second
  integrals, so the GNSS ``vu`` at an epoch and ``(V_k − V_{k−1})/Δt`` are exactly the true
  velocity and the true mean acceleration over ``(t_{k−1}, t_k]`` (before GNSS errors).
* True vertical specific force (m/s², up): ``u = a + γ(φ, h) + δg − E + drift + noise``
  with γ the WGS84 normal gravity through ``boule`` (geodetic latitude, ellipsoidal height) and
  E the Eötvös term ``2Ω v_E cos φ + v_E²/(R_N + h) + v_N²/(R_M + h)`` from the true geographic
  velocity (so ``z = f̄ − V̇ − γ + E = δg``); every term is piecewise linear on the fine grid.
* Gravimeter: ``τ·ẏ + k·y = u`` solved exactly for piecewise-linear ``u``; the file's samples are
  either interval means of ``y`` over ``[t − P/2, t + P/2]`` stamped at the interval centre (free
  running clock, stamps rounded to 1 ms), or point samples of ``y`` behind an undeclared
  zero-phase Gaussian anti-alias filter (σ = 0.4 P) on a clock aligned to multiples of P.
* ``dg_true_mgal`` in the truth = the mean of the injected δg over the GNSS interval
  ``(t_{k−1}, t_k]`` (the quantity SPEC's ``z_k`` measures); ``dg_point_mgal`` = δg at ``t_k``
  at the aircraft's position and height.

Stochastic models (drawn by :func:`draw_config`; none of them is the product simulator's):

* anomaly: Gaussian random fields with Matérn spectra at source depths, upward continued
  (``exp(−|k|Δz)``) to a stack of heights and interpolated (bicubic, then cubic in height) at the
  aircraft's 3-D position: a deep regional field, a plain texture everywhere, a mountain texture
  masked to a wavy half-plane or band ("mountain" zone, 40–60 % of the lines) whose
  short-wavelength (< ~20 km) power at flight height is 10–100× the plain's, 0–3 smooth
  fault-like steps of finite strike length (continued likewise), and a linear regional trend;
* aircraft: boustrophedon main lines, tie lines crossing them, an optional repeat group, a
  test-line variant (one line flown 4×); straight legs with slow lateral wander and speed
  fluctuation, quintic-Hermite turns outside the line windows; wind; constant or draped height;
  vertical motion = resonant AR(2) turbulence (band-pass, 0.15–0.8 Hz) whose intensity switches
  between calm and turbulent stretches (optionally stronger over the mountain zone) + a phugoid
  (20–90 s period, slowly varying amplitude) − a smooth altitude hold (cubic spline, 120 s knots);
* GNSS: 1, 2, 5 or 10 Hz; position errors = random walk + slow AR(1) (10–300 s) + fast AR(1)
  (0.5–3 s) + white; multipath episodes (2–6 min, fast part ×3–10); vertical velocity either
  "carrier" (the central difference of the smooth position errors + small white: consistent
  with the heights, blue above the AR corners), "doppler" (independent AR(1) 0.2–2 s + white)
  or absent (heights only); short outages (gap ≤ 2 s);
* gravimeter: 18.24 Hz GT-1A-like interval means with a declared lag (true lag within ±3 % of
  it), 18.24 Hz de-lagged means, 10 Hz and 2 Hz point samples, 1 Hz means; platform meters
  have an undeclared residual lag 0–0.3 s; sensor noise white + flicker (1/f below a corner);
  drift quadratic in time (0.2–3 mGal/h); optionally one tare (0.5–2 mGal step).

``--clean`` (or ``cfg["clean"] = True``) switches off every error: GNSS errors and outages,
sensor noise, drift, tare, lag mismatch, the undeclared response (point samples then come
straight from the instrument output, interval means are exact), and makes the motion smooth.
"""

from __future__ import annotations

import argparse
import copy
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import signal
from scipy.interpolate import CubicSpline, LSQUnivariateSpline, RectBivariateSpline, make_interp_spline

FINE_HZ = 100            # fine grid of the true motion and the instrument input
PATH_HZ = 10             # grid of the horizontal path, the field and the geographic terms
MGAL = 1e-5              # m/s² per mGal
OMEGA = 7.292115e-5      # rad/s
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)

GRAVIMETERS = {
    # name: (model label, rate Hz, sampling, declared tau range (s), undeclared residual lag range (s))
    "gt1a-18hz": ("GT-1A", 18.24, "mean", (1.5, 2.5), None),
    "gt2a-delagged-18hz": ("GT-2A (de-lagged)", 18.24, "mean", (0.0, 0.0), None),
    "airgrav-10hz-point": ("AIRGrav-like platform", 10.0, "point", (0.0, 0.0), (0.0, 0.3)),
    "platform-2hz-point": ("platform gravimeter", 2.0, "point", (0.0, 0.0), (0.0, 0.3)),
    "platform-1hz-mean": ("platform gravimeter", 1.0, "mean", (0.0, 0.0), (0.0, 0.3)),
}


# ----------------------------------------------------------------------------- configuration


def _lu(rng, lo, hi) -> float:
    """Log-uniform draw."""
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def draw_config(seed: int) -> dict:
    """Every setting of one survey, drawn from ``seed`` (JSON-serialisable)."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xF0E1]))
    testline = seed % 8 == 0
    grav = list(GRAVIMETERS)[int(rng.choice(len(GRAVIMETERS), p=[0.3, 0.15, 0.2, 0.2, 0.15]))]
    gnss_rate = float(rng.choice([1.0, 2.0, 5.0, 10.0], p=[0.15, 0.25, 0.15, 0.45]))
    vmode = str(rng.choice(["carrier", "doppler", "none"], p=[0.4, 0.3, 0.3]))
    model, rate, sampling, tau_rng, resid = GRAVIMETERS[grav]
    tau = round(float(rng.uniform(*tau_rng)), 2) if tau_rng[1] > 0 else 0.0
    cfg = {
        "seed": int(seed),
        "clean": False,
        "name": f"foreign-{seed}",
        "lat0": float(rng.uniform(-55.0, 68.0)),
        "lon0": float(rng.uniform(-175.0, 175.0)),
        "layout": "testline" if testline else "block",
        "heading_deg": float(rng.uniform(0.0, 180.0)),
        "n_main": int(rng.integers(6, 13)),
        "main_length_km": float(rng.uniform(30.0, 60.0)),
        "line_spacing_km": float(rng.uniform(2.0, 5.0)),
        "n_tie": int(rng.integers(2, 5)),
        "repeat_group": bool(rng.random() < 0.4),
        "repeat_passes": int(rng.integers(3, 5)),
        "repeat_length_km": float(rng.uniform(20.0, 30.0)),
        "testline_length_km": 40.0,
        "testline_passes": 4,
        "n_flights": int(rng.integers(2, 4)),
        "airspeed_ms": float(rng.uniform(50.0, 110.0)),
        "wind_ms": float(rng.uniform(0.0, 12.0)),
        "wind_dir_deg": float(rng.uniform(0.0, 360.0)),
        "height_m": float(rng.uniform(300.0, 3000.0)),
        "draped": bool(rng.random() < 0.3),
        "drape_amp_m": float(rng.uniform(150.0, 450.0)),
        "run_in_s": float(rng.uniform(90.0, 180.0)),
        "run_out_s": float(rng.uniform(30.0, 60.0)),
        "wander_m": float(rng.uniform(3.0, 25.0)),
        "speed_fluct_ms": float(rng.uniform(0.2, 1.2)),
        # anomaly
        "field": {
            "regional_std_mgal": float(rng.uniform(5.0, 30.0)),
            "regional_L_km": float(rng.uniform(15.0, 50.0)),
            "regional_nu": float(rng.uniform(0.5, 1.5)),
            "regional_depth_km": float(rng.uniform(2.0, 8.0)),
            "plain_hp_std_mgal": float(rng.uniform(1.0, 5.0)),
            "plain_L_km": float(rng.uniform(1.0, 4.0)),
            "plain_nu": float(rng.uniform(0.5, 1.5)),
            "plain_depth_km": float(rng.uniform(0.5, 2.5)),
            "mountain_power_ratio": _lu(rng, 10.0, 100.0),
            "mountain_L_km": float(rng.uniform(0.5, 3.0)),
            "mountain_nu": float(rng.uniform(0.5, 1.5)),
            "mountain_depth_km": float(rng.uniform(0.2, 1.5)),
            "mountain_edge_km": float(rng.uniform(0.5, 2.0)),
            "zone_shape": str(rng.choice(["half-plane", "band"])),
            "zone_fraction": float(rng.uniform(0.4, 0.6)),
            "zone_wave_km": float(rng.uniform(20.0, 60.0)),
            "zone_wave_amp_km": float(rng.uniform(1.0, 8.0)),
            "n_faults": int(rng.integers(0, 4)),
            "trend_mgal_per_km": [float(v) for v in rng.normal(0.0, 0.25, 2)],
        },
        # vertical motion
        "turbulence_rms_ms2": _lu(rng, 0.05, 0.5),
        "turbulence_peak_hz": float(rng.uniform(0.15, 0.8)),
        "turbulence_damping": float(rng.uniform(0.3, 0.7)),
        "turbulence_cutoff_hz": float(rng.uniform(1.5, 4.0)),
        "turbulence_ratio": float(rng.uniform(2.0, 6.0)),
        "turbulence_dwell_s": float(rng.uniform(300.0, 1200.0)),
        "turbulence_mountain_coupling": float(rng.uniform(0.5, 2.0)) if rng.random() < 0.5 else 0.0,
        "phugoid_period_s": float(rng.uniform(20.0, 90.0)),
        "phugoid_amp_m": float(rng.uniform(1.0, 10.0)),
        "hold_knot_s": 120.0,
        # GNSS
        "gnss_rate_hz": gnss_rate,
        "gnss_velocity": vmode,
        "h_rw_cm_rth": float(rng.uniform(1.0, 5.0)),
        "h_slow_cm": float(rng.uniform(0.5, 3.0)),
        "h_slow_tau_s": _lu(rng, 10.0, 300.0),
        "h_fast_mm": float(rng.uniform(2.0, 6.0)),
        "h_fast_tau_s": float(rng.uniform(0.5, 3.0)),
        "h_white_mm": float(rng.uniform(1.0, 4.0)),
        "horizontal_error_factor": float(rng.uniform(0.4, 0.8)),
        "vu_white_cms": float(rng.uniform(0.1, 0.5)) if vmode == "carrier" else float(rng.uniform(0.2, 0.8)),
        "vu_ar_cms": float(rng.uniform(0.4, 1.2)),
        "vu_ar_tau_s": float(rng.uniform(0.2, 2.0)),
        "episodes_per_hour": float(rng.uniform(0.0, 2.0)),
        "episode_len_s": [120.0, 360.0],
        "episode_factor": [3.0, 10.0],
        "outages_per_flight": int(rng.integers(0, 4)),
        # gravimeter
        "gravimeter": grav,
        "gravimeter_model": model,
        "gravimeter_rate_hz": rate,
        "gravimeter_sampling": sampling,
        "tau_declared_s": tau,
        "tau_true_s": round(tau * (1.0 + float(rng.uniform(-0.03, 0.03))), 4) if tau > 0 else 0.0,
        "residual_lag_s": float(rng.uniform(*resid)) if resid else 0.0,
        "aa_sigma_periods": 0.4 if sampling == "point" else 0.0,
        "scale": 1.0,
        "noise_white_mgal_rthz": float(rng.uniform(0.3, 1.5)),
        "noise_flicker_corner_hz": _lu(rng, 0.002, 0.02),
        "drift_rate_mgal_h": [float(rng.uniform(0.2, 3.0)) * float(rng.choice([-1.0, 1.0])) for _ in range(4)],
        "drift_quad_mgal_h2": [float(rng.uniform(-0.5, 0.5)) for _ in range(4)],
        "tare": bool(rng.random() < 0.2),
        "tare_mgal": float(rng.uniform(0.5, 2.0)) * float(rng.choice([-1.0, 1.0])),
    }
    if testline:
        cfg.update(n_flights=1, repeat_group=False, n_tie=0)
    return cfg


def set_gravimeter(cfg: dict, name: str, tau_s: float | None = None) -> dict:
    """``cfg`` with the gravimeter ``name`` of :data:`GRAVIMETERS` (declared lag ``tau_s``, true = declared)."""
    model, rate, sampling, tau_rng, resid = GRAVIMETERS[name]
    tau = float(np.mean(tau_rng)) if tau_s is None else float(tau_s)
    return {**cfg, "gravimeter": name, "gravimeter_model": model, "gravimeter_rate_hz": rate,
            "gravimeter_sampling": sampling, "tau_declared_s": tau, "tau_true_s": tau,
            "residual_lag_s": float(np.mean(resid)) if resid else 0.0,
            "aa_sigma_periods": 0.4 if sampling == "point" else 0.0}


def clean_config(cfg: dict, smooth_motion: bool = True) -> dict:
    """The same survey with every error off (``clean``) and, with ``smooth_motion``, a calm
    aircraft (weak turbulence, small phugoid)."""
    c = copy.deepcopy(cfg)
    c["clean"] = True
    if smooth_motion:
        c.update(turbulence_rms_ms2=0.02, turbulence_peak_hz=0.15, turbulence_cutoff_hz=0.5, phugoid_amp_m=1.0,
                 turbulence_ratio=1.0, turbulence_mountain_coupling=0.0)
    return c


# ----------------------------------------------------------------------------- geodesy


def _radii(lat_deg):
    s2 = np.sin(np.deg2rad(lat_deg)) ** 2
    w = 1.0 - WGS84_E2 * s2
    return WGS84_A * (1.0 - WGS84_E2) / w ** 1.5, WGS84_A / np.sqrt(w)


def _normal_gravity_mgal(lat_deg, h_m):
    import boule

    return np.asarray(boule.WGS84.normal_gravity((np.zeros_like(lat_deg), lat_deg, h_m)), dtype=float)


def _eotvos_mgal(lat_deg, h_m, ve, vn):
    r_m, r_n = _radii(lat_deg)
    return (2.0 * OMEGA * ve * np.cos(np.deg2rad(lat_deg)) + ve ** 2 / (r_n + h_m) + vn ** 2 / (r_m + h_m)) / MGAL


def _utm_epsg(lat, lon) -> int:
    zone = int((lon + 180.0) // 6.0) + 1
    return (32600 if lat >= 0 else 32700) + zone


# ----------------------------------------------------------------------------- random processes


def _ar1(n, dt, sigma, tau, rng) -> np.ndarray:
    """Stationary first-order Gauss–Markov sequence (std ``sigma``, correlation time ``tau``)."""
    if sigma <= 0 or n == 0:
        return np.zeros(n)
    a = np.exp(-dt / tau)
    w = rng.standard_normal(n) * sigma * np.sqrt(1.0 - a * a)
    x0 = rng.standard_normal() * sigma
    return signal.lfilter([1.0], [1.0, -a], w, zi=[a * x0])[0]


def _smooth_noise(n, dt, corr_s, rng) -> np.ndarray:
    """Unit-std smooth Gaussian noise with a Gaussian correlation of about ``corr_s``."""
    from scipy.ndimage import gaussian_filter1d

    x = gaussian_filter1d(rng.standard_normal(n), corr_s / dt, mode="wrap")
    return x / (np.std(x) + 1e-300)


def _flicker_white(n, fs, white, corner, rng) -> np.ndarray:
    """Noise of one-sided PSD ``white²·(1 + corner/f)`` (units of ``white`` per √Hz)."""
    if white <= 0 or n < 4:
        return np.zeros(n)
    f = np.fft.rfftfreq(n, 1.0 / fs)
    f[0] = f[1]
    psd = white ** 2 * (1.0 + corner / f)
    spec = np.fft.rfft(rng.standard_normal(n)) * np.sqrt(psd * fs / 2.0)
    return np.fft.irfft(spec, n)


def _pl_integrate(a, dt, v0=0.0, h0=0.0):
    """Exact velocity and height of a piecewise-linear acceleration on a uniform grid."""
    v = v0 + np.concatenate([[0.0], np.cumsum(0.5 * (a[:-1] + a[1:]) * dt)])
    dh = v[:-1] * dt + dt * dt * (a[:-1] / 3.0 + a[1:] / 6.0)
    h = h0 + np.concatenate([[0.0], np.cumsum(dh)])
    return v, h


# ----------------------------------------------------------------------------- layout and path


def _layout(cfg: dict) -> list[dict]:
    """Planned legs in block coordinates (m, u along the main lines, w across): line id, kind,
    track, start and end points."""
    legs = []
    if cfg["layout"] == "testline":
        L = cfg["testline_length_km"] * 1000.0
        for p in range(cfg["testline_passes"]):
            s, e = (-L / 2, L / 2) if p % 2 == 0 else (L / 2, -L / 2)
            legs.append({"line": f"R1-{p + 1}", "kind": "repeat", "track": "R1", "uw0": (s, 0.0), "uw1": (e, 0.0)})
        return legs
    n, L, sp = cfg["n_main"], cfg["main_length_km"] * 1000.0, cfg["line_spacing_km"] * 1000.0
    W = (n - 1) * sp
    for i in range(n):
        w = -W / 2 + i * sp
        legs.append({"line": f"M{i + 1:03d}", "kind": "main", "track": None, "uw0": (-L / 2, w), "uw1": (L / 2, w)})
    nt = cfg["n_tie"]
    for j in range(nt):
        u = -L / 2 + 3000.0 + (L - 6000.0) * (j + 0.5) / nt
        legs.append({"line": f"T{j + 1:02d}", "kind": "tie", "track": None,
                     "uw0": (u, -W / 2 - 2000.0), "uw1": (u, W / 2 + 2000.0)})
    if cfg["repeat_group"]:
        R = cfg["repeat_length_km"] * 1000.0
        w = -W / 2 + (n // 2) * sp
        for p in range(cfg["repeat_passes"]):
            s, e = (-R / 2, R / 2) if p % 2 == 0 else (R / 2, -R / 2)
            legs.append({"line": f"R1-{p + 1}", "kind": "repeat", "track": "R1", "uw0": (s, w), "uw1": (e, w)})
    return legs


def _assign_flights(cfg: dict, legs: list[dict], rng) -> list[list[dict]]:
    """Legs per flight, in flying order, directions alternating (boustrophedon)."""
    if cfg["layout"] == "testline":
        return [legs]
    mains = [lg for lg in legs if lg["kind"] == "main"]
    ties = [lg for lg in legs if lg["kind"] == "tie"]
    reps = [lg for lg in legs if lg["kind"] == "repeat"]
    nf = max(1, min(cfg["n_flights"], len(mains) // 2))
    flights = [list(ch) for ch in np.array_split(np.array(mains, dtype=object), nf)]
    for t in ties:
        flights[int(rng.integers(nf))].append(t)
    if reps:
        flights[int(rng.integers(nf))].extend(reps)
    out = []
    for fl in flights:
        seq = []
        for k, lg in enumerate(fl):
            lg = dict(lg)
            if k % 2 == 1 and lg["kind"] != "repeat":
                lg["uw0"], lg["uw1"] = lg["uw1"], lg["uw0"]
            seq.append(lg)
        out.append(seq)
    return out


class _Straight:
    def __init__(self, ta, T, p0, d, v, rng, wander_m, fluct_ms):
        self.ta, self.tb, self.p0, self.d, self.v = ta, ta + T, np.asarray(p0, float), np.asarray(d, float), v
        self.n = np.array([-d[1], d[0]])
        self.comp = []
        for kind, amp in (("w", wander_m), ("s", fluct_ms)):
            for _ in range(3):
                per = rng.uniform(60.0, 600.0)
                om = 2 * np.pi / per
                a = rng.normal(0.0, amp / np.sqrt(3.0))
                if kind == "s":
                    a = a / om        # speed fluctuation → along-track displacement amplitude
                self.comp.append((kind, a, om, rng.uniform(0, 2 * np.pi)))
        self.ramp = min(30.0, T / 4.0)

    def end(self):
        return self.p0 + self.d * self.v * (self.tb - self.ta), self.d * self.v

    def _taper(self, s):
        T, r = self.tb - self.ta, self.ramp
        x = np.clip(np.minimum(s, T - s) / r, 0.0, 1.0)
        w = np.sin(0.5 * np.pi * x) ** 2
        dx = np.where((s < r) & (s > 0), 1.0 / r, np.where((T - s < r) & (T - s > 0), -1.0 / r, 0.0))
        dw = np.pi * np.sin(0.5 * np.pi * x) * np.cos(0.5 * np.pi * x) * dx
        return w, dw

    def eval(self, t):
        s = t - self.ta
        w, dw = self._taper(s)
        pw = np.zeros_like(s)
        dpw = np.zeros_like(s)
        ps = np.zeros_like(s)
        dps = np.zeros_like(s)
        for kind, a, om, ph in self.comp:
            if kind == "w":
                pw += a * np.sin(om * s + ph)
                dpw += a * om * np.cos(om * s + ph)
            else:
                ps += a * np.sin(om * s + ph)
                dps += a * om * np.cos(om * s + ph)
        along = self.v * s + ps * w
        valong = self.v + dps * w + ps * dw
        lat = pw * w
        vlat = dpw * w + pw * dw
        x = self.p0[0] + self.d[0] * along + self.n[0] * lat
        y = self.p0[1] + self.d[1] * along + self.n[1] * lat
        vx = self.d[0] * valong + self.n[0] * vlat
        vy = self.d[1] * valong + self.n[1] * vlat
        return x, y, vx, vy


class _Turn:
    """Quintic Hermite between (p0, v0, a=0) and (p1, v1, a=0)."""

    def __init__(self, ta, T, p0, v0, p1, v1):
        self.ta, self.tb, self.T = ta, ta + T, T
        self.p0, self.v0, self.p1, self.v1 = (np.asarray(x, float) for x in (p0, v0, p1, v1))

    def eval(self, t):
        T = self.T
        s = np.clip((t - self.ta) / T, 0.0, 1.0)
        h0 = 1 - 10 * s**3 + 15 * s**4 - 6 * s**5
        h1 = s - 6 * s**3 + 8 * s**4 - 3 * s**5
        h4 = -4 * s**3 + 7 * s**4 - 3 * s**5
        h5 = 10 * s**3 - 15 * s**4 + 6 * s**5
        d0 = -30 * s**2 + 60 * s**3 - 30 * s**4
        d1 = 1 - 18 * s**2 + 32 * s**3 - 15 * s**4
        d4 = -12 * s**2 + 28 * s**3 - 15 * s**4
        d5 = -d0
        out = []
        for k in range(2):
            p = h0 * self.p0[k] + h1 * T * self.v0[k] + h4 * T * self.v1[k] + h5 * self.p1[k]
            out.append(p)
        for k in range(2):
            v = (d0 * self.p0[k] + d1 * T * self.v0[k] + d4 * T * self.v1[k] + d5 * self.p1[k]) / T
            out.append(v)
        return tuple(out)


class _Path:
    """A flight's horizontal path: segments in time, evaluated in projected metres relative to the
    survey centre."""

    def __init__(self, segments):
        self.segs = segments
        self.starts = np.array([s.ta for s in segments])
        self.t0, self.t1 = segments[0].ta, segments[-1].tb

    def eval(self, t):
        t = np.asarray(t, float)
        idx = np.clip(np.searchsorted(self.starts, t, side="right") - 1, 0, len(self.segs) - 1)
        x = np.empty_like(t)
        y = np.empty_like(t)
        vx = np.empty_like(t)
        vy = np.empty_like(t)
        for i in np.unique(idx):
            m = idx == i
            x[m], y[m], vx[m], vy[m] = self.segs[i].eval(t[m])
        return x, y, vx, vy


class _Dubins:
    """Turn outside the line windows: the shortest circle–straight–circle path (radius R,
    25° bank at the mean speed) from (p0, heading of v0) to (p1, heading of v1), flown with a
    speed going smoothly (smoothstep) from |v0| to |v1|."""

    def __init__(self, ta, p0, v0, p1, v1):
        self.p0, self.p1 = np.asarray(p0, float), np.asarray(p1, float)
        self.s0, self.s1 = float(np.hypot(*v0)), float(np.hypot(*v1))
        vbar = 0.5 * (self.s0 + self.s1)
        R = self.R = vbar ** 2 / (9.81 * np.tan(np.deg2rad(25.0)))
        psi0, psi1 = float(np.arctan2(v0[1], v0[0])), float(np.arctan2(v1[1], v1[0]))
        best = None
        for k0 in (1.0, -1.0):           # +1 left (counter-clockwise), -1 right
            for k1 in (1.0, -1.0):
                c0 = self.p0 + k0 * R * np.array([-np.sin(psi0), np.cos(psi0)])
                c1 = self.p1 + k1 * R * np.array([-np.sin(psi1), np.cos(psi1)])
                base = c1 - c0
                Dc = float(np.hypot(*base))
                phib = float(np.arctan2(base[1], base[0]))
                if k0 == k1:
                    th, lam = phib, Dc
                else:
                    if Dc < 2 * R:
                        continue
                    lam = float(np.sqrt(Dc * Dc - 4 * R * R))
                    g = float(np.arctan2(2 * R, lam))
                    th = phib + g if k0 > 0 else phib - g
                d0 = ((th - psi0) * k0) % (2 * np.pi)
                d1 = ((psi1 - th) * k1) % (2 * np.pi)
                L = R * (d0 + d1) + lam
                if best is None or L < best[0]:
                    best = (L, k0, k1, c0, c1, th, d0, d1, lam)
        self.L, self.k0, self.k1, self.c0, self.c1, self.th, self.d0, self.d1, self.lam = best
        self.psi0 = psi0
        self.ta = ta
        self.T = 2.0 * self.L / (self.s0 + self.s1)
        self.tb = ta + self.T

    def eval(self, t):
        x = np.clip((np.asarray(t, float) - self.ta) / self.T, 0.0, 1.0)
        sig = self.s0 * x * self.T + (self.s1 - self.s0) * self.T * (x ** 3 - 0.5 * x ** 4)
        spd = self.s0 + (self.s1 - self.s0) * (3 * x ** 2 - 2 * x ** 3)
        R = self.R
        a0, a1 = R * self.d0, R * self.d0 + self.lam
        psi = np.where(sig < a0, self.psi0 + self.k0 * sig / R,
                       np.where(sig < a1, self.th, self.th + self.k1 * (sig - a1) / R))
        q0 = self.c0 + self.k0 * R * np.array([np.sin(self.th), -np.cos(self.th)])
        px = np.where(sig < a0, self.c0[0] + self.k0 * R * np.sin(psi),
                      np.where(sig < a1, q0[0] + (sig - a0) * np.cos(self.th), self.c1[0] + self.k1 * R * np.sin(psi)))
        py = np.where(sig < a0, self.c0[1] - self.k0 * R * np.cos(psi),
                      np.where(sig < a1, q0[1] + (sig - a0) * np.sin(self.th), self.c1[1] - self.k1 * R * np.cos(psi)))
        return px, py, spd * np.cos(psi), spd * np.sin(psi)


def _turn(t, p_out, v_out, p_in, v_in) -> list:
    """Turn segments from (p_out, v_out) to (p_in, v_in) (:class:`_Dubins`)."""
    seg = _Dubins(t, p_out, v_out, p_in, v_in)
    end = np.array(seg.eval(np.array([seg.tb]))).ravel()
    if np.hypot(end[0] - p_in[0], end[1] - p_in[1]) > 1.0:
        raise RuntimeError(f"turn misses its end point by {np.hypot(end[0] - p_in[0], end[1] - p_in[1]):.1f} m")
    return [seg]


def _plan_flight(cfg: dict, legs: list[dict], t0: float, rng, rot):
    """Segments and line windows of one flight starting at ``t0`` (integer seconds)."""
    wind = cfg["wind_ms"] * np.array([np.sin(np.deg2rad(cfg["wind_dir_deg"])), np.cos(np.deg2rad(cfg["wind_dir_deg"]))])
    rate = cfg["gnss_rate_hz"]
    segs, windows = [], []
    t = t0
    prev_end = None
    for k, lg in enumerate(legs):
        a, b = rot(np.array(lg["uw0"])), rot(np.array(lg["uw1"]))
        L = float(np.hypot(*(b - a)))
        d = (b - a) / L
        v = cfg["airspeed_ms"] + float(wind @ d)
        run_in = 300.0 if k == 0 else cfg["run_in_s"]
        run_out = 240.0 if k == len(legs) - 1 else cfg["run_out_s"]
        p_in = a - d * v * run_in
        if prev_end is not None:
            for seg in _turn(t, *prev_end, p_in, d * v):
                segs.append(seg)
                t = seg.tb
        T = run_in + L / v + run_out
        st = _Straight(t, T, p_in, d, v, rng, cfg["wander_m"], cfg["speed_fluct_ms"])
        segs.append(st)
        ts = np.ceil((t + run_in) * rate - 1e-6) / rate
        te = np.floor((t + run_in + L / v) * rate + 1e-6) / rate
        windows.append({**lg, "t_start": float(ts), "t_end": float(te), "speed_ms": v})
        t += T
        prev_end = st.end()
    return _Path(segs), windows


# ----------------------------------------------------------------------------- anomaly field


class _Field:
    """δg (mGal) on a stack of heights over a projected grid (km, absolute), plus the mountain zone."""

    def __init__(self, cfg: dict, ext_km, line_pts_km, heights_m, centre_km, rng):
        fc = cfg["field"]
        self.fc = fc
        self.centre = np.asarray(centre_km, float)
        dx = 0.25
        pad = 25.0
        x0, x1, y0, y1 = ext_km
        nx = int(np.ceil((x1 - x0 + 2 * pad) / dx))
        ny = int(np.ceil((y1 - y0 + 2 * pad) / dx))
        nx += nx % 2
        ny += ny % 2
        self.x = x0 - pad + dx * np.arange(nx)
        self.y = y0 - pad + dx * np.arange(ny)
        kx = 2 * np.pi * np.fft.fftfreq(nx, dx)
        ky = 2 * np.pi * np.fft.fftfreq(ny, dx)
        K = np.hypot(*np.meshgrid(kx, ky))
        X, Y = np.meshgrid(self.x, self.y)
        self._zone_setup(line_pts_km, rng)
        zone_grid = self.mountain(X, Y)
        # sources (spectra at their own depths, km below the zero height)
        def matern(L, nu, lowcut=False):
            """Matérn spectrum of correlation length L; ``lowcut``: a texture with little power at
            wavelengths beyond ~20 km (zero-mean sources on those scales)."""
            W = np.fft.fft2(rng.standard_normal((ny, nx)))
            amp = (1.0 + (K * L) ** 2) ** (-(nu + 1.0) / 2.0)
            if lowcut:
                amp = amp * (1.0 - np.exp(-(K * 20.0 / (2 * np.pi)) ** 2))
            return W * amp

        comps = []   # (spectrum at source, source depth km)
        comps.append(("regional", matern(fc["regional_L_km"], fc["regional_nu"]), fc["regional_depth_km"]))
        comps.append(("plain", matern(fc["plain_L_km"], fc["plain_nu"], True), fc["plain_depth_km"]))
        from scipy.ndimage import gaussian_filter

        edge = fc["mountain_edge_km"] / dx
        mask = gaussian_filter(zone_grid.astype(float), edge)
        m_src = np.real(np.fft.ifft2(matern(fc["mountain_L_km"], fc["mountain_nu"], True))) * mask
        comps.append(("mountain", np.fft.fft2(m_src), fc["mountain_depth_km"]))
        faults = []
        for _ in range(fc["n_faults"]):
            pc = line_pts_km[int(rng.integers(len(line_pts_km)))] + rng.normal(0.0, 3.0, 2)
            strike = rng.uniform(0, np.pi)
            sd = np.array([np.cos(strike), np.sin(strike)])
            nd = np.array([-sd[1], sd[0]])
            length = rng.uniform(20.0, 80.0)
            width = rng.uniform(0.5, 2.0)
            amp = rng.uniform(2.0, 10.0) * rng.choice([-1.0, 1.0])
            depth = rng.uniform(0.5, 3.0)
            along = (X - pc[0]) * sd[0] + (Y - pc[1]) * sd[1]
            across = (X - pc[0]) * nd[0] + (Y - pc[1]) * nd[1]
            taper = 0.5 * (1 + np.cos(np.pi * np.clip(np.abs(along) / (length / 2), 0, 1)))
            f = amp * np.tanh(across / width) * taper
            comps.append(("fault", np.fft.fft2(f), depth))
            faults.append({"centre_km": pc.tolist(), "strike_deg": float(np.rad2deg(strike)), "length_km": length,
                           "width_km": width, "step_mgal": 2 * amp, "depth_km": depth})
        self.faults = faults
        # scale the random components at the nominal height (mean line height): the regional's
        # std along the lines; the short-wavelength (< ~20 km) power of the whole field in the
        # plain zone; the mountain texture's so that the zone has mountain_power_ratio × that
        hnom = float(np.mean(heights_m)) / 1000.0
        hp = 1.0 - np.exp(-(K * 20.0 / (2 * np.pi)) ** 4)
        li = self._line_index(line_pts_km)
        inz = self.mountain(line_pts_km[:, 0], line_pts_km[:, 1])

        def at_lines(spec, depth, hpass=False):
            g = np.real(np.fft.ifft2(spec * np.exp(-K * (hnom + depth)) * (hp if hpass else 1.0)))
            return g[li]

        reg = at_lines(comps[0][1], comps[0][2])
        s_reg = fc["regional_std_mgal"] / np.std(reg)
        other_hp = s_reg * at_lines(comps[0][1], comps[0][2], True)
        for _, spec, depth in comps[3:]:
            other_hp = other_hp + at_lines(spec, depth, True)
        pl = at_lines(comps[1][1], comps[1][2], True)
        p_target = fc["plain_hp_std_mgal"] ** 2
        p_other = np.mean(other_hp[~inz] ** 2)
        s_pl = np.sqrt(max(p_target - p_other, 0.1 * p_target) / np.mean(pl[~inz] ** 2))
        base_hp = other_hp + s_pl * pl
        p_plain = float(np.mean(base_hp[~inz] ** 2))
        mt = at_lines(comps[2][1], comps[2][2], True)
        need = max(fc["mountain_power_ratio"] * p_plain - np.mean(base_hp[inz] ** 2), 0.0)
        s_mt = np.sqrt(need / np.mean(mt[inz] ** 2))
        tot_hp = base_hp + s_mt * mt
        self.hp_power = {"plain_mgal2": float(np.mean(tot_hp[~inz] ** 2)), "mountain_mgal2": float(np.mean(tot_hp[inz] ** 2))}
        scales = {"regional": s_reg, "plain": s_pl, "mountain": s_mt, "fault": 1.0}
        self.scales = {k: float(v) for k, v in scales.items() if k != "fault"}
        self.line_std = {}
        for name, spec, depth in comps:
            v = scales[name] * at_lines(spec, depth)
            self.line_std[name] = self.line_std.get(name, 0.0) + float(np.var(v))
        self.line_std = {k: float(np.sqrt(v)) for k, v in self.line_std.items()}
        # the stack of heights
        hmin, hmax = float(np.min(heights_m)) - 80.0, float(np.max(heights_m)) + 80.0
        nlev = max(4, int(np.ceil((hmax - hmin) / 50.0)) + 1)
        self.levels_m = np.linspace(hmin, hmax, nlev)
        # keep the grid over the flown extent only (+3 km)
        ix = (self.x >= x0 - 3) & (self.x <= x1 + 3)
        iy = (self.y >= y0 - 3) & (self.y <= y1 + 3)
        self.gx, self.gy = self.x[ix], self.y[iy]
        total_spec = None
        self.splines = []
        self.level_grids = []
        for hz in self.levels_m:
            acc = np.zeros((ny, nx), complex)
            for name, spec, depth in comps:
                acc += scales[name] * spec * np.exp(-K * (hz / 1000.0 + depth))
            g = np.real(np.fft.ifft2(acc))[np.ix_(iy, ix)]
            g = g + self._trend(*np.meshgrid(self.gx, self.gy))
            self.level_grids.append(g)
            self.splines.append(RectBivariateSpline(self.gy, self.gx, g, kx=3, ky=3))
        del total_spec
        # remove the mean over the lines at the nominal height (an offset is not observable)
        self.offset = float(np.mean(self.at(line_pts_km[:, 0], line_pts_km[:, 1], np.full(len(li[0]), hnom * 1000.0))))

    def _trend(self, X, Y):
        g = self.fc["trend_mgal_per_km"]
        return g[0] * (X - self.centre[0]) + g[1] * (Y - self.centre[1])

    def _line_index(self, pts):
        ix = np.clip(np.round((pts[:, 0] - self.x[0]) / (self.x[1] - self.x[0])).astype(int), 0, self.x.size - 1)
        iy = np.clip(np.round((pts[:, 1] - self.y[0]) / (self.y[1] - self.y[0])).astype(int), 0, self.y.size - 1)
        return iy, ix

    def _zone_setup(self, pts, rng):
        fc = self.fc
        ang = rng.uniform(0, 2 * np.pi)
        self.zn = np.array([np.cos(ang), np.sin(ang)])
        self.zt = np.array([-self.zn[1], self.zn[0]])
        self.zwave = (fc["zone_wave_amp_km"], 2 * np.pi / fc["zone_wave_km"], rng.uniform(0, 2 * np.pi))
        s = self._zone_s(pts[:, 0], pts[:, 1])
        f = fc["zone_fraction"]
        if fc["zone_shape"] == "half-plane":
            self.zlim = (float(np.quantile(s, 1.0 - f)), np.inf)
        else:
            c = float(np.quantile(s, rng.uniform(0.3, 0.7)))
            d = np.abs(s - c)
            hw = float(np.quantile(d, f))
            self.zlim = (c - hw, c + hw)

    def _zone_s(self, x, y):
        a, k, ph = self.zwave
        dx, dy = x - self.centre[0], y - self.centre[1]
        return dx * self.zn[0] + dy * self.zn[1] + a * np.sin(k * (dx * self.zt[0] + dy * self.zt[1]) + ph)

    def mountain(self, x, y):
        s = self._zone_s(np.asarray(x, float), np.asarray(y, float))
        return (s >= self.zlim[0]) & (s <= self.zlim[1])

    def at(self, x_km, y_km, h_m):
        """δg (mGal) at absolute projected km and ellipsoidal height (m): bicubic per level, cubic
        Lagrange across the four nearest levels."""
        x_km, y_km, h_m = (np.asarray(v, float) for v in (x_km, y_km, h_m))
        lv = self.levels_m
        dz = lv[1] - lv[0]
        j = np.clip(np.floor((h_m - lv[0]) / dz).astype(int) - 1, 0, lv.size - 4)
        vals = np.stack([sp.ev(y_km, x_km) for sp in self.splines])   # (nlev, n)
        out = np.zeros_like(h_m)
        for q in range(4):
            wq = np.ones_like(h_m)
            for r in range(4):
                if r != q:
                    wq *= (h_m - lv[j + r]) / (lv[j + q] - lv[j + r])
            out += wq * vals[j + q, np.arange(h_m.size)]
        return out - getattr(self, "offset", 0.0)

    def info(self) -> dict:
        return {"scales": self.scales, "line_std_mgal": self.line_std, "hp_power_lt20km": self.hp_power, "faults": self.faults, "levels_m": self.levels_m.tolist(),
                "zone": {"normal": self.zn.tolist(), "limits_km": [v if np.isfinite(v) else None for v in self.zlim],
                         "wave": list(self.zwave)}, "offset_mgal": self.offset,
                "grid_spacing_km": float(self.x[1] - self.x[0])}


# ----------------------------------------------------------------------------- one flight


def _envelope(n_s, cfg, rng, mnt_s):
    """Turbulence intensity on a 1 s grid: calm/turbulent Markov stretches (smoothed over 30 s), a
    slow log-normal modulation and the optional coupling with the mountain zone."""
    from scipy.ndimage import gaussian_filter1d

    state = np.zeros(n_s)
    s = int(rng.random() < 0.5)
    i = 0
    while i < n_s:
        dur = int(rng.exponential(cfg["turbulence_dwell_s"])) + 30
        state[i:i + dur] = s
        s = 1 - s
        i += dur
    env = 1.0 + (cfg["turbulence_ratio"] - 1.0) * gaussian_filter1d(state, 30.0)
    env *= np.exp(0.2 * _smooth_noise(n_s, 1.0, 60.0, rng))
    if cfg["turbulence_mountain_coupling"] > 0:
        m = np.interp(np.arange(n_s), np.arange(mnt_s.size), mnt_s.astype(float))
        env *= 1.0 + cfg["turbulence_mountain_coupling"] * gaussian_filter1d(m, 20.0)
    return env


def _vertical(cfg, rng, tf_rel, hcmd, windows_rel, mnt_s):
    """True vertical acceleration, velocity and height on the fine grid (exactly consistent)."""
    n = tf_rel.size
    dt = 1.0 / FINE_HZ
    # turbulence: resonant AR(2) with a zero at DC
    fpk, z = cfg["turbulence_peak_hz"], cfg["turbulence_damping"]
    om = 2 * np.pi * fpk
    r = np.exp(-z * om * dt)
    th = om * np.sqrt(1 - z * z) * dt
    at = signal.lfilter([1.0, -1.0], [1.0, -2 * r * np.cos(th), r * r], rng.standard_normal(n + 2000))[2000:]
    # the airframe and the instrument's mounting: nothing above a few Hz (zero-phase 4th order)
    at = signal.sosfiltfilt(signal.butter(4, cfg["turbulence_cutoff_hz"], fs=FINE_HZ, output="sos"), at)
    at /= np.std(at)
    n_s = int(np.ceil(tf_rel[-1])) + 2
    env_s = _envelope(n_s, cfg, rng, mnt_s)
    env = np.interp(tf_rel, np.arange(n_s), env_s)
    at *= env
    # phugoid
    Tp = cfg["phugoid_period_s"] * (1.0 + 0.05 * np.interp(tf_rel, np.arange(n_s), _smooth_noise(n_s, 1.0, 300.0, rng)))
    phase = 2 * np.pi * np.cumsum(dt / Tp) + rng.uniform(0, 2 * np.pi)
    A = cfg["phugoid_amp_m"] * np.exp(0.4 * np.interp(tf_rel, np.arange(n_s), _smooth_noise(n_s, 1.0, 400.0, rng)))
    aph = -A * (2 * np.pi / Tp) ** 2 * np.sin(phase)
    # scale the turbulence so that the total RMS over the line windows is the drawn one
    inw = np.zeros(n, bool)
    for a, b in windows_rel:
        inw[int(a * FINE_HZ):int(b * FINE_HZ) + 1] = True
    target = cfg["turbulence_rms_ms2"]
    rph = np.sqrt(np.mean(aph[inw] ** 2))
    rt = np.sqrt(np.mean(at[inw] ** 2))
    k = np.sqrt(max(target ** 2 - rph ** 2, (0.3 * target) ** 2)) / rt
    a_raw = k * at + aph
    v_raw, h_raw = _pl_integrate(a_raw, dt)
    # altitude hold: remove a least-squares cubic spline (knots every hold_knot_s) of the height
    ks = cfg["hold_knot_s"]
    knots = np.arange(ks, tf_rel[-1] - ks / 2, ks)
    knots = np.round(knots * FINE_HZ) / FINE_HZ
    S = LSQUnivariateSpline(tf_rel, h_raw, knots, k=3)
    a = a_raw - S.derivative(2)(tf_rel) + hcmd[2]
    v = v_raw - S.derivative(1)(tf_rel) + hcmd[1]
    h = h_raw - S(tf_rel) + hcmd[0]
    return a, v, h, {"turbulence_scale": float(k), "phugoid_rms_ms2": float(rph),
                     "vertical_accel_rms_lines_ms2": float(np.sqrt(np.mean(a[inw] ** 2))),
                     "height_dev_rms_m": float(np.std((h - hcmd[0])[inw]))}


def _episodes(t0, t1, cfg, rng):
    n = rng.poisson(cfg["episodes_per_hour"] * (t1 - t0) / 3600.0)
    out = []
    for _ in range(n):
        L = rng.uniform(*cfg["episode_len_s"])
        s = rng.uniform(t0, max(t0, t1 - L))
        out.append((float(s), float(s + L), float(rng.uniform(*cfg["episode_factor"]))))
    return out


def _episode_weight(t, eps):
    """Per-epoch (factor − 1) × raised-cosine window (15 s ramps) of the episodes."""
    w = np.zeros_like(t)
    for s, e, f in eps:
        x = np.clip(np.minimum(t - s, e - t) / 15.0, 0.0, 1.0)
        w = np.maximum(w, (f - 1.0) * np.sin(0.5 * np.pi * x) ** 2)
    return w


def _gnss_errors(cfg, rng, tg, eps):
    """Errors (m, m/s) at the GNSS epochs: up, east, north positions and velocities."""
    n = tg.size
    dt = 1.0 / cfg["gnss_rate_hz"]
    wep = _episode_weight(tg, eps)
    out = {}
    for ax, fac in (("u", 1.0), ("e", cfg["horizontal_error_factor"]), ("n", cfg["horizontal_error_factor"])):
        rw = np.cumsum(rng.standard_normal(n)) * fac * cfg["h_rw_cm_rth"] / 100.0 * np.sqrt(dt / 3600.0)
        slow = _ar1(n, dt, fac * cfg["h_slow_cm"] / 100.0, cfg["h_slow_tau_s"], rng)
        fast = _ar1(n, dt, fac * cfg["h_fast_mm"] / 1000.0, cfg["h_fast_tau_s"], rng)
        mp = _ar1(n, dt, fac * cfg["h_fast_mm"] / 1000.0, rng.uniform(3.0, 30.0), rng) * wep
        white = rng.standard_normal(n) * fac * cfg["h_white_mm"] / 1000.0
        smooth = rw + slow + fast + mp
        pos = smooth + white
        if cfg["gnss_velocity"] == "carrier":
            vel = np.gradient(smooth, tg) + rng.standard_normal(n) * fac * cfg["vu_white_cms"] / 100.0
        else:   # doppler (also used for ve, vn when vu is absent, though not written)
            vel = (_ar1(n, dt, fac * cfg["vu_ar_cms"] / 100.0, cfg["vu_ar_tau_s"], rng) * (1.0 + wep)
                   + rng.standard_normal(n) * fac * cfg["vu_white_cms"] / 100.0 * (1.0 + wep))
        out[ax] = (pos, vel)
    return out, wep


def _sample_gravimeter(cfg, rng, tf, u, cref, g_lo, g_hi):
    """Instrument output ``τ·ẏ + k·y = u`` (u piecewise linear on ``tf``) sampled as configured.

    Returns (stamps, f_z) in s and m/s²."""
    dt = 1.0 / FINE_HZ
    tau = cfg["tau_true_s"] + (0.0 if cfg["clean"] else cfg["residual_lag_s"])
    if cfg["clean"] and cfg["tau_declared_s"] > 0:
        tau = cfg["tau_declared_s"]
    k = cfg["scale"]
    P = 1.0 / cfg["gravimeter_rate_hz"]
    m = np.diff(u) / dt
    if tau > 0:
        alpha = np.exp(-k * dt / tau)
        c = (alpha - 1.0) * m * tau / k ** 2
        w0 = -m[0] * tau / k ** 2
        w = np.concatenate([[w0], signal.lfilter([1.0], [1.0, -alpha], c, zi=[alpha * w0])[0]])
        y = w + u / k
    else:
        y = u / k
    t0 = tf[0]

    def y_at(t):
        i = np.clip(np.floor((t - t0) * FINE_HZ + 1e-9).astype(int), 0, u.size - 2)
        s = t - tf[i]
        if tau <= 0:
            return (u[i] + m[i] * s) / k
        yp0 = u[i] / k - m[i] * tau / k ** 2
        yps = (u[i] + m[i] * s) / k - m[i] * tau / k ** 2
        return yps + (y[i] - yp0) * np.exp(-k * s / tau)

    U = np.concatenate([[0.0], np.cumsum(0.5 * (u[:-1] + u[1:]) * dt)])

    def U_at(t):
        i = np.clip(np.floor((t - t0) * FINE_HZ + 1e-9).astype(int), 0, u.size - 2)
        s = t - tf[i]
        return U[i] + u[i] * s + 0.5 * m[i] * s * s

    if cfg["gravimeter_sampling"] == "mean":
        g0 = g_lo + rng.uniform(0.0, P)
        nmax = int(np.floor((g_hi - g0) / P))
        edges = g0 + P * np.arange(nmax + 1)
        a, b = edges[:-1], edges[1:]
        mean = ((U_at(b) - U_at(a)) - tau * (y_at(b) - y_at(a))) / (k * (b - a))
        stamps = np.round(0.5 * (a + b), 3)
        return stamps, mean + cref / k
    # point samples on the aligned clock (multiples of P), behind a zero-phase Gaussian filter
    j0 = int(np.ceil(g_lo / P))
    j1 = int(np.floor(g_hi / P))
    ts = np.arange(j0, j1 + 1) * P
    sig = cfg["aa_sigma_periods"] * P
    if cfg["clean"] or sig <= 0:
        vals = y_at(ts)
    else:
        half = int(np.ceil(4 * sig * FINE_HZ))
        kern = np.exp(-0.5 * (np.arange(-half, half + 1) / (sig * FINE_HZ)) ** 2)
        kern /= kern.sum()
        yf = signal.oaconvolve(y, kern, mode="same")
        vals = np.interp(ts, tf, yf)
    return np.round(ts, 4), vals + cref / k


def _simulate_flight(cfg, rng, name, legs, t0, rot, field, to_geo, e0n0, drape_fn, fidx):
    rate = cfg["gnss_rate_hz"]
    path, windows = _plan_flight(cfg, legs, t0, rng, rot)
    t1 = float(np.ceil(path.t1))
    nf = int(round((t1 - t0) * FINE_HZ)) + 1
    tf_rel = np.arange(nf) / FINE_HZ
    tf = t0 + tf_rel
    # path on the 10 Hz grid (every 10th fine node) and on a 1 s grid for the commanded height
    step = FINE_HZ // PATH_HZ
    tp = tf[::step]
    xp, yp, vxp, vyp = path.eval(tp)
    sp = np.hypot(vxp, vyp)
    if sp.min() < 20.0 or sp.max() > 160.0:
        raise RuntimeError(f"flight {name}: implausible ground speed {sp.min():.1f}–{sp.max():.1f} m/s")
    ts1 = np.arange(t0, t1 + 0.5, 1.0)
    x1, y1, _, _ = path.eval(ts1)
    X1, Y1 = e0n0[0] + x1 / 1000.0, e0n0[1] + y1 / 1000.0
    mnt_s = field.mountain(X1, Y1) if field is not None else np.zeros(ts1.size, bool)
    if drape_fn is not None:
        hc = make_interp_spline(ts1 - t0, cfg["height_m"] + drape_fn(X1, Y1), k=3)
        hcmd = (hc(tf_rel), hc.derivative(1)(tf_rel), hc.derivative(2)(tf_rel))
    else:
        hcmd = (np.full(nf, cfg["height_m"]), np.zeros(nf), np.zeros(nf))
    wins_rel = [(w["t_start"] - t0, w["t_end"] - t0) for w in windows]
    a, v, h, vinfo = _vertical(cfg, rng, tf_rel, hcmd, wins_rel, mnt_s)
    # geography on the path grid
    hp = h[::step]
    lat_p, lon_p = to_geo(xp, yp)
    dtc = 0.05
    xa, ya, _, _ = path.eval(tp + dtc)
    xb, yb, _, _ = path.eval(tp - dtc)
    lat_a, lon_a = to_geo(xa, ya)
    lat_b, lon_b = to_geo(xb, yb)
    r_m, r_n = _radii(lat_p)
    ve = np.deg2rad(lon_a - lon_b) / (2 * dtc) * (r_n + hp) * np.cos(np.deg2rad(lat_p))
    vn = np.deg2rad(lat_a - lat_b) / (2 * dtc) * (r_m + hp)
    eot_p = _eotvos_mgal(lat_p, hp, ve, vn)
    Xp, Yp = e0n0[0] + xp / 1000.0, e0n0[1] + yp / 1000.0
    dg_p = field.at(Xp, Yp, hp)
    # to the fine grid (cubic in time)
    tpr = tp - t0
    lat_f = CubicSpline(tpr, lat_p)(tf_rel)
    eot_f = CubicSpline(tpr, eot_p)(tf_rel)
    dg_f = CubicSpline(tpr, dg_p)(tf_rel)
    gam_f = _normal_gravity_mgal(lat_f, h)
    # drift, tare, sensor noise (mGal)
    hrs = tf_rel / 3600.0
    fi = fidx % len(cfg["drift_rate_mgal_h"])
    drift = np.zeros(nf)
    noise = np.zeros(nf)
    tare_info = None
    if not cfg["clean"]:
        drift = (float(rng.normal(0.0, 5.0)) + cfg["drift_rate_mgal_h"][fi] * hrs + cfg["drift_quad_mgal_h2"][fi] * hrs ** 2)
        if cfg["tare"] and fidx == cfg.get("_tare_flight", 0):
            tt = float(rng.uniform(0.2, 0.8)) * tf_rel[-1]
            drift = drift + cfg["tare_mgal"] * (tf_rel >= tt)
            tare_info = {"time": t0 + tt, "step_mgal": cfg["tare_mgal"]}
        noise = _flicker_white(nf, FINE_HZ, cfg["noise_white_mgal_rthz"], cfg["noise_flicker_corner_hz"], rng)
    slow = gam_f + dg_f - eot_f + drift + noise           # mGal
    cref = float(np.round(np.mean(slow) * MGAL, 3))
    u = a + slow * MGAL - cref
    g_lo, g_hi = t0 + 60.0, t1 - 5.0
    stamps, fz = _sample_gravimeter(cfg, rng, tf, u, cref, g_lo, g_hi)
    grav = pd.DataFrame({"time": stamps, "f_z": np.round(fz, 9)})
    # GNSS epochs (receiver clock) from t0 + 30 s
    step_g = int(round(FINE_HZ / rate))
    i0 = int(30 * FINE_HZ)
    ig = np.arange(i0, nf, step_g)
    tg = t0 + ig / FINE_HZ
    lat_g, lon_g = to_geo(*path.eval(tg)[:2])
    r_mg, r_ng = _radii(lat_g)
    ve_g = np.interp(tg, tp, ve)
    vn_g = np.interp(tg, tp, vn)
    eps = [] if cfg["clean"] else _episodes(tg[0], tg[-1], cfg, rng)
    if cfg["clean"]:
        z0 = np.zeros(tg.size)
        err = {ax: (z0, z0) for ax in "uen"}
        wep = z0
    else:
        err, wep = _gnss_errors(cfg, rng, tg, eps)
    gnss = pd.DataFrame({
        "time": np.round(tg, 4),
        "lat": lat_g + np.rad2deg(err["n"][0] / (r_mg + h[ig])),
        "lon": lon_g + np.rad2deg(err["e"][0] / ((r_ng + h[ig]) * np.cos(np.deg2rad(lat_g)))),
        "h": h[ig] + err["u"][0],
    })
    if cfg["gnss_velocity"] != "none":
        gnss["vu"] = v[ig] + err["u"][1]
        gnss["ve"] = ve_g + err["e"][1]
        gnss["vn"] = vn_g + err["n"][1]
        if cfg["gnss_velocity"] == "doppler":
            base = np.hypot(cfg["vu_ar_cms"], cfg["vu_white_cms"]) / 100.0
            gnss["sigma_v"] = base * (1.0 + wep) * np.exp(rng.normal(0.0, 0.2, tg.size))
    # outages: short holes (gap ≤ 2 s) anywhere in the record
    keep = np.ones(tg.size, bool)
    outages = []
    if not cfg["clean"]:
        for _ in range(cfg["outages_per_flight"]):
            nmiss = int(rng.integers(1, max(2, int(2 * rate))))
            k0 = int(rng.integers(100, tg.size - 100 - nmiss))
            keep[k0:k0 + nmiss] = False
            outages.append({"t_start": float(tg[k0]), "missing_epochs": nmiss})
    gnss = gnss[keep].reset_index(drop=True)
    for c, nd in (("lat", 10), ("lon", 10), ("h", 5), ("vu", 5), ("ve", 5), ("vn", 5), ("sigma_v", 5)):
        if c in gnss:
            gnss[c] = gnss[c].round(nd)
    # truth at every receiver epoch inside the windows (outage epochs included)
    Cdg = np.concatenate([[0.0], np.cumsum(0.5 * (dg_f[:-1] + dg_f[1:]) / FINE_HZ)])
    xg, yg = path.eval(tg)[:2]
    truth = []
    lines = []
    for w in windows:
        sel = (tg >= w["t_start"] - 1e-6) & (tg <= w["t_end"] + 1e-6)
        ii = ig[sel]
        dgm = (Cdg[ii] - Cdg[ii - step_g]) / (step_g / FINE_HZ)
        X, Y = e0n0[0] + xg[sel] / 1000.0, e0n0[1] + yg[sel] / 1000.0
        mnt = field.mountain(X, Y)
        truth.append(pd.DataFrame({
            "line": w["line"], "flight": name, "kind": w["kind"], "track": w["track"],
            "time": np.round(tg[sel], 4), "easting_km": X, "northing_km": Y, "h_true_m": h[ii],
            "dg_true_mgal": dgm, "dg_point_mgal": dg_f[ii],
            "terrain": np.where(mnt, "mountain", "plain"), "state_true": mnt.astype(np.int8),
            "vu_true_ms": v[ii], "accel_true_ms2": a[ii], "drift_mgal": drift[ii],
            "gnss_recorded": keep[sel], "gnss_noise_factor": 1.0 + wep[sel],
        }))
        lines.append({"line": w["line"], "flight": name, "t_start": f"{w['t_start']:.4f}",
                      "t_end": f"{w['t_end']:.4f}", "kind": w["kind"], "track": w["track"] or ""})
    info = {"t0": t0, "t1": t1, "episodes": [{"t_start": s, "t_end": e, "factor": f} for s, e, f in eps],
            "outages": outages, "tare": tare_info, "drift_rate_mgal_h": cfg["drift_rate_mgal_h"][fi],
            "drift_quad_mgal_h2": cfg["drift_quad_mgal_h2"][fi], "speeds_ms": [w["speed_ms"] for w in windows],
            **vinfo}
    return grav, gnss, pd.concat(truth, ignore_index=True), lines, info


# ----------------------------------------------------------------------------- survey


def _write_toml(path: Path, cfg: dict, crs: str) -> None:
    path.write_text(
        "[survey]\n"
        f'name = "{cfg["name"]}"\n'
        f'crs = "{crs}"\n'
        'normal_gravity = "WGS84"\n\n'
        "[gravimeter]\n"
        f'model = "{cfg["gravimeter_model"]}"\n'
        f"tau_s = {cfg['tau_declared_s']}\n"
        f"scale = {cfg['scale']}\n"
        f"rate_hz = {cfg['gravimeter_rate_hz']}\n\n"
        "[processing]\n", encoding="utf-8")


def simulate(cfg: dict, out_dir) -> Path:
    """Generate the survey of ``cfg`` (see :func:`draw_config`) into ``out_dir`` (replaced)."""
    import pyproj

    out_dir = Path(out_dir)
    rng = np.random.default_rng(np.random.SeedSequence([int(cfg["seed"]), 0x5EED, int(cfg["clean"])]))
    epsg = _utm_epsg(cfg["lat0"], cfg["lon0"])
    crs = f"EPSG:{epsg}"
    fwd = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    inv = pyproj.Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
    e0, n0 = fwd.transform(cfg["lon0"], cfg["lat0"])

    def to_geo(x_m, y_m):
        lon, lat = inv.transform(e0 + np.asarray(x_m), n0 + np.asarray(y_m))
        return np.asarray(lat), np.asarray(lon)

    th = np.deg2rad(cfg["heading_deg"])
    du = np.array([np.sin(th), np.cos(th)])       # heading clockwise from grid north
    dw = np.array([-du[1], du[0]])

    def rot(uw):
        return uw[0] * du + uw[1] * dw

    legs = _layout(cfg)
    flights = _assign_flights(cfg, legs, rng)
    if cfg["tare"]:
        cfg = {**cfg, "_tare_flight": int(rng.integers(len(flights)))}
    # planned line points (km, absolute) and extent, for the field and the zone
    pts = []
    for lg in legs:
        a, b = rot(np.array(lg["uw0"])), rot(np.array(lg["uw1"]))
        s = np.linspace(0, 1, max(2, int(np.hypot(*(b - a)) / 200.0)))[:, None]
        pts.append(a + s * (b - a))
    pts = np.concatenate(pts) / 1000.0 + np.array([e0, n0]) / 1000.0
    # flight start times (successive days) and a dry run of the paths for the extent
    t0s = [float(f * 86400 + 7 * 3600 + int(rng.integers(0, 3600))) for f in range(len(flights))]
    ext = [np.inf, -np.inf, np.inf, -np.inf]
    for fl, t0 in zip(flights, t0s):
        p, _ = _plan_flight(cfg, fl, t0, np.random.default_rng(0), rot)
        xx, yy, _, _ = p.eval(np.arange(p.t0, p.t1, 2.0))
        ext = [min(ext[0], xx.min()), max(ext[1], xx.max()), min(ext[2], yy.min()), max(ext[3], yy.max())]
    ext_km = (e0 / 1000 + ext[0] / 1000, e0 / 1000 + ext[1] / 1000, n0 / 1000 + ext[2] / 1000, n0 / 1000 + ext[3] / 1000)
    # drape: smooth surface tied to the mountain zone (set up after the zone: a first field pass)
    heights = np.array([cfg["height_m"] - 60.0, cfg["height_m"] + 60.0])
    drape_fn = None
    field_rng = np.random.default_rng(np.random.SeedSequence([int(cfg["seed"]), 0xF1E1D]))
    if cfg["draped"]:
        zone_probe = _Field.__new__(_Field)
        zone_probe.fc = cfg["field"]
        zone_probe.centre = np.array([e0, n0]) / 1000.0
        zone_probe._zone_setup(pts, np.random.default_rng(np.random.SeedSequence([int(cfg["seed"]), 0xF1E1D])))
        from scipy.ndimage import gaussian_filter

        gx = np.arange(ext_km[0] - 5, ext_km[1] + 5, 0.5)
        gy = np.arange(ext_km[2] - 5, ext_km[3] + 5, 0.5)
        GX, GY = np.meshgrid(gx, gy)
        drng = np.random.default_rng(np.random.SeedSequence([int(cfg["seed"]), 0xD4A]))
        surf = zone_probe.mountain(GX, GY).astype(float) + 0.3 * gaussian_filter(drng.standard_normal(GX.shape), 8.0) * 20
        surf = gaussian_filter(surf, 10.0)      # 5 km smoothing
        surf = (surf - surf.min()) / (surf.max() - surf.min() + 1e-12)
        slope = np.max(np.hypot(*np.gradient(surf, 500.0)))
        amp = min(cfg["drape_amp_m"], 0.03 / max(slope, 1e-9))        # climb gradient ≤ 3 %
        spl = RectBivariateSpline(gy, gx, amp * surf)
        drape_fn = lambda X, Y: spl.ev(Y, X)   # noqa: E731
        heights = np.array([cfg["height_m"] - 60.0, cfg["height_m"] + amp + 60.0])
        cfg = {**cfg, "_drape_amp_used_m": float(amp)}
    field = _Field(cfg, ext_km, pts, heights, (e0 / 1000.0, n0 / 1000.0), field_rng)
    tmp = Path(tempfile.mkdtemp(prefix=out_dir.name + ".", dir=out_dir.parent if out_dir.parent.exists() else None))
    try:
        all_truth, all_lines, finfo = [], [], {}
        for fidx, (fl, t0) in enumerate(zip(flights, t0s)):
            name = f"F{fidx + 1:02d}"
            grav, gnss, truth, lines, info = _simulate_flight(cfg, rng, name, fl, t0, rot, field, to_geo,
                                                              (e0 / 1000.0, n0 / 1000.0), drape_fn, fidx)
            d = tmp / "flights" / name
            d.mkdir(parents=True)
            comp = {"method": "gzip", "compresslevel": 1}
            grav.to_csv(d / "gravimeter.csv.gz", index=False, float_format="%.9f", compression=comp)
            gnss.to_csv(d / "gnss.csv.gz", index=False, compression=comp)
            all_truth.append(truth)
            all_lines.extend(lines)
            finfo[name] = info
        _write_toml(tmp / "survey.toml", cfg, crs)
        pd.DataFrame(all_lines).to_csv(tmp / "lines.csv", index=False)
        (tmp / "truth").mkdir()
        tr = pd.concat(all_truth, ignore_index=True)
        tr.to_parquet(tmp / "truth" / "lines.parquet", index=False)
        tj = {"generator": "benchmarks/foreign_sim.py", "config": cfg, "crs": crs, "centre_en_m": [e0, n0],
              "field": field.info(), "flights": finfo,
              "terrain_fraction_mountain": float(np.mean(tr["state_true"])),
              "truth_std_mgal": float(tr["dg_true_mgal"].std()),
              "dg_true_definition": "mean of the injected anomaly over the GNSS interval (t_{k-1}, t_k] "
                                    "(dg_point_mgal: at t_k); mGal relative to WGS84 normal gravity"}
        (tmp / "truth" / "truth.json").write_text(json.dumps(tj, indent=1, default=float))
        if not cfg["draped"]:
            _write_grid(tmp / "truth" / "grid.nc", field, cfg, crs)
        if out_dir.exists():
            shutil.rmtree(out_dir)
        tmp.rename(out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def _write_grid(path: Path, field: _Field, cfg: dict, crs: str) -> None:
    import xarray as xr

    gx = field.gx[::4]
    gy = field.gy[::4]
    GX, GY = np.meshgrid(gx, gy)
    dg = field.at(GX.ravel(), GY.ravel(), np.full(GX.size, cfg["height_m"])).reshape(GX.shape)
    ds = xr.Dataset({"dg": (("northing_km", "easting_km"), dg, {"units": "mGal"}),
                     "mountain": (("northing_km", "easting_km"), field.mountain(GX, GY).astype(np.int8))},
                    coords={"northing_km": gy, "easting_km": gx}, attrs={"crs": crs, "height_m": cfg["height_m"]})
    ds.to_netcdf(path)


def summary(cfg: dict) -> str:
    """One-line description of a configuration."""
    lay = ("testline 40 km x4" if cfg["layout"] == "testline" else
           f"{cfg['n_main']}x{cfg['main_length_km']:.0f} km/{cfg['line_spacing_km']:.1f} km+{cfg['n_tie']}T"
           + ("+R" if cfg["repeat_group"] else "") + f" {cfg['n_flights']}F")
    return (f"{lay}; {cfg['gravimeter']} tau {cfg['tau_declared_s']:g}; GNSS {cfg['gnss_rate_hz']:g} Hz "
            f"{cfg['gnss_velocity']}; turb {cfg['turbulence_rms_ms2']:.2f}; "
            f"{'draped' if cfg['draped'] else 'const'} {cfg['height_m']:.0f} m; "
            f"{cfg['airspeed_ms']:.0f} m/s; ratio {cfg['field']['mountain_power_ratio']:.0f}"
            + ("; tare" if cfg["tare"] else ""))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--clean", action="store_true", help="no errors of any kind, smooth motion")
    ap.add_argument("--clean-turbulent", action="store_true", help="no errors, the drawn motion")
    ap.add_argument("--set", nargs="*", default=[], help="key=value overrides (JSON values)")
    a = ap.parse_args()
    cfg = draw_config(a.seed)
    if a.clean:
        cfg = clean_config(cfg)
    elif a.clean_turbulent:
        cfg = clean_config(cfg, smooth_motion=False)
    for kv in a.set:
        k, v = kv.split("=", 1)
        if k == "gravimeter":
            cfg = set_gravimeter(cfg, v)
        else:
            cfg[k] = json.loads(v)
    print(summary(cfg))
    simulate(cfg, a.out)
    print(a.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
