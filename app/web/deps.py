"""FastAPI dependencies: settings, database session, store, job manager, survey reader."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request
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


def get_views(request: Request) -> ResultCache:
    """The re-smoothed recognition maps (``GET /recognition?h=&rho=``), apart from the loaded results:
    slider moves must not push loaded results out of :func:`get_cache`."""
    return request.app.state.views


def of_results(result_ids) -> Callable[[object], bool]:
    """Predicate on cache keys ``(name, result id, …)``: those of the given results."""
    ids = set(result_ids)
    return lambda k: isinstance(k, tuple) and len(k) >= 2 and k[1] in ids


#: the OpenAPI description of :func:`store_has_room`'s refusal
STORE_FULL = {507: {"description": "the server's store is full: the detail says how much it holds and its limit"}}


def store_has_room(store: Store = Depends(get_store), settings: Settings = Depends(get_settings)) -> None:
    """Refuse a request that would store more (a new survey, an upload, a job's results) while the
    store holds its limit already (:class:`~app.web.store.StoreFull`, HTTP 507), before anything is
    extracted, validated or queued; what an upload adds is checked once it is staged
    (:meth:`Store.reserve`)."""
    store.check_room(settings.max_store_bytes)


def room_for_a_survey(db: Session = Depends(get_db), settings: Settings = Depends(get_settings)) -> None:
    """Refuse a new survey (create or import) when the store holds ``AEROGRAV_MAX_SURVEYS`` already
    (HTTP 507, before anything is read)."""
    from sqlalchemy import func, select

    n = db.scalar(select(func.count()).select_from(Survey))
    if n >= settings.max_surveys:
        raise HTTPException(507, f"the server holds {n:,} surveys, the most allowed (AEROGRAV_MAX_SURVEYS = "
                                 f"{settings.max_surveys:,}); nothing was stored — delete surveys no longer needed")


def get_survey_reader(request: Request) -> Callable:
    """``read_survey(path)`` validating a survey directory (raises InputError), with the upload
    limits on every table file (size, decompressed while reading, and rows)."""
    from app.io.survey import read_survey
    from app.io.tables import table_limits

    settings: Settings = request.app.state.settings

    def read(path, overrides=None):
        with table_limits(settings.max_uncompressed_bytes, settings.max_table_rows):
            return read_survey(path, overrides)
    return read


#: a database id (SQLite and PostgreSQL integers are 64-bit: larger ids are a 422, not a 500)
SurveyId = Annotated[int, Path(ge=0, le=2**63 - 1, description="survey id")]
JobId = Annotated[int, Path(ge=0, le=2**63 - 1, description="job id")]


def get_survey_or_404(survey_id: SurveyId, db: Session = Depends(get_db)) -> Survey:
    s = db.get(Survey, survey_id)
    if s is None:
        raise HTTPException(404, f"survey {survey_id} not found")
    return s
