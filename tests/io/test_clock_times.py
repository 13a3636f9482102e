"""Times written as clock strings (hh:mm:ss) are refused with the reason, naming row and column."""

from __future__ import annotations

import pytest

from app.io.errors import InputError
from app.io.survey import read_survey
from tests.io.test_io_survey import make_tables, write_survey


@pytest.mark.parametrize("cell", ["4:01:40", "04:01:40.5", "23:59"])
def test_clock_time_in_lines_csv(tmp_path, cell):
    lines, tabs = make_tables()
    lines = lines.astype({"t_start": object})
    lines.loc[1, "t_start"] = cell
    root = write_survey(tmp_path / "s", lines, tabs)
    with pytest.raises(InputError) as exc:
        read_survey(root)
    e = exc.value
    assert (e.file, e.row, e.column) == ("lines.csv", 3, "t_start")
    assert e.message.startswith(f"not a number: {cell!r} — a clock time (hh:mm:ss)")


def test_other_text_keeps_the_plain_message(tmp_path):
    lines, tabs = make_tables()
    lines = lines.astype({"t_start": object})
    lines.loc[1, "t_start"] = "abc"
    with pytest.raises(InputError) as exc:
        read_survey(write_survey(tmp_path / "s", lines, tabs))
    assert exc.value.message == "not a number: 'abc'"
