"""Calibrate a trained run's entropy thresholds from held-out demos or from its own closed-loop rollouts.

``demos``: the validation episodes of the run's demo buffer, split as in training, with the training calibration
key, so the defaults reproduce the ``calibration.json`` training wrote. ``rollouts``: every replan's entropy of
closed-loop episodes executed at the highest frequency (initial states disjoint from ``evaluate``'s).
"""

from __future__ import annotations

import os
from typing import Literal

import jax
import numpy as np

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.evaluation import calibration, plots
from hipolicy_jax.runs.store import Run, eval_key, heldout_dataset, make_evaluator
from hipolicy_jax.trainer import run_keys


def run_entropies(run: Run, inference: InferenceConfig, source: Literal["demos", "rollouts"] = "demos", *,
                  episodes: int = 20, seed: int | None = None, evaluator=None) -> np.ndarray:
    """Action entropies of the run's held-out demo windows (``inference.calib_windows`` of them) or of every replan
    of ``episodes`` closed-loop episodes at the highest frequency."""
    seed = run.seed if seed is None else seed
    ev = evaluator or make_evaluator(run, inference)
    p = run.policy
    if source == "demos":
        return ev.measure_entropies(p.params, p.normalizer, heldout_dataset(run), run_keys(seed)["eval"])
    if source != "rollouts":
        raise ValueError(f"source: must be 'demos' or 'rollouts', got {source!r}")
    result = ev.evaluate(p.params, p.normalizer, episodes, jax.random.fold_in(eval_key(seed), 1),
                         entropy_guided=False)
    return np.asarray(result.entropy)[np.asarray(result.valid)]


def calibrate_run(run: Run, inference: InferenceConfig, source: Literal["demos", "rollouts"] = "demos", *,
                  episodes: int = 20, seed: int | None = None, out: str = "", bins: int = 24) -> dict:
    """Thresholds at ``inference.percentiles`` of ``run_entropies``; writes the calibration record to ``out``
    (default ``<run>/calibration.json``) and a histogram PNG next to it; → the record (+ ``entropies``)."""
    cfg = run.policy.cfg
    m = cfg.chunk.num_freqs
    percentiles = calibration.effective_percentiles(m, inference.percentiles) if m > 1 else ()
    seed = run.seed if seed is None else seed
    entropies = run_entropies(run, inference, source, episodes=episodes, seed=seed)
    thresholds = calibration.calibrate_thresholds(entropies, m, percentiles or None)
    path = out or os.path.join(run.run_dir, calibration.CALIBRATION_FILE)
    plot = plots.plot_histogram(entropies, thresholds, cfg.chunk.strides, os.path.splitext(path)[0] + ".png",
                                bins=bins, title=f"{run.task} @ step {run.policy.step}: entropies of {source} "
                                f"(N={inference.num_samples}), thresholds at percentiles {list(percentiles)}")
    record = calibration.calibration_record(entropies, thresholds, m, inference, bins=bins, source=source, seed=seed,
                                            checkpoint_step=run.policy.step, task=run.task, plot=plot)
    calibration.write_calibration(record, path)
    return {**record, "path": path, "entropies": entropies}
