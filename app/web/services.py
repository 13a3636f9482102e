"""Operations shared by the routers, ``serve --bootstrap`` and tests: import a survey
directory, add a flight, start a job, prune old files.  Routers stay thin; these functions
hold the store logic.

Concurrency: changes to one survey run under ``Store.survey_lock`` (uploads are kept in
turn, none lost), the snapshot pointer is switched with a conditional update (a writer in
another process that changed it meanwhile gets :class:`SurveyConflict`, HTTP 409), and the
database allows one active job per survey (a unique partial index), so two submissions can
never both start.
"""

from __future__ import annotations

import csv
import functools
import io
import json
import os
import re
import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app.config import MAX_NAME_LENGTH, check_name
from app.io.errors import InputError
from app.io.survey import LINES_COLUMNS

from .db import ACTIVE_STATES, Flight, Job, Line, Result, Survey, utcnow
from .jobs import JobManager
from .store import DEM_NAME, SAFE_NAME, Store, link_tree, relativize, release_memory, survey_qc


class SurveyConflict(Exception):
    """The survey changed meanwhile (another writer); nothing was stored."""


class StorageBudgetExceeded(Exception):
    """The survey would use more disk than its budget; nothing was stored."""


def refresh_survey(db: Session, s: Survey) -> None:
    """Reload the survey under its lock; :class:`SurveyConflict` when it was deleted meanwhile."""
    from sqlalchemy.exc import InvalidRequestError
    try:
        db.refresh(s)
    except InvalidRequestError:
        db.rollback()
        raise SurveyConflict(f"survey {s.id} was deleted meanwhile") from None


def validate(reader: Callable, root: Path):
    """``reader(root)`` with file names in errors relative to the survey directory, and at most
    ``MAX_SURVEY_LINES`` survey lines (InputError naming lines.csv): every line becomes QC, a map
    track and a database row, rebuilt at every change of the survey."""
    lines_csv = Path(root) / "lines.csv"
    if lines_csv.is_file():   # counted before the reader checks every line's window
        with lines_csv.open("rb") as fh:
            _too_many_lines(sum(1 for row in fh if row.strip()) - 1)
    try:
        survey = reader(root)
    except InputError as e:
        err = relativize(e, root)
        if err is e:
            raise
        raise err from e
    _too_many_lines(len(getattr(survey, "lines", ())))
    return survey


#: Most reader warnings returned with an upload (each cut to ``MAX_WARNING_CHARS``): a survey of
#: thousands of lines may give one per line.
MAX_UPLOAD_WARNINGS = 100
MAX_WARNING_CHARS = 2000


def reader_notes(survey, root: Path) -> list[str]:
    """The survey reader's warnings (``Survey.notes``: e.g. a flight no line uses left out because its
    files cannot be read) for the client: file names relative to the survey directory (the staging
    path taken out), at most ``MAX_UPLOAD_WARNINGS`` of at most ``MAX_WARNING_CHARS`` characters, a
    last one saying how many more there were."""
    notes = [str(n) for n in (getattr(survey, "notes", None) or [])]
    prefixes = sorted({str(Path(root)) + os.sep, str(Path(root).resolve()) + os.sep}, key=len, reverse=True)
    out = []
    for n in notes[:MAX_UPLOAD_WARNINGS]:
        for pre in prefixes:
            n = n.replace(pre, "")
        out.append(n if len(n) <= MAX_WARNING_CHARS else n[:MAX_WARNING_CHARS] + f"… ({len(n):,} characters)")
    if len(notes) > MAX_UPLOAD_WARNINGS:
        out.append(f"… and {len(notes) - MAX_UPLOAD_WARNINGS:,} more warnings (the report of a processing run "
                   "lists them all)")
    return out


def _too_many_lines(n: int) -> None:
    if n > MAX_SURVEY_LINES:
        raise InputError("lines.csv", None, None, f"the survey has {n:,} lines; at most {MAX_SURVEY_LINES:,} "
                                                  "allowed (one row per line flown)")


def replace_metadata(db: Session, s: Survey, survey) -> None:
    flights, lines = survey_qc(survey)
    s.flights.clear()
    s.lines.clear()
    db.flush()
    for name, qc in flights.items():
        s.flights.append(Flight(name=name, qc=qc))
    for ln in lines:
        s.lines.append(Line(line=ln["line"], flight=ln["flight"], kind=ln["kind"], t_start=ln["t_start"],
                            t_end=ln["t_end"], qc={**ln["qc"], "track": ln["track"]}, track=ln.get("map_track") or {}))
    crs = getattr(getattr(getattr(survey, "config", None), "survey", None), "crs", None)
    if crs:
        s.crs = crs
    elif s.lines and s.lines[0].track:
        s.crs = s.lines[0].track.get("crs")


def check_budget(store: Store, survey_id: int | None, staged: Path, budget_bytes: int | None) -> None:
    """The survey's files plus the staged snapshot must fit in the survey's storage budget."""
    if not budget_bytes:
        return
    dirs = [staged] + ([store.survey_dir(survey_id)] if survey_id is not None else [])
    used = store.usage_bytes(dirs)
    if used > budget_bytes:
        raise StorageBudgetExceeded(f"the survey would use {used / 2**20:.1f} MB of disk, more than its storage "
                                    f"budget of {budget_bytes / 2**20:.0f} MB (AEROGRAV_SURVEY_STORAGE_MB)")


@contextmanager
def room_for(store: Store, survey_id: int | None, staged: Path, budget_bytes: int | None,
             store_limit_bytes: int | None) -> Iterator[None]:
    """The staged snapshot fits in the survey's storage budget (:class:`StorageBudgetExceeded`)
    and in the store's limit (:class:`~app.web.store.StoreFull`); its new bytes are reserved in the
    store while the block installs it."""
    check_budget(store, survey_id, staged, budget_bytes)
    with store.reserve(staged, store_limit_bytes):
        yield


def install_snapshot(db: Session, store: Store, s: Survey, staged_root: Path, survey,
                     expect_input_dir: str | None = None, check_expected: bool = False) -> None:
    """Rename the validated staging dir into place and switch the pointer in one commit.

    With ``check_expected`` the pointer is switched only if it still is ``expect_input_dir``
    (the snapshot the new one was built from); otherwise :class:`SurveyConflict`."""
    final = store.new_input_dir(s.id)
    store.commit_dir(staged_root, final)
    try:
        if check_expected:
            cond = (Survey.input_dir.is_(None) if expect_input_dir is None
                    else Survey.input_dir == expect_input_dir)
            r = db.execute(update(Survey).where(Survey.id == s.id, cond).values(input_dir=str(final)))
            if r.rowcount != 1:
                raise SurveyConflict(f"survey {s.id} was changed by another request meanwhile; "
                                     "nothing was stored, send it again")
        s.input_dir = str(final)
        replace_metadata(db, s, survey)
        db.commit()
    except Exception:
        db.rollback()
        shutil.rmtree(final, ignore_errors=True)
        raise


def clean_name(name: str, fallback: str = "survey") -> str:
    """A usable survey name from a file name: control characters and separators dropped, cut."""
    name = re.sub(r"[\x00-\x1f\x7f-\x9f\u2028\u2029/\\]", "", name or "").strip()[:MAX_NAME_LENGTH]
    try:
        return check_name(name)
    except ValueError:
        return fallback


def survey_name(survey, fallback: str) -> str:
    name = getattr(getattr(getattr(survey, "config", None), "survey", None), "name", None)
    return name if name and name != "survey" else clean_name(fallback)


def survey_extent_m(survey) -> tuple[str, tuple[float, float, float, float]]:
    """The survey's projected CRS (``survey.crs`` or the UTM zone of its data, as the pipeline
    chooses it) and the extent of its lines there, ``(west, east, south, north)`` in metres."""
    from app.core.geodesy import project_km, utm_crs_for

    flights = survey.flights
    crs = getattr(getattr(getattr(survey, "config", None), "survey", None), "crs", None)
    if not crs:
        lon = np.concatenate([np.asarray(f.gnss["lon"], float)[:: max(1, len(f.gnss) // 1000)] for f in flights.values()])
        lat = np.concatenate([np.asarray(f.gnss["lat"], float)[:: max(1, len(f.gnss) // 1000)] for f in flights.values()])
        crs = utm_crs_for(lon, lat)
    es, ns = [], []
    for row in survey.lines.itertuples(index=False):
        fl = flights.get(row.flight)
        if fl is None:
            continue
        g = fl.gnss
        m = ((g["time"] >= row.t_start) & (g["time"] <= row.t_end)).to_numpy()
        if m.any():
            e, n = project_km(np.asarray(g["lon"], float)[m], np.asarray(g["lat"], float)[m], crs)
            es += [float(np.nanmin(e)), float(np.nanmax(e))]
            ns += [float(np.nanmin(n)), float(np.nanmax(n))]
    if not es:
        raise InputError("lines.csv", None, None, "no survey line has GNSS data: the DEM's coverage cannot be checked")
    return crs, (1000.0 * min(es), 1000.0 * max(es), 1000.0 * min(ns), 1000.0 * max(ns))


def check_survey_dem(root: Path, survey) -> dict | None:
    """The survey directory's ``dem.tif``, when there is one, checked as it arrives
    (:func:`app.io.dem.check_dem`: a raster with a CRS and heights in metres whose footprint covers
    the survey lines); InputError naming ``dem.tif`` otherwise.  None without a DEM."""
    from app.io.dem import check_dem

    p = Path(root) / DEM_NAME
    if not p.is_file():
        return None
    crs, bounds = survey_extent_m(survey)
    return check_dem(p, crs, require_bounds_m=bounds, display=DEM_NAME)


def has_dem(s: Survey) -> bool:
    """The survey's current input holds a terrain model (``dem.tif``)."""
    return bool(s.input_dir) and (Path(s.input_dir) / DEM_NAME).is_file()


def import_survey_tree(db: Session, store: Store, reader: Callable, root: Path, fallback_name: str,
                       budget_bytes: int | None = None, store_limit_bytes: int | None = None,
                       notes: list[str] | None = None) -> Survey:
    """Validate the survey directory ``root`` (already staged under the store's tmp; its optional
    ``dem.tif`` too) and store it; the reader's warnings (:func:`reader_notes`) are appended to
    ``notes`` once it is stored."""
    try:
        survey = validate(reader, root)
        said = reader_notes(survey, root)
        check_survey_dem(root, survey)
        with room_for(store, None, root, budget_bytes, store_limit_bytes):
            s = Survey(name=survey_name(survey, fallback_name))
            db.add(s)
            db.flush()
            try:
                install_snapshot(db, store, s, root, survey)
            except Exception:
                db.rollback()
                raise
        if notes is not None:
            notes.extend(said)
        return s
    finally:
        survey = None
        release_memory()


def import_survey_dir(db: Session, store: Store, reader: Callable, src: Path) -> Survey:
    """Copy a survey directory from anywhere into staging, validate, store."""
    staging = store.staging_dir()
    try:
        root = staging / Path(src).name
        shutil.copytree(src, root, ignore=shutil.ignore_patterns("truth", "__pycache__", ".*"))
        return import_survey_tree(db, store, reader, root, Path(src).name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def toml_string(s: str) -> str:
    """A TOML basic string (JSON escapes are valid TOML for non-surrogate text)."""
    return json.dumps(s, ensure_ascii=False)


def flight_from_lines(lines_raw: bytes | None) -> str | None:
    """The flight id an uploaded lines.csv names, when it names exactly one (and it is usable as a
    folder name); None otherwise."""
    if not lines_raw:
        return None
    try:
        df = pd.read_csv(io.BytesIO(lines_raw), dtype=str, keep_default_na=False, usecols=["flight"])
    except Exception:  # no flight column, unreadable: the reader says what is wrong later
        return None
    ids = {v.strip() for v in df["flight"] if v.strip()}
    if len(ids) != 1:
        return None
    name = ids.pop()
    return name if SAFE_NAME.match(name) else None


#: Most rows of an uploaded lines file (checked before it is parsed).
MAX_LINES_ROWS = 100_000
#: Most lines of a survey, whichever way they came (zip, flight uploads one after another, XYZ blocks)
MAX_SURVEY_LINES = MAX_LINES_ROWS
#: Most columns of an uploaded lines file (line, flight, t_start, t_end, kind, track and a few of the
#: user's own): pandas parses and concatenates a frame with 10⁵ columns for minutes.
MAX_LINES_COLUMNS = 100
#: Most bytes of an uploaded lines file (100,000 rows of a few hundred bytes): it is parsed in memory
#: (pandas needs about 6 times its size), so the request body limit alone would allow gigabytes.
MAX_LINES_BYTES = 32 << 20


def check_lines_upload(lines_raw: bytes | None) -> None:
    """The size of an uploaded lines file, checked before anything parses it: at most
    ``MAX_LINES_BYTES`` bytes, ``MAX_LINES_ROWS`` rows and ``MAX_LINES_COLUMNS`` columns in its
    header (InputError naming lines.csv, row 1 for the header).  The caller may pass the first
    ``MAX_LINES_BYTES + 1`` bytes of a larger upload."""
    if not lines_raw:
        return
    if len(lines_raw) > MAX_LINES_BYTES:
        raise InputError("lines.csv", None, None, f"the lines file is larger than the {MAX_LINES_BYTES >> 20} MB "
                                                  "allowed (one row per line flown: a few hundred bytes each)")
    n_rows = lines_raw.count(b"\n") + 1
    if n_rows > MAX_LINES_ROWS + 1:
        raise InputError("lines.csv", None, None,
                         f"{n_rows:,} rows: more than the {MAX_LINES_ROWS:,} survey lines a lines file may "
                         "list (one row per line flown, a few to a few thousand)")
    header = lines_raw.split(b"\n", 1)[0]
    if header.count(b",") + 1 > MAX_LINES_COLUMNS:
        n_cols = len(next(csv.reader([header.decode("utf-8", "replace")]), []))
        if n_cols > MAX_LINES_COLUMNS:
            raise InputError("lines.csv", 1, None, f"the header has {n_cols:,} columns; at most {MAX_LINES_COLUMNS} "
                                                   "allowed (line, flight, t_start, t_end, kind, track, …)")


#: Columns an uploaded lines file must have (lines.csv's, less ``flight``: the upload's flight).
UPLOADED_LINES_COLUMNS = tuple(c for c in LINES_COLUMNS if c != "flight")


def check_uploaded_lines(df: pd.DataFrame) -> None:
    """An uploaded lines file lists at least one line and has the columns of SPEC §4 (InputError
    naming lines.csv, the row and the column): a file of anything else (e.g. garbage bytes,
    read as a header without rows) would add a flight with no lines beside the stored ones."""
    have = {str(c).strip().lower() for c in df.columns}
    for col in UPLOADED_LINES_COLUMNS:
        if col not in have:
            found = ", ".join(repr(str(c)) for c in list(df.columns)[:10]) or "none"
            raise InputError("lines.csv", 1, col, f"required column '{col}' is missing (columns found: {found})")
    if not any(any(str(v).strip() for v in row) for row in df.itertuples(index=False)):
        raise InputError("lines.csv", 2, None, "the uploaded lines file lists no lines (one row per line flown)")


def _unused_flight_name(s: Survey) -> str:
    """``flight<k>`` for the first k from the number of flights + 1 that no flight of the survey
    has: an unnamed upload never replaces a stored flight."""
    taken = {f.name for f in s.flights}
    k = len(s.flights) + 1
    while f"flight{k}" in taken:
        k += 1
    return f"flight{k}"


def add_flight(db: Session, store: Store, reader: Callable, s: Survey, name: str | None, write_files: Callable,
               lines_raw: bytes | None, budget_bytes: int | None = None,
               store_limit_bytes: int | None = None, notes: list[str] | None = None) -> Survey:
    """Build the next snapshot (hard links to the current one + this flight's files), validate it and
    switch to it, under the survey's lock; ``write_files(flight_dir)`` writes gravimeter.csv and gnss.csv.
    Without a name the flight is called as the uploaded lines.csv calls it (when it names one flight),
    else ``flight<k>``.  The reader's warnings on the new snapshot (:func:`reader_notes`: a flight no
    line uses whose files cannot be read is stored but left out, said there) are appended to
    ``notes`` once it is stored."""
    check_lines_upload(lines_raw)
    with store.survey_lock(s.id):
        refresh_survey(db, s)
        base = s.input_dir
        name = name or flight_from_lines(lines_raw) or _unused_flight_name(s)
        staging = store.staging_dir()
        try:
            root = staging / "survey"
            if base and Path(base).is_dir():
                link_tree(Path(base), root)
            else:
                root.mkdir()
                (root / "survey.toml").write_text(f"[survey]\nname = {toml_string(s.name)}\n", encoding="utf-8")
            fdir = root / "flights" / name
            shutil.rmtree(fdir, ignore_errors=True)
            fdir.mkdir(parents=True)
            write_files(fdir)
            if lines_raw is not None:
                try:
                    new = pd.read_csv(io.BytesIO(lines_raw), dtype=str, keep_default_na=False)
                except Exception as e:
                    raise InputError("lines.csv", None, None, f"cannot read the uploaded lines file: {e}") from e
                check_uploaded_lines(new)
                if "flight" not in new.columns:
                    new.insert(1 if len(new.columns) else 0, "flight", name)
                elif len({v.strip() for v in new["flight"] if v.strip()}) <= 1:
                    new["flight"] = name  # the rows of this one flight, under the name it is uploaded as
                else:
                    new["flight"] = new["flight"].replace("", name)
                lp = root / "lines.csv"
                if lp.exists():
                    old = pd.read_csv(lp, dtype=str, keep_default_na=False)
                    old = old[old["flight"] != name] if "flight" in old.columns else old
                    new = pd.concat([old, new], ignore_index=True).fillna("")
                tmp = lp.with_name("lines.csv.new")
                new.to_csv(tmp, index=False)
                os.replace(tmp, lp)  # a new file: the linked one of the current snapshot is untouched
            survey = validate(reader, root)
            said = reader_notes(survey, root)
            prune_survey(db, store, s.id)
            with room_for(store, s.id, root, budget_bytes, store_limit_bytes):
                install_snapshot(db, store, s, root, survey, expect_input_dir=base, check_expected=True)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
            release_memory()
        prune_survey(db, store, s.id)
    if notes is not None:
        notes.extend(said)
    return s


class JobConflict(Exception):
    pass


# ---------------------------------------------------------------- line listings (/qc, /tracks)
#: Lines of a /qc or /tracks page by default: every realistic survey (a few to a few thousand lines)
#: in one page, as before pagination
LINES_PAGE_DEFAULT = 10_000
#: Most lines of one page (a map track is ~200 points: 20,000 tracks are ~80 MB of JSON)
LINES_PAGE_MAX = 20_000


def line_page(db: Session, s: Survey, offset: int, limit: int) -> tuple[list[Line], int]:
    """The survey's lines ``offset`` … ``offset + limit − 1`` in their stored order (by id), read from
    the database page by page (not every line of the survey), and how many lines it has."""
    total = db.scalar(select(func.count()).select_from(Line).where(Line.survey_id == s.id)) or 0
    if limit <= 0 or offset >= total:
        return [], total
    rows = db.scalars(select(Line).where(Line.survey_id == s.id).order_by(Line.id).offset(offset).limit(limit))
    return list(rows), total


# ---------------------------------------------------------------- survey.toml fields (PATCH)
class SettingsRejected(Exception):
    """The survey.toml change is invalid; ``detail`` is a list of ``{loc, msg, type, input}``."""

    def __init__(self, detail: list[dict]):
        super().__init__(detail[0]["msg"] if detail else "invalid settings")
        self.detail = detail


class NoInput(Exception):
    """The survey has no input snapshot (no survey.toml) yet."""


SETTINGS_FIELDS = {"survey": ("name", "crs", "normal_gravity"),
                   "gravimeter": ("model", "tau_s", "scale", "rate_hz", "base_gravity_mgal")}


@functools.lru_cache(maxsize=256)
def _settings_of(toml_path: str, mtime_ns: int) -> dict | None:
    from app.io.survey import read_config
    try:
        cfg = read_config(Path(toml_path))
    except InputError:
        return None
    return {sec: {k: getattr(getattr(cfg, sec), k) for k in keys} for sec, keys in SETTINGS_FIELDS.items()}


def survey_settings(s: Survey) -> dict | None:
    """The editable survey.toml fields of the current input snapshot (snapshots are immutable, so
    the result is cached by path)."""
    if not s.input_dir:
        return None
    p = Path(s.input_dir) / "survey.toml"
    try:
        st = p.stat()
    except OSError:
        return None
    return _settings_of(str(p), st.st_mtime_ns)


def merged_config(current: dict, patch) -> dict:
    """survey.toml data with the PATCH applied (fields given are set; null removes the key)."""
    data = {k: (dict(v) if isinstance(v, dict) else v) for k, v in current.items()}
    for sec in SETTINGS_FIELDS:
        part = getattr(patch, sec)
        if part is None:
            continue
        table = data.setdefault(sec, {})
        if not isinstance(table, dict):
            raise SettingsRejected([{"loc": [sec], "msg": f"[{sec}] of survey.toml is not a table",
                                     "type": "value_error"}])
        for k in part.model_fields_set:
            v = getattr(part, k)
            if v is None:
                if sec == "survey" and k == "name":
                    raise SettingsRejected([{"loc": ["survey", "name"], "msg": "the name cannot be removed",
                                             "type": "value_error", "input": None}])
                table.pop(k, None)
            else:
                table[k] = v
    return data


def validate_config(data: dict) -> None:
    """SurveyConfig validation (a CRS PROJ cannot use included: the survey section's validator,
    :func:`app.core.geodesy.crs_fault`); errors as 422 details naming ``section.key``."""
    from pydantic import ValidationError

    from app.config import SurveyConfig

    from .errors import validation_detail
    try:
        SurveyConfig.model_validate(data)
    except ValidationError as e:
        raise SettingsRejected(validation_detail(e.errors())) from None


def patch_survey(db: Session, store: Store, reader: Callable, s: Survey, patch, budget_bytes: int | None = None,
                 store_limit_bytes: int | None = None) -> Survey:
    """Apply a :class:`~app.web.schemas.SurveyPatch`: a new input snapshot whose survey.toml carries the
    changes (hard links to the current files, survey.toml replaced), validated with the survey reader and
    switched to under the survey's lock like a flight upload.  A survey without data takes a new name
    only (:class:`NoInput` otherwise)."""
    import tomllib

    from app.io.survey_writer import dumps_toml

    given = {sec: getattr(patch, sec).model_fields_set for sec in SETTINGS_FIELDS if getattr(patch, sec) is not None}
    with store.survey_lock(s.id):
        refresh_survey(db, s)
        base = s.input_dir
        if not base or not (Path(base) / "survey.toml").is_file():
            if any(keys - ({"name"} if sec == "survey" else set()) for sec, keys in given.items()):
                raise NoInput("the survey has no data yet: upload a flight (or import a survey) first, then set "
                              "its survey.toml fields")
            if "name" in given.get("survey", set()):
                data = merged_config({"survey": {"name": s.name}}, patch)
                validate_config(data)
                s.name = data["survey"]["name"]
                db.commit()
            return s
        toml_path = Path(base) / "survey.toml"
        try:
            current = tomllib.loads(toml_path.read_text(encoding="utf-8-sig"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:  # pragma: no cover - validated at upload
            raise SettingsRejected([{"loc": ["survey.toml"], "msg": f"the stored survey.toml is unreadable: {e}",
                                     "type": "value_error"}]) from None
        data = merged_config(current, patch)
        validate_config(data)
        if data == current:
            return s
        staging = store.staging_dir()
        try:
            root = staging / "survey"
            link_tree(Path(base), root)
            tmp = root / "survey.toml.new"
            tmp.write_text(dumps_toml(data), encoding="utf-8")
            os.replace(tmp, root / "survey.toml")  # a new file: the linked one of the current snapshot is untouched
            survey = validate(reader, root)
            with room_for(store, s.id, root, budget_bytes, store_limit_bytes):
                s.name = data["survey"].get("name", s.name)
                install_snapshot(db, store, s, root, survey, expect_input_dir=base, check_expected=True)
        except Exception:
            db.rollback()
            raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)
            release_memory()
        prune_survey(db, store, s.id)
    return s


def replace_dem(db: Session, store: Store, reader: Callable, s: Survey, write_dem: Callable[[Path], None] | None,
                budget_bytes: int | None = None, store_limit_bytes: int | None = None) -> Survey:
    """Add, replace (``write_dem(path)`` writes the new file) or remove (``write_dem=None``) the
    survey's terrain model: a new input snapshot (hard links to the current files, ``dem.tif`` a new
    file or gone), the DEM checked against the survey's lines (:func:`check_survey_dem`) and switched
    to under the survey's lock like a flight upload.  :class:`NoInput` for a survey without data."""
    with store.survey_lock(s.id):
        refresh_survey(db, s)
        base = s.input_dir
        if not base or not (Path(base) / "survey.toml").is_file():
            raise NoInput("the survey has no data yet: upload a flight (or import a survey) first, then its DEM")
        if write_dem is None and not (Path(base) / DEM_NAME).exists():
            return s
        staging = store.staging_dir()
        try:
            root = staging / "survey"
            link_tree(Path(base), root)
            (root / DEM_NAME).unlink(missing_ok=True)   # the link only: the current snapshot keeps its file
            if write_dem is not None:
                write_dem(root / DEM_NAME)
            survey = validate(reader, root)
            check_survey_dem(root, survey)
            with room_for(store, s.id, root, budget_bytes, store_limit_bytes):
                install_snapshot(db, store, s, root, survey, expect_input_dir=base, check_expected=True)
        except Exception:
            db.rollback()
            raise
        finally:
            survey = None
            shutil.rmtree(staging, ignore_errors=True)
            release_memory()
        prune_survey(db, store, s.id)
    return s


def result_outdated(db: Session, s: Survey) -> bool:
    """The current result was computed from another input snapshot than the current one."""
    if s.current_result_id is None or not s.input_dir:
        return False
    r = db.get(Result, s.current_result_id)
    j = db.get(Job, r.job_id) if r is not None else None
    return j is not None and j.input_dir != s.input_dir


# ---------------------------------------------------------------- delete
def delete_survey(db: Session, store: Store, s: Survey) -> list[int]:
    """Remove a survey: its rows (flights, lines, jobs, results) and then its files.  Refused
    (:class:`JobConflict`) while a job is queued or running.  Returns the removed result ids (for
    the caller to drop cached views)."""
    from sqlalchemy import delete

    with store.survey_lock(s.id):
        refresh_survey(db, s)
        active = db.scalars(select(Job).where(Job.survey_id == s.id, Job.status.in_(ACTIVE_STATES))).first()
        if active is not None:
            raise JobConflict(f"job {active.id} is {active.status} on this survey: cancel it or wait, then delete")
        sid = s.id
        result_ids = list(db.scalars(select(Result.id).where(Result.survey_id == sid)))
        db.execute(delete(Result).where(Result.survey_id == sid))
        db.execute(delete(Job).where(Job.survey_id == sid))
        db.delete(s)
        db.commit()
        # the rows are gone: the files follow (moved aside in one rename first, so a half-removed
        # folder is never under surveys/; the bytes freed are taken off the store's count)
        d = store.survey_dir(sid)
        if d.exists():
            store.remove_tree(d)
    return result_ids


def check_grid_size(s: Survey, params: dict[str, Any]) -> None:
    """Before a job starts: the overrides merged over the survey's ``survey.toml`` are valid, and the
    grid over the stored line tracks stays within ``MAX_GRID_CELLS`` (InputError, HTTP 422)."""
    from app.config import check_grid_cells
    from app.io.survey import read_config

    if not s.input_dir or not (Path(s.input_dir) / "survey.toml").is_file():
        return
    cfg = read_config(Path(s.input_dir) / "survey.toml", params)
    e = [x for ln in s.lines for x in (ln.track or {}).get("easting_km", []) if x is not None]
    n = [x for ln in s.lines for x in (ln.track or {}).get("northing_km", []) if x is not None]
    if e and n:
        try:
            check_grid_cells(max(e) - min(e), max(n) - min(n), cfg.processing.grid_spacing_km)
        except ValueError as exc:
            raise InputError(None, None, "processing.grid_spacing_km", str(exc)) from None


def start_job(db: Session, store: Store, jobs: JobManager, s: Survey, kind: str, params: dict[str, Any]) -> Job:
    with store.survey_lock(s.id):  # the input snapshot cannot be pruned between reading and using it
        refresh_survey(db, s)
        if not s.input_dir:
            raise JobConflict("the survey has no data yet: import a survey or upload a flight first")
        if kind == "filter":
            cur = db.get(Result, s.current_result_id) if s.current_result_id is not None else None
            if cur is None or not (Path(cur.dir) / "identified").is_dir():
                raise JobConflict("a filter job starts from a stored identification: run an identify or process "
                                  "job first")
        active = db.scalars(select(Job).where(Job.survey_id == s.id, Job.status.in_(ACTIVE_STATES))).first()
        if active is not None:
            raise JobConflict(f"job {active.id} is still {active.status} on this survey; cancel it or wait")
        job = Job(survey_id=s.id, kind=kind, params=params, status="queued", progress=0.0, stage="queued",
                  em_iterations=[], backend=jobs.backend, input_dir=s.input_dir)
        db.add(job)
        try:
            db.flush()  # the unique partial index allows one active job per survey
        except IntegrityError:
            db.rollback()
            raise JobConflict("another job was started on this survey meanwhile; cancel it or wait") from None
        job.out_dir = str(store.job_out_dir(s.id, job.id))
        db.commit()
    try:
        jobs.submit(job)
    except Exception as e:  # e.g. the Dask scheduler is unreachable
        job.status, job.error, job.finished_at = "failed", f"could not start the job: {e}", utcnow()
        db.commit()
    db.refresh(job)
    return job


def keep_set(db: Session, survey_id: int) -> set[str]:
    """Paths of a survey that must stay: the current input, the inputs and outputs of active jobs,
    and the current and previous results with the inputs they were computed from."""
    s = db.get(Survey, survey_id)
    if s is None:
        return set()
    keep = {s.input_dir} if s.input_dir else set()
    for j in db.scalars(select(Job).where(Job.survey_id == survey_id, Job.status.in_(ACTIVE_STATES))):
        keep |= {j.input_dir, j.out_dir}
    results = list(db.scalars(select(Result).where(Result.survey_id == survey_id).order_by(Result.id.desc())))
    current = [r for r in results if r.id == s.current_result_id]
    previous = [r for r in results if s.current_result_id is None or r.id < s.current_result_id][:1]
    for r in current + previous:
        keep.add(r.dir)
        j = db.get(Job, r.job_id)
        if j is not None:
            keep.add(j.input_dir)
    return {k for k in keep if k}


def prune_survey(db: Session, store: Store, survey_id: int) -> list[Path]:
    """Remove the survey's input snapshots and result folders that are no longer needed."""
    with store.survey_lock(survey_id):
        return store.prune(survey_id, keep_set(db, survey_id))
