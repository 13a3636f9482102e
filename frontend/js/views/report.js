// Report panel: every warning and automatic decision of the current result with its evidence
// (report.json), known sections drawn as tables, any other section shown generically with its JSON.
import { endpoints } from "../api.js";
import { el, fmt, jsonDetails, table } from "../plots.js";
import { labelOf, num, plain, readableView, sectionView } from "./report_labels.js";

const yes = (b) => (b === true ? "yes" : b === false ? "no" : "—");
const pct = (f) => (f === null || f === undefined ? "—" : `${fmt(100 * f, 3)} %`);
const ESTIMATES = [["dg_mgal", "adaptive (final)"], ["dg_stationary_mgal", "stationary"], ["dg_fir_mgal", "FIR 100 s"]];

function card(key, title, ...body) {
  return el("details", { class: "card report-section", id: `report-sec-${key}`, open: true },
    el("summary", {}, el("h3", {}, title)), ...body);
}

function perFlight(obj, headers, row, attrs) {
  return table(["Flight", ...headers], Object.entries(obj || {}).map(([f, v]) => [f, ...row(v ?? {})]), attrs);
}

function repeatRows(rep) {
  return Object.entries(rep || {}).map(([track, v]) => {
    const acc = v.internal_accuracy_mgal || {};
    const nums = ESTIMATES.map(([k]) => (typeof acc[k] === "number" ? acc[k] : null));
    const finite = nums.filter((x) => x !== null);
    const worst = finite.length > 1 ? Math.max(...finite) : null;
    const best = finite.length > 1 ? Math.min(...finite) : null;
    return { track, repeats: v.repeats, nums, acc, worst, best,
      worstName: worst === null ? null : ESTIMATES[nums.indexOf(worst)][1], bestName: best === null ? null : ESTIMATES[nums.indexOf(best)][1] };
  });
}

// one line per decision, in words, for the top of the panel
export function summary(r) {
  const rep = r.report || {};
  const items = [];
  items.push(r.absolute_base_tie
    ? { cls: "ok", text: "Base level: absolute (flights tied to the base gravity at the parking place)." }
    : { cls: "bad", text: "Base level: RELATIVE — no absolute base tie was made; the level of δg may be off by 100+ mGal (set base_gravity_mgal in the survey settings)." });
  const xo = rep.crossovers || {};
  if (xo.status !== undefined) {
    items.push(r.leveled
      ? { cls: "ok", text: `Leveling applied${xo.refused_drift ? ` as one offset per flight — the drift (degree ${xo.refused_drift.degree}) was refused: ${String(xo.refused_drift.status).replace(/^not leveled:\s*/, "")} —` : ""} (F-test p = ${fmt(xo.p_value, 3)}` +
          (xo.cross_validation ? `; held-out lines' crossovers ${fmt(xo.cross_validation.rms_before_mgal, 3)} → ${fmt(xo.cross_validation.rms_cv_mgal, 3)} mGal, p = ${fmt(xo.cross_validation.p_value, 3)}` +
            (xo.cross_validation.absolute_base_tie === false
              ? ` < ${fmt(xo.cross_validation.significance, 3)}, the check where a flight has no absolute base tie: it keeps its own reading offset, so the flights differ in level for certain`
              : "") : "") +
          `); crossover RMS ${fmt(xo.rms_before_mgal, 3)} → ${fmt(xo.rms_after_mgal, 3)} mGal.` }
      : { cls: "warn", text: `Leveling NOT applied — ${String(xo.status).replace(/^not leveled:\s*/, "")}; crossover RMS ${fmt(xo.rms_before_mgal, 3)} mGal` +
        (xo.rms_after_if_leveled_mgal !== undefined ? ` (${fmt(xo.rms_after_if_leveled_mgal, 3)} if leveled).` : ".") });
  }
  // no crossovers: the repeat tracks' passes leveled against each other (stage 10)
  for (const [track, t] of Object.entries(xo.repeat_tracks || {})) {
    const corr = Object.values(t.mean_correction_mgal || {});
    items.push(t.status === "leveled"
      ? { cls: "ok", text: `Repeat track ${track}: its ${t.passes.length} passes leveled against each other (no crossovers) — mean corrections ` +
          `${fmt(Math.min(...corr), 3)} to ${fmt(Math.max(...corr), 3)} mGal (F-test p = ${fmt(t.p_value, 3)}); their mean level is kept.` }
      : { cls: "note", text: `Repeat track ${track}: passes not leveled against each other — ${String(t.status).replace(/^not leveled:\s*/, "")}.` });
  }
  const em = (r.identification || {}).em || {};
  const unreliable = r.warnings.filter((w) => /unreliable|not identified|learning on tie/i.test(w));
  if (em.n_iterations || unreliable.length) {
    items.push({ cls: unreliable.length || em.converged === false ? "warn" : "ok",
      text: `Identification: ${em.model ? `model ${em.model}` : "EM"}${em.selection && em.selection.criterion ? ` (chosen: ${em.selection.criterion})` : ""}, ` +
        `${em.n_iterations || 0} iterations, ${em.converged === false ? "NOT converged" : "converged"}` +
        (unreliable.length ? ` — ${unreliable.join("; ")}` : ".") });
  }
  for (const t of repeatRows(rep.repeat_lines)) {
    if (t.worstName) {
      items.push({ cls: t.worstName.startsWith("adaptive") ? "bad" : "ok",
        text: `Repeat track ${t.track} (${t.repeats} passes): the ${t.worstName} estimate is the least repeatable (${fmt(t.worst, 3)} mGal), ` +
          `the ${t.bestName} the most (${fmt(t.best, 3)} mGal).` });
    }
  }
  // a repeat pass whose std was widened to its own noise (a turbulent pass among calm ones)
  for (const [track, t] of Object.entries((rep.level_refinement || {}).std_repeat_tracks || {})) {
    const more = t.widened_passes || [];
    if (!more.length) continue;
    items.push({ cls: "warn", text: `Std on repeat track ${track}: ` +
      (t.scale != null
        ? `sized by its passes (× ${fmt(t.scale, 3)}); `
        : `the passes' scatter (${fmt(t.noise_part_mgal, 3)} mGal) exceeds the posterior std (${fmt(t.posterior_mgal, 3)} mGal, p = ${fmt(t.noise_p_value, 2)}); `) +
      `${more.map((w) => `${w.line} × ${fmt(w.scale, 3)}`).join(", ")}: ` +
      (more.length > 1
        ? "these passes carry more noise than the others (their departures from them), and their std is widened to it."
        : "this pass carries more noise than the others (its departures from them), and its std is widened to it.") });
  }
  // a repeat pass smoothed again with its own noise level (turbulence the noise model did not give it)
  for (const [track, t] of Object.entries((rep.level_refinement || {}).noisy_passes_rescaled || {})) {
    const done = t.rescaled || [];
    if (!done.length) continue;
    const fall = (r) => fmt(100 * (1 - r.departure_after / r.departure_before), 2);
    items.push({ cls: "warn", text: `Estimate on repeat track ${track}: ` +
      `${done.map((r) => `${r.line} smoothed with its noise level × ${fmt(r.R_factor, 3)} (departure from the other passes −${fall(r)} %)`).join(", ")}: ` +
      (done.length > 1 ? "these passes carry" : "this pass carries") +
      " more noise than the noise model gave them, measured by their departures from the other passes." });
  }
  // a test line's level scaled where its repeat passes agree better so
  const lc = (rep.level_refinement || {}).repeat_level_check;
  if (lc && lc.factor !== undefined && lc.factor !== 1) {
    const at = (lc.factors || []).indexOf(lc.factor), one = (lc.factors || []).indexOf(1);
    const p = (lc.p_values || {})[String(Math.round(lc.factor * 1e6) / 1e6)] ?? Object.values(lc.p_values || {})[0];
    const ref = lc.reference_q_factor !== undefined ? `estimate at ${fmt(lc.reference_q_factor, 3)} × Q(t)`
      : `${fmt(lc.reference_period_s, 3)} s low-pass of z`;
    const where = lc.scaled ? ` in the lines' interiors (${fmt(lc.edge_km, 3)} km or more from their ends)` : "";
    items.push({ cls: "warn", text: `Test line level: Q × ${fmt(lc.factor, 3)}${where} — the repeat passes agree better ` +
      `${where ? "there " : ""}with the other passes' ${ref} (mean square ${fmt(lc.msd_mgal2[at >= 0 ? at : 0], 4)} against ${fmt(lc.msd_mgal2[one >= 0 ? one : 1], 4)} mGal², p = ${fmt(p, 2)}).` });
  }
  if (rep.lag_check) {
    const lc = rep.lag_check;
    items.push({ cls: lc.applied ? "warn" : "ok", text: lc.applied && lc.from_band_fit
      ? `Gravimeter lag: survey.toml says τ = ${fmt(lc.declared_tau_s, 3)} s; fitted where the anomaly is estimated (0.02–0.05 Hz) the flights say ${fmt(lc.band_fit_tau_s, 4)} s: that value was used.`
      : lc.applied && lc.from_one_scale
      ? `Gravimeter lag: survey.toml says τ = ${fmt(lc.declared_tau_s, 3)} s; each flight's in-flight τ minus the time offset applied before it gives ` +
        `${(lc.flight_lags_s || []).map((v) => fmt(v, 3)).join(", ")} s: their median ${fmt(lc.one_scale_tau_s, 3)} s was used.`
      : lc.applied
      ? `Gravimeter lag: survey.toml says τ = ${fmt(lc.declared_tau_s, 3)} s, the flights say ${(lc.estimated_tau_s || []).map((v) => fmt(v, 3)).join(", ")} s: the flights' value was used.`
      : (lc.one_scale || lc.offset_as_lag) && !(lc.one_scale || lc.offset_as_lag).applied
      // the flights' offsets looked like a lag and were tried as one: "confirmed" would hide that
      ? `Gravimeter lag τ = ${fmt(lc.declared_tau_s, 3)} s kept (in-flight τ ${(lc.estimated_tau_s || []).map((v) => fmt(v, 3)).join(", ")} s): ` +
        `${(lc.one_scale || lc.offset_as_lag).reason}.`
      : `Gravimeter lag τ = ${fmt(lc.declared_tau_s, 3)} s confirmed in flight (${(lc.estimated_tau_s || []).map((v) => fmt(v, 3)).join(", ")} s).` });
  }
  if (rep.model_choice !== undefined) {
    const mc = rep.model_choice;
    let text = `Model choice: ${typeof mc === "object" && mc ? (mc.chosen ?? mc.model ?? JSON.stringify(mc).slice(0, 120)) : String(mc)}` +
      (mc && mc.reason ? ` — ${mc.reason}` : "");
    if (mc && typeof mc === "object") {
      // neither order significantly better at the crossovers: their least-error blend (stage 9)
      const b = (mc.order || {}).blend, xr = (mc.order || {}).crossover_rms_mgal || {};
      if (mc.m !== undefined) {
        let order = `anomaly order m = ${mc.m}`;
        if (b) {
          order += `, blended with m = ${b.m} at weight ${fmt(b.weight, 3)} — the least crossover mean square ` +
            (b.drift_removed ? "once the flights' drift is removed " : "") +
            `(RMS ${fmt(b.crossover_rms_mgal, 2)} mGal against ${fmt(xr[String(mc.m)], 2)} for m = ${mc.m} and ` +
            `${fmt(xr[String(b.m)], 2)} for m = ${b.m} alone)`;
        }
        text += ` (${order})`;
      }
      // why FIR, when it is: the crossover guard or the noisy-estimate check (stage 9)
      const g = mc.fir_guard || {}, n = mc.noisy_check || {};
      if (g.applied) {
        text += ` — the adaptive estimate disagrees more at the ${g.n_crossovers} crossovers than FIR 100 s ` +
          `(RMS ${fmt(g.crossover_rms_mgal, 3)} against ${fmt(g.crossover_rms_fir_mgal, 3)} mGal; t-test p = ${fmt(g.p_value, 3)}, ` +
          `signed ranks p = ${fmt(g.p_rank, 3)})`;
      } else if (n.applied) {
        text += ` — the adaptive estimate passes noise (median variance ratio ${fmt(n.median_variance_ratio, 3)}, ` +
          `median disagreement with FIR ${fmt(n.median_disagreement, 3)})`;
        const lp = n.long_lowpass || {};
        if (lp.applied) {
          // FIR itself resolves nothing: a longer low-pass (stage 9, step 3b)
          text += `; FIR 100 s resolves no anomaly either (its crossovers show ${fmt(lp.fir_crossover_std_mgal, 3)} mGal ` +
            `of error against an along-line spread of ${fmt(lp.fir_spread_mgal, 3)}): the ${fmt(lp.period_s, 4)} s ` +
            `low-pass is used, resolving only anomalies longer than that`;
        }
      } else if (mc.repeat_blend && mc.repeat_blend.weight_fir !== undefined) {
        // a test line: the passes' least-error blend with FIR 100 s (stage 9, step 4b)
        const rb = mc.repeat_blend;
        text += ` — too few crossovers to judge; the ${rb.passes} repeat passes agree best with each other's ` +
          `${rb.reference ? String(rb.reference) : fmt(rb.reference_period_s, 3) + " s low-pass of z"} when ${fmt(rb.weight_fir, 3)} of FIR 100 s is blended in ` +
          `(mean square ${fmt(rb.msd_estimate_mgal2, 4)} adaptive, ${fmt(rb.msd_fir_mgal2, 4)} FIR, ` +
          `${fmt(rb.msd_blend_mgal2, 4)} blend, mGal², the reference's noise included)`;
      } else if (mc.small_survey_blend && mc.small_survey_blend.applied) {
        // a small survey nothing can judge: a fixed share of FIR 100 s (stage 9, step 4d)
        const sb = mc.small_survey_blend;
        text += ` — no crossovers or repeat passes can judge an anomaly level learned from ${sb.n_points} ` +
          `decimated points: ${fmt(sb.weight_fir, 3)} of FIR 100 s is blended in (small_survey_fir_weight)`;
      } else if (g.n_crossovers && g.crossover_rms_fir_mgal !== undefined) {
        // the adaptive estimate kept: the crossovers' evidence against FIR 100 s, the alternative
        const better = g.crossover_rms_mgal <= g.crossover_rms_fir_mgal;
        text += ` — at the ${g.n_crossovers} crossovers it agrees ${better ? "better than FIR 100 s" : "worse than FIR 100 s, but not significantly"} ` +
          `(RMS ${fmt(g.crossover_rms_mgal, 3)} against ${fmt(g.crossover_rms_fir_mgal, 3)} mGal` +
          (better ? ")" : `; t-test p = ${fmt(g.p_value, 3)}, signed ranks p = ${fmt(g.p_rank, 3)})`);
      }
      const u = mc.unresolved_check || {};
      if (u.applied) {
        // the estimate chosen so far resolves nothing beyond its noise: a longer low-pass (stage 9, step 4c)
        const lp = u.long_lowpass || {};
        text += `; that estimate resolves no anomaly beyond its noise (its ${u.n_crossovers} crossovers show ` +
          `${fmt(u.crossover_std_mgal, 3)} mGal of error against an along-line spread of ${fmt(u.spread_mgal, 3)}): ` +
          `the ${fmt(lp.period_s, 4)} s low-pass of z is used, resolving only anomalies longer than that`;
      }
    }
    items.push({ cls: mc && (mc.chosen === "FIR" || mc.chosen === "blend with FIR") ? "warn" : "ok", text });
  }
  return el("ul", { id: "report-summary", class: "decisions" }, items.map((i) => el("li", { class: i.cls }, i.text)));
}

function spikeOutcome(d) {
  if (!d.applied) return d.flagged ? "stood down: z left as measured" : "none found";
  const ho = d.height_outliers;
  if (!Array.isArray(ho)) return "repaired";
  // heights-only GNSS: each flag removed as a height spike or step seen through the spline
  const done = ho.filter((o) => o.kind);
  const list = done.map((o) => `${o.kind} ${fmt(100 * o.size_m, 2)} cm at ${fmt(o.time, 1)} s`).join("; ");
  const spikes = done.filter((o) => o.kind === "spike").length;
  return `repaired as ${spikes} height spike(s) and ${done.length - spikes} height step(s)` +
    (ho.length > done.length ? ` (${ho.length - done.length} left: no finite window)` : "") + (list ? `: ${list}` : "");
}

/** A gravimeter slower than the GNSS: were its samples' motion cancelled, and z's band RMS both ways. */
// the lag fitted where the anomaly is estimated (stage 1): its first fit against survey.toml's τ, and the τ used
function bandFitCell(v) {
  const b = v.from_band_fit ? v : v.band_fit;
  if (!b) return "—";
  const it = (b.iterations || [])[0] || {};
  const ms = (x) => (x === null || x === undefined ? x : 1000 * x);
  const first = `first fit Δτ ${fmt(ms(it.dtau_s), 1)} ± ${fmt(ms(it.se_s), 1)} ms`;
  return b.applied ? `${fmt(b.band_fit_tau_s, 4)} s used (${first})` : `not used (${first})`;
}

function motionCompensation(mc) {
  if (!mc) return "— (gravimeter not slower than the GNSS)";
  const band = Array.isArray(mc.band_hz) ? ` at ${fmt(mc.band_hz[0], 2)}–${fmt(mc.band_hz[1], 2)} Hz` : "";
  const has = (x) => x && Number.isFinite(x.band_rms_plain_mgal) && Number.isFinite(x.band_rms_compensated_mgal);
  // short lines (too little line time for the usual comparison): the figures on stretches with
  // shorter edges decided, so they are the ones shown
  const short = has(mc.short_lines) && (mc.survey_short_lines || !has(mc));
  const f = short ? mc.short_lines : (has(mc) ? mc : null);
  const where = f && f !== mc ? ` on the short lines, ${fmt(f.edge_s, 3)} s edges` : "";
  const rms = f
    ? ` (z's RMS${band}${where}: ${fmt(f.band_rms_plain_mgal, 3)} plain, ${fmt(f.band_rms_compensated_mgal, 3)} cancelled, mGal)` : "";
  return (mc.applied ? "yes" : "no") + rms + (mc.applied || rms ? "" : ` — ${mc.reason || "not compared"}`);
}

// the gravimeter's clock tracked along the flight (stage 1): a drift, jumps, and whether the stamps were re-timed
function clockCell(c) {
  if (!c) return "—";
  const what = [];
  if (c.drift_ppm) what.push(`runs ${fmt(-c.drift_ppm, 3)} ppm fast`);
  for (const st of c.steps || []) what.push(`set ${fmt(Math.abs(st.size_s), 3)} s ${st.size_s < 0 ? "forward" : "back"} at ${fmt(st.time_s, 7)} s`);
  const n = (c.windows || []).length;
  return (c.applied ? "re-timed: " : "") + (what.join(", ") || "one offset") + ` (${n} windows)`
    + (c.applied ? `, ${pct(c.residual_reduction)} of the residual removed` : (c.reason ? ` — ${c.reason}` : ""));
}

const RENDER = {
  base_ties: (v) => [perFlight(v, ["Tie applied", "Absolute", "Drift (mGal/h)", "Static periods", "Reading error (mGal)"], (b) => [
    yes(b.applied), yes(b.absolute), fmt(b.drift_mgal_per_h, 3), String((b.static_periods || []).length),
    (b.static_periods || []).map((p) => fmt(p.reading_error_mgal, 2)).join(", ") || "—"])],
  time_offsets: (v) => [perFlight(v, ["Offset (s)", "Std. error (s)", "Correlation", "Compared (Hz)", "Residual reduction",
    "Applied", "Reason", "Gravimeter stamp scatter (ms)", "Gravimeter clock", "GNSS stamp scatter (ms)",
    "GNSS stamps put on the clock", "Motion cancelled at the gravimeter's samples"], (o) => [
    fmt(o.offset_s, 4), fmt(o.se_s, 2), fmt(o.correlation, 4),
    Array.isArray(o.band_hz) ? `${fmt(o.band_hz[0], 2)}–${fmt(o.band_hz[1], 2)}` : "—",
    pct(o.residual_reduction), yes(o.applied), o.reason || "—",
    fmt(o.gravimeter_stamp_jitter_ms, 2), clockCell(o.clock), fmt(o.gnss_stamp_jitter_ms, 2),
    o.gnss_stamps_dejittered === undefined ? "—" : (o.gnss_stamps_dejittered ? "yes"
      : (o.gnss_stamp_jitter_lag1 > 0.5 ? `no (correlated, lag-1 ${fmt(o.gnss_stamp_jitter_lag1, 2)}: a receiver clock)` : "no")),
    motionCompensation(o.motion_compensation)], { id: "report-time-offsets" })],
  // the gravimeter's smoothing relative to the GNSS acceleration (stage 1): fitted per flight, decided for the survey
  response_width: (v, r) => {
    const out = [table(["Width c (s²)", "SE (s²)", "Residual removed", "Applied", "Reason"],
      [[fmt(v.c_s2, 4), fmt(v.se_s2, 2), pct(v.residual_reduction), yes(v.applied), v.reason || "—"]],
      { id: "report-response-width" })];
    const per = Object.entries(((r && r.report) || {}).time_offsets || {}).filter(([, o]) => o && o.response_width);
    if (per.length) {
      out.push(table(["Flight", "Own c (s²)", "SE (s²)", "Band (Hz)", "Residual removed", "Own verdict", "c applied (s²)"],
        per.map(([f, o]) => {
          const w = o.response_width;
          return [f, fmt(w.c_s2, 4), fmt(w.se_s2, 2), Array.isArray(w.band_hz) ? w.band_hz.map((x) => fmt(x, 2)).join("–") : "—",
            pct(w.residual_reduction), w.reason || "—", fmt(w.c_applied_s2, 4)];
        }), { id: "report-response-width-flights" }));
    }
    return out;
  },
  gnss_filled_epochs: (v) => [perFlight(v, ["Missing GNSS epochs put back on the clock"], (n) => [String(n)], { id: "report-gnss-filled" })],
  gravimeter_filled_samples: (v) => [perFlight(v, ["Missing gravimeter samples put back on the clock"], (n) => [String(n)],
    { id: "report-gravimeter-filled" })],
  lag_check: (v) => [table(["Declared τ (s)", "Estimated τ per flight (s)", "Fitted in the band", "Applied", "Reason"],
    [[fmt(v.declared_tau_s, 4), (v.estimated_tau_s || []).map((x) => fmt(x, 4)).join(", "), bandFitCell(v), yes(v.applied),
      v.reason || (v.offset_as_lag && v.offset_as_lag.reason) || (v.one_scale && v.one_scale.reason) || (v.band_fit && v.band_fit.reason) || "—"]],
    { id: "report-lag-check" })],
  // the gravimeter's timing left at the anomaly's edge (stage 1): fitted on the GNSS jerk, taken out when significant
  // (flights pooled unless their own delays disagree: then each flight's own, where significant)
  band_delay: (v) => {
    const out = [table(["Residual delay (ms)", "SE (ms)", "t", "Band (Hz)", "z's band RMS (mGal)", "Applied", "Reason"],
      [[v.delay_s == null ? "—" : fmt(1e3 * v.delay_s, 3), v.se_s == null ? "—" : fmt(1e3 * v.se_s, 2), fmt(v.t_stat, 3),
        (v.band_hz || []).map((x) => fmt(x, 3)).join("–"),
        `${fmt(v.band_rms_mgal, 4)} → ${fmt(v.band_rms_corrected_mgal, 4)}`, yes(v.applied), v.reason || "—"]],
      { id: "report-band-delay" })];
    if (v.flights && v.heterogeneity) {
      const h = v.heterogeneity;
      out.push(el("p", { class: "note", id: "report-band-delay-agree" },
        `Each flight's own delay: ${v.per_flight ? "they disagree" : "they agree"} (χ² ${fmt(h.chi2, 3)} on ${h.dof} `
        + `degrees of freedom, p = ${fmt(h.p_value, 2)}; fitted apart below p = ${fmt(h.p_limit, 4)})`));
      const takenOut = (d) => (!v.applied ? "no"
        : v.per_flight ? (Math.abs(d.t_stat) >= v.min_t ? `its own (${fmt(1e3 * d.delay_s, 3)} ms)` : "no")
          : `pooled (${fmt(1e3 * v.delay_s, 3)} ms)`);
      out.push(table(["Flight", "Own delay (ms)", "SE (ms)", "t", "Taken out of z"],
        Object.entries(v.flights).map(([f, d]) => [f, d.delay_s == null ? "—" : fmt(1e3 * d.delay_s, 3),
          d.se_s == null ? "—" : fmt(1e3 * d.se_s, 2), fmt(d.t_stat, 3), takenOut(d)]),
        { id: "report-band-delay-flights" }));
    }
    return out;
  },
  spike_repair: (v) => [perFlight(v, ["Flagged epochs", "Fraction", "Epochs", "Threshold (robust σ)", "Outcome"], (d) => [
    String(d.flagged ?? "—"), pct(d.fraction), String(d.epochs ?? "—"), fmt(d.threshold, 3),
    spikeOutcome(d)])],
  crossovers: (v, r) => {
    const out = [table(["Status", "F-test p", "Crossovers", "Drift parameters", "RMS before (mGal)", "RMS after (mGal)", "RMS if leveled (mGal)"],
      [[v.status ?? "—", fmt(v.p_value, 3), String(v.n_crossovers ?? "—"), String(v.n_drift_parameters ?? "—"),
        fmt(v.rms_before_mgal, 4), fmt(v.rms_after_mgal, 4), fmt(v.rms_after_if_leveled_mgal, 4)]], { id: "report-leveling" })];
    if (v.cross_validation) {
      const cv = v.cross_validation;
      out.push(el("p", { class: "note" }, "Leave-one-line-out check of the drift (each line's crossovers predicted by the drift fitted without them):"),
        table(["RMS without leveling (mGal)", "Held-out RMS after (mGal)", "p (one-sided)", "Needs p below", "Lines left out"],
          [[fmt(cv.rms_before_mgal, 4), fmt(cv.rms_cv_mgal, 4), fmt(cv.p_value, 3),
            cv.significance === undefined ? "—" : fmt(cv.significance, 3) + (cv.absolute_base_tie === false ? " (a flight without an absolute base tie)" : ""),
            String(cv.n_folds ?? "—")]], { id: "report-leveling-cv" }));
    }
    if (v.std_check) out.push(el("p", { class: "note" }, `σ check at the crossovers: `), readableView(v.std_check));
    // the level leveling leaves common to the flights (no absolute base tie: it is in the std)
    if (v.common_level) {
      const c = v.common_level;
      out.push(el("p", { class: "note", id: "report-common-level" },
        `Common level of the ${c.n_units} flights: their offsets at ${c.n_crossovers} crossovers spread by ${fmt(c.spread_mgal, 3)} mGal, ` +
        `so their mean — the level leveling keeps — is uncertain by ${fmt(c.std_mgal, 3)} mGal` +
        (c.applied ? "; included in δg's std and the grid std (no absolute base tie)." : ` (not added to the std: ${c.reason ?? "—"}).`)),
        table(["Flight", "Offset (mGal)"], Object.entries(c.offsets_mgal || {}).map(([f, o]) => [f, fmt(o, 3)]), { id: "report-common-level-offsets" }));
    }
    // without crossovers: each repeat track's passes leveled against each other
    const rt = Object.entries(v.repeat_tracks || {});
    if (rt.length) {
      out.push(el("h4", {}, "Repeat passes leveled against each other (no crossovers)"),
        table(["Track", "Status", "F-test p", "Drift degree", "Blocks (km)", "Differences RMS before → after (mGal)", "Mean correction per pass (mGal)"],
          rt.map(([track, t]) => ({ attrs: { "data-track": track }, cells: [track, t.status ?? "—", fmt(t.p_value, 3),
            t.degree === undefined ? "—" : String(t.degree), t.block_km === undefined ? "—" : `${t.n_blocks} × ${fmt(t.block_km, 2)}`,
            t.rms_before_mgal === undefined ? "—" : `${fmt(t.rms_before_mgal, 3)} → ${fmt(t.rms_after_mgal, 3)}`,
            Object.entries(t.mean_correction_mgal || {}).map(([ln, c]) => `${ln} ${fmt(c, 3)}`).join(", ") || "—"] })),
          { id: "report-repeat-leveling" }),
        el("p", { class: "note" }, "Each pass's offset and its flight's drift in time, fitted to the passes' differences from their mean " +
          "at common points (block means); the passes' mean level is kept — without a base tie it is still the gravimeter's reading offset."));
    }
    if (r.crossovers && r.crossovers.length) {
      out.push(el("h4", {}, `Crossovers (${r.crossovers.length})`), el("div", { class: "scroll" }, table(["Line a", "Line b", "E (km)", "N (km)", "before (mGal)", "after (mGal)"],
        r.crossovers.map((c) => [String(c.line_a), String(c.line_b), fmt(c.easting_km, 2), fmt(c.northing_km, 2), fmt(c.diff_before_mgal, 3), fmt(c.diff_after_mgal, 3)]),
        { id: "report-crossover-table" })));
    }
    return out;
  },
  repeat_lines: (v) => {
    const rows = repeatRows(v);
    if (!rows.length) return [el("p", { class: "note" }, "No repeat track with two or more passes.")];
    return [table(["Track", "Passes", ...ESTIMATES.map(([, n]) => `${n} (mGal)`), "Least repeatable"],
      rows.map((t) => ({ attrs: { "data-track": t.track }, cells: [t.track, String(t.repeats),
        ...t.nums.map((x, i) => (x === null ? String(t.acc[ESTIMATES[i][0]] ?? "—") : el("span", { class: x === t.worst ? "worst" : "" }, fmt(x, 3)))),
        t.worstName || "—"] })), { id: "report-repeat-table" }),
    el("p", { class: "note" }, "Internal accuracy ε = sqrt(Σ(g − ḡ)² / (n (K−1))) over the K passes of a track, per estimate; " +
      "the least repeatable in red. The passes are overlaid in Line profiles → Repeat track." +
      rows.filter((t) => typeof t.acc.dg_unleveled_mgal === "number" && t.acc.dg_unleveled_mgal !== t.acc.dg_mgal)
        .map((t) => ` Track ${t.track}: adaptive before leveling ${fmt(t.acc.dg_unleveled_mgal, 3)} mGal (the baselines are not leveled).`).join(""))];
  },
  noise_model: (v) => {
    const out = [table(["Family", "Fit", "Level band (Hz)", "Level scale", "Fitted up to (Hz)"],
      [[v.family ?? "—", v.fit ?? "—", (v.level_band_hz || []).join("–"), fmt(v.level_scale, 3), fmt(v.fit_fmax_hz ?? v.fmax_hz, 3)]])];
    if (v.components) out.push(el("h4", {}, "Components"), readableView(v.components));
    // the anomaly's spectrum beside the noise in the fit: the random walk, rolled off where the data ask for it
    if (v.anomaly_rolloff_s != null) {
      out.push(el("p", { class: "note", id: "report-anomaly-rolloff" }, v.anomaly_rolloff_s > 0
        ? `Anomaly in the fit: random walk of order ${v.m ?? "—"} × exp(−β f), β = ${fmt(v.anomaly_rolloff_s, 3)} s ` +
          "(a field seen from above its sources falls exponentially; β = 4π·depth / speed)"
        : `Anomaly in the fit: random walk of order ${v.m ?? "—"} (no roll-off: the spectra do not support one)`));
    }
    // the checks of the family and of its corners against the FIR differences (crossovers, repeat passes)
    for (const [key, what] of [["family_check", "Coloured velocity checked against the FIR differences"],
                               ["corner_check", "Noise corners checked against the FIR differences"]]) {
      const c = v[key];
      if (!c) continue;
      const text = `${what}: ${c.applied ? "changed" : "kept"}` +
        (c.n ? ` — ${c.n} differences, predicted ${fmt(c.predicted_ms_mgal2, 3)} mGal², bound ${fmt(c.bound_mgal2, 3)} mGal²` : "") +
        (c.reason ? `; ${c.reason}` : "");
      out.push(el("p", { class: c.applied ? "warnline" : "note", id: `report-${key.replace("_", "-")}` }, text));
    }
    // the GNSS heights' bound on the velocity error (stage 3): whether it applied, and whether it changed the fit
    const vb = v.velocity_bound;
    if (vb) {
      const text = "Velocity error bounded by the GNSS heights: " +
        (!vb.applied ? `not applied${vb.reason ? ` — ${vb.reason}` : ""}`
          : vb.refitted ? `refitted — the free fit put ${fmt(vb.max_model_to_misfit, 3)}× the heights–velocities misfit ` +
                          `below ${fmt((vb.f_hz || [])[1], 3)} Hz; after: ${fmt(vb.max_model_to_misfit_after, 3)}×`
                        : `kept — the fit stays under it (${fmt(vb.max_model_to_misfit, 3)}×)`) +
        (vb.z_to_misfit != null ? `; z's noise ${fmt(vb.z_to_misfit, 3)}× the misfit's at 0.02–0.05 Hz` : "") +
        (vb.cautious_shape ? (vb.cautious_shape.refuted
          ? `. The corner moved below the data was refuted by the heights (${fmt(vb.cautious_shape.model_to_misfit, 3)}× the misfit, ` +
            `p = ${fmt(vb.cautious_shape.p_value, 4)}): the shape as fitted kept (${fmt(vb.cautious_shape.unmoved_model_to_misfit, 3)}×, ` +
            `p = ${fmt(vb.cautious_shape.unmoved_p_value, 4)})`
          : `. The corner moved below the data stands (p = ${fmt(vb.cautious_shape.p_value, 4)} against the heights)`) : "");
      out.push(el("p", { class: vb.refitted ? "warnline" : "note", id: "report-velocity-bound" }, text));
    }
    // a family that won at the margin, filtered again with white velocity and compared at the crossovers
    const cc = v.crossover_check;
    if (cc) {
      const rms = cc.crossover_rms_mgal || {};
      const text = `Family checked at the crossovers against ${cc.alternative ?? "white velocity"}: ` +
        (cc.applied ? `${cc.alternative} used instead of ${cc.family}` : "not changed") +
        (cc.crossovers_compared ? ` — crossover RMS ${fmt(rms[cc.family], 3)} (${cc.family}) against ${fmt(rms[cc.alternative], 3)} mGal ` +
          `(${cc.alternative}) at ${cc.crossovers_compared}, p = ${fmt(cc.p_value, 3)} (t-test), ${fmt(cc.p_rank, 3)} (signed ranks)` : "") +
        (cc.reason ? `. ${cc.reason}` : "");
      out.push(el("p", { class: cc.applied ? "warnline" : "note", id: "report-family-crossovers" }, text));
    }
    if (v.candidates && v.candidates.length) {
      const c = [...v.candidates].sort((a, b) => (a.bic ?? Infinity) - (b.bic ?? Infinity));
      out.push(el("h4", {}, "Candidates by BIC (the family used is marked)"), table(["Family", "−log L", "Parameters", "BIC", "ΔBIC", ""],
        c.map((x) => ({ attrs: { class: x.family === v.family ? "chosen" : "" }, cells: [x.family, fmt(x.nll, 1), String(x.n_params ?? "—"), fmt(x.bic, 1),
          fmt(x.bic - c[0].bic, 3), x.family === v.family ? "chosen" : ""] })),
        { id: "report-noise-candidates" }));
    }
    return out;
  },
  model_order: (v) => [el("p", {}, `Order of the anomaly model m = ${v.m} (largest full-rate likelihood).`),
    table(["m", "log L", "Q stationary (mGal²)"], Object.keys(v.loglik || {}).map((m) => [m, fmt(v.loglik[m], 1), fmt((v.Q_stationary_mgal2 || {})[m], 4)]))],
};

const TITLES = {
  base_ties: "Base ties", time_offsets: "Gravimeter–GNSS time offsets and time stamps", gnss_filled_epochs: "Missing GNSS epochs",
  gravimeter_filled_samples: "Missing gravimeter samples", lag_check: "Lag check (τ in flight)",
  band_delay: "Residual gravimeter delay at the anomaly's edge",
  response_width: "Gravimeter response matched (GNSS acceleration smoothed to the meter's)",
  spike_repair: "GNSS spike repair (velocity spikes; height spikes and steps where vu comes from the heights)", crossovers: "Leveling at crossovers", repeat_lines: "Repeat-line internal accuracy",
  noise_model: "Noise model", model_order: "Model order", model_choice: "Model choice and why", identification: "Identification (EM)",
  counts: "Counts", timings_s: "Stage timings", grid: "Grid", level_refinement: "Level refinement (anomaly levels and σ)",
  calibration: "In-flight calibration", grid_std_cross_validation: "Grid σ cross-validation", products: "Products (atmosphere, datum, terrain, grids)",
  repeat_tracks_inferred: "Repeat tracks inferred from positions", model_order_candidates: "Anomaly orders identified",
  adaptive_minus_fir: "Adaptive − FIR 100 s per line (before leveling)", reused_identification: "Identification reused (filter job)",
  model_order_likelihood: "Model order by likelihood", noise_episodes: "Noise episodes (where R(t) was far above its typical level)",
};
// shown in the header (survey, CRS), the warnings box and the timings (threads)
const SKIP = new Set(["warnings", "survey", "crs", "threads"]);
// the sections in the order an analyst reads them: accuracy, the estimate's choices, the noise and the
// identification, what the measurement decided, then the rest; sections the page does not know follow
const ORDER = ["crossovers", "repeat_lines", "adaptive_minus_fir", "model_choice", "noise_model", "noise_episodes", "model_order", "model_order_candidates",
  "identification", "spike_repair", "base_ties", "time_offsets", "response_width", "lag_check", "band_delay", "gnss_filled_epochs",
  "gravimeter_filled_samples", "calibration", "level_refinement", "products", "grid", "repeat_tracks_inferred", "counts", "timings_s"];

// model choice: the decision, then each check with its evidence, then the per-line table
function modelChoice(v) {
  if (!v || typeof v !== "object") return [readableView(v, TITLES)];
  const order = v.order || {};
  const rows = [["Estimate used", String(v.chosen ?? "—")],
    ["Anomaly order m", `${v.m ?? "—"}${order.criterion ? ` — ${plain(order.criterion, TITLES)}` : ""}`]];
  if (v.anomaly_levels !== undefined) rows.push(["Anomaly levels (Q)", `${v.anomaly_levels}${v.anomaly_levels_reason ? ` — ${v.anomaly_levels_reason}` : ""}`]);
  const out = [table(["", ""], rows, { class: "readable kv", id: "report-model-choice" })];
  const rest = Object.fromEntries(Object.entries(v).filter(([k]) => !["chosen", "m", "anomaly_levels", "anomaly_levels_reason", "lines"].includes(k)));
  // the order's criterion and m are in the rows above: its other evidence (crossover RMS per order, blend) below
  const orderRest = Object.fromEntries(Object.entries(order).filter(([k]) => !(k === "criterion" || (k === "m" && order.m === v.m))));
  if (Object.keys(orderRest).length) rest.order = orderRest; else delete rest.order;
  out.push(...sectionView(rest, TITLES));
  if (v.lines) out.push(el("h4", {}, "Per line"), el("div", { class: "scroll" }, readableView(v.lines, TITLES)));
  return out;
}

// stage timings: seconds, share of the run, total
function timings(v, rep) {
  const entries = Object.entries(v || {}).filter(([, s]) => typeof s === "number");
  const total = entries.reduce((a, [, s]) => a + s, 0);
  return [table(["Stage", "Time (s)", "Share"], [...entries.map(([k, s]) => ({ attrs: { title: `report.json key: ${k}` },
    cells: [labelOf(k), fmt(s, 2), total > 0 ? `${fmt(100 * s / total, 1)} %` : "—"] })),
  { attrs: { class: "total" }, cells: ["Total", fmt(total, 2), ""] }], { id: "report-timings" }),
  rep.threads !== undefined ? el("p", { class: "note" }, `Lines filtered on ${rep.threads} thread(s) (the outputs do not depend on it).`) : null];
}

// the stretches where the noise level the smoother used was far above the survey's typical one
function noiseEpisodes(v) {
  if (!v || typeof v !== "object") return [readableView(v, TITLES)];
  const eps = Array.isArray(v.episodes) ? v.episodes : [];
  const head = el("p", { class: "note" }, v.typical_R_cm2s2 === null || v.typical_R_cm2s2 === undefined
    ? "No noise level R(t) on the lines."
    : `Stretches of at least ${fmt(v.min_duration_s, 3)} s where R(t) exceeds ${fmt(v.factor, 3)}× the survey's typical `
      + `${fmt(v.typical_R_cm2s2, 3)} (cm/s)² (gaps up to ${fmt(v.bridge_s, 3)} s bridged): the estimate there leans on the `
      + "anomaly model and its std is wider; compare it with FIR 100 s on the line's profile. Nothing was filtered differently.");
  if (!eps.length) return [head, el("p", { id: "report-noise-episodes" }, "None.")];
  return [head, el("div", { class: "scroll" }, table(["Line", "Flight", "Along line (km)", "Duration (s)", "R peak / typical",
    "R mean / typical", "Std there (mGal)", "Std elsewhere on the line (mGal)"],
  eps.map((e) => ({ attrs: { "data-line": e.line }, cells: [e.line, e.flight, `${fmt(e.along_start_km, 3)}–${fmt(e.along_end_km, 3)}`,
    fmt(e.duration_s, 3), fmt(e.R_peak_over_typical, 3), fmt(e.R_mean_over_typical, 3), fmt(e.std_mean_mgal, 3),
    fmt(e.std_line_quiet_mgal, 3)] })), { id: "report-noise-episodes" }))];
}

Object.assign(RENDER, {
  noise_episodes: (v) => noiseEpisodes(v),
  model_choice: (v) => modelChoice(v),
  timings_s: (v, r) => timings(v, r.report || {}),
  calibration: (v) => [v === null ? el("p", { class: "note" }, "Not run (no calibration lines).") : sectionView(v, TITLES)].flat(),
  model_order_candidates: (v) => [el("p", {}, `Anomaly orders identified: ${Array.isArray(v) ? v.map((m) => `m = ${m}`).join(", ") : String(v)}.`)],
  repeat_tracks_inferred: (v) => [v && Object.keys(v).length ? readableView(v, TITLES)
    : el("p", { class: "note" }, "None: every repeat line has its track in lines.csv.")],
});

function adaptiveMinusFir(r) {
  return [el("p", { class: "note" }, "Where the adaptive estimate departs from the industry FIR baseline; a large RMS on a smooth line deserves a look at its profile."),
    el("div", { class: "scroll" }, table(["Line", "Flight", "Kind", "Epochs", "RMS (mGal)", "Mean (mGal)", "Std (mGal)"],
      r.adaptive_minus_fir.map((d) => ({ attrs: { "data-line": d.line }, cells: [d.line, d.flight, d.kind, String(d.n), fmt(d.rms_mgal, 3), fmt(d.mean_mgal, 3), fmt(d.std_mgal, 3)] })),
      { id: "report-diff-table" }))];
}

function identificationCard(r) {
  const id = r.identification || {};
  const em = id.em || {};
  const out = [];
  const sel = em.selection;
  if (sel && Array.isArray(sel.candidates)) {
    out.push(el("p", {}, `Model selection (${sel.criterion ?? "—"}): chosen ${sel.chosen ?? "—"}; EM ${em.converged === false ? "did NOT converge" : "converged"} after ${em.n_iterations} iterations, log L ${fmt(em.loglik, 2)}.`),
      table(["Model", "N1 (Q levels)", "N2 (R levels)", "log L", "Parameters", "BIC", "Iterations", ""],
        sel.candidates.map((c) => ({ attrs: { class: c.model === sel.chosen ? "chosen" : "" }, cells: [String(c.model), String(c.n_q ?? "—"), String(c.n_r ?? "—"),
          fmt(c.loglik, 2), String(c.n_params ?? "—"), fmt(c.bic, 2), String(c.iterations ?? "—"), c.model === sel.chosen ? "chosen" : ""] })),
        { id: "report-em-selection" }));
  }
  if (id.states && id.states.length) {
    out.push(el("h4", {}, "States (numbered from 0, as on the recognition map)"),
      table(["State", "Q (mGal² per step)", "R ((cm/s)²)", "Stay probability"], id.states.map((s) => [`state ${s.index}`, fmt(s.Q, 4), fmt(s.R, 4),
        id.transition && id.transition[s.index] ? fmt(id.transition[s.index][s.index], 4) : "—"])));
  }
  const levels = levelSupport(((r.report || {}).identification || {}).level_support);
  if (levels) out.push(...levels);
  if (id.lines_skipped && Object.keys(id.lines_skipped).length) out.push(el("h4", {}, "Lines not identified"), readableView(id.lines_skipped));
  return out;
}

// each anomaly level: where its own EM learned it, where the state map applies it, and the level
// filtered with (an emptied level at its value of an earlier EM iteration: identification.level_support)
function levelSupport(ls) {
  if (!ls || !Array.isArray(ls.Q_mgal2) || !ls.Q_mgal2.length) return null;
  const bo = ls.backoff && ls.backoff.iteration !== null && ls.backoff.iteration !== undefined ? ls.backoff : null;
  const used = bo ? bo.Q_used_mgal2 : ls.Q_mgal2;
  const flagged = new Set(ls.unsupported || []);
  const why = (i) => (!flagged.has(i) ? "" : bo ? `emptied by its EM: its level at iteration ${bo.iteration} used`
    : "emptied by its EM: filtered with its final level");
  return [el("h4", {}, `Anomaly levels: where their own EM learned them and where the state map (order m = ${ls.map_from_m ?? "—"}'s) applies them`),
    table(["Level", "Q learned (mGal² per step)", "Q filtered with", "Share under its own EM", "Share under the map", ""],
      ls.Q_mgal2.map((q, i) => ({ attrs: { class: flagged.has(i) ? "flagged" : "" }, cells: [`level ${i}`, fmt(q, 4),
        fmt(used[i], 4), pct(ls.share_em ? ls.share_em[i] : null), pct(ls.share_map ? ls.share_map[i] : null), why(i)] })),
      { id: "report-level-support" })];
}

// the top of the panel: what the result is, the warnings (first, boxed), the decisions in words
function header(s, r, rep) {
  const dl = el("a", { href: `/api/surveys/${s.id}/export?format=report`, download: "", id: "report-download" }, "Download report.json");
  return el("div", { class: "card" }, el("h3", {}, `Report of result ${r.result_id} (job ${r.job_id})`),
    el("p", { class: "note", id: "report-meta" }, [rep.survey ? `Survey ${rep.survey}` : null, rep.crs ? `CRS ${rep.crs}` : null]
      .filter(Boolean).join(" · "), rep.survey || rep.crs ? " · " : "", dl),
    s.result_outdated ? el("p", { class: "warnline", id: "report-outdated" }, "The survey's data or settings changed after this result: run processing again.") : null,
    el("div", { class: `warnbox${r.warnings.length ? "" : " clear"}`, id: "report-warnings-box" },
      el("h4", {}, r.warnings.length ? `Warnings (${r.warnings.length})` : "Warnings (0)"),
      r.warnings.length ? el("ul", { id: "report-warnings", class: "warnings" }, r.warnings.map((w) => el("li", { title: w }, plain(w, TITLES))))
        : el("p", { class: "note", id: "report-warnings" }, "none")),
    el("h4", {}, "Decisions"), summary(r));
}

// buttons to the sections (the address keeps the survey and tab: no #anchors)
function sectionNav(parts) {
  return el("div", { class: "report-nav", id: "report-nav" }, el("span", { class: "note" }, "Go to: "),
    parts.map((p) => {
      const b = el("button", { type: "button", class: "linkish" }, p.querySelector("summary h3").textContent);
      b.addEventListener("click", () => { p.open = true; p.scrollIntoView({ block: "start" }); });
      return b;
    }));
}

export async function render(sec, ctx) {
  const s = ctx.survey;
  if (!s.current_result_id) {
    sec.replaceChildren(el("div", { class: "empty" }, "No results yet: run a processing job first."));
    return;
  }
  const r = await endpoints.report(s.id);
  const rep = r.report || {};
  const cards = [];
  const add = (key, body, json) => cards.push(card(key, TITLES[key] || labelOf(key), ...body, json === undefined ? jsonDetails(key, rep[key]) : json));
  for (const key of ORDER) {
    if (key === "adaptive_minus_fir") { if (r.adaptive_minus_fir.length) add(key, adaptiveMinusFir(r), null); continue; }
    if (key === "identification") { add(key, identificationCard(r), rep.identification ? undefined : null); continue; }
    if (!(key in rep) || (rep[key] === null && key !== "calibration")) continue;
    add(key, RENDER[key] ? RENDER[key](rep[key], r) : sectionView(rep[key], TITLES));
  }
  // sections this page has no drawing for (new keys): labelled from their names, with their JSON
  for (const [key, v] of Object.entries(rep)) {
    if (ORDER.includes(key) || SKIP.has(key)) continue;
    add(key, sectionView(v, TITLES));
  }
  const all = el("details", { class: "card report-section", id: "report-all-fields" },
    el("summary", {}, el("h3", {}, "All fields (report.json as written)")),
    el("p", { class: "note" }, "Every key of the result's report.json, raw; the same file as ", el("a", { href: `/api/surveys/${s.id}/export?format=report`, download: "" }, "Download report.json"), "."),
    el("pre", { class: "json-all" }, JSON.stringify(rep, null, 2)));
  sec.replaceChildren(header(s, r, rep), sectionNav(cards), ...cards, all);
  sec.dataset.resultId = r.result_id;
}
