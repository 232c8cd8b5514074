"""The compacted rollout (``Rollout(compact=True)``, the ``Evaluator``'s default) against the vmapped episode of
every episode (``compact=False``, the rollout the campaigns' records were made with): the same per-episode success,
steps and decisions on the same keys; bit for bit the same when one block holds every episode.

The policy is a tiny real one (the sampler of an untrained tiny network and an execution strategy) steered by the
scripted expert, so episodes succeed at different control steps and finished episodes drop out of the batch; the
network's actions perturb the expert's, so the outcomes read the sampler.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.common import make_bench_policy
from hipolicy_jax import envs
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.evaluation import rollout
from hipolicy_jax.evaluation.execution import make_execution
from hipolicy_jax.evaluation.policy import PolicyArgs, make_policy_fn

EPISODES, MAX_STEPS = 6, 72


def guided_policy(execution: str, perturb: float = 0.003):
    """(env, policy_fn, init_fn, PolicyArgs, Rollout kwargs, N) of the expert-steered tiny policy."""
    env = envs.make("press_button")
    pol = make_bench_policy("tiny", "state", state_dim=env.state_dim, action_dim=env.action_dim)
    inference = InferenceConfig(num_samples=4, sampler="ddim", num_steps=2, execution=execution)
    strategy = make_execution(inference)
    net_fn, net_init = make_policy_fn(pol.net, pol.cfg, env.action_dim, inference)
    exec_len = strategy.exec_len(pol.cfg.chunk)

    def init_fn(obs, key):
        return net_init(obs, key), env.expert_plan(obs["state"], key), jnp.zeros((), jnp.float32)

    def policy_fn(history, key, pstate, args):
        ex_state, plan, t = pstate
        out, ex_state = net_fn(history, key, ex_state, args)
        expert = jax.vmap(lambda s: env.expert_action(plan, t + s))(jnp.arange(exec_len, dtype=jnp.float32))
        n = exec_len if out.num_actions is None else out.num_actions
        return out._replace(actions=expert + perturb * jnp.tanh(out.actions)), (ex_state, plan, t + n)

    thresholds = np.array([-np.inf, -0.5, 0.5, np.inf], np.float32)  # the tiny net's entropies select all strides
    kwargs = dict(history_len=pol.cfg.chunk.obs_span, chunk_len=exec_len, max_steps=MAX_STEPS,
                  min_actions=strategy.min_actions(pol.cfg.chunk))
    return env, policy_fn, init_fn, PolicyArgs(pol.params, pol.normalizer, thresholds), kwargs, 4


def _outcomes(res):
    return {k: np.asarray(getattr(res, k)) for k in ("success", "steps", "valid", "start", "executed", "stride")}


def _run(execution, block):
    env, policy_fn, init_fn, args, kwargs, n = guided_policy(execution)
    old = rollout.Rollout(env, policy_fn, init_fn, **kwargs)
    new = rollout.Rollout(env, policy_fn, init_fn, compact=True, block=block, rows_per_episode=n, **kwargs)
    key = jax.random.key(3)
    return old(EPISODES, key, args), new(EPISODES, key, args), new, args


def _assert_same_outcomes(a, b):
    for k, v in _outcomes(a).items():
        np.testing.assert_array_equal(v, _outcomes(b)[k], err_msg=k)


def test_default_block_keeps_blocks_large():
    assert rollout.default_block(6, min_rows=160) == 6  # few rows: one block, the vmapped episode's batch
    assert rollout.default_block(20, 16, min_rows=160) == 10  # 320 sampler rows: two blocks of 160
    assert rollout.default_block(100, 16, min_rows=160) == 10 and rollout.default_block(100, 100, min_rows=160) == 2
    assert rollout.default_block(100, 1, min_rows=160) == 100 and rollout.default_block(1000, 1, min_rows=160) == 167
    assert rollout.default_block(1, 100, min_rows=160) == 1 and rollout.default_block(7, 50, min_rows=160) == 4
    assert rollout.default_block(100, 100, min_rows=8192) == 100  # an accelerator: one block up to 8192 rows


def test_one_block_is_the_vmapped_rollout_bit_for_bit_and_compiles_once():
    """Chunk execution, one block of every episode (the default for few sampler rows): the same results bit for bit
    (entropies, recorded joint positions) although finished episodes are gathered out of the batch; a second call
    with new arguments of the same shapes does not retrace."""
    (res_old, rec_old), (res_new, rec_new), new, args = _run("chunk", None)
    assert new.block_for(EPISODES) == EPISODES
    steps = np.asarray(res_old.steps)
    assert bool(res_old.success.any()) and len(set(steps.tolist())) > 1  # episodes end at different steps
    _assert_same_outcomes(res_old, res_new)
    np.testing.assert_array_equal(np.asarray(res_new.entropy), np.asarray(res_old.entropy))
    np.testing.assert_array_equal(np.asarray(rec_new.qpos), np.asarray(rec_old.qpos))
    np.testing.assert_array_equal(np.asarray(rec_new.body_pos), np.asarray(rec_old.body_pos))
    assert new.traces == 1
    new(EPISODES, jax.random.key(4), args._replace(params=jax.tree.map(lambda x: x * 1.01, args.params)))
    assert new.traces == 1  # retrace guard: same shapes, same compile


def test_blocks_of_running_episodes_keep_every_outcome_aac():
    """AAC (decisions of 1..L_c actions, so episodes fall out of step and the control steps stop early), blocks of
    two episodes: the same success, steps, decisions, their starts, executed actions and strides."""
    (res_old, _), (res_new, _), new, _ = _run("aac", 2)
    assert new.block_for(EPISODES) == 2
    valid = np.asarray(res_old.valid)
    assert len(set(valid.sum(axis=1).tolist())) > 1  # episodes take different numbers of decisions
    _assert_same_outcomes(res_old, res_new)
    np.testing.assert_allclose(np.asarray(res_new.entropy)[valid], np.asarray(res_old.entropy)[valid], rtol=1e-4)
    assert new.traces == 1


@pytest.mark.slow
@pytest.mark.parametrize("execution", ["chunk", "te"])
def test_blocks_of_running_episodes_keep_every_outcome(execution):
    (res_old, _), (res_new, _), _, _ = _run(execution, 2)
    _assert_same_outcomes(res_old, res_new)


@pytest.mark.slow
@pytest.mark.parametrize("execution", ["chunk", "aac"])
def test_hundred_episodes_of_a_trained_run(tmp_path, execution):
    """A trained run (demos → 1,000 training steps of a tiny network, as ``experiments.train`` makes it) evaluated on
    100 episodes with the campaigns' sampler (N = 16, DDIM 10: 1,600 sampler rows, so blocks of 10 episodes): the
    vmapped rollout and the compacted one, from the campaign's first evaluation key. One block of every episode is
    the vmapped rollout bit for bit; blocks of 10 run the sampler at another batch size, whose float32 rounding
    differs in the last bits (≤ 1e-5 in the actions), so an episode at a knife's edge may go another way — at most
    5 of 100, and the success rate within 5 points. A compaction that mixed up episodes, keys or policy state would
    change most of them."""
    from hipolicy_jax.config import EvalConfig, ModelConfig, PolicyConfig, TrainConfig
    from hipolicy_jax.evaluation.evaluator import Evaluator
    from hipolicy_jax.runs.store import eval_key, load_run
    from hipolicy_jax.runs.train import RunConfig, main

    inference = InferenceConfig(num_samples=16, sampler="ddim", num_steps=10, execution=execution)
    main(RunConfig(task="latch_door", out=str(tmp_path / "run"), data=str(tmp_path / "demos.zarr"), episodes=20,
                   policy=PolicyConfig(model=ModelConfig(size="tiny", fusion_heads=2)),
                   train=TrainConfig(batch_size=32, num_steps=1000, warmup_steps=50, log_every=500, ckpt_every=1000),
                   eval=EvalConfig(episodes=1, every=0), inference=inference, progress=False))
    run = load_run(str(tmp_path / "run"))
    p, key = run.policy, eval_key(0)
    results = {}
    for name, compact, block in (("vmapped", False, None), ("one block", True, 100), ("blocks", True, None)):
        ev = Evaluator("latch_door", p.cfg, run.action_dim, inference, compact=compact)
        ev._rollout.block = block
        assert ev._rollout.block_for(100) == (None if not compact else block or 10)
        results[name] = ev.rollout(p.params, p.normalizer, 100, key, entropy_guided=False)[0]  # highest frequency
    old = results["vmapped"]
    steps = np.asarray(old.steps)
    assert float(old.success_rate) >= 0.05 and len(set(steps.tolist())) > 5, (old.success_rate, steps)
    _assert_same_outcomes(old, results["one block"])
    np.testing.assert_array_equal(np.asarray(results["one block"].entropy), np.asarray(old.entropy))
    new = results["blocks"]
    same = (np.asarray(new.success) == np.asarray(old.success)) & (np.asarray(new.steps) == steps)
    assert same.sum() >= 95, np.flatnonzero(~same)
    assert abs(float(new.success_rate) - float(old.success_rate)) <= 0.05
