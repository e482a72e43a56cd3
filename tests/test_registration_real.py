"""Registration on real scans from ../shared/data/logs (skipped when the data is absent).

- ``outdoor_scan_pair.mcap``: two real lidar scans and a reference T_target_source (small_gicp's own
  GICP result at 0.1 m / k=10; fast_gicp differs from it by 0.23 deg / 1.9 cm).
- ``rgbd_fragment.mcap``: a real coloured RGB-D fragment registered against a copy of itself moved
  by a known transform, both halves independently subsampled and noised.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.frames import LidarFrame
from fleetcal.pipeline.transforms import apply, from_xyz_rpy, invert, make_T, rotation_error_deg, translation_error_m
from fleetcal.stages.registration import RegistrationConfig, pointset_from_frame, prepare_pointset, register


def load_lidar_frames(path: Path, topic: str) -> list[LidarFrame]:
    """All LidarFrames of ``topic`` (via ``frames.iter_lidar_frames``)."""
    from fleetcal.readers.open import open_log

    reader = open_log(path)
    try:
        try:
            from fleetcal.readers.frames import iter_lidar_frames
        except ImportError:
            from fleetcal.readers.decode import decode_pointcloud2

            return [
                decode_pointcloud2(reader.deserialize(raw), raw.topic, raw.log_time_ns)
                for raw in reader.messages([topic])
            ]
        return list(iter_lidar_frames(reader, topic))
    finally:
        reader.close()


def perturbation(seed: int, translation_m: float, rotation_deg: float) -> NDArray[np.float64]:
    """A transform moving by exactly ``translation_m`` and rotating by ``rotation_deg`` (random axes)."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    rotvec = axis / np.linalg.norm(axis) * np.radians(rotation_deg)
    return make_T(
        Rotation.from_rotvec(rotvec).as_matrix(), direction / np.linalg.norm(direction) * translation_m
    )


@pytest.fixture(scope="module")
def outdoor(shared_data: Path) -> tuple[LidarFrame, LidarFrame, NDArray[np.float64]]:
    log = shared_data / "logs" / "outdoor_scan_pair.mcap"
    if not log.exists():
        pytest.skip(f"{log} not present")
    truth = json.loads(log.with_suffix(".truth.json").read_text())
    frames = load_lidar_frames(log, truth["lidar_topic"])
    reg = truth["registration"]
    return frames[reg["target_index"]], frames[reg["source_index"]], np.array(reg["T_target_source"])


OUTDOOR_STARTS = {
    "identity": None,
    "perturbed_a": perturbation(1, 0.5, 5.0),
    "perturbed_b": perturbation(2, 0.5, 5.0),
}


@pytest.mark.parametrize("start", list(OUTDOOR_STARTS))
@pytest.mark.parametrize(("method", "channels"), [("gicp", "none"), ("mcgicp", "intensity")])
def test_outdoor_pair_matches_reference(
    outdoor: tuple[LidarFrame, LidarFrame, NDArray[np.float64]], method: str, channels: str, start: str
) -> None:
    """Within 3 cm / 0.3 deg of the reference from identity and from 0.5 m / 5 deg perturbed starts.

    0.25 m voxels, k = 20, Cauchy kernel (scale 1): without a robust kernel the far (up to 1 m)
    correspondences tilt the roll by 0.67 deg at these settings (see the report).
    """
    target_frame, source_frame, T_ref = outdoor
    config = RegistrationConfig(method=method, channels=channels, voxel_size_m=0.25, robust_kernel="cauchy")
    target = pointset_from_frame(target_frame, config)
    source = pointset_from_frame(source_frame, config)
    delta = OUTDOOR_STARTS[start]
    T_init = np.eye(4) if delta is None else T_ref @ delta
    result = register(source, target, T_init, config)
    assert result.converged
    assert result.fitness > 0.9
    assert not result.degenerate
    assert translation_error_m(result.T_target_source, T_ref) < 0.03
    assert rotation_error_deg(result.T_target_source, T_ref) < 0.3


@pytest.fixture(scope="module")
def rgbd_pair(shared_data: Path) -> tuple[tuple, tuple, NDArray[np.float64]]:
    """(target points, colours), (source points, colours), T_target_source (9.8 cm, 4.7 deg)."""
    log = shared_data / "logs" / "rgbd_fragment.mcap"
    if not log.exists():
        pytest.skip(f"{log} not present")
    truth = json.loads(log.with_suffix(".truth.json").read_text())
    frame = load_lidar_frames(log, truth["lidar_topic"])[0]
    assert {"r", "g", "b"} <= set(frame.channels)
    rng = np.random.default_rng(0)
    pts = frame.points_xyz.astype(np.float64)
    T_true = from_xyz_rpy(0.06, -0.05, 0.06, 2.0, -3.0, 3.0)
    in_target = rng.random(len(pts)) < 0.5
    in_source = rng.random(len(pts)) < 0.5
    target_pts = pts[in_target] + rng.normal(0, 0.005, (in_target.sum(), 3))
    source_pts = apply(invert(T_true), pts[in_source]) + rng.normal(0, 0.005, (in_source.sum(), 3))
    target_rgb = {c: frame.channels[c][in_target] for c in "rgb"}
    source_rgb = {c: frame.channels[c][in_source] for c in "rgb"}
    return (target_pts, target_rgb), (source_pts, source_rgb), T_true


@pytest.mark.parametrize(
    ("method", "channels", "max_t_m", "max_r_deg"),
    [
        ("mcgicp", "color", 0.01, 0.2),
        ("color_icp", "color", 0.02, 0.5),  # baseline, reported beside MC-GICP
        ("gicp", "none", 0.03, 1.0),  # baseline: geometry alone is weaker on this fragment
    ],
)
def test_rgbd_fragment_known_motion(
    rgbd_pair: tuple[tuple, tuple, NDArray[np.float64]],
    method: str,
    channels: str,
    max_t_m: float,
    max_r_deg: float,
) -> None:
    (target_pts, target_rgb), (source_pts, source_rgb), T_true = rgbd_pair
    config = RegistrationConfig(
        method=method, channels=channels, voxel_size_m=0.02, max_correspondence_distance_m=0.2
    )
    target = prepare_pointset(target_pts, target_rgb, config)
    source = prepare_pointset(source_pts, source_rgb, config)
    result = register(source, target, np.eye(4), config)
    t_err = translation_error_m(result.T_target_source, T_true)
    r_err = rotation_error_deg(result.T_target_source, T_true)
    print(f"rgbd {method}: {t_err * 1000:.1f} mm, {r_err:.3f} deg, {result.iterations} iterations")
    assert result.converged and result.fitness > 0.95
    assert t_err < max_t_m and r_err < max_r_deg
