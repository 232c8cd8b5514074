"""Execution strategies: AAC's chunk size and temporal ensembling against closed forms; the episode loop runs
variable-length decisions."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax import envs
from hipolicy_jax.config import ChunkConfig, InferenceConfig
from hipolicy_jax.evaluation import execution, rollout
from hipolicy_jax.sampling import action_entropy


@pytest.mark.parametrize("h,k", [([0, 0, 0, 5, 5, 5, 5, 5], 3),  # uncertainty jumps after step 3
                                 ([1, 1, 1, 1], 4),  # flat: the whole chunk
                                 ([3, 2, 1, 0], 4),  # falling: the whole chunk
                                 ([0, 9, 9, 9], 1),  # uncertain from step 2 on: one action
                                 ([2.0], 1)])
def test_aac_chunk_size_closed_forms(h, k):
    assert int(execution.aac_chunk_size(jnp.asarray(h, jnp.float32))) == k


def test_step_entropies_average_to_the_sampler_entropy():
    x = jax.random.normal(jax.random.key(0), (16, 8, 3)) * jnp.linspace(0.1, 1.0, 8)[None, :, None]
    h = execution.step_entropies(x)
    assert h.shape == (8,) and bool(jnp.all(jnp.diff(h) > 0))  # the spread grows along the chunk
    np.testing.assert_allclose(float(h.mean()), float(action_entropy(x)), rtol=1e-5)


def _decision(actions, stride=1, entropy=0.0):
    actions = jnp.asarray(actions, jnp.float32)
    return execution.Decision(chunks=actions[None], entropy=jnp.float32(entropy), freq_index=jnp.int32(0),
                              stride=jnp.int32(stride), actions=actions)


def test_temporal_ensembling_weights_closed_form():
    """ACT's weights exp(-m·i), i = 0 for the oldest of the stored predictions of the current step."""
    m, chunk = 0.5, ChunkConfig(strides=(1,), chunk_len=3)
    te = execution.TemporalEnsembling(decay=m)
    state = te.init(chunk, 1)
    out, state = te.decide(_decision([[1.0], [2.0], [3.0]]), state, chunk)
    assert out.actions.shape == (1, 1) and int(out.num_actions) == 1 and float(out.actions[0, 0]) == 1.0
    out, state = te.decide(_decision([[10.0], [20.0], [30.0]]), state, chunk)
    w = math.exp(-m)  # the newest prediction (10) is one step younger than the oldest (2)
    assert float(out.actions[0, 0]) == pytest.approx((2.0 + w * 10.0) / (1.0 + w), rel=1e-6)
    out, state = te.decide(_decision([[100.0], [0.0], [0.0]]), state, chunk)
    expect = (3.0 + math.exp(-m) * 20.0 + math.exp(-2 * m) * 100.0) / (1 + math.exp(-m) + math.exp(-2 * m))
    assert float(out.actions[0, 0]) == pytest.approx(expect, rel=1e-6)
    out, state = te.decide(_decision([[7.0], [0.0], [0.0]]), state, chunk)  # the first chunk no longer covers t
    expect = (30.0 + math.exp(-m) * 0.0 + math.exp(-2 * m) * 7.0) / (1 + math.exp(-m) + math.exp(-2 * m))
    assert float(out.actions[0, 0]) == pytest.approx(expect, rel=1e-6) and int(state.count) == 3


def test_chunk_and_aac_decide():
    chunk = ChunkConfig(strides=(1,), chunk_len=4)
    samples = jnp.stack([jnp.zeros((4, 2)), jnp.concatenate([jnp.zeros((2, 2)), jnp.ones((2, 2))])])
    d = execution.Decision(chunks=samples, entropy=jnp.float32(0.0), freq_index=jnp.int32(0), stride=jnp.int32(1),
                           actions=samples[0])
    out, _ = execution.ChunkExecution().decide(d, (), chunk)
    assert int(out.num_actions) == 4
    out, _ = execution.AdaptiveChunking().decide(d, (), chunk)
    assert int(out.num_actions) == 2  # the samples agree on 2 steps, then split
    with pytest.raises(ValueError, match="inference.execution: 'aac' reads the entropy of N >= 2"):
        execution.make_execution(InferenceConfig(execution="aac", num_samples=1))


@pytest.mark.parametrize("freq_index,k", [(0, 4), (1, 3), (2, 1)])
def test_chunk_and_aac_read_the_selected_frequency(freq_index, k):
    """Strides (1, 2, 3), L_c = 4: AAC sizes the decision from the SELECTED frequency's segment of the N samples.

    Two samples; sample 1 = sample 0 + 1 on the steps where they split, so per step var = 0 (h = ½·log ε) where they
    agree and var = ½ (h = ½·log(πe + ε)) where they split. Segments in descending-stride order:
      - stride 3 (index 2, chunk steps 0..3): split from step 2 on: h = (c, v, v, v), H(k) = (c, (c+v)/2,
        (c+2v)/3, (c+3v)/4), jumps (v−c)/2 > (v−c)/6 > (v−c)/12 → k* = 1;
      - stride 2 (index 1, chunk steps 4..7): split on step 4 only: h = (c, c, c, v), jumps (0, 0, (v−c)/4) → k* = 3;
      - stride 1 (index 0, chunk steps 8..11): never split: H flat, no jump > 0 → k* = L_c = 4.
    Both strategies execute sample 0's chunk at the selected frequency (``Decision.actions``) at its stride; chunk
    execution runs all L_c = 4 of it whatever the frequency."""
    chunk = ChunkConfig(strides=(1, 2, 3), chunk_len=4)
    base = jnp.arange(12, dtype=jnp.float32)[:, None] * jnp.ones((1, 2))  # (M·L_c, A): action t = (t, t)
    split = jnp.zeros(12).at[jnp.array([1, 2, 3, 7])].set(1.0)[:, None]  # where sample 1 departs from sample 0
    samples = jnp.stack([base, base + split])  # (N=2, 12, 2)
    segment = 2 - freq_index  # frequency index k lives in segment M−1−k
    actions = samples[0, 4 * segment:4 * segment + 4]
    stride = (1, 2, 3)[freq_index]
    d = execution.Decision(chunks=samples, entropy=jnp.float32(-1.0), freq_index=jnp.int32(freq_index),
                           stride=jnp.int32(stride), actions=actions)
    np.testing.assert_array_equal(np.asarray(actions[:, 0]), 4 * segment + np.arange(4))  # the hand-made layout
    out, _ = execution.ChunkExecution().decide(d, (), chunk)
    assert int(out.num_actions) == 4 and int(out.stride) == stride
    np.testing.assert_array_equal(np.asarray(out.actions), np.asarray(actions))
    out, _ = execution.AdaptiveChunking().decide(d, (), chunk)
    assert int(out.num_actions) == k and int(out.stride) == stride and float(out.entropy) == -1.0
    executed = np.asarray(out.actions)[:int(out.num_actions), 0]
    np.testing.assert_array_equal(executed, 4 * segment + np.arange(k))  # e.g. index 1: chunk steps 4, 5, 6


def test_episode_loop_executes_the_decided_number_of_actions():
    """A policy that asks for 1, 2, 3, 1, 2, 3, ... actions: decisions start where the previous ones ended."""
    env = envs.make("press_button")

    def policy(obs_history, key, count, args):
        tcp = obs_history["state"][-1, :3]
        action = jnp.concatenate([tcp, jnp.zeros((1,))])
        n = count % 3 + 1
        return rollout.PolicyOutput(jnp.tile(action, (4, 1)), jnp.int32(1), jnp.float32(n), n), count + 1

    res = rollout.evaluate_stateful(policy, lambda obs, key: jnp.zeros((), jnp.int32), env, 2, jax.random.key(0),
                                    history_len=1, chunk_len=4, max_steps=11, min_actions=1)
    valid = np.asarray(res.valid)
    assert res.valid.shape == (2, 11) and valid.sum(axis=1).tolist() == [6, 6]
    np.testing.assert_array_equal(np.asarray(res.start)[0, :6], [0, 1, 3, 6, 7, 9])
    np.testing.assert_array_equal(np.asarray(res.executed)[0, :6], [1, 2, 3, 1, 2, 2])  # the last one hits the limit
    np.testing.assert_array_equal(np.asarray(res.steps), [11, 11])


def test_delayed_chunk_executes_the_committed_actions_then_the_new_chunk_from_d():
    """Asynchronous execution, d = 2, L_c = 4: the first decision runs C[0:2] and commits C[2:4]; every later one
    runs the committed pair, then nothing more of its own chunk (L_c − d = 2), and commits its C[2:4]."""
    chunk = ChunkConfig(strides=(1,), chunk_len=4)
    # d = 0 is synchronous execution: the plain chunk strategy, the same code path as without the setting
    assert execution.make_execution(InferenceConfig(delay=0)) == execution.make_execution(InferenceConfig())
    assert isinstance(execution.make_execution(InferenceConfig(delay=0, handover="inpaint")), execution.ChunkExecution)
    ex = execution.make_execution(InferenceConfig(delay=2))
    assert isinstance(ex, execution.DelayedChunk) and ex.min_actions(chunk) == 2 and ex.prefix(None) is None
    state = ex.init(chunk, 1)
    out, state = ex.decide(_decision([[0.0], [1.0], [2.0], [3.0]]), state, chunk)
    assert int(out.num_actions) == 2 and out.actions[:2, 0].tolist() == [0.0, 1.0]
    assert state.pending[:, 0].tolist() == [2.0, 3.0] and bool(state.valid)
    out, state = ex.decide(_decision([[10.0], [11.0], [12.0], [13.0]]), state, chunk)
    assert out.actions[:2, 0].tolist() == [2.0, 3.0] and state.pending[:, 0].tolist() == [12.0, 13.0]
    ex1 = execution.make_execution(InferenceConfig(delay=1, handover="inpaint"))
    state = ex1.init(chunk, 1)
    _, state = ex1.decide(_decision([[0.0], [1.0], [2.0], [3.0]]), state, chunk)
    out, state = ex1.decide(_decision([[10.0], [11.0], [12.0], [13.0]]), state, chunk)
    assert int(out.num_actions) == 3 and out.actions[:3, 0].tolist() == [3.0, 11.0, 12.0]
    pending, valid = ex1.prefix(state)
    assert pending[:, 0].tolist() == [13.0] and bool(valid)
    with pytest.raises(ValueError, match=r"inference.delay: .* 1 <= d <= exec_steps/2 = 2, got 3"):
        execution.make_execution(InferenceConfig(delay=3)).init(chunk, 1)
    with pytest.raises(ValueError, match="inference.delay: asynchronous execution runs whole chunks"):
        InferenceConfig(delay=1, execution="te")


def test_delayed_decisions_start_every_chunk_len_minus_d_steps():
    """In the episode loop a delay-d policy decides every L_c − d control steps, each executing L_c − d actions."""
    env = envs.make("press_button")
    chunk = ChunkConfig(strides=(1,), chunk_len=4)
    ex = execution.make_execution(InferenceConfig(delay=1))

    def policy(obs_history, key, state, args):
        tcp = obs_history["state"][-1, :3]
        actions = jnp.tile(jnp.concatenate([tcp, jnp.zeros((1,))]), (4, 1))
        return ex.decide(_decision(actions), state, chunk)

    res = rollout.evaluate_stateful(policy, lambda obs, key: ex.init(chunk, 4), env, 2, jax.random.key(0),
                                    history_len=1, chunk_len=4, max_steps=10, min_actions=ex.min_actions(chunk))
    assert res.valid.shape == (2, 4) and np.asarray(res.valid).sum(axis=1).tolist() == [4, 4]
    np.testing.assert_array_equal(np.asarray(res.start)[0], [0, 3, 6, 9])
    np.testing.assert_array_equal(np.asarray(res.executed)[0], [3, 3, 3, 1])


@pytest.mark.parametrize("handover", ["inpaint", "naive"])
def test_inpaint_handover_starts_the_new_chunk_on_the_committed_actions(handover, monkeypatch):
    """Delay d = 2, L_c = 4, strides (1, 2, 3), through ``make_policy_fn`` and the real sampler (the fake network of
    test_sampling, DDIM, N = 3): the first decision commits sample 0's C[2:4] at its selected frequency. With
    ``handover='inpaint'`` the next decision's chunks start on exactly those d actions in every sample and at every
    frequency; with 'naive' they are sampled freely and start elsewhere. Either way the robot runs the committed
    actions while the decision is computed."""
    from test_sampling import RELEASE, AffineNormalizer, FakeNet, _cfg

    from hipolicy_jax.evaluation import policy as policy_lib

    cfg = _cfg()  # strides (1, 2, 3), L_c = 4, sample prediction
    inference = InferenceConfig(num_samples=3, sampler="ddim", num_steps=3, delay=2, handover=handover)
    results, sample = [], policy_lib.sample  # every SampleResult the policy's sampler returns (it runs eagerly)

    def spy(*args, **kwargs):
        results.append(sample(*args, **kwargs))
        return results[-1]

    monkeypatch.setattr(policy_lib, "sample", spy)
    policy_fn, init_fn = policy_lib.make_policy_fn(FakeNet(), cfg, 2, inference)
    args = policy_lib.PolicyArgs({"w": jnp.float32(0.5), "v": jnp.float32(0.3)}, AffineNormalizer(jnp.float32(2.0)),
                                 RELEASE)
    span = cfg.chunk.obs_span
    history = {"state": jnp.linspace(0.0, 1.0, span * 5, dtype=jnp.float32).reshape(span, 5)}
    state = init_fn(None, jax.random.key(0))
    out, state = policy_fn(history, jax.random.key(1), state, args)
    committed = np.asarray(results[-1].actions[0, 2:4])  # sample 0 at the selected frequency, steps 2, 3
    np.testing.assert_array_equal(np.asarray(state.pending), committed)
    out, state = policy_fn(jax.tree.map(lambda x: x + 0.1, history), jax.random.key(2), state, args)
    assert len(results) == 2
    np.testing.assert_array_equal(np.asarray(out.actions[:2]), committed)  # run while the decision is computed
    segments = np.asarray(results[-1].chunks[0]).reshape(3, 3, 4, 2)  # (N, M, L_c, A)
    gap = np.abs(segments[:, :, :2] - committed).max(axis=-1)  # (N, M, d): every sample, frequency, prefix step
    if handover == "inpaint":
        assert gap.max() < 1e-5, gap  # the last renoise writes the clean prefix (float32 normalise / unnormalise)
    else:
        assert gap.min() > 1e-2, gap
