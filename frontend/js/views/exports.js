// Exports of the stored results: each grid product (free-air; Bouguer with a DEM; free-air at flight
// height beside the datum one) as GeoTIFF, netCDF, Surfer and CSV, line data with every product column
// (Parquet, Geosoft XYZ), crossovers and the report.
import { endpoints } from "../api.js";
import { el } from "../plots.js";

const GRID_FORMATS = [
  ["geotiff", "GeoTIFF (.tif: bands dg, dg_std in mGal, with CRS)"],
  ["netcdf", "CF-netCDF (.nc: dg, dg_std on x/y in metres, CRS)"],
  ["surfer", "Surfer ASCII (.grd, x/y in metres)"],
  ["csv", "CSV (km)"],
];
const OTHER_FORMATS = [
  ["parquet", "Line data (lines.parquet: every estimate and product column)"],
  ["xyz", "Line data as Geosoft XYZ (X/Y in metres, product channels included)"],
  ["crossovers", "Crossovers (CSV)"],
  ["report", "Report (JSON)"],
];

// Which grids the result has (report.json products.grids; older results: from the products sections).
export function gridProducts(report) {
  const p = (report && report.products) || {};
  const datum = p.datum && ["constant", "draped"].includes(p.datum.datum) ? p.datum : null;
  const grids = p.grids || {};
  return {
    datum,
    freeAir: "free_air" in grids ? !!grids.free_air : true,
    bouguer: "bouguer" in grids ? !!grids.bouguer : !!(p.terrain && p.terrain.dem),
    flight: "free_air_flight_height" in grids ? !!grids.free_air_flight_height : false,
  };
}

function links(s, prefix, params) {
  return el("div", { class: "buttons" }, GRID_FORMATS.map(([f, label]) => {
    const q = new URLSearchParams({ format: f, ...params });
    return el("a", { href: `/api/surveys/${s.id}/export?${q}`, download: "", id: `export-${prefix}${f}` }, label);
  }));
}

export async function render(sec, ctx) {
  const s = ctx.survey;
  if (!s.current_result_id) {
    sec.replaceChildren(el("div", { class: "empty" }, "No results yet: run a processing job first."));
    return;
  }
  const rep = await endpoints.report(s.id).catch(() => null);
  const g = gridProducts(rep && rep.report);
  const at = g.datum ? `at the ${g.datum.datum} datum` : "at flight height";
  const noBouguer = s.has_dem
    ? "the current result was computed without the survey's DEM: process the survey again"
    : "the survey has no DEM (dem.tif): add one under “Terrain model (DEM)” on the left and process again";
  // a result without a grid (a test line: its lines span less than two cells) offers no grid files
  const noGrid = ((rep && rep.report && rep.report.warnings) || []).find((w) => String(w).includes("grid files not written"));
  sec.replaceChildren(el("div", { class: "card" }, el("h3", {}, `Exports of result ${s.current_result_id} (job ${s.result_job_id ?? "?"})`),
    el("h4", {}, `Free-air anomaly grid δg ${at}`),
    g.freeAir ? links(s, "", {}) : el("p", { class: "note", id: "export-grid-missing" },
      `Not available: this result has no grid${noGrid ? ` — ${noGrid}` : ""}. The line data below hold every estimate.`),
    g.flight ? el("h4", {}, "Free-air anomaly grid at flight height (before continuation)") : null,
    g.flight ? links(s, "flight-", { height: "flight" }) : null,
    g.freeAir ? el("h4", {}, `Bouguer anomaly grid δg_B ${at}`) : null,
    !g.freeAir ? null : g.bouguer ? links(s, "bouguer-", { product: "bouguer" })
      : el("p", { class: "note", id: "export-bouguer-missing" }, `Not available: ${noBouguer}.`),
    el("h4", {}, "Line data and reports"),
    el("div", { class: "buttons" }, OTHER_FORMATS.map(([f, label]) =>
      el("a", { href: `/api/surveys/${s.id}/export?format=${f}`, download: "", id: `export-${f}` }, label))),
    el("p", { class: "note" }, "Grid and XYZ coordinates are in the unit of the survey's projected CRS (metres for UTM), so GIS software puts the map where it is; the grid CSV and lines.parquet keep the pipeline's km columns. Line data carry every product column the result has: atmospheric correction, δg at flight height and at the datum, terrain effect, Bouguer anomaly."),
    el("p", { class: "note" }, "Every plot has a “Save PNG” button (and the camera icon in its toolbar).")));
}
