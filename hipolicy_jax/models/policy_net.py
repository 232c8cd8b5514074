"""The policy network: observation encoder + conditional U-Net denoiser, built from a ``PolicyConfig``.

The sampler encodes the observation once and then denoises many times::

    cond = net.apply(variables, obs, method=PolicyNet.encode)                # (B, M, Dc)
    eps = net.apply(variables, x, t, cond, method=PolicyNet.denoise)         # inside lax.scan

``encode`` touches only the encoder's parameters and ``denoise`` only the U-Net's, so the scan body never re-runs
the encoder. The sampler goes one step further and also hoists the observation half of the FiLM heads::

    film_c = net.apply(variables, cond, method=PolicyNet.film_condition)     # {block: (B, K, 2C)}, once
    film_t = net.apply(variables, t[None], method=PolicyNet.film_steps)      # {block: (1, 2C)}, per step
    eps = net.apply(variables, x, film_t_row, film_c, method=PolicyNet.denoise_film)   # inside lax.scan

``init_policy_params`` returns the full variables dict (``{"params": ...}``) accepted by ``apply``.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import flax.linen as nn

from hipolicy_jax.config import PolicyConfig
from hipolicy_jax.data.windowing import obs_offsets
from hipolicy_jax.models.encoders import ObsEncoder
from hipolicy_jax.models.unet import ConditionalUnet1D, FiLMParts


class PolicyNet(nn.Module):
    """``ObsEncoder(cfg.encoder)`` followed by ``ConditionalUnet1D`` configured from ``cfg.model`` / ``cfg.chunk``.

    Shapes: ``obs`` arrays ``(B, M, L_h, ...)`` (see ``ObsEncoder``), ``x`` ``(B, M*L_c, action_dim)``,
    ``timesteps`` ``(B,)`` (or a scalar), condition ``(B, M, L_h * F)``.
    """

    cfg: PolicyConfig
    action_dim: int

    def setup(self):
        model, chunk = self.cfg.model, self.cfg.chunk
        offsets = tuple(tuple(int(o) for o in row) for row in obs_offsets(chunk))
        self.obs_encoder = ObsEncoder(self.cfg.encoder, frame_offsets=offsets)  # each distinct frame encoded once
        self.unet = ConditionalUnet1D(
            down_dims=model.unet_dims,
            kernel_size=model.unet_kernel,
            n_groups=model.n_groups,
            step_embed_dim=model.unet_step_embed,
            num_freqs=chunk.num_freqs,
            chunk_len=chunk.chunk_len,
            condition=model.condition,
            fusion=model.fusion,
            fusion_heads=model.fusion_heads,
            compute_dtype=model.compute_dtype,
            fusion_token_dim=model.fusion_token_dim,
            fusion_kind=model.fusion_kind,
        )

    def encode(self, obs, train: bool = False) -> jax.Array:
        """Observation dict ``(B, M, L_h, ...)`` -> condition ``(B, M, Dc)``. ``train`` needs a ``"crop"`` rng for
        image observations (random crops); otherwise images are centre-cropped."""
        return self.obs_encoder(obs, train=train)

    def denoise(self, x: jax.Array, timesteps: jax.Array, cond: jax.Array) -> jax.Array:
        """Noisy chunk ``(B, M*L_c, A)``, steps ``(B,)``, condition ``(B, M, Dc)`` -> prediction ``(B, M*L_c, A)``."""
        if x.shape[-1] != self.action_dim:
            raise ValueError(f"x: expected shape (B, M*L_c, action_dim={self.action_dim}), got {x.shape}")
        return self.unet(x, timesteps, cond)

    def film_condition(self, cond: jax.Array) -> dict[str, jax.Array]:
        """Observation half of every U-Net block's FiLM: condition ``(B, M, Dc)`` -> ``{block: (B, K, 2C)}``."""
        return self.unet.film_condition(cond)

    def film_steps(self, timesteps: jax.Array) -> dict[str, jax.Array]:
        """Step half of every U-Net block's FiLM for a reverse schedule: ``(S,)`` -> ``{block: (S, 2C)}``."""
        return self.unet.film_steps(timesteps)

    def denoise_film(self, x: jax.Array, film_step: dict[str, jax.Array], film_cond: dict[str, jax.Array]) -> jax.Array:
        """``denoise`` with precomputed FiLM halves: ``film_step`` ``{block: (2C,) or (B, 2C)}`` (one row of
        ``film_steps``) and ``film_cond`` ``{block: (B, K, 2C)}`` (``film_condition``) -> ``(B, M*L_c, A)``.
        Equal to ``denoise(x, t, cond)`` up to float rounding."""
        if x.shape[-1] != self.action_dim:
            raise ValueError(f"x: expected shape (B, M*L_c, action_dim={self.action_dim}), got {x.shape}")
        film = {name: FiLMParts(film_step[name], film_cond[name]) for name in film_cond}
        return self.unet(x, None, None, film=film)

    def __call__(self, obs, x: jax.Array, timesteps: jax.Array, train: bool = False) -> jax.Array:
        """``denoise(x, timesteps, encode(obs, train))``; used for initialisation and the training loss."""
        return self.denoise(x, timesteps, self.encode(obs, train=train))


def init_policy_params(cfg: PolicyConfig, action_dim: int, example_obs, key: jax.Array):
    """Initialise ``PolicyNet(cfg, action_dim)`` for observations shaped like ``example_obs`` (``(B, M, L_h, ...)``).

    Returns the variables dict ``{"params": ...}``, to be passed as the first argument of ``PolicyNet.apply``.
    Only shapes and dtypes of ``example_obs`` matter.
    """
    b = jnp.shape(example_obs["state"])[0]
    x = jnp.zeros((b, cfg.chunk.horizon, action_dim), jnp.float32)
    t = jnp.zeros((b,), jnp.int32)
    return init_variables(PolicyNet(cfg, action_dim), key, example_obs, x, t, train=False)


def init_variables(module: nn.Module, key: jax.Array, *args, **kwargs):
    """``module.init(key, *args, **kwargs)`` compiled with XLA's backend optimisations off.

    Initialisation runs once, so its run time does not matter, but its compile time does: on a CPU the many
    random initialisers of a U-Net compile about 4x faster this way (e.g. ~2 s instead of ~9 s for the tiny model).
    ``args`` are traced (arrays or pytrees of arrays); ``kwargs`` are static (e.g. ``train=False``). Inside a
    trace (``jax.eval_shape`` of a train state, say) it is a plain ``module.init``.
    """
    if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves((key, args))):
        return module.init(key, *args, **kwargs)
    lowered = jax.jit(lambda k, a: module.init(k, *a, **kwargs)).lower(key, args)
    return lowered.compile(compiler_options={"xla_backend_optimization_level": 0})(key, args)


def param_count(params) -> int:
    """Total number of scalars in a parameter pytree (a variables dict or any sub-tree of it)."""
    return int(sum(math.prod(jnp.shape(p)) for p in jax.tree_util.tree_leaves(params)))
