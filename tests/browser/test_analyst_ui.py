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
@pytest.fixture
def fake_server(tmp_path, monkeypatch):
    from app.web.main import create_app
    from app.web.settings import Settings
    from tests.web.conftest import FAKE_ENTRY

    from .conftest import LiveServer
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "0.01")
    app = create_app(Settings(data_dir=tmp_path / "data", poll_interval_s=0.1, pipeline_entry=FAKE_ENTRY))
    with LiveServer(app) as srv:
        yield srv


def _processed_survey(url: str, tmp_path, name="tiny") -> int:
    import httpx

    from tests.web.conftest import make_tiny_survey, zip_dir
    z = zip_dir(make_tiny_survey(tmp_path / name, name=name))
    with httpx.Client(base_url=url, timeout=30) as c:
        sid = c.post("/api/surveys/import", files={"file": (f"{name}.zip", z, "application/zip")}).json()["id"]
        _run(c, sid)
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
    assert "Leveling NOT applied" in summary and "F-test p = 0.269" in summary
    assert "adaptive (final) estimate is the least repeatable (3.73 mGal)" in summary
    assert "Model choice: adaptive" in summary
    assert page.locator("#report-warnings li").count() == 2
    assert page.locator("#report-repeat-table span.worst").inner_text() == "3.73"
    assert page.locator("#report-diff-table tbody tr").count() == 3
    assert page.locator("#report-crossover-table tbody tr").count() == 1
    assert page.locator("#report-em-selection tr.chosen").inner_text().startswith("2x1")
    assert page.locator("#report-noise-candidates tbody tr").count() == 2
    for key in ("base_ties", "time_offsets", "lag_check", "spike_repair", "crossovers", "noise_model", "model_order",
                "model_choice", "future_section", "counts"):
        assert page.locator(f"#report-sec-{key}").count() == 1, key
    assert "stood down" not in page.inner_text("#report-sec-spike_repair") and "repaired" in page.inner_text("#report-sec-spike_repair")
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
