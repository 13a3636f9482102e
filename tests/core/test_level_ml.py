"""Local noise level, full-rate level refinement and order selection on data drawn from the model."""

import numpy as np
import pytest

from app.core.level_ml import refine_levels, select_order, select_subset
from app.core.noise_level import local_noise_variance_cm2s2

DT = 0.1


def _simulate(Q_t, R_t, m, rng):
    """z = δg − 1000·∇r/Δt with ∇^m δg = q, Var q = Q_t, Var r = R_t (the model of SPEC §2)."""
    g = rng.normal(0, np.sqrt(Q_t))
    for _ in range(m):
        g = np.cumsum(g)
    r = rng.normal(0, np.sqrt(R_t))
    z = g.copy()
    z[1:] -= 1000.0 * np.diff(r) / DT
    z[0] = np.nan
    return z, g


def test_local_noise_level_tracks_episodes():
    rng = np.random.default_rng(1)
    n = 30000
    R = np.full(n, 1.69)
    R[10000:14000] = 25.0
    z, _ = _simulate(np.full(n, 1e-5), R, 2, rng)
    est = local_noise_variance_cm2s2(z, DT, window_s=20.0)
    assert np.median(est[2000:9000]) == pytest.approx(1.69, rel=0.05)
    assert np.median(est[10500:13500]) == pytest.approx(25.0, rel=0.05)
    # 20 s windows: a single estimate scatters by ~10 %
    assert np.std(est[2000:9000] / 1.69) < 0.15
    with pytest.raises(ValueError):
        local_noise_variance_cm2s2(np.ones(3), DT)


def test_refine_levels_recovers_switching_q():
    rng = np.random.default_rng(2)
    Qs = np.array([2e-6, 4e-5])
    zl, sl, rl = [], [], []
    for w in range(8):
        n = 12000
        s = np.zeros(n, int)
        s[3000 + 500 * w: 7000 + 300 * w] = 1
        z, _ = _simulate(Qs[s], np.full(n, 2.0), 2, rng)
        zl.append(z)
        sl.append(s)
        rl.append(np.full(n, 2.0))
    # start far from the truth, R as a per-epoch base with an unknown factor
    fit = refine_levels(zl, sl, [1e-7, 1e-3], [1.0], DT, 2, r_base_lines=[r / 1.5 for r in rl])
    assert fit.Q_mgal2[0] == pytest.approx(2e-6, rel=0.35)
    assert fit.Q_mgal2[1] == pytest.approx(4e-5, rel=0.35)
    assert fit.R_cm2s2[0] == pytest.approx(1.5, rel=0.05)
    assert fit.loglik >= fit.loglik_start


@pytest.mark.parametrize("m_true,Q", [(1, 0.05), (2, 2e-5)])
def test_select_order_finds_the_generating_order(m_true, Q):
    rng = np.random.default_rng(3 + m_true)
    zl, rl = [], []
    for _ in range(5):
        z, _ = _simulate(np.full(15000, Q), np.full(15000, 1.7), m_true, rng)
        zl.append(z)
        rl.append(np.full(15000, 1.7))
    choice = select_order(zl, rl, DT, candidates=(1, 2))
    assert choice.m == m_true
    assert choice.Q_mgal2[m_true] == pytest.approx(Q, rel=0.3)


def test_refine_levels_is_the_same_on_a_thread_pool():
    """The lines' likelihoods computed on a thread pool (the Kalman kernels release the GIL)
    are summed in line order: the fit is bit-for-bit the one of the builtin map, and the
    kernels did run concurrently (more than one worker thread took part)."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from app.core.noise_model import NoiseComponent, NoiseModel

    rng = np.random.default_rng(5)
    zl, sl = [], []
    for w in range(6):
        n = 6000
        s = np.zeros(n, int)
        s[1500 + 200 * w: 4000] = 1
        z, _ = _simulate(np.array([3e-6, 5e-5])[s], np.full(n, 2.0), 2, rng)
        zl.append(z)
        sl.append(s)
    # a coloured model too: its generic kernel is the other loop that must release the GIL
    coloured = NoiseModel((NoiseComponent(1, 0.0, 2e8), NoiseComponent(2, 0.5, 1e3)), DT, "velocity + height")
    for noise in (None, coloured):
        ref = refine_levels(zl, sl, [1e-6, 1e-4], [2.0], DT, 2, fit_r=False, noise=noise)
        seen: set = set()

        def on_pool(f, items, ex, seen=seen):
            def g(k):
                seen.add(threading.get_ident())
                return f(k)
            return ex.map(g, items)

        with ThreadPoolExecutor(3) as ex:
            par = refine_levels(zl, sl, [1e-6, 1e-4], [2.0], DT, 2, fit_r=False, noise=noise,
                                map_lines=lambda f, items, ex=ex, on_pool=on_pool: on_pool(f, items, ex))
        assert np.array_equal(par.Q_mgal2, ref.Q_mgal2)
        assert par.loglik == ref.loglik and par.n_evaluations == ref.n_evaluations
        assert len(seen) > 1


def test_cap_lifted_smooth_level():
    """A lifted smoothest level comes down to the stationary level, never below the EM's; a
    level not lifted, one below the stationary level, the other levels and a one-level model
    are left as they are."""
    from app.core.level_ml import cap_lifted_smooth_level

    q, capped = cap_lifted_smooth_level([15.7, 62.4], [1.46, 56.6], 8.97)      # unseen 1619's numbers
    assert capped and q.tolist() == [8.97, 62.4]
    q, capped = cap_lifted_smooth_level([15.7, 62.4], [10.0, 56.6], 8.97)      # EM's own level above it
    assert capped and q.tolist() == [10.0, 62.4]
    for args in (([5.0, 62.4], [1.46, 56.6], 8.97),     # lifted, still below the stationary level
                 ([1.46, 62.4], [1.46, 56.6], 0.5),     # not lifted (the EM's level kept)
                 ([15.7], [1.46], 8.97),                # one level: the stationary model itself
                 ([15.7, 62.4], [1.46, 56.6], float("nan"))):
        q, capped = cap_lifted_smooth_level(*args)
        assert not capped and q.tolist() == list(args[0])
    with pytest.raises(ValueError, match="shape"):
        cap_lifted_smooth_level([1.0, 2.0], [1.0], 1.0)


def test_select_subset_breaks_ties_by_state_index():
    """States of equal occupancy are visited in index order, whatever the CPU's sort does with
    ties (numpy 2's default argsort of [2, 1, 2, 2, 1] is [1 4 2 0 3] on an AVX-512 CPU).  Line
    i holds only state i, with [2, 1, 2, 2, 1] epochs; a budget of 4 epochs takes the two rare
    states' lines, then the first of the tied states: lines 0, 1, 4 — on every machine."""
    counts = [2, 1, 2, 2, 1]
    states = [np.full(c, i) for i, c in enumerate(counts)]
    assert select_subset(counts, states, 5, max_epochs=4) == [0, 1, 4]
    # with room for all, every line
    assert select_subset(counts, states, 5, max_epochs=100) == [0, 1, 2, 3, 4]
