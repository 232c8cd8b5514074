"""Ray-cast camera: depth of a known scene, colours, point-cloud count and bounds, sampling, vmap/jit, env obs."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from hipolicy_jax import envs
from hipolicy_jax.envs import camera as camera_lib

SCENE = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.01" rgba="0.5 0.5 0.5 1"/>
    <body name="box" pos="0 0 0.05">
      <joint name="slide" type="slide" axis="1 0 0"/>
      <geom name="box" type="box" size="0.05 0.05 0.05" rgba="1 0 0 1"/>
    </body>
  </worldbody>
</mujoco>
"""

# straight down from 0.5 m: image centre on the box top (z = 0.1), corners on the floor
CFG = camera_lib.CameraConfig(height=33, width=33, fovy=60.0, pos=(0.0, 0.0, 0.5), lookat=(0.0, 0.0, 0.0),
                              num_points=32, point_rgb=True, crop_low=(-1, -1, 0.003), crop_high=(1, 1, 1))


@pytest.fixture(scope="module")
def scene():
    m = mujoco.MjModel.from_xml_string(SCENE)
    mx = mjx.put_model(m)
    d = mjx.forward(mx, mjx.make_data(mx))
    return m, mx, d


def test_known_scene_depth_and_colour(scene):
    m, mx, d = scene
    cam = camera_lib.Camera(m, CFG)
    obs = jax.jit(lambda d, k: cam.observe(mx, d, k))(d, jax.random.PRNGKey(0))
    depth, image = np.asarray(obs["depth"]), np.asarray(obs["image"])
    assert depth.shape == (33, 33) and depth.dtype == np.float32
    assert image.shape == (33, 33, 3) and image.dtype == np.uint8
    np.testing.assert_allclose(depth[16, 16], 0.4, atol=1e-4)  # 0.5 m camera height - 0.1 m box top
    np.testing.assert_allclose(depth[0, 0], 0.5, atol=1e-4)  # planar depth of the floor at a corner
    r, g, b = image[16, 16].astype(int)
    assert r > 150 and g < 30 and b < 30  # red box, lit from above
    assert abs(int(image[0, 0, 0]) - int(image[0, 0, 1])) < 5  # grey floor


def test_point_cloud_count_and_bounds(scene):
    m, mx, d = scene
    cam = camera_lib.Camera(m, CFG)
    pc = np.asarray(jax.jit(lambda d, k: cam.observe(mx, d, k, ("point_cloud",)))(d, jax.random.PRNGKey(1))[
        "point_cloud"])
    assert pc.shape == (32, 6) and pc.dtype == np.float32
    # the crop removes the floor: every point is on the box's top face (z = 0.1, |x|, |y| <= 0.05)
    np.testing.assert_allclose(pc[:, 2], 0.1, atol=1e-4)
    assert (np.abs(pc[:, :2]) <= 0.05 + 1e-4).all()
    np.testing.assert_allclose(pc[:, 3:], np.broadcast_to([1, 0, 0], (32, 3)) * pc[:, 3:4], atol=1e-6)
    # random sampling without replacement while enough points are visible
    assert len(np.unique(pc[:, :3], axis=0)) == 32


def test_farthest_point_sampling():
    pts = jnp.array([[0.0, 0, 0], [1.0, 0, 0], [0.5, 0, 0], [0.9, 0, 0], [5.0, 0, 0]])
    valid = jnp.array([True, True, True, True, False])
    idx = np.asarray(camera_lib.farthest_point_indices(pts, valid, 3))
    assert list(idx) == [0, 1, 2]  # start, farthest valid, then the middle; the invalid far point is never used
    few = np.asarray(camera_lib.random_point_indices(jax.random.PRNGKey(0), valid, 6))
    assert set(few.tolist()) == {0, 1, 2, 3}


def test_camera_vmap_jit(scene):
    m, mx, d = scene
    cam = camera_lib.Camera(m, camera_lib.CameraConfig(height=16, width=16, pos=(0.0, 0.0, 0.5),
                                                       lookat=(0.0, 0.0, 0.0), sampling="fps", num_points=32))
    ds = jax.vmap(lambda x: mjx.forward(mx, d.replace(qpos=jnp.array([x]))))(jnp.array([0.0, 0.3]))
    out = jax.jit(jax.vmap(lambda d, k: cam.observe(mx, d, k)))(ds, jax.random.split(jax.random.PRNGKey(0), 2))
    assert out["image"].shape == (2, 16, 16, 3) and out["point_cloud"].shape == (2, 32, 3)
    # the box moved by 0.3 m in x: the centre pixel now sees the floor
    c = 8
    assert float(out["depth"][0, c, c]) < float(out["depth"][1, c, c]) - 0.05


def test_env_camera_observations():
    cfg = camera_lib.CameraConfig(height=24, width=24, num_points=128)
    env = envs.make("press_button", obs_keys=("state", "image", "depth", "point_cloud"), camera=cfg)
    assert env.obs_shapes == {"state": (7,), "image": (24, 24, 3), "depth": (24, 24), "point_cloud": (128, 3)}
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    for k, shape in env.obs_shapes.items():
        assert state.obs[k].shape == shape, k
    pc = np.asarray(state.obs["point_cloud"])
    assert np.isfinite(pc).all() and (pc[:, 2] >= cfg.crop_low[2]).all() and (np.abs(pc[:, :2]) <= 0.35).all()
    assert float(state.obs["depth"].max()) > 0.3
