"""The analyst off the happy path in Chromium (test pipeline): typed nonsense in the profile's and the
grid's number fields is said in place (no unhandled 422), Back/Forward walk the tabs, plots drawn at one
window size fit another when their tab is shown again, and the jobs table follows a running job."""

from __future__ import annotations

import pytest

from .test_analyst_ui import _open_processed, _processed_survey, _tab, fake_pipeline_server, fake_server  # noqa: F401  (fixture)

pytestmark = [pytest.mark.browser]


def _no_errors(page):
    assert not [e for e in page.errors if "favicon" not in e], page.errors


def test_profile_lowpass_rejects_nonsense(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    _open_processed(page, fake_server.url, tmp_path, "profile", "#profile-plot[data-line] .main-svg")
    z_name = "() => document.querySelector('#profile-plot').data[0].name"
    assert "30 s" in page.evaluate(z_name)
    for bad in ["-5", "1e9", ""]:
        page.fill("#profile-lp", bad)
        page.dispatch_event("#profile-lp", "change")
        page.wait_for_selector("#profile-status.error", timeout=5000)
        assert "from 0 to 600" in page.inner_text("#profile-status"), bad
        assert page.get_attribute("#profile-lp", "aria-invalid") == "true"
    _no_errors(page)   # nothing was sent: no 422, no unhandled rejection
    page.fill("#profile-lp", "60")
    page.dispatch_event("#profile-lp", "change")
    page.wait_for_function(f"() => ({z_name})().includes('60 s')", timeout=10000)
    assert "error" not in (page.get_attribute("#profile-status", "class") or "")
    assert page.get_attribute("#profile-lp", "aria-invalid") == "false"
    _no_errors(page)


def _active(page):
    return page.eval_on_selector("#tabs button.active", "b => b.dataset.tab")


def test_back_and_forward_walk_the_tabs(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    sid = _open_processed(page, fake_server.url, tmp_path, "qc", "#view-qc:not([hidden])")
    _tab(page, "process")
    _tab(page, "grid")
    page.wait_for_selector("#grid-plot .main-svg", timeout=20000)
    page.go_back()
    page.wait_for_function("() => document.querySelector('#tabs button.active').dataset.tab === 'process'", timeout=5000)
    assert page.is_visible("#view-process") and page.is_hidden("#view-grid")
    assert page.url.endswith(f"#survey={sid}&tab=process")
    page.go_back()
    page.wait_for_function("() => document.querySelector('#tabs button.active').dataset.tab === 'qc'", timeout=5000)
    assert page.is_visible("#view-qc")
    page.go_forward()
    page.wait_for_function("() => document.querySelector('#tabs button.active').dataset.tab === 'process'", timeout=5000)
    assert page.url.endswith("tab=process")
    _no_errors(page)


def test_a_tab_clicked_while_the_page_loads_is_not_lost(fake_server, browser_page, tmp_path):  # noqa: F811
    """The survey list held back until after a click on "Anomaly grid": once it arrives the grid
    is shown, not the address's tab (the click used to be lost under load)."""
    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    held = []
    page.route("**/api/surveys", lambda route: route.continue_() if held else held.append(route))
    page.goto(f"{fake_server.url}/#survey={sid}&tab=qc")
    for _ in range(200):   # the module scripts may ask for the list after the load event: up to 10 s
        if held:
            break
        page.wait_for_timeout(50)
    assert held, "the page asked for the survey list"
    _tab(page, "grid")
    held[0].continue_()
    page.wait_for_selector("#grid-plot .main-svg", timeout=20000)
    assert _active(page) == "grid" and page.is_hidden("#view-qc")
    assert page.url.endswith(f"#survey={sid}&tab=grid")
    _no_errors(page)


def test_plots_fit_a_window_resized_while_their_tab_was_hidden(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    _open_processed(page, fake_server.url, tmp_path, "profile", "#profile-plot[data-line] .main-svg")
    _tab(page, "qc")
    page.set_viewport_size({"width": 800, "height": 600})
    _tab(page, "profile")
    fits = """() => { const p = document.querySelector('#profile-plot');
                      return p.querySelector('.main-svg').getBoundingClientRect().width <= p.clientWidth + 1; }"""
    page.wait_for_function(fits, timeout=5000)
    # no "Share chart..." in the plot toolbar: it uploads the plot's (the survey's) data to Plotly Cloud
    assert page.locator("#profile-plot .modebar-btn[data-title='Download plot as a PNG']").count() == 1
    assert page.locator(".modebar-btn[data-title*='Share'], .modebar-btn[data-title*='Chart Studio']").count() == 0
    _no_errors(page)


def test_grid_colour_range_from_above_to_is_said(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    _open_processed(page, fake_server.url, tmp_path, "grid", "#grid-plot[data-variable] .main-svg")
    page.fill("#grid-zmin", "10")
    page.fill("#grid-zmax", "-10")
    page.dispatch_event("#grid-zmax", "change")
    page.wait_for_selector("#grid-limits.error", timeout=5000)
    assert "ignored" in page.inner_text("#grid-limits")
    assert page.get_attribute("#grid-zmin", "aria-invalid") == "true"
    zmin, zmax = float(page.get_attribute("#grid-plot", "data-zmin")), float(page.get_attribute("#grid-plot", "data-zmax"))
    centre = float(page.get_attribute("#grid-plot", "data-centre"))
    assert (zmin + zmax) / 2 == pytest.approx(centre) and zmax > centre   # the robust default, not the typed values
    page.fill("#grid-zmax", "20")
    page.dispatch_event("#grid-zmax", "change")
    page.wait_for_function("() => document.querySelector('#grid-plot').dataset.zmax === '20'", timeout=5000)
    assert "error" not in page.get_attribute("#grid-limits", "class")
    _no_errors(page)


@pytest.fixture
def slow_server(tmp_path, monkeypatch):
    with fake_pipeline_server(tmp_path, monkeypatch, 0.5) as srv:
        yield srv


def test_jobs_table_follows_the_running_job(slow_server, browser_page, tmp_path):
    import httpx

    from tests.web.conftest import make_tiny_survey, zip_dir
    page = browser_page
    z = zip_dir(make_tiny_survey(tmp_path / "tiny", name="tiny"))
    with httpx.Client(base_url=slow_server.url, timeout=30) as c:
        sid = c.post("/api/surveys/import", files={"file": ("tiny.zip", z, "application/zip")}).json()["id"]
    page.goto(f"{slow_server.url}/#survey={sid}&tab=process")
    page.wait_for_selector("#run-job:not([disabled])")
    page.click("#run-job")
    page.wait_for_function("() => { const s = document.querySelector('#job-status'); return s && s.textContent === 'running'; }",
                           timeout=20000)
    # while the job box says running, so does the jobs table (it said "queued" until the job ended)
    page.wait_for_function("""() => { const b = document.querySelector('#job-history tbody tr .badge');
                                      return b && b.textContent === 'running'; }""", timeout=5000)
    page.wait_for_function("() => document.querySelector('#job-status').textContent === 'succeeded'", timeout=60000)
    page.wait_for_function("() => document.querySelector('#job-history tbody tr .badge').textContent === 'succeeded'", timeout=5000)
    _no_errors(page)


_WIDEST = """() => { const W = document.documentElement.clientWidth; const out = [];
  for (const e of document.querySelectorAll('body *')) { const r = e.getBoundingClientRect();
    if (r.width && r.right > W + 1 && !e.closest('.js-plotly-plot .main-svg, .js-plotly-plot .svg-container > *')) out.push(`${e.tagName}#${e.id}.${e.className} ${Math.round(r.right)}`); }
  return {W, scroll: document.documentElement.scrollWidth, over: out.slice(0, 6)}; }"""


@pytest.mark.parametrize("tab,ready", [("qc", "#qc-lines tbody tr"), ("process", ".em-row"), ("report", "#report-summary li"),
                                       ("recognition", "#rec-map .main-svg"), ("profile", "#profile-plot .main-svg"),
                                       ("grid", "#grid-plot .main-svg"), ("export", "#export-geotiff")])
def test_nothing_wider_than_an_800px_window(fake_server, browser_page, tmp_path, tab, ready):  # noqa: F811
    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    page.set_viewport_size({"width": 800, "height": 600})
    page.goto(f"{fake_server.url}/#survey={sid}&tab={tab}")
    page.wait_for_selector(ready, timeout=20000)
    page.wait_for_timeout(300)
    w = page.evaluate(_WIDEST)
    page.screenshot(path=str(tmp_path / f"narrow-{tab}.png"), full_page=True)
    assert w["scroll"] <= w["W"], w
    _no_errors(page)


def test_em_rows_and_jobs_answer_the_keyboard(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    _open_processed(page, fake_server.url, tmp_path, "process", ".em-row")
    n = page.locator(".em-row").count()
    assert n >= 2 and page.get_attribute("#em-detail", "data-iteration") == page.inner_text(f".em-row[data-index='{n - 1}'] td")
    page.focus(".em-row[data-index='0']")
    page.keyboard.press("Enter")
    page.wait_for_function("() => document.querySelector('#em-detail').dataset.iteration === "
                           "document.querySelector(\".em-row[data-index='0'] td\").textContent")
    assert page.evaluate("() => document.activeElement.dataset.index") == "0"   # focus stays on the row
    page.keyboard.press("Shift+Tab")
    page.keyboard.press("Tab")
    page.keyboard.press("Tab")                                                   # the next row, from the keyboard
    assert page.evaluate("() => document.activeElement.dataset.index") == "1"
    page.keyboard.press(" ")
    page.wait_for_selector(".em-row[data-index='1'].selected")
    # the jobs table's rows too
    page.focus("#job-history tbody tr")
    page.keyboard.press("Enter")
    page.wait_for_selector("#job-status")
    _no_errors(page)


def test_out_of_range_parameter_in_the_closed_block_is_named(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    page.goto(f"{fake_server.url}/#survey={sid}&tab=process")
    page.wait_for_selector("#params-form .params input[name=em_max_iter]", state="attached")
    page.eval_on_selector("#params-form input[name=em_max_iter]", "e => { e.value = '-3'; }")   # block stays closed
    assert page.eval_on_selector("#params-form details", "d => d.open") is False
    page.wait_for_selector("#job-history tbody tr")          # the processing job (the table loads after the form)
    n_jobs = page.locator("#job-history tbody tr").count()
    page.click("#run-job")
    page.wait_for_selector("#job-box .error:visible", timeout=5000)
    msg = page.inner_text("#job-box .error")
    assert "Not started" in msg and "em_max_iter" in msg, msg
    assert page.eval_on_selector("#params-form details", "d => d.open") is True
    assert page.evaluate("() => document.activeElement.name") == "em_max_iter"
    assert page.locator("#job-history tbody tr").count() == n_jobs           # nothing was submitted
    page.fill("#params-form input[name=em_max_iter]", "60")
    page.click("#run-job")
    page.wait_for_function(f"() => document.querySelectorAll('#job-history tbody tr').length === {n_jobs + 1}",
                           timeout=10000)
    assert page.is_hidden("#job-box .error")
    _no_errors(page)


def test_recognition_status_recovers_after_a_failed_request(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    _open_processed(page, fake_server.url, tmp_path, "recognition", "#rec-map[data-signature]")
    failed = []

    def once(route):
        if not failed:
            failed.append(route.request.url)
            route.fulfill(status=503, json={"detail": "server busy"})
        else:
            route.continue_()
    page.route("**/recognition?*", once)
    set_range = "(e, v) => { e.value = v; e.dispatchEvent(new Event('input', {bubbles: true})); }"
    page.eval_on_selector("#rec-h", set_range, "2")
    page.wait_for_selector("#rec-status.error", timeout=5000)
    assert "server busy" in page.inner_text("#rec-status")
    page.eval_on_selector("#rec-h", set_range, "3")
    page.wait_for_function("() => document.querySelector('#rec-map').dataset.h === '3'", timeout=10000)
    assert "error" not in page.get_attribute("#rec-status", "class")   # the good answer is not shown as an error
    assert "h=3" in page.inner_text("#rec-status")
    page.errors[:] = [e for e in page.errors if "503" not in e]          # the staged failure
    _no_errors(page)


_OVERLAPS = """(sel) => {
  const r = [...document.querySelectorAll(`${sel} .textpoint text, ${sel} .annotation-text`)].map((t) => [t.textContent, t.getBoundingClientRect()]);
  const out = [];
  for (let i = 0; i < r.length; i++) for (let j = i + 1; j < r.length; j++) {
    const a = r[i][1], b = r[j][1];
    const w = Math.min(a.right, b.right) - Math.max(a.left, b.left), h = Math.min(a.bottom, b.bottom) - Math.max(a.top, b.top);
    if (w > 1 && h > 1) out.push(`${r[i][0]} / ${r[j][0]}`);
  }
  return {n: r.length, out}; }"""


def test_repeat_line_labels_do_not_print_over_each_other(live_server, browser_page, tmp_path):
    """omolon-mini has two repeat lines flown over one track (R1-1, R1-2): their labels were drawn at
    the same point, one over the other, on the QC line map and the grid."""
    import shutil
    from pathlib import Path

    import httpx

    from tests.web.conftest import zip_dir
    sample = Path(__file__).resolve().parents[2] / "sample_surveys" / "omolon-mini"   # in the repository
    src = tmp_path / "omolon-mini"
    shutil.copytree(sample, src, ignore=shutil.ignore_patterns("truth"))
    with httpx.Client(base_url=live_server.url, timeout=60) as c:
        sid = c.post("/api/surveys/import", files={"file": ("s.zip", zip_dir(src), "application/zip")}).json()["id"]
    page = browser_page
    page.goto(f"{live_server.url}/#survey={sid}&tab=qc")
    page.wait_for_selector("#line-map .textpoint text", timeout=30000)
    res = page.evaluate(_OVERLAPS, "#line-map")
    assert res["n"] == 16 and not res["out"], res
    # the stacked ones are a column of annotations left of their shared start (test_walkthrough_fixes_ui)
    assert page.locator("#line-map .textpoint text").count() == 13
    assert page.locator("#line-map .annotation-text").count() == 3
    _no_errors(page)


def test_a_result_view_open_during_the_job_shows_the_result_when_it_ends(slow_server, browser_page, tmp_path):
    """Reloaded mid-job on the recognition tab (no view watches the job): the map appears when the job
    ends, without clicking another tab or survey; it used to say "No results yet" until then."""
    import httpx

    from tests.web.conftest import make_tiny_survey, zip_dir
    page = browser_page
    z = zip_dir(make_tiny_survey(tmp_path / "tiny", name="tiny"))
    with httpx.Client(base_url=slow_server.url, timeout=30) as c:
        sid = c.post("/api/surveys/import", files={"file": ("tiny.zip", z, "application/zip")}).json()["id"]
        c.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).raise_for_status()
    page.goto(f"{slow_server.url}/#survey={sid}&tab=recognition")
    page.wait_for_selector("#view-recognition .empty:has-text('No results yet')")
    page.wait_for_selector("#survey-list li .badge:has-text('running')", timeout=10000)
    page.wait_for_selector("#rec-map[data-signature]", timeout=60000)
    page.wait_for_selector("#survey-list li .badge:has-text('succeeded')", timeout=5000)
    _no_errors(page)


def test_summary_says_when_a_longer_lowpass_replaces_fir(fake_server, browser_page):  # noqa: F811
    """Where FIR 100 s itself resolves nothing (stage 9, step 3b) the report's summary says which
    low-pass was used and the crossovers' evidence, not just "FIR" (the figures of generated 78)."""
    page = browser_page
    page.goto(fake_server.url)
    text = page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const nc = {applied: true, median_variance_ratio: 2.70, median_disagreement: 1.15,
                    long_lowpass: {applied: true, fir_crossover_std_mgal: 86.6, fir_spread_mgal: 76.4, period_s: 800}};
        const r = {warnings: [], report: {model_choice: {chosen: 'FIR', m: 2, noisy_check: nc, fir_guard: {applied: false}}}};
        const off = {warnings: [], report: {model_choice: {chosen: 'FIR', m: 2,
                     noisy_check: {...nc, long_lowpass: {applied: false}}, fir_guard: {applied: false}}}};
        return [m.summary(r).textContent, m.summary(off).textContent];
    }""")
    assert ("the adaptive estimate passes noise (median variance ratio 2.7, median disagreement with FIR 1.15); "
            "FIR 100 s resolves no anomaly either (its crossovers show 86.6 mGal of error against an along-line "
            "spread of 76.4): the 800 s low-pass is used") in text[0]
    assert "passes noise" in text[1] and "low-pass is used" not in text[1]
    _no_errors(page)


def test_summary_says_when_the_estimate_resolves_nothing(fake_server, browser_page):  # noqa: F811
    """Where the estimate kept by the checks before resolves nothing beyond its noise (stage 9,
    step 4c) the summary says so after the crossovers' verdict, with the low-pass used and the
    evidence (the figures of foreign 817); a check that did not apply adds nothing."""
    page = browser_page
    page.goto(fake_server.url)
    text = page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const g = {applied: false, n_crossovers: 28, crossover_rms_mgal: 65.0, crossover_rms_fir_mgal: 64.6,
                   p_value: 0.48, p_rank: 0.26};
        const u = {applied: true, n_crossovers: 28, crossover_std_mgal: 43.6, spread_mgal: 20.3,
                   long_lowpass: {applied: true, period_s: 800}};
        const on = {warnings: [], report: {model_choice: {chosen: 'FIR', m: 2, noisy_check: {applied: false},
                    fir_guard: g, unresolved_check: u}}};
        const off = {warnings: [], report: {model_choice: {chosen: 'adaptive', m: 2, noisy_check: {applied: false},
                     fir_guard: g, unresolved_check: {...u, applied: false}}}};
        return [m.summary(on).textContent, m.summary(off).textContent];
    }""")
    assert ("that estimate resolves no anomaly beyond its noise (its 28 crossovers show 43.6 mGal of error "
            "against an along-line spread of 20.3): the 800 s low-pass of z is used") in text[0]
    assert "Model choice: adaptive" in text[1] and "resolves no anomaly" not in text[1]
    _no_errors(page)
