"""The hyper-parameter table (results/PROTOCOL.md (e)): observation horizon L_h, chunk length L_c and number of
frequencies M around the defaults (3, 8, 3) → ``<results>/hparams[_rlow].*``."""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

from hipolicy_jax.config import PolicyConfig
from hipolicy_jax.campaigns.budgets import BUDGETS
from hipolicy_jax.campaigns.campaign import Column
from hipolicy_jax.campaigns.report import RATE_BOUNDS, bar_figure, ci, markdown_table, outcomes
from hipolicy_jax.campaigns.tables import common
from hipolicy_jax.campaigns.tables.common import PaperArgs, TaskName, table_seeds, write_results


@dataclasses.dataclass(frozen=True)
class HparamsArgs(PaperArgs):
    """Observation horizon L_h, chunk length L_c and number of frequencies M (strides 1..M)."""

    TABLE: ClassVar[str] = "hparams"

    tasks: tuple[TaskName, ...] = ("press_button",)
    rows: tuple[tuple[int, int, int], ...] = ((3, 8, 3), (1, 8, 3), (5, 8, 3), (3, 4, 3), (3, 8, 1))


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
    records = common.collect(args, columns)
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
