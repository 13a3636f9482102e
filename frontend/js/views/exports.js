// Exports of the stored results (GeoTIFF, netCDF, Surfer, CSV, Parquet, Geosoft XYZ) and the report.
import { el } from "../plots.js";

const FORMATS = [
  ["geotiff", "GeoTIFF grid (.tif: bands dg, dg_std in mGal, with CRS)"],
  ["netcdf", "CF-netCDF grid (.nc: dg, dg_std on x/y in metres, CRS)"],
  ["surfer", "Surfer ASCII grid (.grd, x/y in metres)"],
  ["csv", "Grid as CSV (km)"],
  ["parquet", "Line data (lines.parquet)"],
  ["xyz", "Line data as Geosoft XYZ (X/Y in metres)"],
  ["crossovers", "Crossovers (CSV)"],
  ["report", "Report (JSON)"],
];

export async function render(sec, ctx) {
  const s = ctx.survey;
  if (!s.current_result_id) {
    sec.replaceChildren(el("div", { class: "empty" }, "No results yet: run a processing job first."));
    return;
  }
  sec.replaceChildren(el("div", { class: "card" }, el("h3", {}, `Exports of result ${s.current_result_id} (job ${s.last_job ? s.last_job.id : "?"})`),
    el("div", { class: "buttons" }, FORMATS.map(([f, label]) =>
      el("a", { href: `/api/surveys/${s.id}/export?format=${f}`, download: "", id: `export-${f}` }, label))),
    el("p", { class: "note" }, "Grid and XYZ coordinates are in the unit of the survey's projected CRS (metres for UTM), so GIS software puts the map where it is; the grid CSV and lines.parquet keep the pipeline's km columns."),
    el("p", { class: "note" }, "Every plot has a “Save PNG” button (and the camera icon in its toolbar).")));
}
