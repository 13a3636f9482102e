"""Tests of crossovers and line leveling against analytic truth and simulations."""

import numpy as np
import pytest

from app.core.leveling import (
    LineTrack,
    common_level_std,
    cross_validated_leveling,
    crossover_table,
    find_crossovers,
    level_lines,
)


def _field(e, n):
    return 20 * np.sin(e / 7.0) * np.cos(n / 5.0) + 0.3 * e


def _straight(e0, n0, e1, n1, t0, speed_kms=0.1, rate_hz=10.0, kind="main", wobble=0.0, seed=0):
    length = np.hypot(e1 - e0, n1 - n0)
    npts = int(round(length / speed_kms * rate_hz)) + 1
    s = np.linspace(0, 1, npts)
    t = t0 + s * length / speed_kms
    if wobble:  # non-uniform speed: time not linear in position
        rng = np.random.default_rng(seed)
        t = t0 + (s + wobble * np.sin(2 * np.pi * s * rng.uniform(0.5, 1.5))) * length / speed_kms
    e = e0 + s * (e1 - e0)
    n = n0 + s * (n1 - n0)
    return e, n, t


def _survey(drift_deg=1, seed=1, wobble=0.0, noise=0.0):
    rng = np.random.default_rng(seed)
    lines, truth, ranges = {}, {}, {}
    t = 0.0
    specs = [(f"M{k}", (0.0, 2.0 * k, 30.0, 2.0 * k + 0.5), "main") for k in range(8)]
    specs += [(f"T{k}", (3.0 + 8.0 * k, -1.0, 3.5 + 8.0 * k, 16.0), "tie") for k in range(4)]
    for name, (e0, n0, e1, n1), kind in specs:
        if rng.uniform() < 0.5:
            e0, n0, e1, n1 = e1, n1, e0, n0
        e, n, tt = _straight(e0, n0, e1, n1, t, kind=kind, wobble=wobble, seed=len(lines))
        coef = rng.normal(0, 3.0, drift_deg + 1)
        tau = 2 * (tt - tt[0]) / (tt[-1] - tt[0]) - 1
        drift = np.polynomial.polynomial.polyval(tau, coef)
        std = np.full(tt.size, 0.3)
        dg = _field(e, n) + drift + noise * rng.standard_normal(tt.size)
        lines[name] = LineTrack(e, n, tt, dg, std, kind)
        truth[name] = drift
        ranges[name] = (tt[0], tt[-1])
        t = tt[-1] + 600.0
    return lines, truth, ranges


def test_crossing_of_two_straight_lines_at_analytic_point():
    # A: (0,0)->(10,5), B: (2,6)->(8,-2); intersection solved by hand:
    # (10s, 5s) = (2+6u, 6-8u) -> u = 5/11, s = 26/55 -> (52/11, 26/11)
    ea, na, ta = _straight(0, 0, 10, 5, 100.0)
    eb, nb, tb = _straight(2, 6, 8, -2, 5000.0)
    ga = 3.0 + 0.01 * (ta - 100.0)       # linear in time -> exact interpolation
    gb = -1.0 + 0.002 * (tb - 5000.0)
    lines = {"A": LineTrack(ea, na, ta, ga, np.full_like(ta, 0.2), "main"),
             "B": LineTrack(eb, nb, tb, gb, np.full_like(tb, 0.4), "tie")}
    x = find_crossovers(lines)
    assert len(x) == 1
    r = x.iloc[0]
    assert (r.line_a, r.line_b) == ("A", "B")
    xe, xn = 52 / 11, 26 / 11
    assert r.easting_km == pytest.approx(xe, abs=1e-9)
    assert r.northing_km == pytest.approx(xn, abs=1e-9)
    ta_true = 100.0 + np.hypot(xe, xn) / 0.1
    tb_true = 5000.0 + np.hypot(xe - 2, xn - 6) / 0.1
    assert r.time_a == pytest.approx(ta_true, abs=1e-6)
    assert r.time_b == pytest.approx(tb_true, abs=1e-6)
    assert r.dg_a == pytest.approx(3.0 + 0.01 * (ta_true - 100), abs=1e-8)
    assert r.dg_b == pytest.approx(-1.0 + 0.002 * (tb_true - 5000), abs=1e-8)
    assert (r.std_a, r.std_b) == pytest.approx((0.2, 0.4))


def test_parallel_and_repeat_lines():
    e, n, t = _straight(0, 0, 10, 0, 0.0)
    e2, n2, t2 = _straight(0, 1, 10, 1, 1000.0)
    e3, n3, t3 = _straight(5, -1, 5, 2, 2000.0)
    z = np.zeros
    lines = {"A": LineTrack(e, n, t, z(t.size), z(t.size), "main"),
             "B": LineTrack(e2, n2, t2, z(t2.size), z(t2.size), "main"),
             "R": LineTrack(e3, n3, t3, z(t3.size), z(t3.size), "repeat")}
    assert len(find_crossovers(lines)) == 0            # parallel, repeat excluded
    x = find_crossovers(lines, include_repeat=True)
    assert len(x) == 2 and set(x.line_b) == {"R"}
    assert np.allclose(np.sort(x.northing_km), [0, 1])


def test_no_crossing_inside_a_data_gap():
    e, n, t = _straight(0, 0, 10, 0, 0.0)
    keep = (e < 4.0) | (e > 6.0)                      # 2 km gap around e = 5
    e3, n3, t3 = _straight(5, -1, 5, 2, 2000.0)
    e4, n4, t4 = _straight(2, -1, 2, 2, 3000.0)
    z = np.zeros
    lines = {"A": LineTrack(e[keep], n[keep], t[keep], z(keep.sum()), z(keep.sum()), "main"),
             "T5": LineTrack(e3, n3, t3, z(t3.size), z(t3.size), "tie"),
             "T2": LineTrack(e4, n4, t4, z(t4.size), z(t4.size), "tie")}
    x = find_crossovers(lines)
    assert list(x.line_b) == ["T2"]
    assert x.easting_km.iloc[0] == pytest.approx(2.0)


def test_grid_crossover_count_and_positions():
    lines, _, _ = _survey()
    x = find_crossovers(lines)
    assert len(x) == 8 * 4                                  # every main crosses every tie
    assert set(x.line_a.str[0]) == {"M"} and set(x.line_b.str[0]) == {"T"}
    # the crossing lies on both analytic lines
    for r in x.itertuples():
        k, j = int(r.line_a[1:]), int(r.line_b[1:])
        assert r.northing_km == pytest.approx(2.0 * k + 0.5 * r.easting_km / 30.0, abs=1e-9)
        assert r.easting_km == pytest.approx(3.0 + 8 * j + 0.5 * (r.northing_km + 1) / 17.0, abs=1e-9)
    # no spurious self crossings, values close to the field (drifts included)
    assert np.all(x.line_a != x.line_b)


def _plane_free_rms(lines, truth, res):
    """RMS of (true − estimated drift) after removing the unobservable part.

    For linear drifts on two families of straight parallel lines flown at
    constant speed, any function that is linear along every line gives zero
    crossover differences: 1, e, n and u·v, with u, v the coordinates normal
    to the main (direction (30, 0.5)) and tie (direction (0.5, 17)) lines.
    """
    e = np.concatenate([lines[k].easting_km for k in lines])
    n = np.concatenate([lines[k].northing_km for k in lines])
    r = np.concatenate([truth[k] - res.correction(k, lines[k].time_s) for k in lines])
    u = n - e / 60.0
    v = e - n / 34.0
    G = np.column_stack([np.ones_like(e), e, n, u * v])
    c, *_ = np.linalg.lstsq(G, r, rcond=None)
    return float(np.sqrt(np.mean((r - G @ c) ** 2))), float(np.sqrt(np.mean(np.concatenate(list(truth.values())) ** 2)))


def test_leveling_removes_linear_drifts():
    lines, truth, ranges = _survey(drift_deg=1, noise=0.0)
    x = find_crossovers(lines)
    res = level_lines(x, ranges, degree=1)
    assert res.rms_after <= res.rms_before / 3
    assert res.rms_after < 0.05
    err, size = _plane_free_rms(lines, truth, res)
    assert err < 0.01 * size
    # crossover table (SPEC §5) consistent with the differences
    tab = crossover_table(x, res)
    assert list(tab.columns) == ["line_a", "line_b", "easting_km", "northing_km",
                                 "diff_before_mgal", "diff_after_mgal"]
    np.testing.assert_allclose(tab.diff_before_mgal, x.dg_a - x.dg_b)
    # after-differences equal the differences of the corrected values
    da = np.array([res.apply(a, t, g) for a, t, g in zip(x.line_a, x.time_a, x.dg_a)])
    db = np.array([res.apply(b, t, g) for b, t, g in zip(x.line_b, x.time_b, x.dg_b)])
    np.testing.assert_allclose(da - db, res.diff_after, atol=1e-10)


def test_leveling_constant_offsets_recovered_up_to_constant_and_reference():
    lines, truth, ranges = _survey(drift_deg=0, noise=0.0)
    x = find_crossovers(lines)
    res = level_lines(x, ranges, degree=0)
    est = np.array([res.coefs[k][0] for k in lines])
    tru = np.array([truth[k][0] for k in lines])
    np.testing.assert_allclose(est - est.mean(), tru - tru.mean(), atol=1e-4)
    assert abs(est.sum()) < 1e-8                       # minimum norm: zero mean offset
    summ = res.summary()
    assert summ["n_crossovers"] == 32 and summ["rms_before_mgal"] == res.rms_before
    assert summ["coefs_mgal"]["M0"] == [res.coefs["M0"][0]]
    res_ref = level_lines(x, ranges, degree=0, reference="T2")
    assert np.all(res_ref.coefs["T2"] == 0)
    est_r = np.array([res_ref.coefs[k][0] for k in lines])
    np.testing.assert_allclose(est_r, tru - truth["T2"][0], atol=1e-4)


def test_leveling_with_noise_weighted_and_degree_reduction():
    lines, truth, ranges = _survey(drift_deg=1, noise=0.0, seed=5)
    rng = np.random.default_rng(3)
    x = find_crossovers(lines)
    x["dg_a"] += rng.normal(0, 0.3, len(x))
    x["dg_b"] += rng.normal(0, 0.3, len(x))
    res = level_lines(x, ranges, degree=2, sigma0_mgal=0.1)
    assert res.rms_after <= res.rms_before / 3
    # ties cross 8 mains -> degree 2 kept; mains cross 4 ties -> 4 > 3: kept too
    assert res.degrees["T0"] == 2 and res.degrees["M0"] == 2
    # a line with 2 crossings gets a constant only
    sub = x[(x.line_b == "T0") | ((x.line_a == "M0") & (x.line_b.isin(["T1"])))]
    r2 = level_lines(sub, ranges, degree=1)
    assert r2.degrees["T1"] == 0 and r2.degrees["M0"] == 0 and r2.degrees["T0"] == 1
    # every line with a crossover gets a drift; lines without crossovers (T2, T3) get none,
    # are reported as unleveled and get zero correction
    crossed = set(sub.line_a) | set(sub.line_b)
    assert crossed == {f"M{k}" for k in range(8)} | {"T0", "T1"}
    assert set(r2.coefs) == crossed
    assert r2.unleveled_lines == ["T2", "T3"]
    for ln in ("T2", "T3"):
        assert np.all(r2.correction(ln, lines[ln].time_s) == 0)
    assert np.any(r2.correction("M3", lines["M3"].time_s) != 0)


def test_leveling_errors():
    lines, _, ranges = _survey()
    x = find_crossovers(lines)
    with pytest.raises(ValueError, match="no crossovers"):
        level_lines(x.iloc[:0], ranges)
    bad = x.copy()
    bad.loc[3, "dg_a"] = np.nan
    r = level_lines(bad, ranges, degree=0)
    assert r.n_crossovers == len(x) - 1 and np.isnan(r.diff_after[3]) and np.isfinite(r.rms_after)
    bad["dg_b"] = np.nan
    with pytest.raises(ValueError, match="finite"):
        level_lines(bad, ranges)
    with pytest.raises(ValueError, match="degree"):
        level_lines(x, ranges, degree=3)
    with pytest.raises(ValueError, match="reference"):
        level_lines(x, ranges, reference="nope")
    with pytest.raises(ValueError, match="time range"):
        level_lines(x, {k: v for k, v in ranges.items() if k != "M0"})
    with pytest.raises(ValueError):
        LineTrack([0, 1], [0, 1], [1, 0], [0, 0], [0, 0])


def _two_flights(lines, ranges):
    """The survey's lines split into flights F1 (M0–M3, T0, T1) and F2 (the rest), and each
    flight's time span (s)."""
    flight = {k: ("F1" if k in ("M0", "M1", "M2", "M3", "T0", "T1") else "F2") for k in lines}
    span = {}
    for k, f in flight.items():
        t0, t1 = ranges[k]
        span[f] = (min(t0, span.get(f, (t0, t1))[0]), max(t1, span.get(f, (t0, t1))[1]))
    return flight, span


def test_per_flight_drift_with_groups():
    """Seed 001's alternative: one drift polynomial per flight, shared by its lines."""
    lines, truth, ranges = _survey(drift_deg=0, noise=0.0, seed=11)
    flight, span = _two_flights(lines, ranges)
    coef = {"F1": (2.0, -4.0), "F2": (-1.0, 3.0)}            # mGal, mGal per half span
    new_truth = {}
    for k, tr in lines.items():
        f = flight[k]
        tau = 2 * (tr.time_s - span[f][0]) / (span[f][1] - span[f][0]) - 1
        d = coef[f][0] + coef[f][1] * tau
        tr.dg_mgal = tr.dg_mgal - truth[k] + d               # replace the line offsets by flight drift
        new_truth[k] = d
    x = find_crossovers(lines)
    res = level_lines(x, ranges, degree=1, groups=flight)
    assert set(res.coefs) == {"F1", "F2"} and res.unit_of["M5"] == "F2"
    assert res.time_ranges["F1"] == pytest.approx(span["F1"])
    assert res.rms_after < 1e-3 * res.rms_before
    # recovered up to the common constant
    r = np.concatenate([new_truth[k] - res.correction(k, lines[k].time_s) for k in lines])
    assert np.ptp(r) < 1e-3
    np.testing.assert_allclose(res.coefs["F1"][1], -4.0, atol=1e-3)
    np.testing.assert_allclose(res.coefs["F2"][1], 3.0, atol=1e-3)
    # a reference flight carries zero drift; its own slope then stays in the data
    res_ref = level_lines(x, ranges, degree=1, groups=flight, reference="F1")
    assert np.all(res_ref.coefs["F1"] == 0) and np.all(res_ref.correction("M0", [1e3, 2e3]) == 0)
    assert res_ref.rms_after < res_ref.rms_before


def test_weighted_min_norm_prefers_offsets_to_slopes():
    """Offsets only (plus a north-south step between 'flights'), leveled with degree 1.

    The plane/bilinear null space of degree-1 leveling cannot be seen in the
    crossovers; the weighted minimum norm assigns it to offsets, which here is
    the truth, so lines are recovered up to the common constant."""
    lines, truth, ranges = _survey(drift_deg=0, noise=0.0, seed=4)
    for k, tr in lines.items():                       # add a 30 mGal step: northern mains flown later
        if k.startswith("M") and int(k[1:]) >= 4:
            tr.dg_mgal = tr.dg_mgal + 30.0
            truth[k] = truth[k] + 30.0
    x = find_crossovers(lines)

    def err(res):
        r = np.concatenate([truth[k] - res.correction(k, lines[k].time_s) for k in lines])
        return np.sqrt(np.mean((r - r.mean()) ** 2))

    weighted = level_lines(x, ranges, degree=1)
    plain = level_lines(x, ranges, degree=1, slope_scale=1.0)
    assert weighted.rms_after < 1e-3 and plain.rms_after < 1e-3   # both fit the crossovers
    assert err(weighted) < 0.05
    assert err(plain) > 20 * err(weighted)                        # a tilt leaks in without weighting
    with pytest.raises(ValueError, match="slope_scale"):
        level_lines(x, ranges, slope_scale=0.0)


def _flight_survey(drift_scale: float, seed: int):
    """Lines in three flights; each line's error = a smooth along-line error of its own
    (what a smoother leaves, correlated along the line) + the flight's linear drift."""
    lines, truth, ranges = _survey(drift_deg=0, noise=0.0, seed=seed)
    rng = np.random.default_rng(seed)
    names = sorted(lines)
    flight = {k: f"F{i % 3}" for i, k in enumerate(names)}
    span = {}
    for k, f in flight.items():
        t0, t1 = ranges[k]
        span[f] = (min(t0, span.get(f, (t0, t1))[0]), max(t1, span.get(f, (t0, t1))[1]))
    coef = {f: rng.normal(0, 3.0, 2) * drift_scale for f in span}
    for k, tr in lines.items():
        f = flight[k]
        tau = 2 * (tr.time_s - span[f][0]) / (span[f][1] - span[f][0]) - 1
        s = (tr.time_s - tr.time_s[0]) / 60.0
        smooth_err = 1.5 * np.sin(s * rng.uniform(0.5, 2.0) + rng.uniform(0, 6.3))
        tr.dg_mgal = tr.dg_mgal - truth[k] + coef[f][0] + coef[f][1] * tau + smooth_err
    return find_crossovers(lines), ranges, flight


def test_cross_validated_leveling_confirms_a_real_drift_and_rejects_none():
    """Leave-one-line-out: a flight drift (±3 mGal) is predicted at held-out lines' crossovers
    (significantly lower RMS); with no drift at all, the drift fitted to the lines' own
    correlated errors does not predict held-out crossovers better than no correction."""
    p_real, p_none = [], []
    for seed in range(5):
        x, ranges, flight = _flight_survey(1.0, seed)
        cv = cross_validated_leveling(x, ranges, degree=1, groups=flight)
        assert cv["n_folds"] == 12
        p_real.append(cv["p_value"])
        if cv["p_value"] < 0.01:
            assert cv["rms_cv_mgal"] < cv["rms_before_mgal"]
        x, ranges, flight = _flight_survey(0.0, seed)
        cv0 = cross_validated_leveling(x, ranges, degree=1, groups=flight)
        p_none.append(cv0["p_value"])
    assert np.median(p_real) < 0.01
    assert min(p_none) > 0.01


def test_drift_is_not_extrapolated_to_lines_without_crossings():
    """A flight's drift is applied over the lines whose crossings determined it; a line of the
    same flight flown later with no crossings (a repeat pass) gets the edge value, not the
    slope carried on."""
    lines, truth, ranges = _survey(drift_deg=1, noise=0.0, seed=5)
    flight = {k: "F1" for k in lines}
    t_end = max(t1 for _, t1 in ranges.values())
    ranges = dict(ranges, X=(t_end + 3000.0, t_end + 3600.0))
    flight["X"] = "F1"
    res = level_lines(find_crossovers(lines), ranges, degree=1, groups=flight)
    assert res.degrees["F1"] == 1 and abs(res.coefs["F1"][1]) > 0.1
    assert res.fit_ranges["F1"][1] == pytest.approx(t_end)
    edge = res.correction("M0", [t_end])[0]
    np.testing.assert_allclose(res.correction("X", [t_end + 3000.0, t_end + 3600.0]), edge)
    # inside the span the polynomial itself
    t0, t1 = res.time_ranges["F1"]
    t_mid = 0.5 * (ranges["M3"][0] + ranges["M3"][1])
    tau = 2 * (t_mid - t0) / (t1 - t0) - 1
    np.testing.assert_allclose(res.correction("M3", [t_mid])[0], res.coefs["F1"][0] + res.coefs["F1"][1] * tau)


def test_keep_mean_level_per_connected_group():
    """Hand-computed: two connected groups of drift units and one unit without crossings.
    Each group's epoch-weighted mean correction is removed; differences inside a group (what
    the crossovers see) and the unconnected unit are unchanged."""
    from app.core.leveling import keep_mean_level

    unit = np.array(["a", "a", "b", "b", "b", "c", "d", "d", "e"], dtype=object)
    corr = np.array([1.0, 3.0, 5.0, 5.0, 5.0, 10.0, -2.0, 4.0, 7.0])
    out, removed = keep_mean_level(corr, unit, [("a", "b"), ("b", "a"), ("d", "e")])
    m_ab = (1 + 3 + 5 + 5 + 5) / 5.0
    m_de = (-2 + 4 + 7) / 3.0
    np.testing.assert_allclose(out, corr - np.array([m_ab] * 5 + [0.0] + [m_de] * 3))
    assert sorted(removed) == sorted([m_ab, m_de])
    assert out[5] == 10.0
    with pytest.raises(ValueError, match="1-D"):
        keep_mean_level(corr[:3], unit, [])


def test_keep_mean_level_anchored_on_tied_epochs():
    """Hand-computed: where a group holds anchored epochs (flights with an absolute tie), the
    mean correction over those alone is removed; a group without any keeps its own mean; the
    anchors of another group change nothing in this one."""
    from app.core.leveling import connected_groups, keep_mean_level

    unit = np.array(["a", "a", "b", "b", "c", "d", "e"], dtype=object)
    corr = np.array([-150.0, -150.0, 2.0, 4.0, 1.0, 5.0, 9.0])
    anchor = np.array([False, False, True, True, True, False, False])
    out, removed = keep_mean_level(corr, unit, [("a", "b"), ("c", "c"), ("d", "e")], anchor)
    # group {a, b}: anchored mean (2 + 4) / 2 = 3; group {c}: its anchor 1; group {d, e}: mean 7
    np.testing.assert_allclose(out, [-153.0, -153.0, -1.0, 1.0, 0.0, -2.0, 2.0])
    assert sorted(removed) == [1.0, 3.0, 7.0]
    # no anchor: the plain epoch mean, (−300 + 6) / 4 = −73.5
    out0, _ = keep_mean_level(corr, unit, [("a", "b"), ("c", "c"), ("d", "e")])
    np.testing.assert_allclose(out0[:4], corr[:4] + 73.5)
    assert connected_groups([("b", "a"), ("c", "c"), ("e", "d")]) == {"a": "a", "b": "a", "c": "c", "d": "d", "e": "d"}
    with pytest.raises(ValueError, match="anchor"):
        keep_mean_level(corr, unit, [], anchor[:3])


def test_common_level_std_is_calibrated_for_exchangeable_flight_offsets():
    """Simulation with known truth: n = 2–4 flights whose offsets are draws of std s = 5 mGal,
    seen at 30 crossovers between flights with 1.5 mGal of noise each.  Over 3000 surveys the
    reported variance of the level leveling keeps (the offsets' mean) is unbiased: its mean is
    s²/n within 6 % for every n (the level's own mean square is s²/n within its sampling error),
    and the spread's mean square estimates s² within 6 %; the fitted offsets are the true ones less
    their mean.  (One survey's std comes from n − 1 degrees of freedom, so the level over it is
    t-like: it is the variance that is calibrated, not a 2σ coverage of two flights.)"""
    rng = np.random.default_rng(5)
    sq = {n: ([], []) for n in (2, 3, 4)}
    spread = []
    for trial in range(3000):
        n = 2 + trial % 3
        flights = [f"F{i}" for i in range(n)]
        off = rng.normal(0.0, 5.0, n)
        a = rng.integers(0, n, 30)
        b = (a + rng.integers(1, n, 30)) % n               # another flight
        d = off[a] - off[b] + rng.normal(0.0, 1.5, 30)
        res = common_level_std([flights[i] for i in a], [flights[i] for i in b], d)
        assert res.n_units == n and res.n_crossovers == 30
        sq[n][0].append(np.mean(off) ** 2)
        sq[n][1].append(res.std_mgal ** 2)
        spread.append(res.spread_mgal ** 2)
        if trial == 0:
            np.testing.assert_allclose([res.offsets_mgal[f] for f in flights], off - off.mean(), atol=1.5)
    for n, (level2, var) in sq.items():   # 1000 surveys each: the level's mean square within 3 SE (13 %)
        assert np.mean(var) == pytest.approx(25.0 / n, rel=0.06), n
        assert np.mean(level2) == pytest.approx(25.0 / n, rel=0.13), n
    assert np.mean(spread) == pytest.approx(25.0, rel=0.06)


def test_common_level_std_needs_two_connected_flights():
    assert common_level_std(["F1", "F1"], ["F1", "F1"], [1.0, 2.0]) is None          # one flight
    assert common_level_std(["F1"], ["F2"], [1.0]) is None                            # no residual dof
    res = common_level_std(["F1", "F1", "F1"], ["F2", "F2", "F2"], [4.0, 4.0, 4.0])   # no noise: s exact
    assert res.spread_mgal == pytest.approx(np.sqrt(8.0)) and res.std_mgal == pytest.approx(2.0)
    with pytest.raises(ValueError, match="1-D of one length"):
        common_level_std(["F1"], ["F2", "F3"], [1.0])


def test_drift_free_differences_are_the_residuals_of_the_drift_model():
    """Two flights with a linear drift each, crossover differences = the drift's difference
    plus noise: the drift-free differences equal the residuals of a least-squares fit of a
    design matrix built here by hand (offset and slope in each flight's normalised time), and
    the drift alone leaves nothing; two columns are treated alike."""
    from app.core.leveling import drift_free_differences

    lines, _, ranges = _survey(drift_deg=0, noise=0.0, seed=11)
    flight, span = _two_flights(lines, ranges)
    x = find_crossovers(lines)

    def design_row(line, t):
        f = flight[line]
        tau = 2 * (t - span[f][0]) / (span[f][1] - span[f][0]) - 1
        row = np.zeros(4)
        row[0 if f == "F1" else 2] = 1.0
        row[1 if f == "F1" else 3] = tau
        return row

    A = np.array([design_row(a, ta) - design_row(b, tb)
                  for a, b, ta, tb in zip(x["line_a"], x["line_b"], x["time_a"], x["time_b"])])
    rng = np.random.default_rng(3)
    drift = A @ np.array([5.0, -3.0, -2.0, 4.0])
    noise = rng.normal(0.0, 1.0, (len(x), 2))
    d = drift[:, None] + noise
    got = drift_free_differences(x, d, ranges, degree=1, groups=flight)
    expected = noise - A @ np.linalg.lstsq(A, noise, rcond=None)[0]
    np.testing.assert_allclose(got, expected, atol=1e-9)
    np.testing.assert_allclose(drift_free_differences(x, drift, ranges, 1, flight), 0.0, atol=1e-9)
    # a NaN row stays NaN and leaves the fit
    d[0, 1] = np.nan
    got = drift_free_differences(x, d, ranges, 1, flight)
    assert np.isnan(got[0]).all() and np.isfinite(got[1:]).all()
    with pytest.raises(ValueError, match="shape"):
        drift_free_differences(x, d[:-1], ranges, 1, flight)


def test_drift_free_differences_degrees_of_freedom():
    """The residuals' degrees of freedom are the rows less the rank of the drift model — built
    here by hand: two flights with offset and slope, less the common constant the crossovers
    cannot see (rank 3).  Over many draws of unit white differences the residuals' sum of
    squares averages that number (E Σ r² = n − rank for a projection)."""
    from app.core.leveling import drift_free_differences

    lines, _, ranges = _survey(drift_deg=0, noise=0.0, seed=11)
    flight, _ = _two_flights(lines, ranges)
    x = find_crossovers(lines)
    rng = np.random.default_rng(5)
    d = rng.normal(0.0, 1.0, (len(x), 4000))
    got, dof = drift_free_differences(x, d, ranges, degree=1, groups=flight, with_dof=True)
    assert dof == len(x) - 3
    assert np.mean(np.sum(got ** 2, axis=0)) == pytest.approx(dof, rel=0.03)
    # a degree-0 drift (one offset per flight): rank 1
    _, dof0 = drift_free_differences(x, d[:, 0], ranges, degree=0, groups=flight, with_dof=True)
    assert dof0 == len(x) - 1
