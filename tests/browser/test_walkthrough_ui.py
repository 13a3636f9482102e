"""What an analyst walking through the application met (test pipeline): a filter job started from the
recognition map shows up in the survey list and on the Processing tab; the EM table says which EM run
(model order, or the stored identification) each row belongs to; the profile names the states it
shades; the report's model choice reads as a table and says why the adaptive estimate beat FIR."""

from __future__ import annotations

import pytest

from .test_analyst_ui import _open_processed, fake_pipeline_server, fake_server  # noqa: F401  (fixture)

pytestmark = [pytest.mark.browser]


def _no_errors(page):
    assert not [e for e in page.errors if "favicon" not in e], page.errors


@pytest.fixture
def paced_server(tmp_path, monkeypatch):
    with fake_pipeline_server(tmp_path, monkeypatch, 0.3) as srv:
        yield srv


def test_apply_h_rho_shows_the_filter_job_in_the_list_and_on_processing(paced_server, browser_page, tmp_path):
    """"Apply h, ρ" said "filter job N started — see Process", but the survey list kept the old badge
    (polled every 10 s) and the Processing tab showed the previous job, not watching the new one."""
    page = browser_page
    _open_processed(page, paced_server.url, tmp_path, "recognition", "#rec-map[data-signature]")
    page.wait_for_selector("#survey-list li.active .badge:has-text('succeeded')")
    page.click("#rec-apply")
    page.wait_for_selector("#rec-apply-note[data-job]", timeout=5000)
    job = page.get_attribute("#rec-apply-note", "data-job")
    # the list says the survey is busy at once (not at the next 10 s poll)
    page.wait_for_selector("#survey-list li.active .badge:is(:has-text('queued'), :has-text('running'))", timeout=2500)
    page.click("#tabs button[data-tab=process]")
    page.wait_for_selector(f"#job-box strong:has-text('Job {job}')", timeout=5000)
    assert "(filter," in page.inner_text("#job-box")
    page.wait_for_selector("#job-status:has-text('succeeded')", timeout=30000)   # watched to its end
    _no_errors(page)


def _model_choice_line(page, model_choice_js: str) -> dict:
    """The report summary's "Model choice" line (text and class) for a report whose
    ``model_choice`` is the JavaScript object literal ``model_choice_js``."""
    return page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const rep = {warnings: [], report: {model_choice: """ + model_choice_js + """}};
        const li = [...m.summary(rep).querySelectorAll('li')].find((l) => l.textContent.startsWith('Model choice'));
        return {text: li.textContent, cls: li.className};
    }""")


def _em_rows(model, n, nr=2):
    a = [[0.9 if i == j else 0.1 / (2 * nr - 1) for j in range(2 * nr)] for i in range(2 * nr)]
    return [{"iteration": i, "Q": [1e-5, 5e-5], "R": [1.7, 17.0][:nr], "objective": -2200.0 + i, "transition": a,
             "model": model} for i in range(n)]


def test_em_table_says_which_run_each_row_belongs_to(paced_server, browser_page, tmp_path):
    """The real pipeline runs EM once per model order (rows "m=1 2x2" then "m=2 2x2", iterations from 0
    in each) and a filter job lists the stored identification's ("stored"): the table showed one column
    of iterations restarting at 0 halfway, and "Final iteration" only for the last run."""
    page = browser_page
    _open_processed(page, paced_server.url, tmp_path, "process", ".em-row")
    rows = _em_rows("m=1 2x2", 3) + _em_rows("m=2 2x2", 4)
    got = page.evaluate("""async (rows) => {
        const m = await import('/js/views/process.js');
        const t = m.emTable(rows, 6);
        const cells = [...t.querySelectorAll(':scope > tbody > tr')].map((tr) => [tr.dataset.run, tr.children[0].textContent,
                                                                    tr.children[1].textContent, tr.classList.contains('final')]);
        return {head: [...t.querySelectorAll('th')].map((th) => th.textContent), cells,
                end1: m.emDetail(rows, 2, false).querySelector('h4').textContent,
                mid2: m.emDetail(rows, 4, false).querySelector('h4').textContent,
                last: m.emDetail(rows, 6, true).querySelector('h4').textContent};
    }""", rows)
    assert got["head"][:2] == ["EM run", "Iteration"]
    assert [c[:3] for c in got["cells"]] == [["m=1 2x2", "m=1 2x2", "0"], ["m=1 2x2", "m=1 2x2", "1"], ["m=1 2x2", "m=1 2x2", "2"],
                                             ["m=2 2x2", "m=2 2x2", "0"], ["m=2 2x2", "m=2 2x2", "1"], ["m=2 2x2", "m=2 2x2", "2"],
                                             ["m=2 2x2", "m=2 2x2", "3"]]
    assert [c[3] for c in got["cells"]] == [False, False, True, False, False, False, True]   # each run's last row
    assert got["end1"].startswith("Final iteration 2 of EM run m=1 2x2 —"), got["end1"]
    assert got["mid2"].startswith("Selected iteration 1 of EM run m=2 2x2 (of 3)"), got["mid2"]
    assert got["last"].startswith("Latest iteration 3 of EM run m=2 2x2"), got["last"]
    # rows without a run (older jobs, the test pipeline) keep the plain table
    assert page.inner_text("#em-table thead tr th") == "Iteration"
    assert page.locator("#em-runs-note").count() == 0
    _no_errors(page)


def test_profile_names_the_states_it_shades(fake_server_2x2, browser_page, tmp_path):
    """The profile said "shaded bands: states > 0 (rougher anomaly)", wrong for a 2×2 model where
    state 1 is (Q0, R1): the same smooth anomaly, noisier GNSS. The shaded states are now named in
    the legend as on the recognition map."""
    page = browser_page
    _open_processed(page, fake_server_2x2.url, tmp_path, "profile", "#profile-plot[data-line] .main-svg")
    assert "rougher anomaly" not in page.inner_text("#profile-status")
    names = page.evaluate("() => document.querySelector('#profile-plot').data.map((t) => t.name)")
    shaded = [n for n in names if n and n.startswith("shaded: ")]
    # the test pipeline's lines are in state 0 and 1 only: state 1 shaded, named by its levels
    assert shaded == ["shaded: state 1 (Q0, R1): Q=0.041 mGal² per step, R=17.3 (cm/s)²"], names
    _no_errors(page)


@pytest.fixture
def fake_server_2x2(fake_server, browser_page):  # noqa: F811
    """The test pipeline's result with a 2×2 identification (states 0…3 = (Q0,R0), (Q0,R1), (Q1,R0), (Q1,R1))."""
    def report(route):
        r = route.fetch().json()
        r["identification"]["states"] = [{"index": 0, "Q": 0.041, "R": 1.679}, {"index": 1, "Q": 0.041, "R": 17.3},
                                         {"index": 2, "Q": 0.353, "R": 1.679}, {"index": 3, "Q": 0.353, "R": 17.3}]
        route.fulfill(json=r)
    browser_page.route("**/api/surveys/*/report", report)
    return fake_server


def test_model_choice_says_why_adaptive_and_reads_as_a_table(fake_server, browser_page):  # noqa: F811
    """omolon-mini's report: "Model choice: adaptive (anomaly order m = 2, …)" said nothing of FIR 100 s,
    the alternative it was weighed against at the crossovers, and the model-choice card drew each
    line's record as its own key/value table (16 lines: some 160 rows in one column)."""
    page = browser_page
    page.goto(fake_server.url)
    got = page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const p = await import('/js/plots.js');
        const guard = (rms, fir, pv) => ({warnings: [], report: {model_choice: {chosen: 'adaptive', m: 2, noisy_check: {applied: false},
            fir_guard: {n_crossovers: 30, crossover_rms_mgal: rms, crossover_rms_fir_mgal: fir, p_value: pv, p_rank: 0.89, applied: false}}}});
        const lines = {M001: {estimate: 'adaptive', flattening_ratio: 1.21, detectable: true},
                       M002: {estimate: 'adaptive', flattening_ratio: 1.31, detectable: false}};
        const t = p.genericView({chosen: 'adaptive', lines}).querySelector('table table');
        return {better: m.summary(guard(4.345, 6.574, 0.976)).textContent, worse: m.summary(guard(5.1, 4.9, 0.31)).textContent,
                head: [...t.querySelectorAll(':scope > thead th')].map((th) => th.textContent),
                rows: [...t.querySelectorAll(':scope > tbody > tr')].map((tr) => [...tr.children].map((td) => td.textContent))};
    }""")
    assert "— at the 30 crossovers it agrees better than FIR 100 s (RMS 4.345 against 6.574 mGal)" in got["better"], got
    assert ("— at the 30 crossovers it agrees worse than FIR 100 s, but not significantly (RMS 5.1 against 4.9 mGal; "
            "t-test p = 0.31, signed ranks p = 0.89)") in got["worse"], got
    assert got["head"] == ["", "estimate", "flattening_ratio", "detectable"]
    assert got["rows"] == [["M001", "adaptive", "1.21", "true"], ["M002", "adaptive", "1.31", "false"]]
    _no_errors(page)


def test_model_choice_on_a_test_line_gives_the_repeat_blend(fake_server, browser_page):  # noqa: F811
    """A test line has no crossovers for the FIR guard: the report says that its passes judged,
    and with what weight FIR was blended in (generated survey 208's figures), marked as a
    departure from the adaptive estimate."""
    page = browser_page
    page.goto(fake_server.url)
    got = _model_choice_line(page, """{chosen: 'blend with FIR', m: 2, noisy_check: {applied: false},
        fir_guard: {applied: false, reason: '0 crossovers (< 4)'},
        repeat_blend: {weight_fir: 0.6412, passes: 4, tracks: 1, reference_period_s: 50, msd_estimate_mgal2: 61.23,
                       msd_fir_mgal2: 60.87, msd_blend_mgal2: 60.31, applied: true, fir_std_floor_mgal: 2.1}}""")
    assert got["text"].startswith("Model choice: blend with FIR (anomaly order m = 2) — too few crossovers to judge; "
                                  "the 4 repeat passes agree best with each other's 50 s low-pass of z when 0.641 of "
                                  "FIR 100 s is blended in (mean square 61.23 adaptive, 60.87 FIR, 60.31 blend"), got
    assert got["cls"] == "warn"
    # the default reference since session 48: the other passes smoothed lightly, named as such
    text = _model_choice_line(page, """{chosen: 'blend with FIR', m: 2, noisy_check: {applied: false},
        fir_guard: {applied: false, reason: '0 crossovers (< 4)'},
        repeat_blend: {weight_fir: 0.8379, passes: 4, tracks: 1, reference: 'estimate at 300 x Q(t)',
                       reference_q_factor: 300, msd_estimate_mgal2: 37.70, msd_fir_mgal2: 33.38,
                       msd_blend_mgal2: 33.1, applied: true, fir_std_floor_mgal: 2.1}}""")["text"]
    assert "agree best with each other's estimate at 300 x Q(t) when 0.838 of FIR 100 s is blended in" in text, text
    _no_errors(page)


def test_model_choice_on_a_small_survey_gives_its_share_of_fir(fake_server, browser_page):  # noqa: F811
    """A small survey with nothing to judge its estimate (no crossovers, no repeat track, one
    level from 44 decimated points): the report says why and what share of FIR was blended in,
    marked as a departure from the adaptive estimate."""
    page = browser_page
    page.goto(fake_server.url)
    got = _model_choice_line(page, """{chosen: 'blend with FIR', m: 2, noisy_check: {applied: false},
        fir_guard: {applied: false, reason: '0 crossovers (< 4)'},
        repeat_blend: {applied: false, reason: 'no repeat track of 3 passes or more'},
        small_survey_blend: {applied: true, weight_fir: 0.3, n_points: 44, reason: 'no crossovers'}}""")
    assert got["text"].startswith("Model choice: blend with FIR (anomaly order m = 2) — no crossovers or repeat "
                                  "passes can judge an anomaly level learned from 44 decimated points: 0.3 of FIR "
                                  "100 s is blended in (small_survey_fir_weight)"), got
    assert got["cls"] == "warn"
    _no_errors(page)


def test_lag_from_the_flights_on_one_scale_is_told_as_such(fake_server, browser_page):  # noqa: F811
    """Generated survey 237's lag check: two flights' offsets took the lag, the third's τ fit
    found it.  The summary said "the flights say 0.006, 0.011, 0.269 s: the flights' value was
    used", naming three values none of which was used; it must give the lags on one scale and
    the τ used."""
    page = browser_page
    page.goto(fake_server.url)
    got = page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const rep = {warnings: [], report: {lag_check: {declared_tau_s: 0, estimated_tau_s: [0.0061, 0.0108, 0.2687],
            time_offsets_s: [-0.2460, -0.2446, 0], flight_lags_s: [0.2521, 0.2554, 0.2687], one_scale_tau_s: 0.2554,
            from_one_scale: true, applied: true, band_rms_improvement: 0.091,
            reason: 'τ fits minus applied time offsets 0.252, 0.255, 0.269 s; z RMS at 0.02–0.05 Hz 21.6 → 19.6 mGal'}}};
        const li = [...m.summary(rep).querySelectorAll('li')].find((l) => l.textContent.startsWith('Gravimeter lag'));
        return {text: li.textContent, cls: li.className};
    }""")
    assert got["text"] == ("Gravimeter lag: survey.toml says τ = 0 s; each flight's in-flight τ minus the time offset "
                           "applied before it gives 0.252, 0.255, 0.269 s: their median 0.255 s was used."), got
    assert got["cls"] == "warn"
    _no_errors(page)


def test_a_lag_tried_and_refused_is_not_called_confirmed(fake_server, browser_page):  # noqa: F811
    """Generated survey 234: every flight's time offset (≈ −0.25 s) looked like a lag, and read
    as one it did not lower z's band RMS.  The summary said "τ = 0 s confirmed in flight (0.001,
    0.004, 0.001 s)", hiding that a 0.26 s lag was tried; it must say the τ was kept and why."""
    page = browser_page
    page.goto(fake_server.url)
    got = page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const why = "the flights' lags on one scale (0.256, 0.255, 0.258 s) as τ = 0.256 s change z's RMS at 0.02–0.05 Hz by +0.4 %: not used";
        const lag = (extra) => ({warnings: [], report: {lag_check: {declared_tau_s: 0, estimated_tau_s: [0.0012, 0.0038, 0.0015],
            applied: false, ...extra}}});
        const text = (r) => [...m.summary(r).querySelectorAll('li')].find((l) => l.textContent.startsWith('Gravimeter lag')).textContent;
        return {refused: text(lag({one_scale: {applied: false, from_one_scale: true, reason: why}})), plain: text(lag({}))};
    }""")
    assert got["refused"] == ("Gravimeter lag τ = 0 s kept (in-flight τ 0.001, 0.004, 0.002 s): the flights' lags on one "
                              "scale (0.256, 0.255, 0.258 s) as τ = 0.256 s change z's RMS at 0.02–0.05 Hz by +0.4 %: "
                              "not used."), got
    assert got["plain"] == "Gravimeter lag τ = 0 s confirmed in flight (0.001, 0.004, 0.002 s).", got
    _no_errors(page)


def test_a_repeat_pass_widened_to_its_own_noise_is_named(fake_server, browser_page):  # noqa: F811
    """Generated test line 304: two of four passes flew through turbulence, and their std was
    widened to the noise their departures from the other passes show.  The summary names
    those passes (the report's ``widened_passes``) with their factors, says whether the track
    was sized by its passes or floored at their noise, and gives no line for a track where no
    pass was widened."""
    page = browser_page
    page.goto(fake_server.url)
    got = page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const rep = (track) => ({warnings: [], report: {level_refinement: {std_repeat_tracks: {R1: track}}}});
        const text = (r) => [...m.summary(r).querySelectorAll('li')].filter((l) => l.textContent.startsWith('Std on repeat'))
            .map((l) => [l.textContent, l.className]);
        const floor = {scale: null, noise_part_mgal: 49.13, posterior_mgal: 14.9, noise_p_value: 2.2e-25,
            pass_lines: ['R1-1', 'R1-2', 'R1-3', 'R1-4'], pass_scales: [1.0, 5.362, 1.0, 3.635],
            widened_passes: [{line: 'R1-2', scale: 5.362, noise_ratio: 28.75}, {line: 'R1-4', scale: 3.635, noise_ratio: 13.2}]};
        const sized = {scale: 1.27, pass_lines: ['R1-1', 'R1-2', 'R1-3', 'R1-4'], pass_scales: [1.27, 2.1, 1.27, 1.27],
            widened_passes: [{line: 'R1-2', scale: 2.1, noise_ratio: 4.0}]};
        const even = {scale: 1.27, pass_lines: ['R1-1', 'R1-2'], pass_scales: [1.27, 1.27], widened_passes: []};
        return {floor: text(rep(floor)), sized: text(rep(sized)), even: text(rep(even)), none: text({warnings: [], report: {}})};
    }""")
    assert got["floor"] == [["Std on repeat track R1: the passes' scatter (49.13 mGal) exceeds the posterior std (14.9 "
                             "mGal, p = 2.2e-25); R1-2 × 5.362, R1-4 × 3.635: these passes carry more noise than the "
                             "others (their departures from them), and their std is widened to it.", "warn"]], got
    assert got["sized"] == [["Std on repeat track R1: sized by its passes (× 1.27); R1-2 × 2.1: this pass carries more "
                             "noise than the others (its departures from them), and its std is widened to it.", "warn"]], got
    assert got["even"] == [] and got["none"] == [], got
    _no_errors(page)


def test_a_repeat_pass_smoothed_with_its_own_noise_is_named(fake_server, browser_page):  # noqa: F811
    """Generated test line 304: two turbulent passes were smoothed again with their noise level
    raised to what their departures from the other passes show.  The summary names them with
    the factor and how much their departure fell; a pass tried and not kept is not named."""
    page = browser_page
    page.goto(fake_server.url)
    got = page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const text = (t) => [...m.summary({warnings: [], report: {level_refinement: {noisy_passes_rescaled: {R1: t}}}})
            .querySelectorAll('li')].filter((l) => l.textContent.startsWith('Estimate on repeat')).map((l) => l.textContent);
        const a = {line: 'R1-2', R_factor: 28.43, departure_before: 10.0, departure_after: 7.86};
        const b = {line: 'R1-4', R_factor: 16.29, departure_before: 5.0, departure_after: 2.95};
        const c = {line: 'R1-3', R_factor: 3.5, departure_before: 2.0, departure_after: 3.1};
        return {two: text({tried: [a, b, c], rescaled: [a, b]}), none: text({tried: [c], rescaled: []})};
    }""")
    assert got["two"] == ["Estimate on repeat track R1: R1-2 smoothed with its noise level × 28.43 (departure from the "
                          "other passes −21.4 %), R1-4 smoothed with its noise level × 16.29 (departure from the other "
                          "passes −41 %): these passes carry more noise than the noise model gave them, measured by "
                          "their departures from the other passes."], got
    assert got["none"] == [], got
    _no_errors(page)


def test_a_test_lines_lowered_level_is_named(fake_server, browser_page):  # noqa: F811
    """Generated test line 248: its repeat passes agreed better at Q/3; the summary says so with
    the two figures and the p-value, and says nothing where the level was kept.  A level raised
    against the smoother reference names that reference and the interior it was judged on."""
    page = browser_page
    page.goto(fake_server.url)
    got = page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const text = (lc) => [...m.summary({warnings: [], report: {level_refinement: {repeat_level_check: lc}}})
            .querySelectorAll('li')].filter((l) => l.textContent.startsWith('Test line level')).map((l) => l.textContent);
        const lowered = {factors: [0.3333333, 1.0], msd_mgal2: [743.7, 887.75], p_values: {'0.333333': 0.0123},
                         reference_period_s: 50, factor: 0.3333333};
        const raised = {factors: [0.3333333, 1.0, 3.0], msd_mgal2: [5.817, 4.304, 3.721],
                        p_values: {'0.333333': 0.98, '3': 0.0312}, reference: 'estimate at 300 x Q(t)',
                        reference_q_factor: 300, edge_km: 10, factor: 3.0,
                        scaled: "Q(t) x 3 in the lines' interiors (10 km or more from their ends)"};
        return {lowered: text(lowered), kept: text({...lowered, factor: 1.0}), raised: text(raised)};
    }""")
    assert got["lowered"] == ["Test line level: Q × 0.333 — the repeat passes agree better with the other passes' 50 s "
                              "low-pass of z (mean square 743.7 against 887.75 mGal², p = 0.01)."], got
    assert got["kept"] == [], got
    # raised, against the other passes' smoother reference: the figures of Q x 3 and Q, and its p
    assert got["raised"] == ["Test line level: Q × 3 in the lines' interiors (10 km or more from their ends) — the "
                             "repeat passes agree better there with the other passes' estimate at 300 × Q(t) (mean "
                             "square 3.721 against 4.304 mGal², p = 0.03)."], got
    _no_errors(page)


def test_surveys_of_one_name_can_be_told_apart(fake_server, browser_page, tmp_path):  # noqa: F811
    """The same zip imported twice gave two list entries both reading "tiny" (and the same title)."""
    import httpx

    from tests.web.conftest import make_tiny_survey, zip_dir
    z = zip_dir(make_tiny_survey(tmp_path / "tiny", name="tiny"))
    with httpx.Client(base_url=fake_server.url, timeout=30) as c:
        ids = [c.post("/api/surveys/import", files={"file": ("tiny.zip", z, "application/zip")}).json()["id"] for _ in range(2)]
        c.post("/api/surveys", json={"name": "other"}).raise_for_status()
    page = browser_page
    page.goto(f"{fake_server.url}/#survey={ids[1]}&tab=qc")
    page.wait_for_selector("#qc-lines tbody tr", timeout=20000)
    names = page.eval_on_selector_all("#survey-list li span:first-child", "ss => ss.map((s) => s.textContent)")
    assert sorted(names) == sorted([f"tiny (#{ids[0]})", f"tiny (#{ids[1]})", "other"]), names
    assert page.inner_text("#survey-title").startswith(f"tiny (#{ids[1]}) —")
    # the list answers the keyboard (it was mouse-only: Tab went from the token to "new survey name")
    page.focus(f"#survey-list li[data-survey-id='{ids[0]}']")
    page.keyboard.press("Enter")
    page.wait_for_function(f"() => document.querySelector('#survey-title').textContent.startsWith('tiny (#{ids[0]}) —')")
    assert page.evaluate("() => document.activeElement.dataset.surveyId") == str(ids[0])   # focus kept on redraw
    _no_errors(page)


def test_grid_summary_leaves_out_the_thread_count(fake_server, browser_page, tmp_path):  # noqa: F811
    """The grid's summary line began "threads: 2 ·" (report.json's worker thread count) before the
    crossover figures."""
    page = browser_page

    def grid(route):
        g = route.fetch().json()
        g["report"] = {**(g.get("report") or {}), "threads": 2, "grid_rmse_mgal": 0.5}
        route.fulfill(json=g)
    page.route("**/api/surveys/*/grid", grid)
    _open_processed(page, fake_server.url, tmp_path, "grid", "#grid-plot .main-svg")
    text = page.inner_text("#grid-summary")
    assert "grid rmse mgal: 0.5" in text and "threads" not in text, text
    _no_errors(page)


def test_leveling_summary_says_why_and_how_a_survey_was_leveled(fake_server, browser_page):  # noqa: F811
    """Where a flight has no absolute base tie the held-out check of the drift is at p < 0.5 (stage 10):
    the summary says so and why, and says nothing of it where every flight is tied; a drift refused and
    offsets applied instead is said too."""
    page = browser_page
    page.goto(fake_server.url)
    got = page.evaluate("""async () => {
        const m = await import('/js/views/report.js');
        const rep = (tied) => ({warnings: [], leveled: true, report: {crossovers: {status: 'leveled', p_value: 0.004,
            rms_before_mgal: 14.3, rms_after_mgal: 8.44, cross_validation: {rms_before_mgal: 14.3, rms_cv_mgal: 10.33,
            p_value: 0.084, n_folds: 10, significance: tied ? 0.05 : 0.5, absolute_base_tie: tied}}}});
        const offsets = rep(true);
        offsets.report.crossovers.refused_drift = {degree: 1, status: 'not leveled: the drift model is not significant at the crossovers (F-test p = 0.034 > 0.01)'};
        return {untied: m.summary(rep(false)).textContent, tied: m.summary(rep(true)).textContent,
                offsets: m.summary(offsets).textContent};
    }""")
    assert ("held-out lines' crossovers 14.3 → 10.33 mGal, p = 0.084 < 0.5, the check where a flight has no absolute "
            "base tie: it keeps its own reading offset, so the flights differ in level for certain") in got["untied"], got
    assert "p = 0.084); crossover RMS 14.3 → 8.44 mGal" in got["tied"] and "reading offset" not in got["tied"], got
    assert "one offset per flight" not in got["tied"]
    assert ("Leveling applied as one offset per flight — the drift (degree 1) was refused: the drift model is not "
            "significant at the crossovers (F-test p = 0.034 > 0.01) — (F-test p = 0.004") in got["offsets"], got
    _no_errors(page)
