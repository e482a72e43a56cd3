"""``sensor_msgs/CameraInfo`` (ROS 1 ``D, K, R, P`` or ROS 2 ``d, k, r, p`` spelling) -> ``CameraModel``."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import DecodeError


def _array(msg: Any, name: str) -> NDArray[np.float64]:
    value = getattr(msg, name, None)
    if value is None:
        value = getattr(msg, name.upper(), None)
    if value is None:
        raise DecodeError(f"CameraInfo has no {name}/{name.upper()} field")
    return np.asarray(value, dtype=np.float64).reshape(-1)


def decode_camera_info(msg: Any, rectified: bool = False) -> CameraModel:
    """Camera model of a CameraInfo message object: size, K (3x3), D and the distortion model.

    ``plumb_bob``, ``rational_polynomial`` and ``equidistant`` (also ``fisheye``, ``radtan``,
    ``cylindrical``, and an empty string for no distortion) are understood. Binning and ROI are
    not applied: the model describes the full-resolution image of ``width`` x ``height``.

    ``rectified``: the model of the image_proc-rectified image (``image_rect``) instead of the raw one,
    as ROS defines it: the distortion is already removed, the intrinsics are the left 3x3 of P (K where
    P is all zero), with no distortion model, and a stereo camera's rectification rotation R (not the
    identity) becomes ``R_rect``, so points in the camera's tf frame project where the rectified image
    shows them. P's baseline column (Tx = -fx B of a right camera) is not applied: the image's tf
    frame is taken to be that camera's own.

    Raises:
        DecodeError: K all zero (uncalibrated camera), not finite, or not 9 values; an unknown
            distortion model; a non-positive image size; a rectified camera's R set but not a rotation.
    """
    K = _array(msg, "k")
    if K.size != 9:
        raise DecodeError(f"CameraInfo K has {K.size} values, expected 9")
    if not np.all(np.isfinite(K)):
        raise DecodeError("CameraInfo K is not finite")
    if not np.any(K):
        raise DecodeError("CameraInfo K is all zero (camera not calibrated)")
    if rectified:
        P = _array(msg, "p")
        if P.size == 12 and np.all(np.isfinite(P)) and np.any(P):
            K = P.reshape(3, 4)[:, :3].reshape(-1)
        R = _array(msg, "r")
        is_set = R.size == 9 and bool(np.any(R)) and not np.array_equal(R, np.eye(3).reshape(-1))
        R_rect = R.reshape(3, 3) if is_set else None  # validated by CameraModel
        return CameraModel(int(msg.width), int(msg.height), K.reshape(3, 3), np.zeros(0), "none", R_rect)
    D = _array(msg, "d")
    model = str(msg.distortion_model).strip().lower()
    return CameraModel(int(msg.width), int(msg.height), K.reshape(3, 3), D, model)


def rectification_rotation(msg: Any) -> float:
    """Angle (degrees) of the CameraInfo's rectification rotation R; 0 for a monocular camera (R = I or
    unset)."""
    R = _array(msg, "r")
    if R.size != 9 or not np.all(np.isfinite(R)) or not np.any(R):
        return 0.0
    cos_angle = np.clip((np.trace(R.reshape(3, 3)) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos_angle)))


def stereo_baseline_m(msg: Any) -> float:
    """Baseline B (metres) of a stereo right camera from its CameraInfo's P (``Tx = -fx' B``); 0 for a
    left or monocular camera (or P unset)."""
    P = _array(msg, "p")
    if P.size != 12 or not np.all(np.isfinite(P)) or P[0] <= 0:
        return 0.0
    return float(-P[3] / P[0])
