"""Stage 10 on a test line (no crossovers): the repeat passes leveled against each other
(simulation with known truth, no simulator: passes of one track with known offsets, drift and
along-track correlated errors)."""

import numpy as np
import pandas as pd
import pytest
from scipy.ndimage import gaussian_filter1d

from app.config import ProcessingParams
from app.pipeline.stages.leveling import level_lines_table


def _test_line(rng, offsets_mgal, rate_mgal_h, heights_m=(2000.0,) * 4, noise_mgal=0.4, corr_samples=15.0):
    """Four 40 km passes of one E-W track at 60 m/s, 1 Hz, alternating directions, 20 min apart,
    one flight; ``dg_unleveled_mgal`` = truth + each pass's offset + the flight's linear drift
    + an error correlated over ~1 km (a Gaussian kernel of ``corr_samples`` epochs of 60 m)."""
    s = np.arange(0.0, 40.0, 0.06)
    truth = 10.0 * np.sin(s / 4.0) + 3.0 * np.cos(s / 1.3)
    rows = []
    for k, (off, h) in enumerate(zip(offsets_mgal, heights_m)):
        e = s if k % 2 == 0 else s[::-1]
        g = truth if k % 2 == 0 else truth[::-1]
        t = 1000.0 + 1200.0 * k + np.arange(s.size)
        err = gaussian_filter1d(rng.normal(0.0, 1.0, s.size), corr_samples)
        err *= noise_mgal / err.std()
        rows.append(pd.DataFrame({"line": f"R1-{k + 1}", "flight": "F01", "kind": "repeat", "track": "R1", "time": t,
                                  "easting_km": e, "northing_km": 0.02 * rng.normal(size=s.size), "h": h,
                                  "dg_true_mgal": g, "dg_unleveled_mgal": g + off + err}))
    table = pd.concat(rows, ignore_index=True)
    table["dg_unleveled_mgal"] += rate_mgal_h * (table["time"] - table["time"].mean()) / 3600.0
    table["dg_mgal"] = table["dg_unleveled_mgal"]
    table["dg_std_mgal"] = noise_mgal
    return table


def _pass_offsets(table, col):
    e = table[col] - table["dg_true_mgal"]
    return e.groupby(table["line"]).mean().to_numpy()


def test_offsets_and_drift_of_the_passes_are_removed_keeping_their_mean_level():
    p = ProcessingParams()
    for seed in range(3):
        table = _test_line(np.random.default_rng(seed), [1.5, -2.0, 0.5, 3.0], 2.0)
        warnings: list = []
        cx, rep = level_lines_table(table, p, warnings, tied=False)
        assert len(cx) == 0 and rep["status"] == "not leveled: no crossovers"
        tr = rep["repeat_tracks"]["R1"]
        assert tr["status"] == "leveled" and tr["p_value"] < 0.01
        before, after = _pass_offsets(table, "dg_unleveled_mgal"), _pass_offsets(table, "dg_mgal")
        assert np.ptp(before) > 5.0
        assert np.ptp(after) < 0.3                       # the passes agree in level now
        assert after.mean() == pytest.approx(before.mean(), abs=0.05)   # ... at their mean level
        # each pass's own error, less its mean: the drift inside the pass is gone too
        inside = [np.std(g["dg_mgal"] - g["dg_true_mgal"]) for _, g in table.groupby("line")]
        assert max(inside) < 0.6
        assert any("passes were leveled against each other" in w for w in warnings)
        assert set(tr["mean_correction_mgal"]) == {"R1-1", "R1-2", "R1-3", "R1-4"}


def test_passes_without_offsets_lose_nothing():
    """By default the passes are always leveled (the F-test's p reported).  Without offsets or
    drift the fit removes the part of the passes' errors that looks like offsets and drift (a
    least-squares projection of their differences, which the passes' mean does not share), so the
    passes' total error cannot grow (one pass's may); inside the passes it stays put."""
    for seed in range(10):
        table = _test_line(np.random.default_rng(100 + seed), [0.0] * 4, 0.0)
        _, rep = level_lines_table(table, ProcessingParams(), [], tied=False)
        assert rep["repeat_tracks"]["R1"]["status"] == "leveled"
        err = {col: table[col] - table["dg_true_mgal"] for col in ("dg_unleveled_mgal", "dg_mgal")}
        total = {col: np.sqrt(np.mean(e ** 2)) for col, e in err.items()}
        inside = {col: np.sqrt(np.mean((e - e.groupby(table["line"]).transform("mean")) ** 2)) for col, e in err.items()}
        assert total["dg_mgal"] <= total["dg_unleveled_mgal"] * 1.005
        assert inside["dg_mgal"] <= inside["dg_unleveled_mgal"] * 1.05


def test_tied_passes_without_offsets_are_left_alone():
    """Flights tied to an absolute base reading: leveled only where the F-test finds offsets or a
    drift (p < 0.05 by default); where untied, always (above).  The errors here are correlated
    over well under a block (50 s, 3 km), as the F-test assumes."""
    p = ProcessingParams()
    left = 0
    for seed in range(30):
        table = _test_line(np.random.default_rng(100 + seed), [0.0] * 4, 0.0, corr_samples=4.0)
        _, rep = level_lines_table(table, p, [], tied=True)
        assert rep["repeat_tracks"]["R1"]["absolute_base_tie"] is True
        if rep["repeat_tracks"]["R1"]["status"] != "leveled":
            left += 1
            assert np.array_equal(table["dg_mgal"], table["dg_unleveled_mgal"])
    assert left >= 26
    # ... and still levels passes that differ
    table = _test_line(np.random.default_rng(7), [1.5, -2.0, 0.5, 3.0], 2.0)
    _, rep = level_lines_table(table, p, [], tied=True)
    assert rep["repeat_tracks"]["R1"]["status"] == "leveled"


def test_passes_at_different_heights_are_not_leveled():
    table = _test_line(np.random.default_rng(5), [1.5, -2.0, 0.5, 3.0], 2.0, heights_m=(1000.0, 1000.0, 2000.0, 2000.0))
    _, rep = level_lines_table(table, ProcessingParams(), [], tied=False)
    assert rep["repeat_tracks"]["R1"]["status"].startswith("not leveled: the passes were flown 1000 m apart")
    assert np.array_equal(table["dg_mgal"], table["dg_unleveled_mgal"])


def test_switched_off():
    table = _test_line(np.random.default_rng(6), [1.5, -2.0, 0.5, 3.0], 2.0)
    _, rep = level_lines_table(table, ProcessingParams(leveling_repeat_tracks=False), [], tied=False)
    assert "repeat_tracks" not in rep
    assert np.array_equal(table["dg_mgal"], table["dg_unleveled_mgal"])


def test_a_pass_without_heights_or_with_a_hole_is_still_leveled():
    table = _test_line(np.random.default_rng(8), [1.5, -2.0, 0.5, 3.0], 2.0)
    table.loc[table["line"] == "R1-2", "h"] = np.nan             # heights lost on one pass
    hole = (table["line"] == "R1-3") & (table["easting_km"].between(10.0, 12.0))
    table.loc[hole, ["dg_unleveled_mgal", "dg_mgal"]] = np.nan    # a gap in one pass's estimate
    _, rep = level_lines_table(table, ProcessingParams(), [], tied=False)
    assert rep["repeat_tracks"]["R1"]["status"] == "leveled"
    ok = table["dg_mgal"].notna()
    after = (table["dg_mgal"] - table["dg_true_mgal"])[ok].groupby(table["line"][ok]).mean()
    assert np.ptp(after) < 0.3
    assert table.loc[hole, "dg_mgal"].isna().all()


def test_passes_flown_one_way_are_leveled_by_their_offsets():
    """A small survey's repeat line flown four times the same way (found on a random layout,
    where a drift traded against offsets put 10⁶ mGal on the passes): offsets only, bounded."""
    table = _test_line(np.random.default_rng(9), [1.5, -2.0, 0.5, 3.0], 2.0)
    for ln, g in table.groupby("line"):
        if int(ln[-1]) % 2 == 0:       # the returning passes turned round: all flown eastwards
            order = g.index.to_numpy()
            table.loc[order, ["easting_km", "dg_true_mgal"]] = table.loc[order[::-1], ["easting_km", "dg_true_mgal"]].to_numpy()
    off = table.groupby("line")["dg_unleveled_mgal"].transform("mean") - table.groupby("line")["dg_true_mgal"].transform("mean")
    table["dg_unleveled_mgal"] = table["dg_true_mgal"] + off
    table["dg_mgal"] = table["dg_unleveled_mgal"]
    _, rep = level_lines_table(table, ProcessingParams(), [], tied=False)
    tr = rep["repeat_tracks"]["R1"]
    assert tr["status"] == "leveled" and tr["degree"] == 0
    corr = table["dg_unleveled_mgal"] - table["dg_mgal"]
    assert corr.abs().max() < 5.0
    after = (table["dg_mgal"] - table["dg_true_mgal"]).groupby(table["line"]).mean()
    assert np.ptp(after) < 0.1


def test_random_tracks_never_end_further_from_the_truth():
    """Random repeat tracks — 2 to 6 passes, 1 to 3 flights hours apart, flown back and forth,
    one way or at random, overlapping wholly or in part, with gaps, offsets, drifts and errors of
    different sizes: leveled or not, the passes' error with the survey's mean removed never
    grows (the fit is a least-squares projection of their differences), and nothing raises."""
    rng = np.random.default_rng(11)
    s = np.arange(0.0, 30.0, 0.06)
    truth = 8.0 * np.sin(s / 3.0) + 2.0 * np.cos(s / 0.9)
    for case in range(24):
        K, nf = int(rng.integers(2, 7)), int(rng.integers(1, 4))
        way = ["back and forth", "one way", "random"][case % 3]
        rows, t0 = [], 1000.0
        flights = [f"F{min(k * nf // K, nf - 1)}" for k in range(K)]
        for k in range(K):
            keep = slice(0, s.size) if k % 2 == 0 or case % 2 == 0 else slice(0, int(0.8 * s.size))
            ss, g = s[keep], truth[keep]
            if {"back and forth": k % 2 == 1, "one way": False, "random": bool(rng.integers(2))}[way]:
                ss, g = ss[::-1], g[::-1]
            if k and flights[k] != flights[k - 1]:
                t0 += 20000.0
            t = t0 + np.arange(ss.size) * rng.uniform(0.5, 0.7)
            t0 = t[-1] + rng.uniform(200.0, 900.0)
            err = gaussian_filter1d(rng.normal(0.0, 1.0, ss.size), 10.0) * rng.uniform(0.5, 6.0)
            val = g + err + rng.normal(0.0, 3.0) + rng.normal(0.0, 2.0) * (t - 1000.0) / 3600.0
            if case % 4 == 3:
                val[ss.size // 3: ss.size // 3 + 20] = np.nan
            rows.append(pd.DataFrame({"line": f"R-{k}", "flight": flights[k], "kind": "repeat", "track": "R",
                                      "time": t, "easting_km": ss, "northing_km": 0.02 * rng.normal(size=ss.size),
                                      "h": 2000.0, "dg_true_mgal": g, "dg_unleveled_mgal": val}))
        table = pd.concat(rows, ignore_index=True)
        table["dg_mgal"] = table["dg_unleveled_mgal"]
        table["dg_std_mgal"] = rng.uniform(0.5, 3.0)
        level_lines_table(table, ProcessingParams(), [], tied=bool(case % 5 == 0))
        e0 = table["dg_unleveled_mgal"] - table["dg_true_mgal"]
        e1 = table["dg_mgal"] - table["dg_true_mgal"]
        assert np.nanstd(e1) <= 1.02 * np.nanstd(e0), (case, K, nf, way)
