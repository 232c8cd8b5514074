"""A Meta-World v3 task with reproducible initial states, and its scripted expert.

``MetaWorldTask("assembly")`` builds the goal-observable v3 env (as DP3: the goal is part of the 39-D observation,
and every reset draws a new random object / goal placement). ``reset(seed)`` re-seeds the env's generator before
the reset, so an initial state is a function of its seed alone — the same seed gives the same state in any process
and after any history, so demos, expert checks and (later) every policy column share initial states. (Meta-World's
own ``reset(seed=...)`` ignores the seed, and ``gym.make("Meta-World/MT1", ...)`` picks one of 50 fixed placements
with a generator seeded only at construction.)

Observation (39,) float64: hand xyz, gripper opening (normalised distance of the fingers) — the first 4 features
are the agent's proprioception —, then object poses, the previous frame's 18 features, and the goal xyz.
Action (4,), in one of two spaces (``ACTION_SPACES``):

- ``delta`` (Meta-World's own): xyz displacement of the hand's mocap target and gripper effort, each in [-1, 1]
  (the env clips; the actions recorded here are the clipped ones, i.e. those executed); a displacement of 1 moves
  the target by ``action_scale`` (1 cm).
- ``target``: the hand's mocap target as an absolute xyz position (m, the world frame) and the gripper effort.
  ``step`` turns it into the displacement that reaches it from the current target, clipped to [-1, 1]: the target
  moves at most 1 cm a step towards it, and an unreached target is approached over the next steps. The expert's
  episodes are the same in both spaces; only the recorded action differs (the target after each step). A chunk
  of absolute targets executed at a larger stride moves the hand faster (up to that bound), as in the MJX tasks; a
  chunk of displacements does not. The bound is an option of executing targets: ``move_limit`` (in ``action_scale``
  units; 1 = 1 cm a step, the default; s gives a stride-s chunk the headroom of s steps) and ``move_clip``
  (``axis``: clip each axis, the default and Meta-World's own; ``direction``: scale the move, keeping its
  direction). The scripted expert and the demos always run at Meta-World's own bound.

Episodes are truncated at 500 control steps (12.5 ms of simulation each).

**Execution semantics** (``execute``, ``SEMANTICS``): ``rate`` gives each policy action one control step;
``waypoint`` (HiPolicy's release, where each action is a target the controller runs to) holds each action's target
— absolute, or for a displacement the mocap target when the action starts + delta x ``action_scale``, summed or not
— until the mocap target has travelled there (at the move bound, 1 cm a step for displacements) and the hand is
within ``tolerance`` of it, or ``waypoint_steps`` x stride control steps ran. The policy sees one observation per
action. **Waypoints, measured** (10 tasks: basketball, assembly, shelf-place, bin-picking, hand-insert, stick-push,
coffee-pull, pick-out-of-hole, pick-place-wall, coffee-push; the expert's own episodes, seed 0): at rest the hand
(observation[:3]) sits 3.7-4.1 mm from its mocap target; while the expert moves it, it trails by a median 2.6-4.0
cm per task (90th percentile 3.3-8.0 cm; over 3 seeds of all 10 tasks: median 3.3, p90 5.0, p99 7.1, max 10.1 cm);
from rest, a target 1 / 2 / 3 / 5 cm away is within 1 cm after 2 / 5 / 6 / 8 control steps. The scripted experts
rely on that lag (the gripper closes while the hand still travels): held to a tighter tolerance the hand stops
short of where the expert's timing expects it. The expert chunked on summed displacements under ``waypoint`` (3
seeds x 10 tasks, 500 steps; successes at strides 1 / 2 / 3): tolerance 1 cm 19 / 22 / 23 of 30, 2 cm 24 / 24 / 24,
3 cm 30 / 27 / 25, 4 cm 30 / 29 / 24; at 4 cm stride 1 takes 99 control steps a mean episode, about the demos'
own, and the bound cut at most 1 % of a task's actions at stride 1 (none on 9 tasks; at strides 2-3 up to 24 % on
3 tasks); a bound of 3 or 5 steps x stride gave the same successes (2-3 cm). Hence the defaults: 4 cm
(``WAYPOINT_TOLERANCE``), 5 steps x stride (``WAYPOINT_STEPS``).

``run_expert(seed, camera)`` runs the task's scripted expert (``metaworld.policies.ENV_POLICY_MAP``) until its
first success (``info["success"]``) or the step limit and returns the episode's frames: the observation (and point
cloud) before each action, cut at the success step, as the MJX tasks' demos.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import io
import typing
import warnings

import mujoco
import numpy as np

from metaworld_bridge.tasks import env_name

OBS_DIM = 39
ACTION_DIM = 4
PROPRIO_DIM = 4  # hand xyz + gripper opening (DP3's agent_pos is 9-D: hand xyz + both fingertips' xyz)
MAX_STEPS = 500
ACTION_SPACES = ("delta", "target")
# How a ``target`` action's move is bounded per control step (the limit in units of ``action_scale``, 1 cm):
# ``axis`` clips each axis on its own (Meta-World's own clip: a far target bends the path towards the diagonal);
# ``direction`` scales the whole move so its largest axis is within the limit (the path points at the target).
MOVE_CLIPS = ("axis", "direction")
# How an action is executed (``MetaWorldTask.execute``): ``rate``, one control step per action; ``waypoint``, the
# action is a target held until the hand reaches it (within ``tolerance``) or a bound of control steps.
SEMANTICS = ("rate", "waypoint")
# Per action dimension, what a policy's action means: ``absolute`` (a target or an effort) or ``delta`` (a
# displacement; a stride-s action of a policy trained on summed deltas carries the sum of s recorded ones). The demo
# buffer's ``action_kinds`` attribute and the policy server's metadata carry one per dimension.
ACTION_KINDS = ("absolute", "delta")
KINDS_OF_SPACE = {"delta": ("delta", "delta", "delta", "absolute"), "target": ("absolute",) * 4}
# Waypoint defaults, chosen from the hand's lag measured on expert episodes (the module docstring, "Waypoints"): the
# hand counts as at its target within the distance it trails its mocap target at the demos' speed; the bound is
# ``WAYPOINT_STEPS`` control steps x the decision's stride.
WAYPOINT_TOLERANCE = 0.04
WAYPOINT_STEPS = 5
# the project's task-name prefix of a policy trained on each action space (``metaworld:assembly``,
# ``metaworld-target:assembly``; hipolicy_jax.envs.external.SUITES)
SUITE_OF_SPACE = {"delta": "metaworld", "target": "metaworld-target"}
_SIM_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # everything mj_step advances (qpos, qvel, act, mocap, warmstart, ...)
_ENV_STATE = ("curr_path_length", "_prev_obs", "_last_stable_obs")  # what the env carries between steps
_MOCAP_EPS = 1e-6  # m: the mocap target is at a waypoint (it moves there exactly, up to float32 rounding)
_CLIP_EPS = 1e-4  # a move counts as clipped beyond the bound + this (float32 targets round by ~1e-5 of 1 cm)


def _import_metaworld():
    """metaworld's env dict and expert policies (its import prints gymnasium registration noise: silenced)."""
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.simplefilter("ignore")
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE
        from metaworld.policies import ENV_POLICY_MAP
    return ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE, ENV_POLICY_MAP


def available_tasks() -> tuple[str, ...]:
    """Task names with a v3 env and a scripted expert (``assembly``, ``basketball``, ...)."""
    envs, policies = _import_metaworld()
    return tuple(sorted(name[: -len("-v3")] for name in policies
                        if name.endswith("-v3") and f"{name}-goal-observable" in envs))


@dataclasses.dataclass
class Episode:
    """One expert episode: ``frames`` {key: (T, ...)} (``state`` (T, 39) float32, ``action`` (T, 4) float32, and
    ``point_cloud`` (T, P, 3) float32 when a camera was given), ``success``, ``steps`` (control steps until the
    first success or the step limit: physical time; = T for ``run_expert``) and its ``seed``; ``decisions`` (the
    expert's chunks; ``run_expert``: one per step), ``actions`` (actions executed), ``clipped`` and ``unreached``
    (actions, as ``MetaWorldTask.execute`` reports them)."""

    frames: dict[str, np.ndarray]
    success: bool
    steps: int
    seed: int
    decisions: int = 0
    actions: int = 0
    clipped: int = 0
    unreached: int = 0


class Executed(typing.NamedTuple):
    """What ``MetaWorldTask.execute`` did with one action: ``obs`` (39,) float64 after it, ``success``,
    ``truncated`` (the step limit came), ``control_steps`` (>= 1: physical time, 12.5 ms of simulation each),
    ``clipped`` (rate: the per-step bound cut the move), ``unreached`` (waypoint: the bound of control steps came
    before the target was reached — the mocap target there and the hand within the tolerance)."""

    obs: np.ndarray
    success: bool
    truncated: bool
    control_steps: int
    clipped: bool
    unreached: bool


class MetaWorldTask:
    """One Meta-World v3 task (goal observable) with seeded resets and its scripted expert."""

    def __init__(self, task: str, max_steps: int = MAX_STEPS, action_space: str = "delta", move_limit: float = 1.0,
                 move_clip: str = "axis"):
        envs, policies = _import_metaworld()
        name = env_name(task)
        key = f"{name}-goal-observable"
        if key not in envs or name not in policies:
            raise ValueError(f"task: no Meta-World v3 task {task!r} with a scripted expert; known: "
                             f"{', '.join(available_tasks())}")
        if action_space not in ACTION_SPACES:
            raise ValueError(f"action_space: one of {', '.join(ACTION_SPACES)}, got {action_space!r}")
        if not 1 <= max_steps <= MAX_STEPS:
            raise ValueError(f"max_steps: must be in [1, {MAX_STEPS}] (Meta-World's limit), got {max_steps}")
        self.check_move(action_space, move_limit, move_clip)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.env = envs[key]()
        # the experts warn "Constant(s) may be too high. Environments clip response to [-1, 1]" (they are clipped)
        warnings.filterwarnings("ignore", message="Constant", category=UserWarning, module="metaworld.policies")
        # fresh random placements on every reset, drawn from the env's own (seedable) generator
        self.env._freeze_rand_vec = False
        self.env.seeded_rand_vec = True
        self.expert = policies[name]()
        self.task, self.name, self.max_steps, self.action_space = task, name, max_steps, action_space
        self.move_limit, self.move_clip = float(move_limit), move_clip
        self._obs: np.ndarray | None = None

    @staticmethod
    def check_move(action_space: str, move_limit: float, move_clip: str) -> None:
        """``ValueError`` naming the option unless ``move_limit`` / ``move_clip`` are valid for ``action_space``."""
        if move_clip not in MOVE_CLIPS:
            raise ValueError(f"move_clip: one of {', '.join(MOVE_CLIPS)}, got {move_clip!r}")
        if not (np.isfinite(move_limit) and move_limit > 0):
            raise ValueError(f"move_limit: must be > 0 (units of 1 cm a step), got {move_limit}")
        if action_space == "delta" and (move_limit != 1.0 or move_clip != "axis"):
            raise ValueError(f"move_limit / move_clip: bound the moves of absolute targets (action_space 'target'); "
                             f"displacements are Meta-World's own, got move_limit={move_limit}, "
                             f"move_clip={move_clip!r} with action_space 'delta'")

    @property
    def model(self) -> mujoco.MjModel:
        return self.env.model

    @property
    def data(self) -> mujoco.MjData:
        return self.env.data

    def reset(self, seed: int) -> np.ndarray:
        """Reset to the initial state of ``seed`` → observation (39,) float64."""
        self.env.seed(int(seed))
        obs, _ = self.env.reset()
        # geom poses of the current qpos (a reset may end with mj_step, whose kinematics lag one step behind);
        # kinematics only: the next step recomputes everything, so the dynamics are unchanged
        mujoco.mj_kinematics(self.model, self.data)
        self._obs = obs
        return obs

    def step(self, action: np.ndarray) -> tuple[np.ndarray, bool, bool]:
        """Apply ``action`` (4,) of the task's action space for one control step → (observation, success,
        truncated)."""
        action = np.asarray(action, np.float64)
        if self.action_space != "target":
            return self._step_delta(action)
        return self._step_target(action, self.move_limit, self.move_clip)[:3]

    def _step_target(self, action: np.ndarray, move_limit: float, move_clip: str
                     ) -> tuple[np.ndarray, bool, bool, bool]:
        """One control step towards the absolute target ``action`` (4,: xyz m, gripper effort), the move bounded by
        ``move_limit`` (cm) and ``move_clip`` → (observation, success, truncated, whether the bound cut the move)."""
        # the move to the target in units of the limit; Meta-World clips each axis to [-1, 1] of its action_scale,
        # which is the limit while the step runs
        move = (action[:3] - self.data.mocap_pos[0]) / (self.env.action_scale * move_limit)
        cut = bool(np.abs(move).max() > 1.0 + _CLIP_EPS)
        if move_clip == "direction":
            move = move * min(1.0, 1.0 / max(float(np.abs(move).max()), 1e-12))
        base = self.env.action_scale
        self.env.action_scale = base * move_limit
        try:
            return (*self._step_delta(np.concatenate([move, action[3:]])), cut)
        finally:
            self.env.action_scale = base

    @staticmethod
    def check_semantics(semantics: str, tolerance: float = WAYPOINT_TOLERANCE,
                        waypoint_steps: int = WAYPOINT_STEPS) -> None:
        """``ValueError`` naming the option unless the execution settings are valid (``SEMANTICS``; a tolerance
        > 0 m; a bound of >= 1 control steps per action and unit of stride)."""
        if semantics not in SEMANTICS:
            raise ValueError(f"semantics: one of {', '.join(SEMANTICS)}, got {semantics!r}")
        if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float, np.integer, np.floating)) or not (
                np.isfinite(tolerance) and tolerance > 0):
            raise ValueError(f"waypoint_tolerance: must be > 0 (metres of the hand from its target), got {tolerance}")
        if isinstance(waypoint_steps, bool) or not isinstance(waypoint_steps, (int, np.integer)) or waypoint_steps < 1:
            raise ValueError(f"waypoint_steps: must be an integer >= 1 (control steps per action and unit of "
                             f"stride), got {waypoint_steps}")

    def waypoint_target(self, action: np.ndarray) -> np.ndarray:
        """The absolute target (4,: xyz m, gripper effort) that ``action`` (4,) of the task's action space stands
        for under ``waypoint``, now: a ``target`` action itself, a ``delta`` action (summed or not) the mocap target
        + delta * ``action_scale`` (not clipped to [-1, 1]); xyz clipped to the mocap's workspace, where the hand
        can go."""
        action = np.asarray(action, np.float64)
        pos = action[:3] if self.action_space == "target" else (self.data.mocap_pos[0]
                                                                + action[:3] * self.env.action_scale)
        return np.concatenate([np.clip(pos, self.env.mocap_low, self.env.mocap_high), action[3:]])

    def execute(self, action: np.ndarray, semantics: str = "rate", stride: int = 1,
                tolerance: float = WAYPOINT_TOLERANCE, waypoint_steps: int = WAYPOINT_STEPS) -> Executed:
        """Execute one policy action (4,) of the task's action space, decided at ``stride``, under ``semantics``
        → ``Executed`` (the observation after it, success, truncated, control steps taken, clipped, unreached).

        - ``rate``: one control step (``step``). ``clipped``: the per-step bound cut the move (a displacement
          beyond [-1, 1] that Meta-World clips, e.g. a summed delta; a target further than ``move_limit``).
        - ``waypoint``: the action's target (``waypoint_target``, fixed when the action starts) is given to the
          controller every control step — the target→displacement conversion repeated, at the task's move bound
          (Meta-World's own for displacements), so the hand's mocap target travels to it — until it has arrived
          there and the hand (observation[:3]) is within ``tolerance`` m of it, or ``waypoint_steps * stride``
          control steps ran (``unreached``), or the episode ended (success, or the step limit: the limit counts
          control steps under both semantics). The first control step is the one ``rate`` takes, so with targets
          reached in one step (within the move bound and the tolerance) both semantics are the same, step for
          step. Requiring the mocap's arrival keeps a move beyond the bound (a summed delta) whole: the hand alone
          could be within the tolerance before the target had travelled the whole way.
        """
        if semantics == "rate":
            action = np.asarray(action, np.float64)
            if self.action_space == "target":
                obs, success, truncated, cut = self._step_target(action, self.move_limit, self.move_clip)
            else:
                cut = bool(np.abs(action[:3]).max() > 1.0 + _CLIP_EPS)
                obs, success, truncated = self._step_delta(action)
            return Executed(obs, success, truncated, 1, cut, False)
        self.check_semantics(semantics, tolerance, waypoint_steps)
        if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
            raise ValueError(f"stride: must be an integer >= 1, got {stride}")
        target = self.waypoint_target(action)
        obs, success, truncated = self.step(action)  # the control step rate takes
        steps, bound = 1, int(waypoint_steps) * int(stride)
        limit, clip = (self.move_limit, self.move_clip) if self.action_space == "target" else (1.0, "axis")

        def arrived(obs: np.ndarray) -> bool:
            return bool(np.abs(self.data.mocap_pos[0] - target[:3]).max() <= _MOCAP_EPS
                        and np.linalg.norm(obs[:3] - target[:3]) <= tolerance)

        while not (success or truncated or arrived(obs)) and steps < bound:
            obs, success, truncated, _ = self._step_target(target, limit, clip)
            steps += 1
        return Executed(obs, success, truncated, steps, False, not (success or truncated or arrived(obs)))

    def _step_delta(self, action: np.ndarray) -> tuple[np.ndarray, bool, bool]:
        """Apply a ``delta`` action (4,), clipped to [-1, 1]."""
        obs, _, _, truncated, info = self.env.step(np.clip(np.asarray(action, np.float64), -1.0, 1.0))
        self._obs = obs
        return obs, bool(info["success"]), bool(truncated) or self.env.curr_path_length >= self.max_steps

    def to_delta(self, target: np.ndarray) -> np.ndarray:
        """A ``target`` action (4,) → the ``delta`` action that moves the mocap target to it now (unclipped)."""
        target = np.asarray(target, np.float64)
        return np.concatenate([(target[:3] - self.data.mocap_pos[0]) / self.env.action_scale, target[3:]])

    def to_target(self, delta: np.ndarray) -> np.ndarray:
        """A ``delta`` action (4,) → the ``target`` action it amounts to now: where it puts the mocap target (the
        env's clipping to [-1, 1] and to its workspace applied), and the gripper effort."""
        delta = np.clip(np.asarray(delta, np.float64), -1.0, 1.0)
        pos = np.clip(self.data.mocap_pos[0] + delta[:3] * self.env.action_scale, self.env.mocap_low,
                      self.env.mocap_high)
        return np.concatenate([pos, delta[3:]])

    def expert_action(self, obs: np.ndarray) -> np.ndarray:
        """The scripted expert's action for ``obs``, clipped to [-1, 1] (what the env executes), float32."""
        return np.clip(self.expert.get_action(obs), -1.0, 1.0).astype(np.float32)

    def snapshot(self):
        """The simulation and the env's step-to-step state, for ``restore``."""
        state = np.empty(mujoco.mj_stateSize(self.model, _SIM_STATE))
        mujoco.mj_getState(self.model, self.data, state, _SIM_STATE)
        return state, {k: copy.deepcopy(getattr(self.env, k)) for k in _ENV_STATE}, self._obs

    def restore(self, snapshot) -> None:
        """Back to a ``snapshot`` (then the same actions give the same episode)."""
        state, attrs, obs = snapshot
        mujoco.mj_setState(self.model, self.data, state, _SIM_STATE)
        mujoco.mj_kinematics(self.model, self.data)  # as after a reset: poses of the restored qpos
        for k, v in attrs.items():
            setattr(self.env, k, copy.deepcopy(v))
        self._obs = obs

    def run_strided_expert(self, seed: int, stride: int, chunk_len: int = 8, *, summed_deltas: bool = False,
                           semantics: str = "rate", tolerance: float = WAYPOINT_TOLERANCE,
                           waypoint_steps: int = WAYPOINT_STEPS) -> Episode:
        """The expert executed as a chunking policy at ``stride``, from the initial state of ``seed``: at each
        decision the expert runs ``chunk_len * stride`` steps ahead in the simulator (then restored), its actions
        are cut into blocks of ``stride`` and each block gives one action in the task's action space, ``chunk_len``
        of them, executed by ``execute`` under ``semantics``; closed loop (the next decision starts from where the
        executed chunk led). A block's action is its last one (every ``stride``-th: right for absolute targets and
        the gripper), or, with ``summed_deltas`` (displacements only), the sum of its ``stride`` xyz displacements
        and its last gripper effort (the motion of the whole block, as a policy trained on summed deltas predicts;
        a last block cut short by the expert's success ahead sums what there is). Stride 1 replays ``run_expert``'s
        episode under ``rate``. ``frames["action"]`` (A, 4) float32 holds the executed actions; ``steps`` counts
        control steps (physical time), ``actions`` = A, ``decisions`` the chunks; ``clipped`` / ``unreached`` count
        actions as ``execute`` reports them."""
        if stride < 1 or chunk_len < 1:
            raise ValueError(f"stride, chunk_len: must be >= 1, got {stride}, {chunk_len}")
        if summed_deltas and self.action_space != "delta":
            raise ValueError(f"summed_deltas: sums displacement actions (action_space 'delta'); absolute targets are "
                             f"sampled, got action_space {self.action_space!r}")
        self.check_semantics(semantics, tolerance, waypoint_steps)
        obs = self.reset(seed)
        executed, success, truncated = [], False, False
        control_steps = decisions = clipped = unreached = 0
        while not (success or truncated):
            snap, plan, ahead = self.snapshot(), [], obs
            for _ in range(chunk_len * stride):
                action = self.expert_action(ahead)
                plan.append(action if self.action_space == "delta" else self.to_target(action).astype(np.float32))
                ahead, done, end = self._step_delta(action)
                if done or end:
                    break
            self.restore(snap)
            if summed_deltas:
                blocks = [np.stack(plan[i:i + stride]) for i in range(0, len(plan), stride)]
                chunk = [np.concatenate([b[:, :3].sum(0, dtype=np.float64), b[-1, 3:]]).astype(np.float32)
                         for b in blocks]
            else:
                chunk = plan[stride - 1::stride] or plan[-1:]  # the last step ahead when the expert finished sooner
            decisions += 1
            for action in chunk[:chunk_len]:
                executed.append(action)
                done = self.execute(action, semantics, stride, tolerance, waypoint_steps)
                obs, success, truncated = done.obs, done.success, done.truncated
                control_steps += done.control_steps
                clipped += done.clipped
                unreached += done.unreached
                if success or truncated:
                    break
        return Episode(frames={"action": np.stack(executed)}, success=success, steps=control_steps, seed=int(seed),
                       decisions=decisions, actions=len(executed), clipped=clipped, unreached=unreached)

    def run_expert(self, seed: int, camera=None) -> Episode:
        """The expert's episode from the initial state of ``seed``; ``camera`` (a ``PointCloudCamera`` of this
        task's model) adds a ``point_cloud`` per frame. The actions are recorded in the task's action space (the
        episode itself is the same in both)."""
        obs = self.reset(seed)
        states, actions, clouds = [], [], []
        success = False
        for _ in range(self.max_steps):
            action = self.expert_action(obs)
            states.append(obs.astype(np.float32))
            actions.append(action if self.action_space == "delta" else self.to_target(action).astype(np.float32))
            if camera is not None:
                clouds.append(camera(self.model, self.data))
            obs, success, truncated = self._step_delta(action)
            if success or truncated:
                break
        frames = {"state": np.stack(states), "action": np.stack(actions)}
        if camera is not None:
            frames["point_cloud"] = np.stack(clouds)
        return Episode(frames=frames, success=success, steps=len(actions), seed=int(seed), decisions=len(actions),
                       actions=len(actions))
