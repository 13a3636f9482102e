"""Why a result file is missing: an identification (no line estimates yet) against a processed
result that has no grid (a test line), whose 404 gives the report's reason."""

import json
from types import SimpleNamespace

import pytest
from fastapi import HTTPException

from app.web.routers.results import _result_file

NO_GRID = ("gridding: the lines span less than two grid cells in one direction: no map to grid "
           "(grid files not written)")


def _detail(r, name):
    with pytest.raises(HTTPException) as ei:
        _result_file(r, name)
    assert ei.value.status_code == 404
    return ei.value.detail


def test_missing_grid_of_a_processed_result_gives_the_reports_reason(tmp_path):
    d = tmp_path / "r"
    (d / "identified").mkdir(parents=True)
    r = SimpleNamespace(dir=str(d))
    assert "is an identification" in _detail(r, "grid.nc")          # identify job: no lines yet
    (d / "lines.parquet").write_bytes(b"x")                           # a process job's result
    (d / "report.json").write_text(json.dumps({"warnings": ["other", NO_GRID]}))
    detail = _detail(r, "grid.nc")
    assert detail.startswith("this result has no grid: ") and "grid files not written" in detail
    (d / "report.json").write_text(json.dumps({"warnings": []}))
    assert _detail(r, "grid.nc") == "grid.nc is not among the stored results"
    assert _result_file(r, "lines.parquet") == d / "lines.parquet"
