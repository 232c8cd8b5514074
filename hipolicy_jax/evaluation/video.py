"""Videos of rollouts for humans: H.264 mp4 (gif when no FFmpeg backend is installed).

Frames come from MuJoCo's offscreen OpenGL renderer when an OpenGL platform works, otherwise from the jitted
ray-cast camera (``camera.py``). The platform follows ``MUJOCO_GL`` when it is set; unset, on a Linux machine
without a display, EGL is used (then OSMesa) instead of mujoco's default GLFW, silently (``opengl_backend``).

The camera is framed per episode from geometry, not per task: every visible bounded geom (the gripper and the task's
objects, the floor left out) over the whole trajectory, with the episode's randomised body placements, fits into
the picture seen from the front and above (``episode_view``, ``CameraView``), so a new task needs no camera edits.

The rollout is the evaluation's episode loop (``rollout.make_episode_fn`` with recording on), which records the
joint positions of every control step; frames are rendered afterwards on the host. ``trajectory_from_rollout``
takes an episode of a batched evaluation (``rollout.rollout_episodes``) instead, so a video of an evaluated policy
needs no second compile.

Videos play at the control rate (1 / ``env.control_dt``, 10 fps by default). mp4 is written in-process by PyAV
(libx264, yuv420p, odd sizes padded to even), or by imageio-ffmpeg's ffmpeg binary when PyAV is missing; neither
forks the multithreaded JAX process (imageio's ffmpeg plugin does, and JAX warns about it).

    python -m hipolicy_jax.evaluation.video --task latch_door --output door.mp4
    python -m hipolicy_jax.evaluation.video --task press_button --stride 2 --output press_x2.gif
"""

from __future__ import annotations

import argparse
import copy
import functools
import importlib
import os
import platform
import shutil
import subprocess
import warnings
from fractions import Fraction
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from hipolicy_jax import envs as envs_lib
from hipolicy_jax.envs import camera as camera_lib
from hipolicy_jax.evaluation import rollout
from hipolicy_jax.envs.base import MjxEnv


class Trajectory(NamedTuple):
    """One recorded episode: qpos (T+1, nq) from the reset on, body_pos (n, 3) the episode's randomised body
    placements, steps () control steps executed, success () bool; optionally the policy's per-decision entropy (R,),
    stride (R,) and start (R,), the control step each decision was taken at (to annotate frames, see
    ``annotate_frames``), for the decisions that happened."""

    qpos: np.ndarray
    body_pos: np.ndarray
    steps: int
    success: bool
    entropy: np.ndarray | None = None
    stride: np.ndarray | None = None
    start: np.ndarray | None = None


def _decisions(trace, index=()) -> dict:
    """The valid decisions of a trace (``rollout.Trace`` or ``EvalResult``, optionally of one episode)."""
    valid = np.asarray(trace.valid[index], bool)
    return {k: np.asarray(getattr(trace, k)[index])[valid] for k in ("entropy", "stride", "start")}


def trajectory_from_rollout(result: rollout.EvalResult, recording: rollout.Recording, episode: int) -> Trajectory:
    """Episode ``episode`` of a batched ``rollout.rollout_episodes`` result as a ``Trajectory``."""
    result, recording = jax.device_get((result, recording))
    steps = int(result.steps[episode])
    return Trajectory(qpos=np.asarray(recording.qpos[episode, :steps + 1]),
                      body_pos=np.asarray(recording.body_pos[episode]), steps=steps,
                      success=bool(result.success[episode]), **_decisions(result, episode))


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
    state, trace, rec = jax.device_get(jax.jit(episode)(key, policy_args))
    steps = int(state.step)
    return Trajectory(qpos=np.asarray(rec.qpos[:steps + 1]), body_pos=np.asarray(rec.body_pos), steps=steps,
                      success=bool(state.success), **_decisions(trace))


# ---------------------------------------------------------------------------------------------- OpenGL contexts
_GL_OFF = ("disable", "disabled", "off", "false", "0")
_GL_MODULES = {"egl": "mujoco.egl", "osmesa": "mujoco.osmesa", "glfw": "mujoco.glfw", "glx": "mujoco.glfw"}
_PROBE_XML = "<mujoco><worldbody/></mujoco>"


def _gl_candidates() -> tuple[str, ...]:
    """OpenGL platforms to try, in order: the one ``MUJOCO_GL`` names when set ('default' = mujoco's own choice,
    none when it disables rendering); unset, on Linux, GLFW then EGL and OSMesa with a display and only EGL then
    OSMesa without one (GLFW cannot work there and only prints errors), elsewhere mujoco's own choice."""
    requested = os.environ.get("MUJOCO_GL", "").lower().strip()
    if requested in _GL_OFF:
        return ()
    if requested:
        return (requested if requested in _GL_MODULES else "default",)
    if platform.system() != "Linux":
        return ("default",)
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return ("glfw", "egl", "osmesa")
    return ("egl", "osmesa")


def _context_class(name: str) -> type | None:
    """The ``GLContext`` class of a platform ('default': the one mujoco picked from ``MUJOCO_GL`` at import)."""
    if name == "default":
        return getattr(mujoco, "GLContext", None)
    before = os.environ.get("PYOPENGL_PLATFORM")
    try:
        return importlib.import_module(_GL_MODULES[name]).GLContext
    except Exception:
        # mujoco.egl / mujoco.osmesa set PYOPENGL_PLATFORM before importing PyOpenGL; undo it when that failed so
        # the next platform can still be tried.
        if before is None:
            os.environ.pop("PYOPENGL_PLATFORM", None)
        raise


def _gl_context() -> tuple[str, type] | None:
    """(platform name, ``GLContext`` class) of the first OpenGL platform that renders here, or None, probed with an
    8x8 context (a few ms; no state is kept between calls). GLFW's warnings about a missing display are silenced
    while probing."""
    for name in _gl_candidates():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                cls = _context_class(name)
                if cls is None:
                    continue
                _OffscreenRenderer(mujoco.MjModel.from_xml_string(_PROBE_XML), 8, 8, cls).close()
            except Exception:  # noqa: BLE001 - any GL failure means "try the next platform"
                continue
        return (cls.__module__.rsplit(".", 1)[-1] if name == "default" else name, cls)
    return None


def opengl_backend() -> str | None:
    """The OpenGL platform MuJoCo's offscreen renderer uses here ('egl', 'osmesa', 'glfw', ...), or None.

    ``MUJOCO_GL``, when set, is obeyed (and 'disable' means none). Unset, on a Linux machine without a display
    (``DISPLAY`` / ``WAYLAND_DISPLAY``), EGL is used (then OSMesa) instead of mujoco's default GLFW, which needs a
    display. The choice is made here, per call, rather than through ``MUJOCO_GL``: mujoco reads that variable once,
    when it is imported, and this module neither sets it nor depends on being imported first.
    """
    found = _gl_context()
    return found[0] if found else None


def opengl_available() -> bool:
    """Whether MuJoCo's offscreen OpenGL renderer works here (see ``opengl_backend``); prints nothing."""
    return _gl_context() is not None


class _OffscreenRenderer:
    """MuJoCo's offscreen OpenGL rendering (as ``mujoco.Renderer``) on a given ``GLContext`` class; mujoco.Renderer
    always uses the platform chosen when mujoco was imported. Grows the model's offscreen buffer to H × W."""

    def __init__(self, model: mujoco.MjModel, height: int, width: int, context_cls: type):
        vis = model.vis.global_
        vis.offwidth, vis.offheight = max(vis.offwidth, width), max(vis.offheight, height)
        self._model, self._height, self._width = model, height, width
        self._con = None
        self._gl = context_cls(vis.offwidth, vis.offheight)
        try:
            self._gl.make_current()
            if context_cls.__module__ == "mujoco.glfw":
                # GLFW only warns when it has no display. MjrContext must not be tried without a current context:
                # after that failure mujoco's GL loader aborts the process on any later MjrContext (mujoco 3.17).
                import glfw

                if not glfw.get_current_context():
                    raise RuntimeError("GLFW could not create an OpenGL context")
            self._con = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
        except BaseException:
            self.close()
            raise
        self._scene = mujoco.MjvScene(model, maxgeom=10000)  # as mujoco.Renderer
        self._option, self._perturb = mujoco.MjvOption(), mujoco.MjvPerturb()
        self._rect = mujoco.MjrRect(0, 0, width, height)

    def render(self, data: mujoco.MjData, camera: mujoco.MjvCamera) -> np.ndarray:
        """RGB image (H, W, 3) uint8 of ``data`` seen from ``camera``; row 0 is the top."""
        self._gl.make_current()
        mujoco.mjv_updateScene(self._model, data, self._option, self._perturb, camera, mujoco.mjtCatBit.mjCAT_ALL,
                               self._scene)
        mujoco.mjr_render(self._rect, self._scene, self._con)
        out = np.empty((self._height, self._width, 3), np.uint8)
        mujoco.mjr_readPixels(out, None, self._rect, self._con)
        return np.flipud(out)

    def close(self) -> None:
        if self._con is not None:
            self._con.free()
            self._con = None
        if self._gl is not None:
            self._gl.free()
            self._gl = None


# ---------------------------------------------------------------------------------------------- framing
class CameraView(NamedTuple):
    """A fixed camera without roll looking at ``lookat`` (3,) from ``distance`` metres, at ``azimuth`` and
    ``elevation`` degrees (MuJoCo's free-camera convention: azimuth -90 looks along -y, i.e. from the front of the
    tasks' scenes; elevation < 0 looks down), with a vertical field of view of ``fovy`` degrees."""

    lookat: tuple[float, float, float]
    distance: float
    azimuth: float = -90.0
    elevation: float = -45.0
    fovy: float = 30.0

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit (forward, right, up) vectors (3,) of the camera in the world frame (z up)."""
        az, el = np.deg2rad(self.azimuth), np.deg2rad(self.elevation)
        forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        right = np.array([np.sin(az), -np.cos(az), 0.0])
        return forward, right, np.cross(right, forward)

    def position(self) -> np.ndarray:
        """Camera position (3,) in the world frame."""
        return np.asarray(self.lookat, np.float64) - self.distance * self.axes()[0]

    def mjv_camera(self) -> mujoco.MjvCamera:
        """The view as a MuJoCo free camera (its field of view is the model's ``vis.global_.fovy``)."""
        cam = mujoco.MjvCamera()
        cam.type = mujoco.mjtCamera.mjCAMERA_FREE
        cam.lookat[:] = self.lookat
        cam.distance, cam.azimuth, cam.elevation = self.distance, self.azimuth, self.elevation
        return cam

    def camera_config(self, height: int, width: int) -> camera_lib.CameraConfig:
        """The view as a ray-cast ``camera.CameraConfig`` of H × W pixels."""
        return camera_lib.CameraConfig(height=height, width=width, fovy=self.fovy,
                                       pos=tuple(float(x) for x in self.position()),
                                       lookat=tuple(float(x) for x in self.lookat))

    def project(self, points: np.ndarray, height: int, width: int) -> np.ndarray:
        """Image coordinates (N, 2) = (column, row) of world points (N, 3) in an H × W image: pixel (i, j) spans
        [j, j + 1) × [i, i + 1), so a point is in the picture when 0 <= column < W and 0 <= row < H. Points behind
        the camera get NaN."""
        forward, right, up = self.axes()
        rel = np.asarray(points, np.float64).reshape(-1, 3) - self.position()
        depth = rel @ forward
        depth = np.where(depth > 1e-9, depth, np.nan)
        f = 0.5 * height / np.tan(np.deg2rad(self.fovy) / 2)
        return np.stack([0.5 * width + f * (rel @ right) / depth, 0.5 * height - f * (rel @ up) / depth], axis=-1)


def scene_points(model: mujoco.MjModel, qpos: np.ndarray) -> np.ndarray:
    """World corners (T·G·8, 3) of the bounding boxes of the G visible, bounded geoms of ``model`` (the gripper and
    the task's objects; planes and height fields such as the floor are left out) at each of the joint positions
    ``qpos`` (T, nq). Geoms are visible when their alpha is > 0 and their group is drawn by default (0–2)."""
    keep = ((model.geom_type != mujoco.mjtGeom.mjGEOM_PLANE) & (model.geom_type != mujoco.mjtGeom.mjGEOM_HFIELD)
            & (model.geom_rgba[:, 3] > 0) & (model.geom_group < 3))
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    aabb = model.geom_aabb[keep]
    local = aabb[:, None, :3] + signs[None] * aabb[:, None, 3:]  # (G, 8, 3) in each geom's frame
    data = mujoco.MjData(model)
    out = []
    for q in np.asarray(qpos).reshape(-1, model.nq):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        xmat = data.geom_xmat[keep].reshape(-1, 3, 3)
        out.append(data.geom_xpos[keep][:, None] + np.einsum("gij,gkj->gki", xmat, local))
    return np.concatenate(out).reshape(-1, 3) if out else np.zeros((0, 3))


def frame_view(points: np.ndarray, *, aspect: float, azimuth: float = -90.0, elevation: float = -45.0,
               fovy: float = 30.0, margin: float = 0.06, top: float = 0.0) -> CameraView:
    """The closest ``CameraView`` from direction (``azimuth``, ``elevation``) that shows every point of ``points``
    (N, 3) in an image of width / height ``aspect``, centred on the points' extent in the picture, with a
    ``margin`` fraction of each half-size of the image left free on every side and the top ``top`` fraction of the
    image height kept free as well (room for a banner, see ``annotate_frames``)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(points):
        raise ValueError("points: need at least one point to frame")
    if not 0.0 <= margin < 1.0:
        raise ValueError(f"margin: must be in [0, 1), got {margin}")
    if not 0.0 <= top < (1.0 - margin) / 2:
        raise ValueError(f"top: must be in [0, (1 - margin) / 2), got {top}")
    base = CameraView(lookat=(0.0, 0.0, 0.0), distance=1.0, azimuth=azimuth, elevation=elevation, fovy=fovy)
    forward, right, up = base.axes()
    # the window the points may use, in tangent units (offset / depth) from the optical axis
    t = np.tan(np.deg2rad(fovy) / 2)
    half_x, low_y, high_y = (1.0 - margin) * t * aspect, -(1.0 - margin) * t, (1.0 - margin - 2.0 * top) * t
    centre_y = 0.5 * (low_y + high_y)

    def fit(lookat):
        rel = points - lookat
        a, b, z = rel @ right, rel @ up, rel @ forward
        # every point in the window: |a| <= half_x (d + z) and low_y (d + z) <= b <= high_y (d + z)
        d = max(float(np.max(np.abs(a) / half_x - z)), float(np.max(b / high_y - z)),
                float(np.max(b / low_y - z)), float(np.max(-z)) + 1e-3)
        return d, a / (d + z), b / (d + z)

    lookat = 0.5 * (points.min(0) + points.max(0))
    for _ in range(8):  # move the look-at point until the points' projected extent is centred in the window
        d, x, y = fit(lookat)
        lookat = lookat + d * (0.5 * (x.max() + x.min()) * right + (0.5 * (y.max() + y.min()) - centre_y) * up)
    d, _, _ = fit(lookat)
    return base._replace(lookat=tuple(float(v) for v in lookat), distance=d)


def episode_view(env: MjxEnv, traj: Trajectory, *, height: int = 240, width: int = 320, azimuth: float = -90.0,
                 elevation: float = -45.0, fovy: float = 30.0, top: float = 0.0) -> CameraView:
    """The camera framed on an episode: every pose of the gripper and of the task's objects over the trajectory
    (with its randomised body placements) fits into an H × W picture, below its top ``top`` fraction
    (``frame_view`` of ``scene_points``)."""
    model = _episode_mj_model(env, traj.body_pos)
    return frame_view(scene_points(model, traj.qpos), aspect=width / height, azimuth=azimuth, elevation=elevation,
                      fovy=fovy, top=top)


def _episode_mj_model(env: MjxEnv, body_pos: np.ndarray) -> mujoco.MjModel:
    """A host copy of the env's model with the episode's randomised body placements ``body_pos`` (n, 3)."""
    model = copy.deepcopy(env.mj_model)
    for name, pos in zip(env.randomised_bodies, np.asarray(body_pos).reshape(-1, 3)):
        model.body(name).pos[:] = pos
    return model


def render_frames(env: MjxEnv, traj: Trajectory, *, height: int = 240, width: int = 320, backend: str = "auto",
                  view: CameraView | None = None) -> np.ndarray:
    """Frames (T+1, H, W, 3) uint8 of a trajectory. backend: 'opengl', 'raycast' or 'auto' (OpenGL if it works).

    ``view``: the camera; by default ``episode_view`` (framed on the gripper and objects over the whole episode).
    """
    if backend not in ("auto", "opengl", "raycast"):
        raise ValueError(f"backend: must be 'auto', 'opengl' or 'raycast', got {backend!r}")
    view = episode_view(env, traj, height=height, width=width) if view is None else view
    gl = _gl_context() if backend in ("auto", "opengl") else None
    if backend == "opengl" and gl is None:
        raise RuntimeError(f"backend='opengl': no OpenGL platform works here (MUJOCO_GL="
                           f"{os.environ.get('MUJOCO_GL', '')!r}); use backend='raycast'")
    if gl is not None:
        model = _episode_mj_model(env, traj.body_pos)
        model.vis.global_.fovy = view.fovy
        if model.nlight:  # the scene lights it: a dim headlight keeps colours from washing out
            model.vis.headlight.ambient[:], model.vis.headlight.diffuse[:] = 0.05, 0.25
        data = mujoco.MjData(model)
        cam = view.mjv_camera()
        renderer = _OffscreenRenderer(model, height, width, gl[1])
        frames = []
        try:
            for q in traj.qpos:
                data.qpos[:] = q
                mujoco.mj_forward(model, data)
                frames.append(renderer.render(data, cam))
        finally:
            renderer.close()
        return np.stack(frames)
    cam = camera_lib.Camera(env.mj_model, view.camera_config(height, width))
    mjx_model = env.episode_model({"body_pos": jnp.asarray(traj.body_pos)})

    @jax.jit
    def frame(q):
        data = mjx.forward(mjx_model, mjx.make_data(env.mjx_model).replace(qpos=q))
        return cam.observe(mjx_model, data, jax.random.PRNGKey(0), ("image",))["image"]

    return np.stack([np.asarray(frame(jnp.asarray(q))) for q in traj.qpos])


# One colour per stride (index = stride - 1, cycling), shared by frame annotations and entropy plots.
STRIDE_COLORS: tuple[tuple[int, int, int], ...] = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                                                  (148, 103, 189), (140, 86, 75))


def stride_color(stride: int) -> tuple[int, int, int]:
    """RGB (0-255) colour of an execution stride."""
    return STRIDE_COLORS[(int(stride) - 1) % len(STRIDE_COLORS)]


def banner_height(height: int) -> int:
    """Pixel rows of ``annotate_frames``' banner in frames of ``height`` rows."""
    return max(10, height // 12)


def _decision_at(traj: Trajectory, step: int) -> int:
    """Index of the decision whose actions drove control step ``step`` (the last one taken at or before it)."""
    return max(int(np.searchsorted(traj.start, step, side="right")) - 1, 0)


def annotate_frames(frames: np.ndarray, traj: Trajectory) -> np.ndarray:
    """Frames with a top banner naming the control step and, when ``traj`` has them, the stride (banner colour)
    and entropy of the chunk being executed. Frame i shows the state after step i, driven by the last decision
    taken at or before step i-1."""
    from PIL import Image, ImageDraw, ImageFont

    band = banner_height(frames.shape[1])
    font = ImageFont.load_default(size=max(8, band - 3))
    out = []
    for i, frame in enumerate(frames):
        img = Image.fromarray(np.asarray(frame))
        draw = ImageDraw.Draw(img)
        text, color = f"t={i}", (40, 40, 40)
        if traj.stride is not None and traj.start is not None and len(traj.stride):
            r = _decision_at(traj, max(i - 1, 0))
            color = stride_color(traj.stride[r])
            text += f"  stride {int(traj.stride[r])}"
            if traj.entropy is not None and np.isfinite(traj.entropy[r]):
                text += f"  H={float(traj.entropy[r]):.2f}"
        draw.rectangle((0, 0, img.width, band), fill=color)
        draw.text((3, 1), text, fill=(255, 255, 255), font=font)
        out.append(np.asarray(img))
    return np.stack(out)


# ---------------------------------------------------------------------------------------------- writing
_PYAV_ENCODERS = ("libx264", "libopenh264", "mpeg4")  # H.264 first: browsers and players open it


@functools.cache
def _pyav_encoder() -> str | None:
    """The first mp4 video encoder of ``_PYAV_ENCODERS`` that PyAV's FFmpeg libraries provide, or None."""
    try:
        import av
    except ImportError:
        return None
    for name in _PYAV_ENCODERS:
        try:
            av.codec.Codec(name, "w")
            return name
        except Exception:  # noqa: BLE001 - encoder not built into this FFmpeg
            continue
    return None


@functools.cache
def _ffmpeg_exe() -> str | None:
    """imageio-ffmpeg's ffmpeg binary (bundled, or a system one it found), or None."""
    try:
        import imageio_ffmpeg

        exe = imageio_ffmpeg.get_ffmpeg_exe()
        return exe if (os.path.exists(exe) or shutil.which(exe)) else None
    except Exception:  # noqa: BLE001 - not installed, or no binary for this platform
        return None


def mp4_backend() -> str | None:
    """What writes mp4 videos: 'pyav' (PyAV's in-process FFmpeg libraries, preferred: nothing is forked from the
    multithreaded JAX process), 'imageio-ffmpeg' (its ffmpeg binary, run as a subprocess) or None (gif only)."""
    if _pyav_encoder() is not None:
        return "pyav"
    if _ffmpeg_exe() is not None:
        return "imageio-ffmpeg"
    return None


def ffmpeg_available() -> bool:
    """Whether mp4 videos can be written (an FFmpeg backend: PyAV, else imageio-ffmpeg; see ``mp4_backend``)."""
    return mp4_backend() is not None


def resolve_format(fmt: str = "auto") -> str:
    """'mp4', 'gif' or 'none' for a requested video format: 'auto' is mp4 when an FFmpeg backend is available
    (``mp4_backend``), else gif."""
    if fmt not in ("auto", "mp4", "gif", "none"):
        raise ValueError(f"video_format: must be 'auto', 'mp4', 'gif' or 'none', got {fmt!r}")
    if fmt == "auto":
        return "mp4" if ffmpeg_available() else "gif"
    if fmt == "mp4" and not ffmpeg_available():
        raise ValueError("video_format: 'mp4' needs an FFmpeg backend (pip install av, or imageio-ffmpeg); "
                         "use 'gif' or 'auto'")
    return fmt


def _even_frames(frames: np.ndarray) -> np.ndarray:
    """Frames (T, H', W', 3) with H' and W' rounded up to even sizes (as H.264 in yuv420p needs) by repeating the
    last row / column."""
    pad_h, pad_w = frames.shape[1] % 2, frames.shape[2] % 2
    if pad_h or pad_w:
        frames = np.pad(frames, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    return frames


def _write_mp4_pyav(frames: np.ndarray, path: str, fps: float) -> None:
    import av

    codec = _pyav_encoder()
    with av.open(path, mode="w", options={"movflags": "+faststart"}) as container:
        stream = container.add_stream(codec, rate=Fraction(float(fps)).limit_denominator(1001))
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        if codec == "libx264":
            stream.options = {"crf": "20", "preset": "medium"}
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():  # flush the encoder
            container.mux(packet)


def _write_mp4_ffmpeg(frames: np.ndarray, path: str, fps: float) -> None:
    # The binary is run without a preexec_fn (imageio's ffmpeg plugin passes os.setpgrp), so subprocess execs it
    # without running Python fork handlers: JAX's "os.fork() was called" warning does not fire.
    rate = Fraction(float(fps)).limit_denominator(1001)
    cmd = [_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
           "-s", f"{frames.shape[2]}x{frames.shape[1]}", "-r", f"{rate.numerator}/{rate.denominator}", "-i", "-",
           "-an", "-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", "20", "-movflags", "+faststart", path]
    result = subprocess.run(cmd, input=np.ascontiguousarray(frames).tobytes(), capture_output=True,
                            start_new_session=True)
    if result.returncode != 0:
        raise RuntimeError(f"ffmpeg failed writing {path}: {result.stderr.decode(errors='replace').strip()}")


def save_video(frames: np.ndarray, path: str, fps: float) -> str:
    """Write frames (T, H, W, 3) uint8 at ``fps`` frames per second to ``path``; returns the path written.

    '.gif': an endlessly looping gif (Pillow). '.mp4': H.264 (yuv420p, odd H or W padded to even) through
    ``mp4_backend()``; with no FFmpeg backend the video is written as a gif next to it (``path`` with '.gif')
    instead, with a warning, and that path is returned. Nothing forks the (multithreaded) JAX process.
    """
    import imageio.v2 as imageio

    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or not len(frames):
        raise ValueError(f"frames: must be (T, H, W, 3) uint8 with T >= 1, got {frames.shape} {frames.dtype}")
    if not fps > 0:
        raise ValueError(f"fps: must be > 0, got {fps}")
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".gif", ".mp4"):
        raise ValueError(f"path: must end in .mp4 or .gif, got {path!r}")
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if ext == ".mp4":
        backend = mp4_backend()
        if backend is not None:
            frames = _even_frames(frames)
            (_write_mp4_pyav if backend == "pyav" else _write_mp4_ffmpeg)(frames, path, fps)
            return path
        path = os.path.splitext(path)[0] + ".gif"
        warnings.warn(f"no FFmpeg backend for mp4 (pip install av); writing {path} instead", stacklevel=2)
    imageio.mimsave(path, list(frames), duration=1000.0 / fps, loop=0)
    return path


def save_episode_video(env: MjxEnv, result: rollout.EvalResult, recording: rollout.Recording,
                       path: str, *, episode: int | None = None, backend: str = "auto", height: int = 240,
                       width: int = 320) -> tuple[str, int]:
    """Render one episode of a recorded batched rollout (default: the first successful one, else episode 0),
    annotated with stride and entropy, at the control rate 1 / env.control_dt → (path written, episode index); the
    path is ``path`` with '.gif' when an mp4 was asked for and no FFmpeg backend exists (see ``save_video``)."""
    if episode is None:
        success = np.asarray(result.success)
        episode = int(np.argmax(success)) if success.any() else 0
    traj = trajectory_from_rollout(result, recording, episode)
    # the camera keeps the gripper and objects below the banner
    view = episode_view(env, traj, height=height, width=width, top=min(banner_height(height) / height, 0.4))
    frames = render_frames(env, traj, height=height, width=width, backend=backend, view=view)
    path = save_video(annotate_frames(frames, traj), path, 1.0 / env.control_dt)
    return path, episode


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", required=True, choices=envs_lib.TASKS)
    p.add_argument("--output", default=None, help="default videos/<task>.mp4 (.gif without an FFmpeg backend)")
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
    output = args.output or os.path.join("videos", f"{args.task}.{resolve_format('auto')}")
    path = save_video(frames, output, 1.0 / env.control_dt)
    print(f"{args.task}: {traj.steps} steps, success {traj.success}, {len(frames)} frames -> {path}")


if __name__ == "__main__":
    main()
