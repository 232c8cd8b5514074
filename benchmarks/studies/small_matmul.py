"""The N=1 latency's bound, one kernel at a time: how fast XLA's CPU dot streams a weight matrix when few rows
multiply it.

    python -m benchmarks.studies.small_matmul   # M 4/8/16/32 rows x the DP low-dim U-Net's largest weights, fp32 + bf16

One denoising step of one sample multiplies M = 4–16 rows (the chunk's time steps at each U-Net level) by every
weight matrix once (the convolutions are im2col matmuls in bf16, ``models.unet.conv1d``), so the step cannot run
faster than reading all weights from memory: weight bytes / read bandwidth. This benchmark times that dot alone,
``x (M, K) @ W (K, N)`` with K x N the U-Net's largest kernels (im2col: 5 taps x C_in rows), and reports the GB/s
it streams the weights at against the machine's read bandwidth measured in the same process
(``common.memory_bandwidth_gbs``). Each ``--xla-flags`` variant runs in its own subprocess (XLA reads its flags
once, at start): XLA's default dot emitter, and the XNNPACK / oneDNN paths this jaxlib offers.

The layouts: ``x@W`` (the network's), ``W^T stored`` (the weight kept as (N, K), contracted on its minor axis).
The table shows the largest weight (10240 x 2048); the JSON has every shape and ``best`` per dtype and M.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

from benchmarks.common import base_parser, markdown_table, report_rows

NAME = "small_matmul"
MODULE = "studies.small_matmul"  # python -m benchmarks.studies.small_matmul
# (K, N): im2col kernels of the DP low-dim U-Net (down dims 512 / 1024 / 2048, 5 taps) — the weights that dominate
# its 65.8 M parameters
SHAPES = [(5 * 1024, 2048), (5 * 2048, 2048), (5 * 2048, 1024)]
VARIANTS = {"xla default": "", "xnn dot fusion": "--xla_cpu_experimental_xnn_fusion_type=dot",
            "onednn": "--xla_cpu_use_onednn=true"}


def parse_args(argv=None):
    p = base_parser(MODULE, __doc__)
    p.add_argument("--rows", nargs="+", type=int, default=[4, 8, 16, 32], help="M: rows multiplying the weights")
    p.add_argument("--dtypes", nargs="+", default=["float32", "bfloat16"], choices=["float32", "bfloat16"])
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--repeats", type=int, default=30)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)  # a variant's own process
    return p.parse_args(argv)


def measure(rows: list[int], dtypes: list[str], repeats: int) -> dict:
    """In this process (its XLA flags): the read bandwidth and, per (dtype, layout, M, K, N), the median ms of the
    dot and the GB/s it streams the weights at."""
    import jax
    import jax.numpy as jnp

    from benchmarks.common import memory_bandwidth_gbs, timed_calls

    bandwidth = memory_bandwidth_gbs(mbytes=256, repeats=5)
    out = []
    for dtype in dtypes:
        dt = jnp.dtype(dtype)
        for k, n in SHAPES:
            w = jax.random.normal(jax.random.key(1), (k, n), jnp.float32).astype(dt)
            wt = jnp.asarray(np.asarray(w).T.copy())
            layouts = {"x@W": (_dot(jax, jnp, 0), w), "W^T stored": (_dot(jax, jnp, 1), wt)}
            for m in rows:
                x = jax.random.normal(jax.random.key(0), (m, k), jnp.float32).astype(dt)
                for layout, (fn, weight) in layouts.items():
                    times, _ = timed_calls(lambda i: fn(x, weight), repeats, warmup=2)
                    ms = float(np.median(times)) * 1e3
                    out.append({"dtype": dtype, "layout": layout, "m": m, "k": k, "n": n, "ms": ms,
                                "weight_mb": k * n * dt.itemsize / 2**20,
                                "weight_gbs": k * n * dt.itemsize / (ms / 1e3) / 1e9})
    return {"bandwidth_gbs": bandwidth["gbs"], "rows": out}


def _dot(jax, jnp, weight_axis: int):
    """jit(x (M, K) · W) contracting W's axis ``weight_axis`` (0: W is (K, N); 1: W is stored (N, K))."""
    dims = (((1,), (weight_axis,)), ((), ()))
    return jax.jit(lambda a, b: jax.lax.dot_general(a, b, dims, preferred_element_type=jnp.float32))


def _largest(rows: list[dict]) -> dict:
    """(variant, dtype, M) → {layout: row} of the largest weight (the table; the JSON keeps every shape)."""
    k, n = max(SHAPES, key=lambda kn: kn[0] * kn[1])
    out: dict = {}
    for r in rows:
        if (r["k"], r["n"]) == (k, n):
            out.setdefault((r["variant"], r["dtype"], r["m"]), {})[r["layout"]] = r
    return out


def main(argv=None) -> dict:
    args = parse_args(argv)
    if args.child is not None:
        print(json.dumps(measure(args.rows, args.dtypes, args.repeats)))
        return {}
    rows, bandwidths = [], {}
    for variant in args.variants:
        env = dict(os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + " " + VARIANTS[variant]).strip())
        cmd = [sys.executable, "-m", "benchmarks.studies.small_matmul", "--child", variant, "--rows",
               *map(str, args.rows), "--dtypes", *args.dtypes, "--repeats", str(args.repeats)]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode != 0:
            print(f"[{variant}] failed: {proc.stderr.strip().splitlines()[-1:]}", flush=True)
            continue
        res = json.loads(proc.stdout.strip().splitlines()[-1])
        bandwidths[variant] = res["bandwidth_gbs"]
        for r in res["rows"]:
            rows.append({"variant": variant, **r, "fraction_of_bandwidth": r["weight_gbs"] / res["bandwidth_gbs"]})
        print(f"[{variant}] read bandwidth {res['bandwidth_gbs']:.1f} GB/s", flush=True)
    table = markdown_table(
        ["variant", "dtype", "M", "ms x@W", "ms W^T stored", "weights GB/s (best)", "of bandwidth (best)"],
        [[v, d, m, by["x@W"]["ms"], by["W^T stored"]["ms"], max(r["weight_gbs"] for r in by.values()),
          f"{100 * max(r['fraction_of_bandwidth'] for r in by.values()):.0f} %"]
         for (v, d, m), by in _largest(rows).items()])
    best = {}
    for r in rows:
        key = (r["dtype"], r["m"])
        if r["fraction_of_bandwidth"] > best.get(key, {}).get("fraction_of_bandwidth", -1):
            best[key] = r
    return report_rows(NAME, argv, args, rows, table, module=MODULE, bandwidth_gbs=bandwidths,
                       best=[{"dtype": d, "m": m, "variant": r["variant"], "layout": r["layout"],
                              "fraction_of_bandwidth": r["fraction_of_bandwidth"]} for (d, m), r in sorted(best.items())])


if __name__ == "__main__":
    main()
