"""The analyst's workflow in Chromium (issue items 2–6) on a survey processed by the test
pipeline (``tests.web.fake_pipeline``, which writes a report shaped like the real one): the report
panel, the survey metadata editor and deleting a survey, maps and profiles, exports, and the API
pages working offline.  Screenshots go to the test's tmp_path (``screenshots/``)."""

from __future__ import annotations

from urllib.parse import urlsplit

import pytest

pytestmark = [pytest.mark.browser]


@pytest.fixture
def shots(tmp_path):
    d = tmp_path / "screenshots"
    d.mkdir()
    return lambda page, name: page.screenshot(path=str(d / name), full_page=True)


def test_api_docs_work_offline_under_the_csp(live_server, browser_page, shots):
    page = browser_page
    requests, finished, failed = [], [], []
    page.on("request", lambda r: requests.append(r.url))
    page.on("requestfinished", lambda r: finished.append(r.url))
    page.on("requestfailed", lambda r: failed.append((r.url, r.failure)))
    page.goto(live_server.url + "/docs")
    page.wait_for_selector(".swagger-ui .info .title:has-text('Aerograv')", timeout=20000)
    page.wait_for_selector(".opblock-tag-section", timeout=20000)
    shots(page, "docs-swagger.png")
    hosts = {urlsplit(u).hostname for u in requests if u.startswith("http")}
    assert hosts == {"127.0.0.1"}, hosts   # Swagger UI asks nothing of another host
    assert not page.errors, page.errors   # no CSP violation, no failed request
    page.goto(live_server.url + "/redoc")
    page.wait_for_selector("h1:has-text('Aerograv')", timeout=20000)
    page.wait_for_selector(".menu-content label", timeout=20000)
    shots(page, "docs-redoc.png")
    # ReDoc's footer logo points at its CDN: the CSP keeps it from loading (the logo hides itself)
    assert {urlsplit(u).hostname for u in finished if u.startswith("http")} == {"127.0.0.1"}, finished
    assert all(f == "csp" for u, f in failed if urlsplit(u).hostname != "127.0.0.1"), failed
    assert all("logo-mini.svg" in e for e in page.errors), page.errors


# ---------------------------------------------------------------- a processed survey (test pipeline)
def fake_pipeline_server(tmp_path, monkeypatch, delay_s: float):
    """A live server running the test pipeline, each stage taking ``delay_s`` (a context manager)."""
    from app.web.main import create_app
    from app.web.settings import Settings
    from tests.web.conftest import FAKE_ENTRY

    from .conftest import LiveServer
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", str(delay_s))
    app = create_app(Settings(data_dir=tmp_path / "data", poll_interval_s=0.1, pipeline_entry=FAKE_ENTRY))
    return LiveServer(app)


@pytest.fixture
def fake_server(tmp_path, monkeypatch):
    with fake_pipeline_server(tmp_path, monkeypatch, 0.01) as srv:
        yield srv


def _processed_survey(url: str, tmp_path, name="tiny") -> int:
    import httpx

    from tests.web.conftest import make_tiny_survey, zip_dir
    z = zip_dir(make_tiny_survey(tmp_path / name, name=name))
    with httpx.Client(base_url=url, timeout=30) as c:
        sid = c.post("/api/surveys/import", files={"file": (f"{name}.zip", z, "application/zip")}).json()["id"]
        _run(c, sid)
    return sid


def _open_processed(page, url: str, tmp_path, tab: str, ready: str, timeout: int = 30000) -> int:
    """A processed tiny survey opened in the browser on ``tab``, once ``ready`` (a selector) is
    on the page; returns the survey id."""
    sid = _processed_survey(url, tmp_path)
    page.goto(f"{url}/#survey={sid}&tab={tab}")
    page.wait_for_selector(ready, timeout=timeout)
    return sid


def _run(c, sid):
    import time
    job = c.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    t_end = time.monotonic() + 30
    while c.get(f"/api/jobs/{job['id']}").json()["status"] in ("queued", "running"):
        assert time.monotonic() < t_end
        time.sleep(0.1)
    assert c.get(f"/api/jobs/{job['id']}").json()["status"] == "succeeded"


def _tab(page, name):
    page.click(f"#tabs button[data-tab={name}]")


def test_report_panel_settings_and_delete(fake_server, browser_page, tmp_path, shots):
    import httpx

    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    page.goto(f"{fake_server.url}/#survey={sid}&tab=report")
    page.wait_for_selector("#report-summary li", timeout=20000)
    summary = page.inner_text("#report-summary")
    assert "RELATIVE — no absolute base tie" in summary
    assert "Leveling NOT applied" in summary and "does not predict held-out lines' crossovers" in summary
    # the leave-one-line-out evidence is shown beside the F-test
    cv_row = page.inner_text("#report-leveling-cv tbody tr")
    assert "1.31" in cv_row and "0.83" in cv_row
    assert "adaptive (final) estimate is the least repeatable (3.73 mGal)" in summary
    # no crossovers: the repeat passes leveled against each other, said in words and in a table
    assert ("Repeat track R1: its 3 passes leveled against each other (no crossovers) — mean corrections "
            "-0.69 to 0.81 mGal (F-test p = 0.002); their mean level is kept.") in summary
    rl = page.inner_text("#report-repeat-leveling tbody tr")
    assert "leveled" in rl and "13 × 3" in rl and "1.16 → 0.62" in rl and "R1-1 0.81" in rl
    assert "adaptive before leveling 4.02 mGal" in page.inner_text("#report-sec-repeat_lines")
    # why FIR: the guard's evidence, both tests
    assert ("Model choice: FIR (anomaly order m = 2, blended with m = 1 at weight 0.296 — the least crossover mean "
            "square once the flights' drift is removed (RMS 4.53 mGal against 4.58 for m = 2 and 4.8 for m = 1 alone)) "
            "— the adaptive estimate disagrees "
            "more at the 30 crossovers "
            "than FIR 100 s (RMS 48.5 against 21.9 mGal; t-test p = 0.104, signed ranks p = 0.002)") in summary
    assert page.locator("#report-warnings li").count() == 2
    assert page.locator("#report-repeat-table span.worst").inner_text() == "3.73"
    assert page.locator("#report-diff-table tbody tr").count() == 3
    assert page.locator("#report-crossover-table tbody tr").count() == 1
    assert page.locator("#report-em-selection tr.chosen").inner_text().startswith("2x1")
    # where each level was learned and where it is applied: the emptied level, and the level it is filtered with
    flagged = page.locator("#report-level-support tr.flagged")
    assert flagged.count() == 1
    cells = flagged.locator("td")
    assert cells.nth(1).inner_text() == "0.353" and cells.nth(2).inner_text() == "0.062"
    assert cells.nth(3).inner_text() == "1 %" and cells.nth(4).inner_text() == "54 %"
    assert cells.last.inner_text() == "emptied by its EM: its level at iteration 14 used"
    assert page.locator("#report-noise-candidates tbody tr").count() == 2
    fam = page.inner_text("#report-family-crossovers")
    assert fam.startswith("Family checked at the crossovers against white velocity: white velocity used instead of "
                          "coloured height — crossover RMS 7.06 (coloured height) against 5.87 mGal (white velocity) "
                          "at 30, p = 0.023 (t-test), 0.002 (signed ranks)")
    # the noise episodes: where on which line, how far above the typical level, the std there and elsewhere
    ep = page.locator("#report-noise-episodes tbody tr")
    assert ep.count() == 1
    assert ep.first.inner_text().split("\t") == ["L1", "f1", "0.5–1.8", "226.5", "18.8", "13.7", "7.75", "3.78"]
    # the time stamps and the noise family's check against the FIR differences, with their evidence
    offsets = page.locator("#report-time-offsets tbody tr")
    assert "\t1.9\t" in offsets.nth(0).inner_text() and offsets.nth(0).locator("td").nth(-2).inner_text() == "yes"
    # a gravimeter slower than the GNSS: its motion cancelled at its samples on the first flight, not the second
    assert offsets.nth(0).locator("td").last.inner_text() == (
        "yes (z's RMS at 0.01–0.02 Hz: 16.8 plain, 11.9 cancelled, mGal)")
    if offsets.count() > 1:
        assert offsets.nth(1).locator("td").last.inner_text().startswith("no (z's RMS")
    assert "\t0.01–0.4\t" in offsets.nth(0).inner_text()        # the band the accelerations were compared in
    # the gravimeter's clock: re-timed on the first flight (a drift and a jump), one offset on the others
    assert offsets.nth(0).locator("td").nth(9).inner_text() == (
        "re-timed: runs 18.6 ppm fast, set 0.197 s forward at 13880.65 s (14 windows), 96 % of the residual removed")
    if offsets.count() > 1:
        assert offsets.nth(1).locator("td").nth(9).inner_text() == "one offset (12 windows) — one offset fits every window"
    assert page.locator("#report-gnss-filled tbody tr").first.locator("td").last.inner_text() == "2"
    assert page.locator("#report-gravimeter-filled tbody tr").first.locator("td").last.inner_text() == "7"
    fc = page.inner_text("#report-family-check")
    assert fc.startswith("Coloured velocity checked against the FIR differences: changed — 21 differences")
    vb = page.inner_text("#report-velocity-bound")
    assert vb.startswith("Velocity error bounded by the GNSS heights: refitted — the free fit put 15.0")
    assert "after: 2.691" in vb and "0.972" in vb
    assert "refuted by the heights (2.691× the misfit, p = 0.0035): the shape as fitted kept (1.202×" in vb
    assert page.inner_text("#report-anomaly-rolloff").startswith(
        "Anomaly in the fit: random walk of order 2 × exp(−β f), β = 148.9 s")
    lag = page.locator("#report-lag-check tbody tr").first.locator("td")
    assert lag.last.inner_text().startswith("the flights' time offsets read as a lag (τ = 2.050 s)")
    assert lag.nth(2).inner_text() == "not used (first fit Δτ -0.4 ± 1.1 ms)"
    bd = page.locator("#report-band-delay tbody tr").first.locator("td")
    assert [bd.nth(i).inner_text() for i in range(6)] == ["18.1", "0.34", "52.7", "0.01–0.05", "59.64 → 24.08", "yes"]
    assert bd.last.inner_text().startswith("the gravimeter is 18.1 ms late against the GNSS")
    assert page.inner_text("#report-band-delay-agree").startswith("Each flight's own delay: they agree (χ² 0.23 on 2")
    rows = page.locator("#report-band-delay-flights tbody tr")
    assert rows.count() == 3
    assert [rows.nth(1).locator("td").nth(i).inner_text() for i in (0, 1, 4)] == ["F02", "18.3", "pooled (18.1 ms)"]
    assert page.inner_text("#report-common-level").startswith(
        "Common level of the 3 flights: their offsets at 12 crossovers spread by 4.33 mGal, so their mean — the level "
        "leveling keeps — is uncertain by 2.5 mGal; included in δg's std and the grid std")
    assert page.locator("#report-common-level-offsets tbody tr").count() == 3
    rw = page.locator("#report-response-width tbody tr").first.locator("td")
    assert [rw.nth(i).inner_text() for i in range(4)] == ["0.0136", "6.0e-5", "72.8 %", "yes"]
    rwf = page.locator("#report-response-width-flights tbody tr")
    assert rwf.count() == offsets.count() and rwf.first.locator("td").nth(1).inner_text() == "0.0136"
    for key in ("base_ties", "time_offsets", "response_width", "lag_check", "band_delay", "spike_repair", "crossovers", "noise_model", "model_order",
                "model_choice", "future_section", "counts"):
        assert page.locator(f"#report-sec-{key}").count() == 1, key
    assert "stood down" not in page.inner_text("#report-sec-spike_repair") and "repaired" in page.inner_text("#report-sec-spike_repair")
    assert "1 height spike(s) and 1 height step(s): spike 20 cm at 1234.5 s; step -5 cm at 1300 s" in \
        page.inner_text("#report-sec-spike_repair")
    # a section the page does not know: shown generically, its JSON one click away, markup as text
    sec = page.locator("#report-sec-future_section")
    assert "<b>not markup</b>" in sec.inner_text() and sec.locator("b").count() == 0
    sec.locator("details.json summary").click()
    assert '"value": 1' in sec.locator("details.json pre").inner_text()
    shots(page, "report.png")

    # the profile legend does not claim leveling that was not applied
    _tab(page, "profile")
    page.wait_for_selector("#profile-plot[data-line] .main-svg", timeout=20000)
    legend = page.text_content("#profile-plot .legend")
    assert "not leveled" in legend and "(final, leveled)" not in legend
    assert page.locator("#profile-not-leveled").count() == 1
    # the report's noise episode on this line: outlined over its km, in the legend and the status line
    assert page.get_attribute("#profile-plot", "data-line") == "L1"
    shapes = page.evaluate("() => document.querySelector('#profile-plot').layout.shapes"
                           ".filter((s) => s.name === 'noise-episode').map((s) => [s.x0, s.x1])")
    assert shapes == [[0.5, 1.8]]
    assert "noise episode: R(t) over 4× its typical level" in legend
    assert "noise episode (dashed): 0.5–1.8 km, R up to 18.8× typical" in page.inner_text("#profile-status")
    # the grid title says the level is relative
    _tab(page, "grid")
    page.wait_for_selector("#grid-plot .main-svg .gtitle", timeout=20000)
    assert "relative level (no absolute base tie)" in page.text_content("#grid-plot .gtitle")

    # settings: a bad value is refused in place (field named, marked); good values are saved
    _tab(page, "settings")
    page.wait_for_selector("#settings-form")
    assert page.input_value("[name='gravimeter.tau_s']") == "0"
    page.fill("[name='gravimeter.tau_s']", "-1")
    page.click("#settings-save")
    page.wait_for_selector("#view-settings .error:visible")
    assert "gravimeter.tau_s" in page.inner_text("#view-settings .error")
    assert page.locator("[name='gravimeter.tau_s'].invalid").count() == 1
    page.errors.clear()   # the 422 above is expected
    page.fill("[name='gravimeter.tau_s']", "2")
    page.fill("[name='gravimeter.base_gravity_mgal']", "982316.4")
    page.fill("[name='survey.name']", "Block A")
    page.click("#settings-save")
    page.wait_for_function("() => document.querySelector('#settings-status') && document.querySelector('#settings-status').dataset.saved")
    assert "run processing again" in page.inner_text("#settings-status")
    page.wait_for_selector("#survey-list li.active:has-text('Block A')")
    assert page.input_value("[name='gravimeter.base_gravity_mgal']") == "982316.4"
    shots(page, "settings.png")
    with httpx.Client(base_url=fake_server.url) as c:
        s = c.get(f"/api/surveys/{sid}").json()
        assert s["settings"]["gravimeter"]["tau_s"] == 2.0 and s["result_outdated"]
        _run(c, sid)   # the job reads the new survey.toml: now the base tie is absolute
    page.reload()
    _tab(page, "grid")
    page.wait_for_selector("#grid-plot .main-svg .gtitle", timeout=20000)
    assert "relative level" not in page.text_content("#grid-plot .gtitle") and page.locator("#grid-relative").count() == 0
    _tab(page, "report")
    page.wait_for_selector("#report-summary li", timeout=20000)
    assert "Base level: absolute" in page.inner_text("#report-summary")

    # a survey built from a flight upload: the flight is named as lines.csv names it
    from tests.web.conftest import make_tiny_survey
    tiny = make_tiny_survey(tmp_path / "upload")
    page.fill("#new-survey input[name=name]", "Block B")
    page.click("#new-survey button")
    page.wait_for_selector("#survey-list li.active:has-text('Block B')")
    page.wait_for_selector("#flight-upload:not([hidden])")
    page.set_input_files("#flight-form input[name=gravimeter]", str(tiny / "flights" / "f1" / "gravimeter.csv"))
    page.set_input_files("#flight-form input[name=gnss]", str(tiny / "flights" / "f1" / "gnss.csv"))
    lines = tmp_path / "lines-f01.csv"
    lines.write_text("line,flight,t_start,t_end,kind\nB1,F01,1010,1140,main\nB2,F01,1150,1280,main\n")
    page.set_input_files("#flight-form input[name=lines]", str(lines))
    page.click("#flight-form button[type=submit]")
    _tab(page, "qc")
    page.wait_for_selector("#qc-flights td:has-text('F01')", timeout=20000)

    # delete it from the settings tab (after the confirmation)
    n = page.locator("#survey-list li").count()
    _tab(page, "settings")
    page.wait_for_selector("#survey-delete")
    page.once("dialog", lambda d: d.accept())
    page.click("#survey-delete")
    page.wait_for_function(f"() => document.querySelectorAll('#survey-list li').length === {n - 1}")
    assert page.locator("#survey-list li:has-text('Block B')").count() == 0
    assert page.locator("#survey-list li.active:has-text('Block A')").count() == 1
    assert not page.errors, page.errors


def _click_line_on_map(page, plot_sel, line, axis="x"):
    """Click, with the mouse, the pixel where the plot draws the first point of ``line``'s track."""
    xy = page.evaluate("""([sel, line, ax]) => {
        const gd = document.querySelector(sel);
        const tr = gd.data.find((t) => t.mode === 'lines' && t.customdata && t.customdata[0] === line
                                        && (t.xaxis || 'x') === ax);
        const i = Math.floor(tr.x.length / 2);
        const fl = gd._fullLayout, xa = fl[ax === 'x' ? 'xaxis' : 'xaxis2'], ya = fl[ax === 'x' ? 'yaxis' : 'yaxis2'];
        const box = gd.querySelector('.main-svg').getBoundingClientRect();
        return [box.left + xa._offset + xa.l2p(tr.x[i]), box.top + ya._offset + ya.l2p(tr.y[i])];
    }""", [plot_sel, line, axis])
    page.mouse.move(xy[0], xy[1])
    page.mouse.click(xy[0], xy[1])


def _open_profile_from_map(page, plot_sel, line, axis="x", attempts=3):
    """Click ``line`` on the map until its profile opens: the pixel is read from the plot's
    current layout at each attempt — on a cold, busy browser the first click can land while
    Plotly is still laying out the maps just drawn (seen once on a fresh 2-core checkout)."""
    want = f"() => document.querySelector('#profile-plot') && document.querySelector('#profile-plot').dataset.line === '{line}'"
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    for k in range(attempts):
        _click_line_on_map(page, plot_sel, line, axis)
        try:
            page.wait_for_function(want, timeout=8000)
            return
        except PlaywrightTimeout:
            if k == attempts - 1:
                raise


def test_maps_profiles_em_and_exports(fake_server, browser_page, tmp_path, shots):
    import numpy as np

    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    page.goto(f"{fake_server.url}/#survey={sid}&tab=grid")
    page.wait_for_selector("#grid-plot[data-variable] .main-svg", timeout=20000)
    # diverging scale, symmetric robust limits, white at the centre: the median of the grid on this
    # survey without a base tie (its level is relative), so the map is not one colour
    zmin, zmax = float(page.get_attribute("#grid-plot", "data-zmin")), float(page.get_attribute("#grid-plot", "data-zmax"))
    centre = float(page.get_attribute("#grid-plot", "data-centre"))
    z = np.array(page.evaluate("() => document.querySelector('#grid-plot').data[0].z.flat()"), dtype=float)
    assert centre == pytest.approx(np.nanmedian(z), abs=0.5) and (zmin + zmax) / 2 == pytest.approx(centre)
    assert zmax > centre and "white at" in page.inner_text("#grid-limits") and "median" in page.inner_text("#grid-limits")
    cs = page.evaluate("() => document.querySelector('#grid-plot').data[0].colorscale")
    mid = next(c for p, c in cs if abs(p - 0.5) < 1e-9)
    assert mid == "#f7f7f7"
    assert page.locator("#grid-plot .textpoint").count() == 3           # line labels L1, L2, T1
    shots(page, "grid-default.png")
    # own limits: white stays at the centre
    lo, hi = centre - 5.0, centre + 15.0
    page.fill("#grid-zmin", repr(lo))
    page.fill("#grid-zmax", repr(hi))
    page.dispatch_event("#grid-zmax", "change")
    page.wait_for_function(f"() => +document.querySelector('#grid-plot').dataset.zmax === {hi!r}")
    cs = page.evaluate("() => document.querySelector('#grid-plot').data[0].colorscale")
    assert [c for p, c in cs if abs(p - 0.25) < 1e-6] == ["#f7f7f7"]   # (centre − lo) / 20
    # hillshade layer
    page.check("#grid-hillshade")
    page.wait_for_function("() => document.querySelector('#grid-plot').dataset.hillshade === '1'")
    assert page.evaluate("() => document.querySelector('#grid-plot').data.some((t) => t.name === 'hillshade')")
    shots(page, "grid-hillshade.png")
    # δg and σ side by side
    page.select_option("#grid-var", "both")
    page.wait_for_function("() => document.querySelector('#grid-plot').dataset.variable === 'both'")
    assert page.locator("#grid-plot .colorbar").count() == 2 and page.locator("#grid-plot .xy2").count() + \
        page.locator("#grid-plot .x2y2").count() >= 1
    shots(page, "grid-side-by-side.png")
    # a click on line L2 in the σ map opens its profile
    _open_profile_from_map(page, "#grid-plot", "L2", axis="x2")
    assert page.locator("#tabs button.active").inner_text() == "Line profiles"
    # the profile shows adaptive − FIR and σ in their own panel
    names = page.evaluate("() => document.querySelector('#profile-plot').data.map((t) => t.name)")
    assert "adaptive − FIR" in names and "± σ (adaptive)" in names
    text = page.text_content("#profile-plot")
    assert "adaptive − FIR, σ (mGal)" in text
    assert "adaptive − FIR: RMS" in page.inner_text("#profile-status")
    shots(page, "profile-L2.png")

    # recognition map: a click on a point opens its line's profile
    page.click("#tabs button[data-tab=recognition]")
    page.wait_for_selector("#rec-map[data-signature]", timeout=20000)
    legend = page.text_content("#rec-map .legend")
    assert "state 0 (Q0, R0)" in legend and "state 1 (Q1, R0)" in legend
    xy = page.evaluate("""() => {
        const gd = document.querySelector('#rec-map'), t = gd.data[0];
        const i = t.customdata.indexOf('T1');
        const fl = gd._fullLayout, box = gd.querySelector('.main-svg').getBoundingClientRect();
        return [box.left + fl.xaxis._offset + fl.xaxis.l2p(t.x[i]), box.top + fl.yaxis._offset + fl.yaxis.l2p(t.y[i])];
    }""")
    page.mouse.move(*xy)
    page.mouse.click(*xy)
    page.wait_for_function("() => document.querySelector('#profile-plot').dataset.line === 'T1'", timeout=20000)

    # the QC line map too
    page.click("#tabs button[data-tab=qc]")
    page.wait_for_selector("#line-map .main-svg", timeout=20000)
    _open_profile_from_map(page, "#line-map", "L1")

    # EM table: states counted from 0 with their (Q, R), the full transition matrix of the final iteration
    page.click("#tabs button[data-tab=process]")
    page.wait_for_selector("#em-detail", timeout=20000)
    head = page.inner_text("#em-table thead")
    assert "Q0 (mGal² per step)" in head and "R0 ((cm/s)²)" in head and "stay s1 (Q1, R0)" in head and "Q2" not in head
    assert page.get_attribute("#em-detail", "data-iteration") == "2" and "Final iteration 2" in page.inner_text("#em-detail")
    assert page.locator("#em-transition tbody tr").count() == 2 and page.locator("#em-transition tbody td").count() == 6
    assert page.locator("#em-states tbody tr").count() == 2
    assert [c.strip() for c in page.inner_text("#em-transition tbody tr:first-child").split("\t")] == ["s0 (Q0, R0)", "0.98", "0.02"]
    page.click(".em-row[data-index='0']")
    page.wait_for_function("() => document.querySelector('#em-detail').dataset.iteration === '0'")
    shots(page, "em-table.png")

    # exports from the page: netCDF and the XYZ line data, read back
    page.click("#tabs button[data-tab=export]")
    page.wait_for_selector("#export-xyz")
    got = {}
    for fmt in ("netcdf", "xyz", "geotiff"):
        with page.expect_download() as dl:
            page.click(f"#export-{fmt}")
        got[fmt] = tmp_path / dl.value.suggested_filename
        dl.value.save_as(got[fmt])
    import rasterio
    import xarray as xr

    from app.io.xyz import scan_xyz
    with xr.open_dataset(got["netcdf"]) as ds, rasterio.open(got["geotiff"]) as t:
        assert ds.x.attrs["units"] == "m"
        assert float(ds.x.min()) - t.res[0] / 2 == pytest.approx(t.bounds.left)
        assert float(ds.y.max()) + t.res[1] / 2 == pytest.approx(t.bounds.top)
    scan = scan_xyz(got["xyz"])
    assert [b.line_id for b in scan.blocks] == ["L1", "L2", "T1"]
    x = np.array([float(r.split()[0]) for r in scan.data_lines])
    assert 30_000 < x.max() - x.min() < 50_000   # the ~38 km of the test lines in metres, not km
    assert not page.errors, page.errors


def test_apply_h_rho_starts_a_filter_job(fake_server, browser_page, tmp_path, shots):
    """The recognition map opens on the result's own (h, ρ); "Apply h, ρ" starts a filter job
    with the values on the sliders."""
    import time

    import httpx

    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    page.goto(f"{fake_server.url}/#survey={sid}&tab=recognition")
    page.wait_for_selector("#rec-map .main-svg", timeout=20000)
    page.eval_on_selector("#rec-h", "(e) => { e.value = 1.2; e.dispatchEvent(new Event('input', {bubbles: true})); }")
    page.eval_on_selector("#rec-rho", "(e) => { e.value = 6; e.dispatchEvent(new Event('input', {bubbles: true})); }")
    page.wait_for_function("() => document.querySelector('#rec-map').dataset.h === '1.2'", timeout=10000)
    assert page.is_visible("#rec-preview") and "current result was made with" in page.inner_text("#rec-preview")
    page.click("#rec-apply")
    page.wait_for_selector("#rec-apply-note[data-job]", timeout=10000)
    shots(page, "recognition-apply.png")
    jid = int(page.get_attribute("#rec-apply-note", "data-job"))
    with httpx.Client(base_url=fake_server.url, timeout=30) as c:
        job = c.get(f"/api/jobs/{jid}").json()
        assert job["kind"] == "filter" and job["params"]["nlmeans_h_per_km"] == 1.2
        assert job["params"]["nlmeans_rho_km"] == 6
        t_end = time.monotonic() + 30
        while c.get(f"/api/jobs/{jid}").json()["status"] in ("queued", "running"):
            assert time.monotonic() < t_end
            time.sleep(0.1)
        assert c.get(f"/api/jobs/{jid}").json()["status"] == "succeeded"


def test_short_lines_motion_compensation_shows_its_figures(tmp_path, monkeypatch, browser_page):
    # lines too short for the usual comparison of the plain and the motion-cancelled means: the
    # report shows the short-line comparison's figures (50 s edges) that decided
    monkeypatch.setenv("AEROGRAV_FAKE_SHORT_LINES", "1")
    with fake_pipeline_server(tmp_path, monkeypatch, 0.01) as srv:
        page = browser_page
        _open_processed(page, srv.url, tmp_path, "report", "#report-time-offsets tbody tr")
        cell = page.locator("#report-time-offsets tbody tr").first.locator("td").last.inner_text()
        assert cell == "yes (z's RMS at 0.01–0.02 Hz on the short lines, 50 s edges: 31.8 plain, 12 cancelled, mGal)", cell
