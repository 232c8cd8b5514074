"""The Meta-World benchmark (``results/metaworld/PROTOCOL.md``): its DP pilot, its campaign and its table, built on the
MJX campaign's machinery (``campaign``, ``budgets``, ``report``, ``tables``) with the runs' external evaluation
(``runs.external``: the policy served here, the episodes run by ``metaworld_bridge`` in its own venv).

- ``pilot``: DP (state, seed 0) trained 8000 steps on the protocol's first two tasks, checkpoints at 1000 / 2000 /
  4000 / 8000 evaluated; chooses the training length T (``choose_training_steps``).
- ``main``: the four columns (DP, DP+HiPolicy on state; DP3, DP3+HiPolicy on point clouds) on the protocol's tasks,
  run in the protocol's order (state before point clouds, task by task, DP first, seeds 0, 1, 2) under a
  ``--until`` deadline, then the table rebuilt from the records: success with paired comparisons, and DP3's metric
  (mean of the 5 best periodic evaluations) beside DP3's published numbers. ``--plan`` writes what is left.

``experiments.metaworld`` parses the flags of each.
"""

from __future__ import annotations

import dataclasses
import os
from typing import ClassVar, Literal

import numpy as np
from tqdm.auto import tqdm

from hipolicy_jax.campaigns.budgets import (BUDGETS, DP, METAWORLD_PILOT, METAWORLD_PILOT_STEPS,
                                            METAWORLD_POINTCLOUD_TASKS, METAWORLD_STATE_TASKS, METAWORLD_STEPS)
from hipolicy_jax.campaigns.campaign import (EXTERNAL_EVAL_SEED, Column, CostModel, Job, Periodic, damaged_lines,
                                             readme_section, update_readme, work_off)
from hipolicy_jax.campaigns.report import markdown_table, p_text, paired, spent_measured_text
from hipolicy_jax.campaigns.tables import (PAIRED_NOTE_CELLS, PaperArgs, table_record, campaign, demo_steps,
                                           eval_episodes, grouped_rows, rows_by_group, speed_rows,
                                           steps_average_note, success_by_task_figure, table_seeds, write_results)
from hipolicy_jax.runs.store import read_json, write_json
from hipolicy_jax.runs.lock import CAMPAIGN_LOCK_FILE, RunLock, RunLockedError

PROTOCOL_FILE = "results/metaworld/PROTOCOL.md"
DIAGNOSIS = "results/metaworld/diagnosis"  # the post hoc diagnosis's files (``DiagnoseArgs.results``)
STRIDED_EXPERTS = "strided_experts.json"  # the bridge's chunking expert per stride and action space (diagnosis)
# The protocol's tasks in its order (round robin over DP3's groups), with their DP3 group.
TASKS: tuple[tuple[str, str], ...] = (
    ("basketball", "medium"), ("assembly", "hard"), ("shelf-place", "very hard"), ("bin-picking", "medium"),
    ("hand-insert", "hard"), ("stick-push", "very hard"), ("coffee-pull", "medium"), ("pick-out-of-hole", "hard"),
    ("pick-place-wall", "very hard"), ("coffee-push", "medium"), ("pick-place", "hard"), ("hammer", "medium"),
    ("push", "hard"), ("push-wall", "medium"), ("sweep", "medium"), ("sweep-into", "medium"))
GROUPS = ("medium", "hard", "very hard")
COLUMNS = (Column("DP", "state", DP), Column("DP+HiPolicy", "state"), Column("DP3", "pointcloud", DP),
           Column("DP3+HiPolicy", "pointcloud"))


def full_name(task: str) -> str:
    """``assembly`` → ``metaworld:assembly``; a full name (``metaworld-target:assembly``) is kept."""
    return task if ":" in task else f"metaworld:{task}"


def protocol_tasks(count: int | None = None) -> tuple[str, ...]:
    """The first ``count`` of the protocol's tasks (all when None), full names."""
    return tuple(full_name(t) for t, _ in TASKS[:count])


@dataclasses.dataclass(frozen=True)
class MetaWorldArgs(PaperArgs):
    COMMAND: ClassVar[str] = "experiments.metaworld"
    PROTOCOL: ClassVar[str] = PROTOCOL_FILE

    budget: Literal["metaworld", "smoke"] = "metaworld"
    tasks: tuple[str, ...] = ()  # Meta-World tasks (``assembly`` or ``metaworld:assembly``); default: the protocol's
    results: str = "results/metaworld"

    def __post_init__(self):
        object.__setattr__(self, "tasks", tuple(full_name(t) for t in (self.tasks or self.default_tasks())))

    def default_tasks(self) -> tuple[str, ...]:
        return protocol_tasks()


@dataclasses.dataclass(frozen=True)
class PilotArgs(MetaWorldArgs):
    """DP-only pilot (results/metaworld/PROTOCOL.md): DP (state, seed 0) trained 8000 steps on the protocol's first
    two tasks, its checkpoints at 1000 / 2000 / 4000 / 8000 evaluated on 100 episodes; chooses the training length."""

    TABLE: ClassVar[str] = "pilot"
    seeds: tuple[int, ...] = (0,)
    # the budget rules' other measurements (PROTOCOL.md "Budget"): a point-cloud train step (CPU-s at batch 64,
    # `benchmarks.train_step --obs pointcloud --num-points 512`, other jobs paused) and the bridge's point-cloud
    # camera (ms per frame); given, the pilot table applies rules 1 and 2
    pointcloud_train_s_per_step: float | None = None
    camera_ms_per_frame: float | None = None
    budget_hours: float = 40.0

    def default_tasks(self) -> tuple[str, ...]:
        return protocol_tasks(2)


@dataclasses.dataclass(frozen=True)
class MainArgs(MetaWorldArgs):
    """The Meta-World table: DP, DP+HiPolicy (state) on the protocol's state tasks and DP3, DP3+HiPolicy (point
    clouds) on its point-cloud tasks, 3 seeds x 100 episodes through the policy server; DP3's metric beside DP3's
    published numbers."""

    TABLE: ClassVar[str] = "main"
    # the point-cloud columns' tasks (default: the first METAWORLD_POINTCLOUD_TASKS of the protocol's order)
    pointcloud_tasks: tuple[str, ...] | None = None
    steps: int | None = None  # training steps T (default: the pilot's, budgets.METAWORLD_STEPS)
    published: str = "results/metaworld/dp3_published.json"  # DP3's Table XVIII
    until: str = ""  # HH:MM or YYYY-MM-DD HH:MM: start only the jobs estimated to end before it
    plan: bool = False  # write what is left (results/metaworld/plan.md) and stop
    # end by rebuilding the table and the results page's section from the records; --no-tables writes only the plan
    # of what is left, so that a run narrowed to a few tasks (--tasks) leaves the full table alone
    tables: bool = True
    # the results page whose section for this table (between readme_markers(results)) is rewritten from the table
    # (README.md before issue #61; old command lines still parse); '' = leave it
    readme: str = "docs/results.md"

    def default_tasks(self) -> tuple[str, ...]:
        return protocol_tasks(METAWORLD_STATE_TASKS)

    def resolved_pointcloud_tasks(self) -> tuple[str, ...]:
        if self.pointcloud_tasks is not None:
            return tuple(full_name(t) for t in self.pointcloud_tasks)
        return protocol_tasks(METAWORLD_POINTCLOUD_TASKS or 0)

    def training_steps(self) -> int:
        return training_steps(self.budget, self.steps)


def training_steps(budget: str, steps: int | None) -> int:
    """T: ``steps`` (``--steps``), else the pilot's (``budgets.METAWORLD_STEPS``); the smoke budget keeps its own."""
    if budget != "metaworld":
        return BUDGETS[budget].train.num_steps
    steps = steps or METAWORLD_STEPS
    if steps is None:
        raise ValueError("steps: the Meta-World training length is not fixed yet; run the pilot first "
                         "(python -m experiments.metaworld pilot), record its T in results/metaworld/PROTOCOL.md "
                         "and hipolicy_jax/campaigns/budgets.py METAWORLD_STEPS (or pass --steps)")
    return steps


def run_changes(budget: str, steps: int | None) -> tuple[tuple[str, int], ...]:
    """The campaign runs' changes to the budget's config: the training length when it is not the budget's own."""
    n = training_steps(budget, steps)
    return () if n == BUDGETS[budget].train.num_steps else (("train.num_steps", n),)


@dataclasses.dataclass(frozen=True)
class DiagnoseArgs(MetaWorldArgs):
    """Post hoc, not in the protocol: per task, how far a stride's segment of Meta-World's displacement actions moves
    the hand (the campaign's demos; none for ``metaworld-target:<task>``, whose actions are absolute), and each
    recorded DP+HiPolicy network evaluated again at stride 1 (w/o EG) on its seed's initial states, beside DP and the
    guided evaluation → ``results/metaworld/diagnosis/`` (amendment 1's tasks: pass ``--tasks metaworld-target:...
    --results results/metaworld/target/diagnosis``)."""

    TABLE: ClassVar[str] = "diagnose"
    results: str = DIAGNOSIS
    experts: str = os.path.join(DIAGNOSIS, STRIDED_EXPERTS)  # check_experts' summary
    steps: int | None = None  # training steps T of the runs (default: the pilot's, as ``main``)

    def default_tasks(self) -> tuple[str, ...]:
        return protocol_tasks(METAWORLD_STATE_TASKS)


# ------------------------------------------------------------------------------------------------ pilot


def choose_training_steps(rates: dict[int, list[float]], tolerance: float = 0.05) -> int:
    """The pilot's rule: the fewest training steps whose mean success over the tasks is within ``tolerance`` of the
    best step count's ({steps: [success per task]})."""
    means = {steps: float(np.mean(r)) for steps, r in rates.items()}
    best = max(means.values())
    return min(steps for steps, m in means.items() if m >= best - tolerance - 1e-12)


def budget_rules(*, budget_s: float, spent_s: float, steps: int, state_s_per_step: float, state_eval_s_per_100: float,
                 pc_s_per_step: float, pc_eval_s_per_100: float, periodic_episodes: int = 200, seeds: int = 3,
                 tasks: int = len(TASKS), min_tasks: int = 10, state_share: float = 0.6) -> dict:
    """The protocol's budget rules 1 and 2 (CPU-seconds): a network costs its training (rate × ``steps``) and its
    evaluations (100 main + ``periodic_episodes`` episodes); a task's column pair costs 2 × ``seeds`` networks.
    K: all ``tasks`` when their state columns fit ``state_share`` of what is left after ``spent_s``, else the
    largest K ≥ ``min_tasks`` that fits (None: none fits, T must drop); P: the point-cloud tasks the rest carries."""
    left = budget_s - spent_s
    episodes = (100 + periodic_episodes) / 100
    state_task = 2 * seeds * (state_s_per_step * steps + state_eval_s_per_100 * episodes)
    pc_task = 2 * seeds * (pc_s_per_step * steps + pc_eval_s_per_100 * episodes)
    fits = [k for k in range(min_tasks, tasks + 1) if k * state_task <= state_share * left]
    k = max(fits) if fits else None
    p = None if k is None else max(int((left - k * state_task) // pc_task), 0)
    return {"left_s": left, "state_task_s": state_task, "pointcloud_task_s": pc_task, "state_tasks": k,
            "pointcloud_tasks": None if p is None else min(p, k), "steps": steps}


def pilot_table(args: PilotArgs) -> str:
    """Per task, DP's success at each pilot checkpoint, the chosen T and the measured rates the budget rules need;
    writes ``<results>/pilot.md`` / ``.json`` and ``pilot_choice.json``."""
    camp = campaign(args)
    dp = Column("DP", "state", DP)
    seed = args.seeds[0]
    # its own runs (never a table's): every kept checkpoint at the pilot's interval; smoke: 12 steps, kept at 6, 12
    pilot = METAWORLD_PILOT if args.budget == "metaworld" else {"train.ckpt_every": 6}
    steps = METAWORLD_PILOT_STEPS if args.budget == "metaworld" else (6, 12)
    rates: dict[int, list[float]] = {}
    rows, records, costs = [], [], []
    for task in tqdm(args.tasks, desc="metaworld pilot", unit="task", disable=not args.progress):
        ev = camp.evaluate(task, dp, seed, pilot, periodic=Periodic(eval_episodes(args), EXTERNAL_EVAL_SEED,
                                                                    tuple(steps[:-1])))
        if ev is None:
            rows.append([task, *(["–"] * len(steps))])
            continue
        record = camp.record(task, dp, seed, pilot)
        records.append(table_record(camp, task, dp, seed, pilot, ev))
        by_step = {c["step"]: c["success_rate"] for c in ev["periodic"]["checkpoints"]}
        by_step[int(record["checkpoint_step"])] = ev["success_rate"]
        for n in steps:
            if n in by_step:
                rates.setdefault(n, []).append(by_step[n])
        rows.append([task, *(f"{100 * by_step[n]:.0f}" if n in by_step else "–" for n in steps)])
        training = record.get("training") or {}
        per_eval = [ev.get("main_eval_s", ev["eval_s"]) * (ev.get("cpu_cores") or 2)] + [
            c["eval_s"] * (c.get("cpu_cores") or 2) for c in ev["periodic"]["checkpoints"]]
        costs.append({"task": task, "train_cpu_s_per_step": (training.get("wall_time_s") or 0)
                      * (training.get("cpu_cores") or 2) / max(training.get("steps") or 1, 1),
                      "eval_cpu_s_per_100_episodes": float(np.median(per_eval)) * 100 / eval_episodes(args)})
    complete = bool(rates) and all(len(r) == len(args.tasks) for r in rates.values())
    chosen = choose_training_steps(rates) if complete else None
    rules = None
    if chosen and costs and args.pointcloud_train_s_per_step and args.camera_ms_per_frame:
        spent = CostModel(args.records, args.runs).spent(args.budget)
        inputs = {"spent_s": spent["train_s"] + spent["eval_s"],
                  "state_s_per_step": float(np.median([c["train_cpu_s_per_step"] for c in costs])),
                  "state_eval_s_per_100": float(np.median([c["eval_cpu_s_per_100_episodes"] for c in costs])),
                  "pc_s_per_step": args.pointcloud_train_s_per_step}
        frames_100 = float(np.mean([np.mean(r["steps"]) for r in records])) * 100  # frames per 100 episodes
        inputs["pc_eval_s_per_100"] = inputs["state_eval_s_per_100"] + frames_100 * args.camera_ms_per_frame / 1000
        # rule 1: T, or the next smaller pilot candidate while not even 10 tasks' state columns fit
        for n in sorted((n for n in steps if n <= chosen), reverse=True):
            rules = budget_rules(budget_s=args.budget_hours * 3600, steps=n, **inputs)
            if rules["state_tasks"] is not None:
                break
        rules["inputs"] = {**inputs, "camera_ms_per_frame": args.camera_ms_per_frame,
                           "frames_per_100_episodes": frames_100}
    rows.append(["mean", *(f"{100 * np.mean(rates[n]):.1f}" if n in rates else "–" for n in steps)])
    table = markdown_table(["Task", *(f"DP @ {n} steps (%)" for n in steps)], rows)
    notes = [f"DP only (one stride), seed {seed}, one run per task; each checkpoint evaluated on "
             f"{eval_episodes(args)} episodes through the policy server (initial-state seeds "
             f"{EXTERNAL_EVAL_SEED + 1000 * seed}...).",
             "Rule: T = the fewest steps whose mean success over the tasks is within 5 points of the best."
             + (f" **T = {chosen}**." if chosen else " Not every checkpoint is evaluated yet."),
             "Measured costs (CPU-seconds): " + ("; ".join(
                 f"{c['task']}: training {c['train_cpu_s_per_step']:.2f} s/step, evaluation "
                 f"{c['eval_cpu_s_per_100_episodes']:.0f} s per 100 episodes" for c in costs) or "–")]
    os.makedirs(args.results, exist_ok=True)
    if rules is not None:
        notes.append(f"Budget rules ({args.budget_hours:g} CPU-hours; {rules['left_s'] / 3600:.1f} h left after the "
                     f"pilot): a task's state columns cost {rules['state_task_s'] / 3600:.2f} h, its point-cloud "
                     f"columns {rules['pointcloud_task_s'] / 3600:.2f} h → state columns on the first "
                     f"**{rules['state_tasks']}** tasks, point-cloud columns on the first "
                     f"**{rules['pointcloud_tasks']}**, T = {rules['steps']}.")
    write_json(os.path.join(args.results, "pilot_choice.json"),
               {"T": chosen, "rates": {str(k): v for k, v in rates.items()}, "costs": costs, "budget_rules": rules})
    return write_results(args, "Meta-World DP pilot: success by training length", notes, table, records)


# ------------------------------------------------------------------------------------------------- main


def main_jobs(args: MainArgs) -> list[Job]:
    """The protocol's order: state columns before point clouds; task by task in the protocol's order; DP before
    DP+HiPolicy; seeds ascending."""
    changes = run_changes(args.budget, args.steps)
    pc_tasks = set(args.resolved_pointcloud_tasks())
    jobs = []
    for obs in ("state", "pointcloud"):
        for task in args.tasks:
            if obs == "pointcloud" and task not in pc_tasks:
                continue
            for col in (c for c in COLUMNS if c.obs_type == obs):
                jobs += [Job(task, col, seed, changes) for seed in args.seeds]
    return jobs


def write_plan(args: MainArgs, costs: list[dict], spent: dict[str, float]) -> str:
    """``<results>/plan.md``: the pending jobs with their estimated CPU-seconds and what the records spent so far.
    ``costs``: ``CostModel.estimate`` rows; ``spent``: ``CostModel.spent`` of the budget's records. Returns the
    path."""
    pending = [c for c in costs if not c["done"]]
    known = [c["seconds"] for c in pending if c["seconds"] is not None]
    spent_h = (spent["train_s"] + spent["eval_s"]) / 3600
    lines = ["# Meta-World campaign: what is left", "",
             f"{len(pending)} of {len(costs)} evaluations pending, {sum(c['trains'] for c in pending)} runs to "
             f"train; estimated {sum(known) / 3600:.1f} CPU-hours for the {len(known)} with a measured rate"
             + (f" ({len(pending) - len(known)} not yet measured)" if len(known) < len(pending) else "") + ".", "",
             f"Spent so far: {spent_h:.1f} CPU-hours in the `{args.budget}` records (runs trained: {spent['runs']}, "
             f"evaluations: {spent['evaluations']}; the pilot and every arm included) "
             f"{spent_measured_text(spent)}; spent + left: {spent_h + sum(known) / 3600:.1f} CPU-hours. Counted as wall time × cores, as the "
             f"protocol's budget counts them: {spent['wall_core_s'] / 3600:.1f} spent.", "",
             *pending_lines(pending, costs)]
    return write_plan_file(args.results, lines)


def pending_lines(pending: list[dict], costs: list[dict]) -> list[str]:
    """A plan's table of the pending evaluations (task, column, seed, whether its run trains, the estimated CPU-s)
    and the lines naming damaged records."""
    return [markdown_table(["Task", "Column", "Seed", "Trains", "Estimated CPU-s"],
                           [[c["job"].task, c["job"].col.label, str(c["job"].seed), "yes" if c["trains"] else "",
                             "–" if c["seconds"] is None else f"{c['seconds']:.0f}"] for c in pending]),
            *damaged_lines(costs)]


def write_plan_file(results: str, lines: list[str]) -> str:
    """Write ``<results>/plan.md`` from its lines; → its path."""
    os.makedirs(results, exist_ok=True)
    path = os.path.join(results, "plan.md")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    return path


def readme_markers(results: str) -> tuple[str, str]:
    """The results page's markers around the section ``main --results RESULTS`` writes: one pair per table."""
    md = os.path.normpath(os.path.join(results, "main.md"))
    return (f"<!-- Meta-World table: written by `python -m experiments.metaworld main` from {md} -->",
            f"<!-- end of Meta-World table {md} -->")


def write_readme_section(args: MainArgs, md: str, recorded: int, jobs: int) -> None:
    """The results page's section for this table (``--readme``, docs/results.md: a level-4 copy of ``md`` with its
    plot, under a line saying how many of the table's runs are recorded; links relative to the page); the page is
    left as is, with a line saying so, when its markers are absent."""
    readme_dir = os.path.dirname(os.path.abspath(args.readme))
    plan = os.path.relpath(os.path.join(args.results, "plan.md"), readme_dir)
    head = (f"{recorded} of {jobs} runs recorded" + ("" if recorded == jobs else f"; what is left and its estimated "
                                                     f"cost: [{os.path.basename(plan)}]({plan})") + ".")
    begin, end = readme_markers(args.results)
    if update_readme(args.readme, head + "\n\n" + readme_section([md], readme_dir, level=4), begin, end):
        print(f"updated the Meta-World table in {args.readme}")
    else:
        print(f"{args.readme}: no markers ({begin!r} ... {end!r}); left as is")


def published_numbers(path: str) -> dict[str, dict]:
    """DP3's Table XVIII by bare task name ({} when the file is missing)."""
    return read_json(path).get("tasks", {}) if os.path.exists(path) else {}


PAIRED_TESTS = "Paired comparisons: sign-flip and McNemar p"  # the section of the main table's other two tests
# the main table's paired cells: the seed-level t test's verdict there, its other two tests in PAIRED_TESTS
MAIN_PAIRED_NOTE = (PAIRED_NOTE_CELLS + f" Each paired cell's sign-flip p over seeds and episode-level McNemar p are "
                    f"in the section *{PAIRED_TESTS}* below.")


def paired_tests_section(args: MainArgs, records: list[dict], pairs: list[tuple[str, str]],
                         groups: list[tuple[str, list[str]]]) -> str:
    """The protocol's other two tests of the main table's paired cells (``results/metaworld/PROTOCOL.md``,
    Statistics), row for row: the exact sign-flip p over the (task, seed) differences (``stats.sign_flip_p``) and
    the episode-level exact McNemar p (``stats.mcnemar_exact``), as ``report.paired`` computes them; '–' without a
    pair."""
    def cells(tasks: list[str]) -> list[str]:
        out = []
        for new, base in pairs:
            c = paired(records, table_seeds(args), tasks, new, base)
            out += ["–", "–"] if c is None else [p_text(c.sign_flip_p), p_text(c.mcnemar_p)]
        return out

    rows = rows_by_group(args, cells, groups=groups)
    header = ["Task", *(f"{a} − {b}: {test}" for a, b in pairs for test in ("sign-flip p",
                                                                          "episode-level McNemar p"))]
    return (f"\n## {PAIRED_TESTS}\n\n"
            "The same paired differences as the table's paired cells, whose verdict is the seed-level t test's, "
            "with the protocol's two other tests. Sign-flip p: exact, over every pattern of signs of the (task, "
            "seed) differences (each a seed's mean over its shared episodes), each task weighing the same, two-sided; "
            f"{len(args.seeds)} seeds of one task cannot give less than {2 / 2 ** len(args.seeds):g}. Episode-level "
            "McNemar p: exact, over the discordant (seed, episode) pairs of the rows' tasks, every episode counted "
            "as independent whatever network it came from; for information only (protocol v2).\n\n"
            + markdown_table(header, rows) + "\n")


def main_table(args: MainArgs) -> str:
    """Run what is pending (unless ``--from-records``), then write ``<results>/main.md`` / ``.png`` / ``.json``."""
    camp = campaign(args)
    jobs = main_jobs(args)
    if not args.from_records:
        model = CostModel(args.records, args.runs)
        costs = model.estimate(camp, jobs)
        if args.plan:
            return write_plan(args, costs, model.spent(args.budget))
        work_off(camp, costs, lambda j: camp.run_config(j.task, j.col, j.seed, dict(j.changes)).out_dir(),
                 until=args.until, progress=args.progress)
        if not args.tables:
            now = CostModel(args.records, args.runs)  # read again: the runs just done are recorded
            return write_plan(args, now.estimate(camp, jobs), now.spent(args.budget))
    reader = campaign(dataclasses.replace(args, from_records=True))
    records = []
    for task, col, seed, changes in jobs:
        ev = reader.evaluate(task, col, seed, dict(changes))
        if ev is not None:
            records.append(table_record(reader, task, col, seed, dict(changes), ev))
    labels = [c.label for c in COLUMNS]
    group = {full: g for full in args.tasks for t, g in TASKS if full.partition(":")[2] == t}  # by bare task name
    groups = [(g, [t for t in args.tasks if group.get(t) == g]) for g in GROUPS]
    groups.append(("other", [t for t in args.tasks if t not in group]))
    pairs = [("DP+HiPolicy", "DP"), ("DP3+HiPolicy", "DP3")]
    rows = grouped_rows(args, records, labels, paired=pairs, groups=groups,
                        extra=lambda t: [group.get(t, "–"), demo_steps(args, t)])
    table = markdown_table(["Task", "DP3 group", "Demo steps", *labels, *(f"{a} − {b} (points)" for a, b in pairs)],
                           rows)
    published = published_numbers(args.published)

    def pub(task: str, key: str) -> str:
        v = published.get(task.partition(":")[2], {}).get(key)
        return "–" if v is None else f"{v[0]:g} ± {v[1]:g}"

    def gap(task: str, column: str, key: str) -> str:
        """Our column's DP3 metric (mean over all its seeds) minus the published mean, in points."""
        from hipolicy_jax.campaigns.report import values

        ours = [v for v in values(records, "dp3_metric", args.seeds, task=task, column=column) if np.isfinite(v)]
        v = published.get(task.partition(":")[2], {}).get(key)
        if not ours or v is None or len(ours) < len(args.seeds):
            return "–"
        return f"{100 * np.mean(ours) - v[0]:+.1f}"

    gaps = (("DP", "dp_image", "DP (state) − published DP (image)"), ("DP3", "dp3", "DP3 − published DP3"))
    metric_rows = grouped_rows(args, records, labels, metric="dp3_metric", groups=groups,
                               extra=lambda t: [pub(t, "dp_image"), pub(t, "dp3")])
    for row in metric_rows:  # the gap columns: per task only
        row += [gap(row[0], c, k) if ":" in row[0] else "" for c, k, _ in gaps]
    metric_table = markdown_table(["Task", "published DP (image)", "published DP3", *labels,
                                   *(f"{label} (points)" for _, _, label in gaps)], metric_rows)
    steps = args.training_steps()
    notes = [f"Success rate (%) over 100 episodes per seed (initial states {EXTERNAL_EVAL_SEED}+1000·seed+i, the same "
             f"for every column), step limit 200, through the policy server (`metaworld_bridge.evaluate`, openpi's "
             f"client); whole-chunk execution, HiPolicy entropy-guided at thresholds from a held-out demo. Training: "
             f"{steps} steps on 10 demos (one more held out).", MAIN_PAIRED_NOTE,
             "Point-cloud columns on " + (", ".join(args.resolved_pointcloud_tasks()) or "no task: at 512 points a "
                                          "task's DP3 columns cost more than the 40 CPU-hours leave")
             + " (protocol budget rule 2, pilot entry); '–' where a column has no record."]
    figure = success_by_task_figure(args, records, labels, "Meta-World")
    md = write_results(args, "Meta-World: success rate (%)", notes, table, records, figure)
    with open(md, "a") as f:
        f.write(paired_tests_section(args, records, pairs, groups))
        f.write("\n## DP3's metric beside DP3's published numbers\n\n"
                "Per seed, the mean of the 5 best of 10 periodic evaluations (each kept checkpoint, every T/10 "
                "steps, on 20 episodes from initial states 2000000+1000·seed+i), as DP3 reports; mean over seeds with "
                "its t interval. Published: DP3 (arXiv 2403.03954) Table XVIII, mean ± std over 3 seeds, "
                "**Meta-World v2 (mujoco-py), image DP, 3000 epochs**: a reference, not a replication target. "
                f"The gaps: our column's mean over its {len(args.seeds)} seeds minus the published mean, once every "
                "seed is recorded; our DP reads the 39-D state, the published DP images.\n\n"
                + metric_table + "\n")
    displaced = displacement_records(args)
    if displaced is not None:
        with open(md, "a") as f:
            f.write(amendment_section(args, records, displaced, groups))
    if args.readme:
        write_readme_section(args, md, len(records), len(jobs))
    return md


TARGET_SUITE = "metaworld-target"  # amendment 1: absolute hand targets (``envs.external``)
DISPLACEMENTS = "DP (displacements)"  # the main table's DP on the same task, relabelled beside DP on targets


def displacement_records(args: MainArgs) -> list[dict] | None:
    """For a table on absolute targets (amendment 1): the main campaign's recorded DP evaluations of the same tasks
    on displacements, each relabelled as the target task's ``DISPLACEMENTS`` column; None for any other table."""
    targets = [t for t in args.tasks if t.partition(":")[0] == TARGET_SUITE]
    if not targets:
        return None
    bare = dataclasses.replace(args, tasks=tuple(f"metaworld:{t.partition(':')[2]}" for t in targets),
                               from_records=True, pointcloud_tasks=())
    reader, out = campaign(bare), []
    for task, col, seed, changes in main_jobs(bare):
        ev = reader.evaluate(task, col, seed, dict(changes)) if col.label == "DP" else None
        if ev is not None:
            rec = table_record(reader, task, col, seed, dict(changes), ev)
            out.append({**rec, "task": f"{TARGET_SUITE}:{task.partition(':')[2]}", "column": DISPLACEMENTS})
    return out


def amendment_section(args: MainArgs, records: list[dict], displaced: list[dict],
                      groups: list[tuple[str, list[str]]], diagnosis: str = DIAGNOSIS) -> str:
    """Amendment 1's secondary comparisons (``results/metaworld/PROTOCOL.md``) as markdown: DP on targets against
    DP on displacements (``displaced``: ``displacement_records``) on the same initial states, and steps to success
    of DP+HiPolicy against DP on targets, beside what striding gives the task's own scripted expert on targets and
    how often its demos already move the hand at the action bound (the diagnosis files in ``diagnosis``: '–' where
    they are missing)."""
    both = records + displaced
    rows = grouped_rows(args, both, [DISPLACEMENTS, "DP"], paired=[("DP", DISPLACEMENTS)], groups=groups)
    tasks = [t for _, ts in groups for t in ts]
    speed = speed_rows(args, records, args.seeds, tasks, new="DP+HiPolicy", base="DP")
    experts = strided_experts(os.path.join(diagnosis, STRIDED_EXPERTS))
    coverage = demo_coverages(diagnosis, tasks)

    def striding_cells(task: str) -> list[str]:
        """The chunked expert's steps on targets per stride, and the demos' length / steps at the bound."""
        by_stride = experts.get(task.partition(":")[2], {}).get("target", {})
        steps = [by_stride.get(s, {}).get("mean_steps") for s in ("1", "2", "3")]
        cov = coverage.get(task, {})
        return [" / ".join("–" if v is None else f"{v:.1f}" for v in steps) if by_stride else "–",
                f"{cov['mean_steps']:.1f} / {cov['mean_steps_at_bound']:.1f}" if "mean_steps_at_bound" in cov else "–"]

    for row in speed:  # per task only: the average row gets blanks
        row += striding_cells(row[0]) if row[0] in tasks else ["", ""]
    covers = steps_average_note(records, args.seeds, tasks, "DP+HiPolicy", "DP")
    return ("\n## Amendment 1, secondary: DP on absolute targets against DP on displacements\n\n"
            "The same demos, seeds and initial states; DP (displacements) is the main table's DP "
            "(`results/metaworld/main.md`, its records in `results/runs/metaworld/metaworld_<task>/`). Paired as "
            "the main table pairs its columns.\n\n"
            + markdown_table(["Task", "DP on displacements (%)", "DP on targets (%)",
                              "DP on targets − DP on displacements (points)"], rows)
            + "\n\n## Amendment 1, secondary: steps to success, DP+HiPolicy against DP (targets)\n\n"
            "Two networks per seed on the same initial states. Steps saved: per seed, 100 · mean(DP − "
            "DP+HiPolicy) / mean(DP) over the episodes both succeeded in; mean over seeds with its t interval and "
            "p. What striding can give here, from the post hoc diagnosis (`results/metaworld/diagnosis/`, not part "
            "of the protocol): *Expert chunked on targets*, the scripted expert's mean steps to success executed as "
            "a chunking policy on absolute targets at stride 1 / 2 / 3 (every s-th of its planned targets, 8 per "
            f"chunk, closed loop; `{STRIDED_EXPERTS}`); *Demo steps / at the bound*, the demos' mean length and the "
            "fewest steps in which the hand could trace their paths when every step moved its target the most "
            "the env allows (1 cm per axis: Σ_t max_i |a[t, i]| over the xyz displacements, "
            "`data.windowing.steps_at_bound`; `<task>_coverage.json`; a step that pushes the target against the "
            "workspace's edge counts as a move, so where the hand works at that edge the bound is loose), a bound on "
            "what any stride can save." + (" " + covers if covers else "") + "\n\n"
            + markdown_table(["Task", "DP SR (%)", "DP+HiPolicy SR (%)", "Success cost (points)", "DP steps",
                              "DP+HiPolicy steps", "Steps saved (%)", "Expert chunked on targets: steps at stride "
                              "1 / 2 / 3", "Demo steps / at the bound"], speed) + "\n")


# ---------------------------------------------------------------------------------------------- diagnose

STRIDE1 = "DP+HiPolicy at stride 1"  # the same network as DP+HiPolicy, entropy guidance off (w/o EG)
STRIDED_EXPERTS_COMMAND = (".venv-metaworld/bin/python -m metaworld_bridge.check_experts --tasks <the protocol's tasks> "
                           "--strides 1 2 3 --action-spaces delta target --seeds 20 --max-steps 200 --out "
                           f"{DIAGNOSIS}/{STRIDED_EXPERTS}")


def strided_experts(path: str) -> dict:
    """The per-task entries of ``check_experts``'s summary at ``path`` ({task: {action space: {stride: summary}}},
    bare task names); empty when the file is missing."""
    return read_json(path).get("tasks", {}) if os.path.exists(path) else {}


def demo_coverages(results: str, tasks) -> dict[str, dict]:
    """{task: ``demo_coverage`` of its displacement demos} from ``<results>/<bare task>_coverage.json``, for the
    ``tasks`` (full names) whose file exists."""
    paths = {t: coverage_path(results, t) for t in tasks}
    return {t: read_json(p) for t, p in paths.items() if os.path.exists(p)}


def coverage_path(results: str, task: str) -> str:
    """Where ``diagnose`` keeps ``demo_coverage`` of ``task``'s (full name) displacement demos."""
    return os.path.join(results, f"{task.partition(':')[2]}_coverage.json")


def demo_coverage(path: str, chunk) -> dict:
    """What the demos at ``path`` say about executing their strides' segments: per stride the median and quartiles
    of ``windowing.delta_segment_coverage`` (hand xyz), the share of xyz action entries at the action bound
    (|a| ≥ 0.999: the expert already moves as fast as an action can), and the demos' mean length beside the fewest
    steps in which actions within the bound trace their hand paths (``windowing.steps_at_bound``)."""
    from hipolicy_jax.data.replay_buffer import ReplayBuffer
    from hipolicy_jax.data.windowing import delta_segment_coverage, steps_at_bound

    buffer = ReplayBuffer.load(path)
    actions = np.asarray(buffer.data["action"], np.float64)
    cov = delta_segment_coverage(actions, buffer.episode_ends, chunk)
    fewest = steps_at_bound(actions, buffer.episode_ends)
    return {"data": os.path.relpath(path), "episodes": int(len(buffer.episode_ends)), "frames": int(len(actions)),
            "strides": {str(s): {"windows": int(v.size), "median": float(np.median(v)),
                                 "quartiles": [float(q) for q in np.percentile(v, [25, 75])]} for s, v in cov.items()},
            "saturated_xyz": float(np.mean(np.abs(actions[:, :3]) >= 0.999)),
            "mean_steps": float(np.mean(buffer.episode_lengths())), "mean_steps_at_bound": float(np.mean(fewest))}


def diagnose_table(args: DiagnoseArgs) -> str:
    """Per task: the demos' segment coverage (``<task>_coverage.json``) and, per seed whose DP+HiPolicy evaluation is
    recorded, its network at stride 1 on the same initial states (``runs.external.evaluate_report``, whose guided
    pass is the campaign's, kept in the run → ``<task>_<variant>_seed<k>_eval.json``); made when missing (unless
    ``--from-records``), then ``<results>/diagnose.md`` / ``.json`` / ``.png`` from those files and the records."""
    from hipolicy_jax.campaigns.report import paired_cell
    from hipolicy_jax.runs.external import evaluate_report
    from hipolicy_jax.runs.store import read_inference
    from hipolicy_jax.runs.train import finished

    camp = campaign(args)
    reader = campaign(dataclasses.replace(args, from_records=True))
    dp, hip = COLUMNS[0], COLUMNS[1]
    changes = dict(run_changes(args.budget, args.steps))
    os.makedirs(args.results, exist_ok=True)
    records, missing = [], {}
    for task in tqdm(args.tasks, desc="metaworld diagnose", unit="task", disable=not args.progress):
        bare = task.partition(":")[2]
        path = coverage_path(args.results, task)
        cfg = camp.run_config(task, hip, args.seeds[0], changes)
        displacements = task.partition(":")[0] != TARGET_SUITE  # coverage speaks of displacement actions only
        if displacements and not os.path.exists(path) and not args.from_records:
            write_json(path, demo_coverage(camp.ensure_demos(cfg, args.seeds[0]), cfg.policy.chunk))
        for seed in args.seeds:
            evs = {col: reader.evaluate(task, col, seed, changes) for col in (dp, hip)}
            rows = {col: table_record(reader, task, col, seed, changes, ev) for col, ev in evs.items() if ev}
            records += rows.values()
            guided = evs[hip]
            run_dir = camp.run_config(task, hip, seed, changes).out_dir()
            path = os.path.join(args.results, f"{bare}_{os.path.basename(os.path.dirname(run_dir))}_seed{seed}_eval.json")
            if guided is None:
                continue
            if not os.path.exists(path) and not args.from_records and finished(camp.run_config(task, hip, seed,
                                                                                                changes)):
                try:  # one process evaluates a network: another diagnose (or a campaign on the run) holds it
                    with RunLock(run_dir, CAMPAIGN_LOCK_FILE, "campaign or diagnose process",
                                 "this diagnose leaves it to that one"):
                        if not os.path.exists(path):  # that process may have just written it
                            report = evaluate_report(run_dir, read_inference(run_dir), episodes=eval_episodes(args),
                                                     seed=seed, out=os.path.join(run_dir, "eval"), log=lambda msg: None)
                            write_json(path, report)
                except RunLockedError as e:
                    print(f"[metaworld] skipped: {e}", flush=True)
            if not os.path.exists(path):
                missing.setdefault(task, []).append(seed)
                continue
            report = read_json(path)
            if report["params_sha256"] != guided["network"]["params_sha256"]:
                raise ValueError(f"{path}: evaluated network {report['params_sha256'][:12]}, but the record of "
                                 f"{task} DP+HiPolicy seed {seed} holds {guided['network']['params_sha256'][:12]}; "
                                 f"delete the file and run `python -m experiments.metaworld diagnose` again")
            plain = report["without_eg"]
            records.append({**rows[hip], "column": STRIDE1, "periodic": None, "dp3_metric": None,
                            **{k: plain[k] for k in ("success_rate", "mean_steps_success", "mean_steps",
                                                     "mean_decisions", "stride1_frac", "mean_entropy", "success",
                                                     "steps", "decisions")},
                            "eval_s": 0.0 if report["reused"]["without_eg"] else None})
    labels = [dp.label, hip.label, STRIDE1]
    pairs = [(STRIDE1, dp.label), (hip.label, STRIDE1)]
    coverage = demo_coverages(args.results, args.tasks)

    def cells(task: str) -> list[str]:
        cov = coverage.get(task, {}).get("strides", {})
        hip_recs = [r for r in records if r["task"] == task and r["column"] == hip.label]
        share = [np.mean([r.get(f"stride{s}_frac") or 0.0 for r in hip_recs]) for s in (1, 2, 3)] if hip_recs else []
        return [*(f"{cov[s]['median']:.2f}" if s in cov else "–" for s in ("2", "3")),
                f"{100 * coverage[task]['saturated_xyz']:.0f}" if task in coverage else "–",
                " / ".join(f"{100 * v:.0f}" for v in share) if hip_recs else "–"]

    experts = strided_experts(args.experts)

    def expert_cells(task: str) -> list[str]:
        by_space = experts.get(task.partition(":")[2], {})
        return [" / ".join(f"{100 * by_space[space][s]['success_rate']:.0f}" if s in by_space.get(space, {}) else "–"
                           for s in ("1", "2", "3")) for space in ("delta", "target")]

    rows = grouped_rows(args, records, labels, paired=pairs, groups=[("tasks", list(args.tasks))],
                        extra=lambda t: [*cells(t), *expert_cells(t)])
    table = markdown_table(["Task", "coverage stride 2", "coverage stride 3", "xyz at bound (%)",
                            "DP+HiPolicy strides 1 / 2 / 3 (% decisions)",
                            "expert chunked at stride 1 / 2 / 3, displacements (%)",
                            "the same, absolute targets (%)", *labels,
                            *(f"{a} − {b} (points)" for a, b in pairs)], rows)
    notes = ["**Post hoc: not part of the pre-registered protocol** (`results/metaworld/PROTOCOL.md`); its "
             "evaluations never enter the campaign's table.",
             "Coverage: a stride-s segment of Meta-World's actions (xyz moves of the hand's target, executed one "
             "per control step) moves the hand by Σ_k a[t+1+ks]; the demo moved Σ_{i<8s} a[t+1+i] over the span "
             "the segment stands for, while the gripper command follows the demo's schedule over that whole span. "
             "Coverage = the executed move projected on the demo's, median over the demos' windows "
             "(`data.windowing.delta_segment_coverage`): ~1/s means the segment lags its own gripper schedule by "
             "a factor s. With absolute targets (the MJX tasks' joint targets) a segment's last commanded target "
             "is the demo's at the end of that span (coverage 1 of the commands); the hand or joints reach it only "
             "as fast as the env moves them. "
             "'xyz at bound': share of the demos' xyz action entries at ±1, where no segment can move faster. "
             "Both are '–' on absolute hand targets (`metaworld-target:<task>`), where a segment's commanded targets "
             "end where the demo's did, and the hand, moved at most 1 cm a step towards them, may lag them.",
             "Expert chunked: the scripted expert as a chunking policy, closed loop: at each decision it runs "
             "8·s steps ahead in the simulator (then restored) and every s-th of its actions is executed, 8 per "
             "chunk; as Meta-World's displacements, or as absolute hand targets (each turned into the displacement "
             "that reaches it, at most 1 cm a step); success over the seeds of "
             f"`{os.path.relpath(args.experts)}` (`{STRIDED_EXPERTS_COMMAND}`; '–' until it is run). It is what "
             "HiPolicy's stride-s segments would execute if the network were the expert.",
             f"{STRIDE1}: each DP+HiPolicy network served again with entropy guidance off (always stride 1), on the "
             f"same {eval_episodes(args)} initial states per seed as DP and DP+HiPolicy "
             "(`python -m experiments.evaluate --checkpoint RUN`, its guided pass the campaign's, reused). "
             f"{STRIDE1} − DP compares two networks at one execution; DP+HiPolicy − {STRIDE1} is one network, "
             "guidance on vs off.", PAIRED_NOTE_CELLS]
    if len(args.tasks) > 1:
        for new, base in pairs:
            done = [t for t in args.tasks if all({r["seed"] for r in records if r["task"] == t and r["column"] == c}
                                                 >= set(args.seeds) for c in (new, base))]
            if done:
                notes.append(f"{new} − {base}, over the {len(done)} task(s) with every seed: "
                             + paired_cell(records, args.seeds, done, new, base))
    if missing:
        notes.append(f"No {STRIDE1} pass for: " + "; ".join(f"{t} seed{'s' * (len(v) > 1)} {', '.join(map(str, v))}"
                                                            for t, v in missing.items())
                     + ". A pass serves the run's checkpoint, which git does not keep: it is made on the machine "
                       "that trained the network (run this command before its run folder is gone); a retrained "
                       "network would not be the recorded one.")
    figure = success_by_task_figure(args, records, labels, "Meta-World, post hoc: DP+HiPolicy's network at stride 1")
    targets = all(t.partition(":")[0] == TARGET_SUITE for t in args.tasks)
    return write_results(args, "Meta-World diagnosis: HiPolicy's strides on "
                         + ("absolute hand targets" if targets else "displacement actions") + " (post hoc)", notes,
                         table, records, figure)


SUBCOMMANDS: dict[str, type] = {"pilot": PilotArgs, "main": MainArgs, "diagnose": DiagnoseArgs}
BUILDERS = {"pilot": pilot_table, "main": main_table, "diagnose": diagnose_table}


def build(args: MetaWorldArgs) -> str:
    return BUILDERS[type(args).TABLE](args)


__all__ = ["BUILDERS", "COLUMNS", "DiagnoseArgs", "MainArgs", "PilotArgs", "SUBCOMMANDS", "TASKS", "build",
           "choose_training_steps", "demo_coverage", "diagnose_table", "main_jobs", "main_table", "pilot_table", "protocol_tasks",
           "run_changes", "training_steps", "write_plan"]
