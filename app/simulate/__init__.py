"""Survey simulator (test bed): writes a SPEC §4 survey directory plus ``truth/``."""

from app.simulate.presets import PRESETS, SimConfig
from app.simulate.run import simulate_survey

__all__ = ["simulate_survey", "PRESETS", "SimConfig"]
