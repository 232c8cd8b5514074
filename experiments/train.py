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

import sys

from hipolicy_jax import parallel
from hipolicy_jax.runs.cli import prepare_process
from hipolicy_jax.runs.lock import RunLockedError
from hipolicy_jax.runs.train import RunConfig, main
from hipolicy_jax.trainer import CheckpointWriteError, TrainingInterrupted

def _quiet_unraisable(hook):
    """sys.unraisablehook that drops asyncio's 'Event loop is closed' from orbax's writer threads at shutdown."""
    def quiet(unraisable):
        if not (isinstance(unraisable.exc_value, RuntimeError) and "Event loop is closed" in str(unraisable.exc_value)):
            hook(unraisable)

    return quiet


if __name__ == "__main__":
    sys.unraisablehook = _quiet_unraisable(sys.unraisablehook)
    prepare_process()
    parallel.initialize_distributed()  # multi-process training when the launcher set JAX_COORDINATOR_ADDRESS
    try:
        main(tyro.cli(RunConfig, description=__doc__))
    except TrainingInterrupted as e:
        print(f"interrupted by {e}", file=sys.stderr)
        raise SystemExit(128 + e.signum)
    except (ValueError, FileNotFoundError, FileExistsError, FloatingPointError, RunLockedError,
            CheckpointWriteError) as e:
        raise SystemExit(f"error: {e}")
