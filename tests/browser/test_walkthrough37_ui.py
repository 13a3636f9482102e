"""An analyst's walkthrough (session 37) in Chromium (test pipeline), with the server's answers
altered where a case needs them: a result without a grid offers no grid files and says why; a
result older than the survey's settings is said above every result view; a refused job submit
(409: one is running) stays on screen instead of being wiped by the job box's redraw."""

from __future__ import annotations

import json
import time

import pytest
from playwright.sync_api import Error as PlaywrightError

from .test_analyst_ui import _processed_survey, _tab, fake_pipeline_server, fake_server  # noqa: F401  (fixture)

pytestmark = [pytest.mark.browser]

NO_GRID = ("gridding: the lines span less than two grid cells in one direction: no map to grid "
           "(grid files not written)")


def _no_errors(page):
    assert not [e for e in page.errors if "favicon" not in e and "409" not in e], page.errors


def test_a_result_without_a_grid_offers_no_grid_files(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)

    def no_grid(route):
        body = route.fetch().json()
        rep = body.setdefault("report", {})
        rep.setdefault("products", {})["grids"] = {"free_air": None, "bouguer": None, "free_air_flight_height": None}
        body["warnings"] = list(body.get("warnings", [])) + [NO_GRID]
        rep["warnings"] = list(rep.get("warnings", [])) + [NO_GRID]
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    page.route(f"**/api/surveys/{sid}/report", no_grid)
    page.goto(f"{fake_server.url}/#survey={sid}&tab=export")
    page.wait_for_selector("#export-grid-missing", timeout=20000)
    assert "grid files not written" in page.inner_text("#export-grid-missing")
    assert page.query_selector("#export-geotiff") is None and page.query_selector("#export-parquet") is not None
    _no_errors(page)


def test_an_outdated_result_is_said_above_the_result_views(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)

    def outdated(route):
        if route.request.method != "GET":
            return route.continue_()
        body = route.fetch().json()
        for s in body if isinstance(body, list) else [body]:
            s["result_outdated"] = True
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    page.route("**/api/surveys", outdated)
    page.goto(f"{fake_server.url}/#survey={sid}&tab=grid")
    page.wait_for_selector("#outdated-banner:not([hidden])", timeout=20000)
    assert "run processing again" in page.inner_text("#outdated-banner")
    _tab(page, "qc")
    page.wait_for_selector("#outdated-banner[hidden]", state="attached", timeout=5000)
    _tab(page, "export")
    page.wait_for_selector("#outdated-banner:not([hidden])", timeout=5000)
    _no_errors(page)


def test_a_refused_submit_stays_on_screen(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    detail = "job 6 is still running on this survey; cancel it or wait"

    def busy(route):
        if route.request.method == "POST":
            return route.fulfill(status=409, content_type="application/json", body=json.dumps({"detail": detail}))
        return route.continue_()

    page.route(f"**/api/surveys/{sid}/jobs", busy)
    page.goto(f"{fake_server.url}/#survey={sid}&tab=process")
    page.wait_for_selector("#run-job:not([disabled])", timeout=20000)
    page.click("#run-job")
    page.wait_for_selector("#submit-msg .error:not([hidden])", timeout=5000)
    time.sleep(1.5)                     # the job box is redrawn every 0.5 s while a job is watched
    assert detail in page.inner_text("#submit-msg")
    # refused because a job started elsewhere (another tab): that job is shown and watched here, not
    # "No job yet" beside "job N is still running"
    jid = page.evaluate(f"async () => (await (await fetch('/api/surveys/{sid}')).json()).last_job.id")

    def running(route):
        if route.request.method != "GET":
            return route.continue_()
        try:
            body = route.fetch().json()
        except PlaywrightError:          # the page closed under a poll in flight (teardown)
            return None
        for s in body:
            if s["id"] == sid:
                s["last_job"]["status"] = "running"
        route.fulfill(status=200, content_type="application/json", body=json.dumps(body))

    page.route("**/api/surveys", running)
    with page.expect_request(lambda r: r.url.endswith(f"/api/jobs/{jid}"), timeout=10000):
        page.click("#run-job")
    page.wait_for_selector("#job-status", timeout=5000)
    page.unroute("**/api/surveys", running)
    _no_errors(page)
