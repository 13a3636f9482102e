"""``aerograv serve``: run the web application with uvicorn.

``serve(host, port, bootstrap)``: when ``bootstrap`` is a survey directory and the
store holds no survey yet, the survey is imported (validated, copied into the data
directory) and a ``process`` job is started, so a fresh ``make serve`` shows a
processed sample survey after a short wait.
"""

from __future__ import annotations

import logging
from pathlib import Path

from sqlalchemy import func, select

from .db import Survey
from .main import create_app
from .services import import_survey_dir, start_job
from .settings import Settings

log = logging.getLogger("aerograv.web.serve")


def bootstrap_store(app, survey_dir: str | Path) -> int | None:
    """Import ``survey_dir`` and start a process job when the store is empty; returns the job id."""
    from app.io.survey import read_survey

    st = app.state
    with st.Session() as db:
        if db.scalar(select(func.count()).select_from(Survey)):
            log.info("store not empty: bootstrap of %s skipped", survey_dir)
            return None
        s = import_survey_dir(db, st.store, read_survey, Path(survey_dir))
        job = start_job(db, st.store, st.jobs, s, "process", {})
        log.info("bootstrap: imported %s as survey %d, job %d started", survey_dir, s.id, job.id)
        return job.id


def serve(host: str = "127.0.0.1", port: int = 8000, bootstrap: str | None = None,
          settings: Settings | None = None) -> None:
    import uvicorn

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    settings = settings or Settings()
    if settings.bind_host is None:  # the default Host allow-list is the bind address and localhost
        settings.bind_host = host
    app = create_app(settings)
    if bootstrap:
        bootstrap_store(app, bootstrap)
    print(f"Aerograv: http://{host}:{port}/  (API docs at /docs, data in {app.state.settings.data_dir})", flush=True)
    uvicorn.run(app, host=host, port=port, log_level="info")


if __name__ == "__main__":  # python -m app.web.serve [--host] [--port] [--bootstrap DIR]
    import argparse

    ap = argparse.ArgumentParser(description="Aerograv web server")
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--port", type=int, default=8000)
    ap.add_argument("--bootstrap", default=None)
    a = ap.parse_args()
    serve(a.host, a.port, a.bootstrap)
