"""A Meta-World v3 task with reproducible initial states, and its scripted expert.

``MetaWorldTask("assembly")`` builds the goal-observable v3 env (as DP3: the goal is part of the 39-D observation,
and every reset draws a new random object / goal placement). ``reset(seed)`` re-seeds the env's generator before
the reset, so an initial state is a function of its seed alone — the same seed gives the same state in any process
and after any history, so demos, expert checks and (later) every policy column share initial states. (Meta-World's
own ``reset(seed=...)`` ignores the seed, and ``gym.make("Meta-World/MT1", ...)`` picks one of 50 fixed placements
with a generator seeded only at construction.)

Observation (39,) float64: hand xyz, gripper opening (normalised distance of the fingers) — the first 4 features
are the agent's proprioception —, then object poses, the previous frame's 18 features, and the goal xyz.
Action (4,): xyz displacement of the hand's mocap target and gripper effort, each in [-1, 1] (the env clips; the
actions recorded here are the clipped ones, i.e. those executed). Episodes are truncated at 500 steps.

``run_expert(seed, camera)`` runs the task's scripted expert (``metaworld.policies.ENV_POLICY_MAP``) until its
first success (``info["success"]``) or the step limit and returns the episode's frames: the observation (and point
cloud) before each action, cut at the success step, as the MJX tasks' demos.
"""

from __future__ import annotations

import contextlib
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

    def __init__(self, task: str, max_steps: int = MAX_STEPS):
        envs, policies = _import_metaworld()
        name = env_name(task)
        key = f"{name}-goal-observable"
        if key not in envs or name not in policies:
            raise ValueError(f"task: no Meta-World v3 task {task!r} with a scripted expert; known: "
                             f"{', '.join(available_tasks())}")
        if not 1 <= max_steps <= MAX_STEPS:
            raise ValueError(f"max_steps: must be in [1, {MAX_STEPS}] (Meta-World's limit), got {max_steps}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.env = envs[key]()
        # the experts warn "Constant(s) may be too high. Environments clip response to [-1, 1]" (they are clipped)
        warnings.filterwarnings("ignore", message="Constant", category=UserWarning, module="metaworld.policies")
        # fresh random placements on every reset, drawn from the env's own (seedable) generator
        self.env._freeze_rand_vec = False
        self.env.seeded_rand_vec = True
        self.expert = policies[name]()
        self.task, self.name, self.max_steps = task, name, max_steps
        self._obs: np.ndarray | None = None

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
        """Apply ``action`` (4,) (clipped to [-1, 1]) → (observation, success, truncated)."""
        obs, _, _, truncated, info = self.env.step(np.clip(np.asarray(action, np.float64), -1.0, 1.0))
        self._obs = obs
        return obs, bool(info["success"]), bool(truncated) or self.env.curr_path_length >= self.max_steps

    def expert_action(self, obs: np.ndarray) -> np.ndarray:
        """The scripted expert's action for ``obs``, clipped to [-1, 1] (what the env executes), float32."""
        return np.clip(self.expert.get_action(obs), -1.0, 1.0).astype(np.float32)

    def run_expert(self, seed: int, camera=None) -> Episode:
        """The expert's episode from the initial state of ``seed``; ``camera`` (a ``PointCloudCamera`` of this
        task's model) adds a ``point_cloud`` per frame."""
        obs = self.reset(seed)
        states, actions, clouds = [], [], []
        success = False
        for _ in range(self.max_steps):
            action = self.expert_action(obs)
            states.append(obs.astype(np.float32))
            actions.append(action)
            if camera is not None:
                clouds.append(camera(self.model, self.data))
            obs, success, truncated = self.step(action)
            if success or truncated:
                break
        frames = {"state": np.stack(states), "action": np.stack(actions)}
        if camera is not None:
            frames["point_cloud"] = np.stack(clouds)
        return Episode(frames=frames, success=success, steps=len(actions), seed=int(seed))
