"""Continuation to a common datum through the whole pipeline (issue acceptance, products part 5):
on a simulated draped survey the continued anomaly at the datum is compared with the true field at
the datum, and repeat passes flown at different heights are compared before and after continuation.

Survey: the ``draped`` preset shrunk to one flight (5 main lines of 30 km 2 km apart, 3 ties, the
repeat track flown twice), draped ±200 m around 3000 m (the preset's ±50 m barely moves the field
at 3 km: the datum would not matter) and the two repeat passes 300 m below and 300 m above the
other lines (``repeat_height_offsets_m``).  One identification, then the filter stage with
``datum = "flight"`` (the line estimates at flight height, the reference), ``"constant"`` (the mean
flight height) and ``"draped"``.  The simulator has no atmosphere, so the atmospheric correction is
off here (it would add a constant ~0.6 mGal the truth does not have).

Truth at the datum: the simulator writes the truth at flight height only (``truth/lines.parquet``
``dg_true_mgal`` at ``h_true_m``; ``truth/grid.nc`` at the nominal height).  It records its point
masses in ``truth.json`` ``field.sources`` (x, y relative to ``survey_centre_km``, m; z, m; mass,
kg; ``offset_mgal``), so the true field at any point is harmonica's ``point_gravity(g_z)`` of them
minus the offset — checked here against ``dg_true_mgal`` at flight height first.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

SIM = dict(n_main=5, main_length_km=30.0, n_tie=3, n_repeat=2, repeat_length_km=20.0, n_flights=1,
           drape_amp_m=200.0, repeat_height_offsets_m=(-300.0, 300.0), compress=False)
DATUMS = ("flight", "constant", "draped")


def _rms(a) -> float:
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a ** 2)))


class TrueField:
    """The simulator's anomaly at any position (km, absolute) and height (m), from truth.json."""

    def __init__(self, survey: Path):
        tj = json.loads((survey / "truth" / "truth.json").read_text())
        self.src = tj["field"]["sources"]
        self.e0, self.n0 = tj["survey_centre_km"]

    def __call__(self, e_km, n_km, h_m) -> np.ndarray:
        import harmonica as hm

        e, n = np.asarray(e_km, float), np.asarray(n_km, float)
        h = np.broadcast_to(np.asarray(h_m, float), e.shape)
        s = self.src
        return hm.point_gravity(((e - self.e0) * 1000.0, (n - self.n0) * 1000.0, h), (s["x_m"], s["y_m"], s["z_m"]),
                                s["mass_kg"], field="g_z") - s["offset_mgal"]


@pytest.fixture(scope="module")
def datum_runs(tmp_path_factory):
    """The survey, its truth and the three filter outputs (one identification)."""
    from app.config import SurveyConfig
    from app.io.survey import read_survey
    from app.pipeline.evaluate import merge_truth
    from app.pipeline.runs import Tracker, run_filter, run_identify
    from app.simulate import simulate_survey

    base = tmp_path_factory.mktemp("datum")
    survey = simulate_survey("draped", base / "survey", seed=1, **SIM)
    idf = run_identify(read_survey(survey, {"atmospheric_correction": False}), Tracker(None))
    truth = pd.read_parquet(survey / "truth" / "lines.parquet")
    cfg0 = json.loads(json.dumps(idf.config))
    runs = {}
    for datum in DATUMS:
        cfg = json.loads(json.dumps(cfg0))
        cfg["processing"]["datum"] = datum
        idf.config = SurveyConfig.model_validate(cfg).model_dump(mode="json")
        out = base / f"out-{datum}"
        report = run_filter(idf, out, Tracker(None))
        lines = pd.read_parquet(out / "lines.parquet")
        lines["line"] = lines["line"].astype(str)
        runs[datum] = {"report": report, "lines": lines, "merged": merge_truth(lines, truth)}
    return {"survey": survey, "truth": truth, "field": TrueField(survey), "runs": runs}


def test_truth_from_the_sources_is_the_simulators(datum_runs):
    m = datum_runs["runs"]["flight"]["merged"]
    m = m[m["dg_true_mgal"].notna()]
    f = datum_runs["field"](m["easting_km"], m["northing_km"], m["h_true_m"])
    # epoch positions vs the interval midpoints the simulator evaluates at (5 m of track)
    assert _rms(f - m["dg_true_mgal"]) < 0.05


def figures(d) -> dict:
    """The acceptance figures (mGal) on the survey lines (main and tie) and the repeat passes."""
    field, runs = d["field"], d["runs"]
    ref = runs["flight"]["merged"]
    ref = ref[(ref["kind"] != "repeat") & ref["dg_true_mgal"].notna()]
    out = {"line_rms_flight_height": _rms(ref["dg_mgal"] - ref["dg_true_mgal"])}
    for datum in ("constant", "draped"):
        m = runs[datum]["merged"]
        m = m[(m["kind"] != "repeat") & m["dg_true_mgal"].notna()]
        at_datum = field(m["easting_km"], m["northing_km"], m["datum_height_m"])
        out[datum] = {"continued_vs_truth_at_datum": _rms(m["dg_mgal"] - at_datum),
                      "flight_values_vs_truth_at_datum": _rms(m["dg_flight_mgal"] - at_datum),
                      "truth_flight_vs_truth_datum": _rms(m["dg_true_mgal"] - at_datum),
                      "datum_height_m": [float(m["datum_height_m"].min()), float(m["datum_height_m"].max())]}
    out["repeat"] = repeat_figures(runs["constant"]["lines"], d)
    return out


def _on_track(g: pd.DataFrame, col: str, x) -> np.ndarray:
    g = g.sort_values("easting_km")
    return np.interp(x, g["easting_km"].to_numpy(), g[col].to_numpy(float), left=np.nan, right=np.nan)


def repeat_figures(lines: pd.DataFrame, d) -> dict:
    """The two repeat passes (east–west over one track) compared point by point along the track.

    * before: the line estimates at flight height (``dg_flight_mgal``, 600 m apart in height);
    * after, as processed: the pipeline's continued values (one joint fit of every line: the passes
      agree by construction, as far as their positions coincide);
    * after, each pass on its own: the pipeline's equivalent sources refitted to the other lines plus
      that pass only, evaluated on the pass at the datum — the passes then share no data."""
    from app.core.continuation import fit_equivalent_sources

    a, b = lines[lines["line"] == "R1-1"], lines[lines["line"] == "R1-2"]
    x = a["easting_km"].to_numpy()
    others = ~lines["line"].isin(["R1-1", "R1-2"])
    own = {}
    for name in ("R1-1", "R1-2"):
        s = lines[others | (lines["line"] == name)]
        model = fit_equivalent_sources(s["easting_km"].to_numpy() * 1000.0, s["northing_km"].to_numpy() * 1000.0,
                                       s["h"].to_numpy(float), s["dg_flight_mgal"].to_numpy(float),
                                       np.maximum(s["dg_std_mgal"].to_numpy(float), 1e-3), s["line"].to_numpy())
        p = lines[lines["line"] == name]
        own[name] = p.assign(own=model.predict(p["easting_km"].to_numpy() * 1000.0, p["northing_km"].to_numpy() * 1000.0,
                                               p["datum_height_m"].to_numpy(float)))
    truth = d["truth"]
    ta, tb = truth[truth["line"] == "R1-1"], truth[truth["line"] == "R1-2"]
    at_datum = d["field"](a["easting_km"], a["northing_km"], a["datum_height_m"])
    return {"height_m": [float(a["h"].mean()), float(b["h"].mean())],
            "before": _rms(a["dg_flight_mgal"].to_numpy() - _on_track(b, "dg_flight_mgal", x)),
            "true_vertical_signal": _rms(ta["dg_true_mgal"].to_numpy()
                                         - _on_track(tb, "dg_true_mgal", ta["easting_km"].to_numpy())),
            "after_joint": _rms(a["dg_mgal"].to_numpy() - _on_track(b, "dg_mgal", x)),
            "after_own_fit": _rms(own["R1-1"]["own"].to_numpy() - _on_track(own["R1-2"], "own", x)),
            "own_fit_vs_truth_at_datum": [_rms(own["R1-1"]["own"].to_numpy() - at_datum),
                                          _rms(own["R1-2"]["own"].to_numpy()
                                               - _on_track(b.assign(t=d["field"](b["easting_km"], b["northing_km"],
                                                                                 b["datum_height_m"])), "t", x))]}


def test_continued_anomaly_at_the_datum_vs_truth(datum_runs):
    f = figures(datum_runs)
    print("datum figures (mGal):", json.dumps(f, indent=1))
    line_rms = f["line_rms_flight_height"]
    for datum in ("constant", "draped"):
        g = f[datum]
        assert g["continued_vs_truth_at_datum"] <= 1.1 * line_rms, (datum, g, line_rms)
    # the constant datum is a real continuation here (the drape moves the field by 0.3+ mGal) and
    # it costs no accuracy against taking the flight values as the datum's.  It cannot be asked to
    # beat them by much: the field moves by ~0.44 mGal between the heights, under line errors of
    # ~4 mGal, so a perfect continuation gains ~0.02 mGal.  (It used to beat them by 0.7 mGal while
    # the lines' white-velocity level was over-stated: the equivalent sources smoothed noisier lines
    # (line RMS 4.81 mGal); with the level the GNSS heights allow (stage 3) the lines are at 4.12
    # and the continued values 4.24 against 4.13.)
    assert f["constant"]["truth_flight_vs_truth_datum"] > 0.3
    assert f["constant"]["continued_vs_truth_at_datum"] < 1.05 * f["constant"]["flight_values_vs_truth_at_datum"]
    rep = datum_runs["runs"]["constant"]["report"]
    assert rep["products"]["datum"]["datum"] == "constant"
    assert rep["products"]["datum"]["height_m"]["mean"] == pytest.approx(3000.0, abs=60.0)


def test_repeat_passes_at_different_heights_agree_after_continuation(datum_runs):
    r = figures(datum_runs)["repeat"]
    print("repeat passes (mGal):", json.dumps(r, indent=1))
    assert r["height_m"][1] - r["height_m"][0] == pytest.approx(600.0, abs=30.0)
    assert r["true_vertical_signal"] > 2.0           # 600 m of height difference is visible in the field
    assert r["after_joint"] < 0.1 * r["before"]      # as processed (one fit of every line)
    assert r["after_own_fit"] < r["before"]          # each pass continued without the other one


def test_flight_height_grid_beside_the_datum_grid(datum_runs):
    """With a datum, ``grid.*`` is at the datum and ``grid_flight.*`` at flight height (the line
    estimates before continuation); without one there is no ``grid_flight``."""
    import xarray as xr

    runs = datum_runs["runs"]
    assert runs["flight"]["report"]["products"]["grids"]["free_air_flight_height"] is None
    rep = runs["constant"]["report"]["products"]["grids"]
    assert rep == {"free_air": "grid", "bouguer": None, "free_air_flight_height": "grid_flight"}
    out = datum_runs["survey"].parent
    assert not (out / "out-flight" / "grid_flight.nc").exists()
    with xr.open_dataset(out / "out-constant" / "grid_flight.nc") as gf, \
            xr.open_dataset(out / "out-flight" / "grid.nc") as g0, xr.open_dataset(out / "out-constant" / "grid.nc") as gd:
        assert gf["dg"].shape == g0["dg"].shape == gd["dg"].shape
        a, b, c = gf["dg"].values, g0["dg"].values, gd["dg"].values
        ok = np.isfinite(a) & np.isfinite(b) & np.isfinite(c)
        # the same values as a run without datum (up to the std rescaling that weights the gridding) ...
        print("grid_flight vs flight run", _rms(a[ok] - b[ok]), "grid_flight vs datum grid", _rms(a[ok] - c[ok]))
        assert _rms(a[ok] - b[ok]) < 0.5 * _rms(a[ok] - c[ok])
        assert np.isfinite(gf["dg_std"].values[ok]).all()
