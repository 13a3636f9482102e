"""The Report tab reads as a report, not as report.json's keys: the warnings boxed first, sections
labelled in words with their units, numbers rounded, developer references (report.json keys, the
specification's sections) said in the page's words — and nothing lost: every key of report.json in
the "All fields" view and the download (test pipeline's report, a warning added that names a
report.json key, a section the page does not know)."""

from __future__ import annotations

import json
import re

import pytest

from .test_analyst_ui import _processed_survey, fake_pipeline_server, fake_server  # noqa: F401  (fixture)

pytestmark = [pytest.mark.browser]

REFERENCE = ("flight F01: 3 epochs of z flagged as spikes; vu comes from the heights, so they were removed as 1 height "
             "step(s) (report spike_repair.height_outliers)")


def test_report_reads_in_words_and_keeps_every_field(fake_server, browser_page, tmp_path):  # noqa: F811
    import httpx

    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    with httpx.Client(base_url=fake_server.url) as c:
        report = json.loads(c.get(f"/api/surveys/{sid}/export", params={"format": "report"}).content)
    report["warnings"].append(REFERENCE)
    report["level_refinement"] = {"Q_mgal2": [4.43789275973775e-06, 4.655698411061688e-05], "R_local_scale": 1.2248512946530747,
                                  "loglik_gain": 42.123261735308915, "std_level_reason": None}

    def patched(route):
        body = route.fetch().json()
        body["report"], body["warnings"] = report, report["warnings"]
        route.fulfill(json=body)
    page.route(f"**/api/surveys/{sid}/report", patched)
    page.goto(f"{fake_server.url}/#survey={sid}&tab=report")
    page.wait_for_selector("#report-summary li", timeout=20000)

    # the warnings first: boxed above the decisions and every section, each one of report.json's
    order = page.evaluate("""() => [...document.querySelectorAll('#report-warnings-box, #report-summary, .report-section')]
                             .map((e) => e.id)""")
    assert order[:2] == ["report-warnings-box", "report-summary"], order
    shown = page.locator("#report-warnings li").all_inner_texts()
    assert len(shown) == len(report["warnings"])
    # a report.json key in a warning is said as the section that lists it (the whole text in its tooltip)
    assert shown[-1].endswith("1 height step(s) (listed under “GNSS spike repair (velocity spikes; height spikes and steps "
                              "where vu comes from the heights)”)"), shown[-1]
    assert page.locator("#report-warnings li").last.get_attribute("title") == REFERENCE

    # labels in words with units, the raw key in the tooltip; no snake_case name left as a label
    keys = page.evaluate("""() => [...document.querySelectorAll('#view-report .report-section:not(#report-all-fields) .key')]
                            .map((k) => [k.textContent, k.title])""")
    assert keys and not [k for k, _ in keys if re.search(r"[a-z]_[a-z]", k)], keys
    label = dict(keys)
    assert label["Anomaly levels Q (mGal² per step)"] == "report.json key: Q_mgal2"
    assert label["Log-likelihood gain"] == "report.json key: loglik_gain"
    # numbers to 4 significant digits, computed here from the report
    row = lambda sec, text: page.locator(f"#report-sec-{sec} tr:has(th:has-text('{text}')) td").first.inner_text()  # noqa: E731
    assert row("level_refinement", "Anomaly levels Q") == ", ".join(f"{v:.3e}".replace("e-06", "e-6").replace("e-05", "e-5")
                                                                     for v in report["level_refinement"]["Q_mgal2"])
    assert row("level_refinement", "Scale of the local noise level R") == f"{report['level_refinement']['R_local_scale']:.4g}"
    assert row("counts", "GNSS epochs on lines") == str(report["counts"]["epochs"])
    # a section the page has no drawing for: titled and labelled from its key
    assert page.locator("#report-sec-future_section summary h3").inner_text() == "Future section"
    assert "<b>not markup</b>" in page.inner_text("#report-sec-future_section")

    # the stage timings: seconds, share and total from report.json's timings_s
    t = report["timings_s"]
    total = sum(t.values())
    rows = page.locator("#report-timings tbody tr").all_inner_texts()
    assert rows[-1].split("\t")[:2] == ["Total", f"{total:.2f}".rstrip("0").rstrip(".")]
    first = rows[0].split("\t")
    assert first[0] == "Reading the survey" and first[2] == f"{100 * t['ingest'] / total:.1f}".rstrip("0").rstrip(".") + " %"

    # nothing lost: "All fields" holds report.json as written, and the download link is the file
    page.click("#report-all-fields summary")
    assert json.loads(page.inner_text("#report-all-fields pre")) == report
    href = page.get_attribute("#report-download", "href")
    assert href == f"/api/surveys/{sid}/export?format=report"
    # every top-level key has its section, but those the header and the timings carry
    sections = set(page.evaluate("() => [...document.querySelectorAll('.report-section')].map((e) => e.id.replace('report-sec-', ''))"))
    assert set(report) - {"warnings", "survey", "crs", "threads"} <= sections, set(report) - sections
    assert page.locator("#report-nav button").count() == len(sections) - 1   # "All fields" is the last card, not a section
    assert not page.errors, page.errors
