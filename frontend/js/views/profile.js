// Line profiles: z low-passed, adaptive δg ± 2σ, stationary smoother, FIR 100 s, state bands.
import { endpoints } from "../api.js";
import { el, esc, fmt, plotConfig, pngButton, stateColor } from "../plots.js";

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

export async function render(sec, ctx) {
  const s = ctx.survey;
  if (!s.current_result_id) {
    sec.replaceChildren(el("div", { class: "empty" }, "No results yet: run a processing job first."));
    return;
  }
  const lines = await endpoints.lines(s.id);
  const withData = lines.filter((l) => l.stats);
  const sel = el("select", { id: "profile-line" }, withData.map((l) => el("option", { value: l.line },
    `${l.line} (${l.kind}, flight ${l.flight}, ${fmt(l.qc.length_km, 1)} km, σ̄ ${fmt(l.stats.sigma_mean_mgal, 2)} mGal)`)));
  const lp = el("input", { type: "number", id: "profile-lp", min: 0, max: 600, step: 5, value: 30, style: "width:5rem" });
  const status = el("div", { class: "note", id: "profile-status" });
  const plot = el("div", { class: "plot", id: "profile-plot", style: "height:520px" });
  sec.replaceChildren(el("div", { class: "card" }, el("h3", {}, "Line profile"),
    el("div", { class: "controls" }, el("label", {}, "Line", sel), el("label", {}, "z low-pass FWHM (s)", lp)),
    status, plot));
  let pngAdded = false;

  const draw = async () => {
    const p = await endpoints.profile(s.id, sel.value, { max_points: 2500, z_lowpass_s: lp.value });
    const x = p.distance_km;
    const lo = p.dg.map((v, i) => (v === null || p.dg_std[i] === null ? null : v - 2 * p.dg_std[i]));
    const hi = p.dg.map((v, i) => (v === null || p.dg_std[i] === null ? null : v + 2 * p.dg_std[i]));
    const cd = p.time;
    const ht = (name) => `${name}: %{y:.2f} mGal<br>%{x:.2f} km, t=%{customdata:.1f} s<extra></extra>`;
    const traces = [
      { x, y: p.z_lowpassed, name: `z, low-passed (${p.z_lowpass_s} s)`, mode: "lines", line: { color: "#9e9e9e", width: 1 }, customdata: cd, hovertemplate: ht("z") },
      { x, y: lo, mode: "lines", line: { width: 0 }, showlegend: false, hoverinfo: "skip" },
      { x, y: hi, mode: "lines", line: { width: 0 }, fill: "tonexty", fillcolor: "rgba(31,111,235,0.18)", name: "adaptive ± 2σ", hoverinfo: "skip" },
      { x, y: p.dg, name: "adaptive δg (final, leveled)", mode: "lines", line: { color: "#1f6feb", width: 2 }, customdata: cd, hovertemplate: ht("δg") },
      { x, y: p.dg_stationary, name: "stationary smoother", mode: "lines", line: { color: "#e6550d", width: 1.5, dash: "dash" }, customdata: cd, hovertemplate: ht("stationary") },
      { x, y: p.dg_fir, name: "FIR 100 s", mode: "lines", line: { color: "#31a354", width: 1.5, dash: "dot" }, customdata: cd, hovertemplate: ht("FIR") },
    ];
    // y range from the filtered series (z can carry large transients at the line ends)
    const vals = [...lo, ...hi, ...p.dg_stationary, ...p.dg_fir].filter((v) => v !== null && Number.isFinite(v));
    const ymin = Math.min(...vals), ymax = Math.max(...vals), pad = 0.25 * Math.max(ymax - ymin, 1);
    const layout = {
      title: { text: `Line ${esc(p.line)} (${esc(p.kind)}, flight ${esc(p.flight)})`, font: { size: 15 } },
      margin: { l: 70, r: 20, t: 40, b: 55 },
      xaxis: { title: { text: "Distance along line (km)" } },
      yaxis: { title: { text: "Gravity anomaly δg (mGal)" }, range: vals.length ? [ymin - pad, ymax + pad] : undefined },
      legend: { orientation: "h", y: -0.16 },
      shapes: stateShapes(x, p.state),
      hovermode: "x unified",
    };
    await Plotly.react(plot, traces, layout, plotConfig(`${s.name}-line-${p.line}`));
    if (!pngAdded) { plot.after(pngButton(plot, `${s.name}-line-profile`)); pngAdded = true; }
    const sigma = p.dg_std.filter((v) => v !== null);
    status.textContent = `${p.n_total} epochs (${p.step === 1 ? "all" : `1 in ${p.step}`} shown) · shaded bands: states > 0 (rougher anomaly) · mean σ ${fmt(sigma.reduce((a, b) => a + b, 0) / Math.max(1, sigma.length), 3)} mGal`;
    plot.dataset.line = p.line;
  };
  sel.addEventListener("change", draw);
  lp.addEventListener("change", draw);
  if (withData.length) await draw(); else status.textContent = "No line has results.";
}
