"""Browser side of the hardening issue (item 10): under the CSP the page works and writes through
its own origin, a survey name made of markup is shown as text in the page and in Plotly's titles
(no live link), and another site cannot make the analyst's browser change anything."""

from __future__ import annotations

import pytest

from tests.web.conftest import make_tiny_survey

from .conftest import SCREENSHOTS

pytestmark = [pytest.mark.browser]

HOSTILE = '<a href="https:&#47;&#47;evil.example">click<b>me'


def test_names_are_text_and_page_works_under_csp(live_server, browser_page, tmp_path):
    page = browser_page
    tiny = make_tiny_survey(tmp_path / "tiny")
    page.goto(live_server.url)
    page.wait_for_selector("text=Select or import a survey")
    # create a survey and upload a flight through the page (same-origin writes under the CSP)
    page.fill("#new-survey input[name=name]", HOSTILE)
    page.click("#new-survey button")
    page.wait_for_selector("#flight-upload:not([hidden])")
    page.fill("#flight-form input[name=flight]", "F1")
    page.set_input_files("#flight-form input[name=gravimeter]", str(tiny / "flights" / "f1" / "gravimeter.csv"))
    page.set_input_files("#flight-form input[name=gnss]", str(tiny / "flights" / "f1" / "gnss.csv"))
    lines = tmp_path / "lines.csv"
    lines.write_text("line,t_start,t_end,kind\nL1,1010,1140,main\nL2,1150,1280,main\n")
    page.set_input_files("#flight-form input[name=lines]", str(lines))
    page.click("#flight-form button[type=submit]")
    page.wait_for_selector("#qc-flights td:has-text('F1')", timeout=30000)
    page.wait_for_selector("#line-map .main-svg .gtitle", timeout=30000)
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SCREENSHOTS / "hostile-name.png"), full_page=True)
    title = page.text_content("#line-map .gtitle")
    assert title.startswith(HOSTILE), title  # exactly the name, entities included
    assert page.locator("#line-map a").count() == 0 and page.locator("a[href*='evil']").count() == 0
    assert page.locator("#survey-list li span").first.inner_text() == HOSTILE
    assert page.inner_text("#survey-title").startswith(HOSTILE)
    assert not page.errors, page.errors  # no CSP violation, no failed request

    # another site posting to the API through this browser is refused, nothing changes
    n = len(page.evaluate("() => fetch('/api/surveys').then(r => r.json())"))
    evil = page.context.new_page()
    evil.set_content(f"""<form id=f method=post action="{live_server.url}/api/surveys/import"
                         enctype="multipart/form-data"><input name=file type=file></form>""")
    with evil.expect_response(lambda r: "/api/surveys/import" in r.url) as resp:
        evil.evaluate("document.getElementById('f').submit()")
    assert resp.value.status == 403
    assert len(page.evaluate("() => fetch('/api/surveys').then(r => r.json())")) == n
