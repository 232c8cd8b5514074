"""press_button: press a small spring-loaded button, hold it down, release it (precise and non-Markovian).

Scene (``assets/press_button.xml``): a button housing placed at a random spot on the table (a mocap body) with a
2.2 cm square cap on a vertical spring-loaded slide joint (travel 12 mm). The closed fingers press the cap; the only
contact pairs are finger-cap.

Success: the cap was held pressed (depth > ``PRESS_DEPTH``) for at least ``hold_time`` seconds without interruption
and then released (depth < ``RELEASE_DEPTH``). The hold counter lives in ``State.info`` and is NOT observed: while
the button is held the observation is stationary, so a policy must remember how long it has been pressing — the
pause in the demonstrations is non-Markovian. The scripted expert holds for a random duration
``hold_time + U(0.3, 1.5)`` seconds.

state (7,): TCP xyz, gripper opening, button base xy, cap depth (m, positive when pressed).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hipolicy_jax.envs import base

CAP_TOP = 0.032  # height of the cap's top face at rest (m)
PRESS_DEPTH = 0.007
RELEASE_DEPTH = 0.003


class PressButton(base.MjxEnv):
    """Press, hold for at least ``hold_time`` seconds, release. Step limit 150 at 10 Hz."""

    xml_file = "press_button.xml"
    task_state_dim = 3
    default_max_steps = 150
    randomised_bodies = ("button_base",)

    def __init__(self, *, hold_time: float = 1.0, **kwargs):
        super().__init__(**kwargs)
        self.hold_time = float(hold_time)
        self.hold_steps = int(round(hold_time / self.control_dt))
        m = self.mj_model
        self._button_qadr = int(m.jnt_qposadr[m.joint("button").id])

    def _sample_init(self, key):
        kx, ky = jax.random.split(key)
        xy = jnp.stack([base.uniform(kx, -0.15, 0.15), base.uniform(ky, -0.15, 0.05)])
        body_pos = jnp.concatenate([xy, jnp.zeros((1,))])[None]
        info = {"hold": jnp.zeros((), jnp.int32), "held": jnp.zeros((), bool)}
        return jnp.zeros((self.mj_model.nq,)), body_pos, info

    def depth(self, data) -> jax.Array:
        """Cap depth below its rest position (m), ()."""
        return -data.qpos[self._button_qadr]

    def timed_phase(self, qpos):
        """The cap held pressed (depth > ``PRESS_DEPTH``), which must last ``hold_steps`` control steps."""
        return -np.asarray(qpos)[..., self._button_qadr] > PRESS_DEPTH, self.hold_steps

    def _task_update(self, data, info):
        depth = self.depth(data)
        pressed = depth > PRESS_DEPTH
        hold = jnp.where(pressed, info["hold"] + 1, 0)
        released = depth < RELEASE_DEPTH
        success = info["held"] & released
        # "held" survives partial lifts and is cleared by a full release: success needs an uninterrupted hold.
        held = ~released & (info["held"] | (hold >= self.hold_steps))
        info = dict(info, hold=hold.astype(jnp.int32), held=held)
        return info, success.astype(jnp.float32), success

    def _task_state(self, data, info):
        return jnp.concatenate([info["body_pos"][0, :2], self.depth(data)[None]])

    def expert_plan(self, obs_state, key):
        ks = jax.random.split(key, 10)
        dt = self.control_dt
        tcp, bxy = obs_state[:3], obs_state[4:6]
        start = jnp.concatenate([tcp, jnp.zeros((1,))])
        target_xy = bxy + base.uniform(ks[0], -0.003, 0.003, (2,))
        z_above = base.uniform(ks[1], 0.07, 0.11)
        z_press = jnp.float32(CAP_TOP - 0.015 + base.FINGER_BOTTOM)  # 3 mm past the joint's travel: pressed against its stop
        above = jnp.concatenate([target_xy, z_above[None], jnp.ones((1,))])
        press = jnp.concatenate([target_xy, z_press[None], jnp.ones((1,))])
        lift = jnp.concatenate([target_xy, (z_press + base.uniform(ks[2], 0.04, 0.07))[None], jnp.ones((1,))])
        hold = (self.hold_time + base.uniform(ks[3], 0.3, 1.5)) / dt
        segments = [
            (above, base.move_steps(ks[4], jnp.linalg.norm(above[:3] - tcp), dt, min_time=1.0)),
            (above, base.uniform(ks[5], 0.0, 0.6) / dt),  # hesitate above the button
            (press, base.uniform(ks[6], 0.7, 1.1) / dt),
            (press, hold),  # the non-Markovian hold
            (lift, base.uniform(ks[7], 0.6, 1.0) / dt),
        ]
        wobble = base.sample_wobble(ks[8], self.expert_wobble)
        return base.plan_from_segments(start, segments, wobble=wobble)
