"""The browser's QC tab and ``aerograv inspect`` show the same figures (one QC function)."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from app.cli import main as cli_main
from app.pipeline.inspect import inspect_survey
from app.simulate import simulate_survey

from .conftest import import_zip

# web QC name → column of the inspect table
FIGURES = {"gravimeter_samples": "n_gravimeter", "gnss_samples": "n_gnss", "gravimeter_rate_hz": "gravimeter_rate_hz",
           "gnss_rate_hz": "gnss_rate_hz", "gravimeter_max_gap_s": "gravimeter_max_gap_s",
           "gnss_max_gap_s": "gnss_max_gap_s", "duration_s": "duration_s", "length_km": "length_km"}


def _zip_input(root) -> bytes:
    """The survey's input files (not the simulator's truth/)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(root.rglob("*")):
            rel = p.relative_to(root)
            if p.is_file() and rel.parts[0] != "truth":
                zf.write(p, rel.as_posix())
    return buf.getvalue()


def test_web_qc_equals_cli_inspect(client, tmp_path, capsys):
    root = simulate_survey("tiny", tmp_path / "sim", seed=5, n_main=2, n_tie=1)
    table = inspect_survey(root)                      # what `aerograv inspect` prints
    assert cli_main(["inspect", str(root)]) == 0
    printed = capsys.readouterr().out
    assert "lag_s" in printed and all(str(l) in printed for l in table["line"].dropna())

    r = import_zip(client, _zip_input(root))
    assert r.status_code == 201, r.text
    qc = client.get(f"/api/surveys/{r.json()['id']}/qc").json()

    flights = table[table["level"] == "flight"].set_index("flight")
    assert sorted(f["name"] for f in qc["flights"]) == sorted(flights.index)
    for f in qc["flights"]:
        row = flights.loc[f["name"]]
        for key, col in FIGURES.items():
            assert f["qc"][key] == pytest.approx(row[col], rel=1e-12), (f["name"], key)
    # the flight rows include the taxi and turns: a mean interval would read a much lower rate
    assert all(f["qc"]["gravimeter_rate_hz"] == pytest.approx(18.24, rel=1e-3) for f in qc["flights"])

    lines = table[table["level"] == "line"].set_index("line")
    assert [l["line"] for l in qc["lines"]] == list(lines.index)
    for l in qc["lines"]:
        row = lines.loc[l["line"]]
        assert (l["flight"], l["kind"]) == (row["flight"], row["kind"])
        for key, col in FIGURES.items():
            assert l["qc"][key] == pytest.approx(row[col], rel=1e-12), (l["line"], key)
        assert l["qc"]["speed_ms"] == pytest.approx(1000 * row["length_km"] / row["duration_s"], rel=1e-12)
        assert np.isfinite(l["qc"]["mean_h_m"])
