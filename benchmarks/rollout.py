"""Closed-loop rollout throughput: control (env) steps per second of batched MJX rollouts with the policy in the loop.

    python -m benchmarks.rollout                         # CPU default: press_button, cpu size, N=4, DDIM 10
    python -m benchmarks.rollout --num-samples 100 --sampler ddpm --num-steps 100 --batches 1 16 100   # GPU

Uses the evaluation path itself: an ``evaluation.Evaluator`` (one compiled rollout per episode count) with an
initialised (untrained) policy. Control steps executed are counted from the result
(``EvalResult.steps``: an episode stops early only if it succeeds), so steps/s is exact even when some finish.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from benchmarks.common import (base_parser, device_kind, latency_stats, make_bench_policy, markdown_table, precision_context,
                               timed_calls, report_rows)
from hipolicy_jax import envs
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.evaluation import Evaluator

NAME = "rollout"


def parse_args(argv=None) -> argparse.Namespace:
    cpu = device_kind() == "cpu"
    p = base_parser(NAME, __doc__)
    p.add_argument("--task", default="press_button")
    p.add_argument("--size", default="cpu", choices=["tiny", "cpu", "paper"])
    p.add_argument("--batches", nargs="+", type=int, default=[1, 16, 100], help="episodes per rollout")
    p.add_argument("--num-samples", type=int, default=4 if cpu else 100, help="N samples per replan")
    p.add_argument("--sampler", default="ddim" if cpu else "ddpm", choices=["ddpm", "ddim"])
    p.add_argument("--num-steps", type=int, default=10 if cpu else 100, help="reverse steps per replan")
    p.add_argument("--max-steps", type=int, default=48 if cpu else None,
                   help="control steps per episode (default: the task's limit on a GPU, 48 on a CPU)")
    p.add_argument("--repeats", type=int, default=3 if cpu else 10)
    p.add_argument("--row-budget-s", type=float, default=60.0 if cpu else None)
    p.add_argument("--quick", action="store_true", help="batches 1 and 16, 24 control steps, 2 repeats")
    args = p.parse_args(argv)
    if args.quick:
        args.batches, args.max_steps, args.repeats = [1, 16], 24, 2
    return args


def main(argv=None) -> dict:
    args = parse_args(argv)
    env = envs.make(args.task)
    policy = make_bench_policy(args.size, "state", state_dim=env.state_dim, action_dim=env.action_dim)
    cfg = policy.cfg
    inference = InferenceConfig(num_samples=args.num_samples, sampler=args.sampler, num_steps=args.num_steps)
    evaluator = Evaluator(env, cfg, env.action_dim, inference, max_steps=args.max_steps)
    rows = []
    for e in args.batches:
        steps_done = {}

        def run(i, e=e):
            res = evaluator.evaluate(policy.params, policy.normalizer, e, jax.random.key(1000 + i))
            steps_done[i] = res.steps
            return res

        with precision_context(args.matmul_precision):
            times, first = timed_calls(run, args.repeats, args.row_budget_s, warmup=1, min_calls=1)
        control_steps = [int(np.sum(steps_done[i])) for i in range(len(times))]
        stats = latency_stats(times)
        sps = float(np.median([s / t for s, t in zip(control_steps, times)]))
        chunk = cfg.chunk.chunk_len
        r = {"episodes": e, **stats, "compile_s": first, "control_steps": control_steps,
             "env_steps_per_s": sps, "replans_per_s": sps / chunk,
             "samples_per_s": sps / chunk * args.num_samples}
        rows.append(r)
        print(f"E={e:<4} {stats['median_s']:.2f} s/rollout  {sps:8.1f} env steps/s  "
              f"{control_steps[0]} control steps  first call {first:.1f} s", flush=True)
    table = markdown_table(["episodes", "median s", "control steps", "env steps/s", "replans/s", "samples/s",
                            "first call s"],
                           [[r["episodes"], r["median_s"], r["control_steps"][0], r["env_steps_per_s"],
                             r["replans_per_s"], r["samples_per_s"], r["compile_s"]] for r in rows])
    return report_rows(NAME, argv, args, rows, table, task=args.task, chunk_len=cfg.chunk.chunk_len)


if __name__ == "__main__":
    main()
