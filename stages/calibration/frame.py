"""Calibration frames: one paired lidar scan and camera image, ready for the objective (lidar feature,
image gradients, ego-motion), and the per-frame work that builds them from decoded frames."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.config import feature_names
from fleetcal.pipeline.errors import ProcessingError
from fleetcal.pipeline.frames import CameraFrame, LidarFrame
from fleetcal.pipeline.transforms import Mat4, apply, screw_apply


class GradientImage(Protocol):
    """Anything with image gradients, e.g. ``stages.image_gradients.ImageGradients``: ``gxy`` (H, W, 2)
    along columns and rows (float32, or int16 in some fixed unit), and (H, W) float32 views or derivations of
    it in grey levels, at every ``stride``-th pixel of the image (``gxy[i, j]`` at pixel (u, v) =
    (j * stride, i * stride))."""

    @property
    def gxy(self) -> NDArray[np.float32] | NDArray[np.int16]: ...

    @property
    def gx(self) -> NDArray[np.float32]: ...

    @property
    def gy(self) -> NDArray[np.float32]: ...

    @property
    def magnitude(self) -> NDArray[np.float32]: ...

    @property
    def stride(self) -> int: ...


@dataclass
class CalibrationFrame:
    """One paired lidar scan and camera image.

    Attributes:
        points_xyz: (N, 3) lidar points in the lidar frame at the scan stamp, metres.
        feature: (N,) lidar feature in [0, 1] (``stages.lidar_features``), or (N, C) for C features
            (e.g. range and normals): each gets its own lidar gradients and the frame's score is the
            mean of the C scores. Points with a NaN in any column are dropped.
        camera: intrinsics of the image.
        gradients: image gradients after blur (``compute_image_gradients``): ``gxy`` (H', W', 2) at every
            ``stride``-th pixel, which the objective reads in place, and its ``gx``, ``gy``, ``magnitude``.
        intensity: (H, W) equalised grey, uint8 0-255 (or float in [0, 1]); needed by the NMI metric only.
        mask: (H, W) bool, True where the image is valid; None: all valid.
        T_camera_camera0: 4x4 pose of the reference camera in this camera (identity for one camera).
        T_lidar_motion: 4x4 ``T_lidar(camera stamp)_lidar(scan stamp)``: ego-motion from the scan
            stamp to the camera stamp, applied to the points once (None: no motion).
        point_time_offsets_s: (N,) optional per-point capture time minus the camera stamp, seconds,
            used with ``twist_lidar`` for motion during the sweep (each point then moves by its own
            offset; ``T_lidar_motion`` is then normally None).
        twist_lidar: (6,) optional lidar velocity (vx, vy, vz m/s, wx, wy, wz rad/s) in the lidar frame.
        camera_twist_lidar: (6,) optional lidar twist (as ``twist_lidar``) about the camera stamp: moves the
            points on by a clock offset or a rolling shutter's row time (``stages.calibration.timing``); None:
            ``twist_lidar``'s, if any.
        readout_s: the camera's rolling-shutter readout, first to last row, seconds (0: global shutter).
        stamp_ns: camera stamp (for reports).
        label: free text (e.g. the camera topic).
    """

    points_xyz: NDArray[np.floating]
    feature: NDArray[np.floating]
    camera: CameraModel
    gradients: GradientImage
    intensity: NDArray[np.floating] | NDArray[np.uint8] | None = None
    mask: NDArray[np.bool_] | None = None
    T_camera_camera0: Mat4 = field(default_factory=lambda: np.eye(4))
    T_lidar_motion: Mat4 | None = None
    point_time_offsets_s: NDArray[np.floating] | None = None
    twist_lidar: NDArray[np.floating] | None = None
    camera_twist_lidar: NDArray[np.floating] | None = None
    readout_s: float = 0.0
    stamp_ns: int = 0
    label: str = ""

    def points_at_camera_stamp(self) -> NDArray[np.float64]:
        """(N, 3) points moved to the camera stamp (``compensate_ego_motion``), lidar frame, metres."""
        return compensate_ego_motion(self.points_xyz, self.T_lidar_motion, self.point_time_offsets_s,
                                     self.twist_lidar)

    def twist_at_camera(self) -> NDArray[np.float64] | None:
        """(6,) lidar twist about the camera stamp (``camera_twist_lidar``, else ``twist_lidar``); None: unknown."""
        twist = self.camera_twist_lidar if self.camera_twist_lidar is not None else self.twist_lidar
        return None if twist is None else np.asarray(twist, dtype=np.float64).reshape(6)

    def motion_rotation(self) -> NDArray[np.float64] | None:
        """3x3 rotation of the lidar frame from capture to the camera stamp (a sweep's at its median point
        time: ``exp(w dt)``, as ``compensate_ego_motion`` turns points), None without motion."""
        R: NDArray[np.float64] | None = None
        if self.point_time_offsets_s is not None and self.twist_lidar is not None:
            dt = float(np.median(np.asarray(self.point_time_offsets_s, dtype=np.float64)))
            R = Rotation.from_rotvec(np.asarray(self.twist_lidar, dtype=np.float64)[3:] * dt).as_matrix()
        if self.T_lidar_motion is not None:
            R_scan = np.asarray(self.T_lidar_motion, dtype=np.float64)[:3, :3]
            R = R_scan if R is None else R_scan @ R
        return R


def fold_rectification(frame: CalibrationFrame) -> CalibrationFrame:
    """The frame with its camera's rectification rotation (``CameraModel.R_rect``, a rectified stereo
    image) moved into ``T_camera_camera0``, for the objective's kernels, which take intrinsics only; the
    frame itself when the camera has none. The extrinsic estimated stays that of the camera's tf frame."""
    R = frame.camera.R_rect
    if R is None:
        return frame
    T_rect_camera = np.eye(4)
    T_rect_camera[:3, :3] = R
    return replace(frame, camera=frame.camera.without_rectification(),
                   T_camera_camera0=T_rect_camera @ np.asarray(frame.T_camera_camera0, dtype=np.float64))


def compensate_ego_motion(points_xyz: NDArray[np.floating], T_lidar_motion: Mat4 | None = None,
                          point_time_offsets_s: NDArray[np.floating] | None = None,
                          twist_lidar: NDArray[np.floating] | None = None) -> NDArray[np.float64]:
    """Move scan points to the camera stamp: first each point by the constant lidar twist over its time
    offset ``dt = t_point - t_camera`` (the screw motion ``exp(twist dt)``, which expresses a point in the
    lidar frame at the camera stamp; first order ``p + (v + w x p) dt``), then by ``T_lidar_motion``."""
    pts = np.asarray(points_xyz, dtype=np.float64)
    if point_time_offsets_s is not None and twist_lidar is not None:
        tw = np.asarray(twist_lidar, dtype=np.float64).ravel()
        dt = np.asarray(point_time_offsets_s, dtype=np.float64).ravel()
        if tw.shape != (6,) or dt.shape[0] != pts.shape[0]:
            raise ProcessingError("twist_lidar must be (6,) and point time offsets one per point")
        pts = screw_apply(tw, dt, pts)
    if T_lidar_motion is not None:
        pts = apply(np.asarray(T_lidar_motion, dtype=np.float64), pts)
    return pts


def default_blur_sigma_px(width_px: int) -> float:
    """Gaussian blur (pixels) of the image before Sobel: 2 px up to 1240 px wide, then width / 620
    (3.1 px at 1920). On KITTI (1242 px) 1.5-2 px gave 0.09-0.14 deg / 6-8 cm and 2.6 px 0.23 deg /
    10 cm; on the synthetic 640 px scene 2 px beat 1 px (0.13 vs 0.36 deg)."""
    return max(2.0, float(width_px) / 620.0)


def log_range_feature(points_xyz: NDArray[np.floating]) -> NDArray[np.float64]:
    """log(range) scaled to [0, 1] (range in metres from the lidar origin, floored at 0.1 m).

    Unlike the histogram-equalised range, smooth ramps (the ground) get small gradients relative to
    depth discontinuities. Evidence is mixed, so it is an option, not the default: KITTI 0.24 deg /
    6.6 cm (range: 0.14 deg / 8 cm); nuScenes joint 3.1 deg with ego-motion, 0.60 deg without
    (range: 0.37 / 1.23 deg), see benchmarks/bench_gom.py.
    """
    r = np.linalg.norm(np.asarray(points_xyz, dtype=np.float64), axis=1)
    lr = np.log(np.maximum(r, 0.1))
    finite = np.isfinite(lr)
    if not np.any(finite):
        return np.full(r.shape, np.nan)
    lo, hi = float(lr[finite].min()), float(lr[finite].max())
    return np.asarray((lr - lo) / (hi - lo) if hi > lo else np.full(r.shape, 0.5))


@dataclass
class LidarFeatures:
    """Per-frame result of ``lidar_feature_stage``: the decoded scan (points in its lidar frame, metres, and
    its channels, e.g. per-point ``time``) and its lidar feature, (N,) or (N, C)."""

    lidar: LidarFrame
    feature: NDArray[np.floating]


@dataclass
class CameraFeatures:
    """Per-frame result of ``camera_feature_stage``.

    Attributes:
        stamp_ns, topic, frame_id: of the image.
        camera: its intrinsics.
        gradients: image gradients after the blur (``stages.image_gradients.compute_image_gradients``), kept
            at the widest stride the blur allows (``stages.image_gradients.sampling_stride``).
        intensity: (H, W) histogram-equalised grey, uint8 (for NMI), or None when the stage was not asked for it.
        image: the decoded image when the stage was asked to keep it (for overlays), else None.
    """

    stamp_ns: int
    topic: str
    frame_id: str
    camera: CameraModel
    gradients: GradientImage
    intensity: NDArray[np.uint8] | None
    image: NDArray[np.generic] | None = None


AUTO_FEATURES = ("range", "normals", "intensity")
"""The columns of the ``auto`` lidar feature, in order; ``intensity`` only where the scan's intensity channel
takes more than one value."""

AUTO_FEATURE_GROUPS = ((0, 1), (2,))
"""The alternatives among the ``auto`` columns (``SolverConfig.feature_groups``): the geometry the lidar sees
(range and normals) and what it reads of the surfaces (intensity)."""


def auto_feature_names(lidar: LidarFrame) -> list[str]:
    """The ``auto`` feature's columns for this scan (``AUTO_FEATURES``)."""
    intensity = lidar.channel("intensity")
    varied = intensity is not None and np.unique(np.asarray(intensity)[: 100_000]).size > 1
    return list(AUTO_FEATURES if varied else AUTO_FEATURES[:2])


def lidar_feature_stage(lidar: LidarFrame, feature: str = "range") -> LidarFeatures:
    """Per-frame stage: the lidar feature(s) of one scan (``stages.lidar_features``: ``range``,
    ``intensity``, ``normals``; or ``log_range``, see ``log_range_feature``; several joined by ``+`` give
    an (N, C) feature; ``auto``: the columns of ``auto_feature_names``)."""
    from fleetcal.stages.lidar_features import compute_lidar_feature

    columns: list[NDArray[np.floating]] = []
    for name in auto_feature_names(lidar) if feature == "auto" else feature_names(feature):
        if name == "log_range":
            columns.append(log_range_feature(lidar.points_xyz))
        else:
            columns.append(compute_lidar_feature(lidar.points_xyz, name,  # type: ignore[arg-type]
                                                 intensity=lidar.channel("intensity")))
    values = columns[0] if len(columns) == 1 else np.stack(columns, axis=1)
    return LidarFeatures(lidar, values)


def usable_groups(frames: list[CalibrationFrame], groups: tuple[tuple[int, ...], ...]) -> list[tuple[int, ...]]:
    """The column groups of ``groups`` that every frame's (N, C) feature holds."""
    columns = min((np.shape(f.feature)[1] if np.ndim(f.feature) == 2 else 1 for f in frames), default=0)
    return [g for g in groups if max(g) < columns]


def with_columns(frames: list[CalibrationFrame], columns: tuple[int, ...]) -> list[CalibrationFrame]:
    """The frames with only the feature ``columns`` of their (N, C) feature ((N,) for one column)."""
    pick: int | list[int] = columns[0] if len(columns) == 1 else list(columns)
    return [replace(f, feature=np.asarray(f.feature)[:, pick]) for f in frames]


def camera_feature_stage(camera: CameraFrame, blur_sigma_px: float | None = None,
                         keep_image: bool = False, keep_grey: bool = True) -> CameraFeatures:
    """Per-frame stage: image gradients of one image after a Gaussian blur (None: ``default_blur_sigma_px``
    of its width), kept at every ``sampling_stride(blur)``-th pixel (what the blur leaves of the image needs no
    more: a 1920 px image's gradients take a quarter of the memory) as int16 (``quantised``: half again), and
    its equalised grey with ``keep_grey``
    (the NMI metric's image term); the image itself only with ``keep_image``.

    Raises:
        ProcessingError: the camera frame has no CameraModel (no CameraInfo in the log).
    """
    from fleetcal.stages.image_gradients import compute_image_gradients, quantised, sampling_stride, subsampled

    if camera.camera is None:
        raise ProcessingError(f"camera {camera.topic} has no CameraInfo: intrinsics are unknown")
    sigma = default_blur_sigma_px(camera.width) if blur_sigma_px is None else blur_sigma_px
    grads = quantised(subsampled(compute_image_gradients(camera.image, blur_sigma_px=sigma), sampling_stride(sigma)))
    return CameraFeatures(camera.stamp_ns, camera.topic, camera.frame_id, camera.camera, grads,
                          equalised_grey(camera.image) if keep_grey else None, camera.image if keep_image else None)


def equalised_grey(image: NDArray[Any]) -> NDArray[np.uint8]:
    """(H, W) histogram-equalised grey, uint8, of a decoded image (grey or colour)."""
    import cv2

    from fleetcal.stages.image_gradients import to_grey_u8

    return np.asarray(cv2.equalizeHist(to_grey_u8(image)), dtype=np.uint8)


def join_frame(lidar: LidarFeatures, camera: CameraFeatures, T_camera_camera0: Mat4 | None = None,
               T_lidar_motion: Mat4 | None = None, points_xyz: NDArray[np.float64] | None = None) -> CalibrationFrame:
    """The CalibrationFrame of one lidar scan's and one image's per-frame results; ``points_xyz``: the scan's
    points as float64 where the caller holds them already (one array for every camera of the scan)."""
    return CalibrationFrame(
        points_xyz=np.asarray(lidar.lidar.points_xyz if points_xyz is None else points_xyz, dtype=np.float64),
        feature=lidar.feature,
        camera=camera.camera, gradients=camera.gradients, intensity=camera.intensity,
        T_camera_camera0=np.eye(4) if T_camera_camera0 is None else np.asarray(T_camera_camera0),
        T_lidar_motion=T_lidar_motion, stamp_ns=camera.stamp_ns, label=camera.topic)


def build_frame(lidar: LidarFrame, camera: CameraFrame, feature: str = "range",
                blur_sigma_px: float | None = None, T_camera_camera0: Mat4 | None = None,
                T_lidar_motion: Mat4 | None = None) -> CalibrationFrame:
    """A CalibrationFrame from decoded frames: ``lidar_feature_stage`` and ``camera_feature_stage`` in
    process, joined.

    Raises:
        ProcessingError: the camera frame has no CameraModel (no CameraInfo in the log).
    """
    return join_frame(lidar_feature_stage(lidar, feature), camera_feature_stage(camera, blur_sigma_px),
                      T_camera_camera0, T_lidar_motion)
