"""Web application settings (pydantic-settings, environment prefix ``AEROGRAV_``).

``AEROGRAV_DATA_DIR``      where surveys, results and the default SQLite file live
``AEROGRAV_DATABASE_URL``  any SQLAlchemy URL; default ``sqlite:///<DATA_DIR>/aerograv.db``
``AEROGRAV_DASK_SCHEDULER`` address of a Dask scheduler; jobs run there when set
``AEROGRAV_TOKEN``         when set, every mutating request needs ``Authorization: Bearer <token>``
``AEROGRAV_MAX_UPLOAD_MB`` request body limit (413 above it)
``AEROGRAV_MAX_JSON_KB``   body limit of every other request (JSON: a survey, a job, settings; and
                           a form sent to an endpoint that takes no files): 413 above it
``AEROGRAV_MAX_UNCOMPRESSED_MB`` total uncompressed size of an imported zip, also the largest table
                           file the reader accepts (default 4 × the upload limit)
``AEROGRAV_MAX_TABLE_ROWS`` most data rows of one uploaded table file
``AEROGRAV_SURVEY_STORAGE_MB`` storage budget per survey (inputs and results kept on disk;
                           default 10 × the upload limit); reported in ``/api/health``
``AEROGRAV_MAX_STORE_MB``  most disk the whole data directory may hold (every survey's inputs and
                           results, the SQLite file; default 20 GB): new surveys and uploads that
                           would go above it are refused (507); reported in ``/api/health``
``AEROGRAV_MAX_SURVEYS``   most surveys the store holds (default 10 000): a new survey or import beyond
                           it is refused (507)
``AEROGRAV_ALLOWED_HOSTS`` comma-separated Host header values accepted (``*`` = any); default: the
                           bind address, ``localhost``, ``127.0.0.1`` and ``::1``
``AEROGRAV_MAX_JOBS``      most local job processes running at once (default: the CPUs); later
                           jobs wait, queued, for a free slot
``AEROGRAV_JOB_TIMEOUT_S`` longest a job may run (default 24 h): a job still running then is stopped
                           and marked failed, saying so (its slot frees for the jobs waiting)
``AEROGRAV_RECOGNITION_VIEWS`` / ``AEROGRAV_RECOGNITION_VIEWS_MB`` the recognition maps re-smoothed for
                           ``GET /recognition?h=&rho=`` kept for reuse (default the last 32, at most 128 MB
                           of their arrays)
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="AEROGRAV_", extra="ignore")

    data_dir: Path = Field(Path("data"), description="Data directory (surveys, results, SQLite file)")
    database_url: str | None = Field(None, description="SQLAlchemy URL; SQLite in the data directory when unset")
    dask_scheduler: str | None = Field(None, description="Dask scheduler address, e.g. tcp://10.0.0.5:8786")
    token: str | None = Field(None, description="Bearer token required on mutating requests when set")
    max_upload_mb: float = Field(500.0, gt=0, description="Largest accepted upload: a multipart/form-data body "
                                 "sent to an endpoint that takes files (MB)")
    max_json_kb: float = Field(1024.0, gt=0, description="Largest accepted body of any other request (kB): a JSON "
                               "body is held in memory and parsed into objects many times its size, so the upload "
                               "limit would let one request take gigabytes")
    pipeline_entry: str = Field(
        "app.pipeline.process:run_job",
        description="'module:function' run by jobs: run_job(input_dir, out_dir, overrides, progress, kind, "
        "previous_dir), or a function with process_survey's signature that runs 'process' jobs only (tests swap it)")
    poll_interval_s: float = Field(0.5, gt=0, description="How often the job monitor checks worker processes")
    reconcile_interval_s: float = Field(10.0, gt=0, description="How often active jobs in the store are checked "
                                        "against live workers")
    max_uncompressed_mb: float | None = Field(None, gt=0, description="Largest total uncompressed size of an "
                                              "imported zip and of one table file (MB); 4 × max_upload_mb when unset")
    max_table_rows: int = Field(10_000_000, ge=1, description="Most data rows of one uploaded table file")
    survey_storage_mb: float | None = Field(None, gt=0, description="Storage budget per survey (MB); "
                                            "10 × max_upload_mb when unset")
    max_store_mb: float = Field(20480.0, gt=0, description="Most disk the data directory may hold (MB): every "
                                "survey's inputs and results and the SQLite file; new surveys and uploads that "
                                "would take it above are refused (HTTP 507)")
    max_surveys: int = Field(10_000, ge=1, description="Most surveys the store holds: an empty survey costs no "
                             "disk, so the store's limit alone let requests add surveys without end (each listed by "
                             "every GET /api/surveys and counted by /api/health)")
    allowed_hosts: str | None = Field(None, description="Comma-separated Host header values accepted ('*' = any); "
                                      "default the bind address, localhost, 127.0.0.1, ::1")
    bind_host: str | None = Field(None, description="The address `aerograv serve` binds (set by serve)")
    max_jobs: int | None = Field(None, ge=1, le=1024, description="Most local job processes running at once "
                                 "(default: the CPUs this server may use); later jobs wait, queued, for a free slot "
                                 "— every job is a process of its own, so many surveys started at once would "
                                 "otherwise take the machine's memory")
    job_timeout_s: float = Field(86400.0, gt=0, description="Longest a job may run (s) from its start: a job still "
                                 "running then is stopped and marked failed, so that no job holds a worker slot "
                                 "(and its CPUs) without end")
    recognition_views: int = Field(32, ge=1, le=10_000, description="Re-smoothed recognition maps kept for reuse "
                                   "(GET /recognition with h, ρ, mode: NL-means runs once per (result, h, ρ, "
                                   "mode) among the last this many, not on every request)")
    recognition_views_mb: float = Field(128.0, gt=0, le=65536, description="Most memory those maps' arrays may "
                                        "hold (MB; the newest is always kept)")

    @property
    def db_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(Path(self.data_dir).resolve() / 'aerograv.db').as_posix()}"

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)

    @property
    def max_json_bytes(self) -> int:
        """Body limit of requests that are not uploads (never above the upload limit)."""
        return min(int(self.max_json_kb * 1024), self.max_upload_bytes)

    @property
    def max_uncompressed_bytes(self) -> int:
        mb = self.max_uncompressed_mb if self.max_uncompressed_mb is not None else 4 * self.max_upload_mb
        return int(mb * 1024 * 1024)

    @property
    def survey_storage_bytes(self) -> int:
        mb = self.survey_storage_mb if self.survey_storage_mb is not None else 10 * self.max_upload_mb
        return int(mb * 1024 * 1024)

    @property
    def max_store_bytes(self) -> int:
        return int(self.max_store_mb * 1024 * 1024)

    def allowed_host_set(self) -> set[str] | None:
        """Host names (lower case, no port) accepted; None = any (``*``, or a wildcard bind address
        without an explicit list)."""
        if self.allowed_hosts is not None:
            hosts = {h.strip().lower().strip("[]") for h in self.allowed_hosts.split(",") if h.strip()}
            return None if "*" in hosts else hosts
        bind = (self.bind_host or "").strip().lower().strip("[]")
        if bind in ("0.0.0.0", "::", "*"):
            return None
        return {"localhost", "127.0.0.1", "::1"} | ({bind} if bind else set())


@lru_cache
def get_settings() -> Settings:
    return Settings()
