// Processing: parameters form (defaults + explanations from ProcessingParams), job progress, live EM table.
import { endpoints } from "../api.js";
import { el, fmt, showError, titleFromChoice } from "../plots.js";

let poller = null;
let schemaCache = null;

function fieldInfo(prop) {
  let p = prop, nullable = false;
  if (prop.anyOf) {
    nullable = prop.anyOf.some((a) => a.type === "null");
    p = { ...prop, ...(prop.anyOf.find((a) => a.type !== "null") || {}) };
  }
  return { type: p.type, enum: p.enum || (p.const !== undefined ? [p.const] : null), nullable,
    min: p.minimum ?? p.exclusiveMinimum, max: p.maximum ?? p.exclusiveMaximum, title: prop.title, description: prop.description };
}

function paramField(name, prop, def) {
  const f = fieldInfo(prop);
  let input;
  if (f.enum) {
    input = el("select", { name }, f.enum.map((v) => el("option", { value: v, selected: v === def }, v)));
  } else if (f.type === "boolean") {
    input = el("input", { type: "checkbox", name, checked: !!def });
  } else if (f.type === "array") {
    // e.g. a frequency band: numbers separated by commas
    input = el("input", { type: "text", name, value: Array.isArray(def) ? def.join(", ") : "",
      placeholder: "comma-separated numbers" });
  } else {
    input = el("input", { type: "number", name, step: f.type === "integer" ? 1 : "any", min: f.min, max: f.max,
      value: def ?? "", placeholder: def === null ? "auto" : "" });
  }
  input.dataset.default = JSON.stringify(def);
  input.dataset.kind = f.enum ? "enum" : f.type;
  const range = f.min !== undefined || f.max !== undefined ? ` [${f.min ?? "−∞"} … ${f.max ?? "∞"}]` : "";
  return el("label", {}, el("span", { class: "name" }, name), " ", input,
    el("span", { class: "desc" }, (f.description || "") + (def === null ? " (auto when empty)" : ` (default ${def})`) + range));
}

// The parameters by pipeline stage (the server's groups: common ones shown, advanced ones folded);
// a parameter of the schema in no group (an older server, a new field) goes to "Other": none is left out.
export function buildForm(schema, defaults, groups = []) {
  const names = Object.keys(schema.properties);
  const placed = new Set(groups.flatMap((g) => [...g.common, ...g.advanced]));
  const loose = names.filter((n) => !placed.has(n));
  const all = [...groups, ...(loose.length ? [{ key: "unlisted", title: "Other parameters", common: [], advanced: loose }] : [])];
  const grid = (list) => el("div", { class: "params" }, list.filter((n) => schema.properties[n]).map((n) => paramField(n, schema.properties[n], defaults[n])));
  return el("div", { class: "param-groups" }, all.map((g) => {
    const common = g.common.filter((n) => schema.properties[n]), advanced = g.advanced.filter((n) => schema.properties[n]);
    if (!common.length && !advanced.length) return null;
    return el("fieldset", { class: "param-group", "data-group": g.key }, el("legend", {}, g.title),
      common.length ? grid(common) : null,
      advanced.length ? el("details", { class: "advanced" }, el("summary", {}, `Advanced (${advanced.length})`), grid(advanced)) : null);
  }));
}

function collectParams(form) {
  const out = {};
  for (const input of form.querySelectorAll(".params input, .params select")) {
    const def = JSON.parse(input.dataset.default);
    let v;
    if (input.type === "checkbox") v = input.checked;
    else if (input.dataset.kind === "enum") v = input.value;
    else if (input.dataset.kind === "array") v = input.value.split(",").map((t) => t.trim()).filter((t) => t).map(Number);
    else if (input.value === "") v = null;
    else v = input.dataset.kind === "integer" ? parseInt(input.value, 10) : parseFloat(input.value);
    if (JSON.stringify(v) !== JSON.stringify(def)) out[input.name] = v;
  }
  return out;
}

// States are numbered from 0 as on the recognition map: state k = (Q level k div N2, R level k mod N2).
function stateName(k, nr) { return `s${k} (Q${Math.floor(k / nr)}, R${k % nr})`; }

// A job can run EM more than once (one run per anomaly model order, "m=1 2x2" then "m=2 2x2"; a
// filter job shows the stored identification's, "stored"): each row says its run, and the last row
// of a run is that run's final iteration.
const runOf = (r) => r.model ?? "";
const lastOfRun = (rows, k) => k === rows.length - 1 || runOf(rows[k + 1]) !== runOf(rows[k]);

export function emTable(rows, selected) {
  if (!rows.length) return el("p", { class: "note", id: "em-empty" }, "EM iterations appear here while the identification runs.");
  const runs = rows.some((r) => r.model);
  const shape = rows[rows.length - 1];   // columns named by the newest run's levels; shorter rows leave cells empty
  const nq = Math.max(...rows.map((r) => r.Q.length)), nr = Math.max(...rows.map((r) => r.R.length));
  const nstates = Math.max(0, ...rows.map((r) => (r.transition ? r.transition.length : 0)));
  const head = [...(runs ? ["EM run"] : []), "Iteration", ...Array.from({ length: nq }, (_, i) => `Q${i} (mGal² per step)`),
    ...Array.from({ length: nr }, (_, j) => `R${j} ((cm/s)²)`), "Objective"];
  for (let i = 0; i < nstates; i++) head.push(`stay ${stateName(i, shape.R.length || nr)}`);
  const pad = (vals, n) => Array.from({ length: n }, (_, i) => el("td", {}, i < vals.length ? fmt(vals[i], 4) : ""));
  return el("table", { id: "em-table" }, el("thead", {}, el("tr", {}, head.map((h) => el("th", {}, h)))),
    el("tbody", {}, rows.map((r, k) => el("tr", { class: `em-row${k === selected ? " selected" : ""}${lastOfRun(rows, k) ? " final" : ""}`, "data-index": k,
      ...(runs ? { "data-run": runOf(r) } : {}) },
      runs ? el("td", { class: "l" }, runOf(r) || "—") : null,
      el("td", {}, r.iteration), pad(r.Q, nq), pad(r.R, nr),
      el("td", {}, fmt(r.objective, 6)),
      Array.from({ length: nstates }, (_, i) => el("td", {}, r.transition && r.transition[i] ? fmt(r.transition[i][i], 4) : "—"))))));
}

// One iteration in full: each state's (Q, R) levels and the whole transition matrix a_ij.
export function emDetail(rows, k, live) {
  const r = rows[k];
  if (!r) return el("div", { id: "em-detail" });
  const nr = r.R.length, n = r.Q.length * nr;
  const states = Array.from({ length: n }, (_, s) => ({ name: stateName(s, nr), Q: r.Q[Math.floor(s / nr)], R: r.R[s % nr] }));
  const a = r.transition && r.transition.length === n ? r.transition : null;
  let end = k;
  while (!lastOfRun(rows, end)) end += 1;
  const word = k === rows.length - 1 ? (live ? "Latest" : "Final") : k === end ? "Final" : "Selected";
  const caption = `${word} iteration ${r.iteration}` + (r.model ? ` of EM run ${r.model}` : "") +
    (k === end ? "" : ` (of ${rows[end].iteration})`) + " — click a row above to see another";
  return el("div", { id: "em-detail", "data-iteration": r.iteration, ...(r.model ? { "data-run": r.model } : {}) },
    el("h4", {}, caption),
    el("div", { class: "row" },
      el("table", { id: "em-states" }, el("thead", {}, el("tr", {}, ["State", "Q (mGal² per step)", "R ((cm/s)²)"].map((h, i) => el("th", { class: i ? "" : "l" }, h)))),
        el("tbody", {}, states.map((s) => el("tr", {}, el("td", { class: "l" }, s.name), el("td", {}, fmt(s.Q, 4)), el("td", {}, fmt(s.R, 4)))))),
      a ? el("table", { id: "em-transition" },
        el("thead", {}, el("tr", {}, el("th", { class: "l" }, "from ↓ / to →"), states.map((s) => el("th", {}, s.name)))),
        el("tbody", {}, a.map((row, i) => el("tr", {}, el("td", { class: "l" }, states[i].name),
          row.map((v, j) => el("td", { class: i === j ? "diag" : "" }, fmt(v, 4)))))))
        : el("p", { class: "note" }, "No transition matrix recorded for this iteration.")));
}

let emSelected = null;

// a row that acts on a click also acts from the keyboard: Tab to it, Enter or Space
function clickable(tr, act, label) {
  tr.tabIndex = 0;
  tr.title = `${label} (click, or Enter)`;
  tr.addEventListener("click", act);
  tr.addEventListener("keydown", (ev) => { if (ev.key === "Enter" || ev.key === " ") { ev.preventDefault(); act(); } });
}  // row index the analyst clicked (null: follow the newest)

function renderJob(box, job) {
  const pct = Math.round(100 * (job.progress || 0));
  const rows = job.em_iterations || [];
  const live = ["queued", "running"].includes(job.status);
  const sel = emSelected !== null && emSelected < rows.length ? emSelected : rows.length - 1;
  box.replaceChildren(...[
    el("div", { class: "row" },
      el("div", {}, el("strong", {}, `Job ${job.id}`), ` (${job.kind}, ${job.backend}) — `,
        el("span", { class: `badge ${job.status}`, id: "job-status" }, job.status),
        " stage ", el("span", { class: "stage", id: "job-stage" }, job.stage || "—"), ` — ${pct}%`)),
    el("progress", { id: "job-progress", max: 1, value: job.progress || 0 }),
    job.error ? el("div", { class: "error", id: "job-error" }, job.error) : null,
    el("h3", {}, "EM iterations (identification of Q, R and the transition matrix)"),
    el("p", { class: "note" }, "States are numbered from 0 as on the recognition map: state k has Q level k div N2 and R level k mod N2 (N2 = number of R levels)."),
    rows.some((r) => r.model) ? el("p", { class: "note", id: "em-runs-note" }, "EM run: EM is run once per anomaly model order m (m=1, m=2, with the model's Q×R levels), " +
      "iterations counted from 0 in each; “stored” rows are the identification a filter job reuses, not run again.") : null,
    el("div", { class: "scroll" }, emTable(rows, sel)),
    rows.length ? emDetail(rows, sel, live) : null].filter(Boolean));
  const sc = box.querySelector(".scroll");
  if (sc && emSelected === null) sc.scrollTop = sc.scrollHeight;  // the newest (final) iteration in view
  for (const tr of box.querySelectorAll(".em-row")) {
    const pick = () => { emSelected = +tr.dataset.index; renderJob(box, job); box.querySelector(`.em-row[data-index="${tr.dataset.index}"]`).focus(); };
    clickable(tr, pick, `show EM iteration ${tr.dataset.run ? `${tr.dataset.run} ` : ""}${tr.children[tr.dataset.run === undefined ? 0 : 1].textContent} in full`);
  }
  const cancel = el("button", { id: "job-cancel", disabled: !["queued", "running"].includes(job.status) }, "Cancel job");
  cancel.addEventListener("click", async () => {
    try { renderJob(box, await endpoints.cancelJob(job.id)); } catch (e) { showError(box, e); }
  });
  box.firstChild.append(cancel);
}

function watch(box, jobId, ctx, onDone) {
  if (poller) clearInterval(poller);
  let busy = false, lastStatus = "queued", ticks = 0;
  const tick = async () => {
    if (busy) return;
    busy = true;
    try {
      const job = await endpoints.job(jobId);
      renderJob(box, job);
      // the jobs table below says what the job box says (queued → running), not the state at submit
      // (its status when it changes, its progress every 5 s)
      ticks += 1;
      if ((job.status !== lastStatus || ticks % 10 === 0) && ["queued", "running"].includes(job.status) && onDone) Promise.resolve(onDone(job)).catch(() => {});
      lastStatus = job.status;
      if (!["queued", "running"].includes(job.status)) {
        clearInterval(poller); poller = null;
        if (job.status === "succeeded") ctx.resultsChanged();
        await ctx.refreshSurvey();
        onDone && onDone(job);
      }
    } catch (e) { showError(box, e); } finally { busy = false; }
  };
  poller = setInterval(tick, 500);
  tick();
}

export async function render(sec, ctx) {
  const s = ctx.survey;
  emSelected = null;
  schemaCache = schemaCache || await endpoints.paramsSchema();
  const form = el("form", { id: "params-form" });
  const kind = el("select", { name: "kind", id: "job-kind" },
    el("option", { value: "process" }, "process — identification, recognition, filtering, leveling, grid"),
    el("option", { value: "identify" }, "identify — measurement, noise model, EM learning, recognition (stored)"),
    el("option", { value: "filter" }, "filter — from the stored identification: NL-means (h, ρ), filtering, leveling, grid"));
  titleFromChoice(kind);
  const run = el("button", { type: "submit", class: "primary", id: "run-job", disabled: !s.has_input }, "Run processing");
  const reset = el("button", { type: "button" }, "Reset to defaults");
  form.append(el("div", { class: "controls" }, el("label", {}, "Job ", kind), run, reset),
    el("details", {}, el("summary", {}, "Processing parameters (defaults shown; only changed values are sent)"),
      buildForm(schemaCache.schema, schemaCache.defaults, schemaCache.groups)));
  // the submit's own message (a 409 while a job runs) outside the job box, which the watcher redraws
  const submitMsg = el("div", { id: "submit-msg" });
  form.append(submitMsg);
  const setRunning = (on) => {
    run.disabled = on || !s.has_input;
    run.title = on ? "a job is running on this survey: cancel it or wait for it to end" : "";
  };
  const jobBox = el("div", { class: "card", id: "job-box" }, el("p", { class: "note" }, "No job yet."));
  const history = el("div", { class: "card" }, el("h3", {}, "Jobs of this survey"), el("div", { id: "job-history" }));
  sec.replaceChildren(el("div", { class: "card" }, el("h3", {}, "Run a job"), form), jobBox, history);

  const onJob = (job) => {
    if (job) setRunning(["queued", "running"].includes(job.status));
    // "job N is still running" (a refused submit) is over once that job has ended
    if (job && !["queued", "running"].includes(job.status) && submitMsg.textContent.includes(`job ${job.id} `)) showError(submitMsg, null);
    return loadHistory();
  };
  const loadHistory = async () => {
    const jobs = await endpoints.jobs(s.id);
    history.querySelector("#job-history").replaceChildren(jobs.length ? el("table", {},
      el("thead", {}, el("tr", {}, ["Job", "Kind", "Status", "Progress", "Created (UTC)", "Finished (UTC)", "Error"].map((h) => el("th", { class: "l" }, h)))),
      el("tbody", {}, jobs.map((j) => {
        const tr = el("tr", { style: "cursor:pointer" }, el("td", { class: "l" }, j.id), el("td", { class: "l" }, j.kind),
          el("td", { class: "l" }, el("span", { class: `badge ${j.status}` }, j.status)), el("td", {}, `${Math.round(100 * j.progress)}%`),
          el("td", { class: "l" }, j.created_at.replace("T", " ").slice(0, 19)), el("td", { class: "l" }, (j.finished_at || "").replace("T", " ").slice(0, 19)),
          el("td", { class: "l" }, j.error || ""));
        clickable(tr, () => { emSelected = null; renderJob(jobBox, j); }, `show job ${j.id}`);
        return tr;
      }))) : el("p", { class: "note" }, "none"));
  };

  reset.addEventListener("click", () => {
    const box = sec.querySelector("#params-form > details");
    box.replaceChildren(box.querySelector("summary"), buildForm(schemaCache.schema, schemaCache.defaults, schemaCache.groups));
  });
  // a parameter out of its range inside the closed "Processing parameters" block: the browser refused
  // the submit without a word ("not focusable"); open the block, name the fields, point at the first
  run.addEventListener("click", (ev) => {
    const bad = [...form.querySelectorAll(".params input, .params select")].filter((i) => !i.checkValidity());
    if (!bad.length) return;
    ev.preventDefault();
    for (const i of bad) for (let d = i.closest("details"); d; d = d.parentElement.closest("details")) d.open = true;
    showError(jobBox, new Error("Not started — fix these parameters: " +
      bad.map((i) => `${i.name} (${i.validationMessage})`).join("; ")));
    bad[0].reportValidity();
    bad[0].focus();
  });
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    showError(jobBox, null);
    showError(submitMsg, null);
    try {
      const job = await endpoints.submitJob(s.id, kind.value, collectParams(form));
      emSelected = null;
      renderJob(jobBox, job);
      setRunning(true);
      watch(jobBox, job.id, ctx, onJob);
      loadHistory();
      ctx.jobStarted();
    } catch (e) {
      showError(submitMsg, e);
      // 409: a job was started meanwhile (another browser tab, the recognition map's "Apply h, ρ"):
      // this view said "No job yet" beside "job N is still running" — show that job and watch it
      if (e.status === 409) {
        await ctx.jobStarted();
        const j = ctx.survey && ctx.survey.id === s.id ? ctx.survey.last_job : null;
        if (j && ["queued", "running"].includes(j.status)) {
          emSelected = null;
          renderJob(jobBox, j);
          setRunning(true);
          watch(jobBox, j.id, ctx, onJob);
          loadHistory();
        }
      }
    }
  });
  await loadHistory();
  if (s.last_job) {
    renderJob(jobBox, s.last_job);
    if (["queued", "running"].includes(s.last_job.status)) {
      setRunning(true);
      watch(jobBox, s.last_job.id, ctx, onJob);
    }
  }
}
