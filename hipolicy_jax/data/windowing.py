"""Multi-frequency observation windows and action chunks as frame indices.

For a current frame t and stride s (``ChunkConfig``):

    observations  o[t-(L_h-1)s], ..., o[t-s], o[t]                 (L_h frames ending at t)
    actions       a[t+δ], a[t+δ+s], ..., a[t+δ+(L_c-1)s]           (L_c steps from t+δ)

The M strides are laid out in segment order (``chunk.segment_strides``: largest stride, i.e. lowest frequency,
first), and the action chunk concatenates the M segments along time: ``(M*L_c,)``.

Training (``sample_indices``) turns a replay buffer's episode ends into global frame indices once, at dataset build
time, padding by repeating an episode's first / last frame (Diffusion Policy's sampler convention: observation
history before the first frame repeats it, actions after the last frame repeat it) so that no window crosses an
episode boundary and an episode of any length ≥ 1 trains (``TrainConfig.max_action_pad`` can limit the padding
after the last frame, as Diffusion Policy's ``pad_after`` does). Evaluation (``gather_history``) reads the same
windows out of the env's rolling base-rate history of ``chunk.obs_span`` frames, with jax arrays, under jit / vmap.

Delta actions (``ChunkConfig.action_kinds``): the indices above are right for absolute targets. For a displacement
dimension, taking every s-th recorded delta would leave a stride-s segment with one step of motion per action, a
1/s of the demo's; ``segment_actions`` instead gives each stride-s action the sum of the s deltas of its block
(zero motion for frames outside the episode), so a segment moves as far as the demo did over the same span.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from hipolicy_jax.config import ChunkConfig, check_action_kinds
from hipolicy_jax.data.replay_buffer import check_episode_ends


def obs_offsets(chunk: ChunkConfig) -> np.ndarray:
    """``(M, L_h)`` int64 frame offsets from the current frame: row m is ``-(L_h-1)s, ..., -s, 0`` for stride s."""
    steps = np.arange(chunk.obs_horizon, dtype=np.int64) - (chunk.obs_horizon - 1)  # -(L_h-1), ..., 0
    return np.asarray(chunk.segment_strides, dtype=np.int64)[:, None] * steps[None, :]


def action_offsets(chunk: ChunkConfig) -> np.ndarray:
    """``(M, L_c)`` int64 action offsets from the current frame: row m is ``δ, δ+s, ..., δ+(L_c-1)s``."""
    steps = np.arange(chunk.chunk_len, dtype=np.int64)
    return chunk.action_offset + np.asarray(chunk.segment_strides, dtype=np.int64)[:, None] * steps[None, :]


def sample_indices(episode_ends: np.ndarray, chunk: ChunkConfig,
                   max_action_pad: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Global frame indices of every training sample.

    Args:
      episode_ends: ``(E,)`` cumulative episode ends (ReplayBuffer layout).
      chunk: windowing configuration.
      max_action_pad: ``TrainConfig.max_action_pad``: at most this many of a window's frames past its episode's last
        frame, i.e. current frames ``t <= end - chunk.action_span + max_action_pad`` (``end`` one past the last
        frame); None: no limit. An episode shorter than ``chunk.action_span - max_action_pad`` frames has no such
        window and gives none, with a warning naming it (Diffusion Policy's ``SequenceSampler`` yields exactly these
        windows for ``pad_before = chunk.obs_span - 1``, ``pad_after = max_action_pad`` and sequence length
        ``chunk.obs_span - 1 + chunk.action_span``; it yields none for such an episode, silently).

    Returns:
      current: ``(S,)`` int64 current frames t, every frame of an episode whose first action for a frame >= t,
        ``a[t + max(δ, 0)]``, lies in the episode (and within the limit), in time order; with no limit an episode
        too short for any (one frame with δ = 1) gives its first frame, its actions all the last one's.
      obs_idx: ``(S, M, L_h)`` int64 observation frames per stride (segment order), clamped to the episode.
      act_idx: ``(S, M*L_c)`` int64 action frames, the M segments concatenated in segment order, clamped to the
        episode.

    Raises:
      ValueError: no episode is long enough for a window under ``max_action_pad``.
    """
    ends = check_episode_ends(episode_ends, None)
    starts = np.concatenate([[0], ends[:-1]])
    lengths = ends - starts
    num_valid = np.maximum(lengths - max(chunk.action_offset, 0), 1)  # t ∈ [start, max(end-1-max(δ, 0), start)]
    if max_action_pad is not None:
        # t's window ends at t + action_span - 1 <= end - 1 + max_action_pad
        num_valid = np.clip(lengths - chunk.action_span + max_action_pad + 1, 0, num_valid)
        short = np.flatnonzero(num_valid == 0)
        if short.size:
            need = chunk.action_span - max_action_pad
            listed = ", ".join(f"{e} ({lengths[e]} frames)" for e in short[:10])
            more = f" and {short.size - 10} more" if short.size > 10 else ""
            which = (f"episode {listed} of the buffer's {ends.shape[0]} is" if short.size == 1 else
                     f"episodes {listed}{more} of the buffer's {ends.shape[0]} are")
            msg = (f"train.max_action_pad={max_action_pad}: a window needs an episode of at least {need} frames "
                   f"(chunk.action_span={chunk.action_span} - max_action_pad); {which} shorter")
            if short.size == ends.shape[0]:
                raise ValueError(f"{msg}: no episode has a window (raise train.max_action_pad, or None for no limit)")
            warnings.warn(f"{msg} and train no window" if short.size > 1 else f"{msg} and trains no window",
                          stacklevel=2)
    episode = np.repeat(np.arange(ends.shape[0]), num_valid)
    first_sample = np.concatenate([[0], np.cumsum(num_valid)[:-1]])
    current = starts[episode] + np.arange(episode.shape[0], dtype=np.int64) - first_sample[episode]

    lo = starts[episode][:, None, None]
    hi = (ends[episode] - 1)[:, None, None]
    obs_idx = np.clip(current[:, None, None] + obs_offsets(chunk)[None], lo, hi)
    act_idx = np.clip(current[:, None, None] + action_offsets(chunk)[None], lo, hi)
    return current, obs_idx, act_idx.reshape(current.shape[0], chunk.horizon)


def segment_actions(actions: np.ndarray, episode_ends: np.ndarray, current: np.ndarray, chunk: ChunkConfig,
                    kinds: Sequence[str]) -> np.ndarray:
    """Every sample's action chunk in data units, with delta dimensions carrying their blocks' motion.

    For sample t, the segment at stride s and step i stands for the block of s base-rate frames
    ``b = t+δ+i·s, ..., t+δ+i·s+s-1``:

    - an ``'absolute'`` dimension holds ``a[b_0]``, its first frame clamped to the episode (``sample_indices``'s
      action frames: past the last frame it repeats the last action, i.e. holds the final target);
    - a ``'delta'`` dimension holds ``Σ_j a[b_j]`` over the block's frames that lie inside the episode: a frame
      past the episode's last frame (or before its first, for δ < 0) contributes zero motion, since the robot holds
      still there. So a block wholly past the end is 0 at every stride, stride 1 included (not a repeat of the
      last delta), and a block cut by the end sums only its frames inside.

    With every dimension absolute this equals ``actions[act_idx]`` of ``sample_indices`` exactly.

    Args:
      actions: ``(N, A)`` actions of every frame (ReplayBuffer layout).
      episode_ends: ``(E,)`` cumulative episode ends.
      current: ``(S,)`` current frames t (``sample_indices``'s, or any subset of them).
      chunk: windowing configuration (strides, L_c, δ).
      kinds: ``(A,)`` 'absolute' / 'delta' per action dimension (``ChunkConfig.kinds``).

    Returns:
      ``(S, M*L_c, A)`` in the actions' dtype, the M segments concatenated in segment order. Delta sums are taken
      in float64 and rounded once.
    """
    actions = np.asarray(actions)
    kinds = check_action_kinds(kinds, "kinds", actions.shape[-1])
    ends = check_episode_ends(episode_ends, actions.shape[0])
    current = np.asarray(current, np.int64)
    episode = np.searchsorted(ends, current, side="right")
    start = np.concatenate([[0], ends[:-1]])[episode][:, None, None]  # (S, 1, 1)
    end = ends[episode][:, None, None]
    first = current[:, None, None] + action_offsets(chunk)[None]  # (S, M, L_c) each block's first frame
    out = actions[np.clip(first, start, end - 1).reshape(current.shape[0], chunk.horizon)]
    delta = np.asarray([k == "delta" for k in kinds])
    if delta.any():
        moves = actions[:, delta].astype(np.float64)
        sums = []
        for m, s in enumerate(chunk.segment_strides):  # M strides; every sample at once
            frames = first[:, m, :, None] + np.arange(s)  # (S, L_c, s)
            inside = (frames >= start) & (frames < end)
            sums.append((moves[np.clip(frames, 0, moves.shape[0] - 1)] * inside[..., None]).sum(axis=2))
        out[..., delta] = np.concatenate(sums, axis=1).astype(out.dtype)
    return out


def check_recorded_kinds(kinds: Sequence[str], recorded: Sequence[str] | None, where: str,
                         field: str = "chunk.action_kinds") -> None:
    """Raise a one-line ``ValueError`` when ``recorded`` (a buffer's or a task's kinds; None: not recorded) differs
    from ``kinds``, the policy's (``field``)."""
    if recorded is not None and tuple(recorded) != tuple(kinds):
        raise ValueError(f"{field}: the policy's actions are {list(kinds)}, but {where} has action_kinds "
                         f"{list(recorded)}; pass --policy.chunk.action-kinds {' '.join(recorded)} (or leave it None: "
                         f"training takes the demos')")


def resolve_chunk_kinds(chunk: ChunkConfig, recorded: Sequence[str] | None, task_kinds: Sequence[str] | None,
                        action_dim: int, where: str) -> ChunkConfig:
    """The chunk a run trains with, its ``action_kinds`` settled against its demos (``runs.train``).

    The demos' kinds are the buffer's ``recorded`` ones (its ``action_kinds`` attribute), else the task's
    ``task_kinds`` (a task acts with one kind of action: MJX tasks absolute, an external suite its own), else
    unknown. A chunk that declares its kinds keeps them, and they must equal the demos' where those are known. A
    chunk that leaves them None takes the demos' kinds: stored in the returned chunk when any is a delta, left None
    when all are absolute (so a run's identity is what it was before kinds existed); unknown kinds are refused when
    a stride above 1 needs them (at stride 1 alone both kinds sample every recorded action; only the padding past
    an episode's end differs, and unknown kinds train as absolute, as before kinds existed).

    Args:
      chunk: the run's windowing; recorded / task_kinds: ``(A,)`` kinds or None; action_dim: A; where: the
        buffer, for messages.

    Raises:
      ValueError: one line naming the field, when kinds disagree, have the wrong length, or are needed and unknown.
    """
    if recorded is not None:
        recorded = check_action_kinds(recorded, f"{where}: action_kinds", action_dim)
    if recorded is not None and task_kinds is not None and tuple(task_kinds) != recorded:
        raise ValueError(f"data: {where} has action_kinds {list(recorded)}, its task acts with {list(task_kinds)}; "
                         f"these demos are not of this task (pass its --task or other --data)")
    known = recorded if recorded is not None else task_kinds
    if chunk.action_kinds is not None:
        check_recorded_kinds(chunk.kinds(action_dim), known, where if recorded is not None else "its task")
        return chunk
    if known is None:
        if max(chunk.strides) > 1:
            raise ValueError(f"chunk.action_kinds: {where} does not record whether its {action_dim} action dimensions "
                             f"are 'absolute' or 'delta' (its action_kinds attribute), and strides {chunk.strides} "
                             f"need it; pass --policy.chunk.action-kinds (one per dimension) or import the data "
                             f"with --action-kinds")
        return chunk
    known = check_action_kinds(known, "action_kinds", action_dim)
    return dataclasses.replace(chunk, action_kinds=known) if "delta" in known else chunk


def history_window_indices(chunk: ChunkConfig) -> np.ndarray:
    """``(M, L_h)`` positions inside a base-rate history of ``chunk.obs_span`` frames (last = current) per stride.

    For strides (1, 2, 3) and L_h = 3: obs_span 7 and ``[[0, 3, 6], [2, 4, 6], [4, 5, 6]]``.
    """
    return obs_offsets(chunk) + (chunk.obs_span - 1)


def gather_history(history: dict[str, jnp.ndarray], chunk: ChunkConfig) -> dict[str, jnp.ndarray]:
    """Per-stride observation windows from a rolling history.

    Args:
      history: ``{key: (obs_span, ...)}`` base-rate frames, oldest first, the last one current; frames before the
        episode start should repeat the first frame (as ``sample_indices`` pads).
      chunk: windowing configuration.

    Returns:
      ``{key: (M, L_h, ...)}`` in segment order. Works on numpy or jax arrays, under jit and vmap.
    """
    idx = history_window_indices(chunk)
    out = {}
    for key, frames in history.items():
        if frames.shape[0] != chunk.obs_span:
            raise ValueError(f"history[{key!r}]: expected (obs_span={chunk.obs_span}, ...) frames, "
                             f"got shape {frames.shape}")
        out[key] = jnp.take(frames, idx, axis=0)
    return out


def delta_segment_coverage(actions: np.ndarray, episode_ends: np.ndarray, chunk: ChunkConfig,
                           dims: tuple[int, ...] = (0, 1, 2), min_norm: float = 0.5) -> dict[int, np.ndarray]:
    """How far a stride's segment moves the robot, when actions are per-step displacements, relative to the demo's
    movement over the time that segment stands for.

    A segment at stride s from frame t holds a[t+δ], a[t+δ+s], ..., a[t+δ+(L_c-1)s] and is executed one action per
    control step. With absolute targets (the MJX tasks) its last target is the demo's at t+δ+(L_c-1)s, so it gets
    where the demo got, s times sooner. With displacements (Meta-World: xyz moves of the hand's target) it moves
    ``C = Σ_k a[t+δ+ks]`` while the demo moved ``D = Σ_{i<L_c s} a[t+δ+i]`` over the span, and any absolute channel
    (a gripper command) still follows the demo's schedule over the whole span. Coverage is C projected on D,
    ``C·D / |D|²``: 1 at stride 1, about 1/s for smooth motion.

    Args:
      actions: ``(N, A)`` actions of every frame (ReplayBuffer layout).
      episode_ends: ``(E,)`` cumulative episode ends.
      chunk: windowing configuration (strides, L_c, δ).
      dims: the displacement channels of an action.
      min_norm: windows whose demo displacement ``|D|`` is below it (action units) are left out (the robot holds
        still: no direction to cover).

    Returns:
      ``{stride: (W,) coverage}`` over every window whose span lies inside its episode and moves at least
      ``min_norm``, in time order.
    """
    actions = np.asarray(actions, np.float64)[:, list(dims)]
    ends = check_episode_ends(episode_ends, actions.shape[0])
    starts = np.concatenate([[0], ends[:-1]])
    csum = np.concatenate([np.zeros((1, actions.shape[1])), np.cumsum(actions, axis=0)])  # csum[i] = Σ_{j<i} a[j]
    out = {}
    for s in sorted(set(chunk.segment_strides)):
        span = chunk.chunk_len * s
        first = [np.arange(a + chunk.action_offset, e - span + 1) for a, e in zip(starts, ends)]
        first = np.concatenate(first) if first else np.zeros(0, np.int64)
        executed = actions[first[:, None] + s * np.arange(chunk.chunk_len)[None, :]].sum(axis=1)  # (W, d) C
        demo = csum[first + span] - csum[first]  # (W, d) D
        norm2 = (demo ** 2).sum(axis=1)
        keep = norm2 >= min_norm ** 2
        out[s] = (executed * demo).sum(axis=1)[keep] / norm2[keep]
    return out


def steps_at_bound(actions: np.ndarray, episode_ends: np.ndarray, dims: tuple[int, ...] = (0, 1, 2),
                   bound: float = 1.0) -> np.ndarray:
    """Per episode, the fewest control steps in which displacements of at most ``bound`` per channel trace its
    demo's path: Σ_t max_i |a[t, i]| / bound over the ``dims`` channels (the path's length in the max norm). With
    Meta-World's actions (xyz moves of the hand's target, at most 1 cm a step) it is how fast any policy, at any
    stride, could follow the demo's hand path; steps that only move the gripper count zero, so it is a lower bound.

    Args:
      actions: ``(N, A)`` per-step displacements of every frame (ReplayBuffer layout).
      episode_ends: ``(E,)`` cumulative episode ends.
      dims: the displacement channels of an action.
      bound: the largest displacement a step can make per channel.

    Returns:
      ``(E,)`` steps, fractional.
    """
    moves = np.abs(np.asarray(actions, np.float64)[:, list(dims)]).max(axis=1) / bound  # (N,)
    ends = check_episode_ends(episode_ends, moves.shape[0])
    return np.add.reduceat(moves, np.concatenate([[0], ends[:-1]]))
