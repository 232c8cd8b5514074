"""Amendment 2 of the Meta-World protocol (``campaigns.metaworld_amendment2``): T_task from a demo buffer, the plateau
and budget rules by hand, the job list and its variant names, the evaluation keys of the new columns (the old ones
unchanged), the reading rule, and the tables rebuilt from fake records, every cell recomputed here. Nothing here
trains, serves a policy or runs the bridge."""

import dataclasses
import itertools
import json
import math
import os

import numpy as np
import pytest
from scipy import stats as sps

from hipolicy_jax.campaigns import budgets as budgets_lib
from hipolicy_jax.campaigns import metaworld_amendment2 as a2
from hipolicy_jax.campaigns.budgets import DP
from hipolicy_jax.campaigns.campaign import (RECORD_VERSION, Campaign, Column, check_column, evaluation_key,
                                             record_path)
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.evaluation.stats import Estimate
from hipolicy_jax.runs.store import write_json

TOTALS = {"bin-picking": 22202, "stick-push": 17152, "coffee-pull": 18560, "hand-insert": 13913,
          "pick-out-of-hole": 26506}


def _args(tmp_path, **kw):
    steps_file = tmp_path / "t_task.json"
    if not steps_file.exists():
        write_json(str(steps_file), {"tasks": {t: {"T": n, "epochs": 3000, "batch": 128} for t, n in TOTALS.items()}})
    base = dict(runs=str(tmp_path / "runs"), records=str(tmp_path / "rec"), data=str(tmp_path / "data"),
                results=str(tmp_path / "res"), steps_file=str(steps_file), progress=False)
    return a2.Amendment2Args(**{**base, **kw})


def test_t_task_from_a_toy_buffer(tmp_path):
    """W = frames · (E − 1) / E for 11 demos (one held out); T = round(3000 · W / 128), half up; written to the
    steps file once, then read from it (the buffer no longer needed)."""
    lengths = list(range(50, 61))  # 11 demos, 605 frames
    episodes = [{"state": np.zeros((n, 39), np.float32), "action": np.zeros((n, 4), np.float32)} for n in lengths]
    args = a2.Amendment2Args(runs=str(tmp_path / "runs"), data=str(tmp_path / "data"),
                             steps_file=str(tmp_path / "t.json"), results=str(tmp_path / "res"), fraction=0.5)
    cfg = Campaign("metaworld", runs=args.runs, data=args.data).run_config(
        "metaworld-target:hand-insert", a2.columns("metaworld-target:hand-insert").dp, 0)
    os.makedirs(args.data)
    ReplayBuffer.from_episodes(episodes).save(cfg.data_path())
    assert cfg.data_path().endswith("metaworld-target_hand-insert_11.zarr")
    # 605 · 10 / 11 = 550 windows; 3000 · 550 / 128 = 12890.625 → 12891
    assert a2.task_total(args, "metaworld-target:hand-insert", collect=False) == 12891
    entry = json.loads((tmp_path / "t.json").read_text())["tasks"]["hand-insert"]
    assert (entry["frames"], entry["episodes"], entry["windows"], entry["T"]) == (605, 11, 550.0, 12891)
    import shutil

    shutil.rmtree(cfg.data_path())
    assert a2.task_total(args, "metaworld:hand-insert", collect=False) == 12891  # arm B: the same demos, the file
    assert a2.run_changes(args, "metaworld-target:hand-insert") == {"train.batch_size": 128,
                                                                     "train.num_steps": 2 * (12891 // 4)}
    with pytest.raises(ValueError, match="steps_file: .* has no T_task for coffee-pull"):
        a2.task_total(args, "metaworld-target:coffee-pull", collect=False)
    # the amendment's own numbers: hand-insert 653 frames, pick-out-of-hole 1244 (11 demos each)
    assert a2.training_windows(653, 11, 0.1) == pytest.approx(593.636, abs=1e-3)
    assert a2.task_steps(a2.training_windows(653, 11, 0.1)) == 13913
    assert a2.task_steps(a2.training_windows(1244, 11, 0.1)) == 26506
    assert a2.task_steps(64, epochs=3000, batch=128) == 1500 and a2.task_steps(0.1, 10, 4) == 1  # 0.25: at least 1
    assert a2.task_steps(1.0, epochs=2, batch=4) == 1  # 0.5 rounds half up
    assert a2.fraction_steps(13913) == (3478, 6956, 10434, 13913) and a2.steps_at(13913, 0.75) == 10434
    with pytest.raises(ValueError, match="fraction"):
        a2.steps_at(13913, 0.3)
    with pytest.raises(ValueError, match="episodes"):
        a2.training_windows(10, 1, 0.1)


def test_plateau_rule_and_budget_phrase():
    assert a2.choose_fraction({0.25: [0.2, 0.4], 0.5: [0.5, 0.6], 0.75: [0.6, 0.6], 1.0: [0.55, 0.6]}) == 0.5
    # best 0.53 (f = 1); 0.75's 0.50 is within 5 points, 0.5's 0.30 is not
    assert a2.choose_fraction({0.25: [0.1, 0.1], 0.5: [0.3, 0.3], 0.75: [0.5, 0.5], 1.0: [0.56, 0.5]}) == 0.75
    assert a2.choose_fraction({0.25: [0.0, 0.0], 0.5: [0.0, 0.0], 0.75: [0.0, 0.0], 1.0: [0.0, 0.0]}) == 0.25
    assert a2.budget_phrase(1.0) == "DP3's budget" and a2.budget_phrase(0.5) == "the plateau, 0.5·T"


def test_budget_rule_by_hand():
    # a DP network: 0.1 s/step, 20 s per 100 waypoint episodes, 10 per 100 rate episodes; DP+HiPolicy: a train step
    # × 2, an episode × 10. Episodes per network: DP 100 + 100; DP+HiPolicy waypoint 50 + 100 + 100 + 7·50 + 100 =
    # 700, rate 50 + 100 = 150.
    assert a2.episodes_per_network() == {"DP": {"waypoint": 100, "rate": 100},
                                         "DP+HiPolicy": {"waypoint": 700, "rate": 150}}
    rates = a2.Rates(0.1, {"waypoint": 20.0, "rate": 10.0}, 2.0, 10.0)
    # at n steps: DP 0.1 n + 20 + 10; DP+HiPolicy 0.2 n + 10 (7 · 20 + 1.5 · 10) = 0.2 n + 1550
    assert a2.network_costs(1000, rates) == pytest.approx({"DP": 130.0, "DP+HiPolicy": 1750.0})
    assert a2.task_cost(1000, rates) == pytest.approx(3 * 1880.0)
    # a task at n steps costs 0.9 n + 4740; T_task 4000 for all five: n = 4000 / 3000 / 2000 / 1000 by fraction
    totals = [4000] * 5
    r = a2.budget_rule(left_s=41700, totals=totals, fraction=1.0, rates=rates)
    assert (r["fraction"], r["tasks"]) == (1.0, 5) and r["task_cost_s"] == pytest.approx([8340.0] * 5)
    r = a2.budget_rule(left_s=30000, totals=totals, fraction=1.0, rates=rates)  # 3 · 8340 = 25020 fits, 4 do not
    assert (r["fraction"], r["tasks"], r["tried"]) == (1.0, 3, [(1.0, 3)])
    # 3 tasks fit at neither f = 1 (25020) nor 3/4 (3 · 7440 = 22320); at 1/2, 3 · 6540 = 19620 does, 4 do not
    r = a2.budget_rule(left_s=20000, totals=totals, fraction=1.0, rates=rates)
    assert (r["fraction"], r["tasks"], r["tried"]) == (0.5, 3, [(1.0, None), (0.75, None), (0.5, 3)])
    r = a2.budget_rule(left_s=20000, totals=totals, fraction=0.75, rates=rates)  # starts at the plateau's f
    assert r["tried"][0] == (0.75, None) and r["fraction"] == 0.5
    r = a2.budget_rule(left_s=10000, totals=totals, fraction=1.0, rates=rates)  # 3 · 5640 = 16920 at 1/4
    assert r["fraction"] is None and r["tasks"] is None and len(r["tried"]) == 4
    assert a2.fitting_prefix([5.0, 5.0, 5.0], 12.0, 1) == 2 and a2.arm_b_tasks([5.0, 5.0, 5.0], 12.0) == 2
    assert a2.arm_b_tasks([20.0, 1.0], 12.0) == 1  # at least one task
    with pytest.raises(ValueError, match="fraction"):
        a2.budget_rule(left_s=1.0, totals=totals, fraction=0.6, rates=rates)


def test_reading_rule():
    e = lambda mean, low, high: Estimate(mean, low, high)  # noqa: E731
    assert a2.reading_rule(e(-0.02, -0.08, 0.04)) == "keeps"
    assert a2.reading_rule(e(-0.05, -0.09, -0.01)) == "keeps; significant loss"
    assert a2.reading_rule(e(-0.2, -0.3, -0.1)) == "loses"
    assert a2.reading_rule(e(-0.05, -0.15, 0.05)) == "inconclusive"
    assert a2.reading_rule(e(-0.05, -0.10, -0.01)) == "loses"  # the lower end must be above −10 points to keep
    assert a2.reading_rule(e(0.1, 0.05, 0.15)) == "keeps"
    assert a2.reading_rule(e(0.1, math.nan, math.nan)) == "–"


def test_job_list_order_steps_batch_and_variant_names(tmp_path, monkeypatch):
    args = _args(tmp_path, fraction=0.5)
    jobs = a2.amendment2_jobs(args)
    tasks = [f"metaworld-target:{t}" for t in a2.TASKS]
    assert list(dict.fromkeys(j.task for j in jobs)) == tasks
    labels = ["DP", "DP+HiPolicy", "DP (rate)", "DP+HiPolicy (rate)", "DP+HiPolicy (demo thresholds)",
              "DP+HiPolicy (success rule)", "DP+HiPolicy at stride 1"]
    assert [(j.task, j.col.label, j.seed) for j in jobs] == [(t, c, s) for t in tasks for c in labels
                                                             for s in (0, 1, 2)]
    camp = Campaign("metaworld", runs=args.runs)
    for j in jobs:
        bare = j.task.partition(":")[2]
        n = 2 * (TOTALS[bare] // 4)
        assert dict(j.changes) == {"train.batch_size": 128, "train.num_steps": n}
        cfg = camp.run_config(j.task, j.col, j.seed, dict(j.changes))
        assert cfg.train.batch_size == 128 and cfg.train.num_steps == n
        variant = "dp" if j.col.label.startswith("DP (") or j.col.label == "DP" else "hipolicy"
        assert cfg.out_dir() == os.path.join(args.runs, "metaworld", f"metaworld-target_{bare}", "state",
                                             f"{variant}_kinds-aaaa_batchsize128_t{n}", f"seed{j.seed}")
        assert cfg.policy.chunk.strides == ((1,) if variant == "dp" else (1, 2, 3))
    # the older campaigns' variants: other directories, so nothing old is reused
    old = camp.run_config("metaworld-target:bin-picking", Column("DP", "state", DP), 0, {"train.num_steps": 4000})
    assert os.path.basename(os.path.dirname(old.out_dir())) == "dp_t4000"
    # arm B: displacements, summed deltas declared in the name
    b = a2.amendment2_jobs(_args(tmp_path, arm="b", tasks=("bin-picking",), fraction=1.0))
    cfg = camp.run_config(b[3].task, b[3].col, b[3].seed, dict(b[3].changes))
    assert b[3].task == "metaworld:bin-picking" and cfg.policy.chunk.action_kinds == ("delta", "delta", "delta",
                                                                                      "absolute")
    variant = f"hipolicy_kinds-ddda_batchsize128_t{TOTALS['bin-picking']}"
    assert os.path.basename(os.path.dirname(cfg.out_dir())) == variant
    # the pilot entry of 2026-12-07 (results/metaworld/PROTOCOL.md) fixed f and K as pilot_choice.json says
    choice = json.load(open(os.path.join(a2.RESULTS, "pilot_choice.json")))
    assert (budgets_lib.METAWORLD_A2_FRACTION, budgets_lib.METAWORLD_A2_TASKS) == (0.25, 5)
    assert (choice["fraction"], choice["budget_rule"]["fraction"], choice["budget_rule"]["tasks"]) == (0.25, 0.25, 5)
    # f not fixed: one line naming the field and the pilot
    monkeypatch.setattr(budgets_lib, "METAWORLD_A2_FRACTION", None)
    with pytest.raises(ValueError, match="fraction: amendment 2's training length f is not fixed yet"):
        a2.amendment2_jobs(_args(tmp_path))
    with pytest.raises(ValueError, match="tasks: arm b's tasks are not fixed yet"):
        a2.amendment2_jobs(_args(tmp_path, arm="b", fraction=1.0))
    with pytest.raises(ValueError, match="tasks: arm a runs on metaworld-target"):
        _args(tmp_path, tasks=("metaworld:bin-picking",))
    with pytest.raises(ValueError, match="fraction: must be one of"):
        _args(tmp_path, fraction=0.3)


OLD_KEY = ('{"episodes": 100, "eval_seed": 3, "execution": "chunk", "guided": true, "num_samples": 16, '
           '"num_steps": 10, "percentiles": null, "sampler": "auto", "te_decay": null}')


def test_evaluation_keys_of_the_new_columns_and_the_old_ones_unchanged():
    inference = InferenceConfig(num_samples=16, sampler="auto", num_steps=10, calib_windows=128)
    for col in (Column("DP", "state", DP), Column("DP+HiPolicy"), Column("DP+HiPolicy", calibration="demos")):
        assert evaluation_key(inference, col, 100, 3) == OLD_KEY
    camp = Campaign("metaworld")
    cols = a2.columns("metaworld-target:bin-picking")
    keys = {c.label: camp._key(c, 3)[1] for c in cols}
    # one key per evaluation of a network (keys are per run record: DP's and DP+HiPolicy's are two records)
    dp_keys = {keys[c.label] for c in cols if c.changes == cols.dp.changes}
    hip_keys = {keys[c.label] for c in cols if c.changes == cols.hip.changes}
    assert len(dp_keys) == 2 and len(hip_keys) == 5 and OLD_KEY not in keys.values()
    primary = json.loads(keys["DP+HiPolicy"])
    assert primary["semantics"] == "waypoint" and primary["max_steps"] == 500
    assert primary["calibration"] == {"source": "rollouts", "rule": "percentiles", "episodes": 50}
    assert json.loads(keys["DP+HiPolicy (success rule)"])["calibration"]["margin"] == 0.05
    assert "calibration" not in json.loads(keys["DP+HiPolicy (demo thresholds)"])
    assert json.loads(keys["DP+HiPolicy at stride 1"])["guided"] is False
    rate = json.loads(keys["DP (rate)"])
    assert "semantics" not in rate and rate["max_steps"] == 500
    with pytest.raises(ValueError, match="calibration must be one of"):
        check_column(Column("x", calibration="closed"))
    with pytest.raises(ValueError, match="max_steps must be None"):
        check_column(Column("x", max_steps=0))


# ------------------------------------------------------------------------------------------ tables from records

TASKS2 = ("bin-picking", "hand-insert")
E = 8  # episodes per evaluation in the fake records


def _fake_evaluation(rng, key: str, strides: int) -> dict:
    success = rng.random(E) < rng.uniform(0.4, 0.95)
    success[0] = True  # every pair of columns solves initial state 0: the savings have a state on every seed
    decisions = rng.integers(5, 30, E)
    actions = decisions * 8 - rng.integers(0, 4, E)
    steps = actions + rng.integers(0, 40, E)
    fracs = rng.dirichlet(np.ones(3)) if strides > 1 else np.array([1.0, 0.0, 0.0])
    ev = {"settings": json.loads(key), "success": success.tolist(), "steps": steps.tolist(),
          "decisions": decisions.tolist(), "actions": actions.tolist(), "success_rate": float(success.mean()),
          "stride1_frac": float(fracs[0]), "eval_s": 10.0, "eval_cpu_s": 9.0, "cpu_cores": 1}
    if json.loads(key).get("semantics") is None:  # rate: the bridge counts the actions its bound clipped
        ev["clipped"] = rng.integers(0, 4, E).tolist()
    if strides > 1:
        ev.update(stride2_frac=float(fracs[1]), stride3_frac=float(fracs[2]),
                  calibration={"intended_mix": {"1": 0.1, "2": 0.6, "3": 0.3}})
    return ev


def _write_fake_records(args) -> list:
    """One record per network (DP, DP+HiPolicy × task × seed) holding its columns' evaluations under their keys."""
    camp = Campaign(args.budget, runs=args.runs, records=args.records, episodes=E)
    rng = np.random.default_rng(7)
    by_path: dict[str, dict] = {}
    for job in a2.amendment2_jobs(args):
        cfg = camp.run_config(job.task, job.col, job.seed, dict(job.changes))
        path = record_path(args.records, args.runs, cfg)
        rec = by_path.setdefault(path, {"version": RECORD_VERSION, "budget": args.budget, "task": job.task,
                                        "seed": job.seed, "training": {"steps": cfg.train.num_steps,
                                                                       "wall_time_s": 100.0, "cpu_time_s": 90.0,
                                                                       "cpu_cores": 1},
                                        "evaluations": {}})
        key = camp._key(job.col, job.seed)[1]
        rec["evaluations"][key] = _fake_evaluation(rng, key, len(cfg.policy.chunk.strides))
    for path, rec in by_path.items():
        write_json(path, rec)
    return list(by_path)


def _t_interval(values, bounds=None):
    v = np.asarray(values, float)
    m, se = v.mean(), v.std(ddof=1) / math.sqrt(v.size)
    half = sps.t.ppf(0.975, v.size - 1) * se
    lo, hi = m - half, m + half
    if bounds:
        lo, hi = max(lo, bounds[0]), min(hi, bounds[1])
    return m, lo, hi, se, v.size - 1.0


def _welch(per_task, bounds=None):
    m = np.mean([t[0] for t in per_task])
    var = [t[3] ** 2 for t in per_task]
    se = math.sqrt(sum(var)) / len(per_task)
    df = sum(var) ** 2 / sum(v ** 2 / t[4] for v, t in zip(var, per_task))
    half = sps.t.ppf(0.975, df) * se
    lo, hi = m - half, m + half
    if bounds:
        lo, hi = max(lo, bounds[0]), min(hi, bounds[1])
    return m, lo, hi, se, df


def _text(iv, scale=1.0, signed=False):
    fmt = "+.1f" if signed else ".1f"
    m, lo, hi = (x * scale for x in iv[:3])
    return f"{m:{fmt}} [{lo:{fmt}}, {hi:{fmt}}]"


def _p(iv):
    m, _, _, se, df = iv
    return f"{2 * sps.t.sf(abs(m) / se, df):.2g}"


def _sign_flip(per_task_seed_values):
    flat = [(v, 1.0 / (len(vals) * len(per_task_seed_values))) for vals in per_task_seed_values for v in vals]
    observed = abs(sum(v * w for v, w in flat))
    count = sum(abs(sum(s * v * w for s, (v, w) in zip(signs, flat))) >= observed - 1e-12
                for signs in itertools.product((1, -1), repeat=len(flat)))
    return f"{count / 2 ** len(flat):.2g}"


def _reading(iv):
    keeps, below = iv[1] > -0.10, iv[2] < 0
    return ("keeps; significant loss" if below else "keeps") if keeps else ("loses" if below else "inconclusive")


def _rows(section: str) -> list[list[str]]:
    return [[c.strip() for c in line.strip()[1:-1].split("|")] for line in section.splitlines()
            if line.startswith("| ") and not line.startswith("| Task") and not line.startswith("| :")]


def test_tables_rebuild_from_records_and_every_cell_recomputes(tmp_path):
    args = _args(tmp_path, tasks=TASKS2, fraction=1.0, from_records=True, episodes=E)
    _write_fake_records(args)
    md = a2.amendment2_table(args)
    text = open(md).read()
    assert md == os.path.join(args.results, "amendment2.md") and "(interim)" not in text
    assert "training DP3's budget (f = 1 of T_task" in text and "bin-picking: 22202 of 22202" in text
    records = json.loads(open(os.path.join(args.results, "amendment2.json")).read())["records"]
    assert len(records) == 2 * 3 * 7
    rec = {(r["task"], r["column"], r["seed"]): r for r in records}
    tasks = [f"metaworld-target:{t}" for t in TASKS2]
    sections = text.split("\n## ")[1:]
    assert len(sections) == len(a2.COMPARISONS) + 2
    for section, (new, base, title, _) in zip(sections, a2.COMPARISONS):
        assert section.startswith(title)
        success_part, savings_part = section.split("What it saves")
        got = _rows(success_part)
        per_task = {}
        for row, task in zip(got, tasks):
            b = [np.mean(rec[task, base, s]["success"]) for s in (0, 1, 2)]
            n = [np.mean(rec[task, new, s]["success"]) for s in (0, 1, 2)]
            d = [np.mean(np.asarray(rec[task, new, s]["success"], float) - rec[task, base, s]["success"])
                 for s in (0, 1, 2)]
            assert len(set(b)) > 1 and len(set(n)) > 1 and len(set(d)) > 1  # no equal-seed fallback here
            ivs = [_t_interval(b, (0, 1)), _t_interval(n, (0, 1)), _t_interval(d, (-1, 1))]
            per_task[task] = (ivs, d)
            assert row == [task, _text(ivs[0], 100), _text(ivs[1], 100), _text(ivs[2], 100, True), _p(ivs[2]),
                           _sign_flip([d]), _reading(ivs[2])], (title, task)
        avg = [_welch([per_task[t][0][i] for t in tasks], bounds) for i, bounds in
               enumerate([(0, 1), (0, 1), (-1, 1)])]
        assert got[-1] == ["**Average**", _text(avg[0], 100), _text(avg[1], 100), _text(avg[2], 100, True),
                           _p(avg[2]), _sign_flip([per_task[t][1] for t in tasks]), _reading(avg[2])], title
        # savings: on the states both columns solved, per seed
        got = _rows(savings_part)
        cells_avg = {}
        for row, task in zip(got, tasks):
            expect = [task]
            for field in ("decisions", "actions", "steps"):
                bm, nm, rel = [], [], []
                for s in (0, 1, 2):
                    a, b = rec[task, new, s], rec[task, base, s]
                    both = np.asarray(a["success"], bool) & np.asarray(b["success"], bool)
                    bm.append(np.mean(np.asarray(b[field], float)[both]))
                    nm.append(np.mean(np.asarray(a[field], float)[both]))
                    rel.append((nm[-1] - bm[-1]) / bm[-1])
                ivs = [_t_interval(bm, (0, math.inf)), _t_interval(nm, (0, math.inf)), _t_interval(rel)]
                cells_avg.setdefault(field, []).append(ivs)
                expect += [_text(ivs[0]), _text(ivs[1]), _text(ivs[2], 100, True)]
            assert row == expect, (title, task)
        expect = ["**Average**"]
        for field in ("decisions", "actions", "steps"):
            ivs = cells_avg[field]
            expect += [_text(_welch([i[0] for i in ivs], (0, math.inf))),
                       _text(_welch([i[1] for i in ivs], (0, math.inf))),
                       _text(_welch([i[2] for i in ivs]), 100, True)]
        assert got[-1] == expect, title
    # the stride mixes: intended (the calibration's) → achieved (mean over seeds)
    mix = _rows(sections[-2])
    for row, task in zip(mix, tasks):
        cells = []
        for column in a2.HIP_COLUMNS:
            ach = [np.mean([rec[task, column, s][f"stride{k}_frac"] for s in (0, 1, 2)]) for k in (1, 2, 3)]
            cells.append("10 / 60 / 30 → " + " / ".join(f"{100 * v:.0f}" for v in ach))
        assert row == [task, *cells]
    # the clipped share under rate: per network Σ clipped / Σ actions, t interval over seeds, Welch over tasks
    clipped = _rows(sections[-1])
    per = {c: [_t_interval([sum(rec[t, c, s]["clipped"]) / sum(rec[t, c, s]["actions"]) for s in (0, 1, 2)],
                           (0, 1)) for t in tasks] for c in ("DP (rate)", "DP+HiPolicy (rate)")}
    assert clipped == [[task, *(_text(per[c][i], 100) for c in per)] for i, task in enumerate(tasks)] + [
        ["**Average**", *(_text(_welch(per[c], (0, 1)), 100) for c in per)]]
    # interim: a record missing → the title and a note say so; the cells of that task's pair go to its seeds
    missing = a2.amendment2_jobs(args)[0]
    camp = Campaign(args.budget, runs=args.runs, records=args.records, episodes=E)
    path = record_path(args.records, args.runs, camp.run_config(missing.task, missing.col, missing.seed,
                                                                dict(missing.changes)))
    os.remove(path)  # DP seed 0 of bin-picking: its waypoint and rate evaluations
    text = open(a2.amendment2_table(args)).read()
    assert "(interim)" in text.splitlines()[0] and f"**Interim: {2 * 3 * 7 - 2} of {2 * 3 * 7} evaluations recorded**" \
        in text


def test_plan_lists_the_pending_jobs_and_the_budget_rules_estimate(tmp_path, monkeypatch):
    from experiments.metaworld import main as metaworld, parse_args

    args = _args(tmp_path, fraction=0.5, tasks=("bin-picking",), plan=True)
    choice = {"rates": {"train_s_per_step": 0.1, "eval_s_per_100": {"waypoint": 20.0, "rate": 10.0},
                        "hip_train_factor": 2.0, "hip_eval_factor": 10.0}}
    write_json(str(tmp_path / "pilot_choice.json"), choice)  # the pilot's, beside its t_task.json
    flags = ["--runs", args.runs, "--records", args.records, "--data", args.data, "--results", args.results,
             "--steps-file", args.steps_file, "--tasks", "bin-picking", "--fraction", "0.5", "--plan",
             "--no-progress"]
    path = metaworld(parse_args(["amendment2", *flags]))
    text = open(path).read()
    assert path == os.path.join(args.results, "plan.md")
    assert "21 of 21 evaluations pending, 6 runs to train (f = 0.5, batch 128" in text
    n = 2 * (TOTALS["bin-picking"] // 4)  # a task at n steps: 3 · (0.3 n + 1580) CPU-s (test_budget_rule_by_hand)
    expected = 3 * (0.3 * n + 1580) / 3600
    assert f"metaworld-target:bin-picking: {expected:.1f} h; {expected:.1f} CPU-hours in all." in text
    assert "| metaworld-target:bin-picking | DP+HiPolicy (success rule) | 2 |" in text
    assert not os.path.exists(args.runs)  # a plan trains nothing
    # --no-tables with a deadline already past: nothing starts, the plan is written, no table (a calibrate_run that
    # takes the columns' step limit, as the campaign requires before it starts)
    from hipolicy_jax.runs import calibrate as calibrate_lib

    monkeypatch.setattr(calibrate_lib, "calibrate_run", lambda run, inference, source="demos", *, max_steps=None,
                        **kw: pytest.fail("calibrated"))
    path = metaworld(parse_args(["amendment2", *flags[:-2], "--no-tables", "--until", "2000-01-01 00:00",
                                 "--no-progress"]))
    assert path == os.path.join(args.results, "plan.md") and not os.path.exists(args.runs)
    assert not os.path.exists(os.path.join(args.results, "amendment2.md"))


# ------------------------------------------------------------- the campaign's external evaluation of a new column


class _Policy:
    def __init__(self, strides):
        from hipolicy_jax.config import ChunkConfig, PolicyConfig

        self.cfg = PolicyConfig(chunk=ChunkConfig(strides=strides))
        self.params = {"w": np.arange(6, dtype=np.float32).reshape(2, 3)}
        self.step = 40
        self.meta = {"train": {"ckpt_every": 10}}


class _Run:
    def __init__(self, run_dir, strides=(1, 2, 3)):
        self.run_dir, self.task, self.seed = str(run_dir), "metaworld-target:bin-picking", 1
        self.policy = _Policy(strides)


def _bridge_record(episodes):
    eps = [{"seed": 1_001_000 + i, "success": i % 2 == 0, "steps": 100 + i, "decisions": 10 + i, "actions": 60 + i,
            "strides": {"1": 2, "2": 3, "3": 5 + i}, "mean_entropy": 0.5, "clipped": i} for i in range(episodes)]
    return {"per_episode": eps, "wall_s": 3.0, "cpu_s": 2.5, "seconds": {"total": 3.0},
            "successes": sum(e["success"] for e in eps), "episodes": episodes}


def test_closed_loop_columns_calibrate_once_per_network_at_the_columns_step_limit(tmp_path, monkeypatch):
    """A closed-loop column (``calibration='rollouts'`` / ``'success'``) calibrates through ``runs.calibrate`` once per
    network (kept in the run dir with its fingerprint), serves the evaluation at those thresholds with the column's
    semantics and step limit, and records where its thresholds came from; a stride-1 column turns guidance off; the
    demo column reads the run's ``calibration.json``."""
    from hipolicy_jax.evaluation import calibration
    from hipolicy_jax.runs import calibrate as calibrate_lib
    from hipolicy_jax.runs import external as external_lib

    served, calibrations = [], []

    def fake_evaluate_run(run_dir, *, episodes, first_seed, max_steps, inference=None, keep=False, **kw):
        served.append({"first_seed": first_seed, "max_steps": max_steps, "inference": inference})
        return _bridge_record(episodes)

    def fake_calibrate_run(run, inference, source="demos", *, episodes=20, seed=None, out="", rule="percentiles",
                           margin=0.05, max_steps=None, **kw):
        calibrations.append({"source": source, "rule": rule, "episodes": episodes, "seed": seed, "margin": margin,
                             "max_steps": max_steps, "semantics": inference.semantics, "out": out})
        return {"thresholds": [-math.inf, 0.25, 0.75, math.inf], "percentiles": [10.0, 70.0], "source": source,
                "rule": rule, "episodes": episodes, "first_seed": 3_000_000 + 1000 * seed,
                "intended_mix": {"1": 0.1, "2": 0.6, "3": 0.3}, "entropies": np.zeros(3), "path": out}

    monkeypatch.setattr(external_lib, "evaluate_run", fake_evaluate_run)
    monkeypatch.setattr(calibrate_lib, "calibrate_run", fake_calibrate_run)
    camp = Campaign("metaworld", episodes=4)
    cols = a2.columns("metaworld-target:bin-picking")
    run = _Run(tmp_path)

    def evaluate(col):
        inference, key = camp._key(col, 1)
        return camp._external_evaluation(run, col, 1, inference, key, a2.NO_PERIODIC)

    ev = evaluate(cols.hip)
    (cal,) = calibrations
    assert cal == {"source": "rollouts", "rule": "percentiles", "episodes": 50, "seed": 1, "margin": 0.05,
                   "max_steps": 500, "semantics": "waypoint",
                   "out": os.path.join(str(tmp_path), "calibration_percentiles_waypoint.json")}
    call = served[-1]
    assert call["max_steps"] == 500 and call["first_seed"] == 1_001_000
    assert call["inference"].semantics == "waypoint" and call["inference"].thresholds == (0.25, 0.75)
    assert ev["thresholds"] == [-math.inf, 0.25, 0.75, math.inf] and ev["max_steps"] == 500
    assert ev["calibration"]["source"] == "rollouts" and ev["calibration"]["intended_mix"]["2"] == 0.6
    assert ev["calibration"]["file"] == "calibration_percentiles_waypoint.json" and "periodic" not in ev
    assert ev["eval_s"] >= 3.0 and ev["success"] == [True, False, True, False] and ev["clipped"] == [0, 1, 2, 3]
    kept = json.loads((tmp_path / "calibration_percentiles_waypoint.json").read_text())
    assert kept["max_steps"] == 500 and kept["semantics"] == "waypoint" and len(kept["params_sha256"]) == 64
    # the same network again: its calibration is reused, costs nothing here
    again = evaluate(cols.hip)
    assert len(calibrations) == 1 and again["calibration"]["calibration_s"] == 0.0
    assert again["thresholds"] == ev["thresholds"]
    # another network in the run dir (retrained): calibrated again
    run.policy.params = {"w": np.ones((2, 3), np.float32)}
    evaluate(cols.hip)
    assert len(calibrations) == 2
    # under rate and with the success rule: their own calibrations and files
    evaluate(cols.hip_rate)
    evaluate(cols.hip_success)
    assert [(c["rule"], c["semantics"]) for c in calibrations[2:]] == [("percentiles", "rate"), ("success", "waypoint")]
    assert served[-2]["inference"].semantics == "rate"
    # stride 1: guidance off, no calibration
    ev = evaluate(cols.hip_stride1)
    assert served[-1]["inference"].entropy_guided is False and ev["thresholds"] is None
    assert ev["calibration"]["intended_mix"] == {"1": 1.0, "2": 0.0, "3": 0.0} and len(calibrations) == 4
    # demo thresholds: the run's calibration.json, as training wrote it
    calibration.write_calibration({"thresholds": [-math.inf, 0.1, 0.2, math.inf], "percentiles": [10.0, 70.0]},
                                  os.path.join(str(tmp_path), calibration.CALIBRATION_FILE))
    ev = evaluate(cols.hip_demos)
    assert ev["thresholds"] == [-math.inf, 0.1, 0.2, math.inf] and ev["calibration"]["source"] == "demos"
    assert served[-1]["inference"].thresholds is None and served[-1]["max_steps"] == 500
    # DP (another run, one stride): no thresholds, no calibration
    dp_run = _Run(tmp_path / "dp", strides=(1,))
    inference, key = camp._key(cols.dp, 1)
    ev = camp._external_evaluation(dp_run, cols.dp, 1, inference, key, a2.NO_PERIODIC)
    assert ev["thresholds"] is None and "calibration" not in ev and len(calibrations) == 4
    # a rebuild from the records alone runs nothing and says the table is interim
    args = _args(tmp_path / "campaign", tasks=("bin-picking",), fraction=1.0)
    assert "(interim)" in open(a2.amendment2_table(dataclasses.replace(args, from_records=True))).read()
    assert not os.path.exists(args.runs) and not os.path.exists(args.data)


def test_pilot_table_from_records_applies_the_plateau_and_budget_rules(tmp_path):
    """``pilot2 --from-records``: DP's success at the four fractions per task, f by the plateau rule, the measured
    rates (medians over the two tasks) and the budget rule at those rates, all by hand."""
    from experiments.metaworld import main as metaworld, parse_args

    args = _args(tmp_path)  # writes the five tasks' T_task
    camp = Campaign("metaworld", runs=args.runs, records=args.records)
    success = {"bin-picking": [0.2, 0.5, 0.6, 0.62], "hand-insert": [0.3, 0.6, 0.7, 0.7]}
    train_rate = {"bin-picking": 0.3, "hand-insert": 0.5}
    waypoint_cpu = {"bin-picking": [100.0, 90.0, 110.0, 120.0], "hand-insert": [200.0, 180.0, 220.0, 240.0]}
    rate_cpu = {"bin-picking": 50.0, "hand-insert": 70.0}
    for bare in a2.PILOT_TASKS:
        task = f"metaworld-target:{bare}"
        total = TOTALS[bare]
        steps = a2.fraction_steps(total)
        changes = {"train.batch_size": 128, "train.num_steps": total, "train.ckpt_every": steps[0]}
        cols = a2.columns(task)
        cfg = camp.run_config(task, cols.dp, 0, changes)

        def ev(rate, cpu):
            ok = [True] * round(100 * rate) + [False] * (100 - round(100 * rate))
            return {"success": ok, "steps": [100] * 100, "decisions": [10] * 100, "actions": [80] * 100,
                    "success_rate": rate, "eval_s": cpu, "eval_cpu_s": cpu, "cpu_cores": 1}

        main = ev(success[bare][3], sum(waypoint_cpu[bare]))
        main.update(main_eval_s=waypoint_cpu[bare][0], main_eval_cpu_s=waypoint_cpu[bare][0],
                    periodic={"checkpoints": [{"step": n, "success_rate": r, "eval_s": c, "eval_cpu_s": c,
                                               "cpu_cores": 1}
                                              for n, r, c in zip(steps[:3], success[bare], waypoint_cpu[bare][1:])]})
        write_json(record_path(args.records, args.runs, cfg), {
            "version": RECORD_VERSION, "budget": "metaworld", "task": task, "seed": 0, "checkpoint_step": total,
            "training": {"steps": total, "wall_time_s": 1.0, "cpu_time_s": train_rate[bare] * total, "cpu_cores": 1},
            "evaluations": {camp._key(cols.dp, 0)[1]: main,
                            camp._key(cols.dp_rate, 0)[1]: ev(0.1, rate_cpu[bare])}})
    flags = ["--runs", args.runs, "--records", args.records, "--data", args.data, "--results", args.results,
             "--steps-file", args.steps_file, "--from-records", "--no-progress", "--hipolicy-train-factor", "2",
             "--hipolicy-eval-factor", "10"]
    text = open(metaworld(parse_args(["pilot2", *flags]))).read()
    rows = _rows(text.split("| Task")[1])
    assert rows == [["metaworld-target:bin-picking", "22202", "20", "50", "60", "62", "10"],
                    ["metaworld-target:hand-insert", "13913", "30", "60", "70", "70", "10"],
                    ["mean", "", "25.0", "55.0", "65.0", "66.0", ""]]
    # the plateau: best 66 % at f = 1; 65 % at 3/4 is within 5 points, 55 % at 1/2 is not
    assert "**f = 0.75** (the plateau, 0.75·T)" in text
    choice = json.loads((tmp_path / "res" / "pilot_choice.json").read_text())
    # rates: training 0.3 and 0.5 s/step → 0.4; waypoint medians 105 and 210 → 157.5; rate 50 and 70 → 60
    r = choice["rates"]
    assert r["train_s_per_step"] == pytest.approx(0.4) and (r["hip_train_factor"], r["hip_eval_factor"]) == (2, 10)
    assert r["eval_s_per_100"] == pytest.approx({"waypoint": 157.5, "rate": 60.0})
    spent = 0.3 * 22202 + 0.5 * 13913 + 420 + 50 + 840 + 70  # both runs' training, every evaluation
    assert choice["spent_s"] == pytest.approx(spent)
    # a network at n steps: DP 0.4 n + 157.5 + 60; DP+HiPolicy 0.8 n + 10 (7 · 157.5 + 1.5 · 60); a task 3 × both
    cost = {t: 3 * (1.2 * 3 * (n // 4) + 217.5 + 11925.0) for t, n in TOTALS.items()}
    rule = choice["budget_rule"]
    assert rule["task_cost_s"] == pytest.approx([cost[t] for t in a2.TASKS])
    left = 80 * 3600 - spent
    assert sum(cost[t] for t in a2.TASKS[:3]) <= left < sum(cost[t] for t in a2.TASKS[:4])
    assert (rule["fraction"], rule["tasks"]) == (0.75, 3)
    assert "**the first 3 tasks** (bin-picking, stick-push, coffee-pull), **f = 0.75**." in text
    # arm B: the first of arm A's tasks that fit 20 CPU-hours at the same f and rates (bin-picking: 26.8 h → one)
    assert cost["bin-picking"] > 20 * 3600 and choice["arm_b"]["tasks"] == 1
    assert "the first **1** task(s) fit 20 CPU-hours at f = 0.75" in text


def test_mjx_columns_take_closed_loop_thresholds_too(monkeypatch):
    """``Campaign._thresholds`` (an MJX evaluation) with ``calibration='rollouts'``: the percentiles of the run's
    stride-1 closed-loop entropies in the column's execution, once per run and setting; ``'success'``: the
    success rule's thresholds; ``'demos'`` is left to the run's calibration.json as before."""
    from hipolicy_jax.campaigns import campaign as campaign_lib
    from hipolicy_jax.runs import calibrate as calibrate_lib

    calls = []

    def fake_entropies(run, inference, source="demos", *, episodes=20, seed=None, evaluator=None, **kw):
        calls.append(("rollouts", source, episodes, seed, inference.semantics))
        return np.linspace(0.0, 1.0, 101)

    def fake_success(run, inference, *, episodes=20, seed=None, margin=0.05, evaluator=None, **kw):
        calls.append(("success", episodes, seed, margin))
        return {"thresholds": (-math.inf, 0.3, 0.4, math.inf)}

    monkeypatch.setattr(campaign_lib, "run_entropies", fake_entropies)
    monkeypatch.setattr(calibrate_lib, "success_constrained", fake_success)
    camp = Campaign("cpu")
    run = _Run("/nonexistent/run")
    col = Column("HiPolicy (closed loop)", semantics="waypoint", calibration="rollouts")
    inference = camp._key(col, 2)[0]
    th = camp._thresholds(run, col, ev=None, seed=2, inference=inference)
    assert th == pytest.approx((-math.inf, 0.1, 0.7, math.inf))  # the 10th / 70th percentiles of 0, 0.01, ..., 1
    assert camp._thresholds(run, col, ev=None, seed=2, inference=inference) == th
    assert calls == [("rollouts", "rollouts", 50, 2, "waypoint")]  # once per run and setting
    th = camp._thresholds(run, col._replace(calibration="success"), ev=None, seed=2, inference=inference)
    assert th == (-math.inf, 0.3, 0.4, math.inf) and calls[-1] == ("success", 50, 2, 0.05)
    assert camp._thresholds(run, col._replace(guided=False), ev=None, seed=2) is None


def test_docs_quote_the_pilots_numbers():
    """docs/metaworld.md's pilot sentence and the protocol's pilot entry print the success per fraction that
    pilot_choice.json holds (bin-picking first, hand-insert second), and the f and K it chose."""
    choice = json.load(open(os.path.join(a2.RESULTS, "pilot_choice.json")))
    per_task = list(zip(*(choice["success"][f] for f in ("0.25", "0.5", "0.75", "1.0"))))
    docs = " ".join(open(os.path.join("docs", "metaworld.md")).read().split())
    for task, rates in zip(("bin-picking", "hand-insert"), per_task):
        assert f"{task} " + " / ".join(f"{100 * r:.0f}" for r in rates) + " %" in docs, task
    protocol = open(os.path.join("results", "metaworld", "PROTOCOL.md")).read()
    for task, rates in zip(("bin-picking", "hand-insert"), per_task):
        assert f"| {task} | " + " | ".join(f"{100 * r:.0f} %" for r in rates) + " |" in protocol, task
    means = [sum(choice["success"][f]) / 2 for f in ("0.25", "0.5", "0.75", "1.0")]
    assert "| mean | " + " | ".join(f"{100 * m:.1f} %" for m in means) + " |" in protocol
    assert choice["fraction"] == 0.25 and "**f = 0.25**" in protocol and "(K = 5)" in protocol
