"""Execution strategies: how one decision's N sampled chunks become the actions the robot executes.

Every strategy sees the sampler's result for one episode (``Decision``: all N chunks, the entropy, the selected
frequency) and its own memory, and returns a ``rollout.PolicyOutput``: ``exec_len`` actions of which the first
``num_actions`` run before the next decision. ``InferenceConfig.execution`` names the strategy; adding one = a class
here + one line in ``EXECUTIONS`` (+ its name in ``config.ExecutionKind``).

- ``chunk``: the selected frequency's L_c actions, all executed (Diffusion Policy; HiPolicy's entropy-guided
  execution when the thresholds select the frequency).
- ``aac``: adaptive action chunking (AAC, arXiv 2604.04161): parameter-free and training-free. Per step t of the
  selected frequency's chunk the Gaussian action entropy h_t of the N samples; H(k) = mean(h_1..h_k), the mean
  entropy of the first k steps; the decision executes k* actions, where H has its largest jump H(k*+1) − H(k*)
  (uncertainty rises most right after step k*); all L_c when H never rises. High entropy early → short chunks and
  frequent re-planning, low entropy → long chunks.
- ``te``: temporal ensembling (ACT): a decision at every control step; the executed action is the weighted mean of
  every stored chunk's prediction for the current step (the last L_c decisions), weights exp(−m·i) with i = 0 for
  the oldest prediction (ACT's m = 0.01, ``inference.te_decay``).
- ``chunk`` with ``inference.delay`` d > 0: asynchronous execution under an inference delay (``DelayedChunk``). A
  decision taken at control step t0 (from the observation at t0) is ready at t0 + d; meanwhile the robot executes
  the d actions the previous chunk committed for t0..t0+d−1. The new chunk C (its action i is for t0+i) then runs
  from C[d], and the next decision starts d steps before C is used up, at t0 + L_c − d: every decision executes
  L_c − d actions, the d committed ones first. The episode's first decision has nothing committed and runs
  synchronously (C[0 : L_c − d]). With ``handover='inpaint'`` the committed actions are passed to the sampler as
  the prefix of the new chunk (``sampling.sample(prefix=...)``), at every frequency.

A strategy whose decisions read their memory into the sampler offers ``prefix(state) -> (prefix (d, A), valid ())``
(None otherwise); ``policy.make_policy_fn`` passes it on.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple, Protocol

import jax
import jax.numpy as jnp

from hipolicy_jax.config import ChunkConfig, InferenceConfig
from hipolicy_jax.evaluation.rollout import PolicyOutput
from hipolicy_jax.sampling import segment_of


class Decision(NamedTuple):
    """The sampler's result for ONE episode: chunks (N, M·L_c, A) unnormalised, entropy (), freq_index () int32,
    stride () int32, actions (E, A): sample 0's executable actions at the selected frequency (E =
    ``chunk.exec_steps`` from ``chunk.exec_start``; the whole segment, E = L_c, unless the chunk predicts actions
    for observed frames or executes fewer, as Diffusion Policy's ``n_action_steps``)."""

    chunks: jax.Array
    entropy: jax.Array
    freq_index: jax.Array
    stride: jax.Array
    actions: jax.Array


class ExecutionStrategy(Protocol):
    name: str

    def exec_len(self, chunk: ChunkConfig) -> int: ...

    def min_actions(self, chunk: ChunkConfig) -> int: ...

    def init(self, chunk: ChunkConfig, action_dim: int) -> Any: ...

    def decide(self, d: Decision, state: Any, chunk: ChunkConfig) -> tuple[PolicyOutput, Any]: ...


def step_entropies(samples: jax.Array, eps: float = 1e-6) -> jax.Array:
    """Per-step Gaussian action entropy of N samples: (N, T, A) → (T,), the mean over A of 0.5·log(2πe·var + ε)
    with the ddof=1 variance over N (the sampler's entropy, not averaged over time)."""
    var = jnp.var(samples, axis=0, ddof=1)
    return jnp.mean(0.5 * jnp.log(2.0 * jnp.pi * jnp.e * var + eps), axis=-1)


def aac_chunk_size(h: jax.Array) -> jax.Array:
    """AAC's chunk size from per-step entropies h (T,): k* = argmax_k H(k+1) − H(k) with H(k) = mean(h[:k]), k in
    1..T−1; T when H never rises. → () int32 in [1, T]."""
    t = h.shape[0]
    if t == 1:
        return jnp.ones((), jnp.int32)
    running = jnp.cumsum(h) / jnp.arange(1, t + 1)  # H(1..T)
    jumps = running[1:] - running[:-1]  # H(k+1) - H(k), k = 1..T-1
    k = jnp.argmax(jumps).astype(jnp.int32) + 1
    return jnp.where(jumps.max() > 0, k, jnp.int32(t))


def _selected_samples(d: Decision, chunk: ChunkConfig) -> jax.Array:
    """The N samples' executable actions at the selected frequency: (N, E, A)."""
    n = d.chunks.shape[0]
    seg = segment_of(chunk, d.chunks, jnp.broadcast_to(d.freq_index, (n,)))
    return seg[:, chunk.exec_start:chunk.exec_start + chunk.exec_steps]


@dataclasses.dataclass(frozen=True)
class ChunkExecution:
    """Execute the selected frequency's whole chunk (L_c actions) per decision."""

    name: str = "chunk"

    def exec_len(self, chunk: ChunkConfig) -> int:
        return chunk.exec_steps

    def min_actions(self, chunk: ChunkConfig) -> int:
        return chunk.exec_steps

    def init(self, chunk: ChunkConfig, action_dim: int):
        return ()

    def decide(self, d: Decision, state, chunk: ChunkConfig):
        return PolicyOutput(d.actions, d.stride, d.entropy, jnp.int32(chunk.exec_steps)), state


@dataclasses.dataclass(frozen=True)
class AdaptiveChunking:
    """AAC: execute the first k* actions of sample 0's chunk, k* from the entropy curve of the N samples."""

    eps: float = 1e-6
    name: str = "aac"

    def exec_len(self, chunk: ChunkConfig) -> int:
        return chunk.exec_steps

    def min_actions(self, chunk: ChunkConfig) -> int:
        return 1

    def init(self, chunk: ChunkConfig, action_dim: int):
        return ()

    def decide(self, d: Decision, state, chunk: ChunkConfig):
        k = aac_chunk_size(step_entropies(_selected_samples(d, chunk), self.eps))
        return PolicyOutput(d.actions, d.stride, d.entropy, k), state


class EnsembleState(NamedTuple):
    """Temporal ensembling's memory: the last L_c chunks (L_c, L_c, A), newest first (row j was predicted j steps
    ago, so its prediction for the current step is ``chunks[j, j]``), and how many are stored () int32."""

    chunks: jax.Array
    count: jax.Array


@dataclasses.dataclass(frozen=True)
class TemporalEnsembling:
    """ACT's temporal ensembling: one decision and one action per control step."""

    decay: float = 0.01  # m in exp(-m·i), i = 0 for the oldest prediction
    name: str = "te"

    def exec_len(self, chunk: ChunkConfig) -> int:
        return 1

    def min_actions(self, chunk: ChunkConfig) -> int:
        return 1

    def init(self, chunk: ChunkConfig, action_dim: int) -> EnsembleState:
        lc = chunk.exec_steps
        return EnsembleState(jnp.zeros((lc, lc, action_dim), jnp.float32), jnp.zeros((), jnp.int32))

    def decide(self, d: Decision, state: EnsembleState, chunk: ChunkConfig):
        lc = chunk.exec_steps
        chunks = jnp.concatenate([d.actions[None].astype(jnp.float32), state.chunks[:-1]], axis=0)
        count = jnp.minimum(state.count + 1, lc)
        j = jnp.arange(lc)
        preds = chunks[j, j]  # (L_c, A): each stored chunk's prediction for the current step
        age_rank = (count - 1) - j  # 0 for the oldest stored prediction
        w = jnp.where(j < count, jnp.exp(-self.decay * age_rank.astype(jnp.float32)), 0.0)
        action = jnp.sum(w[:, None] * preds, axis=0) / jnp.sum(w)
        return PolicyOutput(action[None], d.stride, d.entropy, jnp.int32(1)), EnsembleState(chunks, count)


class DelayState(NamedTuple):
    """Asynchronous execution's memory: the d actions (d, A) the last chunk committed for the next decision's
    delay, and whether there are any yet () bool (False before the episode's first decision)."""

    pending: jax.Array
    valid: jax.Array


@dataclasses.dataclass(frozen=True)
class DelayedChunk:
    """Whole chunks under an inference delay of ``delay`` control steps (see the module docstring)."""

    delay: int
    handover: str = "naive"  # 'naive' | 'inpaint'
    name: str = "chunk"

    def check(self, chunk: ChunkConfig) -> None:
        if self.handover == "inpaint" and chunk.exec_start:
            raise ValueError(f"inference.handover: 'inpaint' fixes a segment's first d actions, which are for "
                             f"observed frames when chunk.action_offset < 0 (got {chunk.action_offset}); use "
                             f"'naive'")
        if not 1 <= self.delay <= chunk.exec_steps // 2:
            raise ValueError(f"inference.delay: a decision must be ready before the next one starts, so "
                             f"1 <= d <= exec_steps/2 = {chunk.exec_steps // 2}, got {self.delay}")

    def exec_len(self, chunk: ChunkConfig) -> int:
        return chunk.exec_steps

    def min_actions(self, chunk: ChunkConfig) -> int:
        self.check(chunk)
        return chunk.exec_steps - self.delay

    def init(self, chunk: ChunkConfig, action_dim: int) -> DelayState:
        self.check(chunk)
        return DelayState(jnp.zeros((self.delay, action_dim), jnp.float32), jnp.zeros((), bool))

    def prefix(self, state: DelayState):
        return (state.pending, state.valid) if self.handover == "inpaint" else None

    def decide(self, d: Decision, state: DelayState, chunk: ChunkConfig):
        lc, k = chunk.exec_steps, self.delay
        new = d.actions.astype(jnp.float32)  # (L_c, A), action i for control step t0 + i
        first = jnp.where(state.valid, state.pending, new[:k])  # the d steps the decision takes to be ready
        actions = jnp.concatenate([first, new[k:]], axis=0)  # the last d are committed to the next decision
        out = PolicyOutput(actions, d.stride, d.entropy, jnp.int32(lc - k))
        return out, DelayState(new[lc - k:], jnp.ones((), bool))


def make_execution(inference: InferenceConfig) -> ExecutionStrategy:
    """The execution strategy ``inference.execution`` names, with its settings (``DelayedChunk`` when
    ``inference.delay`` > 0)."""
    if inference.delay > 0:
        if inference.execution != "chunk":
            raise ValueError(f"inference.delay: asynchronous execution runs whole chunks, got execution "
                             f"{inference.execution!r}")
        return DelayedChunk(inference.delay, inference.handover)
    if inference.execution not in EXECUTIONS:
        raise ValueError(f"inference.execution: must be one of {sorted(EXECUTIONS)}, got {inference.execution!r}")
    if inference.execution == "aac" and inference.num_samples < 2:
        raise ValueError(f"inference.execution: 'aac' reads the entropy of N >= 2 samples, got "
                         f"inference.num_samples={inference.num_samples}")
    return EXECUTIONS[inference.execution](inference)


EXECUTIONS = {
    "chunk": lambda inference: ChunkExecution(),
    "aac": lambda inference: AdaptiveChunking(eps=inference.entropy_eps),
    "te": lambda inference: TemporalEnsembling(decay=inference.te_decay),
}

__all__ = ["EXECUTIONS", "AdaptiveChunking", "ChunkExecution", "Decision", "DelayState", "DelayedChunk",
           "EnsembleState", "TemporalEnsembling",
           "aac_chunk_size", "make_execution", "step_entropies"]
