"""Seed-002 experiment: two-filter (Fraser–Potter) fixed-interval smoothing.

Research only: the product smooths with :func:`app.core.smoother.kalman_smooth`
(Bryson–Frazier or RTS).  The two-filter smoother is kept to reproduce seed 002's
comparison (``benchmarks/seed002_sphere.py``): on the same linear-Gaussian model it must
equal :func:`app.core.smoother.rts_smooth`.

Reference: Fraser & Potter (1969), IEEE TAC 14(4).
"""

from __future__ import annotations

import numpy as np

from app.core.smoother import SmoothedStates, generic_model_inputs, kalman_filter


def two_filter_smooth(A, Qmat, C, Rmeas, z, x0, P0, u=None) -> SmoothedStates:
    """Two-filter (Fraser–Potter) fixed-interval smoother.

    Forward: Kalman filter (:func:`app.core.smoother.kalman_filter`).  Backward: an
    information filter run from k = T−1 down to 0 with no prior information at the end,
    carrying the information matrix ``I_k`` and vector ``i_k`` of the measurements
    ``z_{k+1..T−1}`` about ``x_k``.  The backward prediction is written as
    ``I_{k} = Aᵀ (I + M Q)⁻¹ M A``, ``i_k = Aᵀ (I + M Q)⁻¹ (j − M u_{k+1})`` with
    ``M, j`` the information after using ``z_{k+1}``, which avoids the inverses of
    ``A``, of ``Q`` and of the (possibly singular) information matrix; the fusion is
    ``P_s = (I + P_f I_B)⁻¹ P_f``, ``x_s = (I + P_f I_B)⁻¹ (x_f + P_f i_B)``, which avoids
    the inverse of the filtered covariance.  The classical form of seed 002 inverts
    ``A`` in the backward model; this form gives the same numbers where that one
    exists.

    Parameters
    ----------
    A, Qmat, C, Rmeas, z, x0, P0, u
        As :func:`app.core.smoother.kalman_filter`; ``Rmeas`` must be positive definite
        (the backward information update uses ``Cᵀ R⁻¹ C``), so the seed-000 model, which
        has no measurement noise, is smoothed with :func:`app.core.smoother.kalman_smooth`
        instead.

    Returns
    -------
    SmoothedStates
        ``(xs (T, n), Ps (T, n, n), loglik)``, the log-likelihood of the forward filter.

    Raises
    ------
    ValueError
        ``Rmeas`` not positive definite, or bad shapes.
    """
    A, Qm, C, Rm, zz, x0v, P0v, uu = generic_model_inputs(A, Qmat, C, Rmeas, z, x0, P0, u)
    if np.any(np.linalg.eigvalsh(np.asarray(Rm)) <= 0.0):
        raise ValueError("two_filter_smooth needs a positive definite measurement covariance "
                         "(the backward information filter uses R⁻¹); use the Bryson–Frazier "
                         "or RTS smoother for models without measurement noise")
    xf, Pf, _, _, ll = kalman_filter(A, Qmat, C, Rmeas, z, x0, P0, u)
    N, n = xf.shape
    I = np.eye(n)
    IB = np.zeros((n, n))  # information about x_k from z_{k+1..}
    iB = np.zeros(n)
    xs = np.empty_like(xf)
    Ps = np.empty_like(Pf)
    for k in range(N - 1, -1, -1):
        # fuse
        F = I + Pf[k] @ IB
        Psk = np.linalg.solve(F, Pf[k])
        Ps[k] = 0.5 * (Psk + Psk.T)
        xs[k] = np.linalg.solve(F, xf[k] + Pf[k] @ iB)
        if k == 0:
            break
        # add z_k
        M = IB.copy()
        j = iB.copy()
        if np.all(np.isfinite(zz[k])):
            CtRi = np.linalg.solve(Rm[k], C).T  # Cᵀ R⁻¹ (R symmetric)
            M = M + CtRi @ C
            j = j + CtRi @ zz[k]
        # predict backwards to k−1 through x_k = A x_{k−1} + u_k + w_k
        W = np.linalg.solve(I + M @ Qm[k], np.column_stack([M, j - M @ uu[k]]))
        IB = A.T @ W[:, :n] @ A
        IB = 0.5 * (IB + IB.T)
        iB = A.T @ W[:, n]
    return SmoothedStates(xs, Ps, ll)
