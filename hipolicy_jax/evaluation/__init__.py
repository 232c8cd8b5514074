"""Inference and evaluation as a library stage: closed-loop rollouts, the per-episode policy, threshold calibration,
the ``Evaluator`` that owns their compiled programs, plots and videos.

- ``rollout``: the batched episode loop (``Rollout`` owns one compiled ``jit(vmap(episode))``), the scripted expert
  as a policy;
- ``policy``: trained network → per-episode ``policy_fn`` over the one sampler;
- ``calibration``: entropy measurement, percentile thresholds, threshold resolution, ``calibration.json``;
- ``evaluator``: ``Evaluator`` (evaluate / calibrate one policy setting on one task) and result summaries;
- ``plots`` / ``video``: entropy traces, histograms and rollout videos.
"""

from hipolicy_jax.evaluation.evaluator import Evaluator, eval_summary, result_record
from hipolicy_jax.evaluation.rollout import EvalResult, PolicyOutput, Recording, Rollout

__all__ = ["EvalResult", "Evaluator", "PolicyOutput", "Recording", "Rollout", "eval_summary", "result_record"]
