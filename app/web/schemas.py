"""Pydantic request/response schemas of the REST API."""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from app.config import Name

JobKind = Literal["process", "identify", "filter"]
JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class SurveyCreate(BaseModel):
    model_config = ConfigDict(allow_inf_nan=False)
    name: Name = Field(..., min_length=1, max_length=200, description="Survey name (no control characters, "
                       "no '/' or '\\')")


class FlightOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: int
    name: str
    qc: dict[str, Any] = {}


class SurveyOut(BaseModel):
    id: int
    name: str
    created_at: dt.datetime
    crs: str | None = None
    flights: list[str] = []
    n_lines: int = 0
    has_input: bool = False
    current_result_id: int | None = None
    last_job: "JobOut | None" = None


class EMIteration(BaseModel):
    model_config = ConfigDict(extra="allow")
    iteration: int
    Q: list[float] = Field(default_factory=list, description="Q_i, mGal² per GNSS step")
    R: list[float] = Field(default_factory=list, description="R_j, (cm/s)²")
    objective: float | None = None
    transition: list[list[float]] | None = None


class JobCreate(BaseModel):
    model_config = ConfigDict(allow_inf_nan=False)
    kind: JobKind = "process"
    params: dict[str, Any] = Field(default_factory=dict,
                                   description="ProcessingParams overrides (see GET /api/params/schema)")


class JobOut(BaseModel):
    id: int
    survey_id: int
    kind: JobKind
    status: JobStatus
    progress: float = Field(..., ge=0, le=1)
    stage: str | None = None
    em_iterations: list[EMIteration] = []
    error: str | None = None
    params: dict[str, Any] = {}
    backend: str = "local"
    created_at: dt.datetime
    started_at: dt.datetime | None = None
    finished_at: dt.datetime | None = None


class LineOut(BaseModel):
    id: int
    line: str
    flight: str
    kind: str
    t_start: float
    t_end: float
    qc: dict[str, Any] = {}
    stats: dict[str, Any] | None = Field(None, description="From the current result: dg mean/std/min/max (mGal), n")


class QCOut(BaseModel):
    survey_id: int
    flights: list[FlightOut]
    lines: list[LineOut]


class RecognitionOut(BaseModel):
    survey_id: int
    result_id: int
    h: float = Field(..., description="NL-means weight decay h (1/km)")
    rho: float = Field(..., description="NL-means radius ρ (km)")
    mode: Literal["hard", "soft"]
    n_states: int
    states: list[dict[str, Any]] = Field(default_factory=list, description="{index, Q, R} per state")
    n_points: int
    easting_km: list[float] | None = None
    northing_km: list[float] | None = None
    line: list[str] | None = None
    state_raw: list[int] | None = None
    state: list[int] = Field(..., description="Smoothed state per point")
    p_max: list[float] = Field(..., description="Smoothed probability of the chosen state")
    elapsed_ms: float


class ProfileOut(BaseModel):
    survey_id: int
    line: str
    flight: str
    kind: str
    n_total: int
    step: int = Field(..., description="Decimation stride applied for the browser")
    z_lowpass_s: float
    time: list[float]
    distance_km: list[float]
    z_lowpassed: list[float | None]
    dg: list[float | None]
    dg_std: list[float | None]
    dg_stationary: list[float | None]
    dg_fir: list[float | None]
    dg_unleveled: list[float | None] | None = None
    state: list[int | None]


class GridOut(BaseModel):
    survey_id: int
    result_id: int
    crs: str | None = None
    easting_km: list[float]
    northing_km: list[float]
    dg: list[list[float | None]]
    dg_std: list[list[float | None]] | None = None
    lines: list[dict[str, Any]] = Field(default_factory=list, description="{line, kind, easting_km[], northing_km[]}")
    crossovers: list[dict[str, Any]] = []
    report: dict[str, Any] = {}


SurveyOut.model_rebuild()
