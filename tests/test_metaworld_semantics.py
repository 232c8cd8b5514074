"""Meta-World bridge: execution semantics (``rate`` | ``waypoint``, issue 58) and summed delta actions (issue 62).

The bridge runs in its own venv (``bash scripts/setup_metaworld.sh`` → ``.venv-metaworld``; ``METAWORLD_VENV``
chooses another), so every test here runs its code there in a subprocess; without the venv they are skipped.
"""

import json
import os
import subprocess

import pytest

from metaworld_venv import PYTHON, ROOT, VENV, bridge, in_bridge, needs_venv  # noqa: F401 (tests/metaworld_venv.py)



@needs_venv
def test_waypoint_with_targets_reached_in_one_step_is_rate():
    """With a tolerance so large that the hand is always within it, a target reached in one control step (a move
    within the per-step bound) ends its waypoint after that step: ``waypoint`` is ``rate`` step for step — the same
    observations, outcome and counts — for the expert's own displacements and targets, and for the expert chunked
    at stride 2 (every 2nd displacement; targets with the headroom of 2 cm a step)."""
    in_bridge("""
import numpy as np
from metaworld_bridge.env import MetaWorldTask
for space, kwargs in (("delta", {}), ("target", {}), ("target", {"move_limit": 2.0})):
    a, b = (MetaWorldTask("assembly", 150, action_space=space, **kwargs) for _ in range(2))
    if not kwargs:  # step by step, the expert's episode of seed 3
        actions = a.run_expert(3).frames["action"]
        a.reset(3), b.reset(3)
        for act in actions:
            ra = a.execute(act, "rate")
            wb = b.execute(act, "waypoint", 1, tolerance=100.0, waypoint_steps=5)
            np.testing.assert_array_equal(ra.obs, wb.obs)
            assert (ra.success, ra.truncated, ra.control_steps) == (wb.success, wb.truncated, wb.control_steps) == \\
                (ra.success, ra.truncated, 1)
            assert not wb.unreached and not wb.clipped
        assert ra.success
    if space == "target" and not kwargs:
        continue  # every 2nd target lies up to 2 cm away: not reached in one step at 1 cm a step
    rate = a.run_strided_expert(3, 2)
    way = b.run_strided_expert(3, 2, semantics="waypoint", tolerance=100.0, waypoint_steps=5)
    np.testing.assert_array_equal(rate.frames["action"], way.frames["action"])
    assert (rate.success, rate.steps, rate.actions, rate.decisions) == \\
        (way.success, way.steps, way.actions, way.decisions), (rate, way)
    assert rate.steps == rate.actions and way.unreached == 0
print("ok")
""")


@needs_venv
def test_counts_of_a_two_decision_episode_by_hand():
    """``evaluate`` against a scripted server (two replies) counts decisions, actions and control steps per episode.
    A tolerance of 1 µm is never met, so every waypoint runs its bound: ``waypoint_steps`` (2) x the reply's stride.
    Decision 1, stride 1, 2 actions: 2 + 2 control steps; decision 2, stride 3: 6 steps, then the step limit (12)
    cuts the next action after 2: 4 actions, 12 control steps, 3 unreached (the cut one ended the episode); the
    history got one frame per completed action (3). Under ``rate`` the same replies take 1 step an action: the
    limit 3 ends decision 2 after its first action (2 decisions, 3 actions, 3 steps); the summed displacement of 2.5
    cm is clipped by the environment's limit (1 of 3)."""
    out = in_bridge("""
import json
import numpy as np
import metaworld_bridge.evaluate as ev

class Server:
    def __init__(self):
        self.sent = []
    def get_server_metadata(self):
        return {"task": "metaworld:assembly", "action_dim": 4, "obs": {"state": {"shape": [2, 39]}},
                "action_kinds": ["delta", "delta", "delta", "absolute"], "strides": [1, 3]}
    def infer(self, msg):
        self.sent.append(msg)
        n = len(self.sent) - 1
        if n == 0:
            return {"actions": np.array([[0.5, 0, 0, -1], [0, 0.5, 0, -1]], np.float32), "stride": 1}
        return {"actions": np.array([[2.5, 0, 0, -1], [0, 0, 0.5, -1], [0, 0, 0.5, -1]], np.float32), "stride": 3}

servers = []
def client(url, key):
    servers.append(Server())
    return servers[-1]
ev.check_server = lambda url: None
ev._openpi_client = client
frames = []
orig = ev._Slot._frame
def counted(self, obs):
    frames.append(obs.copy())
    return orig(self, obs)
ev._Slot._frame = counted
rec = ev.evaluate("assembly", "ws://fake", 1, 0, num_envs=1, max_steps=12, progress=False, semantics="waypoint",
                  waypoint_tolerance=1e-6, waypoint_steps=2)
ep = rec["per_episode"][0]
assert (ep["decisions"], ep["actions"], ep["control_steps"], ep["steps"], ep["unreached"], ep["clipped"]) == \\
    (2, 4, 12, 12, 3, 0), ep
assert len(frames) == 1 + 3  # the reset's frame, then one per completed action
hist = servers[0].sent[1]["state"]
np.testing.assert_array_equal(hist, np.stack(frames[1:3]).astype(np.float32))  # after actions 1 and 2
assert (rec["mean_decisions"], rec["mean_actions"], rec["mean_control_steps"], rec["mean_steps"]) == (2, 4, 12, 12)
assert rec["semantics"] == "waypoint" and rec["waypoint_tolerance"] == 1e-6 and rec["waypoint_steps"] == 2
assert rec["action_kinds"] == ["delta", "delta", "delta", "absolute"] and rec["summed_deltas"]
assert rec["unreached"]["actions"] == 3 and rec["unreached"]["of"] == 4
frames.clear()
rec = ev.evaluate("assembly", "ws://fake", 1, 0, num_envs=1, max_steps=3, progress=False)
ep = rec["per_episode"][0]
assert (ep["decisions"], ep["actions"], ep["control_steps"], ep["steps"], ep["clipped"]) == (2, 3, 3, 3, 1), ep
assert rec["clipped"] == {**rec["clipped"], "actions": 1, "of": 3} and rec["semantics"] == "rate"
print(json.dumps(rec["per_episode"]))
print("ok")
""")
    assert '"actions": 3, "control_steps": 3, "clipped": 1' in out  # the summary as written to --out


@needs_venv
def test_a_summed_delta_under_waypoint_lands_where_its_deltas_would():
    """Three displacements of (0.8, -0.6, 0.3) executed one per control step, then held until the hand settles,
    put the hand where one summed displacement (2.4, -1.8, 0.9) executed as a waypoint does (within the tolerance),
    over at least 3 control steps (the move bound is 1 cm a step); under ``rate`` the same summed displacement is
    clipped by Meta-World's limit to 1 cm on x and y, so the hand's target moves (1, -1, 0.9) cm."""
    in_bridge("""
import numpy as np
from metaworld_bridge.env import KINDS_OF_SPACE, MetaWorldTask, WAYPOINT_TOLERANCE
d = np.array([0.8, -0.6, 0.3, -1.0])
steps = MetaWorldTask("assembly", 200)
steps.reset(5)
start = steps.data.mocap_pos[0].copy()
for _ in range(3):
    steps.execute(d, "rate")
for _ in range(40):
    obs, _, _ = steps.step(np.array([0.0, 0.0, 0.0, -1.0]))
np.testing.assert_allclose(steps.data.mocap_pos[0] - start, 3 * d[:3] * 0.01, atol=1e-9)
summed = np.concatenate([3 * d[:3], d[3:]])
way = MetaWorldTask("assembly", 200)
way.reset(5)
done = way.execute(summed, "waypoint", stride=3)
assert done.control_steps >= 3 and not done.unreached and not done.clipped, done[1:]
np.testing.assert_allclose(way.data.mocap_pos[0], steps.data.mocap_pos[0], atol=1e-9)
assert np.linalg.norm(done.obs[:3] - (start + 3 * d[:3] * 0.01)) <= WAYPOINT_TOLERANCE
assert np.linalg.norm(done.obs[:3] - obs[:3]) <= WAYPOINT_TOLERANCE
rate = MetaWorldTask("assembly", 200)
rate.reset(5)
r = rate.execute(summed, "rate", stride=3)
assert r.clipped and r.control_steps == 1
np.testing.assert_allclose((rate.data.mocap_pos[0] - start) * 100, [1, -1, 0.9], atol=1e-9)
assert KINDS_OF_SPACE == {"delta": ("delta", "delta", "delta", "absolute"), "target": ("absolute",) * 4}
print("ok")
""")


@needs_venv
def test_collected_demos_declare_their_action_kinds(tmp_path):
    """The demo buffer's root attribute ``action_kinds``: displacements on xyz and an absolute gripper effort for
    the ``delta`` space, all absolute for ``target``."""
    import zarr

    for space, kinds in (("delta", ["delta", "delta", "delta", "absolute"]), ("target", ["absolute"] * 4)):
        path = str(tmp_path / f"{space}.zarr")
        r = bridge("metaworld_bridge.collect", "--task", "assembly", "--episodes", "1", "--out", path,
                   "--no-point-cloud", "--action-space", space, "--no-progress")
        assert r.returncode == 0, r.stderr[-2000:]
        assert dict(zarr.open_group(path, mode="r").attrs)["action_kinds"] == kinds


CHUNKED = """
import json, sys
from metaworld_bridge.env import MetaWorldTask
task, seeds, semantics = sys.argv[1], int(sys.argv[2]), sys.argv[3]
env = MetaWorldTask(task, 500)
out = {}
for stride in (1, 2, 3):
    eps = [env.run_strided_expert(s, stride, summed_deltas=stride > 1, semantics=semantics) for s in range(seeds)]
    out[stride] = [sum(e.success for e in eps), [e.steps for e in eps], sum(e.clipped for e in eps)]
print(json.dumps(out))
print("ok")
"""


def chunked_expert(task: str, seeds: int, semantics: str) -> dict:
    r = subprocess.run([PYTHON, "-c", CHUNKED, task, str(seeds), semantics], cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return {int(k): v for k, v in json.loads(r.stdout.strip().splitlines()[-2]).items()}


@needs_venv
@pytest.mark.parametrize("task", ["stick-push", "pick-place-wall"])
def test_expert_chunked_on_summed_deltas_keeps_the_demos_success(task):
    """The scripted expert chunked on displacements at strides 2 and 3 with summed deltas, executed as waypoints,
    succeeds on every seed the expert itself does (issue 62: chunked as every stride-th displacement, the expert
    failed on all 20 seeds of both at strides 2 and 3)."""
    got = chunked_expert(task, 3, "waypoint")
    assert got[1][0] == 3, got
    for stride in (2, 3):
        assert got[stride][0] == got[1][0], (stride, got)


@needs_venv
@pytest.mark.slow
@pytest.mark.parametrize("task", ["coffee-pull", "coffee-push", "bin-picking"])
def test_expert_chunked_on_summed_deltas_keeps_the_demos_success_more_tasks(task):
    """As above on three more tasks, 5 seeds each (measured on 20 seeds: 20 / 20 / 20 at strides 1 / 2 / 3 on each;
    chunked as every stride-th displacement, at strides 2 / 3: coffee-pull 0 / 0, coffee-push 5 / 5, bin-picking
    20 / 17)."""
    got = chunked_expert(task, 5, "waypoint")
    assert got[1][0] == 5, got
    for stride in (2, 3):
        assert got[stride][0] == got[1][0], (stride, got)


@needs_venv
def test_bad_execution_settings_name_the_option():
    """Each bad setting gives one line naming the option and what it expects, from the API and from both CLIs
    (before any server is asked)."""
    in_bridge("""
from metaworld_bridge.env import MetaWorldTask
cases = ((("jump",), "semantics: one of rate, waypoint, got 'jump'"),
         (("waypoint", 0.0), "waypoint_tolerance: must be > 0 (metres of the hand from its target), got 0.0"),
         (("waypoint", -0.01), "waypoint_tolerance: must be > 0"),
         (("waypoint", 0.01, 0), "waypoint_steps: must be an integer >= 1"))
for args, msg in cases:
    try:
        MetaWorldTask.check_semantics(*args)
    except ValueError as e:
        assert msg in str(e), str(e)
    else:
        raise AssertionError(args)
env = MetaWorldTask("assembly", 200)
env.reset(0)
for call, msg in ((lambda: env.execute([0, 0, 0, 0], "waypoint", 0), "stride: must be an integer >= 1, got 0"),
                  (lambda: env.execute([0, 0, 0, 0], "glide"), "semantics: one of rate, waypoint"),
                  (lambda: MetaWorldTask("assembly", 200, action_space="target").run_strided_expert(
                      0, 2, summed_deltas=True), "summed_deltas: sums displacement actions")):
    try:
        call()
    except ValueError as e:
        assert msg in str(e), str(e)
    else:
        raise AssertionError(msg)
print("ok")
""")
    for flags, msg in ((["--semantics", "jump"], "error: semantics: one of rate, waypoint, got 'jump'"),
                       (["--semantics", "waypoint", "--waypoint-tolerance", "0"],
                        "error: waypoint_tolerance: must be > 0 (metres of the hand from its target), got 0.0"),
                       (["--semantics", "waypoint", "--waypoint-steps", "0"],
                        "error: waypoint_steps: must be an integer >= 1 (control steps per action and unit of "
                        "stride), got 0")):
        r = bridge("metaworld_bridge.evaluate", "--task", "assembly", "--url", "ws://127.0.0.1:9", "--episodes", "1",
                   "--no-progress", *flags)
        assert r.returncode != 0 and r.stderr.strip() == msg, r.stderr
        r = bridge("metaworld_bridge.check_experts", "--tasks", "assembly", "--strides", "2", "--seeds", "1",
                   "--out", os.devnull, *flags)
        assert r.returncode != 0 and r.stderr.strip() == msg, r.stderr
    r = bridge("metaworld_bridge.check_experts", "--tasks", "assembly", "--strides", "2", "--delta-chunks", "sum",
               "--out", os.devnull)
    assert r.returncode != 0 and r.stderr.strip() == "error: delta_chunks: each one of every, summed, got 'sum'"


@needs_venv
def test_served_action_kinds_are_checked_against_the_action_space():
    in_bridge("""
from metaworld_bridge.evaluate import action_kinds
assert action_kinds({}) == ["absolute"] * 4  # policies trained before kinds were declared
assert action_kinds({"action_kinds": ["delta", "delta", "delta", "absolute"]}) == ["delta"] * 3 + ["absolute"]
for meta, space, msg in (({"action_kinds": ["delta"] * 3 + ["absolute"]}, "target", "pass --action-space delta"),
                         ({"action_kinds": ["delta"] * 4}, "delta", "the gripper (dim 3) is an effort"),
                         ({"action_kinds": ["delta"] * 3}, "delta", "expected 4 of absolute, delta")):
    try:
        action_kinds(meta, space)
    except ValueError as e:
        assert str(e).startswith("action_kinds: ") and msg in str(e), str(e)
    else:
        raise AssertionError(meta)
print("ok")
""")


@needs_venv
def test_check_experts_records_every_variant(tmp_path):
    """``check_experts --strides`` with both delta chunkings and both semantics: one entry per (variant, stride)
    with its counts, one printed line per task and variant; the plain keys (``delta``, ``target``) keep their
    meaning (every stride-th action, one control step each)."""
    out = tmp_path / "strided.json"
    r = bridge("metaworld_bridge.check_experts", "--tasks", "coffee-push", "--strides", "1", "2", "--action-spaces",
               "delta", "target", "--delta-chunks", "every", "summed", "--semantics", "rate", "waypoint", "--seeds",
               "1", "--max-steps", "150", "--out", str(out), timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    report = json.loads(out.read_text())
    keys = ["delta", "delta@waypoint", "delta+summed", "delta+summed@waypoint", "target", "target@waypoint"]
    assert report["variants"] == keys and sorted(report["tasks"]["coffee-push"]) == sorted(keys)
    assert report["waypoint_tolerance"] == 0.04 and report["waypoint_steps"] == 5
    for key in keys:
        assert f"coffee-push        {key:<22} success at strides 1/2: " in r.stdout
        for stride, row in report["tasks"]["coffee-push"][key].items():
            assert row["mean_actions"] >= row["mean_decisions"] >= 1
            if "@" not in key:  # rate: one control step an action
                assert row["mean_control_steps"] == row["mean_actions"] and row["unreached"] == 0
            else:
                assert row["mean_control_steps"] >= row["mean_actions"] and row["clipped"] == 0
    rows = report["tasks"]["coffee-push"]
    assert rows["delta"]["1"] == rows["delta+summed"]["1"]  # stride 1: a block of one, summed or not
    assert rows["delta"]["1"]["successes"] == 1
