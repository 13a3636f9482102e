"""Surveys the defaults were not tuned on: random draws of the simulator's settings.

    python benchmarks/bench_unseen.py [--seeds 31 32 ...] [--workdir /tmp/aerograv-unseen]
                                      [--oracle] [--json out.json]

``bench_regimes.py`` switches one regime on at a time, and those regimes are the ones the
defaults were measured on.  Here every survey (omolon-mini's geometry) draws all of these at
once from the seed (:func:`draw`), so the combinations are new:

* GNSS rate 1, 2, 5 or 10 Hz; heights only (white 3–10 mm + Gauss–Markov 1.5–5 cm, 20–120 s)
  or velocities (white 0.3–2 cm/s, often with a Gauss–Markov part 0.3–2 cm/s, 2–20 s);
* half of them a platform gravimeter (1, 2, 10 or 20 Hz, interval means or point samples
  behind a sinc² filter), else the GT-1A of the preset;
* peaked turbulence up to 0.3–0.5 m/s² RMS; a drape of 10–60 m; a time offset;
* field: mountain std 10–35 mGal, plain std 3–12 mGal, mountain source density 0.05–0.4 km⁻²;
* from seed 39 on also noise episodes (0–4 per hour, up to 3–8× the noise), flight height
  0.5–4 km, line spacing 1–4 km, gravimeter noise 0.3–2 mGal/√Hz and wind 0–15 m/s.

``--geometry`` draws small random survey layouts instead (:func:`draw_geometry`: 2–14 main
lines of 12–70 km at 0.8–8 km spacing, 0–3 ties, 1–3 flights, 0–4 repeat passes, 55–130 m/s,
0.3–4.5 km height, four UTM zones of both hemispheres, WGS84 or Helmert 1901, GNSS at
1–20 Hz, 40 % platform gravimeters, 30 % heights-only GNSS, wind, noise episodes); a survey
the pipeline refuses (lines too short to regularize even at 0.25 km steps) is counted, not
scored.  A layout of 12 km lines has no 10 km core: a fifth of each line is left out instead.

Each survey is processed with default settings in a child process and scored as in
``bench_regimes.py`` (:func:`bench_regimes.run_survey`: RMS against truth of the default estimate, FIR 100 s and the
stationary smoother; std coverage); ``--oracle`` adds the truth-tuned oracle (slow).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_regimes import run_survey  # noqa: E402


def draw(seed: int) -> dict:
    """The SimConfig overrides of survey ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(1000 + seed)
    ov: dict = {"gnss_rate_hz": float(rng.choice([1.0, 2.0, 5.0, 10.0]))}
    if rng.random() < 0.4:
        ov.update(gnss_velocity=False, sigma_h_m=float(rng.uniform(0.003, 0.01)),
                  h_colored_m=float(rng.uniform(0.015, 0.05)), h_colored_tau_s=float(rng.uniform(20, 120)))
    else:
        ov.update(sigma_vu_cms=float(rng.uniform(0.3, 2.0)))
        if rng.random() < 0.6:
            ov.update(vu_colored_cms=float(rng.uniform(0.3, 2.0)), vu_colored_tau_s=float(rng.uniform(2, 20)))
    if rng.random() < 0.5:
        rate = float(rng.choice([1.0, 2.0, 10.0, 20.0]))
        sampling = str(rng.choice(["mean", "point"]))
        ov.update(gravimeter_model="AIRGrav", tau_true_s=0.0, tau_declared_s=0.0, gravimeter_clock="aligned",
                  gravimeter_rate_hz=rate, gravimeter_sampling=sampling)
        if sampling == "point":
            ov.update(gravimeter_fir_boxcars=2, gravimeter_fir_width_s=1.0 / rate)
    if rng.random() < 0.5:
        ov.update(turbulence_spectrum="peaked", turbulence_peak_hz=float(rng.uniform(0.2, 0.5)),
                  turbulence_slopes=(3.0, 8.0), turbulence_rms_ms2=(0.2, float(rng.uniform(0.3, 0.5))))
    if rng.random() < 0.4:
        ov.update(drape_amp_m=float(rng.uniform(10, 60)))
    ov.update(drift_rate_mgal_h=(0.2, float(rng.uniform(0.5, 3.0))), speed_ms=float(rng.uniform(60, 110)),
              mountain_std_mgal=float(rng.uniform(10, 35)), plain_std_mgal=float(rng.uniform(3, 12)),
              mountain_sources_per_km2=float(rng.uniform(0.05, 0.4)))
    if seed > 38:
        ov.update(episode_rate_per_h=float(rng.uniform(0, 4)), episode_factor=(2.0, float(rng.uniform(3, 8))),
                  height_m=float(rng.uniform(500, 4000)), main_spacing_km=float(rng.uniform(1.0, 4.0)),
                  grav_noise_mgal_rthz=float(rng.uniform(0.3, 2.0)), wind_ms=float(rng.uniform(0, 15)))
    if rng.random() < 0.3:
        ov.update(time_offset_s=float(rng.uniform(-0.1, 0.1)))
    return ov


def draw_geometry(seed: int) -> dict:
    """The SimConfig overrides of the small random layout ``seed`` (``--geometry``)."""
    rng = np.random.default_rng(5000 + seed)
    ov = dict(
        n_main=int(rng.choice([2, 3, 5, 8, 14])), main_length_km=float(rng.choice([12, 25, 40, 70])),
        main_spacing_km=float(rng.choice([0.8, 2.0, 4.0, 8.0])), n_tie=int(rng.choice([0, 1, 2, 3])),
        n_flights=int(rng.choice([1, 1, 2, 3])), n_repeat=int(rng.choice([0, 0, 2, 4])),
        speed_ms=float(rng.uniform(55, 130)), height_m=float(rng.uniform(300, 4500)),
        crs=str(rng.choice(["EPSG:32657", "EPSG:32733", "EPSG:32612", "EPSG:32636"])),
        normal_gravity=str(rng.choice(["WGS84", "WGS84", "Helmert1901"])),
        gnss_rate_hz=float(rng.choice([1.0, 2.0, 5.0, 10.0, 20.0])),
        wind_ms=float(rng.uniform(0, 20)), episode_rate_per_h=float(rng.uniform(0, 4)),
        mountain_std_mgal=float(rng.uniform(5, 40)), plain_std_mgal=float(rng.uniform(2, 15)),
    )
    if rng.random() < 0.4:
        ov.update(gravimeter_model="AIRGrav", tau_true_s=0.0, tau_declared_s=0.0, gravimeter_clock="aligned",
                  gravimeter_rate_hz=float(rng.choice([1.0, 2.0, 10.0])))
    if rng.random() < 0.3:
        ov.update(gnss_velocity=False, sigma_h_m=0.005, h_colored_m=0.03)
    if rng.random() < 0.3:
        ov.update(compress=True)
    return ov


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="*", default=list(range(31, 47)))
    ap.add_argument("--workdir", default="/tmp/aerograv-unseen")
    ap.add_argument("--oracle", action="store_true", help="also the truth-tuned oracle (slow)")
    ap.add_argument("--geometry", action="store_true", help="small random layouts (draw_geometry) instead")
    ap.add_argument("--json", default=None)
    ap.add_argument("--params", default=None, help="processing overrides (JSON) instead of the defaults")
    ap.add_argument("--bodies", choices=["points", "prisms"], default="points",
                    help="the mountains' bodies: point masses (the draws as always) or prisms "
                         "(app.simulate.field._mountain_prisms; the draw is otherwise unchanged)")
    a = ap.parse_args()
    work = Path(a.workdir)
    work.mkdir(parents=True, exist_ok=True)
    rows, refused = [], []
    for seed in a.seeds:
        ov = draw_geometry(seed) if a.geometry else draw(seed)
        kind = "layout" if a.geometry else "unseen"
        if a.bodies != "points":
            ov["mountain_bodies"] = a.bodies
            kind += "-" + a.bodies
        try:
            s = run_survey(kind, "omolon-mini", ov, work, seed,
                           params=a.params, with_oracle=a.oracle)
        except RuntimeError as exc:  # the pipeline refused the survey (its message says why)
            print(f"seed {seed}: refused: {str(exc).strip().splitlines()[-1][:200]}", flush=True)
            refused.append(seed)
            continue
        s.update(seed=seed, overrides=ov)
        rows.append(s)
    ratios = np.array([r["dg_mgal"] / r["dg_fir_mgal"] for r in rows])
    cov = np.array([r["std_coverage"] for r in rows])
    scored = np.isfinite(ratios)  # lines shorter than 20 km have no core to score
    ratios, cov = ratios[scored], cov[scored]
    print(f"\nadaptive/FIR over {len(ratios)} scored surveys (of {len(rows)}): mean {ratios.mean():.3f}, "
          f"max {ratios.max():.3f}, worse than FIR on {int(np.sum(ratios > 1.0))}; 2σ coverage "
          f"{cov.min():.2f}–{cov.max():.2f} (mean {cov.mean():.3f}, below 0.90 on {int(np.sum(cov < 0.9))}); "
          f"refused {len(refused)} {refused}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
