"""Stage 8, filtering (SPEC §2 steps 5–6): the smoothed recognition map held on the full-rate
grid, Q(t) from the map's probabilities, the local noise level R(t), the Q levels refined by
the full-rate likelihood, the non-stationary Kalman smoother with posterior std, the
stationary (Q₁, R) smoother and the FIR 100 s low-pass beside it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from app.core.accuracy import (
    REPEAT_MAX_SPREAD_KM,
    across_track_spread_km,
    noise_excess_p_value,
    repeat_error_parts,
    repeat_line_accuracy,
    repeat_pass_departures,
    repeat_pass_noise_ratio,
    repeat_pass_std_scales,
)
from app.core.baselines import fir_gap_error_mgal, fir_lowpass_mgal
from app.core.level_ml import cap_lifted_smooth_level, lift_levels, raise_rough_level, refine_levels
from app.core.model_check import blend_estimates, leave_one_out_msd_mgal2, leave_one_out_msd_test
from app.core.noise_model import white_velocity, with_white_floor
from app.core.smoother import kalman_smooth, level_spread_std_mgal, mixture_std_mgal
from app.pipeline.parallel import line_map
from app.pipeline.stages.identification import unlearned_levels
from app.pipeline.stages.lines import LineData
from app.pipeline.stages.measurement import FlightMeasurement

#: Seconds of flight data on either side of a line given to the smoother (run-in).
MARGIN_S = 60.0


def fir_baseline(m: FlightMeasurement, cutoff_period_s: float, max_gap_error_mgal: float | None = None) -> np.ndarray:
    """FIR 100 s low-pass (seed 004) of ``z`` over the whole flight (mGal), so line edges
    see the run-in data as in industry practice.  Left out (NaN) where missing samples inside
    the record (a gravimeter dropout) or the record's own ends can move it by more than
    ``max_gap_error_mgal`` (:func:`app.core.baselines.fir_gap_error_mgal`): a renormalised
    low-pass across them is not an estimate of anything there, and the model checks compare
    with it.  A flight recorded from the ground loses only ground time; a record that starts
    or ends in the air loses up to half a kernel of its lines."""
    dt = float(np.median(np.diff(m.t_s)))
    fir = fir_lowpass_mgal(m.z_mgal, dt, cutoff_period_s)
    if max_gap_error_mgal is not None:
        bound = fir_gap_error_mgal(m.z_mgal, dt, cutoff_period_s, record_ends=True)
        fir[bound > max_gap_error_mgal] = np.nan
    return fir


def fir_line_column(lines: list[LineData], flights: dict[str, FlightMeasurement], cutoff_period_s: float,
                    max_gap_error_mgal: float | None = None) -> np.ndarray:
    """:func:`fir_baseline` at ``cutoff_period_s`` over each flight, on the lines' epochs in the
    order of :func:`filter_survey`'s table (lines in turn), mGal, shape (table rows,)."""
    fir = {name: fir_baseline(flights[name], cutoff_period_s, max_gap_error_mgal)
           for name in dict.fromkeys(ln.flight for ln in lines)}
    if not lines:
        return np.zeros(0)
    return np.concatenate([fir[ln.flight][ln.sl] for ln in lines])


#: Share of the line epochs with z above which FIR's absence near holes blinds the model checks.
FIR_LOSS_BLIND = 0.5


def fir_loss_warnings(lines: list[LineData], fir: dict[str, np.ndarray], p) -> list[str]:
    """Warnings where FIR 100 s was left out near missing samples (:func:`fir_baseline`):
    per flight, the line epochs lost; and when more than :data:`FIR_LOSS_BLIND` of all line
    epochs with z lack it, that the checks comparing with FIR see too little of the survey
    (holes that cut lines into stretches of a few minutes also hide the low frequencies the
    noise model is fitted on: docs/METHOD.md, stage 1, gaps)."""
    out = []
    lost_all = with_z = 0
    for name in fir:
        lost = sum(int(np.sum(np.isfinite(ln.z_mgal) & ~np.isfinite(fir[name][ln.sl])))
                   for ln in lines if ln.flight == name)
        with_z += sum(int(np.sum(np.isfinite(ln.z_mgal))) for ln in lines if ln.flight == name)
        lost_all += lost
        if lost:
            out.append(f"flight {name}: FIR {p.fir_cutoff_period_s:g} s left out over {lost} line epochs near missing "
                       f"samples inside the record or its ends in the air (their values could move it by more than "
                       f"{p.fir_gap_max_error_mgal:g} mGal there; processing.fir_gap_max_error_mgal); the model "
                       "checks use FIR elsewhere")
    if with_z and lost_all > FIR_LOSS_BLIND * with_z:
        out.append(f"FIR {p.fir_cutoff_period_s:g} s is left out on {100 * lost_all / with_z:.0f} % of the line "
                   "epochs (holes in the gravimeter record): the checks that compare with it (noise family and "
                   "corners, FIR guard, flattening) see too little of the survey to catch a wrong noise model, "
                   "and stretches of a few minutes between holes hide the low frequencies it is fitted on — "
                   "treat the estimate with caution (on a test line with three 4-10 s holes per pass it was "
                   "4-7x the error without them)")
    return out


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


def _stretch_interior(along_km: np.ndarray, edge_km: float, min_points: int) -> np.ndarray:
    """Boolean mask of the positions ``along_km`` at least ``edge_km`` from both ends of their
    range; every position where fewer than ``min_points`` would remain."""
    keep = (along_km >= np.min(along_km) + edge_km) & (along_km <= np.max(along_km) - edge_km)
    return keep if keep.sum() >= min_points else np.ones(along_km.size, bool)


def _interior(pr: PreparedLine, edge_km: float) -> np.ndarray:
    """Boolean mask over a prepared line's extended epochs: on the line and at least
    ``edge_km`` along it (its cumulative horizontal distance; an epoch without a position adds
    no distance) from both of its ends."""
    e = np.asarray(pr.line.easting_km, float)
    n = np.asarray(pr.line.northing_km, float)
    step = np.hypot(np.diff(e), np.diff(n))
    along = np.concatenate([[0.0], np.cumsum(np.where(np.isfinite(step), step, 0.0))])   # a missing fix: no step
    inside = np.minimum(along, along[-1] - along) >= edge_km
    out = np.zeros(pr.z_ext.size, bool)
    out[pr.inner] = inside
    return out


def filter_line(z_mgal, Q_mgal2, R_cm2s2, dt_s: float, m: int, method: str, noise=None):
    """Non-stationary Kalman smoother on one line: (dg_mgal, dg_std_mgal)."""
    res = kalman_smooth(np.asarray(z_mgal, float), np.asarray(Q_mgal2, float),
                        np.asarray(R_cm2s2, float), dt_s, m=m, method=method, noise=noise)
    return np.asarray(res.dg_mgal), np.asarray(res.dg_std_mgal)


@dataclass
class PreparedLine:
    """One line ready for smoothing: the line, its states held on the full-rate grid, and z
    and R(t) over the line plus ``MARGIN_S`` of run-in on either side (``inner`` selects the
    line itself).  ``idx``/``pq``: the decimated points' indices and Q-level probabilities
    (None for a line that was not identified).  ``q_factor``: where set (shape of ``z_ext``),
    Q(t) is multiplied by it (a test line's level scaled in the lines' interiors,
    :meth:`Filtered.repeat_level_check`)."""

    line: LineData
    s_full: np.ndarray
    s_ext: np.ndarray
    z_ext: np.ndarray
    inner: slice
    r_ext: np.ndarray | None
    idx: np.ndarray | None
    pq: np.ndarray | None
    q_factor: np.ndarray | None = None


def prepare_lines(lines: list[LineData], flights: dict[str, FlightMeasurement], reg, smap, n_q: int, n_r: int,
                  r_local: dict, dt_s: float) -> list[PreparedLine]:
    """States of the smoothed map held at full rate, run-in margins, local levels."""
    state_of, pq_of = {}, {}
    pq_all = smap.probs.reshape(len(smap.probs), n_q, n_r).sum(axis=2)
    off = 0
    for ln, idx in zip(reg.lines, reg.idx):
        nl = len(idx)
        state_of[ln.line] = (np.asarray(idx, int), smap.states[off:off + nl])
        pq_of[ln.line] = pq_all[off:off + nl]
        off += nl
    margin = int(round(MARGIN_S / dt_s))
    out = []
    for ln in lines:
        m = flights[ln.flight]
        n = ln.t_s.size
        idx = pq = None
        if ln.line in state_of:
            idx, st = state_of[ln.line]
            pq = pq_of[ln.line]
            s_full = hold_states(n, idx, st)
        else:
            s_full = np.zeros(n, int)  # documented fallback: the smoothest state
        a0 = max(0, ln.sl.start - margin)
        a1 = min(m.t_s.size, ln.sl.stop + margin)
        s_ext = np.concatenate([np.full(ln.sl.start - a0, s_full[0]), s_full, np.full(a1 - ln.sl.stop, s_full[-1])])
        out.append(PreparedLine(ln, s_full, s_ext, m.z_mgal[a0:a1], slice(ln.sl.start - a0, ln.sl.start - a0 + n),
                                r_local[ln.flight][a0:a1] if r_local else None, idx, pq))
    return out


def em_level_scale(prepared: list[PreparedLine], R_levels, n_r: int, n_dec: int, p) -> float:
    """Factor from the local level R(t) to the EM's level on the regularized band.

    The level of R(t) comes from the EM on the regularized band — what the smoother's pass
    band sees.  The measured local level only gives its shape in time: with coloured GNSS
    velocity noise the band level is many times the white level.  The factor is bounded
    below by ``em_level_scale_min`` (1: only ever scale up) and trusted only from
    ``min_points_adaptive`` decimated points."""
    if not prepared or prepared[0].r_ext is None or n_dec < p.min_points_adaptive:
        return 1.0
    hf = np.concatenate([pr.r_ext[np.asarray(pr.s_ext) % n_r == 0] for pr in prepared])
    if not hf.size:
        return 1.0
    return float(np.clip(R_levels[0] / np.median(hf), p.em_level_scale_min, 1e4))


def q_series(pr: PreparedLine, Q_levels, n_r: int, q_from_posteriors: bool, mean: str = "geometric") -> np.ndarray:
    """Q(t) over the extended line: the held state's level, or — where the map is unsure
    between levels — a level between them (``mean`` of the levels weighted by the smoothed
    probabilities: 'geometric' or 'arithmetic'), changing smoothly between decimated points
    instead of jumping at the hold boundaries."""
    q = Q_levels[pr.s_ext // n_r]
    if q_from_posteriors and pr.pq is not None:
        if mean == "arithmetic":
            lq = np.log(pr.pq @ np.asarray(Q_levels, float))
        else:
            lq = pr.pq @ np.log(Q_levels)
        q = np.exp(np.interp(np.arange(len(pr.s_ext)) - pr.inner.start, pr.idx, lq))
    return q


@dataclass
class Filtered:
    """Result of :func:`filter_survey`.

    Attributes
    ----------
    table : DataFrame
        One row per GNSS epoch on the lines (the columns of ``lines.parquet`` before leveling).
    Q_levels : ndarray
        The Q levels used (after the refinement).
    level_fit : app.core.level_ml.LevelFit or None
    r_scale : float
        :func:`em_level_scale`.
    smooth_lift_cap : dict or None
        When the smoothest level was lifted above the stationary model's and brought down to it
        (``refine_lift_max_stationary``): the lifted, stationary, EM and used levels (mGal²).
    """

    table: pd.DataFrame
    Q_levels: np.ndarray
    level_fit: object
    r_scale: float
    r_stationary: float = float("nan")
    prepared: list | None = None
    Q_stationary: float = float("nan")
    Q_stationary_used: float = float("nan")
    r_lines: list | None = None
    n_r: int = 1
    std_level_factor: float | None = None
    std_level_reason: str | None = None
    std_repeat_tracks: dict | None = None
    smooth_lift_cap: dict | None = None
    unlearned_levels: dict | None = None
    noisy_passes: dict | None = None
    repeat_level: dict | None = None
    rough_level: dict | None = None
    level_scale: float = 1.0
    crossover_check: dict | None = None
    crossover_factor: float = 1.0
    noise_floor: dict | None = None

    def noise_for(self, base):
        """The noise model these lines were smoothed with: ``base`` (the survey's fitted model),
        with the crossover noise floor (:attr:`noise_floor`, stage 8's check) where it applied."""
        if not (self.noise_floor or {}).get("applied"):
            return base
        return with_white_floor(base if base is not None else white_velocity(float(self.noise_floor["dt_s"])),
                                float(self.noise_floor["weight_mgal2"]))

    def fitted_levels(self) -> np.ndarray:
        """The levels as the refinement left them (mGal²): :attr:`Q_levels` without the
        repeat level check's factor, the crossover level check's and the analyst's
        ``anomaly_level_scale``, and with the
        roughest level before ``rough_level_factor`` raised it (a filter job's warm start, the
        report's ``Q_mgal2``)."""
        q = np.asarray(self.Q_levels, float) / (float((self.repeat_level or {}).get("factor", 1.0))
                                                * float(self.level_scale) * float(self.crossover_factor))
        if self.rough_level is not None:
            q = q.copy()
            q[-1] = float(self.rough_level["lifted_mgal2"])
        return q

    def report(self, p) -> dict | None:
        """The report's ``level_refinement`` section."""
        f = self.level_fit
        scale = {"anomaly_level_scale": float(self.level_scale), "crossover_level_check": self.crossover_check,
                 "crossover_noise_floor": self.noise_floor}
        if f is None:   # no refinement (refine_levels off): still say how the std was widened
            return ({"std_level_factor": self.std_level_factor, "std_level_reason": self.std_level_reason,
                     "std_repeat_tracks": self.std_repeat_tracks, "noisy_passes_rescaled": self.noisy_passes,
                     "repeat_level_check": self.repeat_level, **scale}
                    if (self.std_level_reason or self.noisy_passes or self.repeat_level or self.level_scale != 1.0
                        or self.crossover_check is not None or self.noise_floor is not None)
                    else None)
        # the refinement's levels (a filter job's warm start: it repeats the check on them); the
        # repeat level check's factor and the rough level's factor, where they changed them, are in
        # their own sections
        q_refined = self.fitted_levels()
        return {"Q_mgal2": q_refined.tolist(), "Q_full_rate_ml_mgal2": np.asarray(f.Q_mgal2).tolist(),
                "lift_only": bool(p.refine_lift_only), "R_local_scale": self.r_scale, "noise_model": p.noise_model,
                "loglik_gain": f.loglik - f.loglik_start, "n_epochs": f.n_epochs, "n_evaluations": f.n_evaluations,
                "Q_stationary_mgal2": self.Q_stationary, "Q_stationary_used_mgal2": self.Q_stationary_used,
                "std_level_factor": self.std_level_factor,
                "std_level_reason": self.std_level_reason, "std_repeat_tracks": self.std_repeat_tracks,
                "noisy_passes_rescaled": self.noisy_passes, "repeat_level_check": self.repeat_level,
                "smooth_lift_capped": self.smooth_lift_cap, "unlearned_levels": self.unlearned_levels,
                "rough_level": self.rough_level, **scale}

    def estimate_q(self, pr: PreparedLine, q_from_posteriors: bool) -> np.ndarray:
        """Q(t) over the extended line as the estimate uses it: the one level, or
        :func:`q_series` of the levels (times the line's ``q_factor`` where set)."""
        q = (np.full(pr.z_ext.size, float(self.Q_levels[0])) if len(self.Q_levels) == 1 else
             q_series(pr, self.Q_levels, self.n_r, q_from_posteriors))
        return q if pr.q_factor is None else q * pr.q_factor

    def level_spread_std(self, dt_s: float, m: int, method: str, noise, factor: float,
                         n_points: int | None = None, min_points: int | None = None,
                         q_from_posteriors: bool = True, repeat_min_samples: float | None = None,
                         fir_period_s: float = 100.0, repeat_significance: float = 0.1,
                         min_contrast: float | None = None, em_levels_mgal2=None) -> None:
        """Levels learned from too few points: widen ``dg_std_mgal`` by the spread of the
        estimates with the Q levels scaled by 1/f and f (:func:`app.core.smoother.level_spread_std_mgal`,
        ``std_level_factor`` = f); the report's ``level_refinement.std_level_factor`` and
        ``std_level_reason`` say so.  It applies with one anomaly level (too few decimated
        points for two), and with ``n_q`` levels when the EM learned them from fewer than
        ``n_q × min_points`` decimated points (``n_points``): fewer points per level than one
        level needs, or levels the EM did not tell apart (of the levels as learned,
        ``em_levels_mgal2`` — before any refinement lifts one —, the largest within
        ``min_contrast`` of the smallest: the map then says nothing of where the anomaly is
        rougher, and the level is as unsure as one level's).  Q(t) is the estimate's (the
        levels' geometric mean under the map's probabilities with ``q_from_posteriors``),
        scaled as a whole.  With
        ``repeat_min_samples``, repeat tracks that measure their own error get
        :meth:`repeat_calibrated_std` instead (``fir_period_s``: the length of one independent
        stretch; ``repeat_significance``: the level its smoothing part must pass).  Run for the
        order that is used only."""
        n_q = len(self.Q_levels)
        few = n_q > 1 and n_points is not None and min_points is not None and n_points < n_q * min_points
        learned = np.asarray(self.Q_levels if em_levels_mgal2 is None else em_levels_mgal2, dtype=float)
        contrast = float(learned.max() / learned.min()) if n_q > 1 and learned.min() > 0 else np.inf
        alike = n_q > 1 and not few and min_contrast is not None and contrast < min_contrast
        if (n_q != 1 and not few and not alike) or factor <= 1.0 or not self.prepared or self.r_lines is None:
            if repeat_min_samples is not None and self.prepared:
                self.repeat_noise_floor(repeat_min_samples, fir_period_s, repeat_significance)
            return
        reason = ("one anomaly level" if n_q == 1 else
                  f"{n_q} anomaly levels from {n_points} decimated points (< {n_q} x {min_points})" if few else
                  f"{n_q} anomaly levels within a factor {contrast:.2f} of each other (< {min_contrast:g}): "
                  "the map does not tell them apart")
        done, floors = (self.repeat_calibrated_std(dt_s, m, method, noise, factor, q_from_posteriors,
                                                   repeat_min_samples, fir_period_s, repeat_significance)
                        if repeat_min_samples is not None else (set(), {}))
        col = self.table["dg_std_mgal"].to_numpy().copy()
        off = 0
        spread = False
        for i, (pr, r) in enumerate(zip(self.prepared, self.r_lines)):
            n = pr.inner.stop - pr.inner.start
            if i not in done:
                q = self.estimate_q(pr, q_from_posteriors)
                res = level_spread_std_mgal(pr.z_ext, q, r, dt_s, factor, m=m, method=method, noise=noise)
                # a pass whose own noise the repeats measured above its posterior: at least that
                floor = floors.get(i, 1.0) * col[off:off + n]
                col[off:off + n] = np.maximum(np.maximum(col[off:off + n], np.asarray(res.dg_std_mgal)[pr.inner]),
                                              floor)
                spread = True
            off += n
        self.table["dg_std_mgal"] = col
        self.std_level_factor = float(factor) if spread else None
        self.std_level_reason = reason
        if done:
            self.std_level_reason += ("; the repeat tracks' std sized by their passes' error "
                                      "(level_refinement.std_repeat_tracks)" + ("" if spread else " alone"))

    def repeat_calibrated_std(self, dt_s: float, m: int, method: str, noise, factor: float,
                              q_from_posteriors: bool, min_samples: float, period_s: float,
                              significance: float = 0.1) -> set:
        """Where repeat passes measure their error, their ``dg_std_mgal`` widened to it
        (never narrowed: the measure is noisy and misses what the less-smoothed estimate
        also smooths away) instead of by the levels' spread.  Per repeat track: the passes'
        scatter of the estimate (the noise part) and of its difference from the estimate at
        ``factor`` × Q (:func:`app.core.accuracy.repeat_error_parts`: the smoothing part,
        which the passes share); each pass's std is multiplied by
        ``c_i = max(c, sqrt(ρ_i + smoothing / mean σ²))``, ``c = max(1, sqrt((noise +
        smoothing) / mean σ²))`` the track's (σ the posterior std at the passes' common points,
        ``ρ_i`` the pass's own noise over its posterior,
        :func:`app.core.accuracy.repeat_pass_noise_ratio`: a pass through a turbulent stretch
        carries more than the others), so it keeps its shape (wider at line ends and holes).  A
        track needs ``min_samples`` independent stretches (``period_s`` of flight each,
        times passes − 1), and a smoothing part significantly above 0 (one-sided p below
        ``significance``, :meth:`app.core.accuracy.RepeatErrorParts.smoothing_p_value`): where
        the passes' shared difference is lost in their noise the measure says nothing of the
        error they share and the track keeps the spread (test line, seed 3: 2σ coverage 0.75
        sized by its passes, 0.90 with the spread) — but not below each pass's own noise where
        the passes' scatter exceeds the posterior significantly
        (:func:`app.core.accuracy.noise_excess_p_value` of the mean ``ρ_i`` below
        ``significance``; the floor ``max(1, sqrt(ρ_i))`` × σ_i).  Lines off the tracks are left to the
        spread: a track says little about the rest of a survey (one repeat line in the plains of a mountain survey).
        Returns the indices of the prepared lines done and the floors' factors by line index;
        ``std_repeat_tracks`` gives the figures per track for the report."""
        std = self.table["dg_std_mgal"].to_numpy().copy()
        done, figures, floors = set(), {}, {}
        for track, passes in self._repeat_tracks(figures, "level spread kept").items():
            xs, ds, ss, geo = [], [], [], []
            for i, off, n in passes:
                pr, r = self.prepared[i], self.r_lines[i]
                q = self.estimate_q(pr, q_from_posteriors)
                x_lo = filter_line(pr.z_ext, q, r, dt_s, m, method, noise)[0][pr.inner]
                x_hi = filter_line(pr.z_ext, factor * q, r, dt_s, m, method, noise)[0][pr.inner]
                xs.append(x_lo)
                ds.append(x_lo - x_hi)
                ss.append(std[off:off + n] ** 2)
                geo.append((pr.line.easting_km, pr.line.northing_km))
            try:
                acc = [repeat_line_accuracy([(e, nn, v) for (e, nn), v in zip(geo, vals)])
                       for vals in (xs, ds, ss)]
            except ValueError:
                continue
            parts = repeat_error_parts(acc[0].values_mgal, acc[1].values_mgal)
            samples = self._track_stretches(acc[0], passes, period_s)
            post_v = float(np.mean(acc[2].values_mgal))
            if samples < min_samples or not post_v > 0:
                continue
            fig = {"scale": None, "noise_part_mgal": float(np.sqrt(parts.noise_var_mgal2)),
                   "smoothing_part_mgal": float(np.sqrt(parts.smoothing_var_mgal2)),
                   "posterior_mgal": float(np.sqrt(post_v)), "passes": parts.n_repeats,
                   "pass_lines": self._pass_lines(passes),
                   "independent_stretches": float(samples), "versus_q_factor": float(factor)}
            figures[str(track)] = fig
            fig["smoothing_p_value"] = p_smooth = parts.smoothing_p_value(max(1.0, samples / (parts.n_repeats - 1)))
            # each pass's own noise (a pass through a turbulent stretch carries more than the
            # others): the passes' scatter of the estimate, split by pass
            ratio = _pass_noise_ratio(acc[0].values_mgal, acc[2].values_mgal, post_v)
            fig["pass_noise_ratio"] = [float(x) for x in ratio]
            if not (parts.smoothing_var_mgal2 > 0 and p_smooth < significance):
                # the passes' shared difference is lost in their noise: the measure says
                # nothing of the error they share, and the level spread stays; but the
                # noise the passes show is measured, and where it exceeds the posterior
                # significantly each pass's std is widened to at least its own noise
                fig["reason"] = (f"smoothing part lost in the passes' noise (p = {p_smooth:.3g}, needs "
                                 f"< {significance:g}): level spread kept")
                c_pass = _noise_floor(fig, ratio, parts.noise_var_mgal2, post_v, samples, significance)
                for (i, _, _), c in zip(passes, [] if c_pass is None else c_pass):
                    floors[i] = float(c)
                continue
            # the track's scale, and more on a pass whose own noise exceeds the track's
            fig["scale"] = scale = parts.std_scale(post_v)
            c_pass = _record_pass_scales(fig, repeat_pass_std_scales(ratio, scale, parts.smoothing_var_mgal2 / post_v),
                                         ratio)
            for (i, off, n), c in zip(passes, c_pass):
                std[off:off + n] *= c
                done.add(i)
        self.table["dg_std_mgal"] = std
        self.std_repeat_tracks = figures or None
        return done, floors

    def _repeat_tracks(self, figures: dict, kept: str) -> dict:
        """The repeat tracks among the prepared lines with two passes or more: track → list of
        (line index, offset in the table, epochs).  A track whose passes lie apart across it is
        left out, its reason in ``figures`` (with what the std then keeps, ``kept``)."""
        tracks: dict = {}
        off = 0
        for i, pr in enumerate(self.prepared):
            n = pr.inner.stop - pr.inner.start
            if pr.line is not None and pr.line.kind == "repeat" and pr.line.track is not None:
                tracks.setdefault(pr.line.track, []).append((i, off, n))
            off += n
        out = {}
        for track, passes in tracks.items():
            if len(passes) < 2:
                continue
            spread = across_track_spread_km([self.prepared[i].line.easting_km for i, _, _ in passes],
                                            [self.prepared[i].line.northing_km for i, _, _ in passes])
            if spread > REPEAT_MAX_SPREAD_KM:
                # not repeats of one track: their scatter holds the anomaly's change across it
                figures[str(track)] = {"scale": None, "passes": len(passes), "across_track_spread_km": spread,
                                       "reason": f"passes {spread:.2f} km apart across the track (more than "
                                                 f"{REPEAT_MAX_SPREAD_KM} km): not repeats, {kept}"}
                continue
            out[track] = passes
        return out

    def _pass_lines(self, passes: list) -> list:
        """The line ids of a track's passes, in the order of its per-pass figures."""
        return [str(getattr(self.prepared[i].line, "line", i)) for i, _, _ in passes]

    def _track_stretches(self, acc, passes: list, period_s: float) -> float:
        """Independent stretches of a track's scatter: its common length over the distance one
        ``period_s`` of flight spans, times passes − 1 (the scatter's degrees of freedom)."""
        length_m = 1000.0 * float(acc.along_km[-1] - acc.along_km[0])
        speed = float(np.mean([self.prepared[i].line.speed_ms for i, _, _ in passes]))
        return length_m / (speed * period_s) * (acc.n_repeats - 1)

    def rescale_noisy_passes(self, dt_s: float, m: int, method: str, noise, q_from_posteriors: bool,
                             min_samples: float, period_s: float, significance: float = 0.1) -> None:
        """Repeat passes that carry more noise than the noise model gave them smoothed again with
        their noise level raised to what they show (before any std is widened).  Per repeat
        track with ``min_samples`` independent stretches of ``period_s``: each pass's noise
        over its posterior, ρ_i (:func:`app.core.accuracy.repeat_pass_noise_ratio`, from the
        passes' departures from each other); where the passes' mean ρ exceeds 1 at p below
        ``significance`` (:func:`app.core.accuracy.noise_excess_p_value`), every pass with
        ρ_i > 1 is smoothed again with R(t) × ρ_i — a pass flown through turbulence is smoothed
        more, as its noise asks — and kept, with the new smoother's posterior std, where its
        departure from the other passes falls by ``NOISY_PASS_MIN_FALL`` or more (a departure
        that more smoothing does not remove is not noise of its own: generated test line 56's
        third pass, ρ = 3.5, rose 7.0 → 9.2 mGal from the truth smoothed so).  Passes with
        ρ_i ≤ 1 are left as they are (never less smoothing than the model's).  The report's
        ``level_refinement.noisy_passes_rescaled`` gives each track's figures."""
        if not self.prepared or self.r_lines is None:
            return
        est = self.table["dg_mgal"].to_numpy().copy()
        std = self.table["dg_std_mgal"].to_numpy().copy()
        rcol = self.table["R_cm2s2"].to_numpy().copy()
        figures: dict = {}
        for track, passes in self._repeat_tracks({}, "").items():
            sc = self._track_scatter(passes, est, std, min_samples, period_s)
            if sc is None:
                continue
            geo, acc, samples, post_v, ratio = sc
            p_val = noise_excess_p_value(float(np.mean(ratio)), 1.0, samples)
            fig = {"pass_lines": self._pass_lines(passes), "pass_noise_ratio": [float(x) for x in ratio],
                   "noise_p_value": float(p_val), "tried": [], "rescaled": []}
            figures[str(track)] = fig
            if not p_val < significance:
                continue
            trial, runs = est.copy(), {}
            for (i, off, n), rho in zip(passes, ratio):
                if rho > 1.0:
                    pr = self.prepared[i]
                    r = self.r_lines[i] * float(rho)
                    x, s = filter_line(pr.z_ext, self.estimate_q(pr, q_from_posteriors), r, dt_s, m, method, noise)
                    runs[i] = (float(rho), r, x[pr.inner], s[pr.inner])
                    trial[off:off + n] = x[pr.inner]
            if not runs:
                continue
            moved = repeat_line_accuracy([(e, nn, trial[off:off + n]) for (e, nn), (_, off, n) in zip(geo, passes)])
            # kept where the pass departs clearly less from the other passes (as they were): noise
            # of its own smoothed away, not anomaly detail (a slow departure more smoothing does not
            # remove, which a smoother estimate meets only by sharing the others' smoothing error)
            post = _posterior_at(acc[0].values_mgal, acc[1].values_mgal, post_v)
            before = repeat_pass_departures(acc[0].values_mgal, acc[0].values_mgal, post)
            after = repeat_pass_departures(moved.values_mgal, acc[0].values_mgal, post)
            for k, (i, off, n) in enumerate(passes):
                if i not in runs:
                    continue
                rho, r, x, s = runs[i]
                entry = {"line": self._pass_lines([(i, off, n)])[0], "R_factor": rho,
                         "departure_before": float(before[k]), "departure_after": float(after[k])}
                fig["tried"].append(entry)
                if not after[k] < (1.0 - NOISY_PASS_MIN_FALL) * before[k]:
                    continue
                est[off:off + n], std[off:off + n], rcol[off:off + n] = x, s, r[self.prepared[i].inner]
                self.r_lines[i] = r
                fig["rescaled"].append(entry)
        self.table["dg_mgal"] = est
        self.table["dg_unleveled_mgal"] = est
        self.table["dg_std_mgal"] = std
        self.table["R_cm2s2"] = rcol
        self.noisy_passes = figures or None

    def repeat_level_check(self, dt_s: float, m: int, method: str, noise, q_from_posteriors: bool, factors,
                           significance: float, ref_period_s: float, ref_periods: float, min_passes: int,
                           period_s: float = 100.0, reference_q_factor: float | None = None,
                           edge_km: float = 0.0) -> None:
        """A test-line survey's anomaly level chosen by its repeat passes (in place; before any
        std is widened).  Each factor f of ``factors`` scales Q(t) as a whole; the repeat passes
        (tracks of ``min_passes`` or more) are smoothed at f·Q(t), and each pass is compared with
        the other passes' reference by :func:`app.core.model_check.leave_one_out_msd_mgal2`: the
        passes share the anomaly, not the noise, so the figure ranks the levels by their error
        against the truth, up to the reference's own noise (the same for every f) and smoothing
        error.  The reference is each pass smoothed at ``reference_q_factor`` × Q(t) under the
        noise model (a level far above the estimate's: it keeps most of what the estimate rounds
        off and, knowing the noise's shape, carries a fraction of a low-pass's noise), or, with
        ``reference_q_factor`` None, a light low-pass of z (FIR of z at ``ref_period_s``, a
        kernel of ``ref_periods`` periods).  Only positions at least ``edge_km`` from the ends
        of each track's common stretch are compared (all of them where fewer than three blocks
        would remain): near the ends the smoother sees the anomaly from one side only and the
        run-in's manoeuvres, and the level that suits them is not the one the line needs.  The
        factor with the least figure is used where the passes agree significantly better so
        (one-sided p below ``significance``, :func:`app.core.model_check.leave_one_out_msd_test`
        over blocks of ``period_s`` of flight), and only where it was judged: with ``edge_km``
        > 0 every line's Q(t) is multiplied by f ``edge_km`` or more from its ends (its
        ``q_factor``; the ends and run-ins keep theirs), with 0 the levels are scaled; every
        line is then smoothed again.  Else the levels stay.  The report's
        ``level_refinement.repeat_level_check`` gives the figure of each factor.  Only where the
        crossovers are too few to judge the estimate (the caller's condition): a repeat track
        says little about the lines off it."""
        tracks = [t for t in self._repeat_tracks({}, "").values() if len(t) >= min_passes]
        if not tracks or not self.prepared or self.r_lines is None:
            return
        est = self.table["dg_mgal"].to_numpy()
        ids = [i for t in tracks for i, _, _ in t]
        refs = self._level_check_references(ids, dt_s, m, method, noise, q_from_posteriors, ref_period_s, ref_periods,
                                            reference_q_factor)

        def values(f: float) -> list:
            """Per track: (estimate at f·Q(t), reference), each (passes, common positions)."""
            out = []
            for passes in tracks:
                geo = [(self.prepared[i].line.easting_km, self.prepared[i].line.northing_km) for i, _, _ in passes]
                cols = []
                for i, off, n in passes:
                    pr = self.prepared[i]
                    x = (est[off:off + n] if f == 1.0 else
                         filter_line(pr.z_ext, f * self.estimate_q(pr, q_from_posteriors), self.r_lines[i], dt_s, m,
                                     method, noise)[0][pr.inner])
                    ok = np.isfinite(x) & np.isfinite(refs[i])
                    cols.append((np.where(ok, x, np.nan), np.where(ok, refs[i], np.nan)))
                try:
                    acc = [repeat_line_accuracy([(e, nn, c[k]) for (e, nn), c in zip(geo, cols)]) for k in (0, 1)]
                except ValueError:
                    continue
                out.append((acc[0].values_mgal, acc[1].values_mgal, acc[0]))
            return out

        if not values(1.0):
            self.repeat_level = {"factor": 1.0, "reason": "no common stretch of the passes"}
            return
        vals = {f: values(f) for f in sorted({float(x) for x in factors} | {1.0})}
        speed = float(np.mean([self.prepared[i].line.speed_ms for i in ids]))
        step_km = float(np.median(np.diff(vals[1.0][0][2].along_km)))
        block = max(1, int(round(period_s * speed / 1000.0 / step_km)))
        if edge_km > 0 and len({len(v) for v in vals.values()}) == 1:
            # the tracks' interiors (each track's own common stretch less edge_km at either end)
            masks = [_stretch_interior(np.asarray(acc.along_km), edge_km, 3 * block) for _, _, acc in vals[1.0]]
            vals = {f: [(x[:, k], r[:, k], acc) for (x, r, acc), k in zip(v, masks)] for f, v in vals.items()}
            if all(k.all() for k in masks):   # stretches too short for an interior: judged, and used, whole
                edge_km = 0.0
        else:
            edge_km = 0.0
        msd = {f: float(np.nanmean(np.concatenate([leave_one_out_msd_mgal2(x, r) for x, r, _ in v])))
               for f, v in vals.items()}
        tests = {f: leave_one_out_msd_test([x for x, _, _ in vals[f]], [x for x, _, _ in vals[1.0]],
                                           [r for _, r, _ in vals[1.0]], block)
                 for f in vals if f != 1.0}
        ref_name = (f"estimate at {reference_q_factor:g} x Q(t)" if reference_q_factor is not None else
                    f"{ref_period_s:g} s low-pass of z")
        rep = {"factors": list(vals), "msd_mgal2": [msd[f] for f in vals],
               "p_values": {f"{f:g}": tests[f][1] for f in tests}, "significance": float(significance),
               "block_positions": block, "block_s": float(period_s), "reference": ref_name,
               **({"reference_q_factor": float(reference_q_factor)} if reference_q_factor is not None else
                  {"reference_period_s": float(ref_period_s)}),
               "edge_km": float(edge_km), "positions": int(sum(x.shape[1] for x, _, _ in vals[1.0])),
               "factor": 1.0}
        self.repeat_level = rep
        better = [f for f in tests if tests[f][0] < 0 and tests[f][1] < significance]
        if not better:
            rep["reason"] = "no other level makes the passes agree significantly better"
            return
        best = min(better, key=lambda f: msd[f])
        rep["factor"] = best
        rep["reason"] = (f"the passes agree better with the others' {ref_name} at {best:g} x Q "
                         f"({msd[best]:.4g} against {msd[1.0]:.4g} mGal², the reference's noise included; one-sided "
                         f"p = {tests[best][1]:.3g} over {block}-position blocks)")
        if edge_km > 0:
            # used where it was judged: Q(t) scaled in each line's interior (edge_km or more from
            # its ends), the ends and run-ins kept at the level they had
            for i, pr in enumerate(self.prepared):
                self.prepared[i] = replace(pr, q_factor=(1.0 if pr.q_factor is None else pr.q_factor)
                                           * np.where(_interior(pr, edge_km), best, 1.0))
            rep["scaled"] = f"Q(t) x {best:g} in the lines' interiors ({edge_km:g} km or more from their ends)"
        else:
            self.Q_levels = np.asarray(self.Q_levels, float) * best
            rep["Q_used_mgal2"] = self.Q_levels.tolist()
        self._smooth_again(dt_s, m, method, noise, q_from_posteriors)

    def _level_check_references(self, ids: list, dt_s: float, m: int, method: str, noise, q_from_posteriors: bool,
                                ref_period_s: float, ref_periods: float, reference_q_factor: float | None) -> dict:
        """:meth:`repeat_level_check`'s reference per prepared line index of ``ids``: the line
        smoothed at ``reference_q_factor`` × Q(t), or (None) the FIR low-pass of z at
        ``ref_period_s`` with a kernel of ``ref_periods`` periods (mGal, the line's epochs)."""
        if reference_q_factor is None:
            return {i: fir_lowpass_mgal(self.prepared[i].line.z_mgal, dt_s, ref_period_s, ref_periods) for i in ids}
        return dict(zip(ids, self._smoothed_at(ids, float(reference_q_factor), dt_s, m, method, noise,
                                               q_from_posteriors)))

    def _smoothed_at(self, ids: list, factor: float, dt_s: float, m: int, method: str, noise,
                     q_from_posteriors: bool) -> list:
        """The prepared lines ``ids`` smoothed at ``factor`` × their Q(t) (:meth:`estimate_q`) with
        their R(t): one array per line over the line's own epochs (mGal), in the order of ``ids``."""
        return [x for x, _ in self._smooth_lines(ids, factor, dt_s, m, method, noise, q_from_posteriors)]

    def _smooth_lines(self, ids: list, factor: float, dt_s: float, m: int, method: str, noise,
                      q_from_posteriors: bool) -> list:
        """The prepared lines ``ids`` smoothed at ``factor`` × Q(t) with their R(t) under ``noise``:
        one ``(dg_mgal, dg_std_mgal)`` pair per line over the line's own epochs, in the order of ``ids``."""
        def smooth(i: int):
            pr = self.prepared[i]
            x, sd = filter_line(pr.z_ext, factor * self.estimate_q(pr, q_from_posteriors), self.r_lines[i], dt_s,
                                m, method, noise)
            return x[pr.inner], sd[pr.inner]
        return list(line_map()(smooth, ids))

    def smoothed_at(self, factor: float, dt_s: float, m: int, method: str, noise, q_from_posteriors: bool) -> list:
        """Every line smoothed at ``factor`` × its Q(t) with its R(t): one array per line over the
        line's own epochs (mGal), in the table's line order."""
        return self._smoothed_at(list(range(len(self.prepared))), factor, dt_s, m, method, noise, q_from_posteriors)

    def smoothed_with(self, noise, dt_s: float, m: int, method: str, q_from_posteriors: bool) -> list:
        """Every line smoothed at its Q(t) and R(t) under the noise model ``noise``: one
        ``(dg_mgal, dg_std_mgal)`` pair per line over the line's own epochs, in the table's line order."""
        return self._smooth_lines(list(range(len(self.prepared))), 1.0, dt_s, m, method, noise, q_from_posteriors)

    def add_noise_floor(self, floor: dict, noise, dt_s: float, m: int, method: str, q_from_posteriors: bool) -> None:
        """The crossover noise floor applied (in place): :attr:`noise_floor` set to ``floor`` (its
        report) and every line smoothed again under ``noise`` (the model with the floor)."""
        self.noise_floor = floor
        self._smooth_again(dt_s, m, method, noise, q_from_posteriors)

    def scale_levels(self, factor: float, dt_s: float, m: int, method: str, noise, q_from_posteriors: bool) -> None:
        """Every anomaly level × ``factor`` (the crossover level check's, :attr:`crossover_factor`)
        and every line smoothed again at it (in place)."""
        self.Q_levels = np.asarray(self.Q_levels, float) * float(factor)
        self.crossover_factor *= float(factor)
        self._smooth_again(dt_s, m, method, noise, q_from_posteriors)

    def _smooth_again(self, dt_s: float, m: int, method: str, noise, q_from_posteriors: bool) -> None:
        """Every line smoothed again at its Q(t) (:meth:`estimate_q`): ``dg_mgal``,
        ``dg_unleveled_mgal``, ``dg_std_mgal`` and ``Q_mgal2`` replaced (in place)."""
        def smooth(i: int):
            pr = self.prepared[i]
            q = self.estimate_q(pr, q_from_posteriors)
            return q, filter_line(pr.z_ext, q, self.r_lines[i], dt_s, m, method, noise)

        cols = {c: self.table[c].to_numpy().copy() for c in ("dg_mgal", "dg_std_mgal", "Q_mgal2")}
        off = 0
        for i, (q, (x, s)) in enumerate(line_map()(smooth, range(len(self.prepared)))):
            pr = self.prepared[i]
            n = pr.inner.stop - pr.inner.start
            cols["dg_mgal"][off:off + n], cols["dg_std_mgal"][off:off + n] = x[pr.inner], s[pr.inner]
            cols["Q_mgal2"][off:off + n] = q[pr.inner]
            off += n
        for c, v in cols.items():
            self.table[c] = v
        self.table["dg_unleveled_mgal"] = cols["dg_mgal"]

    def repeat_reference(self, dt_s: float, m: int, method: str, noise, q_from_posteriors: bool, factor: float,
                         min_passes: int) -> None:
        """The repeat blend's reference (in place: column ``dg_repeat_reference_mgal``, NaN off the
        repeat tracks of ``min_passes`` or more): each pass smoothed again at ``factor``·Q(t) under
        the fitted noise model and its R(t).

        The blend (stage 9, :func:`app.pipeline.stages.choice.repeat_blend`) compares each pass
        with the mean reference of the *other* passes: what it needs of the reference is noise
        independent between passes (any per-pass estimate has that) and little of the anomaly
        rounded off where the estimate and FIR 100 s differ.  A light low-pass of z keeps the
        anomaly but, at 2 Hz, carries ~13 mGal of noise against 1–2 mGal between the two
        estimates, and the weight scatters over most of [0, 1] with four passes.  The smoother at
        a level far above the estimate's (at 300·Q about 2.6× its bandwidth for m = 2 under white
        velocity noise, where the bandwidth goes as Q^(1/6)) keeps
        most of the anomaly the estimate rounds off and, knowing the noise's shape, passes a
        fraction of the low-pass's noise."""
        tracks = [t for t in self._repeat_tracks({}, "").values() if len(t) >= min_passes]
        col = np.full(len(self.table), np.nan)
        if tracks and self.prepared and self.r_lines is not None:
            passes = [(i, off, n) for t in tracks for i, off, n in t]
            smoothed = self._smoothed_at([i for i, _, _ in passes], factor, dt_s, m, method, noise, q_from_posteriors)
            for (_, off, n), x in zip(passes, smoothed):
                col[off:off + n] = x
        self.table["dg_repeat_reference_mgal"] = col

    def _track_scatter(self, passes: list, est: np.ndarray, std: np.ndarray, min_samples: float, period_s: float):
        """A repeat track's passes of the estimate ``est`` and of the variance ``std²`` at their
        common points (:func:`app.core.accuracy.repeat_line_accuracy`), with the track's
        independent stretches, the mean posterior variance there and each pass's noise ratio
        ρ_i: (geo, (accuracy of est, of std²), stretches, mean variance, ρ); None where the
        passes have no common points, fewer than ``min_samples`` stretches of ``period_s`` or
        no positive variance."""
        geo = [(self.prepared[i].line.easting_km, self.prepared[i].line.northing_km) for i, _, _ in passes]
        try:
            acc = [repeat_line_accuracy([(e, nn, col[off:off + n]) for (e, nn), (_, off, n) in zip(geo, passes)])
                   for col in (est, std ** 2)]
        except ValueError:
            return None
        samples = self._track_stretches(acc[0], passes, period_s)
        post_v = float(np.mean(acc[1].values_mgal))
        if samples < min_samples or not post_v > 0:
            return None
        return geo, acc, samples, post_v, _pass_noise_ratio(acc[0].values_mgal, acc[1].values_mgal, post_v)

    def repeat_noise_floor(self, min_samples: float, period_s: float, significance: float = 0.1) -> None:
        """Where the std is not sized by the repeats (two levels learned from enough points:
        :meth:`level_spread_std` leaves it), a repeat pass's ``dg_std_mgal`` is still widened
        to its own noise when the passes' scatter exceeds the posterior significantly: the
        factor ``max(1, sqrt(ρ_i))``, ρ_i the pass's noise over its posterior
        (:func:`app.core.accuracy.repeat_pass_noise_ratio`; their mean's
        :func:`app.core.accuracy.noise_excess_p_value` below ``significance``; a track needs
        ``min_samples`` independent stretches of ``period_s``).  The passes' scatter measures
        the noise part of their error directly; a pass through a turbulent stretch carries more
        than the noise model gave it.  Never narrowed; the report's
        ``level_refinement.std_repeat_tracks`` gives the figures."""
        if not self.prepared:
            return
        std = self.table["dg_std_mgal"].to_numpy().copy()
        est = self.table["dg_mgal"].to_numpy()
        figures: dict = {}
        for track, passes in self._repeat_tracks(figures, "std left as it is").items():
            sc = self._track_scatter(passes, est, std, min_samples, period_s)
            if sc is None:
                continue
            _, acc, samples, post_v, ratio = sc
            noise_v = float(acc[0].epsilon_mgal) ** 2
            fig = figures[str(track)] = {
                "scale": None, "noise_part_mgal": float(np.sqrt(noise_v)), "posterior_mgal": float(np.sqrt(post_v)),
                "passes": len(passes), "pass_lines": self._pass_lines(passes), "independent_stretches": float(samples),
                "pass_noise_ratio": [float(x) for x in ratio],
                "reason": "two levels from enough points: no level spread"}
            c_pass = _noise_floor(fig, ratio, noise_v, post_v, samples, significance)
            if c_pass is None:
                continue
            for (_, off, n), c in zip(passes, c_pass):
                std[off:off + n] *= c
        self.table["dg_std_mgal"] = std
        self.std_repeat_tracks = figures or None

    def mixture_std(self, dt_s: float, m: int, method: str, noise) -> None:
        """Replace ``dg_std_mgal`` by the std of the mixture of levels (``std_state_mixture``),
        where the map is unsure of the level: the larger of two measures of it at each epoch —
        the smoother under the probability-weighted *arithmetic* mean of the Q levels (not
        the geometric mean the estimate uses), and the law of total variance over the
        smoothers of each level held along the whole line, weighted by the map's
        probabilities (:func:`app.core.smoother.mixture_std_mgal`, about the estimate).
        Neither alone is cautious enough everywhere: where the map is unsure, the first is
        wider; where one level's smoother departs from the estimate, the second.  Run for the
        order that is used only."""
        if len(self.Q_levels) < 2 or not self.prepared or self.r_lines is None:
            return
        col = self.table["dg_std_mgal"].to_numpy().copy()
        est = self.table["dg_mgal"].to_numpy()
        sizes = [pr.inner.stop - pr.inner.start for pr in self.prepared]
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int)

        def line_std(i: int):
            pr, r, off, n = self.prepared[i], self.r_lines[i], int(offsets[i]), sizes[i]
            if pr.pq is None:
                return None
            scale = 1.0 if pr.q_factor is None else pr.q_factor
            q = q_series(pr, self.Q_levels, self.n_r, True, "arithmetic") * scale
            arith = filter_line(pr.z_ext, q, r, dt_s, m, method, noise)[1][pr.inner]
            runs = [filter_line(pr.z_ext, np.full(pr.z_ext.size, qk) * scale, r, dt_s, m, method, noise)
                    for qk in self.Q_levels]
            pos = np.arange(n, dtype=float)
            w = np.array([np.interp(pos, pr.idx, pr.pq[:, k]) for k in range(len(self.Q_levels))])
            total = mixture_std_mgal(est[off:off + n], np.array([x[pr.inner] for x, _ in runs]),
                                     np.array([s[pr.inner] for _, s in runs]), w)
            return np.maximum(arith, total)

        for k, std in enumerate(line_map()(line_std, range(len(self.prepared)))):
            if std is not None:
                col[offsets[k]:offsets[k] + sizes[k]] = std
        self.table["dg_std_mgal"] = col

    def blend_order(self, other_mgal, weight: float) -> None:
        """Blend the other order's estimate into this one (stage 9 step 1, ``order_blend``), in
        place: ``dg_mgal`` = ``dg_unleveled_mgal`` = ``(1 − w)·this + w·other``, its std that of
        the mixture (:func:`app.core.model_check.blend_estimates`).  ``other_mgal``: shape (rows
        of the table,), the same lines and epochs in the same order (both orders' tables come
        from the same prepared lines); where it has no value this estimate stays."""
        other = np.asarray(other_mgal, dtype=float)
        if other.shape != (len(self.table),):
            raise ValueError(f"the other order's estimate has shape {other.shape}, the table {len(self.table)} rows")
        blended, std = blend_estimates(other, self.table["dg_unleveled_mgal"].to_numpy(),
                                       self.table["dg_std_mgal"].to_numpy(), weight)
        self.table["dg_mgal"] = blended
        self.table["dg_unleveled_mgal"] = blended
        self.table["dg_std_mgal"] = std

    def add_stationary(self, dt_s: float, m: int, method: str, noise, p=None) -> None:
        """Fill the ``dg_stationary_mgal`` column (when :func:`filter_survey` skipped it): the
        stationary model — one Q for the whole survey by the full-rate likelihood, the survey's
        typical noise level R (:func:`stationary_level`)."""
        if not np.isfinite(self.Q_stationary):
            self.Q_stationary = stationary_level(self.prepared, self.Q_levels, self.r_stationary, dt_s, m, noise, p)
        # one level for every terrain is at most the roughest terrain's: above the highest level
        # the full-rate likelihood spends Q on noise its one R leaves unexplained (noise
        # episodes), and the baseline passes it (independent generator's seed 39: 140x the
        # highest level, 83 mGal from the truth against the anomaly's std of 20)
        self.Q_stationary_used = float(min(self.Q_stationary, float(np.max(self.Q_levels))))

        def smooth(pr: PreparedLine) -> np.ndarray:
            q = np.full(pr.z_ext.size, self.Q_stationary_used)
            return filter_line(pr.z_ext, q, np.full_like(q, self.r_stationary), dt_s, m, method, noise)[0][pr.inner]

        self.table["dg_stationary_mgal"] = np.concatenate(list(line_map()(smooth, self.prepared)))


def _record_pass_scales(fig: dict, c_pass: np.ndarray, ratio: np.ndarray) -> np.ndarray:
    """Put a track's per-pass std factors in its report figures (``pass_scales``) and name the
    passes widened beyond the track's own factor (``widened_passes``: line, factor, noise over
    the posterior) — what the warning and the report view tell.  Returns ``c_pass``."""
    base = max(1.0, fig.get("scale") or 1.0)
    fig["pass_scales"] = [float(x) for x in c_pass]
    fig["widened_passes"] = [{"line": ln, "scale": float(c), "noise_ratio": float(r)}
                             for ln, c, r in zip(fig["pass_lines"], c_pass, ratio) if c > 1.05 * base]
    return c_pass


def _noise_floor(fig: dict, ratio: np.ndarray, noise_var_mgal2: float, post_var_mgal2: float, dof: float,
                 significance: float) -> np.ndarray | None:
    """The floor of a track's passes at their own noise (factors ``max(1, sqrt(ρ_i))``) when the
    passes' mean noise ratio exceeds 1 at p < ``significance``
    (:func:`app.core.accuracy.noise_excess_p_value`), else None; the test and the decision go in
    the track's report figures ``fig`` (its ``reason`` extended)."""
    fig["noise_p_value"] = p = noise_excess_p_value(float(np.mean(ratio)), 1.0, dof)
    if not p < significance:
        fig["reason"] += f"; the passes' noise not significantly above the posterior (p = {p:.3g})"
        return None
    fig["reason"] += (f"; the passes' noise ({np.sqrt(noise_var_mgal2):.3g} mGal) exceeds the posterior std "
                      f"({np.sqrt(post_var_mgal2):.3g} mGal, p = {p:.3g}): each pass's std at least its own noise")
    return _record_pass_scales(fig, repeat_pass_std_scales(ratio), ratio)


def pass_noise_warnings(tracks: dict | None) -> list[str]:
    """Warnings naming the repeat passes whose std was widened beyond their track's to their
    own noise (``Filtered.std_repeat_tracks``: a pass flown through turbulence the noise model
    did not give it); none where every pass kept the track's scale."""
    out = []
    for track, t in (tracks or {}).items():
        more = t.get("widened_passes")
        if more:
            out.append(f"repeat track {track}: the noise of "
                       + ", ".join(f"pass {w['line']} is {w['noise_ratio']:.3g}x" for w in more)
                       + " its posterior variance (departures from the other passes: more noise than the noise "
                       "model gave it); the std is widened to that noise, and the estimate carries it")
    return out


#: Smallest fall of a repeat pass's departure from the other passes (a fraction) for its
#: smoothing with its own noise level to be kept (:meth:`Filtered.rescale_noisy_passes`).  In
#: simulation a pass with 16× the modelled noise variance falls by 14–78 %, calm passes move by
#: at most 5 % by chance, and a slow 6 mGal swing more smoothing cannot remove by 1 %.
NOISY_PASS_MIN_FALL = 0.10


def rescaled_pass_warnings(tracks: dict | None) -> list[str]:
    """Warnings naming the repeat passes smoothed again with their own noise level
    (``Filtered.noisy_passes``, :meth:`Filtered.rescale_noisy_passes`)."""
    out = []
    for track, t in (tracks or {}).items():
        if t.get("rescaled"):
            out.append(f"repeat track {track}: "
                       + ", ".join(f"pass {r['line']} smoothed with its noise level x {r['R_factor']:.3g}"
                                   for r in t["rescaled"])
                       + " (its departures from the other passes show more noise than the noise model gave it, "
                       "and fall when it is smoothed so)")
    return out


def _posterior_at(values_mgal: np.ndarray, posterior_var_mgal2: np.ndarray, mean_var_mgal2: float) -> np.ndarray:
    """A track's posterior variances at its passes' common points (shape (K, n)); where a hole
    left the two on different points, or a variance is not positive there, their mean
    ``mean_var_mgal2`` (> 0) at every point instead."""
    post = np.asarray(posterior_var_mgal2, float)
    if post.shape != values_mgal.shape or not np.all(post > 0):
        post = np.full(values_mgal.shape[1], mean_var_mgal2)
    return post


def _pass_noise_ratio(values_mgal: np.ndarray, posterior_var_mgal2: np.ndarray, mean_var_mgal2: float) -> np.ndarray:
    """:func:`app.core.accuracy.repeat_pass_noise_ratio` of a track's passes (shape (K, n)) over
    their posterior variances (:func:`_posterior_at`)."""
    return repeat_pass_noise_ratio(values_mgal, _posterior_at(values_mgal, posterior_var_mgal2, mean_var_mgal2))


def rough_level(Q_levels, Q_full_rate_ml, factor: float) -> tuple[np.ndarray, dict | None]:
    """The levels the smoother uses (mGal²), the roughest raised by
    :func:`app.core.level_ml.raise_rough_level` (``rough_level_factor``), and the report's
    ``level_refinement.rough_level`` (None with one level, without a refinement —
    ``Q_full_rate_ml`` None — or with a factor of 1: the levels are kept)."""
    q = np.asarray(Q_levels, float)
    if q.size < 2 or factor == 1.0 or Q_full_rate_ml is None:
        return q, None
    used, raised = raise_rough_level(q, Q_full_rate_ml, factor)
    return used, {"factor": float(factor), "full_rate_ml_mgal2": float(np.asarray(Q_full_rate_ml, float)[-1]),
                  "lifted_mgal2": float(q[-1]), "used_mgal2": float(used[-1]), "raised": bool(raised)}


def stationary_level(prepared: list, Q_levels, r_stationary: float, dt_s: float, m: int, noise, p=None) -> float:
    """The one anomaly level Q of the stationary model, by the full-rate likelihood of the lines
    at the survey's typical noise level (the seed-000 baseline took the smooth state's level,
    which over-smooths every rough stretch)."""
    Qs = np.asarray(Q_levels, float)
    start = float(np.exp(np.mean(np.log(Qs))))
    try:
        fit = refine_levels([pr.z_ext for pr in prepared], [np.zeros(pr.z_ext.size, int) for pr in prepared],
                            np.array([start]), np.array([r_stationary]), dt_s, m,
                            max_epochs=p.refine_max_epochs if p is not None else 100_000, fit_r=False, noise=noise,
                            map_lines=line_map())
        return float(fit.Q_mgal2[0])
    except (ValueError, FloatingPointError):
        return float(Qs[0])


def lifted_levels(Q_ml_mgal2, Q_em_mgal2, unlearned=()) -> tuple[np.ndarray, dict | None]:
    """``refine_lift_only`` (:func:`app.core.level_ml.lift_levels`) and, when a level was left to
    the likelihood (``unlearned``, :func:`app.pipeline.stages.identification.unlearned_levels`),
    the report's ``level_refinement.unlearned_levels`` (None otherwise)."""
    q = lift_levels(Q_ml_mgal2, Q_em_mgal2, unlearned)
    bad = sorted(int(i) for i in unlearned)
    if not bad:
        return q, None
    return q, {"levels": bad, "em_floor_mgal2": [float(x) for x in np.asarray(Q_em_mgal2, float)[bad]],
               "used_mgal2": [float(x) for x in q[bad]],
               "reason": "taken back from the EM's first iterations (identification.level_support.backoff), not "
                         "learned from a terrain: the full-rate likelihood's level under the map, not floored at it"}


def filter_survey(lines: list[LineData], flights: dict[str, FlightMeasurement], fir: dict, ident, smap,
                  r_local: dict, noise, dt_s: float, p, warnings: list, progress=None,
                  stationary: bool = True, q_start=None, q_stationary: float | None = None) -> Filtered:
    """Stage 8 for one identification (order ``ident.m``) and one smoothed map; without
    ``stationary`` the baseline column is left NaN (:meth:`Filtered.add_stationary`).  ``q_start``:
    the Q levels an earlier refinement found (a filter run with other h, ρ starts from them);
    ``q_stationary``: the stationary model's level an earlier run of this order fitted (mGal²;
    it does not depend on h, ρ, so a filter job takes it instead of fitting it again)."""
    em = ident.learned.em
    Qs, Rs = np.asarray(em.Q, float), np.asarray(em.R, float)
    n_r = len(Rs)
    unlearned = None
    prepared = prepare_lines(lines, flights, ident.regularized, smap, len(Qs), n_r, r_local, dt_s)
    r_scale = em_level_scale(prepared, Rs, n_r, ident.n_points, p)
    level_fit = None
    if p.refine_levels:
        try:
            warm = q_start is not None and len(q_start) == len(Qs)
            level_fit = refine_levels([pr.z_ext for pr in prepared], [pr.s_ext for pr in prepared],
                                      np.asarray(q_start, float) if warm else Qs, Rs, dt_s,
                                      ident.m, max_epochs=p.refine_max_epochs,
                                      r_base_lines=[r_scale * pr.r_ext for pr in prepared] if r_local else None,
                                      fit_r=False, noise=noise, simplex_step=0.3 if warm else 1.0,
                                      max_evaluations=8 * len(Qs) if warm else None, map_lines=line_map())
            Qs = np.asarray(level_fit.Q_mgal2, float)
            if p.refine_lift_only:
                # a guard against a collapsed level, not a replacement of the EM's levels (config);
                # the report keeps the likelihood's own levels beside the ones used
                Qs, unlearned = lifted_levels(Qs, em.Q, unlearned_levels(ident, p.level_backoff_floor_min_iteration))
        except (ValueError, FloatingPointError) as exc:
            warnings.append(f"level refinement skipped: {exc}")
    if r_local:
        r_stationary = r_scale * float(np.median(np.concatenate([pr.r_ext for pr in prepared])))
    else:
        r_stationary = float(Rs[0])
    lift_cap = None
    if p.refine_lift_only and p.refine_lift_max_stationary and len(Qs) > 1 and Qs[0] > float(em.Q[0]):
        # the smoothest level lifted: never above the one-level model's full-rate level (the
        # stationary baseline's, fitted here only when needed and kept for the baseline column)
        if q_stationary is None or not (np.isfinite(q_stationary) and q_stationary > 0):
            q_stationary = stationary_level(prepared, Qs, r_stationary, dt_s, ident.m, noise, p)
        lifted = float(Qs[0])
        Qs, capped = cap_lifted_smooth_level(Qs, em.Q, q_stationary)
        if capped:
            lift_cap = {"lifted_mgal2": lifted, "stationary_mgal2": float(q_stationary),
                        "em_mgal2": float(em.Q[0]), "used_mgal2": float(Qs[0])}
    # m = 2's prior falls as ω⁻⁴, faster than a real anomaly toward the cutoff; m = 1's (ω⁻²) does not
    Qs, rough = rough_level(Qs, None if level_fit is None else level_fit.Q_mgal2,
                            p.rough_level_factor if ident.m >= 2 else 1.0)
    # the analyst's smoothing strength (config anomaly_level_scale): the levels as fitted, times it
    Qs = np.asarray(Qs, float) * float(p.anomaly_level_scale)

    def smooth(pr: PreparedLine):
        q = q_series(pr, Qs, n_r, p.q_from_posteriors)
        r = Rs[pr.s_ext % n_r] if pr.r_ext is None else r_scale * pr.r_ext
        return q, r, filter_line(pr.z_ext, q, r, dt_s, ident.m, p.smoother, noise)

    frames, r_lines = [], []
    for i, (pr, (q, r, (dg, std))) in enumerate(zip(prepared, line_map()(smooth, prepared))):
        ln, inner = pr.line, pr.inner
        r_lines.append(r)
        # stationary baseline (seed 000 Fig. 8): one (Q₁, R₁) pair — the smooth state's Q
        # and the survey's typical noise level
        dgs = np.full(pr.z_ext.size, np.nan)
        frames.append(pd.DataFrame({
            "line": ln.line, "flight": ln.flight, "kind": ln.kind, "time": ln.t_s,
            "lat": ln.lat_deg, "lon": ln.lon_deg, "h": ln.h_m,
            "easting_km": ln.easting_km, "northing_km": ln.northing_km,
            "z_mgal": ln.z_mgal, "dg_mgal": dg[inner], "dg_std_mgal": std[inner],
            "dg_unleveled_mgal": dg[inner], "dg_stationary_mgal": dgs[inner],
            "dg_fir_mgal": fir[ln.flight][ln.sl], "state": pr.s_full,
            "Q_mgal2": q[inner], "R_cm2s2": r[inner],
            "track": ln.track,
        }))
        if progress is not None:
            progress((i + 1) / len(prepared))
    out = Filtered(pd.concat(frames, ignore_index=True), np.asarray(Qs, float), level_fit, r_scale, r_stationary,
                   prepared, r_lines=r_lines, n_r=n_r)
    if q_stationary is not None and np.isfinite(q_stationary) and q_stationary > 0:
        out.Q_stationary = float(q_stationary)
    out.smooth_lift_cap = lift_cap
    out.unlearned_levels = unlearned
    out.rough_level = rough
    out.level_scale = float(p.anomaly_level_scale)
    if stationary:
        out.add_stationary(dt_s, ident.m, p.smoother, noise, p)
    return out
