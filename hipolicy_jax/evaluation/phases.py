"""Timed phases: how long rollouts hold a phase whose duration the task's success checks, and at which stride.

A chunk predicted at stride s covers s·L_c steps of demonstration time in L_c control steps (``rollout``): coarse
strides replay the demonstrations faster. Where success needs a phase to *last* (press_button: the cap held
pressed for ``hold_steps`` control steps), a phase the demos hold for k steps lasts about k/s steps when a
stride-s chunk executes it. An env names such a phase with ``MjxEnv.timed_phase(qpos)`` (None when it has none);
``timed_phase_report`` reads it from a rollout's ``Recording`` and the strides of its decisions.

Shapes: ``EvalResult`` per-decision fields (E, R); ``Recording.qpos`` (E, T+1, nq), index 0 the reset state and
index t the state after control step t-1.
"""

from __future__ import annotations

import numpy as np

from hipolicy_jax.evaluation.rollout import EvalResult, Recording


def step_strides(result: EvalResult, num_steps: int) -> np.ndarray:
    """The stride of the decision executing each control step → (E, num_steps) int, 0 where no decision ran."""
    start, stride = np.asarray(result.start), np.asarray(result.stride)
    executed, valid = np.asarray(result.executed), np.asarray(result.valid)
    out = np.zeros((start.shape[0], num_steps), np.int64)
    for e, r in zip(*np.nonzero(valid)):
        out[e, start[e, r]:start[e, r] + executed[e, r]] = stride[e, r]
    return out


def phase_runs(in_phase: np.ndarray, strides: np.ndarray, steps: int) -> list[tuple[int, int]]:
    """Maximal runs of one episode's phase → [(length in control steps, stride)], the stride the one most of the
    run's steps executed at (ties: the smaller). ``in_phase`` (T+1,) bool per recorded state, ``strides`` (T,) per
    control step, ``steps`` the control steps the episode ran (states 1..steps count)."""
    runs, t = [], 1
    while t <= steps:
        if not in_phase[t]:
            t += 1
            continue
        s = t
        while t <= steps and in_phase[t]:
            t += 1
        counts = np.bincount(strides[s - 1:t - 1])
        runs.append((t - s, int(np.argmax(counts))))
    return runs


def timed_phase_report(env, result: EvalResult, recording: Recording) -> dict | None:
    """Per-episode and per-stride durations of ``env.timed_phase`` in one batched rollout, or None (no such phase).

    → ``{"required_steps", "reached": fraction of episodes whose longest run lasts the required steps,
    "longest": per-episode longest run, "by_stride": {stride: {"runs", "median_steps", "reached"}}}`` where
    ``by_stride`` groups every run by the stride that executed most of it, ``reached`` the share of those runs
    that last the required steps."""
    timed = env.timed_phase(np.asarray(recording.qpos))
    if timed is None:
        return None
    in_phase, need = timed
    steps = np.asarray(result.steps)
    strides = step_strides(result, in_phase.shape[1] - 1)
    per_episode = [phase_runs(in_phase[e], strides[e], int(steps[e])) for e in range(len(steps))]
    longest = [max((n for n, _ in runs), default=0) for runs in per_episode]
    by_stride: dict[int, list[int]] = {}
    for runs in per_episode:
        for n, s in runs:
            by_stride.setdefault(s, []).append(n)
    return {"required_steps": int(need),
            "reached": float(np.mean(np.asarray(longest) >= need)),
            "longest": longest,
            "by_stride": {str(s): {"runs": len(v), "median_steps": float(np.median(v)),
                                   "reached": float(np.mean(np.asarray(v) >= need))}
                          for s, v in sorted(by_stride.items())}}
