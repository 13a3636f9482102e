"""GNSS files without ``vu``: the vertical velocity is derived from the heights.

Expectations are analytic: a not-a-knot cubic spline reproduces a cubic exactly, so
``vu`` must equal the cubic's derivative; for a smooth trajectory the pipeline's
``(V_k − V_{k−1})/Δt`` must approach the true mean acceleration over each interval.
"""

from __future__ import annotations

import numpy as np
import pytest

from app.io.errors import InputError
from app.io.survey import read_survey
from tests.io.test_io_survey import T0, make_tables, write_survey


def _survey_without_vu(tmp_path, h_fn, drop=None):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    gnss = gnss.drop(columns="vu").copy()
    gnss["h"] = h_fn(gnss["time"].to_numpy() - T0)
    if drop is not None:
        gnss = gnss.loc[~drop(gnss["time"].to_numpy() - T0)].reset_index(drop=True)
    root = write_survey(tmp_path / "s", lines, {"F1": (grav, gnss)})
    return root, gnss


def test_cubic_heights_give_the_exact_derivative(tmp_path):
    # h = 3000 + 0.5 τ − 2e-4 τ² + 3e-7 τ³ (τ = t − T0): the spline is the cubic itself
    c = (3000.0, 0.5, -2e-4, 3e-7)
    root, gnss = _survey_without_vu(tmp_path, lambda x: c[0] + c[1] * x + c[2] * x ** 2 + c[3] * x ** 3)
    s = read_survey(root)
    fl = s.flights["F1"]
    assert fl.vu_derived_from_h is True
    assert list(fl.gnss.columns) == ["time", "lat", "lon", "h", "vu", "ve", "vn"]
    x = fl.gnss["time"].to_numpy() - T0
    np.testing.assert_allclose(fl.gnss["vu"].to_numpy(), c[1] + 2 * c[2] * x + 3 * c[3] * x ** 2, rtol=0, atol=1e-9)


def test_vu_present_is_not_derived(tmp_path):
    lines, tabs = make_tables()
    root = write_survey(tmp_path / "s", lines, tabs)
    fl = read_survey(root).flights["F1"]
    assert fl.vu_derived_from_h is False
    np.testing.assert_array_equal(fl.gnss["vu"].to_numpy(), tabs["F1"][1]["vu"].to_numpy())


def test_velocity_differences_are_the_mean_acceleration(tmp_path):
    # phugoid-like motion h = A sin(ω τ): mean acceleration over (t_{k-1}, t_k] is
    # (h'(t_k) − h'(t_{k-1}))/Δt = A ω (cos ω t_k − cos ω t_{k-1})/Δt
    a_m, w = 5.0, 2 * np.pi / 20.0
    root, _ = _survey_without_vu(tmp_path, lambda x: 3000.0 + a_m * np.sin(w * x))
    g = read_survey(root).flights["F1"].gnss
    t = g["time"].to_numpy() - T0
    vu = g["vu"].to_numpy()
    got = np.diff(vu) / np.diff(t)
    ref = a_m * w * np.diff(np.cos(w * t)) / np.diff(t)
    inner = slice(10, -10)  # the not-a-knot ends are less accurate
    # spline error O(Δt⁴·h⁗) ≈ 0.1⁴·A·ω⁴ ≈ 5e-7 of the acceleration amplitude A·ω²
    np.testing.assert_allclose(got[inner], ref[inner], rtol=0, atol=1e-6 * a_m * w ** 2)


def test_gaps_split_the_spline_and_short_runs_are_errors(tmp_path):
    c = (3000.0, 0.5, -2e-4, 3e-7)
    cubic = lambda x: c[0] + c[1] * x + c[2] * x ** 2 + c[3] * x ** 3  # noqa: E731
    # a 5 s hole at τ = 5..10 s (before the first line): two runs, each still exact
    root, gnss = _survey_without_vu(tmp_path, cubic, drop=lambda x: (x > 5.0) & (x < 10.0))
    g = read_survey(root).flights["F1"].gnss
    x = g["time"].to_numpy() - T0
    np.testing.assert_allclose(g["vu"].to_numpy(), c[1] + 2 * c[2] * x + 3 * c[3] * x ** 2, rtol=0, atol=1e-9)
    # three samples stranded between two holes (τ = 5.0, 5.1, 5.2 kept): the error names their rows
    drop = lambda x: ((x > 3.0) & (x < 4.95)) | ((x > 5.25) & (x < 8.0))  # noqa: E731
    root, gnss = _survey_without_vu(tmp_path / "b", cubic, drop=drop)
    i = int(np.flatnonzero(np.isclose(gnss["time"].to_numpy() - T0, 5.0))[0])
    with pytest.raises(InputError) as ei:
        read_survey(root)
    e = ei.value
    assert (e.file, e.row, e.column) == ("flights/F1/gnss.csv", i + 2, "h")
    assert f"rows {i + 2}–{i + 4}" in e.message and "at least 4" in e.message


def test_empty_vu_column_is_derived(tmp_path):
    lines, tabs = make_tables()
    grav, gnss = tabs["F1"]
    gnss = gnss.copy()
    gnss["vu"] = np.nan
    gnss["h"] = 3000.0 + 0.25 * (gnss["time"] - T0)
    root = write_survey(tmp_path / "s", lines, {"F1": (grav, gnss)})
    fl = read_survey(root).flights["F1"]
    assert fl.vu_derived_from_h
    np.testing.assert_allclose(fl.gnss["vu"].to_numpy(), 0.25, rtol=0, atol=1e-9)
