"""Aerograv: adaptive processing of airborne gravimetry surveys.

Layers (data flows one way): ``app.io`` (files) → ``app.core`` (pure numerics)
→ ``app.pipeline`` (named stages of SPEC §2/§3) → ``app.cli`` / ``app.web``.
"""

__version__ = "0.1.0"
