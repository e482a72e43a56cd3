"""Camera image gradients (GOM paper section 3.3): grey, histogram equalisation, optional Gaussian
blur, 3x3 Sobel, gradient magnitude and orientation; plus an optional undistortion helper.

Pixel (row, column) = (v, u) of the image; ``gx`` is the derivative along u (columns, x right) and
``gy`` along v (rows, y down), so ``orientation = atan2(gy, gx)`` is in the optical-frame image plane.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.frames import CameraFrame
from fleetcal.stages import image_kernels

__all__ = [
    "QUANTA_PER_GREY_LEVEL",
    "CameraGradientResult",
    "ImageGradients",
    "camera_frame_gradients",
    "compute_image_gradients",
    "quantised",
    "sampling_stride",
    "subsampled",
    "to_grey_u8",
    "undistort_image",
]


@dataclass
class ImageGradients:
    """Gradients of one image: one (H, W, 2) array, the rest views or computed on demand.

    Attributes:
        gxy: (H, W, 2) 3x3 Sobel derivative along columns (x, channel 0) and rows (y, channel 1), in
            equalised 8-bit grey levels (Sobel weights unnormalised, so a step of 1 grey level gives 4) times
            ``scale``: float32 (scale 1), or int16 in ``QUANTA_PER_GREY_LEVEL`` steps (``quantised``).
            Interleaved as the GOM kernel reads it, so the objective shares it without a copy.
        stride: ``gxy[i, j]`` is the gradient at image pixel (u, v) = (j * stride, i * stride) (``subsampled``);
            1: every pixel.
        scale: units of ``gxy`` per grey level of gradient.
    ``gx``, ``gy``, ``magnitude`` (``hypot(gx, gy)``) and ``orientation`` (``atan2(gy, gx)``, radians in
    (-pi, pi], 0 where the magnitude is 0) are (H, W) float32 in grey levels: views of float32 ``gxy``, the
    others computed on each access, so a frame holds ``gxy`` alone. All are 0 on the 1-pixel image border
    and outside the (eroded) valid mask.
    """

    gxy: NDArray[np.float32] | NDArray[np.int16]
    stride: int = 1
    scale: float = 1.0

    def _channel(self, c: int) -> NDArray[np.float32]:
        g = self.gxy[:, :, c]
        if g.dtype == np.float32 and self.scale == 1.0:
            return g  # type: ignore[return-value]
        return np.asarray(g, dtype=np.float32) * np.float32(1.0 / self.scale)

    @property
    def gx(self) -> NDArray[np.float32]:
        return self._channel(0)

    @property
    def gy(self) -> NDArray[np.float32]:
        return self._channel(1)

    @property
    def magnitude(self) -> NDArray[np.float32]:
        return np.hypot(self.gx, self.gy)

    @property
    def orientation(self) -> NDArray[np.float32]:
        return np.arctan2(self.gy, self.gx)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.gxy.shape[0]), int(self.gxy.shape[1]))


def to_grey_u8(image: NDArray[np.generic]) -> NDArray[np.uint8]:
    """8-bit grey of an (H, W) uint8/uint16 or (H, W, 3) RGB uint8/uint16 image.

    16-bit images are scaled min-max to 0..255 first (so 12-bit data in 16-bit words uses the whole
    range); colour is converted with the ITU-R 601 weights of ``cv2.COLOR_RGB2GRAY``.

    Raises:
        InputError: not an ndarray, wrong shape or dtype.
    """
    _check_image(image)
    img = np.ascontiguousarray(image)
    if img.dtype == np.uint16:
        lo, hi = int(img.min()), int(img.max())
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        img = cv2.convertScaleAbs(img, alpha=scale, beta=-lo * scale)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return np.ascontiguousarray(img, dtype=np.uint8)


def compute_image_gradients(
    image: NDArray[np.generic],
    blur_sigma_px: float = 0.0,
    equalize: bool = True,
    mask: NDArray[np.bool_] | None = None,
) -> ImageGradients:
    """Sobel gradients of an image after grey conversion, equalisation and optional blur.

    Args:
        image: (H, W) mono8/mono16 or (H, W, 3) RGB uint8 (see ``to_grey_u8``); H, W >= 3.
        blur_sigma_px: Gaussian blur sigma in pixels before the Sobel (0: none).
        equalize: histogram-equalise the grey image (``cv2.equalizeHist``; with a mask the histogram
            is taken over the valid pixels only).
        mask: optional (H, W) bool, True where the image is valid. Gradients are zeroed where the
            3x3 Sobel window touches an invalid pixel (the mask eroded by one pixel).

    Returns:
        ImageGradients (float32). A constant image gives exactly zero gradients (no blur round-off).

    Raises:
        InputError: bad image shape/dtype, image smaller than 3x3, bad mask, negative/NaN sigma.
    """
    grey = to_grey_u8(image)
    height, width = grey.shape
    if height < 3 or width < 3:
        raise InputError(f"image of {height}x{width} pixels is too small for a 3x3 Sobel (need >= 3x3)")
    if not np.isfinite(blur_sigma_px) or blur_sigma_px < 0:
        raise InputError(f"blur_sigma_px must be a finite number >= 0, got {blur_sigma_px}")
    valid_u8 = _valid_mask(mask, grey.shape)
    if int(grey.min()) == int(grey.max()):
        return ImageGradients(np.zeros((height, width, 2), np.float32))
    if equalize:
        grey = _equalize(grey, valid_u8)
    grey_f: NDArray[np.float32] = grey.astype(np.float32)
    if blur_sigma_px > 0:
        sigma = float(blur_sigma_px)
        grey_f = np.asarray(cv2.GaussianBlur(grey_f, (0, 0), sigmaX=sigma, sigmaY=sigma), dtype=np.float32)
    gxy = np.empty((height, width, 2), np.float32)
    gxy[:, :, 0] = cv2.Sobel(grey_f, cv2.CV_32F, 1, 0, ksize=3)
    gxy[:, :, 1] = cv2.Sobel(grey_f, cv2.CV_32F, 0, 1, ksize=3)
    if valid_u8 is None:
        image_kernels.zero_border_and_invalid(gxy, np.empty((0, 0), np.uint8), False)
    else:
        eroded = cv2.erode(valid_u8, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
        image_kernels.zero_border_and_invalid(gxy, eroded, True)
    return ImageGradients(gxy)


def sampling_stride(blur_sigma_px: float) -> int:
    """The widest pixel stride at which gradients of an image blurred by a Gaussian of ``blur_sigma_px`` pixels
    can be stored without losing what the blur left: the largest s whose grid's Nyquist frequency 1 / (2 s)
    cycles per pixel the Gaussian passes at no more than 1e-3 of its peak, exp(-pi^2 sigma^2 / (2 s^2)) <= 1e-3,
    i.e. s <= pi sigma / sqrt(2 ln 1000) = 0.845 sigma (at least 1). 2 px of blur: 1; 3.1 px (1920 px wide): 2."""
    if not np.isfinite(blur_sigma_px) or blur_sigma_px <= 0:
        return 1
    return max(1, int(np.floor(np.pi * float(blur_sigma_px) / np.sqrt(2.0 * np.log(1000.0)))))


def subsampled(gradients: ImageGradients, stride: int) -> ImageGradients:
    """``gradients`` kept at every ``stride``-th pixel along rows and columns (``ImageGradients.stride``
    times ``stride``): a quarter of the memory at stride 2. Interpolated between the kept pixels they are the
    full image's gradients wherever the image was blurred enough for the stride (``sampling_stride``)."""
    if stride < 1:
        raise InputError(f"stride must be >= 1, got {stride}")
    if stride == 1:
        return gradients
    kept = cast("NDArray[np.float32] | NDArray[np.int16]", np.ascontiguousarray(gradients.gxy[::stride, ::stride]))
    return ImageGradients(kept, gradients.stride * stride, gradients.scale)


QUANTA_PER_GREY_LEVEL = 32
"""Steps of a ``quantised`` gradient per grey level: the largest power of two that holds the largest 3x3 Sobel
response of an 8-bit image (4 x 255 = 1020 grey levels, 32,640 steps) in int16."""


def quantised(gradients: ImageGradients) -> ImageGradients:
    """``gradients`` held as int16 in steps of 1 / ``QUANTA_PER_GREY_LEVEL`` grey level: half the memory of
    float32, each value within 1/64 grey level of the float's (the blurred image's own 8-bit rounding is 32
    times coarser)."""
    if gradients.gxy.dtype == np.int16:
        return gradients
    steps = np.rint(np.asarray(gradients.gxy, dtype=np.float32) * np.float32(QUANTA_PER_GREY_LEVEL / gradients.scale))
    limit = np.iinfo(np.int16).max
    return ImageGradients(np.clip(steps, -limit, limit).astype(np.int16), gradients.stride,
                          float(QUANTA_PER_GREY_LEVEL))


def undistort_image(
    image: NDArray[np.generic], camera: CameraModel
) -> tuple[NDArray[np.generic], CameraModel]:
    """Remove lens distortion; returns the image and its distortion-free pinhole model (same K).

    ``plumb_bob`` / ``rational_polynomial`` use ``cv2.undistort``; ``equidistant`` uses
    ``cv2.fisheye.undistortImage``; ``none`` (or all-zero coefficients) returns the image unchanged.
    Pixels with no source come out 0.

    Raises:
        InputError: image size differs from the camera's, or a ``cylindrical`` model (a panorama has
            no pinhole equivalent).
    """
    _check_image(image)
    height, width = int(image.shape[0]), int(image.shape[1])
    if (width, height) != (camera.width, camera.height):
        raise InputError(f"image is {width}x{height} but the camera model is {camera.width}x{camera.height}")
    model = camera.distortion_model
    if model == "cylindrical":
        raise InputError("a cylindrical (panoramic) camera cannot be undistorted to a pinhole image")
    pinhole = CameraModel(camera.width, camera.height, camera.K.copy(), np.zeros(5), "plumb_bob", camera.R_rect)
    if model == "none" or not np.any(camera.D):
        return image, pinhole
    if model == "equidistant":
        out = cv2.fisheye.undistortImage(np.asarray(image), camera.K, camera.coefficients(4), Knew=camera.K)
    else:
        n = 8 if model == "rational_polynomial" else 5
        out = cv2.undistort(np.asarray(image), camera.K, camera.coefficients(n))
    return np.asarray(out), pinhole


@dataclass
class CameraGradientResult:
    """Per-frame result of ``camera_frame_gradients``: stamp, topic, size and the gradients."""

    stamp_ns: int
    topic: str
    width: int
    height: int
    gradients: ImageGradients


def camera_frame_gradients(
    frame: CameraFrame, blur_sigma_px: float = 0.0, equalize: bool = True, undistort: bool = False
) -> CameraGradientResult:
    """Engine stage: gradients of one camera frame (undistorted first when asked and a model exists).

    Raises:
        InputError: a blank (constant) image, or bad image data.
    """
    image = frame.image
    _check_image(image)
    if image.size and int(image.min()) == int(image.max()):
        raise InputError(f"blank image (constant value {int(image.min())}) at stamp {frame.stamp_ns}")
    if undistort and frame.camera is not None:
        image, _ = undistort_image(image, frame.camera)
    grads = compute_image_gradients(image, blur_sigma_px=blur_sigma_px, equalize=equalize)
    return CameraGradientResult(frame.stamp_ns, frame.topic, frame.width, frame.height, grads)


def _check_image(image: object) -> None:
    if not isinstance(image, np.ndarray):
        raise InputError(f"image must be a numpy array, got {type(image).__name__}")
    if image.dtype not in (np.uint8, np.uint16):
        raise InputError(f"image dtype must be uint8 or uint16, got {image.dtype}")
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3):
        return
    raise InputError(f"image must be (H, W) or (H, W, 3), got shape {image.shape}")


def _valid_mask(mask: NDArray[np.bool_] | None, shape: tuple[int, ...]) -> NDArray[np.uint8] | None:
    if mask is None:
        return None
    if not isinstance(mask, np.ndarray) or mask.shape != shape:
        got = getattr(mask, "shape", type(mask).__name__)
        raise InputError(f"mask must be an array of the image's shape {shape}, got {got}")
    return np.ascontiguousarray(mask, dtype=bool).view(np.uint8)


def _equalize(grey: NDArray[np.uint8], valid_u8: NDArray[np.uint8] | None) -> NDArray[np.uint8]:
    if valid_u8 is None:
        return np.asarray(cv2.equalizeHist(grey))
    hist = np.bincount(grey[valid_u8.astype(bool)], minlength=256).astype(np.float64)
    total = hist.sum()
    nonzero = np.flatnonzero(hist)
    if nonzero.size <= 1:
        return grey
    cdf = np.cumsum(hist)
    first = hist[nonzero[0]]
    lut = np.clip(np.rint((cdf - first) * 255.0 / (total - first)), 0, 255).astype(np.uint8)
    return np.asarray(cv2.LUT(grey, lut))
