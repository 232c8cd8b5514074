"""Keep freed host memory for reuse: glibc's allocator tuned so that XLA:CPU's large buffers stop page-faulting.

XLA:CPU allocates every large buffer of a step (activations, gradients, outputs) with ``malloc`` and frees it when
the step ends. glibc serves an allocation above 32 MB with a fresh ``mmap`` and returns it with ``munmap``, so the
next step touches brand-new pages: one page fault per 4 KB. A point-cloud train step (64 windows × 6 frames × 512
points × 256 channels = 201 MB per activation) then spends most of its time in the kernel: an element-wise pass over
one such array took 60 ms, 49,153 page faults, instead of 6 ms (``benchmarks.roofline``, PERFORMANCE.md).

``keep_freed_memory()`` tells glibc (``mallopt``) to serve every allocation from one arena's heap (``M_ARENA_MAX``
1, ``M_MMAP_MAX`` 0) and never to give freed memory back (``M_TRIM_THRESHOLD`` the largest value): once the heap
has grown to a step's size (two steps), a step reuses the pages of the one before. The numbers a program computes
do not change; its resident memory stays at its peak. Call it
before the first JAX computation (the arena limit only binds threads that have not allocated yet); every entry
point does (``runs.cli.prepare_process``). ``HIPOLICY_KEEP_FREED_MEMORY=0`` turns it off. Elsewhere than glibc
(macOS, musl) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

ENV = "HIPOLICY_KEEP_FREED_MEMORY"
M_TRIM_THRESHOLD, M_MMAP_MAX, M_ARENA_MAX = -1, -4, -8  # glibc's malloc.h
GLIBC_DEFAULTS = {M_MMAP_MAX: 65536, M_TRIM_THRESHOLD: 128 * 1024}  # mallopt(3)
KEEP = {M_MMAP_MAX: 0, M_TRIM_THRESHOLD: -1}  # -1: as size_t the largest value, so never trim


def _glibc():
    """glibc's ``libc`` (None elsewhere)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.gnu_get_libc_version  # noqa: B018 -- only glibc has it
    except (OSError, AttributeError):
        return None
    libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return libc


def keep_freed_memory(enable: bool | None = None) -> bool:
    """Tune glibc to keep freed memory (``enable=True``; None: unless ``HIPOLICY_KEEP_FREED_MEMORY=0``) or put
    back its defaults for large allocations (``enable=False``; the one-arena limit stays). → whether glibc took
    the settings (False without glibc or when turned off)."""
    if enable is None:
        enable = os.environ.get(ENV, "1") != "0"
    libc = _glibc()
    if libc is None:
        return False
    if not enable:
        for k, v in GLIBC_DEFAULTS.items():
            libc.mallopt(k, v)
        return False
    results = [libc.mallopt(M_ARENA_MAX, 1)] + [libc.mallopt(k, v) for k, v in KEEP.items()]
    return all(r == 1 for r in results)


__all__ = ["ENV", "keep_freed_memory"]
