"""Shared base for the MJX task suite: ``State``, the ``MjxEnv`` API and the scripted-expert plan machinery.

API (MuJoCo Playground style, written for ONE instance; batch with ``jax.vmap`` at the call site)::

    env = make("press_button")
    state = env.reset(key)                 # State
    state = env.step(state, action)        # action (4,) float32 = absolute TCP target (x, y, z) + gripper command

The robot (``assets/common.xml``) is a floating parallel gripper: a hand body on three slide joints whose origin is
the tool-centre point (TCP), and two capsule fingers on slide joints. Position actuators track the action, so the
action is an absolute end-effector target; a chunk executed at a larger stride (targets further apart) at the same
control rate therefore moves the hand faster. The gripper command g in [0, 1] maps to a finger half-opening
``FINGER_OPEN * (1 - g)`` (0 = open, 1 = closed); the finger actuators have a bounded force, so closing on an object
squeezes it with at most that force and the object is held by friction alone.

One control step (``control_dt``, 10 Hz by default) runs ``n_substeps`` physics steps in ``lax.scan``.

Observations (``State.obs``)::

    state        (D,)        float32   TCP xyz, gripper opening (m) (the first PROPRIO_DIM = 4: proprioception), then
                                       task-specific object poses / joint angles
    image        (H, W, 3)   uint8     optional, jitted ray-cast camera (see camera.py)
    depth        (H, W)      float32   optional
    point_cloud  (P, 3|6)    float32   optional

Scripted experts are time-indexed waypoint state machines (``ExpertPlan``): a plan is drawn from the first
observation and a key (randomised speed, pauses, waypoint noise and a small smooth wobble); ``expert_action(plan,
t)`` is the action at (possibly fractional) control step t. Plans are pure arrays, so experts run batched under vmap.
"""

from __future__ import annotations

import contextlib
import io
import os
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct
# mujoco.mjx prints "Failed to import warp / mujoco_warp" when its optional GPU backend (NVIDIA Warp) is absent;
# this project never uses that backend, so the import runs with stdout silenced
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx

ASSETS_DIR = os.path.join(os.path.dirname(__file__), "assets")

FINGER_OPEN = 0.045  # finger half-opening (m) at gripper command 0; joint range is [0, FINGER_OPEN]
FINGER_RADIUS = 0.008  # capsule radius of the fingers (m)
FINGER_BOTTOM = 0.018  # lowest point of the fingers below the TCP (m)
ACTION_DIM = 4
PROPRIO_DIM = 4  # leading features of the state observation that are proprioception (TCP xyz, gripper opening)


@struct.dataclass
class State:
    """Environment state of one episode (every leaf is an array; batch with vmap).

    data: mjx.Data of the physics. obs: dict of observations (see module docstring). reward () float32,
    done () bool (success or step limit), success () bool (sticky), step () int32 control steps taken.
    info: task bookkeeping; always holds ``rng`` (a PRNG key advanced every step, used by stochastic observation
    parts such as point-cloud sub-sampling) plus task-specific hidden variables (e.g. the button's hold counter).
    """

    data: mjx.Data
    obs: dict[str, jax.Array]
    reward: jax.Array
    done: jax.Array
    success: jax.Array
    step: jax.Array
    info: dict[str, Any]


@struct.dataclass
class ExpertPlan:
    """A scripted expert's plan for one episode.

    waypoints: (K, 4) points in the task's plan space (cartesian TCP + gripper for most tasks).
    times: (K,) float32 control step at which each waypoint is reached (ascending, times[0] = 0); between waypoints
      the plan moves along a minimum-jerk profile (rest to rest). A repeated waypoint is a pause.
    params: (P,) float32 task-specific constants of the plan space (e.g. the door hinge position).
    wobble: (3, 3) float32 rows (amplitude, angular frequency per step, phase) of a smooth xyz wobble.
    """

    waypoints: jax.Array
    times: jax.Array
    params: jax.Array
    wobble: jax.Array


def min_jerk(u: jax.Array) -> jax.Array:
    """Minimum-jerk time scaling s(u) = 10u^3 - 15u^4 + 6u^5 on u clipped to [0, 1]."""
    u = jnp.clip(u, 0.0, 1.0)
    return u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)


def interp_plan(plan: ExpertPlan, t: jax.Array) -> jax.Array:
    """Plan-space point (4,) at control step ``t`` (scalar, may be fractional); holds the last waypoint after."""
    times, wps = plan.times, plan.waypoints
    k = jnp.clip(jnp.searchsorted(times, t, side="right"), 1, times.shape[0] - 1)
    t0, t1 = times[k - 1], times[k]
    s = min_jerk((t - t0) / jnp.maximum(t1 - t0, 1e-6))
    return wps[k - 1] + s * (wps[k] - wps[k - 1])


def plan_from_segments(start: jax.Array, segments: list[tuple[jax.Array, jax.Array]], params=None,
                       wobble=None) -> ExpertPlan:
    """Build an ``ExpertPlan`` from a start point (4,) and a list of (waypoint (4,), duration in steps ())."""
    wps = jnp.stack([start] + [w for w, _ in segments]).astype(jnp.float32)
    durs = jnp.stack([jnp.asarray(d, jnp.float32) for _, d in segments])
    times = jnp.concatenate([jnp.zeros((1,), jnp.float32), jnp.cumsum(jnp.maximum(durs, 1e-3))])
    params = jnp.zeros((1,), jnp.float32) if params is None else jnp.asarray(params, jnp.float32)
    wobble = jnp.zeros((3, 3), jnp.float32) if wobble is None else wobble
    return ExpertPlan(waypoints=wps, times=times, params=params, wobble=wobble)


def sample_wobble(key: jax.Array, amplitude: float) -> jax.Array:
    """Random smooth wobble (3, 3): per axis amplitude in [0.5, 1]·amplitude, 0.3–0.9 rad/step, random phase."""
    ka, kf, kp = jax.random.split(key, 3)
    amp = amplitude * jax.random.uniform(ka, (3,), minval=0.5, maxval=1.0)
    freq = jax.random.uniform(kf, (3,), minval=0.3, maxval=0.9)
    phase = jax.random.uniform(kp, (3,), minval=0.0, maxval=2 * jnp.pi)
    return jnp.stack([amp, freq, phase], axis=1)


def move_steps(key: jax.Array, dist: jax.Array, control_dt: float, speed=(0.12, 0.2), min_time: float = 0.5):
    """Duration in control steps of a point-to-point move of ``dist`` metres at a random mean speed (m/s)."""
    v = jax.random.uniform(key, (), minval=speed[0], maxval=speed[1])
    return jnp.maximum(dist / v, min_time) / control_dt


def uniform(key, low, high, shape=()):
    """``jax.random.uniform`` with a short name and array bounds."""
    return jax.random.uniform(key, shape, minval=jnp.asarray(low, jnp.float32), maxval=jnp.asarray(high, jnp.float32))


def yaw_quat(yaw: jax.Array) -> jax.Array:
    """Quaternion (4,) wxyz of a rotation by ``yaw`` about z."""
    return jnp.stack([jnp.cos(yaw / 2), jnp.zeros(()), jnp.zeros(()), jnp.sin(yaw / 2)])


def sample_separated_xy(key: jax.Array, n: int, low, high, min_dist: float, tries: int = 16) -> jax.Array:
    """``n`` points (n, 2) uniform in the box [low, high]² with pairwise distance >= ``min_dist`` (rejection
    sampling over ``tries`` candidate sets; the best candidate is used if none satisfies it)."""
    cands = jax.random.uniform(key, (tries, n, 2), minval=jnp.asarray(low), maxval=jnp.asarray(high))
    d = jnp.linalg.norm(cands[:, :, None] - cands[:, None, :], axis=-1) + jnp.eye(n) * 1e3
    closest = d.min(axis=(1, 2))
    ok = closest >= min_dist
    idx = jnp.where(ok.any(), jnp.argmax(ok), jnp.argmax(closest))
    return cands[idx]


class MjxEnv:
    """Base class of every task. Holds only the fixed model and configuration; all state lives in ``State``.

    Subclasses set ``xml_file``, ``task_state_dim`` and ``default_max_steps`` and implement ``_sample_init``,
    ``_task_update``, ``_task_state`` and ``expert_plan`` (plus optionally ``_applied_force`` and
    ``_plan_to_action``).
    """

    xml_file: str = ""
    task_state_dim: int = 0
    default_max_steps: int = 200
    # TCP workspace (x, y, z) low / high; actions are clipped to it.
    workspace_low = (-0.35, -0.35, FINGER_BOTTOM + 0.002)
    workspace_high = (0.35, 0.35, 0.35)
    # Bodies (children of the world) whose position is randomised per episode. MJX does not move the children of
    # mocap bodies, so placements are episode-specific ``body_pos`` values kept in ``info['body_pos']`` (n, 3) and
    # written into the model used by that episode (``episode_model``).
    randomised_bodies: tuple[str, ...] = ()
    # ``waypoint`` execution (``InferenceConfig.semantics``): the hand is at a target within this distance (m), and a
    # target gets at most this many control steps per unit of stride. Measured on the scripted experts: after one
    # 0.1 s control step the hand is within 2 mm of a stride-1 target (99th percentile) and of a stride-3 one except
    # in contact (press_button, stack_cubes; docs/execution.md)
    waypoint_tolerance: float = 0.005
    waypoint_steps: int = 3

    def __init__(self, *, control_dt: float = 0.1, max_steps: int | None = None,
                 obs_keys: tuple[str, ...] = ("state",), camera=None, expert_wobble: float = 0.0015,
                 controller_speed: float | None = None):
        """control_dt: seconds per control step (10–20 Hz advised). max_steps: episode step limit (task default when
        None). obs_keys: observations to compute, a subset of ('state', 'image', 'depth', 'point_cloud').
        camera: a ``camera.CameraConfig`` (default one when an image key is requested and None).
        expert_wobble: amplitude (m) of the scripted expert's smooth hand wobble.
        controller_speed: speed limit (m/s) of the hand's set-point (``step``); None: the servo gets each target
        at once."""
        valid = ("state", "image", "depth", "point_cloud")
        bad = [k for k in obs_keys if k not in valid]
        if bad or "state" not in obs_keys:
            raise ValueError(f"obs_keys: must contain 'state' and only {valid}, got {obs_keys}")
        self.mj_model = mujoco.MjModel.from_xml_path(os.path.join(ASSETS_DIR, self.xml_file))
        self.mjx_model = mjx.put_model(self.mj_model)
        timestep = float(self.mj_model.opt.timestep)
        self.n_substeps = int(round(control_dt / timestep))
        if self.n_substeps < 1 or abs(self.n_substeps * timestep - control_dt) > 1e-9:
            raise ValueError(f"control_dt: must be a positive multiple of the physics timestep {timestep}, "
                             f"got {control_dt}")
        self.control_dt = float(control_dt)
        self.max_steps = int(max_steps if max_steps is not None else self.default_max_steps)
        self.obs_keys = tuple(obs_keys)
        self.expert_wobble = float(expert_wobble)
        if controller_speed is not None and not controller_speed > 0:
            raise ValueError(f"controller_speed: must be None (no limit) or > 0 m/s, got {controller_speed}")
        self.controller_speed = None if controller_speed is None else float(controller_speed)
        self.camera = None
        if any(k in self.obs_keys for k in ("image", "depth", "point_cloud")):
            from hipolicy_jax.envs import camera as camera_lib

            self.camera = camera_lib.Camera(self.mj_model, camera or camera_lib.CameraConfig())
        m = self.mj_model
        self._hand_qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in ("hand_x", "hand_y", "hand_z")])
        self._finger_qadr = np.array([m.jnt_qposadr[m.joint(n).id] for n in ("finger_l", "finger_r")])
        self._hand_dadr = np.array([m.jnt_dofadr[m.joint(n).id] for n in ("hand_x", "hand_y", "hand_z")])
        self._rand_body_ids = np.array([m.body(n).id for n in self.randomised_bodies], dtype=np.int32)

    # ------------------------------------------------------------------ public API
    @property
    def name(self) -> str:
        return self.xml_file.removesuffix(".xml")

    @property
    def action_dim(self) -> int:
        return ACTION_DIM

    @property
    def action_kinds(self) -> tuple[str, ...]:
        """Per action dimension, ``'absolute'`` or ``'delta'`` (``ChunkConfig.action_kinds``): every MJX task's
        action is an absolute target (hand xyz, gripper)."""
        return ("absolute",) * self.action_dim

    @property
    def state_dim(self) -> int:
        return PROPRIO_DIM + self.task_state_dim

    @property
    def obs_shapes(self) -> dict[str, tuple[int, ...]]:
        """Observation key -> shape of one (unbatched) observation."""
        shapes = {"state": (self.state_dim,)}
        if self.camera is not None:
            cfg = self.camera.config
            if "image" in self.obs_keys:
                shapes["image"] = (cfg.height, cfg.width, 3)
            if "depth" in self.obs_keys:
                shapes["depth"] = (cfg.height, cfg.width)
            if "point_cloud" in self.obs_keys:
                shapes["point_cloud"] = (cfg.num_points, 6 if cfg.point_rgb else 3)
        return shapes

    @property
    def obs_dtypes(self) -> dict[str, str]:
        """Observation key -> dtype name (the camera's image is uint8, everything else float32)."""
        return {k: ("uint8" if k == "image" else "float32") for k in self.obs_shapes}

    def reset(self, key: jax.Array) -> State:
        """Start an episode with randomised initial conditions drawn from ``key``."""
        k_init, k_hand, k_rng = jax.random.split(key, 3)
        qpos, body_pos, info = self._sample_init(k_init)
        info = dict(info, body_pos=jnp.asarray(body_pos, jnp.float32).reshape(len(self.randomised_bodies), 3))
        model = self.episode_model(info)
        hand = jnp.stack([uniform(k, lo, hi) for k, lo, hi in
                          zip(jax.random.split(k_hand, 3), (-0.08, 0.08, 0.17), (0.08, 0.16, 0.24))])
        qpos = qpos.at[self._hand_qadr].set(hand).at[self._finger_qadr].set(FINGER_OPEN)
        data = mjx.make_data(self.mjx_model)
        ctrl = jnp.concatenate([hand, jnp.full((2,), FINGER_OPEN)])
        data = data.replace(qpos=qpos, ctrl=ctrl)
        # Kinematics only (body, geom and site poses, which the observation reads): the first ``step`` runs the full
        # forward dynamics again from qpos, qvel and ctrl, and nothing else a forward pass writes is read before
        # that (the solver's warm start is written by the step alone). A full ``mjx.forward`` here would put a
        # second copy of collision and the constraint solver into every rollout's program.
        data = mjx.kinematics(model, data)
        info = dict(info, rng=k_rng)
        obs = self._observe(model, data, info)
        zero = jnp.zeros((), jnp.float32)
        return State(data=data, obs=obs, reward=zero, done=jnp.zeros((), bool), success=jnp.zeros((), bool),
                     step=jnp.zeros((), jnp.int32), info=info)

    def step(self, state: State, action: jax.Array) -> State:
        """Advance one control step towards the absolute target ``action`` (4,) = (x, y, z, gripper).

        With a ``controller_speed`` v the hand's set-point moves from the last one straight towards the target by
        at most v · control_dt (the servo tracks the set-point within the step); otherwise it is the target."""
        ctrl = self.action_to_ctrl(action)
        if self.controller_speed is not None:
            last = state.data.ctrl[:3]
            move = ctrl[:3] - last
            limit = self.controller_speed * self.control_dt
            scale = jnp.minimum(1.0, limit / jnp.maximum(jnp.linalg.norm(move), 1e-12))
            ctrl = ctrl.at[:3].set(last + scale * move)
        data = state.data.replace(ctrl=ctrl)
        model = self.episode_model(state.info)

        def substep(d, _):
            d = d.replace(qfrc_applied=self._applied_force(d))
            return mjx.step(model, d), None

        data, _ = jax.lax.scan(substep, data, None, length=self.n_substeps)
        rng, _ = jax.random.split(state.info["rng"])
        info, reward, success_now = self._task_update(data, dict(state.info, rng=rng))
        success = state.success | success_now
        step = state.step + 1
        done = success | (step >= self.max_steps)
        obs = self._observe(model, data, info)
        return State(data=data, obs=obs, reward=reward.astype(jnp.float32), done=done, success=success, step=step,
                     info=info)

    def action_to_ctrl(self, action: jax.Array) -> jax.Array:
        """Clip an action (4,) to the workspace and map it to the actuator controls (5,)."""
        action = jnp.asarray(action, jnp.float32)
        xyz = jnp.clip(action[:3], jnp.asarray(self.workspace_low), jnp.asarray(self.workspace_high))
        half = FINGER_OPEN * (1.0 - jnp.clip(action[3], 0.0, 1.0))
        return jnp.concatenate([xyz, jnp.stack([half, half])])

    def reach_error(self, state: State, action: jax.Array) -> jax.Array:
        """Distance (m) () from the hand (TCP) to the target of ``action`` (4,), clipped to the workspace: how far a
        waypoint is from reached (``rollout``'s ``waypoint`` semantics). The gripper command is not part of it: a
        grasp stops the fingers before the command's opening, so a closed gripper would never count as arrived."""
        target = jnp.clip(jnp.asarray(action[:3], jnp.float32), jnp.asarray(self.workspace_low),
                          jnp.asarray(self.workspace_high))
        return jnp.linalg.norm(self.tcp(state.data) - target)

    def episode_model(self, info: dict) -> mjx.Model:
        """The MJX model of an episode: the shared model with this episode's randomised body placements."""
        if not self.randomised_bodies:
            return self.mjx_model
        body_pos = jnp.asarray(self.mjx_model.body_pos).at[self._rand_body_ids].set(info["body_pos"])
        return self.mjx_model.replace(body_pos=body_pos)

    def tcp(self, data: mjx.Data) -> jax.Array:
        """TCP position (3,)."""
        return data.qpos[self._hand_qadr]

    def gripper_opening(self, data: mjx.Data) -> jax.Array:
        """Distance between the finger axes (m), () — 2·FINGER_OPEN fully open, 0 fully closed."""
        return data.qpos[self._finger_qadr].sum()

    # ------------------------------------------------------------------ experts
    def expert_plan(self, obs_state: jax.Array, key: jax.Array) -> ExpertPlan:
        """Scripted expert plan for the episode whose first ``state`` observation is ``obs_state`` (D,)."""
        raise NotImplementedError

    def expert_action(self, plan: ExpertPlan, t: jax.Array) -> jax.Array:
        """Expert action (4,) at control step ``t`` (scalar, may be fractional)."""
        point = interp_plan(plan, jnp.asarray(t, jnp.float32))
        action = self._plan_to_action(point, plan.params)
        amp, freq, phase = plan.wobble[:, 0], plan.wobble[:, 1], plan.wobble[:, 2]
        wob = amp * (jnp.sin(freq * t + phase) - jnp.sin(phase))
        return action.at[:3].add(wob)

    def _plan_to_action(self, point: jax.Array, params: jax.Array) -> jax.Array:
        """Map a plan-space point (4,) to an action (4,); identity for cartesian plans."""
        return point

    def timed_phase(self, qpos: np.ndarray) -> tuple[np.ndarray, int] | None:
        """The control steps of a phase whose duration the success condition checks, for recorded joint positions
        ``qpos`` (..., T, nq) → (in_phase (..., T) bool, the steps it must last); None for tasks without one.
        ``evaluation.phases`` measures how long rollouts hold such a phase and at which stride."""
        return None

    # ------------------------------------------------------------------ task hooks
    def _sample_init(self, key: jax.Array) -> tuple[jax.Array, jax.Array, dict]:
        """Randomised initial (qpos (nq,), body_pos (len(randomised_bodies), 3), task info dict).

        The hand and finger entries of qpos are overwritten by ``reset``."""
        raise NotImplementedError

    def _applied_force(self, data: mjx.Data) -> jax.Array:
        """Generalised force (nv,) applied during every physics substep (e.g. a latch detent); zero by default."""
        return jnp.zeros_like(data.qfrc_applied)

    def _task_update(self, data: mjx.Data, info: dict) -> tuple[dict, jax.Array, jax.Array]:
        """After a control step: (new info, reward (), success this step () bool)."""
        raise NotImplementedError

    def _task_state(self, data: mjx.Data, info: dict) -> jax.Array:
        """Task part of the ``state`` observation, (task_state_dim,)."""
        raise NotImplementedError

    def _observe(self, model: mjx.Model, data: mjx.Data, info: dict) -> dict[str, jax.Array]:
        state = jnp.concatenate([self.tcp(data), self.gripper_opening(data)[None], self._task_state(data, info)])
        obs = {"state": state.astype(jnp.float32)}
        if self.camera is not None:
            obs.update(self.camera.observe(model, data, info["rng"], self.obs_keys))
        return obs
