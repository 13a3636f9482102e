"""A second analyst walkthrough (test pipeline): the survey list after a cancelled re-run, the labels of
a repeat track's passes on the maps, and the Processing tab in a 700 px wide window."""

from __future__ import annotations

import pytest

from .test_analyst_ui import _processed_survey, fake_server  # noqa: F401  (fixture)

pytestmark = [pytest.mark.browser]


def _no_errors(page):
    assert not [e for e in page.errors if "favicon" not in e], page.errors


def test_a_cancelled_rerun_leaves_the_list_saying_the_result_is_there(fake_server, browser_page, tmp_path,  # noqa: F811
                                                                      monkeypatch):
    """A processed survey run again and the job cancelled: its result is still current and shown, but
    the survey list's badge said "cancelled" (the newest job's status), as if there were no result,
    and the Exports tab named the cancelled job as the result's."""
    import httpx
    sid = _processed_survey(fake_server.url, tmp_path)
    with httpx.Client(base_url=fake_server.url, timeout=30) as c:
        done = c.get(f"/api/surveys/{sid}").json()["last_job"]["id"]
    page = browser_page
    page.goto(f"{fake_server.url}/#survey={sid}&tab=process")
    page.wait_for_selector("#survey-list li.active .badge:has-text('succeeded')", timeout=20000)
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "2")   # the re-run is slow enough to cancel
    page.click("#run-job")
    page.wait_for_selector("#job-status:has-text('running')", timeout=20000)
    page.click("#job-cancel")
    page.wait_for_selector("#job-status:has-text('cancelled')", timeout=10000)
    li = "#survey-list li.active"
    page.wait_for_selector(f"{li} .last-run", timeout=10000)
    assert page.inner_text(f"{li} .badge") == "succeeded"          # the current result, not the newest job
    assert page.inner_text(f"{li} .last-run") == "last run cancelled"
    title = page.get_attribute(f"{li} .badge", "title")
    assert f"result of job {done}" in title and "cancelled" in title, title
    # the result is still there, and said to be the first job's
    page.click("#tabs button[data-tab=export]")
    page.wait_for_selector("#view-export h3", timeout=10000)
    assert page.inner_text("#view-export h3").endswith(f"(job {done})"), page.inner_text("#view-export h3")
    page.click("#tabs button[data-tab=report]")
    page.wait_for_selector("#report-summary li", timeout=10000)
    _no_errors(page)
