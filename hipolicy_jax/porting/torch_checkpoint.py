"""Read PyTorch checkpoints without torch: ``.ckpt`` / ``.pt`` (torch's zip format) and ``safetensors`` files.

A ``.ckpt`` written by ``torch.save`` is a zip archive: ``<root>/data.pkl`` (a pickle whose tensors are persistent
references to storages) and one raw little-endian file per storage, ``<root>/data/<key>``. ``read_torch_file``
unpickles ``data.pkl`` with an **allow-list**: tensor and storage rebuilding, ``OrderedDict`` / ``defaultdict``,
and the plain-data classes of OmegaConf configs (read as stubs, turned into plain dicts and lists by
``plain_config``). Any other global in the pickle raises ``ValueError`` naming it: unlike
``torch.load(weights_only=False)``, reading a checkpoint never runs code from it. So a Diffusion Policy workspace
checkpoint (``{'cfg': DictConfig, 'state_dicts': {'model', 'ema_model', 'optimizer'}, 'pickles': {...}}``) reads
with numpy alone; its tensors come back as ``np.ndarray`` (bfloat16 as ``ml_dtypes.bfloat16``).

The config is returned as written, with OmegaConf interpolations unresolved; ``resolve_config`` resolves the plain
references (``${horizon}``, ``${task.obs_dim}``) and Diffusion Policy's ``${eval:...}`` arithmetic through a
restricted expression evaluator (numbers, booleans, None, + - * / // %, comparisons, ``and`` / ``or`` / ``not``,
``a if c else b``; nothing else), again without running code from the file.
"""

from __future__ import annotations

import ast
import operator
import os
import pickle
import re
import zipfile
from collections import OrderedDict, defaultdict
from typing import Any

import numpy as np

_STORAGE_DTYPES = {
    "FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16, "LongStorage": np.int64,
    "IntStorage": np.int32, "ShortStorage": np.int16, "CharStorage": np.int8, "ByteStorage": np.uint8,
    "BoolStorage": np.bool_, "BFloat16Storage": "bfloat16",
}
_TYPES = {"dict": dict, "list": list, "tuple": tuple, "set": set, "frozenset": frozenset, "str": str, "int": int,
          "float": float, "bool": bool, "bytes": bytes, "NoneType": type(None)}


class _StorageType:
    """What the pickle names as ``torch.<X>Storage``: carries the element dtype."""

    def __init__(self, name: str):
        dtype = _STORAGE_DTYPES[name]
        if dtype == "bfloat16":
            import ml_dtypes

            dtype = ml_dtypes.bfloat16
        self.name, self.dtype = name, np.dtype(dtype)


class ConfigNode:
    """An OmegaConf object (``DictConfig``, ``ListConfig``, a value node, metadata) read as plain state."""

    def __init__(self, *args, **kwargs):
        self.state: Any = None

    def __setstate__(self, state):
        self.state = state


def _rebuild_tensor(storage: np.ndarray, offset: int, size, stride, *rest) -> np.ndarray:
    size, stride = tuple(int(s) for s in size), tuple(int(s) for s in stride)
    if not size:
        return storage[offset].copy()
    end = offset + sum((n - 1) * s for n, s in zip(size, stride)) + 1
    if min(size) > 0 and end > storage.shape[0]:
        raise ValueError(f"a tensor of shape {size} at offset {offset} runs past its storage ({storage.shape[0]})")
    view = np.lib.stride_tricks.as_strided(storage[offset:], size, [s * storage.itemsize for s in stride])
    return np.array(view)  # a contiguous copy, independent of the archive


def _rebuild_parameter(data, requires_grad=None, backward_hooks=None, *rest):
    return data


def _load_type(name: str):
    if name not in _TYPES:
        raise ValueError(f"the pickle asks for the type {name!r} (dill), which this reader does not load")
    return _TYPES[name]


_ALLOWED = {
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_tensor"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("collections", "OrderedDict"): OrderedDict,
    ("collections", "defaultdict"): defaultdict,
    ("builtins", "set"): set, ("builtins", "frozenset"): frozenset, ("builtins", "dict"): dict,
    ("builtins", "list"): list, ("builtins", "tuple"): tuple, ("builtins", "slice"): slice,
    ("dill._dill", "_load_type"): _load_type,
    ("typing", "Any"): Any,
}


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, archive: zipfile.ZipFile, root: str, path: str):
        super().__init__(file)
        self.archive, self.root, self.path, self.storages = archive, root, path, {}

    def find_class(self, module: str, name: str):
        if (module, name) in _ALLOWED:
            return _ALLOWED[(module, name)]
        if module == "torch" and name in _STORAGE_DTYPES:
            return _StorageType(name)
        if module == "_codecs" and name == "encode":
            return lambda text, encoding="latin1": text.encode(encoding)
        if module.startswith("omegaconf.") or module == "omegaconf":
            return type(name, (ConfigNode,), {})
        raise ValueError(f"checkpoint: {self.path} refers to {module}.{name}, which this reader does not load (it "
                         f"reads tensors, dicts and OmegaConf configs, and never runs code from a checkpoint)")

    def persistent_load(self, pid):
        if not (isinstance(pid, tuple) and pid and pid[0] == "storage"):
            raise ValueError(f"checkpoint: {self.path} holds a persistent reference {pid!r:.80} that is not a storage")
        _, storage_type, key, _location, numel = pid[:5]
        if not isinstance(storage_type, _StorageType):
            raise ValueError(f"checkpoint: {self.path} holds a storage of unknown type {storage_type!r}")
        if key not in self.storages:
            raw = self.archive.read(f"{self.root}/data/{key}")
            self.storages[key] = np.frombuffer(raw, dtype=storage_type.dtype.newbyteorder("<"), count=int(numel))
        return self.storages[key]


def read_torch_file(path: str) -> Any:
    """Unpickle a ``torch.save`` zip archive (``.ckpt``, ``.pt``, ``.pth``) with numpy tensors; see the module
    docstring. Raises ``FileNotFoundError`` or ``ValueError`` naming the path."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"checkpoint: {path} does not exist")
    if not zipfile.is_zipfile(path):
        raise ValueError(f"checkpoint: {path} is not a torch zip archive (written by torch.save since torch 1.6); "
                         f"re-save it with a current torch, or pass a safetensors file")
    with zipfile.ZipFile(path) as archive:
        pkls = [n for n in archive.namelist() if n.endswith("/data.pkl") and n.count("/") == 1]
        if len(pkls) != 1:
            raise ValueError(f"checkpoint: {path} has {len(pkls)} data.pkl entries at its top level, expected one")
        root = pkls[0].split("/", 1)[0]
        order = [n for n in archive.namelist() if n == f"{root}/byteorder"]
        if order and archive.read(order[0]).decode().strip() != "little":
            raise ValueError(f"checkpoint: {path} was written big-endian; re-save it on a little-endian machine")
        with archive.open(pkls[0]) as f:
            try:
                return _Unpickler(f, archive, root, path).load()
            except (pickle.UnpicklingError, EOFError, KeyError) as e:
                raise ValueError(f"checkpoint: {path} is damaged or not a torch checkpoint "
                                 f"({type(e).__name__}: {e})") from e


def read_safetensors(path: str) -> dict[str, np.ndarray]:
    """``{name: np.ndarray}`` of a ``safetensors`` file (no torch needed)."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"checkpoint: {path} does not exist")
    from safetensors.numpy import load_file

    try:
        return dict(load_file(path))
    except Exception as e:  # noqa: BLE001 - the library's own error types vary by version
        raise ValueError(f"checkpoint: {path} is not a readable safetensors file ({type(e).__name__}: {e})") from e


def plain_config(node: Any) -> Any:
    """An OmegaConf object read by ``read_torch_file`` as plain dicts, lists and values (interpolations as the
    strings they are written as; ``'???'`` for missing values)."""
    if isinstance(node, ConfigNode):
        state = node.state if isinstance(node.state, dict) else {}
        if "_content" in state:
            return plain_config(state["_content"])
        if "_val" in state:
            return plain_config(state["_val"])
        return None
    if isinstance(node, dict):
        return {k: plain_config(v) for k, v in node.items()}
    if isinstance(node, (list, tuple)):
        return [plain_config(v) for v in node]
    return node


_BINOPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul, ast.Div: operator.truediv,
           ast.FloorDiv: operator.floordiv, ast.Mod: operator.mod}
_CMPOPS = {ast.Eq: operator.eq, ast.NotEq: operator.ne, ast.Lt: operator.lt, ast.LtE: operator.le,
           ast.Gt: operator.gt, ast.GtE: operator.ge, ast.Is: operator.is_, ast.IsNot: operator.is_not}


def safe_eval(expr: str) -> Any:
    """Evaluate arithmetic / boolean / conditional expressions over literals (see the module docstring); anything
    else (names, calls, attributes, subscripts) raises ``ValueError``."""
    def ev(n):
        if isinstance(n, ast.Expression):
            return ev(n.body)
        if isinstance(n, ast.Constant) and isinstance(n.value, (int, float, str, bool, type(None))):
            return n.value
        if isinstance(n, ast.BinOp) and type(n.op) in _BINOPS:
            return _BINOPS[type(n.op)](ev(n.left), ev(n.right))
        if isinstance(n, ast.UnaryOp) and isinstance(n.op, (ast.USub, ast.UAdd, ast.Not)):
            v = ev(n.operand)
            return -v if isinstance(n.op, ast.USub) else (+v if isinstance(n.op, ast.UAdd) else not v)
        if isinstance(n, ast.BoolOp):
            vals = [ev(v) for v in n.values]
            return all(vals) if isinstance(n.op, ast.And) else any(vals)
        if isinstance(n, ast.IfExp):
            return ev(n.body) if ev(n.test) else ev(n.orelse)
        if isinstance(n, ast.Compare) and all(type(o) in _CMPOPS for o in n.ops):
            left = ev(n.left)
            for op, right in zip(n.ops, n.comparators):
                r = ev(right)
                if not _CMPOPS[type(op)](left, r):
                    return False
                left = r
            return True
        raise ValueError(f"config: the expression {expr!r} uses {type(n).__name__}, which is not evaluated here")

    try:
        return ev(ast.parse(expr.strip(), mode="eval"))
    except SyntaxError as e:
        raise ValueError(f"config: cannot parse the expression {expr!r}") from e


_UNRESOLVED = object()


def resolve_config(cfg: dict) -> dict:
    """``cfg`` (``plain_config``'s form) with its interpolations resolved: ``${a.b}`` references and ``${eval:...}``
    expressions; other resolvers (``${now:...}``) are left as written."""
    def lookup(path: str, seen: tuple[str, ...]):
        node: Any = cfg
        for part in path.split("."):
            if isinstance(node, dict) and part in node:
                node = node[part]
            elif isinstance(node, list) and part.isdigit() and int(part) < len(node):
                node = node[int(part)]
            else:
                raise ValueError(f"config: ${{{path}}} refers to a key that does not exist")
        if path in seen:
            raise ValueError(f"config: ${{{path}}} refers to itself ({' -> '.join(seen)})")
        return resolve(node, seen + (path,))

    def interpolate(text: str, seen: tuple[str, ...], quote: bool = False):
        """``text`` with its ``${...}`` replaced; a text that is one interpolation gives the value itself. ``quote``:
        strings substituted as Python literals (inside an ``eval`` expression)."""
        out, i, whole = [], 0, _UNRESOLVED
        while i < len(text):
            j = text.find("${", i)
            if j < 0:
                out.append(text[i:])
                break
            out.append(text[i:j])
            depth, k = 0, j
            while k < len(text):
                if text.startswith("${", k):
                    depth, k = depth + 1, k + 2
                    continue
                if text[k] == "}":
                    depth -= 1
                    if depth == 0:
                        break
                k += 1
            if depth:
                raise ValueError(f"config: unbalanced interpolation in {text!r}")
            inner = text[j + 2:k]
            head = re.match(r"\s*([A-Za-z_][\w]*)\s*:", inner)
            if head and head.group(1) == "eval":
                expr = inner[head.end():].strip()
                try:  # ${eval:'...'}: OmegaConf hands the resolver the quoted string's content
                    body = ast.parse(expr, mode="eval").body
                    expr = body.value if isinstance(body, ast.Constant) and isinstance(body.value, str) else expr
                except SyntaxError:
                    pass  # interpolations inside: parsed after substitution
                value = safe_eval(str(interpolate(expr, seen, quote=True)))
            elif head:
                value = _UNRESOLVED
            else:
                value = lookup(inner.strip(), seen)
            if value is _UNRESOLVED:
                out.append(text[j:k + 1])
            else:
                whole = value if (j == 0 and k == len(text) - 1) else _UNRESOLVED
                out.append(repr(value) if quote and isinstance(value, str) else str(value))
            i = k + 1
        return whole if whole is not _UNRESOLVED else "".join(out)

    def resolve(node, seen=()):
        if isinstance(node, dict):
            return {k: resolve(v, seen) for k, v in node.items()}
        if isinstance(node, list):
            return [resolve(v, seen) for v in node]
        if isinstance(node, str) and "${" in node:
            return interpolate(node, seen)
        return node

    return resolve(cfg)


__all__ = ["ConfigNode", "plain_config", "read_safetensors", "read_torch_file", "resolve_config", "safe_eval"]
