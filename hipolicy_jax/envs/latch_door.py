"""latch_door: push a hinged cabinet door shut past a latch detent (the paper's "close the microwave door").

Scene (``assets/latch_door.xml``): a cabinet with an 18 cm door on a vertical hinge, placed at a random spot
(episode body_pos), the door open at a random angle in [0.6, 1.1] rad. Only finger-door contacts exist.

Latch: a detent acts on the hinge as a generalised force (applied every physics substep): in the detent zone
``LATCH_LOW < angle < LATCH_HIGH`` a spring-like bump pushes the door open with a peak torque of ``detent_torque``
(~9 N at the 13 cm push radius); below ``LATCH_LOW`` the catch pulls it shut. A gentle push therefore leaves the door
resting just open, and closing it takes a deliberate firm push past the detent.

Success: latched, i.e. the door angle is below ``LATCHED`` (0.03 rad).

Demonstrations pause: the expert sweeps the door to just outside the detent, pauses 0.8–2 s (the non-Markovian
pause: the scene is static and nothing observable says when to go on), then pushes through the latch.

state (7,): TCP xyz, gripper opening, door angle (rad, 0 = closed), hinge xy.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from hipolicy_jax.envs import base

LATCH_LOW = 0.05
LATCH_HIGH = 0.15
LATCHED = 0.03
PUSH_RADIUS = 0.13  # distance of the pushing finger from the hinge (m)
CONTACT_OFFSET = 0.012 + base.FINGER_RADIUS  # finger axis to the door's mid plane when touching its front face
PUSH_Z = 0.07


class LatchDoor(base.MjxEnv):
    """Close the door past its latch. Step limit 200 at 10 Hz. The expert plans in polar coordinates about the
    hinge: plan points are (angle, radius, z, gripper), params = hinge xy."""

    xml_file = "latch_door.xml"
    task_state_dim = 3
    default_max_steps = 200
    randomised_bodies = ("door_frame",)

    def __init__(self, *, detent_torque: float = 1.2, latch_torque: float = 0.3, **kwargs):
        super().__init__(**kwargs)
        self.detent_torque = float(detent_torque)
        self.latch_torque = float(latch_torque)
        m = self.mj_model
        self._door_qadr = int(m.jnt_qposadr[m.joint("door").id])
        self._door_dadr = int(m.jnt_dofadr[m.joint("door").id])

    def _sample_init(self, key):
        kx, ky, ka = jax.random.split(key, 3)
        hinge = jnp.stack([base.uniform(kx, -0.15, -0.05), base.uniform(ky, -0.04, 0.04), jnp.zeros(())])
        qpos = jnp.zeros((self.mj_model.nq,)).at[self._door_qadr].set(base.uniform(ka, 0.6, 1.1))
        return qpos, hinge[None], {}

    def door_angle(self, data) -> jax.Array:
        """Door angle (rad), (); 0 = closed."""
        return data.qpos[self._door_qadr]

    def detent_torque_at(self, angle: jax.Array) -> jax.Array:
        """Latch torque on the hinge (N·m), positive = opening, at door angle ``angle``."""
        u = (angle - LATCH_LOW) / (LATCH_HIGH - LATCH_LOW)
        bump = jnp.where((u > 0) & (u < 1), self.detent_torque * jnp.sin(jnp.pi * jnp.clip(u, 0.0, 1.0)), 0.0)
        catch = -self.latch_torque * jnp.clip((LATCH_LOW - angle) / 0.01, 0.0, 1.0)
        return bump + catch

    def _applied_force(self, data):
        tau = self.detent_torque_at(self.door_angle(data))
        return jnp.zeros_like(data.qfrc_applied).at[self._door_dadr].set(tau)

    def _task_update(self, data, info):
        success = self.door_angle(data) < LATCHED
        return info, success.astype(jnp.float32), success

    def _task_state(self, data, info):
        return jnp.concatenate([self.door_angle(data)[None], info["body_pos"][0, :2]])

    def _plan_to_action(self, point, params):
        phi, rho = point[0], point[1]
        xy = params[:2] + rho * jnp.stack([jnp.cos(phi), jnp.sin(phi)])
        return jnp.concatenate([xy, point[2:4]])

    def expert_plan(self, obs_state, key):
        ks = jax.random.split(key, 12)
        dt = self.control_dt
        tcp, angle0, hinge = obs_state[:3], obs_state[4], obs_state[5:7]
        rel = tcp[:2] - hinge
        start = jnp.stack([jnp.arctan2(rel[1], rel[0]), jnp.linalg.norm(rel), tcp[2], jnp.zeros(())])
        rho = PUSH_RADIUS + base.uniform(ks[0], -0.01, 0.01)
        delta = jnp.arcsin(CONTACT_OFFSET / rho)  # finger angle ahead of the door angle when touching
        z_push = PUSH_Z + base.uniform(ks[1], -0.01, 0.01)
        z_high = base.uniform(ks[2], 0.17, 0.2)
        phi_pre = angle0 + delta + base.uniform(ks[3], 0.25, 0.35)
        phi_pause = LATCH_HIGH + base.uniform(ks[4], 0.01, 0.06) + delta
        phi_final = -0.2 + delta

        def pt(phi, z):
            return jnp.stack([phi, rho, z, jnp.ones(())])

        arc_len = (phi_pre - phi_pause) * rho
        pre_xyz = jnp.concatenate([hinge + rho * jnp.stack([jnp.cos(phi_pre), jnp.sin(phi_pre)]), z_high[None]])
        approach = jnp.linalg.norm(pre_xyz - tcp)
        segments = [
            (pt(phi_pre, z_high), base.move_steps(ks[5], approach, dt, min_time=1.2)),
            (pt(phi_pre, z_push), base.uniform(ks[6], 0.7, 1.0) / dt),
            (pt(phi_pause, z_push), base.move_steps(ks[7], arc_len, dt, speed=(0.08, 0.14), min_time=1.2)),
            (pt(phi_pause, z_push), base.uniform(ks[8], 0.8, 2.0) / dt),  # the non-Markovian pause
            (pt(phi_final, z_push), base.uniform(ks[9], 0.8, 1.2) / dt),
            (pt(phi_final, z_push), jnp.float32(1.0 / dt)),
        ]
        wobble = base.sample_wobble(ks[10], self.expert_wobble)
        return base.plan_from_segments(start, segments, params=hinge, wobble=wobble)
