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
4. unnormalises the chunks → (B, N, M·L_c, A);
5. computes the action entropy H = mean over frequencies, steps and action dims of 0.5·log(2πe·var + ε), with the
   ddof=1 variance over the N samples of the *unnormalised* actions (as the reference release);
6. selects the execution frequency from ascending thresholds (lowest entropy → highest frequency) and returns
   sample 0's chunk at that frequency.

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


class SampleResult(NamedTuple):
    chunks: jax.Array  # (B, N, M·L_c, A) unnormalised actions of all samples
    entropy: jax.Array  # (B,) action entropy; NaN when N == 1
    freq_index: jax.Array  # (B,) int32, index into chunk.strides (0 = highest frequency)
    stride: jax.Array  # (B,) int32, the selected stride
    actions: jax.Array  # (B, L_c, A) sample 0's chunk at the selected stride


def action_entropy(chunks: jax.Array, eps: float = 1e-6) -> jax.Array:
    """Gaussian action entropy of N samples: chunks (..., N, T, A) → (...), N ≥ 2.

    H = mean over (T, A) of 0.5·log(2πe·var + eps), var the unbiased (ddof=1) variance over the N axis.
    """
    var = jnp.var(chunks, axis=-3, ddof=1)
    return jnp.mean(0.5 * jnp.log(2.0 * jnp.pi * jnp.e * var + eps), axis=(-2, -1))


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
                  horizon: int, action_dim: int, film: bool = False) -> jax.Array:
    """One chain of the head's sampler for a batch → normalised chunks (B, horizon, A), from Gaussian noise.

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
        return plan.update(row, x, out, k), None

    step_keys = jax.random.split(key, plan.table.time.shape[0])
    x, _ = jax.lax.scan(body, x, (plan.table, step_keys))
    return plan.finish(x)


def sample(params, normalizer, obs: dict[str, jax.Array], key: jax.Array, thresholds=None, *, net,
           cfg: PolicyConfig, action_dim: int, inference: InferenceConfig = InferenceConfig(),
           obs_normalized: bool = False) -> SampleResult:
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
    """
    head = make_head(cfg)
    n = inference.num_samples
    cond = net.apply(params, obs if obs_normalized else normalizer.normalize_obs(obs), method=net.encode)
    film = precomputes_film(net)
    if film:
        cond = net.apply(params, cond, method=net.film_condition)  # {block: (B, K, 2C)}, once per call
    chain = functools.partial(denoise_chain, net, params, cond, head=head, inference=inference,
                              horizon=cfg.chunk.horizon, action_dim=action_dim, film=film)
    chunks = jax.vmap(chain)(jax.random.split(key, n))  # (N, B, T, A)
    chunks = normalizer.unnormalize("action", jnp.swapaxes(chunks, 0, 1))  # (B, N, T, A)
    if n >= 2:
        entropy = action_entropy(chunks, inference.entropy_eps)
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
