"""Amendment 2 of the Meta-World protocol (``results/metaworld/PROTOCOL.md``, "Amendment 2"): the release's execution
(``waypoint``), DP3's training budget (3,000 epochs at batch 128) and closed-loop thresholds, on the campaign's
machinery (``campaign``: columns, records, cost model, ``work_off``; ``report`` / ``evaluation.stats``: cells).

- ``pilot2``: DP (state, seed 0) on bin-picking and hand-insert (absolute targets) trained T_task steps at batch 128,
  its checkpoints at T/4, T/2, 3T/4 and T evaluated by the main metric (100 episodes, 500-step limit, ``waypoint``)
  and its final network once more under ``rate``; the plateau rule chooses f, the measured rates feed the budget
  rule (``budget_rule``) → ``<results>/pilot2.md`` / ``pilot_choice.json``, and T_task of the five tasks →
  ``t_task.json``.
- ``amendment2``: DP and DP+HiPolicy (state, seeds 0, 1, 2, f·T_task steps at batch 128) on the arm's tasks in order,
  every network evaluated as the amendment lists (``columns``: the primary ``waypoint`` with closed-loop thresholds,
  and the secondary evaluations of the same networks), then ``<results>/amendment2.md`` / ``.json`` from the records
  alone. Arm ``a``: absolute hand targets (``metaworld-target:``); arm ``b``: Meta-World's displacements with summed
  deltas (``metaworld:``; training sums a stride's deltas from the buffer's ``action_kinds``).

Run dirs and records are the Meta-World budget's (``results/runs/metaworld/<suite>_<task>/state/...``) under variant
names that carry the action kinds, the batch and the steps (``dp_kinds-aaaa_batchsize128_t13913``), so no older
campaign's run or record is reused by mistake.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import ClassVar, Literal, NamedTuple

import numpy as np
from tqdm.auto import tqdm

from hipolicy_jax.campaigns import budgets as budgets_lib
from hipolicy_jax.campaigns.budgets import BUDGETS, DP
from hipolicy_jax.campaigns.campaign import (CLOSED_LOOP_EPISODES, EXTERNAL_EVAL_SEED, SUCCESS_MARGIN, Column,
                                             CostModel, Job, Periodic,
                                             work_off)
from hipolicy_jax.campaigns.metaworld import MetaWorldArgs, choose_training_steps, pending_lines, write_plan_file
from hipolicy_jax.campaigns.report import (COUNT_BOUNDS, EPISODE_COUNTS, cpu_s, ci, interval_text, markdown_table,
                                           p_text, paired, relative_count_difference)
from hipolicy_jax.campaigns.tables import campaign, eval_episodes, table_record, write_results
from hipolicy_jax.envs import external
from hipolicy_jax.evaluation import calibration, stats
from hipolicy_jax.runs.store import read_json, write_json

RESULTS = "results/metaworld/amendment2"
STEPS_FILE = os.path.join(RESULTS, "t_task.json")  # T_task per task (bare name), written by pilot2
# Arm A's tasks, in the amendment's order (rules on committed files; PROTOCOL.md "Amendment 2")
TASKS = ("bin-picking", "stick-push", "coffee-pull", "hand-insert", "pick-out-of-hole")
PILOT_TASKS = ("bin-picking", "hand-insert")
SUITES = {"a": "metaworld-target", "b": "metaworld"}  # arm → external suite
EPOCHS, BATCH = 3000, 128  # DP3's published budget
FRACTIONS = (0.25, 0.5, 0.75, 1.0)  # the pilot's candidates for f
MAX_STEPS = 500  # the evaluations' step limit (control steps): Meta-World's own
BUDGET_HOURS = {"a": 80.0, "b": 20.0}
MIN_TASKS = {"a": 3, "b": 1}
KEEP_BOUND = -0.10  # the reading rule: DP+HiPolicy keeps DP's success when the average's lower end is above this
EVAL_EPISODES = 100

# Column labels: the primary pair and the secondary evaluations of the same networks
DP_LABEL, HIP_LABEL = "DP", "DP+HiPolicy"
DP_RATE, HIP_RATE = "DP (rate)", "DP+HiPolicy (rate)"
HIP_DEMOS = "DP+HiPolicy (demo thresholds)"
HIP_SUCCESS = "DP+HiPolicy (success rule)"
HIP_STRIDE1 = "DP+HiPolicy at stride 1"
NO_PERIODIC = Periodic(0, EXTERNAL_EVAL_SEED, ())  # amendment 2 has no periodic (DP3-metric) evaluations


def full_name(task: str, arm: str) -> str:
    """``bin-picking`` → ``metaworld-target:bin-picking`` (arm a) or ``metaworld:bin-picking`` (arm b); a full name is
    kept."""
    return task if ":" in task else f"{SUITES[arm]}:{task}"


def suite_kinds(task: str) -> tuple[str, ...]:
    """The action kinds of ``task``'s suite (``envs.external``): what its demo buffers record and its runs train
    with (declared in the columns, so the variant name carries them)."""
    suite = external.SUITES[task.partition(":")[0]]
    return tuple(suite.action_kinds or ("absolute",) * suite.action_dim)


class Columns(NamedTuple):
    """The amendment's columns on one suite: the primary pair, then the secondary evaluations of the same networks
    (DP's own secondary is ``rate``; a single-stride network has no thresholds, so DP's ``waypoint`` evaluation is
    the base of the secondary comparisons 2-4)."""

    dp: Column
    hip: Column
    dp_rate: Column
    hip_rate: Column
    hip_demos: Column
    hip_success: Column
    hip_stride1: Column

    def secondary(self) -> tuple[Column, ...]:
        return self.dp_rate, self.hip_rate, self.hip_demos, self.hip_success, self.hip_stride1


def columns(task: str) -> Columns:
    """``Columns`` of ``task``'s suite: ``waypoint`` at the 500-step limit, DP+HiPolicy at closed-loop thresholds
    (10 / 70 percentiles of its stride-1 entropies on 50 calibration episodes); the action kinds declared."""
    kinds = (("chunk.action_kinds", suite_kinds(task)),)
    dp = Column(DP_LABEL, "state", DP + kinds, semantics="waypoint", max_steps=MAX_STEPS)
    hip = Column(HIP_LABEL, "state", kinds, semantics="waypoint", max_steps=MAX_STEPS, calibration="rollouts")
    return Columns(dp, hip, dp._replace(label=DP_RATE, semantics="rate"),
                   hip._replace(label=HIP_RATE, semantics="rate"),
                   hip._replace(label=HIP_DEMOS, calibration="demos"),
                   hip._replace(label=HIP_SUCCESS, calibration="success"),
                   hip._replace(label=HIP_STRIDE1, guided=False, calibration="demos"))


# (new, base, section title, what it compares): the primary comparison first
COMPARISONS = (
    (HIP_LABEL, DP_LABEL, "Primary: DP+HiPolicy − DP under `waypoint`, closed-loop thresholds",
     "Thresholds at the 10th / 70th percentiles of the network's own stride-1 entropies on 50 calibration episodes "
     "(initial states 3000000+1000·seed+i), rolled out under `waypoint`"),
    (HIP_RATE, DP_RATE, "Secondary 1: the same under `rate`",
     "Both columns under `rate` (one control step an action); DP+HiPolicy's closed-loop thresholds calibrated under "
     "`rate` on the same 50 calibration episodes"),
    (HIP_DEMOS, DP_LABEL, "Secondary 2: thresholds from the held-out demo (version 1's) under `waypoint`",
     "DP+HiPolicy at the 10th / 70th percentiles of its held-out demo's entropies (the run's `calibration.json`)"),
    (HIP_SUCCESS, DP_LABEL, "Secondary 3: the success-constrained rule under `waypoint`",
     f"The most aggressive candidate of `calibration.percentile_ladder(3)` whose success on the 50 calibration "
     f"episodes is within {100 * SUCCESS_MARGIN:g} points of stride 1's on them"),
    (HIP_STRIDE1, DP_LABEL, "Secondary 4: DP+HiPolicy always at stride 1 under `waypoint`",
     "The DP+HiPolicy network without entropy guidance: two networks at one execution"),
)
HIP_COLUMNS = (HIP_LABEL, HIP_RATE, HIP_DEMOS, HIP_SUCCESS, HIP_STRIDE1)


# -------------------------------------------------------------------------------------------- training length


def training_windows(frames: int, episodes: int, val_ratio: float) -> float:
    """W: the training windows of a run on a buffer of ``episodes`` demos and ``frames`` frames, one per frame of
    its training demos (``data.dataset.split_episodes`` holds ``max(round(val_ratio · E), 1)`` out, chosen by the
    run's seed). T_task is one number per task, so W is the expectation over which demos are held out (each demo
    equally likely): frames · (E − held out) / E."""
    if episodes < 2 or frames < episodes:
        raise ValueError(f"episodes: a training length needs >= 2 demos of >= 1 frame each, got {episodes} demos "
                         f"of {frames} frames")
    held = min(max(int(round(val_ratio * episodes)), 1 if val_ratio > 0 else 0), episodes - 1)
    return frames * (episodes - held) / episodes


def task_steps(windows: float, epochs: int = EPOCHS, batch: int = BATCH) -> int:
    """T_task = round(epochs · W / batch) (half up): ``epochs`` passes over W windows at ``batch`` a step."""
    if windows <= 0 or epochs < 1 or batch < 1:
        raise ValueError(f"windows: need W > 0, epochs >= 1, batch >= 1; got {windows}, {epochs}, {batch}")
    return max(int(math.floor(epochs * windows / batch + 0.5)), 1)


def fraction_steps(total: int) -> tuple[int, ...]:
    """The steps of the four pilot fractions of ``total`` = T_task: (q, 2q, 3q, T) with q = T // 4, the pilot's
    checkpoint interval (so the pilot's checkpoint of fraction f and a run of f·T_task train the same steps)."""
    if total < 4:
        raise ValueError(f"steps: T_task must be >= 4 to have four fractions, got {total}")
    q = total // 4
    return q, 2 * q, 3 * q, total


def steps_at(total: int, fraction: float) -> int:
    """f·T_task as ``fraction_steps`` counts it; ``ValueError`` naming the field for a fraction not in FRACTIONS."""
    if fraction not in FRACTIONS:
        raise ValueError(f"fraction: must be one of {list(FRACTIONS)}, got {fraction}")
    return fraction_steps(total)[FRACTIONS.index(fraction)]


def choose_fraction(rates: dict[float, list[float]], tolerance: float = 0.05) -> float:
    """The plateau rule: the smallest fraction whose mean success over the pilot's tasks is within ``tolerance`` of
    the best fraction's ({fraction: [success per task]}; ``metaworld.choose_training_steps`` on fractions)."""
    return choose_training_steps(rates, tolerance)


def budget_phrase(fraction: float) -> str:
    """How the tables name the training length: "DP3's budget" at f = 1, else "the plateau, f·T"."""
    return "DP3's budget" if fraction == 1.0 else f"the plateau, {fraction:g}·T"


# ------------------------------------------------------------------------------------------------- budget rule

LADDER = len(calibration.percentile_ladder(3))  # the success rule's candidates (7)


def episodes_per_network() -> dict[str, dict[str, int]]:
    """Evaluation episodes per network and semantics, as ``columns`` makes them: DP: 100 under each semantics;
    DP+HiPolicy under ``waypoint``: 50 calibration episodes at stride 1, the primary 100, demo thresholds 100, the
    success rule's candidates (7 × 50) and stride 1 100; under ``rate``: 50 calibration + 100."""
    c, e = CLOSED_LOOP_EPISODES, EVAL_EPISODES
    return {DP_LABEL: {"waypoint": e, "rate": e},
            HIP_LABEL: {"waypoint": c + e + e + LADDER * c + e, "rate": c + e}}


class Rates(NamedTuple):
    """The pilot's measured rates (CPU-seconds) and DP+HiPolicy's cost relative to DP's."""

    train_s_per_step: float  # DP at batch 128
    eval_s_per_100: dict  # {semantics: DP's CPU-s per 100 episodes}
    hip_train_factor: float = 1.0  # DP+HiPolicy's train step / DP's
    hip_eval_factor: float = 1.0  # DP+HiPolicy's evaluation episode / DP's


def network_costs(steps: int, rates: Rates) -> dict[str, float]:
    """CPU-seconds of one DP and one DP+HiPolicy network trained ``steps`` and evaluated as the amendment lists
    (``episodes_per_network``)."""
    eps = episodes_per_network()
    evals = {col: sum(n / 100 * rates.eval_s_per_100[sem] for sem, n in eps[col].items()) for col in eps}
    return {DP_LABEL: rates.train_s_per_step * steps + evals[DP_LABEL],
            HIP_LABEL: rates.train_s_per_step * rates.hip_train_factor * steps
            + rates.hip_eval_factor * evals[HIP_LABEL]}


def task_cost(steps: int, rates: Rates, seeds: int = 3) -> float:
    """A task's two columns × ``seeds`` networks at ``steps`` training steps."""
    return seeds * sum(network_costs(steps, rates).values())


def fitting_prefix(costs: list[float], left_s: float, min_tasks: int) -> int | None:
    """All tasks when their costs fit ``left_s``, else the largest K >= ``min_tasks`` whose first K fit; None when
    not even ``min_tasks`` fit."""
    fits = [k for k in range(min_tasks, len(costs) + 1) if sum(costs[:k]) <= left_s + 1e-9]
    return max(fits) if fits else None


def budget_rule(*, left_s: float, totals: list[int], fraction: float, rates: Rates, seeds: int = 3,
                min_tasks: int = 3) -> dict:
    """Amendment 2's budget rule: with ``totals`` the T_task of the arm's tasks in order, all tasks if their cost at
    ``fraction``·T_task fits ``left_s`` (what the pilot left), else the largest K >= ``min_tasks`` that fits; else f
    drops to the next smaller pilot fraction and the rule is applied again. → {fraction, tasks (K), task_cost_s (at
    the chosen fraction), left_s, tried: [(fraction, K or None)]}; fraction and tasks None when nothing fits."""
    if fraction not in FRACTIONS:
        raise ValueError(f"fraction: must be one of {list(FRACTIONS)}, got {fraction}")
    tried = []
    for f in sorted((x for x in FRACTIONS if x <= fraction), reverse=True):
        costs = [task_cost(steps_at(t, f), rates, seeds) for t in totals]
        k = fitting_prefix(costs, left_s, min_tasks)
        tried.append((f, k))
        if k is not None:
            return {"fraction": f, "tasks": k, "task_cost_s": costs, "left_s": left_s, "tried": tried}
    return {"fraction": None, "tasks": None, "task_cost_s": [], "left_s": left_s, "tried": tried}


def arm_b_tasks(costs: list[float], budget_s: float) -> int:
    """Arm B's task count: the first tasks of arm A's list that fit ``budget_s`` (at least one)."""
    return fitting_prefix(costs, budget_s, 1) or 1


# ------------------------------------------------------------------------------------------------ reading rule


def reading_rule(diff: stats.Estimate, bound: float = KEEP_BOUND) -> str:
    """The amendment's reading of DP+HiPolicy − DP (a fraction, its 95 % interval): 'keeps' when the lower end is
    above ``bound`` (−10 points); 'loses' when the upper end is below 0 and it does not keep; otherwise
    'inconclusive'; both when both hold ('keeps; significant loss'); '–' without an interval (one seed)."""
    if not (math.isfinite(diff.low) and math.isfinite(diff.high)):
        return "–"
    keeps, below = diff.low > bound, diff.high < 0
    if keeps:
        return "keeps; significant loss" if below else "keeps"
    return "loses" if below else "inconclusive"


# ------------------------------------------------------------------------------------------------------ args


@dataclasses.dataclass(frozen=True)
class Amendment2Args(MetaWorldArgs):
    """Amendment 2's main runs (results/metaworld/PROTOCOL.md): DP and DP+HiPolicy (state, seeds 0, 1, 2, f·T_task
    steps at batch 128) on the arm's tasks in order, each network evaluated under `waypoint` at closed-loop
    thresholds and the secondary settings; the tables rebuilt from the records."""

    TABLE: ClassVar[str] = "amendment2"
    arm: Literal["a", "b"] = "a"  # a: absolute hand targets (metaworld-target:); b: summed deltas (metaworld:)
    results: str = ""  # '' = results/metaworld/amendment2 (arm a), results/metaworld/amendment2/arm_b (arm b)
    steps_file: str = STEPS_FILE  # T_task per task (pilot2 writes it; missing tasks are computed from their buffers)
    fraction: float | None = None  # f (default: budgets.METAWORLD_A2_FRACTION, the pilot entry's)
    until: str = ""  # HH:MM or YYYY-MM-DD HH:MM: start only the jobs estimated to end before it
    plan: bool = False  # write what is left (<results>/plan.md) with its estimated cost, and stop
    # end by rebuilding the table from the records; --no-tables writes only the plan of what is left, so that a
    # process narrowed to some tasks (one per core: --tasks) leaves the full table alone
    tables: bool = True

    def __post_init__(self):
        object.__setattr__(self, "results", self.results or (RESULTS if self.arm == "a"
                                                             else os.path.join(RESULTS, "arm_b")))
        tasks = self.tasks or self.default_tasks()
        object.__setattr__(self, "tasks", tuple(full_name(t, self.arm) for t in tasks))
        for t in self.tasks:
            if t.partition(":")[0] != SUITES[self.arm]:
                raise ValueError(f"tasks: arm {self.arm} runs on {SUITES[self.arm]}:<task>, got {t}")
        if self.fraction is not None and self.fraction not in FRACTIONS:
            raise ValueError(f"fraction: must be one of {list(FRACTIONS)}, got {self.fraction}")

    def default_tasks(self) -> tuple[str, ...]:
        count = budgets_lib.METAWORLD_A2_TASKS if self.arm == "a" else budgets_lib.METAWORLD_A2_B_TASKS
        if count is None and self.arm == "b":
            return ()
        return TASKS[:count or len(TASKS)]

    def resolved_fraction(self) -> float:
        f = self.fraction if self.fraction is not None else budgets_lib.METAWORLD_A2_FRACTION
        if f is None:
            raise ValueError("fraction: amendment 2's training length f is not fixed yet; run its pilot (python -m "
                             "experiments.metaworld pilot2), record f in results/metaworld/PROTOCOL.md and "
                             "hipolicy_jax/campaigns/budgets.py METAWORLD_A2_FRACTION (or pass --fraction)")
        return f


@dataclasses.dataclass(frozen=True)
class Pilot2Args(Amendment2Args):
    """Amendment 2's DP pilot: DP (state, seed 0) on bin-picking and hand-insert (absolute targets) trained T_task
    steps at batch 128, checkpoints at T/4, T/2, 3T/4, T evaluated on 100 episodes under `waypoint` (500-step limit),
    the final network also under `rate`; the plateau rule's f, the measured rates and the budget rule."""

    TABLE: ClassVar[str] = "pilot2"
    seeds: tuple[int, ...] = (0,)
    budget_hours: float = BUDGET_HOURS["a"]
    # DP+HiPolicy's cost relative to DP's, for the budget rule's estimate (None: measured from amendment 1's records,
    # the same tasks at batch 64 under rate: its train step, and its evaluation episode at the 200-step limit)
    hipolicy_train_factor: float | None = None
    hipolicy_eval_factor: float | None = None

    def default_tasks(self) -> tuple[str, ...]:
        return PILOT_TASKS


# ------------------------------------------------------------------------------------------- T_task per task


def budget_epochs(budget: str) -> tuple[int, int]:
    """(epochs, batch) of T_task on ``budget``: DP3's 3,000 at 128 on the Meta-World budget; the smoke budget's one
    epoch at its own batch (a test's few demos hold fewer than 128 windows)."""
    return (EPOCHS, BATCH) if budget == "metaworld" else (1, BUDGETS[budget].train.batch_size)


def task_total(args: Amendment2Args, task: str, *, collect: bool) -> int:
    """T_task of ``task`` (any suite: keyed by its bare name, as both arms' demos are the same expert episodes):
    from ``args.steps_file``, else computed from the task's demo buffer (collected first when ``collect``) and added
    to the file; ``ValueError`` naming the file when neither is there."""
    bare = task.partition(":")[2]
    table = read_json(args.steps_file) if os.path.exists(args.steps_file) else {}
    entry = table.get("tasks", {}).get(bare)
    epochs, batch = budget_epochs(args.budget)
    if entry is not None and (entry.get("epochs"), entry.get("batch")) == (epochs, batch):
        return int(entry["T"])
    camp = campaign(args)
    cfg = camp.run_config(task, columns(task).dp, args.seeds[0])
    path = cfg.data_path()
    if collect and not os.path.exists(path):
        camp.ensure_demos(cfg, args.seeds[0])
    if not os.path.exists(path):
        raise ValueError(f"steps_file: {args.steps_file} has no T_task for {bare} and its demos ({path}) are not "
                         f"here; run `python -m experiments.metaworld pilot2` (it writes every task's T_task)")
    from hipolicy_jax.data.replay_buffer import ReplayBuffer

    buffer = ReplayBuffer.load(path)
    frames, episodes = int(buffer.num_frames), int(buffer.num_episodes)
    windows = training_windows(frames, episodes, cfg.val_ratio)
    total = task_steps(windows, epochs, batch)
    table.setdefault("tasks", {})[bare] = {"frames": frames, "episodes": episodes, "windows": windows,
                                           "epochs": epochs, "batch": batch, "T": total,
                                           "data": os.path.relpath(path)}
    table["rule"] = ("T = round(epochs · W / batch), W = frames · (E − held out) / E: one training window per "
                     "frame of the run's training demos, in expectation over the held-out demo")
    write_json(args.steps_file, table)
    return total


def run_changes(args: Amendment2Args, task: str, *, collect: bool = False) -> dict:
    """A main run's changes to the budget: batch 128 and f·T_task steps (the smoke budget: its batch)."""
    _, batch = budget_epochs(args.budget)
    return {"train.batch_size": batch,
            "train.num_steps": steps_at(task_total(args, task, collect=collect), args.resolved_fraction())}


def pilot_changes(args: Amendment2Args, task: str, *, collect: bool = False) -> dict:
    """The pilot run's changes: batch 128, T_task steps, a checkpoint every T_task // 4 kept."""
    _, batch = budget_epochs(args.budget)
    total = task_total(args, task, collect=collect)
    return {"train.batch_size": batch, "train.num_steps": total, "train.ckpt_every": fraction_steps(total)[0]}


# ---------------------------------------------------------------------------------------------------- jobs


def amendment2_jobs(args: Amendment2Args, *, collect: bool = False) -> list[Job]:
    """The amendment's order: task by task in the arm's order; per task DP's primary evaluations (seeds
    ascending), DP+HiPolicy's, then the secondary evaluations of the same networks (DP under rate, DP+HiPolicy
    under rate, with demo thresholds, with the success rule, at stride 1), so a run's checkpoint is evaluated
    completely while it is at hand."""
    if not args.tasks:
        raise ValueError("tasks: arm b's tasks are not fixed yet (budgets.METAWORLD_A2_B_TASKS, the dated entry "
                         "after arm A's runs); pass --tasks")
    jobs = []
    for task in args.tasks:
        changes = tuple(sorted(run_changes(args, task, collect=collect).items()))
        cols = columns(task)
        for col in (cols.dp, cols.hip, *cols.secondary()):
            jobs += [Job(task, col, seed, changes) for seed in args.seeds]
    return jobs


def run_of(args: Amendment2Args):
    camp = campaign(args)
    return lambda j: camp.run_config(j.task, j.col, j.seed, dict(j.changes)).out_dir()


# ----------------------------------------------------------------------------------------------- the tables


def _record(records: list[dict], task: str, column: str, seed: int) -> dict | None:
    hit = [r for r in records if r["task"] == task and r["column"] == column and r["seed"] == seed]
    return hit[0] if hit else None


COUNTS = tuple(EPISODE_COUNTS.items())  # (record field, name): decisions, actions, control steps


def solved_means(records: list[dict], seeds, task: str, new: str, base: str, field: str
                 ) -> dict[int, tuple[float, float]]:
    """Per seed with both columns recorded: (base's, new's) mean ``field`` per episode (decisions, actions or
    control steps) over the initial states both solved; seeds where no state was solved by both are left out."""
    out = {}
    for s in seeds:
        a, b = _record(records, task, new, s), _record(records, task, base, s)
        if a is None or b is None:
            continue
        both = np.asarray(a["success"], bool) & np.asarray(b["success"], bool)
        if both.any():
            out[s] = (float(np.mean(np.asarray(b[field], float)[both])),
                      float(np.mean(np.asarray(a[field], float)[both])))
    return out


def savings_rows(records: list[dict], seeds, tasks: list[str], new: str, base: str) -> list[list[str]]:
    """Per task and averaged: base's and new's mean decisions, actions and control steps per episode on the
    initial states both solved (mean over seeds with its t interval) and new's relative difference (%), mean over
    seeds with its t interval (``report.relative_count_difference``; the average: Welch over the tasks); '–' until
    every task has a seed."""
    rows = []
    for label, ts in [(t, [t]) for t in tasks] + ([("**Average**", list(tasks))] if len(tasks) > 1 else []):
        row = [label]
        for field, _ in COUNTS:
            per_task = [solved_means(records, seeds, t, new, base, field) for t in ts]
            if not all(per_task):
                row += ["–", "–", "–"]
                continue
            for i in (0, 1):
                groups = [{s: [v[i]] for s, v in m.items()} for m in per_task]
                iv = (stats.seed_mean(groups[0], bounds=COUNT_BOUNDS) if len(groups) == 1
                      else stats.average(groups, bounds=COUNT_BOUNDS))
                row.append(interval_text(iv))
            row.append(interval_text(relative_count_difference(records, seeds, ts, new, base, field), 100.0,
                                     signed=True))
        rows.append(row)
    return rows


def success_rows(records: list[dict], seeds, tasks: list[str], new: str, base: str) -> list[list[str]]:
    """Per task and averaged: success of base and new (%) with seed-level t intervals, new − base on the shared
    initial states (points; t interval over seeds, its p and the sign-flip p; the average: Welch over the tasks'
    seed means) and the amendment's reading of it (``reading_rule``)."""
    rows = []
    for label, ts in [(t, [t]) for t in tasks] + ([("**Average**", list(tasks))] if len(tasks) > 1 else []):
        c = paired(records, seeds, ts, new, base)
        diff = "–" if c is None else interval_text(c.diff, 100.0, signed=True)
        rows.append([label, ci(records, "success_rate", seeds, ts, 100.0, column=base),
                     ci(records, "success_rate", seeds, ts, 100.0, column=new), diff,
                     "–" if c is None else p_text(c.p), "–" if c is None else p_text(c.sign_flip_p),
                     "–" if c is None else reading_rule(c.diff)])
    return rows


def mix_text(mix: dict | None) -> str:
    """{stride: fraction} → '10 / 60 / 30' (% of decisions at strides 1 / 2 / 3)."""
    if not mix:
        return "–"
    return " / ".join(f"{100 * float(mix[k]):.0f}" for k in sorted(mix, key=int))


def mix_rows(records: list[dict], seeds, tasks: list[str]) -> list[list[str]]:
    """Per task, per DP+HiPolicy cell: the intended stride mix of its thresholds (the calibration's, mean over
    seeds) and the achieved one (the evaluation's share of decisions per stride, mean over seeds)."""
    rows = []
    for task in tasks:
        row = [task]
        for column in HIP_COLUMNS:
            recs = [r for s in seeds if (r := _record(records, task, column, s)) is not None]
            intended = [(r.get("calibration") or {}).get("intended_mix") for r in recs]
            intended = [m for m in intended if m]
            strides = {k[6:-5] for r in recs for k in r if k.startswith("stride") and k.endswith("_frac")}
            strides |= {k for m in intended for k in m}  # a stride none of its decisions took: 0
            achieved = {k: float(np.mean([r.get(f"stride{k}_frac") or 0.0 for r in recs])) for k in strides}
            want = {k: float(np.mean([m[k] for m in intended])) for k in intended[0]} if intended else None
            row.append(f"{mix_text(want)} → {mix_text(achieved)}" if recs else "–")
        rows.append(row)
    return rows


RATE_COLUMNS = (DP_RATE, HIP_RATE)


def clipped_rows(records: list[dict], seeds, tasks: list[str]) -> list[list[str]]:
    """Per task and averaged, per ``rate`` column: the share of executed actions the bridge's per-step bound
    clipped (%; per network Σ clipped / Σ actions, mean over seeds with its t interval; the average: Welch over the
    tasks); '–' where the records do not count them."""
    def groups(task: str, column: str) -> dict[int, list[float]]:
        out = {}
        for s in seeds:
            r = _record(records, task, column, s)
            if r is not None and r.get("clipped") is not None and sum(r["actions"]) > 0:
                out[s] = [sum(r["clipped"]) / sum(r["actions"])]
        return out

    rows = []
    for label, ts in [(t, [t]) for t in tasks] + ([("**Average**", list(tasks))] if len(tasks) > 1 else []):
        row = [label]
        for column in RATE_COLUMNS:
            g = [groups(t, column) for t in ts]
            iv = (stats.NAN if not all(g) else stats.seed_mean(g[0], bounds=(0.0, 1.0)) if len(g) == 1
                  else stats.average(g, bounds=(0.0, 1.0)))
            row.append(interval_text(iv, 100.0))
        rows.append(row)
    return rows


def steps_cell(args: Amendment2Args, task: str, fraction: float) -> str:
    try:
        total = task_total(args, task, collect=False)
    except ValueError:
        return "–"
    return f"{steps_at(total, fraction)} of {total}"


def table_records(args: Amendment2Args, jobs: list[Job]) -> tuple[list[dict], int]:
    """The jobs' recorded evaluations as table rows (``tables.table_record``) and how many jobs have none."""
    reader = campaign(dataclasses.replace(args, from_records=True))
    records, missing = [], 0
    for task, col, seed, changes in jobs:
        ev = reader.evaluate(task, col, seed, dict(changes))
        if ev is None:
            missing += 1
            continue
        records.append(table_record(reader, task, col, seed, dict(changes), ev))
    return records, missing


def build_tables(args: Amendment2Args, records: list[dict], jobs: int, missing: int) -> str:
    """``<results>/amendment2.md`` / ``.json`` from the table rows: the primary comparison (success, the paired
    difference and its reading, the savings), each secondary comparison in its own section, the stride mixes;
    interim while evaluations are missing."""
    f = args.resolved_fraction()
    tasks = list(args.tasks)
    seeds = tuple(args.seeds)
    arm = ("absolute hand targets (`metaworld-target:`)" if args.arm == "a"
           else "displacements with summed deltas (`metaworld:`)")
    interim = missing > 0
    success_header = ["Task", "{base} (%)", "{new} (%)", "{new} − {base} (points)", "t-test p", "sign-flip p",
                      "reading"]
    savings_header = ["Task", *(h for _, name in COUNTS for h in (f"{{base}} {name}", f"{{new}} {name}",
                                                                  f"{{new}} vs {{base}}: {name} (%)"))]
    sections = []
    for i, (new, base, title, what) in enumerate(COMPARISONS):
        fmt = dict(new=new, base=base)
        body = (f"\n## {title}\n\n{what}. Success on the same {eval_episodes(args)} initial states per seed "
                f"(1000000+1000·seed+i); the paired difference's t interval over seeds (95 %), its p, the sign-flip "
                f"p over the (task, seed) differences; the average row: Welch over the tasks' seed means. Reading "
                f"rule (PROTOCOL.md, amendment 2): *keeps* when the lower end is above {100 * KEEP_BOUND:+.0f} "
                f"points, *loses* when the upper end is below 0 and it does not keep, else *inconclusive* (both "
                f"written when both hold); the rule is fixed for the average"
                + (", the primary comparison" if i == 0 else "") + "; per task it is shown for information.\n\n"
                + markdown_table([h.format(**fmt) for h in success_header],
                                 success_rows(records, seeds, tasks, new, base))
                + f"\n\nWhat it saves: per network, on the initial states both columns of the seed solved, the mean "
                  f"decisions, actions and control steps (physical time) per episode (mean over seeds with its t "
                  f"interval), and {new}'s relative difference to {base}, mean over seeds with its t interval "
                  f"(negative: fewer).\n\n"
                + markdown_table([h.format(**fmt) for h in savings_header],
                                 savings_rows(records, seeds, tasks, new, base)) + "\n")
        sections.append(body)
    mix = ("\n## Stride mix: intended → achieved\n\nPer DP+HiPolicy cell, the share of decisions (%) at strides "
           "1 / 2 / 3 that its thresholds intend (the calibration's percentiles: 10 / 70 → 10 / 60 / 30; the success "
           "rule's chosen candidate; stride 1: all at stride 1), then the share its evaluation achieved; means over "
           "the recorded seeds.\n\n"
           + markdown_table(["Task", *HIP_COLUMNS], mix_rows(records, seeds, tasks)) + "\n")
    clipped = ("\n## Clipped actions under `rate`\n\nThe share of executed actions (%) whose move Meta-World's 1 cm "
               "bound cut (the bridge's `clipped` count), per network Σ clipped / Σ actions; mean over seeds with its "
               "t interval.\n\n" + markdown_table(["Task", *(f"{c} clipped (%)" for c in RATE_COLUMNS)],
                                                   clipped_rows(records, seeds, tasks)) + "\n")
    steps = [f"{t}: {steps_cell(args, t, f)}" for t in tasks]
    notes = [f"Arm {args.arm.upper()}: {arm}. DP and DP+HiPolicy (state), seeds {', '.join(map(str, seeds))}; "
             f"training {budget_phrase(f)} (f = {f:g} of T_task = round(3000 · W / 128) steps at batch 128, W the "
             f"task's training windows): " + "; ".join(steps) + ".",
             f"Evaluation: {eval_episodes(args)} episodes per network from initial states 1000000+1000·seed+i (the "
             f"same for both columns), step limit {MAX_STEPS} control steps, N = 16, DDIM 10, whole-chunk execution, "
             f"`waypoint` at the bridge's defaults (4 cm, 5 control steps per unit of stride) unless a section says "
             f"`rate`."]
    if args.arm == "b" and len(tasks) < len(TASKS):
        notes.append(f"Arm B runs on {len(tasks)} of arm A's {len(TASKS)} tasks: the first that fit its "
                     f"{BUDGET_HOURS['b']:g} CPU-hours (PROTOCOL.md, amendment 2).")
    notes.append("The budget line above is the Meta-World budget's (version 1); this amendment changes it as said "
                 "here: batch 128, f·T_task steps, no periodic (DP3-metric) evaluations.")
    new, base = COMPARISONS[0][:2]
    primary = paired(records, seeds, tasks, new, base) if tasks else None
    if primary is not None:
        notes.append(f"**Primary comparison** ({new} − {base}, `waypoint`, averaged over the {len(tasks)} task(s)): "
                     f"{interval_text(primary.diff, 100.0, signed=True)} points → **{reading_rule(primary.diff)}**"
                     + (" (interim)" if interim else "") + ".")
    if interim:
        notes.insert(0, f"**Interim: {jobs - missing} of {jobs} evaluations recorded**; a cell averages the seeds it "
                        f"has, and an average row needs every task; the table is final when every evaluation is "
                        f"recorded (`python -m experiments.metaworld amendment2 --plan` lists what is left).")
    title = "Meta-World amendment 2, arm " + args.arm.upper() + ": DP+HiPolicy against DP" + (
        " (interim)" if interim else "")
    return write_results(args, title, notes, "".join(sections).lstrip("\n") + mix + clipped, records)


def amendment2_table(args: Amendment2Args) -> str:
    """Run what is pending (unless ``--from-records``; ``--plan`` only writes what is left), then write
    ``<results>/amendment2.md`` / ``.json`` from the records alone."""
    live = not args.from_records and not args.plan
    jobs = amendment2_jobs(args, collect=live)
    if not args.from_records:
        camp = campaign(args)
        model = CostModel(args.records, args.runs)
        costs = model.estimate(camp, jobs)
        if args.plan:
            return write_plan(args, costs)
        work_off(camp, costs, run_of(args), until=args.until, progress=args.progress, periodic=NO_PERIODIC)
        if not args.tables:
            return write_plan(args, CostModel(args.records, args.runs).estimate(camp, jobs))
    records, missing = table_records(args, jobs)
    return build_tables(args, records, len(jobs), missing)


def pilot_rates(path: str) -> dict | None:
    """The pilot's measured rates and factors (``pilot_choice.json``'s ``rates``), None before the pilot."""
    return read_json(path).get("rates") if os.path.exists(path) else None


def write_plan(args: Amendment2Args, costs: list[dict]) -> str:
    """``<results>/plan.md``: the pending jobs with the cost model's estimates (CPU-seconds from the records), and
    the budget rule's estimate of the arm (the pilot's rates) beside what the arm's records spent so far."""
    pending = [c for c in costs if not c["done"]]
    known = [c["seconds"] for c in pending if c["seconds"] is not None]
    f = args.resolved_fraction()
    lines = [f"# Meta-World amendment 2, arm {args.arm.upper()}: what is left", "",
             f"{len(pending)} of {len(costs)} evaluations pending, {sum(c['trains'] for c in pending)} runs to train "
             f"(f = {f:g}, batch 128, tasks: {', '.join(args.tasks)}); the cost model's estimate "
             f"{sum(known) / 3600:.1f} CPU-hours for the {len(known)} with a measured rate"
             + (f" ({len(pending) - len(known)} not yet measured)" if len(known) < len(pending) else "")
             + " (it knows no closed-loop calibration: the budget rule's estimate below counts it)."]
    rates = pilot_rates(os.path.join(os.path.dirname(args.steps_file), "pilot_choice.json"))  # pilot2's, beside
    if rates:
        r = Rates(rates["train_s_per_step"], rates["eval_s_per_100"], rates["hip_train_factor"],
                  rates["hip_eval_factor"])
        per = [task_cost(steps_at(task_total(args, t, collect=False), f), r, len(args.seeds)) for t in args.tasks]
        lines += ["", "The budget rule's estimate (the pilot's rates, `pilot_choice.json`): "
                  + "; ".join(f"{t}: {c / 3600:.1f} h" for t, c in zip(args.tasks, per))
                  + f"; {sum(per) / 3600:.1f} CPU-hours in all."]
    lines += ["", *pending_lines(pending, costs)]
    return write_plan_file(args.results, lines)


# ------------------------------------------------------------------------------------------------------ pilot


def amendment1_factors(records: str) -> dict[str, float | None]:
    """DP+HiPolicy's cost relative to DP's from amendment 1's records (``<records>/metaworld/metaworld-target_*/
    state/{dp,hipolicy}_t4000``): the medians of its training CPU-s per step and of its main evaluation's CPU-s,
    each over DP's; None where a side has no record."""
    import glob

    def rows(variant: str) -> tuple[list[float], list[float]]:
        train, evals = [], []
        for path in glob.glob(os.path.join(records, "metaworld", "metaworld-target_*", "state", variant, "seed*.json")):
            rec = read_json(path)
            t = rec.get("training") or {}
            if t.get("steps") and t.get("wall_time_s"):
                train.append(cpu_s(t["wall_time_s"], t.get("cpu_cores"), t.get("cpu_time_s")) / t["steps"])
            for ev in rec.get("evaluations", {}).values():
                if ev.get("main_eval_s"):
                    evals.append(cpu_s(ev["main_eval_s"], ev.get("cpu_cores"), ev.get("main_eval_cpu_s")))
        return train, evals

    (dp_t, dp_e), (hip_t, hip_e) = rows("dp_t4000"), rows("hipolicy_t4000")
    ratio = (lambda a, b: float(np.median(a) / np.median(b)) if a and b else None)
    return {"hip_train_factor": ratio(hip_t, dp_t), "hip_eval_factor": ratio(hip_e, dp_e)}


def pilot2_table(args: Pilot2Args) -> str:
    """Per pilot task, DP's success at T/4, T/2, 3T/4 and T (``waypoint``), the plateau rule's f, the measured rates
    (CPU-s per training step at batch 128, per 100 episodes under each semantics), T_task of the arm's five tasks
    and the budget rule → ``<results>/pilot2.md`` / ``.json``, ``pilot_choice.json``, ``t_task.json``."""
    camp = campaign(args)
    seed = args.seeds[0]
    live = not args.from_records
    # every arm-A task's T_task (its demos collected when missing), for the budget rule; a smoke run: its own tasks
    totals = {t: None for t in (TASKS if args.budget == "metaworld" else [t.partition(":")[2] for t in args.tasks])}
    for t in totals:
        try:
            totals[t] = task_total(args, full_name(t, "a"), collect=live)
        except ValueError:
            if live:
                raise
    rates: dict[float, list[float]] = {}
    rows, records, costs = [], [], []
    for task in tqdm(args.tasks, desc="metaworld pilot2", unit="task", disable=not args.progress):
        cols = columns(task)
        total = totals.get(task.partition(":")[2]) or task_total(args, task, collect=live)
        changes = pilot_changes(args, task, collect=live)
        at = fraction_steps(total)
        ev = camp.evaluate(task, cols.dp, seed, changes,
                           periodic=Periodic(eval_episodes(args), EXTERNAL_EVAL_SEED, at[:-1]))
        rate_ev = camp.evaluate(task, cols.dp_rate, seed, changes, periodic=NO_PERIODIC) if ev is not None else None
        if ev is None:
            rows.append([task, str(total), *(["–"] * len(at)), "–"])
            continue
        record = camp.record(task, cols.dp, seed, changes)
        records.append(table_record(camp, task, cols.dp, seed, changes, ev))
        by_step = {c["step"]: c["success_rate"] for c in ev["periodic"]["checkpoints"]}
        by_step[int(record["checkpoint_step"])] = ev["success_rate"]
        for f, n in zip(FRACTIONS, at):
            if n in by_step:
                rates.setdefault(f, []).append(by_step[n])
        rows.append([task, str(total), *(f"{100 * by_step[n]:.0f}" if n in by_step else "–" for n in at),
                     "–" if rate_ev is None else f"{100 * rate_ev['success_rate']:.0f}"])
        training = record.get("training") or {}
        waypoint = [cpu_s(ev["main_eval_s"], ev.get("cpu_cores"), ev.get("main_eval_cpu_s"))] + [
            cpu_s(c["eval_s"], c.get("cpu_cores"), c.get("eval_cpu_s")) for c in ev["periodic"]["checkpoints"]]
        cost = {"task": task, "train_cpu_s_per_step": cpu_s(training.get("wall_time_s") or 0.0,
                                                            training.get("cpu_cores"), training.get("cpu_time_s"))
                / max(training.get("steps") or 1, 1),
                "eval_cpu_s_per_100": {"waypoint": float(np.median(waypoint)) * 100 / eval_episodes(args)}}
        if rate_ev is not None:
            records.append(table_record(camp, task, cols.dp_rate, seed, changes, rate_ev))
            cost["eval_cpu_s_per_100"]["rate"] = (cpu_s(rate_ev["eval_s"], rate_ev.get("cpu_cores"),
                                                        rate_ev.get("eval_cpu_s")) * 100 / eval_episodes(args))
        costs.append(cost)
    complete = bool(rates) and all(len(r) == len(args.tasks) for r in rates.values()) and len(rates) == 4
    chosen = choose_fraction(rates) if complete else None
    found = amendment1_factors(args.records)
    factors = {"hip_train_factor": args.hipolicy_train_factor or found["hip_train_factor"] or 1.0,
               "hip_eval_factor": args.hipolicy_eval_factor or found["hip_eval_factor"] or 1.0}
    factor_source = ("given" if args.hipolicy_train_factor or args.hipolicy_eval_factor
                     else "amendment 1's records, batch 64, `rate`, 200-step limit" if all(found.values())
                     else "no amendment-1 record here: 1")
    measured = None
    rule = None
    spent = sum(cpu_s(r.get("eval_s") or 0.0, r.get("cpu_cores"), r.get("eval_cpu_s")) for r in records) + sum(
        {r["run"]: cpu_s(r.get("training_s") or 0.0, r.get("training_cores"), r.get("training_cpu_s"))
         for r in records}.values())
    if costs and all("rate" in c["eval_cpu_s_per_100"] for c in costs):
        measured = {"train_s_per_step": float(np.median([c["train_cpu_s_per_step"] for c in costs])),
                    "eval_s_per_100": {s: float(np.median([c["eval_cpu_s_per_100"][s] for c in costs]))
                                       for s in ("waypoint", "rate")}, **factors}
    if chosen is not None and measured is not None and all(totals.values()):
        rule = budget_rule(left_s=args.budget_hours * 3600 - spent, totals=list(totals.values()),
                           fraction=chosen, rates=Rates(**measured), seeds=3,
                           min_tasks=min(MIN_TASKS["a"], len(totals)))
    rows.append(["mean", "", *(f"{100 * np.mean(rates[f]):.1f}" if f in rates else "–" for f in FRACTIONS), ""])
    table = markdown_table(["Task", "T_task", *(f"DP @ {f:g}·T (%)" for f in FRACTIONS), "DP @ T under rate (%)"],
                           rows)
    notes = [f"DP only (one stride), seed {seed}, one run per task trained T_task steps at batch 128 with a "
             f"checkpoint every T_task // 4; each checkpoint evaluated on {eval_episodes(args)} episodes (initial "
             f"states {EXTERNAL_EVAL_SEED + 1000 * seed}+i) under `waypoint`, step limit {MAX_STEPS}; the final "
             f"network also under `rate`.",
             "T_task = round(3000 · W / 128), W = frames · (E − 1) / E of the task's 11-demo buffer (one window "
             "per frame of the 10 training demos, in expectation over the held-out one): "
             + "; ".join(f"{t}: {'–' if v is None else v}" for t, v in totals.items()) + ".",
             "Plateau rule: f = the smallest of 1/4, 1/2, 3/4, 1 whose mean success over the two tasks is within 5 "
             "points of the best." + (f" **f = {chosen:g}** ({budget_phrase(chosen)})." if chosen is not None
                                      else " Not every checkpoint is evaluated yet."),
             "Measured rates (CPU-seconds, process CPU time where recorded): " + ("; ".join(
                 f"{c['task']}: training {c['train_cpu_s_per_step']:.3f} s/step at batch 128, evaluation "
                 + ", ".join(f"{v:.0f} s per 100 episodes under `{k}`" for k, v in c["eval_cpu_s_per_100"].items())
                 for c in costs) or "–") + ".",
             f"DP+HiPolicy relative to DP (the budget rule's estimate): train step × "
             f"{factors['hip_train_factor']:.2f}, evaluation episode × {factors['hip_eval_factor']:.2f} "
             f"({factor_source})."]
    if rule is not None:
        if rule["tasks"] is None:
            notes.append(f"Budget rule ({args.budget_hours:g} CPU-hours, the pilot's {spent / 3600:.1f} h spent): not "
                         f"even {MIN_TASKS['a']} tasks fit at f = 1/4.")
        else:
            notes.append(f"Budget rule ({args.budget_hours:g} CPU-hours, the pilot's {spent / 3600:.1f} h spent, "
                         f"{rule['left_s'] / 3600:.1f} h left): per task "
                         + ", ".join(f"{c / 3600:.1f} h" for c in rule["task_cost_s"])
                         + f" at f = {rule['fraction']:g} → **the first {rule['tasks']} tasks** ("
                         + ", ".join(TASKS[:rule["tasks"]]) + f"), **f = {rule['fraction']:g}**"
                         + (f" (lowered from {chosen:g})" if rule["fraction"] != chosen else "") + ".")
    arm_b = None
    if rule is not None and rule["fraction"] is not None:  # arm B's count at these rates (fixed after arm A's runs)
        costs_b = [task_cost(steps_at(n, rule["fraction"]), Rates(**measured)) for n in totals.values()]
        arm_b = {"tasks": arm_b_tasks(costs_b, BUDGET_HOURS["b"] * 3600), "task_cost_s": costs_b}
        notes.append(f"Arm B at these rates (an estimate; its dated entry after arm A's runs fixes it): the first "
                     f"**{arm_b['tasks']}** task(s) fit {BUDGET_HOURS['b']:g} CPU-hours at f = {rule['fraction']:g}.")
    os.makedirs(args.results, exist_ok=True)
    write_json(os.path.join(args.results, "pilot_choice.json"),
               {"fraction": chosen, "success": {str(k): v for k, v in rates.items()}, "T_task": totals,
                "costs": costs, "rates": measured, "spent_s": spent, "budget_rule": rule, "arm_b": arm_b})
    return write_results(args, "Meta-World amendment 2: DP pilot (plateau rule and budget rule)", notes, table,
                         records)


SUBCOMMANDS: dict[str, type] = {"pilot2": Pilot2Args, "amendment2": Amendment2Args}
BUILDERS = {"pilot2": pilot2_table, "amendment2": amendment2_table}

__all__ = ["Amendment2Args", "BUILDERS", "COMPARISONS", "Columns", "FRACTIONS", "PILOT_TASKS", "Pilot2Args", "Rates",
           "SUBCOMMANDS", "TASKS", "amendment1_factors", "amendment2_jobs", "amendment2_table", "arm_b_tasks",
           "budget_rule", "build_tables", "choose_fraction", "columns", "episodes_per_network", "fitting_prefix",
           "fraction_steps", "network_costs", "pilot2_table", "reading_rule", "run_changes", "savings_rows",
           "solved_means", "steps_at", "success_rows", "task_cost", "task_steps", "task_total", "training_windows"]
