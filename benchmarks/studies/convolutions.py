"""Before / after of the U-Net's short-sequence convolutions, measured side by side (interleaved calls) in one run.

    python -m benchmarks.studies.convolutions            # CPU default: cpu size, state obs, DP (L_c 8, 16) and HiPolicy

Variants of the same network and parameters:

* ``native``: every temporal convolution is ``lax.conv_general_dilated`` (as ``nn.Conv``) and the up-sampling is the
  transposed convolution of ``nn.ConvTranspose(C, (4,), strides=(2,), padding=((2, 2),))`` — the U-Net before
  the change;
* ``after``: ``models.unet.conv1d`` (im2col matmul where the sequence is shorter than the kernel) and
  ``models.unet.Upsample1d`` (the transposed conv as one stride-1 conv, even / odd outputs interleaved).

Why it matters: with ``L_c = 8`` the single-frequency U-Net's deepest level is 2 steps long and the level above
4, shorter than the 5-tap kernel. XLA then swaps the convolution's operands and its CPU backend runs that form very
slowly; the transposed conv's gradient (input-dilated) has no fast path either. The three-frequency HiPolicy
(``3·L_c = 24`` steps, deepest level 6) escaped the first problem, so before the change the DP *baseline* trained
slower than HiPolicy. Rows: one train step (AdamW + EMA, batch ``--batch``) and one sampler call (one observation,
N samples, DDIM steps) per config and variant; ``max abs diff`` compares the variants' outputs on the same inputs.
"""

from __future__ import annotations

import contextlib
import time

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import base_parser, make_bench_policy, markdown_table, report_rows
from hipolicy_jax.config import TrainConfig, replace
from hipolicy_jax.models import unet
from hipolicy_jax.models.policy_net import PolicyNet, init_policy_params
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.sampling import sample
from hipolicy_jax.training import init_train_state, make_optimizer, make_train_step

NAME = "convolutions"
MODULE = "studies.convolutions"  # python -m benchmarks.studies.convolutions
VARIANTS = ("native", "after")
# label -> (strides, L_c)
CONFIGS = {"DP L_c=8": ((1,), 8), "DP L_c=16": ((1,), 16), "HiPolicy 1/2/3 L_c=8": ((1, 2, 3), 8)}


def native_conv1d(x, kernel, padding, stride=1, compute_dtype="float32"):
    """XLA's native convolution, ``models.unet.conv1d``'s signature (the float32 baseline: ``compute_dtype`` is
    accepted and not used)."""
    return jax.lax.conv_general_dilated(x, kernel.astype(x.dtype), (stride,), (padding,),
                                        dimension_numbers=("NWC", "WIO", "NWC"))


class NativeUpsample(nn.Module):
    """``Upsample1d``'s parameters through ``lax.conv_transpose`` (what ``nn.ConvTranspose`` runs)."""

    features: int
    compute_dtype: str = "float32"  # ``Upsample1d``'s fields; the native baseline runs in float32

    @nn.compact
    def __call__(self, x):
        w = self.param("kernel", jax.nn.initializers.lecun_normal(), (4, x.shape[-1], self.features))
        bias = self.param("bias", jax.nn.initializers.zeros, (self.features,))
        return jax.lax.conv_transpose(x, w, (2,), ((2, 2),), dimension_numbers=("NWC", "WIO", "NWC")) + bias


@contextlib.contextmanager
def native_convs(enabled: bool):
    """Within the block (while tracing) the U-Net uses the native convolutions when ``enabled``."""
    saved = unet.conv1d, unet.Upsample1d
    if enabled:
        unet.conv1d, unet.Upsample1d = native_conv1d, NativeUpsample
    try:
        yield
    finally:
        unet.conv1d, unet.Upsample1d = saved


def parse_args(argv=None):
    p = base_parser(MODULE, __doc__)
    p.add_argument("--size", default="cpu", choices=["tiny", "cpu", "paper"])
    p.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    p.add_argument("--batch", type=int, default=64, help="train-step batch")
    p.add_argument("--num-samples", type=int, default=16)
    p.add_argument("--ddim-steps", type=int, default=10)
    p.add_argument("--rounds", type=int, default=10, help="interleaved rounds (one call of every variant each)")
    p.add_argument("--budget-s", type=float, default=45.0, help="per config and kind, after at least 3 rounds")
    return p.parse_args(argv)


def compiled_calls(size: str, strides, chunk_len: int, args):
    """{kind: {variant: fn(i) -> array}} for kind ``train`` / ``sample``, each variant traced in its context,
    plus the outputs of one call per variant on identical inputs."""
    base = make_bench_policy(size, "state")
    cfg = replace(base.cfg, **{"chunk.strides": tuple(strides), "chunk.chunk_len": chunk_len})
    action_dim = base.net.action_dim
    obs = {"state": jax.random.uniform(jax.random.key(1), (1, cfg.chunk.num_freqs, cfg.chunk.obs_horizon,
                                                            base.obs["state"].shape[-1]))}
    params = init_policy_params(cfg, action_dim, obs, jax.random.key(0))
    net = PolicyNet(cfg, action_dim)
    train_cfg = TrainConfig(batch_size=args.batch, num_steps=10_000, warmup_steps=10)
    tx = make_optimizer(train_cfg)
    batch = {"obs": jax.tree.map(lambda a: jnp.repeat(2.0 * a - 1.0, args.batch, axis=0), obs),
             "action": jax.random.uniform(jax.random.key(2), (args.batch, cfg.chunk.horizon, action_dim), minval=-1.0,
                                          maxval=1.0)}
    calls, outputs = {"train": {}, "sample": {}}, {"train": {}, "sample": {}}
    for variant in VARIANTS:
        with native_convs(variant == "native"):
            step = make_train_step(net, cfg, train_cfg, tx)
            fresh = lambda: init_train_state(jax.tree.map(jnp.copy, params), tx)  # noqa: E731 (steps donate it)
            holder = {"state": fresh()}
            inference = InferenceConfig(num_samples=args.num_samples, sampler="ddim", num_steps=args.ddim_steps)
            sampler = jax.jit(lambda p, o, k: sample(p, base.normalizer, o, k, net=net, cfg=cfg,
                                                     action_dim=action_dim, inference=inference).chunks)
            # trace + compile inside the context; later calls reuse the executable
            _, metrics = step(fresh(), batch, jax.random.key(3))
            outputs["train"][variant] = np.asarray(metrics["loss"])
            outputs["sample"][variant] = np.asarray(sampler(params, obs, jax.random.key(4)))

        def train_call(i, step=step, holder=holder):
            holder["state"], m = step(holder["state"], batch, jax.random.key(3))  # the state is donated
            return m["loss"]

        calls["train"][variant] = train_call
        calls["sample"][variant] = lambda i, sampler=sampler: sampler(params, obs, jax.random.key(i))
    return calls, outputs


def interleaved(fns: dict, rounds: int, budget_s: float) -> dict[str, float]:
    """Median seconds per variant, the variants called in alternating order each round."""
    for v in VARIANTS:
        jax.block_until_ready(fns[v](-1))  # warm-up
    times = {v: [] for v in VARIANTS}
    start = time.perf_counter()
    for r in range(rounds):
        for v in (VARIANTS if r % 2 == 0 else VARIANTS[::-1]):
            t0 = time.perf_counter()
            jax.block_until_ready(fns[v](r))
            times[v].append(time.perf_counter() - t0)
        if r >= 2 and time.perf_counter() - start > budget_s:
            break
    return {v: float(np.median(t)) for v, t in times.items()} | {"rounds": len(times["after"])}


def main(argv=None) -> dict:
    args = parse_args(argv)
    rows = []
    for label in args.configs:
        strides, chunk_len = CONFIGS[label]
        calls, outputs = compiled_calls(args.size, strides, chunk_len, args)
        for kind in ("train", "sample"):
            med = interleaved(calls[kind], args.rounds, args.budget_s)
            diff = float(np.max(np.abs(outputs[kind]["native"] - outputs[kind]["after"])))
            row = {"config": label, "strides": list(strides), "chunk_len": chunk_len, "kind": kind,
                   "rounds": med["rounds"], "native_median_s": med["native"], "after_median_s": med["after"],
                   "speedup": med["native"] / med["after"], "max_abs_diff": diff}
            rows.append(row)
            print(f"{label:<22} {kind:<6} native {med['native'] * 1e3:8.1f} ms  after {med['after'] * 1e3:8.1f} ms"
                  f"  x{row['speedup']:.2f}  max|diff| {diff:.1e}", flush=True)
    what = {"train": f"train step, batch {args.batch}",
            "sample": f"sample, N={args.num_samples}, DDIM {args.ddim_steps}"}
    table = markdown_table(["config", "call", "rounds", "native ms", "after ms", "native/after", "max abs diff"],
                           [[r["config"], what[r["kind"]], r["rounds"], r["native_median_s"] * 1e3,
                             r["after_median_s"] * 1e3, r["speedup"], r["max_abs_diff"]] for r in rows])
    return report_rows(NAME, argv, args, rows, table, module=MODULE)


if __name__ == "__main__":
    main()
