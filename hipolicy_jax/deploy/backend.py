"""What a deployed policy computes, behind one interface: ``PolicyBackend.decide``.

A backend answers a batch of observation histories with the sampler's decisions — the same ``Decision`` the
evaluator's execution strategies read (``evaluation.policy.make_decision_fn``), vmapped over the batch::

    decide(obs {key: (B, obs_span, ...)}, key_data (B, 2) uint32) -> {
        "actions": (B, L_c, A) float32   sample 0's chunk at the selected frequency (unnormalised),
        "stride": (B,) int32, "freq_index": (B,) int32, "entropy": (B,) float32 (NaN when N = 1),
        "chunks": (B, N, M·L_c, A) float32  all N samples at every frequency}

``obs`` holds the raw control-rate history of every observation key the policy reads (oldest first, the last frame
current; pad an episode's start by repeating its first frame), ``key_data`` one raw threefry PRNG key per row
(``jax.random.key_data``): the decision is a deterministic function of it. Two backends:

- ``InProcessBackend``: a trained run's checkpoint, compiled here (``from_run``);
- ``ExportedBackend``: the ``jax.export`` artifact ``deploy.export`` writes, run without the model code.

Both carry ``metadata`` (the manifest: observation keys, shapes and dtypes, strides, chunk length, action dim,
inference settings, thresholds) and compile their batch size on first use (``warmup``).
"""

from __future__ import annotations

import dataclasses
import os
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax import envs as envs_lib
from hipolicy_jax.checkpoint import config_to_dict
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.deploy.artifact import load_artifact
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.evaluation.policy import PolicyArgs, make_decision_fn
from hipolicy_jax.models.policy_net import PolicyNet
from hipolicy_jax.runs.store import load_run, run_inference

MANIFEST_VERSION = 1
OUTPUT_KEYS = ("actions", "stride", "freq_index", "entropy", "chunks")


def obs_spec(task: str, cfg) -> dict[str, dict]:
    """{key: {"shape": [obs_span, ...], "dtype": ...}} of the history the policy of ``cfg`` reads on ``task``."""
    env = (envs_lib.external.make(task, cfg.encoder) if envs_lib.external.is_external(task)
           else envs_lib.make_for_encoder(task, cfg.encoder))
    return {k: {"shape": [cfg.chunk.obs_span, *env.obs_shapes[k]], "dtype": env.obs_dtypes[k]}
            for k in cfg.encoder.obs_keys}


def make_metadata(*, task: str, cfg, action_dim: int, inference: InferenceConfig, thresholds,
                  thresholds_source: str, obs: dict[str, dict], extra: dict | None = None) -> dict:
    """The manifest a backend and an export describe themselves with (strict JSON)."""
    return {"format": "hipolicy_jax.policy", "version": MANIFEST_VERSION, "task": task,
            "obs": obs, "action_dim": int(action_dim), "strides": list(cfg.chunk.strides),
            "chunk_len": int(cfg.chunk.chunk_len), "obs_horizon": int(cfg.chunk.obs_horizon),
            "obs_span": int(cfg.chunk.obs_span), "horizon": int(cfg.chunk.horizon),
            "num_samples": int(inference.num_samples), "objective": cfg.objective, "policy": config_to_dict(cfg),
            "inference": dataclasses.asdict(inference.sampler_settings()),
            "thresholds": [float(t) for t in np.asarray(thresholds).tolist()], "thresholds_source": thresholds_source,
            "outputs": {"actions": ["B", cfg.chunk.chunk_len, action_dim], "stride": ["B"], "freq_index": ["B"],
                        "entropy": ["B"], "chunks": ["B", inference.num_samples, cfg.chunk.horizon, action_dim]},
            **(extra or {})}


def batched_decide(decide_one: Callable) -> Callable:
    """``decide(args, obs {key: (B, ...)}, key_data (B, 2)) -> {name: (B, ...)}`` from the one-episode decision."""
    def decide(args, obs, key_data):
        keys = jax.random.wrap_key_data(key_data)
        d = jax.vmap(lambda o, k: decide_one(o, k, args))(obs, keys)
        return {"actions": d.actions.astype(jnp.float32), "stride": d.stride.astype(jnp.int32),
                "freq_index": d.freq_index.astype(jnp.int32), "entropy": d.entropy.astype(jnp.float32),
                "chunks": d.chunks.astype(jnp.float32)}

    return decide


class PolicyBackend:
    """Common part: ``metadata``, input checks and the timed ``decide``; subclasses set ``_fn`` and ``_args``."""

    metadata: dict
    _fn: Callable
    _args: Any

    def decide(self, obs: dict[str, np.ndarray], key_data: np.ndarray) -> dict[str, np.ndarray]:
        out = self._fn(self._args, {k: jnp.asarray(obs[k]) for k in self.metadata["obs"]},
                       jnp.asarray(key_data, jnp.uint32))
        return {k: np.asarray(v) for k, v in out.items()}

    def warmup(self, batch: int = 1) -> float:
        """Compile for ``batch`` rows and run once; → seconds it took."""
        t0 = time.perf_counter()
        self.decide(zeros_obs(self.metadata, batch), np.zeros((batch, 2), np.uint32))
        return time.perf_counter() - t0


def zeros_obs(metadata: dict, batch: int) -> dict[str, np.ndarray]:
    """An all-zero observation history batch as ``metadata`` describes it."""
    return {k: np.zeros((batch, *spec["shape"]), spec["dtype"]) for k, spec in metadata["obs"].items()}


class InProcessBackend(PolicyBackend):
    """A trained run's policy, compiled in this process (``jax.jit`` of the batched decision)."""

    def __init__(self, *, task: str, cfg, action_dim: int, params, normalizer, inference: InferenceConfig,
                 thresholds, thresholds_source: str = "given", extra: dict | None = None):
        self.cfg, self.inference = cfg, inference
        net = PolicyNet(cfg, action_dim)
        th = calibration.guidance_thresholds(thresholds, cfg.chunk.num_freqs, inference.entropy_guided)
        self._args = PolicyArgs(params, normalizer, jnp.asarray(th))
        self._decide = batched_decide(make_decision_fn(net, cfg, action_dim, inference))
        self._fn = jax.jit(self._decide)
        self.metadata = make_metadata(task=task, cfg=cfg, action_dim=action_dim, inference=inference,
                                      thresholds=th, thresholds_source=thresholds_source,
                                      obs=obs_spec(task, cfg), extra=extra)

    @classmethod
    def from_run(cls, path: str, inference: InferenceConfig | None = None, step: int | None = None
                 ) -> "InProcessBackend":
        """The (EMA) policy of a run dir, with its stored inference settings (or ``inference``) and calibration."""
        run = load_run(path, step)
        inference = inference or run_inference(run)
        calib = calibration.read_calibration(run.run_dir)
        thresholds, source = calibration.resolve_thresholds(inference, run.policy.cfg.chunk.num_freqs, calib)
        return cls(task=run.task, cfg=run.policy.cfg, action_dim=run.action_dim, params=run.policy.params,
                   normalizer=run.policy.normalizer, inference=inference, thresholds=thresholds,
                   thresholds_source=source,
                   extra={"run": os.path.relpath(run.run_dir), "checkpoint_step": int(run.policy.step)})


class ExportedBackend(PolicyBackend):
    """The policy ``deploy.export`` wrote: the serialised program, its flat parameters and the manifest; runs without
    the model code."""

    def __init__(self, directory: str):
        self.metadata, exported, leaves = load_artifact(directory)
        self._args = leaves
        self._fn = jax.jit(exported.call)
        self.directory = directory


__all__ = ["ExportedBackend", "InProcessBackend", "OUTPUT_KEYS", "PolicyBackend", "batched_decide",
           "make_metadata", "obs_spec", "zeros_obs"]
