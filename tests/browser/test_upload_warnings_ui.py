"""An accepted upload's warnings (the survey reader's) are shown under the upload's form."""

from __future__ import annotations

from tests.web.conftest import make_tiny_survey, zip_with


def test_import_and_flight_upload_show_the_reader_warnings(live_server, browser_page, tmp_path):
    page = browser_page
    src = make_tiny_survey(tmp_path / "tiny", name="tiny")
    zpath = tmp_path / "tiny.zip"
    zpath.write_bytes(zip_with(src, {"flights/ferry/gravimeter.csv": b"not,a\nfile", "flights/ferry/gnss.csv": b"x"}))
    page.goto(live_server.url)
    page.set_input_files("#import-file", str(zpath))
    page.click("#import-btn")
    box = page.wait_for_selector("#import-error-warnings", timeout=30000)
    assert "flight ferry is not read" in box.inner_text() and "tiny" in box.inner_text()
    page.wait_for_selector("#flight-upload:visible", timeout=30000)
    junk = tmp_path / "junk.csv"
    junk.write_bytes(b"\x00garbage")
    page.fill("#flight-form input[name=flight]", "junk")
    page.set_input_files("#flight-form input[name=gravimeter]", str(junk))
    page.set_input_files("#flight-form input[name=gnss]", str(junk))
    page.click("#flight-form button[type=submit]")
    box = page.wait_for_selector("#flight-error-warnings", timeout=30000)
    assert "flight junk is not read" in box.inner_text()
    assert page.locator("#flight-error").is_hidden()
