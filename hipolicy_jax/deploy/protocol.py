"""The policy server's wire protocol: openpi's (``openpi-client``), so ``openpi_client.websocket_client_policy.
WebsocketClientPolicy`` and ``action_chunk_broker.ActionChunkBroker`` drive a HiPolicy server unchanged.

Frames are msgpack maps in openpi's msgpack-numpy encoding: an array is the map ``{b"__ndarray__": True, b"data":
bytes, b"dtype": str, b"shape": [..]}`` and a numpy scalar ``{b"__npgeneric__": True, b"data": value, b"dtype":
str}``; only numeric arrays (bool, int, uint, float) are accepted.

1. On connect the server sends one binary frame: the policy's manifest (``backend.make_metadata``) plus
   ``"server"``: the protocol, the reserved entries, the execution strategy, the key seed, batching settings.
2. Each client binary frame is ONE robot's observation: ``{key: array}``, the control-rate history
   ``(obs_span, ...)`` of every observation key the manifest lists (oldest first, the last frame current; pad an
   episode's start by repeating its first frame), plus optional reserved entries (``RESERVED``):

   - ``key``: uint32 array (2,), this decision's raw PRNG key (``jax.random.key_data``);
   - ``seed``: int in [0, 2**32), this decision's key is ``jax.random.key(seed)`` (raw ``(0, seed)``);
   - ``reset``: True on an episode's first observation: restarts the connection's decision count and execution
     memory (a new connection starts fresh too);
   - ``chunks``: True to also get all N samples at every frequency.

   Without ``key`` or ``seed`` (what an openpi client sends) the n-th decision of a connection (n = 0, 1, ... since
   it opened or since its last ``reset``) uses ``decision_key(server_seed, n)`` = ``fold_in(key(server_seed), n)``:
   an episode on a fresh connection draws the keys an in-process rollout draws from ``key(server_seed)``, so remote
   and in-process episodes are identical (``experiments.serve --seed``, default 0).
3. The reply (binary frame): ``actions`` (n, A) float32, the actions to execute one per control step: the served
   execution strategy applied to the decision (``chunk``: the selected stride's L_c actions, ``aac``: its first k*,
   ``te``: one ensembled action, ``delay`` d: L_c − d with the d committed ones first, the new chunk inpainted on
   them with ``handover='inpaint'``); ``stride``, ``freq_index`` (ints), ``entropy`` (float, NaN when N = 1),
   ``decision`` (n), ``server_timing`` ``{"infer_ms": the batched decision, "queue_ms": waiting for it, "batch":
   observations decided together}`` and, when asked, ``chunks`` (N, M·L_c, A).
4. A request the server cannot answer gets a TEXT frame with one line naming the problem (openpi's client raises
   on any text frame) and the connection stays open; an internal failure sends its line and closes the connection
   with 1011, as openpi does. ``GET /healthz`` answers 200 over HTTP.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import msgpack
import numpy as np

DEFAULT_MAX_MESSAGE_BYTES = 16 * 2**20
RESERVED = ("key", "seed", "reset", "chunks")
PROTOCOL = "openpi-msgpack-numpy"
_NUMERIC = "biuf"


class ProtocolError(ValueError):
    """A request the server cannot answer; the message is sent back as the error frame."""


def _encode(obj):
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in _NUMERIC:
            raise TypeError(f"cannot send an array of dtype {obj.dtype}")
        arr = np.ascontiguousarray(obj)
        return {b"__ndarray__": True, b"data": arr.tobytes(), b"dtype": arr.dtype.str, b"shape": list(arr.shape)}
    if isinstance(obj, np.generic):
        if obj.dtype.kind not in _NUMERIC:
            raise TypeError(f"cannot send a scalar of dtype {obj.dtype}")
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    raise TypeError(f"cannot send {type(obj).__name__}")


def _dtype(name) -> np.dtype:
    try:
        dtype = np.dtype(name.decode() if isinstance(name, bytes) else name)
    except Exception:  # noqa: BLE001 - anything np.dtype refuses
        raise ProtocolError(f"array payload: unknown dtype {name!r}") from None
    if dtype.kind not in _NUMERIC:
        raise ProtocolError(f"array payload: dtype {dtype} is not numeric (bool, int, uint or float)")
    return dtype


def _decode(obj: dict):
    if b"__ndarray__" in obj:
        dtype, shape, data = _dtype(obj.get(b"dtype")), obj.get(b"shape"), obj.get(b"data")
        if (not isinstance(shape, (list, tuple)) or len(shape) > 32
                or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)):
            raise ProtocolError(f"array payload: shape must be a list of non-negative ints, got {shape!r}")
        if not isinstance(data, bytes):
            raise ProtocolError(f"array payload: data must be bytes, got {type(data).__name__}")
        want = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if len(data) != want:
            raise ProtocolError(f"array payload: {len(data)} data bytes for shape {tuple(shape)} of {dtype} "
                                f"(expected {want})")
        return np.frombuffer(data, dtype).reshape(shape)
    if b"__npgeneric__" in obj:
        dtype = _dtype(obj.get(b"dtype"))
        try:
            return dtype.type(obj.get(b"data"))
        except Exception as e:  # noqa: BLE001
            raise ProtocolError(f"scalar payload: {obj.get(b'data')!r} is not a {dtype} ({e})") from None
    return obj


def pack(message: Any) -> bytes:
    """A message (maps, lists, numbers, strings, numpy arrays and scalars) → one msgpack frame, as openpi's
    ``msgpack_numpy.packb``."""
    return msgpack.packb(message, default=_encode, use_bin_type=True)


def unpack(data: bytes | str) -> Any:
    """A frame → the message (as openpi's ``msgpack_numpy.unpackb``); ``ProtocolError`` for a text frame or
    anything that is not one msgpack value."""
    if isinstance(data, str):
        raise ProtocolError("expected a binary msgpack frame, got a text frame")
    try:
        return msgpack.unpackb(data, object_hook=_decode, raw=False)
    except ProtocolError:
        raise
    except Exception as e:  # noqa: BLE001 - garbage bytes
        raise ProtocolError(f"frame is not a msgpack message ({type(e).__name__}: {e})") from None


def one_line(message: str, limit: int = 2000) -> str:
    """An error as the one line the server sends."""
    line = " ".join(str(message).split())
    return line if len(line) <= limit else line[:limit - 3] + "..."


class Request(NamedTuple):
    """One parsed observation frame: obs {key: (obs_span, ...)} in the manifest's dtypes, key_data (2,) uint32 or
    None (the connection's next default key), reset, chunks."""

    obs: dict[str, np.ndarray]
    key_data: np.ndarray | None
    reset: bool
    chunks: bool


def parse_request(message: Any, metadata: dict) -> Request:
    """Validate an observation frame against the manifest; ``ProtocolError`` naming the entry otherwise."""
    if not isinstance(message, dict):
        raise ProtocolError(f"expected a map of observation key to array, got {type(message).__name__}")
    spec = metadata["obs"]
    names = [k for k in message if k not in RESERVED]
    bad = [k for k in names if not isinstance(k, str)]
    if bad:
        raise ProtocolError(f"observation keys must be strings, got {bad[:3]!r}")
    unknown, missing = sorted(set(names) - set(spec)), sorted(set(spec) - set(names))
    if unknown or missing:
        raise ProtocolError(f"observation keys {sorted(names)} do not match the policy's {sorted(spec)} "
                            f"(unknown: {unknown}, missing: {missing}; reserved entries: {list(RESERVED)})")
    obs = {}
    for k, s in spec.items():
        x, want, dtype = message[k], tuple(s["shape"]), np.dtype(s["dtype"])
        if not isinstance(x, np.ndarray):
            raise ProtocolError(f"{k}: expected an array of shape {want}, got {type(x).__name__}")
        if x.shape != want:
            hint = " (one observation history per request)" if x.shape[1:] == want else ""
            raise ProtocolError(f"{k}: expected shape {want}, got {x.shape}{hint}")
        if dtype.kind == "f":
            if x.dtype.kind != "f":
                raise ProtocolError(f"{k}: expected floating values ({dtype}), got dtype {x.dtype}")
            if not np.all(np.isfinite(x)):
                raise ProtocolError(f"{k}: holds NaN or Inf")
        elif x.dtype != dtype:
            raise ProtocolError(f"{k}: expected dtype {dtype}, got {x.dtype}")
        obs[k] = x.astype(dtype, copy=False)
    return Request(obs, _key_data(message), _flag(message, "reset"), _flag(message, "chunks"))


def _flag(message: dict, name: str) -> bool:
    value = message.get(name, False)
    if not isinstance(value, (bool, np.bool_)):
        raise ProtocolError(f"{name}: expected true or false, got {value!r}")
    return bool(value)


def _key_data(message: dict) -> np.ndarray | None:
    if "key" in message and "seed" in message:
        raise ProtocolError("key, seed: pass at most one of them")
    if "key" in message:
        kd = message["key"]
        if not isinstance(kd, np.ndarray) or kd.dtype != np.uint32 or kd.shape != (2,):
            got = f"{kd.dtype} {kd.shape}" if isinstance(kd, np.ndarray) else type(kd).__name__
            raise ProtocolError(f"key: expected uint32 raw PRNG key data of shape (2,) (jax.random.key_data), "
                                f"got {got}")
        return kd
    if "seed" in message:
        seed = message["seed"]
        if isinstance(seed, np.integer):
            seed = int(seed)
        if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed < 2**32:
            raise ProtocolError(f"seed: expected an int in [0, 2**32), got {seed!r}")
        return seed_key_data(seed)
    return None


def seed_key_data(seed: int) -> np.ndarray:
    """Raw data of ``jax.random.key(seed)`` for a 32-bit seed: (0, seed)."""
    return np.array([0, seed], np.uint32)


def decision_key(seed: int, n: int) -> np.ndarray:
    """Raw data (2,) uint32 of the key of a connection's n-th decision when the client sends none:
    ``jax.random.key_data(jax.random.fold_in(jax.random.key(seed), n))``."""
    import jax

    return np.asarray(jax.random.key_data(jax.random.fold_in(jax.random.key(np.uint32(seed)), np.uint32(n))))


__all__ = ["DEFAULT_MAX_MESSAGE_BYTES", "PROTOCOL", "RESERVED", "ProtocolError", "Request", "decision_key",
           "one_line", "pack", "parse_request", "seed_key_data", "unpack"]
