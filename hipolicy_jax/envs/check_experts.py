"""Expert success over many seeds, compile times and env throughput for every task.

    python -m hipolicy_jax.envs.check_experts --episodes 100 --batches 1 64 256

Prints one line per task: expert success rate and mean episode length over ``--episodes`` seeds, the compile time
of ``jit(env.step)`` (batch 1) and of the batched expert rollout, and env control steps per second of
``jit(vmap(step))`` driven by the expert, at every batch size in ``--batches``.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax import envs as envs_lib
from hipolicy_jax.envs import demos


def step_compile_time(env) -> float:
    """Seconds to compile ``jit(env.step)`` for one instance."""
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    action = jnp.zeros((env.action_dim,), jnp.float32)
    t0 = time.perf_counter()
    jax.jit(env.step).lower(state, action).compile()
    return time.perf_counter() - t0


def throughput(env, batch: int, steps: int = 20, repeats: int = 2) -> float:
    """Env control steps per second of ``jit(vmap(step))`` at ``batch``, actions from the expert plans."""

    def init(key):
        k1, k2 = jax.random.split(key)
        state = env.reset(k1)
        return state, env.expert_plan(state.obs["state"], k2)

    def advance(state, plan):
        def body(s, t):
            return env.step(s, env.expert_action(plan, t)), None

        state, _ = jax.lax.scan(body, state, state.step.astype(jnp.float32) + jnp.arange(steps, dtype=jnp.float32))
        return state

    keys = jax.device_put(jax.random.split(jax.random.PRNGKey(1), batch))
    state, plan = jax.jit(jax.vmap(init))(keys)
    fn = jax.jit(jax.vmap(lambda s, p: advance(s, p)))
    state = jax.block_until_ready(fn(state, plan))  # compile
    t0 = time.perf_counter()
    for _ in range(repeats):
        state = fn(state, plan)
    jax.block_until_ready(state)
    return batch * steps * repeats / (time.perf_counter() - t0)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="*", default=list(envs_lib.TASKS))
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--batches", type=int, nargs="*", default=[1, 64, 256])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    print(f"devices: {jax.devices()}")
    for task in args.tasks:
        run = demos.expert_rollout(task, args.episodes)
        env = run.env
        t_step = step_compile_time(env)
        keys = jax.device_put(jax.random.split(jax.random.PRNGKey(args.seed), args.episodes))
        t0 = time.perf_counter()
        compiled = run.jitted.lower(keys).compile()
        t_roll = time.perf_counter() - t0
        t0 = time.perf_counter()
        trace = jax.block_until_ready(compiled(keys))
        t_run = time.perf_counter() - t0
        success = np.asarray(trace.success)
        steps = np.asarray(trace.steps)
        finite = bool(np.isfinite(np.asarray(trace.obs["state"])).all())
        line = (f"{task:13s} expert success {success.mean() * 100:5.1f}% ({success.sum()}/{success.size}), "
                f"steps mean {steps[success].mean():.1f} [{steps[success].min()}-{steps[success].max()}], "
                f"finite {finite}, compile step {t_step:.1f}s rollout {t_roll:.1f}s, "
                f"rollout run {t_run:.1f}s")
        print(line, flush=True)
        rates = [f"B={b}: {throughput(env, b):.0f}" for b in args.batches]
        print(f"{task:13s} env steps/s " + ", ".join(rates), flush=True)


if __name__ == "__main__":
    main()
