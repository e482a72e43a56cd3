"""Alignment metrics between a lidar scan and a camera image, evaluated for a batch of poses.

All metrics share one interface: a ``*Scorer`` is built once per lidar/camera frame (inputs validated
and packed), then ``scorer.score(T_camera_lidar_batch)`` returns a ``MetricBatch`` for (P, 4, 4)
candidate extrinsics in one numba call (parallel over poses). Higher is better for every metric.

- GOM (paper eq. 9-11): gradient orientation alignment weighted by both gradient magnitudes, in [0, 1].
- NMI (paper eq. 3): normalised mutual information of lidar feature vs image intensity, in [1, 2].
- Levinson & Thrun: sum of lidar depth discontinuity x blurred mean-subtracted image edge value.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import ProcessingError
from fleetcal.stages.calibration import metric_kernels as mk

MetricName = Literal["gom", "nmi", "levinson"]
METRICS: tuple[str, ...] = ("gom", "nmi", "levinson")


@dataclass
class MetricBatch:
    """Scores of a batch of poses for one frame.

    Attributes:
        scores: (P,) metric value per pose (0 where no point projects).
        counts: (P,) lidar points that project inside the image and its valid mask.
        sums: GOM only: (P, 2) its numerator and weight sums (score = numerator / (2 weight)), from which
            the scores of two disjoint point sets combine (``plus``); None for other metrics.
    """

    scores: NDArray[np.float64]
    counts: NDArray[np.int64]
    sums: NDArray[np.float64] | None = None

    @classmethod
    def of_gom(cls, num: NDArray[np.float64], den: NDArray[np.float64], counts: NDArray[np.int64]) -> MetricBatch:
        """GOM's batch from its per-pose numerator, weight and projected-point count."""
        with np.errstate(divide="ignore", invalid="ignore"):
            gom = np.where(den > 0, num / (2.0 * den), 0.0)
        return cls(np.asarray(gom), np.asarray(counts), np.stack([num, den], axis=1))

    def rows(self, chosen: NDArray[np.bool_]) -> MetricBatch:
        """This batch's poses where ``chosen`` (P,) holds."""
        return MetricBatch(self.scores[chosen], self.counts[chosen], None if self.sums is None else self.sums[chosen])

    def plus(self, other: MetricBatch) -> MetricBatch:
        """The GOM batch of the same poses over this batch's points and ``other``'s (disjoint sets).

        Raises:
            ProcessingError: either batch carries no sums (not GOM).
        """
        if self.sums is None or other.sums is None:
            raise ProcessingError("only GOM batches combine over point sets")
        sums = self.sums + other.sums
        return MetricBatch.of_gom(sums[:, 0], sums[:, 1], self.counts + other.counts)


def camera_params(camera: CameraModel, stride: int = 1, row_stride: int | None = None) -> NDArray[np.float64]:
    """Pack a CameraModel into the (16,) float64 layout the kernels read (see ``metric_kernels``), in pixels of
    an image kept at every ``stride``-th column and ``row_stride``-th row (None: ``stride``; its pixel (j, i) is
    the image's (j * stride, i * row_stride)).

    Raises:
        ProcessingError: the camera has a rectification rotation, which the kernels do not apply (fold
            it into the pose first: ``stages.calibration.frame.fold_rectification``).
    """
    if camera.R_rect is not None:
        raise ProcessingError("camera has a rectification rotation R: fold it into the pose before scoring")
    cam = np.zeros(mk.CAM_PARAMS)
    cam[0] = mk.MODEL_CODES[camera.distortion_model]
    if camera.distortion_model in ("plumb_bob", "rational_polynomial") and not np.any(camera.D):
        # all coefficients zero (a rectified image: KITTI, nuScenes): the pinhole projection, exactly, without
        # the distortion polynomial per point (a third of a GOM evaluation on KITTI)
        cam[0] = mk.MODEL_NONE
    row_stride = stride if row_stride is None else row_stride
    cam[1:6] = np.array([camera.fx / stride, camera.fy / row_stride, camera.cx / stride, camera.cy / row_stride,
                         camera.K[0, 1] / stride])
    cam[6:14] = camera.coefficients(8)
    cam[14] = np.inf
    if camera.distortion_model in ("plumb_bob", "rational_polynomial") and np.any(camera.D):
        cam[14] = camera._max_undistorted_radius()
    return cam


def project_points(points_cam: NDArray[np.floating], camera: CameraModel) -> tuple[
        NDArray[np.float64], NDArray[np.bool_]]:
    """numba projection of (N, 3) optical-frame points; same contract as ``CameraModel.project``."""
    pts = _points(points_cam)
    uv, valid = mk.project_points_kernel(pts, camera_params(camera), camera.width, camera.height)
    return np.asarray(uv), np.asarray(valid)


def sample_bicubic(planes: NDArray[np.floating], uv: NDArray[np.floating]) -> NDArray[np.float64]:
    """Keys bicubic (a = -0.5) samples (N, C) of an (H, W) or (H, W, C) image at pixels (N, 2)
    (pixel centres at integer coordinates, edges clamped)."""
    return np.asarray(mk.sample_bicubic_kernel(_planes(planes, np.float64),
                                               np.ascontiguousarray(uv, dtype=np.float64)))


def _points(points: NDArray[np.floating]) -> NDArray[np.float64]:
    pts = np.ascontiguousarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ProcessingError(f"points must be (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ProcessingError("lidar points contain NaN or infinity")
    return pts


def _planes(image: NDArray[np.floating], dtype: type[np.floating] = np.float32) -> NDArray[np.floating]:
    """(H, W, C) C-contiguous copy of an image in ``dtype`` (none when it already is): float32 for the
    objective's images, whose values come from 8-bit grey levels (half the memory of float64, and the
    kernels sum in float64)."""
    arr = np.asarray(image, dtype=dtype)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ProcessingError(f"image must be (H, W) or (H, W, C), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ProcessingError("image contains NaN or infinity")
    return np.ascontiguousarray(arr)


ALL_VALID = np.ones((1, 1), dtype=np.uint8)
"""The valid mask of every image without a mask of its own, whatever its size: the kernels read a (1, 1) mask as
all valid (``metric_kernels._in_view``) and skip the lookup per point and pose. Shared: never written (left
writeable because numba compiles its kernels again for read-only arrays)."""


def _mask(mask: NDArray[np.generic] | None, shape: tuple[int, int]) -> NDArray[np.uint8]:
    if mask is None:
        return ALL_VALID
    m = np.ascontiguousarray(np.asarray(mask) != 0, dtype=np.uint8)
    if m.shape != shape:
        raise ProcessingError(f"valid mask {m.shape} does not match image {shape}")
    return m


def _size_message(shape: tuple[int, ...], camera: CameraModel, stride: int = 1, row_stride: int | None = None) -> str:
    strides = f"{stride}" if row_stride in (None, stride) else f"{stride} x {row_stride}"
    kept = f" kept at a stride of {strides} pixels" if max(stride, row_stride or stride) > 1 else ""
    return f"image {shape[1]}x{shape[0]} does not match camera {camera.width}x{camera.height}{kept}"


def kept_shape(camera: CameraModel, stride: int, row_stride: int | None = None) -> tuple[int, int]:
    """(rows, columns) of an image of ``camera`` kept at every ``stride``-th column and ``row_stride``-th row
    (None: ``stride``; ``image[::row_stride, ::stride]``)."""
    row_stride = stride if row_stride is None else row_stride
    return (-(-camera.height // row_stride), -(-camera.width // stride))


def _check_kept(shape: tuple[int, ...], camera: CameraModel, stride: int = 1, row_stride: int | None = None) -> None:
    """Raise ProcessingError unless an image plane of ``shape`` (H', W'[, C]) is ``camera``'s image kept at
    every ``stride``-th column and ``row_stride``-th row (None: ``stride``)."""
    if min(stride, row_stride or stride) < 1 or tuple(shape[:2]) != kept_shape(camera, stride, row_stride):
        raise ProcessingError(_size_message(shape, camera, stride, row_stride))


def _kept_mask(mask: NDArray[np.generic] | None, camera: CameraModel, stride: int) -> NDArray[np.uint8]:
    """(H', W') uint8 valid mask at the pixels kept at ``stride`` of ``camera``'s whole-image (H, W) ``mask``
    (None: all valid)."""
    if mask is None:
        return ALL_VALID
    return np.ascontiguousarray(_mask(mask, (camera.height, camera.width))[::stride, ::stride])


def _per_point(values: NDArray[np.floating], n: int, name: str) -> NDArray[np.float64]:
    arr = np.ascontiguousarray(values, dtype=np.float64).ravel()
    if arr.shape[0] != n:
        raise ProcessingError(f"{name} has {arr.shape[0]} values for {n} points")
    if not np.all(np.isfinite(arr)):
        raise ProcessingError(f"{name} contains NaN or infinity")
    return arr


def pose_batch(T_camera_lidar_batch: NDArray[np.floating]) -> NDArray[np.float64]:
    """(P, 3, 4) contiguous ``[R | t]`` rows from (P, 4, 4) or (4, 4) transforms."""
    T = np.asarray(T_camera_lidar_batch, dtype=np.float64)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ProcessingError(f"poses must be (P, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ProcessingError("poses contain NaN or infinity")
    return np.ascontiguousarray(T[:, :3, :])


def focal_batch(focal_scale: NDArray[np.floating] | None, n_pose: int) -> NDArray[np.float64]:
    """(P,) focal scales of a pose batch (None: 1 for every pose)."""
    if focal_scale is None:
        return np.ones(n_pose)
    fs = np.ascontiguousarray(focal_scale, dtype=np.float64).ravel()
    if fs.shape[0] != n_pose or not np.all(fs > 0):
        raise ProcessingError(f"focal_scale must be {n_pose} positive values")
    return fs


def roll_turns(poses: NDArray[np.float64], R_gradients: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """(P, 2) cos and sin of twice each pose's roll about the optical axis relative to the camera rotation
    ``R_gradients`` (3, 3) the lidar gradients were computed at (None: no turn) for poses (P, 3, 4)."""
    roll2 = np.zeros((poses.shape[0], 2))
    roll2[:, 0] = 1.0
    if R_gradients is not None:
        R_rel = poses[:, :, :3] @ R_gradients.T
        roll = np.arctan2(R_rel[:, 1, 0], R_rel[:, 0, 0])
        roll2 = np.ascontiguousarray(np.column_stack([np.cos(2 * roll), np.sin(2 * roll)]))
    return roll2


@dataclass(frozen=True)
class GradientPlanes:
    """One image's gradients packed for the GOM kernel, built once per frame and shared by its scorers.

    Attributes:
        planes: (H', W', 2) float32 or int16 image gradient along u and along v (e.g. Sobel) at every
            ``stride``-th pixel: ``planes[i, j]`` is the image's pixel (u, v) = (j * stride, i * stride). In any
            unit: GOM is a ratio of sums each linear in the image gradient's magnitude, so only its directions
            and relative magnitudes enter (int16: ``image_gradients.quantised`` steps, read as they are).
        mask: (H', W') uint8, 1 where the image is valid, at the same pixels; ``ALL_VALID`` (1, 1) for an
            image without a mask.
        stride: pixels of the image per kept pixel, along rows and columns.
        row_stride: pixels of the image per kept row where it differs from ``stride`` (planes smoothed along
            one direction and thinned, ``blurred_along``): ``planes[i, j]`` is then the image's
            (j * stride, i * row_stride). None: ``stride``.
    """

    planes: NDArray[np.floating]
    mask: NDArray[np.uint8]
    stride: int = 1
    row_stride: int | None = None

    @classmethod
    def of(cls, image_gx: NDArray[np.floating], image_gy: NDArray[np.floating], camera: CameraModel,
           mask: NDArray[np.generic] | None = None) -> GradientPlanes:
        """Pack (H, W) gradients along u and v of an image of ``camera`` (optional (H, W) valid mask)."""
        igx, igy = np.asarray(image_gx), np.asarray(image_gy)
        if igx.shape != igy.shape or igx.ndim != 2:
            raise ProcessingError(f"image gradients {igx.shape} / {igy.shape} must be equal (H, W)")
        return cls.of_stacked(np.stack([igx, igy], axis=2), camera, mask)

    @classmethod
    def of_stacked(cls, image_gxy: NDArray[np.floating] | NDArray[np.int16], camera: CameraModel,
                   mask: NDArray[np.generic] | None = None, stride: int = 1) -> GradientPlanes:
        """Pack (H', W', 2) gradients (along u, along v) of an image of ``camera`` kept at every ``stride``-th
        pixel (``ImageGradients.stride``); ``mask`` is the whole image's (H, W). A C-contiguous float32 or int16
        array (``ImageGradients.gxy``) is shared, not copied; others become float32."""
        gxy = np.asarray(image_gxy)
        if gxy.ndim != 3 or gxy.shape[2] != 2:
            raise ProcessingError(f"stacked image gradients must be (H, W, 2), got {gxy.shape}")
        _check_kept(gxy.shape, camera, stride)
        shared = gxy.dtype == np.int16 and gxy.flags.c_contiguous
        return cls(gxy if shared else _planes(gxy), _kept_mask(mask, camera, stride), stride)

    @property
    def width_px(self) -> int:
        """Width of the image the planes were kept from, to within ``stride`` pixels."""
        return int(self.planes.shape[1]) * self.stride

    @property
    def strides(self) -> tuple[int, int]:
        """Pixels of the image per kept column and per kept row."""
        return self.stride, self.stride if self.row_stride is None else self.row_stride

    def as_float32(self) -> GradientPlanes:
        """These planes with their values in float32 (themselves where they are)."""
        if self.planes.dtype == np.float32:
            return self
        return dataclasses.replace(self, planes=np.ascontiguousarray(self.planes, dtype=np.float32))

    def _channel(self, c: int) -> NDArray[np.float32]:
        """Channel ``c`` (0: along u, 1: along v) as float32 in the planes' unit, for filtering (a view of float32
        planes)."""
        return np.asarray(self.planes[:, :, c], dtype=np.float32)

    def _square_stride(self) -> int:
        """The stride of planes kept at one stride along rows and columns (the blurs below assume it)."""
        if self.strides[0] != self.strides[1]:
            raise ProcessingError(f"planes kept at {self.strides[0]} x {self.strides[1]} pixels cannot be blurred "
                                  "again")
        return self.stride

    def blurred(self, sigma_px: float) -> GradientPlanes:
        """The gradients smoothed by a Gaussian of ``sigma_px`` image pixels (equal to the gradients of the
        image blurred by it: both are linear filters); same mask and stride."""
        sigma = sigma_px / self._square_stride()
        planes = np.stack([cv2.GaussianBlur(self._channel(c), (0, 0), sigma) for c in range(2)], axis=2)
        return GradientPlanes(np.ascontiguousarray(planes), self.mask, self.stride)

    def blurred_along(self, direction_uv: NDArray[np.floating], sigma_px: float,
                      thinned: bool = False) -> GradientPlanes:
        """The gradients smoothed by a one-dimensional Gaussian of ``sigma_px`` image pixels along the image
        direction ``direction_uv`` (2,) (e.g. across a lidar's rings) and not across it; same mask and stride.

        ``thinned``: kept only at every k-th column and l-th row of these planes, the widest that this blur
        and the least blur the planes' own stride implies (``least_blur_px``) together allow
        (``blur_thinning``): smoothed by 10 px across near-horizontal rings, planes kept at every second pixel
        keep every eighth row."""
        stride = self._square_stride()
        d = np.asarray(direction_uv, dtype=np.float64)
        d = d / np.linalg.norm(d)
        sigma = sigma_px / stride
        half = max(1, int(np.ceil(3.0 * sigma)))
        du, dv = np.meshgrid(np.arange(-half, half + 1.0), np.arange(-half, half + 1.0))
        along = du * d[0] + dv * d[1]
        across = np.abs(du * -d[1] + dv * d[0])
        kernel = np.exp(-0.5 * (along / sigma) ** 2) * np.maximum(0.0, 1.0 - across)  # line, 1 px wide
        kernel /= kernel.sum()
        planes = np.stack([cv2.filter2D(self._channel(c), -1, kernel, borderType=cv2.BORDER_REFLECT)
                           for c in range(2)], axis=2)
        if not thinned:
            return GradientPlanes(np.ascontiguousarray(planes), self.mask, stride)
        k, rows = blur_thinning(d, sigma_px, least_blur_px(stride), stride)
        return GradientPlanes(np.ascontiguousarray(planes[::rows, ::k]), _thinned_mask(self.mask, k, rows),
                              stride * k, stride * rows)


def least_blur_px(stride: int) -> float:
    """The least Gaussian blur (sigma, image pixels) of an image whose gradients ``sampling_stride`` keeps at
    ``stride`` pixels: sigma = stride sqrt(2 ln 1000) / pi (1.18 px at stride 1)."""
    return float(stride * np.sqrt(2.0 * np.log(1000.0)) / np.pi)


def blur_thinning(direction_uv: NDArray[np.float64], sigma_px: float, blur_px: float, stride: int) -> tuple[int, int]:
    """(k, l): every k-th column and l-th row of planes kept at ``stride`` image pixels is all an image needs
    once blurred by an isotropic Gaussian of ``blur_px`` and a one-dimensional one of ``sigma_px`` along the unit
    ``direction_uv`` (image pixels). Together they are a Gaussian of covariance S = blur^2 I + sigma^2 d d^T;
    its response on the columns' Nyquist line (any row frequency) peaks as that of a Gaussian of variance
    det S / S_vv (the rows': det S / S_uu), so each is kept at that Gaussian's ``sampling_stride``, a multiple
    of ``stride``. Across near-horizontal rings (d = (0, 1)) the rows take the stride of sqrt(blur^2 + sigma^2),
    the columns that of the blur alone; a diagonal d thins both, less."""
    from fleetcal.stages.image_gradients import sampling_stride

    S = blur_px**2 * np.eye(2) + sigma_px**2 * np.outer(direction_uv, direction_uv)
    det = float(np.linalg.det(S))
    columns = sampling_stride(float(np.sqrt(det / S[1, 1])))
    rows = sampling_stride(float(np.sqrt(det / S[0, 0])))
    return max(1, columns // stride), max(1, rows // stride)


def _thinned_mask(mask: NDArray[np.uint8], k: int, rows: int) -> NDArray[np.uint8]:
    """``mask`` at every k-th column and ``rows``-th row (the shared all-valid mask stays shared)."""
    if (k == rows == 1) or mask is ALL_VALID:
        return mask
    return np.ascontiguousarray(mask[::rows, ::k])


class GomScorer:
    """GOM of one lidar scan (with its sphere gradients) against one image's gradients."""

    def __init__(self, points_xyz: NDArray[np.floating], lidar_gx: NDArray[np.floating],
                 lidar_gy: NDArray[np.floating], lidar_magnitude: NDArray[np.floating],
                 image: GradientPlanes, camera: CameraModel,
                 R_camera_lidar_gradients: NDArray[np.floating] | None = None) -> None:
        """Args: points (N, 3) lidar frame; lidar gradient x/y/magnitude (N,) on the camera sphere;
        the image's gradient planes (shared, not copied); camera intrinsics; optional 3x3 rotation of
        the camera the lidar gradients were computed at: when given, each pose's roll about the optical
        axis relative to it turns the lidar gradient orientations (the paper keeps them fixed, which
        costs accuracy when the initial roll is off)."""
        self.points = _points(points_xyz)
        n = self.points.shape[0]
        gx = _per_point(lidar_gx, n, "lidar gx")
        gy = _per_point(lidar_gy, n, "lidar gy")
        self.magnitude = _per_point(lidar_magnitude, n, "lidar magnitude")
        theta = np.arctan2(gy, gx)
        self.c2 = np.ascontiguousarray(np.cos(2 * theta))
        self.s2 = np.ascontiguousarray(np.sin(2 * theta))
        _check_kept(image.planes.shape, camera, *image.strides)
        self.image = image
        self.camera = camera
        self.cam = camera_params(camera, *image.strides)
        self.R_gradients = None if R_camera_lidar_gradients is None else np.asarray(
            R_camera_lidar_gradients, dtype=np.float64).reshape(3, 3)

    def against(self, image: GradientPlanes) -> GomScorer:
        """This scorer's lidar gradients against other gradient planes of the same camera (e.g.
        ``image.blurred(...)`` for a wider basin), kept at their own strides."""
        _check_kept(image.planes.shape, self.camera, *image.strides)
        twin = copy.copy(self)
        twin.image = image
        twin.cam = camera_params(self.camera, *image.strides)
        return twin

    def subset(self, index: NDArray[np.int64]) -> GomScorer:
        """This scorer on the points ``index`` only (same image gradients)."""
        part = copy.copy(self)
        part.points = np.ascontiguousarray(self.points[index])
        part.c2 = np.ascontiguousarray(self.c2[index])
        part.s2 = np.ascontiguousarray(self.s2[index])
        part.magnitude = np.ascontiguousarray(self.magnitude[index])
        return part

    def score(self, T_camera_lidar_batch: NDArray[np.floating],
              focal_scale: NDArray[np.floating] | None = None) -> MetricBatch:
        num, den, count = self._sums(T_camera_lidar_batch, focal_scale)
        return MetricBatch.of_gom(num, den, count)

    def alignment(self, T_camera_lidar_batch: NDArray[np.floating]) -> NDArray[np.float64]:
        """(P,) GOM's numerator above chance, ``sum mu cos 2(a - b)`` over the projected points (lidar times
        image gradient magnitudes): large where many strong edges align. Unlike GOM it is not divided by the
        weight seen, so a pose that sees a few aligned edges does not beat one that sees many."""
        num, den, _ = self._sums(T_camera_lidar_batch, None)
        return np.asarray(num - den)

    def _sums(self, T_camera_lidar_batch: NDArray[np.floating], focal_scale: NDArray[np.floating] | None) -> tuple[
            NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """The GOM kernel's numerator, denominator and projected-point count per pose."""
        poses = pose_batch(T_camera_lidar_batch)
        num, den, count = mk.gom_batch_kernel(self.points, self.c2, self.s2, self.magnitude, self.image.planes,
                                              self.image.mask, self.cam, poses,
                                              focal_batch(focal_scale, poses.shape[0]),
                                              roll_turns(poses, self.R_gradients))
        return num, den, count


class NmiScorer:
    """NMI (paper eq. 3) of the lidar feature against the image intensity at the projected points."""

    def __init__(self, points_xyz: NDArray[np.floating], lidar_values: NDArray[np.floating],
                 image_intensity: NDArray[np.floating] | NDArray[np.uint8], camera: CameraModel,
                 mask: NDArray[np.generic] | None = None, bins: int = 32) -> None:
        """Args: points (N, 3) lidar frame; lidar feature (N,) in [0, 1]; image intensity (H, W), float in
        [0, 1] or uint8 (0-255, scaled); camera intrinsics; optional valid mask; histogram bins per axis."""
        self.points = _points(points_xyz)
        vals = _per_point(lidar_values, self.points.shape[0], "lidar feature")
        if bins < 2:
            raise ProcessingError("NMI needs at least 2 histogram bins")
        self.bins = int(bins)
        self.lidar_bin = np.ascontiguousarray(np.clip((vals * bins).astype(np.int64), 0, bins - 1))
        img = np.asarray(image_intensity)
        if img.shape != (camera.height, camera.width):
            raise ProcessingError(_size_message(img.shape, camera))
        self.planes = _planes(img / np.float32(255.0) if img.dtype == np.uint8 else img)
        self.mask = _mask(mask, img.shape)
        self.cam = camera_params(camera)

    def score(self, T_camera_lidar_batch: NDArray[np.floating],
              focal_scale: NDArray[np.floating] | None = None) -> MetricBatch:
        poses = pose_batch(T_camera_lidar_batch)
        nmi, count = mk.nmi_batch_kernel(self.points, self.lidar_bin, self.planes, self.mask, self.cam, poses,
                                         focal_batch(focal_scale, poses.shape[0]), self.bins)
        return MetricBatch(np.asarray(nmi), np.asarray(count))


class LevinsonScorer:
    """Levinson & Thrun: depth-discontinuity weight x edge image, summed over projected points."""

    def __init__(self, points_xyz: NDArray[np.floating], lidar_weight: NDArray[np.floating],
                 edge_image: NDArray[np.floating], camera: CameraModel,
                 mask: NDArray[np.generic] | None = None, stride: int = 1) -> None:
        """Args: points (N, 3) lidar frame; per-point depth-discontinuity weight (N,); edge image
        (H', W') from ``levinson_edge_image`` at every ``stride``-th pixel of the image; camera intrinsics;
        optional (H, W) valid mask of the whole image."""
        self.points = _points(points_xyz)
        self.weight = _per_point(lidar_weight, self.points.shape[0], "lidar weight")
        img = np.asarray(edge_image)
        if img.ndim != 2:
            raise ProcessingError(f"edge image must be (H, W), got {img.shape}")
        _check_kept(img.shape, camera, stride)
        self.planes = _planes(img)
        self.mask = _kept_mask(mask, camera, stride)
        self.cam = camera_params(camera, stride)
        self.scale = 1.0 / max(float(np.sum(self.weight)), 1e-12)

    def score(self, T_camera_lidar_batch: NDArray[np.floating],
              focal_scale: NDArray[np.floating] | None = None) -> MetricBatch:
        poses = pose_batch(T_camera_lidar_batch)
        s, count = mk.levinson_batch_kernel(self.points, self.weight, self.planes, self.mask, self.cam, poses,
                                            focal_batch(focal_scale, poses.shape[0]))
        return MetricBatch(np.asarray(s) * self.scale, np.asarray(count))


def levinson_edge_image(gradient_magnitude: NDArray[np.floating],
                        blur_sigma_px: float = 3.0) -> NDArray[np.float32]:
    """Levinson & Thrun's image term: edge strength scaled to [0, 1], Gaussian-blurred to widen the
    capture range, minus its mean (removes the bias towards edge-rich regions)."""
    mag = np.asarray(gradient_magnitude, dtype=np.float32)
    top = float(np.max(mag)) if mag.size else 0.0
    edges = np.asarray(mag / top if top > 0 else mag, dtype=np.float32)
    if blur_sigma_px > 0:
        edges = np.asarray(cv2.GaussianBlur(edges, (0, 0), blur_sigma_px), dtype=np.float32)
    return np.asarray(edges - np.float32(edges.mean()), dtype=np.float32)


def gom_reference(lidar_gx: NDArray[np.floating], lidar_gy: NDArray[np.floating],
                  lidar_magnitude: NDArray[np.floating], image_gx: NDArray[np.floating],
                  image_gy: NDArray[np.floating]) -> float:
    """GOM (eq. 9-11) of already-matched gradient pairs, with explicit angles; for checks and tests."""
    th_l = np.arctan2(lidar_gy, lidar_gx)
    th_i = np.arctan2(image_gy, image_gx)
    alpha = np.cos(2 * (th_i - th_l)) + 1
    mu = np.hypot(image_gx, image_gy) * np.asarray(lidar_magnitude)
    den = float(np.sum(mu))
    return float(np.sum(mu * alpha) / (2 * den)) if den > 0 else 0.0
