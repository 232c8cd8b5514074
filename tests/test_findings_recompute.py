"""An independent re-computation of the committed findings from the committed run records.

``results/findings.md`` is what a reader quotes. This test recomputes every cell of it from
``results/runs/cpu/<task>/<obs>/<variant>/seed<k>.json`` alone, with json, numpy and scipy: not the project's
statistics module, not its table code, not the tables' JSON. It checks each paired cell's point, interval and
verdict (wins / ties / loses), the averages' p, the tasks' W/T/L tally, the same-network speed rows and the
training-budget rows. A table left stale after new records, a pairing of the wrong seeds or episodes, or a slip in
the interval fails here.

The rules recomputed (results/PROTOCOL.md, version 2): a seed (one trained network) contributes the mean over its
100 episodes of the per-episode difference on the same initial states; a task's cell is the mean over the seeds
both columns have, with the 95 % t interval over seeds (scipy's one-sample t test), clipped to [-100, +100]
points; when every seed gives the same value, the episode-level standard error replaces the seeds' one. An
average is the mean of the task means with a Welch–Satterthwaite t interval.
"""

from __future__ import annotations

import json
import math
import os
import re

import numpy as np
import pytest
from scipy import stats

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RECORDS = os.path.join(ROOT, "results", "runs", "cpu")
FINDINGS = os.path.join(ROOT, "results", "findings.md")
TASKS = ("press_button", "stack_cubes", "latch_door", "pick_place")
SEEDS = (0, 1, 2)  # the paired seeds (the baseline's extra seeds 3, 4 have no HiPolicy partner)
ROUND = 0.05 + 1e-9  # the tables print one decimal


# ---------------------------------------------------------------------------------------------------------- records

def _rlow_suffix(task: str) -> str:
    """The Rlow variant's directory suffix from the pilot's committed choice (``_d25``, ``_t8000``)."""
    with open(os.path.join(ROOT, "results", "pilot_choice.json")) as f:
        change = json.load(f)[task]
    if "episodes" in change:
        return f"_d{change['episodes']}"
    return f"_t{change['train.num_steps']}"


def _evaluation(task: str, obs: str, variant: str, seed: int, execution: str, guided: bool) -> dict | None:
    """The one 100-episode evaluation of a run with the campaign's default inference settings."""
    path = os.path.join(RECORDS, task, obs, variant, f"seed{seed}.json")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        record = json.load(f)
    found = []
    for key, e in record["evaluations"].items():
        s = json.loads(key)
        if (s["execution"] == execution and s["guided"] == guided and s["episodes"] == 100
                and s.get("percentiles") is None and s.get("num_samples") == 16 and s.get("num_steps") == 10
                and s.get("sampler", "auto") == "auto"):
            found.append(e)
    assert len(found) <= 1, f"{path}: {len(found)} evaluations match ({execution}, guided={guided})"
    return found[0] if found else None


# (new, base) columns: (obs, variant prefix, execution, guided)
COLUMNS = {
    "DP": ("state", "dp", "chunk", True),
    "DP+HiPolicy": ("state", "hipolicy", "chunk", True),
    "HiPolicy": ("state", "hipolicy", "chunk", True),
    "DP3": ("pointcloud", "dp", "chunk", True),
    "DP3+HiPolicy": ("pointcloud", "hipolicy", "chunk", True),
    "DP+TE": ("state", "dp", "te", True),
    "DP+AAC": ("state", "dp", "aac", True),
    "w/o EG": ("state", "hipolicy", "chunk", False),
}


def _pairs(task: str, new: str, base: str, suffix: str) -> dict[int, tuple[dict, dict]]:
    """Per seed both columns have: (new's evaluation, base's evaluation)."""
    out = {}
    for seed in SEEDS:
        (obs_a, var_a, ex_a, g_a), (obs_b, var_b, ex_b, g_b) = COLUMNS[new], COLUMNS[base]
        a = _evaluation(task, obs_a, var_a + suffix, seed, ex_a, g_a)
        b = _evaluation(task, obs_b, var_b + suffix, seed, ex_b, g_b)
        if a is not None and b is not None:
            assert len(a["success"]) == len(b["success"]) == 100, (task, new, base, seed)
            if (obs_a, var_a) == (obs_b, var_b):  # one run: both evaluations must come from one network
                na, nb = a["network"], b["network"]
                if na.get("params_sha256") and nb.get("params_sha256"):
                    assert na["params_sha256"] == nb["params_sha256"], (task, new, base, seed)
                else:
                    assert na["final_loss"] == nb["final_loss"], (task, new, base, seed)
            out[seed] = (a, b)
    return out


# ------------------------------------------------------------------------------------------------------- statistics

def _seed_level(groups: list[np.ndarray], lo_hi=(-1.0, 1.0)):
    """(mean, low, high, se, df) of the mean over seeds of each seed's episode mean."""
    values = np.array([g.mean() for g in groups])
    if len(values) < 2:
        return float(values.mean()), math.nan, math.nan, math.nan, 0.0
    df = len(values) - 1
    if np.ptp(values) > 0:
        test = stats.ttest_1samp(values, 0.0)
        ci = test.confidence_interval(0.95)
        se = float(values.std(ddof=1) / math.sqrt(len(values)))
        low, high = ci.low, ci.high
    else:  # equal seeds: the episode-level standard error
        se = math.sqrt(sum(g.var(ddof=1) / g.size for g in groups)) / len(groups)
        half = stats.t.ppf(0.975, df) * se
        low, high = values.mean() - half, values.mean() + half
    return float(values.mean()), max(low, lo_hi[0]), min(high, lo_hi[1]), se, df


def _welch(per_task):
    """The mean of the task means with its Welch–Satterthwaite interval and p."""
    means = np.array([t[0] for t in per_task])
    var = np.array([t[3] ** 2 for t in per_task])
    df = var.sum() ** 2 / sum(v ** 2 / t[4] for v, t in zip(var, per_task))
    se = math.sqrt(var.sum()) / len(per_task)
    mean = float(means.mean())
    half = stats.t.ppf(0.975, df) * se
    p = 2 * stats.t.sf(abs(mean) / se, df)
    return mean, max(mean - half, -1.0), min(mean + half, 1.0), p


def _success_diffs(pairs) -> list[np.ndarray]:
    return [np.asarray(a["success"], float) - np.asarray(b["success"], float) for a, b in pairs.values()]


def _verdict(low: float, high: float) -> str:
    if not math.isfinite(low):
        return "–"
    return "wins" if low > 0 else "loses" if high < 0 else "ties"


# ---------------------------------------------------------------------------------------------------------- reading

_NUM = r"[+-]?\d+(?:\.\d+)?"
_CELL = re.compile(rf"^({_NUM})(?: \[({_NUM}), ({_NUM})\])?(?:,? ?p=([^ ]+))?(?: \(?(wins|ties|loses)\)?)?"
                   r"(?: \(1 seed: no test\))?$")


def _parse(cell: str):
    """'-22.7 [-27.8, -17.5] loses' / '+16.0 [+11.2, +20.8], p=0.0042 (wins)' → (m, lo, hi, p, verdict)."""
    m = _CELL.match(cell.strip())
    assert m, f"cannot read the cell {cell!r}"
    mean, low, high, p, verdict = m.groups()
    f = (lambda x: math.nan if x is None else float(x))
    return f(mean), f(low), f(high), (math.nan if p in (None, "–") else float(p)), verdict


def _tables(text: str) -> dict[str, list[list[str]]]:
    """Each markdown table under its section title ('' for the first): its body rows as cells."""
    out, title, rows = {}, "", None
    for line in text.splitlines():
        if line.startswith("## "):
            title = line[3:].strip()
        elif line.startswith("|"):
            if rows is None:
                rows = out.setdefault(title, [])
                continue  # the header
            if set(line) <= set("|-: "):
                continue
            rows.append([c.strip() for c in line.strip().strip("|").split(" | ")])
        else:
            rows = None
    return out


def _close(printed: float, value: float, what: str):
    assert abs(printed - value) <= ROUND, f"{what}: the table prints {printed}, the records give {value:.4f}"


def _check_cell(cell: str, groups: list[np.ndarray] | None, what: str):
    if groups is None or not groups:
        assert cell == "–", f"{what}: the table prints {cell!r} but the records hold no pair"
        return None
    assert cell != "–", f"{what}: the records hold {len(groups)} paired seed(s) but the table prints '–'"
    est = _seed_level(groups)
    m, lo, hi, _, verdict = _parse(cell)
    _close(m, 100 * est[0], what + " (mean)")
    if math.isfinite(est[1]) and est[1] == est[2]:  # no width (every episode of every seed agrees): 'm' alone
        assert math.isnan(lo) and math.isnan(hi), f"{what}: the records give a zero-width interval, the table {cell!r}"
    elif math.isfinite(est[1]):
        _close(lo, 100 * est[1], what + " (low)")
        _close(hi, 100 * est[2], what + " (high)")
    assert (verdict or "–") == _verdict(est[1], est[2]), f"{what}: verdict {verdict} vs {_verdict(est[1], est[2])}"
    return est


# ------------------------------------------------------------------------------------------------------------ tests

@pytest.fixture(scope="module")
def findings():
    if not os.path.exists(FINDINGS):
        pytest.skip("no committed findings yet")
    with open(FINDINGS) as f:
        return _tables(f.read())


def test_every_paired_cell_recomputes_from_the_records(findings):
    rows = findings[""]
    assert rows, "findings.md has no comparison table"
    tally = {"wins": 0, "ties": 0, "loses": 0}
    checked = 0
    for row in rows:
        comparison, regime = row[0], row[1]
        new, base = comparison.split(" vs ")
        suffix_of = (lambda t: "") if regime.startswith("100 demos") else _rlow_suffix
        per_task, counts = [], {"wins": 0, "ties": 0, "loses": 0}
        for task, cell in zip(TASKS, row[2:6]):
            pairs = _pairs(task, new, base, suffix_of(task))
            est = _check_cell(cell, _success_diffs(pairs) if pairs else None, f"{comparison}, {regime}, {task}")
            if est is not None:
                checked += 1
                per_task.append((est, _success_diffs(pairs)))
                v = _verdict(est[1], est[2])
                if v in counts:
                    counts[v] += 1
        # the average over the table's tasks: printed only when every task has a pair
        average = row[6]
        if len(per_task) == len(TASKS) and all(math.isfinite(e[1]) for e, _ in per_task):
            mean, low, high, p = _welch([e for e, _ in per_task])
            m, lo, hi, printed_p, verdict = _parse(average)
            _close(m, 100 * mean, f"{comparison}, {regime}, average")
            _close(lo, 100 * low, f"{comparison}, {regime}, average (low)")
            _close(hi, 100 * high, f"{comparison}, {regime}, average (high)")
            assert verdict == _verdict(low, high), (comparison, regime, verdict)
            assert printed_p == pytest.approx(p, rel=0.05, abs=5e-5), (comparison, regime, printed_p, p)
            # the exact sign-flip p over the (task, seed) differences, each task weighing the same
            values = [np.array([g.mean() for g in groups]) for _, groups in per_task]
            flat = np.concatenate(values)
            weights = np.concatenate([np.full(v.size, 1 / (v.size * len(values))) for v in values])
            signs = 1 - 2 * ((np.arange(2 ** flat.size)[:, None] >> np.arange(flat.size)) & 1)
            observed = abs(weights @ flat)
            sign_flip = np.mean(np.abs(signs @ (weights * flat)) >= observed - 1e-12)
            assert float(row[7]) == pytest.approx(sign_flip, rel=0.05, abs=5e-5), (comparison, regime)
        elif len(per_task) < len(TASKS):
            assert average == "–", f"{comparison}, {regime}: an average over tasks without a pair: {average!r}"
        assert row[-1] == "/".join(str(counts[v]) for v in ("wins", "ties", "loses")), (comparison, regime, row[-1])
        for v in tally:
            tally[v] += counts[v]
    assert checked >= 10, f"only {checked} cells could be checked"
    with open(FINDINGS) as f:
        text = f.read()
    total = sum(tally.values())
    assert (f"Over the {total} (comparison, task) cells: HiPolicy wins {tally['wins']}, ties {tally['ties']}, "
            f"loses {tally['loses']}.") in text


def _speed_title(findings, regime: str) -> str:
    titles = [t for t in findings if t.startswith("Entropy-guided execution") and regime in t]
    assert len(titles) == 1, (regime, list(findings))
    return titles[0]


@pytest.mark.parametrize("regime", ["100 demos", "Rlow"])
def test_same_network_speed_rows_recompute_from_the_records(findings, regime):
    """HiPolicy vs w/o EG on one network: success cost (points) and the steps to success saved (%)."""
    rows = {r[0]: r for r in findings[_speed_title(findings, regime)]}
    suffix_of = (lambda t: "") if regime == "100 demos" else _rlow_suffix
    for task in TASKS:
        row, pairs = rows[task], _pairs(task, "HiPolicy", "w/o EG", suffix_of(task))
        what = f"speed, {regime}, {task}"
        if len(pairs) < 2:
            continue
        _check_cell(row[3].replace(" (", " ").rstrip(")"), _success_diffs(pairs), what + " success cost")
        saved = []
        for a, b in pairs.values():
            both = np.asarray(a["success"], bool) & np.asarray(b["success"], bool)
            if both.any():
                na, nb = np.asarray(a["steps"], float)[both], np.asarray(b["steps"], float)[both]
                saved.append((nb - na) / nb.mean())
        cell = row[6].split(", p=")[0]
        if not saved:  # a seed without a shared success contributes no steps; none at all: no cell
            assert cell == "–", (what, cell)
            continue
        est = _seed_level(saved, lo_hi=(-math.inf, math.inf))
        m, lo, hi, _, _ = _parse(cell)
        _close(m, 100 * est[0], what + " steps saved")
        if math.isfinite(est[1]):
            _close(lo, 100 * est[1], what + " steps saved (low)")
            _close(hi, 100 * est[2], what + " steps saved (high)")
        word = "faster" if est[1] > 0 else "slower" if est[2] < 0 else "no difference"
        assert row[6].endswith(f"({word})"), (what, row[6], word)


def test_training_budget_rows_recompute_from_the_records(findings):
    """DP+HiPolicy − DP by training steps: 2,000 steps are the main table's runs, longer ones ``_t<steps>``."""
    title = [t for t in findings if t.startswith("Training budget")]
    if not title:
        pytest.skip("no budget rows yet")
    rows = findings[title[0]]
    estimates = {}  # (steps, task): the seed-level estimate the cell recomputes to
    for row in rows[:-1]:
        steps = int(row[0].split()[0].replace(",", ""))
        suffix = "" if steps == 2000 else f"_t{steps}"
        for task, cell in zip(TASKS, row[1:]):
            pairs = _pairs(task, "DP+HiPolicy", "DP", suffix)
            if task in ("latch_door", "pick_place"):  # the budget study's tasks are press_button and stack_cubes
                assert cell == "–", (steps, task, cell)
                continue
            estimates[steps, task] = _check_cell(cell, _success_diffs(pairs) if pairs else None,
                                                 f"budget {steps}, {task}")
    # the last row answers the protocol's question per task: the gap shrinks / grows when the longest training's
    # t interval excludes the 2,000-step point estimate (by which mean is nearer 0), else it holds
    answer = rows[-1]
    assert answer[0] == "Gap 2,000 → 24,000 steps (protocol's rule)", answer
    for task, cell in zip(TASKS, answer[1:]):
        first, last = estimates.get((2000, task)), estimates.get((24000, task))
        if first is None or last is None or not math.isfinite(last[1]):
            assert cell == "–", (task, cell)
            continue
        want = ("holds" if last[1] <= first[0] <= last[2]
                else "shrinks" if abs(last[0]) < abs(first[0]) else "grows")
        assert cell == want, (task, cell, want)


def _bootstrap(per_task: list[list[np.ndarray]], resamples: int = 10_000, seed: int = 12345):
    """Version 1's hierarchical bootstrap, written again: per resample and task, 3 seeds drawn with replacement and
    each drawn seed's episodes with replacement; the resample's value is the mean over tasks of the mean of the
    drawn seeds' episode means; the 2.5 / 97.5 % quantiles. Another random stream than the project's."""
    rng = np.random.default_rng(seed)
    values = np.zeros(resamples)
    for groups in per_task:
        total = np.zeros(resamples)
        for _ in range(len(groups)):
            pick = rng.integers(0, len(groups), resamples)
            for j, g in enumerate(groups):
                chosen = pick == j
                total[chosen] += g[rng.integers(0, g.size, (int(chosen.sum()), g.size))].mean(axis=1)
        values += total / len(groups)
    values /= len(per_task)
    return np.quantile(values, 0.025), np.quantile(values, 0.975)


def test_bootstrap_beside_the_t_interval_recomputes_from_the_records(findings):
    """Every row of the side-by-side section: the t cell as the main table's, the hierarchical bootstrap's interval
    from an independent resampling (within 1 point: Monte Carlo error), each verdict, and the summary's count."""
    title = [t for t in findings if t.startswith("The verdict's interval beside")]
    if not title:
        pytest.skip("no side-by-side section yet")
    rows, same = findings[title[0]], 0
    for comparison, regime, task, t_cell, boot_cell, agree in rows:
        new, base = comparison.split(" vs ")
        suffix_of = (lambda t: "") if regime.startswith("100 demos") else _rlow_suffix
        tasks = TASKS if task == "Average" else (task,)
        groups = [_success_diffs(_pairs(t, new, base, suffix_of(t))) for t in tasks]
        what = f"{comparison}, {regime}, {task}"
        if task == "Average":
            mean, low, high, _ = _welch([_seed_level(g) for g in groups])
        else:
            mean, low, high = _seed_level(groups[0])[:3]
        m, lo, hi, _, t_verdict = _parse(t_cell)
        for printed, value, part in ((m, mean, "mean"), (lo, low, "low"), (hi, high, "high")):
            _close(printed, 100 * value, f"{what} (t {part})")
        assert t_verdict == _verdict(low, high), what
        b_low, b_high = _bootstrap(groups)
        bm, blo, bhi, _, b_verdict = _parse(boot_cell)
        _close(bm, 100 * mean, f"{what} (bootstrap mean)")
        assert abs(blo - 100 * b_low) <= 1.0 and abs(bhi - 100 * b_high) <= 1.0, (what, blo, bhi, b_low, b_high)
        if min(abs(b_low), abs(b_high)) > 0.01:  # a bound within a point of 0 may fall either side
            assert b_verdict == _verdict(b_low, b_high), what
        assert agree == ("yes" if t_verdict == b_verdict else "**no**"), what
        same += agree == "yes"
    with open(FINDINGS) as f:
        assert f"They give the same verdict in {same} of {len(rows)} cells" in f.read()


# ------------------------------------------------------------------------------------------------------- Meta-World

METAWORLD = os.path.join(ROOT, "results", "metaworld", "main.md")


def _metaworld_columns(text: str) -> tuple[int, dict[str, str]]:
    """The training steps T the table states, and its state columns' record directories."""
    steps = int(re.search(r"Training: (\d+) steps", text).group(1))
    return steps, {"DP": f"dp_t{steps}", "DP+HiPolicy": f"hipolicy_t{steps}"}


def _metaworld_runs(task: str, variant: str) -> dict[int, dict]:
    """Per seed, the run's main evaluation (100 episodes, whole chunks, guided when the policy has strides)."""
    out = {}
    for seed in SEEDS:
        suite, _, name = task.partition(":")
        path = os.path.join(ROOT, "results", "runs", "metaworld", f"{suite}_{name}", "state", variant,
                            f"seed{seed}.json")
        if not os.path.exists(path):
            continue
        with open(path) as f:
            evaluations = json.load(f)["evaluations"]
        main = [e for k, e in evaluations.items()
                if json.loads(k)["guided"] and json.loads(k)["execution"] == "chunk" and json.loads(k)["episodes"] == 100]
        assert len(main) == 1, path
        out[seed] = main[0]
    return out


METAWORLD_TARGET = os.path.join(ROOT, "results", "metaworld", "target", "main.md")


@pytest.mark.parametrize("table, suite", [(METAWORLD, "metaworld:"), (METAWORLD_TARGET, "metaworld-target:")],
                         ids=["main", "amendment-1"])
def test_metaworld_table_recomputes_from_the_records(table, suite):
    """Each state cell (success with its interval over seeds), each paired difference on the shared initial states,
    and DP3's metric (per seed the mean of the 5 best periodic evaluations) from the bridge's run records: the main
    table (displacement actions) and amendment 1's (absolute hand targets, its primary comparison)."""
    if not os.path.exists(table):
        pytest.skip(f"no committed {table}")
    with open(table) as f:
        text = f.read()
    steps, variants = _metaworld_columns(text)
    sections = _tables(text)
    main = {r[0]: r for r in sections[""]}
    dp3_title = [t for t in sections if t.startswith("DP3's metric")]
    dp3 = {r[0]: r for r in sections[dp3_title[0]]} if dp3_title else {}
    checked = 0
    for task, row in main.items():
        if not task.startswith(suite):
            continue
        runs = {col: _metaworld_runs(task, v) for col, v in variants.items()}
        for col, cell in (("DP", row[3]), ("DP+HiPolicy", row[4])):
            rates = [np.asarray(e["success"], float) for e in runs[col].values()]
            if not rates:
                assert cell == "–", (task, col, cell)
                continue
            est = _seed_level(rates, lo_hi=(0.0, 1.0))
            m, lo, hi, _, _ = _parse(cell)
            _close(m, 100 * est[0], f"{task} {col}")
            if math.isfinite(est[1]) and est[1] < est[2]:
                _close(lo, 100 * est[1], f"{task} {col} (low)")
                _close(hi, 100 * est[2], f"{task} {col} (high)")
            checked += 1
            if task in dp3:  # DP3's metric: the mean of each seed's 5 best periodic evaluations
                best = [sorted((c["success_rate"] for c in e["periodic"]["checkpoints"]), reverse=True)[:5]
                        for e in runs[col].values()]
                dp3_cell = dp3[task][3 if col == "DP" else 4]
                _close(_parse(dp3_cell)[0], 100 * np.mean([np.mean(b) for b in best]), f"{task} {col} DP3 metric")
        shared = sorted(set(runs["DP"]) & set(runs["DP+HiPolicy"]))
        diffs = [np.asarray(runs["DP+HiPolicy"][s]["success"], float) - np.asarray(runs["DP"][s]["success"], float)
                 for s in shared]
        cell = row[7]
        if not diffs:
            assert cell == "–", (task, cell)
            continue
        _check_cell(cell.split(", p=")[0] + (f" {_parse(cell)[4]}" if _parse(cell)[4] else ""), diffs,
                    f"{task} DP+HiPolicy − DP")
        checked += 1
    assert checked, f"{table} has no recorded cell"


def _amendment_rows(section: str) -> tuple[dict[str, str], list[list[str]]]:
    """Amendment 1's table: its state columns' record directories and the task rows of ``section``; skips the test
    while the table is not committed."""
    if not os.path.exists(METAWORLD_TARGET):
        pytest.skip("no committed table of amendment 1 yet")
    with open(METAWORLD_TARGET) as f:
        text = f.read()
    _, variants = _metaworld_columns(text)
    return variants, [r for r in _tables(text)[section] if r[0].startswith("metaworld-target:")]


def test_metaworld_target_secondary_comparison_recomputes_from_the_records():
    """Amendment 1's secondary comparison: each task's DP on absolute targets − DP on displacements (the main
    campaign's DP of the same task), paired on the shared initial states, from the two campaigns' run records."""
    variants, rows = _amendment_rows("Amendment 1, secondary: DP on absolute targets against DP on displacements")
    checked = 0
    for row in rows:
        target = _metaworld_runs(row[0], variants["DP"])
        displaced = _metaworld_runs("metaworld:" + row[0].partition(":")[2], variants["DP"])
        assert displaced, f"{row[0]}: the main campaign holds no DP record of this task"
        for runs, cell in ((displaced, row[1]), (target, row[2])):
            rates = [np.asarray(e["success"], float) for e in runs.values()]
            if not rates:
                assert cell == "–", (row[0], cell)
                continue
            _close(_parse(cell)[0], 100 * _seed_level(rates, lo_hi=(0.0, 1.0))[0], f"{row[0]} {cell}")
        shared = sorted(set(target) & set(displaced))
        diffs = [np.asarray(target[s]["success"], float) - np.asarray(displaced[s]["success"], float)
                 for s in shared]
        cell = row[3]
        verdict = _parse(cell)[4] if cell != "–" else None
        _check_cell(cell.split(", p=")[0] + (f" {verdict}" if verdict else ""), diffs or None,
                    f"{row[0]} DP on targets − DP on displacements")
        checked += 1
    assert checked, "the amendment's table has no task row"


def test_metaworld_target_steps_saved_recompute_from_the_records():
    """Amendment 1's steps to success: per seed, over the episodes both DP and DP+HiPolicy succeeded in on the shared
    initial states, 100 · mean(DP − DP+HiPolicy steps) / mean(DP steps); the mean over seeds, its t interval and
    the verdict the table prints; '–' where no seed has such an episode."""
    variants, rows = _amendment_rows("Amendment 1, secondary: steps to success, DP+HiPolicy against DP (targets)")
    checked = 0
    for row in rows:
        dp, hip = (_metaworld_runs(row[0], variants[c]) for c in ("DP", "DP+HiPolicy"))
        saved = []
        for seed in sorted(set(dp) & set(hip)):
            both = np.asarray(dp[seed]["success"], bool) & np.asarray(hip[seed]["success"], bool)
            if both.any():
                base = np.asarray(dp[seed]["steps"], float)[both]
                saved.append((base - np.asarray(hip[seed]["steps"], float)[both]) / base.mean())
        cell = row[6]
        if not saved:
            assert cell == "–", (row[0], cell)
            continue
        m, lo, hi, _, _ = _parse(cell.split(", p=")[0])
        est = _seed_level(saved, lo_hi=(-math.inf, math.inf))
        _close(m, 100 * est[0], f"{row[0]} steps saved")
        if math.isfinite(est[1]):
            _close(lo, 100 * est[1], f"{row[0]} steps saved (low)")
            _close(hi, 100 * est[2], f"{row[0]} steps saved (high)")
            expected = "faster" if est[1] > 0 else "slower" if est[2] < 0 else "no difference"
            assert cell.endswith(f"({expected})"), (row[0], cell, expected)
        checked += 1
    assert checked, "the amendment's steps table has no recorded cell"
