"""The processing parameters grouped by pipeline stage for the form (app.config.param_groups): every
parameter in exactly one group, the listed groups naming only real parameters, and a parameter added
later landing by its name's prefix, else in "other" — never left out."""

from __future__ import annotations

from pydantic import Field

from app.config import PARAM_GROUPS, ProcessingParams, param_groups


def _members(groups):
    return [n for g in groups for n in g["common"] + g["advanced"]]


def test_every_parameter_in_exactly_one_group():
    names = _members(param_groups())
    assert sorted(names) == sorted(ProcessingParams.model_fields) and len(names) == len(set(names))
    listed = [n for _, _, common, advanced in PARAM_GROUPS for n in common + advanced]
    assert len(listed) == len(set(listed)), "a parameter listed in two groups"
    assert set(listed) <= set(ProcessingParams.model_fields), set(listed) - set(ProcessingParams.model_fields)
    # the pipeline's stages in their order, each with its common parameters shown
    groups = param_groups()
    assert [g["key"] for g in groups][:3] == ["measurement", "noise", "order"]
    assert all(g["common"] for g in groups)
    assert "nlmeans_h_per_km" in next(g for g in groups if g["key"] == "recognition")["common"]


def test_a_parameter_added_later_lands_somewhere():
    class Later(ProcessingParams):
        noise_new_knob: float = Field(1.0, description="a new noise-model setting")
        leveling_new_test: bool = True
        something_else: int = 3

    groups = {g["key"]: g for g in param_groups(Later)}
    assert "noise_new_knob" in groups["noise"]["advanced"]
    assert "leveling_new_test" in groups["leveling"]["advanced"]
    assert groups["other"]["advanced"] == ["something_else"]
    assert sorted(_members(groups.values())) == sorted(Later.model_fields)
