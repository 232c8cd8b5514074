"""Jitted ray-cast camera for the MJX tasks: RGB, depth and a workspace point cloud, with no host round trip.

One ray per pixel is cast with ``mujoco.mjx.ray`` against every visible geom (the tasks use only primitives). Colour
is the hit geom's rgba shaded by a Lambertian term (normals from the gradient of the hit-point map) plus ambient;
depth is the planar (optical-axis) depth in metres, 0 where nothing is hit. The point cloud is the hit points in
the world frame, cropped to an axis-aligned workspace box (by default above the table top, so the table is
removed), then down-sampled to a fixed number of points by random choice (``info['rng']``) or farthest-point
sampling. Every function works on one instance and runs under vmap + jit.

Shapes: image (H, W, 3) uint8; depth (H, W) float32; point_cloud (P, 3) or (P, 6) float32 (xyz, rgb in [0, 1]).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera looking from ``pos`` at ``lookat`` (world frame, z up), ``fovy`` degrees, H × W pixels.

    Point cloud: ``num_points`` points from the crop box [crop_low, crop_high], xyz (+ rgb if ``point_rgb``),
    down-sampled by ``sampling`` ('random' or 'fps').
    """

    height: int = 64
    width: int = 64
    fovy: float = 50.0
    pos: tuple[float, float, float] = (0.0, 0.5, 0.5)
    lookat: tuple[float, float, float] = (0.0, -0.05, 0.03)
    num_points: int = 512
    point_rgb: bool = False
    sampling: Literal["random", "fps"] = "random"
    crop_low: tuple[float, float, float] = (-0.35, -0.35, 0.003)
    crop_high: tuple[float, float, float] = (0.35, 0.35, 0.4)
    light_dir: tuple[float, float, float] = (0.3, 0.5, -1.0)
    ambient: float = 0.35
    background: tuple[float, float, float] = (0.55, 0.65, 0.8)

    def __post_init__(self):
        if self.height < 1 or self.width < 1:
            raise ValueError(f"camera height/width: must be >= 1, got {self.height}x{self.width}")
        if not 0.0 < self.fovy < 180.0:
            raise ValueError(f"camera.fovy: must be in (0, 180) degrees, got {self.fovy}")
        if self.num_points < 1:
            raise ValueError(f"camera.num_points: must be >= 1, got {self.num_points}")
        if self.sampling not in ("random", "fps"):
            raise ValueError(f"camera.sampling: must be 'random' or 'fps', got {self.sampling!r}")
        if np.allclose(self.pos, self.lookat):
            raise ValueError("camera.pos and camera.lookat must differ")


def camera_rays(config: CameraConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin (3,), unit ray directions (H, W, 3), optical axis (3,)) in the world frame; row 0 is the top."""
    pos, lookat = np.asarray(config.pos, np.float64), np.asarray(config.lookat, np.float64)
    forward = (lookat - pos) / np.linalg.norm(lookat - pos)
    up_hint = np.array([0.0, 0.0, 1.0]) if abs(forward[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    right = np.cross(forward, up_hint)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    f = 0.5 * config.height / np.tan(np.deg2rad(config.fovy) / 2)
    u = np.arange(config.width) + 0.5 - config.width / 2
    v = np.arange(config.height) + 0.5 - config.height / 2
    uu, vv = np.meshgrid(u, v)  # (H, W)
    dirs = forward * f + uu[..., None] * right - vv[..., None] * up
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return pos.astype(np.float32), dirs.astype(np.float32), forward.astype(np.float32)


def farthest_point_indices(points: jax.Array, valid: jax.Array, num: int) -> jax.Array:
    """Indices (num,) of a farthest-point sample of ``points`` (N, 3) restricted to ``valid`` (N,) bool points,
    starting from the first valid point. With fewer valid points than ``num`` the sample repeats points."""
    first = jnp.argmax(valid)
    dist0 = jnp.where(valid, jnp.inf, -1.0)

    def body(i, carry):
        idx, dist = carry
        last = points[idx[i - 1]]
        dist = jnp.where(valid, jnp.minimum(dist, jnp.sum((points - last) ** 2, axis=-1)), -1.0)
        return idx.at[i].set(jnp.argmax(dist)), dist

    idx = jnp.zeros((num,), jnp.int32).at[0].set(first)
    idx, _ = jax.lax.fori_loop(1, num, body, (idx, dist0))
    return idx


def random_point_indices(key: jax.Array, valid: jax.Array, num: int) -> jax.Array:
    """Indices (num,) of a uniformly random subset of the ``valid`` (N,) points, without replacement while there
    are enough; missing entries repeat the chosen valid points."""
    scores = jnp.where(valid, jax.random.uniform(key, valid.shape), -1.0)
    k = min(num, valid.shape[0])
    _, idx = jax.lax.top_k(scores, k)
    n_valid = jnp.minimum(valid.sum(), k)
    return idx[jnp.arange(num) % jnp.maximum(n_valid, 1)]


class Camera:
    """A fixed ray-cast camera for one MuJoCo model (holds only constants)."""

    def __init__(self, mj_model: mujoco.MjModel, config: CameraConfig = CameraConfig()):
        self.config = config
        origin, dirs, forward = camera_rays(config)
        self.origin = origin
        self.dirs = dirs
        self.forward = forward
        light = np.asarray(config.light_dir, np.float32)
        self.light = light / np.linalg.norm(light)
        self.geom_rgb = np.asarray(mj_model.geom_rgba[:, :3], np.float32)

    def cast(self, model: mjx.Model, data: mjx.Data) -> tuple[jax.Array, jax.Array]:
        """Ray distance (H, W) float32 (-1 where nothing is hit) and hit geom id (H, W) int32 (-1 likewise)."""
        h, w = self.config.height, self.config.width
        origin = jnp.asarray(self.origin)
        if model.mat_rgba.shape[0] == 0:
            # mjx.ray indexes mat_rgba even for geoms without a material; give a model without materials one row.
            model = model.replace(mat_rgba=jnp.ones((1, 4), jnp.float32))
        dist, geom = jax.vmap(lambda v: mjx.ray(model, data, origin, v))(jnp.asarray(self.dirs).reshape(-1, 3))
        return dist.reshape(h, w).astype(jnp.float32), geom.reshape(h, w).astype(jnp.int32)

    def render(self, model: mjx.Model, data: mjx.Data) -> dict[str, jax.Array]:
        """Everything the camera sees: ``rgb`` (H, W, 3) float32 in [0, 1], ``depth`` (H, W) planar depth (0 = no
        hit), ``points`` (H, W, 3) world hit points, ``hit`` (H, W) bool."""
        dist, geom = self.cast(model, data)
        hit = geom >= 0
        dirs = jnp.asarray(self.dirs)
        safe = jnp.where(hit, dist, 0.0)
        points = jnp.asarray(self.origin) + safe[..., None] * dirs
        depth = safe * (dirs @ jnp.asarray(self.forward))
        # Normals from the hit-point map: central differences, flipped to face the camera.
        dx = jnp.gradient(points, axis=1)
        dy = jnp.gradient(points, axis=0)
        normal = jnp.cross(dx, dy)
        normal = normal / (jnp.linalg.norm(normal, axis=-1, keepdims=True) + 1e-9)
        normal = jnp.where((jnp.sum(normal * dirs, -1) > 0)[..., None], -normal, normal)
        lambert = jnp.clip(-(normal @ jnp.asarray(self.light)), 0.0, 1.0)
        shade = self.config.ambient + (1.0 - self.config.ambient) * lambert
        base = jnp.asarray(self.geom_rgb)[jnp.maximum(geom, 0)]
        rgb = jnp.where(hit[..., None], base * shade[..., None], jnp.asarray(self.config.background))
        return {"rgb": jnp.clip(rgb, 0.0, 1.0), "depth": depth, "points": points, "hit": hit}

    def point_cloud(self, rendered: dict[str, jax.Array], key: jax.Array) -> jax.Array:
        """Cropped, down-sampled point cloud (P, 3 or 6) from ``render``'s output."""
        cfg = self.config
        pts = rendered["points"].reshape(-1, 3)
        inside = jnp.all((pts >= jnp.asarray(cfg.crop_low)) & (pts <= jnp.asarray(cfg.crop_high)), axis=-1)
        valid = rendered["hit"].reshape(-1) & inside
        if cfg.sampling == "fps":
            idx = farthest_point_indices(pts, valid, cfg.num_points)
        else:
            idx = random_point_indices(key, valid, cfg.num_points)
        out = pts[idx]
        if cfg.point_rgb:
            out = jnp.concatenate([out, rendered["rgb"].reshape(-1, 3)[idx]], axis=-1)
        # A view with no point in the crop box gives all zeros rather than background points.
        return jnp.where(valid.any(), out, 0.0).astype(jnp.float32)

    def observe(self, model: mjx.Model, data: mjx.Data, key: jax.Array,
                keys: tuple[str, ...] = ("image", "depth", "point_cloud")) -> dict[str, jax.Array]:
        """The camera observations named in ``keys`` ('image' uint8, 'depth', 'point_cloud')."""
        r = self.render(model, data)
        obs = {}
        if "image" in keys:
            obs["image"] = jnp.round(r["rgb"] * 255.0).astype(jnp.uint8)
        if "depth" in keys:
            obs["depth"] = r["depth"].astype(jnp.float32)
        if "point_cloud" in keys:
            obs["point_cloud"] = self.point_cloud(r, key)
        return obs
