"""What every table of the MJX campaign shares: ``PaperArgs`` (the flags all tables have), the table's name and
command line, its runs' configs and seeds, ``collect`` (every evaluation of a table, from its records or trained /
evaluated and recorded), the markdown / JSON / figure writer with its header, and the row layouts (per task, by
precise / non-precise group, averages).

Each table's own module (``main``, ``ablation``, ...) builds on these; ``campaigns.metaworld`` does too.
"""

from __future__ import annotations

import dataclasses
import glob
import os
import shlex
from typing import ClassVar, Literal

from tqdm.auto import tqdm

from hipolicy_jax.envs import TASK_PRECISE
from hipolicy_jax.campaigns.budgets import BUDGETS, DP, regime_changes, run_config
from hipolicy_jax.campaigns.campaign import Campaign, Column
from hipolicy_jax.campaigns.report import (RATE_BOUNDS, bar_figure, changes_text, ci, cost_note, outcomes,
                                           paired_cell, relative_gain, task_mean)
from hipolicy_jax.runs.store import read_json, write_json
from hipolicy_jax.runs.train import RunConfig


TaskName = Literal["press_button", "latch_door", "stack_cubes", "pick_place"]
ObsName = Literal["state", "image", "pointcloud"]


@dataclasses.dataclass(frozen=True)
class PaperArgs:
    """What every table of the campaign shares: the budget, tasks, seeds and demo regime of its runs, and where
    its runs, records, demo buffers and results are. Each table's args class adds its own fields and ``TABLE``."""

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
    TABLE: ClassVar[str]  # the table's sub-command (``table_name``): set by each table's args class

    def run_changes(self, task: str) -> list[dict]:
        """The run-level changes this table trains ``task``'s runs under: its regime's. A table that trains its runs
        otherwise says so here (``BudgetArgs``: one set per step count; ``SemanticsArgs``: its step count)."""
        return [regime_changes(self.regime, task)]


def table_name(args: PaperArgs) -> str:
    """The table's sub-command: its class's ``TABLE`` (the tables of this package and of other modules, e.g.
    ``campaigns.metaworld``)."""
    return type(args).TABLE


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
    """The run-level changes a table trains ``task``'s runs under (``PaperArgs.run_changes``): its regime's, or for
    the training-budget table one set per step count (the budget's own count: none)."""
    return args.run_changes(task)


def collect(args: PaperArgs, columns: list[Column]) -> list[dict]:
    """Every (task, seed, column) evaluation of the table, from its run's record or trained / evaluated and recorded
    (one progress bar over them, with an ETA) → one record per evaluation (per-episode outcomes included).
    The tables call it as ``common.collect``: the one place a test fakes it."""
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


# the paired cells' note; a table whose own file does not report the episode-level McNemar p (the Meta-World tables:
# findings.md has no rows of theirs) says where it is, or that it has none, after PAIRED_NOTE_CELLS
PAIRED_NOTE_CELLS = ("Paired columns: per seed both columns have, the mean per-episode success difference on the "
                     "shared initial states; their mean with its 95 % t interval over seeds and the seed-level t "
                     "test's p (protocol v2); wins / loses when the interval excludes 0 (p < 0.05).")
PAIRED_NOTE = PAIRED_NOTE_CELLS + " The episode-level McNemar p is in findings.md."
