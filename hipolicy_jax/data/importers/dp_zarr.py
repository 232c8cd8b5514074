"""Import a Diffusion Policy zarr ReplayBuffer (a directory, zarr format 2 or 3, or a ``.zip``).

Layout: ``data/<key>`` time-first arrays and ``meta/episode_ends``. Default key map: every data key as is, with DP's
``img`` renamed ``image``. Action kinds: the caller's, or the zarr root attribute ``action_kinds`` (this project's
and the Meta-World bridge's buffers) when the action is ``data/action`` alone.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np
import zarr

from hipolicy_jax.data.importers.assemble import EpisodeLoader, ImportSummary, _assemble
from hipolicy_jax.data.importers.keymap import (KeyMap, _check_sources_exist, _concat_sources, _unused_note,
                                                _with_action)
from hipolicy_jax.data.replay_buffer import ACTION_KINDS_ATTR, ReplayBuffer
from hipolicy_jax.data.validation import DataValidationError, check_source_episode_ends


def import_dp_zarr(src: str | os.PathLike, key_map: KeyMap | None = None, min_length: int = 1,
                   action_kinds: Sequence[str] | None = None) -> tuple[ReplayBuffer, ImportSummary]:
    """Import a Diffusion Policy zarr ReplayBuffer (directory or ``.zip``) -> ``(buffer, summary)``.

    Default key map: every ``data/<key>`` as is, ``img`` renamed ``image`` (DP's Push-T). Float images are
    converted to uint8 (``assemble``). Action kinds: ``action_kinds``, or the root attribute ``action_kinds``
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
    key_map = _with_action(key_map, "action")
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
