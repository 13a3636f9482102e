"""What an analyst walking through the application met (test pipeline): a filter job started from the
recognition map shows up in the survey list and on the Processing tab; the EM table says which EM run
(model order, or the stored identification) each row belongs to; the profile names the states it
shades; the report's model choice reads as a table and says why the adaptive estimate beat FIR."""

from __future__ import annotations

import pytest

from .test_analyst_ui import _open_processed, fake_pipeline_server

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
