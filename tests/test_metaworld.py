"""Meta-World bridge: expert demos collected in the Meta-World venv (``metaworld_bridge.collect``, subprocess) land in
the project's zarr layout with state and point clouds, and the project trains on them as ``metaworld:<task>``.

The bridge needs its own venv (``bash scripts/setup_metaworld.sh`` → ``.venv-metaworld``; ``METAWORLD_VENV``
chooses another); without it the tests that run the bridge are skipped.
"""

import dataclasses
import json
import os
import resource
import subprocess
import sys

import numpy as np
import pytest

from hipolicy_jax import envs
from hipolicy_jax.config import EncoderConfig, InferenceConfig, ModelConfig, PolicyConfig, TrainConfig
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.envs import external
from hipolicy_jax.runs.store import read_inference
from hipolicy_jax.runs.train import RunConfig, main

from metaworld_venv import PYTHON, ROOT, VENV, bridge, in_bridge, needs_venv  # noqa: F401 (tests/metaworld_venv.py)

TASK, EPISODES, POINTS = "assembly", 2, 64


@pytest.fixture(scope="module")
def demos(tmp_path_factory):
    """Two assembly demos (64-point clouds from a 32 x 32 ray grid), collected twice from the same seeds."""
    out = tmp_path_factory.mktemp("metaworld")
    paths = [str(out / "a.zarr"), str(out / "b.zarr")]
    for path in paths:
        r = bridge("metaworld_bridge.collect", "--task", TASK, "--episodes", str(EPISODES), "--out", path,
                   "--num-points", str(POINTS), "--camera-size", "32", "--no-progress")
        assert r.returncode == 0, r.stderr[-2000:]
    return paths, r.stdout


@needs_venv
def test_bridge_imports_no_jax():
    code = ("import sys, metaworld_bridge.collect, metaworld_bridge.check_experts, metaworld_bridge.evaluate; "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('jax', 'jaxlib', 'flax', 'hipolicy_jax')); "
            "assert not bad, bad")
    r = subprocess.run([PYTHON, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]


@needs_venv
def test_collect_writes_the_project_layout(demos):
    import zarr

    (path, again), stdout = demos
    assert f"{TASK}: {EPISODES} successful of" in stdout and "mean steps" in stdout
    buf = ReplayBuffer.load(path)  # the project's loader validates lengths, ranks, finiteness, episode_ends
    assert buf.num_episodes == EPISODES and sorted(buf.keys) == ["action", "point_cloud", "state"]
    t = buf.num_frames
    assert buf.data["state"].shape == (t, 39) and buf.data["action"].shape == (t, 4)
    assert buf.data["point_cloud"].shape == (t, POINTS, 3)
    assert all(v.dtype == np.float32 for v in buf.data.values()) and buf.episode_ends.dtype == np.int64
    root = zarr.open_group(path, mode="r")
    assert root["meta/episode_ends"].dtype == np.int64
    attrs = dict(root.attrs)
    assert attrs["task"] == TASK and attrs["seeds"] == [0, 1] and attrs["steps"] == buf.episode_lengths().tolist()
    for key, arr in buf.data.items():
        assert np.isfinite(arr).all(), key
    assert np.abs(buf.data["action"]).max() <= 1.0
    # every point lies in DP3's crop box (its own frame, floor in the world) and on or above the table
    crop = attrs["crop"]
    pts = buf.data["point_cloud"].reshape(-1, 3).astype(np.float64)
    local = (pts - np.asarray(crop["frame_origin"])) @ np.asarray(crop["frame_rotation"]).T
    assert np.all(local[:, :2] > np.asarray(crop["low"][:2]) - 1e-6)
    assert np.all(local[:, :2] < np.asarray(crop["high"][:2]) + 1e-6)
    assert np.all(pts[:, 2] > crop["floor_z"] - 1e-6) and np.all(pts[:, 2] < 1.5)
    # the clouds see the hand: some point lies within 10 cm of the hand position (state[:3]) in most frames
    near = np.linalg.norm(buf.data["point_cloud"] - buf.data["state"][:, None, :3], axis=-1).min(axis=1) < 0.1
    assert near.mean() > 0.9
    # seeded initial states: the same seeds give the same demos, to the bit
    other = ReplayBuffer.load(again)
    for key in buf.keys:
        np.testing.assert_array_equal(buf.data[key], other.data[key])
    np.testing.assert_array_equal(buf.episode_ends, other.episode_ends)


@needs_venv
def test_action_spaces_and_the_strided_expert(tmp_path):
    """The bridge's two action spaces give the same expert episode; its absolute targets replayed open loop succeed;
    a snapshot restores the simulation exactly; the expert as a chunking policy at stride 1 is the expert's own
    episode; ``check_experts --strides`` records every (task, space, stride)."""
    code = """
import numpy as np
from metaworld_bridge.env import MetaWorldTask
delta, target = MetaWorldTask("assembly", 200), MetaWorldTask("assembly", 200, action_space="target")
a, b = delta.run_expert(0), target.run_expert(0)
assert a.success and b.success and a.steps == b.steps
np.testing.assert_array_equal(a.frames["state"], b.frames["state"])
np.testing.assert_array_equal(a.frames["action"][:, 3], b.frames["action"][:, 3])  # the gripper: the same
assert np.abs(b.frames["action"][:, :3] - b.frames["state"][:, :3]).max() < 0.1  # world xyz, by the hand
target.reset(0)
for act in b.frames["action"]:
    obs, success, truncated = target.step(act)
assert success
delta.reset(0)
snap = delta.snapshot()
first = [delta.step(a.frames["action"][i])[0] for i in range(10)]
delta.restore(snap)
again = [delta.step(a.frames["action"][i])[0] for i in range(10)]
np.testing.assert_array_equal(np.stack(first), np.stack(again))
c = delta.run_strided_expert(0, 1)
assert c.success and c.steps == a.steps
np.testing.assert_array_equal(c.frames["action"], a.frames["action"])
try:
    delta.run_strided_expert(0, 0)
except ValueError as e:
    assert "stride" in str(e)
else:
    raise AssertionError("stride 0 accepted")
try:
    MetaWorldTask("assembly", action_space="joint")
except ValueError as e:
    assert "action_space" in str(e) and "target" in str(e)
else:
    raise AssertionError("an unknown action space accepted")
print("ok")
"""
    r = subprocess.run([PYTHON, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-3000:]
    out = tmp_path / "strided.json"
    r = bridge("metaworld_bridge.check_experts", "--tasks", "assembly", "--strides", "1", "3", "--action-spaces",
               "delta", "target", "--seeds", "2", "--max-steps", "200", "--out", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    report = json.loads(out.read_text())
    task = report["tasks"]["assembly"]
    assert sorted(task) == ["delta", "target"] and all(sorted(v) == ["1", "3"] for v in task.values())
    assert task["delta"]["1"]["successes"] == task["target"]["1"]["successes"] == 2
    assert report["chunk_len"] == 8 and report["seeds"] == [0, 1]


@needs_venv
def test_target_moves_are_bounded_as_configured():
    """A target 3 cm along x and 1 cm along y, one control step: Meta-World's own bound (1 cm, each axis clipped)
    bends the move to (1, 1) cm; ``direction`` keeps it pointing at the target (1, 1/3); a limit of s cm gives s
    steps of headroom ((2, 2/3) at 2; reached at 3 or 5); the env's own action_scale is restored after each step;
    displacement actions refuse the options."""
    code = """
import numpy as np
from metaworld_bridge.env import MetaWorldTask
want = {(1.0, "axis"): [1, 1, 0], (1.0, "direction"): [1, 1 / 3, 0], (2.0, "direction"): [2, 2 / 3, 0],
        (3.0, "axis"): [3, 1, 0], (5.0, "direction"): [3, 1, 0]}
for (limit, clip), cm in want.items():
    env = MetaWorldTask("assembly", 200, action_space="target", move_limit=limit, move_clip=clip)
    env.reset(0)
    start = env.data.mocap_pos[0].copy()
    env.step(np.concatenate([start + [0.03, 0.01, 0.0], [0.0]]))
    np.testing.assert_allclose((env.data.mocap_pos[0] - start) * 100, cm, atol=1e-9)
    assert env.env.action_scale == 0.01
for kwargs, msg in (({"move_limit": 2.0}, "move_limit / move_clip: bound the moves of absolute targets"),
                    ({"action_space": "target", "move_clip": "sphere"}, "move_clip: one of axis, direction"),
                    ({"action_space": "target", "move_limit": 0.0}, "move_limit: must be > 0")):
    try:
        MetaWorldTask("assembly", 200, **kwargs)
    except ValueError as e:
        assert msg in str(e), str(e)
    else:
        raise AssertionError(kwargs)
print("ok")
"""
    r = subprocess.run([PYTHON, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-3000:]


def _pointcloud_config(path: str, out: str) -> RunConfig:
    return RunConfig(task=f"metaworld:{TASK}", data=path, out=out, val_ratio=0.5,
                     policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2),
                                         encoder=EncoderConfig(obs_type="pointcloud", num_points=POINTS)),
                     train=TrainConfig(batch_size=16, num_steps=12, warmup_steps=2, log_every=6, ckpt_every=12),
                     inference=InferenceConfig(num_samples=4, num_steps=2, calib_windows=8),
                     eval=dataclasses.replace(RunConfig().eval, every=0), final_eval=False, progress=False)


@pytest.fixture(scope="module")
def pointcloud_run(demos, tmp_path_factory):
    """A tiny point-cloud HiPolicy trained for 12 steps on the two demos: (run dir, config, summary)."""
    (path, _), _ = demos
    cfg = _pointcloud_config(path, str(tmp_path_factory.mktemp("pc") / "run"))
    return cfg.out_dir(), cfg, main(cfg)


@needs_venv
def test_train_pointcloud_policy_on_metaworld_demos(pointcloud_run):
    run_dir, cfg, summary = pointcloud_run
    assert cfg.policy.encoder.state_dims == 4  # proprioception: hand xyz + gripper
    assert summary["steps"] == 12 and summary["eval"] is None and np.isfinite(summary["final_loss"])
    assert summary["task"] == "metaworld:assembly" and summary["demos"]["episodes"] == EPISODES
    th = summary["thresholds"]  # calibrated on the held-out demos without an env
    assert len(th) == 4 and th[0] == -np.inf and th[-1] == np.inf and th[1] <= th[2]
    # a state policy on the same buffer: the whole 39-D state
    info = main(dataclasses.replace(cfg, policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2)),
                                    dry_run=True))
    assert info["batch"]["obs.state"][-1] == 39 and info["batch"]["action"][-1] == 4


@pytest.fixture(scope="module")
def served(pointcloud_run):
    """The trained point-cloud policy behind the project's server on a free port: (url, server)."""
    from hipolicy_jax.runs.serve import run_backend
    from hipolicy_jax.deploy.server import PolicyServer, ServerConfig

    srv = PolicyServer(run_backend(pointcloud_run[0]), ServerConfig(port=0, max_batch=2),
                       log=lambda msg: None)
    srv.start_in_thread()
    yield f"ws://127.0.0.1:{srv.port}", srv
    srv.stop()


def evaluate_remote(url: str, tmp_path, *args: str) -> tuple[subprocess.CompletedProcess, dict | None]:
    out = tmp_path / f"eval{len(list(tmp_path.iterdir()))}.json"
    r = bridge("metaworld_bridge.evaluate", "--task", TASK, "--url", url, "--camera-size", "32", "--max-steps",
               str(MAX_STEPS), "--no-progress", "--out", str(out), *args, timeout=300)
    return r, (json.loads(out.read_text()) if r.returncode == 0 else None)


MAX_STEPS = 24


@needs_venv
def test_metaworld_episodes_through_the_policy_server(served, tmp_path):
    """The env side (Meta-World venv, openpi's client) runs episodes against the served policy: every episode is a
    function of (policy, initial-state seed) alone, the same whether 2 envs are batched together or run one by one
    (up to the float rounding of a batched call: entropies agree to 1e-5)."""
    url, srv = served
    r, rec = evaluate_remote(url, tmp_path, "--episodes", "2", "--envs", "2", "--first-seed", "500")
    assert r.returncode == 0, r.stderr[-3000:]
    assert f"{TASK}: " in r.stdout and "success" in r.stdout
    assert rec["episodes"] == 2 and rec["seeds"] == [500, 501] and rec["envs"] == 2
    assert rec["policy"]["task"] == f"metaworld:{TASK}" and rec["policy"]["strides"] == srv.metadata["strides"]
    for ep in rec["per_episode"]:
        assert 1 <= ep["steps"] <= MAX_STEPS and ep["decisions"] >= 1
        assert ep["success"] or ep["steps"] == MAX_STEPS  # an episode ends at success or the step limit
        assert sum(ep["strides"].values()) == ep["decisions"]
        assert ep["actions"] == ep["control_steps"] == ep["steps"] and ep["unreached"] == 0  # rate: a step an action
        assert set(map(int, ep["strides"])) <= set(rec["policy"]["strides"])
    assert rec["openpi_client"] == "0.1.2" and rec["seconds"]["camera"] > 0
    assert rec["semantics"] == "rate"
    assert rec["action_kinds"] == list(srv.metadata.get("action_kinds", ["absolute"] * 4))  # undeclared: absolute
    assert rec["mean_control_steps"] == rec["mean_steps"] == rec["mean_actions"] >= rec["mean_decisions"]
    # one env at a time, on the same seeds: the same episodes, decision for decision
    r1, one = evaluate_remote(url, tmp_path, "--episodes", "2", "--envs", "1", "--first-seed", "500")
    assert r1.returncode == 0, r1.stderr[-3000:]
    drop = lambda eps: [{k: v for k, v in ep.items() if k not in ("mean_entropy", "entropies")}  # noqa: E731
                        for ep in eps]
    assert drop(one["per_episode"]) == drop(rec["per_episode"])
    np.testing.assert_allclose([ep["mean_entropy"] for ep in one["per_episode"]],
                               [ep["mean_entropy"] for ep in rec["per_episode"]], rtol=1e-5)
    for a, b in zip(one["per_episode"], rec["per_episode"]):  # every decision's entropy and stride (issue 58)
        assert len(a["entropies"]) == len(a["decision_strides"]) == a["decisions"]
        assert {int(s): a["decision_strides"].count(int(s)) for s in a["strides"]} == \
            {int(s): n for s, n in a["strides"].items()}
        np.testing.assert_allclose(a["entropies"], b["entropies"], rtol=1e-5)


@needs_venv
def test_metaworld_evaluation_errors_name_the_fix(served, tmp_path):
    url, _ = served
    r = bridge("metaworld_bridge.evaluate", "--task", "push", "--url", url, "--episodes", "1", "--no-progress")
    assert r.returncode != 0 and "trained on 'metaworld:assembly', not 'metaworld:push'" in r.stderr
    r = bridge("metaworld_bridge.evaluate", "--task", TASK, "--url", url, "--episodes", "1", "--no-progress",
               "--action-space", "target")
    assert r.returncode != 0 and "not 'metaworld-target:assembly'" in r.stderr
    assert "its actions are the 'delta' space: pass --action-space delta" in r.stderr
    r = bridge("metaworld_bridge.evaluate", "--task", TASK, "--url", "ws://127.0.0.1:9", "--episodes", "1",
               "--no-progress")
    assert r.returncode != 0 and "no policy server answers at ws://127.0.0.1:9" in r.stderr
    assert "python -m experiments.serve --checkpoint" in r.stderr


@needs_venv
def test_absolute_target_suite_end_to_end(demos, tmp_path):
    """``metaworld-target:<task>``: the bridge records absolute hand targets, training refuses a buffer of the other
    action space (naming the task and the command that fit), and the campaign's evaluation serves the policy to a
    bridge that executes targets."""
    import zarr

    from hipolicy_jax.runs.external import evaluate_run

    path = str(tmp_path / "target.zarr")
    r = bridge("metaworld_bridge.collect", "--task", TASK, "--episodes", "2", "--out", path, "--no-point-cloud",
               "--action-space", "target", "--no-progress")
    assert r.returncode == 0, r.stderr[-2000:]
    attrs = dict(zarr.open_group(path, mode="r").attrs)
    assert attrs["action_space"] == "target" and "absolute" in attrs["action"]
    buf, delta = ReplayBuffer.load(path), ReplayBuffer.load(demos[0][0])
    np.testing.assert_array_equal(buf.data["state"], delta.data["state"])  # the same expert episodes
    assert np.abs(buf.data["action"][:, :3] - buf.data["state"][:, :3]).max() < 0.1  # targets by the hand
    ok = dict(eval=dataclasses.replace(RunConfig().eval, every=0), final_eval=False, progress=False)
    with pytest.raises(ValueError, match=r"holds actions in the 'target' space.*pass --task metaworld-target:assembly"):
        main(RunConfig(task=f"metaworld:{TASK}", data=path, dry_run=True, **ok))
    with pytest.raises(ValueError, match=r"'delta' space.*--task metaworld:assembly.*--action-space target"):
        main(RunConfig(task=f"metaworld-target:{TASK}", data=demos[0][0], dry_run=True, **ok))
    cfg = RunConfig(task=f"metaworld-target:{TASK}", data=path, out=str(tmp_path / "run"), val_ratio=0.5,
                    policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2)),
                    train=TrainConfig(batch_size=16, num_steps=6, warmup_steps=2, log_every=6, ckpt_every=6),
                    inference=InferenceConfig(num_samples=4, num_steps=2, calib_windows=8), **ok)
    assert main(cfg)["task"] == "metaworld-target:assembly"
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    rec = evaluate_run(cfg.out_dir(), episodes=2, first_seed=700, max_steps=MAX_STEPS, envs=2, log=lambda m: None)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    # its CPU time counts the bridge (a child process) besides this process's serving threads
    bridge_s = after.ru_utime + after.ru_stime - children.ru_utime - children.ru_stime
    assert 0 < bridge_s <= rec["cpu_s"]
    assert rec["action_space"] == "target" and rec["policy"]["task"] == "metaworld-target:assembly"
    assert rec["seeds"] == [700, 701] and all(1 <= ep["steps"] <= MAX_STEPS for ep in rec["per_episode"])


@needs_venv
def test_external_task_errors_name_the_fix(demos, tmp_path):
    (path, _), _ = demos
    ok = dict(eval=dataclasses.replace(RunConfig().eval, every=0), final_eval=False, dry_run=True, progress=False)
    with pytest.raises(ValueError, match="holds demos of metaworld:assembly, not metaworld:push"):
        main(RunConfig(task="metaworld:push", data=path, **ok))
    cfg = RunConfig(task="metaworld:assembly", data=path, **ok)
    with pytest.raises(ValueError, match=r"point_cloud has frames of shape \(64, 3\).*expects \(512, 3\)"):
        main(dataclasses.replace(cfg, policy=PolicyConfig(encoder=EncoderConfig(obs_type="pointcloud"))))


def test_external_task_config(tmp_path):
    cfg = RunConfig(task="metaworld:assembly")  # no MJX env: training evaluates nothing, by default
    assert cfg.eval.every == 0 and not cfg.final_eval
    assert dataclasses.replace(cfg, episodes=7).eval.every == 0  # stable under replace
    with pytest.raises(ValueError, match="eval.every: metaworld:assembly has no MJX env.*experiments.evaluate"):
        RunConfig(task="metaworld:assembly", eval=dataclasses.replace(RunConfig().eval, every=500))
    with pytest.raises(ValueError, match="or an external task"):
        RunConfig(task="assembly")
    with pytest.raises(ValueError, match="needs a task name"):
        RunConfig(task="metaworld:")
    with pytest.raises(ValueError, match="unknown external suite"):
        RunConfig(task="robosuite:lift")
    with pytest.raises(ValueError, match="no MJX env"):
        envs.make("metaworld:assembly")
    cfg = RunConfig(task="metaworld:assembly", episodes=7, eval=dataclasses.replace(RunConfig().eval, every=0),
                    final_eval=False, dry_run=True, out=str(tmp_path / "run"))
    assert cfg.data_path() == os.path.join("data", "metaworld_assembly_7.zarr")
    assert dataclasses.replace(cfg, out="").out_dir() == os.path.join("runs", "metaworld_assembly_state_seed0")
    spec = external.make("metaworld:assembly", EncoderConfig(obs_type="pointcloud", num_points=128))
    assert spec.action_dim == 4 and spec.obs_shapes == {"state": (39,), "point_cloud": (128, 3)}
    # a missing buffer is never collected here: the error names the bridge's commands
    with pytest.raises(FileNotFoundError, match=r"scripts/setup_metaworld.sh && .*metaworld_bridge.collect "
                                                r"--task assembly --episodes 7"):
        main(dataclasses.replace(cfg, data=str(tmp_path / "missing.zarr")))
    # an MJX task's buffer does not fit: state is 39-D here
    mjx = ReplayBuffer.from_episodes([{"state": np.zeros((30, 7), np.float32), "action": np.zeros((30, 4), np.float32)}])
    mjx.save(str(tmp_path / "mjx.zarr"))
    with pytest.raises(ValueError, match=r"data/state has frames of shape \(7,\), the metaworld:assembly task "
                                         r"expects \(39,\)"):
        main(dataclasses.replace(cfg, data=str(tmp_path / "mjx.zarr")))


def test_farthest_point_sampling_is_deterministic_and_spread():
    sys.path.insert(0, ROOT)
    from metaworld_bridge.pointcloud import farthest_point_indices

    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.normal(0, 0.01, (500, 3)), [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]])
    idx = farthest_point_indices(pts, 8)
    assert idx[0] == 0 and {500, 501} <= set(idx.tolist()) and len(set(idx.tolist())) == 8
    np.testing.assert_array_equal(idx, farthest_point_indices(pts, 8))
    np.testing.assert_array_equal(farthest_point_indices(pts[:3], 7), [0, 1, 2, 0, 1, 2, 0])  # few points: cyclic
    assert farthest_point_indices(pts[:0], 4).size == 0


def test_metaworld_budget_layout():
    """The metaworld budget's runs: task dirs without ':', one 11-demo buffer for every column, 10 evenly spaced
    checkpoints kept and room for two more (a pilot's explicit interval keeps all of its own), 512 points for DP3,
    the 200-step limit."""
    from hipolicy_jax.campaigns.budgets import DP, METAWORLD_PILOT, run_config

    cfg = run_config("metaworld", "metaworld:hammer", "state", DP, 2, run_changes={"train.num_steps": 3000})
    assert cfg.out_dir() == os.path.join("runs/paper", "metaworld", "metaworld_hammer", "state", "dp_t3000", "seed2")
    assert cfg.data_path() == os.path.join("data", "metaworld_hammer_11.zarr") and cfg.episodes == 11
    assert (cfg.train.ckpt_every, cfg.train.ckpt_keep, cfg.train.seed) == (300, 12, 2) and not cfg.final_eval
    pc = run_config("metaworld", "metaworld:hammer", "pointcloud", (), 0)
    assert pc.data_path() == cfg.data_path() and pc.policy.encoder.num_points == 512
    assert pc.policy.encoder.state_dims == 4 and pc.policy.diffusion.prediction_type == "sample"
    pilot = run_config("metaworld", "metaworld:hammer", "state", DP, 0, run_changes=METAWORLD_PILOT)
    assert (pilot.train.num_steps, pilot.train.ckpt_every, pilot.train.ckpt_keep) == (8000, 1000, 10)
    assert envs.episode_limit("metaworld:hammer") == 200


def test_external_summary_and_dp3_metric():
    from hipolicy_jax.campaigns.campaign import dp3_metric, external_summary
    from hipolicy_jax.campaigns.metaworld import choose_training_steps

    eps = [{"seed": 1, "success": True, "steps": 60, "decisions": 5, "strides": {"1": 2, "3": 3}, "mean_entropy": 0.5},
           {"seed": 2, "success": False, "steps": 200, "decisions": 25, "strides": {"1": 25}, "mean_entropy": None},
           {"seed": 3, "success": True, "steps": 100, "decisions": 10, "strides": {"2": 10}, "mean_entropy": 1.5}]
    s = external_summary({"per_episode": eps})
    assert s["success_rate"] == pytest.approx(2 / 3) and s["mean_steps_success"] == 80.0
    assert s["mean_steps"] == 120.0 and s["mean_decisions"] == pytest.approx(40 / 3)
    assert s["mean_actions_per_decision"] == pytest.approx(360 / 40)
    assert (s["stride1_frac"], s["stride2_frac"], s["stride3_frac"]) == (27 / 40, 10 / 40, 3 / 40)
    assert s["mean_entropy"] == 1.0  # episodes without an entropy (one stride) are left out
    assert np.isnan(external_summary({"per_episode": eps[1:2]})["mean_steps_success"])
    # DP3's metric: the mean of the 5 best periodic rates (all of them when fewer)
    assert dp3_metric([0.1, 0.9, 0.5, 0.3, 0.7, 0.2, 0.6]) == pytest.approx((0.9 + 0.7 + 0.6 + 0.5 + 0.3) / 5)
    assert dp3_metric([0.4, 0.2]) == pytest.approx(0.3) and dp3_metric([]) is None
    # the pilot's rule: the fewest steps within 5 points of the best mean over tasks
    assert choose_training_steps({1000: [0.2, 0.4], 2000: [0.5, 0.6], 4000: [0.6, 0.6], 8000: [0.55, 0.6]}) == 2000
    assert choose_training_steps({1000: [0.2, 0.4], 2000: [0.5, 0.5], 4000: [0.6, 0.62]}) == 4000
    assert choose_training_steps({1000: [0.0, 0.0], 2000: [0.0, 0.0]}) == 1000


@needs_venv
@pytest.mark.slow
def test_metaworld_campaign_end_to_end(tmp_path, monkeypatch, capsys):
    """The Meta-World campaign stage (smoke budget): the pilot collects demos through the bridge, trains DP and
    evaluates its final network and its kept checkpoint through the served policy; the main table trains and
    evaluates all four columns (state and point clouds) with periodic evaluations for DP3's metric, one record per
    network; both tables rebuild from the records alone."""
    from experiments.metaworld import main as metaworld, parse_args

    flags = ["--budget", "smoke", "--tasks", "assembly", "--runs", str(tmp_path / "runs"), "--data",
             str(tmp_path / "data"), "--records", str(tmp_path / "rec"), "--results", str(tmp_path / "res"),
             "--episodes", "2", "--no-progress"]
    # a budget far above what a smoke pilot costs on any machine: every task carries both column pairs
    big = ["--budget-hours", "100000"]
    md = metaworld(parse_args(["pilot", *flags, *big, "--pointcloud-train-s-per-step", "3", "--camera-ms-per-frame",
                               "25"]))
    rec = json.loads((tmp_path / "rec" / "smoke" / "metaworld_assembly" / "state" / "dp_ckptevery6" /
                      "seed0.json").read_text())
    (ev,) = rec["evaluations"].values()
    assert ev["first_seed"] == 1_000_000 and ev["max_steps"] == 200 and len(ev["success"]) == 2
    assert ev["network"]["params_sha256"] == rec["network"]["params_sha256"]
    rows = ev["periodic"]["checkpoints"]
    assert [r["step"] for r in rows] == [6] and rows[0]["first_seed"] == 1_000_000  # the pilot: main states
    assert rows[0]["params_sha256"] != rec["network"]["params_sha256"]  # another network, kept apart
    assert ev["dp3_metric"] == rows[0]["success_rate"]
    assert ev["eval_s"] == pytest.approx(ev["main_eval_s"] + rows[0]["eval_s"])
    text = open(md).read()
    assert "results/metaworld/PROTOCOL.md" in text and "| metaworld:assembly |" in text
    assert "python -m experiments.metaworld pilot" in text
    choice = json.loads((tmp_path / "res" / "pilot_choice.json").read_text())
    assert choice["T"] in (6, 12) and choice["costs"][0]["train_cpu_s_per_step"] > 0
    rules = choice["budget_rules"]
    assert rules["state_tasks"] == 16 and rules["pointcloud_tasks"] == 16 and rules["steps"] == choice["T"]
    assert "state columns on the first **16** tasks" in text
    again = metaworld(parse_args(["pilot", *flags, *big, "--pointcloud-train-s-per-step", "3", "--camera-ms-per-frame",
                                  "25", "--from-records"]))
    assert open(again).read().split("| Task")[1] == text.split("| Task")[1]

    # the main table: its own runs (the pilot's are not table runs), the demos reused
    main_flags = [*flags, "--seeds", "0", "--pointcloud-tasks", "assembly", "--published",
                  str(tmp_path / "published.json"), "--readme", str(tmp_path / "README.md")]
    from hipolicy_jax.campaigns.metaworld import readme_markers

    begin, end = readme_markers(str(tmp_path / "res"))
    (tmp_path / "README.md").write_text(f"{begin}\n{end}\n")
    (tmp_path / "published.json").write_text(json.dumps({"tasks": {"assembly": {"dp_image": [15, 1], "dp3": [99, 1]}}}))
    md = metaworld(parse_args(["main", *main_flags]))
    text = open(md).read()
    for column in ("DP", "DP+HiPolicy", "DP3", "DP3+HiPolicy"):
        assert f" {column} |" in text.split("\n## ")[0]
    assert "15 ± 1" in text and "99 ± 1" in text  # published, beside ours
    table = json.loads((tmp_path / "res" / "main.json").read_text())["records"]
    assert sorted(r["column"] for r in table) == ["DP", "DP+HiPolicy", "DP3", "DP3+HiPolicy"]
    metric = {r["column"]: r["dp3_metric"] for r in table}  # one seed: the gaps are our value − the published mean
    row = text.split("## DP3's metric")[1].split("| metaworld:assembly |")[1].split("\n")[0]
    assert [c.strip() for c in row.strip().strip("|").split(" | ")[-2:]] == [f"{100 * metric['DP'] - 15:+.1f}",
                                                                              f"{100 * metric['DP3'] - 99:+.1f}"]
    for r in table:
        assert len(r["success"]) == 2 and r["dp3_metric"] is not None
        assert [c["step"] for c in r["periodic"]["checkpoints"]] == [6, 12]
        assert all(c["first_seed"] == 2_000_000 for c in r["periodic"]["checkpoints"])
    hip = json.loads((tmp_path / "rec" / "smoke" / "metaworld_assembly" / "pointcloud" / "hipolicy" /
                      "seed0.json").read_text())
    assert hip["policy"]["encoder"]["obs_type"] == "pointcloud" and hip["policy"]["chunk"]["strides"] != [1]
    assert metaworld(parse_args(["main", *main_flags, "--from-records"])) == md
    assert open(md).read().split("| Task")[1:] == text.split("| Task")[1:]
    section = (tmp_path / "README.md").read_text()  # the README's copy of the table, under the count of runs
    assert section.startswith(f"{begin}\n\n4 of 4 runs recorded.\n\n#### Meta-World: success rate (%)")
    assert text.split("| Task")[1].split("\n## ")[0] in section and "\n##### DP3's metric" in section

    # every evaluation was kept in its run dir as it finished: with the record lost (a campaign stopped before
    # writing it), the campaign makes it again from what was kept, without running an episode
    from hipolicy_jax.runs import external

    run_dir = tmp_path / "runs" / "smoke" / "metaworld_assembly" / "pointcloud" / "hipolicy" / "seed0"
    assert len(list((run_dir / "external_eval").glob("step*.json"))) == 3  # the final network, 2 periodic
    lost = tmp_path / "rec" / "smoke" / "metaworld_assembly" / "pointcloud" / "hipolicy" / "seed0.json"
    lost.unlink()
    monkeypatch.setattr(external, "_run", lambda *a, **k: pytest.fail(f"ran the bridge again: {a}"))
    metaworld(parse_args(["main", *main_flags]))
    again = json.loads(lost.read_text())
    (old,), (new,) = hip["evaluations"].values(), again["evaluations"].values()
    for k in ("success", "steps", "decisions", "first_seed", "eval_s", "dp3_metric"):
        assert new[k] == old[k], k
    assert new["periodic"]["checkpoints"] == old["periodic"]["checkpoints"]

    # experiments.evaluate on the same run: its guided pass is the campaign's evaluation of seed 0 (kept, reused);
    # the pass without entropy guidance runs the bridge and decides at stride 1 only
    monkeypatch.undo()
    from experiments.evaluate import EvaluateArgs, main as evaluate

    inference = read_inference(str(run_dir))
    report = evaluate(EvaluateArgs(checkpoint=str(run_dir), episodes=2, inference=inference, out=str(tmp_path / "ev")))
    assert report["seeds"] == [1_000_000, 1_000_001] and report["params_sha256"] == hip["network"]["params_sha256"]
    assert report["with_eg"]["success"] == old["success"] and report["with_eg"]["steps"] == old["steps"]
    assert report["without_eg"]["stride1_frac"] == 1.0 and len(report["without_eg"]["steps"]) == 2
    assert report["reused"] == {"with_eg": True, "without_eg": False}
    written = json.loads((tmp_path / "ev" / "eval.json").read_text())["without_eg"]
    assert [written[k] for k in ("success", "steps", "decisions")] == [report["without_eg"][k] for k in
                                                                      ("success", "steps", "decisions")]
    assert len(list((run_dir / "external_eval").glob("step*.json"))) == 4  # the unguided pass, kept too

    # the post-hoc diagnosis: the demos' segment coverage, and the state DP+HiPolicy network at stride 1 (its
    # guided pass the campaign's, reused; the unguided one run through the bridge), beside DP, from its own files
    from hipolicy_jax.campaigns.metaworld import STRIDE1

    diag = [str(tmp_path / "diag") if f == str(tmp_path / "res") else f for f in flags] + [
        "--seeds", "0", "--experts", str(tmp_path / "diag" / "strided_experts.json")]
    md = metaworld(parse_args(["diagnose", *diag]))
    cov = json.loads((tmp_path / "diag" / "assembly_coverage.json").read_text())
    assert cov["strides"]["1"]["median"] == pytest.approx(1.0) and cov["episodes"] == 6  # the smoke budget's demos
    assert 0.2 < cov["strides"]["3"]["median"] < 0.5  # the expert's displacement actions: about 1/3
    (state_eval,) = (tmp_path / "diag").glob("assembly_*_seed0_eval.json")
    report = json.loads(state_eval.read_text())
    state_hip = json.loads((tmp_path / "rec" / "smoke" / "metaworld_assembly" / "state" / "hipolicy" /
                            "seed0.json").read_text())
    assert report["params_sha256"] == state_hip["network"]["params_sha256"]
    assert report["reused"]["with_eg"] and report["without_eg"]["stride1_frac"] == 1.0
    (guided,) = state_hip["evaluations"].values()
    assert report["with_eg"]["success"] == guided["success"]
    rows = {r["column"]: r for r in json.loads((tmp_path / "diag" / "diagnose.json").read_text())["records"]}
    assert rows[STRIDE1]["success"] == report["without_eg"]["success"]
    assert rows[STRIDE1]["run"] == rows["DP+HiPolicy"]["run"]
    text = open(md).read()
    assert "Post hoc" in text and "| metaworld:assembly |" in text and STRIDE1 in text
    monkeypatch.setattr(external, "_run", lambda *a, **k: pytest.fail(f"ran the bridge again: {a}"))
    again = open(metaworld(parse_args(["diagnose", *diag, "--from-records"]))).read()
    assert again.split("| Task")[1:] == text.split("| Task")[1:]
    assert "| – / – / – | – / – / – |" in text  # the chunking expert: not run yet
    (tmp_path / "diag" / "strided_experts.json").write_text(json.dumps({"tasks": {"assembly": {
        "delta": {"1": {"success_rate": 1.0}, "2": {"success_rate": 0.0}},
        "target": {"1": {"success_rate": 1.0}, "2": {"success_rate": 0.35}, "3": {"success_rate": 0.05}}}}}))
    text = open(metaworld(parse_args(["diagnose", *diag, "--from-records"]))).read()
    assert "| 100 / 0 / – | 100 / 35 / 5 |" in text
    # a network without its stride-1 pass (its checkpoint gone with the machine that trained it) is named
    state_eval.unlink()
    text = open(metaworld(parse_args(["diagnose", *diag, "--from-records"]))).read()
    assert f"No {STRIDE1} pass for: metaworld:assembly seed 0. A pass serves the run's checkpoint" in text
    # a second diagnose process while one holds the run (a live pid's lock): it leaves the network to that one
    import socket

    state_dir = tmp_path / "runs" / "smoke" / "metaworld_assembly" / "state" / "hipolicy" / "seed0"
    assert (state_dir / "ckpt").exists() or any(state_dir.iterdir())
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        (state_dir / ".campaign.lock").write_text(json.dumps({"pid": sleeper.pid, "host": socket.gethostname()}))
        capsys.readouterr()
        text = open(metaworld(parse_args(["diagnose", *diag]))).read()
        assert not state_eval.exists() and f"No {STRIDE1} pass for: metaworld:assembly seed 0." in text
        assert f"skipped: {state_dir} is in use by another campaign or diagnose process (pid {sleeper.pid}" in \
            capsys.readouterr().out
    finally:
        sleeper.kill()
        sleeper.wait()
    (state_dir / ".campaign.lock").unlink()
    metaworld(parse_args(["diagnose", *diag]))  # the lock gone: the pass is made again from what the run kept
    assert json.loads(state_eval.read_text())["without_eg"]["success"] == report["without_eg"]["success"]
    assert not (state_dir / ".campaign.lock").exists()  # released


def test_demo_coverage_of_displacement_demos(tmp_path):
    """The diagnosis's demo summary: at constant speed a stride-s segment covers 1/s of the demo's move; the share of
    xyz entries at the action bound is counted per entry; a demo moving at the bound every step can go no faster."""
    from hipolicy_jax.campaigns.metaworld import demo_coverage
    from hipolicy_jax.config import ChunkConfig

    episodes = [{"state": np.zeros((n, 39), np.float32),
                 "action": np.tile(np.array([[1.0, 0.5, 0.0, 1.0]], np.float32), (n, 1))} for n in (40, 50)]
    ReplayBuffer.from_episodes(episodes).save(str(tmp_path / "d.zarr"))
    cov = demo_coverage(str(tmp_path / "d.zarr"), ChunkConfig(strides=(1, 2, 3)))
    assert cov["episodes"] == 2 and cov["frames"] == 90
    for s in (1, 2, 3):
        row = cov["strides"][str(s)]
        assert row["windows"] == (40 - 8 * s) + (50 - 8 * s)
        assert row["median"] == pytest.approx(1 / s) and row["quartiles"] == pytest.approx([1 / s, 1 / s])
    assert cov["saturated_xyz"] == pytest.approx(1 / 3)  # x at +1; y at 0.5, z at 0
    assert cov["mean_steps"] == 45.0 and cov["mean_steps_at_bound"] == pytest.approx(45.0)  # x at the bound throughout


def test_metaworld_budget_rules_by_hand():
    from hipolicy_jax.campaigns.metaworld import budget_rules

    # a state network: 0.25 s/step x 1000 + 150 s per 100 episodes x 3 = 700 s; a task: 6 networks = 4200 s
    # a point-cloud network: 3 s/step x 1000 + 600 x 3 = 4800 s; a task 28800 s
    r = budget_rules(budget_s=144000, spent_s=4000, steps=1000, state_s_per_step=0.25, state_eval_s_per_100=150,
                     pc_s_per_step=3.0, pc_eval_s_per_100=600)
    assert r["state_task_s"] == pytest.approx(4200) and r["pointcloud_task_s"] == pytest.approx(28800)
    assert r["state_tasks"] == 16  # 16 x 4200 = 67200 <= 0.6 x 140000 = 84000
    assert r["pointcloud_tasks"] == 2  # (140000 - 67200) // 28800 = 2
    # tighter: 60 % of what is left fits 12 state tasks
    r = budget_rules(budget_s=144000, spent_s=4000, steps=1000, state_s_per_step=0.25, state_eval_s_per_100=150,
                     pc_s_per_step=3.0, pc_eval_s_per_100=600, state_share=12.5 * 4200 / 140000)
    assert r["state_tasks"] == 12 and r["pointcloud_tasks"] == int((140000 - 12 * 4200) // 28800)
    # not even 10 tasks: None (the pilot table then tries a smaller T)
    r = budget_rules(budget_s=50000, spent_s=4000, steps=1000, state_s_per_step=0.25, state_eval_s_per_100=150,
                     pc_s_per_step=3.0, pc_eval_s_per_100=600)
    assert r["state_tasks"] is None and r["pointcloud_tasks"] is None


def test_the_plan_states_what_is_left_and_what_was_spent(tmp_path):
    """``main --plan``: the pending jobs with their estimates (an unmeasured one counted apart), and what the
    records spent so far beside spent + left."""
    from hipolicy_jax.campaigns.metaworld import MainArgs, main_jobs, write_plan

    args = MainArgs(tasks=("basketball",), results=str(tmp_path))
    jobs = main_jobs(args)
    assert [(j.task, j.col.label, j.seed) for j in jobs[:4]] == [
        ("metaworld:basketball", "DP", 0), ("metaworld:basketball", "DP", 1), ("metaworld:basketball", "DP", 2),
        ("metaworld:basketball", "DP+HiPolicy", 0)]
    costs = [{"job": j, "done": i == 0, "trains": i > 1, "seconds": 0.0 if i == 0 else None if i == 5 else 1800.0}
             for i, j in enumerate(jobs)]
    spent = {"train_s": 3600.0, "runs": 1, "eval_s": 1800.0, "evaluations": 2, "measured_runs": 1,
             "measured_evaluations": 1, "wall_core_s": 9000.0}
    text = open(write_plan(args, costs, spent)).read()
    assert ("5 of 6 evaluations pending, 4 runs to train; estimated 2.0 CPU-hours for the 4 with a measured rate "
            "(1 not yet measured).") in text
    assert ("Spent so far: 1.5 CPU-hours in the `metaworld` records (runs trained: 1, evaluations: 2; the pilot and "
            "every arm included) (process CPU time of 1 of 1 runs and 1 of 2 evaluations, wall time × the cores its "
            "process ran on for the rest") in text
    assert "spent + left: 3.5 CPU-hours. Counted as wall time × cores, as the protocol's budget counts them: 2.5 spent." in text
    assert "| metaworld:basketball | DP+HiPolicy | 2 | yes | – |" in text
    assert "| metaworld:basketball | DP | 0 |" not in text  # recorded: not pending


def test_diagnose_on_absolute_targets_computes_no_displacement_coverage(tmp_path):
    """``diagnose`` on amendment 1's tasks: no segment coverage (it speaks of displacement actions; no demos are
    collected for it), a title naming absolute targets, and the chunked expert's target column from ``--experts``."""
    from hipolicy_jax.campaigns.metaworld import DiagnoseArgs, diagnose_table
    from hipolicy_jax.runs.store import write_json

    experts = tmp_path / "experts.json"
    write_json(str(experts), {"tasks": {"assembly": {"target": {"1": {"success_rate": 1.0},
                                                                "3": {"success_rate": 0.85}}}}})
    args = DiagnoseArgs(tasks=("metaworld-target:assembly",), results=str(tmp_path / "diag"), experts=str(experts),
                        records=str(tmp_path / "rec"), runs=str(tmp_path / "runs"), data=str(tmp_path / "data"),
                        progress=False)
    text = open(diagnose_table(args)).read()
    assert text.startswith("# Meta-World diagnosis: HiPolicy's strides on absolute hand targets (post hoc)")
    assert not list((tmp_path / "diag").glob("*_coverage.json")) and not (tmp_path / "data").exists()
    row = text.split("| metaworld-target:assembly | ")[1].split("\n")[0].split(" | ")
    assert row[:6] == ["–", "–", "–", "–", "– / – / –", "100 / – / 85"]


def test_amendment_section_pairs_targets_with_displacements_and_counts_steps_saved(tmp_path):
    """Amendment 1's secondary comparisons from table records: DP on targets − DP on displacements per seed on the
    shared initial states, and the steps DP+HiPolicy saves against DP over the episodes both succeeded in
    (closed-form numbers), beside the chunked expert's steps on targets and the demos' share at the action bound
    from the diagnosis files; a task without records or files prints '–'."""
    from hipolicy_jax.runs.store import write_json
    from hipolicy_jax.campaigns.metaworld import DISPLACEMENTS, MainArgs, amendment_section, displacement_records

    def rec(task, column, seed, success, steps):
        return {"task": task, "column": column, "seed": seed, "success": success, "steps": steps,
                "success_rate": float(np.mean(success))}

    t, other = "metaworld-target:assembly", "metaworld-target:hammer"
    args = MainArgs(tasks=(t, other), seeds=(0, 1))
    displaced = [rec(t, DISPLACEMENTS, 0, [1, 0, 0, 1], [90, 200, 200, 90]),
                 rec(t, DISPLACEMENTS, 1, [0, 0, 1, 1], [200, 200, 90, 90])]
    records = [rec(t, "DP", 0, [1, 1, 1, 1], [100, 100, 80, 90]), rec(t, "DP", 1, [1, 0, 1, 1], [60, 200, 80, 90]),
               rec(t, "DP+HiPolicy", 0, [1, 1, 1, 0], [50, 50, 40, 200]),
               rec(t, "DP+HiPolicy", 1, [1, 0, 1, 1], [30, 200, 40, 60])]
    write_json(str(tmp_path / "strided_experts.json"), {"tasks": {"assembly": {
        "delta": {"1": {"mean_steps": 90.0}},
        "target": {"1": {"mean_steps": 89.75}, "2": {"mean_steps": 70.25}, "3": {"mean_steps": None}}}}})
    write_json(str(tmp_path / "assembly_coverage.json"), {"saturated_xyz": 0.2, "mean_steps": 79.18,
                                                          "mean_steps_at_bound": 61.84})
    text = amendment_section(args, records, displaced, [("hard", [t]), ("medium", [other])], diagnosis=str(tmp_path))
    first, second = text.split("## Amendment 1, secondary: steps to success")

    def rows(section):
        return [[c.strip() for c in line.strip()[1:-1].split("|")] for line in section.splitlines()
                if line.startswith("| ") and not line.startswith("| Task") and not line.startswith("| :")]

    # Two seeds: the 95 % t interval's half-width is tan(0.475 pi) * se = 12.706 se (Student's t with 1 degree of
    # freedom is Cauchy), se = |v0 - v1| / 2, p = 1 - 2 atan(|mean| / se) / pi; with equal seed values the
    # episode-level se = sqrt(sum of var(ddof=1) / 4) / 2. Rates clip to [0, 100], differences to [-100, +100].
    # DP on displacements: 2/4 and 2/4, se = sqrt(2 (1/3) / 4) / 2 = 0.204 -> [-209.4, +309.4] -> [0.0, 100.0].
    # DP on targets: 4/4 and 3/4, mean 87.5, se 12.5 -> [-71.3, +246.3] -> [0.0, 100.0].
    # targets - displacements per seed: (0 + 1 + 1 + 0) / 4 and (1 + 0 + 0 + 0) / 4: +37.5, se 12.5, t = 3,
    # p = 1 - 2 atan(3) / pi = 0.2048 -> 0.2, ties.
    cells = ["50.0 [0.0, 100.0]", "87.5 [0.0, 100.0]", "+37.5 [-100.0, +100.0], p=0.2 (ties)"]
    assert rows(first) == [[t, *cells], ["**Average (hard)**", *cells], [other, "–", "–", "–"],
                           ["**Average (medium)**", "–", "–", "–"], ["**Total average**", "–", "–", "–"]]
    # steps: DP+HiPolicy 3/4 and 3/4 (equal: se = sqrt(2 (1/4) / 4) / 2 = 0.177 -> [-149.6, ...] -> [0, 100]);
    # success cost per seed -1/4 and 0: -12.5, se 12.5 -> clipped to [-100, +100], ties.
    # DP's steps to success: seed 0 (100 + 100 + 80 + 90) / 4 = 92.5, seed 1 (60 + 80 + 90) / 3 = 76.67: 84.58,
    # se 7.917, half-width 100.59 -> [0.0, 185.2]; DP+HiPolicy's: 140/3 and 130/3: 45.0, se 1.667 -> [23.8, 66.2].
    # Saved, over the episodes both succeeded in: seed 0 (episodes 0-2) (280 - 140) / 280 = 0.5, seed 1 (episodes
    # 0, 2, 3) (230 - 130) / 230 = 0.4348: +46.74, se 3.261 -> [+5.3, +88.2]; t = 14.33, p = 0.0443 -> faster.
    assert rows(second) == [
        [t, "87.5 [0.0, 100.0]", "75.0 [0.0, 100.0]", "-12.5 [-100.0, +100.0] (ties)", "84.6 [0.0, 185.2]",
         "45.0 [23.8, 66.2]", "+46.7 [+5.3, +88.2], p=0.044 (faster)", "89.8 / 70.2 / –", "79.2 / 61.8"],
        [other, "–", "–", "–", "–", "–", "–", "–", "–"],  # no records, no diagnosis files
        ["**Average**", "–", "–", "–", "–", "–", "–", "", ""]]  # a task without records: no average; per task only
    assert displacement_records(MainArgs(tasks=("assembly",))) is None  # a table on displacements has none


def test_main_table_rewrites_its_readme_section_only(tmp_path):
    """``main`` ends by copying its table into the README between its own markers (one pair per ``--results``), under
    a line counting the recorded runs; another table's markers and the README's other text stay as they are, and a
    README without the markers is left alone."""
    from hipolicy_jax.campaigns.metaworld import MainArgs, readme_markers, write_readme_section

    res = tmp_path / "results" / "metaworld"
    res.mkdir(parents=True)
    md = res / "main.md"
    md.write_text("# Meta-World: success rate (%)\n\n| a |\n|---|\n| 1 |\n\n## DP3's metric\n\n| b |\n")
    (res / "main.png").write_bytes(b"png")
    readme = tmp_path / "README.md"
    begin, end = readme_markers(str(res))
    other_begin, other_end = readme_markers(str(res / "target"))
    assert begin != other_begin and end != other_end
    assert readme_markers(str(res) + "/") == (begin, end)
    readme.write_text(f"### Meta-World\n\n{begin}\nold\n{end}\n\n{other_begin}\nkept\n{other_end}\n")
    args = MainArgs(tasks=("basketball",), results=str(res), readme=str(readme))
    write_readme_section(args, str(md), 4, 6)
    text = readme.read_text()
    section = text.split(begin)[1].split(end)[0]
    assert "old" not in section and "\nkept\n" in text
    assert section.strip().startswith("4 of 6 runs recorded; what is left and its estimated cost: "
                                      f"[plan.md]({os.path.relpath(res / 'plan.md', tmp_path)}).")
    assert f"\n#### Meta-World: success rate (%) — `{os.path.relpath(md, tmp_path)}`\n" in section
    assert "\n##### DP3's metric\n" in section and "| 1 |" in section and "| b |" in section
    assert f"![main.png]({os.path.relpath(res / 'main.png', tmp_path)})" in section
    write_readme_section(args, str(md), 6, 6)
    assert readme.read_text().split(begin)[1].split(end)[0].strip().startswith("6 of 6 runs recorded.\n")
    bare = tmp_path / "BARE.md"
    bare.write_text("no markers\n")
    write_readme_section(dataclasses.replace(args, readme=str(bare)), str(md), 4, 6)
    assert bare.read_text() == "no markers\n"


def test_main_writes_its_tables_into_the_results_page():
    """Issue #61: ``main --readme`` (the flag keeps its name) defaults to docs/results.md, which holds each committed
    table's markers once (the README holds none); each table's own command line, printed with ``--readme README.md``,
    still parses."""
    import re
    import shlex

    from experiments.metaworld import parse_args
    from hipolicy_jax.campaigns.metaworld import readme_markers

    args = parse_args(["main"])
    assert args.readme == "docs/results.md"
    text = open(os.path.join(ROOT, args.readme)).read()
    readme = open(os.path.join(ROOT, "README.md")).read()
    for results in ("results/metaworld", "results/metaworld/target"):
        begin, end = readme_markers(results)
        assert text.count(begin) == 1 and text.count(end) == 1 and text.index(begin) < text.index(end)
        assert begin not in readme
        with open(os.path.join(ROOT, results, "main.md")) as f:
            command = re.search(r"^Command: `(.*)`$", f.read(), re.M).group(1)
        old = parse_args(shlex.split(command)[3:])
        assert type(old) is type(args) and old.results == results and old.readme in ("README.md", "docs/results.md")


def test_main_no_tables_writes_only_the_plan(tmp_path):
    """``main --tasks X --no-tables`` (a run narrowed to force a few jobs) leaves ``main.md`` and the README table
    alone and ends by writing its plan of what is left; without the flag the same call rebuilds both."""
    from experiments.metaworld import main as metaworld, parse_args
    from hipolicy_jax.campaigns.metaworld import readme_markers

    res = tmp_path / "results"
    readme = tmp_path / "README.md"
    begin, end = readme_markers(str(res))
    readme.write_text(f"intro\n{begin}\nthe full table\n{end}\n")
    flags = ["--tasks", "basketball", "--runs", str(tmp_path / "runs"), "--records", str(tmp_path / "records"),
             "--results", str(res), "--data", str(tmp_path / "data"), "--readme", str(readme), "--no-progress",
             "--until", "2000-01-01 00:00"]  # a deadline already past: nothing starts
    args = parse_args(["main", *flags, "--no-tables"])
    assert not args.tables
    plan = metaworld(args)
    assert sorted(p.name for p in res.iterdir()) == ["plan.md"] and plan == str(res / "plan.md")
    assert "6 of 6 evaluations pending" in (res / "plan.md").read_text()
    assert "the full table" in readme.read_text() and not (tmp_path / "runs").exists()
    metaworld(parse_args(["main", *flags]))
    assert (res / "main.md").exists() and "the full table" not in readme.read_text()
    assert "0 of 6 runs recorded" in readme.read_text().split(begin)[1]
