"""Where an output's distance to the truth lies: the anomaly levels or the state map.

    python benchmarks/level_scan.py [SURVEY OUT] [--oracle] [--json out.json]

``SURVEY`` is a simulated survey (with ``truth/``), ``OUT`` the directory ``aerograv process
SURVEY --out OUT`` wrote; without them (``make bench``) the bundled ``omolon-mini`` is processed
into a temporary directory and scanned with the oracle.  Every line of ``OUT/lines.parquet`` is smoothed again with the
product's smoother and noise model (``report.json``), from its own ``z_mgal`` and the levels
the product applied there (``Q_mgal2`` and ``R_cm2s2``, the chosen order ``m``) — on the line
alone, without the run-in margins, so the scan's own α = 1 is its reference, beside the
product's ``dg_mgal``:

* **the scale scan**: Q(t) × α for α = 2^k, k = −4…4.  For each α the RMS against the truth,
  scored as in ``bench_regimes.py`` (10 km in from each end, each line's mean error removed),
  divided by the FIR 100 s column's on the same epochs; the α the innovations likelihood of z
  prefers, and the truth's best;
* with ``--oracle``: the truth-tuned per-terrain oracle of ``bench_regimes.py`` and, when it
  uses the product's order, its per-terrain levels (and noise scale) applied through the
  product's own soft map — the map's probability of the rough level recovered from Q(t)
  between the two refined levels (``level_refinement.Q_mgal2``; Q(t) is their geometric mean
  weighted by it) —, and the product's levels on the true terrain.  The first says how much of
  the distance to the oracle the levels account for, the second how much the map does.

Session 56 (MEASUREMENTS.md): over 10 stored two-level surveys the oracle's levels on the
product's own map took the m = 2 estimate from 0.897 to 0.800× FIR against the oracle's 0.770.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_regimes import _core, _demeaned_rms, noise_from_report, oracle  # noqa: E402

from app.core.smoother import kalman_loglik, kalman_smooth  # noqa: E402
from app.pipeline.evaluate import merge_truth  # noqa: E402
from app.pipeline.process import process_survey  # noqa: E402

#: Scale factors of Q(t) scanned: 2^k, k = −4…4.
ALPHAS = tuple(2.0 ** k for k in range(-4, 5))


def _lines(merged: pd.DataFrame, core_index) -> list[dict]:
    """Per line: z, Q(t), R(t), truth, terrain and the scored epochs (sorted by time)."""
    scored = merged.index.isin(core_index)
    out = []
    for line, g in merged.assign(_scored=scored).groupby("line", sort=False):
        g = g.sort_values("time")
        if len(g) < 10:
            continue
        out.append({"line": line, "z": g["z_mgal"].to_numpy(float), "q": g["Q_mgal2"].to_numpy(float),
                    "r": g["R_cm2s2"].to_numpy(float), "truth": g["dg_true_mgal"].to_numpy(float),
                    "fir": g["dg_fir_mgal"].to_numpy(float),
                    "terrain": g["terrain"].to_numpy() if "terrain" in g else None,
                    "keep": g["_scored"].to_numpy(bool)})
    return out


def _ratio(lines: list[dict], q_of, r_scale: float, dt: float, m: int, noise) -> float:
    """RMS against the truth of the smoother under Q(t) = ``q_of(line)`` over the scored
    epochs (each line's mean error removed), divided by FIR's — each over the epochs where it
    has values, as ``bench_regimes.py`` scores them (FIR is left out near holes)."""
    e_all, f_all = [], []
    for ln in lines:
        est = kalman_smooth(ln["z"], q_of(ln), ln["r"] * r_scale, dt, m=m, noise=noise).dg_mgal
        for x, acc in ((est, e_all), (ln["fir"], f_all)):
            k = ln["keep"] & np.isfinite(ln["truth"]) & np.isfinite(x)
            if k.any():
                e = (x - ln["truth"])[k]
                acc.append(e - e.mean())
    e, f = np.concatenate(e_all), np.concatenate(f_all)
    return float(np.sqrt(np.mean(e ** 2) / np.mean(f ** 2)))


def _p_rough(q: np.ndarray, levels) -> np.ndarray:
    """The map's probability of the rough level where Q(t) = Q₀^(1−p)·Q₁^p."""
    lo, hi = np.log(levels[0]), np.log(levels[-1])
    return np.clip((np.log(q) - lo) / (hi - lo), 0.0, 1.0)


def scan(survey: Path, out: Path, with_oracle: bool = False) -> dict:
    """The scale scan and, with ``with_oracle``, the levels/map split (module docstring)."""
    report = json.loads((out / "report.json").read_text())
    noise = noise_from_report(report)
    dt = float(report["noise_model"]["dt_s"])
    m = int(report["model_choice"]["m"])
    merged = merge_truth(pd.read_parquet(out / "lines.parquet"), pd.read_parquet(survey / "truth" / "lines.parquet"))
    core = _core(merged)
    lines = _lines(merged, core.index)
    fir = _demeaned_rms(core, "dg_fir_mgal")
    res = {"survey": survey.name, "m": m, "fir_rms_mgal": fir, "built_ratio": _demeaned_rms(core, "dg_mgal") / fir}
    ratios = [_ratio(lines, lambda ln, a=a: ln["q"] * a, 1.0, dt, m, noise) for a in ALPHAS]
    logliks = [float(sum(kalman_loglik(ln["z"], ln["q"] * a, ln["r"], dt, m=m, noise=noise) for ln in lines))
               for a in ALPHAS]
    res["scan"] = {f"{a:g}": {"ratio": r, "loglik": ll} for a, r, ll in zip(ALPHAS, ratios, logliks)}
    res["alpha_likelihood"] = ALPHAS[int(np.argmax(logliks))]
    res["alpha_truth"] = ALPHAS[int(np.argmin(ratios))]
    res["ratio_at_1"] = ratios[ALPHAS.index(1.0)]
    if not with_oracle:
        return res
    orc = oracle(survey, out, merged)
    res["oracle"] = {**orc, "ratio": orc["rms"] / fir}
    levels = (report.get("level_refinement") or {}).get("Q_mgal2") or []
    q_orc = orc["Q_mgal2"]
    if (orc["m"] != m or len(levels) != 2 or not levels[1] > levels[0] or len(q_orc) != 2
            or lines[0]["terrain"] is None):
        res["split"] = None   # the oracle's levels are for another order, or one level: nothing to split
        return res
    smooth_c, rough_c = sorted(q_orc, key=q_orc.get)

    def oracle_on_map(ln):
        p = _p_rough(ln["q"], levels)
        return np.exp((1.0 - p) * np.log(q_orc[smooth_c]) + p * np.log(q_orc[rough_c]))

    def ours_on_terrain(ln):
        return np.where(ln["terrain"] == rough_c, levels[-1], levels[0])

    res["split"] = {"oracle_levels_on_our_map": _ratio(lines, oracle_on_map, orc["R_scale"], dt, m, noise),
                    "our_levels_on_true_terrain": _ratio(lines, ours_on_terrain, 1.0, dt, m, noise),
                    "rough_class": rough_c}
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("survey", type=Path, nargs="?")
    ap.add_argument("out", type=Path, nargs="?")
    ap.add_argument("--oracle", action="store_true", help="also the oracle and the levels/map split (slow)")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    if (a.survey is None) != (a.out is None):
        ap.error("give both SURVEY and OUT, or neither (the bundled omolon-mini)")
    if a.survey is None:
        with tempfile.TemporaryDirectory() as tmp:
            survey = ROOT / "sample_surveys" / "omolon-mini"
            process_survey(survey, Path(tmp) / "out")
            res = scan(survey, Path(tmp) / "out", True)
    else:
        res = scan(a.survey, a.out, a.oracle)
    print(f"{res['survey']}: m = {res['m']}, as built {res['built_ratio']:.3f}x FIR ({res['fir_rms_mgal']:.2f} mGal); "
          f"re-smoothed at the applied levels {res['ratio_at_1']:.3f}")
    print("  alpha  " + " ".join(f"{k:>6s}" for k in res["scan"]))
    print("  ratio  " + " ".join(f"{v['ratio']:6.3f}" for v in res["scan"].values()))
    print(f"  likelihood's alpha {res['alpha_likelihood']:g}, truth's best {res['alpha_truth']:g}")
    if "oracle" in res:
        o = res["oracle"]
        print(f"  oracle (m = {o['m']}, true terrain) {o['ratio']:.3f}x FIR")
        if res["split"]:
            s = res["split"]
            print(f"  oracle's levels on our map {s['oracle_levels_on_our_map']:.3f}; "
                  f"our levels on the true terrain {s['our_levels_on_true_terrain']:.3f}")
        else:
            print("  no levels/map split (the oracle's order is not the product's, or one level)")
    if a.json:
        a.json.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
