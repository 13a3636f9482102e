"""Every JSON endpoint declares its response model (the OpenAPI document describes what it returns)."""

from __future__ import annotations

import pytest
from fastapi.routing import APIRoute
from pydantic import ValidationError

from app.web.schemas import GridOut, ProfileOut

#: endpoints that answer with a file or no body
NOT_JSON = {("GET", "/api/surveys/{survey_id}/export"), ("DELETE", "/api/surveys/{survey_id}")}


def test_every_api_route_declares_a_response_model(client):
    missing = []
    for route in client.app.routes:
        if not isinstance(route, APIRoute) or not route.path.startswith("/api"):
            continue
        for method in route.methods:
            if (method, route.path) not in NOT_JSON and route.response_model is None:
                missing.append(f"{method} {route.path}")
    assert not missing, missing


def test_response_models_refuse_undeclared_fields():
    """A key added to a response without its declaration fails instead of vanishing."""
    body = dict(survey_id=1, result_id=2, easting_km=[0.0], northing_km=[0.0], dg=[[1.0]])
    GridOut(**body)
    with pytest.raises(ValidationError):
        GridOut(**body, not_a_declared_field="x")


def test_non_finite_values_are_written_as_null():
    p = ProfileOut(survey_id=1, line="L", flight="F", kind="main", n_total=2, step=1, z_lowpass_s=30.0,
                   time=[0.0, 0.1], distance_km=[0.0, 0.01], z_lowpassed=[float("nan"), 1.0], dg=[None, 2.0],
                   dg_std=[float("inf"), 1.0], dg_stationary=[1.0, 1.0], dg_fir=[1.0, 1.0], state=[None, 1])
    text = p.model_dump_json()
    assert '"z_lowpassed":[null,1.0]' in text and '"dg_std":[null,1.0]' in text and "NaN" not in text
