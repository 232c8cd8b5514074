"""The machine a benchmark ran on, written into every benchmark JSON (``"machine"``).

``machine_info()`` → ``{cpu_model, cpu_count, cpu_affinity, load_average, peaks}``: the CPU model (``/proc/cpuinfo``
"model name", ``lscpu`` where /proc is missing), the logical core count and the cores this process may run on, the
1/5/15-minute load average when the JSON is written (other jobs on a shared machine show up here) and the machine
peaks **measured in the same process** by the ``measure`` it is given (``benchmarks.common.machine_peaks`` for the
JAX benchmarks, when ``write_results`` writes the JSON):

- ``matmul_f32_gflops``: the best GFLOP/s of an n x n float32 matmul (``common.matmul_peak_gflops``; n = 2048 on a
  CPU, 8192 otherwise),
- ``bandwidth_gbs``: the best GB/s of summing a 256 MB float32 array (``common.memory_bandwidth_gbs``).

They take ~2–4 s on a 2-core CPU. ``HIPOLICY_BENCH_PEAKS=0`` skips them (``peaks`` is then None), e.g. for a quick
smoke run. This module does not import JAX, so a script of another framework (the PyTorch peer) records the rest
and measures its own peaks.
"""

from __future__ import annotations

import os
import subprocess
from typing import Any, Callable

PEAKS_ENV = "HIPOLICY_BENCH_PEAKS"


def cpu_model(cpuinfo: str = "/proc/cpuinfo") -> str:
    """The first "model name" of ``cpuinfo`` (``lscpu``'s "Model name" when the file is missing or has none;
    "unknown" when neither says)."""
    text = ""
    if os.path.exists(cpuinfo):
        with open(cpuinfo, errors="replace") as f:
            text = f.read()
    name = _model_name(text)
    if name is None:
        try:
            name = _model_name(subprocess.run(["lscpu"], capture_output=True, text=True, timeout=30).stdout)
        except (OSError, subprocess.SubprocessError):
            name = None
    return name or "unknown"


def _model_name(text: str) -> str | None:
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip().lower() == "model name" and value.strip():
            return value.strip()
    return None


def cpu_affinity() -> int | None:
    """How many cores this process may run on (None where the OS does not say)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None


def load_average() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def machine_info(measure: Callable[[], dict] | None = None) -> dict[str, Any]:
    """The ``machine`` entry of a benchmark JSON; ``measure()`` measures the peaks in this process (JAX benchmarks:
    ``benchmarks.common.machine_peaks``; the PyTorch peer its own). ``peaks`` is None without ``measure`` or when
    ``HIPOLICY_BENCH_PEAKS`` is 0."""
    skip = measure is None or os.environ.get(PEAKS_ENV, "1") == "0"
    return {"cpu_model": cpu_model(), "cpu_count": os.cpu_count(), "cpu_affinity": cpu_affinity(),
            "load_average": load_average(), "peaks": None if skip else measure()}


__all__ = ["PEAKS_ENV", "cpu_affinity", "cpu_model", "load_average", "machine_info"]
