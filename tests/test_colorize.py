"""Colour from calibrated cameras on synthetic scenes whose true colours are known analytically."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import apply, from_xyz_rpy, invert
from fleetcal.stages.colorize import colorize, colorize_frame, fill_unseen

W, H = 160, 120
K = np.array([[100.0, 0.0, 79.5], [0.0, 100.0, 59.5], [0.0, 0.0, 1.0]])
# camera looking along lidar +x (optical z = lidar x), 0.2 m to the side and 0.1 m below the lidar
T_LIDAR_CAMERA = from_xyz_rpy(0.0, 0.2, -0.1, -90.0, 0.0, -90.0)
T_CAMERA_LIDAR = invert(T_LIDAR_CAMERA)


def camera() -> CameraModel:
    return CameraModel(W, H, K, np.zeros(5), "plumb_bob")


def linear_image() -> NDArray[np.uint8]:
    """r = u, g = 2 v, b = 200 - u: linear in the pixel, so bilinear sampling is exact."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.stack([u, 2 * v, 200 - u], axis=-1).astype(np.uint8)


def expected_colour(points_lidar: NDArray[np.float64]) -> NDArray[np.float64]:
    p = apply(T_CAMERA_LIDAR, points_lidar)
    u = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]
    v = K[1, 1] * p[:, 1] / p[:, 2] + K[1, 2]
    u, v = np.clip(u, 0, W - 1), np.clip(v, 0, H - 1)
    return np.stack([u, 2 * v, 200 - u], axis=1)


def wall_points(rng: np.random.Generator, n: int, x_m: float = 5.0) -> NDArray[np.float64]:
    """Points on the plane x = x_m (lidar frame), spread wider than the camera's field of view."""
    return np.stack([np.full(n, x_m), rng.uniform(-6, 6, n), rng.uniform(-4, 4, n)], axis=1)


def test_colours_match_the_image_at_the_true_projection() -> None:
    rng = np.random.default_rng(1)
    pts = wall_points(rng, 5000)
    rgb, seen = colorize(pts, [(linear_image(), camera(), T_CAMERA_LIDAR)])
    assert rgb.dtype == np.uint8 and rgb.shape == (5000, 3)
    # the field of view is +-38.7 deg x +-31 deg: on the wall at 5 m about |y - 0.2| < 4 m, |z + 0.1| < 3 m
    inside = (np.abs(pts[:, 1] - 0.2) < 3.9) & (np.abs(pts[:, 2] + 0.1) < 2.9)
    outside = (np.abs(pts[:, 1] - 0.2) > 4.1) | (np.abs(pts[:, 2] + 0.1) > 3.1)
    assert np.all(seen[inside]) and not np.any(seen[outside])
    error = np.abs(rgb[seen].astype(np.float64) - expected_colour(pts[seen]))
    assert error.max() <= 1.0  # rounding to uint8 only
    assert np.all(rgb[~seen] == 0)


def test_points_behind_the_camera_and_non_finite_points_are_unseen() -> None:
    pts = np.array([[-5.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [5.0, 0.2, -0.1], [0.0, 0.2, -0.1]])
    rgb, seen = colorize(pts, [(linear_image(), camera(), T_CAMERA_LIDAR)])
    np.testing.assert_array_equal(seen, [False, False, True, False])
    np.testing.assert_allclose(rgb[2], [80, 119, 120], atol=1)  # the principal point


def test_occluded_points_are_rejected_by_the_z_buffer() -> None:
    rng = np.random.default_rng(2)
    wall = wall_points(rng, 20000)
    # a 1 m x 1 m board at 2 m in front of the camera, dense like a lidar sees it
    gy, gz = np.meshgrid(np.linspace(-0.3, 0.7, 40), np.linspace(-0.6, 0.4, 40))
    board = np.stack([np.full(gy.size, 2.0), gy.ravel(), gz.ravel()], axis=1)
    pts = np.concatenate([wall, board])
    image = linear_image()
    view = [(image, camera(), T_CAMERA_LIDAR)]
    # wall points whose line of sight from the camera crosses the board's interior
    p_cam = apply(T_CAMERA_LIDAR, wall)
    hit = p_cam * (2.0 / p_cam[:, 2:3])  # where the ray to the point crosses the board plane z_cam = 2
    board_cam = apply(T_CAMERA_LIDAR, board)
    lo, hi = board_cam[:, :2].min(axis=0) + 0.05, board_cam[:, :2].max(axis=0) - 0.05
    hidden = np.all((hit[:, :2] > lo) & (hit[:, :2] < hi), axis=1)
    assert hidden.sum() > 100
    _, seen = colorize(pts, view)
    assert not np.any(seen[: len(wall)][hidden])
    assert seen[len(wall) :].mean() > 0.99  # the board itself is seen
    # wall points projecting more than two z-buffer cells (8 px) from the board's silhouette stay seen
    uv_wall, in_image = camera().project(p_cam)
    uv_board, _ = camera().project(board_cam)
    near_board = np.all((uv_wall > uv_board.min(axis=0) - 8) & (uv_wall < uv_board.max(axis=0) + 8), axis=1)
    assert np.all(seen[: len(wall)][in_image & ~near_board])
    _, seen_no_check = colorize(pts, view, occlusion=False)
    assert np.all(seen_no_check[: len(wall)][hidden])


def test_each_point_takes_the_view_nearest_its_principal_point() -> None:
    rng = np.random.default_rng(3)
    pts = wall_points(rng, 4000)
    # a second camera on the same mount turned 30 deg to the left, seeing a uniform colour
    T_lidar_cam2 = from_xyz_rpy(0.0, 0.2, -0.1, 0.0, 0.0, 30.0) @ T_LIDAR_CAMERA
    uniform = np.full((H, W, 3), (10, 250, 30), dtype=np.uint8)
    views = [(linear_image(), camera(), T_CAMERA_LIDAR), (uniform, camera(), invert(T_lidar_cam2))]
    rgb, seen = colorize(pts, views)
    rays = pts - np.array([0.0, 0.2, -0.1])
    angle1 = np.degrees(np.arctan2(rays[:, 1], rays[:, 0]))
    from_second = seen & np.all(rgb == (10, 250, 30), axis=1)
    # left of the bisector (15 deg) the second camera is nearer its centre; right of it, the first
    assert np.all(from_second[seen & (angle1 > 17) & (np.abs(rays[:, 2]) < 0.5)])
    assert not np.any(from_second[seen & (angle1 < 13) & (np.abs(rays[:, 2]) < 0.5)])
    # points only the second camera sees are coloured too
    assert np.any(seen & (angle1 > 45))


def test_fill_unseen_uses_the_mean_of_seen_points_and_colorize_frame_adds_channels() -> None:
    rgb = np.array([[10, 20, 30], [30, 40, 50], [0, 0, 0]], dtype=np.uint8)
    seen = np.array([True, True, False])
    np.testing.assert_array_equal(fill_unseen(rgb, seen)[2], [20, 30, 40])
    np.testing.assert_array_equal(fill_unseen(rgb, np.zeros(3, bool))[0], [128, 128, 128])
    rng = np.random.default_rng(4)
    pts = wall_points(rng, 500).astype(np.float32)
    frame = LidarFrame(7, "/lidar", "lidar", pts, {"intensity": np.ones(500, np.float32)})
    out = colorize_frame(frame, [(linear_image(), camera(), T_CAMERA_LIDAR)])
    assert set(out.channels) == {"intensity", "r", "g", "b", "seen"}
    seen_out = out.channels["seen"].astype(bool)
    assert 0 < seen_out.sum() < 500 and out.stamp_ns == 7
    assert out.channels["r"].dtype == np.uint8
    mean_r = np.rint(out.channels["r"][seen_out].astype(np.float64).mean())
    assert np.all(np.abs(out.channels["r"][~seen_out].astype(np.float64) - mean_r) <= 1)


def test_bad_views_raise_input_error() -> None:
    pts = np.zeros((3, 3))
    with pytest.raises(InputError, match="camera model is 160x120"):
        colorize(pts, [(np.zeros((10, 10, 3), np.uint8), camera(), T_CAMERA_LIDAR)])
    with pytest.raises(InputError, match="rigid"):
        colorize(pts, [(linear_image(), camera(), np.ones((4, 4)))])
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        colorize(np.zeros((3, 2)), [])


def _stripes(x_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Wall colour by world x: red on [0, 0.5) m of every metre, blue on the rest."""
    red = np.mod(x_m, 1.0) < 0.5
    return np.where(red[:, None], [200.0, 0.0, 0.0], [0.0, 0.0, 200.0])


@pytest.mark.parametrize("sweep", [False, True])
def test_moving_rig_colours_points_at_the_image_stamp(sweep: bool) -> None:
    """A side camera (looking along lidar +y at a striped wall 6 m away) fires 40 ms after the scan stamp
    while the rig drives along the wall at 10 m/s: 0.4 m of motion, most of a 0.5 m stripe. With the points
    moved to the image's stamp by the /tf odometry (``ego_motion.points_at``), they take their own stripe's
    colour; left at the scan stamp, most (whole scan) or half (firing times over the sweep) take the
    neighbour's."""
    from fleetcal.pipeline.transforms import TransformTree
    from fleetcal.workflows.ego_motion import points_at

    speed, stamp_ns, camera_ns = 10.0, 1_700_000_000_000_000_000, 1_700_000_000_040_000_000
    tree = TransformTree()
    for t in np.arange(-0.2, 0.3, 0.01):
        tree.add("odom", "lidar", from_xyz_rpy(speed * t, 0, 0, 0, 0, 0), stamp_ns + round(t * 1e9), static=False)
    rng = np.random.default_rng(5)
    world = np.c_[rng.uniform(-3.5, 3.5, 4000), np.full(4000, 6.0), rng.uniform(-1.5, 1.5, 4000)]
    times = rng.uniform(0.0, 0.1, world.shape[0]) if sweep else np.zeros(world.shape[0])
    points = world - np.c_[speed * times, np.zeros_like(times), np.zeros_like(times)]  # firing-time frames
    frame = LidarFrame(stamp_ns, "/lidar", "lidar", points, channels={"time": times} if sweep else {})
    R_camera_lidar = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # optical z = lidar y
    T_camera_lidar = np.eye(4)
    T_camera_lidar[:3, :3] = R_camera_lidar
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    rays = R_camera_lidar.T @ np.stack([(u.ravel() - K[0, 2]) / K[0, 0], (v.ravel() - K[1, 2]) / K[1, 1],
                                         np.ones(u.size)])  # fmt: skip
    x_hit = speed * 0.04 + rays[0] * 6.0 / rays[1]  # the camera is 0.4 m along at its stamp
    image = _stripes(x_hit).reshape(H, W, 3).astype(np.uint8)
    truth = _stripes(world[:, 0])
    views = [(image, camera(), T_camera_lidar)]

    moved = points_at(tree, frame, camera_ns)
    assert moved is not None and points_at(None, frame, camera_ns) is None
    np.testing.assert_allclose(moved, world - [speed * 0.04, 0, 0], atol=1e-6)
    right = {}
    for name, per_view in (("at image stamp", [moved]), ("at scan stamp", None)):
        rgb, seen = colorize(points, views, points_per_view=per_view)
        assert seen.mean() > 0.95
        right[name] = float(np.mean(np.abs(rgb[seen].astype(float) - truth[seen]).max(axis=1) < 100))
    assert right["at image stamp"] > 0.97, right
    # left where they are, points sit 0.4 m (whole scan) or -0.6..0.4 m (by firing time) off their stripe
    assert right["at scan stamp"] < (0.6 if sweep else 0.3), right
