"""Stage 1's spike repair on heights-only GNSS: a cycle slip in the heights that z's matched
templates miss under turbulence is found in z's double integral and removed as a step of its
size (simulation with known truth, no simulator)."""

import numpy as np

from app.config import ProcessingParams
from app.core import geodesy
from app.core.baselines import fir_lowpass_mgal
from app.core.measurement import anomaly_measurement_mgal
from app.pipeline.stages.measurement import despike_z


def _record(seed: int, steps: dict):
    """Two hours at 2 Hz: heave, a 15 mGal anomaly, the gravimeter/GNSS mismatch of a turbulent
    record as 2 cm of white displacement (z's noise rising as f⁴, ~20 000 mGal) and 1 cm of
    white height noise; ``steps`` {epoch: size m} added to the heights."""
    rng = np.random.default_rng(seed)
    dt = 0.5
    t = 1000.0 + np.arange(14400) * dt
    h = 3000.0 + sum(a * np.sin(2 * np.pi * t / p + rng.uniform(0, 6.3)) for a, p in ((0.5, 19.0), (2.0, 60.0)))
    eps = rng.normal(0, 0.02, t.size)
    mismatch = np.r_[0.0, np.diff(eps, 2), 0.0] / dt ** 2                  # m/s²
    fbar = np.r_[np.nan, np.diff(geodesy.vertical_velocity_from_heights_ms(t, h)) / dt]
    fbar = fbar + 15e-5 * np.sin(2 * np.pi * t / 700.0) + mismatch
    heights = h + rng.normal(0, 0.01, t.size)
    clean_heights = heights.copy()
    for j, size in steps.items():
        heights[j:] += size
    zero = np.zeros(t.size)

    def z_of(hh):
        return anomaly_measurement_mgal(fbar, t, geodesy.vertical_velocity_from_heights_ms(t, hh), zero, zero)

    return t, z_of(heights), z_of(clean_heights)


def test_cycle_slips_missed_by_the_templates_are_found_in_the_double_integral():
    steps = {3000: 0.25, 9000: -0.2}
    t, z, clean = _record(2, steps)
    assert np.nanstd(clean) > 15_000.0
    p = ProcessingParams()
    # without the double integral the templates miss both slips
    _, ev_off = despike_z(z.copy(), t, p.model_copy(update={"height_step_threshold": None}), [], True)
    found_off = [f for f in ev_off.get("height_outliers", []) for j in steps if abs(f["time"] - t[j]) <= 1.0]
    assert found_off == []
    notes: list = []
    fixed, ev = despike_z(z.copy(), t, p, notes, True)
    for j, size in steps.items():
        hit = [f for f in ev["height_outliers"] if abs(f["time"] - t[j]) <= 0.5]
        assert len(hit) == 1 and hit[0]["kind"] == "step" and abs(hit[0]["size_m"] - size) < 0.04, (j, hit)
    assert ev["fraction"] < 0.001
    err = np.abs(fir_lowpass_mgal(fixed[1:], 0.5) - fir_lowpass_mgal(clean[1:], 0.5))[300:-300]
    left = np.abs(fir_lowpass_mgal(z[1:], 0.5) - fir_lowpass_mgal(clean[1:], 0.5))[300:-300]
    assert left.max() > 10.0 and err.max() < 2.5, (left.max(), err.max())
    # the clean record: nothing flagged by the double integral
    _, ev_clean = despike_z(clean.copy(), t, p, [], True)
    assert not [f for f in ev_clean.get("height_outliers", []) if f["kind"] == "step" and abs(f["size_m"]) > 0.1]


def test_height_misfit_only_for_a_gravimeter_at_least_as_fast_as_the_gnss():
    """The gravimeter's double integral less the heights is formed for a 20 Hz gravimeter on
    1 Hz GNSS — level flight at 9.8 m/s², so S is a straight line (the gravimeter's integral
    starts 10 s before the GNSS) and a 0.3 m cycle slip at epoch 300 a step of −0.3 m on it —
    and not for a 0.5 Hz gravimeter (None: z's own double integral is searched there)."""
    from app.core import gravimeter as gm
    from app.pipeline.stages.measurement import height_misfit

    t = 10.0 + np.arange(600) * 1.0
    h = np.full(t.size, 3000.0)
    h[300:] += 0.3
    gamma = np.full(t.size, 980000.0)
    zero = np.zeros(t.size)
    for rate, formed in ((20.0, True), (0.5, False)):
        stamps = (np.arange(int(620 * rate)) + 0.5) / rate
        series = gm.integrate_samples(stamps, np.full(stamps.size, 9.8), dejitter=False)
        s = height_misfit(series, (t, h, gamma, zero), (0.0, 1.0, 0.0))
        assert (s is not None) == formed
        if formed:
            design = np.column_stack([np.ones(t.size), t, np.arange(t.size) >= 300])
            coef, *_ = np.linalg.lstsq(design, s, rcond=None)
            assert abs(coef[2] + 0.3) < 1e-6
            np.testing.assert_allclose(s, design @ coef, atol=1e-6)
