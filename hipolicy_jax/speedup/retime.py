"""DemoSpeedup's segmentation and downsampling, pure numpy: entropies in, the accelerated episodes out.

- ``label_frames(entropy (T,)) -> (T,) int8``: ``PRECISE`` (0) or ``CASUAL`` (1) per frame of one demo (the rule
  ``config.SpeedupConfig`` describes: per-demo z-score, running median over ``min_segment`` frames, precise below
  ``precise_z`` in runs of at least ``min_segment`` frames, the first ``casual_prefix`` frames casual);
- ``segments(labels (T,))``: the runs of equal labels, ``[(start, end, label), ...]`` (end exclusive);
- ``keep_indices(labels (T,)) -> (K,) int64``: the frames kept (the walk of the authors' ``process_action_label``:
  a precise frame advances ``precise_rate``, a casual one ``casual_rate`` when the next ``casual_rate`` frames are all
  casual, else to the next precise frame), always with the first (0) and the last (T-1) frame;
- ``retime_episode(episode {key: (T, ...)}, kept (K,), kinds (A,)) -> {key: (K, ...)}``: observations and absolute
  action dimensions are the kept frames'; a delta dimension of kept frame k_j is the sum of the deltas from k_j up to
  the next kept frame (exclusive), so the accelerated demo moves as far as the original did;
- ``accelerate(buffer, entropy (T,), kinds, cfg) -> (ReplayBuffer, [per-episode record])``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.speedup.config import SpeedupConfig

PRECISE, CASUAL = 0, 1  # upstream's labels: 0 precision, 1 non-precision (casual)


def zscore(x: np.ndarray) -> np.ndarray:
    """``(x - mean) / std`` over the demo (``(T,)``); a constant demo (values within 1e-9 relative of each other,
    so that rounding in the mean does not read as variation) gives zeros."""
    x = np.asarray(x, np.float64)
    if x.size == 0 or np.ptp(x) <= 1e-9 * max(1.0, float(np.max(np.abs(x)))):
        return np.zeros_like(x)
    return (x - np.mean(x)) / np.std(x)


def running_median(x: np.ndarray, window: int) -> np.ndarray:
    """Centred running median of ``x`` ``(T,)`` over ``window`` frames, the ends padded with the edge values."""
    x = np.asarray(x, np.float64)
    if window <= 1 or x.size == 0:
        return x.copy()
    left = (window - 1) // 2
    padded = np.pad(x, (left, window - 1 - left), mode="edge")
    return np.median(np.lib.stride_tricks.sliding_window_view(padded, window), axis=-1)


def segments(labels: np.ndarray) -> list[tuple[int, int, int]]:
    """Runs of equal labels ``[(start, end, label), ...]``, end exclusive, covering ``labels`` ``(T,)`` in order."""
    labels = np.asarray(labels)
    if labels.size == 0:
        return []
    cuts = np.flatnonzero(np.diff(labels)) + 1
    starts = np.concatenate([[0], cuts])
    ends = np.concatenate([cuts, [labels.size]])
    return [(int(s), int(e), int(labels[s])) for s, e in zip(starts, ends)]


def label_frames(entropy: np.ndarray, cfg: SpeedupConfig) -> np.ndarray:
    """``(T,)`` int8 ``PRECISE`` / ``CASUAL`` of one demo from its per-frame entropies ``(T,)`` (module docstring)."""
    h = np.asarray(entropy, np.float64)
    if h.ndim != 1 or h.size == 0:
        raise ValueError(f"entropy: expected one demo's per-frame entropies (T,), got shape {h.shape}")
    if not np.isfinite(h).all():
        raise ValueError(f"entropy: expected finite values, frame {int(np.argmin(np.isfinite(h)))} is not")
    smooth = running_median(zscore(h), cfg.min_segment)
    labels = np.where(smooth < cfg.precise_z, PRECISE, CASUAL).astype(np.int8)
    for start, end, label in segments(labels):
        if label == PRECISE and end - start < cfg.min_segment:  # shorter than a cluster: noise, casual
            labels[start:end] = CASUAL
    labels[:cfg.casual_prefix] = CASUAL
    return labels


def keep_indices(labels: np.ndarray, cfg: SpeedupConfig) -> np.ndarray:
    """``(K,)`` int64 ascending frames of one demo kept on the accelerated timeline, from its labels ``(T,)``;
    frame 0 and frame T-1 always (module docstring)."""
    labels = np.asarray(labels)
    last = labels.size - 1
    if last < 0:
        raise ValueError("labels: empty demo (0 frames)")
    kept, i = [0], 0
    while True:
        if labels[i] == PRECISE:
            nxt = i + cfg.precise_rate
        elif np.all(labels[i:i + cfg.casual_rate] == CASUAL):
            nxt = i + cfg.casual_rate
        else:
            nxt = i + 1 + int(np.flatnonzero(labels[i + 1:] == PRECISE)[0])
        if nxt >= last:
            break
        kept.append(nxt)
        i = nxt
    if last > 0:
        kept.append(last)
    return np.asarray(kept, np.int64)


def retime_episode(episode: dict[str, np.ndarray], kept: np.ndarray,
                   kinds: Sequence[str]) -> dict[str, np.ndarray]:
    """One episode ``{key: (T, ...)}`` on the accelerated timeline ``{key: (K, ...)}``: every key's kept frames,
    except the ``action`` dimensions whose kind is ``'delta'``: the sum of ``action[k_j : k_{j+1}]`` (the last kept
    frame's own delta)."""
    kept = np.asarray(kept, np.int64)
    out = {key: np.asarray(arr)[kept] for key, arr in episode.items()}
    delta = np.asarray([k == "delta" for k in kinds], bool)
    if "action" in episode and delta.any():
        action = np.asarray(episode["action"])
        if action.shape[-1] != delta.size:
            raise ValueError(f"action_kinds: {len(kinds)} kinds for {action.shape[-1]}-dim actions")
        out["action"] = out["action"].copy()  # reduceat: the sum of action[k_j : k_{j+1}], the last to the end
        out["action"][:, delta] = np.add.reduceat(action[:, delta], kept, axis=0).astype(action.dtype)
    return out


def accelerate(buffer: ReplayBuffer, entropy: np.ndarray, kinds: Sequence[str],
               cfg: SpeedupConfig) -> tuple[ReplayBuffer, list[dict]]:
    """The accelerated buffer of ``buffer`` from per-frame entropies ``(T,)`` (``entropy.frame_entropies``) and the
    actions' ``kinds`` ``(A,)``; its ``action_kinds`` are the source's. Also, per episode, ``{original_length,
    new_length, kept (K,), segments [[start, end, label, rate], ...]}`` in source frames."""
    entropy = np.asarray(entropy, np.float64)
    if entropy.shape != (buffer.num_frames,):
        raise ValueError(f"entropy: expected one value per frame ({buffer.num_frames},), got {entropy.shape}")
    episodes, record = [], []
    for e in range(buffer.num_episodes):
        sl = buffer.episode_slice(e)
        labels = label_frames(entropy[sl], cfg)
        kept = keep_indices(labels, cfg)
        episodes.append(retime_episode(buffer.get_episode(e), kept, kinds))
        record.append({"original_length": int(sl.stop - sl.start), "new_length": int(kept.size),
                       "kept": kept.tolist(),
                       "segments": [[s, t, lab, cfg.rate(lab)] for s, t, lab in segments(labels)]})
    return ReplayBuffer.from_episodes(episodes, action_kinds=buffer.action_kinds), record
