"""Batched closed-loop evaluation of chunking policies on the MJX tasks.

Policy interface (written for ONE episode; ``evaluate`` vmaps it over episodes)::

    policy_fn(obs_history, key) -> PolicyOutput(actions (L, A), stride () int32, entropy () float32,
                                                num_actions () int32 or None)

``obs_history`` maps every observation key to ``(history_len, ...)``: the last ``history_len`` control-rate
observations, oldest first, padded at the episode start by repeating the first observation (as training windows
are padded). After each decision the executor executes the first ``num_actions`` (default all L) actions and
appends the observation after each to the history. What executing an action means is the *semantics*
(``InferenceConfig.semantics``):

- ``rate``: one control step per action, so a chunk predicted at stride s covers s·L steps of demonstration time in
  L control steps (the execution speed-up is physical time).
- ``waypoint`` (the HiPolicy release's): an action is a target the env's controller is given, control step after
  control step, until ``env.reach_error`` is within ``waypoint_tolerance`` or ``waypoint_steps`` × the decision's
  stride control steps have run (at least one); the history gets one frame per action (the observation where the
  action ended), so the policy's windows count actions, not control steps, as the release's environment yields
  one observation per action. With a controller that reaches every target in one step, the same episode as
  ``rate``.

``stride`` and ``entropy`` are only recorded (and the stride bounds a waypoint). Each decision's trace counts the
actions it executed and the control steps they took (equal under ``rate``).
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
once it is done or reaches the step limit. The episode loop comes in pieces (``make_episode_loop``): the vmapped
episode runs every episode's pieces until the longest is over; the compacted rollout (``compacted_rollout``,
``Rollout(compact=True)``, the ``Evaluator``'s) runs each round of decisions on blocks of the episodes still
running, so finished episodes cost neither sampler nor physics (the time of an evaluation is almost all sampler:
``benchmarks/results/PERFORMANCE.md``, "Evaluation profile").

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
    control step it was taken at), executed (the control steps its actions took) and actions (how many of its
    actions ran; = executed under ``rate`` semantics). Entries where valid is False are padding."""

    entropy: jax.Array
    stride: jax.Array
    valid: jax.Array
    start: jax.Array
    executed: jax.Array
    actions: jax.Array


class EvalResult(NamedTuple):
    """Evaluation of E episodes with R replans each.

    success_rate () float32, mean_steps_success () float32 (mean control steps of successful episodes; NaN if
    none), success (E,) bool, steps (E,) int32 control steps executed (physical time), and per decision (E, R):
    entropy float32, stride int32, valid bool (the episode was still running at that decision; entries where False
    are padding), start int32 (the control step the decision was taken at), executed int32 (control steps it took),
    actions int32 (actions it executed). Per episode: decisions = valid.sum(1), actions = actions.sum(1).
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
    actions: jax.Array


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


class EpisodeLoop(NamedTuple):
    """The episode loop of ONE episode in pieces, so that a rollout can drive many episodes through the same code:
    ``init(key) -> carry``, ``running(carry) -> ()`` bool (the episode takes another decision), ``decide(carry,
    policy_args) -> carry`` (one decision and the control steps it executes), ``finish(carry) -> (final State,
    Trace[, Recording])``. ``make_episode_fn`` runs them in a ``lax.while_loop``; ``Rollout`` either vmaps that over
    episodes or (``compact``) calls ``decide`` on blocks of the episodes still running."""

    init: Callable[[jax.Array], tuple]
    running: Callable[[tuple], jax.Array]
    decide: Callable[[tuple, Any], tuple]
    finish: Callable[[tuple], tuple]


class Semantics(NamedTuple):
    """How an action executes (``InferenceConfig.semantics`` and its waypoint bounds; see the module docstring):
    kind ``rate`` | ``waypoint``, tolerance (m) of ``env.reach_error``, steps: control steps per unit of stride a
    waypoint may take."""

    kind: str = "rate"
    tolerance: float = 0.005
    steps: int = 3

    @classmethod
    def of(cls, inference, env: MjxEnv) -> "Semantics":
        """The semantics an ``InferenceConfig`` names, the waypoint bounds it leaves None the env's own."""
        tol, steps = inference.waypoint_tolerance, inference.waypoint_steps
        return cls(inference.semantics, env.waypoint_tolerance if tol is None else tol,
                   env.waypoint_steps if steps is None else steps)

    def check(self) -> None:
        if self.kind not in ("rate", "waypoint"):
            raise ValueError(f"semantics: must be 'rate' or 'waypoint', got {self.kind!r}")
        if not self.tolerance > 0 or self.steps < 1:
            raise ValueError(f"semantics: waypoint tolerance must be > 0 and steps >= 1, got {self.tolerance}, "
                             f"{self.steps}")


RATE = Semantics()


def make_episode_loop(env: MjxEnv, policy_fn: StatefulPolicyFn, init_fn: InitFn, *, history_len: int,
                      chunk_len: int, max_steps: int | None = None, record: bool = False,
                      record_obs: tuple[str, ...] = (), min_actions: int | None = None,
                      early_exit: bool = False, semantics: Semantics = RATE) -> EpisodeLoop:
    """The pieces of ``make_episode_fn``'s episode (same arguments). ``early_exit``: a decision's actions run
    in a ``lax.while_loop`` that stops once the episode has executed the decision's ``num_actions`` actions (or is
    over), instead of a ``lax.scan`` over all ``chunk_len`` (masked past them); the same steps and states either
    way, fewer physics steps under ``vmap`` when every episode of the batch executes fewer than ``chunk_len``."""
    min_actions = chunk_len if min_actions is None else int(min_actions)
    if history_len < 1 or chunk_len < 1 or not 1 <= min_actions <= chunk_len:
        raise ValueError(f"history_len, chunk_len must be >= 1 and min_actions in [1, chunk_len], got {history_len}, "
                         f"{chunk_len}, {min_actions}")
    semantics.check()
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

    def init(key):
        k_reset, k_init, k_policy = jax.random.split(key, 3)
        state = env.reset(k_reset)
        history = init_history(state.obs, history_len)
        pstate = init_fn(state.obs, k_init)
        trace = Trace(entropy=jnp.full((num_replans,), jnp.nan, jnp.float32),
                      stride=jnp.zeros((num_replans,), jnp.int32), valid=jnp.zeros((num_replans,), bool),
                      start=jnp.zeros((num_replans,), jnp.int32), executed=jnp.zeros((num_replans,), jnp.int32),
                      actions=jnp.zeros((num_replans,), jnp.int32))
        # per control step snapshots, index = the step count after it (0: the reset); entries are rewritten with the
        # same frozen state once the episode is over
        frames = jax.tree.map(lambda x: jnp.zeros((limit + 1, *x.shape), x.dtype), snapshot(state)) if record else ()
        frames = jax.tree.map(lambda buf, x: buf.at[0].set(x), frames, snapshot(state)) if record else ()
        body_pos = state.info["body_pos"]
        return jnp.zeros((), jnp.int32), state, history, pstate, trace, frames, k_policy, body_pos

    def running(carry):
        r, state = carry[0], carry[1]
        return (r < num_replans) & ~finished(state)

    def decide(carry, policy_args):
        r, state, history, pstate, trace, frames, k_policy, body_pos = carry
        out, pstate = policy_fn(history, jax.random.fold_in(k_policy, r), pstate, policy_args)
        n = chunk_len if out.num_actions is None else jnp.clip(out.num_actions, 1, chunk_len)
        start = state.step

        def record_step(frames, state):
            return jax.tree.map(lambda buf, x: buf.at[state.step].set(x), frames, snapshot(state)) if record else ()

        def act_rate(inner, i_action):
            i, action = i_action
            state, history, frames, count = inner
            new_state = env.step(state, action)
            new_history = push_history(history, new_state.obs)
            keep = finished(state) | (i >= n)
            state, history = _select(keep, state, new_state), _select(keep, history, new_history)
            frames = record_step(frames, state)
            return (state, history, frames, count + ~keep), None

        bound = semantics.steps * jnp.maximum(jnp.asarray(out.stride, jnp.int32), 1)

        def act_waypoint(inner, i_action):
            i, action = i_action
            state, history, frames, count = inner
            skip = finished(state) | (i >= n)

            def more(c):
                k, s = c[0], c[1]
                arrived = (k > 0) & (env.reach_error(s, action) <= semantics.tolerance)
                return ~skip & (k < bound) & ~finished(s) & ~arrived

            def one(c):
                k, s, fr = c
                s = env.step(s, action)
                return k + 1, s, record_step(fr, s)

            _, state, frames = jax.lax.while_loop(more, one, (jnp.zeros((), jnp.int32), state, frames))
            history = _select(skip, history, push_history(history, state.obs))
            return (state, history, frames, count + ~skip), None

        act = act_waypoint if semantics.kind == "waypoint" else act_rate
        count = jnp.zeros((), jnp.int32)

        if early_exit:
            def more(inner):
                i, state = inner[0], inner[1]
                return (i < chunk_len) & (i < n) & ~finished(state)

            def one(inner):
                i = inner[0]
                return (i + 1, *act(inner[1:], (i, out.actions[i]))[0])

            _, state, history, frames, count = jax.lax.while_loop(
                more, one, (jnp.zeros((), jnp.int32), state, history, frames, count))
        else:
            (state, history, frames, count), _ = jax.lax.scan(act, (state, history, frames, count),
                                                              (jnp.arange(chunk_len), out.actions))
        trace = Trace(entropy=trace.entropy.at[r].set(jnp.asarray(out.entropy, jnp.float32)),
                      stride=trace.stride.at[r].set(jnp.asarray(out.stride, jnp.int32)),
                      valid=trace.valid.at[r].set(True), start=trace.start.at[r].set(start),
                      executed=trace.executed.at[r].set(state.step - start),
                      actions=trace.actions.at[r].set(count))
        return r + 1, state, history, pstate, trace, frames, k_policy, body_pos

    def finish(carry):
        _, state, _, _, trace, frames, _, body_pos = carry
        if not record:
            return state, trace
        # entries past the last step repeat the final state
        after = jnp.arange(limit + 1) > state.step
        qpos, obs = jax.tree.map(lambda buf: jnp.where(after.reshape(-1, *([1] * (buf.ndim - 1))), buf[state.step],
                                                       buf), frames)
        return state, trace, Recording(qpos=qpos, body_pos=body_pos, obs=obs)

    return EpisodeLoop(init, running, decide, finish)


def make_episode_fn(env: MjxEnv, policy_fn: StatefulPolicyFn, init_fn: InitFn, *, history_len: int,
                    chunk_len: int, max_steps: int | None = None, record: bool = False,
                    record_obs: tuple[str, ...] = (), min_actions: int | None = None,
                    semantics: Semantics = RATE) -> Callable[[jax.Array, Any], tuple]:
    """The un-batched, un-jitted rollout of one episode: ``episode(key, policy_args) -> (final State, Trace)``, plus a
    ``Recording`` (qpos and the ``record_obs`` observations of every control step) as a third element when
    ``record``. ``Rollout`` vmaps and jits it; ``video`` jits it alone.

    Every decision returns ``chunk_len`` actions of which the first ``num_actions`` (all when None) are executed,
    one per control step, before the next decision; ``min_actions`` (default ``chunk_len``) is the fewest a decision
    may execute and sizes the per-decision trace: R = ceil(limit / min_actions) entries. The decisions run in a
    ``lax.while_loop`` that stops once the episode is over (under ``vmap``: once every episode is). ``semantics``:
    how each action executes (``Semantics``; default ``rate``, one control step)."""
    loop = make_episode_loop(env, policy_fn, init_fn, history_len=history_len, chunk_len=chunk_len,
                             max_steps=max_steps, record=record, record_obs=record_obs, min_actions=min_actions,
                             semantics=semantics)

    def episode(key, policy_args):
        carry = jax.lax.while_loop(loop.running, lambda c: loop.decide(c, policy_args), loop.init(key))
        return loop.finish(carry)

    return episode


def default_block(num_episodes: int, rows_per_episode: int = 1, min_rows: int | None = None) -> int:
    """Episodes per block of a compacted rollout: equal blocks of at least ``min_rows`` policy rows
    (``rows_per_episode``: the sampler's N; default ``MIN_BLOCK_ROWS`` of the backend), so a block runs the policy
    as fast per row as the whole batch while finished episodes drop out in steps of a block. On a CPU the sampler's
    time per episode is flat from ~64 to 1600 rows (cpu-size U-Net, N = 16: 10 episodes 129 ms, 25 124 ms, 100
    142 ms; PERFORMANCE.md, "Evaluation profile"); an accelerator wants far larger batches."""
    if min_rows is None:
        min_rows = MIN_BLOCK_ROWS.get(jax.default_backend(), MIN_BLOCK_ROWS["other"])
    k = max(1, num_episodes * max(1, rows_per_episode) // max(1, min_rows))
    return -(-num_episodes // k)


MIN_BLOCK_ROWS = {"cpu": 160, "other": 8192}


def compacted_rollout(loop: EpisodeLoop, num_episodes: int, block: int) -> Callable[[jax.Array, Any], tuple]:
    """``rollout(keys (E,), policy_args) -> vmap(finish)`` of E episodes that decide in blocks of ``block`` running
    episodes: every round of decisions gathers the episodes still running (in episode order) into
    ceil(running / block) blocks and calls ``vmap(decide)`` on each, so finished episodes cost neither policy nor
    physics, and a round of decisions costs as many blocks as there are running episodes. Every episode's own
    computation (keys, decisions, control steps, trace, recording) is that of ``make_episode_fn``; only the batch
    its policy and physics run in changes (``block`` = E: the whole batch, as ``vmap`` of the episode)."""
    e, g = int(num_episodes), int(block)
    if not 1 <= g <= e:
        raise ValueError(f"block: episodes per block must be in [1, num_episodes={e}], got {g}")
    padded = -(-e // g) * g

    def rollout(keys, policy_args):
        carry = jax.vmap(loop.init)(keys)
        decide = jax.vmap(loop.decide, in_axes=(0, None))

        def any_running(carry):
            return jnp.any(jax.vmap(loop.running)(carry))

        def round_of_decisions(carry):
            live = jax.vmap(loop.running)(carry)
            count = live.sum()
            order = jnp.argsort(~live, stable=True)  # running episodes first, in episode order
            order = jnp.concatenate([order, jnp.full((padded - e,), e - 1, order.dtype)])

            def one_block(b, carry):
                pos = b * g + jnp.arange(g)
                idx = jax.lax.dynamic_slice(order, (b * g,), (g,))
                new = decide(jax.tree.map(lambda x: x[idx], carry), policy_args)
                dest = jnp.where(pos < count, idx, e)  # rows past the running ones are dropped
                return jax.tree.map(lambda x, y: x.at[dest].set(y, mode="drop"), carry, new)

            return jax.lax.fori_loop(0, (count + g - 1) // g, one_block, carry)

        carry = jax.lax.while_loop(any_running, round_of_decisions, carry)
        return jax.vmap(loop.finish)(carry)

    return rollout


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

    ``compact=True`` runs the episodes through ``compacted_rollout`` instead (``block`` episodes per block, default
    ``default_block(num_episodes, rows_per_episode)``): finished episodes stop costing policy and physics, and when
    a decision may execute fewer than ``chunk_len`` actions (``min_actions`` < ``chunk_len``) its control steps stop
    once the running episodes have executed them (``early_exit``). Every episode's keys, decisions and control
    steps are the same. The floating-point results are the vmapped episode's bit for bit when one block holds
    every episode and there is no early exit; blocks of fewer episodes run the policy at another batch size, and
    the early exit's loop compiles the physics in another context, so their results may differ in the last bits
    (as those of any other batch size do). Only for policies whose rows are independent episodes: a policy whose
    i-th row is tied to the i-th episode (e.g. a remote policy with one connection per row) needs the default.

    With several (local) devices the episodes are sharded across them (when their count divides ``num_episodes``;
    otherwise everything runs on one device), ``policy_args`` is replicated and ``compact`` is not used.
    ``semantics``: how each action executes (``Semantics``; default ``rate``).
    """

    def __init__(self, env: MjxEnv, policy_fn: StatefulPolicyFn, init_fn: InitFn, *, history_len: int,
                 chunk_len: int, max_steps: int | None = None, min_actions: int | None = None,
                 compact: bool = False, block: int | None = None, rows_per_episode: int = 1,
                 semantics: Semantics = RATE):
        self.env, self.policy_fn, self.init_fn = env, policy_fn, init_fn
        self.history_len, self.chunk_len, self.max_steps = history_len, chunk_len, max_steps
        self.compact, self.block, self.rows_per_episode = compact, block, rows_per_episode
        self.semantics = semantics
        self.traces = 0
        kwargs = dict(history_len=history_len, chunk_len=chunk_len, max_steps=max_steps, record=True,
                      min_actions=min_actions, semantics=semantics)
        episode = make_episode_fn(env, policy_fn, init_fn, **kwargs)

        def rollout_episode(key, policy_args):
            self.traces += 1
            return episode(key, policy_args)

        self._jitted = jax.jit(jax.vmap(rollout_episode, in_axes=(0, None)))
        # a decision that may execute fewer than chunk_len actions (AAC, asynchronous chunks) stops its control steps
        # early; otherwise the scan is kept (the physics compiles as in the vmapped episode: bit for bit the same
        # states when a block holds every episode)
        loop = make_episode_loop(env, policy_fn, init_fn, early_exit=(min_actions or chunk_len) < chunk_len,
                                 **kwargs)

        def rollout_compacted(keys, policy_args, block):
            self.traces += 1
            return compacted_rollout(loop, keys.shape[0], block)(keys, policy_args)

        self._compacted = jax.jit(rollout_compacted, static_argnums=2)
        self._checked: set = set()

    def block_for(self, num_episodes: int) -> int | None:
        """Episodes per block of a compacted rollout of ``num_episodes`` (None: not compacted)."""
        if not self.compact:
            return None
        return min(self.block, num_episodes) if self.block else default_block(num_episodes, self.rows_per_episode)

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
            state, trace, recording = self._jitted(keys, policy_args)
        elif self.compact:
            state, trace, recording = self._compacted(jax.device_put(keys), policy_args,
                                                      self.block_for(num_episodes))
        else:
            state, trace, recording = self._jitted(jax.device_put(keys), policy_args)
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
                     policy_args=(), min_actions: int | None = None,
                     semantics: Semantics = RATE) -> tuple[EvalResult, Recording]:
    """One-off ``Rollout``: ``evaluate_stateful`` that also returns the batched ``Recording`` (qpos (E, T+1, nq),
    body_pos (E, n, 3)), e.g. to render a video of an evaluated episode. Compiles on every call: keep a ``Rollout``
    to evaluate repeatedly."""
    rollout = Rollout(_resolve(task), policy_fn, init_fn, history_len=history_len, chunk_len=chunk_len,
                      max_steps=max_steps, min_actions=min_actions, semantics=semantics)
    return rollout(num_episodes, key, policy_args)


def evaluate_stateful(policy_fn: StatefulPolicyFn, init_fn: InitFn, task: str | MjxEnv, num_episodes: int,
                      key: jax.Array, *, history_len: int, chunk_len: int, max_steps: int | None = None,
                      policy_args=(), min_actions: int | None = None, semantics: Semantics = RATE) -> EvalResult:
    """``evaluate`` for a policy that carries its own state (see the module docstring)."""
    return rollout_episodes(policy_fn, init_fn, task, num_episodes, key, history_len=history_len,
                            chunk_len=chunk_len, max_steps=max_steps, policy_args=policy_args,
                            min_actions=min_actions, semantics=semantics)[0]


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


def expert_counts(env: MjxEnv, stride: int, num_episodes: int, key: jax.Array, *, chunk_len: int = 8,
                  semantics: Semantics = RATE) -> dict:
    """The scripted expert chunked at ``stride`` (``expert_policy``) on ``num_episodes`` episodes under
    ``semantics``: → {success_rate, mean control steps, actions and decisions per episode}. What a policy that
    reproduced the demos exactly would do at that stride; ``experiments.expert_semantics`` tabulates it."""
    policy_fn, init_fn = expert_policy(env, chunk_len, stride)
    res = evaluate_stateful(policy_fn, init_fn, env, num_episodes, key, history_len=1, chunk_len=chunk_len,
                            semantics=semantics)
    valid = res.valid
    return {"success_rate": float(res.success_rate), "mean_steps": float(jnp.mean(res.steps)),
            "mean_actions": float(jnp.mean(jnp.where(valid, res.actions, 0).sum(axis=1))),
            "mean_decisions": float(jnp.mean(valid.sum(axis=1)))}

