"""Third hostile pass over the web server: each test is a case that was broken (a 500, a hang, a
request costing the server far more than its size) and the behaviour the fix gives."""

from __future__ import annotations

import io
import time
import zipfile
from pathlib import Path

import pytest

from .conftest import import_zip, make_tiny_survey, zip_dir


@pytest.fixture(scope="module")
def tiny_src(tmp_path_factory) -> Path:
    return make_tiny_survey(tmp_path_factory.mktemp("third") / "tiny", name="tiny")


def _zip_with(src: Path, replace: dict[str, bytes]) -> bytes:
    """The survey ``src`` zipped under ``s/``, with the files named in ``replace`` (paths relative
    to the survey directory) holding other content."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(src.rglob("*")):
            rel = p.relative_to(src).as_posix()
            if p.is_file() and rel not in replace:
                zf.write(p, "s/" + rel)
        for rel, data in replace.items():
            zf.writestr("s/" + rel, data)
    return buf.getvalue()


def test_unpaired_surrogates_in_json_are_4xx(client, tiny_src):
    """A JSON string may escape half of a UTF-16 pair (``"\\ud800"``); Python reads it as a lone
    surrogate that cannot be written as UTF-8, so the 422 echoing it, the survey.toml written with it
    and the database row all failed with a 500.  Every such request is a 4xx with a reason now, and
    nothing is stored."""
    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    before = client.get(f"/api/surveys/{sid}").json()
    s = b"\\ud800"
    cases = [("POST", "/api/surveys", b'{"name": "a' + s + b'"}'),
             ("POST", f"/api/surveys/{sid}/jobs", b'{"kind": "process", "params": {"x' + s + b'": 1}}'),
             ("POST", f"/api/surveys/{sid}/jobs", b'{"kind": "p' + s + b'"}'),
             ("POST", f"/api/surveys/{sid}/jobs", b'{"kind": "process", "params": {"em_tol": "' + s + b'"}}'),
             ("PATCH", f"/api/surveys/{sid}", b'{"survey": {"name": "' + s + b'"}}'),
             ("PATCH", f"/api/surveys/{sid}", b'{"survey": {"crs": "' + s + b'"}}'),
             ("PATCH", f"/api/surveys/{sid}", b'{"gravimeter": {"model": "GT' + s + b'"}}'),
             ("PATCH", f"/api/surveys/{sid}", b'{"gravimeter": {"tau_s": "' + s + b'"}}')]
    for method, url, body in cases:
        r = client.request(method, url, content=body, headers={"content-type": "application/json"})
        assert r.status_code == 422, (method, url, body, r.status_code, r.text[:300])
        assert r.json()["detail"], r.text
    assert [x["id"] for x in client.get("/api/surveys").json()] == [sid]
    after = client.get(f"/api/surveys/{sid}").json()
    assert after["settings"] == before["settings"] and after["last_job"] is None


def test_huge_survey_toml_refused_unread(client, tiny_src):
    """survey.toml was read whole and parsed whatever its size: a 0.3 MB zip holding a 300 MB comment
    in it cost the server 800 MB and 10 s and was stored (and read again at every job submission).
    It is refused from its size, naming survey.toml, and nothing is stored."""
    from app.io.survey import MAX_CONFIG_BYTES

    toml = (tiny_src / "survey.toml").read_bytes() + b"# " + b"x" * (MAX_CONFIG_BYTES + 10) + b"\n"
    t0 = time.monotonic()
    r = import_zip(client, _zip_with(tiny_src, {"survey.toml": toml}))
    assert r.status_code == 422, r.text[:300]
    d = r.json()["detail"]
    assert d["file"] == "survey.toml" and "MB" in d["message"], d
    assert time.monotonic() - t0 < 5.0
    assert client.get("/api/surveys").json() == []
    # a survey.toml just under the bound is read as before
    ok = (tiny_src / "survey.toml").read_bytes() + b"# " + b"x" * (MAX_CONFIG_BYTES - 1000) + b"\n"
    assert import_zip(client, _zip_with(tiny_src, {"survey.toml": ok})).status_code == 201
