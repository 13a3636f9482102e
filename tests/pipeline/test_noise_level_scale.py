"""Stage 3's level for the white-velocity family: the band measurement, or the fitted level
where that is lower and the crossovers can check it (``white_level_fitted``).

Simulation with known truth: z is white GNSS velocity noise differenced once (σ_v known,
so R = (100 σ_v)² (cm/s)² exactly) plus a turbulence bump at 0.25–0.5 Hz — inside the band
(0.1, 0.5) Hz where the local level is measured, above the 0.2 Hz the shape is fitted to.
The band measurement then over-states R; the fitted level does not.
"""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import signal

from app.config import ProcessingParams
from app.pipeline.stages.lines import LineData
from app.pipeline.stages.noise import model_noise

DT_S = 0.1
SIGMA_V_MS = 0.01            # white velocity noise: R = 1 (cm/s)²
R_TRUE_CM2S2 = (100.0 * SIGMA_V_MS) ** 2
N_LINE = 6000                # 600 s per line
N_LINES = 4


def _survey(bump_factor: float, seed: int = 3):
    """One flight of N_LINES back-to-back lines; z = Δv/Δt (mGal) + a band-limited bump whose
    power is ``bump_factor`` × the white-velocity noise's power in 0.25–0.5 Hz."""
    rng = np.random.default_rng(seed)
    n = N_LINES * N_LINE + 1
    v = SIGMA_V_MS * rng.standard_normal(n)
    z = np.diff(v) / DT_S * 1e5
    t = np.arange(z.size) * DT_S
    z += 20.0 * np.sin(2 * np.pi * t / 400.0)          # a smooth anomaly (mGal)
    if bump_factor > 0:
        sos = signal.butter(6, [0.25, 0.5], btype="bandpass", fs=1 / DT_S, output="sos")
        white_in_band = signal.sosfiltfilt(sos, z - 20.0 * np.sin(2 * np.pi * t / 400.0))
        bump = signal.sosfiltfilt(sos, rng.standard_normal(z.size))
        z += bump * np.sqrt(bump_factor) * white_in_band.std() / bump.std()
    flights = {"F1": SimpleNamespace(z_mgal=z, heights_only=False)}
    lines = []
    for k in range(N_LINES):
        sl = slice(k * N_LINE, (k + 1) * N_LINE)
        m = sl.stop - sl.start
        lines.append(LineData(f"L{k}", "F1", "main", None, sl, t[sl], np.zeros(m), np.zeros(m), np.full(m, 500.0),
                              np.linspace(0, 60, m), np.full(m, 2.0 * k), z[sl].copy(), 100.0))
    return lines, flights


def _level(stage, lines) -> float:
    """Mean R (cm/s)² the smoother uses on the lines."""
    return float(np.mean(np.concatenate([stage.r_local[ln.flight][ln.sl] for ln in lines])))


@pytest.fixture(scope="module")
def bumped():
    return _survey(bump_factor=4.0)


def test_bump_overstates_band_level_fitted_level_is_true(bumped):
    lines, flights = bumped
    p = ProcessingParams(noise_family="white velocity")
    checked = model_noise(lines, flights, DT_S, p, n_crossovers=10)
    unchecked = model_noise(lines, flights, DT_S, p, n_crossovers=2)
    assert checked.model.is_white_velocity
    # without crossovers to check it: the band measurement, over-stated by the bump
    assert unchecked.scale == 1.0
    assert _level(unchecked, lines) > 1.5 * R_TRUE_CM2S2
    # with them: the fitted level, within 20 % of the true R
    assert checked.scale < 0.8
    assert _level(checked, lines) == pytest.approx(R_TRUE_CM2S2, rel=0.2)
    assert "fitted level" in checked.level_note and "cannot check" in unchecked.level_note
    # the parameter off: the band measurement whatever the crossovers
    off = model_noise(lines, flights, DT_S, p.model_copy(update={"white_level_fitted": False}), n_crossovers=10)
    assert off.scale == 1.0


def test_white_level_never_raised():
    """No bump: the band measurement is the true level already; the fitted one may be a bit
    above or below it by chance, and the factor never exceeds 1."""
    lines, flights = _survey(bump_factor=0.0, seed=5)
    st = model_noise(lines, flights, DT_S, ProcessingParams(noise_family="white velocity"), n_crossovers=10)
    assert 0.8 < st.scale <= 1.0
    assert _level(st, lines) == pytest.approx(R_TRUE_CM2S2, rel=0.2)
