"""File side of the store: survey input snapshots, atomic imports, QC, cached results.

Layout under the data directory::

    surveys/<survey_id>/input/<uuid>/          an immutable, validated input snapshot
    surveys/<survey_id>/results/job-<job_id>/  the outputs of one job (SPEC §5)
    tmp/                                       staging (same filesystem: renames are atomic)

New files are staged in ``tmp/``, validated with ``read_survey`` and only then renamed
into place; the database pointer (``Survey.input_dir``) is switched afterwards in one
transaction.  A rejected upload leaves nothing behind.

Snapshots are immutable, so a flight upload builds the next snapshot from hard links to the
current one (no copy).  Changes to one survey's files are serialized by :meth:`Store.survey_lock`;
:meth:`Store.prune` removes the snapshots and result folders no longer needed (everything but the
current input, the inputs of active jobs, and the current and previous results with their
inputs); :meth:`Store.clean_start` removes what a stopped server left half-written.

The whole store is bounded too (``AEROGRAV_MAX_STORE_MB``): :meth:`Store.reserve` admits a staged
snapshot only when the bytes it adds fit, :meth:`Store.check_room` refuses new surveys, uploads and
jobs while the store is at its limit (:class:`StoreFull`, HTTP 507).  The count is the data directory
walked (each file once) at most every ``USAGE_TTL_S`` seconds, kept current in between: admitted
snapshots are added, removed folders (:meth:`Store.remove_tree`) subtracted, and a finished job
makes the next check walk again (its results).
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import stat
import struct
import threading
import time
import uuid
import zipfile
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from app.config import check_name
from app.io.errors import InputError
from app.jsonsafe import finite_float, float_list

SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,99}\Z")  # \Z: "$" would accept a final newline
#: zip archives: most entries, deepest path, longest path element
MAX_ZIP_ENTRIES = 10_000
MAX_ZIP_DEPTH = 8
MAX_ZIP_NAME = 200
#: most bytes of a zip's central directory (its table of contents: 46 bytes and the name per entry)
MAX_ZIP_DIRECTORY = 16 << 20
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)
#: seconds the store's measured size is trusted before the data directory is walked again
USAGE_TTL_S = 30.0
#: the temporary file of an atomic write (``app.io.export.atomic_path``: ``.<stem>.<12 hex>.tmp<suffix>``)
ATOMIC_TMP = re.compile(r"^\..+\.[0-9a-f]{12}\.tmp(\.[^.]+)?\Z")


def size_text(n: int) -> str:
    """A byte count for people: kB, MB or GB."""
    if n >= 2**30:
        return f"{n / 2**30:.2f} GB"
    return f"{n / 2**20:.1f} MB" if n >= 2**20 else f"{n / 1024:.0f} kB"


class StoreFull(Exception):
    """The store is at its limit (``AEROGRAV_MAX_STORE_MB``), or would go above it with what a
    request adds; nothing was stored."""

    def __init__(self, used: int, adding: int, limit: int):
        self.used, self.adding, self.limit = used, adding, limit
        what = f" and this upload adds {size_text(adding)}" if adding else ""
        super().__init__(f"the server's store is full: it holds {size_text(used)} of its {size_text(limit)} limit{what} "
                         "(AEROGRAV_MAX_STORE_MB); nothing was stored — delete surveys no longer needed, or "
                         "ask the administrator to raise the limit")


def file_stats(dirs: Iterable[Path]) -> Iterator[os.stat_result]:
    """``lstat`` of every file under ``dirs`` (files that vanish while walking are skipped)."""
    for d in dirs:
        for dirpath, _dirs, files in os.walk(d):
            for f in files:
                try:
                    yield os.lstat(os.path.join(dirpath, f))
                except OSError:
                    continue


def own_bytes(path: Path) -> int:
    """Bytes that removing ``path`` frees: the files under it whose every hard link is under it
    too (a snapshot's files linked from another snapshot stay on disk)."""
    seen: dict[tuple[int, int], list[int]] = {}
    for st in file_stats([path]):
        c = seen.setdefault((st.st_dev, st.st_ino), [0, st.st_nlink, st.st_size])
        c[0] += 1
    return sum(size for n, nlink, size in seen.values() if n >= nlink)


class Store:
    def __init__(self, data_dir: Path):
        self.root = Path(data_dir).resolve()
        self.tmp = self.root / "tmp"
        self.tmp.mkdir(parents=True, exist_ok=True)
        (self.root / "surveys").mkdir(parents=True, exist_ok=True)
        self._locks: dict[int, threading.RLock] = {}
        self._locks_guard = threading.Lock()
        self._usage_lock = threading.Lock()
        self._usage: int | None = None     # bytes of the data directory (staging left out) at the last walk, kept current
        self._usage_t = 0.0                 # when it was walked (time.monotonic)
        self._pending = 0                   # bytes admitted by reserve() whose snapshot is not installed yet

    def survey_lock(self, survey_id: int) -> threading.RLock:
        """The lock serializing changes to one survey's input snapshot, jobs and files (in this
        process; the database's conditional updates catch writers from other processes)."""
        with self._locks_guard:
            return self._locks.setdefault(int(survey_id), threading.RLock())

    def staging_dir(self) -> Path:
        d = self.tmp / uuid.uuid4().hex
        d.mkdir(parents=True)
        return d

    def survey_dir(self, survey_id: int) -> Path:
        return self.root / "surveys" / str(survey_id)

    def new_input_dir(self, survey_id: int) -> Path:
        d = self.survey_dir(survey_id) / "input"
        d.mkdir(parents=True, exist_ok=True)
        return d / uuid.uuid4().hex

    def job_out_dir(self, survey_id: int, job_id: int) -> Path:
        d = self.survey_dir(survey_id) / "results"
        d.mkdir(parents=True, exist_ok=True)
        return d / f"job-{job_id}"

    def commit_dir(self, staged: Path, final: Path) -> Path:
        final.parent.mkdir(parents=True, exist_ok=True)
        os.replace(staged, final)
        return final

    # -- storage -------------------------------------------------------------
    def usage_bytes(self, dirs: Iterable[Path]) -> int:
        """Bytes on disk under ``dirs``, each file counted once (snapshots share hard links)."""
        seen: set[tuple[int, int]] = set()
        total = 0
        for st in file_stats(dirs):
            key = (st.st_dev, st.st_ino)
            if key not in seen:
                seen.add(key)
                total += st.st_size
        return total

    def survey_usage_bytes(self, survey_id: int) -> int:
        return self.usage_bytes([self.survey_dir(survey_id)])

    def _walk_usage(self) -> int:
        """Bytes of the data directory, each file once: surveys, results, the SQLite file — not the
        staging area (a request's staged files are counted by its :meth:`reserve`)."""
        dirs, total = [], 0
        for p in self.root.iterdir():
            if p.name == self.tmp.name:
                continue
            try:
                st = p.lstat()
            except OSError:
                continue
            if stat.S_ISDIR(st.st_mode):
                dirs.append(p)
            else:
                total += st.st_size
        return total + self.usage_bytes(dirs)

    def _usage_now(self) -> int:
        """The store's bytes, admitted snapshots included (call under ``_usage_lock``)."""
        if self._usage is None or time.monotonic() - self._usage_t > USAGE_TTL_S:
            self._usage = self._walk_usage()
            self._usage_t = time.monotonic()
        return self._usage + self._pending

    def store_usage_bytes(self) -> int:
        """Bytes the store holds (see the module's docstring for how it is kept current)."""
        with self._usage_lock:
            return self._usage_now()

    def invalidate_usage(self) -> None:
        """The next count walks the data directory (e.g. a job wrote its results)."""
        with self._usage_lock:
            self._usage = None

    def check_room(self, limit: int | None) -> None:
        """:class:`StoreFull` when the store already holds ``limit`` bytes or more (no limit: None)."""
        if not limit:
            return
        with self._usage_lock:
            used = self._usage_now()
        if used >= limit:
            raise StoreFull(used, 0, limit)

    @contextmanager
    def reserve(self, staged: Path, limit: int | None) -> Iterator[int]:
        """Room in the store for the files written fresh under ``staged`` (its hard links to stored
        files add nothing): :class:`StoreFull` when the store would go above ``limit`` bytes.  The
        check and the reservation are one step, so concurrent requests cannot all pass on the same
        free space.  The bytes count as stored when the block ends normally (the snapshot was
        installed), and are released when it raises."""
        if not limit:
            yield 0
            return
        n = own_bytes(staged)
        with self._usage_lock:
            used = self._usage_now()
            if used + n > limit:
                raise StoreFull(used, n, limit)
            self._pending += n
        ok = False
        try:
            yield n
            ok = True
        finally:
            with self._usage_lock:
                self._pending -= n
                if ok and self._usage is not None:
                    self._usage += n

    def remove_tree(self, path: Path) -> None:
        """Remove the folder ``path`` (a survey, a snapshot, a result): moved into the staging area in
        one rename — nothing half-removed stays in place — and the bytes it frees taken off the
        store's count, then deleted."""
        freed = own_bytes(path)
        trash = self.staging_dir() / "removed"
        try:
            with self._usage_lock:
                os.replace(path, trash)
                if self._usage is not None:
                    self._usage = max(0, self._usage - freed)
        finally:
            shutil.rmtree(trash.parent, ignore_errors=True)

    def prune(self, survey_id: int, keep: set[str]) -> list[Path]:
        """Remove the input snapshots and result folders of a survey whose paths are not in ``keep``
        (``.partial`` folders of running jobs are left alone); returns what was removed."""
        keep = {str(Path(k).resolve()) for k in keep if k}
        removed = []
        for sub in ("input", "results"):
            d = self.survey_dir(survey_id) / sub
            if not d.is_dir():
                continue
            for p in d.iterdir():
                if p.name.endswith(".partial") or str(p.resolve()) in keep:
                    continue
                try:
                    self.remove_tree(p)
                except OSError:   # gone meanwhile, or not removable now: the next prune tries again
                    continue
                removed.append(p)
        return removed

    def clean_start(self, active_out_dirs: set[str], tmp_age_s: float = 3600.0) -> list[Path]:
        """At start-up: ``.partial`` result folders of jobs not active, and staging folders and the
        temporary files of atomic writes in result folders (an export written on demand when the
        server stopped) older than ``tmp_age_s`` (another server may share the data directory),
        are removed."""
        removed = []
        active = {str(Path(d).resolve()) + ".partial" for d in active_out_dirs if d}
        for p in (self.root / "surveys").glob("*/results/*.partial"):
            if str(p.resolve()) not in active:
                shutil.rmtree(p, ignore_errors=True)
                removed.append(p)
        now = time.time()
        leftovers = [p for p in (self.root / "surveys").glob("*/results/*/.*.tmp*") if ATOMIC_TMP.match(p.name)]
        for p in leftovers + list(self.tmp.iterdir()):
            try:
                old = now - p.stat().st_mtime > tmp_age_s
            except OSError:
                continue
            if old:
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
                removed.append(p)
        return removed


def release_memory() -> None:
    """Give the memory freed after a large request (a survey read into DataFrames) back to the
    system: glibc keeps freed blocks in per-thread arenas, so a server's RSS would otherwise
    stay at the largest survey ever validated times the number of worker threads."""
    global _TRIM
    if _TRIM is None:
        try:
            import ctypes
            _TRIM = ctypes.CDLL("libc.so.6").malloc_trim
        except (OSError, AttributeError):  # not glibc
            _TRIM = False
    if _TRIM:
        _TRIM(0)


_TRIM = None


def link_tree(src: Path, dst: Path) -> None:
    """``dst`` as a tree of hard links to the files of ``src`` (copies where linking fails).
    Files in ``dst`` must be replaced (``os.replace`` / unlink first), never rewritten in place."""
    def link(a, b):
        try:
            os.link(a, b)
        except OSError:
            shutil.copy2(a, b)
    shutil.copytree(src, dst, copy_function=link)


def relativize(err: InputError, root: Path) -> InputError:
    """Report file names relative to the survey directory, not the staging path."""
    if err.file:
        try:
            rel = Path(err.file).resolve().relative_to(Path(root).resolve())
            err = InputError(rel.as_posix(), err.row, err.column, err.message)
        except ValueError:
            pass
    return err


def _clip(name: str, n: int = 80) -> str:
    return name if len(name) <= n else f"{name[:n]}… ({len(name)} characters)"


def _entry_parts(name: str) -> list[str]:
    """The path elements of a zip entry name, or InputError when it is unsafe or unreasonable."""
    if len(name) > MAX_ZIP_DEPTH * (MAX_ZIP_NAME + 1):
        raise InputError(_clip(name), None, None, f"zip entry name of {len(name)} characters is too long")
    n = name.replace("\\", "/")
    parts = [p for p in n.split("/") if p not in ("", ".")]
    if n.startswith("/") or re.match(r"^[A-Za-z]:", n) or ".." in parts:
        raise InputError(_clip(name), None, None, "unsafe path in the zip archive")
    if len(parts) > MAX_ZIP_DEPTH:
        raise InputError(_clip(name), None, None,
                         f"zip entry nested {len(parts)} folders deep; at most {MAX_ZIP_DEPTH} allowed")
    for p in parts:
        if len(p) > MAX_ZIP_NAME or len(p.encode("utf-8", "surrogateescape")) > 255:
            raise InputError(_clip(name), None, None,
                             f"a name in this zip entry's path is longer than {MAX_ZIP_NAME} characters")
    return parts


#: the optional terrain model of a survey directory (the pipeline's terrain correction reads it)
DEM_NAME = "dem.tif"


def _survey_member(rel: list[str]) -> bool:
    """The files of a survey directory the reader and the pipeline use (everything else in a zip is
    not stored)."""
    return rel in (["survey.toml"], ["lines.csv"], [DEM_NAME]) or (len(rel) == 3 and rel[0] == "flights")


def _check_zip_directory(fileobj, max_entries: int) -> None:
    """Bound the archive's table of contents before :class:`zipfile.ZipFile` reads it: ZipFile loads
    the whole central directory and builds an object per entry (a 40 MB zip of 500,000 empty entries
    cost 270 MB and 5 s), so its size, the count the end record declares and the entries actually
    there (walked header by header: the declared count may lie) are checked first.  Damage is left
    to ZipFile to report."""
    try:
        endrec = zipfile._EndRecData(fileobj)
    except OSError:
        endrec = None
    if not endrec:
        return
    size_cd, declared = endrec[zipfile._ECD_SIZE], endrec[zipfile._ECD_ENTRIES_TOTAL]
    if size_cd > MAX_ZIP_DIRECTORY:
        raise InputError("upload", None, None, f"the archive's table of contents is {size_cd / 2**20:.0f} MB, more "
                         f"than the {MAX_ZIP_DIRECTORY / 2**20:.0f} MB allowed (at most {max_entries:,} entries)")
    if declared > max_entries:
        raise InputError("upload", None, None, f"the archive has {declared:,} entries; at most "
                                               f"{max_entries:,} allowed")
    start = endrec[zipfile._ECD_LOCATION] - size_cd
    if endrec[zipfile._ECD_SIGNATURE] == zipfile.stringEndArchive64:
        start -= zipfile.sizeEndCentDir64 + zipfile.sizeEndCentDir64Locator
    if start < 0:
        return
    fileobj.seek(start)
    cd = fileobj.read(size_cd)
    fileobj.seek(0)
    i = n = 0
    while i + 46 <= len(cd) and cd[i:i + 4] == b"PK\x01\x02":
        name_len, extra_len, comment_len = struct.unpack_from("<HHH", cd, i + 28)
        i += 46 + name_len + extra_len + comment_len
        n += 1
        if n > max_entries:
            raise InputError("upload", None, None, f"the archive has more than {max_entries:,} entries (its "
                                                   f"end record says {declared:,}); at most {max_entries:,} allowed")


def extract_survey_zip(fileobj, dest: Path, max_bytes: int | None = None,
                       max_entries: int = MAX_ZIP_ENTRIES) -> Path:
    """Extract the survey files of a zip into ``dest``; return the survey root (``dest`` or one
    folder below it).

    Streamed: every entry is decompressed in 1 MB chunks and the bytes actually produced are
    counted against ``max_bytes`` (the declared sizes are checked first, but not trusted), so
    memory stays constant whatever the archive claims.  Only ``survey.toml``, ``lines.csv``, the
    optional ``dem.tif`` and the files of ``flights/<flight>/`` are extracted.  Unsafe, over-long or over-deep names,
    encrypted, damaged or size-lying entries and more than ``max_entries`` entries are
    InputErrors."""
    _check_zip_directory(fileobj, max_entries)
    try:
        zf = zipfile.ZipFile(fileobj)
        infos = zf.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError, NotImplementedError, RuntimeError,
            OSError) as exc:
        if isinstance(exc, OSError) and exc.errno in DISK_FULL:
            raise
        raise InputError("upload", None, None, f"not a zip archive (or a damaged one): {exc}") from None
    with zf:
        if len(infos) > max_entries:
            raise InputError("upload", None, None, f"the archive has {len(infos):,} entries; at most "
                                                   f"{max_entries:,} allowed")
        total = sum(i.file_size for i in infos)
        if max_bytes is not None and total > max_bytes:
            raise InputError("upload", None, None, f"the archive expands to {total / 2**20:.0f} MB, more than the "
                             f"{max_bytes / 2**20:.0f} MB allowed (AEROGRAV_MAX_UNCOMPRESSED_MB)")
        files: list[tuple[zipfile.ZipInfo, list[str]]] = []
        for info in infos:
            parts = _entry_parts(info.filename)
            if (info.is_dir() or not parts or parts[0] == "__MACOSX" or parts[-1] == ".DS_Store"
                    or parts[-1].startswith("._")):
                continue
            files.append((info, parts))
        tops = [p[:-1] for _, p in files if p[-1] == "survey.toml" and len(p) <= 2]
        if [] in tops:
            root_parts: list[str] = []
        elif len(tops) == 1:
            root_parts = tops[0]
        else:
            raise InputError("survey.toml", None, None,
                             "the zip must contain a survey directory: survey.toml at the top level or in one folder")
        written = 0
        for info, parts in files:
            rel = parts[len(root_parts):]
            if parts[:len(root_parts)] != root_parts or not _survey_member(rel):
                continue
            for p, what in zip(rel[1:], ("flight name", "file name")):   # the file's own name too
                try:
                    check_name(p, what)
                except ValueError as exc:
                    raise InputError(_clip(info.filename), None, None, str(exc)) from None
            if info.flag_bits & 0x1:
                raise InputError(_clip(info.filename), None, None, "the zip entry is encrypted (password protected)")
            target = dest.joinpath(*parts)
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                with zf.open(info) as src, open(target, "wb") as out:
                    size = 0
                    while True:
                        chunk = src.read(1 << 20)
                        if not chunk:
                            break
                        size += len(chunk)
                        written += len(chunk)
                        if max_bytes is not None and written > max_bytes:
                            raise InputError("upload", None, None,
                                             f"the archive expands to more than the {max_bytes / 2**20:.0f} MB "
                                             "allowed (AEROGRAV_MAX_UNCOMPRESSED_MB)")
                        out.write(chunk)
                if size != info.file_size:
                    raise zipfile.BadZipFile(f"{size} bytes where the header says {info.file_size}")
            except InputError:
                raise
            except (zipfile.BadZipFile, zlib.error, EOFError, RuntimeError, NotImplementedError, ValueError) as exc:
                raise InputError(_clip(info.filename), None, None, f"damaged zip entry: {exc}") from None
            except OSError as exc:
                if exc.errno in DISK_FULL:
                    raise
                raise InputError(_clip(info.filename), None, None, f"cannot extract: {exc.strerror or exc}") from None
    return dest.joinpath(*root_parts)


#: the QC table's figures of a flight or line, under the names the web's QC has always used
_QC_FIELDS = {"gravimeter_samples": "n_gravimeter", "gnss_samples": "n_gnss",
              "gravimeter_rate_hz": "gravimeter_rate_hz", "gnss_rate_hz": "gnss_rate_hz",
              "gravimeter_max_gap_s": "gravimeter_max_gap_s", "gnss_max_gap_s": "gnss_max_gap_s",
              "duration_s": "duration_s", "length_km": "length_km"}


def _qc_figures(row) -> dict[str, Any]:
    q: dict[str, Any] = {k: finite_float(getattr(row, c)) for k, c in _QC_FIELDS.items()}
    q["gravimeter_samples"] = int(row.n_gravimeter)
    q["gnss_samples"] = int(row.n_gnss)
    return q


def _line_tracks(lon: np.ndarray, lat: np.ndarray, picks: list[np.ndarray], crs: str) -> list[dict]:
    """The map tracks of a flight's lines (each ``picks[i]``: indices of its decimated GNSS
    positions) in the survey CRS (km), projected in one call."""
    from app.core.geodesy import project_km

    idx = np.concatenate(picks) if picks else np.zeros(0, int)
    try:
        e, n = project_km(lon[idx], lat[idx], crs)
    except Exception:  # pragma: no cover - bad CRS string: no map, QC still shown
        return [{} for _ in picks]
    cuts = np.cumsum([len(p) for p in picks])[:-1]
    return [{"easting_km": float_list(ei, 3), "northing_km": float_list(ni, 3), "crs": crs}
            for ei, ni in zip(np.split(np.asarray(e), cuts), np.split(np.asarray(n), cuts))]


def _line_samples(t: np.ndarray, sorted_t: bool, t_start: float, t_end: float) -> np.ndarray:
    """Indices of the samples with ``t_start <= t <= t_end`` (by bisection when ``t`` is sorted:
    a mask over the whole flight for every line made the QC of many lines quadratic)."""
    if sorted_t:
        return np.arange(np.searchsorted(t, t_start, "left"), np.searchsorted(t, t_end, "right"))
    return np.flatnonzero((t >= t_start) & (t <= t_end))


def survey_qc(survey, track_points: int = 150) -> tuple[dict[str, dict], list[dict]]:
    """Per-flight and per-line QC from a validated ``Survey``, plus each line's decimated track in
    the survey CRS (km) for the line map.

    The figures (sample counts, rates from the median interval, largest gaps, durations,
    ellipsoidal path lengths) are those of ``aerograv inspect``
    (:func:`app.pipeline.inspect.inspect_table`, without the time offsets: seconds per flight
    at every upload, and the processing report gives them); a line adds its mean speed
    (``length / duration``) and mean GNSS height."""
    from app.core.geodesy import utm_crs_for
    from app.pipeline.inspect import inspect_table

    crs = getattr(getattr(getattr(survey, "config", None), "survey", None), "crs", None)
    if not crs:
        g0 = next(iter(survey.flights.values())).gnss if survey.flights else None
        crs = utm_crs_for(g0["lon"], g0["lat"]) if g0 is not None and len(g0) else "EPSG:4326"
    table = inspect_table(survey, time_offsets=False)
    flights: dict[str, dict] = {}
    for row in table[table["level"] == "flight"].itertuples(index=False):
        flights[str(row.flight)] = {**_qc_figures(row), "t_start": finite_float(row.t_start),
                                    "t_end": finite_float(row.t_end)}
    lines: list[dict] = []
    arrays: dict[str, tuple] = {}          # per flight: time, lon, lat, h, time sorted
    picks: dict[str, list[tuple[int, np.ndarray]]] = {}
    for row in table[table["level"] == "line"].itertuples(index=False):
        if row.flight not in arrays:
            g = survey.flights[row.flight].gnss
            t = g["time"].to_numpy(float)
            arrays[row.flight] = (t, g["lon"].to_numpy(float), g["lat"].to_numpy(float), g["h"].to_numpy(float),
                                  bool(np.all(t[1:] >= t[:-1])))
        t, _lon, _lat, h, sorted_t = arrays[row.flight]
        idx = _line_samples(t, sorted_t, row.t_start, row.t_end)
        q = _qc_figures(row)
        q["speed_ms"] = finite_float(1000.0 * row.length_km / row.duration_s) if row.duration_s > 0 else None
        q["mean_h_m"] = finite_float(np.mean(h[idx])) if idx.size else None
        track = row.track
        picks.setdefault(row.flight, []).append((len(lines), idx[::max(1, idx.size // track_points)]))
        lines.append({"line": str(row.line), "flight": str(row.flight), "kind": str(row.kind),
                      "track": None if track is None or (isinstance(track, float) and np.isnan(track)) else str(track),
                      "t_start": float(row.t_start), "t_end": float(row.t_end), "qc": q, "map_track": {}})
    for flight, items in picks.items():
        _t, lon, lat, _h, _s = arrays[flight]
        for (i, _), tr in zip(items, _line_tracks(lon, lat, [p for _, p in items], crs)):
            lines[i]["map_track"] = tr
    return flights, lines


def approx_nbytes(value, depth: int = 4) -> int:
    """Rough memory held by a cached result (bytes): its arrays and tables, found through
    containers and object attributes down to ``depth`` levels; anything else counts 0."""
    if depth < 0 or value is None:
        return 0
    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    if isinstance(value, (pd.DataFrame, pd.Series)):
        return int(np.sum(value.memory_usage(index=True, deep=False)))
    if isinstance(value, dict):
        return sum(approx_nbytes(v, depth - 1) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(approx_nbytes(v, depth - 1) for v in value)
    attrs = getattr(value, "__dict__", None)
    if isinstance(attrs, dict):
        return sum(approx_nbytes(v, depth - 1) for v in attrs.values())
    return 0


class ResultCache:
    """Small LRU of loaded result objects (DataFrames, grids, recognition maps) per key: at most
    ``size`` entries and ``max_bytes`` of their arrays (:func:`approx_nbytes`; the newest entry is
    always kept) — sixteen results of the finest grid allowed would otherwise hold ~6 GB."""

    def __init__(self, size: int = 16, max_bytes: int = 1 << 30):
        self.size = size
        self.max_bytes = max_bytes
        self._d: OrderedDict = OrderedDict()
        self._bytes: dict[Any, int] = {}
        self._lock = threading.Lock()
        self._key_locks: dict[Any, threading.Lock] = {}

    def get(self, key, build: Callable[[], Any]):
        with self._lock:
            if key in self._d:
                self._d.move_to_end(key)
                return self._d[key]
            kl = self._key_locks.setdefault(key, threading.Lock())
        with kl:  # build once even under concurrent requests
            with self._lock:
                if key in self._d:
                    return self._d[key]
            val = build()
            nbytes = approx_nbytes(val)
            with self._lock:
                self._d[key] = val
                self._bytes[key] = nbytes
                while len(self._d) > 1 and (len(self._d) > self.size or sum(self._bytes.values()) > self.max_bytes):
                    old, _ = self._d.popitem(last=False)
                    self._bytes.pop(old, None)
                self._key_locks.pop(key, None)
            return val

    def discard(self, predicate: Callable[[Any], bool]) -> int:
        """Drop the entries whose key matches (e.g. the results of a deleted survey: database ids
        may be reused)."""
        with self._lock:
            keys = [k for k in self._d if predicate(k)]
            for k in keys:
                del self._d[k]
                self._bytes.pop(k, None)
            return len(keys)
