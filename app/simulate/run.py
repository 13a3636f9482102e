"""Survey simulator: ``simulate_survey(preset, out_dir, seed, progress, **overrides)``.

Physics (SPEC §1, "up" positive).  For every flight, on one time scale:

* true vertical specific force (m/s²)
  ``f = a_up + γ(φ, h)/1e5 + δg/1e5 − E/1e5 + drift/1e5 + noise``
  with γ from :func:`app.core.geodesy.normal_gravity_mgal` (the survey's model) and
  E from :func:`app.core.geodesy.eotvos_mgal` at the true position and velocity;
* gravimeter output ``f'`` from ``τ·ḟ' + k·f' = f`` (solved exactly), sampled at
  18.24 Hz as the mean of ``f'`` over each sampling interval, stamped at the
  interval centre + ``time_offset_s`` and rounded to 1 ms;
* GNSS at 10 Hz on exact multiples of 0.1 s: true position/velocity + white noise
  (vertical velocity noise with noisy episodes);
* parking-place (base) readings (``apron_s > 0``): the aircraft stands still at the
  airport (fixed lat/lon, ``airport_h_m``) for ``apron_s`` before and after each flight,
  separated from the airborne data by an unrecorded gap of ``apron_gap_s`` (taxi, climb)
  in both files.  At rest the gravimeter input is ``f = g_base + drift + noise``
  (``g_base`` = ``[gravimeter] base_gravity_mgal``), through the same lag and scale, on
  the instrument's continuous sampling grid; the drift runs on through the gaps.

Realistic regimes (docs/SIMULATOR.md; all off by default, the original presets are unchanged):

* platform gravimeter: point samples or interval means (``gravimeter_sampling``) on a free or
  aligned clock (exact multiples of the period), behind an internal zero-phase FIR of cascaded
  boxcars (``gravimeter_fir_*``, exact for piecewise polynomials) and the lag ``tau_true_s``,
  neither of which the processing is told (``survey.toml`` has ``tau_declared_s``);
* heavy turbulence with a peaked spectrum (``turbulence_spectrum = "peaked"``);
* draped flight (``drape_amp_m``): the height follows a smooth surface of the position, the
  gravimeter and GNSS see its exact acceleration/velocity, and ``dg_true`` is the anomaly of the
  point sources at the actual height (``truth/grid.nc`` stays at ``height_m``);
* heights-only GNSS (``gnss_velocity = False``: time, lat, lon, h) with a Gauss–Markov height
  error (``h_colored_m``) on top of the white one.

The injected δg is built so that its mean over every GNSS interval (t_{k−1}, t_k]
is exactly ``dg_true_mgal[k]`` of ``truth/lines.parquet``; the true vertical
velocity is the exact integral of the true vertical acceleration.  So with all
noise, drift, lag and scale error switched off,
``z_k = f̄_k − (V_k − V_{k−1})/Δt − γ_k + E_k = dg_true_k`` up to the difference
between the interval means and the epoch values of γ and E (≪ 0.01 mGal on lines).
"""

from __future__ import annotations

import dataclasses
import time as _time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
import xarray as xr
from scipy.interpolate import CubicSpline, LinearNDInterpolator, PPoly, make_interp_spline

from app.core.geodesy import (
    OMEGA_EARTH,
    eotvos_mgal,
    normal_gravity_mgal,
    project_km,
    radii_of_curvature_m,
    unproject_km,
)
from app.io.survey_writer import GNSS_HEIGHTS_ONLY_COLUMNS, write_survey
from app.simulate.field import make_field
from app.simulate.markov import empirical_transition, make_state_map, markov_line
from app.simulate.motion import layout_lines, make_drape, plan_flight, vertical_motion
from app.simulate.presets import PRESETS, SimConfig
from app.simulate.sensors import (
    LaggedResponse,
    LaggedResponseN,
    fir_gain,
    fir_pp,
    gauss_markov,
    noise_episodes,
    quadratic_from_means,
    sigma_factor,
)
from app.simulate.topography import make_topography

MGAL = 1e-5  # m/s² per mGal

# tags of the auxiliary random streams (np.random.SeedSequence([seed, tag, flight index])): options
# draw from their own streams so that switching one on leaves the rest of the survey unchanged
_TAG_VU_COLORED = 0xC01
_TAG_VU_POSITION = 0xB05
_TAG_H_COLORED = 0x4C0
_TAG_H_COLORED_APRON = 0x4CA
_TAG_DRAPE = 0xD4A
_TAG_TOPO = 0x7090


def _aux_rng(seed, tag: int, index: int = 0) -> np.random.Generator:
    """A deterministic auxiliary stream: same (seed, tag, index), same numbers, in every process."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(tag), int(index)]))


def _legacy_gravimeter(cfg: SimConfig) -> bool:
    """The original GT-1A sampling: interval means on a free-running clock, no internal filter."""
    return (cfg.gravimeter_sampling == "mean" and cfg.gravimeter_clock == "free"
            and cfg.gravimeter_fir_boxcars == 0)


def _check_regime(cfg: SimConfig) -> None:
    if cfg.gravimeter_sampling not in ("mean", "point"):
        raise ValueError(f"gravimeter_sampling must be 'mean' or 'point', not {cfg.gravimeter_sampling!r}")
    if cfg.gravimeter_clock not in ("free", "aligned"):
        raise ValueError(f"gravimeter_clock must be 'free' or 'aligned', not {cfg.gravimeter_clock!r}")
    if cfg.gravimeter_fir_boxcars < 0 or (cfg.gravimeter_fir_boxcars > 0 and cfg.gravimeter_fir_width_s <= 0):
        raise ValueError("gravimeter_fir_boxcars > 0 needs gravimeter_fir_width_s > 0")
    if cfg.field_std_over not in ("grid", "lines"):
        raise ValueError(f"field_std_over must be 'grid' or 'lines', not {cfg.field_std_over!r}")
    if cfg.drape_amp_m > 0 and cfg.field_kind != "sources":
        raise ValueError("draped flight (drape_amp_m > 0) needs field_kind = 'sources'")
    if cfg.topo_amp_m > 0 and cfg.field_kind != "sources":
        raise ValueError("topography (topo_amp_m > 0) needs field_kind = 'sources'")
    if cfg.topo_clearance_m > 0 and cfg.topo_amp_m <= 0:
        raise ValueError("terrain-following flight (topo_clearance_m > 0) needs topography (topo_amp_m > 0)")
    if cfg.topo_clearance_m > 0 and cfg.drape_amp_m > 0:
        raise ValueError("choose one drape: drape_amp_m (plane waves) or topo_clearance_m (terrain following)")
    if cfg.repeat_height_offsets_m and cfg.field_kind != "sources":
        raise ValueError("repeat passes at other heights (repeat_height_offsets_m) need field_kind = 'sources'")


def _fir_half_s(cfg: SimConfig) -> float:
    return 0.5 * cfg.gravimeter_fir_boxcars * cfg.gravimeter_fir_width_s


def _instrument_output(comps, cfg: SimConfig, times, edges) -> np.ndarray:
    """Sum over input components (PPoly, m/s²) of the gravimeter output (new regimes).

    Each component goes through the internal zero-phase FIR (``gravimeter_fir_*``, exact), the
    lag and scale (``τ·ẏ + k·y = u``, exact) and is then sampled: at ``times`` ("point") or as the
    mean over ``[edges[j], edges[j+1]]`` ("mean").
    """
    out = np.zeros(len(times))
    for pp in comps:
        if cfg.gravimeter_fir_boxcars > 0:
            pp = fir_pp(pp, cfg.gravimeter_fir_boxcars, cfg.gravimeter_fir_width_s)
        lr = LaggedResponseN(pp, cfg.tau_true_s, cfg.scale_true)
        out += lr.y(times) if cfg.gravimeter_sampling == "point" else lr.interval_means(edges)
    return out


def _sample_lattice(cfg: SimConfig, origin: float, lo: float, hi: float):
    """Samples whose intervals ``[t − P/2, t + P/2]`` lie in ``[lo, hi]`` on the lattice of interval
    edges ``origin + j·P`` (P = 1/rate).  Returns ``(times, edges)``; with the aligned clock the times
    are exact multiples of P (computed as ``j/rate``)."""
    rate = cfg.gravimeter_rate_hz
    j0 = int(np.ceil((lo - origin) * rate - 1e-9))
    j1 = int(np.floor((hi - origin) * rate + 1e-9))
    j = np.arange(j0, j1 + 1)
    if cfg.gravimeter_clock == "aligned":
        edges = (j - 0.5) / rate
        times = j[:-1] / rate
    else:
        edges = origin + j / rate
        times = 0.5 * (edges[:-1] + edges[1:])
    return times, edges


def _cubic_pp(t, y) -> PPoly:
    cs = CubicSpline(t, y, bc_type="not-a-knot")
    return PPoly(cs.c, cs.x)


def _geo_state(path, tq, h, cfg, e0_km, n0_km):
    """Latitude, longitude and geographic velocities at times ``tq`` (exact path)."""
    x = path.x_pp(tq) / 1000.0 + e0_km
    y = path.y_pp(tq) / 1000.0 + n0_km
    lon, lat = unproject_km(x, y, cfg.crs)
    dt = 0.005
    lon_p, lat_p = unproject_km(path.x_pp(tq + dt) / 1000.0 + e0_km, path.y_pp(tq + dt) / 1000.0 + n0_km, cfg.crs)
    lon_m, lat_m = unproject_km(path.x_pp(tq - dt) / 1000.0 + e0_km, path.y_pp(tq - dt) / 1000.0 + n0_km, cfg.crs)
    r_m, r_n = radii_of_curvature_m(lat)
    dlat = np.deg2rad(lat_p - lat_m) / (2 * dt)
    dlon = np.deg2rad(lon_p - lon_m) / (2 * dt)
    ve = dlon * (r_n + h) * np.cos(np.deg2rad(lat))
    vn = dlat * (r_m + h)
    return x, y, lat, lon, ve, vn


def _extend_drift(drift_pp: PPoly, td, rw, off, rate, t0, t_lo, t_hi, cfg, rng) -> PPoly:
    """The drift beyond the airborne span, continuous with it (it keeps running on the ground).

    The random walk continues from its first node backwards and from its last node forwards on the
    same 10 s grid (steps from ``rng``); outside ``[td[0], td[-1]]`` the drift is a cubic spline
    through the new nodes and the three nearest airborne nodes, inside it is ``drift_pp`` itself
    (so the airborne data do not change).  The result is continuous at the splice nodes.
    """
    step = cfg.drift_rw_mgal_rth * np.sqrt(10.0 / 3600.0)
    nb = max(int(np.ceil((td[0] - t_lo) / 10.0)), 3)
    na = max(int(np.ceil((t_hi - td[-1]) / 10.0)), 3)
    tb = td[0] - 10.0 * np.arange(nb, 0, -1)
    ta = td[-1] + 10.0 * np.arange(1, na + 1)
    rwb = rw[0] - np.cumsum(rng.standard_normal(nb) * step)[::-1]
    rwa = rw[-1] + np.cumsum(rng.standard_normal(na) * step)
    lin = lambda t: off + rate * (t - t0) / 3600.0  # noqa: E731
    air = drift_pp(td[:3]), drift_pp(td[-3:])
    sb = _cubic_pp(np.concatenate([tb, td[:3]]), np.concatenate([(lin(tb) + rwb) * MGAL, air[0]]))
    sa = _cubic_pp(np.concatenate([td[-3:], ta]), np.concatenate([air[1], (lin(ta) + rwa) * MGAL]))
    c = np.concatenate([sb.c[:, :nb], drift_pp.c, sa.c[:, 2:]], axis=1)
    x = np.concatenate([tb, drift_pp.x, ta])
    return PPoly(c, x)


def _apron_segments(path, cfg: SimConfig):
    """GNSS spans ``(name, t_start, t_end)`` of the static segments before and after a flight."""
    if cfg.apron_s <= 0:
        return []
    a1 = round(path.t0 - cfg.apron_gap_s, 1)
    b0 = round(path.t1 + cfg.apron_gap_s, 1)
    return [("before", round(a1 - cfg.apron_s, 1), a1), ("after", b0, round(b0 + cfg.apron_s, 1))]


class ApronReadings(NamedTuple):
    """Result of :func:`simulate_apron` (unpacks as ``gravimeter, gnss, info``)."""

    gravimeter: pd.DataFrame   # static gravimeter rows
    gnss: pd.DataFrame         # static GNSS rows
    info: dict                 # truth of the segment (spans, true drift)


def simulate_apron(seg, cfg: SimConfig, rng, airport: dict, drift_full: PPoly, g_start: float,
                   h_rng=None) -> ApronReadings:
    """Static readings on the apron over the GNSS span ``seg = (name, a, b)``.

    The gravimeter reads the true specific force at rest ``f = g_base`` (+ drift + noise) through
    the same lag and scale as in flight, on the instrument's continuous 18.24 Hz sampling grid
    (the one started at ``g_start``); only intervals wholly inside ``[a, b]`` are written.  New
    regimes (internal FIR, point samples, aligned clock) sample the same way as in flight; ``h_rng``
    draws the coloured height error of the static GNSS (``h_colored_m``).
    """
    name, a, b = seg
    n = int(round((b - a) * cfg.gnss_rate_hz)) + 1
    tg = a + np.arange(n) / cfg.gnss_rate_hz
    lat0, lon0, h0 = airport["lat_deg"], airport["lon_deg"], airport["h_m"]
    # --- gravimeter
    legacy = _legacy_gravimeter(cfg)
    if legacy:
        rate_g = cfg.gravimeter_rate_hz
        j0 = int(np.ceil((a - g_start) * rate_g))
        j1 = int(np.floor((b - g_start) * rate_g))
        edges = g_start + np.arange(j0, j1 + 1) / rate_g
        edges = edges[(edges >= a) & (edges <= b)]
        centres = 0.5 * (edges[:-1] + edges[1:])
    else:
        centres, edges = _sample_lattice(cfg, g_start, a, b)
    m = edges.size - 1
    cref = airport["g_base_mgal"] * MGAL
    fz = np.full(m, cref / cfg.scale_true)
    comps = [drift_full]
    if cfg.grav_noise_mgal_rthz > 0:
        fs = cfg.fine_rate_hz
        tn = np.arange(a - 20.0, b + 10.0, 1.0 / fs)
        sd = cfg.grav_noise_mgal_rthz * np.sqrt(fs) * MGAL
        comps.append(_cubic_pp(tn, rng.standard_normal(tn.size) * sd))
    if legacy:
        for pp in comps:
            fz += LaggedResponse(pp, cfg.tau_true_s, cfg.scale_true).interval_means(edges)
    else:
        fz += _instrument_output(comps, cfg, centres, edges)
    grav = pd.DataFrame({"time": np.round(centres + cfg.time_offset_s, 3), "f_z": fz,
                         "f_x": rng.standard_normal(m) * cfg.horizontal_noise_ms2,
                         "f_y": rng.standard_normal(m) * cfg.horizontal_noise_ms2})
    # --- GNSS at rest: position noise (cm), velocity noise at the usual (quiet) level
    r_m, r_n = radii_of_curvature_m(lat0)
    sig_vu = np.full(n, cfg.sigma_vu_cms / 100.0)
    gnss = pd.DataFrame({
        "time": tg,
        "lat": lat0 + np.rad2deg(rng.standard_normal(n) * cfg.sigma_pos_m / (r_m + h0)),
        "lon": lon0 + np.rad2deg(rng.standard_normal(n) * cfg.sigma_pos_m / ((r_n + h0) * np.cos(np.deg2rad(lat0)))),
        "h": h0 + rng.standard_normal(n) * cfg.sigma_h_m,
        "vu": rng.standard_normal(n) * sig_vu,
        "ve": rng.standard_normal(n) * cfg.sigma_vh_cms / 100.0,
        "vn": rng.standard_normal(n) * cfg.sigma_vh_cms / 100.0,
        "sigma_v": sig_vu * np.exp(rng.normal(0.0, 0.2, n)),
    })
    if cfg.h_colored_m > 0 and h_rng is not None:
        gnss["h"] += gauss_markov(tg, cfg.h_colored_m, cfg.h_colored_tau_s, h_rng)
    if not cfg.gnss_velocity:
        gnss = gnss[["time", "lat", "lon", "h"]]
    D = drift_full.antiderivative()
    info = {"segment": name, "t_start": a, "t_end": b,
            "gravimeter_t_start": float(edges[0]), "gravimeter_t_end": float(edges[-1]),
            "drift_mean_mgal": float((D(edges[-1]) - D(edges[0])) / (edges[-1] - edges[0]) / MGAL),
            "drift_start_mgal": float(drift_full(edges[0]) / MGAL),
            "drift_end_mgal": float(drift_full(edges[-1]) / MGAL)}
    return ApronReadings(grav, gnss, info)


@dataclass
class _TrueMotion:
    """True state of the aircraft at the GNSS epochs of one flight (and the motion polynomials)."""

    a_pp: PPoly            # vertical acceleration (m/s²) of the turbulence/phugoid motion
    h_pp: PPoly            # its height (m)
    d_pp: PPoly | None     # draped height above height_m (m), None without a drape
    info: dict             # motion truth for truth.json
    h: np.ndarray          # ellipsoidal height (m)
    vu: np.ndarray         # vertical velocity (m/s)
    x: np.ndarray          # easting (km, absolute)
    y: np.ndarray          # northing (km)
    lat: np.ndarray
    lon: np.ndarray
    ve: np.ndarray         # east and north velocity (m/s)
    vn: np.ndarray
    gamma: np.ndarray      # normal gravity (mGal)
    eot: np.ndarray        # Eötvös (mGal)


def _pass_height_offset_m(path, cfg: SimConfig, ts: np.ndarray) -> np.ndarray:
    """Height offset (m) of the repeat passes (``repeat_height_offsets_m``) at times ``ts``: pass r's
    offset is held from the start of its run-in to the end of its run-out (other lines: 0), and
    eased with a half cosine between consecutive lines (in the turns)."""
    offs = tuple(float(v) for v in cfg.repeat_height_offsets_m)
    held = []                                   # (t_start, t_end, offset) per line, in flying order
    for ln, ta, tb in path.windows:
        off = 0.0
        if ln.kind == "repeat":
            r = int(str(ln.line).rsplit("-", 1)[-1]) - 1
            off = offs[r % len(offs)]
        held.append((ta - cfg.run_in_s, tb + cfg.run_out_s, off))
    out = np.full(ts.shape, held[0][2] if held else 0.0)
    for (_a0, a1, oa), (b0, _b1, ob) in zip(held[:-1], held[1:]):
        s = np.clip((ts - a1) / max(b0 - a1, 1e-9), 0.0, 1.0)
        ramp = oa + (ob - oa) * 0.5 * (1.0 - np.cos(np.pi * s))
        out = np.where(ts > a1, ramp, out)
    return out


def _true_motion(path, cfg: SimConfig, rng, tg, e0_km, n0_km, drape) -> _TrueMotion:
    """Vertical motion (exact piecewise cubic acceleration and its integrals), the optional drape
    (and repeat passes at their own heights), and position, velocity, normal gravity and Eötvös at
    the GNSS epochs ``tg``."""
    a_pp, v_pp, h_pp, motion_info = vertical_motion(path.t0, path.t1, cfg, rng)
    d_pp = None
    if drape is not None or cfg.repeat_height_offsets_m:
        # draped height as an exact quintic spline in time through 1 s samples along the path;
        # its first and second derivatives are the drape's vertical velocity and acceleration
        ts = np.arange(path.t0 - 40.0, path.t1 + 40.0 + 0.5, 1.0)
        d = drape(path.x_pp(ts), path.y_pp(ts)) if drape is not None else np.zeros(ts.size)
        if cfg.repeat_height_offsets_m:
            d = d + _pass_height_offset_m(path, cfg, ts)
        d_pp = PPoly.from_spline(make_interp_spline(ts, d, k=5))
        h = cfg.height_m + h_pp(tg) + d_pp(tg)
        vu = v_pp(tg) + d_pp.derivative()(tg)
    else:
        h = cfg.height_m + h_pp(tg)
        vu = v_pp(tg)
    x, y, lat, lon, ve, vn = _geo_state(path, tg, h, cfg, e0_km, n0_km)
    gamma = normal_gravity_mgal(lat, h, cfg.normal_gravity)
    eot = eotvos_mgal(lat, h, ve, vn)
    return _TrueMotion(a_pp, h_pp, d_pp, motion_info, h, vu, x, y, lat, lon, ve, vn, gamma, eot)


def _anomaly_means(path, cfg: SimConfig, tg, e0_km, n0_km, motion: _TrueMotion, dg_means_fn):
    """δg over each GNSS interval (t_{k−1}, t_k] from the positions (and, draped, the heights) at
    the interval midpoints: ``(dg_mgal, extra truth columns)``."""
    dt = 1.0 / cfg.gnss_rate_hz
    tm = tg - 0.5 * dt
    xm = path.x_pp(tm) / 1000.0 + e0_km
    ym = path.y_pp(tm) / 1000.0 + n0_km
    if motion.d_pp is not None:
        return dg_means_fn(tg, xm, ym, cfg.height_m + motion.h_pp(tm) + motion.d_pp(tm))
    return dg_means_fn(tg, xm, ym)


@dataclass
class _Drift:
    """Gravimeter drift of one flight: offset + linear rate + random walk on a 10 s grid."""

    rate_mgal_h: float
    offset_mgal: float
    td: np.ndarray         # random-walk nodes (s)
    rw: np.ndarray         # random walk at the nodes (mGal)
    pp: PPoly              # the drift as a cubic spline (m/s²)


def _draw_drift(cfg: SimConfig, rng, t0: float, t1: float) -> _Drift:
    """The flight's drift (mGal): random sign and rate, offset, random walk."""
    rate = float(rng.uniform(*cfg.drift_rate_mgal_h)) * float(rng.choice([-1.0, 1.0]))
    if cfg.drift_rate_mgal_h[1] == 0.0:
        rate = 0.0
    off = float(rng.normal(0.0, cfg.drift_offset_std_mgal)) if cfg.drift_offset_std_mgal > 0 else 0.0
    td = np.arange(t0 - 30.0, t1 + 40.0, 10.0)
    rw = np.cumsum(rng.standard_normal(td.size)) * cfg.drift_rw_mgal_rth * np.sqrt(10.0 / 3600.0)
    drift_d = off + rate * (td - t0) / 3600.0 + rw
    return _Drift(rate, off, td, rw, _cubic_pp(td, drift_d * MGAL))


def _gravimeter_inputs(cfg: SimConfig, rng, motion: _TrueMotion, tg, dg, drift: _Drift, t0: float, t1: float):
    """Inputs of the gravimeter ODE, each an exact piecewise polynomial (m/s²), and the constant
    ``cref`` (m/s²) taken out of the slowly varying part: ``(components, cref)``."""
    slow = (motion.gamma - motion.eot) * MGAL
    cref = float(np.round(np.mean(slow), 3))
    comps = [motion.a_pp, _cubic_pp(tg, slow - cref), quadratic_from_means(tg, dg * MGAL), drift.pp]
    if motion.d_pp is not None:
        comps.append(motion.d_pp.derivative(2))
    fs = cfg.fine_rate_hz
    noise_sd_mgal = cfg.grav_noise_mgal_rthz * np.sqrt(fs)
    if cfg.grav_noise_mgal_rthz > 0:
        tn = np.arange(t0 - 10.0, t1 + 10.0, 1.0 / fs)
        comps.append(_cubic_pp(tn, rng.standard_normal(tn.size) * noise_sd_mgal * MGAL))
    return comps, cref


@dataclass
class _GravimeterSamples:
    """The gravimeter's vertical readings of one flight (true time)."""

    centres: np.ndarray    # sample times (interval centres, or point-sample times)
    edges: np.ndarray      # interval edges
    f_z: np.ndarray        # readings (m/s²)
    g_start: float         # origin of the sampling lattice (first interval start, free clock)


def _sample_gravimeter(comps, cref: float, cfg: SimConfig, rng, t0: float, t1: float) -> _GravimeterSamples:
    """The instrument's output sampled at its rate: a random clock phase, then either the original
    GT-1A interval means or the new regimes (internal FIR, point or mean samples, free or aligned
    clock: lattice origin ``g_start``, or −P/2 so that the samples sit on exact multiples of P)."""
    rate_g = cfg.gravimeter_rate_hz
    phase = float(rng.uniform(0.0, 1.0 / rate_g))
    g_start = t0 + 20.0 + phase      # ≥ 10 τ after the ODE inputs start
    if _legacy_gravimeter(cfg):
        m = int(np.floor((t1 - 1.0 - g_start) * rate_g))
        edges = g_start + np.arange(m + 1) / rate_g
        fz = np.full(m, cref / cfg.scale_true)
        for pp in comps:
            fz += LaggedResponse(pp, cfg.tau_true_s, cfg.scale_true).interval_means(edges)
        centres = 0.5 * (edges[:-1] + edges[1:])
    else:
        if cfg.gravimeter_clock == "aligned":
            g_start = -0.5 / rate_g
        centres, edges = _sample_lattice(cfg, g_start, t0 + 20.0 + _fir_half_s(cfg),
                                         t1 - 1.0 - _fir_half_s(cfg))
        fz = np.full(centres.size, cref / cfg.scale_true) + _instrument_output(comps, cfg, centres, edges)
    return _GravimeterSamples(centres, edges, fz, g_start)


def _gravimeter_table(path, cfg: SimConfig, rng, motion: _TrueMotion, tg, smp: _GravimeterSamples) -> pd.DataFrame:
    """``gravimeter.csv`` rows: stamped vertical readings and the horizontal specific force
    (east, north) at the sample centres, kinematic + Coriolis + noise."""
    m = smp.centres.size
    centres = smp.centres
    ae = path.x_pp.derivative(2)(centres)
    an = path.y_pp.derivative(2)(centres)
    latc = np.interp(centres, tg, motion.lat)
    vec = np.interp(centres, tg, motion.ve)
    vnc = np.interp(centres, tg, motion.vn)
    vuc = np.interp(centres, tg, motion.vu)
    s_, c_ = np.sin(np.deg2rad(latc)), np.cos(np.deg2rad(latc))
    fx = ae + 2 * OMEGA_EARTH * (c_ * vuc - s_ * vnc) + rng.standard_normal(m) * cfg.horizontal_noise_ms2
    fy = an + 2 * OMEGA_EARTH * s_ * vec + rng.standard_normal(m) * cfg.horizontal_noise_ms2
    return pd.DataFrame({"time": np.round(centres + cfg.time_offset_s, 3), "f_z": smp.f_z, "f_x": fx, "f_y": fy})


@dataclass
class _GnssRecord:
    """``gnss.csv`` rows of one flight and the true vertical-velocity noise behind them."""

    table: pd.DataFrame
    sigma_vu_ms: np.ndarray    # true vu noise std per epoch (m/s)
    episodes: list             # noisy episodes (t_start, t_end, sigma_factor)


def _gnss_record(cfg: SimConfig, rng, motion: _TrueMotion, tg, t0: float, t1: float, aux_seed: int,
                 flight_idx: int) -> _GnssRecord:
    """True position and velocity + white noise (vu noise with noisy episodes), the optional
    coloured errors from their own streams, heights only when ``cfg.gnss_velocity`` is False."""
    n = tg.size
    lat, lon, h = motion.lat, motion.lon, motion.h
    episodes = noise_episodes(t0, t1, cfg.episode_rate_per_h, cfg.episode_len_s, cfg.episode_factor, rng)
    sig_vu = cfg.sigma_vu_cms / 100.0 * sigma_factor(tg, episodes)       # m/s
    r_m, r_n = radii_of_curvature_m(lat)
    vu_extra = 0.0
    if cfg.vu_colored_cms > 0:
        vu_extra = vu_extra + _colored_noise(tg, cfg, _aux_rng(aux_seed, _TAG_VU_COLORED, flight_idx))
    if cfg.vu_from_position_m > 0:
        vu_extra = vu_extra + _position_derived_noise(tg, cfg, _aux_rng(aux_seed, _TAG_VU_POSITION, flight_idx))
    gnss = pd.DataFrame({
        "time": tg,
        "lat": lat + np.rad2deg(rng.standard_normal(n) * cfg.sigma_pos_m / (r_m + h)),
        "lon": lon + np.rad2deg(rng.standard_normal(n) * cfg.sigma_pos_m / ((r_n + h) * np.cos(np.deg2rad(lat)))),
        "h": h + rng.standard_normal(n) * cfg.sigma_h_m,
        "vu": motion.vu + rng.standard_normal(n) * sig_vu + vu_extra,
        "ve": motion.ve + rng.standard_normal(n) * cfg.sigma_vh_cms / 100.0,
        "vn": motion.vn + rng.standard_normal(n) * cfg.sigma_vh_cms / 100.0,
        # receiver's formal sigma: follows the true level, imperfectly
        "sigma_v": sig_vu * np.exp(rng.normal(0.0, 0.2, n)),
    })
    if cfg.h_colored_m > 0:
        gnss["h"] += gauss_markov(tg, cfg.h_colored_m, cfg.h_colored_tau_s,
                                  _aux_rng(aux_seed, _TAG_H_COLORED, flight_idx))
    if not cfg.gnss_velocity:
        gnss = gnss[["time", "lat", "lon", "h"]]
    return _GnssRecord(gnss, sig_vu, episodes)


def _add_aprons(path, cfg: SimConfig, apron_rng, airport: dict, drift: _Drift, g_start: float, aux_seed: int,
                flight_idx: int, grav: pd.DataFrame, gnss: pd.DataFrame):
    """Parking-place readings before and after the flight (their own random stream; the drift keeps
    running): ``(gravimeter, gnss, apron truth list)`` with the static rows added."""
    segs = _apron_segments(path, cfg)
    if not segs:
        return grav, gnss, []
    if apron_rng is None:
        raise ValueError("apron segments need apron_rng")
    drift_full = _extend_drift(drift.pp, drift.td, drift.rw, drift.offset_mgal, drift.rate_mgal_h, path.t0,
                               segs[0][1] - 60.0, segs[-1][2] + 60.0, cfg, apron_rng)
    parts = [simulate_apron(sg, cfg, apron_rng, airport, drift_full, g_start,
                            _aux_rng(aux_seed, _TAG_H_COLORED_APRON, 2 * flight_idx + j) if cfg.h_colored_m > 0
                            else None)
             for j, sg in enumerate(segs)]
    grav = pd.concat([parts[0].gravimeter, grav, parts[1].gravimeter], ignore_index=True)
    gnss = pd.concat([parts[0].gnss, gnss, parts[1].gnss], ignore_index=True)
    return grav, gnss, [p.info for p in parts]


def _truth_epochs(cfg: SimConfig, motion: _TrueMotion, tg, dg, extra: dict, sigma_vu_ms, drift_mgal) -> pd.DataFrame:
    """Truth per GNSS epoch, rounded far below every noise level (keeps the committed sample small)."""
    epochs = pd.DataFrame({
        "time": np.round(tg, 3), "easting_km": np.round(motion.x, 6), "northing_km": np.round(motion.y, 6),
        "dg_true_mgal": np.round(dg, 5), "R_true_cm2s2": (sigma_vu_ms * 100.0) ** 2,
        "drift_mgal": np.round(drift_mgal, 4), "vu_true_ms": np.round(motion.vu, 5),
    })
    if not cfg.gnss_velocity:
        epochs["R_true_cm2s2"] = np.nan      # no velocity in the file: no velocity noise level
    for k, v in extra.items():
        epochs[k] = v
    epochs["state_true"] = epochs["state_true"].astype(np.int8)
    cols = ["time", "easting_km", "northing_km", "dg_true_mgal", "terrain", "state_true",
            "Q_true_mgal2", "R_true_cm2s2", "drift_mgal", "vu_true_ms"]
    if "terrain_mgal" in epochs:
        cols.append("terrain_mgal")
    if _truth_has_height(cfg):
        epochs["h_true_m"] = motion.h        # true (draped, moving) ellipsoidal height, full precision
        cols.append("h_true_m")
    return epochs[cols]


def simulate_flight(path, cfg: SimConfig, rng, e0_km, n0_km, dg_means_fn, flight_idx: int = 0,
                    apron_rng=None, airport: dict | None = None, seed: int | None = None, drape=None):
    """Simulate one flight.

    Parameters
    ----------
    path : FlightPath
    dg_means_fn : callable
        ``dg_means_fn(t_epochs, x_km_mid, y_km_mid) -> (dg_mgal, extra)``: the mean of δg over
        each GNSS interval (t_{k−1}, t_k] (mGal); positions are absolute projected km
        at the interval midpoints.

    apron_rng : numpy.random.Generator, optional
        Random numbers of the parking-place segments (a separate stream, so the airborne data
        do not depend on ``cfg.apron_s``).
    airport : dict, optional
        ``lat_deg, lon_deg, h_m, g_base_mgal`` of the parking place; with ``cfg.apron_s > 0``
        static segments are added before and after the airborne data (see :func:`simulate_apron`).
    seed : int, optional
        Survey seed: the auxiliary streams (coloured GNSS errors) are
        ``SeedSequence([seed, tag, flight_idx])``; None uses a stable hash of the flight start.
    drape : app.simulate.motion.Drape, optional
        Draped flight surface (m above ``height_m`` as a function of position relative to the centre).

    Returns
    -------
    dict with ``gravimeter`` and ``gnss`` DataFrames, ``epochs`` (truth per GNSS epoch),
    ``info`` (per-flight truth for truth.json).
    """
    t0, t1 = path.t0, path.t1
    n = int(round((t1 - t0) * cfg.gnss_rate_hz)) + 1
    tg = t0 + np.arange(n) / cfg.gnss_rate_hz
    aux_seed = seed if seed is not None else zlib.crc32(repr((float(t0), path.name)).encode())
    # the main stream is drawn in this order: motion, anomaly (Markov), drift, sensor noise, clock
    # phase, horizontal noise, GNSS
    motion = _true_motion(path, cfg, rng, tg, e0_km, n0_km, drape)
    dg, extra = _anomaly_means(path, cfg, tg, e0_km, n0_km, motion, dg_means_fn)
    drift = _draw_drift(cfg, rng, t0, t1)
    comps, cref = _gravimeter_inputs(cfg, rng, motion, tg, dg, drift, t0, t1)
    smp = _sample_gravimeter(comps, cref, cfg, rng, t0, t1)
    grav = _gravimeter_table(path, cfg, rng, motion, tg, smp)
    rec = _gnss_record(cfg, rng, motion, tg, t0, t1, aux_seed, flight_idx)
    gnss, aprons = rec.table, []
    if airport is not None:
        grav, gnss, aprons = _add_aprons(path, cfg, apron_rng, airport, drift, smp.g_start, aux_seed,
                                         flight_idx, grav, gnss)
    epochs = _truth_epochs(cfg, motion, tg, dg, extra, rec.sigma_vu_ms, drift.pp(tg) / MGAL)
    info = {"t0": t0, "t1": t1, "drift_offset_mgal": drift.offset_mgal, "drift_rate_mgal_h": drift.rate_mgal_h,
            "drift_rw_mgal_rth": cfg.drift_rw_mgal_rth, "gravimeter_first_interval_start": smp.g_start,
            "gnss_noisy_episodes": [{"t_start": s, "t_end": e, "sigma_factor": f} for s, e, f in rec.episodes],
            "apron": aprons,
            **motion.info}
    if not _legacy_gravimeter(cfg):
        info["gravimeter_first_sample_time"] = float(smp.centres[0])
    return {"gravimeter": grav, "gnss": gnss, "epochs": epochs, "info": info}


def _extent(paths):
    xs, ys = [], []
    for p in paths:
        t = np.arange(p.t0, p.t1, 1.0)
        xs.append(p.x_pp(t) / 1000.0)
        ys.append(p.y_pp(t) / 1000.0)
    x = np.concatenate(xs)
    y = np.concatenate(ys)
    return float(x.min()), float(x.max()), float(y.min()), float(y.max())


def _plan_flights(cfg: SimConfig, planned, rng) -> list:
    """The lines split into ``cfg.n_flights`` consecutive flights, one :class:`FlightPath` each
    (flights on successive days, a random start within the hour)."""
    chunks = np.array_split(np.arange(len(planned)), max(1, min(cfg.n_flights, len(planned))))
    paths = []
    for i, ch in enumerate(chunks):
        t0 = float(round(cfg.epoch_offset_s + i * cfg.flight_spacing_s + rng.uniform(0, 3600)))
        paths.append(plan_flight(f"F{i + 1:02d}", [planned[j] for j in ch], t0, cfg, rng))
    return paths


def _line_points(planned) -> tuple[np.ndarray, np.ndarray]:
    """Points every ~0.1 km along the planned line windows (km relative to the centre)."""
    pts = []
    for ln in planned:
        a, b = np.array(ln.start_km), np.array(ln.end_km)
        k = max(2, int(np.hypot(*(b - a)) / 0.1) + 1)
        pts.append(a + np.linspace(0.0, 1.0, k)[:, None] * (b - a))
    P = np.concatenate(pts)
    return P[:, 0], P[:, 1]


class _SourcesAnomaly:
    """Point-source field (``field_kind = "sources"``), plus the topography's gravity when there is
    one: δg along each flight, and the truth grid."""

    def __init__(self, cfg: SimConfig, fld, topo):
        self.cfg, self.fld, self.topo = cfg, fld, topo

    def for_path(self, path):
        """``dg_means_fn`` of :func:`simulate_flight` for one flight."""
        cfg, fld, topo = self.cfg, self.fld, self.topo

        def fn(tg, xm, ym, hm=None):
            mnt = fld.terrain_mountain(xm, ym)
            val = fld(xm, ym) if hm is None else fld.at(xm, ym, hm)
            extra = {"terrain": np.where(mnt, "mountain", "plain"),
                     "state_true": mnt.astype(np.int64),
                     "Q_true_mgal2": np.full(tg.size, np.nan)}
            if topo is not None:
                tmg = topo.effect_along(tg, xm, ym, cfg.height_m if hm is None else hm,
                                        int(round(cfg.gnss_rate_hz)))
                val = val + tmg
                extra["terrain_mgal"] = np.round(tmg, 5)
            return val, extra
        return fn

    def truth_grid(self, truth_lines: pd.DataFrame) -> xr.Dataset:
        """``truth/grid.nc``: the field at flight height and the mountain mask."""
        cfg, fld = self.cfg, self.fld
        return xr.Dataset({"dg": (("northing_km", "easting_km"), fld.dg_mgal,
                                  {"units": "mGal", "long_name": "true gravity disturbance at flight height"}),
                           "mountain": (("northing_km", "easting_km"),
                                        fld.terrain_mountain(*np.meshgrid(fld.easting_km, fld.northing_km)).astype(np.int8))},
                          coords={"northing_km": fld.northing_km, "easting_km": fld.easting_km},
                          attrs={"crs": cfg.crs, "height_m": cfg.height_m})

    def truth_json(self) -> dict:
        """Nothing beyond ``field`` (already in the setup's ``truth_extra``)."""
        return {}


class _MarkovAnomaly:
    """Markov-jump anomaly (``field_kind = "markov"``, seed 000): states held on blocks of GNSS
    epochs following a state map; δg drawn per line window during the flights (main stream)."""

    def __init__(self, cfg: SimConfig, smap, rng, e0: float, n0: float):
        self.cfg, self.smap, self.rng, self.e0, self.n0 = cfg, smap, rng, e0, n0
        self.block_paths: list[np.ndarray] = []     # block states of every main line, in flying order

    def for_path(self, path):
        """``dg_means_fn`` of :func:`simulate_flight` for one flight."""
        cfg, smap, rng, e0, n0, block_paths = self.cfg, self.smap, self.rng, self.e0, self.n0, self.block_paths

        def fn(tg, xm, ym, hm=None):
            nq = tg.size
            dg = np.full(nq, np.nan)
            state = np.zeros(nq, np.int64)
            Q = np.full(nq, np.nan)
            for ln, ts, te in path.windows:
                i0 = int(round((ts - tg[0]) * cfg.gnss_rate_hz))
                i1 = int(round((te - tg[0]) * cfg.gnss_rate_hz))
                ne = i1 - i0 + 1
                nb = int(np.ceil(ne / cfg.markov_block_epochs))
                bc = i0 + np.minimum(np.arange(nb) * cfg.markov_block_epochs + cfg.markov_block_epochs // 2, ne - 1)
                sb = smap.state(xm[bc] - e0, ym[bc] - n0)
                if ln.kind == "main":
                    block_paths.append(sb)
                d, s, q = markov_line(ne, sb, cfg.markov_block_epochs, cfg.markov_Q_mgal2,
                                      float(rng.normal(0.0, cfg.markov_dg0_std_mgal)), rng)
                dg[i0:i1 + 1], state[i0:i1 + 1], Q[i0:i1 + 1] = d, s, q
            ok = np.isfinite(dg)
            dg = np.interp(tg, tg[ok], dg[ok])     # linear ramps through turns
            st = smap.state(xm - e0, ym - n0)
            state = np.where(np.isfinite(Q), state, st)
            return dg, {"terrain": np.where(state == 1, "mountain", "plain"),
                        "state_true": state, "Q_true_mgal2": Q}
        return fn

    def truth_grid(self, truth_lines: pd.DataFrame) -> xr.Dataset:
        """``truth/grid.nc``: the state map, and δg interpolated linearly between the lines (the
        Markov anomaly exists on the lines only; NaN outside them)."""
        cfg, smap, e0, n0 = self.cfg, self.smap, self.e0, self.n0
        xg, yg = smap.x_km + e0, smap.y_km + n0
        X, Y = np.meshgrid(smap.x_km, smap.y_km)
        st = smap.state(X, Y).astype(np.int8)
        sub = truth_lines.iloc[::50]
        lin = LinearNDInterpolator(sub[["easting_km", "northing_km"]].to_numpy(), sub["dg_true_mgal"].to_numpy())
        dgg = lin(X + e0, Y + n0)
        return xr.Dataset({"dg": (("northing_km", "easting_km"), dgg, {"units": "mGal"}),
                           "state": (("northing_km", "easting_km"), st)},
                          coords={"northing_km": yg, "easting_km": xg},
                          attrs={"crs": cfg.crs, "height_m": cfg.height_m,
                                 "note": "Markov preset: dg interpolated linearly between lines"})

    def truth_json(self) -> dict:
        """truth.json ``markov``: the model and the empirical transitions of the flown block states."""
        cfg, block_paths = self.cfg, self.block_paths
        P = empirical_transition(block_paths)
        pi = np.bincount(np.concatenate(block_paths), minlength=2) / sum(len(b) for b in block_paths)
        return {"markov": {
            "m": 1, "Q_mgal2": list(cfg.markov_Q_mgal2), "Q_step": "per GNSS step (0.1 s)",
            "R_cm2s2": [cfg.sigma_vu_cms ** 2],
            "transition_target": [[cfg.markov_a11, 1 - cfg.markov_a11], [1 - cfg.markov_a22, cfg.markov_a22]],
            "transition_empirical": P.tolist(),
            "transition_grid_km": cfg.markov_map_step_km,
            "state_fraction": pi.tolist(),
            "state_map_sigma_km": self.smap.sigma_km,
            "initial_state_per_line": [int(b[0]) for b in block_paths],
        }}


@dataclass
class _FieldSetup:
    """The anomaly of a survey and what shapes the flight height."""

    anomaly: _SourcesAnomaly | _MarkovAnomaly
    drape: object | None           # app.simulate.motion.Drape (or the terrain-following drape)
    topo: object | None            # app.simulate.topography.Topography
    truth_extra: dict              # truth.json entries: "topography", "field"


def _make_field(cfg: SimConfig, planned, ext, e0: float, n0: float, rng, seed) -> _FieldSetup:
    """Drape and topography (auxiliary streams), then the anomaly field (main stream)."""
    truth_extra: dict = {}
    drape = make_drape(cfg, planned, _aux_rng(seed, _TAG_DRAPE)) if cfg.drape_amp_m > 0 else None
    topo = None
    if cfg.topo_amp_m > 0:
        topo = make_topography(cfg, ext, e0, n0, planned, _aux_rng(seed, _TAG_TOPO))
        truth_extra["topography"] = topo.info
        if topo.drape is not None:
            drape = topo.drape
    if cfg.field_kind == "sources":
        line_pts = _line_points(planned) if cfg.field_std_over == "lines" else None
        fld = make_field(cfg, ext, e0, n0, rng, line_pts)
        truth_extra["field"] = fld.info
        if drape is not None or cfg.repeat_height_offsets_m:
            src = fld.sources
            truth_extra["field"] = {**fld.info, "sources": {
                "note": ("draped flight: dg_true = harmonica point_gravity(field='g_z') of these point masses "
                         "at the actual position and height (x, y relative to survey_centre_km, metres; "
                         "z, height in metres) minus offset_mgal; truth/grid.nc stays at the nominal height_m"),
                "x_m": src["x_m"], "y_m": src["y_m"], "z_m": src["z_m"], "mass_kg": src["mass_kg"],
                "offset_mgal": src["offset_mgal"], "n_mountain": src["n_mountain"],
                **({"prisms_m": src["prisms_m"], "prism_density_kgm3": src["prism_density_kgm3"],
                    "prisms_note": ("plus harmonica prism_gravity(field='g_z') of these prisms (west, east, "
                                    "south, north, bottom, top in metres) and densities (kg/m³)")}
                   if "prisms_m" in src else {})}}
        anomaly = _SourcesAnomaly(cfg, fld, topo)
    elif cfg.field_kind == "markov":
        rows = [ln.start_km[1] for ln in planned if ln.kind == "main"]
        half = cfg.main_length_km / 2.0
        smap = make_state_map(ext, cfg.markov_a11, cfg.markov_a22, rng, cfg.markov_map_step_km,
                              rows_y_km=rows, row_x_km=(-half, half))
        anomaly = _MarkovAnomaly(cfg, smap, rng, e0, n0)
    else:
        raise ValueError(f"unknown field_kind {cfg.field_kind!r}")
    return _FieldSetup(anomaly, drape, topo, truth_extra)


def _airport(cfg: SimConfig, e0: float, n0: float) -> dict | None:
    """The parking place (``cfg.apron_s > 0``): position, height, normal gravity and base gravity."""
    if cfg.apron_s <= 0:
        return None
    ax, ay = cfg.airport_km if cfg.airport_km is not None else (-cfg.main_length_km / 2.0 - 20.0, 0.0)
    alon, alat = (float(v) for v in unproject_km(e0 + ax, n0 + ay, cfg.crs))
    gamma_ap = float(normal_gravity_mgal(alat, cfg.airport_h_m, cfg.normal_gravity))
    return {"lat_deg": round(alat, 7), "lon_deg": round(alon, 7), "h_m": cfg.airport_h_m,
            "easting_km": e0 + ax, "northing_km": n0 + ay,
            "normal_gravity_mgal": gamma_ap, "local_anomaly_mgal": cfg.airport_anomaly_mgal,
            "g_base_mgal": round(gamma_ap + cfg.airport_anomaly_mgal, 2)}


@dataclass
class _FlownSurvey:
    """Every flight simulated: the files' contents and the truth."""

    flights: dict          # flight -> (gravimeter DataFrame, gnss DataFrame)
    lines: pd.DataFrame    # lines.csv
    truth_lines: pd.DataFrame
    flight_info: dict      # flight -> truth.json "flights" entry


def _fly(paths, cfg: SimConfig, rng, e0: float, n0: float, field: _FieldSetup, airport, seed, report) -> _FlownSurvey:
    """Simulate every flight (main stream in flight order; the parking-place segments draw from
    their own streams, so the airborne data do not depend on them) and cut the truth per line."""
    apron_rngs = [np.random.default_rng(ss) for ss in np.random.SeedSequence([seed, 0xA9]).spawn(len(paths))]
    flights = {}
    truth_rows = []
    lines_rows = []
    flight_info = {}
    for i, path in enumerate(paths):
        report(f"flight {path.name}", 0.1 + 0.75 * i / len(paths), {"flight": path.name})
        res = simulate_flight(path, cfg, rng, e0, n0, field.anomaly.for_path(path), i,
                              apron_rng=apron_rngs[i], airport=airport, seed=seed, drape=field.drape)
        flights[path.name] = (res["gravimeter"], res["gnss"])
        flight_info[path.name] = res["info"]
        ep = res["epochs"]
        for ln, ts, te in path.windows:
            lines_rows.append({"line": ln.line, "flight": path.name, "t_start": ts, "t_end": te,
                               "kind": ln.kind, "track": ln.track})
            sel = ep[(ep["time"] >= ts - 1e-6) & (ep["time"] <= te + 1e-6)].copy()
            sel.insert(0, "kind", ln.kind)
            sel.insert(0, "flight", path.name)
            sel.insert(0, "line", ln.line)
            sel.insert(3, "track", ln.track)
            truth_rows.append(sel)
    return _FlownSurvey(flights, pd.DataFrame(lines_rows), pd.concat(truth_rows, ignore_index=True), flight_info)


def _truth_json(preset: str, seed: int, cfg: SimConfig, e0: float, n0: float, airport, flight_info: dict,
                field: _FieldSetup) -> dict:
    """``truth/truth.json``: the configuration, every injected error and its convention, per-flight truth,
    the field (and topography, regime, Markov model when present)."""
    truth_json = {
        "preset": preset, "seed": seed, "config": dataclasses.asdict(cfg),
        "tau_s": cfg.tau_true_s, "scale": cfg.scale_true,
        "tau_declared_s": cfg.tau_declared_s, "scale_declared": cfg.scale_declared,
        "time_offset_s": cfg.time_offset_s,
        "time_offset_convention": "gravimeter time stamp = true interval centre + time_offset_s (then rounded to 1 ms)",
        "gravimeter_noise_mgal_rthz": cfg.grav_noise_mgal_rthz,
        "gravimeter_noise_std_per_fine_sample_mgal": cfg.grav_noise_mgal_rthz * np.sqrt(cfg.fine_rate_hz),
        "gravimeter_noise_note": "white noise at fine_rate_hz added to the ODE input (before lag and scale)",
        "gravimeter_model_note": "tau*df'/dt + k*f' = f + drift + noise; f_x, f_y are east/north specific force, no lag, no misalignment",
        "sigma_vu_cms": cfg.sigma_vu_cms, "sigma_vh_cms": cfg.sigma_vh_cms,
        "sigma_pos_m": cfg.sigma_pos_m, "sigma_h_m": cfg.sigma_h_m,
        "dg_true_definition": "mean of the injected anomaly over the GNSS interval (t_{k-1}, t_k]",
        "normal_gravity": cfg.normal_gravity, "crs": cfg.crs,
        "time_scale": "seconds since the survey time origin (GNSS epochs on exact multiples of 0.1 s; "
                      "flights on successive days)",
        "gnss_sigma_v_note": "sigma_v column = true vu noise std in force x lognormal(0, 0.2) per epoch",
        "horizontal_note": "f_x = east, f_y = north specific force (kinematic + Coriolis) at the sample centre",
        "survey_centre_km": [e0, n0],
        "base_gravity_mgal": airport["g_base_mgal"] if airport else None,
        "airport": airport,
        "apron_note": ("parking-place readings: per flight a static GNSS span of apron_s before the "
                       "airborne data (ending apron_gap_s before flight t0) and one after (starting "
                       "apron_gap_s after t1); the gravimeter reads f = g_base at rest through the same "
                       "lag, scale, drift and noise; drift = offset + rate*(t - t0)/3600 + random walk, "
                       "continuous across the unrecorded gaps; flights[*].apron gives each segment's "
                       "GNSS span, gravimeter interval span and true drift (mean over the gravimeter span)"),
        "flights": flight_info,
        **field.truth_extra,
    }
    regime = _regime_notes(cfg, field.drape)
    if regime:
        truth_json["regime"] = regime
    truth_json.update(field.anomaly.truth_json())
    return truth_json


def _survey_toml(cfg: SimConfig, airport) -> dict:
    """``survey.toml``: what the processing is told (declared τ and scale, not the true ones)."""
    return {"survey": {"name": cfg.name, "crs": cfg.crs, "normal_gravity": cfg.normal_gravity},
            "gravimeter": {"model": cfg.gravimeter_model, "tau_s": cfg.tau_declared_s,
                           "scale": cfg.scale_declared, "rate_hz": cfg.gravimeter_rate_hz,
                           "base_gravity_mgal": airport["g_base_mgal"] if airport else None},
            "processing": dict(cfg.processing)}


def simulate_survey(preset: str, out_dir, seed: int = 0, progress=None, **overrides) -> Path:
    """Simulate a survey and write it (SPEC §4) with its ``truth/`` folder.

    Parameters
    ----------
    preset : str
        A key of :data:`PRESETS` (``tiny``, ``omolon-mini``, ``omolon``, ``kalgoorlie``, ``markov``, and the
        realistic regimes ``testline-2hz``, ``platform-*``, ``heights-only-*``, ``turbulent``, ``draped``;
        docs/SIMULATOR.md).
    out_dir : path
        Destination directory (replaced atomically if it exists).
    seed : int
        Seed of the random generator; same seed, same survey.
    progress : callable, optional
        ``progress(stage: str, fraction: float, info: dict | None)``.
    **overrides
        Any :class:`SimConfig` field.

    Returns
    -------
    pathlib.Path
        The survey directory.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {sorted(PRESETS)}")
    cfg = PRESETS[preset].replace(**overrides)
    _check_regime(cfg)
    rng = np.random.default_rng(seed)
    clock = _time.perf_counter()

    def report(stage, frac, info=None):
        if progress is not None:
            progress(stage, float(frac), info)

    report("plan", 0.0)
    e0, n0 = (float(v) for v in project_km(cfg.lon0_deg, cfg.lat0_deg, cfg.crs))
    planned = layout_lines(cfg)
    paths = _plan_flights(cfg, planned, rng)
    ext = _extent(paths)
    report("field", 0.05)
    field = _make_field(cfg, planned, ext, e0, n0, rng, seed)
    airport = _airport(cfg, e0, n0)
    flown = _fly(paths, cfg, rng, e0, n0, field, airport, seed, report)
    report("truth", 0.88)
    grid = field.anomaly.truth_grid(flown.truth_lines)
    truth_json = _truth_json(preset, seed, cfg, e0, n0, airport, flown.flight_info, field)
    report("write", 0.9)
    out = write_survey(out_dir, _survey_toml(cfg, airport), flown.lines, flown.flights, flown.truth_lines, grid,
                       truth_json, compress=cfg.compress,
                       gnss_columns=None if cfg.gnss_velocity else GNSS_HEIGHTS_ONLY_COLUMNS,
                       dem=field.topo.dem if field.topo is not None else None)
    report("done", 1.0, {"seconds": _time.perf_counter() - clock})
    return out


def _regime_notes(cfg: SimConfig, drape) -> dict:
    """truth.json ``regime``: what the new (realistic) options injected; empty for the original presets."""
    out: dict = {}
    if not _legacy_gravimeter(cfg):
        g = {"sampling": cfg.gravimeter_sampling, "clock": cfg.gravimeter_clock,
             "rate_hz": cfg.gravimeter_rate_hz,
             "sampling_note": ("point: f_z is the instrument's output (after its internal filter, lag and scale) "
                               "at the sample time; mean: its mean over [t - P/2, t + P/2]; stamp = sample time "
                               "+ time_offset_s, rounded to 1 ms"
                               + ("; aligned clock: sample times are exact multiples of P = 1/rate_hz"
                                  if cfg.gravimeter_clock == "aligned" else ""))}
        if cfg.gravimeter_fir_boxcars > 0:
            n, W = cfg.gravimeter_fir_boxcars, cfg.gravimeter_fir_width_s
            f = np.array([0.01, 0.05, 0.1, 0.2, 0.3, 0.5])
            g["internal_filter"] = {
                "kind": "zero-phase FIR: cascaded boxcars (linear phase, delay removed from the stamps)",
                "boxcars": n, "width_s": W, "response": "H(f) = sinc(f*width_s)**boxcars (real)",
                "gain_at_hz": dict(zip([f"{v:g}" for v in f], fir_gain(f, n, W).round(5).tolist())),
                "note": "not declared in survey.toml: the processing does not know it"}
        out["gravimeter"] = g
    if cfg.turbulence_spectrum != "band":
        out["turbulence"] = {"spectrum": cfg.turbulence_spectrum, "peak_hz": cfg.turbulence_peak_hz,
                             "psd_slopes": list(cfg.turbulence_slopes),
                             "note": "PSD of the turbulence acceleration ∝ x^a/(1 + x^(a+b)), x = f/peak_hz"}
    if drape is not None and cfg.topo_clearance_m > 0:
        out["drape"] = {"terrain_following": drape.info(), "smooth_km": cfg.topo_drape_smooth_km,
                        "note": ("height = smoothed terrain + clearance_m + lift_m + turbulence/phugoid motion; the "
                                 "true height per epoch is h_true_m in lines.parquet; truth/grid.nc (sources only, "
                                 "no terrain) stays at height_m")}
    elif drape is not None:
        out["drape"] = {"amp_m": cfg.drape_amp_m, "wavelength_km": list(cfg.drape_wavelength_km),
                        "components": drape.info(),
                        "note": ("height = height_m + drape(x, y) + turbulence/phugoid motion; drape = sum of plane "
                                 "waves in the survey plane (x, y m from the centre) plus a constant, spanning exactly "
                                 "[-amp_m, +amp_m] on the line windows; the true height per epoch is h_true_m "
                                 "in lines.parquet; truth/grid.nc stays at height_m")}
    if cfg.repeat_height_offsets_m:
        out["repeat_heights"] = {"offsets_m": [float(v) for v in cfg.repeat_height_offsets_m],
                                 "note": ("repeat pass r (R1-<r+1>) flies offsets_m[r % len] above the other lines "
                                          "(on top of any drape), held from its run-in to its run-out and eased "
                                          "with a half cosine in the turns; true height per epoch: h_true_m; the "
                                          "point sources are in field.sources")}
    if not cfg.gnss_velocity or cfg.h_colored_m > 0:
        out["gnss"] = {"velocity_columns": bool(cfg.gnss_velocity), "rate_hz": cfg.gnss_rate_hz,
                       "h_white_m": cfg.sigma_h_m, "h_colored_m": cfg.h_colored_m,
                       "h_colored_tau_s": cfg.h_colored_tau_s,
                       "note": ("height error = white (h_white_m) + first-order Gauss-Markov (h_colored_m, "
                                "correlation exp(-|dt|/tau)); heights-only: gnss.csv has time, lat, lon, h, "
                                "R_true_cm2s2 is NaN")}
    if cfg.wind_ms != 0.0:
        out["wind_ms"] = cfg.wind_ms
    return out


def _truth_has_height(cfg: SimConfig) -> bool:
    """``h_true_m`` is in truth/lines.parquet when the height matters: draped flight or heights-only GNSS."""
    return (cfg.drape_amp_m > 0 or cfg.topo_clearance_m > 0 or bool(cfg.repeat_height_offsets_m)
            or not cfg.gnss_velocity)


def _stable_rng(*key) -> np.random.Generator:
    """Fallback stream from a process-independent hash (zlib.crc32 of the key's repr), not ``hash()``
    (string hashing is randomised per process by PYTHONHASHSEED)."""
    return np.random.default_rng(zlib.crc32(repr(key).encode()))


def _position_derived_noise(t, cfg, rng=None) -> np.ndarray:
    """GNSS vertical velocity error of a receiver that differences its positions: white
    position noise (std ``vu_from_position_m``) differenced over each epoch, so the error
    has *less* power at low frequency than white velocity noise (blue, not red).
    ``rng``: its own stream (the simulator passes ``SeedSequence([seed, tag, flight])``)."""
    if cfg.vu_from_position_m <= 0:
        return np.zeros(t.size)
    g = rng if rng is not None else _stable_rng(float(t[0]), "position")
    e = g.standard_normal(t.size + 1) * cfg.vu_from_position_m
    dt = np.diff(t, prepend=t[0] - np.median(np.diff(t)))
    return np.diff(e) / dt


def _colored_noise(t, cfg, rng=None) -> np.ndarray:
    """Exponentially correlated GNSS velocity error (m/s), not the white noise the model
    assumes; its own random stream (``rng``; default: a stable hash of the start time and τ) so the
    rest of the survey is unchanged."""
    if cfg.vu_colored_cms <= 0:
        return np.zeros(t.size)
    g = rng if rng is not None else _stable_rng(float(t[0]), float(cfg.vu_colored_tau_s))
    dt = np.diff(t, prepend=t[0])
    a = np.exp(-dt / cfg.vu_colored_tau_s)
    w = g.standard_normal(t.size) * cfg.vu_colored_cms / 100.0
    out = np.empty(t.size)
    out[0] = w[0]
    for i in range(1, t.size):
        out[i] = a[i] * out[i - 1] + np.sqrt(1.0 - a[i] ** 2) * w[i]
    return out
