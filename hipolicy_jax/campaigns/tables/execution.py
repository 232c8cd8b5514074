"""The execution table (results/PROTOCOL.md (c)): the same trained runs executed as whole chunks (DP), with temporal
ensembling (DP+TE), adaptive action chunking (DP+AAC), always at stride 1 (w/o EG) and entropy-guided (HiPolicy):
success, steps to success and decisions → ``<results>/execution[_rlow].*``."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from hipolicy_jax.evaluation import stats
from hipolicy_jax.campaigns.budgets import DP
from hipolicy_jax.campaigns.campaign import Column
from hipolicy_jax.campaigns.report import ci, markdown_table, outcomes, paired_cell, stride_cell
from hipolicy_jax.campaigns.tables import common
from hipolicy_jax.campaigns.tables.common import PAIRED_NOTE, PaperArgs, table_seeds, write_results


@dataclasses.dataclass(frozen=True)
class ExecutionArgs(PaperArgs):
    """Execution strategies: DP (whole chunks), DP+TE (temporal ensembling), DP+AAC (adaptive action chunking),
    HiPolicy always at stride 1 (w/o EG) and entropy-guided (HiPolicy)."""

    TABLE: ClassVar[str] = "execution"


EXECUTION = [Column("DP", "state", DP), Column("DP+TE", "state", DP, execution="te"),
             Column("DP+AAC", "state", DP, execution="aac"), Column("w/o EG", "state", (), guided=False),
             Column("HiPolicy")]


def execution_columns(args: ExecutionArgs) -> list[Column]:
    return list(EXECUTION)


def execution_table(args: ExecutionArgs) -> str:
    records = common.collect(args, EXECUTION)
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
