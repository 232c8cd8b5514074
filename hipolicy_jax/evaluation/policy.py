"""From a trained network to an executable per-episode policy: ``make_policy_fn``.

``make_policy_fn`` wraps the one sampler (``sampling.sample``) for ONE episode: the environment's base-rate
observation history ``{key: (obs_span, ...)}`` → per-stride windows (``data.windowing.gather_history``) → N samples
→ the execution strategy (``execution``) → ``PolicyOutput(actions, stride, entropy, num_actions)``. Rollouts
``vmap`` it over episodes; the parameters travel as a traced ``PolicyArgs`` so one compiled rollout serves every
evaluation of a run (``Evaluator``).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax

from hipolicy_jax.config import InferenceConfig, PolicyConfig
from hipolicy_jax.data.windowing import gather_history
from hipolicy_jax.evaluation.execution import Decision, make_execution
from hipolicy_jax.sampling import sample


class PolicyArgs(NamedTuple):
    """The traced inputs of a policy: network variables, fitted normaliser, (M+1,) thresholds or None."""

    params: Any
    normalizer: Any
    thresholds: Any = None


def make_decision_fn(net, cfg: PolicyConfig, action_dim: int,
                     inference: InferenceConfig = InferenceConfig()) -> Callable[..., Decision]:
    """``decide(obs_history, key, args: PolicyArgs, prefix=None) -> Decision`` for ONE episode: the sampler's
    chunks (``inference.samples_drawn``: N, or sample 0 alone where nothing reads the others), entropy and selected
    frequency before any execution strategy; ``Decision.actions`` are sample 0's executable actions at that
    frequency (``chunk.exec_steps`` from ``chunk.exec_start``: the whole segment for HiPolicy). ``prefix``: None or ``(actions (d, A),
    valid ())`` committed actions to inpaint (``sampling.sample``). What the policy server and the exported policy
    compute; ``make_policy_fn`` adds the execution strategy."""
    keys = cfg.encoder.obs_keys
    inference = inference.decision_settings(cfg.chunk.num_freqs)  # one stride, no AAC: sample 0 alone

    def decide(obs_history, key, args: PolicyArgs, prefix=None) -> Decision:
        missing = [k for k in keys if k not in obs_history]
        if missing:
            raise ValueError(f"obs_history lacks {missing}; the policy reads {keys}")
        windows = gather_history({k: obs_history[k] for k in keys}, cfg.chunk)
        obs = jax.tree.map(lambda x: x[None], windows)  # (1, M, L_h, ...)
        pre = {} if prefix is None else {"prefix": prefix[0][None], "prefix_valid": prefix[1][None]}
        res = sample(args.params, args.normalizer, obs, key, args.thresholds, net=net, cfg=cfg,
                     action_dim=action_dim, inference=inference, **pre)
        d = Decision(*(x[0] for x in res))
        start = cfg.chunk.exec_start  # the executable actions: from the current frame, chunk.exec_steps of them
        return d._replace(actions=d.actions[start:start + cfg.chunk.exec_steps])

    return decide


def make_policy_fn(net, cfg: PolicyConfig, action_dim: int,
                   inference: InferenceConfig = InferenceConfig()) -> tuple[Callable, Callable]:
    """``(policy_fn, init_fn)`` for ONE episode (vmap over episodes), as ``rollout.Rollout`` takes them:
    ``policy_fn(obs_history, key, execution_state, args: PolicyArgs) -> (PolicyOutput, execution_state)`` and
    ``init_fn(first_obs, key) -> execution_state``.

    obs_history: ``{key: (chunk.obs_span, ...)}`` raw base-rate observations, oldest first, padded at episode start
    by repeating the first frame. Keys the policy does not read are ignored. The N samples become actions through
    ``inference.execution`` (``execution.make_execution``); only ``inference.sampler_settings()`` is used, the
    thresholds travel in ``args``.
    """
    execution = make_execution(inference)
    decide = make_decision_fn(net, cfg, action_dim, inference)
    prefix = getattr(execution, "prefix", lambda state: None)

    def policy_fn(obs_history, key, state, args: PolicyArgs):
        return execution.decide(decide(obs_history, key, args, prefix(state)), state, cfg.chunk)

    def init_fn(obs, key):
        return execution.init(cfg.chunk, action_dim)

    return policy_fn, init_fn
