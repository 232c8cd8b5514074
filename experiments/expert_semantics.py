"""The scripted experts chunked at each stride under each execution semantics and controller speed.

    python -m experiments.expert_semantics --episodes 20 --out results/semantics/experts.json

What a policy that reproduced its demos exactly would do when its chunks run at stride s: per task, stride,
semantics (``rate``: one control step per action; ``waypoint``: each action a target reached within the tolerance)
and controller speed limit (None: the position servo gets each target at once), the success rate and the mean
control steps (physical time), actions and decisions per episode, on the same initial states. Writes the JSON
record and prints a markdown table.
"""

from __future__ import annotations

import argparse
import platform
import sys

import jax

from hipolicy_jax import envs as envs_lib
from hipolicy_jax.config import InferenceConfig
from hipolicy_jax.evaluation.rollout import Semantics, expert_counts
from hipolicy_jax import jsonio


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=list(envs_lib.TASKS))
    parser.add_argument("--strides", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--semantics", nargs="+", default=["rate", "waypoint"], choices=["rate", "waypoint"])
    parser.add_argument("--speeds", nargs="+", default=["none", "0.25"],
                        help="controller speed limits in m/s ('none': no limit)")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--chunk-len", type=int, default=8)
    parser.add_argument("--tolerance", type=float, default=None, help="m (default: each task's own)")
    parser.add_argument("--waypoint-steps", type=int, default=None, help="per unit of stride (default: the task's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="", help="JSON record path (none: print only)")
    args = parser.parse_args(argv)
    speeds = [None if s.lower() == "none" else float(s) for s in args.speeds]
    rows = []
    print("| task | controller speed | stride | semantics | success | control steps | actions | decisions |")
    print("|---|---|---|---|---|---|---|---|")
    for task in args.tasks:
        for speed in speeds:
            env = envs_lib.make(task, **({} if speed is None else {"controller_speed": speed}))
            for stride in args.strides:
                for kind in args.semantics:
                    sem = Semantics.of(InferenceConfig(semantics=kind, waypoint_tolerance=args.tolerance,
                                                       waypoint_steps=args.waypoint_steps), env)
                    row = {"task": task, "controller_speed": speed, "stride": stride, "semantics": kind,
                           **expert_counts(env, stride, args.episodes, jax.random.PRNGKey(args.seed),
                                           chunk_len=args.chunk_len, semantics=sem)}
                    rows.append(row)
                    print(f"| {task} | {'none' if speed is None else f'{speed:g} m/s'} | {stride} | {kind} | "
                          f"{row['success_rate']:.2f} | {row['mean_steps']:.1f} | {row['mean_actions']:.1f} | "
                          f"{row['mean_decisions']:.1f} |", flush=True)
    record = {"what": "scripted experts chunked at each stride under each execution semantics "
                      "(experiments.expert_semantics)",
              "command": "python -m experiments.expert_semantics " + " ".join(sys.argv[1:] if argv is None else argv),
              "episodes": args.episodes, "seed": args.seed, "chunk_len": args.chunk_len,
              "waypoint_tolerance": args.tolerance, "waypoint_steps": args.waypoint_steps,
              "cpu": platform.processor() or platform.machine(), "rows": rows}
    if args.out:
        jsonio.dump(record, args.out)
    return record


if __name__ == "__main__":
    main()
