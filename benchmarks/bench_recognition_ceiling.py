"""How accurate can the recognition map be on the markov preset?  (issue #3)

Run: ``.venv/bin/python benchmarks/bench_recognition_ceiling.py [n_seeds]``

Exact-model simulation with the geometry and Θ of the ``markov`` preset (seed 000
Table 1/2): 50 east–west lines × 110 km, 2 km apart, decimated points every 1 km;
the state map is the simulator's thresholded smooth random field
(:func:`app.simulate.markov.make_state_map`); each line's decimated sequence is drawn
*exactly* from the MA model of the regularization (``x_k = Σ c_l q_{k−l} + Σ d_l r_{k−l}``,
``Var q = Q(state)``, m = 1, 10 Hz, 100 m/s), so the recognition model is right and Θ
is the truth.  What remains is the information in the data.

Printed per seed, the fraction of points whose state is right for

* ``line``      per-line Viterbi (seed 000 §4.3, no spatial information);
* ``pooled``    per-line Viterbi with the neighbouring lines' evidence (``stages.pooled_evidence``:
  h = 0.7 /km, ρ = 5 km);
* ``nl 1.4/5``  NL-means (soft) of the pooled posteriors with the paper's h = 1.4 /km, ρ = 5 km;
* ``nl 0.5/10`` the same with h = 0.5 /km, ρ = 10 km;
* ``lin*``      best kernel smoothing of the per-point log-likelihood ratio, kernel
  ``exp(−h·d)``, radius and threshold **chosen with the truth** (an optimistic bound
  for any linear smoothing);
* ``potts*``    exact MAP of a Potts random field (along-line and cross-line couplings,
  minimum cut) with the coupling **chosen with the truth**.

On seeds 0–2 all of them stay below 0.95 (≈ 0.90–0.94): the per-point evidence
is weak (the GNSS noise dominates x above ≈ 0.008 Hz, wavelengths < 12 km), so
no smoothing of it reaches 0.95 on these maps.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, maximum_flow
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.ma_approx import fit_ma_model  # noqa: E402
from app.core.nlmeans import RecognitionMap  # noqa: E402
from app.core.recognition import recognize_lines, state_evidence  # noqa: E402
from app.core.regularize import design_regularization  # noqa: E402
from app.simulate.markov import make_state_map  # noqa: E402

Q_TRUE = np.array([0.0414, 0.3533])
R_TRUE = 1.6787
A_TRUE = np.array([[0.9876, 0.0124], [0.0303, 0.9697]])


def simulate(seed: int, c, d, n_lines: int = 50, length_km: float = 110.0, spacing_km: float = 2.0):
    """Lines (x, truth states, easting, northing) from the exact MA model on a simulator state map."""
    rng = np.random.default_rng(seed)
    rows = (np.arange(n_lines) - (n_lines - 1) / 2.0) * spacing_km
    half = length_km / 2.0
    smap = make_state_map((-half, half, rows.min(), rows.max()), A_TRUE[0, 0], A_TRUE[1, 1], rng,
                          1.0, rows_y_km=rows, row_x_km=(-half, half))
    xk = np.arange(-half + 0.5, half, 1.0)
    pad = max(len(c), len(d))
    xs, ss, es, ns = [], [], [], []
    for y in rows:
        s = smap.state(xk, np.full(xk.size, y))
        sp_ = np.r_[np.full(pad, s[0]), s]
        q = rng.standard_normal(sp_.size) * np.sqrt(Q_TRUE[sp_])
        r = rng.standard_normal(sp_.size) * np.sqrt(R_TRUE)
        x = np.convolve(q, c)[:sp_.size] + np.convolve(r, d)[:sp_.size]
        xs.append(x[pad:])
        ss.append(s)
        es.append(xk.copy())
        ns.append(np.full(xk.size, y))
    return xs, ss, np.concatenate(es), np.concatenate(ns)


def potts_map(llr, pairs_i, pairs_j, weights, scale: float = 1000.0) -> np.ndarray:
    """Exact MAP of a binary Potts field by minimum cut: minimise
    ``Σ_i −llr_i·s_i + Σ_(i,j) w_ij·[s_i ≠ s_j]`` over ``s ∈ {0, 1}^T``."""
    T = llr.size
    s, t = T, T + 1
    u1 = np.maximum(-llr, 0.0)   # cost of state 1 (beyond the cheaper one)
    u0 = np.maximum(llr, 0.0)    # cost of state 0
    rows = np.r_[np.full(T, s), np.arange(T), pairs_i, pairs_j]
    cols = np.r_[np.arange(T), np.full(T, t), pairs_j, pairs_i]
    cap = np.round(np.r_[u0, u1, weights, weights] * scale).astype(np.int32)
    C = sp.csr_matrix((cap, (rows, cols)), shape=(T + 2, T + 2))
    C.sum_duplicates()
    resid = C - maximum_flow(C, s, t).flow
    resid.data[resid.data < 0] = 0
    resid.eliminate_zeros()
    reach = breadth_first_order(resid, s, directed=True, return_predecessors=False)
    lab = np.zeros(T, dtype=int)
    lab[reach[reach < T]] = 1    # source side: the edge to the sink (cost of state 1) not cut
    return lab


def run(seed: int, c, d) -> dict:
    xs, ss, e, n = simulate(seed, c, d)
    truth = np.concatenate(ss)
    line = np.concatenate([np.full(len(x), w) for w, x in enumerate(xs)])
    pi = np.array([0.7, 0.3])
    rm = RecognitionMap(e, n, max_rho_km=15.0)
    out = {}
    paths, _ = recognize_lines(xs, c, d, Q_TRUE, [R_TRUE], A_TRUE, pi)
    out["line"] = np.mean(np.concatenate(paths) == truth)
    llr = np.concatenate([state_evidence(x, c, d, Q_TRUE, [R_TRUE])[:, 1] for x in xs])
    ev = np.column_stack([np.zeros_like(llr), llr])
    pooled = rm.neighbour_sum(ev, 0.7, 5.0, groups=line)
    extra = np.split(pooled, np.cumsum([len(x) for x in xs])[:-1])
    paths, probs = recognize_lines(xs, c, d, Q_TRUE, [R_TRUE], A_TRUE, pi, extra_loglik=extra)
    out["pooled"] = np.mean(np.concatenate(paths) == truth)
    P = np.concatenate(probs)
    for h, rho in ((1.4, 5.0), (0.5, 10.0)):
        out[f"nl {h:g}/{rho:g}"] = np.mean(rm.smooth(P, h, rho, "soft")[1] == truth)
    best = 0.0
    ones = np.ones_like(llr)
    for h in (0.1, 0.2, 0.3, 0.5, 0.7):
        for rho in (5.0, 8.0, 12.0):
            m = (rm.neighbour_sum(llr, h, rho) + llr) / (rm.neighbour_sum(ones, h, rho) + 1.0)
            best = max(best, max(np.mean((m > thr) == truth) for thr in np.linspace(-0.1, 0.1, 21)))
    out["lin*"] = best
    # Potts: along-line links of coupling J, cross-line links to the points of the neighbouring
    # lines within 2.5 km weighted by exp(-d) and scaled so that one point's links to one
    # neighbouring line sum to J·step/spacing = J/2 on average (a boundary costs the same per km
    # whether it crosses the lines or runs between them)
    i_al = np.flatnonzero(line[:-1] == line[1:])
    xy = np.column_stack([e, n])
    pr = cKDTree(xy).query_pairs(2.5, output_type="ndarray")
    pr = pr[line[pr[:, 0]] != line[pr[:, 1]]]
    w_cross = np.exp(-np.hypot(*(xy[pr[:, 0]] - xy[pr[:, 1]]).T))
    per_point_per_line = 2.0 * w_cross.sum() / e.size / 2.0
    w_cross *= 0.5 / per_point_per_line
    best = 0.0
    for J in (0.4, 0.6, 0.8, 1.0, 1.2, 1.5):
        lab = potts_map(llr, np.r_[i_al, pr[:, 0]], np.r_[i_al + 1, pr[:, 1]],
                        np.r_[np.full(i_al.size, J), J * w_cross])
        best = max(best, np.mean(lab == truth))
    out["potts*"] = best
    return out


def main(n_seeds: int = 3):
    design = design_regularization(0.1, 100.0, step_km=1.0)
    ma = fit_ma_model(design, 1)
    c, d = np.asarray(ma.c, float), np.asarray(ma.d, float)
    print(f"MA model m=1: K={len(c) - 1}, L={len(d) - 1}")
    for seed in range(n_seeds):
        t0 = time.perf_counter()
        res = run(seed, c, d)
        print(f"seed {seed}: " + "  ".join(f"{k} {v:.3f}" for k, v in res.items())
              + f"  ({time.perf_counter() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
