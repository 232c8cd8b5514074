"""Reproduce the paper's experiment tables on the MJX tasks: ``python -m experiments.paper TABLE --budget B``.

Tables (sub-commands), each trained with ``hipolicy_jax.runs.train`` and evaluated on the same episodes per seed:

- ``main``: DP vs DP+HiPolicy per task, precise / non-precise tasks apart (``envs.TASK_PRECISE``); with
  ``--obs-types state pointcloud`` also DP3 vs DP3+HiPolicy (point-cloud encoder, sample prediction).
- ``ablation``: HiPolicy with hierarchical / low-only / high-only observation conditions, without fusion, and
  without the hierarchy (one stride, i.e. DP).
- ``entropy``: success and execution steps of DP, DP+HiPolicy without entropy-guided execution (always stride 1)
  and with it (the same trained model, two evaluations).
- ``thresholds``: entropy-guided execution with thresholds at several percentile pairs of held-out demo entropies.
- ``hparams``: L_h, L_c and M around the defaults (3, 8, 3).

Budgets: ``smoke`` (tiny model, a dozen steps: checks the pipeline in a couple of minutes), ``cpu`` (CPU model,
2000 steps: about 10 minutes of training per run on 2 cores), ``gpu`` (paper-size model, N=100, 100 DDPM steps).
Runs go to ``--runs/<budget>/<task>/<obs>/<variant>/seed<k>`` and are shared between tables (DP, HiPolicy); an
existing finished run is reused and an unfinished one resumed. Evaluations are cached per run in
``paper_evals.json``. Outputs: ``--results/<table>.md`` (mean ± std over seeds, with the command and seeds at the
top), ``<table>.png`` and ``<table>.json`` (every per-seed number).

    python -m experiments.paper entropy --budget smoke --tasks press_button --seeds 0
    python -m experiments.paper main --budget cpu --tasks press_button latch_door --seeds 0 1 2
"""

from __future__ import annotations

import dataclasses
import json
import os
import shlex
import sys
import time
from typing import Any, Literal, NamedTuple

import numpy as np
import tyro

from hipolicy_jax.config import InferenceConfig, PolicyConfig
from hipolicy_jax.envs import TASK_PRECISE
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.evaluation.evaluator import Evaluator, eval_summary
from hipolicy_jax.runs.budgets import BUDGETS, DP, run_config, variant_name
from hipolicy_jax.runs.calibrate import run_entropies
from hipolicy_jax.runs.store import Run, eval_key, make_evaluator, read_json, write_json
from hipolicy_jax.runs.train import RunConfig, ensure_trained

TaskName = Literal["press_button", "latch_door", "stack_cubes", "pick_place"]
ObsName = Literal["state", "image", "pointcloud"]
TABLES = ("main", "ablation", "entropy", "thresholds", "hparams")
BASELINE_NAME = {"state": "DP", "image": "DP (image)", "pointcloud": "DP3"}


@dataclasses.dataclass(frozen=True)
class PaperArgs:
    budget: Literal["smoke", "cpu", "gpu"] = "cpu"
    tasks: tuple[TaskName, ...] = ("press_button", "stack_cubes", "latch_door", "pick_place")
    seeds: tuple[int, ...] = (0, 1, 2)
    runs: str = "runs/paper"  # run dirs: <runs>/<budget>/<task>/<obs>/<variant>/seed<k>
    results: str = "results"  # <results>/<table>.{md,png,json}
    data: str = "data"  # demo buffers: <data>/<task>_<obs keys>_<episodes>.zarr
    episodes: int | None = None  # evaluation episodes (default: the budget's)
    progress: bool = True


@dataclasses.dataclass(frozen=True)
class MainArgs(PaperArgs):
    """DP vs DP+HiPolicy (and DP3 vs DP3+HiPolicy with --obs-types state pointcloud), precise / non-precise."""

    obs_types: tuple[ObsName, ...] | None = None  # default: state; on the gpu budget state and pointcloud

    def resolved_obs_types(self) -> tuple[str, ...]:
        if self.obs_types is not None:
            return tuple(self.obs_types)
        return ("state", "pointcloud") if self.budget == "gpu" else ("state",)


@dataclasses.dataclass(frozen=True)
class AblationArgs(PaperArgs):
    """Observation condition hier / low / high, w/o fusion, w/o hierarchy (one stride)."""


@dataclasses.dataclass(frozen=True)
class EntropyArgs(PaperArgs):
    """Success and execution steps of DP, DP+HiPolicy w/o entropy-guided execution, DP+HiPolicy."""


@dataclasses.dataclass(frozen=True)
class ThresholdsArgs(PaperArgs):
    """Entropy thresholds at several percentile pairs of held-out demo entropies."""

    tasks: tuple[TaskName, ...] = ("press_button",)
    pairs: tuple[tuple[float, float], ...] = ((10.0, 70.0), (40.0, 90.0), (3.0, 40.0))


@dataclasses.dataclass(frozen=True)
class HparamsArgs(PaperArgs):
    """Observation horizon L_h, chunk length L_c and number of frequencies M (strides 1..M)."""

    tasks: tuple[TaskName, ...] = ("press_button",)
    rows: tuple[tuple[int, int, int], ...] = ((3, 8, 3), (1, 8, 3), (5, 8, 3), (3, 4, 3), (3, 8, 1))


SUBCOMMANDS: dict[str, type] = {"main": MainArgs, "ablation": AblationArgs, "entropy": EntropyArgs,
                                "thresholds": ThresholdsArgs, "hparams": HparamsArgs}


def table_name(args: PaperArgs) -> str:
    return next(k for k, v in SUBCOMMANDS.items() if type(args) is v)


def parse_args(argv: list[str] | None = None) -> PaperArgs:
    """Parse ``TABLE [--flags]`` into the table's args dataclass."""
    return tyro.extras.subcommand_cli_from_dict(SUBCOMMANDS, args=argv, description=__doc__)


def command_line(args: PaperArgs) -> str:
    """The exact command reproducing ``args`` (every field spelled out; parses back to ``args``)."""
    parts = ["python", "-m", "experiments.paper", table_name(args)]
    for f in dataclasses.fields(args):
        value, flag = getattr(args, f.name), "--" + f.name.replace("_", "-")
        if isinstance(value, bool):
            parts.append(flag if value else "--no-" + f.name.replace("_", "-"))
        elif value is None:
            parts += [flag, "None"]
        elif isinstance(value, tuple):
            flat = [x for v in value for x in (v if isinstance(v, tuple) else (v,))]
            parts += [flag, *(f"{x:g}" if isinstance(x, float) else str(x) for x in flat)]
        else:
            parts += [flag, str(value)]
    return shlex.join(parts)


# ----------------------------------------------------------------------------------------------------- runs


class Column(NamedTuple):
    """One evaluated setting: a trained variant (obs type + config changes) and how it is executed.

    ``percentiles``: thresholds at these percentiles of the run's held-out demo entropies instead of its
    ``calibration.json``; ``guided=False``: always the highest frequency."""

    label: str
    obs_type: str = "state"
    changes: tuple[tuple[str, Any], ...] = ()
    guided: bool = True
    percentiles: tuple[float, ...] | None = None


def eval_episodes(args: PaperArgs) -> int:
    """Evaluation episodes per seed: ``--episodes`` or the budget's."""
    return BUDGETS[args.budget].eval.episodes if args.episodes is None else args.episodes


def train_args(args: PaperArgs, task: str, obs_type: str, changes, seed: int) -> RunConfig:
    """The ``RunConfig`` of one run (``budgets.run_config`` with this table's directories and episodes)."""
    return run_config(args.budget, task, obs_type, changes, seed, runs=args.runs, data=args.data,
                      eval_episodes=eval_episodes(args), progress=args.progress)


def _thresholds(run: Run, col: Column, inference: InferenceConfig, evaluator: Evaluator, seed: int,
                cache: dict) -> tuple[float, ...] | None:
    """The column's thresholds for a run: its ``calibration.json`` or, with ``col.percentiles``, those percentiles of
    its held-out demo entropies (measured once per run); None without entropy guidance or for one frequency."""
    m = run.policy.cfg.chunk.num_freqs
    if m == 1 or not col.guided:
        return None
    if col.percentiles is None:
        return calibration.resolve_thresholds(inference, m, calibration.read_calibration(run.run_dir))[0]
    if run.run_dir not in cache:
        cache[run.run_dir] = run_entropies(run, inference, "demos", seed=seed, evaluator=evaluator)
    return calibration.calibrate_thresholds(cache[run.run_dir], m, col.percentiles)


def evaluate_cached(run: Run, evaluator: Evaluator, episodes: int, seed: int, thresholds, guided: bool) -> dict:
    """``eval_summary`` of one evaluation of a run, cached in ``<run>/paper_evals.json`` by its settings."""
    inf = evaluator.inference
    key = json.dumps({"step": run.policy.step, "episodes": episodes, "num_samples": inf.num_samples,
                      "sampler": inf.sampler, "num_steps": inf.num_steps, "seed": seed, "guided": guided,
                      "thresholds": None if thresholds is None else [float(t) for t in thresholds]})
    path = os.path.join(run.run_dir, "paper_evals.json")
    cache = read_json(path) if os.path.exists(path) else {}
    if key not in cache:
        p = run.policy
        result = evaluator.evaluate(p.params, p.normalizer, episodes, eval_key(seed), thresholds,
                                    entropy_guided=guided)
        cache[key] = {**eval_summary(result), "thresholds": None if thresholds is None else list(thresholds)}
        write_json(path, cache)
    return cache[key]


def collect(args: PaperArgs, columns: list[Column]) -> list[dict]:
    """Train what is missing and evaluate every (task, seed, column) → one record per evaluation. One
    ``Evaluator`` per (task, variant) serves all its seeds (one compile)."""
    inference = BUDGETS[args.budget].inference
    entropy_cache: dict = {}
    evaluators: dict = {}
    records = []
    t0 = time.perf_counter()
    for task in args.tasks:
        for seed in args.seeds:
            for col in columns:
                run = ensure_trained(train_args(args, task, col.obs_type, col.changes, seed))
                ident = (task, run.policy.cfg, run.action_dim)
                if ident not in evaluators:
                    evaluators[ident] = make_evaluator(run, inference)
                ev = evaluators[ident]
                th = _thresholds(run, col, inference, ev, seed, entropy_cache)
                summary = evaluate_cached(run, ev, eval_episodes(args), seed, th, col.guided)
                records.append({"task": task, "seed": seed, "column": col.label,
                                "run": os.path.relpath(run.run_dir), **summary})
                print(f"[paper {time.perf_counter() - t0:7.0f}s] {task} seed {seed} {col.label}: success "
                      f"{summary['success_rate']:.2f}, steps (successful) {summary['mean_steps_success']:.1f}",
                      flush=True)
    return records


# ------------------------------------------------------------------------------------------- formatting


def mean_std(values, scale: float = 1.0, digits: int = 1) -> str:
    """'m ± s' (sample std over seeds) of the finite values, 'm' for one value, '–' for none."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], np.float64) * scale
    if v.size == 0:
        return "–"
    if v.size == 1:
        return f"{v[0]:.{digits}f}"
    return f"{v.mean():.{digits}f} ± {v.std(ddof=1):.{digits}f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A GitHub markdown table: the first column left-aligned, the others right-aligned."""
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join([":---"] + ["---:"] * (len(header) - 1)) + " |"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _nanmean(x) -> float:
    x = np.asarray(x, np.float64)
    return float(np.mean(x[np.isfinite(x)])) if np.isfinite(x).any() else np.nan


def values(records: list[dict], metric: str, seeds, **match) -> list[float]:
    """Per-seed ``metric`` of the records matching ``match`` (NaN where a seed is missing)."""
    out = []
    for s in seeds:
        hit = [r for r in records if r["seed"] == s and all(r.get(k) == v for k, v in match.items())]
        v = hit[0].get(metric) if hit else None
        out.append(np.nan if v is None else float(v))
    return out


def task_average(records: list[dict], metric: str, seeds, tasks, **match) -> list[float]:
    """Per seed, the mean of ``metric`` over ``tasks`` (NaN-ignoring)."""
    per_task = np.array([values(records, metric, seeds, task=t, **match) for t in tasks], np.float64)
    return [_nanmean(per_task[:, j]) for j in range(len(seeds))] if len(tasks) else [np.nan] * len(seeds)


def results_header(title: str, args: PaperArgs, notes: list[str]) -> str:
    b = BUDGETS[args.budget]
    lines = [f"# {title}", "", f"Command: `{command_line(args)}`", "",
             f"Seeds: {', '.join(str(s) for s in args.seeds)} (mean ± sample std over seeds). Budget `{args.budget}`: "
             f"{b.note}; evaluation episodes: {eval_episodes(args)} per seed, the same initial states for "
             f"every column."]
    lines += [""] + [f"- {n}" for n in notes] if notes else []
    return "\n".join(lines) + "\n"


def write_results(args: PaperArgs, title: str, notes: list[str], table: str, records: list[dict],
                  figure=None) -> str:
    """Write ``<results>/<table>.md`` (+ ``.json`` with every record, + ``.png`` from ``figure(path)``)."""
    name = table_name(args)
    os.makedirs(args.results, exist_ok=True)
    md = os.path.join(args.results, f"{name}.md")
    with open(md, "w") as f:
        f.write(results_header(title, args, notes) + "\n" + table + "\n")
    write_json(os.path.join(args.results, f"{name}.json"),
               {"command": command_line(args), "args": dataclasses.asdict(args), "records": records})
    if figure is not None:
        figure(os.path.join(args.results, f"{name}.png"))
    return md


def success_by_task_figure(args: PaperArgs, records: list[dict], labels: list[str], title: str):
    """``figure(path)``: success-rate bars per task, one bar per column label."""
    def figure(path):
        series = {c: [values(records, "success_rate", args.seeds, task=t, column=c) for t in args.tasks]
                  for c in labels}
        return bar_figure(path, list(args.tasks), [("success rate", series)], title)

    return figure


def bar_figure(path: str, groups: list[str], panels: list[tuple[str, dict[str, list[list[float]]]]],
               title: str) -> str:
    """Grouped bar chart(s): per panel (ylabel, {series: per-group per-seed values}), mean with std error bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(max(5.0, 1.3 * len(groups) + 2.5) * len(panels), 3.6),
                             squeeze=False)
    for ax, (ylabel, series) in zip(axes[0], panels):
        width = 0.8 / max(len(series), 1)
        x = np.arange(len(groups))
        for i, (name, per_group) in enumerate(series.items()):
            means, stds = [], []
            for vals in per_group:
                v = np.asarray([a for a in vals if np.isfinite(a)], np.float64)
                means.append(v.mean() if v.size else np.nan)
                stds.append(v.std(ddof=1) if v.size > 1 else 0.0)
            ax.bar(x + (i - (len(series) - 1) / 2) * width, means, width, yerr=stds, capsize=2, label=name)
        ax.set_xticks(x, groups, rotation=20, ha="right", fontsize=8)
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _rel(base: list[float], new: list[float]) -> str:
    """' (+x%)': relative change of the mean of ``new`` over the mean of ``base`` ('' when undefined)."""
    b, n = _nanmean(base), _nanmean(new)
    return f" ({(n - b) / b * 100:+.0f}%)" if np.isfinite(b) and np.isfinite(n) and b > 0 else ""


def grouped_rows(args: PaperArgs, records, columns: list[str], metric: str = "success_rate", scale: float = 100.0,
                 extra=None, rel_to: dict[str, str] | None = None) -> list[list[str]]:
    """Rows per task, precise tasks first then non-precise, each group followed by its average, then the total.
    ``extra(task) -> list[str]`` adds leading cells; ``rel_to`` {column: baseline column} adds relative gains to
    average rows."""
    rows = []
    precise = [t for t in args.tasks if TASK_PRECISE[t]]
    other = [t for t in args.tasks if not TASK_PRECISE[t]]
    n_extra = len(extra(args.tasks[0])) if extra else 0

    def avg_row(label, tasks):
        cells = []
        for c in columns:
            v = task_average(records, metric, args.seeds, tasks, column=c)
            gain = _rel(task_average(records, metric, args.seeds, tasks, column=rel_to[c]), v) \
                if rel_to and c in rel_to else ""
            cells.append(mean_std(v, scale) + gain)
        return [f"**{label}**"] + [""] * n_extra + cells

    for name, tasks in (("precise", precise), ("non-precise", other)):
        for t in tasks:
            rows.append([t] + (extra(t) if extra else [])
                        + [mean_std(values(records, metric, args.seeds, task=t, column=c), scale) for c in columns])
        if tasks and precise and other:
            rows.append(avg_row(f"Average ({name})", tasks))
    rows.append(avg_row("Total average" if precise and other else "Average", list(args.tasks)))
    return rows


def demo_steps(args: PaperArgs, task: str, obs_types: tuple[str, ...] = ("state",)) -> str:
    """Mean demo length (control steps) of the task's first existing demo buffer, '–' before one exists."""
    from hipolicy_jax.data.replay_buffer import ReplayBuffer

    for obs in obs_types:
        path = train_args(args, task, obs, (), args.seeds[0]).data_path()
        if os.path.exists(path):
            return f"{ReplayBuffer.load(path).episode_lengths().mean():.0f}"
    return "–"


# ------------------------------------------------------------------------------------------------ tables


def main_table(args: MainArgs) -> str:
    columns = []
    obs_types = args.resolved_obs_types()
    for obs in obs_types:
        base = BASELINE_NAME[obs]
        columns += [Column(base, obs, DP), Column(f"{base}+HiPolicy", obs)]
    records = collect(args, columns)
    labels = [c.label for c in columns]
    rel = {f"{BASELINE_NAME[o]}+HiPolicy": BASELINE_NAME[o] for o in obs_types}
    rows = grouped_rows(args, records, labels, rel_to=rel,
                        extra=lambda t: ["yes" if TASK_PRECISE[t] else "no", demo_steps(args, t, obs_types)])
    table = markdown_table(["Task", "Precise", "Demo steps", *labels], rows)
    notes = ["Success rate (%) with entropy-guided execution, thresholds calibrated on held-out demos "
             "(10th / 70th percentiles); relative gain over the baseline in the average rows.",
             "DP = one stride (single-frequency Diffusion Policy); DP3 = point-cloud encoder, sample prediction."]
    if "pointcloud" in obs_types:
        pc = train_args(args, args.tasks[0], "pointcloud", (), args.seeds[0]).policy.encoder
        notes.append(f"DP3 columns: {pc.num_points} points (xyz{'+rgb' if pc.point_dims == 6 else ''}) from one "
                     f"ray-cast camera plus proprioception (the first {pc.state_dims} state features: TCP xyz, "
                     "gripper); the DP columns read the full state (proprioception and object poses).")

    figure = success_by_task_figure(args, records, labels, "main results")
    return write_results(args, "Main results: success rate (%)", notes, table, records, figure)


ABLATION = [("Hier.", ()), ("Low", (("model.condition", "low"),)), ("High", (("model.condition", "high"),)),
            ("w/o Fusion", (("model.fusion", False),)), ("w/o Hier.", DP)]


def ablation_table(args: AblationArgs) -> str:
    columns = [Column(label, "state", changes) for label, changes in ABLATION]
    records = collect(args, columns)
    labels = [c.label for c in columns]
    rows = grouped_rows(args, records, labels)
    table = markdown_table(["Task", *labels], rows)
    notes = ["Success rate (%) with entropy-guided execution. Condition: every frequency segment conditioned on its "
             "own frequency's observations (Hier.), or all on the lowest (Low) / highest (High); w/o Fusion: no "
             "CLS-token attention; w/o Hier.: one stride (DP)."]

    figure = success_by_task_figure(args, records, labels, "ablation")
    return write_results(args, "Ablation: success rate (%)", notes, table, records, figure)


def _stride_cell(records, seeds, **match) -> str:
    hits = [r for r in records if r["seed"] in seeds and all(r.get(k) == v for k, v in match.items())]
    keys = sorted({k for r in hits for k in r if k.startswith("stride") and k.endswith("_frac")},
                  key=lambda k: int(k[6:-5]))
    if not keys:
        return "–"
    return "/".join(f"{100 * np.mean([r.get(k, 0.0) for r in hits]):.0f}" for k in keys)


PANELS = (("success rate", "success_rate"), ("steps (successful)", "mean_steps_success"))


def entropy_table(args: EntropyArgs) -> str:
    columns = [Column("DP", "state", DP), Column("w/o EG", "state", (), guided=False), Column("HiPolicy")]
    records = collect(args, columns)
    header = ["Task", "DP SR", "DP Steps", "w/o EG SR", "w/o EG Steps", "HiPolicy SR", "HiPolicy Steps",
              "HiPolicy strides (%)"]
    rows = []
    groups = [[t] for t in args.tasks] + [list(args.tasks)]
    for i, tasks in enumerate(groups):
        label = tasks[0] if i < len(args.tasks) else "**Average**"
        cells = [label]
        for c in ("DP", "w/o EG", "HiPolicy"):
            sr = task_average(records, "success_rate", args.seeds, tasks, column=c)
            steps = task_average(records, "mean_steps_success", args.seeds, tasks, column=c)
            gain = ""
            if c == "HiPolicy" and label == "**Average**":
                b = _nanmean(task_average(records, "mean_steps_success", args.seeds, tasks, column="w/o EG"))
                n = _nanmean(steps)
                gain = f" ({(b - n) / b * 100:+.0f}% faster)" if np.isfinite(b) and np.isfinite(n) and b > 0 else ""
            cells += [mean_std(sr, 100.0), mean_std(steps) + gain]
        cells.append(_stride_cell(records, args.seeds, column="HiPolicy",
                                  **({"task": tasks[0]} if len(tasks) == 1 else {})))
        rows.append(cells)
        if len(args.tasks) == 1:
            break
    table = markdown_table(header, rows)
    notes = ["SR: success rate (%). Steps: mean control steps of the successful episodes (over the seeds with any).",
             "w/o EG: the HiPolicy model executing its highest frequency (stride 1) at every replan; HiPolicy: "
             "entropy-guided execution with the calibrated thresholds (same trained model, same episodes).",
             "Strides: share of replans executed at stride 1/2/3."]

    def figure(path):
        cols = ["DP", "w/o EG", "HiPolicy"]
        panels = [(ylabel, {c: [values(records, metric, args.seeds, task=t, column=c) for t in args.tasks]
                            for c in cols})
                  for ylabel, metric in PANELS]
        return bar_figure(path, list(args.tasks), panels, "entropy-guided execution")

    return write_results(args, "Entropy-guided execution: success rate (%) and execution steps", notes, table,
                         records, figure)


def thresholds_table(args: ThresholdsArgs) -> str:
    columns = [Column(f"p{a:g}/p{b:g}", percentiles=(a, b)) for a, b in args.pairs]
    columns.append(Column("always stride 1", guided=False))
    records = collect(args, columns)
    header = ["Task", "Percentiles", "Thresholds", "SR (%)", "Steps", "Strides 1/2/3 (%)"]
    rows = []
    for t in args.tasks:
        for c in columns:
            hits = [r for r in records if r["task"] == t and r["column"] == c.label]
            th = [r["thresholds"] for r in hits if r.get("thresholds")]
            th_cell = ("{" + ", ".join(f"{np.mean([x[k] for x in th]):.2f}" for k in range(1, len(th[0]) - 1)) + "}"
                       if th else "–")
            rows.append([t, c.label, th_cell,
                         mean_std(values(records, "success_rate", args.seeds, task=t, column=c.label), 100.0),
                         mean_std(values(records, "mean_steps_success", args.seeds, task=t, column=c.label)),
                         _stride_cell(records, args.seeds, task=t, column=c.label)])
    table = markdown_table(header, rows)
    notes = ["Inner thresholds at the given percentiles of the run's held-out demo entropies (mean over seeds); "
             "higher thresholds execute the highest frequency more often.",
             "Steps: mean control steps of the successful episodes (over the seeds with any)."]

    def figure(path):
        labels = [c.label for c in columns]
        panels = [(ylabel, {t: [values(records, metric, args.seeds, task=t, column=c) for c in labels]
                            for t in args.tasks})
                  for ylabel, metric in PANELS]
        return bar_figure(path, labels, panels, "threshold ablation")

    return write_results(args, "Entropy thresholds ablation", notes, table, records, figure)


def hparam_changes(lh: int, lc: int, m: int, base: PolicyConfig) -> tuple[tuple[str, Any], ...]:
    """Config changes of an (L_h, L_c, M) row relative to the budget's policy (strides 1..M)."""
    changes = []
    if lh != base.chunk.obs_horizon:
        changes.append(("chunk.obs_horizon", lh))
    if lc != base.chunk.chunk_len:
        changes.append(("chunk.chunk_len", lc))
    if tuple(range(1, m + 1)) != base.chunk.strides:
        changes.append(("chunk.strides", tuple(range(1, m + 1))))
    return tuple(sorted(changes))


def hparams_table(args: HparamsArgs) -> str:
    base = BUDGETS[args.budget].policy
    columns = [Column(f"L_h={lh}, L_c={lc}, M={m}", "state", hparam_changes(lh, lc, m, base))
               for lh, lc, m in args.rows]
    records = collect(args, columns)
    rows = []
    for (lh, lc, m), c in zip(args.rows, columns):
        per_task = [mean_std(values(records, "success_rate", args.seeds, task=t, column=c.label), 100.0)
                    for t in args.tasks]
        avg = mean_std(task_average(records, "success_rate", args.seeds, list(args.tasks), column=c.label), 100.0)
        default = " (default)" if not c.changes else ""
        rows.append([f"{lh}{default}", str(lc), str(m), *per_task] + ([avg] if len(args.tasks) > 1 else []))
    header = ["L_h", "L_c", "M", *args.tasks] + (["Average"] if len(args.tasks) > 1 else [])
    table = markdown_table(header, rows)
    notes = ["Success rate (%) with entropy-guided execution; M frequencies = strides 1..M (M=1 is DP)."]

    def figure(path):
        series = {t: [values(records, "success_rate", args.seeds, task=t, column=c.label) for c in columns]
                  for t in args.tasks}
        return bar_figure(path, [c.label for c in columns], [("success rate", series)], "hyper-parameter ablation")

    return write_results(args, "Hyper-parameter ablation: success rate (%)", notes, table, records, figure)


BUILDERS = {"main": main_table, "ablation": ablation_table, "entropy": entropy_table,
            "thresholds": thresholds_table, "hparams": hparams_table}


def main(args: PaperArgs) -> str:
    """Build one table; returns the path of its markdown file."""
    name = table_name(args)
    t0 = time.perf_counter()
    path = BUILDERS[name](args)
    with open(path) as f:
        print(f.read())
    print(f"[paper] {name}: {time.perf_counter() - t0:.0f}s -> {path}")
    return path


if __name__ == "__main__":
    main(parse_args(sys.argv[1:]))
