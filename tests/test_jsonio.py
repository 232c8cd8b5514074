"""Strict JSON: NaN → null, ±∞ → strings read back as floats, NumPy values as plain numbers."""

import json
import math

import numpy as np

from hipolicy_jax import jsonio


def test_round_trip_and_strictness(tmp_path):
    obj = {"th": (-math.inf, np.float32(-1.5), math.inf), "nan": float("nan"), "n": np.int64(3), "b": np.bool_(True),
           "a": np.arange(3), "nested": [{"x": np.float64(0.25)}]}
    path = jsonio.dump(obj, str(tmp_path / "x.json"))
    text = open(path).read()
    json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(AssertionError(c)))  # no NaN / Infinity tokens
    back = jsonio.load(path)
    assert back == {"th": [-math.inf, -1.5, math.inf], "nan": None, "n": 3, "b": True, "a": [0, 1, 2],
                    "nested": [{"x": 0.25}]}
    assert jsonio.loads('{"t": [-Infinity, 1.0, Infinity]}') == {"t": [-math.inf, 1.0, math.inf]}  # older files
