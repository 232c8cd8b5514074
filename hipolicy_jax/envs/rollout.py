"""Batched closed-loop evaluation of chunking policies on the MJX tasks.

Policy interface (written for ONE episode; ``evaluate`` vmaps it over episodes)::

    policy_fn(obs_history, key) -> PolicyOutput(actions (L_c, A), stride () int32, entropy () float32)

``obs_history`` maps every observation key to ``(history_len, ...)``: the last ``history_len`` control-rate
observations, oldest first, padded at the episode start by repeating the first observation (as training windows
are padded). After each replan the executor executes all ``L_c`` actions of the chunk, one per control step, and
appends every new observation to the history, so a chunk predicted at stride s covers s·L_c steps of demonstration
time in L_c control steps (the execution speed-up); ``stride`` and ``entropy`` are only recorded.

Policies with memory (the scripted expert) use ``evaluate_stateful`` with
``policy_fn(obs_history, key, policy_state, policy_args) -> (PolicyOutput, policy_state)`` and
``init_fn(first_obs, key) -> policy_state``.

Compilation is cached: ``policy_args`` (e.g. network parameters, normaliser, thresholds) is a traced pytree passed
to ``policy_fn(obs_history, key, policy_args)``, so evaluating new parameters with the same ``policy_fn`` object
reuses the compiled rollout instead of recompiling (20–50 s a task on a CPU).

All episodes run in one jitted rollout: ``lax.scan`` over replans, an inner ``lax.scan`` over the chunk's steps.
An episode is frozen (env state, history and policy state masked) once it is done or reaches the step limit.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from hipolicy_jax import envs as envs_lib
from hipolicy_jax.envs.base import ExpertPlan, MjxEnv


class PolicyOutput(NamedTuple):
    """One replan: actions (L_c, A) to execute one per control step, the stride they were predicted at () int32
    and the policy's entropy estimate () float32 (NaN when the policy has none)."""

    actions: jax.Array
    stride: jax.Array
    entropy: jax.Array


class EvalResult(NamedTuple):
    """Evaluation of E episodes with R replans each.

    success_rate () float32, mean_steps_success () float32 (mean control steps of successful episodes; NaN if
    none), success (E,) bool, steps (E,) int32 control steps executed, entropy (E, R) float32, stride (E, R) int32,
    valid (E, R) bool (the episode was still running at that replan; entries where False are meaningless).
    """

    success_rate: jax.Array
    mean_steps_success: jax.Array
    success: jax.Array
    steps: jax.Array
    entropy: jax.Array
    stride: jax.Array
    valid: jax.Array


PolicyFn = Callable[[dict[str, jax.Array], jax.Array], PolicyOutput]
StatefulPolicyFn = Callable[[dict[str, jax.Array], jax.Array, Any, Any], tuple[PolicyOutput, Any]]
InitFn = Callable[[dict[str, jax.Array], jax.Array], Any]


def init_history(obs: dict[str, jax.Array], history_len: int) -> dict[str, jax.Array]:
    """History (history_len, ...) per key, padded by repeating ``obs``."""
    return {k: jnp.repeat(v[None], history_len, axis=0) for k, v in obs.items()}


def push_history(history: dict[str, jax.Array], obs: dict[str, jax.Array]) -> dict[str, jax.Array]:
    """Drop the oldest frame and append ``obs`` as the newest."""
    return {k: jnp.concatenate([h[1:], obs[k][None]], axis=0) for k, h in history.items()}


def _select(pred: jax.Array, new, old):
    """Tree-wise ``new if pred else old`` for a scalar bool ``pred``."""
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), new, old)


@functools.lru_cache(maxsize=16)
def _make(task: str) -> MjxEnv:
    return envs_lib.make(task)


def _resolve(task: str | MjxEnv) -> MjxEnv:
    """Envs are immutable, so one instance per task name keeps compiled rollouts cacheable."""
    return _make(task) if isinstance(task, str) else task


def make_episode_fn(env: MjxEnv, policy_fn: StatefulPolicyFn, init_fn: InitFn, *, history_len: int,
                    chunk_len: int, max_steps: int | None = None) -> Callable[[jax.Array], tuple]:
    """The un-batched, un-jitted rollout of one episode: ``episode(key, policy_args) -> (final State, entropy (R,),
    stride (R,), valid (R,))``. ``evaluate_stateful`` vmaps and jits it."""
    if history_len < 1 or chunk_len < 1:
        raise ValueError(f"history_len and chunk_len must be >= 1, got {history_len}, {chunk_len}")
    limit = int(max_steps if max_steps is not None else env.max_steps)
    num_replans = math.ceil(limit / chunk_len)

    def finished(state):
        return state.done | (state.step >= limit)

    def episode(key, policy_args):
        k_reset, k_init, k_policy = jax.random.split(key, 3)
        state = env.reset(k_reset)
        history = init_history(state.obs, history_len)
        pstate = init_fn(state.obs, k_init)

        def replan(carry, r):
            state, history, pstate = carry
            valid = ~finished(state)
            out, new_pstate = policy_fn(history, jax.random.fold_in(k_policy, r), pstate, policy_args)
            pstate = _select(valid, new_pstate, pstate)

            def act(inner, action):
                state, history = inner
                new_state = env.step(state, action)
                new_history = push_history(history, new_state.obs)
                keep = finished(state)
                return (_select(keep, state, new_state), _select(keep, history, new_history)), None

            (state, history), _ = jax.lax.scan(act, (state, history), out.actions)
            trace = (jnp.asarray(out.entropy, jnp.float32), jnp.asarray(out.stride, jnp.int32), valid)
            return (state, history, pstate), trace

        (state, _, _), (entropy, stride, valid) = jax.lax.scan(
            replan, (state, history, pstate), jnp.arange(num_replans))
        return state, entropy, stride, valid

    return episode


def check_policy_shape(env: MjxEnv, policy_fn: StatefulPolicyFn, init_fn: InitFn, policy_args, *,
                       history_len: int, chunk_len: int) -> None:
    """Check the policy's chunk shape once, abstractly (no compile)."""
    def probe(key, args):
        state = env.reset(key)
        hist = init_history(state.obs, history_len)
        return policy_fn(hist, key, init_fn(state.obs, key), args)[0]

    out = jax.eval_shape(probe, jax.random.PRNGKey(0), policy_args)
    if out.actions.shape != (chunk_len, env.action_dim):
        raise ValueError(f"policy_fn: actions must have shape (chunk_len={chunk_len}, A={env.action_dim}), "
                         f"got {out.actions.shape}")


@functools.lru_cache(maxsize=32)
def compiled_rollout(env: MjxEnv, policy_fn: StatefulPolicyFn, init_fn: InitFn, history_len: int, chunk_len: int,
                     max_steps: int | None):
    """``jit(vmap(episode))(keys (E,), policy_args)``, cached per (env, policy_fn, init_fn, shapes)."""
    episode = make_episode_fn(env, policy_fn, init_fn, history_len=history_len, chunk_len=chunk_len,
                              max_steps=max_steps)
    return jax.jit(jax.vmap(episode, in_axes=(0, None)))


def evaluate_stateful(policy_fn: StatefulPolicyFn, init_fn: InitFn, task: str | MjxEnv, num_episodes: int,
                      key: jax.Array, *, history_len: int, chunk_len: int, max_steps: int | None = None,
                      policy_args=()) -> EvalResult:
    """``evaluate`` for a policy that carries its own state (see the module docstring)."""
    env = _resolve(task)
    check_policy_shape(env, policy_fn, init_fn, policy_args, history_len=history_len, chunk_len=chunk_len)
    rollout = compiled_rollout(env, policy_fn, init_fn, history_len, chunk_len, max_steps)
    keys = jax.device_put(jax.random.split(key, num_episodes))
    state, entropy, stride, valid = rollout(keys, policy_args)
    success = state.success
    steps = state.step
    n_succ = success.sum()
    mean_steps = jnp.where(n_succ > 0, jnp.sum(jnp.where(success, steps, 0)) / jnp.maximum(n_succ, 1), jnp.nan)
    return EvalResult(success_rate=success.mean(dtype=jnp.float32), mean_steps_success=mean_steps.astype(jnp.float32),
                      success=success, steps=steps, entropy=entropy, stride=stride, valid=valid)


def _no_state(obs, key):
    return ()


@functools.lru_cache(maxsize=32)
def _as_stateful(policy_fn: Callable, with_args: bool) -> StatefulPolicyFn:
    """A stable stateful wrapper per policy_fn (stable identity keeps ``compiled_rollout``'s cache warm)."""
    def stateful(history, key, pstate, args):
        out = policy_fn(history, key, args) if with_args else policy_fn(history, key)
        return out, pstate

    return stateful


def evaluate(policy_fn: Callable, task: str | MjxEnv, num_episodes: int, key: jax.Array, *, history_len: int,
             chunk_len: int, max_steps: int | None = None, policy_args=None) -> EvalResult:
    """Run ``num_episodes`` episodes of ``task`` in parallel in one compiled rollout and score ``policy_fn``.

    policy_fn(obs_history, key) -> PolicyOutput for one episode (see the module docstring), or
    policy_fn(obs_history, key, policy_args) when ``policy_args`` (a traced pytree) is given. ``max_steps``
    (default: the task's) caps each episode's control steps; an episode reaching it counts as a failure.
    """
    stateful = _as_stateful(policy_fn, policy_args is not None)
    return evaluate_stateful(stateful, _no_state, task, num_episodes, key, history_len=history_len,
                             chunk_len=chunk_len, max_steps=max_steps,
                             policy_args=() if policy_args is None else policy_args)


class ExpertState(NamedTuple):
    """Carried state of the scripted expert as a policy: its plan and its plan clock (control steps, float32)."""

    plan: ExpertPlan
    t: jax.Array


def expert_policy(task: str | MjxEnv, chunk_len: int, stride: int = 1) -> tuple[StatefulPolicyFn, InitFn]:
    """The task's scripted expert as a stateful chunking policy for ``evaluate_stateful``.

    Each replan returns the next ``chunk_len`` plan points taken every ``stride`` steps of plan time, so at
    stride s the expert executes its demonstration s times faster. Entropy is reported as 0.
    """
    env = _resolve(task)

    def init_fn(obs, key):
        return ExpertState(plan=env.expert_plan(obs["state"], key), t=jnp.zeros((), jnp.float32))

    def policy_fn(history, key, pstate, args):
        ts = pstate.t + stride * jnp.arange(chunk_len, dtype=jnp.float32)
        actions = jax.vmap(lambda t: env.expert_action(pstate.plan, t))(ts)
        out = PolicyOutput(actions=actions, stride=jnp.int32(stride), entropy=jnp.zeros((), jnp.float32))
        return out, pstate._replace(t=pstate.t + stride * chunk_len)

    return policy_fn, init_fn
