"""Simulator geometric truth against ``CameraModel.project``, the log's CameraInfo and its ``/tf``.

Pixel convention: ``CameraModel`` pixel (u, v) is the centre of pixel (u, v). A rendered edge must sit where
``project`` puts the 3D edge (sub-pixel, measured with the slanted-edge method), the log must carry the
intrinsics used for rendering, images and scans must be rendered from the poses at their header stamps
(an image: at its stamp minus the camera's clock offset, row by row under a rolling shutter), and the ``/tf``
odometry must give exactly the simulator's ego-motion between those stamps.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import map_coordinates
from scipy.optimize import curve_fit
from scipy.special import erfc

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.transforms import apply, invert, rotation_error_deg, translation_error_m
from fleetcal.readers.frames import iter_camera_frames, load_tf_tree
from fleetcal.readers.open import open_log
from fleetcal.workflows.simulator.camera import SimCamera, pinhole_camera, render, render_depth, row_times_s
from fleetcal.workflows.simulator.lidar import LidarModel, simulate_scan
from fleetcal.workflows.simulator.motion import LoopMotion
from fleetcal.workflows.simulator.raycast import TriangleGrid, build_grid
from fleetcal.workflows.simulator.scene import RouteSpec, Scene, SceneBuilder, build_scene
from fleetcal.workflows.simulator.truth import ODOM_FRAME, build_rig, camera_topics, load_truth, truth_path_for
from fleetcal.workflows.simulator.write import START_NS, SimulationOptions, _event_times, simulate_log

PLANE_Z_M = 6.0
SLANT = np.tan(np.radians(4.0))


# ---------------------------------------------------------------- 1. pixel convention: slanted edges
def _edge_scene(vertical: bool, edge_m: float) -> tuple[Scene, TriangleGrid, np.ndarray, np.ndarray]:
    """Plane z = PLANE_Z_M (camera frame = world frame) painted white / black on either side of a line
    slanted 4 deg from vertical (``vertical``) or horizontal through (edge_m, 0) or (0, edge_m).

    Returns (scene, grid, a, d): the edge is the 3D line ``a + s d``."""
    b = SceneBuilder(np.random.default_rng(0))
    L = 40.0
    if vertical:
        a, d = np.array([edge_m, 0.0, PLANE_Z_M]), np.array([SLANT, 1.0, 0.0])
        start = a - d * L / 2
        b.quad(start - [L, 0, 0], [L, 0, 0], d * L, "paint_white")
        b.quad(start, [L, 0, 0], d * L, "tile_black")
    else:
        a, d = np.array([0.0, edge_m, PLANE_Z_M]), np.array([1.0, SLANT, 0.0])
        start = a - d * L / 2
        b.quad(start - [0, L, 0], d * L, [0, L, 0], "paint_white")
        b.quad(start, d * L, [0, L, 0], "tile_black")
    scene = b.build("edge", 0, RouteSpec(10.0, 10.0, 1.0), 1.9)
    return scene, build_grid(scene.triangles), a, d


def _esf(delta: np.ndarray, low: float, high: float, centre: float, sigma: float) -> np.ndarray:
    """Edge spread function: ``high`` for delta << centre, ``low`` for delta >> centre (Gaussian blur)."""
    return low + (high - low) * 0.5 * erfc((delta - centre) / (np.sqrt(2.0) * sigma))


def rendered_edge_offset_px(model: CameraModel, vertical: bool, render_model: CameraModel | None = None) -> float:
    """Sub-pixel offset (px) of the rendered white/black edge from ``model.project`` of the 3D edge,
    positive = rendered edge to the right (vertical edge) or below (horizontal edge). Slanted-edge method:
    every pixel near the edge gives one ESF sample at its signed distance from the projected edge; many
    sub-pixel phases make the fitted centre exact despite one ray per pixel."""
    scene, grid, a, d = _edge_scene(vertical, edge_m=0.37)
    cam = SimCamera(render_model or model, blur_sigma_px=0.7, noise_dn=0.0)
    img = render(scene, grid, cam, np.eye(4), np.random.default_rng(0)).astype(np.float64)[..., 1]
    s = np.linspace(-12.0, 12.0, 24001)
    uv_edge, ok = model.project(a[None] + s[:, None] * d[None])
    uv_edge = uv_edge[ok]
    v, u = np.mgrid[0 : model.height, 0 : model.width].astype(np.float64)
    if vertical:  # horizontal distance to the edge curve u_edge(v)
        delta = u - np.interp(v, uv_edge[:, 1], uv_edge[:, 0])
    else:
        delta = v - np.interp(u, uv_edge[:, 0], uv_edge[:, 1])
    margin = 6
    inner = np.zeros(img.shape, dtype=bool)
    inner[margin:-margin, margin:-margin] = True
    near = inner & (np.abs(delta) < 5.0)
    popt, _ = curve_fit(_esf, delta[near], img[near], p0=(img.min(), img.max(), 0.0, 0.8))
    assert popt[1] - popt[0] > 100, "edge contrast missing: scene not in view"
    assert 0.5 < popt[3] < 1.2, f"edge width {popt[3]:.2f} px is not the 0.7 px blur"
    return float(popt[2])


@pytest.mark.parametrize("vertical", [True, False])
def test_rendered_edge_lies_where_camera_model_projects_it(vertical: bool) -> None:
    model = pinhole_camera(320, 240)  # plumb_bob distortion, off-centre principal point
    assert abs(rendered_edge_offset_px(model, vertical)) < 0.05


def test_edge_offset_measurement_detects_a_half_pixel_convention_error() -> None:
    """The check above can fail: rays cast through pixel corners (principal point off by 0.5 px)."""
    model = pinhole_camera(320, 240)
    K = model.K.copy()
    K[0, 2] -= 0.5  # rendering with cx - 0.5 shifts the image content 0.5 px left
    shifted = CameraModel(model.width, model.height, K, model.D, model.distortion_model)
    offset = rendered_edge_offset_px(model, True, render_model=shifted)
    assert offset == pytest.approx(-0.5, abs=0.05)


# ---------------------------------------------------------------- 2./3. log intrinsics, stamps, tf motion
@pytest.fixture(scope="module")
def corner_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, SimulationOptions]:
    """20 frames at 20 m/s round the open scene's first corner (yaw rate 2.5 rad/s), two cameras."""
    opts = SimulationOptions(
        frames=20, scene="open", speed_m_s=20.0, cameras=2, beams=16, columns=256, width=96, height=64, seed=5
    )
    result = simulate_log(tmp_path_factory.mktemp("geom") / "corner.mcap", opts)
    return Path(result.log_path), load_truth(result.truth_path), opts


def test_log_camera_info_is_the_rendering_model_and_images_are_rendered_at_their_stamps(corner_log) -> None:
    path, truth, opts = corner_log
    scene = build_scene(opts.scene, opts.seed)
    grid = build_grid(scene.triangles)
    motion = LoopMotion(scene.route, opts.speed)
    rig = build_rig(opts.cameras, scene.lidar_height_m, opts.perturb_deg, opts.perturb_m, opts.seed)
    _, image_stamps, _ = _event_times(opts)
    model = pinhole_camera(opts.width, opts.height)
    reader = open_log(path)
    for index in range(opts.cameras):
        frames = list(iter_camera_frames(reader, truth["pairs"][index]["camera_topic"]))
        assert [f.stamp_ns for f in frames] == image_stamps[index]
        for sub in (0, len(frames) // 2):
            frame = frames[sub]
            assert frame.camera is not None
            assert frame.camera.distortion_model == model.distortion_model
            np.testing.assert_array_equal(frame.camera.K, model.K)
            np.testing.assert_array_equal(frame.camera.D, model.D)
            t_s = (frame.stamp_ns - START_NS) / 1e9
            T_world_camera = motion.T_world_base(t_s) @ rig.T_base_cameras[index]
            rng = np.random.default_rng(np.random.SeedSequence([opts.seed, 0xC0, index, sub]))
            cam = SimCamera(model, spectral_mix=min(0.15 * index, 0.6))
            exposure = 1.0 + 0.05 * np.sin(0.7 * t_s + index)
            expected = render(scene, grid, cam, T_world_camera, rng, exposure_scale=exposure)
            np.testing.assert_array_equal(frame.image, expected)
            # 5 ms earlier (10 cm at 20 m/s) is a visibly different image
            early = motion.T_world_base(t_s - 0.005) @ rig.T_base_cameras[index]
            rng = np.random.default_rng(np.random.SeedSequence([opts.seed, 0xC0, index, sub]))
            other = render(scene, grid, cam, early, rng, exposure_scale=exposure)
            assert np.mean(np.abs(other.astype(int) - expected.astype(int))) > 1.0


def test_tf_ego_motion_between_scan_and_camera_stamps_is_exact(corner_log) -> None:
    """T_lidar(camera stamp)_lidar(scan stamp) from the log's /tf equals the simulator's motion model
    (< 1 um, < 1e-6 deg) on the straight and in the corner; the truth trajectory matches /tf too."""
    path, truth, opts = corner_log
    scene = build_scene(opts.scene, opts.seed)
    motion = LoopMotion(scene.route, opts.speed)
    rig = build_rig(opts.cameras, scene.lidar_height_m, opts.perturb_deg, opts.perturb_m, opts.seed)
    scans, image_stamps, _ = _event_times(opts)
    tree = load_tf_tree(open_log(path))
    T_world_odom = motion.T_world_base(0.0)

    def T_world_lidar(stamp_ns: int) -> np.ndarray:
        return motion.T_world_base((stamp_ns - START_NS) / 1e9) @ rig.T_base_lidar

    turned = []
    for index in range(opts.cameras):
        for scan_ns, cam_ns in zip(scans, image_stamps[index], strict=False):
            T_log = invert(tree.lookup(ODOM_FRAME, "lidar", cam_ns)) @ tree.lookup(ODOM_FRAME, "lidar", scan_ns)
            T_sim = invert(T_world_lidar(cam_ns)) @ T_world_lidar(scan_ns)
            assert translation_error_m(T_log, T_sim) < 1e-6
            assert rotation_error_deg(T_log, T_sim) < 1e-6
            turned.append(rotation_error_deg(T_sim, np.eye(4)))
            # the camera pose in the log (odom tf + true rig) is the rendering pose
            T_odom_cam = tree.lookup(ODOM_FRAME, "lidar", cam_ns) @ invert(truth["pairs"][index]["T_camera_lidar"])
            T_render = invert(T_world_odom) @ motion.T_world_base((cam_ns - START_NS) / 1e9) @ rig.T_base_cameras[index]
            assert translation_error_m(T_odom_cam, T_render) < 1e-6
    assert max(turned) > 1.0, "the log should include the corner (ego rotation between the stamps)"
    T_odom_lidar0 = tree.lookup(ODOM_FRAME, "lidar", scans[0])
    for entry in truth["trajectory"]:
        T_map_lidar = invert(T_odom_lidar0) @ tree.lookup(ODOM_FRAME, "lidar", entry["stamp_ns"])
        assert translation_error_m(T_map_lidar, entry["T_map_lidar"]) < 1e-6


# ---------------------------------------------------------------- camera clock offset and rolling shutter
CLOCK_OPTS = SimulationOptions(
    frames=3, scene="open", speed_m_s=20.0, cameras=2, beams=16, columns=256, width=96, height=64, seed=7
)


@pytest.fixture(scope="module")
def clock_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[float, float], Path]:
    """The same 20 m/s drive with (time offset ms, readout ms) = (0, 0), (30, 0) and (30, 20)."""
    folder = tmp_path_factory.mktemp("clocks")
    logs = {}
    for offset_ms, readout_ms in ((0.0, 0.0), (30.0, 0.0), (30.0, 20.0)):
        opts = replace(CLOCK_OPTS, time_offset_ms=offset_ms, readout_ms=readout_ms)
        result = simulate_log(folder / f"clock_{offset_ms:g}_{readout_ms:g}.mcap", opts)
        logs[offset_ms, readout_ms] = Path(result.log_path)
    return logs


def _expected_image(opts: SimulationOptions, index: int, sub: int, T_world_camera: np.ndarray, exposed_s: float):
    """The simulator's image ``sub`` of camera ``index`` rendered from ``T_world_camera`` (its seeded noise,
    its auto-exposure at lidar time ``exposed_s``)."""
    scene = build_scene(opts.scene, opts.seed)
    rng = np.random.default_rng(np.random.SeedSequence([opts.seed, 0xC0, index, sub]))
    cam = SimCamera(pinhole_camera(opts.width, opts.height), spectral_mix=min(0.15 * index, 0.6))
    exposure = 1.0 + 0.05 * np.sin(0.7 * exposed_s + index)
    return render(scene, build_grid(scene.triangles), cam, T_world_camera, rng, exposure_scale=exposure)


def test_camera_clock_offset_shows_the_scene_at_stamp_minus_offset(clock_logs) -> None:
    """30 ms offset, global shutter: the image stamped t is, bit for bit, the global-shutter image taken at lidar
    time t - 30 ms (60 cm earlier at 20 m/s), which differs visibly from the one taken at t."""
    opts = replace(CLOCK_OPTS, time_offset_ms=30.0)
    scene = build_scene(opts.scene, opts.seed)
    motion = LoopMotion(scene.route, opts.speed)
    rig = build_rig(opts.cameras, scene.lidar_height_m, opts.perturb_deg, opts.perturb_m, opts.seed)
    _, image_stamps, _ = _event_times(opts)
    with open_log(clock_logs[30.0, 0.0]) as reader:
        for index in range(opts.cameras):
            frames = list(iter_camera_frames(reader, camera_topics(index, False)[0]))
            assert [f.stamp_ns for f in frames] == image_stamps[index]
            for sub, frame in enumerate(frames):
                exposed_s = (frame.stamp_ns - START_NS) / 1e9 - 0.03
                T_world_camera = motion.T_world_base(exposed_s) @ rig.T_base_cameras[index]
                expected = _expected_image(opts, index, sub, T_world_camera, exposed_s)
                np.testing.assert_array_equal(frame.image, expected)
                at_stamp = motion.T_world_base(exposed_s + 0.03) @ rig.T_base_cameras[index]
                other = _expected_image(opts, index, sub, at_stamp, exposed_s)
                assert np.mean(np.abs(other.astype(int) - expected.astype(int))) > 1.0


def test_rolling_shutter_log_images_are_cast_row_by_row_from_the_offset_time(clock_logs) -> None:
    """30 ms offset and 20 ms readout: each image is the render from one pose per row, row r at lidar time
    t - 30 ms + 20 ms * r / (H - 1), and differs from the global-shutter image of the same log."""
    opts = replace(CLOCK_OPTS, time_offset_ms=30.0, readout_ms=20.0)
    scene = build_scene(opts.scene, opts.seed)
    motion = LoopMotion(scene.route, opts.speed)
    rig = build_rig(opts.cameras, scene.lidar_height_m, opts.perturb_deg, opts.perturb_m, opts.seed)
    with open_log(clock_logs[30.0, 20.0]) as rolling, open_log(clock_logs[30.0, 0.0]) as glob:
        for index in range(opts.cameras):
            topic = camera_topics(index, False)[0]
            pairs = zip(iter_camera_frames(rolling, topic), iter_camera_frames(glob, topic), strict=True)
            for sub, (frame, global_frame) in enumerate(pairs):
                exposed_s = (frame.stamp_ns - START_NS) / 1e9 - 0.03
                times = row_times_s(exposed_s, 0.02, opts.height)
                per_row = motion.T_world_base_many(times) @ rig.T_base_cameras[index]
                np.testing.assert_array_equal(frame.image, _expected_image(opts, index, sub, per_row, exposed_s))
                assert np.mean(np.abs(frame.image.astype(int) - global_frame.image.astype(int))) > 1.0


def test_camera_clocks_change_only_the_images(clock_logs) -> None:
    """Stamps, /tf odometry (lidar time), /tf_static, camera infos and scans are byte-identical with or without
    a clock offset and rolling shutter; the images differ; the truth file records each camera's clock."""
    images = {camera_topics(i, False)[0] for i in range(CLOCK_OPTS.cameras)}

    def messages(path: Path) -> list[tuple[str, int, bytes]]:
        with open_log(path) as reader:
            return [(m.topic, m.log_time_ns, bytes(m.data)) for m in reader.messages()]

    base = messages(clock_logs[0.0, 0.0])
    for key in ((30.0, 0.0), (30.0, 20.0)):
        other = messages(clock_logs[key])
        assert [m[:2] for m in other] == [m[:2] for m in base]
        assert [m for m in other if m[0] not in images] == [m for m in base if m[0] not in images]
        assert all(a[2] != b[2] for a, b in zip(other, base, strict=True) if a[0] in images)
        truth = load_truth(truth_path_for(clock_logs[key]))
        assert [(p["time_offset_s"], p["readout_s"]) for p in truth["pairs"]] == [(key[0] / 1e3, key[1] / 1e3)] * 2


# ---------------------------------------------------------------- 4. lidar + truth extrinsic + motion = depth
def test_moving_lidar_points_with_truth_extrinsic_and_motion_hit_rendered_depth() -> None:
    """Noise-free street scan taken in a corner at 20 m/s, moved 20 ms on to the camera stamp (the ego-motion
    the log's /tf gives, see above) and into the camera with the true T_camera_lidar, lands on the depth
    rendered at the camera stamp (median < 1 mm); without the ego-motion, or with a 0.5 deg turn about the
    optical axis, it does not."""
    scene = build_scene("street", 5)
    grid = build_grid(scene.triangles)
    motion = LoopMotion(scene.route, 20.0)
    rig = build_rig(1, scene.lidar_height_m, 2.0, 0.1, 5)
    scan_s, cam_s = 2.3, 2.32  # on the first corner's arc
    T_world_lidar_scan = motion.T_world_base(scan_s) @ rig.T_base_lidar
    T_world_lidar_cam = motion.T_world_base(cam_s) @ rig.T_base_lidar
    assert rotation_error_deg(T_world_lidar_scan, T_world_lidar_cam) > 2.0
    lidar = LidarModel(beams=64, columns=1024, range_noise_m=0.0, dropout=0.0, seed=5)
    scan = simulate_scan(scene, grid, lidar, T_world_lidar_scan, np.random.default_rng(0))
    points = scan.points_xyz[scan.valid].astype(np.float64)
    cam = SimCamera(pinhole_camera(640, 360))
    depth = render_depth(grid, cam, motion.T_world_base(cam_s) @ rig.T_base_cameras[0])
    T_motion = invert(T_world_lidar_cam) @ T_world_lidar_scan
    T_true = rig.T_camera_lidar[0]

    def agree(T_camera_scan: np.ndarray) -> tuple[float, float]:
        """(median |depth residual| m, fraction of points within 1 cm of the rendered depth)."""
        p = apply(T_camera_scan, points)
        uv, ok = cam.model.project(p)
        d = map_coordinates(depth, [uv[ok, 1], uv[ok, 0]], order=1, mode="nearest")
        r = np.abs(d - p[ok, 2])
        return float(np.nanmedian(r)), float(np.nanmean(r < 0.01))

    median, frac = agree(T_true @ T_motion)
    assert median < 0.001 and frac > 0.9
    assert agree(T_true)[1] < frac - 0.1
    c, s = np.cos(np.radians(0.5)), np.sin(np.radians(0.5))
    roll = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    assert agree(roll @ T_true @ T_motion)[1] < frac - 0.3
