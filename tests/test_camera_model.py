"""The valid region of the lens models (``CameraModel.max_undistorted_radius``, ``max_view_angle_rad``):
derived from the coefficients, checked against a dense NumPy scan of the radial map, with projection and
unprojection inside it round-tripping and far-off points culled without overflow or warnings."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.workflows.simulator.camera import WIDE_ANGLE_D, fisheye_camera, pinhole_camera, wide_angle_camera

RATIONAL_D = np.array([-0.40, 0.20, -0.001, 0.0002, -0.07, 0.01, 0.0, 0.002])


def _first_fold_reference(camera: CameraModel, r_hi: float = 20.0, n: int = 2_000_001) -> float:
    """NumPy reference: the first radius on a dense grid where ``r -> r radial(r^2)`` stops growing (inf
    when it grows all the way to ``r_hi``)."""
    k1, k2, _, _, k3, k4, k5, k6 = camera.coefficients(8)
    if camera.distortion_model == "plumb_bob":
        k4 = k5 = k6 = 0.0
    r = np.linspace(0.0, r_hi, n)
    s = r * r
    f = r * (1 + s * (k1 + s * (k2 + s * k3))) / (1 + s * (k4 + s * (k5 + s * k6)))
    grows = np.diff(f) > 0
    return float("inf") if np.all(grows) else float(r[int(np.argmin(grows))])


def _wide(model: str = "plumb_bob") -> CameraModel:
    cam = wide_angle_camera(1280, 720)
    if model == "plumb_bob":
        return cam
    return CameraModel(cam.width, cam.height, cam.K, RATIONAL_D, model)


@pytest.mark.parametrize("model", ["plumb_bob", "rational_polynomial"])
def test_max_undistorted_radius_is_where_the_radial_map_stops_growing(model: str) -> None:
    cam = _wide(model)
    r_max = cam.max_undistorted_radius
    assert r_max == pytest.approx(_first_fold_reference(cam), abs=2e-5)
    if model == "plumb_bob":
        assert np.degrees(np.arctan(r_max)) == pytest.approx(50.1, abs=0.1)  # inside the 59 deg corners
    r = np.linspace(0.0, r_max, 10_001)
    f, df = cam._radial_map(r)
    assert np.all(np.diff(f) > 0)  # monotonic inside the region
    assert df[-1] == pytest.approx(0.0, abs=1e-9)  # and flat at its edge
    f_out, _ = cam._radial_map(np.array([r_max * 1.05]))
    assert f_out[0] < f[-1]  # folds back beyond it


def test_mild_and_undistorted_lenses_have_no_limit() -> None:
    assert pinhole_camera(640, 360).max_undistorted_radius == float("inf")
    assert _first_fold_reference(pinhole_camera(640, 360)) == float("inf")
    plain = CameraModel(640, 360, np.array([[500.0, 0, 320], [0, 500, 180], [0, 0, 1]]), np.zeros(5))
    assert plain.max_undistorted_radius == float("inf")
    assert fisheye_camera(640, 360).max_view_angle_rad == pytest.approx(np.radians(89.0))


def test_equidistant_view_angle_stops_where_theta_d_stops_growing() -> None:
    K = np.array([[300.0, 0, 320], [0, 300, 240], [0, 0, 1]])
    cam = CameraModel(640, 480, K, np.array([-0.2, 0.0, 0.0, 0.0]), "equidistant")
    th = np.linspace(0.0, np.pi / 2, 1_000_001)
    reference = th[int(np.argmin(np.diff(th * (1 - 0.2 * th**2)) > 0))]
    assert cam.max_view_angle_rad == pytest.approx(reference, abs=1e-5)  # sqrt(1 / 0.6) = 1.29 rad
    behind_fold = np.array([[np.sin(1.35), 0.0, np.cos(1.35)], [np.sin(1.2), 0.0, np.cos(1.2)]])
    _, valid = cam.project(behind_fold)
    assert valid.tolist() == [False, True]


@pytest.mark.parametrize("model", ["plumb_bob", "rational_polynomial"])
def test_projection_inside_the_region_matches_opencv_and_round_trips(model: str) -> None:
    cam = _wide(model)
    rng = np.random.default_rng(3)
    pts = rng.uniform(-1.5, 1.5, size=(20_000, 3))
    pts[:, 2] = rng.uniform(0.2, 3.0, 20_000)
    uv, valid = cam.project(pts)
    inside_region = np.hypot(pts[:, 0], pts[:, 1]) / pts[:, 2] <= cam.max_undistorted_radius
    assert not np.any(valid & ~inside_region)
    assert valid.sum() > 3000
    cv_uv, _ = cv2.projectPoints(pts[valid].reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cam.K, cam.D)
    np.testing.assert_allclose(uv[valid], cv_uv.reshape(-1, 2), atol=1e-6)
    rays = cam.unproject(uv[valid])
    r = np.hypot(pts[valid, 0], pts[valid, 1]) / pts[valid, 2]
    well_inside = r < 0.95 * cam.max_undistorted_radius  # at the edge the map is flat: rays ill-conditioned
    np.testing.assert_allclose(rays[well_inside, :2], pts[valid][well_inside, :2] / pts[valid][well_inside, 2:],
                               atol=1e-9)
    uv_back, ok = cam.project(rays)
    assert np.all(ok)
    np.testing.assert_allclose(uv_back[well_inside], uv[valid][well_inside], atol=1e-6)
    np.testing.assert_allclose(uv_back, uv[valid], atol=0.05)  # tangential terms converge slowly at the fold


def test_pixels_beyond_the_region_unproject_to_its_edge() -> None:
    """The wide-angle image's corners lie beyond the image of the valid region: they get the ray at the
    region's edge in their direction; every pixel inside it round-trips."""
    cam = wide_angle_camera(1280, 720)
    v, u = np.mgrid[0:720:8, 0:1280:8]
    uv = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rays = cam.unproject(uv)
        uv_back, valid = cam.project(rays)
    assert np.all(np.isfinite(rays))
    radius = np.hypot(rays[:, 0], rays[:, 1]) / rays[:, 2]
    assert np.all(radius <= cam.max_undistorted_radius + 1e-12)
    f_edge = float(cam._radial_map(np.array([cam.max_undistorted_radius]))[0][0])
    d = (uv - [cam.cx, cam.cy]) / cam.fx
    beyond = np.hypot(d[:, 0], d[:, 1]) > f_edge * 1.01
    within = np.hypot(d[:, 0], d[:, 1]) < f_edge * 0.99
    assert 0.005 < beyond.mean() < 0.05  # the corners
    np.testing.assert_allclose(radius[beyond], cam.max_undistorted_radius, rtol=1e-9)
    assert np.all(valid[within])
    np.testing.assert_allclose(uv_back[within], uv[within], atol=1e-6)
    assert not np.any(np.abs(uv_back[beyond] - uv[beyond]).max(axis=1) < 1.0)  # lands short


@pytest.mark.parametrize("make", [wide_angle_camera, pinhole_camera, fisheye_camera])
def test_far_off_points_are_culled_without_overflow_or_warnings(make: object) -> None:
    cam = make(1280, 720)  # type: ignore[operator]
    pts = np.array([[1e200, 1.0, 1e-300], [1.0, 1.0, 0.0], [1.0, 1.0, -1.0], [1e5, 1e5, 1.0],
                    [1e308, -1e308, 1e-3], [100.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv, valid = cam.project(pts)
    assert valid.tolist() == [False] * 6 + [True]
    np.testing.assert_allclose(uv[-1], [cam.cx, cam.cy])


def test_wide_angle_coefficients_are_the_real_lens() -> None:
    cam = wide_angle_camera(1280, 720)
    assert cam.fx == pytest.approx(897.0)
    np.testing.assert_array_equal(cam.D, WIDE_ANGLE_D)
