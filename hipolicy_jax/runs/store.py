"""A trained run on disk: locate and load it, its stored inference settings, calibration and held-out data.

A run directory (``experiments.train --out``) holds ``checkpoints/<step>/`` (orbax: state, normaliser, meta),
``inference.json`` (the ``InferenceConfig`` its evaluations used), ``calibration.json`` (entropy thresholds and
how they were measured), ``summary.json``, ``metrics.jsonl`` and ``tb/``. The inference settings are stored
beside the checkpoints, not in them: they are not part of the run's identity.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import NamedTuple

import jax
import numpy as np

from hipolicy_jax import jsonio
from hipolicy_jax.checkpoint import LoadedPolicy, config_from_dict, load_policy
from hipolicy_jax.config import InferenceConfig, replace
from hipolicy_jax.data.dataset import SequenceDataset, train_heldout_datasets
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.evaluation.evaluator import Evaluator

INFERENCE_FILE = "inference.json"
# Salt of the evaluation key: rollouts use fold_in(key(seed), EVAL_SALT), so their initial states never coincide
# with those of the demos collected from key(seed).
EVAL_SALT = 0x5EED


def eval_key(seed: int) -> jax.Array:
    """Evaluation PRNG key of a seed, disjoint from the demo-collection key ``key(seed)``."""
    return jax.random.fold_in(jax.random.key(seed), EVAL_SALT)


def write_json(path: str, obj) -> str:
    """Strict JSON (``jsonio``: NaN as null, ±∞ as strings)."""
    return jsonio.dump(obj, path)


def read_json(path: str):
    return jsonio.load(path)


def write_inference(run_dir: str, inference: InferenceConfig) -> str:
    """Store the inference settings of a run's evaluations beside it (``inference.json``)."""
    return write_json(os.path.join(run_dir, INFERENCE_FILE), dataclasses.asdict(inference))


def read_inference(run_dir: str) -> InferenceConfig | None:
    """The run's stored ``InferenceConfig`` (None when the run has none)."""
    path = os.path.join(run_dir, INFERENCE_FILE)
    return config_from_dict(InferenceConfig, read_json(path)) if os.path.exists(path) else None


class Run(NamedTuple):
    """A trained run: its output dir (summary, calibration, eval/), checkpoint dir, loaded policy and task."""

    run_dir: str
    ckpt_dir: str
    policy: LoadedPolicy
    task: str

    @property
    def action_dim(self) -> int:
        return int(self.policy.meta["action_dim"])

    @property
    def seed(self) -> int:
        """The training seed."""
        return int(self.policy.meta["train"]["seed"])


def resolve_run(path: str) -> tuple[str, str]:
    """(run_dir, checkpoint_dir) from a train output dir (holding ``checkpoints/``) or the checkpoints dir itself."""
    path = os.path.abspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"checkpoint: {path} does not exist; expected a run directory (holding "
                                f"checkpoints/) or its checkpoints/ directory")
    if os.path.isdir(os.path.join(path, "checkpoints")):
        return path, os.path.join(path, "checkpoints")
    if os.path.isdir(path) and any(d.isdigit() for d in os.listdir(path)):
        return os.path.dirname(path), path
    raise FileNotFoundError(f"checkpoint: {path} is neither a run dir holding checkpoints/ nor a checkpoints dir")


def load_run(path: str, step: int | None = None) -> Run:
    """Load the (EMA) policy of a run dir or checkpoints dir; the task comes from the checkpoint's meta."""
    run_dir, ckpt_dir = resolve_run(path)
    loaded = load_policy(ckpt_dir, step)
    # orbax restores device-committed arrays; jit keys its cache on commitment, so an uncommitted copy lets an
    # evaluator compiled for the training state (same process) run it without compiling again
    uncommitted = functools.partial(jax.tree.map, lambda x: jax.device_put(np.asarray(x)))
    loaded = loaded._replace(params=uncommitted(loaded.params), normalizer=uncommitted(loaded.normalizer))
    if "task" not in loaded.meta:
        raise ValueError(f"{ckpt_dir}: checkpoint meta lacks 'task' (not written by experiments.train?)")
    return Run(run_dir, ckpt_dir, loaded, str(loaded.meta["task"]))


def with_compute_dtype(run: Run, compute_dtype: str) -> Run:
    """The run with its U-Net rebuilt for ``model.compute_dtype`` ('float32' | 'bfloat16'; 'run': unchanged). The
    parameters are the same float32 ones: only the operand dtype of the convolutions and fusion attention changes."""
    if compute_dtype in ("run", run.policy.cfg.model.compute_dtype):
        return run
    from hipolicy_jax.models.policy_net import PolicyNet

    cfg = replace(run.policy.cfg, **{"model.compute_dtype": compute_dtype})
    return run._replace(policy=run.policy._replace(cfg=cfg, net=PolicyNet(cfg, run.action_dim)))


def run_inference(run: Run, default: InferenceConfig = InferenceConfig()) -> InferenceConfig:
    """The inference settings stored with the run, else ``default``."""
    return read_inference(run.run_dir) or default


def heldout_dataset(run: Run) -> SequenceDataset:
    """The run's held-out demo windows: the episode split of training, the checkpoint's normaliser."""
    meta, cfg = run.policy.meta, run.policy.cfg
    if not os.path.exists(meta.get("data", "")):
        raise FileNotFoundError(f"the run's demo buffer {meta.get('data')!r} (meta['data']) is missing; "
                                f"calibrate from rollouts (--source rollouts) or re-collect it with "
                                f"experiments.collect")
    buffer = ReplayBuffer.load(meta["data"])
    _, val = train_heldout_datasets(buffer, cfg.chunk, cfg.encoder.obs_keys, float(meta["val_ratio"]), run.seed,
                                    normalizer=run.policy.normalizer,
                                    max_action_pad=meta["train"].get("max_action_pad"))  # absent: written before it
    return val


def make_evaluator(run: Run, inference: InferenceConfig, max_steps: int | None = None) -> Evaluator:
    """An ``Evaluator`` for the run's task, policy config and action dim."""
    return Evaluator(run.task, run.policy.cfg, run.action_dim, inference, max_steps=max_steps)
