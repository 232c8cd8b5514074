"""Tasks of external simulators: trained on here from demos collected elsewhere, with no MJX env.

A task name ``<suite>:<task>`` (e.g. ``metaworld:assembly``) names a task of a simulator that cannot share this
venv; its demos come from a bridge in its own venv (``metaworld_bridge``, ``.venv-metaworld``) as a zarr in the
project's layout. Training needs to know only the shapes of its actions and observations (to check the demos) and
how many leading state features are proprioception; it is never rolled out in-process (evaluation goes through the
policy server). Nothing here imports the simulator.
"""

from __future__ import annotations

import dataclasses
import os
import re

from hipolicy_jax.config import EncoderConfig, check_action_kinds


@dataclasses.dataclass(frozen=True)
class ExternalSuite:
    """A simulator whose tasks are trained on from external demos."""

    name: str
    action_dim: int
    state_dim: int
    proprio_dim: int  # leading state features that are the agent's proprioception (what vision policies read)
    setup: str  # how to make its venv
    collect: str  # its demo-collection command, formatted with task, episodes, path
    evaluate: str  # its closed-loop evaluation against a policy server: task, url, episodes, first_seed, envs,
    # max_steps, out (a JSON record of every episode)
    eval_max_steps: int  # the campaigns' episode step limit
    source: str = ""  # the ``source`` attribute its bridge writes into a demo buffer (default ``<name>_bridge``)
    action_space: str = "delta"  # the ``action_space`` attribute its demos must hold (absent: ``delta``)
    # per action dimension 'absolute' or 'delta' (ChunkConfig.action_kinds): what its demos' actions are, and the
    # ``action_kinds`` attribute its bridge writes into a demo buffer; None: all absolute
    action_kinds: tuple[str, ...] | None = None

    def __post_init__(self):
        if self.action_kinds is not None:
            check_action_kinds(self.action_kinds, f"SUITES[{self.name!r}].action_kinds", self.action_dim)

    @property
    def bridge(self) -> str:
        return self.source or f"{self.name}_bridge"


_METAWORLD_COLLECT = (".venv-metaworld/bin/python -m metaworld_bridge.collect --task {task} --episodes {episodes} "
                      "--out {path}")
_METAWORLD_EVALUATE = (".venv-metaworld/bin/python -m metaworld_bridge.evaluate --task {task} --url {url} "
                       "--episodes {episodes} --first-seed {first_seed} --envs {envs} --max-steps {max_steps} "
                       "--out {out}")
SUITES: dict[str, ExternalSuite] = {
    # Meta-World v3 (metaworld_bridge): 39-D observation (hand xyz, gripper opening, objects, previous frame, goal),
    # 4-D action (hand xyz displacement, gripper effort); proprioception = hand xyz + gripper (DP3 used a 9-D
    # agent_pos: hand xyz and both fingertips); campaign episodes of 200 steps, DP3's (results/metaworld/PROTOCOL.md)
    # The hand's displacements are deltas, the gripper effort is absolute: a stride-s action sums s steps of
    # motion (data.windowing.segment_actions).
    "metaworld": ExternalSuite("metaworld", action_dim=4, state_dim=39, proprio_dim=4,
                               setup="bash scripts/setup_metaworld.sh", collect=_METAWORLD_COLLECT,
                               evaluate=_METAWORLD_EVALUATE, eval_max_steps=200,
                               action_kinds=("delta", "delta", "delta", "absolute")),
    # the same tasks with absolute actions: the hand target's xyz (m) and the gripper effort; the bridge turns a
    # target into the displacement that reaches it (at most 1 cm a step), so a chunk executed at a larger stride
    # moves the hand faster, as in the MJX tasks (results/metaworld/diagnosis/)
    "metaworld-target": ExternalSuite("metaworld-target", action_dim=4, state_dim=39, proprio_dim=4,
                                      setup="bash scripts/setup_metaworld.sh",
                                      collect=_METAWORLD_COLLECT + " --action-space target",
                                      evaluate=_METAWORLD_EVALUATE + " --action-space target", eval_max_steps=200,
                                      source="metaworld_bridge", action_space="target",
                                      action_kinds=("absolute",) * 4),
}

# Initial states of evaluations (results/metaworld/PROTOCOL.md): training seed k's main episodes start from
# initial-state seeds EVAL_SEED + 1000 k + i, its periodic (DP3-metric) episodes from PERIODIC_SEED + 1000 k + i.
EVAL_SEED = 1_000_000
PERIODIC_SEED = 2_000_000

_TASK_RE = re.compile(r"^[a-z0-9][a-z0-9_-]*$")


def is_external(name: str) -> bool:
    """Whether ``name`` names a task of an external suite (``<suite>:<task>``)."""
    return ":" in name and name.split(":", 1)[0] in SUITES


def check_name(name: str) -> None:
    """Raise ``ValueError`` naming the problem unless ``name`` is ``<suite>:<task>`` of a known suite."""
    suite, _, task = name.partition(":")
    if suite not in SUITES:
        raise ValueError(f"task: unknown external suite {suite!r} in {name!r}; known: {sorted(SUITES)}")
    if not _TASK_RE.match(task):
        raise ValueError(f"task: {name!r} needs a task name after '{suite}:' (lowercase, digits, '-', '_'), "
                         f"e.g. '{suite}:assembly'")


@dataclasses.dataclass(frozen=True)
class ExternalTask:
    """What training knows of an external task: ``name`` (``metaworld:assembly``), its suite, the suite's task
    name, the action size and the per-frame observation shapes a policy with a given encoder reads (the
    ``action_dim`` / ``obs_shapes`` / ``name`` of an ``MjxEnv``, without the env)."""

    name: str
    suite: ExternalSuite
    task: str
    obs_shapes: dict[str, tuple[int, ...]]

    @property
    def action_dim(self) -> int:
        return self.suite.action_dim

    @property
    def action_kinds(self) -> tuple[str, ...]:
        """Per action dimension 'absolute' or 'delta' (the suite's; ``MjxEnv.action_kinds``)."""
        return self.suite.action_kinds or ("absolute",) * self.action_dim

    @property
    def obs_dtypes(self) -> dict[str, str]:
        """Per-key dtype of the observations a bridge sends (all float32)."""
        return {k: "float32" for k in self.obs_shapes}


def make(name: str, encoder: EncoderConfig = EncoderConfig()) -> ExternalTask:
    """The external task ``name`` as seen by a policy with ``encoder`` (its state and, for point-cloud encoders,
    ``point_cloud`` (num_points, point_dims); images are not provided by any bridge yet)."""
    check_name(name)
    suite_name, _, task = name.partition(":")
    suite = SUITES[suite_name]
    shapes: dict[str, tuple[int, ...]] = {"state": (suite.state_dim,)}
    if encoder.obs_type == "pointcloud":
        shapes["point_cloud"] = (encoder.num_points, encoder.point_dims)
    return ExternalTask(name=name, suite=suite, task=task, obs_shapes=shapes)


def default_data_path(name: str, episodes: int) -> str:
    """``data/<suite>_<task>_<episodes>.zarr`` (where the suite's collect command writes by default); the same
    buffer serves state and point-cloud policies."""
    suite, _, task = name.partition(":")
    return os.path.join("data", f"{suite}_{task}_{episodes}.zarr")


def collect_hint(name: str, episodes: int, path: str) -> str:
    """The commands that make the demos of ``name`` at ``path`` (for error messages)."""
    check_name(name)
    suite_name, _, task = name.partition(":")
    suite = SUITES[suite_name]
    return f"{suite.setup} && {suite.collect.format(task=task, episodes=episodes, path=path)}"


def _base_name(task: str) -> str:
    """``assembly-v3`` → ``assembly`` (a bridge records bare task names)."""
    return re.sub(r"-v\d+$", "", task)


def check_demos(name: str, path: str) -> None:
    """Raise ``ValueError`` when the demo buffer at ``path`` records (root attributes ``source`` = the suite's
    bridge, ``task``, ``action_space``) that it holds demos of another task, or actions of another action space
    (absent: ``delta``), than the suite's. Buffers without these attributes pass (their shapes are still checked
    against the task)."""
    import zarr

    try:
        attrs = dict(zarr.open_group(path, mode="r").attrs)
    except Exception:  # unreadable: ReplayBuffer.load reports it with its own message
        return
    suite, _, task = name.partition(":")
    recorded = attrs.get("task")
    if attrs.get("source") != SUITES[suite].bridge:
        return
    if isinstance(recorded, str) and _base_name(recorded) != _base_name(task):
        raise ValueError(f"data: {path} holds demos of {suite}:{recorded}, not {name}; pass --task "
                         f"{suite}:{recorded} or other --data")
    space = attrs.get("action_space", "delta")
    if space != SUITES[suite].action_space:
        other = [n for n, s in SUITES.items() if s.bridge == SUITES[suite].bridge and s.action_space == space]
        raise ValueError(f"data: {path} holds actions in the {space!r} space, {name} trains on "
                         f"{SUITES[suite].action_space!r} actions; pass "
                         + (f"--task {other[0]}:{task}" if other else "other --data")
                         + " or collect them: " + collect_hint(name, n := len(attrs.get("seeds") or ()) or 10,
                                                               default_data_path(name, n)))
