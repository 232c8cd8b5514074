"""The front page's results at a glance (README.md, ``docs/glance.png``): DP against DP+HiPolicy, success and
control steps to success, as the committed tables print them — the MJX training-budget table at its longest
training (``results/budget.md``: press_button and stack_cubes, 24,000 steps) and Meta-World on absolute hand targets
(protocol amendment 1, ``results/metaworld/target/main.md``: the total average; its steps average the tasks on which
both columns have successful episodes). Every evaluation behind them executes one action per control step (``rate``
semantics, docs/execution.md).

    python -m experiments.glance            # docs/glance.png from the committed tables
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import textwrap

BUDGET_TABLE = "results/budget.md"
TARGET_TABLE = "results/metaworld/target/main.md"
BUDGET_STEPS = "24,000"  # the budget table's longest training
MJX_TASKS = ("press_button", "stack_cubes")
STEPS_SECTION = "Amendment 1, secondary: steps to success"  # target/main.md's steps table
FIGURE = "docs/glance.png"


@dataclasses.dataclass(frozen=True)
class GlanceRow:
    """One row of the glance table: the cells as the source table prints them."""

    label: str
    source: str  # the table file, relative to the repository
    dp_success: str
    hip_success: str
    difference: str  # DP+HiPolicy − DP (points), with p and verdict
    dp_steps: str
    hip_steps: str


def markdown_tables(text: str) -> list[tuple[str, list[str], list[list[str]]]]:
    """Every pipe table of ``text`` as (the last heading above it, header cells, row cells)."""
    out, heading, block = [], "", []
    for line in text.splitlines() + [""]:
        if line.startswith("|"):
            block.append([c.strip() for c in line.strip().strip("|").split("|")])
            continue
        if block:
            out.append((heading, block[0], [r for r in block[1:] if not set("".join(r)) <= set(":-")]))
            block = []
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
    return out


def parse_cell(cell: str) -> tuple[float, float, float]:
    """'98.3 [97.7, 99.0]' → (98.3, 97.7, 99.0); '100.0' → (100.0, 100.0, 100.0); '–' → NaNs."""
    m = re.match(r"^([-+]?\d+(?:\.\d+)?)(?: \[([-+]?\d+(?:\.\d+)?), ([-+]?\d+(?:\.\d+)?)\])?", cell.strip())
    if not m:
        return math.nan, math.nan, math.nan
    mean = float(m.group(1))
    return (mean, float(m.group(2)), float(m.group(3))) if m.group(2) else (mean, mean, mean)


def _row(tables, section: str, key: tuple[str, ...]) -> dict[str, str]:
    for heading, header, rows in tables:
        if heading.startswith(section):
            for row in rows:
                if tuple(row[:len(key)]) == key:
                    return dict(zip(header, row))
    raise ValueError(f"no row {key} in the table under {section!r}")


def glance_rows(root: str = ".") -> list[GlanceRow]:
    """The glance table's rows from the committed tables under ``root``."""
    with open(os.path.join(root, BUDGET_TABLE)) as f:
        budget = markdown_tables(f.read())
    rows = []
    for task in MJX_TASKS:
        r = _row(budget, "Training-budget sensitivity", (task, BUDGET_STEPS))
        rows.append(GlanceRow(f"MJX {task}, {BUDGET_STEPS} training steps", BUDGET_TABLE, r["DP SR (%)"], r["DP+HiPolicy SR (%)"],
                              r["DP+HiPolicy − DP (points)"], r["DP steps"], r["DP+HiPolicy steps"]))
    with open(os.path.join(root, TARGET_TABLE)) as f:
        target = markdown_tables(f.read())
    tasks = [r[0] for h, _, rs in target if h.startswith("Meta-World: success rate") for r in rs
             if not r[0].startswith("**")]
    success = _row(target, "Meta-World: success rate", ("**Total average**",))
    steps = _row(target, STEPS_SECTION, ("**Average**",))
    rows.append(GlanceRow(f"Meta-World, {len(tasks)} tasks on absolute hand targets", TARGET_TABLE, success["DP"], success["DP+HiPolicy"],
                          success["DP+HiPolicy − DP (points)"], steps["DP steps"], steps["DP+HiPolicy steps"]))
    return rows


def fewer_steps(row: GlanceRow) -> float:
    """How many percent fewer control steps DP+HiPolicy's successful episodes take than DP's (of the printed means)."""
    return 100.0 * (1.0 - parse_cell(row.hip_steps)[0] / parse_cell(row.dp_steps)[0])


def plot_glance(rows: list[GlanceRow], path: str) -> dict[str, dict[str, list[float]]]:
    """Success and steps to success, DP beside DP+HiPolicy per row, with the printed intervals as error bars; →
    the plotted means, {panel: {column: [per row]}}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    panels = (("success", "success rate (%)", ("dp_success", "hip_success")),
              ("steps", "control steps to success", ("dp_steps", "hip_steps")))
    groups = ["\n".join(textwrap.wrap(r.label.replace(", ", ": ", 1), 22)) for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(10.0, 3.9))
    plotted: dict[str, dict[str, list[float]]] = {}
    x = np.arange(len(rows))
    for ax, (name, ylabel, fields) in zip(axes, panels):
        plotted[name] = {}
        for i, (column, field) in enumerate(zip(("DP", "DP+HiPolicy"), fields)):
            cells = [parse_cell(getattr(r, field)) for r in rows]
            means = np.array([c[0] for c in cells])
            err = np.array([[c[0] - c[1], c[2] - c[0]] for c in cells]).T
            ax.bar(x + (i - 0.5) * 0.4, means, 0.4, yerr=np.nan_to_num(err), capsize=3, label=column)
            plotted[name][column] = [float(m) for m in means]
        ax.set_xticks(x, groups, fontsize=8)
        ax.set_ylabel(ylabel)
        ax.grid(axis="y", alpha=0.3)
    axes[1].legend(fontsize=8, loc="upper left")
    fig.suptitle("DP vs DP+HiPolicy, `rate` semantics (one action per control step); 95 % t intervals over seeds",
                 fontsize=10)
    fig.text(0.99, 0.01, "steps: mean control steps of the successful episodes (Meta-World: over the tasks both "
             "columns solve)", ha="right", va="bottom", fontsize=7)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return plotted
