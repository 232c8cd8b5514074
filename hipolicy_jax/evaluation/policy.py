"""From a trained network to an executable per-episode policy: ``make_policy_fn``.

``make_policy_fn`` wraps the one sampler (``sampling.sample``) for ONE episode: the environment's base-rate
observation history ``{key: (obs_span, ...)}`` → per-stride windows (``data.windowing.gather_history``) → N samples
→ ``PolicyOutput(actions (L_c, A), stride, entropy)``. Rollouts ``vmap`` it over episodes; the parameters travel
as a traced ``PolicyArgs`` so one compiled rollout serves every evaluation of a run (``Evaluator``).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax

from hipolicy_jax.config import InferenceConfig, PolicyConfig
from hipolicy_jax.data.windowing import gather_history
from hipolicy_jax.evaluation.rollout import PolicyOutput
from hipolicy_jax.sampling import sample


class PolicyArgs(NamedTuple):
    """The traced inputs of a policy: network variables, fitted normaliser, (M+1,) thresholds or None."""

    params: Any
    normalizer: Any
    thresholds: Any = None


def make_policy_fn(net, cfg: PolicyConfig, action_dim: int,
                   inference: InferenceConfig = InferenceConfig()) -> Callable:
    """``policy_fn(obs_history, key, args: PolicyArgs) -> PolicyOutput`` for one episode (vmap it over episodes).

    obs_history: ``{key: (chunk.obs_span, ...)}`` raw base-rate observations, oldest first, padded at episode start
    by repeating the first frame. Keys the policy does not read are ignored. Only ``inference.sampler_settings()``
    is used (N, sampler, steps); thresholds travel in ``args``.
    """
    keys = cfg.encoder.obs_keys
    inference = inference.sampler_settings()

    def policy_fn(obs_history, key, args: PolicyArgs):
        missing = [k for k in keys if k not in obs_history]
        if missing:
            raise ValueError(f"obs_history lacks {missing}; the policy reads {keys}")
        windows = gather_history({k: obs_history[k] for k in keys}, cfg.chunk)
        obs = jax.tree.map(lambda x: x[None], windows)  # (1, M, L_h, ...)
        res = sample(args.params, args.normalizer, obs, key, args.thresholds, net=net, cfg=cfg,
                     action_dim=action_dim, inference=inference)
        return PolicyOutput(actions=res.actions[0], stride=res.stride[0], entropy=res.entropy[0])

    return policy_fn
