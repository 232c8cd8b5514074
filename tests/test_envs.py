"""MJX tasks: registry, jitted reset/step, observation shapes, expert success, task mechanics, demo dataset."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax import envs
from hipolicy_jax.envs import demos, latch_door, press_button

N_EXPERT = 3  # expert seeds per task in the quick suite (100 seeds: python -m hipolicy_jax.envs.check_experts)


@functools.lru_cache(maxsize=None)
def jitted(task):
    """(env, jit(reset), jit(step)) for one unbatched instance, shared across tests."""
    env = envs.make(task)
    return env, jax.jit(env.reset), jax.jit(env.step)


def test_registry():
    assert set(envs.TASKS) == {"press_button", "latch_door", "stack_cubes", "pick_place"}
    with pytest.raises(ValueError, match="task_name"):
        envs.make("open_drawer")
    with pytest.raises(ValueError, match="obs_keys"):
        envs.make("press_button", obs_keys=("image",))
    with pytest.raises(ValueError, match="control_dt"):
        envs.make("press_button", control_dt=0.0123)
    env = envs.make("latch_door", control_dt=0.05, max_steps=77)
    assert env.n_substeps == 10 and env.max_steps == 77 and env.control_dt == 0.05
    assert env.action_dim == 4 and env.obs_shapes == {"state": (7,)}


@pytest.mark.parametrize("task", ["press_button", "latch_door"])
def test_jit_reset_step_single_instance(task):
    env, reset, step = jitted(task)
    state = reset(jax.random.PRNGKey(0))
    assert state.obs["state"].shape == env.obs_shapes["state"] and state.obs["state"].dtype == jnp.float32
    tcp = state.obs["state"][:3]
    np.testing.assert_allclose(tcp, state.data.qpos[:3], atol=1e-6)
    target = tcp + jnp.array([0.03, -0.02, -0.02])
    for _ in range(5):
        state = step(state, jnp.concatenate([target, jnp.ones((1,))]))
    assert step._cache_size() == 1  # no recompiles across steps
    assert int(state.step) == 5 and not bool(state.done)
    # the position actuators track the absolute target and the gripper closes
    np.testing.assert_allclose(state.obs["state"][:3], target, atol=3e-3)
    assert float(state.obs["state"][3]) < 0.01
    assert np.isfinite(np.asarray(state.obs["state"])).all()


@pytest.mark.parametrize("task", [t if t == "press_button" else pytest.param(t, marks=pytest.mark.slow)
                                  for t in envs.TASKS])
def test_expert_rollout(task):
    run = demos.expert_rollout(task, N_EXPERT)
    env = run.env
    trace = jax.device_get(run(jax.random.split(jax.random.PRNGKey(0), N_EXPERT)))
    T = env.max_steps
    assert trace.obs["state"].shape == (N_EXPERT, T) + env.obs_shapes["state"]
    assert trace.action.shape == (N_EXPERT, T, env.action_dim)
    assert np.isfinite(trace.obs["state"]).all() and np.isfinite(trace.action).all()
    assert trace.success.all(), trace.steps
    assert ((trace.steps >= 35) & (trace.steps < T)).all(), trace.steps
    # demonstrations vary: different initial states, different lengths or actions
    assert np.ptp(trace.obs["state"][:, 0, 4:], axis=0).max() > 0.01
    # smooth expert motion: no target jumps above 5 cm per control step
    for i in range(N_EXPERT):
        n = trace.steps[i]
        assert np.abs(np.diff(trace.action[i, :n, :3], axis=0)).max() < 0.05


def _press(env, reset, step, hold_steps):
    """Drive the closed gripper onto the button, hold for ``hold_steps``, lift; returns (success, max depth)."""
    state = reset(jax.random.PRNGKey(3))
    bxy = state.obs["state"][4:6]
    above = jnp.concatenate([bxy, jnp.array([0.09, 1.0])])
    down = jnp.concatenate([bxy, jnp.array([press_button.CAP_TOP - 0.015 + 0.018, 1.0])])
    actions = [above] * 12 + [down] * (3 + hold_steps) + [above] * 6
    depth = 0.0
    for a in actions:
        state = step(state, a)
        depth = max(depth, float(state.obs["state"][6]))
    return bool(state.success), depth


def test_press_button_needs_hold_then_release():
    env, reset, step = jitted("press_button")
    ok_short, depth = _press(env, reset, step, hold_steps=env.hold_steps - 6)
    assert depth > press_button.PRESS_DEPTH and not ok_short
    ok_long, _ = _press(env, reset, step, hold_steps=env.hold_steps + 2)
    assert ok_long
    # the hidden hold timer is in info, not in the observed state
    state = reset(jax.random.PRNGKey(0))
    assert "hold" in state.info and state.obs["state"].shape == (7,)


def test_latch_door_detent_and_catch():
    env, reset, step = jitted("latch_door")
    state = reset(jax.random.PRNGKey(1))
    hold = jnp.concatenate([state.obs["state"][:3], jnp.zeros((1,))])
    adr = env._door_qadr
    in_detent = state.replace(data=state.data.replace(qpos=state.data.qpos.at[adr].set(0.09)))
    for _ in range(5):
        in_detent = step(in_detent, hold)
    assert float(in_detent.obs["state"][4]) > latch_door.LATCH_HIGH - 0.01  # pushed back open
    assert not bool(in_detent.success)
    past = state.replace(data=state.data.replace(qpos=state.data.qpos.at[adr].set(0.045)))
    for _ in range(3):
        past = step(past, hold)
    assert float(past.obs["state"][4]) < latch_door.LATCHED and bool(past.success) and bool(past.done)


def test_collect_demos_dataset_round_trip(tmp_path):
    from hipolicy_jax.data.replay_buffer import ReplayBuffer

    episodes = demos.collect_demos("press_button", N_EXPERT, jax.random.PRNGKey(0), batch_size=N_EXPERT)
    assert len(episodes) == N_EXPERT
    for ep in episodes:
        assert ep["state"].shape[0] == ep["action"].shape[0] >= 35
        assert ep["state"].shape[1] == 7 and ep["action"].shape[1] == 4
    buf = ReplayBuffer.from_episodes(episodes)
    path = tmp_path / "demos.zarr"
    buf.save(path)
    with pytest.raises(FileExistsError):
        buf.save(path)
    loaded = ReplayBuffer.load(path)
    np.testing.assert_array_equal(loaded.episode_ends, np.cumsum([len(e["action"]) for e in episodes]))
    np.testing.assert_allclose(loaded.data["state"], np.concatenate([e["state"] for e in episodes]))
    np.testing.assert_allclose(loaded.data["action"], np.concatenate([e["action"] for e in episodes]))


@pytest.mark.slow
def test_collect_cli_refuses_overwrite(tmp_path):
    from experiments import collect

    out = tmp_path / "pb.zarr"
    argv = ["--task", "press_button", "--episodes", str(N_EXPERT), "--batch-size", str(N_EXPERT),
            "--output", str(out)]
    collect.main(argv)
    assert (out / "meta").exists()
    with pytest.raises(SystemExit):
        collect.main(argv)
    collect.main(argv + ["--force"])


@pytest.mark.parametrize("task", ["press_button"] + [pytest.param(t, marks=pytest.mark.slow)
                                                     for t in ("latch_door", "pick_place")])
def test_kinematic_reset_runs_the_same_episode_as_a_full_forward(task, monkeypatch):
    """``reset`` computes only the kinematics (a full ``mjx.forward`` would compile the physics twice into every
    rollout): the observations, and every control step after it, are bit-for-bit those of a reset that runs the
    full forward dynamics. press_button observes a point cloud too (ray casts read the geom poses)."""
    from mujoco import mjx
    from hipolicy_jax.envs.camera import CameraConfig

    keys = ("state", "point_cloud") if task == "press_button" else ("state",)
    env = envs.make(task, obs_keys=keys, camera=CameraConfig(width=16, height=16, num_points=32))
    actions = jnp.array([[0.03, -0.02, 0.12, 0.0], [0.05, 0.0, 0.08, 1.0], [0.05, 0.01, 0.05, 1.0]])

    def run(key):  # a fresh function per call: jit must trace it again
        def episode(key):
            state = env.reset(key)

            def one(s, a):
                s = env.step(s, a)
                return s, (s.obs, s.data.qpos, s.data.qvel)

            _, after = jax.lax.scan(one, state, actions)
            return state.obs, state.data.geom_xpos, after
        return jax.device_get(jax.jit(episode)(key))

    key = jax.random.PRNGKey(3)
    ours = run(key)
    forward = mjx.forward
    calls = []
    monkeypatch.setattr(mjx, "kinematics", lambda m, d: calls.append(1) or forward(m, d))
    reference = run(key)
    assert calls, "the reference trace did not go through reset's kinematics"
    for a, b in zip(jax.tree.leaves(ours), jax.tree.leaves(reference), strict=True):
        np.testing.assert_array_equal(a, b)
    assert np.abs(ours[2][1][-1] - ours[2][1][0]).max() > 1e-3  # the hand moved: the steps did something
