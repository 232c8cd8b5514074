"""Calibrate a trained run's entropy thresholds from held-out demos or from its own closed-loop rollouts.

``demos``: the validation episodes of the run's demo buffer, split as in training, with the training calibration
key, so the defaults reproduce the ``calibration.json`` training wrote. ``rollouts``: every replan's entropy of
closed-loop episodes executed at the highest frequency (initial states disjoint from ``evaluate``'s).

Two rules turn entropies into thresholds: ``percentiles`` (``inference.percentiles`` of the entropies: the paper's)
and ``success`` (closed loop only): every candidate of a ladder of percentiles (``calibration.percentile_ladder``,
cautious to aggressive) is rolled out with entropy guidance on the same calibration episodes, and the most
aggressive whose success is within ``margin`` of those episodes' success at stride 1 is kept. The record keeps
every candidate's success, control steps, intended and achieved stride mix.

Closed-loop episodes run where the task does (``closed_loop``): an MJX task in one compiled ``Evaluator`` rollout
(initial states from ``calibration_key``), an external task (``metaworld:<task>``) through the policy server and its
bridge (``runs.external.calibration_rollout``: initial-state seeds ``CALIBRATION_SEED + 1000 seed + i``). Both are
disjoint from the evaluation's episodes; one candidate loop serves both.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Callable, Literal, NamedTuple, Sequence

import jax
import numpy as np

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.envs import external
from hipolicy_jax.evaluation import calibration, plots
from hipolicy_jax.runs.store import Run, eval_key, heldout_dataset, make_evaluator
from hipolicy_jax.trainer import run_keys


def calibration_key(seed: int) -> jax.Array:
    """The key of a run's closed-loop calibration episodes: initial states disjoint from ``eval_key(seed)``'s."""
    return jax.random.fold_in(eval_key(seed), 1)


class ClosedLoop(NamedTuple):
    """One pass over a run's calibration episodes: D decision slots (E × R for an MJX rollout, every decision of
    every episode for a bridge's), of which ``valid`` ran."""

    success_rate: float
    mean_steps: float  # control steps per episode
    entropy: np.ndarray  # (D,) float: each decision's entropy (NaN where it had none)
    stride: np.ndarray  # (D,) int: the stride each decision executed
    valid: np.ndarray  # (D,) bool


def closed_loop(run: Run, inference: InferenceConfig, *, episodes: int = 20, seed: int | None = None,
                evaluator=None, envs: int = 8, log=print,
                max_steps: int | None = None) -> Callable[[Sequence[float] | None], ClosedLoop]:
    """``evaluate_thresholds(thresholds) -> ClosedLoop`` on the run's ``episodes`` calibration episodes (the same
    initial states every call): thresholds None rolls out at stride 1, M+1 thresholds with entropy guidance. An MJX
    task rolls out in ``evaluator`` (default ``make_evaluator``) from ``calibration_key(seed)``; an external task
    through its bridge (``external.calibration_rollout``, ``envs`` episodes at a time, kept in the run dir).
    ``max_steps``: the episodes' step limit in control steps (None: the task's own), the evaluation's they calibrate
    for."""
    seed = run.seed if seed is None else seed
    if external.is_external(run.task):
        from hipolicy_jax.runs import external as bridge

        bridge.calibration_seeds(seed, episodes)  # checked before anything is served

        def evaluate_thresholds(thresholds):
            r = bridge.calibration_rollout(run, inference, thresholds, episodes=episodes, seed=seed, envs=envs,
                                           log=log, max_steps=max_steps)
            return ClosedLoop(r["success_rate"], r["mean_steps"], r["entropies"], r["strides"],
                              np.ones(r["strides"].shape, bool))
        return evaluate_thresholds
    ev = evaluator or make_evaluator(run, inference, max_steps=max_steps)
    p, key = run.policy, calibration_key(seed)

    def evaluate_thresholds(thresholds):
        res = ev.evaluate(p.params, p.normalizer, episodes, key, thresholds, entropy_guided=thresholds is not None)
        return ClosedLoop(float(res.success_rate), float(np.mean(np.asarray(res.steps))),
                          np.asarray(res.entropy).ravel(), np.asarray(res.stride).ravel(),
                          np.asarray(res.valid, bool).ravel())
    return evaluate_thresholds


def run_entropies(run: Run, inference: InferenceConfig, source: Literal["demos", "rollouts"] = "demos", *,
                  episodes: int = 20, seed: int | None = None, evaluator=None, envs: int = 8,
                  log=print, max_steps: int | None = None) -> np.ndarray:
    """Action entropies of the run's held-out demo windows (``inference.calib_windows`` of them) or of every replan
    of ``episodes`` closed-loop episodes at the highest frequency (``closed_loop``: MJX or external)."""
    seed = run.seed if seed is None else seed
    if source == "demos":
        p = run.policy
        if evaluator is None and external.is_external(run.task):  # no env to build: the demo half of an Evaluator
            from hipolicy_jax.runs.train import DemoCalibrator
            evaluator = DemoCalibrator(run.task, p.cfg, run.action_dim, inference)
        ev = evaluator or make_evaluator(run, inference)
        return ev.measure_entropies(p.params, p.normalizer, heldout_dataset(run), run_keys(seed)["eval"])
    if source != "rollouts":
        raise ValueError(f"source: must be 'demos' or 'rollouts', got {source!r}")
    base = closed_loop(run, inference, episodes=episodes, seed=seed, evaluator=evaluator, envs=envs, log=log,
                       max_steps=max_steps)(None)
    return base.entropy[base.valid]


def success_constrained(run: Run, inference: InferenceConfig, *, episodes: int = 20, seed: int | None = None,
                        margin: float = 0.05, ladder: Sequence[Sequence[float]] | None = None,
                        evaluator=None, envs: int = 8, log=print, max_steps: int | None = None) -> dict:
    """The success-constrained rule on ``episodes`` calibration episodes (``closed_loop``): stride-1 rollouts
    give the entropies and the baseline success; each ``ladder`` candidate (default ``percentile_ladder``) is rolled
    out with entropy guidance from the same initial states. → {entropies, baseline, candidates, chosen (index),
    percentiles, thresholds}."""
    cfg = run.policy.cfg
    m = cfg.chunk.num_freqs
    if m == 1:
        raise ValueError("rule: 'success' chooses among strides; a single-stride policy has none to choose")
    if not 0 <= margin <= 1:  # checked before any episode runs (choose_success_constrained checks it again)
        raise ValueError(f"margin: a success-rate difference in [0, 1], got {margin}")
    ladder = calibration.percentile_ladder(m) if ladder is None else tuple(tuple(map(float, q)) for q in ladder)
    for q in ladder:
        calibration.intended_mix(q, cfg.chunk.strides)  # ValueError naming the percentiles before any episode runs
    evaluate_thresholds = closed_loop(run, inference, episodes=episodes, seed=seed, evaluator=evaluator, envs=envs,
                                      log=log, max_steps=max_steps)
    base = evaluate_thresholds(None)
    entropies = base.entropy[base.valid]
    candidates = []
    for q in ladder:
        thresholds = calibration.calibrate_thresholds(entropies, m, q)
        res = evaluate_thresholds(thresholds)
        candidates.append({"percentiles": list(q), "thresholds": [float(t) for t in thresholds],
                           "success_rate": res.success_rate, "mean_steps": res.mean_steps,
                           "intended_mix": calibration.intended_mix(q, cfg.chunk.strides),
                           "achieved_mix": calibration.achieved_mix(res.stride, res.valid, cfg.chunk.strides)})
    chosen = calibration.choose_success_constrained(candidates, base.success_rate, margin)
    return {"entropies": entropies, "candidates": candidates, "chosen": chosen, "margin": margin,
            "baseline": {"success_rate": base.success_rate, "mean_steps": base.mean_steps},
            "percentiles": tuple(candidates[chosen]["percentiles"]),
            "thresholds": tuple(candidates[chosen]["thresholds"])}


def calibrate_run(run: Run, inference: InferenceConfig, source: Literal["demos", "rollouts"] = "demos", *,
                  episodes: int = 20, seed: int | None = None, out: str = "", bins: int = 24,
                  rule: Literal["percentiles", "success"] = "percentiles", margin: float = 0.05,
                  ladder: Sequence[Sequence[float]] | None = None, envs: int = 8, log=print,
                  max_steps: int | None = None) -> dict:
    """Thresholds by ``rule`` (the module docstring): at ``inference.percentiles`` of ``run_entropies``, or the
    success-constrained choice (``success_constrained``; closed-loop ``source='rollouts'`` only); writes the
    calibration record to ``out`` (default ``<run>/calibration.json``) and a histogram PNG next to it; → the record
    (+ ``entropies``). A closed-loop record also names its ``episodes`` and, for an external task, the first of
    their initial-state seeds (``first_seed``); ``envs``: an external task's episodes at a time; ``max_steps``: the
    closed-loop episodes' step limit (None: the task's own; a record names a given one)."""
    cfg = run.policy.cfg
    m = cfg.chunk.num_freqs
    seed = run.seed if seed is None else seed
    extra = {}
    if rule == "success":
        if source != "rollouts":
            raise ValueError(f"rule: 'success' rolls the candidates out in closed loop; it needs source "
                             f"'rollouts', got {source!r}")
        chosen = success_constrained(run, inference, episodes=episodes, seed=seed, margin=margin, ladder=ladder,
                                     envs=envs, log=log, max_steps=max_steps)
        entropies, thresholds, percentiles = chosen["entropies"], chosen["thresholds"], chosen["percentiles"]
        inference = dataclasses.replace(inference, percentiles=percentiles)
        extra = {k: chosen[k] for k in ("candidates", "chosen", "margin", "baseline")}
    elif rule == "percentiles":
        percentiles = calibration.effective_percentiles(m, inference.percentiles) if m > 1 else ()
        entropies = run_entropies(run, inference, source, episodes=episodes, seed=seed, envs=envs, log=log,
                                  max_steps=max_steps)
        thresholds = calibration.calibrate_thresholds(entropies, m, percentiles or None)
    else:
        raise ValueError(f"rule: must be 'percentiles' or 'success', got {rule!r}")
    if source == "rollouts":
        extra["episodes"] = episodes
        if max_steps is not None:
            extra["max_steps"] = int(max_steps)
        if external.is_external(run.task):
            from hipolicy_jax.runs.external import calibration_seeds
            extra["first_seed"] = calibration_seeds(seed, episodes)[0]
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
