"""Processing jobs: the worker-side job function and the server-side job manager.

The same function, :func:`execute_job`, runs in a local worker process (default:
one ``multiprocessing`` *spawn* process per job) or on a Dask worker (when
``AEROGRAV_DASK_SCHEDULER`` is set).  It reports progress, the stage and every EM
iteration through the database, writes the outputs into a job-specific directory
(``<out_dir>.partial`` renamed to ``<out_dir>`` when complete) and, only when it
succeeded, switches the survey's result pointer in the same transaction that marks
the job succeeded.  Every status change is a conditional update, so a job cancelled
or declared dead by the server can never overwrite the survey's results afterwards.

The server-side :class:`JobManager` starts workers (at most ``max_jobs`` local processes at once,
default the CPUs; later jobs wait, queued, and start oldest first as slots free), cancels them,
and watches them:
a worker process that dies (killed, out of memory, segfault) turns its job into
``failed`` with the reason; the survey and its previous results are untouched.  That record
is durable: when the store refuses the write (disk full, database locked) the death stays
pending and is written again on every pass until the store accepts it.  Active jobs in the
store are also reconciled with the live workers: at start-up all of them are failed (no
worker survives its server), and every ``reconcile_interval_s`` a local job whose worker
process is gone is failed — gone also when its pid now names a thread of another process or a
process started after the job (pids are reused).
"""

from __future__ import annotations

import datetime as dt
import importlib
import inspect
import json
import logging
import multiprocessing
import os
import shutil
import signal
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sqlalchemy import update

from app.jsonsafe import to_jsonable
from app.pipeline.parallel import cpu_count, freeze_imports, thread_count

from .db import ACTIVE_STATES, Job, Result, Survey, session_factory, utcnow
from .errors import hide_server_paths

log = logging.getLogger("aerograv.web.jobs")


class JobCancelled(Exception):
    """Raised inside the worker when the job was cancelled meanwhile."""


def load_entry(entry: str) -> Callable:
    """Resolve ``'module:function'``."""
    mod, _, fn = entry.partition(":")
    return getattr(importlib.import_module(mod), fn)


def execute_job(job_id: int, db_url: str, entry: str, input_dir: str, out_dir: str,
                kind: str, params: dict[str, Any], threads: int | None = None, one_shot: bool = False) -> str:
    """Run one job to completion (in a worker).  Returns the final status.

    ``threads``: the job process's share of the CPUs for the per-line loops
    (``AEROGRAV_THREADS``, :mod:`app.pipeline.parallel`), set when the variable is not already
    set; the output does not depend on it.  ``one_shot``: the process ends with this job (a
    local job's own process): the imports are frozen out of the garbage collector's reach
    (:func:`app.pipeline.parallel.freeze_imports`)."""
    if threads is not None and not os.environ.get("AEROGRAV_THREADS", "").strip():
        os.environ["AEROGRAV_THREADS"] = str(max(1, int(threads)))
    Session = session_factory(db_url)
    with Session() as s:
        res = s.execute(update(Job).where(Job.id == job_id, Job.status == "queued")
                        .values(status="running", started_at=utcnow(), worker_pid=os.getpid(),
                                stage="starting", progress=0.0))
        s.commit()
        if res.rowcount != 1:
            return "not-started"

    em_rows: list[dict[str, Any]] = []
    last = {"t": 0.0, "stage": None, "p": 0.0}

    def write(values: dict[str, Any]) -> None:
        with Session() as s:
            r = s.execute(update(Job).where(Job.id == job_id, Job.status == "running").values(**values))
            s.commit()
            if r.rowcount != 1:
                raise JobCancelled()

    def progress(stage: str, fraction: float, info: dict | None = None) -> None:
        now = time.monotonic()
        values: dict[str, Any] = {}
        if info and "em_iteration" in info:
            em_rows.append(to_jsonable(dict(info["em_iteration"])))
            values["em_iterations"] = list(em_rows)
        if values or stage != last["stage"] or now - last["t"] > 0.3:
            # the bar never steps back, whatever an entry reports
            last["p"] = max(last["p"], float(min(max(fraction, 0.0), 0.999)))
            values.update(stage=str(stage), progress=last["p"])
            last["t"], last["stage"] = now, stage
            write(values)

    out = Path(out_dir)
    partial = out.with_name(out.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    placed = False   # the result folder moved into place, not yet recorded
    try:
        fn = load_entry(entry)
        if one_shot:
            freeze_imports()
        kw: dict[str, Any] = {}
        if "kind" in inspect.signature(fn).parameters:
            kw["kind"] = kind
            if kind == "filter":
                kw["previous_dir"] = _previous_result_dir(Session, job_id)
                em_rows.extend(_stored_em_table(kw["previous_dir"]))
                write({"stage": "reusing identification", "em_iterations": list(em_rows)})
        elif kind != "process":
            raise ValueError(f"the pipeline entry {entry} runs 'process' jobs only")
        report = fn(input_dir, str(partial), overrides=params or None, progress=progress, **kw)
        if out.exists():
            shutil.rmtree(out)
        os.replace(partial, out)
        placed = True
        with Session() as s:
            r = s.execute(update(Job).where(Job.id == job_id, Job.status == "running")
                          .values(status="succeeded", progress=1.0, stage="done", finished_at=utcnow(),
                                  em_iterations=list(em_rows) if em_rows else Job.em_iterations))
            if r.rowcount != 1:
                s.rollback()
                raise JobCancelled()
            job = s.get(Job, job_id)
            result = Result(survey_id=job.survey_id, job_id=job_id, dir=str(out),
                            report=to_jsonable(report) if isinstance(report, dict) else {})
            s.add(result)
            s.flush()
            s.execute(update(Survey).where(Survey.id == job.survey_id).values(current_result_id=result.id))
            s.commit()
        return "succeeded"
    except JobCancelled:
        shutil.rmtree(partial, ignore_errors=True)
        if placed:   # cancelled (or its survey deleted) while the pipeline finished: no orphan folder
            shutil.rmtree(out, ignore_errors=True)
        return "cancelled"
    except BaseException as exc:  # noqa: BLE001 - every failure is reported on the job
        shutil.rmtree(partial, ignore_errors=True)
        # the survey's snapshot and result folders by the file's place in them (flights/f1/gnss.csv)
        msg = hide_server_paths(str(exc) or type(exc).__name__, out.parent.parent)
        if type(exc).__name__ != "InputError":
            msg = f"{type(exc).__name__}: {msg}"
            log.error("job %s failed:\n%s", job_id, traceback.format_exc())
        with Session() as s:
            s.execute(update(Job).where(Job.id == job_id, Job.status == "running")
                      .values(status="failed", error=msg[:4000], finished_at=utcnow()))
            s.commit()
        if isinstance(exc, (KeyboardInterrupt, SystemExit)):
            raise
        return "failed"


def _previous_result_dir(Session, job_id: int) -> str:
    """The directory of the survey's current result (a filter job starts from its identification)."""
    with Session() as s:
        job = s.get(Job, job_id)
        survey = s.get(Survey, job.survey_id)
        res = s.get(Result, survey.current_result_id) if survey.current_result_id is not None else None
        if res is None or not (Path(res.dir) / "identified").is_dir():
            raise ValueError("a filter job needs a stored identification: run an identify or process job first")
        return res.dir


def _stored_em_table(result_dir: str) -> list[dict[str, Any]]:
    """The EM iteration table of the identification a filter job reuses (not recomputed)."""
    p = Path(result_dir) / "identification.json"
    if not p.exists():
        return []
    rows = json.loads(p.read_text()).get("em", {}).get("iterations", [])
    return [to_jsonable({**r, "model": "stored"}) for r in rows]


def _death_reason(exitcode: int | None) -> str:
    if exitcode is None:
        return "worker process vanished"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        return f"worker process died: killed by {name}"
    return f"worker process died with exit code {exitcode}"


def _pid_alive(pid: int, started_at=None) -> bool:
    """Whether ``pid`` is still a job's worker process: alive and not a zombie, a process and not
    a thread of another one (thread ids share the pid space: a pid freed by a dead worker is soon
    a new thread's), and, when the job's start (``started_at``, naive UTC, set by the worker
    itself) is known, started no later than the job — a pid reused by a later process is not
    the worker.  Without ``/proc`` only the first test is made."""
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    try:
        status = Path(f"/proc/{int(pid)}/status").read_text()
        stat = Path(f"/proc/{int(pid)}/stat").read_text()
    except OSError:
        return True
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    if fields.get("Tgid", str(int(pid))).strip() != str(int(pid)):
        return False
    after_comm = stat.rsplit(")", 1)[-1].split()   # fields 3… of /proc/<pid>/stat
    if after_comm[0] == "Z":
        return False
    if started_at is not None:
        started = _process_start_epoch_s(int(after_comm[19]))   # field 22: start, clock ticks after boot
        job_start = started_at.replace(tzinfo=dt.UTC).timestamp() if started_at.tzinfo is None \
            else started_at.timestamp()
        if started is not None and started > job_start + 2.0:
            return False
    return True


def _process_start_epoch_s(ticks_after_boot: int) -> float | None:
    """A process's start (s since the epoch) from its start in clock ticks after boot."""
    try:
        btime = next(int(line.split()[1]) for line in Path("/proc/stat").read_text().splitlines()
                     if line.startswith("btime "))
    except (OSError, StopIteration, ValueError):
        return None
    return btime + ticks_after_boot / os.sysconf("SC_CLK_TCK")


class JobManager:
    """Starts, cancels and watches jobs (local processes or a Dask cluster)."""

    def __init__(self, settings, Session):
        self.settings = settings
        self.Session = Session
        self._procs: dict[int, multiprocessing.process.BaseProcess] = {}
        self._futures: dict[int, Any] = {}
        self._lock = threading.Lock()
        self._client = None
        self._pending: dict[int, str] = {}  # job id -> reason of a worker death not yet recorded
        self._waiting: deque[tuple[int, tuple]] = deque()  # local jobs queued for a free slot (id, args)
        self._started: dict[int, float] = {}  # job id -> when its worker started or its task was submitted (monotonic)
        self._last_reconcile = 0.0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        #: called with the job id after a worker ended (any outcome), from the monitor thread
        self.on_finished: list[Callable[[int], None]] = []

    # -- lifecycle ---------------------------------------------------------
    def recover(self) -> int:
        """At start-up: jobs left queued/running by a previous server are failed."""
        with self.Session() as s:
            r = s.execute(update(Job).where(Job.status.in_(ACTIVE_STATES))
                          .values(status="failed", error="server restarted", finished_at=utcnow()))
            s.commit()
            return r.rowcount or 0

    def start(self) -> None:
        self._thread = threading.Thread(target=self._monitor, name="aerograv-job-monitor", daemon=True)
        self._thread.start()

    def shutdown(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        try:
            self._record_pending()
        except Exception:  # pragma: no cover
            pass
        with self._lock:
            procs = list(self._procs.values())
            self._procs.clear()
            self._waiting.clear()  # still queued: the next start-up marks them "server restarted"
        for p in procs:  # the next start-up marks their jobs "server restarted"
            if p.is_alive():
                p.terminate()
            p.join(timeout=5)
        if self._client is not None:
            try:
                self._client.close()
            except Exception:  # pragma: no cover
                pass
            self._client = None

    # -- submission --------------------------------------------------------
    @property
    def backend(self) -> str:
        return "dask" if self.settings.dask_scheduler else "local"

    def _dask_client(self):
        if self._client is None:
            from distributed import Client
            self._client = Client(self.settings.dask_scheduler, set_as_default=False, timeout="20s")
        return self._client

    def max_local_jobs(self) -> int:
        """Most local job processes at once: ``settings.max_jobs``, default the CPUs."""
        n = getattr(self.settings, "max_jobs", None)
        return int(n) if n else cpu_count()

    def _running(self) -> int:
        """Live local job processes (call under ``_lock``)."""
        return sum(1 for p in self._procs.values() if p.is_alive())

    def thread_share(self) -> int | None:
        """Threads for a job process started now: the server's CPUs (:func:`app.pipeline.parallel.thread_count`)
        shared among the local jobs running and this one, so that concurrent jobs do not
        oversubscribe the cores; None when ``AEROGRAV_THREADS`` is set (every job then uses it).
        Call under ``_lock``."""
        if os.environ.get("AEROGRAV_THREADS", "").strip():
            return None
        return max(1, thread_count() // (self._running() + 1))

    def _start_local(self, job_id: int, args: tuple) -> None:
        """Spawn the job's worker process (call under ``_lock``)."""
        ctx = multiprocessing.get_context("spawn")
        p = ctx.Process(target=execute_job, args=args + (self.thread_share(),), kwargs={"one_shot": True},
                        name=f"aerograv-job-{job_id}")
        p.start()
        self._procs[job_id] = p
        self._started[job_id] = time.monotonic()

    def submit(self, job: Job) -> None:
        """Start the job: on Dask, or in a process of its own — or, when ``max_local_jobs``
        processes already run, keep it queued until one ends (the monitor starts it)."""
        args = (job.id, self.settings.db_url, self.settings.pipeline_entry, job.input_dir, job.out_dir,
                job.kind, dict(job.params or {}))
        waits = False
        with self._lock:
            if self.backend == "dask":
                fut = self._dask_client().submit(execute_job, *args, pure=False, key=f"aerograv-job-{job.id}")
                self._futures[job.id] = fut
                self._started[job.id] = time.monotonic()
            elif self._waiting or self._running() >= self.max_local_jobs():
                self._waiting.append((job.id, args))
                waits = True
            else:
                self._start_local(job.id, args)
        if waits:  # what the browser shows until a slot frees
            with self.Session() as s:
                s.execute(update(Job).where(Job.id == job.id, Job.status == "queued")
                          .values(stage=f"waiting for a free worker (all {self.max_local_jobs()} busy)"))
                s.commit()

    def _start_waiting(self) -> None:
        """Start queued local jobs while slots are free, oldest first."""
        with self._lock:
            while self._waiting and self._running() < self.max_local_jobs():
                jid, args = self._waiting.popleft()
                self._start_local(jid, args)

    def waiting(self) -> list[int]:
        """Ids of the local jobs queued for a free slot, oldest first."""
        with self._lock:
            return [jid for jid, _ in self._waiting]

    def cancel(self, job_id: int) -> bool:
        """Mark the job cancelled (if still active) and stop its worker."""
        with self.Session() as s:
            r = s.execute(update(Job).where(Job.id == job_id, Job.status.in_(ACTIVE_STATES))
                          .values(status="cancelled", finished_at=utcnow(), stage="cancelled"))
            s.commit()
            changed = (r.rowcount or 0) == 1
        with self._lock:
            p = self._procs.get(job_id)
            fut = self._futures.get(job_id)
            was_waiting = changed and any(jid == job_id for jid, _ in self._waiting)
            if was_waiting:  # a job still waiting for a slot never starts
                self._waiting = deque((jid, a) for jid, a in self._waiting if jid != job_id)
        if p is not None and p.is_alive():
            p.terminate()
        if fut is not None:
            fut.cancel()  # a running Dask task stops at its next progress report
        if was_waiting:  # no worker will end: the job's files are pruned now
            self._notify(job_id)
        return changed

    def worker_pid(self, job_id: int) -> int | None:
        with self._lock:
            p = self._procs.get(job_id)
        return p.pid if p is not None else None

    # -- watching ----------------------------------------------------------
    def _fail_if_active(self, job_id: int, reason: str) -> None:
        """Record the failure (raises when the store refuses the write)."""
        with self.Session() as s:
            s.execute(update(Job).where(Job.id == job_id, Job.status.in_(ACTIVE_STATES))
                      .values(status="failed", error=reason, finished_at=utcnow()))
            s.commit()
        self._remove_partial(job_id)

    def _remove_partial(self, job_id: int) -> None:
        """Remove the half-written result folder of a job that ended without its result."""
        with self.Session() as s:
            job = s.get(Job, job_id)
            out = job.out_dir if job else None
        if out:
            shutil.rmtree(out + ".partial", ignore_errors=True)

    def stop_overdue(self) -> list[int]:
        """Fail and stop the jobs running longer than ``settings.job_timeout_s`` (the worker's writes
        then find the job no longer running and it stops; a local worker is terminated at once).
        Returns their ids."""
        limit = getattr(self.settings, "job_timeout_s", None)
        if not limit:
            return []
        now = time.monotonic()
        with self._lock:
            over = [jid for jid, t0 in self._started.items() if now - t0 > limit
                    and (jid in self._procs or jid in self._futures)]
        stopped = []
        for jid in over:
            reason = (f"stopped: the job ran longer than the {limit / 3600:g} h allowed (AEROGRAV_JOB_TIMEOUT_S); "
                      "the survey's current result is unchanged")
            try:
                self._fail_if_active(jid, reason)
            except Exception as exc:  # noqa: BLE001 - tried again on the next pass
                log.warning("job %s: could not record its timeout yet (%s)", jid, exc)
                continue
            with self._lock:
                self._started.pop(jid, None)
                p, fut = self._procs.get(jid), self._futures.get(jid)
            if p is not None and p.is_alive():
                p.terminate()
                p.join(timeout=5)
                self._remove_partial(jid)      # what the worker wrote until it was stopped
            if fut is not None:
                fut.cancel()                   # a running task stops at its next progress report
            stopped.append(jid)
        return stopped

    def check(self) -> None:
        """One pass of the monitor (also called by tests)."""
        self.stop_overdue()
        with self._lock:
            dead = [(jid, p) for jid, p in self._procs.items() if not p.is_alive()]
            for jid, _ in dead:
                del self._procs[jid]
                self._started.pop(jid, None)
            done = [(jid, f) for jid, f in self._futures.items() if f.done()]
            for jid, _ in done:
                del self._futures[jid]
                self._started.pop(jid, None)
        for jid, p in dead:
            p.join(timeout=1)
            self._pending[jid] = _death_reason(p.exitcode)
        for jid, f in done:
            if f.status == "error":
                try:
                    exc = f.exception(timeout=1)
                    reason = f"dask worker failed: {type(exc).__name__}: {exc}"
                except Exception as e:  # pragma: no cover
                    reason = f"dask worker failed: {e}"
            elif f.status == "cancelled":
                reason = "dask task cancelled or lost"
            else:
                reason = "job ended without reporting its result"
            self._pending[jid] = reason
        self._record_pending()
        self._start_waiting()
        now = time.monotonic()
        if now - self._last_reconcile >= getattr(self.settings, "reconcile_interval_s", 10.0):
            self._last_reconcile = now
            self.reconcile()

    def _record_pending(self) -> None:
        for jid, reason in list(self._pending.items()):
            try:
                self._fail_if_active(jid, reason)
            except Exception as exc:  # noqa: BLE001 - kept, written again on the next pass
                log.warning("job %s: could not record the worker's end yet (%s); will retry", jid, exc)
                continue
            del self._pending[jid]
            self._notify(jid)

    def reconcile(self, queued_grace_s: float = 60.0) -> list[int]:
        """Fail local jobs the store says are active but that have no live worker: not watched by
        this server, and their worker process (``worker_pid``) gone; a queued job without a worker
        gets ``queued_grace_s`` to start.  Returns the ids failed."""
        from sqlalchemy import select

        failed = []
        with self._lock:
            watched = set(self._procs) | set(self._futures) | set(self._pending) | {j for j, _ in self._waiting}
        with self.Session() as s:
            active = list(s.scalars(select(Job).where(Job.status.in_(ACTIVE_STATES), Job.backend == "local")))
        cutoff = utcnow() - dt.timedelta(seconds=queued_grace_s)
        for j in active:
            if j.id in watched or self.backend != "local":
                continue
            if j.worker_pid and _pid_alive(j.worker_pid, j.started_at):
                continue
            if j.status == "queued" and j.created_at and j.created_at > cutoff:
                continue
            reason = "worker lost: no live worker process for this job"
            try:
                self._fail_if_active(j.id, reason)
                failed.append(j.id)
            except Exception as exc:  # noqa: BLE001
                log.warning("job %s: could not record the lost worker yet (%s)", j.id, exc)
                with self._lock:
                    self._pending[j.id] = reason
        return failed

    def _notify(self, job_id: int) -> None:
        for cb in self.on_finished:
            try:
                cb(job_id)
            except Exception:  # pragma: no cover - a hook never breaks the monitor
                log.exception("on_finished hook failed for job %s", job_id)

    def _monitor(self) -> None:
        while not self._stop.wait(self.settings.poll_interval_s):
            try:
                self.check()
            except Exception:  # pragma: no cover - keep watching
                log.exception("job monitor pass failed")
