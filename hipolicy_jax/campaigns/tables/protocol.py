"""The campaign: every table of results/PROTOCOL.md (``protocol_tables``) with the campaign's settings, their
evaluations as jobs under ONE progress bar (``campaign_jobs``, ``campaign_shard``; in process or as cluster jobs),
the plan of what is left (``write_plan``), then every table, ``findings.md``, the index ``campaign.md`` and the
results page's campaign section (``--readme``) rebuilt from the records (``campaign_table``)."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from typing import ClassVar, Literal

from hipolicy_jax.campaigns.budgets import REGIMES
from hipolicy_jax.campaigns.campaign import (README_BEGIN, README_END, Campaign, CostModel, Job, damaged_lines,
                                             parse_until, readme_section, schedule, shard, update_readme, work_off)
from hipolicy_jax.campaigns.report import changes_text, markdown_table, spent_measured_text
from hipolicy_jax.campaigns.tables.ablation import AblationArgs
from hipolicy_jax.campaigns.tables.budget import BudgetArgs
from hipolicy_jax.campaigns.tables.common import (ObsName, PaperArgs, campaign, column_seeds, command_line, table_name,
                                                  table_run_changes)
from hipolicy_jax.campaigns.tables.execution import ExecutionArgs
from hipolicy_jax.campaigns.tables.findings import findings_table
from hipolicy_jax.campaigns.tables.hparams import HparamsArgs
from hipolicy_jax.campaigns.tables.main import MainArgs
from hipolicy_jax.campaigns.tables.registry import COLUMNS, TABLE_BUILDERS
from hipolicy_jax.campaigns.tables.semantics import SemanticsArgs
from hipolicy_jax.campaigns.tables.thresholds import ThresholdsArgs


@dataclasses.dataclass(frozen=True)
class CampaignArgs(PaperArgs):
    """The whole protocol: every table's runs and evaluations under one progress bar, then every table."""

    TABLE: ClassVar[str] = "campaign"

    baseline_seeds: tuple[int, ...] = (3, 4)
    episodes: int | None = 100
    regimes: tuple[Literal["r100", "rlow"], ...] = ("r100", "rlow")
    obs_types: tuple[ObsName, ...] = ("state", "pointcloud")  # main table in R100: DP and the DP3 columns
    # the results page whose campaign section (between the markers) is rewritten from the tables (README.md before
    # issue #61; old command lines still parse); '' = leave it
    readme: str = "docs/results.md"
    plan: bool = False  # write what is left (evaluations, runs to train, estimated CPU-hours) and stop
    # K N: only the K-th (0-based) of N shards of the runs, so that N processes split the campaign — one per core
    # (`taskset -c K`) or per machine sharing the records; every evaluation of a run is in its run's shard. A shard
    # ends by writing the plan of what is left; build the tables with --from-records once every shard has finished
    shard: tuple[int, int] = (0, 1)
    # HH:MM or YYYY-MM-DD HH:MM (local time): start only the jobs whose estimated time ends before it, skip the rest
    # (a scheduler's time limit, a session's end); '' = no limit
    until: str = ""
    # end by rebuilding every table and the results page's section from the records; --no-tables writes only the plan of
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
            paths.append(TABLE_BUILDERS[table_name(t)](built[-1]))
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
            print(f"{args.readme}: no campaign markers ({README_BEGIN!r} ... {README_END!r}); left as is")
    return index
