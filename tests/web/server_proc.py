"""A real ``aerograv serve`` in a subprocess on a free loopback port, with its memory readable.

Shared by ``tests/web/test_hostile.py`` and ``benchmarks/bench_soak.py``: the hostile cases that
are about memory or concurrency need the server as its own process (its peak RSS from
``/proc/<pid>/status`` VmHWM, resettable through ``/proc/<pid>/clear_refs``) and real sockets.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FAKE_ENTRY = "tests.web.fake_pipeline:process_survey"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _status_kb(pid: int, key: str) -> int:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise KeyError(key)


class ServerProcess:
    """``python -m app.cli serve`` with ``AEROGRAV_*`` settings from ``env``; a context manager."""

    def __init__(self, data_dir: Path, env: dict[str, str] | None = None, fake_pipeline: bool = True,
                 log_path: Path | None = None):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.data_dir = Path(data_dir)
        self.env = {**os.environ, "AEROGRAV_DATA_DIR": str(self.data_dir),
                    "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
        if fake_pipeline:
            self.env.update(AEROGRAV_PIPELINE_ENTRY=FAKE_ENTRY, AEROGRAV_FAKE_DELAY_S=self.env.get("AEROGRAV_FAKE_DELAY_S", "0.02"))
        self.env.update(env or {})
        self.log_path = log_path or (self.data_dir.parent / f"server-{self.port}.log")
        self.proc: subprocess.Popen | None = None

    def start(self, timeout: float = 60.0) -> ServerProcess:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen([sys.executable, "-m", "app.cli", "serve", "--host", "127.0.0.1", "--port",
                                      str(self.port)], cwd=ROOT, env=self.env, stdout=self._log,
                                     stderr=subprocess.STDOUT)
        t_end = time.monotonic() + timeout
        while True:
            try:
                if self.get("/api/health")[0] == 200:
                    return self
            except OSError:
                pass
            if self.proc.poll() is not None or time.monotonic() > t_end:
                self.stop()
                raise RuntimeError(f"the server did not start: {self.log_path.read_text()[-3000:]}")
            time.sleep(0.1)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        if getattr(self, "_log", None):
            self._log.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # -- memory ------------------------------------------------------------
    @property
    def pid(self) -> int:
        return self.proc.pid

    def rss_mb(self) -> float:
        return _status_kb(self.pid, "VmRSS") / 1024

    def peak_mb(self) -> float:
        return _status_kb(self.pid, "VmHWM") / 1024

    def reset_peak(self) -> None:
        """Reset VmHWM to the current RSS (Linux: ``echo 5 > /proc/PID/clear_refs``)."""
        with open(f"/proc/{self.pid}/clear_refs", "w") as fh:
            fh.write("5")

    # -- HTTP ----------------------------------------------------------------
    def request(self, method: str, path: str, body: bytes | None = None, headers: dict | None = None,
                timeout: float = 60.0) -> tuple[int, bytes, dict]:
        req = urllib.request.Request(self.url + path, data=body, method=method, headers=headers or {})
        try:
            with urllib.request.urlopen(req, timeout=timeout) as r:
                return r.status, r.read(), dict(r.headers)
        except urllib.error.HTTPError as e:
            return e.code, e.read(), dict(e.headers)

    def get(self, path: str, **kw) -> tuple[int, bytes, dict]:
        return self.request("GET", path, **kw)

    def json(self, method: str, path: str, obj=None, **kw) -> tuple[int, object]:
        body = None if obj is None else json.dumps(obj).encode()
        st, raw, _ = self.request(method, path, body, {"Content-Type": "application/json"} if body else {}, **kw)
        try:
            return st, json.loads(raw) if raw else None
        except ValueError:
            return st, raw.decode(errors="replace")

    def post_files(self, path: str, files: dict[str, tuple[str, bytes]], fields: dict[str, str] | None = None,
                   **kw) -> tuple[int, object]:
        body, ctype = multipart(files, fields)
        st, raw, _ = self.request("POST", path, body, {"Content-Type": ctype}, **kw)
        try:
            return st, json.loads(raw) if raw else None
        except ValueError:
            return st, raw.decode(errors="replace")


def multipart(files: dict[str, tuple[str, bytes]], fields: dict[str, str] | None = None) -> tuple[bytes, str]:
    """Encode ``{field: (filename, bytes)}`` and plain ``fields`` as multipart/form-data."""
    boundary = "aerograv" + os.urandom(8).hex()
    parts = []
    for k, v in (fields or {}).items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n'.encode()
                     + v.encode() + b"\r\n")
    for k, (fname, data) in files.items():
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"; filename="{fname}"\r\n'
                     f"Content-Type: application/octet-stream\r\n\r\n".encode() + data + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


def inflated_survey_zip(survey_root: Path, csv_mb: float, member: str = "flights/f1/gnss.csv") -> bytes:
    """The survey at ``survey_root`` zipped, with ``member`` padded to ``csv_mb`` MB by repeating its
    last row (a valid-looking survey whose CSV deflates ~300:1: the import-memory attack)."""
    import io
    import zipfile

    root = Path(survey_root)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for p in sorted(root.rglob("*")):
            if not p.is_file():
                continue
            arc = p.relative_to(root).as_posix()
            if arc != member:
                zf.write(p, arc)
                continue
            data = p.read_bytes()
            last = data.rstrip(b"\n").rsplit(b"\n", 1)[-1] + b"\n"
            block = last * max(1, (1 << 20) // len(last))
            with zf.open(arc, "w", force_zip64=True) as fh:
                fh.write(data)
                written = len(data)
                while written < csv_mb * (1 << 20):
                    fh.write(block)
                    written += len(block)
    return buf.getvalue()
