"""The protocol's DP-only pilot: per task, DP at 100 demos, then the Rlow candidates until one lands in [15, 85] %
→ ``<results>/pilot.{md,json}`` and ``pilot_choice.json`` (the choice to record in results/PROTOCOL.md and
``campaigns.budgets.REGIMES['rlow']``)."""

from __future__ import annotations

import dataclasses
import os
from typing import ClassVar

from tqdm.auto import tqdm

from hipolicy_jax.campaigns.budgets import DP
from hipolicy_jax.campaigns.campaign import Column, choose_low_regime, pilot_candidates
from hipolicy_jax.campaigns.report import changes_text, markdown_table
from hipolicy_jax.campaigns.tables.common import PaperArgs, campaign, eval_episodes, table_record, write_results
from hipolicy_jax.runs.store import write_json


@dataclasses.dataclass(frozen=True)
class PilotArgs(PaperArgs):
    """The protocol's DP-only pilot that chooses each task's Rlow regime (seed 0)."""

    TABLE: ClassVar[str] = "pilot"

    seeds: tuple[int, ...] = (0,)


def pilot_table(args: PilotArgs) -> str:
    """The protocol's DP-only pilot: DP (seed ``args.seeds[0]``) at 100 demos, then the Rlow candidates until one
    lands in [15, 85] %; writes ``<results>/pilot.md`` / ``.json`` with the choice per task (to be recorded in
    results/PROTOCOL.md and ``campaigns.budgets.REGIMES['rlow']`` before any HiPolicy run of that regime)."""
    camp = campaign(args)
    dp = Column("DP", "state", DP)
    seed = args.seeds[0]
    rows, records, choices = [], [], {}
    for task in tqdm(args.tasks, desc="pilot", unit="task", disable=not args.progress):
        base = camp.evaluate(task, dp, seed)
        tried = []
        if base is not None:
            records.append(table_record(camp, task, dp, seed, {}, base))
            for changes in pilot_candidates(base["success_rate"]):
                ev = camp.evaluate(task, dp, seed, changes)
                if ev is None:
                    break
                tried.append((changes, ev["success_rate"]))
                records.append(table_record(camp, task, dp, seed, changes, ev))
                if 0.15 <= ev["success_rate"] <= 0.85:
                    break
        if tried:
            choice, in_range = choose_low_regime(tried)
            choices[task] = {"run_changes": choice, "in_range": in_range}
        desc = ", ".join(f"{changes_text(c)}: {100 * sr:.0f} %" for c, sr in tried) or "–"
        chosen = changes_text(choices[task]["run_changes"]) + ("" if choices[task]["in_range"] else
                                                               " (closest to 50 %, none in range)") \
            if task in choices else "–"
        rows.append([task, "–" if base is None else f"{100 * base['success_rate']:.0f}", desc, chosen])
    table = markdown_table(["Task", "DP @ 100 demos (%)", "Candidates tried (DP success)", "Rlow"], rows)
    regimes = {t: c["run_changes"] for t, c in choices.items()}
    notes = [f"DP only (one stride), seed {seed}, {eval_episodes(args)} evaluation episodes per candidate.",
             f"Record the choice in results/PROTOCOL.md and in hipolicy_jax/campaigns/budgets.py: "
             f"`REGIMES['rlow'] = {regimes!r}`."]
    write_json(os.path.join(args.results, "pilot_choice.json"), regimes)
    return write_results(args, "DP pilot: the low-data regime per task", notes, table, records)
