"""Fixtures for the web tests: a tiny valid survey, zips of it, and app/client factories."""

from __future__ import annotations

import io
import os
import time
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fastapi.testclient import TestClient

from app.web.main import create_app
from app.web.settings import Settings

FAKE_ENTRY = "tests.web.fake_pipeline:process_survey"


def make_tiny_survey(root: Path, name: str = "tiny", seed: int = 0) -> Path:
    """A small valid survey: one flight, two main lines and a tie line (a few hundred kB of CSV)."""
    rng = np.random.default_rng(seed)
    root = Path(root)
    fdir = root / "flights" / "f1"
    fdir.mkdir(parents=True, exist_ok=True)
    (root / "survey.toml").write_text(
        f'[survey]\nname = "{name}"\ncrs = "EPSG:32657"\n\n[gravimeter]\nmodel = "GT-1A"\ntau_s = 0.0\nscale = 1.0\n')
    t0, t1 = 1000.0, 1400.0
    tn = np.round(np.arange(t0, t1 + 1e-9, 0.1), 3)
    lat = 62.0 + 0.00002 * (tn - t0)
    lon = 158.0 + 0.00192 * (tn - t0)  # ~100 m/s east
    pd.DataFrame({"time": tn, "lat": lat, "lon": lon, "h": 1000.0 + rng.normal(0, 0.05, tn.size),
                  "vu": rng.normal(0, 0.02, tn.size)}).to_csv(fdir / "gnss.csv", index=False, float_format="%.8f")
    tg = np.round(np.arange(t0 - 1.0, t1 + 1.0, 1 / 18.24), 4)
    pd.DataFrame({"time": tg, "f_z": 9.8195 + rng.normal(0, 1e-4, tg.size)}).to_csv(
        fdir / "gravimeter.csv", index=False, float_format="%.7f")
    pd.DataFrame({"line": ["L1", "L2", "T1"], "flight": ["f1"] * 3, "t_start": [1010.0, 1150.0, 1290.0],
                  "t_end": [1140.0, 1280.0, 1390.0], "kind": ["main", "main", "tie"]}).to_csv(
        root / "lines.csv", index=False)
    return root


def make_dem(path: Path, crs: str = "EPSG:32657", bounds_deg=(157.9, 158.9, 61.97, 62.03), spacing_m: float = 250.0,
             shift_m: tuple[float, float] = (0.0, 0.0)) -> Path:
    """A small terrain model (GeoTIFF, float32) covering ``bounds_deg = (lon0, lon1, lat0, lat1)`` (by
    default the tiny survey and a few km around it), heights 200–600 m; ``shift_m`` moves it."""
    from app.core.geodesy import project_km
    from app.core.terrain import Dem
    from app.io.dem import write_dem

    lon0, lon1, lat0, lat1 = bounds_deg
    e, n = project_km(np.array([lon0, lon1, lon0, lon1]), np.array([lat0, lat0, lat1, lat1]), crs)
    x = np.arange(np.floor(e.min() * 1000 / spacing_m), np.ceil(e.max() * 1000 / spacing_m) + 1) * spacing_m + shift_m[0]
    y = np.arange(np.floor(n.min() * 1000 / spacing_m), np.ceil(n.max() * 1000 / spacing_m) + 1) * spacing_m + shift_m[1]
    X, Y = np.meshgrid(x, y)
    height = 400.0 + 150.0 * np.sin(X / 4000.0) * np.cos(Y / 3000.0) + 50.0 * np.sin(X / 900.0)
    return write_dem(Path(path), Dem(x, y, height, crs=crs))


def zip_dir(root: Path, nested: bool = True) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(Path(root).rglob("*")):
            if p.is_file():
                arc = p.relative_to(root)
                zf.write(p, (Path(root.name) / arc).as_posix() if nested else arc.as_posix())
    return buf.getvalue()


def zip_with(src: Path, replace: dict[str, bytes]) -> bytes:
    """The survey ``src`` zipped under ``s/``, with the files named in ``replace`` (paths relative
    to the survey directory) holding other content."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(Path(src).rglob("*")):
            rel = p.relative_to(src).as_posix()
            if p.is_file() and rel not in replace:
                zf.write(p, "s/" + rel)
        for rel, data in replace.items():
            zf.writestr("s/" + rel, data)
    return buf.getvalue()


@pytest.fixture(scope="session")
def tiny_survey(tmp_path_factory) -> Path:
    return make_tiny_survey(tmp_path_factory.mktemp("surveys") / "tiny")


@pytest.fixture(scope="session")
def tiny_zip(tiny_survey) -> bytes:
    return zip_dir(tiny_survey)


@pytest.fixture
def make_client(tmp_path, monkeypatch):
    """Factory: ``make_client(**settings)`` → a running TestClient (lifespan started) on tmp data dir."""
    clients = []
    monkeypatch.setenv("AEROGRAV_FAKE_DELAY_S", os.environ.get("AEROGRAV_FAKE_DELAY_S", "0.02"))

    def make(**kw):
        kw.setdefault("data_dir", tmp_path / "data")
        kw.setdefault("pipeline_entry", FAKE_ENTRY)
        kw.setdefault("poll_interval_s", 0.1)
        c = TestClient(create_app(Settings(**kw)), base_url="http://localhost")
        c.__enter__()
        clients.append(c)
        return c

    yield make
    for c in reversed(clients):
        c.__exit__(None, None, None)


@pytest.fixture
def client(make_client):
    return make_client()


def wait_job(client, job_id: int, timeout: float = 60.0, until=("succeeded", "failed", "cancelled")) -> dict:
    t_end = time.monotonic() + timeout
    while True:
        j = client.get(f"/api/jobs/{job_id}").json()
        if j["status"] in until:
            return j
        if time.monotonic() > t_end:
            raise AssertionError(f"job {job_id} still {j['status']} after {timeout} s: {j}")
        time.sleep(0.1)


def import_zip(client, data: bytes, name: str = "survey.zip", headers=None):
    return client.post("/api/surveys/import", files={"file": (name, data, "application/zip")}, headers=headers or {})
