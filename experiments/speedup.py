"""Accelerate demonstrations with DemoSpeedup (arXiv 2506.05064): a proxy policy's per-frame action entropy decides
which parts of each demo are sped up, and by how much.

    python -m experiments.speedup --data data/press_button_state_100.zarr --proxy runs/press_button_dp_seed0 \\
        --out data/press_button_state_100_speedup.zarr
    python -m experiments.speedup --data SRC.zarr --proxy RUN_DIR --out DST.zarr --speedup.casual-prefix 10

Samples ``--speedup.num-samples`` chunks from the proxy at every demo frame (its ``inference.json`` sampler), labels
every frame precise or casual from the kernel-density entropy of the first action, keeps every
``--speedup.precise-rate``-th frame of precise segments and every ``--speedup.casual-rate``-th of casual ones, and
writes the accelerated buffer at ``--out`` (same zarr layout, the source's attributes and a ``speedup`` record).
Prints the accelerated length beside the original's and writes a plot of one demo's entropy with its segments and
rates (``--plot``, default ``<out>_entropy.png``). A proxy trained on another task, action size or observations, or
a missing ``--data``, is refused in one line.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import tyro
import zarr
from tqdm import tqdm

from hipolicy_jax.runs.cli import prepare_process
from hipolicy_jax.speedup.config import SpeedupConfig
from hipolicy_jax.speedup.plot import plot_episode
from hipolicy_jax.speedup.stage import SpeedupResult, load_demos, speedup_demos


@dataclasses.dataclass(frozen=True)
class SpeedupArgs:
    data: str  # the demo buffer to accelerate (zarr)
    proxy: str  # the proxy policy: a run dir (holding checkpoints/) or its checkpoints/ dir
    out: str  # where to write the accelerated buffer (zarr)
    speedup: SpeedupConfig = SpeedupConfig()  # DemoSpeedup's estimator, segmentation and rates
    plot: str = ""  # the entropy plot (default: <out without .zarr>_entropy.png)
    episode: int = 0  # the demo the plot shows
    step: int | None = None  # the proxy's checkpoint step (default: the latest)
    seed: int = 0  # the sampler's PRNG key
    batch_size: int = 64  # frames per sampler call
    overwrite: bool = False  # replace an existing --out
    progress: bool = True


def default_plot_path(out: str) -> str:
    """``<out without .zarr>_entropy.png``, next to the output buffer."""
    stem = out[:-len(".zarr")] if out.endswith(".zarr") else out
    return f"{os.path.normpath(stem)}_entropy.png"


def summary_lines(result: SpeedupResult) -> list[str]:
    """The original and the accelerated length: frames, episodes, per-episode mean, and the ratio."""
    src, acc = result.source, result.accelerated
    lines = []
    for name, buf in (("original", src), ("accelerated", acc)):
        lengths = buf.episode_lengths()
        lines.append(f"{name:>11}: {buf.num_frames:6d} frames, {buf.num_episodes} episodes, "
                     f"{float(np.mean(lengths)):.1f} frames per episode (min {int(lengths.min())}, "
                     f"max {int(lengths.max())})")
    lines.append(f"{'speed-up':>11}: x{src.num_frames / acc.num_frames:.2f} fewer frames")
    h, rec = result.entropy, result.record
    n, bandwidth = rec["config"]["num_samples"], rec.get("bandwidth", rec["config"]["bandwidth"])
    lines.append(f"{'entropy':>11}: median {float(np.median(h)):.3f} (10-90%: {float(np.percentile(h, 10)):.3f}-"
                 f"{float(np.percentile(h, 90)):.3f}; ceiling log N = {np.log(n):.3f}, "
                 f"{100 * rec['saturated_fraction']:.0f}% of frames at it)")
    if rec["saturated_fraction"] > 0.5:
        lines.append(f"warning: {100 * rec['saturated_fraction']:.0f}% of frames sit at the ceiling log N: the proxy's "
                     f"samples are spread far wider than the bandwidth {bandwidth:g}, so the segmentation has "
                     f"little to read; consider a larger --speedup.bandwidth or a --speedup.bandwidth-ladder")
    return lines


def _episode_ends(path: str) -> np.ndarray | None:
    """The buffer's ``meta/episode_ends`` alone (the bar's total, the plotted episode's check; None when it does not
    read); a missing buffer is refused here in one line."""
    if not os.path.exists(path):
        load_demos(path)  # raises its one-line FileNotFoundError
    try:
        return np.asarray(zarr.open_group(path, mode="r")["meta"]["episode_ends"][...])
    except Exception:  # a damaged buffer: ReplayBuffer.load names the damage when the stage reads it
        return None


def main(args: SpeedupArgs) -> SpeedupResult:
    """Run the stage, print the lengths, write the plot; returns the stage's result."""
    ends = _episode_ends(args.data)
    if args.episode < 0 or (ends is not None and args.episode >= ends.size):
        raise ValueError(f"--episode: the demo to plot, in [0, {'E' if ends is None else ends.size}), "
                         f"got {args.episode}")
    with tqdm(total=None if ends is None else int(ends[-1]), desc="proxy entropy", unit="frame", disable=not args.progress) as bar:
        result = speedup_demos(args.data, args.proxy, args.out, args.speedup, seed=args.seed, step=args.step,
                               batch_size=args.batch_size, overwrite=args.overwrite, progress=bar.update)
    sl = result.source.episode_slice(args.episode)
    rec = result.record
    path = plot_episode(result.entropy[sl], rec["segments"][args.episode], np.asarray(rec["kept"][args.episode]),
                        args.plot or default_plot_path(args.out),
                        title=f"{rec['task']} demo {args.episode}: {sl.stop - sl.start} -> "
                              f"{rec['new_lengths'][args.episode]} frames (DemoSpeedup, N={args.speedup.num_samples})")
    for line in summary_lines(result):
        print(line)
    print(f"wrote {args.out} and {path}")
    return result


def cli(argv: list[str] | None = None) -> SpeedupResult:
    """Parse ``argv`` and run; a bad value, a missing file or an existing ``--out`` ends in one line."""
    try:
        return main(tyro.cli(SpeedupArgs, args=argv, description=__doc__))
    except (ValueError, FileNotFoundError, FileExistsError) as e:
        raise SystemExit(f"error: {e}") from None


if __name__ == "__main__":
    prepare_process()
    cli()
