"""Benchmark of the noise-model fit (stage 3): the compiled search (Nelder–Mead and the
Whittle likelihood in numba) against SciPy's Nelder–Mead on the numpy likelihood — the fit as
it was —, side by side on the same spectra.

Run: ``.venv/bin/python benchmarks/bench_noise_fit.py``

Thirteen 30-minute lines of z at 2 Hz: an anomaly whose spectrum falls exponentially (28 mGal)
plus a white (1.5 cm/s) and a Gauss–Markov (1 cm/s, 12 s) GNSS velocity error differenced once.
:func:`app.core.noise_model.fit_noise_model` with its defaults (every family, m = 1, 2, 3, the
roll-off screen) runs twice: as built (:meth:`_Whittle.minimize`) and with
:meth:`_Whittle.nelder_mead_scipy` on :meth:`_Whittle.nll_numpy` in its place.  Printed: the
wall time of each (median of 3), their ratio, the number of likelihood evaluations, and how
far the two fits differ (family, order, largest relative difference of the components'
weights and of Q).  The compiled search is SciPy's step for step (tests: the same points with
a stable sort); the two differ where SciPy's simplex holds equal values (1e300 outside the
likelihood's domain), which numpy's default argsort orders by the CPU's SIMD sort.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.core import noise_model as nm  # noqa: E402


def lines(seed: int = 0, dt: float = 0.5, n_line: int = 3600, n_lines: int = 13) -> list[np.ndarray]:
    """z per line (mGal): exponential-spectrum anomaly + white and Gauss–Markov velocity error."""
    rng = np.random.default_rng(seed)
    phi = float(np.exp(-dt / 12.0))
    n = n_line * n_lines
    gm = np.empty(n)
    acc = 0.0
    e = rng.normal(0.0, 0.01 * np.sqrt(1.0 - phi ** 2), n)
    for i in range(n):
        acc = phi * acc + e[i]
        gm[i] = acc
    r = gm + rng.normal(0.0, 0.015, n)          # m/s
    f = np.fft.rfftfreq(n_line, dt)
    out = []
    for k in range(n_lines):
        x = np.fft.irfft(np.exp(-f / 0.006) * (f > 0) * (rng.normal(size=f.size) + 1j * rng.normal(size=f.size)),
                         n_line)
        rr = r[k * n_line:(k + 1) * n_line]
        out.append(28.0 * x / x.std() - np.diff(np.concatenate([[rr[0]], rr])) / dt * 1e5)
    return out


def timed_fit(z, dt: float, reference: bool):
    """(median wall s of 3, the fit, likelihood evaluations of one fit)."""
    built = nm._Whittle.minimize
    evals = [0]

    def counted(self, x0, spec, mm, maxiter, template=None, pos=None):
        if reference:
            nll = nm._Whittle.nll
            nm._Whittle.nll = nm._Whittle.nll_numpy
            try:
                res = nm._Whittle.nelder_mead_scipy(self, x0, spec, mm, maxiter, template, pos)
            finally:
                nm._Whittle.nll = nll
        else:
            res = built(self, x0, spec, mm, maxiter, template, pos)
        evals[0] += int(res.nfev)
        return res

    nm._Whittle.minimize = counted
    try:
        times, fit = [], None
        for _ in range(3):
            evals[0] = 0
            t0 = time.perf_counter()
            fit = nm.fit_noise_model(z, dt)
            times.append(time.perf_counter() - t0)
        return statistics.median(times), fit, evals[0]
    finally:
        nm._Whittle.minimize = built


def main() -> int:
    dt = 0.5
    z = lines(dt=dt)
    nm.fit_noise_model(z[:2], dt)                 # compile the kernels (numba's cache) first
    t_k, fit_k, n_k = timed_fit(z, dt, reference=False)
    t_n, fit_n, n_n = timed_fit(z, dt, reference=True)
    wk = np.array([c.weight for c in fit_k.model.components])
    wn = np.array([c.weight for c in fit_n.model.components])
    same = fit_k.model.family == fit_n.model.family and wk.shape == wn.shape
    print(f"noise fit, 13 lines x 30 min at 2 Hz: compiled {t_k:.2f} s ({n_k} evaluations), "
          f"SciPy + numpy {t_n:.2f} s ({n_n} evaluations); time ratio {t_n / t_k:.2f}")
    print(f"  family {fit_k.model.family!r} / {fit_n.model.family!r}, m {fit_k.m} / {fit_n.m}", end="")
    if same:
        print(f", weights differ by at most {np.max(np.abs(wk / wn - 1.0)):.1e} (relative), "
              f"Q by {abs(fit_k.Q_mgal2 / fit_n.Q_mgal2 - 1.0):.1e}")
    else:
        print(" (different families)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
