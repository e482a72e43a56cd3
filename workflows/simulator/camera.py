"""Camera rendering by ray casting the scene through ``CameraModel.unproject``.

Pixel value = exposure x (spectral mix of albedo and reflectivity) x (ambient + diffuse sun shading),
sRGB gamma, slight Gaussian blur and sensor noise; rays that miss see a sky gradient. No shadows.
Camera frame: optical (x right, y down, z forward). A global-shutter image is cast from one camera pose, a
rolling-shutter image from one pose per image row (``row_times_s``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.special import ndtri

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import ConfigError, ProcessingError
from fleetcal.workflows.simulator.raycast import TriangleGrid, cast_rays, run_chunked
from fleetcal.workflows.simulator.raycast_kernels import shade_kernel
from fleetcal.workflows.simulator.scene import MATERIAL_ALBEDO, MATERIAL_REFLECTIVITY, Scene

SUN_DIR_WORLD = np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82])
SKY_RGB = np.array([0.55, 0.70, 0.95])


def pinhole_camera(width: int, height: int) -> CameraModel:
    """Pinhole camera, about 84 deg horizontal field of view, mild plumb_bob barrel distortion."""
    f = 0.55 * width
    K = np.array([[f, 0.0, width / 2 - 0.5 + 3.2], [0.0, f, height / 2 - 0.5 - 2.1], [0.0, 0.0, 1.0]])
    return CameraModel(width, height, K, np.array([-0.08, 0.02, 0.0004, -0.0003, 0.0]), "plumb_bob")


def rectified_stereo_camera(width: int, height: int) -> CameraModel:
    """One camera of a rectified stereo pair (``image_rect``): the pinhole's intrinsics, no distortion, and
    images taken in a frame turned 1.5 deg from the camera's own (its CameraInfo's rectification
    rotation R, as a stereo calibration writes it)."""
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    R_rect = Rotation.from_rotvec(np.radians(1.5) * axis).as_matrix()
    return CameraModel(width, height, pinhole_camera(width, height).K, np.zeros(0), "none", R_rect)


WIDE_ANGLE_D = np.array([-0.4398, 0.2329, -0.0011, 0.00021, -0.073])
"""plumb_bob coefficients (k1 k2 p1 p2 k3) of a real wide-angle lens (fx 897 px at 1280x720, about 105 deg
across the width): its radial map stops growing 50 deg off axis, inside the image's corners."""
WIDE_ANGLE_FX_PER_WIDTH = 897.0 / 1280.0


def wide_angle_camera(width: int, height: int) -> CameraModel:
    """Wide-angle pinhole with strong plumb_bob barrel distortion (``WIDE_ANGLE_D``, fx = 0.70 x width):
    the image's corners lie beyond the model's valid region (``CameraModel.max_undistorted_radius``) and
    render black."""
    f = WIDE_ANGLE_FX_PER_WIDTH * width
    K = np.array([[f, 0.0, width / 2 - 0.5], [0.0, f, height / 2 - 0.5], [0.0, 0.0, 1.0]])
    return CameraModel(width, height, K, WIDE_ANGLE_D.copy(), "plumb_bob")


def fisheye_camera(width: int, height: int) -> CameraModel:
    """Equidistant fisheye: 180 deg across the image width."""
    f = width / np.pi
    K = np.array([[f, 0.0, width / 2 - 0.5], [0.0, f, height / 2 - 0.5], [0.0, 0.0, 1.0]])
    return CameraModel(width, height, K, np.array([0.02, -0.004, 0.0008, 0.0]), "equidistant")


def panorama_camera(width: int, height: int) -> CameraModel:
    """Cylindrical panorama (the GOM paper's eq. 6, a Ladybug-style stitched image): 360 deg of azimuth
    across the width, +-45 deg of elevation (tan 1) over the height."""
    K = np.array([[width / (2 * np.pi), 0.0, width / 2 - 0.5], [0.0, height / 2, height / 2 - 0.5], [0.0, 0.0, 1.0]])
    return CameraModel(width, height, K, np.zeros(0), "cylindrical")


@dataclass
class SimCamera:
    """One simulated camera.

    Attributes:
        model: intrinsics.
        spectral_mix: 0 renders visible albedo, 1 renders lidar reflectivity (a near-infrared camera);
            values between mix the two.
        exposure: linear gain before gamma.
        blur_sigma_px: Gaussian blur (optics), pixels.
        noise_dn: standard deviation of the sensor noise, 8-bit digital numbers.
    """

    model: CameraModel
    spectral_mix: float = 0.0
    exposure: float = 1.4
    blur_sigma_px: float = 0.7
    noise_dn: float = 2.0
    _rays_cam: NDArray[np.float64] | None = field(default=None, repr=False)
    _ray_ok: NDArray[np.bool_] | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not 0.0 <= self.spectral_mix <= 1.0:
            raise ConfigError(f"spectral_mix must be in [0, 1], got {self.spectral_mix}")

    def rays(self) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """(H*W, 3) unit rays of the pixel centres (optical frame) and which pixels see the scene."""
        if self._rays_cam is None or self._ray_ok is None:
            m = self.model
            R = b"" if m.R_rect is None else m.R_rect.tobytes()
            key = (m.width, m.height, m.distortion_model, m.K.tobytes(), m.D.tobytes(), R)
            self._rays_cam, self._ray_ok = _pixel_rays(key, m)
            return self._rays_cam, self._ray_ok
        return self._rays_cam, self._ray_ok


_RAY_CACHE: dict[tuple[object, ...], tuple[NDArray[np.float64], NDArray[np.bool_]]] = {}


def _pixel_rays(key: tuple[object, ...], m: CameraModel) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Unit pixel rays of camera model ``m``, computed once per distinct model (``key``) per process."""
    cached = _RAY_CACHE.get(key)
    if cached is not None:
        return cached
    v, u = np.mgrid[0 : m.height, 0 : m.width]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    rays = m.unproject(uv)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    # a pixel sees the scene where its ray projects back onto it: not outside a fisheye's circle nor
    # beyond the valid region of a strongly distorted lens (there unproject gives the region's edge)
    uv_back, valid = m.project(rays)
    ok: NDArray[np.bool_] = np.asarray(valid & (np.abs(uv_back - uv).max(axis=1) < 0.01))
    rays[~ok] = (0.0, 0.0, 1.0)
    rays = np.ascontiguousarray(rays)
    rays.flags.writeable = False
    ok.flags.writeable = False
    if len(_RAY_CACHE) >= 4:
        _RAY_CACHE.pop(next(iter(_RAY_CACHE)))
    _RAY_CACHE[key] = (rays, ok)
    return rays, ok


def row_times_s(first_row_s: float, readout_s: float, height: int) -> NDArray[np.float64]:
    """(H,) exposure times (s, on the clock of ``first_row_s``) of image rows 0..H-1 of a rolling-shutter
    camera whose rows are exposed one after another over ``readout_s`` seconds from the first to the last:
    ``first_row_s + readout_s * r / (H - 1)``."""
    if not (np.isfinite(readout_s) and readout_s >= 0):
        raise ConfigError(f"readout must be a non-negative number of seconds, got {readout_s}")
    rows = np.arange(height, dtype=np.float64)
    return first_row_s + readout_s * rows / max(height - 1, 1)


def _world_rays(
    camera: SimCamera, T_world_camera: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(H*W, 3) ray origins and directions (world frame, m) of the pixel centres seen from one optical-frame
    pose (4, 4) or from one pose per image row (H, 4, 4); both C-contiguous."""
    rays_cam, _ = camera.rays()
    m = camera.model
    T = np.asarray(T_world_camera, dtype=np.float64)
    if T.shape == (4, 4):
        t = np.ascontiguousarray(T[:3, 3])
        dirs = np.ascontiguousarray(np.einsum("ij,kj->ik", rays_cam, T[:3, :3]))
        return np.ascontiguousarray(np.broadcast_to(t, dirs.shape)), dirs
    if T.shape != (m.height, 4, 4):
        raise ProcessingError(f"camera pose must be (4, 4) or one per image row ({m.height}, 4, 4), got {T.shape}")
    rows = rays_cam.reshape(m.height, m.width, 3)
    dirs = np.einsum("hwj,hij->hwi", rows, np.ascontiguousarray(T[:, :3, :3])).reshape(-1, 3)
    return np.ascontiguousarray(np.repeat(T[:, :3, 3], m.width, axis=0)), np.ascontiguousarray(dirs)


def render(
    scene: Scene,
    grid: TriangleGrid,
    camera: SimCamera,
    T_world_camera: NDArray[np.float64],
    rng: np.random.Generator,
    exposure_scale: float = 1.0,
    threads: int | None = None,
) -> NDArray[np.uint8]:
    """(H, W, 3) uint8 RGB image seen from ``T_world_camera``: the optical frame's pose in the world, (4, 4)
    for a global shutter, or (H, 4, 4) one pose per image row for a rolling shutter (row r is cast from
    ``T_world_camera[r]``; see ``row_times_s``).

    ``rng`` draws the sensor noise; ``exposure_scale`` multiplies the camera's exposure (auto-exposure drift).
    """
    m = camera.model
    _, ray_ok = camera.rays()
    origins, dirs = _world_rays(camera, T_world_camera)
    t_hit, tri = cast_rays(grid, origins, dirs, t_max=500.0, threads=threads)
    rgb = np.empty((dirs.shape[0], 3), dtype=np.float32)
    gain = float(camera.exposure * exposure_scale)

    def work(a: int, b: int) -> None:
        shade_kernel(
            origins[a:b],
            dirs[a:b],
            ray_ok[a:b],
            t_hit[a:b],
            tri[a:b],
            scene.normals,
            scene.tex_origin,
            scene.tex_u,
            scene.tex_v,
            scene.tex_scale_m,
            scene.tex_kind,
            scene.tex_seed,
            scene.mat_a,
            scene.mat_b,
            MATERIAL_ALBEDO,
            MATERIAL_REFLECTIVITY,
            SUN_DIR_WORLD,
            SKY_RGB,
            float(camera.spectral_mix),
            gain,
            2.2,
            rgb[a:b],
        )

    run_chunked(dirs.shape[0], work, threads)
    img: NDArray[np.float32] = rgb.reshape(m.height, m.width, 3)
    if camera.blur_sigma_px > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), camera.blur_sigma_px), dtype=np.float32)
    img += np.take(_gaussian_lut(camera.noise_dn), rng.integers(0, 256, size=img.shape, dtype=np.uint8))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@cache
def _gaussian_lut(sigma: float) -> NDArray[np.float32]:
    """256 equiprobable quantiles of N(0, sigma^2): indexing it with uniform bytes gives Gaussian noise
    (4x cheaper than ``standard_normal`` on 2.7 M pixels)."""
    return np.asarray(sigma * ndtri((np.arange(256) + 0.5) / 256), dtype=np.float32)


def render_depth(
    grid: TriangleGrid, camera: SimCamera, T_world_camera: NDArray[np.float64], threads: int | None = None
) -> NDArray[np.float32]:
    """(H, W) float32 z-depth (m, along the optical axis) of the first surface per pixel; NaN where none.

    ``T_world_camera``: as in ``render``, (4, 4) or one pose per image row (H, 4, 4); each row's depth is
    along the optical axis of its own pose.
    """
    rays_cam, ray_ok = camera.rays()
    origins, dirs = _world_rays(camera, T_world_camera)
    t_hit, tri = cast_rays(grid, origins, dirs, t_max=500.0, threads=threads)
    depth = np.where((tri >= 0) & ray_ok, t_hit * rays_cam[:, 2], np.nan)
    return depth.reshape(camera.model.height, camera.model.width).astype(np.float32)
