"""Survey simulator (test bed): writes a SPEC §4 survey directory plus ``truth/``."""

from app.simulate.presets import PRESET_NOTES, PRESETS, SimConfig

__all__ = ["simulate_survey", "PRESETS", "PRESET_NOTES", "SimConfig"]


def __getattr__(name):  # the simulator itself is imported on first use (the CLI only needs the presets)
    if name == "simulate_survey":
        from app.simulate.run import simulate_survey
        return simulate_survey
    raise AttributeError(f"module 'app.simulate' has no attribute {name!r}")
