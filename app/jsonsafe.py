"""JSON-safe values: the one converter of numpy/pandas values and non-finite floats to plain JSON.

JSON has no NaN or infinity: every non-finite float becomes ``null``.  numpy scalars and arrays,
pandas frames and series, dataclasses, paths, dates and pydantic models become their plain JSON
counterparts.  Used by :mod:`app.io.export` (``report.json``, ``identification.json``), the
pipeline and the web layer (job reports, EM tables, survey QC, result arrays), so a value reads
the same in a file and in the browser.  Depends on the standard library and numpy only (pandas
lazily), so every layer above :mod:`app.core` may import it.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
from pathlib import Path

import numpy as np

__all__ = ["dumps", "finite_float", "finite_tree", "float_list", "int_list", "to_jsonable"]


def to_jsonable(obj):
    """Convert numpy/pandas/dataclass/Path values into plain JSON types.

    Non-finite floats become ``None`` (JSON has no NaN).  Raises TypeError for
    anything else it cannot convert.
    """
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, np.integer)) and not isinstance(obj, np.bool_):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return [to_jsonable(v) for v in obj.tolist()] if obj.ndim else to_jsonable(obj.item())
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, (_dt.datetime, _dt.date)):
        return obj.isoformat()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_jsonable(dataclasses.asdict(obj))
    try:
        import pandas as pd

        if isinstance(obj, pd.DataFrame):
            return to_jsonable(obj.to_dict(orient="records"))
        if isinstance(obj, pd.Series):
            return to_jsonable(obj.tolist())
        if isinstance(obj, pd.Timestamp):
            return obj.isoformat()
    except ImportError:  # pragma: no cover
        pass
    if hasattr(obj, "model_dump"):  # pydantic
        return to_jsonable(obj.model_dump())
    raise TypeError(f"cannot write {type(obj).__name__} to JSON")


def finite_tree(obj):
    """Non-finite Python floats in nested dicts/lists/tuples → None (string keys), leaving every
    other value as it is: the pass before :class:`json.JSONEncoder` with ``default=to_jsonable``,
    whose ``default`` never sees a float."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k if isinstance(k, str) else str(k): finite_tree(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_tree(v) for v in obj]
    return obj


def encoder(indent: int | None = None, separators: tuple[str, str] | None = None) -> json.JSONEncoder:
    """A strict encoder (``allow_nan=False``) converting what json cannot by :func:`to_jsonable`;
    feed it ``finite_tree(obj)``."""
    return json.JSONEncoder(indent=indent, separators=separators, allow_nan=False, ensure_ascii=False,
                            default=to_jsonable)


def dumps(obj, indent: int | None = None) -> str:
    """``obj`` as strict JSON text (NaN/±inf → null, numpy values converted)."""
    return encoder(indent).encode(finite_tree(obj))


def float_list(a, nd: int | None = None) -> list:
    """Array → list of floats, rounded to ``nd`` decimals (when given), NaN/±inf → None."""
    a = np.asarray(a, dtype=float)
    r = np.round(a, nd) if nd is not None else a
    ok = np.isfinite(r)
    if ok.all():
        return r.tolist()
    out = r.astype(object)
    out[~ok] = None
    return out.tolist()


def int_list(a) -> list:
    """Array → list of ints; NaN/±inf in a float array → None."""
    a = np.asarray(a)
    if a.dtype.kind == "f":
        ok = np.isfinite(a)
        out = np.where(ok, a, -1).astype(int).astype(object)
        out[~ok] = None
        return out.tolist()
    return a.astype(int).tolist()


def finite_float(x, nd: int | None = None) -> float | None:
    """A number as a float (rounded to ``nd`` decimals when given), None when missing or non-finite."""
    if x is None:
        return None
    f = float(x)
    if not math.isfinite(f):
        return None
    return round(f, nd) if nd is not None else f
