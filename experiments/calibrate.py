"""Calibrate entropy thresholds: ``python -m experiments.calibrate --checkpoint RUN_DIR [--percentiles 10 70]``.

Measures the trained policy's Gaussian action entropy (N samples per window) either on the held-out demos
(``--source demos``: the validation episodes of the run's demo buffer, split as in training from ``meta["data"]``,
``meta["val_ratio"]`` and the training seed) or on its own closed-loop rollouts executed at the highest frequency
(``--source rollouts``: every replan's entropy). The M+1 thresholds are (−inf, the M−1 percentiles, +inf): the
paper took the 10th and 70th percentiles for M = 3 (the default). With the defaults and ``--source demos`` this
reproduces the calibration ``experiments.train`` wrote (same windows, same key).

Writes ``RUN_DIR/calibration.json`` (read by ``experiments.evaluate``; ``--out`` to write elsewhere) and a histogram
PNG next to it (``calibration.png``), and prints a text histogram with the thresholds marked.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Literal

import jax
import numpy as np
import tyro

from experiments.common import (EvalOptions, Run, eval_key, evaluate_policy_recorded, load_run, run_action_dim,
                                write_json)
from hipolicy_jax.data.dataset import SequenceDataset, split_episodes
from hipolicy_jax.data.replay_buffer import ReplayBuffer
from hipolicy_jax.policy import calibrate_thresholds, measure_entropies, policy_obs_keys
from hipolicy_jax.trainer import run_keys


@dataclasses.dataclass(frozen=True)
class CalibrateArgs:
    checkpoint: str  # run dir (holding checkpoints/) or its checkpoints/ dir
    step: int | None = None  # checkpoint step (default: the latest)
    percentiles: tuple[float, ...] | None = None  # M-1 ascending values; default (10, 70) for M=3, else even
    source: Literal["demos", "rollouts"] = "demos"
    num_samples: int = 16  # N for the entropy estimate
    sampler: Literal["ddpm", "ddim"] = "ddim"
    num_steps: int = 10  # denoising steps
    calib_windows: int = 128  # demos: evenly spaced held-out windows
    episodes: int = 20  # rollouts: episodes
    seed: int | None = None  # default: the run's training seed
    out: str = ""  # default RUN_DIR/calibration.json (the histogram goes next to it as .png)
    bins: int = 24

    def options(self) -> EvalOptions:
        return EvalOptions(episodes=self.episodes, num_samples=self.num_samples, sampler=self.sampler,
                           num_steps=self.num_steps, every=0, entropy_guided=False,
                           calib_windows=self.calib_windows)


def held_out_dataset(run: Run) -> SequenceDataset:
    """The run's held-out demo windows: the episode split of training, the checkpoint's normaliser."""
    meta, cfg = run.policy.meta, run.policy.cfg
    if not os.path.exists(meta.get("data", "")):
        raise FileNotFoundError(f"the run's demo buffer {meta.get('data')!r} (meta['data']) is missing; "
                                f"use --source rollouts or re-collect it with experiments.collect")
    buffer = ReplayBuffer.load(meta["data"])
    _, val_mask = split_episodes(buffer.num_episodes, float(meta["val_ratio"]), int(meta["train"]["seed"]))
    return SequenceDataset(buffer, cfg.chunk, obs_keys=policy_obs_keys(cfg.encoder), episode_mask=val_mask,
                           normalizer=run.policy.normalizer)


def demo_entropies(run: Run, opts: EvalOptions, key) -> np.ndarray:
    """Action entropies of up to ``opts.calib_windows`` evenly spaced held-out demo windows."""
    p = run.policy
    return measure_entropies(p.net, p.params, p.normalizer, p.cfg, run_action_dim(run), held_out_dataset(run), key,
                             max_windows=opts.calib_windows, num_samples=opts.num_samples, num_steps=opts.num_steps,
                             sampler=opts.sampler)


def rollout_entropies(run: Run, opts: EvalOptions, key) -> np.ndarray:
    """Entropies of every replan of ``opts.episodes`` closed-loop episodes executed at the highest frequency."""
    p = run.policy
    result, _ = evaluate_policy_recorded(p.net, p.params, p.normalizer, p.cfg, run_action_dim(run), run.task,
                                         dataclasses.replace(opts, entropy_guided=False), key)
    return np.asarray(result.entropy)[np.asarray(result.valid)]


def effective_percentiles(num_freqs: int, percentiles: tuple[float, ...] | None) -> tuple[float, ...]:
    """The M-1 percentiles ``policy.calibrate_thresholds`` uses for ``percentiles`` (None: its default)."""
    if percentiles is not None:
        return tuple(float(x) for x in percentiles)
    if num_freqs == 3:
        return (10.0, 70.0)
    return tuple(float(x) for x in np.linspace(0, 100, num_freqs + 1)[1:-1])


def thresholds_for(entropies: np.ndarray, num_freqs: int, percentiles: tuple[float, ...]) -> tuple[float, ...]:
    """M+1 thresholds; a single-frequency policy has nothing to select: (-inf, +inf)."""
    if num_freqs == 1:
        return (-np.inf, np.inf)
    return calibrate_thresholds(entropies, num_freqs, percentiles)


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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hipolicy_jax.envs.video import stride_color

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


def main(args: CalibrateArgs) -> dict:
    run = load_run(args.checkpoint, args.step)
    cfg = run.policy.cfg
    m = cfg.chunk.num_freqs
    pct = effective_percentiles(m, args.percentiles) if m > 1 else ()
    if len(pct) != m - 1:
        raise ValueError(f"percentiles: need M-1={m - 1} values for M={m} strides {cfg.chunk.strides}, got {pct}")
    seed = int(run.policy.meta["train"]["seed"]) if args.seed is None else args.seed
    opts = args.options()
    if args.source == "demos":
        entropies = demo_entropies(run, opts, run_keys(seed)["eval"])  # train's calibration key
    else:
        # episodes disjoint from those experiments.evaluate scores (eval_key(seed))
        entropies = rollout_entropies(run, opts, jax.random.fold_in(eval_key(seed), 1))
    thresholds = thresholds_for(entropies, m, pct)
    path = args.out or os.path.join(run.run_dir, "calibration.json")
    plot = plot_histogram(entropies, thresholds, cfg.chunk.strides, os.path.splitext(path)[0] + ".png",
                          bins=args.bins, title=f"{run.task} @ step {run.policy.step}: entropies of {args.source} "
                          f"(N={args.num_samples}), thresholds at percentiles {list(pct)}")
    finite = entropies[np.isfinite(entropies)]
    record = {"thresholds": list(thresholds), "percentiles": list(pct), "num_windows": int(entropies.size),
              "num_samples": args.num_samples, "sampler": args.sampler, "num_steps": args.num_steps,
              "entropy_quantiles": {str(q): float(np.percentile(finite, q)) for q in (0, 10, 50, 70, 100)}
              if finite.size else {},
              "source": args.source, "seed": seed, "checkpoint_step": run.policy.step, "task": run.task,
              "histogram": dict(zip(("counts", "edges"), (x.tolist() for x in np.histogram(finite, bins=args.bins))))
              if finite.size else {}, "plot": plot}
    write_json(path, record)
    print(f"{run.task} @ step {run.policy.step}: {entropies.size} entropies from {args.source} "
          f"(N={args.num_samples}, {args.sampler} {args.num_steps} steps)")
    print(text_histogram(entropies, thresholds, args.bins))
    print(f"thresholds {[round(float(t), 4) for t in thresholds]} (percentiles {list(pct)}) -> {path}, {plot}")
    return record


if __name__ == "__main__":
    main(tyro.cli(CalibrateArgs, description=__doc__))
