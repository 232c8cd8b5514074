"""Import external demonstration datasets into the project's layout (``ReplayBuffer``).

Three sources are supported, each read episode by episode, mapped to the project's keys, validated
(``hipolicy_jax.data.validation``) and concatenated:

* ``import_dp_zarr``: a Diffusion Policy zarr ReplayBuffer (a directory, zarr format 2 or 3, or a ``.zip``):
  ``data/<key>`` time-first arrays and ``meta/episode_ends``. Default key map: every data key as is, with DP's
  ``img`` renamed ``image``.
* ``import_robomimic``: a robomimic hdf5 file: ``data/demo_<i>/obs/<key>`` and ``data/demo_<i>/actions``, demos in
  numeric order (``demo_10`` after ``demo_9``). Default key map: ``action=actions``,
  ``state=robot0_eef_pos,robot0_eef_quat,robot0_gripper_qpos`` (those present) and ``image=agentview_image``
  (if present).
* ``import_lerobot``: a local LeRobot dataset folder, v2.x or v3.0 (``codebase_version`` in ``meta/info.json``,
  with ``fps``, ``features`` and the ``data_path`` / ``video_path`` templates). v2.x: one parquet file per episode
  and, for ``video`` features, one mp4 per episode and camera. v3.0: episodes grouped in
  ``data/chunk-NNN/file-NNN.parquet`` and ``videos/<key>/chunk-NNN/file-NNN.mp4`` files, each located by its row of
  ``meta/episodes/chunk-NNN/file-NNN.parquet``. Video frames are decoded and matched by timestamp. Default key map:
  ``state=observation.state``, ``action=action`` and the camera feature as ``image`` (several cameras:
  ``image_<name>`` each).

Key maps are ``{project_key: (source_key, ...)}``; several source keys are concatenated along the last axis
(``state=robot0_eef_pos,robot0_gripper_qpos``). An explicit key map imports exactly its keys, plus ``action`` from
the format's default action source when it does not name ``action``. Images (keys ``image`` or ``image_*``) are
converted to ``(T, H, W, 3) uint8``: floats in [0, 1] are scaled by 255, floats in [0, 255] rounded (the scale is
decided by the first episode and then required of all), and the conversion is recorded in the summary.

Action kinds (``ChunkConfig.action_kinds``: per action dimension ``'absolute'`` or ``'delta'``): every importer
takes ``action_kinds=`` (``--action-kinds`` of ``experiments.import_data``; one kind for every dimension, or one per
dimension) and reads them from the source where it says so: a zarr root attribute ``action_kinds`` (this project's
and the Meta-World bridge's buffers), or robomimic's robosuite controller (``data`` attribute ``env_args``:
``env_kwargs.controller_configs.control_delta``; true: every dimension a delta but the last, the gripper, absolute;
false: all absolute) when the action is the default ``actions``. A flag that disagrees with the source is an error.
The buffer records the kinds (root attribute ``action_kinds``); when neither says, it records none and the
summary notes it: training then takes its task's kinds, and refuses when there is no task to say and a stride
above 1 needs them (``data.windowing.resolve_chunk_kinds``).

Nothing is dropped silently. Empty episodes, and episodes shorter than ``min_length`` frames when a caller asks for
one (default 1: every episode is kept, since training pads episode edges as Diffusion Policy's sampler does), are
dropped and listed with their reason in the ``ImportSummary``; every other
problem (missing key, wrong rank, obs/action length mismatch, NaN / Inf, decreasing ``episode_ends``, frames out of
order, a dtype or shape that disagrees with the metadata) raises ``DataValidationError`` naming the file, the key
and expected vs actual. Source keys that are not imported are listed in the summary's notes.

h5py (robomimic), pyarrow (LeRobot) and PyAV (LeRobot videos) are optional: ``pip install 'hipolicy_jax[import]'``.
"""

from __future__ import annotations

import dataclasses
import glob
import json
import os
import re
from collections.abc import Callable, Iterable, Sequence

import numpy as np
import zarr

from hipolicy_jax.config import check_action_kinds
from hipolicy_jax.data.replay_buffer import ACTION_KINDS_ATTR, ReplayBuffer
from hipolicy_jax.data.validation import (DataValidationError, check_episode_arrays, check_finite,
                                          check_same_frame_shape, check_source_episode_ends, describe,
                                          too_short_reason)

KeyMap = dict[str, tuple[str, ...]]

FORMATS = ("dp-zarr", "robomimic", "lerobot")
DEFAULT_ACTION_SOURCE = {"dp-zarr": "action", "robomimic": "actions", "lerobot": "action"}
ROBOMIMIC_STATE_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
ROBOMIMIC_IMAGE_KEY = "agentview_image"
# LeRobot bookkeeping columns: read for validation, never imported.
LEROBOT_INDEX_COLUMNS = ("episode_index", "frame_index", "timestamp", "index", "task_index")


# ------------------------------------------------------------------------------------------------------ key maps
def parse_key_map(specs: Sequence[str]) -> KeyMap:
    """``["state=eef_pos,gripper_qpos", "image=img"]`` -> ``{"state": ("eef_pos", "gripper_qpos"), "image": ("img",)}``.

    Raises ``ValueError`` for a spec without ``=``, an empty key or source, or a project key given twice.
    """
    key_map: KeyMap = {}
    for spec in specs:
        key, sep, sources = spec.partition("=")
        key = key.strip()
        parts = tuple(s.strip() for s in sources.split(","))
        if not sep or not key or not all(parts):
            raise ValueError(f"--key-map {spec!r}: expected 'obs_key=src_key' or 'obs_key=src_key1,src_key2' "
                             f"(sources concatenated along the last axis)")
        if key in key_map:
            raise ValueError(f"--key-map {spec!r}: key {key!r} is mapped twice")
        key_map[key] = parts
    return key_map


def format_key_map(key_map: KeyMap) -> str:
    """``'action=actions state=robot0_eef_pos,robot0_gripper_qpos'``."""
    return " ".join(f"{k}={','.join(v)}" for k, v in key_map.items())


def is_image_key(key: str) -> bool:
    """Project keys stored as ``(T, H, W, 3) uint8``: ``image`` and ``image_*``."""
    return key == "image" or key.startswith("image_")


def _with_action(key_map: KeyMap, fmt: str) -> KeyMap:
    if "action" in key_map:
        return dict(key_map)
    return {"action": (DEFAULT_ACTION_SOURCE[fmt],), **key_map}


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


def _concat_sources(parts: list[tuple[str, np.ndarray]], key: str, where: str) -> np.ndarray:
    """One source as is; several concatenated along the last axis (1-D sources count as ``(T, 1)``)."""
    if len(parts) == 1:
        return parts[0][1]
    for name, a in parts:
        if a.ndim == 0:
            raise DataValidationError(f"{where}: source {name!r} of key {key!r} is a scalar ({a.dtype}), expected a "
                                      f"time-first array (T, ...)")
    arrays = [(name, a[:, None] if a.ndim == 1 else a) for name, a in parts]
    ref_name, ref = arrays[0]
    for name, a in arrays[1:]:
        if a.ndim != ref.ndim or a.shape[:-1] != ref.shape[:-1]:
            raise DataValidationError(f"{where}: cannot concatenate sources of key {key!r} along the last axis: "
                                      f"{ref_name!r} is {describe(ref)} but {name!r} is {describe(a)}; expected "
                                      f"equal shapes except the last axis")
    return np.concatenate([a for _, a in arrays], axis=-1)


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


def _check_sources_exist(key_map: KeyMap, available: Sequence[str], where: str) -> None:
    for key, sources in key_map.items():
        for src in sources:
            if src not in available:
                raise DataValidationError(f"{where}: missing key {src!r} (mapped to {key!r}); available keys "
                                          f"{sorted(available)}")


def _unused_note(available: Iterable[str], key_map: KeyMap) -> list[str]:
    used = {s for sources in key_map.values() for s in sources}
    unused = sorted(set(available) - used)
    return [f"source keys not imported: {', '.join(unused)}"] if unused else []


# ---------------------------------------------------------------------------------------------------- DP zarr
def import_dp_zarr(src: str | os.PathLike, key_map: KeyMap | None = None, min_length: int = 1,
                   action_kinds: Sequence[str] | None = None) -> tuple[ReplayBuffer, ImportSummary]:
    """Import a Diffusion Policy zarr ReplayBuffer (directory or ``.zip``) -> ``(buffer, summary)``.

    Default key map: every ``data/<key>`` as is, ``img`` renamed ``image`` (DP's Push-T). Float images are
    converted to uint8 (module docstring). Action kinds: ``action_kinds``, or the root attribute ``action_kinds``
    when the action is imported from ``data/action`` alone.
    """
    src = os.fspath(src)
    if not os.path.exists(src):
        raise FileNotFoundError(f"{src}: no such Diffusion Policy zarr dataset")
    try:
        store = zarr.storage.ZipStore(src, mode="r") if os.path.isfile(src) else src
        root = zarr.open_group(store, mode="r")
    except Exception as e:
        raise DataValidationError(f"{src}: not a zarr group ({type(e).__name__}: {e}); expected a Diffusion Policy "
                                  f"ReplayBuffer with 'data/<key>' and 'meta/episode_ends'") from e
    if "data" not in root:
        raise DataValidationError(f"{src}: missing group 'data'; expected 'data/<key>' arrays")
    if "meta" not in root or "episode_ends" not in root["meta"]:
        raise DataValidationError(f"{src}: missing key 'meta/episode_ends'; expected cumulative episode ends (E,)")
    available = sorted(root["data"].array_keys())
    if key_map is None:
        key_map = {("image" if k == "img" and "image" not in available else k): (k,) for k in available}
        if "action" not in key_map:
            raise DataValidationError(f"{src}: missing key 'data/action'; available keys {available}")
    key_map = _with_action(key_map, "dp-zarr")
    _check_sources_exist(key_map, available, f"{src}: data")

    used = list(dict.fromkeys(s for sources in key_map.values() for s in sources))
    data = {s: root["data"][s] for s in used}  # zarr arrays, read one episode at a time
    ref = key_map["action"][0]
    num_frames = data[ref].shape[0] if data[ref].ndim else 0
    for s, arr in data.items():
        if arr.ndim == 0 or arr.shape[0] != num_frames:
            raise DataValidationError(f"{src}: data/{s} is {arr.dtype} {tuple(arr.shape)}, expected {num_frames} "
                                      f"frames (the length of data/{ref}); obs/action length mismatch")
    lengths = check_source_episode_ends(root["meta"]["episode_ends"][...], num_frames, f"{src}: meta/episode_ends")
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    sources = {k: ",".join(f"data/{s}" for s in v) for k, v in key_map.items()}

    def loader(i: int) -> EpisodeLoader:
        sl = slice(int(starts[i]), int(starts[i] + lengths[i]))
        where = f"{src}: episode {i}"
        return lambda: ({k: _concat_sources([(s, np.asarray(data[s][sl])) for s in v], k, where)
                         for k, v in key_map.items()}, sources)

    episodes = ((f"episode {i}", f"{src}: episode {i} (frames {int(starts[i])}:{int(starts[i] + lengths[i])})",
                 loader(i)) for i in range(len(lengths)))
    notes = (["img renamed image"] if key_map.get("image") == ("img",) else []) + _unused_note(available, key_map)
    said = root.attrs.get(ACTION_KINDS_ATTR) if key_map["action"] == ("action",) else None
    return _assemble(src, "dp-zarr", key_map, min_length, episodes, notes, action_kinds=action_kinds,
                     source_kinds=said)


# -------------------------------------------------------------------------------------------------- robomimic
def robomimic_demo_names(names: Iterable[str]) -> tuple[list[str], list[str]]:
    """``(demos in numeric order, other names)``: ``demo_10`` sorts after ``demo_9``."""
    demos, other = [], []
    for n in names:
        (demos if re.fullmatch(r"demo_\d+", n) else other).append(n)
    return sorted(demos, key=lambda n: int(n.split("_")[1])), sorted(other)


def robomimic_action_kinds(env_args, action_dim: int) -> tuple[str, ...] | None:
    """The kinds robomimic's ``data`` attribute ``env_args`` (JSON) says its ``actions`` are: robosuite's
    ``env_kwargs.controller_configs.control_delta`` true → every dimension a delta but the last (the gripper,
    absolute), false → all absolute; None when it does not say (no such entry, or JSON that does not parse)."""
    try:
        args = json.loads(env_args) if isinstance(env_args, (str, bytes)) else env_args
        delta = args["env_kwargs"]["controller_configs"]["control_delta"]
    except (TypeError, KeyError, ValueError):
        return None
    if not isinstance(delta, bool):
        return None
    return ("delta",) * (action_dim - 1) + ("absolute",) if delta else ("absolute",) * action_dim


def import_robomimic(src: str | os.PathLike, key_map: KeyMap | None = None, min_length: int = 1,
                     action_kinds: Sequence[str] | None = None) -> tuple[ReplayBuffer, ImportSummary]:
    """Import a robomimic hdf5 file -> ``(buffer, summary)``.

    Source keys name ``data/demo_<i>/obs/<key>``, a dataset of the demo group itself (``actions``, ``rewards``,
    ``dones``, ``states``) or a path inside the demo group (``next_obs/<key>``). Demos are read in numeric order.
    Action kinds: ``action_kinds``, or robosuite's ``control_delta`` (``robomimic_action_kinds``) when the action
    is imported from ``actions`` alone.
    """
    h5py = _optional_import("h5py", "importing robomimic hdf5")
    src = os.fspath(src)
    if not os.path.exists(src):
        raise FileNotFoundError(f"{src}: no such robomimic hdf5 file")
    try:
        f = h5py.File(src, "r")
    except OSError as e:
        raise DataValidationError(f"{src}: not a readable HDF5 file ({e}); expected a robomimic dataset with "
                                  f"'data/demo_<i>/obs/<key>' and 'data/demo_<i>/actions'") from e
    with f:
        if "data" not in f:
            raise DataValidationError(f"{src}: missing group 'data'; expected 'data/demo_<i>/obs/<key>' and "
                                      f"'data/demo_<i>/actions'")
        demos, other = robomimic_demo_names(f["data"].keys())
        if not demos:
            raise DataValidationError(f"{src}: no 'data/demo_<i>' groups, found {other}")
        first = f["data"][demos[0]]
        obs_keys = sorted(first["obs"].keys()) if "obs" in first else []
        top_keys = sorted(k for k in first.keys() if isinstance(first[k], h5py.Dataset))
        available = top_keys + obs_keys
        if key_map is None:
            key_map = {"action": ("actions",)}
            state = tuple(k for k in ROBOMIMIC_STATE_KEYS if k in obs_keys)
            if state:
                key_map["state"] = state
            if ROBOMIMIC_IMAGE_KEY in obs_keys:
                key_map["image"] = (ROBOMIMIC_IMAGE_KEY,)
        key_map = _with_action(key_map, "robomimic")

        def read(demo, name: str, key: str, where: str) -> tuple[str, np.ndarray]:
            if "/" in name:
                path = name
            elif name in demo and isinstance(demo[name], h5py.Dataset):
                path = name
            else:
                path = f"obs/{name}"
            if path not in demo or not isinstance(demo[path], h5py.Dataset):
                obs = sorted(demo["obs"].keys()) if "obs" in demo else []
                raise DataValidationError(f"{where}: missing key {path!r} (mapped to {key!r}); demo datasets "
                                          f"{sorted(k for k in demo.keys() if isinstance(demo[k], h5py.Dataset))}, "
                                          f"obs keys {obs}")
            return path, np.asarray(demo[path][...])

        def loader(demo_name: str) -> EpisodeLoader:
            def load():
                demo = f["data"][demo_name]
                where = f"{src}: data/{demo_name}"
                out, sources = {}, {}
                for key, names in key_map.items():
                    parts = [read(demo, n, key, where) for n in names]
                    out[key] = _concat_sources(parts, key, where)
                    sources[key] = ",".join(p for p, _ in parts)
                declared = demo.attrs.get("num_samples")
                if declared is not None and "action" in out and out["action"].ndim and \
                        int(declared) != out["action"].shape[0]:
                    raise DataValidationError(f"{where}: attribute num_samples is {int(declared)} but key 'action' "
                                              f"(from {sources['action']}) has {out['action'].shape[0]} frames; "
                                              f"expected them equal")
                return out, sources
            return load

        episodes = ((d, f"{src}: data/{d}", loader(d)) for d in demos)
        notes = ([f"ignored non-demo entries in data/: {', '.join(other)}"] if other else []) \
            + _unused_note(available, key_map)
        said = None
        if key_map["action"] == ("actions",) and "actions" in first and first["actions"].ndim == 2:
            said = robomimic_action_kinds(f["data"].attrs.get("env_args"), int(first["actions"].shape[1]))
        return _assemble(src, "robomimic", key_map, min_length, episodes, notes, action_kinds=action_kinds,
                         source_kinds=said)


# ---------------------------------------------------------------------------------------------------- LeRobot
LEROBOT_VERSIONS = "v2.x (v2.0, v2.1: one parquet file per episode) and v3.0 (episodes grouped in " \
                   "chunk-NNN/file-NNN parquet and mp4 files)"


def _lerobot_layout(version: str) -> str | None:
    """``'v2'`` or ``'v3'`` for a supported ``codebase_version``, else None."""
    if re.fullmatch(r"v2(\.\d+)*", version):
        return "v2"
    if re.fullmatch(r"v3\.0(\.0)*", version):
        return "v3"
    return None


def _read_json(path: str) -> dict:
    if not os.path.isfile(path):
        raise DataValidationError(f"{path}: missing; expected a LeRobot dataset folder ({LEROBOT_VERSIONS}) with "
                                  f"meta/info.json")
    try:
        with open(path) as fh:
            return json.load(fh)
    except json.JSONDecodeError as e:
        raise DataValidationError(f"{path}: not valid JSON ({e})") from e


@dataclasses.dataclass(frozen=True)
class _LeRobotEpisode:
    """Where one LeRobot episode lives, from the dataset's metadata (either layout).

    Attributes:
      index: its ``episode_index``.
      data_path: the parquet file holding its frames.
      rows: ``(start, stop)`` rows of that file (v3.0, several episodes a file); None: the whole file (v2.x).
      length: its declared number of frames, checked against the rows read; None when not declared.
      first_index: its first global frame ``index`` (v3.0 ``dataset_from_index``); None: not checked.
      video: video key -> ``(mp4 path, the episode's start in that file in seconds)``.
    """

    index: int
    data_path: str
    rows: tuple[int, int] | None
    length: int | None
    first_index: int | None
    video: Callable[[str], tuple[str, float]]

    @property
    def where(self) -> str:
        rows = "" if self.rows is None else f", rows {self.rows[0]}:{self.rows[1]}"
        return f"{self.data_path} (episode {self.index}{rows})"


def _format_path(template, field: str, info_path: str, example: str, **fields) -> str:
    """``info[field].format(**fields)``; a missing or mismatched template names the field and what it should hold."""
    if not isinstance(template, str) or not template:
        raise DataValidationError(f"{info_path}: missing key {field!r}; expected a path template like {example!r}")
    try:
        return template.format(**fields)
    except (KeyError, IndexError, ValueError) as e:
        raise DataValidationError(f"{info_path}: {field} {template!r} does not format with {sorted(fields)} "
                                  f"({type(e).__name__}: {e}); expected a template like {example!r}") from e


def _lerobot_v2_episodes(root: str, info: dict, info_path: str) -> list[_LeRobotEpisode]:
    """v2.x: one parquet file (and one mp4 per camera) per episode, named by ``data_path`` / ``video_path``."""
    chunks_size = int(info.get("chunks_size", 1000))
    data_example = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
    video_example = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"

    def video(ep: int) -> Callable[[str], tuple[str, float]]:
        def path(key: str) -> tuple[str, float]:
            if not info.get("video_path"):
                raise DataValidationError(f"{info_path}: feature {key!r} has dtype 'video' but info has no "
                                          f"'video_path'")
            return os.path.join(root, _format_path(info["video_path"], "video_path", info_path, video_example,
                                                   episode_chunk=ep // chunks_size, video_key=key,
                                                   episode_index=ep)), 0.0
        return path

    return [_LeRobotEpisode(ep, os.path.join(root, _format_path(info["data_path"], "data_path", info_path,
                                                                data_example, episode_chunk=ep // chunks_size,
                                                                episode_index=ep)),
                            None, declared, None, video(ep))
            for ep, declared in _lerobot_episodes(root, info)]


def _lerobot_episodes(root: str, info: dict) -> list[tuple[int, int | None]]:
    """v2.x: ``[(episode_index, declared length or None)]`` from ``meta/episodes.jsonl``, else ``total_episodes``."""
    path = os.path.join(root, "meta", "episodes.jsonl")
    if os.path.isfile(path):
        out = []
        with open(path) as fh:
            for line_no, line in enumerate(fh, 1):
                if not line.strip():
                    continue
                try:
                    row = json.loads(line)
                    out.append((int(row["episode_index"]), int(row["length"]) if "length" in row else None))
                except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
                    raise DataValidationError(f"{path}: line {line_no}: expected a JSON object with an integer "
                                              f"'episode_index' ({type(e).__name__}: {e})") from e
        return sorted(out)
    if "total_episodes" not in info:
        raise DataValidationError(f"{os.path.join(root, 'meta', 'info.json')}: missing key 'total_episodes' (and "
                                  f"no meta/episodes.jsonl); expected the number of episodes")
    return [(i, None) for i in range(int(info["total_episodes"]))]


# v3.0 meta/episodes columns locating an episode's frames (LeRobot's LeRobotDatasetMetadata._save_episode_metadata).
LEROBOT_V3_EPISODE_COLUMNS = ("episode_index", "dataset_from_index", "dataset_to_index", "data/chunk_index",
                              "data/file_index")


def _read_parquet(pq, path: str, columns: Sequence[str] | None = None, what: str = ""):
    """A parquet table (``columns`` of it); an unreadable file is a ``DataValidationError`` naming it."""
    import pyarrow as pa

    try:
        return pq.read_table(path, columns=None if columns is None else list(columns))
    except (pa.ArrowException, OSError) as e:
        raise DataValidationError(f"{path}: not a readable parquet file ({type(e).__name__}: {e}); expected "
                                  f"{what or 'a LeRobot parquet file'}") from e


def _int_column(table, name: str, path: str) -> np.ndarray:
    arr = _arrow_to_numpy(table.column(name), f"{path}: column {name!r}")
    if arr.dtype.kind not in "iu" or arr.ndim != 1:
        raise DataValidationError(f"{path}: column {name!r} is {describe(arr)}, expected one integer per episode")
    return arr.astype(np.int64)


def _lerobot_v3_episodes(root: str, info: dict, info_path: str, pq) -> list[_LeRobotEpisode]:
    """v3.0: episodes listed in ``meta/episodes/chunk-NNN/file-NNN.parquet`` (one row each) with their global frame
    range ``dataset_from_index:dataset_to_index`` in the parquet file ``data/chunk_index``, ``data/file_index`` (its
    rows follow those of the earlier files) and, per camera, the mp4 file ``videos/<key>/chunk_index``,
    ``file_index`` and the episode's start ``videos/<key>/from_timestamp`` in it."""
    meta_dir = os.path.join(root, "meta", "episodes")
    meta_files = sorted(glob.glob(os.path.join(glob.escape(meta_dir), "*", "*.parquet")))
    if not meta_files:
        raise DataValidationError(f"{meta_dir}: missing; expected the per-episode metadata "
                                  f"meta/episodes/chunk-NNN/file-NNN.parquet of a LeRobot v3.0 dataset "
                                  f"(codebase_version in {info_path})")
    rows: dict[int, dict] = {}
    for path in meta_files:
        names = _read_parquet_schema(pq, path, "LeRobot v3.0 episode metadata")
        for c in LEROBOT_V3_EPISODE_COLUMNS:
            if c not in names:
                raise DataValidationError(f"{path}: missing column {c!r}; expected the LeRobot v3.0 episode columns "
                                          f"{list(LEROBOT_V3_EPISODE_COLUMNS)}")
        wanted = [c for c in names if c in LEROBOT_V3_EPISODE_COLUMNS or c == "length" or c.startswith("videos/")]
        table = _read_parquet(pq, path, wanted, "LeRobot v3.0 episode metadata")
        cols = {c: _int_column(table, c, path) for c in wanted if not c.startswith("videos/")}
        # videos/<key>/... columns are read when that camera is imported (a camera left out may have gaps)
        videos = {c: table.column(c) for c in wanted if c.startswith("videos/")}
        for i in range(table.num_rows):
            row = {**{c: v[i] for c, v in cols.items()}, "_videos": (videos, i)}
            ep = int(row["episode_index"])
            if ep in rows:
                raise DataValidationError(f"{path}: episode_index {ep} is listed twice (also in {rows[ep]['_meta']}); "
                                          f"expected each episode once")
            start, stop = int(row["dataset_from_index"]), int(row["dataset_to_index"])
            if start < 0 or stop < start:
                raise DataValidationError(f"{path}: episode {ep}: dataset_from_index:dataset_to_index is "
                                          f"{start}:{stop}, expected 0 <= from <= to")
            if "length" in row and int(row["length"]) != stop - start:
                raise DataValidationError(f"{path}: episode {ep}: column 'length' is {int(row['length'])}, expected "
                                          f"{stop - start} (dataset_to_index {stop} - dataset_from_index {start})")
            rows[ep] = {**row, "_meta": path}
    if "total_episodes" in info and int(info["total_episodes"]) != len(rows):
        listed = ", ".join(os.path.relpath(f, meta_dir) for f in meta_files)
        raise DataValidationError(f"{info_path}: total_episodes is {int(info['total_episodes'])}, but {meta_dir} "
                                  f"lists {len(rows)} episodes ({listed}); expected every episode listed once (is "
                                  f"an episodes file missing?)")

    data_example = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    video_example = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    # Data files in (chunk, file) order; each one's first row is the global frame index after the earlier files'.
    files = sorted({(int(r["data/chunk_index"]), int(r["data/file_index"])) for r in rows.values()})
    offsets: dict[tuple[int, int], tuple[str, int, int]] = {}
    offset = 0
    for chunk, file in files:
        path = os.path.join(root, _format_path(info["data_path"], "data_path", info_path, data_example,
                                               chunk_index=chunk, file_index=file))
        if not os.path.isfile(path):
            eps = sorted(ep for ep, r in rows.items() if (r["data/chunk_index"], r["data/file_index"]) == (chunk, file))
            raise DataValidationError(f"{path}: missing parquet file of episodes {eps} (data/chunk_index {chunk}, "
                                      f"data/file_index {file} in {rows[eps[0]]['_meta']}; data_path "
                                      f"{info['data_path']!r})")
        try:
            num_rows = pq.read_metadata(path).num_rows
        except Exception as e:  # pyarrow raises ArrowInvalid / OSError for a damaged footer
            raise DataValidationError(f"{path}: not a readable parquet file ({type(e).__name__}: {e})") from e
        offsets[(chunk, file)] = (path, offset, num_rows)
        offset += num_rows

    def video(row: dict) -> Callable[[str], tuple[str, float]]:
        def path(key: str) -> tuple[str, float]:
            videos, i = row["_videos"]
            cols = [f"videos/{key}/chunk_index", f"videos/{key}/file_index", f"videos/{key}/from_timestamp"]
            values = []
            for c, kind in zip(cols, (int, int, float)):
                if c not in videos:
                    raise DataValidationError(f"{row['_meta']}: missing column {c!r} of video feature {key!r}; "
                                              f"expected {cols}")
                value = videos[c][i].as_py()
                if not isinstance(value, (int, float)) or isinstance(value, bool) or \
                        (kind is int and not float(value).is_integer()) or not np.isfinite(value):
                    raise DataValidationError(f"{row['_meta']}: episode {int(row['episode_index'])}: column {c!r} "
                                              f"holds {value!r}, expected {'an integer' if kind is int else 'seconds'}")
                values.append(kind(value))
            if not info.get("video_path"):
                raise DataValidationError(f"{info_path}: feature {key!r} has dtype 'video' but info has no "
                                          f"'video_path'")
            return os.path.join(root, _format_path(info["video_path"], "video_path", info_path, video_example,
                                                   video_key=key, chunk_index=values[0],
                                                   file_index=values[1])), values[2]
        return path

    episodes = []
    for ep in sorted(rows):
        row = rows[ep]
        path, first, num_rows = offsets[(int(row["data/chunk_index"]), int(row["data/file_index"]))]
        start, stop = int(row["dataset_from_index"]), int(row["dataset_to_index"])
        a, b = start - first, stop - first
        if a < 0 or b > num_rows:
            raise DataValidationError(f"{row['_meta']}: episode {ep}: dataset_from_index:dataset_to_index "
                                      f"{start}:{stop} is rows {a}:{b} of {path}, which holds {num_rows} rows "
                                      f"(dataset frames {first}:{first + num_rows}); expected the episode's frames "
                                      f"inside its parquet file")
        episodes.append(_LeRobotEpisode(ep, path, (a, b), None, start, video(row)))
    return episodes


def _read_parquet_schema(pq, path: str, what: str) -> list[str]:
    try:
        return list(pq.read_schema(path).names)
    except Exception as e:  # pyarrow raises ArrowInvalid / OSError for a file that is not parquet
        raise DataValidationError(f"{path}: not a readable parquet file ({type(e).__name__}: {e}); expected "
                                  f"{what}") from e


def _arrow_to_numpy(column, where: str) -> np.ndarray:
    """A parquet column (scalars or nested equal-length lists) -> ``(n, *shape)``; raises on nulls or ragged lists."""
    import pyarrow as pa
    import pyarrow.compute as pc

    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    n = len(arr)
    if arr.null_count:
        raise DataValidationError(f"{where}: contains {arr.null_count} null values; expected a value in every frame")
    shape = []
    while pa.types.is_list(arr.type) or pa.types.is_large_list(arr.type) or pa.types.is_fixed_size_list(arr.type):
        lengths = np.asarray(pc.list_value_length(arr).to_numpy(zero_copy_only=False))
        if lengths.size and (lengths != lengths[0]).any():
            raise DataValidationError(f"{where}: ragged lists of lengths {sorted(set(lengths.tolist()))}; expected "
                                      f"the same length in every frame")
        shape.append(int(lengths[0]) if lengths.size else 0)
        arr = arr.flatten()
        if arr.null_count:
            raise DataValidationError(f"{where}: contains null values; expected a value in every frame")
    if not (pa.types.is_integer(arr.type) or pa.types.is_floating(arr.type) or pa.types.is_boolean(arr.type)):
        raise DataValidationError(f"{where}: unsupported arrow type {column.type}; expected numbers or lists of "
                                  f"numbers")
    return np.asarray(arr.to_numpy(zero_copy_only=False)).reshape(n, *shape)


def _decode_video(path: str, timestamps: np.ndarray, fps: float, where: str, start: float = 0.0) -> np.ndarray:
    """Frames of ``path`` at ``start + timestamps`` seconds (nearest frame, within half a frame period)
    -> ``(n, H, W, 3) uint8``.

    ``start`` is the episode's first frame in a video that holds several episodes (v3.0 ``from_timestamp``): the
    decoder seeks to the key frame before it and decodes only the episode's span.
    """
    av = _optional_import("av", "decoding LeRobot videos")
    if not os.path.isfile(path):
        raise DataValidationError(f"{where}: missing video file {path}")
    tolerance = 0.5 / fps
    wanted = start + np.asarray(timestamps, np.float64)
    lo, hi = float(wanted.min()) - tolerance, float(wanted.max()) + tolerance
    decoded = []
    try:
        with av.open(path) as container:
            stream = container.streams.video[0]
            seek = lo > 0 and stream.time_base is not None
            if seek:
                container.seek(int(lo / stream.time_base), stream=stream, backward=True, any_frame=False)
            for i, fr in enumerate(container.decode(stream)):
                if fr.time is None and seek:
                    raise DataValidationError(f"{path}: frame {i} after seeking to {lo:.4f}s has no timestamp; "
                                              f"expected timed frames")
                t = float(fr.time) if fr.time is not None else i / fps
                if t > hi:
                    break
                if t >= lo:
                    decoded.append((t, fr.to_ndarray(format="rgb24")))
    except av.error.FFmpegError as e:
        raise DataValidationError(f"{path}: cannot decode video ({e})") from e
    if not decoded:
        raise DataValidationError(f"{path}: no video frames at {lo + tolerance:.4f}s-{hi - tolerance:.4f}s; expected "
                                  f"{len(timestamps)} frames for {where}")
    times = np.asarray([t for t, _ in decoded])
    nearest = np.abs(times[None, :] - wanted[:, None]).argmin(axis=1)
    error = np.abs(times[nearest] - wanted)
    if (error > tolerance).any():
        i = int(np.argmax(error > tolerance))
        in_file = f" (+ from_timestamp {start:.4f}s = {wanted[i]:.4f}s in the file)" if start else ""
        raise DataValidationError(f"{path}: no video frame within {tolerance:.4f}s of frame {i}'s timestamp "
                                  f"{timestamps[i]:.4f}s{in_file} (nearest {times[nearest[i]]:.4f}s; decoded "
                                  f"{len(times)} frames at {times[0]:.4f}s-{times[-1]:.4f}s) for {where}")
    return np.stack([decoded[j][1] for j in nearest])


def _decode_images(column, where: str) -> np.ndarray:
    """A LeRobot ``image`` column (structs with encoded ``bytes``) -> ``(n, H, W, C)``."""
    import imageio.v3 as iio

    frames = []
    for i, item in enumerate(column.to_pylist()):
        data = item.get("bytes") if isinstance(item, dict) else None
        if not data:
            raise DataValidationError(f"{where}: frame {i} has no encoded image bytes; expected a struct "
                                      f"{{'bytes': <png/jpeg>, 'path': ...}}")
        img = np.asarray(iio.imread(data))
        img = img[..., None] if img.ndim == 2 else img
        if frames and img.shape != frames[0].shape:
            raise DataValidationError(f"{where}: frame {i} decodes to {describe(img)}, expected "
                                      f"{describe(frames[0])} as frame 0")
        frames.append(img)
    return np.stack(frames)


def _check_feature(arr: np.ndarray, feature: dict, where: str) -> np.ndarray:
    """Match a column to its ``meta/info.json`` feature: declared dtype and per-frame shape ([1] -> (n, 1))."""
    shape = tuple(int(d) for d in feature.get("shape", arr.shape[1:]))
    if arr.ndim == 1 and shape == (1,):
        arr = arr[:, None]
    if tuple(arr.shape[1:]) != shape:
        raise DataValidationError(f"{where}: frames of shape {tuple(arr.shape[1:])}, expected {shape} as declared in "
                                  f"meta/info.json")
    dtype = feature.get("dtype")
    if dtype in (None, "video", "image", "string"):
        return arr
    try:
        declared = np.dtype(dtype)
    except TypeError as e:
        raise DataValidationError(f"{where}: meta/info.json declares dtype {dtype!r}, not a numeric dtype") from e
    if declared != arr.dtype:
        raise DataValidationError(f"{where}: dtype {arr.dtype}, expected {dtype} as declared in meta/info.json")
    return arr


def import_lerobot(src: str | os.PathLike, key_map: KeyMap | None = None, min_length: int = 1,
                   action_kinds: Sequence[str] | None = None) -> tuple[ReplayBuffer, ImportSummary]:
    """Import a local LeRobot dataset folder, v2.x or v3.0 (``codebase_version`` in ``meta/info.json``)
    -> ``(buffer, summary)``.

    Layouts: v2.x has one parquet file (and one mp4 per camera) per episode, listed in ``meta/episodes.jsonl``;
    v3.0 groups episodes in ``data/chunk-NNN/file-NNN.parquet`` and ``videos/<key>/chunk-NNN/file-NNN.mp4`` files,
    each episode located by its row in ``meta/episodes/chunk-NNN/file-NNN.parquet`` (``dataset_from_index``,
    ``dataset_to_index``, ``data/chunk_index``, ``data/file_index``, ``videos/<key>/from_timestamp`` ...). Any other
    version is refused, naming the supported ones.

    Checks per episode, in both layouts: its rows lie inside its parquet file (v3.0), ``episode_index`` equals the
    episode, the global ``index`` runs ``dataset_from_index..dataset_to_index - 1`` (v3.0), ``frame_index`` is
    ``0..n-1``, ``timestamp`` strictly increases, the length matches the metadata, and each column's dtype and
    per-frame shape match ``features`` in ``meta/info.json``. Video frames are decoded at the parquet timestamps
    (plus the episode's ``from_timestamp`` in a v3.0 file): nearest frame, within half a period of ``fps``.
    """
    pq = _optional_import("pyarrow.parquet", "importing LeRobot datasets")
    root = os.fspath(src)
    if not os.path.isdir(root):
        raise FileNotFoundError(f"{root}: no such LeRobot dataset folder")
    info_path = os.path.join(root, "meta", "info.json")
    info = _read_json(info_path)
    version = str(info.get("codebase_version", ""))
    layout = _lerobot_layout(version)
    if layout is None:
        raise DataValidationError(f"{info_path}: codebase_version {version or None!r} is not supported; supported "
                                  f"versions: {LEROBOT_VERSIONS}")
    for field in ("fps", "features", "data_path"):
        if field not in info:
            raise DataValidationError(f"{info_path}: missing key {field!r}")
    fps, features = float(info["fps"]), info["features"]
    if layout == "v2":
        episodes_list = _lerobot_v2_episodes(root, info, info_path)
        listed_in = os.path.join(root, "meta", "episodes.jsonl")
    else:
        episodes_list = _lerobot_v3_episodes(root, info, info_path, pq)
        listed_in = os.path.join(root, "meta", "episodes")
    if not episodes_list:
        raise DataValidationError(f"{listed_in}: no episodes listed; expected at least one")

    available = sorted(k for k in features if k not in LEROBOT_INDEX_COLUMNS)
    num_files = len({e.data_path for e in episodes_list})
    notes = [] if layout == "v2" else [f"LeRobot {version}: {len(episodes_list)} episodes in {num_files} parquet "
                                       f"file{'s' if num_files != 1 else ''}"]
    if key_map is None:
        key_map = {}
        if "observation.state" in features:
            key_map["state"] = ("observation.state",)
        key_map["action"] = ("action",)
        cameras = [k for k, f in features.items() if f.get("dtype") in ("video", "image")]
        present = []
        for cam in cameras:
            vpath = episodes_list[0].video(cam)[0] if features[cam]["dtype"] == "video" else None
            if vpath is not None and not os.path.isfile(vpath):
                notes.append(f"video feature {cam} not imported: {vpath} missing")
            else:
                present.append(cam)
        for cam in present:
            key_map["image" if len(present) == 1 else f"image_{cam.rsplit('.', 1)[-1]}"] = (cam,)
    key_map = _with_action(key_map, "lerobot")
    _check_sources_exist(key_map, list(features), f"{info_path}: features")
    used = list(dict.fromkeys(s for sources in key_map.values() for s in sources))
    columns = [s for s in used if features[s].get("dtype") != "video"]
    cache: dict[str, tuple[list[str], object]] = {}  # the last parquet file read (v3.0: several episodes each)

    def read_table(path: str, ep: int):
        if path not in cache:
            cache.clear()
            if not os.path.isfile(path):
                raise DataValidationError(f"{path}: missing parquet file of episode {ep} (data_path "
                                          f"{info['data_path']!r})")
            names = _read_parquet_schema(pq, path, "LeRobot frame data")
            for c in columns:
                if c not in names:
                    raise DataValidationError(f"{path}: missing column {c!r}; columns {names}")
            index_cols = [c for c in ("episode_index", "index", "frame_index", "timestamp") if c in names]
            cache[path] = (index_cols, _read_parquet(pq, path, dict.fromkeys(columns + index_cols),
                                                     "LeRobot frame data"))
        return cache[path]

    def loader(episode: _LeRobotEpisode) -> EpisodeLoader:
        def load():
            ep, path = episode.index, episode.data_path
            index_cols, table = read_table(path, ep)
            row0 = 0
            if episode.rows is not None:
                row0 = episode.rows[0]
                table = table.slice(row0, episode.rows[1] - row0)
            n = table.num_rows
            label = episode.where if episode.rows is not None else path

            def column(name: str) -> np.ndarray:
                return _arrow_to_numpy(table.column(name), f"{label}: column {name!r}").ravel()

            if "episode_index" in index_cols:
                got = column("episode_index")
                if (got != ep).any():
                    raise DataValidationError(f"{label}: column 'episode_index' holds {sorted(set(got.tolist()))}, "
                                              f"expected only {ep}")
            if "index" in index_cols and episode.first_index is not None:
                got, expected = column("index"), np.arange(episode.first_index, episode.first_index + n)
                if not np.array_equal(got, expected):
                    bad = int(np.argmax(got != expected))
                    raise DataValidationError(f"{label}: column 'index' is not the episode's dataset_from_index.."
                                              f"dataset_to_index - 1 = {expected[0]}..{expected[-1]}: row "
                                              f"{row0 + bad} holds {int(got[bad])}, expected {int(expected[bad])}")
            if "frame_index" in index_cols:
                got = column("frame_index")
                if not np.array_equal(got, np.arange(n)):
                    bad = int(np.argmax(got != np.arange(n)))
                    raise DataValidationError(f"{label}: column 'frame_index' is not 0..{n - 1} in order: row "
                                              f"{row0 + bad} holds {int(got[bad])}, expected {bad}")
            if "timestamp" in index_cols:
                ts = column("timestamp").astype(np.float64)
                if n > 1 and not (np.diff(ts) > 0).all():
                    bad = int(np.argmax(np.diff(ts) <= 0)) + 1
                    raise DataValidationError(f"{label}: column 'timestamp' must strictly increase: row {row0 + bad} "
                                              f"is {ts[bad]:.6f}s after {ts[bad - 1]:.6f}s")
            else:
                ts = np.arange(n, dtype=np.float64) / fps
            if episode.length is not None and episode.length != n:
                raise DataValidationError(f"{path}: {n} rows, expected {episode.length} (the length of episode {ep} "
                                          f"in meta/episodes.jsonl)")
            arrays, sources = {}, {}
            for s in used:
                feature = features[s]
                if feature.get("dtype") == "video":
                    vpath, start = episode.video(s)
                    arrays[s] = _decode_video(vpath, ts, fps, f"{label}: feature {s!r}", start) if n else \
                        np.zeros((0, *feature.get("shape", (0, 0, 3))), np.uint8)
                    sources[s] = os.path.relpath(vpath, root)
                elif feature.get("dtype") == "image":
                    arrays[s] = _decode_images(table.column(s), f"{label}: column {s!r}")
                    sources[s] = s
                else:
                    arrays[s] = _check_feature(_arrow_to_numpy(table.column(s), f"{label}: column {s!r}"), feature,
                                               f"{label}: column {s!r}")
                    sources[s] = s
                if feature.get("dtype") in ("video", "image") and n:
                    _check_image_shape(arrays[s], feature, f"{label}: feature {s!r} ({sources[s]})")
            where = episode.where
            out = {k: _concat_sources([(s, arrays[s]) for s in v], k, where) for k, v in key_map.items()}
            return out, {k: ",".join(sources[s] for s in v) for k, v in key_map.items()}
        return load

    episodes = ((f"episode {e.index}", e.where, loader(e)) for e in episodes_list)
    notes += _unused_note(available, key_map)
    return _assemble(root, "lerobot", key_map, min_length, episodes, notes, action_kinds=action_kinds)


def _check_image_shape(frames: np.ndarray, feature: dict, where: str) -> None:
    """Decoded frames ``(n, H, W, C)`` against the declared shape, ``[H, W, C]`` or ``[C, H, W]``."""
    shape = tuple(int(d) for d in feature.get("shape", ()))
    got = tuple(frames.shape[1:])
    if shape and got != shape and (len(shape) != 3 or got != (shape[1], shape[2], shape[0])):
        raise DataValidationError(f"{where}: decoded frames of shape {got}, expected {shape} as declared in "
                                  f"meta/info.json")


# --------------------------------------------------------------------------------------------------- dispatch
IMPORTERS = {"dp-zarr": import_dp_zarr, "robomimic": import_robomimic, "lerobot": import_lerobot}


def import_dataset(fmt: str, src: str | os.PathLike, key_map: KeyMap | None = None,
                   min_length: int = 1, action_kinds: Sequence[str] | None = None
                   ) -> tuple[ReplayBuffer, ImportSummary]:
    """Import ``src`` in format ``fmt`` (one of ``FORMATS``) -> ``(buffer, summary)``; ``action_kinds``: the actions'
    kinds where the source does not say (module docstring)."""
    if fmt not in IMPORTERS:
        raise ValueError(f"format: expected one of {list(FORMATS)}, got {fmt!r}")
    return IMPORTERS[fmt](src, key_map=key_map, min_length=min_length, action_kinds=action_kinds)
