"""Batched evaluation: expert as a policy, history padding/order, masking of finished episodes, step limits."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax import envs
from hipolicy_jax.evaluation import rollout

CHUNK = 8
HIST = 3


def test_history_padding_and_order():
    obs0 = {"state": jnp.array([1.0, 2.0]), "image": jnp.zeros((2, 2, 3), jnp.uint8)}
    hist = rollout.init_history(obs0, 3)
    assert hist["state"].shape == (3, 2) and hist["image"].shape == (3, 2, 2, 3)
    np.testing.assert_array_equal(hist["state"], [[1, 2], [1, 2], [1, 2]])
    hist = rollout.push_history(hist, {"state": jnp.array([3.0, 4.0]), "image": jnp.ones((2, 2, 3), jnp.uint8)})
    np.testing.assert_array_equal(hist["state"], [[1, 2], [1, 2], [3, 4]])  # oldest first, newest last
    assert int(hist["image"][-1].sum()) == 12 and int(hist["image"][0].sum()) == 0


def test_expert_policy_evaluation_and_masking():
    env = envs.make("press_button")
    policy_fn, init_fn = rollout.expert_policy(env, CHUNK)
    res = rollout.evaluate_stateful(policy_fn, init_fn, env, 4, jax.random.PRNGKey(0), history_len=HIST,
                                    chunk_len=CHUNK)
    num_replans = -(-env.max_steps // CHUNK)
    assert res.entropy.shape == res.stride.shape == res.valid.shape == (4, num_replans)
    assert float(res.success_rate) == 1.0 and bool(res.success.all())
    steps = np.asarray(res.steps)
    assert (steps < env.max_steps).all()
    np.testing.assert_allclose(float(res.mean_steps_success), steps.mean(), rtol=1e-6)
    # an episode is valid at replan r iff it had not finished before the r-th chunk started
    r = np.arange(num_replans)
    np.testing.assert_array_equal(np.asarray(res.valid), r[None, :] * CHUNK < steps[:, None])
    valid = np.asarray(res.valid)
    assert (np.asarray(res.stride)[valid] == 1).all() and (np.asarray(res.entropy)[valid] == 0).all()
    # each decision started where the previous one ended and executed its whole chunk (the last one up to the end)
    start, executed = np.asarray(res.start), np.asarray(res.executed)
    for e in range(4):
        n = valid[e].sum()
        np.testing.assert_array_equal(start[e, :n], np.arange(n) * CHUNK)
        assert executed[e, :n].sum() == steps[e] and (executed[e, :n - 1] == CHUNK).all()


def test_stateless_policy_step_limit_and_history():
    env = envs.make("press_button")

    def hold_still(obs_history, key):
        # newest observation last; the policy keeps the hand where it is and records the history length
        tcp = obs_history["state"][-1, :3]
        action = jnp.concatenate([tcp, jnp.zeros((1,))])
        return rollout.PolicyOutput(actions=jnp.tile(action, (CHUNK, 1)), stride=jnp.int32(2),
                                    entropy=obs_history["state"].shape[0] * jnp.ones((), jnp.float32))

    res = rollout.evaluate(hold_still, env, 3, jax.random.PRNGKey(1), history_len=HIST, chunk_len=CHUNK,
                           max_steps=20)
    # 20 is not a multiple of the chunk: the last chunk is cut by masking, not executed past the limit
    np.testing.assert_array_equal(np.asarray(res.steps), [20, 20, 20])
    assert float(res.success_rate) == 0.0 and np.isnan(float(res.mean_steps_success))
    assert res.valid.shape == (3, 3) and bool(res.valid.all())
    assert (np.asarray(res.stride) == 2).all() and (np.asarray(res.entropy) == HIST).all()
    np.testing.assert_array_equal(np.asarray(res.executed), [[8, 8, 4]] * 3)


def test_policy_chunk_shape_is_checked():
    env = envs.make("press_button")

    def bad(obs_history, key):
        return rollout.PolicyOutput(actions=jnp.zeros((CHUNK + 1, 4)), stride=jnp.int32(1),
                                    entropy=jnp.zeros(()))

    with pytest.raises(ValueError, match="chunk_len"):
        rollout.evaluate(bad, env, 2, jax.random.PRNGKey(0), history_len=HIST, chunk_len=CHUNK)
    stateful, init_fn = rollout.stateless(bad, with_args=False)
    ro = rollout.Rollout(env, stateful, init_fn, history_len=HIST, chunk_len=CHUNK)
    for _ in range(2):  # a failed check is not remembered as passed
        with pytest.raises(ValueError, match="chunk_len"):
            ro(2, jax.random.PRNGKey(0))
    assert ro.traces == 0  # rejected before anything compiled


def test_rollout_object_owns_its_compile_and_checks_shapes_once_per_argument_shapes():
    """A ``Rollout`` compiles once for new arguments of the same shapes (trace counter), re-checks the policy's
    shapes only when the shapes of its traced arguments change (that a second object compiles on its own, i.e. that
    there is no global cache, is checked with the ``Evaluator`` in test_experiments.py)."""
    env = envs.make("press_button")
    policy_traces = []

    def scaled(obs_history, key, state, args):
        policy_traces.append(1)
        tcp = obs_history["state"][-1, :3]
        action = jnp.concatenate([tcp, jnp.zeros((1,))]) * args["scale"].mean()
        return rollout.PolicyOutput(actions=jnp.tile(action, (CHUNK, 1)), stride=jnp.int32(1),
                                    entropy=jnp.zeros(())), state

    ro = rollout.Rollout(env, scaled, rollout._no_state, history_len=HIST, chunk_len=CHUNK, max_steps=8)
    ro(2, jax.random.PRNGKey(0), {"scale": np.ones(3, np.float32)})
    assert ro.traces == 1 and len(policy_traces) == 2  # one shape check + one trace of the compiled rollout
    res, rec = ro(2, jax.random.PRNGKey(1), {"scale": np.full(3, 2.0, np.float32)})  # same shapes: no check, no trace
    assert ro.traces == 1 and len(policy_traces) == 2
    assert res.steps.shape == (2,) and rec.qpos.shape[:2] == (2, 9)
    ro(2, jax.random.PRNGKey(1), {"scale": np.ones(5, np.float32)})  # new shapes: checked and compiled again
    assert ro.traces == 2 and len(policy_traces) == 4


@pytest.mark.slow
def test_strided_expert_is_faster():
    """Executing the expert's plan at stride 2 finishes the door in about half the control steps."""
    env = envs.make("latch_door")
    results = {}
    for stride in (1, 2):
        policy_fn, init_fn = rollout.expert_policy(env, CHUNK, stride)
        results[stride] = rollout.evaluate_stateful(policy_fn, init_fn, env, 8, jax.random.PRNGKey(2),
                                                    history_len=HIST, chunk_len=CHUNK)
    assert float(results[1].success_rate) == 1.0 and float(results[2].success_rate) >= 0.75
    assert float(results[2].mean_steps_success) < 0.65 * float(results[1].mean_steps_success)


@pytest.mark.slow
@pytest.mark.parametrize("task", envs.TASKS)
def test_expert_success_100_seeds(task):
    env = envs.make(task)
    policy_fn, init_fn = rollout.expert_policy(env, CHUNK)
    res = rollout.evaluate_stateful(policy_fn, init_fn, env, 100, jax.random.PRNGKey(0), history_len=1,
                                    chunk_len=CHUNK)
    assert float(res.success_rate) >= 0.95
