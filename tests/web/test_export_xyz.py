"""``GET /api/surveys/{id}/export?format=xyz``: ``lines.xyz`` is written beside the result at the
first request — once under concurrent first requests, atomically, and never served in part."""

from __future__ import annotations

import errno
import os
import threading
from pathlib import Path

import pytest

from .conftest import import_zip, wait_job


@pytest.fixture
def processed(client, tiny_zip):
    """A survey with a current result (fake pipeline): (client, survey id, result folder)."""
    sid = import_zip(client, tiny_zip).json()["id"]
    job = client.post(f"/api/surveys/{sid}/jobs", json={"kind": "process"}).json()
    assert wait_job(client, job["id"])["status"] == "succeeded"
    from app.web.db import Result, Survey
    with client.app.state.Session() as db:
        rdir = Path(db.get(Result, db.get(Survey, sid).current_result_id).dir)
    assert (rdir / "lines.parquet").is_file() and not (rdir / "lines.xyz").exists()
    return client, sid, rdir


def _leftovers(rdir: Path) -> list[str]:
    """Temporary files of atomic writes left in the result folder."""
    return sorted(p.name for p in rdir.iterdir() if p.name.startswith("."))


def test_concurrent_first_xyz_exports_write_once_and_serve_the_whole_file(processed, monkeypatch):
    """Two first requests at once: the second used to find no lines.xyz and write one of its own
    (reading the whole lines.parquet again: N requests, N copies of the work and the memory). The
    first writer is held inside the write until the second request is done or has waited 1 s; the
    file is written once and both responses are the whole, identical file, with no temporary file
    left.  (The pause only gives the old code's second request time to reach the writer; nothing
    asserts how long anything took: the threads' 60 s joins only guard against a hang.)"""
    import app.io.export as export

    client, sid, rdir = processed
    real = export.write_lines_xyz
    calls: list[Path] = []
    first_inside, release = threading.Event(), threading.Event()

    def held_writer(path, *a, **kw):
        calls.append(Path(path))
        if len(calls) == 1:
            first_inside.set()
            release.wait(30)
        else:
            release.set()          # a second writer: the old code's duplicate work
        return real(path, *a, **kw)

    monkeypatch.setattr(export, "write_lines_xyz", held_writer)
    responses: dict[str, object] = {}

    def get(key):
        responses[key] = client.get(f"/api/surveys/{sid}/export", params={"format": "xyz"})

    a = threading.Thread(target=get, args=("a",))
    a.start()
    assert first_inside.wait(60), "the first request never reached the writer"
    b = threading.Thread(target=get, args=("b",))
    b.start()
    b.join(1.0)                    # new code: b waits on the survey's lock; old code: b is writing
    release.set()
    a.join(60)
    b.join(60)
    assert not a.is_alive() and not b.is_alive(), "an export request hung"
    assert len(calls) == 1, f"lines.xyz written {len(calls)} times"
    whole = (rdir / "lines.xyz").read_bytes()
    assert whole.count(b"\n") > 100
    for key in ("a", "b"):
        r = responses[key]
        assert r.status_code == 200, r.text[:300]
        assert r.content == whole
    assert _leftovers(rdir) == []
    # later requests serve the stored file without writing it again
    assert client.get(f"/api/surveys/{sid}/export", params={"format": "xyz"}).content == whole
    assert len(calls) == 1


def test_xyz_write_failing_half_way_leaves_no_file_to_serve(processed, monkeypatch):
    """A write that fails half-way (here: an I/O error after half the file) leaves neither
    lines.xyz nor its temporary file: the request is an error naming the I/O failure, and the next
    request writes and serves the whole file (a lines.xyz left half-written would be served, cut,
    for good)."""
    import app.io.xyz as xyz

    client, sid, rdir = processed
    real = xyz.write_xyz

    def failing(path, *a, **kw):
        real(path, *a, **kw)
        size = os.path.getsize(path)
        with open(path, "r+b") as fh:
            fh.truncate(size // 2)
        raise OSError(errno.EIO, "simulated I/O error")

    monkeypatch.setattr(xyz, "write_xyz", failing)
    r = client.get(f"/api/surveys/{sid}/export", params={"format": "xyz"})
    assert r.status_code == 500 and "I/O error" in r.json()["detail"], r.text[:300]
    assert not (rdir / "lines.xyz").exists() and _leftovers(rdir) == []
    monkeypatch.setattr(xyz, "write_xyz", real)
    r = client.get(f"/api/surveys/{sid}/export", params={"format": "xyz"})
    assert r.status_code == 200 and r.content == (rdir / "lines.xyz").read_bytes()
    from app.io.xyz import scan_xyz
    assert scan_xyz(rdir / "lines.xyz").names


def test_xyz_of_a_result_without_line_data_is_a_404(processed):
    """A result without lines.parquet (an identification, or a damaged folder) has no line data
    to export: a 404 naming lines.parquet, where the export answered with a 500 (FileResponse of a
    lines.xyz that was never written)."""
    client, sid, rdir = processed
    (rdir / "lines.parquet").unlink()
    r = client.get(f"/api/surveys/{sid}/export", params={"format": "xyz"})
    assert r.status_code == 404 and "lines.parquet" in r.json()["detail"], r.text[:300]
    assert not (rdir / "lines.xyz").exists()


def test_leftover_temporary_files_removed_at_start(processed, make_client):
    """A server stopped in the middle of an export leaves the atomic write's temporary file in the
    result folder; the next start removes it once it is older than the staging age (another server
    may share the data directory), and keeps the results' own files and recent ones."""
    client, sid, rdir = processed
    old = rdir / ".lines.0123456789ab.tmp.xyz"
    old.write_bytes(b"half")
    os.utime(old, (1e9, 1e9))
    recent = rdir / ".lines.ba9876543210.tmp.xyz"
    recent.write_bytes(b"half")
    before = sorted(p.name for p in rdir.iterdir() if not p.name.startswith("."))
    make_client(data_dir=client.app.state.settings.data_dir)  # a restart
    assert not old.exists() and recent.exists()
    assert sorted(p.name for p in rdir.iterdir() if not p.name.startswith(".")) == before
