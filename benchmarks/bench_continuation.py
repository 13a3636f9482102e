"""Benchmark: equivalent-source continuation on the 74-line ``omolon`` preset (57 × 200 km + 17 ties).

The survey is the preset's own geometry (``app.simulate.motion.layout_lines``) and anomaly
(``app.simulate.field.make_field``, the same point sources), flown draped (``drape_amp_m``, default
±150 m, plane waves 5-15 km) and sampled at ``--rate-hz`` (1 Hz = 100 m; the continuation
block-averages to 500 m whatever the rate, so the rate only changes the thinning time).  The line
estimates are the true anomaly at the actual height plus along-line Gauss-Markov errors (1.5 mGal,
3 km), with their std given.  Full sensor simulation of omolon is not needed for this stage: the
continuation sees only (position, height, estimate, std).

Reports: thinning, fit (method "gb": gradient-boosted sources; α from an exact fit of a central
sub-area), prediction on a 1 km grid at the datum, local-window posterior std on that grid, peak
RSS (resource.getrusage), and the accuracy at the datum against the true field there (on the
lines and on the grid) with the std's z-score.

Run: ``.venv/bin/python benchmarks/bench_continuation.py [--rate-hz 1] [--drape-m 150] [--json out.json]``
"""

from __future__ import annotations

import argparse
import json
import resource
import time

import numpy as np


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def build(rate_hz: float, drape_m: float, seed: int = 1):
    from app.simulate.field import make_field
    from app.simulate.motion import layout_lines, make_drape
    from app.simulate.presets import PRESETS

    cfg = PRESETS["omolon"].replace(drape_amp_m=drape_m, drape_wavelength_km=(5.0, 15.0))
    rng = np.random.default_rng(seed)
    lines = layout_lines(cfg)
    step_km = cfg.speed_ms / rate_hz / 1000.0
    E, N, L = [], [], []
    for ln in lines:
        a, b = np.array(ln.start_km), np.array(ln.end_km)
        k = int(np.hypot(*(b - a)) / step_km) + 1
        P = a + np.linspace(0, 1, k)[:, None] * (b - a)
        E.append(P[:, 0])
        N.append(P[:, 1])
        L += [ln.line] * k
    x, y, lab = np.concatenate(E), np.concatenate(N), np.array(L)
    ext = (x.min(), x.max(), y.min(), y.max())
    fld = make_field(cfg, ext, 0.0, 0.0, rng)
    drape = make_drape(cfg, lines, np.random.default_rng(seed + 1)) if drape_m > 0 else None
    h = cfg.height_m + (drape(x * 1000, y * 1000) if drape is not None else 0.0)
    true = fld.at(x, y, h)
    err = np.empty(x.size)
    a = np.exp(-step_km / 3.0)
    g = np.random.default_rng(seed + 2)
    for name in np.unique(lab):
        idx = np.flatnonzero(lab == name)
        w = g.standard_normal(idx.size) * 1.5
        v = np.empty(idx.size)
        v[0] = w[0]
        for i in range(1, idx.size):
            v[i] = a * v[i - 1] + np.sqrt(1 - a * a) * w[i]
        err[idx] = v
    return cfg, fld, x * 1000, y * 1000, h, lab, true, true + err, np.full(x.size, 1.5)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rate-hz", type=float, default=1.0)
    ap.add_argument("--drape-m", type=float, default=150.0)
    ap.add_argument("--grid-km", type=float, default=1.0)
    ap.add_argument("--json")
    args = ap.parse_args()
    from app.core.continuation import fit_equivalent_sources

    t0 = time.perf_counter()
    cfg, fld, e, n, h, lab, true, obs, std = build(args.rate_hz, args.drape_m)
    t_build = time.perf_counter() - t0
    rss0 = rss_mb()
    t0 = time.perf_counter()
    model = fit_equivalent_sources(e, n, h, obs, std, lab, error_corr_m=3000.0)
    t_fit = time.perf_counter() - t0
    rss_fit = rss_mb()
    datum = cfg.height_m
    sp = args.grid_km * 1000
    gx, gy = np.meshgrid(np.arange(e.min(), e.max() + 1, sp), np.arange(n.min(), n.max() + 1, sp))
    gx, gy = gx.ravel(), gy.ravel()
    t0 = time.perf_counter()
    gp = model.predict(gx, gy, datum)
    t_pred = time.perf_counter() - t0
    t0 = time.perf_counter()
    gs = model.predict_std(gx, gy, datum)
    t_std = time.perf_counter() - t0
    rss_std = rss_mb()
    sub = slice(None, None, 10)
    lp = model.predict(e[sub], n[sub], datum)
    lt = fld.at(e[sub] / 1000, n[sub] / 1000, np.full(lp.size, datum))
    gt = fld.at(gx / 1000, gy / 1000, np.full(gx.size, datum))
    line_rms = float(np.sqrt(np.mean((obs - true) ** 2)))
    out = {
        "epochs": int(e.size), "lines": int(np.unique(lab).size), "rate_hz": args.rate_hz, "drape_m": args.drape_m,
        "blocks": model.info["n_data"], "sources": model.info["n_sources"], "method": model.method,
        "damping": model.damping, "depth_m": model.depth_m, "window_m": model.info.get("window_m"),
        "std_window_m": model.info.get("std_window_m"), "grid_nodes": int(gx.size),
        "seconds": {"build_survey": round(t_build, 1), "fit": round(t_fit, 1), "predict_grid": round(t_pred, 1),
                    "predict_std_grid": round(t_std, 1)},
        "peak_rss_mb": {"after_build": round(rss0), "after_fit": round(rss_fit), "after_std": round(rss_std)},
        "accuracy_mgal": {"line_rms_vs_truth_at_flight_height": round(line_rms, 3),
                          "continued_vs_truth_at_datum_on_lines": round(float(np.sqrt(np.mean((lp - lt) ** 2))), 3),
                          "continued_vs_truth_at_datum_grid": round(float(np.sqrt(np.mean((gp - gt) ** 2))), 3),
                          "grid_std_rms": round(float(np.sqrt(np.mean(gs ** 2))), 3),
                          "grid_z_rms": round(float(np.sqrt(np.mean(((gp - gt) / gs) ** 2))), 3)},
        "info": {k: v for k, v in model.info.items() if k not in ("gb_rmse_first_last",)},
    }
    print(json.dumps(out, indent=1, default=float))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1, default=float)


if __name__ == "__main__":
    main()
