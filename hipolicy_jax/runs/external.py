"""A run of an external task (``metaworld:<task>``, ``envs.external``) through its bridge, which lives in its own venv:
collecting its demos and evaluating a trained run closed-loop.

Both run the suite's bridge as a subprocess (``ExternalSuite.collect`` / ``.evaluate``); evaluation serves the run's
policy here with the project's server (``deploy``, on a free localhost port, batches of up to ``envs``) while the
bridge runs the episodes against it. Nothing here imports the simulator.

``calibration_rollout`` runs a run's closed-loop calibration episodes (``hipolicy_jax.runs.calibrate``, source
``rollouts``): from initial states ``CALIBRATION_SEED + 1000 seed + i``, disjoint from every evaluation's, at stride 1
(their entropies and the baseline success) or guided by given thresholds (a candidate of the success rule).

``evaluate_report`` is ``experiments.evaluate`` for such a run: the run's own execution and the same episodes
without entropy guidance, summarised like an MJX evaluation and written to ``eval.json``.

``evaluate_run`` returns the bridge's record (``metaworld_bridge.evaluate``): per episode ``seed``, ``success``,
``steps``, ``decisions``, ``strides`` (counts), ``mean_entropy``, per decision ``decision_strides`` and
``entropies``, plus the policy's manifest entries and timings.
With ``keep`` it also keeps the record in the run dir (``external_eval/``), keyed by checkpoint and settings, and a
later call with the same network (its parameters' fingerprint) and settings returns it without running a single
episode: a campaign that stops halfway through a run's evaluations resumes where it stopped.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shlex
import subprocess
import tempfile
import time
from typing import Sequence

import numpy as np

from hipolicy_jax import jsonio
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.envs import external
from hipolicy_jax.runs.records import params_fingerprint
from hipolicy_jax.runs.train import cpu_seconds


def _run(command: str, what: str, timeout: float | None = None) -> subprocess.CompletedProcess:
    """Run a bridge ``command`` (a shell-free argument string) from the repository root; ``RuntimeError`` with its
    last lines when it fails."""
    r = subprocess.run(shlex.split(command), capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        tail = "\n".join((r.stderr or r.stdout).strip().splitlines()[-5:])
        raise RuntimeError(f"{what} failed ({command}):\n{tail}")
    return r


def check_bridge(name: str) -> None:
    """``FileNotFoundError`` naming the set-up command unless the suite's bridge venv exists."""
    suite = external.SUITES[name.partition(":")[0]]
    python = shlex.split(suite.collect)[0]
    if not os.path.exists(python):
        raise FileNotFoundError(f"task {name}: its bridge's venv ({python}) is missing; make it with `{suite.setup}`")


def collect_demos(name: str, episodes: int, path: str, *, num_points: int | None, max_steps: int,
                  log=print) -> str:
    """Collect ``episodes`` expert demos of the external task ``name`` into ``path`` (the bridge's zarr); → its
    summary line."""
    external.check_name(name)
    check_bridge(name)
    suite = external.SUITES[name.partition(":")[0]]
    task = name.partition(":")[2]
    cmd = suite.collect.format(task=task, episodes=episodes, path=path)
    cmd += " --no-progress" + f" --max-steps {max_steps}"
    cmd += " --no-point-cloud" if num_points is None else f" --num-points {num_points}"
    t0 = time.perf_counter()
    line = _run(cmd, f"collecting {name} demos").stdout.strip().splitlines()[-1]
    log(f"[external] {line} ({time.perf_counter() - t0:.0f} s)")
    return line


def kept_path(run_dir: str, step: int, settings: dict) -> str:
    """Where ``evaluate_run(keep=True)`` keeps the record of checkpoint ``step`` under ``settings``."""
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:16]
    return os.path.join(run_dir, "external_eval", f"step{step}_{digest}.json")


def evaluate_run(run_dir: str, *, episodes: int, first_seed: int, max_steps: int, step: int | None = None,
                 inference: InferenceConfig | None = None, envs: int = 8, timeout: float | None = None,
                 keep: bool = False, fields: Sequence[str] = (), log=print) -> dict:
    """Serve the run at ``run_dir`` (checkpoint ``step``, default the latest; its stored inference settings unless
    ``inference``) and evaluate it on ``episodes`` episodes of its task from initial-state seeds ``first_seed``, ...
    with its bridge, ``envs`` at a time; → the bridge's record plus ``checkpoint_step``, the network's
    ``params_sha256`` (``records.params_fingerprint``), ``wall_s`` (serving and episodes), ``cpu_s`` (the CPU
    time of this process, whose threads serve the policy, and of the bridge) and ``reused`` (True: the record
    ``keep`` kept from an earlier call with the same network and settings; its ``wall_s`` and ``cpu_s`` are that
    call's; a kept record is reused only if every episode holds the per-episode ``fields``, so one kept before the
    bridge recorded them is made again)."""
    from hipolicy_jax.runs.serve import run_backend
    from hipolicy_jax.deploy.server import PolicyServer, ServerConfig

    t0, c0 = time.perf_counter(), cpu_seconds()
    backend = run_backend(run_dir, inference, step)
    name = backend.metadata["task"]
    external.check_name(name)
    fingerprint = params_fingerprint(backend._args.params)
    settings = {"episodes": episodes, "first_seed": first_seed, "max_steps": max_steps,
                "inference": backend.metadata.get("inference"), "thresholds": backend.metadata.get("thresholds")}
    flags = ""
    if inference is not None and inference.semantics != "rate":  # the bridge executes; rate settings stay as they were
        settings["semantics"] = {"semantics": inference.semantics, "waypoint_tolerance": inference.waypoint_tolerance,
                                 "waypoint_steps": inference.waypoint_steps}
        flags = f" --semantics {inference.semantics}"  # bounds left None: the bridge's own, measured on its experts
        tol, steps = inference.waypoint_tolerance, inference.waypoint_steps
        flags += ("" if tol is None else f" --waypoint-tolerance {tol!r}") + \
            ("" if steps is None else f" --waypoint-steps {steps}")
    path = kept_path(run_dir, backend.metadata.get("checkpoint_step"), settings) if keep else None
    kept = read_kept(path, log) if path is not None else None
    if kept is not None:
        complete = all(f in e for e in kept.get("per_episode") or [{}] for f in fields)
        if kept.get("params_sha256") == fingerprint and kept.get("settings") == settings and complete:
            log(f"[external] {name} step {kept['checkpoint_step']}: {kept['successes']}/{kept['episodes']} success "
                f"(kept in {os.path.relpath(path)})")
            return {**kept, "reused": True}
    check_bridge(name)
    suite = external.SUITES[name.partition(":")[0]]
    envs = max(1, min(envs, episodes))
    server = PolicyServer(backend, ServerConfig(port=0, max_batch=envs), log=lambda msg: None)
    server.start_in_thread()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            out = os.path.join(tmp, "eval.json")
            cmd = suite.evaluate.format(task=name.partition(":")[2], url=f"ws://127.0.0.1:{server.port}",
                                        episodes=episodes, first_seed=first_seed, envs=envs, max_steps=max_steps,
                                        out=out)
            _run(cmd + flags + " --no-progress", f"evaluating {run_dir} on {name}", timeout)
            with open(out) as f:
                record = json.load(f)
    finally:
        server.stop()
    record["checkpoint_step"] = backend.metadata.get("checkpoint_step")
    record["params_sha256"] = fingerprint
    record["wall_s"] = time.perf_counter() - t0
    record["cpu_s"] = cpu_seconds() - c0
    if path is not None:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with open(path + ".tmp", "w") as f:
            json.dump({**record, "settings": settings}, f)
        os.replace(path + ".tmp", path)
    record["reused"] = False
    log(f"[external] {name} step {record['checkpoint_step']}: {record['successes']}/{record['episodes']} success "
        f"({record['seconds']['total']:.0f} s)")
    return record


CALIBRATION_SEED = 3_000_000
"""First initial-state seed of an external run's closed-loop calibration episodes: training seed k calibrates on
seeds ``CALIBRATION_SEED + 1000 k + i`` (i < 1000). Calibrating on the episodes a result is measured on would tune
the thresholds to them, so the range is disjoint from the demos' (seeds from 0), the campaign's evaluation
(``envs.external.EVAL_SEED`` = 1,000,000 + 1000 k + i) and its periodic DP3-metric episodes
(``envs.external.PERIODIC_SEED`` = 2,000,000 + 1000 k + i), as the MJX tasks' ``calibrate.calibration_key`` is
disjoint from ``eval_key``."""

CALIBRATION_FIELDS = ("decision_strides", "entropies")  # what calibration reads of each episode of a bridge's record


def calibration_seeds(seed: int, episodes: int) -> range:
    """The initial-state seeds of training seed ``seed``'s ``episodes`` calibration episodes (``CALIBRATION_SEED``);
    ``ValueError`` naming the field when they would leave the seed's range of 1000."""
    if int(seed) < 0:
        raise ValueError(f"seed: calibration seeds start at CALIBRATION_SEED + 1000 seed; need seed >= 0, got {seed}")
    if not 1 <= episodes <= 1000:
        raise ValueError(f"episodes: 1 to 1000 calibration episodes per seed (its range of initial states), got "
                         f"{episodes}")
    first = CALIBRATION_SEED + 1000 * int(seed)
    return range(first, first + episodes)


def calibration_rollout(run, inference: InferenceConfig, thresholds: Sequence[float] | None = None, *,
                        episodes: int, seed: int, envs: int = 8, log=print, max_steps: int | None = None) -> dict:
    """``run``'s (a ``store.Run`` or a run dir, its latest checkpoint) ``episodes`` closed-loop calibration
    episodes (``calibration_seeds(seed, episodes)``) through its bridge, served with ``inference`` (its sampler,
    execution and semantics): ``thresholds`` None at stride 1 (``entropy_guided=False``: every decision's entropy,
    what the thresholds are calibrated on), else guided by those M+1 (or M−1 inner) thresholds. Kept in the run dir
    (``evaluate_run(keep=True)``), so a repeated calibration runs no episode again. → {``success_rate``,
    ``mean_steps`` (control steps), ``entropies`` (D,) float64 (NaN where a decision had none), ``strides`` (D,)
    int (D: every decision of every episode, episode by episode), ``decisions`` (E,) int, ``seeds`` (E,),
    ``record`` (the bridge's)}. ``max_steps``: the episodes' step limit (None: the suite's ``eval_max_steps``)."""
    from hipolicy_jax.runs.store import load_run

    seeds = calibration_seeds(seed, episodes)
    run = load_run(run) if isinstance(run, str) else run
    external.check_name(run.task)
    suite = external.SUITES[run.task.partition(":")[0]]
    m = run.policy.cfg.chunk.num_freqs
    if thresholds is None:  # stride 1 ignores the thresholds: none are needed, even before any calibration
        inference = dataclasses.replace(inference, entropy_guided=False,
                                        thresholds=inference.thresholds or tuple(float(i) for i in range(m - 1)))
    else:
        inference = dataclasses.replace(inference, entropy_guided=True,
                                        thresholds=tuple(float(t) for t in thresholds))
    limit = suite.eval_max_steps if max_steps is None else int(max_steps)
    record = evaluate_run(run.run_dir, episodes=episodes, first_seed=seeds[0], max_steps=limit,
                          step=int(run.policy.step), inference=inference, envs=envs, keep=True,
                          fields=CALIBRATION_FIELDS, log=log)
    return rollout_arrays(record)


def rollout_arrays(record: dict) -> dict:
    """``calibration_rollout``'s arrays from a bridge's record; ``ValueError`` naming the field when an episode's
    per-decision lists do not hold one entry per decision."""
    eps = record["per_episode"]
    for e in eps:
        for f in CALIBRATION_FIELDS:
            if f not in e:
                raise ValueError(f"per_episode.{f}: missing from the bridge's record (seed {e['seed']}); the bridge "
                                 f"predates per-decision records")
            if len(e[f]) != e["decisions"]:
                raise ValueError(f"per_episode.{f}: {len(e[f])} entries for {e['decisions']} decisions (seed "
                                 f"{e['seed']})")
    entropies = [np.nan if h is None else float(h) for e in eps for h in e["entropies"]]
    return {"success_rate": float(np.mean([bool(e["success"]) for e in eps])),
            "mean_steps": float(np.mean([e["steps"] for e in eps])),
            "entropies": np.asarray(entropies, np.float64),
            "strides": np.asarray([s for e in eps for s in e["decision_strides"]], np.int64),
            "decisions": np.asarray([e["decisions"] for e in eps], np.int64),
            "seeds": [int(e["seed"]) for e in eps], "record": record}


def closed_loop_entropies(run, inference: InferenceConfig, *, episodes: int, seed: int, envs: int = 8,
                          log=print) -> np.ndarray:
    """(D,) the entropies of every decision of ``run``'s ``episodes`` calibration episodes at stride 1
    (``calibration_rollout``; NaN where a decision had none)."""
    return calibration_rollout(run, inference, episodes=episodes, seed=seed, envs=envs, log=log)["entropies"]


def read_kept(path: str, log=print) -> dict | None:
    """The evaluation ``evaluate_run(keep=True)`` kept at ``path``; None when there is none, or when it does not
    read (not valid JSON, not an object): then one line through ``log`` names the file and says it is made again
    (it is only a cache of an evaluation that can be remade)."""
    if not os.path.exists(path):
        return None
    try:
        kept = jsonio.load(path, hint="")
    except jsonio.DamagedFileError as e:
        log(f"[external] {e.path}: {e.problem}; this kept evaluation is made again")
        return None
    if not isinstance(kept, dict):
        log(f"[external] {path}: holds no JSON object; this kept evaluation is made again")
        return None
    return kept


def external_summary(record: dict) -> dict:
    """``eval_summary``'s scalars from a bridge's evaluation record (``evaluate_run``): ``steps`` are control steps,
    ``actions`` the actions executed (a record from before the bridge counted them: one per control step)."""
    eps = record["per_episode"]
    success = np.asarray([e["success"] for e in eps], bool)
    steps = np.asarray([e["steps"] for e in eps], float)
    decisions = np.asarray([e["decisions"] for e in eps], float)
    actions = np.asarray([e.get("actions", e["steps"]) for e in eps], float)
    counts: dict[int, int] = {}
    for e in eps:
        for stride, n in e["strides"].items():
            counts[int(stride)] = counts.get(int(stride), 0) + int(n)
    out = {"success_rate": float(success.mean()),
           "mean_steps_success": float(steps[success].mean()) if success.any() else float("nan"),
           "mean_steps": float(steps.mean()), "mean_decisions": float(decisions.mean()),
           "mean_actions": float(actions.mean()),
           "mean_actions_per_decision": float(actions.sum() / max(decisions.sum(), 1))}
    total = sum(counts.values())
    for stride in sorted(counts):
        out[f"stride{stride}_frac"] = counts[stride] / total
    ent = [e["mean_entropy"] for e in eps if e.get("mean_entropy") is not None]
    if ent:
        out["mean_entropy"] = float(np.mean(ent))
    return out


def summary(record: dict) -> dict:
    """``external_summary`` plus per episode ``success``, ``steps`` (control steps), ``decisions`` and ``actions``."""
    eps = record["per_episode"]
    return {**external_summary(record), **{k: [type_(e[k]) for e in eps] for k, type_ in
                                           (("success", bool), ("steps", int), ("decisions", int))},
            "actions": [int(e.get("actions", e["steps"])) for e in eps]}


def evaluate_report(run_dir: str, inference: InferenceConfig, *, episodes: int, seed: int, step: int | None = None,
                    out: str = "", envs: int = 8, log=print) -> dict:
    """``experiments.evaluate`` of an external task's run: ``episodes`` episodes from initial-state seeds
    ``EVAL_SEED + 1000 seed + i`` (a campaign's evaluation of training seed ``seed``), served with ``inference``,
    once with entropy-guided execution and once always at stride 1 (skipped for a single-stride policy: the same
    run); both kept in the run dir (``evaluate_run(keep=True)``). Writes ``eval.json`` into ``out`` (default
    ``run_dir/eval``) and returns it: ``with_eg`` / ``without_eg`` (``summary``), the network's fingerprint, the
    checkpoint step, the initial-state seeds, the settings and ``reused`` (per pass: kept from an earlier
    evaluation of the same network and settings, e.g. a campaign's)."""
    from hipolicy_jax.evaluation import calibration
    from hipolicy_jax.runs.store import load_run, write_json

    run = load_run(run_dir, step)
    external.check_name(run.task)
    suite = external.SUITES[run.task.partition(":")[0]]
    first = external.EVAL_SEED + 1000 * int(seed)
    thresholds, source = calibration.resolve_thresholds(inference, run.policy.cfg.chunk.num_freqs,
                                                        calibration.read_calibration(run.run_dir))
    common = dict(episodes=episodes, first_seed=first, max_steps=suite.eval_max_steps, step=run.policy.step,
                  envs=envs, keep=True, log=log)
    guided = evaluate_run(run.run_dir, inference=inference, **common)
    plain = (guided if run.policy.cfg.chunk.num_freqs == 1 else
             evaluate_run(run.run_dir, inference=dataclasses.replace(inference, entropy_guided=False), **common))
    report = {"task": run.task, "checkpoint_step": guided["checkpoint_step"],
              "params_sha256": guided["params_sha256"], "episodes": episodes,
              "seeds": [first + i for i in range(episodes)], "max_steps": suite.eval_max_steps,
              "inference": dataclasses.asdict(inference), "thresholds": [float(t) for t in thresholds],
              "thresholds_source": source, "with_eg": summary(guided), "without_eg": summary(plain),
              "wall_s": guided["wall_s"] + (0.0 if plain is guided else plain["wall_s"]),
              "reused": {"with_eg": guided["reused"], "without_eg": plain["reused"]}}
    out = out or os.path.join(run.run_dir, "eval")
    os.makedirs(out, exist_ok=True)
    write_json(os.path.join(out, "eval.json"), report)
    return report


__all__ = ["CALIBRATION_FIELDS", "CALIBRATION_SEED", "calibration_rollout", "calibration_seeds", "check_bridge",
           "closed_loop_entropies", "collect_demos", "evaluate_report", "evaluate_run", "external_summary",
           "kept_path", "read_kept", "rollout_arrays", "summary"]
