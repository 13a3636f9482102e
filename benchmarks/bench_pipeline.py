"""Full `aerograv process` on a simulated preset: wall time per stage and peak memory.

    python benchmarks/bench_pipeline.py [--preset omolon] [--seed 2] [--workdir /tmp/aerograv-bench]

Simulates the preset (if not already there), processes it in a child process measuring
its peak RSS, and prints the stage timings and the accuracy against the truth, beside the
FIR 100 s and stationary baselines measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="omolon")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--workdir", default="/tmp/aerograv-bench")
    ap.add_argument("--params", default=None)
    a = ap.parse_args()
    work = Path(a.workdir)
    survey = work / f"{a.preset}-{a.seed}"
    out = work / f"{a.preset}-{a.seed}-out"
    if not (survey / "survey.toml").exists():
        from app.simulate import simulate_survey

        t0 = time.perf_counter()
        simulate_survey(a.preset, survey, seed=a.seed)
        print(f"simulated {a.preset} in {time.perf_counter() - t0:.1f} s")
    cmd = [sys.executable, "-m", "app.cli", "process", str(survey), "--out", str(out)]
    if a.params:
        cmd += ["--params", a.params]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stderr=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    rep = json.loads((out / "report.json").read_text())
    print(f"aerograv process {a.preset}: {wall:.1f} s wall, peak RSS {peak_mb:.0f} MB, "
          f"{rep['counts']['lines']} lines, {rep['counts']['epochs']} epochs")
    print("stage timings (s):", json.dumps(rep["timings_s"]))
    from app.pipeline.evaluate import evaluate

    ev = evaluate(survey, out)
    lines = ev["lines"]
    print(f"{'estimate':22s} {'all':>7s} {'mountain':>9s} {'plain':>7s}   (RMS vs truth, mGal, 10 km line ends excluded)")
    for col in ("dg_mgal", "dg_unleveled_mgal", "dg_stationary_mgal", "dg_fir_mgal"):
        d = lines[col]
        print(f"{col:22s} {d['all']:7.3f} {d.get('mountain', float('nan')):9.3f} {d.get('plain', float('nan')):7.3f}")
    fir = lines["dg_fir_mgal"]["all"]
    print(f"adaptive / FIR 100 s = {lines['dg_mgal']['all'] / fir:.3f}; "
          f"adaptive / stationary = {lines['dg_mgal']['all'] / lines['dg_stationary_mgal']['all']:.3f}")
    print("std calibration (|err| < 2σ):", round(lines["std_calibration_dg_mgal"], 3))
    print("recognition accuracy:", ev["recognition"])
    if "grid" in ev:
        print("grid vs truth:", ev["grid"])
    print("crossovers:", ev["crossovers"])
    print("repeat lines:", ev["repeat_lines"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
