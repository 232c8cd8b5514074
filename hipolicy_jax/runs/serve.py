"""A trained run as a deployable policy: its checkpoint, stored inference settings and calibrated thresholds behind
``deploy``'s ``InProcessBackend`` (what ``experiments.serve --checkpoint`` serves and ``experiments.export``
exports)."""

from __future__ import annotations

import os

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.deploy.backend import InProcessBackend
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.runs.store import load_run, run_inference


def run_backend(path: str, inference: InferenceConfig | None = None, step: int | None = None) -> InProcessBackend:
    """The (EMA) policy of the run at ``path`` (checkpoint ``step``, default the latest) with its stored inference
    settings (or ``inference``) and its calibration's thresholds; the manifest names the run and the step."""
    run = load_run(path, step)
    inference = inference or run_inference(run)
    calib = calibration.read_calibration(run.run_dir)
    thresholds, source = calibration.resolve_thresholds(inference, run.policy.cfg.chunk.num_freqs, calib)
    return InProcessBackend(task=run.task, cfg=run.policy.cfg, action_dim=run.action_dim, params=run.policy.params,
                            normalizer=run.policy.normalizer, inference=inference, thresholds=thresholds,
                            thresholds_source=source,
                            extra={"run": os.path.relpath(run.run_dir), "checkpoint_step": int(run.policy.step)})


__all__ = ["run_backend"]
