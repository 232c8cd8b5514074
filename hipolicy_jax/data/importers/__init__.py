"""Data stage, the flow's entry: other projects' demo formats read into our replay-buffer layout (``ReplayBuffer``).

    importers -> replay_buffer -> windowing -> normalizer -> dataset   (``hipolicy_jax.data``)

Each importer reads its source episode by episode, maps the source's keys to the project's (``keymap``), validates
(``hipolicy_jax.data.validation``), converts images, settles the action kinds and concatenates (``assemble``), giving
``(ReplayBuffer, ImportSummary)``; ``experiments.import_data`` writes the buffer, which training reads like any other.

Formats, one module each (the module's docstring gives its layout, default key map and action kinds):

* ``dp-zarr`` (``dp_zarr.import_dp_zarr``): a Diffusion Policy zarr ReplayBuffer (directory, zarr 2 or 3, ``.zip``).
* ``robomimic`` (``robomimic.import_robomimic``): a robomimic hdf5 file.
* ``lerobot`` (``lerobot.import_lerobot``): a local LeRobot dataset folder, v2.x or v3.0 (layouts in
  ``lerobot_layout``, video and image decoding in ``lerobot_frames``).

Public names:

* registry: ``FORMATS`` (the format names), ``IMPORTERS`` (format -> importer), ``import_dataset(fmt, src, ...)``;
* importers: ``import_dp_zarr``, ``import_robomimic``, ``import_lerobot``, each
  ``(src, key_map=None, min_length=1, action_kinds=None) -> (ReplayBuffer, ImportSummary)``;
* key maps: ``KeyMap``, ``parse_key_map``, ``format_key_map``, ``is_image_key``;
* records: ``ImportSummary`` (kept and dropped episodes, keys, notes, action kinds), ``EpisodeRecord``,
  ``EpisodeLoader``;
* robomimic helpers: ``robomimic_demo_names``, ``robomimic_action_kinds``.

Key maps are ``{project_key: (source_key, ...)}``; several source keys are concatenated along the last axis
(``state=robot0_eef_pos,robot0_gripper_qpos``). An explicit key map imports exactly its keys, plus ``action`` from
the format's default action source when it does not name ``action``. Images (keys ``image`` or ``image_*``) are
converted to ``(T, H, W, 3) uint8``: floats in [0, 1] are scaled by 255, floats in [0, 255] rounded (the scale is
decided by the first episode and then required of all), and the conversion is recorded in the summary.

Action kinds (``ChunkConfig.action_kinds``: per action dimension ``'absolute'`` or ``'delta'``): every importer
takes ``action_kinds=`` (``--action-kinds`` of ``experiments.import_data``; one kind for every dimension, or one per
dimension) and reads them from the source where it says so: a zarr root attribute ``action_kinds`` (this project's
and the Meta-World bridge's buffers), or robomimic's robosuite controller (``data`` attribute ``env_args``:
``env_kwargs.controller_configs.control_delta``; true: every dimension a delta but the last, the gripper, absolute;
false: all absolute) when the action is the default ``actions``. A flag that disagrees with the source is an error.
The buffer records the kinds (root attribute ``action_kinds``); when neither says, it records none and the
summary notes it: training then takes its task's kinds, and refuses when there is no task to say and a stride
above 1 needs them (``data.windowing.resolve_chunk_kinds``).

Nothing is dropped silently. Empty episodes, and episodes shorter than ``min_length`` frames when a caller asks for
one (default 1: every episode is kept, since training pads episode edges as Diffusion Policy's sampler does), are
dropped and listed with their reason in the ``ImportSummary``; every other
problem (missing key, wrong rank, obs/action length mismatch, NaN / Inf, decreasing ``episode_ends``, frames out of
order, a dtype or shape that disagrees with the metadata) raises ``DataValidationError`` naming the file, the key
and expected vs actual. Source keys that are not imported are listed in the summary's notes.

h5py (robomimic), pyarrow (LeRobot) and PyAV (LeRobot videos) are optional: ``pip install 'hipolicy_jax[import]'``.

A new format: one module here with ``import_<format>(src, key_map=None, min_length=1, action_kinds=None)`` that
hands its episodes to ``assemble._assemble`` (``dp_zarr`` is the shortest example), and one line in ``IMPORTERS``
below (``FORMATS``, and so ``experiments.import_data``'s choices, follow from it).
"""

from __future__ import annotations

import os
from collections.abc import Sequence

from hipolicy_jax.data.importers.assemble import EpisodeLoader, EpisodeRecord, ImportSummary
from hipolicy_jax.data.importers.dp_zarr import import_dp_zarr
from hipolicy_jax.data.importers.keymap import KeyMap, format_key_map, is_image_key, parse_key_map
from hipolicy_jax.data.importers.lerobot import import_lerobot
from hipolicy_jax.data.importers.robomimic import import_robomimic, robomimic_action_kinds, robomimic_demo_names
from hipolicy_jax.data.replay_buffer import ReplayBuffer

IMPORTERS = {"dp-zarr": import_dp_zarr, "robomimic": import_robomimic, "lerobot": import_lerobot}
FORMATS = tuple(IMPORTERS)


def import_dataset(fmt: str, src: str | os.PathLike, key_map: KeyMap | None = None,
                   min_length: int = 1, action_kinds: Sequence[str] | None = None
                   ) -> tuple[ReplayBuffer, ImportSummary]:
    """Import ``src`` in format ``fmt`` (one of ``FORMATS``) -> ``(buffer, summary)``; ``action_kinds``: the actions'
    kinds where the source does not say (package docstring)."""
    if fmt not in IMPORTERS:
        raise ValueError(f"format: expected one of {list(FORMATS)}, got {fmt!r}")
    return IMPORTERS[fmt](src, key_map=key_map, min_length=min_length, action_kinds=action_kinds)


__all__ = [
    "FORMATS",
    "IMPORTERS",
    "import_dataset",
    "import_dp_zarr",
    "import_robomimic",
    "import_lerobot",
    "KeyMap",
    "parse_key_map",
    "format_key_map",
    "is_image_key",
    "ImportSummary",
    "EpisodeRecord",
    "EpisodeLoader",
    "robomimic_demo_names",
    "robomimic_action_kinds",
]
