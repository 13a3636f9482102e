// Anomaly grid: heatmap or contours of δg (or its σ) with lines and crossovers overlaid, equal aspect in km.
import { endpoints } from "../api.js";
import { el, esc, fmt, mapLayout, plotConfig, pngButton } from "../plots.js";

export async function render(sec, ctx) {
  const s = ctx.survey;
  if (!s.current_result_id) {
    sec.replaceChildren(el("div", { class: "empty" }, "No results yet: run a processing job first."));
    return;
  }
  const g = await endpoints.grid(s.id);
  const varIn = el("select", { id: "grid-var" }, el("option", { value: "dg" }, "anomaly δg"), el("option", { value: "dg_std", disabled: !g.dg_std }, "posterior σ"));
  const styleIn = el("select", { id: "grid-style" }, el("option", { value: "heatmap" }, "heatmap"), el("option", { value: "contour" }, "filled contours"));
  const linesIn = el("input", { type: "checkbox", id: "grid-lines", checked: true });
  const xoIn = el("input", { type: "checkbox", id: "grid-xo", checked: true });
  const plot = el("div", { class: "plot square", id: "grid-plot" });
  const rep = g.report || {};
  const summary = [];
  for (const [k, v] of Object.entries(rep)) if (typeof v === "number") summary.push(`${k.replaceAll("_", " ")}: ${fmt(v, 4)}`);
  sec.replaceChildren(el("div", { class: "card" }, el("h3", {}, `Anomaly grid (${g.crs || "projected CRS"})`),
    el("div", { class: "controls" }, el("label", {}, "show", varIn), el("label", {}, "style", styleIn),
      el("label", {}, linesIn, "survey lines"), el("label", {}, xoIn, "crossovers")),
    el("p", { class: "note", id: "grid-summary" }, summary.slice(0, 8).join(" · ")), plot));

  const draw = async () => {
    const isStd = varIn.value === "dg_std";
    const z = isStd ? g.dg_std : g.dg;
    // robust colour range (1st–99th percentile) so a few edge cells do not wash out the anomalies
    const flat = z.flat().filter((v) => v !== null).sort((a, b) => a - b);
    const q = (p) => flat[Math.min(flat.length - 1, Math.max(0, Math.round(p * (flat.length - 1))))];
    const zmin = q(0.01), zmax = q(0.99);
    const field = {
      x: g.easting_km, y: g.northing_km, z, type: styleIn.value, name: isStd ? "σ" : "δg",
      colorscale: isStd ? "Viridis" : "RdBu", reversescale: false, zmin, zmax,  // high anomalies red
      colorbar: { title: { text: isStd ? "σ (mGal)" : "δg (mGal)" } },
      hovertemplate: `E %{x:.2f} km, N %{y:.2f} km<br>${isStd ? "σ" : "δg"} %{z:.2f} mGal<extra></extra>`,
      ...(styleIn.value === "contour" ? { contours: { coloring: "fill", showlines: true }, line: { width: 0.5, color: "rgba(0,0,0,0.3)" }, ncontours: 24 } : {}),
    };
    const traces = [field];
    if (linesIn.checked) {
      g.lines.forEach((l, i) => traces.push({ x: l.easting_km, y: l.northing_km, type: "scatter", mode: "lines",
        line: { color: isStd ? "rgba(255,255,255,0.75)" : (l.kind === "tie" ? "rgba(60,60,60,0.8)" : "rgba(0,0,0,0.55)"), width: 1, dash: l.kind === "tie" ? "dash" : "solid" },
        name: "lines", legendgroup: "lines", showlegend: i === 0, hovertemplate: `line ${esc(l.line)}<extra></extra>` }));
    }
    // overlapping repeat passes are not crossings: show main/tie intersections only
    const kind = Object.fromEntries(g.lines.map((l) => [l.line, l.kind]));
    const xo = g.crossovers.filter((c) => !(kind[c.line_a] === "repeat" && kind[c.line_b] === "repeat"));
    if (xoIn.checked && xo.length) {
      traces.push({ x: xo.map((c) => c.easting_km), y: xo.map((c) => c.northing_km), type: "scatter", mode: "markers",
        name: "crossovers", marker: { symbol: "x-thin", size: 7, color: "rgba(0,0,0,0.7)", line: { width: 1.5, color: "rgba(0,0,0,0.7)" } },
        text: xo.map((c) => `${esc(c.line_a)} × ${esc(c.line_b)}: before ${fmt(c.diff_before_mgal, 2)}, after ${fmt(c.diff_after_mgal, 2)} mGal`),
        hovertemplate: "%{text}<extra></extra>" });
    }
    await Plotly.react(plot, traces, mapLayout(`${s.name}: ${isStd ? "posterior σ of δg" : "free-air anomaly δg at flight height"}`), plotConfig(`${s.name}-grid`));
    plot.dataset.variable = varIn.value;
  };
  for (const c of [varIn, styleIn, linesIn, xoIn]) c.addEventListener("change", draw);
  await draw();
  plot.after(pngButton(plot, `${s.name}-grid`));
}
