"""stack_cubes: grasp a 4 cm cube and place it on a 5 cm base cube within 1.5 cm (precise and long).

Scene (``assets/stack_cubes.xml``): a free red cube at a random position and yaw, a blue base cube fixed to the
table at another random position (episode body_pos). Contact pairs: cube-table, cube-fingers, cube-base.

Gripper model: two capsule fingers on slide joints, each driven by a position actuator towards
``FINGER_OPEN·(1-g)`` with its force clipped to 12 N, so a closed gripper squeezes the cube with a bounded force
and the cube is lifted by contact friction alone (μ = 1.5 finger / 1.2 cube, pyramidal cones); nothing attaches
it to the hand. Only the cube's own contacts exist (the fingers pass through the table and the base cube; the
workspace keeps the fingertips above the table).

Success: the cube rests on the base cube (centre within ``tolerance`` in xy, at the right height, nearly still)
and the gripper has let go (opening > 7 cm).

state (13,): TCP xyz, gripper opening, cube position (3) and quaternion (4, wxyz), base cube xy.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from hipolicy_jax.envs import base

CUBE_HALF = 0.02
BASE_HALF = 0.025
BASE_TOP = 2 * BASE_HALF
RELEASED_OPENING = 0.07


class StackCubes(base.MjxEnv):
    """Pick the red cube and stack it on the blue one. Step limit 200 at 10 Hz."""

    xml_file = "stack_cubes.xml"
    task_state_dim = 9
    default_max_steps = 200
    randomised_bodies = ("base_cube",)

    def __init__(self, *, tolerance: float = 0.015, **kwargs):
        super().__init__(**kwargs)
        self.tolerance = float(tolerance)
        m = self.mj_model
        self._cube_qadr = int(m.jnt_qposadr[m.joint("cube").id])
        self._cube_dadr = int(m.jnt_dofadr[m.joint("cube").id])

    def _sample_init(self, key):
        kp, ky = jax.random.split(key)
        xy = base.sample_separated_xy(kp, 2, (-0.15, -0.15), (0.15, 0.08), 0.11)
        yaw = base.uniform(ky, -0.4, 0.4)
        qpos = jnp.zeros((self.mj_model.nq,))
        cube = jnp.concatenate([xy[0], jnp.full((1,), CUBE_HALF), base.yaw_quat(yaw)])
        qpos = qpos.at[self._cube_qadr:self._cube_qadr + 7].set(cube)
        body_pos = jnp.concatenate([xy[1], jnp.full((1,), BASE_HALF)])[None]
        return qpos, body_pos, {}

    def cube_pose(self, data) -> jax.Array:
        """Cube position and quaternion (7,)."""
        return data.qpos[self._cube_qadr:self._cube_qadr + 7]

    def _task_update(self, data, info):
        pos = self.cube_pose(data)[:3]
        vel = data.qvel[self._cube_dadr:self._cube_dadr + 3]
        base_xy = info["body_pos"][0, :2]
        on_top = (jnp.linalg.norm(pos[:2] - base_xy) < self.tolerance) & (
            jnp.abs(pos[2] - (BASE_TOP + CUBE_HALF)) < 0.005)
        success = on_top & (jnp.linalg.norm(vel) < 0.05) & (self.gripper_opening(data) > RELEASED_OPENING)
        return info, success.astype(jnp.float32), success

    def _task_state(self, data, info):
        return jnp.concatenate([self.cube_pose(data), info["body_pos"][0, :2]])

    def expert_plan(self, obs_state, key):
        ks = jax.random.split(key, 16)
        dt = self.control_dt
        tcp, cube, base_xy = obs_state[:3], obs_state[4:7], obs_state[11:13]
        start = jnp.concatenate([tcp, jnp.zeros((1,))])
        grasp_xy = cube[:2] + base.uniform(ks[0], -0.002, 0.002, (2,))
        place_xy = base_xy + base.uniform(ks[1], -0.003, 0.003, (2,))
        z_above = base.uniform(ks[2], 0.08, 0.11)
        z_grasp = cube[2] + base.uniform(ks[3], 0.003, 0.008)
        z_carry = base.uniform(ks[4], 0.12, 0.15)
        z_place = BASE_TOP + CUBE_HALF + (z_grasp - cube[2]) + base.uniform(ks[5], 0.003, 0.006)

        def pt(xy, z, g):
            return jnp.concatenate([xy, jnp.reshape(z, (1,)), jnp.full((1,), g)])

        above = pt(grasp_xy, z_above, 0.0)
        carry_start = pt(grasp_xy, z_carry, 1.0)
        carry_end = pt(place_xy, z_carry, 1.0)
        segments = [
            (above, base.move_steps(ks[6], jnp.linalg.norm(above[:3] - tcp), dt, min_time=1.0)),
            (pt(grasp_xy, z_grasp, 0.0), base.uniform(ks[7], 0.8, 1.2) / dt),
            (pt(grasp_xy, z_grasp, 1.0), base.uniform(ks[8], 0.5, 0.8) / dt),
            (pt(grasp_xy, z_grasp, 1.0), base.uniform(ks[9], 0.1, 0.4) / dt),
            (carry_start, base.uniform(ks[10], 0.8, 1.1) / dt),
            (carry_end, base.move_steps(ks[11], jnp.linalg.norm(carry_end[:2] - carry_start[:2]), dt,
                                        min_time=1.0)),
            (pt(place_xy, z_place, 1.0), base.uniform(ks[12], 0.9, 1.3) / dt),
            (pt(place_xy, z_place, 0.0), base.uniform(ks[13], 0.4, 0.7) / dt),
            (pt(place_xy, z_place + 0.06, 0.0), base.uniform(ks[14], 0.6, 1.0) / dt),
        ]
        wobble = base.sample_wobble(ks[15], self.expert_wobble)
        return base.plan_from_segments(start, segments, wobble=wobble)
