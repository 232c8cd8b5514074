"""The paper's tables (results/PROTOCOL.md) as a library stage: one args dataclass a table (``SUBCOMMANDS``), one
builder a table (``BUILDERS``; ``build(args)`` → the path of its markdown), and the campaign that runs every table's
evaluations under one progress bar. ``experiments.paper`` parses the flags into these dataclasses and calls ``build``.

Each table trains and evaluates through ``campaign.Campaign`` (or reads its records with ``from_records``) and writes
``<results>/<table>[_rlow].{md,json,png}``; its cells come from ``report``. The modules:

- ``common``: what every table shares (``PaperArgs``, ``table_name``, ``command_line``, ``collect``,
  ``write_results``, ``grouped_rows``, ...);
- ``main``, ``ablation``, ``execution``, ``thresholds``, ``hparams``, ``pilot``, ``budget``, ``semantics``: one table
  each — its args class (``TABLE``: its sub-command), its columns and its builder;
- ``findings``: ``findings.md``, the paired comparisons gathered from the built tables;
- ``registry``: one line a table (args class, builder, columns);
- ``protocol``: the campaign — the protocol's tables, their jobs, the plan of what is left, then every table, the
  findings and the results page's campaign section (``--readme``) rebuilt from the records.

A new table is one module (its args class with its ``TABLE``, its columns and builder) and one line in
``registry.ENTRIES``; the campaign runs it once ``protocol.protocol_tables`` lists it.
"""

from __future__ import annotations

from hipolicy_jax.campaigns.tables.common import (PAIRED_NOTE, PAIRED_NOTE_CELLS, ObsName, PaperArgs, TaskName,
                                                  campaign, collect, column_seeds, command_line, demo_steps,
                                                  eval_episodes, grouped_rows, protocol_path, regime_text,
                                                  results_header, results_name, rows_by_group,
                                                  success_by_task_figure, table_name, table_record,
                                                  table_run_changes, table_seeds, train_args, write_results)
from hipolicy_jax.campaigns.tables.main import BASELINE_NAME, MainArgs, main_columns, main_table
from hipolicy_jax.campaigns.tables.ablation import (ABLATION, ABLATION_MCNEMAR, AblationArgs, ablation_columns,
                                                    ablation_table)
from hipolicy_jax.campaigns.tables.execution import EXECUTION, ExecutionArgs, execution_columns, execution_table
from hipolicy_jax.campaigns.tables.thresholds import PANELS, ThresholdsArgs, thresholds_columns, thresholds_table
from hipolicy_jax.campaigns.tables.hparams import HparamsArgs, hparam_changes, hparams_columns, hparams_table
from hipolicy_jax.campaigns.tables.pilot import PilotArgs, pilot_table
from hipolicy_jax.campaigns.tables.budget import (BUDGET_COLUMNS, BUDGET_MCNEMAR, BudgetArgs, budget_answer,
                                                  budget_columns, budget_gaps, budget_records, budget_table)
from hipolicy_jax.campaigns.tables.semantics import (SEMANTICS_READING, SemanticsArgs, semantics_columns,
                                                     semantics_settings, semantics_table, setting_text)
from hipolicy_jax.campaigns.tables.registry import COLUMNS, ENTRIES, TABLE_ARGS, TABLE_BUILDERS
from hipolicy_jax.campaigns.tables.findings import (FINDINGS, VERDICTS, findings_table, interval_comparison,
                                                    interval_summary, saved_groups, speed_rows, steps_average_note,
                                                    steps_tasks)
from hipolicy_jax.campaigns.tables.protocol import (CampaignArgs, campaign_jobs, campaign_shard, campaign_table,
                                                    protocol_tables, write_plan)

TABLES = ("main", "ablation", "execution", "thresholds", "hparams", "pilot", "budget", "campaign")
SUBCOMMANDS: dict[str, type] = {**TABLE_ARGS, CampaignArgs.TABLE: CampaignArgs}
BUILDERS = {**TABLE_BUILDERS, CampaignArgs.TABLE: campaign_table}


def build(args: PaperArgs) -> str:
    """Build the table ``args`` stands for (its runs trained / evaluated as needed); → its markdown file's path."""
    return BUILDERS[table_name(args)](args)


__all__ = ["ABLATION", "ABLATION_MCNEMAR", "AblationArgs", "BASELINE_NAME", "BUDGET_COLUMNS", "BUDGET_MCNEMAR",
           "BUILDERS", "BudgetArgs", "COLUMNS", "CampaignArgs", "ENTRIES", "EXECUTION", "ExecutionArgs", "FINDINGS",
           "HparamsArgs", "MainArgs", "ObsName", "PAIRED_NOTE", "PAIRED_NOTE_CELLS", "PANELS", "PaperArgs",
           "PilotArgs", "SEMANTICS_READING", "SUBCOMMANDS", "SemanticsArgs", "TABLES", "TABLE_ARGS", "TABLE_BUILDERS",
           "TaskName", "ThresholdsArgs", "VERDICTS", "ablation_columns", "ablation_table", "budget_answer",
           "budget_columns", "budget_gaps", "budget_records", "budget_table", "build", "campaign", "campaign_jobs",
           "campaign_shard", "campaign_table", "collect", "column_seeds", "command_line", "demo_steps",
           "eval_episodes", "execution_columns", "execution_table", "findings_table", "grouped_rows",
           "hparam_changes", "hparams_columns", "hparams_table", "interval_comparison", "interval_summary",
           "main_columns", "main_table", "pilot_table", "protocol_path", "protocol_tables", "regime_text",
           "results_header", "results_name", "rows_by_group", "saved_groups", "semantics_columns",
           "semantics_settings", "semantics_table", "setting_text", "speed_rows", "steps_average_note", "steps_tasks",
           "success_by_task_figure", "table_name", "table_record", "table_run_changes", "table_seeds",
           "thresholds_columns", "thresholds_table", "train_args", "write_plan", "write_results"]
