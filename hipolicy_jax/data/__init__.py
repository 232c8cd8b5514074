"""Data stages: episode storage -> multi-frequency window indices -> normalisation -> batches.

``replay_buffer`` (Diffusion Policy zarr layout), ``windowing`` (frame indices per stride), ``normalizer``
(min–max limits to [-1, 1]) and ``dataset`` (normalised, deterministically batched samples).
"""

from hipolicy_jax.data.dataset import SequenceDataset, split_episodes
from hipolicy_jax.data.normalizer import Normalizer, image_to_float
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.data.windowing import (action_offsets, delta_segment_coverage, gather_history,
                                         history_window_indices, obs_offsets, sample_indices)

__all__ = [
    "ReplayBuffer",
    "Normalizer",
    "image_to_float",
    "SequenceDataset",
    "split_episodes",
    "sample_indices",
    "history_window_indices",
    "gather_history",
    "obs_offsets",
    "action_offsets",
    "delta_segment_coverage",
]
