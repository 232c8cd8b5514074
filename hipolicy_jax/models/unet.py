"""Conditional 1D U-Net denoiser: Diffusion Policy's ``ConditionalUnet1D`` plus HiPolicy's two fusion modules.

Layout: the noisy chunk ``x`` is ``(B, M*L_c, A)``, one ``L_c``-step segment per frequency in segment order (lowest
frequency first); the condition ``cond`` is ``(B, M, Dc)`` in the same order. Convolutions run over the whole
``M*L_c`` sequence (kernels cross segment boundaries), as in the release.

* **Hierarchical FiLM.** In every residual block, the time steps of segment ``m`` are modulated by a FiLM scale and
  bias computed from ``[step embedding ⊕ cond[:, m]]`` with the block's single ``Mish -> Dense(2C)`` head (same
  weights for every segment, different conditions). After ``l`` down-samplings a segment is ``L_c / 2^l`` steps
  long. ``condition='low'`` / ``'high'`` (ablations) give every segment ``cond[:, 0]`` / ``cond[:, M-1]``.
* **Global fusion.** Placed as in the release: inside *both* residual blocks of the first down level, so the first
  block sees the raw noisy action segments (``C_in = A``) and the second ``down_dims[0]``-channel features. Such a
  block computes a global feature ``(L_c, C_in)`` from its input ``(B, M*L_c, C_in)`` (``SegmentFusion``, below)
  and concatenates it channel-wise to every segment. Its first conv then maps ``2*C_in -> 2*C_out`` channels; only
  the first ``C_out`` ("local") channels are FiLM-modulated, the other ``C_out`` ("global") channels bypass FiLM and
  are concatenated back, and the second conv maps ``2*C_out -> C_out``. The residual path uses the block's original
  input. The release does the same.

  The global feature differs from the release's. ``fusion_kind='attention'`` (the default) computes it as the paper
  describes: the input is split into ``M`` segment tokens of ``L_c*C_in`` features (each segment flattened time
  first), a learned CLS token is prepended, multi-head self-attention runs over each sample's ``M+1`` tokens, and
  the CLS output, reshaped to ``(L_c, C_in)``, is the global feature. No information crosses the batch axis. When
  ``L_c*C_in`` is not a multiple of ``fusion_heads`` the query/key/value width is rounded up to the next multiple
  (the output projection still returns the token width); when it is a multiple (every release setting) the
  attention has the release's shape. ``fusion_token_dim`` projects wide tokens to a smaller width first (a model
  change, ``SegmentFusion``).

  The release flattens each segment channels first (``(C_in, L_c)``) and builds the attention with
  ``torch.nn.MultiheadAttention`` and its default ``batch_first=False``, but feeds it ``(B, M+1, D)`` tokens. So its
  attention runs along the *batch* axis, separately at each of the ``M+1`` token positions. The CLS position holds
  B copies of the one learned CLS token: its scores are all equal, the softmax is uniform and its output is
  ``out_proj(v_proj(cls))``. The release's "global feature" is therefore a learned constant, independent of the
  input and of the batch (the segment positions do attend across samples, but their outputs are discarded): a
  fusion ablation run with the release's code compares against a learned bias. ``fusion_kind='release'`` computes
  that constant exactly (reshaped channels first, as the release reshapes it), to run the release's weights;
  docs/fidelity.md names the test that checks it and the ablation of the two kinds.

* **FiLM split (sampling speed).** Mish is element-wise and the FiLM head is linear, so
  ``Dense(mish([step ⊕ cond])) = mish(step)·W_t + (mish(cond)·W_c + b)`` with ``W_t, W_c`` the first ``d`` and the
  remaining rows of the head's kernel. The parameter tree is unchanged (``film/kernel`` ``(d+Dc, 2C)``,
  ``film/bias``). The sampler computes the observation half with ``film_condition`` once per call; inside the
  denoising loop only the step half (``film_steps``, one row per step) is computed and added
  (``__call__(..., film=...)``).

With ``M == 1`` the module is exactly a single-frequency Diffusion Policy U-Net: no fusion parameters and one FiLM
condition for the whole sequence. Diffusion Policy's quirk of never using the first level's skip connection is kept
(the up path has ``levels-1`` stages, each consuming one skip from the deepest level upward).
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import flax.linen as nn

ConditionMode = Literal["hier", "low", "high"]
ComputeDtype = Literal["float32", "bfloat16"]


def mish(x: jax.Array) -> jax.Array:
    """Mish ``x·tanh(softplus(x))`` with one ``exp`` instead of ``exp + log1p + tanh``; same shape and dtype.

    ``tanh(log(1 + e)) = n / (n + 2)`` with ``e = exp(x)``, ``n = e·(e + 2)``. For ``x ≥ 20`` the ratio is 1 in
    float32, so ``x`` is clipped there before the ``exp`` (no ``inf / inf``). Matches ``jax.nn.mish`` to float32
    rounding (max abs. difference ~2e-6 on [-30, 30]) and is ~10 % faster for the U-Net on a CPU, where the
    element-wise work competes with the convolutions.
    """
    e = jnp.exp(jnp.minimum(x, 20.0))
    n = e * (e + 2.0)
    return x * (n / (n + 2.0))


def sinusoidal_embedding(t: jax.Array, dim: int) -> jax.Array:
    """Diffusion Policy's sinusoidal step embedding: ``(...,) -> (..., dim)`` (``[sin, cos]``, base 10000)."""
    half = dim // 2
    freqs = jnp.exp(jnp.arange(half, dtype=jnp.float32) * -(math.log(10000.0) / (half - 1)))
    arg = jnp.asarray(t).astype(jnp.float32)[..., None] * freqs
    return jnp.concatenate([jnp.sin(arg), jnp.cos(arg)], axis=-1)


class StepEncoder(nn.Module):
    """Diffusion Policy's diffusion-step encoder: ``SinusoidalPosEmb(d) -> Dense(4d) -> Mish -> Dense(d)``,
    ``(...,) -> (..., d)``. Its layers are named ``step_dense0`` / ``step_dense1``; the U-Net shares its scope, so
    they sit at the U-Net's top level, as before this module existed."""

    dim: int

    @nn.compact
    def __call__(self, t: jax.Array) -> jax.Array:
        step = nn.Dense(4 * self.dim, name="step_dense0")(sinusoidal_embedding(t, self.dim))
        return nn.Dense(self.dim, name="step_dense1")(mish(step))


class FiLMInput(NamedTuple):
    """Raw FiLM conditioning of one denoiser call: step embedding ``(B, d)`` and condition ``(B, K, Dc)``."""

    step: jax.Array
    cond: jax.Array


class FiLMParts(NamedTuple):
    """Precomputed halves of one block's FiLM head: ``step = mish(step)·W_t`` ``(2C,)`` or ``(B, 2C)`` and
    ``cond = mish(cond)·W_c + b`` ``(B, K, 2C)``; the FiLM embedding is their broadcast sum ``(B, K, 2C)``."""

    step: jax.Array
    cond: jax.Array


def film_step_part(film_params, step: jax.Array) -> jax.Array:
    """``mish(step)·W_t``: step ``(..., d)`` -> ``(..., 2C)``; ``film_params`` is a block's ``film`` subtree."""
    return mish(step) @ film_params["kernel"][: step.shape[-1]]


def film_cond_part(film_params, cond: jax.Array) -> jax.Array:
    """``mish(cond)·W_c + b``: cond ``(..., Dc)`` -> ``(..., 2C)``; ``W_c`` is the last ``Dc`` rows of the kernel."""
    kernel = film_params["kernel"]
    return mish(cond) @ kernel[kernel.shape[0] - cond.shape[-1]:] + film_params["bias"]


def film_embed(parts: FiLMParts) -> jax.Array:
    """``(B, K, 2C)`` FiLM embedding from its two precomputed halves (the step half broadcasts over ``K``)."""
    return parts.cond + parts.step[..., None, :]


class FiLMHead(nn.Module):
    """Diffusion Policy's ``cond_encoder`` (``Mish -> Linear(features)``), with ``nn.Dense``'s parameter tree.

    ``film`` is one of: an array ``(B, K, Din)`` (the concatenated ``[step ⊕ cond]``: ``mish(film)·W + b``), a
    ``FiLMInput`` (the same through the split ``mish(step)·W_t + mish(cond)·W_c + b``) or precomputed ``FiLMParts``
    (only the broadcast sum). Returns ``(B, K, features)``.
    """

    features: int

    @nn.compact
    def __call__(self, film) -> jax.Array:
        if isinstance(film, FiLMParts):
            return film_embed(film)
        din = film.step.shape[-1] + film.cond.shape[-1] if isinstance(film, FiLMInput) else film.shape[-1]
        params = {"kernel": self.param("kernel", nn.initializers.lecun_normal(), (din, self.features)),
                  "bias": self.param("bias", nn.initializers.zeros_init(), (self.features,))}
        if isinstance(film, FiLMInput):
            return film_embed(FiLMParts(film_step_part(params, film.step), film_cond_part(params, film.cond)))
        return mish(film) @ params["kernel"] + params["bias"]


def conv1d(x: jax.Array, kernel: jax.Array, padding: tuple[int, int], stride: int = 1,
           compute_dtype: ComputeDtype = "float32") -> jax.Array:
    """1D cross-correlation ``(B, T, C_in) * (k, C_in, C_out) -> (B, T_out, C_out)``, as ``nn.Conv`` (no bias).

    ``compute_dtype='float32'``: XLA's native convolution, except where the input is shorter than the kernel (the
    deepest U-Net levels of short chunks: ``T = 2, 4`` with ``k = 5``): there XLA swaps the convolution's operands
    and its CPU backend runs the result ~35x slower than the equivalent im2col matmul (forward and gradient;
    ``benchmarks.studies.convolutions`` measures the model-level gain), so the windows are gathered and multiplied
    directly.

    ``compute_dtype='bfloat16'``: always the im2col matmul, with bf16 operands and float32 accumulation and output
    (``preferred_element_type``). XLA's CPU convolution gains nothing from bf16 operands, its matmul uses the BF16
    dot-product / AMX instructions where the CPU has them (``benchmarks.profile`` measures both).
    """
    k = kernel.shape[0]
    if compute_dtype == "float32" and x.shape[1] >= k:
        return jax.lax.conv_general_dilated(x, kernel.astype(x.dtype), (stride,), (padding,),
                                            dimension_numbers=("NWC", "WIO", "NWC"))
    dtype = jnp.dtype(compute_dtype)
    xp = jnp.pad(x.astype(dtype), ((0, 0), padding, (0, 0)))
    t_out = (xp.shape[1] - k) // stride + 1
    cols = xp if k == 1 and stride == 1 else jnp.concatenate(
        [xp[:, i:i + stride * (t_out - 1) + 1:stride] for i in range(k)], axis=-1)
    w = kernel.reshape(k * kernel.shape[1], kernel.shape[2])
    if dtype == jnp.float32:
        return cols @ w
    return matmul_lowp(cols, w)


@jax.custom_vjp
def matmul_lowp(a: jax.Array, w: jax.Array) -> jax.Array:
    """``a @ w`` for low-precision activations ``a`` ``(..., K)`` (e.g. bf16) and a float32 weight ``w`` ``(K, N)``:
    operands in ``a``'s dtype, float32 accumulation and output ``(..., N)``.

    The custom gradient keeps the backward pass in the same precision: the float32 cotangent is rounded to
    ``a``'s dtype once, both gradient matmuls take low-precision operands with float32 accumulation, ``da`` is
    returned in ``a``'s dtype and ``dw`` in float32. (Differentiating the plain mixed-dtype ``dot_general`` would
    promote the weight gradient's operands to float32 and lose the bf16 speed-up in training.)
    """
    return jax.lax.dot_general(a, w.astype(a.dtype), (((a.ndim - 1,), (0,)), ((), ())),
                               preferred_element_type=jnp.float32)


def _matmul_lowp_fwd(a, w):
    wl = w.astype(a.dtype)
    return jax.lax.dot_general(a, wl, (((a.ndim - 1,), (0,)), ((), ())), preferred_element_type=jnp.float32), (a, wl)


def _matmul_lowp_bwd(res, g):
    a, wl = res
    gl = g.astype(a.dtype)
    da = jax.lax.dot_general(gl, wl, (((g.ndim - 1,), (1,)), ((), ())), preferred_element_type=jnp.float32)
    lead = tuple(range(a.ndim - 1))
    dw = jax.lax.dot_general(a, gl, ((lead, lead), ((), ())), preferred_element_type=jnp.float32)
    return da.astype(a.dtype), dw


matmul_lowp.defvjp(_matmul_lowp_fwd, _matmul_lowp_bwd)


def lowp_kernels(variables, compute_dtype: ComputeDtype):
    """``variables`` with the U-Net's convolution and fusion-attention kernels cast to ``compute_dtype`` (other
    leaves unchanged; a no-op for float32). The sampler does this once per call, before its loop: at small N every
    denoising step is bound by reading the weights, and bf16 kernels halve those bytes (the per-step cast of
    float32 kernels would add to them). Kernels: the 3-D ``kernel`` leaves outside the observation encoder
    (convolutions and the attention's projections) and every ``kernel`` under a ``fusion`` module; FiLM and step-MLP
    kernels (2-D) and the encoder stay."""
    if compute_dtype == "float32":
        return variables
    dtype = jnp.dtype(compute_dtype)

    def cast(path, leaf):
        keys = [getattr(k, "key", getattr(k, "name", "")) for k in path]
        if keys[-1] == "kernel" and "obs_encoder" not in keys and (leaf.ndim == 3 or "fusion" in keys):
            return leaf.astype(dtype)
        return leaf

    return jax.tree_util.tree_map_with_path(cast, variables)


class Conv1d(nn.Module):
    """``nn.Conv(features, (kernel_size,), strides=stride, padding=kernel_size // 2)`` with the same parameter tree
    (``kernel (k, C_in, features)``, ``bias``) through ``conv1d``: ``(B, T, C_in) -> (B, ceil(T / stride), features)``.
    """

    features: int
    kernel_size: int
    stride: int = 1
    compute_dtype: ComputeDtype = "float32"  # conv1d's operand dtype; parameters and output stay float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        k, pad = self.kernel_size, self.kernel_size // 2
        w = self.param("kernel", nn.initializers.lecun_normal(), (k, x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))
        return conv1d(x, w, (pad, pad), self.stride, self.compute_dtype) + bias


class Upsample1d(nn.Module):
    """2x temporal up-sampling ``(B, T, C_in) -> (B, 2T, features)``: the same function and parameter tree
    (``kernel (4, C_in, features)``, ``bias``) as ``nn.ConvTranspose(features, (4,), strides=(2,),
    padding=((2, 2),))``, computed as one stride-1 convolution.

    The transposed conv gives ``y[2i] = x[i-1]·w0 + x[i]·w2`` and ``y[2i+1] = x[i]·w1 + x[i+1]·w3`` (zero outside
    ``[0, T)``). So a 3-tap convolution over the zero-padded input with ``2·features`` outputs, taps
    ``[[w0, 0], [w2, w1], [0, w3]]``, yields the even and odd outputs side by side, and a reshape interleaves them.
    XLA's CPU backend has no fast path for the input-dilated convolutions of a transposed conv's gradient (17-23x
    slower than this form at batch 64 on a 2-core CPU).
    """

    features: int
    compute_dtype: ComputeDtype = "float32"

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        b, t, c = x.shape
        w = self.param("kernel", nn.initializers.lecun_normal(), (4, c, self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))
        zero = jnp.zeros_like(w[0])
        taps = jnp.stack([jnp.concatenate([w[0], zero], -1), jnp.concatenate([w[2], w[1]], -1),
                          jnp.concatenate([zero, w[3]], -1)])  # (3, C_in, 2·features): [even | odd]
        return conv1d(x, taps, (1, 1), 1, self.compute_dtype).reshape(b, 2 * t, self.features) + bias


class Conv1dBlock(nn.Module):
    """``Conv1d(k, pad k//2) -> GroupNorm(n_groups) -> Mish``: ``(B, T, C_in) -> (B, T, out_channels)``."""

    out_channels: int
    kernel_size: int
    n_groups: int = 8
    compute_dtype: ComputeDtype = "float32"  # the convolution's; GroupNorm and Mish run in float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        x = Conv1d(self.out_channels, self.kernel_size, compute_dtype=self.compute_dtype, name="conv")(x)
        x = nn.GroupNorm(num_groups=self.n_groups, epsilon=1e-5, name="norm")(x)
        return mish(x)


FusionKind = Literal["attention", "release"]


class ReleaseFusionAttention(nn.Module):
    """The release's fusion output, ``out_proj(v_proj(cls))``: ``cls`` ``(D,)`` -> ``(out_features,)``.

    Same parameter tree as the ``value`` and ``out`` projections of ``nn.MultiHeadDotProductAttention`` (``value``
    kernel ``(D, heads, head_dim)``, ``out`` kernel ``(heads, head_dim, out_features)``), so a checkpoint's weights
    map onto either kind alike. The release's query and key projections do not affect its output (every score of the
    CLS position is equal, whatever they are) nor receive a gradient, so they are not kept.
    """

    num_heads: int
    qkv_features: int
    out_features: int
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, cls: jax.Array) -> jax.Array:
        head_dim = self.qkv_features // self.num_heads
        v = nn.DenseGeneral((self.num_heads, head_dim), dtype=self.dtype, name="value")(cls)
        return nn.DenseGeneral(self.out_features, axis=(-2, -1), dtype=self.dtype, name="out")(v)


class SegmentFusion(nn.Module):
    """HiPolicy's global feature: CLS-token self-attention over the ``num_segments`` segment tokens of each sample.

    ``(B, num_segments * L, C) -> (B, L, C)``: tokens ``[CLS, flatten(seg_0), ..., flatten(seg_{M-1})]`` of size
    ``L*C``; the CLS output is the global feature. Attention is over tokens *within* a sample (unlike the release,
    whose ``batch_first=False`` attention runs along the batch and so makes the CLS output a learned constant,
    ``out_proj(v_proj(cls))``; see the module docstring).

    ``kind='release'`` computes the release's function instead: ``out_proj(v_proj(cls))`` reshaped as the release
    reshapes it (``(C, L)``, channels first), the same for every sample and input (``ReleaseFusionAttention``);
    it needs ``L*C`` divisible by ``num_heads``, as torch does.

    ``token_dim`` (a model change, not the paper's form; None = the paper's): each segment token is first
    projected ``L*C -> token_dim`` (one shared ``Dense``), the attention runs on ``token_dim``-wide tokens and only
    the CLS output is projected back ``token_dim -> L*C``; tokens no wider than ``token_dim`` keep the paper's
    form (the first block's raw action segments). With ``L*C = 2048``, three segments and ``token_dim = 256`` that
    is 1.3 M instead of 16.8 M parameters and about a twentieth of the fusion's FLOPs (6.3 vs 134 MFLOP per sample).
    """

    num_segments: int
    num_heads: int = 8
    compute_dtype: ComputeDtype = "float32"  # the attention's projections and scores; the output is float32
    token_dim: int | None = None
    kind: FusionKind = "attention"

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        b, t, c = x.shape
        seg = t // self.num_segments
        d = seg * c
        dtype = jnp.dtype(self.compute_dtype)
        if self.kind == "release":
            if d % self.num_heads:
                raise ValueError(f"model.fusion_heads: the release's fusion needs the token size L_c*C={d} divisible "
                                 f"by fusion_heads={self.num_heads} (torch's MultiheadAttention does)")
            # the release's function: a learned constant, laid out as its (C, L_c) reshape of the CLS output
            cls = self.param("cls", nn.initializers.normal(stddev=1.0), (1, 1, d))
            glob = ReleaseFusionAttention(self.num_heads, d, d, dtype, name="attention")(cls[0, 0])
            glob = glob.astype(jnp.float32).reshape(c, seg).T  # (L, C)
            return jnp.broadcast_to(glob, (b, seg, c))
        tokens = x.reshape(b, self.num_segments, d)
        light = self.token_dim is not None and d > self.token_dim
        if light:
            tokens = nn.Dense(self.token_dim, dtype=dtype, name="token_in")(tokens).astype(jnp.float32)
        width = tokens.shape[-1]
        cls = self.param("cls", nn.initializers.normal(stddev=1.0), (1, 1, width))
        tokens = jnp.concatenate([jnp.broadcast_to(cls, (b, 1, width)), tokens], axis=1)  # (B, M+1, D)
        qkv = -(-width // self.num_heads) * self.num_heads
        out = nn.MultiHeadDotProductAttention(num_heads=self.num_heads, qkv_features=qkv, out_features=width,
                                              dtype=dtype, name="attention")(tokens, tokens)
        glob = out[:, 0].astype(jnp.float32)  # (B, D)
        if light:
            glob = nn.Dense(d, dtype=dtype, name="token_out")(glob).astype(jnp.float32)
        return glob.reshape(b, seg, c)


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

    ``film_cond`` is what ``FiLMHead`` takes: ``(B, K, Dcond)`` ``[step ⊕ cond]``, a ``FiLMInput`` or this block's
    precomputed ``FiLMParts``, with ``K`` dividing ``T`` (``K = M`` for hierarchical FiLM, ``K = 1`` for a single
    condition). With ``fusion`` the block follows the release's first-level block (module docstring);
    ``num_segments`` (M) is then the number of fusion tokens besides CLS.
    """

    out_channels: int
    kernel_size: int = 5
    n_groups: int = 8
    fusion: bool = False
    num_segments: int = 1
    fusion_heads: int = 8
    compute_dtype: ComputeDtype = "float32"
    fusion_token_dim: int | None = None
    fusion_kind: FusionKind = "attention"

    @nn.compact
    def __call__(self, x: jax.Array, film_cond) -> jax.Array:
        c, dt = self.out_channels, self.compute_dtype
        embed = FiLMHead(2 * c, name="film")(film_cond)  # (B, K, 2C)
        if self.fusion:
            glob = SegmentFusion(self.num_segments, self.fusion_heads, dt, self.fusion_token_dim, self.fusion_kind,
                                 name="fusion")(x)  # (B, L, C_in)
            glob = jnp.tile(glob, (1, self.num_segments, 1))  # same global feature for every segment
            h = Conv1dBlock(2 * c, self.kernel_size, self.n_groups, dt, name="block0")(jnp.concatenate([x, glob], -1))
            h = jnp.concatenate([apply_film(h[..., :c], embed), h[..., c:]], axis=-1)
        else:
            h = Conv1dBlock(c, self.kernel_size, self.n_groups, dt, name="block0")(x)
            h = apply_film(h, embed)
        h = Conv1dBlock(c, self.kernel_size, self.n_groups, dt, name="block1")(h)
        res = x if x.shape[-1] == c else Conv1d(c, 1, compute_dtype=dt, name="residual")(x)
        return h + res


class ConditionalUnet1D(nn.Module):
    """HiPolicy denoiser: ``(x (B, M*L_c, A), timesteps (B,) or (), cond (B, M, Dc)) -> (B, M*L_c, A)``.

    Fields: ``down_dims`` (channel width per level), ``kernel_size``, ``n_groups`` (GroupNorm), ``step_embed_dim``,
    ``num_freqs`` (M), ``chunk_len`` (L_c), ``condition`` ('hier' | 'low' | 'high'), ``fusion`` (global fusion, only
    active when M > 1), ``fusion_heads``, ``fusion_token_dim`` (None: the paper's full-width segment tokens; else the
    lighter fusion of ``SegmentFusion``), ``fusion_kind`` ('attention': per-sample attention over the segment
    tokens, as the paper describes; 'release': the release's learned constant, for its weights), ``compute_dtype`` ('float32' | 'bfloat16': the operands of every
    convolution and of the fusion attention; parameters, accumulation, GroupNorm, Mish, FiLM and the output stay
    float32). ``chunk_len`` must be divisible by ``2^(len(down_dims)-1)``.
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
    compute_dtype: ComputeDtype = "float32"
    fusion_token_dim: int | None = None
    fusion_kind: FusionKind = "attention"

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

    def block_specs(self) -> tuple[tuple[str, int, bool], ...]:
        """``(name, channels, fusion)`` of every residual block, in call order (the FiLM precompute's keys)."""
        specs = []
        for i, ch in enumerate(self.down_dims):
            fuse = self.uses_fusion and i == 0
            specs += [(f"down{i}_res0", ch, fuse), (f"down{i}_res1", ch, fuse)]
        specs += [("mid_res0", self.down_dims[-1], False), ("mid_res1", self.down_dims[-1], False)]
        for j, ch in enumerate(reversed(self.down_dims[:-1])):
            specs += [(f"up{j}_res0", ch, False), (f"up{j}_res1", ch, False)]
        return tuple(specs)

    def _film_cond(self, cond: jax.Array) -> jax.Array:
        """The per-segment conditions the FiLM heads see: ``(B, M, Dc)`` -> ``(B, K, Dc)`` (``K = 1`` for low/high)."""
        if self.condition == "low":
            return cond[:, :1]
        if self.condition == "high":
            return cond[:, -1:]
        return cond

    def film_condition(self, cond: jax.Array) -> dict[str, jax.Array]:
        """Observation half of every block's FiLM, once per sampler call: cond ``(B, M, Dc)`` -> ``{block: (B, K,
        2C)}`` = ``mish(cond)·W_c + b``. Reads the bound parameters (call through ``apply``)."""
        params = self.variables["params"]
        cond = self._film_cond(cond)
        return {name: film_cond_part(params[name]["film"], cond) for name, _, _ in self.block_specs()}

    def film_steps(self, timesteps: jax.Array) -> dict[str, jax.Array]:
        """Step half of every block's FiLM: timesteps ``(S,)`` -> ``{block: (S, 2C)}`` = ``mish(StepEncoder(t))·W_t``.
        Reads the bound parameters (call through ``apply``)."""
        params = self.variables["params"]
        step = StepEncoder(self.step_embed_dim, parent=None).apply(  # unbound: not a submodule
            {"params": {k: params[k] for k in ("step_dense0", "step_dense1")}}, timesteps)  # (S, d)
        return {name: film_step_part(params[name]["film"], step) for name, _, _ in self.block_specs()}

    @nn.compact
    def __call__(self, x: jax.Array, timesteps: jax.Array | None, cond: jax.Array | None,
                 film: dict[str, FiLMParts] | None = None) -> jax.Array:
        """Denoise ``x`` ``(B, M*L_c, A)`` at ``timesteps`` ``(B,)`` or ``()`` given ``cond`` ``(B, M, Dc)``.

        ``film``: ``{block: FiLMParts}`` precomputed from ``film_steps`` (one step's row) and ``film_condition``;
        when given, ``timesteps`` and ``cond`` are not used (pass None) and no step MLP or FiLM matmul runs.
        """
        if film is None:
            self._check(x, cond)
        elif x.ndim != 3 or x.shape[1] != self.num_freqs * self.chunk_len:
            raise ValueError(f"x: expected shape (B, M*L_c={self.num_freqs * self.chunk_len}, A), got {x.shape}")
        b, _, a = x.shape
        if film is None:
            step_encoder = StepEncoder(self.step_embed_dim)
            nn.share_scope(self, step_encoder)  # its Dense layers live at the U-Net's top level
            step = step_encoder(jnp.broadcast_to(jnp.asarray(timesteps), (b,)))  # (B, d)
            film_in = FiLMInput(step, self._film_cond(cond))
            films = {name: film_in for name, _, _ in self.block_specs()}
        else:
            films = film
        dt = self.compute_dtype
        blocks = {name: ConditionalResidualBlock1D(ch, self.kernel_size, self.n_groups, fuse, self.num_freqs,
                                                   self.fusion_heads, dt, self.fusion_token_dim,
                                                   self.fusion_kind, name=name)
                  for name, ch, fuse in self.block_specs()}

        def res(name, h):
            return blocks[name](h, films[name])

        levels = len(self.down_dims)
        skips = []
        for i, ch in enumerate(self.down_dims):
            x = res(f"down{i}_res0", x)
            x = res(f"down{i}_res1", x)
            skips.append(x)
            if i < levels - 1:
                x = Conv1d(ch, 3, stride=2, compute_dtype=dt, name=f"down{i}_downsample")(x)

        x = res("mid_res0", x)
        x = res("mid_res1", x)

        for j, ch in enumerate(reversed(self.down_dims[:-1])):
            x = jnp.concatenate([x, skips.pop()], axis=-1)
            x = res(f"up{j}_res0", x)
            x = res(f"up{j}_res1", x)
            x = Upsample1d(ch, dt, name=f"up{j}_upsample")(x)

        x = Conv1dBlock(self.down_dims[0], self.kernel_size, self.n_groups, dt, name="final_block")(x)
        return Conv1d(a, 1, compute_dtype=dt, name="final_conv")(x)
