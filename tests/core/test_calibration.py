"""Tests of in-flight gravimeter calibration (app.core.calibration).

Truth comes from simulations written here: sinusoidal manoeuvres with exact
(analytic) interval means, a first-order lag solved analytically, a random-walk
anomaly, white GNSS and gravimeter noise, a linear drift.
"""

import numpy as np
import pytest
from scipy.signal import welch

from app.core.calibration import (
    CalibrationSpectra,
    anomaly_level_mgal2_s,
    calibrate,
    corrected_specific_force_ms2,
    plan_calibration,
)

DT = 0.1
G = 9.8


def _sinus_means(t_edges, amp, omega, phase):
    """Interval means over (t_{k-1}, t_k] of amp·sin(ωt+φ) and of its derivative.

    amp, phase: shape (R,); returns two arrays (R, n)."""
    a = np.asarray(amp, dtype=float)[:, None]
    ph = np.asarray(phase, dtype=float)[:, None]
    t = t_edges[None, :]
    prim = -a * np.cos(omega * t + ph) / omega
    val = a * np.sin(omega * t + ph)
    dt = np.diff(t_edges)[None, :]
    return np.diff(prim, axis=1) / dt, np.diff(val, axis=1) / dt


def _simulate(rng, reps, n, spectra, truth, omegas=(0.35, 0.25, 0.45), powers=(2.0, 1.125, 1.125)):
    """Manoeuvre segments at 10 Hz; returns t (n,), z, f', f_x, f_y (reps, n) in m/s².

    The gravimeter equation τḟ' + kf' = f_3 − δ1 f_y + δ2 f_x + δf_T + δf is used in
    interval-mean form with exact (analytic) means of ḟ' and f'.
    """
    tau, k, d1, d2 = truth
    t_edges = np.arange(n + 1) * DT
    t = t_edges[1:]
    wz, wx, wy = omegas
    amp = [np.full(reps, np.sqrt(2 * p)) for p in powers]
    fz, fz_dot = _sinus_means(t_edges, amp[0], wz, rng.uniform(0, 2 * np.pi, reps))
    fz = fz + G
    fx, _ = _sinus_means(t_edges, amp[1], wx, rng.uniform(0, 2 * np.pi, reps))
    fy, _ = _sinus_means(t_edges, amp[2], wy, rng.uniform(0, 2 * np.pi, reps))
    mgal = 1e-5
    # random-walk anomaly, increment variance d·Δt (mGal²), arbitrary start
    dg = mgal * (rng.normal(0, np.sqrt(spectra.d_dg_mgal2_s * DT), (reps, n)).cumsum(axis=1)
                 + rng.normal(0, 30, (reps, 1)))
    df = mgal * rng.normal(0, np.sqrt(spectra.d_f_mgal2_s / DT), (reps, n))
    drift = mgal * (rng.normal(0, 50, (reps, 1)) + rng.normal(0, 0.02, (reps, 1)) * t)
    if spectra.gnss == "doppler":
        dv = rng.normal(0, np.sqrt(spectra.d_v_m2_s / DT), (reps, n + 1))
        gnss_acc = np.diff(dv, axis=1) / DT
    else:
        dh = rng.normal(0, np.sqrt(spectra.d_h_m2_s / DT), (reps, n + 2))
        gnss_acc = np.diff(dh, 2, axis=1) / DT ** 2
    # f_3 = τḟ' + kf' + δ1 f_y − δ2 f_x − δf_T − δf ;  z = f' − f_3 + δg − (GNSS acc. error)
    f3 = tau * fz_dot + k * fz + d1 * fy - d2 * fx - drift - df
    z = fz - f3 + dg - gnss_acc
    return t, z, fz, fx, fy


SPECTRA = {
    "doppler": CalibrationSpectra(d_f_mgal2_s=25.0, d_dg_mgal2_s=1.0, gnss="doppler",
                                  d_v_m2_s=(0.05e-2) ** 2),
    "phase": CalibrationSpectra(d_f_mgal2_s=25.0, d_dg_mgal2_s=1.0, gnss="phase",
                                d_h_m2_s=(0.5e-2) ** 2),
}
TRUTH = (2.0, 1.003, 2e-4, -3e-4)


@pytest.mark.parametrize("gnss", ["doppler", "phase"])
def test_monte_carlo_matches_dxx_and_planner(gnss):
    spectra = SPECTRA[gnss]
    reps, n = 60, 6000
    rng = np.random.default_rng(20261123 + (gnss == "phase"))
    t, z, fz, fx, fy = _simulate(rng, reps, n, spectra, TRUTH)
    res = [calibrate(t, z[i], fz[i], fx[i], fy[i], spectra=spectra, tau0_s=1.9, k0=1.0)
           for i in range(reps)]
    x = np.array([r.x for r in res])
    std = np.array([r.std for r in res])
    err = x - np.array(TRUTH)
    # each realisation: recovered within 3 standard errors (allow the odd 3σ excursion)
    assert np.all(np.abs(err[0]) < 3 * std[0])
    assert np.mean(np.abs(err) < 3 * std) >= 0.97
    # std from D_XX is essentially the same for every realisation (sinusoid powers fixed)
    assert np.ptp(std, axis=0).max() / std.mean(axis=0).min() < 0.1
    scatter = err.std(axis=0, ddof=1)
    ratio = scatter / std.mean(axis=0)
    assert np.all(np.abs(ratio - 1) < 0.3), ratio
    # no bias beyond the Monte Carlo's resolution
    assert np.all(np.abs(err.mean(axis=0)) < 4 * scatter / np.sqrt(reps))
    # residual whiteness: the spectra describe the data
    chi2 = np.mean([r.chi2_per_dof for r in res])
    assert abs(chi2 - 1) < 0.05
    # the planner predicts the same scatter for the same conditions
    plan = plan_calibration(n * DT, omega_rad_s=0.35, omega_x_rad_s=0.25, omega_y_rad_s=0.45,
                            power_z_ms2sq=2.0, power_x_ms2sq=1.125, power_y_ms2sq=1.125,
                            gnss=gnss, d_v_m2_s=spectra.d_v_m2_s, d_h_m2_s=spectra.d_h_m2_s,
                            d_f_mgal2_s=spectra.d_f_mgal2_s, d_dg_mgal2_s=spectra.d_dg_mgal2_s)
    assert plan["names"] == ["tau", "k", "d1", "d2"]
    assert not plan["degenerate_joint"]
    assert np.all(np.abs(plan["std"] / scatter - 1) < 0.3), plan["std"] / scatter
    assert np.all(np.abs(plan["std"] / std.mean(axis=0) - 1) < 0.1)


def _lagged_sinusoid_means(t_edges, amp, omega, phase, tau, k):
    """Interval means of the steady-state output of τẏ + ky = amp·sin(ωt+φ)."""
    h = 1.0 / (k + 1j * omega * tau)
    return _sinus_means(t_edges, np.array([amp * abs(h)]), omega,
                        np.array([phase + np.angle(h)]))[0][0]


def test_recovers_lag_from_first_order_physics_noise_free():
    """Vertical acceleration → gravimeter solved analytically (transfer 1/(k+iωτ))."""
    tau, k, d1, d2 = 2.3, 0.998, 4e-4, -2.5e-4
    n = 3000
    t_edges = np.arange(n + 1) * DT
    t = t_edges[1:]
    comps_z = [(1.5, 0.3, 0.2), (0.8, 0.11, 1.3), (0.4, 0.62, 2.0)]    # (amp, ω, φ) of vertical acc.
    comps_x = [(1.2, 0.21, 0.5), (0.5, 0.5, 2.5)]
    comps_y = [(1.0, 0.17, 1.0), (0.6, 0.41, 0.1)]

    def means(comps):
        return sum(_sinus_means(t_edges, np.array([a]), w, np.array([p]))[0][0] for a, w, p in comps)

    a_z, f_x, f_y = means(comps_z), means(comps_x), means(comps_y)
    f3 = G + a_z                                         # true vertical specific force (δg = 0)
    # f_g = f_3 − δ1 f_y + δ2 f_x passes through the lag: constant → G/k, sinusoids by transfer fn
    f_raw = G / k + sum(_lagged_sinusoid_means(t_edges, a, w, p, tau, k) for a, w, p in comps_z)
    f_raw = f_raw + sum(_lagged_sinusoid_means(t_edges, -d1 * a, w, p, tau, k) for a, w, p in comps_y)
    f_raw = f_raw + sum(_lagged_sinusoid_means(t_edges, d2 * a, w, p, tau, k) for a, w, p in comps_x)
    z = f_raw - f3                                       # = f̄' − V̇ − γ + E with δg = 0
    spectra = CalibrationSpectra(d_f_mgal2_s=1e-6, d_dg_mgal2_s=1e-6, d_v_m2_s=1e-12)
    r = calibrate(t, z, f_raw, f_x, f_y, spectra=spectra)
    assert r.tau_s == pytest.approx(tau, abs=1e-6)
    assert r.k == pytest.approx(k, abs=1e-8)
    assert r.d1_rad == pytest.approx(d1, abs=1e-8)
    assert r.d2_rad == pytest.approx(d2, abs=1e-8)
    # applying the estimate restores f_3 (interior, away from the stencil's edges)
    from app.core.calibration import derivative_of_interval_means
    fdot = derivative_of_interval_means(f_raw, DT)
    f_corr = corrected_specific_force_ms2(r.tau_s * fdot + r.k * f_raw[3:-3], f_x[3:-3], f_y[3:-3],
                                          r.d1_rad, r.d2_rad)
    assert np.max(np.abs(f_corr - f3[3:-3])) < 1e-6       # < 0.1 mGal


def test_subset_estimation_and_exact_fdot():
    spectra = SPECTRA["doppler"]
    reps, n = 40, 4000
    truth = (2.0, 1.0, 0.0, 0.0)
    rng = np.random.default_rng(7)
    t, z, fz, fx, fy = _simulate(rng, reps, n, spectra, truth)
    res = [calibrate(t, z[i], fz[i], spectra=spectra, params=("k", "tau"), tau0_s=2.5, k0=0.9)
           for i in range(reps)]
    assert res[0].names == ("tau", "k")
    assert res[0].d1_rad == 0.0 and res[0].d2_rad == 0.0
    x = np.array([r.x for r in res])
    std = np.mean([r.std for r in res], axis=0)
    err = x - np.array(truth[:2])
    assert np.all(np.abs(err.std(axis=0, ddof=1) / std - 1) < 0.3)
    # one parameter, the other held at its nominal (here true) value
    rk = calibrate(t, z[0], fz[0], spectra=spectra, params=("k",), tau0_s=2.0)
    assert rk.tau_s == 2.0 and abs(rk.k - 1.0) < 3 * rk.std[0]
    # the 7-point stencil for ḟ' agrees with the exact interval means of ḟ'
    t_edges = np.arange(n + 1) * DT
    rng2 = np.random.default_rng(11)
    phase = rng2.uniform(0, 2 * np.pi, 1)
    fz1, fz1_dot = _sinus_means(t_edges, np.array([2.0]), 0.35, phase)
    z1 = -2.0 * fz1_dot[0] + 1e-5 * rng2.normal(0, 30, n)
    r_exact = calibrate(t, z1, fz1[0] + G, spectra=spectra, params=("tau", "k"), fdot_raw_ms3=fz1_dot[0])
    r_stencil = calibrate(t, z1, fz1[0] + G, spectra=spectra, params=("tau", "k"))
    np.testing.assert_allclose(r_stencil.x, r_exact.x, atol=1e-3 * r_exact.std.min())
    np.testing.assert_allclose(r_stencil.std, r_exact.std, rtol=1e-6)
    plan = plan_calibration(n * DT, omega_rad_s=0.35, power_z_ms2sq=2.0, gnss="doppler",
                            d_v_m2_s=spectra.d_v_m2_s, d_f_mgal2_s=25.0, d_dg_mgal2_s=1.0,
                            params=("k",), joint=False)
    assert plan["std"][0] == pytest.approx(rk.std[0], rel=0.1)


def test_spectra_match_simulated_noise_periodogram():
    """Discrete spectra equal the Welch density of the GNSS-rate noise model."""
    rng = np.random.default_rng(3)
    sp = CalibrationSpectra(d_f_mgal2_s=25.0, d_dg_mgal2_s=0.0, d_v_m2_s=(0.5e-2) ** 2)
    n = 200_000
    dv = rng.normal(0, np.sqrt(sp.d_v_m2_s / DT), n + 1)
    noise = np.diff(dv) / DT + 1e-5 * rng.normal(0, np.sqrt(sp.d_f_mgal2_s / DT), n)
    f_hz, p_onesided = welch(noise, fs=1 / DT, nperseg=1024)
    s_two_sided_rad = p_onesided / 2 / (2 * np.pi)          # per Hz one-sided → per rad/s two-sided
    model = sp.density_ms2(2 * np.pi * f_hz, DT)
    band = (f_hz > 0.05) & (f_hz < 4.9)
    assert np.median(s_two_sided_rad[band] / model[band]) == pytest.approx(1.0, abs=0.05)
    # per-epoch variances of the same noise give the same spectra
    sp3 = CalibrationSpectra.from_epoch_variances(DT, f_var_mgal2=np.var(1e5 * (noise - np.diff(dv) / DT)),
                                                  dg_step_var_mgal2=0.0,
                                                  r_cm2s2=np.var(1e2 * dv))
    assert sp3.d_v_m2_s == pytest.approx(sp.d_v_m2_s, rel=0.02)
    assert sp3.d_f_mgal2_s == pytest.approx(sp.d_f_mgal2_s, rel=0.02)
    # continuous forms of seed 001: ω² S_V + S_δf + d/(2πω²)
    sp2 = CalibrationSpectra(d_f_mgal2_s=25.0, d_dg_mgal2_s=2.0, d_v_m2_s=1e-5, discrete=False)
    w = np.array([0.01, 0.3, 3.0])
    expect = (2.0e-10 / w ** 2 + 1e-5 * w ** 2 + 25e-10) / (2 * np.pi)
    np.testing.assert_allclose(sp2.density_ms2(w, DT), expect, rtol=1e-12)


def test_planner_closed_forms_and_paper_formula():
    kw = dict(speed_ms=100 / 3.6, gnss="doppler", discrete=False)
    p = plan_calibration(3600.0, **kw)
    w = 9.7803 / (100 / 3.6)
    assert p["omega_rad_s"] == pytest.approx(w)
    assert p["d_dg_mgal2_s"] == pytest.approx(anomaly_level_mgal2_s(100 / 3.6, 0.1))
    # long record: the finite-record (Fejér) planner approaches 2π/(L P Γ)
    np.testing.assert_allclose(p["std_single"], p["std_asymptotic_single"], rtol=0.02)
    # the printed tables use 4π/T: variance 2× the integrated one for δ and τ
    ratio = p["std_paper_formula_single"] / p["std_asymptotic_single"]
    np.testing.assert_allclose(ratio[[0, 2, 3]], np.sqrt(2), rtol=1e-9)
    # hand evaluation of Table 1's δ row with the stated parameters
    d = 0.1 * (100 / 3.6) / 1000 * 1e-10
    num = w ** 4 * 0.25e-4 + w ** 2 * 25e-10 + d
    assert p["std_paper_formula_single"][2] == pytest.approx(np.sqrt(2 * num / (3600 * 3 * w ** 2)))
    # same frequency on all channels: flagged as degenerate for a joint 4-parameter fit
    assert p["degenerate_joint"]


def _one_segment(seed=1, n=3000, omegas=(0.35, 0.25, 0.45), powers=(2.0, 1.125, 1.125)):
    rng = np.random.default_rng(seed)
    return _simulate(rng, 1, n, SPECTRA["doppler"], TRUTH, omegas=omegas, powers=powers)


def test_bad_input_raises_clear_errors():
    sp = SPECTRA["doppler"]
    t, z, fz, fx, fy = _one_segment()
    z, fz, fx, fy = z[0], fz[0], fx[0], fy[0]
    with pytest.raises(ValueError, match="too short"):
        calibrate(t[:40], z[:40], fz[:40], fx[:40], fy[:40], spectra=sp)
    with pytest.raises(ValueError, match="not excited"):
        calibrate(t, z, fz, fx, np.full_like(fy, 0.3), spectra=sp)
    with pytest.raises(ValueError, match="not excited"):
        calibrate(t, z, np.full_like(fz, G), fx, fy, spectra=sp, params=("tau", "k"))
    # four regressors from one frequency line: singular normal matrix
    t1, z1, fz1, fx1, fy1 = _one_segment(omegas=(0.35, 0.35, 0.35))
    with pytest.raises(ValueError, match="singular"):
        calibrate(t1, z1[0], fz1[0], fx1[0], fy1[0], spectra=sp)
    # … but two of them are fine
    r = calibrate(t1, z1[0], fz1[0], spectra=sp, params=("tau", "k"))
    assert np.all(np.isfinite(r.std))
    zn = z.copy()
    zn[100] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        calibrate(t, zn, fz, fx, fy, spectra=sp)
    tg = t.copy()
    tg[1500:] += 1.0
    with pytest.raises(ValueError, match="uniformly"):
        calibrate(tg, z, fz, fx, fy, spectra=sp)
    with pytest.raises(ValueError, match="unknown"):
        calibrate(t, z, fz, fx, fy, spectra=sp, params=("tau", "scale"))
    with pytest.raises(ValueError, match="needs f_y"):
        calibrate(t, z, fz, spectra=sp, params=("d1",))
    with pytest.raises(ValueError, match="drift_degree"):
        calibrate(t, z, fz, fx, fy, spectra=sp, drift_degree=0)
    with pytest.raises(ValueError, match="samples"):
        calibrate(t, z[:-1], fz, fx, fy, spectra=sp)
    with pytest.raises(ValueError, match="gnss"):
        CalibrationSpectra(d_f_mgal2_s=1.0, d_dg_mgal2_s=1.0, gnss="ppp")
    with pytest.raises(ValueError, match="singular"):
        plan_calibration(600.0, speed_ms=50.0, power_x_ms2sq=0.0)
    with pytest.raises(ValueError, match="omega_rad_s or"):
        plan_calibration(600.0, d_dg_mgal2_s=1.0)
