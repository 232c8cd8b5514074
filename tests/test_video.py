"""Rollout videos: mp4 through PyAV (no fork of the JAX process), the imageio-ffmpeg and gif fallbacks, the camera
framed on each task's workspace (both renderers) and a silent OpenGL probe on a headless machine."""

import os
import subprocess
import sys
import warnings

import imageio.v3 as iio
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hipolicy_jax import envs
from hipolicy_jax.evaluation import video

FPS = 10.0


def _frames(t=5, h=24, w=32):
    """Smooth test frames (T, H, W, 3) uint8: colour gradients moving with t (they survive lossy coding)."""
    yy, xx = np.mgrid[0:h, 0:w]
    frames = [np.stack([(xx * 255 // max(w - 1, 1) + 20 * i) % 256, yy * 255 // max(h - 1, 1),
                        np.full_like(xx, 40 * i % 256)], axis=-1) for i in range(t)]
    return np.asarray(frames, np.uint8)


def _save_without_fork_warning(frames, path):
    jnp.ones(3).block_until_ready()  # JAX (and its fork warning hook) is up and multithreaded
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = video.save_video(frames, path, FPS)
    forks = [w for w in caught if "fork" in str(w.message)]
    assert not forks, [str(w.message) for w in forks]
    return out


def test_mp4_through_pyav_reads_back_as_h264(tmp_path):
    assert video.mp4_backend() == "pyav" and video.ffmpeg_available()  # av is a dependency
    frames = _frames()
    path = _save_without_fork_warning(frames, str(tmp_path / "sub" / "v.mp4"))
    assert path == str(tmp_path / "sub" / "v.mp4")
    back = iio.imread(path, plugin="pyav")
    assert back.shape == frames.shape and back.dtype == np.uint8
    assert np.abs(back.astype(int) - frames).mean() < 8
    meta = iio.immeta(path, plugin="pyav")
    assert meta["codec"] == "h264" and meta["video_format"] == "yuv420p" and meta["fps"] == pytest.approx(FPS)


def test_mp4_odd_sizes_are_padded_to_even(tmp_path):
    frames = _frames(t=3, h=23, w=31)
    back = iio.imread(video.save_video(frames, str(tmp_path / "odd.mp4"), FPS), plugin="pyav")
    assert back.shape == (3, 24, 32, 3)
    assert np.abs(back[:, :23, :31].astype(int) - frames).mean() < 8


def test_mp4_through_imageio_ffmpeg_when_pyav_is_missing(tmp_path, monkeypatch):
    if video._ffmpeg_exe() is None:
        pytest.skip("imageio-ffmpeg has no ffmpeg binary here")
    monkeypatch.setattr(video, "_pyav_encoder", lambda: None)
    assert video.mp4_backend() == "imageio-ffmpeg" and video.resolve_format("auto") == "mp4"
    frames = _frames(t=4, h=23, w=32)
    path = _save_without_fork_warning(frames, str(tmp_path / "ff.mp4"))
    back = iio.imread(path, plugin="pyav")
    assert back.shape == (4, 24, 32, 3)
    assert iio.immeta(path, plugin="pyav")["codec"] == "h264"


def test_gif_fallback_without_ffmpeg(tmp_path, monkeypatch):
    monkeypatch.setattr(video, "_pyav_encoder", lambda: None)
    monkeypatch.setattr(video, "_ffmpeg_exe", lambda: None)
    assert video.mp4_backend() is None and not video.ffmpeg_available()
    assert video.resolve_format("auto") == "gif" and video.resolve_format("none") == "none"
    with pytest.raises(ValueError, match="video_format: 'mp4' needs an FFmpeg backend"):
        video.resolve_format("mp4")
    frames = _frames(t=4)
    with pytest.warns(UserWarning, match="no FFmpeg backend"):
        path = video.save_video(frames, str(tmp_path / "v.mp4"), FPS)
    assert path == str(tmp_path / "v.gif") and not os.path.exists(tmp_path / "v.mp4")
    back = iio.imread(path, index=None)
    assert back.shape[:3] == frames.shape[:3]
    assert video.save_video(frames, str(tmp_path / "direct.gif"), FPS).endswith("direct.gif")


def test_format_and_input_errors_name_the_field(tmp_path):
    with pytest.raises(ValueError, match="video_format: must be 'auto', 'mp4', 'gif' or 'none', got 'webm'"):
        video.resolve_format("webm")
    with pytest.raises(ValueError, match="frames: must be"):
        video.save_video(_frames().astype(np.float32), str(tmp_path / "v.mp4"), FPS)
    with pytest.raises(ValueError, match="path: must end in .mp4 or .gif"):
        video.save_video(_frames(), str(tmp_path / "v.avi"), FPS)
    with pytest.raises(ValueError, match="fps: must be > 0"):
        video.save_video(_frames(), str(tmp_path / "v.mp4"), 0.0)
    with pytest.raises(ValueError, match="top: must be in"):
        video.frame_view(np.zeros((2, 3)), aspect=1.0, top=0.5)
    with pytest.raises(ValueError, match="points: need at least one"):
        video.frame_view(np.zeros((0, 3)), aspect=1.0)
    with pytest.raises(ValueError, match="backend: must be"):
        video.render_frames(envs.make("press_button"), _sketch_trajectory(envs.make("press_button")), backend="x")


_HEADLESS_PROBE = """
import os, sys
from hipolicy_jax.evaluation import video
print("MARK", flush=True)
print("MARK", file=sys.stderr, flush=True)
print("RESULT", video.opengl_available(), video.opengl_backend(), os.environ.get("MUJOCO_GL"), flush=True)
"""


def test_headless_opengl_probe_is_silent_and_leaves_mujoco_gl_alone():
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY",
                                                              "PYOPENGL_PLATFORM")}
    proc = subprocess.run([sys.executable, "-c", _HEADLESS_PROBE], env=env, capture_output=True, text=True,
                          timeout=120, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert proc.returncode == 0, proc.stderr
    # Only what the probe prints counts (importing mujoco.mjx prints its own notes first).
    assert proc.stderr.split("MARK\n", 1)[1] == "", proc.stderr
    result = proc.stdout.split("MARK\n", 1)[1].split()
    assert result[0] == "RESULT" and result[3] == "None", proc.stdout
    assert (result[1], result[2]) in (("True", "egl"), ("True", "osmesa"), ("False", "None")), proc.stdout


def test_mujoco_gl_disable_means_raycast(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "disable")
    assert not video.opengl_available() and video.opengl_backend() is None
    env = envs.make("press_button")
    with pytest.raises(RuntimeError, match="backend='opengl'"):
        video.render_frames(env, _sketch_trajectory(env), height=6, width=8, backend="opengl")


# ---------------------------------------------------------------------------------------------- framing
def _qadr(env, joint):
    return int(env.mj_model.jnt_qposadr[env.mj_model.joint(joint).id])


def _sketch_trajectory(env, body_xy=(0.1, -0.1)):
    """A 3-frame trajectory built on the host (no JAX compile): the hand at the far corner of the reset range
    (nearest to the camera, highest), above the task's randomised body and near the table; that body at body_xy."""
    body_pos = np.array([[body_xy[0], body_xy[1], 0.0]] * len(env.randomised_bodies))
    qpos = np.tile(np.asarray(env.mj_model.qpos0), (3, 1))
    for t, hand in enumerate([(-0.08, 0.16, 0.24), (body_xy[0], body_xy[1], 0.15), (body_xy[0], body_xy[1], 0.05)]):
        for joint, value in zip(("hand_x", "hand_y", "hand_z"), hand):
            qpos[t, _qadr(env, joint)] = value
    return video.Trajectory(qpos=qpos, body_pos=body_pos, steps=2, success=False)


def _tcp(env, qpos):
    return qpos[:, [_qadr(env, j) for j in ("hand_x", "hand_y", "hand_z")]]


def _foreground_fraction(frames):
    """Per frame (T,): fraction of pixels that differ from the most common colour (the floor)."""
    flat = frames.reshape(len(frames), -1, 3).astype(int)
    out = []
    for f in flat:
        colours, counts = np.unique(f, axis=0, return_counts=True)
        out.append(float(np.mean(np.abs(f - colours[np.argmax(counts)]).sum(-1) > 40)))
    return np.asarray(out)


@pytest.mark.parametrize("task", envs.TASKS)
def test_view_frames_gripper_and_objects(task):
    env = envs.make(task)
    traj = _sketch_trajectory(env)
    for h, w in ((240, 320), (48, 64)):
        view = video.episode_view(env, traj, height=h, width=w)
        model = video._episode_mj_model(env, traj.body_pos)
        uv = view.project(video.scene_points(model, traj.qpos), h, w)
        assert np.all((uv >= 0) & (uv < [w, h])), "every gripper / object box corner is in the picture"
        span = (uv.max(0) - uv.min(0)) / [w, h]
        assert span.max() > 0.85, f"the workspace fills the picture (span {span})"
        tcp = view.project(_tcp(env, traj.qpos), h, w)
        assert np.all((tcp >= 0) & (tcp < [w, h]))
        for name in env.randomised_bodies:  # the task's objects are in view
            corner = view.project(np.asarray(model.body(name).pos)[None], h, w)
            assert np.all((corner >= 0) & (corner < [w, h]))
        top = video.banner_height(h) / h  # room for annotate_frames' banner
        below = video.episode_view(env, traj, height=h, width=w, top=top).project(
            video.scene_points(model, traj.qpos), h, w)
        assert below[:, 1].min() >= top * h and below[:, 1].max() < h
        span = (below.max(0) - below.min(0)) / [w, (1 - top) * h]
        assert span.max() > 0.85, f"the workspace fills the picture below the banner (span {span})"
    if video.opengl_available():
        frames = video.render_frames(env, traj, height=48, width=64, backend="opengl")
        assert frames.shape == (3, 48, 64, 3)
        fg = _foreground_fraction(frames)
        assert np.all(fg > 0.05) and fg.max() > 0.15, f"gripper and objects cover a good part of each frame: {fg}"


def test_raycast_view_matches_projection():
    """The ray-cast camera uses the same view: the projected TCP lands on the gripper (not the floor)."""
    env = envs.make("stack_cubes")
    traj = _sketch_trajectory(env)
    h, w = 24, 32
    frames = video.render_frames(env, traj, height=h, width=w, backend="raycast")
    assert frames.shape == (3, h, w, 3) and frames.dtype == np.uint8
    assert np.all(_foreground_fraction(frames) > 0.08)
    if video.opengl_available():
        gl = video.render_frames(env, traj, height=h, width=w, backend="opengl")
        both = _foreground_fraction(frames) / _foreground_fraction(gl)
        assert np.all((both > 0.6) & (both < 1.6)), both  # same framing, different shading


def test_default_view_is_episode_view_and_an_explicit_one_is_used():
    env = envs.make("press_button")
    traj = _sketch_trajectory(env)
    traj = traj._replace(qpos=traj.qpos[:1])
    auto = video.render_frames(env, traj, height=24, width=32)
    framed = video.render_frames(env, traj, height=24, width=32, view=video.episode_view(env, traj, height=24,
                                                                                           width=32))
    np.testing.assert_array_equal(auto, framed)
    far = video.CameraView(lookat=(0.0, 0.0, 0.05), distance=1.2, elevation=-70.0)
    assert np.abs(video.render_frames(env, traj, height=24, width=32, view=far).astype(int) - auto).mean() > 10


@pytest.mark.slow
@pytest.mark.parametrize("task", envs.TASKS)
def test_expert_episode_is_framed(task, tmp_path):
    """A whole scripted-expert episode: the TCP stays in the picture, objects cover part of every frame, and the
    episode is written as a 10 fps mp4 of T+1 frames."""
    env = envs.make(task)
    traj = video.record_trajectory(env, jax.random.PRNGKey(0))
    assert traj.success
    h, w = 48, 64
    frames = video.render_frames(env, traj, height=h, width=w)
    assert frames.shape == (traj.steps + 1, h, w, 3)
    tcp = video.episode_view(env, traj, height=h, width=w).project(_tcp(env, traj.qpos), h, w)
    assert np.all((tcp >= 0) & (tcp < [w, h]))
    assert np.all(_foreground_fraction(frames) > 0.05)
    path = _save_without_fork_warning(frames, str(tmp_path / f"{task}.mp4"))
    assert iio.imread(path, plugin="pyav").shape == frames.shape
    assert iio.immeta(path, plugin="pyav")["fps"] == pytest.approx(1.0 / env.control_dt)
