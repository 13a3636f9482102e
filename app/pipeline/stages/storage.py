"""Store and load a stage's result: a tree of dataclasses, arrays, tables and plain values.

A later stage can start from a stored earlier one (the web's ``filter`` job starts from a
stored identification).  The format is data, not code: ``state.json`` holds the tree with
every array replaced by a key into ``arrays.npz`` (loaded with ``allow_pickle=False``) and
every DataFrame by a key into ``frames/<key>.parquet``; dataclasses are rebuilt only from
an allow-list of modules (this package, ``app.pipeline.runs`` and ``app.core``), so a stored file cannot name
arbitrary code.

Supported values: None, bool, int, float (non-finite included), str, list, tuple, dict with
string keys, ``slice``, numpy arrays and scalars, ``pandas.DataFrame``,
``types.SimpleNamespace`` and dataclass instances whose fields are supported values.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd

_ALLOWED_PREFIXES = ("app.pipeline.stages", "app.pipeline.runs", "app.core")
FORMAT = "aerograv-stage/1"


class _Writer:
    def __init__(self):
        self.arrays: dict[str, np.ndarray] = {}
        self.frames: dict[str, pd.DataFrame] = {}

    def encode(self, v):
        if v is None or isinstance(v, (bool, str)):
            return v
        if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
            return int(v)
        if isinstance(v, (float, np.floating)):
            v = float(v)
            return v if math.isfinite(v) else {"__float__": repr(v)}
        if isinstance(v, np.bool_):
            return bool(v)
        if isinstance(v, np.ndarray):
            if v.dtype == object:
                return {"__list_array__": [self.encode(x) for x in v.tolist()]}
            key = f"a{len(self.arrays)}"
            self.arrays[key] = v
            return {"__array__": key}
        if isinstance(v, pd.DataFrame):
            key = f"f{len(self.frames)}"
            self.frames[key] = v
            return {"__frame__": key}
        if isinstance(v, slice):
            return {"__slice__": [v.start, v.stop, v.step]}
        if isinstance(v, tuple):
            return {"__tuple__": [self.encode(x) for x in v]}
        if isinstance(v, list):
            return [self.encode(x) for x in v]
        if isinstance(v, dict):
            if not all(isinstance(k, str) for k in v):
                return {"__items__": [[self.encode(k), self.encode(x)] for k, x in v.items()]}
            return {"__dict__": {k: self.encode(x) for k, x in v.items()}}
        if isinstance(v, SimpleNamespace):
            return {"__namespace__": {k: self.encode(x) for k, x in vars(v).items()}}
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            cls = type(v)
            if not cls.__module__.startswith(_ALLOWED_PREFIXES):
                raise TypeError(f"cannot store a {cls.__module__}.{cls.__qualname__}")
            fields = {f.name: self.encode(getattr(v, f.name)) for f in dataclasses.fields(v)}
            extra = {k: self.encode(x) for k, x in vars(v).items()
                     if k not in fields} if hasattr(v, "__dict__") else {}
            return {"__dataclass__": f"{cls.__module__}:{cls.__qualname__}", "fields": fields, "extra": extra}
        raise TypeError(f"cannot store a value of type {type(v).__name__}")


class _Reader:
    def __init__(self, arrays, frames_dir: Path):
        self.arrays = arrays
        self.frames_dir = frames_dir

    def decode(self, v):
        if isinstance(v, list):
            return [self.decode(x) for x in v]
        if not isinstance(v, dict):
            return v
        if "__float__" in v:
            return float(v["__float__"])
        if "__array__" in v:
            return np.array(self.arrays[v["__array__"]])
        if "__list_array__" in v:
            out = np.empty(len(v["__list_array__"]), dtype=object)
            out[:] = [self.decode(x) for x in v["__list_array__"]]
            return out
        if "__frame__" in v:
            key = str(v["__frame__"])
            if not key.isalnum():
                raise ValueError(f"bad frame key {key!r}")
            return pd.read_parquet(self.frames_dir / f"{key}.parquet")
        if "__slice__" in v:
            return slice(*v["__slice__"])
        if "__tuple__" in v:
            return tuple(self.decode(x) for x in v["__tuple__"])
        if "__items__" in v:
            return {self.decode(k): self.decode(x) for k, x in v["__items__"]}
        if "__dict__" in v:
            return {k: self.decode(x) for k, x in v["__dict__"].items()}
        if "__namespace__" in v:
            return SimpleNamespace(**{k: self.decode(x) for k, x in v["__namespace__"].items()})
        if "__dataclass__" in v:
            mod, _, name = v["__dataclass__"].partition(":")
            if not mod.startswith(_ALLOWED_PREFIXES) or not name.isidentifier():
                raise ValueError(f"stored stage names a class outside the allowed modules: {v['__dataclass__']!r}")
            cls = getattr(importlib.import_module(mod), name)
            if not dataclasses.is_dataclass(cls):
                raise ValueError(f"{v['__dataclass__']} is not a dataclass")
            fields = {k: self.decode(x) for k, x in v["fields"].items()}
            init = {f.name: fields[f.name] for f in dataclasses.fields(cls) if f.init and f.name in fields}
            obj = cls(**init)
            for f in dataclasses.fields(cls):
                if not f.init and f.name in fields:
                    object.__setattr__(obj, f.name, fields[f.name])
            for k, x in v.get("extra", {}).items():
                object.__setattr__(obj, k, self.decode(x))
            return obj
        raise ValueError(f"unknown stored value {list(v)[:3]}")


def save(obj, path) -> Path:
    """Store ``obj`` in the directory ``path`` (replaced atomically when it exists)."""
    path = Path(path)
    w = _Writer()
    tree = {"format": FORMAT, "value": w.encode(obj)}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        (tmp / "state.json").write_text(json.dumps(tree), encoding="utf-8")
        np.savez(tmp / "arrays.npz", **w.arrays)
        if w.frames:
            (tmp / "frames").mkdir()
            for k, df in w.frames.items():
                df.to_parquet(tmp / "frames" / f"{k}.parquet", index=False)
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            if old.exists():
                shutil.rmtree(old)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def load(path):
    """The object stored by :func:`save` in the directory ``path``."""
    path = Path(path)
    tree = json.loads((path / "state.json").read_text(encoding="utf-8"))
    if tree.get("format") != FORMAT:
        raise ValueError(f"{path}: not a stored stage result (format {tree.get('format')!r})")
    with np.load(path / "arrays.npz", allow_pickle=False) as arrays:
        return _Reader({k: arrays[k] for k in arrays.files}, path / "frames").decode(tree["value"])
