"""Train-step throughput: steps/s and samples/s of ``training.make_train_step`` per config, and its compile time.

    python -m benchmarks.train_step                              # CPU default: cpu size, state obs, batch 128
    python -m benchmarks.train_step --sizes cpu paper --obs state image pointcloud     # GPU grid
    python -m benchmarks.train_step --obs pointcloud --num-points 128 512 --batch 64   # DP3 point budgets

The step is the real one (AdamW + cosine schedule + EMA, the train state donated) on a synthetic normalised batch
of ``--batch`` windows; the first call's time (trace + compile + one step) and the ``lower().compile()`` time are
reported separately from the steady-state median.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from benchmarks.common import (ACTION_DIM, base_parser, example_obs, device_kind, latency_stats, make_bench_policy,
                               markdown_table, param_count, precision_context, timed_calls, report_rows)
from hipolicy_jax.config import TrainConfig
from hipolicy_jax.training import init_train_state, make_optimizer, make_train_step

NAME = "train_step"


def parse_args(argv=None) -> argparse.Namespace:
    cpu = device_kind() == "cpu"
    p = base_parser(NAME, __doc__, grid=True)
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--num-points", type=int, nargs="+", default=[512], help="point-cloud sizes (pointcloud rows)")
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--row-budget-s", type=float, default=30.0 if cpu else None)
    p.add_argument("--quick", action="store_true", help="cpu size, state obs, 5 repeats")
    args = p.parse_args(argv)
    if args.quick:
        args.sizes, args.obs, args.repeats = ["cpu"], ["state"], 5
    return args


def synthetic_batch(cfg, batch: int, key: jax.Array) -> dict:
    """A normalised training batch ``{"obs": {k: (B, M, L_h, ...)}, "action": (B, M·L_c, A)}`` in [-1, 1]."""
    k1, k2 = jax.random.split(key)
    obs = jax.tree.map(lambda a: 2.0 * a - 1.0 if a.ndim == 4 else a, example_obs(cfg, batch, k1))
    action = jax.random.uniform(k2, (batch, cfg.chunk.horizon, ACTION_DIM), minval=-1.0, maxval=1.0)
    return {"obs": obs, "action": action}


def bench_config_row(size: str, obs: str, args, points: int | None = None) -> dict:
    """Compile time, first-step time and steady-state step latency of one config (``points``: point-cloud size)."""
    policy = make_bench_policy(size, obs, **({} if points is None else {"encoder.num_points": points}))
    train_cfg = TrainConfig(batch_size=args.batch, num_steps=10_000, warmup_steps=10)
    tx = make_optimizer(train_cfg)
    step = make_train_step(policy.net, policy.cfg, train_cfg, tx)
    batch = synthetic_batch(policy.cfg, args.batch, jax.random.key(1))
    key = jax.random.key(2)
    holder = {"state": init_train_state(policy.params, tx)}

    def one(i):
        holder["state"], metrics = step(holder["state"], batch, key)  # the state is donated: keep only the new one
        return metrics["loss"]

    with precision_context(args.matmul_precision):
        t0 = time.perf_counter()
        step.lower(holder["state"], batch, key).compile()
        compile_s = time.perf_counter() - t0
        times, first = timed_calls(one, 0, warmup=1)  # first call: trace + compile (again, jit's cache) + run
        cache = step._cache_size()
        times, _ = timed_calls(one, args.repeats, args.row_budget_s, warmup=0)
        retraces = step._cache_size() - cache
    stats = latency_stats(times)
    loss = float(one(0))
    return {"size": size, "obs": obs, "points": points, "batch": args.batch, "params": param_count(policy.params),
            **stats,
            "steps_per_s": 1.0 / stats["median_s"], "samples_per_s": args.batch / stats["median_s"],
            "compile_s": compile_s, "first_step_s": first, "retraces": retraces, "final_loss": loss,
            "loss_finite": bool(np.isfinite(loss))}


def main(argv=None) -> dict:
    args = parse_args(argv)
    rows = []
    for size in args.sizes:
        for obs, points in [(o, p) for o in args.obs for p in (args.num_points if o == "pointcloud" else [None])]:
            r = bench_config_row(size, obs, args, points)
            rows.append(r)
            name = f"{size}/{obs}" + ("" if points is None else f"/{points} points")
            print(f"[{name}] batch {r['batch']}: {r['median_s'] * 1e3:.1f} ms/step, {r['steps_per_s']:.2f} "
                  f"steps/s, {r['samples_per_s']:.0f} samples/s, compile {r['compile_s']:.1f} s, first step "
                  f"{r['first_step_s']:.1f} s", flush=True)
    table = markdown_table(
        ["size", "obs", "points", "params", "batch", "median ms", "p90 ms", "steps/s", "samples/s", "compile s",
         "first step s"],
        [[r["size"], r["obs"], "–" if r["points"] is None else r["points"], f"{r['params']:,}", r["batch"],
          r["median_s"] * 1e3, r["p90_s"] * 1e3, r["steps_per_s"], r["samples_per_s"], r["compile_s"],
          r["first_step_s"]] for r in rows])
    return report_rows(NAME, argv, args, rows, table)


if __name__ == "__main__":
    main()
