"""A second analyst walkthrough (test pipeline): the survey list after a cancelled re-run, the labels of
a repeat track's passes on the maps, and the Processing tab in a 700 px wide window."""

from __future__ import annotations

import pytest

from .test_analyst_ui import _processed_survey, _run, fake_server  # noqa: F401  (fixture)

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


# every line label on a map (lone labels: the text trace; a repeat track's passes: annotations) with its box
_LABEL_BOXES = """(sel) => [...document.querySelectorAll(`${sel} .textpoint text, ${sel} .annotation-text`)].map((t) => {
  const r = t.getBoundingClientRect();
  return {text: t.textContent, left: r.left, right: r.right, top: r.top, bottom: r.bottom}; })"""


def _run_together(boxes, gap=3.0):
    """Pairs of labels that overlap, or sit on one row closer than ``gap`` px (read as one word)."""
    out = []
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            rows = min(a["bottom"], b["bottom"]) - max(a["top"], b["top"])      # > 0: they share a row
            cols = min(a["right"], b["right"]) - max(a["left"], b["left"])      # > -gap: touching or overlapping
            if rows > 1 and cols > -gap:
                out.append(f"{a['text']} / {b['text']}")
    return out


def _omolon(url, tmp_path, process):
    import shutil
    from pathlib import Path

    import httpx

    from tests.web.conftest import zip_dir
    src = tmp_path / "omolon-mini"
    shutil.copytree(Path(__file__).resolve().parents[2] / "sample_surveys" / "omolon-mini", src,
                    ignore=shutil.ignore_patterns("truth"))
    with httpx.Client(base_url=url, timeout=120) as c:
        sid = c.post("/api/surveys/import", files={"file": ("s.zip", zip_dir(src), "application/zip")}).json()["id"]
        if process:
            _run(c, sid)
    return sid


def test_repeat_pass_labels_read_one_per_pass(fake_server, browser_page, tmp_path):  # noqa: F811
    """omolon-mini's repeat track R1 is flown three times from one point: its labels read "R1-1R1-3"
    above "R1-2" on the QC map and the grid (above-left and above-right of the point, touching). The
    passes' labels are now a column left of the point, one row per pass in order, each opening its
    own profile."""
    sid = _omolon(fake_server.url, tmp_path, process=True)
    page = browser_page
    page.goto(f"{fake_server.url}/#survey={sid}&tab=qc")
    page.wait_for_selector("#line-map .textpoint text", timeout=30000)
    for sel in ("#line-map", "#grid-plot"):
        if sel == "#grid-plot":
            page.click("#tabs button[data-tab=grid]")
            page.wait_for_selector("#grid-plot .textpoint text", timeout=30000)
        boxes = page.evaluate(_LABEL_BOXES, sel)
        assert sorted(b["text"] for b in boxes) == sorted([f"M{i:03d}" for i in range(1, 11)] + ["T01", "T02", "T03",
                                                                                          "R1-1", "R1-2", "R1-3"]), boxes
        assert not _run_together(boxes), (sel, _run_together(boxes))
        passes = sorted((b for b in boxes if b["text"].startswith("R1-")), key=lambda b: b["top"])
        assert [b["text"] for b in passes] == ["R1-1", "R1-2", "R1-3"]               # one row per pass, in order
        assert all(p["bottom"] <= q["top"] + 1 for p, q in zip(passes, passes[1:]))
        assert max(b["right"] for b in passes) - min(b["right"] for b in passes) < 1   # one column
    # a click on a pass's label opens that pass's profile
    page.click("#grid-plot .annotation-text:text-is('R1-3')")
    page.wait_for_selector("#profile-plot[data-line='R1-3'] .main-svg", timeout=20000)
    # the rule itself: lines starting at one point share a column, the others stand alone
    got = page.evaluate("async () => (await import('/js/plots.js')).labelGroups([0, 0.001, 10, 0], [0, 0, 5, 0.0005])")
    assert got == {"group": [0, 0, 2, 0], "rank": [0, 1, 0, 2], "size": [3, 3, 1, 3]}
    _no_errors(page)


_BOXES = """(sel) => {
  const e = document.querySelector(sel), r = e.getBoundingClientRect();
  const card = e.closest('.card').getBoundingClientRect();
  // the same select free of any container: its natural width
  const free = e.cloneNode(true);
  free.style.position = 'absolute'; free.style.visibility = 'hidden';
  document.body.append(free);
  const natural = free.getBoundingClientRect().width;
  free.remove();
  return {left: r.left, right: r.right, width: r.width, natural, card: [card.left, card.right], vw: innerWidth,
          docw: document.documentElement.scrollWidth, title: e.title, text: e.selectedOptions[0].textContent}; }"""


def test_the_job_dropdown_fits_a_700_px_window(fake_server, browser_page, tmp_path):  # noqa: F811
    """At 700 px the job drop-down ("process — identification, recognition, filtering, leveling, grid",
    472 px wide) ran 65 px past its card and the window (a horizontal scroll bar for the whole page). It
    now shrinks to its card, its text cut with an ellipsis and whole in its tooltip; wide windows keep
    it at its full width."""
    sid = _processed_survey(fake_server.url, tmp_path)
    page = browser_page
    page.goto(f"{fake_server.url}/#survey={sid}&tab=process")
    page.wait_for_selector("#job-box .badge", timeout=20000)
    wide = page.evaluate(_BOXES, "#job-kind")
    assert abs(wide["width"] - wide["natural"]) < 1, wide          # a wide window: not cut
    assert wide["title"] == wide["text"]
    page.set_viewport_size({"width": 700, "height": 1000})
    page.wait_for_timeout(300)
    b = page.evaluate(_BOXES, "#job-kind")
    assert b["card"][0] <= b["left"] and b["right"] <= b["card"][1], b   # inside its card …
    assert b["right"] <= b["vw"] and b["docw"] <= b["vw"], b             # … and the window: no page scroll bar
    assert b["width"] < b["natural"], b
    assert b["title"] == b["text"] == "process — identification, recognition, filtering, leveling, grid"
    assert page.evaluate("() => getComputedStyle(document.querySelector('#job-kind')).textOverflow") == "ellipsis"
    # another choice: its text in the tooltip
    page.select_option("#job-kind", "filter")
    assert page.get_attribute("#job-kind", "title").startswith("filter — from the stored identification")
    _no_errors(page)
