"""DemoSpeedup's per-frame action entropy: a Gaussian kernel density over a proxy policy's N sampled first actions.

``kde_entropy(samples (..., N, D)) -> (...)`` is the estimator (``KDE.kde_entropy`` of the authors' code, written
anew): with the kernel k(x, y) = exp(-|x - y|^2 / (2 h^2)) (unnormalised, as upstream), every sample's density is
its mean kernel value over the N samples (itself included), and the entropy is minus the mean log density:

    H = -1/N sum_i log( 1/N sum_j k(x_i, x_j) + eps )

so a point mass gives -log(1 + eps) ~ 0 and N samples far apart (relative to h) give log N, the largest value.
For samples of N(mu, s^2 I_D) and N -> oo it tends to (D/2) log(1 + s^2/h^2) + D s^2 / (2 (h^2 + s^2)); adding
(D/2) log(2 pi h^2) (the kernel's normalisation) gives the usual kernel-density differential entropy estimate.

``frame_entropies`` feeds every frame's observation window of a buffer through the project's one-call sampler
(``sampling.make_sampler``) in fixed-size batches (one compile), takes the first action of the highest-frequency
segment of each of the N chunks, normalised as the proxy was trained (``Normalizer.normalize('action')``), and
returns one entropy per frame ``(T,)``. ``saturated_fraction`` says how many of them sit at the ceiling log N.
``ladder_entropies`` returns them under each of ``SpeedupConfig.bandwidths()`` at once ``(K, T)`` (one sampling
pass), and ``choose_bandwidth`` applies the ladder rule (the first candidate with at most ``max_saturated`` of the
frames at the ceiling; none: the last).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import numpy as np

from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.data.windowing import obs_offsets
from hipolicy_jax.sampling import make_sampler
from hipolicy_jax.speedup.config import SpeedupConfig


def kde_entropy(samples, bandwidth: float, eps: float = 1e-8) -> np.ndarray:
    """Kernel-density entropy of N samples: ``samples`` ``(..., N, D)`` -> ``(...)`` float64 (module docstring)."""
    x = np.asarray(samples, np.float64)
    if x.ndim < 2 or x.shape[-2] < 2:
        raise ValueError(f"samples: expected (..., N, D) with N >= 2, got shape {x.shape}")
    if not bandwidth > 0:
        raise ValueError(f"bandwidth: must be > 0, got {bandwidth}")
    sq = np.sum(np.square(x[..., :, None, :] - x[..., None, :, :]), axis=-1)  # (..., N, N)
    density = np.mean(np.exp(-sq / (2.0 * bandwidth ** 2)), axis=-1)  # (..., N)
    return -np.mean(np.log(density + eps), axis=-1)


def saturated_fraction(entropy, num_samples: int, tol: float = 1e-3) -> float:
    """The fraction of ``entropy`` ``(T,)`` within ``tol`` of the estimator's ceiling log N: frames whose N samples
    each sit alone in their kernel (spread far wider than the bandwidth), so their entropy says nothing about them.
    Near 1, the segmentation has nothing to read: the bandwidth is too small for the proxy's samples."""
    h = np.asarray(entropy, np.float64)
    return float(np.mean(h >= np.log(num_samples) - tol)) if h.size else 0.0


def choose_bandwidth(entropies, cfg: SpeedupConfig) -> int:
    """The index into ``cfg.bandwidths()`` the ladder rule takes for ``entropies`` ``(K, T)`` (one row per
    candidate): the first whose saturated fraction is at most ``cfg.max_saturated``, else the last."""
    h = np.asarray(entropies, np.float64)
    if h.ndim != 2 or h.shape[0] != len(cfg.bandwidths()):
        raise ValueError(f"entropies: expected ({len(cfg.bandwidths())}, T), one row per candidate bandwidth, got "
                         f"shape {h.shape}")
    fractions = [saturated_fraction(row, cfg.num_samples) for row in h]
    return next((i for i, f in enumerate(fractions) if f <= cfg.max_saturated), len(fractions) - 1)


def frame_windows(episode_ends: np.ndarray, chunk) -> np.ndarray:
    """``(T, M, L_h)`` int64 observation frames of every frame t of every episode (``windowing.obs_offsets``),
    clamped to its episode: the window the policy sees at t, as in training and rollouts."""
    ends = np.asarray(episode_ends, np.int64)
    t = np.arange(int(ends[-1]), dtype=np.int64)
    episode = np.searchsorted(ends, t, side="right")
    lo = np.concatenate([[0], ends[:-1]])[episode][:, None, None]
    hi = (ends[episode] - 1)[:, None, None]
    return np.clip(t[:, None, None] + obs_offsets(chunk)[None], lo, hi)


def frame_entropies(policy, buffer: ReplayBuffer, cfg: SpeedupConfig, key: jax.Array, *,
                    inference: InferenceConfig = InferenceConfig(), batch_size: int = 64,
                    progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Entropy ``(T,)`` float64 of the proxy's first action at every frame of ``buffer``, under the bandwidth the
    ladder rule chooses (``cfg.bandwidth`` when the ladder is empty); arguments as ``ladder_entropies``."""
    h = ladder_entropies(policy, buffer, cfg, key, inference=inference, batch_size=batch_size, progress=progress)
    return h[choose_bandwidth(h, cfg)]


def ladder_entropies(policy, buffer: ReplayBuffer, cfg: SpeedupConfig, key: jax.Array, *,
                     inference: InferenceConfig = InferenceConfig(), batch_size: int = 64,
                     progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Entropy ``(K, T)`` float64 of the proxy's first action at every frame of ``buffer``, one row per candidate
    bandwidth of ``cfg.bandwidths()`` (the same samples for every row).

    Args:
      policy: the proxy, a ``checkpoint.LoadedPolicy`` (``runs.store.load_run(...).policy``): ``cfg``, ``net``,
        ``params``, ``normalizer``, ``meta['action_dim']``.
      buffer: the demos; holds the proxy's observation keys (``stage.check_proxy_fits``).
      cfg: ``num_samples`` N, ``bandwidths()``, ``density_eps``.
      key: PRNG key; batch i draws from ``fold_in(key, i)``, so the result is a function of the key.
      inference: sampler and steps (its ``num_samples`` is replaced by ``cfg.num_samples``).
      batch_size: frames per sampler call; the last batch is padded, so the sampler compiles once.
      progress: called with the number of frames done after each batch.
    """
    pcfg, chunk = policy.cfg, policy.cfg.chunk
    action_dim = int(policy.meta["action_dim"])
    settings = dataclasses.replace(inference.sampler_settings(), num_samples=cfg.num_samples)
    sampler = make_sampler(policy.net, pcfg, action_dim, settings)
    windows = frame_windows(buffer.episode_ends, chunk)  # (T, M, L_h)
    first = (chunk.num_freqs - 1) * chunk.chunk_len  # the highest frequency's segment is the last one
    num_frames, out = windows.shape[0], []
    for i, start in enumerate(range(0, num_frames, batch_size)):
        idx = np.arange(start, min(start + batch_size, num_frames))
        idx = np.concatenate([idx, np.repeat(idx[-1:], batch_size - len(idx))])  # one compiled shape
        obs = {k: buffer.data[k][windows[idx]] for k in pcfg.encoder.obs_keys}  # (B, M, L_h, ...) raw
        res = sampler(policy.params, policy.normalizer, obs, jax.random.fold_in(key, i))
        chunks = np.asarray(policy.normalizer.normalize("action", np.asarray(res.chunks)))  # (B, N, M*L_c, A)
        h = np.stack([kde_entropy(chunks[:, :, first, :], b, cfg.density_eps) for b in cfg.bandwidths()])  # (K, B)
        done = min(batch_size, num_frames - start)
        out.append(h[:, :done])
        if progress is not None:
            progress(done)
    return np.concatenate(out, axis=1)
