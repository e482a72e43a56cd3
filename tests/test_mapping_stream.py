"""The pieces that make mapping stream and reuse work: merged keyframes, the queued voxel map, the
prefetching scan source, and the odometry on the first scans of a real drive (KITTI 00)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.transforms import from_xyz_rpy, invert, translation_error_m
from fleetcal.stages.registration import RegistrationConfig, VoxelMap, prepare_pointset, register
from fleetcal.stages.registration.pointset import merge_pointsets, transformed_pointset
from fleetcal.workflows.mapping import map_frames, prefetched
from tests.test_registration import room_scene


def test_transformed_pointset_rotates_covariances_and_registers_back() -> None:
    rng = np.random.default_rng(30)
    config = RegistrationConfig(voxel_size_m=0.1)
    scan = prepare_pointset(room_scene(rng), None, config)
    T = from_xyz_rpy(0.3, -0.2, 0.1, 2.0, -1.0, 15.0)
    moved = transformed_pointset(scan, T)
    R = T[:3, :3]
    np.testing.assert_allclose(moved.points_xyz, scan.points_xyz @ R.T + T[:3, 3], atol=1e-12)
    np.testing.assert_allclose(moved.covariances[7], R @ scan.covariances[7] @ R.T, atol=1e-12)
    result = register(scan, moved, np.eye(4), config)  # moved = T applied to scan
    assert translation_error_m(result.T_target_source, T) < 1e-3


def test_merge_pointsets_averages_points_descriptors_and_covariances_per_voxel() -> None:
    rng = np.random.default_rng(31)
    config = RegistrationConfig(method="mcgicp", channels="intensity", voxel_size_m=0.2)
    world = room_scene(rng, 6000)
    scans = [prepare_pointset(world + rng.normal(0, 0.01, world.shape), {"intensity": world[:, 0] + 5.0}, config)
             for _ in range(2)]  # fmt: skip
    merged = merge_pointsets(scans, config)
    # NumPy reference: group the concatenated rows by voxel and average them
    points = np.concatenate([s.points_xyz for s in scans])
    rows = np.concatenate([np.concatenate([s.points_xyz, s.channels, s.covariances.reshape(-1, 9)], 1) for s in scans])
    _, inverse = np.unique(np.floor(points / 0.2).astype(np.int64), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    reference = np.stack([rows[inverse == v].mean(axis=0) for v in range(inverse.max() + 1)])
    reference = reference[np.lexsort(reference[:, 2::-1].T)]
    got = np.concatenate([merged.points_xyz, merged.channels, merged.covariances.reshape(-1, 9)], 1)
    got = got[np.lexsort(got[:, 2::-1].T)]
    np.testing.assert_allclose(got, reference, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(merged.covariances) > 0)
    np.testing.assert_allclose(merged.channel_variance, [merged.channels[:, 0].var()])
    assert merged.frame_id == "map" and merged.channel_names == ("intensity",)


def test_voxel_map_queued_inserts_equal_one_pass_reference() -> None:
    rng = np.random.default_rng(32)
    voxel_map = VoxelMap(0.5)
    scans = [rng.uniform(-5, 5, (int(rng.integers(50, 400)), 3)) for _ in range(40)]
    for points in scans:
        voxel_map.insert(points, {"intensity": points[:, 0] * 2.0})
    every = np.concatenate(scans)
    keys, inverse = np.unique(np.floor(every / 0.5).astype(np.int64), axis=0, return_inverse=True)
    inverse = inverse.ravel()
    means = np.stack([every[inverse == v].mean(axis=0) for v in range(keys.shape[0])])
    got = voxel_map.points()
    assert voxel_map.n_voxels == keys.shape[0]
    np.testing.assert_allclose(got[np.lexsort(got.T[::-1])], means[np.lexsort(means.T[::-1])], atol=1e-12)
    intensity = np.asarray(voxel_map.channels()["intensity"], dtype=np.float64)
    np.testing.assert_allclose(intensity, 2.0 * got[:, 0], rtol=1e-6)


def test_prefetched_keeps_order_raises_producer_errors_and_stops_early() -> None:
    assert list(prefetched(iter(range(50)))) == list(range(50))

    def failing() -> object:
        yield 1
        raise ValueError("bad scan")

    stream = prefetched(failing())
    assert next(stream) == 1
    with pytest.raises(ValueError, match="bad scan"):
        next(stream)
    produced: list[int] = []

    def endless() -> object:
        for i in range(10**9):
            produced.append(i)
            yield i

    before = threading.active_count()
    stream = prefetched(endless(), depth=2)
    assert next(stream) == 0
    stream.close()  # the consumer stops: the producer stops within its put timeout
    time.sleep(0.5)
    assert threading.active_count() == before and len(produced) < 10


def test_first_scans_of_a_real_drive_follow_the_reference(shared_data: Path) -> None:
    """KITTI odometry 00, first 8 scans (~6 m): the streamed, prefetched mapping path stays within
    3 cm of the reference per scan, as accurate as the whole-drive benchmark (docs/performance.md)."""
    from fleetcal.readers.frames import iter_lidar_frames
    from fleetcal.readers.open import open_log

    log = shared_data / "logs" / "kitti_odometry_00_scans_50-100.mcap"
    truth = json.loads(log.with_suffix(".truth.json").read_text())
    with open_log(log) as reader:
        frames = [f for _, f in zip(range(8), iter_lidar_frames(reader, truth["lidar_topic"]), strict=False)]
    poses = np.array(truth["lidar_poses"][:8])
    steps, voxel_map, used_tf = map_frames(iter(frames), Config())
    assert len(steps) == 8 and not used_tf and voxel_map.n_voxels > 0
    for step, T_world_lidar in zip(steps, poses, strict=True):
        assert translation_error_m(step.T_map_lidar, invert(poses[0]) @ T_world_lidar) < 0.03
        assert step.converged
    assert not any(step.degenerate for step in steps[1:])  # a street fixes every direction of the motion
