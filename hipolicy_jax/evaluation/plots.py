"""Plots of evaluations and calibrations: per-replan entropy traces, entropy histograms (PNG and text).

Strides are coloured as in videos (``video.stride_color``), so a trace, a histogram and a rollout video of the same
run read alike.
"""

from __future__ import annotations

import os

import numpy as np

from hipolicy_jax.evaluation.video import stride_color


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_entropy_traces(result, thresholds, strides: tuple[int, ...], path: str, *, episodes: int = 4,
                        title: str = "", percentiles=None) -> str:
    """PNG of per-decision entropy over control steps for the first ``episodes`` episodes of an ``EvalResult``:
    each decision from the control step it was taken at to the next, its executed stride as a background band, the
    finite thresholds as dashed lines."""
    from matplotlib.patches import Patch

    plt = _pyplot()
    ent, stride, valid, start = (np.asarray(x) for x in (result.entropy, result.stride, result.valid, result.start))
    success, steps = np.asarray(result.success), np.asarray(result.steps)
    n = max(1, min(episodes, ent.shape[0]))
    fig, axes = plt.subplots(n, 1, figsize=(8, 1.9 * n + 0.8), sharex=True, squeeze=False)
    inner = [(k, t) for k, t in enumerate(thresholds) if np.isfinite(t)]
    finite = ent[valid & np.isfinite(ent)]
    for e, ax in enumerate(axes[:, 0]):
        rs = np.flatnonzero(valid[e])
        begin = start[e, rs]
        end = np.append(begin[1:], steps[e])
        for r, a, b in zip(rs, begin, end):
            color = np.array(stride_color(stride[e, r])) / 255
            ax.axvspan(a, max(b, a + 0.5), color=color, alpha=0.25, lw=0, zorder=0)
        if rs.size and np.isfinite(ent[e, rs]).any():
            x = np.append(begin, end[-1])
            y = np.append(ent[e, rs], ent[e, rs[-1]])
            ax.step(x, y, where="post", color="k", lw=1.2)
            ax.plot(begin, ent[e, rs], "k.", ms=4)
        for k, t in inner:
            label = f"th{k}" + (f" (p{percentiles[k - 1]:g})" if percentiles and 0 < k <= len(percentiles) else "")
            ax.axhline(t, color="gray", ls="--", lw=0.9)
            ax.text(1.0, t, " " + label, transform=ax.get_yaxis_transform(), va="center", fontsize=7, color="gray")
        if finite.size:
            lo, hi = float(finite.min()), float(finite.max())
            for _, t in inner:
                lo, hi = min(lo, t), max(hi, t)
            pad = 0.1 * max(hi - lo, 1e-3)
            ax.set_ylim(lo - pad, hi + pad)
        ax.set_ylabel("entropy")
        ax.set_title(f"episode {e}: {'success' if success[e] else 'failure'} in {int(steps[e])} steps", fontsize=9)
    axes[-1, 0].set_xlabel("control step")
    handles = [Patch(color=np.array(stride_color(s)) / 255, alpha=0.4, label=f"stride {s}") for s in strides]
    fig.legend(handles=handles, loc="lower center", ncol=len(strides), fontsize=8, frameon=False)
    fig.suptitle(title or "action entropy per replan", fontsize=10)
    fig.tight_layout(rect=(0, 0.04, 0.95, 1.0))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def text_histogram(entropies: np.ndarray, thresholds, bins: int = 24, width: int = 40) -> str:
    """Text histogram of entropies, one line per bin, with the bins holding a finite threshold marked."""
    h = np.asarray(entropies, np.float64)
    h = h[np.isfinite(h)]
    if h.size == 0:
        return "(no finite entropies)"
    counts, edges = np.histogram(h, bins=bins)
    top = max(int(counts.max()), 1)
    inner = [(k, float(t)) for k, t in enumerate(thresholds) if np.isfinite(t)]
    lines = []
    for i, c in enumerate(counts):
        lo, hi = edges[i], edges[i + 1]
        marks = [f"th{k}={t:.3f}" for k, t in inner if lo <= t < hi or (i == len(counts) - 1 and t == hi)]
        bar = "#" * int(round(width * c / top))
        lines.append(f"[{lo:8.3f}, {hi:8.3f}) {c:5d} {bar:<{width}} {'<- ' + ', '.join(marks) if marks else ''}")
    q = np.percentile(h, [0, 10, 50, 70, 100])
    lines.append(f"n={h.size}  min {q[0]:.3f}  p10 {q[1]:.3f}  median {q[2]:.3f}  p70 {q[3]:.3f}  max {q[4]:.3f}")
    return "\n".join(line.rstrip() for line in lines)


def plot_histogram(entropies: np.ndarray, thresholds, strides: tuple[int, ...], path: str, *, bins: int = 24,
                   title: str = "") -> str:
    """PNG histogram of the entropies; the entropy ranges selecting each stride shaded, thresholds as lines."""
    plt = _pyplot()
    h = np.asarray(entropies, np.float64)
    h = h[np.isfinite(h)]
    fig, ax = plt.subplots(figsize=(6.5, 3.4))
    if h.size:
        ax.hist(h, bins=bins, color="0.35", zorder=2)
        lo, hi = float(h.min()), float(h.max())
        pad = 0.05 * max(hi - lo, 1e-3)
        lo, hi = lo - pad, hi + pad
        for k, s in enumerate(strides):
            a, b = max(float(thresholds[k]), lo), min(float(thresholds[k + 1]), hi)
            if a < b:
                ax.axvspan(a, b, color=np.array(stride_color(s)) / 255, alpha=0.2, lw=0, zorder=0, label=f"stride {s}")
        for t in thresholds:
            if np.isfinite(t):
                ax.axvline(float(t), color="k", ls="--", lw=1)
        ax.set_xlim(lo, hi)
        ax.legend(fontsize=8)
    ax.set_xlabel("action entropy")
    ax.set_ylabel("count")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
