"""Episode storage in Diffusion Policy's ReplayBuffer layout.

Every episode's frames are concatenated along time: ``data[key]`` is ``(T, ...)`` with T the total number of frames
of all episodes, and ``episode_ends`` holds the cumulative end index of each episode (int64, strictly increasing,
last == T). On disk (zarr) the same layout is ``data/<key>`` (chunked along time) and ``meta/episode_ends``, which
is what Diffusion Policy's ``ReplayBuffer`` writes, so its datasets load directly.

Standard keys used by the project (others are allowed and only checked for consistent length and finiteness):

    state        (T, D)            float
    action       (T, A)            float
    image        (T, H, W, 3)      uint8
    point_cloud  (T, P, 3 or 6)    float (xyz or xyz+rgb)
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
from collections.abc import Iterator, Sequence

import numpy as np
import zarr

# key -> (layout for messages, number of dimensions, allowed trailing sizes or None, required dtype or None)
STANDARD_KEYS: dict[str, tuple[str, int, tuple[int, ...] | None, str | None]] = {
    "state": ("(T, D)", 2, None, None),
    "action": ("(T, A)", 2, None, None),
    "image": ("(T, H, W, 3) uint8", 4, (3,), "uint8"),
    "point_cloud": ("(T, P, 3 or 6)", 3, (3, 6), None),
}

_TARGET_CHUNK_BYTES = 4 * 2**20  # zarr chunks along time of about 4 MiB


@contextlib.contextmanager
def collection_lock(path: str, who: str = "data") -> Iterator[None]:
    """Hold ``<dir>/.<name>.lock`` while this process makes the dataset at ``path``: processes that need the same
    missing dataset (a campaign's shards) make it once; the others wait here (saying so, prefixed ``[who]``) and
    then find it made. The caller checks ``os.path.exists(path)`` inside the block."""
    from filelock import FileLock, Timeout

    parent = os.path.dirname(os.path.abspath(path))
    os.makedirs(parent, exist_ok=True)
    lock = FileLock(os.path.join(parent, f".{os.path.basename(path)}.lock"))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        print(f"[{who}] waiting for another process collecting {path} (lock {lock.lock_file})", flush=True)
        lock.acquire()
    try:
        yield
    finally:
        lock.release()


def expected_layout(key: str) -> str:
    """The documented shape of a standard key, e.g. ``'(T, H, W, 3) uint8'`` for ``image``; ``'(T, ...)'`` else."""
    return STANDARD_KEYS[key][0] if key in STANDARD_KEYS else "(T, ...)"


def check_episode_ends(episode_ends, num_frames: int | None) -> np.ndarray:
    """Validate cumulative episode ends ``(E,)`` (and, unless ``num_frames`` is None, that the last equals it).

    Returns them as int64; raises ``ValueError`` naming ``episode_ends`` and expected vs actual otherwise.
    """
    ends = np.asarray(episode_ends)
    if ends.ndim != 1:
        raise ValueError(f"episode_ends: expected a 1-D array (E,), got shape {ends.shape}")
    if ends.size == 0:
        raise ValueError("episode_ends: empty buffer (no episodes)")
    if ends.dtype.kind not in "iu":
        raise ValueError(f"episode_ends: expected an integer dtype (int64), got {ends.dtype}")
    ends = ends.astype(np.int64)
    lengths = np.diff(np.concatenate([[0], ends]))
    if np.any(lengths <= 0):
        bad = int(np.argmax(lengths <= 0))
        raise ValueError(f"episode_ends: expected strictly increasing positive ends, but episode {bad} ends at "
                         f"{int(ends[bad])} after the previous end {int(ends[bad]) - int(lengths[bad])}")
    if num_frames is not None and ends[-1] != num_frames:
        raise ValueError(f"episode_ends: last end must equal the number of frames {num_frames}, got {int(ends[-1])}")
    return ends


def _check_array(key: str, arr: np.ndarray, num_frames: int, length_ref: str) -> None:
    """Length, standard-key layout and finiteness of one ``(T, ...)`` array."""
    if arr.ndim == 0:
        raise ValueError(f"data[{key!r}]: expected a time-first array {expected_layout(key)}, got a scalar")
    if arr.shape[0] != num_frames:
        raise ValueError(f"data[{key!r}]: has {arr.shape[0]} frames, expected {num_frames} "
                         f"(the length of {length_ref!r})")
    if key in STANDARD_KEYS:
        layout, ndim, trailing, dtype = STANDARD_KEYS[key]
        if arr.ndim != ndim or (trailing is not None and arr.shape[-1] not in trailing):
            raise ValueError(f"data[{key!r}]: expected shape {layout}, got {arr.shape}")
        if dtype is not None and arr.dtype != np.dtype(dtype):
            raise ValueError(f"data[{key!r}]: expected dtype {dtype} {layout}, got {arr.dtype}")
    if arr.dtype.kind in "fc":
        finite = np.isfinite(arr.reshape(num_frames, -1)).all(axis=1)
        if not finite.all():
            raise ValueError(f"data[{key!r}]: contains NaN or Inf, expected finite values; first bad frame index "
                             f"{int(np.argmin(finite))}")


@dataclasses.dataclass(frozen=True, eq=False)
class ReplayBuffer:
    """In-memory episodes: ``data[key]`` ``(T, ...)`` time-first arrays and cumulative ``episode_ends`` ``(E,)``."""

    data: dict[str, np.ndarray]
    episode_ends: np.ndarray

    def __post_init__(self):
        if not self.data:
            raise ValueError("data: empty buffer (no keys)")
        data = {str(k): np.asarray(v) for k, v in self.data.items()}
        ref = next(iter(data))
        num_frames = data[ref].shape[0] if data[ref].ndim else 0
        if num_frames == 0:
            raise ValueError(f"data[{ref!r}]: empty buffer (0 frames)")
        for key, arr in data.items():
            _check_array(key, arr, num_frames, ref)
        ends = check_episode_ends(self.episode_ends, num_frames)
        object.__setattr__(self, "data", data)
        object.__setattr__(self, "episode_ends", ends)

    # ----------------------------------------------------------------------------------------------- queries
    @property
    def num_episodes(self) -> int:
        """E, the number of episodes."""
        return int(self.episode_ends.shape[0])

    @property
    def num_frames(self) -> int:
        """T, the total number of frames."""
        return int(self.episode_ends[-1])

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(self.data)

    def episode_lengths(self) -> np.ndarray:
        """``(E,)`` int64 number of frames per episode."""
        return np.diff(np.concatenate([[0], self.episode_ends]))

    def episode_slice(self, i: int) -> slice:
        """Global frame range of episode ``i`` (negative ``i`` counts from the end)."""
        if not -self.num_episodes <= i < self.num_episodes:
            raise IndexError(f"episode index {i} out of range for {self.num_episodes} episodes")
        i %= self.num_episodes
        start = 0 if i == 0 else int(self.episode_ends[i - 1])
        return slice(start, int(self.episode_ends[i]))

    def get_episode(self, i: int) -> dict[str, np.ndarray]:
        """Views of episode ``i``'s frames: ``{key: (T_i, ...)}``."""
        sl = self.episode_slice(i)
        return {key: arr[sl] for key, arr in self.data.items()}

    # ------------------------------------------------------------------------------------------ construction
    @classmethod
    def from_episodes(cls, episodes: Sequence[dict[str, np.ndarray]]) -> ReplayBuffer:
        """Concatenate episodes ``[{key: (T_i, ...)}, ...]``; every episode must hold the same keys."""
        if len(episodes) == 0:
            raise ValueError("episodes: empty buffer (no episodes given)")
        keys = list(episodes[0])
        lengths = []
        for i, ep in enumerate(episodes):
            if set(ep) != set(keys):
                raise ValueError(f"episode {i}: has keys {sorted(ep)}, expected {sorted(keys)} (the keys of episode 0)")
            n = np.asarray(ep[keys[0]]).shape[0]
            for key in keys:
                got = np.asarray(ep[key]).shape[0]
                if got != n:
                    raise ValueError(f"episode {i}: data[{key!r}] has {got} frames, expected {n} "
                                     f"(the length of {keys[0]!r})")
            lengths.append(n)
        data = {key: np.concatenate([np.asarray(ep[key]) for ep in episodes], axis=0) for key in keys}
        return cls(data=data, episode_ends=np.cumsum(np.asarray(lengths, dtype=np.int64)))

    # ----------------------------------------------------------------------------------------------- storage
    def save(self, path: str | os.PathLike, overwrite: bool = False) -> None:
        """Write ``data/<key>`` (chunked along time) and ``meta/episode_ends`` to a zarr directory at ``path``."""
        path = os.fspath(path)
        if os.path.lexists(path):
            if not overwrite:
                raise FileExistsError(f"{path!r} already exists; pass overwrite=True to replace it")
            if os.path.isdir(path) and not os.path.islink(path):
                shutil.rmtree(path)
            else:
                os.remove(path)
        root = zarr.open_group(path, mode="w")
        data_group = root.create_group("data")
        for key, arr in self.data.items():
            frame_bytes = max(1, arr[:1].nbytes)
            chunk_t = int(min(arr.shape[0], max(1, _TARGET_CHUNK_BYTES // frame_bytes)))
            data_group.create_array(key, data=arr, chunks=(chunk_t,) + tuple(max(1, d) for d in arr.shape[1:]))
        root.create_group("meta").create_array("episode_ends", data=self.episode_ends)

    @classmethod
    def load(cls, path: str | os.PathLike, keys: Sequence[str] | None = None) -> ReplayBuffer:
        """Read a zarr replay buffer (ours or Diffusion Policy's) into memory; ``keys`` picks a subset of data."""
        path = os.fspath(path)
        if not os.path.exists(path):
            raise FileNotFoundError(f"no replay buffer at {path!r}")
        root = zarr.open_group(path, mode="r")
        if "data" not in root or "meta" not in root or "episode_ends" not in root["meta"]:
            raise ValueError(f"{path!r}: expected zarr groups 'data/<key>' and 'meta/episode_ends'")
        data_group = root["data"]
        available = sorted(data_group.array_keys())
        wanted = available if keys is None else list(keys)
        for key in wanted:
            if key not in available:
                raise ValueError(f"{path!r}: key {key!r} not in data, available keys {available}")
        data = {key: np.asarray(data_group[key][...]) for key in wanted}
        return cls(data=data, episode_ends=np.asarray(root["meta"]["episode_ends"][...]))
