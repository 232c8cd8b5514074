"""One-call N-sample latency and memory of the jitted sampler (the paper's sample-times table).

    python -m benchmarks.sampling                      # CPU default: cpu size, state obs, N 1/10/100, < 10 min
    python -m benchmarks.sampling --sizes cpu paper --obs state image pointcloud --ns 1 5 10 100 500   # GPU grid
    python -m benchmarks.sampling --shapes dp-lowdim hipolicy hipolicy-nofusion --samplers ddpm --ns 1 100

For every (size, obs, sampler, N): median / p90 latency of ``sampling.make_sampler`` (``block_until_ready``, after a
warm-up call that also compiles), the ratio latency(N) / latency(1), peak memory (device allocator on a GPU, RSS on
a CPU) and the achieved GFLOP/s. A ``loop`` row times N separate N=1 calls from Python, which is what the one-call
design (encode once, ``vmap`` over the N draws) replaces. FLOPs per sample-step come from XLA's cost analysis of
the denoising-loop body; the machine peaks (fp32, and bf16 operands with fp32 accumulation) are estimated from a
large matmul in the same run. ``--shapes`` benchmarks the PyTorch comparison's shapes at paper size instead
(``common.SHAPES``: Diffusion Policy's low-dim U-Net to the parameter, the HiPolicy shape with / without fusion).

The paper reports 105.5 ms at N=1 and 107.5 ms at N=100 (ratio 1.02, +63 MB) for 100 DDPM steps on a GPU.
"""

from __future__ import annotations

import argparse
import functools
import math
import sys

import jax
import jax.numpy as jnp

from benchmarks.common import (MemoryMonitor, base_parser, bench_models, compiled_flops, device_kind, latency_stats,
                               markdown_table, matmul_peak_gflops, memory_bandwidth_gbs, param_count,
                               precision_context, timed_calls, write_results)
from hipolicy_jax.config import InferenceConfig, PolicyConfig, replace
from hipolicy_jax.models.policy_net import PolicyNet, init_policy_params
from hipolicy_jax.sampling import make_sampler

NAME = "sampling"


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line flags; defaults depend on the device (a full grid on an accelerator, a small one on a CPU)."""
    cpu = device_kind() == "cpu"
    p = base_parser(NAME, __doc__, grid=True)
    p.add_argument("--ns", nargs="+", type=int, default=[1, 10, 100] if cpu else [1, 5, 10, 100, 500])
    p.add_argument("--samplers", nargs="+", default=["ddim", "ddpm"], choices=["ddpm", "ddim", "euler"],
                   help="euler: the flow-matching head (same network) with --ddim-steps Euler steps")
    p.add_argument("--ddim-steps", type=int, default=10, help="DDIM / Euler steps")
    p.add_argument("--repeats", type=int, default=20, help="timed calls per row after the warm-up")
    p.add_argument("--row-budget-s", type=float, default=20.0 if cpu else None,
                   help="stop a row's repeats once it has spent this long (at least 2 calls); CPU default 20 s")
    p.add_argument("--loop-ns", nargs="+", type=int, default=None,
                   help="N values timed as a Python loop of N single calls (default: the largest N <= 100)")
    p.add_argument("--loop-repeats", type=int, default=3 if cpu else 5)
    p.add_argument("--peak-n", type=int, default=None, help="matmul size of the peak estimate (default 2048 / 8192)")
    p.add_argument("--quick", action="store_true", help="cpu size, state obs, DDIM only, N 1/10, 5 repeats")
    args = p.parse_args(argv)
    if args.quick:
        args.sizes, args.obs, args.samplers, args.ns, args.repeats = ["cpu"], ["state"], ["ddim"], [1, 10], 5
    if args.loop_ns is None:
        small = [n for n in args.ns if 1 < n <= 100]
        args.loop_ns = [max(small)] if small else []
    return args


def sampler_steps(cfg: PolicyConfig, sampler: str, ddim_steps: int) -> int:
    """Reverse steps of ``sampler``: every train step for DDPM, ``ddim_steps`` for DDIM and Euler."""
    return cfg.diffusion.num_train_steps if sampler == "ddpm" else ddim_steps


def compiled_sampler(policy, sampler: str, steps: int, n: int):
    """``make_sampler`` for one row: the flow head for 'euler' (the network is the same), diffusion otherwise."""
    cfg = replace(policy.cfg, objective="flow") if sampler == "euler" else policy.cfg
    return make_sampler(PolicyNet(cfg, policy.net.action_dim), cfg, policy.net.action_dim,
                        InferenceConfig(num_samples=n, sampler=sampler, num_steps=steps))


def flops_per_sample_step(policy, batch: int = 1) -> float:
    """XLA FLOPs of one denoising step (the ``lax.scan`` body: ``denoise_film`` with precomputed FiLM) per sample,
    at ``batch`` samples of one observation."""
    net, params, cfg = policy.net, policy.params, policy.cfg
    cond = net.apply(params, net.apply(params, policy.normalizer.normalize_obs(policy.obs), method=net.encode),
                     method=net.film_condition)
    film_row = jax.tree.map(lambda a: a[0], net.apply(params, jnp.zeros((1,), jnp.int32), method=net.film_steps))
    x = jnp.zeros((batch, 1, cfg.chunk.horizon, net.action_dim), jnp.float32)

    def body(p, x, film_row, cond):
        return jax.vmap(lambda xi: net.apply(p, xi, film_row, cond, method=net.denoise_film))(x)

    return compiled_flops(body, params, x, film_row, cond) / batch


def bench_vmap_row(policy, sampler: str, steps: int, n: int, args) -> dict:
    """Latency, memory and retrace count of the compiled sampler with ``num_samples=n`` (one compiled call)."""
    fn = compiled_sampler(policy, sampler, steps, n)
    call = functools.partial(fn, policy.params, policy.normalizer, policy.obs)
    with precision_context(args.matmul_precision):
        with MemoryMonitor() as mem:
            times, first = timed_calls(lambda i: call(jax.random.key(i + 1000)).chunks, 1, warmup=1)
            first_after_compile = times[0]  # the call right after the compiling one
            cache = fn._cache_size()
            times, _ = timed_calls(lambda i: call(jax.random.key(i)).chunks, args.repeats, args.row_budget_s,
                                   warmup=0)
            retraces = fn._cache_size() - cache
    stats = latency_stats(times)
    return {**stats, "compile_s": first, "first_after_compile_s": first_after_compile,
            "first_call_ratio": first_after_compile / stats["median_s"], "mem_peak_mb": mem.peak_mb,
            "mem_delta_mb": mem.delta_mb, "mem_kind": mem.kind, "retraces": retraces}


def bench_loop_row(policy, sampler: str, steps: int, n: int, args) -> dict:
    """Latency of N separate ``num_samples=1`` calls dispatched from a Python loop (what the one call replaces)."""
    call = functools.partial(compiled_sampler(policy, sampler, steps, 1), policy.params, policy.normalizer,
                             policy.obs)

    def loop(i):
        base = jax.random.key(i + 10_000)
        return [call(jax.random.fold_in(base, j)).chunks for j in range(n)]

    with precision_context(args.matmul_precision):
        call(jax.random.key(0)).chunks.block_until_ready()  # compiled already by the N=1 row, or now
        with MemoryMonitor() as mem:
            times, _ = timed_calls(loop, args.loop_repeats, args.row_budget_s, warmup=0, min_calls=1)
    return {**latency_stats(times), "compile_s": math.nan, "mem_peak_mb": mem.peak_mb,
            "mem_delta_mb": mem.delta_mb, "mem_kind": mem.kind, "retraces": 0}


def default_policy_param_count() -> int:
    """Parameters of ``PolicyNet(PolicyConfig(), 4)`` on a 10-dim state (the default CPU-sized state policy)."""
    cfg = PolicyConfig()
    obs = {"state": jnp.zeros((1, cfg.chunk.num_freqs, cfg.chunk.obs_horizon, 10))}
    shapes = jax.eval_shape(lambda k: init_policy_params(cfg, 4, obs, k), jax.random.key(0))
    return param_count(shapes)


def main(argv=None) -> dict:
    """Run the benchmark, print its tables, write the JSON; returns the JSON payload."""
    args = parse_args(argv)
    peak = matmul_peak_gflops(args.peak_n)
    peak_bf16 = matmul_peak_gflops(args.peak_n, dtype=jnp.bfloat16)
    bandwidth = memory_bandwidth_gbs()
    print(f"machine peak ({peak['n']}x{peak['n']} matmul): f32 {peak['gflops']:.1f} GFLOP/s, bf16 operands "
          f"{peak_bf16['gflops']:.1f} GFLOP/s; memory read bandwidth {bandwidth['gbs']:.1f} GB/s")
    rows, models = [], []
    for model in bench_models(args):
        size, obs = model.size, model.obs
        policy = model.policy()
        fl = flops_per_sample_step(policy)
        weight_mb = sum(leaf.size * (2 if model.dtype == "bfloat16" and leaf.ndim == 3 else 4)
                        for leaf in jax.tree.leaves(policy.params)) / 2**20
        models.append({"size": size, "obs": obs, "dtype": model.dtype, "params": param_count(policy.params),
                       "flops_per_sample_step": fl, "weight_mb_per_step": weight_mb,
                       "weight_read_bound_ms_per_step": weight_mb * 2**20 / bandwidth["gbs"] / 1e6})
        print(f"[{size}/{obs}/{model.dtype}] {param_count(policy.params):,} params, {fl / 1e6:.2f} MFLOP per sample-step")
        for sampler in args.samplers:
            steps = sampler_steps(policy.cfg, sampler, args.ddim_steps)
            base = None
            for n in args.ns:
                for mode in ["vmap"] + (["loop"] if n in args.loop_ns else []):
                    bench = bench_vmap_row if mode == "vmap" else bench_loop_row
                    r = bench(policy, sampler, steps, n, args)
                    if mode == "vmap" and n == min(args.ns):
                        base = r["median_s"] if n == 1 else None
                    r.update(size=size, obs=obs, dtype=model.dtype, sampler=sampler, steps=steps, n=n, mode=mode,
                             ratio_to_n1=r["median_s"] / base if base else math.nan,
                             gflops=fl * n * steps / r["median_s"] / 1e9)
                    r["fraction_of_peak"] = r["gflops"] / peak["gflops"]
                    r["fraction_of_bf16_peak"] = r["gflops"] / peak_bf16["gflops"]
                    rows.append(r)
                    print(f"  {sampler}{steps:>4} N={n:<4} {mode:<4} median {r['median_s'] * 1e3:9.1f} ms  "
                          f"p90 {r['p90_s'] * 1e3:9.1f} ms  x{r['ratio_to_n1']:.2f}  "
                          f"{r['gflops']:6.1f} GFLOP/s  {r['mem_kind']} +{r['mem_delta_mb']:.0f} MB", flush=True)
    for r in rows:  # loop rows: speed-up of the one call over the loop at the same N
        if r["mode"] == "loop":
            match = [v for v in rows if v["mode"] == "vmap" and all(v[k] == r[k] for k in
                                                                     ("size", "obs", "dtype", "sampler", "n"))]
            r["loop_over_vmap"] = r["median_s"] / match[0]["median_s"] if match else math.nan
    table = markdown_table(
        ["size", "obs", "dtype", "sampler", "steps", "N", "mode", "median ms", "p90 ms", "calls", "lat(N)/lat(1)",
         "GFLOP/s", "% f32 peak", "% bf16 peak", "mem +MB", "compile s", "1st call after compile / median"],
        [[r["size"], r["obs"], r["dtype"], r["sampler"], r["steps"], r["n"], r["mode"], r["median_s"] * 1e3,
          r["p90_s"] * 1e3, r["calls"], r["ratio_to_n1"], r["gflops"], 100 * r["fraction_of_peak"],
          100 * r["fraction_of_bf16_peak"], r["mem_delta_mb"], r["compile_s"], r.get("first_call_ratio", math.nan)]
         for r in rows])
    print(table)
    loops = [r for r in rows if r["mode"] == "loop"]
    if loops:
        print("\n" + markdown_table(["size", "obs", "dtype", "sampler", "N", "loop / one call"],
                                    [[r["size"], r["obs"], r["dtype"], r["sampler"], r["n"], r["loop_over_vmap"]]
                                     for r in loops]))
    payload = {"command": "python -m benchmarks.sampling " + " ".join(sys.argv[1:] if argv is None else argv),
               "args": {k: v for k, v in vars(args).items() if k != "out_dir"}, "machine_peak": peak,
               "machine_peak_bf16": peak_bf16,
               "memory_bandwidth": bandwidth,
               "default_policy_params": default_policy_param_count(), "models": models, "rows": rows,
               "table_md": table}
    path = write_results(NAME + ("_shapes" if args.shapes else ""), payload, args.out_dir)  # the peer shapes apart
    print(f"wrote {path}")
    return payload


if __name__ == "__main__":
    main()
