"""Wall time of `aerograv process` with the per-line loops on one thread and on several,
side by side in the same run, and a check that the outputs are identical.

    python benchmarks/bench_threads.py [--survey sample_surveys/omolon-mini] [--threads 2] [--repeat 2]

The smoother's numba kernels release the GIL, so the lines are filtered (and their likelihoods
summed, in line order) on a thread pool (`app/pipeline/parallel.py`, ``AEROGRAV_THREADS``).
Each run is a child process (``--repeat`` times, the best kept: the first run of a fresh
checkout also compiles the kernels); the ratio printed is threads=N over threads=1.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from app.pipeline.parallel import cpu_count  # noqa: E402


def run(survey: Path, out: Path, threads: int) -> float:
    env = {**os.environ, "AEROGRAV_THREADS": str(threads)}
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "app.cli", "process", str(survey), "--out", str(out)], env=env,
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--survey", default=str(Path(__file__).resolve().parent.parent / "sample_surveys" / "omolon-mini"))
    ap.add_argument("--threads", type=int, default=cpu_count())
    ap.add_argument("--repeat", type=int, default=2)
    a = ap.parse_args()
    survey = Path(a.survey)
    with tempfile.TemporaryDirectory() as tmp:
        best, stages = {}, {}
        for _ in range(a.repeat):
            for n in (1, a.threads):
                out = Path(tmp) / f"t{n}"
                t = run(survey, out, n)
                if t < best.get(n, np.inf):
                    best[n] = t
                    rep = json.loads((out / "report.json").read_text())
                    stages[n] = rep["timings_s"]
                    assert rep["threads"] == n, (rep["threads"], n)
        same = pd.read_parquet(Path(tmp) / "t1" / "lines.parquet").equals(
            pd.read_parquet(Path(tmp) / f"t{a.threads}" / "lines.parquet"))
    print(f"{survey.name}: threads=1 {best[1]:.2f} s, threads={a.threads} {best[a.threads]:.2f} s, "
          f"ratio {best[a.threads] / best[1]:.2f}; lines.parquet identical: {same}")
    for k in ("noise", "filtering", "choice"):
        print(f"  {k:10s} {stages[1].get(k, float('nan')):6.2f} s -> {stages[a.threads].get(k, float('nan')):6.2f} s")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
