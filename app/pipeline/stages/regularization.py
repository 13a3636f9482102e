"""Stage 4, regularization (SPEC §2 step 1): ∇^m, Kaiser low-pass, decimation to ~1 km and
the MA approximation of both components (anomaly and the coloured error of z), each
stretch of a line without missing epochs on its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.config import SurveyConfig
from app.core.ma_approx import fit_ma_model
from app.core.regularize import design_regularization, min_line_samples, regularize_line
from app.pipeline.stages.lines import LineData, finite_segments

#: finest decimation step (km) the regularization falls back to when every line is too short
#: for the configured one
MIN_FALLBACK_STEP_KM = 0.25


class LinesTooShort(ValueError):
    """No line is long enough for the regularization filter at the step tried."""


@dataclass
class Regularized:
    design: object                 # app.core.regularize.RegularizationDesign
    ma: object                     # app.core.ma_approx.MAModel
    lines: list                    # LineData used for identification
    x: list                        # decimated regularized sequences
    idx: list                      # full-rate indices (into the line) of each decimated point
    skipped: dict                  # line → reason
    note: str = ""                 # a fallback taken (finer decimation), for the report


def stretch_bounds(idx, n: int) -> list[tuple[int, int]]:
    """``(start, stop)`` in one line's decimated sequence of each stretch regularized on its own
    (:func:`_regularize_segments`): inside a stretch consecutive full-rate indices ``idx``
    differ by the decimation factor ``n``; a hole in z (and the filter's edges around it)
    makes a larger step."""
    idx = np.asarray(idx)
    cut = np.flatnonzero(np.diff(idx) != int(n)) + 1
    edges = np.r_[0, cut, idx.size]
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def split_stretches(reg: Regularized, arrays: list | None = None) -> tuple[list, list[int]]:
    """Per-line arrays (``reg.x`` when None; first axis along the line's decimated points)
    cut into their stretches (:func:`stretch_bounds`), in line order, and the index of the
    line each piece belongs to.  The EM and the recognition take each stretch as a sequence
    of its own: the window model's lags must not reach across a hole (joined, the points on
    both sides of each hole were taken for neighbours, and on a generated survey with a
    1.2 s gravimeter gap every 240 s the rough level of m = 2 came out 40× the level without
    the gaps)."""
    arrays = reg.x if arrays is None else arrays
    pieces, owner = [], []
    for w, (a, idx) in enumerate(zip(arrays, reg.idx)):
        for s, e in stretch_bounds(idx, reg.design.n):
            pieces.append(a[s:e])
            owner.append(w)
    return pieces, owner


def join_stretches(pieces: list, owner: list[int], n_lines: int) -> list:
    """The inverse of :func:`split_stretches`: each line's pieces joined in order."""
    out: list[list] = [[] for _ in range(n_lines)]
    for piece, w in zip(pieces, owner):
        out[w].append(np.asarray(piece))
    return [np.concatenate(o) for o in out]


def _regularize_segments(z_mgal, m: int, design):
    """Regularize each finite stretch of a line separately and join the results.

    A missing epoch of z cannot be filled: z is a difference of velocities, so its noise
    telescopes (Σ z over a window leaves only the velocity errors at the window's ends);
    any filled value leaves the neighbours' ±1000·r/Δt uncancelled — thousands of mGal in
    one sample, tens after the low-pass, which the EM reads as anomaly bursts."""
    need = min_line_samples(design, m)
    xs, idxs = [], []
    for a, b in finite_segments(z_mgal):
        if b - a >= need:
            x, idx = regularize_line(np.asarray(z_mgal[a:b], float), m, design)
            xs.append(x)
            idxs.append(idx + a)
    if not xs:
        n = int(np.isfinite(np.asarray(z_mgal, float)).sum())
        raise ValueError(f"line too short for regularization: no stretch without missing epochs has {need} "
                         f"samples ({n} finite of {len(z_mgal)})")
    return np.concatenate(xs), np.concatenate(idxs)


def regularize_lines(lines: list[LineData], cfg: SurveyConfig, dt_s: float, m: int, noise=None) -> Regularized:
    """∇^m, Kaiser low-pass, decimation and the MA approximation (SPEC §2 step 1), for the
    anomaly order ``m``; tie lines only with ``include_tie_lines``."""
    p = cfg.processing
    use = [ln for ln in lines if ln.kind != "tie" or p.include_tie_lines]
    if not use:
        raise ValueError("no lines to identify (all are tie lines and include_tie_lines is false)")
    speed = float(np.nanmedian([ln.speed_ms for ln in use]))
    step = float(p.decimation_step_km)
    try:
        return _regularize_at(use, p, dt_s, speed, step, m, noise)
    except LinesTooShort as first:
        # Lines shorter than the filter at ~1 km steps (a 12 km line at 100 m/s): a finer
        # step shortens the filter with it.  Only when the step is not set by n or a cut-off.
        if p.decimation_n is not None or p.cutoff_hz is not None:
            raise
        while step / 2.0 >= MIN_FALLBACK_STEP_KM:
            step /= 2.0
            try:
                reg = _regularize_at(use, p, dt_s, speed, step, m, noise)
            except LinesTooShort:
                continue
            reg.note = (f"every line is too short for the regularization at {p.decimation_step_km:g} km steps: "
                        f"decimated at {step:g} km instead (a shorter filter; more GNSS noise per point)")
            return reg
        raise first


def _regularize_at(use: list, p, dt_s: float, speed: float, step_km: float, m: int, noise) -> Regularized:
    design = design_regularization(dt_s, speed, step_km=step_km, n=p.decimation_n,
                                   cutoff_hz=p.cutoff_hz, attenuation_db=p.stopband_attenuation_db,
                                   difference_grid=p.regularization_difference_grid)
    ma = fit_ma_model(design, m, K=p.ma_order_K, L=p.ma_order_L,
                      noise=None if noise is None or noise.is_white_velocity else noise)
    kept, xs, idxs, skipped = [], [], [], {}
    for ln in use:
        try:
            x, idx = _regularize_segments(ln.z_mgal, m, design)
        except ValueError as exc:
            skipped[ln.line] = str(exc)
            continue
        if len(x) < ma.p + 3:
            skipped[ln.line] = f"only {len(x)} decimated points (need {ma.p + 3})"
            continue
        kept.append(ln)
        xs.append(np.asarray(x, float))
        idxs.append(np.asarray(idx, int))
    if not kept:
        raise LinesTooShort("every line is too short for the regularization filter: "
                         + "; ".join(f"{k}: {v}" for k, v in skipped.items()))
    return Regularized(design, ma, kept, xs, idxs, skipped)
