"""Soak benchmark: mixed traffic from 8 threads against one real server.

A real ``aerograv serve`` (subprocess on a free loopback port, 5 MB upload limit, the test
fixture's fake pipeline so jobs take about a second) receives ``--requests`` (200) requests in
a fixed random mix: flight uploads and zip imports, job submissions, reads of every view, and
bad inputs (inflating, encrypted, damaged and not-a-zip archives, NaN and out-of-bound
parameters, ids beyond 64 bits, bad names, cross-site and foreign-Host requests).

Prints the request count, the status histogram per kind of request, the uploads answered 201
but missing afterwards (lost), the jobs still active a minute after the traffic (stuck), and
the server's RSS: baseline (after a warm-up), peak during the traffic (VmHWM) and after.
Targets: no 5xx, no lost upload, no stuck job, RSS after within ±10 % of the baseline.
Writes ``benchmarks/results/bench_soak.json``.

    .venv/bin/python benchmarks/bench_soak.py [--requests 200] [--threads 8] [--real]
"""

from __future__ import annotations

import argparse
import collections
import json
import random
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _bad_request(srv, sids: list, bad_zips: dict, grav: bytes, gnss: bytes):
    """One hostile request (a random kind: damaged zips, NaN or out-of-range parameters, huge ids,
    odd names, a foreign Origin or Host, deep JSON, a bad flight name); returns its status."""
    sid = rng_choice(sids)
    kind = rng_choice(["zip", "nan", "bounds", "id", "name", "origin", "host", "deep", "flightname"])
    if kind == "zip":
        name = rng_choice(sorted(bad_zips))
        return srv.post_files("/api/surveys/import", {"file": (name + ".zip", bad_zips[name])})[0]
    if kind == "nan":
        return srv.request("POST", f"/api/surveys/{sid}/jobs", b'{"kind": "process", "params": {"em_tol": NaN}}',
                           {"Content-Type": "application/json"})[0]
    if kind == "bounds":
        p = rng_choice([{"grid_spacing_km": 0.005}, {"em_max_iter": 1e9}, {"nlmeans_rho_km": 1e308},
                        {"decimation_n": 1e12}, {"ma_order_K": 1e6}])
        return srv.json("POST", f"/api/surveys/{sid}/jobs", {"kind": "process", "params": p})[0]
    if kind == "id":
        return srv.get(rng_choice(["/api/surveys/99999999999999999999999", "/api/jobs/18446744073709551617",
                                   "/api/surveys/123456/grid"]))[0]
    if kind == "name":
        return srv.json("POST", "/api/surveys", {"name": rng_choice(["a\nb", "x" * 5000, "a/b", "nul\x00"])})[0]
    if kind == "origin":
        return srv.request("POST", "/api/surveys", b'{"name": "csrf"}',
                           {"Content-Type": "application/json", "Origin": "http://evil.example"})[0]
    if kind == "host":
        return srv.request("GET", "/api/surveys", headers={"Host": "rebind.evil.example"})[0]
    if kind == "deep":
        return srv.request("POST", "/api/surveys", b"[" * 50000 + b"]" * 50000,
                           {"Content-Type": "application/json"})[0]
    files = {"gravimeter": ("g.csv", grav), "gnss": ("n.csv", gnss)}
    return srv.post_files(f"/api/surveys/{sid}/flights", files, {"flight": "bad\nname"})[0]


def main() -> dict:
    from tests.web.conftest import make_tiny_survey, zip_dir
    from tests.web.server_proc import ServerProcess, inflated_survey_zip
    from tests.web.test_hostile import _patch_headers

    ap = argparse.ArgumentParser()
    ap.add_argument("--requests", type=int, default=200)
    ap.add_argument("--threads", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--real", action="store_true", help="run the real pipeline in jobs (slow)")
    ap.add_argument("--warmup-rounds", type=int, default=1, help="rounds of half as many requests before the baseline")
    a = ap.parse_args()
    rng = random.Random(a.seed)

    tmp = Path(tempfile.mkdtemp(prefix="aerograv-soak-"))
    tiny = make_tiny_survey(tmp / "tiny", name="soak")
    good_zip = zip_dir(tiny)
    fdir = tiny / "flights" / "f1"
    grav, gnss = (fdir / "gravimeter.csv").read_bytes(), (fdir / "gnss.csv").read_bytes()
    # uploaded flights lie side by side, 2 km apart (as a survey block is flown), not on one track
    g0 = pd.read_csv(fdir / "gnss.csv")
    gnss_at = [g0.assign(lat=g0["lat"] + 0.018 * (k + 1)).to_csv(index=False, float_format="%.8f").encode()
               for k in range(60)]
    lines0 = pd.read_csv(tiny / "lines.csv").drop(columns=["flight"])
    bad_zips = {"inflating": inflated_survey_zip(tiny, 30), "encrypted": _patch_headers(good_zip, "tiny/survey.toml", 1),
                "damaged": good_zip[:len(good_zip) // 2] + bytes(1000), "not-a-zip": b"hello" * 100}
    member = "tiny/flights/f1/gnss.csv"
    bad_zips["size-lying"] = _patch_headers(good_zip, member, size=10)

    env = {"AEROGRAV_MAX_UPLOAD_MB": "5", "AEROGRAV_POLL_INTERVAL_S": "0.2", "AEROGRAV_FAKE_DELAY_S": "0.03",
           "AEROGRAV_FAKE_DECIMATE": "100", **json.loads(__import__("os").environ.get("SOAK_ENV", "{}"))}
    out: dict = {"requests": a.requests, "threads": a.threads}
    with ServerProcess(tmp / "data", env=env, fake_pipeline=not a.real) as srv:
        # ---- set-up and warm-up: every code path once (imports pandas, pyarrow, xarray, ...)
        sids = []
        for _ in range(3):
            st, s = srv.post_files("/api/surveys/import", {"file": ("soak.zip", good_zip)})
            assert st == 201, s
            sids.append(s["id"])
        st, s = srv.json("POST", "/api/surveys", {"name": "uploads"})
        sids.append(s["id"])
        for sid in sids[:3]:
            st, j = srv.json("POST", f"/api/surveys/{sid}/jobs", {"kind": "process"})
            assert st == 201, j
        _wait_idle(srv, sids, 120)
        for sid in sids[:3]:
            for path in (f"/api/surveys/{sid}/grid", f"/api/surveys/{sid}/lines/L1", f"/api/surveys/{sid}/recognition",
                         f"/api/surveys/{sid}/lines", f"/api/surveys/{sid}/qc", f"/api/surveys/{sid}/tracks"):
                srv.get(path)
        for name, data in bad_zips.items():
            srv.post_files("/api/surveys/import", {"file": (name + ".zip", data)})
        cold = srv.rss_mb()

        uploaded: dict[int, set[str]] = collections.defaultdict(set)
        lock = threading.Lock()
        counter = iter(range(10**9))

        def flight_upload():
            sid = rng_choice(sids)
            k = next(counter)
            name = f"S{k}"
            files = {"gravimeter": ("gravimeter.csv", grav), "gnss": ("gnss.csv", gnss_at[k % len(gnss_at)]),
                     "lines": ("lines.csv", lines0.assign(line=lambda d: f"{name}_" + d.line).to_csv(index=False).encode())}
            st, body = srv.post_files(f"/api/surveys/{sid}/flights", files, {"flight": name}, timeout=120)
            if st == 201:
                with lock:
                    uploaded[sid].add(name)
            return st

        def import_zip():
            st, body = srv.post_files("/api/surveys/import", {"file": ("soak.zip", good_zip)}, timeout=120)
            if st == 201:
                with lock:
                    sids.append(body["id"])
            return st

        def submit_job():
            return srv.json("POST", f"/api/surveys/{rng_choice(sids)}/jobs",
                            {"kind": rng_choice(["process", "identify", "filter"]), "params": {"em_max_iter": 20}})[0]

        def read():
            sid = rng_choice(sids)
            path = rng_choice([f"/api/surveys/{sid}", "/api/surveys", f"/api/surveys/{sid}/qc", f"/api/surveys/{sid}/lines",
                               f"/api/surveys/{sid}/grid", f"/api/surveys/{sid}/lines/L2?z_lowpass_s=10",
                               f"/api/surveys/{sid}/recognition?h=1&rho=5", f"/api/surveys/{sid}/jobs",
                               f"/api/surveys/{sid}/export?format=csv", "/api/health", f"/api/surveys/{sid}/tracks", "/"])
            return srv.get(path, timeout=60)[0]

        def bad():
            return _bad_request(srv, sids, bad_zips, grav, gnss)

        ops = [("upload", flight_upload)] * 20 + [("import", import_zip)] * 10 + [("job", submit_job)] * 15 + \
              [("read", read)] * 35 + [("bad", bad)] * 20
        hist: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
        errors: list[str] = []

        def run(op):
            kind, fn = op
            try:
                st = fn()
            except Exception as exc:  # a dropped connection counts as a failure
                st = f"exception {type(exc).__name__}"
                errors.append(f"{kind}: {exc}")
            with lock:
                hist[kind][st] += 1

        def traffic(n):
            plan = [rng.choice(ops) for _ in range(n)]
            with ThreadPoolExecutor(max_workers=a.threads) as ex:
                list(ex.map(run, plan))

        # warm-up rounds of the same traffic (thread pool, allocator arenas, caches reach their steady
        # state), then the measured run; the baseline is the idle RSS after the warm-up
        warm_rss = []
        for _ in range(a.warmup_rounds):
            traffic(a.requests // 2)
            _wait_idle(srv, sids, 60)
            time.sleep(2.0)
            warm_rss.append(round(srv.rss_mb(), 1))
        hist.clear()
        errors.clear()
        uploaded.clear()
        baseline = srv.rss_mb()
        srv.reset_peak()
        t0 = time.perf_counter()
        traffic(a.requests)
        elapsed = time.perf_counter() - t0
        peak = srv.peak_mb()
        stuck = _wait_idle(srv, sids, 60)
        lost = []
        for sid, names in uploaded.items():
            st, s = srv.json("GET", f"/api/surveys/{sid}")
            lost += [f"{sid}/{n}" for n in names - set(s["flights"])]
        time.sleep(2.0)
        after = srv.rss_mb()
        h = srv.json("GET", "/api/health")[1]

    n5xx = sum(c for k in hist.values() for st, c in k.items() if not isinstance(st, int) or st >= 500)
    out.update(elapsed_s=round(elapsed, 2), histogram={k: {str(s): c for s, c in sorted(v.items(), key=str)}
                                                       for k, v in sorted(hist.items())},
               n_5xx_or_dropped=n5xx, lost_uploads=lost, stuck_jobs=stuck, uploads_kept=sum(map(len, uploaded.values())),
               rss_mb={"cold": round(cold, 1), "after_warmup_rounds": warm_rss, "baseline": round(baseline, 1),
                       "peak": round(peak, 1), "after": round(after, 1)},
               storage_mb=h["storage"]["used_mb_total"], errors=errors[:10])
    out["pass"] = n5xx == 0 and not lost and not stuck and abs(after - baseline) <= 0.10 * baseline
    print(f"{a.requests} requests from {a.threads} threads in {elapsed:.1f} s")
    for k, v in out["histogram"].items():
        print(f"  {k:7s} " + ", ".join(f"{s}: {c}" for s, c in v.items()))
    print(f"5xx or dropped: {n5xx}; uploads kept {out['uploads_kept']}, lost {len(lost)}; stuck jobs {len(stuck)}")
    print(f"server RSS: {cold:.0f} MB before the warm-up traffic, {', '.join(map(str, warm_rss))} MB after "
          f"{a.warmup_rounds} warm-up round(s) of {a.requests // 2} requests")
    print(f"server RSS: baseline {baseline:.0f} MB, peak {peak:.0f} MB, after {after:.0f} MB "
          f"({100 * (after - baseline) / baseline:+.1f} %); data on disk {out['storage_mb']:.1f} MB")
    print("PASS" if out["pass"] else "FAIL", "(no 5xx, no lost upload, no stuck job, RSS after within ±10 % of baseline)")
    res = ROOT / "benchmarks" / "results"
    res.mkdir(parents=True, exist_ok=True)
    (res / "bench_soak.json").write_text(json.dumps(out, indent=2))
    return out


_rng_lock = threading.Lock()
_rng = random.Random(1)


def rng_choice(seq):
    with _rng_lock:
        return _rng.choice(list(seq))


def _wait_idle(srv, sids, timeout: float) -> list[int]:
    """Wait until no job of the surveys is queued or running; returns those still active."""
    t_end = time.monotonic() + timeout
    while True:
        active = []
        for sid in list(sids):
            st, jobs = srv.json("GET", f"/api/surveys/{sid}/jobs")
            active += [j["id"] for j in (jobs if st == 200 else []) if j["status"] in ("queued", "running")]
        if not active or time.monotonic() > t_end:
            return active
        time.sleep(0.5)


if __name__ == "__main__":
    sys.exit(0 if main()["pass"] else 1)
