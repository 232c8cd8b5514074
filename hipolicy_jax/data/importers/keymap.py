"""Key maps: which source keys an importer reads into which project keys, and how several sources combine.

A key map is ``{project_key: (source_key, ...)}``; several source keys are concatenated along the last axis
(``state=robot0_eef_pos,robot0_gripper_qpos``; ``_concat_sources``). An explicit key map imports exactly its keys,
plus ``action`` from the format's default action source when it does not name ``action`` (``_with_action``). Project
keys ``image`` and ``image_*`` are images (``is_image_key``), stored as ``(T, H, W, 3) uint8``. Every source key a
map names must exist (``_check_sources_exist``); source keys not imported are listed in the summary's notes
(``_unused_note``).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from hipolicy_jax.data.validation import DataValidationError, describe

KeyMap = dict[str, tuple[str, ...]]


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


def _with_action(key_map: KeyMap, action_source: str) -> KeyMap:
    """``key_map`` with ``action`` from ``action_source`` (the format's default) when it does not name ``action``."""
    if "action" in key_map:
        return dict(key_map)
    return {"action": (action_source,), **key_map}


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
