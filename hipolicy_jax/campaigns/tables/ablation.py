"""The ablation table (results/PROTOCOL.md (b)): HiPolicy's observation conditions (hierarchical / low / high),
without fusion, with the release's fusion and without the hierarchy (DP) → ``<results>/ablation[_rlow].*``."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from hipolicy_jax.campaigns.budgets import DP
from hipolicy_jax.campaigns.campaign import Column
from hipolicy_jax.campaigns.report import markdown_table
from hipolicy_jax.campaigns.tables import common
from hipolicy_jax.campaigns.tables.common import (PAIRED_NOTE_CELLS, PaperArgs, grouped_rows, success_by_task_figure,
                                                  write_results)


@dataclasses.dataclass(frozen=True)
class AblationArgs(PaperArgs):
    """Observation condition hier / low / high, w/o fusion, w/o hierarchy (one stride)."""

    TABLE: ClassVar[str] = "ablation"


ABLATION_MCNEMAR = ("The episode-level McNemar p of Hier. − w/o Hier. is in findings.md (DP+HiPolicy vs DP, Rlow: the "
                    "same networks); Hier. − Release fusion has none.")


ABLATION = [("Hier.", ()), ("Low", (("model.condition", "low"),)), ("High", (("model.condition", "high"),)),
            ("w/o Fusion", (("model.fusion", False),)), ("Release fusion", (("model.fusion_kind", "release"),)),
            ("w/o Hier.", DP)]


def ablation_columns(args: AblationArgs) -> list[Column]:
    return [Column(label, "state", changes) for label, changes in ABLATION]


def ablation_table(args: AblationArgs) -> str:
    columns = ablation_columns(args)
    records = common.collect(args, columns)
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
