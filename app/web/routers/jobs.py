"""Jobs: submit processing on a survey, watch progress and EM iterations, cancel."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException
from pydantic import ValidationError
from sqlalchemy import select
from sqlalchemy.orm import Session

from app.config import ProcessingParams

from ..db import ACTIVE_STATES, Job, Survey
from ..deps import JobId, get_db, get_jobs, get_store, get_survey_or_404
from ..errors import validation_detail
from ..jobs import JobManager
from ..schemas import JobCreate, JobOut
from ..services import JobConflict, SurveyConflict, check_grid_size, start_job
from ..store import Store
from .surveys import job_out

router = APIRouter(tags=["jobs"])


@router.post("/api/surveys/{survey_id}/jobs", response_model=JobOut, status_code=201)
def create_job(body: JobCreate, s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
               store: Store = Depends(get_store), jobs: JobManager = Depends(get_jobs)) -> JobOut:
    """Queue a job.  ``params`` are ProcessingParams overrides (422 when invalid)."""
    try:
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
