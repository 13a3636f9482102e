// Line profiles: z low-passed, adaptive δg ± 2σ, stationary smoother, FIR 100 s, state bands, and the
// products the result has: δg at flight height beside the datum values, the Bouguer anomaly, the
// terrain effect (shown from the legend).
import { endpoints } from "../api.js";
import { el, esc, fmt, plotConfig, pngButton, stateColor, titleFromChoice } from "../plots.js";
import { stateLabel } from "./recognition.js";
import { trackCard, trackOf } from "./tracks.js";

function stateShapes(x, state) {
  const shapes = [];
  let i0 = 0;
  for (let i = 1; i <= state.length; i++) {
    if (i === state.length || state[i] !== state[i0]) {
      if (state[i0] !== null && state[i0] > 0) {
        shapes.push({ type: "rect", xref: "x", yref: "paper", x0: x[i0], x1: x[Math.min(i, x.length - 1)], y0: 0, y1: 1,
          fillcolor: stateColor(state[i0]), opacity: 0.13, line: { width: 0 }, layer: "below" });
      }
      i0 = i;
    }
  }
  return shapes;
}

// the line's noise episodes (report noise_episodes): outlined, not filled, over both panels
function episodeShapes(eps) {
  return eps.map((e) => ({ type: "rect", xref: "x", yref: "paper", x0: e.along_start_km, x1: e.along_end_km, y0: 0, y1: 1,
    fillcolor: "rgba(0,0,0,0)", line: { color: "#b2182b", width: 1.5, dash: "dash" }, layer: "above", name: "noise-episode" }));
}

let drawLine = null;  // (line) => select and draw it, set by render

// a click on a line in a map brought us here: show that line
export function shown(sec, ctx) {
  const line = ctx.consumeLine();
  if (line !== null && drawLine) drawLine(line);
}

export async function render(sec, ctx) {
  const s = ctx.survey;
  drawLine = null;
  if (!s.current_result_id) {
    sec.replaceChildren(el("div", { class: "empty" }, "No results yet: run a processing job first."));
    return;
  }
  const [lines, report, rt] = await Promise.all([endpoints.lines(s.id), endpoints.report(s.id).catch(() => null),
    endpoints.repeatTracks(s.id).catch(() => ({ tracks: [] }))]);
  const leveled = !!(report && report.leveled);
  const states = (report && report.identification && report.identification.states) || [];
  const levStatus = report ? report.leveling_status : null;
  const diffs = Object.fromEntries(((report && report.adaptive_minus_fir) || []).map((d) => [d.line, d]));
  const ne = report && report.report ? report.report.noise_episodes : null;
  const episodes = ne && Array.isArray(ne.episodes) ? ne.episodes : [];
  const withData = lines.filter((l) => l.stats);
  const sel = el("select", { id: "profile-line" }, withData.map((l) => el("option", { value: l.line },
    `${l.line} (${l.kind}, flight ${l.flight}, ${fmt(l.qc.length_km, 1)} km, σ̄ ${fmt(l.stats.sigma_mean_mgal, 2)} mGal)`)));
  const lp = el("input", { type: "number", id: "profile-lp", min: 0, max: 600, step: 5, value: 30, style: "width:5rem" });
  const status = el("div", { class: "note", id: "profile-status" });
  const plot = el("div", { class: "plot", id: "profile-plot", style: "height:680px" });
  const lineCard = el("div", { class: "card", id: "line-card" }, el("h3", {}, "Line profile"),
    el("div", { class: "controls" }, el("label", {}, "Line", sel), el("label", {}, "z low-pass FWHM (s)", lp)),
    leveled || !levStatus ? null : el("p", { class: "warnline", id: "profile-not-leveled" }, `Leveling was not applied (${levStatus}): δg is the unleveled estimate.`),
    status, plot);
  // a repeat track's passes overlaid on one along-track axis: first when every line is a pass (a test line)
  const tc = trackCard(s, rt.tracks);
  const allPasses = tc && withData.every((l) => trackOf(rt.tracks, l.line) !== null);
  sec.replaceChildren(...(tc ? (allPasses ? [tc.card, lineCard] : [lineCard, tc.card]) : [lineCard]));
  const trackLoaded = tc ? tc.load() : null;
  let pngAdded = false;

  // the z low-pass must be a number of seconds in [0, 600]: anything else is said, not sent
  const lpValue = () => {
    const raw = lp.value.trim();
    const v = raw === "" || lp.validity.badInput ? NaN : Number(raw);
    return Number.isFinite(v) && v >= +lp.min && v <= +lp.max ? v : null;
  };
  const fail = (msg) => { status.textContent = msg; status.classList.add("error"); };
  const draw = async () => {
    const zl = lpValue();
    lp.setAttribute("aria-invalid", zl === null ? "true" : "false");
    if (zl === null) {
      fail(`z low-pass FWHM must be a number of seconds from ${lp.min} to ${lp.max}; the plot still shows the last valid value.`);
      return;
    }
    status.classList.remove("error");
    let p;
    try {
      p = await endpoints.profile(s.id, sel.value, { max_points: 2500, z_lowpass_s: zl });
    } catch (e) { fail(`Error: ${e.message}`); return; }
    const x = p.distance_km;
    const lo = p.dg.map((v, i) => (v === null || p.dg_std[i] === null ? null : v - 2 * p.dg_std[i]));
    const hi = p.dg.map((v, i) => (v === null || p.dg_std[i] === null ? null : v + 2 * p.dg_std[i]));
    const cd = p.time;
    const ht = (name) => `${name}: %{y:.2f} mGal<br>%{x:.2f} km, t=%{customdata:.1f} s<extra></extra>`;
    // adaptive − FIR, both before leveling (the filters' difference alone), beside σ
    const ad = p.dg_unleveled || p.dg;
    const diff = ad.map((v, i) => (v === null || p.dg_fir[i] === null ? null : v - p.dg_fir[i]));
    const neg = p.dg_std.map((v) => (v === null ? null : -v));
    const a2 = { xaxis: "x", yaxis: "y2" };
    const atDatum = p.dg_flight !== null && p.dg_flight !== undefined;
    const dgName = (leveled ? "adaptive δg (final, leveled)" : "adaptive δg (final, not leveled)") + (atDatum ? ", at the datum" : "");
    const traces = [
      { x, y: p.z_lowpassed, name: `z, low-passed (${p.z_lowpass_s} s)`, mode: "lines", line: { color: "#9e9e9e", width: 1 }, customdata: cd, hovertemplate: ht("z") },
      { x, y: lo, mode: "lines", line: { width: 0 }, showlegend: false, hoverinfo: "skip" },
      { x, y: hi, mode: "lines", line: { width: 0 }, fill: "tonexty", fillcolor: "rgba(31,111,235,0.18)", name: "adaptive ± 2σ", hoverinfo: "skip" },
      { x, y: p.dg, name: dgName, mode: "lines", line: { color: "#1f6feb", width: 2 }, customdata: cd, hovertemplate: ht("δg") },
      { x, y: p.dg_stationary, name: "stationary smoother", mode: "lines", line: { color: "#e6550d", width: 1.5, dash: "dash" }, customdata: cd, hovertemplate: ht("stationary") },
      { x, y: p.dg_fir, name: "FIR 100 s", mode: "lines", line: { color: "#31a354", width: 1.5, dash: "dot" }, customdata: cd, hovertemplate: ht("FIR") },
      { x, y: diff, name: "adaptive − FIR", mode: "lines", line: { color: "#6a3d9a", width: 1.5 }, customdata: cd, hovertemplate: ht("adaptive − FIR"), ...a2 },
      { x, y: p.dg_std, name: "± σ (adaptive)", legendgroup: "sigma", mode: "lines", line: { color: "#1f6feb", width: 1, dash: "dot" }, customdata: cd, hovertemplate: ht("σ"), ...a2 },
      { x, y: neg, name: "− σ", legendgroup: "sigma", showlegend: false, mode: "lines", line: { color: "#1f6feb", width: 1, dash: "dot" }, hoverinfo: "skip", ...a2 },
    ];
    // products (null when the result has none)
    const products = [];
    if (atDatum) {
      products.push("dg_flight");
      traces.push({ x, y: p.dg_flight, name: "δg at flight height (before continuation)", mode: "lines", line: { color: "#5b8fd6", width: 1.5, dash: "dashdot" }, customdata: cd, hovertemplate: ht("δg at flight height") });
    }
    if (p.dg_bouguer) {
      products.push("dg_bouguer");
      traces.push({ x, y: p.dg_bouguer, name: "Bouguer anomaly δg_B" + (atDatum ? ", at the datum" : ""), mode: "lines", line: { color: "#8c510a", width: 2 }, customdata: cd, hovertemplate: ht("δg_B") });
    }
    if (p.terrain) {
      products.push("terrain");
      traces.push({ x, y: p.terrain, name: "terrain effect (DEM)", visible: "legendonly", mode: "lines", line: { color: "#bf812d", width: 1, dash: "dot" }, customdata: cd, hovertemplate: ht("terrain effect") });
    }
    // the shaded states (all but state 0), named by their (Q, R) levels as on the recognition map
    const shaded = [...new Set(p.state.filter((v) => v !== null && v > 0))].sort((a, b) => a - b);
    for (const k of shaded) {
      traces.push({ x: [null], y: [null], type: "scatter", mode: "markers", name: `shaded: ${esc(stateLabel(states, k))}`, legendgroup: "states",
        marker: { symbol: "square", size: 13, color: stateColor(k), opacity: 0.35 }, hoverinfo: "skip" });
    }
    const eps = episodes.filter((e) => e.line === p.line);
    if (eps.length) {
      traces.push({ x: [null], y: [null], type: "scatter", mode: "lines", name: `noise episode: R(t) over ${fmt(ne.factor, 3)}× its typical level`,
        line: { color: "#b2182b", width: 1.5, dash: "dash" }, hoverinfo: "skip" });
    }
    // y range from the filtered series (z can carry large transients at the line ends)
    const vals = [...lo, ...hi, ...p.dg_stationary, ...p.dg_fir, ...(p.dg_bouguer || []), ...(atDatum ? p.dg_flight : [])]
      .filter((v) => v !== null && Number.isFinite(v));
    const ymin = Math.min(...vals), ymax = Math.max(...vals), pad = 0.25 * Math.max(ymax - ymin, 1);
    const layout = {
      title: { text: `Line ${esc(p.line)} (${esc(p.kind)}, flight ${esc(p.flight)})`, font: { size: 15 } },
      margin: { l: 70, r: 20, t: 40, b: 55 },
      xaxis: { title: { text: "Distance along line (km)" }, anchor: "y2" },
      yaxis: { title: { text: "Gravity anomaly δg (mGal)" }, range: vals.length ? [ymin - pad, ymax + pad] : undefined, domain: [0.36, 1] },
      yaxis2: { title: { text: "adaptive − FIR, σ (mGal)" }, domain: [0, 0.27], zeroline: true },
      legend: { orientation: "h", y: -0.12 },
      shapes: [...stateShapes(x, p.state), ...episodeShapes(eps)],
      hovermode: "x unified",
    };
    await Plotly.react(plot, traces, layout, plotConfig(`${s.name}-line-${p.line}`));
    if (!pngAdded) { plot.after(pngButton(plot, `${s.name}-line-profile`)); pngAdded = true; }
    const sigma = p.dg_std.filter((v) => v !== null);
    const d = diffs[p.line];
    const track = trackOf(rt.tracks, p.line);
    if (track !== null && tc) tc.show(track);
    status.textContent = `${p.n_total} epochs (${p.step === 1 ? "all" : `1 in ${p.step}`} shown) · shaded bands: the recognised state where it is not state 0 (legend; colours as on the recognition map) · mean σ ${fmt(sigma.reduce((a, b) => a + b, 0) / Math.max(1, sigma.length), 3)} mGal` +
      (d ? ` · adaptive − FIR: RMS ${fmt(d.rms_mgal, 3)} mGal (std ${fmt(d.std_mgal, 3)})` : "") +
      (track !== null ? ` · a pass of repeat track ${track}: its passes are overlaid in "Repeat track"` : "") +
      (eps.length ? ` · noise episode${eps.length > 1 ? "s" : ""} (dashed): ${eps.map((e) => `${fmt(e.along_start_km, 3)}–${fmt(e.along_end_km, 3)} km, R up to ${fmt(e.R_peak_over_typical, 3)}× typical`).join("; ")} — the estimate leans on the anomaly model there` : "");
    plot.dataset.line = p.line;
    plot.dataset.leveled = leveled ? "1" : "0";
    plot.dataset.products = products.join(" ");
    plot.dataset.episodes = String(eps.length);
  };
  const syncTitle = titleFromChoice(sel);
  drawLine = (line) => {
    if (![...sel.options].some((o) => o.value === line)) return;
    sel.value = line;
    syncTitle();
    draw();
  };
  sel.addEventListener("change", draw);
  lp.addEventListener("change", draw);
  const wanted = ctx.consumeLine();
  if (wanted !== null && withData.some((l) => l.line === wanted)) sel.value = wanted;
  syncTitle();
  if (withData.length) await draw(); else status.textContent = "No line has results.";
  await trackLoaded;
}
