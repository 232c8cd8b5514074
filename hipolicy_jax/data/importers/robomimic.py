"""Import a robomimic hdf5 file (h5py, optional: ``pip install 'hipolicy_jax[import]'``).

Layout: ``data/demo_<i>/obs/<key>`` and ``data/demo_<i>/actions``, demos in numeric order (``demo_10`` after
``demo_9``). Default key map: ``action=actions``, ``state=robot0_eef_pos,robot0_eef_quat,robot0_gripper_qpos``
(those present) and ``image=agentview_image`` (if present). Action kinds: the caller's, or robosuite's controller
(``data`` attribute ``env_args``: ``env_kwargs.controller_configs.control_delta``; true: every dimension a delta but
the last, the gripper, absolute; false: all absolute) when the action is the default ``actions``.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable, Sequence

import numpy as np

from hipolicy_jax.data.importers.assemble import EpisodeLoader, ImportSummary, _assemble, _optional_import
from hipolicy_jax.data.importers.keymap import KeyMap, _concat_sources, _unused_note, _with_action
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.data.validation import DataValidationError

ROBOMIMIC_STATE_KEYS = ("robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")
ROBOMIMIC_IMAGE_KEY = "agentview_image"


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
        key_map = _with_action(key_map, "actions")

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
