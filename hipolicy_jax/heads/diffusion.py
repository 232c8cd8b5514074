"""The diffusion head: DDPM training, and DDPM / DDIM sampling as one update over a precomputed step table.

Conventions follow Diffusion Policy (diffusers' ``DDPMScheduler`` / ``DDIMScheduler``): ``squaredcos_cap_v2`` betas,
train timesteps 0..K-1, fixed-small posterior variance, ``clip_sample`` on the predicted clean sample, ε- or
sample-(x0-)prediction.

Every sampler is ONE reverse-step rule over a per-step table (``ReverseTable``)::

    x0_raw = predicted clean sample                     # (x_t - sqrt(1-ᾱ_t)·ε̂)/sqrt(ᾱ_t), or the model output
    eps    = ε̂, or (x_t - sqrt(ᾱ_t)·x0_raw)/sqrt(1-ᾱ_t) # the model's ε
    x0     = clip(x0_raw)
    eps_c  = (x_t - sqrt(ᾱ_t)·x0)/sqrt(1-ᾱ_t)           # ε consistent with the clipped x0
    x_prev = c_x0·x0 + c_xt·x_t + c_eps·eps + c_eps_c·eps_c + σ·z

- DDPM (all K steps): c_x0 = sqrt(ᾱ_prev)·β_t/(1-ᾱ_t), c_xt = sqrt(α_t)·(1-ᾱ_prev)/(1-ᾱ_t), no ε terms,
  σ² = (1-ᾱ_prev)/(1-ᾱ_t)·β_t (0 at the last step), as ``DDPMScheduler``.
- DDIM (η = 0, S ≤ K steps, "leading" timesteps (S-1..0)·K/S, ᾱ_prev = 1 past the end): c_x0 = sqrt(ᾱ_prev),
  c_eps = sqrt(1-ᾱ_prev), as ``DDIMScheduler.step`` with its default ``use_clipped_model_output=False`` (what
  Diffusion Policy runs). ``ddim-clipped`` puts that weight on ``eps_c`` instead (``use_clipped_model_output=True``):
  the trajectory then stays consistent with the clipped clean sample, which differs from the default only while
  the prediction is clipped.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax.config import DiffusionConfig, InferenceConfig, PolicyConfig
from hipolicy_jax.heads.base import StepPlan, TrainingExample, identity

SAMPLERS = ("ddpm", "ddim", "ddim-clipped")
DEFAULT_DDIM_STEPS = 10


def make_betas(cfg: DiffusionConfig) -> np.ndarray:
    """β_1..β_K, shape (K,), float32 values (held as float64) as diffusers' schedulers store them: the schedule is
    computed in float64 and rounded to float32 (``torch.tensor(betas, dtype=torch.float32)``)."""
    k = cfg.num_train_steps
    if cfg.beta_schedule == "linear":
        betas = np.linspace(cfg.beta_start, cfg.beta_end, k, dtype=np.float64)
    else:
        def alpha_bar(t):
            return np.cos((t + 0.008) / 1.008 * np.pi / 2) ** 2

        i = np.arange(k, dtype=np.float64)
        betas = np.minimum(1.0 - alpha_bar((i + 1) / k) / alpha_bar(i / k), 0.999)
    return betas.astype(np.float32).astype(np.float64)


def alphas_cumprod(cfg: DiffusionConfig) -> np.ndarray:
    """ᾱ_t for t = 0..K-1, shape (K,): diffusers' float32 ``cumprod(1 - β)`` (held as float64). Its rounding is
    part of the function a Diffusion Policy checkpoint was trained and sampled with: at t = 0, 1 - ᾱ_0 in float32
    differs from β_0 by ~1e-5 relative, which moves the last DDPM step by as much (``tests/test_porting.py``)."""
    alphas = (1.0 - make_betas(cfg).astype(np.float32)).astype(np.float32)
    return np.cumprod(alphas, dtype=np.float32).astype(np.float64)


class ReverseTable(NamedTuple):
    """Per reverse step arrays, each (S,), in the order they are applied (noisiest first)."""

    time: jax.Array  # int32 model timestep
    sqrt_ab: jax.Array  # sqrt(ᾱ_t)
    sqrt_1m_ab: jax.Array  # sqrt(1-ᾱ_t)
    c_x0: jax.Array
    c_xt: jax.Array
    c_eps: jax.Array  # weight of the model's ε
    c_eps_c: jax.Array  # weight of the ε recomputed from the clipped clean sample
    sigma: jax.Array
    sqrt_ab_prev: jax.Array  # sqrt(ᾱ) of the level the step leads to (1 after the last step)
    sqrt_1m_ab_prev: jax.Array


def resolve_sampler(cfg: DiffusionConfig, inference: InferenceConfig) -> tuple[str, int]:
    """(sampler, number of steps) of ``inference`` for this head: ``auto`` is DDIM; DDPM runs every train step and
    DDIM ``num_steps`` (default 10, at most K)."""
    sampler = "ddim" if inference.sampler == "auto" else inference.sampler
    if sampler not in SAMPLERS:
        raise ValueError(f"inference.sampler: the diffusion head samples with {' / '.join(SAMPLERS)}, "
                         f"got {sampler!r}")
    k = cfg.num_train_steps
    if sampler == "ddpm":
        steps = k if inference.num_steps is None else inference.num_steps
        if steps != k:
            raise ValueError(f"inference.num_steps: DDPM denoises through all {k} train steps, got {steps}; use "
                             f"--inference.sampler ddim for fewer")
        return sampler, steps
    steps = min(DEFAULT_DDIM_STEPS, k) if inference.num_steps is None else inference.num_steps
    if not 1 <= steps <= k:
        raise ValueError(f"inference.num_steps: DDIM takes 1 to {k} (diffusion.num_train_steps) steps, got {steps}")
    return sampler, steps


def reverse_table(cfg: DiffusionConfig, sampler: str, num_steps: int) -> ReverseTable:
    """Coefficient table of ``sampler`` ('ddpm' | 'ddim' | 'ddim-clipped') with ``num_steps`` steps."""
    k = cfg.num_train_steps
    ab = alphas_cumprod(cfg)
    if sampler == "ddpm":
        if num_steps != k:
            raise ValueError(f"inference.num_steps: DDPM runs all {k} steps, got {num_steps}; use 'ddim'")
        t = np.arange(k - 1, -1, -1)
        prev = t - 1
    elif sampler in ("ddim", "ddim-clipped"):
        if not 1 <= num_steps <= k:
            raise ValueError(f"inference.num_steps: must be in [1, {k}], got {num_steps}")
        ratio = k // num_steps
        t = (np.arange(num_steps) * ratio)[::-1]
        prev = t - ratio
    else:
        raise ValueError(f"inference.sampler: must be one of {SAMPLERS}, got {sampler!r}")
    ab_t = ab[t]
    ab_prev = np.where(prev >= 0, ab[np.maximum(prev, 0)], 1.0)
    zero = np.zeros_like(ab_t)
    if sampler == "ddpm":  # diffusers' DDPMScheduler (Diffusion Policy's 0.11.1): β_t and α_t = 1 - β_t as stored
        beta_t = make_betas(cfg)[t]
        alpha_t = (1.0 - beta_t.astype(np.float32)).astype(np.float32).astype(np.float64)
        c_x0 = np.sqrt(ab_prev) * beta_t / (1.0 - ab_t)
        c_xt = np.sqrt(alpha_t) * (1.0 - ab_prev) / (1.0 - ab_t)
        c_eps = c_eps_c = zero
        var = np.clip((1.0 - ab_prev) / (1.0 - ab_t) * beta_t, 1e-20, None)
        sigma = np.where(t > 0, np.sqrt(var), 0.0)
    else:
        c_x0, c_xt, sigma = np.sqrt(ab_prev), zero, zero
        c_eps, c_eps_c = (np.sqrt(1.0 - ab_prev), zero) if sampler == "ddim" else (zero, np.sqrt(1.0 - ab_prev))
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    return ReverseTable(jnp.asarray(t, jnp.int32), f32(np.sqrt(ab_t)), f32(np.sqrt(1.0 - ab_t)), f32(c_x0),
                        f32(c_xt), f32(c_eps), f32(c_eps_c), f32(sigma), f32(np.sqrt(ab_prev)),
                        f32(np.sqrt(1.0 - ab_prev)))


def add_noise(cfg: DiffusionConfig, x0: jax.Array, noise: jax.Array, t: jax.Array) -> jax.Array:
    """Forward process q(x_t | x_0): x0, noise (B, T, A); t (B,) int in [0, K)."""
    ab = jnp.asarray(alphas_cumprod(cfg), jnp.float32)[t][:, None, None]
    return jnp.sqrt(ab) * x0 + jnp.sqrt(1.0 - ab) * noise


def training_target(cfg: DiffusionConfig, x0: jax.Array, noise: jax.Array) -> jax.Array:
    """What the denoiser regresses: ε for 'epsilon', x0 for 'sample'."""
    return noise if cfg.prediction_type == "epsilon" else x0


def reverse_step(cfg: DiffusionConfig, row: ReverseTable, x_t: jax.Array, model_out: jax.Array,
                 z: jax.Array | None) -> jax.Array:
    """One reverse update with table row ``row`` (scalars); x_t, model_out, z (…, T, A) → x_prev.
    ``z`` (standard normal noise) may be None for deterministic tables (σ = 0 at every step)."""
    if cfg.prediction_type == "epsilon":
        eps = model_out
        x0 = (x_t - row.sqrt_1m_ab * eps) / row.sqrt_ab
    else:
        x0 = model_out
        eps = (x_t - row.sqrt_ab * x0) / row.sqrt_1m_ab
    if cfg.clip_sample:
        x0 = jnp.clip(x0, -cfg.clip_range, cfg.clip_range)
    eps_c = (x_t - row.sqrt_ab * x0) / row.sqrt_1m_ab
    out = row.c_x0 * x0 + row.c_xt * x_t + row.c_eps * eps + row.c_eps_c * eps_c
    return out if z is None else out + row.sigma * z


@dataclasses.dataclass(frozen=True)
class DiffusionHead:
    """DDPM training (uniform timesteps, MSE on ε or x0) and DDPM / DDIM sampling."""

    cfg: DiffusionConfig = DiffusionConfig()
    name: str = "diffusion"

    def training_example(self, x0: jax.Array, key: jax.Array) -> TrainingExample:
        k_t, k_noise = jax.random.split(key)
        t = jax.random.randint(k_t, (x0.shape[0],), 0, self.cfg.num_train_steps)
        noise = jax.random.normal(k_noise, x0.shape, x0.dtype)
        return TrainingExample(add_noise(self.cfg, x0, noise, t), t, training_target(self.cfg, x0, noise))

    def plan(self, inference: InferenceConfig) -> StepPlan:
        sampler, steps = resolve_sampler(self.cfg, inference)
        table = reverse_table(self.cfg, sampler, steps)
        cfg = self.cfg

        if sampler == "ddpm":
            def update(row, x, out, key):
                return reverse_step(cfg, row, x, out, jax.random.normal(key, x.shape, x.dtype))
        else:
            def update(row, x, out, key):
                return reverse_step(cfg, row, x, out, None)

        def renoise(row, x0, noise):
            return row.sqrt_ab_prev * x0 + row.sqrt_1m_ab_prev * noise

        return StepPlan(table, update, identity, renoise)

    def describe(self, inference: InferenceConfig) -> str:
        sampler, steps = resolve_sampler(self.cfg, inference)
        return f"{sampler.upper()} {steps}"


def make(cfg: PolicyConfig) -> DiffusionHead:
    return DiffusionHead(cfg.diffusion)
