"""The DemoSpeedup stage on disk: a demo buffer and a trained proxy run in, the accelerated buffer out.

``speedup_demos(data, proxy, out, cfg)`` reads the zarr buffer at ``data`` (``ReplayBuffer.load``), loads the proxy
run (``runs.store.load_run``), refuses a proxy that does not fit the demos in one line (``check_proxy_fits``),
measures every frame's entropy under each candidate bandwidth and takes the one the ladder rule chooses
(``entropy.ladder_entropies``, ``choose_bandwidth``), accelerates every episode (``retime.accelerate``) and
writes the result at ``out`` in the same layout (``data/<key>``, ``meta/episode_ends``), through a temporary sibling
renamed into place. The source's root attributes are copied (``action_kinds`` among them), and the root attribute
``speedup`` (``SPEEDUP_ATTR``) records what was done: method, source, proxy run and step, task, config, sampler
settings, seed, the action kinds used, per-episode original and new lengths, kept frames, segments with their rates,
the per-frame entropies (source timeline) and the fraction of them at the estimator's ceiling log N
(``entropy.saturated_fraction``: near 1, the bandwidth is too small for the proxy's samples), the bandwidth used and
that fraction under every candidate.

A buffer's task (``buffer_task``): its root attribute ``task``, else the ``task`` of its ``speedup`` record, else the
task its file name starts with (``data/<task>_...zarr``, as ``envs.demos.default_data_path`` names buffers), else
unknown (then only the shapes are checked).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from collections.abc import Callable

import jax
import numpy as np
import zarr

from hipolicy_jax.data.replay_buffer import ACTION_KINDS_ATTR, ReplayBuffer
from hipolicy_jax.data.windowing import check_recorded_kinds
from hipolicy_jax.envs import TASKS
from hipolicy_jax.jsonio import one_line
from hipolicy_jax.runs.store import Run, load_run, run_inference
from hipolicy_jax.speedup.config import SpeedupConfig
from hipolicy_jax.speedup.entropy import choose_bandwidth, ladder_entropies, saturated_fraction
from hipolicy_jax.speedup.retime import accelerate

SPEEDUP_ATTR = "speedup"  # the accelerated buffer's root attribute: the record of what was done
METHOD = "DemoSpeedup (Guo et al., arXiv 2506.05064; code lingxiao-guo/DemoSpeedup), hipolicy_jax.speedup"


def _slug(task: str) -> str:
    return task.replace(":", "_")


def root_attrs(path: str) -> dict:
    """The root attributes of the zarr buffer at ``path`` (a plain dict)."""
    return dict(zarr.open_group(path, mode="r").attrs)


def buffer_task(path: str, attrs: dict | None = None, known: tuple[str, ...] = TASKS) -> str | None:
    """The task of the buffer at ``path`` (module docstring), or None when it does not say."""
    attrs = root_attrs(path) if attrs is None else attrs
    if isinstance(attrs.get("task"), str):
        return attrs["task"]
    record = attrs.get(SPEEDUP_ATTR)
    if isinstance(record, dict) and isinstance(record.get("task"), str):
        return record["task"]
    name = os.path.basename(os.path.normpath(path))
    matches = [t for t in known if name.startswith(_slug(t) + "_") or name.startswith(_slug(t) + ".")]
    return max(matches, key=len) if matches else None


def check_proxy_fits(buffer: ReplayBuffer, proxy: Run, path: str, task: str | None) -> tuple[str, ...]:
    """Raise a one-line ``ValueError`` naming ``--proxy`` when the proxy run was trained on another task than the
    buffer's (``task``; None: unknown), with another action size, on observation keys the buffer lacks or of
    another per-frame shape, or with other action kinds than the buffer records. Returns the action kinds to
    re-derive actions with: the buffer's, else the proxy's (``ChunkConfig.kinds``)."""
    meta, cfg = proxy.policy.meta, proxy.policy.cfg
    where = f"the proxy {proxy.run_dir}"
    if task is not None and _slug(task) != _slug(proxy.task):
        raise ValueError(f"--proxy: {where} was trained on {proxy.task}, {path} holds {task} demos; pass a proxy "
                         f"trained on {task} (or the {proxy.task} demos)")
    if "action" not in buffer.data or buffer.data["action"].ndim != 2:
        raise ValueError(f"--data: {path} has no data/action of shape (T, A); keys {sorted(buffer.data)}")
    action_dim = int(meta["action_dim"])
    have = int(buffer.data["action"].shape[1])
    if have != action_dim:
        raise ValueError(f"--proxy: {where} acts with {action_dim}-dim actions, {path} holds {have}-dim actions; "
                         f"pass a proxy trained on these demos' task")
    keys = tuple(cfg.encoder.obs_keys)
    missing = [k for k in keys if k not in buffer.data]
    if missing:
        raise ValueError(f"--proxy: {where} reads observation keys {list(keys)}, {path} lacks {missing} (has "
                         f"{sorted(buffer.data)}); pass a proxy trained on this buffer's observations")
    for key, shape in (meta.get("obs_shapes") or {}).items():
        if key in buffer.data and tuple(buffer.data[key].shape[1:]) != tuple(shape):
            raise ValueError(f"--proxy: {where} was trained on {key} frames of shape {tuple(shape)}, {path} holds "
                             f"{tuple(buffer.data[key].shape[1:])}; pass a proxy trained on these demos' task")
    kinds = cfg.chunk.kinds(action_dim)
    try:
        check_recorded_kinds(kinds, buffer.action_kinds, path)
    except ValueError:
        raise ValueError(f"--proxy: {where} acts with action_kinds {list(kinds)}, {path} records "
                         f"{list(buffer.action_kinds)}; pass a proxy trained on these demos") from None
    return tuple(buffer.action_kinds) if buffer.action_kinds is not None else kinds


def load_demos(path: str) -> ReplayBuffer:
    """The buffer at ``path``; a missing one is a one-line ``FileNotFoundError`` naming ``--data``."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"--data: no replay buffer at {path!r}; collect it (python -m experiments.collect) "
                                f"or pass another --data")
    return ReplayBuffer.load(path)


def write_buffer(buffer: ReplayBuffer, path: str, attrs: dict, overwrite: bool = False) -> None:
    """Save ``buffer`` at ``path`` (``ReplayBuffer.save``) with the root ``attrs`` too, through a temporary sibling
    renamed into place (no half-written buffer at ``path``)."""
    if os.path.lexists(path) and not overwrite:
        raise FileExistsError(f"--out: {path} already exists; pass --overwrite to replace it")
    partial = f"{path}.partial-{os.getpid()}"
    shutil.rmtree(partial, ignore_errors=True)
    buffer.save(partial)
    root = zarr.open_group(partial, mode="r+")
    root.attrs.update({k: v for k, v in attrs.items() if k != ACTION_KINDS_ATTR})
    if os.path.lexists(path):
        shutil.rmtree(path) if os.path.isdir(path) and not os.path.islink(path) else os.remove(path)
    os.replace(partial, path)


@dataclasses.dataclass(frozen=True)
class SpeedupResult:
    """What ``speedup_demos`` made: the source and accelerated buffers, per-frame entropies ``(T,)`` of the source,
    the written record (the ``speedup`` attribute) and the output path."""

    source: ReplayBuffer
    accelerated: ReplayBuffer
    entropy: np.ndarray
    record: dict
    path: str


def speedup_demos(data: str, proxy: str | Run, out: str, cfg: SpeedupConfig = SpeedupConfig(), *, seed: int = 0,
                  step: int | None = None, batch_size: int = 64, overwrite: bool = False,
                  progress: Callable[[int], None] | None = None) -> SpeedupResult:
    """Accelerate the demo buffer at ``data`` with the proxy run ``proxy`` (a run dir, or a loaded ``Run``) and write
    the accelerated buffer at ``out`` (module docstring). ``seed``: the sampler's PRNG key is ``key(seed)``;
    ``step``: the proxy's checkpoint (default the latest); ``progress(n)``: n more frames measured."""
    if os.path.abspath(out) == os.path.abspath(data):
        raise ValueError(f"--out: {out} is the source buffer; pass another path")
    if os.path.lexists(out) and not overwrite:
        raise FileExistsError(f"--out: {out} already exists; pass --overwrite to replace it")
    buffer = load_demos(data)
    attrs = root_attrs(data)
    try:
        run = proxy if isinstance(proxy, Run) else load_run(proxy, step)
    except FileNotFoundError as e:
        raise FileNotFoundError(f"--proxy: {one_line(e)}") from None
    same_data = os.path.abspath(str(run.policy.meta.get("data", ""))) == os.path.abspath(data)
    task = run.task if same_data else buffer_task(data, attrs)
    kinds = check_proxy_fits(buffer, run, data, task)
    inference = run_inference(run).sampler_settings()
    ladder = ladder_entropies(run.policy, buffer, cfg, jax.random.key(seed), inference=inference,
                              batch_size=batch_size, progress=progress)  # (K, T): one row per candidate bandwidth
    chosen = choose_bandwidth(ladder, cfg)
    entropy = ladder[chosen]
    accelerated, episodes = accelerate(buffer, entropy, kinds, cfg)
    record = {"method": METHOD, "source": os.path.abspath(data), "proxy": run.run_dir, "proxy_step": run.policy.step,
              "task": task or run.task, "config": dataclasses.asdict(cfg),
              "sampler": {"num_samples": cfg.num_samples, "sampler": inference.sampler,
                          "num_steps": inference.num_steps},
              "seed": seed, "action_kinds": list(kinds),
              "original_frames": buffer.num_frames, "new_frames": accelerated.num_frames,
              "original_lengths": [e["original_length"] for e in episodes],
              "new_lengths": [e["new_length"] for e in episodes],
              "kept": [e["kept"] for e in episodes], "segments": [e["segments"] for e in episodes],
              "saturated_fraction": saturated_fraction(entropy, cfg.num_samples),
              "bandwidth": cfg.bandwidths()[chosen],
              "saturated_by_bandwidth": {f"{b:g}": saturated_fraction(row, cfg.num_samples)
                                         for b, row in zip(cfg.bandwidths(), ladder)},
              "entropy": [float(h) for h in entropy]}
    write_buffer(accelerated, out, {**attrs, SPEEDUP_ATTR: record}, overwrite=overwrite)
    return SpeedupResult(buffer, accelerated, entropy, record, out)
