"""``aerograv process``: run the stages of SPEC §2/§3 and write the outputs of SPEC §5.

``process_survey(survey_dir, out_dir, overrides=None, progress=None) -> report``

Outputs (all written atomically: temporary name, then rename):
``lines.parquet``, ``identification.json``, ``recognition.parquet``, ``crossovers.csv``,
``grid.nc``, ``grid.tif``, ``grid.grd``, ``grid.csv``, ``report.json``.  The stages are
those of :mod:`app.pipeline.stages`, run by :mod:`app.pipeline.runs`.
"""

from __future__ import annotations

from pathlib import Path

from app.io import export
from app.io.survey import read_survey
from app.pipeline.runs import Progress, Tracker, run_filter, run_identify, save_identified


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
    tr = Tracker(progress)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tr.start("ingest")
    survey = read_survey(survey_dir, overrides)
    identified = run_identify(survey, tr)
    if keep_identification:
        save_identified(identified, out)
    report = run_filter(identified, out, tr)
    export.write_json(report, out / "report.json")
    return report
