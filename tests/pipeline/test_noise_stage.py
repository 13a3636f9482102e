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
    # the GNSS file of the same flight: velocities with that error (the aircraft level), heights
    # with a 2 cm error of their own (stage 3's velocity bound)
    flights = {"F1": SimpleNamespace(z_mgal=z, heights_only=False, t_s=t, vu_ms=v[1:],
                                     h_m=rng.normal(0.0, 0.02, z.size))}
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
    # the crossovers' part of the level (the heights' cap is the next test's)
    p = ProcessingParams(noise_family="white velocity", noise_velocity_bound=False)
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


def test_band_level_overstated_by_a_bump_is_capped_by_the_heights(bumped):
    """No crossovers to check a fitted level: the band measurement holds the bump, but the GNSS
    heights show the velocity error below 0.01 Hz, and the level is lowered to what they allow
    (within the bound's 0.9-quantile slack of the true R); with the bound off it stays over-stated."""
    lines, flights = bumped
    p = ProcessingParams(noise_family="white velocity")
    capped = model_noise(lines, flights, DT_S, p, n_crossovers=0)
    free = model_noise(lines, flights, DT_S, p.model_copy(update={"noise_velocity_bound": False}), n_crossovers=0)
    assert _level(free, lines) > 1.5 * R_TRUE_CM2S2
    assert 0.8 * R_TRUE_CM2S2 < _level(capped, lines) < 1.5 * R_TRUE_CM2S2
    assert "GNSS heights allow" in capped.level_note
    off = model_noise(lines, flights, DT_S, p.model_copy(update={"white_level_bounded": False}), n_crossovers=0)
    assert _level(off, lines) == pytest.approx(_level(free, lines))


def test_white_level_never_raised():
    """No bump: the band measurement is the true level already; the fitted one may be a bit
    above or below it by chance, and the factor never exceeds 1."""
    lines, flights = _survey(bump_factor=0.0, seed=5)
    st = model_noise(lines, flights, DT_S, ProcessingParams(noise_family="white velocity"), n_crossovers=10)
    assert 0.8 < st.scale <= 1.0
    assert _level(st, lines) == pytest.approx(R_TRUE_CM2S2, rel=0.2)


# --- check_noise_corners: the FIR crossovers bound the noise a moved-corner model predicts

def _grid_survey(fir_std_mgal: float, seed: int = 2):
    """Six east–west and six north–south 20 km lines (36 crossovers) whose FIR estimates are
    independent smooth noises of std ``fir_std_mgal`` (no anomaly: the FIR error is its noise)."""
    rng = np.random.default_rng(seed)
    n = 2000                                   # 200 s at 0.1 s, 10 m steps
    lines, fir = [], {}
    for k in range(12):
        f = f"F{k}"
        s = np.linspace(0.0, 20.0, n)
        c = 2.0 + 3.0 * (k % 6)
        e, nn = (s, np.full(n, c)) if k < 6 else (np.full(n, c), s)
        w = np.convolve(rng.standard_normal(n + 199), np.ones(200) / 200, mode="valid")
        fir[f] = w / w.std() * fir_std_mgal
        t = 1000.0 * k + 0.1 * np.arange(n)
        lines.append(LineData(f"L{k}", f, "main" if k < 6 else "tie", None, slice(0, n), t, np.zeros(n),
                              np.zeros(n), np.full(n, 500.0), e, nn, np.zeros(n), 100.0))
    return lines, fir


def _stage_pair(level_cm2s2: float, info=None):
    """A white-velocity 'moved' stage at ``level_cm2s2`` everywhere, with an 'unmoved' twin
    (``info``: the model's record of the cautious decision; default a moved corner)."""
    from app.core.model_check import fir_noise_variance_mgal2
    from app.core.noise_model import NoiseComponent, NoiseModel
    from app.pipeline.stages.noise import NoiseStage

    model = NoiseModel((NoiseComponent(1, 0.0, 1.0),), DT_S, "white velocity",
                       info=info if info is not None else {"hidden_corners_hz": [0.02]})
    fit = SimpleNamespace(candidates=[], n_bins=0, fmax_hz=0.2, Q_mgal2=0.0, m=2)
    r = {f"F{k}": np.full(2000, level_cm2s2) for k in range(12)}
    moved = NoiseStage(fit, model, (0.1, 0.5), r, 1.0)
    moved.unmoved = NoiseStage(fit, model, (0.1, 0.5), {k: v * 0.1 for k, v in r.items()}, 0.1)
    return moved, fir_noise_variance_mgal2(model, level_cm2s2, DT_S, 100.0)


@pytest.mark.parametrize("info,what", [({"hidden_corners_hz": [0.02]}, "corners moved below the data"),
                                       ({"hidden_corners_hz": [], "white_height_nested": True},
                                        "random-walk height part")])
def test_corner_check_keeps_the_fit_when_the_move_overstates_fir_noise(info, what):
    """Both cautious decisions of the noise fit (a corner moved below the data, a bare white
    height given its random-walk part) are undone by the same crossover bound."""
    from app.pipeline.stages.noise import check_noise_corners

    p = ProcessingParams()
    lines, fir = _grid_survey(fir_std_mgal=3.0)
    moved, var1 = _stage_pair(1.0, info)
    level_right = 9.0 / var1                   # predicts the FIR noise the crossovers show
    moved, _ = _stage_pair(level_right, info)
    used = check_noise_corners(moved, lines, fir, DT_S, p)
    assert used is moved and not used.corner_check["applied"]
    assert used.corner_check["n"] == 36
    # the FIR noise variance is linear in the level: 9 mGal² per line, 18 per crossover
    assert used.corner_check["predicted_ms_mgal2"] == pytest.approx(18.0)
    assert used.unmoved is None                 # decided: the alternative is not kept
    moved, _ = _stage_pair(4.0 * level_right, info)  # 4x the noise variance the crossovers allow
    alternative = moved.unmoved
    used = check_noise_corners(moved, lines, fir, DT_S, p)
    assert used is alternative and used.corner_check["applied"]
    assert "kept" in used.corner_check["reason"] and what in used.corner_check["reason"]
    assert used.corner_check["white_height_nested"] == bool(info.get("white_height_nested"))
    off = check_noise_corners(_stage_pair(4.0 * level_right, info)[0], lines, fir, DT_S,
                              p.model_copy(update={"noise_corner_check": False}))
    assert not off.corner_check["applied"]


def _short_lines(seconds: float, seed: int = 5):
    """Four lines of ``seconds`` each of white GNSS velocity noise (R_TRUE_CM2S2) on one flight."""
    rng = np.random.default_rng(seed)
    n_line = int(round(seconds / DT_S))
    z = np.diff(SIGMA_V_MS * rng.standard_normal(N_LINES * n_line + 1)) / DT_S * 1e5
    t = np.arange(z.size) * DT_S
    flights = {"F1": SimpleNamespace(z_mgal=z, heights_only=False, t_s=t)}
    lines = []
    for k in range(N_LINES):
        sl = slice(k * n_line, (k + 1) * n_line)
        lines.append(LineData(f"L{k}", "F1", "main", None, sl, t[sl], np.zeros(n_line), np.zeros(n_line),
                              np.full(n_line, 500.0), np.linspace(0, 9, n_line), np.full(n_line, 2.0 * k),
                              z[sl].copy(), 100.0))
    return lines, flights


def test_short_lines_fit_on_shorter_stretches_and_say_so():
    """Lines of 90 s (a 12 km line at 130 m/s) have no 120 s stretch: the fit uses the
    60 s ones, finds the true white-velocity level, and the report and a warning say so; lines
    of 45 s are refused with the longest stretch named.  600 s lines use 120 s stretches."""
    p = ProcessingParams()
    lines, flights = _short_lines(90.0)
    stage = model_noise(lines, flights, DT_S, p)
    assert stage.fit_min_stretch_s == 60.0 and stage.describe()["fit_min_stretch_s"] == 60.0
    assert "fitted on stretches of 60-120 s" in stage.warning
    # the error of z the smoother is given, against the true white-velocity PSD (two-sided, mGal²/Hz)
    f = np.array([0.02, 0.05, 0.1, 0.2])
    true_psd = (1e5 * SIGMA_V_MS) ** 2 / DT_S * (2.0 * np.sin(np.pi * f * DT_S)) ** 2
    assert np.allclose(stage.model.psd(f, _level(stage, lines)), true_psd, rtol=0.3)
    with pytest.raises(ValueError, match="the longest is 45 s"):
        model_noise(*_short_lines(45.0), DT_S, p)
    long_stage = model_noise(*_survey(bump_factor=0.0), DT_S, p)
    assert long_stage.fit_min_stretch_s == 120.0 and long_stage.warning == ""


# --- check_noise_family: crossovers and repeat passes bound the FIR noise a coloured velocity predicts

def _repeat_track(fir_std_mgal: float, seed: int = 4):
    """One 60 km track flown four times, both ways, at 100 m/s (0.5 s steps); the FIR estimate
    of every pass is a shared anomaly plus its own smooth noise of std ``fir_std_mgal``."""
    rng = np.random.default_rng(seed)
    n, dt = 1200, 0.5
    s_km = np.linspace(0.0, 60.0, n)
    lines, fir = [], {}
    for k in range(4):
        e = s_km if k % 2 == 0 else s_km[::-1]
        w = np.convolve(rng.standard_normal(n + 199), np.ones(200) / 200, mode="valid")
        fir[f"F{k}"] = 15.0 * np.sin(e / 7.0) + w / w.std() * fir_std_mgal
        t = 1000.0 * k + dt * np.arange(n)
        lines.append(LineData(f"R{k}", f"F{k}", "repeat", "T1", slice(0, n), t, np.zeros(n), np.zeros(n),
                              np.full(n, 500.0), e, np.full(n, 3.0), np.zeros(n), 100.0))
    return lines, fir


def _family_pair(chosen_var_mgal2: float, alternative_var_mgal2: float):
    """A 'coloured velocity' stage predicting ``chosen_var_mgal2`` of FIR noise per pass, with
    an alternative predicting ``alternative_var_mgal2``."""
    from app.core.model_check import fir_noise_variance_mgal2
    from app.core.noise_model import NoiseComponent, NoiseModel
    from app.pipeline.stages.noise import NoiseStage

    fit = SimpleNamespace(candidates=[], n_bins=0, fmax_hz=0.2, Q_mgal2=0.0, m=2)
    model = NoiseModel((NoiseComponent(1, 0.0, 1.0),), 0.5, "white velocity")
    unit = fir_noise_variance_mgal2(model, 1.0, 0.5, 100.0)
    coloured = NoiseModel((NoiseComponent(1, 0.0, 1.0),), 0.5, "Gauss-Markov velocity")

    def stage(m, var):
        return NoiseStage(fit, m, (0.1, 0.5), {f"F{k}": np.full(1200, var / unit) for k in range(4)}, 1.0)

    chosen = stage(coloured, chosen_var_mgal2)
    chosen.alternative = stage(model, alternative_var_mgal2)
    return chosen


def test_family_check_falls_back_when_the_repeats_show_less_fir_noise():
    """The 4 passes give 3 contrasts at each of 7 positions (one every 100 s of flight); FIR
    noise 1.5 mGal per pass.  A model predicting 4x that
    variance gives way to the alternative that predicts it; one predicting it is kept; and an
    alternative that misses by more the other way (1/10 of it) does not replace a 2.5x one."""
    from app.pipeline.stages.noise import check_noise_family

    p = ProcessingParams()
    lines, fir = _repeat_track(fir_std_mgal=1.5)
    st = _family_pair(4.0 * 2.25, 2.25)
    alt = st.alternative
    used = check_noise_family(st, lines, fir, 0.5, p)
    assert used is alt and used.family_check["applied"] and used.family_check["n"] == 21
    assert used.family_check["predicted_ms_mgal2"] == pytest.approx(9.0)
    assert "white velocity used" in used.family_check["reason"]
    assert "family_check" in used.describe()
    st = _family_pair(2.25, 0.5)
    used = check_noise_family(st, lines, fir, 0.5, p)
    assert used is st and not used.family_check["applied"] and used.alternative is None
    st = _family_pair(2.5 * 2.25, 0.225)
    used = check_noise_family(st, lines, fir, 0.5, p)
    assert used is st and not used.family_check["applied"] and "no better" in used.family_check["reason"]
    off = _family_pair(4.0 * 2.25, 2.25)
    off_used = check_noise_family(off, lines, fir, 0.5, p.model_copy(update={"noise_family_check": False}))
    assert off_used is off and off_used.family_check is None and off_used.alternative is None


def test_noise_fit_bridges_short_holes_only():
    """A line's holes of at most BRIDGE_MAX_S inside it take the acceleration's prediction of z;
    a longer hole, or missing values at the line's ends, stay missing (the fit splits there)."""
    from app.pipeline.stages.noise import BRIDGE_MAX_S, bridged

    dt = 0.5
    n = 400
    z = np.ones(n)
    z[:3] = np.nan                                   # the line's start
    z[100:104] = np.nan                              # 2 s: bridged
    long = int(BRIDGE_MAX_S / dt) + 2
    z[200:200 + long] = np.nan                       # longer than BRIDGE_MAX_S: kept
    ln = LineData("L", "F", "main", None, slice(10, 10 + n), dt * np.arange(n), np.zeros(n), np.zeros(n),
                  np.zeros(n), np.zeros(n), np.zeros(n), z, 100.0)
    pred = {"F": (np.arange(500, dtype=float), 1000)}
    out = bridged(ln, pred, dt)
    np.testing.assert_array_equal(out[100:104], np.arange(110, 114))
    assert np.isnan(out[:3]).all() and np.isnan(out[200:200 + long]).all()
    assert np.array_equal(out[np.isfinite(z)], z[np.isfinite(z)])
    assert bridged(ln, {}, dt) is z
    short = bridged(ln, {"F": (np.arange(500, dtype=float), 3)}, dt)   # the flight allows 3 epochs
    assert np.isnan(short[100:104]).all()
