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
  async surveyDeleted(id) {
    if (state.surveyId === id) state.surveyId = null;
    state.rendered = {};
    await loadSurveys();
    if (state.surveys.length) selectSurvey(state.surveys[0].id);
    else { history.replaceState(null, "", "#"); document.getElementById("flight-upload").hidden = true; showTab(state.tab); }
  },
};
window.aerograv = { state, ctx };

async function loadSurveys() {
  try {
    state.surveys = await endpoints.surveys();
    renderSurveyList();
  } catch (e) { showError(document.querySelector(".sidebar section"), e); }
}

function renderSurveyList() {
  const ul = document.getElementById("survey-list");
  ul.replaceChildren(...state.surveys.map((s) => {
    const st = s.last_job ? s.last_job.status : (s.has_input ? "imported" : "empty");
    const li = el("li", { class: s.id === state.surveyId ? "active" : "", "data-survey-id": s.id },
      el("span", {}, s.name), el("span", { class: `badge ${st}` }, st));
    li.addEventListener("click", () => selectSurvey(s.id));
    return li;
  }));
  const s = ctx.survey;
  document.getElementById("survey-title").textContent = s ? `${s.name} — ${s.flights.length} flight(s), ${s.n_lines} line(s)` : "";
}

function selectSurvey(id) {
  state.surveyId = id;
  state.rendered = {};
  location.hash = `#survey=${id}&tab=${state.tab}`;
  renderSurveyList();
  document.getElementById("flight-upload").hidden = !id;
  showTab(state.tab);
}

function showTab(tab) {
  state.tab = tab;
  for (const b of document.querySelectorAll("#tabs button")) b.classList.toggle("active", b.dataset.tab === tab);
  const has = !!ctx.survey;
  document.getElementById("no-survey").hidden = has;
  for (const name of Object.keys(VIEWS)) {
    const sec = document.getElementById(`view-${name}`);
    sec.hidden = !has || name !== tab;
  }
  if (!has) return;
  if (state.surveyId) history.replaceState(null, "", `#survey=${state.surveyId}&tab=${tab}`);
  const sec = document.getElementById(`view-${tab}`);
  const key = `${state.surveyId}`;
  if (state.rendered[tab] !== key) {
    state.rendered[tab] = key;
    VIEWS[tab].render(sec, ctx).catch((e) => showError(sec, e));
  } else if (VIEWS[tab].shown) {
    VIEWS[tab].shown(sec, ctx);
  }
}

function setupUploads() {
  const btn = document.getElementById("import-btn");
  const input = document.getElementById("import-file");
  const bar = document.getElementById("import-progress");
  const err = document.getElementById("import-error");
  btn.addEventListener("click", async () => {
    err.hidden = true;
    if (!input.files.length) { err.hidden = false; err.textContent = "Choose a .zip file first."; return; }
    const fd = new FormData();
    fd.append("file", input.files[0]);
    bar.hidden = false; bar.value = 0; btn.disabled = true;
    try {
      const s = await upload("/api/surveys/import", fd, (f) => { bar.value = f; });
      bar.value = 1;
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
    const fd = new FormData(form);
    if (!fd.get("flight")) fd.delete("flight");
    if (fd.get("lines") && fd.get("lines").size === 0) fd.delete("lines");
    fbar.hidden = false; fbar.value = 0;
    try {
      await upload(`/api/surveys/${state.surveyId}/flights`, fd, (f) => { fbar.value = f; });
      form.reset();
      await loadSurveys();
      state.rendered = {};
      showTab(state.tab);
    } catch (e) {
      ferr.hidden = false; ferr.textContent = `Flight rejected — ${e.message}`;
    } finally { setTimeout(() => { fbar.hidden = true; }, 800); }
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
  for (const b of document.querySelectorAll("#tabs button")) b.addEventListener("click", () => showTab(b.dataset.tab));
  setupUploads();
  await loadSurveys();
  const m = /survey=(\d+)(?:&tab=(\w+))?/.exec(location.hash);
  if (m && state.surveys.some((s) => s.id === +m[1])) {
    if (m[2] && VIEWS[m[2]]) state.tab = m[2];
    selectSurvey(+m[1]);
  } else if (state.surveys.length) {
    selectSurvey(state.surveys[0].id);
  }
  setInterval(loadSurveys, 10000);
}

main();
