"""Stage 1, measurement (SPEC §1, §3): corrections and the anomaly measurement ``z_k`` of every
flight, the in-flight check of the declared lag, base ties to the parking-place readings.

:func:`measure` runs the stage on a survey and returns a :class:`Measurement`:

* the declared lag τ checked in flight (:func:`check_lag`: τ-only seed-001 calibration on up
  to three flights, used when they agree and differ from survey.toml), or the full in-flight
  calibration when ``processing.calibrate``;
* per flight (:func:`measure_flight`): normal gravity, Eötvös, the gravimeter–GNSS time
  offset (applied only when significant and useful), lag/scale inversion and interval
  means, epochs crossing record gaps left missing, spikes repaired;
* :func:`base_tie`: the static parking-place readings remove each flight's reading error
  and drift.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd
from scipy.optimize import minimize_scalar

from app.config import SurveyConfig
from app.core import clock, epochs, geodesy
from app.core import gravimeter as gm
from app.core import response as resp
from app.core.baselines import fir_kernel
from app.core.calibration import CalibrationSpectra, calibrate
from app.core.measurement import (
    MGAL_PER_MS2,
    anomaly_measurement_mgal,
    band_delay_fit,
    delay_correction_mgal,
    delay_heterogeneity,
    gnss_acceleration_ms2,
    gravimeter_height_misfit_m,
    height_outlier_mask,
    height_step_mask,
    height_step_sizes_m,
    repair_height_outliers,
    repair_spikes,
    spike_mask,
)
from app.core.noise_level import band_fit_coefficient, band_rms_mgal, local_noise_variance_cm2s2
from app.io.errors import InputError
from app.io.survey import gnss_runs
from app.io.tables import median_rate_hz
from app.pipeline.parallel import line_map


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
    heights_only: bool = False        # the GNSS file had no vu (derived from the heights)
    gnss_filled: int = 0              # missing GNSS epochs put back (fill_gnss_epochs)
    #: a gravimeter slower than the GNSS: z with the motion cancelled at its sample boundaries,
    #: its spike repair and notes (:func:`slow_gravimeter_z`), until :func:`choose_motion_compensation`
    #: decides for the survey
    compensated: tuple | None = None
    #: ∂z/∂τ (mGal/s): how z moves with the lag τ (the gravimeter's jerk on the GNSS intervals;
    #: z is linear in τ at a fixed time offset), for :func:`band_lag`
    dz_dtau_mgal_s: np.ndarray | None = None
    gravimeter_filled: int = 0        # missing gravimeter samples put back (fill_gravimeter_samples)


def each_flight(fn, items) -> list:
    """``[fn(x) for x in items]`` on the line threads (:func:`app.pipeline.parallel.line_map`),
    in the items' order: the flights of a survey are measured at once where the machine has
    the cores (their numerics release the GIL), and every sum over them is taken in their order,
    so the results do not depend on the thread count.  An exception is raised as the loop would
    raise it (the first item's, in order)."""
    return list(line_map()(fn, items))


def measure_flight(flight, cfg: SurveyConfig, tau_s: float | None = None,
                   scale: float | None = None, line_windows=None, compensation: bool = True,
                   match_response: bool = True, response_c_s2: float | None = None) -> FlightMeasurement:
    """Corrections and the anomaly measurement ``z_k`` (SPEC §1) for one whole flight.

    Parameters
    ----------
    flight : app.io.survey.Flight
    cfg : SurveyConfig
    tau_s, scale : float, optional
        Override the gravimeter lag and scale of ``survey.toml`` (in-flight calibration).
    line_windows : ndarray, shape (n_lines, 2), optional
        The flight's line windows (t_start, t_end in s): where a choice between two versions of
        z is judged (:func:`slow_gravimeter_z`); the airborne epochs when not given.
    compensation : bool
        Also form the motion-compensated z of a slow gravimeter for :func:`choose_motion_compensation`
        (only :func:`measure` uses it; the lag and calibration checks, which compare plain z
        with plain z, skip that work).
    match_response : bool
        Smooth the GNSS acceleration by the gravimeter's fitted response width
        (:func:`response_width`, when ``processing.match_response``); the lag and calibration
        checks, which read the gravimeter's response from z themselves, pass False.
    response_c_s2 : float, optional
        The response width to apply (s², 0 for none) whatever this flight's own fit decides: the
        survey's decision (:func:`choose_response_width`); the fit is still reported.
    """
    p = cfg.processing
    tau = cfg.gravimeter.tau_s if tau_s is None else tau_s
    k = cfg.gravimeter.scale if scale is None else scale
    notes = []
    vu_from_h = bool(getattr(flight, "vu_derived_from_h", False))
    gn, gnss_stamps = dejitter_gnss(flight.gnss, p.max_gap_s, vu_from_h, notes)
    gn, filled, fill_info = fill_gnss_epochs(gn, p.max_gap_s, vu_from_h, p.gnss_fill_max_error_mgal,
                                             p.fir_cutoff_period_s)
    n_filled = int(filled.sum())
    if n_filled:
        notes.append(f"{n_filled} missing GNSS epoch(s) put back on the receiver's clock (steps that are a whole "
                     f"multiple of the median step, at most {p.max_gap_s:g} s long): positions and velocities there "
                     "from the cubic spline through the record (report gnss_filled_epochs)")
    if fill_info.get("left"):
        notes.append(f"{fill_info['left']} hole(s) of missing GNSS epochs left as holes: a spline bridge over "
                     f"them moves FIR {p.fir_cutoff_period_s:g} s by more than {p.gnss_fill_max_error_mgal:g} mGal "
                     f"on this record (measured on it: {fill_info['error_mgal']})")
    t = gn["time"].to_numpy(float)
    lat = gn["lat"].to_numpy(float)
    lon = gn["lon"].to_numpy(float)
    h = gn["h"].to_numpy(float)
    vu = gn["vu"].to_numpy(float)
    if "ve" in gn and "vn" in gn:
        ve, vn = checked_horizontal_velocities(t, lat, lon, h, gn["ve"].to_numpy(float), gn["vn"].to_numpy(float),
                                               notes)
    else:
        ve, vn = geodesy.velocities_from_positions_ms(t, lat, lon, h)
    gamma = geodesy.normal_gravity_mgal(lat, h, cfg.survey.normal_gravity)
    eot = geodesy.eotvos_mgal(lat, h, ve, vn)

    rec_notes: list = []
    rec = gravimeter_record(flight.gravimeter, p, rec_notes)
    runs = height_runs(rec.series, t, vu_from_h, p)
    offset_notes: list = []
    offset_info = time_offset(rec.series, t, vu, tau, k, p, offset_notes, runs)
    # the gravimeter's clock along the flight: a drift or a jump re-times its stamps
    clock, retimed = gravimeter_clock(rec, (t, vu, ve, vn), (tau, k), p, vu_from_h, offset_info)
    if retimed is not None:   # kept when the flight's one-offset fit on it is better (judge_clock)
        new_notes, new_offset_notes = [], []
        new_rec = gravimeter_record(retimed, p, new_notes)
        new_runs = height_runs(new_rec.series, t, vu_from_h, p)
        new_offset = time_offset(new_rec.series, t, vu, tau, k, p, new_offset_notes, new_runs)
        if judge_clock(clock, offset_info, new_offset, p):
            rec, runs, offset_info, rec_notes, offset_notes = new_rec, new_runs, new_offset, new_notes, new_offset_notes
    notes.extend(rec_notes)
    if clock is not None:
        offset_info["clock"] = clock
        notes.extend(clock.pop("notes", []))
    series, t_grav, g_filled = rec.series, rec.t_s, rec.filled
    if vu_from_h:
        notes.append("vu derived from the GNSS heights (the file has no vu column): derivative of the not-a-knot "
                     "cubic spline through h, per contiguous run"
                     + ("; the gravimeter's double integral put through the same spline, so the aircraft's motion "
                        "cancels however coarsely the heights sample it" if runs is not None else ""))
    notes.extend(offset_notes)
    check_acceleration_gain(flight, offset_info, notes)
    # the report's time_offsets section: the stamps the samples were integrated on
    offset_info["gravimeter_stamp_jitter_ms"] = 1e3 * rec.largest_s
    offset_info["gravimeter_stamp_scatter_ms"] = 1e3 * rec.scale_s
    offset_info["gravimeter_stamps_dejittered"] = rec.dejittered
    offset_info.update(gnss_stamps)
    # how z's gravimeter side was formed: through the heights' spline (height_matched_means) or not
    offset_info["height_matched_means"] = runs is not None
    offset = offset_info.get("offset_s", 0.0)
    applied = bool(offset_info.get("applied", False))
    fbar = gm.gnss_side_means(series, t, tau, k, offset if applied else 0.0, runs)
    z = anomaly_measurement_mgal(fbar, t, vu, gamma, eot)
    # what matching the meter's response adds to z (mGal; None when it is not matched)
    matched = (match_meter_response(fbar, t, vu, series.step_s, p, response_c_s2, offset_info, notes)
               if match_response and p.match_response else None)
    if matched is not None:
        z = z + matched
    dz_dtau = 1e5 * (gm.gnss_side_means(series, t, tau + 1.0, k, offset if applied else 0.0, runs) - fbar)
    mask_gaps(z, t, t_grav + (offset if applied else 0.0), p.gravimeter_gap_margin_s, notes)
    # a flight without lines is judged on its airborne epochs
    judged = judged_epochs(t, ve, vn, line_windows if line_windows is not None and len(line_windows) else None)
    z_mc = (slow_gravimeter_z(series, (t, vu, gamma, eot, judged), (tau, k, offset if applied else 0.0), z, p,
                              offset_info, matched) if compensation else None)
    vu_from_h = bool(getattr(flight, "vu_derived_from_h", False))
    misfit = (height_misfit(series, (t, h, gamma, eot), (tau, k, offset if applied else 0.0))
              if vu_from_h and p.height_step_threshold is not None else None)
    compensated = None
    if z_mc is not None:
        notes_mc = list(notes)
        compensated = (*despike_z(z_mc, t, p, notes_mc, vu_from_h, filled, misfit), notes_mc)
    z, despike = despike_z(z, t, p, notes, vu_from_h, filled, misfit)
    return FlightMeasurement(flight.name, t, lat, lon, h, vu, ve, vn, gamma, eot, fbar, z,
                             float(offset), float(offset_info.get("correlation", np.nan)), applied, notes,
                             despike, offset_info, vu_from_h, n_filled, compensated, dz_dtau,
                             int(g_filled.sum()))


class GravimeterRecord(NamedTuple):
    """A flight's gravimeter record as z is formed from it (:func:`gravimeter_record`)."""

    series: object          # app.core.gravimeter.IntegratedSeries on the record's clock
    t_s: np.ndarray         # sample times (s): the dejittered clock, put-back samples included
    filled: np.ndarray      # bool per sample: put back (fill_gravimeter_samples)
    fill_info: dict         # what the fill measured (error_mgal, left)
    scale_s: float          # robust scatter of the stamps about the clock (s)
    largest_s: float        # largest scatter (s)
    dejittered: bool        # the samples were integrated on the clock, not their stamps
    f_ms2: np.ndarray       # f_z per sample (m/s²), put-back samples included


def gravimeter_record(gr: pd.DataFrame, p, notes: list) -> GravimeterRecord:
    """The gravimeter record ``gr`` (columns ``time`` s, ``f_z`` m/s²) as every z of the
    flight is formed from it: the stamps put on the instrument's uniform clock
    (:func:`app.core.gravimeter.dejitter_times_s`), dropped samples put back where the record
    predicts them (:func:`fill_gravimeter_samples`), integrated
    (:func:`app.core.gravimeter.integrate_samples`).  The measurement, the in-flight calibration
    and the QC table's time offset all start from it.  What was done is appended to ``notes``."""
    stamps = gr["time"].to_numpy(float)
    uniform = gm.dejitter_times_s(stamps)
    jitter = float(np.max(np.abs(uniform - stamps))) if stamps.size else 0.0
    scale_s, largest_s = gm.stamp_scatter_s(stamps)
    if jitter > gm.ROUNDING_JITTER_S:  # beyond a millisecond rounding: say so
        notes.append(f"gravimeter time stamps scatter up to {1e3 * jitter:.1f} ms about a uniform clock: the "
                     "samples were integrated on the clock (the instrument's sampling is uniform; the stamps' "
                     "scatter times the aircraft's acceleration would otherwise enter z)")
    elif not jitter > 0 and scale_s > gm.ROUNDING_JITTER_S:
        notes.append(f"gravimeter time stamps scatter by {1e3 * scale_s:.1f} ms (robust scale; up to "
                     f"{1e3 * largest_s:.1f} ms) about a uniform clock, more than stamp jitter: the samples were "
                     "integrated on their stamps as irregular sampling — if the instrument's clock is uniform, "
                     "that scatter times the aircraft's acceleration is in z")
    t_grav, f_z, g_filled, g_info = fill_gravimeter_samples(uniform, gr["f_z"].to_numpy(float), p.max_gap_s,
                                                             p.gravimeter_fill_max_error_mgal, p.fir_cutoff_period_s)
    _fill_notes(int(g_filled.sum()), g_info, p, notes)
    series = gm.integrate_samples(t_grav, f_z, dejitter=False)
    return GravimeterRecord(series, t_grav, g_filled, g_info, scale_s, largest_s, bool(jitter > 0), f_z)


def _fill_notes(n_filled: int, info: dict, p, notes: list) -> None:
    """What :func:`fill_gravimeter_samples` did, in the flight's notes."""
    if n_filled:
        notes.append(f"{n_filled} missing gravimeter sample(s) put back on the instrument's clock (steps that are a "
                     f"whole multiple of the median step, at most {p.max_gap_s:g} s long): the samples there from the "
                     f"cubic spline through the record, which moves FIR {p.fir_cutoff_period_s:g} s by at most "
                     f"{p.gravimeter_fill_max_error_mgal:g} mGal on this record (measured on it: {info['error_mgal']}; "
                     "report gravimeter_filled_samples)")
    if info.get("left"):
        notes.append(f"{info['left']} hole(s) of missing gravimeter samples left as holes: a spline bridge over them "
                     f"moves FIR {p.fir_cutoff_period_s:g} s by more than {p.gravimeter_fill_max_error_mgal:g} mGal on "
                     f"this record (measured on it: {info['error_mgal']})")


def checked_horizontal_velocities(t, lat, lon, h, ve, vn, notes: list) -> tuple[np.ndarray, np.ndarray]:
    """The GNSS file's ``ve``, ``vn`` (m/s), checked against the velocity of its own positions
    (:func:`app.core.geodesy.horizontal_velocity_misfit_ms`).  When they disagree by more than a
    quarter of the speed (and 5 m/s) and a relabelling — ve and vn swapped, a sign flipped —
    agrees (:func:`app.core.geodesy.velocity_relabelling`: its mean misfit within a quarter of the
    speed, and under a third of the next candidate's), that relabelling is used, with a note;
    otherwise they are kept, with a note that the anomaly is wrong (normal gravity and the Eötvös
    correction use them: a swap on the sample survey's east–west lines is 613 mGal RMS)."""
    speed, misfit, n_moving = geodesy.horizontal_velocity_misfit_ms(t, lat, lon, h, ve, vn)
    if not (n_moving >= 100 and misfit > max(5.0, 0.25 * speed)):
        return ve, vn
    what = (f"the GNSS file's ve/vn differ from the velocity of its own positions by {misfit:.0f} m/s "
            f"(median, at a median speed of {speed:.0f} m/s)")
    best = geodesy.velocity_relabelling(t, lat, lon, h, ve, vn)
    if best is not None and best[3] <= max(5.0, 0.25 * speed) and best[3] < best[4] / 3.0:
        label, ve_new, vn_new, mis, runner_up = best
        notes.append(f"{what}; with {label} they agree to {mis:.2g} m/s (mean; the next relabelling "
                     f"{runner_up:.2g} m/s): the columns were read so (normal gravity and the Eötvös correction "
                     "use them)")
        return ve_new, vn_new
    notes.append(f"{what}: a column is mislabelled — lat and lon swapped, ve and vn swapped or a sign flipped? "
                 "Normal gravity and the Eötvös correction use them; the anomaly is wrong by up to hundreds of mGal "
                 "until the columns are right")
    return ve, vn


def slow_gravimeter_z(series: gm.IntegratedSeries, gnss: tuple, response: tuple, z: np.ndarray, p,
                      info: dict, matched_mgal: np.ndarray | None = None) -> np.ndarray | None:
    """z of a gravimeter sampled slower than the GNSS with the aircraft's motion cancelled at its
    sample boundaries (:func:`app.core.gravimeter.motion_compensated_means`; None for a gravimeter
    that is not slower, by ``p.slow_gravimeter_min_ratio`` GNSS steps), and the evidence for
    :func:`choose_motion_compensation` in ``info['motion_compensation']`` (the report's
    time_offsets entry of the flight).

    Plain interval means (``z``) interpolate the gravimeter's integral between its sample
    boundaries and so miss how the aircraft's acceleration moved it inside a sample (on a 1 Hz
    mean record beside 10 Hz GNSS with 0.15 m/s² of turbulence: 1.4·10⁵ mGal²/Hz at
    0.02–0.05 Hz, with no GNSS error at all); the compensated means cancel the motion at the
    boundaries but sample the GNSS velocity there, which folds its error above the gravimeter's
    Nyquist frequency into the anomaly band (heights differentiated at 10 Hz: worse than the
    plain means).  Which is larger depends on the turbulence and on the GNSS, so the data
    decide: the RMS of both versions at 1–2 × 1/``fir_cutoff_period_s`` Hz over the lines
    (:func:`app.core.noise_level.band_rms_mgal`; the anomaly is the same in both and small there
    beside either noise).  ``gnss`` = (t_s, vu_ms, gamma_mgal, eotvos_mgal, judged), ``judged``
    the epochs compared on (the line windows: a turn's manoeuvres would rule the comparison),
    ``response`` = (tau_s, scale, time_offset_s); ``matched_mgal``: what matching the meter's
    response added to the plain z (:func:`matched_acceleration_change_mgal`), added to the
    compensated z too (the same meter, the same GNSS acceleration)."""
    t, vu, gamma, eot, judged = gnss
    dt = float(np.median(np.diff(t))) if t.size > 1 else float("nan")
    ratio = p.slow_gravimeter_min_ratio
    if ratio is None or not np.isfinite(dt) or series.step_s < ratio * dt:
        return None
    band = (1.0 / p.fir_cutoff_period_s, 2.0 / p.fir_cutoff_period_s)
    rec = {"applied": False, "gravimeter_step_s": series.step_s, "gnss_step_s": dt, "band_hz": list(band),
           "n_epochs": 0}
    info["motion_compensation"] = rec
    if not band[1] < 0.5 / dt:
        rec["reason"] = "the comparison band is above the GNSS Nyquist frequency"
        return None
    tau, k, offset = response
    z_mc = anomaly_measurement_mgal(gm.motion_compensated_means(series, t, vu, tau, k, time_offset_s=offset),
                                    t, vu, gamma, eot)
    if matched_mgal is not None:
        z_mc = z_mc + matched_mgal
    z_mc[~np.isfinite(z)] = np.nan              # the plain record's gap mask
    usable = judged & np.isfinite(z) & np.isfinite(z_mc)
    (r0, n), (r1, _) = (band_rms_mgal(x, dt, band, usable=usable) for x in (z, z_mc))
    rec.update({"band_rms_plain_mgal": r0, "band_rms_compensated_mgal": r1, "n_epochs": int(n)})
    if n * dt < USUAL_MIN_PERIODS * p.fir_cutoff_period_s:
        # short lines (under 3 FIR periods each leave nothing at 1-period edges): the same figures
        # on stretches of at least 1.5 periods with half a period left out at each end — only
        # where this flight alone is too short for the usual comparison (when the survey pools
        # too little, every flight is; a flight with enough makes the pool enough)
        edge = SHORT_LINE_EDGE_PERIODS * p.fir_cutoff_period_s
        (s0, ns), (s1, _) = (band_rms_mgal(x, dt, band, usable=usable, edge_s=edge) for x in (z, z_mc))
        rec["short_lines"] = {"edge_s": edge, "band_rms_plain_mgal": s0, "band_rms_compensated_mgal": s1,
                              "n_epochs": int(ns)}
    return z_mc


#: the usual comparison of :func:`choose_motion_compensation` needs this many FIR cut-off periods
#: of lines (pooled over the flights, 100 s left out at each end of every stretch)
USUAL_MIN_PERIODS = 10.0
#: the short-line comparison of :func:`slow_gravimeter_z`: the edge left out of each stretch (in
#: FIR cut-off periods; the usual comparison leaves one period, ``band_rms_mgal``'s 100 s) and the
#: least line time it needs (periods)
SHORT_LINE_EDGE_PERIODS = 0.5
SHORT_LINE_MIN_PERIODS = 5.0


def _pooled_band_rms(recs: list, key: str | None) -> tuple[float, float, int]:
    """The flights' band RMS of the plain and the compensated z pooled by their epochs (mGal, mGal,
    epochs): the usual comparison (``key`` None) or ``rec[key]``'s (``"short_lines"``)."""
    ss0 = ss1 = 0.0
    n = 0
    for m, r in recs:
        f = r if key is None else r.get(key)
        if m.compensated is not None and f and f["n_epochs"] and np.isfinite(f["band_rms_plain_mgal"]) \
                and np.isfinite(f["band_rms_compensated_mgal"]):
            ss0 += f["band_rms_plain_mgal"] ** 2 * f["n_epochs"]
            ss1 += f["band_rms_compensated_mgal"] ** 2 * f["n_epochs"]
            n += f["n_epochs"]
    r0, r1 = (float(np.sqrt(x / n)) if n else float("nan") for x in (ss0, ss1))
    return r0, r1, n


def _short_lines_choice(recs: list, dt: float, band, p) -> tuple[str, float, float]:
    """Where the usual comparison has too little line time: ``("", r0, r1)`` when the short-line
    figures (50 s edges) over at least :data:`SHORT_LINE_MIN_PERIODS` FIR periods of lines show
    the compensated z quieter by ``p.slow_gravimeter_short_drop`` or more, else why not."""
    r0, r1, n = _pooled_band_rms(recs, "short_lines")
    period = p.fir_cutoff_period_s
    if not n or n * dt < SHORT_LINE_MIN_PERIODS * period:
        return (f"{n * dt:.0f} s of lines even with {SHORT_LINE_EDGE_PERIODS * period:.0f} s edges (fewer than "
                f"{SHORT_LINE_MIN_PERIODS * period:.0f} s)"), r0, r1
    if r1 < (1.0 - p.slow_gravimeter_short_drop) * r0:
        return "", r0, r1
    return (f"on the short lines ({n * dt:.0f} s, {SHORT_LINE_EDGE_PERIODS * period:.0f} s edges) z's RMS at "
            f"{band[0]:g}–{band[1]:g} Hz {r0:.3g} → {r1:.3g} mGal, not {100 * p.slow_gravimeter_short_drop:.0f} % "
            "lower"), r0, r1


def choose_motion_compensation(flights: dict, p) -> None:
    """For the whole survey, in place: every flight of a gravimeter slower than the GNSS gets its
    motion-compensated z (:func:`slow_gravimeter_z`) when that lowers z's band RMS, pooled over
    the flights by their epochs, by ≥ 3 % over ≥ 10 FIR cut-off periods of lines; else all keep
    the plain interval means.  One choice for all flights, not one each: the noise model is
    shared by the flights, and a mixture fitted worse than either (simulated 1 Hz platform
    survey: the compensated flights with a 300 s one left plain, 6.43 → 7.79 mGal), and a
    300 s flight's band RMS scatters by more than 3 % alone.

    **Short lines** (too little line time for that: lines of 250 s leave nothing at 100 s edges):
    the figures on stretches of ≥ 1.5 periods with half a period left out at each end
    (:data:`SHORT_LINE_EDGE_PERIODS`), over ≥ 5 periods of lines, and the compensated z taken only
    when it is quieter by ``p.slow_gravimeter_short_drop`` (20 %) or more — a shorter record
    scatters more, so only a clear drop counts.  A five-line 25 km survey with a 1 Hz interval-mean
    meter in 0.15–0.6 m/s² of turbulence kept the plain means, whose interpolation error read as
    GNSS noise 160× the receiver's and flattened the estimate (16.3 mGal against FIR's 8.76);
    compensated (band RMS 31.8 → 12.0 mGal) 4.53 against FIR's 5.05."""
    recs = [(m, m.time_offset.get("motion_compensation")) for m in flights.values()]
    recs = [(m, r) for m, r in recs if r is not None]
    if not recs:
        return
    dt = float(recs[0][1]["gnss_step_s"])
    band = recs[0][1]["band_hz"]
    r0, r1, n = _pooled_band_rms(recs, None)
    short = None
    if not n or n * dt < USUAL_MIN_PERIODS * p.fir_cutoff_period_s:
        why_short, s0, s1 = _short_lines_choice(recs, dt, band, p)
        short = {"band_rms_plain_mgal": s0, "band_rms_compensated_mgal": s1, "used": not why_short}
        if not why_short:
            why = ""
        elif not n:
            why = f"no line long enough to compare the two at 100 s edges; {why_short}"
        else:
            why = (f"plain interval means kept: {n * dt:.0f} s of lines to compare the two on, fewer than "
                   f"{USUAL_MIN_PERIODS * p.fir_cutoff_period_s:.0f} s ({USUAL_MIN_PERIODS:g} FIR cut-off periods); "
                   f"{why_short}")
    elif r1 < 0.97 * r0:
        why = ""
    else:
        why = (f"plain interval means kept: cancelling the motion at the sample boundaries would not lower z's "
               f"RMS at {band[0]:g}–{band[1]:g} Hz by 3 % over the survey ({r0:.3g} → {r1:.3g} mGal; the GNSS "
               "velocity's error folds into the band)")
    for m, r in recs:
        r.update({"survey_band_rms_plain_mgal": r0, "survey_band_rms_compensated_mgal": r1})
        if short is not None:
            r["survey_short_lines"] = short
        if why or m.compensated is None:
            r.setdefault("reason", why or "not compared on this flight")
            continue
        m.z_mgal, m.despike, m.notes = m.compensated
        r["applied"] = True
        if short is not None:
            r["reason"] = (f"motion cancelled at the gravimeter's {r['gravimeter_step_s']:g} s sample boundaries: on "
                           f"the short lines z's RMS at {band[0]:g}–{band[1]:g} Hz {short['band_rms_plain_mgal']:.3g} "
                           f"→ {short['band_rms_compensated_mgal']:.3g} mGal (≥ "
                           f"{100 * p.slow_gravimeter_short_drop:.0f} % lower)")
        else:
            r["reason"] = (f"motion cancelled at the gravimeter's {r['gravimeter_step_s']:g} s sample boundaries: z's "
                           f"RMS at {band[0]:g}–{band[1]:g} Hz over the survey {r0:.3g} → {r1:.3g} mGal")
    for m in flights.values():
        m.compensated = None                    # the unused version is not kept


#: the positions' verdict on stamps scattering more than dejitter_times_s allows by default
#: (app.core.epochs.positions_follow_stamps): below this correlation the epochs stayed on the
#: receiver's clock (the sample survey's F01 with ±20 ms stamps: −0.004; positions truly taken at
#: those times: 0.996), over at least this many moving epoch intervals
POSITIONS_ON_CLOCK_MAX_CORR = 0.3
POSITIONS_MIN_INTERVALS = 100


def dejitter_gnss(gn: pd.DataFrame, max_gap_s: float, vu_from_h: bool, notes: list) -> tuple[pd.DataFrame, dict]:
    """The GNSS stamps put back on the receiver's uniform clock when they scatter about it like
    a logger's or a rounding's stamps (:func:`app.core.gravimeter.dejitter_times_s`: a robust
    scale of at most 1.5 ms or 5 % of the step) **and** the scatter is uncorrelated from epoch to epoch (lag-1
    correlation below 0.5).  A receiver whose clock is not steered stamps its epochs at the
    true, slowly drifting times (a sawtooth): those are kept.  The positions belong to the
    clock's epochs; on stamps scattered by ±1 ms the 2 Hz test line's FIR 100 s error went from
    1.92 to 2.38 mGal, the estimate's from 1.47 to 1.86 with its 2σ coverage down to 0.96 (±2 ms:
    0.75–0.89).  Stamps scattering by more than that bound are put back on the clock too (up
    to a quarter of a step) when the positions say the epochs stayed on it: the distances
    between consecutive epochs do not follow the stamp intervals
    (:func:`app.core.epochs.positions_follow_stamps`, correlation below
    :data:`POSITIONS_ON_CLOCK_MAX_CORR`; the sample survey with ±20 ms stamps at 10 Hz was 168
    mGal RMS off kept as stamped, 0.26 now).  A ``vu`` derived from the heights is derived again on the clock's epochs.
    Returns the table and the evidence for the report (``gnss_stamp_jitter_ms``,
    ``gnss_stamp_jitter_lag1``, ``gnss_stamps_dejittered``)."""
    t = gn["time"].to_numpy(float)
    u = gm.dejitter_times_s(t)
    dev = t - u
    jitter = float(np.max(np.abs(dev))) if dev.size else 0.0
    scale_s, largest_s = gm.stamp_scatter_s(t)
    info = {"gnss_stamp_jitter_ms": 1e3 * largest_s, "gnss_stamp_scatter_ms": 1e3 * scale_s,
            "gnss_stamps_dejittered": False}
    by_positions = False
    if not jitter > 1e-6 and scale_s > gm.ROUNDING_JITTER_S and {"lat", "lon"} <= set(gn.columns):
        # more scatter than jitter is allowed by default: the positions say whether the epochs
        # moved with the stamps (irregular sampling) or stayed on the receiver's clock
        corr, n_used = epochs.positions_follow_stamps(t, gn["lat"].to_numpy(float), gn["lon"].to_numpy(float))
        info.update(gnss_stamp_positions_corr=corr, gnss_stamp_positions_intervals=n_used)
        if np.isfinite(corr) and n_used >= POSITIONS_MIN_INTERVALS and corr < POSITIONS_ON_CLOCK_MAX_CORR:
            u = gm.dejitter_times_s(t, max_jitter_s=0.25 * float(np.median(np.diff(t))))
            dev = t - u
            jitter = float(np.max(np.abs(dev))) if dev.size else 0.0
            by_positions = jitter > 1e-6
    if not jitter > 1e-6:   # on the clock already (float round-off), or too irregular for jitter
        if scale_s > gm.ROUNDING_JITTER_S:
            corr = info.get("gnss_stamp_positions_corr")
            said = ("" if corr is None or not np.isfinite(corr) else
                    f" (the positions move with the stamps: correlation {corr:.2f} of the distances between "
                    "epochs with their intervals)" if corr >= POSITIONS_ON_CLOCK_MAX_CORR else
                    f" (the positions do not follow the stamps, correlation {corr:.2f}, but some stamp is a "
                    "quarter step or more off the clock)")
            notes.append(f"GNSS time stamps scatter by {1e3 * scale_s:.1f} ms (robust scale; up to "
                         f"{1e3 * largest_s:.1f} ms) about a uniform clock, more than stamp jitter{said}: kept as "
                         "stamped — if the receiver's epochs are uniform, velocities differenced over these "
                         "stamps carry the aircraft's acceleration times their relative error")
        return gn, info
    moved = np.abs(dev) > 1e-9
    d = dev[moved]
    lag1 = float(np.corrcoef(d[1:], d[:-1])[0, 1]) if d.size > 10 and np.std(d) > 0 else float("nan")
    info["gnss_stamp_jitter_lag1"] = lag1
    if not (np.isfinite(lag1) and lag1 < 0.5):
        if jitter > gm.ROUNDING_JITTER_S:
            notes.append(f"GNSS time stamps deviate up to {1e3 * jitter:.1f} ms from a uniform clock, correlated from "
                         f"epoch to epoch (lag-1 correlation {lag1:.2f}: a receiver clock, not stamp jitter): kept")
        return gn, info
    runs = gnss_runs(u, max_gap_s)
    if vu_from_h and min(b - a for a, b in runs) < 4:
        # a step at the gap limit fell the other side of it: a run too short for the spline (the
        # reader checked the stamps' runs) — keep the stamps rather than refuse the flight
        info["reason"] = "kept: a run between gaps would be too short to derive vu from the heights"
        return gn, info
    out = gn.copy()
    out["time"] = u
    if vu_from_h:
        for a, b in runs:
            out.iloc[a:b, out.columns.get_loc("vu")] = geodesy.vertical_velocity_from_heights_ms(
                u[a:b], out["h"].to_numpy(float)[a:b])
    info["gnss_stamps_dejittered"] = True
    if by_positions:
        notes.append(f"GNSS time stamps scatter up to {1e3 * jitter:.1f} ms about a uniform clock, uncorrelated from "
                     f"epoch to epoch (lag-1 correlation {lag1:.2f}), and the positions do not move with them "
                     f"(correlation {info['gnss_stamp_positions_corr']:.2f} of the distances between epochs with "
                     "their intervals): a logger's stamps — the receiver's epochs were put back on its clock")
    elif jitter > gm.ROUNDING_JITTER_S:
        notes.append(f"GNSS time stamps scatter up to {1e3 * jitter:.1f} ms about a uniform clock, uncorrelated from "
                     f"epoch to epoch (lag-1 correlation {lag1:.2f}): the receiver's epochs were put back on the clock")
    return out, info


def fill_gnss_epochs(gn: pd.DataFrame, max_step_s: float, vu_from_h: bool, max_error_mgal: float | None = None,
                     cutoff_period_s: float = 100.0) -> tuple[pd.DataFrame, np.ndarray, dict]:
    """The GNSS table with its missing epochs put back on the receiver's clock
    (:func:`app.core.epochs.uniform_epochs`: steps of a whole number of median steps, at most
    ``max_step_s``) where the record says a spline bridge is good enough — the FIR
    ``cutoff_period_s`` low-pass of the acceleration moves by at most ``max_error_mgal`` when
    as many epochs are taken out of it elsewhere (:func:`app.core.epochs.fill_error_mgal`; a
    longer hole stays a hole) — every column there from the cubic spline through the record
    (:func:`app.core.epochs.fill_at`, per run between record gaps; longitude unwrapped).  A
    ``vu`` derived from the heights is derived again on the filled epochs: the spline through
    the filled heights is the record's own, so ``vu`` is unchanged at the recorded epochs.
    Returns the table, a mask of the inserted epochs and the evidence (``error_mgal`` per number
    of epochs missing in a row, ``left``: holes left)."""
    t = gn["time"].to_numpy(float)
    t_new, ins = epochs.uniform_epochs(t, max_step_s)
    info: dict = {}
    if not ins.any():
        return gn, ins, info
    if max_error_mgal is not None:
        t_new, ins, info = _fillable(t, t_new, ins, gn["h"].to_numpy(float) if vu_from_h else gn["vu"].to_numpy(float),
                                     vu_from_h, max_error_mgal, cutoff_period_s)
        if not ins.any():
            return gn, ins, info
    runs = _runs_left(t, ins)
    out = {"time": t_new}
    for c in gn.columns:
        if c == "time" or (c == "vu" and vu_from_h):
            continue
        v = gn[c].to_numpy(float)
        if c == "lon":   # across ±180°: the spline on the unwrapped longitude, only the new ones wrapped
            u = epochs.fill_at(t, np.rad2deg(np.unwrap(np.deg2rad(v))), t_new, ins, runs)
            out[c] = np.where(ins, (u + 180.0) % 360.0 - 180.0, 0.0)
            out[c][~ins] = v
        else:
            out[c] = epochs.fill_at(t, v, t_new, ins, runs)
    if vu_from_h:
        vu = np.empty(t_new.size)
        for a, b in gnss_runs(t_new, max_step_s):
            # filling only joins runs, so each is at least as long as the reader's (≥ 4 samples)
            vu[a:b] = (geodesy.vertical_velocity_from_heights_ms(t_new[a:b], out["h"][a:b]) if b - a >= 4
                       else np.interp(t_new[a:b], t, gn["vu"].to_numpy(float)))
        out["vu"] = vu
    return pd.DataFrame(out, columns=list(gn.columns)), ins, info


def _runs_left(t, ins) -> list[tuple[int, int]]:
    """Index ranges ``[a, b)`` of the record ``t`` between the gaps that stay gaps once the
    epochs ``ins`` (of the filled clock) are put back: a step that was filled is no break."""
    filled_step = np.diff(np.flatnonzero(~ins)) > 1
    dt = np.diff(t)
    cut = np.flatnonzero((dt > 1.5 * float(np.median(dt))) & ~filled_step) + 1
    edges = np.concatenate([[0], cut, [t.size]])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def fill_gravimeter_samples(t_s, f_ms2, max_step_s: float, max_error_mgal: float | None,
                            cutoff_period_s: float = 100.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """The gravimeter's samples with the missing ones of its clock put back where the record
    says a spline bridge is good enough.

    A logger that drops a sample leaves one step of two (or a few) clock steps
    (:func:`app.core.epochs.uniform_epochs`, at most ``max_step_s``).  Left as a hole, the
    integral over it is unknown and z is left out around it (:func:`mask_gaps`: ± the gap
    margin, 4 s of z per dropped sample), which splits the lines into stretches; one dropped
    sample a minute left most lines of a survey too short to identify.  A record sampled
    fast against the aircraft's motion (a GT-1A's 18 Hz) predicts a missing sample closely,
    a 2 Hz platform's does not (its samples' lag-1 correlation is 0.46): the record decides,
    as for the GNSS (:func:`app.core.epochs.fill_error_mgal` on the samples themselves — as
    many samples taken out at 40 places, the cubic spline through the rest, the largest
    change of the FIR ``cutoff_period_s`` low-pass, RMS over the places).  Holes whose bridge
    moves it by at most ``max_error_mgal`` are filled from the spline through the record
    (per run between the gaps that stay); the others stay holes.  ``max_error_mgal`` None: no
    sample is put back.

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        Sample times on the instrument's clock (s; stamp jitter removed), strictly increasing.
    f_ms2 : ndarray, shape (n,)
        The samples (m/s²).
    max_step_s : float
        Longest step filled (s).
    max_error_mgal : float or None
        Largest change of the FIR low-pass a fill may cost (mGal).
    cutoff_period_s : float
        The low-pass's cutoff period (s).

    Returns
    -------
    t_new, f_new : ndarray, shape (N,)
        The samples with the inserted ones among them.
    inserted : ndarray of bool, shape (N,)
    info : dict
        ``error_mgal`` per number of samples missing in a row, ``left`` (holes left as holes);
        empty when no sample is missing.
    """
    t = np.asarray(t_s, dtype=float)
    f = np.asarray(f_ms2, dtype=float)
    none = (t, f, np.zeros(t.size, bool))
    if max_error_mgal is None:
        return (*none, {})
    t_new, ins = epochs.uniform_epochs(t, max_step_s)
    if not ins.any():
        return (*none, {})
    t_new, ins, info = _fillable(t, t_new, ins, f, False, max_error_mgal, cutoff_period_s, acceleration=True)
    if not ins.any():
        return (*none, info)
    return t_new, epochs.fill_at(t, f, t_new, ins, _runs_left(t, ins)), ins, info


def _fillable(t, t_new, ins, y, derivative: bool, max_error_mgal: float, cutoff_period_s: float,
              acceleration: bool = False):
    """Keep the inserted epochs of the holes whose length the record can bridge
    (:func:`fill_gnss_epochs`, :func:`fill_gravimeter_samples`)."""
    dt = float(np.median(np.diff(t)))
    kernel = fir_kernel(dt, cutoff_period_s)
    idx = np.flatnonzero(ins)
    groups = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)   # the epochs of each hole
    err = {m: epochs.fill_error_mgal(t, y, m, kernel, derivative, acceleration=acceleration)
           for m in sorted({g.size for g in groups})}
    keep = np.ones(t_new.size, bool)
    left = 0
    for g in groups:
        if not err[g.size] <= max_error_mgal:          # NaN (no stretch to measure on): no fill
            keep[g] = False
            left += 1
    info = {"error_mgal": {str(m): round(e, 3) for m, e in err.items()}, "left": left}
    return t_new[keep], ins[keep], info


#: an applied gravimeter–GNSS time offset this large (s) is a difference of clocks, said in a note
LARGE_TIME_OFFSET_S = 1.0


def height_runs(series: gm.IntegratedSeries, t, vu_from_h: bool, p) -> list | None:
    """The GNSS runs over which the heights' spline derived vu, when the gravimeter is to be
    compared with the heights through the same spline (:func:`app.core.gravimeter.height_matched_means`):
    vu from the heights, ``height_matched_means`` on, and a gravimeter sampled at least as often as
    the GNSS (a slower one's double integral between its samples is a spline's guess of the motion:
    :func:`slow_gravimeter_z` cancels the motion at its sample boundaries instead).  None otherwise."""
    if not (vu_from_h and p.height_matched_means) or t.size < 4:
        return None
    if series.step_s > 1.01 * float(np.median(np.diff(t))):
        return None
    return gnss_runs(t, p.max_gap_s)


def time_offset(series, t, vu, tau: float, k: float, p, notes: list, runs=None) -> dict:
    """The gravimeter–GNSS time offset and the decision to apply it (with its evidence).

    Applied only when the estimate is significant (``time_offset_min_z`` standard errors)
    and removes a real share of the acceleration residual (``time_offset_min_improvement``):
    an offset a few ms from zero only trades one response mismatch for another."""
    if not p.estimate_time_offset:
        return {"estimated": False}
    band = (0.01, acceleration_band_top_hz(float(np.median(np.diff(t))), series.step_s))
    try:
        fit = gm.fit_time_offset(series, t, vu, tau, k, p.max_time_offset_s, band_hz=band, height_runs=runs)
    except ValueError as exc:  # too short a flight, etc.
        notes.append(f"time offset not estimated: {exc}")
        return {"estimated": False}
    offset, corr = fit.offset_s, fit.correlation
    info = {"estimated": True, "offset_s": offset, "se_s": fit.se_s, "correlation": corr, "gain": fit.gain,
            "gain_low": fit.gain_low, "gain_low_correlation": fit.gain_low_correlation,
            "gain_low_band_hz": list(gm.GAIN_LOW_BAND_HZ),
            "residual_reduction": fit.relative_improvement, "residual_m2s4": fit.cost_min,
            "band_hz": [float(b) for b in band]}
    if not (np.isfinite(corr) and corr > 0.1):
        notes.append(f"the gravimeter's and the GNSS vertical accelerations do not match at any time offset "
                     f"within ±{p.max_time_offset_s:g} s (best correlation {corr:.2f}): the two files' time "
                     "scales differ (GPS vs UTC, time zone?) or one of them is not this flight's; set "
                     "[gravimeter] time_offset_s — the anomaly is not usable as it is")
    if not p.apply_time_offset:
        return info
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
    info.update(applied=not why, reason="; ".join(why) if why else "significant and improves the fit")
    if why:
        notes.append(f"time offset {offset:.4f} s not applied: {'; '.join(why)}")
    elif abs(offset) >= LARGE_TIME_OFFSET_S:
        notes.append(f"time offset {offset:.4f} s applied (± {fit.se_s:.1g} s, correlation {corr:.3f}): the "
                     "gravimeter's and the GNSS's clocks differ by that much"
                     + (" — GPS − UTC leap seconds (18 s since 2017): one file is on UTC, the other on GPS time"
                        if 16.5 <= abs(offset) <= 18.5 else "")
                     + "; lines.csv windows and the outputs are on the GNSS's time scale")
    return info


#: The search (± s) of each clock-tracking window about the flight's own time offset.
CLOCK_SEARCH_S = 2.0
#: Fewest windows (with a correlation above :data:`CLOCK_MIN_CORRELATION`) the clock is tracked on.
CLOCK_MIN_WINDOWS = 5
#: Windows whose accelerations correlate less than this are left out (calm air: no timing in them).
CLOCK_MIN_CORRELATION = 0.5


def clock_retimed(rec: GravimeterRecord, clock_info: dict | None) -> pd.DataFrame | None:
    """The gravimeter record ``rec`` (:func:`gravimeter_record`) re-timed as :func:`gravimeter_clock`
    decided (its evidence ``clock_info``, ``model`` kept when applied): its samples on the
    instrument's clock (dejittered, dropped ones put back), the clock put on the GNSS's scale —
    a record of ``time`` and ``f_z`` for :func:`gravimeter_record` again.  The clock, not the raw
    stamps: a rounding of the stamps that the dejitter recognises would no longer be one after
    part of them moved by a fraction of the rounding.  None when no re-timing was applied."""
    if not (clock_info and clock_info.get("applied") and clock_info.get("model")):
        return None
    mod = clock_info["model"]
    model = clock.ClockModel(mod["offset_s"], mod["drift_s_per_s"], mod["t_ref_s"],
                             tuple(tuple(x) for x in mod["steps"]))
    return pd.DataFrame({"time": clock.retime_stamps_s(rec.t_s, model, mod["reference_s"]), "f_z": rec.f_ms2})


def _window_offsets(rec: GravimeterRecord, gnss: tuple, response: tuple, p, vu_from_h: bool, center: float,
                    band: tuple, gap_at: np.ndarray) -> list[tuple]:
    """The time offset on each clock window (:func:`app.core.clock.clock_windows`), searched
    ±:data:`CLOCK_SEARCH_S` about ``center`` (s): ``(centre s, offset s, se s, correlation)`` of the
    windows that hold none of the gaps ``gap_at`` (a step inside would blur its offset) and
    correlate at least :data:`CLOCK_MIN_CORRELATION`."""
    t, vu, ve, vn = gnss
    tau, k = response
    rows = []
    for a, b in clock.clock_windows(t, np.hypot(ve, vn) > 20.0, p.clock_window_s):
        tw, vw = t[a:b], vu[a:b]
        if np.any((gap_at + center > tw[0]) & (gap_at + center <= tw[-1])):
            continue
        try:
            fit = gm.fit_time_offset(rec.series, tw, vw, tau, k, CLOCK_SEARCH_S, band,
                                     height_runs(rec.series, tw, vu_from_h, p), center_s=center)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            continue   # a window the fit cannot take (too short a run, a flat record): left out
        if np.isfinite(fit.correlation) and fit.correlation >= CLOCK_MIN_CORRELATION and 0 < fit.se_s < np.inf:
            rows.append((0.5 * float(tw[0] + tw[-1]), fit.offset_s, fit.se_s, fit.correlation))
    return rows


def gravimeter_clock(rec: GravimeterRecord, gnss: tuple, response: tuple, p, vu_from_h: bool,
                     offset_info: dict) -> tuple[dict | None, pd.DataFrame | None]:
    """The gravimeter's clock tracked against the GNSS's along one flight (:mod:`app.core.clock`).

    The time offset is fitted on windows of ``clock_window_s`` over the airborne runs
    (:func:`app.core.gravimeter.fit_time_offset`, searched ±:data:`CLOCK_SEARCH_S` about the
    flight's offset), windows whose accelerations correlate under :data:`CLOCK_MIN_CORRELATION`
    left out; :func:`app.core.clock.fit_clock_at_gaps` keeps a drift or steps only where the
    windows' own scatter says they are real (``clock_p``) and they move the clock by at least
    ``clock_min_change_s``, a step only at a gap of the record (a clock set forward; one set back
    makes the stamps go back, which the reader refuses).  The record's clock re-timed by the
    model (:func:`clock_retimed`; the constant part stays with the flight's time offset) is a
    proposal: :func:`measure_flight` keeps it when the flight's one-offset fit on it is better
    (:func:`judge_clock`).

    Parameters
    ----------
    rec : GravimeterRecord
        The flight's gravimeter record (:func:`gravimeter_record`): its clock is what is re-timed.
    gnss : tuple
        ``(t, vu, ve, vn)`` at the GNSS epochs (s, m/s).
    response : tuple
        ``(τ, k)`` of the interval means.
    offset_info : dict
        :func:`time_offset`'s evidence for the whole flight.

    Returns
    -------
    (dict or None, DataFrame or None)
        The evidence (``windows``, ``drift_ppm``, ``steps``, ``terms``, ``reason``, ``notes``)
        — None when tracking is off or the offset was not estimated — and the re-timed record
        proposed (None when the windows show nothing to mend).
    """
    if not (p.clock_track and p.estimate_time_offset and offset_info.get("estimated")):
        return None, None
    t = gnss[0]
    center = float(offset_info.get("offset_s", 0.0))
    band = (0.01, acceleration_band_top_hz(float(np.median(np.diff(t))), rec.series.step_s))
    step_s = float(rec.series.step_s)
    gap_at, gap_extra, lost = clock.step_candidates(rec.t_s, max(p.clock_min_change_s, 0.5 * step_s))
    # a window across a gap that is not whole samples would blur a step there: left out
    rows = _window_offsets(rec, gnss, response, p, vu_from_h, center, band, gap_at[~lost])
    info: dict = {"window_s": float(p.clock_window_s), "windows": [
        {"t_s": r[0], "offset_s": r[1], "se_s": r[2], "correlation": r[3]} for r in rows], "applied": False,
        "candidate_gaps": int(gap_at.size)}
    if len(rows) < CLOCK_MIN_WINDOWS:
        info["reason"] = f"{len(rows)} windows with the accelerations correlated (< {CLOCK_MIN_WINDOWS}): not tracked"
        return info, None
    wt, wo, wse = (np.array([r[i] for r in rows]) for i in range(3))
    model, info["steps"] = clock.fit_clock_at_gaps(wt, wo, wse, (gap_at, gap_extra), step_s, center, p.clock_p,
                                                   p.clock_min_change_s)
    info.update(drift_ppm=1e6 * model.drift_s_per_s, drift_over_flight_s=model.drift_s_per_s * float(wt[-1] - wt[0]),
                terms=model.terms)
    if not model.changes:
        info["reason"] = "one offset fits every window"
        return info, None
    what = []
    if model.drift_s_per_s:
        what.append(f"runs {-1e6 * model.drift_s_per_s:+.1f} ppm fast ({-1e3 * info['drift_over_flight_s']:+.0f} ms "
                    f"over {(wt[-1] - wt[0]) / 3600:.1f} h)")
    what += [f"was set {abs(st['size_s']):.3f} s {'forward' if st['size_s'] < 0 else 'back'} at {st['time_s']:.2f} s "
             f"(a {st['gap_s']:.3f} s gap of the record)" for st in info["steps"]]
    ref = float(np.sum(wt / wse ** 2) / np.sum(1.0 / wse ** 2)) - center   # on the stamps' scale
    info["model"] = {"offset_s": model.offset_s, "drift_s_per_s": model.drift_s_per_s, "t_ref_s": model.t_ref_s,
                     "steps": [list(x) for x in model.steps], "reference_s": ref}
    retimed = clock_retimed(rec, {**info, "applied": True})
    if not np.all(np.diff(retimed["time"].to_numpy(float)) > 0):
        info.pop("model")
        info["reason"] = "the re-timed stamps would not increase (a jump larger than its gap): not re-timed"
        info["notes"] = [f"the gravimeter's clock {' and '.join(what)} against the GNSS's, not re-timed: "
                         + info["reason"]]
        return info, None
    info["what"] = what
    info["n_windows"] = len(rows)
    return info, retimed


def judge_clock(info: dict, before: dict, after: dict, p) -> bool:
    """Whether the re-timed record :func:`gravimeter_clock` proposed is kept (``info`` updated in
    place, with the notes): the flight's band-passed acceleration residual with one offset
    (:func:`time_offset`'s fit, ``residual_m2s4``) before and after must drop by
    ``time_offset_min_improvement`` at least."""
    what, n = " and ".join(info.pop("what")), info.pop("n_windows")
    r0, r1 = before.get("residual_m2s4", np.nan), after.get("residual_m2s4", np.nan)
    gain = (r0 - r1) / r0 if np.isfinite(r0) and np.isfinite(r1) and r0 > 0 else np.nan
    info.update(residual_before_m2s4=r0, residual_after_m2s4=r1, residual_reduction=gain)
    if not gain >= p.time_offset_min_improvement:
        info.pop("model")
        info["reason"] = (f"re-timing removes only {100 * gain:.2f} % of the acceleration residual "
                          f"(< {100 * p.time_offset_min_improvement:g} %)" if np.isfinite(gain)
                          else "the re-timed record's time offset could not be fitted")
        info["notes"] = [f"the gravimeter's clock {what} against the GNSS's by {n} windows of "
                         f"{p.clock_window_s:g} s, not re-timed: {info['reason']}"]
        return False
    info.update(applied=True, reason="significant, and removes that share of the acceleration residual")
    info["notes"] = [f"the gravimeter's clock {what} against the GNSS's (time offsets of {n} windows of "
                     f"{p.clock_window_s:g} s): the gravimeter's stamps re-timed to the GNSS's scale, "
                     f"{100 * gain:.0f} % of the acceleration residual removed (report time_offsets.clock)"]
    return True


#: the gravimeter's acceleration per unit of the GNSS's when the GNSS heights (and velocities) are in
#: feet: 0.3048 (m per foot); within ±:data:`FEET_GAIN_TOLERANCE` of it a flight is refused (clean
#: surveys: 0.88–1.02; in feet 0.302–0.312, a 1 Hz heights-only record the farthest)
FEET_GAIN = 0.3048
FEET_GAIN_TOLERANCE = 0.08
#: gains outside this range (the gravimeter's and the GNSS accelerations at different scales) are warned about
PLAUSIBLE_GAIN = (0.7, 1.4)


def response_width(fbar_ms2, t, vu, gravimeter_step_s: float, p) -> dict:
    """The gravimeter's smoothing relative to the GNSS acceleration (:func:`app.core.response.fit_response_width`,
    in the time offset's band) and this flight's verdict on matching it, with its evidence (the
    report's time_offsets entry ``response_width``; :func:`choose_response_width` decides for the
    survey).

    Applied when the width is significant (``response_min_z`` standard errors) and removes at
    least ``response_min_improvement`` of the band-passed residual: a platform meter's point
    samples behind its decimation filter (2 Hz, two 0.5 s boxcars: c ≈ 0.014 s², 65–80 % of the
    residual at 0.01–0.8 Hz).  Interval means on the GNSS's own clock match already (c = 0)."""
    t = np.asarray(t, float)
    dt = float(np.median(np.diff(t))) if t.size > 1 else float("nan")
    band = (0.01, acceleration_band_top_hz(dt, gravimeter_step_s))
    try:
        fit = resp.fit_response_width(fbar_ms2, gnss_acceleration_ms2(t, vu), dt, band)
    except ValueError as exc:
        return {"estimated": False, "applied": False, "reason": str(exc)}
    info = {"estimated": True, "c_s2": fit.c_s2, "se_s2": fit.se_s2, "band_hz": [float(b) for b in band],
            "residual_reduction": fit.relative_improvement, "cost_zero": fit.cost_zero, "cost_min": fit.cost_min}
    why = []
    if not fit.c_s2 > p.response_min_z * fit.se_s2:
        why.append(f"not significant (c ≤ {p.response_min_z:g} × standard error {fit.se_s2:.2g} s²)")
    if not fit.relative_improvement >= p.response_min_improvement:
        why.append(f"removes only {100 * fit.relative_improvement:.1f} % of the residual "
                   f"(< {100 * p.response_min_improvement:g} %)")
    info.update(applied=not why, reason="; ".join(why) if why else "significant and improves the fit")
    return info


def choose_response_width(flights: dict, p) -> tuple[dict | None, list]:
    """One decision for the survey on matching the gravimeter's response (:func:`response_width`):
    the meter is the same on every flight, and a mixture of matched and unmatched z would be one
    noise model fitted to two shapes.  The flights' widths are pooled by their inverse variances
    and their residuals by their sums; the survey matches when the pooled width is significant
    and removes ``response_min_improvement`` of the pooled residual.  Returns the decision's
    evidence (None when no flight was fitted) and the flights whose own verdict differs (a flight
    too short to fit included), to be measured again with the survey's width (0 s² when it does
    not match)."""
    fits = {n: m.time_offset.get("response_width") for n, m in flights.items()}
    fits = {n: f for n, f in fits.items() if f and f.get("estimated")}
    if not fits:
        return None, []
    w = {n: 1.0 / f["se_s2"] ** 2 for n, f in fits.items() if np.isfinite(f["se_s2"]) and f["se_s2"] > 0}
    if w:
        c = float(sum(w[n] * fits[n]["c_s2"] for n in w) / sum(w.values()))
        se = float(1.0 / np.sqrt(sum(w.values())))
    else:
        c, se = 0.0, float("inf")
    c0 = sum(f["cost_zero"] for f in fits.values())
    reduction = float(sum(f["cost_zero"] - f["cost_min"] for f in fits.values()) / c0) if c0 > 0 else 0.0
    applied = bool(c > p.response_min_z * se and reduction >= p.response_min_improvement)
    rec = {"c_s2": c, "se_s2": se, "residual_reduction": reduction, "applied": applied, "flights": len(fits),
           "reason": (f"pooled over {len(fits)} flight(s): c = {c:.4f} ± {se:.1g} s², removing "
                      f"{100 * reduction:.1f} % of the residual"
                      + ("" if applied else f" — not matched (needs > {p.response_min_z:g} standard errors and "
                                            f"≥ {100 * p.response_min_improvement:g} %)"))}
    # every flight measured with a verdict, fitted or not (a record too short to fit has the same meter)
    again = [n for n, m in flights.items() if m.time_offset.get("response_width") is not None
             and bool(m.time_offset["response_width"].get("c_applied_s2", 0.0) > 0.0) != applied]
    return rec, again


def match_meter_response(fbar_ms2, t, vu, gravimeter_step_s: float, p, response_c_s2: float | None,
                         info: dict, notes: list) -> np.ndarray | None:
    """This flight's response width fitted (:func:`response_width`, into ``info['response_width']``
    with the width applied) and, when this flight's verdict — or the survey's ``response_c_s2``
    (s²) — matches it, what smoothing z's GNSS acceleration by it adds to z (mGal,
    :func:`matched_acceleration_change_mgal`); None when nothing is matched."""
    width = response_width(fbar_ms2, t, vu, gravimeter_step_s, p)
    c = (width["c_s2"] if width["applied"] else 0.0) if response_c_s2 is None else float(response_c_s2)
    width["c_applied_s2"] = c
    info["response_width"] = width
    if not c > 0.0:
        return None
    own = (f"this flight's fit {width['c_s2']:.4f} ± {width['se_s2']:.1g} s² at {width['band_hz'][0]:g}–"
           f"{width['band_hz'][1]:.2g} Hz removes {100 * width['residual_reduction']:.0f} % of the residual there"
           if width.get("estimated") else f"the survey's; this flight not fitted: {width['reason']}")
    notes.append(f"the gravimeter reads the aircraft's acceleration smoother than the GNSS does (a decimation or "
                 f"anti-alias filter survey.toml does not declare): the GNSS acceleration smoothed to match, "
                 f"exp(−c·ω²) with c = {c:.4f} s² ({own})")
    return matched_acceleration_change_mgal(t, vu, c, p.max_gap_s)


def matched_acceleration_change_mgal(t, vu, c_s2: float, max_gap_s: float) -> np.ndarray:
    """What z gains (mGal, per epoch) when its GNSS acceleration is smoothed by the response width
    ``c_s2`` (s²): :func:`app.core.response.matching_change` of the acceleration over the record's
    contiguous stretches (:func:`app.io.survey.gnss_runs`; no filter reaches across a gap)."""
    t = np.asarray(t, float)
    return resp.matching_change(gnss_acceleration_ms2(t, vu), t, c_s2, gnss_runs(t, max_gap_s)) * MGAL_PER_MS2


def check_acceleration_gain(flight, info: dict, notes: list) -> None:
    """The gravimeter and the GNSS see the same aircraft acceleration, m/s² for m/s²: the gain of
    the time-offset fit (:class:`app.core.gravimeter.TimeOffsetFit`) is 1 within ~12 % on clean
    surveys (a 2 Hz platform's response: 0.88).  Where the two correlate (> 0.5), a gain of
    0.3048 ± 8 % is GNSS heights in feet — with a vu in ft/s, or derived from them: no check of the
    GNSS file alone sees it, and normal gravity then moves 0.31 mGal per foot of height (+2100 mGal
    on the sample survey) — an ``InputError`` naming the GNSS file's ``h``, unless the low band's
    gain (``gain_low``, correlation > 0.5) is not about 0.3048 too (± 25 %): a lag declared wrong
    lowers the gain with frequency (τ 3 s declared 0: 0.29–0.32, and 0.93–0.97 below 0.05 Hz), feet
    at every frequency; the low band's gain alone within ± 8 % at correlation > 0.9 (0.997–1.002 on
    clean surveys, 0.304–0.308 in feet) is feet too, whatever the lag.  Any other gain outside
    :data:`PLAUSIBLE_GAIN` is a note (a unit of f_z, h or vu, or a response unlike survey.toml's)."""
    gain, corr = float(info.get("gain", np.nan)), float(info.get("correlation", np.nan))
    low, low_corr = float(info.get("gain_low", np.nan)), float(info.get("gain_low_correlation", np.nan))
    full = bool(np.isfinite(gain) and np.isfinite(corr) and corr > 0.5)
    low_differs = np.isfinite(low) and low_corr > 0.5 and abs(low / FEET_GAIN - 1.0) > 0.25
    low_feet = np.isfinite(low) and low_corr > 0.9 and abs(low / FEET_GAIN - 1.0) < FEET_GAIN_TOLERANCE
    what = (f"the gravimeter's vertical acceleration is {gain:.4g} × the GNSS's (correlation {corr:.3f}, "
            f"{info['band_hz'][0]:g}–{info['band_hz'][1]:.2g} Hz)") if "band_hz" in info else ""
    if low_feet or (full and abs(gain / FEET_GAIN - 1.0) < FEET_GAIN_TOLERANCE and not low_differs):
        low_txt = f"; {low:.3g} at {info['gain_low_band_hz'][0]:g}–{info['gain_low_band_hz'][1]:g} Hz" \
            if np.isfinite(low) and low_corr > 0.5 else ""
        raise InputError(f"flights/{flight.name}/{Path(flight.gnss_path).name}", None, "h",
                         f"{what}{low_txt}: 0.3048 m per foot — the GNSS heights look like feet (and vu like ft/s, "
                         "or derived from them); SPEC's GNSS file has h in metres (ellipsoidal) and vu in m/s (if "
                         "they are, the gravimeter's response is not survey.toml's: check f_z's unit and scale)")
    if full and not PLAUSIBLE_GAIN[0] <= gain <= PLAUSIBLE_GAIN[1]:
        notes.append(f"{what}, not 1: a unit of f_z, h or vu is not SPEC's, or the gravimeter's response is not "
                     "the one survey.toml declares (tau_s, scale); z holds the difference times the aircraft's "
                     "acceleration")


def mask_gaps(z, t, t_grav, margin_s: float, notes: list) -> None:
    """Leave z missing (in place) where its interval spans a GNSS gap or its gravimeter
    integral crosses a gravimeter record gap.

    An interval spanning a data gap is no measurement of anything; nor is one whose
    gravimeter integral crosses a gap of the gravimeter record: the spline bridges it, but
    ∫f over the gap is unknown and every z after it would carry the error (the lag
    inversion's derivative spreads it over ~τ: keep ``margin_s``)."""
    dt = np.diff(t)
    z[np.concatenate([[False], dt > 1.5 * np.median(dt)])] = np.nan
    gstep = np.diff(t_grav)
    gh = float(np.median(gstep))
    dropouts = []   # (start, end, epochs) of each gap of at most a minute: a dropout, not a pause
    for i in np.flatnonzero(gstep > 1.5 * gh):
        a = t_grav[i] - margin_s
        b = t_grav[i + 1] + margin_s
        hit = (t > a) & (np.concatenate([[t[0] - 1.0], t[:-1]]) < b)
        z[hit] = np.nan
        if t_grav[i + 1] - t_grav[i] <= 60.0 and hit.any():
            dropouts.append((float(t_grav[i]), float(t_grav[i + 1]), int(hit.sum())))
    notes.extend(_dropout_notes(dropouts))


#: Dropouts of one flight's gravimeter record named one by one; more are summed up in one note.
MAX_DROPOUT_NOTES = 5


def _dropout_notes(dropouts: list) -> list[str]:
    """The notes on the gravimeter record's dropouts (start, end in s; epochs of z lost): one
    per dropout up to :data:`MAX_DROPOUT_NOTES`, else one that sums them up (a logger dropping
    a sample a minute would otherwise fill the report with a line per hole)."""
    if len(dropouts) <= MAX_DROPOUT_NOTES:
        return [f"gravimeter record gap {a:.2f}–{b:.2f} s: {n} epochs of z left without measurement"
                for a, b, n in dropouts]
    spans = [b - a for a, b, _ in dropouts]
    lost = sum(n for _, _, n in dropouts)
    first = ", ".join(f"{a:.2f}–{b:.2f}" for a, b, _ in dropouts[:3])
    return [f"{len(dropouts)} gravimeter record gaps ({min(spans):.2f}–{max(spans):.2f} s long; {first} s, …): "
            f"{lost} epochs of z left without measurement in all"]


#: Largest lag (s) an in-flight τ estimate may give and still be taken for one (GT-1A: 2 s;
#: a negative or larger value is a failed fit, e.g. across a hole of the record).
MAX_TAU_S = 30.0

#: Epochs on either side of a filled GNSS epoch where the spike repair raises no flag (the
#: half-width of the height-outlier templates, app.core.measurement.height_outlier_mask).
FILL_GUARD = 16


def height_misfit(series: gm.IntegratedSeries, gnss: tuple, response: tuple) -> np.ndarray | None:
    """The gravimeter's double integral less the GNSS heights at the epochs (m), where a cycle
    slip is a step (:func:`app.core.measurement.gravimeter_height_misfit_m`); None for a
    gravimeter sampled slower than the GNSS, whose double integral between its samples is the
    spline's guess of the motion (z's own double integral is used there).  ``gnss``: (t, h,
    γ, E) at the epochs; ``response``: (τ, k, time offset) as for the interval means."""
    t, h, gamma, eot = gnss
    if t.size < 2 or series.step_s > 1.01 * float(np.median(np.diff(t))):
        return None
    tau, k, offset = response
    return gravimeter_height_misfit_m(t, gm.double_integral_m(series, t, tau, k, offset), h, gamma, eot)


def despike_z(z, t_s, p, notes: list, vu_from_heights: bool = False, filled=None, misfit_m=None):
    """Repair isolated spikes of z (:func:`app.core.measurement.spike_mask`); stand down when
    more than ``despike_max_fraction`` of the epochs would be flagged.  Where ``vu`` was
    derived from the heights the spline's response to a height spike or step is also looked
    for (:func:`app.core.measurement.height_outlier_mask`; a step also in the gravimeter's and
    z's double integrals, :func:`app.core.measurement.height_step_mask`, ``height_step_threshold``),
    and a flag is removed as one (:func:`app.core.measurement.repair_height_outliers`, a step
    sized from the double integral; the report lists each: epoch time
    in s, kind, size in m); otherwise each flagged run is replaced by its mean
    (:func:`app.core.measurement.repair_spikes`).  ``t_s``: the GNSS times (s).  ``filled``:
    the GNSS epochs put back on the clock (:func:`fill_gnss_epochs`); the spline that bridges
    them smooths the aircraft's motion there, which the detector can take for a height step
    (a 3.5 s fill on the 2 Hz test line: a 26 cm "step"), so no flag is raised within
    :data:`FILL_GUARD` epochs of them (``ignored_near_filled`` in the evidence).
    ``misfit_m``: the gravimeter's double integral less the heights (:func:`height_misfit`),
    where the step search looks instead of z's double integral.  Returns (z, evidence)."""
    t = np.asarray(t_s, float)
    dt_s = float(np.median(np.diff(t)))
    despike = {"threshold": p.despike_threshold, "flagged": 0, "epochs": int(np.isfinite(z).sum()),
               "applied": False, "repair": "height outliers" if vu_from_heights else "run mean"}
    if p.despike_threshold is None:
        return z, despike
    spikes = spike_mask(z, dt_s, p.despike_threshold)
    step_sizes = None
    if vu_from_heights:  # a height outlier rings through the spline: the matched patterns see it
        spikes |= height_outlier_mask(z, t, p.despike_threshold)
        if p.height_step_threshold is not None:   # and a step, clearest in z's double integral
            sizes = height_step_sizes_m(z, t, misfit_m=misfit_m)
            steps = height_step_mask(z, t, p.height_step_threshold, sizes_m=sizes)
            if misfit_m is not None:   # and where z's own double integral sees one (2 Hz test line: a
                steps |= height_step_mask(z, t, p.height_step_threshold)   # 0.1 m step only it saw)
            # a step the double integral sees is sized there (within an epoch of its flag). From
            # the gravimeter's own double integral always (sizes within ~1.5 cm); from z's only
            # where the templates do not flag too (at their flags on clean records z's double
            # integral's size is noise, ±0.2 m at 1 Hz), else the templates size it as before
            alone = steps if misfit_m is not None else (
                steps & ~(np.convolve(spikes.astype(float), np.ones(5), mode="same") > 0.5))
            at_step = np.convolve(alone.astype(float), np.ones(3), mode="same") > 0.5
            if at_step.any():
                step_sizes = np.where(at_step, sizes, np.nan)
            spikes |= steps
    if filled is not None and np.any(filled):
        near = np.convolve(np.asarray(filled, float), np.ones(2 * FILL_GUARD + 1), mode="same") > 0.5
        despike["ignored_near_filled"] = int(np.sum(spikes & near))
        spikes &= ~near
    n_flag = int(spikes.sum())
    frac = n_flag / max(1, despike["epochs"])
    despike.update(flagged=n_flag, fraction=frac)
    if n_flag and frac > p.despike_max_fraction:
        # spikes are rare by nature: this many flags means the noise is not what the
        # detector assumes (a heavy-tailed or rough record); repairing would destroy data
        despike["reason"] = "stood down: too many flags"
        notes.append(f"spike repair stood down: {n_flag} of {despike['epochs']} epochs ({100 * frac:.2f} %) "
                     f"would be flagged, more than {100 * p.despike_max_fraction:g} % — z left as measured")
    elif n_flag and vu_from_heights:
        z, fixes = repair_height_outliers(z, t, spikes, step_sizes_m=step_sizes)
        despike["applied"] = True
        despike["height_outliers"] = [{"time": float(t[f["epoch"]]), "kind": f["kind"], "size_m": f["size_m"]}
                                      for f in fixes]
        kinds = [f["kind"] for f in fixes if f["kind"]]
        notes.append(f"{n_flag} epochs of z ({100 * frac:.3f} %) flagged as spikes (> {p.despike_threshold:g} local "
                     f"robust std from the neighbours' mean); vu comes from the heights, so they were removed as "
                     f"{kinds.count('spike')} height spike(s) and {kinds.count('step')} height step(s) "
                     f"(report spike_repair.height_outliers)")
    elif n_flag:
        z = repair_spikes(z, spikes)
        despike["applied"] = True
        notes.append(f"{n_flag} epochs of z ({100 * frac:.3f} %) repaired as spikes "
                     f"(> {p.despike_threshold:g} local robust std from the neighbours' mean)")
    return z, despike


def acceleration_band_top_hz(dt_s: float, gravimeter_step_s: float | None = None) -> float:
    """Highest frequency (Hz) at which the GNSS-derived vertical acceleration is compared with
    the gravimeter's (time offset, lag check): a fifth of the GNSS rate, two fifths of the
    gravimeter's (its median step ``gravimeter_step_s``; 80 % of its Nyquist frequency), at
    most 1 Hz.  Above it a 1–2 Hz receiver's (or differenced heights') acceleration no longer
    follows the aircraft's (aliasing, interpolation), and fitting it biased the lag of a 1 Hz
    heights-only survey by 0.35 s.  Nor does a 1–2 Hz gravimeter's: its samples, put back on
    10 Hz GNSS epochs through the spline of their integral, lack the aircraft's acceleration
    near and above their Nyquist frequency, and that mismatch ruled the comparison.  Generated
    surveys (benchmarks/foreign_sim.py, 1 Hz interval means on 10 Hz GNSS, a 0.04–0.21 s lag
    nobody declared): up to 1 Hz the offset's correlation was 0.48–0.99, its fit removed
    0.7–5 % of the residual and one flight of three kept its lag (left unapplied), the
    estimate 2.7x and 1.55x FIR's error; up to 0.4 Hz every flight's offset lies within
    0.015 s of the lag (correlation 0.76–0.999, 4–15 % removed) and the estimate is 0.69x and
    0.82x FIR's.  Up to 0.2 Hz the offsets of a 2 Hz heights-only survey scattered by ±0.07 s."""
    top = min(1.0, 0.2 / dt_s)
    if gravimeter_step_s is not None and np.isfinite(gravimeter_step_s) and gravimeter_step_s > 0:
        top = min(top, 0.4 / gravimeter_step_s)
    return float(top)


def _running_mean(x, n: int) -> np.ndarray:
    """Centred running mean over ``n`` samples (NaN ignored; NaN where a window has none)."""
    x = np.asarray(x, float)
    ok = np.isfinite(x)
    c = np.concatenate([[0.0], np.cumsum(np.where(ok, x, 0.0))])
    k = np.concatenate([[0], np.cumsum(ok)])
    i = np.arange(x.size)
    lo, hi = np.clip(i - n // 2, 0, x.size), np.clip(i - n // 2 + n, 0, x.size)
    cnt = k[hi] - k[lo]
    return np.where(cnt > 0, (c[hi] - c[lo]) / np.maximum(cnt, 1), np.nan)


def static_segments(t_s, ve_ms, vn_ms, vu_ms, min_duration_s: float = 60.0, max_speed_ms: float = 0.5,
                    trim_s: float = 10.0, smooth_s: float = 5.0) -> list[tuple[int, int]]:
    """Index ranges ``[i0, i1)`` where the aircraft stands still (parking place readings).

    A GNSS epoch is static when its horizontal and vertical speeds, averaged over
    ``smooth_s`` (s) around it, are below ``max_speed_ms``; runs shorter than
    ``min_duration_s`` are ignored and ``trim_s`` is cut from both ends of each run
    (taxi start/stop).  The average is what makes parking visible in velocities
    differenced from positions: 2 cm of position noise at 20 Hz gives 0.6 m/s of
    velocity noise per epoch (no epoch below 0.5 m/s for long), but 0.006 m/s over 5 s —
    a heights-only flight at 20 Hz lost its base tie and kept a 199 mGal reading error."""
    t = np.asarray(t_s, float)
    dt = float(np.nanmedian(np.diff(t))) if t.size > 1 else 1.0
    n = max(1, int(round(smooth_s / dt))) if dt > 0 else 1
    ve, vn, vu = (_running_mean(v, n) for v in (ve_ms, vn_ms, vu_ms))
    with np.errstate(invalid="ignore"):
        still = (np.hypot(ve, vn) < max_speed_ms) & (np.abs(vu) < max_speed_ms)
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


def line_windows(lines, flight: str) -> np.ndarray | None:
    """The ``(t_start, t_end)`` windows (s) of one flight's lines in ``lines.csv``'s table,
    shape (n_lines, 2); None without a line table."""
    if lines is None or not len(lines):
        return None
    return lines.loc[lines["flight"] == flight, ["t_start", "t_end"]].to_numpy(float)


def judged_epochs(t_s, ve_ms, vn_ms, windows=None, min_speed_ms: float = 20.0) -> np.ndarray:
    """The epochs the in-flight checks judge, shape (n,) bool: inside the lines' ``windows`` (s,
    shape (n_lines, 2); none when it is empty) when given, else (None) the airborne ones (faster
    than ``min_speed_ms`` horizontally)."""
    t = np.asarray(t_s, dtype=float)
    if windows is None:
        return np.hypot(ve_ms, vn_ms) > min_speed_ms
    out = np.zeros(t.size, bool)
    for a, b in np.asarray(windows, float):
        out |= (t >= a) & (t <= b)
    return out


def airborne(m: FlightMeasurement, min_speed_ms: float = 20.0) -> np.ndarray:
    """Epochs of a measured flight moving faster than ``min_speed_ms`` horizontally (m/s): the
    airborne part the in-flight lag checks use, shape (n,) bool."""
    return np.hypot(m.ve_ms, m.vn_ms) > min_speed_ms


def calibrate_gravimeter(flight, cfg: SurveyConfig, max_duration_s: float = 3600.0,
                         params: tuple = ("tau", "k"), measured: FlightMeasurement | None = None) -> dict:
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
    m = measure_flight(flight, cfg, compensation=False, match_response=False) if measured is None else measured
    t = m.t_s
    dt = float(np.median(np.diff(t)))
    moving = airborne(m)
    # z is left missing where the gravimeter's integral crosses a hole of its record: fbar there
    # is the spline's bridge, not a measurement (one such hole made τ −7685 s)
    ok = moving & np.isfinite(m.fbar_ms2) & np.isfinite(m.z_mgal)
    steps_ok = np.concatenate([[False], np.abs(np.diff(t) - dt) < 0.01 * dt])
    good = ok & steps_ok
    d = np.diff(np.concatenate([[0], good.astype(int), [0]]))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    if starts.size == 0:
        raise ValueError(f"flight {flight.name}: no airborne segment to calibrate on")
    k = int(np.argmax(stops - starts))
    a, b = int(starts[k]), int(stops[k])
    b = min(b, a + int(max_duration_s / dt))
    # the record as z was formed from it (the clock re-timed as the measurement decided)
    rec = gravimeter_record(flight.gravimeter, cfg.processing, [])
    retimed = clock_retimed(rec, m.time_offset.get("clock"))
    series = (rec if retimed is None else gravimeter_record(retimed, cfg.processing, [])).series
    off = m.time_offset_s if m.time_offset_applied else 0.0
    seg = slice(a - 1, b) if a > 0 else slice(a, b)
    tt = t[seg]
    # as z was formed: over the heights' spline runs where vu came from the heights (the
    # segment's own spline would differ from theirs at its ends)
    runs = height_runs(series, t, m.heights_only, cfg.processing)
    fraw = gm.gnss_side_means(series, t, 0.0, 1.0, off, runs)[seg]
    fdot = gm.gnss_side_means(series, t, 1.0, 1.0, off, runs)[seg] - fraw
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
                    fmax_hz=acceleration_band_top_hz(dt, series.step_s))
    names = list(res.names)
    return {"flight": flight.name, "t_start": float(tt[1]), "t_end": float(tt[-1]),
            "tau_s": float(res.tau_s), "k": float(res.k),
            "std": {n: float(v) for n, v in zip(names, np.asarray(res.std))},
            "chi2_per_dof": float(getattr(res, "chi2_per_dof", np.nan)),
            "time_offset_s": float(off), "time_offset_applied": bool(m.time_offset_applied)}


@dataclass
class Measurement:
    """Result of :func:`measure`.

    Attributes
    ----------
    flights : dict of FlightMeasurement
    base_ties : dict
        Per flight: what :func:`base_tie` did (periods, drift, absolute or not).
    lag_check, calibration : dict or None
        The in-flight lag check / calibration and its decision.
    warnings : list of str
    dt_s : float
        Median GNSS step (s).
    band_delay : dict or None
        :func:`check_band_delay`'s fit and decision (None when off).
    response_width : dict or None
        :func:`choose_response_width`'s pooled fit and decision (None when no flight was fitted).
    """

    flights: dict
    base_ties: dict
    lag_check: dict | None
    calibration: dict | None
    warnings: list
    dt_s: float
    band_delay: dict | None = None
    response_width: dict | None = None


def check_lag(survey, cfg: SurveyConfig, warnings: list) -> tuple[float | None, dict | None]:
    """The declared lag τ checked in flight (seed 001 calibration, τ only, first three flights).

    A wrong τ leaves (τ_true − τ)·ḟ of the aircraft's jerk in z, thousands of mGal.  The
    median estimate is used only when every flight agrees within ``lag_check_s``, it
    differs from survey.toml's by more than that, and it lowers z's RMS where the estimate
    is made (:func:`lag_band_check`).  A difference between ``lag_check_min_change_s`` and
    ``lag_check_s`` is used only when that band check runs and confirms it: a 0.06 s error
    of the declared GT-1A lag (2.07 s against 2.009) was estimated as 2.022 s, 0.048 s from
    the declared value — below the old threshold, and kept; z's RMS at 0.02–0.05 Hz was
    189 mGal with it and 75 with the estimate, the noise fit's level 8× too high.  Returns
    (τ to use or None, evidence)."""
    p = cfg.processing
    taus, names, offsets, fitted = [], [], [], []
    declared = {}        # each checked flight measured once with survey.toml's τ, for every check below
    def measured_and_fitted(name):
        try:
            m = measure_flight(survey.flights[name], cfg, compensation=False, match_response=False)
        except (ValueError, np.linalg.LinAlgError):
            return None, None
        try:
            return m, calibrate_gravimeter(survey.flights[name], cfg, params=("tau",), measured=m)
        except (ValueError, np.linalg.LinAlgError):
            return m, None

    checked = sorted(survey.flights)[:3]
    for name, (m, cal) in zip(checked, each_flight(measured_and_fitted, checked)):
        if m is not None:
            declared[name] = m
        if cal is None:
            continue
        fitted.append(name)
        offsets.append(cal["time_offset_s"] if cal["time_offset_applied"] else 0.0)
        tau = cal["tau_s"]
        if np.isfinite(tau) and 0.0 <= tau <= MAX_TAU_S:   # else no lag: the fit failed
            taus.append(tau)
            names.append(name)
    tau_lag, info_lag = offset_as_lag(survey, cfg, fitted, offsets, declared)
    if tau_lag is not None and info_lag is not None:
        warnings.append(f"gravimeter lag: survey.toml says τ = {cfg.gravimeter.tau_s:g} s; the flights' gravimeter "
                        f"lags the GNSS by {tau_lag - cfg.gravimeter.tau_s:.3f} s more, and as a lag (not a shift "
                        f"of the time stamps) it leaves z quieter: using τ = {tau_lag:.3f} s")
        return tau_lag, info_lag
    info_one = None
    if info_lag is None:
        offset_of = dict(zip(fitted, offsets))
        tau_one, info_one = lag_on_one_scale(survey, cfg, names, taus, [offset_of[n] for n in names], declared)
        if tau_one is not None and info_one is not None:
            warnings.append(f"gravimeter lag: survey.toml says τ = {cfg.gravimeter.tau_s:g} s; the flights say "
                            f"{tau_one:.3f} s once each one's time offset is counted as the lag it took up "
                            f"({info_one['reason']}): using τ = {tau_one:.3f} s")
            return tau_one, info_one
    tau_band, info_band = band_lag(survey, cfg, fitted, declared)
    if tau_band is not None:
        info_band.update({"estimated_tau_s": taus, "offset_as_lag": info_lag} if info_lag is not None
                         else {"estimated_tau_s": taus})
        if info_one is not None:
            info_band["one_scale"] = info_one    # tried and refused: the evidence
        warnings.append(f"gravimeter lag: survey.toml says τ = {cfg.gravimeter.tau_s:g} s; in the band where the "
                        f"anomaly is estimated the flights say {tau_band:.3f} s ({info_band['reason']}): using "
                        f"{tau_band:.3f} s")
        return tau_band, info_band
    if not taus:
        if info_lag is None and info_band is None:
            return None, None
        info = {"declared_tau_s": cfg.gravimeter.tau_s, "estimated_tau_s": [], "applied": False}
        info.update({k: v for k, v in (("offset_as_lag", info_lag), ("band_fit", info_band)) if v is not None})
        return None, info
    tau_est = float(np.median(taus))
    change = abs(tau_est - cfg.gravimeter.tau_s)
    small = change <= p.lag_check_s     # confirmed by the band check, or not used
    applied = change > min(p.lag_check_min_change_s, p.lag_check_s) and float(np.ptp(taus)) < p.lag_check_s
    info = {"declared_tau_s": cfg.gravimeter.tau_s, "estimated_tau_s": taus, "applied": applied}
    if info_band is not None:
        info["band_fit"] = info_band           # tried and refused: the evidence
    if info_lag is not None:
        info["offset_as_lag"] = info_lag       # tried and refused: the evidence
    if info_one is not None:
        info["one_scale"] = info_one           # tried and refused: the evidence
    if applied:
        info.update(lag_band_check([survey.flights[n] for n in names], cfg, tau_est, [declared[n] for n in names]))
        gain = info["band_rms_improvement"]
        if not np.isfinite(gain) and small:
            applied = info["applied"] = False
            info["reason"] = (f"the in-flight τ {tau_est:.3f} s is within {p.lag_check_s:g} s of survey.toml's and "
                              "the band check could not confirm it (no airborne stretch of 300 s): survey.toml's τ kept")
        elif not np.isfinite(gain):  # no airborne stretch long enough to compare: as before the check
            info["reason"] = "the band check could not run (no airborne stretch of 300 s); the in-flight τ used"
        elif gain < p.lag_check_min_improvement and gain > 0 and _band_confirms(info_band, tau_est, p):
            info["reason"] = (f"the in-flight τ {tau_est:.3f} s lowers z's RMS at {info['band_hz'][0]:g}–"
                              f"{info['band_hz'][1]:g} Hz by {100 * gain:.1f} % only, but the band fit agrees "
                              f"(Δτ {info_band['iterations'][0]['dtau_s']:+.4f} ± "
                              f"{info_band['iterations'][0]['se_s']:.4f} s): the in-flight τ used")
        elif gain < p.lag_check_min_improvement:
            applied = info["applied"] = False
            info["reason"] = (f"the in-flight τ {tau_est:.3f} s changes z's RMS at {info['band_hz'][0]:g}–"
                              f"{info['band_hz'][1]:g} Hz by {-100 * gain:+.1f} % (needs "
                              f"−{100 * p.lag_check_min_improvement:g} %): survey.toml's τ kept")
    if not applied:
        return None, info
    warnings.append(f"gravimeter lag: survey.toml says τ = {cfg.gravimeter.tau_s:g} s, the flights say "
                    f"{tau_est:.3f} s (estimates {', '.join(f'{v:.3f}' for v in taus)}); using {tau_est:.3f} s")
    return tau_est, info


#: a lag search (:func:`lag_band_search`) replaces the check's τ only when it lowers z's band RMS by this share
LAG_SEARCH_MIN_IMPROVEMENT = 0.05
#: times the search interval is moved on past an edge its minimum lands on
LAG_SEARCH_MAX_WIDENINGS = 4


def check_lag_with_search(survey, cfg: SurveyConfig, warnings: list) -> tuple[float | None, dict | None]:
    """:func:`check_lag`, and where it moved τ, the τ that minimises z's band RMS near it
    (:func:`lag_band_search`), used when that RMS is lower by :data:`LAG_SEARCH_MIN_IMPROVEMENT`.

    The in-flight fits are linear about the τ they start from, and the time-offset fit takes up
    part of a lag as a shift: a lag far from the declared one is found only in part.  τ declared
    0 on the sample survey (a GT-1A, τ 2 s) gave 1.433 s, z's band RMS 535 → 198 mGal (28.5 at
    2.0 s), a 0.42 s band delay left for stage 1 to take out of z, and 5.48 mGal against 3.30.
    The band RMS — the figure every lag check is judged by — has a sharp minimum at the lag.
    Returns (τ to use or None, evidence: the check's, with the search under ``band_search``)."""
    tau, info = check_lag(survey, cfg, warnings)
    if tau is None or info is None:
        return tau, info
    search = lag_band_search(survey, cfg, float(tau), cfg.gravimeter.tau_s)
    if search is None:
        return tau, info
    info = {**info, "band_search": search}
    if search["applied"]:
        warnings.append(f"gravimeter lag: z's RMS at {search['band_hz'][0]:g}–{search['band_hz'][1]:g} Hz is least at "
                        f"τ = {search['tau_s']:.3f} s ({search['band_rms_mgal']:.1f} mGal, against "
                        f"{search['band_rms_check_mgal']:.1f} at the check's {tau:.3f} s): using τ = "
                        f"{search['tau_s']:.3f} s")
        return search["tau_s"], info
    return tau, info


def lag_band_search(survey, cfg: SurveyConfig, tau_check_s: float, tau_declared_s: float) -> dict | None:
    """The τ (s) in ``[τ_c − w, τ_c + w]`` (``w = max(0.5, 2·|τ_c − τ_declared|)``, within
    0–``MAX_TAU_S``; moved on by ``w`` past an edge the minimum lands on, at most
    :data:`LAG_SEARCH_MAX_WIDENINGS` times) that minimises z's RMS at 2–5 × 1/``fir_cutoff_period_s`` Hz over the
    airborne stretches of the first three flights, pooled by their epochs (bounded Brent,
    to 5 ms; each flight measured with its time offset re-estimated at every τ, as in
    :func:`lag_band_check`).  ``applied`` when it is below the RMS at ``tau_check_s`` by
    :data:`LAG_SEARCH_MIN_IMPROVEMENT`.  None when no flight gives the band."""
    p = cfg.processing
    band = (2.0 / p.fir_cutoff_period_s, 5.0 / p.fir_cutoff_period_s)
    flights = [survey.flights[n] for n in sorted(survey.flights)[:3]]
    cache: dict[float, float] = {}

    def rms(tau: float) -> float:
        if tau not in cache:
            def power(flight):
                try:
                    m = measure_flight(flight, cfg, tau_s=float(tau), compensation=False, match_response=False)
                except (ValueError, np.linalg.LinAlgError):
                    return None
                return band_power(m, band, airborne(m) & np.isfinite(m.z_mgal))

            ss, n_tot = 0.0, 0
            for got in each_flight(power, flights):
                if got is not None:
                    ss, n_tot = ss + got[0], n_tot + got[1]
            cache[tau] = float(np.sqrt(ss / n_tot)) if n_tot else float("nan")
        return cache[tau]

    r_check = rms(tau_check_s)
    if not np.isfinite(r_check):
        return None
    w = max(0.5, 2.0 * abs(tau_check_s - tau_declared_s))
    lo, hi = max(0.0, tau_check_s - w), min(MAX_TAU_S, tau_check_s + w)
    for _ in range(LAG_SEARCH_MAX_WIDENINGS + 1):
        res = minimize_scalar(lambda x: rms(float(x)) if np.isfinite(rms(float(x))) else np.inf,
                              bounds=(lo, hi), method="bounded", options={"xatol": 0.005})
        tau_best = float(res.x)
        # a minimum at an edge of the interval (the check found a far lag only in part): look beyond it
        if tau_best > hi - 0.02 and hi < MAX_TAU_S:
            lo, hi = tau_best - 0.02, min(MAX_TAU_S, tau_best + w)
        elif tau_best < lo + 0.02 and lo > 0.0:
            lo, hi = max(0.0, tau_best - w), tau_best + 0.02
        else:
            break
    r_best = rms(tau_best)
    applied = bool(np.isfinite(r_best) and r_best < (1.0 - LAG_SEARCH_MIN_IMPROVEMENT) * r_check)
    return {"band_hz": list(band), "interval_s": [lo, hi], "tau_s": tau_best, "band_rms_mgal": r_best,
            "band_rms_check_mgal": r_check, "evaluations": len(cache), "applied": applied}


def _band_check_passes(check: dict, p, min_improvement: float | None = None) -> bool:
    """Does a τ's band check (:func:`lag_band_check`) lower z's band RMS by ``min_improvement``
    (a share; default ``lag_check_min_improvement``)?"""
    gain = check["band_rms_improvement"]
    need = p.lag_check_min_improvement if min_improvement is None else min_improvement
    return bool(np.isfinite(gain) and gain >= need)


def _band_confirms(info_band: dict | None, tau_est: float, p) -> bool:
    """Does the band fit's first estimate confirm the wideband τ: ``lag_band_confirm_z`` standard
    errors from survey.toml's τ, the same way, and within two standard errors of the wideband τ?

    A lag error of 0.02–0.04 s (a GT-1A's declared τ a little off) moves z's band RMS by less
    than 1 % — the GNSS noise rules the band — yet its jerk above the band raises the noise
    fit's level: generated 9 (declared 1.59 s, true 1.5695, wideband 1.568, band RMS −0.7 %)
    2.98 → 2.33 mGal with the true τ, 30 (1.72 / 1.6826 / 1.677, −0.8 %) 2.39 → 2.27.  The band
    fit alone is too imprecise there to be used (3.7 and 3.3 standard errors), but two
    estimates from different bands that agree are.  The wideband τ's false moves did not
    pass: generated 32 (true and declared 0, wideband 0.039 s, band 1.8 standard errors), 55
    (0.020 against the band's 0.007 ± 0.004), layout 195 (2.0 / 1.957, band 2.5)."""
    if not info_band or not info_band.get("iterations"):
        return False
    first = info_band["iterations"][0]
    d, se = first.get("dtau_s", np.nan), first.get("se_s", np.nan)
    if not (np.isfinite(d) and np.isfinite(se) and se > 0):
        return False
    tau0 = info_band["declared_tau_s"]
    return (abs(d) >= p.lag_band_confirm_z * se and np.sign(d) == np.sign(tau_est - tau0)
            and abs(tau_est - (tau0 + d)) <= 2.0 * se)


def _pooled_band_fit(measured: list, band: tuple) -> dict:
    """The flights' band fits of z on ∂z/∂τ (:func:`app.core.noise_level.band_fit_coefficient`,
    airborne epochs) pooled by inverse variance: Δτ (s), its standard error, z's band RMS
    before and after (mGal, pooled by epochs) and each flight's own fit."""
    w = wc = ss0 = ss1 = 0.0
    n_tot = 0
    per = {}
    for m in measured:
        dt = float(np.median(np.diff(m.t_s)))
        if m.dz_dtau_mgal_s is None or not band[1] < 0.5 / dt:
            continue
        f = band_fit_coefficient(m.z_mgal, m.dz_dtau_mgal_s, dt, band, usable=airborne(m))
        if not (np.isfinite(f.coef) and f.se > 0):
            continue
        per[m.flight] = {"dtau_s": f.coef, "se_s": f.se, "dof": f.dof}
        w += 1.0 / f.se ** 2
        wc += f.coef / f.se ** 2
        ss0 += f.rms_before_mgal ** 2 * f.n_epochs
        ss1 += f.rms_after_mgal ** 2 * f.n_epochs
        n_tot += f.n_epochs
    if not w:
        return {"dtau_s": float("nan"), "se_s": float("nan"), "n_epochs": 0, "flights": per}
    return {"dtau_s": wc / w, "se_s": float(w ** -0.5), "rms_before_mgal": float(np.sqrt(ss0 / n_tot)),
            "rms_after_mgal": float(np.sqrt(ss1 / n_tot)), "n_epochs": n_tot, "flights": per}


def band_lag(survey, cfg: SurveyConfig, names: list, declared: dict,
             max_iterations: int = 5) -> tuple[float | None, dict | None]:
    """τ fitted where the anomaly is estimated: the lag whose z holds the least of the
    gravimeter's jerk in the band just above FIR's cutoff (2–5 × 1/``fir_cutoff_period_s`` Hz).

    z is linear in τ at a fixed time offset (``∂z/∂τ`` = the gravimeter's jerk on the GNSS
    intervals), so the band's least-squares τ is one regression per flight
    (:func:`app.core.noise_level.band_fit_coefficient`), pooled over the checked flights.  The
    time offset is fitted after τ (0.01 Hz up to the GNSS band's top) and takes up part of a lag
    error, so the fit is repeated with each new τ (the flights measured again, their offsets
    re-fitted) until its change is within one standard error (at most ``max_iterations``).  The wideband τ
    fit of :func:`calibrate_gravimeter` weighs the response above 0.1 Hz, where the records
    (interval means, heights differenced twice) differ from a first-order lag, and the offset
    with it: on a generated GT-1A survey (declared 2.07 s, true 2.009 s, a 35 s phugoid of 0.2
    m/s²) it gave 2.022 s, and z's RMS at 0.02–0.05 Hz stayed 75 mGal — its estimate 1.31×
    FIR's error; the band fit gave 2.0087 s (51 mGal, the GNSS's own noise there).
    Used when the first fit is ``lag_band_fit_z`` standard errors from survey.toml's τ, the result
    lies in 0–``MAX_TAU_S``, and z's band RMS (re-measured, :func:`lag_band_check`) is lower by
    ``lag_check_min_improvement``.  The fit runs over the airborne epochs: the turns' manoeuvres
    make it 2–6× more precise than the lines alone, and closer to the true τ on generated
    surveys (33: 2.0065 against the lines' 2.0100, true 2.0039), but they also carry a small
    generated layout's bias (167: true and declared 2.0 s, 2.059 at 3.8 standard errors, its
    error 5.59 → 5.95 mGal) — hence 5 standard errors, not 3.  Returns
    (τ or None, evidence or None when not tried)."""
    p = cfg.processing
    if not p.lag_band_fit or not names:
        return None, None
    band = (2.0 / p.fir_cutoff_period_s, 5.0 / p.fir_cutoff_period_s)
    tau0 = cfg.gravimeter.tau_s
    fit = _pooled_band_fit([declared[n] for n in names], band)
    info = {"declared_tau_s": tau0, "band_hz": list(band), "iterations": [{"tau_s": tau0, **fit}],
            "applied": False, "from_band_fit": True}
    if not fit["n_epochs"]:
        info["reason"] = "no airborne stretch long enough for the band fit"
        return None, info
    if not abs(fit["dtau_s"]) > p.lag_band_fit_z * fit["se_s"]:
        info["reason"] = (f"survey.toml's τ fits the band: Δτ {fit['dtau_s']:+.4f} s within "
                          f"{p.lag_band_fit_z:g} standard errors ({fit['se_s']:.4f} s)")
        return None, info
    tau = tau0
    for _ in range(max_iterations):
        tau = tau + fit["dtau_s"]
        if not 0.0 <= tau <= MAX_TAU_S:
            info["reason"] = f"the band fit leaves the lag's range (τ = {tau:.3f} s)"
            return None, info
        try:
            measured = each_flight(lambda n, t=tau: measure_flight(survey.flights[n], cfg, tau_s=t, compensation=False,
                                                                   match_response=False),
                                   names)
        except (ValueError, np.linalg.LinAlgError) as exc:
            info["reason"] = f"a flight could not be measured at τ = {tau:.3f} s: {exc}"
            return None, info
        fit = _pooled_band_fit(measured, band)
        info["iterations"].append({"tau_s": tau, **fit})
        if not fit["n_epochs"] or abs(fit["dtau_s"]) <= fit["se_s"]:
            break
    info["band_fit_tau_s"] = tau
    check = lag_band_check([survey.flights[n] for n in names], cfg, tau, [declared[n] for n in names], measured)
    info.update(check)
    gain = check["band_rms_improvement"]
    if not _band_check_passes(check, p):
        info["reason"] = (f"the band-fitted τ {tau:.4f} s changes z's RMS at {band[0]:g}–{band[1]:g} Hz by "
                          f"{-100 * gain:+.1f} % (needs −{100 * p.lag_check_min_improvement:g} %): survey.toml's "
                          "τ kept")
        return None, info
    info["applied"] = True
    info["reason"] = (f"Δτ {tau - tau0:+.4f} s, {abs(info['iterations'][0]['dtau_s']) / info['iterations'][0]['se_s']:.0f}"
                      f" standard errors at the first fit; z's RMS at {band[0]:g}–{band[1]:g} Hz "
                      f"{check['band_rms_declared_mgal']:.1f} → {check['band_rms_estimated_mgal']:.1f} mGal")
    return tau, info


def offset_as_lag(survey, cfg: SurveyConfig, names: list, offsets: list,
                  declared: dict | None = None) -> tuple[float | None, dict | None]:
    """The flights' time offsets read as an undeclared lag: ``τ + median(−offset)`` (s) and the
    evidence, or ``(None, None)`` when that does not leave z quieter.

    A first-order lag τ delays the gravimeter by about τ where the time offset is fitted (below
    0.2·f_GNSS), so the offset fit takes an undeclared lag for a shift of the stamps and the
    τ-only calibration, fitted after it, finds nothing left.  But a shift is not a lag: above
    the fitted band a lag also damps (at 0.6 Hz a 0.1 s lag passes 94 % of the aircraft's
    acceleration and delays it 0.095 s, not 0.1), and that mismatch, 1–2·10³ mGal of heavy
    turbulence, is averaged on the GNSS intervals and folded into the anomaly band.  A
    generated survey with a 10 Hz platform meter's 0.098 s undeclared lag on 1 Hz GNSS got
    offsets of −0.083 to −0.088 s; declared as a lag its estimate's error went 4.51 → 2.58 mGal
    (FIR's 4.38 → 2.75).  Tried when every one of the flights (``names``, the first three)
    has an applied offset of −0.02 to −0.5 s (the gravimeter late) and they agree within
    ``lag_check_s``; used when the lag check's band test (:func:`lag_band_check`) finds z's
    RMS lowered by ``lag_check_min_improvement`` — a real shift of the stamps (a logger's
    latency) is left as an offset, since as a lag it would damp the acceleration wrongly.
    Not tried where a flight's gravimeter is slower than its GNSS (:func:`_slow_gravimeter`).  Only with ``lag_from_time_offsets`` (on by default
    since the repeat passes size a track's std only where their smoothing part is
    significant: on the 4-pass test line the lag it finds, right as it is, had let them narrow
    the std below the error they share)."""
    p = cfg.processing
    if not p.lag_from_time_offsets or p.lag_check_s is None or not offsets or len(offsets) != len(names):
        return None, None
    late = [-o for o in offsets]
    if not all(p.lag_check_min_change_s <= x <= 0.5 for x in late) or float(np.ptp(late)) > p.lag_check_s:
        return None, None
    if any(_slow_gravimeter(survey.flights[n], p.slow_gravimeter_min_ratio) for n in names):
        return None, None
    tau_c = cfg.gravimeter.tau_s + float(np.median(late))
    check = lag_band_check([survey.flights[n] for n in names], cfg, tau_c,
                           [declared[n] for n in names] if declared else None)
    info = {"declared_tau_s": cfg.gravimeter.tau_s, "estimated_tau_s": [cfg.gravimeter.tau_s + x for x in late],
            "from_time_offsets": True, **check}
    gain = check["band_rms_improvement"]
    if not _band_check_passes(check, p):
        info["applied"] = False
        info["reason"] = (f"the flights' time offsets read as a lag (τ = {tau_c:.3f} s) change z's RMS at "
                          f"{check['band_hz'][0]:g}–{check['band_hz'][1]:g} Hz by {-100 * gain:+.1f} %: kept as "
                          "offsets")
        return None, info
    info["applied"] = True
    info["reason"] = (f"the flights' time offsets ({', '.join(f'{-x:+.3f}' for x in late)} s) read as a lag: "
                      f"τ = {tau_c:.3f} s lowers z's RMS at {check['band_hz'][0]:g}–{check['band_hz'][1]:g} Hz by "
                      f"{100 * gain:.1f} %")
    return tau_c, info


def lag_on_one_scale(survey, cfg: SurveyConfig, names: list, taus: list, offsets: list,
                     declared: dict) -> tuple[float | None, dict | None]:
    """The flights' lags on one scale: each flight's τ fit minus the time offset applied before
    it, ``τ_i − offset_i`` (s), and the evidence; ``(None, None)`` when not tried.

    Measured at survey.toml's τ, a flight's time offset fit can take an undeclared lag for a
    shift of the stamps (``offset ≈ −lag``); the τ-only fit after it then finds little left.
    Another flight's offset, not significant or not helpful enough, is not applied, and its τ
    fit finds the lag itself.  Compared as they come the flights disagree, and neither
    :func:`offset_as_lag` (every offset applied) nor the median of the τ fits (the flights
    agree) runs, while the band fit pooled them half-way: generated survey 237 (1 Hz interval
    means, 0.261 s undeclared) had offsets −0.246, −0.245 s applied and τ fits 0.006, 0.011 s
    on two flights, no offset and 0.269 s on the third; the band fit stopped at 0.225 s and
    the estimate was 1.36× FIR's error (0.61× with the true τ).  On one scale they agree
    (0.252, 0.255, 0.269 s), and their median 0.255 s took the estimate to 0.56× FIR's error.
    Tried (``lag_one_scale``) when some flight's offset was applied and :func:`offset_as_lag`
    did not run (also where the gravimeter is slower than its GNSS, which that path leaves
    out); the lags must agree within ``lag_check_s``, differ from survey.toml's τ by more than
    it and lie in 0–``MAX_TAU_S``; used when the band check (:func:`lag_band_check`) lowers
    z's band RMS by ``lag_one_scale_min_improvement`` (5 %, not the 1 % of the other lag
    checks: over generated surveys 1–262 this path would change τ on 16, within 0.016 s of
    the true lag on all; the two whose band RMS fell by only 2.3 and 2.8 % lost accuracy,
    2.64 → 3.64 and 5.05 → 5.40 mGal — 1 and 2 Hz meters on 2 and 5 Hz GNSS, where z takes
    the slow record between its samples —, the five that gained 9–78 % won, 2.58 → 2.04,
    5.54 → 3.98, 4.10 → 3.70, 4.56 → 0.99 and 2.26 → 1.80 mGal).
    ``names``/``taus``/``offsets``: the flights with a τ fit, their τ (s) and applied offset
    (s, 0 when not applied)."""
    p = cfg.processing
    if not p.lag_one_scale or p.lag_check_s is None or not names or not any(o != 0.0 for o in offsets):
        return None, None
    lags = [float(t - o) for t, o in zip(taus, offsets)]
    tau_c = float(np.median(lags))
    tau0 = cfg.gravimeter.tau_s
    if float(np.ptp(lags)) > p.lag_check_s or abs(tau_c - tau0) <= p.lag_check_s or not 0.0 <= tau_c <= MAX_TAU_S:
        return None, None
    info = {"declared_tau_s": tau0, "estimated_tau_s": list(taus), "time_offsets_s": list(offsets),
            "flight_lags_s": lags, "one_scale_tau_s": tau_c, "from_one_scale": True, "applied": False}
    try:
        check = lag_band_check([survey.flights[n] for n in names], cfg, tau_c, [declared[n] for n in names])
    except (ValueError, np.linalg.LinAlgError) as exc:
        info["reason"] = f"a flight could not be measured at τ = {tau_c:.3f} s: {exc}"
        return None, info
    info.update(check)
    gain = check["band_rms_improvement"]
    if not _band_check_passes(check, p, p.lag_one_scale_min_improvement):
        info["reason"] = (f"the flights' lags on one scale ({', '.join(f'{x:.3f}' for x in lags)} s) as τ = "
                          f"{tau_c:.3f} s change z's RMS at {check['band_hz'][0]:g}–{check['band_hz'][1]:g} Hz by "
                          f"{-100 * gain:+.1f} %: not used")
        return None, info
    info["applied"] = True
    info["reason"] = (f"τ fits minus applied time offsets {', '.join(f'{x:.3f}' for x in lags)} s; z's RMS at "
                      f"{check['band_hz'][0]:g}–{check['band_hz'][1]:g} Hz "
                      f"{check['band_rms_declared_mgal']:.1f} → {check['band_rms_estimated_mgal']:.1f} mGal")
    return tau_c, info


def _slow_gravimeter(flight, min_ratio: float | None) -> bool:
    """Is the flight's gravimeter slower than its GNSS — its sampling interval at least
    ``min_ratio`` GNSS steps (``slow_gravimeter_min_ratio``, the measure stage 1's motion
    compensation uses; None: never), both rates from the stamps (:func:`app.io.tables.median_rate_hz`)?
    There z takes the gravimeter between its samples (interpolated, or the means compensated
    for the motion), and a lag inverted on the slow record changes z above the band more than
    the damping it undoes: on two generated surveys with 2 Hz point samples on 5 and 10 Hz
    GNSS, the offsets read as a lag (τ right, 0.028 and 0.085 s) took the estimate 5.00 → 5.31
    and 1.41 → 1.57 mGal, FIR unchanged."""
    if min_ratio is None:
        return False
    f_grav = median_rate_hz(flight.gravimeter["time"].to_numpy(float))
    f_gnss = median_rate_hz(flight.gnss["time"].to_numpy(float))
    return bool(np.isfinite(f_grav) and np.isfinite(f_gnss) and f_gnss >= min_ratio * f_grav)


def band_power(m: FlightMeasurement, band: tuple, usable: np.ndarray) -> tuple[float, int]:
    """z's power in ``band`` (Hz) over the ``usable`` epochs of a measured flight, for pooling
    flights by their epochs: (RMS² × epochs in mGal², epochs); (0, 0) where the GNSS rate does not
    reach the band (:func:`app.core.noise_level.band_rms_mgal`)."""
    dt = float(np.median(np.diff(m.t_s)))
    if not band[1] < 0.5 / dt:
        return 0.0, 0
    r, n = band_rms_mgal(m.z_mgal, dt, band, usable=usable)
    return (float(r) ** 2 * n, int(n)) if n else (0.0, 0)


def lag_band_check(flights: list, cfg: SurveyConfig, tau_s: float, declared: list | None = None,
                   estimated: list | None = None) -> dict:
    """Does the in-flight τ make z better where the anomaly is estimated?

    The τ-only calibration fits up to ``acceleration_band_top_hz``, where the response of
    the records (interval means, an internal filter, heights differentiated twice) differs
    from a first-order lag's; a τ that absorbs that mismatch changes z in the band the
    smoother works in — just above FIR's cutoff — for the worse (a GT-1A with its declared,
    true τ = 2.0 s and 2 Hz heights: 2.093 s in flight when fitted across record holes, z's RMS at 0.02–0.05 Hz 43 → 61
    mGal, the estimate's error 3.2 → 6.6 mGal).  A real lag error lowers it there (τ 2.4 s
    declared 2.0: 78 → 33 mGal).  Compared on the flights the τ was estimated on, each with
    the time offset re-estimated for its τ: the RMS of z in 2–5 × 1/``fir_cutoff_period_s``
    Hz over the airborne stretches (:func:`app.core.noise_level.band_rms_mgal`), flights
    pooled by their epochs.  ``declared``: the flights already measured with survey.toml's τ
    (:func:`check_lag` measures them once for all its checks), else measured here.  It runs
    where the τ check would change τ (10 of 321 simulated surveys) and where the time offsets
    may be a lag (:func:`offset_as_lag`).  ``estimated``: the flights already measured with
    ``tau_s`` (:func:`band_lag`'s last fit), else measured here."""
    p = cfg.processing
    band = (2.0 / p.fir_cutoff_period_s, 5.0 / p.fir_cutoff_period_s)
    def powers(i):
        # measured already, or now (plain z either way), the flights at once (each_flight)
        m0 = (measure_flight(flights[i], cfg, compensation=False, match_response=False) if declared is None
              else declared[i])
        m1 = (measure_flight(flights[i], cfg, tau_s=tau_s, compensation=False, match_response=False)
              if estimated is None else estimated[i])
        # the same epochs for both (a gap's or a spike's mask moves with the time offset)
        usable = airborne(m0) & np.isfinite(m0.z_mgal) & np.isfinite(m1.z_mgal)
        return [band_power(m, band, usable) for m in (m0, m1)]

    ss = {"declared": 0.0, "estimated": 0.0}
    n_tot = 0
    for (e0, n), (e1, _) in each_flight(powers, range(len(flights))):   # summed in the flights' order
        ss["declared"] += e0
        ss["estimated"] += e1
        n_tot += n
    r0 = float(np.sqrt(ss["declared"] / n_tot)) if n_tot else float("nan")
    r1 = float(np.sqrt(ss["estimated"] / n_tot)) if n_tot else float("nan")
    gain = 1.0 - r1 / r0 if n_tot and r0 > 0 else float("nan")
    return {"band_hz": list(band), "band_rms_declared_mgal": r0, "band_rms_estimated_mgal": r1,
            "band_rms_improvement": gain, "band_epochs": n_tot}


def measure(survey, progress=None) -> Measurement:
    """Stage 1 on a survey (:class:`app.io.survey.Survey`): lag check or calibration, every
    flight measured and tied to its base readings.  ``progress(fraction)`` after each flight."""
    cfg = survey.config
    p = cfg.processing
    warnings: list[str] = list(getattr(survey, "notes", []))   # what the readers assumed or dropped
    tau_s = scale = None
    calibration = lag_check = None
    if p.calibrate:
        first = sorted(survey.flights)[0]
        try:
            calibration = calibrate_gravimeter(survey.flights[first], cfg)
            tau_s, scale = calibration["tau_s"], calibration["k"]
        except (ValueError, np.linalg.LinAlgError) as exc:
            warnings.append(f"in-flight calibration failed, nominal tau/scale used: {exc}")
    if calibration is None and p.lag_check_s is not None:
        tau_s, lag_check = check_lag_with_search(survey, cfg, warnings)
    flights, base_ties = {}, {}
    names = list(survey.flights)
    measured = line_map()(lambda name: measure_flight(survey.flights[name], cfg, tau_s=tau_s, scale=scale,
                                                      line_windows=line_windows(getattr(survey, "lines", None), name)),
                          names)
    for i, (name, m) in enumerate(zip(names, measured)):     # in the flights' order as each is done
        flights[name] = m
        if progress is not None:
            progress((i + 1) / len(names))
    response, again = choose_response_width(flights, p)
    if again:     # the flights whose own verdict is not the survey's, measured with the survey's width
        c = response["c_s2"] if response["applied"] else 0.0
        redone = line_map()(lambda name: measure_flight(survey.flights[name], cfg, tau_s=tau_s, scale=scale,
                                                        line_windows=line_windows(getattr(survey, "lines", None),
                                                                                  name), response_c_s2=c),
                            again)
        flights.update(zip(again, redone))
        response["measured_again"] = list(again)
    choose_motion_compensation(flights, p)
    band_delay = check_band_delay(flights, getattr(survey, "lines", None), p, warnings)
    for name in names:
        warnings.extend(f"flight {name}: {n}" for n in flights[name].notes)
        base_ties[name] = base_tie(flights[name], cfg.gravimeter.base_gravity_mgal)
    if not any(b.get("applied") and b.get("absolute") for b in base_ties.values()):
        why = ("no base_gravity_mgal in survey.toml" if cfg.gravimeter.base_gravity_mgal is None
               else "no static parking-place segment found in the flights")
        warnings.append(f"no absolute base tie ({why}): the level of dg carries the gravimeter's reading "
                        "error (scale × g, easily 100+ mGal); differences along and between lines are "
                        "reliable, absolute values are not")
    dt_s = float(np.median(np.concatenate([np.diff(m.t_s) for m in flights.values()])))
    return Measurement(flights, base_ties, lag_check, calibration, warnings, dt_s, band_delay, response)


def check_band_delay(flights: dict, lines, p, warnings: list) -> dict | None:
    """The gravimeter's timing left at the anomaly's edge, taken out of z (in place) when
    significant; the report's ``band_delay``.

    The time offset (fitted at 0.01–0.8 Hz) and the lag leave the delay that fits the
    turbulence best; an instrument whose response is not a pure lag and shift (an anti-alias
    filter, a platform's loop) is then still late or early at the phugoid's periods, just above
    the FIR cut-off, where 10⁴ mGal of motion make milliseconds into tens of mGal
    (:func:`app.core.measurement.band_delay_fit`).  Fitted at 1–5 × 1/``fir_cutoff_period_s``
    over the lines (the airborne epochs without a line table), the flights pooled (one
    instrument); taken out below 10 × 1/``fir_cutoff_period_s`` (:func:`delay_correction_mgal`)
    when it exceeds ``band_delay_min_t`` standard errors, z above that left as the offset fit
    made it.  Each record's runs on one time step are fitted apart (a hole left as a hole).

    **Flights that disagree are fitted apart.**  The time offsets are applied per flight (each
    where significant and useful), so what they leave can differ between flights; when the
    flights' own delays disagree by more than their errors (:func:`delay_heterogeneity`,
    p < ``band_delay_flights_p``) each flight's own delay is taken out where it exceeds
    ``band_delay_min_t`` standard errors, and no other.  (Foreign survey 947: offsets of −45
    and −32 ms applied on two flights, the third's −31 ms not; the flights' delays after them
    −6 ± 5, +11 ± 15, +38 ± 3 ms; pooled +30 ms, which put 36 ms back into the first.)"""
    steps = [np.diff(m.t_s) for m in flights.values() if m.t_s.size > 1]
    if not p.band_delay_check or not steps:
        return None
    dt = float(np.median(np.concatenate(steps)))
    nyq = 0.5 / dt
    band = (1.0 / p.fir_cutoff_period_s, 5.0 / p.fir_cutoff_period_s)
    lowpass = min(10.0 / p.fir_cutoff_period_s, 0.8 * nyq)
    rec: dict = {"band_hz": list(band), "lowpass_hz": lowpass, "min_t": p.band_delay_min_t, "applied": False}
    if not band[1] < nyq:
        rec["reason"] = f"the band {band[0]:g}–{band[1]:g} Hz is not below the GNSS Nyquist frequency"
        return rec
    per_flight, accel = {}, {}
    for name, m in flights.items():
        a = gnss_acceleration_ms2(m.t_s, m.vu_ms) * geodesy.MGAL_PER_MS2
        accel[name] = a
        usable = judged_epochs(m.t_s, m.ve_ms, m.vn_ms, line_windows(lines, name))
        per_flight[name] = [(m.t_s[i0:i1], m.z_mgal[i0:i1], a[i0:i1], usable[i0:i1])
                            for i0, i1 in gnss_runs(m.t_s, 0.0)]
    # each run on its own step (flights may differ)
    fit = band_delay_fit([s for segs in per_flight.values() for s in segs], None, band)
    rec.update({"delay_s": fit.delay_s, "se_s": fit.se_s, "t_stat": fit.t_stat, "n_independent": fit.n_independent,
                "band_rms_mgal": fit.band_rms_mgal, "band_rms_corrected_mgal": fit.band_rms_corrected_mgal,
                "n_epochs": fit.n_epochs})
    if not np.isfinite(fit.t_stat):
        rec["reason"] = f"too few line epochs to fit ({fit.n_epochs})"
        return rec
    delays = _flights_band_delays(per_flight, band, rec, p) if len(flights) > 1 else None
    if delays is None:       # one instrument, one delay
        if abs(fit.t_stat) < p.band_delay_min_t:
            rec["reason"] = (f"residual delay {1e3 * fit.delay_s:+.1f} ms at {band[0]:g}–{band[1]:g} Hz is "
                             f"{abs(fit.t_stat):.1f} standard errors (< {p.band_delay_min_t:g}): z kept")
            return rec
        delays = dict.fromkeys(flights, fit.delay_s)
        rec["reason"] = (f"the gravimeter is {1e3 * abs(fit.delay_s):.1f} ms {'late' if fit.delay_s > 0 else 'early'} "
                         f"against the GNSS at {band[0]:g}–{band[1]:g} Hz "
                         f"({abs(fit.t_stat):.1f} standard errors) after the time offset and lag: taken out of z below "
                         f"{lowpass:g} Hz (z's band RMS {fit.band_rms_mgal:.3g} → {fit.band_rms_corrected_mgal:.3g} mGal)")
    elif not delays:
        rec["reason"] += f": no flight's own delay reaches {p.band_delay_min_t:g} standard errors, z kept"
        return rec
    else:
        rec["reason"] += (": taken out of z below " f"{lowpass:g} Hz on "
                          + ", ".join(f"{n} ({1e3 * d:+.1f} ms)" for n, d in delays.items()))
    for name, d in delays.items():
        m = flights[name]
        corr = np.zeros(m.t_s.size)
        for i0, i1 in gnss_runs(m.t_s, 0.0):       # each run on one step (a hole left as a hole)
            r = slice(i0, i1)
            if i1 - i0 > 1:
                nyq_r = 0.5 / float(np.median(np.diff(m.t_s[r])))     # a flight logged slower: its own
                corr[r] = delay_correction_mgal(m.t_s[r], accel[name][r], d, min(lowpass, 0.8 * nyq_r))
        m.z_mgal = np.where(np.isfinite(corr), m.z_mgal - corr, m.z_mgal)
    rec["applied"] = True
    warnings.append(f"gravimeter timing: {rec['reason']} (report band_delay)")
    return rec


def _flights_band_delays(per_flight: dict, band: tuple, rec: dict, p) -> dict | None:
    """Each flight's own band delay (:func:`check_band_delay`), recorded in ``rec['flights']`` and
    ``rec['heterogeneity']``: None when the flights agree (the pooled delay stands), else
    ``{flight: delay_s}`` for the flights whose own delay is significant (``rec['reason']`` says
    why they are fitted apart)."""
    fits = {name: band_delay_fit(segs, None, band) for name, segs in per_flight.items()}
    rec["flights"] = {name: {"delay_s": f.delay_s, "se_s": f.se_s, "t_stat": f.t_stat, "n_epochs": f.n_epochs}
                      for name, f in fits.items()}
    het = delay_heterogeneity([f.delay_s for f in fits.values()], [f.se_s for f in fits.values()])
    rec["heterogeneity"] = {**het, "p_limit": p.band_delay_flights_p}
    if not (het["dof"] and het["p_value"] < p.band_delay_flights_p):
        return None
    rec["per_flight"] = True
    each = ", ".join(f"{n} {1e3 * f.delay_s:+.1f} ± {1e3 * f.se_s:.1f} ms" for n, f in fits.items()
                     if np.isfinite(f.delay_s))
    rec["reason"] = (f"the flights' delays disagree ({each}; "
                     f"χ² {het['chi2']:.1f} on {het['dof']} degrees of freedom, p = {het['p_value']:.2g} < "
                     f"{p.band_delay_flights_p:g}: the time offsets left each its own), each fitted apart")
    return {name: f.delay_s for name, f in fits.items()
            if np.isfinite(f.t_stat) and abs(f.t_stat) >= p.band_delay_min_t}
