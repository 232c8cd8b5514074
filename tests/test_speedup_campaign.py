"""Amendment 5 (``campaigns.speedup``): HiPolicy against DemoSpeedup. The run-level ``speedup`` change, the jobs'
order, the bandwidth ladder, the refusal to train on a missing accelerated buffer, the table and its reading rule on
numbers written here, and the whole pipeline on the smoke budget (proxy → stage → runs → table)."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from hipolicy_jax.campaigns import speedup as amend
from hipolicy_jax.campaigns.budgets import BUDGETS, DP, run_changes_name, run_config, speedup_data_path
from hipolicy_jax.campaigns.campaign import Campaign, Column
from hipolicy_jax.speedup.config import SpeedupConfig
from hipolicy_jax.speedup.entropy import choose_bandwidth


def test_speedup_run_change_names_the_dir_and_the_accelerated_buffer(tmp_path):
    assert run_changes_name({"train.num_steps": 8000, "speedup": True}) == "_speedup_t8000"
    with pytest.raises(ValueError, match="'speedup' is True"):
        run_changes_name({"speedup": "yes"})
    plain = run_config("cpu", "press_button", "state", DP, 0, runs=str(tmp_path), data="data",
                       run_changes={"train.num_steps": 8000})
    fast = run_config("cpu", "press_button", "state", DP, 0, runs=str(tmp_path), data="data",
                      run_changes={"train.num_steps": 8000, "speedup": True})
    assert plain.data == "data/press_button_state_100.zarr"
    assert fast.data == speedup_data_path(plain.data) == "data/press_button_state_100_speedup.zarr"
    assert fast.out_dir().endswith(os.path.join("dp_speedup_t8000", "seed0"))
    assert fast.train.num_steps == plain.train.num_steps == 8000


def test_a_missing_accelerated_buffer_is_refused_not_collected(tmp_path):
    """Training would collect plain expert demos at a missing data path; for an accelerated buffer the campaign
    stops in one line instead."""
    camp = Campaign("smoke", runs=str(tmp_path / "runs"), data=str(tmp_path / "data"),
                    records=str(tmp_path / "records"))
    cfg = camp.run_config("press_button", Column("DP", "state", DP), 0, {"speedup": True})
    with pytest.raises(FileNotFoundError, match="no DemoSpeedup-accelerated buffer.*experiments.paper speedup"):
        camp.ensure_demos(cfg, 0)
    assert not os.path.exists(cfg.data)


def test_jobs_put_the_proxys_new_evaluation_first_and_train_five_methods_on_four_networks():
    args = amend.SpeedupArgs()
    jobs = amend.jobs(args)
    assert len(jobs) == 3 * 5 * 2 * 3  # tasks x methods x semantics x seeds
    first = jobs[0]
    assert (first.task, first.col.label, first.col.execution, first.seed) == ("press_button", "DP+AAC (waypoint)",
                                                                             "aac", 0)
    runs = amend.run_of(args)
    # a shared network's first job is an evaluation no earlier table made (so a pre-fix network is retrained first)
    firsts = {}
    for j in jobs:
        firsts.setdefault(runs(j), j.col)
    assert all(c.semantics == "waypoint" for c in firsts.values())
    press = [j for j in jobs if j.task == "press_button"]
    assert len({runs(j) for j in press}) == 4 * 3  # DP and DP+AAC share their networks
    by_label = {j.col.label: j for j in press if j.seed == 0}
    assert runs(by_label["DP"]) == runs(by_label["DP+AAC"]) == runs(by_label["DP (waypoint)"])
    assert runs(by_label["DP (DemoSpeedup)"]).endswith(os.path.join("lc4_s1_speedup_t8000", "seed0"))
    assert runs(by_label["HiPolicy (DemoSpeedup)"]).endswith(os.path.join("lc4_speedup_t8000", "seed0"))
    assert runs(by_label["DP+HiPolicy"]).endswith(os.path.join("hipolicy_t8000", "seed0"))  # budget.md's cell
    assert by_label["DP (waypoint)"].col.semantics == "waypoint"
    assert {dict(j.changes).get("speedup", False) for j in press if "DemoSpeedup" in j.col.label} == {True}


def test_bandwidth_ladder_takes_the_first_candidate_that_does_not_saturate():
    cfg = SpeedupConfig(num_samples=4, bandwidth_ladder=(0.01, 0.1), max_saturated=0.5)
    ceiling = np.log(4)
    rows = np.array([[ceiling] * 4,  # 0.002: every frame at the ceiling
                     [ceiling, ceiling, ceiling, 0.3],  # 0.01: 3 of 4
                     [ceiling, 0.2, 0.1, 0.3]])  # 0.1: 1 of 4 -> chosen
    assert choose_bandwidth(rows, cfg) == 2 and cfg.bandwidths()[2] == 0.1
    assert choose_bandwidth(np.full((3, 4), ceiling), cfg) == 2  # none fits: the last
    assert choose_bandwidth(np.zeros((3, 4)), cfg) == 0  # the paper's bandwidth when it reads
    with pytest.raises(ValueError, match=r"expected \(3, T\)"):
        choose_bandwidth(rows[:2], cfg)
    with pytest.raises(ValueError, match="speedup.bandwidth_ladder: must be increasing bandwidths"):
        SpeedupConfig(bandwidth_ladder=(0.01, 0.005))
    with pytest.raises(ValueError, match="speedup.max_saturated"):
        SpeedupConfig(max_saturated=1.5)


def _records(rng, tasks=("press_button", "stack_cubes", "latch_door"), seeds=(0, 1, 2)):
    """Table rows: DP succeeds in 90 %, DemoSpeedup keeps it at 40 % fewer steps, HiPolicy at 30 % fewer, the stack
    at 50 % fewer, AAC loses 30 points; per episode the same initial states."""
    plan = {"DP": (0.9, 60.0), "DP (DemoSpeedup)": (0.9, 36.0), "DP+AAC": (0.6, 60.0), "DP+HiPolicy": (0.9, 42.0),
            "HiPolicy (DemoSpeedup)": (0.9, 30.0)}
    out = []
    for task in tasks:
        for seed in seeds:
            base = rng.random(100) < 0.9
            for label, (rate, steps) in plan.items():
                success = base.copy() if rate == 0.9 else base & (rng.random(100) < rate / 0.9)
                n = np.round(steps * (1 + 0.05 * rng.standard_normal(100))).astype(int)
                net = "dp" if label in ("DP", "DP+AAC") else label
                out.append({"task": task, "seed": seed, "column": label, "run": f"{task}/{net}/seed{seed}",
                            "eval_s": 60.0, "success": success.tolist(),
                            "steps": n.tolist(), "decisions": (n // 8).tolist(), "actions": n.tolist(),
                            "success_rate": float(success.mean()),
                            "mean_steps_success": float(n[success].mean()), "training_s": 1800.0,
                            "training_cores": 1, "training_cpu_s": 1800.0})
    return out


def test_table_reads_each_method_against_dp_by_the_amendments_rule(tmp_path):
    args = amend.SpeedupArgs(budget="smoke", results=str(tmp_path), semantics=("rate",), progress=False)
    stage = tmp_path / "speedup" / "stage"
    stage.mkdir(parents=True)
    for task in args.tasks:
        (stage / f"{task}.json").write_text(json.dumps(
            {"original_frames": 6000, "new_frames": 2500, "speedup": 2.4, "mean_original_length": 60.0,
             "mean_new_length": 25.0, "precise_fraction": 0.3, "bandwidth": 0.02, "saturated_fraction": 0.1,
             "stage_cpu_s": 120.0}))
    text = open(amend.build_table(args, _records(np.random.default_rng(0)), 45, 0, 0)).read()
    reading = {line.split(" | ")[0].strip("| "): line.split(" | ")[1].rstrip(" |")
               for line in text.split("### Reading")[1].split("\n## ")[0].splitlines() if line.startswith("| ")
               and "Method" not in line and "---" not in line}
    assert reading["DP (DemoSpeedup)"] == "keeps DP's success; faster"
    assert reading["HiPolicy (DemoSpeedup)"] == "keeps DP's success; faster"
    assert reading["DP+HiPolicy"] == "keeps DP's success; faster"
    assert reading["DP+AAC"].startswith("does not keep DP's success")
    # the speed table: the stack's control steps about 50 % fewer than DP's on the shared successes
    row = next(line for line in text.splitlines() if line.startswith("| **Average** | HiPolicy (DemoSpeedup) | "))
    steps_saved = float(row.split(" | ")[-1].split()[0])
    assert -52.0 < steps_saved < -48.0, row
    assert "6,000 → 2,500 (x2.40)" in text
    cost = next(line for line in text.split("## Training cost")[1].splitlines()
                if line.startswith("| DP (DemoSpeedup) | "))
    assert cost == "| DP (DemoSpeedup) | 0.50 + 0.53 (proxy and stage, per task) |"  # 1800 s + (1800 + 120) s


def test_pre_fix_networks_are_left_out_of_the_table(tmp_path):
    args = amend.SpeedupArgs(budget="smoke", results=str(tmp_path))
    old = {"params_sha256": "aa" * 32, "final_loss": 0.01}
    (tmp_path / "speedup").mkdir()
    (tmp_path / "speedup" / amend.PRE_FIX).write_text(json.dumps({"networks": {"r.json": [old]}}))
    nets = amend.pre_fix_networks(args)
    assert amend.is_pre_fix({"params_sha256": "aa" * 32, "final_loss": 0.02}, nets)
    assert not amend.is_pre_fix({"params_sha256": "bb" * 32, "final_loss": 0.01}, nets)
    assert not amend.is_pre_fix(None, nets)


def test_committed_pre_fix_list_names_the_shared_cells():
    doc = json.load(open(os.path.join("results", "speedup", amend.PRE_FIX)))
    assert sorted(doc["networks"]) == sorted(
        f"results/runs/cpu/{t}/state/{v}_t8000/seed{s}.json" for t in ("press_button", "stack_cubes")
        for v in ("dp", "hipolicy") for s in (0, 1, 2))
    assert all(len(n["params_sha256"]) == 64 for nets in doc["networks"].values() for n in nets)


@pytest.mark.slow
def test_smoke_pipeline_proxy_stage_runs_and_table(tmp_path):
    """On the smoke budget, one task and seed: the proxy (DP) trains and is evaluated, the stage writes the
    accelerated buffer and its committed summary, the DemoSpeedup runs train on that buffer (shorter than the
    demos, half the chunk), every method is evaluated on the same initial states, and the table rebuilds from the
    records alone."""
    steps = BUDGETS["smoke"].train.num_steps
    args = amend.SpeedupArgs(budget="smoke", tasks=("press_button",), seeds=(0,), steps=steps, semantics=("rate",),
                             runs=str(tmp_path / "runs"), results=str(tmp_path / "results"),
                             records=str(tmp_path / "records"), data=str(tmp_path / "data"), progress=False)
    path = amend.speedup_table(args)
    summary = json.load(open(tmp_path / "results" / "speedup" / "stage" / "press_button.json"))
    assert summary["new_frames"] < summary["original_frames"] and summary["proxy"].endswith("seed0")
    assert summary["bandwidth"] in amend.SPEEDUP.bandwidths()
    assert (tmp_path / "results" / "speedup" / "stage" / "press_button_entropy.png").stat().st_size > 0
    camp = amend.campaign(amend.dataclasses.replace(args, from_records=True))
    episodes = {}
    for job in amend.jobs(args):
        record = camp.record(job.task, job.col, job.seed, dict(job.changes))
        ev = camp.evaluate(job.task, job.col, job.seed, dict(job.changes))
        assert ev is not None, job
        episodes[job.col.label] = len(ev["success"])
        if "DemoSpeedup" in job.col.label:
            assert record["data"].endswith("_speedup.zarr") and record["policy"]["chunk"]["chunk_len"] == 4
    assert set(episodes.values()) == {BUDGETS["smoke"].eval.episodes}
    rebuilt = amend.speedup_table(amend.dataclasses.replace(args, from_records=True))
    assert open(rebuilt).read() == open(path).read()
