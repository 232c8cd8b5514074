"""Statistics of evaluation outcomes whose unit is the trained network (results/PROTOCOL.md v2).

Outcomes come per seed (one trained network a seed): ``{seed: (E,) values}`` (success as 0/1, steps, or the
per-episode differences of two columns on the same initial states). A seed contributes ONE value, the mean over
its episodes; a cell is the mean of its S seed values with a t interval over seeds,

    mean ± t(1 − α/2, S − 1) · s / √S,

and its p is the two-sided t test of that mean against 0. When all S seed values are equal (s = 0), the
episode-level standard error √(Σ_s v_s / E_s) / S replaces s / √S, so that three equal seeds never give a zero-width
interval. An average over tasks is the mean of the task means, with standard error √(Σ_t SE_t²) / T and
Welch–Satterthwaite degrees of freedom. ``sign_flip_p`` is the exact permutation test over the (task, seed)
differences, and ``mcnemar_exact`` the episode-level test (it treats every episode as independent: a column, not
the verdict).

Why not the version-1 hierarchical bootstrap (seeds, then episodes, percentile interval) for the verdict: with 3
seeds it covered 81–89 % for a nominal 95 % when seeds differ and 98–99 % when they do not; the t interval over
seeds covers 94–96 % in both (``tests/test_stats.py`` measures both). ``hierarchical_bootstrap`` keeps it as a
second interval, shown beside the t interval, so a reader sees where the two disagree.
"""

from __future__ import annotations

import math
from typing import Mapping, NamedTuple, Sequence

import numpy as np
from scipy import stats as sps

LEVEL = 0.95


class Estimate(NamedTuple):
    """A mean over trained networks: its ``level`` interval, the two-sided p of the t test against 0, the degrees
    of freedom and the number of seeds (summed over tasks for an average). NaN interval and p with one seed."""

    mean: float
    low: float
    high: float
    p: float = math.nan
    df: float = math.nan
    seeds: int = 0
    se: float = math.nan


NAN = Estimate(math.nan, math.nan, math.nan)


def _as_groups(groups: Mapping[int, Sequence[float]] | Sequence[Sequence[float]]) -> list[np.ndarray]:
    """Per-seed finite values (non-finite ones dropped: the steps of failed episodes); seeds without any left out."""
    items = groups.values() if isinstance(groups, Mapping) else groups
    out = [np.asarray(g, np.float64).ravel() for g in items]
    out = [g[np.isfinite(g)] for g in out]
    return [g for g in out if g.size]


def seed_values(groups) -> np.ndarray:
    """(S,) the mean over each seed's episodes: one value per trained network."""
    return np.asarray([g.mean() for g in _as_groups(groups)], np.float64)


def _from_se(mean: float, se: float, df: float, seeds: int, level: float,
             bounds: tuple[float, float] | None = None) -> Estimate:
    if not (df > 0 and np.isfinite(se)):
        return Estimate(mean, math.nan, math.nan, math.nan, df, seeds, se)
    half = float(sps.t.ppf(0.5 + level / 2.0, df)) * se
    if se > 0:
        p = float(2.0 * sps.t.sf(abs(mean) / se, df))
    else:
        p = 1.0 if mean == 0 else 0.0
    low, high = mean - half, mean + half
    if bounds is not None:  # the quantity's own range (a rate in [0, 1]): the interval never claims beyond it
        low, high = max(low, bounds[0]), min(high, bounds[1])
    return Estimate(mean, low, high, p, df, seeds, se)


def seed_mean(groups, *, level: float = LEVEL, bounds: tuple[float, float] | None = None) -> Estimate:
    """The mean over seeds of the per-seed means, with the t interval over seeds and the t test against 0.

    ``groups``: ``{seed: (E,) values}`` or a list of per-seed arrays (non-finite values dropped). One seed: the
    point only (no interval, no p); none: NaN. ``bounds``: the range of the quantity (e.g. (0, 1) for a success
    rate, (−1, 1) for a difference of two), to which the interval is clipped."""
    g = _as_groups(groups)
    if not g:
        return NAN
    v = np.asarray([x.mean() for x in g])
    s, mean = len(g), float(v.mean())
    if s == 1:
        return Estimate(mean, math.nan, math.nan, math.nan, 0.0, 1, math.nan)
    se = float(v.std(ddof=1) / math.sqrt(s))
    if se == 0.0:  # equal seed values: the episode-level standard error instead of a zero-width interval
        se = math.sqrt(sum(x.var(ddof=1) / x.size for x in g if x.size > 1)) / s
    return _from_se(mean, se, s - 1.0, s, level, bounds)


def average(tasks: Sequence, *, level: float = LEVEL, bounds: tuple[float, float] | None = None) -> Estimate:
    """The mean over tasks of each task's ``seed_mean``: standard error √(Σ SE_t²)/T, Welch–Satterthwaite degrees
    of freedom (``tasks``: one ``groups`` per task; a task without values is left out)."""
    per_task = [seed_mean(t, level=level) for t in tasks]
    per_task = [e for e in per_task if np.isfinite(e.mean)]
    if not per_task:
        return NAN
    n = len(per_task)
    mean = float(np.mean([e.mean for e in per_task]))
    seeds = sum(e.seeds for e in per_task)
    if any(e.df <= 0 or not np.isfinite(e.se) for e in per_task):
        return Estimate(mean, math.nan, math.nan, math.nan, 0.0, seeds, math.nan)
    var = [e.se ** 2 for e in per_task]
    se = math.sqrt(sum(var)) / n
    denominator = sum(v ** 2 / e.df for v, e in zip(var, per_task))
    df = sum(var) ** 2 / denominator if denominator > 0 else float(sum(e.df for e in per_task))
    return _from_se(mean, se, df, seeds, level, bounds)


def paired_groups(a: Mapping[int, Sequence[float]], b: Mapping[int, Sequence[float]]) -> dict[int, np.ndarray]:
    """Per seed both columns have: the per-episode differences ``a − b`` (episodes index-aligned: the same initial
    states)."""
    out = {}
    for s in sorted(set(a) & set(b)):
        x, y = np.asarray(a[s], np.float64), np.asarray(b[s], np.float64)
        if x.shape != y.shape:
            raise ValueError(f"seed {s}: paired outcomes need the same episodes, got {x.shape} and {y.shape}")
        out[s] = x - y
    return out


def paired_difference(a, b, *, level: float = LEVEL, bounds: tuple[float, float] | None = None) -> Estimate:
    """``seed_mean`` of the per-episode differences ``a − b`` over the seeds both columns have."""
    return seed_mean(paired_groups(a, b), level=level, bounds=bounds)


BOOTSTRAP_RESAMPLES = 10_000


def _resampled_means(groups: list[np.ndarray], resamples: int, rng: np.random.Generator) -> np.ndarray:
    """(resamples,) means of hierarchical resamples: S seed slots drawn with replacement, then for every slot its
    seed's episodes drawn with replacement, independently of the other slots; a resample's value is the mean of
    its slots' episode means."""
    s = len(groups)
    picks = rng.integers(0, s, size=(resamples, s))  # the seed of every slot
    slot_means = np.zeros((resamples, s))
    for j, g in enumerate(groups):  # every slot's episode resample, as if it had drawn seed j
        idx = rng.integers(0, g.size, size=(resamples, s, g.size))
        slot_means += np.where(picks == j, g[idx].mean(axis=2), 0.0)
    return slot_means.mean(axis=1)


def hierarchical_bootstrap(tasks: Sequence, *, level: float = LEVEL, resamples: int = BOOTSTRAP_RESAMPLES,
                           seed: int = 0) -> Estimate:
    """Version 1's interval, kept beside the t interval (never the verdict's): the percentile interval of the
    hierarchical bootstrap (seeds with replacement, then each drawn seed's episodes with replacement) of the mean
    over tasks of the per-task mean seed values; every task resampled independently. ``tasks``: one ``groups``
    per task (one task: its mean over seeds, as ``seed_mean``); tasks without values are left out. Deterministic
    given ``seed``. With 3 seeds it under-covers when the seeds differ (``tests/test_stats.py``): it treats the
    three networks as the population. ``p``, ``df`` and ``se`` are NaN (no test)."""
    per_task = [g for g in (_as_groups(t) for t in tasks) if g]
    if not per_task:
        return NAN
    point = float(np.mean([np.mean([x.mean() for x in g]) for g in per_task]))
    seeds = sum(len(g) for g in per_task)
    if all(len(g) == 1 and g[0].size == 1 for g in per_task):
        return Estimate(point, math.nan, math.nan, math.nan, math.nan, seeds)
    rng = np.random.default_rng(seed)
    boot = np.mean([_resampled_means(g, resamples, rng) for g in per_task], axis=0)
    a = (1.0 - level) / 2.0
    return Estimate(point, float(np.quantile(boot, a)), float(np.quantile(boot, 1.0 - a)), math.nan, math.nan, seeds)


def sign_flip_p(tasks: Sequence, *, max_exact: int = 40, resamples: int = 100_000, seed: int = 0) -> float:
    """Exact two-sided sign-flip permutation p of the mean over tasks of the per-task mean seed differences:
    under the null every (task, seed) difference is as likely negated; the share of all 2^n sign patterns whose
    |statistic| reaches the observed one when n ≤ ``max_exact`` (n = 12 for 4 tasks × 3 seeds: the smallest possible
    p is 2/4096; n = 30 for 10 tasks × 3 seeds), else of ``resamples`` random patterns. The exact count splits the
    differences in two halves, enumerates each half's 2^(n/2) signed sums and counts, for each sum of one half, the
    sums of the other that reach the observed |statistic| (a sorted search): 2 · 2^(n/2) sums instead of 2^n."""
    values = [seed_values(t) for t in tasks]
    values = [v for v in values if v.size]
    if not values:
        return math.nan
    flat = np.concatenate(values)
    weights = np.concatenate([np.full(v.size, 1.0 / (v.size * len(values))) for v in values])
    weighted = weights * flat
    threshold = abs(float(np.sum(weighted))) - 1e-12  # a pattern counts when its |statistic| reaches this
    if threshold <= 0.0:  # the observed statistic is 0: every pattern reaches it
        return 1.0
    n = flat.size
    if n > max_exact:
        signs = np.random.default_rng(seed).choice((1.0, -1.0), size=(resamples, n))
        return float(np.mean(np.abs(signs @ weighted) >= threshold))

    def signed_sums(v: np.ndarray) -> np.ndarray:  # the 2^len(v) sums Σ ± v_i, one sign pattern each
        sums = np.zeros(1)
        for x in v:
            sums = np.concatenate([sums + x, sums - x])
        return sums

    first, second = signed_sums(weighted[: n // 2]), np.sort(signed_sums(weighted[n // 2:]))
    # first + second ≥ threshold, or first + second ≤ −threshold (disjoint: threshold > 0)
    above = second.size - np.searchsorted(second, threshold - first, side="left")
    below = np.searchsorted(second, -threshold - first, side="right")
    return int(above.sum() + below.sum()) / 2 ** n


def mcnemar_exact(a: Mapping, b: Mapping) -> tuple[int, int, float]:
    """Exact two-sided McNemar test of paired binary outcomes over the shared (seed, episode) pairs → (pairs where
    only ``a`` succeeded, pairs where only ``b`` succeeded, p-value). p = 1 without discordant pairs. Episode-level:
    it treats every episode as independent, whatever network it came from. Exact for any number of pairs (a float
    ``2.0 ** n`` overflows past 1,023 discordant pairs); a p below the smallest float (about 5e-324) is 0.0."""
    only_a = only_b = 0
    for s in sorted(set(a) & set(b)):
        x, y = np.asarray(a[s], bool), np.asarray(b[s], bool)
        only_a += int(np.sum(x & ~y))
        only_b += int(np.sum(~x & y))
    n = only_a + only_b
    if n == 0:
        return only_a, only_b, 1.0
    k = min(only_a, only_b)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2 ** n  # exact integers, one correct rounding: any n
    return only_a, only_b, min(1.0, 2.0 * tail)


def verdict(diff: Estimate) -> str:
    """'wins' / 'loses' when the paired interval excludes 0 (the t test's p < 1 − level), 'ties' otherwise, '–'
    without an interval (one seed)."""
    if not math.isfinite(diff.low):
        return "–"
    if diff.low > 0:
        return "wins"
    if diff.high < 0:
        return "loses"
    return "ties"


__all__ = ["BOOTSTRAP_RESAMPLES", "Estimate", "LEVEL", "average", "hierarchical_bootstrap", "mcnemar_exact", "paired_difference", "paired_groups", "seed_mean",
           "seed_values", "sign_flip_p", "verdict"]
