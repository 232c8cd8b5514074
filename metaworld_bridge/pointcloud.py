"""Point clouds of a Meta-World scene as DP3 makes them, ray-cast on the CPU (``mujoco.mj_multiRay``, no OpenGL).

DP3 (YanjieZe/3D-Diffusion-Policy, ``MetaWorldEnv``) renders a 128 × 128 depth image from the ``corner2`` camera
moved to (0.6, 0.295, 0.8) (orientation and fovy 60° unchanged), back-projects it, crops the points to a box and
farthest-point samples 512 of them. Here each pixel's ray is cast with ``mj_multiRay`` against the geoms a default
render shows (groups 0–2; transparent geoms are skipped by MuJoCo), so the hit points are the depth image
back-projected to world xyz, exactly.

DP3's crop box is given in its own point frame: its points are the camera-frame points (x right, y up, z towards the
viewer) rotated by Rx(61.4°)·Ry(−7°), a hand-tuned rotation that makes that frame's z nearly the world's up
(0.56° off) and turns x, y by 129.5° about it. The box x ∈ (−0.5, 1), y ∈ (−1.5, −0.4) is applied in that frame
exactly; it is an oriented rectangle on the table that drops the background and the region within 0.4 m of the
camera. Its floor z > −0.795 is the plane 5 mm above the table top (z = 0) in a levelled frame, but the 0.56° tilt
of the exact frame makes that plane cut through the table (keeping 60 % of the table's points); it is therefore
applied as z > 0.005 in the world frame, which is what DP3's bound means. The ceiling (z < 100) never binds.

Farthest-point sampling (numpy) starts from the first cropped point in raster order (row 0 = top of the image), so
a frame's cloud is deterministic; with fewer cropped points than asked the cropped points repeat cyclically, and a
view with none gives zeros (as the MJX tasks' camera).

Shapes: depth (H, W) float32 planar depth in metres (0 = no hit); points (P, 3) float32 world xyz.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

DP3_CAMERA = "corner2"
DP3_CAMERA_POS = (0.6, 0.295, 0.8)  # DP3 sets model.cam_pos[corner2] to this
DP3_IMAGE_SIZE = 128
DP3_NUM_POINTS = 512
DP3_FRAME_ANGLES_DEG = (61.4, -7.0)  # DP3's pc_transform: Rx(61.4°) @ Ry(-7°) applied to camera-frame points
DP3_CROP_LOW = (-0.5, -1.5, -0.795)  # in DP3's point frame
DP3_CROP_HIGH = (1.0, -0.4, 100.0)
DP3_FLOOR_Z = 0.005  # DP3's floor z > -0.795 below a camera at z = 0.8: 5 mm above the table top (z = 0)
VISIBLE_GEOM_GROUPS = (1, 1, 1, 0, 0, 0)  # what a default mjvOption renders


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """Pinhole camera ``camera`` of the model, placed at ``pos`` (None: where the model has it), ``size`` × ``size``
    rays; ``num_points`` points per cloud after DP3's crop."""

    size: int = DP3_IMAGE_SIZE
    num_points: int = DP3_NUM_POINTS
    camera: str = DP3_CAMERA
    pos: tuple[float, float, float] | None = DP3_CAMERA_POS

    def __post_init__(self):
        if self.size < 1:
            raise ValueError(f"camera size: must be >= 1, got {self.size}")
        if self.num_points < 1:
            raise ValueError(f"num_points: must be >= 1, got {self.num_points}")


def _rot_x(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), np.sin(a)], [0.0, -np.sin(a), np.cos(a)]])


def _rot_y(deg: float) -> np.ndarray:
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])


def farthest_point_indices(points: np.ndarray, num: int) -> np.ndarray:
    """Indices (num,) of a farthest-point sample of ``points`` (N, 3), starting from index 0. With N <= num every
    point is taken and the indices repeat cyclically; N = 0 gives an empty array."""
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    if n <= num:
        return np.arange(num) % n
    coords = np.ascontiguousarray(np.asarray(points, np.float64).T)  # (3, N): one contiguous row per axis
    idx = np.zeros(num, np.int64)
    dist = np.full(n, np.inf)  # squared distance of every point to the sample so far
    d, t = np.empty(n), np.empty(n)
    last = 0
    for i in range(1, num):
        d.fill(0.0)
        for axis in coords:  # in-place (x - x_last)^2 + ...: 3-4x faster than an (N, 3) difference per step
            np.subtract(axis, axis[last], out=t)
            t *= t
            d += t
        np.minimum(dist, d, out=dist)
        last = int(np.argmax(dist))
        idx[i] = last
    return idx


class PointCloudCamera:
    """DP3's point-cloud camera for one Meta-World model (holds only constants; reads ``MjData``, never writes it)."""

    def __init__(self, model: mujoco.MjModel, config: CameraConfig = CameraConfig()):
        self.config = config
        cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, config.camera)
        if cid < 0:
            raise ValueError(f"camera: the model has no camera {config.camera!r}")
        if model.cam_bodyid[cid] != 0 or model.cam_mode[cid] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED:
            raise ValueError(f"camera {config.camera!r}: expected a fixed camera of the world body")
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, model.cam_quat[cid])
        self.rot = rot.reshape(3, 3)  # columns: camera x (right), y (up), z (backwards) in the world frame
        self.pos = np.asarray(config.pos if config.pos is not None else model.cam_pos[cid], np.float64)
        h = w = config.size
        f = 0.5 * h / np.tan(np.deg2rad(model.cam_fovy[cid]) / 2)
        u = (np.arange(w) + 0.5 - w / 2) / f
        v = (np.arange(h) + 0.5 - h / 2) / f
        uu, vv = np.meshgrid(u, v)  # (H, W), row 0 at the top
        cam_dirs = np.stack([uu, -vv, -np.ones_like(uu)], axis=-1)  # unit optical-axis component: dist = depth
        self.dirs = np.ascontiguousarray((cam_dirs @ self.rot.T).reshape(-1, 3))
        # DP3's point frame (the crop is a fixed world region: it stays where DP3 has it whatever config.pos is)
        self.to_dp3 = _rot_x(DP3_FRAME_ANGLES_DEG[0]) @ _rot_y(DP3_FRAME_ANGLES_DEG[1]) @ self.rot.T
        self.dp3_origin = np.asarray(DP3_CAMERA_POS, np.float64)
        self._geomgroup = np.asarray(VISIBLE_GEOM_GROUPS, np.uint8)
        self._geomid = np.zeros(h * w, np.int32)
        self._dist = np.zeros(h * w, np.float64)

    def cast(self, model: mujoco.MjModel, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """World hit points (H·W, 3) and hit mask (H·W,) of every pixel's ray (``data``'s geom poses must be
        current: ``mj_kinematics`` or ``mj_forward`` after the last change of qpos)."""
        n = self.dirs.shape[0]
        mujoco.mj_multiRay(model, data, self.pos, self.dirs.reshape(-1), self._geomgroup, 1, -1, self._geomid,
                           self._dist, n, 100.0)
        hit = self._geomid >= 0
        dist = np.where(hit, self._dist, 0.0)
        return self.pos + dist[:, None] * self.dirs, hit

    def depth(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """Planar depth (H, W) float32 in metres, 0 where the ray hits nothing."""
        self.cast(model, data)
        hit = self._geomid >= 0
        s = self.config.size
        return np.where(hit, self._dist, 0.0).reshape(s, s).astype(np.float32)

    def crop_mask(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: which world points (N, 3) lie in DP3's crop (see the module docstring)."""
        local = (points - self.dp3_origin) @ self.to_dp3.T
        low, high = np.asarray(DP3_CROP_LOW), np.asarray(DP3_CROP_HIGH)
        in_xy = np.all((local[:, :2] > low[:2]) & (local[:, :2] < high[:2]), axis=1)
        return in_xy & (points[:, 2] > DP3_FLOOR_Z) & (local[:, 2] < high[2])

    def __call__(self, model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
        """The frame's point cloud (num_points, 3) float32, world xyz."""
        points, hit = self.cast(model, data)
        kept = points[hit & self.crop_mask(points)]
        idx = farthest_point_indices(kept, self.config.num_points)
        if idx.size == 0:
            return np.zeros((self.config.num_points, 3), np.float32)
        return kept[idx].astype(np.float32)
