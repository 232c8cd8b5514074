"""Strict JSON for every file the project writes, so that jq, browsers and other strict readers accept them.

Python's ``json`` writes ``NaN`` / ``Infinity``, which are not JSON. Here NaN is written as ``null`` and ±∞ as the
strings ``"Infinity"`` / ``"-Infinity"``, which ``load`` / ``loads`` turn back into floats (so thresholds such as
``[-inf, -1.2, -0.8, inf]`` survive a round trip); NumPy scalars and arrays become numbers and lists, tuples lists.

A stored file that does not read back (``load`` of a truncated or garbled JSON file, ``ReplayBuffer.load`` of a
damaged zarr buffer) raises ``DamagedFileError``: one line naming the file, what is wrong with it and what to do; a
campaign skips the run it belongs to and lists it at the end.
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
    line (per-episode outcomes stay small in git); → the path. Written to a temporary sibling renamed into place, so
    a reader never sees half a file."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    text = dumps(obj, indent=indent)
    if indent is not None:
        text = _SCALAR_LIST.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)
    partial = f"{path}.partial-{os.getpid()}"  # renamed into place: a write cut off never leaves half a file
    with open(partial, "w") as f:
        f.write(text + "\n")
    os.replace(partial, path)
    return path


def loads(text: str) -> Any:
    """Parse JSON (strict, or older files with bare NaN / Infinity) with ±∞ strings back to floats."""
    return from_strict(json.loads(text))


class DamagedFileError(ValueError):
    """A stored file that does not read back as it was written; the message is one line: ``<path>: <what is wrong>;
    <what to do>``. ``path``, ``problem`` and ``hint`` keep its parts (``with_hint`` swaps the advice)."""

    def __init__(self, path: str, problem: str, hint: str = ""):
        self.path = str(path)
        self.problem, self.hint = (" ".join(str(t).split()) for t in (problem, hint))  # one line, however long
        super().__init__(f"{self.path}: {self.problem}" + (f"; {self.hint}" if self.hint else ""))

    def with_hint(self, hint: str) -> DamagedFileError:
        """The same damage with other advice (a caller knows better how that file is made again)."""
        new = type(self).__new__(type(self))
        DamagedFileError.__init__(new, self.path, self.problem, hint)
        return new


def one_line(text: str, limit: int = 200) -> str:
    """``text``'s first non-empty line, at most ``limit`` characters (an error message quoted inside another)."""
    line = next((ln.strip() for ln in str(text).splitlines() if ln.strip()), "")
    return line if len(line) <= limit else line[:limit - 1] + "…"


def restore_hint(path: str, redo: str = "delete it so that it is made again") -> str:
    """The advice for a damaged file the project wrote: restore it from git when it is tracked, else ``redo``."""
    return f"restore it from git (git checkout -- {path}) or {redo}"


def load(path: str, hint: str | None = None) -> Any:
    """The JSON file at ``path`` (``loads``). A file that is not UTF-8 text or not valid JSON (truncated, garbled)
    raises ``DamagedFileError`` naming the path, the line and column and ``hint`` (default: ``restore_hint``)."""
    with open(path, "rb") as f:
        raw = f.read()
    hint = restore_hint(path) if hint is None else hint
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise DamagedFileError(path, f"not UTF-8 text (byte 0x{raw[e.start]:02x} at offset {e.start})",
                               hint) from None
    try:
        return loads(text)
    except json.JSONDecodeError as e:
        where = "it is empty" if not text.strip() else f"{e.msg}: line {e.lineno}, column {e.colno}"
        raise DamagedFileError(path, f"not valid JSON ({where})", hint) from None


__all__ = ["INF", "NEG_INF", "DamagedFileError", "dump", "dumps", "from_strict", "load", "loads", "one_line",
           "restore_hint", "to_strict"]
