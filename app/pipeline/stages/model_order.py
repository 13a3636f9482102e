"""Order m of the anomaly model ∇^m δg = q.

SPEC §2 leaves m to the analyst (default 2).  :func:`candidate_orders` says which orders
are identified; the choice between them is made on their outputs
(:mod:`app.pipeline.stages.choice`).  :func:`choose_model_order` is the full-rate
likelihood alternative (``model_order = 'likelihood'``).
"""

from __future__ import annotations

from app.core.level_ml import select_order
from app.core.noise_level import local_noise_variance_cm2s2
from app.pipeline.stages.lines import LineData


def choose_model_order(lines: list[LineData], dt_s: float, noise=None, r_local: dict | None = None):
    """Order m of the anomaly model by the full-rate likelihood of the main lines (SPEC §2
    leaves m to the analyst; seed 000 notes: choose it by likelihood)."""
    use = [ln for ln in lines if ln.kind != "tie" and ln.z_mgal.size >= 100] or lines
    zl = [ln.z_mgal for ln in use]
    if r_local:
        rl = [r_local[ln.flight][ln.sl] for ln in use]
    else:
        rl = [local_noise_variance_cm2s2(z, dt_s) for z in zl]
    return select_order(zl, rl, dt_s, noise=noise)


def candidate_orders(p, n_crossovers: int) -> list[int]:
    """The orders m to identify: ``processing.m`` when set (and ``recognition_order`` for its
    state map); otherwise 1 and 2 — the crossovers choose between them when there are at least
    ``choice_min_crossovers`` (:mod:`app.pipeline.stages.choice`), else m = 2 (SPEC's
    default) filters with m = 1's state map."""
    if p.m is not None:
        extra = [p.recognition_order] if p.recognition_order not in (None, p.m) else []
        return sorted({int(p.m), *extra})
    return [1, 2]
