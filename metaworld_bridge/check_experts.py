"""How often Meta-World's scripted experts succeed on DP3's Medium, Hard and Very Hard tasks (v3).

    python -m metaworld_bridge.check_experts --seeds 50          # → results/metaworld/experts.json
    python -m metaworld_bridge.check_experts --tasks assembly --strides 1 2 3 --action-spaces delta target \
        --seeds 20 --max-steps 200 --out strided.json                 # the expert as a chunking policy per stride
    python -m metaworld_bridge.check_experts --tasks assembly --strides 1 2 3 --action-spaces delta target \
        --delta-chunks every summed --semantics rate waypoint --seeds 20 --out strided.json

With ``--strides``, every (action space, delta chunking, semantics) is a variant, keyed in the JSON as the action
space (``delta``, ``target``: every stride-th action, ``rate``: today's), ``+summed`` for displacements chunked with
summed deltas (a stride-s action = the sum of its block's s expert displacements) and ``@waypoint`` for the
waypoint semantics (``delta+summed@waypoint``); per stride: successes, the mean control steps of the successful
episodes (``mean_steps``: physical time) and of all (``mean_control_steps``), the mean actions and decisions, and
the share of actions clipped by the environment's limit (``rate``) or unreached within the bound (``waypoint``).

Every task runs its expert from the initial states of seeds 0..N-1 (``env.MetaWorldTask.reset``: the seeds the
demos are collected from) until the first success or the step limit (``--max-steps``, default 500), without a camera. The JSON holds, per
task, successes out of N, the mean (min, max) steps of the successful episodes and the failed seeds, plus the
group totals and the versions it ran with.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import sys
import time

import numpy as np

from metaworld_bridge.env import ACTION_SPACES, MAX_STEPS, WAYPOINT_STEPS, WAYPOINT_TOLERANCE, MetaWorldTask
from metaworld_bridge.evaluate import add_semantics_flags
from metaworld_bridge.tasks import DP3_GROUPS

DEFAULT_OUT = os.path.join("results", "metaworld", "experts.json")
DELTA_CHUNKS = ("every", "summed")  # displacements chunked as every stride-th one, or as the sum of each block


def variant(space: str, chunks: str = "every", semantics: str = "rate") -> str:
    """The JSON key of a chunking variant: ``delta``, ``target``, ``delta+summed``, ``target@waypoint``, ..."""
    return space + ("+summed" if chunks == "summed" else "") + ("" if semantics == "rate" else f"@{semantics}")


def check_task(task: str, seeds: int, first_seed: int = 0, max_steps: int = MAX_STEPS, stride: int | None = None,
               action_space: str = "delta", chunk_len: int = 8, *, summed_deltas: bool = False,
               semantics: str = "rate", tolerance: float = WAYPOINT_TOLERANCE,
               waypoint_steps: int = WAYPOINT_STEPS) -> dict:
    """Expert success of ``task`` over ``seeds`` initial states from ``first_seed``; with ``stride``, the expert
    as a chunking policy at that stride (``MetaWorldTask.run_strided_expert``) in ``action_space``, displacements
    chunked as every stride-th one or ``summed_deltas``, executed under ``semantics``. ``mean_steps`` (min, max):
    control steps of the successful episodes; the means of ``control_steps``, ``actions`` and ``decisions`` are
    over all episodes; ``clipped`` / ``unreached``: shares of the executed actions."""
    env = MetaWorldTask(task, max_steps=max_steps, action_space=action_space)
    steps, failed, eps = [], [], []
    for s in range(first_seed, first_seed + seeds):
        ep = env.run_expert(s) if stride is None else env.run_strided_expert(
            s, stride, chunk_len, summed_deltas=summed_deltas, semantics=semantics, tolerance=tolerance,
            waypoint_steps=waypoint_steps)
        eps.append(ep)
        (steps.append(ep.steps) if ep.success else failed.append(s))
    ok = np.asarray(steps)
    actions = sum(e.actions for e in eps)
    return {"successes": len(steps), "episodes": seeds, "success_rate": len(steps) / seeds,
            "mean_steps": float(ok.mean()) if ok.size else None, "min_steps": int(ok.min()) if ok.size else None,
            "max_steps": int(ok.max()) if ok.size else None, "failed_seeds": failed,
            "mean_control_steps": float(np.mean([e.steps for e in eps])),
            "mean_actions": float(np.mean([e.actions for e in eps])),
            "mean_decisions": float(np.mean([e.decisions for e in eps])),
            "clipped": sum(e.clipped for e in eps) / max(actions, 1),
            "unreached": sum(e.unreached for e in eps) / max(actions, 1)}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m metaworld_bridge.check_experts", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, default=50, help="initial states per task")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--groups", nargs="+", default=list(DP3_GROUPS), choices=list(DP3_GROUPS))
    parser.add_argument("--tasks", nargs="+", default=None, help="these tasks instead of --groups")
    parser.add_argument("--max-steps", type=int, default=MAX_STEPS,
                        help="step limit of an episode (Meta-World: 500; DP3 evaluates with 200)")
    parser.add_argument("--strides", nargs="+", type=int, default=None,
                        help="run the expert as a chunking policy at each of these strides (chunks of --chunk-len "
                             "actions, every stride-th of its actions ahead) instead of step by step")
    parser.add_argument("--action-spaces", nargs="+", default=["delta"], choices=list(ACTION_SPACES),
                        help="with --strides: the action spaces its chunks are executed in")
    parser.add_argument("--chunk-len", type=int, default=8, help="with --strides: actions per chunk (L_c)")
    parser.add_argument("--delta-chunks", nargs="+", default=["every"],
                        help="with --strides, displacements: chunk them as every stride-th one (every, today's) "
                             "and/or as the sum of each block of stride (summed)")
    add_semantics_flags(parser, many=True)
    parser.add_argument("--out", default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    if args.seeds < 1:
        raise SystemExit(f"error: seeds: must be >= 1, got {args.seeds}")
    bad = [c for c in args.delta_chunks if c not in DELTA_CHUNKS]
    if bad:
        raise SystemExit(f"error: delta_chunks: each one of {', '.join(DELTA_CHUNKS)}, got {bad[0]!r}")
    try:
        for semantics in args.semantics:
            MetaWorldTask.check_semantics(semantics, args.waypoint_tolerance, args.waypoint_steps)
    except ValueError as e:
        raise SystemExit(f"error: {e}")
    if args.strides is not None:
        return strided(args)
    groups = {"custom": tuple(args.tasks)} if args.tasks else {g: DP3_GROUPS[g] for g in args.groups}
    t0 = time.perf_counter()
    tasks, totals = {}, {}
    try:
        for group, names in groups.items():
            for name in names:
                t = time.perf_counter()
                tasks[name] = {"group": group, **check_task(name, args.seeds, args.first_seed, args.max_steps)}
                r = tasks[name]
                mean = "-" if r["mean_steps"] is None else f"{r['mean_steps']:.1f}"
                print(f"{group:>9} {name:<18} {r['successes']:>3}/{args.seeds}  mean steps {mean:>6}  "
                      f"({time.perf_counter() - t:.1f} s)", flush=True)
            ok = sum(tasks[n]["successes"] for n in names)
            totals[group] = {"tasks": len(names), "successes": ok, "episodes": len(names) * args.seeds,
                             "success_rate": ok / (len(names) * args.seeds)}
    except ValueError as e:
        raise SystemExit(f"error: {e}")
    report = {
        "what": "Meta-World v3 scripted experts (metaworld.policies.ENV_POLICY_MAP), goal-observable envs, one "
                "episode per seed until the first success (info['success']) or the step limit",
        "seeds": list(range(args.first_seed, args.first_seed + args.seeds)), "max_steps": args.max_steps,
        "metaworld": importlib.metadata.version("metaworld"), "mujoco": importlib.metadata.version("mujoco"),
        "python": sys.version.split()[0], "seconds": round(time.perf_counter() - t0, 1),
        "groups": totals, "tasks": tasks,
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
        f.write("\n")
    print(", ".join(f"{g}: {v['successes']}/{v['episodes']}" for g, v in totals.items()) + f" → {args.out}")
    return report


def strided(args) -> dict:
    """``--strides``: per task, variant (action space, delta chunking, semantics) and stride, the chunking expert's
    success and counts → ``--out``; prints per task and variant the successes at each stride."""
    names = list(args.tasks) if args.tasks else [n for g in args.groups for n in DP3_GROUPS[g]]
    variants = [(space, chunks, sem) for space in args.action_spaces
                for chunks in (args.delta_chunks if space == "delta" else ["every"]) for sem in args.semantics]
    t0 = time.perf_counter()
    tasks: dict[str, dict] = {}
    try:
        for name in names:
            for space, chunks, sem in variants:
                t, key = time.perf_counter(), variant(space, chunks, sem)
                rows = {}
                for stride in args.strides:
                    rows[str(stride)] = check_task(name, args.seeds, args.first_seed, args.max_steps, stride, space,
                                                   args.chunk_len, summed_deltas=chunks == "summed", semantics=sem,
                                                   tolerance=args.waypoint_tolerance,
                                                   waypoint_steps=args.waypoint_steps)
                tasks.setdefault(name, {})[key] = rows
                ok = " | ".join(f"{r['successes']:>2}/{args.seeds}" for r in rows.values())
                cs = " / ".join(f"{r['mean_control_steps']:.0f}" for r in rows.values())
                cut = " / ".join(f"{100 * r['clipped' if sem == 'rate' else 'unreached']:.0f}" for r in rows.values())
                print(f"{name:<18} {key:<22} success at strides {'/'.join(map(str, args.strides))}: {ok}; control "
                      f"steps {cs}; % {'clipped' if sem == 'rate' else 'unreached'} {cut}  "
                      f"({time.perf_counter() - t:.1f} s)", flush=True)
    except ValueError as e:
        raise SystemExit(f"error: {e}")
    report = {
        "what": "Meta-World v3 scripted experts executed as chunking policies: at each decision the expert runs "
                f"{args.chunk_len} x stride steps ahead in the simulator (then restored) and each block of stride of "
                f"its actions gives one action (its last; '+summed': the sum of its displacements), {args.chunk_len} "
                "per chunk, closed loop; 'delta': Meta-World's displacement actions, 'target': absolute hand "
                "targets; '@waypoint': each action held until the hand reaches it (MetaWorldTask.run_strided_expert)",
        "seeds": list(range(args.first_seed, args.first_seed + args.seeds)), "max_steps": args.max_steps,
        "chunk_len": args.chunk_len, "strides": args.strides, "action_spaces": args.action_spaces,
        "delta_chunks": args.delta_chunks, "semantics": args.semantics,
        "waypoint_tolerance": args.waypoint_tolerance, "waypoint_steps": args.waypoint_steps,
        "variants": [variant(*v) for v in variants],
        "metaworld": importlib.metadata.version("metaworld"), "mujoco": importlib.metadata.version("mujoco"),
        "python": sys.version.split()[0], "seconds": round(time.perf_counter() - t0, 1), "tasks": tasks,
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
        f.write("\n")
    print(f"→ {args.out}")
    return report


if __name__ == "__main__":
    main()
