"""Before / after of the throughput changes, measured side by side (interleaved calls) in one run.

    python -m benchmarks.studies.compute_dtype                # CPU default: the DP low-dim and HiPolicy shapes
    python -m benchmarks.studies.compute_dtype --shapes hipolicy --n 100 --batch 128 --rounds 5

Variants, on the same parameters, batch and keys:

* train step ``where guard``: float32, the non-finite guard as the tree-wide ``where`` over the new and the old
  train state (the code before this change, rebuilt here from the library's pieces);
* train step ``float32``: the library's step (the guard is a ``lax.cond`` branch);
* train step ``bfloat16``: the same with ``model.compute_dtype='bfloat16'``;
* sampler ``float32`` / ``bfloat16``: ``sampling.make_sampler``, N samples of one observation, DDIM ``--steps``.

The rounds interleave the variants so that load from other processes hits them alike. Reported: the median per
variant and its ratio to the first variant of its workload, and the loss (train) or the largest sample difference
to float32 (sampler).
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from benchmarks.common import base_parser, bench_models, markdown_table, peer_shape_args, report_rows
from benchmarks.sampling import compiled_sampler
from benchmarks.train_step import train_setup
from hipolicy_jax.config import TrainConfig
from hipolicy_jax.heads import make_head
from hipolicy_jax.training import TrainState, ema_decay, make_optimizer, policy_loss

NAME = "compute_dtype"
MODULE = "studies.compute_dtype"  # python -m benchmarks.studies.compute_dtype


def parse_args(argv=None):
    p = base_parser(MODULE, __doc__, grid=True)
    p.add_argument("--n", type=int, default=100, help="samples per sampler call")
    p.add_argument("--steps", type=int, default=10, help="DDIM steps per sampler call")
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--quick", action="store_true", help="tiny size, N 4, batch 8, 2 rounds (the smoke test)")
    return peer_shape_args(p.parse_args(argv), n=4, batch=8, rounds=2, steps=2)


def where_guard_step(net, cfg, train_cfg: TrainConfig, tx):
    """The train step as it was before the guard became a branch: the update always runs, then a tree-wide
    ``where(finite, new, old)`` selects every leaf of the state."""
    head = make_head(cfg)

    def step(state: TrainState, batch: dict, base_key: jax.Array):
        key = jax.random.fold_in(base_key, state.step)
        loss, grads = jax.value_and_grad(policy_loss)(state.params, batch, key, net=net, head=head)
        finite = jnp.isfinite(loss) & jnp.isfinite(optax.tree.norm(grads))
        updates, opt_state = tx.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        ema = optax.incremental_update(params, state.ema_params, 1.0 - ema_decay(state.step + 1, train_cfg))
        new = TrainState(step=state.step + 1, params=params, ema_params=ema, opt_state=opt_state)
        new = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, state)
        return new, {"loss": loss}

    return jax.jit(step, donate_argnums=0)


def interleave(calls: dict, rounds: int) -> dict[str, list[float]]:
    """Each call once per round, in turn; ``block_until_ready`` on its result. Every call is run once first."""
    for fn in calls.values():
        jax.block_until_ready(fn())
    times = {name: [] for name in calls}
    for _ in range(rounds):
        for name, fn in calls.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - t0)
    return times


def train_calls(model, batch_size: int) -> tuple[dict, dict]:
    calls, losses = {}, {}
    for variant in ("where guard", "float32", "bfloat16"):
        dtype = "bfloat16" if variant == "bfloat16" else "float32"
        policy, step, batch, key, holder = train_setup(model, batch_size, **{"model.compute_dtype": dtype})
        if variant == "where guard":
            train_cfg = TrainConfig(batch_size=batch_size, num_steps=10_000, warmup_steps=10)
            step = where_guard_step(policy.net, policy.cfg, train_cfg, make_optimizer(train_cfg))

        def call(step=step, batch=batch, key=key, holder=holder, variant=variant):
            holder["state"], metrics = step(holder["state"], batch, key)
            losses[variant] = metrics["loss"]
            return metrics["loss"]

        calls[variant] = call
    return calls, losses


def sample_calls(model, n: int, steps: int) -> tuple[dict, dict]:
    calls, outs = {}, {}
    for dtype in ("float32", "bfloat16"):
        policy = model._replace(changes={**model.changes, "model.compute_dtype": dtype}).policy()
        fn = compiled_sampler(policy, "ddim", steps, n)

        def call(fn=fn, policy=policy, dtype=dtype):
            outs[dtype] = fn(policy.params, policy.normalizer, policy.obs, jax.random.key(0)).chunks
            return outs[dtype]

        calls[dtype] = call
    return calls, outs


def main(argv=None) -> dict:
    args = parse_args(argv)
    rows = []
    models = [m for m in bench_models(args) if m.dtype == "float32"]  # the dtype is a variant here
    for model in models:
        for workload in ("train", "sample"):
            if workload == "train":
                calls, extra = train_calls(model, args.batch)
                label = f"train step, batch {args.batch}"
            else:
                calls, extra = sample_calls(model, args.n, args.steps)
                label = f"sample N={args.n}, DDIM {args.steps}"
            times = interleave(calls, args.rounds)
            base = float(np.median(times[next(iter(calls))]))
            for variant, ts in times.items():
                med = float(np.median(ts))
                if workload == "train":
                    check = float(extra[variant])
                else:
                    check = float(jnp.max(jnp.abs(extra[variant] - extra["float32"])))
                rows.append({"model": model.size, "workload": workload, "label": label, "variant": variant,
                             "rounds": args.rounds, "median_s": med, "times_s": ts, "speedup": base / med,
                             "loss" if workload == "train" else "max_abs_diff_to_float32": check})
                print(f"[{model.size}] {label} {variant:<12} {med * 1e3:9.1f} ms  x{base / med:.2f}", flush=True)
    table = markdown_table(["model", "workload", "variant", "rounds", "median ms", "speed-up vs first variant",
                            "loss / max |Δ| to float32"],
                           [[r["model"], r["label"], r["variant"], r["rounds"], r["median_s"] * 1e3, r["speedup"],
                             r.get("loss", r.get("max_abs_diff_to_float32"))] for r in rows])
    return report_rows(NAME, argv, args, rows, table, module=MODULE)


if __name__ == "__main__":
    main()
