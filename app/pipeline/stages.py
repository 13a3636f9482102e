"""The named stages of the method (SPEC §2 and §3), each on plain data.

``process.py`` runs them in order:

1. :func:`measure_flight` — corrections and the measurement ``z_k`` over a whole flight
   (normal gravity, Eötvös, gravimeter time offset, lag/scale inversion, interval means);
2. :func:`base_tie` — parking-place readings remove each flight's reading error and drift;
   :func:`cut_lines` — the survey lines as GNSS-epoch tables with projected positions;
   :func:`choose_model_order` — m by the full-rate likelihood;
3. :func:`fir_baseline` — the FIR 100 s low-pass (seed 004) on the whole flight;
4. :func:`regularize_lines` — ∇^m, Kaiser low-pass, decimation, MA approximation;
5. :func:`learn` — EM learning of Θ over all lines (the EM iteration table);
6. :func:`recognize` — Viterbi paths and posterior state probabilities per line;
7. :func:`smooth_recognition` — NL-means over the recognition map;
8. :func:`hold_states`, :func:`filter_line` — states held on the full-rate grid, the GNSS
   noise level R(t) (:mod:`app.core.noise_level`), Q levels refined by the full-rate
   likelihood (:mod:`app.core.level_ml`), non-stationary Kalman smoother with posterior
   std, stationary (Q₁, R) smoother beside it;
9. leveling (crossovers, per-flight drift polynomials, significance test) and
10. gridding (collocation with its std) — in ``process.py``, on the whole line table.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from app.config import SurveyConfig
from app.core import geodesy
from app.core import gravimeter as gm
from app.core.measurement import anomaly_measurement_mgal

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- 1. measurement
@dataclass
class FlightMeasurement:
    """Per-GNSS-epoch measurement of one flight (arrays of shape (n,))."""

    flight: str
    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    h_m: np.ndarray
    vu_ms: np.ndarray
    ve_ms: np.ndarray
    vn_ms: np.ndarray
    gamma_mgal: np.ndarray
    eotvos_mgal: np.ndarray
    fbar_ms2: np.ndarray
    z_mgal: np.ndarray
    time_offset_s: float = 0.0
    time_offset_corr: float = float("nan")
    time_offset_applied: bool = False
    notes: list = field(default_factory=list)
    despike: dict = field(default_factory=dict)
    time_offset: dict = field(default_factory=dict)


def measure_flight(flight, cfg: SurveyConfig, tau_s: float | None = None,
                   scale: float | None = None) -> FlightMeasurement:
    """Corrections and the anomaly measurement ``z_k`` (SPEC §1) for one whole flight.

    Parameters
    ----------
    flight : app.io.survey.Flight
    cfg : SurveyConfig
    tau_s, scale : float, optional
        Override the gravimeter lag and scale of ``survey.toml`` (in-flight calibration).
    """
    p = cfg.processing
    tau = cfg.gravimeter.tau_s if tau_s is None else tau_s
    k = cfg.gravimeter.scale if scale is None else scale
    gn = flight.gnss
    t = gn["time"].to_numpy(float)
    lat = gn["lat"].to_numpy(float)
    lon = gn["lon"].to_numpy(float)
    h = gn["h"].to_numpy(float)
    vu = gn["vu"].to_numpy(float)
    if "ve" in gn and "vn" in gn:
        ve = gn["ve"].to_numpy(float)
        vn = gn["vn"].to_numpy(float)
    else:
        ve, vn = geodesy.velocities_from_positions_ms(t, lat, lon, h)
    gamma = geodesy.normal_gravity_mgal(lat, h, cfg.survey.normal_gravity)
    eot = geodesy.eotvos_mgal(lat, h, ve, vn)

    gr = flight.gravimeter
    series = gm.integrate_samples(gr["time"].to_numpy(float), gr["f_z"].to_numpy(float))
    offset, corr, applied = 0.0, float("nan"), False
    notes = []
    offset_info: dict = {"estimated": False}
    if getattr(flight, "vu_derived_from_h", False):
        notes.append("vu derived from the GNSS heights (the file has no vu column): derivative of the not-a-knot "
                     "cubic spline through h, per contiguous run")
    if p.estimate_time_offset:
        try:
            fit = gm.fit_time_offset(series, t, vu, tau, k, p.max_time_offset_s,
                                     band_hz=(0.01, acceleration_band_top_hz(float(np.median(np.diff(t))))))
            offset, corr = fit.offset_s, fit.correlation
            offset_info = {"estimated": True, "offset_s": offset, "se_s": fit.se_s, "correlation": corr,
                           "residual_reduction": fit.relative_improvement}
        except ValueError as exc:  # too short a flight, etc.
            notes.append(f"time offset not estimated: {exc}")
            offset = 0.0
            fit = None
        if fit is not None and p.apply_time_offset:
            # applied only when the estimate is significant and it removes a real share of the
            # residual: an offset a few ms from zero only trades one response mismatch for another
            why = []
            if not (np.isfinite(corr) and corr > 0.5):
                why.append(f"correlation {corr:.2f} ≤ 0.5")
            if not abs(offset) < p.max_time_offset_s:
                why.append(f"at the search limit ±{p.max_time_offset_s:g} s")
            if not abs(offset) > p.time_offset_min_z * fit.se_s:
                why.append(f"not significant (|offset| ≤ {p.time_offset_min_z:g} × standard error {fit.se_s:.2g} s)")
            if not fit.relative_improvement >= p.time_offset_min_improvement:
                why.append(f"removes only {100 * fit.relative_improvement:.2f} % of the residual "
                           f"(< {100 * p.time_offset_min_improvement:g} %)")
            applied = not why
            offset_info.update(applied=applied, reason="; ".join(why) if why else "significant and improves the fit")
            if not applied:
                notes.append(f"time offset {offset:.4f} s not applied: {'; '.join(why)}")
    fbar = gm.interval_means(series, t, tau, k, time_offset_s=offset if applied else 0.0)
    z = anomaly_measurement_mgal(fbar, t, vu, gamma, eot)
    # an interval spanning a data gap is no measurement of anything
    dt = np.diff(t)
    long_step = np.concatenate([[False], dt > 1.5 * np.median(dt)])
    z[long_step] = np.nan
    # nor is one whose gravimeter integral crosses a gap of the gravimeter record: the
    # spline bridges it, but ∫f over the gap is unknown and every z after it would carry
    # the error (the lag inversion's derivative spreads it over ~τ: keep a margin)
    gt = gr["time"].to_numpy(float) + (offset if applied else 0.0)
    gstep = np.diff(gt)
    gh = float(np.median(gstep))
    for i in np.flatnonzero(gstep > 1.5 * gh):
        a = gt[i] - p.gravimeter_gap_margin_s
        b = gt[i + 1] + p.gravimeter_gap_margin_s
        hit = (t > a) & (np.concatenate([[t[0] - 1.0], t[:-1]]) < b)
        z[hit] = np.nan
        if gt[i + 1] - gt[i] <= 60.0 and hit.any():  # a dropout, not a pause of the recording
            notes.append(f"gravimeter record gap {gt[i]:.2f}–{gt[i + 1]:.2f} s: {int(hit.sum())} epochs of z "
                         "left without measurement")
    despike = {"threshold": p.despike_threshold, "flagged": 0, "epochs": int(np.isfinite(z).sum()),
               "applied": False}
    if p.despike_threshold is not None:
        from app.core.measurement import repair_spikes, spike_mask

        spikes = spike_mask(z, float(np.median(dt)), p.despike_threshold)
        n_flag = int(spikes.sum())
        frac = n_flag / max(1, despike["epochs"])
        despike.update(flagged=n_flag, fraction=frac)
        if n_flag and frac > p.despike_max_fraction:
            # spikes are rare by nature: this many flags means the noise is not what the
            # detector assumes (a heavy-tailed or rough record); repairing would destroy data
            despike["reason"] = "stood down: too many flags"
            notes.append(f"spike repair stood down: {n_flag} of {despike['epochs']} epochs ({100 * frac:.2f} %) "
                         f"would be flagged, more than {100 * p.despike_max_fraction:g} % — z left as measured")
        elif n_flag:
            z = repair_spikes(z, spikes)
            despike["applied"] = True
            notes.append(f"{n_flag} epochs of z ({100 * frac:.3f} %) repaired as spikes "
                         f"(> {p.despike_threshold:g} local robust std from the neighbours' mean)")
    return FlightMeasurement(flight.name, t, lat, lon, h, vu, ve, vn, gamma, eot, fbar, z,
                             float(offset), float(corr), applied, notes, despike, offset_info)


def acceleration_band_top_hz(dt_s: float) -> float:
    """Highest frequency (Hz) at which the GNSS-derived vertical acceleration is compared with
    the gravimeter's (time offset, lag check): a fifth of the GNSS rate, at most 1 Hz.  Above
    it a 1–2 Hz receiver's (or differenced heights') acceleration no longer follows the
    aircraft's (aliasing, interpolation), and fitting it biased the lag of a 1 Hz heights-only
    survey by 0.35 s."""
    return float(min(1.0, 0.2 / dt_s))


def static_segments(t_s, ve_ms, vn_ms, vu_ms, min_duration_s: float = 60.0, max_speed_ms: float = 0.5,
                    trim_s: float = 10.0) -> list[tuple[int, int]]:
    """Index ranges ``[i0, i1)`` where the aircraft stands still (parking place readings).

    A GNSS epoch is static when its horizontal and vertical speeds are below
    ``max_speed_ms``; runs shorter than ``min_duration_s`` are ignored and
    ``trim_s`` is cut from both ends of each run (taxi start/stop)."""
    t = np.asarray(t_s, float)
    still = (np.hypot(ve_ms, vn_ms) < max_speed_ms) & (np.abs(vu_ms) < max_speed_ms)
    out = []
    if not still.any():
        return out
    d = np.diff(np.concatenate([[0], still.astype(int), [0]]))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    for a, b in zip(starts, stops):
        if b - a < 2 or t[b - 1] - t[a] < min_duration_s:
            continue
        a2 = int(np.searchsorted(t, t[a] + trim_s))
        b2 = int(np.searchsorted(t, t[b - 1] - trim_s, side="right"))
        if b2 - a2 > 10:
            out.append((a2, b2))
    return out


def base_tie(m: FlightMeasurement, base_gravity_mgal: float | None) -> dict:
    """Tie the gravimeter to the parking place (base) readings of a flight, in place.

    At rest ``z = g − γ`` (SPEC §1).  With ``base_gravity_mgal`` known, the mean
    reading error of each static period is ``mean(z) − (g_base − γ)``; with one
    period it is removed as a constant, with two or more as a straight line in
    time (instrument drift) through the first and last.  Without the base value
    only the change between the first and last static period (the drift) is
    removed.  The measurement ``z_mgal`` is corrected in place.

    Returns
    -------
    dict
        What was done: periods (time, error), drift rate (mGal/h), constant (mGal).
    """
    segs = static_segments(m.t_s, m.ve_ms, m.vn_ms, m.vu_ms)
    info = {"static_periods": [], "applied": False}
    if not segs:
        return info
    errs, times = [], []
    for a, b in segs:
        # at rest V̇ = 0 exactly: use the gravimeter alone (the GNSS velocity noise would
        # add ~2·10⁴ mGal per epoch to z); the mean of interval means over the segment is
        # the mean reading
        reading = m.fbar_ms2[a:b] * 1e5 - m.gamma_mgal[a:b]
        ok = np.isfinite(reading)
        if ok.sum() < 10:
            continue
        g_minus_gamma = (base_gravity_mgal - m.gamma_mgal[a:b][ok]) if base_gravity_mgal is not None else 0.0
        e = float(np.mean(reading[ok] - g_minus_gamma))
        errs.append(e)
        times.append(float(np.mean(m.t_s[a:b])))
        info["static_periods"].append({"t_start": float(m.t_s[a]), "t_end": float(m.t_s[b - 1]),
                                       "reading_error_mgal" if base_gravity_mgal is not None
                                       else "reading_mgal": e})
    if not errs:
        return info
    t = m.t_s
    if len(errs) >= 2 and times[-1] - times[0] > 600.0:
        rate = (errs[-1] - errs[0]) / (times[-1] - times[0])
        drift = errs[0] + rate * (t - times[0])
        info["drift_mgal_per_h"] = rate * 3600.0
    else:
        drift = np.full(t.shape, errs[0])
        info["drift_mgal_per_h"] = 0.0
    if base_gravity_mgal is None:
        drift = drift - errs[0]  # relative: the absolute level stays unknown
        if len(errs) < 2:
            return info
    m.z_mgal = m.z_mgal - drift
    info["applied"] = True
    info["absolute"] = base_gravity_mgal is not None
    return info


def calibrate_gravimeter(flight, cfg: SurveyConfig, max_duration_s: float = 3600.0,
                         params: tuple = ("tau", "k")) -> dict:
    """In-flight calibration of τ and k (seed 001 §3–4) on one flight's longest airborne
    stretch without gaps, by frequency-domain weighted least squares.

    The noise spectra: the GNSS noise level from the high-frequency content of z, a
    random-walk anomaly of 10 mGal² per step (generous on purpose, see below) and 1 mGal²
    gravimeter noise per epoch; they only weight the frequencies.

    Returns
    -------
    dict
        ``tau_s``, ``k``, their standard errors (from D_XX) and the segment used.
    """
    from app.core.calibration import CalibrationSpectra, calibrate
    from app.core.noise_level import local_noise_variance_cm2s2

    m = measure_flight(flight, cfg)
    t = m.t_s
    dt = float(np.median(np.diff(t)))
    moving = np.hypot(m.ve_ms, m.vn_ms) > 20.0
    ok = moving & np.isfinite(m.fbar_ms2)
    steps_ok = np.concatenate([[False], np.abs(np.diff(t) - dt) < 0.01 * dt])
    good = ok & steps_ok
    d = np.diff(np.concatenate([[0], good.astype(int), [0]]))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    if starts.size == 0:
        raise ValueError(f"flight {flight.name}: no airborne segment to calibrate on")
    k = int(np.argmax(stops - starts))
    a, b = int(starts[k]), int(stops[k])
    b = min(b, a + int(max_duration_s / dt))
    gr = flight.gravimeter
    series = gm.integrate_samples(gr["time"].to_numpy(float), gr["f_z"].to_numpy(float))
    off = m.time_offset_s if m.time_offset_applied else 0.0
    tt = t[a - 1:b] if a > 0 else t[a:b]
    fraw = gm.interval_means(series, tt, 0.0, 1.0, time_offset_s=off)
    fdot = gm.interval_means(series, tt, 1.0, 1.0, time_offset_s=off) - fraw
    z = anomaly_measurement_mgal(fraw, tt, m.vu_ms[a - 1:b] if a > 0 else m.vu_ms[a:b],
                                 m.gamma_mgal[a - 1:b] if a > 0 else m.gamma_mgal[a:b],
                                 m.eotvos_mgal[a - 1:b] if a > 0 else m.eotvos_mgal[a:b]) * 1e-5
    sl = slice(1, None)
    r = float(np.median(local_noise_variance_cm2s2(z[sl] * 1e5, dt)))
    # The gravimeter reading f' (a regressor) itself contains the anomaly, so the anomaly
    # band must be weighted down generously: with 0.01 / 1 / 10 mGal² per step the scale k
    # came out 11σ / 2σ / 0.7σ from the truth on the simulator (τ within 1σ in all three).
    spectra = CalibrationSpectra.from_epoch_variances(dt, f_var_mgal2=1.0, dg_step_var_mgal2=10.0, r_cm2s2=r)
    res = calibrate(tt[sl], z[sl], fraw[sl], spectra=spectra, params=tuple(params),
                    tau0_s=cfg.gravimeter.tau_s, k0=cfg.gravimeter.scale, fdot_raw_ms3=fdot[sl],
                    fmax_hz=acceleration_band_top_hz(dt))
    names = list(res.names)
    return {"flight": flight.name, "t_start": float(tt[1]), "t_end": float(tt[-1]),
            "tau_s": float(res.tau_s), "k": float(res.k),
            "std": {n: float(v) for n, v in zip(names, np.asarray(res.std))},
            "chi2_per_dof": float(getattr(res, "chi2_per_dof", np.nan))}


# --------------------------------------------------------------------------- 2. lines
@dataclass
class LineData:
    """One survey line on the GNSS epochs inside its window."""

    line: str
    flight: str
    kind: str
    track: str | None
    sl: slice                      # slice of the flight arrays
    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    h_m: np.ndarray
    easting_km: np.ndarray
    northing_km: np.ndarray
    z_mgal: np.ndarray
    speed_ms: float


def survey_crs(cfg: SurveyConfig, flights: dict[str, FlightMeasurement]) -> str:
    """The projected CRS: ``survey.crs`` or the UTM zone of the data."""
    if cfg.survey.crs:
        return cfg.survey.crs
    lon = np.concatenate([m.lon_deg[:: max(1, m.lon_deg.size // 1000)] for m in flights.values()])
    lat = np.concatenate([m.lat_deg[:: max(1, m.lat_deg.size // 1000)] for m in flights.values()])
    return geodesy.utm_crs_for(lon, lat)


def cut_lines(lines: pd.DataFrame, flights: dict[str, FlightMeasurement], crs: str) -> list[LineData]:
    """Cut every line of ``lines.csv`` out of its flight's measurement."""
    out = []
    for row in lines.itertuples(index=False):
        m = flights[str(row.flight)]
        i0 = int(np.searchsorted(m.t_s, row.t_start, side="left"))
        i1 = int(np.searchsorted(m.t_s, row.t_end, side="right"))
        sl = slice(i0, i1)
        e, n = geodesy.project_km(m.lon_deg[sl], m.lat_deg[sl], crs)
        z = m.z_mgal[sl].copy()
        speed = float(np.nanmedian(np.hypot(m.ve_ms[sl], m.vn_ms[sl]))) if i1 > i0 else float("nan")
        track = getattr(row, "track", None)
        if track is not None and (isinstance(track, float) and np.isnan(track)):
            track = None
        out.append(LineData(str(row.line), str(row.flight), str(row.kind),
                            None if track is None else str(track), sl, m.t_s[sl], m.lat_deg[sl],
                            m.lon_deg[sl], m.h_m[sl], np.asarray(e), np.asarray(n), z, speed))
    return out



# --------------------------------------------------------------------------- 2a. noise model
def level_band(p, dt_s: float) -> tuple[float, float]:
    """The band (Hz) in which the local noise level R(t) is measured, inside the GNSS
    Nyquist frequency (1–2 Hz receivers)."""
    f2 = min(float(p.noise_band_hz[1]), 0.8 * 0.5 / dt_s)
    return (min(float(p.noise_band_hz[0]), 0.5 * f2), f2)


def fit_noise(lines: list[LineData], dt_s: float, p):
    """The error of z as a coloured process (:mod:`app.core.noise_model`), fitted on the
    finite stretches of every line; returns (NoiseFit, model normalised so that a level R is
    the equivalent white velocity noise in :func:`level_band`)."""
    from app.core.noise_model import FAMILIES, fit_noise_model

    fams = FAMILIES if p.noise_family == "auto" else tuple(f for f in FAMILIES if f[0] == p.noise_family)
    segs = [ln.z_mgal[a:b] for ln in lines for a, b in finite_segments(ln.z_mgal)]
    fmax = min(float(p.noise_fit_fmax_hz), 0.8 * 0.5 / dt_s)
    diffs = repeat_differences(lines, dt_s, min(2.0 * fmax, 0.45 / dt_s)) if p.noise_fit_repeats else []
    fit = fit_noise_model(segs, dt_s, m=2, fmax_hz=fmax, families=fams, differences=diffs,
                          octave_weights=p.noise_fit_octave_weights, knee_max_fraction=p.noise_knee_max_fraction)
    return fit, fit.model.normalized(level_band(p, dt_s))


def repeat_differences(lines: list[LineData], dt_s: float, lowpass_hz: float) -> list:
    """Differences of the passes of every repeat track (disjoint consecutive pairs, so the
    differences are independent), on a common along-track grid (:func:`app.core.noise_model.pass_difference`).
    The along-track coordinate is the projection on the track's principal axis."""
    from app.core.noise_model import pass_difference

    tracks: dict = {}
    for ln in lines:
        if ln.kind == "repeat" and ln.track is not None:
            tracks.setdefault(ln.track, []).append(ln)
    out = []
    for passes in tracks.values():
        passes = sorted(passes, key=lambda ln: float(ln.t_s[0]))
        if len(passes) < 2:
            continue
        e = np.concatenate([ln.easting_km for ln in passes])
        n = np.concatenate([ln.northing_km for ln in passes])
        xy = np.column_stack([e - e.mean(), n - n.mean()])
        axis = np.linalg.svd(xy, full_matrices=False)[2][0]
        for a, b in zip(passes[0::2], passes[1::2]):
            sa = 1000.0 * ((a.easting_km - e.mean()) * axis[0] + (a.northing_km - n.mean()) * axis[1])
            sb = 1000.0 * ((b.easting_km - e.mean()) * axis[0] + (b.northing_km - n.mean()) * axis[1])
            d = pass_difference(sa, a.z_mgal, sb, b.z_mgal, dt_s, lowpass_hz)
            if d is not None:
                out.append(d)
    return out


def noise_levels(flights: dict[str, FlightMeasurement], dt_s: float, p) -> dict[str, np.ndarray]:
    """Local noise level R(t) ((cm/s)², equivalent white velocity noise) of every flight:
    z's content in :func:`level_band` (``noise_model = 'band'``) or near the Nyquist frequency
    (``'local'``); empty for ``'states'`` (the recognised R_j levels are used instead)."""
    from app.core.noise_level import band_noise_variance_cm2s2, local_noise_variance_cm2s2

    if p.noise_model == "local":
        return {name: local_noise_variance_cm2s2(fm.z_mgal, dt_s) for name, fm in flights.items()}
    if p.noise_model == "band":
        band = level_band(p, dt_s)
        return {name: band_noise_variance_cm2s2(fm.z_mgal, dt_s, band) for name, fm in flights.items()}
    return {}


def level_scale(noise_fit, band_hz, lines: list[LineData], r_local: dict) -> float:
    """Factor from the measured local levels R(t) to the fitted noise model's level.

    The model's weights were fitted on the pooled spectra of the lines, i.e. at the mean
    level over the lines' epochs; the local measurement (in ``band_hz``) gives the level's
    changes in time.  When the model describes the measurement band well the factor is
    ≈ 1; where it does not (a turbulence band the family cannot follow) it carries the
    measured changes in time to the fitted level where the smoother separates anomaly
    from noise."""
    if not r_local or noise_fit.model.is_white_velocity:
        # the paper's shape: the band measurement is already its level
        return 1.0
    vals = np.concatenate([r_local[ln.flight][ln.sl][np.isfinite(ln.z_mgal)] for ln in lines])
    if not vals.size:
        return 1.0
    return float(noise_fit.model.equivalent_white_R(band_hz) / np.mean(vals))


# --------------------------------------------------------------------------- 2b. model order
def choose_model_order(lines: list[LineData], dt_s: float, noise=None, r_local: dict | None = None):
    """Order m of the anomaly model by the full-rate likelihood of the main lines (SPEC §2
    leaves m to the analyst; seed 000 notes: choose it by likelihood)."""
    from app.core.level_ml import select_order
    from app.core.noise_level import local_noise_variance_cm2s2

    use = [ln for ln in lines if ln.kind != "tie" and ln.z_mgal.size >= 100] or lines
    zl = [ln.z_mgal for ln in use]
    if r_local:
        rl = [r_local[ln.flight][ln.sl] for ln in use]
    else:
        rl = [local_noise_variance_cm2s2(z, dt_s) for z in zl]
    return select_order(zl, rl, dt_s, noise=noise)


# --------------------------------------------------------------------------- 3. FIR baseline
def fir_baseline(m: FlightMeasurement, cutoff_period_s: float) -> np.ndarray:
    """FIR 100 s low-pass (seed 004) of ``z`` over the whole flight (mGal), so line edges
    see the run-in data as in industry practice."""
    from app.core.baselines import fir_lowpass_mgal

    dt = float(np.median(np.diff(m.t_s)))
    return fir_lowpass_mgal(m.z_mgal, dt, cutoff_period_s)


# --------------------------------------------------------------------------- 4. regularization
@dataclass
class Regularized:
    design: object                 # app.core.regularize.RegularizationDesign
    ma: object                     # app.core.ma_approx.MAModel
    lines: list                    # LineData used for identification
    x: list                        # decimated regularized sequences
    idx: list                      # full-rate indices (into the line) of each decimated point
    skipped: dict                  # line → reason


def finite_segments(z) -> list[tuple[int, int]]:
    """(start, stop) index pairs of the runs of finite values of z."""
    ok = np.isfinite(np.asarray(z, float))
    d = np.diff(np.concatenate([[0], ok.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def _regularize_segments(z_mgal, m: int, design):
    """Regularize each finite stretch of a line separately and join the results.

    A missing epoch of z cannot be filled: z is a difference of velocities, so its noise
    telescopes (Σ z over a window leaves only the velocity errors at the window's ends);
    any filled value leaves the neighbours' ±1000·r/Δt uncancelled — thousands of mGal in
    one sample, tens after the low-pass, which the EM reads as anomaly bursts."""
    from app.core.regularize import min_line_samples, regularize_line

    need = min_line_samples(design, m)
    xs, idxs = [], []
    for a, b in finite_segments(z_mgal):
        if b - a >= need:
            x, idx = regularize_line(np.asarray(z_mgal[a:b], float), m, design)
            xs.append(x)
            idxs.append(idx + a)
    if not xs:
        n = int(np.isfinite(np.asarray(z_mgal, float)).sum())
        raise ValueError(f"line too short for regularization: no stretch without missing epochs has {need} "
                         f"samples ({n} finite of {len(z_mgal)})")
    return np.concatenate(xs), np.concatenate(idxs)


def regularize_lines(lines: list[LineData], cfg: SurveyConfig, dt_s: float, noise=None) -> Regularized:
    """∇^m, Kaiser low-pass, decimation and the MA approximation (SPEC §2 step 1)."""
    from app.core.ma_approx import fit_ma_model
    from app.core.regularize import design_regularization, regularize_line

    p = cfg.processing
    use = [ln for ln in lines if ln.kind != "tie" or p.include_tie_lines]
    if not use:
        raise ValueError("no lines to identify (all are tie lines and include_tie_lines is false)")
    speed = float(np.nanmedian([ln.speed_ms for ln in use]))
    design = design_regularization(dt_s, speed, step_km=p.decimation_step_km, n=p.decimation_n,
                                   cutoff_hz=p.cutoff_hz, attenuation_db=p.stopband_attenuation_db,
                                   difference_grid=p.regularization_difference_grid)
    ma = fit_ma_model(design, p.m, K=p.ma_order_K, L=p.ma_order_L,
                      noise=None if noise is None or noise.is_white_velocity else noise)
    kept, xs, idxs, skipped = [], [], [], {}
    for ln in use:
        try:
            x, idx = _regularize_segments(ln.z_mgal, p.m, design)
        except ValueError as exc:
            skipped[ln.line] = str(exc)
            continue
        if len(x) < ma.p + 3:
            skipped[ln.line] = f"only {len(x)} decimated points (need {ma.p + 3})"
            continue
        kept.append(ln)
        xs.append(np.asarray(x, float))
        idxs.append(np.asarray(idx, int))
    if not kept:
        raise ValueError("every line is too short for the regularization filter: "
                         + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    return Regularized(design, ma, kept, xs, idxs, skipped)


# --------------------------------------------------------------------------- 5-7. identification
def _n_params(n_q: int, n_r: int, n_lines: int) -> int:
    n = n_q * n_r
    return n_q + n_r + n * (n - 1) + n_lines * (n - 1)


def learn(reg: Regularized, cfg: SurveyConfig, callback=None):
    """EM learning of Θ = {Q_i, R_j, a_ij, π_i(w)} over all lines (SPEC §2 step 2).

    With ``processing.n_r = None`` the number of GNSS noise levels is chosen by
    BIC between 1 and 2 (noise episodes of the GNSS are common in real data and a
    model without them explains them as anomaly intensity).  With ``processing.n_q = None``
    there are two anomaly levels when the lines give at least ``min_points_adaptive``
    decimated points, one otherwise (the stationary model: all a short survey supports).  Returns the EM
    result of the chosen model with ``selection`` (candidates, log-likelihood,
    BIC) attached."""
    from app.core.mjls_em import fit_em

    p = cfg.processing
    r_cands = [p.n_r] if p.n_r is not None else [1, 2]
    n_points = int(sum(len(x) for x in reg.x))
    # N1 = 2 anomaly levels need enough decimated points to be told apart; a short survey
    # (a test line flown a few times: ~100 points) gets the stationary model (one level)
    q_cands = [p.n_q] if p.n_q is not None else [2 if n_points >= p.min_points_adaptive else 1]
    n_points = int(sum(len(x) for x in reg.x))
    results, table = {}, []
    for n_q in q_cands:
        for n_r in r_cands:
            tag = f"{n_q}x{n_r}"

            def cb(rec, tag=tag):
                if callback is not None:
                    callback({**rec, "model": tag})

            res = fit_em(reg.x, reg.ma.c, reg.ma.d, n_q=n_q, n_r=n_r, max_iter=p.em_max_iter,
                         tol=p.em_tol, callback=cb)
            k = _n_params(n_q, n_r, len(reg.x))
            bic = -2.0 * float(res.loglik) + k * np.log(max(n_points, 2))
            results[(n_q, n_r)] = res
            table.append({"model": tag, "n_q": n_q, "n_r": n_r, "loglik": float(res.loglik),
                          "n_params": k, "bic": float(bic), "iterations": len(res.iterations) - 1})
    best = min(table, key=lambda r: r["bic"])
    em = results[(best["n_q"], best["n_r"])]
    em.selection = {"criterion": "BIC" if len(table) > 1 else "fixed", "candidates": table,
                    "chosen": best["model"]}
    return em


def pooled_evidence(reg: Regularized, em, h_per_km: float, rho_km: float) -> list | None:
    """Cross-line evidence for each line's recognition (the anomaly-intensity part only).

    Each decimated point's log-evidence for the Q levels (relative to the smoothest),
    summed with weights ``exp(−h·d)`` over the points of *other* lines within ``ρ``:
    the anomaly's statistics are a property of the place, so neighbouring lines carry
    evidence about it; the GNSS noise levels are not (episodes are in time), so the
    R part is marginalised out before pooling.  Returns one (T_w, N) array per line,
    or None when pooling is off (ρ = 0)."""
    from app.core.nlmeans import RecognitionMap
    from app.core.recognition import state_evidence

    if rho_km <= 0 or len(reg.x) < 2:
        return None
    n_q, n_r = len(em.Q), len(em.R)
    ev = np.concatenate([state_evidence(x, reg.ma.c, reg.ma.d, em.Q, em.R) for x in reg.x])
    ev = ev.reshape(len(ev), n_q, n_r)
    top = ev.max(axis=2, keepdims=True)
    ev_q = (top + np.log(np.mean(np.exp(ev - top), axis=2, keepdims=True)))[:, :, 0]
    ev_q = ev_q - ev_q[:, :1]
    e = np.concatenate([ln.easting_km[i] for ln, i in zip(reg.lines, reg.idx)])
    n = np.concatenate([ln.northing_km[i] for ln, i in zip(reg.lines, reg.idx)])
    line_id = np.concatenate([np.full(len(x), w) for w, x in enumerate(reg.x)])
    rmap = RecognitionMap(e, n, max_rho_km=max(rho_km, 1e-6))
    pooled_q = rmap.neighbour_sum(ev_q, h_per_km, rho_km, groups=line_id)
    pooled = np.repeat(pooled_q, n_r, axis=1)
    return np.split(pooled, np.cumsum([len(x) for x in reg.x])[:-1])


def recognize(reg: Regularized, em, cfg: SurveyConfig | None = None) -> tuple[list, list]:
    """Viterbi path and posterior probabilities per line (SPEC §2 step 3).

    ``em.initial`` must hold one row of initial probabilities per regularized line.
    With ``processing.recognition_pool_rho_km > 0`` the evidence of neighbouring lines
    about the anomaly intensity is added to each line's emissions (:func:`pooled_evidence`)."""
    from app.core.recognition import recognize_lines

    extra = None
    if cfg is not None:
        p = cfg.processing
        extra = pooled_evidence(reg, em, p.recognition_pool_h_per_km, p.recognition_pool_rho_km)
    paths, probs = recognize_lines(reg.x, reg.ma.c, reg.ma.d, em.Q, em.R, em.transition,
                                   np.asarray(em.initial), extra_loglik=extra)
    return [np.asarray(s, int) for s in paths], [np.asarray(p, float) for p in probs]


def recognition_table(reg: Regularized, paths, probs) -> pd.DataFrame:
    """The decimated points of all lines: line, time, position, x, raw state, posteriors."""
    rows = []
    for ln, x, idx, s, pr in zip(reg.lines, reg.x, reg.idx, paths, probs):
        d = {"line": ln.line, "time": ln.t_s[idx], "easting_km": ln.easting_km[idx],
             "northing_km": ln.northing_km[idx], "x": x, "state_raw": s}
        for i in range(pr.shape[1]):
            d[f"p_{i}"] = pr[:, i]
        rows.append(pd.DataFrame(d))
    return pd.concat(rows, ignore_index=True)


def smooth_recognition(table: pd.DataFrame, n_states: int, h_per_km: float, rho_km: float,
                       mode: str = "soft", rmap=None):
    """NL-means smoothing of the recognition map (SPEC §2 step 4).

    Returns (labels (T,), probs (T, N), rmap)."""
    from app.core.nlmeans import RecognitionMap

    if rmap is None:
        rmap = RecognitionMap(table["easting_km"].to_numpy(), table["northing_km"].to_numpy(),
                              max_rho_km=max(15.0, rho_km))
    if mode == "soft":
        src = table[[f"p_{i}" for i in range(n_states)]].to_numpy()
    else:
        src = table["state_raw"].to_numpy()
    probs, labels = rmap.smooth(src, h_per_km, rho_km, mode=mode)
    return np.asarray(labels, int), np.asarray(probs, float), rmap


def hold_states(n_epochs: int, idx: np.ndarray, states: np.ndarray) -> np.ndarray:
    """Hold decimated states on the full-rate grid: each epoch takes the state of the
    nearest decimated point (by index)."""
    idx = np.asarray(idx, int)
    states = np.asarray(states, int)
    if idx.size == 0:
        raise ValueError("no decimated points")
    mid = 0.5 * (idx[1:] + idx[:-1])
    k = np.searchsorted(mid, np.arange(n_epochs), side="right")
    return states[k]


# --------------------------------------------------------------------------- 8. filtering
def filter_line(z_mgal, Q_mgal2, R_cm2s2, dt_s: float, m: int, method: str, noise=None):
    """Non-stationary Kalman smoother on one line: (dg_mgal, dg_std_mgal)."""
    from app.core.smoother import kalman_smooth

    res = kalman_smooth(np.asarray(z_mgal, float), np.asarray(Q_mgal2, float),
                        np.asarray(R_cm2s2, float), dt_s, m=m, method=method, noise=noise)
    return np.asarray(res.dg_mgal), np.asarray(res.dg_std_mgal)
