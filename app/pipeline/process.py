"""``aerograv process``: run the stages of SPEC §2/§3 and write the outputs of SPEC §5.

``process_survey(survey_dir, out_dir, overrides=None, progress=None) -> report``

Outputs (all written atomically: temporary name, then rename):
``lines.parquet``, ``identification.json``, ``recognition.parquet``, ``crossovers.csv``,
``grid.nc``, ``grid.tif``, ``grid.grd``, ``grid.csv``, ``report.json``.  The stages are
those of :mod:`app.pipeline.stages`, run by :mod:`app.pipeline.runs`.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

import pandas as pd

from app.io import export
from app.io.survey import read_survey
from app.pipeline.parallel import thread_count
from app.pipeline.runs import (
    PLANS,
    Identified,
    Measured,
    Progress,
    Tracker,
    measure_survey,
    run_filter,
    run_identify,
    save_identified,
)
from app.pipeline.stages.noise import CHECK_FAMILY, family_check_due, family_crossover_choice

#: where the noise family's crossover check writes the white-velocity run's outputs (removed after)
FAMILY_CHECK_DIR = ".noise-family-check"


def process_survey(survey_dir, out_dir, overrides: dict | None = None, progress: Progress | None = None,
                   keep_identification: bool = False) -> dict:
    """Process a survey directory (SPEC §4) into the outputs of SPEC §5.

    Parameters
    ----------
    survey_dir : path
        The survey directory.
    out_dir : path
        Output directory (created).
    overrides : dict, optional
        ProcessingParams overrides on top of ``survey.toml``'s ``[processing]``.
    progress : callable, optional
        ``progress(stage, fraction, info)``; EM iterations arrive as
        ``info = {"em_iteration": {...}}``.
    keep_identification : bool
        Also store the identification (``<out>/identified/``) so that a later filter run
        (other h, ρ) can start from it.

    Returns
    -------
    dict
        The report (also written to ``report.json``).
    """
    thread_count()  # a bad AEROGRAV_THREADS is an error before any work
    tr = Tracker(progress)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tr.start("ingest")
    survey = read_survey(survey_dir, overrides)
    measured = measure_survey(survey, tr)
    identified = run_identify(survey, tr, measured)
    check, alternative = _family_alternative(survey, measured, identified, out, tr)
    try:
        report = run_filter(identified, out, tr)
    except BaseException:
        shutil.rmtree(out / FAMILY_CHECK_DIR, ignore_errors=True)   # no second run's files left behind
        raise
    identified, report = _family_checked(check, alternative, identified, report, out)
    if keep_identification:
        save_identified(identified, out)
    export.write_json(report, out / "report.json")
    return report


def _family_alternative(survey, measured: Measured, identified: Identified, out: Path, tr: Tracker):
    """The noise family's crossover check, first half (``noise_family_crossover_check``): when
    :func:`~app.pipeline.stages.noise.family_check_due`, the survey (as read and measured once:
    ``measured``, which no noise family changes) identified and filtered again with white
    velocity noise into ``<out>/.noise-family-check`` (stage "noise family check").  A failure
    of that optional run keeps the first run and is said (``failed``, a warning).  Returns (the check's record, None or (Identified, report,
    directory) of that run)."""
    p = identified.cfg.processing
    check = family_check_due(identified.noise.describe(), identified.n_crossovers, p)
    if not check["due"]:
        return check, None
    tr.start("noise family check")
    tmp = out / FAMILY_CHECK_DIR
    silent = Tracker(None)
    cfg = survey.config.model_copy(update={"processing": p.model_copy(update={"noise_family": CHECK_FAMILY})})
    try:
        alt_idf = run_identify(dataclasses.replace(survey, config=cfg), silent, measured)
        alt_report = run_filter(alt_idf, tmp, silent)
    except Exception as exc:   # an optional second run: its failure must not cost the first run's result
        shutil.rmtree(tmp, ignore_errors=True)
        check["failed"] = f"{type(exc).__name__}: {exc}"
        check["reason"] += f"; the white-velocity run failed ({check['failed']}): the fit's family kept"
        return check, None
    return check, (alt_idf, alt_report, tmp)


def _family_checked(check: dict, alternative, identified: Identified, report: dict, out: Path):
    """The noise family's crossover check, second half: the two runs compared at the
    crossovers (:func:`~app.pipeline.stages.noise.family_crossover_choice`); when white velocity
    wins, its outputs replace the first run's in ``out`` and its report and identification are
    returned, with a warning.  The check's record goes in ``noise_model.crossover_check``."""
    if alternative is not None:
        alt_idf, alt_report, tmp = alternative
        try:
            family_crossover_choice(check, pd.read_csv(out / "crossovers.csv"), pd.read_csv(tmp / "crossovers.csv"),
                                    identified.cfg.processing.order_choice_p)
            if check["applied"]:
                for f in sorted(tmp.iterdir()):
                    if f.is_file():
                        os.replace(f, out / f.name)
                alt_report["timings_s"] = report.get("timings_s", alt_report.get("timings_s"))
                alt_report["warnings"].append(f"noise family: {check['family']} was chosen by the spectra, "
                                              f"{check['reason']}")
                identified, report = alt_idf, alt_report
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    if check.get("failed"):
        report.setdefault("warnings", []).append(f"noise family: {check['reason']}")
    report.setdefault("noise_model", {})["crossover_check"] = {k: v for k, v in check.items() if k != "due"}
    return identified, report


def _write_recognition_raw(out: Path, ident) -> None:
    """The raw posteriors (before NL-means) of the state map the filter uses, with its levels:
    the web's recognition endpoint smooths these with the analyst's (h, ρ) through the same
    function as the filter (:func:`app.pipeline.stages.recognition.state_map`)."""
    rec = ident.recognition
    t = rec.table.copy()
    t.attrs = {}
    export.write_parquet(t.assign(n_q=rec.n_q, n_r=rec.n_r), out / "recognition_raw.parquet")


def identify_survey(survey_dir, out_dir, overrides: dict | None = None, progress: Progress | None = None) -> dict:
    """The ``identify`` job: measurement → noise model → regularization → learning →
    recognition, stored in ``<out>/identified/`` for later ``filter`` runs, with
    ``identification.json`` (EM table of every order), ``recognition_raw.parquet`` and a
    ``report.json`` of what was measured and decided so far.  Returns that report."""
    from app.pipeline.runs import recognition_order_ident
    from app.pipeline.stages.outputs import identification_json
    from app.pipeline.stages.recognition import state_map

    thread_count()  # a bad AEROGRAV_THREADS is an error before any work
    tr = Tracker(progress, PLANS["identify"])
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tr.start("ingest")
    survey = read_survey(survey_dir, overrides)
    idf = run_identify(survey, tr)
    save_identified(idf, out)
    p = idf.cfg.processing
    m = p.m if p.m is not None else max(idf.identifications)
    ident = recognition_order_ident(idf, m)
    smap = state_map(ident.recognition, p.nlmeans_h_per_km, p.nlmeans_rho_km, p.nlmeans_mode)
    export.write_parquet(smap.table(ident.recognition), out / "recognition.parquet")
    _write_recognition_raw(out, ident)
    ident_json = identification_json(idf.identifications[m], idf.noise.model, smap, idf.dt_s)
    ident_json["orders"] = {str(k): {"em": {"iterations": v.learned.em.iterations, "selection": v.learned.selection}}
                            for k, v in idf.identifications.items()}
    export.write_json(ident_json, out / "identification.json")
    tr.close()
    report = {"survey": idf.cfg.survey.name, "stage": "identified", "crs": idf.crs, "warnings": idf.warnings,
              "noise_model": idf.noise.describe(), **idf.measurement_report, "timings_s": tr.timings,
              "counts": {"lines": len(idf.lines), "crossovers": idf.n_crossovers,
                         "decimated_points": {str(k): v.n_points for k, v in idf.identifications.items()}}}
    export.write_json(report, out / "report.json")
    return report


#: The settings a filter job was given, kept beside the identification it copies (a JSON object of
#: ``ProcessingParams`` fields): the next filter job from that result starts from them.
FILTER_SETTINGS = "filter_settings.json"


def filter_from(identified_dir, out_dir, overrides: dict | None = None, progress: Progress | None = None,
                survey_dir=None) -> dict:
    """The ``filter`` job: start from the identification stored in ``identified_dir``
    (:func:`identify_survey` or ``process`` in the web application) and run NL-means (h, ρ
    from ``overrides`` ``nlmeans_h_per_km``/``nlmeans_rho_km``) → filtering → model choice →
    leveling → gridding → the files of SPEC §5.  The EM is not recomputed.  Filter-stage
    settings in ``overrides`` apply over those the filter job that made ``identified_dir``
    was given (:data:`FILTER_SETTINGS`, kept beside the identification: a filter job given only
    h and ρ keeps an earlier one's smoothing strength or FIR period); settings of earlier stages
    are kept as identified.  The report's ``filter_settings`` says which came from where."""
    import json
    import shutil

    from app.config import SurveyConfig
    from app.pipeline.runs import IDENTIFIED_DIR, load_identified

    thread_count()  # a bad AEROGRAV_THREADS is an error before any work

    tr = Tracker(progress, PLANS["filter"])
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tr.start("ingest")
    idf = load_identified(identified_dir)
    if survey_dir is not None:
        idf.survey_dir = str(survey_dir)   # the job's input (a DEM uploaded since is used)
    src = Path(identified_dir) / IDENTIFIED_DIR
    earlier = src / FILTER_SETTINGS
    carried = json.loads(earlier.read_text()) if earlier.is_file() else {}
    settings = {**carried, **(overrides or {})}
    if settings:
        cfg = idf.config
        cfg["processing"] = {**cfg.get("processing", {}), **settings}
        idf.config = SurveyConfig.model_validate(cfg).model_dump(mode="json")
    if src.resolve() != (out / IDENTIFIED_DIR).resolve():  # the next filter starts from here too
        shutil.copytree(src, out / IDENTIFIED_DIR, copy_function=_link_or_copy, dirs_exist_ok=True)
    # this job's settings for the next filter job: a new file put in place (the copied one may be
    # a hard link to the earlier result's, which must stay as it is)
    tmp = out / IDENTIFIED_DIR / (FILTER_SETTINGS + ".partial")
    tmp.write_text(json.dumps(settings, sort_keys=True))
    os.replace(tmp, out / IDENTIFIED_DIR / FILTER_SETTINGS)
    identification_timings = dict(idf.timings)
    idf.timings = {}
    # The anomaly order: m = 1, where the run this one starts from found it significantly better
    # at the crossovers, or m = 2 where too few crossovers could tell, is kept; where m = 2 stood by
    # the crossover test (blended or not), both orders are filtered again — each warm-started from
    # the levels that run found — and chosen or blended at the new h, ρ by their own crossovers,
    # as `process` would (stage 9 step 1).  The stationary baseline has no states: its level,
    # fitted by that run, is taken as it is.
    orders = q_start = q_stationary = None
    prev_report = Path(identified_dir) / "report.json"
    if prev_report.exists():
        prev = json.loads(prev_report.read_text())
        prev_m = prev.get("model_choice", {}).get("m")
        order = prev.get("model_choice", {}).get("order") or {}
        blend = order.get("blend")
        if prev_m in idf.identifications:
            q_stationary = {int(prev_m): (prev.get("level_refinement") or {}).get("Q_stationary_mgal2")}
        if idf.cfg.processing.m is None and prev_m in idf.identifications:
            q_start = {int(prev_m): (prev.get("level_refinement") or {}).get("Q_mgal2")}
            q_start.update({int(m): q for m, q in (order.get("Q_mgal2_by_order") or {}).items() if int(m) != prev_m})
            if blend and blend.get("Q_mgal2") is not None:   # a result stored before Q_mgal2_by_order
                q_start.setdefault(int(blend["m"]), blend["Q_mgal2"])
            # m = 2 stood by the crossover test: at other h, ρ the blend's weight may be other than
            # that run's (0 included), so both orders are filtered as `process` would
            blend_open = (int(prev_m) == 2 and idf.cfg.processing.order_blend
                          and order.get("p_m2_worse_than_m1") is not None)
            if not (blend or blend_open):
                orders = [int(prev_m)]
    report = run_filter(idf, out, tr, orders=orders, q_start=q_start, q_stationary=q_stationary)
    if orders:
        report["model_choice"]["order"] = {"criterion": "as chosen by the run this filter starts from", "m": orders[0]}
    report["filter_settings"] = {"carried": carried, "given": dict(overrides or {}),
                                 "note": "settings given to the filter job that made the result this one "
                                         "starts from, under this job's own (given)"}
    report["reused_identification"] = {"from": str(identified_dir), "timings_s": identification_timings,
                                       "note": "EM not recomputed: the stored identification was filtered with "
                                               f"h = {idf.cfg.processing.nlmeans_h_per_km:g} /km, "
                                               f"ρ = {idf.cfg.processing.nlmeans_rho_km:g} km"}
    _write_recognition_raw(out, _used_ident(idf, report))
    export.write_json(report, out / "report.json")
    return report


def _used_ident(idf, report: dict):
    from app.pipeline.runs import recognition_order_ident

    return recognition_order_ident(idf, int(report["model_choice"]["m"]))


def _link_or_copy(src, dst):
    import os
    import shutil

    if os.path.exists(dst) and os.path.samefile(src, dst):
        return dst   # a filter job run again into the same folder: already linked
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)
    return dst


def run_job(input_dir, out_dir, overrides: dict | None = None, progress: Progress | None = None,
            kind: str = "process", previous_dir=None) -> dict:
    """The web application's job entry: ``process`` (everything, the identification kept for
    later filters), ``identify`` (:func:`identify_survey`) or ``filter`` (:func:`filter_from`
    the previous result ``previous_dir``)."""
    if kind == "process":
        report = process_survey(input_dir, out_dir, overrides, progress, keep_identification=True)
        from app.pipeline.runs import load_identified

        _write_recognition_raw(Path(out_dir), _used_ident(load_identified(out_dir), report))
        return report
    if kind == "identify":
        return identify_survey(input_dir, out_dir, overrides, progress)
    if kind == "filter":
        if previous_dir is None:
            raise ValueError("a filter job needs a stored identification: run identify or process first")
        return filter_from(previous_dir, out_dir, overrides, progress, survey_dir=input_dir)
    raise ValueError(f"unknown job kind {kind!r}")
