"""Strict JSON for every file the project writes, so that jq, browsers and other strict readers accept them.

Python's ``json`` writes ``NaN`` / ``Infinity``, which are not JSON. Here NaN is written as ``null`` and ±∞ as the
strings ``"Infinity"`` / ``"-Infinity"``, which ``load`` / ``loads`` turn back into floats (so thresholds such as
``[-inf, -1.2, -0.8, inf]`` survive a round trip); NumPy scalars and arrays become numbers and lists, tuples lists.
"""

from __future__ import annotations

import json
import math
import os
import re
from typing import Any

import numpy as np

INF, NEG_INF = "Infinity", "-Infinity"


def to_strict(obj: Any) -> Any:
    """``obj`` with NaN → None, ±∞ → "Infinity" / "-Infinity", NumPy values → Python ones, tuples → lists."""
    if isinstance(obj, dict):
        return {str(k): to_strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_strict(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_strict(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        if math.isnan(x):
            return None
        if math.isinf(x):
            return INF if x > 0 else NEG_INF
        return x
    return obj


def from_strict(obj: Any) -> Any:
    """Inverse of ``to_strict`` for ±∞: "Infinity" / "-Infinity" strings back to floats (NaN stays None)."""
    if isinstance(obj, dict):
        return {k: from_strict(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [from_strict(v) for v in obj]
    if obj == INF:
        return math.inf
    if obj == NEG_INF:
        return -math.inf
    return obj


def dumps(obj: Any, **kwargs) -> str:
    """Strict JSON text of ``obj`` (``json.dumps`` keywords pass through)."""
    return json.dumps(to_strict(obj), allow_nan=False, **kwargs)


_SCALAR = r'(?:-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?|true|false|null|"-?Infinity")'
_SCALAR_LIST = re.compile(r"\[\s*(" + _SCALAR + r"(?:,\s*" + _SCALAR + r")*)\s*\]")


def dump(obj: Any, path: str, indent: int | None = 2) -> str:
    """Write ``obj`` as strict JSON to ``path`` (creating its directory), indented, with lists of numbers on one
    line (per-episode outcomes stay small in git); → the path."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    text = dumps(obj, indent=indent)
    if indent is not None:
        text = _SCALAR_LIST.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)
    with open(path, "w") as f:
        f.write(text + "\n")
    return path


def loads(text: str) -> Any:
    """Parse JSON (strict, or older files with bare NaN / Infinity) with ±∞ strings back to floats."""
    return from_strict(json.loads(text))


def load(path: str) -> Any:
    with open(path) as f:
        return loads(f.read())


__all__ = ["INF", "NEG_INF", "dump", "dumps", "from_strict", "load", "loads", "to_strict"]
