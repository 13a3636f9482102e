# Aerograv: the package and its command line.  `docker run IMAGE process /data/survey --out /data/out`
# Runs as the unprivileged user `aerograv` (uid 10001; /data belongs to it).  The health check
# asks /api/health with the image's own Python (slim images have no curl or wget); it applies
# to `serve` (the default command) on port 8000.  Behind a proxy or a published port, set
# AEROGRAV_ALLOWED_HOSTS to the names browsers use (any Host is accepted on 0.0.0.0 otherwise).
FROM python:3.11-slim
ENV PIP_NO_CACHE_DIR=1 PYTHONUNBUFFERED=1 AEROGRAV_DATA_DIR=/data AEROGRAV_FRONTEND_DIR=/opt/aerograv/frontend
WORKDIR /opt/aerograv
COPY pyproject.toml README.md ./
COPY app ./app
COPY frontend ./frontend
RUN pip install --upgrade pip && pip install . \
    && useradd --system --uid 10001 --user-group --no-create-home --home-dir /data --shell /usr/sbin/nologin aerograv \
    && mkdir -p /data && chown aerograv:aerograv /data
USER aerograv
VOLUME /data
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD ["python", "-c", "import sys, urllib.request; r = urllib.request.urlopen('http://127.0.0.1:8000/api/health', timeout=4); sys.exit(0 if r.status == 200 else 1)"]
ENTRYPOINT ["aerograv"]
CMD ["serve", "--host", "0.0.0.0", "--port", "8000"]
