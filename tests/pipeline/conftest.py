import pytest


@pytest.fixture(scope="session")
def tiny_survey(tmp_path_factory):
    """The simulator's `tiny` preset (4 main + 2 tie lines of 30 km), written once per session."""
    from app.simulate import simulate_survey

    return simulate_survey("tiny", tmp_path_factory.mktemp("tiny") / "survey", seed=3)


@pytest.fixture(scope="session")
def tiny_processed(tiny_survey, tmp_path_factory):
    """`aerograv process` outputs of the tiny survey, and the progress events it emitted."""
    from app.pipeline.process import process_survey

    out = tmp_path_factory.mktemp("tiny_out")
    events = []
    report = process_survey(tiny_survey, out, progress=lambda s, f, i: events.append((s, f, i)))
    return out, report, events


@pytest.fixture(scope="session")
def foreign_sim():
    """``benchmarks/foreign_sim.py``: the survey generator written without ``app.simulate``."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "foreign_sim.py"
    spec = importlib.util.spec_from_file_location("foreign_sim", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
