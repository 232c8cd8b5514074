"""Calibrate a trained run's entropy thresholds from held-out demos or from its own closed-loop rollouts.

``demos``: the validation episodes of the run's demo buffer, split as in training, with the training calibration
key, so the defaults reproduce the ``calibration.json`` training wrote. ``rollouts``: every replan's entropy of
closed-loop episodes executed at the highest frequency (initial states disjoint from ``evaluate``'s).

Two rules turn entropies into thresholds: ``percentiles`` (``inference.percentiles`` of the entropies: the paper's)
and ``success`` (closed loop only): every candidate of a ladder of percentiles (``calibration.percentile_ladder``,
cautious to aggressive) is rolled out with entropy guidance on the same calibration episodes, and the most
aggressive whose success is within ``margin`` of those episodes' success at stride 1 is kept. The record keeps
every candidate's success, control steps, intended and achieved stride mix.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Literal, Sequence

import jax
import numpy as np

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.evaluation import calibration, plots
from hipolicy_jax.runs.store import Run, eval_key, heldout_dataset, make_evaluator
from hipolicy_jax.trainer import run_keys


def calibration_key(seed: int) -> jax.Array:
    """The key of a run's closed-loop calibration episodes: initial states disjoint from ``eval_key(seed)``'s."""
    return jax.random.fold_in(eval_key(seed), 1)


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
    result = ev.evaluate(p.params, p.normalizer, episodes, calibration_key(seed), entropy_guided=False)
    return np.asarray(result.entropy)[np.asarray(result.valid)]


def success_constrained(run: Run, inference: InferenceConfig, *, episodes: int = 20, seed: int | None = None,
                        margin: float = 0.05, ladder: Sequence[Sequence[float]] | None = None,
                        evaluator=None) -> dict:
    """The success-constrained rule on ``episodes`` calibration episodes (``calibration_key``): stride-1 rollouts
    give the entropies and the baseline success; each ``ladder`` candidate (default ``percentile_ladder``) is rolled
    out with entropy guidance from the same initial states. → {entropies, baseline, candidates, chosen (index),
    percentiles, thresholds}."""
    cfg = run.policy.cfg
    m = cfg.chunk.num_freqs
    if m == 1:
        raise ValueError("rule: 'success' chooses among strides; a single-stride policy has none to choose")
    seed = run.seed if seed is None else seed
    ev = evaluator or make_evaluator(run, inference)
    p, key = run.policy, calibration_key(seed)
    base = ev.evaluate(p.params, p.normalizer, episodes, key, entropy_guided=False)
    entropies = np.asarray(base.entropy)[np.asarray(base.valid)]
    ladder = calibration.percentile_ladder(m) if ladder is None else tuple(tuple(map(float, q)) for q in ladder)
    candidates = []
    for q in ladder:
        thresholds = calibration.calibrate_thresholds(entropies, m, q)
        res = ev.evaluate(p.params, p.normalizer, episodes, key, thresholds, entropy_guided=True)
        candidates.append({"percentiles": list(q), "thresholds": [float(t) for t in thresholds],
                           "success_rate": float(res.success_rate),
                           "mean_steps": float(np.mean(np.asarray(res.steps))),
                           "intended_mix": calibration.intended_mix(q, cfg.chunk.strides),
                           "achieved_mix": calibration.achieved_mix(res.stride, res.valid, cfg.chunk.strides)})
    chosen = calibration.choose_success_constrained(candidates, float(base.success_rate), margin)
    return {"entropies": entropies, "candidates": candidates, "chosen": chosen, "margin": margin,
            "baseline": {"success_rate": float(base.success_rate),
                         "mean_steps": float(np.mean(np.asarray(base.steps)))},
            "percentiles": tuple(candidates[chosen]["percentiles"]),
            "thresholds": tuple(candidates[chosen]["thresholds"])}


def calibrate_run(run: Run, inference: InferenceConfig, source: Literal["demos", "rollouts"] = "demos", *,
                  episodes: int = 20, seed: int | None = None, out: str = "", bins: int = 24,
                  rule: Literal["percentiles", "success"] = "percentiles", margin: float = 0.05,
                  ladder: Sequence[Sequence[float]] | None = None) -> dict:
    """Thresholds by ``rule`` (the module docstring): at ``inference.percentiles`` of ``run_entropies``, or the
    success-constrained choice (``success_constrained``; closed-loop ``source='rollouts'`` only); writes the
    calibration record to ``out`` (default ``<run>/calibration.json``) and a histogram PNG next to it; → the record
    (+ ``entropies``)."""
    cfg = run.policy.cfg
    m = cfg.chunk.num_freqs
    seed = run.seed if seed is None else seed
    extra = {}
    if rule == "success":
        if source != "rollouts":
            raise ValueError(f"rule: 'success' rolls the candidates out in closed loop; it needs source "
                             f"'rollouts', got {source!r}")
        chosen = success_constrained(run, inference, episodes=episodes, seed=seed, margin=margin, ladder=ladder)
        entropies, thresholds, percentiles = chosen["entropies"], chosen["thresholds"], chosen["percentiles"]
        inference = dataclasses.replace(inference, percentiles=percentiles)
        extra = {k: chosen[k] for k in ("candidates", "chosen", "margin", "baseline")}
    elif rule == "percentiles":
        percentiles = calibration.effective_percentiles(m, inference.percentiles) if m > 1 else ()
        entropies = run_entropies(run, inference, source, episodes=episodes, seed=seed)
        thresholds = calibration.calibrate_thresholds(entropies, m, percentiles or None)
    else:
        raise ValueError(f"rule: must be 'percentiles' or 'success', got {rule!r}")
    if m > 1:
        extra["intended_mix"] = calibration.intended_mix(percentiles, cfg.chunk.strides)
    path = out or os.path.join(run.run_dir, calibration.CALIBRATION_FILE)
    plot = plots.plot_histogram(entropies, thresholds, cfg.chunk.strides, os.path.splitext(path)[0] + ".png",
                                bins=bins, title=f"{run.task} @ step {run.policy.step}: entropies of {source} "
                                f"(N={inference.num_samples}), thresholds at percentiles {list(percentiles)}")
    record = calibration.calibration_record(entropies, thresholds, m, inference, bins=bins, source=source, seed=seed,
                                            checkpoint_step=run.policy.step, task=run.task, plot=plot, rule=rule,
                                            **extra)
    calibration.write_calibration(record, path)
    return {**record, "path": path, "entropies": entropies}
