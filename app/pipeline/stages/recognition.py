"""Stages 6–7, recognition (SPEC §2 steps 3–4): the MAP state path and posterior state
probabilities per line (with the neighbouring lines' evidence about the anomaly intensity
pooled in), then the recognition map smoothed by NL-means (h, ρ) and the state chosen at
every decimated point.

:func:`state_map` is the one function that turns the raw posteriors into the map a filter
uses; the web's recognition endpoint calls it too, so the map the page shows for (h, ρ) is
the map a ``filter`` job with those values uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from app.config import SurveyConfig
from app.core.nlmeans import RecognitionMap
from app.core.recognition import recognize_lines, state_evidence, stationary_distribution
from app.pipeline.stages.regularization import Regularized, join_stretches, split_stretches


def pooled_evidence(reg: Regularized, em, h_per_km: float, rho_km: float, stretches: list | None = None) -> list | None:
    """Cross-line evidence for each line's recognition (the anomaly-intensity part only).

    Each decimated point's log-evidence for the Q levels (relative to the smoothest),
    summed with weights ``exp(−h·d)`` over the points of *other* lines within ``ρ``:
    the anomaly's statistics are a property of the place, so neighbouring lines carry
    evidence about it; the GNSS noise levels are not (episodes are in time), so the
    R part is marginalised out before pooling.  The evidence is taken per stretch between holes
    (``stretches``: :func:`split_stretches`' pieces of ``reg.x``, computed when not given).
    Returns one (T_w, N) array per line, or None when pooling is off (ρ = 0)."""
    if rho_km <= 0 or len(reg.x) < 2:
        return None
    n_q, n_r = len(em.Q), len(em.R)
    stretches = split_stretches(reg)[0] if stretches is None else stretches
    ev = np.concatenate([state_evidence(x, reg.ma.c, reg.ma.d, em.Q, em.R) for x in stretches])
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
    extra = None
    # each stretch without missing epochs on its own (split_stretches): the line's initial
    # probabilities start its first, the chain's stationary distribution the others
    seqs, owner = split_stretches(reg)
    if cfg is not None:
        p = cfg.processing
        extra = pooled_evidence(reg, em, p.recognition_pool_h_per_km, p.recognition_pool_rho_km, seqs)
    stationary = stationary_distribution(np.asarray(em.transition))
    initial = np.asarray(em.initial, float)
    starts = [initial[w] if k == 0 or owner[k - 1] != w else stationary for k, w in enumerate(owner)]
    paths, probs = recognize_lines(seqs, reg.ma.c, reg.ma.d, em.Q, em.R, em.transition, np.asarray(starts),
                                   extra_loglik=None if extra is None else split_stretches(reg, extra)[0])
    paths = join_stretches([np.asarray(s, int) for s in paths], owner, len(reg.x))
    return paths, join_stretches([np.asarray(p, float) for p in probs], owner, len(reg.x))


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
    if rmap is None:
        rmap = RecognitionMap(table["easting_km"].to_numpy(), table["northing_km"].to_numpy(),
                              max_rho_km=max(15.0, rho_km))
    if mode == "soft":
        src = table[[f"p_{i}" for i in range(n_states)]].to_numpy()
    else:
        src = table["state_raw"].to_numpy()
    probs, labels = rmap.smooth(src, h_per_km, rho_km, mode=mode)
    return np.asarray(labels, int), np.asarray(probs, float), rmap


def choose_states(raw_probs: np.ndarray, smoothed_probs: np.ndarray, n_q: int, n_r: int) -> np.ndarray:
    """The state at every decimated point from the smoothed map (the pipeline's rule).

    The anomaly intensity is a property of the place, the GNSS noise level of the moment:
    the Q level is decided on the smoothed map's marginal, the R level on the line's own
    (raw) posterior given that Q level.  With one R level this is the smoothed map's argmax.

    Parameters
    ----------
    raw_probs, smoothed_probs : ndarray, shape (T, N1·N2)
    n_q, n_r : int
    """
    sm = np.asarray(smoothed_probs, float)
    if n_r == 1:
        return sm.argmax(axis=1).astype(int)
    raw = np.asarray(raw_probs, float).reshape(-1, n_q, n_r)
    i_q = sm.reshape(-1, n_q, n_r).sum(axis=2).argmax(axis=1)
    j_r = raw[np.arange(len(i_q)), i_q, :].argmax(axis=1)
    return (i_q * n_r + j_r).astype(int)


@dataclass
class Recognition:
    """Result of :func:`recognize_survey`: the decimated points with their raw posteriors.

    ``table``: line, time, easting_km, northing_km, x, state_raw, p_0 … p_{N−1} (raw).
    """

    table: pd.DataFrame
    n_q: int
    n_r: int

    @property
    def n_states(self) -> int:
        return self.n_q * self.n_r


def recognize_survey(reg: Regularized, theta, cfg: SurveyConfig) -> Recognition:
    """Stage 6: Viterbi paths and posteriors of every regularized line."""
    paths, probs = recognize(reg, theta, cfg)
    return Recognition(recognition_table(reg, paths, probs), len(theta.Q), len(theta.R))


@dataclass
class StateMap:
    """Result of :func:`state_map`: the smoothed recognition map and the chosen states.

    Attributes
    ----------
    states : ndarray of int, shape (T,)
    probs : ndarray, shape (T, N)
        Smoothed state probabilities.
    h_per_km, rho_km : float
    mode : str
    """

    states: np.ndarray
    probs: np.ndarray
    h_per_km: float
    rho_km: float
    mode: str

    def table(self, recognition: Recognition) -> pd.DataFrame:
        """``recognition.parquet`` (SPEC §5): raw state, smoothed state, smoothed p_i."""
        rec = recognition.table.copy()
        rec["state_smoothed"] = self.states
        for i in range(recognition.n_states):
            rec[f"p_{i}"] = self.probs[:, i]
        cols = ["line", "time", "easting_km", "northing_km", "x", "state_raw", "state_smoothed"]
        return rec[cols + [f"p_{i}" for i in range(recognition.n_states)]]


def state_map(recognition: Recognition, h_per_km: float, rho_km: float, mode: str = "soft",
              rmap=None) -> StateMap:
    """Stage 7: NL-means over the raw posteriors, then :func:`choose_states`."""
    t = recognition.table
    labels, probs, _ = smooth_recognition(t, recognition.n_states, h_per_km, rho_km, mode, rmap=rmap)
    if recognition.n_r == 1:
        states = labels  # NL-means's own choice (argmax, or the vote in 'hard' mode)
    else:
        raw = t[[f"p_{i}" for i in range(recognition.n_states)]].to_numpy()
        states = choose_states(raw, probs, recognition.n_q, recognition.n_r)
    return StateMap(states, probs, float(h_per_km), float(rho_km), mode)
