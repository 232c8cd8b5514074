"""A LeRobot episode's frames: videos decoded at the parquet timestamps, image columns decoded, columns checked
against the ``features`` of ``meta/info.json``. PyAV (videos) is optional (``pip install 'hipolicy_jax[import]'``).
"""

from __future__ import annotations

import os

import numpy as np

from hipolicy_jax.data.importers.assemble import _optional_import
from hipolicy_jax.data.validation import DataValidationError, describe


def _decode_video(path: str, timestamps: np.ndarray, fps: float, where: str, start: float = 0.0) -> np.ndarray:
    """Frames of ``path`` at ``start + timestamps`` seconds (nearest frame, within half a frame period)
    -> ``(n, H, W, 3) uint8``.

    ``start`` is the episode's first frame in a video that holds several episodes (v3.0 ``from_timestamp``): the
    decoder seeks to the key frame before it and decodes only the episode's span.
    """
    av = _optional_import("av", "decoding LeRobot videos")
    if not os.path.isfile(path):
        raise DataValidationError(f"{where}: missing video file {path}")
    tolerance = 0.5 / fps
    wanted = start + np.asarray(timestamps, np.float64)
    lo, hi = float(wanted.min()) - tolerance, float(wanted.max()) + tolerance
    decoded = []
    try:
        with av.open(path) as container:
            stream = container.streams.video[0]
            seek = lo > 0 and stream.time_base is not None
            if seek:
                container.seek(int(lo / stream.time_base), stream=stream, backward=True, any_frame=False)
            for i, fr in enumerate(container.decode(stream)):
                if fr.time is None and seek:
                    raise DataValidationError(f"{path}: frame {i} after seeking to {lo:.4f}s has no timestamp; "
                                              f"expected timed frames")
                t = float(fr.time) if fr.time is not None else i / fps
                if t > hi:
                    break
                if t >= lo:
                    decoded.append((t, fr.to_ndarray(format="rgb24")))
    except av.error.FFmpegError as e:
        raise DataValidationError(f"{path}: cannot decode video ({e})") from e
    if not decoded:
        raise DataValidationError(f"{path}: no video frames at {lo + tolerance:.4f}s-{hi - tolerance:.4f}s; expected "
                                  f"{len(timestamps)} frames for {where}")
    times = np.asarray([t for t, _ in decoded])
    nearest = np.abs(times[None, :] - wanted[:, None]).argmin(axis=1)
    error = np.abs(times[nearest] - wanted)
    if (error > tolerance).any():
        i = int(np.argmax(error > tolerance))
        in_file = f" (+ from_timestamp {start:.4f}s = {wanted[i]:.4f}s in the file)" if start else ""
        raise DataValidationError(f"{path}: no video frame within {tolerance:.4f}s of frame {i}'s timestamp "
                                  f"{timestamps[i]:.4f}s{in_file} (nearest {times[nearest[i]]:.4f}s; decoded "
                                  f"{len(times)} frames at {times[0]:.4f}s-{times[-1]:.4f}s) for {where}")
    return np.stack([decoded[j][1] for j in nearest])


def _decode_images(column, where: str) -> np.ndarray:
    """A LeRobot ``image`` column (structs with encoded ``bytes``) -> ``(n, H, W, C)``."""
    import imageio.v3 as iio

    frames = []
    for i, item in enumerate(column.to_pylist()):
        data = item.get("bytes") if isinstance(item, dict) else None
        if not data:
            raise DataValidationError(f"{where}: frame {i} has no encoded image bytes; expected a struct "
                                      f"{{'bytes': <png/jpeg>, 'path': ...}}")
        img = np.asarray(iio.imread(data))
        img = img[..., None] if img.ndim == 2 else img
        if frames and img.shape != frames[0].shape:
            raise DataValidationError(f"{where}: frame {i} decodes to {describe(img)}, expected "
                                      f"{describe(frames[0])} as frame 0")
        frames.append(img)
    return np.stack(frames)


def _check_feature(arr: np.ndarray, feature: dict, where: str) -> np.ndarray:
    """Match a column to its ``meta/info.json`` feature: declared dtype and per-frame shape ([1] -> (n, 1))."""
    shape = tuple(int(d) for d in feature.get("shape", arr.shape[1:]))
    if arr.ndim == 1 and shape == (1,):
        arr = arr[:, None]
    if tuple(arr.shape[1:]) != shape:
        raise DataValidationError(f"{where}: frames of shape {tuple(arr.shape[1:])}, expected {shape} as declared in "
                                  f"meta/info.json")
    dtype = feature.get("dtype")
    if dtype in (None, "video", "image", "string"):
        return arr
    try:
        declared = np.dtype(dtype)
    except TypeError as e:
        raise DataValidationError(f"{where}: meta/info.json declares dtype {dtype!r}, not a numeric dtype") from e
    if declared != arr.dtype:
        raise DataValidationError(f"{where}: dtype {arr.dtype}, expected {dtype} as declared in meta/info.json")
    return arr


def _check_image_shape(frames: np.ndarray, feature: dict, where: str) -> None:
    """Decoded frames ``(n, H, W, C)`` against the declared shape, ``[H, W, C]`` or ``[C, H, W]``."""
    shape = tuple(int(d) for d in feature.get("shape", ()))
    got = tuple(frames.shape[1:])
    if shape and got != shape and (len(shape) != 3 or got != (shape[1], shape[2], shape[0])):
        raise DataValidationError(f"{where}: decoded frames of shape {got}, expected {shape} as declared in "
                                  f"meta/info.json")
