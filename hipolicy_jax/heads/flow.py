"""The flow-matching head: conditional flow matching on the linear (OT) path, sampled with Euler steps.

As openpi's action expert: the path ``x_τ = τ·ε + (1−τ)·a`` runs from the action chunk ``a`` (τ = 0) to Gaussian
noise ``ε`` (τ = 1); the network regresses the path's velocity ``u = ε − a`` from ``x_τ`` and the time input
``τ·time_scale``. Sampling integrates ``dx/dτ = v(x, τ)`` from τ = 1 to 0 with K Euler steps
``x ← x − (1/K)·v(x, τ_k)``, τ_k = 1 − k/K; K is ``inference.num_steps`` (default 10) and may be 1, where the sample
is ``ε − v(ε, 1)``: the model's mean prediction of the chunk. The final sample is clipped to the normalised action
range when ``flow.clip_sample``.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax.config import FlowConfig, InferenceConfig, PolicyConfig
from hipolicy_jax.heads.base import StepPlan, TrainingExample, identity

SAMPLERS = ("euler",)
DEFAULT_STEPS = 10


class EulerTable(NamedTuple):
    """Per Euler step arrays, each (K,): ``time`` the network's time input τ_k·time_scale, ``dt`` the step 1/K."""

    time: jax.Array
    dt: jax.Array
    tau_next: jax.Array  # τ after the step, 1 − (k+1)/K (0 after the last)


def resolve_sampler(inference: InferenceConfig) -> tuple[str, int]:
    """(sampler, number of Euler steps) of ``inference`` for this head: ``auto`` is ``euler``, 10 steps."""
    sampler = "euler" if inference.sampler == "auto" else inference.sampler
    if sampler not in SAMPLERS:
        raise ValueError(f"inference.sampler: the flow head samples with 'euler' (or 'auto'), got {sampler!r}")
    return sampler, DEFAULT_STEPS if inference.num_steps is None else inference.num_steps


def euler_table(cfg: FlowConfig, num_steps: int) -> EulerTable:
    """Times τ_k = 1 − k/K (k = 0..K−1, scaled by ``time_scale``) and steps 1/K."""
    if num_steps < 1:
        raise ValueError(f"inference.num_steps: the flow head needs >= 1 Euler step, got {num_steps}")
    tau = 1.0 - np.arange(num_steps, dtype=np.float64) / num_steps
    return EulerTable(jnp.asarray(tau * cfg.time_scale, jnp.float32), jnp.full((num_steps,), 1.0 / num_steps),
                      jnp.asarray(1.0 - np.arange(1, num_steps + 1) / num_steps, jnp.float32))


def sample_time(cfg: FlowConfig, key: jax.Array, batch: int) -> jax.Array:
    """Training times τ (B,): uniform on [0, 1), or openpi's 0.001 + 0.999·Beta(1.5, 1)."""
    if cfg.time_sampling == "beta":
        return 0.001 + 0.999 * jax.random.beta(key, 1.5, 1.0, (batch,))
    return jax.random.uniform(key, (batch,))


@dataclasses.dataclass(frozen=True)
class FlowHead:
    """Conditional flow matching (velocity prediction) and Euler sampling."""

    cfg: FlowConfig = FlowConfig()
    name: str = "flow"

    def training_example(self, x0: jax.Array, key: jax.Array) -> TrainingExample:
        k_t, k_noise = jax.random.split(key)
        tau = sample_time(self.cfg, k_t, x0.shape[0])
        noise = jax.random.normal(k_noise, x0.shape, x0.dtype)
        t = tau[:, None, None]
        return TrainingExample(t * noise + (1.0 - t) * x0, tau * self.cfg.time_scale, noise - x0)

    def plan(self, inference: InferenceConfig) -> StepPlan:
        _, steps = resolve_sampler(inference)
        cfg = self.cfg

        def update(row, x, velocity, key):
            return x - row.dt * velocity

        def finish(x):
            return jnp.clip(x, -cfg.clip_range, cfg.clip_range)

        def renoise(row, x0, noise):
            return row.tau_next * noise + (1.0 - row.tau_next) * x0

        return StepPlan(euler_table(cfg, steps), update, finish if cfg.clip_sample else identity, renoise)

    def describe(self, inference: InferenceConfig) -> str:
        return f"Euler {resolve_sampler(inference)[1]}"


def make(cfg: PolicyConfig) -> FlowHead:
    return FlowHead(cfg.flow)
