"""Batched closed-loop evaluation of chunking policies on the MJX tasks.

Policy interface (written for ONE episode; ``evaluate`` vmaps it over episodes)::

    policy_fn(obs_history, key) -> PolicyOutput(actions (L, A), stride () int32, entropy () float32,
                                                num_actions () int32 or None)

``obs_history`` maps every observation key to ``(history_len, ...)``: the last ``history_len`` control-rate
observations, oldest first, padded at the episode start by repeating the first observation (as training windows
are padded). After each decision the executor executes the first ``num_actions`` (default all L) actions, one per
control step, and appends every new observation to the history, so a chunk predicted at stride s covers s·L steps
of demonstration time in L control steps (the execution speed-up); ``stride`` and ``entropy`` are only recorded.
How a policy's samples become these actions (the whole chunk, adaptive chunk sizes, temporal ensembling) is the
execution strategy (``evaluation.execution``).

Policies with memory (the scripted expert) use ``evaluate_stateful`` with
``policy_fn(obs_history, key, policy_state, policy_args) -> (PolicyOutput, policy_state)`` and
``init_fn(first_obs, key) -> policy_state``.

A ``Rollout`` object owns one compiled batched rollout: ``policy_args`` (e.g. network parameters, normaliser,
thresholds) is a traced pytree passed to ``policy_fn(obs_history, key, policy_args)``, so calling the same
``Rollout`` with new parameters reuses its compile (20–50 s a task on a CPU). The functions ``evaluate`` /
``evaluate_stateful`` / ``rollout_episodes`` build a fresh ``Rollout`` per call, for one-off evaluations; there is
no global cache.

All episodes run in one jitted rollout: a ``lax.while_loop`` over decisions (until every episode is over), an
inner ``lax.scan`` over the decision's actions. An episode is frozen (env state, history and policy state masked)
once it is done or reaches the step limit.

The same episode loop (``make_episode_fn``) also records what videos need: the joint positions of every control
step (and optionally observations), as a ``Recording``. Batched rollouts always record qpos (E·T·nq floats, cheap),
so one compiled rollout serves scoring (``evaluate``), traces and videos (``rollout_episodes``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from hipolicy_jax import envs as envs_lib
from hipolicy_jax import parallel
from hipolicy_jax.envs.base import ExpertPlan, MjxEnv


class PolicyOutput(NamedTuple):
    """One decision: actions (L, A) to execute one per control step, the stride they were predicted at () int32,
    the policy's entropy estimate () float32 (NaN when the policy has none) and how many of the actions to execute
    before the next decision, ``num_actions`` () int32 in [1, L] (None: all L)."""

    actions: jax.Array
    stride: jax.Array
    entropy: jax.Array
    num_actions: Any = None


class Trace(NamedTuple):
    """Per-decision record of one episode, each (R,): entropy, stride, valid (the decision happened), start (the
    control step it was taken at) and executed (how many of its actions ran). Entries where valid is False are
    padding."""

    entropy: jax.Array
    stride: jax.Array
    valid: jax.Array
    start: jax.Array
    executed: jax.Array


class EvalResult(NamedTuple):
    """Evaluation of E episodes with R replans each.

    success_rate () float32, mean_steps_success () float32 (mean control steps of successful episodes; NaN if
    none), success (E,) bool, steps (E,) int32 control steps executed, and per decision (E, R): entropy float32,
    stride int32, valid bool (the episode was still running at that decision; entries where False are padding),
    start int32 (the control step the decision was taken at), executed int32 (actions it executed).
    """

    success_rate: jax.Array
    mean_steps_success: jax.Array
    success: jax.Array
    steps: jax.Array
    entropy: jax.Array
    stride: jax.Array
    valid: jax.Array
    start: jax.Array
    executed: jax.Array


class Recording(NamedTuple):
    """Per-step record of an episode (leading (E,) axis when batched): qpos (T+1, nq) from the reset on, frozen
    after the episode ends; body_pos (n, 3) the episode's randomised body placements; obs {key: (T+1, ...)} for the
    recorded observation keys (empty unless asked for). T = replans · chunk_len; entries past ``steps`` repeat
    the final state."""

    qpos: jax.Array
    body_pos: jax.Array
    obs: dict[str, jax.Array]


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


def _resolve(task: str | MjxEnv) -> MjxEnv:
    return envs_lib.make(task) if isinstance(task, str) else task


def make_episode_fn(env: MjxEnv, policy_fn: StatefulPolicyFn, init_fn: InitFn, *, history_len: int,
                    chunk_len: int, max_steps: int | None = None, record: bool = False,
                    record_obs: tuple[str, ...] = (),
                    min_actions: int | None = None) -> Callable[[jax.Array, Any], tuple]:
    """The un-batched, un-jitted rollout of one episode: ``episode(key, policy_args) -> (final State, Trace)``, plus a
    ``Recording`` (qpos and the ``record_obs`` observations of every control step) as a third element when
    ``record``. ``Rollout`` vmaps and jits it; ``video`` jits it alone.

    Every decision returns ``chunk_len`` actions of which the first ``num_actions`` (all when None) are executed,
    one per control step, before the next decision; ``min_actions`` (default ``chunk_len``) is the fewest a decision
    may execute and sizes the per-decision trace: R = ceil(limit / min_actions) entries. The decisions run in a
    ``lax.while_loop`` that stops once the episode is over (under ``vmap``: once every episode is)."""
    min_actions = chunk_len if min_actions is None else int(min_actions)
    if history_len < 1 or chunk_len < 1 or not 1 <= min_actions <= chunk_len:
        raise ValueError(f"history_len, chunk_len must be >= 1 and min_actions in [1, chunk_len], got {history_len}, "
                         f"{chunk_len}, {min_actions}")
    missing = [k for k in record_obs if k not in env.obs_keys]
    if missing:
        raise ValueError(f"record_obs: {missing} not among the env's observations {env.obs_keys}")
    limit = int(max_steps if max_steps is not None else env.max_steps)
    num_replans = math.ceil(limit / min_actions)
    record_obs = tuple(record_obs)

    def finished(state):
        return state.done | (state.step >= limit)

    def snapshot(state):
        return state.data.qpos, {k: state.obs[k] for k in record_obs}

    def episode(key, policy_args):
        k_reset, k_init, k_policy = jax.random.split(key, 3)
        state = env.reset(k_reset)
        history = init_history(state.obs, history_len)
        pstate = init_fn(state.obs, k_init)
        trace = Trace(entropy=jnp.full((num_replans,), jnp.nan, jnp.float32),
                      stride=jnp.zeros((num_replans,), jnp.int32), valid=jnp.zeros((num_replans,), bool),
                      start=jnp.zeros((num_replans,), jnp.int32), executed=jnp.zeros((num_replans,), jnp.int32))
        # per control step snapshots, index = the step count after it (0: the reset); entries are rewritten with the
        # same frozen state once the episode is over
        frames = jax.tree.map(lambda x: jnp.zeros((limit + 1, *x.shape), x.dtype), snapshot(state)) if record else ()
        frames = jax.tree.map(lambda buf, x: buf.at[0].set(x), frames, snapshot(state)) if record else ()

        def running(carry):
            r, state = carry[0], carry[1]
            return (r < num_replans) & ~finished(state)

        def decide(carry):
            r, state, history, pstate, trace, frames = carry
            out, pstate = policy_fn(history, jax.random.fold_in(k_policy, r), pstate, policy_args)
            n = chunk_len if out.num_actions is None else jnp.clip(out.num_actions, 1, chunk_len)
            start = state.step

            def act(inner, i_action):
                i, action = i_action
                state, history, frames = inner
                new_state = env.step(state, action)
                new_history = push_history(history, new_state.obs)
                keep = finished(state) | (i >= n)
                state, history = _select(keep, state, new_state), _select(keep, history, new_history)
                if record:
                    frames = jax.tree.map(lambda buf, x: buf.at[state.step].set(x), frames, snapshot(state))
                return (state, history, frames), None

            (state, history, frames), _ = jax.lax.scan(act, (state, history, frames),
                                                       (jnp.arange(chunk_len), out.actions))
            trace = Trace(entropy=trace.entropy.at[r].set(jnp.asarray(out.entropy, jnp.float32)),
                          stride=trace.stride.at[r].set(jnp.asarray(out.stride, jnp.int32)),
                          valid=trace.valid.at[r].set(True), start=trace.start.at[r].set(start),
                          executed=trace.executed.at[r].set(state.step - start))
            return r + 1, state, history, pstate, trace, frames

        body_pos = state.info["body_pos"]
        _, state, _, _, trace, frames = jax.lax.while_loop(
            running, decide, (jnp.zeros((), jnp.int32), state, history, pstate, trace, frames))
        if not record:
            return state, trace
        # entries past the last step repeat the final state
        after = jnp.arange(limit + 1) > state.step
        qpos, obs = jax.tree.map(lambda buf: jnp.where(after.reshape(-1, *([1] * (buf.ndim - 1))), buf[state.step],
                                                       buf), frames)
        return state, trace, Recording(qpos=qpos, body_pos=body_pos, obs=obs)

    return episode


def check_policy_shape(env: MjxEnv, policy_fn: StatefulPolicyFn, init_fn: InitFn, policy_args, *,
                       history_len: int, chunk_len: int) -> None:
    """Check the policy's chunk shape abstractly (``jax.eval_shape``, no compile)."""
    def probe(key, args):
        state = env.reset(key)
        hist = init_history(state.obs, history_len)
        return policy_fn(hist, key, init_fn(state.obs, key), args)[0]

    out = jax.eval_shape(probe, jax.random.PRNGKey(0), policy_args)
    if out.actions.shape != (chunk_len, env.action_dim):
        raise ValueError(f"policy_fn: actions must have shape (chunk_len={chunk_len}, A={env.action_dim}), "
                         f"got {out.actions.shape}")


def _signature(tree) -> tuple:
    leaves, treedef = jax.tree.flatten(tree)
    return treedef, tuple((tuple(jnp.shape(x)), jnp.result_type(x)) for x in leaves)


class Rollout:
    """One compiled batched rollout of a (stateful) policy in one env: ``jit(vmap(episode))`` over episode keys.

    ``rollout(num_episodes, key, policy_args) -> (EvalResult, Recording)`` (qpos recorded). The object owns its
    compiled program: calls with new ``policy_args`` of the same shapes (new parameters, thresholds) and the same
    number of episodes reuse it. ``traces`` counts how often the episode was traced (one per compile).

    With several (local) devices the episodes are sharded across them (when their count divides ``num_episodes``;
    otherwise everything runs on one device) and ``policy_args`` is replicated.
    """

    def __init__(self, env: MjxEnv, policy_fn: StatefulPolicyFn, init_fn: InitFn, *, history_len: int,
                 chunk_len: int, max_steps: int | None = None, min_actions: int | None = None):
        self.env, self.policy_fn, self.init_fn = env, policy_fn, init_fn
        self.history_len, self.chunk_len, self.max_steps = history_len, chunk_len, max_steps
        self.traces = 0
        episode = make_episode_fn(env, policy_fn, init_fn, history_len=history_len, chunk_len=chunk_len,
                                  max_steps=max_steps, record=True, min_actions=min_actions)

        def rollout_episode(key, policy_args):
            self.traces += 1
            return episode(key, policy_args)

        self._jitted = jax.jit(jax.vmap(rollout_episode, in_axes=(0, None)))
        self._checked: set = set()

    def __call__(self, num_episodes: int, key: jax.Array, policy_args=()) -> tuple[EvalResult, Recording]:
        signature = _signature(policy_args)
        if signature not in self._checked:
            check_policy_shape(self.env, self.policy_fn, self.init_fn, policy_args, history_len=self.history_len,
                               chunk_len=self.chunk_len)
            self._checked.add(signature)
        keys = jax.random.split(key, num_episodes)
        mesh = parallel.make_mesh(local=True)  # evaluation is process-local, also in a multi-process run
        if mesh is not None and num_episodes % mesh.size == 0:
            keys = parallel.shard_batch(keys, mesh)
            policy_args = parallel.replicate(policy_args, mesh)
        else:
            keys = jax.device_put(keys)
        state, trace, recording = self._jitted(keys, policy_args)
        return score(state, trace), recording


def score(state, trace: Trace) -> EvalResult:
    """``EvalResult`` of a batch of final env states and their per-decision traces."""
    success, steps = state.success, state.step
    n_succ = success.sum()
    mean_steps = jnp.where(n_succ > 0, jnp.sum(jnp.where(success, steps, 0)) / jnp.maximum(n_succ, 1), jnp.nan)
    return EvalResult(success_rate=success.mean(dtype=jnp.float32),
                      mean_steps_success=mean_steps.astype(jnp.float32), success=success, steps=steps,
                      **trace._asdict())


def rollout_episodes(policy_fn: StatefulPolicyFn, init_fn: InitFn, task: str | MjxEnv, num_episodes: int,
                     key: jax.Array, *, history_len: int, chunk_len: int, max_steps: int | None = None,
                     policy_args=(), min_actions: int | None = None) -> tuple[EvalResult, Recording]:
    """One-off ``Rollout``: ``evaluate_stateful`` that also returns the batched ``Recording`` (qpos (E, T+1, nq),
    body_pos (E, n, 3)), e.g. to render a video of an evaluated episode. Compiles on every call: keep a ``Rollout``
    to evaluate repeatedly."""
    rollout = Rollout(_resolve(task), policy_fn, init_fn, history_len=history_len, chunk_len=chunk_len,
                      max_steps=max_steps, min_actions=min_actions)
    return rollout(num_episodes, key, policy_args)


def evaluate_stateful(policy_fn: StatefulPolicyFn, init_fn: InitFn, task: str | MjxEnv, num_episodes: int,
                      key: jax.Array, *, history_len: int, chunk_len: int, max_steps: int | None = None,
                      policy_args=(), min_actions: int | None = None) -> EvalResult:
    """``evaluate`` for a policy that carries its own state (see the module docstring)."""
    return rollout_episodes(policy_fn, init_fn, task, num_episodes, key, history_len=history_len,
                            chunk_len=chunk_len, max_steps=max_steps, policy_args=policy_args,
                            min_actions=min_actions)[0]


def _no_state(obs, key):
    return ()


def stateless(policy_fn: Callable, with_args: bool = True) -> tuple[StatefulPolicyFn, InitFn]:
    """``(policy_fn, init_fn)`` for ``Rollout`` / ``evaluate_stateful`` / ``make_episode_fn`` from a stateless
    ``policy_fn(obs_history, key[, policy_args])``."""
    def stateful(history, key, pstate, args):
        out = policy_fn(history, key, args) if with_args else policy_fn(history, key)
        return out, pstate

    return stateful, _no_state


def evaluate(policy_fn: Callable, task: str | MjxEnv, num_episodes: int, key: jax.Array, *, history_len: int,
             chunk_len: int, max_steps: int | None = None, policy_args=None) -> EvalResult:
    """Run ``num_episodes`` episodes of ``task`` in parallel in one compiled rollout and score ``policy_fn``.

    policy_fn(obs_history, key) -> PolicyOutput for one episode (see the module docstring), or
    policy_fn(obs_history, key, policy_args) when ``policy_args`` (a traced pytree) is given. ``max_steps``
    (default: the task's) caps each episode's control steps; an episode reaching it counts as a failure.
    """
    stateful, init_fn = stateless(policy_fn, policy_args is not None)
    return evaluate_stateful(stateful, init_fn, task, num_episodes, key, history_len=history_len,
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
