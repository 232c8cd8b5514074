"""Train-step throughput: steps/s and samples/s of ``training.make_train_step`` per config, and its compile time.

    python -m benchmarks.train_step                              # CPU default: cpu size, state obs, batch 128
    python -m benchmarks.train_step --sizes cpu paper --obs state image pointcloud     # GPU grid
    python -m benchmarks.train_step --obs pointcloud --num-points 128 512 --batch 64   # DP3 point budgets
    python -m benchmarks.train_step --shapes dp-lowdim hipolicy hipolicy-nofusion   # the PyTorch comparison's shapes

The step is the real one (AdamW + cosine schedule + EMA, the train state donated) on a synthetic normalised batch
of ``--batch`` windows; the first call's time (trace + compile + one step) and the ``lower().compile()`` time are
reported separately from the steady-state median. FLOPs per step come from XLA's cost analysis of the compiled
step; GFLOP/s is reported against the machine's fp32 and bf16-operand matmul peaks measured in the same run.
"""

from __future__ import annotations

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import (ACTION_DIM, STATE_DIM, BenchModel, base_parser, bench_models, device_kind, example_obs,
                               latency_stats, markdown_table, matmul_peak_gflops, param_count, precision_context,
                               report_rows, timed_calls)
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


def synthetic_batch(cfg, batch: int, key: jax.Array, state_dim: int = STATE_DIM, action_dim: int = ACTION_DIM) -> dict:
    """A normalised training batch ``{"obs": {k: (B, M, L_h, ...)}, "action": (B, M·L_c, A)}`` in [-1, 1]."""
    k1, k2 = jax.random.split(key)
    obs = jax.tree.map(lambda a: 2.0 * a - 1.0 if a.ndim == 4 else a, example_obs(cfg, batch, k1, state_dim))
    action = jax.random.uniform(k2, (batch, cfg.chunk.horizon, action_dim), minval=-1.0, maxval=1.0)
    return {"obs": obs, "action": action}


def train_setup(model: BenchModel, batch_size: int, **changes):
    """(policy, jitted train step, synthetic batch, key, holder of the donated train state) of one model: the real
    step (AdamW + cosine schedule + EMA) at ``batch_size``; ``changes`` go to the policy config."""
    policy = model.policy(**changes)
    train_cfg = TrainConfig(batch_size=batch_size, num_steps=10_000, warmup_steps=10)
    tx = make_optimizer(train_cfg)
    step = make_train_step(policy.net, policy.cfg, train_cfg, tx)
    batch = synthetic_batch(policy.cfg, batch_size, jax.random.key(1), model.state_dim, model.action_dim)
    return policy, step, batch, jax.random.key(2), {"state": init_train_state(policy.params, tx)}


def bench_config_row(model: BenchModel, args, points: int | None = None, peaks: dict | None = None) -> dict:
    """Compile time, first-step time, steady-state step latency and FLOPs of one model (``points``: point-cloud
    size)."""
    size, obs = model.size, model.obs
    policy, step, batch, key, holder = train_setup(model, args.batch,
                                                   **({} if points is None else {"encoder.num_points": points}))

    def one(i):
        holder["state"], metrics = step(holder["state"], batch, key)  # the state is donated: keep only the new one
        return metrics["loss"]

    with precision_context(args.matmul_precision):
        t0 = time.perf_counter()
        compiled = step.lower(holder["state"], batch, key).compile()
        compile_s = time.perf_counter() - t0
        analysis = compiled.cost_analysis()
        analysis = (analysis[0] if analysis else {}) if isinstance(analysis, (list, tuple)) else (analysis or {})
        flops = float(analysis.get("flops", math.nan))
        times, first = timed_calls(one, 0, warmup=1)  # first call: trace + compile (again, jit's cache) + run
        cache = step._cache_size()
        times, _ = timed_calls(one, args.repeats, args.row_budget_s, warmup=0)
        retraces = step._cache_size() - cache
    stats = latency_stats(times)
    loss = float(one(0))
    return {"size": size, "obs": obs, "dtype": model.dtype, "points": points, "batch": args.batch, "params": param_count(policy.params),
            **stats,
            "steps_per_s": 1.0 / stats["median_s"], "samples_per_s": args.batch / stats["median_s"],
            "compile_s": compile_s, "first_step_s": first, "retraces": retraces, "final_loss": loss,
            "loss_finite": bool(np.isfinite(loss)), "flops_per_step": flops,
            "gflops": flops / stats["median_s"] / 1e9,
            **{f"fraction_of_{k}_peak": flops / stats["median_s"] / 1e9 / v["gflops"] for k, v in (peaks or {}).items()}}


def main(argv=None) -> dict:
    args = parse_args(argv)
    peaks = {"f32": matmul_peak_gflops(), "bf16": matmul_peak_gflops(dtype=jnp.bfloat16)}
    print(f"machine peak: f32 {peaks['f32']['gflops']:.1f} GFLOP/s, bf16 operands {peaks['bf16']['gflops']:.1f} "
          f"GFLOP/s")
    rows = []
    for model in bench_models(args):
        for points in (args.num_points if model.obs == "pointcloud" else [None]):
            r = bench_config_row(model, args, points, peaks)
            rows.append(r)
            name = f"{model.size}/{model.obs}/{model.dtype}" + ("" if points is None else f"/{points} points")
            print(f"[{name}] batch {r['batch']}: {r['median_s'] * 1e3:.1f} ms/step, {r['steps_per_s']:.2f} "
                  f"steps/s, {r['samples_per_s']:.0f} samples/s, {r['gflops']:.1f} GFLOP/s, compile "
                  f"{r['compile_s']:.1f} s, first step {r['first_step_s']:.1f} s", flush=True)
    table = markdown_table(
        ["size", "obs", "dtype", "points", "params", "batch", "median ms", "p90 ms", "steps/s", "samples/s", "GFLOP/s",
         "% f32 peak", "% bf16 peak", "compile s", "first step s"],
        [[r["size"], r["obs"], r["dtype"], "–" if r["points"] is None else r["points"], f"{r['params']:,}", r["batch"],
          r["median_s"] * 1e3, r["p90_s"] * 1e3, r["steps_per_s"], r["samples_per_s"], r["gflops"],
          100 * r["fraction_of_f32_peak"], 100 * r["fraction_of_bf16_peak"], r["compile_s"], r["first_step_s"]]
         for r in rows])
    return report_rows(NAME + ("_shapes" if args.shapes else ""), argv, args, rows, table, machine_peaks=peaks)


if __name__ == "__main__":
    main()
