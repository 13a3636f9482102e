"""Pydantic request/response schemas of the REST API.

Every JSON endpoint declares its response model and returns an instance of it; FastAPI writes
it with pydantic's serializer (non-finite floats → null).  Response models forbid undeclared
fields, so a key added to a response without its declaration fails loudly instead of vanishing.
QC figures and line statistics come from stored JSON and allow further keys."""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictFloat

from app.config import Name

JobKind = Literal["process", "identify", "filter"]
JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class SurveyCreate(BaseModel):
    model_config = ConfigDict(allow_inf_nan=False)
    name: Name = Field(..., min_length=1, max_length=200, description="Survey name (no control characters, "
                       "no '/' or '\\')")


class Out(BaseModel):
    """A response body: every field the endpoint returns is declared here."""
    model_config = ConfigDict(extra="forbid")


class SensorQC(BaseModel):
    """QC figures of a flight or line: those of ``aerograv inspect`` (app.pipeline.inspect.inspect_table)."""
    model_config = ConfigDict(extra="allow")
    gravimeter_samples: int | None = Field(None, description="Gravimeter samples in the window")
    gnss_samples: int | None = Field(None, description="GNSS samples in the window")
    gravimeter_rate_hz: float | None = Field(None, description="Gravimeter rate from the median interval (Hz)")
    gnss_rate_hz: float | None = Field(None, description="GNSS rate from the median interval (Hz)")
    gravimeter_max_gap_s: float | None = Field(None, description="Largest gravimeter step, window edges included (s)")
    gnss_max_gap_s: float | None = Field(None, description="Largest GNSS step, window edges included (s)")
    duration_s: float | None = None
    length_km: float | None = Field(None, description="Ellipsoidal path length of the GNSS track at flight height")


class FlightQC(SensorQC):
    t_start: float | None = None
    t_end: float | None = None


class LineQC(SensorQC):
    speed_ms: float | None = Field(None, description="length / duration (m/s)")
    mean_h_m: float | None = Field(None, description="Mean GNSS height over the line (m)")
    track: str | None = Field(None, description="Track id of lines.csv (repeat lines share one)")


class FlightOut(Out):
    model_config = ConfigDict(from_attributes=True)
    id: int
    name: str
    qc: FlightQC = Field(default_factory=FlightQC)


class SurveySectionPatch(BaseModel):
    """``[survey]`` of survey.toml: the fields given are set (null removes an optional one)."""
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    name: str | None = Field(None, description="Survey name (also the name in the survey list)")
    crs: str | None = Field(None, description="Projected CRS, e.g. 'EPSG:32657' (null: the UTM zone of the data)")
    normal_gravity: str | None = Field(None, description="'WGS84', 'GRS80' or 'Helmert1901'")


class GravimeterSectionPatch(BaseModel):
    """``[gravimeter]`` of survey.toml: the fields given are set (null removes an optional one).  Numbers
    must be JSON numbers: ``true`` or ``"3"`` are refused, not read as 1.0 or 3.0 (as for job parameters)."""
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    model: str | None = Field(None, description="Gravimeter model, e.g. 'GT-1A'")
    tau_s: StrictFloat | None = Field(None, description="First-order lag time constant (s); 0 if already de-lagged")
    scale: StrictFloat | None = Field(None, description="Scale k of the gravimeter model")
    rate_hz: StrictFloat | None = Field(None, description="Declared sampling rate (Hz); null: inferred from the time stamps")
    base_gravity_mgal: StrictFloat | None = Field(None, description="Absolute gravity at the parking place (mGal); "
                                            "null: no absolute base tie (the level of dg is relative)")


class SurveyPatch(BaseModel):
    """Changes to a survey's ``survey.toml`` (validated by app.config.SurveyConfig; a 422 names the
    field as ``section.key``).  Fields left out keep their value."""
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    survey: SurveySectionPatch | None = None
    gravimeter: GravimeterSectionPatch | None = None


class SurveySettings(Out):
    """The editable fields of the current ``survey.toml`` (after defaults)."""
    survey: dict[str, Any] = Field(default_factory=dict, description="name, crs, normal_gravity")
    gravimeter: dict[str, Any] = Field(default_factory=dict,
                                       description="model, tau_s, scale, rate_hz, base_gravity_mgal")


class SurveyOut(Out):
    id: int
    name: str
    created_at: dt.datetime
    crs: str | None = None
    flights: list[str] = []
    n_lines: int = 0
    has_input: bool = False
    current_result_id: int | None = None
    result_job_id: int | None = Field(None, description="The job that computed the current result (null: no result). "
                                      "``last_job`` is the newest job, which may have been cancelled or failed "
                                      "since: the current result stays")
    result_outdated: bool = Field(False, description="The survey's input (data or survey.toml) changed after the "
                                  "current result was computed: run processing again")
    settings: SurveySettings | None = Field(None, description="survey.toml fields of the current input")
    last_job: JobOut | None = None
    has_dem: bool = Field(False, description="The current input holds a terrain model (dem.tif): processing "
                          "adds the terrain correction and the Bouguer anomaly")


class SurveyUploadOut(SurveyOut):
    """The survey after a flight upload or a survey import, with what the survey reader warned about."""
    warnings: list[str] = Field(default_factory=list, description="The survey reader's warnings on the stored "
                                "input (every flight's, not only the uploaded one's), e.g. a flight no line uses "
                                "left out because its files cannot be read; at most 100, file names relative to "
                                "the survey directory. Empty when the reader had nothing to say")


class EMIteration(BaseModel):
    model_config = ConfigDict(extra="allow")
    iteration: int
    Q: list[float] = Field(default_factory=list, description="Q_i, mGal² per GNSS step")
    R: list[float] = Field(default_factory=list, description="R_j, (cm/s)²")
    objective: float | None = None
    transition: list[list[float]] | None = None


class JobCreate(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    kind: JobKind = "process"
    params: dict[str, Any] = Field(default_factory=dict,
                                   description="ProcessingParams overrides (see GET /api/params/schema)")


class JobOut(Out):
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


class LineStats(BaseModel):
    """Statistics of a line's final anomaly in the current result."""
    model_config = ConfigDict(extra="allow")
    n: int
    dg_mean_mgal: float | None = None
    dg_std_mgal: float | None = None
    dg_min_mgal: float | None = None
    dg_max_mgal: float | None = None
    sigma_mean_mgal: float | None = Field(None, description="Mean posterior σ (mGal)")


class LineOut(Out):
    id: int
    line: str
    flight: str
    kind: str
    t_start: float
    t_end: float
    qc: LineQC = Field(default_factory=LineQC)
    stats: LineStats | None = Field(None, description="From the current result: dg mean/std/min/max (mGal), n")


class LinePage(Out):
    """A page of the survey's lines (``?offset=&limit=``): ``lines_total`` says how many there are."""
    lines_total: int = Field(0, description="Lines of the survey (all pages)")
    offset: int = Field(0, description="Index of the page's first line among the survey's lines (by id)")
    limit: int = Field(0, description="Most lines the page could hold (the request's limit)")


class QCOut(LinePage):
    survey_id: int
    flights: list[FlightOut] = Field(..., description="Every flight (not paged)")
    lines: list[LineOut] = Field(..., description="The page's lines")


class TrackLine(Out):
    line: str
    flight: str
    kind: str
    easting_km: list[float | None] = Field(default_factory=list)
    northing_km: list[float | None] = Field(default_factory=list)


class TracksOut(LinePage):
    """Decimated line tracks in the survey CRS (km), a page of them."""
    survey_id: int
    crs: str | None = None
    lines: list[TrackLine]


class SurveyStorage(Out):
    survey_id: int
    used_mb: float
    over_budget: bool


class StorageOut(Out):
    budget_mb_per_survey: float
    surveys: list[SurveyStorage]
    used_mb_total: float
    max_store_mb: float = Field(..., description="Most the data directory may hold (AEROGRAV_MAX_STORE_MB)")
    store_used_mb: float = Field(..., description="What the data directory holds: every survey's files and the "
                                 "SQLite file (recounted at most every 30 s, kept current in between)")


class HealthOut(Out):
    status: str
    backend: str = Field(..., description="Job backend: local or dask")
    auth: bool = Field(..., description="Mutating requests need the token")
    max_upload_mb: float
    max_uncompressed_mb: float
    allowed_hosts: list[str]
    storage: StorageOut


class ParamGroup(Out):
    key: str
    title: str
    common: list[str] = Field(..., description="Parameters shown at once")
    advanced: list[str] = Field(..., description="Parameters folded under 'advanced'")


class ParamsSchemaOut(Out):
    model_config = ConfigDict(populate_by_name=True)
    json_schema: dict[str, Any] = Field(..., alias="schema", description="JSON schema of ProcessingParams")
    defaults: dict[str, Any]
    groups: list[ParamGroup] = Field(default_factory=list, description="Every parameter in exactly one group, by "
                                     "pipeline stage (app.config.param_groups)")


class RecognitionOut(Out):
    survey_id: int
    result_id: int
    h: float = Field(..., description="NL-means weight decay h (1/km)")
    rho: float = Field(..., description="NL-means radius ρ (km)")
    mode: Literal["hard", "soft"]
    n_states: int
    states: list[dict[str, Any]] = Field(default_factory=list, description="{index, Q, R} per state")
    n_points: int
    easting_km: list[float | None] | None = None
    northing_km: list[float | None] | None = None
    line: list[str] | None = None
    state_raw: list[int] | None = None
    state: list[int] = Field(..., description="Smoothed state per point")
    p_max: list[float | None] = Field(..., description="Smoothed probability of the chosen state")
    smoother: str = Field("", description="The function that made the map")
    time: list[float | None] | None = None
    elapsed_ms: float


class ProfileOut(Out):
    survey_id: int
    line: str
    flight: str
    kind: str
    n_total: int
    step: int = Field(..., description="Decimation stride applied for the browser")
    z_lowpass_s: float
    time: list[float | None]
    distance_km: list[float | None]
    z_lowpassed: list[float | None]
    dg: list[float | None]
    dg_std: list[float | None]
    dg_stationary: list[float | None]
    dg_fir: list[float | None]
    dg_unleveled: list[float | None] | None = None
    state: list[int | None]
    # geophysical products (app.pipeline.stages.products): null when the result has no such column
    height_m: list[float | None] | None = Field(None, description="flight height h (m)")
    atm_corr: list[float | None] | None = Field(None, description="atmospheric correction added (mGal)")
    dg_flight: list[float | None] | None = Field(None, description="δg at flight height before continuation "
                                                 "(a datum was used: dg is at the datum)")
    dg_flight_std: list[float | None] | None = None
    dg_datum: list[float | None] | None = Field(None, description="δg continued to the datum, before leveling")
    dg_datum_std: list[float | None] | None = None
    datum_height_m: list[float | None] | None = Field(None, description="height of the datum (m)")
    terrain: list[float | None] | None = Field(None, description="terrain effect of the DEM (mGal)")
    terrain_height_m: list[float | None] | None = Field(None, description="DEM height under the point (m)")
    dg_bouguer: list[float | None] | None = Field(None, description="complete Bouguer anomaly dg − terrain (mGal)")


class RepeatTrackSummary(Out):
    track: str
    lines: list[str] = Field(..., description="The passes (lines) of the track, in lines.csv's order")
    internal_accuracy_mgal: dict[str, float | None] | None = Field(
        None, description="report.json repeat_lines.<track>.internal_accuracy_mgal (dg_mgal = adaptive, "
        "dg_stationary_mgal, dg_fir_mgal)")


class RepeatTracksOut(Out):
    survey_id: int
    result_id: int
    tracks: list[RepeatTrackSummary]


class TrackAxis(Out):
    origin_easting_km: float
    origin_northing_km: float
    unit_easting: float
    unit_northing: float
    azimuth_deg: float = Field(..., description="Direction of increasing along-track distance, degrees "
                               "clockwise from grid north")
    length_km: float


class TrackPass(Out):
    line: str
    flight: str
    direction: Literal["forward", "reverse"] = Field(..., description="forward: along-track distance grows "
                                                     "with time (as on the track's first pass)")
    n_total: int
    step: int = Field(..., description="Decimation stride applied for the browser")
    t_start: float | None
    t_end: float | None
    across_rms_m: float | None = Field(None, description="RMS distance of the pass from the track's axis (m)")
    sigma_mean_mgal: float | None = None
    time: list[float | None]
    along_km: list[float | None] = Field(..., description="Distance along the track's axis from its origin (km)")
    dg: list[float | None] | None
    dg_std: list[float | None] | None
    dg_stationary: list[float | None] | None
    dg_fir: list[float | None] | None


class RepeatTrackOut(Out):
    """The passes of a repeat track on one along-track axis (app.web.repeat)."""
    survey_id: int
    result_id: int
    track: str
    axis: TrackAxis
    passes: list[TrackPass]
    repeatability: dict[str, Any] | None = Field(None, description="report.json repeat_lines.<track>")
    std_check: dict[str, Any] | None = Field(None, description="report.json level_refinement.std_repeat_tracks.<track>")


class GridLine(Out):
    line: str
    kind: str
    easting_km: list[float | None]
    northing_km: list[float | None]


class GridOut(Out):
    survey_id: int
    result_id: int
    crs: str | None = None
    easting_km: list[float | None]
    northing_km: list[float | None]
    dg: list[list[float | None]]
    dg_std: list[list[float | None]] | None = None
    lines: list[GridLine] = Field(default_factory=list, description="Decimated line tracks for the overlay (km)")
    crossovers: list[dict[str, Any]] = Field(default_factory=list, description="crossovers.csv rows")
    report: dict[str, Any] = Field(default_factory=dict, description="The result's report.json")
    product: str = Field("free_air", description="free_air or bouguer")
    height: str = Field("flight", description="flight (the flight height) or datum (continued to the datum)")
    datum: dict[str, Any] | None = Field(None, description="report.json products.datum when a datum was used")
    available: dict[str, dict[str, bool]] = Field(default_factory=dict, description="{free_air: {flight, datum}, "
                                                  "bouguer: {flight, datum}}: which grids the result has")
    unavailable: dict[str, str] = Field(default_factory=dict, description="why a grid is not available, by "
                                        "'<product>@<height>' (e.g. 'bouguer@datum': the survey has no DEM)")


class LineDifference(Out):
    line: str
    flight: str
    kind: str
    n: int
    rms_mgal: float | None = Field(None, description="RMS of adaptive − FIR (both before leveling), mGal")
    mean_mgal: float | None = Field(None, description="Mean of adaptive − FIR, mGal")
    std_mgal: float | None = Field(None, description="Standard deviation of adaptive − FIR, mGal")


class ReportOut(Out):
    """The current result's report.json with what the browser needs beside it."""
    survey_id: int
    result_id: int
    job_id: int
    warnings: list[str] = Field(default_factory=list, description="report.json 'warnings'")
    leveled: bool = Field(False, description="crossovers.status == 'leveled' (leveling applied)")
    leveling_status: str | None = Field(None, description="report.json crossovers.status")
    absolute_base_tie: bool = Field(True, description="False when a warning says 'no absolute base tie': "
                                    "the level of dg is relative")
    adaptive_minus_fir: list[LineDifference] = Field(default_factory=list,
                                                     description="Per line, from lines.parquet")
    crossovers: list[dict[str, Any]] = Field(default_factory=list, description="crossovers.csv rows: line_a, line_b, "
                                             "easting_km, northing_km, diff_before_mgal, diff_after_mgal")
    identification: dict[str, Any] = Field(default_factory=dict, description="From identification.json: states "
                                           "{index, Q, R}, transition, em {selection, converged, loglik, "
                                           "n_iterations, final}, lines_skipped")
    report: dict[str, Any] = Field(default_factory=dict, description="report.json as written by the pipeline")


SurveyOut.model_rebuild()
SurveyUploadOut.model_rebuild()
