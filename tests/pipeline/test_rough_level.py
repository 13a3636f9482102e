"""The rough level the smoother uses (``rough_level_factor``, METHOD stage 8 "The rough level").

The premise, checked on simulations with known truth: the m = 2 likelihood fits the level where
the data say most, below the smoother's cutoff, so an anomaly whose spectrum falls slower than
the prior's ω⁻⁴ (here an Ornstein–Uhlenbeck process: flat, then ω⁻²) is smoothed with a level
below the one its RMS needs, and twice the likelihood's level is closer to the truth.  Then the
pipeline's rule: the roughest level at least twice the full-rate likelihood's (the EM's kept where
higher), the levels before it kept for the report and a filter job's warm start (checked on the
sample survey in ``test_filter_job_blend.py``)."""

import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from app.core.level_ml import raise_rough_level
from app.core.smoother import kalman_loglik, kalman_smooth
from app.pipeline.stages.filtering import rough_level

DT_S = 0.1
R_CM2S2 = 4.0


def _ou_line(seed: int, n: int = 60_000, tau_s: float = 60.0, sd_mgal: float = 5.0):
    """An OU anomaly (mGal) and z = anomaly + the derivative of white velocity noise of R."""
    rng = np.random.default_rng(seed)
    a = np.exp(-DT_S / tau_s)
    e = rng.normal(0.0, sd_mgal * np.sqrt(1 - a * a), n)
    s = np.zeros(n)
    for k in range(1, n):
        s[k] = a * s[k - 1] + e[k]
    v_ms = rng.normal(0.0, np.sqrt(R_CM2S2) * 1e-2, n + 1)
    return s, s + np.diff(v_ms) / DT_S * 1e5


def _rms(z, s, q):
    n = z.size
    est = kalman_smooth(z, np.full(n, q), np.full(n, R_CM2S2), DT_S, m=2).dg_mgal
    err = (est - s)[3000:-3000]
    return float(np.sqrt(np.mean((err - err.mean()) ** 2)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_likelihood_level_is_below_what_a_flatter_anomaly_needs(seed):
    s, z = _ou_line(seed)
    n = z.size

    def nll(log_q):
        return -kalman_loglik(z, np.full(n, np.exp(log_q)), np.full(n, R_CM2S2), DT_S, m=2)

    q_ml = float(np.exp(minimize_scalar(nll, bounds=(np.log(1e-16), np.log(1e2)), method="bounded").x))
    log_grid = np.log(q_ml) + np.linspace(-2.0, 5.0, 15)     # the RMS against the truth, 0.14–150× q_ml
    rms = [_rms(z, s, np.exp(g)) for g in log_grid]
    q_opt = float(np.exp(log_grid[int(np.argmin(rms))]))
    assert q_opt > 3.0 * q_ml                        # measured 4.5–90× on seeds 0–5
    assert _rms(z, s, 2 * q_ml) < _rms(z, s, q_ml)   # twice the likelihood's level: closer to the truth


def test_rough_level_raises_the_roughest_to_twice_the_likelihood():
    # the EM's level (lifted) below twice the likelihood's: raised to 2 × 3e-5
    used, rep = rough_level([1e-6, 4e-5], [5e-7, 3e-5], 2.0)
    np.testing.assert_allclose(used, [1e-6, 6e-5])
    assert rep == {"factor": 2.0, "full_rate_ml_mgal2": 3e-5, "lifted_mgal2": 4e-5, "used_mgal2": 6e-5,
                   "raised": True}
    # the EM's level already above twice the likelihood's: kept
    kept, rep = rough_level([1e-6, 9e-5], [5e-7, 3e-5], 2.0)
    np.testing.assert_allclose(kept, [1e-6, 9e-5])
    assert rep["raised"] is False and rep["used_mgal2"] == 9e-5
    used3, _ = rough_level([1e-6, 1e-5, 4e-5], [1e-6, 1e-5, 4e-5], 3.0)   # three levels: the top one
    np.testing.assert_allclose(used3, [1e-6, 1e-5, 1.2e-4])
    one, none = rough_level([3e-6], [1e-6], 2.0)        # one level: nothing is rougher than the rest
    np.testing.assert_allclose(one, [3e-6])
    assert none is None
    assert rough_level([1e-6, 4e-5], None, 2.0)[1] is None     # no refinement: the levels as learned
    assert rough_level([1e-6, 4e-5], [5e-7, 3e-5], 1.0)[1] is None


def test_raise_rough_level_checks_its_inputs():
    with pytest.raises(ValueError, match="shape"):
        raise_rough_level([1e-6, 4e-5], [3e-5], 2.0)
    with pytest.raises(ValueError, match="factor"):
        raise_rough_level([1e-6, 4e-5], [5e-7, 3e-5], 0.5)
    q, raised = raise_rough_level([1e-6, 4e-5], [5e-7, np.nan], 2.0)   # no likelihood level: kept
    np.testing.assert_allclose(q, [1e-6, 4e-5])
    assert raised is False
