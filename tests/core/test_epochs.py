"""Missing epochs of a uniformly clocked record (app.core.epochs): put back on the clock and
filled; analytic cases."""

import numpy as np
import pytest

from app.core.epochs import fill_at, uniform_epochs


def test_missing_epochs_are_put_back_and_nothing_else():
    t_full = 1000.0 + 0.5 * np.arange(40)
    drop = [5, 12, 13, 30]                              # one, then two in a row, then one
    t = np.delete(t_full, drop)
    t_new, ins = uniform_epochs(t, max_step_s=1.5)
    np.testing.assert_allclose(t_new, t_full, atol=1e-12)
    np.testing.assert_array_equal(np.flatnonzero(ins), drop)
    # a step longer than allowed (three missing: 2.0 s) stays a gap
    t3 = np.delete(t_full, [20, 21, 22])
    t_new, ins = uniform_epochs(t3, max_step_s=1.5)
    np.testing.assert_array_equal(t_new, t3)
    assert not ins.any()
    # a step off the clock (1.3 median steps) is not a missing epoch
    t_odd = np.concatenate([t_full[:10], t_full[10:] + 0.15])
    t_new, ins = uniform_epochs(t_odd, max_step_s=5.0)
    np.testing.assert_array_equal(t_new, t_odd)
    with pytest.raises(ValueError):
        uniform_epochs(t_full[::-1], 1.0)


def test_fill_is_the_cubic_through_the_record_and_keeps_recorded_values():
    """A not-a-knot cubic spline reproduces a cubic polynomial exactly; recorded values are kept
    bit for bit; no value is made across a record gap (between runs)."""
    t_full = 0.5 * np.arange(60)
    y_full = 2.0 + 0.3 * t_full - 0.04 * t_full ** 2 + 0.001 * t_full ** 3
    keep = np.ones(60, bool)
    keep[[7, 33, 34]] = False
    t, y = t_full[keep], y_full[keep]
    t_new, ins = uniform_epochs(t, 2.0)
    got = fill_at(t, y, t_new, ins)
    np.testing.assert_allclose(got, y_full, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got[~ins], y)
    # two runs: the epoch missing inside the first is filled from it alone (a linear run
    # extrapolated by the other would not be)
    y_two = np.where(t < 20.0, 1.0 + t, 100.0)
    got = fill_at(t, y_two, t_new, ins, runs=[(0, int(np.sum(t < 20.0))), (int(np.sum(t < 20.0)), t.size)])
    assert got[7] == pytest.approx(1.0 + 3.5)
    with pytest.raises(ValueError):
        fill_at(t, y[:-1], t_new, ins)
