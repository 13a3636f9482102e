"""Operations shared by the routers, ``serve --bootstrap`` and tests: import a survey
directory, start a job.  Routers stay thin; these functions hold the store logic."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, Callable

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.io.errors import InputError

from .db import ACTIVE_STATES, Flight, Job, Line, Survey, utcnow
from .jobs import JobManager
from .store import Store, relativize, survey_qc


def validate(reader: Callable, root: Path):
    """``reader(root)`` with file names in errors relative to the survey directory."""
    try:
        return reader(root)
    except InputError as e:
        raise relativize(e, root)


def replace_metadata(db: Session, s: Survey, survey) -> None:
    flights, lines = survey_qc(survey)
    s.flights.clear()
    s.lines.clear()
    db.flush()
    for name, qc in flights.items():
        s.flights.append(Flight(name=name, qc=qc))
    for ln in lines:
        s.lines.append(Line(line=ln["line"], flight=ln["flight"], kind=ln["kind"], t_start=ln["t_start"],
                            t_end=ln["t_end"], qc={**ln["qc"], "track": ln["track"]}, track=ln.get("map_track") or {}))
    crs = getattr(getattr(getattr(survey, "config", None), "survey", None), "crs", None)
    if crs:
        s.crs = crs
    elif s.lines and s.lines[0].track:
        s.crs = s.lines[0].track.get("crs")


def install_snapshot(db: Session, store: Store, s: Survey, staged_root: Path, survey) -> None:
    """Rename the validated staging dir into place and switch the pointer in one commit."""
    final = store.new_input_dir(s.id)
    store.commit_dir(staged_root, final)
    try:
        s.input_dir = str(final)
        replace_metadata(db, s, survey)
        db.commit()
    except Exception:
        db.rollback()
        shutil.rmtree(final, ignore_errors=True)
        raise


def survey_name(survey, fallback: str) -> str:
    name = getattr(getattr(getattr(survey, "config", None), "survey", None), "name", None)
    return name if name and name != "survey" else fallback


def import_survey_tree(db: Session, store: Store, reader: Callable, root: Path, fallback_name: str) -> Survey:
    """Validate the survey directory ``root`` (already staged under the store's tmp) and store it."""
    survey = validate(reader, root)
    s = Survey(name=survey_name(survey, fallback_name))
    db.add(s)
    db.flush()
    try:
        install_snapshot(db, store, s, root, survey)
    except Exception:
        db.rollback()
        raise
    return s


def import_survey_dir(db: Session, store: Store, reader: Callable, src: Path) -> Survey:
    """Copy a survey directory from anywhere into staging, validate, store."""
    staging = store.staging_dir()
    try:
        root = staging / Path(src).name
        shutil.copytree(src, root, ignore=shutil.ignore_patterns("truth", "__pycache__", ".*"))
        return import_survey_tree(db, store, reader, root, Path(src).name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


class JobConflict(Exception):
    pass


def start_job(db: Session, store: Store, jobs: JobManager, s: Survey, kind: str, params: dict[str, Any]) -> Job:
    if not s.input_dir:
        raise JobConflict("the survey has no data yet: import a survey or upload a flight first")
    active = db.scalars(select(Job).where(Job.survey_id == s.id, Job.status.in_(ACTIVE_STATES))).first()
    if active is not None:
        raise JobConflict(f"job {active.id} is still {active.status} on this survey; cancel it or wait")
    job = Job(survey_id=s.id, kind=kind, params=params, status="queued", progress=0.0, stage="queued",
              em_iterations=[], backend=jobs.backend, input_dir=s.input_dir)
    db.add(job)
    db.flush()
    job.out_dir = str(store.job_out_dir(s.id, job.id))
    db.commit()
    try:
        jobs.submit(job)
    except Exception as e:  # e.g. the Dask scheduler is unreachable
        job.status, job.error, job.finished_at = "failed", f"could not start the job: {e}", utcnow()
        db.commit()
    db.refresh(job)
    return job
