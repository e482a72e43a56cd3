"""Lidar-camera rotation from motion (hand-eye calibration, ``A X = X B``).

Over one time interval the camera moves by ``T_A = T_ca_cb`` (pose of the camera at time b in the
camera at time a) and the lidar by ``T_B = T_la_lb``. With the unknown ``T_X = T_camera_lidar``
(``p_camera = T_X @ p_lidar``), ``T_A = T_X T_B T_X^-1``, so

- rotation: ``R_A R_X = R_X R_B``, i.e. ``rotvec(R_A) = R_X @ rotvec(R_B)``;
- translation: ``R_A t_X + t_A = R_X t_B + t_X``: the camera travels along ``R_X t_B`` up to the lever arm
  ``(I - R_A) t_X``, known from images only as a direction ``u``.

``camera_motion`` measures ``R_A`` and ``u`` from two images; ``motion_rotation`` solves ``R_X`` from both
(rotation axes and directions of travel). Motion about and along one axis only (a straight drive) leaves
``R_X`` free about it, which the result reports instead of inventing a value. The translation ``t_X`` is
not solved: from a car's motion only its component along the travel shows, as a change of the travel's
direction by ``|R_A - I| |t_X| / |t_B|`` (about 2 cm in 0.8 m on a simulated drive), below the directions'
noise; solved, it came out 0.4 m off (``docs/accuracy.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import InputError

FloatArray = NDArray[np.float64]

_MIN_RAY_Z = 0.1  # rays beyond ~84 deg off the optical axis have no usable normalised coordinates


@dataclass(frozen=True)
class CameraMotion:
    """Motion of one camera between two images a and b.

    Attributes:
        R_a_b: (3, 3) rotation of the camera at b expressed in the camera at a (rotation of ``T_a_b``).
        direction_a: (3,) unit direction of the camera centre at b in the camera frame at a (the
            translation of ``T_a_b`` up to scale); None when the parallax left after removing the
            rotation is too small to determine it (a rotation-only motion or a distant scene).
        inliers: feature tracks consistent with the fitted motion.
        parallax_px: median displacement of the tracked features, pixels.
        translation_parallax_px: median displacement left after removing the best pure rotation,
            pixels; the part of the image motion that only translation explains.
    """

    R_a_b: FloatArray
    direction_a: FloatArray | None
    inliers: int
    parallax_px: float
    translation_parallax_px: float

    @property
    def rotvec_a_b(self) -> FloatArray:
        """(3,) rotation vector of ``R_a_b``, radians, in the camera frame at a."""
        return np.asarray(Rotation.from_matrix(self.R_a_b).as_rotvec())


@dataclass(frozen=True)
class HandEyeRotation:
    """Rotation ``R_camera_lidar`` from motion (``motion_rotation``).

    Attributes:
        R_camera_lidar: (3, 3) rotation of ``T_camera_lidar``. When ``free_axis_lidar`` is set, the
            rotation about that axis is arbitrary (see ``rotations_about``).
        pairs_used: vector pairs used (rotation axes of intervals that turned enough, directions of travel).
        residual_deg: weighted RMS angle between each camera vector and its lidar vector turned by
            ``R_camera_lidar``, degrees.
        free_angle_std_deg: standard deviation of the rotation about the lidar vectors' dominant direction,
            degrees; inf when nothing fixes it.
        free_axis_lidar: (3,) unit axis in the lidar frame (sign arbitrary) about which the rotation is
            not determined (every lidar vector nearly parallel to it); None when fully determined.
    """

    R_camera_lidar: FloatArray
    pairs_used: int
    residual_deg: float
    free_angle_std_deg: float
    free_axis_lidar: FloatArray | None


def kabsch(source: FloatArray, target: FloatArray, weights: FloatArray | None = None) -> FloatArray:
    """Rotation R (3, 3) minimising ``sum w |target - R source|^2`` over (N, 3) vector pairs (SVD,
    with the determinant corrected so that R is proper)."""
    w = np.ones(len(source)) if weights is None else weights
    H = (source * w[:, None]).T @ target
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    return np.asarray(Vt.T @ np.diag([1.0, 1.0, d]) @ U.T)


def _check_images(grey_a: NDArray[np.uint8], grey_b: NDArray[np.uint8], camera: CameraModel) -> None:
    for grey in (grey_a, grey_b):
        if grey.dtype != np.uint8 or grey.shape != (camera.height, camera.width):
            raise InputError(f"camera_motion needs uint8 images of {camera.height}x{camera.width}, "
                             f"got {grey.dtype} {grey.shape}")


def _track(grey_a: NDArray[np.uint8], grey_b: NDArray[np.uint8], max_features: int,
           max_fb_error_px: float) -> tuple[FloatArray, FloatArray]:
    """Pixels (M, 2) in a and b of corners tracked a -> b and back to within ``max_fb_error_px``."""
    corners = cv2.goodFeaturesToTrack(grey_a, maxCorners=max_features, qualityLevel=0.01, minDistance=7)
    if corners is None:
        return np.zeros((0, 2)), np.zeros((0, 2))
    p_a = corners.astype(np.float32).reshape(-1, 1, 2)
    p_b, ok_ab, _ = cv2.calcOpticalFlowPyrLK(grey_a, grey_b, p_a, np.empty_like(p_a), winSize=(21, 21), maxLevel=3)
    p_back, ok_ba, _ = cv2.calcOpticalFlowPyrLK(grey_b, grey_a, p_b, np.empty_like(p_a), winSize=(21, 21),
                                                maxLevel=3)
    fb = np.linalg.norm((p_back - p_a).reshape(-1, 2), axis=1)
    keep = (ok_ab.ravel() == 1) & (ok_ba.ravel() == 1) & (fb < max_fb_error_px)
    return p_a.reshape(-1, 2)[keep].astype(np.float64), p_b.reshape(-1, 2)[keep].astype(np.float64)


def _bearings(camera: CameraModel, uv: FloatArray) -> FloatArray:
    rays = camera.unproject(uv)
    return np.asarray(rays / np.linalg.norm(rays, axis=1, keepdims=True))


def _angles(R: FloatArray, f_a: FloatArray, f_b: FloatArray) -> FloatArray:
    """Angles (rad) between the bearings ``f_b`` and ``R @ f_a``."""
    return np.asarray(np.arccos(np.clip(np.sum((f_a @ R.T) * f_b, axis=1), -1.0, 1.0)))


def _pure_rotation(f_a: FloatArray, f_b: FloatArray, tolerance_rad: float) -> tuple[FloatArray, FloatArray]:
    """``R_b_a`` with ``f_b ~ R_b_a f_a`` (Kabsch, refitted on the tracks within ``tolerance_rad`` or
    3 median residuals) and the residual angles (rad) of all tracks."""
    R = kabsch(f_a, f_b)
    for _ in range(2):
        err = _angles(R, f_a, f_b)
        keep = err < max(tolerance_rad, 3.0 * float(np.median(err)))
        R = kabsch(f_a[keep], f_b[keep])
    return R, _angles(R, f_a, f_b)


def _essential_motion(f_a: FloatArray, f_b: FloatArray, threshold: float) -> tuple[FloatArray, FloatArray, int]:
    """(R_a_b, unit direction of b's centre in a, cheirality inliers) from the essential matrix of
    normalised coordinates; inliers is 0 when no essential matrix was found."""
    x_a = np.ascontiguousarray(f_a[:, :2] / f_a[:, 2:])
    x_b = np.ascontiguousarray(f_b[:, :2] / f_b[:, 2:])
    E, mask = cv2.findEssentialMat(x_a, x_b, np.eye(3), method=cv2.USAC_ACCURATE, prob=0.999, threshold=threshold)
    if E is None or E.shape[0] < 3:
        return np.eye(3), np.zeros(3), 0
    inliers, R_b_a, t_b_a, _ = cv2.recoverPose(E[:3], x_a, x_b, np.eye(3), mask=mask)
    centre_a = -R_b_a.T @ t_b_a.ravel()
    return np.asarray(R_b_a.T), centre_a / max(float(np.linalg.norm(centre_a)), 1e-12), int(inliers)


def camera_motion(grey_a: NDArray[np.uint8], grey_b: NDArray[np.uint8], camera: CameraModel,
                  max_features: int = 1000, min_inliers: int = 30, threshold_px: float = 1.0,
                  min_parallax_px: float = 1.0) -> CameraMotion | None:
    """Relative motion of a camera between two grey images (uint8, height x width).

    Corners of a are tracked into b by pyramidal Lucas-Kanade and kept when tracking back lands within
    ``threshold_px``; their pixels become bearings through ``camera.unproject`` (distortion removed).
    The best pure rotation is fitted to the unit bearings (Kabsch: a pure rotation maps them exactly,
    ``f_b = R_b_a f_a``, for any scene depth); the median parallax it leaves is what only translation
    explains. At or above ``min_parallax_px`` (1 px: several times the tracking noise of about 0.1 px,
    so the direction of travel stands out of it) the essential matrix of the normalised coordinates
    (OpenCV's USAC_ACCURATE, a RANSAC with local optimisation and a final polish, inlier threshold
    ``threshold_px / f``) and the cheirality test give the rotation and the direction of travel.
    Below it the essential matrix is degenerate (any translation fits a pure rotation), and so is a
    matrix without ``min_inliers`` tracks in front of both cameras: the pure rotation is returned
    with no direction, its error bounded by the neglected parallax (``translation_parallax_px / f``).

    Args:
        grey_a, grey_b: images at times a and b, of the camera's size.
        camera: intrinsics of the camera that took both images.
        max_features: most corners tracked.
        min_inliers: fewest consistent tracks for a result.
        threshold_px: forward-backward tracking and epipolar tolerance, pixels.
        min_parallax_px: rotation-compensated median parallax above which the translation direction
            is estimated, pixels.

    Returns:
        The motion, or None when fewer than ``min_inliers`` tracks agree (a textureless or blank pair).
    """
    _check_images(grey_a, grey_b, camera)
    uv_a, uv_b = _track(grey_a, grey_b, max_features, threshold_px)
    f_a, f_b = _bearings(camera, uv_a), _bearings(camera, uv_b)
    front = (f_a[:, 2] > _MIN_RAY_Z) & (f_b[:, 2] > _MIN_RAY_Z)
    if np.count_nonzero(front) < min_inliers:
        return None
    f_a, f_b = f_a[front], f_b[front]
    focal = 0.5 * (camera.fx + camera.fy)
    parallax_px = float(np.median(np.linalg.norm(uv_b[front] - uv_a[front], axis=1)))
    R_b_a, err = _pure_rotation(f_a, f_b, (threshold_px + min_parallax_px) / focal)
    translation_px = float(np.median(err)) * focal
    if translation_px >= min_parallax_px:
        R_a_b, direction, inliers = _essential_motion(f_a, f_b, threshold_px / focal)
        if inliers >= min_inliers:
            return CameraMotion(R_a_b, direction, inliers, parallax_px, translation_px)
    inliers = int(np.count_nonzero(err < (threshold_px + min_parallax_px) / focal))
    if inliers < min_inliers:
        return None
    return CameraMotion(np.asarray(R_b_a.T), None, inliers, parallax_px, translation_px)


def rotations_about(R_camera_lidar: FloatArray, free_axis_lidar: FloatArray, n: int) -> FloatArray:
    """(n, 3, 3) rotations ``R_camera_lidar @ Rot(free_axis_lidar, theta)``, theta = 360 deg k / n.

    Every member satisfies the same hand-eye rotation equations when the lidar rotations are about
    ``free_axis_lidar``: the one-dimensional family that a search over the free angle scores.
    """
    axis = np.asarray(free_axis_lidar, dtype=np.float64)
    theta = 2.0 * np.pi * np.arange(n) / n
    spins = Rotation.from_rotvec(theta[:, None] * (axis / np.linalg.norm(axis))[None, :]).as_matrix()
    return np.asarray(np.einsum("ij,njk->nik", R_camera_lidar, spins))


TRAVEL_NOISE_DEG = 1.0
"""Direction noise of a camera's travel measured from two images, degrees (besides the lever arm)."""
LEVER_M = 2.0
"""Largest camera-lidar distance assumed: a turn of theta moves the camera's travel by up to
``theta * LEVER_M`` off the lidar's turned travel (``t_A = R_X t_B + (I - R_A) t_X``)."""


def motion_rotation(camera_motions: list[CameraMotion], lidar_T_a_b: NDArray[np.floating],
                    noise_deg: float = 0.1, max_free_std_deg: float = 1.5) -> HandEyeRotation | None:
    """``R_camera_lidar`` from both what motion tells about it: each interval's rotation axis
    (``rotvec_camera = R_X rotvec_lidar``) and, where the camera measured it, its direction of travel
    (``u = R_X t_B / |t_B|`` up to the lever arm ``(I - R_A) t_X``). A ground vehicle that drives and turns
    fixes all three angles: its turns give the up axis and its travel the forward one.

    Each pair of unit vectors is weighted by the inverse square of its angular noise: a rotation axis by
    ``noise_deg`` over its angle, a travel direction by ``TRAVEL_NOISE_DEG`` plus the lever arm's
    ``theta * LEVER_M / |t_B|``. The rotation about the dominant lidar vector is free when its standard
    deviation ``1 / sqrt(l2 + l3)`` (eigenvalues of the weighted scatter, rad^-2) exceeds
    ``max_free_std_deg`` (1.5 deg: a third of the +-4.5 deg that ``initialisation`` searches around a
    rotation from motion).

    Args:
        camera_motions: the camera's motion over each interval (``camera_motion``).
        lidar_T_a_b: (N, 4, 4) the lidar's motion over the same intervals (``T_la_lb``).

    Returns:
        The rotation, or None where no interval turned or travelled enough to say anything.
    """
    T_B = np.asarray(lidar_T_a_b, dtype=np.float64).reshape(-1, 4, 4)
    if len(camera_motions) != T_B.shape[0]:
        raise InputError(f"{len(camera_motions)} camera motions for {T_B.shape[0]} lidar motions")
    sigma = np.radians(noise_deg)
    lidar, camera, weight = [], [], []
    for motion, T in zip(camera_motions, T_B, strict=True):
        b = Rotation.from_matrix(T[:3, :3]).as_rotvec()
        angle = float(np.linalg.norm(b))
        if angle > 5.0 * sigma:
            lidar.append(b / angle)
            camera.append(motion.rotvec_a_b / max(float(np.linalg.norm(motion.rotvec_a_b)), 1e-12))
            weight.append((angle / sigma) ** 2)
        travel = float(np.linalg.norm(T[:3, 3]))
        if motion.direction_a is not None and travel > 0:
            spread = np.radians(TRAVEL_NOISE_DEG) + angle * LEVER_M / travel
            if spread < np.radians(20.0):
                lidar.append(T[:3, 3] / travel)
                camera.append(np.asarray(motion.direction_a, dtype=np.float64))
                weight.append(spread**-2)
    if not lidar:
        return None
    b_all, a_all, w = np.asarray(lidar), np.asarray(camera), np.asarray(weight)
    R = kabsch(b_all, a_all, w)
    residual = np.linalg.norm(a_all - b_all @ R.T, axis=1)
    eigval, eigvec = np.linalg.eigh((b_all * w[:, None]).T @ b_all)
    perpendicular = float(eigval[0] + eigval[1])
    free_std = float(np.degrees(1.0 / np.sqrt(perpendicular))) if perpendicular > 0 else float("inf")
    return HandEyeRotation(R, len(b_all), float(np.degrees(np.sqrt(np.average(residual**2, weights=w)))),
                           free_std, eigvec[:, 2] if free_std > max_free_std_deg else None)
