"""Camera gradient stage: kernel vs NumPy reference, Sobel/orientation ground truth, masks, edge cases."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.frames import CameraFrame
from fleetcal.stages import image_kernels
from fleetcal.stages.image_gradients import (
    ImageGradients,
    camera_frame_gradients,
    compute_image_gradients,
    sampling_stride,
    subsampled,
    to_grey_u8,
    undistort_image,
)


def reference_zeroed(gx: np.ndarray, gy: np.ndarray, valid: np.ndarray | None) -> tuple[np.ndarray, ...]:
    """Slow reference of ``image_kernels.zero_border_and_invalid``: zero border/invalid; and hypot."""
    keep = np.zeros(gx.shape, dtype=bool)
    keep[1:-1, 1:-1] = True
    if valid is not None:
        keep &= valid.astype(bool)
    gx_ref = np.where(keep, gx, 0).astype(np.float32)
    gy_ref = np.where(keep, gy, 0).astype(np.float32)
    mag = np.hypot(gx_ref.astype(np.float64), gy_ref.astype(np.float64))
    return gx_ref, gy_ref, mag


def reference_sobel(grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3x3 Sobel by explicit shifted sums (interior pixels only, border left 0)."""
    g = grey.astype(np.float64)
    gx = np.zeros_like(g)
    gy = np.zeros_like(g)
    h, w = g.shape
    for dr, wr in ((-1, 1.0), (0, 2.0), (1, 1.0)):
        gx[1:-1, 1:-1] += wr * (g[1 + dr : h - 1 + dr, 2:] - g[1 + dr : h - 1 + dr, :-2])
    for dc, wc in ((-1, 1.0), (0, 2.0), (1, 1.0)):
        gy[1:-1, 1:-1] += wc * (g[2:, 1 + dc : w - 1 + dc] - g[:-2, 1 + dc : w - 1 + dc])
    return gx, gy


@pytest.mark.parametrize("shape", [(3, 3), (7, 11), (64, 48)])
@pytest.mark.parametrize("with_mask", [False, True])
def test_border_kernel_matches_reference(shape: tuple[int, int], with_mask: bool) -> None:
    rng = np.random.default_rng(sum(shape))
    gxy = rng.normal(scale=50, size=(*shape, 2)).astype(np.float32)
    valid = (rng.random(shape) > 0.3).astype(np.uint8) if with_mask else None
    gx_ref, gy_ref, mag_ref = reference_zeroed(gxy[:, :, 0], gxy[:, :, 1], valid)
    image_kernels.zero_border_and_invalid(gxy, valid if valid is not None else np.empty((0, 0), np.uint8), with_mask)
    grads = ImageGradients(gxy)
    np.testing.assert_array_equal(grads.gx, gx_ref)
    np.testing.assert_array_equal(grads.gy, gy_ref)
    np.testing.assert_allclose(grads.magnitude, mag_ref, rtol=1e-6, atol=1e-6)
    assert grads.magnitude.dtype == grads.orientation.dtype == np.float32


def test_border_kernel_constant_and_zero_inputs() -> None:
    gxy = np.stack([np.full((5, 6), 3.0, np.float32), np.full((5, 6), 4.0, np.float32)], axis=2)
    image_kernels.zero_border_and_invalid(gxy, np.empty((0, 0), np.uint8), False)
    mag = ImageGradients(gxy).magnitude
    assert np.all(mag[1:-1, 1:-1] == 5.0)
    assert mag[0].sum() == mag[-1].sum() == mag[:, 0].sum() == mag[:, -1].sum() == 0.0
    zeros = np.zeros((4, 4, 2), np.float32)
    image_kernels.zero_border_and_invalid(zeros, np.empty((0, 0), np.uint8), False)
    assert not ImageGradients(zeros).orientation.any()


def test_sobel_matches_explicit_reference_on_random_image() -> None:
    rng = np.random.default_rng(3)
    grey = rng.integers(0, 256, size=(40, 57), dtype=np.uint8)
    grads = compute_image_gradients(grey, equalize=False)
    gx_ref, gy_ref = reference_sobel(grey)
    np.testing.assert_allclose(grads.gx, gx_ref, atol=1e-3)
    np.testing.assert_allclose(grads.gy, gy_ref, atol=1e-3)
    np.testing.assert_allclose(grads.magnitude, np.hypot(gx_ref, gy_ref), rtol=1e-5, atol=1e-3)
    interior = (slice(1, -1), slice(1, -1))
    np.testing.assert_allclose(grads.orientation[interior], np.arctan2(gy_ref, gx_ref)[interior], atol=1e-5)
    for arr in (grads.gx, grads.gy, grads.magnitude, grads.orientation):
        assert arr.dtype == np.float32 and arr.shape == grey.shape


@pytest.mark.parametrize("theta_deg", [0.0, 30.0, 90.0, 135.0, -60.0, 180.0])
def test_orientation_of_a_ramp_is_its_direction(theta_deg: float) -> None:
    theta = np.radians(theta_deg)
    rows, cols = np.mgrid[0:60, 0:80].astype(np.float64)
    ramp = 128 + 1.2 * ((cols - 40) * np.cos(theta) + (rows - 30) * np.sin(theta))
    grey = np.clip(np.round(ramp), 0, 255).astype(np.uint8)
    inner = (slice(6, -6), slice(6, -6))
    grads = compute_image_gradients(grey, blur_sigma_px=2.0, equalize=False)
    err = np.angle(np.exp(1j * (grads.orientation[inner].astype(np.float64) - theta)))
    assert np.median(np.abs(err)) < np.radians(2.0)
    assert np.median(grads.magnitude[inner]) == pytest.approx(8 * 1.2, rel=0.05)
    wide = compute_image_gradients((grey.astype(np.uint16) * 200), blur_sigma_px=2.0, equalize=False)
    err16 = np.angle(np.exp(1j * (wide.orientation[inner].astype(np.float64) - theta)))
    assert np.median(np.abs(err16)) < np.radians(2.0)


def test_constant_image_gives_zero_gradients() -> None:
    for image in (
        np.full((20, 30), 77, np.uint8),
        np.full((20, 30, 3), 200, np.uint8),
        np.full((20, 30), 4000, np.uint16),
    ):
        for sigma in (0.0, 2.0):
            grads = compute_image_gradients(image, blur_sigma_px=sigma)
            assert not grads.magnitude.any() and not grads.orientation.any()
            assert not grads.gx.any() and not grads.gy.any()


def test_grey_conversion_rgb_and_mono16() -> None:
    rng = np.random.default_rng(5)
    rgb = rng.integers(0, 256, size=(10, 12, 3), dtype=np.uint8)
    expected = np.round(rgb @ np.array([0.299, 0.587, 0.114]))
    assert np.abs(to_grey_u8(rgb).astype(int) - expected).max() <= 1
    mono8 = rng.integers(0, 256, size=(10, 12), dtype=np.uint8)
    mono8[0, 0], mono8[0, 1] = 0, 255
    np.testing.assert_array_equal(to_grey_u8(mono8.astype(np.uint16) * 257), mono8)
    twelve_bit = mono8.astype(np.uint16) * 16
    assert np.abs(to_grey_u8(twelve_bit).astype(int) - mono8).max() <= 1


def test_equalisation_spreads_a_low_contrast_image() -> None:
    rng = np.random.default_rng(7)
    dull = rng.integers(100, 110, size=(50, 50), dtype=np.uint8)
    plain = compute_image_gradients(dull, equalize=False)
    eq = compute_image_gradients(dull, equalize=True)
    assert eq.magnitude.mean() > 10 * plain.magnitude.mean()
    grey_eq = cv2.equalizeHist(dull)
    gx_ref, _ = reference_sobel(grey_eq)
    np.testing.assert_allclose(eq.gx, gx_ref, atol=1e-3)


def test_mask_zeroes_outside_and_keeps_inside() -> None:
    rng = np.random.default_rng(11)
    grey = rng.integers(0, 256, size=(30, 40), dtype=np.uint8)
    mask = np.zeros(grey.shape, bool)
    mask[5:25, 8:30] = True
    masked = compute_image_gradients(grey, equalize=False, mask=mask)
    full = compute_image_gradients(grey, equalize=False)
    inner = np.zeros_like(mask)
    inner[6:24, 9:29] = True
    np.testing.assert_array_equal(masked.magnitude[inner], full.magnitude[inner])
    assert not masked.magnitude[~inner].any() and not masked.orientation[~inner].any()


def test_masked_equalisation_over_everything_equals_opencv() -> None:
    rng = np.random.default_rng(13)
    grey = rng.integers(20, 180, size=(25, 35), dtype=np.uint8)
    everything = compute_image_gradients(grey, mask=np.ones(grey.shape, bool))
    plain = compute_image_gradients(grey)
    inner = (slice(1, -1), slice(1, -1))
    np.testing.assert_array_equal(everything.gx[inner], plain.gx[inner])
    np.testing.assert_array_equal(everything.gy[inner], plain.gy[inner])


def test_masked_equalisation_ignores_invalid_pixels() -> None:
    rng = np.random.default_rng(19)
    grey = rng.integers(100, 120, size=(30, 30), dtype=np.uint8)
    grey[:, :10] = 255
    mask = np.zeros(grey.shape, bool)
    mask[:, 10:] = True
    masked = compute_image_gradients(grey, mask=mask, equalize=True)
    unmasked_part = compute_image_gradients(np.ascontiguousarray(grey[:, 10:]), equalize=True)
    np.testing.assert_array_equal(masked.gx[1:-1, 12:-1], unmasked_part.gx[1:-1, 2:-1])


def test_blur_matches_gaussian_then_sobel() -> None:
    rng = np.random.default_rng(17)
    grey = rng.integers(0, 256, size=(40, 50), dtype=np.uint8)
    grads = compute_image_gradients(grey, blur_sigma_px=1.5, equalize=False)
    blurred = cv2.GaussianBlur(grey.astype(np.float32), (0, 0), 1.5)
    gx_ref, gy_ref = reference_sobel(blurred)
    np.testing.assert_allclose(grads.gx, gx_ref, atol=1e-3)
    np.testing.assert_allclose(grads.gy, gy_ref, atol=1e-3)
    assert grads.magnitude.mean() < 0.5 * compute_image_gradients(grey, equalize=False).magnitude.mean()


@pytest.mark.parametrize("sigma, stride", [(0.0, 1), (1.0, 1), (2.0, 1), (2.58, 2), (3.1, 2), (3.6, 3), (6.2, 5)])
def test_sampling_stride_is_the_widest_the_blur_allows(sigma: float, stride: int) -> None:
    """The Gaussian's response at the kept grid's Nyquist frequency (1 / (2 s) cycles per pixel) is at most
    1e-3 of its peak at the stride chosen and above it at the next one (or the stride is 1)."""
    def response(s: int) -> float:
        return float(np.exp(-(np.pi**2) * sigma**2 / (2.0 * s**2)))

    assert sampling_stride(sigma) == stride
    assert stride == 1 or response(stride) <= 1e-3
    assert response(stride + 1) > 1e-3


def test_subsampled_gradients_keep_every_strideth_pixel() -> None:
    gxy = np.random.default_rng(4).standard_normal((7, 10, 2)).astype(np.float32)
    kept = subsampled(ImageGradients(gxy), 3)
    assert kept.gxy.shape == (3, 4, 2) and kept.stride == 3 and kept.gxy.flags.c_contiguous
    assert kept.gxy[2, 3, 1] == gxy[6, 9, 1] and kept.gx[1, 2] == gxy[3, 6, 0]
    assert subsampled(kept, 2).stride == 6 and subsampled(kept, 1) is kept
    with pytest.raises(InputError, match="stride"):
        subsampled(kept, 0)


@pytest.mark.parametrize(
    "image, kwargs, match",
    [
        (np.zeros((10, 10), np.float32), {}, "dtype"),
        (np.zeros((10, 10, 4), np.uint8), {}, "shape"),
        (np.zeros(10, np.uint8), {}, "shape"),
        (np.zeros((2, 10), np.uint8), {}, "too small"),
        ([[1, 2, 3]], {}, "numpy array"),
        (np.zeros((10, 10), np.uint8), {"blur_sigma_px": -1.0}, "blur_sigma_px"),
        (np.zeros((10, 10), np.uint8), {"blur_sigma_px": float("nan")}, "blur_sigma_px"),
        (np.zeros((10, 10), np.uint8), {"mask": np.ones((9, 10), bool)}, "mask"),
    ],
)
def test_bad_inputs_raise_input_error(image: object, kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(InputError, match=match):
        compute_image_gradients(image, **kwargs)  # type: ignore[arg-type]


def _dot_image(camera: CameraModel, uv: np.ndarray) -> np.ndarray:
    image = np.zeros((camera.height, camera.width), np.uint8)
    u, v = np.round(uv).astype(int)
    image[v - 2 : v + 3, u - 2 : u + 3] = 255
    return image


@pytest.mark.parametrize(
    "model, D",
    [
        ("plumb_bob", [-0.3, 0.1, 0.001, -0.002, 0.0]),
        ("rational_polynomial", [-0.25, 0.08, 0.0, 0.0, 0.0, 0.02, 0.0, 0.0]),
        ("equidistant", [0.05, -0.01, 0.002, 0.0]),
    ],
)
def test_undistort_moves_a_point_to_its_pinhole_projection(model: str, D: list[float]) -> None:
    K = np.array([[400.0, 0, 320], [0, 400.0, 240], [0, 0, 1]])
    camera = CameraModel(640, 480, K, np.array(D), model)
    point = np.array([[0.45, -0.3, 1.0]])
    uv_distorted, ok = camera.project(point)
    assert ok[0]
    undistorted, pinhole = undistort_image(_dot_image(camera, uv_distorted[0]), camera)
    vs, us = np.nonzero(np.asarray(undistorted, dtype=np.int32) > 64)
    uv_pinhole = (K @ point[0])[:2] / point[0, 2]
    shift = np.linalg.norm(uv_distorted[0] - uv_pinhole)
    assert shift > 5.0
    assert np.hypot(us.mean() - uv_pinhole[0], vs.mean() - uv_pinhole[1]) < 1.5
    assert pinhole.distortion_model == "plumb_bob" and not pinhole.D.any()


def test_undistort_without_distortion_and_errors() -> None:
    K = np.array([[400.0, 0, 320], [0, 400.0, 240], [0, 0, 1]])
    image = np.random.default_rng(0).integers(0, 255, (480, 640), dtype=np.uint8)
    same, _ = undistort_image(image, CameraModel(640, 480, K, np.zeros(5), "none"))
    assert same is image
    with pytest.raises(InputError, match="cylindrical"):
        undistort_image(image, CameraModel(640, 480, K, np.zeros(0), "cylindrical"))
    with pytest.raises(InputError, match="640x480"):
        undistort_image(image[:, :600], CameraModel(640, 480, K, np.zeros(5), "plumb_bob"))


def test_camera_stage_skips_blank_and_returns_gradients() -> None:
    blank = CameraFrame(
        stamp_ns=5, topic="/cam", frame_id="cam", image=np.zeros((20, 20), np.uint8), encoding="mono8"
    )
    with pytest.raises(InputError, match="blank image"):
        camera_frame_gradients(blank)
    image = np.zeros((20, 30, 3), np.uint8)
    image[:, 15:] = 200
    result = camera_frame_gradients(CameraFrame(7, "/cam", "cam", image, "rgb8"))
    assert (result.stamp_ns, result.width, result.height) == (7, 30, 20)
    column_strength = result.gradients.magnitude[1:-1].sum(axis=0)
    assert set(np.flatnonzero(column_strength)) == {14, 15}
    assert np.allclose(np.abs(result.gradients.orientation[5, 14:16]), 0.0)


def test_kitti_image_gradients(shared_data: Path) -> None:
    from fleetcal.readers.frames import iter_camera_frames
    from fleetcal.readers.open import open_log

    with open_log(shared_data / "logs" / "kitti_2011_09_26.mcap") as reader:
        frame = next(iter_camera_frames(reader, "/kitti/camera_color_left/image_raw"))
    result = camera_frame_gradients(frame, blur_sigma_px=1.0)
    grads = result.gradients
    assert grads.shape == (375, 1242) == (result.height, result.width)
    assert not grads.magnitude[0].any() and not grads.magnitude[:, -1].any()
    assert (grads.magnitude > 0).mean() > 0.8
    assert np.all(np.abs(grads.orientation) <= np.pi)
    gx_ref, gy_ref = reference_sobel(
        cv2.GaussianBlur(cv2.equalizeHist(to_grey_u8(frame.image)).astype(np.float32), (0, 0), 1.0)
    )
    np.testing.assert_allclose(grads.gx, gx_ref, atol=2e-3)
    np.testing.assert_allclose(grads.gy, gy_ref, atol=2e-3)
