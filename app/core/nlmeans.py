"""Recognition-map smoothing over all lines (NL-means, SPEC §2 step 4; seed 000 §6).

Each decimated point ``i`` is re-estimated from all points ``j`` (of all lines,
itself included) within distance ``ρ`` with weights ``exp(−h·d_ij)`` (d in km)::

    p_i(n) = Σ_j w_ij · v_j(n) / Σ_j w_ij,      state_i = argmax_n p_i(n)

``v_j`` is the one-hot indicator of the recognised state (``mode='hard'``, the
paper's form) or the posterior probability vector (``mode='soft'``).

The neighbour graph (unordered pairs within ``max_rho_km``, CSR by first point)
is built once; a smoothing at any ``h``, ``ρ ≤ max_rho_km`` recomputes the pair
weights and costs two sparse-dense products (≈ 30 ms for 20 000 points and
3.3 M pairs).  Coincident points (distance 0) weigh as the point itself.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


class RecognitionMap:
    """Neighbour graph of the decimated points of a survey.

    Parameters
    ----------
    easting_km, northing_km : (T,) array_like
        Planar coordinates of all decimated points of all lines (km).
    max_rho_km : float
        Largest neighbourhood radius that :meth:`smooth` will accept (km).

    Notes
    -----
    Memory is 12 bytes per unordered pair within ``max_rho_km``
    (≈ 40 MB for 100 lines × 200 points, 2 km × 1 km spacing, 15 km).
    """

    def __init__(self, easting_km, northing_km, max_rho_km: float = 15.0):
        e = np.asarray(easting_km, dtype=float).reshape(-1)
        n = np.asarray(northing_km, dtype=float).reshape(-1)
        if e.shape != n.shape:
            raise ValueError("easting_km and northing_km must have the same length")
        if not (np.all(np.isfinite(e)) and np.all(np.isfinite(n))):
            raise ValueError("coordinates contain NaN or infinite values")
        if not (np.isfinite(max_rho_km) and max_rho_km >= 0):
            raise ValueError("max_rho_km must be finite and >= 0")
        self.n_points = e.size
        self.max_rho_km = float(max_rho_km)
        xy = np.column_stack([e, n])
        if e.size > 1:
            pairs = cKDTree(xy).query_pairs(self.max_rho_km, output_type="ndarray")
        else:
            pairs = np.empty((0, 2), dtype=np.intp)
        order = np.argsort(pairs[:, 0], kind="stable")
        pairs = pairs[order]
        self._d = np.hypot(*(xy[pairs[:, 0]] - xy[pairs[:, 1]]).T) if pairs.size else np.empty(0)
        itype = np.int32 if pairs.shape[0] < 2**31 - 1 else np.int64
        self._indices = pairs[:, 1].astype(itype)
        self._indptr = np.r_[0, np.cumsum(np.bincount(pairs[:, 0], minlength=e.size))].astype(itype)

    @property
    def n_pairs(self) -> int:
        """Number of unordered pairs of distinct points within ``max_rho_km``."""
        return int(self._d.size)

    def neighbour_sum(self, values, h_per_km: float, rho_km: float, groups=None) -> np.ndarray:
        """``Σ_j exp(−h·d_ij)·values_j`` over the points ``j ≠ i`` within ``ρ``.

        Parameters
        ----------
        values : (T,) or (T, N) array
        h_per_km, rho_km : float
            Kernel decay (1/km) and radius (km, ≤ ``max_rho_km``).
        groups : (T,) array, optional
            Group label per point (e.g. the line); pairs in the same group are
            left out, so a line's own evidence (already in its HMM) is not counted twice.

        Returns
        -------
        ndarray, shape of ``values``
        """
        if not (np.isfinite(h_per_km) and h_per_km >= 0):
            raise ValueError(f"h_per_km must be finite and >= 0, got {h_per_km}")
        if not (np.isfinite(rho_km) and 0 <= rho_km <= self.max_rho_km):
            raise ValueError(f"rho_km must be in [0, {self.max_rho_km}], got {rho_km}")
        v = np.asarray(values, dtype=float)
        if v.shape[0] != self.n_points:
            raise ValueError(f"expected {self.n_points} rows, got {v.shape[0]}")
        T = self.n_points
        w = np.where(self._d <= rho_km, np.exp(-h_per_km * self._d), 0.0)
        if groups is not None:
            g = np.asarray(groups).reshape(-1)
            if g.shape != (T,):
                raise ValueError(f"groups must have shape ({T},)")
            first = np.repeat(np.arange(T), np.diff(self._indptr))
            w = np.where(g[first] != g[self._indices], w, 0.0)
        M = sp.csr_matrix((w, self._indices, self._indptr), shape=(T, T))
        return M @ v + M.T @ v

    def smooth(self, labels_or_probs, h_per_km: float, rho_km: float, mode: str = "soft",
               n_states: int | None = None):
        """Smooth a recognition map.

        Parameters
        ----------
        labels_or_probs : (T,) int labels (``mode='hard'``) or (T, N) probabilities
            (``mode='soft'``; a (T,) label array is also accepted and one-hot encoded).
        h_per_km : float >= 0
            Kernel decay ``h`` in ``exp(−h·d)`` (1/km).
        rho_km : float, 0 <= ρ <= max_rho_km
            Neighbourhood radius (km).
        mode : 'hard' | 'soft'
        n_states : int, optional
            Number of states for label input (default ``max(label) + 1``).

        Returns
        -------
        probs : (T, N) smoothed probabilities (rows sum to 1).
        labels : (T,) int, ``argmax`` of ``probs`` (lowest index on ties).
        """
        if not (np.isfinite(h_per_km) and h_per_km >= 0):
            raise ValueError(f"h_per_km must be finite and >= 0, got {h_per_km}")
        if not (np.isfinite(rho_km) and 0 <= rho_km <= self.max_rho_km):
            raise ValueError(f"rho_km must be in [0, {self.max_rho_km}], got {rho_km}")
        if mode not in ("hard", "soft"):
            raise ValueError("mode must be 'hard' or 'soft'")
        v = np.asarray(labels_or_probs)
        T = self.n_points
        if v.ndim == 1 or mode == "hard":
            if v.ndim == 2:  # hard mode from probabilities: take their argmax
                if v.shape[0] != T:
                    raise ValueError(f"expected {T} rows, got {v.shape[0]}")
                n_states = n_states or v.shape[1]
                v = np.argmax(v, axis=1)
            if v.shape != (T,):
                raise ValueError(f"labels must have shape ({T},), got {v.shape}")
            if not np.issubdtype(v.dtype, np.integer):
                if not np.all(np.isfinite(v)) or np.any(v != np.round(v)):
                    raise ValueError("labels must be integers")
                v = v.astype(np.int64)
            if T and v.min() < 0:
                raise ValueError("labels must be >= 0")
            N = int(n_states or (v.max() + 1 if T else 1))
            if T and v.max() >= N:
                raise ValueError("a label is >= n_states")
            P = np.zeros((T, N))
            P[np.arange(T), v] = 1.0
        else:
            P = np.asarray(v, dtype=float)
            if P.ndim != 2 or P.shape[0] != T:
                raise ValueError(f"probabilities must have shape ({T}, N), got {P.shape}")
            if not np.all(np.isfinite(P)) or np.any(P < 0):
                raise ValueError("probabilities must be finite and >= 0")
        w = np.where(self._d <= rho_km, np.exp(-h_per_km * self._d), 0.0)
        M = sp.csr_matrix((w, self._indices, self._indptr), shape=(T, T))  # pairs i < j
        Pa = np.column_stack([P, np.ones(T)])  # last column accumulates the weight sum
        acc = Pa + M @ Pa + M.T @ Pa            # self weight exp(0) = 1, both directions
        num, den = acc[:, :-1], acc[:, -1]
        probs = num / den[:, None]
        if mode == "soft":
            tot = probs.sum(axis=1, keepdims=True)
            probs = np.divide(probs, tot, out=np.full_like(probs, 1.0 / P.shape[1]), where=tot > 0)
        return probs, np.argmax(probs, axis=1)
