"""Before / after of the sampler optimisations, measured side by side (interleaved calls) in one run.

    python -m benchmarks.studies.optimisation     # CPU default: cpu size, state obs, DDIM 10 + DDPM 100, N 1/100

Variants, all through ``sampling.make_sampler`` on the same parameters and keys:

* ``before``: the FiLM heads (step MLP and ``mish(step)·W_t + mish(cond)·W_c + b`` of every block) run inside every
  denoising step and mish is ``jax.nn.mish`` (``exp + log1p + tanh``). The code before the optimisation ran the
  unsplit ``mish([step ⊕ cond])·W + b``; the split form lets XLA hoist the loop-invariant half by itself, so this
  baseline is if anything faster than the original and the measured gain a lower bound;
* ``film``: the observation half ``mish(cond)·W_c + b`` computed once per call (``PolicyNet.film_condition``),
  ``jax.nn.mish``;
* ``mish``: FiLM per step, one-``exp`` closed-form mish (``models.unet.mish``);
* ``after``: both (what ``sample`` does now).

Every variant is traced once; the rounds interleave the variants so that load from other processes hits them
alike. Reported: median latency per variant and ``before / after``, and that outputs agree to float rounding.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import math
import time

import jax
import numpy as np

from benchmarks.common import device_kind, make_bench_policy, markdown_table, report_rows
from hipolicy_jax.models import unet
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.sampling import make_sampler

NAME = "optimisation"
MODULE = "studies.optimisation"  # python -m benchmarks.studies.optimisation
VARIANTS = ("before", "film", "mish", "after")


@contextlib.contextmanager
def exact_mish(enabled: bool):
    """Within the block, the U-Net uses ``jax.nn.mish`` (the pre-optimisation activation) when ``enabled``."""
    saved = unet.mish
    unet.mish = jax.nn.mish if enabled else saved
    try:
        yield
    finally:
        unet.mish = saved


@dataclasses.dataclass(frozen=True)
class PerStepNet:
    """A ``PolicyNet`` seen through the plain protocol (``encode`` / ``denoise`` only): the sampler then runs the
    FiLM heads in every step. ``exact`` selects ``jax.nn.mish`` while tracing. Hashable, so it is a valid static
    argument and each variant compiles separately."""

    net: object
    exact: bool

    def encode(self, *a, **k):  # protocol marker: the sampler passes the bound method to ``apply``
        raise NotImplementedError

    def denoise(self, *a, **k):  # protocol marker
        raise NotImplementedError

    @property
    def action_dim(self) -> int:
        return self.net.action_dim

    def apply(self, params, *args, method, **kwargs):
        with exact_mish(self.exact):
            return self.net.apply(params, *args, method=method.__name__, **kwargs)


@dataclasses.dataclass(frozen=True)
class PrecomputeNet(PerStepNet):
    """As ``PerStepNet`` but also offering the FiLM precompute protocol, so the sampler hoists the FiLM heads."""

    def film_condition(self, *a, **k):  # protocol marker
        raise NotImplementedError

    def film_steps(self, *a, **k):  # protocol marker
        raise NotImplementedError

    def denoise_film(self, *a, **k):  # protocol marker
        raise NotImplementedError


def variant_net(net, variant: str):
    """The network object the sampler gets for ``variant`` (``after`` is the ``PolicyNet`` itself)."""
    return {"before": PerStepNet(net, True), "film": PrecomputeNet(net, True), "mish": PerStepNet(net, False),
            "after": net}[variant]


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m benchmarks.studies.optimisation", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="cpu", choices=["tiny", "cpu", "paper"])
    p.add_argument("--obs", default="state", choices=["state", "image", "pointcloud"])
    p.add_argument("--ns", nargs="+", type=int, default=[1, 100])
    p.add_argument("--samplers", nargs="+", default=["ddim", "ddpm"], choices=["ddpm", "ddim"])
    p.add_argument("--ddim-steps", type=int, default=10)
    p.add_argument("--rounds", type=int, default=15, help="interleaved rounds (one call of every variant each)")
    p.add_argument("--budget-s", type=float, default=60.0 if device_kind() == "cpu" else None,
                   help="stop a setting's rounds once it has spent this long (at least 3 rounds)")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS,
                   help="variants to time ('before' and 'after' are always included)")
    p.add_argument("--out-dir", default=None)
    args = p.parse_args(argv)
    args.variants = [v for v in VARIANTS if v in set(args.variants) | {"before", "after"}]
    return args


def compare(policy, sampler: str, steps: int, n: int, rounds: int, budget_s: float | None,
            variants=VARIANTS) -> dict:
    """Interleaved timing of ``variants`` at one (sampler, N); returns medians (NaN for variants not timed),
    speed-ups over ``before`` and the largest output difference to ``after``."""
    inference = InferenceConfig(num_samples=n, sampler=sampler, num_steps=steps)
    fns = {v: make_sampler(variant_net(policy.net, v), policy.cfg, policy.net.action_dim, inference)
           for v in variants}

    def call(variant, key):
        return fns[variant](policy.params, policy.normalizer, policy.obs, key).chunks

    outs = {v: np.asarray(call(v, jax.random.key(0))) for v in variants}  # compiles every variant
    cache = sum(fn._cache_size() for fn in fns.values())
    times = {v: [] for v in variants}
    start = time.perf_counter()
    for r in range(rounds):
        order = variants if r % 2 == 0 else variants[::-1]
        for v in order:
            t0 = time.perf_counter()
            call(v, jax.random.key(r + 1)).block_until_ready()
            times[v].append(time.perf_counter() - t0)
        if budget_s is not None and r >= 2 and time.perf_counter() - start > budget_s:
            break
    med = {v: float(np.median(times[v])) if v in times else math.nan for v in VARIANTS}
    gap = max(float(np.max(np.abs(outs[v] - outs["after"]))) for v in variants)
    return {"sampler": sampler, "steps": steps, "n": n, "rounds": len(times["after"]),
            **{f"{v}_median_s": med[v] for v in VARIANTS},
            **{f"speedup_{v}": med["before"] / med[v] for v in VARIANTS if v != "before"},
            "max_abs_diff": gap, "retraces": sum(fn._cache_size() for fn in fns.values()) - cache}


def main(argv=None) -> dict:
    args = parse_args(argv)
    policy = make_bench_policy(args.size, args.obs)
    rows = []
    for sampler in args.samplers:
        steps = policy.cfg.diffusion.num_train_steps if sampler == "ddpm" else args.ddim_steps
        for n in args.ns:
            r = compare(policy, sampler, steps, n, args.rounds, args.budget_s, args.variants)
            rows.append(r)
            print(f"{sampler}{steps:>4} N={n:<4} " + "  ".join(f"{v} {r[f'{v}_median_s'] * 1e3:.1f} ms"
                                                              for v in VARIANTS)
                  + f"  before/after x{r['speedup_after']:.3f}  max|diff| {r['max_abs_diff']:.1e}", flush=True)
    table = markdown_table(
        ["sampler", "steps", "N", "rounds", "before ms", "FiLM hoisted ms", "fast mish ms", "after ms",
         "before/after", "max abs diff"],
        [[r["sampler"], r["steps"], r["n"], r["rounds"], r["before_median_s"] * 1e3, r["film_median_s"] * 1e3,
          r["mish_median_s"] * 1e3, r["after_median_s"] * 1e3, r["speedup_after"], r["max_abs_diff"]]
         for r in rows])
    return report_rows(NAME, argv, args, rows, table, module=MODULE, size=args.size, obs=args.obs)


if __name__ == "__main__":
    main()
