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
    hand_eye_rotation,
    hand_eye_translation,
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


def rotation_pairs(R_camera_lidar: NDArray[np.float64], lidar: NDArray[np.float64], noise_deg: float,
                   seed: int) -> NDArray[np.float64]:
    rng = np.random.default_rng(seed)
    return np.asarray(lidar @ R_camera_lidar.T + rng.normal(scale=np.deg2rad(noise_deg), size=lidar.shape))


def random_axes(rng: np.random.Generator, n: int) -> NDArray[np.float64]:
    axes = rng.normal(size=(n, 3))
    return np.asarray(axes / np.linalg.norm(axes, axis=1, keepdims=True))


def test_hand_eye_rotation_with_axes_spread_over_3d() -> None:
    rng = np.random.default_rng(2)
    R_true = Rotation.random(random_state=rng).as_matrix()
    angles = np.deg2rad(rng.uniform(5.0, 20.0, 40))  # expected error about 0.07 deg at 0.05 deg noise
    angles[:4] = np.deg2rad(0.2)  # below 5 noise_deg: left out
    lidar = random_axes(rng, 40) * angles[:, None]
    result = hand_eye_rotation(rotation_pairs(R_true, lidar, 0.05, seed=3), lidar)
    assert result is not None
    assert angle_deg(result.R_camera_lidar, R_true) < 0.2
    assert result.pairs_used == 36
    assert result.free_axis_lidar is None
    assert result.free_angle_std_deg < 0.2  # 0.1 deg default noise over about 0.23 rad * sqrt(36 * 2 / 3)
    assert 0.05 < result.residual_deg < 0.15  # sqrt(3) * 0.05 deg per pair


def yaw_only(rng: np.random.Generator, n: int, tilt_deg: float = 0.0) -> NDArray[np.float64]:
    yaw = np.deg2rad(rng.uniform(2.0, 10.0, n) * rng.choice([-1.0, 1.0], n))
    tilt = np.deg2rad(rng.normal(scale=tilt_deg, size=(n, 2))) if tilt_deg else np.zeros((n, 2))
    return np.column_stack([tilt, yaw])


@pytest.mark.parametrize("tilt_deg", [0.0, 0.2])
def test_hand_eye_rotation_yaw_only_leaves_the_yaw_axis_free(tilt_deg: float) -> None:
    rng = np.random.default_rng(4)
    R_true = Rotation.from_euler("xyz", [2.0, -3.0, 5.0], degrees=True).as_matrix() @ R_FORWARD_MOUNT
    lidar = yaw_only(rng, 25, tilt_deg)
    result = hand_eye_rotation(rotation_pairs(R_true, lidar, 0.05, seed=5), lidar)
    assert result is not None and result.free_axis_lidar is not None
    assert result.free_angle_std_deg > 1.0
    assert abs(result.free_axis_lidar @ np.array([0.0, 0.0, 1.0])) > np.cos(np.deg2rad(2.0))
    mapped = result.R_camera_lidar @ result.free_axis_lidar
    assert np.rad2deg(np.arccos(min(abs(mapped @ (R_true @ result.free_axis_lidar)), 1.0))) < 0.2
    family = rotations_about(result.R_camera_lidar, result.free_axis_lidar, 360)
    assert family.shape == (360, 3, 3)
    assert min(angle_deg(R, R_true) for R in family) < 1.0


def test_hand_eye_rotation_with_large_tilts_is_determined() -> None:
    rng = np.random.default_rng(6)
    R_true = Rotation.random(random_state=rng).as_matrix()
    lidar = yaw_only(rng, 25, tilt_deg=3.0)  # pitch and roll of a few degrees: an uneven road
    result = hand_eye_rotation(rotation_pairs(R_true, lidar, 0.05, seed=7), lidar)
    assert result is not None and result.free_axis_lidar is None
    assert angle_deg(result.R_camera_lidar, R_true) < 0.5


def test_hand_eye_rotation_counts_pairs() -> None:
    R = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    one = np.deg2rad([[0.0, 0.0, 5.0]])
    single = hand_eye_rotation(one @ R.T, one)
    assert single is not None and single.pairs_used == 1 and single.free_axis_lidar is not None
    assert hand_eye_rotation(np.zeros((3, 3)), np.full((3, 3), 1e-4)) is None
    zero_weight = hand_eye_rotation(one @ R.T, one, weights=np.zeros(1))
    assert zero_weight is None
    with pytest.raises(InputError, match="rotations"):
        hand_eye_rotation(np.zeros((3, 3)), np.zeros((2, 3)))


def camera_motions_from(T_X: NDArray[np.float64], lidar_T: list[NDArray[np.float64]], rng: np.random.Generator,
                        noise_deg: float) -> list[CameraMotion]:
    """Camera motions ``T_A = T_X T_B T_X^-1`` with rotation and direction noise of ``noise_deg``."""
    out = []
    for T_B in lidar_T:
        T_A = T_X @ T_B @ tf.invert(T_X)
        jitter = Rotation.from_rotvec(rng.normal(scale=np.deg2rad(noise_deg), size=3)).as_matrix()
        direction = Rotation.from_rotvec(rng.normal(scale=np.deg2rad(noise_deg), size=3)).apply(T_A[:3, 3])
        out.append(CameraMotion(T_A[:3, :3] @ jitter, direction / np.linalg.norm(direction), 500, 20.0, 10.0))
    return out


def test_hand_eye_translation_with_3d_motion() -> None:
    rng = np.random.default_rng(8)
    T_X = tf.make_T(Rotation.random(random_state=rng).as_matrix(), [0.3, -0.2, 0.5])
    lidar_T = [tf.make_T(Rotation.from_rotvec(axis * np.deg2rad(rng.uniform(5, 15))).as_matrix(), rng.normal(size=3))
               for axis in random_axes(rng, 20)]
    motions = camera_motions_from(T_X, lidar_T, rng, noise_deg=0.05)
    result = hand_eye_translation(T_X[:3, :3], motions, np.array(lidar_T))
    assert result is not None
    assert np.max(np.abs(result.translation_m - T_X[:3, 3])) < 0.02
    assert np.all(result.observable) and result.free_directions_camera.shape == (0, 3)
    assert np.all((result.std_m > 1e-4) & (result.std_m < 0.02))
    assert result.pairs_used == 20 and np.all(result.scales_m > 0)


def planar_drive(rng: np.random.Generator, n: int, forward_only: bool) -> list[NDArray[np.float64]]:
    """Lidar motions that yaw about lidar z and move 1 m in the lidar's xy plane: along the mean
    heading (a car), or in any direction (a holonomic robot)."""
    out = []
    for _ in range(n):
        yaw = rng.uniform(-15.0, 15.0)
        heading = np.deg2rad(yaw / 2.0) + (0.0 if forward_only else rng.uniform(-np.pi, np.pi))
        out.append(tf.from_xyz_rpy(np.cos(heading), np.sin(heading), 0.0, 0.0, 0.0, yaw))
    return out


@pytest.mark.parametrize(("forward_only", "observable"), [(False, [True, False, True]), (True, [False, False, True])])
def test_hand_eye_translation_planar_motion_leaves_the_yaw_axis_free(forward_only: bool,
                                                                     observable: list[bool]) -> None:
    """Camera y points down the yaw axis: never observable. Driving only forward, the camera's travel
    direction hardly changes with its lateral offset (which changes the unknown scale instead), so
    camera x is flagged as well."""
    rng = np.random.default_rng(9)
    T_X = tf.make_T(Rotation.from_euler("xyz", [1.0, 2.0, -1.5], degrees=True).as_matrix() @ R_FORWARD_MOUNT,
                    [0.1, 0.4, -0.3])
    lidar_T = planar_drive(rng, 20, forward_only)
    result = hand_eye_translation(T_X[:3, :3], camera_motions_from(T_X, lidar_T, rng, 0.02), np.array(lidar_T))
    assert result is not None
    assert result.observable.tolist() == observable
    assert np.all(np.isinf(result.std_m[~result.observable]))
    assert np.all(result.std_m[result.observable] < 0.01)
    free = result.free_directions_camera
    assert free.shape == (observable.count(False), 3)
    yaw_axis = T_X[:3, :3] @ np.array([0.0, 0.0, 1.0])
    assert np.linalg.norm(free @ yaw_axis) > np.cos(np.deg2rad(0.5))  # the yaw axis lies in the free span
    error = result.translation_m - T_X[:3, 3]
    assert np.linalg.norm(error - free.T @ (free @ error)) < 0.02
    assert np.all(np.abs(free @ result.translation_m) < 1e-9)  # nothing invented along free directions


def test_hand_eye_translation_drops_reversed_and_undetermined_pairs() -> None:
    rng = np.random.default_rng(10)
    T_X = tf.make_T(Rotation.random(random_state=rng).as_matrix(), [0.2, 0.1, -0.4])
    lidar_T = [tf.make_T(Rotation.from_rotvec(axis * np.deg2rad(10.0)).as_matrix(), rng.normal(size=3))
               for axis in random_axes(rng, 12)]
    motions = camera_motions_from(T_X, lidar_T, rng, noise_deg=0.0)
    assert motions[0].direction_a is not None
    motions[0] = CameraMotion(motions[0].R_a_b, -motions[0].direction_a, 500, 20.0, 10.0)
    motions[1] = CameraMotion(motions[1].R_a_b, None, 500, 20.0, 0.2)
    result = hand_eye_translation(T_X[:3, :3], motions, np.array(lidar_T))
    assert result is not None and result.pairs_used == 10
    np.testing.assert_allclose(result.translation_m, T_X[:3, 3], atol=1e-6)
    assert hand_eye_translation(T_X[:3, :3], motions[:3], np.array(lidar_T[:3])) is None
    with pytest.raises(InputError, match="lidar motions"):
        hand_eye_translation(T_X[:3, :3], motions, np.array(lidar_T[:5]))


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
    assert hand_eye_rotation(np.stack([m.rotvec_a_b for m in motions]),
                             np.stack([Rotation.from_matrix(T[:3, :3]).as_rotvec() for T in lidar])
                             ).free_axis_lidar is not None  # type: ignore[union-attr]  # rotations alone: not whole


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
