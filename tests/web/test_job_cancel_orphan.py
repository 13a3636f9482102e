"""A job cancelled (or whose survey was deleted) while its pipeline was finishing must not
leave its result folder behind: the pipeline returns, the folder is moved into place, and the
job's row is no longer 'running' when the success is to be recorded."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import update

from app.web.db import Job, Survey, session_factory
from app.web.jobs import execute_job

DB = {}


def cancelling_pipeline(input_dir, out_dir, overrides=None, progress=None):
    """Writes a result, cancels its own job in the database (as the web's cancel or a survey
    delete would, meanwhile), and returns without reporting progress again."""
    (Path(out_dir) / "lines.parquet").write_bytes(b"x")
    with session_factory(DB["url"])() as s:
        s.execute(update(Job).where(Job.id == DB["job"]).values(status="cancelled"))
        s.commit()
    return {"ok": True}


def finishing_pipeline(input_dir, out_dir, overrides=None, progress=None):
    (Path(out_dir) / "lines.parquet").write_bytes(b"x")
    return {"ok": True}


def _job(tmp_path) -> tuple[str, int]:
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    with session_factory(url)() as s:
        sv = Survey(name="s")
        s.add(sv)
        s.flush()
        job = Job(survey_id=sv.id, kind="process", params={})
        s.add(job)
        s.commit()
        return url, job.id


def test_cancelled_while_finishing_leaves_no_result_folder(tmp_path):
    url, jid = _job(tmp_path)
    DB.update(url=url, job=jid)
    out = tmp_path / "results" / "job-1"
    status = execute_job(jid, url, f"{__name__}:cancelling_pipeline", str(tmp_path), str(out), "process", {})
    assert status == "cancelled"
    assert not out.exists() and not out.with_name(out.name + ".partial").exists()


def test_finished_job_keeps_its_result_folder(tmp_path):
    url, jid = _job(tmp_path)
    out = tmp_path / "results" / "job-1"
    status = execute_job(jid, url, f"{__name__}:finishing_pipeline", str(tmp_path), str(out), "process", {})
    assert status == "succeeded" and (out / "lines.parquet").exists()
