"""CameraInfo and TF decoding, the tf tree from a log, and camera models against OpenCV."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import DecodeError, TransformError
from fleetcal.pipeline.transforms import from_xyz_rpy, rotation_error_deg, translation_error_m
from fleetcal.readers.decode import decode_camera_info, decode_tf, rectification_rotation, stereo_baseline_m
from fleetcal.readers.frames import CameraInfoTracker, is_rectified_topic, iter_camera_frames
from fleetcal.readers.open import open_log
from fleetcal.workflows.pairing import iter_pairs
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.log_writer import LogWriter
from fleetcal.workflows.sinks.ros_messages import Profile

K = np.array([[600.0, 0.0, 320.5], [0.0, 580.0, 240.25], [0.0, 0.0, 1.0]])
MODELS = {
    "plumb_bob": np.array([-0.28, 0.07, 0.001, -0.0005, -0.008]),
    "rational_polynomial": np.array([0.4, -0.1, 0.001, 0.0005, 0.01, 0.8, -0.05, 0.02]),
    "equidistant": np.array([0.05, -0.01, 0.002, -0.0004]),
    "cylindrical": np.zeros(0),
    "none": np.zeros(0),
}


def _roundtrip(msg: Any, msgtype: str, profile: Profile) -> Any:
    store = rm.get_store(profile)
    if profile == "ros1":
        return store.deserialize_ros1(bytes(store.serialize_ros1(msg, msgtype)), msgtype)
    return store.deserialize_cdr(bytes(store.serialize_cdr(msg, msgtype)), msgtype)


@pytest.mark.parametrize("profile", ["ros2", "ros1"])
@pytest.mark.parametrize("model", list(MODELS))
def test_camera_info_roundtrip(model: str, profile: Profile) -> None:
    camera = CameraModel(640, 480, K, MODELS[model], model)
    msg = _roundtrip(rm.camera_info(5, "cam", camera, profile), "sensor_msgs/msg/CameraInfo", profile)
    assert hasattr(msg, "K" if profile == "ros1" else "k")
    back = decode_camera_info(msg)
    assert (back.width, back.height) == (640, 480)
    np.testing.assert_array_equal(back.K, K)
    if model == "none":
        assert back.distortion_model == "plumb_bob" and not np.any(back.D)
    else:
        assert back.distortion_model == model
        np.testing.assert_array_equal(back.D, MODELS[model])


def test_bad_camera_info_raises() -> None:
    msg = rm.camera_info(5, "cam", CameraModel(640, 480, K, MODELS["plumb_bob"]))
    with pytest.raises(DecodeError, match="all zero"):
        decode_camera_info(dataclasses.replace(msg, k=np.zeros(9)))
    with pytest.raises(DecodeError, match="not finite"):
        decode_camera_info(dataclasses.replace(msg, k=np.full(9, np.nan)))
    with pytest.raises(DecodeError, match="distortion model 'kb8'"):
        decode_camera_info(dataclasses.replace(msg, distortion_model="kb8"))
    with pytest.raises(DecodeError, match="size 0x480"):
        decode_camera_info(dataclasses.replace(msg, width=0))
    assert decode_camera_info(dataclasses.replace(msg, distortion_model="")).distortion_model == "none"
    assert (
        decode_camera_info(dataclasses.replace(msg, distortion_model="fisheye")).distortion_model
        == "equidistant"
    )


@pytest.mark.parametrize("profile", ["ros2", "ros1"])
def test_tf_roundtrip_strips_slashes(profile: Profile) -> None:
    T1 = from_xyz_rpy(1.0, -2.0, 0.5, 10.0, -20.0, 170.0)
    T2 = from_xyz_rpy(0.0, 0.1, 0.2, -90.0, 0.0, -90.0)
    msg = rm.tf_message([(123, "/odom", "/base_link", T1), (456, "base_link", "cam", T2)], profile)
    out = decode_tf(_roundtrip(msg, "tf2_msgs/msg/TFMessage", profile))
    assert [(s, p, c) for s, p, c, _ in out] == [(123, "odom", "base_link"), (456, "base_link", "cam")]
    np.testing.assert_allclose(out[0][3], T1, atol=1e-12)
    np.testing.assert_allclose(out[1][3], T2, atol=1e-12)


def _scaled_quaternion(msg: Any, scale: float) -> Any:
    q = msg.transforms[0].transform.rotation
    for axis in "xyzw":
        setattr(q, axis, getattr(q, axis) * scale)
    return msg


def test_tf_quaternion_checks() -> None:
    T = from_xyz_rpy(0.3, 0.2, 0.1, 5.0, 6.0, 7.0)
    out = decode_tf(_scaled_quaternion(rm.tf_message([(1, "a", "b", T)]), 1.05))
    assert rotation_error_deg(out[0][3], T) < 1e-9 and translation_error_m(out[0][3], T) < 1e-12
    with pytest.raises(TransformError, match="norm 2"):
        decode_tf(_scaled_quaternion(rm.tf_message([(1, "a", "b", T)]), 2.0))
    with pytest.raises(TransformError, match="norm 0"):
        decode_tf(_scaled_quaternion(rm.tf_message([(1, "a", "b", T)]), 0.0))
    nan = rm.tf_message([(1, "a", "b", T)])
    nan.transforms[0].transform.translation.x = float("nan")
    with pytest.raises(TransformError, match="NaN"):
        decode_tf(nan)


def test_load_tf_tree_skips_bad_entries(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from fleetcal.readers.frames import load_tf_tree
    from fleetcal.readers.open import open_log
    T_base_lidar = from_xyz_rpy(0.5, 0.0, 1.8, 0.0, 0.0, 3.0)
    T_base_cam = from_xyz_rpy(1.0, 0.2, 1.5, -90.0, 0.0, -90.0)
    bad = rm.tf_message([(0, "base", "broken", np.eye(4))])
    bad.transforms[0].transform.rotation.w = 5.0
    with LogWriter(tmp_path / "tf.mcap", "mcap") as writer:
        static = rm.tf_message([(0, "/base", "lidar", T_base_lidar), (0, "base", "cam", T_base_cam)])
        writer.write("/tf_static", "tf2_msgs/msg/TFMessage", 0, static)
        for i in range(3):
            T_odom_base = from_xyz_rpy(float(i), 0.0, 0.0, 0.0, 0.0, 0.0)
            writer.write(
                "/tf",
                "tf2_msgs/msg/TFMessage",
                i * 10**9,
                rm.tf_message([(i * 10**9, "odom", "base", T_odom_base)]),
            )
        writer.write("/tf", "tf2_msgs/msg/TFMessage", 5 * 10**9, bad)
    with open_log(tmp_path / "tf.mcap") as reader, caplog.at_level(logging.WARNING):
        tree = load_tf_tree(reader)
    assert "skipped 1 bad tf entries" in caplog.text
    assert sorted(tree.edges()) == [("base", "cam", True), ("base", "lidar", True), ("odom", "base", False)]
    T_cam_lidar = tree.lookup("cam", "lidar")
    np.testing.assert_allclose(T_cam_lidar, np.linalg.inv(T_base_cam) @ T_base_lidar, atol=1e-12)
    T_odom_lidar = tree.lookup("odom", "lidar", stamp_ns=1_500_000_000)
    np.testing.assert_allclose(T_odom_lidar[:3, 3], [2.0, 0.0, 1.8], atol=1e-12)


def _grid_points(camera: CameraModel, max_angle_deg: float) -> np.ndarray:
    """Optical-frame points (N, 3) on rays up to ``max_angle_deg`` off the axis, depths 1..20 m."""
    rng = np.random.default_rng(0)
    theta = np.radians(rng.uniform(0, max_angle_deg, 400))
    phi = rng.uniform(-np.pi, np.pi, 400)
    rays = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    return rays * rng.uniform(1, 20, (400, 1))


@pytest.mark.parametrize("model", ["plumb_bob", "rational_polynomial"])
def test_pinhole_projection_matches_opencv(model: str) -> None:
    camera = CameraModel(640, 480, K, MODELS[model], model)
    pts = _grid_points(camera, 30.0)
    uv, valid = camera.project(pts)
    assert valid.mean() > 0.5
    cv_uv, _ = cv2.projectPoints(
        pts, np.zeros(3), np.zeros(3), K, camera.coefficients(8 if model != "plumb_bob" else 5)
    )
    np.testing.assert_allclose(uv[valid], cv_uv.reshape(-1, 2)[valid], atol=1e-6)


def test_equidistant_projection_matches_opencv_fisheye() -> None:
    camera = CameraModel(640, 480, K, MODELS["equidistant"], "equidistant")
    pts = _grid_points(camera, 60.0)
    uv, valid = camera.project(pts)
    assert valid.mean() > 0.3
    cv_uv, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, camera.D)
    np.testing.assert_allclose(uv[valid], cv_uv.reshape(-1, 2)[valid], atol=1e-6)


@pytest.mark.parametrize("model", list(MODELS))
def test_project_unproject_roundtrip(model: str) -> None:
    K_model = K.copy()
    if model == "cylindrical":
        K_model[0, 0] = 640 / (2 * np.pi) * 1.5
    camera = CameraModel(640, 480, K_model, MODELS[model], model)
    pts = _grid_points(camera, 35.0)
    uv, valid = camera.project(pts)
    assert valid.sum() > 100
    rays = camera.unproject(uv[valid])
    dirs = pts[valid] / np.linalg.norm(pts[valid], axis=1, keepdims=True)
    rays_unit = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(dirs * rays_unit, axis=1), -1, 1)))
    assert float(angle.max()) < 1e-4
    uv_again, valid_again = camera.project(rays * 7.0)
    assert valid_again.all()
    np.testing.assert_allclose(uv_again, uv[valid], atol=1e-6)


@pytest.mark.parametrize(
    "log", ["kitti_2011_09_26.mcap", "nuscenes_n015.bag", "pjlab_road_rig1", "pjlab_road_rig2"]
)
def test_real_logs_camera_info_and_tf(shared_data: Path, log: str) -> None:
    from fleetcal.readers.frames import camera_info_topic_for, load_tf_tree
    from fleetcal.readers.open import open_log

    truth = json.loads((shared_data / "logs" / (log.split(".")[0] + ".truth.json")).read_text())
    with open_log(shared_data / "logs" / log) as reader:
        tree = load_tf_tree(reader)
        for pair in truth["pairs"]:
            info_topic = camera_info_topic_for(pair["camera_topic"], reader.topics)
            assert info_topic is not None
            raw = next(iter(reader.messages(topics=[info_topic])))
            camera = decode_camera_info(reader.deserialize(raw))
            assert camera.fx > 300 and 0 < camera.cx < camera.width and 0 < camera.cy < camera.height
            assert camera.distortion_model in ("plumb_bob", "rational_polynomial", "equidistant", "none")
            T_log = tree.lookup(pair["camera_frame"], truth["lidar_frame"], stamp_ns=None)
            T_expected = np.array(pair["T_camera_lidar_in_log"])
            if tree.is_static_path(pair["camera_frame"], truth["lidar_frame"]):
                np.testing.assert_allclose(T_log, T_expected, atol=1e-6)


def _info_with_new_camera_matrix(profile: Profile = "ros2") -> tuple[Any, NDArray[np.float64]]:
    """CameraInfo of a distorted 640x480 camera whose P holds the new camera matrix of its rectified
    images (OpenCV, alpha 0: only valid pixels), as camera_calibration writes it."""
    D = MODELS["plumb_bob"]
    K_rect, _ = cv2.getOptimalNewCameraMatrix(K, D, (640, 480), 0.0)
    msg = rm.camera_info(5, "cam", CameraModel(640, 480, K, D, "plumb_bob"), profile)
    P = np.zeros((3, 4))
    P[:, :3] = K_rect
    return dataclasses.replace(msg, **{("P" if profile == "ros1" else "p"): P.reshape(-1)}), K_rect


@pytest.mark.parametrize("stereo", [False, True])
@pytest.mark.parametrize("profile", ["ros2", "ros1"])
def test_rectified_images_project_like_opencv_rectification(profile: Profile, stereo: bool) -> None:
    """A point's pixel in the rectified image (the raw pixel undistorted by OpenCV's ``undistortPoints(uv,
    K, D, R, P)``) is where the rectified model projects the point, given in the camera's own frame, to
    1e-3 px; the raw model would be off by pixels. ``stereo``: R is a 1.9 deg rotation, which the model
    applies (without it about 18 px off), keeps when written back, and undoes in ``unproject``."""
    msg, K_rect = _info_with_new_camera_matrix(profile)
    R = Rotation.from_euler("xyz", [0.8, -1.7, 0.4], degrees=True).as_matrix() if stereo else np.eye(3)
    msg = dataclasses.replace(msg, **{("R" if profile == "ros1" else "r"): R.reshape(-1)})
    msg = _roundtrip(msg, "sensor_msgs/msg/CameraInfo", profile)
    raw = decode_camera_info(msg)
    rect = decode_camera_info(msg, rectified=True)
    assert rect.distortion_model == "none" and rect.D.size == 0
    np.testing.assert_allclose(rect.K, K_rect)
    assert raw.R_rect is None and (rect.R_rect is not None) == stereo
    rng = np.random.default_rng(0)
    depth = rng.uniform(4, 20, 200)
    points = np.column_stack([depth * rng.uniform(-0.4, 0.4, 200), depth * rng.uniform(-0.3, 0.3, 200), depth])
    uv_raw, ok_raw = raw.project(points)
    uv_rect, ok_rect = rect.project(points)
    assert ok_raw.all() and ok_rect.all()
    uv_cv = cv2.undistortPoints(uv_raw.reshape(-1, 1, 2), K, raw.D, R=R, P=K_rect).reshape(-1, 2)
    np.testing.assert_allclose(uv_rect, uv_cv, atol=1e-3)
    assert np.max(np.linalg.norm(uv_raw - uv_cv, axis=1)) > 5.0
    rays = rect.unproject(uv_rect)  # back into the camera's frame
    np.testing.assert_allclose(rays / rays[:, 2:], points / points[:, 2:], atol=1e-9)
    if stereo:
        assert rect.R_rect is not None
        np.testing.assert_allclose(rect.R_rect, R, atol=1e-12)
        uv_no_r, _ = rect.without_rectification().project(points)
        assert np.median(np.linalg.norm(uv_no_r - uv_cv, axis=1)) > 10.0
        again = decode_camera_info(rm.camera_info(5, "cam", rect, profile), rectified=True)  # written back
        assert again.R_rect is not None
        np.testing.assert_allclose(again.R_rect, R, atol=1e-12)


def test_rectified_camera_info_without_P_keeps_K_and_reports_its_rotation() -> None:
    msg = rm.camera_info(5, "cam", CameraModel(640, 480, K, MODELS["plumb_bob"], "plumb_bob"))
    no_p = decode_camera_info(dataclasses.replace(msg, p=np.zeros(12)), rectified=True)
    np.testing.assert_array_equal(no_p.K, K)
    assert no_p.distortion_model == "none"
    assert rectification_rotation(msg) == 0.0
    assert rectification_rotation(dataclasses.replace(msg, r=np.zeros(9))) == 0.0  # unset
    R = Rotation.from_euler("y", 3.0, degrees=True).as_matrix()
    assert rectification_rotation(dataclasses.replace(msg, r=R.reshape(-1))) == pytest.approx(3.0)


def test_rectified_topic_names() -> None:
    for topic in ("/cam/image_rect", "/cam/image_rect_color", "/cam/image_rect_color/compressed",
                  "/camera/depth/image_rect_raw", "/cam/rect/image", "/stereo/left/image_rectified"):
        assert is_rectified_topic(topic), topic
    for topic in ("/cam/image_raw", "/cam/image/compressed", "/direct/image", "/rectangle_cam/image_raw",
                  "/cam/image_color"):
        assert not is_rectified_topic(topic), topic


def test_rectified_and_raw_topics_of_one_camera_get_their_own_models(tmp_path: Path) -> None:
    """``/cam/image_raw`` and ``/cam/image_rect_color`` share ``/cam/camera_info``: the raw images get K and
    the distortion, the rectified ones P's intrinsics and none."""
    msg, K_rect = _info_with_new_camera_matrix()
    path = tmp_path / "rect.mcap"
    img = np.zeros((480, 640), np.uint8)
    with LogWriter(path, "mcap") as writer:
        writer.write("/cam/camera_info", "sensor_msgs/msg/CameraInfo", 1, msg)
        for topic in ("/cam/image_raw", "/cam/image_rect_color"):
            writer.write(topic, "sensor_msgs/msg/Image", 2, rm.image(2, "cam", img, "mono8"))
    with open_log(path) as reader:
        raw = next(iter_camera_frames(reader, "/cam/image_raw")).camera
        rect = next(iter_camera_frames(reader, "/cam/image_rect_color")).camera
    assert raw is not None and rect is not None
    assert raw.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(raw.K, K)
    assert rect.distortion_model == "none"
    np.testing.assert_allclose(rect.K, K_rect)


def test_a_rectified_topic_named_otherwise_is_rectified_when_listed(tmp_path: Path) -> None:
    """``/cam/image_color`` carries rectified images under a name that does not say so: listed in
    ``io.rectified_topics`` it gets P's intrinsics and no distortion, through the
    pairing the calibrate workflow uses; unlisted, K and the distortion."""
    msg, K_rect = _info_with_new_camera_matrix()
    path = tmp_path / "color.mcap"
    points = np.array([[5.0, 0.0, 0.0], [6.0, 1.0, 0.5], [7.0, -1.0, 0.2]], np.float32)
    with LogWriter(path, "mcap") as writer:
        writer.write("/cam/camera_info", "sensor_msgs/msg/CameraInfo", 1, msg)
        writer.write("/lidar", "sensor_msgs/msg/PointCloud2", 2, rm.pointcloud2(2, "lidar", points))
        writer.write("/cam/image_color", "sensor_msgs/msg/Image", 2,
                     rm.image(2, "cam", np.zeros((480, 640), np.uint8), "mono8"))
    with open_log(path) as reader:
        listed = CameraInfoTracker.for_image(reader, "/cam/image_color", ["/cam/image_color"]).model
        unlisted = CameraInfoTracker.for_image(reader, "/cam/image_color", ["/other/image"]).model
        [(_, paired)] = list(iter_pairs(reader, "/lidar", "/cam/image_color", rectified_topics=["/cam/image_color"]))
    assert listed is not None and unlisted is not None and paired.camera is not None
    assert listed.distortion_model == paired.camera.distortion_model == "none"
    np.testing.assert_allclose(listed.K, K_rect)
    np.testing.assert_allclose(paired.camera.K, K_rect)
    assert unlisted.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(unlisted.K, K)


def test_rectification_R_that_is_not_a_rotation_is_a_decode_error() -> None:
    msg, _ = _info_with_new_camera_matrix()
    bad = dataclasses.replace(msg, r=(2.0 * np.eye(3)).reshape(-1))
    with pytest.raises(DecodeError, match="not a rotation"):
        decode_camera_info(bad, rectified=True)
    assert decode_camera_info(bad).R_rect is None  # the raw images do not use R


def test_stereo_rectification_rotation_is_told_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    msg, _ = _info_with_new_camera_matrix()
    R = Rotation.from_euler("y", 1.5, degrees=True).as_matrix()
    msg = dataclasses.replace(msg, r=R.reshape(-1))
    path = tmp_path / "stereo.mcap"
    with LogWriter(path, "mcap") as writer:
        for t in (1, 3):
            writer.write("/cam/camera_info", "sensor_msgs/msg/CameraInfo", t, msg)
            writer.write("/cam/image_rect", "sensor_msgs/msg/Image", t + 1,
                         rm.image(t + 1, "cam", np.zeros((480, 640), np.uint8), "mono8"))
    with open_log(path) as reader, caplog.at_level(logging.INFO):
        frames = list(iter_camera_frames(reader, "/cam/image_rect"))
    assert len(frames) == 2
    assert all(f.camera is not None and f.camera.R_rect is not None for f in frames)
    told = [r.getMessage() for r in caplog.records if "rectification rotation" in r.getMessage()]
    assert len(told) == 1 and "1.50 deg" in told[0]
    assert not any("baseline" in r.getMessage() for r in caplog.records)  # a left camera: P[0, 3] = 0


def test_stereo_right_camera_baseline_is_warned_once_and_not_applied(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    msg, K_rect = _info_with_new_camera_matrix()
    P = np.zeros((3, 4))
    P[:, :3] = K_rect
    P[0, 3] = -K_rect[0, 0] * 0.12  # right camera, 12 cm baseline
    msg = dataclasses.replace(msg, p=P.reshape(-1))
    assert stereo_baseline_m(msg) == pytest.approx(0.12)
    path = tmp_path / "right.mcap"
    with LogWriter(path, "mcap") as writer:
        for t in (1, 3, 5):
            writer.write("/right/camera_info", "sensor_msgs/msg/CameraInfo", t, msg)
            writer.write("/right/image_rect", "sensor_msgs/msg/Image", t + 1,
                         rm.image(t + 1, "right_optical", np.zeros((480, 640), np.uint8), "mono8"))
    with open_log(path) as reader, caplog.at_level(logging.WARNING):
        frames = list(iter_camera_frames(reader, "/right/image_rect"))
    warned = [r.getMessage() for r in caplog.records if "baseline" in r.getMessage()]
    assert len(frames) == 3 and len(warned) == 1 and "0.120 m" in warned[0]
    points = np.array([[0.5, -0.2, 8.0]])
    uv, _ = frames[0].camera.project(points)  # the baseline column is not in the projection
    np.testing.assert_allclose(uv[0], K_rect[:2, :2] @ (points[0, :2] / 8.0) + K_rect[:2, 2], atol=1e-9)
