"""What checked checkpoints cost a load: restores with and without verifying the SHA-256 checksums.

    python -m benchmarks.studies.checkpoint_load              # cpu and paper sizes, state policy, 10 rounds
    python -m benchmarks.studies.checkpoint_load --sizes tiny --rounds 2

Per size: a train state (parameters, EMA parameters, AdamW state) of the benchmark policy and a fitted normaliser
are saved once with ``checkpoint.Checkpointer`` (which stores the checksums). Then, in interleaved rounds (the order
rotates each round), four restores of that step:

- ``policy, checked``: what ``load_policy`` (evaluate, calibrate, export, serve) does now: the step, EMA parameters
  and normaliser alone (``restore_policy``), verified;
- ``full, unchecked``: what ``load_policy`` did before checksums: the whole train state, not verified;
- ``full, checked``: what training's resume does now: the whole train state, every tree verified;

and, on the trees a policy load returns, the checksums alone (their share of a policy load).

Reported: the trees' bytes, the median of each and the ratios ``policy, checked / full, unchecked`` (a policy load
now against before) and ``full, checked / full, unchecked`` (resume). Writes
``benchmarks/studies/results/checkpoint_load_<device>.json``. The files are read from the page cache after the
first round, so the checksums' share is that of a warm disk: the largest it can be.
"""

from __future__ import annotations

import os
import tempfile
import time

import jax
import numpy as np

from benchmarks.common import base_parser, make_bench_policy, markdown_table, report_rows
from hipolicy_jax import checkpoint
from hipolicy_jax.config import TrainConfig
from hipolicy_jax.training import init_train_state, make_optimizer

NAME = "checkpoint_load"
MODULE = "studies.checkpoint_load"  # python -m benchmarks.studies.checkpoint_load


def parse_args(argv=None):
    p = base_parser(MODULE, __doc__)
    p.add_argument("--sizes", nargs="+", default=["cpu", "paper"], choices=["tiny", "cpu", "paper"])
    p.add_argument("--rounds", type=int, default=10, help="timed restores of each kind")
    return p.parse_args(argv)


def _folder_bytes(path: str) -> int:
    return sum(os.path.getsize(os.path.join(root, f)) for root, _, files in os.walk(path) for f in files)


KINDS = ("policy_checked", "full_unchecked", "full_checked")


def measure(size: str, rounds: int) -> dict:
    """One size's row: tree bytes, median seconds of each kind of restore (``KINDS``), their ratios."""
    policy = make_bench_policy(size, "state")
    tx = make_optimizer(TrainConfig())
    state = init_train_state(policy.params, tx)
    state = state.replace(step=state.step + 1)
    abstract_state = jax.eval_shape(lambda: state)
    abstract_params = jax.eval_shape(lambda: policy.params)
    with tempfile.TemporaryDirectory() as tmp:
        with checkpoint.Checkpointer(tmp) as ckpt:
            ckpt.save(1, state, policy.normalizer, {"benchmark": size}, force=True)
            ckpt.wait()

        def restore(kind: str):
            with checkpoint.Checkpointer(tmp) as ckpt:  # a fresh one per load, as load_policy and resume open one
                if kind.startswith("policy"):
                    return ckpt.restore_policy(1, abstract_params, check=kind.endswith("_checked"))
                return ckpt.restore(1, abstract_state, check=kind.endswith("_checked"))

        times: dict[str, list[float]] = {k: [] for k in KINDS + ("policy_checksums",)}
        for kind in KINDS:  # warm-up: the page cache, orbax's first-call set-up
            restore(kind)
        for r in range(rounds):
            for kind in KINDS[r % len(KINDS):] + KINDS[:r % len(KINDS)]:
                t0 = time.perf_counter()
                out = jax.block_until_ready(restore(kind))
                times[kind].append(time.perf_counter() - t0)
                if kind == "policy_checked":
                    ema, norm, meta = out
                    t0 = time.perf_counter()
                    read = checkpoint.tree_checksums({"step": state.step, "ema_params": ema, "normalizer": norm})
                    times["policy_checksums"].append(time.perf_counter() - t0)
                    assert all(meta["checksums"][k] == v for k, v in read.items())
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {"size": size, "params": int(sum(np.asarray(x).size for x in jax.tree.leaves(state.params))),
            "tree_bytes": sum(np.asarray(x).nbytes for x in jax.tree.leaves(state)), "rounds": rounds,
            **{f"{k}_median_s": v for k, v in med.items()},
            "policy_load_vs_before": med["policy_checked"] / med["full_unchecked"],
            "resume_vs_before": med["full_checked"] / med["full_unchecked"],
            "policy_checksums_share": med["policy_checksums"] / med["policy_checked"],
            "times_s": {k: [float(x) for x in v] for k, v in times.items()}}


def main(argv=None) -> dict:
    args = parse_args(argv)
    rows = [measure(size, args.rounds) for size in args.sizes]
    table = markdown_table(
        ["size", "params", "train state (MB)", "policy, checked (s)", "full, unchecked (s)", "full, checked (s)",
         "policy load now / before", "resume now / before", "checksums' share of a policy load"],
        [[r["size"], r["params"], r["tree_bytes"] / 1e6, r["policy_checked_median_s"], r["full_unchecked_median_s"],
          r["full_checked_median_s"], f"{r['policy_load_vs_before']:.2f}x", f"{r['resume_vs_before']:.2f}x",
          f"{100 * r['policy_checksums_share']:.0f} %"] for r in rows])
    return report_rows(NAME, argv, args, rows, table, module=MODULE, note=note(rows))


def note(rows: list[dict]) -> str:
    """The figures in words, every number from ``rows``."""
    parts = [f"{r['size']} size ({r['tree_bytes'] / 1e6:,.0f} MB of train state): a policy load takes "
             f"{r['policy_load_vs_before']:.2f}x the time of the unchecked full load it replaces "
             f"({r['policy_checked_median_s']:.3f} s vs {r['full_unchecked_median_s']:.3f} s), its checksums "
             f"{100 * r['policy_checksums_share']:.0f} % of it; a resume {r['resume_vs_before']:.2f}x "
             f"(+{r['full_checked_median_s'] - r['full_unchecked_median_s']:.2f} s, once per training run)"
             for r in rows]
    return ("A policy load (evaluate, calibrate, export, serve) now reads only the trees a policy uses (step, EMA "
            "parameters, normaliser) and verifies them; training's resume reads and verifies all five. "
            + "; ".join(parts) + ".")


if __name__ == "__main__":
    main()
