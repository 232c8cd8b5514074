"""Train DP + HiPolicy on an MJX task: ``python -m experiments.train [--task latch_door] [--train.num-steps 500] ...``.

With no arguments: collects (or reuses) 100 expert demos of the default task, trains a CPU-sized HiPolicy on
low-dim state with a progress bar, evaluates periodically with batched MJX rollouts, calibrates the entropy
thresholds on held-out demos, and writes under ``--out`` (default ``runs/<task>_<obs>_seed<seed>``):
``checkpoints/``, ``metrics.jsonl``, ``tb/`` (TensorBoard), ``inference.json``, ``calibration.json`` and
``summary.json``. Re-running the same command resumes from the last checkpoint; ``--inference.*`` settings (N,
sampler, steps, thresholds) can change between runs without blocking the resume. ``--help`` lists every option.
"""

from __future__ import annotations

import tyro

from hipolicy_jax.runs.train import RunConfig, main

if __name__ == "__main__":
    try:
        main(tyro.cli(RunConfig, description=__doc__))
    except (ValueError, FileNotFoundError, FileExistsError, FloatingPointError) as e:
        raise SystemExit(f"error: {e}")
