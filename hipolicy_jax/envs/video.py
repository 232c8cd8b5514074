"""Videos of rollouts for humans (gif, or mp4 when imageio-ffmpeg is installed).

Frames come from MuJoCo's offscreen renderer when an OpenGL backend works (``MUJOCO_GL=egl`` or ``osmesa``),
otherwise from the jitted ray-cast camera (``camera.py``). The rollout itself is one jitted scan that records the
joint positions of every control step; frames are rendered afterwards on the host.

    python -m hipolicy_jax.envs.video --task latch_door --output door.gif
    python -m hipolicy_jax.envs.video --task press_button --stride 2 --output press_x2.gif
"""

from __future__ import annotations

import argparse
import math
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from hipolicy_jax import envs as envs_lib
from hipolicy_jax.envs import camera as camera_lib
from hipolicy_jax.envs import rollout
from hipolicy_jax.envs.base import MjxEnv


class Trajectory(NamedTuple):
    """One recorded episode: qpos (T+1, nq) from the reset on, body_pos (n, 3) the episode's randomised body
    placements, steps () control steps executed, success () bool."""

    qpos: np.ndarray
    body_pos: np.ndarray
    steps: int
    success: bool


def record_trajectory(env: MjxEnv, key: jax.Array, policy_fn=None, init_fn=None, *, chunk_len: int = 8,
                      history_len: int = 1, max_steps: int | None = None, policy_args=()) -> Trajectory:
    """Run one episode of a stateful policy (default: the scripted expert at stride 1) and record its qpos."""
    if policy_fn is None:
        policy_fn, init_fn = rollout.expert_policy(env, chunk_len)
    limit = int(max_steps or env.max_steps)
    num_replans = math.ceil(limit / chunk_len)

    def run(key):
        k_reset, k_init, k_pol = jax.random.split(key, 3)
        state = env.reset(k_reset)
        history = rollout.init_history(state.obs, history_len)
        pstate = init_fn(state.obs, k_init)

        def replan(carry, r):
            state, history, pstate = carry
            out, pstate = policy_fn(history, jax.random.fold_in(k_pol, r), pstate, policy_args)

            def act(inner, action):
                state, history = inner
                stop = state.done | (state.step >= limit)
                new = env.step(state, action)
                new_hist = rollout.push_history(history, new.obs)
                state = jax.tree.map(lambda a, b: jnp.where(stop, a, b), state, new)
                history = jax.tree.map(lambda a, b: jnp.where(stop, a, b), history, new_hist)
                return (state, history), state.data.qpos

            (state, history), qpos = jax.lax.scan(act, (state, history), out.actions)
            return (state, history, pstate), qpos

        qpos0 = state.data.qpos
        (state, _, _), qpos = jax.lax.scan(replan, (state, history, pstate), jnp.arange(num_replans))
        qpos = jnp.concatenate([qpos0[None], qpos.reshape(-1, qpos0.shape[0])])
        return qpos, state.info["body_pos"], state.step, state.success

    qpos, body_pos, steps, success = jax.device_get(jax.jit(run)(key))
    steps = int(steps)
    return Trajectory(qpos=np.asarray(qpos[:steps + 1]), body_pos=np.asarray(body_pos), steps=steps,
                      success=bool(success))


def opengl_available() -> bool:
    """Whether MuJoCo's offscreen renderer can be created here."""
    try:
        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody/></mujoco>")
        renderer = mujoco.Renderer(model, 8, 8)
        renderer.close()
        return True
    except Exception:  # noqa: BLE001 - any GL failure means "not available"
        return False


def _episode_mj_model(env: MjxEnv, body_pos: np.ndarray) -> mujoco.MjModel:
    model = mujoco.MjModel.from_xml_path(os.path.join(os.path.dirname(__file__), "assets", env.xml_file))
    for name, pos in zip(env.randomised_bodies, body_pos):
        model.body(name).pos[:] = pos
    return model


def render_frames(env: MjxEnv, traj: Trajectory, *, height: int = 240, width: int = 320,
                  backend: str = "auto") -> np.ndarray:
    """Frames (T+1, H, W, 3) uint8 of a trajectory. backend: 'opengl', 'raycast' or 'auto' (OpenGL if it works)."""
    if backend == "auto":
        backend = "opengl" if opengl_available() else "raycast"
    if backend == "opengl":
        model = _episode_mj_model(env, traj.body_pos)
        data = mujoco.MjData(model)
        cam = mujoco.MjvCamera()
        cam.lookat[:] = (0.0, -0.05, 0.05)
        cam.distance, cam.azimuth, cam.elevation = 0.85, -90.0, -35.0
        renderer = mujoco.Renderer(model, height, width)
        frames = []
        try:
            for q in traj.qpos:
                data.qpos[:] = q
                mujoco.mj_forward(model, data)
                renderer.update_scene(data, camera=cam)
                frames.append(renderer.render().copy())
        finally:
            renderer.close()
        return np.stack(frames)
    if backend != "raycast":
        raise ValueError(f"backend: must be 'auto', 'opengl' or 'raycast', got {backend!r}")
    cam = camera_lib.Camera(env.mj_model, camera_lib.CameraConfig(height=height, width=width))
    model = env.episode_model({"body_pos": jnp.asarray(traj.body_pos)})

    @jax.jit
    def frame(q):
        data = mjx.forward(model, mjx.make_data(env.mjx_model).replace(qpos=q))
        return cam.observe(model, data, jax.random.PRNGKey(0), ("image",))["image"]

    return np.stack([np.asarray(frame(jnp.asarray(q))) for q in traj.qpos])


def save_video(frames: np.ndarray, path: str, fps: float) -> str:
    """Write frames (T, H, W, 3) uint8 to ``path`` (.gif, or .mp4 with imageio-ffmpeg); returns the path."""
    import imageio.v2 as imageio

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if path.endswith(".gif"):
        imageio.mimsave(path, list(frames), duration=1000.0 / fps, loop=0)
    else:
        imageio.mimsave(path, list(frames), fps=fps)
    return path


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", required=True, choices=envs_lib.TASKS)
    p.add_argument("--output", default=None, help="default videos/<task>.gif")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stride", type=int, default=1, help="execute the expert's plan at this stride")
    p.add_argument("--backend", default="auto", choices=["auto", "opengl", "raycast"])
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--width", type=int, default=320)
    args = p.parse_args(argv)
    env = envs_lib.make(args.task)
    policy_fn, init_fn = rollout.expert_policy(env, 8, args.stride)
    traj = record_trajectory(env, jax.random.PRNGKey(args.seed), policy_fn, init_fn)
    frames = render_frames(env, traj, height=args.height, width=args.width, backend=args.backend)
    path = save_video(frames, args.output or os.path.join("videos", f"{args.task}.gif"), 1.0 / env.control_dt)
    print(f"{args.task}: {traj.steps} steps, success {traj.success}, {len(frames)} frames -> {path}")


if __name__ == "__main__":
    main()
