"""Q(t) from the smoothed map's probabilities instead of the held hard state: where the
recognition is unsure (plains next to mountains, misrecognised patches) the smoother
should not switch to the rough level — plains get more accurate, mountains do not get
worse (simulation with known truth)."""

import numpy as np
import pandas as pd

from app.pipeline.evaluate import merge_truth


def test_posterior_weighted_q_beats_hard_states_on_plains(tmp_path):
    from app.pipeline.process import process_survey
    from app.simulate import simulate_survey

    survey = simulate_survey("omolon-mini", tmp_path / "s", seed=9, n_main=8, n_repeat=0, n_flights=2)
    truth = pd.read_parquet(survey / "truth" / "lines.parquet")
    rms = {}
    for soft in (True, False):
        out = tmp_path / f"soft{soft}"
        process_survey(survey, out, {"q_from_posteriors": soft, "m": 1})
        m = merge_truth(pd.read_parquet(out / "lines.parquet"), truth)
        L = m.groupby("line")["along_km"].transform("max")
        core = m[(m["along_km"] > 10) & (m["along_km"] < L - 10)]
        e = core["dg_unleveled_mgal"] - core["dg_true_mgal"]
        e = e - e.groupby(core["line"]).transform("mean")
        rms[soft] = {t: float(np.sqrt(np.mean(e[core["terrain"] == t] ** 2))) for t in ("plain", "mountain")}
        q = pd.read_parquet(out / "lines.parquet")["Q_mgal2"]
        assert q.notna().all() and (q > 0).all()
    assert rms[True]["plain"] < rms[False]["plain"], rms
    assert rms[True]["mountain"] < 1.02 * rms[False]["mountain"], rms
