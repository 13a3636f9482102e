"""Follow-ups of the attacker audit: invisible-only names, warnings of an upload shown to the client,
the recognition view cached, the /tracks and /qc listings paginated."""

from __future__ import annotations

from pathlib import Path

import pytest

from .conftest import import_zip, make_tiny_survey, zip_dir


@pytest.fixture(scope="module")
def tiny_src(tmp_path_factory) -> Path:
    return make_tiny_survey(tmp_path_factory.mktemp("followups") / "tiny", name="tiny")


# ---------------------------------------------------------------- 1. names with nothing visible
@pytest.mark.parametrize("name", ["\u200b", "\u2060\ufeff", "\u0301\u0308", "\u3000"])
def test_invisible_survey_name_refused_naming_the_field(client, name):
    r = client.post("/api/surveys", json={"name": name})
    assert r.status_code == 422, r.text
    err = r.json()["detail"][0]
    assert err["loc"][-1] == "name"
    assert "visible" in err["msg"] or "empty" in err["msg"]
    assert client.get("/api/surveys").json() == []


def test_names_in_other_scripts_accepted(client):
    for name in ("Съёмка Камчатка", "航空重力測量", "Café Müller-Øst"):
        r = client.post("/api/surveys", json={"name": name})
        assert r.status_code == 201, r.text
        assert r.json()["name"] == name


def test_patch_invisible_model_refused(client, tiny_src):
    sid = import_zip(client, zip_dir(tiny_src)).json()["id"]
    r = client.patch(f"/api/surveys/{sid}", json={"gravimeter": {"model": "\u200b\u2060"}})
    assert r.status_code == 422, r.text
    assert r.json()["detail"][0]["loc"] == ["gravimeter", "model"]
    r = client.patch(f"/api/surveys/{sid}", json={"survey": {"name": "\ufeff"}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["survey", "name"]
    assert client.get(f"/api/surveys/{sid}").json()["settings"]["gravimeter"]["model"] == "GT-1A"


# ---------------------------------------------------------------- 2. an upload's warnings reach the client
GARBAGE = {"gravimeter": ("g.csv", b"\x00\x01garbage\xff", "text/csv"),
           "gnss": ("n.csv", b"nonsense,,\n1,2\n", "text/csv")}


def test_unused_garbage_flight_upload_says_so(client, tiny_src):
    imp = import_zip(client, zip_dir(tiny_src))
    assert imp.status_code == 201 and imp.json()["warnings"] == []
    sid = imp.json()["id"]
    r = client.post(f"/api/surveys/{sid}/flights", data={"flight": "junk"}, files=GARBAGE)
    assert r.status_code == 201, r.text
    body = r.json()
    assert any(w.startswith("flight junk is not read") and "flights/junk/gnss.csv" in w for w in body["warnings"])
    data_dir = str(client.app.state.settings.data_dir)
    assert not any(data_dir in w or "/tmp" in w for w in body["warnings"])    # no server path
    assert body["flights"] == ["f1"]             # stored, left out of the survey: what the warning says
    # a plain GET carries no warnings field (the upload's answer does)
    assert "warnings" not in client.get(f"/api/surveys/{sid}").json()
    ok = client.post(f"/api/surveys/{sid}/flights", data={"flight": "f1"}, files={
        "gravimeter": ("g.csv", (tiny_src / "flights/f1/gravimeter.csv").read_bytes(), "text/csv"),
        "gnss": ("n.csv", (tiny_src / "flights/f1/gnss.csv").read_bytes(), "text/csv")})
    assert ok.status_code == 201
    assert any("flight junk" in w for w in ok.json()["warnings"])   # still there: every flight's warnings


def test_import_with_unused_garbage_flight_says_so(client, tiny_src):
    from .conftest import zip_with
    data = zip_with(tiny_src, {"flights/ferry/gravimeter.csv": b"not,a\nfile", "flights/ferry/gnss.csv": b"\xff\xfe"})
    r = import_zip(client, data)
    assert r.status_code == 201, r.text
    assert any(w.startswith("flight ferry is not read") for w in r.json()["warnings"])


def test_reader_notes_bounded_and_relative(tmp_path):
    from types import SimpleNamespace

    from app.web.services import MAX_UPLOAD_WARNINGS, reader_notes
    root = tmp_path / "staging" / "survey"
    root.mkdir(parents=True)
    notes = [f"file {root}/flights/f{i}/gnss.csv: odd" for i in range(MAX_UPLOAD_WARNINGS + 5)] + ["x" * 5000]
    out = reader_notes(SimpleNamespace(notes=notes), root)
    assert len(out) == MAX_UPLOAD_WARNINGS + 1 and out[0] == "file flights/f0/gnss.csv: odd"
    assert out[-1].startswith("… and 6 more warnings")
    assert reader_notes(SimpleNamespace(notes=["y" * 5000]), root)[0].endswith("(5,000 characters)")
    assert reader_notes(object(), root) == []
