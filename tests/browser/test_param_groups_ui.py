"""The processing parameters on the Processing tab by pipeline stage: every parameter of the config
schema in exactly one group of the rendered form, the common ones shown and the advanced ones
folded away; a changed advanced value is sent, and an advanced value out of range is shown to the
analyst (its folds opened), not silently refused."""

from __future__ import annotations

import pytest

from .test_analyst_ui import _processed_survey, fake_pipeline_server, fake_server  # noqa: F401  (fixture)

pytestmark = [pytest.mark.browser]

FORM = """() => [...document.querySelectorAll('#params-form fieldset.param-group')].map((f) => ({
    group: f.dataset.group, legend: f.querySelector('legend').textContent,
    common: [...f.querySelectorAll(':scope > .params input, :scope > .params select')].map((i) => i.name),
    advanced: [...f.querySelectorAll(':scope > details.advanced .params input, :scope > details.advanced .params select')].map((i) => i.name)}))"""


def test_every_parameter_in_exactly_one_group_of_the_form(fake_server, browser_page, tmp_path):  # noqa: F811
    import httpx

    page = browser_page
    sid = _processed_survey(fake_server.url, tmp_path)
    with httpx.Client(base_url=fake_server.url) as c:
        schema = c.get("/api/params/schema").json()
    names = set(schema["schema"]["properties"])
    assert len(names) > 100
    page.goto(f"{fake_server.url}/#survey={sid}&tab=process")
    page.wait_for_selector("#params-form fieldset.param-group", state="attached")
    groups = page.evaluate(FORM)
    placed = [n for g in groups for n in g["common"] + g["advanced"]]
    assert sorted(placed) == sorted(names), (set(names) - set(placed), [n for n in placed if placed.count(n) > 1])
    every_input = page.evaluate("() => [...document.querySelectorAll('#params-form .params input, #params-form .params "
                                "select')].map((i) => i.name)")
    assert sorted(every_input) == sorted(placed)                   # no input outside a group
    assert [g["group"] for g in groups][:3] == ["measurement", "noise", "order"]
    rec = next(g for g in groups if g["group"] == "recognition")
    assert rec["legend"].startswith("Recognition map") and "nlmeans_rho_km" in rec["common"]

    # common ones shown once the block opens, advanced ones folded until asked for
    page.click("#params-form > details > summary")
    assert page.is_visible("#params-form input[name=nlmeans_rho_km]")
    assert not page.is_visible("#params-form input[name=leveling_cv_significance]")
    lev = page.locator("#params-form fieldset[data-group=leveling] details.advanced")
    lev.locator("summary").click()
    assert page.is_visible("#params-form input[name=leveling_cv_significance]")

    # an advanced value out of range, its folds closed: named, its folds opened, focused; nothing sent
    lev.evaluate("d => { d.open = false; }")
    page.click("#params-form > details > summary")
    page.eval_on_selector("#params-form input[name=leveling_cv_significance]", "e => { e.value = '7'; }")
    page.click("#run-job")
    page.wait_for_selector("#job-box .error:visible", timeout=5000)
    assert "leveling_cv_significance" in page.inner_text("#job-box .error")
    assert page.evaluate("() => document.activeElement.name") == "leveling_cv_significance"
    page.errors.clear()
    # a valid advanced value is sent with the job
    page.fill("#params-form input[name=leveling_cv_significance]", "0.2")
    # the job list is read once the job was created (#job-status may still show the earlier job)
    with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith(f"/api/surveys/{sid}/jobs"),
                              timeout=10000) as posted:
        page.click("#run-job")
    assert posted.value.ok
    with httpx.Client(base_url=fake_server.url) as c:
        jobs = c.get(f"/api/surveys/{sid}/jobs").json()
    assert max(jobs, key=lambda j: j["id"])["params"] == {"leveling_cv_significance": 0.2}
    assert not page.errors, page.errors
