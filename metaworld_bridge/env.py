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

Episodes are truncated at 500 steps.

``run_expert(seed, camera)`` runs the task's scripted expert (``metaworld.policies.ENV_POLICY_MAP``) until its
first success (``info["success"]``) or the step limit and returns the episode's frames: the observation (and point
cloud) before each action, cut at the success step, as the MJX tasks' demos.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import io
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
# the project's task-name prefix of a policy trained on each action space (``metaworld:assembly``,
# ``metaworld-target:assembly``; hipolicy_jax.envs.external.SUITES)
SUITE_OF_SPACE = {"delta": "metaworld", "target": "metaworld-target"}
_SIM_STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # everything mj_step advances (qpos, qvel, act, mocap, warmstart, ...)
_ENV_STATE = ("curr_path_length", "_prev_obs", "_last_stable_obs")  # what the env carries between steps


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
    ``point_cloud`` (T, P, 3) float32 when a camera was given), ``success``, ``steps`` (= T: control steps until
    the first success, or the step limit) and its ``seed``."""

    frames: dict[str, np.ndarray]
    success: bool
    steps: int
    seed: int


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
        """Apply ``action`` (4,) of the task's action space → (observation, success, truncated)."""
        action = np.asarray(action, np.float64)
        if self.action_space != "target":
            return self._step_delta(action)
        # the move to the target in units of the limit; Meta-World clips each axis to [-1, 1] of its action_scale,
        # which is the limit while the step runs
        move = (action[:3] - self.data.mocap_pos[0]) / (self.env.action_scale * self.move_limit)
        if self.move_clip == "direction":
            move = move * min(1.0, 1.0 / max(float(np.abs(move).max()), 1e-12))
        base = self.env.action_scale
        self.env.action_scale = base * self.move_limit
        try:
            return self._step_delta(np.concatenate([move, action[3:]]))
        finally:
            self.env.action_scale = base

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

    def run_strided_expert(self, seed: int, stride: int, chunk_len: int = 8) -> Episode:
        """The expert executed as a chunking policy at ``stride``, from the initial state of ``seed``: at each
        decision the expert runs ``chunk_len * stride`` steps ahead in the simulator (then restored) and every
        ``stride``-th of its actions, in the task's action space, is executed, ``chunk_len`` of them; closed loop
        (the next decision starts from where the executed chunk led). Stride 1 replays ``run_expert``'s episode; a
        larger stride is the expert sped up as HiPolicy's stride-s segments would be. ``frames`` holds the
        executed actions."""
        if stride < 1 or chunk_len < 1:
            raise ValueError(f"stride, chunk_len: must be >= 1, got {stride}, {chunk_len}")
        obs = self.reset(seed)
        executed, success = [], False
        while not success and len(executed) < self.max_steps:
            snap, plan, ahead = self.snapshot(), [], obs
            for _ in range(chunk_len * stride):
                action = self.expert_action(ahead)
                plan.append(action if self.action_space == "delta" else self.to_target(action).astype(np.float32))
                ahead, done, truncated = self._step_delta(action)
                if done or truncated:
                    break
            self.restore(snap)
            chunk = plan[stride - 1::stride] or plan[-1:]  # the last step ahead when the expert finished sooner
            truncated = False
            for action in chunk[:chunk_len]:
                executed.append(action)
                obs, success, truncated = self.step(action)
                if success or truncated:
                    break
            if truncated:
                break
        return Episode(frames={"action": np.stack(executed)}, success=success, steps=len(executed), seed=int(seed))

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
        return Episode(frames=frames, success=success, steps=len(actions), seed=int(seed))
