"""Benchmark: server memory while importing a small zip that inflates to a huge CSV.

A real ``aerograv serve`` (subprocess, 20 MB upload limit by default) receives a ~1-2 MB zip of a
valid survey whose ``gnss.csv`` is padded to ``--csv-mb`` MB (386 by default, the case of the
hardening issue).  Prints the status, the time to answer and the server's RSS before, at its
peak (VmHWM, reset just before the request) and after.

    .venv/bin/python benchmarks/bench_import_memory.py [--csv-mb 386] [--upload-mb 20]

Measured (2 shared cores): before the hardening 152 -> 1128 MB peak (+977 MB), 422 after 3.7 s;
after it +3 MB, 422 after 0.03 s (the archive's 386 MB exceed the 80 MB uncompressed budget).
A CSV within the budget (``--csv-mb 75``) is parsed: +203 MB, about 2.7x its size.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    from tests.web.conftest import make_tiny_survey
    from tests.web.server_proc import ServerProcess, inflated_survey_zip

    ap = argparse.ArgumentParser()
    ap.add_argument("--csv-mb", type=float, default=386.0)
    ap.add_argument("--upload-mb", type=float, default=20.0)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        survey = make_tiny_survey(tmp / "survey", name="inflated")
        t0 = time.perf_counter()
        data = inflated_survey_zip(survey, a.csv_mb)
        print(f"zip: {len(data) / 2**20:.2f} MB holding a {a.csv_mb:.0f} MB gnss.csv (built in "
              f"{time.perf_counter() - t0:.1f} s)")
        with ServerProcess(tmp / "data", env={"AEROGRAV_MAX_UPLOAD_MB": str(a.upload_mb)}) as srv:
            srv.get("/api/surveys")
            base = srv.rss_mb()
            srv.reset_peak()
            t0 = time.perf_counter()
            st, body = srv.post_files("/api/surveys/import", {"file": ("inflated.zip", data)}, timeout=300)
            dt = time.perf_counter() - t0
            peak = srv.peak_mb()
            after = srv.rss_mb()
            detail = body.get("detail") if isinstance(body, dict) else body
            print(f"status {st} in {dt:.2f} s: {str(detail)[:200]}")
            print(f"server RSS: before {base:.0f} MB, peak {peak:.0f} MB (+{peak - base:.0f}), after {after:.0f} MB")
            left = list((tmp / "data" / "surveys").glob("*/input/*"))
            print(f"stored input snapshots: {len(left)}")


if __name__ == "__main__":
    main()
