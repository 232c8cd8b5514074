"""Timed phases: per-step strides from decisions, phase runs, the report, and press_button's hold under coarse strides."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax import envs
from hipolicy_jax.evaluation import phases, rollout
from hipolicy_jax.evaluation.rollout import EvalResult, Recording


def _result(start, stride, executed, valid, steps) -> EvalResult:
    z = jnp.zeros(np.shape(start))
    return EvalResult(success_rate=jnp.zeros(()), mean_steps_success=jnp.zeros(()),
                      success=jnp.zeros(len(steps), bool), steps=jnp.asarray(steps), entropy=z,
                      stride=jnp.asarray(stride), valid=jnp.asarray(valid), start=jnp.asarray(start),
                      executed=jnp.asarray(executed), actions=jnp.asarray(executed))


def test_step_strides_follow_the_decisions():
    # episode 0: 3 decisions (4, 4, 2 actions) at strides 1, 2, 3; episode 1: one decision of 4 then padding
    res = _result(start=[[0, 4, 8], [0, 4, 8]], stride=[[1, 2, 3], [2, 1, 1]], executed=[[4, 4, 2], [4, 4, 4]],
                  valid=[[True, True, True], [True, False, False]], steps=[10, 4])
    np.testing.assert_array_equal(phases.step_strides(res, 12), [[1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 0, 0],
                                                                  [2, 2, 2, 2, 0, 0, 0, 0, 0, 0, 0, 0]])


def test_phase_runs_lengths_and_majority_stride():
    # states 0..10 (state t follows control step t-1); the reset state (index 0) never counts
    in_phase = np.array([1, 1, 1, 0, 0, 1, 1, 1, 1, 0, 1], bool)
    strides = np.array([1, 1, 2, 2, 1, 2, 2, 3, 3, 3])
    # runs: states 1-2 (steps 0-1: stride 1), states 5-8 (steps 4-7: strides 1, 2, 2, 3 → 2), state 10 (step 9: 3)
    assert phases.phase_runs(in_phase, strides, steps=10) == [(2, 1), (4, 2), (1, 3)]
    # states past the episode's end do not count: the last run is cut at state 7
    assert phases.phase_runs(in_phase, strides, steps=7) == [(2, 1), (3, 2)]
    assert phases.phase_runs(np.zeros(11, bool), strides, steps=10) == []
    # a tie between strides goes to the smaller (finer) one
    assert phases.phase_runs(np.array([0, 1, 1], bool), np.array([2, 1]), steps=2) == [(2, 1)]


class _Env:
    """A stand-in env whose timed phase is qpos[..., 0] > 0 and must last 3 steps."""

    def timed_phase(self, qpos):
        return np.asarray(qpos)[..., 0] > 0, 3


def test_timed_phase_report_counts_episodes_and_strides():
    qpos = np.zeros((2, 9, 1))
    qpos[0, 1:5, 0] = 1  # episode 0: one run of 4 states at stride 1
    qpos[1, 1:3, 0] = 1  # episode 1: runs of 2 (stride 2) and 3 (stride 1)
    qpos[1, 4:7, 0] = 1
    res = _result(start=[[0, 4], [0, 3]], stride=[[1, 1], [2, 1]], executed=[[4, 4], [3, 5]],
                  valid=[[True, True], [True, True]], steps=[8, 8])
    rep = phases.timed_phase_report(_Env(), res, Recording(jnp.asarray(qpos), jnp.zeros((2, 1, 3)), {}))
    assert rep["required_steps"] == 3 and rep["longest"] == [4, 3] and rep["reached"] == 1.0
    assert rep["by_stride"] == {"1": {"runs": 2, "median_steps": 3.5, "reached": 1.0},
                                "2": {"runs": 1, "median_steps": 2.0, "reached": 0.0}}
    assert phases.timed_phase_report(envs.make("latch_door"), res, Recording(jnp.asarray(qpos), None, {})) is None


@pytest.mark.slow
def test_coarse_strides_compress_the_press_button_hold():
    """The scripted expert executed at stride 2 holds the button half as long, and fails exactly when the halved
    hold falls short of the required second."""
    env = envs.make("press_button")
    reports, success = {}, {}
    for stride in (1, 2):
        policy_fn, init_fn = rollout.expert_policy(env, 8, stride)
        res, rec = rollout.rollout_episodes(policy_fn, init_fn, env, 8, jax.random.PRNGKey(3), history_len=1,
                                            chunk_len=8)
        reports[stride], success[stride] = phases.timed_phase_report(env, res, rec), np.asarray(res.success)
    assert reports[1]["required_steps"] == env.hold_steps == 10
    assert reports[1]["reached"] == 1.0 and success[1].all() and list(reports[1]["by_stride"]) == ["1"]
    assert list(reports[2]["by_stride"]) == ["2"]
    long1, long2 = np.array(reports[1]["longest"]), np.array(reports[2]["longest"])
    assert (np.abs(long2 - long1 / 2) <= 1).all()
    np.testing.assert_array_equal(success[2], long2 >= 10)
