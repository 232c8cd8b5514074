"""Closed-loop calibration of an external task's run (issue 58 item 3): the bridge records every decision's stride and
entropy, and ``experiments.calibrate --source rollouts [--rule success]`` rolls a ``metaworld:`` run out through
the policy server and its bridge on calibration episodes disjoint from the evaluation's.

The bridge runs in its own venv (``bash scripts/setup_metaworld.sh`` → ``.venv-metaworld``; ``METAWORLD_VENV``
chooses another); the tests that run it are skipped without it. The calibration logic is also tested with the bridge
faked at ``runs.external.evaluate_run`` (a scripted policy whose entropies, strides and successes are known by hand).
"""

import dataclasses
import json
import os
import subprocess
import types

import numpy as np
import pytest

from hipolicy_jax.config import InferenceConfig, PolicyConfig
from hipolicy_jax.envs import external as envs_external
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.runs import calibrate as calib
from hipolicy_jax.runs import external

from metaworld_venv import PYTHON, ROOT, VENV, bridge, in_bridge, needs_venv  # noqa: F401 (tests/metaworld_venv.py)



@needs_venv
def test_bridge_record_keeps_every_decisions_stride_and_entropy():
    """Against a scripted server (one action a reply, strides 1, 3, 2, entropies 0.25, NaN, 1.5), each episode's
    summary lists one stride and one entropy per decision (null for NaN: strict JSON), consistent with its stride
    counts and mean entropy; the other fields keep their meaning."""
    out = in_bridge("""
import json
import numpy as np
import metaworld_bridge.evaluate as ev

REPLIES = [(1, 0.25), (3, float("nan")), (2, 1.5)]

class Server:
    def __init__(self):
        self.n = 0
    def get_server_metadata(self):
        return {"task": "metaworld:assembly", "action_dim": 4, "obs": {"state": {"shape": [2, 39]}},
                "action_kinds": ["delta", "delta", "delta", "absolute"], "strides": [1, 2, 3]}
    def infer(self, msg):
        stride, h = REPLIES[self.n % 3]
        self.n += 1
        return {"actions": np.zeros((1, 4), np.float32), "stride": stride, "entropy": np.float32(h)}

ev.check_server = lambda url: None
ev._openpi_client = lambda url, key: Server()
rec = ev.evaluate("assembly", "ws://fake", 2, 40, num_envs=2, max_steps=3, progress=False)
assert rec["seeds"] == [40, 41]
for ep in rec["per_episode"]:
    assert (ep["decisions"], ep["actions"], ep["steps"]) == (3, 3, 3), ep
    assert ep["decision_strides"] == [1, 3, 2] and ep["entropies"] == [0.25, None, 1.5], ep
    assert len(ep["decision_strides"]) == len(ep["entropies"]) == ep["decisions"]
    assert ep["strides"] == {1: 1, 2: 1, 3: 1} and ep["mean_entropy"] == 0.875
print(json.dumps(rec["per_episode"], allow_nan=False))
print("ok")
""")
    eps = json.loads(out.strip().splitlines()[-2])
    assert [ep["entropies"] for ep in eps] == [[0.25, None, 1.5]] * 2


# -- the calibration logic with the bridge faked at evaluate_run ------------------------------------------------------

E, D = 4, 5  # calibration episodes, decisions per episode
LADDER = ((90.0, 98.0), (50.0, 90.0), (10.0, 70.0), (2.0, 30.0))


def scripted_bridge(calls: list):
    """``evaluate_run`` of a scripted policy: decision j of episode i has entropy 5i + j (0 ... 19 over the E = 4
    episodes); guided by thresholds (−inf, t1, t2, +inf) it runs stride 1 below t1, 2 below t2, else 3 (the lowest
    entropies at the highest frequency, ``sampling.select_frequency``); an episode succeeds unless more than 30 % of
    its decisions ran at stride 3, and takes 40 control steps less 2 per decision above stride 1."""
    def evaluate_run(run_dir, *, episodes, first_seed, max_steps, step=None, inference=None, envs=8, timeout=None,
                     keep=False, fields=(), log=print):
        calls.append(dict(run_dir=run_dir, episodes=episodes, first_seed=first_seed, max_steps=max_steps, step=step,
                          inference=inference, envs=envs, keep=keep, fields=tuple(fields)))
        th = calibration.inner_to_full(inference.thresholds, 3, "thresholds")
        eps = []
        for i in range(episodes):
            h = [float(D * i + j) for j in range(D)]
            s = [1 + int(np.searchsorted(th[1:-1], x, side="right")) if inference.entropy_guided else 1 for x in h]
            eps.append({"seed": first_seed + i, "success": s.count(3) <= 0.3 * D,
                        "steps": 40 - 2 * sum(x > 1 for x in s), "decisions": D, "actions": D,
                        "strides": {str(k): s.count(k) for k in sorted(set(s))}, "mean_entropy": float(np.mean(h)),
                        "decision_strides": s, "entropies": h})
        return {"per_episode": eps, "successes": sum(e["success"] for e in eps), "episodes": episodes,
                "checkpoint_step": step, "reused": False}
    return evaluate_run


def fake_run(tmp_path, task="metaworld-target:assembly", seed=2):
    """What calibration reads of a ``store.Run``: run dir, task, training seed, the policy's config and step."""
    return types.SimpleNamespace(run_dir=str(tmp_path), ckpt_dir=str(tmp_path / "checkpoints"), task=task, seed=seed,
                                 action_dim=4, policy=types.SimpleNamespace(cfg=PolicyConfig(), step=12))


@pytest.fixture
def bridge_calls(monkeypatch):
    """The calls to the faked ``evaluate_run``; building an MJX evaluator fails the test."""
    calls = []
    monkeypatch.setattr(external, "evaluate_run", scripted_bridge(calls))

    def no_mjx(*a, **k):
        raise AssertionError("an external run built an MJX Evaluator")
    monkeypatch.setattr(calib, "make_evaluator", no_mjx)
    return calls


def test_external_closed_loop_entropies_come_from_stride1_calibration_episodes(tmp_path, bridge_calls):
    run, inf = fake_run(tmp_path), InferenceConfig(num_samples=4)
    h = calib.run_entropies(run, inf, "rollouts", episodes=E)
    np.testing.assert_array_equal(h, np.arange(E * D, dtype=float))  # every decision, episode by episode
    (call,) = bridge_calls
    first = external.CALIBRATION_SEED + 1000 * run.seed
    assert call["first_seed"] == first == 3_002_000 and call["episodes"] == E
    assert not call["inference"].entropy_guided and call["inference"].num_samples == 4
    assert call["keep"] and set(external.CALIBRATION_FIELDS) <= set(call["fields"])
    assert call["max_steps"] == envs_external.SUITES["metaworld-target"].eval_max_steps and call["step"] == 12
    # disjoint from every evaluation's initial states, for every training seed a campaign runs
    cal = {s for k in range(10) for s in external.calibration_seeds(k, 1000)}
    for base in (envs_external.EVAL_SEED, envs_external.PERIODIC_SEED):
        assert not cal & {base + 1000 * k + i for k in range(10) for i in range(1000)}
    assert min(cal) > 1000  # nor the demos' (seeds from 0)
    np.testing.assert_array_equal(external.closed_loop_entropies(run, inf, episodes=E, seed=run.seed), h)
    with pytest.raises(ValueError, match="episodes: 1 to 1000 calibration episodes per seed"):
        calib.run_entropies(run, inf, "rollouts", episodes=1001)
    with pytest.raises(ValueError, match="seed: calibration seeds start at CALIBRATION_SEED"):
        calib.run_entropies(run, inf, "rollouts", episodes=E, seed=-1)
    assert len(bridge_calls) == 2  # the errors came before any episode


def test_external_success_rule_by_hand(tmp_path, bridge_calls):
    """The scripted policy by hand (entropies 0 ... 19, baseline success 1.0 at stride 1): (90, 98) sends only
    h = 19 to stride 3 (episode 3: 1 of 5, succeeds): 1.0; (50, 90) sends 18, 19: 0.75; (10, 70) sends 14 ... 19
    (episode 2 has 1 of 5): 0.75; (2, 30) sends 6 ... 19: 0.25. Margin 0.25 keeps (10, 70), whose achieved mix is
    its intended 10/60/30; margin 0.05 keeps the most cautious."""
    run, inf = fake_run(tmp_path), InferenceConfig(num_samples=4)
    rec = calib.calibrate_run(run, inf, "rollouts", episodes=E, rule="success", margin=0.25, ladder=LADDER,
                              out=str(tmp_path / "c.json"))
    assert [c["success_rate"] for c in rec["candidates"]] == [1.0, 0.75, 0.75, 0.25]
    assert rec["baseline"] == {"success_rate": 1.0, "mean_steps": 40.0} and rec["chosen"] == 2
    chosen = rec["candidates"][2]
    assert chosen["achieved_mix"] == pytest.approx(chosen["intended_mix"]) == {"1": 0.1, "2": 0.6, "3": 0.3}
    assert chosen["mean_steps"] == 40 - 2 * 18 / E  # 18 of 20 decisions above stride 1
    assert rec["thresholds"] == chosen["thresholds"] and rec["percentiles"] == [10.0, 70.0]
    # one stride-1 pass, then each candidate on the same episodes with its thresholds at its percentiles
    assert len(bridge_calls) == 1 + len(LADDER)
    assert {c["first_seed"] for c in bridge_calls} == {3_002_000} and {c["episodes"] for c in bridge_calls} == {E}
    assert [c["inference"].entropy_guided for c in bridge_calls] == [False] + [True] * len(LADDER)
    for call, c, q in zip(bridge_calls[1:], rec["candidates"], LADDER):
        want = calibration.calibrate_thresholds(np.arange(E * D, dtype=float), 3, q)
        assert list(call["inference"].thresholds) == c["thresholds"] == [float(t) for t in want]
    saved = json.load(open(tmp_path / "c.json"))
    assert saved["rule"] == "success" and saved["source"] == "rollouts" and saved["first_seed"] == 3_002_000
    assert saved["episodes"] == E and saved["chosen"] == 2 and saved["num_windows"] == E * D
    assert saved["intended_mix"] == {"1": 0.1, "2": 0.6, "3": 0.3} and saved["margin"] == 0.25
    assert os.path.exists(tmp_path / "c.png")
    rec = calib.calibrate_run(run, inf, "rollouts", episodes=E, rule="success", margin=0.05, ladder=LADDER,
                              out=str(tmp_path / "c.json"))
    assert rec["chosen"] == 0 and rec["percentiles"] == [90.0, 98.0]
    n = len(bridge_calls)
    with pytest.raises(ValueError, match="margin: a success-rate difference in"):
        calib.success_constrained(run, inf, episodes=E, margin=2.0)
    with pytest.raises(ValueError, match="percentiles: need M-1=2 values"):
        calib.success_constrained(run, inf, episodes=E, ladder=[(50.0,)])
    assert len(bridge_calls) == n  # both refused before any episode


def test_external_percentile_rule_and_the_cli(tmp_path, bridge_calls, monkeypatch, capsys):
    """``--source rollouts`` thresholds an external run at the percentiles of its stride-1 entropies; ``--rule
    success`` prints the calibration episodes' initial states and every candidate."""
    from experiments import calibrate as cli

    run = fake_run(tmp_path)
    rec = calib.calibrate_run(run, InferenceConfig(num_samples=4, percentiles=(25.0, 75.0)), "rollouts",
                              episodes=E, out=str(tmp_path / "p.json"))
    assert rec["thresholds"][1:3] == pytest.approx([4.75, 14.25]) and rec["thresholds"][::3] == [-np.inf, np.inf]
    assert rec["intended_mix"] == {"1": 0.25, "2": 0.5, "3": 0.25} and rec["percentiles"] == [25.0, 75.0]
    monkeypatch.setattr(cli, "load_run", lambda path, step=None: run)
    monkeypatch.setattr(calibration, "percentile_ladder", lambda m: LADDER)
    cli.main(cli.CalibrateArgs(checkpoint=str(tmp_path), source="rollouts", rule="success", margin=0.25, episodes=E,
                               inference=InferenceConfig(num_samples=4), out=str(tmp_path / "s.json")))
    out = capsys.readouterr().out
    assert "stride 1 on 4 calibration episodes (initial states 3002000..3002003): success 1.00, 40.0 control" in out
    assert "[10.0, 70.0]: 0.75, 31.0 steps, {1: 0.10->0.10, 2: 0.60->0.60, 3: 0.30->0.30}  <- chosen" in out
    assert "20 entropies from rollouts" in out


# -- end to end: a tiny metaworld-target run, served, calibrated through its bridge -----------------------------------

MAX_STEPS = 24


@needs_venv
@pytest.mark.slow
def test_external_closed_loop_calibration_end_to_end(tmp_path, monkeypatch, capsys):
    """A tiny ``metaworld-target:assembly`` run (6 training steps on 2 demos) calibrated by the success rule through
    the policy server and the bridge: the entropies are every decision's of the stride-1 pass, each pass is kept in
    the run dir, and a repeated calibration runs no episode again; a kept pass without per-decision fields (from
    before the bridge recorded them) is run again."""
    from hipolicy_jax.config import ModelConfig, TrainConfig
    from hipolicy_jax.runs.store import load_run
    from hipolicy_jax.runs.train import RunConfig, main

    path = str(tmp_path / "target.zarr")
    r = subprocess.run([PYTHON, "-m", "metaworld_bridge.collect", "--task", "assembly", "--episodes", "2", "--out",
                        path, "--no-point-cloud", "--action-space", "target", "--no-progress"], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    cfg = RunConfig(task="metaworld-target:assembly", data=path, out=str(tmp_path / "run"), val_ratio=0.5,
                    policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2)),
                    train=TrainConfig(batch_size=16, num_steps=6, warmup_steps=2, log_every=6, ckpt_every=6),
                    inference=InferenceConfig(num_samples=4, num_steps=2, calib_windows=8),
                    eval=dataclasses.replace(RunConfig().eval, every=0), final_eval=False, progress=False)
    main(cfg)
    suite = envs_external.SUITES["metaworld-target"]
    monkeypatch.setitem(envs_external.SUITES, "metaworld-target", dataclasses.replace(suite, eval_max_steps=MAX_STEPS))
    run, logs = load_run(cfg.out_dir()), []
    # the held-out demos need no env either: training's own calibration windows
    trained = json.load(open(os.path.join(cfg.out_dir(), "calibration.json")))
    assert len(calib.run_entropies(run, cfg.inference, "demos")) == trained["num_windows"]
    ladder = ((50.0, 90.0), (10.0, 70.0))
    rec = calib.calibrate_run(run, cfg.inference, "rollouts", episodes=2, seed=0, rule="success", margin=0.5,
                              ladder=ladder, envs=2, out=str(tmp_path / "c.json"), log=logs.append)
    kept = sorted(os.listdir(os.path.join(cfg.out_dir(), "external_eval")))
    assert len(kept) == 1 + len(ladder)
    passes = [json.load(open(os.path.join(cfg.out_dir(), "external_eval", k))) for k in kept]
    base = next(p for p in passes if p["settings"]["thresholds"][1] == np.inf)  # stride 1: (-inf, inf, inf, inf)
    assert base["seeds"] == [3_000_000, 3_000_001] and base["max_steps"] == MAX_STEPS
    h = []
    for ep in base["per_episode"]:
        assert len(ep["entropies"]) == len(ep["decision_strides"]) == ep["decisions"] >= 1
        assert set(ep["decision_strides"]) == {1}  # stride 1: not guided
        h += ep["entropies"]
    np.testing.assert_allclose(rec["entropies"], h)
    assert rec["baseline"]["success_rate"] == np.mean([ep["success"] for ep in base["per_episode"]])
    for c in rec["candidates"]:
        assert sum(c["achieved_mix"].values()) == pytest.approx(1.0) and 1 <= c["mean_steps"] <= MAX_STEPS
    assert rec["chosen"] == calibration.choose_success_constrained(rec["candidates"],
                                                                   rec["baseline"]["success_rate"], 0.5)
    assert rec["first_seed"] == 3_000_000 and rec["episodes"] == 2
    # again: every pass is the kept one
    logs.clear()
    again = calib.calibrate_run(run, cfg.inference, "rollouts", episodes=2, seed=0, rule="success", margin=0.5,
                                ladder=ladder, envs=2, out=str(tmp_path / "c2.json"), log=logs.append)
    assert len(logs) == 1 + len(ladder) and all("kept in" in m for m in logs)
    assert again["candidates"] == rec["candidates"] and again["chosen"] == rec["chosen"]
    # a kept stride-1 pass from before the bridge kept per-decision fields is made again
    name = kept[passes.index(base)]
    stale = {**base, "per_episode": [{k: v for k, v in ep.items() if k not in external.CALIBRATION_FIELDS}
                                     for ep in base["per_episode"]]}
    with open(os.path.join(cfg.out_dir(), "external_eval", name), "w") as f:
        json.dump(stale, f)
    res = external.calibration_rollout(run, cfg.inference, episodes=2, seed=0, envs=2, log=logs.append)
    assert res["record"]["reused"] is False and len(res["entropies"]) == sum(res["decisions"])
    np.testing.assert_allclose(res["entropies"], h, rtol=1e-5)


def test_calibration_episodes_run_at_the_given_step_limit(tmp_path, monkeypatch):
    """``calibrate_run(max_steps=...)`` reaches the bridge's episodes (a campaign column evaluating at Meta-World's
    500 steps calibrates at 500, not at the suite's 200); None keeps the suite's limit."""
    limits = []

    def fake_evaluate_run(run_dir, *, episodes, first_seed, max_steps, **kw):
        limits.append(max_steps)
        eps = [{"seed": first_seed + i, "success": True, "steps": 10, "decisions": 2, "actions": 16,
                "entropies": [0.1 * i, 0.2], "decision_strides": [1, 1]} for i in range(episodes)]
        return {"per_episode": eps}

    monkeypatch.setattr(external, "evaluate_run", fake_evaluate_run)
    run = fake_run(tmp_path)
    record = calib.calibrate_run(run, InferenceConfig(num_samples=4), "rollouts", episodes=3, seed=0, max_steps=500,
                                 out=str(tmp_path / "c.json"))
    assert limits == [500] and record["max_steps"] == 500
    calib.calibrate_run(run, InferenceConfig(num_samples=4), "rollouts", episodes=3, seed=0,
                        out=str(tmp_path / "d.json"))
    assert limits[-1] == envs_external.SUITES["metaworld-target"].eval_max_steps
