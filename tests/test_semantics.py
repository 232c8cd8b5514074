"""Execution semantics (``InferenceConfig.semantics``): ``rate`` (one control step per action) and ``waypoint``
(each action a target the controller is given until reached), the counts every evaluation records (decisions,
actions, control steps) and the MJX tasks' controller speed limit."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from hipolicy_jax import envs
from hipolicy_jax.campaigns.campaign import Column, evaluation_key
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.envs.base import State
from hipolicy_jax.evaluation.evaluator import eval_summary, result_record
from hipolicy_jax.evaluation.rollout import (PolicyOutput, Semantics, evaluate_stateful, expert_policy,
                                             rollout_episodes, stateless)


@struct.dataclass
class _ToyData:
    qpos: jax.Array


class ToyLine:
    """A hand on a line that moves at most 1 a control step towards its target; success once it reaches 7."""

    obs_keys = ("state",)
    action_dim = 1
    max_steps = 30

    def _state(self, x, step, success):
        return State(data=_ToyData(qpos=x[None]), obs={"state": x[None]}, reward=jnp.zeros(()),
                     done=success | (step >= self.max_steps), success=success, step=step,
                     info={"body_pos": jnp.zeros((0, 3))})

    def reset(self, key):
        return self._state(jnp.zeros(()), jnp.zeros((), jnp.int32), jnp.zeros((), bool))

    def step(self, state, action):
        x = state.data.qpos[0]
        x = x + jnp.clip(action[0] - x, -1.0, 1.0)
        return self._state(x, state.step + 1, state.success | (x >= 7.0))

    def reach_error(self, state, action):
        return jnp.abs(state.data.qpos[0] - action[0])


def _toy_policy(history, key):
    """Targets 2 and 4 ahead of where the hand was last observed (the history's newest frame)."""
    x = history["state"][-1, 0]
    return PolicyOutput(actions=jnp.stack([x + 2.0, x + 4.0])[:, None], stride=jnp.int32(1),
                        entropy=jnp.zeros(()))


def _toy(semantics: Semantics):
    policy_fn, init_fn = stateless(_toy_policy, with_args=False)
    return evaluate_stateful(policy_fn, init_fn, ToyLine(), 1, jax.random.PRNGKey(0), history_len=1, chunk_len=2,
                             semantics=semantics)


def _counts(result):
    rec = result_record(result)
    return rec["decisions"][0], rec["actions"][0], rec["steps"][0]


def test_counts_on_a_toy_by_hand():
    # rate: x 0→1→2 | 3→4 | 5→6 | 7: 4 decisions, 7 actions, 7 control steps
    rate = _toy(Semantics("rate"))
    assert bool(rate.success[0]) and _counts(rate) == (4, 7, 7)
    # waypoint: decision 1 from 0: target 2 (2 steps), 4 (2 steps); decision 2 from 4 (one frame per action):
    # target 6 (2 steps), 8 (1 step: 7 is success, the episode ends): 2 decisions, 4 actions, 7 control steps
    way = _toy(Semantics("waypoint", tolerance=0.01, steps=3))
    assert bool(way.success[0]) and _counts(way) == (2, 4, 7)
    np.testing.assert_array_equal(np.asarray(way.executed)[0, :2], [4, 3])
    np.testing.assert_array_equal(np.asarray(way.actions)[0, :2], [2, 2])
    assert np.asarray(way.start)[0, 1] == 4
    summary = eval_summary(way)
    assert summary["mean_decisions"] == 2 and summary["mean_actions"] == 4 and summary["mean_steps"] == 7
    assert summary["mean_actions_per_decision"] == 2
    # a bound of one control step per waypoint (× stride 1) is the rate episode
    assert _counts(_toy(Semantics("waypoint", tolerance=0.01, steps=1))) == (4, 7, 7)


def test_waypoint_bound_scales_with_the_stride():
    def far(history, key):  # one target 10 ahead, at stride 2: at most 2·steps control steps
        x = history["state"][-1, 0]
        return PolicyOutput(actions=jnp.stack([x + 10.0])[:, None], stride=jnp.int32(2), entropy=jnp.zeros(()))

    policy_fn, init_fn = stateless(far, with_args=False)
    res = evaluate_stateful(policy_fn, init_fn, ToyLine(), 1, jax.random.PRNGKey(0), history_len=1, chunk_len=1,
                            semantics=Semantics("waypoint", tolerance=0.01, steps=2))
    np.testing.assert_array_equal(np.asarray(res.executed)[0, :2], [4, 3])  # 0→4 (bound 4), 4→7 (success)


def test_waypoint_equals_rate_when_every_target_is_reached_in_one_step():
    env = envs.make("press_button")
    policy_fn, init_fn = expert_policy(env, 8, stride=2)
    kw = dict(history_len=3, chunk_len=8, max_steps=40)
    rate, rate_rec = rollout_episodes(policy_fn, init_fn, env, 3, jax.random.PRNGKey(1), **kw)
    way, way_rec = rollout_episodes(policy_fn, init_fn, env, 3, jax.random.PRNGKey(1),
                                    semantics=Semantics("waypoint", tolerance=10.0, steps=3), **kw)
    for field in ("success", "steps", "valid", "start", "executed", "actions", "stride"):
        np.testing.assert_array_equal(np.asarray(getattr(way, field)), np.asarray(getattr(rate, field)), field)
    np.testing.assert_array_equal(np.asarray(rate.actions), np.asarray(rate.executed))  # rate: one step an action
    np.testing.assert_allclose(np.asarray(way_rec.qpos), np.asarray(rate_rec.qpos), atol=1e-5)


def test_controller_speed_bounds_the_hand_and_waypoints_wait_for_it():
    speed = 0.25
    env = envs.make("stack_cubes", controller_speed=speed)
    policy_fn, init_fn = expert_policy(env, 8, stride=3)
    kw = dict(history_len=1, chunk_len=8)
    way, rec = rollout_episodes(policy_fn, init_fn, env, 4, jax.random.PRNGKey(0),
                                semantics=Semantics("waypoint", tolerance=0.005, steps=3), **kw)
    # the hand moves at most v·dt a control step (a little servo slack)
    hand = np.asarray(rec.qpos)[:, :, env._hand_qadr]
    moves = np.linalg.norm(np.diff(hand, axis=1), axis=-1)
    assert moves.max() <= speed * env.control_dt * 1.05 + 1e-3
    # stride-3 targets are further apart than the controller goes in a step: more control steps than actions,
    # and the scripted stack still succeeds when each target is reached before the next
    rec_way = result_record(way)
    assert np.all(np.asarray(rec_way["steps"]) > np.asarray(rec_way["actions"]))
    assert float(way.success_rate) >= 0.75
    # the same targets at one control step each leave the hand behind them (the fingers close short of the cube)
    rate = evaluate_stateful(policy_fn, init_fn, env, 4, jax.random.PRNGKey(0), **kw)
    assert float(rate.success_rate) <= 0.25


def test_bad_settings_name_the_field():
    with pytest.raises(ValueError, match="inference.semantics: must be 'rate' or 'waypoint'"):
        InferenceConfig(semantics="teleport")
    with pytest.raises(ValueError, match=r"inference.waypoint_tolerance: \(m\) must be None \(the env"):
        InferenceConfig(waypoint_tolerance=0.0)
    with pytest.raises(ValueError, match="inference.waypoint_steps"):
        InferenceConfig(waypoint_steps=0)
    with pytest.raises(ValueError, match="inference.controller_speed"):
        InferenceConfig(controller_speed=-1.0)
    with pytest.raises(ValueError, match="controller_speed: must be None"):
        envs.make("press_button", controller_speed=0.0)
    with pytest.raises(ValueError, match="semantics: must be 'rate' or 'waypoint'"):
        _toy(Semantics("teleport"))
    # bounds left None are the env's own; given ones win
    env = envs.make("press_button")
    assert Semantics.of(InferenceConfig(semantics="waypoint"), env) == Semantics("waypoint", 0.005, 3)
    assert Semantics.of(InferenceConfig(semantics="waypoint", waypoint_steps=7), env).steps == 7


def test_rate_evaluation_keys_are_unchanged_and_other_semantics_get_their_own():
    col = Column("DP+HiPolicy")
    rate = json.loads(evaluation_key(InferenceConfig(), col, 100, 3))
    assert "semantics" not in rate and "controller_speed" not in rate
    way = json.loads(evaluation_key(InferenceConfig(semantics="waypoint"), col, 100, 3))
    assert way["semantics"] == "waypoint" and way["waypoint_tolerance"] is None and way["waypoint_steps"] is None
    way = json.loads(evaluation_key(InferenceConfig(semantics="waypoint", waypoint_tolerance=0.01), col, 100, 3))
    assert way["waypoint_tolerance"] == 0.01
    slow = json.loads(evaluation_key(InferenceConfig(controller_speed=0.25), col, 100, 3))
    assert slow["semantics"] == "rate" and slow["controller_speed"] == 0.25 and slow["waypoint_steps"] is None
    # what a compiled rollout depends on includes the semantics; what a sampler depends on does not
    inf = InferenceConfig(semantics="waypoint", controller_speed=0.2)
    assert inf.rollout_settings().semantics == "waypoint" and inf.rollout_settings().controller_speed == 0.2
    assert inf.sampler_settings() == InferenceConfig().sampler_settings()
    assert dataclasses.replace(inf, thresholds=(0.1, 0.2)).rollout_settings() == inf.rollout_settings()
