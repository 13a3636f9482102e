// Aerograv single-page app: survey list, uploads, tabs with the views.
import { endpoints, getToken, setToken, upload } from "./api.js";
import { el, showError } from "./plots.js";
import * as qc from "./views/qc.js";
import * as processView from "./views/process.js";
import * as recognition from "./views/recognition.js";
import * as profile from "./views/profile.js";
import * as grid from "./views/grid.js";
import * as exportsView from "./views/exports.js";
import * as settings from "./views/settings.js";
import * as report from "./views/report.js";

const VIEWS = { qc, settings, process: processView, report, recognition, profile, grid, export: exportsView };
const state = { surveys: [], surveyId: null, tab: "qc", rendered: {}, profileLine: null };

const ctx = {
  get survey() { return state.surveys.find((s) => s.id === state.surveyId) || null; },
  async refreshSurvey() {
    await loadSurveys();
    return ctx.survey;
  },
  // after a job succeeded: views that show results must reload
  resultsChanged() { state.rendered = { process: state.rendered.process }; },
  // a click on a line in any map: the line's profile
  openProfile(line) {
    if (!ctx.survey || !ctx.survey.current_result_id) return;
    state.profileLine = String(line);
    showTab("profile");
  },
  consumeLine() { const l = state.profileLine; state.profileLine = null; return l; },
  // a job started from a view (Processing, the recognition map's "Apply h, ρ"): the survey list says
  // so at once (and polls every 2 s while it runs); the Processing tab shows and watches it when opened
  async jobStarted() {
    if (state.tab !== "process") delete state.rendered.process;
    await loadSurveys();
    pollSurveys();
  },
  async surveyDeleted(id) {
    if (state.surveyId === id) state.surveyId = null;
    state.rendered = {};
    await loadSurveys();
    if (state.surveys.length) selectSurvey(state.surveys[0].id);
    else { history.replaceState(null, "", "#"); document.getElementById("flight-upload").hidden = true; showTab(state.tab); }
  },
};
window.aerograv = { state, ctx };

const RESULT_TABS = ["report", "recognition", "profile", "grid", "export"];

// a result older than the survey's data or settings: said above every result view but the report
// (which says it itself), not only in the report
function syncOutdated() {
  const s = ctx.survey;
  document.getElementById("outdated-banner").hidden =
    !(s && s.result_outdated && s.current_result_id && RESULT_TABS.includes(state.tab) && state.tab !== "report");
}

async function loadSurveys() {
  try {
    const before = ctx.survey ? ctx.survey.current_result_id : undefined;
    state.surveys = await endpoints.surveys();
    renderSurveyList();
    syncOutdated();
    // a job finished while the analyst was elsewhere (another tab, or the page reloaded mid-job so no
    // view watches it): the result views reload, the one on screen at once
    const s = ctx.survey;
    if (s && before !== undefined && s.current_result_id !== before) {
      ctx.resultsChanged();
      if (RESULT_TABS.includes(state.tab)) showTab(state.tab, false);
    }
  } catch (e) { showError(document.querySelector(".sidebar section"), e); }
}

// the survey list (status badges, new results) every 10 s, every 2 s while the survey's job runs
let pollTimer = null;
function pollSurveys() {
  clearTimeout(pollTimer);   // one chain of polls, also when a started job re-arms it
  const s = ctx.survey;
  const busy = s && s.last_job && ["queued", "running"].includes(s.last_job.status);
  pollTimer = setTimeout(async () => { await loadSurveys(); pollSurveys(); }, busy ? 2000 : 10000);
}

// a survey's name, with its id when another survey has the same name (the same zip imported twice)
function surveyName(s) {
  return state.surveys.some((o) => o.id !== s.id && o.name === s.name) ? `${s.name} (#${s.id})` : s.name;
}

// A survey's badge says what the analyst has: a job at work, else the current result, else the newest
// job's end. A re-run cancelled or failed leaves the previous result current (and shown in every
// view): the badge stays "succeeded" for that result, and a note under it says how the last run ended.
function surveyBadge(s) {
  const last = s.last_job;
  if (last && ["queued", "running"].includes(last.status)) {
    return { status: last.status, title: `job ${last.id} ${last.status}` };
  }
  if (s.current_result_id) {
    const job = s.result_job_id ?? "?";
    const other = last && last.id !== s.result_job_id && last.status !== "succeeded" ? last : null;
    return { status: "succeeded", title: `current result: the result of job ${job}` +
        (other ? `; the last run (job ${other.id}) was ${other.status} and changed nothing` : ""),
      note: other ? `last run ${other.status}` : null, noteClass: other ? other.status : null };
  }
  if (last) return { status: last.status, title: `job ${last.id} ${last.status}; no result yet` };
  return { status: s.has_input ? "imported" : "empty", title: s.has_input ? "not processed yet" : "no data yet" };
}

function renderSurveyList() {
  const ul = document.getElementById("survey-list");
  // the list is redrawn every 10 s (2 s while a job runs): a survey the keyboard was on keeps the focus
  const focused = ul.contains(document.activeElement) ? document.activeElement.dataset.surveyId : null;
  ul.replaceChildren(...state.surveys.map((s) => {
    const b = surveyBadge(s);
    const li = el("li", { class: s.id === state.surveyId ? "active" : "", "data-survey-id": s.id },
      el("span", {}, surveyName(s)), el("span", { class: `badge ${b.status}`, title: b.title }, b.status),
      b.note ? el("small", { class: `last-run ${b.noteClass}`, title: b.title }, b.note) : null);
    // a survey is chosen from the keyboard too (Tab to it, Enter or Space): the list was mouse-only
    li.tabIndex = 0;
    li.setAttribute("role", "button");
    if (s.id === state.surveyId) li.setAttribute("aria-current", "true");
    li.addEventListener("click", () => selectSurvey(s.id));
    li.addEventListener("keydown", (ev) => {
      if (ev.key === "Enter" || ev.key === " ") { ev.preventDefault(); selectSurvey(s.id); }
    });
    return li;
  }));
  if (focused !== null && focused !== undefined) {
    const li = ul.querySelector(`li[data-survey-id="${CSS.escape(focused)}"]`);
    if (li) li.focus();
  }
  const s = ctx.survey;
  document.getElementById("survey-title").textContent = s ? `${surveyName(s)} — ${s.flights.length} flight(s), ${s.n_lines} line(s)` : "";
  renderDemStatus(s);
}

// the DEM section: shown for a survey with data; says whether it has a terrain model
function renderDemStatus(s) {
  const box = document.getElementById("dem-upload");
  box.hidden = !(s && s.has_input);
  if (!s) return;
  box.dataset.hasDem = s.has_dem ? "1" : "0";
  document.getElementById("dem-status").textContent = s.has_dem
    ? "This survey has a terrain model (dem.tif): processing adds the terrain correction and the Bouguer anomaly. Upload another to replace it."
    : "No terrain model: upload a GeoTIFF DEM (its CRS, heights in metres, covering the lines) for the terrain correction and the Bouguer anomaly.";
  document.getElementById("dem-remove").hidden = !s.has_dem;
}

function selectSurvey(id, push = true) {
  state.surveyId = id;
  state.rendered = {};
  renderSurveyList();
  document.getElementById("flight-upload").hidden = !id;
  showTab(state.tab, push);
}

// every survey or tab the analyst opens is a history entry: Back and Forward go through them
function syncUrl(push) {
  const want = `#survey=${state.surveyId}&tab=${state.tab}`;
  if (location.hash === want) return;
  if (push && location.hash) history.pushState(null, "", want);
  else history.replaceState(null, "", want);
}

// the survey and tab in the URL (Back, Forward, an edited address): shown without a new entry
function applyHash() {
  const m = /survey=(\d+)(?:&tab=(\w+))?/.exec(location.hash);
  if (!m || !state.surveys.some((s) => s.id === +m[1])) return false;
  const tab = m[2] && VIEWS[m[2]] ? m[2] : state.tab;
  if (+m[1] !== state.surveyId) { state.tab = tab; selectSurvey(+m[1], false); }
  else if (tab !== state.tab) showTab(tab, false);
  return true;
}

function showTab(tab, push = true) {
  state.tab = tab;
  for (const b of document.querySelectorAll("#tabs button")) b.classList.toggle("active", b.dataset.tab === tab);
  const has = !!ctx.survey;
  document.getElementById("no-survey").hidden = has;
  for (const name of Object.keys(VIEWS)) {
    const sec = document.getElementById(`view-${name}`);
    sec.hidden = !has || name !== tab;
  }
  syncOutdated();
  if (!has) return;
  if (state.surveyId) syncUrl(push);
  const sec = document.getElementById(`view-${tab}`);
  const key = `${state.surveyId}`;
  if (state.rendered[tab] !== key) {
    state.rendered[tab] = key;
    VIEWS[tab].render(sec, ctx).catch((e) => showError(sec, e));
  } else {
    // plots drawn while the window had another size (or the view was hidden): fit them to it now
    for (const p of sec.querySelectorAll(".js-plotly-plot")) Plotly.Plots.resize(p).catch(() => {});
    if (VIEWS[tab].shown) VIEWS[tab].shown(sec, ctx);
  }
}

// An accepted upload's warnings (the survey reader's: e.g. a flight no line uses left out because its
// files cannot be read), shown under the upload's error line until the next upload there.
function showUploadWarnings(below, warnings, surveyName = "") {
  const id = `${below.id}-warnings`;
  document.getElementById(id)?.remove();
  if (!Array.isArray(warnings) || !warnings.length) return;
  below.after(el("div", { id, class: "warnline" },
    `${surveyName ? `Survey “${surveyName}”: stored` : "Stored"}, with ${warnings.length === 1 ? "a warning" : `${warnings.length} warnings`} from the survey reader:`,
    el("ul", {}, warnings.map((w) => el("li", {}, String(w))))));
}

function setupUploads() {
  const btn = document.getElementById("import-btn");
  const input = document.getElementById("import-file");
  const bar = document.getElementById("import-progress");
  const err = document.getElementById("import-error");
  btn.addEventListener("click", async () => {
    err.hidden = true;
    showUploadWarnings(err, []);
    if (!input.files.length) { err.hidden = false; err.textContent = "Choose a .zip file first."; return; }
    const fd = new FormData();
    fd.append("file", input.files[0]);
    bar.hidden = false; bar.value = 0; btn.disabled = true;
    try {
      const s = await upload("/api/surveys/import", fd, (f) => { bar.value = f; });
      bar.value = 1;
      showUploadWarnings(err, s && s.warnings, s && s.name);
      await loadSurveys();
      selectSurvey(s.id);
      input.value = "";
    } catch (e) {
      err.hidden = false; err.textContent = `Import rejected — ${e.message}`;
    } finally { btn.disabled = false; setTimeout(() => { bar.hidden = true; }, 800); }
  });

  const form = document.getElementById("flight-form");
  const fbar = document.getElementById("flight-progress");
  const ferr = document.getElementById("flight-error");
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    ferr.hidden = true;
    showUploadWarnings(ferr, []);
    const fd = new FormData(form);
    if (!fd.get("flight")) fd.delete("flight");
    if (fd.get("lines") && fd.get("lines").size === 0) fd.delete("lines");
    fbar.hidden = false; fbar.value = 0;
    try {
      const up = await upload(`/api/surveys/${state.surveyId}/flights`, fd, (f) => { fbar.value = f; });
      showUploadWarnings(ferr, up && up.warnings, up && up.name);
      form.reset();
      await loadSurveys();
      state.rendered = {};
      showTab(state.tab);
    } catch (e) {
      ferr.hidden = false; ferr.textContent = `Flight rejected — ${e.message}`;
    } finally { setTimeout(() => { fbar.hidden = true; }, 800); }
  });

  const dbtn = document.getElementById("dem-btn");
  const dinput = document.getElementById("dem-file");
  const dbar = document.getElementById("dem-progress");
  const derr = document.getElementById("dem-error");
  const demChanged = async () => {
    await loadSurveys();
    state.rendered = {};
    showTab(state.tab);
  };
  dbtn.addEventListener("click", async () => {
    derr.hidden = true;
    if (!dinput.files.length) { derr.hidden = false; derr.textContent = "Choose a GeoTIFF file first."; return; }
    const fd = new FormData();
    fd.append("dem", dinput.files[0]);
    dbar.hidden = false; dbar.value = 0; dbtn.disabled = true;
    try {
      await upload(`/api/surveys/${state.surveyId}/dem`, fd, (f) => { dbar.value = f; }, "PUT");
      dinput.value = "";
      await demChanged();
    } catch (e) {
      derr.hidden = false; derr.textContent = `DEM rejected — ${e.message}`;
    } finally { dbtn.disabled = false; setTimeout(() => { dbar.hidden = true; }, 800); }
  });
  document.getElementById("dem-remove").addEventListener("click", async () => {
    derr.hidden = true;
    if (!confirm("Remove this survey's terrain model? The next processing has no Bouguer anomaly.")) return;
    try {
      await endpoints.deleteDem(state.surveyId);
      await demChanged();
    } catch (e) { derr.hidden = false; derr.textContent = `${e.message}`; }
  });

  document.getElementById("new-survey").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const name = ev.target.name.value.trim();
    try {
      const s = await endpoints.createSurvey(name);
      ev.target.reset();
      await loadSurveys();
      selectSurvey(s.id);
    } catch (e) { showError(ev.target.parentElement, e); }
  });
}

async function main() {
  const tok = document.getElementById("token");
  tok.value = getToken();
  tok.addEventListener("change", () => setToken(tok.value.trim()));
  // a tab clicked while the survey list is still on its way is the one shown once it arrives (the
  // address's tab would otherwise win and the click be lost)
  let booting = true;
  let clickedWhileLoading = null;
  for (const b of document.querySelectorAll("#tabs button")) {
    b.addEventListener("click", () => {
      if (booting) clickedWhileLoading = b.dataset.tab;
      showTab(b.dataset.tab);
    });
  }
  setupUploads();
  await loadSurveys();
  booting = false;
  if (!applyHash() && state.surveys.length) selectSurvey(state.surveys[0].id, false);
  if (clickedWhileLoading && clickedWhileLoading !== state.tab && ctx.survey) showTab(clickedWhileLoading);
  window.addEventListener("popstate", applyHash);
  window.addEventListener("hashchange", applyHash);
  pollSurveys();
}

main();
