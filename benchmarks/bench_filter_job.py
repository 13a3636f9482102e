"""A ``filter`` job (new h, ρ from the stored identification) against the full ``process`` job
on the same survey, measured side by side in this run (target: filter ≤ 40 % of process).

    python benchmarks/bench_filter_job.py [--survey sample_surveys/omolon-mini] [--repeat 2]

Both run through :func:`app.pipeline.process.run_job`, the web workers' entry, in child
processes (so each pays its own imports, as a worker does).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CODE = """
import sys
from app.pipeline.process import run_job
from app.pipeline.parallel import freeze_imports
freeze_imports()   # as a local job's own process does (app.web.jobs.execute_job, one_shot)
kind, src, out, prev = sys.argv[1:5]
run_job(src, out, {"nlmeans_h_per_km": 1.0, "nlmeans_rho_km": 6.0} if kind == "filter" else None,
        kind=kind, previous_dir=prev if prev != "-" else None)
"""


def timed(kind: str, src: str, out: Path, prev: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", CODE, kind, src, str(out), prev], check=True, cwd=ROOT)
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--survey", default=str(ROOT / "sample_surveys" / "omolon-mini"))
    ap.add_argument("--repeat", type=int, default=2)
    a = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="aerograv-filter-bench-"))
    proc, filt = [], []
    for i in range(a.repeat):
        proc.append(timed("process", a.survey, work / f"p{i}", "-"))
        filt.append(timed("filter", a.survey, work / f"f{i}", str(work / f"p{i}")))
    p, f = min(proc), min(filt)
    print(f"process job {p:.2f} s, filter job {f:.2f} s (best of {a.repeat}, child processes): "
          f"filter / process = {f / p:.2f} (target ≤ 0.40)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
