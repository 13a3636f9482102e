"""``aerograv process``: run the stages of SPEC §2/§3 and write the outputs of SPEC §5.

``process_survey(survey_dir, out_dir, overrides=None, progress=None) -> report``

Outputs (all written atomically: temporary name, then rename):
``lines.parquet``, ``identification.json``, ``recognition.parquet``, ``crossovers.csv``,
``grid.nc``, ``grid.tif``, ``grid.grd``, ``grid.csv``, ``report.json``.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import numpy as np
import pandas as pd

from app.pipeline import stages

log = logging.getLogger(__name__)

Progress = Callable[[str, float, dict | None], None]

#: Stage weights for the overall progress fraction.
_STAGES = [("ingest", 0.10), ("measurement", 0.15), ("fir", 0.03), ("regularization", 0.07),
           ("learning", 0.25), ("recognition", 0.05), ("nlmeans", 0.02), ("filtering", 0.18),
           ("leveling", 0.03), ("gridding", 0.07), ("writing", 0.05)]


class _Tracker:
    def __init__(self, progress: Progress | None):
        self.progress = progress
        self.timings: dict[str, float] = {}
        self._t0 = None
        self._stage = None
        self._done = 0.0

    def start(self, stage: str):
        self._finish()
        self._stage = stage
        self._t0 = time.perf_counter()
        self.emit(0.0)

    def emit(self, within: float, info: dict | None = None):
        if self.progress is None or self._stage is None:
            return
        w = dict(_STAGES).get(self._stage, 0.0)
        self.progress(self._stage, min(1.0, self._done + w * float(within)), info)

    def _finish(self):
        if self._stage is not None:
            self.timings[self._stage] = round(time.perf_counter() - self._t0, 4)
            self._done += dict(_STAGES).get(self._stage, 0.0)
            self._stage = None

    def close(self):
        self._finish()
        if self.progress is not None:
            self.progress("done", 1.0, None)


def process_survey(survey_dir, out_dir, overrides: dict | None = None,
                   progress: Progress | None = None) -> dict:
    """Process a survey directory (SPEC §4) into the outputs of SPEC §5.

    Parameters
    ----------
    survey_dir : path
        The survey directory.
    out_dir : path
        Output directory (created).
    overrides : dict, optional
        ProcessingParams overrides on top of ``survey.toml``'s ``[processing]``.
    progress : callable, optional
        ``progress(stage, fraction, info)``; EM iterations arrive as
        ``info = {"em_iteration": {...}}``.

    Returns
    -------
    dict
        The report (also written to ``report.json``).
    """
    from app.io.survey import read_survey

    tr = _Tracker(progress)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    warnings: list[str] = []

    tr.start("ingest")
    survey = read_survey(survey_dir, overrides)
    cfg = survey.config
    p = cfg.processing

    tr.start("measurement")
    tau_s = scale = None
    calibration = None
    if p.calibrate:
        first = sorted(survey.flights)[0]
        try:
            calibration = stages.calibrate_gravimeter(survey.flights[first], cfg)
            tau_s, scale = calibration["tau_s"], calibration["k"]
        except (ValueError, np.linalg.LinAlgError) as exc:
            warnings.append(f"in-flight calibration failed, nominal tau/scale used: {exc}")
    lag_check = None
    if calibration is None and p.lag_check_s is not None:
        # the declared lag τ is checked in flight (seed 001 calibration, τ only): a wrong τ
        # leaves (τ_true − τ)·ḟ of the aircraft's jerk in z, thousands of mGal
        taus = []
        for name in sorted(survey.flights)[:3]:
            try:
                taus.append(stages.calibrate_gravimeter(survey.flights[name], cfg, params=("tau",))["tau_s"])
            except (ValueError, np.linalg.LinAlgError):
                continue
        if taus:
            tau_est = float(np.median(taus))
            # only a consistent disagreement: every flight must agree within the tolerance
            applied = (abs(tau_est - cfg.gravimeter.tau_s) > p.lag_check_s
                       and float(np.ptp(taus)) < p.lag_check_s)
            lag_check = {"declared_tau_s": cfg.gravimeter.tau_s, "estimated_tau_s": taus, "applied": applied}
            if applied:
                tau_s = tau_est
                warnings.append(f"gravimeter lag: survey.toml says τ = {cfg.gravimeter.tau_s:g} s, the flights say "
                                f"{tau_est:.3f} s (estimates {', '.join(f'{v:.3f}' for v in taus)}); "
                                f"using {tau_est:.3f} s")
    flights = {}
    base_ties: dict = {}
    names = list(survey.flights)
    for i, name in enumerate(names):
        flights[name] = stages.measure_flight(survey.flights[name], cfg, tau_s=tau_s, scale=scale)
        warnings.extend(f"flight {name}: {n}" for n in flights[name].notes)
        base_ties[name] = stages.base_tie(flights[name], cfg.gravimeter.base_gravity_mgal)
        tr.emit((i + 1) / len(names))
    if not any(b.get("applied") and b.get("absolute") for b in base_ties.values()):
        why = ("no base_gravity_mgal in survey.toml" if cfg.gravimeter.base_gravity_mgal is None
               else "no static parking-place segment found in the flights")
        warnings.append(f"no absolute base tie ({why}): the level of dg carries the gravimeter's reading "
                        "error (scale × g, easily 100+ mGal); differences along and between lines are "
                        "reliable, absolute values are not")
    crs = stages.survey_crs(cfg, flights)
    lines = stages.cut_lines(survey.lines, flights, crs)
    _check_grid_size(lines, p)
    dt_s = float(np.median(np.concatenate([np.diff(m.t_s) for m in flights.values()])))

    noise_fit, noise = stages.fit_noise(lines, dt_s, p)
    band = stages.level_band(p, dt_s)
    r_local = stages.noise_levels(flights, dt_s, p)
    r_fit_scale = stages.level_scale(noise_fit, band, lines, r_local)
    r_local = {k: v * r_fit_scale for k, v in r_local.items()}

    order = None
    if p.m is None:
        if p.model_order == "likelihood":
            order = stages.choose_model_order(lines, dt_s, noise, r_local)
            p.m = order.m
        else:
            # the order whose spectrum fits the lines best where anomaly and noise meet
            p.m = noise_fit.m
    tr.start("fir")
    fir = {name: stages.fir_baseline(m, p.fir_cutoff_period_s) for name, m in flights.items()}

    tr.start("regularization")
    reg = stages.regularize_lines(lines, cfg, dt_s, noise)
    for ln, why in reg.skipped.items():
        warnings.append(f"line {ln} not identified: {why}")
    n_dec = sum(len(x) for x in reg.x)
    if n_dec < 200:
        warnings.append(f"identification from only {n_dec} decimated points ({len(reg.x)} lines): "
                        "the learned Q/R levels and transitions are unreliable")
    learn_mask = [ln.kind != "tie" or p.include_tie_lines for ln in reg.lines]
    if sum(learn_mask) == 0:
        learn_mask = [True] * len(reg.lines)
        warnings.append("no main lines could be regularized; learning on tie lines")

    tr.start("learning")
    em_rows: list[dict] = []

    def on_iter(rec: dict):
        em_rows.append(rec)
        tr.emit(min(0.95, len(em_rows) / max(2, p.em_max_iter)), {"em_iteration": rec})

    learn_reg = stages.Regularized(reg.design, reg.ma, [l for l, k in zip(reg.lines, learn_mask) if k],
                                   [x for x, k in zip(reg.x, learn_mask) if k],
                                   [i for i, k in zip(reg.idx, learn_mask) if k], reg.skipped)
    em = stages.learn(learn_reg, cfg, callback=on_iter)
    n_states = len(em.Q) * len(em.R)
    stationary = _stationary_distribution(np.asarray(em.transition))
    # per-line initial probabilities: learned lines from EM (rows mapped back through
    # em.line_index, since EM drops lines too short for its window), others the chain's
    # stationary distribution
    learned_pos = [i for i, k in enumerate(learn_mask) if k]
    initial_all = [stationary] * len(reg.lines)
    line_index = getattr(em, "line_index", None)
    if line_index is None:
        line_index = list(range(len(em.initial)))
    for row, w in enumerate(line_index):
        initial_all[learned_pos[int(w)]] = np.asarray(em.initial[row])

    tr.start("recognition")

    # Θ with one row of initial probabilities per regularized line
    theta = SimpleNamespace(Q=em.Q, R=em.R, transition=em.transition, initial=initial_all)
    paths, probs = stages.recognize(reg, theta, cfg)
    rec = stages.recognition_table(reg, paths, probs)

    tr.start("nlmeans")
    labels, sprobs, _ = stages.smooth_recognition(rec, n_states, p.nlmeans_h_per_km, p.nlmeans_rho_km,
                                                  p.nlmeans_mode)
    n_q_, n_r_ = len(em.Q), len(em.R)
    if n_r_ > 1:
        # The anomaly intensity is a property of the place, the GNSS noise level of the
        # moment: decide the Q level on the smoothed map's marginal, the R level on the
        # line's own posterior given that Q level.
        raw = rec[[f"p_{i}" for i in range(n_states)]].to_numpy().reshape(-1, n_q_, n_r_)
        i_q = sprobs.reshape(-1, n_q_, n_r_).sum(axis=2).argmax(axis=1)
        j_r = raw[np.arange(len(i_q)), i_q, :].argmax(axis=1)
        labels = i_q * n_r_ + j_r
    rec["state_smoothed"] = labels
    for i in range(n_states):
        rec[f"p_{i}"] = sprobs[:, i]  # SPEC §5: p_i are the smoothed map's probabilities
    rec_cols = ["line", "time", "easting_km", "northing_km", "x", "state_raw", "state_smoothed"] + \
        [f"p_{i}" for i in range(n_states)]
    rec = rec[rec_cols]

    tr.start("filtering")
    Qs = np.asarray(em.Q, float)
    Rs = np.asarray(em.R, float)
    n_r = len(Rs)
    state_of = {}
    pq_of = {}
    pq_all = sprobs.reshape(len(sprobs), len(em.Q), n_r).sum(axis=2)
    off = 0
    for ln, idx in zip(reg.lines, reg.idx):
        nl = len(idx)
        state_of[ln.line] = (idx, labels[off:off + nl])
        pq_of[ln.line] = pq_all[off:off + nl]
        off += nl
    margin = int(round(60.0 / dt_s))
    prepared = []
    for ln in lines:
        m = flights[ln.flight]
        n = ln.t_s.size
        if ln.line in state_of:
            idx, st = state_of[ln.line]
            s_full = stages.hold_states(n, idx, st)
        else:
            s_full = np.zeros(n, int)  # documented fallback: the smoothest state
        a0 = max(0, ln.sl.start - margin)
        a1 = min(m.t_s.size, ln.sl.stop + margin)
        s_ext = np.concatenate([np.full(ln.sl.start - a0, s_full[0]), s_full,
                                np.full(a1 - ln.sl.stop, s_full[-1])])
        prepared.append((ln, s_full, s_ext, m.z_mgal[a0:a1], slice(ln.sl.start - a0, ln.sl.start - a0 + n),
                         r_local[ln.flight][a0:a1] if r_local else None))
    level_fit = None
    r_scale = 1.0
    if r_local:
        # The level of R(t) comes from the EM on the regularized band — what the smoother's
        # pass band sees.  The high-frequency estimate only gives its shape in time: with
        # coloured GNSS velocity noise the band level is many times the white level.
        # Noise whose power falls toward low frequency (velocities differenced from
        # positions) is already measured near the band by the 'band' model, so the
        # factor is ≥ 1 (it only adds low-frequency power the measurement band does not
        # see); and it is trusted only from enough points.
        hf = np.concatenate([t[5][np.asarray(t[2]) % n_r == 0] for t in prepared])
        if hf.size and n_dec >= 200:
            r_scale = float(np.clip(Rs[0] / np.median(hf), p.em_level_scale_min, 1e4))
    if p.refine_levels:
        from app.core.level_ml import refine_levels

        try:
            level_fit = refine_levels([t[3] for t in prepared], [t[2] for t in prepared], Qs, Rs, dt_s, p.m,
                                      max_epochs=p.refine_max_epochs,
                                      r_base_lines=[r_scale * t[5] for t in prepared] if r_local else None,
                                      fit_r=False, noise=noise)
            Qs = level_fit.Q_mgal2
        except (ValueError, FloatingPointError) as exc:
            warnings.append(f"level refinement skipped: {exc}")
    if r_local:
        r_stationary = r_scale * float(np.median(np.concatenate([t[5] for t in prepared])))
    else:
        r_stationary = float(Rs[0])
    frames = []
    for i, (ln, s_full, s_ext, z_ext, inner, rl) in enumerate(prepared):
        q = Qs[s_ext // n_r]
        if p.q_from_posteriors and ln.line in pq_of:
            # where the map is unsure between levels, a level between them (geometric mean
            # weighted by the smoothed probabilities), changing smoothly between decimated
            # points instead of jumping at the hold boundaries
            idx, _ = state_of[ln.line]
            logq = pq_of[ln.line] @ np.log(Qs)
            q = np.exp(np.interp(np.arange(len(s_ext)) - inner.start, idx, logq))
        r = Rs[s_ext % n_r] if rl is None else r_scale * rl
        dg, std = stages.filter_line(z_ext, q, r, dt_s, p.m, p.smoother, noise)
        # stationary baseline (seed 000 Fig. 8): one (Q₁, R₁) pair — the smooth state's Q
        # and the survey's typical noise level
        dgs, _ = stages.filter_line(z_ext, np.full_like(q, Qs[0]), np.full_like(q, r_stationary), dt_s, p.m,
                                    p.smoother, noise)
        frames.append(pd.DataFrame({
            "line": ln.line, "flight": ln.flight, "kind": ln.kind, "time": ln.t_s,
            "lat": ln.lat_deg, "lon": ln.lon_deg, "h": ln.h_m,
            "easting_km": ln.easting_km, "northing_km": ln.northing_km,
            "z_mgal": ln.z_mgal, "dg_mgal": dg[inner], "dg_std_mgal": std[inner],
            "dg_unleveled_mgal": dg[inner], "dg_stationary_mgal": dgs[inner],
            "dg_fir_mgal": fir[ln.flight][ln.sl], "state": s_full,
            "Q_mgal2": q[inner], "R_cm2s2": r[inner],
            "track": ln.track,
        }))
        tr.emit((i + 1) / len(lines))
    table = pd.concat(frames, ignore_index=True)

    tr.start("leveling")
    crossovers, lev_report = _level(table, p, warnings)

    sc = lev_report.get("std_check", {})
    if p.std_crossover_check and "factor" in sc and sc["factor"] != 1.0:
        # The crossovers are an independent check of dg_std (core.accuracy.crossover_std_factor).
        # Model misfit shows up in both directions: coloured GNSS noise the white model does
        # not see (std too small), an anomaly smoother than the random-walk model (too large).
        table["dg_std_mgal"] = table["dg_std_mgal"] * sc["factor"]
        sc["applied_factor"] = sc["factor"]
    tr.start("gridding")
    grid_cv: dict = {}
    grid = _grid(table, p, warnings, lev_report.get("rms_after_mgal"), grid_cv)

    tr.start("writing")
    from app.io import export

    cols = ["line", "flight", "kind", "time", "lat", "lon", "h", "easting_km", "northing_km", "z_mgal",
            "dg_mgal", "dg_std_mgal", "dg_unleveled_mgal", "dg_stationary_mgal", "dg_fir_mgal", "state",
            "Q_mgal2", "R_cm2s2"]
    export.write_parquet(table[cols], out / "lines.parquet")
    export.write_parquet(rec, out / "recognition.parquet")
    export.write_csv(crossovers, out / "crossovers.csv")
    ident = _identification_json(reg, em, em_rows, learn_mask, initial_all, p, dt_s)
    export.write_json(ident, out / "identification.json")
    if grid is not None:
        e, nn, g, gs = grid
        export.write_grid_netcdf(out / "grid.nc", e, nn, g, gs, crs)
        export.write_grid_geotiff(out / "grid.tif", e, nn, g, gs, crs)
        export.write_grid_surfer(out / "grid.grd", e, nn, g, gs)
        export.write_grid_csv(out / "grid.csv", e, nn, g, gs)
    tr.close()

    report = _report(survey, table, flights, crs, crossovers, lev_report, reg, em, tr.timings,
                     warnings, grid)
    report["base_ties"] = base_ties
    if grid_cv:
        report["grid_std_cross_validation"] = grid_cv
    if order is not None:
        report["model_order"] = {"m": order.m, "loglik": {str(k): v for k, v in order.loglik.items()},
                                 "Q_stationary_mgal2": {str(k): v for k, v in order.Q_mgal2.items()}}
    report["noise_model"] = {**noise.describe(), "level_band_hz": list(band), "level_scale": r_fit_scale,
                             "candidates": noise_fit.candidates, "n_bins": noise_fit.n_bins,
                             "fit_fmax_hz": noise_fit.fmax_hz}
    if calibration is not None:
        report["calibration"] = calibration
    if lag_check is not None:
        report["lag_check"] = lag_check
    if level_fit is not None:
        report["level_refinement"] = {"Q_mgal2": level_fit.Q_mgal2.tolist(),
                                      "R_local_scale": r_scale,
                                      "noise_model": p.noise_model,
                                      "loglik_gain": level_fit.loglik - level_fit.loglik_start,
                                      "n_epochs": level_fit.n_epochs, "n_evaluations": level_fit.n_evaluations}
    export.write_json(report, out / "report.json")
    return report


# --------------------------------------------------------------------------- helpers
def _stationary_distribution(a: np.ndarray) -> np.ndarray:
    w, v = np.linalg.eig(a.T)
    k = int(np.argmin(np.abs(w - 1.0)))
    pi = np.abs(np.real(v[:, k]))
    return pi / pi.sum()


def _tracks(table: pd.DataFrame, col: str):
    from app.core.leveling import LineTrack

    tracks = {}
    for line, g in table.groupby("line", sort=False):
        tracks[str(line)] = LineTrack(g["easting_km"].to_numpy(), g["northing_km"].to_numpy(),
                                      g["time"].to_numpy(), g[col].to_numpy(), g["dg_std_mgal"].to_numpy(),
                                      str(g["kind"].iloc[0]))
    return tracks


def _level(table: pd.DataFrame, p, warnings: list) -> tuple[pd.DataFrame, dict]:
    """Crossovers and leveling; on failure keep the unleveled estimate and say why."""
    from app.core.leveling import find_crossovers, level_lines

    cols = ["line_a", "line_b", "easting_km", "northing_km", "diff_before_mgal", "diff_after_mgal"]
    try:
        cx = find_crossovers(_tracks(table, "dg_unleveled_mgal"), include_repeat=p.leveling_include_repeat)
    except ValueError as exc:
        warnings.append(f"crossovers: {exc}")
        return pd.DataFrame(columns=cols), {"status": f"not leveled: {exc}"}
    if len(cx) == 0:
        warnings.append("no crossovers between lines: leveling skipped")
        return pd.DataFrame(columns=cols), {"status": "not leveled: no crossovers"}
    ranges = {str(l): (float(g["time"].min()), float(g["time"].max()))
              for l, g in table.groupby("line", sort=False)}
    try:
        groups = None
        if p.leveling_per_flight:
            groups = {str(l): str(g["flight"].iloc[0]) for l, g in table.groupby("line", sort=False)}
        res = level_lines(cx, ranges, degree=p.leveling_degree, groups=groups)
    except ValueError as exc:
        warnings.append(f"leveling: {exc}")
        cx = cx.assign(diff_before_mgal=cx["dg_a"] - cx["dg_b"], diff_after_mgal=cx["dg_a"] - cx["dg_b"])
        return cx[cols], {"status": f"not leveled: {exc}"}
    before = (cx["dg_a"] - cx["dg_b"]).to_numpy(float)
    after = np.asarray(res.diff_after, float)
    # Is the drift model supported by the crossovers at all?  F-test of the drift
    # parameters against "no correction": after base ties the crossover differences are
    # mostly the lines' own errors, and fitting them only adds noise to the lines.
    ok = np.isfinite(before) & np.isfinite(after)
    pred_var = (cx["std_a"] ** 2 + cx["std_b"] ** 2).to_numpy(float)
    lines_x = set(cx["line_a"].astype(str)) | set(cx["line_b"].astype(str))
    units = {groups[l] for l in lines_x} if groups else lines_x
    k = max(1, (len(units) - 1) * (p.leveling_degree + 1))
    n = int(ok.sum())
    ssr0 = float(np.sum(before[ok] ** 2))
    ssr1 = float(np.sum(after[ok] ** 2))
    p_value = 0.0
    if n > k + 1 and ssr1 > 0:
        from scipy.stats import f as f_dist

        F = ((ssr0 - ssr1) / k) / (ssr1 / (n - k))
        p_value = float(f_dist.sf(F, k, n - k))
    rep = {"degree": p.leveling_degree, "per_flight": bool(p.leveling_per_flight), "n_crossovers": int(len(cx)),
           "rms_before_mgal": float(res.rms_before), "n_drift_parameters": k, "p_value": p_value}
    if p_value > p.leveling_significance:
        rep.update(status="not leveled: the drift model is not significant at the crossovers "
                          f"(F-test p = {p_value:.3g} > {p.leveling_significance})",
                   rms_after_mgal=float(res.rms_before), rms_after_if_leveled_mgal=float(res.rms_after))
        rep["std_check"] = _std_check(before, pred_var, p)
        cx = cx.assign(diff_before_mgal=before, diff_after_mgal=before)
        return cx[cols], rep
    corr = np.zeros(len(table))
    for line, g in table.groupby("line", sort=False):
        corr[g.index.to_numpy()] = res.correction(str(line), g["time"].to_numpy())
    table["dg_mgal"] = table["dg_unleveled_mgal"].to_numpy() - corr
    cx = cx.assign(diff_before_mgal=before, diff_after_mgal=after)
    rep.update(status="leveled", rms_after_mgal=float(res.rms_after))
    rep["std_check"] = _std_check(after, pred_var, p)
    return cx[cols], rep


def _check_grid_size(lines, p) -> None:
    """Refuse, before the heavy stages, a grid over the lines' extent with more than
    ``app.config.MAX_GRID_CELLS`` nodes."""
    from app.config import check_grid_cells
    from app.io.errors import InputError

    e = np.concatenate([ln.easting_km for ln in lines] or [np.zeros(1)])
    n = np.concatenate([ln.northing_km for ln in lines] or [np.zeros(1)])
    e, n = e[np.isfinite(e)], n[np.isfinite(n)]
    if e.size and n.size:
        try:
            check_grid_cells(float(np.ptp(e)), float(np.ptp(n)), p.grid_spacing_km)
        except ValueError as exc:
            raise InputError(None, None, "processing.grid_spacing_km", str(exc)) from None


def _std_check(diff_mgal, pred_var_mgal2, p) -> dict:
    """Crossover differences against the lines' posterior std: an independent check of
    ``dg_std_mgal``."""
    from app.core.accuracy import crossover_std_factor

    return crossover_std_factor(diff_mgal, pred_var_mgal2, p.std_crossover_shared_fraction,
                                p.std_crossover_min_n, p.std_crossover_min_factor)


def _grid(table: pd.DataFrame, p, warnings: list, crossover_rms_mgal: float | None = None,
          grid_cv: dict | None = None):
    from app.core.gridding import Collocation, Spline

    grid_cv = {} if grid_cv is None else grid_cv
    try:
        # what the crossovers still disagree by, beyond the lines' own posterior std, is an
        # error shared along each line (leveling residual): model it as such in the grid's std
        # The smoother's errors are correlated along a line over the smoother's own
        # resolution (several km), far longer than the thinning step: a share of their
        # variance (grid_line_error_fraction) can be carried as an error shared along each
        # line — it widens the std towards calibration (mini 0.92 → 0.97 of cells within 2σ)
        # but costs grid RMS (kalgoorlie 3.41 → 3.73 mGal), so it is off by default.
        line_err = p.grid_line_error_fraction * float(np.mean(table["dg_std_mgal"] ** 2))
        if crossover_rms_mgal is not None and np.isfinite(crossover_rms_mgal):
            line_err = max(line_err, crossover_rms_mgal ** 2 / 2.0 - float(np.mean(table["dg_std_mgal"] ** 2)))
        est = (Collocation(error_corr_km=p.grid_error_corr_km, line_error_mgal2=line_err)
               if p.gridding == "collocation" else Spline())
        kw = {} if p.grid_mask_km is None else {"mask_km": p.grid_mask_km}
        est.fit(table["easting_km"].to_numpy(), table["northing_km"].to_numpy(),
                table["dg_mgal"].to_numpy(), table["dg_std_mgal"].to_numpy(), line=table["line"].to_numpy())
        g = est.grid(spacing_km=p.grid_spacing_km, **kw)
        if len(g[0]) < 2 or len(g[1]) < 2 or not np.isfinite(g[2]).any():
            raise ValueError("the lines span less than two grid cells in one direction: no map to grid "
                             "(grid files not written)")
        if p.gridding == "collocation" and p.grid_std_line_floor:
            from app.core.gridding import line_std_floor

            floor = line_std_floor(g[0], g[1], table["easting_km"].to_numpy(), table["northing_km"].to_numpy(),
                                   table["dg_std_mgal"].to_numpy())
            g = (g[0], g[1], g[2], np.where(np.isfinite(g[3]), np.maximum(g[3], floor), g[3]))
        if p.gridding == "collocation" and p.grid_std_cross_validate:
            from app.core.gridding import cross_validated_std_factor

            main = table["kind"].to_numpy() != "repeat"
            try:
                cv = cross_validated_std_factor(
                    lambda: Collocation(error_corr_km=p.grid_error_corr_km, line_error_mgal2=line_err),
                    table["easting_km"].to_numpy()[main], table["northing_km"].to_numpy()[main],
                    table["dg_mgal"].to_numpy()[main], table["dg_std_mgal"].to_numpy()[main],
                    table["line"].to_numpy()[main])
                grid_cv.update(cv)
                if cv["factor"] > 1.0:   # only ever widen: a too-small std is the dangerous error
                    g = (g[0], g[1], g[2], g[3] * cv["factor"])
            except ValueError as exc:
                warnings.append(f"grid std cross-validation skipped: {exc}")
        return g
    except ValueError as exc:
        warnings.append(f"gridding: {exc}")
        return None


def _identification_json(reg, em, em_rows, learn_mask, initial_all, p, dt_s) -> dict:
    from app.core.ma_approx import model_vs_true_spectrum

    d = reg.design
    ma = reg.ma
    n_r = len(em.R)
    sel = getattr(em, "selection", {})
    states = [{"index": i * n_r + j, "Q": float(em.Q[i]), "R": float(em.R[j])}
              for i in range(len(em.Q)) for j in range(n_r)]
    f = np.linspace(0, 0.5 / (d.n * d.dt_s), 64)
    try:
        spec = {k: np.asarray(v).tolist() for k, v in model_vs_true_spectrum(ma, d, f).items()}
    except Exception as exc:  # the fit display must never break processing
        spec = {"error": str(exc)}
    return {
        "m": p.m,
        "dt_s": dt_s,
        "units": {"Q": "mGal^2 per GNSS step (dt_s)", "R": "(cm/s)^2"},
        "regularization": {"n": int(d.n), "cutoff_hz": float(d.cutoff_hz), "stop_hz": float(d.stop_hz),
                           "width_hz": float(d.width_hz), "attenuation_db": float(d.attenuation_db),
                           "n_taps": int(len(d.taps)), "decimated_step_s": float(d.n * d.dt_s),
                           "difference_grid": d.difference_grid, "beta": float(d.beta)},
        "ma": {"K": int(ma.K), "L": int(ma.L), "p": int(ma.p), "c": np.asarray(ma.c).tolist(),
               "d": np.asarray(ma.d).tolist(), "misfit_q": float(ma.misfit_q), "misfit_r": float(ma.misfit_r),
               "band_error_q": float(ma.band_error_q), "band_error_r": float(ma.band_error_r),
               "spectrum": spec},
        "em": {"iterations": [_em_record(r) for r in em.iterations],
               "converged": bool(getattr(em, "converged", True)),
               "loglik": float(getattr(em, "loglik", np.nan)), "model": sel.get("chosen"),
               "selection": sel},
        "transition": np.asarray(em.transition).tolist(),
        "initial": {ln.line: np.asarray(pi).tolist() for ln, pi in zip(reg.lines, initial_all)},
        "states": states,
        "lines_learned": [ln.line for ln, k in zip(reg.lines, learn_mask) if k],
        "lines_skipped": reg.skipped,
        "nlmeans": {"h_per_km": p.nlmeans_h_per_km, "rho_km": p.nlmeans_rho_km, "mode": p.nlmeans_mode},
    }


def _em_record(r: dict) -> dict:
    return {"iteration": int(r["iteration"]), "Q": [float(v) for v in r["Q"]], "R": [float(v) for v in r["R"]],
            "objective": float(r["objective"]),
            "transition": [[float(v) for v in row] for row in r.get("transition", [])]}


def _report(survey, table, flights, crs, crossovers, lev_report, reg, em, timings, warnings, grid) -> dict:
    from app.core import accuracy

    rep = {
        "survey": survey.config.survey.name,
        "crs": crs,
        "counts": {"flights": len(flights), "lines": int(table["line"].nunique()),
                   "epochs": int(len(table)), "decimated_points": int(sum(len(x) for x in reg.x)),
                   "crossovers": int(len(crossovers))},
        "time_offsets": {n: {"offset_s": m.time_offset_s, "correlation": m.time_offset_corr,
                             "applied": m.time_offset_applied, **m.time_offset} for n, m in flights.items()},
        "spike_repair": {n: m.despike for n, m in flights.items()},
        "crossovers": lev_report,
        "identification": {"Q_mgal2": np.asarray(em.Q).tolist(), "R_cm2s2": np.asarray(em.R).tolist(),
                           "transition": np.asarray(em.transition).tolist()},
        "timings_s": timings,
        "warnings": warnings,
    }
    rep["repeat_lines"] = _repeat_accuracy(table, accuracy)
    if grid is not None:
        rep["grid"] = {"nx": int(len(grid[0])), "ny": int(len(grid[1])),
                       "valid_cells": int(np.isfinite(grid[2]).sum())}
    return rep


def _repeat_accuracy(table, accuracy) -> dict:
    rep = table[table["kind"] == "repeat"]
    out = {}
    if rep.empty or "track" not in rep:
        return out
    for track, g in rep.groupby("track"):
        groups = [gg for _, gg in g.groupby("line", sort=False)]
        if len(groups) < 2:
            continue
        res = {}
        for col in ("dg_mgal", "dg_fir_mgal", "dg_stationary_mgal"):
            try:
                res[col] = float(accuracy.repeat_line_accuracy(
                    [(gg["easting_km"].to_numpy(), gg["northing_km"].to_numpy(), gg[col].to_numpy())
                     for gg in groups]))
            except (ValueError, AttributeError, TypeError) as exc:
                res[col] = f"n/a: {exc}"
        out[str(track)] = {"repeats": len(groups), "internal_accuracy_mgal": res}
    return out
