// Survey settings: the survey.toml fields (name, CRS, normal gravity, gravimeter) edited in place
// (PATCH /api/surveys/{id}), and deleting the survey (DELETE, after a confirmation).
import { endpoints } from "../api.js";
import { el, showError } from "../plots.js";

const FIELDS = [
  ["survey", "name", "Name", "text", "the survey's name"],
  ["survey", "crs", "CRS", "text", "projected CRS, e.g. EPSG:32657 (empty: the UTM zone of the data)"],
  ["survey", "normal_gravity", "Normal gravity", "select", "WGS84 (Somigliana) or Helmert 1901"],
  ["gravimeter", "model", "Gravimeter model", "text", "e.g. GT-1A"],
  ["gravimeter", "tau_s", "Lag τ (s)", "number", "first-order lag time constant; 0 if the data are already de-lagged"],
  ["gravimeter", "scale", "Scale k", "number", "scale of the gravimeter model"],
  ["gravimeter", "rate_hz", "Sampling rate (Hz)", "number", "declared gravimeter rate, a check (empty: inferred from the time stamps)"],
  ["gravimeter", "base_gravity_mgal", "Base gravity (mGal)", "number", "absolute gravity at the parking place (empty: no absolute base tie, the level of δg is relative)"],
];
const OPTIONAL = new Set(["crs", "rate_hz", "base_gravity_mgal"]);

export async function render(sec, ctx) {
  const s = ctx.survey;
  const cur = s.settings || { survey: { name: s.name }, gravimeter: {} };
  const form = el("form", { id: "settings-form", class: "params" });
  for (const [section, key, label, type, help] of FIELDS) {
    const v = (cur[section] || {})[key];
    const name = `${section}.${key}`;
    const input = type === "select"
      ? el("select", { name }, ["WGS84", "GRS80", "Helmert1901"].map((o) => el("option", { value: o, selected: o === v }, o)))
      : el("input", { name, type, step: type === "number" ? "any" : undefined, value: v ?? "",
        placeholder: OPTIONAL.has(key) ? (key === "crs" ? "auto (UTM)" : "none") : "" });
    input.dataset.initial = JSON.stringify(v ?? null);
    input.disabled = !s.has_input && name !== "survey.name";
    form.append(el("label", {}, el("span", { class: "name" }, label), " ", input, el("span", { class: "desc" }, `${name} — ${help}`)));
  }
  const save = el("button", { type: "submit", class: "primary", id: "settings-save" }, "Save settings");
  const status = el("div", { class: "note", id: "settings-status" },
    s.has_input ? "" : "This survey has no data yet: only its name can change until a flight is uploaded.");
  const del = el("button", { type: "button", id: "survey-delete", class: "danger" }, "Delete this survey…");
  sec.replaceChildren(
    el("div", { class: "card" }, el("h3", {}, "Survey settings (survey.toml)"),
      el("p", { class: "note" }, "Saved as a new version of the survey's input; the current result stays until the survey is processed again."),
      form, el("div", { class: "controls" }, save), status),
    el("div", { class: "card" }, el("h3", {}, "Delete"), el("p", { class: "note" }, "Removes the survey with its flights, jobs, results and files. Not possible while a job runs."), del));
  form.append(el("div", {}));  // grid filler
  form.addEventListener("submit", async (ev) => { ev.preventDefault(); });
  save.addEventListener("click", async (ev) => {
    ev.preventDefault();
    showError(sec.firstChild, null);
    for (const i of form.querySelectorAll(".invalid")) i.classList.remove("invalid");
    const body = {};
    for (const input of form.querySelectorAll("input, select")) {
      if (input.disabled) continue;
      const [section, key] = input.name.split(".");
      let v = input.value.trim();
      if (input.type === "number") v = v === "" ? null : Number(v);
      else if (v === "" && OPTIONAL.has(key)) v = null;
      if (JSON.stringify(v) === input.dataset.initial) continue;
      (body[section] = body[section] || {})[key] = v;
    }
    if (!Object.keys(body).length) { status.textContent = "Nothing changed."; return; }
    save.disabled = true;
    try {
      const out = await endpoints.patchSurvey(s.id, body);
      await ctx.refreshSurvey();
      ctx.resultsChanged();
      status.textContent = `Saved${out.result_outdated ? ": run processing again to apply the new settings" : ""}.`;
      status.dataset.saved = String(Date.now());
      render(sec, ctx).then(() => { sec.querySelector("#settings-status").textContent = status.textContent; sec.querySelector("#settings-status").dataset.saved = status.dataset.saved; });
    } catch (e) {
      showError(sec.firstChild, e);
      const d = e.body && e.body.detail;
      if (Array.isArray(d)) {
        for (const x of d) {
          const loc = (x.loc || []).filter((p) => p !== "body").join(".");
          const input = form.querySelector(`[name="${CSS.escape(loc)}"]`);
          if (input) input.classList.add("invalid");
        }
      }
    } finally { save.disabled = false; }
  });
  del.addEventListener("click", async () => {
    if (!window.confirm(`Delete the survey "${s.name}" with all its flights, jobs, results and files?`)) return;
    try {
      await endpoints.deleteSurvey(s.id);
      await ctx.surveyDeleted(s.id);
    } catch (e) { showError(sec.lastChild, e); }
  });
}
