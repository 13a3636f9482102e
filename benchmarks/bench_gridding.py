"""Benchmark: grid 100 lines × 100 km (10 m sampling) at 1 km cells.

Compares :class:`app.core.gridding.Collocation` (local neighbourhoods, with
posterior std) with :class:`app.core.gridding.Spline`, ``scipy.interpolate.griddata``
(cubic) on the same block means, and ``verde.Spline`` on 2 km block medians
(verde's dense solve cannot take the 0.5 km data).  Also times crossover search
and leveling on the same survey.  The field is analytic (a sum of Gaussian
bumps), so every method's RMS against the truth is reported too.

Run: ``.venv/bin/python benchmarks/bench_gridding.py [--lines 100] [--length-km 100] [--json out.json]``
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def field(e, n, seed=0, n_bumps=300, extent=100.0):
    rng = np.random.default_rng(seed)
    ce = rng.uniform(-10, extent + 10, n_bumps)
    cn = rng.uniform(-10, extent + 10, n_bumps)
    w = rng.uniform(2.0, 8.0, n_bumps)
    a = rng.normal(0, 15.0, n_bumps)
    out = np.zeros_like(e)
    for k in range(n_bumps):
        out += a[k] * np.exp(-((e - ce[k]) ** 2 + (n - cn[k]) ** 2) / (2 * w[k] ** 2))
    return out


def survey(n_lines=100, length_km=100.0, step_km=0.01, n_ties=10, noise_mgal=1.0, seed=1):
    rng = np.random.default_rng(seed)
    spacing = length_km / (n_lines - 1)
    es, ns, labs = [], [], []
    x = np.arange(0.0, length_km + 1e-9, step_km)
    for k in range(n_lines):
        es.append(x)
        ns.append(np.full_like(x, k * spacing))
        labs.append(np.full(x.size, k))
    for j in range(n_ties):
        es.append(np.full_like(x, (j + 0.5) * length_km / n_ties))
        ns.append(x)
        labs.append(np.full(x.size, n_lines + j))
    e = np.concatenate(es)
    n = np.concatenate(ns)
    lab = np.concatenate(labs)
    truth = field(e, n, extent=length_km)
    # smoothed-estimate-like errors: white noise low-passed over ~1 km
    from scipy.ndimage import uniform_filter1d
    noise = uniform_filter1d(rng.standard_normal(e.size), 100) * np.sqrt(100) * noise_mgal
    return e, n, lab, truth + noise, np.full(e.size, noise_mgal)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--lines", type=int, default=100)
    ap.add_argument("--length-km", type=float, default=100.0)
    ap.add_argument("--spacing-km", type=float, default=1.0)
    ap.add_argument("--json", default=None)
    ap.add_argument("--skip-verde", action="store_true")
    args = ap.parse_args(argv)

    from scipy.interpolate import griddata

    from app.core.accuracy import grid_rms_in_hull, std_calibration
    from app.core.gridding import Collocation, Spline, block_thin
    from app.core.leveling import LineTrack, find_crossovers, level_lines

    t0 = time.perf_counter()
    e, n, lab, dg, std = survey(args.lines, args.length_km)
    print(f"survey: {e.size} points, {np.unique(lab).size} lines ({time.perf_counter() - t0:.1f} s to simulate)")
    out = {"n_points": int(e.size), "n_lines": int(np.unique(lab).size)}

    # crossovers + leveling (time = 10 s per km along each line)
    lines = {}
    for k in np.unique(lab):
        m = lab == k
        t = 1e5 * k + np.arange(m.sum()) * 0.1
        lines[str(k)] = LineTrack(e[m], n[m], t, dg[m], std[m], "main" if k < args.lines else "tie")
    t0 = time.perf_counter()
    x = find_crossovers(lines)
    out["crossovers_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    lev = level_lines(x, {k: (v.time_s[0], v.time_s[-1]) for k, v in lines.items()}, degree=1)
    out["leveling_s"] = time.perf_counter() - t0
    out["n_crossovers"] = int(len(x))
    print(f"crossovers: {len(x)} in {out['crossovers_s']:.2f} s; leveling {out['leveling_s']:.2f} s "
          f"(rms {lev.rms_before:.3f} -> {lev.rms_after:.3f} mGal)")

    region = (0.0, args.length_km, 0.0, args.length_km)
    ge = np.arange(0.0, args.length_km + 1e-9, args.spacing_km)
    GE, GN = np.meshgrid(ge, ge)
    true_grid = field(GE.ravel(), GN.ravel(), extent=args.length_km).reshape(GE.shape)

    def report(name, seconds, grid, sd=None):
        rms = grid_rms_in_hull(ge, ge, grid, true_grid, e[::100], n[::100])
        row = {"seconds": seconds, "rms_mgal": rms}
        if sd is not None:
            row["frac_within_2sigma"] = std_calibration(grid - true_grid, sd, 2.0)
            row["median_std_mgal"] = float(np.nanmedian(sd))
        out[name] = row
        print(f"{name:>22s}: {seconds:7.2f} s   rms vs truth {rms:.3f} mGal"
              + (f"   |err|<2σ {row['frac_within_2sigma']:.3f}" if sd is not None else ""))

    t0 = time.perf_counter()
    col = Collocation(thin_km=0.5, error_corr_km=1.0).fit(e, n, dg, std, line=lab)
    t_fit = time.perf_counter() - t0
    _, _, g_col, s_col = col.grid(region=region, spacing_km=args.spacing_km)
    t_col = time.perf_counter() - t0
    out["collocation_params"] = {"variance_mgal2": col.variance_mgal2_, "length_km": col.length_km_,
                                 "nugget_mgal2": col.nugget_mgal2_, "fit_s": t_fit,
                                 "n_thinned": col.n_thinned_}
    report("collocation", t_col, g_col, s_col)

    t0 = time.perf_counter()
    _, _, g_sp, _ = Spline(thin_km=0.5).fit(e, n, dg, std, line=lab).grid(region=region, spacing_km=args.spacing_km)
    report("Spline (Clough-Tocher)", time.perf_counter() - t0, g_sp)

    t0 = time.perf_counter()
    te, tn, tv, _, _ = block_thin(e, n, dg, std, 0.5)
    g_gd = griddata((te, tn), tv, (GE, GN), method="cubic")
    report("scipy griddata cubic", time.perf_counter() - t0, g_gd)

    if not args.skip_verde:
        try:
            import verde as vd
        except ImportError:
            print("verde not installed: skipped")
        else:
            t0 = time.perf_counter()
            coords, val = vd.BlockReduce(np.median, spacing=2.0).filter((e, n), dg)
            spl = vd.Spline(damping=1e-6).fit(coords, val)
            g_vd = spl.predict((GE, GN))
            report("verde.Spline (2 km)", time.perf_counter() - t0, g_vd)
            out["ratio_collocation_vs_verde"] = out["collocation"]["seconds"] / out["verde.Spline (2 km)"]["seconds"]
    out["ratio_collocation_vs_griddata"] = out["collocation"]["seconds"] / out["scipy griddata cubic"]["seconds"]
    print(f"time ratio collocation / griddata: {out['ratio_collocation_vs_griddata']:.1f}"
          + (f"; collocation / verde.Spline: {out['ratio_collocation_vs_verde']:.2f}"
             if "ratio_collocation_vs_verde" in out else ""))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2, default=float)
    return out


if __name__ == "__main__":
    main()
