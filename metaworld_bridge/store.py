"""Episodes → the project's zarr replay-buffer layout (``hipolicy_jax.data.replay_buffer``; Diffusion Policy's).

``data/<key>`` holds every episode's frames concatenated along time (chunked along time, about 4 MiB a chunk) and
``meta/episode_ends`` the cumulative end of each episode (int64, strictly increasing, last = number of frames).
Keys written by the bridge: ``state`` (T, 39) float32, ``action`` (T, 4) float32 and, with a camera,
``point_cloud`` (T, P, 3) float32. The root's attributes record where the demos came from (task, seeds, camera,
crop) and ``action_kinds`` (one of ``absolute`` / ``delta`` per action dim: whether a stride-s segment samples or
sums it); ``ReplayBuffer.load`` does not need them. Each array stores its SHA-256 and each chunk zstd's checksum, as
``ReplayBuffer.save`` writes them, so a buffer damaged on disk is named when it is read.

The buffer is written to a temporary sibling and renamed into place, so no reader ever sees a half-written one.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from collections.abc import Sequence

import numpy as np
import zarr

_TARGET_CHUNK_BYTES = 4 * 2**20


def concatenate(episodes: Sequence[dict[str, np.ndarray]]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Episodes [{key: (T_i, ...)}] → ({key: (T, ...)}, episode_ends (E,) int64); checks keys and lengths."""
    if not episodes:
        raise ValueError("episodes: none to write")
    keys = list(episodes[0])
    lengths = []
    for i, ep in enumerate(episodes):
        if set(ep) != set(keys):
            raise ValueError(f"episode {i}: keys {sorted(ep)}, expected {sorted(keys)}")
        n = {k: len(v) for k, v in ep.items()}
        if len(set(n.values())) != 1 or n[keys[0]] == 0:
            raise ValueError(f"episode {i}: frames per key {n}; expected one positive length")
        lengths.append(n[keys[0]])
    data = {k: np.concatenate([ep[k] for ep in episodes], axis=0) for k in keys}
    for k, v in data.items():
        if v.dtype.kind == "f" and not np.isfinite(v).all():
            raise ValueError(f"data[{k!r}]: contains NaN or Inf")
    return data, np.cumsum(np.asarray(lengths, np.int64))


def array_sha256(arr: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and C-order bytes: ``hipolicy_jax.data.replay_buffer.array_sha256``, which
    ``ReplayBuffer.load`` compares with the one stored here (this venv does not import the project)."""
    arr = np.ascontiguousarray(arr)
    h = hashlib.sha256(f"{arr.dtype.str}{tuple(arr.shape)}".encode())
    h.update(memoryview(arr).cast("B") if arr.size else b"")
    return h.hexdigest()


def _write_array(group, name: str, arr: np.ndarray, chunks) -> None:
    """As ``ReplayBuffer.save`` writes an array: zstd with its content checksum on every chunk, every chunk written
    and the array's SHA-256 in its attributes, so ``ReplayBuffer.load`` names a damaged chunk."""
    group.create_array(name, data=arr, chunks=chunks, compressors=zarr.codecs.ZstdCodec(level=0, checksum=True),
                       attributes={"sha256": array_sha256(arr)}, config={"write_empty_chunks": True})


def write_buffer(path: str, episodes: Sequence[dict[str, np.ndarray]], attrs: dict | None = None,
                 overwrite: bool = False) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Write ``episodes`` to a zarr directory at ``path`` → (data, episode_ends) as written."""
    path = os.fspath(path)
    if os.path.lexists(path) and not overwrite:
        raise FileExistsError(f"out: {path} already exists; pass --overwrite to replace it, or another --out")
    data, ends = concatenate(episodes)
    kinds = (attrs or {}).get("action_kinds")
    if kinds is not None and "action" in data and (len(kinds) != data["action"].shape[-1]
                                                   or not set(kinds) <= {"absolute", "delta"}):
        raise ValueError(f"action_kinds: one of absolute / delta per action dim ({data['action'].shape[-1]}), got "
                         f"{list(kinds)}")
    parent = os.path.dirname(os.path.abspath(path))
    os.makedirs(parent, exist_ok=True)
    partial = f"{path}.partial-{os.getpid()}"
    shutil.rmtree(partial, ignore_errors=True)
    root = zarr.open_group(partial, mode="w")
    if attrs:
        root.attrs.update(attrs)
    group = root.create_group("data")
    for key, arr in data.items():
        frame_bytes = max(1, arr[:1].nbytes)
        chunk_t = int(min(arr.shape[0], max(1, _TARGET_CHUNK_BYTES // frame_bytes)))
        _write_array(group, key, arr, (chunk_t,) + tuple(max(1, d) for d in arr.shape[1:]))
    _write_array(root.create_group("meta"), "episode_ends", ends, "auto")
    if os.path.lexists(path):
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path)
        else:
            os.remove(path)
    os.replace(partial, path)
    return data, ends
