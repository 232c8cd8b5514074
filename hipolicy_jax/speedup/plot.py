"""One demo's DemoSpeedup entropy over time, its segments shaded by label with their rates, its kept frames marked."""

from __future__ import annotations

import os

import numpy as np

from hipolicy_jax.speedup.retime import PRECISE

_COLORS = {PRECISE: "tab:blue", 1: "tab:orange"}
_NAMES = {PRECISE: "precise", 1: "casual"}


def plot_episode(entropy: np.ndarray, segments, kept: np.ndarray, path: str, *, title: str = "") -> str:
    """Write a PNG at ``path``: ``entropy`` ``(T,)`` of one demo against its frame index, each of its ``segments``
    ``[(start, end, label, rate), ...]`` shaded (blue precise, orange casual) and labelled ``xrate``, and the ``kept``
    ``(K,)`` frames marked on the curve. Returns ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = np.asarray(entropy, np.float64)
    kept = np.asarray(kept, np.int64)
    fig, ax = plt.subplots(figsize=(10, 3.6))
    top = float(np.max(h)) if h.size else 1.0
    seen = set()
    for start, end, label, rate in segments:
        name = None if label in seen else f"{_NAMES.get(label, label)} segment"
        seen.add(label)
        ax.axvspan(start - 0.5, end - 0.5, color=_COLORS.get(label, "grey"), alpha=0.18, lw=0, label=name)
        ax.text((start + end - 1) / 2, top, f"x{rate}", ha="center", va="bottom", fontsize=8)
    ax.plot(np.arange(h.size), h, color="black", lw=1.2, label="entropy (proxy, N samples)")
    ax.plot(kept, h[kept], "o", ms=3.5, color="tab:red", label=f"kept frames ({kept.size} of {h.size})")
    ax.set_xlabel("demo frame")
    ax.set_ylabel("first-action entropy (KDE)")
    ax.set_title(title or f"DemoSpeedup: {h.size} -> {kept.size} frames")
    ax.legend(loc="lower right", fontsize=8)
    ax.margins(x=0.01, y=0.12)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
