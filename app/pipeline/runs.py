"""Runs of the stages: ``identify`` (measurement → noise → identification) and ``filter``
(NL-means → filtering → model choice → leveling → gridding → outputs).

``process`` is both.  The web's ``identify`` job stores an :class:`Identified`
(:func:`save_identified`) beside its outputs; its ``filter`` job loads it and runs
:func:`run_filter` with the analyst's h, ρ — the EM is not recomputed.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from app.config import SurveyConfig
from app.pipeline.parallel import thread_count
from app.pipeline.stages import storage
from app.pipeline.stages.choice import Candidate, choose_model, choose_order, count_crossovers
from app.pipeline.stages.filtering import (
    filter_survey,
    fir_baseline,
    fir_line_column,
    fir_loss_warnings,
    pass_noise_warnings,
    rescaled_pass_warnings,
)
from app.pipeline.stages.gridding import grid_survey
from app.pipeline.stages.identification import Identification, back_off_levels, identify, level_support
from app.pipeline.stages.level_check import check_levels_at_crossovers
from app.pipeline.stages.leveling import add_common_level_std, level_survey, reading_error_std_mgal
from app.pipeline.stages.lines import SurveyLines, survey_lines
from app.pipeline.stages.measurement import Measurement, measure
from app.pipeline.stages.model_order import candidate_orders, choose_model_order
from app.pipeline.stages.noise import check_noise_corners, check_noise_family, model_noise, noise_episodes
from app.pipeline.stages.outputs import build_report, identification_json, write_outputs
from app.pipeline.stages.products import apply_products, flight_height_table, refresh_bouguer
from app.pipeline.stages.recognition import state_map

Progress = Callable[[str, float, dict | None], None]

#: Stage weights for the overall progress fraction of a ``process`` run (identify: 0–0.75, filter:
#: 0.75–1); a run of part of the stages (:data:`PLANS`) spreads its own stages' weights over 0–1.
STAGE_WEIGHTS = {"ingest": 0.05, "measurement": 0.15, "noise": 0.07, "fir": 0.02, "regularization": 0.04,
                 "learning": 0.34, "recognition": 0.08, "nlmeans": 0.02, "filtering": 0.12, "level_check": 0.01,
                 "choice": 0.02,
                 "leveling": 0.02, "gridding": 0.04, "writing": 0.02}
STAGE_ORDER = list(STAGE_WEIGHTS)
#: The stages each kind of run goes through, known before it starts.
PLANS = {"process": STAGE_ORDER,
         "identify": STAGE_ORDER[:STAGE_ORDER.index("recognition") + 1],
         "filter": ["ingest", *STAGE_ORDER[STAGE_ORDER.index("nlmeans"):]]}
#: Stages run once per anomaly order (the identification of every candidate order; the NL-means and
#: filtering of every order filtered): each run of the group has its own share of the group's weight.
REPEATED_GROUPS = (("regularization", "learning", "recognition"), ("nlmeans", "filtering"))


class Tracker:
    """Progress and timings: ``start(stage)``, ``emit(fraction within, info)``, ``close()``.

    The fraction follows a plan of stages known up front (:data:`PLANS`) with their weights; a
    group of stages run once per anomaly order (:data:`REPEATED_GROUPS`) is announced with
    ``runs(k, n, label)`` and its k-th run fills the k-th n-th of the group's share — the second EM
    run moves the bar on instead of repeating the first's — and the stage is reported as e.g.
    ``learning (m=2, run 2 of 2)``.  The fraction reported never decreases."""

    def __init__(self, progress: Progress | None, plan: list[str] | None = None):
        self.progress = progress
        self.timings: dict[str, float] = {}
        self.plan = list(plan or STAGE_ORDER)
        total = sum(STAGE_WEIGHTS[s] for s in self.plan)
        self._weight = {s: STAGE_WEIGHTS[s] / total for s in self.plan}
        self._stage: str | None = None
        self._t0 = 0.0
        self._last = 0.0
        self._run: tuple[int, int, str] | None = None

    def runs(self, k: int | None, n: int = 1, label: str = "") -> None:
        """The k-th (from 0) of ``n`` runs of a repeated group of stages starts (None: no run)."""
        self._run = None if k is None else (int(k), max(1, int(n)), str(label))

    def start(self, stage: str) -> None:
        self._finish()
        self._stage = stage
        self._t0 = time.perf_counter()
        self.emit(0.0)

    def fraction(self, stage: str, within: float) -> float:
        """The overall fraction at ``within`` (0–1) of ``stage`` in the plan and the current run."""
        if stage not in self._weight:
            return self._last
        before = sum(self._weight[s] for s in self.plan[:self.plan.index(stage)])
        w = self._weight[stage] * min(1.0, max(0.0, float(within)))
        group = [s for g in REPEATED_GROUPS if stage in g for s in g if s in self._weight]
        if not group or self._run is None or self._run[1] == 1:
            return before + w
        k, n, _ = self._run
        g0 = sum(self._weight[s] for s in self.plan[:self.plan.index(group[0])])
        share = sum(self._weight[s] for s in group)
        return g0 + (min(k, n - 1) * share + (before - g0) + w) / n

    def label(self) -> str:
        """The stage as reported: its name, and which run of a repeated group it belongs to."""
        stage = str(self._stage)
        if self._run is None or self._run[1] == 1 or not any(stage in g for g in REPEATED_GROUPS):
            return stage
        k, n, label = self._run
        return f"{stage} ({label + ', ' if label else ''}run {k + 1} of {n})"

    def emit(self, within: float, info: dict | None = None) -> None:
        if self.progress is None or self._stage is None:
            return
        self._last = max(self._last, min(1.0, self.fraction(self._stage, within)))
        self.progress(self.label(), self._last, info)

    def _finish(self) -> None:
        if self._stage is not None:
            self.timings[self._stage] = round(self.timings.get(self._stage, 0.0) + time.perf_counter() - self._t0, 4)
            self._stage = None

    def close(self) -> None:
        self._finish()
        if self.progress is not None:
            self.progress("done", 1.0, None)


@dataclass
class FlightSeries:
    """What the filter needs of a flight's measurement: z (mGal) at the GNSS epochs (s) and the
    measurement's decisions with their evidence (time offset, spike repair)."""

    name: str
    t_s: np.ndarray
    z_mgal: np.ndarray
    time_offset_s: float
    time_offset_corr: float
    time_offset_applied: bool
    time_offset: dict
    despike: dict
    gnss_filled: int = 0
    gravimeter_filled: int = 0


@dataclass
class Identified:
    """Result of :func:`run_identify`: everything :func:`run_filter` starts from."""

    config: dict
    crs: str
    dt_s: float
    lines: list
    flights: dict
    fir: dict
    noise: object
    identifications: dict
    n_crossovers: int
    measurement_report: dict
    warnings: list
    timings: dict
    survey_dir: str | None = None

    @property
    def cfg(self) -> SurveyConfig:
        return SurveyConfig.model_validate(self.config)


@dataclass
class Measured:
    """Result of :func:`measure_survey`: the measurement stage's flights and decisions, the
    survey's lines cut from them and their crossover count — nothing the noise model or a
    later stage decides."""

    measurement: Measurement
    lines: SurveyLines
    n_crossovers: int


def measure_survey(survey, tr: Tracker) -> Measured:
    """Measurement → lines (stages 1–2), shared by every identification of the survey."""
    tr.start("measurement")
    meas = measure(survey, progress=tr.emit)
    sl = survey_lines(survey, meas)
    return Measured(meas, sl, count_crossovers(sl.lines, survey.config.processing.leveling_include_repeat))


def run_identify(survey, tr: Tracker, measured: Measured | None = None) -> Identified:
    """Measurement → lines → noise model → FIR → identification of every candidate order.
    ``measured``: the survey's measurement already made (:func:`measure_survey`; it depends
    on no setting after stage 2, so a second identification with another noise family starts
    from it), used on a copy — the caller's stays as it was."""
    cfg = survey.config
    p = cfg.processing
    measured = measure_survey(survey, tr) if measured is None else copy.deepcopy(measured)
    meas, sl, n_cx = measured.measurement, measured.lines, measured.n_crossovers
    tr.start("noise")
    noise = model_noise(sl.lines, meas.flights, meas.dt_s, p, n_cx)
    tr.start("fir")
    fir = {name: fir_baseline(m, p.fir_cutoff_period_s, p.fir_gap_max_error_mgal) for name, m in meas.flights.items()}
    noise = check_noise_family(noise, sl.lines, fir, meas.dt_s, p)
    noise = check_noise_corners(noise, sl.lines, fir, meas.dt_s, p)
    warnings = list(meas.warnings) + sl.warnings + fir_loss_warnings(sl.lines, fir, p)
    warnings += [f"repeat lines {', '.join(members)} have no track in lines.csv: they fly one track and are "
                 f"compared as track {track} (report repeat_tracks_inferred; give them a track id to set it)"
                 for track, members in sl.inferred_tracks.items()]
    if noise.warning:
        warnings.append(noise.warning)
    extra: dict = {}
    if p.m is None and p.model_order == "likelihood":
        order = choose_model_order(sl.lines, meas.dt_s, noise.model, noise.r_local)
        orders = [order.m]
        extra["likelihood"] = {"m": order.m, "loglik": {str(k): v for k, v in order.loglik.items()},
                               "Q_stationary_mgal2": {str(k): v for k, v in order.Q_mgal2.items()}}
    elif p.m is None and p.model_order == "spectrum":
        orders = [noise.fit.m]
    else:
        orders = candidate_orders(p, n_cx)
    idents = {}
    for k, m in enumerate(orders):
        def em_cb(rec, m=m):
            tr.emit(min(0.95, rec["iteration"] / max(2, p.em_max_iter)),
                    {"em_iteration": {**rec, "model": f"m={m} {rec.get('model', '')}".strip()}})

        tr.runs(k, len(orders), f"m={m}")   # each order's identification: its own share of the bar
        idents[m] = identify(sl.lines, meas.dt_s, noise.model, cfg, m, callback=em_cb, progress=tr.start)
        warnings.extend(w for w in idents[m].warnings if w not in warnings)
    tr.runs(None)
    flights = {n: FlightSeries(n, f.t_s, f.z_mgal, f.time_offset_s, f.time_offset_corr, f.time_offset_applied,
                               f.time_offset, f.despike, f.gnss_filled, f.gravimeter_filled)
               for n, f in meas.flights.items()}
    mrep = {"base_ties": meas.base_ties, "lag_check": meas.lag_check, "calibration": meas.calibration,
            "band_delay": meas.band_delay, "response_width": meas.response_width,
            "repeat_tracks_inferred": sl.inferred_tracks,
            "model_order_candidates": orders, **({"model_order_likelihood": extra["likelihood"]} if extra else {})}
    return Identified(cfg.model_dump(mode="json"), sl.crs, meas.dt_s, sl.lines, flights, fir, noise, idents, n_cx,
                      mrep, warnings, dict(tr.timings), str(survey.root))


def recognition_order_ident(idf: Identified, m: int):
    """The identification order m filters with (its Q levels, the state map of
    ``recognition_order`` when identified: :func:`_recognised_by`)."""
    return _recognised_by(idf.identifications, m, idf.cfg.processing)


def filter_orders(idf: Identified, p) -> list[int]:
    """The identified orders that are filtered: ``processing.m`` when set; m = 2 alone when
    the crossovers are too few to choose (m = 1 then only lends its state map); else all."""
    if p.m is not None:
        return [int(p.m)]
    if idf.n_crossovers < p.choice_min_crossovers and 2 in idf.identifications:
        return [2]
    return sorted(idf.identifications)


def _recognised_by(idents: dict, m: int, p):
    """The identification of order m, with the state map of the order ``recognition_order``
    when that was identified too and has the same levels (N1 × N2): the recognition of
    terrain classes is better on the m = 1 regularized band, the Q levels stay m's own."""
    r = p.recognition_order
    if r is None or r == m or r not in idents:
        return idents[m]
    a, b = idents[m], idents[r]
    if (len(a.learned.em.Q), len(a.learned.em.R)) != (len(b.learned.em.Q), len(b.learned.em.R)):
        return a
    hybrid = Identification(m, b.regularized, a.learned, b.recognition, b.n_points, a.warnings,
                            own_recognition=a.recognition)
    hybrid.recognition_m = r
    if p.level_support_backoff:   # a level m's EM emptied but r's map applies: as learned before it emptied
        hybrid = back_off_levels(hybrid, p.level_support_min_share, p.level_support_map_share)
    return hybrid


def repeat_level_factors(p) -> tuple[float, ...]:
    """The factors of Q(t) the repeat level check tries: ``1 / repeat_level_factor``, 1, and with
    ``repeat_level_raise`` ``repeat_level_factor^k`` for k = 1 .. ``repeat_level_raise_steps``."""
    f = float(p.repeat_level_factor)
    raised = tuple(f ** k for k in range(1, int(p.repeat_level_raise_steps) + 1)) if p.repeat_level_raise else ()
    return (1.0 / f, 1.0) + raised


def _test_line_level(filtered, idf, m: int, p, warnings: list) -> None:
    """A test line's anomaly level checked by its repeat passes (``repeat_level_*``,
    :meth:`app.pipeline.stages.filtering.Filtered.repeat_level_check`), in place; a warning
    says when it was scaled."""
    factors = repeat_level_factors(p)
    filtered.repeat_level_check(
        idf.dt_s, m, p.smoother, filtered.noise_for(idf.noise.model), p.q_from_posteriors, factors,
        p.repeat_level_significance,
        p.repeat_blend_reference_period_s, p.repeat_blend_reference_periods, p.repeat_blend_min_passes,
        p.repeat_level_block_s,
        reference_q_factor=(p.repeat_blend_reference_q_factor if p.repeat_level_reference == "smoother" else None),
        edge_km=p.repeat_level_edge_km)
    lc = filtered.repeat_level
    if lc and lc.get("factor", 1.0) != 1.0:
        warnings.append(f"test line: anomaly level x {lc['factor']:.3g}"
                        + (f" ({lc['scaled']})" if lc.get("scaled") else "") + f": {lc['reason']}")


def _level_spread(cand, dt_s: float, m: int, noise, p) -> None:
    """Levels learned from too few points (one level, or two from < 2 x min_points_adaptive) or
    learned alike (within std_level_min_contrast): the std also carries the levels' uncertainty
    (:meth:`app.pipeline.stages.filtering.Filtered.level_spread_std`), in place."""
    cand.filtered.level_spread_std(dt_s, m, p.smoother, noise, p.std_level_factor, n_points=cand.ident.n_points,
                                   min_points=p.min_points_adaptive, q_from_posteriors=p.q_from_posteriors,
                                   repeat_min_samples=p.std_repeat_min_samples or None,
                                   fir_period_s=p.fir_cutoff_period_s, repeat_significance=p.std_repeat_significance,
                                   min_contrast=p.std_level_min_contrast, em_levels_mgal2=_learned_levels(cand))


def _learned_levels(cand) -> np.ndarray:
    """The levels as the EM learned them (mGal²), before any refinement lifts one; a level the
    EM did not learn (taken back from its first iterations, ``unlearned_levels``) as the
    likelihood set it: the EM told no contrast there."""
    q = np.asarray(cand.ident.learned.em.Q, dtype=float).copy()
    ul = cand.filtered.unlearned_levels
    if ul:
        q[ul["levels"]] = ul["used_mgal2"]
    return q


def run_filter(idf: Identified, out_dir, tr: Tracker, h_per_km: float | None = None, rho_km: float | None = None,
               survey_name: str | None = None, orders: list[int] | None = None,
               q_start: dict | None = None, q_stationary: dict | None = None) -> dict:
    """NL-means (h, ρ; default the survey's) → filtering of every identified order → model choice
    → leveling → gridding → the files of SPEC §5.  Returns the report.  ``q_start``: {order: the Q
    levels an earlier refinement found} (a filter job's warm start); ``q_stationary``: {order: the
    stationary model's level an earlier run fitted} (independent of h, ρ: a filter job reuses it)."""
    cfg = idf.cfg
    p = cfg.processing
    h = p.nlmeans_h_per_km if h_per_km is None else float(h_per_km)
    rho = p.nlmeans_rho_km if rho_km is None else float(rho_km)
    warnings = list(idf.warnings)
    cands = {}
    orders = orders or filter_orders(idf, p)
    maps = {}   # one NL-means per recognition: both orders filter with m = 1's map (recognition_order)
    for k, m in enumerate(orders):
        tr.runs(k, len(orders), f"m={m}")
        tr.start("nlmeans")
        ident = _recognised_by(idf.identifications, m, p)
        if id(ident.recognition) not in maps:
            maps[id(ident.recognition)] = state_map(ident.recognition, h, rho, p.nlmeans_mode)
        smap = maps[id(ident.recognition)]
        tr.start("filtering")
        filt = filter_survey(idf.lines, idf.flights, idf.fir, ident, smap, idf.noise.r_local, idf.noise.model,
                             idf.dt_s, p, warnings, progress=tr.emit, stationary=len(orders) == 1,
                             q_start=(q_start or {}).get(m), q_stationary=(q_stationary or {}).get(m))
        cands[m] = Candidate(ident, smap, filt)
    tr.runs(None)
    # the crossovers against the std (reported); with crossover_level_check, levels lowered where they show more
    tr.start("level_check")
    check_levels_at_crossovers({m: c.filtered for m, c in cands.items()}, idf.dt_s, idf.noise.model, p, warnings)
    tr.start("choice")
    m_best, order_rep = choose_order(cands, p)
    if len(cands) > 1:
        # every order's levels (a later filter job's warm starts); the baseline only for the order used
        order_rep["Q_mgal2_by_order"] = {str(m): [float(q) for q in c.filtered.fitted_levels()] for m, c in cands.items()}
        cands[m_best].filtered.add_stationary(idf.dt_s, m_best, p.smoother, idf.noise.model, p)
    blend = order_rep.get("blend")
    # the other order's estimate, kept for the blend (stage 9 step 1)
    blend_est = cands[blend["m"]].filtered.table["dg_unleveled_mgal"].to_numpy().copy() if blend else None
    # the chosen order's noise model as its lines were smoothed (with the crossover noise floor where
    # stage 8 added one): every later smoothing and noise prediction of that order uses it
    noise = cands[m_best].filtered.noise_for(idf.noise.model)
    for m in [k for k in cands if k != m_best]:
        # the other order's filtered lines are not read after the order is chosen: freed before
        # the std, leveling and gridding, a copy of every epoch's columns less at the peak
        del cands[m]
    if p.rescale_noisy_passes:  # repeat passes noisier than the model: smoothed with their own level
        cands[m_best].filtered.rescale_noisy_passes(idf.dt_s, m_best, p.smoother, noise,
                                                    p.q_from_posteriors, p.std_repeat_min_samples or 0.0,
                                                    p.fir_cutoff_period_s, p.std_repeat_significance)
        warnings.extend(rescaled_pass_warnings(cands[m_best].filtered.noisy_passes))
    if p.repeat_level_check and count_crossovers(idf.lines, p.leveling_include_repeat) < p.fir_guard_min_crossovers:
        # a test line: its level scaled where its repeat passes agree better so (the crossovers cannot judge it)
        _test_line_level(cands[m_best].filtered, idf, m_best, p, warnings)
    if (p.repeat_blend and p.repeat_blend_reference == "smoother"
            and count_crossovers(idf.lines, p.leveling_include_repeat) < p.fir_guard_min_crossovers):
        # a test line's blend with FIR (stage 9) judged against the other passes smoothed lightly
        cands[m_best].filtered.repeat_reference(idf.dt_s, m_best, p.smoother, noise, p.q_from_posteriors,
                                                p.repeat_blend_reference_q_factor, p.repeat_blend_min_passes)
    if p.std_state_mixture:  # and the std of the mixture of levels
        cands[m_best].filtered.mixture_std(idf.dt_s, m_best, p.smoother, noise)
    _level_spread(cands[m_best], idf.dt_s, m_best, noise, p)
    warnings.extend(pass_noise_warnings(cands[m_best].filtered.std_repeat_tracks))
    if blend:   # after m_best's own std: the blend's spread adds to it
        cands[m_best].filtered.blend_order(blend_est, blend["weight"])
    choice = choose_model(cands, noise, idf.dt_s, p, warnings, order=(m_best, order_rep),
                          # renormalised across holes and the records' ends: a long kernel reaches them
                          # from most lines, and a one-sided mean is still the heavy smoothing wanted
                          fir_at=lambda period: fir_line_column(idf.lines, idf.flights, period))
    best = cands[choice.m]
    table = choice.table
    products = apply_products(table, idf.survey_dir, idf.crs, p, warnings)
    tr.start("leveling")
    base_ties = idf.measurement_report.get("base_ties", {})
    ties = [bool(b.get("applied") and b.get("absolute")) for b in base_ties.values()]
    leveled = level_survey(table, p, warnings, tied=bool(ties) and all(ties),
                           tied_flights={f for f, b in base_ties.items() if b.get("applied") and b.get("absolute")},
                           reading_error_mgal=reading_error_std_mgal(base_ties))
    refresh_bouguer(table)
    tr.start("gridding")
    grid = grid_survey(table, p, warnings, leveled.report.get("rms_after_mgal"))
    grid_bouguer = None
    if "dg_bouguer_mgal" in table:
        grid_bouguer = grid_survey(table.assign(dg_mgal=table["dg_bouguer_mgal"]), p, warnings,
                                   leveled.report.get("rms_after_mgal"))
    grid_flight = None
    at_flight = flight_height_table(table)
    if at_flight is not None:  # continued to a datum: the free-air map at flight height beside it
        # (no crossover term: the crossovers were measured at the datum)
        grid_flight = grid_survey(at_flight, p, warnings, None)
    add_common_level_std(table, [grid, grid_bouguer, grid_flight], leveled.report, any(ties), p, warnings)
    tr.start("writing")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ident_json = identification_json(idf.identifications[choice.m], idf.noise.model, best.smap, idf.dt_s)
    ident_json["state_map_from_m"] = best.ident.recognition_m if hasattr(best.ident, "recognition_m") else choice.m
    write_outputs(out, table, best.smap.table(best.ident.recognition), leveled.crossovers, ident_json, grid, idf.crs,
                  grid_bouguer=grid_bouguer, grid_flight=grid_flight)
    tr.close()
    report = build_report(survey_name or cfg.survey.name, idf.crs, table, idf.flights, leveled, best.ident, grid,
                          warnings)
    _add_noted_sections(report, best.ident, table, p, warnings, bool(best.filtered.unlearned_levels))
    report.update(idf.measurement_report)
    report["noise_model"] = idf.noise.describe()
    report["model_choice"] = choice.report
    report["products"] = {**products.report, "grids": {
        "free_air": "grid" if grid is not None else None,
        "bouguer": "grid_bouguer" if grid_bouguer is not None else None,
        "free_air_flight_height": "grid_flight" if grid_flight is not None else None}}
    _add_filter_sections(report, best.filtered.report(p), grid, {**idf.timings, **tr.timings})
    return report


def _add_noted_sections(report: dict, ident, table, p, warnings: list, unlearned: bool = False) -> None:
    """The report's sections that only say what the analyst should know (in place, each with its
    warnings): where each anomaly level is learned and applied (``identification.level_support``;
    ``unlearned``: the filter left a level the EM never learned to the likelihood), and the
    lines' noise episodes (``noise_episodes``)."""
    support, support_warnings = level_support(ident, p.level_support_min_share, p.level_support_map_share,
                                              p.level_backoff_floor_min_iteration if unlearned else 0)
    report["identification"]["level_support"] = support
    warnings.extend(support_warnings)
    report["noise_episodes"], episode_warnings = noise_episodes(table, p.noise_episode_factor, p.noise_episode_min_s,
                                                                p.noise_episode_bridge_s)
    warnings.extend(episode_warnings)


def _add_filter_sections(report: dict, level_rep: dict | None, grid, timings: dict) -> None:
    """The report's sections of the filtering and gridding (in place): the levels used
    (``level_refinement``), the grid std's cross-validation, the stage timings and threads."""
    if level_rep is not None:
        report["level_refinement"] = level_rep
    if grid is not None and grid.cross_validation:
        report["grid_std_cross_validation"] = grid.cross_validation
    report["timings_s"] = timings
    report["threads"] = thread_count()  # the line loops' threads (the output does not depend on them)


IDENTIFIED_DIR = "identified"


def save_identified(idf: Identified, out_dir) -> Path:
    """Store the identification beside the outputs (``<out>/identified/``)."""
    return storage.save(idf, Path(out_dir) / IDENTIFIED_DIR)


def load_identified(out_dir) -> Identified:
    """The :class:`Identified` stored by :func:`save_identified` in ``out_dir``."""
    obj = storage.load(Path(out_dir) / IDENTIFIED_DIR)
    if not isinstance(obj, Identified):
        raise ValueError(f"{out_dir}: the stored stage is not an identification")
    return obj
