"""Configuration models: ``survey.toml`` (SPEC §4) and every processing default.

``ProcessingParams`` holds every tunable of the pipeline with its default; the
``[processing]`` table of ``survey.toml`` and the web job ``params`` override it.
Units live in the names.

Every number is finite (``allow_inf_nan=False`` on the shared base class, so new fields get it
too) and bounded; the bounds that protect the machine rather than the method are the ``MAX_*``
caps below, in one place, quoted in the validation messages.
"""

from __future__ import annotations

import re
import unicodedata
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, field_validator, model_validator

# --- caps derived from what one job on one worker (a few GB, 1-2 cores) can do --------------
#: grid nodes of the anomaly map: 2000 × 2000; dg and dg_std in float64 are 64 MB, the
#: collocation solves one small local system per node (checked from the lines' extent and
#: ``grid_spacing_km`` when the job is submitted and again when the pipeline has the extent)
MAX_GRID_CELLS = 4_000_000
#: EM iterations (the default stops within ~60; each iteration is a pass over all lines)
MAX_EM_ITER = 1000
#: decimation factor n (100 at 10 Hz and 100 m/s for 1 km; the Kaiser filter has ~n·A/20 taps)
MAX_DECIMATION_N = 10_000
#: MA orders K, L (chosen ≤ 20 when automatic; the EM chain has N + N(N−1)·p super-states with
#: (p+1)² covariances each)
MAX_MA_ORDER = 40
#: names: survey, flight, line and track ids
MAX_NAME_LENGTH = 200

#: control characters, line/paragraph separators, and the bidirectional-text controls (a name
#: holding U+202E displays reversed: spoofed)
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029\u200e\u200f\u202a-\u202e\u2066-\u2069]")
#: unpaired UTF-16 surrogates (a JSON string may hold one as an escape; UTF-8 cannot encode it)
_SURROGATE = re.compile("[\ud800-\udfff]")


def check_label(value: str, what: str = "label") -> str:
    """Free text shown in the browser and the report (an instrument's model): at most
    ``MAX_NAME_LENGTH`` characters, no control characters and, unless empty, at least one visible
    character (:func:`has_visible`); path separators are allowed."""
    if len(value) > MAX_NAME_LENGTH:
        raise ValueError(f"{what} is {len(value)} characters long; at most {MAX_NAME_LENGTH} allowed")
    m = _CONTROL.search(value)
    if m:
        raise ValueError(f"{what} contains the control character {m.group()!r} (newline, tab, NUL, "
                         "a text-direction override, …)")
    m = _SURROGATE.search(value)
    if m:  # JSON may escape half of a UTF-16 pair ("\\ud800"): no UTF-8 file or database takes it
        raise ValueError(f"{what} contains {m.group()!r}, half of a UTF-16 surrogate pair (not a character)")
    if value and not has_visible(value):
        raise ValueError(f"{what} has no visible character (only {_describe_invisible(value)}): it would show "
                         "as a blank; write at least one letter, digit, punctuation mark or symbol")
    return value


#: Unicode general categories that show as something: letters, numbers, punctuation, symbols (not
#: separators Z*, format and other characters C*, or combining marks M* on their own)
_VISIBLE_CATEGORIES = frozenset("LNPS")


def has_visible(value: str) -> bool:
    """``value`` holds at least one character of Unicode category L, N, P or S (a zero-width space,
    word joiner, byte-order mark, ideographic space or a lone combining mark shows nothing)."""
    return any(unicodedata.category(c)[0] in _VISIBLE_CATEGORIES for c in value)


def _describe_invisible(value: str, most: int = 4) -> str:
    """The distinct characters of ``value`` by code point and Unicode name, e.g. ``U+200B ZERO WIDTH SPACE``."""
    seen = list(dict.fromkeys(value))
    names = [f"U+{ord(c):04X} {unicodedata.name(c, unicodedata.category(c))}" for c in seen[:most]]
    return ", ".join(names) + (f" and {len(seen) - most} more" if len(seen) > most else "")


def check_name(value: str, what: str = "name") -> str:
    """A name shown in the browser and used as a file or folder name: not empty, at most
    ``MAX_NAME_LENGTH`` characters, no control characters, at least one visible character (Unicode
    category L, N, P or S: not only zero-width, format, space or combining characters), no path
    separators."""
    if not isinstance(value, str):
        raise ValueError(f"{what} must be text")
    if not value.strip():
        raise ValueError(f"{what} is empty" + (f" (only {_describe_invisible(value)})" if value else ""))
    check_label(value, what)
    if "/" in value or "\\" in value:
        raise ValueError(f"{what} contains a path separator ('/' or '\\')")
    if value.strip() in (".", ".."):
        raise ValueError(f"{what} cannot be '.' or '..'")
    return value


#: a validated name (see :func:`check_name`)
Name = Annotated[str, AfterValidator(check_name)]


#: validated free text (see :func:`check_label`)
Label = Annotated[str, AfterValidator(check_label)]


def grid_cells(extent_e_km: float, extent_n_km: float, spacing_km: float) -> int:
    """Nodes of the regular grid over an extent (as ``app.core.gridding`` lays it out)."""
    nx = int(extent_e_km / spacing_km + 1e-9) + 1
    ny = int(extent_n_km / spacing_km + 1e-9) + 1
    return nx * ny


def check_grid_cells(extent_e_km: float, extent_n_km: float, spacing_km: float) -> None:
    """ValueError naming the bound when the grid over the extent would exceed ``MAX_GRID_CELLS``."""
    n = grid_cells(extent_e_km, extent_n_km, spacing_km)
    if n > MAX_GRID_CELLS:
        finest = ((extent_e_km * extent_n_km) / MAX_GRID_CELLS) ** 0.5
        raise ValueError(f"grid_spacing_km = {spacing_km:g} over {extent_e_km:.1f} × {extent_n_km:.1f} km gives "
                         f"{n:,} grid cells, more than the {MAX_GRID_CELLS:,} allowed (use ≥ {finest:.3g} km)")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


#: a PROJ parameter naming a file by path (PROJ opens it while the CRS is built: a FIFO or a terminal
#: would block the process), or a WKT/PROJJSON grid file given by path
_CRS_FILE = re.compile(r"(?i)\b(?:nadgrids|geoidgrids|grids|xy_grids|z_grids|init|file)\s*=\s*[^\s/\\]*[/\\]\S*"
                       r"|(?:parameterfile|\"filename\")[^/\\]*[/\\]")


MAX_CRS_LENGTH = 200


def _crs_text_fault(v: str) -> None:
    """Refuse a CRS longer than ``MAX_CRS_LENGTH`` (a WKT), naming the EPSG code to write when
    PROJ identifies one (:func:`app.core.geodesy.epsg_for_text`)."""
    if len(v) <= MAX_CRS_LENGTH:
        return
    from app.core.geodesy import epsg_for_text

    code = epsg_for_text(v)
    hint = f": it is EPSG:{code}, write crs = 'EPSG:{code}'" if code is not None else ""
    raise ValueError(f"crs is {len(v)} characters long (a WKT?); at most {MAX_CRS_LENGTH} allowed — give an EPSG "
                     f"code or a PROJ string{hint}")


class SurveySection(_Strict):
    name: Name = "survey"
    crs: str | None = Field(None, description="Projected CRS for distances and grids, e.g. 'EPSG:32657' (at most "
                            "200 characters: an EPSG code or PROJ string); UTM chosen if absent")
    normal_gravity: Literal["WGS84", "GRS80", "Helmert1901"] = "WGS84"

    @field_validator("crs")
    @classmethod
    def _usable_crs(cls, v: str | None) -> str | None:
        # refused here, naming survey.crs, rather than by PROJ in the middle of processing
        from app.core.geodesy import crs_fault

        if v is not None:
            _crs_text_fault(v)
            check_label(v, "crs")
            m = _CRS_FILE.search(v)
            if m:
                raise ValueError(f"the CRS names a file ({m.group(0)[:80]}): grids and init files by path are "
                                 "not read (a grid by its bare name from PROJ's data is, e.g. +nadgrids=@null)")
        why = None if v is None else crs_fault(v)
        if why:
            raise ValueError(why)
        return v


class GravimeterSection(_Strict):
    model: Label = "GT-1A"
    tau_s: float = Field(2.0, ge=0.0, le=60.0, description="First-order lag time constant (s); 0 if already de-lagged")
    scale: float = Field(1.0, gt=0.0, le=10.0, description="Scale k of the gravimeter model τ·ḟ' + k·f' = f_g + …")
    base_gravity_mgal: float | None = Field(None, ge=970_000.0, le=990_000.0, description="Absolute gravity at the parking place (mGal)")
    reading_offset_mgal: float | None = Field(
        None, ge=-2e6, le=2e6, description="DGS .dat only: mGal added to the meter's relative gravity reading to make an absolute-"
        "looking specific force; None: 0 when the readings already look absolute (7e5–1.3e6 mGal), otherwise the "
        "nominal 978000 mGal (the base tie then fixes the level)")
    rate_hz: float | None = Field(None, gt=0.0, le=1000.0, description="Declared sampling rate of the gravimeter (Hz): "
                                  "a check of the rate inferred from the time stamps (median interval); "
                                  "None infers it (0.5–100 Hz accepted)")
    time_offset_s: float | None = Field(
        None, ge=-1e10, le=1e10, description="G file: seconds added to UTC seconds of day to reach the survey time scale "
        "(e.g. day·86400 + GPS−UTC leap seconds); DGS .dat: seconds added to the GPS seconds of week "
        "(the survey time of the first record when the records carry no GPS time); whole days inferred "
        "from the GNSS times when None")


def _column_ref(v):
    if isinstance(v, bool) or not isinstance(v, (str, int)):
        raise ValueError("expected a column name (text) or a column number (integer, from 1)")
    if isinstance(v, int) and v < 1:
        raise ValueError("a column number counts from 1")
    if isinstance(v, str):
        if not v.strip():
            raise ValueError("a column name cannot be empty")
        return v.strip()
    return v


#: a column of an XYZ file: its name in the file's header (matched without regard to case) or its
#: 1-based position (for files without a header line)
ColumnRef = Annotated[str | int, BeforeValidator(_column_ref)]

F_Z_UNITS = ("m/s2", "mGal", "um/s2")
#: multiplier turning each f_z unit into m/s²
F_Z_UNIT_TO_MS2 = {"m/s2": 1.0, "mGal": 1e-5, "um/s2": 1e-6}


class _ColumnMap(_Strict):
    time: ColumnRef | None = Field(None, description="Time (s, survey time scale)")
    line: ColumnRef | None = Field(None, description="Line id column (instead of Line/Tie block headers)")

    def refs(self, fields) -> dict:
        """``{field: ref}`` of the given fields that are set."""
        return {f: getattr(self, f) for f in fields if getattr(self, f, None) is not None}


class GravimeterColumns(_ColumnMap):
    f_z: ColumnRef | None = Field(None, description="Vertical specific force, up")
    f_x: ColumnRef | None = None
    f_y: ColumnRef | None = None
    f_z_unit: Literal["m/s2", "mGal", "um/s2"] | None = Field(
        None, description="Unit of f_z (and f_x, f_y) in XYZ files and in gravimeter.csv (the values must agree "
        "with it); inferred from the magnitude (~9.8 → m/s², ~980000 → mGal, ~9.8e6 → µm/s²) when None")


class GnssColumns(_ColumnMap):
    lat: ColumnRef | None = None
    lon: ColumnRef | None = None
    h: ColumnRef | None = None
    vu: ColumnRef | None = None
    ve: ColumnRef | None = None
    vn: ColumnRef | None = None
    sigma_v: ColumnRef | None = None


GRAVIMETER_FIELDS = ("time", "line", "f_z", "f_x", "f_y")
GNSS_FIELDS = ("time", "line", "lat", "lon", "h", "vu", "ve", "vn", "sigma_v")


class ColumnsSection(GravimeterColumns, GnssColumns):
    """``[columns]``: which column of an XYZ file holds what (SPEC §4 names).

    Keys at the top level apply to every XYZ file of the survey;
    ``[columns.gravimeter]`` and ``[columns.gnss]`` override them for
    ``gravimeter.xyz`` and ``gnss.xyz`` (and for the gravimeter and GNSS
    columns of a combined ``<name>.xyz``).  An unmapped field is looked up in
    the file's header under its own name (``time``, ``f_z``, …).
    """

    gravimeter: GravimeterColumns | None = None
    gnss: GnssColumns | None = None

    def for_role(self, role: str) -> dict:
        """Effective ``{field: ref}`` (and ``f_z_unit``) for ``role`` ∈ {"gravimeter", "gnss"}."""
        fields = GRAVIMETER_FIELDS if role == "gravimeter" else GNSS_FIELDS
        out = self.refs(fields)
        sub = self.gravimeter if role == "gravimeter" else self.gnss
        if sub is not None:
            out.update(sub.refs(fields))
        if role == "gravimeter":
            unit = (sub.f_z_unit if sub is not None and sub.f_z_unit is not None else self.f_z_unit)
            out["f_z_unit"] = unit
        return out

    @model_validator(mode="after")
    def _distinct(self):
        for role in ("gravimeter", "gnss"):
            m = {k: v for k, v in self.for_role(role).items() if k != "f_z_unit"}
            seen: dict = {}
            for k, v in m.items():
                key = v.lower() if isinstance(v, str) else v
                if key in seen:
                    raise ValueError(f"{seen[key]} and {k} name the same column {v!r} (for the {role} file)")
                seen[key] = k
        return self


class ProcessingParams(_Strict):
    """Every pipeline default (SPEC §2, §3). All fields overridable."""

    # --- ingest / validation
    gnss_rate_hz: float | None = Field(None, gt=0, le=1000, description="Declared GNSS rate (Hz); inferred when None")
    rate_tolerance: float = Field(0.25, gt=0, le=1, description="Allowed relative deviation of the median rate from the declared one")
    geoid_height_m: float | None = Field(None, ge=-120, le=100, description="The GNSS heights are orthometric (above "
                                         "the geoid, 'MSL'): add this geoid undulation N (m) to make them ellipsoidal, "
                                         "as SPEC's h is (normal gravity moves 0.31 mGal per metre of height; nothing in "
                                         "the files shows which datum they use).  None: h is ellipsoidal")
    max_gap_s: float = Field(2.0, gt=0, le=3600, description="Longest allowed gap between consecutive samples inside "
                             "a line window (s): one missing epoch of a 1 Hz record, three of a 2 Hz one.  Missing "
                             "GNSS epochs are put back where the record shows a spline bridges them "
                             "(gnss_fill_max_error_mgal); near missing gravimeter samples FIR 100 s is left out "
                             "(fir_gap_max_error_mgal) and the smoother carries on")
    gravimeter_gap_margin_s: float = Field(2.0, ge=0, le=600, description="Epochs of z within this margin of a gap in "
                                           "the gravimeter record are treated as missing (the lag inversion "
                                           "spreads the unknown integral over ~τ)")
    despike_threshold: float | None = Field(6.0, gt=0, le=1000, description="Epochs of z whose residual from the mean "
                                            "of their neighbours exceeds this many local robust std (GNSS velocity "
                                            "spikes, cycle slips) are repaired; None keeps z as it is")
    height_step_threshold: float | None = Field(8.0, gt=0, le=1000, description="Where vu is derived from "
                                                 "the heights, also flag a step of the heights (a cycle slip) where "
                                                 "its size in the gravimeter's double integral less the heights (or "
                                                 "in the double integral of z) exceeds this many local robust "
                                                 "scales (app.core.measurement.height_step_mask); None: off")
    despike_max_fraction: float = Field(0.01, gt=0, le=1, description="Spike repair stands down (z left as "
                                        "measured, with a warning) when it would flag more than this share "
                                        "of a flight's epochs")
    max_nan_run: int = Field(0, ge=0, le=100_000, description="Longest run of missing values tolerated (interpolated; a missing f_z is a hole of the record instead); longer runs are errors")
    # --- measurement
    estimate_time_offset: bool = True
    apply_time_offset: bool = Field(True, description="Shift the gravimeter time scale by the cross-correlation estimate")
    max_time_offset_s: float = Field(60.0, gt=0, le=600, description="Search range (± s) of the gravimeter–GNSS "
                                     "time offset (at most an eighth of a flight): wide enough for GPS−UTC leap "
                                     "seconds (18 s), which left uncorrected put 480 mGal of error on every epoch")
    time_offset_min_z: float = Field(3.0, ge=0, le=1000, description="Apply the estimated time offset only when it exceeds "
                                     "this many standard errors")
    time_offset_min_improvement: float = Field(0.01, ge=0, lt=1, description="… and removes at least this share "
                                               "of the band-passed acceleration residual")
    clock_track: bool = Field(True, description="Track the gravimeter's clock against the GNSS's along each flight "
                              "(the time offset on clock_window_s windows): a drift (a free-running logger, ppm) or a "
                              "jump (a clock set forward in flight, a gap of the record) re-times the gravimeter's "
                              "stamps (app.core.clock; report time_offsets.<flight>.clock)")
    clock_window_s: float = Field(300.0, ge=60, le=3600, description="Length of the clock-tracking windows (s)")
    clock_p: float = Field(1e-3, gt=0, lt=0.5, description="Significance of a clock drift or jump (partial F-test "
                           "against the windows' own scatter)")
    clock_min_change_s: float = Field(0.02, gt=0, le=10, description="Smallest clock change (s: a drift over the "
                                      "flight, a jump) the tracking acts on")
    match_response: bool = Field(True, description="Smooth the GNSS acceleration by the zero-phase Gaussian "
                                 "exp(−c·ω²) fitted to the gravimeter's (a meter's undeclared decimation filter: "
                                 "two 0.5 s boxcars on a 2 Hz platform), when significant and improving the fit")
    response_min_z: float = Field(3.0, ge=0, le=1000, description="Apply the fitted response width only when it "
                                  "exceeds this many standard errors")
    response_min_improvement: float = Field(0.05, ge=0, lt=1, description="… and removes at least this share of the "
                                            "band-passed acceleration residual")
    slow_gravimeter_min_ratio: float | None = Field(1.5, gt=1, le=100, description="A gravimeter whose sampling "
                                                    "interval is at least this many GNSS steps is also tried with "
                                                    "its motion cancelled at its own sample boundaries "
                                                    "(app.core.gravimeter.motion_compensated_means), kept when z is "
                                                    "quieter above the anomaly band; None never")
    slow_gravimeter_short_drop: float = Field(0.2, ge=0, lt=1, description="Where the lines hold less than 10 FIR "
                                              "cut-off periods of stretches 3 periods long (short lines), the "
                                              "motion-compensated z is still used when, on the lines' stretches of "
                                              "at least 1.5 periods with half a period left out at each end, it is "
                                              "quieter above the anomaly band by at least this share (its band RMS "
                                              "below 1 − this times the plain means') over at least 5 periods")
    height_matched_means: bool = Field(True, description="Where vu is derived from the GNSS heights, compare them with "
                                       "the gravimeter's double integral put through the same spline "
                                       "(app.core.gravimeter.height_matched_means): the aircraft's motion cancels "
                                       "however coarsely the heights sample it; False: the gravimeter's exact "
                                       "interval means against the spline's acceleration")
    band_delay_check: bool = Field(True, description="Fit the gravimeter's timing left after the time offset and "
                                   "lag at 1-5 x 1/fir_cutoff_period_s (z's band on the GNSS jerk's, over the lines, "
                                   "flights pooled) and take it out of z below 10 x 1/fir_cutoff_period_s when "
                                   "significant (band_delay_min_t); report band_delay")
    band_delay_min_t: float = Field(4.0, ge=1, le=1000, description="The residual delay is taken out when it "
                                    "exceeds this many standard errors (one independent sample per 1/(2B) s of "
                                    "the band's width B)")
    band_delay_flights_p: float = Field(0.001, gt=0, le=1, description="The flights' own residual delays are "
                                        "taken out apart (each where it exceeds band_delay_min_t standard errors) "
                                        "when they disagree at this p-value (Cochran's χ²; the time offsets, "
                                        "applied per flight, can leave each flight its own delay); else one pooled "
                                        "delay for the instrument")
    # --- anomaly model
    m: int | None = Field(None, ge=1, le=3, description="Order of the difference operator ∇^m δg = q; None "
                          "chooses it from the data (model_order)")
    model_order: Literal["crossovers", "spectrum", "likelihood"] = Field(
        "crossovers", description="How m is chosen when not given: 'crossovers' = m = 1 and 2 both identified and "
        "filtered, m = 2 used unless m = 1's agree significantly better at the crossovers (order_choice_p; with fewer than "
        "choice_min_crossovers crossovers: m = 2, SPEC's default); 'spectrum' = the Whittle likelihood of the lines' "
        "spectra up to noise_fit_fmax_hz; 'likelihood' = the full-rate Kalman likelihood (m = 1, 2; dominated "
        "by the high-frequency noise)")
    recognition_order: int | None = Field(1, ge=1, le=3, description="The state map (recognition of the "
                                          "anomaly levels) of this anomaly order when it is identified, whichever "
                                          "order filters (m = 1 recognises terrain classes best: the sample 0.80 "
                                          "against 0.56 with m = 2); None: each order its own")
    order_choice_p: float = Field(0.05, gt=0, le=1, description="m = 1 replaces SPEC's default m = 2 only when its "
                                  "estimates agree significantly better at the crossovers (one-sided p below this, by the "
                                  "squared differences' paired t-test, or the signed ranks of their magnitudes when "
                                  "m = 2's crossover RMS is the larger): "
                                  "the crossovers are blind to the error two crossing lines share")
    order_blend: bool = Field(True, description="Where m = 1 is not significantly better, the estimate is the blend "
                              "w·(m = 1) + (1 − w)·(m = 2) whose crossover differences have the least mean square "
                              "(w in [0, 1], app.core.model_check.crossover_blend_weight); the std adds the blend's "
                              "share of the two orders' difference, w(1 − w)·(m₁ − m₂)². Off: m = 2 alone")
    choice_min_crossovers: int = Field(10, ge=3, le=1_000_000, description="Crossovers needed to choose between "
                                       "models (m, the FIR guard) by their crossover differences")
    flatten_check: bool = Field(True, description="A line whose estimate is flattened (flatten_min_ratio) takes the "
                                "stationary or the FIR estimate")
    flatten_min_ratio: float = Field(0.5, gt=0, le=1, description="An estimate whose along-line variance is below "
                                     "this share of the anomaly variance the FIR shows beyond its noise is flattened")
    noisy_max_ratio: float = Field(3.0, gt=1, le=1000, description="Every line takes FIR when the lines' median "
                                   "ratio of the estimate's along-line variance to the anomaly variance FIR shows "
                                   "beyond its noise exceeds this (the estimate passes noise; with flatten_check)")
    noisy_max_disagreement: float = Field(1.0, gt=0, le=1000, description="Every line takes FIR when the median "
                                          "RMS(estimate − FIR) / std(FIR) over the lines FIR resolves exceeds this "
                                          "(the estimate's error would exceed the anomaly; also bars a flattened "
                                          "line's stationary replacement; with flatten_check)")
    fir_guard: bool = Field(True, description="Use FIR 100 s when the chosen estimate disagrees significantly more "
                            "at the crossovers than FIR does")
    fir_long_periods_s: tuple[float, ...] = Field((200.0, 400.0, 800.0), description="Where the noisy check falls "
                                                  "back to FIR and FIR's crossovers show an error at least its whole "
                                                  "along-line spread (it resolves no anomaly: aliased motion on a "
                                                  "1-2 Hz record), the shortest of these longer low-passes (s) whose lines "
                                                  "vary by more than its crossovers' error is used (else the one with "
                                                  "the least); the same where the estimate kept after the FIR guard "
                                                  "shows such crossovers itself (model_choice.unresolved_check); "
                                                  "() = off")
    fir_long_max_error_ratio: float = Field(0.5, gt=0, le=1, description="The longer low-pass replaces FIR (or "
                                            "the estimate that resolves nothing) only where its crossover error is "
                                            "at most this share of the replaced one's: the error its crossovers show "
                                            "must be noise the longer low-pass removes, not the lines' levels, "
                                            "which it keeps")
    fir_guard_smoothing_std: bool = Field(True, description="When the FIR guard switches to FIR, add to FIR's std "
                                          "the anomaly it clips as the adaptive estimate sees it (var(a − FIR(a)) "
                                          "per line): an error crossing lines share, invisible at the crossovers")
    fir_guard_min_crossovers: int = Field(4, ge=2, le=1_000_000, description="Crossovers needed for the FIR "
                                          "guard's paired test (its p-value accounts for how few there are)")
    fir_guard_p: float = Field(0.05, gt=0, lt=0.5, description="Significance of those tests (one-sided p of the "
                               "paired t-test on the squared crossover differences, or of the signed-rank test on "
                               "their magnitudes when the crossover RMS agrees), below fir_guard_many_crossovers")
    fir_guard_many_crossovers: int = Field(20, ge=2, le=1_000_000, description="From this many crossovers on, the FIR "
                                           "guard's tests use fir_guard_p_many: FIR's crossovers understate its error "
                                           "(two crossing lines share the anomaly it clips), so with many crossovers a "
                                           "small bias of the test reads as significant")
    fir_guard_p_many: float = Field(0.01, gt=0, lt=0.5, description="Significance of the FIR guard's tests with at "
                                    "least fir_guard_many_crossovers crossovers (of 21 firings at p < 0.05 re-run "
                                    "without the guard, 15 of the 17 with ≥ 20 crossovers were better than FIR, "
                                    "all but one of those at p ≥ 0.01; MEASUREMENTS.md session 43)")
    repeat_blend: bool = Field(True, description="Where the crossovers are too few for the FIR guard (a test-line "
                               "survey), blend FIR 100 s into the estimate with the weight whose repeat passes agree "
                               "best with the other passes' light low-pass of z "
                               "(app.core.model_check.repeat_blend_weight); the report's model_choice.repeat_blend")
    repeat_blend_reference: Literal["smoother", "lowpass"] = Field(
        "smoother", description="The repeat blend's reference on the other passes: 'smoother' — each pass smoothed "
        "at repeat_blend_reference_q_factor x Q(t) under the fitted noise model (it rounds off little of the "
        "anomaly, and its noise is a fraction of a low-pass of z's: on 56 test lines the weight's jackknife error "
        "over the passes 0.1-0.7 against 0.2-3); 'lowpass' — FIR of z at repeat_blend_reference_period_s")
    repeat_blend_reference_q_factor: float = Field(300.0, ge=1, le=1e6, description="The smoother reference's anomaly "
                                                   "level over the estimate's Q(t): about 2.6x its bandwidth (m = 2, white "
                                                   "velocity noise: the bandwidth goes as Q^(1/6)); "
                                                   "at 10x the reference shares half the estimate's rounding and the "
                                                   "weight comes out half the truth's (MEASUREMENTS.md, session 48)")
    repeat_blend_reference_period_s: float = Field(50.0, gt=0, le=100, description="The repeat level check's "
                                                   "reference, and the repeat blend's with repeat_blend_reference = "
                                                   "'lowpass': FIR of z at this period (s), half FIR's, so that it "
                                                   "rounds off little of the anomaly; its noise, independent between "
                                                   "passes, only adds scatter")
    repeat_blend_reference_periods: float = Field(6.0, ge=1, le=20, description="Length of the reference's kernel "
                                                  "in periods: sharp (the default FIR's 2 periods let its transition "
                                                  "band round off what it should keep)")
    repeat_blend_min_passes: int = Field(3, ge=2, le=1000, description="Passes of one track the repeat blend needs")
    small_survey_fir_weight: float = Field(0.3, ge=0, le=1, description="Where nothing in the data can judge the "
                                           "estimate — fewer than fir_guard_min_crossovers crossovers, no repeat "
                                           "track of repeat_blend_min_passes passes — and its one anomaly level was "
                                           "learned from fewer than min_points_adaptive decimated points, this share "
                                           "of FIR 100 s is blended into it (0: off).  Held-out random layouts of that "
                                           "kind (14 of 100): adaptive / FIR 0.948 -> 0.921, the worst 1.45 -> 1.26, "
                                           "better on 7, worse on 7 (the pooled least-error share on the layouts it "
                                           "was chosen on: 0.33)")
    repeat_blend_shrink: bool = Field(False, description="The repeat blend's weight shrunk towards 0 (the adaptive "
                                      "estimate alone) by its jackknife error over the passes (positive-part "
                                      "James-Stein, app.core.model_check.shrunk_repeat_blend_weight). With four "
                                      "passes the weight scatters over most of [0, 1]: unshrunk it took FIR whole "
                                      "on test lines whose estimate was 0.35-0.8x FIR's error (own test lines "
                                      "0.69 -> 0.62x FIR with it), but shrunk it also lets through estimates that "
                                      "round off a sharp anomaly (independent generator's 1032 0.99 -> 1.03x FIR; "
                                      "a 2.3x-FIR estimate 1.13-1.53x): off, since a blend that is wrongly taken "
                                      "stays at or below FIR's error and one wrongly left does not")
    # --- regularization (SPEC §2 step 1)
    decimation_n: int | None = Field(None, ge=2, le=MAX_DECIMATION_N, description="Decimation factor n; chosen for ~1 km steps when None")
    decimation_step_km: float = Field(1.0, gt=0, le=50)
    cutoff_hz: float | None = Field(None, gt=0, le=500, description="Kaiser low-pass cut-off ω_s (Hz); from n when None")
    stopband_attenuation_db: float = Field(60.0, gt=10, le=200)
    regularization_difference_grid: Literal["decimated", "full"] = Field(
        "decimated", description="Where ∇^m is taken: on the decimated grid (default; keeps the GNSS noise "
        "from aliasing through the Kaiser side-lobes) or at full rate (the literal order of seed 000)")
    ma_order_K: int | None = Field(None, ge=0, le=MAX_MA_ORDER)
    ma_order_L: int | None = Field(None, ge=0, le=MAX_MA_ORDER)
    # --- EM learning (step 2)
    n_q: int | None = Field(None, ge=1, le=4, description="N1: number of anomaly intensity levels Q_i; None: 2, "
                            "or 1 (the stationary model) when the lines give fewer than min_points_adaptive "
                            "decimated points")
    min_points_adaptive: int = Field(200, ge=1, le=10_000_000, description="Decimated points needed for two anomaly levels (n_q = None)")
    n_r: int | None = Field(2, ge=1, le=3, description="N2: number of GNSS noise levels R_j; None chooses "
                            "1 or 2 by BIC (GNSS noise episodes need 2)")
    em_max_iter: int = Field(60, ge=1, le=MAX_EM_ITER)
    em_tol: float = Field(1e-6, gt=0, le=1, description="Stop when the relative objective increase is below this")
    include_tie_lines: bool = True
    level_support_min_share: float = Field(0.02, ge=0, le=1, description="An anomaly level its own EM gave to less "
                                           "than this share of the decimated points is not learned from a terrain "
                                           "(a state that shed its points; its Q drifts up on the few jumps left)")
    level_support_map_share: float = Field(0.1, ge=0, le=1, description="The report warns (identification."
                                           "level_support) when the state map applies a level below "
                                           "level_support_min_share to at least this share of the points")
    level_support_backoff: bool = Field(True, description="Such a level is filtered with its Q at the last EM "
                                        "iteration whose transition matrix still gave every level "
                                        "level_support_min_share of the steps (the level as learned from a terrain, "
                                        "before its state shed its points)")
    level_backoff_floor_min_iteration: int = Field(2, ge=0, le=MAX_EM_ITER, description="A level "
                                                   "level_support_backoff took from an EM iteration before this one "
                                                   "was never learned from a terrain (its state lost its points after "
                                                   "the first M-step: the value is the initial guess moved once): it "
                                                   "is no floor for the full-rate likelihood's level under the map "
                                                   "(refine_lift_only), which is used, kept at least the level below "
                                                   "it (0: every level taken back is a floor)")
    refine_levels: bool = Field(True, description="Re-estimate Q_i, R_j by full-rate Kalman likelihood given the "
                                "recognised states (the decimated EM can collapse a smooth state's Q)")
    refine_lift_only: bool = Field(True, description="The refinement may only raise a Q level above the EM's, "
                                   "never lower it: it guards against a collapsed level. At full rate the "
                                   "likelihood is ruled by frequencies above the anomaly band, where the "
                                   "random-walk model's spectrum decays slower than a real anomaly's, so its "
                                   "maximum sits 3-50x below the RMS-optimal level and can invert the levels")
    refine_lift_max_stationary: bool = Field(True, description="A smoothest level the refinement lifted above the "
                                             "EM's is never lifted above the one-level (stationary) model's "
                                             "full-rate level: the smooth part of a survey is no rougher than the "
                                             "whole (a lift beyond it under-smoothed the plains 1.5-2x)")
    anomaly_level_scale: float = Field(1.0, ge=0.01, le=100, description="The analyst's smoothing strength: every "
                                       "anomaly level Q the smoother uses is multiplied by this after the levels are "
                                       "fitted (> 1 smooths less, < 1 more; 1: the levels as fitted).  The "
                                       "RMS-optimal scale of the fitted levels runs from 1/16 to 8 from survey to "
                                       "survey and nothing in the data has been found to tell which way "
                                       "(MEASUREMENTS.md, session 56): set it from independent evidence (ground "
                                       "data, an earlier survey, repeat lines); the model checks of stage 9 still "
                                       "guard the result")
    crossover_noise_floor: bool = Field(False, description="When the crossovers (drift removed) show significantly "
                                        "more error than an order's posterior std predicts (p < crossover_level_p, "
                                        "at least crossover_level_min_crossovers) and the estimate keeps the anomaly "
                                        "FIR 100 s shows (crossover_noise_floor_min_flattening), a white noise floor "
                                        "(white in z, scaled by R(t)) is added to that order's noise model: the least "
                                        "at which the excess is no longer significant, found by bisection; the lines "
                                        "are smoothed again with it (more smoothing where the floor exceeds the "
                                        "fitted noise, a wider std); report level_refinement.crossover_noise_floor.  "
                                        "Off by default: it gained 5-13 % on an independent generator's point-sampled "
                                        "platform meters (aliased motion) but on held-out draws of both generators it "
                                        "lost on 7 of the 9 surveys where it applied, by up to 5 % (MEASUREMENTS.md, "
                                        "session 58)")
    crossover_noise_floor_min_flattening: float = Field(0.9, ge=0, description="crossover_noise_floor needs the "
                                                        "estimate to keep at least this much of the anomaly FIR 100 s "
                                                        "shows beyond its noise (the median flattening ratio over the "
                                                        "lines where FIR shows it, at least 3): an excess at the "
                                                        "crossovers of an estimate already smoother than FIR's anomaly "
                                                        "is not noise read as anomaly (MEASUREMENTS.md, session 58)")
    crossover_level_check: bool = Field(False, description="When the crossovers (drift removed) show significantly "
                                        "more error than the estimate's posterior std predicts, the noise in the "
                                        "anomaly band is more than the noise model knows and the likelihood read it "
                                        "as anomaly: the lines are smoothed again with every anomaly level x 2^-k and, "
                                        "when the scale s whose crossovers agree best agrees significantly better, the "
                                        "levels are multiplied by sqrt(s) (half-way: the crossovers cannot see the "
                                        "error two crossing lines share); report level_refinement.crossover_level_check "
                                        "(the excess test is reported either way).  Off by default: it gained on an "
                                        "independent generator's point-sampled platform meters (aliased motion) and "
                                        "lost on every survey of our unseen draws where it fired (MEASUREMENTS.md, "
                                        "session 57)")
    crossover_level_p: float = Field(0.05, gt=0, lt=1, description="Significance of both steps of "
                                     "crossover_level_check: the excess over the std, then the lower level's gain")
    crossover_level_min_crossovers: int = Field(8, ge=3, description="Fewest crossovers for crossover_level_check")
    crossover_level_all_orders: bool = Field(False, description="crossover_level_check scans every anomaly order "
                                             "when any order's crossovers show the excess (False: only the orders "
                                             "whose own crossovers show it; on 18 generated surveys every order "
                                             "gained more on average but lost on 4, its own on 1)")
    crossover_level_min_scale: float = Field(2.0 ** -8, gt=0, lt=1, description="Lowest scale crossover_level_check "
                                             "scans (a power of 2)")
    rough_level_factor: float = Field(2.0, ge=1, le=100, description="With m >= 2 and two or more anomaly "
                                      "levels the roughest is filtered at no less than this factor times its "
                                      "full-rate likelihood level (the EM's, when higher, is kept): the likelihood "
                                      "fits the level where the data say most, below the smoother's cutoff, and a "
                                      "real anomaly's spectrum falls slower than the m = 2 prior's toward the "
                                      "cutoff, so the mountains came out over-smoothed (the truth-tuned oracle's "
                                      "mountain level was 1.1-24x, median 3x, the likelihood's on two independent "
                                      "simulators). 1: the levels as lifted")
    q_from_posteriors: bool = Field(True, description="Q(t) for filtering: the Q levels' geometric mean weighted "
                                    "by the smoothed map's probabilities, interpolated between decimated points "
                                    "(False: the held state's level, jumping at the hold boundaries)")
    std_level_factor: float = Field(10.0, ge=1, le=1000, description="On a survey with one anomaly level (too few "
                                    "decimated points for two), or n_q levels learned from fewer than "
                                    "n_q x min_points_adaptive decimated points, dg_std_mgal also carries the "
                                    "levels' uncertainty: "
                                    "the larger difference between the estimate at Q and at Q/f or f·Q (f = this) "
                                    "is added in quadrature; 1 = off.  The data do not fix Q there within a decade "
                                    "(held-out small layouts: the RMS-optimal Q 6-34x above the estimate on some, "
                                    "below it on others; 2-sigma coverage 0.81-0.89 on average without it)")
    std_level_min_contrast: float = Field(3.0, ge=1, le=1000, description="Two or more anomaly levels whose "
                                          "largest is within this factor of the smallest are levels the EM did not "
                                          "tell apart (the map says nothing of where the anomaly is rougher): "
                                          "dg_std_mgal carries the level's uncertainty as with one level "
                                          "(std_level_factor).  1 = off")
    std_repeat_min_samples: float = Field(8.0, ge=0, description="Where std_level_factor would widen the std and "
                                          "repeat passes measure the error instead (the passes' scatter: the noise "
                                          "part; their common difference from the estimate at std_level_factor x Q: "
                                          "the smoothing part), a repeat track's dg_std_mgal is widened (never "
                                          "narrowed) to that error, given at least this many independent stretches "
                                          "on the track (fir_cutoff_period_s of flight x (passes - 1)); lines off "
                                          "the tracks keep the spread; 0 = off")
    repeat_level_check: bool = Field(True, description="Where the crossovers are too few to judge the estimate "
                                     "(fewer than fir_guard_min_crossovers: a test line) and a repeat track has "
                                     "repeat_blend_min_passes passes or more, the anomaly level Q(t) is scaled by "
                                     "1 / repeat_level_factor (or by its powers up to repeat_level_raise_steps, with "
                                     "repeat_level_raise) "
                                     "when the passes then agree significantly better with the other passes' "
                                     "reference (repeat_level_reference) away from the ends of their common stretch "
                                     "(repeat_level_edge_km; repeat_level_significance)")
    repeat_level_factor: float = Field(3.0, gt=1, le=100, description="The repeat level check tries Q(t) / this "
                                       "(and Q(t) x this with repeat_level_raise)")
    repeat_level_raise: bool = Field(True, description="The repeat level check also tries Q(t) x repeat_level_factor. "
                                     "Against the other passes smoothed at 300 x Q(t), in the interiors: on 64 "
                                     "held-out generated test lines better than the check that only lowered by > 1 % "
                                     "on 9, worse on 1; against the 50 s low-pass of z (the check's earlier "
                                     "reference) Q x 3 had made 5 of 18 less repeatable and one 9 % worse")
    repeat_level_raise_steps: int = Field(2, ge=1, le=4, description="With repeat_level_raise, the check tries "
                                          "Q(t) x repeat_level_factor^k for k = 1 .. this (3 and 9 by default) and "
                                          "keeps the significant one with the least figure: a level a decade too low "
                                          "(the generator's test lines 1064, 1176: 10-14 % less error) is not mended "
                                          "by x 3 alone.  1 = x 3 only (session 49's ladder)")
    repeat_level_reference: Literal["smoother", "lowpass"] = Field(
        "smoother", description="The repeat level check's reference: each pass smoothed at "
        "repeat_blend_reference_q_factor x Q(t) under the fitted noise model ('smoother'), or the light low-pass of z "
        "of repeat_blend_reference_period_s ('lowpass', the earlier reference: ~13 mGal of noise at 2 Hz, which left "
        "the check little power)")
    repeat_level_edge_km: float = Field(10.0, ge=0, le=1000, description="The repeat level check compares the passes "
                                        "only this far (km) or more from the ends of their common stretch (all of it "
                                        "where fewer than three test blocks would remain), and a scaled level is used "
                                        "only there, on every line this far or more from its ends (the ends keep "
                                        "theirs): near the ends the smoother sees the anomaly from one side and the "
                                        "run-in's manoeuvres, and a level that suits the interior is not the one they "
                                        "need (scaled along whole lines, held-out test lines 69-84 gained 0.540 -> "
                                        "0.526 x FIR in the interiors and lost 0.598 -> 0.609 over whole lines).  "
                                        "0: the whole common stretch judged, the levels scaled everywhere")
    repeat_level_block_s: float = Field(50.0, gt=0, le=10_000, description="Block length (s of flight) of the repeat "
                                        "level check's t-test over the passes' figure difference: several times the "
                                        "difference's own correlation (its integrated autocorrelation 0.8 km, up to 4 "
                                        "km, over 88 generated test lines at 100 m positions; blocks of 50 s at "
                                        "60 m/s are 3 km)")
    repeat_level_significance: float = Field(0.1, gt=0, le=1, description="A scaled level is used "
                                             "only where the passes agree better so at this one-sided level "
                                             "(t-test over repeat_level_block_s blocks of the passes' figure "
                                             "difference)")
    rescale_noisy_passes: bool = Field(True, description="Repeat passes whose departures from the other passes "
                                       "show more noise than their posterior (the passes' mean noise ratio above 1 "
                                       "at std_repeat_significance, std_repeat_min_samples stretches) are smoothed "
                                       "again with their noise level R(t) times their own ratio: a pass flown "
                                       "through turbulence the noise model did not give it is smoothed more")
    std_repeat_significance: float = Field(0.1, gt=0, le=1, description="The passes size a repeat track's std only "
                                           "when their smoothing part is above 0 at this one-sided level (F-test of "
                                           "their mean difference against its noise, one degree of freedom per "
                                           "independent stretch; 1 = any positive estimate): a smoothing part lost "
                                           "in the passes' noise says nothing of the error they share")
    std_state_mixture: bool = Field(True, description="dg_std_mgal as the std of a mixture of levels where the map is "
                                    "unsure: the larger of the smoother under the probability-weighted arithmetic "
                                    "mean of the Q levels and the law of total variance over each level's smoother "
                                    "(dg_mgal uses the geometric mean)")
    noise_model: Literal["band", "local", "states"] = Field(
        "band", description="GNSS noise level for filtering: 'band' = R(t) from z's content just above the "
        "anomaly band (noise_band_hz), scaled to the EM's in-band level; 'local' = R(t) from the high-frequency "
        "content of z, scaled likewise; 'states' = the recognised R_j levels (seed 000)")
    noise_level_unmix: bool = Field(False, description="Measure the band level R(t) on z less its part linear in "
                                    "the gravimeter's specific force (lags ±5 epochs, band-passed): the two instruments' "
                                    "response mismatch follows the turbulence, not the GNSS noise, and has no weight in "
                                    "the anomaly band.  Off by default: over 88 surveys as good on average, but its two "
                                    "largest changes were losses (docs/MEASUREMENTS.md, session 20)")
    noise_band_hz: tuple[float, float] = Field((0.1, 0.5), description="Band (Hz) in which the 'band' noise "
                                               "model measures the local GNSS noise level")
    noise_family_crossover_check: bool = Field(True, description="When the noise fit chose another family than "
                                               "white velocity (the paper's) by fewer than twice the BIC margin, and "
                                               "the survey has noise_family_crossover_min crossovers or more: identify "
                                               "and filter again with white velocity and use it when its estimate "
                                               "agrees significantly better at the crossovers (the order choice's "
                                               "paired tests at order_choice_p).  Process jobs only")
    noise_family_crossover_min: int = Field(20, ge=3, le=1_000_000, description="Crossovers needed for that check")
    noise_episode_factor: float = Field(4.0, gt=1, le=1e6, description="Report (and warn of) the stretches of the lines "
                                        "where the noise level the smoother used, R(t), exceeds this many times the "
                                        "survey's typical level (its median over the lines' epochs): the report's "
                                        "noise_episodes.  Nothing is filtered differently")
    noise_episode_min_s: float = Field(30.0, ge=0, le=1e5, description="Shortest noise episode listed (s)")
    noise_episode_bridge_s: float = Field(10.0, ge=0, le=1e5, description="Gaps up to this long (s) inside a noise "
                                          "episode are bridged (one episode, not two)")
    noise_family: Literal["auto", "white velocity", "Gauss-Markov velocity", "white height", "coloured height",
                          "white + Gauss-Markov velocity", "velocity + height", "white velocity + coloured height",
                          "white + coloured height", "coloured velocity + height"] = Field(
        "auto", description="Shape of the error of z in the smoother (app.core.noise_model): 'auto' fits every "
        "family to the lines' spectra and keeps the best by BIC; 'white velocity' is seed 000's model")
    noise_corner_check: bool = Field(True, description="Keep the noise fit's own shape below the data (AR "
                                     "corners where the spectra put them; a bare white height without the "
                                     "random-walk height part the nesting family adds) when the cautious shape "
                                     "predicts more FIR noise than the FIR crossover differences allow (one-sided "
                                     "test at noise_corner_alpha)")
    noise_corner_alpha: float = Field(0.05, gt=0, lt=0.5, description="Level of that test (χ² bound of the "
                                      "crossovers' mean square difference)")
    gnss_fill_max_error_mgal: float | None = Field(5.0, gt=0, description="A hole of missing GNSS epochs is put "
                                                   "back on the receiver's clock (spline) when, with as many epochs "
                                                   "taken out of the record elsewhere, the bridge moves FIR 100 s by "
                                                   "at most this (mGal, peak, RMS over 40 places): 1-6 missing epochs "
                                                   "of a 2 Hz record 0.1-3.6, 25+ of a 10 Hz one in turbulence 41-210. "
                                                   "None = any hole up to max_gap_s")
    gravimeter_fill_max_error_mgal: float | None = Field(1.0, gt=0, description="A hole of missing gravimeter "
                                                         "samples (a step of a whole number of clock steps, at most "
                                                         "max_gap_s) is put back on the instrument's clock (spline) "
                                                         "when, with as many samples taken out of the record "
                                                         "elsewhere, the bridge moves FIR 100 s by at most this (mGal, "
                                                         "peak, RMS over 40 places; the bound at which FIR is kept "
                                                         "next to a hole, fir_gap_max_error_mgal). None = never: every "
                                                         "missing sample a hole")
    fir_gap_max_error_mgal: float | None = Field(1.0, gt=0, description="FIR 100 s is left out (NaN) where missing "
                                                 "samples inside the record could move it by more than this (mGal; "
                                                 "robust std of z next to the hole × the kernel weight on it): one missing sample of "
                                                 "a 2 Hz platform record moved it by up to 150 mGal. None = never")
    noise_family_check: bool = Field(True, description="When the noise fit chose a coloured (Gauss-Markov) "
                                     "velocity error, fall back on the best family without one if the chosen model "
                                     "predicts more FIR noise than the FIR differences at the crossovers and between "
                                     "repeat passes allow (one-sided test at noise_family_alpha) and the fallback does not "
                                     "predict significantly less: a flat acceleration noise carried down into the "
                                     "anomaly band flattens the estimate")
    noise_family_alpha: float = Field(0.05, gt=0, lt=0.5, description="Level of that test (and of the check that "
                                      "the fallback does not predict significantly less FIR noise than the "
                                      "differences show)")
    white_level_bounded: bool = Field(True, description="With the white-velocity family and the heights' bound on the "
                                      "velocity error applied, lower the level to what the bound allows below "
                                      "0.01 Hz (the band measurement can hold a turbulence bump the f² shape "
                                      "carries down)")
    white_level_fitted: bool = Field(True, description="With the white-velocity family, lower the noise level "
                                     "from the band measurement (noise_band_hz) to the level fitted to the lines' "
                                     "spectra when that is lower — on surveys with at least "
                                     "fir_guard_min_crossovers crossovers, where the FIR guard checks the rougher "
                                     "estimate (a level fitted on two or three lines' spectra misses by 2x either "
                                     "way)")
    noise_fit_repeats: bool = Field(True, description="Fit the noise model also to the differences of the passes "
                                    "of repeat tracks (the anomaly cancels: the noise alone, down to the band "
                                    "where it hides under the anomaly)")
    em_level_scale_min: float = Field(1.0, gt=0, le=1, description="The local noise level R(t) is scaled to the "
                                      "EM's level on the regularized band (where anomaly and noise meet); this "
                                      "bounds the factor from below (1 = only ever scale up, as before the noise "
                                      "shape was fitted)")
    noise_height_tau_min_s: float = Field(20.0, gt=0, le=10_000, description="Shortest correlation time (s) of a "
                                          "GNSS height error: with heights-only GNSS, the corner of a height family "
                                          "preferred to a velocity one is kept below 1/(2π·this) (0.008 Hz) as well "
                                          "as below the lowest fitted frequency")
    noise_knee_max_fraction: float | None = Field(None, gt=0, le=100, description="Corner frequencies of the "
                                                  "AR(1) noise components at most this × the lowest fitted "
                                                  "frequency (None: anywhere)")
    noise_fit_octave_weights: bool = Field(False, description="Weight the spectra's bins so that every octave "
                                           "counts like the lowest one")
    noise_anomaly_rolloff: bool = Field(True, description="Fit the anomaly's spectrum in the noise fit as the random "
                                        "walk times exp(-beta f), beta free (a field seen from above its sources "
                                        "falls exponentially); False: the random walk alone")
    noise_fit_fmax_hz: float = Field(0.2, gt=0, le=500, description="Highest frequency (Hz) of the spectra the noise "
                                     "model is fitted to (clipped to 0.8 × the GNSS Nyquist frequency)")
    noise_fit_min_s: tuple[float, float] = Field((120.0, 60.0), description="Shortest stretch of z (s) the noise "
                                                 "model is fitted on; the second value is used, with a warning, "
                                                 "when no line has a stretch as long as the first (short lines)")
    refine_max_epochs: int = Field(100_000, ge=1000, le=10_000_000, description="Cap on epochs used by the level "
                                   "refinement (a subset of lines covering every state; ~3 h of 10 Hz data is "
                                   "enough to see a collapsed level, which is all the refinement now corrects)")

    @field_validator("noise_band_hz")
    @classmethod
    def _band_increasing(cls, v):
        if not 0 < v[0] < v[1] <= 500:
            raise ValueError("noise_band_hz must be (f1, f2) with 0 < f1 < f2 ≤ 500 (Hz)")
        return v

    @field_validator("fir_long_periods_s")
    @classmethod
    def _long_periods(cls, v):
        if len(v) > 8 or not all(0 < x <= 10_000 for x in v):
            raise ValueError("fir_long_periods_s must hold at most 8 periods, each 0 < P ≤ 10000 (s)")
        return v

    @field_validator("noise_fit_min_s")
    @classmethod
    def _stretches_decreasing(cls, v):
        if not 0 < v[1] <= v[0] <= 100_000:
            raise ValueError("noise_fit_min_s must be (s1, s2) with 0 < s2 ≤ s1 ≤ 100000 (s)")
        return v
    recognition_pool_h_per_km: float = Field(0.7, ge=0, le=100, description="Decay of the weights with which neighbouring "
                                             "lines' evidence about the anomaly intensity enters each line's recognition")
    recognition_pool_rho_km: float = Field(5.0, ge=0, le=15, description="Radius of that evidence pooling (km); 0 = off "
                                           "(the paper's per-line recognition)")
    # --- recognition smoothing (step 4)
    nlmeans_h_per_km: float = Field(0.5, ge=0, le=100, description="NL-means weight decay h (1/km); SPEC default 0.5 (the paper used 1.4)")
    nlmeans_rho_km: float = Field(10.0, ge=0, le=15, description="NL-means radius ρ (km); SPEC default 10 (the paper used 5)")
    nlmeans_mode: Literal["hard", "soft"] = "soft"
    # --- filtering (steps 5-6)
    smoother: Literal["bf", "rts"] = "bf"
    fir_cutoff_period_s: float = Field(100.0, gt=0, le=10_000)
    # --- survey level (SPEC §3)
    calibrate: bool = False
    lag_check_s: float | None = Field(0.05, gt=0, le=10, description="Estimate the gravimeter lag τ in flight (τ only, "
                                      "first three flights) and use the median when it differs from survey.toml's "
                                      "by more than this (s) and the flights agree within it; None trusts "
                                      "survey.toml")
    lag_check_min_change_s: float = Field(0.02, gt=0, le=10, description="An in-flight τ closer to survey.toml's "
                                          "than lag_check_s, but more than this (s) away, is used only when the band "
                                          "check runs and confirms it (lag_check_min_improvement)")
    lag_from_time_offsets: bool = Field(True, description="Read the flights' time offsets of −0.02 to −0.5 s as an "
                                        "undeclared gravimeter lag when that lowers z's band RMS (lag check); on since "
                                        "session 27, when the repeat passes size a track's std only where their "
                                        "smoothing part is significant (std_repeat_significance): on the 4-pass test "
                                        "line the lag it finds no longer narrows the std (seed 3 2σ coverage 0.94); "
                                        "not tried for a gravimeter slower than the GNSS (slow_gravimeter_min_ratio)")
    lag_band_fit: bool = Field(True, description="Fit τ where the anomaly is estimated: the lag that leaves the least of "
                               "the gravimeter's jerk in z at 2–5 × 1/fir_cutoff_period_s Hz (lag check; used when "
                               "significant at lag_band_fit_z standard errors and it lowers z's RMS there by "
                               "lag_check_min_improvement)")
    lag_band_fit_z: float = Field(5.0, gt=0, le=100, description="Standard errors by which the band-fitted τ must differ "
                                  "from survey.toml's to be used (the fit's error counts the band's independent samples "
                                  "and takes the turns' manoeuvres as the lines' motion)")
    lag_band_confirm_z: float = Field(3.0, gt=0, le=100, description="A wideband in-flight τ whose band check gains "
                                      "less than lag_check_min_improvement (but > 0) is still used when the band fit's "
                                      "first estimate lies this many standard errors from survey.toml's τ and within "
                                      "two of the wideband τ")
    lag_check_min_improvement: float = Field(0.01, ge=0, lt=1, description="The in-flight τ of lag_check_s is used only "
                                             "when it also lowers the RMS of z by at least this share in the band just above "
                                             "FIR's cutoff (2–5 × 1/fir_cutoff_period_s), where the estimate "
                                             "separates anomaly from noise")
    lag_one_scale: bool = Field(True, description="Compare the flights' in-flight lags on one scale, each τ fit minus "
                                "the time offset applied before it (a time offset fitted at survey.toml's τ can take "
                                "an undeclared lag for a shift of the stamps on some flights and not on others), and "
                                "use their median when they agree (lag check)")
    lag_one_scale_min_improvement: float = Field(0.05, ge=0, lt=1, description="The lags on one scale are used only "
                                                 "when they lower z's RMS in the band just above FIR's cutoff by at "
                                                 "least this share (on 16 generated surveys the two that gained 2.3 "
                                                 "and 2.8 % lost accuracy, 1 Hz and 2 Hz meters on 2-5 Hz GNSS; "
                                                 "the five that gained 9-78 % won)")
    leveling_degree: int = Field(1, ge=0, le=2)
    noise_velocity_bound: bool = Field(True, description="Bound the noise model's GNSS velocity error from above by "
                                       "the spectrum of what the file's heights and velocities disagree on "
                                       "(h − ∫vu), where the anomaly hides the noise in z (not for velocities "
                                       "derived from the heights)")
    noise_velocity_bound_fmax_hz: float = Field(0.01, gt=0, le=1, description="Highest frequency (Hz) of that "
                                                "bound: below it the velocity error dominates the misfit and the "
                                                "GNSS the error of z")
    noise_velocity_bound_quantile: float = Field(0.9, gt=0, lt=1, description="The bound binds from this quantile "
                                                 "of its estimate's sampling distribution (χ²) on, so a group that fell "
                                                 "low by chance does not pull the noise model down")
    std_unresolved_bound: bool = Field(True, description="On a line that does not resolve the anomaly (FIR shows "
                                       "none beyond its predicted noise and the estimate varies by less than its "
                                       "std), widen dg_std_mgal to Var(FIR) - Var(estimate), the error a smooth "
                                       "estimate can have; also on every line FIR cannot judge alone when the lines' "
                                       "median flattening ratio is below flatten_min_ratio (flattened as a whole)")
    std_common_level: bool = Field(True, description="Without an absolute base tie, add to dg_std_mgal and the grid "
                                   "std the std of the level leveling leaves common to the flights: the flights' "
                                   "offsets at the crossovers, read as draws of one drift, spread by s; their mean is "
                                   "off by s/sqrt(n) (report crossovers.common_level)")
    std_crossover_check: bool = Field(True, description="Rescale dg_std by what the crossover differences say "
                                      "about the two lines' errors (widen only, below std_crossover_min_n)")
    std_crossover_min_n: int = Field(20, ge=3, le=1_000_000, description="Crossovers needed to also narrow dg_std (fewer: the "
                                     "check only widens it)")
    std_crossover_min_n_widen: int = Field(2, ge=2, le=1_000_000, description="Crossovers needed to widen dg_std "
                                           "(a small survey's std has nothing else to check it)")
    std_crossover_min_factor: float = Field(1.0, gt=0, le=1, description="Never narrow dg_std by more than this "
                                            "factor (default 1: never narrow — crossovers see only the difference of two lines' errors, blind to "
                                            "what they share, so they can show a std too small, never too large)")
    std_crossover_shared_fraction: float = Field(0.2, ge=0, lt=1, description="Correlation assumed between two "
                                                 "crossing lines' errors (they share part of the unresolved anomaly "
                                                 "at the crossing), so Var(diff) = 2σ²(1 − this).  What the std "
                                                 "needed against truth implies varies with the survey (0-0.6 over two "
                                                 "seeds of 11 regimes); 0.2 gave the 2σ coverage closest to 95 % over "
                                                 "both (mean |cov − 0.95| 0.024 against 0.029 with 0.4)")
    leveling_cross_validate: bool = Field(True, description="Apply the leveling only when the drift, fitted "
                                          "without a line's crossovers, also predicts them (leave-one-line-out RMS "
                                          "significantly below the RMS without leveling, paired test at "
                                          "leveling_cv_significance)")
    leveling_significance: float = Field(0.01, gt=0, le=1, description="Apply the leveling only when the drift "
                                         "model's F-test against no correction at the crossovers has p below this "
                                         "(1 = always apply)")
    leveling_cv_significance: float = Field(0.05, gt=0, le=1, description="Significance of the leave-one-line-out "
                                            "check (leveling_cross_validate), a second test after the F-test has "
                                            "called the drift significant: one-sided p of the held-out RMS being "
                                            "below the RMS without leveling.  At 0.01 it refused an independent "
                                            "survey's flight offsets (crossover RMS 11.5 -> 1.0 mGal, p = 0.019; "
                                            "its lines 9.8 mGal from the truth unleveled, 3.0 leveled); 0.05 "
                                            "levels none of 43 own simulated surveys the 0.01 did not")
    leveling_cv_significance_untied: float = Field(0.5, gt=0, le=1, description="The same check where a flight "
                                                   "has no absolute base tie: each such flight keeps its own "
                                                   "reading offset, so the flights differ in level for certain and "
                                                   "the held-out RMS need only be lower, more likely than not (0.5). "
                                                   "Independent generator (no ties): 13 of 112 surveys closer to "
                                                   "the truth by > 3 %, none further; the own simulator's surveys "
                                                   "with their ties dropped: 5 of 30 closer, none further")
    leveling_offset_fallback: bool = Field(True, description="Where the drift of leveling_degree is refused, try "
                                           "one offset per flight (degree 0) under the same tests: half the "
                                           "parameters, more power for the flights' level differences alone")
    leveling_per_flight: bool = Field(True, description="One drift polynomial per flight (the instrument drifts, not the line); False: one per line")
    leveling_max_height_difference_m: float = Field(300.0, gt=0, le=100_000, description="Warn when crossing "
                                                    "lines were flown more than this far apart in height (m) at a "
                                                    "crossover: the anomaly differs with height, which leveling takes "
                                                    "for drift (not when the lines were continued to a datum)")
    leveling_repeat_tracks: bool = Field(True, description="On a survey without crossovers, level each repeat "
                                         "track's passes against each other: each pass's offset and each flight's "
                                         "drift (leveling_degree) fitted to the passes' differences at common points, "
                                         "applied when their F-test has p ≤ leveling_repeat_significance; the "
                                         "passes' mean level kept")
    leveling_repeat_significance: float = Field(0.05, gt=0, le=1, description="Apply the repeat-track leveling to "
                                                "passes whose flights are tied to an absolute base reading only when "
                                                "the F-test of their offsets and drift against no correction has p "
                                                "at most this: the ties took out each flight's offset and drift, and "
                                                "leveling the passes' own errors against each other costs as often "
                                                "as it gains (119 tied test lines with truth, docs/MEASUREMENTS.md, "
                                                "session 50)")
    leveling_repeat_significance_untied: float = Field(1.0, gt=0, le=1, description="The same where a flight of "
                                                       "the passes has no absolute base tie: it keeps its reading "
                                                       "offset and drift, so its passes differ in level for certain "
                                                       "(1 = always; the p is reported): the fit is a least-squares "
                                                       "projection of their differences, so their total error "
                                                       "cannot grow")
    leveling_repeat_drift_significance: float = Field(0.05, gt=0, le=1, description="The repeat-track leveling "
                                                      "fits each flight's drift (leveling_degree) besides the passes' "
                                                      "offsets only when it explains their differences beyond the "
                                                      "offsets (partial F-test p below this): passes flown one way "
                                                      "see a drift mostly as offsets, and a drift fitted to their "
                                                      "errors there runs away")
    leveling_repeat_block_s: float = Field(50.0, gt=0, le=3600, description="Length (s of flight) of the blocks whose "
                                           "mean differences the repeat-track leveling fits: the estimates' errors are "
                                           "correlated over about the smoother's span, so shorter blocks would count "
                                           "one error many times")
    leveling_include_repeat: bool = Field(False, description="Use repeat lines' crossings in leveling (repeats of one track overlap along their whole length; with per-flight leveling they are corrected through their flight)")
    grid_line_error_fraction: float = Field(0.0, ge=0, le=1, description="Share of the lines' posterior variance "
                                            "treated as an error shared along each line in the collocation")
    grid_std_line_floor: bool = Field(True, description="Grid std never below the posterior std of the nearby line "
                                      "estimates (their errors are correlated along the lines, so averaging them "
                                      "does not reduce the error as independent data would)")
    grid_std_cross_validate: bool = Field(False, description="Scale the grid std up by the RMS of leave-line-out "
                                          "normalised residuals when the collocation model under-states it")
    grid_error_corr_km: float = Field(1.0, ge=0, le=1000, description="Along-line error correlation length for thinning in collocation")
    # --- geophysical products (app.pipeline.stages.products)
    atmospheric_correction: bool = Field(False, description="Add the IAG atmospheric correction δg_atm(h) (US "
                                         "Standard Atmosphere 1976: 0.84 mGal at 330 m) to every estimate. Off by "
                                         "default: dg_mgal is SPEC §1's disturbance, whose z has no atmospheric "
                                         "term; the correction is written per epoch (atm_corr_mgal) either way")
    datum: Literal["flight", "constant", "draped"] = Field(
        "flight", description="Surface the anomaly is given on: 'flight' (the flight height, no continuation), "
        "'constant' (datum_height_m) or 'draped' (a smooth surface through the flight heights); the others "
        "continue the line estimates by equivalent sources, and leveling and gridding use the continued values")
    datum_height_m: float | None = Field(None, ge=-1000, le=20000, description="Height of the constant datum (m, "
                                         "ellipsoidal); None: the mean flight height")
    datum_smoothing_m: float = Field(2000.0, gt=0, le=100_000, description="Smoothing length of the draped datum (m)")
    bouguer_density_kgm3: float = Field(2670.0, gt=0, le=5000, description="Density of the terrain correction (kg/m³)")
    terrain_radius_m: float = Field(20_000.0, gt=0, le=200_000, description="Radius of the DEM prisms summed (m)")
    terrain_near_radius_m: float | None = Field(5000.0, gt=0, le=200_000, description="Exact prisms within this "
                                                "radius, 4×4 blocks beyond (None: every prism exact)")
    dem_spacing_m: float | None = Field(None, gt=0, le=10_000, description="Cell size the DEM is resampled to (m); "
                                        "None: its own")
    dem_height_offset_m: float = Field(0.0, ge=-1000, le=1000, description="Added to the DEM's heights to reach the "
                                       "GNSS's ellipsoidal heights (a geoid height, m)")
    grid_spacing_km: float = Field(1.0, ge=0.01, le=100, description="Grid node spacing (km); the grid "
                                   f"over the lines' extent may have at most {MAX_GRID_CELLS:,} nodes")
    gridding: Literal["collocation", "spline"] = "collocation"
    grid_mask_km: float | None = Field(None, gt=0, le=1000, description="Mask cells farther than this from any line; 1.5× line spacing when None")


class SurveyConfig(_Strict):
    """The whole ``survey.toml``."""

    survey: SurveySection = SurveySection()
    gravimeter: GravimeterSection = GravimeterSection()
    processing: ProcessingParams = ProcessingParams()
    columns: ColumnsSection = ColumnsSection()


# ---------------------------------------------------------------- the parameters by pipeline stage
#: The processing parameters grouped by the stage that uses them, for the parameters form:
#: (key, title, the common parameters — shown —, the advanced ones — folded away).  A parameter in
#: no list lands by its name's prefix (:data:`PARAM_GROUP_PREFIXES`), else in "other": a parameter
#: added later is never left out of the form (:func:`param_groups`).
PARAM_GROUPS: tuple[tuple[str, str, tuple[str, ...], tuple[str, ...]], ...] = (
    ("measurement", "Measurement: rates, gaps, spikes, time offset, gravimeter lag",
     ("max_gap_s", "despike_threshold", "apply_time_offset", "calibrate"),
     ("gnss_rate_hz", "rate_tolerance", "geoid_height_m", "gravimeter_gap_margin_s", "height_step_threshold", "despike_max_fraction",
      "max_nan_run", "estimate_time_offset", "max_time_offset_s", "time_offset_min_z", "time_offset_min_improvement",
      "clock_track", "clock_window_s", "clock_p", "clock_min_change_s",
      "match_response", "response_min_z", "response_min_improvement",
      "slow_gravimeter_min_ratio", "slow_gravimeter_short_drop", "height_matched_means", "band_delay_check", "band_delay_min_t", "band_delay_flights_p", "gnss_fill_max_error_mgal", "gravimeter_fill_max_error_mgal", "lag_check_s",
      "lag_check_min_change_s", "lag_from_time_offsets", "lag_band_fit", "lag_band_fit_z", "lag_band_confirm_z",
      "lag_check_min_improvement", "lag_one_scale", "lag_one_scale_min_improvement")),
    ("noise", "Noise model: the error of z and the local GNSS noise level",
     ("noise_model", "noise_family", "noise_band_hz"),
     ("noise_level_unmix", "noise_corner_check", "noise_corner_alpha", "noise_family_check", "noise_family_alpha",
      "white_level_bounded", "white_level_fitted", "noise_fit_repeats", "em_level_scale_min", "noise_height_tau_min_s",
      "noise_knee_max_fraction", "noise_fit_octave_weights", "noise_anomaly_rolloff", "noise_fit_fmax_hz",
      "noise_fit_min_s", "noise_velocity_bound", "noise_velocity_bound_fmax_hz", "noise_velocity_bound_quantile",
      "noise_episode_factor", "noise_episode_min_s", "noise_episode_bridge_s", "noise_family_crossover_check",
      "noise_family_crossover_min")),
    ("order", "Anomaly model: the order m",
     ("m", "model_order"),
     ("recognition_order", "order_choice_p", "order_blend")),
    ("regularization", "Regularization: decimation, low-pass, MA approximation",
     ("decimation_step_km",),
     ("decimation_n", "cutoff_hz", "stopband_attenuation_db", "regularization_difference_grid", "ma_order_K",
      "ma_order_L")),
    ("identification", "Identification: EM learning of the levels and transitions",
     ("n_q", "n_r", "em_max_iter", "em_tol"),
     ("min_points_adaptive", "include_tie_lines", "level_support_min_share", "level_support_map_share",
      "level_support_backoff", "level_backoff_floor_min_iteration", "refine_levels", "refine_lift_only",
      "refine_lift_max_stationary", "refine_max_epochs",
      "rough_level_factor", "crossover_noise_floor",
      "crossover_noise_floor_min_flattening", "crossover_level_check", "crossover_level_p", "crossover_level_min_crossovers",
      "crossover_level_all_orders", "crossover_level_min_scale")),
    ("recognition", "Recognition map: NL-means smoothing and cross-line evidence",
     ("nlmeans_h_per_km", "nlmeans_rho_km", "nlmeans_mode"),
     ("recognition_pool_h_per_km", "recognition_pool_rho_km")),
    ("filtering", "Filtering and the posterior std",
     ("smoother", "fir_cutoff_period_s", "anomaly_level_scale"),
     ("fir_gap_max_error_mgal", "q_from_posteriors", "std_level_factor", "std_level_min_contrast",
      "std_repeat_min_samples",
      "std_repeat_significance", "std_state_mixture", "std_unresolved_bound", "std_common_level", "std_crossover_check",
      "std_crossover_min_n", "std_crossover_min_n_widen", "std_crossover_min_factor", "std_crossover_shared_fraction",
      "rescale_noisy_passes")),
    ("choice", "Model choice: flattened and noisy estimates, FIR guard, test lines",
     ("fir_guard", "flatten_check", "repeat_blend"),
     ("choice_min_crossovers", "flatten_min_ratio", "noisy_max_ratio", "noisy_max_disagreement", "fir_long_periods_s",
      "fir_long_max_error_ratio", "fir_guard_smoothing_std", "fir_guard_min_crossovers", "fir_guard_p", "fir_guard_many_crossovers",
      "fir_guard_p_many",
      "repeat_blend_reference", "repeat_blend_reference_q_factor",
      "repeat_blend_reference_period_s", "repeat_blend_reference_periods", "repeat_blend_min_passes",
      "repeat_blend_shrink", "small_survey_fir_weight",
      "repeat_level_check", "repeat_level_factor", "repeat_level_raise", "repeat_level_raise_steps",
      "repeat_level_reference",
      "repeat_level_edge_km", "repeat_level_block_s", "repeat_level_significance")),
    ("leveling", "Leveling at the crossovers",
     ("leveling_degree", "leveling_per_flight", "leveling_significance"),
     ("leveling_cross_validate", "leveling_cv_significance", "leveling_cv_significance_untied",
      "leveling_offset_fallback", "leveling_max_height_difference_m", "leveling_include_repeat",
      "leveling_repeat_tracks", "leveling_repeat_significance", "leveling_repeat_significance_untied",
      "leveling_repeat_drift_significance",
      "leveling_repeat_block_s")),
    ("gridding", "Gridding and the grid std",
     ("grid_spacing_km", "gridding", "grid_mask_km"),
     ("grid_line_error_fraction", "grid_std_line_floor", "grid_std_cross_validate", "grid_error_corr_km")),
    ("products", "Products: atmosphere, datum, terrain and Bouguer",
     ("atmospheric_correction", "datum", "datum_height_m", "bouguer_density_kgm3"),
     ("datum_smoothing_m", "terrain_radius_m", "terrain_near_radius_m", "dem_spacing_m", "dem_height_offset_m")),
)
#: name prefix → group, for a parameter no group lists (first match wins; advanced)
PARAM_GROUP_PREFIXES: tuple[tuple[str, str], ...] = (
    ("noise_", "noise"), ("lag_", "measurement"), ("time_offset", "measurement"), ("despike", "measurement"),
    ("gnss_", "measurement"), ("gravimeter_", "measurement"), ("band_delay", "measurement"), ("em_", "identification"),
    ("refine_", "identification"), ("nlmeans_", "recognition"), ("recognition_", "recognition"), ("std_", "filtering"),
    ("fir_guard", "choice"), ("repeat_", "choice"), ("flatten", "choice"), ("noisy_", "choice"), ("fir_", "filtering"),
    ("order", "order"), ("decimation", "regularization"), ("ma_order", "regularization"), ("leveling", "leveling"),
    ("grid", "gridding"), ("datum", "products"), ("terrain", "products"), ("dem_", "products"), ("bouguer", "products"),
    ("atmospher", "products"),
)


def param_groups(model: type[BaseModel] = ProcessingParams) -> list[dict]:
    """The parameters of ``model`` by group: ``[{key, title, common: [...], advanced: [...]}]``, in
    :data:`PARAM_GROUPS`' order and each list in the model's field order, every field in exactly
    one group (by :data:`PARAM_GROUPS`, then its name's prefix, else ``other``); empty groups left out."""
    where: dict[str, tuple[str, bool]] = {}
    for key, _, common, advanced in PARAM_GROUPS:
        where.update({n: (key, True) for n in common})
        where.update({n: (key, False) for n in advanced})
    groups = {key: {"key": key, "title": title, "common": [], "advanced": []} for key, title, _, _ in PARAM_GROUPS}
    groups["other"] = {"key": "other", "title": "Other parameters", "common": [], "advanced": []}
    for name in model.model_fields:
        key, common = where.get(name) or (next((g for p, g in PARAM_GROUP_PREFIXES if name.startswith(p)), "other"), False)
        groups[key]["common" if common else "advanced"].append(name)
    return [g for g in groups.values() if g["common"] or g["advanced"]]
