"""Stage 8's level spread on surveys whose anomaly levels were learned from few points
(simulation with known truth: the model's own two-level anomaly, white velocity noise).

A small survey's EM can miss its levels by a decade (held-out random layouts with 206–393
decimated points for two levels: 2σ coverage down to 0.74 in the mountains).  With both
levels 10× too low, the posterior std covers the error on about half of the epochs (0.39–0.55
over three seeds); the spread of the estimates at Q/10 and 10·Q (the one-level rule, extended
to levels learned from fewer than ``n_q × min_points`` points) brings it to about 85 %
(0.84–0.86).  The estimate itself is unchanged.  From enough points the
std is left as the smoother gave it."""

import numpy as np
import pandas as pd

from app.core.smoother import kalman_smooth, level_spread_std_mgal
from app.pipeline.stages.filtering import Filtered, PreparedLine


def _two_level_line(rng, T, dt, q_levels, R, step):
    """One line whose first half is the smooth level and second half the rough one: z, truth,
    the held state per epoch, and decimated points (every ``step`` epochs) with their map
    probabilities (0.9 on the true level)."""
    state = (np.arange(T) >= T // 2).astype(int)
    q = rng.normal(size=T) * np.sqrt(np.asarray(q_levels)[state])
    dg = np.cumsum(np.cumsum(q)) + 30.0
    r = rng.normal(size=T + 1) * np.sqrt(R)
    z = dg - 1000.0 * (r[1:] - r[:-1]) / dt
    idx = np.arange(step // 2, T, step)
    pq = np.where(state[idx, None] == np.arange(2)[None, :], 0.9, 0.1)
    return z, dg, state, idx, pq


def test_levels_from_few_points_carry_their_uncertainty():
    dt, T, R, step = 0.1, 20000, 1.0, 100
    q_true = np.array([2e-9, 2e-7])
    q_used = q_true / 10          # both levels a decade low, as a small survey's EM may give
    cov = {"plain": [], "spread": []}
    kept = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        z, dg, state, idx, pq = _two_level_line(rng, T, dt, q_true, R, step)
        pr = PreparedLine(None, state, state, z, slice(0, T), None, idx, pq)
        lq = np.exp(np.interp(np.arange(T), idx, pq @ np.log(q_used)))   # the estimate's Q(t)
        sm = kalman_smooth(z, lq, np.full(T, R), dt, m=2)
        table = pd.DataFrame({"dg_mgal": sm.dg_mgal, "dg_std_mgal": sm.dg_std_mgal})
        n_points = idx.size                                                # 200 < 2 x 200
        inner = slice(1000, T - 1000)
        err = np.abs(sm.dg_mgal - dg)[inner]
        for enough in (False, True):
            f = Filtered(table.copy(), q_used, None, 1.0, prepared=[pr], r_lines=[np.full(T, R)], n_r=1)
            f.level_spread_std(dt, 2, "bf", None, 10.0, n_points=n_points * (3 if enough else 1),
                               min_points=200)
            std = f.table["dg_std_mgal"].to_numpy()
            if enough:
                kept.append(np.array_equal(std, sm.dg_std_mgal) and f.std_level_factor is None)
            else:
                assert f.std_level_factor == 10.0 and "2 anomaly levels from 200" in f.std_level_reason
                np.testing.assert_array_equal(f.table["dg_mgal"].to_numpy(), sm.dg_mgal)
                cov["spread"].append(np.mean(err < 2 * std[inner]))
        cov["plain"].append(np.mean(err < 2 * sm.dg_std_mgal[inner]))
    assert np.mean(cov["plain"]) < 0.7, cov
    assert np.mean(cov["spread"]) > 0.8, cov
    assert all(kept)


def _repeat_passes(rng, n_pass, T, dt, q, R, speed_ms, r_factors=None):
    """One track flown ``n_pass`` times in alternating directions: the same random-walk
    anomaly, white velocity noise of its own on each pass (variance R, times
    ``r_factors[k]`` on pass k when given)."""
    from types import SimpleNamespace

    dg = np.cumsum(np.cumsum(rng.normal(size=T) * np.sqrt(q))) + 30.0
    s_km = np.arange(T) * dt * speed_ms / 1000.0
    lines, zs, truths = [], [], []
    for k in range(n_pass):
        o = slice(None) if k % 2 == 0 else slice(None, None, -1)
        r = rng.normal(size=T + 1) * np.sqrt(R * (1.0 if r_factors is None else r_factors[k]))
        zs.append(dg[o] - 1000.0 * (r[1:] - r[:-1]) / dt)
        truths.append(dg[o])
        lines.append(SimpleNamespace(kind="repeat", track="T1", easting_km=500.0 + s_km[o],
                                     northing_km=np.full(T, 7000.0), speed_ms=speed_ms))
    return lines, zs, truths


def test_repeat_passes_size_the_std_instead_of_the_level_spread():
    """A one-level survey of repeat passes (the test-line case): the std is sized by the
    error the passes show, never narrowed below the posterior; the level spread (a decade
    either way) would cover nearly every epoch.  With the level a decade too low the
    posterior is too narrow and the passes widen it."""
    dt, T, R, speed = 0.5, 3000, 1.0, 60.0      # 4 passes of 1500 s, 90 km: 45 stretches of 100 s
    q_true = 2e-5
    cov = {"repeat": [], "spread": [], "low_posterior": [], "low_repeat": []}
    for seed in range(3):
        rng = np.random.default_rng(seed)
        lines, zs, truths = _repeat_passes(rng, 4, T, dt, q_true, R, speed)
        for case, q_used in (("ok", q_true), ("low", q_true / 10)):
            sms = [kalman_smooth(z, np.full(T, q_used), np.full(T, R), dt, m=2) for z in zs]
            table = pd.DataFrame({"dg_mgal": np.concatenate([s.dg_mgal for s in sms]),
                                  "dg_std_mgal": np.concatenate([s.dg_std_mgal for s in sms])})
            prepared = [PreparedLine(ln, np.zeros(T, int), np.zeros(T, int), z, slice(0, T), None, None, None)
                        for ln, z in zip(lines, zs)]
            inner = np.concatenate([np.arange(k * T + 300, (k + 1) * T - 300) for k in range(4)])
            err = np.abs(table["dg_mgal"].to_numpy() - np.concatenate(truths))[inner]
            runs = {}
            for rule, min_samples in (("repeat", 8.0), ("spread", None)):
                f = Filtered(table.copy(), np.array([q_used]), None, 1.0, prepared=prepared,
                             r_lines=[np.full(T, R)] * 4, n_r=1)
                f.level_spread_std(dt, 2, "bf", None, 10.0, repeat_min_samples=min_samples, fir_period_s=100.0)
                np.testing.assert_array_equal(f.table["dg_mgal"].to_numpy(), table["dg_mgal"].to_numpy())
                runs[rule] = f
            rep = runs["repeat"]
            track = rep.std_repeat_tracks["T1"]
            if track["smoothing_p_value"] < 0.1:   # the smoothing part significant: the passes size it
                assert rep.std_level_factor is None and "repeat tracks" in rep.std_level_reason
                assert track["scale"] >= 1.0
            else:                                  # not: the spread stays (seed 0 with Q right, p = 0.36)
                assert rep.std_level_factor == 10.0 and track["scale"] is None
                assert case == "ok"
            assert runs["spread"].std_level_factor == 10.0
            std = {k: f.table["dg_std_mgal"].to_numpy()[inner] for k, f in runs.items()}
            if case == "ok":
                cov["repeat"].append(np.mean(err < 2 * std["repeat"]))
                cov["spread"].append(np.mean(err < 2 * std["spread"]))
            else:
                cov["low_posterior"].append(np.mean(err < 2 * table["dg_std_mgal"].to_numpy()[inner]))
                cov["low_repeat"].append(np.mean(err < 2 * std["repeat"]))
                assert rep.std_repeat_tracks["T1"]["scale"] > 1.2
    assert 0.92 < np.mean(cov["repeat"]) < 0.98, cov
    assert np.mean(cov["spread"]) > np.mean(cov["repeat"]) + 0.02, cov
    assert np.mean(cov["low_repeat"]) > np.mean(cov["low_posterior"]) + 0.1, cov


def test_too_few_repeat_stretches_keep_the_level_spread():
    dt, T, R = 0.5, 600, 1.0       # 2 passes of 300 s: 3 stretches of 100 s
    rng = np.random.default_rng(0)
    lines, zs, _ = _repeat_passes(rng, 2, T, dt, 2e-5, R, 60.0)
    sms = [kalman_smooth(z, np.full(T, 2e-5), np.full(T, R), dt, m=2) for z in zs]
    table = pd.DataFrame({"dg_mgal": np.concatenate([s.dg_mgal for s in sms]),
                          "dg_std_mgal": np.concatenate([s.dg_std_mgal for s in sms])})
    prepared = [PreparedLine(ln, np.zeros(T, int), np.zeros(T, int), z, slice(0, T), None, None, None)
                for ln, z in zip(lines, zs)]
    f = Filtered(table, np.array([2e-5]), None, 1.0, prepared=prepared, r_lines=[np.full(T, R)] * 2, n_r=1)
    f.level_spread_std(dt, 2, "bf", None, 10.0, repeat_min_samples=8.0, fir_period_s=100.0)
    assert f.std_level_factor == 10.0 and f.std_repeat_tracks is None


def test_lines_off_the_repeat_track_keep_the_level_spread():
    """A repeat track says little about the rest of a survey: a main line beside it gets the
    spread, the passes their own scale."""
    from types import SimpleNamespace

    dt, T, R, q = 0.5, 3000, 1.0, 2e-5
    rng = np.random.default_rng(1)
    lines, zs, _ = _repeat_passes(rng, 4, T, dt, q, R, 60.0)
    main = SimpleNamespace(kind="main", track=None, easting_km=np.arange(T) * 0.03, northing_km=np.zeros(T),
                           speed_ms=60.0)
    lines.append(main)
    zs.append(zs[0][::-1] + 5.0)
    sms = [kalman_smooth(z, np.full(T, q), np.full(T, R), dt, m=2) for z in zs]
    table = pd.DataFrame({"dg_mgal": np.concatenate([s.dg_mgal for s in sms]),
                          "dg_std_mgal": np.concatenate([s.dg_std_mgal for s in sms])})
    prepared = [PreparedLine(ln, np.zeros(T, int), np.zeros(T, int), z, slice(0, T), None, None, None)
                for ln, z in zip(lines, zs)]
    f = Filtered(table.copy(), np.array([q]), None, 1.0, prepared=prepared, r_lines=[np.full(T, R)] * 5, n_r=1)
    f.level_spread_std(dt, 2, "bf", None, 10.0, repeat_min_samples=8.0, fir_period_s=100.0)
    std = f.table["dg_std_mgal"].to_numpy()
    c = f.std_repeat_tracks["T1"]["scale"]
    np.testing.assert_allclose(std[:4 * T], c * table["dg_std_mgal"].to_numpy()[:4 * T])
    spread = level_spread_std_mgal(zs[4], np.full(T, q), np.full(T, R), dt, 10.0, m=2).dg_std_mgal
    np.testing.assert_allclose(std[4 * T:], np.maximum(sms[4].dg_std_mgal, spread))
    assert f.std_level_factor == 10.0 and "repeat tracks" in f.std_level_reason


def test_repeat_passes_without_a_measured_shared_error_keep_the_level_spread():
    """Where the passes' shared difference from the less-smoothed estimate is lost in their
    noise (the smoothing part clipped at 0, or not significant at p < 0.1), the measure says
    nothing about the error the passes share, so the track keeps the (wider) level spread;
    where it is measured, the passes size the std.  On a nearly flat anomaly the shared part
    is pure noise: it comes out above 0 on some seeds, and the F-test keeps the spread on
    most (it sizes by chance at most on about 1 in 10)."""
    dt, T, R, speed = 0.5, 3000, 1.0, 60.0
    seen = {"kept": 0, "sized": 0}
    for seed in range(8):
        rng = np.random.default_rng(100 + seed)
        lines, zs, _ = _repeat_passes(rng, 4, T, dt, 1e-12, R, speed)
        sms = [kalman_smooth(z, np.full(T, 2e-6), np.full(T, R), dt, m=2) for z in zs]
        table = pd.DataFrame({"dg_mgal": np.concatenate([s.dg_mgal for s in sms]),
                              "dg_std_mgal": np.concatenate([s.dg_std_mgal for s in sms])})
        prepared = [PreparedLine(ln, np.zeros(T, int), np.zeros(T, int), z, slice(0, T), None, None, None)
                    for ln, z in zip(lines, zs)]
        runs = {}
        for rule, min_samples in (("repeat", 8.0), ("spread", None)):
            f = Filtered(table.copy(), np.array([2e-6]), None, 1.0, prepared=prepared,
                         r_lines=[np.full(T, R)] * 4, n_r=1)
            f.level_spread_std(dt, 2, "bf", None, 10.0, repeat_min_samples=min_samples, fir_period_s=100.0)
            runs[rule] = f
        track = runs["repeat"].std_repeat_tracks["T1"]
        if track["smoothing_part_mgal"] == 0.0 or track["smoothing_p_value"] >= 0.1:
            seen["kept"] += 1
            assert track["scale"] is None and runs["repeat"].std_level_factor == 10.0
            np.testing.assert_array_equal(runs["repeat"].table["dg_std_mgal"], runs["spread"].table["dg_std_mgal"])
        else:
            seen["sized"] += 1
            assert track["scale"] >= 1.0 and runs["repeat"].std_level_factor is None
        seen["positive"] = seen.get("positive", 0) + int(track["smoothing_part_mgal"] > 0.0)
    # the shared part is noise here: it comes out above 0 on some seeds, significant on few
    assert seen["positive"] >= 2 and seen["kept"] >= 6, seen


def test_a_pass_through_turbulence_gets_a_std_of_its_own_noise():
    """One of four passes carries 16× the noise variance the model was given (a turbulent
    stretch; generated test line 304: pass errors 22–78 mGal against one posterior of 15).
    Each pass's own noise, from its departures from the other passes, sizes its std: with the
    level right (the passes' shared part not significant, so the spread stays) the noisy pass
    gets at least its own noise as a floor; with the level a decade low (the shared part
    measured) the track's scale, and the noisy pass more: its own noise plus the shared part.
    Its 2σ coverage (0.37–0.54 from the posterior alone) comes to 0.94–1.00 where the spread
    would give 0.79–0.86 (and the calm passes' floor stays below 1.3), and, with the level low,
    0.55 → 0.86 beside the track's one scale."""
    dt, T, R, speed = 0.5, 3000, 1.0, 60.0
    for seed, (case, q_used) in enumerate((("ok", 2e-5), ("low", 2e-6), ("ok", 2e-5))):
        rng = np.random.default_rng(40 + seed)
        lines, zs, truths = _repeat_passes(rng, 4, T, dt, 2e-5, R, speed, r_factors=[1.0, 16.0, 1.0, 1.0])
        sms = [kalman_smooth(z, np.full(T, q_used), np.full(T, R), dt, m=2) for z in zs]
        table = pd.DataFrame({"dg_mgal": np.concatenate([s.dg_mgal for s in sms]),
                              "dg_std_mgal": np.concatenate([s.dg_std_mgal for s in sms])})
        prepared = [PreparedLine(ln, np.zeros(T, int), np.zeros(T, int), z, slice(0, T), None, None, None)
                    for ln, z in zip(lines, zs)]
        f = Filtered(table.copy(), np.array([q_used]), None, 1.0, prepared=prepared,
                     r_lines=[np.full(T, R)] * 4, n_r=1)
        f.level_spread_std(dt, 2, "bf", None, 10.0, repeat_min_samples=8.0, fir_period_s=100.0)
        spread = Filtered(table.copy(), np.array([q_used]), None, 1.0, prepared=prepared,
                          r_lines=[np.full(T, R)] * 4, n_r=1)
        spread.level_spread_std(dt, 2, "bf", None, 10.0, repeat_min_samples=None, fir_period_s=100.0)
        track = f.std_repeat_tracks["T1"]
        # the noisy pass's own noise is measured about 4× the others' (σ ratio √16)
        assert track["pass_lines"] == ["0", "1", "2", "3"]   # the passes, in the order of their figures
        noise = np.array(track["pass_noise_ratio"])
        assert noise[1] > 2.0 * np.max(np.delete(noise, 1)), track
        inner = slice(300, T - 300)
        std = f.table["dg_std_mgal"].to_numpy().reshape(4, T)
        post = table["dg_std_mgal"].to_numpy().reshape(4, T)
        err = np.abs(np.array([s.dg_mgal for s in sms]) - np.array(truths))
        cov_pass = [float(np.mean(err[k, inner] < 2 * std[k, inner])) for k in range(4)]
        cov_spread = float(np.mean(err[1, inner] < 2 * spread.table["dg_std_mgal"].to_numpy().reshape(4, T)[1, inner]))
        assert np.mean(err[1, inner] < 2 * post[1, inner]) < 0.75
        if case == "ok":
            assert cov_pass[1] >= 0.9 and cov_pass[1] > cov_spread + 0.05, (case, cov_pass, cov_spread, track)
        else:                                 # one scale for the track would leave the noisy pass short
            pooled = [float(np.mean(err[k, inner] < 2 * track["scale"] * post[k, inner])) for k in range(4)]
            assert cov_pass[1] > pooled[1] + 0.1, (cov_pass, pooled)
        if track["scale"] is None:           # the shared part not significant: the floor beside the spread
            assert case == "ok" and track["noise_p_value"] < 0.1
            assert track["pass_scales"][1] > 2.0 and max(np.delete(track["pass_scales"], 1)) < 1.3
            # named: the noisy pass, and at most a calm one widened by chance a little
            assert "1" in [w["line"] for w in track["widened_passes"]]
            assert all(w["scale"] < 1.3 for w in track["widened_passes"] if w["line"] != "1")
            np.testing.assert_array_less(spread.table["dg_std_mgal"].to_numpy() - 1e-12,
                                         f.table["dg_std_mgal"].to_numpy())   # never below the spread
        else:                                 # measured: each pass scaled by its own noise
            c = np.array(track["pass_scales"])
            np.testing.assert_allclose(std, c[:, None] * post)
            # the calm passes keep the track's scale (never less); the noisy one gets more
            np.testing.assert_allclose(np.delete(c, 1), track["scale"])
            assert c[1] > 1.4 * track["scale"], track
        # the estimate is untouched
        np.testing.assert_array_equal(f.table["dg_mgal"].to_numpy(), table["dg_mgal"].to_numpy())


def test_a_two_level_survey_floors_a_noisy_pass_at_its_own_noise():
    """Two levels learned from enough points: the level spread leaves the std alone, but a
    repeat pass whose own noise the passes show far above its posterior (16× the variance the
    model was given) is widened to it; the calm passes and every line off the track keep their
    std.  With every pass's noise as modelled the std is left as it is (the scatter is not
    significantly above the posterior)."""
    dt, T, R, speed, q = 0.5, 3000, 1.0, 60.0, 2e-5
    for factors, noisy in (([1.0, 16.0, 1.0, 1.0], True), ([1.0, 1.0, 1.0, 1.0], False)):
        rng = np.random.default_rng(7)
        lines, zs, truths = _repeat_passes(rng, 4, T, dt, q, R, speed, r_factors=factors)
        sms = [kalman_smooth(z, np.full(T, q), np.full(T, R), dt, m=2) for z in zs]
        table = pd.DataFrame({"dg_mgal": np.concatenate([s.dg_mgal for s in sms]),
                              "dg_std_mgal": np.concatenate([s.dg_std_mgal for s in sms])})
        prepared = [PreparedLine(ln, np.zeros(T, int), np.zeros(T, int), z, slice(0, T), None, None, None)
                    for ln, z in zip(lines, zs)]
        f = Filtered(table.copy(), np.array([q, 30 * q]), None, 1.0, prepared=prepared,
                     r_lines=[np.full(T, R)] * 4, n_r=1)
        f.level_spread_std(dt, 2, "bf", None, 10.0, n_points=5000, min_points=200,
                           repeat_min_samples=8.0, fir_period_s=100.0)
        assert f.std_level_factor is None             # no spread: two levels from enough points
        track = f.std_repeat_tracks["T1"]
        std = f.table["dg_std_mgal"].to_numpy().reshape(4, T)
        post = table["dg_std_mgal"].to_numpy().reshape(4, T)
        if noisy:
            c = np.array(track["pass_scales"])
            assert track["noise_p_value"] < 0.1 and c[1] > 2.5 and np.all(np.delete(c, 1) < 1.3), track
            np.testing.assert_allclose(std, c[:, None] * post)
            err = np.abs(np.array([s.dg_mgal for s in sms]) - np.array(truths))[1, 300:-300]
            assert np.mean(err < 2 * std[1, 300:-300]) > 0.9 > np.mean(err < 2 * post[1, 300:-300])
        else:
            assert track["noise_p_value"] >= 0.1 and "pass_scales" not in track, track
            np.testing.assert_array_equal(std, post)


def test_a_hole_in_one_pass_leaves_the_pass_noise_measurable():
    """A pass with a hole (NaN) in its std but not in its estimate, and one with a zero std
    stretch: the passes' figures come on the points they share and the survey is processed
    (before, the per-pass ratio needed the estimates and the posteriors on the same points)."""
    dt, T, R, speed, q = 0.5, 3000, 1.0, 60.0, 2e-5
    rng = np.random.default_rng(3)
    lines, zs, _ = _repeat_passes(rng, 4, T, dt, q, R, speed, r_factors=[1.0, 16.0, 1.0, 1.0])
    sms = [kalman_smooth(z, np.full(T, q), np.full(T, R), dt, m=2) for z in zs]
    std = np.concatenate([s.dg_std_mgal for s in sms])
    std[T + 500:T + 520] = np.nan
    std[2 * T + 900:2 * T + 905] = 0.0
    table = pd.DataFrame({"dg_mgal": np.concatenate([s.dg_mgal for s in sms]), "dg_std_mgal": std})
    prepared = [PreparedLine(ln, np.zeros(T, int), np.zeros(T, int), z, slice(0, T), None, None, None)
                for ln, z in zip(lines, zs)]
    for n_q, n_points in ((1, None), (2, 5000)):
        f = Filtered(table.copy(), np.array([q, 30 * q][:n_q]), None, 1.0, prepared=prepared,
                     r_lines=[np.full(T, R)] * 4, n_r=1)
        f.level_spread_std(dt, 2, "bf", None, 10.0, n_points=n_points, min_points=200,
                           repeat_min_samples=8.0, fir_period_s=100.0)
        ratio = f.std_repeat_tracks["T1"]["pass_noise_ratio"]
        assert len(ratio) == 4 and ratio[1] > 4.0 * max(np.delete(ratio, 1)), (n_q, ratio)


def test_passes_widened_to_their_own_noise_are_warned_about():
    """The warning names each pass widened beyond its track's scale with its noise over its
    posterior variance (generated 304's R1-2: 28.4×, its std widened 5.33×); the
    passes at the track's scale and tracks without per-pass figures give none."""
    from app.pipeline.stages.filtering import _record_pass_scales, pass_noise_warnings

    # the passes widened beyond the track's own factor by more than 5 %, as the stage records them
    floor_fig = {"scale": None, "pass_lines": ["R1-1", "R1-2", "R1-3", "R1-4"]}
    _record_pass_scales(floor_fig, np.array([1.0, 5.33, 1.0, 4.04]), np.array([0.2, 28.43, 0.1, 16.3]))
    sized_fig = {"scale": 1.27, "pass_lines": ["A", "B"]}
    _record_pass_scales(sized_fig, np.array([1.27, 1.3]), np.array([1.0, 1.69]))
    assert [w["line"] for w in floor_fig["widened_passes"]] == ["R1-2", "R1-4"] and sized_fig["widened_passes"] == []
    old = {"scale": 1.3, "noise_part_mgal": 2.0}
    got = pass_noise_warnings({"R1": floor_fig, "T2": sized_fig, "T3": old})
    assert got == ["repeat track R1: the noise of pass R1-2 is 28.4x, pass R1-4 is 16.3x its posterior variance "
                   "(departures from the other passes: more noise than the noise model gave it); the std is widened "
                   "to that noise, and the estimate carries it"], got
    assert pass_noise_warnings(None) == [] and pass_noise_warnings({}) == []


def _track_table(lines, zs, q, R, T, dt):
    sms = [kalman_smooth(z, np.full(T, q), np.full(T, R), dt, m=2) for z in zs]
    table = pd.DataFrame({"dg_mgal": np.concatenate([s.dg_mgal for s in sms]),
                          "dg_unleveled_mgal": np.concatenate([s.dg_mgal for s in sms]),
                          "dg_std_mgal": np.concatenate([s.dg_std_mgal for s in sms]),
                          "R_cm2s2": np.full(len(zs) * T, R)})
    prepared = [PreparedLine(ln, np.zeros(T, int), np.zeros(T, int), z, slice(0, T), None, None, None)
                for ln, z in zip(lines, zs)]
    return Filtered(table, np.array([q]), None, 1.0, prepared=prepared, r_lines=[np.full(T, R)] * len(zs), n_r=1)


def test_a_pass_through_turbulence_is_smoothed_with_its_own_noise():
    """One of four passes carries 16× the noise variance the model was given: its departures
    from the other passes measure that, and it is smoothed again with R × its noise ratio —
    the smoother at that level, exactly — which brings its error against the truth down
    towards the smoother's at the true level (16 R); the calm passes are left as they were.
    With every pass as modelled nothing is smoothed again."""
    dt, T, R, speed, q = 0.5, 3000, 1.0, 60.0, 2e-5
    inner = slice(300, T - 300)
    errs = []
    for seed in range(3):
        rng = np.random.default_rng(61 + seed)
        lines, zs, truths = _repeat_passes(rng, 4, T, dt, q, R, speed, r_factors=[1.0, 16.0, 1.0, 1.0])
        f = _track_table(lines, zs, q, R, T, dt)
        before = f.table["dg_mgal"].to_numpy().reshape(4, T).copy()
        f.rescale_noisy_passes(dt, 2, "bf", None, True, 8.0, 100.0)
        after = f.table["dg_mgal"].to_numpy().reshape(4, T)
        track = f.noisy_passes["T1"]
        assert track["noise_p_value"] < 0.1
        factors = {r["line"]: r["R_factor"] for r in track["rescaled"]}
        assert "1" in factors and all(v < 1.5 for k, v in factors.items() if k != "1"), track
        rho = factors["1"]
        assert 3.0 < rho < 30.0, track            # its noise over its posterior (16x the model: 4-12 measured)
        ref = kalman_smooth(zs[1], np.full(T, q), np.full(T, R * rho), dt, m=2)
        np.testing.assert_allclose(after[1], ref.dg_mgal, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(f.table["dg_std_mgal"].to_numpy().reshape(4, T)[1], ref.dg_std_mgal, rtol=1e-9)
        np.testing.assert_allclose(f.table["R_cm2s2"].to_numpy().reshape(4, T)[1], R * rho)
        calm = [k for k in (0, 2, 3) if str(k) not in factors]   # a calm pass at most a little (chance)
        np.testing.assert_array_equal(after[calm], before[calm])
        def rms(x, truth=truths[1]):
            return float(np.sqrt(np.mean((x[inner] - truth[inner]) ** 2)))
        best = rms(kalman_smooth(zs[1], np.full(T, q), np.full(T, 16 * R), dt, m=2).dg_mgal)
        assert rms(after[1]) < 0.85 * rms(before[1]), (rms(after[1]), rms(before[1]))
        errs.append((rms(after[1]), best))
    # ρ is measured against the posterior, which holds a smoothing part: R × ρ stays below the
    # true 16 R, and so does the gain (seeds 61-63: 1.77, 2.64, 2.39 against 1.70, 2.27, 2.24 mGal)
    assert np.mean([a for a, _ in errs]) < 1.15 * np.mean([b for _, b in errs]), errs
    rng = np.random.default_rng(70)
    lines, zs, _ = _repeat_passes(rng, 4, T, dt, q, R, speed)
    f = _track_table(lines, zs, q, R, T, dt)
    before = f.table["dg_mgal"].to_numpy().copy()
    f.rescale_noisy_passes(dt, 2, "bf", None, True, 8.0, 100.0)
    assert f.noisy_passes["T1"]["noise_p_value"] >= 0.1 and not f.noisy_passes["T1"]["rescaled"]
    np.testing.assert_array_equal(f.table["dg_mgal"].to_numpy(), before)


def test_a_pass_with_a_slow_departure_is_not_smoothed_more():
    """A pass that departs from the others slowly (a 20-minute swing of 6 mGal, which more
    smoothing does not remove: generated test line 56's third pass, whose error grew 7.0 →
    9.2 mGal when it was smoothed with R × 3.5) is tried and left as it was: its departure
    from the other passes does not fall."""
    dt, T, R, speed, q = 0.5, 3000, 1.0, 60.0, 2e-5
    rng = np.random.default_rng(80)
    lines, zs, _ = _repeat_passes(rng, 4, T, dt, q, R, speed)
    t = np.arange(T) * dt
    zs[2] = zs[2] + 6.0 * np.sin(2 * np.pi * t / 1200.0)
    f = _track_table(lines, zs, q, R, T, dt)
    before = f.table["dg_mgal"].to_numpy().copy()
    f.rescale_noisy_passes(dt, 2, "bf", None, True, 8.0, 100.0)
    track = f.noisy_passes["T1"]
    assert track["noise_p_value"] < 0.1 and "2" in [r["line"] for r in track["tried"]], track
    tried = {r["line"]: r for r in track["tried"]}
    assert tried["2"]["departure_after"] > 0.95 * tried["2"]["departure_before"]
    assert "2" not in [r["line"] for r in track["rescaled"]]
    np.testing.assert_array_equal(f.table["dg_mgal"].to_numpy().reshape(4, T)[2], before.reshape(4, T)[2])


def test_a_noisy_pass_with_a_hole_or_only_two_passes_is_smoothed_again():
    """A hole (NaN) in the noisy pass's std and a zero-std stretch in a calm one: the noisy pass
    is still found and smoothed again, the others left.  Two passes alone cannot tell whose
    noise it is (each departs from the other alike): both are smoothed more, by one factor."""
    dt, T, R, speed, q = 0.5, 3000, 1.0, 60.0, 2e-5
    rng = np.random.default_rng(61)
    lines, zs, truths = _repeat_passes(rng, 4, T, dt, q, R, speed, r_factors=[1.0, 16.0, 1.0, 1.0])
    f = _track_table(lines, zs, q, R, T, dt)
    std = f.table["dg_std_mgal"].to_numpy().copy()
    std[T + 500:T + 520] = np.nan
    std[2 * T + 900:2 * T + 905] = 0.0
    f.table["dg_std_mgal"] = std
    before = f.table["dg_mgal"].to_numpy().reshape(4, T).copy()
    f.rescale_noisy_passes(dt, 2, "bf", None, True, 8.0, 100.0)
    done = {r["line"]: r["R_factor"] for r in f.noisy_passes["T1"]["rescaled"]}
    assert "1" in done and done["1"] > 3.0, f.noisy_passes
    after = f.table["dg_mgal"].to_numpy().reshape(4, T)
    assert np.all(np.isfinite(after)) and np.all(np.isfinite(f.table["dg_std_mgal"].to_numpy().reshape(4, T)[1]))
    inner = slice(300, T - 300)
    assert np.std(after[1, inner] - truths[1][inner]) < 0.85 * np.std(before[1, inner] - truths[1][inner])
    # two passes, one of them noisy
    g = _track_table(lines[:2], zs[:2], q, R, T, dt)
    g.rescale_noisy_passes(dt, 2, "bf", None, True, 8.0, 100.0)
    track = g.noisy_passes["T1"]
    assert track["noise_p_value"] < 0.1
    np.testing.assert_allclose(track["pass_noise_ratio"][0], track["pass_noise_ratio"][1])
    assert {r["line"] for r in track["tried"]} == {"0", "1"}


def _level_track(seed, q_true, q_used):
    dt, T, R, speed = 0.5, 3000, 1.0, 60.0
    rng = np.random.default_rng(seed)
    lines, zs, truths = _repeat_passes(rng, 4, T, dt, q_true, R, speed)
    for ln, z in zip(lines, zs):
        ln.z_mgal = z
    for ln in lines:
        ln.speed_ms = speed
    f = _track_table(lines, zs, q_used, R, T, dt)
    f.table["Q_mgal2"] = q_used
    return f, truths, dt, T


def test_a_test_lines_level_is_lowered_where_its_passes_agree_better_so():
    """The model's level 10x too high (the estimate passes noise): the repeat passes agree
    better with the other passes' 50 s low-pass of z at Q/3, so every line is smoothed again
    there — the smoother at Q/3, exactly — and its error against the truth falls.  With the
    level right, Q/3 over-smooths, the passes agree worse, and nothing changes."""
    q = 2e-5
    inner = slice(300, -300)
    for seed in (90, 93, 96):     # lowered on 7 of seeds 90-99 (the test's power), never with Q right
        f, truths, dt, T = _level_track(seed, q, 10 * q)
        before = f.table["dg_mgal"].to_numpy().reshape(4, T).copy()
        f.repeat_level_check(dt, 2, "bf", None, True, (1 / 3, 1.0), 0.1, 50.0, 6.0, 3)
        rep = f.repeat_level
        assert rep["factor"] == 1 / 3 and rep["msd_mgal2"][0] < rep["msd_mgal2"][1], rep
        assert rep["p_values"]["0.333333"] < 0.1, rep
        np.testing.assert_allclose(f.Q_levels, [10 * q / 3])
        after = f.table["dg_mgal"].to_numpy().reshape(4, T)
        for k in range(4):
            ref = kalman_smooth(f.prepared[k].z_ext, np.full(T, 10 * q / 3), np.full(T, 1.0), dt, m=2)
            np.testing.assert_allclose(after[k], ref.dg_mgal, rtol=1e-9, atol=1e-9)
        err = [float(np.sqrt(np.mean((x[:, inner] - np.array(truths)[:, inner]) ** 2))) for x in (before, after)]
        assert err[1] < 0.9 * err[0], err
        # the level right: kept
        g, _, dt, T = _level_track(seed, q, q)
        kept = g.table["dg_mgal"].to_numpy().copy()
        g.repeat_level_check(dt, 2, "bf", None, True, (1 / 3, 1.0), 0.1, 50.0, 6.0, 3)
        assert g.repeat_level["factor"] == 1.0, g.repeat_level
        np.testing.assert_array_equal(g.table["dg_mgal"].to_numpy(), kept)
        np.testing.assert_allclose(g.Q_levels, [q])


def test_a_test_lines_level_is_raised_or_lowered_by_its_passes_against_their_smoother_reference():
    """Against the other passes smoothed at 300 x Q(t), away from the tracks' ends, the check
    looks both ways: with the model's level 10x too low (the estimate rounds the anomaly off)
    it raises Q by 3 — in the lines' interiors, where it judged, every line smoothed again
    with that Q(t), exactly — and the error against the truth there falls; with it 10x too
    high it lowers Q by 3; with the level right nothing changes."""
    q = 2e-5
    inner = slice(400, -400)       # 12 km in: 30 m per epoch
    args = (0.1, 50.0, 6.0, 3, 50.0)
    # seeds 90-97: raised on 6 of 8 with the level 10x too low, lowered on 7 of 8 with it 10x too
    # high, never moved with the level right
    for seed in (90, 91, 92):
        for q_used, want in ((q / 10, 3.0), (10 * q, 1 / 3)):
            f, truths, dt, T = _level_track(seed, q, q_used)
            before = f.table["dg_mgal"].to_numpy().reshape(4, T).copy()
            f.repeat_level_check(dt, 2, "bf", None, True, (1 / 3, 1.0, 3.0), *args, reference_q_factor=300.0,
                                 edge_km=10.0)
            rep = f.repeat_level
            assert rep["factor"] == want, rep
            assert rep["reference"] == "estimate at 300 x Q(t)" and rep["edge_km"] == 10.0, rep
            np.testing.assert_allclose(f.Q_levels, [q_used])
            # Q(t) scaled 10 km or more from the ends of each 90 km pass (30 m per epoch), kept nearer
            along = np.arange(T) * dt * 60.0 / 1000.0
            q_t = np.where(np.minimum(along, along[-1] - along) >= 10.0, q_used * want, q_used)
            np.testing.assert_allclose(f.table["Q_mgal2"].to_numpy().reshape(4, T)[0], q_t)
            after = f.table["dg_mgal"].to_numpy().reshape(4, T)
            ref = kalman_smooth(f.prepared[0].z_ext, q_t, np.full(T, 1.0), dt, m=2)
            np.testing.assert_allclose(after[0], ref.dg_mgal, rtol=1e-9, atol=1e-9)
            err = [float(np.sqrt(np.mean((x[:, inner] - np.array(truths)[:, inner]) ** 2))) for x in (before, after)]
            assert err[1] < 0.95 * err[0], (seed, q_used, err)
        g, _, dt, T = _level_track(seed, q, q)
        kept = g.table["dg_mgal"].to_numpy().copy()
        g.repeat_level_check(dt, 2, "bf", None, True, (1 / 3, 1.0, 3.0), *args, reference_q_factor=300.0,
                             edge_km=10.0)
        assert g.repeat_level["factor"] == 1.0, g.repeat_level
        np.testing.assert_array_equal(g.table["dg_mgal"].to_numpy(), kept)
        # the interior only: 90 km passes less 10 km at either end
        interior = g.repeat_level["positions"]
        g.repeat_level_check(dt, 2, "bf", None, True, (1 / 3, 1.0, 3.0), *args, reference_q_factor=300.0, edge_km=0.0)
        assert abs(interior / g.repeat_level["positions"] - 70.0 / 90.0) < 0.01, (interior, g.repeat_level)


def test_a_short_test_lines_level_is_judged_and_scaled_along_whole_lines():
    """Passes too short for an interior (27 km: 10 km off either end leaves less than three
    50 s blocks) are judged over their whole common stretch, and the level found there is
    used along whole lines (the levels scaled), not in an interior that does not exist."""
    q = 2e-5
    dt, T, R, speed = 0.5, 900, 1.0, 60.0
    for seed in (90, 91, 92, 93):
        rng = np.random.default_rng(seed)
        lines, zs, truths = _repeat_passes(rng, 4, T, dt, q, R, speed)
        for ln, z in zip(lines, zs):
            ln.z_mgal = z
        f = _track_table(lines, zs, 10 * q, R, T, dt)
        f.table["Q_mgal2"] = 10 * q
        f.repeat_level_check(dt, 2, "bf", None, True, (1 / 3, 1.0, 3.0), 0.1, 50.0, 6.0, 3, 50.0,
                             reference_q_factor=300.0, edge_km=10.0)
        rep = f.repeat_level
        assert rep["edge_km"] == 0.0 and "scaled" not in rep, rep
        if rep["factor"] != 1.0:
            np.testing.assert_allclose(f.Q_levels, [10 * q * rep["factor"]])
            np.testing.assert_allclose(f.table["Q_mgal2"].to_numpy(), 10 * q * rep["factor"])
            break
    else:
        raise AssertionError("the check never moved the level on four short tracks 10x too rough")


def test_a_lines_interior_is_measured_along_it_and_a_missing_position_adds_no_distance():
    """The interior a test line's scaled level applies to: epochs at least edge_km along the
    line (its cumulative horizontal distance, here a 30 km line bent at 10 km) from both ends,
    none in the run-ins; a position missing mid-line leaves the distance as it was."""
    from types import SimpleNamespace

    from app.pipeline.stages.filtering import _interior
    s = np.linspace(0.0, 30.0, 301)                     # 100 m steps
    e = np.where(s <= 10.0, s, 10.0)                    # east 10 km, then north 20 km
    n = np.where(s <= 10.0, 0.0, s - 10.0)
    line = SimpleNamespace(easting_km=e.copy(), northing_km=n.copy())
    pr = PreparedLine(line, None, None, np.zeros(341), slice(20, 321), None, None, None)
    mask = _interior(pr, 10.0)
    assert not mask[:20].any() and not mask[321:].any()
    np.testing.assert_array_equal(np.flatnonzero(mask) - 20, np.arange(100, 201))
    # one missing fix at 15 km: its two steps add nothing (29.8 km in all), and the rest of the
    # line keeps its distance (a NaN carried along would have cut the interior at 15 km)
    line.easting_km[150] = np.nan
    mask = _interior(pr, 10.0)
    np.testing.assert_array_equal(np.flatnonzero(mask) - 20, np.arange(100, 201))


def test_levels_the_em_did_not_tell_apart_carry_their_uncertainty():
    """Two levels learned alike (within ``min_contrast`` of each other) from enough points: the
    map says nothing of where the anomaly is rougher — here a line whose second half is 100x
    rougher, smoothed at two learned levels 1.7x apart near their geometric mean (as the EM
    gives where the noise hides the contrast: the 1 Hz GNSS regime, 1.18x).  The posterior std
    covers the rough half's error on about half of its epochs; the one-level spread on ~88 %.  Levels learned apart (or
    the learned ones when a refinement lifted one past the contrast) are judged as learned."""
    dt, T, R, step = 0.1, 20000, 1.0, 100
    q_true = np.array([2e-9, 2e-7])
    q_alike = np.array([1.5e-8, 2.5e-8])
    cov = {"plain": [], "spread": []}
    for seed in range(3):
        rng = np.random.default_rng(10 + seed)
        z, dg, state, idx, pq = _two_level_line(rng, T, dt, q_true, R, step)
        pq = np.full_like(pq, 0.5)   # the map cannot tell the levels apart either
        pr = PreparedLine(None, state, state, z, slice(0, T), None, idx, pq)
        lq = np.exp(np.interp(np.arange(T), idx, pq @ np.log(q_alike)))
        sm = kalman_smooth(z, lq, np.full(T, R), dt, m=2)
        table = pd.DataFrame({"dg_mgal": sm.dg_mgal, "dg_std_mgal": sm.dg_std_mgal})
        rough = slice(T // 2 + 1000, T - 1000)
        err = np.abs(sm.dg_mgal - dg)[rough]
        for learned, expect in ((q_alike, True), (q_true, False), (None, True)):
            # None: the levels as refined are judged (q_alike here)
            f = Filtered(table.copy(), q_alike, None, 1.0, prepared=[pr], r_lines=[np.full(T, R)], n_r=1)
            f.level_spread_std(dt, 2, "bf", None, 10.0, n_points=5000, min_points=200, min_contrast=3.0,
                               em_levels_mgal2=learned)
            std = f.table["dg_std_mgal"].to_numpy()
            if expect:
                assert f.std_level_factor == 10.0 and "within a factor 1.67" in f.std_level_reason
                np.testing.assert_array_equal(f.table["dg_mgal"].to_numpy(), sm.dg_mgal)
                assert np.all(std >= sm.dg_std_mgal)
                if learned is not None:
                    cov["spread"].append(np.mean(err < 2 * std[rough]))
            else:
                assert f.std_level_factor is None and np.array_equal(std, sm.dg_std_mgal)
        # off (min_contrast None): left as the smoother gave it
        f = Filtered(table.copy(), q_alike, None, 1.0, prepared=[pr], r_lines=[np.full(T, R)], n_r=1)
        f.level_spread_std(dt, 2, "bf", None, 10.0, n_points=5000, min_points=200, em_levels_mgal2=q_alike)
        assert f.std_level_factor is None
        cov["plain"].append(np.mean(err < 2 * sm.dg_std_mgal[rough]))
    assert np.mean(cov["plain"]) < 0.65, cov     # 0.50-0.58 on the rough half
    assert np.mean(cov["spread"]) > 0.85, cov    # 0.87-0.89


def test_a_test_lines_level_a_decade_too_low_is_raised_by_the_ladder():
    """With the model's level 30x too low the check's ladder (Q/3, Q, 3Q, 9Q: the defaults'
    ``repeat_level_factors``) takes 9Q where the passes agree significantly better so, and the
    error against the truth in the interiors falls below what 3Q alone gives; with the level
    right the ladder leaves it.  Seeds 90-99: 9Q on 10 of 10 (error 6-19 % below 3Q's), never
    moved with the level right."""
    from app.config import ProcessingParams
    from app.pipeline.runs import repeat_level_factors

    ladder = repeat_level_factors(ProcessingParams())
    assert ladder == (1 / 3, 1.0, 3.0, 9.0)
    assert repeat_level_factors(ProcessingParams(repeat_level_raise_steps=1)) == (1 / 3, 1.0, 3.0)
    q = 2e-5
    inner = slice(400, -400)
    args = (0.1, 50.0, 6.0, 3, 50.0)
    errs = {}
    for seed in (90, 91, 92):
        for name, factors in (("three", (1 / 3, 1.0, 3.0)), ("ladder", ladder)):
            f, truths, dt, T = _level_track(seed, q, q / 30)
            f.repeat_level_check(dt, 2, "bf", None, True, factors, *args, reference_q_factor=300.0, edge_km=10.0)
            after = f.table["dg_mgal"].to_numpy().reshape(4, T)
            errs.setdefault(name, []).append(float(np.sqrt(np.mean((after[:, inner] - np.array(truths)[:, inner]) ** 2))))
            if name == "ladder":
                assert f.repeat_level["factor"] == 9.0, f.repeat_level
        g, _, dt, T = _level_track(seed, q, q)
        g.repeat_level_check(dt, 2, "bf", None, True, ladder, *args, reference_q_factor=300.0, edge_km=10.0)
        assert g.repeat_level["factor"] == 1.0, g.repeat_level
    assert all(b < 0.95 * a for a, b in zip(errs["three"], errs["ladder"])), errs
