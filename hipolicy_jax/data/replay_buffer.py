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

``action_kinds`` (optional): per action dimension ``'absolute'`` or ``'delta'`` (``ChunkConfig.action_kinds``),
stored as the zarr root attribute ``action_kinds`` (a list of strings, one per action dimension; the Meta-World
bridge writes the same attribute). None: not recorded (buffers written before it existed, imports whose source did
not say); training then takes the task's kinds (``runs.train``).

Damage on disk is caught where a buffer is read (``ReplayBuffer.load``) and reported as one ``BufferDamaged`` line
naming the buffer, the part and what to do. ``save`` compresses each chunk with zstd's content checksum, writes every
chunk (also one holding only the fill value) and stores each array's SHA-256 in its attributes, so in a buffer it
wrote a changed chunk fails to decode (naming the chunk), a deleted chunk is missing (naming it) and any other change
(a chunk swapped, metadata edited) fails the SHA-256. A buffer written without them (Diffusion Policy's, or this
project's before checksums were stored) is checked as far as zarr can: a chunk that fails to decode or metadata that
does not parse is named; a missing data chunk reads as the array's fill value (zarr leaves out chunks that hold only
it, so it cannot be told from a deleted one) and is noted on stderr; a missing ``meta/episode_ends`` chunk (never
all fill value) is an error.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import itertools
import os
import shutil
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence

import numpy as np
import zarr

from hipolicy_jax.config import check_action_kinds
from hipolicy_jax.jsonio import DamagedFileError, one_line
from hipolicy_jax.jsonio import load as load_json

# key -> (layout for messages, number of dimensions, allowed trailing sizes or None, required dtype or None)
STANDARD_KEYS: dict[str, tuple[str, int, tuple[int, ...] | None, str | None]] = {
    "state": ("(T, D)", 2, None, None),
    "action": ("(T, A)", 2, None, None),
    "image": ("(T, H, W, 3) uint8", 4, (3,), "uint8"),
    "point_cloud": ("(T, P, 3 or 6)", 3, (3, 6), None),
}

_TARGET_CHUNK_BYTES = 4 * 2**20  # zarr chunks along time of about 4 MiB
SHA256_ATTR = "sha256"  # an array's attribute: the SHA-256 of its dtype, shape and bytes when it was written
ACTION_KINDS_ATTR = "action_kinds"  # the root's attribute: ["absolute" | "delta", ...], one per action dimension
DAMAGED_HINT = "the buffer is damaged: delete it to collect it again (or import it again)"
_METADATA_FILES = ("zarr.json", ".zgroup", ".zarray", ".zattrs", ".zmetadata")


class BufferDamaged(DamagedFileError):
    """A zarr replay buffer on disk that does not read back as written: one line ``<buffer>: <part> <what is
    wrong>; <what to do>`` (metadata that does not parse, a chunk that fails to decode or is missing, an array whose
    SHA-256 differs from the one stored when it was written)."""


def array_sha256(arr: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and C-order bytes (what ``save`` stores and ``load`` compares)."""
    arr = np.ascontiguousarray(arr)
    h = hashlib.sha256(f"{arr.dtype.str}{tuple(arr.shape)}".encode())
    h.update(memoryview(arr).cast("B") if arr.size else b"")
    return h.hexdigest()


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
    """In-memory episodes: ``data[key]`` ``(T, ...)`` time-first arrays and cumulative ``episode_ends`` ``(E,)``;
    ``action_kinds`` ``(A,)`` 'absolute' / 'delta' per action dimension, or None when not recorded."""

    data: dict[str, np.ndarray]
    episode_ends: np.ndarray
    action_kinds: tuple[str, ...] | None = None

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
        if self.action_kinds is not None:
            dim = data["action"].shape[-1] if "action" in data and data["action"].ndim == 2 else None
            object.__setattr__(self, "action_kinds", check_action_kinds(self.action_kinds, "action_kinds", dim))
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
    def from_episodes(cls, episodes: Sequence[dict[str, np.ndarray]],
                      action_kinds: Sequence[str] | None = None) -> ReplayBuffer:
        """Concatenate episodes ``[{key: (T_i, ...)}, ...]``; every episode must hold the same keys.
        ``action_kinds``: the actions' kinds, one per dimension (None: not recorded)."""
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
        return cls(data=data, episode_ends=np.cumsum(np.asarray(lengths, dtype=np.int64)),
                   action_kinds=None if action_kinds is None else tuple(action_kinds))

    # ----------------------------------------------------------------------------------------------- storage
    def save(self, path: str | os.PathLike, overwrite: bool = False) -> None:
        """Write ``data/<key>`` (chunked along time) and ``meta/episode_ends`` to a zarr directory at ``path``, each
        array with its SHA-256 and every chunk with zstd's checksum (what ``load`` checks), and ``action_kinds``
        (when recorded) as the root attribute ``action_kinds``."""
        path = os.fspath(path)
        if os.path.lexists(path):
            if not overwrite:
                raise FileExistsError(f"{path!r} already exists; pass overwrite=True to replace it")
            if os.path.isdir(path) and not os.path.islink(path):
                shutil.rmtree(path)
            else:
                os.remove(path)
        root = zarr.open_group(path, mode="w")
        if self.action_kinds is not None:
            root.attrs[ACTION_KINDS_ATTR] = list(self.action_kinds)
        data_group = root.create_group("data")
        for key, arr in self.data.items():
            frame_bytes = max(1, arr[:1].nbytes)
            chunk_t = int(min(arr.shape[0], max(1, _TARGET_CHUNK_BYTES // frame_bytes)))
            _write_array(data_group, key, arr, (chunk_t,) + tuple(max(1, d) for d in arr.shape[1:]))
        _write_array(root.create_group("meta"), "episode_ends", self.episode_ends, "auto")

    @classmethod
    def load(cls, path: str | os.PathLike, keys: Sequence[str] | None = None,
             hint: str = DAMAGED_HINT) -> ReplayBuffer:
        """Read a zarr replay buffer (ours or Diffusion Policy's) into memory; ``keys`` picks a subset of data.

        A damaged buffer raises ``BufferDamaged`` (one line: the buffer, the part, what is wrong, then ``hint``):
        metadata (``zarr.json``) that does not parse or is missing, a chunk that fails to decode or whose file is
        missing, an array that differs from the SHA-256 stored when it was written."""
        path = os.fspath(path)
        if not os.path.exists(path):
            raise FileNotFoundError(f"no replay buffer at {path!r}")
        root = _metadata(path, hint, lambda: zarr.open_group(path, mode="r"))
        layout = _metadata(path, hint, lambda: "data" in root and "meta" in root and "episode_ends" in root["meta"])
        if not layout:
            raise ValueError(f"{path!r}: expected zarr groups 'data/<key>' and 'meta/episode_ends'")
        data_group = _metadata(path, hint, lambda: root["data"])
        with warnings.catch_warnings():  # a folder without metadata: named below when it is damage
            warnings.filterwarnings("ignore", message=".*not recognized as a component of a Zarr hierarchy")
            available = _metadata(path, hint, lambda: sorted(data_group.array_keys()))
        wanted = available if keys is None else list(keys)
        for key in wanted:
            if key not in available:
                lost = os.path.join(path, "data", key)
                if os.path.isdir(lost) and not any(os.path.exists(os.path.join(lost, m)) for m in _METADATA_FILES):
                    raise BufferDamaged(path, f"data/{key} has no zarr.json (its metadata is missing)", hint)
                raise ValueError(f"{path!r}: key {key!r} not in data, available keys {available}")
        folders = os.path.join(path, "data")
        for name in sorted(os.listdir(folders)) if keys is None and os.path.isdir(folders) else []:
            # an array whose metadata was deleted is not listed: it must not drop out of the buffer unnoticed
            folder = os.path.join(folders, name)
            if (name not in available and os.path.isdir(folder) and not name.startswith(".")
                    and not any(os.path.exists(os.path.join(folder, m)) for m in _METADATA_FILES)):
                raise BufferDamaged(path, f"data/{name} has no zarr.json (its metadata is missing)", hint)
        data = {key: _read_array(path, _metadata(path, hint, lambda k=key: data_group[k]), hint) for key in wanted}
        ends = _read_array(path, _metadata(path, hint, lambda: root["meta"]["episode_ends"]), hint,
                           never_fill=True)
        kinds = _metadata(path, hint, lambda: root.attrs.get(ACTION_KINDS_ATTR))
        try:
            return cls(data=data, episode_ends=ends, action_kinds=kinds)
        except ValueError as e:
            raise ValueError(f"{path}: {' '.join(str(e).split())}") from None


def _write_array(group, name: str, arr: np.ndarray, chunks) -> None:
    """One array of a buffer: zstd with its content checksum on every chunk, every chunk written (also one holding
    only the fill value, so a missing chunk file is damage) and the array's SHA-256 in its attributes."""
    group.create_array(name, data=arr, chunks=chunks, compressors=zarr.codecs.ZstdCodec(level=0, checksum=True),
                       attributes={SHA256_ATTR: array_sha256(arr)}, config={"write_empty_chunks": True})


def _metadata(path: str, hint: str, read: Callable):
    """``read()`` of a buffer's zarr metadata; a failure → ``BufferDamaged`` naming the metadata file that does not
    parse (or the missing root metadata, or zarr's own error)."""
    try:
        return read()
    except (MemoryError, KeyboardInterrupt):
        raise
    except Exception as e:
        raise BufferDamaged(path, _metadata_problem(path) or f"its zarr metadata does not read "
                                                              f"({type(e).__name__}: {one_line(e)})", hint) from None


def _metadata_problem(path: str) -> str | None:
    """What is wrong with the metadata files of the zarr directory at ``path``: the first that is not valid JSON,
    or a root without any; None when they all parse."""
    if not os.path.isdir(path):
        return None
    if not any(os.path.exists(os.path.join(path, m)) for m in ("zarr.json", ".zgroup")):
        return "holds no zarr.json at its root (not a zarr buffer, or its metadata is missing)"
    for folder, dirs, files in os.walk(path):
        dirs.sort()
        for name in sorted(f for f in files if f in _METADATA_FILES):
            file = os.path.join(folder, name)
            try:
                load_json(file, hint="")
            except DamagedFileError as e:
                return f"{os.path.relpath(file, path)} is {e.problem}"
    return None


def _chunk_files(path: str, arr) -> Iterator[tuple[tuple[int, ...], str]]:
    """(chunk coordinates, file relative to the buffer) of every chunk of ``arr``."""
    for coords in itertools.product(*(range(n) for n in arr.cdata_shape)):
        yield coords, os.path.join(arr.path, *arr.metadata.encode_chunk_key(coords).split("/"))


def _chunk_name(arr, coords: tuple[int, ...], file: str) -> str:
    """``data/action chunk 3 (data/action/c/3/0)``: by its index along time when only time is chunked."""
    index = coords[0] if not any(coords[1:]) else coords
    return f"{arr.path} chunk {index} ({file})"


def _read_array(path: str, arr, hint: str, never_fill: bool = False) -> np.ndarray:
    """All of ``arr`` (a buffer's zarr array), checked: its chunk files present, each decoding, and its SHA-256
    the stored one (when ``save`` stored it); ``never_fill``: an array none of whose chunks can hold only the fill
    value (``meta/episode_ends``), so a missing chunk is damage even without a stored SHA-256."""
    stored = arr.attrs.get(SHA256_ATTR)
    missing = [(c, f) for c, f in _chunk_files(path, arr) if not os.path.exists(os.path.join(path, f))] \
        if os.path.isdir(path) else []
    if missing and (stored is not None or never_fill):
        coords, file = missing[0]
        more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
        raise BufferDamaged(path, f"{_chunk_name(arr, coords, file)} is missing{more}", hint)
    if missing:
        print(f"[data] {path}: {len(missing)} chunk(s) of {arr.path} have no file (first {missing[0][1]}) and read as "
              f"its fill value {arr.fill_value}: a buffer written without checksums cannot tell a chunk left out for "
              f"holding only that value from a deleted one", file=sys.stderr, flush=True)
    try:
        values = np.asarray(arr[...])
    except (MemoryError, KeyboardInterrupt):
        raise
    except Exception as e:
        coords, file, err = _first_bad_chunk(arr, path) or ((), arr.path, e)
        raise BufferDamaged(path, f"{_chunk_name(arr, coords, file) if coords else arr.path} fails to decode "
                                  f"({type(err).__name__}: {one_line(err)})", hint) from None
    if stored is not None and array_sha256(values) != stored:
        raise BufferDamaged(path, f"{arr.path} does not match the SHA-256 stored when it was written", hint)
    return values


def _first_bad_chunk(arr, path: str) -> tuple[tuple[int, ...], str, Exception] | None:
    """(coordinates, file, error) of the first chunk of ``arr`` that fails to read; None when each reads alone."""
    for coords, file in _chunk_files(path, arr):
        region = tuple(slice(c * s, min((c + 1) * s, n)) for c, s, n in zip(coords, arr.chunks, arr.shape))
        try:
            arr[region]
        except (MemoryError, KeyboardInterrupt):
            raise
        except Exception as e:
            return coords, file, e
    return None
