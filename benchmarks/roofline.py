"""The training step against this machine's roofline, stage by stage: point-cloud and image policies, DP and HiPolicy.

    python -m benchmarks.roofline                     # CPU default: point clouds (128 / 512) and images (84 px)
    python -m benchmarks.roofline --obs pointcloud --num-points 512 --methods hipolicy --batch 64
    python -m benchmarks.roofline --quick             # tiny sizes, one repeat (the smoke test)

For every (method, observation, point count, batch) it compiles and times, each on its own after a warm-up, the
stages of the real train step (``training.make_train_step``) on a synthetic normalised batch:

- ``encoder forward``: the observation encoder (``PolicyNet.encode``, training mode: random crops for images);
- ``encoder forward + backward``: the same with its VJP to the encoder's parameters (the cotangent a condition);
- ``denoiser forward + backward``: the U-Net and the head's loss with gradients to the U-Net's parameters and to
  the condition, the condition given;
- ``optimizer + EMA``: AdamW, the cosine schedule and the EMA update on the whole parameter tree (state donated);
- ``train step``: the real step, all of the above in one program.

Per stage: XLA's cost analysis of the compiled program (``flops``, ``bytes accessed``), the median wall time, and
the roofline bound ``max(flops / matmul peak, bytes / bandwidth)`` with the float32 matmul peak and the read
bandwidth measured in the same process (``common.machine_peaks``); ``× roofline`` is the median over that bound.
``bytes accessed`` sums every (fused) operation's operands and results, so it counts traffic that a cache may
serve: the memory bound it gives is an upper estimate of what DRAM must carry. For point clouds the analytic
matmul FLOPs of DP3's PointNet are reported beside XLA's count (``pointnet_matmul_gflop``). The train step's
hottest operations come from a ``jax.profiler`` trace (``benchmarks.profile``'s grouping by model part).
"""

from __future__ import annotations

import argparse
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import (ACTION_DIM, STATE_DIM, BenchModel, device_kind, latency_stats, machine_peaks,
                               markdown_table, report_rows, timed_calls)
from benchmarks.profile import HloIndex, breakdown, trace_events
from benchmarks.train_step import synthetic_batch
from hipolicy_jax.config import TrainConfig
from hipolicy_jax.data.windowing import obs_offsets
from hipolicy_jax.heads import make_head
from hipolicy_jax.models.encoders import PointCloudEncoder, distinct_frames
from hipolicy_jax.training import apply_gradients, init_train_state, make_optimizer, make_train_step

NAME = "roofline"
METHODS = {"dp": {"chunk.strides": (1,)}, "hipolicy": {}}  # DP: one stride; HiPolicy: the defaults (1, 2, 3)
STAGES = ("encoder forward", "encoder forward + backward", "denoiser forward + backward", "optimizer + EMA",
          "train step")


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog=f"python -m benchmarks.{NAME}", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out-dir", default=None)
    p.add_argument("--size", default="cpu", choices=["tiny", "cpu", "paper"])
    p.add_argument("--obs", nargs="+", default=["pointcloud", "image"], choices=["pointcloud", "image"])
    p.add_argument("--num-points", type=int, nargs="+", default=[128, 512], help="point-cloud sizes")
    p.add_argument("--image-size", type=int, default=84, help="image H = W (the crop keeps its default ratio)")
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    p.add_argument("--batch", type=int, nargs="+", default=[64, 128])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--row-budget-s", type=float, default=20.0, help="stop a stage's timing after this many seconds")
    p.add_argument("--profile-calls", type=int, default=2, help="traced train steps for the hottest operations "
                                                                "(0: no trace)")
    p.add_argument("--quick", action="store_true", help="tiny size, 64 points, batch 8, one repeat")
    args = p.parse_args(argv)
    if args.quick:
        args.size, args.num_points, args.batch, args.repeats, args.profile_calls = "tiny", [64], [8], 1, 1
    for flag, values in (("--num-points", args.num_points), ("--batch", args.batch)):
        if any(v < 1 for v in values):
            p.error(f"{flag}: every value must be >= 1, got {values}")
    return args


def cost(compiled) -> tuple[float, float]:
    """(flops, bytes accessed) of a compiled program from XLA's cost analysis (nan where it says nothing)."""
    analysis = compiled.cost_analysis()
    analysis = (analysis[0] if analysis else {}) if isinstance(analysis, (list, tuple)) else (analysis or {})
    return float(analysis.get("flops", math.nan)), float(analysis.get("bytes accessed", math.nan))


def roofline_s(flops: float, bytes_: float, peaks: dict) -> tuple[float, str]:
    """(the lower bound on the time of ``flops`` and ``bytes_`` at the measured peaks, the bound that binds)."""
    compute = flops / (peaks["matmul_f32_gflops"] * 1e9)
    memory = bytes_ / (peaks["bandwidth_gbs"] * 1e9)
    return max(compute, memory), ("compute" if compute >= memory else "memory")


def pointnet_matmul_flops(cfg, batch: int) -> dict[str, float]:
    """DP3's PointNet's matmul FLOPs per train step, counted by hand: per point ``point_dims·64 + 64·128 + 128·256``
    multiply-adds, per frame ``256·point_out``, over ``batch`` × the distinct frames of the window (each encoded
    once) × ``num_points``. Backward: the weight gradient of every layer and the input gradient of all but the
    first (the points need none), so forward + backward = 3× forward minus the first layer's input gradient."""
    e, chunk = cfg.encoder, cfg.chunk
    offsets = tuple(tuple(int(o) for o in row) for row in obs_offsets(chunk))
    frames = len(distinct_frames(offsets, chunk.num_freqs, chunk.obs_horizon)[0])
    widths = (e.point_dims, *PointCloudEncoder.widths)
    per_point = [a * b for a, b in zip(widths[:-1], widths[1:])]
    points = batch * frames * e.num_points
    forward = 2.0 * (points * sum(per_point) + batch * frames * widths[-1] * e.point_out)
    first_input_grad = 2.0 * points * per_point[0]
    return {"distinct_frames": frames, "points": points, "forward": forward,
            "forward_backward": 3.0 * forward - first_input_grad}


class Stages:
    """The compiled stages of one policy's train step on one synthetic batch; ``run(name)`` calls one of them."""

    def __init__(self, policy, batch_size: int):
        self.policy, cfg, net = policy, policy.cfg, policy.net
        self.train_cfg = TrainConfig(batch_size=batch_size, num_steps=10_000, warmup_steps=10)
        self.tx = make_optimizer(self.train_cfg)
        self.batch = synthetic_batch(cfg, batch_size, jax.random.key(1), STATE_DIM, ACTION_DIM)
        self.key = jax.random.key(2)
        head = make_head(cfg)
        params = policy.params

        def encode(p, obs, key):
            return net.apply(p, obs, train=True, method=net.encode, rngs={"crop": key})

        def encode_grad(p, obs, key, cot):
            cond, vjp = jax.vjp(lambda q: encode(q, obs, key), p)
            return cond, vjp(cot)[0]

        def denoise_grad(p, cond, action, key):
            def loss(q, c):
                example = head.training_example(action, key)
                pred = net.apply(q, example.x, example.time, c, method=net.denoise)
                return jnp.mean(jnp.square(pred - example.target))
            return jax.value_and_grad(loss, argnums=(0, 1))(p, cond)

        train_cfg, tx = self.train_cfg, self.tx

        def update(state, grads):
            return apply_gradients(state, grads, tx, train_cfg)

        obs, action, key = self.batch["obs"], self.batch["action"], self.key
        cond = jax.jit(encode)(params, obs, key)
        self.cond_shape = tuple(cond.shape)
        cot = jnp.ones_like(cond)
        grads = jax.tree.map(jnp.zeros_like, params)
        # each donated state owns its buffers (the stages above keep reading ``params``)
        self.holder = {k: init_train_state(jax.tree.map(jnp.copy, params), self.tx) for k in ("update", "step")}
        step = make_train_step(net, cfg, self.train_cfg, self.tx)
        update_jit = jax.jit(update, donate_argnums=0)
        self._programs: dict[str, tuple[Callable, tuple | None]] = {
            "encoder forward": (jax.jit(encode), (params, obs, key)),
            "encoder forward + backward": (jax.jit(encode_grad), (params, obs, key, cot)),
            "denoiser forward + backward": (jax.jit(denoise_grad), (params, cond, action, key)),
            "optimizer + EMA": (update_jit, None),  # the donated states: read from ``holder`` at each call
            "train step": (step, None),
        }
        self._grads = grads

    def _args(self, name: str) -> tuple:
        if name == "optimizer + EMA":
            return self.holder["update"], self._grads
        if name == "train step":
            return self.holder["step"], self.batch, self.key
        return self._programs[name][1]

    def compiled(self, name: str):
        """Stage ``name`` lowered and compiled for its arguments (for XLA's cost analysis and HLO text)."""
        return self._programs[name][0].lower(*self._args(name)).compile()

    def call(self, name: str):
        """One call of stage ``name`` (the donated states of the update and the step are carried over)."""
        fn, args = self._programs[name]
        if name == "optimizer + EMA":
            self.holder["update"] = fn(self.holder["update"], self._grads)
            return self.holder["update"].step
        if name == "train step":
            self.holder["step"], metrics = fn(self.holder["step"], self.batch, self.key)
            return metrics["loss"]
        return fn(*args)


def bench_row(model: BenchModel, method: str, batch: int, points: int | None, args, peaks: dict) -> dict:
    """One (method, observation, points, batch) row: every stage's cost, time and roofline, the hottest ops."""
    changes = dict(METHODS[method])
    if points is not None:
        changes["encoder.num_points"] = points
    if model.obs == "image" and args.image_size is not None and model.size != "tiny":
        changes["encoder.image_size"] = args.image_size
        changes["encoder.crop_size"] = round(args.image_size * 76 / 84)
    policy = model.policy(**changes)
    stages = Stages(policy, batch)
    out = {"method": method, "obs": model.obs, "size": model.size, "points": points,
           "image_size": policy.cfg.encoder.image_size if model.obs == "image" else None, "batch": batch,
           "condition_shape": list(stages.cond_shape), "stages": {}}
    for name in STAGES:
        flops, bytes_ = cost(stages.compiled(name))
        times, first = timed_calls(lambda i, n=name: stages.call(n), args.repeats, args.row_budget_s, warmup=1)
        stats = latency_stats(times)
        bound, binds = roofline_s(flops, bytes_, peaks)
        out["stages"][name] = {**stats, "first_call_s": first, "flops": flops, "bytes": bytes_,
                               "intensity": flops / bytes_ if bytes_ else math.nan, "roofline_s": bound,
                               "bound": binds, "x_roofline": stats["median_s"] / bound if bound else math.nan,
                               "gflops": flops / stats["median_s"] / 1e9}
    step = out["stages"]["train step"]
    out["samples_per_s"] = batch / step["median_s"]
    out["stage_sum_s"] = sum(out["stages"][n]["median_s"] for n in STAGES[1:4])
    if model.obs == "pointcloud":
        out["pointnet_matmul_gflop"] = {k: (v / 1e9 if k in ("forward", "forward_backward") else v)
                                        for k, v in pointnet_matmul_flops(policy.cfg, batch).items()}
    if args.profile_calls:
        hlo = stages.compiled("train step").as_text()
        events, wall = trace_events(lambda: stages.call("train step"), args.profile_calls)
        res = breakdown(events, HloIndex(hlo), args.profile_calls, "train")
        out["profile"] = {"wall_ms": wall * 1e3, "total_op_ms": res["total_op_ms"],
                          "top_ops_ms": res["top_ops_ms"], "passes_ms": res["passes_ms"]}
    return out


def table(rows: list[dict]) -> str:
    body = []
    for r in rows:
        obs = (f"{r['obs']} {r['points']} pts" if r["obs"] == "pointcloud" else f"{r['obs']} {r['image_size']} px")
        for name in STAGES:
            s = r["stages"][name]
            body.append([r["method"], obs, r["batch"], name, s["median_s"] * 1e3, s["flops"] / 1e9, s["bytes"] / 1e9,
                         s["intensity"], s["gflops"], s["roofline_s"] * 1e3, s["bound"], f"**{s['x_roofline']:.2f}**"])
    return markdown_table(["method", "obs", "batch", "stage", "median ms", "GFLOP", "GB accessed", "FLOP/byte",
                           "GFLOP/s", "roofline ms", "bound", "× roofline"], body)


def main(argv=None) -> dict:
    args = parse_args(argv)
    peaks = machine_peaks()
    print(f"machine: f32 matmul {peaks['matmul_f32_gflops']:.1f} GFLOP/s, read bandwidth {peaks['bandwidth_gbs']:.1f} "
          f"GB/s ({device_kind()})", flush=True)
    rows = []
    for obs in args.obs:
        model = BenchModel(args.size, obs, {}, STATE_DIM, ACTION_DIM)
        for points in (args.num_points if obs == "pointcloud" else [None]):
            for method in args.methods:
                for batch in args.batch:
                    r = bench_row(model, method, batch, points, args, peaks)
                    rows.append(r)
                    s = r["stages"]["train step"]
                    enc = r["stages"]["encoder forward + backward"]
                    print(f"[{method} {obs} {points or ''} batch {batch}] step {s['median_s'] * 1e3:.0f} ms "
                          f"({r['samples_per_s']:.0f} samples/s, {s['x_roofline']:.2f}x its roofline); encoder "
                          f"fwd+bwd {enc['median_s'] * 1e3:.0f} ms ({enc['x_roofline']:.2f}x)", flush=True)
    return report_rows(NAME, argv, args, rows, table(rows), peaks=peaks,
                       note="Each stage compiled and timed on its own (median of `--repeats` after a warm-up); "
                            "the roofline is max(FLOPs / matmul peak, bytes accessed / read bandwidth) at the peaks "
                            "measured in the same run (`peaks`).")


if __name__ == "__main__":
    main()
