// Repeat tracks (a test line flown several times, or a repeat line of a survey): every pass of a
// track overlaid on one along-track axis — the distance along the track's principal direction from
// one origin (server: app/web/repeat.py), so a pass flown the other way lines up with the others —
// with the estimate chosen (adaptive ± σ, stationary, FIR 100 s) and the track's repeatability
// figures from report.json beside it.
import { endpoints } from "../api.js";
import { el, esc, fmt, plotConfig, pngButton, stateColor, table, titleFromChoice } from "../plots.js";

// estimate → [the pass's series, legend words, report.json internal_accuracy_mgal key]
export const TRACK_ESTIMATES = {
  adaptive: ["dg", "adaptive δg (final)", "dg_mgal"],
  stationary: ["dg_stationary", "stationary smoother", "dg_stationary_mgal"],
  fir: ["dg_fir", "FIR 100 s", "dg_fir_mgal"],
};

// the repeatability figures of report.json repeat_lines.<track>, the chosen estimate's row marked
function repeatability(t, chosen) {
  const rl = t.repeatability || {};
  const acc = rl.internal_accuracy_mgal || {};
  const rows = Object.entries(TRACK_ESTIMATES).map(([k, [, name, key]]) => [k, name, typeof acc[key] === "number" ? acc[key] : null]);
  const finite = rows.map((r) => r[2]).filter((v) => v !== null);
  const worst = finite.length > 1 ? Math.max(...finite) : null;
  const out = [el("h4", {}, "Repeatability (report)"),
    table(["Estimate", "Internal accuracy ε (mGal)"], rows.map(([k, name, v]) => ({
      attrs: { class: k === chosen ? "chosen" : "", "data-estimate": k },
      cells: [name, v === null ? "—" : el("span", { class: v === worst ? "worst" : "" }, fmt(v, 3))] })),
    { id: "track-repeatability" }),
    el("p", { class: "note" }, `ε = sqrt(Σ(g − ḡ)² / (n (K−1))) over the K = ${rl.repeats ?? t.passes.length} passes` +
      (worst !== null ? "; the least repeatable estimate in red." : ".") +
      (rl.across_track_spread_km != null ? ` Passes' spread across the track: ${fmt(1000 * rl.across_track_spread_km, 3)} m.` : ""))];
  const sc = t.std_check;
  if (sc && sc.posterior_mgal != null) {
    out.push(el("p", { class: "note", id: "track-std-check" }, `Adaptive σ against the passes: posterior σ ${fmt(sc.posterior_mgal, 3)} mGal, ` +
      `the passes' scatter ${fmt(sc.noise_part_mgal, 3)} mGal` + (sc.scale != null ? `; σ scaled × ${fmt(sc.scale, 3)}.` : ".")));
  }
  out.push(el("h4", {}, "Passes"), table(["Pass", "Direction", "Start (s)", "Off axis (m)", "Mean σ (mGal)"],
    t.passes.map((p) => ({ attrs: { "data-line": p.line, title: `flight ${p.flight}; off axis: RMS distance from the track's axis` },
      cells: [p.line, p.direction, fmt(p.t_start, 1), fmt(p.across_rms_m, 2), fmt(p.sigma_mean_mgal, 3)] })),
    { id: "track-passes" }));
  return out;
}

const rgba = (hex, a) => `rgba(${[1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16)).join(",")},${a})`;

function traces(t, estimate, band) {
  const [key, name] = TRACK_ESTIMATES[estimate];
  const out = [];
  t.passes.forEach((p, i) => {
    const y = p[key] || p.along_km.map(() => null);
    const colour = stateColor(i);
    const label = `${esc(p.line)} (${p.direction === "reverse" ? "reverse" : "forward"})`;
    if (band > 0 && estimate === "adaptive" && p.dg_std) {
      const lo = y.map((v, j) => (v === null || p.dg_std[j] === null ? null : v - band * p.dg_std[j]));
      const hi = y.map((v, j) => (v === null || p.dg_std[j] === null ? null : v + band * p.dg_std[j]));
      out.push({ x: p.along_km, y: lo, mode: "lines", line: { width: 0 }, showlegend: false, hoverinfo: "skip", legendgroup: p.line,
        meta: { line: p.line, role: "band-low" } });
      out.push({ x: p.along_km, y: hi, mode: "lines", line: { width: 0 }, fill: "tonexty", fillcolor: rgba(colour, 0.18), showlegend: false,
        hoverinfo: "skip", legendgroup: p.line, meta: { line: p.line, role: "band-high" } });
    }
    out.push({ x: p.along_km, y, name: label, mode: "lines", legendgroup: p.line, line: { color: colour, width: 1.8, dash: p.direction === "reverse" ? "dash" : "solid" },
      customdata: p.time, meta: { line: p.line, role: "estimate" },
      hovertemplate: `${label}: %{y:.2f} mGal<br>%{x:.2f} km along the track, t=%{customdata:.1f} s<extra></extra>` });
  });
  return out;
}

// The repeat-track card (null when the result has no track of two or more passes).  Returns
// { card, show(track) }: show() selects a track (a pass opened from a map).
export function trackCard(s, tracks) {
  if (!tracks || !tracks.length) return null;
  const sel = el("select", { id: "track-select" }, tracks.map((t) => el("option", { value: t.track }, `${t.track} (${t.lines.length} passes: ${t.lines.join(", ")})`)));
  const est = el("select", { id: "track-estimate" }, Object.entries(TRACK_ESTIMATES).map(([k, [, n]]) => el("option", { value: k }, n)));
  const band = el("select", { id: "track-band" }, [["0", "none"], ["1", "± σ"], ["2", "± 2σ"]].map(([v, n]) => el("option", { value: v, selected: v === "2" }, n)));
  const status = el("div", { class: "note", id: "track-status" });
  const plot = el("div", { class: "plot", id: "track-plot", style: "height:520px" });
  const side = el("div", { class: "track-side", id: "track-side" });
  const card = el("div", { class: "card", id: "track-card" }, el("h3", {}, "Repeat track: passes overlaid"),
    el("p", { class: "note" }, "Every pass of the track against one along-track distance (the projection of its positions on the track's " +
      "direction, from one origin): passes flown the other way (dashed) line up with the others."),
    el("div", { class: "controls" }, el("label", {}, "Track", sel), el("label", {}, "Estimate", est), el("label", {}, "Band (adaptive)", band)),
    status, el("div", { class: "track-row" }, plot, side));
  let data = null, pngAdded = false;
  const syncTitle = titleFromChoice(sel);
  const redraw = async () => {
    if (!data) return;
    band.disabled = est.value !== "adaptive";
    band.title = band.disabled ? "only the adaptive estimate has a posterior σ" : "";
    const name = TRACK_ESTIMATES[est.value][1];
    const layout = {
      title: { text: `Repeat track ${esc(data.track)}: ${data.passes.length} passes, ${esc(name)}`, font: { size: 15 } },
      margin: { l: 70, r: 20, t: 40, b: 55 },
      xaxis: { title: { text: `Distance along the track (km, azimuth ${fmt(data.axis.azimuth_deg, 1)}°)` }, range: [-0.02 * data.axis.length_km, 1.02 * data.axis.length_km] },
      yaxis: { title: { text: "Gravity anomaly δg (mGal)" } },
      legend: { orientation: "h", y: -0.16 }, hovermode: "closest",
    };
    await Plotly.react(plot, traces(data, est.value, +band.value), layout, plotConfig(`${s.name}-track-${data.track}`));
    if (!pngAdded) { card.append(pngButton(plot, `${s.name}-repeat-track`)); pngAdded = true; }
    side.replaceChildren(...repeatability(data, est.value));
    plot.dataset.track = data.track;
    plot.dataset.estimate = est.value;
  };
  let asked = 0;   // a track chosen while another loads: only the last one asked is drawn
  const load = async () => {
    status.classList.remove("error");
    const mine = ++asked;
    let got;
    try {
      got = await endpoints.repeatTrack(s.id, sel.value, { max_points: 1500 });
    } catch (e) { if (mine === asked) { status.textContent = `Error: ${e.message}`; status.classList.add("error"); } return; }
    if (mine !== asked) return;
    data = got;
    const rev = data.passes.filter((p) => p.direction === "reverse").length;
    status.textContent = `${data.passes.length} passes (${rev} flown the other way), track ${fmt(data.axis.length_km, 2)} km long; ` +
      `distance 0 at the end the first pass (${data.passes[0].line}) starts from.`;
    await redraw();
  };
  sel.addEventListener("change", load);
  est.addEventListener("change", redraw);
  band.addEventListener("change", redraw);
  const show = (track) => {
    if (![...sel.options].some((o) => o.value === track)) return;
    if (sel.value !== track) { sel.value = track; syncTitle(); load(); }
  };
  return { card, load, show };
}

// the track a line is a pass of (null when none)
export function trackOf(tracks, line) {
  const t = (tracks || []).find((x) => x.lines.includes(line));
  return t ? t.track : null;
}
