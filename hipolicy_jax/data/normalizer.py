"""Min–max ("limits") normalisation as in Diffusion Policy's ``LinearNormalizer``.

Per feature (the last axis) the fitted range [min, max] maps affinely onto [-1, 1]: ``y = x * scale + offset``.
A feature whose range is below ``range_eps`` (1e-4) is constant in the data; Diffusion Policy then uses scale 1 and
offset ``-min``, so it maps to 0 and unnormalises back to ``min`` exactly, with no division by a tiny range.
Point clouds ``(..., P, C)`` are fitted per coordinate channel C over all frames and points.

Images are not fitted: ``image_to_float`` maps uint8 [0, 255] to float32 [-1, 1] by a fixed map.

Per-segment statistics (delta actions, ``ChunkConfig.action_kinds``): a stride-s segment of summed deltas spans
about s times the range of a stride-1 one, so one range for every segment would squeeze the short strides into a
fraction of [-1, 1]. ``fit(..., segment_len={"action": L_c})`` fits the action's range per segment of the
``(S, M*L_c, A)`` chunks and stores it per chunk position, stats ``(M*L_c, A)`` (each segment's row repeated L_c
times). ``normalize`` / ``unnormalize`` are the one place actions are (un)normalised (dataset, sampler, calibration,
server): with per-position stats they require ``(..., M*L_c, A)`` and apply each position's segment range; with
per-feature stats ``(A,)`` (every all-absolute policy, and every normaliser saved before per-segment stats existed)
they are what they always were, bit for bit.

``Normalizer`` is a ``flax.struct`` pytree, so it passes through jit and is saved with a checkpoint (orbax);
``to_dict`` / ``from_dict`` give the plain-numpy form.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import jax
import numpy as np
from flax import struct

Array = np.ndarray | jax.Array
STAT_NAMES = ("scale", "offset", "min", "max")


def image_to_float(image: Array) -> Array:
    """uint8 images ``(..., H, W, 3)`` in [0, 255] -> float32 in [-1, 1] (0 -> -1, 255 -> +1)."""
    return image.astype(np.float32) * np.float32(2.0 / 255.0) - np.float32(1.0)


def _fit_segment_limits(x: np.ndarray, segment_len: int, range_eps: float) -> dict[str, np.ndarray]:
    """``{scale, offset, min, max}`` float32 ``(H, C)`` for chunks ``x`` ``(S, H, C)``: segment m (positions
    ``m*segment_len .. (m+1)*segment_len - 1``) fitted over every sample and position in it, per feature."""
    if x.ndim != 3 or x.shape[1] % segment_len:
        raise ValueError(f"Normalizer.fit: per-segment statistics need chunks (S, M*L_c, C) with M*L_c divisible by "
                         f"segment_len={segment_len}, got shape {x.shape}")
    segments = x.reshape(x.shape[0], x.shape[1] // segment_len, segment_len, x.shape[2]).swapaxes(0, 1)
    fitted = [_fit_limits(seg, range_eps) for seg in segments]  # M × {name: (C,)}
    return {name: np.repeat(np.stack([f[name] for f in fitted]), segment_len, axis=0) for name in STAT_NAMES}


def _fit_limits(x: np.ndarray, range_eps: float) -> dict[str, np.ndarray]:
    """``{scale, offset, min, max}`` float32 ``(C,)`` for ``x`` ``(..., C)`` so that [min, max] -> [-1, 1]."""
    flat = np.asarray(x, dtype=np.float64).reshape(-1, x.shape[-1])
    x_min, x_max = flat.min(axis=0), flat.max(axis=0)
    x_range = x_max - x_min
    constant = x_range < range_eps
    scale = np.where(constant, 1.0, 2.0 / np.where(constant, 1.0, x_range))
    offset = np.where(constant, -x_min, -1.0 - scale * x_min)
    return {name: v.astype(np.float32) for name, v in zip(STAT_NAMES, (scale, offset, x_min, x_max))}


@struct.dataclass
class Normalizer:
    """Per-key affine normalisation; ``stats[key]`` holds float32 ``(C,)`` arrays ``scale, offset, min, max``."""

    stats: dict[str, dict[str, Array]]

    @classmethod
    def fit(cls, arrays: Mapping[str, np.ndarray], keys: Sequence[str] | None = None,
            range_eps: float = 1e-4, segment_len: Mapping[str, int] | None = None) -> Normalizer:
        """Fit [min, max] -> [-1, 1] per last-axis feature.

        Args:
          arrays: ``{key: (..., C)}`` data, e.g. ``state`` (T, D), ``action`` (T, A), ``point_cloud`` (T, P, C).
          keys: which keys to fit; default every key that is not a uint8 image.
          range_eps: features with max - min below this are treated as constant (mapped to 0).
          segment_len: ``{key: L_c}``: fit that key per segment instead: its array is chunks ``(S, M*L_c, C)``
            and its stats ``(M*L_c, C)`` (module docstring); other keys as above.
        """
        keys = [k for k, v in arrays.items() if np.asarray(v).dtype != np.uint8] if keys is None else list(keys)
        stats = {}
        for key in keys:
            if key not in arrays:
                raise ValueError(f"Normalizer.fit: key {key!r} not in arrays, available keys {sorted(arrays)}")
            x = np.asarray(arrays[key])
            if x.dtype == np.uint8:
                raise ValueError(f"Normalizer.fit: key {key!r} is uint8 (an image); images are not fitted, "
                                 f"use image_to_float")
            if x.ndim < 1 or x.size == 0:
                raise ValueError(f"Normalizer.fit: key {key!r} expected a non-empty (..., C) array, "
                                 f"got shape {x.shape}")
            if segment_len and key in segment_len:
                stats[key] = _fit_segment_limits(x, int(segment_len[key]), range_eps)
            else:
                stats[key] = _fit_limits(x, range_eps)
        return cls(stats=stats)

    def _stats(self, key: str, x: Array) -> dict[str, Array]:
        if key not in self.stats:
            raise KeyError(f"Normalizer has no statistics for key {key!r}; fitted keys {sorted(self.stats)}")
        s = self.stats[key]
        shape = tuple(s["scale"].shape)
        if len(shape) > 1 and tuple(x.shape[-len(shape):]) != shape:
            raise ValueError(f"Normalizer: {key!r} has per-segment statistics for chunks (..., M*L_c, A) = "
                             f"(..., {', '.join(map(str, shape))}), got shape {tuple(x.shape)}")
        return s

    def per_segment(self, key: str) -> bool:
        """Whether ``key`` has per-segment statistics ``(M*L_c, C)`` (delta actions), not per-feature ``(C,)``."""
        return key in self.stats and np.ndim(self.stats[key]["scale"]) > 1

    def normalize(self, key: str, x: Array) -> Array:
        """``x`` ``(..., C)`` in data units -> normalised, same shape, float32 (numpy stays numpy, jax stays jax).
        With per-segment statistics ``(M*L_c, C)``, ``x`` must be chunks ``(..., M*L_c, C)``."""
        s = self._stats(key, x)
        return x.astype(s["scale"].dtype) * s["scale"] + s["offset"]

    def unnormalize(self, key: str, x: Array) -> Array:
        """Inverse of ``normalize``: ``(..., C)`` (or chunks ``(..., M*L_c, C)``) normalised -> data units."""
        s = self._stats(key, x)
        return (x.astype(s["scale"].dtype) - s["offset"]) / s["scale"]

    def normalize_obs(self, obs: Mapping[str, Array]) -> dict[str, Array]:
        """Normalise every observation: fitted keys affinely, uint8 images by ``image_to_float``."""
        out = {}
        for key, x in obs.items():
            if key in self.stats:
                out[key] = self.normalize(key, x)
            elif x.dtype == np.uint8:
                out[key] = image_to_float(x)
            else:
                raise KeyError(f"Normalizer has no statistics for observation key {key!r} (dtype {x.dtype}) and it "
                               f"is not a uint8 image; fitted keys {sorted(self.stats)}")
        return out

    def to_dict(self) -> dict[str, dict[str, np.ndarray]]:
        """Plain numpy copy ``{key: {scale, offset, min, max}}``."""
        return {key: {name: np.asarray(s[name]) for name in STAT_NAMES} for key, s in self.stats.items()}

    @classmethod
    def from_dict(cls, stats: Mapping[str, Mapping[str, np.ndarray]]) -> Normalizer:
        """Rebuild from ``to_dict``'s form; every key needs ``scale, offset, min, max`` of one shape (``(C,)``, or
        ``(M*L_c, C)`` per segment)."""
        out = {}
        for key, s in stats.items():
            missing = [name for name in STAT_NAMES if name not in s]
            if missing:
                raise ValueError(f"Normalizer.from_dict: key {key!r} is missing {missing}, expected {list(STAT_NAMES)}")
            arrays = {name: np.asarray(s[name], dtype=np.float32) for name in STAT_NAMES}
            shapes = {name: a.shape for name, a in arrays.items()}
            if len(set(shapes.values())) != 1:
                raise ValueError(f"Normalizer.from_dict: key {key!r} expected stats of one shape, (C,) or "
                                 f"(M*L_c, C), got {shapes}")
            out[key] = arrays
        return cls(stats=out)
