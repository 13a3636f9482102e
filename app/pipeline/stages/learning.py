"""Stage 5, learning (SPEC §2 step 2): EM of Θ = {Q_i, R_j, a_ij, π_i(w)} over the lines'
regularized sequences, the number of noise (and anomaly) levels chosen from the data; every
iteration recorded (the EM iteration table).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.config import SurveyConfig
from app.core.mjls_em import fit_em
from app.core.recognition import stationary_distribution
from app.pipeline.stages.regularization import Regularized, split_stretches


def _n_params(n_q: int, n_r: int, n_lines: int) -> int:
    n = n_q * n_r
    return n_q + n_r + n * (n - 1) + n_lines * (n - 1)


def learning_sequences(reg: Regularized) -> tuple[list, list[int]]:
    """The sequences the EM learns from and the index in ``reg`` of each one's line: each
    stretch of a line without missing epochs on its own
    (:func:`app.pipeline.stages.regularization.split_stretches`), those too short for the EM's
    window (``p + 2`` points) left out — unless that leaves none, when the lines' stretches are
    taken joined as before (holes every few minutes on every line)."""
    pieces, owner = split_stretches(reg)
    kept = [(x, w) for x, w in zip(pieces, owner) if len(x) >= reg.ma.p + 2]
    if not kept:
        return list(reg.x), list(range(len(reg.x)))
    return [x for x, _ in kept], [w for _, w in kept]


def learn(reg: Regularized, cfg: SurveyConfig, callback=None, sequences: list | None = None):
    """EM learning of Θ = {Q_i, R_j, a_ij, π_i(w)} over all lines (SPEC §2 step 2).

    With ``processing.n_r = None`` the number of GNSS noise levels is chosen by
    BIC between 1 and 2 (noise episodes of the GNSS are common in real data and a
    model without them explains them as anomaly intensity).  With ``processing.n_q = None``
    there are two anomaly levels when the lines give at least ``min_points_adaptive``
    decimated points, one otherwise (the stationary model: all a short survey supports).
    The EM learns from ``sequences`` (:func:`learning_sequences` of ``reg`` when not given).

    Returns
    -------
    (EMResult, dict)
        The EM result of the chosen model and the selection (candidates with log-likelihood
        and BIC, the chosen model)."""
    p = cfg.processing
    r_cands = [p.n_r] if p.n_r is not None else [1, 2]
    seqs = learning_sequences(reg)[0] if sequences is None else sequences
    n_points = int(sum(len(x) for x in seqs))
    # N1 = 2 anomaly levels need enough decimated points to be told apart; a short survey
    # (a test line flown a few times: ~100 points) gets the stationary model (one level)
    q_cands = [p.n_q] if p.n_q is not None else [2 if n_points >= p.min_points_adaptive else 1]
    results, table = {}, []
    for n_q in q_cands:
        for n_r in r_cands:
            tag = f"{n_q}x{n_r}"

            def cb(rec, tag=tag):
                if callback is not None:
                    callback({**rec, "model": tag})

            res = fit_em(seqs, reg.ma.c, reg.ma.d, n_q=n_q, n_r=n_r, max_iter=p.em_max_iter,
                         tol=p.em_tol, callback=cb)
            k = _n_params(n_q, n_r, len(seqs))
            bic = -2.0 * float(res.loglik) + k * np.log(max(n_points, 2))
            results[(n_q, n_r)] = res
            table.append({"model": tag, "n_q": n_q, "n_r": n_r, "loglik": float(res.loglik),
                          "n_params": k, "bic": float(bic), "iterations": len(res.iterations) - 1})
    best = min(table, key=lambda r: r["bic"])
    em = results[(best["n_q"], best["n_r"])]
    selection = {"criterion": "BIC" if len(table) > 1 else "fixed", "candidates": table, "chosen": best["model"]}
    return em, selection


@dataclass
class Learned:
    """Result of :func:`learn_survey`.

    Attributes
    ----------
    em : app.core.mjls_em.EMResult
    selection : dict
        Candidate models (levels N1 × N2) with log-likelihood and BIC, the chosen one.
    initial : list of ndarray
        Initial state probabilities per regularized line (EM's for learned lines, the
        chain's stationary distribution for the others).
    learn_mask : list of bool
        Which regularized lines the EM learned from.
    iterations : list of dict
        The EM iteration table as streamed (with the candidate model's tag).
    """

    em: object
    selection: dict
    initial: list
    learn_mask: list
    iterations: list

    @property
    def theta(self):
        """Θ with one row of initial probabilities per regularized line (plain data)."""
        from types import SimpleNamespace

        return SimpleNamespace(Q=self.em.Q, R=self.em.R, transition=self.em.transition, initial=self.initial)


def learn_survey(reg: Regularized, cfg: SurveyConfig, warnings: list, callback=None) -> Learned:
    """Stage 5: EM over the main lines (tie lines with ``include_tie_lines``)."""
    p = cfg.processing
    learn_mask = [ln.kind != "tie" or p.include_tie_lines for ln in reg.lines]
    if sum(learn_mask) == 0:
        learn_mask = [True] * len(reg.lines)
        warnings.append("no main lines could be regularized; learning on tie lines")
    rows: list[dict] = []

    def on_iter(rec: dict):
        rows.append(rec)
        if callback is not None:
            callback(rec)

    sub = Regularized(reg.design, reg.ma, [ln for ln, k in zip(reg.lines, learn_mask) if k],
                      [x for x, k in zip(reg.x, learn_mask) if k],
                      [i for i, k in zip(reg.idx, learn_mask) if k], reg.skipped)
    seqs, owner = learning_sequences(sub)
    em, selection = learn(sub, cfg, callback=on_iter, sequences=seqs)
    # per-line initial probabilities: learned lines from EM — the row of the line's first
    # stretch the EM kept (rows mapped back through em.line_index, since EM drops sequences too
    # short for its window) —, others the chain's stationary distribution
    stationary = stationary_distribution(np.asarray(em.transition))
    learned_pos = [i for i, k in enumerate(learn_mask) if k]
    initial = [stationary] * len(reg.lines)
    line_index = getattr(em, "line_index", None)
    if line_index is None:
        line_index = list(range(len(em.initial)))
    done = set()
    for row, w in enumerate(line_index):
        line = owner[int(w)]
        if line not in done:
            initial[learned_pos[line]] = np.asarray(em.initial[row])
            done.add(line)
    return Learned(em, selection, initial, learn_mask, rows)
