"""Operations shared by the routers, ``serve --bootstrap`` and tests: import a survey
directory, add a flight, start a job, prune old files.  Routers stay thin; these functions
hold the store logic.

Concurrency: changes to one survey run under ``Store.survey_lock`` (uploads are kept in
turn, none lost), the snapshot pointer is switched with a conditional update (a writer in
another process that changed it meanwhile gets :class:`SurveyConflict`, HTTP 409), and the
database allows one active job per survey (a unique partial index), so two submissions can
never both start.
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil
from pathlib import Path
from typing import Any, Callable

import pandas as pd
from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.config import MAX_NAME_LENGTH, check_name
from app.io.errors import InputError

from .db import ACTIVE_STATES, Flight, Job, Line, Result, Survey, utcnow
from .jobs import JobManager
from .store import Store, link_tree, relativize, release_memory, survey_qc


class SurveyConflict(Exception):
    """The survey changed meanwhile (another writer); nothing was stored."""


class StorageBudgetExceeded(Exception):
    """The survey would use more disk than its budget; nothing was stored."""


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


def check_budget(store: Store, survey_id: int | None, staged: Path, budget_bytes: int | None) -> None:
    """The survey's files plus the staged snapshot must fit in the survey's storage budget."""
    if not budget_bytes:
        return
    dirs = [staged] + ([store.survey_dir(survey_id)] if survey_id is not None else [])
    used = store.usage_bytes(dirs)
    if used > budget_bytes:
        raise StorageBudgetExceeded(f"the survey would use {used / 2**20:.1f} MB of disk, more than its storage "
                                    f"budget of {budget_bytes / 2**20:.0f} MB (AEROGRAV_SURVEY_STORAGE_MB)")


def install_snapshot(db: Session, store: Store, s: Survey, staged_root: Path, survey,
                     expect_input_dir: str | None = None, check_expected: bool = False) -> None:
    """Rename the validated staging dir into place and switch the pointer in one commit.

    With ``check_expected`` the pointer is switched only if it still is ``expect_input_dir``
    (the snapshot the new one was built from); otherwise :class:`SurveyConflict`."""
    final = store.new_input_dir(s.id)
    store.commit_dir(staged_root, final)
    try:
        if check_expected:
            cond = (Survey.input_dir.is_(None) if expect_input_dir is None
                    else Survey.input_dir == expect_input_dir)
            r = db.execute(update(Survey).where(Survey.id == s.id, cond).values(input_dir=str(final)))
            if r.rowcount != 1:
                raise SurveyConflict(f"survey {s.id} was changed by another request meanwhile; "
                                     "nothing was stored, send it again")
        s.input_dir = str(final)
        replace_metadata(db, s, survey)
        db.commit()
    except Exception:
        db.rollback()
        shutil.rmtree(final, ignore_errors=True)
        raise


def clean_name(name: str, fallback: str = "survey") -> str:
    """A usable survey name from a file name: control characters and separators dropped, cut."""
    name = re.sub(r"[\x00-\x1f\x7f-\x9f\u2028\u2029/\\]", "", name or "").strip()[:MAX_NAME_LENGTH]
    try:
        return check_name(name)
    except ValueError:
        return fallback


def survey_name(survey, fallback: str) -> str:
    name = getattr(getattr(getattr(survey, "config", None), "survey", None), "name", None)
    return name if name and name != "survey" else clean_name(fallback)


def import_survey_tree(db: Session, store: Store, reader: Callable, root: Path, fallback_name: str,
                       budget_bytes: int | None = None) -> Survey:
    """Validate the survey directory ``root`` (already staged under the store's tmp) and store it."""
    try:
        survey = validate(reader, root)
        check_budget(store, None, root, budget_bytes)
        s = Survey(name=survey_name(survey, fallback_name))
        db.add(s)
        db.flush()
        try:
            install_snapshot(db, store, s, root, survey)
        except Exception:
            db.rollback()
            raise
        return s
    finally:
        survey = None
        release_memory()


def import_survey_dir(db: Session, store: Store, reader: Callable, src: Path) -> Survey:
    """Copy a survey directory from anywhere into staging, validate, store."""
    staging = store.staging_dir()
    try:
        root = staging / Path(src).name
        shutil.copytree(src, root, ignore=shutil.ignore_patterns("truth", "__pycache__", ".*"))
        return import_survey_tree(db, store, reader, root, Path(src).name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def toml_string(s: str) -> str:
    """A TOML basic string (JSON escapes are valid TOML for non-surrogate text)."""
    return json.dumps(s, ensure_ascii=False)


def add_flight(db: Session, store: Store, reader: Callable, s: Survey, name: str | None, write_files: Callable,
               lines_raw: bytes | None, budget_bytes: int | None = None) -> Survey:
    """Build the next snapshot (hard links to the current one + this flight's files), validate it and
    switch to it, under the survey's lock; ``write_files(flight_dir)`` writes gravimeter.csv and gnss.csv."""
    with store.survey_lock(s.id):
        db.refresh(s)
        base = s.input_dir
        name = name or f"flight{len(s.flights) + 1}"
        staging = store.staging_dir()
        try:
            root = staging / "survey"
            if base and Path(base).is_dir():
                link_tree(Path(base), root)
            else:
                root.mkdir()
                (root / "survey.toml").write_text(f"[survey]\nname = {toml_string(s.name)}\n", encoding="utf-8")
            fdir = root / "flights" / name
            shutil.rmtree(fdir, ignore_errors=True)
            fdir.mkdir(parents=True)
            write_files(fdir)
            if lines_raw is not None:
                try:
                    new = pd.read_csv(io.BytesIO(lines_raw), dtype=str, keep_default_na=False)
                except Exception as e:
                    raise InputError("lines.csv", None, None, f"cannot read the uploaded lines file: {e}")
                if "flight" not in new.columns:
                    new.insert(1 if len(new.columns) else 0, "flight", name)
                else:
                    new["flight"] = new["flight"].replace("", name)
                lp = root / "lines.csv"
                if lp.exists():
                    old = pd.read_csv(lp, dtype=str, keep_default_na=False)
                    old = old[old["flight"] != name] if "flight" in old.columns else old
                    new = pd.concat([old, new], ignore_index=True).fillna("")
                tmp = lp.with_name("lines.csv.new")
                new.to_csv(tmp, index=False)
                os.replace(tmp, lp)  # a new file: the linked one of the current snapshot is untouched
            survey = validate(reader, root)
            prune_survey(db, store, s.id)
            check_budget(store, s.id, root, budget_bytes)
            install_snapshot(db, store, s, root, survey, expect_input_dir=base, check_expected=True)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
            release_memory()
        prune_survey(db, store, s.id)
    return s


class JobConflict(Exception):
    pass


def check_grid_size(s: Survey, params: dict[str, Any]) -> None:
    """Before a job starts: the overrides merged over the survey's ``survey.toml`` are valid, and the
    grid over the stored line tracks stays within ``MAX_GRID_CELLS`` (InputError, HTTP 422)."""
    from app.config import check_grid_cells
    from app.io.survey import read_config

    if not s.input_dir or not (Path(s.input_dir) / "survey.toml").is_file():
        return
    cfg = read_config(Path(s.input_dir) / "survey.toml", params)
    e = [x for ln in s.lines for x in (ln.track or {}).get("easting_km", []) if x is not None]
    n = [x for ln in s.lines for x in (ln.track or {}).get("northing_km", []) if x is not None]
    if e and n:
        try:
            check_grid_cells(max(e) - min(e), max(n) - min(n), cfg.processing.grid_spacing_km)
        except ValueError as exc:
            raise InputError(None, None, "processing.grid_spacing_km", str(exc)) from None


def start_job(db: Session, store: Store, jobs: JobManager, s: Survey, kind: str, params: dict[str, Any]) -> Job:
    with store.survey_lock(s.id):  # the input snapshot cannot be pruned between reading and using it
        db.refresh(s)
        if not s.input_dir:
            raise JobConflict("the survey has no data yet: import a survey or upload a flight first")
        active = db.scalars(select(Job).where(Job.survey_id == s.id, Job.status.in_(ACTIVE_STATES))).first()
        if active is not None:
            raise JobConflict(f"job {active.id} is still {active.status} on this survey; cancel it or wait")
        job = Job(survey_id=s.id, kind=kind, params=params, status="queued", progress=0.0, stage="queued",
                  em_iterations=[], backend=jobs.backend, input_dir=s.input_dir)
        db.add(job)
        try:
            db.flush()  # the unique partial index allows one active job per survey
        except IntegrityError:
            db.rollback()
            raise JobConflict("another job was started on this survey meanwhile; cancel it or wait") from None
        job.out_dir = str(store.job_out_dir(s.id, job.id))
        db.commit()
    try:
        jobs.submit(job)
    except Exception as e:  # e.g. the Dask scheduler is unreachable
        job.status, job.error, job.finished_at = "failed", f"could not start the job: {e}", utcnow()
        db.commit()
    db.refresh(job)
    return job


def keep_set(db: Session, survey_id: int) -> set[str]:
    """Paths of a survey that must stay: the current input, the inputs and outputs of active jobs,
    and the current and previous results with the inputs they were computed from."""
    s = db.get(Survey, survey_id)
    if s is None:
        return set()
    keep = {s.input_dir} if s.input_dir else set()
    for j in db.scalars(select(Job).where(Job.survey_id == survey_id, Job.status.in_(ACTIVE_STATES))):
        keep |= {j.input_dir, j.out_dir}
    results = list(db.scalars(select(Result).where(Result.survey_id == survey_id).order_by(Result.id.desc())))
    current = [r for r in results if r.id == s.current_result_id]
    previous = [r for r in results if s.current_result_id is None or r.id < s.current_result_id][:1]
    for r in current + previous:
        keep.add(r.dir)
        j = db.get(Job, r.job_id)
        if j is not None:
            keep.add(j.input_dir)
    return {k for k in keep if k}


def prune_survey(db: Session, store: Store, survey_id: int) -> list[Path]:
    """Remove the survey's input snapshots and result folders that are no longer needed."""
    with store.survey_lock(survey_id):
        return store.prune(survey_id, keep_set(db, survey_id))
