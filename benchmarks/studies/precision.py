"""Does bf16 change what the policy samples? Per-dimension sample statistics of a trained run, float32 vs bfloat16.

    python -m benchmarks.studies.precision --checkpoints runs/paper/cpu/press_button/state/hipolicy/seed0 \
        runs/paper/cpu/latch_door/state/hipolicy/seed0 [--samples 1000 --observations 8]

For each run and each of ``--observations`` held-out demo observations, ``--samples`` chunks are drawn with the
run's inference setting (same keys) by the float32 network and by the same float32 parameters with
``model.compute_dtype='bfloat16'``. Per action dimension (and time step) it compares the sample mean and standard
deviation over every (observation, step, dimension) with a float32 std of at least 1e-3: ``mean_diff_over_std`` =
max |mean_bf16 - mean_f32| / std_f32 and ``std_rel_diff`` (median, 95th percentile, max) = |std_bf16 / std_f32 - 1|
(the 2 % criterion), with the same figures for two float32 draws with different keys as
the noise floor of ``--samples`` samples; also the stride agreement and the entropy difference. The closed-loop
check is ``python -m experiments.evaluate --checkpoint RUN --episodes 100 --compute-dtype bfloat16`` against
``--compute-dtype float32`` (same initial states).
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from benchmarks.common import base_parser, markdown_table, report_rows
from hipolicy_jax.runs.store import heldout_dataset, load_run, run_inference, with_compute_dtype
from hipolicy_jax.sampling import make_sampler

NAME = "precision"
MODULE = "studies.precision"  # python -m benchmarks.studies.precision


def parse_args(argv=None):
    p = base_parser(MODULE, __doc__)
    p.add_argument("--checkpoints", nargs="+", required=True, help="trained run dirs")
    p.add_argument("--samples", type=int, default=1000)
    p.add_argument("--observations", type=int, default=8)
    return p.parse_args(argv)


def _stats(chunks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(B, N, T, A) -> per (B, T, A) mean and std over the N samples."""
    return chunks.mean(axis=1), chunks.std(axis=1, ddof=1)


def _compare(a: np.ndarray, b: np.ndarray, min_std: float = 1e-3) -> dict[str, float]:
    """Mean and std differences of ``b`` against ``a`` over every (observation, step, action dim) whose std in
    ``a`` is at least ``min_std`` (action units: dims pinned at a clip bound have no spread to compare)."""
    (ma, sa), (mb, sb) = _stats(a), _stats(b)
    keep = sa >= min_std
    mean_d = (np.abs(mb - ma) / np.maximum(sa, min_std))[keep]
    std_d = np.abs(sb / np.maximum(sa, min_std) - 1.0)[keep]
    return {"cells": int(keep.sum()), "cells_total": int(keep.size),
            "mean_diff_over_std": float(np.max(mean_d)), "std_rel_diff": float(np.max(std_d)),
            "std_rel_diff_p95": float(np.percentile(std_d, 95)), "std_rel_diff_median": float(np.median(std_d))}


def compare_run(path: str, samples: int, observations: int) -> dict:
    """Float32 vs bfloat16 sample statistics of one run on ``observations`` held-out observations."""
    run = load_run(path)
    inference = dataclasses.replace(run_inference(run), num_samples=samples)
    val = heldout_dataset(run)
    idx = np.linspace(0, len(val) - 1, observations).astype(int)
    obs = val.get_batch(idx)["obs"]
    raw = {k: val.normalizer.unnormalize(k, v) if k in val.normalizer.stats else v for k, v in obs.items()}
    draws = {}
    for dt, key in (("float32", 0), ("float32_rekey", 1), ("bfloat16", 0)):
        r = with_compute_dtype(run, dt.split("_")[0])
        fn = make_sampler(r.policy.net, r.policy.cfg, r.action_dim, inference)
        draws[dt] = jax.tree.map(np.asarray, fn(r.policy.params, r.policy.normalizer, raw, jax.random.key(key)))
    f32, rekey, bf16 = draws["float32"], draws["float32_rekey"], draws["bfloat16"]
    chunks = {k: v.chunks for k, v in draws.items()}  # (B, N, T, A)
    return {"run": path, "task": run.task, "samples": samples, "observations": observations,
            "inference": dataclasses.asdict(inference),
            "bf16_vs_f32": _compare(chunks["float32"], chunks["bfloat16"]),
            "f32_rekeyed_vs_f32": _compare(chunks["float32"], chunks["float32_rekey"]),
            "stride_agreement": float(np.mean(f32.stride == bf16.stride)),
            "entropy_abs_diff": float(np.max(np.abs(f32.entropy - bf16.entropy))),
            "entropy_abs_diff_rekeyed": float(np.max(np.abs(f32.entropy - rekey.entropy)))}


def main(argv=None) -> dict:
    args = parse_args(argv)
    rows = []
    for path in args.checkpoints:
        r = compare_run(path, args.samples, args.observations)
        rows.append(r)
        b, f = r["bf16_vs_f32"], r["f32_rekeyed_vs_f32"]
        print(f"[{r['task']}] |Δstd|/std bf16 vs f32: median {100 * b['std_rel_diff_median']:.2f} %, p95 "
              f"{100 * b['std_rel_diff_p95']:.2f} %, max {100 * b['std_rel_diff']:.2f} %; two f32 draws: median "
              f"{100 * f['std_rel_diff_median']:.2f} %, p95 {100 * f['std_rel_diff_p95']:.2f} %, max "
              f"{100 * f['std_rel_diff']:.2f} %", flush=True)

    def pct(d):
        return (f"{100 * d['std_rel_diff_median']:.2f} / {100 * d['std_rel_diff_p95']:.2f} / "
                f"{100 * d['std_rel_diff']:.2f}")

    table = markdown_table(
        ["task", "samples x obs", "cells", "|Δstd|/std bf16 vs f32, median / p95 / max (%)",
         "same, two f32 draws (%)", "max |Δmean|/std bf16", "same, two f32 draws", "stride agreement",
         "max |ΔH| bf16", "max |ΔH| f32 draws"],
        [[r["task"], f"{r['samples']} x {r['observations']}",
          f"{r['bf16_vs_f32']['cells']} / {r['bf16_vs_f32']['cells_total']}", pct(r["bf16_vs_f32"]),
          pct(r["f32_rekeyed_vs_f32"]), r["bf16_vs_f32"]["mean_diff_over_std"],
          r["f32_rekeyed_vs_f32"]["mean_diff_over_std"], r["stride_agreement"], r["entropy_abs_diff"],
          r["entropy_abs_diff_rekeyed"]] for r in rows])
    return report_rows(NAME, argv, args, rows, table, module=MODULE)


if __name__ == "__main__":
    main()
