"""Stage 3, noise model: the error of z as a coloured process and its level in time.

* :func:`fit_noise` — the shape (:mod:`app.core.noise_model`), fitted on the multitaper
  spectra of every line's z and of the pass differences of repeat tracks
  (:func:`repeat_differences`), normalised so that a level R is the equivalent white
  velocity noise in :func:`level_band`;
* :func:`noise_levels` — the local level R(t) of every flight, measured in that band;
* :func:`level_scale` — the factor that carries the measured level to the fitted model's.

:func:`model_noise` runs the three and returns a :class:`NoiseStage`.  After filtering,
:func:`noise_episodes` lists the stretches of the lines where the level the smoother used was
far above the survey's typical one (the report's ``noise_episodes``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.core.accuracy import REPEAT_MAX_SPREAD_KM, across_track_spread_km
from app.core.geodesy import MGAL_PER_MS2
from app.core.measurement import gnss_acceleration_ms2, height_velocity_misfit_m, response_prediction_mgal
from app.core.model_check import (
    crossover_comparison,
    difference_nll,
    fir_noise_variance_mgal2,
    noise_overstated,
    repeat_contrasts,
    significantly_worse,
)
from app.core.noise_level import band_noise_variance_cm2s2, elevated_runs, local_noise_variance_cm2s2
from app.core.noise_model import BIC_MARGIN, FAMILIES, VelocityBound, fit_noise_model, pass_differences, velocity_bound
from app.pipeline.stages.lines import LineData, finite_segments, line_crossovers
from app.pipeline.stages.measurement import FlightMeasurement


def level_band(p, dt_s: float) -> tuple[float, float]:
    """The band (Hz) in which the local noise level R(t) is measured, inside the GNSS
    Nyquist frequency (1–2 Hz receivers)."""
    f2 = min(float(p.noise_band_hz[1]), 0.8 * 0.5 / dt_s)
    return (min(float(p.noise_band_hz[0]), 0.5 * f2), f2)


def misfit_bound(lines: list[LineData], flights: dict[str, FlightMeasurement], dt_s: float,
                 p) -> VelocityBound | None:
    """The GNSS height–velocity misfit's spectrum (:func:`app.core.noise_model.velocity_bound`)
    over every flight whose velocities came from the file (not derived from its heights,
    where the two agree by construction), from the first line's start to the last line's end
    (turns included: the GNSS is the same receiver, and the longer the stretch the lower the
    frequencies it shows), split where h or vu is missing.  None when off
    (``noise_velocity_bound``) or no flight has such a stretch."""
    if not p.noise_velocity_bound:
        return None
    segs = []
    for name, fm in flights.items():
        if getattr(fm, "heights_only", False) or getattr(fm, "vu_ms", None) is None:
            continue
        own = [ln for ln in lines if ln.flight == name and ln.t_s.size]
        if not own:
            continue
        t0, t1 = min(float(ln.t_s[0]) for ln in own), max(float(ln.t_s[-1]) for ln in own)
        k = (fm.t_s >= t0) & (fm.t_s <= t1)
        t, h, v = fm.t_s[k], fm.h_m[k], fm.vu_ms[k]
        ok = np.isfinite(t) & np.isfinite(h) & np.isfinite(v)
        for a, b in finite_segments(np.where(ok, 0.0, np.nan)):
            # and split where epochs are missing (the spectrum needs a uniform step)
            cuts = [a] + (a + 1 + np.flatnonzero(np.diff(t[a:b]) > 1.5 * dt_s)).tolist() + [b]
            for c0, c1 in zip(cuts[:-1], cuts[1:]):
                if c1 - c0 >= 64:
                    segs.append(height_velocity_misfit_m(t[c0:c1], h[c0:c1], v[c0:c1]))
    if not segs:
        return None
    return velocity_bound(segs, dt_s, min(0.05, 0.4 / dt_s), quantile=p.noise_velocity_bound_quantile)


def fit_noise(lines: list[LineData], dt_s: float, p, heights_only: bool = False, families=None, bridges=None,
              bound: VelocityBound | None = None):
    """The error of z as a coloured process (:mod:`app.core.noise_model`), fitted on the
    finite stretches of every line; returns (NoiseFit, model normalised so that a level R is
    the equivalent white velocity noise in :func:`level_band`).  ``heights_only``: every
    flight's vu was derived from its heights, so among the families the spectra cannot tell
    apart (within the BIC margin) a height family is preferred (:func:`fit_noise_model`).
    Also returns the shortest stretch used (s): ``noise_fit_min_s[0]``, or ``[1]`` when no line
    is that long.  ``families``: the candidates (default: every family, or
    ``p.noise_family`` when set).  ``bound``: :func:`misfit_bound`."""
    fams = families if families is not None else (
        FAMILIES if p.noise_family == "auto" else tuple(f for f in FAMILIES if f[0] == p.noise_family))
    zs = [bridged(ln, bridges, dt_s) for ln in lines]
    segs = [z[a:b] for z in zs for a, b in finite_segments(z)]
    fmax = min(float(p.noise_fit_fmax_hz), 0.8 * 0.5 / dt_s)
    diffs = repeat_differences(lines, dt_s, min(2.0 * fmax, 0.45 / dt_s)) if p.noise_fit_repeats else []
    longest_s = max((s.size * dt_s for s in segs), default=0.0)
    min_s = float(p.noise_fit_min_s[0])
    if longest_s < min_s:  # short lines: the shorter stretches, with a warning (the fit's lowest
        min_s = min(min_s, float(p.noise_fit_min_s[1]))  # frequency rises to ~4.5/min_s Hz)
        if longest_s < min_s:
            raise ValueError(f"no line has a stretch of z of at least {min_s:g} s to fit the noise model on "
                             f"(the longest is {longest_s:.0f} s): the lines are too short for this survey's "
                             "noise model (processing.noise_fit_min_s)")
    fit = fit_noise_model(segs, dt_s, m=2, fmax_hz=fmax, families=fams, differences=diffs,
                          octave_weights=p.noise_fit_octave_weights, knee_max_fraction=p.noise_knee_max_fraction,
                          prefer_height=heights_only, min_duration_s=min_s,
                          height_tau_min_s=p.noise_height_tau_min_s, bound=bound,
                          bound_fmax_hz=p.noise_velocity_bound_fmax_hz, anomaly_rolloff=p.noise_anomaly_rolloff)
    return fit, fit.model.normalized(level_band(p, dt_s)), min_s


#: Longest hole of z (s) the noise fit bridges with the acceleration's prediction of z.
BRIDGE_MAX_S = 10.0


def bridge_for(fm: FlightMeasurement, dt_s: float, band_hz) -> tuple[np.ndarray, int]:
    """A flight's bridge for the noise fit: z as the GNSS acceleration predicts it
    (:func:`app.core.measurement.response_prediction_mgal`) and the longest hole (epochs) it
    may fill.  What the prediction misses adds, over a hole of n epochs, a velocity error of
    about ``n·(σ_res·Δt)²`` in variance — a step whose flat spectrum competes with the velocity
    noise at the lowest frequencies.  A hole is bridged only while that stays below one epoch's
    velocity noise (the band level R, as equivalent white velocity noise): on the 2 Hz test line
    (σ_res 3,500 mGal, loud heights-only GNSS) a 9-epoch mask is bridged; on a quiet 10 Hz GT-1A
    record (σ_res 2,250 mGal, 0.5 cm/s GNSS) no hole is, and bridging 1–2 s holes there put a
    Gauss–Markov velocity into the fit (1.94 → 7.31 mGal)."""
    pred = response_prediction_mgal(fm.z_mgal, gnss_acceleration_ms2(fm.t_s, fm.vu_ms))
    ok = np.isfinite(pred) & np.isfinite(fm.z_mgal)
    if ok.sum() < 100:
        return pred, 0
    res = (fm.z_mgal - pred)[ok]
    sigma_res_ms2 = 1.4826 * float(np.median(np.abs(res - np.median(res)))) * 1e-5
    level = band_noise_variance_cm2s2(fm.z_mgal, dt_s, band_hz, t_s=fm.t_s)
    r_m2s2 = float(np.nanmedian(level)) * 1e-4 if np.any(np.isfinite(level)) else 0.0
    if not (sigma_res_ms2 > 0 and r_m2s2 > 0):
        return pred, 0
    return pred, int(np.floor(r_m2s2 / (sigma_res_ms2 * dt_s) ** 2))


def bridged(ln: LineData, bridges, dt_s: float) -> np.ndarray:
    """The line's z with its short holes (at most :data:`BRIDGE_MAX_S` and the flight's
    :func:`bridge_for` length; a gravimeter dropout) filled by the flight's prediction, so that
    the noise fit sees whole lines: split at a hole, a 600 s line's halves lose the lowest
    frequencies, where the velocity part of the noise shows."""
    z = ln.z_mgal
    if not bridges or ln.flight not in bridges or np.all(np.isfinite(z)):
        return z
    pred, n_max = bridges[ln.flight]
    pred = pred[ln.sl]
    out = z.copy()
    bad = ~np.isfinite(z)
    d = np.diff(np.concatenate([[0], bad.astype(np.int8), [0]]))
    for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)):
        if a > 0 and b < z.size and (b - a) * dt_s <= BRIDGE_MAX_S and b - a <= n_max:
            out[a:b] = pred[a:b]
    return out


def repeat_tracks(lines: list[LineData]) -> list[tuple[list[LineData], list[np.ndarray]]]:
    """Every repeat track with at least two passes: the passes in time order and their
    along-track positions (m, the projection on the principal axis of all the track's points,
    so passes flown in opposite directions line up).  A track whose passes lie more than
    :data:`app.core.accuracy.REPEAT_MAX_SPREAD_KM` apart across it is left out: its pass
    differences hold the anomaly's change across the track as well as the noise (the report
    warns about it, :func:`app.pipeline.stages.outputs.repeat_track_warnings`)."""
    tracks: dict = {}
    for ln in lines:
        if ln.kind == "repeat" and ln.track is not None:
            tracks.setdefault(ln.track, []).append(ln)
    out = []
    for passes in tracks.values():
        if len(passes) < 2:
            continue
        passes = sorted(passes, key=lambda ln: float(ln.t_s[0]))
        if across_track_spread_km([ln.easting_km for ln in passes],
                                  [ln.northing_km for ln in passes]) > REPEAT_MAX_SPREAD_KM:
            continue
        e = np.concatenate([ln.easting_km for ln in passes])
        n = np.concatenate([ln.northing_km for ln in passes])
        axis = np.linalg.svd(np.column_stack([e - e.mean(), n - n.mean()]), full_matrices=False)[2][0]
        out.append((passes, [1000.0 * ((ln.easting_km - e.mean()) * axis[0] + (ln.northing_km - n.mean()) * axis[1])
                             for ln in passes]))
    return out


def repeat_differences(lines: list[LineData], dt_s: float, lowpass_hz: float) -> list:
    """Differences of the passes of every repeat track (disjoint consecutive pairs, so the
    differences are independent), on a common along-track grid, in finite stretches around
    holes (:func:`app.core.noise_model.pass_differences`)."""
    out = []
    for passes, along in repeat_tracks(lines):
        for i in range(0, len(passes) - 1, 2):
            a, b = passes[i], passes[i + 1]
            out.extend(pass_differences(along[i], a.z_mgal, along[i + 1], b.z_mgal, dt_s, lowpass_hz))
    return out


def repeat_fir_contrasts(lines: list[LineData], fir: dict[str, np.ndarray], spacing_s: float) -> np.ndarray:
    """Contrasts of the FIR estimates of the passes of every repeat track
    (:func:`app.core.model_check.repeat_contrasts`), every ``spacing_s`` of flight along the
    track (at the passes' mean speed).  The anomaly cancels; each contrast has the variance of
    one pass's FIR noise, plus whatever differs between the passes (drift, height), which only
    adds: they bound the FIR noise as crossover differences do."""
    out = [repeat_contrasts(along, [fir[ln.flight][ln.sl] for ln in passes],
                            float(np.mean([ln.speed_ms for ln in passes])) * spacing_s)
           for passes, along in repeat_tracks(lines)]
    return np.concatenate(out) if out else np.zeros(0)


def noise_levels(flights: dict[str, FlightMeasurement], dt_s: float, p) -> dict[str, np.ndarray]:
    """Local noise level R(t) ((cm/s)², equivalent white velocity noise) of every flight:
    z's content in :func:`level_band` (``noise_model = 'band'``) — less its part linear in the
    gravimeter's specific force f̄ with ``noise_level_unmix``, the two instruments' response
    mismatch, which follows the turbulence and has no weight in the anomaly band — or near the
    Nyquist frequency (``'local'``); empty for ``'states'`` (the recognised R_j levels are used
    instead)."""
    if p.noise_model == "local":
        return {name: local_noise_variance_cm2s2(fm.z_mgal, dt_s) for name, fm in flights.items()}
    if p.noise_model == "band":
        band = level_band(p, dt_s)
        return {name: band_noise_variance_cm2s2(fm.z_mgal, dt_s, band,
                                                regressor_mgal=fm.fbar_ms2 * MGAL_PER_MS2 if p.noise_level_unmix else None,
                                                t_s=fm.t_s)
                for name, fm in flights.items()}
    return {}


def line_levels(lines: list[LineData], r_local: dict) -> np.ndarray:
    """The local levels R(t) ((cm/s)²) at the lines' epochs where z is measured."""
    return np.concatenate([r_local[ln.flight][ln.sl][np.isfinite(ln.z_mgal)] for ln in lines])


def level_scale(noise_fit, band_hz, lines: list[LineData], r_local: dict, white_lower: bool = False) -> float:
    """Factor from the measured local levels R(t) to the fitted noise model's level.

    The model's weights were fitted on the pooled spectra of the lines, i.e. at the mean
    level over the lines' epochs; the local measurement (in ``band_hz``) gives the level's
    changes in time.  When the model describes the measurement band well the factor is
    ≈ 1; where it does not (a turbulence band the family cannot follow) it carries the
    measured changes in time to the fitted level where the smoother separates anomaly
    from noise.

    The white-velocity family (the paper's shape) takes the band measurement as its level
    (factor 1), unless ``white_lower``: then the factor is the fitted level's when that is
    lower (never above 1) — a band that holds a turbulence bump above the f² shape (a 1 Hz
    platform gravimeter: 4–7×) over-states the noise in the anomaly band and flattens the
    estimate."""
    if not r_local:
        return 1.0
    if noise_fit.model.is_white_velocity and not white_lower:
        return 1.0
    vals = line_levels(lines, r_local)
    if not vals.size:
        return 1.0
    scale = float(noise_fit.model.equivalent_white_R(band_hz) / np.mean(vals))
    return min(scale, 1.0) if noise_fit.model.is_white_velocity else scale


@dataclass
class NoiseStage:
    """Result of :func:`model_noise`.

    Attributes
    ----------
    fit : app.core.noise_model.NoiseFit
        The Whittle fit (absolute weights, every candidate family).
    model : app.core.noise_model.NoiseModel
        The chosen shape, normalised to the equivalent white velocity noise in ``band_hz``.
    band_hz : (float, float)
        Band in which the local level is measured.
    r_local : dict of ndarray
        Per flight, the level R(t) ((cm/s)², equivalent white) at every GNSS epoch,
        already multiplied by ``scale``; empty with ``noise_model = 'states'``.
    scale : float
        :func:`level_scale`.
    """

    fit: object
    model: object
    band_hz: tuple
    r_local: dict
    scale: float
    level_note: str = ""
    unmoved: NoiseStage | None = None
    corner_check: dict | None = None
    alternative: NoiseStage | None = None
    family_check: dict | None = None
    holes_bridged: dict | None = None
    fit_min_stretch_s: float | None = None
    warning: str = ""

    def describe(self) -> dict:
        """The report's ``noise_model`` section."""
        out = {**self.model.describe(), "level_band_hz": list(self.band_hz), "level_scale": self.scale,
               "level_note": self.level_note,
               "candidates": self.fit.candidates, "n_bins": self.fit.n_bins, "fit_fmax_hz": self.fit.fmax_hz,
               "Q_whittle_mgal2": self.fit.Q_mgal2, "m_whittle": self.fit.m,
               "fit_min_stretch_s": self.fit_min_stretch_s}
        if self.corner_check is not None:
            out["corner_check"] = self.corner_check
        if self.family_check is not None:
            out["family_check"] = self.family_check
        if self.holes_bridged:
            out["holes_bridged"] = self.holes_bridged
        return out


def model_noise(lines: list[LineData], flights: dict[str, FlightMeasurement], dt_s: float, p,
                n_crossovers: int = 0) -> NoiseStage:
    """Stage 3: the noise model of the survey and the local level of every flight.
    ``n_crossovers`` (geometry) decides whether a white-velocity level may be lowered to
    its fitted value (``white_level_fitted``: only where the FIR guard can check it)."""
    heights_only = bool(flights) and all(getattr(f, "heights_only", False) for f in flights.values())
    bridges = {name: bridge_for(fm, dt_s, level_band(p, dt_s)) for name, fm in flights.items()
               if not np.all(np.isfinite(fm.z_mgal[1:]))}
    bound = misfit_bound(lines, flights, dt_s, p)
    fit, model, min_s = fit_noise(lines, dt_s, p, heights_only, bridges=bridges, bound=bound)
    band = level_band(p, dt_s)
    r_local = noise_levels(flights, dt_s, p)
    stage = _noise_stage(fit, model, band, lines, r_local, n_crossovers, p)
    if fit.unmoved is not None:
        stage.unmoved = _noise_stage(fit.unmoved, fit.unmoved.model.normalized(band), band, lines, r_local,
                                     n_crossovers, p)
    plain = tuple(f for f in FAMILIES if not coloured_velocity(f[1]))
    if p.noise_family == "auto" and p.noise_family_check and coloured_velocity(dict(FAMILIES)[fit.model.family]):
        # the family a check against the FIR differences may fall back on (check_noise_family)
        alt_fit, alt_model, _ = fit_noise(lines, dt_s, p, heights_only, families=plain, bridges=bridges,
                                          bound=bound)
        stage.alternative = _noise_stage(alt_fit, alt_model, band, lines, r_local, n_crossovers, p)
        if alt_fit.unmoved is not None:
            stage.alternative.unmoved = _noise_stage(alt_fit.unmoved, alt_fit.unmoved.model.normalized(band), band,
                                                     lines, r_local, n_crossovers, p)
    warning = ""
    if min_s < float(p.noise_fit_min_s[0]):
        warning = (f"the noise model was fitted on stretches of {min_s:g}-{p.noise_fit_min_s[0]:g} s (no line "
                   f"is {p.noise_fit_min_s[0]:g} s long): its shape is seen only above "
                   f"about {4.5 / min_s:.3f} Hz and is weak in the anomaly band")
    bridged_rep = {name: {"max_hole_epochs": n_max,
                          "epochs_bridged": sum(int(np.sum(np.isnan(ln.z_mgal) & np.isfinite(bridged(ln, bridges, dt_s))))
                                                for ln in lines if ln.flight == name)}
                   for name, (_, n_max) in bridges.items()}
    for st in (stage, stage.unmoved, stage.alternative, stage.alternative and stage.alternative.unmoved):
        if st is not None:
            st.fit_min_stretch_s, st.warning, st.holes_bridged = min_s, warning, bridged_rep
    return stage


def _noise_stage(fit, model, band, lines: list[LineData], r_local: dict, n_crossovers: int, p) -> NoiseStage:
    """The stage's result for one fit: the level scale and the scaled local levels."""
    vb = fit.model.info.get("velocity_bound") or {}
    bounded = bool(p.white_level_bounded and vb.get("applied") and fit.model.is_white_velocity)
    white_lower = bool(p.white_level_fitted and p.fir_guard and n_crossovers >= p.fir_guard_min_crossovers)
    scale = level_scale(fit, band, lines, r_local, white_lower)
    capped = 1.0
    if bounded and r_local:
        # the heights' bound: no more white velocity error below 0.01 Hz than they show (only
        # ever lowering: the bound cannot say a level is too low).  The ratio was taken at the
        # fitted level; the level used is the mean of the scaled R(t)
        over = float(vb.get("max_model_to_misfit_after", vb.get("max_model_to_misfit", 1.0)))
        vals = line_levels(lines, r_local)
        r_fit = float(fit.model.equivalent_white_R(band))
        if vals.size and r_fit > 0:
            capped = max(over * scale * float(np.mean(vals)) / r_fit, 1.0)
            scale = scale / capped
    if not model.is_white_velocity:
        note = "the fitted model's level (local changes in time from the band measurement)"
    elif white_lower:
        note = (f"white velocity: the fitted level where lower than the band measurement ({n_crossovers} "
                f"crossovers, the FIR guard checks it)")
    else:
        note = ("white velocity: the band measurement" +
                (f" (the fitted level is not used: {n_crossovers} crossovers < {p.fir_guard_min_crossovers} "
                 "cannot check it)" if p.white_level_fitted else ""))
    if capped > 1.0:
        note += (f"; lowered by {capped:.2f}x to the velocity error the GNSS heights allow below "
                 f"{p.noise_velocity_bound_fmax_hz:g} Hz (velocity_bound)")
    return NoiseStage(fit, model, band, {k: v * scale for k, v in r_local.items()}, scale, note)


def coloured_velocity(spec) -> bool:
    """Does a family's spec ((order, φ free?), ...) hold a coloured (AR) velocity component?"""
    return any(order == 1 and free for order, free in spec)


def check_noise_family(stage: NoiseStage, lines: list[LineData], fir: dict[str, np.ndarray], dt_s: float,
                       p) -> NoiseStage:
    """Fall back from a coloured-velocity family to the best family without one when the
    chosen model predicts significantly more FIR noise than the FIR differences at the
    crossovers and between repeat passes allow (``noise_family_check``).

    A coloured velocity error has a corner below which its acceleration spectrum is flat:
    it puts as much noise at 0.005 Hz as at 0.1 Hz.  On heights-only GNSS the spectra can
    choose it for what are defects above the anomaly band — a gravimeter's stamps scattered
    by ±5 ms on a 2 Hz record, undetected height outliers — and carry that level down into the
    anomaly band, where the smoother then calls the anomaly noise: the simulated 2 Hz test
    line's estimate was flattened to 0.53 of the truth's variance, 1.4x the FIR error, while
    its passes' FIR differences showed 1.7 mGal of FIR noise against the 3.0 the model
    predicted.  Those differences need no model: each bounds ``σ_a² + σ_b²`` from above
    (:func:`app.core.model_check.noise_overstated`, one-sided ``noise_family_alpha``).  A
    Gauss–Markov velocity error that is really there (a receiver's correlated velocity
    noise) predicts the FIR noise the differences show and is kept."""
    alt, stage.alternative = stage.alternative, None
    if alt is None or not p.noise_family_check:
        return stage
    rec: dict = {"chosen": stage.model.family, "alternative": alt.model.family, "applied": False}
    d, shares = fir_differences(lines, fir, p)
    b = fir_noise_bound(stage, lines, dt_s, p, (d, shares), alpha=p.noise_family_alpha)
    if b is None:
        stage.family_check = {**rec, "n": 0, "reason": "no crossovers or repeat passes to check the coloured velocity"}
        return stage
    rec.update(_bound_fields(b, "fir_difference_ms_mgal2"))
    if not b.overstated:
        stage.family_check = rec
        return stage
    v = shares * predicted_fir_variance_mgal2(stage, lines, dt_s, p)
    v_alt = shares * predicted_fir_variance_mgal2(alt, lines, dt_s, p)
    nll, nll_alt = difference_nll(d, v), difference_nll(d, v_alt)
    rec.update(alternative_predicted_ms_mgal2=float(np.mean(v_alt)), nll=nll, alternative_nll=nll_alt)
    if not nll_alt < nll:
        # the alternative misses the differences by more the other way (a real Gauss-Markov
        # velocity error whose differences fell low by chance: the white family predicts far less)
        stage.family_check = {**rec, "reason": (
            f"{stage.model.family} predicts more FIR noise than the differences allow, but {alt.model.family} "
            f"({float(np.mean(v_alt)):.3g} mGal²) explains them no better: kept")}
        return stage
    rec.update(applied=True, reason=(
        f"{stage.model.family} predicts {b.predicted_ms_mgal2:.3g} mGal² of FIR noise in the differences at the "
        f"crossovers and between repeat passes, above the {b.bound_mgal2:.3g} mGal² their FIR differences allow "
        f"({b.n} samples, one-sided {p.noise_family_alpha:g}): {alt.model.family} used"))
    alt.family_check = rec
    return alt


def check_noise_corners(stage: NoiseStage, lines: list[LineData], fir: dict[str, np.ndarray], dt_s: float,
                        p) -> NoiseStage:
    """Keep the noise fit's own shape below the data when the more cautious one over-states
    the noise the crossovers allow (``noise_corner_check``).

    Two decisions of :func:`app.core.noise_model.fit_noise_model` put more noise below the
    fitted band than the spectra show: a corner between the lowest fitted frequency and twice
    the anomaly/noise crossover is moved below the data, and a bare white height error gets a
    random-walk height part (the family that nests it).  On most surveys the spectra's own
    shape there let noise through as anomaly.  But where it was right, the cautious shape
    over-states the noise in the anomaly band, and the estimate is flattened.  The FIR
    estimate's crossover differences bound the noise it passes from above
    (:func:`app.core.model_check.noise_overstated`); when the cautious model's predicted FIR
    noise exceeds that bound significantly, the fit as it was is used.  Returns the stage
    used, with the evidence in ``corner_check``."""
    if stage.unmoved is None:
        return stage
    unmoved, stage.unmoved = stage.unmoved, None   # decided here: not stored twice
    rec: dict = {"hidden_corners_hz": stage.model.info.get("hidden_corners_hz", []),
                 "white_height_nested": bool(stage.model.info.get("white_height_nested", False)), "applied": False}
    if not p.noise_corner_check:
        stage.corner_check = {**rec, "reason": "off (noise_corner_check)"}
        return stage
    b = fir_noise_bound(stage, lines, dt_s, p, fir_differences(lines, fir, p))
    if b is None:
        stage.corner_check = {**rec, "n": 0, "reason": "no crossovers (or no local noise level) to check the cautious shape"}
        return stage
    rec.update(_bound_fields(b, "fir_crossover_ms_mgal2"))
    if not b.overstated:
        stage.corner_check = rec
        return stage
    used = unmoved
    rec.update(applied=True, reason=(
        f"the {'corners moved below the data' if rec['hidden_corners_hz'] else 'random-walk height part'} "
        f"predict {b.predicted_ms_mgal2:.3g} mGal² of FIR noise at the crossovers, above the "
        f"{b.bound_mgal2:.3g} mGal² their FIR differences allow ({b.n} crossovers, one-sided "
        f"{p.noise_corner_alpha:g}): the fit's own shape is kept"))
    used.corner_check = rec
    return used


def fir_noise_bound(stage: NoiseStage, lines: list[LineData], dt_s: float, p, diffs, alpha: float | None = None):
    """The stage's predicted FIR noise at the crossovers and between the passes of repeat
    tracks against the bound their FIR differences ``diffs`` (:func:`fir_differences`) set
    (:func:`app.core.model_check.noise_overstated`, one-sided ``alpha``, default
    ``noise_corner_alpha``); None without such differences or levels.

    The prediction is at the survey's typical level (median over the lines' epochs): the
    question is the model's shape and level in FIR's band, and a noise episode's level —
    measured at 0.1–0.5 Hz — need not hold there; episodes in the differences only widen the
    bound."""
    d, shares = diffs
    var = predicted_fir_variance_mgal2(stage, lines, dt_s, p)
    if var is None or d.size == 0:
        return None
    return noise_overstated(d, shares * var, alpha=p.noise_corner_alpha if alpha is None else alpha)


def _bound_fields(b, ms_key: str) -> dict:
    """A :class:`app.core.model_check.NoiseBound`'s figures for the report (``ms_key``: the name of
    the observed mean square)."""
    return {"n": b.n, ms_key: b.crossover_ms_mgal2, "predicted_ms_mgal2": b.predicted_ms_mgal2,
            "bound_mgal2": b.bound_mgal2}


def fir_differences(lines: list[LineData], fir: dict[str, np.ndarray], p) -> tuple[np.ndarray, np.ndarray]:
    """The FIR estimates' differences at the crossovers and contrasts between repeat passes
    (:func:`repeat_fir_contrasts`, every FIR cut-off period of flight), mGal, and how many
    lines' FIR noise each holds (2 at a crossover, 1 in a repeat contrast): with a model's FIR
    noise variance σ² per line, the predicted variances are ``shares · σ²``."""
    cx = line_crossovers(lines, p.leveling_include_repeat, lambda ln: fir[ln.flight][ln.sl])
    d = (cx["dg_a"] - cx["dg_b"]).to_numpy(float) if len(cx) else np.zeros(0)
    c = repeat_fir_contrasts(lines, fir, p.fir_cutoff_period_s)
    return np.concatenate([d, c]), np.concatenate([np.full(d.size, 2.0), np.ones(c.size)])


def predicted_fir_variance_mgal2(stage: NoiseStage, lines: list[LineData], dt_s: float, p) -> float | None:
    """One line's FIR noise variance (mGal²) under the stage's model at the survey's median
    level; None without local levels."""
    if not stage.r_local:
        return None
    level = float(np.median(np.concatenate([stage.r_local[ln.flight][ln.sl][np.isfinite(ln.z_mgal)]
                                            for ln in lines])))
    return fir_noise_variance_mgal2(stage.model, level, dt_s, p.fir_cutoff_period_s)


def noise_episodes(table, factor: float, min_duration_s: float, bridge_s: float) -> tuple[dict, list[str]]:
    """The stretches of the lines where the noise level the smoother used, R(t) (the table's
    ``R_cm2s2``), exceeds ``factor`` × the survey's typical level (its median over the lines'
    epochs) for at least ``min_duration_s`` (gaps up to ``bridge_s`` bridged:
    :func:`app.core.noise_level.elevated_runs`), for the report and a warning.

    There the smoother leans on the anomaly model more than elsewhere and ``dg_std_mgal`` is
    wider.  R(t) is measured in :func:`level_band` and carried to the anomaly band with the
    survey's noise shape; an episode whose error has another shape — multipath in positions
    differentiated to velocities, whose error falls towards low frequencies — holds less noise
    in the anomaly band than R(t) says, and the estimate can be worse than FIR 100 s there (the
    independent generator's survey 994, line M004: 5.0 against FIR's 1.4 mGal over a 270 s
    episode of 16× the typical level).

    Parameters
    ----------
    table : DataFrame
        One row per epoch of the lines in time order within each line: ``line``, ``flight``,
        ``time`` (s), ``easting_km``, ``northing_km``, ``R_cm2s2``, ``dg_std_mgal``.
    factor : float
        Threshold over the typical level (> 1).
    min_duration_s, bridge_s : float
        Shortest episode listed, longest gap bridged (s).

    Returns
    -------
    (dict, list of str)
        The report's ``noise_episodes`` (typical level, threshold, the episodes with their line,
        times, along-line km, peak and mean level over the typical one, mean std against the
        line's median std outside its episodes) and the warnings.
    """
    r_all = table["R_cm2s2"].to_numpy(float) if "R_cm2s2" in table else np.zeros(0)
    ok = np.isfinite(r_all) & (r_all > 0)
    rep = {"factor": float(factor), "min_duration_s": float(min_duration_s), "bridge_s": float(bridge_s),
           "typical_R_cm2s2": None, "threshold_R_cm2s2": None, "episodes": [], "lines": [], "epoch_fraction": 0.0}
    if not ok.any():
        return rep, []
    typical = float(np.median(r_all[ok]))
    rep.update({"typical_R_cm2s2": typical, "threshold_R_cm2s2": factor * typical})
    n_in = 0
    for line, g in table.groupby("line", sort=False):
        t = g["time"].to_numpy(float)
        if t.size < 2 or not np.all(np.diff(t) > 0):
            continue
        r = g["R_cm2s2"].to_numpy(float)
        std = g["dg_std_mgal"].to_numpy(float)
        along = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(g["easting_km"].to_numpy(float)),
                                                          np.diff(g["northing_km"].to_numpy(float))))])
        runs = elevated_runs(r, t, factor * typical, min_duration_s, bridge_s)
        if not runs:
            continue
        inside = np.zeros(t.size, bool)
        for a, b in runs:
            inside[a:b] = True
        quiet = std[~inside & np.isfinite(std)]
        for a, b in runs:
            seg, sd = r[a:b], std[a:b]
            rep["episodes"].append({
                "line": str(line), "flight": str(g["flight"].iloc[a]), "t_start_s": float(t[a]),
                "t_end_s": float(t[b - 1]), "duration_s": float(t[b - 1] - t[a]),
                "along_start_km": float(along[a]), "along_end_km": float(along[b - 1]),
                "R_peak_over_typical": float(np.nanmax(seg) / typical),
                "R_mean_over_typical": float(np.nanmean(seg) / typical),
                "std_mean_mgal": float(np.nanmean(sd)) if np.isfinite(sd).any() else None,
                "std_line_quiet_mgal": float(np.median(quiet)) if quiet.size else None})
        n_in += int(inside.sum())
    rep["lines"] = sorted({e["line"] for e in rep["episodes"]})
    rep["epoch_fraction"] = n_in / max(1, len(table))
    if not rep["episodes"]:
        return rep, []
    ep = rep["episodes"]
    worst = max(ep, key=lambda e: e["R_peak_over_typical"])
    where = ", ".join(f"{e['line']} {e['along_start_km']:.0f}–{e['along_end_km']:.0f} km" for e in ep[:6])
    more = f" and {len(ep) - 6} more" if len(ep) > 6 else ""
    warning = (f"noise episodes: {len(ep)} stretch{'es' if len(ep) > 1 else ''} of {len(rep['lines'])} "
               f"line{'s' if len(rep['lines']) > 1 else ''} ({where}{more}; {100 * rep['epoch_fraction']:.1f} % of "
               f"the epochs) where the noise level R(t) exceeds {factor:g}× the survey's typical "
               f"{typical:.3g} (cm/s)², up to {worst['R_peak_over_typical']:.0f}× on {worst['line']}: the "
               "estimate there leans on the anomaly model and its std is wider; where the episode's error "
               "is not the survey's shape (multipath in positions) it can be worse than FIR 100 s — compare "
               "the two on those stretches")
    return rep, [warning]


#: the family a crossover check falls back on: the paper's (seed 000) white velocity error
CHECK_FAMILY = "white velocity"


def family_check_due(noise_report: dict, n_crossovers: int, p) -> dict:
    """Should the survey be identified and filtered again with white velocity noise
    (``noise_family_crossover_check``)?  Due when the fit chose another family (``noise_family =
    'auto'``) by fewer than ``2 × BIC_MARGIN`` BIC units over white velocity — a near tie the
    spectra do not settle — and the survey has at least ``noise_family_crossover_min``
    crossovers to compare the two estimates on.  The seed-10 white regime: coloured height by
    10.9 units, 30 crossovers; filtered with it 1.04× FIR, with white velocity 0.91×.

    Parameters
    ----------
    noise_report : dict
        :meth:`NoiseStage.describe` (``family``, ``candidates`` with their ``bic``).
    n_crossovers : int
    p : ProcessingParams

    Returns
    -------
    dict
        ``{"due": bool, "applied": False, "family", "alternative", "bic_gap", "n_crossovers",
        "candidates_bic" (the fit's BIC of every family), "reason"}``.
    """
    family = str(noise_report.get("family"))
    bic = {c.get("family"): c.get("bic") for c in noise_report.get("candidates") or []}
    gap = (float(bic[CHECK_FAMILY]) - float(bic[family])
           if bic.get(CHECK_FAMILY) is not None and bic.get(family) is not None else None)
    rec = {"due": False, "applied": False, "family": family, "alternative": CHECK_FAMILY, "bic_gap": gap,
           "n_crossovers": int(n_crossovers),
           "candidates_bic": {str(k): float(v) for k, v in bic.items() if v is not None}}
    limit = 2.0 * BIC_MARGIN
    if not p.noise_family_crossover_check:
        rec["reason"] = "off (noise_family_crossover_check)"
    elif p.noise_family != "auto":
        rec["reason"] = f"the family is set in survey.toml ({p.noise_family})"
    elif family == CHECK_FAMILY:
        rec["reason"] = "the fit chose white velocity"
    elif gap is None:
        rec["reason"] = "no BIC of both families to compare"
    elif gap >= limit:
        rec["reason"] = f"{family} beats white velocity by {gap:.1f} BIC units (≥ {limit:g}): settled by the spectra"
    elif n_crossovers < p.noise_family_crossover_min:
        rec["reason"] = (f"{n_crossovers} crossovers (< {p.noise_family_crossover_min}) cannot compare the two "
                         "estimates")
    else:
        rec["due"] = True
        rec["reason"] = (f"{family} beats white velocity by only {gap:.1f} BIC units (< {limit:g}): both filtered, "
                         "compared at the crossovers")
    return rec


def family_crossover_choice(check: dict, cx_family, cx_alternative, p_level: float) -> dict:
    """The noise family's crossover check decided (in place on ``check``, also returned):
    white velocity replaces the family the fit chose when its estimate agrees significantly
    better at the crossovers — the paired tests of the order choice on the crossover
    differences before leveling (:func:`app.core.model_check.crossover_comparison`,
    :func:`~app.core.model_check.significantly_worse` at ``p_level``).  ``cx_family``,
    ``cx_alternative``: the two runs' ``crossovers.csv`` tables (line_a, line_b, easting_km,
    northing_km, diff_before_mgal), which must list the same crossovers in the same order."""
    same = (len(cx_family) == len(cx_alternative) and len(cx_family) > 0
            and bool(np.all(cx_family["line_a"].to_numpy() == cx_alternative["line_a"].to_numpy()))
            and bool(np.all(cx_family["line_b"].to_numpy() == cx_alternative["line_b"].to_numpy()))
            and bool(np.allclose(cx_family["easting_km"].to_numpy(float), cx_alternative["easting_km"].to_numpy(float)))
            and bool(np.allclose(cx_family["northing_km"].to_numpy(float), cx_alternative["northing_km"].to_numpy(float))))
    check["applied"] = False
    if not same:
        check["reason"] += "; the two runs' crossovers differ, the fit's family kept"
        return check
    cmp = crossover_comparison(cx_family["diff_before_mgal"].to_numpy(float),
                               cx_alternative["diff_before_mgal"].to_numpy(float))
    check.update({"crossovers_compared": cmp.n, "crossover_rms_mgal": {check["family"]: cmp.rms_a_mgal,
                                                                        CHECK_FAMILY: cmp.rms_b_mgal},
                  "p_value": cmp.p_value, "p_rank": cmp.p_rank, "p_level": float(p_level)})
    check["applied"] = bool(significantly_worse(cmp, p_level))
    verdict = ("white velocity used: its estimate agrees significantly better" if check["applied"]
               else f"{check['family']} kept: white velocity's estimate does not agree significantly better")
    check["reason"] += (f"; {verdict} (crossover RMS {cmp.rms_a_mgal:.3g} → {cmp.rms_b_mgal:.3g} mGal at {cmp.n}; "
                        f"t-test p = {cmp.p_value:.3g}, signed ranks p = {cmp.p_rank:.3g}, needs < {p_level:g})")
    return check
