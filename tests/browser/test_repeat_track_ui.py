"""A test line in Chromium: one 40 km track flown four times in alternating directions
(``testline-2hz``), processed by the real pipeline.  The Line profiles tab overlays its passes on one
along-track axis — checked against the projection of lines.parquet's positions on the track's
principal direction computed here — with the estimate and band chosen, and the track's
repeatability figures from report.json beside it; the single-line view still draws a pass from its
own start."""

from __future__ import annotations

import io
import json
import shutil
import time

import numpy as np
import pandas as pd
import pytest

from .conftest import SCREENSHOTS

pytestmark = [pytest.mark.browser, pytest.mark.slow]

PASS_TRACES = """() => document.getElementById('track-plot').data
  .filter((t) => t.meta && t.meta.role === 'estimate')
  .map((t) => ({line: t.meta.line, x: t.x, y: t.y, t: t.customdata, dash: t.line.dash}))"""
BAND_TRACES = "() => document.getElementById('track-plot').data.filter((t) => t.meta && t.meta.role.startsWith('band')).length"


@pytest.fixture(scope="module")
def testline_zip(tmp_path_factory) -> bytes:
    from app.simulate import simulate_survey
    from tests.web.conftest import zip_dir

    d = simulate_survey("testline-2hz", tmp_path_factory.mktemp("tl") / "testline", seed=1)
    shutil.rmtree(d / "truth")
    return zip_dir(d)


def _processed(url: str, z: bytes) -> tuple[int, pd.DataFrame, dict]:
    """The test line imported and processed; its lines.parquet and report.json as exported."""
    import httpx

    with httpx.Client(base_url=url, timeout=60) as c:
        sid = c.post("/api/surveys/import", files={"file": ("testline.zip", z, "application/zip")}).json()["id"]
        job = c.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
        t_end = time.monotonic() + 240
        while (j := c.get(f"/api/jobs/{job['id']}").json())["status"] in ("queued", "running"):
            assert time.monotonic() < t_end, j
            time.sleep(0.3)
        assert j["status"] == "succeeded", j
        lines = pd.read_parquet(io.BytesIO(c.get(f"/api/surveys/{sid}/export", params={"format": "parquet"}).content))
        report = json.loads(c.get(f"/api/surveys/{sid}/export", params={"format": "report"}).content)
        assert c.get(f"/api/surveys/{sid}/repeat-tracks/nope").status_code == 404
    lines["line"] = lines["line"].astype(str)
    return sid, lines, report


def _axis(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, float]:
    """The track's axis computed here: principal direction of every pass's points (SVD), pointing
    the way the first pass flies, origin at the smallest projection.  (centre, unit, origin)."""
    p = df[["easting_km", "northing_km"]].to_numpy(float)
    c = p.mean(axis=0)
    u = np.linalg.svd(p - c, full_matrices=False)[2][0]
    first = df[df["line"] == df.sort_values("time")["line"].iloc[0]].sort_values("time")
    if np.dot(first[["easting_km", "northing_km"]].to_numpy(float)[-1] - first[["easting_km", "northing_km"]].to_numpy(float)[0], u) < 0:
        u = -u
    return c, u, float(((p - c) @ u).min())


def test_repeat_passes_overlay_on_one_along_track_axis(live_server, browser_page, testline_zip):
    page = browser_page
    sid, df, report = _processed(live_server.url, testline_zip)
    c, u, s0 = _axis(df)
    length = float(((df[["easting_km", "northing_km"]].to_numpy(float) - c) @ u).max()) - s0
    assert 39.0 < length < 41.0

    page.goto(f"{live_server.url}/#survey={sid}&tab=profile")
    page.wait_for_selector("#track-plot[data-track='R1'] .main-svg", timeout=60000)
    # a test line: every line is a pass, so the overlay comes first
    assert page.evaluate("() => document.getElementById('track-card').compareDocumentPosition(document.getElementById('line-card')) "
                         "& Node.DOCUMENT_POSITION_FOLLOWING") > 0
    got = {t["line"]: t for t in page.evaluate(PASS_TRACES)}
    assert sorted(got) == ["R1-1", "R1-2", "R1-3", "R1-4"]
    reversed_seen = 0
    for line, tr in got.items():
        g = df[df["line"] == line].set_index(np.round(df.loc[df["line"] == line, "time"].to_numpy(float), 2))
        t = np.array(tr["t"], dtype=float)
        rows = g.loc[t]
        want_x = (rows[["easting_km", "northing_km"]].to_numpy(float) - c) @ u - s0
        np.testing.assert_allclose(np.array(tr["x"], dtype=float), want_x, atol=2e-3)
        np.testing.assert_allclose(np.array(tr["y"], dtype=float), rows["dg_mgal"].to_numpy(float), atol=1.5e-3)
        x = np.array(tr["x"], dtype=float)
        if x[-1] < x[0]:   # flown the other way: from the far end back to the origin, drawn dashed
            reversed_seen += 1
            assert x[0] > length - 1.0 and x[-1] < 1.0 and tr["dash"] == "dash"
        else:
            assert x[0] < 1.0 and x[-1] > length - 1.0 and tr["dash"] == "solid"
    assert reversed_seen == 2
    # overlaid, the reversed pass R1-2 agrees with R1-1 where both flew: far closer than the anomaly's own spread
    a, b = got["R1-1"], got["R1-2"]
    xa, ya = np.array(a["x"], float), np.array(a["y"], float)
    xb, yb = np.array(b["x"], float)[::-1], np.array(b["y"], float)[::-1]
    common = np.linspace(2.0, length - 2.0, 200)
    diff = np.interp(common, xa, ya) - np.interp(common, xb, yb)
    assert np.sqrt(np.mean(diff ** 2)) < 0.3 * np.std(np.interp(common, xa, ya))

    # the repeatability figures are report.json's
    acc = report["repeat_lines"]["R1"]["internal_accuracy_mgal"]
    cells = {r.get_attribute("data-estimate"): r.locator("td").nth(1).inner_text()
             for r in page.locator("#track-repeatability tbody tr").all()}
    assert cells == {"adaptive": f"{acc['dg_mgal']:.3f}".rstrip("0").rstrip("."),
                     "stationary": f"{acc['dg_stationary_mgal']:.3f}".rstrip("0").rstrip("."),
                     "fir": f"{acc['dg_fir_mgal']:.3f}".rstrip("0").rstrip(".")}
    assert page.locator("#track-passes tbody tr").count() == 4

    # the ± 2σ band by default, none on request; FIR selectable (no σ band: disabled)
    assert page.evaluate(BAND_TRACES) == 8
    page.select_option("#track-band", "0")
    page.wait_for_function(f"() => ({BAND_TRACES})() === 0")
    page.select_option("#track-estimate", "fir")
    page.wait_for_selector("#track-plot[data-estimate='fir']")
    assert page.is_disabled("#track-band")
    fir = {t["line"]: t for t in page.evaluate(PASS_TRACES)}["R1-2"]
    g = df[df["line"] == "R1-2"].set_index(np.round(df.loc[df["line"] == "R1-2", "time"].to_numpy(float), 2))
    want = g.loc[np.array(fir["t"], float), "dg_fir_mgal"].to_numpy(float)
    shown = np.array([np.nan if v is None else v for v in fir["y"]], float)
    np.testing.assert_allclose(shown[np.isfinite(want)], want[np.isfinite(want)], atol=1.5e-3)
    assert page.locator("#track-repeatability tr.chosen").get_attribute("data-estimate") == "fir"

    # the single-line view still draws a pass from its own start
    page.select_option("#profile-line", "R1-2")
    page.wait_for_selector("#profile-plot[data-line='R1-2']")
    x = page.evaluate("() => document.getElementById('profile-plot').data[0].x")
    assert x[0] == 0 and x[-1] > 39.0
    assert "a pass of repeat track R1" in page.inner_text("#profile-status")
    page.screenshot(path=str(SCREENSHOTS / "repeat-track.png"), full_page=True)
    assert not page.errors, page.errors
