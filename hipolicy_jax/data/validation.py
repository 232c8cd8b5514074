"""Validation of episodes read from external datasets, with errors that name the file, the key and what was expected.

The importers (``hipolicy_jax.data.importers``) read one episode at a time into ``{key: (T_i, ...)}`` arrays and run
these checks before anything is written:

* ``check_source_episode_ends``: a source's cumulative ``episode_ends`` must be 1-D integers, non-decreasing, start
  at >= 0 and end at the number of frames. Equal consecutive ends are *empty* episodes (reported and dropped by the
  importer); a decreasing end is an error.
* ``check_episode_arrays``: every key has the same number of frames, standard keys have their documented rank
  (``replay_buffer.STANDARD_KEYS``), images are ``(T, H, W, 3) uint8``.
* ``check_finite``: no NaN / Inf in floating arrays (first bad frame reported).
* ``check_same_frame_shape``: every episode's per-frame shape and dtype of a key match the first kept episode's.
* ``too_short_reason``: the reason an episode is dropped (empty, or fewer frames than a minimum such as
  ``ChunkConfig.action_span``), or None to keep it.

Every failure raises ``DataValidationError`` (a ``ValueError``).
"""

from __future__ import annotations

import numpy as np

from hipolicy_jax.data.replay_buffer import STANDARD_KEYS, expected_layout


class DataValidationError(ValueError):
    """An external dataset does not fit the project's layout; the message names file, key, expected and actual."""


def describe(arr: np.ndarray) -> str:
    """``'float32 (12, 3)'``: dtype and shape for messages."""
    return f"{arr.dtype} {tuple(arr.shape)}"


def check_source_episode_ends(ends, num_frames: int, where: str) -> np.ndarray:
    """Validate a source's cumulative episode ends and return the per-episode lengths ``(E,)`` int64.

    Args:
      ends: the source's ``episode_ends``.
      num_frames: number of frames of the source's data arrays (the last end must equal it).
      where: file and key for messages, e.g. ``"pusht.zarr: meta/episode_ends"``.

    Zero lengths (equal consecutive ends) are allowed here: they are empty episodes, which the importer drops and
    reports. A decreasing end, a negative first end, a non-integer dtype or a wrong last end raise.
    """
    ends = np.asarray(ends)
    if ends.ndim != 1:
        raise DataValidationError(f"{where}: expected a 1-D array (E,) of cumulative episode ends, "
                                  f"got shape {tuple(ends.shape)}")
    if ends.size == 0:
        raise DataValidationError(f"{where}: expected at least one episode, got an empty array")
    if ends.dtype.kind not in "iu":
        raise DataValidationError(f"{where}: expected an integer dtype (int64), got {ends.dtype}")
    ends = ends.astype(np.int64)
    if ends[0] < 0:
        raise DataValidationError(f"{where}: expected non-negative ends, episode 0 ends at {int(ends[0])}")
    lengths = np.diff(np.concatenate([[0], ends]))
    if np.any(lengths < 0):
        bad = int(np.argmax(lengths < 0))
        raise DataValidationError(f"{where}: expected non-decreasing cumulative ends, but episode {bad} ends at "
                                  f"{int(ends[bad])}, before the previous end {int(ends[bad - 1])}")
    if int(ends[-1]) != num_frames:
        raise DataValidationError(f"{where}: expected the last end to equal the number of frames {num_frames}, "
                                  f"got {int(ends[-1])}")
    return lengths


def check_episode_arrays(episode: dict[str, np.ndarray], where: str,
                         sources: dict[str, str] | None = None) -> int:
    """Check one episode's arrays; returns its number of frames T.

    Args:
      episode: ``{key: (T, ...)}`` in the project's keys.
      where: file / episode for messages, e.g. ``"demo.hdf5: data/demo_3"``.
      sources: ``{key: source description}`` added to messages (e.g. ``"obs/agentview_image"``).

    Raises ``DataValidationError`` for a scalar, for keys of different lengths (naming both) and for a standard key
    of the wrong rank, trailing size or dtype (expected vs actual).
    """
    sources = sources or {}

    def name(key: str) -> str:
        src = sources.get(key)
        return f"{key!r}" + (f" (from {src})" if src and src != key else "")

    if not episode:
        raise DataValidationError(f"{where}: no keys to import")
    ref = next(iter(episode))
    length = None
    for key, arr in episode.items():
        if arr.ndim == 0:
            raise DataValidationError(f"{where}: key {name(key)} expected a time-first array "
                                      f"{expected_layout(key)}, got a scalar of dtype {arr.dtype}")
        if length is None:
            length = arr.shape[0]
        elif arr.shape[0] != length:
            raise DataValidationError(f"{where}: key {name(key)} has {arr.shape[0]} frames but key {name(ref)} has "
                                      f"{length}; expected every key to have one frame per time step "
                                      f"(obs/action length mismatch)")
        if key in STANDARD_KEYS:
            layout, ndim, trailing, dtype = STANDARD_KEYS[key]
            if arr.ndim != ndim:
                raise DataValidationError(f"{where}: key {name(key)} expected rank {ndim} {layout}, "
                                          f"got rank {arr.ndim} {describe(arr)}")
            if trailing is not None and arr.shape[-1] not in trailing:
                raise DataValidationError(f"{where}: key {name(key)} expected shape {layout}, got {describe(arr)}")
            if dtype is not None and arr.dtype != np.dtype(dtype):
                raise DataValidationError(f"{where}: key {name(key)} expected dtype {dtype}: {layout}, "
                                          f"got {describe(arr)}")
    return int(length)


def check_finite(episode: dict[str, np.ndarray], where: str, sources: dict[str, str] | None = None) -> None:
    """Raise ``DataValidationError`` naming the key and first bad frame if a float array holds NaN or Inf."""
    sources = sources or {}
    for key, arr in episode.items():
        if arr.dtype.kind not in "fc" or arr.size == 0:
            continue
        finite = np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1)
        if not finite.all():
            frame = int(np.argmin(finite))
            values = arr[frame].ravel()
            bad = values[~np.isfinite(values)]
            src = sources.get(key)
            label = f"{key!r}" + (f" (from {src})" if src and src != key else "")
            raise DataValidationError(f"{where}: key {label} contains {bad[0]} at frame {frame} of "
                                      f"{arr.shape[0]} ({int((~finite).sum())} non-finite frames); "
                                      f"expected finite values")


def check_same_frame_shape(episode: dict[str, np.ndarray], reference: dict[str, tuple[tuple[int, ...], str]],
                           where: str, reference_where: str) -> None:
    """Every key's per-frame shape and dtype must match ``reference`` ``{key: (frame_shape, dtype)}``."""
    for key, arr in episode.items():
        shape, dtype = reference[key]
        if tuple(arr.shape[1:]) != shape or str(arr.dtype) != dtype:
            raise DataValidationError(f"{where}: key {key!r} has frames of {arr.dtype} {tuple(arr.shape[1:])}, "
                                      f"expected {dtype} {shape} as in {reference_where}")


def too_short_reason(length: int, min_length: int) -> str | None:
    """Why an episode of ``length`` frames is dropped (``'empty (0 frames)'``, ``'too short: ...'``), or None."""
    if length == 0:
        return "empty (0 frames)"
    if length < min_length:
        return f"too short: {length} frames < min_length {min_length}"
    return None
