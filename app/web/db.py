"""Persistent store: SQLAlchemy models for surveys, flights, lines, jobs and results.

Metadata lives in the database (SQLite by default); arrays live in files under the
data directory.  A survey points to its current input snapshot (``input_dir``) and
to its current result (``current_result_id``); both pointers are switched in one
transaction only after the new files are complete, so a failed upload or job never
leaves a survey half-written.

At most one job per survey is active (queued or running): a unique partial index says so, so
concurrent submissions cannot both succeed whatever the timing.
"""

from __future__ import annotations

import datetime as dt
import logging
from typing import Any

from sqlalchemy import JSON, Float, ForeignKey, Index, Integer, String, Text, create_engine, event, text, update
from sqlalchemy.engine import Engine
from sqlalchemy.exc import IntegrityError, OperationalError
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship, sessionmaker

JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
ACTIVE_STATES = ("queued", "running")
_ACTIVE_SQL = "status IN ('queued', 'running')"
log = logging.getLogger("aerograv.web.db")


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC).replace(tzinfo=None)


class Base(DeclarativeBase):
    pass


#: Ids are never handed out again after a delete (SQLite's AUTOINCREMENT; without it the next row
#: takes max(id) + 1, so a retried DELETE from a stale tab removed the survey created since).
_NO_ID_REUSE = {"sqlite_autoincrement": True}


class Survey(Base):
    __tablename__ = "surveys"
    __table_args__ = _NO_ID_REUSE
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    input_dir: Mapped[str | None] = mapped_column(Text, nullable=True)  # current input snapshot
    current_result_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    crs: Mapped[str | None] = mapped_column(Text, nullable=True)
    flights: Mapped[list[Flight]] = relationship(back_populates="survey", cascade="all, delete-orphan",
                                                   order_by="Flight.name")
    lines: Mapped[list[Line]] = relationship(back_populates="survey", cascade="all, delete-orphan",
                                               order_by="Line.id")


class Flight(Base):
    __tablename__ = "flights"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    survey_id: Mapped[int] = mapped_column(ForeignKey("surveys.id"), index=True)
    name: Mapped[str] = mapped_column(String(200))
    qc: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    survey: Mapped[Survey] = relationship(back_populates="flights")


class Line(Base):
    __tablename__ = "lines"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    survey_id: Mapped[int] = mapped_column(ForeignKey("surveys.id"), index=True)
    line: Mapped[str] = mapped_column(String(200))
    flight: Mapped[str] = mapped_column(String(200))
    kind: Mapped[str] = mapped_column(String(16))
    t_start: Mapped[float] = mapped_column(Float)
    t_end: Mapped[float] = mapped_column(Float)
    qc: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    track: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # decimated easting_km/northing_km
    survey: Mapped[Survey] = relationship(back_populates="lines")


class Job(Base):
    __tablename__ = "jobs"
    __table_args__ = (Index("uq_jobs_one_active_per_survey", "survey_id", unique=True,
                            sqlite_where=text(_ACTIVE_SQL), postgresql_where=text(_ACTIVE_SQL)), _NO_ID_REUSE)
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    survey_id: Mapped[int] = mapped_column(ForeignKey("surveys.id"), index=True)
    kind: Mapped[str] = mapped_column(String(16))
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    status: Mapped[str] = mapped_column(String(16), default="queued", index=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[str | None] = mapped_column(String(200), nullable=True)
    em_iterations: Mapped[list[dict[str, Any]]] = mapped_column(JSON, default=list)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    backend: Mapped[str] = mapped_column(String(16), default="local")
    worker_pid: Mapped[int | None] = mapped_column(Integer, nullable=True)
    input_dir: Mapped[str | None] = mapped_column(Text, nullable=True)
    out_dir: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)
    started_at: Mapped[dt.datetime | None] = mapped_column(nullable=True)
    finished_at: Mapped[dt.datetime | None] = mapped_column(nullable=True)


class Result(Base):
    __tablename__ = "results"
    __table_args__ = _NO_ID_REUSE
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    survey_id: Mapped[int] = mapped_column(ForeignKey("surveys.id"), index=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id"))
    dir: Mapped[str] = mapped_column(Text)
    report: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    created_at: Mapped[dt.datetime] = mapped_column(default=utcnow)


_ENGINES: dict[str, Engine] = {}


def get_engine(url: str) -> Engine:
    """One engine per URL and process; SQLite in WAL mode with a generous busy timeout
    so that worker processes and the server can write concurrently."""
    eng = _ENGINES.get(url)
    if eng is None:
        if url.startswith("sqlite"):
            eng = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False})

            @event.listens_for(eng, "connect")
            def _pragmas(dbapi_conn, _rec):  # pragma: no cover - trivial
                cur = dbapi_conn.cursor()
                cur.execute("PRAGMA journal_mode=WAL")
                cur.execute("PRAGMA synchronous=NORMAL")
                cur.execute("PRAGMA foreign_keys=ON")
                cur.close()
        else:
            eng = create_engine(url, pool_pre_ping=True)
        Base.metadata.create_all(eng)
        ensure_indexes(eng)
        _ENGINES[url] = eng
    return eng


def ensure_indexes(eng: Engine) -> None:
    """Indexes added after a data directory was created (``create_all`` skips existing tables).
    Duplicate active jobs left by an older version are failed first: only the newest stays."""
    for idx in Job.__table__.indexes:
        try:
            idx.create(eng, checkfirst=True)
        except IntegrityError:
            with eng.begin() as c:
                rows = c.execute(text(f"SELECT id, survey_id FROM jobs WHERE {_ACTIVE_SQL} ORDER BY id DESC")).all()
                seen: set[int] = set()
                for jid, sid in rows:
                    if sid in seen:
                        c.execute(update(Job).where(Job.id == jid).values(
                            status="failed", error="another job was active on this survey", finished_at=utcnow()))
                    seen.add(sid)
            idx.create(eng, checkfirst=True)
        except OperationalError as exc:  # e.g. a database that does not support partial indexes
            log.warning("index %s not created: %s", idx.name, exc)


def session_factory(url: str) -> sessionmaker:
    return sessionmaker(bind=get_engine(url), expire_on_commit=False)
