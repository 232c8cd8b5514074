"""``findings.md``: every paired comparison of HiPolicy with a baseline in the campaign's built tables (read from
their JSON), per task and on average with its verdict, the same-network speed claim (HiPolicy vs w/o EG), the
training-budget gaps and the verdict's t interval beside version 1's hierarchical bootstrap."""

from __future__ import annotations

import os

import numpy as np

from hipolicy_jax.evaluation import stats
from hipolicy_jax.campaigns.budgets import BUDGETS
from hipolicy_jax.campaigns.report import (ci, finding_text, interval_text, leave_one_out, markdown_table, outcomes,
                                           p_text, paired, paired_bootstrap, paired_cell, verdict_text)
from hipolicy_jax.campaigns.tables.budget import budget_gaps, budget_records
from hipolicy_jax.campaigns.tables.common import PaperArgs, results_name, table_name, table_seeds
from hipolicy_jax.campaigns.tables.registry import COLUMNS
from hipolicy_jax.runs.store import read_json


# The paired comparisons of HiPolicy with a baseline that the findings gather: (table, new column, baseline column)
# (the execution table's HiPolicy vs DP and the ablation's Hier. vs w/o Hier. are the main table's runs and
# evaluations again, so they are not counted twice). HiPolicy vs w/o EG is the one same-network comparison: one
# trained network, executed with and without entropy guidance.
FINDINGS = (("main", "DP+HiPolicy", "DP"), ("main", "DP3+HiPolicy", "DP3"), ("execution", "HiPolicy", "DP+TE"),
            ("execution", "HiPolicy", "DP+AAC"), ("execution", "HiPolicy", "w/o EG"))
VERDICTS = ("wins", "ties", "loses")


def _table_json(args: PaperArgs, t: PaperArgs) -> list[dict] | None:
    path = os.path.join(args.results, results_name(t) + ".json")
    return read_json(path)["records"] if os.path.exists(path) else None


def saved_groups(records: list[dict], seeds, task: str, new: str, base: str) -> dict[int, np.ndarray]:
    """Per seed, over the episodes both columns succeeded in: (base − new steps) / mean(base steps), whose mean is
    the fraction of ``base``'s steps to success that ``new`` saves on that network."""
    a = outcomes(records, "mean_steps_success", seeds, task=task, column=new)
    b = outcomes(records, "mean_steps_success", seeds, task=task, column=base)
    shared = set(a) & set(b)
    groups = {}
    for s, d in stats.paired_groups({k: a[k] for k in shared}, {k: b[k] for k in shared}).items():
        both = np.isfinite(d)
        if both.any():
            groups[s] = -d[both] / np.mean(b[s][both])
    return groups


def steps_tasks(records: list[dict], seeds, tasks, new: str, base: str) -> list[str]:
    """The ``tasks`` on which both columns have steps to success (a successful episode on some seed): those a
    speed table's average of steps covers, so that both steps columns average the same tasks. All ``tasks`` while
    one of them has no record of a column yet (its average is none yet: '–')."""
    def has_steps(task: str, column: str) -> bool:
        return any(np.isfinite(v).any()
                   for v in outcomes(records, "mean_steps_success", seeds, task=task, column=column).values())

    if not all(outcomes(records, "success_rate", seeds, task=t, column=c) for t in tasks for c in (base, new)):
        return list(tasks)
    return [t for t in tasks if has_steps(t, base) and has_steps(t, new)]


def steps_average_note(records: list[dict], seeds, tasks, new: str, base: str) -> str:
    """What ``speed_rows``' average row covers when a task leaves its steps: '' when both columns have steps to
    success on every task, else a sentence naming the tasks its steps and steps saved average."""
    both = steps_tasks(records, seeds, tasks, new, base)
    if len(tasks) < 2 or len(both) == len(tasks):
        return ""
    left = [t for t in tasks if t not in both]
    return (f"The average row's success columns average all {len(tasks)} tasks; its steps and steps saved average "
            f"the {len(both)} on which both {base} and {new} have steps to success ("
            + (", ".join(both) or "none") + "), leaving out " + ", ".join(left)
            + " (a column without a successful episode there).")


def speed_rows(args: PaperArgs, records: list[dict], seeds, tasks, new: str = "HiPolicy",
               base: str = "w/o EG") -> list[list[str]]:
    """The paper's speed claim, per task and on average: success of ``base`` and ``new``, the success cost, steps
    to success of each, the steps ``new`` saves (%) with its interval over seeds. By default the same network
    (HiPolicy vs w/o EG); with other columns, two networks per seed on the same initial states. The average row's
    steps and steps saved cover the tasks on which both columns have steps to success (``steps_tasks``; the caller
    says which with ``steps_average_note``), its success columns every task."""
    rows = []
    for label, ts in [(t, [t]) for t in tasks] + ([("**Average**", list(tasks))] if len(tasks) > 1 else []):
        cost = paired(records, seeds, ts, new, base)
        steps_ts = ts if len(ts) == 1 else steps_tasks(records, seeds, ts, new, base)
        groups = [saved_groups(records, seeds, t, new, base) for t in steps_ts]
        saved = (stats.NAN if not groups or not all(groups) else stats.seed_mean(groups[0]) if len(groups) == 1
                 else stats.average(groups))
        saved_text = "–" if not np.isfinite(saved.mean) else (
            f"{interval_text(saved, 100.0, signed=True)}, p={p_text(saved.p)}"
            + (f" ({'faster' if saved.low > 0 else 'slower' if saved.high < 0 else 'no difference'})"
               if np.isfinite(saved.low) else ""))
        rows.append([label,
                     ci(records, "success_rate", seeds, ts, 100.0, column=base),
                     ci(records, "success_rate", seeds, ts, 100.0, column=new),
                     "–" if cost is None else f"{interval_text(cost.diff, 100.0, signed=True)} ({verdict_text(cost)})",
                     *(ci(records, "mean_steps_success", seeds, steps_ts, column=c) if steps_ts else "–"
                       for c in (base, new)),
                     saved_text])
    return rows


def interval_comparison(records: list[dict], seeds, tasks: list[str], new: str, base: str,
                        table: str) -> list[list[str]]:
    """Per task and on average (several tasks), ``new`` − ``base`` success with the verdict's t interval over seeds
    and with version 1's hierarchical bootstrap interval, each with the verdict it gives: rows
    ``[comparison, table, task, t cell, bootstrap cell, same?, t verdict, bootstrap verdict]``; pairs with one seed
    (no t interval) are left out."""
    out = []
    for label, ts in [(task, [task]) for task in tasks] + ([("Average", tasks)] if len(tasks) > 1 else []):
        c = paired(records, seeds, ts, new, base)
        if c is None or stats.verdict(c.diff) not in VERDICTS:
            continue
        boot = paired_bootstrap(records, seeds, ts, new, base)
        tv, bv = stats.verdict(c.diff), stats.verdict(boot)
        out.append([f"{new} vs {base}", table, label, f"{interval_text(c.diff, 100.0, signed=True)} {tv}",
                    f"{interval_text(boot, 100.0, signed=True)} {bv}", "yes" if tv == bv else "**no**", tv, bv])
    return out


def interval_summary(rows: list[list[str]]) -> str:
    """One paragraph on ``interval_comparison`` rows: how often the two intervals give the same verdict and which
    cells they split."""
    split = [r for r in rows if r[6] != r[7]]
    text = (f"The same paired differences (the records of version 2, one network each) with two intervals: the t "
            f"interval over seeds, whose verdict the tables report, and version 1's hierarchical bootstrap over "
            f"seeds × episodes (`stats.hierarchical_bootstrap`, 10,000 resamples, percentile interval), which "
            f"treats the 3 trained networks as the whole population and under-covers when they differ "
            f"(`tests/test_stats.py`). They give the same verdict in {len(rows) - len(split)} of {len(rows)} cells")
    if not split:
        return text + "."
    return text + "; they split on: " + "; ".join(
        f"{r[0]}, {r[1]}, {r[2]} (t: {r[6]}, bootstrap: {r[7]})" for r in split) + "."


def findings_table(args: "CampaignArgs", tables: list[PaperArgs]) -> str | None:
    """``<results>/findings.md``: every paired comparison of ``FINDINGS`` in the built tables, one row each — per
    task the success difference in points on the shared initial states with its 95 % interval over seeds and
    verdict; the average over the table's tasks with the seed-level t test's p, the exact sign-flip p, the
    episode-level McNemar p and the average without each task in turn; the tasks won / tied / lost — then the
    same-network speed claim (HiPolicy vs w/o EG) and, when built, the training-budget rows; read from the tables'
    JSON (their records); → its path, None before any table holds a comparison."""
    rows, tally = [], dict.fromkeys(VERDICTS, 0)
    speed, budget_rows, interval_rows = [], [], []
    for t in tables:
        records = _table_json(args, t)
        if records is None:
            continue
        labels, seeds = {c.label for c in COLUMNS[table_name(t)](t)}, table_seeds(t)
        regime = "100 demos" if t.regime == "r100" else "Rlow"
        if table_name(t) == "budget":
            default = BUDGETS[t.budget].train.num_steps
            for n in t.steps:
                rs = budget_records(records, n, default)
                cells = []
                for task in args.tasks:
                    c = paired(rs, seeds, [task], "DP+HiPolicy", "DP") if task in t.tasks else None
                    cells.append("–" if c is None else finding_text(c))
                budget_rows.append([f"{n:,} steps", *cells])
            budget_rows.append([f"Gap {min(t.steps):,} → {max(t.steps):,} steps (protocol's rule)",
                                *(budget_gaps(records, seeds, task, t.steps, default)[2] if task in t.tasks else "–"
                                  for task in args.tasks)])
            continue
        for name, new, base in FINDINGS:
            if name != table_name(t) or not {new, base} <= labels:  # (DP3 columns: in R100's main table only)
                continue
            cells, counts = [], dict.fromkeys(VERDICTS, 0)
            for task in args.tasks:
                c = paired(records, seeds, [task], new, base) if task in t.tasks else None
                if c is None:
                    cells.append("–")
                    continue
                verdict = stats.verdict(c.diff)
                if verdict in counts:  # not "–" (one seed so far: a point, no test, not counted)
                    counts[verdict] += 1
                cells.append(finding_text(c))
            for v in VERDICTS:
                tally[v] += counts[v]
            avg = paired(records, seeds, list(t.tasks), new, base)
            interval_rows += interval_comparison(records, seeds, list(t.tasks), new, base,
                                                 f"{regime} ({results_name(t)})")
            rows.append([f"{new} vs {base}", f"{regime} ({results_name(t)})", *cells,
                         paired_cell(records, seeds, list(t.tasks), new, base),
                         "–" if avg is None else p_text(avg.sign_flip_p),
                         "–" if avg is None else p_text(avg.mcnemar_p),
                         leave_one_out(records, seeds, list(t.tasks), new, base),
                         "/".join(str(counts[v]) for v in VERDICTS)])
        if table_name(t) == "execution" and {"HiPolicy", "w/o EG"} <= labels:
            speed.append((regime, results_name(t), speed_rows(t, records, seeds, list(t.tasks)),
                          steps_average_note(records, seeds, list(t.tasks), "HiPolicy", "w/o EG")))
    if not rows:
        return None
    table = markdown_table(["Comparison", "Demos (table)", *args.tasks, "Average (seed-level t test)",
                            "Sign-flip p", "Episode-level McNemar p", "Leave one task out", "Tasks W/T/L"], rows)
    total = sum(tally.values())
    lines = ["# Findings: where HiPolicy wins, ties or loses", "",
             "Protocol v2 (`results/PROTOCOL.md`): the unit of evidence is the trained network. Each row is a paired "
             "comparison from one table: per task, the success difference (new − baseline) in points on the shared "
             "initial states — per seed the mean over its 100 episodes, then the mean over seeds with its 95 % t "
             "interval over seeds; **wins** / **loses** when the interval excludes 0 (the seed-level t test's "
             "p < 0.05), else **ties**. Average: the mean of the task means, its t interval (Welch) and p; the exact "
             "sign-flip p permutes the signs of the (task, seed) differences; the episode-level McNemar p treats "
             "every episode as independent and is shown for comparison with version 1 only. Leave one task out: "
             "the average without each task in turn. '–': no pair yet (see campaign_plan.md).", "",
             f"Over the {total} (comparison, task) cells: HiPolicy wins {tally['wins']}, ties {tally['ties']}, loses "
             f"{tally['loses']}.", "", table]
    for regime, name, srows, covers in speed:
        lines += ["", f"## Entropy-guided execution, same network: HiPolicy vs w/o EG, {regime} ({name})", "",
                  "One trained network per seed, executed with entropy guidance (HiPolicy) and always at stride 1 "
                  "(w/o EG) on the same initial states. The paper claims faster execution (fewer control steps) at "
                  "a small success cost. Steps saved: per seed, 100 · mean(w/o EG − HiPolicy) / mean(w/o EG) over "
                  "the episodes both succeeded in; mean over seeds with its t interval and p."
                  + (" " + covers if covers else ""), "",
                  markdown_table(["Task", "w/o EG SR (%)", "HiPolicy SR (%)", "Success cost (points)",
                                  "w/o EG steps", "HiPolicy steps", "Steps saved (%)"], srows)]
    if budget_rows:
        lines += ["", "## Training budget: DP+HiPolicy − DP (points) by training steps (budget.md)", "",
                  markdown_table(["Training", *args.tasks], budget_rows)]
    if interval_rows:
        lines += ["", "## The verdict's interval beside version 1's hierarchical bootstrap", "",
                  interval_summary(interval_rows), "",
                  markdown_table(["Comparison", "Demos (table)", "Task", "t interval over seeds (verdict)",
                                  "Hierarchical bootstrap (its verdict)", "Same verdict"],
                                 [r[:6] for r in interval_rows])]
    out = os.path.join(args.results, "findings.md")
    with open(out, "w") as f:
        f.write("\n".join(lines) + "\n")
    return out
