"""Cells, tables and figures from campaign records (``campaign.Campaign`` evaluations, one dict per (task, seed,
column)): per-episode outcomes, 95 % t intervals over seeds (one value per trained network, ``evaluation.stats``),
paired comparisons on the shared initial states with the seed-level and episode-level tests, the cost of the runs,
markdown tables and bar charts. Pure functions of the records; ``tables`` builds the paper's tables with them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from hipolicy_jax.evaluation import stats
from hipolicy_jax.runs.records import same_network

def mean_std(values, scale: float = 1.0, digits: int = 1) -> str:
    """'m ± s' (sample std over seeds) of the finite values, 'm' for one value, '–' for none."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], np.float64) * scale
    if v.size == 0:
        return "–"
    if v.size == 1:
        return f"{v[0]:.{digits}f}"
    return f"{v.mean():.{digits}f} ± {v.std(ddof=1):.{digits}f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A GitHub markdown table: the first column left-aligned, the others right-aligned."""
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join([":---"] + ["---:"] * (len(header) - 1)) + " |"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _matching(records: list[dict], seed: int, match: dict) -> dict | None:
    hit = [r for r in records if r["seed"] == seed and all(r.get(k) == v for k, v in match.items())]
    return hit[0] if hit else None


def values(records: list[dict], metric: str, seeds, **match) -> list[float]:
    """Per-seed ``metric`` of the records matching ``match`` (NaN where a seed is missing)."""
    out = []
    for s in seeds:
        r = _matching(records, s, match)
        v = r.get(metric) if r else None
        out.append(np.nan if v is None else float(v))
    return out


def outcomes(records: list[dict], metric: str, seeds, **match) -> dict[int, np.ndarray]:
    """Per seed, the per-episode outcomes behind ``metric`` of the matching records: success (0/1) for
    ``success_rate``, the steps of the successful episodes (NaN for failures) for ``mean_steps_success``, the
    decisions per episode for ``mean_decisions``; the per-seed value itself where a record has no episodes."""
    out = {}
    for s in seeds:
        r = _matching(records, s, match)
        if r is None:
            continue
        if "success" in r and metric in ("success_rate", "mean_steps_success", "mean_decisions"):
            success = np.asarray(r["success"], np.float64)
            if metric == "success_rate":
                out[s] = success
            elif metric == "mean_steps_success":
                out[s] = np.where(success > 0, np.asarray(r["steps"], np.float64), np.nan)
            elif "decisions" in r:
                out[s] = np.asarray(r["decisions"], np.float64)
        if s not in out and r.get(metric) is not None:
            out[s] = np.asarray([r[metric]], np.float64)
    return out


RATE_BOUNDS = (0.0, 1.0)  # a success rate's range: its intervals are clipped to it
DIFF_BOUNDS = (-1.0, 1.0)  # a difference of two success rates
RATES = ("success_rate", "dp3_metric")  # DP3's metric: a mean of success rates
COUNT_BOUNDS = (0.0, math.inf)  # steps, decisions, actions: never below 0
COUNTS = ("mean_steps_success", "mean_steps", "mean_decisions", "mean_actions_per_decision")


def interval_text(iv: stats.Estimate, scale: float = 1.0, digits: int = 1, signed: bool = False) -> str:
    """'m [lo, hi]' (a 95 % interval; '+m [+lo, +hi]' with ``signed``, for differences), 'm' when it has no width
    or none (one seed), '–' when undefined."""
    if not np.isfinite(iv.mean):
        return "–"
    m, lo, hi = (x * scale for x in (iv.mean, iv.low, iv.high))
    fmt = f"{'+' if signed else ''}.{digits}f"
    if lo == hi or not (np.isfinite(lo) and np.isfinite(hi)):
        return f"{m:{fmt}}"
    return f"{m:{fmt}} [{lo:{fmt}}, {hi:{fmt}}]"


def ci(records: list[dict], metric: str, seeds, tasks, scale: float = 1.0, **match) -> str:
    """The cell of ``metric`` over ``tasks`` (one task: its seeds × episodes; several: the task average)."""
    groups = [outcomes(records, metric, seeds, task=t, **match) for t in tasks]
    if len(groups) > 1 and not all(groups):
        return "–"  # an average over some of the tasks is not the tasks' average
    bounds = RATE_BOUNDS if metric in RATES else COUNT_BOUNDS if metric in COUNTS else None
    iv = stats.seed_mean(groups[0], bounds=bounds) if len(groups) == 1 else stats.average(groups, bounds=bounds)
    return interval_text(iv, scale)


EPISODE_COUNTS = {"decisions": "decisions", "actions": "actions", "steps": "control steps"}


def relative_count_difference(records: list[dict], seeds, tasks, new: str, base: str, count: str) -> stats.Estimate:
    """``new``'s relative difference to ``base`` in a per-episode ``count`` (``EPISODE_COUNTS``: decisions, actions
    executed, control steps) on the initial states both networks of a seed solved: per seed, mean(new) / mean(base)
    − 1 over those episodes (one value per pair of networks); the mean over seeds with its t interval (one task) or
    the Welch average over ``tasks``. A record from before actions were counted executed one action per control
    step (``rate``): its actions are its steps. NaN where no seed has a shared success."""
    if count not in EPISODE_COUNTS:
        raise ValueError(f"count: one of {sorted(EPISODE_COUNTS)}, got {count!r}")
    per_task = []
    for task in tasks:
        groups = {}
        for s in seeds:
            a, b = (_matching(records, s, {"task": task, "column": c}) for c in (new, base))
            if a is None or b is None or "success" not in a or "success" not in b:
                continue
            both = np.asarray(a["success"], bool) & np.asarray(b["success"], bool)
            if both.any():
                x, y = (np.asarray(r.get(count, r["steps"]), np.float64)[both] for r in (a, b))
                groups[s] = np.asarray([x.mean() / y.mean() - 1.0])
        per_task.append(groups)
    if len(per_task) == 1:
        return stats.seed_mean(per_task[0])
    return stats.average(per_task) if all(per_task) else stats.NAN


def check_one_network(records: list[dict], seeds, task: str, new: str, base: str) -> None:
    """Refuse to pair two evaluations of one run made on different networks (a run retrained between them):
    ``ValueError`` naming the run. Evaluations of two runs (DP vs DP+HiPolicy) are two networks by design."""
    for s in seeds:
        a, b = _matching(records, s, {"task": task, "column": new}), _matching(records, s, {"task": task,
                                                                                           "column": base})
        if (a and b and a.get("run") and a.get("run") == b.get("run") and (a.get("network") or b.get("network"))
                and not same_network(a.get("network"), b.get("network"))):
            raise ValueError(f"{a.get('run')}: '{new}' and '{base}' were evaluated on different networks "
                             f"({a.get('network')} vs {b.get('network')}); re-evaluate the run so that its record "
                             f"holds one network")


class Paired(NamedTuple):
    """A paired comparison of two columns on the shared initial states (success, or another metric)."""

    diff: stats.Estimate  # new − base (a fraction for success): mean over seeds (tasks), t interval, seed-level p
    mcnemar_p: float  # the exact McNemar test's two-sided p over the (seed, episode) pairs: episode-level
    sign_flip_p: float  # exact sign-flip permutation p over the (task, seed) differences
    per_task: tuple  # per task: its ``stats.Estimate`` (for leave-one-task-out lines)

    @property
    def p(self) -> float:
        """The verdict's p: the seed-level t test."""
        return self.diff.p


def _paired_outcomes(records: list[dict], seeds, tasks, new: str, base: str, metric: str):
    """(per task ``new``'s and ``base``'s outcomes, per task the per-episode differences on the seeds both have);
    the differences None while a task has no pair. Refuses evaluations of different networks within one run."""
    for t in tasks:
        check_one_network(records, seeds, t, new, base)
    a = [outcomes(records, metric, seeds, task=t, column=new) for t in tasks]
    b = [outcomes(records, metric, seeds, task=t, column=base) for t in tasks]
    diffs = []
    for x, y in zip(a, b):
        shared = sorted(set(x) & set(y))
        if shared and all(x[s].size == y[s].size > 1 for s in shared):
            diffs.append(stats.paired_groups({s: x[s] for s in shared}, {s: y[s] for s in shared}))
    return a, b, (diffs if len(diffs) == len(tasks) else None)


def paired(records: list[dict], seeds, tasks, new: str, base: str, metric: str = "success_rate") -> Paired | None:
    """``new`` − ``base`` pooled over ``tasks`` (each task's seeds both columns have, episode by episode; for
    ``mean_steps_success`` the episodes both succeeded in); None while a task has no pair."""
    a, b, diffs = _paired_outcomes(records, seeds, tasks, new, base, metric)
    if diffs is None:  # a task without a pair: no pooled comparison over these tasks yet
        return None
    bounds = DIFF_BOUNDS if metric == "success_rate" else None
    per_task = tuple(stats.seed_mean(d, bounds=bounds) for d in diffs)
    iv = per_task[0] if len(diffs) == 1 else stats.average(diffs, bounds=bounds)
    p = math.nan
    if metric == "success_rate":
        pooled_a = {(i, s): v for i, x in enumerate(a) for s, v in x.items()}
        pooled_b = {(i, s): v for i, y in enumerate(b) for s, v in y.items()}
        _, _, p = stats.mcnemar_exact({k: v > 0 for k, v in pooled_a.items()},
                                      {k: v > 0 for k, v in pooled_b.items()})
    return Paired(iv, p, stats.sign_flip_p(diffs), per_task)


def paired_bootstrap(records: list[dict], seeds, tasks, new: str, base: str) -> stats.Estimate | None:
    """``new`` − ``base`` success pooled over ``tasks`` as ``paired`` pairs it, with version 1's hierarchical
    bootstrap interval (``stats.hierarchical_bootstrap``) instead of the t interval; None while a task has no
    pair."""
    _, _, diffs = _paired_outcomes(records, seeds, tasks, new, base, "success_rate")
    return None if diffs is None else stats.hierarchical_bootstrap(diffs)


def verdict_text(c: Paired) -> str:
    """The protocol's verdict of a paired comparison: 'wins' / 'ties' / 'loses' (the seed-level interval)."""
    return stats.verdict(c.diff)


def finding_text(c: Paired) -> str:
    """One task's paired cell of findings.md: 'Δ [lo, hi] wins / ties / loses', or 'Δ (1 seed: no test)' while one
    seed is paired (no interval, so no verdict)."""
    verdict = verdict_text(c)
    if verdict == "–":
        return f"{interval_text(c.diff, 100.0, signed=True)} ({c.diff.seeds} seed: no test)"
    return f"{interval_text(c.diff, 100.0, signed=True)} {verdict}"


def p_text(p: float) -> str:
    """A p-value to 2 significant digits; '–' for NaN (no test); '<1e-300' for 0.0, a p that underflowed a float
    (an exact test's p is never 0)."""
    if not np.isfinite(p):
        return "–"
    return "<1e-300" if p == 0.0 else f"{p:.2g}"


def paired_cell(records: list[dict], seeds, tasks, new: str, base: str) -> str:
    """``new`` − ``base`` success in points on the shared initial states: 'Δ [lo, hi], p=… (wins / ties / loses)'
    with the t interval over seeds and the seed-level t test's p, pooled over ``tasks``; '–' without a pair."""
    c = paired(records, seeds, tasks, new, base)
    if c is None:
        return "–"
    if not np.isfinite(c.p):
        why = f"{c.diff.seeds} seed" if len(tasks) == 1 else "a task has 1 seed"
        return f"{interval_text(c.diff, 100.0, signed=True)} ({why}: no test)"
    return f"{interval_text(c.diff, 100.0, signed=True)}, p={p_text(c.p)} ({verdict_text(c)})"


def gap_trend(first: Paired | None, last: Paired | None) -> str:
    """Whether a paired gap 'shrinks', 'grows' or 'holds' from ``first`` (e.g. the budget's training length) to
    ``last`` (the longest), by the rule ``results/PROTOCOL.md`` fixed before the training-budget runs: it shrinks or
    grows when ``last``'s t interval over seeds excludes ``first``'s point estimate (by whether ``last``'s mean is
    nearer 0 than ``first``'s), else it holds; '–' while either has no pair or ``last`` has no interval (1 seed)."""
    if first is None or last is None or not (np.isfinite(last.diff.low) and np.isfinite(last.diff.high)):
        return "–"
    if last.diff.low <= first.diff.mean <= last.diff.high:
        return "holds"
    return "shrinks" if abs(last.diff.mean) < abs(first.diff.mean) else "grows"


def leave_one_out(records: list[dict], seeds, tasks, new: str, base: str, scale: float = 100.0,
                  metric: str = "success_rate") -> str:
    """The pooled comparison without each task in turn: 'w/o press_button +2.7 [lo, hi]; w/o ...'."""
    if len(tasks) < 3:
        return "–"
    parts = []
    for t in tasks:
        c = paired(records, seeds, [x for x in tasks if x != t], new, base, metric)
        if c is not None:
            parts.append(f"w/o {t} {interval_text(c.diff, scale, signed=True)} ({verdict_text(c)})")
    return "; ".join(parts) or "–"


def cpu_s(wall_s: float, cores: int | None, cpu_time_s: float | None) -> float:
    """What a run or evaluation cost in CPU-seconds: its measured process CPU time, else (records made before it
    was measured) wall time × the cores its process ran on (2 where the record does not say), an upper bound."""
    return cpu_time_s if cpu_time_s is not None else wall_s * (cores or 2)


def measured_text(runs: int, measured_runs: int, evaluations: int, measured_evaluations: int) -> str:
    """How CPU-seconds were counted: '(process CPU time of 3 of 10 runs and 5 of 12 evaluations, wall time × the
    cores its process ran on for the rest: an upper bound, other jobs on those cores count too)'."""
    if runs == measured_runs and evaluations == measured_evaluations:
        return "(measured process CPU time)"
    return (f"(process CPU time of {measured_runs} of {runs} runs and {measured_evaluations} of {evaluations} "
            f"evaluations, wall time × the cores its process ran on for the rest: an upper bound, other jobs on "
            f"those cores count too)")


def spent_measured_text(spent: dict) -> str:
    """``measured_text`` of ``CostModel.spent``'s counts."""
    return measured_text(spent["runs"], spent["measured_runs"], spent["evaluations"], spent["measured_evaluations"])


def cost_note(records: list[dict]) -> str:
    """What the table's runs and evaluations cost, in CPU-hours of this 2-core machine kind, from the records: each
    distinct run's training and each evaluation, counted as ``cpu_s`` counts them (the measured process
    CPU time, else wall time × the cores its process ran on: 2 unless the record says)."""
    train = {r["run"]: cpu_s(r.get("training_s") or 0.0, r.get("training_cores"), r.get("training_cpu_s"))
             for r in records}
    measured_runs = len({r["run"] for r in records if r.get("training_cpu_s") is not None})
    evals = [cpu_s(r.get("eval_s") or 0.0, r.get("cpu_cores"), r.get("eval_cpu_s")) for r in records]
    measured = sum(r.get("eval_cpu_s") is not None for r in records)
    train_h, eval_h = sum(train.values()) / 3600, sum(evals) / 3600
    return (f"Cost: {train_h + eval_h:.1f} CPU-hours on this 2-core machine kind ({train_h:.1f} h training "
            f"{len(train)} runs, {eval_h:.1f} h evaluating), from the records "
            f"{measured_text(len(train), measured_runs, len(evals), measured)}.")


def bar_figure(path: str, groups: list[str], panels: list[tuple[str, dict[str, list[dict]]]], title: str,
               scale: float = 1.0, bounds: list | None = None) -> str:
    """Grouped bar chart(s): per panel (ylabel, {series: per-group per-seed outcomes}), the mean with its 95 %
    interval over seeds as the error bar (clipped to the panel's ``bounds`` entry, e.g. (0, 1) for success). A
    series with no value in any group is left out (legend included); a measured mean of 0 is labelled '0' so that
    it reads apart from a missing one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(max(5.0, 1.3 * len(groups) + 2.5) * len(panels), 3.6),
                             squeeze=False)
    for i_panel, (ax, (ylabel, series)) in enumerate(zip(axes[0], panels)):
        panel_bounds = bounds[i_panel] if bounds else None
        estimates = {name: [stats.seed_mean(g, bounds=panel_bounds) for g in per_group]
                     for name, per_group in series.items()}
        estimates = {name: ivs for name, ivs in estimates.items() if any(np.isfinite(iv.mean) for iv in ivs)}
        width = 0.8 / max(len(estimates), 1)
        x = np.arange(len(groups))
        for i, (name, ivs) in enumerate(estimates.items()):
            means = np.array([iv.mean for iv in ivs]) * scale
            err = np.array([[iv.mean - iv.low, iv.high - iv.mean] for iv in ivs]).T * scale
            pos = x + (i - (len(estimates) - 1) / 2) * width
            bars = ax.bar(pos, means, width, yerr=np.nan_to_num(err), capsize=2, label=name)
            for p, m in zip(pos, means):
                if m == 0.0:
                    ax.annotate("0", (p, 0.0), xytext=(0, 2), textcoords="offset points", ha="center",
                                fontsize=6, color=bars.patches[0].get_facecolor())
        ax.set_xticks(x, groups, rotation=20, ha="right", fontsize=8)
        ax.set_ylabel(ylabel)
        if estimates:
            ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def relative_gain(base: float, new: float) -> str:
    """' (+x%)': relative change of ``new`` over ``base`` ('' when undefined)."""
    return f" ({(new - base) / base * 100:+.0f}%)" if np.isfinite(base) and np.isfinite(new) and base > 0 else ""


def task_mean(records, metric, seeds, tasks, column) -> float:
    groups = [outcomes(records, metric, seeds, task=t, column=column) for t in tasks]
    return stats.average(groups).mean if all(groups) else float("nan")


def stride_cell(records, seeds, **match) -> str:
    hits = [r for r in records if r["seed"] in seeds and all(r.get(k) == v for k, v in match.items())]
    keys = sorted({k for r in hits for k in r if k.startswith("stride") and k.endswith("_frac")},
                  key=lambda k: int(k[6:-5]))
    if not keys:
        return "–"
    return "/".join(f"{100 * np.mean([r.get(k, 0.0) for r in hits]):.0f}" for k in keys)


def changes_text(changes: dict) -> str:
    if "episodes" in changes:
        return f"{changes['episodes']} demos"
    return ", ".join(f"{k.removeprefix('train.').replace('_', ' ')} {v}" for k, v in changes.items()) or "100 demos"
