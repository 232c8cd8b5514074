"""Scripted-expert demonstrations: one jitted, vmapped rollout per batch of episodes, cached on disk as zarr.

``expert_rollout(task, batch_size, ...)`` returns a jitted function ``keys (B, 2) -> ExpertTrace`` that runs the
expert of every episode for the task's full step limit; finished episodes are frozen. ``collect_demos`` compiles it
once and splits the traces at each episode's end (its success step) into time-first numpy episodes ready for
``ReplayBuffer.from_episodes`` (``demo_buffer`` makes the buffer, recording the task's ``action_kinds``, all
absolute for the MJX tasks). ``load_or_collect`` reuses a demo buffer on disk (checked against the policy's
encoder) or collects and saves one at ``default_data_path``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax import envs as envs_lib
from hipolicy_jax.config import EncoderConfig
from hipolicy_jax.data.replay_buffer import ReplayBuffer, collection_lock


class ExpertTrace(NamedTuple):
    """Batched expert rollout of B episodes over T = max_steps control steps.

    obs: dict key -> (B, T, ...) observation before each step; action: (B, T, A) action taken at each step;
    success: (B,) bool; steps: (B,) int32 steps until done (success step, or T). Frames t >= steps are padding.
    """

    obs: dict[str, jax.Array]
    action: jax.Array
    success: jax.Array
    steps: jax.Array


def expert_rollout(task: str, batch_size: int, obs_keys: tuple[str, ...] = ("state",),
                   **overrides) -> Callable[[jax.Array], ExpertTrace]:
    """Jitted ``keys (batch_size, 2) -> ExpertTrace`` for the expert of ``task`` (the function owns its compile:
    keep it to run more batches). ``run.env`` is the env, ``run.jitted`` the jitted rollout."""
    env = envs_lib.make(task, obs_keys=tuple(obs_keys), **overrides)

    def one(key):
        k_reset, k_plan = jax.random.split(key)
        state = env.reset(k_reset)
        plan = env.expert_plan(state.obs["state"], k_plan)

        def body(state, t):
            action = env.expert_action(plan, t.astype(jnp.float32))
            new = env.step(state, action)
            new = jax.tree.map(lambda a, b: jnp.where(state.done, a, b), state, new)
            return new, (state.obs, action)

        state, (obs, action) = jax.lax.scan(body, state, jnp.arange(env.max_steps))
        return ExpertTrace(obs=obs, action=action, success=state.success, steps=state.step)

    fn = jax.jit(jax.vmap(one))

    def run(keys):
        return fn(jax.device_put(keys))

    run.env = env
    run.jitted = fn
    return run


def collect_demos(task: str, num_episodes: int, key: jax.Array, obs_keys: tuple[str, ...] = ("state",), *,
                  batch_size: int = 50, max_batches: int | None = None, progress: Callable[[int], None] | None = None,
                  **overrides) -> list[dict[str, np.ndarray]]:
    """``num_episodes`` successful expert episodes of ``task``, each a dict of time-first numpy arrays:
    ``action`` (T, 4) float32 and one entry per obs key (``state`` (T, D), ``image`` (T, H, W, 3) uint8, ...),
    cut at the episode's success step (the observation at t is the one the action at t was taken from).

    Failed expert episodes are dropped and more are drawn (at most ``max_batches`` batches, default enough for a
    50% failure rate). ``progress(n)`` is called with the number of new episodes after every batch.
    """
    batch_size = max(1, min(batch_size, num_episodes))
    run = expert_rollout(task, batch_size, tuple(obs_keys), **overrides)
    max_batches = max_batches or 2 * -(-num_episodes // batch_size) + 1
    episodes: list[dict[str, np.ndarray]] = []
    for b in range(max_batches):
        if len(episodes) >= num_episodes:
            break
        trace = jax.device_get(run(jax.random.split(jax.random.fold_in(key, b), batch_size)))
        before = len(episodes)
        for i in range(batch_size):
            if not trace.success[i] or len(episodes) >= num_episodes:
                continue
            n = int(trace.steps[i])
            ep = {k: np.asarray(v[i, :n]) for k, v in trace.obs.items()}
            ep["action"] = np.asarray(trace.action[i, :n], np.float32)
            episodes.append(ep)
        if progress is not None:
            progress(len(episodes) - before)
    if len(episodes) < num_episodes:
        raise RuntimeError(f"collect_demos: the {task} expert produced only {len(episodes)} successful episodes "
                           f"of the {num_episodes} asked for in {max_batches} batches of {batch_size}")
    return episodes


def demo_buffer(task: str, episodes: list[dict[str, np.ndarray]]) -> ReplayBuffer:
    """``collect_demos``'s episodes of ``task`` as a buffer that records the task's ``action_kinds`` (saved as the
    zarr root attribute ``action_kinds``)."""
    return ReplayBuffer.from_episodes(episodes, action_kinds=envs_lib.make(task).action_kinds)


def default_data_path(task: str, encoder: EncoderConfig, episodes: int) -> str:
    """``data/<task>_<obs keys>[_<camera>]_<episodes>.zarr``: the camera part (``84px``, ``512pts``, ``512pts-rgb``,
    ``512pts-fps``) appears for image and point-cloud encoders, so buffers of different cameras never collide."""
    points = (f"_{encoder.num_points}pts" + ("-rgb" if encoder.point_dims == 6 else "")
              + ("-fps" if encoder.point_sampling == "fps" else ""))
    cam = {"state": "", "image": f"_{encoder.image_size}px", "pointcloud": points}[encoder.obs_type]
    return os.path.join("data", f"{task}_{'-'.join(encoder.obs_keys)}{cam}_{episodes}.zarr")


# Which config field sets each camera key's per-frame shape (for error messages).
_FRAME_FIELDS = {"image": "policy.encoder.image_size", "point_cloud": "policy.encoder.num_points / point_dims"}


def check_buffer(buffer: ReplayBuffer, encoder: EncoderConfig, path: str) -> None:
    """Raise ``ValueError`` naming the key, the expected and the actual per-frame shape if ``buffer`` lacks a key
    the encoder reads or holds images / point clouds of another size than the encoder's."""
    keys = encoder.obs_keys
    missing = [k for k in (*keys, "action") if k not in buffer.data]
    if missing:
        raise ValueError(f"{path}: lacks keys {missing} (has {sorted(buffer.data)}); collect with those obs")
    expected = {"image": (encoder.image_size, encoder.image_size, 3),
                "point_cloud": (encoder.num_points, encoder.point_dims)}
    for key in keys:
        if key in expected and tuple(buffer.data[key].shape[1:]) != expected[key]:
            raise ValueError(f"{path}: data/{key} has frames of shape {tuple(buffer.data[key].shape[1:])}, the "
                             f"encoder expects {expected[key]}; set {_FRAME_FIELDS[key]} to match, or pass another "
                             f"--data (a missing one is collected with the encoder's camera)")


def check_buffer_fits_env(buffer: ReplayBuffer, env, path: str) -> None:
    """Raise ``ValueError`` naming the key, the buffer's and the env's per-frame shape when the demos' actions or
    observations do not fit the env the run will be evaluated in (e.g. 7-dim actions for a 4-dim task), or when
    the buffer records ``action_kinds`` other than the env's (``env.action_kinds``, where it has them)."""
    expected = {"action": (env.action_dim,), **{k: tuple(v) for k, v in env.obs_shapes.items()}}
    for key, shape in expected.items():
        if key in buffer.data and tuple(buffer.data[key].shape[1:]) != shape:
            raise ValueError(f"{path}: data/{key} has frames of shape {tuple(buffer.data[key].shape[1:])}, the "
                             f"{env.name} task expects {shape}; these demos are not of this task "
                             f"(pass its --task or other --data)")
    task_kinds = getattr(env, "action_kinds", None)
    if buffer.action_kinds is not None and task_kinds is not None and tuple(buffer.action_kinds) != tuple(task_kinds):
        raise ValueError(f"{path}: records action_kinds {list(buffer.action_kinds)}, the {env.name} task acts with "
                         f"{list(task_kinds)}; these demos are not of this task (pass its --task or other --data)")


def load_or_collect(task: str, encoder: EncoderConfig, episodes: int, path: str, seed: int = 0,
                    progress: bool = True) -> ReplayBuffer:
    """Reuse the dataset at ``path`` (checked against ``encoder``: keys and frame shapes) or collect ``episodes``
    expert demos of ``task`` with the encoder's observations and camera and save them there.

    Safe under concurrency and interruption: processes asking for the same dataset (a campaign's shards) collect it
    once — the first holds ``<dir>/.<name>.lock`` and the others wait for it — and it is written to a temporary
    sibling that is renamed into place, so no one ever reads a half-written dataset (a collection cut off leaves
    only its temporary, removed by the next one)."""
    import glob
    import shutil

    with collection_lock(path, "demos"):
        if os.path.exists(path):
            buffer = ReplayBuffer.load(path)
            check_buffer(buffer, encoder, path)
            return buffer
        for partial in glob.glob(glob.escape(path) + ".partial-*"):  # left by a collection that was cut off
            shutil.rmtree(partial, ignore_errors=True)
        if progress:
            print(f"collecting {episodes} expert demos of {task} → {path}")
        kwargs = envs_lib.encoder_env_kwargs(encoder)
        episodes_data = collect_demos(task, episodes, jax.random.key(seed), kwargs.pop("obs_keys"), **kwargs)
        buffer = demo_buffer(task, episodes_data)
        partial = f"{path}.partial-{os.getpid()}"
        buffer.save(partial)
        os.replace(partial, path)
        return buffer
