"""Scripted-expert demonstrations: one jitted, vmapped rollout per batch of episodes.

``expert_rollout(task, batch_size, ...)`` returns a (cached) jitted function ``keys (B, 2) -> ExpertTrace`` that
runs the expert of every episode for the task's full step limit; finished episodes are frozen. ``collect_demos``
splits the traces at each episode's end (its success step) into time-first numpy episodes ready for
``ReplayBuffer.from_episodes``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax import envs as envs_lib


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
    """Jitted ``keys (batch_size, 2) -> ExpertTrace`` for the expert of ``task`` (cached per arguments, so
    repeated calls with the same task, batch size, observation keys and overrides reuse one compilation)."""
    return _expert_rollout(task, int(batch_size), tuple(obs_keys), tuple(sorted(overrides.items())))


@functools.lru_cache(maxsize=16)
def _expert_rollout(task, batch_size, obs_keys, overrides):
    env = envs_lib.make(task, obs_keys=obs_keys, **dict(overrides))

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
