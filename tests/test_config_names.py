"""Names and labels must show something: invisible-only text is refused (app.config.check_name / check_label)."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from app.config import SurveyConfig, check_label, check_name, has_visible

INVISIBLE = ["\u200b", "\u2060\ufeff", "\u0301", "\u0301\u0308\u20dd", "\u3000", "\u00a0\u2003\u3000", "\u00ad",
             "\u200c\u200d", "\u180e", "\u034f\u17b4"]
VISIBLE = ["Съёмка «Камчатка-2024»", "航空重力測量", "Café Müller-Øst", "e\u0301", "Ελληνικά", "تجربة", "1", "#",
           "€", "a\u200b", "\u3000x\u3000", "GT-1A (2A)"]


@pytest.mark.parametrize("value", INVISIBLE)
def test_invisible_only_names_refused(value):
    with pytest.raises(ValueError, match="survey name (has no visible character|is empty)") as e:
        check_name(value, "survey name")
    assert "U+" in str(e.value)          # the characters are named by code point


@pytest.mark.parametrize("value", INVISIBLE)
def test_invisible_only_labels_refused(value):
    with pytest.raises(ValueError, match="model has no visible character"):
        check_label(value, "model")


@pytest.mark.parametrize("value", VISIBLE)
def test_names_in_any_script_pass(value):
    assert has_visible(value)
    assert check_name(value) == value
    assert check_label(value) == value


def test_empty_label_still_allowed_empty_name_not():
    assert check_label("") == ""
    with pytest.raises(ValueError, match="is empty"):
        check_name("")


def test_survey_toml_fields_name_the_key():
    with pytest.raises(ValidationError) as e:
        SurveyConfig.model_validate({"survey": {"name": "\u2060\ufeff"}})
    assert e.value.errors()[0]["loc"] == ("survey", "name")
    with pytest.raises(ValidationError) as e:
        SurveyConfig.model_validate({"gravimeter": {"model": "\u200b\u200b"}})
    assert e.value.errors()[0]["loc"] == ("gravimeter", "model")
    assert SurveyConfig.model_validate({"survey": {"name": "Съёмка"}, "gravimeter": {"model": "重力計"}})
