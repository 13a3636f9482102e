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
    responsive: true, displaylogo: false,
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
