"""The semantics table (results/PROTOCOL.md amendment 4, which kind of speed): the same DP and DP+HiPolicy networks
under ``rate`` and ``waypoint`` execution, with the controller unlimited and speed-limited: success, the paired
difference and the decisions / actions / control steps saved → ``<results>/semantics.{md,json}``."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from hipolicy_jax.campaigns.budgets import BUDGETS, DP
from hipolicy_jax.campaigns.campaign import Column
from hipolicy_jax.campaigns.report import (EPISODE_COUNTS, ci, interval_text, markdown_table, paired_cell,
                                           relative_count_difference)
from hipolicy_jax.campaigns.tables import common
from hipolicy_jax.campaigns.tables.common import PAIRED_NOTE_CELLS, PaperArgs, TaskName, table_seeds, write_results


@dataclasses.dataclass(frozen=True)
class SemanticsArgs(PaperArgs):
    """Which kind of speed (results/PROTOCOL.md amendment 4): DP vs DP+HiPolicy (state, 100 demos, ``steps``
    training steps) evaluated under ``rate`` and ``waypoint`` execution, with the MJX controller unlimited and
    limited to ``controller_speed`` m/s; the same networks for every setting."""

    TABLE: ClassVar[str] = "semantics"

    tasks: tuple[TaskName, ...] = ("press_button", "stack_cubes")
    steps: int = 8000
    controller_speed: float = 0.25

    def run_changes(self, task: str) -> list[dict]:
        """The runs of ``steps`` training steps (the budget's own count: no change)."""
        return [{} if self.steps == BUDGETS[self.budget].train.num_steps else {"train.num_steps": self.steps}]


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
    records = common.collect(args, columns)
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
