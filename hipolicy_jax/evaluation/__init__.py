"""Evaluation, the stage after sampling: a trained policy in closed loop on the MJX tasks, and its thresholds.

    sampling (``hipolicy_jax.sampling``) -> **evaluation** -> experiments (``runs``, ``campaigns``,
    ``experiments/``); ``deploy`` serves the same decision over a websocket

* ``policy``: trained network -> per-episode policy: observation history -> windows -> the one sampler -> the
  execution strategy (``make_policy_fn``, ``make_decision_fn``, ``PolicyArgs``);
* ``execution``: how one decision's N chunks become executed actions: ``chunk``, ``aac`` (adaptive action chunking),
  ``te`` (temporal ensembling) and asynchronous chunks under an inference delay (``make_execution``,
  ``EXECUTIONS``);
* ``rollout``: the batched episode loop: ``Rollout`` owns one compiled rollout of every episode, either
  ``jit(vmap(episode))`` or the compacted rollout (``compact=True``: only the episodes still running decide);
  ``evaluate`` / ``evaluate_stateful`` / ``rollout_episodes`` for one-off use; the scripted expert as a policy
  (``expert_policy``); ``PolicyOutput``, ``EvalResult``, ``Recording``;
* ``evaluator``: ``Evaluator`` (evaluate / calibrate one policy setting on one task; compacted rollout by default),
  ``eval_summary`` and ``result_record``;
* ``calibration``: entropy measurement, percentile and success-constrained thresholds, threshold resolution,
  ``calibration.json``;
* ``phases``: how long rollouts hold a timed phase (press_button's hold), per executed stride;
* ``stats``: seed-level estimates, intervals and tests of evaluation outcomes (results/PROTOCOL.md v2);
* ``plots`` / ``video``: entropy traces, histograms and rollout videos.

Public names re-exported here: ``Evaluator``, ``eval_summary``, ``result_record``, ``Rollout``, ``EvalResult``,
``PolicyOutput``, ``Recording``; everything else comes from its module. Within ``hipolicy_jax`` this package imports
``config``, ``data``, ``envs``, ``models``, ``sampling``, ``parallel`` and ``jsonio``.
"""

from hipolicy_jax.evaluation.evaluator import Evaluator, eval_summary, result_record
from hipolicy_jax.evaluation.rollout import EvalResult, PolicyOutput, Recording, Rollout

__all__ = ["EvalResult", "Evaluator", "PolicyOutput", "Recording", "Rollout", "eval_summary", "result_record"]
