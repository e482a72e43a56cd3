"""Lidar gradient estimates on the sphere: the least-squares fit against Algorithm 1 on an anisotropic
scan grid, and gradients taken at the lidar and carried into a displaced camera's view."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ProcessingError
from fleetcal.pipeline.transforms import apply, from_xyz_rpy
from fleetcal.stages.calibration.sphere_gradients import (
    LidarGradients,
    camera_sphere_neighbours,
    compute_sphere_gradients,
    cross_ring_neighbours,
    lidar_view_gradients,
    ring_spacing_rad,
    sampling_aspect,
    sphere_coordinates,
)


def _doubled_angle_error_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """|a - b| modulo 180 degrees (gradient orientations have no sign in GOM), degrees."""
    return np.abs(np.degrees(np.angle(np.exp(2j * (a - b))) / 2.0))


def _scan_grid(ring_step_deg: float, column_step_deg: float, range_m: float) -> NDArray[np.float64]:
    """Points of a spinning lidar (rings further apart than columns) on a sphere of ``range_m``, in
    an optical frame (z forward, y down), within +-15 deg of the forward axis."""
    az = np.radians(np.arange(-15.0, 15.0, column_step_deg))
    polar = np.radians(90.0 + np.arange(-10.0, 10.0, ring_step_deg))
    A, P = np.meshgrid(az, polar)
    A, P = A.ravel(), P.ravel()
    return range_m * np.column_stack([np.sin(P) * np.sin(A), -np.cos(P), np.sin(P) * np.cos(A)])


def test_least_squares_fit_is_unbiased_where_algorithm_1_leans_towards_the_rings() -> None:
    pts = _scan_grid(ring_step_deg=0.4, column_step_deg=0.1, range_m=10.0)
    uv = sphere_coordinates(pts)
    true_orientation = np.radians(30.0)  # a linear feature ramp, gradient 30 deg from image u
    values = np.cos(true_orientation) * uv[:, 0] + np.sin(true_orientation) * uv[:, 1]
    inner = (np.abs(np.degrees(uv[:, 0])) < 12) & (np.abs(np.degrees(uv[:, 1]) - 90) < 8)
    lsq = compute_sphere_gradients(pts, values, np.eye(4), k=8, fit="lsq")
    paper = compute_sphere_gradients(pts, values, np.eye(4), k=8, fit="paper")
    lsq_err = _doubled_angle_error_deg(lsq.orientation[inner], np.full(inner.sum(), true_orientation))
    paper_err = _doubled_angle_error_deg(paper.orientation[inner], np.full(inner.sum(), true_orientation))
    assert np.median(lsq_err) < 0.5, f"least squares off by {np.median(lsq_err):.2f} deg"
    assert np.median(paper_err) > 5.0, f"Algorithm 1 off by only {np.median(paper_err):.2f} deg"
    np.testing.assert_allclose(lsq.magnitude, paper.magnitude)  # the weight is the paper's


def test_least_squares_fit_on_one_ring_keeps_the_observed_component() -> None:
    az = np.radians(np.arange(-10.0, 10.0, 0.2))
    pts = 10.0 * np.column_stack([np.sin(az), np.zeros_like(az), np.cos(az)])  # one ring
    values = np.degrees(az) * 0.1
    g = compute_sphere_gradients(pts, values, np.eye(4), k=4, fit="lsq")
    inner = slice(5, -5)
    assert np.all(np.isfinite(g.gx)) and np.all(np.isfinite(g.gy))
    assert np.all(np.abs(g.gy[inner]) < 1e-3 * np.abs(g.gx[inner]))
    np.testing.assert_allclose(g.gx[inner], np.degrees(1.0) * 0.1, rtol=0.02)


def test_camera_at_the_lidar_sees_the_lidar_orientations() -> None:
    rng = np.random.default_rng(0)
    pts = _scan_grid(0.4, 0.2, 12.0) * (1 + 0.3 * rng.random((1, 1)))
    values = rng.random(pts.shape[0])
    T = from_xyz_rpy(0, 0, 0, 3.0, -2.0, 1.0)
    carried = lidar_view_gradients(pts, pts, values, T, k=8, fit="lsq")
    direct = compute_sphere_gradients(pts, values, T, k=8, fit="lsq")
    moving = np.hypot(direct.gx, direct.gy) > 1e-9
    err = _doubled_angle_error_deg(carried.orientation[moving], direct.orientation[moving])
    assert np.percentile(err, 99) < 0.5


def test_edge_direction_follows_the_parallax_of_a_displaced_camera() -> None:
    """A painted line on the ground, 4-12 m ahead: its image direction depends on where the camera
    is. Gradients carried from the lidar must be perpendicular to the line as the camera sees it."""
    x = np.arange(-3.0, 3.0, 0.03)
    z = np.arange(4.0, 12.0, 0.06)
    X, Z = np.meshgrid(x, z)
    ground = np.column_stack([X.ravel(), np.full(X.size, 1.6), Z.ravel()])  # 1.6 m below the lidar
    direction = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)  # the line x = z - 7 on the ground
    side = ground[:, 0] - (ground[:, 2] - 7.0)
    values = (side > 0).astype(np.float64)
    T_camera_lidar = from_xyz_rpy(0.8, -0.9, 0.3, 0.0, 0.0, 0.0)  # camera 0.9 m above, 0.8 m aside
    carried = lidar_view_gradients(ground, ground, values, T_camera_lidar, k=16, fit="lsq")
    at_lidar = compute_sphere_gradients(ground, values, np.eye(4), k=16, fit="lsq")
    edge = (carried.magnitude > 0.2) & (np.abs(ground[:, 2] - 7.0) < 2.5)
    assert edge.sum() > 50
    # expected: the line's direction on the camera's sphere, from two points along it
    p = ground[edge]
    a = sphere_coordinates(apply(T_camera_lidar, p))
    b = sphere_coordinates(apply(T_camera_lidar, p + 0.01 * direction))
    line = np.arctan2(b[:, 1] - a[:, 1], b[:, 0] - a[:, 0])
    expected = line + np.pi / 2
    err_carried = _doubled_angle_error_deg(carried.orientation[edge], expected)
    err_lidar_only = _doubled_angle_error_deg(at_lidar.orientation[edge], expected)
    # the step-edge fit itself scatters by ~2.6 deg (median, camera at the lidar); carrying adds nothing
    assert np.median(err_carried) < 2.5, f"carried gradients off by {np.median(err_carried):.2f} deg"
    # orientations left as the lidar sees them are off by the parallax
    assert np.median(err_lidar_only) > 3 * np.median(err_carried), np.median(err_lidar_only)


def test_sampling_aspect_is_column_over_ring_spacing() -> None:
    sparse = sphere_coordinates(_scan_grid(ring_step_deg=1.33, column_step_deg=0.33, range_m=10.0))
    assert sampling_aspect(sparse) == pytest.approx(0.33 / 1.33, rel=0.05)
    square = sphere_coordinates(_scan_grid(ring_step_deg=0.3, column_step_deg=0.3, range_m=10.0))
    assert sampling_aspect(square) == pytest.approx(1.0, abs=0.02)
    dense_rings = sphere_coordinates(_scan_grid(ring_step_deg=0.42, column_step_deg=0.7, range_m=10.0))
    assert sampling_aspect(dense_rings) == 1.0  # rings denser than columns: left alone


def test_sampling_neighbours_see_an_edge_between_sparse_rings() -> None:
    """A 32-beam-like scan (rings 1.33 deg, columns 0.33 deg apart) with a horizontal feature edge:
    the 8 nearest neighbours by angle all lie on the point's own ring, so the edge's vertical gradient
    is invisible; neighbours by sampling reach the rings above and below and find it."""
    pts = _scan_grid(ring_step_deg=1.33, column_step_deg=0.33, range_m=10.0)
    uv = sphere_coordinates(pts)
    values = (uv[:, 1] > np.radians(90.0) + 1e-9).astype(np.float64)  # lower half bright
    by_angle = compute_sphere_gradients(pts, values, np.eye(4), k=8, fit="lsq")
    by_sampling = compute_sphere_gradients(pts, values, np.eye(4), k=8, fit="lsq", neighbours_by="sampling")
    near_edge = np.abs(uv[:, 1] - np.radians(90.0)) < np.radians(1.5)
    inner = near_edge & (np.abs(np.degrees(uv[:, 0])) < 12)
    assert np.all(by_angle.magnitude[inner] == 0)  # own ring only: no change of value seen
    assert np.all(by_sampling.magnitude[inner] > 0)
    vertical = _doubled_angle_error_deg(by_sampling.orientation[inner], np.full(inner.sum(), np.pi / 2))
    assert np.median(vertical) < 1.0, f"edge gradient {np.median(vertical):.2f} deg off vertical"


def _spinning_scan(ring_step_deg: float, rings: int, columns: int) -> NDArray[np.float64]:
    """A full turn of a spinning lidar (lidar frame, z up): ``rings`` rings ``ring_step_deg`` apart about
    the horizon, ``columns`` columns, ranges 6-14 m varying with azimuth."""
    elevation = np.radians((np.arange(rings) - (rings - 1) / 2) * ring_step_deg)
    azimuth = np.radians(np.arange(columns) * 360.0 / columns)
    E, A = np.meshgrid(elevation, azimuth)
    r = 10.0 + 4.0 * np.sin(3 * A)
    return np.column_stack([(r * np.cos(E) * np.cos(A)).ravel(), (r * np.cos(E) * np.sin(A)).ravel(),
                            (r * np.sin(E)).ravel()])


def test_ring_spacing_is_measured_on_the_lidars_own_sphere() -> None:
    """VLP-16-like (16 rings 2 deg apart, 1800 columns), HDL-32-like (1.33 deg, 1080) and 64-beam-like
    (0.4 deg, 2000) scans give their ring spacing, whatever the range."""
    for step, rings, columns in [(2.0, 16, 1800), (1.33, 32, 1080), (0.4, 64, 2000)]:
        scan = _spinning_scan(step, rings, columns)
        assert np.degrees(ring_spacing_rad(scan)) == pytest.approx(step, rel=0.02)
    assert np.isnan(ring_spacing_rad(np.zeros((5, 3))))  # too few points to tell


def test_cross_ring_neighbours_separate_sparse_from_dense_rings() -> None:
    sparse = sphere_coordinates(_scan_grid(ring_step_deg=1.33, column_step_deg=0.33, range_m=10.0))
    dense = sphere_coordinates(_scan_grid(ring_step_deg=0.4, column_step_deg=0.17, range_m=10.0))
    assert cross_ring_neighbours(sparse, 8) < 2  # the camera sphere cannot see horizontal edges
    assert cross_ring_neighbours(dense, 8) >= 2


@pytest.mark.parametrize("view", ["camera", "lidar"])
def test_second_channel_reuses_the_first_channels_neighbours(view: str) -> None:
    """Feature channels of one frame share one sphere search: a second channel's gradients from the
    first channel's neighbours equal those from its own search, on both viewpoints."""
    pts = _scan_grid(ring_step_deg=1.33, column_step_deg=0.33, range_m=10.0)
    pts = pts * (1.0 + 0.2 * np.sin(np.arange(pts.shape[0]) * 0.37))[:, None]  # ranges 8-12 m
    rng = np.random.default_rng(3)
    first, second = rng.random(pts.shape[0]), rng.random(pts.shape[0])
    T = from_xyz_rpy(0.1, -0.2, 0.05, 1.0, -0.5, 1.5)

    def grads(values: NDArray[np.float64], neighbours: NDArray[np.int64] | None = None) -> LidarGradients:
        if view == "camera":
            return compute_sphere_gradients(pts, values, T, k=8, neighbours_by="sampling", neighbours=neighbours)
        return lidar_view_gradients(pts, pts, values, T, k=8, neighbours_by="sampling", neighbours=neighbours)

    shared = grads(second, grads(first).neighbours)
    own = grads(second)
    np.testing.assert_array_equal(shared.neighbours, own.neighbours)
    np.testing.assert_allclose(np.column_stack([shared.gx, shared.gy, shared.magnitude]),
                               np.column_stack([own.gx, own.gy, own.magnitude]), rtol=0, atol=1e-12)
    if view == "camera":
        np.testing.assert_array_equal(camera_sphere_neighbours(pts, T, 8, "sampling"), own.neighbours)
    with pytest.raises(ProcessingError, match="do not match"):
        compute_sphere_gradients(pts, second, T, k=8, neighbours=own.neighbours[:, :4])


def test_algorithm_1_matches_its_numpy_reference() -> None:
    """The paper's fit (``fit="paper"``): g = sum_j dv_j dx_j / K and weight sum_j |dv_j| / K over the K sphere
    neighbours, dx the angle step (radians) from neighbour to point."""
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(400, 3)) + np.array([0.0, 0.0, 8.0])
    values = rng.uniform(size=400)
    got = compute_sphere_gradients(pts, values, np.eye(4), k=6, fit="paper")
    uv = sphere_coordinates(pts)
    d_uv = uv[:, None, :] - uv[got.neighbours]
    d_v = values[:, None] - values[got.neighbours]
    np.testing.assert_allclose(got.gx, (d_v * d_uv[..., 0]).mean(axis=1), atol=1e-12)
    np.testing.assert_allclose(got.gy, (d_v * d_uv[..., 1]).mean(axis=1), atol=1e-12)
    np.testing.assert_allclose(got.magnitude, np.abs(d_v).mean(axis=1), atol=1e-12)
