"""``Evaluator``: closed-loop evaluation and threshold calibration of one policy setting on one task.

An ``Evaluator`` is built once per (task, policy config, action dim, inference settings) and owns everything it
compiles: the task's env (with the encoder's camera), the per-episode policy, the batched rollout
(``rollout.Rollout``) and, for calibration, the batched sampler. Evaluating another checkpoint of the same run,
with or without entropy guidance, or with other thresholds, reuses those compiles; there is no global cache, so
dropping the evaluator frees them.

    ev = Evaluator("press_button", cfg, action_dim=4, inference=InferenceConfig(num_samples=16))
    thresholds, entropies = ev.calibrate(params, normalizer, heldout_dataset, key)
    result, recording = ev.rollout(params, normalizer, 50, key, thresholds)          # entropy-guided
    plain, _ = ev.rollout(params, normalizer, 50, key, thresholds, entropy_guided=False)   # same compile
"""

from __future__ import annotations

import numpy as np

from hipolicy_jax import envs as envs_lib
from hipolicy_jax.config import InferenceConfig, PolicyConfig
from hipolicy_jax.envs.base import MjxEnv
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.evaluation.policy import PolicyArgs, make_policy_fn
from hipolicy_jax.evaluation.execution import make_execution
from hipolicy_jax.evaluation.rollout import EvalResult, Recording, Rollout, Semantics
from hipolicy_jax.models.policy_net import PolicyNet
from hipolicy_jax.sampling import make_sampler


class Evaluator:
    """Closed-loop evaluation of ``PolicyNet(cfg, action_dim)`` on ``task`` with the ``inference`` settings.

    ``task``: a task name (the env is built for the encoder's observations and camera) or an env. ``max_steps``
    caps episodes (default: the task's limit). ``traces`` counts rollout traces (one per compile). ``compact``
    (default): finished episodes stop costing sampler and physics (``rollout.Rollout``, blocks of
    ``rollout.default_block(episodes, inference.samples_drawn(...))`` episodes); False: the vmapped episode of every
    episode to the end of the longest.
    """

    def __init__(self, task: str | MjxEnv, cfg: PolicyConfig, action_dim: int,
                 inference: InferenceConfig = InferenceConfig(), *, max_steps: int | None = None,
                 compact: bool = True):
        self.cfg, self.action_dim, self.inference = cfg, action_dim, inference
        speed = {} if inference.controller_speed is None else {"controller_speed": inference.controller_speed}
        self.env = envs_lib.make_for_encoder(task, cfg.encoder, **speed) if isinstance(task, str) else task
        self.task = task if isinstance(task, str) else task.name
        if self.env.action_dim != action_dim:
            raise ValueError(f"action_dim: the policy predicts {action_dim}-dim actions, the {self.task} env takes "
                             f"{self.env.action_dim}")
        self.net = PolicyNet(cfg, action_dim)
        execution = make_execution(inference)
        policy_fn, init_fn = make_policy_fn(self.net, cfg, action_dim, inference)
        self._rollout = Rollout(self.env, policy_fn, init_fn, history_len=cfg.chunk.obs_span,
                                chunk_len=execution.exec_len(cfg.chunk), max_steps=max_steps,
                                min_actions=execution.min_actions(cfg.chunk), compact=compact,
                                rows_per_episode=inference.samples_drawn(cfg.chunk.num_freqs),
                                semantics=Semantics.of(inference, self.env))
        self._sampler = None

    @property
    def traces(self) -> int:
        return self._rollout.traces

    @property
    def rollout_kind(self) -> str:
        """Which rollout evaluates: ``"compacted"`` (``compact``) or ``"vmapped"``; campaign records keep it, since
        the two take different times for the same evaluation."""
        return "compacted" if self._rollout.compact else "vmapped"

    def rollout(self, params, normalizer, num_episodes: int, key, thresholds=None,
                entropy_guided: bool | None = None) -> tuple[EvalResult, Recording]:
        """Roll out ``num_episodes`` episodes (initial states from ``key``) in one compiled call → (result, qpos
        recording). ``thresholds``: M+1 values or None (highest frequency); ``entropy_guided`` (default
        ``inference.entropy_guided``) False always executes the highest frequency."""
        guided = self.inference.entropy_guided if entropy_guided is None else entropy_guided
        th = calibration.guidance_thresholds(thresholds, self.cfg.chunk.num_freqs, guided)
        return self._rollout(num_episodes, key, PolicyArgs(params, normalizer, th))

    def evaluate(self, params, normalizer, num_episodes: int, key, thresholds=None,
                 entropy_guided: bool | None = None) -> EvalResult:
        """``rollout`` without the recording."""
        return self.rollout(params, normalizer, num_episodes, key, thresholds, entropy_guided)[0]

    def measure_entropies(self, params, normalizer, dataset, key) -> np.ndarray:
        """Action entropies of ``inference.calib_windows`` evenly spaced windows of ``dataset`` (its batches come
        normalised, as ``SequenceDataset`` gives them), through one compiled sampler."""
        if self.inference.num_samples < 2:
            raise ValueError(f"inference.num_samples: entropy needs N >= 2 samples, got "
                             f"{self.inference.num_samples}")
        if self._sampler is None:
            self._sampler = make_sampler(self.net, self.cfg, self.action_dim, self.inference, obs_normalized=True)
        return calibration.measure_entropies(self._sampler, params, normalizer, dataset, key,
                                             max_windows=self.inference.calib_windows)

    def calibrate(self, params, normalizer, dataset, key) -> tuple[tuple[float, ...], np.ndarray]:
        """Thresholds at ``inference.percentiles`` of the entropies of ``dataset``'s windows → (M+1 thresholds,
        entropies). A single-frequency policy needs none: ((−inf, +inf), empty)."""
        m = self.cfg.chunk.num_freqs
        if m == 1:
            return calibration.calibrate_thresholds(np.zeros(0), 1), np.zeros(0)
        h = self.measure_entropies(params, normalizer, dataset, key)
        return calibration.calibrate_thresholds(h, m, self.inference.percentiles), h


def eval_summary(result: EvalResult) -> dict:
    """JSON-able scalars of an ``EvalResult``: success rate, mean control steps (all / successful episodes), mean
    decisions and actions per episode, actions executed per decision, stride fractions, mean entropy."""
    valid = np.asarray(result.valid)
    strides = np.asarray(result.stride)[valid]
    actions = np.asarray(result.actions)
    out = {"success_rate": float(result.success_rate), "mean_steps_success": float(result.mean_steps_success),
           "mean_steps": float(np.mean(np.asarray(result.steps))),
           "mean_decisions": float(valid.sum(axis=1).mean()),
           "mean_actions": float(np.where(valid, actions, 0).sum(axis=1).mean()),
           "mean_actions_per_decision": float(actions[valid].mean()) if valid.any() else np.nan}
    for s in np.unique(strides):
        out[f"stride{int(s)}_frac"] = float(np.mean(strides == s))
    ent = np.asarray(result.entropy)[valid]
    if ent.size and np.isfinite(ent).any():
        out["mean_entropy"] = float(np.nanmean(ent))
    return out


def result_record(result: EvalResult) -> dict:
    """``eval_summary`` plus per episode: success, control steps (``steps``), decisions and actions executed."""
    valid = np.asarray(result.valid)
    return {**eval_summary(result), "success": [bool(x) for x in np.asarray(result.success)],
            "steps": [int(x) for x in np.asarray(result.steps)],
            "decisions": [int(x) for x in valid.sum(axis=1)],
            "actions": [int(x) for x in np.where(valid, np.asarray(result.actions), 0).sum(axis=1)]}
