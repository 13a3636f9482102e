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


def test_fill_error_is_nil_for_a_smooth_record_and_grows_with_the_hole():
    """Heights on a cubic trajectory: the spline bridge is exact, so the low-pass does not move.
    A vertical motion with 0.2–0.9 Hz content (turbulence): the bridge misses what happens inside
    the hole, more the longer it is."""
    from app.core.baselines import fir_kernel
    from app.core.epochs import fill_error_mgal

    dt = 0.5
    t = 1000.0 + dt * np.arange(4000)
    x = t - t[0]
    h_smooth = 300.0 + 2.0 * x - 1e-3 * x ** 2 + 1e-7 * x ** 3
    k = fir_kernel(dt, 100.0)
    assert fill_error_mgal(t, h_smooth, 4, k, derivative=True) < 1e-6
    rng = np.random.default_rng(2)
    w = rng.uniform(2 * np.pi * 0.2, 2 * np.pi * 0.9, 30)
    ph = rng.uniform(0, 2 * np.pi, 30)
    h_turb = h_smooth + 0.2 * np.sin(np.outer(x, w) + ph).sum(axis=1)
    errs = [fill_error_mgal(t, h_turb, m, k, derivative=True) for m in (1, 2, 4, 8)]
    assert all(b > a for a, b in zip(errs, errs[1:]))
    assert errs[-1] > 10 * errs[0]
    with pytest.raises(ValueError):
        fill_error_mgal(t, h_turb, 0, k, derivative=True)
    assert np.isnan(fill_error_mgal(t[:20], h_turb[:20], 4, k, derivative=True))


def test_fill_error_of_samples_themselves():
    """A gravimeter's record (``acceleration``): an acceleration cubic in time is bridged
    exactly; for a sine the not-a-knot spline's miss at a missing sample goes as (ωδ)⁴ and
    the peak of a 100 s low-pass kernel as δ, so halving the rate multiplies the cost by
    about 2⁵ — why an 18 Hz meter's dropped sample is bridged and a 2 Hz one's is not."""
    from app.core.baselines import fir_kernel
    from app.core.epochs import fill_error_mgal

    def cost(dt, y_of_t, m=1):
        t = 500.0 + dt * np.arange(int(600.0 / dt))
        return fill_error_mgal(t, y_of_t(t - t[0]), m, fir_kernel(dt, 100.0), derivative=True, acceleration=True)

    assert cost(1 / 18.24, lambda x: 9.8 + 1e-3 * x - 1e-5 * x ** 2 + 1e-8 * x ** 3) < 1e-9
    sine = lambda x: 0.4 * np.sin(2 * np.pi * 0.25 * x)  # noqa: E731  (0.4 m/s², 4 s period)
    fine, coarse = cost(0.05, sine), cost(0.1, sine)
    assert 2 ** 4.5 < coarse / fine < 2 ** 5.5, coarse / fine
    assert cost(0.1, sine, 2) > cost(0.1, sine, 1)


def test_run_bounds_against_a_loop():
    """Runs of ok epochs, also cut where the clock jumps, against a plain loop over the epochs."""
    from app.core.epochs import run_bounds

    rng = np.random.default_rng(6)
    for _ in range(50):
        n = int(rng.integers(1, 60))
        ok = rng.random(n) < 0.7
        t = np.cumsum(np.where(rng.random(n) < 0.1, 5.0, 1.0))
        want, start = [], None
        for i in range(n):
            jump = i > 0 and t[i] - t[i - 1] > 1.5
            if start is not None and (not ok[i] or jump):
                want.append((start, i))
                start = None
            if ok[i] and start is None:
                start = i
        if start is not None:
            want.append((start, n))
        assert run_bounds(ok, t) == want
        assert run_bounds(ok) == [(a, b) for a, b in
                                  zip(*[np.flatnonzero(np.diff(np.r_[0, ok.astype(int), 0]) == s) for s in (1, -1)])]
