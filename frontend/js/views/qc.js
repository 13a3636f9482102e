// QC: per-flight and per-line rates, gaps, durations, lengths; the line map (km, equal aspect).
import { endpoints } from "../api.js";
import { el, esc, fmt, lineLabels, mapLayout, onLabelClick, plotConfig, pngButton, showError } from "../plots.js";

const KIND_STYLE = { main: { color: "#1f4e79", width: 2 }, tie: { color: "#c0504d", width: 2, dash: "dash" },
  repeat: { color: "#7f7f7f", width: 2, dash: "dot" } };

export async function render(sec, ctx) {
  const s = ctx.survey;
  sec.replaceChildren(el("p", { class: "note" }, "Loading QC…"));
  if (!s.has_input) {
    sec.replaceChildren(el("div", { class: "empty" }, "This survey has no data yet: upload a flight or import a survey zip."));
    return;
  }
  const [qc, tracks] = await Promise.all([endpoints.qc(s.id), endpoints.tracks(s.id)]);
  const flights = el("table", { id: "qc-flights" },
    el("thead", {}, el("tr", {}, ["Flight", "Gravimeter rate (Hz)", "Grav. max gap (s)", "GNSS rate (Hz)", "GNSS max gap (s)",
      "Duration (min)", "Track length (km)"].map((h, i) => el("th", { class: i ? "" : "l" }, h)))),
    el("tbody", {}, qc.flights.map((f) => el("tr", {},
      el("td", { class: "l" }, f.name), el("td", {}, fmt(f.qc.gravimeter_rate_hz, 4)), el("td", {}, fmt(f.qc.gravimeter_max_gap_s)),
      el("td", {}, fmt(f.qc.gnss_rate_hz, 4)), el("td", {}, fmt(f.qc.gnss_max_gap_s)),
      el("td", {}, fmt(f.qc.duration_s / 60, 1)), el("td", {}, fmt(f.qc.length_km, 1))))));
  const lines = el("table", { id: "qc-lines" },
    el("thead", {}, el("tr", {}, ["Line", "Flight", "Kind", "Duration (s)", "Length (km)", "Speed (m/s)", "Mean h (m)",
      "GNSS rate (Hz)", "GNSS max gap (s)", "Grav. rate (Hz)", "Grav. max gap (s)"].map((h, i) => el("th", { class: i < 3 ? "l" : "" }, h)))),
    el("tbody", {}, qc.lines.map((l) => el("tr", { "data-line": l.line },
      el("td", { class: "l" }, l.line), el("td", { class: "l" }, l.flight), el("td", { class: "l" }, l.kind),
      el("td", {}, fmt(l.qc.duration_s, 1)), el("td", {}, fmt(l.qc.length_km, 2)), el("td", {}, fmt(l.qc.speed_ms, 1)),
      el("td", {}, fmt(l.qc.mean_h_m, 0)), el("td", {}, fmt(l.qc.gnss_rate_hz, 3)), el("td", {}, fmt(l.qc.gnss_max_gap_s, 2)),
      el("td", {}, fmt(l.qc.gravimeter_rate_hz, 3)), el("td", {}, fmt(l.qc.gravimeter_max_gap_s, 3))))));
  const mapDiv = el("div", { class: "plot square", id: "line-map" });
  sec.replaceChildren(
    el("div", { class: "row" },
      el("div", { class: "card" }, el("h3", {}, "Flights"), flights),
      el("div", { class: "card", style: "flex:1; min-width:480px" }, el("h3", {}, `Line map (${tracks.crs || "projected"}, km)`),
        mapDiv)),
    el("div", { class: "card" }, el("h3", {}, `Lines (${qc.lines.length})`), el("div", { class: "scroll" }, lines)));
  const seen = new Set();
  const traces = tracks.lines.filter((l) => l.easting_km.length).map((l) => {
    const first = !seen.has(l.kind); seen.add(l.kind);
    return { x: l.easting_km, y: l.northing_km, mode: "lines", type: "scatter", name: `${esc(l.kind)} lines`, legendgroup: l.kind,
      showlegend: first, line: KIND_STYLE[l.kind] || KIND_STYLE.main, text: esc(l.line), customdata: l.easting_km.map(() => l.line),
      hovertemplate: `line ${esc(l.line)} (${esc(l.kind)}, flight ${esc(l.flight)})${s.current_result_id ? " — click for its profile" : ""}<br>E %{x:.2f} km, N %{y:.2f} km<extra></extra>` };
  });
  const labels = lineLabels(tracks.lines);
  traces.push(labels.trace);
  await Plotly.newPlot(mapDiv, traces, mapLayout(`${s.name}: survey lines`, { annotations: labels.annotations }),
    plotConfig(`${s.name}-line-map`));
  mapDiv.on("plotly_click", (ev) => {
    const p = ev && ev.points && ev.points.find((q) => q.customdata !== undefined);
    if (p) ctx.openProfile(p.customdata);
  });
  onLabelClick(mapDiv, (line) => ctx.openProfile(line));
  mapDiv.after(pngButton(mapDiv, `${s.name}-line-map`));
  showError(sec, null);
}
