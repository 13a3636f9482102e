"""Stage 6/8 diagnostic: where the EM put each anomaly level against where the state map puts it
(``identification.level_support``), checked on posteriors whose shares are known by construction."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from app.core.mjls_em import EMResult
from app.core.recognition import last_supported_iteration, level_shares, stationary_distribution
from app.pipeline.stages.identification import Identification, back_off_levels, level_support
from app.pipeline.stages.learning import Learned
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


# ----------------------------------------------------------------- the level as learned before it emptied
def _chain(high_share: float, n_r: int = 2, stay: float = 0.9) -> np.ndarray:
    """A 2-level × n_r transition matrix whose stationary distribution gives anomaly level 1
    ``high_share`` of the steps (closed form of a two-state chain: π₁ = p / (p + q) for leaving
    rates p (0 → 1) and q (1 → 0); the noise levels are entered uniformly)."""
    q = 1.0 - stay
    p = q * high_share / (1.0 - high_share)
    lvl = np.array([[1.0 - p, p], [q, 1.0 - q]])
    return np.kron(lvl, np.full((n_r, n_r), 1.0 / n_r))


def test_stationary_distribution_and_last_supported_iteration_by_closed_form():
    for share in (0.5, 0.1, 0.02, 0.001):
        np.testing.assert_allclose(level_shares(stationary_distribution(_chain(share))[None], 2),
                                   [1.0 - share, share], atol=1e-12)
    chains = [_chain(s) for s in (0.5, 0.1, 0.03, 0.021, 0.019, 0.005)]
    assert last_supported_iteration(chains, 2, 0.02) == 3
    assert last_supported_iteration(chains, 2, 0.2) == 0
    assert last_supported_iteration(chains[4:], 2, 0.02) is None
    with pytest.raises(ValueError, match="stochastic"):
        stationary_distribution(2 * _chain(0.1))


def _emptied(shares, qs, q_final=(0.004, 0.13)) -> Identification:
    """A borrowed-map identification whose m = 2 EM records (Q levels ``qs``, chains giving the
    high level ``shares`` of the steps) end with the high level at 1 % of the points while the
    map applies it to 54 %."""
    records = [{"iteration": k, "Q": list(q), "R": [1.0, 3.0], "objective": float(k), "transition": _chain(s).tolist()}
               for k, (s, q) in enumerate(zip(shares, qs))]
    em = EMResult(np.array(q_final), np.array([1.0, 3.0]), _chain(shares[-1]), np.full((1, 4), 0.25), 0.0,
                  records, False, [0], [], 3)
    learned = Learned(em, {}, [], [True], records)
    ident = Identification(2, None, learned, _recognition(0.54), 1000, [], own_recognition=_recognition(0.01))
    ident.recognition_m = 1
    return ident


def test_an_emptied_level_is_filtered_at_its_value_before_it_emptied():
    shares = [0.5, 0.1, 0.05, 0.021, 0.01, 0.001]
    qs = [(0.008, 0.07), (0.003, 0.027), (0.003, 0.021), (0.0033, 0.024), (0.0035, 0.05), (0.004, 0.13)]
    out = back_off_levels(_emptied(shares, qs), 0.02, 0.1)
    # iteration 3 is the last whose chain gives the high level >= 2 %; the low level keeps its final value
    np.testing.assert_allclose(out.learned.em.Q, [0.004, 0.024])
    assert out.recognition_m == 1 and out.recognition is not None and out.own_recognition is not None
    assert out.level_backoff["iteration"] == 3 and out.level_backoff["Q_em_mgal2"] == [0.004, 0.13]
    np.testing.assert_allclose(out.level_backoff["share_at_iteration"], [0.979, 0.021], atol=1e-9)
    rep, warnings = level_support(out, 0.02, 0.1)
    assert rep["Q_mgal2"] == [0.004, 0.13] and rep["unsupported"] == [1] and rep["backoff"]["iteration"] == 3
    assert len(warnings) == 1 and "iteration 3 (0.024 mGal²)" in warnings[0]


def test_backoff_leaves_supported_or_unrecoverable_levels_alone():
    qs = [(0.008, 0.07)] * 3
    supported = _emptied([0.5, 0.3, 0.3], qs)
    supported.own_recognition = _recognition(0.3)             # its own EM learned it on 30 %
    assert back_off_levels(supported, 0.02, 0.1) is supported
    never = back_off_levels(_emptied([0.01, 0.01, 0.01], qs), 0.02, 0.1)
    assert never.level_backoff["iteration"] is None and "no iteration" in never.level_backoff["reason"]
    np.testing.assert_allclose(never.learned.em.Q, [0.004, 0.13])
    # the earlier value would fall below the smooth level: the levels would no longer ascend
    inverted = back_off_levels(_emptied([0.5, 0.1, 0.001], [(0.008, 0.07), (0.01, 0.003), (0.004, 0.13)]), 0.02, 0.1)
    assert inverted.level_backoff["iteration"] is None and "ascend" in inverted.level_backoff["reason"]
    np.testing.assert_allclose(inverted.learned.em.Q, [0.004, 0.13])


def test_a_level_taken_back_from_the_first_iteration_is_not_learned():
    """A level whose state lost its points after the first M-step is taken back from iteration 1
    (the initial guess moved once): ``unlearned_levels`` names it below the default threshold of
    iteration 2, and never a level taken back from a later iteration or none."""
    from app.pipeline.stages.identification import unlearned_levels

    early = back_off_levels(_emptied([0.5, 0.05, 0.01, 0.005], [(0.008, 0.07), (0.003, 0.9), (0.0035, 0.3),
                                                                   (0.004, 0.13)]), 0.02, 0.1)
    assert early.level_backoff["iteration"] == 1
    np.testing.assert_allclose(early.learned.em.Q, [0.004, 0.9])
    assert unlearned_levels(early, 2) == [1]
    assert unlearned_levels(early, 1) == [] and unlearned_levels(early, 0) == []
    _, said = level_support(early, 0.02, 0.1, 2)
    assert len(said) == 1 and "full-rate likelihood's level" in said[0] and "iteration 1" in said[0]
    _, said = level_support(early, 0.02, 0.1)
    assert len(said) == 1 and "filtered with its level at EM iteration 1 (0.9 mGal²)" in said[0]
    late = back_off_levels(_emptied([0.5, 0.1, 0.05, 0.021, 0.01, 0.001],
                                    [(0.008, 0.07), (0.003, 0.027), (0.003, 0.021), (0.0033, 0.024),
                                     (0.0035, 0.05), (0.004, 0.13)]), 0.02, 0.1)
    assert late.level_backoff["iteration"] == 3 and unlearned_levels(late, 2) == []
    never = back_off_levels(_emptied([0.01, 0.01, 0.01], [(0.008, 0.07)] * 3), 0.02, 0.1)
    assert unlearned_levels(never, 2) == []


def test_lift_levels_floor_every_level_but_an_unlearned_one():
    """refine_lift_only by hand: each likelihood level raised to the EM's, except an unlearned
    level, which keeps the likelihood's level, never below the level under it."""
    from app.pipeline.stages.filtering import lifted_levels

    q, rep = lifted_levels([1e-7, 5e-6], [2e-6, 3e-4])
    np.testing.assert_array_equal(q, [2e-6, 3e-4])
    assert rep is None
    q, rep = lifted_levels([1e-7, 5e-6], [2e-6, 3e-4], [1])
    np.testing.assert_array_equal(q, [2e-6, 5e-6])
    assert rep["levels"] == [1] and rep["em_floor_mgal2"] == [3e-4] and rep["used_mgal2"] == [5e-6]
    q, rep = lifted_levels([1e-7, 1e-6], [2e-6, 3e-4], [1])     # below the smooth level: held at it
    np.testing.assert_array_equal(q, [2e-6, 2e-6])
    q, _ = lifted_levels([1e-7, 4e-5, 1e-6], [2e-6, 1e-5, 3e-4], [2])
    np.testing.assert_array_equal(q, [2e-6, 4e-5, 4e-5])
    with pytest.raises(ValueError, match="shape"):
        lifted_levels([1e-7, 4e-5], [2e-6, 1e-5, 3e-4])
