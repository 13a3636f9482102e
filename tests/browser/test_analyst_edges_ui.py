"""The analyst off the happy path in Chromium (test pipeline): typed nonsense in the profile's and the
grid's number fields is said in place (no unhandled 422), Back/Forward walk the tabs, plots drawn at one
window size fit another when their tab is shown again, and the jobs table follows a running job."""

from __future__ import annotations

import pytest

from .test_analyst_ui import _processed_survey, _tab, fake_server  # noqa: F401  (fixture)

pytestmark = [pytest.mark.browser]


def _no_errors(page):
    assert not [e for e in page.errors if "favicon" not in e], page.errors


def test_profile_lowpass_rejects_nonsense(fake_server, browser_page, tmp_path):  # noqa: F811
    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    page.goto(f"{fake_server.url}/#survey={sid}&tab=profile")
    page.wait_for_selector("#profile-plot[data-line] .main-svg", timeout=20000)
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
