"""GOM calibration on the real logs in ../shared/data/logs against their ``.truth.json`` references.

Each test skips with a reason when the data is absent. ``load_real_frames`` is also used by
``benchmarks/bench_gom.py``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.errors import ProcessingError
from fleetcal.pipeline.transforms import invert, rotation_error_deg, translation_error_m
from fleetcal.readers.frames import load_tf_tree
from fleetcal.readers.open import open_log
from fleetcal.stages.calibration import CalibrationFrame, CalibrationResult, SolverConfig, calibrate
from fleetcal.stages.calibration.calibrator import resolve_auto_rules
from fleetcal.stages.calibration.frame import build_frame
from fleetcal.stages.calibration.problem import CalibrationProblem
from fleetcal.workflows.calibrate import solver_config
from fleetcal.workflows.pairing import iter_pairs
from tests.conftest import SHARED_DATA
from tests.test_calibration_synthetic import per_axis_errors, perturb

LOGS = SHARED_DATA / "logs"


@dataclass
class RealProblem:
    """Frames of a real log, the log's tf guess and the reference, for the first camera."""

    frames: list[CalibrationFrame]
    T_init: NDArray[np.float64]
    T_true: NDArray[np.float64]


def log_path(name: str) -> Path:
    path = LOGS / name
    if not path.exists():
        pytest.skip(f"real log {path} not present (../shared/data/logs next to the repository)")
    return path


DEFAULT_FEATURE = Config().calibration.feature


def load_real_frames(name: str, feature: str = DEFAULT_FEATURE, cameras: int = 1, ego_motion: bool = False,
                     max_frames: int | None = None, tolerance_ns: int = 100_000_000,
                     blur_sigma_px: float | None = None) -> RealProblem:
    """Paired frames of ``name`` for its first ``cameras`` camera topics (joint when > 1: camera k
    gets ``T_camera_k_camera0`` from the log's tf), with ego-motion from ``/tf`` when asked."""
    path = LOGS / name
    stem = name.removesuffix(".mcap").removesuffix(".bag")
    truth = json.loads((LOGS / f"{stem}.truth.json").read_text())
    lidar_topic, lidar_frame = truth["lidar_topic"], truth["lidar_frame"]
    pairs = truth["pairs"][:cameras]
    reader = open_log(path)
    try:
        tree = load_tf_tree(reader)
        cam0 = pairs[0]["camera_frame"]
        T_init = tree.lookup(cam0, lidar_frame)
        frames: list[CalibrationFrame] = []
        for pair in pairs:
            T_c_c0 = tree.lookup(pair["camera_frame"], cam0)
            paired = iter_pairs(reader, lidar_topic, pair["camera_topic"], tolerance_ns, max_frames)
            for lidar, camera in paired:
                motion = None
                if ego_motion:
                    T_odom_lidar_scan = tree.lookup("odom", lidar_frame, lidar.stamp_ns)
                    T_odom_lidar_cam = tree.lookup("odom", lidar_frame, camera.stamp_ns)
                    motion = invert(T_odom_lidar_cam) @ T_odom_lidar_scan
                frames.append(build_frame(lidar, camera, feature, blur_sigma_px, T_camera_camera0=T_c_c0,
                                          T_lidar_motion=motion))
    finally:
        close = getattr(reader, "close", None)
        if close is not None:
            close()
    return RealProblem(frames, T_init, np.asarray(pairs[0]["T_camera_lidar"], dtype=np.float64))


def assert_confirmed_or_ambiguous(result: CalibrationResult) -> None:
    """``recalibrated`` with another seeded run confirming the estimate, or ``suspect`` for one reason only:
    other seeded runs that end far off score as well over the image bands, so the per-axis deviations
    exceed 0.5 deg / 15 cm (two optima the scene does not tell apart; KITTI's two frames leave the yaw /
    sideways ridge of its far street so, from some starts: ``benchmarks/bench_starts.py``)."""
    if result.verdict == "recalibrated":
        assert result.agreeing_repeats >= 1
        return
    assert result.verdict == "suspect" and "uncertain" in result.verdict_reason, result.verdict_reason
    assert result.alike_runs >= 1


def errors(T: NDArray[np.float64], T_true: NDArray[np.float64]) -> tuple[float, float]:
    return rotation_error_deg(T, T_true), translation_error_m(T, T_true)


def test_kitti_log_tf_is_drifted_and_the_defaults_take_the_lidar_sphere() -> None:
    """The log's tf is the drifted calibration, and the workflow's defaults take the lidar's own sphere (the
    paper's camera sphere: 0.133 deg / 7.2 cm from this start, but 0.22-0.57 deg / 10-30 cm from five other
    starts as far off, where the lidar's gives 0.14-0.24 deg / 3-5 cm: ``benchmarks/bench_starts.py``). The
    calibration from it, 0.176 deg / 3.8 cm, is ``tests/test_workflows.py::test_calibrate_kitti_from_log_tf``."""
    log_path("kitti_2011_09_26.mcap")
    problem = load_real_frames("kitti_2011_09_26.mcap")
    assert len(problem.frames) == 2
    rot0, trans0 = errors(problem.T_init, problem.T_true)
    assert rot0 > 1.5 and trans0 > 0.1
    assert resolve_auto_rules(problem.frames, problem.T_init, solver_config(Config())).viewpoint == "lidar"


@pytest.mark.slow
def test_kitti_from_drifted_starts_stays_within_bounds() -> None:
    """A fleet's logs each drift their own way: from two random starts 2 deg / 12 cm off (seeds of
    ``bench_starts.py``, which runs five), defaults. Measured 0.14-0.19 deg / 3-5 cm; the camera sphere
    (``gradient_viewpoint = "camera"``) gave 0.35 / 14 and 0.57 / 24."""
    log_path("kitti_2011_09_26.mcap")
    problem = load_real_frames("kitti_2011_09_26.mcap")
    config = solver_config(Config())
    for seed in (1001, 1002):
        result = calibrate(problem.frames, perturb(problem.T_true, 2.0, 0.12, seed=seed), config)
        rot, trans = errors(result.T_camera_lidar, problem.T_true)
        assert rot <= 0.3 and trans <= 0.10, f"start {seed}: {rot:.3f} deg / {trans:.3f} m"


@pytest.mark.slow
def test_kitti_from_5deg_50cm_off_in_a_wide_box() -> None:
    """``--initial`` 5 deg / 0.5 m off on a random axis, ``--search-deg 10 --search-m 1``, defaults: lidar
    gradients on the lidar's own sphere (least squares, neighbours across rings) do not depend on the
    initial translation, and the swarm first explores on blurred image gradients (measured for this seed
    0.163 deg / 3.7 cm; 10 of 10 seeds within the bound, 0.07-0.19 deg / 3-6 cm, ``bench_gom.py --seeds
    10``; the paper's camera sphere: 0 of 10). Other seeded runs can land in other optima; the best is
    confirmed by at least one."""
    log_path("kitti_2011_09_26.mcap")
    problem = load_real_frames("kitti_2011_09_26.mcap")
    T_start = perturb(problem.T_true, 5.0, 0.5, seed=100)
    rot0, trans0 = errors(T_start, problem.T_true)
    assert rot0 == pytest.approx(5.0, abs=1e-3) and trans0 > 0.45
    cfg = replace(solver_config(Config()), search_deg=10.0, search_m=1.0, seed=0)
    assert (cfg.viewpoint, cfg.fit, cfg.neighbours_on("lidar")) == ("lidar", "lsq", "sampling")
    result = calibrate(problem.frames, T_start, cfg)
    rot, trans = errors(result.T_camera_lidar, problem.T_true)
    assert rot <= 0.3, f"rotation error {rot:.3f} deg"
    assert trans <= 0.10, f"translation error {trans:.3f} m"
    assert_confirmed_or_ambiguous(result)


def test_a_box_wide_in_rotation_only_explores_on_the_lidar_sphere() -> None:
    """A mount knocked 5 deg (10 cm) off, searched with ``--search-deg 10`` and the default 0.5 m: a box
    wide in rotation alone takes the lidar viewpoint and exploration too. From such a start on KITTI (seed
    204, search seed 4) the camera's sphere ended at 2.18 deg / 63 cm, ``suspect``; the lidar's measured
    0.078 deg / 5.0 cm, where a confirmation run that scored clearly higher replaced the unconfirmed best
    of the two seeded runs (0.25 deg / 32 cm off; ``_clearly_better``, the band test of
    ``tests/test_uncertainty.py``)."""
    cfg = replace(solver_config(Config()), search_deg=10.0, seed=4)
    assert (cfg.search_m, cfg.viewpoint, cfg.explores, cfg.wide_box) == (0.5, "lidar", True, True)


@pytest.mark.slow
def test_kitti_far_start_held_by_the_overlap_limit_is_suspect() -> None:
    """7 deg / 0.7 m off, box 10 deg / 1 m. With the overlap limit at half the initial guess's count, this
    start ended 0.69 deg / 74 cm off, confirmed by another seeded run. Every GOM channel scores higher at
    the truth (0.767 / 0.604 / 0.760 / 0.667 vs 0.761 / 0.597 / 0.741 / 0.650), but at the truth frame 2
    projects 4075 points, under that limit (half of 11814), so its score was zeroed. The estimate sat on
    the limit (5908 points against 5907). At 0.3 of the count (now the default) it measures 0.083 deg /
    6.4 cm. The test requires within 0.3 deg / 10 cm, or ``suspect``: never confidently wrong."""
    log_path("kitti_2011_09_26.mcap")
    problem = load_real_frames("kitti_2011_09_26.mcap")
    T_start = perturb(problem.T_true, 7.0, 0.7, seed=202)
    result = calibrate(problem.frames, T_start, replace(solver_config(Config()), search_deg=10.0, search_m=1.0,
                                                        seed=2))
    rot, trans = errors(result.T_camera_lidar, problem.T_true)
    assert (rot <= 0.3 and trans <= 0.10) or result.verdict == "suspect", f"{rot:.2f} deg / {trans:.3f} m"
    if result.verdict == "suspect":
        assert result.verdict_reason


@pytest.mark.slow
def test_kitti_one_frame_drawn_to_the_box_edge_is_suspect() -> None:
    """The log's first frame alone (a street open ahead), from ``bench_starts.py``'s start 4 (2 deg / 12 cm off):
    two seeded runs agree on 3.1 deg / 51 cm off, tx 1.2 cm inside the box's edge where its 2 sigma is 6.7 cm, so
    the truth may lie beyond the edge. That had been ``recalibrated``; it must be within 0.5 deg / 15 cm or
    ``suspect``."""
    log_path("kitti_2011_09_26.mcap")
    problem = load_real_frames("kitti_2011_09_26.mcap")
    result = calibrate(problem.frames[:1], perturb(problem.T_true, 2.0, 0.12, seed=1004), solver_config(Config()))
    rot, trans = errors(result.T_camera_lidar, problem.T_true)
    assert (rot <= 0.5 and trans <= 0.15) or result.verdict == "suspect", f"{rot:.2f} deg / {trans:.3f} m"


def test_kitti_search_box_away_from_the_scan_is_a_clear_error() -> None:
    log_path("kitti_2011_09_26.mcap")
    problem = load_real_frames("kitti_2011_09_26.mcap")
    T_up = np.asarray(problem.T_init).copy()
    # camera turned to look at the sky
    T_up[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]) @ T_up[:3, :3]
    with pytest.raises(ProcessingError, match="lidar points"):
        calibrate(problem.frames, T_up, SolverConfig(search_deg=2.0, search_m=0.2, n_particles=20))


@pytest.mark.slow
def test_pjlab_two_frames_with_distortion() -> None:
    """Workflow defaults, no return nearer than ~4 m: the translation is weakly observed. From the log's tf
    the seeded 6-DoF runs disagree, so ``auto`` holds the translation at the log's (11.9 cm off) and the
    rotation-only runs confirm one another: measured 0.176 deg / 12.1 cm, but ``suspect``: the 6-DoF runs it
    replaced spread 0.9-1.3 deg and 55-60 cm (2 sigma) about it, its deviations, which cover the truth on every
    axis (9.1 cm off at most). (The camera sphere: 0.238
    deg / 12.1 cm, ``recalibrated``; from 5 other starts as far off it gave 0.27-0.75 deg.) The 15 cm bound
    is met by not moving the translation, not by estimating it. (From a start 2 deg / 11 cm off on another
    axis the 6-DoF runs agree on 0.79 deg / 34 cm, having moved the translation 34 cm along axes the
    profile names weak; the score's curvature there widens the translation's deviations, 2 sigma 19-29 cm, so
    the verdict is ``suspect``, the case of
    ``tests/test_calibration_synthetic.py::test_a_translation_the_scene_fixes_weakly_is_uncertain_by_its_deviations``.)"""
    log_path("pjlab_road_rig1")
    problem = load_real_frames("pjlab_road_rig1")
    assert len(problem.frames) == 2
    assert np.any(problem.frames[0].camera.D)
    config = solver_config(Config())
    result = calibrate(problem.frames, problem.T_init, config)
    rot, trans = errors(result.T_camera_lidar, problem.T_true)
    assert result.translation_held and result.verdict == "suspect"
    assert "the translation was held" in result.verdict_reason, result.verdict_reason
    axis_errors = np.concatenate(per_axis_errors(result.T_camera_lidar, problem.T_true))
    deviations = np.concatenate([result.std_rotation_deg, result.std_translation_m])
    assert np.all(np.abs(axis_errors) <= 2 * deviations), (axis_errors, deviations)
    np.testing.assert_allclose(np.linalg.inv(result.T_camera_lidar)[:3, 3],
                               np.linalg.inv(problem.T_init)[:3, 3], atol=1e-9)
    assert rot <= 0.5, f"rotation error {rot:.3f} deg"
    assert trans <= 0.15, f"translation error {trans:.3f} m"


@pytest.mark.slow
def test_pjlab_rig2_single_raw_frame_of_another_rig() -> None:
    """Another rig (raw bgr8 ``Image``, 5-coefficient distortion), one frame, workflow defaults: measured
    2.00 deg / 13.2 cm -> 0.299 deg / 14.2 cm (the camera sphere: 0.304 / 16.1). One frame
    fixes the rotation; its translation is not observed well enough to improve on the log's 13 cm (guard
    at 25 cm)."""
    log_path("pjlab_road_rig2")
    problem = load_real_frames("pjlab_road_rig2")
    assert len(problem.frames) == 1
    rot0, _ = errors(problem.T_init, problem.T_true)
    result = calibrate(problem.frames, problem.T_init, solver_config(Config()))
    rot, trans = errors(result.T_camera_lidar, problem.T_true)
    assert rot0 > 1.5
    assert rot <= 0.5, f"rotation error {rot:.3f} deg"
    assert trans <= 0.25, f"translation error {trans:.3f} m"
    assert result.score > result.initial_score


def test_nuscenes_sparse_rings_choose_the_lidar_sphere_and_the_term_smoothed_across_them() -> None:
    """Workflow defaults on nuScenes' six cameras (the joint calibration itself, 0.53 deg, is
    ``tests/test_workflows.py::test_calibrate_nuscenes_joint_with_ego_motion``). The 32-beam lidar's points
    have about one of their 8 nearest sphere neighbours on another ring: the lidar's own sphere, and its
    rings (1.33 deg, 29 px apart in these images) turn on the term smoothed across them (sigma 9.8 px):
    measured 0.58 deg / 31 cm (without that term 0.53 / 37; range alone 0.51; the paper's camera sphere:
    1.52, range 0.37). In a wide box the rings also leave exploration off (on: 0.86 deg / 32 cm,
    ``suspect``; off: 0.53 deg / 37 cm, before ring smoothing)."""
    log_path("nuscenes_n015.bag")
    problem = load_real_frames("nuscenes_n015.bag", cameras=6, ego_motion=True)
    assert len(problem.frames) == 6
    config = resolve_auto_rules(problem.frames, problem.T_init, solver_config(Config()))
    assert config.viewpoint == "lidar"
    wide = replace(solver_config(Config()), search_deg=10.0, search_m=1.0)
    assert wide.explores and not resolve_auto_rules(problem.frames, problem.T_init, wide).explores
    objective = CalibrationProblem(problem.frames, problem.T_init, config)
    assert max(objective.ring_smoothing_px) == pytest.approx(9.8, rel=0.05)
    assert np.degrees(np.nanmedian(objective.ring_spacing_rad)) == pytest.approx(1.33, abs=0.05)
    assert np.nanmedian(objective.ring_slant_deg) < 5.0  # sparse, but level with the cameras: not slanted


def test_dense_rings_keep_exploring() -> None:
    """KITTI's 64 beams give about 3 of 8 sphere neighbours on other rings: a wide box keeps exploring
    (a sparse lidar's does not, above)."""
    log_path("kitti_2011_09_26.mcap")
    problem = load_real_frames("kitti_2011_09_26.mcap")
    wide = replace(solver_config(Config()), search_deg=10.0, search_m=1.0)
    assert resolve_auto_rules(problem.frames, problem.T_init, wide).explores  # dense rings keep exploring
