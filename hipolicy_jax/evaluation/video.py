"""Videos of rollouts for humans (gif, or mp4 when imageio-ffmpeg is installed).

Frames come from MuJoCo's offscreen renderer when an OpenGL backend works (``MUJOCO_GL=egl`` or ``osmesa``),
otherwise from the jitted ray-cast camera (``camera.py``). The rollout is the evaluation's episode loop
(``rollout.make_episode_fn`` with recording on), which records the joint positions of every control step; frames
are rendered afterwards on the host. ``trajectory_from_rollout`` takes an episode of a batched evaluation
(``rollout.rollout_episodes``) instead, so a video of an evaluated policy needs no second compile.

    python -m hipolicy_jax.evaluation.video --task latch_door --output door.gif
    python -m hipolicy_jax.evaluation.video --task press_button --stride 2 --output press_x2.gif
"""

from __future__ import annotations

import argparse
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from hipolicy_jax import envs as envs_lib
from hipolicy_jax.envs import camera as camera_lib
from hipolicy_jax.evaluation import rollout
from hipolicy_jax.envs.base import ASSETS_DIR, MjxEnv


class Trajectory(NamedTuple):
    """One recorded episode: qpos (T+1, nq) from the reset on, body_pos (n, 3) the episode's randomised body
    placements, steps () control steps executed, success () bool; optionally the policy's per-replan entropy (R,)
    and stride (R,) with its chunk_len (to annotate frames, see ``annotate_frames``)."""

    qpos: np.ndarray
    body_pos: np.ndarray
    steps: int
    success: bool
    entropy: np.ndarray | None = None
    stride: np.ndarray | None = None
    chunk_len: int = 8


def trajectory_from_rollout(result: rollout.EvalResult, recording: rollout.Recording, episode: int,
                            chunk_len: int) -> Trajectory:
    """Episode ``episode`` of a batched ``rollout.rollout_episodes`` result as a ``Trajectory``."""
    result, recording = jax.device_get((result, recording))
    steps = int(result.steps[episode])
    return Trajectory(qpos=np.asarray(recording.qpos[episode, :steps + 1]),
                      body_pos=np.asarray(recording.body_pos[episode]), steps=steps,
                      success=bool(result.success[episode]), entropy=np.asarray(result.entropy[episode]),
                      stride=np.asarray(result.stride[episode]), chunk_len=int(chunk_len))


def record_trajectory(env: MjxEnv, key: jax.Array, policy_fn=None, init_fn=None, *, chunk_len: int = 8,
                      history_len: int = 1, max_steps: int | None = None, policy_args=()) -> Trajectory:
    """Run one episode of a stateful policy (default: the scripted expert at stride 1) and record its qpos.

    The episode is ``rollout.make_episode_fn`` (the evaluation loop) with recording on, jitted for one episode.
    For a stateless ``policy_fn(obs_history, key, policy_args)`` pass ``*rollout.stateless(policy_fn)``.
    """
    if policy_fn is None:
        policy_fn, init_fn = rollout.expert_policy(env, chunk_len)
    episode = rollout.make_episode_fn(env, policy_fn, init_fn, history_len=history_len, chunk_len=chunk_len,
                                      max_steps=max_steps, record=True)
    state, entropy, stride, valid, rec = jax.device_get(jax.jit(episode)(key, policy_args))
    steps = int(state.step)
    return Trajectory(qpos=np.asarray(rec.qpos[:steps + 1]), body_pos=np.asarray(rec.body_pos), steps=steps,
                      success=bool(state.success), entropy=np.asarray(entropy), stride=np.asarray(stride),
                      chunk_len=int(chunk_len))


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
    model = mujoco.MjModel.from_xml_path(os.path.join(ASSETS_DIR, env.xml_file))
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


# One colour per stride (index = stride - 1, cycling), shared by frame annotations and entropy plots.
STRIDE_COLORS: tuple[tuple[int, int, int], ...] = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                                                  (148, 103, 189), (140, 86, 75))


def stride_color(stride: int) -> tuple[int, int, int]:
    """RGB (0-255) colour of an execution stride."""
    return STRIDE_COLORS[(int(stride) - 1) % len(STRIDE_COLORS)]


def annotate_frames(frames: np.ndarray, traj: Trajectory) -> np.ndarray:
    """Frames with a top banner naming the control step and, when ``traj`` has them, the stride (banner colour)
    and entropy of the chunk being executed. Frame i shows the state after step i, driven by replan (i-1)//L_c."""
    from PIL import Image, ImageDraw, ImageFont

    h = frames.shape[1]
    band = max(10, h // 12)
    font = ImageFont.load_default(size=max(8, band - 3))
    out = []
    for i, frame in enumerate(frames):
        img = Image.fromarray(np.asarray(frame))
        draw = ImageDraw.Draw(img)
        text, color = f"t={i}", (40, 40, 40)
        if traj.stride is not None and len(traj.stride):
            r = min(max(i - 1, 0) // traj.chunk_len, len(traj.stride) - 1)
            color = stride_color(traj.stride[r])
            text += f"  stride {int(traj.stride[r])}"
            if traj.entropy is not None and np.isfinite(traj.entropy[r]):
                text += f"  H={float(traj.entropy[r]):.2f}"
        draw.rectangle((0, 0, img.width, band), fill=color)
        draw.text((3, 1), text, fill=(255, 255, 255), font=font)
        out.append(np.asarray(img))
    return np.stack(out)


def ffmpeg_available() -> bool:
    """Whether imageio can write mp4 (the ``imageio-ffmpeg`` backend and its bundled ffmpeg binary)."""
    try:
        import imageio_ffmpeg

        return os.path.exists(imageio_ffmpeg.get_ffmpeg_exe())
    except Exception:  # noqa: BLE001 - not installed, or no binary for this platform
        return False


def resolve_format(fmt: str = "auto") -> str:
    """'mp4', 'gif' or 'none' for a requested video format: 'auto' is mp4 when ffmpeg is available, else gif."""
    if fmt not in ("auto", "mp4", "gif", "none"):
        raise ValueError(f"video format: must be 'auto', 'mp4', 'gif' or 'none', got {fmt!r}")
    if fmt == "auto":
        return "mp4" if ffmpeg_available() else "gif"
    if fmt == "mp4" and not ffmpeg_available():
        raise ValueError("video format: mp4 needs the ffmpeg backend (pip install imageio-ffmpeg); use gif")
    return fmt


def save_video(frames: np.ndarray, path: str, fps: float) -> str:
    """Write frames (T, H, W, 3) uint8 to ``path`` (.gif, or .mp4 with imageio-ffmpeg); returns the path."""
    import imageio.v2 as imageio

    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if path.endswith(".gif"):
        imageio.mimsave(path, list(frames), duration=1000.0 / fps, loop=0)
    else:
        imageio.mimsave(path, list(frames), fps=fps)
    return path


def save_episode_video(env: MjxEnv, result: rollout.EvalResult, recording: rollout.Recording, chunk_len: int,
                       path: str, *, episode: int | None = None, backend: str = "auto", height: int = 240,
                       width: int = 320) -> tuple[str, int]:
    """Render one episode of a recorded batched rollout (default: the first successful one, else episode 0),
    annotated with stride and entropy → (path, episode index)."""
    if episode is None:
        success = np.asarray(result.success)
        episode = int(np.argmax(success)) if success.any() else 0
    traj = trajectory_from_rollout(result, recording, episode, chunk_len)
    frames = render_frames(env, traj, height=height, width=width, backend=backend)
    save_video(annotate_frames(frames, traj), path, 1.0 / env.control_dt)
    return path, episode


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
