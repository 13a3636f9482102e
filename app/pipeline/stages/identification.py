"""Stages 4–6 together, identification: regularization → learning → recognition for one anomaly
order m.  The result is what a later ``filter`` run starts from (:mod:`app.pipeline.runs`).
"""

from __future__ import annotations

from dataclasses import dataclass

from app.config import SurveyConfig
from app.pipeline.stages.learning import Learned, learn_survey
from app.pipeline.stages.recognition import Recognition, recognize_survey
from app.pipeline.stages.regularization import Regularized, regularize_lines


@dataclass
class Identification:
    """Result of :func:`identify` for one order ``m``.

    Attributes
    ----------
    m : int
    regularized : Regularized
    learned : Learned
        Θ, the EM iteration table, the model selection.
    recognition : Recognition
        Decimated points with their raw posteriors (before NL-means).
    n_points : int
        Decimated points of all regularized lines.
    warnings : list of str
    """

    m: int
    regularized: Regularized
    learned: Learned
    recognition: Recognition
    n_points: int
    warnings: list


def identify(lines: list, dt_s: float, noise, cfg: SurveyConfig, m: int, callback=None,
             progress=None) -> Identification:
    """Regularize the lines for order ``m``, learn Θ by EM (``callback(record)`` per
    iteration), recognise the states.  ``progress(step)`` with step in
    {"regularization", "learning", "recognition"} as each begins."""
    warnings: list[str] = []
    if progress is not None:
        progress("regularization")
    reg = regularize_lines(lines, cfg, dt_s, m, None if noise.is_white_velocity else noise)
    if reg.note:
        warnings.append(reg.note)
    for ln, why in reg.skipped.items():
        warnings.append(f"line {ln} not identified: {why}")
    n_dec = sum(len(x) for x in reg.x)
    if n_dec < cfg.processing.min_points_adaptive:
        warnings.append(f"identification from only {n_dec} decimated points ({len(reg.x)} lines): "
                        "the learned Q/R levels and transitions are unreliable")
    if progress is not None:
        progress("learning")
    learned: Learned = learn_survey(reg, cfg, warnings, callback)
    if progress is not None:
        progress("recognition")
    recognition: Recognition = recognize_survey(reg, learned.theta, cfg)
    return Identification(int(m), reg, learned, recognition, int(n_dec), warnings)
