"""DDPM / DDIM noise schedules and update rules as pure functions over precomputed arrays.

Conventions follow Diffusion Policy (diffusers' DDPMScheduler / DDIMScheduler): ``squaredcos_cap_v2`` betas, train
timesteps 0..K-1, fixed-small posterior variance, ``clip_sample`` on the predicted clean sample, ε- or
sample-(x0-)prediction.

Both samplers share ONE reverse-step rule over a precomputed per-step table (``ReverseTable``)::

    x0   = clip(predicted clean sample)              # from ε or directly
    eps  = (x_t - sqrt(ᾱ_t)·x0) / sqrt(1-ᾱ_t)        # ε consistent with the clipped x0
    x_prev = c_x0·x0 + c_xt·x_t + c_eps·eps + σ·z

DDPM (all K steps):  c_x0 = sqrt(ᾱ_prev)·β_t/(1-ᾱ_t), c_xt = sqrt(α_t)·(1-ᾱ_prev)/(1-ᾱ_t), c_eps = 0,
                     σ² = (1-ᾱ_prev)/(1-ᾱ_t)·β_t (0 at the last step).
DDIM (η = 0, S ≤ K steps, timesteps (S-1..0)·K/S):  c_x0 = sqrt(ᾱ_prev), c_xt = 0, c_eps = sqrt(1-ᾱ_prev), σ = 0.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax.config import DiffusionConfig


def make_betas(cfg: DiffusionConfig) -> np.ndarray:
    """β_1..β_K as float64 numpy, shape (K,)."""
    k = cfg.num_train_steps
    if cfg.beta_schedule == "linear":
        return np.linspace(cfg.beta_start, cfg.beta_end, k, dtype=np.float64)

    def alpha_bar(t):
        return np.cos((t + 0.008) / 1.008 * np.pi / 2) ** 2

    i = np.arange(k, dtype=np.float64)
    return np.minimum(1.0 - alpha_bar((i + 1) / k) / alpha_bar(i / k), 0.999)


def alphas_cumprod(cfg: DiffusionConfig) -> np.ndarray:
    """ᾱ_t for t = 0..K-1, shape (K,)."""
    return np.cumprod(1.0 - make_betas(cfg))


class ReverseTable(NamedTuple):
    """Per reverse step arrays, each (S,), in the order they are applied (noisiest first)."""

    timesteps: jax.Array  # int32 model timestep
    sqrt_ab: jax.Array  # sqrt(ᾱ_t)
    sqrt_1m_ab: jax.Array  # sqrt(1-ᾱ_t)
    c_x0: jax.Array
    c_xt: jax.Array
    c_eps: jax.Array
    sigma: jax.Array


def reverse_table(cfg: DiffusionConfig, num_steps: int | None = None, sampler: str | None = None) -> ReverseTable:
    """Coefficient table for ``sampler`` ('ddpm' | 'ddim', default from cfg) with ``num_steps`` steps."""
    sampler = sampler or cfg.sampler
    num_steps = num_steps or cfg.num_inference_steps
    k = cfg.num_train_steps
    ab = alphas_cumprod(cfg)
    if sampler == "ddpm":
        if num_steps != k:
            raise ValueError(f"diffusion.num_inference_steps: DDPM runs all {k} steps, got {num_steps}; use 'ddim'")
        t = np.arange(k - 1, -1, -1)
        prev = t - 1
    elif sampler == "ddim":
        if not 1 <= num_steps <= k:
            raise ValueError(f"diffusion.num_inference_steps: must be in [1, {k}], got {num_steps}")
        ratio = k // num_steps
        t = (np.arange(num_steps) * ratio)[::-1]
        prev = t - ratio
    else:
        raise ValueError(f"diffusion.sampler: must be 'ddpm' or 'ddim', got {sampler!r}")
    ab_t = ab[t]
    ab_prev = np.where(prev >= 0, ab[np.maximum(prev, 0)], 1.0)
    if sampler == "ddpm":
        beta_t = 1.0 - ab_t / ab_prev
        c_x0 = np.sqrt(ab_prev) * beta_t / (1.0 - ab_t)
        c_xt = np.sqrt(1.0 - beta_t) * (1.0 - ab_prev) / (1.0 - ab_t)
        c_eps = np.zeros_like(ab_t)
        var = np.clip((1.0 - ab_prev) / (1.0 - ab_t) * beta_t, 1e-20, None)
        sigma = np.where(t > 0, np.sqrt(var), 0.0)
    else:
        c_x0, c_xt, c_eps = np.sqrt(ab_prev), np.zeros_like(ab_t), np.sqrt(1.0 - ab_prev)
        sigma = np.zeros_like(ab_t)
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    return ReverseTable(jnp.asarray(t, jnp.int32), f32(np.sqrt(ab_t)), f32(np.sqrt(1.0 - ab_t)),
                        f32(c_x0), f32(c_xt), f32(c_eps), f32(sigma))


def add_noise(cfg: DiffusionConfig, x0: jax.Array, noise: jax.Array, t: jax.Array) -> jax.Array:
    """Forward process q(x_t | x_0): x0, noise (B, T, A); t (B,) int in [0, K)."""
    ab = jnp.asarray(alphas_cumprod(cfg), jnp.float32)[t][:, None, None]
    return jnp.sqrt(ab) * x0 + jnp.sqrt(1.0 - ab) * noise


def training_target(cfg: DiffusionConfig, x0: jax.Array, noise: jax.Array) -> jax.Array:
    """What the denoiser regresses: ε for 'epsilon', x0 for 'sample'."""
    return noise if cfg.prediction_type == "epsilon" else x0


def reverse_step(cfg: DiffusionConfig, row: ReverseTable, x_t: jax.Array, model_out: jax.Array,
                 z: jax.Array) -> jax.Array:
    """One reverse update with table row ``row`` (scalars); x_t, model_out, z (…, T, A) → x_prev."""
    if cfg.prediction_type == "epsilon":
        x0 = (x_t - row.sqrt_1m_ab * model_out) / row.sqrt_ab
    else:
        x0 = model_out
    if cfg.clip_sample:
        x0 = jnp.clip(x0, -cfg.clip_range, cfg.clip_range)
    eps = (x_t - row.sqrt_ab * x0) / row.sqrt_1m_ab
    return row.c_x0 * x0 + row.c_xt * x_t + row.c_eps * eps + row.sigma * z
