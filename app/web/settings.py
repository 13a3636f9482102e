"""Web application settings (pydantic-settings, environment prefix ``AEROGRAV_``).

``AEROGRAV_DATA_DIR``      where surveys, results and the default SQLite file live
``AEROGRAV_DATABASE_URL``  any SQLAlchemy URL; default ``sqlite:///<DATA_DIR>/aerograv.db``
``AEROGRAV_DASK_SCHEDULER`` address of a Dask scheduler; jobs run there when set
``AEROGRAV_TOKEN``         when set, every mutating request needs ``Authorization: Bearer <token>``
``AEROGRAV_MAX_UPLOAD_MB`` request body limit (413 above it)
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
    max_upload_mb: float = Field(500.0, gt=0, description="Largest accepted request body (MB)")
    pipeline_entry: str = Field(
        "app.pipeline.process:process_survey",
        description="'module:function' run by jobs; same signature as process_survey (tests swap it)")
    poll_interval_s: float = Field(0.5, gt=0, description="How often the job monitor checks worker processes")

    @property
    def db_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(Path(self.data_dir).resolve() / 'aerograv.db').as_posix()}"

    @property
    def max_upload_bytes(self) -> int:
        return int(self.max_upload_mb * 1024 * 1024)


@lru_cache
def get_settings() -> Settings:
    return Settings()
