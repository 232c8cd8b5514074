"""Closed-loop evaluation of a served policy on a Meta-World v3 task: the env runs here, the policy in the project's
server (``python -m experiments.serve``), spoken to with openpi's own client (``openpi_client``).

    # project venv: serve a run trained on metaworld:<task>
    .venv/bin/python -m experiments.serve --checkpoint runs/metaworld_assembly_state_seed0 --port 8000
    # Meta-World venv: 100 episodes, 10 envs at a time
    .venv-metaworld/bin/python -m metaworld_bridge.evaluate --task assembly --url ws://127.0.0.1:8000 \\
        --episodes 100 --first-seed 1000000 --out results/metaworld_assembly_eval.json

**Episodes.** Episode i starts from the initial state of seed ``first_seed + i`` (``env.MetaWorldTask.reset``: a
function of the seed alone, so every policy evaluated with the same seeds starts from the same states). It ends at
the first step whose ``info["success"]`` is set (success; ``steps`` = the steps taken), or at ``--max-steps``.

**Decisions.** Each decision sends one robot's observation history ``{key: (obs_span, ...)}`` (the keys and shapes
the server's manifest lists; ``state`` (39,) and, for point-cloud policies, ``point_cloud`` (P, 3) from DP3's
corner2 camera, ``pointcloud.py``; an episode's start is padded by repeating its first frame) and gets the actions to
execute and the ``stride`` they were decided at, which run one after another until the reply is used up, the task
succeeds or the step limit comes. The history gets one frame per action, after the action completes. The
decision's PRNG key is sent with it: decision n of the episode from seed s uses the raw key ``(s, n)``, so an
episode's outcome is a function of (policy, seed) alone, the same for every batch size and server (up to the float
rounding of a batched call, which can differ by batch size in the last digits).

**Execution semantics** (``--semantics``, ``env.MetaWorldTask.execute``): ``rate`` (the default) gives each action
one control step; ``waypoint`` (HiPolicy's release) gives each action's target to the controller until the hand's
mocap target has arrived there and the hand is within ``--waypoint-tolerance`` m of it, or ``--waypoint-steps`` x
the decision's stride control steps ran. A delta action's target is relative to where the hand's mocap target is
when the action starts. The step limit counts
control steps (physical time, 12.5 ms each) under both. The server's metadata may declare ``action_kinds`` (one of
``absolute`` / ``delta`` per action dim; a policy trained on summed deltas: ``["delta", "delta", "delta",
"absolute"]``; missing: all absolute); under ``rate`` a summed delta beyond [-1, 1] is clipped by Meta-World's limit,
and the record counts such actions (``clipped``).

**Batching.** ``--envs`` E episodes run at once, each on its own connection (openpi's protocol is one robot per
connection). Every round, each running episode's request is sent from its own thread at the same time and the
server's micro-batching decides them in one batched call (``--max-batch`` on the server ≥ E); then the envs step.

The result (``--out``, JSON) holds per episode: seed, success, ``steps`` (control steps: physical time; also as
``control_steps``), ``decisions``, ``actions`` (executed), ``clipped`` (actions the per-step limit cut, ``rate``),
``unreached`` (actions that ran into the bound before their target was reached, ``waypoint``), the strides
chosen (counts) and the mean entropy, and per decision its stride and entropy (``decision_strides``,
``entropies``: null where there is none; what closed-loop calibration reads, ``hipolicy_jax.runs.calibrate``);
their means (``mean_steps``, ``mean_control_steps``, ``mean_decisions``,
``mean_actions``), the execution settings (``semantics``, ``waypoint_tolerance``, ``waypoint_steps``,
``action_kinds``); and the run's manifest entries (task, run, checkpoint step, strides, inference settings), the
command and wall-clock split (env, camera, waiting for the server).
"""

from __future__ import annotations

import argparse
import collections
import concurrent.futures
import contextlib
import dataclasses
import importlib.metadata
import json
import os
import sys
import time
import urllib.error
import urllib.request

import numpy as np

from metaworld_bridge.env import (ACTION_DIM, ACTION_KINDS, ACTION_SPACES, MAX_STEPS, MOVE_CLIPS, OBS_DIM,
                                  SEMANTICS, SUITE_OF_SPACE, WAYPOINT_STEPS, WAYPOINT_TOLERANCE,
                                  MetaWorldTask)
from metaworld_bridge.pointcloud import DP3_IMAGE_SIZE, CameraConfig, PointCloudCamera
from metaworld_bridge.tasks import task_name

OBS_KEYS = ("state", "point_cloud")


@dataclasses.dataclass
class EpisodeResult:
    """What one episode did: ``steps`` control steps (physical time), ``decisions`` server replies, ``actions``
    executed, ``clipped`` / ``unreached`` actions (``MetaWorldTask.execute``)."""

    seed: int
    success: bool
    steps: int
    decisions: int = 0
    actions: int = 0
    clipped: int = 0
    unreached: int = 0
    strides: list[int] = dataclasses.field(default_factory=list)
    entropy: list[float] = dataclasses.field(default_factory=list)

    def summary(self) -> dict:
        """The record's per-episode entry: the counts, ``strides`` as {stride: decisions}, ``mean_entropy`` over
        the finite entropies, and per decision (``decisions`` of each) ``decision_strides`` and ``entropies``
        (None where the server sent none or NaN: a policy with N = 1)."""
        ent = [e for e in self.entropy if np.isfinite(e)]
        return {"seed": self.seed, "success": self.success, "steps": self.steps, "decisions": self.decisions,
                "actions": self.actions, "control_steps": self.steps, "clipped": self.clipped,
                "unreached": self.unreached,
                "strides": dict(sorted(collections.Counter(self.strides).items())),
                "mean_entropy": float(np.mean(ent)) if ent else None,
                "decision_strides": [int(s) for s in self.strides],
                "entropies": [float(e) if np.isfinite(e) else None for e in self.entropy]}


def _http_url(url: str) -> str:
    return "http" + url[len("ws"):] if url.startswith("ws") else f"http://{url}"


def check_server(url: str, timeout: float = 5.0) -> None:
    """Raise ``ConnectionError`` naming ``url`` and how to start a server unless its ``/healthz`` answers."""
    try:
        with urllib.request.urlopen(_http_url(url).rstrip("/") + "/healthz", timeout=timeout) as r:
            if r.status == 200:
                return
    except (urllib.error.URLError, OSError) as e:
        reason = getattr(e, "reason", e)
        raise ConnectionError(f"url: no policy server answers at {url} ({reason}); start one in the project's venv: "
                              f"python -m experiments.serve --checkpoint RUN_DIR") from None
    raise ConnectionError(f"url: {url}/healthz did not answer 200")


def action_kinds(metadata: dict, action_space: str = "delta") -> list[str]:
    """The served policy's ``action_kinds`` (one of ``env.ACTION_KINDS`` per action dim; missing: all absolute, as
    every policy trained before kinds were declared), checked against the ``action_space`` its actions are executed
    in (a delta on xyz cannot be an absolute target; the gripper is an effort); ``ValueError`` names the mismatch."""
    kinds = metadata.get("action_kinds")
    if kinds is None:
        return ["absolute"] * ACTION_DIM
    kinds = list(kinds)
    if len(kinds) != ACTION_DIM or any(k not in ACTION_KINDS for k in kinds):
        raise ValueError(f"action_kinds: the server declares {kinds}; expected {ACTION_DIM} of "
                         f"{', '.join(ACTION_KINDS)}")
    if kinds[3] != "absolute":
        raise ValueError(f"action_kinds: the gripper (dim 3) is an effort, declared {kinds[3]!r}; expected 'absolute'")
    if action_space == "target" and "delta" in kinds:
        raise ValueError(f"action_kinds: the served policy's xyz actions are {kinds[:3]}, displacements; absolute "
                         f"targets expected with --action-space target (pass --action-space delta)")
    return kinds


def check_metadata(metadata: dict, task: str, action_space: str = "delta") -> dict[str, tuple[int, ...]]:
    """The observation shapes ``{key: (obs_span, ...)}`` the served policy reads, after checking it is a policy of
    ``metaworld:<task>`` (``metaworld-target:<task>`` for absolute targets) with 4-D actions; ``ValueError`` names
    the mismatch."""
    served = metadata.get("task")
    want = f"{SUITE_OF_SPACE[action_space]}:{task_name(task)}"
    if served != want:
        other = {f"{v}:{task_name(task)}": k for k, v in SUITE_OF_SPACE.items()}.get(served)
        hint = f" (its actions are the {other!r} space: pass --action-space {other})" if other else ""
        raise ValueError(f"task: the server's policy was trained on {served!r}, not {want!r}{hint}")
    if metadata.get("action_dim") != ACTION_DIM:
        raise ValueError(f"action_dim: the server's policy acts in {metadata.get('action_dim')} dims, Meta-World in "
                         f"{ACTION_DIM}")
    obs = metadata.get("obs") or {}
    unknown = sorted(set(obs) - set(OBS_KEYS))
    if unknown or "state" not in obs:
        raise ValueError(f"obs: the served policy reads {sorted(obs)}; the bridge provides {list(OBS_KEYS)} "
                         f"(state required)")
    shapes = {k: tuple(int(d) for d in spec["shape"]) for k, spec in obs.items()}
    if shapes["state"][1:] != (OBS_DIM,):
        raise ValueError(f"obs.state: the served policy reads frames of shape {shapes['state'][1:]}, Meta-World's "
                         f"state is ({OBS_DIM},)")
    if "point_cloud" in shapes and (len(shapes["point_cloud"]) != 3 or shapes["point_cloud"][2] != 3):
        raise ValueError(f"obs.point_cloud: the served policy reads frames of shape {shapes['point_cloud'][1:]}; "
                         f"the bridge makes (P, 3) xyz clouds")
    return shapes


class _Slot:
    """One env and its connection: runs one episode at a time."""

    def __init__(self, task: str, make_client, shapes: dict, camera_size: int, max_steps: int,
                 action_space: str = "delta", move_limit: float = 1.0, move_clip: str = "axis",
                 semantics: str = "rate", tolerance: float = WAYPOINT_TOLERANCE, waypoint_steps: int = WAYPOINT_STEPS):
        self.env = MetaWorldTask(task, max_steps=max_steps, action_space=action_space, move_limit=move_limit,
                                 move_clip=move_clip)
        self.semantics, self.tolerance, self.waypoint_steps = semantics, tolerance, waypoint_steps
        self.client = make_client()
        self.shapes = shapes
        self.camera = None
        if "point_cloud" in shapes:
            self.camera = PointCloudCamera(self.env.model, CameraConfig(size=camera_size,
                                                                       num_points=shapes["point_cloud"][1]))
        self.span = shapes["state"][0]
        self.result: EpisodeResult | None = None
        self.history: dict[str, collections.deque] = {}
        self.camera_s = 0.0

    def _frame(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        frame = {"state": obs.astype(np.float32)}
        if self.camera is not None:
            t0 = time.perf_counter()
            frame["point_cloud"] = self.camera(self.env.model, self.env.data)
            self.camera_s += time.perf_counter() - t0
        return frame

    def start(self, seed: int) -> None:
        frame = self._frame(self.env.reset(seed))
        self.history = {k: collections.deque([v] * self.span, maxlen=self.span) for k, v in frame.items()}
        self.result = EpisodeResult(seed=int(seed), success=False, steps=0)

    def request(self) -> dict:
        r = self.result
        msg = {k: np.stack(h) for k, h in self.history.items()}
        msg["key"] = np.asarray([r.seed % 2**32, r.decisions], np.uint32)
        if r.decisions == 0:
            msg["reset"] = True
        return msg

    def step(self, reply: dict) -> bool:
        """Execute the reply's actions; → whether the episode ended."""
        r = self.result
        actions = np.asarray(reply["actions"], np.float32)
        if actions.ndim != 2 or actions.shape[1] != ACTION_DIM or len(actions) == 0:
            raise ValueError(f"reply: actions of shape {actions.shape}, expected (n >= 1, {ACTION_DIM})")
        stride = int(reply.get("stride", 0))
        r.decisions += 1
        r.strides.append(stride)
        r.entropy.append(float(reply.get("entropy", float("nan"))))
        for a in actions:
            done = self.env.execute(a, self.semantics, max(stride, 1), self.tolerance, self.waypoint_steps)
            r.actions += 1
            r.steps += done.control_steps
            r.clipped += done.clipped
            r.unreached += done.unreached
            if done.success or done.truncated:
                r.success = done.success
                return True
            for k, v in self._frame(done.obs).items():  # one frame per action, after it completes
                self.history[k].append(v)
        return False


def _openpi_client(url: str, api_key: str | None):
    """openpi's ``WebsocketClientPolicy`` for ``url`` (its import logs nothing; its connect fails fast here)."""
    from openpi_client.websocket_client_policy import WebsocketClientPolicy

    return WebsocketClientPolicy(url, api_key=api_key)


def evaluate(task: str, url: str, episodes: int, first_seed: int, *, num_envs: int = 10, max_steps: int = MAX_STEPS,
             camera_size: int = DP3_IMAGE_SIZE, api_key: str | None = None, progress: bool = True,
             action_space: str = "delta", move_limit: float = 1.0, move_clip: str = "axis", semantics: str = "rate",
             waypoint_tolerance: float = WAYPOINT_TOLERANCE, waypoint_steps: int = WAYPOINT_STEPS) -> dict:
    """Run ``episodes`` episodes of ``task`` (seeds ``first_seed`` ...) against the server at ``url``, executing its
    actions in ``action_space`` (targets with at most ``move_limit`` cm a step, bounded by ``move_clip``:
    ``env.MOVE_CLIPS``) under ``semantics`` (``env.SEMANTICS``; ``waypoint``: within ``waypoint_tolerance`` m, at
    most ``waypoint_steps`` x stride control steps an action); → the record (see the module docstring)."""
    MetaWorldTask.check_move(action_space, move_limit, move_clip)
    MetaWorldTask.check_semantics(semantics, waypoint_tolerance, waypoint_steps)
    if episodes < 1:
        raise ValueError(f"episodes: must be >= 1, got {episodes}")
    if num_envs < 1:
        raise ValueError(f"envs: must be >= 1, got {num_envs}")
    if first_seed < 0 or first_seed + episodes > 2**32:
        raise ValueError(f"first_seed: seeds must lie in [0, 2**32), got {first_seed}..{first_seed + episodes - 1}")
    check_server(url)
    t_start = time.perf_counter()
    first = _openpi_client(url, api_key)
    metadata = first.get_server_metadata()
    shapes = check_metadata(metadata, task, action_space)
    kinds = action_kinds(metadata, action_space)
    num_envs = min(num_envs, episodes)
    clients = iter([first])
    slots = [_Slot(task, lambda: next(clients, None) or _openpi_client(url, api_key), shapes, camera_size, max_steps,
                   action_space, move_limit, move_clip, semantics, waypoint_tolerance, waypoint_steps)
             for _ in range(num_envs)]
    seeds = list(range(first_seed, first_seed + episodes))
    done: list[EpisodeResult] = []
    wait_s = env_s = 0.0
    bar = _progress(episodes, f"{task_name(task)} eval", progress)
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=num_envs)
    try:
        running = []
        for slot in slots:
            if seeds:
                slot.start(seeds.pop(0))
                running.append(slot)
        while running:
            t0 = time.perf_counter()
            replies = list(pool.map(lambda s: s.client.infer(s.request()), running))
            t1 = time.perf_counter()
            still = []
            for slot, reply in zip(running, replies):
                if slot.step(reply):
                    done.append(slot.result)
                    bar.update(1)
                    bar.set_postfix_str(f"{sum(r.success for r in done)}/{len(done)} success")
                    if seeds:
                        slot.start(seeds.pop(0))
                        still.append(slot)
                else:
                    still.append(slot)
            running = still
            wait_s += t1 - t0
            env_s += time.perf_counter() - t1
    finally:
        bar.close()
        pool.shutdown()
        for slot in slots:
            with contextlib.suppress(Exception):
                slot.client._ws.close()
    done.sort(key=lambda r: r.seed)
    camera_s = sum(s.camera_s for s in slots)
    successes = sum(r.success for r in done)
    return {
        "what": "Meta-World closed-loop evaluation through the policy server (metaworld_bridge.evaluate)",
        "task": task_name(task), "url": url, "episodes": len(done), "first_seed": first_seed,
        "seeds": [r.seed for r in done], "max_steps": max_steps, "envs": num_envs, "action_space": action_space,
        "move_limit": move_limit, "move_clip": move_clip,
        "semantics": semantics, "waypoint_tolerance": waypoint_tolerance, "waypoint_steps": waypoint_steps,
        "action_kinds": kinds, "summed_deltas": "delta" in kinds,
        "success_rate": successes / len(done), "successes": successes,
        "mean_steps": float(np.mean([r.steps for r in done])),
        "mean_control_steps": float(np.mean([r.steps for r in done])),
        "mean_decisions": float(np.mean([r.decisions for r in done])),
        "mean_actions": float(np.mean([r.actions for r in done])),
        "clipped": {"actions": sum(r.clipped for r in done), "of": sum(r.actions for r in done),
                    "what": "actions whose move the per-control-step limit cut (rate: clipped by the environment's "
                            "limit, Meta-World's [-1, 1] for displacements, --move-limit for targets)"},
        "unreached": {"actions": sum(r.unreached for r in done), "of": sum(r.actions for r in done),
                      "what": "waypoint: actions that ran into the bound of control steps before their target was "
                              "reached (the mocap target there, the hand within the tolerance)"},
        "policy": {k: metadata.get(k) for k in ("task", "run", "checkpoint_step", "strides", "chunk_len",
                                                 "obs_span", "num_samples", "inference", "thresholds_source")},
        "server": metadata.get("server"), "camera_size": camera_size if "point_cloud" in shapes else None,
        "seconds": {"total": time.perf_counter() - t_start, "server_wait": wait_s, "env": env_s - camera_s,
                    "camera": camera_s},
        "metaworld": importlib.metadata.version("metaworld"), "mujoco": importlib.metadata.version("mujoco"),
        "openpi_client": importlib.metadata.version("openpi-client"),
        "per_episode": [r.summary() for r in done],
    }


def add_semantics_flags(parser: argparse.ArgumentParser, many: bool = False) -> None:
    """``--semantics`` (several with ``many``), ``--waypoint-tolerance`` and ``--waypoint-steps``; checked by
    ``MetaWorldTask.check_semantics`` (one-line errors naming the option)."""
    parser.add_argument("--semantics", default=["rate"] if many else "rate", nargs="+" if many else None,
                        help=f"how each action is executed: {' or '.join(SEMANTICS)} (rate: one control step an "
                             "action; waypoint: the action's target is held until the hand reaches it or the bound)")
    parser.add_argument("--waypoint-tolerance", type=float, default=WAYPOINT_TOLERANCE,
                        help=f"waypoint: the hand counts as at its target within this many metres (default "
                             f"{WAYPOINT_TOLERANCE}, measured: env.py's docstring)")
    parser.add_argument("--waypoint-steps", type=int, default=WAYPOINT_STEPS,
                        help=f"waypoint: an action runs at most this many control steps x its decision's stride "
                             f"(default {WAYPOINT_STEPS})")


def _progress(total: int, desc: str, enabled: bool):
    from metaworld_bridge.collect import _progress as bar

    return bar(total, desc, enabled)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m metaworld_bridge.evaluate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", required=True, help="Meta-World task, e.g. assembly; the served policy's task")
    parser.add_argument("--url", default="ws://127.0.0.1:8000", help="the policy server (experiments.serve)")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--first-seed", type=int, default=1_000_000,
                        help="initial state of episode i: seed first_seed + i (demos use seeds from 0)")
    parser.add_argument("--envs", type=int, default=10, help="episodes run at once (one connection each)")
    parser.add_argument("--max-steps", type=int, default=MAX_STEPS, help="step limit (Meta-World: 500)")
    parser.add_argument("--camera-size", type=int, default=DP3_IMAGE_SIZE,
                        help="rays per side for point clouds (as the demos: DP3 128)")
    parser.add_argument("--api-key", default=os.environ.get("HIPOLICY_API_KEY", ""),
                        help="sent as 'Authorization: Api-Key <key>' (default $HIPOLICY_API_KEY)")
    parser.add_argument("--action-space", default="delta", choices=list(ACTION_SPACES),
                        help="how the served policy's actions are executed: Meta-World's displacements (delta, a "
                             "metaworld:<task> policy) or absolute hand targets (target, metaworld-target:<task>)")
    parser.add_argument("--move-limit", type=float, default=1.0,
                        help="target actions: the most the hand's target moves in a control step, in cm (Meta-World: "
                             "1); s gives a stride-s chunk the headroom of s steps")
    parser.add_argument("--move-clip", default="axis", choices=list(MOVE_CLIPS),
                        help="target actions: clip each axis to the limit (axis, Meta-World's own) or scale the move "
                             "keeping its direction (direction)")
    add_semantics_flags(parser)
    parser.add_argument("--out", default="", help="write the record here (JSON)")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    try:
        record = evaluate(args.task, args.url, args.episodes, args.first_seed, num_envs=args.envs,
                          max_steps=args.max_steps, camera_size=args.camera_size, api_key=args.api_key or None,
                          progress=not args.no_progress, action_space=args.action_space,
                          move_limit=args.move_limit, move_clip=args.move_clip, semantics=args.semantics,
                          waypoint_tolerance=args.waypoint_tolerance, waypoint_steps=args.waypoint_steps)
    except (ValueError, ConnectionError, RuntimeError) as e:
        raise SystemExit(f"error: {e}")
    record["command"] = " ".join(["python -m metaworld_bridge.evaluate", *(argv if argv is not None else sys.argv[1:])])
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(record, f, indent=1)
    s = record["seconds"]
    clip, miss = record["clipped"], record["unreached"]
    note = (f"{clip['actions']} of {clip['of']} actions clipped by the environment's limit" if args.semantics == "rate"
            else f"{miss['actions']} of {miss['of']} actions unreached within the bound")
    print(f"{record['task']}: {record['successes']}/{record['episodes']} success ({100 * record['success_rate']:.1f} %), "
          f"{args.semantics}: mean decisions {record['mean_decisions']:.1f}, actions {record['mean_actions']:.1f}, "
          f"control steps {record['mean_steps']:.1f}; {note}; {s['total']:.1f} s (server {s['server_wait']:.1f}, "
          f"env {s['env']:.1f}, camera {s['camera']:.1f})" + (f" → {args.out}" if args.out else ""))
    return record


if __name__ == "__main__":
    main()
