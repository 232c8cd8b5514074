"""Experiment entry points on one tiny trained run: evaluate, calibrate, one ``Evaluator`` across checkpoints, and
the paper tables (parsing, the markdown writer on fake numbers, records and rebuilding from them, and one smoke
``paper execution`` run reusing the trained run)."""

import dataclasses
import json
import math
import os
import re
import shlex
import shutil
import subprocess
from pathlib import Path
import sys

import imageio.v3 as iio
from scipy import stats as scipy_stats
import jax
import numpy as np
import pytest
import tyro

from hipolicy_jax.config import InferenceConfig

from experiments import calibrate, evaluate, paper
from hipolicy_jax import envs, jsonio
from hipolicy_jax.evaluation import calibration as calibration_lib
from hipolicy_jax.campaigns.budgets import BUDGETS, DP, variant_name
from hipolicy_jax.checkpoint import config_to_dict
from hipolicy_jax.campaigns.campaign import (Campaign, Column, CostModel, Deadline, Job, choose_low_regime,
                                        evaluation_rollout, parse_until, pilot_candidates, schedule, shard)
from hipolicy_jax.campaigns import report, tables
from hipolicy_jax.runs.cli import parse_with_run_inference
from hipolicy_jax.runs.lock import CAMPAIGN_LOCK_FILE, RunLock
from hipolicy_jax.runs.store import load_run, make_evaluator
from hipolicy_jax.runs.train import train

TASK = "press_button"
SMOKE = BUDGETS["smoke"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The smoke budget's HiPolicy run of press_button, seed 0, trained into a tmp dir (as ``paper`` lays it out)."""
    root = tmp_path_factory.mktemp("paper")
    args = tables.ExecutionArgs(budget="smoke", tasks=(TASK,), seeds=(0,), runs=str(root / "runs"),
                               results=str(root / "results"), records=str(root / "records"), data=str(root / "data"),
                               progress=False)
    targs = tables.train_args(args, TASK, "state", (), 0)
    summary = train(targs)
    assert summary["steps"] == SMOKE.train.num_steps
    return args, targs.out_dir()


def _load(path):
    """A JSON file the project wrote, parsed strictly (NaN / Infinity constants fail the test), ±∞ strings read back
    as floats."""
    def reject(constant):
        raise AssertionError(f"{path}: non-standard JSON constant {constant}")

    with open(path) as f:
        return jsonio.from_strict(json.loads(f.read(), parse_constant=reject))


def _check_summary(s: dict, max_steps: int):
    assert 0.0 <= s["success_rate"] <= 1.0
    assert 1 <= s["mean_steps"] <= max_steps
    assert s["mean_steps_success"] is None or 1 <= s["mean_steps_success"] <= max_steps  # None: no success (NaN)
    fracs = [v for k, v in s.items() if k.startswith("stride") and k.endswith("_frac")]
    assert all(0.0 <= f <= 1.0 for f in fracs) and math.isclose(sum(fracs), 1.0, rel_tol=1e-6)
    assert len(s["success"]) == len(s["steps"]) and all(1 <= x <= max_steps for x in s["steps"])


def test_evaluate_writes_json_trace_and_video(tiny):
    _, run = tiny
    # --inference.* default to the run's inference.json (the smoke budget's N=4, DDIM 2)
    args = parse_with_run_inference(evaluate.EvaluateArgs, ["--checkpoint", run, "--episodes", "3",
                                                            "--video-height", "48", "--video-width", "64"])
    assert args.inference == SMOKE.inference
    report = evaluate.main(args)
    out = os.path.join(run, "eval")
    video = report["files"]["video"]
    assert video.endswith(".mp4")  # PyAV (an FFmpeg binding) is a dependency
    for path in (os.path.join(out, "eval.json"), os.path.join(out, "entropy_trace.png"), video):
        assert os.path.getsize(path) > 0
    saved = _load(os.path.join(out, "eval.json"))
    assert saved["task"] == TASK and saved["episodes"] == 3 and saved["inference"]["num_samples"] == 4
    assert saved["thresholds"] == _load(os.path.join(run, "calibration.json"))["thresholds"]
    assert saved["thresholds_source"] == "calibration.json"
    max_steps = envs.make(TASK).max_steps
    for key in ("with_eg", "without_eg"):
        _check_summary(saved[key], max_steps)
    assert saved["without_eg"]["stride1_frac"] == 1.0  # w/o entropy guidance: always the highest frequency
    for key in ("with_eg", "without_eg"):  # press_button's hold: its durations per executed stride
        timed = saved[key]["timed_phase"]
        assert timed["required_steps"] == 10 and len(timed["longest"]) == 3
        assert 0.0 <= timed["reached"] <= 1.0 and set(timed["by_stride"]) <= {"1", "2", "3"}
    assert set(saved["without_eg"]["timed_phase"]["by_stride"]) <= {"1"}
    assert report["steps_ratio"] > 0 and 0 <= saved["video_episode"] < 3
    # the video is the recorded episode of the batched rollout: the reset frame plus one frame per step
    frames = iio.imread(video, plugin="pyav")  # in-process decoding (no ffmpeg subprocess fork)
    assert frames.shape == (saved["with_eg"]["steps"][saved["video_episode"]] + 1, 48, 64, 3)


@pytest.mark.slow
def test_evaluate_checkpoints_dir_and_threshold_override(tiny, tmp_path):
    _, run = tiny
    # inner thresholds above any entropy: entropy guidance picks stride 1 everywhere, like w/o EG
    args = parse_with_run_inference(evaluate.EvaluateArgs, [
        "--checkpoint", os.path.join(run, "checkpoints"), "--episodes", "3", "--inference.thresholds", "1e6", "2e6",
        "--video", "none", "--out", str(tmp_path / "ev")])
    assert args.inference.num_samples == SMOKE.inference.num_samples  # the run's, with the override on top
    report = evaluate.main(args)
    assert report["thresholds"] == [-math.inf, 1e6, 2e6, math.inf]
    assert report["thresholds_source"] == "inference.thresholds"
    assert report["with_eg"]["stride1_frac"] == 1.0 and "video" not in report["files"]
    assert report["with_eg"]["steps"] == report["without_eg"]["steps"]
    assert (tmp_path / "ev" / "eval.json").exists() and (tmp_path / "ev" / "entropy_trace.png").exists()
    with pytest.raises(ValueError, match="inference.thresholds"):
        evaluate.main(evaluate.EvaluateArgs(checkpoint=run, inference=dataclasses.replace(SMOKE.inference,
                                                                                          thresholds=(1.0,)),
                                            video="none", out=str(tmp_path)))


def test_one_evaluator_two_checkpoints_one_compile(tiny):
    """An ``Evaluator`` owns its compiled rollout, not the parameters: three parameter sets (two checkpoints of a run
    and the last one scaled by 1/2), with and without entropy guidance, one compile, and each set gives its own
    decisions (the first decision's entropy, from the same reset and key, differs between every two sets; the same
    set gives the same entropy again, also from a second ``Evaluator``, which compiles on its own: there is no
    global cache). Without entropy guidance every decision runs stride 1."""
    _, run = tiny
    first, last = load_run(run, 6), load_run(run, SMOKE.train.num_steps)
    halved = jax.tree.map(lambda x: x * 0.5 if jax.numpy.issubdtype(x.dtype, jax.numpy.floating) else x,
                          last.policy.params)
    ev = make_evaluator(last, SMOKE.inference)
    th = (-math.inf, -1.0, 1.0, math.inf)
    sets = {"first": (first.policy.params, first.policy.normalizer),
            "last": (last.policy.params, last.policy.normalizer), "halved": (halved, last.policy.normalizer)}
    results = {(name, guided): ev.evaluate(params, norm, 2, jax.random.key(0), th, guided)
               for name, (params, norm) in sets.items() for guided in (True, False)}
    assert ev.traces == 1
    assert all(r.steps.shape == (2,) for r in results.values())
    h0 = {k: np.asarray(r.entropy)[:, 0] for k, r in results.items()}  # decision 0: valid in every episode
    for a, b in [("first", "last"), ("first", "halved"), ("last", "halved")]:
        assert np.abs(h0[a, True] - h0[b, True]).min() > 1e-4, (a, b, h0[a, True], h0[b, True])
    for name in sets:  # guidance only changes the stride: the first decision's samples are the same
        np.testing.assert_allclose(h0[name, False], h0[name, True], rtol=1e-6)
        r = results[name, False]
        assert (np.asarray(r.stride)[np.asarray(r.valid)] == 1).all()
    other = make_evaluator(last, SMOKE.inference)
    again = other.evaluate(last.policy.params, last.policy.normalizer, 2, jax.random.key(0), th)
    assert other.traces == 1 and ev.traces == 1
    np.testing.assert_allclose(np.asarray(again.entropy)[:, 0], h0["last", True], rtol=1e-5)


@pytest.mark.slow
def test_execution_strategies_in_closed_loop(tiny):
    """Closed loop on the trained run (2 episodes, 24 control steps, L_c = 8, no entropy guidance), the decision
    counts tell the strategies apart:

    - chunk: a decision every L_c steps, decisions = ceil(steps / L_c), each executing L_c (the last: what is left);
    - TE (temporal ensembling): a decision at every control step, decisions = steps, one action each;
    - AAC: each decision executes the k* of its N samples and the next starts where it ended; the first decision's
      k* is recomputed by hand from the sampler's chunks for the same reset and key (per-step entropies of the
      selected frequency, H(k) the running mean, k* at the largest jump), and is < L_c here, so AAC decides more
      often than chunk execution and less often than TE."""
    _, run = tiny
    last = load_run(run)
    cfg, limit, episodes, key = last.policy.cfg, 24, 2, jax.random.key(0)
    lc, m = cfg.chunk.chunk_len, cfg.chunk.num_freqs
    params, norm = last.policy.params, last.policy.normalizer
    from hipolicy_jax.evaluation.evaluator import eval_summary
    out = {}
    for kind in ("chunk", "te", "aac"):  # --inference.execution of experiments.evaluate, the rest the run's
        inference = parse_with_run_inference(evaluate.EvaluateArgs, ["--checkpoint", run, "--inference.execution",
                                                                     kind]).inference
        assert inference == dataclasses.replace(SMOKE.inference, execution=kind)
        ev = make_evaluator(last, inference, max_steps=limit)
        res = ev.evaluate(params, norm, episodes, key, entropy_guided=False)
        valid, steps = np.asarray(res.valid), np.asarray(res.steps)
        decisions = valid.sum(axis=1)
        s = eval_summary(res)  # the report's columns
        assert s["mean_decisions"] == pytest.approx(decisions.mean(), rel=1e-6)
        assert s["mean_decisions"] * s["mean_actions_per_decision"] == pytest.approx(s["mean_steps"], rel=1e-6)
        for e in range(episodes):
            n, executed, start = decisions[e], np.asarray(res.executed)[e, :decisions[e]], np.asarray(res.start)[e]
            assert valid[e, :n].all() and executed.sum() == steps[e] and 1 <= steps[e] <= limit
            np.testing.assert_array_equal(start[:n], np.concatenate([[0], np.cumsum(executed)[:-1]]))
            if kind == "chunk":
                assert n == math.ceil(steps[e] / lc) and (executed[:-1] == lc).all()
            elif kind == "te":
                assert n == steps[e] and (executed == 1).all()
            else:
                assert math.ceil(steps[e] / lc) <= n <= steps[e] and ((executed >= 1) & (executed <= lc)).all()
        out[kind] = (ev, res, decisions)

    ev, res, decisions = out["aac"]  # its first decisions, recomputed outside the rollout
    from hipolicy_jax.evaluation import calibration
    from hipolicy_jax.evaluation.policy import PolicyArgs, make_decision_fn
    from hipolicy_jax.evaluation.rollout import init_history
    decide = make_decision_fn(ev.net, cfg, last.action_dim, ev.inference)
    args = PolicyArgs(params, norm, calibration.guidance_thresholds(None, m, False))
    for e, k_episode in enumerate(jax.random.split(key, episodes)):  # as the rollout derives its keys
        k_reset, _, k_policy = jax.random.split(k_episode, 3)
        d = decide(init_history(ev.env.reset(k_reset).obs, cfg.chunk.obs_span), jax.random.fold_in(k_policy, 0), args)
        assert float(d.entropy) == pytest.approx(float(res.entropy[e, 0]), rel=1e-4)  # the rollout's decision
        segment = np.asarray(d.chunks, np.float64).reshape(-1, m, lc, last.action_dim)[:, m - 1 - int(d.freq_index)]
        h = np.mean(0.5 * np.log(2 * np.pi * np.e * segment.var(axis=0, ddof=1) + 1e-6), axis=-1)  # (L_c,)
        jumps = np.diff(np.cumsum(h) / np.arange(1, lc + 1))  # H(k+1) − H(k), k = 1..L_c−1
        k_star = int(np.argmax(jumps)) + 1 if jumps.max() > 0 else lc
        assert k_star < lc and int(res.executed[e, 0]) == k_star
        assert out["chunk"][2][e] < decisions[e] < out["te"][2][e]


def test_asynchronous_execution_in_closed_loop(tiny):
    """Delay d = 2 with prefix inpainting (flags of experiments.evaluate): every decision executes L_c − d = 6 actions
    and the next one starts when 2 of them remain."""
    _, run = tiny
    args = parse_with_run_inference(evaluate.EvaluateArgs, ["--checkpoint", run, "--inference.delay", "2",
                                                            "--inference.handover", "inpaint"])
    assert args.inference.delay == 2 and args.inference.handover == "inpaint"
    assert args.inference.num_samples == SMOKE.inference.num_samples  # the rest from the run's inference.json
    last = load_run(run)
    ev = make_evaluator(last, args.inference, max_steps=24)
    res = ev.evaluate(last.policy.params, last.policy.normalizer, 2, jax.random.key(0))
    for e in range(2):
        n = int(np.asarray(res.valid)[e].sum())
        np.testing.assert_array_equal(np.asarray(res.start)[e, :n], 6 * np.arange(n))
        executed = np.asarray(res.executed)[e, :n]
        assert (executed[:-1] == 6).all() and 1 <= executed[-1] <= 6  # only the last may stop early


def test_calibrate_demos_reproduces_training_calibration(tiny, tmp_path, capsys):
    _, run = tiny
    record = calibrate.main(parse_with_run_inference(calibrate.CalibrateArgs, [
        "--checkpoint", run, "--out", str(tmp_path / "calibration.json")]))
    saved = _load(tmp_path / "calibration.json")
    trained = _load(os.path.join(run, "calibration.json"))
    np.testing.assert_allclose(saved["thresholds"], trained["thresholds"], rtol=1e-6)
    assert saved["inference"] == trained["inference"]
    th = saved["thresholds"]
    assert len(th) == 4 and th[0] == -math.inf and th[-1] == math.inf and th[1] < th[2]
    assert saved["percentiles"] == [10.0, 70.0] and saved["source"] == "demos"
    assert sum(saved["histogram"]["counts"]) == saved["num_windows"] == record["num_windows"] > 0
    q = saved["entropy_quantiles"]
    assert q["0"] <= th[1] <= th[2] <= q["100"]
    assert (tmp_path / "calibration.png").stat().st_size > 0
    assert "th1=" in capsys.readouterr().out


@pytest.mark.slow
def test_calibrate_rollouts(tiny, tmp_path):
    _, run = tiny
    args = parse_with_run_inference(calibrate.CalibrateArgs, [
        "--checkpoint", run, "--source", "rollouts", "--inference.percentiles", "20", "80", "--episodes", "3",
        "--out", str(tmp_path / "c.json")])
    record = calibrate.main(args)
    th = record["thresholds"]
    assert record["percentiles"] == [20.0, 80.0] and th[0] < th[1] < th[2] < th[3]
    env = envs.make(TASK)
    assert 3 <= record["num_windows"] <= 3 * math.ceil(env.max_steps / 8)
    with pytest.raises(ValueError, match="inference.percentiles"):
        calibrate.main(calibrate.CalibrateArgs(checkpoint=run, inference=InferenceConfig(percentiles=(50.0,)),
                                               out=str(tmp_path / "x.json")))


def test_calibrate_success_constrained_rule(tiny, tmp_path, capsys):
    _, run = tiny
    ladder_len = len(calibration_lib.percentile_ladder(3))
    args = parse_with_run_inference(calibrate.CalibrateArgs, [
        "--checkpoint", run, "--source", "rollouts", "--rule", "success", "--margin", "0.1", "--episodes", "3",
        "--out", str(tmp_path / "c.json")])
    record = calibrate.main(args)
    saved = _load(tmp_path / "c.json")
    cands, base = saved["candidates"], saved["baseline"]
    assert len(cands) == ladder_len and saved["rule"] == "success" and saved["margin"] == 0.1
    # every candidate: thresholds at its percentiles of the stride-1 rollouts' entropies, its mixes
    for c in cands:
        assert c["thresholds"] == list(calibration_lib.calibrate_thresholds(record["entropies"], 3, c["percentiles"]))
        assert c["intended_mix"] == calibration_lib.intended_mix(c["percentiles"], (1, 2, 3))
        assert math.isclose(sum(c["achieved_mix"].values()), 1.0, rel_tol=1e-9)
    # the choice is the rule's on the recorded numbers, and the written thresholds are the chosen candidate's
    want = calibration_lib.choose_success_constrained(cands, base["success_rate"], 0.1)
    assert saved["chosen"] == want and saved["thresholds"] == cands[want]["thresholds"]
    assert saved["percentiles"] == cands[want]["percentiles"]
    assert saved["intended_mix"] == cands[want]["intended_mix"]
    assert "<- chosen" in capsys.readouterr().out
    with pytest.raises(ValueError, match="rule: 'success' rolls the candidates out in closed loop"):
        calibrate.main(calibrate.CalibrateArgs(checkpoint=run, rule="success", out=str(tmp_path / "x.json")))


def test_paper_parsing_and_command_round_trip():
    for name, cls in tables.SUBCOMMANDS.items():
        args = paper.parse_args([name, "--budget", "smoke", "--tasks", "latch_door", "press_button",
                                 "--seeds", "3", "4"])
        assert type(args) is cls and args.tasks == ("latch_door", "press_button") and args.seeds == (3, 4)
        assert paper.parse_args(shlex.split(tables.command_line(args))[3:]) == args
    t = paper.parse_args(["thresholds", "--pairs", "5", "50", "20", "80", "--episodes", "7", "--no-progress"])
    assert t.pairs == ((5.0, 50.0), (20.0, 80.0)) and t.episodes == 7 and not t.progress
    h = paper.parse_args(["hparams", "--rows", "3", "8", "3", "1", "8", "2"])
    assert h.rows == ((3, 8, 3), (1, 8, 2))
    m = paper.parse_args(["main", "--obs-types", "state", "pointcloud"])
    assert m.obs_types == m.resolved_obs_types() == ("state", "pointcloud")
    assert paper.parse_args(["main"]).resolved_obs_types() == ("state",)  # point clouds only when asked on a CPU
    assert paper.parse_args(["main", "--budget", "gpu"]).resolved_obs_types() == ("state", "pointcloud")
    with pytest.raises(SystemExit):
        paper.parse_args(["main", "--tasks", "open_drawer"])
    with pytest.raises(SystemExit):
        paper.parse_args(["figures"])
    # variants are named by their config changes, so tables share runs (DP, HiPolicy)
    base = BUDGETS["cpu"].policy
    assert variant_name(tables.hparam_changes(3, 8, 3, base)) == "hipolicy"
    assert variant_name(tables.hparam_changes(3, 8, 1, base)) == variant_name(DP) == "dp"
    assert variant_name(tables.hparam_changes(1, 4, 2, base)) == "lc4_lh1_s1-2"
    assert variant_name((("objective", "flow"),)) == "flow"


def _fake_records(columns, tasks, seeds, rng, episodes=10):
    records = []
    for t in tasks:
        for s in seeds:
            for c in columns:
                success = rng.random(episodes) < rng.uniform(0.2, 0.9)
                steps = rng.integers(40, 120, episodes)
                records.append({"task": t, "seed": s, "column": c, "success_rate": float(success.mean()),
                                "mean_steps_success": float(steps[success].mean()) if success.any() else float("nan"),
                                "mean_steps": float(steps.mean()), "stride1_frac": 0.5, "stride2_frac": 0.3,
                                "stride3_frac": 0.2, "thresholds": [-math.inf, -1.0, -0.5, math.inf],
                                "success": success.tolist(), "steps": steps.tolist(),
                                "decisions": (steps // 8 + 1).tolist(), "run": f"{t}/{c}/{s}", "training_s": 60.0,
                                "eval_s": 5.0})
    return records


def test_budget_table_and_its_figure_of_success_and_steps(tmp_path, monkeypatch):
    """budget.md / .png: per task and step count, success and steps to success of DP and DP+HiPolicy; the figure's
    top row is success, its bottom row steps to success, each point the seed mean of the table's cell."""
    import matplotlib.figure

    rng = np.random.default_rng(1)
    default, longer = BUDGETS["smoke"].train.num_steps, 4 * BUDGETS["smoke"].train.num_steps
    fake = _fake_records(["DP", "DP+HiPolicy"], ("press_button", "stack_cubes"), (0, 1, 2), rng)
    fake += [{**r, "regime": {"train.num_steps": longer}} for r in
             _fake_records(["DP", "DP+HiPolicy"], ("press_button", "stack_cubes"), (0, 1, 2), rng)]
    monkeypatch.setattr(tables.common, "collect", lambda args, columns: fake)
    drawn = []
    save = matplotlib.figure.Figure.savefig

    def record_then_save(fig, *a, **k):  # each panel's y label and, per error-bar series, its points
        drawn.append([(ax.get_ylabel(), [c.lines[0].get_ydata() for c in ax.containers]) for ax in fig.axes])
        return save(fig, *a, **k)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", record_then_save)
    args = tables.BudgetArgs(budget="smoke", seeds=(0, 1, 2), steps=(default, longer), results=str(tmp_path),
                             runs=str(tmp_path / "runs"), data=str(tmp_path / "data"), progress=False)
    text = open(paper.main(args)).read()
    assert (tmp_path / "budget.png").stat().st_size > 0
    ((top_left, *_, bottom_right),) = drawn
    panels = [label for label, _ in drawn[0]]
    assert panels == ["success rate (%)"] * 2 + ["steps to success (successful episodes)"] * 2
    rows = {tuple(line.split(" | ")[:2]): line.split(" | ") for line in text.splitlines() if line.startswith("| ")}
    hip_steps = [float(rows[("| stack_cubes", f"{n:,}" + (" (budget)" if n == default else ""))][5].split()[0])
                 for n in (default, longer)]
    dp_success = [float(rows[("| press_button", f"{n:,}" + (" (budget)" if n == default else ""))][2].split()[0])
                  for n in (default, longer)]
    np.testing.assert_allclose(top_left[1][0], dp_success, atol=0.051)  # DP's success on press_button
    np.testing.assert_allclose(bottom_right[1][1], hip_steps, atol=0.051)  # DP+HiPolicy's steps on stack_cubes
    answer = [line for line in text.splitlines() if line.startswith("**The answer**")]
    assert len(answer) == 1, text

    def gap(task, n):
        """DP+HiPolicy − DP written again with numpy / scipy: per seed the mean per-episode success difference, the
        mean over seeds with scipy's one-sample t interval (clipped to ±1) and p → (mean, low, high, cell text)."""
        regime = {} if n == default else {"train.num_steps": n}
        by = {(r["column"], r["seed"]): np.asarray(r["success"], float) for r in fake
              if r["task"] == task and r.get("regime", {}) == regime}
        values = np.array([(by["DP+HiPolicy", s] - by["DP", s]).mean() for s in (0, 1, 2)])
        assert np.ptp(values) > 0  # (equal seeds would take the episode-level error instead)
        test = scipy_stats.ttest_1samp(values, 0.0)
        ci = test.confidence_interval(0.95)
        mean, low, high = values.mean(), max(ci.low, -1.0), min(ci.high, 1.0)
        word = "wins" if low > 0 else "loses" if high < 0 else "ties"
        return mean, low, high, f"{100 * mean:+.1f} [{100 * low:+.1f}, {100 * high:+.1f}]", \
            f"p={test.pvalue:.2g} ({word})"

    parts = []
    for task in ("press_button", "stack_cubes"):  # each task's answer is the protocol's rule on its two gaps
        (m0, _, _, first, p0), (m1, lo1, hi1, last, p1) = gap(task, default), gap(task, longer)
        for n, cell, p in ((default, first, p0), (longer, last, p1)):
            row = rows[(f"| {task}", f"{n:,}" + (" (budget)" if n == default else ""))]
            assert row[6].rstrip(" |") == f"{cell}, {p}", (task, n, row[6])
        trend = "holds" if lo1 <= m0 <= hi1 else "shrinks" if abs(m1) < abs(m0) else "grows"
        parts.append(f"{task}: {first} at {default:,} steps, {last} at {longer:,}: **{trend}**")
    assert answer[0].endswith("): " + "; ".join(parts) + "."), (answer[0], parts)


def test_gap_trend_follows_the_protocols_rule():
    """The training-budget answer: shrinks / grows when the longest training's interval excludes the shortest's
    point estimate (by which mean is nearer 0), else holds; '–' without a pair or without an interval."""
    def gap(mean, low=math.nan, high=math.nan):
        return report.Paired(report.stats.Estimate(mean, low, high), math.nan, math.nan, ())

    before = gap(-0.227, -0.278, -0.175)
    assert report.gap_trend(before, gap(0.0, 0.0, 0.0)) == "shrinks"  # 0 ± 0 excludes −22.7
    assert report.gap_trend(before, gap(-0.20, -0.30, -0.10)) == "holds"  # contains −22.7
    assert report.gap_trend(before, gap(-0.40, -0.45, -0.35)) == "grows"  # excludes it, farther from 0
    assert report.gap_trend(gap(0.217, -0.056, 0.489), gap(-0.35, -0.40, -0.30)) == "grows"  # reversed, larger
    assert report.gap_trend(gap(0.217, -0.056, 0.489), gap(0.10, 0.05, 0.15)) == "shrinks"
    assert report.gap_trend(before, gap(0.0)) == "–"  # one seed at the longest training: no interval
    assert report.gap_trend(None, gap(0.0, 0.0, 0.0)) == report.gap_trend(before, None) == "–"


def test_paper_tables_on_fake_numbers(tmp_path, monkeypatch):
    rng = np.random.default_rng(0)
    monkeypatch.setattr(tables.common, "collect", lambda args, columns: _fake_records(
        [c.label for c in columns], args.tasks, args.seeds, rng))
    common = dict(budget="smoke", seeds=(0, 1, 2), runs=str(tmp_path / "runs"), results=str(tmp_path / "res"),
                  data=str(tmp_path / "data"), progress=False)
    tasks = ("press_button", "latch_door", "stack_cubes")
    for args in (tables.MainArgs(tasks=tasks, obs_types=("state", "pointcloud"), **common),
                 tables.AblationArgs(tasks=tasks, **common), tables.ExecutionArgs(tasks=tasks, **common),
                 tables.ThresholdsArgs(**common), tables.HparamsArgs(tasks=("press_button", "latch_door"), **common)):
        md = paper.main(args)
        name = tables.table_name(args)
        text = open(md).read()
        assert tables.command_line(args) in text and "seeds 0, 1, 2" in text and "CPU-hours" in text
        assert (tmp_path / "res" / f"{name}.png").stat().st_size > 0
        assert len(_load(tmp_path / "res" / f"{name}.json")["records"]) > 0
        table = [line for line in text.splitlines() if line.startswith("|")]
        assert len({line.count("|") for line in table}) == 1, text  # every row has the header's columns
        assert re.search(r"\d+\.\d \[\d+\.\d, \d+\.\d\]", text), text  # mean [95 % interval]
    main_md = open(tmp_path / "res" / "main.md").read()
    assert "DP+HiPolicy − DP (points)" in main_md and re.search(r"p=[\d.e-]+ \((wins|ties|loses)\)", main_md)
    # cells by hand from the records: per seed the mean over episodes, then mean ± t(0.975, 2)·s/√3 (clipped to
    # [0, 100] for a rate); the paired cell from the per-seed differences, its p from the t test; the total average
    # from the task means with the Welch standard error and degrees of freedom
    recs = _load(tmp_path / "res" / "main.json")["records"]

    def seed_rates(task, column):
        return np.array([np.mean(r["success"]) for r in sorted(recs, key=lambda r: r["seed"])
                         if r["task"] == task and r["column"] == column])

    def by_hand(v, lo=0.0, hi=1.0, signed=False):
        m, se = v.mean(), v.std(ddof=1) / math.sqrt(v.size)
        half = scipy_stats.t.ppf(0.975, v.size - 1) * se
        f = "+.1f" if signed else ".1f"
        return f"{100 * m:{f}} [{100 * max(m - half, lo):{f}}, {100 * min(m + half, hi):{f}}]", m, se

    row = next(line for line in main_md.splitlines() if line.startswith("| press_button")).split(" | ")
    dp, hi = seed_rates("press_button", "DP"), seed_rates("press_button", "DP+HiPolicy")
    assert row[3] == by_hand(dp)[0] and row[4] == by_hand(hi)[0]
    diff, m, se = by_hand(hi - dp, -1.0, 1.0, signed=True)
    p = 2 * scipy_stats.t.sf(abs(m) / se, 2)
    verdict = "ties" if p >= 0.05 else ("wins" if m > 0 else "loses")
    assert row[7] == f"{diff}, p={p:.2g} ({verdict})", row
    se2 = [by_hand(seed_rates(t, "DP"))[2] ** 2 for t in tasks]
    mean = np.mean([seed_rates(t, "DP").mean() for t in tasks])
    df = sum(se2) ** 2 / sum(v ** 2 / 2 for v in se2)
    half = scipy_stats.t.ppf(0.975, df) * math.sqrt(sum(se2)) / 3
    total = next(line for line in main_md.splitlines() if line.startswith("| **Total average**")).split(" | ")
    assert total[3] == f"{100 * mean:.1f} [{100 * max(mean - half, 0):.1f}, {100 * min(mean + half, 1):.1f}]"
    execution_md = open(tmp_path / "res" / "execution.md").read()
    for label in ("DP SR", "DP+TE SR", "DP+AAC SR", "w/o EG SR", "HiPolicy SR", "HiPolicy Decisions",
                  "HiPolicy − DP+TE (points)", "HiPolicy − DP+AAC (points)"):
        assert label in execution_md
    # precise tasks (press_button, stack_cubes) come first, each group is followed by its average
    order = [main_md.index(k) for k in ("| press_button", "| stack_cubes", "Average (precise)", "| latch_door",
                                        "Average (non-precise)", "Total average")]
    assert order == sorted(order) and "DP3+HiPolicy" in main_md


def test_findings_gather_each_paired_comparison_with_its_verdict(tmp_path):
    """findings.md: one row per (table, HiPolicy vs baseline) pair, a verdict per task from the tables' records,
    '–' for a comparison without records yet (the DP3 columns here), and the tally over every (comparison, task)."""
    from hipolicy_jax.runs.store import write_json

    tasks, seeds = ("press_button", "latch_door"), (0, 1, 2)
    common = dict(budget="smoke", tasks=tasks, seeds=seeds, results=str(tmp_path), progress=False)
    camp = tables.CampaignArgs(**common)
    built = [tables.MainArgs(**common, obs_types=("state", "pointcloud")), tables.ExecutionArgs(**common)]
    assert tables.findings_table(camp, built) is None  # no table built yet

    def rec(task, column, seed, success):
        return {"task": task, "seed": seed, "column": column, "success_rate": float(success),
                "success": [success] * 10, "steps": [50] * 10}

    # main: DP+HiPolicy fails every press_button episode DP solves, and solves every latch_door one DP fails
    main = [rec(t, c, s, (c == "DP") == (t == "press_button")) for t in tasks for c in ("DP", "DP+HiPolicy")
            for s in seeds]
    execution = [rec(t, c, s, True) for t in tasks for c in ("DP+TE", "DP+AAC", "HiPolicy") for s in seeds]
    execution.append(rec("latch_door", "w/o EG", 0, False))  # one seed so far: a point, no verdict, not counted
    write_json(str(tmp_path / "main.json"), {"records": main})
    write_json(str(tmp_path / "execution.json"), {"records": execution})
    text = open(tables.findings_table(camp, built)).read()
    first = text.split("\n## ")[0]  # the comparisons' table (the sections below have rows of their own)
    rows = {line.split(" | ")[0][2:]: line for line in first.splitlines()[1:] if line.startswith("| ")}
    # columns: per task, the average (seed-level t), sign-flip p, episode-level McNemar p (30 episodes each way:
    # p = 1), leave one task out (needs 3 tasks), W/T/L
    assert rows["DP+HiPolicy vs DP"].split(" | ")[2:] == ["-100.0 loses", "+100.0 wins", "+0.0, p=1 (ties)", "1",
                                                           "1", "–", "1/0/1 |"]
    assert rows["DP3+HiPolicy vs DP3"].split(" | ")[2:] == ["–"] * 6 + ["0/0/0 |"]  # no DP3 record yet
    assert rows["HiPolicy vs DP+TE"].split(" | ")[2:4] == ["+0.0 ties", "+0.0 ties"]
    assert "HiPolicy vs DP+AAC" in rows and "HiPolicy vs DP" not in rows  # the main table's pair, counted once
    assert rows["HiPolicy vs w/o EG"].split(" | ")[2:4] == ["–", "+100.0 (1 seed: no test)"]  # same network
    assert "Over the 6 (comparison, task) cells: HiPolicy wins 1, ties 4, loses 1." in text
    assert "## Entropy-guided execution, same network: HiPolicy vs w/o EG" in text
    # version 1's hierarchical bootstrap beside the t interval, per task and average with a verdict (the one-seed
    # w/o EG pair has none): every episode differs by the same amount, so both intervals agree
    side = text.split("## The verdict's interval beside version 1's hierarchical bootstrap")[1]
    assert "| DP+HiPolicy vs DP | 100 demos (main) | press_button | -100.0 loses | -100.0 loses | yes |" in side
    assert "| HiPolicy vs DP+AAC | 100 demos (execution) | Average | +0.0 ties | +0.0 ties | yes |" in side
    assert "They give the same verdict in 9 of 9 cells." in side and "w/o EG" not in side


def test_interval_summary_names_the_cells_the_two_intervals_split():
    rows = [["A vs B", "100 demos (main)", "t1", "+5.0 [-1.0, +11.0] ties", "+5.0 [+1.0, +9.0] wins", "**no**",
             "ties", "wins"],
            ["A vs B", "100 demos (main)", "t2", "+5.0 [+1.0, +9.0] wins", "+5.0 [+2.0, +8.0] wins", "yes",
             "wins", "wins"]]
    text = tables.interval_summary(rows)
    assert text.endswith("They give the same verdict in 1 of 2 cells; they split on: A vs B, 100 demos (main), t1 "
                         "(t: ties, bootstrap: wins).")
    assert tables.interval_summary(rows[1:]).endswith("the same verdict in 1 of 1 cells.")


def test_speed_average_covers_the_same_tasks_in_both_steps_columns():
    """A column that never succeeds on a task has no steps there: the average row's steps (both columns) and steps
    saved cover the tasks where both have steps, its success columns every task, and the note names them. Task a:
    base 60 steps, new 40; task b: base 100, new never succeeds. Over a alone: 60 and 40, saved 1/3; base over
    both tasks would be 80 beside new's 40.
    While a task has no record of a column yet, each column averages every task ('–' for that column)."""
    def rec(task, column, seed, success, steps):
        return {"task": task, "seed": seed, "column": column, "success_rate": float(success),
                "success": [success] * 4, "steps": [steps] * 4}

    records = [rec("a", "base", s, True, 60) for s in range(3)] + [rec("a", "new", s, True, 40) for s in range(3)]
    records += [rec("b", "base", s, True, 100) for s in range(3)] + [rec("b", "new", s, False, 200) for s in range(3)]
    args = None  # speed_rows reads the records alone
    rows = tables.speed_rows(args, records, range(3), ["a", "b"], new="new", base="base")
    assert rows[1][0] == "b" and rows[1][4:] == ["100.0", "–", "–"]
    assert rows[2][0] == "**Average**" and rows[2][1:3] == ["100.0", "50.0"]  # success: both tasks
    assert rows[2][4:6] == ["60.0", "40.0"] and rows[2][6].startswith("+33.3")  # steps: task a only, both columns
    assert tables.steps_average_note(records, range(3), ["a", "b"], "new", "base") == (
        "The average row's success columns average all 2 tasks; its steps and steps saved average the 1 on which "
        "both base and new have steps to success (a), leaving out b (a column without a successful episode there).")
    pending = [r for r in records if not (r["task"] == "b" and r["column"] == "new")]
    # as before: each column's average over all tasks, '–' for the one still without a record on b
    assert tables.speed_rows(args, pending, range(3), ["a", "b"], new="new", base="base")[2][4:] == ["80.0", "–", "–"]
    assert tables.steps_average_note(pending, range(3), ["a", "b"], "new", "base") == ""
    assert tables.steps_average_note(records, range(3), ["a"], "new", "base") == ""


def test_paired_cell_is_seed_level():
    """4 seeds × 100 episodes, the new column succeeding once more on every seed: every seed's difference is +1
    point, so the interval uses the episode-level SE √(4 · 0.01/100)/4 = 0.005 with t(0.975, 3) = 3.1824 and
    p = 2·P(T_3 > 2) = 0.139: a tie (version 1's episode bootstrap called this a win)."""
    ep = [{"task": "a", "seed": s, "column": c, "success_rate": 0.5,
           "success": [True] * 50 + [c == "new"] + [False] * 49} for s in range(4) for c in ("new", "base")]
    assert report.paired_cell(ep, range(4), ["a"], "new", "base") == "+1.0 [-0.6, +2.6], p=0.14 (ties)"
    c = report.paired(ep, range(4), ["a"], "new", "base")
    assert c.mcnemar_p == pytest.approx(2 / 16)  # 4 discordant episodes, all one way
    assert c.sign_flip_p == pytest.approx(2 / 16)  # 4 equal positive seed differences


def test_tables_refuse_to_pair_two_networks_of_one_run():
    net = [{"params_sha256": "a" * 64, "final_loss": 0.1}, {"params_sha256": "b" * 64, "final_loss": 0.1}]
    ep = [{"task": "a", "seed": 0, "column": c, "run": "runs/x/seed0", "network": n, "success": [True, False]}
          for c, n in (("HiPolicy", net[0]), ("w/o EG", net[1]))]
    with pytest.raises(ValueError, match="runs/x/seed0.*different networks"):
        report.paired(ep, (0,), ["a"], "HiPolicy", "w/o EG")
    ep[1]["network"] = net[0]
    assert report.paired(ep, (0,), ["a"], "HiPolicy", "w/o EG").diff.mean == 0.0


def test_table_formatting_helpers():
    assert report.mean_std([0.5, 0.7], 100.0) == "60.0 ± 14.1"
    assert report.mean_std([0.25], 100.0) == "25.0" and report.mean_std([float("nan"), None]) == "–"
    assert report.mean_std([1.0, float("nan"), 3.0]) == "2.0 ± 1.4"  # seeds without a value are left out
    md = report.markdown_table(["Task", "SR"], [["a", "1.0"], ["b", "2.0 ± 0.1"]])
    assert md.splitlines() == ["| Task | SR |", "| :--- | ---: |", "| a | 1.0 |", "| b | 2.0 ± 0.1 |"]
    recs = [{"task": "t", "seed": s, "column": "c", "success_rate": v} for s, v in ((0, 0.2), (1, 0.4))]
    assert report.values(recs, "success_rate", (0, 1, 2), task="t", column="c")[:2] == [0.2, 0.4]
    assert math.isnan(report.values(recs, "success_rate", (0, 1, 2), task="t", column="c")[2])
    # an average or a pooled comparison over tasks of which one has no record yet is '–', not a partial average
    ep = [{"task": t, "seed": 0, "column": c, "success_rate": 0.5, "success": [True, False] * 5}
          for t, c in (("a", "base"), ("b", "base"), ("a", "new"))]
    assert report.ci(ep, "success_rate", (0,), ["a"], 100.0, column="new") == "50.0"  # one network: no interval
    assert report.ci(ep, "success_rate", (0,), ["a", "b"], 100.0, column="new") == "–"
    assert report.ci(ep, "success_rate", (0,), ["a", "b"], 100.0, column="base") != "–"
    assert report.paired_cell(ep, (0,), ["a"], "new", "base") == "+0.0 (1 seed: no test)"
    assert report.paired_cell(ep, (0,), ["a", "b"], "new", "base") == "–"
    # findings.md's per-task cell (the budget rows too): one paired seed is a point with no test, two a verdict
    assert report.finding_text(report.paired(ep, (0,), ["a"], "new", "base")) == "+0.0 (1 seed: no test)"
    two = [{**r, "seed": s, "success": [s == 1 or r["column"] == "new"] * 10} for r in ep[::2] for s in (0, 1)]
    assert report.finding_text(report.paired(two, (0, 1), ["a"], "new", "base")).endswith(" ties")
    far = [{"task": "t", "seed": s, "column": "c", "success_rate": 1.0, "success": [True], "steps": [v]}
           for s, v in ((0, 10), (1, 400))]  # steps to success: the t interval (t(1) = 12.7) clipped at 0
    assert report.ci(far, "mean_steps_success", (0, 1), ["t"], column="c").startswith("205.0 [0.0, 2")
    low = [{"task": "t", "seed": s, "column": "c", "dp3_metric": v} for s, v in ((0, 0.0), (1, 0.02))]
    assert report.ci(low, "dp3_metric", (0, 1), ["t"], 100.0, column="c").startswith("1.0 [0.0, ")  # a rate
    both = ep + [{**ep[1], "column": "new"}]  # both tasks paired, one seed each: a pooled point, no test
    assert report.paired_cell(both, (0,), ["a", "b"], "new", "base") == "+0.0 (a task has 1 seed: no test)"


@pytest.mark.slow
def test_record_trajectory_matches_batched_rollout():
    """``video.record_trajectory`` runs the evaluation's episode loop: same episode key, same outcome."""
    from hipolicy_jax.evaluation import rollout, video

    env = envs.make(TASK)
    policy_fn, init_fn = rollout.expert_policy(env, 8)
    key = jax.random.PRNGKey(3)
    res, rec = rollout.rollout_episodes(policy_fn, init_fn, env, 1, key, history_len=3, chunk_len=8)
    traj = video.record_trajectory(env, jax.random.split(key, 1)[0], policy_fn, init_fn, history_len=3)
    assert traj.success and traj.steps == int(res.steps[0]) and traj.qpos.shape[0] == traj.steps + 1
    np.testing.assert_allclose(traj.qpos, np.asarray(rec.qpos[0, :traj.steps + 1]), atol=1e-5)
    frames = video.annotate_frames(video.render_frames(env, traj._replace(qpos=traj.qpos[:3]), height=24, width=32,
                                                       backend="raycast"), traj)
    assert frames.shape == (3, 24, 32, 3) and frames.dtype == np.uint8


def test_campaign_records_an_evaluation_and_rebuilds_from_it(tiny, tmp_path):
    """A campaign evaluation of a trained run is written to the run's record (configs, calibration, per-episode
    outcomes); a campaign reading records only returns it without the run dir, and nothing for an unrecorded one."""
    args, run = tiny
    camp = Campaign("smoke", runs=args.runs, data=args.data, records=str(tmp_path / "records"), episodes=2,
                    progress=False)
    evaluation = camp.evaluate(TASK, Column("HiPolicy"), 0)
    assert len(evaluation["success"]) == len(evaluation["steps"]) == len(evaluation["decisions"]) == 2
    path = tmp_path / "records" / "smoke" / TASK / "state" / "hipolicy" / "seed0.json"
    record = _load(path)
    assert record["task"] == TASK and record["seed"] == 0 and record["policy"]["chunk"]["strides"] == [1, 2, 3]
    assert record["calibration"]["thresholds"] == _load(os.path.join(run, "calibration.json"))["thresholds"]
    cores = len(os.sched_getaffinity(0))  # wall time x the cores the process ran on: the cost's upper bound
    assert record["training"]["cpu_cores"] == evaluation["cpu_cores"] == cores
    # the cost itself: the process CPU time of the training (all its threads) and of the evaluation
    assert 0 < record["training"]["cpu_time_s"] and 0 < evaluation["eval_cpu_s"]
    # which rollout made it (the Evaluator's default, the compacted one): the cost model plans with its rate
    assert evaluation["rollout"] == "compacted" and evaluation_rollout(evaluation) == "compacted"
    # the demos' size travels with the record, so the main table's "Demo steps" rebuilds without the buffer
    from hipolicy_jax.data.replay_buffer import ReplayBuffer

    buffer = ReplayBuffer.load(tables.train_args(args, TASK, "state", (), 0).data_path())
    assert record["demos"] == {"episodes": SMOKE.demos, "frames": buffer.num_frames}
    lengths = f"{buffer.episode_lengths().mean():.0f}"
    no_buffer = dataclasses.replace(args, records=str(tmp_path / "records"), data=str(tmp_path / "no_data"))
    assert tables.demo_steps(no_buffer, TASK) == tables.demo_steps(args, TASK) == lengths
    assert tables.demo_steps(dataclasses.replace(no_buffer, records=str(tmp_path / "none")), TASK) == "–"
    same = json.dumps([evaluation], sort_keys=True)  # NaN-safe equality
    assert json.dumps(list(record["evaluations"].values()), sort_keys=True) == same
    offline = Campaign("smoke", runs=str(tmp_path / "no_runs"), records=str(tmp_path / "records"), episodes=2,
                       from_records=True)
    assert json.dumps([offline.evaluate(TASK, Column("HiPolicy"), 0)], sort_keys=True) == same
    assert offline.evaluate(TASK, Column("w/o EG", guided=False), 0) is None  # not recorded: never evaluated
    assert offline.evaluate(TASK, Column("HiPolicy"), 1) is None
    # thresholds at the calibration's own percentiles are the calibration's: the recorded evaluation is reused
    again = camp.evaluate(TASK, Column("p10/p70", percentiles=(10.0, 70.0)), 0)
    assert again["same_as"] == json.loads(list(record["evaluations"])[0]) and again["eval_s"] == 0.0
    assert again["success"] == evaluation["success"] and again["thresholds"] == evaluation["thresholds"]
    other = camp.evaluate(TASK, Column("p40/p90", percentiles=(40.0, 90.0)), 0)
    assert "same_as" not in other and other["thresholds"] != evaluation["thresholds"]
    # one network per record: the record and each evaluation carry the EMA parameters' hash and the final loss
    from hipolicy_jax.runs import records as rec_lib

    net = {"params_sha256": rec_lib.params_fingerprint(load_run(run).policy.params),
           "final_loss": _load(os.path.join(run, "summary.json"))["final_loss"]}
    record = _load(path)
    assert record["version"] == 2 and record["network"] == net
    assert all(ev["network"] == net for ev in record["evaluations"].values())
    # a record of another network (the run retrained elsewhere): its evaluations move to 'superseded' and the
    # evaluation asked for is made on this network
    stale = {"params_sha256": "0" * 64, "final_loss": 1.0}
    record["network"] = stale
    for ev in record["evaluations"].values():
        ev["network"] = stale
    jsonio.dump(record, str(path))
    assert camp.evaluate(TASK, Column("HiPolicy"), 0) == _load(path)["evaluations"][list(record["evaluations"])[0]]
    # (a recorded evaluation is of the record's network: returned as it is); a new one is made on the run's
    # network, and the record's evaluations of the other network move aside, to be made again when asked for
    plain = camp.evaluate(TASK, Column("w/o EG", guided=False), 0)
    now = _load(path)
    assert now["network"] == net and plain["network"] == net and list(now["evaluations"].values()) == [plain]
    assert now["superseded"][0]["network"] == stale and len(now["superseded"][0]["evaluations"]) == 3
    assert rec_lib.problems(now) == []


def test_pilot_candidates_and_choice():
    assert pilot_candidates(0.94) == [{"episodes": 50}, {"episodes": 25}, {"episodes": 12}]
    assert pilot_candidates(0.05) == [{"train.num_steps": 4000}, {"train.num_steps": 8000}]
    tried = [({"episodes": 50}, 0.9), ({"episodes": 25}, 0.6), ({"episodes": 12}, 0.2)]
    assert choose_low_regime(tried) == ({"episodes": 25}, True)
    assert choose_low_regime([({"episodes": 50}, 0.95), ({"episodes": 25}, 0.9), ({"episodes": 12}, 0.12)]) == \
        ({"episodes": 12}, False)  # none in range: the closest to 50 %


@pytest.mark.slow
def test_paper_execution_smoke_reuses_trained_run_and_rebuilds_from_records(tiny):
    args, run = tiny
    md = paper.main(args)  # trains only the DP run; the HiPolicy run of the fixture is reused
    text = open(md).read()
    assert "python -m experiments.paper execution --budget smoke" in text and "seeds 0" in text
    assert "| press_button |" in text and os.path.getsize(os.path.join(args.results, "execution.png")) > 0
    records = _load(os.path.join(args.results, "execution.json"))["records"]
    assert {r["column"] for r in records} == {"DP", "DP+TE", "DP+AAC", "w/o EG", "HiPolicy"}
    assert all(0.0 <= r["success_rate"] <= 1.0 for r in records)
    by = {r["column"]: r for r in records}
    assert by["w/o EG"]["run"] == by["HiPolicy"]["run"] == os.path.relpath(run)
    assert by["w/o EG"]["stride1_frac"] == 1.0 and by["DP"]["stride1_frac"] == 1.0
    assert by["DP+TE"]["mean_actions_per_decision"] == 1.0
    again = paper.main(dataclasses.replace(args, from_records=True, runs=args.runs + "_gone"))
    assert open(again).read().split("Cost:")[1] == text.split("Cost:")[1]  # the same table from the records


def test_env_camera_and_data_follow_the_encoder(tmp_path):
    """The env camera, the default demo path and the buffer check all follow the encoder config (image size, point
    count, rgb), so a non-default encoder trains on demos of its own resolution."""
    from hipolicy_jax.config import EncoderConfig
    from hipolicy_jax.data.replay_buffer import ReplayBuffer
    from hipolicy_jax.envs.demos import check_buffer, default_data_path

    img = EncoderConfig(obs_type="image", image_size=40, crop_size=36)
    pts = EncoderConfig(obs_type="pointcloud", num_points=96, point_dims=6)
    state_shape = envs.make_for_encoder(TASK).obs_shapes["state"]
    assert envs.make_for_encoder(TASK, img).obs_shapes == {"state": state_shape, "image": (40, 40, 3)}
    assert envs.make_for_encoder(TASK, pts).obs_shapes["point_cloud"] == (96, 6)
    assert default_data_path(TASK, EncoderConfig(), 100) == os.path.join("data", f"{TASK}_state_100.zarr")
    assert default_data_path(TASK, img, 7).endswith(f"{TASK}_state-image_40px_7.zarr")
    assert default_data_path(TASK, pts, 7).endswith(f"{TASK}_state-point_cloud_96pts-rgb_7.zarr")

    def buffer(points: int, dims: int) -> ReplayBuffer:
        ep = {"state": np.zeros((5, 4), np.float32), "action": np.zeros((5, 4), np.float32),
              "point_cloud": np.zeros((5, points, dims), np.float32)}
        return ReplayBuffer.from_episodes([ep])

    check_buffer(buffer(96, 6), pts, "ok.zarr")
    with pytest.raises(ValueError, match=r"bad.zarr: data/point_cloud .*\(512, 3\).*\(96, 6\).*num_points"):
        check_buffer(buffer(512, 3), pts, "bad.zarr")
    with pytest.raises(ValueError, match=r"lacks keys \['image'\]"):
        check_buffer(buffer(96, 6), img, "img.zarr")


def test_train_args_vision_policies_read_proprioception_only():
    """An image / point-cloud policy picked on the command line reads the state's proprioception only (as DP / DP3),
    unless --privileged-state or an explicit state_dims says otherwise; state policies read everything."""
    from hipolicy_jax.envs.base import PROPRIO_DIM
    from hipolicy_jax.runs.train import RunConfig

    def parse(*argv):
        return tyro.cli(RunConfig, args=list(argv)).policy.encoder.state_dims

    assert parse() is None
    assert parse("--policy.encoder.obs-type", "pointcloud") == PROPRIO_DIM == 4
    assert parse("--policy.encoder.obs-type", "image", "--privileged-state") is None
    assert parse("--policy.encoder.obs-type", "image", "--policy.encoder.state-dims", "7") == 7
    assert tables.train_args(tables.MainArgs(), TASK, "pointcloud", (), 0).policy.encoder.state_dims == PROPRIO_DIM
    assert tables.train_args(tables.MainArgs(), TASK, "pointcloud", (), 0).policy.encoder.num_points == 256


def test_campaign_follows_the_protocol():
    """The campaign's tables are the protocol's: main and execution in both regimes, ablation in Rlow on every task,
    thresholds and hyper-parameters in Rlow on two tasks; baselines get the extra seeds."""
    args = paper.parse_args(["campaign", "--budget", "smoke"])
    protocol = tables.protocol_tables(args)
    got = [(tables.table_name(t), t.regime, t.tasks) for t in protocol]
    four = ("press_button", "stack_cubes", "latch_door", "pick_place")
    two = ("press_button", "latch_door")
    assert got == [("main", "r100", four), ("execution", "r100", four), ("main", "rlow", four),
                   ("execution", "rlow", four), ("ablation", "rlow", four), ("thresholds", "rlow", two),
                   ("hparams", "rlow", two), ("budget", "r100", ("press_button", "stack_cubes"))]
    assert all(t.episodes == 100 and t.baseline_seeds == (3, 4) for t in protocol[:-1])
    budget = protocol[-1]  # protocol v2: DP and DP+HiPolicy, seeds 0-2, at 2,000 (the main runs), 8,000, 24,000
    assert budget.steps == (2000, 8000, 24000) and budget.baseline_seeds == () and budget.seeds == (0, 1, 2)
    assert [c.label for c in tables.COLUMNS["budget"](budget)] == ["DP", "DP+HiPolicy"]
    assert tables.table_run_changes(dataclasses.replace(budget, budget="cpu"), "press_button") == [
        {}, {"train.num_steps": 8000}, {"train.num_steps": 24000}]  # the cpu budget's 2,000 steps: its own runs
    only = tables.protocol_tables(paper.parse_args(["campaign", "--budget", "smoke", "--only", "budget"]))
    assert [tables.table_name(t) for t in only] == ["budget"]
    main = protocol[0]
    dp, hip, dp3, dp3_hip = tables.main_columns(main)  # the DP3 columns are part of the protocol's main table
    assert dp3.obs_type == dp3_hip.obs_type == "pointcloud"
    assert tables.column_seeds(main, dp) == (0, 1, 2, 3, 4) and tables.column_seeds(main, hip) == (0, 1, 2)
    assert tables.column_seeds(main, dp3) == tables.column_seeds(main, dp3_hip) == (0, 1, 2)  # > 5 min a run
    assert paper.parse_args(shlex.split(tables.command_line(args))[3:]) == args


def test_campaign_schedule_completes_paired_comparisons_first():
    """The campaign runs each job once: the protocol's seeds before the baselines' extra seeds, state before point
    clouds, the task with the longest episodes (pick_place) last, else in table order."""
    args = paper.parse_args(["campaign", "--budget", "smoke"])
    jobs, skipped = tables.campaign_jobs(args, tables.protocol_tables(args))
    assert not skipped and len(jobs) == len(set(jobs))
    stage = [(j.seed not in args.seeds, j.col.obs_type != "state", j.task == "pick_place") for j in jobs]
    assert stage == sorted(stage) and len(set(stage)) == 6  # point clouds have no extra seeds
    first = [(j.task, j.col.label, j.seed) for j in jobs[:4]]
    assert first == [("press_button", "DP", 0), ("press_button", "DP", 1), ("press_button", "DP", 2),
                     ("stack_cubes", "DP", 0)]
    extra = [i for i, j in enumerate(jobs) if j.seed not in args.seeds]
    cloud = [i for i, j in enumerate(jobs) if j.col.obs_type == "pointcloud"]
    assert extra and cloud and max(cloud) < min(extra) and jobs[-1].task == "pick_place"
    assert {jobs[i].col.obs_type for i in extra} == {"state"}
    assert schedule([jobs[0], jobs[0]], (0,)) == [jobs[0]]


def test_campaign_shards_split_runs_and_the_plan_estimates_from_records(tmp_path, capsys):
    """--shard K N splits the jobs by run (disjoint, complete, balanced, no run in two shards); the cost model
    estimates a pending job from the records' CPU-seconds (wall × cores): training per step of the variant, else of
    the observation type, plus the evaluation of the task and strategy; recorded jobs, evaluations another column
    shares and unmeasured observation types are told apart; a run resumed from a checkpoint is estimated for
    the steps after it; the plan file sums it."""
    args = paper.parse_args(["campaign", "--budget", "smoke", "--runs", str(tmp_path / "runs"), "--records",
                             str(tmp_path / "records"), "--results", str(tmp_path / "results"), "--no-progress"])
    camp = tables.campaign(args)
    jobs, _ = tables.campaign_jobs(args, tables.protocol_tables(args))
    def run_of(j):
        return camp.run_config(j.task, j.col, j.seed, dict(j.changes)).out_dir()

    parts = [shard(jobs, k, 3, run_of) for k in range(3)]
    assert sorted(id(j) for p in parts for j in p) == sorted(map(id, jobs))  # each job in exactly one shard
    runs = [{run_of(j) for j in p} for p in parts]
    assert not (runs[0] & runs[1] or runs[0] & runs[2] or runs[1] & runs[2])
    assert max(map(len, runs)) - min(map(len, runs)) <= 1

    dp, te = Column("DP", changes=DP), Column("DP+TE", changes=DP, execution="te")
    hip, dp3 = Column("DP+HiPolicy"), Column("DP3", "pointcloud", DP)
    key0 = camp._key(dp, 0)[1]
    dp_cfg = camp.run_config("press_button", dp, 0)

    def write_record(variant, training):
        net = {"params_sha256": None, "final_loss": 0.1}
        record = {"version": 2, "network": net, "policy": config_to_dict(dp_cfg.policy),
                  "train": config_to_dict(dp_cfg.train), "training": training,
                  "evaluations": {key0: {"settings": json.loads(key0), "eval_s": 5.0, "cpu_cores": 2,
                                         "network": net}}}
        path = tmp_path / "records" / "smoke" / "press_button" / "state" / variant / "seed0.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps(record))

    write_record("dp", {"steps": 10, "wall_time_s": 100.0, "cpu_cores": 1})
    # a run of the same network (another regime) from a process that did not say its cores: it shared them with
    # other jobs (1000 CPU-s a step), and the record that says its cores wins
    write_record("dp_t20", {"steps": 10, "wall_time_s": 5000.0})
    model = CostModel(str(tmp_path / "records"), str(tmp_path / "runs"))
    # what was spent: each record's training (wall × its cores, 2 when unstated) and evaluations once
    assert model.spent("smoke") == {"train_s": 100.0 * 1 + 5000.0 * 2, "runs": 2, "eval_s": 2 * 5.0 * 2,
                                    "evaluations": 2, "measured_runs": 0, "measured_evaluations": 0,
                                    "wall_core_s": 100.0 * 1 + 5000.0 * 2 + 2 * 5.0 * 2}
    assert model.spent("cpu") == {"train_s": 0.0, "runs": 0, "eval_s": 0.0, "evaluations": 0, "measured_runs": 0,
                                  "measured_evaluations": 0, "wall_core_s": 0.0}
    todo = [Job("press_button", dp, 0), Job("press_button", dp, 1), Job("press_button", te, 1),
            Job("press_button", Column("w/o Hier.", changes=DP), 1), Job("stack_cubes", hip, 0),
            Job("stack_cubes", dp3, 0), Job("stack_cubes", dp, 0, (("train.num_steps", 40),))]
    rows = model.estimate(camp, todo)
    steps = BUDGETS["smoke"].train.num_steps
    assert [(r["done"], r["trains"], r["seconds"]) for r in rows] == [
        (True, False, 0.0),  # recorded
        (False, True, 10.0 * steps + 10.0),  # trains (10 CPU-s per step) and evaluates (5 s on 2 cores)
        (False, False, 10.0),  # the same run, another strategy: the task's evaluations
        (False, False, 0.0),  # the same evaluation as DP's seed 1 under another table's label
        (False, True, 10.0 * steps + 10.0),  # no record of its network: the state runs' per-step time
        (False, True, None),  # no point-cloud record at all: unmeasured
        (False, True, 10.0 * 40 + 10.0)]  # the DP network on another task and regime: its per-step time × 40 steps
    # a run interrupted at a checkpoint (a preempted job) resumes there: only the steps after it are estimated
    ckpt = Path(dp_cfg.out_dir()).parent / "seed1" / "checkpoints"
    (ckpt / str(steps // 2)).mkdir(parents=True)
    (ckpt / "tmp-orbax").mkdir()  # not a step
    resumed = model.estimate(camp, todo[1:2])[0]
    assert (resumed["trains"], resumed["seconds"]) == (True, 10.0 * (steps - steps // 2) + 10.0)
    shutil.rmtree(ckpt)
    # a campaign estimates once when it starts; each pending job is estimated again before it starts, from the
    # records then: an unmeasured one once its kind has a record, a measured one at the rate newer records measured
    assert model.refresh(camp, rows[5])["seconds"] is None
    assert model.refresh(camp, rows[0]) is rows[0]  # recorded
    assert model.refresh(camp, rows[1]) == rows[1]
    dp3_cfg = camp.run_config("stack_cubes", dp3, 0)
    pc = tmp_path / "records" / "smoke" / "press_button" / "pointcloud" / "dp" / "seed0.json"
    pc.parent.mkdir(parents=True)
    pc.write_text(json.dumps({"version": 2, "policy": config_to_dict(dp3_cfg.policy),
                              "train": config_to_dict(dp3_cfg.train),
                              "training": {"steps": 10, "wall_time_s": 300.0, "cpu_cores": 1}, "evaluations": {}}))
    newer = CostModel(str(tmp_path / "records"), str(tmp_path / "runs"))
    fresh = newer.refresh(camp, rows[5])
    assert (fresh["done"], fresh["trains"], fresh["seconds"]) == (False, True, 30.0 * steps + 10.0)
    # a record that measured its process CPU time (the first rate free of other jobs' share of the cores) sets the
    # per-step rate of the runs after it: 2 CPU-s a step, not the 10 s of wall time x cores
    write_record("dp_t30", {"steps": 10, "wall_time_s": 100.0, "cpu_cores": 1, "cpu_time_s": 20.0})
    fresh = CostModel(str(tmp_path / "records"), str(tmp_path / "runs")).refresh(camp, rows[1])
    assert (fresh["trains"], fresh["seconds"]) == (True, 2.0 * steps + 10.0)
    rows = rows[:-1]
    text = Path(tables.write_plan(args, rows)).read_text()
    assert "1 of 6 evaluations recorded" in text and "1 unmeasured" in text
    assert f"{(2 * (10.0 * steps + 10.0) + 10.0) / 3600:.1f} CPU-hours" in text
    with pytest.raises(ValueError, match="shard: expected K N with 0 <= K < N, got 2 2"):
        tables.campaign_table(dataclasses.replace(args, shard=(2, 2)))


def test_cost_model_plans_evaluations_at_the_compacted_rollout_rate(tmp_path):
    """The compacted rollout (the Evaluator's default) evaluates faster than the vmapped one that made the older
    records (no ``rollout``): an evaluation is estimated from the compacted ones when its selection has any (before
    the cores-stated preference), else from the vmapped ones; a Meta-World evaluation (no MJX rollout) counts as
    made at today's rate."""
    def write(records, name, variant, evaluations, **rec):
        path = tmp_path / records / "cpu" / name.replace(":", "_") / "state" / variant / "seed0.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"training": {}, "evaluations": {
            str(i): {"settings": {"execution": execution}, "eval_s": s, **extra}
            for i, (execution, s, extra) in enumerate(evaluations)}, **rec}))

    stated = {"cpu_cores": 2}
    write("records", "press_button", "dp", [("chunk", 30.0, stated), ("te", 40.0, stated), ("aac", 50.0, stated)])
    write("records", "press_button", "hipolicy", [("chunk", 10.0, {**stated, "rollout": "compacted"}),
                                                  ("aac", 8.0, {"rollout": "compacted"}),  # cores unstated (2)
                                                  ("te", 45.0, {**stated, "rollout": "vmapped"})])
    model = CostModel(str(tmp_path / "records"), str(tmp_path / "runs"))
    assert model.eval_seconds("press_button", "chunk") == 10.0 * 2  # the compacted one, not the vmapped 60
    assert model.eval_seconds("press_button", "te") == (40.0 + 45.0) / 2 * 2  # no compacted one: the vmapped ones
    assert model.eval_seconds("press_button", "aac") == 8.0 * 2  # compacted first, then cores stated
    assert model.eval_seconds("stack_cubes", "chunk") == 10.0 * 2  # any task: compacted, of those cores stated
    # the vmapped older records of an MJX task and a Meta-World record (no "rollout" either): the latter is today's
    write("external", "press_button", "dp", [("chunk", 30.0, stated)])
    write("external", "metaworld:basketball", "dp", [("chunk", 100.0, stated)], task="metaworld:basketball")
    model = CostModel(str(tmp_path / "external"), str(tmp_path / "runs"))
    assert model.eval_seconds("stack_cubes", "chunk") == 100.0 * 2
    assert model.eval_seconds("press_button", "chunk") == 30.0 * 2
    # a Meta-World task's evaluations are read under its folder name (metaworld_basketball)
    assert model.eval_seconds("metaworld_basketball", "chunk") == 100.0 * 2


def test_cost_counts_measured_cpu_time_before_wall_time(tmp_path):
    """A record that measured its process CPU time counts that; an older one counts wall time × its cores (2 when
    unstated): in what was spent, in the estimates (measured ones preferred) and in a table's Cost line."""
    def write(variant, training, evaluation):
        path = tmp_path / "records" / "cpu" / "press_button" / "state" / variant / "seed0.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"training": training, "policy": {"chunk": {"strides": [1]}}, "evaluations": {
            "0": {"settings": {"execution": "chunk"}, "rollout": "compacted", **evaluation}}}))

    write("dp", {"steps": 100, "wall_time_s": 300.0, "cpu_cores": 1, "cpu_time_s": 200.0},
          {"eval_s": 60.0, "cpu_cores": 1, "eval_cpu_s": 40.0})
    write("dp_t8000", {"steps": 100, "wall_time_s": 300.0, "cpu_cores": 1}, {"eval_s": 60.0, "cpu_cores": 1})
    model = CostModel(str(tmp_path / "records"), str(tmp_path / "runs"))
    assert model.spent("cpu") == {"train_s": 200.0 + 300.0, "runs": 2, "eval_s": 40.0 + 60.0, "evaluations": 2,
                                  "measured_runs": 1, "measured_evaluations": 1,
                                  "wall_core_s": 300.0 + 300.0 + 60.0 + 60.0}
    assert model.eval_seconds("press_button", "chunk", 1) == 40.0  # the measured one
    rows = [{"run": "a", "training_s": 300.0, "training_cores": 1, "training_cpu_s": 200.0, "eval_s": 60.0,
             "cpu_cores": 1, "eval_cpu_s": 40.0},
            {"run": "a", "training_s": 300.0, "training_cores": 1, "training_cpu_s": 200.0, "eval_s": 30.0,
             "cpu_cores": 1, "eval_cpu_s": 20.0}]
    assert report.cost_note(rows) == ("Cost: 0.1 CPU-hours on this 2-core machine kind (0.1 h training 1 runs, "
                                      "0.0 h evaluating), from the records (measured process CPU time).")
    rows.append({"run": "b", "training_s": 3600.0, "eval_s": 1800.0})  # an older record: wall × 2 cores
    assert report.cost_note(rows) == (
        "Cost: 3.1 CPU-hours on this 2-core machine kind (2.1 h training 2 runs, 1.0 h evaluating), from the "
        "records (process CPU time of 1 of 2 runs and 2 of 3 evaluations, wall time × the cores its process ran "
        "on for the rest: an upper bound, other jobs on those cores count too).")


def test_cost_model_plans_a_hipolicy_evaluation_from_hipolicy_evaluations(tmp_path):
    """A HiPolicy evaluation draws N samples a decision where DP draws one: a pending evaluation is estimated from
    evaluations of policies with as many strides (on its task, else on any task) before the task's of another
    stride count; records that do not name their policy's strides count for any."""
    def write(name, variant, strides, seconds):
        path = tmp_path / "records" / "metaworld" / name / "state" / variant / "seed0.json"
        path.parent.mkdir(parents=True)
        policy = {"chunk": {"strides": strides}} if strides else {}
        path.write_text(json.dumps({"training": {}, "policy": policy, "evaluations": {"0": {
            "settings": {"execution": "chunk"}, "eval_s": seconds, "cpu_cores": 1}}}))

    write("metaworld_basketball", "dp_t4000", [1], 100.0)
    write("metaworld_basketball", "hipolicy_t4000", [1, 2, 3], 1000.0)
    write("metaworld_assembly", "dp_t4000", [1], 120.0)
    model = CostModel(str(tmp_path / "records"), str(tmp_path / "runs"))
    assert model.eval_seconds("metaworld_basketball", "chunk", 3) == 1000.0
    assert model.eval_seconds("metaworld_basketball", "chunk", 1) == 100.0
    # no HiPolicy record on assembly: basketball's HiPolicy evaluation, not assembly's DP one
    assert model.eval_seconds("metaworld_assembly", "chunk", 3) == 1000.0
    assert model.eval_seconds("metaworld_assembly", "chunk", 1) == 120.0
    # a task with no record: the same stride count on any task (median), else everything
    assert model.eval_seconds("metaworld_shelf-place", "chunk", 1) == 110.0
    assert model.eval_seconds("metaworld_shelf-place", "chunk", 2) == 120.0  # no 2-stride record: all three
    assert model.eval_seconds("metaworld_shelf-place", "te", 1) == 120.0  # no TE record anywhere: all three
    write("metaworld_shelf-place", "unnamed", None, 50.0)  # strides unknown: only the wildcard selections
    model = CostModel(str(tmp_path / "records"), str(tmp_path / "runs"))
    assert model.eval_seconds("metaworld_shelf-place", "chunk", 3) == 1000.0
    assert model.eval_seconds("metaworld_shelf-place", "chunk", 2) == 50.0  # the task's own, any stride count


def test_deadline_starts_only_the_jobs_that_end_before_until():
    """--until: a job starts when its estimated CPU-seconds over the process's cores end before the limit, else the
    next one that fits runs; a run whose training was skipped keeps its later evaluations skipped; recorded jobs
    always pass; unmeasured jobs count at the guess; no limit admits everything. HH:MM is its next occurrence."""
    now = [1000.0]
    deadline = Deadline(until=1000.0 + 100.0, cores=2, guess=50.0, clock=lambda: now[0])
    train_a = {"done": False, "trains": True, "seconds": 300.0}  # 150 s on 2 cores > 100 s left
    eval_a = {"done": False, "trains": False, "seconds": 20.0}  # cheap, but run a was never trained
    assert not deadline.admits(train_a, "runs/a") and not deadline.admits(eval_a, "runs/a")
    assert deadline.admits({"done": False, "trains": True, "seconds": 200.0}, "runs/b")  # 100 s: ends in time
    assert deadline.admits({"done": True, "trains": False, "seconds": 0.0}, "runs/a")  # a record costs nothing
    assert deadline.admits({"done": False, "trains": False, "seconds": None}, "runs/c")  # guess: 25 s
    now[0] = 1090.0  # 10 s left
    assert not deadline.admits({"done": False, "trains": False, "seconds": 40.0}, "runs/c")  # an evaluation: ...
    assert deadline.admits({"done": False, "trains": False, "seconds": 20.0}, "runs/c")  # ... its run not skipped
    assert deadline.skipped == {"runs/a"} and deadline.seconds_left() == 10.0
    assert Deadline(None, 1, 1.0).admits(train_a, "runs/a") and Deadline(None, 1, 1.0).seconds_left() == math.inf

    import datetime
    noon = datetime.datetime(2026, 12, 2, 12, 0).timestamp()
    assert parse_until("", noon) is None
    assert parse_until("14:15", noon) == datetime.datetime(2026, 12, 2, 14, 15).timestamp()
    assert parse_until("9:30", noon) == datetime.datetime(2026, 12, 3, 9, 30).timestamp()  # already past: tomorrow
    assert parse_until("2026-12-05 08:00", noon) == datetime.datetime(2026, 12, 5, 8, 0).timestamp()
    for bad in ("25:00", "soon", "2026-13-01 10:00"):
        with pytest.raises(ValueError, match=r"until: expected HH:MM or YYYY-MM-DD HH:MM \(local time\), got"):
            parse_until(bad, noon)


def test_campaign_until_skips_what_does_not_fit(tmp_path, capsys):
    """A campaign whose --until has passed starts nothing: every pending job is skipped with a line saying its
    estimate and the time left, and the shard still writes its plan of what is left."""
    args = paper.parse_args(["campaign", "--budget", "smoke", "--tasks", "press_button", "--regimes", "r100",
                             "--obs-types", "state", "--runs", str(tmp_path / "runs"), "--records",
                             str(tmp_path / "records"), "--results", str(tmp_path / "results"), "--data",
                             str(tmp_path / "data"), "--no-progress", "--shard", "0", "2", "--until", "2000-01-01 00:00"])
    plan = tables.campaign_table(args)
    out = capsys.readouterr().out
    jobs, _ = tables.campaign_jobs(args, tables.protocol_tables(args))
    lines = [line for line in out.splitlines() if ": skipped, estimated " in line]
    assert lines and all("s left before --until 2000-01-01 00:00" in line for line in lines)
    assert len(lines) == len(shard(jobs, 0, 2, lambda j: tables.campaign(args).run_config(
        j.task, j.col, j.seed, dict(j.changes)).out_dir()))
    assert not (tmp_path / "runs").exists() and "0 of" in Path(plan).read_text()
    with pytest.raises(ValueError, match="until: expected HH:MM"):
        tables.campaign_table(dataclasses.replace(args, until="later"))


def test_campaign_no_tables_leaves_the_tables_and_readme_alone(tmp_path):
    """A campaign narrowed to force a few runs (--tasks / --seeds, no shard) ends by rebuilding the tables and the
    README section for its subset; with --no-tables it writes only its plan of what is left."""
    from hipolicy_jax.campaigns.campaign import README_BEGIN, README_END

    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{README_BEGIN}\nthe full tables\n{README_END}\n")
    argv = ["campaign", "--budget", "smoke", "--tasks", "press_button", "--seeds", "0", "--regimes", "r100",
            "--obs-types", "state", "--runs", str(tmp_path / "runs"), "--records", str(tmp_path / "records"),
            "--data", str(tmp_path / "data"), "--no-progress", "--until", "2000-01-01 00:00", "--readme", str(readme)]
    args = paper.parse_args(argv + ["--results", str(tmp_path / "kept"), "--no-tables"])
    assert not args.tables and "--no-tables" in tables.command_line(args)
    plan = tables.campaign_table(args)
    assert sorted(p.name for p in (tmp_path / "kept").iterdir()) == ["campaign_plan.md"]
    assert "0 of" in Path(plan).read_text() and "the full tables" in readme.read_text()
    built = tables.campaign_table(paper.parse_args(argv + ["--results", str(tmp_path / "built")]))
    assert Path(built).name == "campaign.md" and (tmp_path / "built" / "main.md").exists()
    cost = "The campaign so far cost 0.0 CPU-hours of this 2-core machine kind, each run and evaluation counted once"
    assert cost in Path(built).read_text() and cost in readme.read_text()
    assert "the full tables" not in readme.read_text()


def test_campaign_skips_the_runs_another_campaign_process_works_on(tmp_path, capsys):
    """Two campaign processes never work on one run: a run whose campaign lock a live process holds is skipped with
    a line naming its pid, nothing of it is trained, and the campaign goes on (here: writes its plan)."""
    args = paper.parse_args(["campaign", "--budget", "smoke", "--tasks", "press_button", "--regimes", "r100",
                             "--obs-types", "state", "--runs", str(tmp_path / "runs"), "--records",
                             str(tmp_path / "records"), "--results", str(tmp_path / "results"), "--data",
                             str(tmp_path / "data"), "--no-progress", "--shard", "1", "2"])
    camp = tables.campaign(args)
    jobs, _ = tables.campaign_jobs(args, tables.protocol_tables(args))
    mine = shard(jobs, 1, 2, lambda j: camp.run_config(j.task, j.col, j.seed, dict(j.changes)).out_dir())
    dirs = {camp.run_config(j.task, j.col, j.seed, dict(j.changes)).out_dir() for j in mine}
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        for d in dirs:
            os.makedirs(d)
            Path(d, CAMPAIGN_LOCK_FILE).write_text(json.dumps({"pid": sleeper.pid, "host": os.uname().nodename,
                                                               "started": "2026-12-04T20:28:09"}))
        plan = tables.campaign_table(args)
    finally:
        sleeper.kill()
        sleeper.wait()
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("[campaign]")]
    assert len(lines) == len(mine) and all(
        f"skipped, {tmp_path}/runs/" in line and f"is in use by another campaign process (pid {sleeper.pid} on " in line
        and line.endswith("; another shard is training or evaluating it; this one leaves it to that one")
        for line in lines)
    assert not any(f.name == "summary.json" for d in dirs for f in Path(d).iterdir())
    assert f"0 of {len(mine)} evaluations recorded" in Path(plan).read_text()
    with RunLock(sorted(dirs)[0], CAMPAIGN_LOCK_FILE):  # its owner gone (kill -9): the next process takes it over
        pass
    assert not Path(sorted(dirs)[0], CAMPAIGN_LOCK_FILE).exists()


def test_readme_section_from_table_files(tmp_path):
    """The README's campaign section: each table's markdown one heading level down (its inner headings too), named by
    its file, with its plot; only the text between the markers is replaced."""
    from hipolicy_jax.campaigns.campaign import README_BEGIN, README_END, readme_section, update_readme
    results = tmp_path / "results"
    results.mkdir()
    (results / "main_rlow.md").write_text("# Main results\n\n- Cost: 1.0 CPU-hours\n\n| a |\n|---|\n| 1 |\n")
    (results / "main_rlow.png").write_bytes(b"png")
    (results / "ablation_rlow.md").write_text("# Ablation\n\n| b |\n\n## Per seed\n\n| c |\n")
    section = readme_section([str(results / "main_rlow.md"), str(results / "ablation_rlow.md")], str(tmp_path))
    assert section.startswith("### Main results — `results/main_rlow.md`")
    assert "\n### Ablation — `results/ablation_rlow.md`\n" in section and "\n#### Per seed\n" in section
    assert "## Per seed" not in section.replace("#### Per seed", "")
    assert readme_section([str(results / "ablation_rlow.md")], str(tmp_path), level=4).startswith("#### Ablation")
    assert "![main_rlow.png](results/main_rlow.png)" in section and "ablation_rlow.png" not in section
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{README_BEGIN}\nold\n{README_END}\nafter\n")
    assert update_readme(str(readme), section)
    text = readme.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{README_END}\nafter\n") and "old" not in text
    assert "| 1 |" in text and "- Cost: 1.0 CPU-hours" in text
    other = tmp_path / "OTHER.md"
    other.write_text("no markers\n")
    assert not update_readme(str(other), section) and other.read_text() == "no markers\n"


def test_campaign_writes_its_tables_into_the_results_page():
    """Issue #61: the campaign's ``--readme`` (the flag keeps its name) defaults to docs/results.md, the page that
    holds its markers once (the README, which held them before, holds none); the committed campaign's own command
    line, printed with ``--readme README.md``, still parses."""
    from hipolicy_jax.campaigns.campaign import README_BEGIN, README_END
    root = Path(__file__).resolve().parents[1]
    args = paper.parse_args(["campaign"])
    assert args.readme == "docs/results.md"
    text = (root / args.readme).read_text()
    assert text.count(README_BEGIN) == 1 and text.count(README_END) == 1
    assert text.index(README_BEGIN) < text.index(README_END)
    assert README_BEGIN not in (root / "README.md").read_text()
    command = re.search(r"^Command: `(.*)`$", (root / "results" / "campaign.md").read_text(), re.M).group(1)
    old = paper.parse_args(shlex.split(command)[3:])
    assert type(old) is type(args) and old.readme in ("README.md", "docs/results.md")


def test_evaluate_compute_dtype_rebuilds_the_network_only(tiny):
    """``experiments.evaluate --compute-dtype bfloat16``: the same float32 parameters in a network whose U-Net runs
    bf16 operands; its denoiser output stays close to the float32 one; 'run' leaves the run untouched."""
    from hipolicy_jax.runs.store import with_compute_dtype

    _, run = tiny
    args = parse_with_run_inference(evaluate.EvaluateArgs, ["--checkpoint", run, "--compute-dtype", "bfloat16"])
    assert args.compute_dtype == "bfloat16"
    base = load_run(run)
    assert with_compute_dtype(base, "run") is base and with_compute_dtype(base, "float32") is base
    low = with_compute_dtype(base, "bfloat16")
    assert low.policy.cfg.model.compute_dtype == "bfloat16" and low.policy.net.cfg.model.compute_dtype == "bfloat16"
    assert low.policy.params is base.policy.params and low.task == base.task
    cfg = base.policy.cfg
    x = jax.random.normal(jax.random.key(0), (2, cfg.chunk.horizon, base.action_dim))
    obs = {"state": jax.random.uniform(jax.random.key(2), (2, cfg.chunk.num_freqs, cfg.chunk.obs_horizon,
                                                             base.policy.normalizer.stats["state"]["scale"].shape[-1]))}
    t = np.array([3, 40])
    ref = np.asarray(base.policy.net.apply(base.policy.params, obs, x, t))
    out = low.policy.net.apply(base.policy.params, obs, x, t)
    assert out.dtype == np.float32 and 0 < np.abs(np.asarray(out) - ref).max() < 0.05 * np.abs(ref).max()


_CACHE_PROBE = """
import jax, jax.numpy as jnp
from jax import monitoring
from hipolicy_jax.runs.cli import enable_compilation_cache
hits = []
monitoring.register_event_listener(lambda event, **kw: hits.append(event) if "cache_hits" in event else None)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
print("dir", enable_compilation_cache())
jax.jit(lambda x: jnp.sin(x) @ x.T + 3.0)(jnp.ones((8, 8))).block_until_ready()
print("hits", len(hits))
"""


def test_compilation_cache_is_shared_across_processes(tmp_path):
    """Entry points keep compiled executables on disk: a second process loads what the first compiled;
    JAX_COMPILATION_CACHE_DIR chooses the folder (unset: $XDG_CACHE_HOME/hipolicy_jax/xla), empty turns it off."""
    def probe(**env):
        base = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
        out = subprocess.run([sys.executable, "-c", _CACHE_PROBE], env={**base, **env}, capture_output=True,
                             text=True, check=True).stdout.split("\n")
        return out[0].split(" ", 1)[1], int(out[1].split()[1])

    xdg = tmp_path / "xdg"
    assert probe(XDG_CACHE_HOME=str(xdg)) == (str(xdg / "hipolicy_jax" / "xla"), 0)
    assert os.listdir(xdg / "hipolicy_jax" / "xla")  # the executable is on disk
    assert probe(XDG_CACHE_HOME=str(xdg))[1] >= 1  # ... and the next process loads it
    named = tmp_path / "named"
    assert probe(JAX_COMPILATION_CACHE_DIR=str(named)) == (str(named), 0) and os.listdir(named)
    assert probe(JAX_COMPILATION_CACHE_DIR="", XDG_CACHE_HOME=str(tmp_path / "off")) == ("None", 0)
    assert not (tmp_path / "off").exists()


def test_results_header_names_each_tasks_regime():
    """A low-data table's header says what the regime changed per task (demos or steps), since the budget's note
    describes R100; R100's header adds nothing."""
    from hipolicy_jax.campaigns.budgets import REGIMES
    rlow = tables.AblationArgs(regime="rlow", tasks=tuple(REGIMES["rlow"]))
    header = tables.results_header("T", rlow, [])
    for task, changes in REGIMES["rlow"].items():
        assert f"{task}: {report.changes_text(changes)}" in header
    assert "Regime `rlow` (" in header
    r100 = tables.results_header("T", tables.AblationArgs(regime="r100"), [])
    assert "Regime `r100`;" in r100
