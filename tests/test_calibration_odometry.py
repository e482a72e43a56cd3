"""Ego-motion from fleetcal's own odometry: a log without ``/tf`` odometry (``fleetcal simulate
--no-odometry``) gets its scans moved to the camera stamps by the lidar's twist from a GICP of each chosen
scan with the scan next to it, about as the log's tf would move them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fleetcal.pipeline.config import Config
from fleetcal.readers.decode import decode_pointcloud2
from fleetcal.readers.frames import load_tf_tree
from fleetcal.readers.open import open_log
from fleetcal.stages.calibration.frame import CalibrationFrame, compensate_ego_motion
from fleetcal.workflows import mapping
from fleetcal.workflows.calibrate import collect_frames
from fleetcal.workflows.ego_motion import camera_twist
from fleetcal.workflows.process import ColorSource, colorize_scan
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

LIDAR, CAMERA = "/lidar/points", "/camera_0/image_raw"


def _frames(log: Path, motion_compensation: bool = True, point_times: bool = True) -> tuple[
        list[CalibrationFrame], str]:
    config = Config()
    config.calibration.frames = 3
    config.calibration.feature = "intensity"
    config.calibration.motion_compensation = motion_compensation
    config.calibration.point_times = point_times
    with open_log(log) as reader:
        collected = collect_frames(reader, LIDAR, CAMERA, config, load_tf_tree(reader))
    return collected.frames, collected.motion_source


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The same skewed street at 8 m/s (points cast at their firing times, images 10-30 ms after the scans),
    with and without /tf odometry."""
    folder = tmp_path_factory.mktemp("odometry")
    paths = []
    for odometry in (True, False):
        path = folder / f"street_{'tf' if odometry else 'raw'}.mcap"
        simulate_log(path, SimulationOptions(frames=8, beams=32, columns=1024, width=320, height=180, seed=4,
                                             deskew=False, odometry=odometry), quiet=True)
        paths.append(path)
    return paths[0], paths[1]


def test_a_log_without_tf_odometry_is_moved_by_fleetcals_odometry(logs: tuple[Path, Path]) -> None:
    with_tf, raw = logs
    by_tf, tf_source = _frames(with_tf)
    by_odometry, odometry_source = _frames(raw)
    unmoved, none_source = _frames(raw, motion_compensation=False)
    assert (tf_source, odometry_source, none_source) == ("tf", "odometry", "none")
    for tf_frame, odo_frame, raw_frame in zip(by_tf, by_odometry, unmoved, strict=True):
        assert tf_frame.twist_lidar is not None and odo_frame.twist_lidar is not None
        np.testing.assert_allclose(odo_frame.twist_lidar[:3], tf_frame.twist_lidar[:3], atol=0.3)  # m/s of ~8
        np.testing.assert_allclose(odo_frame.twist_lidar[3:], tf_frame.twist_lidar[3:], atol=0.02)  # rad/s
        np.testing.assert_array_equal(odo_frame.point_time_offsets_s, tf_frame.point_time_offsets_s)
        at_camera_tf = compensate_ego_motion(tf_frame.points_xyz, None, tf_frame.point_time_offsets_s,
                                             tf_frame.twist_lidar)
        at_camera_odo = compensate_ego_motion(odo_frame.points_xyz, None, odo_frame.point_time_offsets_s,
                                              odo_frame.twist_lidar)
        gap_m = np.linalg.norm(at_camera_odo - at_camera_tf, axis=1)
        moved_m = np.linalg.norm(at_camera_tf - raw_frame.points_xyz, axis=1)
        assert np.sqrt(np.mean(gap_m**2)) < 0.03 < 0.5 * np.sqrt(np.mean(moved_m**2)), (gap_m.mean(), moved_m.mean())


def test_scans_that_are_each_others_neighbour_share_one_registration(logs: tuple[Path, Path],
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """All 8 scans of the log chosen: the first two are each other's neighbour (the first scan's is the next
    one), so 7 registrations give the 8 twists, the first two equal."""
    _, raw = logs
    registered: list[tuple[int, int]] = []
    scan_twist = mapping.scan_twist

    def counted(early: mapping.PointSet, late: mapping.PointSet, config: object) -> object:
        registered.append((early.stamp_ns, late.stamp_ns))
        return scan_twist(early, late, config)  # type: ignore[arg-type]

    monkeypatch.setattr(mapping, "scan_twist", counted)
    config = Config()
    config.calibration.frames = 8
    config.calibration.feature = "intensity"
    with open_log(raw) as reader:
        frames = collect_frames(reader, LIDAR, CAMERA, config, load_tf_tree(reader)).frames
    assert len(frames) == 8 and len(registered) == len(set(registered)) == 7
    assert all(early < late for early, late in registered)
    assert frames[0].twist_lidar is not None and frames[1].twist_lidar is not None
    np.testing.assert_array_equal(frames[0].twist_lidar, frames[1].twist_lidar)


def test_the_odometry_path_moves_whole_scans_by_their_stamp_when_point_times_are_off(logs: tuple[Path, Path]) -> None:
    """``calibration.point_times = false`` (clouds de-skewed by their driver): every point of a scan gets the
    scan stamp's offset to the camera, as on the tf path."""
    _, raw = logs
    frames, source = _frames(raw, point_times=False)
    assert source == "odometry"
    for frame in frames:
        offsets = np.asarray(frame.point_time_offsets_s)
        assert offsets.min() == offsets.max() and -0.05 < offsets[0] < 0  # images 10-30 ms after the scan



def test_the_twist_about_a_camera_stamp_is_the_sweeps_on_a_steady_drive(logs: tuple[Path, Path]) -> None:
    """``ego_motion.camera_twist`` (what a clock offset or a rolling shutter moves points by) from the tf's
    odometry about each image's stamp: on a straight steady 8 m/s drive, the sweep's own twist; None without
    /tf odometry."""
    with_tf, raw = logs
    frames, _ = _frames(with_tf)
    for path, expected in ((with_tf, [f.twist_lidar for f in frames]), (raw, [None] * len(frames))):
        with open_log(path) as reader:
            tree = load_tf_tree(reader)
        for frame, twist in zip(frames, expected, strict=True):
            found = camera_twist(tree, "lidar", frame.stamp_ns)
            if twist is None:
                assert found is None
            else:
                assert found is not None
                np.testing.assert_allclose(found, twist, atol=1e-3)
                assert np.linalg.norm(found[:3]) == pytest.approx(8.0, rel=1e-3)


def test_process_colours_a_log_without_tf_odometry_as_the_tf_would(logs: tuple[Path, Path]) -> None:
    """``process`` colouring (``colorize_scan``) of a scan from the log without /tf odometry: the points are
    moved to the image's stamp by fleetcal's own odometry, so their colours are those the log with /tf gives,
    and not those of the points left where the scan saw them."""
    with_tf, raw = logs
    truth = json.loads(with_tf.with_name(with_tf.stem + ".truth.json").read_text())["pairs"][0]
    T_rows = tuple(map(tuple, np.asarray(truth["T_camera_lidar"]).tolist()))
    config = Config()

    def colours(path: Path, ego_motion: bool) -> np.ndarray:
        source = ColorSource((str(path),), ((CAMERA, T_rows),), config.io.pairing_tolerance_ns,
                             ego_motion=ego_motion, lidar_topic=LIDAR,
                             ego_registration=mapping.ego_motion_registration(config))
        with open_log(path) as reader:
            raw_scan = list(reader.messages(topics=[LIDAR]))[3]
            frame = decode_pointcloud2(reader.deserialize(raw_scan), LIDAR, raw_scan.log_time_ns)
        coloured = colorize_scan(frame, source)
        return np.column_stack([coloured.channel(c) for c in "rgb"])

    by_tf, by_odometry, unmoved = colours(with_tf, True), colours(raw, True), colours(raw, False)
    differs = lambda a, b: float(np.mean(np.abs(a - b).max(axis=1) > 30))  # noqa: E731
    assert differs(unmoved, by_tf) > 0.01  # 8 m/s over the 10-30 ms to the image: colours off at edges
    assert differs(by_odometry, by_tf) < 0.5 * differs(unmoved, by_tf), (differs(by_odometry, by_tf),
                                                                          differs(unmoved, by_tf))
