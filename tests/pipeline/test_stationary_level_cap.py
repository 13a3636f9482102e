"""The stationary baseline's one level never exceeds the adaptive model's highest level: one Q
for every terrain is at most the roughest terrain's.  Where the full-rate likelihood put it far
above (noise its one R leaves unexplained), the column passed the noise (an independent
generator's survey: 83 mGal from the truth, the anomaly's std 20; unseen 1681: 45 mGal)."""

import numpy as np
import pandas as pd

from app.config import ProcessingParams
from app.core.smoother import kalman_smooth
from app.pipeline.stages.filtering import Filtered, PreparedLine


def test_stationary_column_at_most_the_highest_level():
    rng = np.random.default_rng(3)
    dt_s, n = 0.1, 6000
    t = np.arange(n) * dt_s
    truth = 8.0 * np.sin(2 * np.pi * t / 300.0) + 3.0 * np.sin(2 * np.pi * t / 90.0)
    # white GNSS velocity noise as z sees it: (r_k − r_{k−1}) / Δt, 1 cm/s² = 1000 mGal
    r_cm2s2 = 4.0
    v_cms = rng.normal(0.0, np.sqrt(r_cm2s2), n + 1)
    z = truth + np.diff(v_cms) / dt_s * 1000.0
    pr = PreparedLine(line=None, s_full=np.zeros(n, int), s_ext=np.zeros(n, int), z_ext=z, inner=slice(0, n),
                      r_ext=None, idx=None, pq=None)
    levels = np.array([1e-7, 1e-5])
    f = Filtered(pd.DataFrame({"dg_stationary_mgal": np.full(n, np.nan)}), levels, None, 1.0,
                 r_stationary=r_cm2s2, prepared=[pr], Q_stationary=1.0)
    f.add_stationary(dt_s, 2, "bf", None, ProcessingParams())
    assert f.Q_stationary == 1.0 and f.Q_stationary_used == levels.max()
    ref = kalman_smooth(z, np.full(n, levels.max()), np.full(n, r_cm2s2), dt_s, m=2).dg_mgal
    np.testing.assert_allclose(f.table["dg_stationary_mgal"].to_numpy(), ref, rtol=1e-9, atol=1e-9)
    unclamped = kalman_smooth(z, np.full(n, 1.0), np.full(n, r_cm2s2), dt_s, m=2).dg_mgal
    err = lambda est: float(np.sqrt(np.mean((est - truth)[500:-500] ** 2)))   # noqa: E731
    assert err(ref) < 0.5 * err(unclamped), (err(ref), err(unclamped))
    # below the highest level the fitted level is used as it is
    f2 = Filtered(pd.DataFrame({"dg_stationary_mgal": np.full(n, np.nan)}), levels, None, 1.0,
                  r_stationary=r_cm2s2, prepared=[pr], Q_stationary=3e-6)
    f2.add_stationary(dt_s, 2, "bf", None, ProcessingParams())
    assert f2.Q_stationary_used == 3e-6
