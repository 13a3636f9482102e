"""app.core.clock: a drift and steps of the gravimeter's clock from windowed time offsets,
against offsets drawn from a known clock."""

import numpy as np
import pytest

from app.core.clock import ClockModel, clock_offset_s, fit_clock, retime_stamps_s

T = np.arange(15) * 300.0 + 10_000.0     # 15 windows of 300 s (1.2 h)
SE = 0.003                               # a window's offset: ±3 ms


def _offsets(rng, drift=0.0, steps=(), se=SE):
    y = 0.05 + drift * (T - T.mean())
    for at, size in steps:
        y = y + np.where(T > at, size, 0.0)
    return y + rng.normal(0.0, se, T.size)


def test_a_constant_clock_is_left_alone():
    """Offsets that scatter by their standard error about a constant: over 400 draws a drift or a
    step (at any of five gaps) is kept on at most 1 % (the terms' level is 1e-3 each; the search
    over the candidates and the size floor make it so), and the constant is the weighted mean."""
    rng = np.random.default_rng(0)
    gaps = T[[3, 6, 7, 10, 12]] + 150.0
    kept = 0
    for _ in range(400):
        y = _offsets(rng)
        m = fit_clock(T, y, np.full(T.size, SE), gaps)
        kept += m.changes
        if not m.changes:
            assert m.offset_s == pytest.approx(y.mean(), abs=1e-12)
    assert kept <= 4


def test_a_drift_is_found_and_sized():
    """20 ppm over 1.2 h (84 ms): found on every draw, its rate within 3 standard errors of the
    least-squares slope's (σ/√Σ(t − t̄)²), and no step taken for it."""
    rng = np.random.default_rng(1)
    sd = SE / np.sqrt(np.sum((T - T.mean()) ** 2))
    for _ in range(50):
        m = fit_clock(T, _offsets(rng, drift=-20e-6), np.full(T.size, SE), [T[5] + 150.0])
        assert m.drift_s_per_s == pytest.approx(-20e-6, abs=3 * sd)
        assert m.steps == ()


def test_a_jump_at_a_gap_is_found_and_not_where_there_is_no_gap():
    """The clock set forward by 0.2 s between windows 7 and 8, at a gap of the record: one step of
    −0.2 s (±3 ms) there, no drift.  Offered only a gap elsewhere, no step can stand in for it
    there on both sides' data: what is kept leaves the offsets' residual far above their
    scatter, which is what the pipeline's acceptance test then judges."""
    rng = np.random.default_rng(2)
    at = 0.5 * (T[7] + T[8])
    y = _offsets(rng, steps=[(at, -0.2)])
    m = fit_clock(T, y, np.full(T.size, SE), [T[2] + 150.0, at, T[11] + 150.0])
    assert len(m.steps) == 1 and m.steps[0][0] == at
    assert m.steps[0][1] == pytest.approx(-0.2, abs=0.003) and m.drift_s_per_s == 0.0
    m2 = fit_clock(T, y, np.full(T.size, SE), [T[2] + 150.0])
    assert not any(x == at for x, _ in m2.steps)
    resid = y - clock_offset_s(m2, T)
    assert np.std(resid) > 10 * SE


def test_one_window_off_makes_no_step_pair():
    """One window 60 ms off (a wrong correlation peak): a step needs two windows on either side
    of it and of every other step, so no pair of steps isolates the window."""
    rng = np.random.default_rng(3)
    y = _offsets(rng)
    y[6] += 0.06
    m = fit_clock(T, y, np.full(T.size, SE), T[:-1] + 150.0)
    assert len(m.steps) <= 1


def test_retimed_stamps_are_the_true_times():
    """Stamps of a clock running 50 ppm fast and set forward by 0.3 s: re-timed by the clock that
    made them, they are the true times plus one constant (left to the flight's offset), to
    within the drift over the jump (50 ppm of 0.3 s: the drift is evaluated on the stamps)."""
    t_true = np.arange(0.0, 4000.0, 0.05)
    jump_at = 2000.0
    stamps = t_true + 50e-6 * t_true + np.where(t_true >= jump_at, 0.3, 0.0)
    gap_mid = 0.5 * (stamps[t_true < jump_at][-1] + stamps[t_true >= jump_at][0])
    model = ClockModel(0.0, -50e-6 / (1 + 50e-6), 0.0, ((gap_mid, -0.3),))
    out = retime_stamps_s(stamps, model, 1000.0)
    d = out - t_true
    assert np.ptp(d) < 20e-6


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="one length"):
        fit_clock(T, T[:-1], np.full(T.size, SE))
    with pytest.raises(ValueError, match="positive"):
        fit_clock(T, T, np.zeros(T.size))
    with pytest.raises(ValueError, match="increasing"):
        fit_clock(T[::-1], T, np.full(T.size, SE))
    with pytest.raises(ValueError, match="finite"):
        fit_clock(T, np.full(T.size, np.nan), np.full(T.size, SE))


def test_a_jump_snaps_to_the_sampling_clock():
    """A sensor sampling every 0.05 s whose logger clock was set 0.3 s forward: the stamps' gap is
    n·0.05 + 0.3 s for the n steps of true time across it.  An estimate 4 ms off snaps to 0.3 s
    exactly; one half a step off (a sensor that restarted) does not snap; a gap shorter than
    the jump plus one step cannot hold it."""
    from app.core.clock import snap_step_s

    step, jump = 0.05, 0.3
    for n in (1, 2, 7):
        gap = n * step + jump
        assert snap_step_s(-(jump - 0.004), gap, step, 0.0125) == pytest.approx(-jump, abs=1e-12)
        assert snap_step_s(-(jump + 0.025), gap, step, 0.0125) is None
    assert snap_step_s(-0.3, 0.28, step, 0.0125) is None


def test_the_drift_refitted_under_snapped_steps():
    """Offsets of a clock drifting 30 ppm and set 0.25 s forward: with the step held at its true
    size the refitted drift is within 3 standard errors of the truth (the slope's σ/√Σ(t − t̄)²
    less the step's share), closer than with the step fitted freely on most draws."""
    from app.core.clock import refit_drift

    rng = np.random.default_rng(4)
    at = 0.5 * (T[7] + T[8])
    sd = SE / np.sqrt(np.sum((T - T.mean()) ** 2))
    closer = 0
    for _ in range(40):
        y = _offsets(rng, drift=-30e-6, steps=[(at, -0.25)])
        m = fit_clock(T, y, np.full(T.size, SE), [at])
        m2 = refit_drift(type(m)(m.offset_s, m.drift_s_per_s, m.t_ref_s, ((at, -0.25),), m.terms), T, y,
                         np.full(T.size, SE))
        assert m2.drift_s_per_s == pytest.approx(-30e-6, abs=3 * sd)
        closer += abs(m2.drift_s_per_s + 30e-6) <= abs(m.drift_s_per_s + 30e-6)
    assert closer >= 25


def test_windows_and_step_candidates_from_known_records():
    """Windows: two airborne runs of 1000 s and 250 s at 10 Hz (a ground stop between, a 30 s gap of
    the record inside the first): 300 s windows fill each gap-free run and none spans the gap or
    the stop.  Candidates: a 2 Hz clock with one sample lost (a whole step) and one 0.3 s jump —
    both gaps, at their middles with their excess over the step, only the lost sample marked a
    whole number of steps."""
    from app.core.clock import clock_windows, step_candidates

    t = np.arange(0.0, 1400.0, 0.1)
    t = t[(t < 500.0) | (t >= 530.0)]                       # 30 s without a record
    moving = (t < 1100.0) | (t >= 1150.0)                   # a stop on the ground
    win = clock_windows(t, moving, 300.0)
    spans = [(t[a], t[b - 1]) for a, b in win]
    assert len(win) == 2 and all(b - a >= 300.0 - 0.2 for a, b in spans)
    assert all((b < 500.0) or (a >= 530.0 and b < 1100.0) or a >= 1150.0 for a, b in spans)
    clk = np.arange(0.0, 600.0, 0.5)
    clk = np.delete(clk, 100)                               # one sample lost
    clk[400:] += 0.3                                        # the clock set 0.3 s forward
    mid, excess, whole = step_candidates(clk, 0.02)
    assert mid.size == 2 and mid[1] == pytest.approx(0.5 * (clk[399] + clk[400]))
    assert mid[0] == pytest.approx(0.5 * (clk[99] + clk[100]))
    assert np.allclose(excess, [0.5, 0.3]) and whole.tolist() == [True, False]


def test_a_jump_is_kept_only_where_its_gap_can_hold_it():
    """Windows of a clock set 0.3 s forward, offered the gap it left (0.35 s of excess on a 0.05 s
    step): one step of exactly −0.3 s there once snapped, no drift.  Offered instead a gap whose
    excess (0.1 s) is shorter than the jump, no step is kept there: the clock cannot have jumped
    further than its gap."""
    from app.core.clock import fit_clock_at_gaps

    rng = np.random.default_rng(5)
    at = 0.5 * (T[7] + T[8])
    y = _offsets(rng, steps=[(at, -0.3)])
    model, ev = fit_clock_at_gaps(T, y, np.full(T.size, SE), (np.array([at]), np.array([0.3 + 0.05])), 0.05)
    assert model.steps == ((at, pytest.approx(-0.3, abs=1e-12)),) and ev[0]["snapped_to_clock"]
    assert model.drift_s_per_s == 0.0
    model, ev = fit_clock_at_gaps(T, y, np.full(T.size, SE), (np.array([at]), np.array([0.1])), 0.05)
    assert model.steps == () and ev == []
