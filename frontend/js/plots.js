// Shared Plotly helpers: config with PNG export, equal-aspect map layouts, state colours.

export const STATE_COLORS = ["#2c7fb8", "#e6550d", "#31a354", "#756bb1", "#de2d26", "#fdae6b", "#636363", "#9ecae1",
  "#a1d99b", "#bcbddc", "#fdd0a2", "#969696"];

export function stateColor(i) { return STATE_COLORS[i % STATE_COLORS.length]; }

// Text for Plotly (titles, trace names, hover templates, hover text): Plotly renders a subset of
// HTML there (<a href>, <b>, …) and substitutes %{…} in templates, so user-supplied names
// (surveys, lines, flights) go through esc(): shown literally, never as markup or links.
export function esc(s) {
  return String(s ?? "").replace(/&/g, "&amp;").replace(/</g, "&lt;").replace(/>/g, "&gt;").replace(/%/g, "&#37;");
}

// A download file name from a survey name.
export function fileName(s) { return String(s ?? "").replace(/[^A-Za-z0-9_.-]+/g, "_").slice(0, 100) || "aerograv"; }

export function plotConfig(filename) {
  return {
    // no "Share chart..." (plotly.js ≥ 3 shows it by default): it uploads the plot's data, i.e. the
    // survey's, to Plotly Cloud — a third party — from a product whose data stay on this server
    responsive: true, displaylogo: false, showSendToCloud: false, showEditInChartStudio: false,
    toImageButtonOptions: { format: "png", filename: fileName(filename), scale: 2 },
    modeBarButtonsToRemove: ["lasso2d", "select2d"],
  };
}

export function mapLayout(title, extra = {}) {
  return {
    title: { text: esc(title), font: { size: 15 } },
    margin: { l: 70, r: 30, t: 40, b: 55 },
    xaxis: { title: { text: "Easting (km)" }, zeroline: false, ticksuffix: "" },
    yaxis: { title: { text: "Northing (km)" }, zeroline: false, scaleanchor: "x", scaleratio: 1 },
    legend: { orientation: "h", y: -0.14 },
    hovermode: "closest",
    ...extra,
  };
}

// A "PNG" button next to a plot: Plotly.downloadImage (toImage under the hood).
export function pngButton(plotDiv, filename) {
  const b = document.createElement("button");
  b.textContent = "Save PNG";
  b.className = "png-btn";
  b.addEventListener("click", () => Plotly.downloadImage(plotDiv, { format: "png", filename: fileName(filename), scale: 2, width: plotDiv.clientWidth, height: plotDiv.clientHeight }));
  return b;
}

export function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v;
    else if (k === "html") e.innerHTML = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null && v !== false) e.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) if (c !== null && c !== undefined) e.append(c.nodeType ? c : document.createTextNode(String(c)));
  return e;
}

// A drop-down's title is its chosen option's whole text: a narrow window cuts the text shown (CSS).
// Returns the function that sets it, for a choice made by code (no change event).
export function titleFromChoice(select) {
  const set = () => { select.title = select.selectedOptions.length ? select.selectedOptions[0].textContent : ""; };
  select.addEventListener("change", set);
  set();
  return set;
}

export function showError(container, err) {
  let box = container.querySelector(":scope > .error");
  if (!box) { box = el("div", { class: "error" }); container.prepend(box); }
  if (!err) { box.hidden = true; box.textContent = ""; return; }
  box.hidden = false;
  box.textContent = err.message || String(err);
}

export function fmt(v, nd = 3) {
  if (v === null || v === undefined || Number.isNaN(v)) return "—";
  if (typeof v !== "number") return String(v);
  if (v !== 0 && (Math.abs(v) < 1e-3 || Math.abs(v) >= 1e6)) return v.toExponential(nd - 1);
  return Number(v.toFixed(nd)).toString();
}

// ---- maps: a diverging colour scale white at 0, robust symmetric limits, hillshade

const DIVERGING = ["#2166ac", "#67a9cf", "#d1e5f0", "#f7f7f7", "#fddbc7", "#ef8a62", "#b2182b"];  // ColorBrewer RdBu, blue low

// Plotly colorscale for [zmin, zmax] whose white stop sits at 0 (limits need not be symmetric).
export function divergingScale(zmin, zmax, centre = 0) {
  let m = zmax > zmin ? (centre - zmin) / (zmax - zmin) : 0.5;
  m = Math.min(1, Math.max(0, m));
  const lo = DIVERGING.slice(0, 4), hi = DIVERGING.slice(3);
  const stops = [];
  lo.forEach((c, i) => stops.push([m * i / 3, c]));
  hi.forEach((c, i) => { if (i) stops.push([m + (1 - m) * i / 3, c]); });
  // Plotly needs strictly increasing positions from 0 to 1
  const out = [];
  for (const [p, c] of stops) if (!out.length || p > out[out.length - 1][0]) out.push([p, c]); else out[out.length - 1] = [p, c];
  out[0][0] = 0; out[out.length - 1][0] = 1;
  if (out.length < 2) return [[0, DIVERGING[0]], [1, DIVERGING[6]]];
  return out;
}

// The p-quantile of the finite values (p in 0…1).
export function quantile(values, p) {
  const v = values.filter((x) => x !== null && Number.isFinite(x)).sort((a, b) => a - b);
  if (!v.length) return null;
  return v[Math.min(v.length - 1, Math.max(0, Math.round(p * (v.length - 1))))];
}

// Symmetric limits ±L around 0 with L the p-quantile of |z| (a few edge cells do not set the scale).
export function symmetricLimit(z, p = 0.98) {
  const L = quantile(z.flat().map((x) => (x === null ? null : Math.abs(x))), p);
  return L && L > 0 ? L : 1;
}

// Hillshade (0…1) of a grid z[ny][nx] with node spacings dx, dy (same unit as x, y): light from
// azimuth 315°, altitude 45°; the vertical exaggeration makes the median slope ~30°.
export function hillshade(z, dx, dy, azimuthDeg = 315, altitudeDeg = 45) {
  const ny = z.length, nx = ny ? z[0].length : 0;
  const at = (j, i) => { const v = z[Math.min(ny - 1, Math.max(0, j))][Math.min(nx - 1, Math.max(0, i))]; return v === null ? NaN : v; };
  const gx = [], gy = [], mags = [];
  for (let j = 0; j < ny; j++) {
    gx.push([]); gy.push([]);
    for (let i = 0; i < nx; i++) {
      const a = (at(j, i + 1) - at(j, i - 1)) / ((Math.min(nx - 1, i + 1) - Math.max(0, i - 1)) * dx || 1);
      const b = (at(j + 1, i) - at(j - 1, i)) / ((Math.min(ny - 1, j + 1) - Math.max(0, j - 1)) * dy || 1);
      gx[j].push(a); gy[j].push(b);
      if (Number.isFinite(a) && Number.isFinite(b)) mags.push(Math.hypot(a, b));
    }
  }
  const med = quantile(mags, 0.5) || 1;
  const k = Math.tan(Math.PI / 6) / med;
  const az = (360 - azimuthDeg + 90) * Math.PI / 180, zen = (90 - altitudeDeg) * Math.PI / 180;
  return gx.map((row, j) => row.map((a, i) => {
    const b = gy[j][i];
    if (!Number.isFinite(a) || !Number.isFinite(b) || z[j][i] === null) return null;
    const slope = Math.atan(k * Math.hypot(a, b));
    const aspect = Math.atan2(b, -a);
    return Math.max(0, Math.cos(zen) * Math.cos(slope) + Math.sin(zen) * Math.sin(slope) * Math.cos(az - aspect));
  }));
}

// Line labels at each line's first point, names as text. Lines that start at (nearly) one point — the
// passes of a repeat track flown the same way — would print their labels over or against each other
// (above-left and above-right of the point read "R1-1R1-3"): they go in a column left of the point
// instead, one row per line in their order, each an annotation of its own (named by its line: a click
// on it opens that line's profile). Lines starting alone keep a text trace (cheap for many lines).
export function labelGroups(x, y) {
  const span = Math.max(Math.max(...x) - Math.min(...x), Math.max(...y) - Math.min(...y), 1e-9);
  const tol = 0.015 * span;
  const group = x.map((xi, i) => x.findIndex((xj, j) => Math.abs(xj - xi) < tol && Math.abs(y[j] - y[i]) < tol));
  const rank = group.map((g, i) => group.slice(0, i).filter((h) => h === g).length);
  const size = group.map((g) => group.filter((h) => h === g).length);
  return { group, rank, size };
}

const LABEL_FONT = { size: 10, color: "rgba(20,20,20,0.85)" };
const LABEL_ROW_PX = 13;

// { trace, annotations }: the text trace of the lone labels and the annotations of the stacked ones
// (for the layout); ``axes`` puts both on a subplot ({xaxis: "x2", yaxis: "y2"}).
export function lineLabels(lines, axes = {}) {
  const ok = lines.filter((l) => l.easting_km.length);
  const x = ok.map((l) => l.easting_km[0]), y = ok.map((l) => l.northing_km[0]);
  const { group, rank, size } = ok.length ? labelGroups(x, y) : { group: [], rank: [], size: [] };
  const alone = ok.map((_, i) => i).filter((i) => size[i] === 1);
  const trace = { x: alone.map((i) => x[i]), y: alone.map((i) => y[i]), text: alone.map((i) => esc(ok[i].line)),
    customdata: alone.map((i) => ok[i].line), type: "scatter", mode: "text", textposition: "middle left",
    textfont: LABEL_FONT, name: "line labels", showlegend: false,
    hovertemplate: "line %{text} — click for its profile<extra></extra>", ...axes };
  const annotations = ok.map((l, i) => (size[i] === 1 ? null : {
    x: x[group[i]], y: y[group[i]], xref: axes.xaxis || "x", yref: axes.yaxis || "y", text: esc(l.line), name: l.line,
    showarrow: false, xanchor: "right", yanchor: "middle", xshift: -4, yshift: ((size[i] - 1) / 2 - rank[i]) * LABEL_ROW_PX,
    font: LABEL_FONT, captureevents: true, hovertext: `line ${esc(l.line)} — click for its profile`,
  })).filter(Boolean);
  return { trace, annotations };
}

// A click on a stacked label (an annotation from lineLabels): its line.
export function onLabelClick(plotDiv, open) {
  plotDiv.on("plotly_clickannotation", (ev) => {
    const line = ev && ev.annotation && ev.annotation.name;
    if (line !== undefined && line !== null) open(line);
  });
}

// ---- tables for the report panel (every cell is text)

export function table(headers, rows, attrs = {}) {
  return el("table", attrs, el("thead", {}, el("tr", {}, headers.map((h, i) => el("th", { class: i ? "" : "l" }, h)))),
    el("tbody", {}, rows.map((r) => el("tr", r.attrs || {}, (r.cells || r).map((c, i) => el("td", { class: i ? "" : "l" }, c))))));
}

// Any JSON value as readable elements: scalars as text, arrays of objects as tables, objects as
// key/value tables (nested to a few levels, then JSON text).
export function genericView(v, depth = 0) {
  if (v === null || v === undefined) return "—";
  if (typeof v === "number") return fmt(v, 4);
  if (typeof v !== "object") return String(v);
  if (depth > 3) return el("code", {}, JSON.stringify(v).slice(0, 500));
  if (Array.isArray(v)) {
    if (!v.length) return "[]";
    if (v.every((x) => x && typeof x === "object" && !Array.isArray(x))) {
      const keys = [...new Set(v.flatMap((x) => Object.keys(x)))];
      return table(keys, v.map((x) => keys.map((k) => genericView(x[k], depth + 1))), { class: "generic" });
    }
    if (v.every((x) => x === null || typeof x !== "object")) return v.map((x) => (typeof x === "number" ? fmt(x, 4) : String(x ?? "—"))).join(", ");
    return el("div", {}, v.map((x) => el("div", {}, genericView(x, depth + 1))));
  }
  // an object of flat records (e.g. model_choice.lines: per line, the same keys): one table, a row each
  const vals = Object.values(v);
  if (vals.length > 1 && vals.every((x) => x && typeof x === "object" && !Array.isArray(x) &&
      Object.values(x).every((y) => y === null || typeof y !== "object"))) {
    const keys = [...new Set(vals.flatMap((x) => Object.keys(x)))];
    return table(["", ...keys], Object.entries(v).map(([k, x]) => [k, ...keys.map((c) => genericView(x[c], depth + 1))]), { class: "generic records" });
  }
  return table(["", ""], Object.entries(v).map(([k, x]) => [k, genericView(x, depth + 1)]), { class: "generic kv" });
}

export function jsonDetails(name, v) {
  return el("details", { class: "json" }, el("summary", {}, `${name} (JSON)`), el("pre", {}, JSON.stringify(v, null, 2)));
}

// WebGL as Plotly's scattergl needs it (regl with two extensions); without it (no GPU, WebGL
// blocked) the maps fall back to SVG scatter instead of showing a blank plot.
function webglOk() {
  try {
    const gl = document.createElement("canvas").getContext("webgl");
    return !!(gl && gl.getExtension("ANGLE_instanced_arrays") && gl.getExtension("OES_element_index_uint"));
  } catch { return false; }
}
export const SCATTER_GL = webglOk() ? "scattergl" : "scatter";
