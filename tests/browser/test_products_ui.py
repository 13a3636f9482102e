"""Geophysical products in Chromium (issue part 5): the grid view switches free-air / Bouguer on a
topography-only survey processed by the real pipeline (the Bouguer map is flat, the free-air one is
the terrain's gravity), the exports list each product, the DEM is uploaded from the sidebar, the
Bouguer choice is disabled with its reason when there is no DEM, and the flight height / datum choice
appears when a datum was used (test pipeline)."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest

pytestmark = [pytest.mark.browser]

#: topo-only, shrunk (2 lines of 20 km, a tie, 500 m prisms): ~5 s to simulate, ~3 s to process
SMALL = dict(n_main=2, main_length_km=20.0, n_tie=1, n_repeat=0, topo_spacing_m=500.0, topo_margin_km=6.0,
             grid_margin_km=4.0)


@pytest.fixture(scope="module")
def topo_zip(tmp_path_factory) -> bytes:
    from app.simulate import simulate_survey
    from tests.web.conftest import zip_dir

    d = simulate_survey("topo-only", tmp_path_factory.mktemp("topo") / "topo-only", seed=2, **SMALL)
    shutil.rmtree(d / "truth")
    return zip_dir(d)


def _wait_job(c, sid, params=None, timeout=90):
    job = c.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": params or {}}).json()
    t_end = time.monotonic() + timeout
    while (j := c.get(f"/api/jobs/{job['id']}").json())["status"] in ("queued", "running"):
        assert time.monotonic() < t_end, j
        time.sleep(0.2)
    assert j["status"] == "succeeded", j


def _z_std(page) -> float:
    z = page.evaluate("() => document.querySelector('#grid-plot').data[0].z")
    return float(np.nanstd(np.array(z, dtype=float)))


def test_free_air_bouguer_switch_on_a_topography_survey(live_server, browser_page, topo_zip, tmp_path):
    import httpx
    import rasterio

    page = browser_page
    with httpx.Client(base_url=live_server.url, timeout=60) as c:
        s = c.post("/api/surveys/import", files={"file": ("topo-only.zip", topo_zip, "application/zip")}).json()
        assert s["has_dem"] is True
        _wait_job(c, s["id"])
    page.goto(f"{live_server.url}/#survey={s['id']}&tab=grid")
    page.wait_for_selector("#grid-plot[data-product] .main-svg", timeout=60000)
    assert page.get_attribute("#grid-plot", "data-product") == "free_air"
    assert "free-air anomaly δg at flight height" in page.text_content("#grid-plot .gtitle")
    assert page.is_visible("#grid-height-label") is False            # no datum: no height choice
    assert page.evaluate("() => document.querySelector('#grid-product option[value=bouguer]').disabled") is False
    # the sidebar says the survey has a DEM; the import form mentions it
    assert page.get_attribute("#dem-upload", "data-has-dem") == "1"
    assert "dem.tif" in page.inner_text("#import-dem-hint")
    free_air = _z_std(page)

    page.select_option("#grid-product", "bouguer")
    page.wait_for_function("() => document.querySelector('#grid-plot').dataset.product === 'bouguer'", timeout=60000)
    assert "Bouguer anomaly δg_B at flight height" in page.text_content("#grid-plot .gtitle")
    bouguer = _z_std(page)
    print(f"grid std: free-air {free_air:.2f} mGal, Bouguer {bouguer:.2f} mGal")
    page.screenshot(path=str(tmp_path / "grid-bouguer.png"), full_page=True)
    # topography only: the free-air map is the terrain's gravity, the Bouguer map is flat
    assert free_air > 5.0 and bouguer < 0.35 * free_air, (free_air, bouguer)
    page.select_option("#grid-product", "free_air")
    page.wait_for_function("() => document.querySelector('#grid-plot').dataset.product === 'free_air'", timeout=60000)
    assert abs(_z_std(page) - free_air) < 1e-6

    # the profile shows the Bouguer anomaly; the exports list it
    page.screenshot(path=str(tmp_path / "grid-free-air.png"), full_page=True)
    page.click("#tabs button[data-tab=profile]")
    page.wait_for_selector("#profile-plot[data-line] .main-svg", timeout=60000)
    page.screenshot(path=str(tmp_path / "profile.png"), full_page=True)
    assert "dg_bouguer" in page.get_attribute("#profile-plot", "data-products").split()
    page.click("#tabs button[data-tab=export]")
    page.wait_for_selector("#export-bouguer-geotiff")
    with page.expect_download() as dl:
        page.click("#export-bouguer-geotiff")
    assert "grid_bouguer.tif" in dl.value.suggested_filename
    dl.value.save_as(tmp_path / "b.tif")
    with rasterio.open(tmp_path / "b.tif") as t:
        assert t.count == 2 and np.nanstd(t.read(1)) < 0.35 * free_air
    assert page.locator("#export-flight-geotiff").count() == 0        # no datum: no flight-height grid
    assert not page.errors, page.errors


def test_no_dem_then_dem_upload_and_datum_choice(tmp_path, monkeypatch, browser_page):
    """Test pipeline: a survey without DEM (Bouguer disabled, the reason shown), a DEM uploaded
    from the sidebar, processed with a datum: Bouguer enabled, the flight height / datum choice."""
    import httpx

    from app.web.main import create_app
    from app.web.settings import Settings
    from tests.web.conftest import FAKE_ENTRY, make_dem, make_tiny_survey, zip_dir

    from .conftest import LiveServer

    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", "0.01")
    page = browser_page
    app = create_app(Settings(data_dir=tmp_path / "data", poll_interval_s=0.1, pipeline_entry=FAKE_ENTRY))
    with LiveServer(app) as srv, httpx.Client(base_url=srv.url, timeout=30) as c:
        sid = c.post("/api/surveys/import", files={"file": ("tiny.zip", zip_dir(make_tiny_survey(tmp_path / "tiny")),
                                                             "application/zip")}).json()["id"]
        _wait_job(c, sid)
        page.goto(f"{srv.url}/#survey={sid}&tab=grid")
        page.wait_for_selector("#grid-plot[data-product] .main-svg", timeout=60000)
        assert page.evaluate("() => document.querySelector('#grid-product option[value=bouguer]').disabled") is True
        assert "has no DEM" in page.get_attribute("#grid-product", "title")
        assert "has no DEM" in page.inner_text("#grid-product-note")
        assert "on the left" in page.inner_text("#grid-product-note")   # this page's way, not PUT /api/…
        page.click("#tabs button[data-tab=export]")
        page.wait_for_selector("#export-bouguer-missing")
        assert "no DEM" in page.inner_text("#export-bouguer-missing")

        # a file that is not a DEM: rejected, the message names dem.tif
        (tmp_path / "bad.tif").write_bytes(b"not a tiff")
        page.set_input_files("#dem-file", str(tmp_path / "bad.tif"))
        page.click("#dem-btn")
        page.wait_for_selector("#dem-error:visible", timeout=60000)
        assert "dem.tif" in page.inner_text("#dem-error")
        page.errors.clear()       # the 422 of the rejected upload is expected
        page.set_input_files("#dem-file", str(make_dem(tmp_path / "srtm.tif")))
        page.click("#dem-btn")
        page.wait_for_function("() => document.querySelector('#dem-upload').dataset.hasDem === '1'", timeout=60000)
        assert page.is_visible("#dem-remove")

        _wait_job(c, sid, {"datum": "constant", "datum_height_m": 1100.0})
        page.goto(f"{srv.url}/#survey={sid}&tab=qc")
        page.reload()
        page.click("#tabs button[data-tab=grid]")
        page.wait_for_selector("#grid-plot[data-product] .main-svg", timeout=60000)
        assert page.get_attribute("#grid-plot", "data-height") == "datum"
        assert page.is_visible("#grid-height-label")
        page.screenshot(path=str(tmp_path / "grid-datum.png"), full_page=True)
        assert "at the constant datum (1100 m)" in page.text_content("#grid-plot .gtitle")
        page.select_option("#grid-height", "flight")
        page.wait_for_function("() => document.querySelector('#grid-plot').dataset.height === 'flight'", timeout=60000)
        assert "at flight height" in page.text_content("#grid-plot .gtitle")
        # with a datum the Bouguer anomaly is at the datum only
        assert page.evaluate("() => document.querySelector('#grid-product option[value=bouguer]').disabled") is True
        page.select_option("#grid-height", "datum")
        page.wait_for_function("() => document.querySelector('#grid-plot').dataset.height === 'datum'", timeout=60000)
        page.select_option("#grid-product", "bouguer")
        page.wait_for_function("() => document.querySelector('#grid-plot').dataset.product === 'bouguer'", timeout=60000)
        page.click("#tabs button[data-tab=export]")
        page.wait_for_selector("#export-bouguer-geotiff")
        assert page.locator("#export-flight-netcdf").count() == 1
        page.click("#tabs button[data-tab=profile]")
        page.wait_for_selector("#profile-plot[data-line] .main-svg", timeout=60000)
        assert set(page.get_attribute("#profile-plot", "data-products").split()) == {"dg_flight", "dg_bouguer", "terrain"}
        assert not page.errors, page.errors
