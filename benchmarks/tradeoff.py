"""Latency–success trade-off of the sampler settings of trained DP+HiPolicy runs (diffusion and flow matching).

    python -m benchmarks.tradeoff                                   # cpu budget, both tasks and heads (~3 h)
    python -m benchmarks.tradeoff --skip-latency                    # quality only (a busy machine is fine)
    python -m benchmarks.tradeoff --only-latency                    # latency only (run it on a quiet machine)
    python -m benchmarks.tradeoff --quick                           # tiny subset, writes benchmarks/results/quick/
    python -m benchmarks.tradeoff --runs latch_door:flow:runs/my_flow_run

For DP+HiPolicy trained at the cpu budget of ``experiments.paper`` on press_button and latch_door, one diffusion run
(variant ``hipolicy``) and one flow-matching run (variant ``flow``, ``--policy.objective flow``) per task, default
``<--runs-root>/cpu/<task>/state/{hipolicy,flow}/seed<--seed>``, every sampler setting — diffusion DDPM 100 /
DDIM 10 / DDIM 4, flow Euler 10 / 4 / 2 / 1 steps — times N ∈ {4, 16, 100} samples per decision gets:

- **decision latency**: one call of the compiled sampler (``sampling.make_sampler``) on B = 1 held-out observation
  window, median (and p90) of up to ``--repeats`` calls after a warm-up that compiles, at most ``--row-budget-s``
  seconds of calls per row;
- **open loop** on ``--windows`` evenly spaced windows of the run's held-out demos (``runs.store.heldout_dataset``,
  batched through ``make_sampler(..., obs_normalized=True)``, the last batch padded so each setting compiles once):
  the **agreement** of the selected stride and the **Spearman** rank correlation of the action entropies with the
  run's reference setting (diffusion DDPM 100, flow Euler 10; N = 100). Each setting selects its stride with its
  OWN thresholds, calibrated at the 10th / 70th percentiles of its own entropies on those same windows: entropies
  of different samplers and N live on different scales, and a user who switches sampler recalibrates;
- **closed loop**: success rate and mean control steps of the successful episodes over ``--episodes`` episodes
  (the same initial states for every setting: ``runs.store.eval_key(--eval-seed)``), entropy-guided with the
  setting's own thresholds, through one ``evaluation.Evaluator`` per setting — only when one batched decision
  (one sampler call for all the episodes at once) costs under ``--closed-loop-limit-s`` (30 s): estimated as the
  B = 1 latency × episodes, measured with one real batched call (after its compile) only when that estimate is
  within a factor 3 of the limit. Settings over the limit get null success / steps and
  ``"closed_loop": "not run: batched decision ~X s > 30 s"``.

Writes ``benchmarks/results/tradeoff_<device>.json`` after every row (rows: ``task, head, sampler, num_steps,
num_samples, latency_ms, agreement, spearman, success_rate, mean_steps`` and more) and, at the end,
``tradeoff_<device>.png`` (decision latency on a log axis vs closed-loop success). Re-running resumes: a row's
latency is kept when it was measured on the same checkpoint, its open- and closed-loop results when they were
computed with the same windows, episodes, percentiles, reference and evaluation seed (``--fresh`` discards the
file); rows of other tasks / heads / N in the file are kept.

``cheapest_within`` names the cheapest setting (mean B = 1 latency over the tasks) whose closed-loop success is
within 3 points of the cpu budget's evaluation setting (diffusion DDIM 10, N = 16) on every task, or better, with
its latency ratio to that setting and to DDPM 100 / N = 100; it is printed at the end and stored as
``cheapest_within_3_points``. Result on the cpu budget (2 cores): "Euler 2, N=4 (flow), 7.99 ms per decision, 0.0927x
the latency of DDIM 10, N=16 and 0.00231x that of DDPM 100, N=100" (benchmarks/results/tradeoff_cpu.json).

The full run takes 2-3 hours on 2 idle cores (longer on a busy machine): closed-loop rollouts, mostly the settings
just under the 30 s limit (a rollout makes up to 19 (press_button) / 25 (latch_door) batched decisions and stops
once every episode is over); open loop ~30 min, half of it the DDPM 100 / N = 100 reference; latency ~20 min.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shlex
import sys
import time
from typing import NamedTuple

import jax
import numpy as np

from benchmarks.common import (RESULTS_DIR, base_parser, device_kind, latency_stats, markdown_table, precision_context,
                               report_rows, timed_calls, write_results)
from hipolicy_jax import jsonio
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.evaluation import calibration, eval_summary
from hipolicy_jax.heads import make_head
from hipolicy_jax.campaigns.budgets import run_config
from hipolicy_jax.runs.store import Run, eval_key, heldout_dataset, load_run, make_evaluator
from hipolicy_jax.runs.train import RunConfig
from hipolicy_jax.sampling import make_sampler, select_frequency
from hipolicy_jax.trainer import run_keys

NAME = "tradeoff"
TASKS = ("press_button", "latch_door")
HEADS = ("diffusion", "flow")
# experiments.paper config changes of each head's cpu-budget run: variant dirs 'hipolicy' and 'flow'
HEAD_CHANGES: dict[str, tuple[tuple[str, str], ...]] = {"diffusion": (), "flow": (("objective", "flow"),)}
EVAL_SETTING = ("diffusion", "ddim", 10, 16)  # the cpu budget's evaluation setting (BUDGETS["cpu"].inference)
TOP_SETTING = ("diffusion", "ddpm", 100, 100)  # the paper's setting
IDENTITY_KEYS = ("task", "head", "sampler", "num_steps", "num_samples", "setting", "run", "checkpoint_step")
LATENCY_KEYS = ("latency_ms", "latency_p90_ms", "latency_min_ms", "latency_calls", "compile_s")
REQUIRED_KEYS = ("task", "head", "sampler", "num_steps", "num_samples", "latency_ms", "agreement", "spearman",
                 "success_rate", "mean_steps")


class Setting(NamedTuple):
    """One sampler setting of one head: sampler name, reverse / Euler steps and N samples per decision."""

    head: str
    sampler: str
    num_steps: int
    num_samples: int

    def inference(self) -> InferenceConfig:
        return InferenceConfig(num_samples=self.num_samples, sampler=self.sampler, num_steps=self.num_steps)


def parse_sampler_steps(text: str, flag: str) -> tuple[str, int]:
    """'ddim:10' → ('ddim', 10); ValueError naming ``flag`` otherwise."""
    sampler, _, steps = text.partition(":")
    if not sampler or not steps.isdigit() or int(steps) < 1:
        raise ValueError(f"{flag}: expected SAMPLER:STEPS such as ddim:10, got {text!r}")
    return sampler, int(steps)


def parse_args(argv=None) -> argparse.Namespace:
    p = base_parser(NAME, __doc__)
    p.add_argument("--tasks", nargs="+", default=list(TASKS))
    p.add_argument("--heads", nargs="+", default=list(HEADS), choices=list(HEADS))
    p.add_argument("--ns", nargs="+", type=int, default=[4, 16, 100], help="N samples per decision")
    p.add_argument("--diffusion-settings", nargs="+", default=["ddpm:100", "ddim:10", "ddim:4"],
                   help="SAMPLER:STEPS of the diffusion head (ddpm, ddim, ddim-clipped)")
    p.add_argument("--flow-settings", nargs="+", default=["euler:10", "euler:4", "euler:2", "euler:1"],
                   help="SAMPLER:STEPS of the flow head (euler)")
    p.add_argument("--diffusion-reference", default="ddpm:100", help="reference SAMPLER:STEPS of the diffusion head")
    p.add_argument("--flow-reference", default="euler:10", help="reference SAMPLER:STEPS of the flow head")
    p.add_argument("--reference-n", type=int, default=100, help="N of the reference settings")
    p.add_argument("--runs-root", default="runs/paper",
                   help="experiments.paper --runs: default run dirs <root>/cpu/<task>/state/{hipolicy,flow}/seed<k>")
    p.add_argument("--seed", type=int, default=0, help="training seed of the default run dirs")
    p.add_argument("--runs", nargs="+", default=[], metavar="TASK:HEAD:PATH",
                   help="run dir of one task and head (of --tasks / --heads) instead of the default under --runs-root")
    p.add_argument("--windows", type=int, default=64, help="held-out windows of the open-loop comparison")
    p.add_argument("--window-batch", type=int, default=32, help="windows per sampler call (last batch padded)")
    p.add_argument("--percentiles", nargs="+", type=float, default=[10.0, 70.0],
                   help="threshold percentiles of each setting's own entropies (M-1 values)")
    p.add_argument("--episodes", type=int, default=50, help="closed-loop episodes per setting")
    p.add_argument("--eval-seed", type=int, default=0, help="initial states: runs.store.eval_key(EVAL_SEED)")
    p.add_argument("--max-steps", type=int, default=None, help="control steps per episode (default: the task's)")
    p.add_argument("--closed-loop-limit-s", type=float, default=30.0,
                   help="closed loop only for settings whose batched decision (B = episodes) costs less")
    p.add_argument("--repeats", type=int, default=20, help="timed B = 1 calls per row after the warm-up")
    p.add_argument("--row-budget-s", type=float, default=20.0,
                   help="stop a row's latency repeats once it has spent this long (at least 2 calls)")
    p.add_argument("--only-latency", action="store_true", help="measure latencies only (on a quiet machine)")
    p.add_argument("--skip-latency", action="store_true", help="open and closed loop only, keep stored latencies")
    p.add_argument("--fresh", action="store_true", help="discard the existing JSON instead of resuming it")
    p.add_argument("--quick", action="store_true",
                   help="press_button, N 4, DDIM 4 / Euler 2, reference N 16, 16 windows, 4 episodes of 48 steps; "
                        "writes under benchmarks/results/quick/ unless --out-dir")
    args = p.parse_args(argv)
    if args.quick:
        args.tasks, args.ns = ["press_button"], [4]
        args.diffusion_settings, args.flow_settings = ["ddim:4"], ["euler:2"]
        args.reference_n, args.windows, args.window_batch, args.episodes = 16, 16, 16, 4
        args.max_steps, args.repeats, args.row_budget_s = args.max_steps or 48, 5, 5.0
        args.out_dir = args.out_dir or os.path.join(RESULTS_DIR, "quick")
    if args.only_latency and args.skip_latency:
        p.error("--only-latency and --skip-latency exclude each other")
    for flag, value in (("--windows", args.windows), ("--window-batch", args.window_batch),
                        ("--episodes", args.episodes), ("--reference-n", args.reference_n)):
        if value < 1 or (flag == "--reference-n" and value < 2):
            p.error(f"{flag}: must be >= {2 if flag == '--reference-n' else 1}, got {value}")
    if min(args.ns) < 2:
        p.error(f"--ns: the entropy needs N >= 2, got {args.ns}")
    try:
        for flag in ("--diffusion-settings", "--flow-settings", "--diffusion-reference", "--flow-reference"):
            value = getattr(args, flag[2:].replace("-", "_"))
            for text in value if isinstance(value, list) else [value]:
                parse_sampler_steps(text, flag)
    except ValueError as e:
        p.error(str(e))
    return args


# ------------------------------------------------------------------------------------------------------ runs


def train_command(cfg: RunConfig) -> str:
    """The exact ``python -m experiments.train`` command of ``cfg``: every field that differs from ``RunConfig()``."""
    parts = ["python", "-m", "experiments.train"]

    def flags(value, default, prefix: str):
        for f in dataclasses.fields(value):
            v, d = getattr(value, f.name), getattr(default, f.name)
            flag = "--" + prefix + f.name.replace("_", "-")
            if dataclasses.is_dataclass(v):
                flags(v, d, prefix + f.name.replace("_", "-") + ".")
            elif v != d:
                if isinstance(v, bool):
                    parts.append(flag if v else "--" + prefix + "no-" + f.name.replace("_", "-"))
                elif isinstance(v, tuple):
                    parts.extend([flag, *(str(x) for x in v)])
                else:
                    parts.extend([flag, str(v)])

    flags(cfg, RunConfig(), "")
    return shlex.join(parts)


def cpu_run_config(root: str, task: str, head: str, seed: int, out: str | None = None) -> RunConfig:
    """The cpu-budget ``RunConfig`` (``runs.budgets``, as ``experiments.paper`` lays runs out) for one task and head
    (``out``: another run dir)."""
    cfg = run_config("cpu", task, "state", HEAD_CHANGES[head], seed, runs=root)
    return dataclasses.replace(cfg, out=out) if out else cfg


def run_paths(args) -> dict[tuple[str, str], tuple[str, str]]:
    """{(task, head): (run dir, the flag that named it)} from ``--runs`` and the ``--runs-root`` layout."""
    paths = {(t, h): (cpu_run_config(args.runs_root, t, h, args.seed).out, "--runs-root")
             for t in args.tasks for h in args.heads}
    for spec in args.runs:
        task, head, path = (spec.split(":", 2) + ["", ""])[:3]
        if head not in HEADS or not task or not path:
            raise ValueError(f"--runs: expected TASK:HEAD:PATH with HEAD one of {list(HEADS)}, got {spec!r}")
        if (task, head) in paths:
            paths[task, head] = (path, "--runs")
    return paths


def open_run(task: str, head: str, path: str, flag: str, args) -> Run:
    """Load a finished run (``checkpoints/`` and ``summary.json``), checking it is a ``head`` run of ``task``;
    one-line errors name the flag and the path."""
    if not all(os.path.exists(os.path.join(path, f)) for f in ("checkpoints", "summary.json")):
        out = None if flag == "--runs-root" else path
        raise FileNotFoundError(f"{flag}: {path} is not a trained run (train it with: "
                                f"{train_command(cpu_run_config(args.runs_root, task, head, args.seed, out))})")
    run = load_run(path)
    if run.policy.cfg.objective != head:
        raise ValueError(f"{flag}: {path} is a {run.policy.cfg.objective} run, not {head}")
    if run.task != task:
        raise ValueError(f"{flag}: {path} is a {run.task} run, not {task}")
    return run


def sweep(args, head: str) -> list[tuple[str, int]]:
    """(sampler, steps) of one head, in the order of its flag."""
    texts = args.diffusion_settings if head == "diffusion" else args.flow_settings
    return [parse_sampler_steps(t, f"--{head}-settings") for t in texts]


def reference_setting(args, head: str) -> Setting:
    flag = f"--{head}-reference"
    return Setting(head, *parse_sampler_steps(getattr(args, flag[2:].replace("-", "_")), flag), args.reference_n)


def setting_name(run: Run, s: Setting) -> str:
    """E.g. 'DDIM 10, N=16' (the head's own description of the sampler)."""
    return f"{make_head(run.policy.cfg).describe(s.inference())}, N={s.num_samples}"


def row_key(row: dict) -> tuple:
    return row["task"], row["head"], row["sampler"], row["num_steps"], row["num_samples"]


# ------------------------------------------------------------------------------------------------- measures


def average_ranks(x: np.ndarray) -> np.ndarray:
    """1-based ranks of ``x`` (n,), ties getting the average of their ranks."""
    _, inverse, counts = np.unique(np.asarray(x, np.float64), return_inverse=True, return_counts=True)
    ends = np.cumsum(counts)
    return ((2 * ends - counts + 1) / 2.0)[inverse]


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman rank correlation of two (n,) samples (Pearson correlation of average ranks); NaN if one is
    constant."""
    ra, rb = average_ranks(a), average_ranks(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    denom = math.sqrt(float(np.sum(ra * ra) * np.sum(rb * rb)))
    return float(np.sum(ra * rb) / denom) if denom > 0 else math.nan


def selected_strides(run: Run, entropies: np.ndarray, thresholds) -> np.ndarray:
    """The stride ``sampling.select_frequency`` selects for each entropy (S,) with M+1 ``thresholds``."""
    chunk = run.policy.cfg.chunk
    k = np.asarray(select_frequency(np.asarray(entropies, np.float32), thresholds, chunk.num_freqs))
    return np.asarray(chunk.strides)[k]


def open_loop(sampler, run: Run, dataset, args) -> dict:
    """Entropies (S,) of ``--windows`` evenly spaced held-out windows, the thresholds at ``--percentiles`` of them
    and the strides those select."""
    p = run.policy
    batch = min(args.window_batch, len(calibration.evenly_spaced(len(dataset), args.windows)))
    h = calibration.measure_entropies(sampler, p.params, p.normalizer, dataset, run_keys(run.seed)["eval"],
                                      max_windows=args.windows, batch_size=batch)
    th = calibration.calibrate_thresholds(h, p.cfg.chunk.num_freqs, args.percentiles)
    return {"entropies": h, "thresholds": th, "strides": selected_strides(run, h, th)}


def stride_fractions(run: Run, strides: np.ndarray, prefix: str) -> dict:
    return {f"{prefix}stride{s}_frac": float(np.mean(strides == s)) for s in run.policy.cfg.chunk.strides}


def measure_latency(sampler, run: Run, obs1, repeats: int, budget_s: float | None) -> dict:
    """B = 1 decision latency of the compiled sampler: median / p90 / min over the timed calls, after a warm-up
    call that compiles (its time: ``compile_s``)."""
    p = run.policy
    th = calibration.guidance_thresholds(None, p.cfg.chunk.num_freqs)  # traced (M+1,): the call selects a stride
    times, first = timed_calls(lambda i: sampler(p.params, p.normalizer, obs1, jax.random.key(i), th).chunks,
                               repeats, budget_s, warmup=1)
    stats = latency_stats(times)
    return {"latency_ms": stats["median_s"] * 1e3, "latency_p90_ms": stats["p90_s"] * 1e3,
            "latency_min_ms": stats["min_s"] * 1e3, "latency_calls": stats["calls"], "compile_s": first}


def batched_decision(sampler, run: Run, dataset, b1_s: float, args) -> tuple[float, str, bool]:
    """(seconds, how they were obtained, run the closed loop?) of one decision for all ``--episodes`` at once:
    B = 1 latency × episodes, measured with one real call (after its compile) when within 3x of the limit."""
    limit, estimate = args.closed_loop_limit_s, b1_s * args.episodes
    if estimate > 3 * limit or estimate < limit / 3:
        return estimate, "B=1 latency x episodes", estimate <= limit
    p = run.policy
    idx = np.resize(calibration.evenly_spaced(len(dataset), args.episodes), args.episodes)
    call = (p.params, p.normalizer, dataset.get_batch(idx)["obs"], jax.random.key(0),
            calibration.guidance_thresholds(None, p.cfg.chunk.num_freqs))
    compiled = sampler.lower(*call).compile()  # compile without running: one call of a near-limit setting is ~30 s
    times, _ = timed_calls(lambda i: compiled(*call).chunks, 1, warmup=0, min_calls=1)
    return times[0], "measured", times[0] <= limit


def closed_loop(run: Run, s: Setting, thresholds, args) -> dict:
    """``eval_summary`` of ``--episodes`` entropy-guided episodes from ``eval_key(--eval-seed)``, one Evaluator."""
    p = run.policy
    t0 = time.perf_counter()
    ev = make_evaluator(run, s.inference(), max_steps=args.max_steps)
    res = ev.evaluate(p.params, p.normalizer, args.episodes, eval_key(args.eval_seed), thresholds,
                      entropy_guided=True)
    summary = eval_summary(res)
    success_steps = summary["mean_steps_success"]
    out = {"success_rate": summary["success_rate"],
           "mean_steps": success_steps if math.isfinite(success_steps) else None,
           "mean_steps_all": summary["mean_steps"], "closed_loop_s": time.perf_counter() - t0,
           **{f"closed_{k}": v for k, v in summary.items() if k.startswith("stride") or k == "mean_entropy"}}
    return out


# ---------------------------------------------------------------------------------------------- the results


def cheapest_within(rows: list[dict], tasks, margin: float = 0.03, base: tuple = EVAL_SETTING,
                    top: tuple = TOP_SETTING) -> dict | None:
    """The setting with the lowest mean B = 1 latency over ``tasks`` whose success is at least ``base``'s minus
    ``margin`` on every task, with its latency ratios to ``base`` and ``top``; None without ``base``'s success and
    latency on every task. Settings are (head, sampler, num_steps, num_samples)."""
    by = {(r["task"], r["head"], r["sampler"], r["num_steps"], r["num_samples"]): r for r in rows}

    def cost(setting) -> float | None:
        rs = [by.get((t, *setting)) for t in tasks]
        if any(r is None or r.get("latency_ms") is None or r.get("success_rate") is None for r in rs):
            return None
        return float(np.mean([r["latency_ms"] for r in rs]))

    def latency(setting) -> float | None:
        rs = [by.get((t, *setting)) for t in tasks]
        ok = all(r is not None and r.get("latency_ms") is not None for r in rs)
        return float(np.mean([r["latency_ms"] for r in rs])) if ok else None

    base_cost = cost(base)
    if base_cost is None:
        return None
    base_success = {t: by[(t, *base)]["success_rate"] for t in tasks}
    best = None
    for setting in sorted({k[1:] for k in by}):
        c = cost(setting)
        if c is None or any(by[(t, *setting)]["success_rate"] < base_success[t] - margin - 1e-9 for t in tasks):
            continue
        if best is None or c < best[1]:
            best = (setting, c)
    setting, c = best
    top_latency = latency(top)
    name = by[(tasks[0], *setting)].get("setting", " ".join(map(str, setting)))
    base_name = by[(tasks[0], *base)].get("setting", " ".join(map(str, base)))
    out = {"head": setting[0], "sampler": setting[1], "num_steps": setting[2], "num_samples": setting[3],
           "setting": name, "latency_ms": c, "margin": margin, "tasks": list(tasks),
           "success_rate": {t: by[(t, *setting)]["success_rate"] for t in tasks}, "base_setting": base_name,
           "base_success_rate": base_success, "latency_ratio_to_base": c / base_cost,
           "latency_ratio_to_top": c / top_latency if top_latency else None}
    top_text = f"{out['latency_ratio_to_top']:.3g}x" if top_latency else "n/a (not measured)"
    out["summary"] = (f"cheapest setting within {margin * 100:g} points of {base_name} ({base[0]}) on "
                      f"{', '.join(tasks)}: {name} ({setting[0]}), {c:.4g} ms per decision, "
                      f"{out['latency_ratio_to_base']:.3g}x the latency of {base_name} and {top_text} that of "
                      f"DDPM 100, N=100")
    return out


def _label(text: str) -> str:
    """'ddpm:100' → 'DDPM 100', 'euler:10' → 'Euler 10'."""
    sampler, steps = parse_sampler_steps(text, "setting")
    return f"{sampler.capitalize() if sampler == 'euler' else sampler.upper()} {steps}"


def recalibration_note(args) -> str:
    """The JSON's ``note``: how strides are selected and compared, for the report."""
    pct = " / ".join(f"{p:g}" for p in args.percentiles)
    return (f"Each setting selects its stride with its OWN thresholds, calibrated at the {pct} percentiles of its own "
            f"entropies on the same {args.windows} held-out windows (a user who switches sampler or N recalibrates). "
            f"Agreement (of the selected stride) and Spearman (of the entropies) compare with the run's reference "
            f"setting: diffusion {_label(args.diffusion_reference)}, flow {_label(args.flow_reference)}, "
            f"N={args.reference_n}. Closed loop: {args.episodes} entropy-guided episodes from the same initial "
            f"states, only where one batched decision for all of them costs under {args.closed_loop_limit_s:g} s; "
            f"steps (succ.) = mean control steps of the successful episodes; latency = one B = 1 decision.")


def _cell(v, scale: float = 1.0):
    return "–" if v is None else v * scale if isinstance(v, float) else v


def _short(v) -> str:
    """A value for the progress lines: 4 significant digits, '–' for None."""
    return "–" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v)


def results_table(rows: list[dict]) -> str:
    """Markdown table of the rows ('–': not measured / not run)."""
    return markdown_table(
        ["task", "head", "setting", "latency ms", "p90 ms", "agreement", "Spearman", "success %", "steps (succ.)",
         "batched s", "closed loop"],
        [[r["task"], r["head"], r.get("setting", ""), _cell(r.get("latency_ms")), _cell(r.get("latency_p90_ms")),
          _cell(r.get("agreement")), _cell(r.get("spearman")), _cell(r.get("success_rate"), 100.0),
          _cell(r.get("mean_steps")), _cell(r.get("batched_decision_s")),
          "run" if r.get("closed_loop") == "run" else (r.get("closed_loop") or "–").replace("not run: ", "skipped: ")]
         for r in rows])


def plot_tradeoff(rows: list[dict], path: str) -> str:
    """PNG: B = 1 decision latency (log x) vs closed-loop success, one point per setting; colour = task, marker =
    head, annotated with sampler / steps / N."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    tasks = list(dict.fromkeys(r["task"] for r in rows))
    colours = {t: f"C{i}" for i, t in enumerate(tasks)}
    markers = {"diffusion": "o", "flow": "^"}
    fig, ax = plt.subplots(figsize=(8, 5))
    points = [r for r in rows if r.get("latency_ms") is not None and r.get("success_rate") is not None]
    for r in points:
        x, y = r["latency_ms"], 100 * r["success_rate"]
        ax.scatter(x, y, c=colours[r["task"]], marker=markers.get(r["head"], "s"), s=36, alpha=0.85)
        ax.annotate(f"{r['sampler']} {r['num_steps']} N{r['num_samples']}", (x, y), fontsize=6,
                    xytext=(3, 3), textcoords="offset points")
    if points:
        ax.set_xscale("log")
    else:
        ax.text(0.5, 0.5, "no setting with both latency and closed-loop success yet", ha="center",
                transform=ax.transAxes)
    handles = [Line2D([], [], color=colours[t], marker="o", ls="", label=t) for t in tasks]
    handles += [Line2D([], [], color="gray", marker=m, ls="", label=h) for h, m in markers.items()]
    ax.legend(handles=handles, fontsize=8, loc="best")
    ax.set_xlabel("decision latency (ms, B = 1, log scale)")
    ax.set_ylabel("closed-loop success (%)")
    ax.set_title("Latency–success trade-off of the sampler settings (entropy-guided, own thresholds)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------------------------------- main


def _result_path(args) -> str:
    return os.path.join(args.out_dir or RESULTS_DIR, f"{NAME}_{device_kind()}.json")


def _sort_rows(rows: list[dict], args) -> list[dict]:
    task_order = {t: i for i, t in enumerate(dict.fromkeys([*args.tasks, *TASKS]))}
    sampler_order = {h: {s: i for i, s in enumerate(sweep(args, h))} for h in HEADS}
    return sorted(rows, key=lambda r: (task_order.get(r["task"], len(task_order)), r["task"], r["head"],
                                       sampler_order[r["head"]].get((r["sampler"], r["num_steps"]), 99),
                                       r["sampler"], -r["num_steps"], r["num_samples"]))


def quality_signature(run: Run, args) -> dict:
    """What a row's open- and closed-loop results depend on besides the setting (stored in the row; resume reuses
    the results only when it matches)."""
    return {"windows": args.windows, "episodes": args.episodes, "eval_seed": args.eval_seed,
            "max_steps": args.max_steps, "percentiles": list(args.percentiles),
            "reference": setting_name(run, reference_setting(args, run.policy.cfg.objective))}


def quality_done(prev: dict, run: Run, args) -> bool:
    """Whether ``prev`` (a stored row of the same run and checkpoint) holds open- and closed-loop results of the
    current settings; a closed loop skipped under another limit is redone."""
    if "closed_loop" not in prev or any(prev.get(k) != v for k, v in quality_signature(run, args).items()):
        return False
    return prev["closed_loop"] == "run" or prev.get("closed_loop_limit_s") == args.closed_loop_limit_s


def reference_entropies(run: Run, dataset, references: dict, args) -> dict:
    """The run's reference open-loop record {setting, entropies, thresholds, strides}: from ``references`` (the
    JSON's) when measured on the same run, checkpoint and windows, else measured now and stored there."""
    ref = reference_setting(args, run.policy.cfg.objective)
    ref_id = f"{run.task}/{ref.head}"
    signature = {"run": os.path.relpath(run.run_dir), "checkpoint_step": run.policy.step, "windows": args.windows,
                 "setting": list(ref)}
    if references.get(ref_id, {}).get("signature") != signature:
        p = run.policy
        t0 = time.perf_counter()
        r = open_loop(make_sampler(p.net, p.cfg, run.action_dim, ref.inference(), obs_normalized=True), run, dataset,
                      args)
        references[ref_id] = {"signature": signature, "setting": setting_name(run, ref), **r,
                              "seconds": time.perf_counter() - t0}
    r = references[ref_id]
    return {"setting": r["setting"], "entropies": np.asarray(r["entropies"], np.float64),
            "thresholds": tuple(float(t) for t in r["thresholds"]), "strides": np.asarray(r["strides"])}


def measure_quality(run: Run, s: Setting, sampler, dataset, reference: dict, b1_s: float | None, args) -> dict:
    """Open loop against ``reference`` (the setting's own thresholds), then the closed loop when the batched
    decision is under the limit; → the row's quality fields."""
    is_reference = s == reference_setting(args, s.head)
    ol = reference if is_reference else open_loop(sampler, run, dataset, args)
    out = {**quality_signature(run, args), "windows_used": int(ol["entropies"].size),
           "thresholds": list(ol["thresholds"]), "agreement": float(np.mean(ol["strides"] == reference["strides"])),
           "spearman": spearman(ol["entropies"], reference["entropies"]),
           "open_mean_entropy": float(np.mean(ol["entropies"])), **stride_fractions(run, ol["strides"], "open_")}
    if b1_s is None:  # no stored B = 1 latency (--skip-latency): one warm call for the estimate
        b1_s = measure_latency(sampler, run, dataset.get_batch(np.zeros(1, np.int64))["obs"], 1, None)["latency_ms"]
        b1_s /= 1e3
    batched_s, source, ok = batched_decision(sampler, run, dataset, b1_s, args)
    out.update(batched_decision_s=batched_s, batched_decision_source=source,
               closed_loop_limit_s=args.closed_loop_limit_s)
    if ok:
        out.update(closed_loop(run, s, ol["thresholds"], args), closed_loop="run")
    else:
        out.update(success_rate=None, mean_steps=None, mean_steps_all=None,
                   closed_loop=f"not run: batched decision ~{batched_s:.3g} s > {args.closed_loop_limit_s:g} s")
    return out


def main(argv=None) -> dict:
    """Run (or resume) the sweep, print the table and the cheapest setting, write the JSON and PNG; → the payload."""
    args = parse_args(argv)
    path = _result_path(args)
    old = {}
    if not args.fresh and os.path.exists(path):
        with open(path) as f:
            old = jsonio.loads(f.read())
    rows = {row_key(r): r for r in old.get("rows", [])}
    references: dict = dict(old.get("references", {}))
    extra = {"note": recalibration_note(args), "percentiles": list(args.percentiles), "references": references}
    runs = {k: open_run(*k, *v, args) for k, v in run_paths(args).items()}  # fail early on a missing run
    command = "python -m benchmarks.tradeoff " + " ".join(sys.argv[1:] if argv is None else argv)

    def save():
        ordered = _sort_rows(list(rows.values()), args)
        write_results(NAME, {"command": command, "args": {k: v for k, v in vars(args).items() if k != "out_dir"},
                             **extra, "rows": ordered, "table_md": results_table(ordered)}, args.out_dir)

    t_start = time.perf_counter()
    with precision_context(args.matmul_precision):
        for (task, head), run in runs.items():
            p, dataset = run.policy, heldout_dataset(run)
            obs1 = dataset.get_batch(np.zeros(1, np.int64))["obs"]  # (1, M, L_h, D): one held-out window
            rel = os.path.relpath(run.run_dir)
            for sampler_name, steps in sweep(args, head):
                for n in args.ns:
                    s = Setting(head, sampler_name, steps, n)
                    row = {"task": task, "head": head, "sampler": sampler_name, "num_steps": steps, "num_samples": n,
                           "setting": setting_name(run, s), "run": rel, "checkpoint_step": p.step,
                           **{k: None for k in REQUIRED_KEYS[5:]}}
                    prev = rows.get((task, *s), {})
                    if prev.get("run") == rel and prev.get("checkpoint_step") == p.step:
                        row.update(prev)
                    else:
                        prev = {}
                    need_latency = not args.skip_latency and row["latency_ms"] is None
                    need_quality = not args.only_latency and not quality_done(prev, run, args)
                    if not (need_latency or need_quality):
                        print(f"[{task}/{head}] {row['setting']}: kept from {path}")
                        continue
                    t0 = time.perf_counter()
                    sampler = make_sampler(p.net, p.cfg, run.action_dim, s.inference(), obs_normalized=True)
                    if need_latency:
                        row.update(measure_latency(sampler, run, obs1, args.repeats, args.row_budget_s))
                    if need_quality:
                        row = {k: v for k, v in row.items() if k in IDENTITY_KEYS or k in LATENCY_KEYS}
                        reference = reference_entropies(run, dataset, references, args)
                        b1_s = None if row.get("latency_ms") is None else row["latency_ms"] / 1e3
                        row.update(measure_quality(run, s, sampler, dataset, reference, b1_s, args))
                    rows[(task, *s)] = {**{k: None for k in REQUIRED_KEYS}, **row,
                                        "row_s": time.perf_counter() - t0}
                    save()
                    r = rows[(task, *s)]
                    print(f"[{task}/{head} {time.perf_counter() - t_start:6.0f}s] {r['setting']}: latency "
                          f"{_short(r['latency_ms'])} ms, agreement {_short(r['agreement'])}, Spearman "
                          f"{_short(r['spearman'])}, success {_short(r['success_rate'])} "
                          f"({r.get('closed_loop', 'open / closed loop not measured')})", flush=True)
    ordered = _sort_rows(list(rows.values()), args)
    cheapest = cheapest_within(ordered, list(dict.fromkeys(r["task"] for r in ordered)))
    png = plot_tradeoff(ordered, os.path.join(os.path.dirname(path), f"{NAME}_{device_kind()}.png"))
    extra.update(cheapest_within_3_points=cheapest, png=os.path.basename(png))
    payload = report_rows(NAME, argv, args, ordered, results_table(ordered), **extra)
    print(f"wrote {png}")
    print(cheapest["summary"] if cheapest else
          "cheapest setting within 3 points: needs the latency and closed-loop success of diffusion DDIM 10, N=16 "
          "on every task")
    return payload


if __name__ == "__main__":
    try:
        main()
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"error: {e}")
