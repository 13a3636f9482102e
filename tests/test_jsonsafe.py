"""app.jsonsafe: the one converter of numpy values and non-finite floats to JSON."""

import json
import math

import numpy as np
import pandas as pd
import pytest

from app.jsonsafe import dumps, finite_float, float_list, int_list, to_jsonable


def test_to_jsonable_numpy_pandas_nonfinite():
    obj = {"a": np.float64(np.nan), "b": [1.0, float("inf"), np.int64(3), np.bool_(True)], 3: np.arange(2.0),
           "df": pd.DataFrame({"u": [1.0, np.nan]}), "t": (np.float32(0.5), -np.inf)}
    assert to_jsonable(obj) == {"a": None, "b": [1.0, None, 3, True], "3": [0.0, 1.0],
                                "df": [{"u": 1.0}, {"u": None}], "t": [0.5, None]}
    with pytest.raises(TypeError):
        to_jsonable(object())


def test_dumps_is_strict_json():
    text = dumps({"x": [np.nan, 1.5, np.int32(2)], "y": float("-inf"), "z": np.arange(3)})
    assert json.loads(text) == {"x": [None, 1.5, 2], "y": None, "z": [0, 1, 2]}
    assert "NaN" not in text and "Infinity" not in text


def test_array_lists_and_scalars():
    assert float_list([1.23456, np.nan, np.inf], 2) == [1.23, None, None]
    assert float_list(np.array([0.5, 2.0])) == [0.5, 2.0]
    assert int_list(np.array([1.0, np.nan, 3.0])) == [1, None, 3]
    assert int_list(np.array([4, 5], dtype=np.int16)) == [4, 5]
    assert finite_float(np.float32(np.nan)) is None and finite_float(None) is None
    assert finite_float(2.71828, 2) == 2.72 and math.isclose(finite_float(np.float64(0.1)), 0.1)
