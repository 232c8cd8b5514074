"""pick_place: put two cubes, one after the other, into a bin (multi-stage, long horizon).

Scene (``assets/pick_place.xml``): a red and a green 4 cm cube (free, random position and yaw) and a 15 × 11 cm
bin at a random position (episode body_pos). Contact pairs: each cube with the table, with both fingers, and the
two cubes with each other. The bin's rim is drawn but not collidable (keeps the contact count low); a cube is in
the bin when its centre lies in the bin's interior. Gripper model as in ``stack_cubes``: bounded-force fingers,
grasping by friction.

Success: both cubes inside the bin, resting on the table (nearly still) and the gripper open.

state (20,): TCP xyz, gripper opening, red cube position + quaternion (7), green cube position + quaternion (7),
bin xy.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from hipolicy_jax.envs import base

CUBE_HALF = 0.02
BIN_HALF = (0.075, 0.055)  # interior half extents (m)
RELEASED_OPENING = 0.07


class PickPlace(base.MjxEnv):
    """Red cube, then green cube, into the bin. Step limit 300 at 10 Hz."""

    xml_file = "pick_place.xml"
    task_state_dim = 16
    default_max_steps = 300
    randomised_bodies = ("bin",)
    workspace_low = (-0.35, -0.35, base.FINGER_BOTTOM + 0.002)

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        m = self.mj_model
        self._qadr = [int(m.jnt_qposadr[m.joint(n).id]) for n in ("cube_a", "cube_b")]
        self._dadr = [int(m.jnt_dofadr[m.joint(n).id]) for n in ("cube_a", "cube_b")]

    def _sample_init(self, key):
        kp, ky = jax.random.split(key)
        xy = base.sample_separated_xy(kp, 3, (-0.2, -0.18), (0.2, 0.06), 0.14, tries=32)
        yaw = base.uniform(ky, -0.4, 0.4, (2,))
        qpos = jnp.zeros((self.mj_model.nq,))
        for i, adr in enumerate(self._qadr):
            cube = jnp.concatenate([xy[i], jnp.full((1,), CUBE_HALF), base.yaw_quat(yaw[i])])
            qpos = qpos.at[adr:adr + 7].set(cube)
        body_pos = jnp.concatenate([xy[2], jnp.zeros((1,))])[None]
        return qpos, body_pos, {}

    def cube_poses(self, data) -> jax.Array:
        """Both cubes' position + quaternion, (2, 7)."""
        return jnp.stack([data.qpos[a:a + 7] for a in self._qadr])

    def in_bin(self, data, info) -> jax.Array:
        """Per cube (2,) bool: centre inside the bin interior (less the cube's half size) and resting on the table."""
        pos = self.cube_poses(data)[:, :3]
        rel = jnp.abs(pos[:, :2] - info["body_pos"][0, :2])
        inside = (rel[:, 0] < BIN_HALF[0] - CUBE_HALF + 0.005) & (rel[:, 1] < BIN_HALF[1] - CUBE_HALF + 0.005)
        vel = jnp.stack([jnp.linalg.norm(data.qvel[a:a + 3]) for a in self._dadr])
        return inside & (pos[:, 2] < CUBE_HALF + 0.005) & (vel < 0.05)

    def _task_update(self, data, info):
        inside = self.in_bin(data, info)
        success = inside.all() & (self.gripper_opening(data) > RELEASED_OPENING)
        return info, success.astype(jnp.float32), success

    def _task_state(self, data, info):
        return jnp.concatenate([self.cube_poses(data).reshape(-1), info["body_pos"][0, :2]])

    def expert_plan(self, obs_state, key):
        ks = jax.random.split(key, 32)
        dt = self.control_dt
        tcp = obs_state[:3]
        cubes = (obs_state[4:7], obs_state[11:14])
        bin_xy = obs_state[18:20]
        start = jnp.concatenate([tcp, jnp.zeros((1,))])
        # drop spots: left and right halves of the bin
        spots = [bin_xy + jnp.stack([sx * base.uniform(k, 0.03, 0.04), base.uniform(k2, -0.008, 0.008)])
                 for sx, k, k2 in ((-1.0, ks[0], ks[1]), (1.0, ks[2], ks[3]))]

        def pt(xy, z, g):
            return jnp.concatenate([xy, jnp.reshape(z, (1,)), jnp.full((1,), g)])

        segments = []
        pos = tcp
        for i in range(2):
            k = jax.random.split(ks[4 + i], 12)
            cube = cubes[i]
            grasp_xy = cube[:2] + base.uniform(k[0], -0.002, 0.002, (2,))
            z_above = base.uniform(k[1], 0.08, 0.11)
            z_grasp = cube[2] + base.uniform(k[2], 0.003, 0.008)
            z_carry = base.uniform(k[3], 0.1, 0.13)
            z_drop = CUBE_HALF + (z_grasp - cube[2]) + base.uniform(k[4], 0.008, 0.015)
            above = pt(grasp_xy, z_above, 0.0)
            lift = pt(grasp_xy, z_carry, 1.0)
            over_bin = pt(spots[i], z_carry, 1.0)
            segments += [
                (above, base.move_steps(k[5], jnp.linalg.norm(above[:3] - pos), dt, min_time=1.0)),
                (pt(grasp_xy, z_grasp, 0.0), base.uniform(k[6], 0.8, 1.2) / dt),
                (pt(grasp_xy, z_grasp, 1.0), base.uniform(k[7], 0.5, 0.8) / dt),
                (lift, base.uniform(k[8], 0.8, 1.1) / dt),
                (over_bin, base.move_steps(k[9], jnp.linalg.norm(over_bin[:2] - lift[:2]), dt, min_time=1.0)),
                (pt(spots[i], z_drop, 1.0), base.uniform(k[10], 0.7, 1.0) / dt),
                (pt(spots[i], z_drop, 0.0), base.uniform(k[11], 0.4, 0.6) / dt),
                (pt(spots[i], z_carry, 0.0), base.uniform(k[4], 0.6, 0.9) / dt),  # clear the released cube
            ]
            pos = jnp.concatenate([spots[i], jnp.reshape(z_carry, (1,))])
        wobble = base.sample_wobble(ks[9], self.expert_wobble)
        return base.plan_from_segments(start, segments, wobble=wobble)
