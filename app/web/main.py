"""FastAPI application factory: ``create_app(settings=None)``.

REST API under ``/api`` (OpenAPI at ``/docs``), the static browser frontend at ``/``
(``frontend/``, no build step) and Plotly's JavaScript served from the installed
``plotly`` package at ``/vendor/plotly.min.js``.
"""

from __future__ import annotations

import hmac
import json
import logging
import os
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from app.config import ProcessingParams
from app.io.errors import InputError

from .db import session_factory
from .jobs import JobManager
from .settings import Settings
from .store import ResultCache, Store

log = logging.getLogger("aerograv.web")

# the checkout's frontend/ (editable install); AEROGRAV_FRONTEND_DIR for installed copies (Dockerfile)
FRONTEND_DIR = Path(os.environ.get("AEROGRAV_FRONTEND_DIR") or Path(__file__).resolve().parents[2] / "frontend")
MUTATING = {"POST", "PUT", "PATCH", "DELETE"}


class PayloadTooLarge(HTTPException):
    def __init__(self, limit_mb: float):
        super().__init__(413, f"upload larger than the limit of {limit_mb:g} MB (AEROGRAV_MAX_UPLOAD_MB)")


async def _send_json(send, status: int, body: dict, headers: list | None = None) -> None:
    raw = json.dumps(body).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(raw)).encode())]
                + (headers or [])})
    await send({"type": "http.response.body", "body": raw})


class GuardMiddleware:
    """Token check on mutating /api requests (401) and the request body limit (413).

    The body limit is enforced on the declared Content-Length and, for streamed
    bodies, on the bytes actually received."""

    def __init__(self, app, settings: Settings):
        self.app = app
        self.settings = settings

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        method = scope["method"]
        headers = {k.lower(): v for k, v in scope.get("headers", [])}
        token = self.settings.token
        if token and method in MUTATING and scope["path"].startswith("/api"):
            given = None
            auth = headers.get(b"authorization", b"").decode("latin-1")
            if auth.lower().startswith("bearer "):
                given = auth[7:].strip()
            elif b"x-aerograv-token" in headers:
                given = headers[b"x-aerograv-token"].decode("latin-1").strip()
            if not given or not hmac.compare_digest(given.encode(), token.encode()):
                return await _send_json(send, 401, {"detail": "missing or invalid token: send 'Authorization: Bearer <token>'"},
                                        [(b"www-authenticate", b"Bearer")])
        limit = self.settings.max_upload_bytes
        cl = headers.get(b"content-length")
        if cl is not None and cl.isdigit() and int(cl) > limit:
            return await _send_json(send, 413, {"detail": PayloadTooLarge(self.settings.max_upload_mb).detail})
        received = 0

        async def limited_receive():
            nonlocal received
            msg = await receive()
            if msg["type"] == "http.request":
                received += len(msg.get("body", b""))
                if received > limit:
                    raise PayloadTooLarge(self.settings.max_upload_mb)
            return msg

        return await self.app(scope, limited_receive, send)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    settings.data_dir = Path(settings.data_dir).resolve()
    store = Store(settings.data_dir)
    Session = session_factory(settings.db_url)
    jobs = JobManager(settings, Session)
    n = jobs.recover()
    if n:
        log.warning("%d job(s) left running by a previous server marked failed", n)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        jobs.start()
        try:
            yield
        finally:
            jobs.shutdown()

    app = FastAPI(title="Aerograv", version="0.1.0", lifespan=lifespan,
                  description="Airborne gravimetry processing: surveys, jobs, recognition, profiles, grids, exports.")
    app.state.settings = settings
    app.state.store = store
    app.state.Session = Session
    app.state.jobs = jobs
    app.state.cache = ResultCache()
    app.add_middleware(GuardMiddleware, settings=settings)

    def _warm(job_id: int) -> None:
        """After a successful job, load its recognition map so the first slider move is fast."""
        from .db import Job, Result
        from .routers.results import _load_recognition
        with Session() as s:
            job = s.get(Job, job_id)
            if job is None or job.status != "succeeded":
                return
            r = s.query(Result).filter(Result.job_id == job_id).first()
        if r is not None and (Path(r.dir) / "recognition.parquet").exists():
            app.state.cache.get(("recognition", r.id), lambda: _load_recognition(r))

    jobs.on_finished.append(_warm)

    @app.exception_handler(InputError)
    async def _input_error(_req: Request, exc: InputError):
        return JSONResponse(status_code=422, content={"detail": exc.to_dict()})

    from .routers import jobs as jobs_router, results, surveys
    app.include_router(surveys.router)
    app.include_router(jobs_router.router)
    app.include_router(results.router)

    @app.get("/api/params/schema", tags=["params"])
    def params_schema() -> dict:
        """ProcessingParams: JSON schema with defaults and descriptions (for the parameters form)."""
        return {"schema": ProcessingParams.model_json_schema(), "defaults": ProcessingParams().model_dump()}

    @app.get("/api/health", tags=["meta"])
    def health() -> dict:
        return {"status": "ok", "backend": jobs.backend, "auth": bool(settings.token),
                "max_upload_mb": settings.max_upload_mb}

    @app.get("/vendor/plotly.min.js", include_in_schema=False)
    def plotly_js():
        import plotly
        path = Path(plotly.__file__).parent / "package_data" / "plotly.min.js"
        return FileResponse(path, media_type="application/javascript",
                            headers={"Cache-Control": "public, max-age=86400"})

    if FRONTEND_DIR.is_dir():
        app.mount("/", StaticFiles(directory=FRONTEND_DIR, html=True), name="frontend")
    return app
