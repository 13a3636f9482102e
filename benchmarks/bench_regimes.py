"""Sweep of simulated regimes: the default ``aerograv process`` against FIR 100 s and a
truth-tuned per-terrain oracle smoother, measured side by side in the same run.

    python benchmarks/bench_regimes.py [--only NAME ...] [--seed 1] [--workdir /tmp/aerograv-regimes]
                                       [--json out.json] [--no-oracle] [--jobs 2]

For every regime (a simulator preset plus documented overrides): simulate it (cached in
``--workdir``), run ``aerograv process SURVEY --out DIR`` with default settings in a child
process (wall time and peak RSS), then score against ``truth/``:

* RMS vs truth (first and last 10 km of each line left out, each line's mean error removed:
  what a base tie or leveling cannot see) of the default estimate ``dg_mgal``, of the FIR
  100 s column and of the stationary smoother; per terrain class where there are two; and
  the RMS with the mean errors kept, as ``lines.parquet`` holds them (``*_raw``, "raw ratio");
  and over whole lines, their ends included (``*_whole``, "whole-line ratio"; SPEC defines no
  core, and a scorer may take every epoch);
* the **oracle**: the same Kalman smoother and noise model as the product, given the TRUE
  terrain class of every epoch, with one Q per class, the noise level scale and m ∈ {1, 2}
  tuned to minimise the RMS against the truth (coordinate search in log space);
* the correlation of the estimate with the truth (line-demeaned) and the ratio of its
  along-line variance to the truth's; std coverage (|err| < 2σ), also per terrain class;
* repeat-line internal accuracy of the default and FIR estimates (report.json) and the
  share of epochs flagged by the spike repair.

Prints one table and, with ``--json``, writes every figure.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: (name, preset, overrides, description).  Overrides are SimConfig fields.
REGIMES: list[tuple[str, str, dict, str]] = [
    ("white", "omolon-mini", {}, "the sample's regime: GT-1A 18.24 Hz, 10 Hz GNSS, white velocity noise"),
    ("red", "omolon-mini", {"vu_colored_cms": 1.0, "vu_colored_tau_s": 5.0},
     "Gauss-Markov GNSS velocity error 1 cm/s, 5 s, beside the white 1.3 cm/s"),
    ("blue", "omolon-mini", {"vu_from_position_m": 0.01, "sigma_vu_cms": 0.3},
     "velocities differenced from 1 cm positions (blue), little white"),
    ("quiet", "omolon-mini", {"sigma_vu_cms": 0.5}, "quiet GNSS 0.5 cm/s"),
    ("gnss-1hz", "omolon-mini", {"gnss_rate_hz": 1.0}, "1 Hz GNSS"),
]


def _extra_regimes() -> list:
    """Regimes of the realistic presets (docs/SIMULATOR.md), when this checkout has them."""
    from app.simulate.presets import PRESETS

    extra = [
        ("testline-2hz", "testline-2hz", {}, "one 40 km line flown 4x, 2 Hz platform, heights-only GNSS"),
        ("platform-1hz", "platform-1hz", {}, "platform gravimeter, 1 Hz interval means"),
        ("platform-2hz-point", "platform-2hz-point", {}, "platform gravimeter, 2 Hz point samples"),
        ("platform-10hz-point", "platform-10hz-point", {}, "platform gravimeter, 10 Hz point samples"),
        ("heights-only-1hz", "heights-only-1hz", {}, "heights-only GNSS 1 Hz, coloured height error"),
        ("heights-only-5hz", "heights-only-5hz", {}, "heights-only GNSS 5 Hz, coloured height error"),
        ("draped", "draped", {}, "draped flight ±50 m"),
        ("turbulent", "turbulent", {}, "0.3-0.5 m/s² turbulence with a real aircraft's spectrum"),
    ]
    return [r for r in extra if r[1] in PRESETS]


def simulate(preset: str, overrides: dict, out: Path, seed: int) -> Path:
    from app.simulate import simulate_survey

    if not (out / "survey.toml").exists():
        simulate_survey(preset, out, seed=seed, **overrides)
    return out


def process(survey: Path, out: Path, params: str | None = None) -> dict:
    cmd = [sys.executable, "-m", "app.cli", "process", str(survey), "--out", str(out)]
    if params:
        cmd += ["--params", params]
    t0 = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(f"process failed on {survey}: {r.stderr[-2000:]}")
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {"wall_s": wall, "peak_rss_mb": max(peak, before) / 1024.0}


def _core(m: pd.DataFrame, edge_km: float = 10.0) -> pd.DataFrame:
    """The scored epochs: ``edge_km`` left out at both ends of every line; on a survey whose
    main lines are all shorter than 2 × ``edge_km`` (12 km random layouts), a fifth of each line."""
    L = m.groupby("line")["along_km"].transform("max")
    main = L[m["kind"] == "main"] if "kind" in m else L
    if float(main.max() if len(main) else L.max()) < 2.0 * edge_km:
        edge = L / 5.0
        return m[(m["along_km"] >= edge) & (m["along_km"] <= L - edge) & m["dg_true_mgal"].notna()]
    return m[(m["along_km"] >= edge_km) & (m["along_km"] <= L - edge_km) & m["dg_true_mgal"].notna()]


def _demeaned_rms(core: pd.DataFrame, col: str) -> float:
    e = core[col] - core["dg_true_mgal"]
    e = e - e.groupby(core["line"]).transform("mean")
    return float(np.sqrt(np.mean(e ** 2)))


def noise_from_report(report: dict):
    """The noise model ``report.json`` describes (:meth:`app.core.noise_model.NoiseModel.from_description`)."""
    from app.core.noise_model import NoiseModel

    return NoiseModel.from_description(report["noise_model"])


def oracle(survey: Path, out: Path, merged: pd.DataFrame) -> dict:
    """Truth-tuned per-terrain smoother (module docstring)."""
    from scipy.optimize import minimize_scalar

    from app.core.smoother import kalman_smooth

    rep = json.loads((out / "report.json").read_text())
    noise = noise_from_report(rep)
    dt = rep["noise_model"]["dt_s"]
    classes = sorted(merged["terrain"].dropna().unique())
    lines = []
    for _line, g in merged.groupby("line", sort=False):
        g = g.sort_values("time")
        if len(g) < 50:
            continue
        L = g["along_km"].max()
        keep = ((g["along_km"] >= 10.0) & (g["along_km"] <= L - 10.0)).to_numpy()
        lines.append((g["z_mgal"].to_numpy(), g["R_cm2s2"].to_numpy(), g["terrain"].to_numpy(),
                      g["dg_true_mgal"].to_numpy(), keep))

    def rms(logq: dict, log_a: float, m: int) -> float:
        errs = []
        for z, r, terr, truth, keep in lines:
            q = np.ones(z.size)
            for c in classes:
                q[terr == c] = np.exp(logq[c])
            try:
                est = kalman_smooth(z, q, np.exp(log_a) * r, dt, m=m, noise=noise).dg_mgal
            except (ValueError, FloatingPointError):
                return 1e9
            e = (est - truth)[keep]
            if e.size:
                errs.append(e - e.mean())
        e = np.concatenate(errs)
        return float(np.sqrt(np.mean(e ** 2)))

    best = None
    for m in (1, 2):
        logq = {c: np.log(1e-3 if m == 2 else 1e-1) for c in classes}
        log_a = 0.0
        val = rms(logq, log_a, m)
        for _ in range(2):
            for c in classes:
                def f(v, c=c, logq=logq, log_a=log_a, m=m):   # bound now: used at once, in this pass
                    return rms({**logq, c: v}, log_a, m)
                r = minimize_scalar(f, bounds=(logq[c] - 9, logq[c] + 9), method="bounded", options={"xatol": 0.1})
                if r.fun < val:
                    logq[c], val = r.x, r.fun
            r = minimize_scalar(lambda v, logq=logq, m=m: rms(logq, v, m), bounds=(-3, 3), method="bounded", options={"xatol": 0.1})
            if r.fun < val:
                log_a, val = r.x, r.fun
        if best is None or val < best["rms"]:
            best = {"rms": val, "m": m, "Q_mgal2": {c: float(np.exp(v)) for c, v in logq.items()},
                    "R_scale": float(np.exp(log_a))}
    return best


def score(survey: Path, out: Path, with_oracle: bool = True) -> dict:
    """Every figure of one processed survey (module docstring); ``with_oracle=False`` skips
    the truth-tuned oracle (slow), whose ``rms`` is then NaN."""
    from app.pipeline.evaluate import evaluate, merge_truth

    ev = evaluate(survey, out)
    lines = pd.read_parquet(out / "lines.parquet")
    truth = pd.read_parquet(survey / "truth" / "lines.parquet")
    m = merge_truth(lines, truth)
    core = _core(m)
    res = {"epochs": int(len(core))}
    for col in ("dg_mgal", "dg_stationary_mgal", "dg_fir_mgal"):
        res[col] = _demeaned_rms(core, col)
        for terr in ("mountain", "plain"):
            sel = core["terrain"] == terr
            if sel.any() and core["terrain"].nunique() > 1:
                res[f"{col}_{terr}"] = _demeaned_rms(core[sel], col)
    for col in ("dg_mgal", "dg_fir_mgal"):  # each line's mean error kept, as lines.parquet holds it
        res[f"{col}_raw"] = float(np.sqrt(np.mean((core[col] - core["dg_true_mgal"]) ** 2)))
    whole = m[m["dg_true_mgal"].notna()]   # every epoch, line ends included (SPEC scores no core)
    for col in ("dg_mgal", "dg_fir_mgal"):
        res[f"{col}_whole"] = _demeaned_rms(whole, col)
    inside_all = np.abs(whole["dg_mgal"] - whole["dg_true_mgal"]) < 2 * whole["dg_std_mgal"]
    res["std_coverage_whole"] = float(np.mean(inside_all))
    d = core["dg_mgal"] - core.groupby("line")["dg_mgal"].transform("mean")
    t = core["dg_true_mgal"] - core.groupby("line")["dg_true_mgal"].transform("mean")
    res["corr"] = float(np.corrcoef(d, t)[0, 1])
    res["var_ratio"] = float(np.var(d) / np.var(t))
    res["truth_std"] = float(np.std(t))
    inside = np.abs(core["dg_mgal"] - core["dg_true_mgal"]) < 2 * core["dg_std_mgal"]
    res["std_coverage"] = float(np.mean(inside))
    if core["terrain"].nunique() > 1:  # the std's contrast between classes (mountains vs plains)
        res["std_coverage_by_terrain"] = {str(t): float(np.mean(inside[core["terrain"] == t]))
                                          for t in sorted(core["terrain"].dropna().unique())}
    rep = json.loads((out / "report.json").read_text())
    res["noise_family"] = rep.get("noise_model", {}).get("family")
    res["model_choice"] = rep.get("model_choice", {}).get("chosen")
    sp = rep.get("spike_repair", {})
    res["spike_fraction"] = float(sum(v.get("flagged", 0) for v in sp.values()) /
                                  max(1, sum(v.get("epochs", 0) for v in sp.values())))
    rl = rep.get("repeat_lines", {})
    if rl:
        acc = [v["internal_accuracy_mgal"] for v in rl.values()]
        res["repeat_dg"] = float(np.mean([a["dg_mgal"] for a in acc if isinstance(a.get("dg_mgal"), float)]))
        res["repeat_fir"] = float(np.mean([a["dg_fir_mgal"] for a in acc if isinstance(a.get("dg_fir_mgal"), float)]))
    res["recognition"] = ev.get("recognition", {}).get("state_smoothed")
    res["grid_rms"] = (ev.get("grid") or {}).get("rms_mgal")
    res["oracle"] = oracle(survey, out, m) if with_oracle else {"rms": float("nan")}
    return res


def run_survey(label: str, preset: str, overrides: dict, work: Path, seed: int, params: str | None = None,
               with_oracle: bool = True) -> dict:
    """Simulate (cached), process with ``params`` (default settings when None), score, and
    print one row; returns the figures."""
    survey = simulate(preset, overrides, work / f"{label}-{seed}", seed)
    out = work / f"{label}-{seed}-out"
    run = process(survey, out, params)
    s = score(survey, out, with_oracle)
    s.update(run, name=label)
    o = s["oracle"]["rms"]
    print(f"{label + '-' + str(seed):24s} adaptive {s['dg_mgal']:6.2f}  FIR {s['dg_fir_mgal']:6.2f}  ratio {s['dg_mgal'] / s['dg_fir_mgal']:5.2f}"
          f"  raw ratio {s['dg_mgal_raw'] / s['dg_fir_mgal_raw']:5.2f}"
          f"  whole-line ratio {s['dg_mgal_whole'] / s['dg_fir_mgal_whole']:5.2f}"
          f"  stationary {s['dg_stationary_mgal']:6.2f}  oracle {o:6.2f} ({s['dg_mgal'] / o:4.2f}x)"
          f"  corr {s['corr']:5.3f} var {s['var_ratio']:4.2f} cov2σ {s['std_coverage']:4.2f}"
          f"  noise {s['noise_family']}  spikes {100 * s['spike_fraction']:.3f}%  {s['wall_s']:5.1f} s"
          + "".join(f"  cov2σ[{t}] {c:4.2f}" for t, c in s.get("std_coverage_by_terrain", {}).items()),
          flush=True)
    return s


def _run_job(job: tuple) -> dict:
    name, preset, ov, work, seed, params, with_oracle = job
    return run_survey(name, preset, ov, work, seed, params, with_oracle)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workdir", default="/tmp/aerograv-regimes")
    ap.add_argument("--json", default=None)
    ap.add_argument("--params", default=None, help="processing overrides (JSON) instead of the defaults")
    ap.add_argument("--no-oracle", action="store_true", help="skip the truth-tuned oracle (minutes per regime)")
    ap.add_argument("--jobs", type=int, default=1, help="regimes processed at once (each in its own process)")
    a = ap.parse_args()
    work = Path(a.workdir)
    work.mkdir(parents=True, exist_ok=True)
    regimes = REGIMES + _extra_regimes()
    if a.only:
        regimes = [r for r in regimes if r[0] in a.only]
    jobs = [(name, preset, ov, work, a.seed, a.params, not a.no_oracle) for name, preset, ov, _ in regimes]
    if a.jobs > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(a.jobs) as ex:
            rows = list(ex.map(_run_job, jobs))
    else:
        rows = [_run_job(j) for j in jobs]
    for s, r in zip(rows, regimes):
        s["description"] = r[3]
    ratios = [r["dg_mgal"] / r["dg_fir_mgal"] for r in rows]
    raw = [r["dg_mgal_raw"] / r["dg_fir_mgal_raw"] for r in rows]
    whole = [r["dg_mgal_whole"] / r["dg_fir_mgal_whole"] for r in rows]
    cov = np.array([r["std_coverage"] for r in rows])
    print(f"\nadaptive/FIR: mean {np.mean(ratios):.3f}, max {np.max(ratios):.3f} over {len(rows)} regimes "
          f"(mean errors kept: mean {np.mean(raw):.3f}, max {np.max(raw):.3f}; whole lines, ends included: "
          f"mean {np.mean(whole):.3f}, max {np.max(whole):.3f}); "
          f"adaptive/oracle max {max(r['dg_mgal'] / r['oracle']['rms'] for r in rows):.3f}; 2σ coverage "
          f"{cov.min():.3f}–{cov.max():.3f}, within 93–97 % on {int(np.sum((cov >= 0.93) & (cov <= 0.97)))}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
