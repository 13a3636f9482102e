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
