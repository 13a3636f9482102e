"""Benchmark of identification: EM learning, hmmlearn side by side, NL-means re-smoothing.

Run: ``.venv/bin/python benchmarks/bench_identification.py``

1. EM to convergence on 74 lines × 200 points, N = 2, with realistic MA
   coefficients (p = 10 and p = 4), data drawn from the model.
2. The order-0 special case (white noise with switching variance) by
   :func:`fit_em` and by hmmlearn ``GaussianHMM`` for the same number of
   iterations from the same start; time ratio and largest parameter difference.
3. NL-means re-smoothing of a 100-line × 200-point recognition map
   (line spacing 2 km, 1 km along line, max_rho 15 km): median of repeats,
   at the paper's (h, ρ) = (1.4 /km, 5 km), the default (0.5 /km, 10 km) and ρ = 15 km.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core.mjls_em import fit_em, sample_ma_mixture, single_thread_blas  # noqa: E402
from app.core.nlmeans import RecognitionMap  # noqa: E402


def simulate(rng, c, d, Qs, Rs, a, T, W):
    return sample_ma_mixture(rng, c, d, Qs, Rs, a, T, W)[0]


def bench_em(rng):
    a = np.array([[0.9876, 0.0124], [0.0303, 0.9697]])
    Q, R = [0.0414, 0.3533], [1.68]
    cases = {
        "p=10": (30.0 * np.hanning(13)[1:-1], 0.02 * np.array([1, -3, 3, -1, 0.5, 0.2])),
        "p=4": (10.0 * np.hanning(7)[1:-1], 0.05 * np.array([1.0, -3.0, 3.0, -1.0])),
    }
    for name, (c, d) in cases.items():
        xs = simulate(rng, c, d, Q, R, a, 200, 74)
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            res = fit_em(xs, c, d, n_q=2, n_r=1)
            times.append(time.perf_counter() - t0)
        print(f"EM 74x200 N=2 {name}: median {statistics.median(times):.2f} s "
              f"({len(res.iterations) - 1} iterations, converged={res.converged}); "
              f"Q={np.round(res.Q, 4)} (true {Q}), R={np.round(res.R, 3)} (true {R}), "
              f"a_ii={np.round(np.diag(res.transition), 4)} (true {np.diag(a)})")


def bench_hmmlearn(rng):
    try:
        from hmmlearn import hmm
    except ImportError:
        print("hmmlearn not installed: skipped")
        return
    a = np.array([[0.9876, 0.0124], [0.0303, 0.9697]])
    xs = simulate(rng, [1.0], [0.0], [0.0414, 0.3533], [1.0], a, 200, 74)
    Q0, a0, pi0 = np.array([0.1, 1.0]), np.array([[0.95, 0.05], [0.05, 0.95]]), np.array([0.5, 0.5])
    n_iter = 30
    t0 = time.perf_counter()
    res = fit_em(xs, [1.0], [0.0], Q_init=Q0, R_init=[1.0], transition_init=a0, initial_init=pi0,
                 max_iter=n_iter, tol=0.0, shared_initial=True)
    t_ours = time.perf_counter() - t0
    X = np.concatenate(xs)[:, None]
    m = hmm.GaussianHMM(n_components=2, covariance_type="diag", params="stmc", init_params="",
                        n_iter=n_iter, tol=-np.inf, covars_prior=0.0, covars_weight=1.0,
                        means_prior=0.0, means_weight=1e12)
    m.startprob_, m.transmat_, m.means_, m.covars_ = pi0, a0, np.zeros((2, 1)), Q0[:, None]
    import logging
    logging.getLogger("hmmlearn").setLevel(logging.ERROR)
    with single_thread_blas():
        t0 = time.perf_counter()
        m.fit(X, lengths=[len(x) for x in xs])
        t_hmm = time.perf_counter() - t0
    cov = m._covars_[:, 0]
    o = np.argsort(cov)
    dq = np.max(np.abs(res.Q / cov[o] - 1))
    da = np.max(np.abs(res.transition - m.transmat_[np.ix_(o, o)]))
    print(f"order-0 case, {n_iter} EM iterations, 74x200: ours {t_ours:.2f} s, hmmlearn {t_hmm:.2f} s, "
          f"ratio {t_ours / t_hmm:.1f}; max rel diff Q {dq:.1e}, max abs diff a_ij {da:.1e}")


def bench_nlmeans(rng):
    e, n = np.meshgrid(np.arange(0.0, 200.0, 1.0), np.arange(0.0, 200.0, 2.0))
    e, n = e.ravel(), n.ravel()
    t0 = time.perf_counter()
    rm = RecognitionMap(e, n, max_rho_km=15.0)
    t_build = time.perf_counter() - t0
    labels = rng.integers(0, 2, e.size)
    P = rng.dirichlet(np.ones(2), size=e.size)
    for mode, v in (("hard", labels), ("soft", P)):
        for h, rho in ((1.4, 5.0), (0.5, 10.0), (1.4, 15.0)):
            times = []
            for _ in range(7):
                t0 = time.perf_counter()
                rm.smooth(v, h_per_km=h, rho_km=rho, mode=mode)
                times.append(time.perf_counter() - t0)
            print(f"NL-means 100x200 ({e.size} points, {rm.n_pairs} pairs <= 15 km, build {t_build:.2f} s): "
                  f"{mode} h={h:g} /km rho={rho:g} km median {1e3 * statistics.median(times):.0f} ms")


if __name__ == "__main__":
    rng = np.random.default_rng(0)
    bench_em(rng)
    bench_hmmlearn(rng)
    bench_nlmeans(rng)
