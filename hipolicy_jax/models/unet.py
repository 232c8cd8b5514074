"""Conditional 1D U-Net denoiser: Diffusion Policy's ``ConditionalUnet1D`` plus HiPolicy's two fusion modules.

Layout: the noisy chunk ``x`` is ``(B, M*L_c, A)``, one ``L_c``-step segment per frequency in segment order (lowest
frequency first); the condition ``cond`` is ``(B, M, Dc)`` in the same order. Convolutions run over the whole
``M*L_c`` sequence (kernels cross segment boundaries), as in the release.

* **Hierarchical FiLM.** In every residual block, the time steps of segment ``m`` are modulated by a FiLM scale and
  bias computed from ``[step embedding ⊕ cond[:, m]]`` with the block's single ``Mish -> Dense(2C)`` head (same
  weights for every segment, different conditions). After ``l`` down-samplings a segment is ``L_c / 2^l`` steps
  long. ``condition='low'`` / ``'high'`` (ablations) give every segment ``cond[:, 0]`` / ``cond[:, M-1]``.
* **Global fusion.** Placed as in the release: inside *both* residual blocks of the first down level. Each of these
  blocks splits its input ``(B, M*L_c, C_in)`` into ``M`` segment tokens of size ``L_c*C_in``, prepends a learned
  CLS token, runs multi-head self-attention over the ``M+1`` tokens, reshapes the CLS output to ``(L_c, C_in)`` and
  concatenates it channel-wise to every segment. The block's first conv then maps ``2*C_in -> 2*C_out`` channels;
  only the first ``C_out`` ("local") channels are FiLM-modulated, the other ``C_out`` ("global") channels bypass
  FiLM and are concatenated back, and the second conv maps ``2*C_out -> C_out``. The residual path uses the
  block's original input. So the first block's tokens are the raw noisy action segments (``C_in = A``) and the
  second block's are ``down_dims[0]``-channel features.

  The release builds the attention with ``torch.nn.MultiheadAttention`` and its default ``batch_first=False`` but
  feeds ``(B, M+1, D)`` tokens, so its attention actually runs across the *batch* axis (with the M+1 tokens as the
  batch) and its "global feature" is the same for every sample of a batch and mixes samples. Here attention runs
  over the ``M+1`` tokens of each sample, as the paper describes: no information crosses the batch axis.
  When ``L_c*C_in`` is not a multiple of ``fusion_heads`` the query/key/value width is rounded up to the next
  multiple (the output projection still returns ``L_c*C_in``); when it is a multiple (every release setting) the
  attention has the release's shape.

With ``M == 1`` the module is exactly a single-frequency Diffusion Policy U-Net: no fusion parameters and one FiLM
condition for the whole sequence. Diffusion Policy's quirk of never using the first level's skip connection is kept
(the up path has ``levels-1`` stages, each consuming one skip from the deepest level upward).
"""

from __future__ import annotations

import math
from typing import Literal

import jax
import jax.numpy as jnp
import flax.linen as nn

ConditionMode = Literal["hier", "low", "high"]


class SinusoidalPosEmb(nn.Module):
    """Diffusion Policy's sinusoidal step embedding: ``(B,) -> (B, dim)`` (``[sin, cos]``, base 10000)."""

    dim: int

    def __call__(self, t: jax.Array) -> jax.Array:
        half = self.dim // 2
        freqs = jnp.exp(jnp.arange(half, dtype=jnp.float32) * -(math.log(10000.0) / (half - 1)))
        arg = t.astype(jnp.float32)[:, None] * freqs[None, :]
        return jnp.concatenate([jnp.sin(arg), jnp.cos(arg)], axis=-1)


class Conv1dBlock(nn.Module):
    """``Conv1d(k, pad k//2) -> GroupNorm(n_groups) -> Mish``: ``(B, T, C_in) -> (B, T, out_channels)``."""

    out_channels: int
    kernel_size: int
    n_groups: int = 8

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        x = nn.Conv(self.out_channels, (self.kernel_size,), padding=self.kernel_size // 2, name="conv")(x)
        x = nn.GroupNorm(num_groups=self.n_groups, epsilon=1e-5, name="norm")(x)
        return jax.nn.mish(x)


class SegmentFusion(nn.Module):
    """HiPolicy's global feature: CLS-token self-attention over the ``num_segments`` segment tokens of each sample.

    ``(B, num_segments * L, C) -> (B, L, C)``: tokens ``[CLS, flatten(seg_0), ..., flatten(seg_{M-1})]`` of size
    ``L*C``; the CLS output is the global feature. Attention is over tokens *within* a sample (unlike the release,
    whose ``batch_first=False`` attention runs across the batch, see the module docstring).
    """

    num_segments: int
    num_heads: int = 8

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        b, t, c = x.shape
        seg = t // self.num_segments
        d = seg * c
        tokens = x.reshape(b, self.num_segments, d)
        cls = self.param("cls", nn.initializers.normal(stddev=1.0), (1, 1, d))
        tokens = jnp.concatenate([jnp.broadcast_to(cls, (b, 1, d)), tokens], axis=1)  # (B, M+1, D)
        qkv = -(-d // self.num_heads) * self.num_heads
        out = nn.MultiHeadDotProductAttention(num_heads=self.num_heads, qkv_features=qkv, out_features=d,
                                              name="attention")(tokens, tokens)
        return out[:, 0].reshape(b, seg, c)


def apply_film(x: jax.Array, embed: jax.Array) -> jax.Array:
    """Per-segment FiLM: ``x`` ``(B, T, C)``, ``embed`` ``(B, K, 2C)`` with ``K | T``.

    Time steps ``[k*T/K, (k+1)*T/K)`` get ``scale_k * x + bias_k`` with ``scale_k, bias_k = embed[:, k, :C],
    embed[:, k, C:]`` (Diffusion Policy's scale-then-bias order).
    """
    b, t, c = x.shape
    k = embed.shape[1]
    scale, bias = embed[..., :c], embed[..., c:]
    y = x.reshape(b, k, t // k, c) * scale[:, :, None, :] + bias[:, :, None, :]
    return y.reshape(b, t, c)


class ConditionalResidualBlock1D(nn.Module):
    """Residual block with per-segment FiLM and optional global fusion: ``(B, T, C_in) -> (B, T, out_channels)``.

    ``film_cond`` is ``(B, K, Dcond)`` with ``K`` dividing ``T`` (``K = M`` for hierarchical FiLM, ``K = 1`` for a
    single condition). With ``fusion`` the block follows the release's first-level block (module docstring);
    ``num_segments`` (M) is then the number of fusion tokens besides CLS.
    """

    out_channels: int
    kernel_size: int = 5
    n_groups: int = 8
    fusion: bool = False
    num_segments: int = 1
    fusion_heads: int = 8

    @nn.compact
    def __call__(self, x: jax.Array, film_cond: jax.Array) -> jax.Array:
        c = self.out_channels
        embed = nn.Dense(2 * c, name="film")(jax.nn.mish(film_cond))  # (B, K, 2C)
        if self.fusion:
            glob = SegmentFusion(self.num_segments, self.fusion_heads, name="fusion")(x)  # (B, L, C_in)
            glob = jnp.tile(glob, (1, self.num_segments, 1))  # same global feature for every segment
            h = Conv1dBlock(2 * c, self.kernel_size, self.n_groups, name="block0")(jnp.concatenate([x, glob], -1))
            h = jnp.concatenate([apply_film(h[..., :c], embed), h[..., c:]], axis=-1)
        else:
            h = Conv1dBlock(c, self.kernel_size, self.n_groups, name="block0")(x)
            h = apply_film(h, embed)
        h = Conv1dBlock(c, self.kernel_size, self.n_groups, name="block1")(h)
        res = x if x.shape[-1] == c else nn.Conv(c, (1,), name="residual")(x)
        return h + res


class ConditionalUnet1D(nn.Module):
    """HiPolicy denoiser: ``(x (B, M*L_c, A), timesteps (B,) or (), cond (B, M, Dc)) -> (B, M*L_c, A)``.

    Fields: ``down_dims`` (channel width per level), ``kernel_size``, ``n_groups`` (GroupNorm), ``step_embed_dim``,
    ``num_freqs`` (M), ``chunk_len`` (L_c), ``condition`` ('hier' | 'low' | 'high'), ``fusion`` (global fusion, only
    active when M > 1), ``fusion_heads``. ``chunk_len`` must be divisible by ``2^(len(down_dims)-1)``.
    """

    down_dims: tuple[int, ...] = (64, 128, 256)
    kernel_size: int = 5
    n_groups: int = 8
    step_embed_dim: int = 64
    num_freqs: int = 1
    chunk_len: int = 8
    condition: ConditionMode = "hier"
    fusion: bool = True
    fusion_heads: int = 8

    @property
    def uses_fusion(self) -> bool:
        """Whether the global fusion is built (needs ``fusion`` and more than one frequency)."""
        return self.fusion and self.num_freqs > 1

    def _check(self, x: jax.Array, cond: jax.Array) -> None:
        m, lc = self.num_freqs, self.chunk_len
        if self.condition not in ("hier", "low", "high"):
            raise ValueError(f"condition: must be 'hier', 'low' or 'high', got {self.condition!r}")
        factor = 2 ** (len(self.down_dims) - 1)
        if lc % factor:
            raise ValueError(f"chunk_len: (L_c={lc}) must be divisible by the down-sampling factor {factor}")
        if x.ndim != 3 or x.shape[1] != m * lc:
            raise ValueError(f"x: expected shape (B, M*L_c={m * lc}, A), got {x.shape}")
        if cond.ndim != 3 or cond.shape[:2] != (x.shape[0], m):
            raise ValueError(f"cond: expected shape (B={x.shape[0]}, M={m}, Dc), got {cond.shape}")

    @nn.compact
    def __call__(self, x: jax.Array, timesteps: jax.Array, cond: jax.Array) -> jax.Array:
        self._check(x, cond)
        b, _, a = x.shape
        d = self.step_embed_dim
        t = jnp.broadcast_to(jnp.asarray(timesteps), (b,))
        step = SinusoidalPosEmb(d)(t)
        step = nn.Dense(4 * d, name="step_dense0")(step)
        step = nn.Dense(d, name="step_dense1")(jax.nn.mish(step))  # (B, d)

        if self.condition == "low":
            cond = cond[:, :1]
        elif self.condition == "high":
            cond = cond[:, -1:]
        k = cond.shape[1]
        film_cond = jnp.concatenate([jnp.broadcast_to(step[:, None, :], (b, k, d)), cond], axis=-1)

        def res(ch, name, fuse=False):
            return ConditionalResidualBlock1D(ch, self.kernel_size, self.n_groups, fuse, self.num_freqs,
                                              self.fusion_heads, name=name)

        levels = len(self.down_dims)
        skips = []
        for i, ch in enumerate(self.down_dims):
            fuse = self.uses_fusion and i == 0
            x = res(ch, f"down{i}_res0", fuse)(x, film_cond)
            x = res(ch, f"down{i}_res1", fuse)(x, film_cond)
            skips.append(x)
            if i < levels - 1:
                x = nn.Conv(ch, (3,), strides=2, padding=1, name=f"down{i}_downsample")(x)

        mid = self.down_dims[-1]
        x = res(mid, "mid_res0")(x, film_cond)
        x = res(mid, "mid_res1")(x, film_cond)

        for j, ch in enumerate(reversed(self.down_dims[:-1])):
            x = jnp.concatenate([x, skips.pop()], axis=-1)
            x = res(ch, f"up{j}_res0")(x, film_cond)
            x = res(ch, f"up{j}_res1")(x, film_cond)
            x = nn.ConvTranspose(ch, (4,), strides=(2,), padding=((2, 2),), name=f"up{j}_upsample")(x)

        x = Conv1dBlock(self.down_dims[0], self.kernel_size, self.n_groups, name="final_block")(x)
        return nn.Conv(a, (1,), name="final_conv")(x)
