"""End-to-end through Chromium: import the sample survey, process it, tune the recognition
map, open a profile, view the grid, download a GeoTIFF and a PNG.  Screenshots of every
view go to test-artifacts/screenshots/."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest

from tests.web.conftest import make_tiny_survey, zip_dir

from .conftest import SCREENSHOTS

SAMPLE = Path(__file__).resolve().parents[2] / "sample_surveys" / "omolon-mini"

pytestmark = [pytest.mark.browser, pytest.mark.slow,
              pytest.mark.skipif(not (SAMPLE / "survey.toml").exists(), reason="sample_surveys/omolon-mini is absent")]


def _shot(page, name):
    page.screenshot(path=str(SCREENSHOTS / name), full_page=True)


def _set_range(page, sel, value):
    page.eval_on_selector(sel, "(e, v) => { e.value = v; e.dispatchEvent(new Event('input', {bubbles: true})); }", str(value))


def test_analyst_workflow(live_server, browser_page, tmp_path):
    page = browser_page
    src = tmp_path / "omolon-mini"
    shutil.copytree(SAMPLE, src, ignore=shutil.ignore_patterns("truth"))
    zpath = tmp_path / "omolon-mini.zip"
    zpath.write_bytes(zip_dir(src))

    bad = tmp_path / "bad" / "omolon-mini"
    shutil.copytree(src, bad)
    rows = (bad / "lines.csv").read_text().splitlines()
    cols = rows[0].split(",")
    cells = rows[2].split(",")
    cells[cols.index("t_start")] = "12:30"
    rows[2] = ",".join(cells)
    (bad / "lines.csv").write_text("\n".join(rows) + "\n")
    bad_zip = tmp_path / "bad.zip"
    bad_zip.write_bytes(zip_dir(bad))

    page.goto(live_server.url)
    page.wait_for_selector("text=Select or import a survey")
    # --- a malformed file is rejected, the error names file, row and column in place
    page.set_input_files("#import-file", str(bad_zip))
    page.click("#import-btn")
    page.wait_for_selector("#import-error:visible", timeout=60000)
    msg = page.inner_text("#import-error")
    assert "lines.csv" in msg and "row 3" in msg and "t_start" in msg, msg
    assert page.locator("#survey-list li").count() == 0
    _shot(page, "00-import-error.png")
    page.errors.clear()  # the 422 above is expected
    # --- import with the upload progress bar
    page.set_input_files("#import-file", str(zpath))
    page.click("#import-btn")
    page.wait_for_selector("#survey-list li:has-text('omolon-mini')", timeout=60000)
    page.wait_for_selector("#qc-lines tbody tr", timeout=30000)
    page.wait_for_selector("#line-map .main-svg")
    assert page.locator("#qc-lines tbody tr").count() == 16
    assert page.locator("#qc-flights tbody tr").count() == 3
    assert "Easting (km)" in page.inner_text("#line-map")
    _shot(page, "01-qc-line-map.png")

    # --- processing: the EM table fills in while the job runs
    page.click("#tabs button[data-tab=process]")
    page.wait_for_selector("#params-form")
    page.click("#params-form details summary")
    assert page.locator("#params-form .params label").count() > 20
    _shot(page, "02-parameters.png")
    page.click("#run-job")
    seen_live, t_end, status = False, time.monotonic() + 300, ""
    while time.monotonic() < t_end:
        status = page.inner_text("#job-status") if page.locator("#job-status").count() else ""
        rows = page.locator(".em-row").count()
        if status == "running" and rows > 0 and not seen_live:
            seen_live = True
            _shot(page, "03-processing-live-em.png")
        if status in ("succeeded", "failed", "cancelled"):
            break
        if page.locator("#job-box .error:visible").count():
            break
        time.sleep(0.2)
    assert status == "succeeded", page.inner_text("#job-box")
    assert seen_live, "no EM iteration row appeared while the job was running"
    assert page.locator(".em-row").count() >= 2
    _shot(page, "04-processing-done.png")

    # --- recognition map: h and ρ re-smooth on the server
    page.click("#tabs button[data-tab=recognition]")
    page.wait_for_selector("#rec-map[data-signature]", timeout=30000)
    sig0 = page.get_attribute("#rec-map", "data-signature")
    _shot(page, "05-recognition-default.png")
    _set_range(page, "#rec-rho", 15)
    _set_range(page, "#rec-h", 0)
    page.wait_for_function("() => { const d = document.querySelector('#rec-map').dataset; return d.h === '0' && d.rho === '15'; }",
                           timeout=15000)
    sig1 = page.get_attribute("#rec-map", "data-signature")
    assert sig1 != sig0, "the recognition map did not change with h and ρ"
    assert "server" in page.inner_text("#rec-status")
    _shot(page, "06-recognition-h0-rho15.png")
    page.select_option("#rec-show", "raw")
    page.wait_for_function("() => document.querySelector('#rec-map').dataset.show === 'raw'")
    # the raw states are not smoothed: h, ρ and the mode are off and the status does not quote them
    assert page.is_disabled("#rec-h") and page.is_disabled("#rec-rho") and page.is_disabled("#rec-mode")
    assert "raw (Viterbi) states" in page.inner_text("#rec-status") and "h=" not in page.inner_text("#rec-status")
    _shot(page, "07-recognition-raw.png")
    page.select_option("#rec-show", "smoothed")
    page.wait_for_function("() => document.querySelector('#rec-map').dataset.show === 'smoothed'")
    assert not page.is_disabled("#rec-h") and "h=" in page.inner_text("#rec-status")

    # --- line profile
    page.click("#tabs button[data-tab=profile]")
    page.wait_for_selector("#profile-plot[data-line] .main-svg", timeout=30000)
    first = page.get_attribute("#profile-plot", "data-line")
    options = page.eval_on_selector_all("#profile-line option", "os => os.map(o => o.value)")
    assert len(options) == 16
    page.select_option("#profile-line", options[3])
    page.wait_for_function(f"() => document.querySelector('#profile-plot').dataset.line === {options[3]!r}")
    assert options[3] != first
    text = page.inner_text("#profile-plot")
    assert "Distance along line (km)" in text and "mGal" in text
    _shot(page, "08-line-profile.png")

    # --- grid with std toggle
    page.click("#tabs button[data-tab=grid]")
    page.wait_for_selector("#grid-plot .main-svg", timeout=30000)
    assert "Northing (km)" in page.inner_text("#grid-plot")
    _shot(page, "09-grid.png")
    with page.expect_download() as dl:
        page.click("#view-grid .png-btn")
    png = tmp_path / "grid.png"
    dl.value.save_as(png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    page.select_option("#grid-var", "dg_std")
    page.wait_for_function("() => document.querySelector('#grid-plot').dataset.variable === 'dg_std'")
    _shot(page, "10-grid-std.png")

    # --- exports: GeoTIFF read back with rasterio
    page.click("#tabs button[data-tab=export]")
    page.wait_for_selector("#export-geotiff")
    _shot(page, "11-exports.png")
    with page.expect_download() as dl:
        page.click("#export-geotiff")
    tif = tmp_path / "grid.tif"
    dl.value.save_as(tif)
    import numpy as np
    import rasterio
    with rasterio.open(tif) as ds:
        assert ds.crs.to_epsg() == 32657
        band = ds.read(1)
        assert band.shape[0] > 5 and band.shape[1] > 5 and np.isfinite(band).sum() > 10
    assert not [e for e in page.errors if "favicon" not in e], page.errors

    # --- a new survey built from an uploaded flight (three files + flight name)
    tiny = make_tiny_survey(tmp_path / "tiny")
    page.fill("#new-survey input[name=name]", "Block B")
    page.click("#new-survey button")
    page.wait_for_selector("#survey-list li.active:has-text('Block B')")
    page.wait_for_selector("#flight-upload:not([hidden])")
    page.fill("#flight-form input[name=flight]", "F21")
    page.set_input_files("#flight-form input[name=gravimeter]", str(tiny / "flights" / "f1" / "gravimeter.csv"))
    page.set_input_files("#flight-form input[name=gnss]", str(tiny / "flights" / "f1" / "gnss.csv"))
    lines = tmp_path / "lines-f21.csv"
    lines.write_text("line,t_start,t_end,kind\nB1,1010,1140,main\nB2,1150,1280,main\n")
    page.set_input_files("#flight-form input[name=lines]", str(lines))
    page.click("#flight-form button[type=submit]")
    page.click("#tabs button[data-tab=qc]")
    page.wait_for_selector("#qc-flights td:has-text('F21')", timeout=30000)
    assert page.locator("#qc-lines tbody tr").count() == 2
    _shot(page, "12-uploaded-flight-qc.png")
