"""The registry of the tables: one line a table — its args class (whose ``TABLE`` is its sub-command of
``experiments.paper``), its builder (args → the path of its markdown) and the columns the campaign evaluates for it
(None: a table the campaign does not run). The package adds the campaign (``protocol``), which builds these tables.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from hipolicy_jax.campaigns.campaign import Column
from hipolicy_jax.campaigns.tables.ablation import AblationArgs, ablation_columns, ablation_table
from hipolicy_jax.campaigns.tables.budget import BudgetArgs, budget_columns, budget_table
from hipolicy_jax.campaigns.tables.common import PaperArgs
from hipolicy_jax.campaigns.tables.execution import ExecutionArgs, execution_columns, execution_table
from hipolicy_jax.campaigns.tables.hparams import HparamsArgs, hparams_columns, hparams_table
from hipolicy_jax.campaigns.tables.main import MainArgs, main_columns, main_table
from hipolicy_jax.campaigns.tables.pilot import PilotArgs, pilot_table
from hipolicy_jax.campaigns.tables.semantics import SemanticsArgs, semantics_columns, semantics_table
from hipolicy_jax.campaigns.tables.thresholds import ThresholdsArgs, thresholds_columns, thresholds_table

ENTRIES: tuple[tuple[type[PaperArgs], Callable[[Any], str], Callable[[Any], list[Column]] | None], ...] = (
    (MainArgs, main_table, main_columns),
    (AblationArgs, ablation_table, ablation_columns),
    (ExecutionArgs, execution_table, execution_columns),
    (ThresholdsArgs, thresholds_table, thresholds_columns),
    (HparamsArgs, hparams_table, hparams_columns),
    (PilotArgs, pilot_table, None),
    (BudgetArgs, budget_table, budget_columns),
    (SemanticsArgs, semantics_table, semantics_columns),
)
TABLE_ARGS: dict[str, type[PaperArgs]] = {cls.TABLE: cls for cls, _, _ in ENTRIES}
TABLE_BUILDERS: dict[str, Callable[[Any], str]] = {cls.TABLE: builder for cls, builder, _ in ENTRIES}
COLUMNS: dict[str, Callable[[Any], list[Column]]] = {cls.TABLE: columns for cls, _, columns in ENTRIES
                                                     if columns is not None}
