// Anomaly grid: δg on a diverging scale white at 0 — at the median for a relative level without a base
// tie — (symmetric robust limits or the analyst's), its σ,
// or both side by side; optional hillshade; lines (click one for its profile), labels and crossovers.
// Products: free-air or Bouguer (with a DEM), at flight height or at the datum (when one was used);
// a choice the result does not have is disabled with the reason as its tooltip.
import { endpoints } from "../api.js";
import { divergingScale, el, esc, fmt, hillshade, lineLabels, mapLayout, onLabelClick, plotConfig, pngButton, quantile, showError, symmetricLimit } from "../plots.js";

export function baseTieMissing(report) {
  return ((report && report.warnings) || []).some((w) => String(w).startsWith("no absolute base tie"));
}

export async function render(sec, ctx) {
  const s = ctx.survey;
  if (!s.current_result_id) {
    sec.replaceChildren(el("div", { class: "empty" }, "No results yet: run a processing job first."));
    return;
  }
  let g = await endpoints.grid(s.id);
  const relative = baseTieMissing(g.report);
  const productIn = el("select", { id: "grid-product" }, el("option", { value: "free_air" }, "free-air"),
    el("option", { value: "bouguer" }, "Bouguer"));
  const heightIn = el("select", { id: "grid-height" }, el("option", { value: "flight" }, "flight height"),
    el("option", { value: "datum" }, "datum"));
  const heightLabel = el("label", { id: "grid-height-label" }, "at", heightIn);
  const productNote = el("span", { class: "note", id: "grid-product-note" });
  // options enabled by what the result has (g.available[product][height]); the reason as tooltip
  const syncChoices = () => {
    productIn.value = g.product;
    heightIn.value = g.height;
    const av = g.available || {}, why = { ...(g.unavailable || {}) };
    // the server's reason names the API (PUT /api/surveys/{id}/dem): the analyst gets this page's way
    for (const k of Object.keys(why)) {
      if (!s.has_dem && /has no DEM/.test(String(why[k]))) {
        why[k] = "this survey has no DEM (terrain model): add one under “Terrain model (DEM)” on the left " +
          "(a GeoTIFF, heights in metres) and process the survey again";
      }
    }
    for (const o of productIn.options) {
      const ok = !!(av[o.value] && av[o.value][g.height]);
      o.disabled = !ok && o.value !== g.product;
      o.title = ok ? "" : (why[`${o.value}@${g.height}`] || "not available");
    }
    for (const o of heightIn.options) {
      const ok = !!(av[g.product] && av[g.product][o.value]);
      o.disabled = !ok && o.value !== g.height;
      o.title = ok ? "" : (why[`${g.product}@${o.value}`] || "not available");
    }
    const noBouguer = [...productIn.options].find((o) => o.value === "bouguer").disabled;
    productIn.title = noBouguer ? `Bouguer: ${why[`bouguer@${g.height}`] || "not available"}` : "";
    productNote.textContent = noBouguer ? `Bouguer anomaly not available: ${why[`bouguer@${g.height}`] || ""}` : "";
    // the height choice only when the values were continued to a datum
    heightLabel.hidden = !g.datum;
  };
  const varIn = el("select", { id: "grid-var" }, el("option", { value: "dg" }, "anomaly δg"),
    el("option", { value: "dg_std", disabled: !g.dg_std }, "posterior σ"),
    el("option", { value: "both", disabled: !g.dg_std }, "δg and σ side by side"));
  const styleIn = el("select", { id: "grid-style" }, el("option", { value: "heatmap" }, "heatmap"), el("option", { value: "contour" }, "filled contours"));
  const zminIn = el("input", { type: "number", id: "grid-zmin", step: "any", placeholder: "auto", style: "width:6rem" });
  const zmaxIn = el("input", { type: "number", id: "grid-zmax", step: "any", placeholder: "auto", style: "width:6rem" });
  const shadeIn = el("input", { type: "checkbox", id: "grid-hillshade" });
  const linesIn = el("input", { type: "checkbox", id: "grid-lines", checked: true });
  const labelsIn = el("input", { type: "checkbox", id: "grid-labels", checked: true });
  const xoIn = el("input", { type: "checkbox", id: "grid-xo", checked: true });
  const plot = el("div", { class: "plot square", id: "grid-plot" });
  const rep = g.report || {};
  const summary = [];
  // the report's figures (not the worker's thread count: how it ran, not what it found)
  for (const [k, v] of Object.entries(rep)) if (typeof v === "number" && k !== "threads") summary.push(`${k.replaceAll("_", " ")}: ${fmt(v, 4)}`);
  const xo = (rep.crossovers && typeof rep.crossovers === "object") ? rep.crossovers : null;
  if (xo && xo.rms_before_mgal !== undefined) summary.push(`crossover RMS ${fmt(xo.rms_before_mgal, 3)} → ${fmt(xo.rms_after_mgal, 3)} mGal (${xo.status})`);
  const limits = el("span", { class: "note", id: "grid-limits" });
  sec.replaceChildren(el("div", { class: "card" }, el("h3", {}, `Anomaly grid (${g.crs || "projected CRS"})`),
    relative ? el("p", { class: "warnline", id: "grid-relative" }, "No absolute base tie was made: the grid's level is relative (it may be off by 100+ mGal); differences are reliable. Set the base gravity in Survey settings.") : null,
    el("div", { class: "controls" }, el("label", {}, "anomaly", productIn), heightLabel, productNote),
    el("div", { class: "controls" }, el("label", {}, "show", varIn), el("label", {}, "style", styleIn),
      el("label", {}, "δg from", zminIn, "to", zmaxIn, "mGal"), limits),
    el("div", { class: "controls" }, el("label", {}, shadeIn, "hillshade"), el("label", {}, linesIn, "survey lines"),
      el("label", {}, labelsIn, "line labels"), el("label", {}, xoIn, "crossovers"),
      el("span", { class: "note" }, "click a line for its profile")),
    el("p", { class: "note", id: "grid-summary" }, summary.slice(0, 8).join(" · ")), plot));

  const shade = () => {
    const dx = g.easting_km.length > 1 ? g.easting_km[1] - g.easting_km[0] : 1;
    const dy = g.northing_km.length > 1 ? g.northing_km[1] - g.northing_km[0] : 1;
    return (g._shade = g._shade || hillshade(g.dg, dx, dy));
  };
  const kind = Object.fromEntries(g.lines.map((l) => [l.line, l.kind]));
  const crossings = g.crossovers.filter((c) => !(kind[c.line_a] === "repeat" && kind[c.line_b] === "repeat"));
  const symbol = () => (g.product === "bouguer" ? "δg_B" : "δg");
  const heightText = () => {
    if (g.height !== "datum" || !g.datum) return "at flight height";
    const hm = g.datum.height_m || {};
    const at = g.datum.datum === "constant" ? `${fmt(hm.mean, 0)} m` : `${fmt(hm.min, 0)}–${fmt(hm.max, 0)} m`;
    return `at the ${g.datum.datum} datum (${at})`;
  };

  const fieldTrace = (isStd, axes, colorbarX) => {
    const z = isStd ? g.dg_std : g.dg;
    let zmin, zmax, colorscale;
    if (isStd) {
      zmin = 0; zmax = symmetricLimit(z, 0.98); colorscale = "Viridis";
    } else {
      // a relative level (no base tie: the whole map may sit 100+ mGal off 0) is centred on its
      // median, else the map is one colour; an absolute one on 0
      const centre = relative ? (quantile(z.flat(), 0.5) ?? 0) : 0;
      const L = symmetricLimit(z.map((row) => row.map((v) => (v === null ? null : v - centre))), 0.98);
      const a = zminIn.value === "" ? centre - L : +zminIn.value, b = zmaxIn.value === "" ? centre + L : +zmaxIn.value;
      // a typed range that is no range (from ≥ to, not a number) is said, not silently replaced
      const bad = zminIn.validity.badInput || zmaxIn.validity.badInput || !(a < b);
      [zmin, zmax] = bad ? [centre - L, centre + L] : [a, b];
      for (const i of [zminIn, zmaxIn]) i.setAttribute("aria-invalid", bad ? "true" : "false");
      colorscale = divergingScale(zmin, zmax, centre);
      plot.dataset.zmin = zmin; plot.dataset.zmax = zmax; plot.dataset.centre = centre;
      limits.classList.toggle("error", bad);
      const white = centre >= zmin && centre <= zmax
        ? `white at ${fmt(centre, 3)}${relative ? " (the median: a relative level)" : ""}`
        : `${fmt(centre, 3)} (white) lies outside: one-sided colours`;
      limits.textContent = (bad ? `“from” must be a number below “to” — ignored; ` : "") +
        `colour scale ${fmt(zmin, 3)} … ${fmt(zmax, 3)} mGal, ${white}` +
        (bad || (zminIn.value === "" && zmaxIn.value === "") ? ` (±98th percentile of |δg${relative ? " − median" : ""}|)` : "");
    }
    return {
      x: g.easting_km, y: g.northing_km, z, type: styleIn.value, name: isStd ? "σ" : symbol(), colorscale, zmin, zmax, zauto: false,
      colorbar: { title: { text: isStd ? "σ (mGal)" : `${symbol()} (mGal)` }, ...(colorbarX !== undefined ? { x: colorbarX, len: 0.9 } : {}) },
      hovertemplate: `E %{x:.2f} km, N %{y:.2f} km<br>${isStd ? "σ" : symbol()} %{z:.2f} mGal<extra></extra>`,
      ...(styleIn.value === "contour" ? { contours: { coloring: "fill", showlines: true, start: zmin, end: zmax, size: (zmax - zmin) / 20 }, line: { width: 0.5, color: "rgba(0,0,0,0.3)" } } : {}),
      ...axes,
    };
  };

  // ``notes`` collects the layout's annotations (the labels of lines starting at one point)
  const overlays = (isStd, axes, first, notes) => {
    const t = [];
    if (shadeIn.checked && !isStd) {
      t.push({ x: g.easting_km, y: g.northing_km, z: shade(), type: "heatmap", colorscale: [[0, "rgb(0,0,0)"], [1, "rgb(255,255,255)"]],
        zmin: 0, zmax: 1, opacity: 0.35, showscale: false, hoverinfo: "skip", name: "hillshade", ...axes });
    }
    if (linesIn.checked) {
      g.lines.forEach((l, i) => t.push({ x: l.easting_km, y: l.northing_km, type: "scatter", mode: "lines",
        line: { color: isStd ? "rgba(255,255,255,0.75)" : (l.kind === "tie" ? "rgba(60,60,60,0.8)" : "rgba(0,0,0,0.55)"), width: 1.5, dash: l.kind === "tie" ? "dash" : "solid" },
        name: "lines", legendgroup: "lines", showlegend: first && i === 0, customdata: l.easting_km.map(() => l.line),
        hovertemplate: `line ${esc(l.line)} (${esc(l.kind)}) — click for its profile<extra></extra>`, ...axes }));
    }
    if (labelsIn.checked) {
      const labels = lineLabels(g.lines, axes);
      t.push(labels.trace);
      notes.push(...labels.annotations);
    }
    if (xoIn.checked && crossings.length) {
      t.push({ x: crossings.map((c) => c.easting_km), y: crossings.map((c) => c.northing_km), type: "scatter", mode: "markers",
        name: "crossovers", legendgroup: "xo", showlegend: first, marker: { symbol: "x-thin", size: 7, color: "rgba(0,0,0,0.7)", line: { width: 1.5, color: "rgba(0,0,0,0.7)" } },
        text: crossings.map((c) => `${esc(c.line_a)} × ${esc(c.line_b)}: before ${fmt(c.diff_before_mgal, 2)}, after ${fmt(c.diff_after_mgal, 2)} mGal`),
        hovertemplate: "%{text}<extra></extra>", ...axes });
    }
    return t;
  };

  const draw = async () => {
    const v = varIn.value;
    const what = g.product === "bouguer" ? "Bouguer anomaly δg_B" : "free-air anomaly δg";
    const title = `${s.name}: ` + (v === "dg_std" ? `posterior σ of ${symbol()} ${heightText()}`
      : `${what} ${heightText()}${relative ? " — relative level (no absolute base tie)" : ""}` + (v === "both" ? " and its σ" : ""));
    let traces, layout;
    const notes = [];
    if (v === "both") {
      const a1 = {}, a2 = { xaxis: "x2", yaxis: "y2" };
      traces = [fieldTrace(false, a1, 0.41), ...overlays(false, a1, true, notes), fieldTrace(true, a2, 0.99), ...overlays(true, a2, false, notes)];
      layout = mapLayout(title, {
        xaxis: { title: { text: "Easting (km)" }, domain: [0, 0.39], zeroline: false },
        yaxis: { title: { text: "Northing (km)" }, scaleanchor: "x", scaleratio: 1, zeroline: false },
        xaxis2: { title: { text: "Easting (km)" }, domain: [0.55, 0.94], matches: "x", zeroline: false },
        yaxis2: { anchor: "x2", scaleanchor: "x2", scaleratio: 1, matches: "y", zeroline: false, showticklabels: false },
      });
      plot.classList.add("wide");
    } else {
      const isStd = v === "dg_std";
      traces = [fieldTrace(isStd, {}), ...overlays(isStd, {}, true, notes)];
      layout = mapLayout(title);
      plot.classList.remove("wide");
    }
    layout.annotations = notes;
    await Plotly.react(plot, traces, layout, plotConfig(`${s.name}-grid`));
    plot.dataset.variable = v;
    plot.dataset.product = g.product;
    plot.dataset.height = g.height;
    plot.dataset.hillshade = shadeIn.checked ? "1" : "0";
    plot.dataset.relative = relative ? "1" : "0";
    plot.dataset.title = title;
  };
  for (const c of [varIn, styleIn, shadeIn, linesIn, labelsIn, xoIn, zminIn, zmaxIn]) c.addEventListener("change", draw);
  // another product or height: its grid from the server (same nodes, lines and crossovers)
  const switchGrid = async () => {
    const want = { product: productIn.value, height: heightIn.value };
    if (!(g.available && g.available[want.product] && g.available[want.product][want.height])) {
      want.height = want.height === "datum" ? "flight" : "datum";   // the other height of this product
    }
    productIn.disabled = heightIn.disabled = true;
    try {
      g = await endpoints.grid(s.id, want);
    } catch (e) {
      showError(sec, e);
    } finally {
      productIn.disabled = heightIn.disabled = false;
    }
    syncChoices();
    varIn.querySelector("option[value=dg_std]").disabled = varIn.querySelector("option[value=both]").disabled = !g.dg_std;
    if (!g.dg_std && varIn.value !== "dg") varIn.value = "dg";
    await draw();
  };
  productIn.addEventListener("change", switchGrid);
  heightIn.addEventListener("change", switchGrid);
  syncChoices();
  await draw();
  plot.on("plotly_click", (ev) => {
    const p = ev && ev.points && ev.points.find((q) => q.customdata !== undefined && q.data.name !== "crossovers");
    if (p) ctx.openProfile(p.customdata);
  });
  onLabelClick(plot, (line) => ctx.openProfile(line));
  plot.after(pngButton(plot, `${s.name}-grid`));
}
