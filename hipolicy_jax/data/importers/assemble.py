"""What every importer shares after reading: image conversion, action kinds, checks, and the buffer plus summary.

A format module reads its source episode by episode and hands ``_assemble`` one ``(name, where, loader)`` per episode;
``_assemble`` converts images, validates (``hipolicy_jax.data.validation``), drops and concatenates, settles the
action kinds (``_settle_kinds``) and returns ``(ReplayBuffer, ImportSummary)``.

Images (keys ``image`` or ``image_*``) are converted to ``(T, H, W, 3) uint8`` (``_ImageConverter``): floats in
[0, 1] are scaled by 255, floats in [0, 255] rounded (the scale is decided by the first episode and then required of
all), and the conversion is recorded in the summary.

Action kinds (``ChunkConfig.action_kinds``: per action dimension ``'absolute'`` or ``'delta'``): the caller's
``action_kinds=`` (one kind for every dimension, or one per dimension) and the kinds the source says must agree where
both are known; the buffer records them (root attribute ``action_kinds``), or none when neither says, and the summary
notes it.

Nothing is dropped silently. Empty episodes, and episodes shorter than ``min_length`` frames when a caller asks for
one (default 1: every episode is kept, since training pads episode edges as Diffusion Policy's sampler does), are
dropped and listed with their reason in the ``ImportSummary``; every other problem (missing key, wrong rank,
obs/action length mismatch, NaN / Inf, a dtype or shape that disagrees with the first kept episode) raises
``DataValidationError`` naming the file, the key and expected vs actual.

``_optional_import`` names the optional package a format needs (``pip install 'hipolicy_jax[import]'``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from hipolicy_jax.config import check_action_kinds
from hipolicy_jax.data.importers.keymap import KeyMap, format_key_map, is_image_key
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.data.validation import (DataValidationError, check_episode_arrays, check_finite,
                                          check_same_frame_shape, too_short_reason)


# ------------------------------------------------------------------------------------------------------- summary
@dataclasses.dataclass(frozen=True)
class EpisodeRecord:
    """One source episode: its name in the source, its number of frames and, if dropped, why."""

    name: str
    length: int
    reason: str | None = None


@dataclasses.dataclass(frozen=True)
class ImportSummary:
    """What an import kept and dropped, and the layout it produced.

    Attributes:
      source: the source path.
      fmt: ``'dp-zarr'``, ``'robomimic'`` or ``'lerobot'``.
      key_map: the key map used (after defaults).
      min_length: episodes shorter than this were dropped.
      kept: the imported episodes, in order.
      dropped: the dropped episodes with their reasons.
      keys: ``{key: (per-frame shape, dtype)}`` of the imported arrays.
      notes: conversions made and source keys not imported.
      action_kinds: the actions' kinds the buffer records (module docstring), None when unknown.
    """

    source: str
    fmt: str
    key_map: KeyMap
    min_length: int
    kept: tuple[EpisodeRecord, ...]
    dropped: tuple[EpisodeRecord, ...]
    keys: dict[str, tuple[tuple[int, ...], str]]
    notes: tuple[str, ...] = ()
    action_kinds: tuple[str, ...] | None = None

    @property
    def num_frames(self) -> int:
        """Frames of the kept episodes."""
        return sum(r.length for r in self.kept)

    def to_dict(self) -> dict:
        """JSON-able form."""
        return {"source": self.source, "format": self.fmt,
                "key_map": {k: list(v) for k, v in self.key_map.items()}, "min_length": self.min_length,
                "num_frames": self.num_frames,
                "kept": [{"name": r.name, "length": r.length} for r in self.kept],
                "dropped": [{"name": r.name, "length": r.length, "reason": r.reason} for r in self.dropped],
                "keys": {k: {"shape": list(s), "dtype": d} for k, (s, d) in self.keys.items()},
                "notes": list(self.notes),
                "action_kinds": None if self.action_kinds is None else list(self.action_kinds)}

    def format(self) -> str:
        """Human-readable multi-line summary (printed by ``experiments.import_data``)."""
        lengths = [r.length for r in self.kept]
        lines = [f"source: {self.source} ({self.fmt})",
                 f"key map: {format_key_map(self.key_map)}",
                 f"kept: {len(self.kept)} episodes, {self.num_frames} frames"
                 + (f", length {min(lengths)}-{max(lengths)}" if lengths else ""),
                 f"dropped: {len(self.dropped)} episodes (min_length {self.min_length})",
                 f"action kinds: {' '.join(self.action_kinds)}" if self.action_kinds is not None else
                 "action kinds: unknown (the source does not say; pass --action-kinds to record them)"]
        lines += [f"  {r.name}: {r.reason}" for r in self.dropped]
        lines.append("keys:" if self.keys else "keys: none")
        lines += [f"  {k}: (T, {', '.join(map(str, s))}) {d}".replace("(T, )", "(T,)")
                  for k, (s, d) in self.keys.items()]
        if self.notes:
            lines.append("notes:")
            lines += [f"  {n}" for n in self.notes]
        return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ shared pieces
def _optional_import(module: str, what: str):
    try:
        return __import__(module, fromlist=["_"])
    except ImportError as e:
        raise ImportError(f"{what} needs the optional package {module.split('.')[0]!r}: "
                          f"pip install 'hipolicy_jax[import]'") from e


class _ImageConverter:
    """Converts image keys to uint8 with one scale per key, decided by the first episode; records notes."""

    def __init__(self):
        self.scale: dict[str, float] = {}
        self.notes: list[str] = []

    def __call__(self, key: str, arr: np.ndarray, where: str, source: str) -> np.ndarray:
        if not is_image_key(key) or arr.dtype == np.uint8 or arr.dtype.kind not in "fiub":
            return arr
        if arr.size == 0:
            return arr.astype(np.uint8)
        label = f"key {key!r}" + (f" (from {source})" if source != key else "")
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            frame = int(np.argmin(np.isfinite(arr.reshape(arr.shape[0], -1)).all(axis=1)))
            raise DataValidationError(f"{where}: {label} contains NaN or Inf at frame {frame}; expected finite pixel "
                                      f"values")
        lo, hi = float(arr.min()), float(arr.max())
        if key not in self.scale:
            self.scale[key] = 255.0 if arr.dtype.kind == "f" and hi <= 1.0 else 1.0
            rng = "[0, 1] scaled by 255 and rounded" if self.scale[key] == 255.0 else "[0, 255] rounded"
            self.notes.append(f"{key}: {arr.dtype} pixels in {rng} to uint8")
        scale = self.scale[key]
        if lo < 0 or hi * scale > 255.0 + 1e-3:
            expected = "[0, 1]" if scale == 255.0 else "[0, 255]"
            raise DataValidationError(f"{where}: {label} has pixel values in [{lo:g}, {hi:g}], expected {expected} "
                                      f"({arr.dtype}) to convert to uint8")
        return np.clip(np.rint(arr.astype(np.float32) * scale), 0, 255).astype(np.uint8)


EpisodeLoader = Callable[[], tuple[dict[str, np.ndarray], dict[str, str]]]


def _settle_kinds(source: str, given: Sequence[str] | None, said: Sequence[str] | None,
                  action_dim: int) -> tuple[str, ...] | None:
    """The kinds an import records: ``given`` (the caller's; one kind stands for every dimension) and ``said`` (the
    source's), which must agree where both are known; None when neither is."""
    try:
        if given is not None:
            given = tuple([given] if isinstance(given, str) else given)
            given = check_action_kinds(given * action_dim if len(given) == 1 else given, "action_kinds", action_dim)
        if said is not None:
            said = check_action_kinds(said, f"{source}: action_kinds", action_dim)
    except ValueError as e:
        raise DataValidationError(str(e)) from None
    if given is not None and said is not None and given != said:
        raise DataValidationError(f"{source}: says its action kinds are {list(said)}, action_kinds gives "
                                  f"{list(given)}; expected them equal (leave --action-kinds out to take the source's)")
    return given if given is not None else said


def _assemble(source: str, fmt: str, key_map: KeyMap, min_length: int,
              episodes: Iterable[tuple[str, str, EpisodeLoader]], notes: Sequence[str],
              images: _ImageConverter | None = None, action_kinds: Sequence[str] | None = None,
              source_kinds: Sequence[str] | None = None) -> tuple[ReplayBuffer, ImportSummary]:
    """Validate, filter and concatenate episodes ``(name, where, loader)``; loaders return mapped arrays + sources.
    ``action_kinds`` (the caller's) and ``source_kinds`` (the source's) settle the kinds recorded (``_settle_kinds``).

    Per episode: structural checks (ranks, lengths, image dtype) raise; empty / too-short episodes are dropped with
    their reason; kept episodes are checked for NaN / Inf and for frames of the same shape and dtype as the first
    kept episode.
    """
    if min_length < 1:
        raise ValueError(f"min_length: expected >= 1, got {min_length}")
    images = images or _ImageConverter()
    kept, dropped, arrays = [], [], []
    reference: dict[str, tuple[tuple[int, ...], str]] | None = None
    reference_where = ""
    for name, where, load in episodes:
        raw, sources = load()
        episode = {k: images(k, np.asarray(a), where, sources.get(k, k)) for k, a in raw.items()}
        length = check_episode_arrays(episode, where, sources)
        reason = too_short_reason(length, min_length)
        if reason is not None:
            dropped.append(EpisodeRecord(name, length, reason))
            continue
        check_finite(episode, where, sources)
        if reference is None:
            reference = {k: (tuple(a.shape[1:]), str(a.dtype)) for k, a in episode.items()}
            reference_where = where
        else:
            check_same_frame_shape(episode, reference, where, reference_where)
        kept.append(EpisodeRecord(name, length))
        arrays.append(episode)
    summary = ImportSummary(source=source, fmt=fmt, key_map=key_map, min_length=min_length, kept=tuple(kept),
                            dropped=tuple(dropped), keys=reference or {}, notes=tuple(images.notes) + tuple(notes))
    if not kept:
        raise DataValidationError(f"{source}: no episode left to import, all {len(dropped)} dropped\n"
                                  f"{summary.format()}")
    action_shape = reference["action"][0] if "action" in reference else ()
    kinds = _settle_kinds(source, action_kinds, source_kinds, action_shape[-1] if len(action_shape) == 1 else 0)
    summary = dataclasses.replace(summary, action_kinds=kinds)
    return ReplayBuffer.from_episodes(arrays, action_kinds=kinds), summary
