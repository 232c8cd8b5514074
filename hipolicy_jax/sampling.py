"""The one-call N-sample sampler with entropy-guided frequency selection, for every generative head.

``sample`` is the only sampler in the code base: evaluation, benchmarks, calibration and tests all call it
(``make_sampler`` compiles it for one setting). One compiled call

1. normalises the observation windows and encodes them ONCE → condition (B, M, Dc);
2. computes the FiLM heads' observation half ``mish(cond)·W_c + b`` once per call, when the network offers
   ``film_condition`` / ``film_steps`` / ``denoise_film`` as ``PolicyNet`` does (a network with only ``encode`` /
   ``denoise`` is called per step with the condition);
3. draws N independent chains per observation: ``vmap`` over the N sample keys, ``lax.scan`` over the generative
   head's precomputed step table (``heads``: DDPM / DDIM for diffusion, Euler for flow matching), the head's
   update applied at every step;
4. unnormalises the chunks → (B, N, M·L_c, A) (``Normalizer.unnormalize``, per segment when the policy has delta
   action dimensions: a stride-s segment's delta dimensions then hold summed deltas, s control steps of motion
   per action, ``ChunkConfig.action_kinds``);
5. computes the action entropy H = mean over frequencies, steps and action dims of 0.5·log(2πe·var + ε), with the
   ddof=1 variance over the N samples of the *unnormalised* actions (as the reference release);
6. selects the execution frequency from ascending thresholds (lowest entropy → highest frequency) and returns
   sample 0's chunk at that frequency.

With a ``prefix`` (asynchronous execution's prefix inpainting) the first d actions of every frequency's segment
are known: after each update of the chain they are overwritten with where a chain ending in them would stand
(the head's ``renoise``, fresh noise per step), so the last step leaves them equal to the prefix and the free
actions were denoised around them; the entropy then averages over the free actions only. The chain's own draws
do not change (the renoising draws from a key split off each step's), so a row whose ``prefix_valid`` is False is
exactly the plain sampler's: one compiled program serves decisions with and without committed actions.

Chunk layout (see ``config``): segments in descending-stride order, so stride ``strides[k]`` (frequency index k,
0 = highest frequency) lives in segment ``M-1-k``.
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax.config import ChunkConfig, InferenceConfig, PolicyConfig
from hipolicy_jax.heads import GenerativeHead, make_head
from hipolicy_jax.models.unet import lowp_kernels


class SampleResult(NamedTuple):
    chunks: jax.Array  # (B, N, M·L_c, A) unnormalised actions of all samples (delta dims at stride s: summed deltas)
    entropy: jax.Array  # (B,) action entropy; NaN when N == 1
    freq_index: jax.Array  # (B,) int32, index into chunk.strides (0 = highest frequency)
    stride: jax.Array  # (B,) int32, the selected stride
    actions: jax.Array  # (B, L_c, A) sample 0's chunk at the selected stride, unnormalised; a delta dimension
    # (``ChunkConfig.action_kinds``) holds the sum of ``stride`` control steps' displacements per action


def action_entropy(chunks: jax.Array, eps: float = 1e-6, free: jax.Array | None = None) -> jax.Array:
    """Gaussian action entropy of N samples: chunks (..., N, T, A) → (...), N ≥ 2.

    H = mean over (T, A) of 0.5·log(2πe·var + eps), var the unbiased (ddof=1) variance over the N axis; with
    ``free`` (..., T) bool the mean runs over the free steps only.
    """
    var = jnp.var(chunks, axis=-3, ddof=1)
    h = 0.5 * jnp.log(2.0 * jnp.pi * jnp.e * var + eps)
    if free is None:
        return jnp.mean(h, axis=(-2, -1))
    w = free.astype(h.dtype)[..., None]
    return jnp.sum(h * w, axis=(-2, -1)) / (jnp.sum(w, axis=(-2, -1)) * h.shape[-1])


def prefix_mask(chunk: ChunkConfig, prefix_len: int, valid: jax.Array) -> jax.Array:
    """(B, M·L_c) bool: the first ``prefix_len`` steps of every frequency's segment, where ``valid`` (B,)."""
    steps = jnp.arange(chunk.horizon) % chunk.chunk_len
    return (steps < prefix_len)[None, :] & jnp.asarray(valid, bool)[:, None]


def select_frequency(entropy: jax.Array, thresholds, num_freqs: int) -> jax.Array:
    """Frequency index per entropy (int32, same shape): k with thresholds[k] ≤ H < thresholds[k+1].

    ``thresholds``: M+1 ascending values (sequence or traced array). Only the M-1 inner thresholds decide;
    entropies beyond the outer ones clamp to the first / last frequency.
    ``thresholds=None`` (uncalibrated) or a NaN entropy selects the highest frequency (index 0).
    """
    if thresholds is None or num_freqs == 1:
        return jnp.zeros(jnp.shape(entropy), jnp.int32)
    inner = jnp.asarray(thresholds, jnp.float32)[1:num_freqs]
    k = jnp.searchsorted(inner, entropy, side="right").astype(jnp.int32)
    return jnp.where(jnp.isnan(entropy), 0, k)


def segment_of(chunk: ChunkConfig, chunks: jax.Array, freq_index: jax.Array) -> jax.Array:
    """The L_c steps of frequency ``freq_index`` from chunks (B, M·L_c, A) → (B, L_c, A)."""
    lc, m = chunk.chunk_len, chunk.num_freqs
    segs = chunks.reshape(chunks.shape[0], m, lc, chunks.shape[-1])
    return jnp.take_along_axis(segs, (m - 1 - freq_index)[:, None, None, None], axis=1)[:, 0]


def precomputes_film(net) -> bool:
    """Whether ``net`` offers the FiLM precompute protocol (``film_condition``, ``film_steps``, ``denoise_film``)."""
    return all(hasattr(net, m) for m in ("film_condition", "film_steps", "denoise_film"))


def denoise_chain(net, params, cond, key: jax.Array, *, head: GenerativeHead, inference: InferenceConfig,
                  horizon: int, action_dim: int, film: bool = False, known: jax.Array | None = None,
                  known_mask: jax.Array | None = None) -> jax.Array:
    """One chain of the head's sampler for a batch → normalised chunks (B, horizon, A), from Gaussian noise.

    ``known`` (B, horizon, A) normalised actions and ``known_mask`` (B, horizon) bool: inpainting; after every
    update the masked entries become ``plan.renoise(row, known, fresh noise)``, so they end equal to ``known``;
    the update draws from the step's key as without ``known``, so unmasked rows are the plain chain's exactly.

    ``cond``: the condition (B, M, Dc), or with ``film`` the precomputed FiLM observation halves
    ``{block: (B, K, 2C)}`` (``film_condition``); each step then only adds its step half (one row of ``film_steps``,
    one row per block). The step halves are deliberately not precomputed into an (S, 2C) table sliced inside the
    loop: on XLA:CPU that made the whole sampler ~1.5x slower (``benchmarks/results/PERFORMANCE.md``).
    """
    plan = head.plan(inference)
    batch = jax.tree.leaves(cond)[0].shape[0]
    shape = (batch, horizon, action_dim)
    key, k0 = jax.random.split(key)
    x = jax.random.normal(k0, shape, jnp.float32)

    def body(x, row_and_key):
        row, k = row_and_key
        if film:
            step = jax.tree.map(lambda a: a[0], net.apply(params, row.time[None], method=net.film_steps))
            out = net.apply(params, x, step, cond, method=net.denoise_film)
        else:
            out = net.apply(params, x, jnp.full((batch,), row.time), cond, method=net.denoise)
        x = plan.update(row, x, out, k)  # the step's key, as without a prefix: a row without one is the plain chain
        if known is None:
            return x, None
        x = jax.lax.optimization_barrier(x)  # the update compiled as without inpainting: unmasked rows bit for bit
        target = plan.renoise(row, known, jax.random.normal(jax.random.split(k)[1], x.shape, x.dtype))
        return jnp.where(known_mask[..., None], target, x), None

    step_keys = jax.random.split(key, plan.table.time.shape[0])
    x, _ = jax.lax.scan(body, x, (plan.table, step_keys))
    return plan.finish(x)


def sample(params, normalizer, obs: dict[str, jax.Array], key: jax.Array, thresholds=None, *, net,
           cfg: PolicyConfig, action_dim: int, inference: InferenceConfig = InferenceConfig(),
           obs_normalized: bool = False, prefix: jax.Array | None = None,
           prefix_valid: jax.Array | None = None) -> SampleResult:
    """Sample N action chunks per observation and select the execution frequency, in one call.

    Args:
      params: PolicyNet variables.
      normalizer: ``data.normalizer.Normalizer`` fitted on the training data.
      obs: observation windows, each (B, M, L_h, ...) in segment order (``data.windowing``); raw unless
        ``obs_normalized`` (static) says they come normalised, as ``SequenceDataset.get_batch`` returns them.
      key: PRNG key; the result is a deterministic function of it.
      thresholds: (M+1,) ascending entropy thresholds (traced, so sweeping them does not recompile) or None
        (always the highest frequency).
      net: the ``PolicyNet`` module; cfg: its ``PolicyConfig`` (the head comes from ``cfg.objective``).
      inference: N, sampler and number of steps (``InferenceConfig``; its thresholds are not read here).
      prefix: (B, d, A) unnormalised actions already committed for the chunk's first d control steps, or None:
        inpainted into the first d steps of every frequency's segment where ``prefix_valid`` (B,) bool (default
        all); the entropy then reads the other steps.

    Returns a ``SampleResult`` of unnormalised actions: absolute targets, and for delta action dimensions at
    stride s the summed deltas of s control steps (``data.windowing.segment_actions``), normalised and
    unnormalised with each segment's statistics (``Normalizer.normalize`` / ``unnormalize``, the one place).
    """
    head = make_head(cfg)
    n = inference.num_samples
    params = lowp_kernels(params, cfg.model.compute_dtype)  # bf16 kernels once per call, not once per step
    cond = net.apply(params, obs if obs_normalized else normalizer.normalize_obs(obs), method=net.encode)
    film = precomputes_film(net)
    if film:
        cond = net.apply(params, cond, method=net.film_condition)  # {block: (B, K, 2C)}, once per call
    known = free = None
    if prefix is not None:
        batch, d = prefix.shape[0], prefix.shape[1]
        if not 1 <= d <= cfg.chunk.chunk_len:
            raise ValueError(f"prefix: (B, d, A) with 1 <= d <= chunk_len={cfg.chunk.chunk_len}, got {prefix.shape}")
        valid = jnp.ones((batch,), bool) if prefix_valid is None else prefix_valid
        mask = prefix_mask(cfg.chunk, d, valid)
        tiled = jnp.tile(jnp.pad(prefix, ((0, 0), (0, cfg.chunk.chunk_len - d), (0, 0))),
                         (1, cfg.chunk.num_freqs, 1))  # (B, T, A)
        known, free = normalizer.normalize("action", tiled), ~mask
    chain = functools.partial(denoise_chain, net, params, cond, head=head, inference=inference,
                              horizon=cfg.chunk.horizon, action_dim=action_dim, film=film, known=known,
                              known_mask=None if known is None else mask)
    chunks = jax.vmap(chain)(jax.random.split(key, n))  # (N, B, T, A)
    chunks = normalizer.unnormalize("action", jnp.swapaxes(chunks, 0, 1))  # (B, N, T, A)
    if n >= 2:
        entropy = action_entropy(chunks, inference.entropy_eps)
        if free is not None:  # rows without a prefix: the plain entropy, bit for bit (the barrier keeps XLA from
            # fusing the two reductions into one that rounds differently)
            masked = action_entropy(jax.lax.optimization_barrier(chunks), inference.entropy_eps, free)
            entropy = jnp.where(jnp.all(free, axis=-1), entropy, masked)
    else:
        entropy = jnp.full(chunks.shape[:1], jnp.nan, jnp.float32)
    k = select_frequency(entropy, thresholds, cfg.chunk.num_freqs)
    strides = jnp.asarray(np.asarray(cfg.chunk.strides), jnp.int32)
    return SampleResult(chunks, entropy, k, strides[k], segment_of(cfg.chunk, chunks[:, 0], k))


def make_sampler(net, cfg: PolicyConfig, action_dim: int, inference: InferenceConfig = InferenceConfig(), *,
                 obs_normalized: bool = False) -> Callable[..., SampleResult]:
    """``sample`` compiled for one network and setting: ``fn(params, normalizer, obs, key, thresholds=None)``.

    The returned function owns its compiled program (no global cache): keep it to reuse the compile; new
    parameters, keys, observations of the same shapes or thresholds of the same structure never retrace. Only
    ``inference.sampler_settings()`` matters, so calibration settings in ``inference`` are ignored.
    """
    fn = functools.partial(sample, net=net, cfg=cfg, action_dim=action_dim, inference=inference.sampler_settings(),
                           obs_normalized=obs_normalized)
    return jax.jit(fn)
