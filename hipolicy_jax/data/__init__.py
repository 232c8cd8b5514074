"""Data, the first stage of the flow: demonstrations on disk -> normalised, batched training samples.

    importers -> replay_buffer -> windowing -> normalizer -> dataset -> (training: ``runs.train``)

* ``importers`` (package): other projects' demo formats (Diffusion Policy zarr, robomimic hdf5, LeRobot) read into
  a ``ReplayBuffer``, checked by ``validation`` (``DataValidationError``); run by ``experiments.import_data``.
* ``replay_buffer``: episode storage in Diffusion Policy's zarr layout (``data/<key>``, ``meta/episode_ends``,
  the optional ``action_kinds`` attribute); the env demos and the importers write it, training reads it.
* ``windowing``: multi-frequency observation windows and action chunks as frame indices per stride (training), and
  the same windows out of an env's rolling history (evaluation, under jit).
* ``normalizer``: min–max limits to [-1, 1] (per segment for delta actions); images by a fixed uint8 map.
* ``dataset``: normalised, deterministically batched samples of a buffer's episodes.

Public names re-exported here: ``ReplayBuffer``; ``Normalizer``, ``image_to_float``; ``SequenceDataset``,
``split_episodes``; ``sample_indices``, ``history_window_indices``, ``gather_history``, ``obs_offsets``,
``action_offsets``, ``delta_segment_coverage``. Other names come from their module (``replay_buffer.collection_lock``,
``windowing.resolve_chunk_kinds``, ``dataset.train_heldout_datasets``, ...), the importers' from
``hipolicy_jax.data.importers`` and the checks' from ``hipolicy_jax.data.validation``. Within ``hipolicy_jax`` this
package imports only ``config`` and ``jsonio``.
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
