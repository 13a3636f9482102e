"""Stage 6/8 diagnostic: where the EM put each anomaly level against where the state map puts it
(``identification.level_support``), checked on posteriors whose shares are known by construction."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from app.core.recognition import level_shares
from app.pipeline.stages.identification import Identification, level_support
from app.pipeline.stages.recognition import Recognition


def _recognition(high_share: float, n: int = 1000, n_r: int = 2) -> Recognition:
    """Posteriors over 2 anomaly levels × n_r noise levels whose high level holds ``high_share`` of
    the points' mass: the first round(high_share·n) points certain of (high, noise 0), the rest
    certain of (low, noise 1)."""
    k = int(round(high_share * n))
    probs = np.zeros((n, 2 * n_r))
    probs[:k, n_r] = 1.0          # state i·n_r + j = (1, 0)
    probs[k:, 1] = 1.0            # (0, 1)
    table = pd.DataFrame({f"p_{i}": probs[:, i] for i in range(2 * n_r)})
    return Recognition(table, 2, n_r)


def _ident(own: Recognition | None, used: Recognition, converged: bool = False) -> Identification:
    em = SimpleNamespace(Q=np.array([0.004, 0.13]), converged=converged)
    ident = Identification(2, None, SimpleNamespace(em=em), used, 1000, [], own_recognition=own)
    if own is not None:
        ident.recognition_m = 1
    return ident


def test_level_shares_by_hand():
    # two points, 2 levels x 2 noise levels: level 1 holds 0.3 + 0.1 of the first point, 0.5 of the second
    probs = np.array([[0.4, 0.2, 0.3, 0.1], [0.25, 0.25, 0.5, 0.0]])
    np.testing.assert_allclose(level_shares(probs, 2), [(0.6 + 0.5) / 2, (0.4 + 0.5) / 2])
    np.testing.assert_allclose(level_shares(probs, 1), probs.mean(axis=0))
    with pytest.raises(ValueError, match="whole number of levels"):
        level_shares(probs, 3)
    with pytest.raises(ValueError, match="non-negative"):
        level_shares(-probs, 2)


def test_a_level_the_em_left_empty_but_the_map_applies_is_reported():
    rep, warnings = level_support(_ident(_recognition(0.01), _recognition(0.54)), 0.02, 0.1)
    np.testing.assert_allclose(rep["share_em"], [0.99, 0.01])
    np.testing.assert_allclose(rep["share_map"], [0.46, 0.54])
    assert rep["unsupported"] == [1] and rep["map_from_m"] == 1 and rep["em_converged"] is False
    assert len(warnings) == 1 and "0.13 mGal²" in warnings[0] and "54 %" in warnings[0]
    assert "did not converge" in warnings[0]


@pytest.mark.parametrize("own, used", [(0.01, 0.05),     # the map uses it little too
                                       (0.30, 0.75),     # the EM learned it on 30 % of the points
                                       (None, 0.01)])    # one order's own map: the shares agree
def test_no_warning_where_the_level_is_learned_or_little_used(own, used):
    ident = _ident(None if own is None else _recognition(own), _recognition(used), converged=True)
    rep, warnings = level_support(ident, 0.02, 0.1)
    assert rep["unsupported"] == [] and warnings == []
    if own is None:
        assert rep["share_em"] == rep["share_map"] and rep["map_from_m"] == 2


def test_points_without_finite_posteriors_are_left_out_and_never_stop_the_processing():
    used = _recognition(0.54)
    used.table.iloc[:10] = np.nan                     # 10 points of the first 540 (all high) unusable
    rep, warnings = level_support(_ident(_recognition(0.01), used), 0.02, 0.1)
    np.testing.assert_allclose(rep["share_map"], [460 / 990, 530 / 990])
    assert rep["unsupported"] == [1] and len(warnings) == 1
    empty = _recognition(0.5)
    empty.table.iloc[:] = np.nan
    rep, warnings = level_support(_ident(_recognition(0.01), empty), 0.02, 0.1)
    assert rep["share_map"] is None and rep["unsupported"] == [] and warnings == []
