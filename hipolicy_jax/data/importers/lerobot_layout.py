"""Where a local LeRobot dataset's episodes live (v2.x and v3.0 layouts), and reading its JSON and parquet files.

``meta/info.json`` gives ``codebase_version``, ``fps``, ``features`` and the ``data_path`` / ``video_path``
templates. v2.x (``_lerobot_v2_episodes``): one parquet file per episode and, for ``video`` features, one mp4 per
episode and camera, episodes listed in ``meta/episodes.jsonl`` (else ``total_episodes``). v3.0
(``_lerobot_v3_episodes``): episodes grouped in ``data/chunk-NNN/file-NNN.parquet`` and
``videos/<key>/chunk-NNN/file-NNN.mp4`` files, each located by its row of ``meta/episodes/chunk-NNN/file-NNN.parquet``.
Either gives one ``_LeRobotEpisode`` per episode. pyarrow is optional (``pip install 'hipolicy_jax[import]'``).
"""

from __future__ import annotations

import dataclasses
import glob
import json
import os
import re
from collections.abc import Callable, Sequence

import numpy as np

from hipolicy_jax.data.validation import DataValidationError, describe

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
