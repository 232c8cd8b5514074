"""Collect scripted-expert demonstrations into a Diffusion Policy style zarr ReplayBuffer.

    python -m experiments.collect --task press_button --episodes 100
    python -m experiments.collect --task stack_cubes --episodes 100 --obs-keys state image point_cloud --force

Writes ``data/<key>`` (time first: state, action and any requested camera keys) and ``meta/episode_ends`` to
``--output`` (default ``data/<task>.zarr``). Episodes are rolled out in batches by the vmapped expert in one jitted
rollout and cut at their success step; failed expert episodes are dropped. Refuses to overwrite an existing
dataset unless ``--force``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
from tqdm import tqdm

from hipolicy_jax import envs
from hipolicy_jax.envs import camera as camera_lib
from hipolicy_jax.envs import demos
from hipolicy_jax.runs.cli import prepare_process


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", required=True, choices=envs.TASKS)
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--output", default=None, help="dataset path (default data/<task>.zarr)")
    p.add_argument("--obs-keys", nargs="+", default=["state"], choices=["state", "image", "depth", "point_cloud"])
    p.add_argument("--image-size", type=int, default=64, help="camera H = W in pixels")
    p.add_argument("--num-points", type=int, default=512)
    p.add_argument("--point-rgb", action="store_true", help="point cloud xyz+rgb instead of xyz")
    p.add_argument("--batch-size", type=int, default=50, help="episodes per jitted batch")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="store_true", help="overwrite an existing dataset")
    args = p.parse_args(argv)
    if args.episodes < 1:
        p.error(f"--episodes: must be >= 1, got {args.episodes}")
    if "state" not in args.obs_keys:
        args.obs_keys = ["state"] + args.obs_keys
    return args


def main(argv=None) -> str:
    """Run the CLI; returns the dataset path."""
    args = parse_args(argv)
    path = args.output or os.path.join("data", f"{args.task}.zarr")
    if os.path.exists(path) and not args.force:
        print(f"error: {path} exists; pass --force to overwrite it", file=sys.stderr)
        raise SystemExit(2)
    overrides = {}
    if set(args.obs_keys) - {"state"}:
        overrides["camera"] = camera_lib.CameraConfig(height=args.image_size, width=args.image_size,
                                                      num_points=args.num_points, point_rgb=args.point_rgb)
    t0 = time.perf_counter()
    with tqdm(total=args.episodes, desc=f"{args.task} demos", unit="ep") as bar:
        episodes = demos.collect_demos(args.task, args.episodes, jax.random.PRNGKey(args.seed),
                                       tuple(args.obs_keys), batch_size=args.batch_size, progress=bar.update,
                                       **overrides)
    buf = demos.demo_buffer(args.task, episodes)
    buf.save(path, overwrite=args.force)
    lengths = [len(e["action"]) for e in episodes]
    print(f"wrote {len(episodes)} episodes ({sum(lengths)} frames, length {min(lengths)}-{max(lengths)}, "
          f"keys {sorted(buf.data)}) to {path} in {time.perf_counter() - t0:.1f}s")
    return path


if __name__ == "__main__":
    prepare_process()
    main()
