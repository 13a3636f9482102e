"""Local GNSS velocity-noise level R(t) from the high-frequency content of z.

Above ~0.5 Hz the measurement ``z_k = δg_k − 1000·(r_k − r_{k−1})/Δt`` is pure noise
(the anomaly at flight height has no power there), so the local variance of the
second difference of z measures the GNSS noise level directly, at full rate and with
thousands of samples per kilometre — far more precisely than a noise state recognised
on the decimated grid.  For white r of variance R (cm/s)²,
``∇z_k = −1000·(r_k − 2r_{k−1} + r_{k−2})/Δt`` has variance ``6·10⁶·R/Δt²``.

Other white errors (gravimeter sensor noise) are lumped into the same effective R,
which is what the smoother needs.  A global factor between this effective level and
the likelihood-optimal one (coloured GNSS noise) is estimated later by maximum
likelihood (:mod:`app.core.level_ml`).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d


def local_noise_variance_cm2s2(z_mgal, dt_s: float, window_s: float = 20.0,
                               floor_cm2s2: float = 1e-4) -> np.ndarray:
    """Local R(t) in (cm/s)² at every epoch.

    Parameters
    ----------
    z_mgal : ndarray, shape (n,)
        The measurement (mGal); NaN allowed (ignored).
    dt_s : float
        GNSS step (s).
    window_s : float
        Length of the centred averaging window (s).
    floor_cm2s2 : float
        Lower bound of the returned values.

    Returns
    -------
    ndarray, shape (n,)
    """
    z = np.asarray(z_mgal, dtype=float)
    if z.ndim != 1:
        raise ValueError("z_mgal must be one-dimensional")
    if not dt_s > 0:
        raise ValueError("dt_s must be positive")
    n = z.size
    if n < 8:
        raise ValueError("need at least 8 epochs to estimate the noise level")
    dz = np.diff(z)
    ok = np.isfinite(dz)
    sq = np.where(ok, dz * dz, 0.0)
    w = max(3, int(round(window_s / dt_s)))
    num = uniform_filter1d(sq, w, mode="nearest")
    den = uniform_filter1d(ok.astype(float), w, mode="nearest")
    var = np.where(den > 0.2, num / np.maximum(den, 1e-12), np.nan)
    if not np.isfinite(var).any():
        raise ValueError("no finite measurement differences to estimate the noise level from")
    var = np.where(np.isfinite(var), var, np.nanmedian(var))
    r = var * dt_s * dt_s / 6.0e6
    r = np.concatenate([[r[0]], r])
    return np.maximum(r, floor_cm2s2)
