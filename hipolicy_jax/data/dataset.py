"""Training samples: multi-frequency windows of a replay buffer, normalised, batched deterministically.

``SequenceDataset`` computes every sample's frame indices once (``windowing.sample_indices``), fits a
``Normalizer`` on the frames of its own episodes (or takes one, e.g. the training set's for a validation set),
normalises the low-dimensional arrays once, and serves batches by fancy indexing:

    obs[key]   (B, M, L_h, ...)   float32 (images (B, M, L_h, H, W, 3) in [-1, 1])
    action     (B, M*L_c, A)      float32 in [-1, 1] over the fitted range

Delta actions (``chunk.action_kinds`` with a ``'delta'``): the action chunks are built once, in data units, by
``windowing.segment_actions`` (a stride-s action of a delta dimension is the sum of its block's s deltas, zero motion
past the episode's end), and the normaliser fits the action per segment (``Normalizer.fit(segment_len=...)``),
since summed deltas span about s times the range of single ones. With every dimension absolute (``action_kinds``
None) the per-frame path below is unchanged, bit for bit.

``batch_indices(key, step, batch_size)`` is a pure function of its arguments: epoch ``step // steps_per_epoch``
is a permutation drawn from ``fold_in(key, epoch)``, so a resumed run sees exactly the batches it would have seen.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import numpy as np

from hipolicy_jax.config import ChunkConfig
from hipolicy_jax.data.normalizer import Normalizer, image_to_float
from hipolicy_jax.data.replay_buffer import ReplayBuffer, expected_layout
from hipolicy_jax.data.windowing import check_recorded_kinds, sample_indices, segment_actions


def split_episodes(num_episodes: int, val_ratio: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Random train / validation split of episodes: two disjoint boolean masks ``(E,)``.

    ``round(val_ratio * E)`` episodes go to validation, at least one when ``val_ratio > 0``, and at least one
    episode always stays in training.
    """
    if num_episodes < 1:
        raise ValueError(f"num_episodes: expected >= 1, got {num_episodes}")
    if not 0.0 <= val_ratio < 1.0:
        raise ValueError(f"val_ratio: expected a value in [0, 1), got {val_ratio}")
    num_val = int(round(val_ratio * num_episodes))
    num_val = min(max(num_val, 1 if val_ratio > 0 else 0), num_episodes - 1)
    val_mask = np.zeros(num_episodes, dtype=bool)
    val_mask[np.random.default_rng(seed).choice(num_episodes, size=num_val, replace=False)] = True
    return ~val_mask, val_mask


class SequenceDataset:
    """Windows of a ``ReplayBuffer`` for one ``ChunkConfig``, over the episodes selected by ``episode_mask``.

    Args:
      buffer: episodes; must hold ``action`` (T, A) and every key of ``obs_keys``.
      chunk: windowing configuration.
      obs_keys: observation keys, e.g. ``("state",)``, ``("image", "state")``, ``("point_cloud", "state")``.
      episode_mask: ``(E,)`` bool, the episodes this dataset uses (default all).
      normalizer: use this instead of fitting one (e.g. the training set's, for validation); it must cover
        ``action`` (per segment when the chunk has a delta dimension) and the non-image observation keys.
      max_action_pad: ``TrainConfig.max_action_pad`` (``windowing.sample_indices``): at most this many of a
        window's frames past its episode's last frame; None: no limit.
    """

    def __init__(self, buffer: ReplayBuffer, chunk: ChunkConfig, obs_keys: Sequence[str],
                 episode_mask: np.ndarray | None = None, normalizer: Normalizer | None = None,
                 max_action_pad: int | None = None):
        self.chunk = chunk
        self.obs_keys = tuple(obs_keys)
        for key in ("action",) + self.obs_keys:
            if key not in buffer.data:
                raise ValueError(f"buffer is missing key {key!r}, expected data[{key!r}] of shape "
                                 f"{expected_layout(key)}; buffer keys {sorted(buffer.data)}")

        if episode_mask is None:
            episode_mask = np.ones(buffer.num_episodes, dtype=bool)
        episode_mask = np.asarray(episode_mask)
        if episode_mask.dtype != bool or episode_mask.shape != (buffer.num_episodes,):
            raise ValueError(f"episode_mask: expected a bool array of shape ({buffer.num_episodes},), "
                             f"got {episode_mask.dtype} {episode_mask.shape}")
        if not episode_mask.any():
            raise ValueError("episode_mask: selects no episodes")
        self.episode_mask = episode_mask

        # Sample indices of the selected episodes (global frame indices into the buffer's arrays).
        current, obs_idx, act_idx = sample_indices(buffer.episode_ends, chunk, max_action_pad)
        keep = episode_mask[np.searchsorted(buffer.episode_ends, current, side="right")]
        if not keep.any():
            raise ValueError(f"train.max_action_pad={max_action_pad}: the selected episodes "
                             f"{np.flatnonzero(episode_mask).tolist()} are all too short for a window (lengths "
                             f"{buffer.episode_lengths()[episode_mask].tolist()}, chunk.action_span="
                             f"{chunk.action_span}); raise it, or None for no limit")
        self.current, self.obs_idx, self.act_idx = current[keep], obs_idx[keep], act_idx[keep]

        # The policy's action kinds; a buffer that records others is not this policy's data.
        kinds = chunk.kinds(buffer.data["action"].shape[-1])
        check_recorded_kinds(kinds, buffer.action_kinds, "the buffer")
        # Delta dimensions: every sample's chunk (S, M*L_c, A) once, summed per block; fitted per segment.
        chunks = (segment_actions(buffer.data["action"], buffer.episode_ends, self.current, chunk, kinds)
                  if chunk.has_delta else None)

        # Normalise the low-dimensional arrays once; images stay uint8 and are converted per batch.
        low_dim = [k for k in ("action",) + self.obs_keys if buffer.data[k].dtype != np.uint8]
        if normalizer is None:
            frames = np.repeat(episode_mask, buffer.episode_lengths())
            fitted = {k: buffer.data[k][frames] for k in low_dim if chunks is None or k != "action"}
            normalizer = Normalizer.fit({**fitted, **({} if chunks is None else {"action": chunks})}, keys=low_dim,
                                        segment_len=None if chunks is None else {"action": chunk.chunk_len})
        if normalizer.per_segment("action") != chunk.has_delta:
            have, need = [("per segment (M*L_c, A)" if x else "per feature (A,)")
                          for x in (normalizer.per_segment("action"), chunk.has_delta)]
            raise ValueError(f"normalizer: its action statistics are {have}, chunk.action_kinds="
                             f"{chunk.action_kinds} needs them {need}; fit it on a dataset of this chunk")
        self.normalizer = normalizer
        self.arrays = {k: (normalizer.normalize(k, buffer.data[k]) if k in low_dim else buffer.data[k])
                       for k in dict.fromkeys(self.obs_keys + (() if chunks is not None else ("action",)))}
        self.action_chunks = None if chunks is None else normalizer.normalize("action", chunks)  # (S, M*L_c, A)

    def __len__(self) -> int:
        """S, the number of samples (current frames) in the selected episodes."""
        return int(self.current.shape[0])

    def steps_per_epoch(self, batch_size: int) -> int:
        """Full batches per epoch (the last partial batch is dropped)."""
        if batch_size < 1:
            raise ValueError(f"batch_size: expected >= 1, got {batch_size}")
        if len(self) < batch_size:
            raise ValueError(f"batch_size: the dataset has {len(self)} samples, fewer than batch_size={batch_size}")
        return len(self) // batch_size

    def batch_indices(self, key: jax.Array, step: int, batch_size: int) -> np.ndarray:
        """``(B,)`` sample indices of training step ``step``; a pure function of ``(key, step, batch_size)``.

        The epoch's permutation is numpy's (PCG64) seeded by the bits of ``fold_in(key, epoch)``: the same
        permutation on every machine and restart, at a fraction of the cost of ``jax.random.permutation`` on the
        host for large datasets.
        """
        per_epoch = self.steps_per_epoch(batch_size)
        epoch, within = divmod(int(step), per_epoch)
        seed = np.asarray(jax.random.key_data(jax.random.fold_in(key, epoch)))
        perm = np.random.default_rng(seed).permutation(len(self))
        return perm[within * batch_size:(within + 1) * batch_size]

    def get_batch(self, idx: np.ndarray) -> dict:
        """Samples ``idx`` ``(B,)`` -> ``{"obs": {key: (B, M, L_h, ...)}, "action": (B, M*L_c, A)}`` float32."""
        idx = np.asarray(idx)
        obs = {}
        for key in self.obs_keys:
            frames = self.arrays[key][self.obs_idx[idx]]
            obs[key] = image_to_float(frames) if frames.dtype == np.uint8 else frames
        action = (self.arrays["action"][self.act_idx[idx]] if self.action_chunks is None
                  else self.action_chunks[idx])
        return {"obs": obs, "action": action}


def train_heldout_datasets(buffer: ReplayBuffer, chunk: ChunkConfig, obs_keys: Sequence[str], val_ratio: float,
                           seed: int, normalizer: Normalizer | None = None,
                           max_action_pad: int | None = None) -> tuple[SequenceDataset, SequenceDataset]:
    """The one train / held-out split of a run: episodes split by ``split_episodes(val_ratio, seed)``; the held-out
    dataset uses the training normaliser (or ``normalizer``, e.g. a checkpoint's, for both) and the same windows
    (``max_action_pad``, ``TrainConfig.max_action_pad``)."""
    train_mask, val_mask = split_episodes(buffer.num_episodes, val_ratio, seed)
    train = SequenceDataset(buffer, chunk, obs_keys=obs_keys, episode_mask=train_mask, normalizer=normalizer,
                            max_action_pad=max_action_pad)
    val = SequenceDataset(buffer, chunk, obs_keys=obs_keys, episode_mask=val_mask, normalizer=train.normalizer,
                          max_action_pad=max_action_pad)
    return train, val
