"""The policy server's messages: msgpack maps, numpy arrays as msgpack extension type 1, one binary websocket frame
per message.

Requests (``type`` names the kind; an optional ``id`` is echoed in the reply):

- ``{"type": "infer", "obs": {key: array}, "key": uint32 array, "chunks": bool}``: ``obs`` is the observation
  history of every key the policy reads, ``(obs_span, ...)`` for one robot or ``(B, obs_span, ...)`` for B;
  ``key`` one raw PRNG key ``(2,)`` / ``(B, 2)`` (``jax.random.key_data``) or ``seed``, an int, instead; ``chunks``
  asks for all N samples too. Reply ``{"type": "result", "actions", "stride", "freq_index", "entropy"[, "chunks"],
  "server_ms"}``, arrays without the batch axis when the request had none.
- ``{"type": "metadata"}``: reply ``{"type": "metadata", "metadata": manifest}`` (``backend.make_metadata``).
- ``{"type": "health"}``: reply ``{"type": "health", "status": "ok", "requests", "errors", "uptime_s"}``.

Any bad request gets ``{"type": "error", "error": "<one line naming the problem>"}`` and the connection stays open.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

NDARRAY_EXT = 1
DEFAULT_MAX_MESSAGE_BYTES = 16 * 2**20
DEFAULT_MAX_BATCH = 1024


class ProtocolError(ValueError):
    """A request the server cannot answer; the message is sent back as the error reply."""


def _default(obj):
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf":
            raise TypeError(f"cannot send an array of dtype {obj.dtype}")
        arr = np.ascontiguousarray(obj)
        return msgpack.ExtType(NDARRAY_EXT, msgpack.packb([arr.dtype.str, list(arr.shape), arr.tobytes()]))
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot send {type(obj).__name__}")


def _ext_hook(code: int, data: bytes):
    if code != NDARRAY_EXT:
        raise ProtocolError(f"unknown msgpack extension type {code} (arrays are type {NDARRAY_EXT})")
    try:
        dtype, shape, raw = msgpack.unpackb(data)
        dtype = np.dtype(dtype)
        if dtype.kind not in "biuf":
            raise ValueError(f"dtype {dtype} is not numeric")
        return np.frombuffer(raw, dtype).reshape(shape)
    except ProtocolError:
        raise
    except Exception as e:  # noqa: BLE001 - any malformed array payload
        raise ProtocolError(f"malformed array payload ({type(e).__name__}: {e})") from None


def pack(message: dict) -> bytes:
    """A message (maps, lists, numbers, strings, numpy arrays) → bytes."""
    return msgpack.packb(message, default=_default, use_bin_type=True)


def unpack(data: bytes | str) -> Any:
    """Bytes → the message; ``ProtocolError`` for anything that is not one msgpack value."""
    if isinstance(data, str):
        raise ProtocolError("expected a binary msgpack frame, got a text frame")
    try:
        return msgpack.unpackb(data, ext_hook=_ext_hook, raw=False, strict_map_key=False)
    except ProtocolError:
        raise
    except Exception as e:  # noqa: BLE001 - garbage bytes
        raise ProtocolError(f"request is not a msgpack message ({type(e).__name__}: {e})") from None


def error_reply(message: str, request_id=None) -> dict:
    reply = {"type": "error", "error": message}
    return reply if request_id is None else {**reply, "id": request_id}


def check_infer(request: dict, metadata: dict, max_batch: int = DEFAULT_MAX_BATCH
                ) -> tuple[dict[str, np.ndarray], np.ndarray, bool]:
    """Validate an ``infer`` request against the manifest → (obs {key: (B, obs_span, ...)} in the manifest's
    dtypes, key_data (B, 2) uint32, whether the request was batched). Raises ``ProtocolError`` naming the field."""
    obs = request.get("obs")
    if not isinstance(obs, dict):
        raise ProtocolError(f"obs: expected a map of observation key to array, got {type(obs).__name__}")
    spec = metadata["obs"]
    unknown = sorted(set(map(str, obs)) - set(spec))
    missing = sorted(set(spec) - set(map(str, obs)))
    if unknown or missing:
        raise ProtocolError(f"obs: keys {sorted(map(str, obs))} do not match the policy's {sorted(spec)} "
                            f"(unknown: {unknown}, missing: {missing})")
    out, batch, batched = {}, None, None
    for k, s in spec.items():
        x = obs[k]
        want = tuple(s["shape"])
        if not isinstance(x, np.ndarray):
            raise ProtocolError(f"obs[{k!r}]: expected an array of shape {want} or (B, *{want}), got "
                                f"{type(x).__name__}")
        if x.shape == want:
            is_batched = False
            x = x[None]
        elif x.ndim == len(want) + 1 and x.shape[1:] == want:
            is_batched = True
        else:
            raise ProtocolError(f"obs[{k!r}]: expected shape {want} or (B, *{want}), got {x.shape}")
        dtype = np.dtype(s["dtype"])
        if dtype.kind == "f":
            if x.dtype.kind != "f":
                raise ProtocolError(f"obs[{k!r}]: expected floating values ({dtype}), got dtype {x.dtype}")
            if not np.all(np.isfinite(x)):
                raise ProtocolError(f"obs[{k!r}]: holds NaN or Inf")
        elif x.dtype != dtype:
            raise ProtocolError(f"obs[{k!r}]: expected dtype {dtype}, got {x.dtype}")
        if batch is None:
            batch, batched = x.shape[0], is_batched
        elif x.shape[0] != batch or is_batched != batched:
            raise ProtocolError(f"obs[{k!r}]: batch {x.shape[0] if is_batched else 'none'} differs from the other "
                                f"keys' ({batch if batched else 'none'})")
        out[k] = x.astype(dtype, copy=False)
    if not 1 <= batch <= max_batch:
        raise ProtocolError(f"obs: batch of {batch} observation histories, the server takes 1 to {max_batch}")
    return out, _key_data(request, batch, batched), batched


def _key_data(request: dict, batch: int, batched: bool) -> np.ndarray:
    if "key" in request:
        kd = request["key"]
        want = (batch, 2) if batched else (2,)
        if not isinstance(kd, np.ndarray) or kd.dtype != np.uint32 or kd.shape != want:
            got = f"{kd.dtype} {kd.shape}" if isinstance(kd, np.ndarray) else type(kd).__name__
            raise ProtocolError(f"key: expected uint32 raw PRNG key data of shape {want} (jax.random.key_data), "
                                f"got {got}")
        return kd.reshape(batch, 2)
    seed = request.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or not 0 <= seed < 2**32:
        raise ProtocolError(f"seed: expected an int in [0, 2**32), got {seed!r}")
    # jax.random.key(seed) for a 32-bit seed is (0, seed); row i gets seed + i
    rows = (np.uint64(seed) + np.arange(batch, dtype=np.uint64)) % np.uint64(2**32)
    return np.stack([np.zeros(batch, np.uint32), rows.astype(np.uint32)], axis=1)


__all__ = ["DEFAULT_MAX_BATCH", "DEFAULT_MAX_MESSAGE_BYTES", "ProtocolError", "check_infer", "error_reply", "pack",
           "unpack"]
