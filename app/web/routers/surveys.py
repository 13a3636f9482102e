"""Surveys: create, list, import a zipped survey directory, upload flights, QC."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Response, UploadFile
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from ..db import Job, Line, Result, Survey
from ..deps import (
    STORE_FULL,
    get_cache,
    get_db,
    get_settings,
    get_store,
    get_survey_or_404,
    get_survey_reader,
    get_views,
    of_results,
    room_for_a_survey,
    store_has_room,
)
from ..schemas import (
    FlightOut,
    JobOut,
    LineOut,
    QCOut,
    SurveyCreate,
    SurveyOut,
    SurveyPatch,
    SurveyUploadOut,
    TrackLine,
    TracksOut,
)
from ..services import (
    LINES_PAGE_DEFAULT,
    LINES_PAGE_MAX,
    MAX_LINES_BYTES,
    MAX_SURVEY_LINES,
    JobConflict,
    NoInput,
    SettingsRejected,
    StorageBudgetExceeded,
    SurveyConflict,
    add_flight,
    delete_survey,
    has_dem,
    import_survey_tree,
    line_page,
    patch_survey,
    replace_dem,
    result_outdated,
    survey_settings,
)
from ..settings import Settings
from ..store import SAFE_NAME, ResultCache, Store, extract_survey_zip

router = APIRouter(prefix="/api/surveys", tags=["surveys"])


def job_out(j: Job) -> JobOut:
    return JobOut(id=j.id, survey_id=j.survey_id, kind=j.kind, status=j.status, progress=j.progress or 0.0,
                  stage=j.stage, em_iterations=j.em_iterations or [], error=j.error, params=j.params or {},
                  backend=j.backend, created_at=j.created_at, started_at=j.started_at, finished_at=j.finished_at)


def survey_out(db: Session, s: Survey, warnings: list[str] | None = None) -> SurveyOut:
    """The survey as the API gives it; with ``warnings`` (an upload's or import's) a :class:`SurveyUploadOut`."""
    last = db.scalars(select(Job).where(Job.survey_id == s.id).order_by(Job.id.desc()).limit(1)).first()
    # counted, not loaded: a survey's Line rows carry their QC and map track (20,000 lines took 1.5 s
    # to load for every listing of the surveys)
    n_lines = len(s.lines) if "lines" in s.__dict__ else db.scalar(
        select(func.count()).select_from(Line).where(Line.survey_id == s.id))
    # the job whose result is current: the newest job may since have been cancelled or failed, and the
    # survey list must not read that as "no result"
    res = db.get(Result, s.current_result_id) if s.current_result_id is not None else None
    fields = dict(id=s.id, name=s.name, created_at=s.created_at, crs=s.crs,
                  flights=[f.name for f in s.flights], n_lines=n_lines, has_input=bool(s.input_dir),
                  current_result_id=s.current_result_id, result_job_id=res.job_id if res is not None else None,
                  result_outdated=result_outdated(db, s),
                  settings=survey_settings(s), last_job=job_out(last) if last else None, has_dem=has_dem(s))
    return SurveyOut(**fields) if warnings is None else SurveyUploadOut(**fields, warnings=warnings)


#: the answer when the store is at its limit (AEROGRAV_MAX_STORE_MB)


@router.post("", response_model=SurveyOut, status_code=201,
             dependencies=[Depends(store_has_room), Depends(room_for_a_survey)],
             responses=STORE_FULL)
def create_survey(body: SurveyCreate, db: Session = Depends(get_db)) -> SurveyOut:
    """An empty survey; add flights with POST /api/surveys/{id}/flights."""
    s = Survey(name=body.name)
    db.add(s)
    db.commit()
    return survey_out(db, s)


@router.get("", response_model=list[SurveyOut])
def list_surveys(db: Session = Depends(get_db)) -> list[SurveyOut]:
    return [survey_out(db, s) for s in db.scalars(select(Survey).order_by(Survey.id))]


@router.get("/{survey_id}", response_model=SurveyOut)
def get_survey(s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db)) -> SurveyOut:
    return survey_out(db, s)


@router.patch("/{survey_id}", response_model=SurveyOut,
              responses={401: {"description": "token missing or wrong"}, 404: {"description": "no such survey"},
                         409: {"description": "no data yet (only the name can be set), or changed meanwhile"},
                         422: {"description": "invalid value: the detail names the field (section.key)"},
                         **STORE_FULL})
def update_survey(body: SurveyPatch, s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
                  store: Store = Depends(get_store), reader: Callable = Depends(get_survey_reader),
                  settings: Settings = Depends(get_settings)) -> SurveyOut:
    """Change survey.toml fields (name, CRS, normal gravity, gravimeter model, τ, scale, rate, base
    gravity): validated like survey.toml, stored as a new input snapshot (the current result stays
    until the survey is processed again; ``result_outdated`` says so)."""
    try:
        patch_survey(db, store, reader, s, body, budget_bytes=settings.survey_storage_bytes,
                     store_limit_bytes=settings.max_store_bytes)
    except SettingsRejected as e:
        raise HTTPException(422, e.detail) from e
    except (NoInput, SurveyConflict) as e:
        raise HTTPException(409, str(e)) from e
    except StorageBudgetExceeded as e:
        raise HTTPException(413, str(e)) from e
    return survey_out(db, s)


@router.delete("/{survey_id}", status_code=204,
               responses={401: {"description": "token missing or wrong"}, 404: {"description": "no such survey"},
                          409: {"description": "a job is queued or running on the survey"}})
def remove_survey(s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
                  store: Store = Depends(get_store), cache: ResultCache = Depends(get_cache),
                  views: ResultCache = Depends(get_views)) -> Response:
    """Delete a survey with its flights, jobs, results and files (409 while a job is active)."""
    try:
        ids = set(delete_survey(db, store, s))
    except (JobConflict, SurveyConflict) as e:
        raise HTTPException(409, str(e)) from e
    for c in (cache, views):        # result ids may be reused
        c.discard(of_results(ids))
    return Response(status_code=204)


@router.post("/import", response_model=SurveyUploadOut, status_code=201,
             dependencies=[Depends(store_has_room), Depends(room_for_a_survey)],
             responses=STORE_FULL)
def import_survey(file: UploadFile = File(..., description="zip of a survey directory (may be nested one level)"),
                  db: Session = Depends(get_db), store: Store = Depends(get_store),
                  reader: Callable = Depends(get_survey_reader),
                  settings: Settings = Depends(get_settings)) -> SurveyUploadOut:
    """Validate a zipped survey directory, then store it atomically (extracted in a stream; the
    uncompressed total and every table file are limited by AEROGRAV_MAX_UNCOMPRESSED_MB).  The
    reader's warnings come back in ``warnings``."""
    staging = store.staging_dir()
    warnings: list[str] = []
    try:
        root = extract_survey_zip(file.file, staging, max_bytes=settings.max_uncompressed_bytes)
        s = import_survey_tree(db, store, reader, root, Path(file.filename or "survey.zip").stem[:300],
                               budget_bytes=settings.survey_storage_bytes,
                               store_limit_bytes=settings.max_store_bytes, notes=warnings)
        return survey_out(db, s, warnings)
    except StorageBudgetExceeded as e:
        raise HTTPException(413, str(e)) from e
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _write_upload(up: UploadFile, dest: Path) -> None:
    """Store an uploaded table as ``dest`` — as ``dest.gz`` when it is gzip-compressed (the
    client's file name is not used, so the content says which; the reader decompresses it
    under the same limits)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    head = up.file.read(2)
    up.file.seek(0)
    if head == b"\x1f\x8b":
        dest = dest.with_name(dest.name + ".gz")
    with open(dest, "wb") as fh:
        shutil.copyfileobj(up.file, fh, 1 << 20)


@router.post("/{survey_id}/flights", response_model=SurveyUploadOut, status_code=201,
             dependencies=[Depends(store_has_room)], responses=STORE_FULL)
def upload_flight(gravimeter: UploadFile = File(..., description="gravimeter.csv (or GT-1A/GT-2A G file)"),
                  gnss: UploadFile = File(..., description="gnss.csv"),
                  lines: UploadFile | None = File(None, description="lines.csv rows for this flight"),
                  flight: str | None = Form(None, description="flight name (directory name)"),
                  s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
                  store: Store = Depends(get_store), reader: Callable = Depends(get_survey_reader),
                  settings: Settings = Depends(get_settings)) -> SurveyUploadOut:
    """Add (or replace) one flight: the new survey snapshot is validated before it replaces the old one.
    Concurrent uploads to one survey are applied in turn (each one is kept).  The reader's warnings
    come back in ``warnings`` (a flight no line uses whose files cannot be read is stored but left
    out of the survey: said there, not only in the server's log)."""
    if flight is not None and not SAFE_NAME.match(flight):
        raise HTTPException(422, {"file": None, "row": None, "column": "flight",
                                  "message": f"flight name {flight[:100]!r}: use letters, digits, '_', '-', '.' "
                                             "(at most 100 characters)"})

    def write_files(fdir: Path) -> None:
        _write_upload(gravimeter, fdir / "gravimeter.csv")
        _write_upload(gnss, fdir / "gnss.csv")

    warnings: list[str] = []
    try:
        add_flight(db, store, reader, s, flight, write_files,
                   lines.file.read(MAX_LINES_BYTES + 1) if lines is not None else None,
                   budget_bytes=settings.survey_storage_bytes, store_limit_bytes=settings.max_store_bytes,
                   notes=warnings)
    except SurveyConflict as e:
        raise HTTPException(409, str(e)) from e
    except StorageBudgetExceeded as e:
        raise HTTPException(413, str(e)) from e
    return survey_out(db, s, warnings)


@router.put("/{survey_id}/dem", response_model=SurveyOut, dependencies=[Depends(store_has_room)],
            responses={404: {"description": "no such survey"}, **STORE_FULL,
                       409: {"description": "no data yet, or changed meanwhile"},
                       413: {"description": "over the upload limit or the survey's storage budget"},
                       422: {"description": "the DEM is not usable: the detail names dem.tif and what is wrong"}})
def put_dem(dem: UploadFile = File(..., description="terrain model: a GeoTIFF with its CRS (other formats, a VRT among them, are refused), "
                                   "heights in metres, covering the survey lines"),
            s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
            store: Store = Depends(get_store), reader: Callable = Depends(get_survey_reader),
            settings: Settings = Depends(get_settings)) -> SurveyOut:
    """Add or replace the survey's terrain model (``dem.tif``): checked (readable, CRS, heights,
    covers the lines), stored as a new input snapshot.  The next processing adds the terrain
    correction and the Bouguer anomaly."""
    limit = settings.max_uncompressed_bytes

    def write(dest: Path) -> None:
        with open(dest, "wb") as fh:
            size = 0
            while chunk := dem.file.read(1 << 20):
                size += len(chunk)
                if size > limit:
                    raise HTTPException(413, f"dem.tif is larger than the {limit / 2**20:.0f} MB allowed "
                                             "(AEROGRAV_MAX_UNCOMPRESSED_MB)")
                fh.write(chunk)

    try:
        replace_dem(db, store, reader, s, write, budget_bytes=settings.survey_storage_bytes,
                    store_limit_bytes=settings.max_store_bytes)
    except (NoInput, SurveyConflict) as e:
        raise HTTPException(409, str(e)) from None
    except StorageBudgetExceeded as e:
        raise HTTPException(413, str(e)) from None
    return survey_out(db, s)


@router.delete("/{survey_id}/dem", response_model=SurveyOut,
               responses={404: {"description": "no such survey"}, 409: {"description": "no data yet, or changed meanwhile"}})
def delete_dem(s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db),
               store: Store = Depends(get_store), reader: Callable = Depends(get_survey_reader)) -> SurveyOut:
    """Remove the survey's terrain model (a new input snapshot without ``dem.tif``)."""
    try:
        replace_dem(db, store, reader, s, None)
    except (NoInput, SurveyConflict) as e:
        raise HTTPException(409, str(e)) from None
    return survey_out(db, s)


#: ``?offset=`` of a line listing: past the last line the page is empty
Offset = Annotated[int, Query(ge=0, le=MAX_SURVEY_LINES, description="index of the page's first line (by id), "
                              f"0 … {MAX_SURVEY_LINES:,}")]
#: ``?limit=`` of a line listing
Limit = Annotated[int, Query(ge=0, le=LINES_PAGE_MAX, description=f"most lines in the page (default "
                             f"{LINES_PAGE_DEFAULT:,}, at most {LINES_PAGE_MAX:,}; 0: only the count)")]


@router.get("/{survey_id}/qc", response_model=QCOut)
def survey_qc_view(s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db), offset: Offset = 0,
                   limit: Limit = LINES_PAGE_DEFAULT) -> QCOut:
    """Per flight and per line: sampling rates, longest gaps, duration, length (every flight; the lines
    a page at a time, ``lines_total`` saying how many there are)."""
    rows, total = line_page(db, s, offset, limit)
    return QCOut(survey_id=s.id, flights=[FlightOut.model_validate(f) for f in s.flights],
                 lines=[LineOut(id=l.id, line=l.line, flight=l.flight, kind=l.kind, t_start=l.t_start,
                                t_end=l.t_end, qc=l.qc or {}) for l in rows],
                 lines_total=total, offset=offset, limit=limit)


@router.get("/{survey_id}/tracks", response_model=TracksOut)
def survey_tracks(s: Survey = Depends(get_survey_or_404), db: Session = Depends(get_db), offset: Offset = 0,
                  limit: Limit = LINES_PAGE_DEFAULT) -> TracksOut:
    """Decimated line tracks in the survey CRS (km) for the line map (available before processing), a
    page at a time (``lines_total`` says how many there are)."""
    rows, total = line_page(db, s, offset, limit)
    return TracksOut(survey_id=s.id, crs=s.crs or next((l.track.get("crs") for l in rows if l.track), None),
                     lines=[TrackLine(line=l.line, flight=l.flight, kind=l.kind,
                                      easting_km=(l.track or {}).get("easting_km", []),
                                      northing_km=(l.track or {}).get("northing_km", [])) for l in rows],
                     lines_total=total, offset=offset, limit=limit)
