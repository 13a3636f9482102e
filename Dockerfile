# Aerograv: the package and its command line.  `docker run IMAGE process /data/survey --out /data/out`
FROM python:3.11-slim
ENV PIP_NO_CACHE_DIR=1 PYTHONUNBUFFERED=1 AEROGRAV_DATA_DIR=/data AEROGRAV_FRONTEND_DIR=/opt/aerograv/frontend
WORKDIR /opt/aerograv
COPY pyproject.toml README.md ./
COPY app ./app
COPY frontend ./frontend
RUN pip install --upgrade pip && pip install .
VOLUME /data
EXPOSE 8000
ENTRYPOINT ["aerograv"]
CMD ["serve", "--host", "0.0.0.0", "--port", "8000"]
