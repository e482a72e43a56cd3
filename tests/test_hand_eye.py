"""Hand-eye initialisation: camera motion from rendered images, rotation and translation from synthetic pairs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

from fleetcal.pipeline import transforms as tf
from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import InputError
from fleetcal.stages.calibration.hand_eye import (
    CameraMotion,
    camera_motion,
    kabsch,
    motion_rotation,
    rotations_about,
)

K = np.array([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
PINHOLE = CameraModel(640, 480, K, np.zeros(0), "none")
PLUMB_BOB = CameraModel(640, 480, K, np.array([-0.28, 0.07, 0.001, -0.0005, -0.008]), "plumb_bob")
# A textured corridor in the frame of camera a (optical: x right, y down, z forward): plane n . p = c,
# with the two coordinates of p that index its texture.
CORRIDOR = [
    (np.array([1.0, 0.0, 0.0]), 4.0, (2, 1)),
    (np.array([1.0, 0.0, 0.0]), -4.0, (2, 1)),
    (np.array([0.0, 1.0, 0.0]), 1.6, (0, 2)),
    (np.array([0.0, 1.0, 0.0]), -2.5, (0, 2)),
    (np.array([0.0, 0.0, 1.0]), 12.0, (0, 1)),
]
TEXELS_PER_M = 32.0
# Lidar (x forward, y left, z up) to camera optical frame, as mounted facing forward.
R_FORWARD_MOUNT = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def angle_deg(R1: NDArray[np.float64], R2: NDArray[np.float64]) -> float:
    return float(np.rad2deg(Rotation.from_matrix(R1.T @ R2).magnitude()))


def textures(seed: int = 0) -> list[NDArray[np.float32]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in CORRIDOR:
        t = gaussian_filter(rng.random((512, 512)), 1.5, mode="wrap")
        out.append(((t - t.min()) / (t.max() - t.min()) * 255.0).astype(np.float32))
    return out


def render(camera: CameraModel, T_a_cam: NDArray[np.float64], tex: list[NDArray[np.float32]]) -> NDArray[np.uint8]:
    """Grey image of the corridor seen by a camera at pose ``T_a_cam`` (ray cast, nearest plane)."""
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    rays = camera.unproject(np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)) @ T_a_cam[:3, :3].T
    origin = T_a_cam[:3, 3]
    depth = np.full(len(rays), np.inf)
    image = np.zeros(len(rays), dtype=np.float32)
    for (normal, offset, axes), texture in zip(CORRIDOR, tex, strict=True):
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            lam = (offset - normal @ origin) / (rays @ normal)
            hit = (lam > 0) & (lam < depth)
            p = np.nan_to_num(origin + lam[:, None] * rays) * TEXELS_PER_M
        maps = [p[:, k].astype(np.float32).reshape(camera.height, camera.width) for k in axes]
        sampled = cv2.remap(texture, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP).ravel()
        image[hit], depth[hit] = sampled[hit], lam[hit]
    return np.clip(image, 0, 255).astype(np.uint8).reshape(camera.height, camera.width)


@pytest.fixture(scope="module")
def corridor() -> list[NDArray[np.float32]]:
    return textures()


def direction_error_deg(motion: CameraMotion, T_a_b: NDArray[np.float64]) -> float:
    assert motion.direction_a is not None
    truth = T_a_b[:3, 3] / np.linalg.norm(T_a_b[:3, 3])
    return float(np.rad2deg(np.arccos(np.clip(motion.direction_a @ truth, -1.0, 1.0))))


@pytest.mark.parametrize("camera", [PINHOLE, PLUMB_BOB], ids=["pinhole", "plumb_bob"])
def test_camera_motion_forward_with_yaw(camera: CameraModel, corridor: list[NDArray[np.float32]]) -> None:
    T_a_b = tf.from_xyz_rpy(0.0, 0.0, 1.0, 0.0, 3.0, 0.0)  # 1 m forward, 3 deg about the optical y axis
    motion = camera_motion(render(camera, np.eye(4), corridor), render(camera, T_a_b, corridor), camera)
    assert motion is not None
    assert angle_deg(motion.R_a_b, T_a_b[:3, :3]) < 0.3
    assert direction_error_deg(motion, T_a_b) < 2.0
    assert motion.inliers >= 200
    assert motion.translation_parallax_px > 3.0
    np.testing.assert_allclose(motion.rotvec_a_b, Rotation.from_matrix(motion.R_a_b).as_rotvec())


def test_camera_motion_sideways_gives_direction_in_frame_a(corridor: list[NDArray[np.float32]]) -> None:
    T_a_b = tf.from_xyz_rpy(0.5, 0.0, 0.0, 0.0, -2.0, 1.0)
    motion = camera_motion(render(PINHOLE, np.eye(4), corridor), render(PINHOLE, T_a_b, corridor), PINHOLE)
    assert motion is not None
    assert angle_deg(motion.R_a_b, T_a_b[:3, :3]) < 0.1
    assert direction_error_deg(motion, T_a_b) < 1.0


def test_camera_motion_pure_rotation(corridor: list[NDArray[np.float32]]) -> None:
    T_a_b = tf.from_xyz_rpy(0.0, 0.0, 0.0, 1.0, 2.5, -0.5)
    motion = camera_motion(render(PINHOLE, np.eye(4), corridor), render(PINHOLE, T_a_b, corridor), PINHOLE)
    assert motion is not None
    assert motion.direction_a is None
    assert motion.translation_parallax_px < 0.5
    assert motion.parallax_px > 10.0
    assert angle_deg(motion.R_a_b, T_a_b[:3, :3]) < 0.05
    assert motion.inliers >= 500


def test_camera_motion_blank_and_identical_textureless_images() -> None:
    blank = np.full((480, 640), 128, dtype=np.uint8)
    assert camera_motion(blank, blank, PINHOLE) is None
    ramp = np.tile(np.linspace(0, 255, 640).astype(np.uint8), (480, 1))
    assert camera_motion(ramp, ramp, PINHOLE) is None


def test_camera_motion_rejects_images_of_another_size() -> None:
    with pytest.raises(InputError, match="480x640"):
        camera_motion(np.zeros((240, 320), np.uint8), np.zeros((240, 320), np.uint8), PINHOLE)


def test_kabsch_recovers_proper_rotation() -> None:
    rng = np.random.default_rng(1)
    R = Rotation.random(random_state=rng).as_matrix()
    src = rng.normal(size=(20, 3))
    assert angle_deg(kabsch(src, src @ R.T), R) < 1e-9
    mirrored = src * np.array([1.0, 1.0, -1.0])  # no rotation fits; the answer must still be proper
    assert np.linalg.det(kabsch(src, mirrored)) == pytest.approx(1.0)


def random_axes(rng: np.random.Generator, n: int) -> NDArray[np.float64]:
    axes = rng.normal(size=(n, 3))
    return np.asarray(axes / np.linalg.norm(axes, axis=1, keepdims=True))


def camera_motions_from(T_X: NDArray[np.float64], lidar_T: list[NDArray[np.float64]], rng: np.random.Generator,
                        noise_deg: float) -> list[CameraMotion]:
    """Camera motions ``T_A = T_X T_B T_X^-1`` with rotation noise of ``noise_deg`` and no travel direction."""
    out = []
    for T_B in lidar_T:
        T_A = T_X @ T_B @ tf.invert(T_X)
        jitter = Rotation.from_rotvec(rng.normal(scale=np.deg2rad(noise_deg), size=3)).as_matrix()
        out.append(CameraMotion(T_A[:3, :3] @ jitter, None, 500, 20.0, 0.1))
    return out


def test_motion_rotation_from_turns_about_axes_spread_over_3d() -> None:
    rng = np.random.default_rng(3)
    R_true = Rotation.random(random_state=rng).as_matrix()
    T_X = tf.make_T(R_true, np.array([0.1, -0.2, 0.3]))
    lidar_T = [tf.make_T(Rotation.from_rotvec(axis * np.deg2rad(rng.uniform(1.0, 6.0))).as_matrix(), np.zeros(3))
               for axis in random_axes(rng, 40)]
    result = motion_rotation(camera_motions_from(T_X, lidar_T, rng, 0.05), np.stack(lidar_T))
    assert result is not None and result.free_axis_lidar is None and result.pairs_used == 40
    assert angle_deg(result.R_camera_lidar, R_true) < 0.2


def _drive(R_camera_lidar: NDArray[np.float64], t_camera_lidar: NDArray[np.float64], yaw_rates_deg: list[float],
           seed: int) -> tuple[list[CameraMotion], NDArray[np.float64]]:
    """Camera motions (with 0.05 deg rotation noise and 0.5 deg travel noise) and lidar ``T_a_b`` of a ground
    vehicle driving 1 m forward along lidar x per interval while yawing by the given angles."""
    rng = np.random.default_rng(seed)
    T_X = tf.make_T(R_camera_lidar, t_camera_lidar)
    motions, lidar = [], []
    for yaw in yaw_rates_deg:
        T_B = tf.make_T(Rotation.from_euler("z", yaw, degrees=True).as_matrix(), np.array([1.0, 0.0, 0.0]))
        T_A = T_X @ T_B @ tf.invert(T_X)
        R_A = Rotation.from_rotvec(np.deg2rad(rng.normal(0.0, 0.05, 3))).as_matrix() @ T_A[:3, :3]
        turn = Rotation.from_rotvec(np.deg2rad(rng.normal(0.0, 0.5, 3))).as_matrix()
        direction = turn @ T_A[:3, 3] / np.linalg.norm(T_A[:3, 3])
        motions.append(CameraMotion(R_A, direction, 100, 10.0, 5.0))
        lidar.append(T_B)
    return motions, np.stack(lidar)


def test_motion_rotation_of_a_car_that_turns_is_whole() -> None:
    """Turns give the up axis, travel the forward one: all three angles, despite yaw-only rotations."""
    R_true = Rotation.from_euler("xyz", [3.0, -2.0, 5.0], degrees=True).as_matrix() @ R_FORWARD_MOUNT
    motions, lidar = _drive(R_true, np.array([0.1, 0.3, -0.2]), [0.0, 0.2, 2.0, 4.0, 3.0, 0.0, 1.5], seed=3)
    result = motion_rotation(motions, lidar)
    assert result is not None and result.free_axis_lidar is None
    assert angle_deg(result.R_camera_lidar, R_true) < 0.5, angle_deg(result.R_camera_lidar, R_true)
    turns_only = [CameraMotion(m.R_a_b, None, m.inliers, m.parallax_px, 0.0) for m in motions]
    alone = motion_rotation(turns_only, lidar)  # the turns alone leave the angle about the up axis free
    assert alone is not None and alone.free_axis_lidar is not None and abs(alone.free_axis_lidar[2]) > 0.99


def test_motion_rotation_of_a_straight_drive_leaves_the_roll_about_the_travel_free() -> None:
    R_true = Rotation.from_euler("xyz", [90.0, 0.0, 90.0], degrees=True).as_matrix() @ R_FORWARD_MOUNT
    motions, lidar = _drive(R_true, np.zeros(3), [0.0] * 6, seed=4)
    result = motion_rotation(motions, lidar)
    assert result is not None and result.free_axis_lidar is not None
    assert abs(abs(result.free_axis_lidar[0]) - 1.0) < 1e-3  # lidar x, the direction of travel
    family = rotations_about(result.R_camera_lidar, result.free_axis_lidar, 360)
    assert min(angle_deg(R, R_true) for R in family) < 1.0


def test_motion_rotation_needs_motion() -> None:
    motions, lidar = _drive(R_FORWARD_MOUNT, np.zeros(3), [0.0, 1.0], seed=5)
    lidar[:, :3, 3] = 0.0
    lidar[:, :3, :3] = np.eye(3)
    assert motion_rotation(motions, lidar) is None
    with pytest.raises(InputError):
        motion_rotation(motions, lidar[:1])
