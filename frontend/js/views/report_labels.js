// Readable names, units and values for report.json: an analyst reads "RMS before leveling (mGal)"
// where the file says rms_before_mgal.  Known keys have a label of their own; any other key is
// spelled out from its name (words, and the unit its suffix names), the raw key kept in the
// cell's tooltip.  Nothing is dropped: every key of a section is shown.
import { el, table } from "../plots.js";

// key → label (unit in brackets where the key has one)
export const LABELS = {
  // counts, grid, run
  flights: "Flights", lines: "Lines", epochs: "GNSS epochs on lines", decimated_points: "Decimated points (identification)",
  crossovers: "Crossovers", nx: "Grid nodes east–west", ny: "Grid nodes north–south", valid_cells: "Grid nodes with a value",
  threads: "Threads", survey: "Survey", crs: "Coordinate reference system",
  // common evidence
  applied: "Applied", reason: "Why", status: "Status", note: "Note", chosen: "Chosen", criterion: "Criterion",
  p_value: "p-value", p_rank: "p-value (signed ranks)", significance: "Significance level", n: "Count", m: "Anomaly order m",
  n_crossovers: "Crossovers", n_lines: "Lines", n_epochs: "Epochs", passes: "Passes", tracks: "Tracks", repeats: "Passes",
  order: "Order", weight: "Weight", factor: "Factor", scale: "Scale", model: "Model", family: "Family", kind: "Kind", time: "Time (s)",
  // model choice
  anomaly_levels: "Anomaly levels (Q)", anomaly_levels_reason: "Why that many levels",
  crossover_rms_mgal: "Crossover RMS (mGal)", crossover_rms_fir_mgal: "Crossover RMS of FIR 100 s (mGal)",
  p_m2_worse_than_m1: "p-value, m = 2 worse than m = 1 (t-test)", p_rank_m2_worse_than_m1: "p-value, m = 2 worse than m = 1 (signed ranks)",
  blend: "Blend of the two orders", drift_removed: "Flights' drift removed first", Q_mgal2_by_order: "Q levels per order (mGal² per step)",
  estimate: "Estimate used", flattening_ratio: "Flattening ratio", flattening_ratio_bound: "Flattening ratio bound",
  fir_signal_var_mgal2: "FIR signal variance (mGal²)", fir_noise_std_mgal: "FIR noise std (mGal)", fir_noise_samples: "FIR independent samples",
  detectable: "Anomaly detectable", estimate_std_mgal: "Estimate spread (mGal)", posterior_std_mgal: "Posterior σ (mGal)", resolved: "Resolved",
  noisy_check: "Noisy-estimate check", fir_guard: "FIR guard at the crossovers", repeat_blend: "Blend with FIR judged by the repeat passes",
  small_survey_blend: "Share of FIR where nothing can judge the estimate (small survey)", n_points: "Decimated points",
  stationary_check: "Stationary-smoother check", max_ratio: "Largest variance ratio allowed", max_disagreement: "Largest disagreement allowed",
  median_disagreement: "Median disagreement with FIR", median_variance_ratio: "Median variance ratio", weight_fir: "Weight of FIR 100 s",
  weight_raw: "Weight of FIR from the passes, before shrinking", weight_se: "Its jackknife error over the passes",
  weight_leave_one_out: "Weight with each pass left out",
  reference: "Reference each pass is compared with (the other passes')", reference_q_factor: "Reference smoother's anomaly level over Q(t)",
  reference_period_s: "Reference low-pass period (s)", msd_estimate_mgal2: "Mean square difference, adaptive (mGal²)",
  msd_fir_mgal2: "Mean square difference, FIR (mGal²)", msd_blend_mgal2: "Mean square difference, blend (mGal²)", passes_noise: "Passes noise",
  long_lowpass: "Longer low-pass", period_s: "Period (s)",
  unresolved_check: "Does the estimate resolve anything beyond its noise", crossover_std_mgal: "Crossover error per line (mGal)",
  spread_mgal: "Along-line spread (mGal)", fir_crossover_std_mgal: "Crossover error per line of the estimate replaced (mGal)",
  fir_spread_mgal: "Along-line spread of the estimate replaced (mGal)", median_line_s: "Median line duration (s)", resolves: "Resolves something",
  // repeat lines
  internal_accuracy_mgal: "Internal accuracy ε (mGal)", dg_mgal: "adaptive (final)", dg_unleveled_mgal: "adaptive before leveling", dg_stationary_mgal: "stationary", dg_fir_mgal: "FIR 100 s",
  across_track_spread_km: "Spread across the track (km)",
  // level refinement
  Q_mgal2: "Anomaly levels Q (mGal² per step)", Q_full_rate_ml_mgal2: "Q by full-rate likelihood (mGal² per step)",
  Q_stationary_mgal2: "Stationary Q (mGal² per step)", Q_stationary_used_mgal2: "Stationary Q used (mGal² per step)",
  R_local_scale: "Scale of the local noise level R", lift_only: "Levels may only rise", noise_model: "Noise model", loglik_gain: "Log-likelihood gain",
  n_evaluations: "Likelihood evaluations", std_level_factor: "Std level factor", std_level_reason: "Why the std carries the level spread",
  std_repeat_tracks: "Std checked on the repeat tracks", noisy_passes_rescaled: "Noisy repeat passes smoothed again",
  repeat_level_check: "Test-line level check", smooth_lift_capped: "Smooth lift capped",
  unlearned_levels: "Levels the EM never learned (the likelihood's level used)", em_floor_mgal2: "Level taken back from the EM (mGal² per step)",
  rough_level: "Rough level (at least the factor × its full-rate likelihood level)", full_rate_ml_mgal2: "Full-rate likelihood level (mGal² per step)",
  lifted_mgal2: "Level as lifted (mGal² per step)", used_mgal2: "Level used (mGal² per step)", raised: "Raised", pass_lines: "Passes", pass_noise_ratio: "Noise ratio per pass",
  noise_part_mgal: "Passes' scatter (mGal)", smoothing_part_mgal: "Smoothing part (mGal)", posterior_mgal: "Posterior σ (mGal)",
  independent_stretches: "Independent stretches", versus_q_factor: "Against Q × factor", smoothing_p_value: "p-value of the smoothing part",
  noise_p_value: "p-value of the passes' noise", tried: "Tried", rescaled: "Smoothed again", factors: "Factors tried", msd_mgal2: "Mean square difference (mGal²)",
  p_values: "p-values", block_positions: "Block positions",
  // noise model
  dt_s: "Sample interval (s)", components: "Components", fit: "Fit", fmax_hz: "Fitted up to (Hz)", fit_fmax_hz: "Fitted up to (Hz)",
  n_bins: "Spectral bins", n_difference_bins: "Spectral bins of pass differences", n_pass_differences: "Pass differences",
  level_band_hz: "Level band (Hz)", level_scale: "Level scale", level_note: "Level", candidates: "Candidates", nll: "−log L", n_params: "Parameters",
  bic: "BIC", nll_by_m: "−log L per anomaly order", anomaly_rolloff_s: "Anomaly roll-off β (s)", Q_whittle_mgal2: "Q of the spectral fit (mGal² per step)",
  m_whittle: "Anomaly order of the spectral fit", phi: "φ", weight_mgal2: "Weight (mGal²)", label: "Component",
  holes_bridged: "Holes bridged in the fit", max_hole_epochs: "Longest hole (epochs)", epochs_bridged: "Epochs bridged",
  fit_min_stretch_s: "Shortest stretch fitted (s)", hidden_corners_hz: "Hidden corners (Hz)",
  // measurement
  offset_s: "Offset (s)", se_s: "Standard error (s)", correlation: "Correlation", estimated: "Estimated", band_hz: "Band (Hz)",
  residual_reduction: "Residual reduction", declared_tau_s: "Declared lag τ (s)", estimated_tau_s: "Lag τ per flight (s)",
  threshold: "Threshold (robust σ)", flagged: "Flagged epochs", fraction: "Fraction", repair: "Repair", height_outliers: "Height outliers",
  size_m: "Size (m)", drift_mgal_per_h: "Drift (mGal/h)", static_periods: "Static periods", reading_error_mgal: "Reading error (mGal)",
  absolute: "Absolute", t_start: "Start (s)", t_end: "End (s)", delay_s: "Delay (s)", t_stat: "t", lowpass_hz: "Low-pass (Hz)",
  min_t: "Smallest t applied", n_independent: "Independent samples",
  // leveling
  rms_before_mgal: "Crossover RMS before leveling (mGal)", rms_after_mgal: "Crossover RMS after leveling (mGal)",
  rms_after_if_leveled_mgal: "Crossover RMS if leveled (mGal)", n_drift_parameters: "Drift parameters", degree: "Drift degree",
  per_flight: "Drift per flight", cross_validation: "Leave-one-line-out check", std_check: "σ check at the crossovers", rms_ratio: "RMS ratio",
  common_level: "Common level", refused_drift: "Drift refused",
  // products
  atmospheric_correction: "Atmospheric correction", mean_mgal: "Mean (mGal)", min_mgal: "Minimum (mGal)", max_mgal: "Maximum (mGal)",
  datum: "Datum", terrain: "Terrain correction", dem: "Terrain model (DEM)", grids: "Grids written", free_air: "Free-air",
  bouguer: "Bouguer", free_air_flight_height: "Free-air at flight height",
  // stage timings
  ingest: "Reading the survey", measurement: "Measurement", noise: "Noise model", fir: "FIR 100 s baseline", regularization: "Regularization",
  learning: "Learning (EM)", recognition: "Recognition", nlmeans: "Recognition map (NL-means)", filtering: "Filtering", choice: "Model choice",
  leveling: "Leveling", gridding: "Gridding", writing: "Writing the outputs",
};

// unit suffixes of report.json keys, longest first
const UNITS = [["_mgal_per_h", "mGal/h"], ["_mgal2", "mGal²"], ["_mgal", "mGal"], ["_cm2s2", "(cm/s)²"], ["_per_km", "1/km"],
  ["_km", "km"], ["_hz", "Hz"], ["_ms", "ms"], ["_m", "m"], ["_s", "s"], ["_deg", "°"]];
const WORDS = { rms: "RMS", fir: "FIR", gnss: "GNSS", em: "EM", dg: "δg", std: "std", msd: "mean square difference", bic: "BIC", nll: "−log L",
  cv: "cross-validation", se: "standard error", tau: "τ", dem: "DEM", crs: "CRS", q: "Q", r: "R", n: "number of", ml: "ML", p: "p" };

// "rms_after_if_leveled_mgal" → "RMS after if leveled (mGal)"; known keys from LABELS
export function labelOf(key) {
  if (Object.prototype.hasOwnProperty.call(LABELS, key)) return LABELS[key];
  let k = String(key), unit = "";
  for (const [suffix, u] of UNITS) {
    if (k.length > suffix.length && k.toLowerCase().endsWith(suffix)) { unit = u; k = k.slice(0, -suffix.length); break; }
  }
  const words = k.split("_").filter(Boolean).map((w) => WORDS[w.toLowerCase()] ?? w);
  let text = words.join(" ");
  text = text.charAt(0).toUpperCase() + text.slice(1);
  return unit ? `${text} (${unit})` : text;
}

// Developer references in report.json's text (its keys, the specification's sections) said in the
// page's words: "(report spike_repair.height_outliers)" → "(listed under “GNSS spike repair”)".
export function plain(s, titles = {}) {
  return String(s)
    .replace(/\s*\(report ([a-z_]+)(?:\.[A-Za-z_.]+)?\)/g, (_, k) => ` (listed under “${titles[k] || labelOf(k)}”)`)
    .replace(/SPEC §\d+'s /g, "the ")
    .replace(/\(SPEC's default\)/g, "(the default)")
    .replace(/\s*\((?:SPEC|METHOD)[^)]*\)/g, "");
}

// a number to 4 significant digits (integers as they are), tiny and huge ones in exponent form
export function num(v) {
  if (v === null || v === undefined || Number.isNaN(v)) return "—";
  if (!Number.isFinite(v)) return String(v);
  if (Number.isInteger(v)) return String(v);
  const a = Math.abs(v);
  if (a !== 0 && (a < 1e-3 || a >= 1e7)) return v.toExponential(3).replace(/\.?0+e/, "e");
  return String(Number(v.toPrecision(4)));
}

function scalar(v, titles) {
  if (v === null || v === undefined) return "—";
  if (typeof v === "boolean") return v ? "yes" : "no";
  if (typeof v === "number") return num(v);
  return plain(v, titles);
}

const isRecord = (x) => x && typeof x === "object" && !Array.isArray(x);
const flat = (x) => isRecord(x) && Object.values(x).every((y) => y === null || typeof y !== "object" ||
  (Array.isArray(y) && y.every((z) => z === null || typeof z !== "object")));

function keyCell(k) { return el("span", { class: "key", title: `report.json key: ${k}` }, labelOf(k)); }

// Any report.json value with readable labels: scalars as text, lists of numbers joined, lists of
// records and objects of flat records (per flight, per line) as one table with labelled columns, other
// objects as label/value rows; deeper than a few levels, JSON text.
export function readableView(v, titles = {}, depth = 0) {
  if (v === null || typeof v !== "object") return scalar(v, titles);
  if (depth > 4) return el("code", {}, JSON.stringify(v).slice(0, 500));
  if (Array.isArray(v)) {
    if (!v.length) return "none";
    if (v.every(isRecord)) {
      const keys = [...new Set(v.flatMap((x) => Object.keys(x)))];
      return table(keys.map((k) => keyCell(k)), v.map((x) => keys.map((k) => readableView(x[k], titles, depth + 1))), { class: "readable" });
    }
    if (v.every((x) => x === null || typeof x !== "object")) return v.map((x) => scalar(x, titles)).join(", ");
    return el("div", {}, v.map((x) => el("div", {}, readableView(x, titles, depth + 1))));
  }
  const entries = Object.entries(v);
  if (!entries.length) return "none";
  const keys = [...new Set(entries.flatMap(([, x]) => (isRecord(x) ? Object.keys(x) : [])))];
  // records sharing most of their keys (per flight, per line): one table, a row each
  if (entries.length > 1 && entries.every(([, x]) => flat(x) && 2 * Object.keys(x).length >= keys.length)) {
    return table(["", ...keys.map((k) => keyCell(k))], entries.map(([k, x]) => [k, ...keys.map((c) => readableView(x[c], titles, depth + 1))]),
      { class: "readable records" });
  }
  return el("table", { class: "readable kv" }, el("tbody", {}, entries.map(([k, x]) =>
    el("tr", {}, el("th", { class: "l" }, keyCell(k)), el("td", { class: "l" }, readableView(x, titles, depth + 1))))));
}

// A section: its plain entries (numbers, text, lists of them) as label/value rows, then each nested
// part under its own heading.
export function sectionView(v, titles = {}) {
  if (!isRecord(v)) return [el("div", { class: "readable-value" }, readableView(v, titles))];
  const isPlain = (x) => x === null || typeof x !== "object" || (Array.isArray(x) && x.every((z) => z === null || typeof z !== "object"));
  const entries = Object.entries(v);
  const plainOnes = entries.filter(([, x]) => isPlain(x));
  const out = plainOnes.length ? [readableView(Object.fromEntries(plainOnes), titles)] : [];
  for (const [k, x] of entries.filter(([, y]) => !isPlain(y))) {
    out.push(el("h4", { title: `report.json key: ${k}` }, labelOf(k)), readableView(x, titles, 1));
  }
  return out;
}
