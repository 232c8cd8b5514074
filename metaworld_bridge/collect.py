"""Collect scripted-expert demos of a Meta-World v3 task into the project's zarr layout (DP3's protocol).

    python -m metaworld_bridge.collect --task assembly --episodes 10 --out data/metaworld_assembly_10.zarr

Seeds ``--seed``, ``--seed + 1``, ... give the initial states (``env.MetaWorldTask.reset``); an episode is kept only
if the expert succeeded, and seeds are drawn until ``--episodes`` succeeded (at most ``--max-seeds``). Each kept
episode is cut at its success step and holds ``state`` (T, 39), ``action`` (T, 4) and, unless
``--no-point-cloud``, ``point_cloud`` (T, --num-points, 3): DP3's corner2 camera ray-cast at ``--camera-size``
squared pixels, cropped and farthest-point sampled (``pointcloud.py``). The buffer's root attribute ``action_kinds``
says per action dim whether it is ``absolute`` or a ``delta`` (``--action-space delta``: ``["delta", "delta",
"delta", "absolute"]``, xyz displacements and the gripper's effort; ``target``: all ``absolute``), so training can
sum a stride-s segment's deltas. The expert first runs without the camera
(a failed episode costs only physics); a successful one is replayed with it and must repeat itself exactly.

Train on the result in the project's venv: ``python -m experiments.train --task metaworld:assembly --data <out>``.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import sys
import time

import numpy as np

from metaworld_bridge.env import ACTION_SPACES, KINDS_OF_SPACE, MAX_STEPS, PROPRIO_DIM, SUITE_OF_SPACE, MetaWorldTask
from metaworld_bridge.pointcloud import (DP3_CAMERA_POS, DP3_CROP_HIGH, DP3_CROP_LOW, DP3_FLOOR_Z, DP3_IMAGE_SIZE,
                                         DP3_NUM_POINTS, CameraConfig, PointCloudCamera)
from metaworld_bridge.store import write_buffer
from metaworld_bridge.tasks import task_name


def default_out(task: str, episodes: int, action_space: str = "delta") -> str:
    """``data/metaworld_<task>_<episodes>.zarr`` (what ``experiments.train --task metaworld:<task>`` looks for;
    absolute targets: ``data/metaworld-target_<task>_<episodes>.zarr``, for ``metaworld-target:<task>``)."""
    return os.path.join("data", f"{SUITE_OF_SPACE[action_space]}_{task_name(task)}_{episodes}.zarr")


def _progress(total: int, desc: str, enabled: bool):
    """A tqdm bar when tqdm is installed and ``enabled``, else a stand-in that does nothing."""
    if enabled:
        try:
            from tqdm import tqdm

            return tqdm(total=total, desc=desc, unit="ep", file=sys.stderr)
        except ImportError:
            pass

    class _Quiet:
        def update(self, n=1):
            pass

        def set_postfix_str(self, s):
            pass

        def close(self):
            pass

    return _Quiet()


def collect(task: str, episodes: int, seed: int = 0, *, num_points: int | None = DP3_NUM_POINTS,
            camera_size: int = DP3_IMAGE_SIZE, max_seeds: int | None = None, max_steps: int = MAX_STEPS,
            progress: bool = True, action_space: str = "delta") -> tuple[list[dict[str, np.ndarray]], dict]:
    """``episodes`` successful expert episodes of ``task`` (frames dicts, actions in ``action_space``) and a record
    of the collection (seeds kept and failed, steps, camera and crop). ``num_points=None``: no point clouds."""
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1, got {episodes}")
    max_seeds = max_seeds or 3 * episodes + 10
    if max_seeds < episodes:
        raise ValueError(f"max_seeds: must be >= episodes ({episodes}), got {max_seeds}")
    env = MetaWorldTask(task, max_steps=max_steps, action_space=action_space)
    camera = None if num_points is None else PointCloudCamera(
        env.model, CameraConfig(size=camera_size, num_points=num_points))
    kept: list[dict[str, np.ndarray]] = []
    kept_seeds, failed_seeds, steps = [], [], []
    bar = _progress(episodes, f"{env.name} demos", progress)
    try:
        for s in range(seed, seed + max_seeds):
            if len(kept) >= episodes:
                break
            trial = env.run_expert(s)
            if not trial.success:
                failed_seeds.append(s)
            else:
                ep = trial if camera is None else env.run_expert(s, camera)
                if ep.steps != trial.steps or not np.array_equal(ep.frames["state"], trial.frames["state"]):
                    raise RuntimeError(f"{env.name}, seed {s}: the replay with the camera diverged from the expert's "
                                       f"run ({ep.steps} vs {trial.steps} steps); the env is not deterministic")
                kept.append(ep.frames)
                kept_seeds.append(s)
                steps.append(ep.steps)
            bar.set_postfix_str(f"{len(kept_seeds)} ok / {len(failed_seeds)} failed")
            bar.update(int(trial.success))
    finally:
        bar.close()
    if len(kept) < episodes:
        raise RuntimeError(f"the {env.name} expert succeeded on only {len(kept)} of {max_seeds} seeds "
                           f"({seed}..{seed + max_seeds - 1}), {episodes} asked for; pass a larger --max-seeds")
    record = {
        "source": "metaworld_bridge", "task": task_name(env.name), "env": f"{env.name}-goal-observable",
        "metaworld": importlib.metadata.version("metaworld"), "mujoco": importlib.metadata.version("mujoco"),
        "seeds": kept_seeds, "failed_seeds": failed_seeds, "steps": steps, "max_steps": max_steps,
        "episode_end": "first success (info['success'])", "proprio_dims": PROPRIO_DIM,
        "state": "Meta-World's 39-D observation (hand xyz, gripper opening, objects, previous frame, goal)",
        "action_space": action_space, "action_kinds": list(KINDS_OF_SPACE[action_space]),
        "action": ("xyz displacement of the hand target and gripper effort, clipped to [-1, 1]"
                   if action_space == "delta" else
                   "the hand target's absolute xyz (m, world frame) after the step, and the gripper effort"),
    }
    if camera is not None:
        record["camera"] = {"name": camera.config.camera, "pos": list(DP3_CAMERA_POS), "size": camera_size,
                            "num_points": num_points, "sampling": "fps from the first cropped point",
                            "frame": "world xyz"}
        record["crop"] = {"frame_rotation": camera.to_dp3.tolist(), "frame_origin": camera.dp3_origin.tolist(),
                          "low": list(DP3_CROP_LOW), "high": list(DP3_CROP_HIGH), "floor_z": DP3_FLOOR_Z,
                          "rule": "world point p kept iff low[:2] < (R (p - origin))[:2] < high[:2], "
                                  "(R (p - origin))[2] < high[2] and p[2] > floor_z"}
    return kept, record


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m metaworld_bridge.collect", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", required=True, help="Meta-World task, e.g. assembly (or assembly-v3)")
    parser.add_argument("--episodes", type=int, default=10, help="successful demos to keep (DP3: 10)")
    parser.add_argument("--out", default="", help="zarr directory (default data/metaworld_<task>_<episodes>.zarr)")
    parser.add_argument("--seed", type=int, default=0, help="first seed of the initial states")
    parser.add_argument("--num-points", type=int, default=DP3_NUM_POINTS, help="points per cloud (DP3: 512)")
    parser.add_argument("--camera-size", type=int, default=DP3_IMAGE_SIZE,
                        help="rays per side of the depth image (DP3: 128)")
    parser.add_argument("--no-point-cloud", action="store_true", help="state and action only")
    parser.add_argument("--max-seeds", type=int, default=None, help="seeds to try at most (default 3 x episodes + 10)")
    parser.add_argument("--max-steps", type=int, default=MAX_STEPS, help="step limit of an episode (Meta-World: 500)")
    parser.add_argument("--action-space", default="delta", choices=list(ACTION_SPACES),
                        help="record Meta-World's displacements (delta) or absolute hand targets (target; train "
                             "with --task metaworld-target:<task>)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    out = args.out or default_out(args.task, args.episodes, args.action_space)
    if os.path.lexists(out) and not args.overwrite:
        raise SystemExit(f"error: out: {out} already exists; pass --overwrite to replace it, or another --out")
    t0 = time.perf_counter()
    try:
        episodes, record = collect(args.task, args.episodes, args.seed,
                                   num_points=None if args.no_point_cloud else args.num_points,
                                   camera_size=args.camera_size, max_seeds=args.max_seeds, max_steps=args.max_steps,
                                   progress=not args.no_progress, action_space=args.action_space)
        data, ends = write_buffer(out, episodes, attrs=record, overwrite=args.overwrite)
    except (ValueError, RuntimeError, FileExistsError, OSError) as e:
        raise SystemExit(f"error: {e}")
    seconds = time.perf_counter() - t0
    steps = np.asarray(record["steps"])
    tried = len(record["seeds"]) + len(record["failed_seeds"])
    shapes = ", ".join(f"{k} {tuple(v.shape)}" for k, v in data.items())
    print(f"{record['task']}: {len(steps)} successful of {tried} expert episodes (seeds {args.seed}.."
          f"{args.seed + tried - 1}, failed {record['failed_seeds']}); mean steps {steps.mean():.1f} "
          f"(min {steps.min()}, max {steps.max()}); {int(ends[-1])} frames: {shapes} → {out} in {seconds:.1f} s")
    return {"out": out, "seconds": seconds, **record}


if __name__ == "__main__":
    main()
