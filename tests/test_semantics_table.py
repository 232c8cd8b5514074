"""results/semantics.md (PROTOCOL amendment 4): DP vs DP+HiPolicy under rate and waypoint execution, with and
without a controller speed limit — the jobs, the evaluation keys and every cell of the table on fake records."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from experiments import paper
from hipolicy_jax.campaigns import report, tables
from hipolicy_jax.campaigns.budgets import BUDGETS
from hipolicy_jax.campaigns.campaign import evaluation_key
from hipolicy_jax.config import InferenceConfig


def _records(columns, tasks, seeds, rng, episodes=12):
    out = []
    for t in tasks:
        for s in seeds:
            for c in columns:
                success = rng.random(episodes) < 0.8
                steps = rng.integers(30, 120, episodes)
                actions = steps - rng.integers(0, 10, episodes) if "waypoint" in c else steps
                out.append({"task": t, "seed": s, "column": c, "success_rate": float(success.mean()),
                            "success": success.tolist(), "steps": steps.tolist(), "actions": actions.tolist(),
                            "decisions": (actions // 8 + 1).tolist(), "run": f"{t}/{c}/{s}", "training_s": 1.0,
                            "eval_s": 1.0})
    return out


def _saving(records, task, seed, new, base, count):
    a = next(r for r in records if (r["task"], r["seed"], r["column"]) == (task, seed, new))
    b = next(r for r in records if (r["task"], r["seed"], r["column"]) == (task, seed, base))
    both = np.asarray(a["success"]) & np.asarray(b["success"])
    return np.mean(np.asarray(a[count])[both]) / np.mean(np.asarray(b[count])[both]) - 1.0


def test_relative_count_difference_closed_form():
    recs = [{"task": "t", "seed": 0, "column": "new", "success": [1, 1, 0], "steps": [10, 20, 99]},
            {"task": "t", "seed": 0, "column": "base", "success": [1, 1, 1], "steps": [20, 40, 5]},
            {"task": "t", "seed": 1, "column": "new", "success": [1, 0, 1], "steps": [30, 1, 30]},
            {"task": "t", "seed": 1, "column": "base", "success": [1, 1, 1], "steps": [40, 1, 40]}]
    est = report.relative_count_difference(recs, (0, 1), ["t"], "new", "base", "steps")
    assert est.mean == pytest.approx(np.mean([15 / 30 - 1, 30 / 40 - 1]))  # -0.5 and -0.25
    # before actions were counted (rate: one per control step) a record's actions are its steps
    assert report.relative_count_difference(recs, (0, 1), ["t"], "new", "base", "actions").mean == est.mean
    with pytest.raises(ValueError, match="count: one of"):
        report.relative_count_difference(recs, (0, 1), ["t"], "new", "base", "episodes")


def test_semantics_jobs_share_one_run_per_network_and_keys_differ():
    args = paper.parse_args(["campaign", "--budget", "smoke", "--tasks", "press_button", "stack_cubes",
                             "--seeds", "0", "1", "2", "--only", "semantics", "--no-progress"])
    (t,) = tables.protocol_tables(args)
    assert isinstance(t, tables.SemanticsArgs) and t.tasks == ("press_button", "stack_cubes")
    jobs, _ = tables.campaign_jobs(args, [t])
    assert len(jobs) == 2 * 8 * 3
    assert {j.changes for j in jobs} == {(("train.num_steps", 8000),)}
    runs = {(j.task, j.col.changes, j.seed) for j in jobs}
    assert len(runs) == 2 * 2 * 3  # 4 settings per network
    keys = {evaluation_key(InferenceConfig(semantics=j.col.semantics, controller_speed=j.col.controller_speed),
                           j.col, 100, j.seed) for j in jobs if j.task == "press_button" and j.seed == 0}
    assert len(keys) == 4  # DP and DP+HiPolicy of one setting share a key: they are other networks
    rate = [k for k in keys if "semantics" not in json.loads(k)]
    assert len(rate) == 1  # the rate evaluation's key is the one the budget table's evaluations have
    # without --only semantics the campaign has no semantics table (its runs have not been made)
    plain = paper.parse_args(["campaign", "--budget", "smoke", "--tasks", "press_button", "--no-progress"])
    assert not any(isinstance(x, tables.SemanticsArgs) for x in tables.protocol_tables(plain))


def test_semantics_table_recomputes(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    args = tables.SemanticsArgs(budget="smoke", seeds=(0, 1, 2), results=str(tmp_path), runs=str(tmp_path / "r"),
                                data=str(tmp_path / "d"), progress=False)
    labels = [c.label for c in tables.semantics_columns(args)]
    assert labels[:2] == ["DP (rate)", "DP+HiPolicy (rate)"] and "DP+HiPolicy (waypoint, 0.25 m/s)" in labels
    fake = _records(labels, args.tasks, args.seeds, rng)
    monkeypatch.setattr(tables.common, "collect", lambda a, columns: fake)
    text = open(paper.main(args)).read()
    rows = [[c.strip() for c in line.strip("|").split(" | ")] for line in text.splitlines()
            if line.startswith("| ") and not line.startswith("| :---")][1:]
    assert len(rows) == 3 * 4  # 2 tasks and the average, 4 settings each
    for task, setting, dp_sr, hp_sr, _, *saved in rows:
        dp, hp = f"DP ({setting})", f"DP+HiPolicy ({setting})"
        tasks = list(args.tasks) if task == "**Average**" else [task]
        for count, cell in zip(("decisions", "actions", "steps"), saved):
            values = [[_saving(fake, t, s, hp, dp, count) for s in args.seeds] for t in tasks]
            mean = 100 * np.mean([np.mean(v) for v in values])
            assert float(cell.split()[0]) == pytest.approx(mean, abs=0.051), (task, setting, count)
        if task != "**Average**":
            sr = 100 * np.mean([np.mean(next(r for r in fake if (r["task"], r["seed"], r["column"]) ==
                                              (task, s, dp))["success"]) for s in args.seeds])
            assert float(dp_sr.split()[0]) == pytest.approx(sr, abs=0.051)
    # rate without a speed limit: one action per control step, so actions and control steps save the same
    rate = next(r for r in rows if r[:2] == ["press_button", "rate"])
    assert rate[6] == rate[7]
    assert not math.isnan(float(rate[5].split()[0]))
    assert BUDGETS["smoke"].train.num_steps != args.steps
