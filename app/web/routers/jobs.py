"""Jobs: submit processing on a survey, watch progress and EM iterations, cancel."""

from __future__ import annotations

import functools
import json

from fastapi import APIRouter, Depends, HTTPException
from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.config import ProcessingParams

from ..db import ACTIVE_STATES, Job, Survey
from ..deps import STORE_FULL, JobId, get_db, get_jobs, get_store, get_survey_or_404, store_has_room
from ..errors import validation_detail
from ..jobs import JobManager
from ..schemas import JobCreate, JobOut
from ..services import JobConflict, SurveyConflict, check_grid_size, start_job
from ..store import Store
from .surveys import job_out

router = APIRouter(tags=["jobs"])


@functools.cache
def _param_types() -> dict[str, set[str]]:
    """JSON types each ProcessingParams field takes (from its JSON schema)."""
    out = {}
    for k, prop in ProcessingParams.model_json_schema().get("properties", {}).items():
        alts = prop.get("anyOf", [prop])
        out[k] = {a.get("type") for a in alts if a.get("type")}
    return out


def _wrong_json_types(params: dict) -> list[dict]:
    """Parameters whose JSON type is not the field's: ``true`` for a number, ``"2"`` for a number
    or ``"yes"`` for a boolean are refused (pydantic's lax mode would read them as 1, 2, True),
    while ``2`` for a number and ``1e9`` for an integer still reach the bounds checks."""
    errors = []
    types = _param_types()
    for k, v in params.items():
        want = types.get(k, set())
        numeric = want & {"integer", "number"}
        if isinstance(v, bool) and numeric and "boolean" not in want:
            errors.append({"loc": [k], "msg": f"a number is expected, not {json.dumps(v)}", "type": "type_error"})
        elif isinstance(v, str) and (numeric or "boolean" in want) and "string" not in want:
            what = "a number" if numeric else "true or false"
            errors.append({"loc": [k], "msg": f"{what} is expected, not a string", "type": "type_error",
                           "input": v[:100]})
        elif not isinstance(v, bool) and "boolean" in want and not (numeric or "string" in want) and v is not None:
            errors.append({"loc": [k], "msg": f"true or false is expected, not {json.dumps(v)[:100]}",
                           "type": "type_error"})
    return errors


@router.post("/api/surveys/{survey_id}/jobs", response_model=JobOut, status_code=201,
             dependencies=[Depends(store_has_room)], responses=STORE_FULL)
def create_job(body: JobCreate, s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
               store: Store = Depends(get_store), jobs: JobManager = Depends(get_jobs)) -> JobOut:
    """Queue a job.  ``params`` are ProcessingParams overrides (422 when invalid); 507 while the store
    is at its limit (the job's results would go above it)."""
    try:
        wrong = _wrong_json_types(body.params)
        if wrong:
            raise HTTPException(422, validation_detail(wrong))
        params = ProcessingParams.model_validate(body.params).model_dump(exclude_unset=True, mode="json")
    except ValidationError as e:
        raise HTTPException(422, validation_detail(e.errors())) from e
    check_grid_size(s, params)
    try:
        job = start_job(db, store, jobs, s, body.kind, params)
    except (JobConflict, SurveyConflict) as e:
        raise HTTPException(409, str(e)) from e
    return job_out(job)


@router.get("/api/surveys/{survey_id}/jobs", response_model=list[JobOut])
def list_jobs(s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db)) -> list[JobOut]:
    return [job_out(j) for j in db.scalars(select(Job).where(Job.survey_id == s.id).order_by(Job.id.desc()))]


def _job_or_404(db: Session, job_id: int) -> Job:
    j = db.get(Job, job_id)
    if j is None:
        raise HTTPException(404, f"job {job_id} not found")
    return j


@router.get("/api/jobs/{job_id}", response_model=JobOut)
def get_job(job_id: JobId, db: Session = Depends(get_db)) -> JobOut:
    return job_out(_job_or_404(db, job_id))


@router.post("/api/jobs/{job_id}/cancel", response_model=JobOut)
def cancel_job(job_id: JobId, db: Session = Depends(get_db), jobs: JobManager = Depends(get_jobs)) -> JobOut:
    """Cancel a queued or running job (409 when it already finished)."""
    j = _job_or_404(db, job_id)
    if j.status not in ACTIVE_STATES:
        raise HTTPException(409, f"job {job_id} is already {j.status}")
    jobs.cancel(job_id)
    db.expire_all()
    return job_out(_job_or_404(db, job_id))
