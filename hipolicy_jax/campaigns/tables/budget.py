"""The training-budget table (results/PROTOCOL.md v2): DP vs DP+HiPolicy (state, 100 demos) trained for several
step counts, and the protocol's answer whether the gap shrinks, holds or grows → ``<results>/budget.{md,json,png}``;
``findings`` reads its gaps too."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from hipolicy_jax.evaluation import stats
from hipolicy_jax.campaigns.budgets import BUDGETS, DP
from hipolicy_jax.campaigns.campaign import Column
from hipolicy_jax.campaigns.report import (COUNT_BOUNDS, RATE_BOUNDS, ci, gap_trend, interval_text, markdown_table,
                                           outcomes, paired, paired_cell)
from hipolicy_jax.campaigns.tables import common
from hipolicy_jax.campaigns.tables.common import PAIRED_NOTE_CELLS, PaperArgs, TaskName, table_seeds, write_results


@dataclasses.dataclass(frozen=True)
class BudgetArgs(PaperArgs):
    """Training-budget sensitivity (results/PROTOCOL.md v2): DP vs DP+HiPolicy (state, 100 demos) trained for
    several step counts; the budget's own count reuses the main table's runs."""

    TABLE: ClassVar[str] = "budget"

    tasks: tuple[TaskName, ...] = ("press_button", "stack_cubes")
    steps: tuple[int, ...] = (2000, 8000, 24000)

    def run_changes(self, task: str) -> list[dict]:
        """One set of run-level changes per step count (the budget's own count: none)."""
        default = BUDGETS[self.budget].train.num_steps
        return [{} if n == default else {"train.num_steps": n} for n in self.steps]


BUDGET_MCNEMAR = ("The episode-level McNemar p of the 2,000-step rows is in findings.md (DP+HiPolicy vs DP, 100 demos: "
                  "the same networks); the longer trainings have none.")


BUDGET_COLUMNS = (Column("DP", "state", DP), Column("DP+HiPolicy"))


def budget_columns(args: BudgetArgs) -> list[Column]:
    return list(BUDGET_COLUMNS)


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
    records = common.collect(args, list(BUDGET_COLUMNS))
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
