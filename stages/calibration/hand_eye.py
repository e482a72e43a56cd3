"""Lidar-camera extrinsic from motion (hand-eye calibration, ``A X = X B``).

Over one time interval the camera moves by ``T_A = T_ca_cb`` (pose of the camera at time b in the
camera at time a) and the lidar by ``T_B = T_la_lb``. With the unknown ``T_X = T_camera_lidar``
(``p_camera = T_X @ p_lidar``), ``T_A = T_X T_B T_X^-1``, so

- rotation: ``R_A R_X = R_X R_B``, i.e. ``rotvec(R_A) = R_X @ rotvec(R_B)``;
- translation: ``R_A t_X + t_A = R_X t_B + t_X``, i.e. ``(R_A - I) t_X + s u = R_X t_B``, where the
  camera's translation ``t_A = s u`` is known from images only as a direction ``u`` (``s > 0``).

``camera_motion`` measures ``R_A`` and ``u`` from two images, ``hand_eye_rotation`` solves ``R_X``
from rotation pairs, ``hand_eye_translation`` solves ``t_X`` given ``R_X``. Rotations about an
axis shared by every interval (a ground vehicle that only yaws) leave ``R_X`` free about that
axis and ``t_X`` free along it; both results report what is free instead of inventing a value.
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
    """Rotation ``R_camera_lidar`` from paired interval rotations.

    Attributes:
        R_camera_lidar: (3, 3) rotation of ``T_camera_lidar``. When ``free_axis_lidar`` is set, the
            rotation about that axis is arbitrary (see ``rotations_about``).
        pairs_used: pairs whose lidar rotation was large enough to use.
        residual_deg: RMS over the used pairs of ``|rotvec_camera - R_camera_lidar @ rotvec_lidar|``,
            degrees (about the angle of the rotation left unexplained per interval).
        free_angle_std_deg: standard deviation of the rotation about the lidar rotations' dominant
            axis, degrees (noise over the excitation perpendicular to it); inf when nothing excites it.
        free_axis_lidar: (3,) unit axis in the lidar frame (sign arbitrary) about which the rotation is
            not determined (all lidar rotations nearly parallel to it); None when fully determined.
    """

    R_camera_lidar: FloatArray
    pairs_used: int
    residual_deg: float
    free_angle_std_deg: float
    free_axis_lidar: FloatArray | None


@dataclass(frozen=True)
class HandEyeTranslation:
    """Translation of ``T_camera_lidar`` from camera motion directions and lidar motions.

    Attributes:
        translation_m: (3,) translation of ``T_camera_lidar`` (lidar origin in the camera frame), metres;
            zero along each of ``free_directions_camera``.
        std_m: (3,) standard deviation per camera axis, metres, from the least-squares covariance
            scaled by the residual, with the free directions held fixed; inf on an unobservable axis.
        observable: (3,) per camera axis, False when the axis lies within 60 deg of a free direction.
        free_directions_camera: (k, 3) unit directions in the camera frame along which the motion
            gives no information (k = 0 for motion that rotates about several axes).
        scales_m: (pairs_used,) camera travel per used pair, metres.
        pairs_used: pairs in the solution (a pair with a non-positive travel is dropped).
    """

    translation_m: FloatArray
    std_m: FloatArray
    observable: NDArray[np.bool_]
    free_directions_camera: FloatArray
    scales_m: FloatArray
    pairs_used: int


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


def _check_pairs(camera_rotvecs: NDArray[np.floating], lidar_rotvecs: NDArray[np.floating],
                 weights: NDArray[np.floating] | None) -> tuple[FloatArray, FloatArray, FloatArray]:
    a = np.asarray(camera_rotvecs, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(lidar_rotvecs, dtype=np.float64).reshape(-1, 3)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, dtype=np.float64).ravel()
    if a.shape != b.shape or w.shape != (len(a),):
        raise InputError(f"hand-eye pairs need (N, 3) rotations and (N,) weights, got {a.shape}, {b.shape}, "
                         f"{w.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(np.isfinite(w)) and np.all(w >= 0)):
        raise InputError("hand-eye rotations must be finite and weights finite and non-negative")
    return a, b, w


def hand_eye_rotation(camera_rotvecs: NDArray[np.floating], lidar_rotvecs: NDArray[np.floating],
                      weights: NDArray[np.floating] | None = None, noise_deg: float = 0.1,
                      max_free_std_deg: float = 1.0) -> HandEyeRotation | None:
    """``R_camera_lidar`` from interval rotations, ``rotvec_camera = R_camera_lidar @ rotvec_lidar``.

    Weighted Kabsch on the rotation vectors (radians): a pair counts in proportion to its angle, since
    a rotation vector's noise does not grow with it. Pairs whose lidar angle is below ``5 noise_deg``
    are left out: their axis is uncertain by more than about 11 deg.

    The rotation about the dominant axis of the lidar rotations (top eigenvector of the weighted
    scatter ``S = sum w b b^T``) is constrained only by the rotation perpendicular to it, so its
    standard deviation is ``sigma / sqrt(l2 + l3)`` (eigenvalues of S, rad^2; sigma the per-axis
    noise: ``noise_deg`` or the residuals' spread, whichever is larger). That is the second and third
    singular values relative to the noise rather than to the first: how parallel the axes must be to
    leave the angle free depends on how precise the rotations are. Above ``max_free_std_deg`` (1 deg,
    about the width of the score's basin for a search over the angle) the axis is reported free.
    Lidar rotations are taken as exact.

    Args:
        camera_rotvecs: (N, 3) rotation vectors of the camera's ``R_a_b`` per interval, radians.
        lidar_rotvecs: (N, 3) rotation vectors of the lidar's ``R_a_b`` over the same intervals, radians.
        weights: (N,) relative confidence of each pair (rescaled to mean 1 over the used pairs).
        noise_deg: per-axis noise of a unit-weight pair's rotation vectors, degrees.
        max_free_std_deg: standard deviation about the dominant axis above which it is free, degrees.

    Returns:
        The rotation, or None when no pair rotated enough. One pair determines two of three angles.
    """
    a, b, w = _check_pairs(camera_rotvecs, lidar_rotvecs, weights)
    sigma = np.deg2rad(noise_deg)
    use = (np.linalg.norm(b, axis=1) > 5.0 * sigma) & (w > 0)
    if not np.any(use):
        return None
    a, b, w = a[use], b[use], w[use] / np.mean(w[use])
    R = kabsch(b, a, w)
    residual = np.linalg.norm(a - b @ R.T, axis=1)
    if len(a) > 1:
        sigma = max(sigma, float(np.sqrt(np.sum(w * residual**2) / (3.0 * len(a) - 3.0))))
    eigval, eigvec = np.linalg.eigh((b * w[:, None]).T @ b)
    perpendicular = float(eigval[0] + eigval[1])
    free_std = np.rad2deg(sigma / np.sqrt(perpendicular)) if perpendicular > 0 else np.inf
    free_axis = eigvec[:, 2] if free_std > max_free_std_deg else None
    return HandEyeRotation(R, len(a), float(np.rad2deg(np.sqrt(np.mean(residual**2)))),
                           float(free_std), free_axis)


def rotations_about(R_camera_lidar: FloatArray, free_axis_lidar: FloatArray, n: int) -> FloatArray:
    """(n, 3, 3) rotations ``R_camera_lidar @ Rot(free_axis_lidar, theta)``, theta = 360 deg k / n.

    Every member satisfies the same hand-eye rotation equations when the lidar rotations are about
    ``free_axis_lidar``: the one-dimensional family that a search over the free angle scores.
    """
    axis = np.asarray(free_axis_lidar, dtype=np.float64)
    theta = 2.0 * np.pi * np.arange(n) / n
    spins = Rotation.from_rotvec(theta[:, None] * (axis / np.linalg.norm(axis))[None, :]).as_matrix()
    return np.asarray(np.einsum("ij,njk->nik", R_camera_lidar, spins))


@dataclass(frozen=True)
class _TranslationPairs:
    """Stacked pairs: ``D = R_A - I`` (N, 3, 3), camera directions ``u`` (N, 3), ``c = R_X t_B`` (N, 3)."""

    D: FloatArray
    u: FloatArray
    c: FloatArray

    def subset(self, keep: NDArray[np.bool_]) -> _TranslationPairs:
        return _TranslationPairs(self.D[keep], self.u[keep], self.c[keep])


def _translation_pairs(R_camera_lidar: FloatArray, camera_motions: list[CameraMotion],
                       lidar_T_a_b: NDArray[np.floating]) -> _TranslationPairs:
    T = np.asarray(lidar_T_a_b, dtype=np.float64)
    if np.shape(R_camera_lidar) != (3, 3):
        raise InputError(f"hand_eye_translation needs a (3, 3) rotation, got {np.shape(R_camera_lidar)}")
    if T.shape != (len(camera_motions), 4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"hand_eye_translation needs ({len(camera_motions)}, 4, 4) finite lidar motions, "
                         f"got {T.shape}")
    keep = [i for i, m in enumerate(camera_motions) if m.direction_a is not None]
    D = np.array([camera_motions[i].R_a_b - np.eye(3) for i in keep]).reshape(-1, 3, 3)
    u = np.array([camera_motions[i].direction_a for i in keep], dtype=np.float64).reshape(-1, 3)
    return _TranslationPairs(D, u, T[keep, :3, 3] @ np.asarray(R_camera_lidar).T)


def _solve_translation(pairs: _TranslationPairs, min_singular_ratio: float) -> tuple[
        FloatArray, FloatArray, FloatArray, FloatArray]:
    """(t, scales, std per camera axis, free directions (k, 3)) of the least squares in (t, s) with
    the scales eliminated: ``M t = g``, ``M = sum D^T P D``, ``g = sum D^T P c``, ``P = I - u u^T``."""
    P = np.eye(3)[None] - pairs.u[:, :, None] * pairs.u[:, None, :]
    M = np.einsum("nji,njk,nkl->il", pairs.D, P, pairs.D)
    g = np.einsum("nji,njk,nk->i", pairs.D, P, pairs.c)
    eigval, eigvec = np.linalg.eigh(M)
    kept = (eigval > 0) & (np.sqrt(np.clip(eigval, 0.0, None)) >= min_singular_ratio * np.sqrt(eigval[-1]))
    V, lam = eigvec[:, kept], eigval[kept]
    t = V @ ((V.T @ g) / lam)
    left = pairs.c - pairs.D @ t
    scales = np.einsum("ni,ni->n", pairs.u, left)
    residual = float(np.sum((left - scales[:, None] * pairs.u) ** 2))
    dof = max(2 * len(scales) - len(lam), 1)
    std = np.sqrt(residual / dof * np.sum(V**2 / lam[None, :], axis=1))
    return t, scales, std, np.asarray(eigvec[:, ~kept].T)


def hand_eye_translation(R_camera_lidar: FloatArray, camera_motions: list[CameraMotion],
                         lidar_T_a_b: NDArray[np.floating],
                         min_singular_ratio: float = 0.1) -> HandEyeTranslation | None:
    """Translation ``t`` of ``T_camera_lidar`` from ``(R_A - I) t + s_i u_i = R_camera_lidar t_B``.

    Per pair, ``R_A`` and ``u_i`` are the camera's ``R_a_b`` and ``direction_a``, ``t_B`` the lidar's
    translation over the same interval and ``s_i > 0`` the camera's unknown travel. The stacked least
    squares in (t, s) is solved with the scales eliminated: ``M t = g``, ``M = sum (R_A - I)^T P_i
    (R_A - I)``, ``P_i = I - u_i u_i^T``. A rotation about an axis tells nothing about ``t`` along
    that axis, so the eigen-directions of M whose singular value (square root of the eigenvalue) is
    below ``min_singular_ratio`` (0.1) of the largest are free: planar motion excites the direction
    along the yaw axis with pitch and roll alone, typically well under a tenth of the yaw. A vehicle
    that only drives forward also leaves the camera's lateral offset weak: that offset changes the
    camera's travel mostly in length (the unknown ``s_i``), hardly in direction. The solution is zero
    along free directions (their signs are arbitrary). Pairs that come out with ``s_i <= 0`` (travel opposite to
    the measured direction) are dropped and the rest solved again. Pairs without a direction are skipped.

    Args:
        R_camera_lidar: (3, 3) rotation of ``T_camera_lidar``.
        camera_motions: per interval, the camera's motion.
        lidar_T_a_b: (N, 4, 4) per interval, the lidar's pose at b in the lidar frame at a, metres.
        min_singular_ratio: relative singular value below which a direction of t is free.

    Returns:
        The translation, or None with fewer than 2 usable pairs.
    """
    pairs = _translation_pairs(R_camera_lidar, camera_motions, lidar_T_a_b)
    if len(pairs.u) < 2:
        return None
    t, scales, std, free = _solve_translation(pairs, min_singular_ratio)
    if np.any(scales <= 0):
        pairs = pairs.subset(scales > 0)
        if len(pairs.u) < 2:
            return None
        t, scales, std, free = _solve_translation(pairs, min_singular_ratio)
    observable = np.sum(free**2, axis=0) < 0.25
    return HandEyeTranslation(t, np.where(observable, std, np.inf), observable, free, scales, len(scales))


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
