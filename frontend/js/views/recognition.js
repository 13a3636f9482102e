// Recognition state map: decimated points coloured by state; h and ρ re-smooth on the server (NL-means).
import { endpoints } from "../api.js";
import { SCATTER_GL, el, esc, fmt, mapLayout, plotConfig, pngButton, stateColor } from "../plots.js";

// "state 2 (Q1, R0): Q=…, R=…": states numbered from 0 as in identification.json, with their levels
export function stateLabel(states, i) {
  const st = states.find((x) => x.index === i);
  if (!st) return `state ${i}`;
  const qs = [...new Set(states.map((x) => x.Q))].sort((a, b) => a - b);
  const rs = [...new Set(states.map((x) => x.R))].sort((a, b) => a - b);
  return `state ${i} (Q${qs.indexOf(st.Q)}, R${rs.indexOf(st.R)}): Q=${fmt(st.Q, 3)} mGal² per step, R=${fmt(st.R, 3)} (cm/s)²`;
}

function signature(arr) {
  let h = 0;
  for (let i = 0; i < arr.length; i++) h = (h * 31 + arr[i] + 1) | 0;
  return (h >>> 0).toString(16);
}

export async function render(sec, ctx) {
  const s = ctx.survey;
  if (!s.current_result_id) {
    sec.replaceChildren(el("div", { class: "empty" }, "No results yet: run a processing job first."));
    return;
  }
  const hIn = el("input", { type: "range", id: "rec-h", min: 0, max: 5, step: 0.1, value: 0.5 });
  const rhoIn = el("input", { type: "range", id: "rec-rho", min: 0, max: 15, step: 0.5, value: 10 });
  const hOut = el("output", { id: "rec-h-val" }, "0.5");
  const rhoOut = el("output", { id: "rec-rho-val" }, "10.0");
  const modeIn = el("select", { id: "rec-mode" }, el("option", { value: "soft" }, "soft (probabilities)"), el("option", { value: "hard" }, "hard (labels)"));
  const showIn = el("select", { id: "rec-show" }, el("option", { value: "smoothed" }, "smoothed states"), el("option", { value: "raw" }, "raw (Viterbi) states"));
  const status = el("div", { class: "note", id: "rec-status" }, "loading…");
  const apply = el("button", { id: "rec-apply", type: "button", title: "Start a filter job with these h, ρ: NL-means → filtering → leveling → grid, reusing the stored identification (no EM)" }, "Apply h, ρ");
  const applyNote = el("span", { class: "note", id: "rec-apply-note" }, "");
  const plot = el("div", { class: "plot square", id: "rec-map" });
  // other h, ρ than the result's are a preview: the profiles, grid and exports still show the result
  const preview = el("p", { class: "warnline", id: "rec-preview", hidden: true });
  sec.replaceChildren(el("div", { class: "card" },
    el("h3", {}, "Recognition map — NL-means smoothing of the Markov states"),
    el("p", { class: "note" }, "Each decimated point is re-estimated from all points within ρ, weighted by exp(−h·d) with d in km. ",
      "Larger ρ or smaller h → smoother map."),
    el("div", { class: "controls" },
      el("label", {}, "h (km⁻¹)", hIn, hOut), el("label", {}, "ρ (km)", rhoIn, rhoOut),
      el("label", {}, "mode", modeIn), el("label", {}, "show", showIn), apply, applyNote),
    preview, status, plot));

  // the current result's own map first (the h, ρ it was made with), then the analyst's values
  const t0 = performance.now();
  const base = await endpoints.recognition(s.id, {});
  const rtt0 = performance.now() - t0;   // said "round trip 0 ms" for the first map
  hIn.value = base.h; rhoIn.value = base.rho; modeIn.value = base.mode;
  hOut.textContent = (+base.h).toFixed(1); rhoOut.textContent = (+base.rho).toFixed(1);
  let current = base.state;
  const legend = Array.from({ length: base.n_states }, (_, i) => ({
    x: [null], y: [null], type: SCATTER_GL, mode: "markers", name: stateLabel(base.states, i),
    marker: { color: stateColor(i), size: 9 }, hoverinfo: "skip" }));
  const colors = (arr) => arr.map((v) => stateColor(v));
  const text = base.line.map((l) => `line ${esc(l)}`);
  const trace = { x: base.easting_km, y: base.northing_km, type: SCATTER_GL, mode: "markers", showlegend: false,
    marker: { color: colors(current), size: 7 }, text, customdata: base.line,
    hovertemplate: "%{text} — click for its profile<br>E %{x:.2f} km, N %{y:.2f} km<extra></extra>" };
  const layout = mapLayout(`${s.name}: recognised states`);
  await Plotly.newPlot(plot, [trace, ...legend], layout, plotConfig(`${s.name}-recognition`));
  if (plot.querySelector(".no-webgl")) {  // Plotly could not start WebGL here: SVG markers instead of a blank map
    Plotly.purge(plot);
    for (const t of [trace, ...legend]) t.type = "scatter";
    await Plotly.newPlot(plot, [trace, ...legend], layout, plotConfig(`${s.name}-recognition`));
  }
  plot.dataset.renderer = trace.type;
  plot.after(pngButton(plot, `${s.name}-recognition`));
  plot.on("plotly_click", (ev) => {
    const p = ev && ev.points && ev.points.find((q) => q.customdata !== undefined && q.customdata !== null);
    if (p) ctx.openProfile(p.customdata);
  });

  const update = (r, rtt) => {
    current = r.state;
    const shown = showIn.value === "raw" ? base.state_raw : current;
    Plotly.restyle(plot, { "marker.color": [colors(shown)] }, [0]);
    const counts = Array.from({ length: base.n_states }, (_, i) => shown.filter((v) => v === i).length);
    const raw = showIn.value === "raw";
    // the raw states are not smoothed: h, ρ and the mode change nothing there
    for (const i of [hIn, rhoIn, modeIn]) {
      i.disabled = raw;
      i.title = raw ? "the raw (Viterbi) states are not smoothed: show the smoothed states to use h, ρ and the mode" : "";
    }
    status.classList.remove("error");   // a failed request before this one is over
    status.textContent = (raw ? `${base.n_points} points · raw (Viterbi) states, before NL-means (h, ρ and the mode apply to the smoothed states) · `
      : `${base.n_points} points · h=${r.h} km⁻¹, ρ=${r.rho} km (${r.mode}) · ` +
        (rtt > 0 ? `server ${fmt(r.elapsed_ms, 1)} ms, round trip ${Math.round(rtt)} ms · ` : "")) +
      counts.map((c, i) => `state ${i}: ${c}`).join(", ");
    const moved = !raw && (+r.h !== +base.h || +r.rho !== +base.rho || r.mode !== base.mode);
    preview.hidden = !moved;
    preview.textContent = moved ? `Preview: the current result was made with h=${base.h} km⁻¹, ρ=${base.rho} km (${base.mode}); ` +
      "its profiles, grid and exports show that. “Apply h, ρ” runs a filter job with the values above." : "";
    plot.dataset.signature = signature(shown);
    plot.dataset.h = r.h; plot.dataset.rho = r.rho; plot.dataset.show = showIn.value;
  };
  update(base, rtt0);

  let inflight = false, pending = false;
  const request = async () => {
    if (inflight) { pending = true; return; }
    inflight = true;
    const t0 = performance.now();
    try {
      const r = await endpoints.recognition(s.id, { h: hIn.value, rho: rhoIn.value, mode: modeIn.value, coords: false });
      update(r, performance.now() - t0);
    } catch (e) { status.textContent = `Error: ${e.message}`; status.classList.add("error"); }
    finally {
      inflight = false;
      if (pending) { pending = false; request(); }
    }
  };
  hIn.addEventListener("input", () => { hOut.textContent = (+hIn.value).toFixed(1); request(); });
  rhoIn.addEventListener("input", () => { rhoOut.textContent = (+rhoIn.value).toFixed(1); request(); });
  modeIn.addEventListener("change", request);
  showIn.addEventListener("change", () => update({ state: current, h: +hIn.value, rho: +rhoIn.value, mode: modeIn.value, elapsed_ms: 0 }, 0));
  apply.addEventListener("click", async () => {
    apply.disabled = true;
    try {
      const job = await endpoints.submitJob(s.id, "filter", { nlmeans_h_per_km: +hIn.value, nlmeans_rho_km: +rhoIn.value, nlmeans_mode: modeIn.value });
      applyNote.classList.remove("error");
      applyNote.textContent = `filter job ${job.id} started (h=${hIn.value} km⁻¹, ρ=${rhoIn.value} km; the identification is reused) — see Processing`;
      applyNote.dataset.job = job.id;
      await ctx.jobStarted();
    } catch (e) { applyNote.textContent = `Error: ${e.message}`; applyNote.classList.add("error"); }
    finally { apply.disabled = false; }
  });
}
