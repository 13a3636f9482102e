"""Interactive re-smoothing of a 74-line recognition map through the API (SPEC §2 step 4)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def _bench_module():
    spec = importlib.util.spec_from_file_location("bench_web", ROOT / "benchmarks" / "bench_web.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _brute_force_nlmeans(rec, h, rho):
    """SPEC §2 step 4 written out directly: every point re-estimated from all points within
    ρ, weights exp(−h·d), on the posterior probabilities; O(N²) in chunks."""
    xy = rec[["easting_km", "northing_km"]].to_numpy()
    p = rec[["p_0", "p_1"]].to_numpy()
    out = np.empty(len(rec), int)
    for a in range(0, len(rec), 1000):
        d = np.hypot(xy[a:a + 1000, None, 0] - xy[None, :, 0], xy[a:a + 1000, None, 1] - xy[None, :, 1])
        w = np.where(d <= rho, np.exp(-h * d), 0.0)
        out[a:a + 1000] = np.argmax(w @ p, axis=1)
    return out


def test_recognition_resmoothing_74_lines(client):
    """The browser's h/ρ re-smoothing on a 74-line map: every setting answers with one
    state per point, different settings give different maps, and the map equals a direct
    evaluation of the NL-means formula (the latency is measured in benchmarks/bench_web.py)."""
    bench = _bench_module()
    rec = bench.synthetic_recognition(74)
    sid = bench.store_recognition_result(client.app, rec, "bench")
    first = client.get(f"/api/surveys/{sid}/recognition").json()
    assert first["n_points"] == len(rec) > 7000
    prev = None
    for h, rho in [(1.4, 5), (0.5, 10), (0.0, 15), (3.0, 2), (1.0, 8)]:
        r = client.get(f"/api/surveys/{sid}/recognition", params={"h": h, "rho": rho, "coords": False})
        assert r.status_code == 200 and len(r.json()["state"]) == len(rec)
        assert r.json()["state"] != prev
        prev = r.json()["state"]
        if (h, rho) in ((1.4, 5), (0.5, 10)):
            agree = np.mean(np.asarray(r.json()["state"]) == _brute_force_nlmeans(rec, h, rho))
            assert agree > 0.999, (h, rho, agree)
