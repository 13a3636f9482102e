"""The store's global limit (``AEROGRAV_MAX_STORE_MB``): each upload was bounded, and each survey
had a budget, but any number of surveys could fill the disk.  A new survey or an upload that
would take the data directory above the limit is refused (507, saying what the store holds and
its limit), nothing is stored or left half-written, and the count stays right between walks of
the data directory (uploads added, removals subtracted, job results recounted)."""

from __future__ import annotations

import hashlib
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from app.web.deps import get_settings
from app.web.settings import Settings
from app.web.store import size_text

from .conftest import import_zip, make_dem, wait_job


@pytest.fixture
def no_rewalk(monkeypatch):
    """The data directory is walked once, at the first count: every later figure is the running
    count (admissions, removals), so a test cannot pass thanks to a timely re-walk."""
    import app.web.store as store_mod
    monkeypatch.setattr(store_mod, "USAGE_TTL_S", 1e9)


def _limit(client, limit_bytes: float) -> None:
    """Set the store's limit through the settings dependency."""
    s = client.app.state.settings.model_copy(update={"max_store_mb": limit_bytes / 2**20})
    client.app.dependency_overrides[get_settings] = lambda: s


def _used(client) -> int:
    return client.app.state.store.store_usage_bytes()


def _survey_bytes(src: Path) -> int:
    return sum(p.stat().st_size for p in src.rglob("*") if p.is_file())


def _files(data_dir: Path) -> dict[str, str]:
    """Every file under surveys/ and tmp/ with its content's hash."""
    out = {}
    for sub in ("surveys", "tmp"):
        for p in sorted((data_dir / sub).rglob("*")):
            if p.is_file():
                out[p.relative_to(data_dir).as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _flight(src: Path, name: str = "f2") -> tuple[dict, dict]:
    fdir = src / "flights" / "f1"
    return ({"gravimeter": ("gravimeter.csv", (fdir / "gravimeter.csv").read_bytes()),
             "gnss": ("gnss.csv", (fdir / "gnss.csv").read_bytes()),
             "lines": ("lines.csv", b"line,t_start,t_end,kind\nX1,1010,1140,main\n")}, {"flight": name})


def test_setting_from_the_environment(monkeypatch, make_client):
    """AEROGRAV_MAX_STORE_MB sets the limit (default 20 GB); /api/health reports it and what the
    store holds."""
    monkeypatch.delenv("AEROGRAV_MAX_STORE_MB", raising=False)
    assert Settings().max_store_bytes == 20 * 2**30
    monkeypatch.setenv("AEROGRAV_MAX_STORE_MB", "1.5")
    assert Settings().max_store_bytes == int(1.5 * 2**20)
    monkeypatch.setenv("AEROGRAV_MAX_STORE_MB", "0")
    with pytest.raises(ValueError):
        Settings()
    c = make_client(max_store_mb=123.0)
    st = c.get("/api/health").json()["storage"]
    assert st["max_store_mb"] == 123.0 and 0 < st["store_used_mb"] < 1   # the SQLite file


def test_import_over_the_limit_refused_and_nothing_stored(client, tiny_survey, tiny_zip, no_rewalk):
    """With room for half a survey more, an import is a 507 naming what the store holds, what the
    upload adds and the limit; no survey, snapshot or staged file is left and nothing stays
    reserved: with room for exactly one more survey (and 2 kB), the same import passes."""
    sid = import_zip(client, tiny_zip).json()["id"]
    size = _survey_bytes(tiny_survey)
    used = _used(client)
    _limit(client, used + size // 2)
    files = _files(Path(client.app.state.settings.data_dir))
    r = import_zip(client, tiny_zip)
    assert r.status_code == 507, r.text[:300]
    d = r.json()["detail"]
    assert "AEROGRAV_MAX_STORE_MB" in d and "nothing was stored" in d, d
    assert f"holds {size_text(used)} of its {size_text(used + size // 2)} limit" in d, d
    assert f"adds {size_text(size)}" in d, d
    assert [s["id"] for s in client.get("/api/surveys").json()] == [sid]
    assert _files(Path(client.app.state.settings.data_dir)) == files
    assert _used(client) == used
    _limit(client, used + size + 2048)
    r = import_zip(client, tiny_zip)
    assert r.status_code == 201, r.text[:300]
    assert _used(client) == used + size


def test_upload_patch_and_dem_over_the_limit_refused_survey_unchanged(client, tiny_survey, tiny_zip, tmp_path,
                                                                      no_rewalk):
    """A flight upload, a PATCH of survey.toml and a DEM that would take the store above its limit
    are 507s: the survey keeps its flights, name, input snapshot and files, and the uploaded files
    staged for the new snapshot are gone."""
    sid = import_zip(client, tiny_zip).json()["id"]
    data_dir = Path(client.app.state.settings.data_dir)
    before = client.get(f"/api/surveys/{sid}").json()
    files = _files(data_dir)
    _limit(client, _used(client) + 10)         # a new survey.toml is about a hundred bytes
    files_in, form = _flight(tiny_survey)
    r = client.post(f"/api/surveys/{sid}/flights", files=files_in, data=form)
    assert r.status_code == 507 and "AEROGRAV_MAX_STORE_MB" in r.json()["detail"], r.text[:300]
    r = client.patch(f"/api/surveys/{sid}", json={"survey": {"name": "renamed"}})
    assert r.status_code == 507 and "AEROGRAV_MAX_STORE_MB" in r.json()["detail"], r.text[:300]
    dem = make_dem(tmp_path / "dem.tif").read_bytes()
    r = client.put(f"/api/surveys/{sid}/dem", files={"dem": ("dem.tif", dem)})
    assert r.status_code == 507 and "AEROGRAV_MAX_STORE_MB" in r.json()["detail"], r.text[:300]
    after = client.get(f"/api/surveys/{sid}").json()
    assert (after["flights"], after["name"], after["n_lines"], after["has_dem"]) == \
        (before["flights"], before["name"], before["n_lines"], False)
    assert _files(data_dir) == files
    # the same upload with room for it is stored
    _limit(client, _used(client) + 2 * _survey_bytes(tiny_survey))
    assert client.post(f"/api/surveys/{sid}/flights", files=files_in, data=form).status_code == 201


def test_full_store_refuses_new_surveys_before_extracting(client, tiny_zip, monkeypatch):
    """At its limit the store takes no new survey, empty or imported: a 507 at once (the zip is not
    extracted nor validated), nothing stored; reading and deleting still work."""
    import app.web.routers.surveys as surveys_router

    sid = import_zip(client, tiny_zip).json()["id"]
    _limit(client, _used(client))
    extracted = []
    monkeypatch.setattr(surveys_router, "extract_survey_zip", lambda *a, **kw: extracted.append(a))
    r = client.post("/api/surveys", json={"name": "one more"})
    assert r.status_code == 507 and "store is full" in r.json()["detail"], r.text[:300]
    r = import_zip(client, tiny_zip)
    assert r.status_code == 507 and "store is full" in r.json()["detail"], r.text[:300]
    assert extracted == []
    assert [s["id"] for s in client.get("/api/surveys").json()] == [sid]
    assert client.get(f"/api/surveys/{sid}/qc").status_code == 200
    assert client.delete(f"/api/surveys/{sid}").status_code == 204
    assert client.post("/api/surveys", json={"name": "one more"}).status_code == 201


def test_concurrent_imports_cannot_share_the_last_free_space(client, tiny_survey, tiny_zip, no_rewalk):
    """Room for one and a half surveys, two imports at once: the check and the reservation are one
    step, so exactly one is stored and the other is a 507 (both checking the same free space
    would store both)."""
    size = _survey_bytes(tiny_survey)
    _limit(client, _used(client) + size * 3 // 2)
    with ThreadPoolExecutor(2) as ex:
        codes = sorted(r.status_code for r in ex.map(lambda i: import_zip(client, tiny_zip, f"s{i}.zip"), range(2)))
    assert codes == [201, 507]
    assert len(client.get("/api/surveys").json()) == 1
    assert list((Path(client.app.state.settings.data_dir) / "tmp").iterdir()) == []


def test_running_count_matches_the_files(client, tiny_survey, tiny_zip, tmp_path, no_rewalk):
    """Between walks of the data directory the count is kept by adding what each upload stores and
    subtracting what removals free (hard-linked snapshot files counted once): after imports, flight
    uploads (one replacing a flight: the old snapshot pruned), a PATCH, a DEM put and removed, and a
    survey deleted, it equals the files actually there."""
    data_dir = Path(client.app.state.settings.data_dir)
    store = client.app.state.store
    first = _used(client)                          # the one walk: the SQLite file and nothing else
    db_then = first - store.usage_bytes([data_dir / "surveys"])

    def check():
        assert _used(client) - db_then == store.usage_bytes([data_dir / "surveys"])

    sid = import_zip(client, tiny_zip).json()["id"]
    check()
    files_in, form = _flight(tiny_survey)
    assert client.post(f"/api/surveys/{sid}/flights", files=files_in, data=form).status_code == 201
    check()
    assert client.post(f"/api/surveys/{sid}/flights", files=files_in, data=form).status_code == 201
    check()
    assert client.patch(f"/api/surveys/{sid}", json={"survey": {"name": "renamed"}}).status_code == 200
    check()
    dem = make_dem(tmp_path / "dem.tif").read_bytes()
    assert client.put(f"/api/surveys/{sid}/dem", files={"dem": ("dem.tif", dem)}).status_code == 200
    check()
    assert client.delete(f"/api/surveys/{sid}/dem").status_code == 200
    check()
    other = import_zip(client, tiny_zip).json()["id"]
    assert client.delete(f"/api/surveys/{sid}").status_code == 204
    check()
    assert client.delete(f"/api/surveys/{other}").status_code == 204
    check()
    assert _used(client) == first


def test_deleting_frees_room_at_once(client, tiny_survey, tiny_zip, no_rewalk):
    """The store full, deleting a survey makes room for the next import at once (not at the next
    walk of the data directory)."""
    sid = import_zip(client, tiny_zip).json()["id"]
    _limit(client, _used(client) + _survey_bytes(tiny_survey) // 2)
    assert import_zip(client, tiny_zip).status_code == 507
    assert client.delete(f"/api/surveys/{sid}").status_code == 204
    assert import_zip(client, tiny_zip).status_code == 201


def test_job_results_counted_when_the_job_ends(client, tiny_zip, no_rewalk):
    """A job writes its results outside any upload: its end makes the next count walk the data
    directory, so they count (without it they would wait for the next walk, here never).  The wait
    for the job monitor's hook is a poll with a 30 s deadline, a hang guard."""
    sid = import_zip(client, tiny_zip).json()["id"]
    used = _used(client)
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    assert wait_job(client, job["id"])["status"] == "succeeded"
    store = client.app.state.store
    results = store.usage_bytes([store.survey_dir(sid) / "results"])
    assert results > 10_000
    t_end = time.monotonic() + 30
    while _used(client) < used + results:
        assert time.monotonic() < t_end, (used, results, _used(client))
        time.sleep(0.05)


def test_full_store_queues_no_job(client, tiny_zip):
    """A job writes results: at its limit the store queues none (507 naming the limit, no job
    recorded, the survey's result unchanged); with room again the same job runs."""
    sid = import_zip(client, tiny_zip).json()["id"]
    _limit(client, _used(client))
    r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": {}})
    assert r.status_code == 507 and "AEROGRAV_MAX_STORE_MB" in r.json()["detail"], r.text[:300]
    assert client.get(f"/api/surveys/{sid}/jobs").json() == []
    assert client.get(f"/api/surveys/{sid}").json()["result_job_id"] is None
    _limit(client, _used(client) + 2**30)
    r = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process", "params": {}})
    assert r.status_code == 201, r.text[:300]
    assert wait_job(client, r.json()["id"])["status"] == "succeeded"
