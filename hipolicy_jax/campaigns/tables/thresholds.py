"""The thresholds table (results/PROTOCOL.md (d)): entropy-guided execution with its thresholds at several
percentile pairs of the held-out demo entropies, and always at stride 1 → ``<results>/thresholds[_rlow].*``."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from hipolicy_jax.campaigns.campaign import Column
from hipolicy_jax.campaigns.report import RATE_BOUNDS, bar_figure, ci, markdown_table, outcomes, stride_cell
from hipolicy_jax.campaigns.tables import common
from hipolicy_jax.campaigns.tables.common import PaperArgs, TaskName, table_seeds, write_results


@dataclasses.dataclass(frozen=True)
class ThresholdsArgs(PaperArgs):
    """Entropy thresholds at several percentile pairs of held-out demo entropies."""

    TABLE: ClassVar[str] = "thresholds"

    tasks: tuple[TaskName, ...] = ("press_button",)
    pairs: tuple[tuple[float, float], ...] = ((10.0, 70.0), (40.0, 90.0), (3.0, 40.0))


PANELS = (("success rate (%)", "success_rate", 100.0), ("steps (successful)", "mean_steps_success", 1.0))


def thresholds_columns(args: ThresholdsArgs) -> list[Column]:
    return [Column(f"p{a:g}/p{b:g}", percentiles=(a, b)) for a, b in args.pairs] + \
        [Column("always stride 1", guided=False)]


def thresholds_table(args: ThresholdsArgs) -> str:
    columns = thresholds_columns(args)
    records = common.collect(args, columns)
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
