"""The paper's tables (results/PROTOCOL.md) as a library stage: one args dataclass a table (``SUBCOMMANDS``), one
builder a table (``BUILDERS``; ``build(args)`` → the path of its markdown), and the campaign that runs every table's
evaluations under one progress bar. ``experiments.paper`` parses the flags into these dataclasses and calls ``build``.

Each table trains and evaluates through ``campaign.Campaign`` (or reads its records with ``from_records``) and writes
``<results>/<table>[_rlow].{md,json,png}``; its cells come from ``report``.
"""

from __future__ import annotations

import dataclasses
import glob
import os
import shlex
import time
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from tqdm.auto import tqdm

from hipolicy_jax.config import PolicyConfig
from hipolicy_jax.envs import TASK_PRECISE
from hipolicy_jax.evaluation import stats
from hipolicy_jax.campaigns.budgets import BUDGETS, DP, REGIMES, regime_changes, run_config
from hipolicy_jax.campaigns.campaign import (README_BEGIN, README_END, Campaign, Column, CostModel, Deadline, Job,
                                            choose_low_regime, damaged_lines, parse_until, work_off, pilot_candidates, readme_section, schedule,
                                        shard, update_readme)
from hipolicy_jax.runs.lock import RunLockedError
from hipolicy_jax.campaigns.report import (COUNT_BOUNDS, EPISODE_COUNTS, RATE_BOUNDS, bar_figure, changes_text, ci,
                                           cost_note, relative_count_difference,
                                           finding_text, gap_trend, interval_text, leave_one_out, markdown_table,
                                           outcomes, p_text, paired, paired_bootstrap, paired_cell, relative_gain,
                                           spent_measured_text, stride_cell, task_mean, verdict_text)
from hipolicy_jax.runs.store import read_json, write_json
from hipolicy_jax.runs.train import RunConfig, cpu_cores

TaskName = Literal["press_button", "latch_door", "stack_cubes", "pick_place"]
ObsName = Literal["state", "image", "pointcloud"]
TABLES = ("main", "ablation", "execution", "thresholds", "hparams", "pilot", "budget", "campaign")
BASELINE_NAME = {"state": "DP", "image": "DP (image)", "pointcloud": "DP3"}


@dataclasses.dataclass(frozen=True)
class PaperArgs:
    budget: Literal["smoke", "cpu", "gpu"] = "cpu"
    tasks: tuple[TaskName, ...] = ("press_button", "stack_cubes", "latch_door", "pick_place")
    seeds: tuple[int, ...] = (0, 1, 2)
    baseline_seeds: tuple[int, ...] = ()  # more seeds for the single-frequency baseline columns (the protocol: 3 4,
    # as their runs train in under 5 minutes)
    regime: Literal["r100", "rlow"] = "r100"  # demo regime (results/PROTOCOL.md): 100 demos, or the pilot's Rlow
    runs: str = "runs/paper"  # run dirs: <runs>/<budget>/<task>/<obs>/<variant>/seed<k>
    results: str = "results"  # <results>/<table>.{md,png,json}
    records: str = "results/runs"  # per-run JSON records (committed): <records>/<budget>/<task>/<obs>/<variant>/...
    data: str = "data"  # demo buffers: <data>/<task>_<obs keys>_<episodes>.zarr
    episodes: int | None = None  # evaluation episodes per seed (default: the budget's)
    from_records: bool = False  # build the table from the records alone: never train nor evaluate
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
class ExecutionArgs(PaperArgs):
    """Execution strategies: DP (whole chunks), DP+TE (temporal ensembling), DP+AAC (adaptive action chunking),
    HiPolicy always at stride 1 (w/o EG) and entropy-guided (HiPolicy)."""


@dataclasses.dataclass(frozen=True)
class CampaignArgs(PaperArgs):
    """The whole protocol: every table's runs and evaluations under one progress bar, then every table."""

    baseline_seeds: tuple[int, ...] = (3, 4)
    episodes: int | None = 100
    regimes: tuple[Literal["r100", "rlow"], ...] = ("r100", "rlow")
    obs_types: tuple[ObsName, ...] = ("state", "pointcloud")  # main table in R100: DP and the DP3 columns
    readme: str = "README.md"  # its campaign section (between the markers) is rewritten from the tables; '' = leave it
    plan: bool = False  # write what is left (evaluations, runs to train, estimated CPU-hours) and stop
    # K N: only the K-th (0-based) of N shards of the runs, so that N processes split the campaign — one per core
    # (`taskset -c K`) or per machine sharing the records; every evaluation of a run is in its run's shard. A shard
    # ends by writing the plan of what is left; build the tables with --from-records once every shard has finished
    shard: tuple[int, int] = (0, 1)
    # HH:MM or YYYY-MM-DD HH:MM (local time): start only the jobs whose estimated time ends before it, skip the rest
    # (a scheduler's time limit, a session's end); '' = no limit
    until: str = ""
    # end by rebuilding every table and the README section from the records; --no-tables writes only the plan of
    # what is left, so that a campaign narrowed to force a few runs (--tasks / --seeds) leaves the full tables alone
    tables: bool = True
    # protocol v2's training-budget table: DP vs DP+HiPolicy (state, 100 demos) at these training step counts
    budget_steps: tuple[int, ...] = (2000, 8000, 24000)
    # only these tables' evaluations (and tables), e.g. `--only budget`: two processes can work on two tables
    # (the semantics table of amendment 4 runs only when named here)
    only: tuple[Literal["main", "ablation", "execution", "thresholds", "hparams", "budget", "semantics"], ...] = ()
    # where the runs are trained and evaluated (campaigns.cluster): inprocess = here, one after another; local /
    # slurm = one submitit job a run (its training and all its evaluations) as local processes / a SLURM job array,
    # waited for here, then the tables as in-process
    executor: Literal["inprocess", "local", "slurm"] = "inprocess"
    cluster_logs: str = ""  # the jobs' pickles and logs ('' = <runs>/cluster-logs)
    cluster_time_min: int = 240  # a job's time limit (SLURM's --time; a job cut off is requeued and resumes)
    cluster_retries: int = 2  # a job that ends without finishing its run is submitted again up to this many times
    cluster_parallel: int = 0  # at most this many jobs at once (0: SLURM's array limit; local: one a core)
    slurm_partition: str = ""  # '' = the cluster's default partition
    slurm_cpus_per_task: int = 2  # the cost model's machine kind: 2 cores
    slurm_mem_gb: float = 0.0  # 0 = the partition's default
    slurm_account: str = ""  # '' = the user's default account
    slurm_sbatch: tuple[str, ...] = ()  # more sbatch options as KEY=VALUE, e.g. qos=high gres=gpu:1 (the gpu budget)


@dataclasses.dataclass(frozen=True)
class PilotArgs(PaperArgs):
    """The protocol's DP-only pilot that chooses each task's Rlow regime (seed 0)."""

    seeds: tuple[int, ...] = (0,)


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


@dataclasses.dataclass(frozen=True)
class BudgetArgs(PaperArgs):
    """Training-budget sensitivity (results/PROTOCOL.md v2): DP vs DP+HiPolicy (state, 100 demos) trained for
    several step counts; the budget's own count reuses the main table's runs."""

    tasks: tuple[TaskName, ...] = ("press_button", "stack_cubes")
    steps: tuple[int, ...] = (2000, 8000, 24000)


@dataclasses.dataclass(frozen=True)
class SemanticsArgs(PaperArgs):
    """Which kind of speed (results/PROTOCOL.md amendment 4): DP vs DP+HiPolicy (state, 100 demos, ``steps``
    training steps) evaluated under ``rate`` and ``waypoint`` execution, with the MJX controller unlimited and
    limited to ``controller_speed`` m/s; the same networks for every setting."""

    tasks: tuple[TaskName, ...] = ("press_button", "stack_cubes")
    steps: int = 8000
    controller_speed: float = 0.25


SUBCOMMANDS: dict[str, type] = {"main": MainArgs, "ablation": AblationArgs, "execution": ExecutionArgs,
                                "thresholds": ThresholdsArgs, "hparams": HparamsArgs, "pilot": PilotArgs,
                                "budget": BudgetArgs, "semantics": SemanticsArgs, "campaign": CampaignArgs}


def table_name(args: PaperArgs) -> str:
    """The table's sub-command: its class's ``TABLE`` (tables of other modules, e.g. ``campaigns.metaworld``), else
    its entry in ``SUBCOMMANDS``."""
    return getattr(type(args), "TABLE", None) or next(k for k, v in SUBCOMMANDS.items() if type(args) is v)


def command_line(args: PaperArgs) -> str:
    """The exact command reproducing ``args`` (every field spelled out; parses back to ``args``): its class's
    ``COMMAND`` module (default ``experiments.paper``) and sub-command."""
    parts = ["python", "-m", getattr(type(args), "COMMAND", "experiments.paper"), table_name(args)]
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


def eval_episodes(args: PaperArgs) -> int:
    """Evaluation episodes per seed: ``--episodes`` or the budget's."""
    return BUDGETS[args.budget].eval.episodes if args.episodes is None else args.episodes


def train_args(args: PaperArgs, task: str, obs_type: str, changes, seed: int) -> RunConfig:
    """The ``RunConfig`` of one run (``budgets.run_config`` with this table's directories and episodes)."""
    return run_config(args.budget, task, obs_type, changes, seed, runs=args.runs, data=args.data,
                      eval_episodes=eval_episodes(args), progress=args.progress)


def column_seeds(args: PaperArgs, col: Column) -> tuple[int, ...]:
    """The seeds a column is evaluated on: ``seeds``, plus ``baseline_seeds`` for the single-frequency state
    baselines (the columns whose runs train in under 5 minutes here, results/PROTOCOL.md)."""
    extra = tuple(col.changes) == DP and col.obs_type == "state"
    return tuple(args.seeds) + (tuple(args.baseline_seeds) if extra else ())


def table_seeds(args: PaperArgs) -> tuple[int, ...]:
    """Every seed any column of the table has (cells use the seeds their column has)."""
    return tuple(dict.fromkeys((*args.seeds, *args.baseline_seeds)))


def campaign(args: PaperArgs) -> Campaign:
    return Campaign(args.budget, runs=args.runs, data=args.data, records=args.records, episodes=eval_episodes(args),
                    from_records=args.from_records, progress=args.progress)


def table_record(camp: Campaign, task: str, col: Column, seed: int, run_changes: dict, evaluation: dict) -> dict:
    """One row of a table's JSON: the evaluation's numbers, its run dir and the run's training time."""
    run = camp.run_config(task, col, seed, run_changes).out_dir()
    training = camp.record(task, col, seed, run_changes).get("training") or {}
    return {"task": task, "seed": seed, "column": col.label, "regime": run_changes, "run": os.path.relpath(run),
            "training_s": training.get("wall_time_s"), "training_cores": training.get("cpu_cores"),
            "training_cpu_s": training.get("cpu_time_s"), **{k: v for k, v in evaluation.items() if k != "settings"}}


def table_run_changes(args: PaperArgs, task: str) -> list[dict]:
    """The run-level changes a table trains ``task``'s runs under: its regime's, or for the training-budget table
    one set per step count (the budget's own count: none)."""
    if isinstance(args, BudgetArgs):
        default = BUDGETS[args.budget].train.num_steps
        return [{} if n == default else {"train.num_steps": n} for n in args.steps]
    if isinstance(args, SemanticsArgs):
        return [{} if args.steps == BUDGETS[args.budget].train.num_steps else {"train.num_steps": args.steps}]
    return [regime_changes(args.regime, task)]


def collect(args: PaperArgs, columns: list[Column]) -> list[dict]:
    """Every (task, seed, column) evaluation of the table, from its run's record or trained / evaluated and recorded
    (one progress bar over them, with an ETA) → one record per evaluation (per-episode outcomes included)."""
    camp = campaign(args)
    jobs = [(t, s, c, ch) for t in args.tasks for ch in table_run_changes(args, t) for c in columns
            for s in column_seeds(args, c)]
    records, missing = [], []
    bar = tqdm(jobs, desc=f"{table_name(args)} ({args.regime})", unit="eval", disable=not args.progress,
               dynamic_ncols=True)
    for task, seed, col, changes in bar:
        bar.set_postfix_str(f"{task} seed {seed} {col.label} {changes_text(changes)}")
        evaluation = camp.evaluate(task, col, seed, changes)
        if evaluation is None:
            missing.append(f"{task} seed {seed} {col.label} {changes_text(changes)}")
            continue
        records.append(table_record(camp, task, col, seed, changes, evaluation))
        steps = evaluation["mean_steps_success"]  # None (NaN in the record) when no episode succeeded
        tqdm.write(f"[paper] {task} seed {seed} {col.label}: success {evaluation['success_rate']:.2f}, steps "
                   f"(successful) {'–' if steps is None else f'{steps:.1f}'}")
    if missing:
        print(f"[paper] {len(missing)} evaluations have no record under {args.records} (shown as '–'): "
              + "; ".join(missing[:8]) + (" ..." if len(missing) > 8 else ""), flush=True)
    return records


def regime_text(args: PaperArgs) -> str:
    """What the regime changes per task, e.g. ' (press_button: 25 demos; pick_place: num steps 8000; these replace
    the budget's demos or steps)'; '' for R100, which changes nothing."""
    parts = []
    for task in args.tasks:
        try:
            changes = regime_changes(args.regime, task)
        except ValueError:
            continue
        if changes:
            parts.append(f"{task}: {changes_text(changes)}")
    return f" ({'; '.join(parts)}; these replace the budget's demos or steps)" if parts else ""


def protocol_path(args: PaperArgs) -> str:
    """The protocol a table runs under: its class's ``PROTOCOL``, else the MJX campaign's."""
    return getattr(type(args), "PROTOCOL", "results/PROTOCOL.md")


def results_header(title: str, args: PaperArgs, notes: list[str]) -> str:
    b = BUDGETS[args.budget]
    lines = [f"# {title}", "", f"Command: `{command_line(args)}`", "",
             f"Protocol: `{protocol_path(args)}`. Regime `{args.regime}`{regime_text(args)}; seeds {', '.join(str(s) for s in args.seeds)}"
             + (f" (single-frequency baselines also {', '.join(map(str, args.baseline_seeds))})"
                if args.baseline_seeds else "") + ". "
             f"Cells: mean over seeds (one value per trained network) with its 95 % t interval over seeds. Budget "
             f"`{args.budget}`: {b.note}; evaluation episodes: {eval_episodes(args)} per seed, the same initial "
             f"states for every column."]
    lines += [""] + [f"- {n}" for n in notes] if notes else []
    return "\n".join(lines) + "\n"


def results_name(args: PaperArgs) -> str:
    """The table's file name without extension: ``main``, ``main_rlow``, ..."""
    return table_name(args) + ("" if args.regime == "r100" else f"_{args.regime}")


def write_results(args: PaperArgs, title: str, notes: list[str], table: str, records: list[dict],
                  figure=None) -> str:
    """Write ``<results>/<table>[_rlow].md`` (+ ``.json`` with every record, + ``.png`` from ``figure(path)``)."""
    name = results_name(args)
    os.makedirs(args.results, exist_ok=True)
    md = os.path.join(args.results, f"{name}.md")
    with open(md, "w") as f:
        f.write(results_header(title, args, [*notes, cost_note(records)]) + "\n" + table + "\n")
    write_json(os.path.join(args.results, f"{name}.json"),
               {"command": command_line(args), "args": dataclasses.asdict(args), "records": records})
    if figure is not None:
        figure(os.path.join(args.results, f"{name}.png"))
    return md


def success_by_task_figure(args: PaperArgs, records: list[dict], labels: list[str], title: str):
    """``figure(path)``: success-rate bars per task, one bar per column label."""
    def figure(path):
        series = {c: [outcomes(records, "success_rate", table_seeds(args), task=t, column=c) for t in args.tasks]
                  for c in labels}
        return bar_figure(path, list(args.tasks), [("success rate (%)", series)], title, scale=100.0,
                          bounds=[RATE_BOUNDS])

    return figure


def grouped_rows(args: PaperArgs, records, columns: list[str], metric: str = "success_rate", scale: float = 100.0,
                 extra=None, rel_to: dict[str, str] | None = None,
                 paired: list[tuple[str, str]] = (), groups: list[tuple[str, list[str]]] | None = None
                 ) -> list[list[str]]:
    """Rows per task by group — ``groups`` [(name, tasks)], default precise tasks then non-precise —, each group
    followed by its average (when there are several), then the total. ``extra(task) -> list[str]`` adds leading
    cells; ``rel_to`` {column: baseline column} adds relative gains to average rows; ``paired`` [(new, base)] adds a
    paired-comparison cell per pair."""
    def cells(tasks):
        out = []
        for c in columns:
            gain = ""
            if rel_to and c in rel_to and len(tasks) > 1:
                gain = relative_gain(task_mean(records, metric, table_seeds(args), tasks, rel_to[c]),
                            task_mean(records, metric, table_seeds(args), tasks, c))
            out.append(ci(records, metric, table_seeds(args), tasks, scale, column=c) + gain)
        return out + [paired_cell(records, table_seeds(args), tasks, new, base) for new, base in paired]

    return rows_by_group(args, cells, extra, groups)


def rows_by_group(args: PaperArgs, cells, extra=None, groups: list[tuple[str, list[str]]] | None = None
                  ) -> list[list[str]]:
    """``grouped_rows``'s layout with any cells: per task ``[task, *extra(task), *cells([task])]`` by group, each
    group's average row ``cells(its tasks)`` when there are several groups, then the total ``cells(args.tasks)``."""
    rows = []
    if groups is None:
        groups = [("precise", [t for t in args.tasks if TASK_PRECISE[t]]),
                  ("non-precise", [t for t in args.tasks if not TASK_PRECISE[t]])]
    n_extra = len(extra(args.tasks[0])) if extra else 0
    several = sum(bool(tasks) for _, tasks in groups) > 1
    for name, tasks in groups:
        for t in tasks:
            rows.append([t] + (extra(t) if extra else []) + cells([t]))
        if tasks and several:
            rows.append([f"**Average ({name})**"] + [""] * n_extra + cells(tasks))
    rows.append([f"**{'Total average' if several else 'Average'}**"] + [""] * n_extra
                + cells(list(args.tasks)))
    return rows


def demo_steps(args: PaperArgs, task: str, obs_types: tuple[str, ...] = ("state",)) -> str:
    """Mean length (control steps) of the task's demos at the budget's demo count: from the first of the task's run
    records that holds its demos' ``episodes`` / ``frames`` (so the table rebuilds from git alone), else from the
    task's demo buffer on this machine; '–' when neither exists yet."""
    from hipolicy_jax.data.replay_buffer import ReplayBuffer

    demos = BUDGETS[args.budget].demos
    for path in sorted(glob.glob(os.path.join(args.records, args.budget, task.replace(":", "_"), "*", "*", "*.json"))):
        d = read_json(path).get("demos")
        if d and d.get("episodes") == demos:
            return f"{d['frames'] / d['episodes']:.0f}"
    for obs in obs_types:
        path = train_args(args, task, obs, (), args.seeds[0]).data_path()
        if os.path.exists(path):
            return f"{ReplayBuffer.load(path).episode_lengths().mean():.0f}"
    return "–"


# ------------------------------------------------------------------------------------------------ tables


def main_columns(args: MainArgs) -> list[Column]:
    columns = []
    for obs in args.resolved_obs_types():
        base = BASELINE_NAME[obs]
        columns += [Column(base, obs, DP), Column(f"{base}+HiPolicy", obs)]
    return columns


# the paired cells' note; a table whose own file does not report the episode-level McNemar p (the Meta-World tables:
# findings.md has no rows of theirs) says where it is, or that it has none, after PAIRED_NOTE_CELLS
PAIRED_NOTE_CELLS = ("Paired columns: per seed both columns have, the mean per-episode success difference on the "
                     "shared initial states; their mean with its 95 % t interval over seeds and the seed-level t "
                     "test's p (protocol v2); wins / loses when the interval excludes 0 (p < 0.05).")
PAIRED_NOTE = PAIRED_NOTE_CELLS + " The episode-level McNemar p is in findings.md."
ABLATION_MCNEMAR = ("The episode-level McNemar p of Hier. − w/o Hier. is in findings.md (DP+HiPolicy vs DP, Rlow: the "
                    "same networks); Hier. − Release fusion has none.")
BUDGET_MCNEMAR = ("The episode-level McNemar p of the 2,000-step rows is in findings.md (DP+HiPolicy vs DP, 100 demos: "
                  "the same networks); the longer trainings have none.")


def main_table(args: MainArgs) -> str:
    columns = main_columns(args)
    obs_types = args.resolved_obs_types()
    records = collect(args, columns)
    labels = [c.label for c in columns]
    rel = {f"{BASELINE_NAME[o]}+HiPolicy": BASELINE_NAME[o] for o in obs_types}
    pairs = [(f"{BASELINE_NAME[o]}+HiPolicy", BASELINE_NAME[o]) for o in obs_types]
    rows = grouped_rows(args, records, labels, rel_to=rel, paired=pairs,
                        extra=lambda t: ["yes" if TASK_PRECISE[t] else "no", demo_steps(args, t, obs_types)])
    table = markdown_table(["Task", "Precise", "Demo steps", *labels, *(f"{a} − {b} (points)" for a, b in pairs)],
                           rows)
    notes = ["Success rate (%) with entropy-guided execution, thresholds calibrated on held-out demos "
             "(10th / 70th percentiles); relative gain over the baseline in the average rows.",
             PAIRED_NOTE,
             "DP = one stride (single-frequency Diffusion Policy); DP3 = point-cloud encoder, sample prediction."]
    if "pointcloud" in obs_types:
        pc = train_args(args, args.tasks[0], "pointcloud", (), args.seeds[0]).policy.encoder
        notes.append(f"DP3 columns: {pc.num_points} points (xyz{'+rgb' if pc.point_dims == 6 else ''}) from one "
                     f"ray-cast camera plus proprioception (the first {pc.state_dims} state features: TCP xyz, "
                     "gripper); the DP columns read the full state (proprioception and object poses).")

    figure = success_by_task_figure(args, records, labels, "main results")
    return write_results(args, "Main results: success rate (%)", notes, table, records, figure)


ABLATION = [("Hier.", ()), ("Low", (("model.condition", "low"),)), ("High", (("model.condition", "high"),)),
            ("w/o Fusion", (("model.fusion", False),)), ("Release fusion", (("model.fusion_kind", "release"),)),
            ("w/o Hier.", DP)]


def ablation_table(args: AblationArgs) -> str:
    columns = [Column(label, "state", changes) for label, changes in ABLATION]
    records = collect(args, columns)
    labels = [c.label for c in columns]
    rows = grouped_rows(args, records, labels, paired=[("Hier.", "w/o Hier."), ("Hier.", "Release fusion")])
    table = markdown_table(["Task", *labels, "Hier. − w/o Hier. (points)", "Hier. − Release fusion (points)"], rows)
    notes = ["Success rate (%) with entropy-guided execution. Condition: every frequency segment conditioned on its "
             "own frequency's observations (Hier.), or all on the lowest (Low) / highest (High); w/o Fusion: no "
             "CLS-token attention; Release fusion: the HiPolicy release's fusion, whose batch_first=False attention "
             "makes it a learned constant, out_proj(v_proj(cls)) (model.fusion_kind='release'); w/o Hier.: one "
             "stride (DP).", PAIRED_NOTE_CELLS + " " + ABLATION_MCNEMAR]

    figure = success_by_task_figure(args, records, labels, "ablation")
    return write_results(args, "Ablation: success rate (%)", notes, table, records, figure)


PANELS = (("success rate (%)", "success_rate", 100.0), ("steps (successful)", "mean_steps_success", 1.0))
EXECUTION = [Column("DP", "state", DP), Column("DP+TE", "state", DP, execution="te"),
             Column("DP+AAC", "state", DP, execution="aac"), Column("w/o EG", "state", (), guided=False),
             Column("HiPolicy")]


def execution_table(args: ExecutionArgs) -> str:
    records = collect(args, EXECUTION)
    labels = [c.label for c in EXECUTION]
    header = ["Task", *(f"{c} {m}" for c in labels for m in ("SR", "Steps", "Decisions")), "HiPolicy strides (%)",
              "HiPolicy − DP+TE (points)", "HiPolicy − DP+AAC (points)", "HiPolicy − DP (points)"]
    rows = []
    groups = [[t] for t in args.tasks] + ([list(args.tasks)] if len(args.tasks) > 1 else [])
    for tasks in groups:
        label = tasks[0] if len(tasks) == 1 else "**Average**"
        cells = [label]
        for c in labels:
            cells += [ci(records, "success_rate", table_seeds(args), tasks, 100.0, column=c),
                      ci(records, "mean_steps_success", table_seeds(args), tasks, column=c),
                      ci(records, "mean_decisions", table_seeds(args), tasks, column=c)]
        every_task = all(any(r["task"] == t and r["column"] == "HiPolicy" for r in records) for t in tasks)
        cells.append(stride_cell(records, table_seeds(args), column="HiPolicy",
                                  **({"task": tasks[0]} if len(tasks) == 1 else {})) if every_task else "–")
        cells += [paired_cell(records, table_seeds(args), tasks, "HiPolicy", "DP+TE"),
                  paired_cell(records, table_seeds(args), tasks, "HiPolicy", "DP+AAC"),
                  paired_cell(records, table_seeds(args), tasks, "HiPolicy", "DP")]
        rows.append(cells)
    table = markdown_table(header, rows)
    notes = ["SR: success rate (%). Steps: mean control steps of the successful episodes. Decisions: policy calls "
             "per episode (each one N-sample sampler call).",
             "DP: one stride, whole chunks (L_c actions per decision); DP+TE: the same DP run with ACT's temporal "
             "ensembling (a decision at every step, weights exp(-0.01 i)); DP+AAC: the same DP run with adaptive "
             "action chunking (k of L_c actions, k from the entropy curve of the N samples); w/o EG: the HiPolicy "
             "run always at stride 1; HiPolicy: entropy-guided execution with the calibrated thresholds.",
             "Strides: share of HiPolicy's decisions executed at stride 1/2/3.", PAIRED_NOTE]

    def figure(path):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6.5, 4.2))
        for i, t in enumerate(args.tasks):
            for j, c in enumerate(labels):
                seeds = table_seeds(args)
                sr = stats.seed_mean(outcomes(records, "success_rate", seeds, task=t, column=c)).mean
                steps = stats.seed_mean(outcomes(records, "mean_steps_success", seeds, task=t, column=c)).mean
                ax.scatter(steps, 100 * sr, color=f"C{j}", marker="os^Dv"[i % 5], s=40,
                           label=c if i == 0 else None)
        ax.set_xlabel("steps to success (control steps, lower is faster)")
        ax.set_ylabel("success rate (%)")
        ax.set_title("speed / success of the execution strategies (marker: task)", fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return path

    return write_results(args, "Execution strategies: success rate (%), steps to success and decisions", notes, table,
                         records, figure)


BUDGET_COLUMNS = (Column("DP", "state", DP), Column("DP+HiPolicy"))


def budget_records(records: list[dict], steps: int, default: int) -> list[dict]:
    """The records of runs trained for ``steps`` (the budget's own count: runs without a step change)."""
    want = {} if steps == default else {"train.num_steps": steps}
    return [r for r in records if (r.get("regime") or {}) == want]


def budget_gaps(records: list[dict], seeds, task: str, steps, default: int) -> tuple[str, str, str]:
    """(the gap DP+HiPolicy − DP at the fewest steps, at the most, and the protocol's answer: 'shrinks' / 'holds' /
    'grows', ``report.gap_trend``) for one task of the training-budget table; '–' where a step count has no pair."""
    lo, hi = min(steps), max(steps)
    first, last = (paired(budget_records(records, n, default), seeds, [task], "DP+HiPolicy", "DP") for n in (lo, hi))
    text = [("–" if c is None else interval_text(c.diff, 100.0, signed=True)) for c in (first, last)]
    return text[0], text[1], gap_trend(first, last)


def budget_answer(args: BudgetArgs, records: list[dict]) -> str:
    """The budget table's answer per task, by the rule the protocol fixed before the runs."""
    default, seeds = BUDGETS[args.budget].train.num_steps, table_seeds(args)
    lo, hi = min(args.steps), max(args.steps)
    parts = []
    for task in args.tasks:
        a, b, trend = budget_gaps(records, seeds, task, args.steps, default)
        parts.append(f"{task}: {a} at {lo:,} steps, {b} at {hi:,}: **{trend}**")
    return (f"**The answer** (`results/PROTOCOL.md`'s rule, fixed before the runs: the gap shrinks or grows when "
            f"its t interval at {hi:,} steps excludes the {lo:,}-step point estimate, else it holds; '–' while "
            f"{hi:,} steps have fewer than 2 paired seeds): " + "; ".join(parts) + ".")


def budget_table(args: BudgetArgs) -> str:
    """Success of DP and DP+HiPolicy vs training steps, the paired difference per step count, and a plot."""
    records = collect(args, list(BUDGET_COLUMNS))
    default = BUDGETS[args.budget].train.num_steps
    seeds = table_seeds(args)
    rows = []
    for task in args.tasks:
        for n in args.steps:
            rs = budget_records(records, n, default)
            rows.append([task, f"{n:,}" + (" (budget)" if n == default else ""),
                         *(ci(rs, "success_rate", seeds, [task], 100.0, column=c.label) for c in BUDGET_COLUMNS),
                         *(ci(rs, "mean_steps_success", seeds, [task], column=c.label) for c in BUDGET_COLUMNS),
                         paired_cell(rs, seeds, [task], "DP+HiPolicy", "DP")])
    header = ["Task", "Training steps", "DP SR (%)", "DP+HiPolicy SR (%)", "DP steps", "DP+HiPolicy steps",
              "DP+HiPolicy − DP (points)"]
    table = markdown_table(header, rows) + "\n\n" + budget_answer(args, records)
    notes = ["Does the gap between DP+HiPolicy and DP shrink, hold or grow with training? The same CPU network and "
             "batch as the budget, trained for more steps (the learning-rate schedule stretched to the step "
             "count); 100 demos; entropy-guided execution with per-run calibrated thresholds.",
             "Steps: mean control steps of the successful episodes.", PAIRED_NOTE_CELLS + " " + BUDGET_MCNEMAR]

    def figure(path):
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        panels = (("success_rate", 100.0, RATE_BOUNDS, "success rate (%)"),
                  ("mean_steps_success", 1.0, COUNT_BOUNDS, "steps to success (successful episodes)"))
        fig, axes = plt.subplots(len(panels), len(args.tasks), figsize=(4.2 * len(args.tasks), 6.6), squeeze=False)
        for row, (metric, scale, bounds, ylabel) in zip(axes, panels):
            for ax, task in zip(row, args.tasks):
                for j, c in enumerate(BUDGET_COLUMNS):
                    pts = [(n, stats.seed_mean(outcomes(budget_records(records, n, default), metric, seeds,
                                                        task=task, column=c.label), bounds=bounds))
                           for n in args.steps]
                    pts = [(n, iv) for n, iv in pts if np.isfinite(iv.mean)]
                    if not pts:
                        continue
                    x = np.array([n for n, _ in pts], float) * (1.0 + 0.03 * (j - 0.5))
                    m = np.array([scale * iv.mean for _, iv in pts])
                    err = np.array([[scale * (iv.mean - iv.low), scale * (iv.high - iv.mean)] for _, iv in pts]).T
                    ax.errorbar(x, m, yerr=err, marker="o", capsize=3, label=c.label, color=f"C{j}")
                ax.set_xscale("log")
                ax.minorticks_off()  # the log axis' minor labels (3×10³ ...) would overprint the step counts
                ax.set_xticks(list(args.steps), [f"{n:,}" for n in args.steps])
                ax.set_xlim(min(args.steps) / 1.3, max(args.steps) * 1.3)
                ax.set_xlabel(f"training steps (batch {BUDGETS[args.budget].train.batch_size})")
                ax.set_ylabel(ylabel)
                if metric == "success_rate":
                    ax.set_ylim(-3, 103)
                else:
                    ax.set_ylim(bottom=0)
                ax.set_title(task, fontsize=10)
                ax.grid(alpha=0.3)
                if ax.get_legend_handles_labels()[0]:
                    ax.legend(fontsize=8)
        fig.suptitle("success and steps to success vs training budget (95 % t intervals over seeds)", fontsize=10)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
        return path

    return write_results(args, "Training-budget sensitivity: DP vs DP+HiPolicy", notes, table, records, figure)


def semantics_settings(args: SemanticsArgs) -> tuple[tuple[str, float | None], ...]:
    """The amendment's four execution settings: (semantics, controller speed limit or None)."""
    return (("rate", None), ("waypoint", None), ("rate", args.controller_speed), ("waypoint", args.controller_speed))


def setting_text(semantics: str, speed: float | None) -> str:
    return semantics + ("" if speed is None else f", {speed:g} m/s")


def semantics_columns(args: SemanticsArgs) -> list[Column]:
    """DP and DP+HiPolicy under each setting: columns with the same runs (changes), evaluated four ways."""
    return [Column(f"{base} ({setting_text(sem, speed)})", "state", changes, semantics=sem, controller_speed=speed)
            for sem, speed in semantics_settings(args) for base, changes in (("DP", DP), ("DP+HiPolicy", ()))]


SEMANTICS_READING = ("Savings: on the initial states both networks of a seed solved, DP+HiPolicy's mean decisions, "
                     "actions executed and control steps per episode relative to DP's (−40 % = 40 % fewer), the "
                     "mean over seeds with its 95 % t interval; the average row: Welch over the tasks. By the "
                     "amendment's rule DP+HiPolicy saves a count when its interval lies below 0.")


def semantics_table(args: SemanticsArgs) -> str:
    """results/semantics.md: success, paired difference and the three counts' savings per task and setting."""
    columns = semantics_columns(args)
    records = collect(args, columns)
    seeds = table_seeds(args)
    header = ["Task", "Execution", "DP SR (%)", "DP+HiPolicy SR (%)", "DP+HiPolicy − DP (points)",
              *(f"{what} saved (%)" for what in ("Decisions", "Actions", "Control steps"))]
    rows = []
    for tasks, name in [([t], t) for t in args.tasks] + ([(list(args.tasks), "**Average**")]
                                                         if len(args.tasks) > 1 else []):
        for sem, speed in semantics_settings(args):
            dp, hp = (f"{base} ({setting_text(sem, speed)})" for base in ("DP", "DP+HiPolicy"))
            rows.append([name, setting_text(sem, speed),
                         *(ci(records, "success_rate", seeds, tasks, 100.0, column=c) for c in (dp, hp)),
                         paired_cell(records, seeds, tasks, hp, dp),
                         *(interval_text(relative_count_difference(records, seeds, tasks, hp, dp, count), 100.0,
                                         signed=True) for count in EPISODE_COUNTS)])
    notes = [f"The same networks ({args.steps:,} training steps, 100 demos, entropy-guided execution at each run's "
             f"calibrated thresholds) under four execution settings: `rate` (one control step per action), "
             f"`waypoint` (each action a target held until the hand is within 5 mm, at most 3 control steps per "
             f"unit of stride, one observation per action), each with the controller unlimited and with its "
             f"set-point limited to {args.controller_speed:g} m/s.", SEMANTICS_READING, PAIRED_NOTE_CELLS]
    return write_results(args, "Which kind of speed: DP vs DP+HiPolicy under rate and waypoint execution", notes,
                         markdown_table(header, rows), records)


def thresholds_columns(args: ThresholdsArgs) -> list[Column]:
    return [Column(f"p{a:g}/p{b:g}", percentiles=(a, b)) for a, b in args.pairs] + \
        [Column("always stride 1", guided=False)]


def thresholds_table(args: ThresholdsArgs) -> str:
    columns = thresholds_columns(args)
    records = collect(args, columns)
    header = ["Task", "Percentiles", "Thresholds", "SR (%)", "Steps", "Strides 1/2/3 (%)"]
    rows = []
    for t in args.tasks:
        for c in columns:
            hits = [r for r in records if r["task"] == t and r["column"] == c.label]
            th = [r["thresholds"] for r in hits if r.get("thresholds")]
            th_cell = ("{" + ", ".join(f"{np.mean([x[k] for x in th]):.2f}" for k in range(1, len(th[0]) - 1)) + "}"
                       if th else "–")
            seeds = table_seeds(args)
            rows.append([t, c.label, th_cell, ci(records, "success_rate", seeds, [t], 100.0, column=c.label),
                         ci(records, "mean_steps_success", seeds, [t], column=c.label),
                         stride_cell(records, seeds, task=t, column=c.label)])
    table = markdown_table(header, rows)
    notes = ["Inner thresholds at the given percentiles of the run's held-out demo entropies (mean over seeds); "
             "higher thresholds execute the highest frequency more often.",
             "Steps: mean control steps of the successful episodes."]

    def figure(path):
        labels = [c.label for c in columns]
        panels = [(ylabel, {t: [outcomes(records, metric, table_seeds(args), task=t, column=c) for c in labels]
                            for t in args.tasks})
                  for ylabel, metric, _ in PANELS]
        return bar_figure(path, labels, panels, "threshold ablation",
                          bounds=[RATE_BOUNDS if metric == "success_rate" else None for _, metric, _ in PANELS])

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


def hparams_columns(args: HparamsArgs) -> list[Column]:
    base = BUDGETS[args.budget].policy
    return [Column(f"L_h={lh}, L_c={lc}, M={m}", "state", hparam_changes(lh, lc, m, base)) for lh, lc, m in args.rows]


def hparams_table(args: HparamsArgs) -> str:
    columns = hparams_columns(args)
    records = collect(args, columns)
    rows = []
    for (lh, lc, m), c in zip(args.rows, columns):
        per_task = [ci(records, "success_rate", table_seeds(args), [t], 100.0, column=c.label) for t in args.tasks]
        avg = ci(records, "success_rate", table_seeds(args), list(args.tasks), 100.0, column=c.label)
        default = " (default)" if not c.changes else ""
        rows.append([f"{lh}{default}", str(lc), str(m), *per_task] + ([avg] if len(args.tasks) > 1 else []))
    header = ["L_h", "L_c", "M", *args.tasks] + (["Average"] if len(args.tasks) > 1 else [])
    table = markdown_table(header, rows)
    notes = ["Success rate (%) with entropy-guided execution; M frequencies = strides 1..M (M=1 is DP)."]

    def figure(path):
        series = {t: [outcomes(records, "success_rate", table_seeds(args), task=t, column=c.label) for c in columns]
                  for t in args.tasks}
        return bar_figure(path, [c.label for c in columns], [("success rate (%)", series)],
                          "hyper-parameter ablation", scale=100.0, bounds=[RATE_BOUNDS])

    return write_results(args, "Hyper-parameter ablation: success rate (%)", notes, table, records, figure)


def pilot_table(args: PilotArgs) -> str:
    """The protocol's DP-only pilot: DP (seed ``args.seeds[0]``) at 100 demos, then the Rlow candidates until one
    lands in [15, 85] %; writes ``<results>/pilot.md`` / ``.json`` with the choice per task (to be recorded in
    results/PROTOCOL.md and ``campaigns.budgets.REGIMES['rlow']`` before any HiPolicy run of that regime)."""
    camp = campaign(args)
    dp = Column("DP", "state", DP)
    seed = args.seeds[0]
    rows, records, choices = [], [], {}
    for task in tqdm(args.tasks, desc="pilot", unit="task", disable=not args.progress):
        base = camp.evaluate(task, dp, seed)
        tried = []
        if base is not None:
            records.append(table_record(camp, task, dp, seed, {}, base))
            for changes in pilot_candidates(base["success_rate"]):
                ev = camp.evaluate(task, dp, seed, changes)
                if ev is None:
                    break
                tried.append((changes, ev["success_rate"]))
                records.append(table_record(camp, task, dp, seed, changes, ev))
                if 0.15 <= ev["success_rate"] <= 0.85:
                    break
        if tried:
            choice, in_range = choose_low_regime(tried)
            choices[task] = {"run_changes": choice, "in_range": in_range}
        desc = ", ".join(f"{changes_text(c)}: {100 * sr:.0f} %" for c, sr in tried) or "–"
        chosen = changes_text(choices[task]["run_changes"]) + ("" if choices[task]["in_range"] else
                                                               " (closest to 50 %, none in range)") \
            if task in choices else "–"
        rows.append([task, "–" if base is None else f"{100 * base['success_rate']:.0f}", desc, chosen])
    table = markdown_table(["Task", "DP @ 100 demos (%)", "Candidates tried (DP success)", "Rlow"], rows)
    regimes = {t: c["run_changes"] for t, c in choices.items()}
    notes = [f"DP only (one stride), seed {seed}, {eval_episodes(args)} evaluation episodes per candidate.",
             f"Record the choice in results/PROTOCOL.md and in hipolicy_jax/campaigns/budgets.py: "
             f"`REGIMES['rlow'] = {regimes!r}`."]
    write_json(os.path.join(args.results, "pilot_choice.json"), regimes)
    return write_results(args, "DP pilot: the low-data regime per task", notes, table, records)


COLUMNS = {"main": main_columns, "ablation": lambda args: [Column(label, "state", c) for label, c in ABLATION],
           "budget": lambda args: list(BUDGET_COLUMNS), "semantics": lambda args: semantics_columns(args),
           "execution": lambda args: list(EXECUTION), "thresholds": thresholds_columns, "hparams": hparams_columns}


def protocol_tables(args: "CampaignArgs") -> list[PaperArgs]:
    """The tables of results/PROTOCOL.md with the campaign's settings: (a) main in both regimes, (c) execution in
    both regimes, (b) ablation in Rlow on all tasks, (d) thresholds and (e) hyper-parameters in Rlow on two tasks
    (v1), and the training-budget table (v2); ``--only`` keeps the named tables."""
    common = {f.name: getattr(args, f.name) for f in dataclasses.fields(PaperArgs)}
    two = tuple(t for t in ("press_button", "latch_door") if t in args.tasks)
    tables = []
    for regime in args.regimes:
        r = {**common, "regime": regime}
        tables += [MainArgs(**r, obs_types=args.obs_types if regime == "r100" else ("state",)),
                   ExecutionArgs(**r)]
    if "rlow" in args.regimes:
        r = {**common, "regime": "rlow"}
        tables += [AblationArgs(**r), ThresholdsArgs(**{**r, "tasks": two}), HparamsArgs(**{**r, "tasks": two})]
    budget_tasks = tuple(t for t in BudgetArgs.tasks if t in args.tasks)
    if args.budget_steps and budget_tasks and "r100" in args.regimes:  # protocol v2's training-budget table
        tables.append(BudgetArgs(**{**common, "regime": "r100", "tasks": budget_tasks, "baseline_seeds": ()},
                                 steps=tuple(args.budget_steps)))
    semantics_tasks = tuple(t for t in SemanticsArgs.tasks if t in args.tasks)
    if "semantics" in args.only and semantics_tasks and "r100" in args.regimes:  # amendment 4, when named
        tables.append(SemanticsArgs(**{**common, "regime": "r100", "tasks": semantics_tasks, "baseline_seeds": ()}))
    if args.only:
        tables = [t for t in tables if table_name(t) in args.only]
    return tables


def campaign_jobs(args: "CampaignArgs", tables: list[PaperArgs]) -> tuple[list[Job], set[str]]:
    """Every (task, column, seed, regime changes) evaluation of the tables, in ``campaign.schedule``'s order, and
    the tasks skipped because the pilot has not chosen their Rlow yet."""
    jobs, skipped = [], set()
    for t in tables:
        for col in COLUMNS[table_name(t)](t):
            for task in t.tasks:
                try:
                    run_changes = table_run_changes(t, task)
                except ValueError:
                    skipped.add(f"{task} ({t.regime}: no pilot choice yet)")
                    continue
                jobs += [Job(task, col, seed, tuple(sorted(changes.items())))
                         for changes in run_changes for seed in column_seeds(t, col)]
    return schedule(jobs, tuple(args.seeds)), skipped


def write_plan(args: "CampaignArgs", costs: list[dict]) -> str:
    """``<results>/campaign_plan.md``: what the campaign (or its shard) has left, per regime and column: evaluations, runs to train
    and the estimated CPU-hours (the records' measured wall times × the cores their processes ran on); → its path."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for c in costs:
        job = c["job"]
        groups.setdefault((changes_text(dict(job.changes)), f"{job.col.label} ({job.col.obs_type})"), []).append(c)
    rows, total = [], 0.0
    for (regime, label), cs in groups.items():
        left = [c for c in cs if not c["done"]]
        if not left:
            continue
        hours = sum(c["seconds"] or 0.0 for c in left) / 3600
        unknown = sum(c["seconds"] is None for c in left)
        total += hours
        rows.append([regime, label, f"{len(cs) - len(left)}/{len(cs)}", str(sum(c["trains"] for c in left)),
                     f"{hours:.1f}" + (f" + {unknown} unmeasured" if unknown else "")])
    done = sum(c["done"] for c in costs)
    lines = ["# Campaign plan", "", f"Command: `{command_line(args)}`", "",
             (f"{done} of {len(costs)} evaluations recorded; left: about **{total:.1f} CPU-hours** "
              "(estimated from the records' measured times: training seconds per step of the same network and "
              "batch, else of its observation type; evaluation seconds of the same task, strategy and stride "
              "count, preferring evaluations made by the compacted rollout, then records that state their "
              "cores)."), "",
             markdown_table(["Regime", "Column", "Recorded", "Runs to train", "CPU-hours left"], rows),
             *damaged_lines(costs)]
    os.makedirs(args.results, exist_ok=True)
    path = os.path.join(args.results, "campaign_plan.md")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path


# The paired comparisons of HiPolicy with a baseline that the findings gather: (table, new column, baseline column)
# (the execution table's HiPolicy vs DP and the ablation's Hier. vs w/o Hier. are the main table's runs and
# evaluations again, so they are not counted twice). HiPolicy vs w/o EG is the one same-network comparison: one
# trained network, executed with and without entropy guidance.
FINDINGS = (("main", "DP+HiPolicy", "DP"), ("main", "DP3+HiPolicy", "DP3"), ("execution", "HiPolicy", "DP+TE"),
            ("execution", "HiPolicy", "DP+AAC"), ("execution", "HiPolicy", "w/o EG"))
VERDICTS = ("wins", "ties", "loses")


def _table_json(args: PaperArgs, t: PaperArgs) -> list[dict] | None:
    path = os.path.join(args.results, results_name(t) + ".json")
    return read_json(path)["records"] if os.path.exists(path) else None


def saved_groups(records: list[dict], seeds, task: str, new: str, base: str) -> dict[int, np.ndarray]:
    """Per seed, over the episodes both columns succeeded in: (base − new steps) / mean(base steps), whose mean is
    the fraction of ``base``'s steps to success that ``new`` saves on that network."""
    a = outcomes(records, "mean_steps_success", seeds, task=task, column=new)
    b = outcomes(records, "mean_steps_success", seeds, task=task, column=base)
    shared = set(a) & set(b)
    groups = {}
    for s, d in stats.paired_groups({k: a[k] for k in shared}, {k: b[k] for k in shared}).items():
        both = np.isfinite(d)
        if both.any():
            groups[s] = -d[both] / np.mean(b[s][both])
    return groups


def steps_tasks(records: list[dict], seeds, tasks, new: str, base: str) -> list[str]:
    """The ``tasks`` on which both columns have steps to success (a successful episode on some seed): those a
    speed table's average of steps covers, so that both steps columns average the same tasks. All ``tasks`` while
    one of them has no record of a column yet (its average is none yet: '–')."""
    def has_steps(task: str, column: str) -> bool:
        return any(np.isfinite(v).any()
                   for v in outcomes(records, "mean_steps_success", seeds, task=task, column=column).values())

    if not all(outcomes(records, "success_rate", seeds, task=t, column=c) for t in tasks for c in (base, new)):
        return list(tasks)
    return [t for t in tasks if has_steps(t, base) and has_steps(t, new)]


def steps_average_note(records: list[dict], seeds, tasks, new: str, base: str) -> str:
    """What ``speed_rows``' average row covers when a task leaves its steps: '' when both columns have steps to
    success on every task, else a sentence naming the tasks its steps and steps saved average."""
    both = steps_tasks(records, seeds, tasks, new, base)
    if len(tasks) < 2 or len(both) == len(tasks):
        return ""
    left = [t for t in tasks if t not in both]
    return (f"The average row's success columns average all {len(tasks)} tasks; its steps and steps saved average "
            f"the {len(both)} on which both {base} and {new} have steps to success ("
            + (", ".join(both) or "none") + "), leaving out " + ", ".join(left)
            + " (a column without a successful episode there).")


def speed_rows(args: PaperArgs, records: list[dict], seeds, tasks, new: str = "HiPolicy",
               base: str = "w/o EG") -> list[list[str]]:
    """The paper's speed claim, per task and on average: success of ``base`` and ``new``, the success cost, steps
    to success of each, the steps ``new`` saves (%) with its interval over seeds. By default the same network
    (HiPolicy vs w/o EG); with other columns, two networks per seed on the same initial states. The average row's
    steps and steps saved cover the tasks on which both columns have steps to success (``steps_tasks``; the caller
    says which with ``steps_average_note``), its success columns every task."""
    rows = []
    for label, ts in [(t, [t]) for t in tasks] + ([("**Average**", list(tasks))] if len(tasks) > 1 else []):
        cost = paired(records, seeds, ts, new, base)
        steps_ts = ts if len(ts) == 1 else steps_tasks(records, seeds, ts, new, base)
        groups = [saved_groups(records, seeds, t, new, base) for t in steps_ts]
        saved = (stats.NAN if not groups or not all(groups) else stats.seed_mean(groups[0]) if len(groups) == 1
                 else stats.average(groups))
        saved_text = "–" if not np.isfinite(saved.mean) else (
            f"{interval_text(saved, 100.0, signed=True)}, p={p_text(saved.p)}"
            + (f" ({'faster' if saved.low > 0 else 'slower' if saved.high < 0 else 'no difference'})"
               if np.isfinite(saved.low) else ""))
        rows.append([label,
                     ci(records, "success_rate", seeds, ts, 100.0, column=base),
                     ci(records, "success_rate", seeds, ts, 100.0, column=new),
                     "–" if cost is None else f"{interval_text(cost.diff, 100.0, signed=True)} ({verdict_text(cost)})",
                     *(ci(records, "mean_steps_success", seeds, steps_ts, column=c) if steps_ts else "–"
                       for c in (base, new)),
                     saved_text])
    return rows


def interval_comparison(records: list[dict], seeds, tasks: list[str], new: str, base: str,
                        table: str) -> list[list[str]]:
    """Per task and on average (several tasks), ``new`` − ``base`` success with the verdict's t interval over seeds
    and with version 1's hierarchical bootstrap interval, each with the verdict it gives: rows
    ``[comparison, table, task, t cell, bootstrap cell, same?, t verdict, bootstrap verdict]``; pairs with one seed
    (no t interval) are left out."""
    out = []
    for label, ts in [(task, [task]) for task in tasks] + ([("Average", tasks)] if len(tasks) > 1 else []):
        c = paired(records, seeds, ts, new, base)
        if c is None or stats.verdict(c.diff) not in VERDICTS:
            continue
        boot = paired_bootstrap(records, seeds, ts, new, base)
        tv, bv = stats.verdict(c.diff), stats.verdict(boot)
        out.append([f"{new} vs {base}", table, label, f"{interval_text(c.diff, 100.0, signed=True)} {tv}",
                    f"{interval_text(boot, 100.0, signed=True)} {bv}", "yes" if tv == bv else "**no**", tv, bv])
    return out


def interval_summary(rows: list[list[str]]) -> str:
    """One paragraph on ``interval_comparison`` rows: how often the two intervals give the same verdict and which
    cells they split."""
    split = [r for r in rows if r[6] != r[7]]
    text = (f"The same paired differences (the records of version 2, one network each) with two intervals: the t "
            f"interval over seeds, whose verdict the tables report, and version 1's hierarchical bootstrap over "
            f"seeds × episodes (`stats.hierarchical_bootstrap`, 10,000 resamples, percentile interval), which "
            f"treats the 3 trained networks as the whole population and under-covers when they differ "
            f"(`tests/test_stats.py`). They give the same verdict in {len(rows) - len(split)} of {len(rows)} cells")
    if not split:
        return text + "."
    return text + "; they split on: " + "; ".join(
        f"{r[0]}, {r[1]}, {r[2]} (t: {r[6]}, bootstrap: {r[7]})" for r in split) + "."


def findings_table(args: "CampaignArgs", tables: list[PaperArgs]) -> str | None:
    """``<results>/findings.md``: every paired comparison of ``FINDINGS`` in the built tables, one row each — per
    task the success difference in points on the shared initial states with its 95 % interval over seeds and
    verdict; the average over the table's tasks with the seed-level t test's p, the exact sign-flip p, the
    episode-level McNemar p and the average without each task in turn; the tasks won / tied / lost — then the
    same-network speed claim (HiPolicy vs w/o EG) and, when built, the training-budget rows; read from the tables'
    JSON (their records); → its path, None before any table holds a comparison."""
    rows, tally = [], dict.fromkeys(VERDICTS, 0)
    speed, budget_rows, interval_rows = [], [], []
    for t in tables:
        records = _table_json(args, t)
        if records is None:
            continue
        labels, seeds = {c.label for c in COLUMNS[table_name(t)](t)}, table_seeds(t)
        regime = "100 demos" if t.regime == "r100" else "Rlow"
        if table_name(t) == "budget":
            default = BUDGETS[t.budget].train.num_steps
            for n in t.steps:
                rs = budget_records(records, n, default)
                cells = []
                for task in args.tasks:
                    c = paired(rs, seeds, [task], "DP+HiPolicy", "DP") if task in t.tasks else None
                    cells.append("–" if c is None else finding_text(c))
                budget_rows.append([f"{n:,} steps", *cells])
            budget_rows.append([f"Gap {min(t.steps):,} → {max(t.steps):,} steps (protocol's rule)",
                                *(budget_gaps(records, seeds, task, t.steps, default)[2] if task in t.tasks else "–"
                                  for task in args.tasks)])
            continue
        for name, new, base in FINDINGS:
            if name != table_name(t) or not {new, base} <= labels:  # (DP3 columns: in R100's main table only)
                continue
            cells, counts = [], dict.fromkeys(VERDICTS, 0)
            for task in args.tasks:
                c = paired(records, seeds, [task], new, base) if task in t.tasks else None
                if c is None:
                    cells.append("–")
                    continue
                verdict = stats.verdict(c.diff)
                if verdict in counts:  # not "–" (one seed so far: a point, no test, not counted)
                    counts[verdict] += 1
                cells.append(finding_text(c))
            for v in VERDICTS:
                tally[v] += counts[v]
            avg = paired(records, seeds, list(t.tasks), new, base)
            interval_rows += interval_comparison(records, seeds, list(t.tasks), new, base,
                                                 f"{regime} ({results_name(t)})")
            rows.append([f"{new} vs {base}", f"{regime} ({results_name(t)})", *cells,
                         paired_cell(records, seeds, list(t.tasks), new, base),
                         "–" if avg is None else p_text(avg.sign_flip_p),
                         "–" if avg is None else p_text(avg.mcnemar_p),
                         leave_one_out(records, seeds, list(t.tasks), new, base),
                         "/".join(str(counts[v]) for v in VERDICTS)])
        if table_name(t) == "execution" and {"HiPolicy", "w/o EG"} <= labels:
            speed.append((regime, results_name(t), speed_rows(t, records, seeds, list(t.tasks)),
                          steps_average_note(records, seeds, list(t.tasks), "HiPolicy", "w/o EG")))
    if not rows:
        return None
    table = markdown_table(["Comparison", "Demos (table)", *args.tasks, "Average (seed-level t test)",
                            "Sign-flip p", "Episode-level McNemar p", "Leave one task out", "Tasks W/T/L"], rows)
    total = sum(tally.values())
    lines = ["# Findings: where HiPolicy wins, ties or loses", "",
             "Protocol v2 (`results/PROTOCOL.md`): the unit of evidence is the trained network. Each row is a paired "
             "comparison from one table: per task, the success difference (new − baseline) in points on the shared "
             "initial states — per seed the mean over its 100 episodes, then the mean over seeds with its 95 % t "
             "interval over seeds; **wins** / **loses** when the interval excludes 0 (the seed-level t test's "
             "p < 0.05), else **ties**. Average: the mean of the task means, its t interval (Welch) and p; the exact "
             "sign-flip p permutes the signs of the (task, seed) differences; the episode-level McNemar p treats "
             "every episode as independent and is shown for comparison with version 1 only. Leave one task out: "
             "the average without each task in turn. '–': no pair yet (see campaign_plan.md).", "",
             f"Over the {total} (comparison, task) cells: HiPolicy wins {tally['wins']}, ties {tally['ties']}, loses "
             f"{tally['loses']}.", "", table]
    for regime, name, srows, covers in speed:
        lines += ["", f"## Entropy-guided execution, same network: HiPolicy vs w/o EG, {regime} ({name})", "",
                  "One trained network per seed, executed with entropy guidance (HiPolicy) and always at stride 1 "
                  "(w/o EG) on the same initial states. The paper claims faster execution (fewer control steps) at "
                  "a small success cost. Steps saved: per seed, 100 · mean(w/o EG − HiPolicy) / mean(w/o EG) over "
                  "the episodes both succeeded in; mean over seeds with its t interval and p."
                  + (" " + covers if covers else ""), "",
                  markdown_table(["Task", "w/o EG SR (%)", "HiPolicy SR (%)", "Success cost (points)",
                                  "w/o EG steps", "HiPolicy steps", "Steps saved (%)"], srows)]
    if budget_rows:
        lines += ["", "## Training budget: DP+HiPolicy − DP (points) by training steps (budget.md)", "",
                  markdown_table(["Training", *args.tasks], budget_rows)]
    if interval_rows:
        lines += ["", "## The verdict's interval beside version 1's hierarchical bootstrap", "",
                  interval_summary(interval_rows), "",
                  markdown_table(["Comparison", "Demos (table)", "Task", "t interval over seeds (verdict)",
                                  "Hierarchical bootstrap (its verdict)", "Same verdict"],
                                 [r[:6] for r in interval_rows])]
    out = os.path.join(args.results, "findings.md")
    with open(out, "w") as f:
        f.write("\n".join(lines) + "\n")
    return out


def campaign_shard(args: "CampaignArgs") -> tuple[Campaign, list[PaperArgs], list[Job], set[str],
                                                   Callable[[Job], str]]:
    """The campaign's work in ``--shard K N``: (its ``Campaign``, the protocol's tables, the shard's jobs in
    ``campaign_jobs``' order, the tasks skipped for want of a pilot choice, ``run_of``: a job's run dir). A bad
    ``--shard`` or ``--until`` is a one-line ``ValueError`` before any work."""
    camp = campaign(args)
    tables = protocol_tables(args)
    jobs, skipped = campaign_jobs(args, tables)
    k, n = args.shard
    if not 0 <= k < n:
        raise ValueError(f"shard: expected K N with 0 <= K < N, got {k} {n}")
    parse_until(args.until)  # a bad --until fails before any work

    def run_of(job: Job) -> str:
        return camp.run_config(job.task, job.col, job.seed, dict(job.changes)).out_dir()

    return camp, tables, shard(jobs, k, n, run_of), skipped, run_of


def campaign_table(args: "CampaignArgs") -> str:
    """Every evaluation of the protocol's tables under ONE progress bar (with its ETA), each kept in its run's record
    as it finishes, then every table rebuilt from the records; → the path of the campaign's index. With
    ``--executor local`` / ``slurm`` the runs are worked off by one job a run (``cluster.work_off``)."""
    camp, tables, jobs, skipped, run_of = campaign_shard(args)
    n = args.shard[1]
    costs = CostModel(args.records, args.runs).estimate(camp, jobs)
    if args.plan:
        return write_plan(args, costs)
    if args.executor == "inprocess" or args.from_records:
        work_off(camp, costs, run_of, until=args.until, progress=args.progress)
    else:
        from hipolicy_jax.campaigns import cluster

        cluster.work_off(args, costs, run_of)
    if n > 1 or not args.tables:  # the other shards may still run (or tables not asked for): what is left
        return write_plan(args, CostModel(args.records, args.runs).estimate(camp, jobs))
    paths, built = [], []
    for t in tables:  # a regime's table holds the tasks the pilot has chosen its demos for
        ready = tuple(task for task in t.tasks if t.regime == "r100" or task in REGIMES[t.regime])
        if ready:
            built.append(dataclasses.replace(t, tasks=ready, from_records=True))
            paths.append(BUILDERS[table_name(t)](built[-1]))
    findings = findings_table(args, built)
    if findings is not None:
        paths.insert(0, findings)
    now = CostModel(args.records, args.runs).estimate(camp, jobs)
    left = [c for c in now if not c["done"]]
    progress = ""
    if left:  # an interim build (--from-records, or a campaign stopped early): say how far it got
        plan = write_plan(args, now)
        progress = (f"Interim: {len(jobs) - len(left)} of {len(jobs)} evaluations recorded; what is left and its "
                    f"estimated cost: [campaign_plan.md]({{}}).")
    spent = CostModel(args.records, args.runs).spent(args.budget)
    cost = (f"The campaign{' so far' if left else ''} cost {(spent['train_s'] + spent['eval_s']) / 3600:.1f} "
            f"CPU-hours of this 2-core machine kind, each run and evaluation counted once (the pilot's included): "
            f"{spent['train_s'] / 3600:.1f} h training {spent['runs']} runs, {spent['eval_s'] / 3600:.1f} h making "
            f"{spent['evaluations']} evaluations {spent_measured_text(spent)}; a table's Cost line counts the runs it shares with others too.")
    lines = [f"# Campaign ({args.budget})", "", f"Command: `{command_line(args)}`", "", cost, "",
             f"{len(jobs)} evaluations; tables:", ""] + [f"- [{os.path.basename(p)}]({os.path.basename(p)})"
                                                           for p in paths]
    if progress:
        lines += ["", progress.format(os.path.basename(plan))]
    if skipped:
        lines += ["", "Not run yet: " + ", ".join(sorted(skipped))]
    index = os.path.join(args.results, "campaign.md")
    with open(index, "w") as f:
        f.write("\n".join(lines) + "\n")
    if args.readme:
        readme_dir = os.path.dirname(os.path.abspath(args.readme))
        section = cost + "\n\n" + readme_section(paths, readme_dir)
        if progress:
            section = progress.format(os.path.relpath(plan, readme_dir)) + "\n\n" + section
        if skipped:
            section += "\n\nNot run yet: " + ", ".join(sorted(skipped)) + "."
        if update_readme(args.readme, section):
            print(f"updated the campaign tables in {args.readme}")
        else:
            print(f"{args.readme}: no campaign markers ({README_BEGIN!r} ... {README_END!r}); README left as is")
    return index


BUILDERS = {"main": main_table, "ablation": ablation_table, "execution": execution_table,
            "thresholds": thresholds_table, "hparams": hparams_table, "pilot": pilot_table,
            "budget": budget_table, "semantics": semantics_table, "campaign": campaign_table}



def build(args: PaperArgs) -> str:
    """Build the table ``args`` stands for (its runs trained / evaluated as needed); → its markdown file's path."""
    return BUILDERS[table_name(args)](args)
