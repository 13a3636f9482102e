"""Stages 4–6 together, identification: regularization → learning → recognition for one anomaly
order m.  The result is what a later ``filter`` run starts from (:mod:`app.pipeline.runs`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace

import numpy as np

from app.config import SurveyConfig
from app.core.recognition import last_supported_iteration, level_shares, stationary_distribution
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
    own_recognition : Recognition or None
        When ``recognition`` is another order's map (:func:`app.pipeline.runs.recognition_order_ident`),
        the raw posteriors of this order's own Θ: where its EM put each level.
    level_backoff : dict or None
        When :func:`back_off_levels` replaced unsupported levels: the EM's final levels, the
        iteration whose levels replaced them and the shares there (``learned.em.Q`` holds the
        levels used).
    """

    m: int
    regularized: Regularized
    learned: Learned
    recognition: Recognition
    n_points: int
    warnings: list
    own_recognition: Recognition | None = None
    level_backoff: dict | None = None


_TOO_FEW = re.compile(r"only (\d+) decimated points \(need (\d+)\)")


def skipped_lines_warning(skipped: dict, n_lines: int, m: int) -> str:
    """One warning for the lines order ``m``'s identification left out (``skipped``: {line: why},
    as :class:`Regularized` holds it; ``n_lines``: lines offered), grouped by reason — a survey of
    short lines had one warning per line and per order (a 14-line layout: 21 lines of warnings
    before the first that said anything else).  The report's ``identification.lines_skipped``
    keeps each line's own reason.  A line the state map used for filtering does not cover (it
    may be m = 1's, ``recognition_order``) is filtered at the smoothest level
    (:func:`app.pipeline.stages.filtering.prepare_lines`)."""
    few = {ln: _TOO_FEW.fullmatch(why) for ln, why in skipped.items()}
    groups: dict[str, list[str]] = {}
    need = sorted({int(mt.group(2)) for mt in few.values() if mt})
    for ln, why in skipped.items():
        if few[ln]:
            groups.setdefault(f"too few decimated points (need {'/'.join(map(str, need))})", []).append(
                f"{ln} ({few[ln].group(1)})")
        else:
            groups.setdefault(why, []).append(ln)
    parts = "; ".join(f"{why}: {', '.join(names)}" for why, names in groups.items())
    return (f"order m = {m}: {len(skipped)} of {n_lines} lines not identified — {parts} "
            "(a line no state map covers is filtered at the smoothest level; report identification.lines_skipped)")


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
    if reg.skipped:
        warnings.append(skipped_lines_warning(reg.skipped, len(reg.x) + len(reg.skipped), m))
    n_dec = sum(len(x) for x in reg.x)
    if n_dec < cfg.processing.min_points_adaptive:
        warnings.append(f"order m = {m}: identification from only {n_dec} decimated points ({len(reg.x)} lines): "
                        "the learned Q/R levels and transitions are unreliable")
    if progress is not None:
        progress("learning")
    learned: Learned = learn_survey(reg, cfg, warnings, callback)
    if progress is not None:
        progress("recognition")
    recognition: Recognition = recognize_survey(reg, learned.theta, cfg)
    return Identification(int(m), reg, learned, recognition, int(n_dec), warnings)


def _shares(rec: Recognition):
    """:func:`level_shares` of a recognition's raw posteriors over its points with finite
    posteriors; None when there is none (a diagnostic must not stop the processing)."""
    probs = rec.table[[f"p_{i}" for i in range(rec.n_states)]].to_numpy(float)
    probs = probs[np.all(np.isfinite(probs), axis=1)]
    return level_shares(probs, rec.n_r) if probs.shape[0] else None


def level_support(ident: Identification, min_share: float, map_share: float,
                  floor_min_iteration: int = 0) -> tuple[dict, list[str]]:
    """Where the EM put each anomaly level against where the filter's state map puts it.

    The state map may be another order's (``recognition_order``: m = 1's map with m = 2's
    levels).  A level the order's own EM gave to almost no decimated point (below
    ``min_share``) is not learned from a terrain: such a state sheds its points over the
    iterations and its Q drifts up on the few jumps left to it (the 1 Hz heights-only regime
    of seed 3: 1 % of the points, Q 0.02 → 0.13 mGal² over 60 iterations without converging).
    When the map applies that level to ``map_share`` or more of the points, the report says
    so: those stretches are smoothed with a level the data there did not give.

    Returns the report's ``identification.level_support`` (``Q_mgal2``, ``share_em``,
    ``share_map``, ``map_from_m``, ``em_converged``, ``unsupported``: indices of such levels;
    a share is None where its recognition has no point with finite posteriors) and the warnings
    (``floor_min_iteration``: ``level_backoff_floor_min_iteration`` where the filter left such
    levels to the likelihood, :func:`unlearned_levels`, else 0 — what the warning says is done
    with them)."""
    em = ident.learned.em
    own = ident.own_recognition or ident.recognition
    backoff = ident.level_backoff
    q = np.asarray(em.Q if backoff is None else backoff["Q_em_mgal2"], dtype=float)
    share_em, share_map = _shares(own), _shares(ident.recognition)
    known = share_em is not None and share_map is not None and share_em.size == share_map.size == q.size
    bad = [i for i in range(q.size) if known and share_em[i] < min_share and share_map[i] >= map_share]
    rep = {"Q_mgal2": q.tolist(), "share_em": None if share_em is None else share_em.tolist(),
           "share_map": None if share_map is None else share_map.tolist(),
           "map_from_m": int(getattr(ident, "recognition_m", ident.m)),
           "em_converged": bool(getattr(em, "converged", True)), "unsupported": bad, "backoff": backoff}
    if unlearned_levels(ident, floor_min_iteration):
        fate = (f"its level at EM iteration {backoff['iteration']}, the last whose transitions gave every level "
                f"{100 * min_share:.2g} % of the steps, comes from the EM's first iterations (before "
                f"{floor_min_iteration}), not from a terrain, so those stretches are filtered with the full-rate "
                "likelihood's level under the map (level_refinement.unlearned_levels)")
    elif backoff is not None and backoff.get("iteration") is not None:
        then = [f"{q_used:.3g} mGal²" for q_used in np.asarray(backoff["Q_used_mgal2"])[bad]]
        fate = (f"they are filtered with its level at EM iteration {backoff['iteration']} ({', '.join(then)}), "
                f"the last whose transitions gave every level {100 * min_share:.2g} % of the steps")
    else:
        fate = "those stretches are filtered with a level their data did not give"
    warnings = [f"anomaly level Q = {q[i]:.3g} mGal² (order m = {ident.m}) holds {100 * share_em[i]:.2g} % of the "
                f"decimated points under its own EM{'' if rep['em_converged'] else ', which did not converge'}, "
                f"but the state map applies it to {100 * share_map[i]:.0f} %: {fate} "
                "(report identification.level_support)" for i in bad]
    return rep, warnings


def back_off_levels(ident: Identification, min_share: float, map_share: float) -> Identification:
    """The identification with each unsupported level (:func:`level_support`) at its value of the
    last EM iteration whose chain still gave every level ``min_share`` of the steps.

    Such a level was learned from a terrain until its state shed its points; from there on its
    Q is fitted to the few jumps left to it (seed 3's heights-only 1 Hz regime: 0.024 mGal² at
    iteration 14, the last whose transitions gave it 2 % of the steps, 0.13 at 60).  The share
    of an iteration is its transition matrix's stationary distribution (the records keep no
    posteriors): the long-run share the chain as learned then expects.  The map that applies
    the level to a tenth or more of the survey is another order's, which found that terrain.
    The other levels keep their final values.  Unchanged (``level_backoff`` records why) when
    the records hold no transition matrices, when no iteration had every level at
    ``min_share``, or when the levels would no longer ascend."""
    rep, _ = level_support(ident, min_share, map_share)
    bad = rep["unsupported"]
    if not bad:
        return ident
    em = ident.learned.em
    records = list(em.iterations)   # this fit's own iteration table (the candidates' other fits are not in it)
    q_em = np.asarray(em.Q, dtype=float)
    info = {"Q_em_mgal2": q_em.tolist(), "Q_used_mgal2": q_em.tolist(), "iteration": None}
    if not records or any(len(r.get("transition", ())) != len(em.Q) * len(em.R) for r in records):
        return _with(ident, level_backoff={**info, "reason": "the EM records hold no transition matrices"})
    k = last_supported_iteration([r["transition"] for r in records], len(em.R), min_share)
    if k is None:
        return _with(ident, level_backoff={**info, "reason": f"no iteration had every level at {min_share:g}"})
    q = q_em.copy()
    q[bad] = np.asarray(records[k]["Q"], dtype=float)[bad]
    if not (np.all(np.diff(q) > 0) and np.all(np.isfinite(q)) and np.all(q > 0)):
        return _with(ident, level_backoff={**info, "reason": "the levels would no longer ascend"})
    info.update(Q_used_mgal2=q.tolist(), iteration=int(records[k]["iteration"]),
                share_at_iteration=level_shares(stationary_distribution(records[k]["transition"])[None],
                                                len(em.R)).tolist(),
                reason=f"levels {bad} held < {min_share:g} of the points under their own EM")
    return _with(ident, learned=replace(ident.learned, em=replace(em, Q=q)), level_backoff=info)


def unlearned_levels(ident: Identification, min_iteration: int) -> list[int]:
    """Indices of the levels :func:`back_off_levels` took from an EM iteration before
    ``min_iteration`` (``level_backoff_floor_min_iteration``): their state lost its points after
    the first M-step or so, and the value is the initialisation's (spread over the chunk
    estimates' quantiles) moved once — not a level learned from a terrain.  Empty when no level
    was taken back."""
    b = ident.level_backoff
    if not b or b.get("iteration") is None or int(b["iteration"]) >= int(min_iteration):
        return []
    return [i for i, (final, used) in enumerate(zip(b["Q_em_mgal2"], b["Q_used_mgal2"])) if final != used]


def _with(ident: Identification, **changes) -> Identification:
    """A copy of ``ident`` with ``changes``, keeping the borrowed map's order (``recognition_m``)."""
    out = replace(ident, **changes)
    if hasattr(ident, "recognition_m"):
        out.recognition_m = ident.recognition_m
    return out
