"""Stage 3's bound on the GNSS velocity error from the heights (``misfit_bound``).

Simulation with known truth: one flight whose heights are exact but for a 2 cm white error
and whose velocities carry a white + Gauss–Markov error of known spectrum; the bound built
from the flight must be that velocity error as z sees it (closed form), and it must not be
built where the velocities came from the heights or the option is off.
"""

from types import SimpleNamespace

import numpy as np
import pytest

from app.config import ProcessingParams
from app.core.noise_model import NoiseComponent, NoiseModel
from app.pipeline.stages.lines import LineData
from app.pipeline.stages.noise import misfit_bound

DT_S = 0.2
PHI = float(np.exp(-DT_S / 15.0))


def _flight(rng, heights_only=False, n=36_000):
    t = 5000.0 + np.arange(n) * DT_S
    h_true = 3000.0 + 5.0 * np.sin(2 * np.pi * t / 90.0)
    v_true = 5.0 * 2 * np.pi / 90.0 * np.cos(2 * np.pi * t / 90.0)
    e = rng.normal(0.0, 0.005 * np.sqrt(1 - PHI ** 2), n)
    gm = np.empty(n)
    acc = 0.0
    for i in range(n):
        acc = PHI * acc + e[i]
        gm[i] = acc
    vu = v_true + gm + rng.normal(0.0, 0.01, n)
    h = h_true + rng.normal(0.0, 0.02, n)
    vu[20_000] = np.nan                      # a missing epoch splits the stretch
    return SimpleNamespace(t_s=t, h_m=h, vu_ms=vu, heights_only=heights_only)


def _lines(fm, flight="F1"):
    out = []
    for k, (a, b) in enumerate(((500, 12_000), (14_000, 26_000), (27_000, 35_000))):
        sl = slice(a, b)
        m = b - a
        out.append(LineData(f"L{k}", flight, "main", None, sl, fm.t_s[sl], np.zeros(m), np.zeros(m), fm.h_m[sl],
                            np.linspace(0, 60, m), np.zeros(m), np.zeros(m), 70.0))
    return out


def test_the_bound_is_the_velocity_error_of_the_flight():
    fm = _flight(np.random.default_rng(8))
    b = misfit_bound(_lines(fm), {"F1": fm}, DT_S, ProcessingParams())
    to_z = (1e5 / DT_S) ** 2
    truth = NoiseModel((NoiseComponent(1, PHI, 0.005 ** 2 * (1 - PHI ** 2) * to_z),
                        NoiseComponent(1, 0.0, 0.01 ** 2 * to_z)), DT_S, "truth")
    low = b.f_hz <= 0.01
    ratio = b.psd[low] / truth.psd(b.f_hz[low])
    assert b.n_segments == 2                                   # split at the missing epoch
    assert b.f_hz.min() < 0.002 and b.f_hz.max() <= 0.05
    assert np.exp(np.mean(np.log(ratio))) == pytest.approx(1.0, abs=0.15)


def test_no_bound_from_heights_only_flights_or_when_off():
    rng = np.random.default_rng(9)
    fm = _flight(rng, heights_only=True)
    assert misfit_bound(_lines(fm), {"F1": fm}, DT_S, ProcessingParams()) is None
    fm = _flight(rng)
    assert misfit_bound(_lines(fm), {"F1": fm}, DT_S, ProcessingParams(noise_velocity_bound=False)) is None
