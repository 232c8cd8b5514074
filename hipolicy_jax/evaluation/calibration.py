"""Entropy thresholds for entropy-guided execution: measurement, percentiles, resolution, the calibration record.

The paper took its thresholds at the 10th and 70th percentiles (M = 3) of the action entropies of held-out data;
the released values (−6.0 / −5.5) are in RoboTwin joint-angle units and do not transfer to other action spaces.
Everything about thresholds lives here, once:

- ``measure_entropies``: action entropies of evenly spaced held-out windows, through one compiled sampler;
- ``default_percentiles`` / ``calibrate_thresholds``: M+1 ascending thresholds (−inf, percentiles…, +inf); a
  single-frequency policy has nothing to select and gets (−inf, +inf);
- ``resolve_thresholds``: explicit thresholds (``InferenceConfig.thresholds``) over the run's calibration;
- ``guidance_thresholds``: the (M+1,) float32 array a rollout traces (without entropy guidance: always stride 1);
- ``intended_mix`` / ``achieved_mix``: the stride mix percentiles aim at, and the one a rollout executed;
- ``percentile_ladder`` / ``choose_success_constrained``: the success-constrained rule: of a ladder of percentiles
  from cautious to aggressive, the most aggressive whose closed-loop success on calibration episodes is within a
  declared margin of the same episodes' success at stride 1 (``runs.calibrate``);
- ``calibration_record`` / ``write_calibration`` / ``read_calibration``: ``calibration.json``.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Callable, Sequence

import jax
import numpy as np

from hipolicy_jax import jsonio
from hipolicy_jax.config import InferenceConfig

CALIBRATION_FILE = "calibration.json"


def default_percentiles(num_freqs: int) -> tuple[float, ...]:
    """The M−1 percentiles used when none are given: (10, 70) for M = 3 as the paper, evenly spaced otherwise."""
    if num_freqs == 3:
        return (10.0, 70.0)
    return tuple(float(x) for x in np.linspace(0, 100, num_freqs + 1)[1:-1])


def effective_percentiles(num_freqs: int, percentiles: Sequence[float] | None) -> tuple[float, ...]:
    """``percentiles`` (or the default) checked to be M−1 ascending values in (0, 100)."""
    p = default_percentiles(num_freqs) if percentiles is None else tuple(float(x) for x in percentiles)
    if len(p) != num_freqs - 1 or any(not 0 < x < 100 for x in p) or any(a >= b for a, b in zip(p, p[1:])):
        raise ValueError(f"inference.percentiles: need M-1={num_freqs - 1} ascending values in (0, 100) for "
                         f"M={num_freqs} strides, got {p}")
    return p


def calibrate_thresholds(entropies: np.ndarray, num_freqs: int,
                         percentiles: Sequence[float] | None = None) -> tuple[float, ...]:
    """M+1 ascending thresholds (−inf, inner percentiles…, +inf) from measured entropies; (−inf, +inf) for M = 1."""
    if num_freqs == 1:
        return (-math.inf, math.inf)
    p = effective_percentiles(num_freqs, percentiles)
    h = np.asarray(entropies, np.float64).ravel()
    h = h[np.isfinite(h)]
    if h.size == 0:
        raise ValueError("calibrate_thresholds: no finite entropies (did you sample with N >= 2?)")
    inner = np.percentile(h, p)
    inner = np.maximum.accumulate(inner + np.arange(len(inner)) * 1e-9)  # strictly ascending even for ties
    return (-math.inf, *(float(x) for x in inner), math.inf)


def intended_mix(percentiles: Sequence[float], strides: Sequence[int]) -> dict[str, float]:
    """The share of decisions per stride that thresholds at ``percentiles`` of an entropy distribution send there,
    when the entropies met are that distribution (the lowest entropies to the highest frequency, stride 1, as
    ``sampling.select_frequency``): {stride: fraction}. (10, 70) and strides (1, 2, 3): {1: 0.1, 2: 0.6, 3: 0.3}."""
    edges = [0.0, *(float(p) / 100 for p in percentiles), 1.0]
    if len(edges) != len(strides) + 1:
        raise ValueError(f"percentiles: need M-1={len(strides) - 1} values for strides {list(strides)}, got "
                         f"{list(percentiles)}")
    return {str(s): round(edges[i + 1] - edges[i], 12) for i, s in enumerate(sorted(strides))}


def achieved_mix(strides: np.ndarray, valid: np.ndarray, all_strides: Sequence[int]) -> dict[str, float]:
    """The share of a rollout's decisions per stride: per-decision ``strides`` (E, R) where ``valid`` → {stride:
    fraction} over ``all_strides`` (0 where none ran)."""
    executed = np.asarray(strides)[np.asarray(valid, bool)]
    n = max(executed.size, 1)
    return {str(s): float(np.sum(executed == s)) / n for s in all_strides}


LADDER_3 = ((90.0, 98.0), (70.0, 95.0), (50.0, 90.0), (30.0, 80.0), (10.0, 70.0), (5.0, 50.0), (2.0, 30.0))


def percentile_ladder(num_freqs: int) -> tuple[tuple[float, ...], ...]:
    """The default candidates of the success-constrained rule, from cautious to aggressive (M−1 percentiles each):
    for M = 3 the share of decisions at stride 1 falls from 90 % to 2 % and at the largest stride grows from 2 % to
    70 % (``LADDER_3``; the paper's (10, 70) is the fifth of seven); for other M, M−1 evenly spaced percentiles below
    90, 70, 50, 30, 10 and 2."""
    if num_freqs < 2:
        return ()
    if num_freqs == 3:
        return LADDER_3
    return tuple(tuple(float(x) for x in np.linspace(q, 99.0, num_freqs)[:-1]) for q in (90, 70, 50, 30, 10, 2))


def choose_success_constrained(candidates: Sequence[dict], baseline_success: float, margin: float) -> int:
    """The success-constrained rule over measured ``candidates`` (cautious to aggressive, each with a
    ``success_rate``): the index of the most aggressive whose success is at least ``baseline_success − margin``;
    0 (the most cautious) when none is. ``margin`` >= 0, in success-rate units (0.05 = 5 points)."""
    if not 0 <= margin <= 1:
        raise ValueError(f"margin: a success-rate difference in [0, 1], got {margin}")
    if not candidates:
        raise ValueError("candidates: the rule needs at least one measured candidate")
    ok = [i for i, c in enumerate(candidates) if c["success_rate"] >= baseline_success - margin - 1e-12]
    return ok[-1] if ok else 0


def evenly_spaced(num_items: int, max_items: int) -> np.ndarray:
    """Up to ``max_items`` evenly spaced indices into ``range(num_items)``."""
    return np.unique(np.linspace(0, num_items - 1, min(max_items, num_items)).astype(np.int64))


def measure_entropies(sampler: Callable, params, normalizer, dataset, key: jax.Array, *, max_windows: int = 128,
                      batch_size: int = 64) -> np.ndarray:
    """Action entropies (S,) of up to ``max_windows`` evenly spaced windows of ``dataset`` (e.g. held-out demos).

    ``sampler``: ``sampling.make_sampler(..., obs_normalized=True)`` with N >= 2 (the dataset's batches come
    normalised); every batch is padded to ``batch_size`` so the sampler compiles once.
    """
    idx = evenly_spaced(len(dataset), max_windows)
    out = []
    for i, start in enumerate(range(0, len(idx), batch_size)):
        chunk = idx[start:start + batch_size]
        chunk = np.concatenate([chunk, np.repeat(chunk[-1:], batch_size - len(chunk))])  # one compiled shape
        res = sampler(params, normalizer, dataset.get_batch(chunk)["obs"], jax.random.fold_in(key, i))
        out.append(np.asarray(res.entropy)[: len(idx) - start])
    return np.concatenate(out)


def inner_to_full(thresholds: Sequence[float], num_freqs: int, field: str) -> tuple[float, ...]:
    """M+1 ascending thresholds from M+1 values or the M−1 inner ones; ValueError naming ``field`` otherwise."""
    th = tuple(float(x) for x in thresholds)
    if len(th) == num_freqs - 1:
        th = (-math.inf, *th, math.inf)
    if len(th) != num_freqs + 1 or any(a >= b for a, b in zip(th, th[1:])):
        raise ValueError(f"{field}: need M+1={num_freqs + 1} (or M-1={num_freqs - 1} inner) ascending values for "
                         f"M={num_freqs} strides, got {list(thresholds)}")
    return th


def resolve_thresholds(inference: InferenceConfig, num_freqs: int,
                       calibration: dict | None) -> tuple[tuple[float, ...], str]:
    """(M+1 thresholds, where they came from): ``inference.thresholds``, the run's calibration record, or
    (−inf, +inf) for a single-frequency policy. Raises ``FileNotFoundError`` when a multi-frequency policy has
    neither."""
    if inference.thresholds is not None:
        return inner_to_full(inference.thresholds, num_freqs, "inference.thresholds"), "inference.thresholds"
    if num_freqs == 1:
        return (-math.inf, math.inf), "single frequency (no thresholds needed)"
    if calibration is None:
        raise FileNotFoundError(f"no {CALIBRATION_FILE}: calibrate the run (python -m experiments.calibrate) or "
                                f"pass --inference.thresholds")
    return inner_to_full(calibration["thresholds"], num_freqs, CALIBRATION_FILE), CALIBRATION_FILE


def guidance_thresholds(thresholds, num_freqs: int, entropy_guided: bool = True) -> np.ndarray:
    """(M+1,) float32 thresholds to trace into a rollout. Without entropy guidance every entropy selects the highest
    frequency: (−inf, +inf, ..., +inf). An array either way keeps one compiled rollout for both evaluations."""
    if not entropy_guided or thresholds is None or num_freqs == 1:
        return np.array([-np.inf] + [np.inf] * num_freqs, np.float32)
    th = np.asarray(thresholds, np.float32)
    if th.shape != (num_freqs + 1,):
        raise ValueError(f"thresholds: need M+1={num_freqs + 1} values for M={num_freqs}, got {th.tolist()}")
    return th


def calibration_record(entropies: np.ndarray, thresholds: Sequence[float], num_freqs: int,
                       inference: InferenceConfig, *, bins: int = 24, **extra) -> dict:
    """The JSON record of one calibration: thresholds, percentiles, the inference settings the entropies were
    measured with, entropy quantiles and histogram, plus ``extra`` (source, seed, step, task, ...)."""
    h = np.asarray(entropies, np.float64).ravel()
    finite = h[np.isfinite(h)]
    record = {"thresholds": [float(t) for t in thresholds],
              "percentiles": list(effective_percentiles(num_freqs, inference.percentiles)) if num_freqs > 1 else [],
              "num_windows": int(h.size), "inference": dataclasses.asdict(inference.sampler_settings()),
              "entropy_quantiles": {str(q): float(np.percentile(finite, q)) for q in (0, 10, 50, 70, 100)}
              if finite.size else {},
              "histogram": dict(zip(("counts", "edges"), (x.tolist() for x in np.histogram(finite, bins=bins))))
              if finite.size else {}}
    record.update(extra)
    return record


def write_calibration(record: dict, path: str) -> str:
    """Write a calibration record (``calibration_record``) to ``path``."""
    return jsonio.dump(record, path)


def read_calibration(run_dir: str) -> dict | None:
    """The run's ``calibration.json`` (None when absent)."""
    path = os.path.join(run_dir, CALIBRATION_FILE)
    if not os.path.exists(path):
        return None
    return jsonio.load(path)
