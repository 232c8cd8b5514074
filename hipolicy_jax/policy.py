"""From a trained network to an executable policy: the per-episode ``policy_fn`` and threshold calibration.

``make_policy_fn`` wraps the one sampler (``sampling.sample``) for ONE episode: the environment's base-rate
observation history ``{key: (obs_span, ...)}`` → per-stride windows (``data.windowing.gather_history``) → N samples
→ ``PolicyOutput(actions (L_c, A), stride, entropy)``. Rollouts ``vmap`` it over episodes; the parameters travel
as a traced ``PolicyArgs`` so one compiled rollout serves every evaluation of a run.

``calibrate_thresholds`` turns action entropies measured on held-out data into the M+1 ascending thresholds used
by entropy-guided execution: the paper took the 10th and 70th percentiles (for M = 3); the released values
(−6.0 / −5.5) are in RoboTwin joint-angle units and do not transfer to other action spaces.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, NamedTuple, Sequence

import jax
import numpy as np

from hipolicy_jax.config import EncoderConfig, PolicyConfig
from hipolicy_jax.data.windowing import gather_history
from hipolicy_jax.sampling import sample, sample_jit


def policy_obs_keys(encoder: EncoderConfig) -> tuple[str, ...]:
    """Observation keys the policy reads: state always, plus the image or point cloud."""
    return {"state": ("state",), "image": ("state", "image"), "pointcloud": ("state", "point_cloud")}[encoder.obs_type]


class PolicyArgs(NamedTuple):
    """The traced inputs of a policy: network variables, fitted normaliser, (M+1,) thresholds or None."""

    params: Any
    normalizer: Any
    thresholds: Any = None


@functools.lru_cache(maxsize=64)
def make_policy_fn(net, cfg: PolicyConfig, action_dim: int, *, num_samples: int | None = None,
                   num_steps: int | None = None, sampler: str | None = None) -> Callable:
    """``policy_fn(obs_history, key, args: PolicyArgs) -> PolicyOutput`` for one episode (vmap it over episodes).

    obs_history: ``{key: (chunk.obs_span, ...)}`` raw base-rate observations, oldest first, padded at episode start
    by repeating the first frame. Keys the policy does not read are ignored. The function is cached per static
    setting, so rollouts compiled for it are reused when only ``args`` (new parameters, thresholds) change.
    """
    from hipolicy_jax.envs.rollout import PolicyOutput

    keys = policy_obs_keys(cfg.encoder)

    def policy_fn(obs_history, key, args: PolicyArgs):
        missing = [k for k in keys if k not in obs_history]
        if missing:
            raise ValueError(f"obs_history lacks {missing}; the policy reads {keys}")
        windows = gather_history({k: obs_history[k] for k in keys}, cfg.chunk)
        obs = jax.tree.map(lambda x: x[None], windows)  # (1, M, L_h, ...)
        res = sample(args.params, args.normalizer, obs, key, net=net, cfg=cfg, action_dim=action_dim,
                     num_samples=num_samples, num_steps=num_steps, sampler=sampler, thresholds=args.thresholds)
        return PolicyOutput(actions=res.actions[0], stride=res.stride[0], entropy=res.entropy[0])

    return policy_fn


def measure_entropies(net, params, normalizer, cfg: PolicyConfig, action_dim: int, dataset, key: jax.Array, *,
                      max_windows: int = 256, batch_size: int = 64, num_samples: int | None = None,
                      num_steps: int | None = None, sampler: str | None = None) -> np.ndarray:
    """Action entropies (S,) of up to ``max_windows`` evenly spaced windows of ``dataset`` (e.g. held-out demos)."""
    n = num_samples or cfg.sampling.num_samples
    if n < 2:
        raise ValueError(f"sampling.num_samples: entropy needs N >= 2 samples, got {n}")
    idx = np.unique(np.linspace(0, len(dataset) - 1, min(max_windows, len(dataset))).astype(np.int64))
    out = []
    for i, start in enumerate(range(0, len(idx), batch_size)):
        chunk = idx[start:start + batch_size]
        chunk = np.concatenate([chunk, np.repeat(chunk[-1:], batch_size - len(chunk))])  # one compiled shape
        res = sample_jit(params, normalizer, dataset.get_batch(chunk)["obs"], jax.random.fold_in(key, i), net=net,
                         cfg=cfg, action_dim=action_dim, num_samples=n, num_steps=num_steps, sampler=sampler,
                         obs_normalized=True)
        out.append(np.asarray(res.entropy)[: len(idx) - start])
    return np.concatenate(out)


def calibrate_thresholds(entropies: np.ndarray, num_freqs: int,
                         percentiles: Sequence[float] | None = None) -> tuple[float, ...]:
    """M+1 ascending thresholds (−inf, inner percentiles…, +inf) from measured entropies.

    ``percentiles``: M-1 ascending values in (0, 100); default (10, 70) for M = 3 as in the paper, and evenly
    spaced otherwise.
    """
    h = np.asarray(entropies, np.float64).ravel()
    h = h[np.isfinite(h)]
    if h.size == 0:
        raise ValueError("calibrate_thresholds: no finite entropies (did you sample with N >= 2?)")
    if percentiles is None:
        percentiles = (10.0, 70.0) if num_freqs == 3 else tuple(np.linspace(0, 100, num_freqs + 1)[1:-1])
    p = tuple(float(x) for x in percentiles)
    if len(p) != num_freqs - 1 or any(not 0 < x < 100 for x in p) or any(a >= b for a, b in zip(p, p[1:])):
        raise ValueError(f"percentiles: need {num_freqs - 1} ascending values in (0, 100) for M={num_freqs}, got {p}")
    inner = np.percentile(h, p) if p else np.array([])
    inner = np.maximum.accumulate(inner + np.arange(len(inner)) * 1e-9)  # strictly ascending even for ties
    return (-math.inf, *(float(x) for x in inner), math.inf)
