"""What a deployed policy computes, behind one interface: ``PolicyBackend.decide``.

A backend answers a batch of observation histories with the sampler's decisions — the same ``Decision`` the
evaluator's execution strategies read (``evaluation.policy.make_decision_fn``), vmapped over the batch::

    decide(obs {key: (B, obs_span, ...)}, key_data (B, 2) uint32, prefix (B, P, A) float32 = zeros,
           prefix_valid (B,) bool = False) -> {
        "actions": (B, L_c, A) float32   sample 0's chunk at the selected frequency (unnormalised),
        "stride": (B,) int32, "freq_index": (B,) int32, "entropy": (B,) float32 (NaN when N = 1),
        "chunks": (B, N, M·L_c, A) float32  all N samples at every frequency (N = the manifest's num_samples:
                                             1 for a single-frequency policy without AAC)}

``obs`` holds the raw control-rate history of every observation key the policy reads (oldest first, the last frame
current; pad an episode's start by repeating its first frame), ``key_data`` one raw threefry PRNG key per row
(``jax.random.key_data``): the decision is a deterministic function of it. ``prefix``: the P actions a row's
previous chunk committed (asynchronous execution with ``handover='inpaint'``: P = ``inference.delay``; 0 otherwise,
``prefix_len``), inpainted into the first P steps of every frequency's segment where ``prefix_valid``; a row whose
``prefix_valid`` is False is exactly the decision without a prefix, so callers always pass both (the policy
server does). Two backends:

- ``InProcessBackend``: a trained policy compiled here (a run's: ``runs.serve.run_backend``);
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
from hipolicy_jax.deploy.artifact import MANIFEST_VERSION, load_artifact
from hipolicy_jax.evaluation import calibration
from hipolicy_jax.evaluation.policy import PolicyArgs, make_decision_fn
from hipolicy_jax.models.policy_net import PolicyNet

OUTPUT_KEYS = ("actions", "stride", "freq_index", "entropy", "chunks")


def obs_spec(task: str, cfg) -> dict[str, dict]:
    """{key: {"shape": [obs_span, ...], "dtype": ...}} of the history the policy of ``cfg`` reads on ``task``."""
    env = (envs_lib.external.make(task, cfg.encoder) if envs_lib.external.is_external(task)
           else envs_lib.make_for_encoder(task, cfg.encoder))
    return {k: {"shape": [cfg.chunk.obs_span, *env.obs_shapes[k]], "dtype": env.obs_dtypes[k]}
            for k in cfg.encoder.obs_keys}


def prefix_len(inference: InferenceConfig) -> int:
    """P, the committed actions the batched decision inpaints: ``inference.delay`` with ``handover='inpaint'``, else 0
    (the prefix input is then empty)."""
    return int(inference.delay) if inference.delay > 0 and inference.handover == "inpaint" else 0


def make_metadata(*, task: str, cfg, action_dim: int, inference: InferenceConfig, thresholds,
                  thresholds_source: str, obs: dict[str, dict], extra: dict | None = None) -> dict:
    """The manifest a backend and an export describe themselves with (strict JSON). ``num_samples``: the chunks a
    decision draws (``InferenceConfig.samples_drawn``: 1 for a single-frequency policy without AAC).
    ``action_kinds``: per action dimension ``'absolute'`` or ``'delta'`` (``ChunkConfig.kinds``; all absolute for a
    policy that declares none): a delta dimension of an action executed at stride s is the SUM of s control steps'
    displacements (``data.windowing.segment_actions``), to apply relative to where the robot is."""
    n = inference.samples_drawn(cfg.chunk.num_freqs)
    return {"format": "hipolicy_jax.policy", "version": MANIFEST_VERSION, "task": task,
            "obs": obs, "action_dim": int(action_dim), "action_kinds": list(cfg.chunk.kinds(int(action_dim))),
            "strides": list(cfg.chunk.strides),
            "chunk_len": int(cfg.chunk.chunk_len), "obs_horizon": int(cfg.chunk.obs_horizon),
            "obs_span": int(cfg.chunk.obs_span), "horizon": int(cfg.chunk.horizon),
            "num_samples": n, "objective": cfg.objective, "policy": config_to_dict(cfg),
            "inference": dataclasses.asdict(inference.decision_settings(cfg.chunk.num_freqs)),
            "thresholds": [float(t) for t in np.asarray(thresholds).tolist()], "thresholds_source": thresholds_source,
            "inputs": {"obs": {k: ["B", *spec["shape"]] for k, spec in obs.items()}, "key_data": ["B", 2],
                       "prefix": ["B", prefix_len(inference), action_dim], "prefix_valid": ["B"]},
            "outputs": {"actions": ["B", cfg.chunk.exec_steps, action_dim], "stride": ["B"], "freq_index": ["B"],
                        "entropy": ["B"], "chunks": ["B", n, cfg.chunk.horizon, action_dim]},
            **(extra or {})}


def batched_decide(decide_one: Callable) -> Callable:
    """``decide(args, obs {key: (B, ...)}, key_data (B, 2), prefix (B, P, A), prefix_valid (B,)) -> {name: (B, ...)}``
    from the one-episode decision; P = 0 (an empty prefix) decides without one."""
    def decide(args, obs, key_data, prefix, prefix_valid):
        keys = jax.random.wrap_key_data(key_data)
        if prefix.shape[1] == 0:
            d = jax.vmap(lambda o, k: decide_one(o, k, args))(obs, keys)
        else:
            d = jax.vmap(lambda o, k, p, v: decide_one(o, k, args, (p, v)))(
                obs, keys, prefix.astype(jnp.float32), prefix_valid.astype(bool))
        return {"actions": d.actions.astype(jnp.float32), "stride": d.stride.astype(jnp.int32),
                "freq_index": d.freq_index.astype(jnp.int32), "entropy": d.entropy.astype(jnp.float32),
                "chunks": d.chunks.astype(jnp.float32)}

    return decide


class PolicyBackend:
    """Common part: ``metadata``, input checks and the timed ``decide``; subclasses set ``_fn`` and ``_args``."""

    metadata: dict
    _fn: Callable
    _args: Any

    def decide(self, obs: dict[str, np.ndarray], key_data: np.ndarray, prefix: np.ndarray | None = None,
               prefix_valid: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """One batched decision (module docstring); no ``prefix`` / ``prefix_valid``: none valid."""
        batch = np.shape(key_data)[0]
        shape = (batch, *self.metadata["inputs"]["prefix"][1:])
        prefix = np.zeros(shape, np.float32) if prefix is None else np.asarray(prefix, np.float32)
        valid = np.zeros((batch,), bool) if prefix_valid is None else np.asarray(prefix_valid, bool)
        if prefix.shape != shape or valid.shape != (batch,):
            raise ValueError(f"prefix, prefix_valid: expected shapes {shape} and {(batch,)} (the manifest's inputs), "
                             f"got {prefix.shape} and {valid.shape}")
        out = self._fn(self._args, {k: jnp.asarray(obs[k]) for k in self.metadata["obs"]},
                       jnp.asarray(key_data, jnp.uint32), jnp.asarray(prefix), jnp.asarray(valid))
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


class ExportedBackend(PolicyBackend):
    """The policy ``deploy.export`` wrote: the serialised program, its flat parameters and the manifest; runs without
    the model code."""

    def __init__(self, directory: str):
        self.metadata, exported, leaves = load_artifact(directory)
        self._args = leaves
        self._fn = jax.jit(exported.call)
        self.directory = directory


__all__ = ["ExportedBackend", "InProcessBackend", "MANIFEST_VERSION", "OUTPUT_KEYS", "PolicyBackend",
           "batched_decide", "make_metadata", "obs_spec", "prefix_len", "zeros_obs"]
