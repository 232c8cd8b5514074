"""An experiment campaign: many (task, seed, column) evaluations of trained runs, each kept as a small JSON record.

A **column** is a trained variant (observation type + config changes on top of a budget) and how it is executed
(entropy guidance on / off, thresholds at other percentiles, an execution strategy). ``evaluate_column`` returns the
column's evaluation of one run: from the run's **record** when it holds it, else by training (or resuming) the run
and evaluating it, after which the record is written. Records live at ``<records>/<budget>/<task>/<obs>/<variant>/
seed<k>.json`` (the run dir's layout) and hold the run's configs, training summary and calibration and, per
evaluation, the per-episode success and steps: small enough for git, enough to rebuild every table (``from_records``
never trains nor evaluates) and to continue a campaign on a new machine.

``Campaign`` owns what evaluations share: one ``Evaluator`` per (task, policy config, inference settings), so all
seeds of a variant compile once, and the held-out entropies of each run.
"""

from __future__ import annotations

import dataclasses
import glob
import json
import os
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from hipolicy_jax import envs, jsonio
from hipolicy_jax.checkpoint import CheckpointDamaged, config_from_dict, config_to_dict
from hipolicy_jax.config import InferenceConfig, PolicyConfig
from hipolicy_jax.data.replay_buffer import collection_lock
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.evaluation.evaluator import Evaluator, result_record
from hipolicy_jax.campaigns.budgets import BUDGETS, SPEEDUP_SUFFIX, run_config
from hipolicy_jax.campaigns.report import changes_text, cpu_s
from hipolicy_jax.runs.calibrate import run_entropies
from hipolicy_jax.runs.external import external_summary
from hipolicy_jax.runs import records as rec_lib
from hipolicy_jax.runs.lock import CAMPAIGN_LOCK_FILE, RunLock, RunLockedError
from hipolicy_jax.runs.store import Run, eval_key, make_evaluator, read_json, write_json
from hipolicy_jax.runs.train import RunConfig, cpu_cores, cpu_seconds, ensure_trained, finished, prepare_out_dir

RECORD_VERSION = rec_lib.RECORD_VERSION
# External tasks' initial states (``envs.external``): seed k's main episodes from EXTERNAL_EVAL_SEED + 1000 k + i,
# its periodic (DP3-metric) episodes from EXTERNAL_PERIODIC_SEED + 1000 k + i.
EXTERNAL_EVAL_SEED = envs.external.EVAL_SEED
EXTERNAL_PERIODIC_SEED = envs.external.PERIODIC_SEED
DP3_METRIC_BEST = 5  # DP3's metric: the mean of the 5 best periodic evaluations


class Periodic(NamedTuple):
    """Evaluations of a run's kept checkpoints (an external task's): ``episodes`` each from initial-state seeds
    ``seed_base + 1000 k + i``; ``steps``: only these checkpoints (None: every kept one at the run's checkpoint
    interval)."""

    episodes: int
    seed_base: int
    steps: tuple[int, ...] | None = None


def dp3_metric(rates: list[float], best: int = DP3_METRIC_BEST) -> float | None:
    """DP3's per-seed number: the mean of the ``best`` highest periodic success rates (of all when fewer)."""
    return float(np.mean(sorted(rates, reverse=True)[:best])) if rates else None


class Column(NamedTuple):
    """One evaluated setting: a trained variant (obs type + config changes) and how it is executed.

    ``percentiles``: thresholds at these percentiles of the run's held-out demo entropies instead of its
    ``calibration.json``; ``guided=False``: always the highest frequency; ``execution``: the execution strategy
    (``InferenceConfig.execution``); ``semantics`` / ``controller_speed``: how each action executes and the MJX
    controller's speed limit (``InferenceConfig``; columns that differ only in these evaluate the same networks);
    ``calibration``: where a guided multi-stride policy's thresholds come from: ``demos`` (the run's
    ``calibration.json``, made by training from its held-out demo, or ``percentiles`` of those entropies),
    ``rollouts`` (the percentiles of the entropies of the network's own stride-1 decisions on
    ``CLOSED_LOOP_EPISODES`` closed-loop calibration episodes, disjoint from the evaluation's, rolled out with the
    column's execution) or ``success`` (the success-constrained rule on those episodes: the most aggressive
    candidate of ``calibration.percentile_ladder`` within ``SUCCESS_MARGIN`` of stride 1's success);
    ``max_steps``: the episodes' step limit (control steps; None: the task's own, ``envs.episode_limit``)."""

    label: str
    obs_type: str = "state"
    changes: tuple[tuple[str, Any], ...] = ()
    guided: bool = True
    percentiles: tuple[float, ...] | None = None
    execution: str = "chunk"
    semantics: str = "rate"
    controller_speed: float | None = None
    calibration: str = "demos"
    max_steps: int | None = None


CALIBRATIONS = ("demos", "rollouts", "success")  # Column.calibration's values
CLOSED_LOOP_EPISODES = 50  # calibration episodes of a closed-loop column (results/metaworld/PROTOCOL.md amendment 2)
SUCCESS_MARGIN = 0.05  # the success-constrained rule's margin (amendment 2)


def check_column(col: Column) -> None:
    """One-line ``ValueError`` naming the field of a column whose threshold source or step limit is not valid."""
    if col.calibration not in CALIBRATIONS:
        raise ValueError(f"column {col.label}: calibration must be one of {list(CALIBRATIONS)}, got "
                         f"{col.calibration!r}")
    if col.calibration == "success" and col.percentiles is not None:
        raise ValueError(f"column {col.label}: calibration 'success' chooses its own percentiles; leave percentiles "
                         f"None, got {list(col.percentiles)}")
    if col.max_steps is not None and int(col.max_steps) < 1:
        raise ValueError(f"column {col.label}: max_steps must be None (the task's limit) or >= 1, got "
                         f"{col.max_steps}")


def record_path(records: str, runs: str, cfg: RunConfig) -> str:
    """``<records>/<the run dir relative to runs>.json``."""
    return os.path.join(records, os.path.relpath(cfg.out_dir(), runs)) + ".json"


def evaluation_key(inference: InferenceConfig, col: Column, episodes: int, eval_seed: int,
                   calibration_episodes: int = CLOSED_LOOP_EPISODES) -> str:
    """The canonical id of one evaluation of a run (what its numbers depend on besides the run; a closed-loop
    column's thresholds also on its ``calibration_episodes``)."""
    settings = {"num_samples": inference.num_samples, "sampler": inference.sampler,
                "num_steps": inference.num_steps, "execution": col.execution,
                "te_decay": inference.te_decay if col.execution == "te" else None, "guided": col.guided,
                "percentiles": None if col.percentiles is None else [float(p) for p in col.percentiles],
                "episodes": episodes, "eval_seed": eval_seed}
    if inference.semantics != "rate" or inference.controller_speed is not None:  # rate keys stay as they were
        settings.update(semantics=inference.semantics, controller_speed=inference.controller_speed,
                        waypoint_tolerance=inference.waypoint_tolerance if inference.semantics == "waypoint" else None,
                        waypoint_steps=inference.waypoint_steps if inference.semantics == "waypoint" else None)
    if col.calibration != "demos":  # the demos' thresholds (every older column) keep their keys as they were
        settings["calibration"] = {"source": "rollouts", "rule": "success" if col.calibration == "success"
                                   else "percentiles", "episodes": int(calibration_episodes),
                                   **({"margin": SUCCESS_MARGIN} if col.calibration == "success" else {})}
    if col.max_steps is not None:  # the task's own limit (every older column) keeps its key as it was
        settings["max_steps"] = int(col.max_steps)
    return json.dumps(settings, sort_keys=True)


def run_summary(run: Run) -> dict:
    """What a record keeps of a trained run: configs, task, data (its path and its ``demos``: episodes and frames),
    training summary, calibration."""
    meta = run.policy.meta
    summary_path = os.path.join(run.run_dir, "summary.json")
    summary = read_json(summary_path) if os.path.exists(summary_path) else {}
    calib = calibration.read_calibration(run.run_dir) or {}
    return {"task": run.task, "seed": run.seed, "checkpoint_step": run.policy.step, "policy": meta["policy"],
            "train": meta["train"], "data": os.path.relpath(meta.get("data", "")), "val_ratio": meta.get("val_ratio"),
            "param_count": meta.get("param_count"), "demos": summary.get("demos"),
            "training": {k: summary.get(k) for k in ("steps", "final_loss", "wall_time_s", "cpu_time_s",
                                                     "cpu_cores")},
            "calibration": {k: calib.get(k) for k in ("thresholds", "percentiles", "num_windows", "inference")}}


class Campaign:
    """Evaluations of one budget's runs, cached in records; ``from_records`` only reads records."""

    def __init__(self, budget: str, *, runs: str = "runs/paper", data: str = "data", records: str = "results/runs",
                 episodes: int | None = None, from_records: bool = False, progress: bool = True):
        self.budget, self.runs, self.data, self.records = budget, runs, data, records
        self.inference = BUDGETS[budget].inference
        self.episodes = BUDGETS[budget].eval.episodes if episodes is None else episodes
        self.from_records, self.progress = from_records, progress
        # closed-loop calibration episodes (Column.calibration rollouts / success): the protocol's 50; a smoke run's 2
        self.calibration_episodes = 2 if budget == "smoke" else CLOSED_LOOP_EPISODES
        self._evaluators: dict = {}
        self._entropies: dict = {}

    def run_config(self, task: str, col: Column, seed: int, run_changes: dict | None = None) -> RunConfig:
        return run_config(self.budget, task, col.obs_type, col.changes, seed, runs=self.runs, data=self.data,
                          eval_episodes=self.episodes, progress=self.progress, run_changes=run_changes)

    def _evaluator(self, run: Run, inference: InferenceConfig) -> Evaluator:
        ident = (run.task, run.policy.cfg, run.action_dim, inference.rollout_settings())
        if ident not in self._evaluators:
            self._evaluators[ident] = make_evaluator(run, inference)
        return self._evaluators[ident]

    def _thresholds(self, run: Run, col: Column, ev: Evaluator, seed: int | None = None,
                    inference: InferenceConfig | None = None) -> tuple[float, ...] | None:
        m = run.policy.cfg.chunk.num_freqs
        if m == 1 or not col.guided:
            return None
        check_column(col)
        if col.calibration != "demos":  # closed loop, in the column's execution (MJX: one compiled rollout)
            from hipolicy_jax.runs.calibrate import success_constrained

            inference = inference or self._key(col, run.seed if seed is None else seed)[0]
            ident = (run.run_dir, col.calibration, col.percentiles, inference.rollout_settings())
            if ident not in self._entropies:
                if col.calibration == "success":
                    self._entropies[ident] = success_constrained(
                        run, inference, episodes=self.calibration_episodes, seed=seed, margin=SUCCESS_MARGIN,
                        evaluator=ev)["thresholds"]
                else:
                    entropies = run_entropies(run, inference, "rollouts", episodes=self.calibration_episodes,
                                              seed=seed, evaluator=ev)
                    self._entropies[ident] = calibration.calibrate_thresholds(
                        entropies, m, col.percentiles or inference.percentiles)
            return tuple(self._entropies[ident])
        calib = calibration.read_calibration(run.run_dir)
        if col.percentiles is None:
            return calibration.resolve_thresholds(self.inference, m, calib)[0]
        if (calib is not None and calib.get("source") == "demos" and calib.get("percentiles") == list(col.percentiles)
                and calib.get("inference") == dataclasses.asdict(self.inference.sampler_settings())):
            return calibration.resolve_thresholds(self.inference, m, calib)[0]  # the same entropies, percentiles
        if run.run_dir not in self._entropies:
            self._entropies[run.run_dir] = run_entropies(run, self.inference, "demos", evaluator=ev)
        return calibration.calibrate_thresholds(self._entropies[run.run_dir], m, col.percentiles)

    def record(self, task: str, col: Column, seed: int, run_changes: dict | None = None) -> dict:
        """The (task, seed) run's record of this column's variant ({} before one exists)."""
        return read_record(record_path(self.records, self.runs, self.run_config(task, col, seed, run_changes)))

    def recorded(self, task: str, col: Column, seed: int, run_changes: dict | None = None) -> bool:
        """Whether the (task, seed) run's record holds this column's evaluation."""
        return self._key(col, seed)[1] in self.record(task, col, seed, run_changes).get("evaluations", {})

    def _key(self, col: Column, seed: int) -> tuple[InferenceConfig, str]:
        inference = dataclasses.replace(self.inference, execution=col.execution, semantics=col.semantics,
                                        controller_speed=col.controller_speed)
        return inference, evaluation_key(inference, col, self.episodes, seed, self.calibration_episodes)

    def evaluate(self, task: str, col: Column, seed: int, run_changes: dict | None = None,
                 periodic: Periodic | None = None) -> dict | None:
        """The column's evaluation of the (task, seed) run: ``eval_summary`` plus per-episode ``success`` /
        ``steps`` / ``decisions`` and the ``thresholds``; from the record, else trained / evaluated and recorded.
        None when ``from_records`` and the record lacks it. An external task (``metaworld:<task>``) is evaluated
        through the policy server and its bridge, with ``periodic`` evaluations of the kept checkpoints (default:
        the budget's, ``periodic_episodes`` each) and DP3's metric over them."""
        cfg = self.run_config(task, col, seed, run_changes)
        path = record_path(self.records, self.runs, cfg)
        inference, key = self._key(col, seed)
        record = read_record(path)
        if key in record.get("evaluations", {}) or self.from_records:
            return record.get("evaluations", {}).get(key)
        # one campaign process works on a run at a time (another shard's: RunLockedError, the caller skips it)
        with RunLock(prepare_out_dir(cfg.out_dir()), CAMPAIGN_LOCK_FILE, "campaign process",
                     "another shard is training or evaluating it; this one leaves it to that one"):
            record = read_record(path)  # that shard may have just recorded it
            if key in record.get("evaluations", {}):
                return record["evaluations"][key]
            self.ensure_demos(cfg, seed)
            run = ensure_trained(cfg)
            summary = run_summary(run)
            net = rec_lib.network(run.policy.params, summary["training"].get("final_loss"))
            if record and not rec_lib.same_network(record.get("network"), net):
                print(f"[campaign] {path}: the run was retrained and its network differs from the record's; the "
                      f"record's {len(record.get('evaluations', {}))} evaluations move to 'superseded' and are "
                      f"made again on the new network", flush=True)
            record = rec_lib.supersede(record, net) if record else record
            if cfg.external:
                evaluation = self._external_evaluation(run, col, seed, inference, key, periodic)
            else:
                ev = self._evaluator(run, inference)
                thresholds = self._thresholds(run, col, ev, seed, inference)
                thresholds_json = (None if thresholds is None
                                   else jsonio.loads(jsonio.dumps([float(t) for t in thresholds])))
                same = _same_evaluation(record.get("evaluations", {}), json.loads(key), thresholds_json)
                if same is not None:  # the same inputs were evaluated under another column's settings (percentiles)
                    evaluation = {**record["evaluations"][same], "settings": json.loads(key),
                                  "same_as": json.loads(same), "eval_s": 0.0}
                else:
                    t0, c0 = time.perf_counter(), cpu_seconds()
                    result = ev.evaluate(run.policy.params, run.policy.normalizer, self.episodes, eval_key(seed),
                                         thresholds, entropy_guided=col.guided)
                    evaluation = {"settings": json.loads(key), **result_record(result), "thresholds": thresholds_json,
                                  "eval_s": time.perf_counter() - t0,
                                  "eval_cpu_s": cpu_seconds() - c0, "cpu_cores": cpu_cores(),
                                  "rollout": ev.rollout_kind}
            evaluation["network"] = net
            evaluation = jsonio.loads(jsonio.dumps(evaluation))  # as records hold it (NaN: None), fresh or reread
            record = {"version": RECORD_VERSION, "budget": self.budget, "run_dir": os.path.relpath(run.run_dir),
                      **summary, "network": record.get("network", net),
                      "evaluations": {**record.get("evaluations", {}), key: evaluation},
                      **({"superseded": record["superseded"]} if record.get("superseded") else {})}
            write_json(path, record)
            return evaluation

    def ensure_demos(self, cfg: RunConfig, seed: int) -> str:
        """``cfg.data_path()``; an external task's demo buffer is collected there when missing, with point clouds of
        the budget's point count (one buffer serves every column), episodes cut at the suite's campaign step limit
        (an MJX task's demos are collected by its training). Campaign processes that need the same missing buffer
        collect it once: the first holds ``<dir>/.<name>.lock`` and the others wait for it, then reuse its buffer
        (as ``envs.demos.load_or_collect`` does for MJX tasks)."""
        from hipolicy_jax.runs.external import collect_demos

        path = cfg.data_path()
        if path.endswith(SPEEDUP_SUFFIX) and not os.path.exists(path):  # training would collect plain demos there
            raise FileNotFoundError(f"{path}: no DemoSpeedup-accelerated buffer; it is made from its proxy run by "
                                    f"python -m experiments.paper speedup before any run trains on it")
        if not cfg.external or os.path.exists(path):
            return path
        points = self.run_config(cfg.task, Column("pc", "pointcloud"), seed).policy.encoder.num_points
        suite = envs.external.SUITES[cfg.task.partition(":")[0]]
        with collection_lock(path, "campaign"):
            if not os.path.exists(path):  # another process may have collected it while this one waited
                collect_demos(cfg.task, cfg.episodes, path, num_points=points, max_steps=suite.eval_max_steps)
        return path

    def _external_evaluation(self, run: Run, col: Column, seed: int, inference: InferenceConfig, key: str,
                             periodic: Periodic | None) -> dict:
        """An external task's evaluation: the final network on the budget's episodes (at the column's step limit,
        its thresholds from the column's ``calibration``: a closed-loop one made first, once per network, and kept
        in the run dir), then the periodic ones (none when ``periodic.episodes`` is 0)."""
        from hipolicy_jax.runs.external import evaluate_run

        check_column(col)
        if col.execution != "chunk" or (col.percentiles is not None and col.calibration == "demos"):
            raise ValueError(f"column {col.label}: external tasks are evaluated with whole-chunk execution at the "
                             f"run's calibrated thresholds only")
        m = run.policy.cfg.chunk.num_freqs
        max_steps = int(col.max_steps) if col.max_steps is not None else envs.episode_limit(run.task)
        calib_summary, calib_s, calib_cpu_s = None, 0.0, 0.0
        if m == 1:
            thresholds = None
        elif not col.guided:  # always stride 1: the thresholds are never read
            inference = dataclasses.replace(inference, entropy_guided=False)
            thresholds = None
            calib_summary = {"source": "none", "intended_mix": {str(s): float(s == min(run.policy.cfg.chunk.strides))
                                                                for s in run.policy.cfg.chunk.strides}}
        elif col.calibration == "demos":
            calib = calibration.read_calibration(run.run_dir)
            thresholds = calibration.resolve_thresholds(self.inference, m, calib)[0]
            percentiles = (calib or {}).get("percentiles") or calibration.effective_percentiles(m, None)
            calib_summary = {"source": "demos", "rule": "percentiles", "percentiles": list(percentiles),
                             "intended_mix": calibration.intended_mix(percentiles, run.policy.cfg.chunk.strides)}
        else:
            t0, c0 = time.perf_counter(), cpu_seconds()
            calib_summary = self._closed_loop_calibration(run, col, seed, inference, max_steps)
            if not calib_summary.pop("reused"):
                calib_s, calib_cpu_s = time.perf_counter() - t0, cpu_seconds() - c0
            thresholds = calibration.inner_to_full(calib_summary["thresholds"], m, "calibration")
            inference = dataclasses.replace(inference, thresholds=tuple(float(t) for t in thresholds[1:-1]))
        first = EXTERNAL_EVAL_SEED + 1000 * seed
        # kept in the run dir as they finish: an interrupted evaluation resumes at the next checkpoint's
        rec = evaluate_run(run.run_dir, episodes=self.episodes, first_seed=first, max_steps=max_steps,
                           inference=inference, keep=True)
        evaluation = {"settings": json.loads(key), **external_summary(rec),
                      "thresholds": None if thresholds is None else [float(t) for t in thresholds],
                      "success": [bool(e["success"]) for e in rec["per_episode"]],
                      "steps": [int(e["steps"]) for e in rec["per_episode"]],
                      "decisions": [int(e["decisions"]) for e in rec["per_episode"]],
                      "actions": [int(e.get("actions", e["steps"])) for e in rec["per_episode"]],
                      # actions the bridge's per-step bound cut (``rate``): where its record counts them
                      **({"clipped": [int(e["clipped"]) for e in rec["per_episode"]]}
                         if rec["per_episode"] and all("clipped" in e for e in rec["per_episode"]) else {}),
                      "first_seed": first, "max_steps": max_steps,
                      "eval_s": rec["wall_s"] + calib_s,
                      "eval_cpu_s": None if rec.get("cpu_s") is None else rec["cpu_s"] + calib_cpu_s,
                      "cpu_cores": cpu_cores(), "timing": rec["seconds"]}
        if calib_summary is not None:  # where the thresholds came from, and what the calibration cost here
            evaluation["calibration"] = {**calib_summary, "calibration_s": calib_s, "calibration_cpu_s": calib_cpu_s}
        b = BUDGETS[self.budget]
        periodic = periodic or (Periodic(b.periodic_episodes, EXTERNAL_PERIODIC_SEED) if b.periodic_episodes
                                else None)
        if periodic is not None and periodic.episodes > 0:
            rows = []
            every = int(run.policy.meta["train"]["ckpt_every"])
            for step in checkpoint_steps(run.run_dir):  # the periodic ones (not step 1's nor an interrupt's)
                if step % every or (periodic.steps is not None and step not in periodic.steps):
                    continue
                first = periodic.seed_base + 1000 * seed
                r = evaluate_run(run.run_dir, episodes=periodic.episodes, first_seed=first, max_steps=max_steps,
                                 inference=inference, step=step, keep=True)
                rows.append({"step": step, "params_sha256": r["params_sha256"], "first_seed": first,
                             "success_rate": r["success_rate"],
                             "success": [bool(e["success"]) for e in r["per_episode"]],
                             "steps": [int(e["steps"]) for e in r["per_episode"]],
                             "eval_s": r["wall_s"], "eval_cpu_s": r.get("cpu_s"), "cpu_cores": cpu_cores()})
            evaluation["periodic"] = {"episodes": periodic.episodes, "seed_base": periodic.seed_base,
                                      "note": "other networks of this run (its kept checkpoints, at the final "
                                              "network's thresholds): DP3's metric only", "checkpoints": rows}
            evaluation["dp3_metric"] = dp3_metric([r["success_rate"] for r in rows])
        # eval_s: everything this evaluation cost (what the cost model plans with); main_eval_s: the final network's;
        # the same for the process CPU time (None when a part predates its measurement)
        checkpoints = evaluation.get("periodic", {}).get("checkpoints", [])
        evaluation["main_eval_s"] = evaluation["eval_s"]
        evaluation["eval_s"] += sum(r["eval_s"] for r in checkpoints)
        evaluation["main_eval_cpu_s"] = evaluation["eval_cpu_s"]
        parts = [evaluation["eval_cpu_s"], *(r["eval_cpu_s"] for r in checkpoints)]
        evaluation["eval_cpu_s"] = None if None in parts else sum(parts)
        return evaluation

    def _closed_loop_calibration(self, run: Run, col: Column, seed: int, inference: InferenceConfig,
                                 max_steps: int) -> dict:
        """The column's closed-loop thresholds for this network (``runs.calibrate.calibrate_run``, source
        ``rollouts``: ``calibration_episodes`` episodes from the bridge's calibration seeds, in the column's
        semantics): made once per network and kept in the run dir as ``calibration_<rule>_<semantics>.json`` (the
        training's ``calibration.json`` stays as it is), with the network's fingerprint; a later evaluation of the
        same network reuses it (``reused`` True). → the summary a record keeps: source, rule, percentiles,
        thresholds, episodes, first seed, intended mix (and the success rule's candidates, choice, baseline)."""
        from hipolicy_jax.runs import calibrate as calibrate_lib
        from hipolicy_jax.runs.records import params_fingerprint

        rule = "success" if col.calibration == "success" else "percentiles"
        path = os.path.join(run.run_dir, f"calibration_{rule}_{inference.semantics}.json")
        fingerprint = params_fingerprint(run.policy.params)
        wanted = {"params_sha256": fingerprint, "semantics": inference.semantics,
                  "episodes": self.calibration_episodes, "max_steps": max_steps, "seed": seed,
                  "margin": SUCCESS_MARGIN if rule == "success" else None,
                  "percentiles_asked": None if col.percentiles is None else [float(p) for p in col.percentiles]}
        kept = read_json(path) if os.path.exists(path) else {}
        reused = bool(kept) and all(kept.get(k) == v for k, v in wanted.items())
        if not reused:
            calib_inference = dataclasses.replace(inference, thresholds=None, entropy_guided=True,
                                                  percentiles=col.percentiles or inference.percentiles)
            # the evaluation's step limit reaches the calibration episodes too
            record = calibrate_lib.calibrate_run(run, calib_inference, source="rollouts", rule=rule,
                                                 episodes=self.calibration_episodes, seed=seed, margin=SUCCESS_MARGIN,
                                                 out=path, max_steps=max_steps)
            kept = {k: v for k, v in record.items() if k not in ("entropies", "path")}
            kept = jsonio.loads(jsonio.dumps({**kept, **wanted}))
            write_json(path, kept)
        keys = ("source", "rule", "percentiles", "thresholds", "episodes", "first_seed", "intended_mix",
                "candidates", "chosen", "margin", "baseline", "num_windows", "max_steps")
        return {"file": os.path.basename(path), **{k: kept[k] for k in keys if k in kept}, "reused": reused}


def checkpoint_steps(run_dir: str) -> list[int]:
    """The steps of a run dir's kept checkpoints, ascending."""
    ckpt = os.path.join(run_dir, "checkpoints")
    return sorted(int(d) for d in os.listdir(ckpt) if d.isdigit()) if os.path.isdir(ckpt) else []


RECORD_HINT = "delete it to redo that run's evaluations"


def load_record_file(path: str) -> dict:
    """The JSON object in the record file at ``path``, any version; one that does not parse, or holds no JSON
    object, raises ``jsonio.DamagedFileError`` (one line: the path, what is wrong, restore it from git or delete
    it)."""
    hint = jsonio.restore_hint(path, RECORD_HINT)
    record = jsonio.load(path, hint)
    if not isinstance(record, dict):
        kind = {list: "array", str: "string", bool: "boolean", type(None): "null"}.get(type(record), "number")
        raise jsonio.DamagedFileError(path, f"holds a JSON {kind}, expected a record (a JSON object)", hint)
    return record


def read_record(path: str) -> dict:
    """The record at ``path`` ({} when there is none); a version-1 record is refused (it may mix networks:
    ``python -m experiments.records upgrade`` stamps its evaluations' networks from git). A record that does not
    parse, or holds no JSON object, raises ``jsonio.DamagedFileError`` (one line: the path, what is wrong, restore
    it from git or delete it)."""
    if not os.path.exists(path):
        return {}
    record = load_record_file(path)
    if record.get("version", 1) < RECORD_VERSION:
        raise ValueError(f"{path}: record version {record.get('version', 1)}, expected {RECORD_VERSION}; upgrade the "
                         f"records first (python -m experiments.records upgrade)")
    return record


def evaluation_rollout(evaluation: dict) -> str:
    """Which rollout made an MJX evaluation of a record: its ``"rollout"`` (``Evaluator.rollout_kind``), else
    ``"vmapped"`` (the records made before the compacted rollout became the Evaluator's default)."""
    return evaluation.get("rollout", "vmapped")


def _same_evaluation(evaluations: dict[str, dict], settings: dict, thresholds: list | None) -> str | None:
    """The key of a recorded evaluation with the same inputs: settings equal but for the percentiles (which only
    choose the thresholds) and the same thresholds; evaluations are deterministic, so its numbers are this one's."""
    def rest(s: dict) -> dict:
        return {k: v for k, v in s.items() if k != "percentiles"}

    for key, ev in evaluations.items():
        if "same_as" not in ev and rest(json.loads(key)) == rest(settings) and ev.get("thresholds") == thresholds:
            return key
    return None


class Job(NamedTuple):
    """One evaluation of a campaign: the (task, seed) run of a column, trained under ``changes`` (the regime's)."""

    task: str
    col: Column
    seed: int
    changes: tuple[tuple[str, Any], ...] = ()


def schedule(jobs: list[Job], main_seeds: tuple[int, ...]) -> list[Job]:
    """The campaign's order, so that every session's work completes paired comparisons soonest: the jobs without
    duplicates, then (stable, else in table order) the protocol's seeds before the baselines' extra seeds (every
    cell reaches the protocol's seed count before any cell goes beyond it), state before point clouds (DP3 runs
    cost 5-10x more), and the task with the longest episodes (the costliest evaluations and training) last."""
    jobs = list(dict.fromkeys(jobs))
    limits = {task: envs.episode_limit(task) for task in {j.task for j in jobs}}
    longest = max(limits.values(), default=0)
    costly = {task for task, n in limits.items() if n == longest and len(set(limits.values())) > 1}
    return sorted(jobs, key=lambda j: (j.seed not in main_seeds, j.col.obs_type != "state", j.task in costly))


def shard(jobs: list[Job], k: int, n: int, run_of: Callable[[Job], str]) -> list[Job]:
    """The jobs of shard ``k`` of ``n``: runs (``run_of(job)``, its run dir) go to shards in turn in the order they
    first appear, so each shard gets a like share of every stage of ``schedule`` and a run is trained and evaluated
    by one shard only (no two processes on one run dir)."""
    runs: dict[str, int] = {}
    for job in jobs:
        runs.setdefault(run_of(job), len(runs) % n)
    return [job for job in jobs if runs[run_of(job)] == k]


def training_key(policy: dict, batch_size: int) -> str:
    """What a training step's cost depends on: the policy config (network, encoder, objective) and the batch size;
    not the task, the number of demos nor the number of steps (a regime's ``_d25`` / ``_t8000`` runs share it).
    The policy dict is read back through ``PolicyConfig`` first, so a record written before a config field existed
    keys as that field's default (the network it trained). ``chunk.action_kinds`` is left out: what the actions
    mean does not change a step's cost, and keys stay as they were before the field existed."""
    try:
        policy = config_to_dict(config_from_dict(PolicyConfig, policy))
        policy["chunk"].pop("action_kinds", None)
    except (TypeError, ValueError, AttributeError):
        pass  # not a policy config this version reads: keyed as written
    return json.dumps({"policy": policy, "batch_size": batch_size}, sort_keys=True)


NOTHING_SPENT = {"train_s": 0.0, "runs": 0, "eval_s": 0.0, "evaluations": 0, "measured_runs": 0,
                 "measured_evaluations": 0, "wall_core_s": 0.0}


class CostModel:
    """CPU-seconds a campaign's pending evaluation will take, from the measured times the records hold (``cpu_s``:
    the process CPU time where a record measured it, else wall time × the cores its process ran on, 2 where it
    does not say): the run's training when it has none yet
    (seconds per step of the same network and batch on the same task, else on any task, else of any run of the
    observation type, × the run's steps after its latest checkpoint), plus the evaluation (the same task, execution strategy and stride count,
    else the strategy and stride count on any task, else the task, else any: ``eval_seconds``); 0 for an
    evaluation another table's column already makes. Medians, each over the first non-empty
    selection narrowed by preferences in turn (each keeps only the rows that have it, when any do): for
    evaluations, those made at today's rate — by the compacted rollout (``"rollout"``; an MJX evaluation without it
    was made by the older, slower vmapped one) or externally (a Meta-World evaluation, no MJX rollout) — then those
    that say their cores (a record without them comes from a process that shared its cores with others, so a run
    slowed by other jobs does not skew them), then those that measured their CPU time; for training, those that
    say their cores, then those that measured their CPU time. None when no record of the observation type exists
    yet. A record that does not read (``jsonio.DamagedFileError``) is left out and kept in ``damaged``."""

    def __init__(self, records: str, runs: str):
        self.records, self.runs = records, runs
        # ((task, obs, training key), seconds per step, (cores stated,))
        self._train: list[tuple[tuple[str, str, str], float, tuple[bool, ...]]] = []
        # ((task, execution, strides), seconds, (at today's rollout rate, cores stated)); strides: how many the
        # policy has (one draws a single sample a decision, several draw N: a several-fold cost), None unknown
        self._eval: list[tuple[tuple[str, str, int | None], float, tuple[bool, ...]]] = []
        # budget → CPU-seconds and counts of what the records hold (``measured_*``: with their CPU time measured)
        self._spent: dict[str, dict[str, float]] = {}
        # path → the one-line reason of a record that does not read (left out of the estimates, listed by work_off)
        self.damaged: dict[str, str] = {}
        for path in sorted(glob.glob(os.path.join(records, "**", "*.json"), recursive=True)):
            try:
                rec = load_record_file(path)
            except jsonio.DamagedFileError as e:
                self.damaged[path] = str(e)
                continue
            parts = os.path.relpath(path, records).split(os.sep)
            if len(parts) < 5 or "training" not in rec:
                continue
            task, obs = parts[-4], parts[-3]
            spent = self._spent.setdefault(parts[0], dict(NOTHING_SPENT))
            key = training_key(rec.get("policy"), (rec.get("train") or {}).get("batch_size"))
            steps, wall = rec["training"].get("steps"), rec["training"].get("wall_time_s")
            cores, cpu = rec["training"].get("cpu_cores"), rec["training"].get("cpu_time_s")
            if wall:
                spent["train_s"] += cpu_s(wall, cores, cpu)
                spent["wall_core_s"] += cpu_s(wall, cores, None)
                spent["runs"] += 1
                spent["measured_runs"] += cpu is not None
            if steps and wall:
                self._train.append(((task, obs, key), cpu_s(wall, cores, cpu) / steps,
                                    (cores is not None, cpu is not None)))
            external = envs.external.is_external(rec.get("task") or "")
            strides = ((rec.get("policy") or {}).get("chunk") or {}).get("strides")
            kind = len(strides) if strides else None
            evaluations = [*rec.get("evaluations", {}).values(),
                           *(ev for old in rec.get("superseded", []) for ev in old["evaluations"].values())]
            for ev in evaluations:
                if ev.get("eval_s"):
                    seconds = cpu_s(ev["eval_s"], ev.get("cpu_cores"), ev.get("eval_cpu_s"))
                    spent["eval_s"] += seconds
                    spent["wall_core_s"] += cpu_s(ev["eval_s"], ev.get("cpu_cores"), None)
                    spent["evaluations"] += 1
                    spent["measured_evaluations"] += ev.get("eval_cpu_s") is not None
                    current = external or evaluation_rollout(ev) == "compacted"
                    self._eval.append(((task, ev["settings"]["execution"], kind), seconds,
                                       (current, ev.get("cpu_cores") is not None, ev.get("eval_cpu_s") is not None)))

    def spent(self, budget: str) -> dict[str, float]:
        """What the records of ``budget`` cost, each run and each evaluation counted once (however many tables use
        it; the pilot's runs included): CPU-seconds of training (``train_s``) over ``runs`` runs and of evaluation
        (``eval_s``) over ``evaluations`` evaluations — an evaluation another column reuses took no time and is
        not counted; ``measured_runs`` / ``measured_evaluations`` of them measured their process CPU time (the
        others count wall time × cores); ``wall_core_s``: all of it as wall time × cores (the upper bound)."""
        return dict(self._spent.get(budget, NOTHING_SPENT))

    @staticmethod
    def _median(rows, *matches) -> float | None:
        """The median of the first non-empty selection: rows ``(key, value, preferences)`` whose key matches ``m``
        where ``m`` is not None; narrowed by each preference in turn to its rows that have it, when there are any."""
        for match in matches:
            chosen = [(v, prefs) for key, v, prefs in rows if all(m is None or k == m for k, m in zip(key, match))]
            if chosen:
                for i in range(len(chosen[0][1])):
                    chosen = [row for row in chosen if row[1][i]] or chosen
                return float(np.median([v for v, _ in chosen]))
        return None

    def _task_dir(self, cfg: RunConfig) -> tuple[str, str]:
        """(task, observation type) as the run's folders name them (``metaworld_basketball`` for the task
        ``metaworld:basketball``): the keys the records are read under."""
        parts = os.path.relpath(cfg.out_dir(), self.runs).split(os.sep)
        return parts[-4], parts[-3]

    def train_seconds(self, cfg: RunConfig) -> float | None:
        """The run's training still to do: the per-step time × the steps after its latest checkpoint (a run
        interrupted and resumed — a preempted job, a restarted campaign — continues from there)."""
        task, obs = self._task_dir(cfg)
        key = training_key(config_to_dict(cfg.policy), cfg.train.batch_size)
        per_step = self._median(self._train, (task, obs, key), (None, obs, key), (None, obs, None))
        done = max([s for s in checkpoint_steps(cfg.out_dir()) if s <= cfg.train.num_steps], default=0)
        return None if per_step is None else per_step * (cfg.train.num_steps - done)

    def eval_seconds(self, task: str, execution: str, strides: int | None = None) -> float | None:
        """``task``: its folder name (``_task_dir``); ``strides``: how many the policy has (None: any). The same
        task, strategy and stride count first, then another task's with the same strategy and stride count (a
        HiPolicy evaluation draws N samples a decision where DP draws one: the stride count sets the cost more
        than the task does), then the task's of any stride count, of any strategy, then any."""
        return self._median(self._eval, (task, execution, strides), (None, execution, strides),
                            (task, execution, None), (task, None, None), (None, None, None))

    def estimate(self, camp: Campaign, jobs: list[Job]) -> list[dict]:
        """Per job: whether it is done (recorded), whether it trains a run, its estimated seconds (0 when done or
        made by an earlier job; None when unmeasured); a job whose record does not read also has ``damaged``, the
        one-line reason (``work_off`` skips it)."""
        rows, trained, evaluated = [], set(), set()
        for job in jobs:
            cfg = camp.run_config(job.task, job.col, job.seed, dict(job.changes))
            try:
                done = camp.recorded(job.task, job.col, job.seed, dict(job.changes))
                needs_train = not done and cfg.out_dir() not in trained and not finished(cfg)
            except jsonio.DamagedFileError as e:  # its record (or run summary) does not read: work_off skips it
                rows.append({"job": job, "done": False, "trains": False, "seconds": 0.0, "damaged": str(e)})
                continue
            trained.add(cfg.out_dir())
            evaluation = (cfg.out_dir(), camp._key(job.col, job.seed)[1])  # another table's column may share it
            seconds = 0.0
            if not done and evaluation not in evaluated:
                strides = len(cfg.policy.chunk.strides)
                parts = [self.eval_seconds(self._task_dir(cfg)[0], job.col.execution, strides)]
                parts += [self.train_seconds(cfg)] if needs_train else []
                seconds = None if None in parts else sum(parts)
            evaluated.add(evaluation)
            rows.append({"job": job, "done": done, "trains": needs_train, "seconds": seconds})
        return rows

    def refresh(self, camp: Campaign, row: dict) -> dict:
        """``row`` (an ``estimate`` row, made when the campaign started) as this model's records estimate it: each
        run a campaign finishes measures the ones after it (the first run of an observation type its kind; the
        first run that measured its process CPU time the wall-time upper bounds of older records)."""
        return row if row["done"] else self.estimate(camp, [row["job"]])[0]


def parse_until(text: str, now: float | None = None) -> float | None:
    """``--until`` as a Unix time: '' → None (no limit); 'HH:MM' → its next occurrence (local time) after ``now``;
    'YYYY-MM-DD HH:MM' (or any ISO date and time) → that time; else a one-line ``ValueError``."""
    import datetime

    if not text:
        return None
    now = time.time() if now is None else now
    start = datetime.datetime.fromtimestamp(now)
    try:
        if len(text) <= 5 and ":" in text:
            hour, minute = (int(v) for v in text.split(":"))
            at = start.replace(hour=hour, minute=minute, second=0, microsecond=0)
            return (at + datetime.timedelta(days=1) if at.timestamp() <= now else at).timestamp()
        return datetime.datetime.fromisoformat(text).timestamp()
    except ValueError:
        raise ValueError(f"until: expected HH:MM or YYYY-MM-DD HH:MM (local time), got {text!r}") from None


class Deadline:
    """A wall-clock limit on a campaign process (a scheduler's time limit, a session's end): a pending job starts
    only when its estimated CPU-seconds (``CostModel``; ``guess`` when unmeasured), spread over the process's
    ``cores``, end before ``until``; otherwise it is skipped and the next one that fits runs. A run whose training
    was skipped stays skipped (its later evaluations would need that training too). ``until=None``: no limit."""

    def __init__(self, until: float | None, cores: int, guess: float, clock: Callable[[], float] = time.time):
        self.until, self.cores, self.guess, self.clock = until, max(int(cores), 1), guess, clock
        self.skipped: set[str] = set()  # run dirs whose training was skipped

    def seconds_left(self) -> float:
        return float("inf") if self.until is None else self.until - self.clock()

    def admits(self, cost: dict, run_dir: str) -> bool:
        """Whether the job of ``cost`` (a ``CostModel.estimate`` row) on the run at ``run_dir`` may start now."""
        if self.until is None or cost["done"]:
            return True
        if run_dir in self.skipped:
            return False
        seconds = self.guess if cost["seconds"] is None else cost["seconds"]
        if seconds / self.cores <= self.seconds_left():
            return True
        if cost["trains"]:
            self.skipped.add(run_dir)
        return False


def work_off(camp: Campaign, costs: list[dict], run_of: Callable[[Job], str], *, until: str = "",
             progress: bool = True, periodic: Periodic | None = None) -> list[tuple[str, str]]:
    """Make every pending evaluation of ``costs`` (``CostModel.estimate`` rows, in order) under ONE progress bar
    with its ETA, each kept in its run's record as it finishes; a job whose estimated time would end after
    ``until`` (``parse_until``) is skipped, as is a run another campaign process holds. Without a progress bar
    (a background run's log) one line per finished job. A job whose record, run files, demo buffer or checkpoint
    is damaged (``jsonio.DamagedFileError``, ``CheckpointDamaged``: one line naming the file and what to do) is
    skipped with that line and the others go on; at the end the skipped ones are listed again (``report_damaged``)
    and returned as (job, reason)."""
    from tqdm.auto import tqdm

    known = [c["seconds"] for c in costs if c["seconds"]]
    guess = float(np.median(known)) if known else 1.0  # a job nothing measured yet
    deadline = Deadline(parse_until(until), cpu_cores(), guess)
    # the bar counts estimated seconds of work (recorded jobs cost 0), so its ETA is the measured rate at which
    # the estimate is worked off: it corrects itself as runs finish faster or slower than their records said
    bar = tqdm(total=round(sum(guess if c["seconds"] is None else c["seconds"] for c in costs)), desc="campaign",
               unit="s", disable=not progress, dynamic_ncols=True,
               bar_format="{l_bar}{bar}| {percentage:.0f}% of the estimated work [{elapsed}<{remaining}] {postfix}")
    model = None  # the records as they are now: made again after each job that ran (it measured the next ones)
    damaged: list[tuple[str, str]] = []  # (job, one-line reason) of the jobs skipped for a damaged stored file
    unread: dict[str, str] = {}  # records the cost models could not read

    def skip(label: str, c: dict, reason: str) -> None:
        bar.update(round(guess if c["seconds"] is None else c["seconds"]))
        tqdm.write(f"[campaign] {time.strftime('%Y-%m-%d %H:%M:%S')} {label}: skipped, {reason}")

    for i, c in enumerate(costs):
        task, col, seed, changes = c["job"]
        label = f"{i + 1}/{len(costs)}: {task} seed {seed} {col.label} {changes_text(dict(changes))}"
        bar.set_postfix_str(label)
        if model is None:
            model = CostModel(camp.records, camp.runs)
            unread.update(model.damaged)
        now = model.refresh(camp, c)
        if now.get("damaged"):  # its record does not read: the other jobs go on, this one is listed at the end
            skip(label, c, now["damaged"])
            damaged.append((label, now["damaged"]))
            continue
        if not deadline.admits(now, run_of(c["job"])):
            bar.update(round(guess if c["seconds"] is None else c["seconds"]))
            estimate = "unmeasured" if now["seconds"] is None else f"{now['seconds'] / deadline.cores:.0f} s"
            tqdm.write(f"[campaign] {time.strftime('%Y-%m-%d %H:%M:%S')} {label}: skipped, estimated {estimate}, "
                       f"{max(deadline.seconds_left(), 0):.0f} s left before --until {until}")
            continue
        t0 = time.perf_counter()
        try:
            evaluation = camp.evaluate(task, col, seed, dict(changes), periodic=periodic)
        except RunLockedError as e:  # another campaign process (a shard started over it) works on this run
            skip(label, c, str(e))
            continue
        except (jsonio.DamagedFileError, CheckpointDamaged) as e:  # a record, demo buffer or checkpoint damaged
            skip(label, c, str(e))
            damaged.append((label, str(e)))
            model = None
            continue
        bar.update(round(guess if c["seconds"] is None else c["seconds"]))
        if not now["done"]:
            model = None
        if not progress and not c["done"] and evaluation is not None:  # a background run's log: a line a job
            print(f"[campaign] {time.strftime('%Y-%m-%d %H:%M:%S')} {label}: "
                  f"{100 * evaluation['success_rate']:.0f} % in {time.perf_counter() - t0:.0f} s", flush=True)
    bar.close()
    report_damaged(damaged, unread)
    return damaged


def damaged_lines(costs: list[dict]) -> list[str]:
    """A plan's lines on the jobs skipped because their record does not read (``CostModel.estimate`` rows with
    ``damaged``): a heading and one line per file, with what to do; [] when there are none."""
    reasons = list(dict.fromkeys(c["damaged"] for c in costs if c.get("damaged")))
    if not reasons:
        return []
    n = sum(bool(c.get("damaged")) for c in costs)
    return ["", f"Skipped, their record does not read ({n} evaluations; each waits until its file is restored or "
                f"deleted):", "", *(f"- {r}" for r in reasons)]


def report_damaged(damaged: list[tuple[str, str]], unread: dict[str, str]) -> None:
    """The end of ``work_off``: one line per job skipped for a damaged stored file (its reason names the file and
    what to do), then the records the cost estimates left out that no skipped job named."""
    if damaged:
        print(f"[campaign] {len(damaged)} job(s) skipped for a damaged stored file; the others went on:", flush=True)
        for label, reason in damaged:
            print(f"[campaign]   {label}: {reason}", flush=True)
    others = {path: reason for path, reason in unread.items() if not any(path in r for _, r in damaged)}
    if others:
        print(f"[campaign] {len(others)} record(s) do not read and were left out of the cost estimates:", flush=True)
        for reason in others.values():
            print(f"[campaign]   {reason}", flush=True)


README_BEGIN = "<!-- campaign tables: written by `python -m experiments.paper campaign` from results/*.md -->"
README_END = "<!-- end of campaign tables -->"


def readme_section(table_paths: list[str], readme_dir: str, level: int = 3) -> str:
    """The results page's section (``--readme``, docs/results.md; the README before issue #61) from the tables'
    markdown files: each table's title at heading ``level`` (one below the page's heading) named by its file
    relative to the page, its other headings moved down as far, its notes (with the cost line), tables and plot;
    links relative to the page (``readme_dir``)."""
    parts = []
    for md in table_paths:
        with open(md) as f:
            text = f.read().strip()
        lines = text.splitlines()
        rel = os.path.relpath(md, readme_dir)
        lines = ["#" * (level - 1) + line if line.startswith("#") else line for line in lines]
        if lines and lines[0].startswith("#" * level + " "):
            lines[0] = f"{lines[0]} — `{rel}`"
        png = md[:-3] + ".png"
        if os.path.exists(png):
            lines += ["", f"![{os.path.basename(png)}]({os.path.relpath(png, readme_dir)})"]
        parts.append("\n".join(lines))
    return "\n\n".join(parts)


def update_readme(readme: str, section: str, begin: str = README_BEGIN, end: str = README_END) -> bool:
    """Replace what stands between the markers ``begin`` and ``end`` in ``readme`` (the results page) with
    ``section``; False (and nothing written) when the markers are missing."""
    with open(readme) as f:
        text = f.read()
    start, stop = text.find(begin), text.find(end)
    if start < 0 or stop < start:
        return False
    new = text[:start + len(begin)] + "\n\n" + section.strip() + "\n\n" + text[stop:]
    with open(readme, "w") as f:
        f.write(new)
    return True


def pilot_candidates(dp_at_100: float) -> list[dict]:
    """The protocol's Rlow candidates after DP's success at 100 demos: fewer demos (50, 25, 12) unless DP is at the
    floor (< 15 %), then more training steps (4000, 8000) at 100 demos."""
    if dp_at_100 >= 0.15:
        return [{"episodes": n} for n in (50, 25, 12)]
    return [{"train.num_steps": k} for k in (4000, 8000)]


def choose_low_regime(tried: list[tuple[dict, float]], low: float = 0.15, high: float = 0.85) -> tuple[dict, bool]:
    """(Rlow's run changes, whether DP lands in [low, high]): the first candidate in range, else the one closest to
    the middle of the range."""
    for changes, success in tried:
        if low <= success <= high:
            return changes, True
    return min(tried, key=lambda cs: abs(cs[1] - (low + high) / 2))[0], False


__all__ = ["CALIBRATIONS", "CLOSED_LOOP_EPISODES", "SUCCESS_MARGIN", "check_column",
           "EXTERNAL_EVAL_SEED",
           "EXTERNAL_PERIODIC_SEED", "NOTHING_SPENT", "Periodic", "checkpoint_steps", "dp3_metric",
           "external_summary", "README_BEGIN", "README_END", "Campaign", "Column", "choose_low_regime", "evaluation_key",
           "damaged_lines", "load_record_file", "pilot_candidates", "readme_section", "record_path", "report_damaged",
           "run_summary", "update_readme", "work_off"]
