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
