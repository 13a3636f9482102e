"""The lines an identification leaves out are said in one warning per order, grouped by reason,
with every line named once (a survey of short lines had one warning per line and per order)."""

from __future__ import annotations

import numpy as np

from app.config import SurveyConfig
from app.pipeline.stages.identification import skipped_lines_warning
from app.pipeline.stages.lines import LineData
from app.pipeline.stages.regularization import regularize_lines

DT_S = 0.5
SPEED_MS = 60.0


def _line(name: str, duration_s: float, rng) -> LineData:
    n = int(duration_s / DT_S)
    t = DT_S * np.arange(n)
    z = 10.0 * np.sin(2 * np.pi * t / 300.0) + rng.normal(0.0, 50.0, n)
    return LineData(name, "F1", "main", None, slice(0, n), t, np.zeros(n), np.zeros(n), np.full(n, 500.0),
                    SPEED_MS * t / 1000.0, np.zeros(n), z, SPEED_MS)


def _config() -> SurveyConfig:
    return SurveyConfig.model_validate({"survey": {"name": "t"}, "gravimeter": {"tau_s": 0.0}})


def test_regularization_reasons_are_grouped_and_every_line_named_once():
    rng = np.random.default_rng(3)
    # four long lines are identified; three short ones fall below the MA order's points
    lines = [_line(f"L{k}", 1800.0, rng) for k in range(4)] + [_line(f"S{k}", 160.0, rng) for k in range(3)]
    reg = regularize_lines(lines, _config(), DT_S, 2)
    assert set(reg.skipped) == {"S0", "S1", "S2"}, reg.skipped
    text = skipped_lines_warning(reg.skipped, len(lines), 2)
    assert text.startswith("order m = 2: 3 of 7 lines not identified")
    for ln, why in reg.skipped.items():
        assert text.count(f"{ln} (") == 1                 # named once, with its own point count
        n_points = why.split()[1]
        assert f"{ln} ({n_points})" in text
    assert text.count("too few decimated points") == 1    # one group, not one per line


def test_other_reasons_keep_their_text():
    text = skipped_lines_warning({"A": "only 4 decimated points (need 9)",
                                  "T1": "line too short for regularization: no stretch of 265 samples",
                                  "T2": "line too short for regularization: no stretch of 265 samples"}, 10, 1)
    assert "order m = 1: 3 of 10 lines not identified" in text
    assert "too few decimated points (need 9): A (4)" in text
    assert "line too short for regularization: no stretch of 265 samples: T1, T2" in text
