"""Benchmark: seed-000 Kalman smoother (m = 2, time-varying Q and R, mean + variance).

Times :func:`app.core.smoother.kalman_smooth` (modified Bryson–Frazier, default, and
RTS) on a long synthetic line, and, on the same data in the same run:

* filterpy: ``KalmanFilter`` loop (Q set per step, Joseph update) + ``rts_smoother``;
  timed on a shorter slice and scaled per epoch;
* simdkalman: its smoother on the same slice (stationary only: simdkalman takes one
  process-noise matrix, so it gets the mean Q and R — a generous comparison);
* :func:`app.core.smoother.smooth_many` on lines of 10 000 epochs.

It also checks that filterpy gives the same answer on the slice.

Run: ``.venv/bin/python benchmarks/bench_smoother.py [--n 1000000] [--slice 20000] [--json out.json]``
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from app.core.smoother import kalman_smooth, rts_smooth, smooth_many
from app.core.statespace import build_model, process_covariance


def simulate(n, dt=0.1, seed=0):
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    Q = np.where((k // 3000) % 2 == 0, 1e-5, 1e-3)
    R = np.where((k // 5000) % 3 == 0, 4.0, 1.0)
    dg = np.cumsum(np.cumsum(rng.normal(size=n) * np.sqrt(Q)))
    r = rng.normal(size=n + 1) * np.sqrt(np.r_[R[0], R])
    z = dg - 1000.0 * np.diff(r) / dt
    return z, Q, R, dg


def best_of(fn, repeat):
    best = np.inf
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def run_filterpy(z, Q, R, dt, m, x0, P0):
    from filterpy.kalman import KalmanFilter

    A, _, C = build_model(m, dt)
    n = m + 2
    kf = KalmanFilter(dim_x=n, dim_z=1)
    kf.F = A
    kf.H = C
    kf.R = np.zeros((1, 1))
    kf.x = x0.copy()
    kf.P = P0.copy()
    N = z.size
    Xs = np.empty((N, n))
    Ps = np.empty((N, n, n))
    Qs = np.empty((N, n, n))
    for k in range(N):
        W = process_covariance(m, Q[k], R[k])
        Qs[k] = W
        if k > 0:
            kf.predict(Q=W)
        kf.update(z[k])
        Xs[k] = kf.x
        Ps[k] = kf.P
    # filterpy's rts_smoother uses Fs[k+1], Qs[k+1] for the step k -> k+1, as we do
    xs, Pss, _, _ = kf.rts_smoother(Xs, Ps, Fs=[A] * N, Qs=Qs)
    return xs[:, 0], np.sqrt(Pss[:, 0, 0])


def run_simdkalman(z, Q, R, dt, m, x0, P0):
    import simdkalman

    A, _, C = build_model(m, dt)
    kf = simdkalman.KalmanFilter(state_transition=A,
                                 process_noise=process_covariance(m, float(np.mean(Q)), float(np.mean(R))),
                                 observation_model=C, observation_noise=1e-12)
    res = kf.smooth(z[None, :], initial_value=x0, initial_covariance=P0)
    return res.states.mean[0, :, 0], np.sqrt(res.states.cov[0, :, 0, 0])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--slice", type=int, default=20_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    dt, m = 0.1, 2
    z, Q, R, dg = simulate(a.n, dt)
    kalman_smooth(z[:1000], Q[:1000], R[:1000], dt, m, "bf")  # compile / load cache
    kalman_smooth(z[:1000], Q[:1000], R[:1000], dt, m, "rts")
    out = {"n": a.n, "slice": a.slice}
    t_bf, res = best_of(lambda: kalman_smooth(z, Q, R, dt, m, "bf"), a.repeat)
    t_rts, _ = best_of(lambda: kalman_smooth(z, Q, R, dt, m, "rts"), a.repeat)
    out["bf_epochs_per_s"] = a.n / t_bf
    out["rts_epochs_per_s"] = a.n / t_rts
    print(f"kalman_smooth bf : {a.n:>9d} epochs in {t_bf:7.3f} s = {a.n / t_bf / 1e6:6.2f} M epochs/s")
    print(f"kalman_smooth rts: {a.n:>9d} epochs in {t_rts:7.3f} s = {a.n / t_rts / 1e6:6.2f} M epochs/s")
    err = res.dg_mgal - dg
    print(f"  check: RMS error {np.sqrt(np.mean(err**2)):.3f} mGal, "
          f"|err|<2σ for {np.mean(np.abs(err) < 2 * res.dg_std_mgal) * 100:.1f} % of epochs")

    lines = [z[i:i + 10_000] for i in range(0, a.n - 10_000 + 1, 10_000)]
    ql = [Q[i:i + 10_000] for i in range(0, a.n - 10_000 + 1, 10_000)]
    rl = [R[i:i + 10_000] for i in range(0, a.n - 10_000 + 1, 10_000)]
    t_many, _ = best_of(lambda: smooth_many(lines, ql, rl, dt, m), 1)
    n_many = 10_000 * len(lines)
    out["smooth_many_epochs_per_s"] = n_many / t_many
    print(f"smooth_many      : {len(lines)} lines × 10000 in {t_many:7.3f} s = {n_many / t_many / 1e6:6.2f} M epochs/s")

    S = min(a.slice, a.n)
    zs, Qs, Rs = z[:S], Q[:S], R[:S]
    n = m + 2
    x0 = np.zeros(n)
    x0[:m] = np.mean(zs[:1000])
    P0 = np.diag([1e6] * m + [Rs[0], Rs[0]])
    ours = kalman_smooth(zs, Qs, Rs, dt, m, "bf", x0=x0, P0=P0)
    try:
        t_fp, (fp_mean, fp_std) = best_of(lambda: run_filterpy(zs, Qs, Rs, dt, m, x0, P0), 1)
        rate = S / t_fp
        out["filterpy_epochs_per_s"] = rate
        out["ratio_vs_filterpy"] = out["bf_epochs_per_s"] / rate
        print(f"filterpy KF+RTS  : {S:>9d} epochs in {t_fp:7.3f} s = {rate / 1e3:8.1f} k epochs/s"
              f"  -> bf is {out['ratio_vs_filterpy']:.0f}× faster")
        print(f"  agreement on the slice: max|Δmean| = {np.max(np.abs(fp_mean - ours.dg_mgal)):.2e} mGal, "
              f"max rel|Δstd| = {np.max(np.abs(fp_std / ours.dg_std_mgal - 1)):.2e}")
    except ImportError:
        print("filterpy not installed")
    # third opinion on a shorter slice: the plain-numpy generic RTS (lstsq gain, Joseph update)
    S2 = min(5000, S)
    A, _, C = build_model(m, dt)
    W = np.array([process_covariance(m, q, r) for q, r in zip(Qs[:S2], Rs[:S2])])
    xs, Ps, _ = rts_smooth(A, W, C, np.zeros((1, 1)), zs[:S2], x0, P0)
    ours2 = kalman_smooth(zs[:S2], Qs[:S2], Rs[:S2], dt, m, "bf", x0=x0, P0=P0)
    print(f"  generic numpy RTS on {S2} epochs: max|Δmean| = {np.max(np.abs(xs[:, 0] - ours2.dg_mgal)):.2e} mGal, "
          f"max rel|Δstd| = {np.max(np.abs(np.sqrt(Ps[:, 0, 0]) / ours2.dg_std_mgal - 1)):.2e}")
    try:
        t_sk, (sk_mean, _) = best_of(lambda: run_simdkalman(zs, Qs, Rs, dt, m, x0, P0), 1)
        rate = S / t_sk
        out["simdkalman_epochs_per_s"] = rate
        out["ratio_vs_simdkalman"] = out["bf_epochs_per_s"] / rate
        print(f"simdkalman (stat): {S:>9d} epochs in {t_sk:7.3f} s = {rate / 1e3:8.1f} k epochs/s"
              f"  -> bf is {out['ratio_vs_simdkalman']:.0f}× faster (one series; simdkalman "
              f"vectorises across series, not time)")
    except ImportError:
        print("simdkalman not installed")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(out, fh, indent=2)
    return out


if __name__ == "__main__":
    main()
