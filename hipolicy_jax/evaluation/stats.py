"""Statistics of evaluation outcomes: hierarchical bootstrap intervals over seeds × episodes, paired comparisons on
shared initial states, and the exact McNemar test.

Outcomes come per seed: ``{seed: (E,) values}`` (success as 0/1, or steps). The interval of a column's mean
resamples the seeds with replacement, then the episodes within each resampled seed, and takes the mean over all
resampled episodes of the seed means; paired comparisons resample (seed, episode) pairs the same way, so both
columns keep their shared initial states. Every function is deterministic given its ``seed`` (default 0).
"""

from __future__ import annotations

import math
from typing import Mapping, NamedTuple, Sequence

import numpy as np

RESAMPLES = 10_000


class Interval(NamedTuple):
    """A point estimate and its percentile bootstrap interval."""

    mean: float
    low: float
    high: float


def _as_groups(groups: Mapping[int, Sequence[float]] | Sequence[Sequence[float]]) -> list[np.ndarray]:
    items = groups.values() if isinstance(groups, Mapping) else groups
    out = [np.asarray(g, np.float64).ravel() for g in items]
    out = [g[np.isfinite(g)] for g in out]
    return [g for g in out if g.size]


def _resampled_means(groups: list[np.ndarray], resamples: int, rng: np.random.Generator) -> np.ndarray:
    """(resamples,) means of the hierarchical resamples: S seed slots drawn with replacement, then for every slot
    its seed's episodes drawn with replacement, independently of the other slots."""
    s = len(groups)
    picks = rng.integers(0, s, size=(resamples, s))  # the seed of every slot
    slot_means = np.zeros((resamples, s))
    for j, g in enumerate(groups):  # every slot's episode resample, as if it had drawn seed j
        idx = rng.integers(0, g.size, size=(resamples, s, g.size))
        slot_means += np.where(picks == j, g[idx].mean(axis=2), 0.0)
    return slot_means.mean(axis=1)


def bootstrap_mean(groups, *, level: float = 0.95, resamples: int = RESAMPLES, seed: int = 0) -> Interval:
    """The mean over seeds of the per-seed means, with a hierarchical bootstrap interval (seeds, then episodes).

    ``groups``: ``{seed: (E,) values}`` or a list of per-seed arrays; non-finite values are dropped (e.g. the steps
    of failed episodes). NaN interval when there are no values; a single value gives a zero-width interval.
    """
    g = _as_groups(groups)
    if not g:
        return Interval(math.nan, math.nan, math.nan)
    point = float(np.mean([x.mean() for x in g]))
    if len(g) == 1 and g[0].size == 1:
        return Interval(point, point, point)
    boot = _resampled_means(g, resamples, np.random.default_rng(seed))
    a = (1.0 - level) / 2.0
    return Interval(point, float(np.quantile(boot, a)), float(np.quantile(boot, 1.0 - a)))


def bootstrap_average(tasks: Sequence, *, level: float = 0.95, resamples: int = RESAMPLES,
                      seed: int = 0) -> Interval:
    """The mean over tasks of each task's ``bootstrap_mean`` point, with an interval from resampling every task's
    seeds and episodes independently (``tasks``: one ``groups`` per task; tasks without values are left out)."""
    per_task = [g for g in (_as_groups(t) for t in tasks) if g]
    if not per_task:
        return Interval(math.nan, math.nan, math.nan)
    rng = np.random.default_rng(seed)
    point = float(np.mean([np.mean([x.mean() for x in g]) for g in per_task]))
    boot = np.mean([_resampled_means(g, resamples, rng) for g in per_task], axis=0)
    a = (1.0 - level) / 2.0
    return Interval(point, float(np.quantile(boot, a)), float(np.quantile(boot, 1.0 - a)))


def paired_difference(a: Mapping[int, Sequence[float]], b: Mapping[int, Sequence[float]], *, level: float = 0.95,
                      resamples: int = RESAMPLES, seed: int = 0) -> Interval:
    """Mean of ``a − b`` over the (seed, episode) pairs the two columns share (seeds in both, episodes index-aligned:
    the same initial states), with the hierarchical bootstrap interval of that mean."""
    shared = sorted(set(a) & set(b))
    diffs = []
    for s in shared:
        x, y = np.asarray(a[s], np.float64), np.asarray(b[s], np.float64)
        if x.shape != y.shape:
            raise ValueError(f"seed {s}: paired outcomes need the same episodes, got {x.shape} and {y.shape}")
        diffs.append(x - y)
    return bootstrap_mean(diffs, level=level, resamples=resamples, seed=seed)


def mcnemar_exact(a: Mapping[int, Sequence[bool]], b: Mapping[int, Sequence[bool]]) -> tuple[int, int, float]:
    """Exact two-sided McNemar test of paired binary outcomes over the shared (seed, episode) pairs → (pairs where
    only ``a`` succeeded, pairs where only ``b`` succeeded, p-value). p = 1 without discordant pairs."""
    only_a = only_b = 0
    for s in sorted(set(a) & set(b)):
        x, y = np.asarray(a[s], bool), np.asarray(b[s], bool)
        only_a += int(np.sum(x & ~y))
        only_b += int(np.sum(~x & y))
    n = only_a + only_b
    if n == 0:
        return only_a, only_b, 1.0
    k = min(only_a, only_b)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2.0 ** n
    return only_a, only_b, min(1.0, 2.0 * tail)


def verdict(diff: Interval) -> str:
    """'wins' / 'loses' when the paired interval excludes 0, 'ties' otherwise (the protocol's wording)."""
    if not math.isfinite(diff.low):
        return "–"
    if diff.low > 0:
        return "wins"
    if diff.high < 0:
        return "loses"
    return "ties"


__all__ = ["Interval", "RESAMPLES", "bootstrap_average", "bootstrap_mean", "mcnemar_exact", "paired_difference",
           "verdict"]
