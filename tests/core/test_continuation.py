"""Equivalent-source continuation (app.core.continuation) on synthetic draped surveys.

The field is harmonica's point_gravity of shallow (≤ 3.2 km below the flight) and deep point masses
(std ~16 mGal at 3000 m); lines 100 m sampled, draped 3000 ± 200 m, with along-line correlated line
errors (Gauss-Markov, 3 km, 1.5 mGal) whose std is given to the fit.
"""

from __future__ import annotations

import harmonica as hm
import numpy as np
import pytest

from app.core.continuation import block_average_lines, draped_datum_height_m, fit_equivalent_sources

H0 = 3000.0


def _errors(lab, step, corr_m, sd, rng):
    err = np.empty(lab.size)
    a = np.exp(-step / corr_m)
    for name in np.unique(lab):
        idx = np.flatnonzero(lab == name)
        w = rng.standard_normal(idx.size) * sd
        x = np.empty(idx.size)
        x[0] = w[0]
        for i in range(1, idx.size):
            x[i] = a * x[i - 1] + np.sqrt(1 - a * a) * w[i]
        err[idx] = x
    return err


def _survey(seed=0, n_main=8, length=30000.0, spacing=2000.0, drape=200.0, noise=1.5, corr_m=3000.0,
            step=100.0, repeat_heights=()):
    rng = np.random.default_rng(seed)
    width = (n_main - 1) * spacing
    ns, nd = 300, 25
    src = (np.r_[rng.uniform(-8e3, length + 8e3, ns), rng.uniform(-3e4, length + 3e4, nd)],
           np.r_[rng.uniform(-8e3, width + 8e3, ns), rng.uniform(-3e4, width + 3e4, nd)],
           np.r_[rng.uniform(-2500.0, 200.0, ns), -rng.uniform(6e3, 2e4, nd)])
    ms = np.r_[rng.standard_normal(ns) * 1e10, np.zeros(nd)]
    md = np.r_[np.zeros(ns), rng.standard_normal(nd) * 1e12]
    gx, gy = np.meshgrid(np.arange(0, length + 1, 1000.0), np.arange(0, width + 1, 1000.0))
    ref = (gx.ravel(), gy.ravel(), np.full(gx.size, H0))
    mass = (ms * 14 / np.std(hm.point_gravity(ref, src, ms, field="g_z"))
            + md * 8 / np.std(hm.point_gravity(ref, src, md, field="g_z")))

    def field(e, n, h):
        return hm.point_gravity((e, n, np.broadcast_to(h, np.shape(e))), src, mass, field="g_z")

    k = 2 * np.pi / rng.uniform(5000, 15000, 12)
    th, ph = rng.uniform(0, np.pi, 12), rng.uniform(0, 2 * np.pi, 12)

    def drape_fn(x, y):
        return np.sum(np.cos(np.multiply.outer(x, k * np.sin(th)) + np.multiply.outer(y, k * np.cos(th)) + ph),
                      axis=-1)

    E, N, L = [], [], []
    for i in range(n_main):
        x = np.arange(0, length + 1, step)
        E.append(x if i % 2 == 0 else x[::-1])
        N.append(np.full(x.size, i * spacing))
        L += [f"L{i}"] * x.size
    for j, xt in enumerate(np.linspace(2000, length - 2000, 3)):
        y = np.arange(-2000, width + 2001, step)
        E.append(np.full(y.size, xt))
        N.append(y)
        L += [f"T{j}"] * y.size
    e, n, lab = np.concatenate(E), np.concatenate(N), np.array(L)
    d = drape_fn(e, n)
    h = H0 + (d - 0.5 * (d.max() + d.min())) / (0.5 * np.ptp(d)) * drape
    # repeat passes over one track between two main lines, each at its own constant height
    for r, hr in enumerate(repeat_heights):
        x = np.arange(5000, length - 5000 + 1, step)
        e = np.r_[e, x]
        n = np.r_[n, np.full(x.size, 0.5 * width + 0.25 * spacing)]
        h = np.r_[h, np.full(x.size, hr)]
        lab = np.r_[lab, np.full(x.size, f"R{r}")]
    true = field(e, n, h)
    obs = true + _errors(lab, step, corr_m, noise, rng)
    return dict(e=e, n=n, h=h, lab=lab, true=true, obs=obs, std=np.full(e.size, noise), field=field,
                gx=gx.ravel(), gy=gy.ravel())


@pytest.fixture(scope="module")
def draped():
    return _survey(seed=3)


@pytest.fixture(scope="module")
def draped_fit(draped):
    S = draped
    return fit_equivalent_sources(S["e"], S["n"], S["h"], S["obs"], S["std"], S["lab"], error_corr_m=3000.0)


def test_continued_anomaly_at_datum_vs_truth(draped, draped_fit):
    S, m = draped, draped_fit
    assert m.method == "exact" and m.info["line_spacing_m"] == pytest.approx(2000.0, rel=0.15)
    line_rms = np.sqrt(np.mean((S["obs"] - S["true"]) ** 2))
    truth_datum = S["field"](S["e"], S["n"], H0)
    # the drape matters: the field at flight height differs from the one at the datum
    assert np.sqrt(np.mean((S["true"] - truth_datum) ** 2)) > 0.3
    cont = m.predict(S["e"], S["n"], H0)
    rms = np.sqrt(np.mean((cont - truth_datum) ** 2))
    assert rms <= 1.1 * line_rms, (rms, line_rms)
    # not continuing (the line values as if at the datum) is worse
    assert np.sqrt(np.mean((S["obs"] - truth_datum) ** 2)) > rms
    # between the lines too (grid nodes inside the survey), with a calibrated posterior std
    gt = S["field"](S["gx"], S["gy"], H0)
    gp, gs = m.predict(S["gx"], S["gy"], H0), m.predict_std(S["gx"], S["gy"], H0)
    assert np.sqrt(np.mean((gp - gt) ** 2)) <= 1.1 * line_rms
    z = np.sqrt(np.mean(((gp - gt) / gs) ** 2))
    assert 0.7 < z < 1.4, z
    # a draped datum: the surface through the flight heights, anomaly there vs truth there
    hd = draped_datum_height_m(S["gx"], S["gy"], S["e"], S["n"], S["h"], smoothing_m=1500.0)
    assert np.ptp(hd) > 150.0
    assert np.sqrt(np.mean((m.predict(S["gx"], S["gy"], hd) - S["field"](S["gx"], S["gy"], hd)) ** 2)) <= 1.1 * line_rms


def test_repeat_lines_at_two_heights_agree_after_continuation():
    S = _survey(seed=5, drape=100.0, repeat_heights=(2600.0, 3400.0))
    ra, rb = S["lab"] == "R0", S["lab"] == "R1"
    before = np.sqrt(np.mean((S["obs"][ra] - S["obs"][rb]) ** 2))
    # each pass continued with its own fit (the survey lines + that pass only)
    base = ~(ra | rb)
    cont = []
    for sel in (ra, rb):
        k = base | sel
        m = fit_equivalent_sources(S["e"][k], S["n"][k], S["h"][k], S["obs"][k], S["std"][k], S["lab"][k],
                                   error_corr_m=3000.0)
        cont.append(m.predict(S["e"][sel], S["n"][sel], H0))
    after = np.sqrt(np.mean((cont[0] - cont[1]) ** 2))
    signal = np.sqrt(np.mean((S["true"][ra] - S["true"][rb]) ** 2))     # the vertical gradient × 800 m
    assert signal > 2.0
    assert after < 0.5 * before, (before, after, signal)
    truth = S["field"](S["e"][ra], S["n"][ra], H0)
    assert np.sqrt(np.mean((cont[0] - truth) ** 2)) < np.sqrt(np.mean((S["obs"][ra] - S["true"][ra]) ** 2))


def test_exact_solve_is_harmonicas_ridge(draped, draped_fit):
    """The posterior mean is harmonica's EquivalentSources fit with damping α and weights 1/(ν·σ)²."""
    m = draped_fit
    d = m.data
    sig = d["std_mgal"] * m.noise_scale
    eqs = hm.EquivalentSources(damping=m.damping, points=m.sources)
    eqs.fit((d["easting_m"], d["northing_m"], d["height_m"]), d["dg_mgal"] - m.mean_mgal, weights=1 / sig ** 2)
    np.testing.assert_allclose(m.coefs, eqs.coefs_, rtol=1e-6, atol=1e-9 * np.abs(eqs.coefs_).max())


def test_gradient_boosted_and_local_std_match_exact(draped, draped_fit):
    S, ex = draped, draped_fit
    gb = fit_equivalent_sources(S["e"], S["n"], S["h"], S["obs"], S["std"], S["lab"], error_corr_m=3000.0,
                                method="gb", max_exact_sources=250)
    assert gb.method == "gb" and gb.info["hyper_subarea"]["n_sources"] == 250
    gt = S["field"](S["gx"], S["gy"], H0)
    gp = gb.predict(S["gx"], S["gy"], H0)
    line_rms = np.sqrt(np.mean((S["obs"] - S["true"]) ** 2))
    assert np.sqrt(np.mean((gp - gt) ** 2)) <= 1.1 * line_rms
    assert np.sqrt(np.mean((gp - ex.predict(S["gx"], S["gy"], H0)) ** 2)) < 0.6
    ratio = gb.predict_std(S["gx"], S["gy"], H0) / ex.predict_std(S["gx"], S["gy"], H0)
    assert np.all(np.abs(ratio - 1) < 0.1), (ratio.min(), ratio.max())


def test_block_average_lines():
    e = np.arange(0.0, 2000.0, 10.0)
    lab = np.where(e < 1000, "A", "B")
    out = block_average_lines(e, 0 * e, 100 + 0 * e, e / 100, np.full(e.size, 2.0), lab, block_m=500.0,
                              error_corr_m=0.0)
    assert out["easting_m"].size == 4 and list(out["count"]) == [50, 50, 50, 50]
    np.testing.assert_allclose(out["std_mgal"], 2.0 / np.sqrt(50))
    # correlated errors: a 500 m block is a quarter of an independent datum when they correlate over 2 km
    out = block_average_lines(e, 0 * e, 100 + 0 * e, e / 100, np.full(e.size, 2.0), lab, block_m=500.0,
                              error_corr_m=2000.0)
    np.testing.assert_allclose(out["std_mgal"], 4.0)
    with pytest.raises(ValueError, match="at least 10"):
        fit_equivalent_sources(e[:5], e[:5], e[:5], e[:5], np.ones(5))
