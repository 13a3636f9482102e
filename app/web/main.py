"""FastAPI application factory: ``create_app(settings=None)``.

REST API under ``/api`` (OpenAPI at ``/docs`` and ``/redoc``), the static browser frontend at
``/`` (``frontend/``, no build step), Plotly's JavaScript served from the installed ``plotly``
package at ``/vendor/plotly.min.js``, and Swagger UI / ReDoc from the installed
``fastapi-offline`` package under ``/docs-static/`` (no CDN: the API pages work offline, under
the same CSP as the application).

Every request passes :class:`GuardMiddleware`: the Host header must be allowed (DNS
rebinding), mutating ``/api`` requests need the token when one is set and, when none is set,
must come from the page itself (``Sec-Fetch-Site`` / ``Origin``: another web site cannot drive
the analyst's browser), bodies are limited (413: the upload limit for a multipart form sent to an
endpoint that takes files, at most ``MAX_FORM_PARTS`` parts; ``AEROGRAV_MAX_JSON_KB`` for any
other body), and every response carries the security headers (a CSP without inline scripts, ``X-Frame-Options: DENY``, ``nosniff``).  Malformed
requests are answered 4xx with a reason, never 500: validation errors echo at most a short
excerpt of the offending value and never a non-finite number.
"""

from __future__ import annotations

import errno
import hmac
import json
import logging
import os
import re
import threading
import time
from contextlib import asynccontextmanager
from pathlib import Path
from urllib.parse import urlsplit

from fastapi import FastAPI, HTTPException, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from sqlalchemy.exc import OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Mount, compile_path

try:
    from python_multipart.multipart import parse_options_header
except ModuleNotFoundError:  # pragma: no cover - python-multipart < 0.0.13
    from multipart.multipart import parse_options_header

from app.config import ProcessingParams, param_groups
from app.io.errors import InputError

from .db import session_factory
from .errors import hide_server_paths, validation_detail
from .jobs import JobManager
from .schemas import HealthOut, ParamsSchemaOut
from .settings import Settings
from .store import ResultCache, Store, StoreFull

log = logging.getLogger("aerograv.web")

# the checkout's frontend/ (editable install); AEROGRAV_FRONTEND_DIR for installed copies (Dockerfile)
FRONTEND_DIR = Path(os.environ.get("AEROGRAV_FRONTEND_DIR") or Path(__file__).resolve().parents[2] / "frontend")
MUTATING = {"POST", "PUT", "PATCH", "DELETE"}
CSP = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; "
       "font-src 'self' data:; connect-src 'self'; worker-src 'self' blob:; object-src 'none'; base-uri 'none'; "
       "form-action 'self'; frame-ancestors 'none'")
# Swagger UI and ReDoc (/docs, /redoc) come from the installed fastapi-offline package and start from
# a script file of our own: the API pages live under the application's CSP, no external host
DOCS_ASSETS = {"swagger-ui-bundle.js": "application/javascript", "swagger-ui.css": "text/css",
               "redoc.standalone.js": "application/javascript", "favicon.png": "image/png"}
SWAGGER_INIT_JS = """window.ui = SwaggerUIBundle({
  url: "/openapi.json", dom_id: "#swagger-ui", layout: "BaseLayout", deepLinking: true,
  showExtensions: true, showCommonExtensions: true, validatorUrl: null,
  presets: [SwaggerUIBundle.presets.apis, SwaggerUIBundle.SwaggerUIStandalonePreset],
});
"""
DOCS_HTML = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Aerograv API — Swagger UI</title>
<link rel="icon" href="/docs-static/favicon.png"><link rel="stylesheet" href="/docs-static/swagger-ui.css">
</head><body><div id="swagger-ui"></div>
<script src="/docs-static/swagger-ui-bundle.js"></script><script src="/docs-static/swagger-init.js"></script>
</body></html>
"""
REDOC_HTML = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Aerograv API — ReDoc</title>
<meta name="viewport" content="width=device-width, initial-scale=1"><link rel="icon" href="/docs-static/favicon.png">
</head><body><redoc spec-url="/openapi.json"></redoc><script src="/docs-static/redoc.standalone.js"></script>
</body></html>
"""


def docs_assets_dir() -> Path | None:
    """The Swagger UI / ReDoc files of the installed ``fastapi-offline`` package."""
    import importlib.util
    spec = importlib.util.find_spec("fastapi_offline")
    if spec is None or not spec.submodule_search_locations:
        return None
    d = Path(list(spec.submodule_search_locations)[0]) / "static"
    return d if d.is_dir() else None


SECURITY_HEADERS = [(b"x-frame-options", b"DENY"), (b"x-content-type-options", b"nosniff"),
                    (b"referrer-policy", b"no-referrer"), (b"cross-origin-opener-policy", b"same-origin")]


class PayloadTooLarge(HTTPException):
    def __init__(self, limit_mb: float):
        super().__init__(413, f"upload larger than the limit of {limit_mb:g} MB (AEROGRAV_MAX_UPLOAD_MB)")


class BodyTooLarge(HTTPException):
    """A request that is not an upload (JSON) with a body over ``AEROGRAV_MAX_JSON_KB``."""

    def __init__(self, limit_bytes: int):
        super().__init__(413, f"request body larger than the limit of {limit_bytes / 1024:g} kB for a request that "
                              "is not an upload (AEROGRAV_MAX_JSON_KB); files go as multipart/form-data to "
                              "the upload endpoints (import, flights, dem)")


#: most parts (files and fields) of an upload form: an upload has at most four (gravimeter, gnss,
#: lines, flight).  The form parser keeps a file part of less than 1 MB in memory (larger ones go
#: to disk), so a body of hundreds of small parts would be held in memory whole.
MAX_FORM_PARTS = 16


class TooManyParts(HTTPException):
    def __init__(self):
        super().__init__(400, f"the multipart form has more than {MAX_FORM_PARTS} parts; an upload sends its "
                              "files (gravimeter, gnss, lines; file; dem) and the flight name only")


class PartCounter:
    """Counts the parts of a multipart body while it streams in: the boundary delimiters seen
    (``--boundary``; the closing one ends the last part), across chunk edges."""

    def __init__(self, boundary: bytes):
        self.delimiter = b"--" + boundary
        self.tail = b""
        self.seen = 0

    def feed(self, chunk: bytes) -> int:
        """Add a chunk of the body; returns the parts begun so far."""
        data = self.tail + chunk
        self.seen += data.count(self.delimiter)
        self.tail = data[-(len(self.delimiter) - 1):] if len(self.delimiter) > 1 else b""
        return max(0, self.seen - 1)


def upload_routes(app) -> list[tuple[re.Pattern, set[str]]]:
    """(path pattern, methods) of the endpoints that take a multipart form (files), from the
    application's OpenAPI description."""
    out = []
    for path, ops in app.openapi().get("paths", {}).items():
        methods = {m.upper() for m, op in ops.items() if isinstance(op, dict)
                   and "multipart/form-data" in ((op.get("requestBody") or {}).get("content") or {})}
        if methods:
            out.append((compile_path(path)[0], methods))
    return out


async def _send_json(send, status: int, body: dict, headers: list | None = None) -> None:
    raw = json.dumps(body).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(raw)).encode())]
                + (headers or [])})
    await send({"type": "http.response.body", "body": raw})


def _split_host(value: str) -> tuple[str, str | None]:
    """'Example.org:8000' → ('example.org', '8000'); '[::1]:80' → ('::1', '80')."""
    value = value.strip().lower()
    if value.startswith("["):
        host, _, rest = value[1:].partition("]")
        return host, rest[1:] if rest.startswith(":") else None
    if value.count(":") == 1:
        host, _, port = value.partition(":")
        return host, port
    return value, None


class GuardMiddleware:
    """Host allow-list (400), same-origin check of mutating /api requests when no token is set
    (403), token check on mutating /api requests (401), the request body limit (413) and the
    security headers of every response.

    The body limit is enforced on the declared Content-Length and, for streamed
    bodies, on the bytes actually received."""

    def __init__(self, app, settings: Settings):
        self.app = app
        self.settings = settings
        self.allowed = settings.allowed_host_set()
        self._uploads: list[tuple[re.Pattern, set[str]]] | None = None

    def _is_upload(self, scope, headers: dict) -> bytes | None:
        """The multipart boundary when the request is a form sent to an endpoint that takes files
        (the upload limit applies), else None (the JSON limit applies)."""
        ctype, params = parse_options_header(headers.get(b"content-type", b""))
        if ctype != b"multipart/form-data" or not params.get(b"boundary"):
            return None
        if self._uploads is None and "app" in scope:
            self._uploads = upload_routes(scope["app"])
        path, method = scope.get("path", ""), scope["method"]
        if any(rx.match(path) and method in methods for rx, methods in self._uploads or ()):
            return params[b"boundary"]
        return None

    def _host_ok(self, host: str) -> bool:
        if self.allowed is None:
            return True
        name, port = _split_host(host)
        return name in self.allowed or (port is not None and f"{name}:{port}" in self.allowed)

    @staticmethod
    def _same_origin(headers: dict, host: str) -> str | None:
        """Why a browser request comes from another site (None: it does not, or not a browser)."""
        site = headers.get(b"sec-fetch-site", b"").decode("latin-1").strip().lower()
        if site and site not in ("same-origin", "none"):
            return f"Sec-Fetch-Site: {site}"
        origin = headers.get(b"origin")
        if origin is not None:
            o = origin.decode("latin-1").strip()
            try:   # a malformed origin ("http://[::1", a port "80x" or 99999) is another site's
                parts = urlsplit(o) if o.lower() != "null" else None
                port_o = parts.port if parts is not None else None
            except ValueError:
                return f"Origin: {o[:100]}"
            if parts is None or not parts.hostname:
                return f"Origin: {o[:100]}"
            name, port = _split_host(host)
            oport = str(port_o or {"http": 80, "https": 443}.get(parts.scheme, ""))
            hport = port or {"http": "80", "https": "443"}.get(parts.scheme, "")
            if parts.hostname.lower() != name or oport != hport:
                return f"Origin: {o[:100]}"
        return None

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        path = scope.get("path", "")
        csp = CSP.encode()

        async def send_secure(msg):
            if msg["type"] == "http.response.start":
                msg = {**msg, "headers": list(msg.get("headers", [])) + SECURITY_HEADERS
                       + [(b"content-security-policy", csp)]}
            await send(msg)

        method = scope["method"]
        headers = {k.lower(): v for k, v in scope.get("headers", [])}
        host = headers.get(b"host", b"").decode("latin-1")
        if not self._host_ok(host):
            return await _send_json(send_secure, 400, {"detail": f"host {host[:100]!r} is not allowed "
                                                       "(AEROGRAV_ALLOWED_HOSTS)"})
        token = self.settings.token
        if not token and method in MUTATING and path.startswith("/api"):
            why = self._same_origin(headers, host)
            if why:
                return await _send_json(send_secure, 403, {"detail": f"cross-site request refused ({why}); "
                                                           "changes come from this application's own page"})
        if token and method in MUTATING and path.startswith("/api"):
            given = None
            auth = headers.get(b"authorization", b"").decode("latin-1")
            if auth.lower().startswith("bearer "):
                given = auth[7:].strip()
            elif b"x-aerograv-token" in headers:
                given = headers[b"x-aerograv-token"].decode("latin-1").strip()
            if not given or not hmac.compare_digest(given.encode(), token.encode()):
                return await _send_json(send_secure, 401, {"detail": "missing or invalid token: send 'Authorization: Bearer <token>'"},
                                        [(b"www-authenticate", b"Bearer")])
        boundary = self._is_upload(scope, headers)
        limit = self.settings.max_upload_bytes if boundary else self.settings.max_json_bytes
        too_large = (lambda: PayloadTooLarge(self.settings.max_upload_mb)) if boundary else (lambda: BodyTooLarge(limit))
        cl = headers.get(b"content-length")
        if cl is not None and cl.isdigit() and int(cl) > limit:
            return await _send_json(send_secure, 413, {"detail": too_large().detail})
        received = 0
        parts = PartCounter(boundary) if boundary else None

        async def limited_receive():
            nonlocal received
            msg = await receive()
            if msg["type"] == "http.request":
                body = msg.get("body", b"")
                received += len(body)
                if received > limit:
                    raise too_large()
                if parts is not None and parts.feed(body) > MAX_FORM_PARTS:
                    raise TooManyParts()
            return msg

        return await self.app(scope, limited_receive, send_secure)


def _recover(settings: Settings, store: Store, Session, jobs: JobManager) -> None:
    """Start-up housekeeping: jobs a previous server left running are marked failed, half-written
    folders are removed, and an open Host allow-list is warned about."""
    n = jobs.recover()
    if n:
        log.warning("%d job(s) left running by a previous server marked failed", n)
    from .db import ACTIVE_STATES, Job
    with Session() as db:
        active_out = {j.out_dir for j in db.query(Job).filter(Job.status.in_(ACTIVE_STATES)) if j.out_dir}
    removed = store.clean_start(active_out)
    if removed:
        log.warning("removed %d half-written folder(s) left by a previous server", len(removed))
    if settings.allowed_host_set() is None:
        log.warning("any Host header is accepted (bound to %s): set AEROGRAV_ALLOWED_HOSTS to this server's "
                    "names to protect browsers against DNS rebinding", settings.bind_host or settings.allowed_hosts)


def _lifespan(jobs: JobManager):
    """The application's lifespan: the job workers run while the server does."""

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        jobs.start()
        try:
            yield
        finally:
            jobs.shutdown()

    return lifespan


def _add_job_hooks(app: FastAPI, jobs: JobManager, Session, store: Store) -> None:
    """After a job ended: recount the store (its results), warm the recognition cache (successful jobs)
    and prune the survey's files."""

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

    def _prune(job_id: int) -> None:
        """After any job ended: remove the survey's snapshots and results no longer needed (in a
        thread of its own: waiting for the survey's lock must not hold up the job monitor)."""
        from .db import Job
        from .services import prune_survey

        def run():
            try:
                with Session() as s:
                    job = s.get(Job, job_id)
                    if job is not None:
                        prune_survey(s, store, job.survey_id)
            except Exception:  # pragma: no cover - retried after the next job or upload
                log.exception("pruning after job %s failed", job_id)
        threading.Thread(target=run, name=f"aerograv-prune-{job_id}", daemon=True).start()

    jobs.on_finished.append(lambda _job_id: store.invalidate_usage())   # its results count from now on
    jobs.on_finished.append(_warm)
    jobs.on_finished.append(_prune)


def _add_exception_handlers(app: FastAPI) -> None:
    """Malformed input → 4xx with a reason; database and disk trouble → 503/507 (never a bare 500)."""

    @app.exception_handler(InputError)
    async def _input_error(req: Request, exc: InputError):
        root = req.app.state.settings.data_dir
        detail = {k: hide_server_paths(v, root) if isinstance(v, str) else v for k, v in exc.to_dict().items()}
        return JSONResponse(status_code=422, content={"detail": detail})

    @app.exception_handler(RequestValidationError)
    async def _validation_error(_req: Request, exc: RequestValidationError):
        return JSONResponse(status_code=422, content={"detail": validation_detail(exc.errors())})

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(req: Request, exc: StarletteHTTPException):
        if exc.status_code == 405:
            # the router names the methods of the first route whose path matched; the path's methods
            # are those of every route matching it (GET, PATCH and DELETE for /api/surveys/{id})
            allowed = [m for m in ("GET", "POST", "PUT", "PATCH", "DELETE")
                       if any(r.matches({**req.scope, "method": m})[0] == Match.FULL for r in req.app.router.routes
                              if not isinstance(r, Mount))]
            if allowed:
                return JSONResponse(status_code=405, headers={"Allow": ", ".join(allowed)},
                                    content={"detail": f"{req.method} is not allowed here; use "
                                                       f"{', '.join(allowed)}"})
        return await http_exception_handler(req, exc)

    @app.exception_handler(RecursionError)
    async def _too_deep(_req: Request, _exc: RecursionError):
        return JSONResponse(status_code=400, content={"detail": "the request is nested too deeply"})

    @app.exception_handler(OperationalError)
    async def _db_unavailable(_req: Request, exc: OperationalError):
        log.error("database error: %s", exc)
        return JSONResponse(status_code=503, content={"detail": f"the database refused the operation, try again "
                                                                f"later ({str(exc.orig)[:200]})"},
                            headers={"Retry-After": "10"})

    @app.exception_handler(StoreFull)
    async def _store_full(_req: Request, exc: StoreFull):
        return JSONResponse(status_code=507, content={"detail": str(exc)})

    @app.exception_handler(OSError)
    async def _os_error(_req: Request, exc: OSError):
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return JSONResponse(status_code=507, content={"detail": "the server's disk is full; nothing was stored"})
        log.exception("I/O error")
        return JSONResponse(status_code=500, content={"detail": f"I/O error on the server: {exc.strerror or exc}"})


def _storage_reporter(settings: Settings, store: Store, Session):
    """``storage_report()``: disk used by each survey against its budget (walked at most every 10 s),
    and by the whole store against its limit (:meth:`Store.store_usage_bytes`)."""
    usage_cache: dict = {"t": -1e9, "v": None}
    usage_lock = threading.Lock()

    def storage_report() -> dict:
        with usage_lock:
            if time.monotonic() - usage_cache["t"] > 10 or usage_cache["v"] is None:
                budget = settings.survey_storage_bytes
                from .db import Survey
                with Session() as db:
                    ids = [i for (i,) in db.query(Survey.id).order_by(Survey.id)]
                rows = []
                for sid in ids:
                    used = store.survey_usage_bytes(sid)
                    rows.append({"survey_id": sid, "used_mb": round(used / 2**20, 3),
                                 "over_budget": used > budget})
                usage_cache["v"] = {"budget_mb_per_survey": round(budget / 2**20, 3), "surveys": rows,
                                    "used_mb_total": round(sum(r["used_mb"] for r in rows), 3)}
                usage_cache["t"] = time.monotonic()
            return {**usage_cache["v"], "max_store_mb": round(settings.max_store_bytes / 2**20, 3),
                    "store_used_mb": round(store.store_usage_bytes() / 2**20, 3)}

    return storage_report


def _add_api_routes(app: FastAPI, settings: Settings, store: Store, Session, jobs: JobManager) -> None:
    """The routers (surveys, jobs, results) and the small meta endpoints (parameter schema, health)."""
    from .routers import jobs as jobs_router
    from .routers import results, surveys
    app.include_router(surveys.router)
    app.include_router(jobs_router.router)
    app.include_router(results.router)

    @app.get("/api/params/schema", tags=["params"], response_model=ParamsSchemaOut)
    def params_schema() -> ParamsSchemaOut:
        """ProcessingParams: JSON schema with defaults and descriptions, and the parameters grouped by
        pipeline stage (common ones and advanced ones), for the parameters form."""
        return ParamsSchemaOut(json_schema=ProcessingParams.model_json_schema(),
                               defaults=ProcessingParams().model_dump(), groups=param_groups())

    storage_report = _storage_reporter(settings, store, Session)

    @app.get("/api/health", tags=["meta"], response_model=HealthOut)
    def health() -> HealthOut:
        hosts = settings.allowed_host_set()
        return HealthOut(status="ok", backend=jobs.backend, auth=bool(settings.token),
                         max_upload_mb=settings.max_upload_mb,
                         max_uncompressed_mb=round(settings.max_uncompressed_bytes / 2**20, 3),
                         allowed_hosts=sorted(hosts) if hosts is not None else ["*"],
                         storage=storage_report())


class _FrontendMount(Mount):
    """The frontend at ``/``, for every path but ``/api``'s: a request to an API path with the wrong
    method then gets the router's 405 with the path's real ``Allow`` methods (the static files
    answered ``HEAD /api/surveys/1`` with 404 and ``PUT /api/surveys/import`` with "Allow: GET,
    HEAD"), an unknown API path its JSON 404."""

    def matches(self, scope):
        path = scope.get("path", "")
        if scope.get("type") == "http" and (path == "/api" or path.startswith("/api/")):
            return Match.NONE, {}
        return super().matches(scope)


def _add_static_routes(app: FastAPI) -> None:
    """Swagger UI / ReDoc from fastapi-offline, Plotly's script, and the frontend at ``/`` (last:
    the mount catches every path the routes above do not)."""

    @app.get("/docs", include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        return HTMLResponse(DOCS_HTML)

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return HTMLResponse(REDOC_HTML)

    @app.get("/docs-static/swagger-init.js", include_in_schema=False)
    def swagger_init() -> Response:
        return Response(SWAGGER_INIT_JS, media_type="application/javascript")

    @app.get("/docs-static/{name}", include_in_schema=False)
    def docs_asset(name: str):
        d = docs_assets_dir()
        if name not in DOCS_ASSETS or d is None or not (d / name).is_file():
            raise HTTPException(404, f"{name[:100]} is not among the API documentation assets "
                                     "(the fastapi-offline package provides them)")
        return FileResponse(d / name, media_type=DOCS_ASSETS[name], headers={"Cache-Control": "public, max-age=86400"})

    @app.get("/vendor/plotly.min.js", include_in_schema=False)
    def plotly_js():
        import plotly
        path = Path(plotly.__file__).parent / "package_data" / "plotly.min.js"
        return FileResponse(path, media_type="application/javascript",
                            headers={"Cache-Control": "public, max-age=86400"})

    if FRONTEND_DIR.is_dir():
        app.router.routes.append(_FrontendMount("/", app=StaticFiles(directory=FRONTEND_DIR, html=True),
                                                name="frontend"))


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()
    settings.data_dir = Path(settings.data_dir).resolve()
    store = Store(settings.data_dir)
    Session = session_factory(settings.db_url)
    jobs = JobManager(settings, Session)
    _recover(settings, store, Session, jobs)

    app = FastAPI(title="Aerograv", version="0.1.0", lifespan=_lifespan(jobs), docs_url=None, redoc_url=None,
                  description="Airborne gravimetry processing: surveys, jobs, recognition, profiles, grids, exports.")
    app.state.settings = settings
    app.state.store = store
    app.state.Session = Session
    app.state.jobs = jobs
    app.state.cache = ResultCache()
    app.state.views = ResultCache(size=settings.recognition_views,
                                  max_bytes=int(settings.recognition_views_mb * 2**20))
    app.add_middleware(GuardMiddleware, settings=settings)
    _add_job_hooks(app, jobs, Session, store)
    _add_exception_handlers(app)
    _add_api_routes(app, settings, store, Session, jobs)
    _add_static_routes(app)
    return app
