"""State-space form of the anomaly model of seed 000 (SPEC §2).

Model (units: δg in mGal, GNSS velocity error r in cm/s, Q in mGal² per GNSS step,
R in (cm/s)²)::

    ∇^m δg_k = q_k,            Var q_k = Q_k
    r_k white,                 Var r_k = R_k
    z_k = δg_k − 1000·(r_k − r_{k−1})/Δt        (mGal)

State ``y_k = (δg_k, δg_{k−1}, …, δg_{k−m+1}, r_k, r_{k−1})`` (length ``n = m + 2``)::

    y_k = A y_{k−1} + B e_k,   e_k = (q_k, r_k),  Cov e_k = diag(Q_k, R_k)
    z_k = C y_k                (no separate measurement noise)

The first row of ``A`` holds the coefficients of ``δg_k = Σ_j a_j δg_{k−j} + q_k``
from the binomial expansion of ``(1 − B)^m`` (m = 1: (1); m = 2: (2, −1);
m = 3: (3, −3, 1)).  The row of ``r_k`` is zero, so ``A`` is singular.
"""

from __future__ import annotations

from math import comb

import numpy as np

#: mGal per (cm/s²): 1 cm/s² = 1 Gal = 1000 mGal.
MGAL_PER_CMS2 = 1000.0


def _check_m(m) -> int:
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)):
        raise ValueError(f"m must be an integer in 1..3, got {m!r}")
    if not 1 <= int(m) <= 3:
        raise ValueError(f"m must be 1, 2 or 3, got {m}")
    return int(m)


def _check_dt(dt_s) -> float:
    dt = float(dt_s)
    if not np.isfinite(dt) or dt <= 0.0:
        raise ValueError(f"dt_s must be a positive finite number of seconds, got {dt_s!r}")
    return dt


def ar_coefficients(m: int) -> np.ndarray:
    """Coefficients ``a_j`` (j = 1..m) of ``δg_k = Σ a_j δg_{k−j} + q_k`` for ``∇^m δg = q``.

    Parameters
    ----------
    m : int
        Order of the backward difference, 1..3.

    Returns
    -------
    ndarray, shape (m,)
        ``a_j = (−1)^{j+1} · binom(m, j)``.
    """
    m = _check_m(m)
    return np.array([(-1.0) ** (j + 1) * comb(m, j) for j in range(1, m + 1)])


def build_model(m: int, dt_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Matrices ``(A, B, C)`` of the seed-000 model.

    Parameters
    ----------
    m : int
        Order of the anomaly model ``∇^m δg = q``, 1..3.
    dt_s : float
        GNSS step Δt (s), > 0.

    Returns
    -------
    A : ndarray, shape (m+2, m+2)
        Transition matrix (singular: the row of ``r_k`` is zero).
    B : ndarray, shape (m+2, 2)
        Noise input: ``B[0, 0] = 1`` (q into δg_k), ``B[m, 1] = 1`` (r into r_k).
    C : ndarray, shape (1, m+2)
        Observation row ``(1, 0, …, 0, −1000/Δt, +1000/Δt)``; with r in cm/s and
        Δt in s it gives ``z`` in mGal.

    Raises
    ------
    ValueError
        If ``m`` is not 1, 2 or 3 or ``dt_s`` is not positive.
    """
    m = _check_m(m)
    dt = _check_dt(dt_s)
    n = m + 2
    A = np.zeros((n, n))
    A[0, :m] = ar_coefficients(m)
    for i in range(1, m):
        A[i, i - 1] = 1.0
    A[m + 1, m] = 1.0
    B = np.zeros((n, 2))
    B[0, 0] = 1.0
    B[m, 1] = 1.0
    C = np.zeros((1, n))
    C[0, 0] = 1.0
    C[0, m] = -MGAL_PER_CMS2 / dt
    C[0, m + 1] = MGAL_PER_CMS2 / dt
    return A, B, C


def process_covariance(m: int, Q_mgal2: float, R_cm2s2: float) -> np.ndarray:
    """State noise covariance ``B diag(Q, R) Bᵀ``, shape (m+2, m+2).

    Parameters
    ----------
    m : int
        Model order, 1..3.
    Q_mgal2 : float
        Variance of q_k (mGal² per GNSS step), ≥ 0.
    R_cm2s2 : float
        Variance of r_k ((cm/s)²), ≥ 0.
    """
    m = _check_m(m)
    if not (Q_mgal2 >= 0 and R_cm2s2 >= 0):
        raise ValueError("Q_mgal2 and R_cm2s2 must be non-negative")
    W = np.zeros((m + 2, m + 2))
    W[0, 0] = float(Q_mgal2)
    W[m, m] = float(R_cm2s2)
    return W
