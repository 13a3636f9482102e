"""FastAPI dependencies: settings, database session, store, job manager, survey reader."""

from __future__ import annotations

from typing import Callable, Iterator

from fastapi import Depends, HTTPException, Request
from sqlalchemy.orm import Session

from .db import Survey
from .jobs import JobManager
from .settings import Settings
from .store import ResultCache, Store


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_db(request: Request) -> Iterator[Session]:
    with request.app.state.Session() as s:
        yield s


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_jobs(request: Request) -> JobManager:
    return request.app.state.jobs


def get_cache(request: Request) -> ResultCache:
    return request.app.state.cache


def get_survey_reader() -> Callable:
    """``read_survey(path)`` validating a survey directory (raises InputError)."""
    from app.io.survey import read_survey
    return read_survey


def get_survey_or_404(survey_id: int, db: Session = Depends(get_db)) -> Survey:
    s = db.get(Survey, survey_id)
    if s is None:
        raise HTTPException(404, f"survey {survey_id} not found")
    return s
