"""Import a local LeRobot dataset folder, v2.x or v3.0 (pyarrow, and PyAV for videos; optional:
``pip install 'hipolicy_jax[import]'``).

The layouts are read by ``lerobot_layout``; video frames are decoded and matched by timestamp, image columns decoded
and columns checked against ``meta/info.json`` by ``lerobot_frames``. Default key map: ``state=observation.state``,
``action=action`` and the camera feature as ``image`` (several cameras: ``image_<name>`` each). The source does not
say its action kinds: the buffer records the caller's, or none.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from hipolicy_jax.data.importers.assemble import EpisodeLoader, ImportSummary, _assemble, _optional_import
from hipolicy_jax.data.importers.keymap import KeyMap, _check_sources_exist, _concat_sources, _unused_note, _with_action
from hipolicy_jax.data.importers.lerobot_frames import (_check_feature, _check_image_shape, _decode_images,
                                                        _decode_video)
from hipolicy_jax.data.importers.lerobot_layout import (LEROBOT_VERSIONS, _arrow_to_numpy, _lerobot_layout,
                                                        _lerobot_v2_episodes, _lerobot_v3_episodes, _LeRobotEpisode,
                                                        _read_json, _read_parquet, _read_parquet_schema)
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.data.validation import DataValidationError

# LeRobot bookkeeping columns: read for validation, never imported.
LEROBOT_INDEX_COLUMNS = ("episode_index", "frame_index", "timestamp", "index", "task_index")


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
    key_map = _with_action(key_map, "action")
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
