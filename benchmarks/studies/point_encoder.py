"""The point-cloud train step before / after, side by side (interleaved) in one run: the encoder's written-out
backward pass (``models.encoders.point_trunk``) and glibc keeping freed memory (``host_memory``).

    python -m benchmarks.studies.point_encoder                       # DP and HiPolicy, 128 / 512 points, batch 64
    python -m benchmarks.studies.point_encoder --trajectory-steps 200  # + the loss over 200 steps, before vs after
    python -m benchmarks.studies.point_encoder --quick               # tiny, the smoke test

Variants of the real train step (``training.make_train_step``, cpu-size policy, synthetic batch), on the same
parameters, batch and keys:

* ``module autodiff``: DP3's PointNet written with ``nn.Dense`` / ``nn.LayerNorm`` / ``jnp.max`` and JAX's
  autodiff, as the encoder was before (``ModulePointCloudEncoder``; it has the same parameters);
* ``written backward``: the library's ``PointCloudEncoder`` (``point_trunk``);

each with glibc's defaults for large allocations (a fresh ``mmap`` per buffer, given back when freed) and with
``host_memory.keep_freed_memory()`` (every entry point's setting). The process limits glibc to one arena first, for
all four. A round runs every variant in turn, ``--settle`` untimed calls then ``--calls`` timed ones (after a
switch of the allocator setting the kept heap needs two steps to grow to its size; then no step page-faults), so
load from other processes hits them alike. Reported: medians, samples/s and
ratios to the first variant; with ``--trajectory-steps``, the losses of the first and the last variant trained
side by side from the same state for that many steps, and their largest relative difference.
"""

from __future__ import annotations

import contextlib
import time

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import ACTION_DIM, STATE_DIM, BenchModel, markdown_table, report_rows
from benchmarks.train_step import synthetic_batch
from hipolicy_jax.config import TrainConfig
from hipolicy_jax.host_memory import keep_freed_memory
from hipolicy_jax.models import encoders
from hipolicy_jax.training import init_train_state, make_optimizer, make_train_step

NAME = "point_encoder"
MODULE = "studies.point_encoder"
METHODS = {"dp": {"chunk.strides": (1,)}, "hipolicy": {}}
VARIANTS = (("module autodiff", False), ("module autodiff", True), ("written backward", False),
            ("written backward", True))


class ModulePointCloudEncoder(nn.Module):
    """DP3's PointNet as the library wrote it before ``point_trunk``: flax modules and JAX's autodiff. The same
    parameters (``dense_i``, ``norm_i``, ``out``, ``out_norm``) and initial values as ``PointCloudEncoder``."""

    out_dim: int = 64
    widths: tuple[int, ...] = (64, 128, 256)

    @nn.compact
    def __call__(self, points):
        x = points
        for i, w in enumerate(self.widths):
            x = nn.relu(nn.LayerNorm(name=f"norm_{i}")(nn.Dense(w, name=f"dense_{i}")(x)))
        x = jnp.max(x, axis=-2)
        return nn.LayerNorm(name="out_norm")(nn.Dense(self.out_dim, name="out")(x))


@contextlib.contextmanager
def point_encoder(kind: str):
    """Trace the policy with ``kind``'s point encoder: 'written backward' (the library's) or 'module autodiff'."""
    saved = encoders.PointCloudEncoder
    if kind == "module autodiff":
        encoders.PointCloudEncoder = ModulePointCloudEncoder
    try:
        yield
    finally:
        encoders.PointCloudEncoder = saved


def parse_args(argv=None):
    import argparse

    p = argparse.ArgumentParser(prog=f"python -m benchmarks.{MODULE}", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out-dir", default=None)
    p.add_argument("--size", default="cpu", choices=["tiny", "cpu", "paper"])
    p.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    p.add_argument("--num-points", type=int, nargs="+", default=[128, 512])
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--settle", type=int, default=2, help="untimed calls per variant and round, before the timed "
                                                          "ones (glibc's heap needs two steps to reach its size)")
    p.add_argument("--calls", type=int, default=2, help="timed calls per variant and round")
    p.add_argument("--trajectory-steps", type=int, default=0,
                   help="train the first and the last variant side by side for this many steps (HiPolicy, the "
                        "largest point count)")
    p.add_argument("--quick", action="store_true", help="tiny size, 32 points, batch 4, 1 round, 3-step trajectory")
    args = p.parse_args(argv)
    if args.quick:
        args.size, args.num_points, args.batch, args.rounds, args.calls, args.settle = "tiny", [32], 4, 1, 1, 1
        args.trajectory_steps = 3
    return args


class Step:
    """One variant's compiled train step and its own (donated) train state."""

    def __init__(self, policy, kind: str, keep: bool, batch_size: int):
        self.kind, self.keep = kind, keep
        train_cfg = TrainConfig(batch_size=batch_size, num_steps=10_000, warmup_steps=10)
        tx = make_optimizer(train_cfg)
        self.batch = synthetic_batch(policy.cfg, batch_size, jax.random.key(1), STATE_DIM, ACTION_DIM)
        self.key = jax.random.key(2)
        self.state = init_train_state(jax.tree.map(jnp.copy, policy.params), tx)
        step = make_train_step(policy.net, policy.cfg, train_cfg, tx)
        with point_encoder(kind):
            self.compiled = step.lower(self.state, self.batch, self.key).compile()

    def __call__(self) -> jax.Array:
        keep_freed_memory(self.keep)
        self.state, metrics = self.compiled(self.state, self.batch, self.key)
        return metrics["loss"]


def label(kind: str, keep: bool) -> str:
    return f"{kind}, {'freed memory kept' if keep else 'glibc defaults'}"


def time_row(model: BenchModel, method: str, points: int, args) -> dict:
    policy = model.policy(**METHODS[method], **{"encoder.num_points": points})
    steps = [Step(policy, kind, keep, args.batch) for kind, keep in VARIANTS]
    times: dict[str, list[float]] = {label(s.kind, s.keep): [] for s in steps}
    losses = {}
    for _ in range(args.rounds):
        for s in steps:
            for _ in range(args.settle):  # the allocator setting takes effect (the kept heap grows to its size)
                jax.block_until_ready(s())
            for _ in range(args.calls):
                t0 = time.perf_counter()
                losses[label(s.kind, s.keep)] = float(jax.block_until_ready(s()))
                times[label(s.kind, s.keep)].append(time.perf_counter() - t0)
    keep_freed_memory(True)
    base = float(np.median(times[label(*VARIANTS[0])]))
    variants = {name: {"median_s": float(np.median(t)), "min_s": float(np.min(t)), "calls": len(t),
                       "samples_per_s": args.batch / float(np.median(t)), "speedup": base / float(np.median(t)),
                       "last_loss": losses[name]} for name, t in times.items()}
    return {"method": method, "points": points, "batch": args.batch, "size": model.size, "variants": variants}


def trajectory(model: BenchModel, points: int, args) -> dict:
    """The first and the last variant trained side by side from the same state for ``--trajectory-steps``."""
    policy = model.policy(**METHODS["hipolicy"], **{"encoder.num_points": points})
    before, after = Step(policy, *VARIANTS[0], args.batch), Step(policy, *VARIANTS[-1], args.batch)
    a, b = [], []
    for _ in range(args.trajectory_steps):
        a.append(float(before()))
        b.append(float(after()))
    keep_freed_memory(True)
    rel = np.abs(np.asarray(a) - np.asarray(b)) / np.abs(np.asarray(a))
    return {"method": "hipolicy", "points": points, "batch": args.batch, "steps": args.trajectory_steps,
            "before": label(*VARIANTS[0]), "after": label(*VARIANTS[-1]), "loss_before": a, "loss_after": b,
            "max_rel_diff": float(rel.max()), "rel_diff_first_10": float(rel[:10].max()),
            "final_loss": [a[-1], b[-1]]}


def main(argv=None) -> dict:
    args = parse_args(argv)
    keep_freed_memory(True)  # the one-arena limit, before the first computation
    rows = []
    for method in args.methods:
        for points in args.num_points:
            model = BenchModel(args.size, "pointcloud", {}, STATE_DIM, ACTION_DIM)
            r = time_row(model, method, points, args)
            rows.append(r)
            print(f"[{method} {points} points, batch {args.batch}] " + ", ".join(
                f"{k}: {v['median_s'] * 1e3:.0f} ms ({v['speedup']:.2f}x)" for k, v in r["variants"].items()),
                flush=True)
    traj = None
    if args.trajectory_steps:
        traj = trajectory(BenchModel(args.size, "pointcloud", {}, STATE_DIM, ACTION_DIM), max(args.num_points),
                          args)
        print(f"[trajectory] {traj['steps']} steps: largest relative loss difference {traj['max_rel_diff']:.2e} "
              f"(first 10 steps {traj['rel_diff_first_10']:.2e})", flush=True)
    names = [label(*v) for v in VARIANTS]
    table = markdown_table(
        ["method", "points", "batch"] + [f"{n} ms" for n in names] + ["after samples/s", "before / after"],
        [[r["method"], r["points"], r["batch"]] + [r["variants"][n]["median_s"] * 1e3 for n in names]
         + [r["variants"][names[-1]]["samples_per_s"], f"**{r['variants'][names[-1]]['speedup']:.2f}**"]
         for r in rows])
    return report_rows(NAME, argv, args, rows, table, module=MODULE, trajectory=traj)


if __name__ == "__main__":
    main()
