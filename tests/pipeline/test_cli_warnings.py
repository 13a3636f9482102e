"""The command line says the readers' warnings before the error that ends a failed run."""

import warnings

import app.pipeline.process as process
from app.cli import main


def test_warnings_before_a_failure_are_said_before_the_error(tmp_path, monkeypatch, capsys):
    def failing(survey_dir, out_dir, overrides=None, progress=None):
        warnings.warn("gnss.csv: lat and lon look like radians", stacklevel=2)
        warnings.warn("gnss.csv: lat and lon look like radians", stacklevel=2)   # said once
        raise ValueError("every line is too short for the regularization")

    monkeypatch.setattr(process, "process_survey", failing)
    (tmp_path / "s").mkdir()
    code = main(["process", str(tmp_path / "s"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2
    w = err.index("warning: gnss.csv: lat and lon look like radians")
    e = err.index("error: every line is too short for the regularization")
    assert w < e and err.count("look like radians") == 1, err
    assert not (tmp_path / "out").exists()          # nothing left behind by the failed run


def test_progress_bar_names_the_stage_after_the_bar(capsys):
    """The CLI's progress bar shows the stage (or the EM iteration) right after the bar, without
    tqdm's postfix comma ("| , ingest" before), and closes at "done"."""
    from app import cli

    progress = cli._progress_bar("process")
    progress("ingest", 0.05)
    progress("learning", 0.5, {"em_iteration": {"iteration": 3, "Q": [1e-5, 2e-4], "R": [1.0]}})
    progress("done", 1.0)
    err = capsys.readouterr().err.replace("\r", "\n")
    assert "| ingest" in err and "| , " not in err
    assert "| EM it 3 Q=[1e-05, 0.0002] R=[1]" in err
    assert "100%" in err
