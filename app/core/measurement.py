"""The anomaly measurement z_k (SPEC §1).

``z_k = f̄_k − (V_k − V_{k−1})/Δt − γ(φ_k, h_k) + E_k``

with ``f̄_k`` the gravimeter's specific force (lag and scale undone) averaged
over ``(t_{k−1}, t_k]``, ``V`` the GNSS vertical velocity (up), ``γ`` normal
gravity and ``E`` the Eötvös correction (positive flying east).  A gravimeter
at rest at a point of gravity g gives ``z = g − γ``.
"""

from __future__ import annotations

import numpy as np

from app.core.geodesy import MGAL_PER_MS2


def gnss_acceleration_ms2(t_s, vu_ms) -> np.ndarray:
    """Mean vertical acceleration over each GNSS interval, ``(V_k − V_{k−1})/Δt_k`` (m/s²).

    Parameters
    ----------
    t_s, vu_ms : ndarray, shape (n,)

    Returns
    -------
    ndarray, shape (n,)
        First element NaN.
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(vu_ms, dtype=float)
    if t.shape != v.shape:
        raise ValueError("t_s and vu_ms must have the same shape")
    out = np.full(t.shape, np.nan)
    if t.size > 1:
        dt = np.diff(t)
        if np.any(dt <= 0):
            raise ValueError("GNSS epochs must be strictly increasing")
        out[1:] = np.diff(v) / dt
    return out


def anomaly_measurement_mgal(fbar_ms2, t_s, vu_ms, gamma_mgal, eotvos_mgal) -> np.ndarray:
    """Free-air anomaly measurement ``z_k`` at every GNSS epoch (mGal).

    Parameters
    ----------
    fbar_ms2 : ndarray, shape (n,)
        Gravimeter specific force (up, lag/scale undone) averaged over
        ``(t_{k−1}, t_k]`` (m/s²); NaN where unavailable.
    t_s : ndarray, shape (n,)
        GNSS epoch times (s).
    vu_ms : ndarray, shape (n,)
        GNSS vertical velocity (m/s, up).
    gamma_mgal : ndarray, shape (n,)
        Normal gravity at each epoch (mGal).
    eotvos_mgal : ndarray, shape (n,)
        Eötvös correction at each epoch (mGal).

    Returns
    -------
    ndarray, shape (n,)
        ``z`` in mGal; the first epoch is NaN (no previous velocity).
    """
    f = np.asarray(fbar_ms2, dtype=float)
    acc = gnss_acceleration_ms2(t_s, vu_ms)
    g = np.asarray(gamma_mgal, dtype=float)
    e = np.asarray(eotvos_mgal, dtype=float)
    if not (f.shape == acc.shape == g.shape == e.shape):
        raise ValueError("all inputs of anomaly_measurement_mgal must have the same shape")
    return (f - acc) * MGAL_PER_MS2 - g + e
