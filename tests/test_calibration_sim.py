"""GOM calibration on simulated logs (``workflows.simulator``) with exact ground truth.

The logs are written by the simulator (64 beams, 512 columns, 640x360 pinhole images, camera fired
10-30 ms after each scan, 8 m/s on the street), their frames are collected by the calibrate
workflow (pairing, ego-motion from ``/tf``, lidar feature, image gradients) and ``calibrate`` starts
from the log's ``/tf_static``, which the simulator perturbed by 5 deg / 0.5 m on a random axis.

Measured (``.venv/bin/python`` loop over these helpers, 10 frames, default ``SolverConfig``):
street, 1280x720 x 1024 columns: range 1.43 deg / 23.9 cm (``fleetcal calibrate --json``);
street, 640x360 x 512 columns: range 3.93 deg / 30.4 cm, intensity 0.249 deg / 0.96 cm.
In the simulator the lidar intensity is the reflectivity that also paints the image, so the
intensity feature is the right one there, while the range feature's optimum is biased (a probe at
the truth: -0.5 deg about the optical axis scores 0.734 vs 0.677 at the truth). The target
of 0.1 deg / 2 cm on the street is reached with a box wide enough for the start (10 deg / 1 m: the
lidar's own sphere, 0.060 deg / 1.0 cm); the default 5 deg / 0.5 m box meets it in translation only.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
from fleetcal.readers.frames import load_tf_tree
from fleetcal.readers.open import open_log
from fleetcal.stages.calibration import CalibrationFrame, SolverConfig, calibrate
from fleetcal.workflows.calibrate import collect_frames, initial_guess, solver_config
from fleetcal.workflows.simulator.truth import load_truth, truth_path_for
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log
from tests.test_calibration_synthetic import perturb

SIM = {"beams": 64, "columns": 512, "width": 640, "height": 360, "perturb_deg": 5.0, "perturb_m": 0.5,
       "seed": 1}


def simulated_frames(out: Path, scene: str, feature: str, frames: int, beams: int = SIM["beams"],
                     columns: int = SIM["columns"], skewed_at_m_s: float | None = None,
                     point_times: bool = True, panorama: bool = False, rectified: bool = False,
                     lidar: str = "spinning", lidar_roll_deg: float = 0.0) -> tuple[
        list[CalibrationFrame], NDArray[np.float64], NDArray[np.float64]]:
    """Frames (as the calibrate workflow collects them), the log's tf guess and the true extrinsic.
    ``skewed_at_m_s``: a motion-distorted log (each column cast from the pose at its firing time) driven
    at that speed; ``point_times``: the workflow's ``calibration.point_times``; ``panorama``: a 1024x256
    cylindrical 360 deg camera instead of the 640x360 pinhole; ``rectified``: rectified stereo images
    (``image_rect``, a CameraInfo R of 1.5 deg); ``lidar``: ``rosette`` for the forward-looking
    non-repetitive lidar (``beams`` lines x ``columns`` samples); ``lidar_roll_deg``: the lidar mounted rolled
    about its forward axis (``fleetcal simulate --lidar-roll``)."""
    name = scene if beams == SIM["beams"] else f"{scene}_{beams}beams"
    if lidar != "spinning":
        name = f"{name}_{lidar}"
    if lidar_roll_deg:
        name = f"{name}_rolled_{lidar_roll_deg:g}"
    if skewed_at_m_s is not None:
        name = f"{name}_skewed_{skewed_at_m_s:g}"
    if panorama:
        name = f"{name}_panorama"
    if rectified:
        name = f"{name}_rectified"
    log = out / (f"{name}.mcap" if columns == SIM["columns"] else f"{name}_{columns}columns.mcap")
    if not log.exists():
        options = {**SIM, "beams": beams, "columns": columns, "lidar": lidar, "lidar_roll_deg": lidar_roll_deg}
        if skewed_at_m_s is not None:
            options.update(deskew=False, speed_m_s=skewed_at_m_s)
        if panorama:
            options.update(panorama=True, width=1024, height=256)
        if rectified:
            options.update(rectified=True)
        simulate_log(log, SimulationOptions(frames=frames, scene=scene, **options))  # type: ignore[arg-type]
    truth = load_truth(truth_path_for(log))
    config = Config()
    config.calibration.feature = feature  # type: ignore[assignment]
    config.calibration.frames = frames
    config.calibration.point_times = point_times
    reader = open_log(log)
    try:
        tree = load_tf_tree(reader)
        pair = truth["pairs"][0]
        col = collect_frames(reader, truth["lidar_topic"], pair["camera_topic"], config, tree)
        T_init = initial_guess(tree, col.lidar_frame, col.camera_frame, None)
    finally:
        close = getattr(reader, "close", None)
        if close is not None:
            close()
    return col.frames, T_init, np.asarray(pair["T_camera_lidar"], dtype=np.float64)


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("sim")


def test_street_intensity_recovers_extrinsic_from_5deg_50cm(sim_dir: Path) -> None:
    frames, T_init, T_true = simulated_frames(sim_dir, "street", "intensity", 10)
    assert len(frames) == 10
    assert rotation_error_deg(T_init, T_true) == pytest.approx(5.0, abs=1e-6)
    assert translation_error_m(T_init, T_true) == pytest.approx(0.5, abs=1e-6)
    assert any(f.T_lidar_motion is not None for f in frames)  # ego-motion from /tf is applied
    result = calibrate(frames, T_init, SolverConfig())
    rot = rotation_error_deg(result.T_camera_lidar, T_true)
    trans = translation_error_m(result.T_camera_lidar, T_true)
    assert rot <= 0.35, f"rotation error {rot:.3f} deg"
    assert trans <= 0.02, f"translation error {trans:.3f} m"
    assert result.verdict == "recalibrated"
    assert result.score > result.initial_score + 0.1


def test_street_wide_box_reaches_the_issue_target_from_5deg_50cm(sim_dir: Path) -> None:
    """From 5 deg / 0.5 m off with a box that holds such an error (10 deg / 1 m, as on KITTI), the auto
    settings take lidar gradients on the lidar's own sphere with the least-squares fit, and the swarm
    first explores against image gradients blurred 3x more (``SolverConfig.explore``): the street
    target of 0.1 deg / 2 cm, confirmed by another seeded run (measured 0.049 deg / 0.9 cm, 2 of the 3
    runs agree). Without exploring 1 of 6 seeded runs found the global optimum (the others stopped at
    3-10 deg / 0.5-1 m, scores 0.666-0.707 vs 0.750) and the estimate (0.060 deg / 1.0 cm) was
    ``suspect``. Algorithm 1's fit instead of lsq: 0.123 deg / 0.4 cm; the camera-centred sphere in the
    default 5 deg / 0.5 m box 0.249 deg / 1.0 cm."""
    frames, T_init, T_true = simulated_frames(sim_dir, "street", "intensity", 10)
    config = SolverConfig(search_deg=10.0, search_m=1.0, repeats=3)
    assert (config.viewpoint, config.fit, config.explores) == ("lidar", "lsq", True)
    assert not SolverConfig().explores
    result = calibrate(frames, T_init, config)
    assert result.verdict == "recalibrated", result.verdict_reason
    assert result.agreeing_repeats >= 1
    assert rotation_error_deg(result.T_camera_lidar, T_true) <= 0.1
    assert translation_error_m(result.T_camera_lidar, T_true) <= 0.02


@pytest.mark.slow
def test_cylindrical_panorama_from_5deg_50cm(sim_dir: Path) -> None:
    """The GOM paper's panoramic camera model (eq. 6; its Ladybug dataset): a 1024x256 cylindrical image
    covering 360 deg, whose CameraInfo says ``cylindrical``, sees the whole scan. From 5 deg / 0.5 m with
    the defaults: measured 0.111 deg / 2.5 cm (0.35 deg per pixel of azimuth)."""
    frames, T_init, T_true = simulated_frames(sim_dir, "street", "intensity", 10, panorama=True)
    assert frames[0].camera.distortion_model == "cylindrical"
    result = calibrate(frames, T_init, SolverConfig())
    assert rotation_error_deg(result.T_camera_lidar, T_true) <= 0.3
    assert translation_error_m(result.T_camera_lidar, T_true) <= 0.05
    assert result.verdict == "recalibrated"


@pytest.mark.slow
def test_rectified_stereo_images_give_the_cameras_own_extrinsic(sim_dir: Path) -> None:
    """Rectified stereo images (``/camera_0/image_rect``; CameraInfo R turns the image frame 1.5 deg from
    the camera's tf frame): read back with R, the extrinsic found is the tf frame's. From 5 deg / 0.5 m,
    defaults; the same frames with R dropped end over 1 deg off. The start lies on the default box's edge:
    on the lidar's sphere (default) the estimate is within 0.3 deg / 5 cm but ``suspect``; on the camera's
    it was 0.262 deg / 1.5 cm, ``recalibrated``. In a 10 deg / 1 m box (exploring) single runs, seeds 0-3,
    ended 6.36 deg / 67 cm, 0.07 / 1.1, 0.08 / 1.2 and 10.1 deg / 86 cm (the box holds far optima); three runs,
    the workflow's default, gave 0.082 deg / 1.2 cm from seeds 0, 1 and 2 (one run there is now ``suspect``)."""
    frames, T_init, T_true = simulated_frames(sim_dir, "street", "intensity", 10, rectified=True)
    assert frames[0].camera.R_rect is not None and frames[0].camera.distortion_model == "none"
    config = SolverConfig()
    result = calibrate(frames, T_init, config)
    assert rotation_error_deg(result.T_camera_lidar, T_true) <= 0.3
    assert translation_error_m(result.T_camera_lidar, T_true) <= 0.05
    dropped = [dataclasses.replace(f, camera=f.camera.without_rectification()) for f in frames]
    ignored = calibrate(dropped, T_init, dataclasses.replace(config, repeats=1))
    assert rotation_error_deg(ignored.T_camera_lidar, T_true) >= 1.0


@pytest.mark.slow
def test_motion_during_the_sweep_is_compensated_point_by_point(sim_dir: Path) -> None:
    """A lidar that does not de-skew, on a car at 15 m/s: points fired over 0.1 s are each moved from their
    own time field to the camera stamp with the lidar's twist from /tf (``calibration.point_times``).
    Moving each scan by its stamp alone leaves the sweep's motion in the points (up to 1.5 m), and the
    translation absorbs it. From 5 deg / 0.5 m, box 10 deg / 1 m, 3 repeats (the control by the stamp: one):
    measured 0.064 deg / 1.8 cm vs 0.155 deg / 24.8 cm by the stamp (``bench_gom.py --sweep``: 5 and 10 m/s
    0.06-0.08 deg / 2 cm vs 13-26 cm; 1280x720 x 1024 columns from 2 deg / 10 cm: 0.17 deg / 2.1 cm vs
    0.06 / 12 cm at 15 m/s, 0.26 / 2.4 vs 0.48 / 60 at 10 m/s)."""
    config = SolverConfig(search_deg=10.0, search_m=1.0, repeats=3)
    errors = {}
    for point_times in (True, False):
        frames, T_init, T_true = simulated_frames(sim_dir, "street", "intensity", 10, skewed_at_m_s=15.0,
                                                  point_times=point_times)
        assert all((f.twist_lidar is not None) == point_times for f in frames)
        result = calibrate(frames, T_init, config if point_times else dataclasses.replace(config, repeats=1))
        errors[point_times] = (rotation_error_deg(result.T_camera_lidar, T_true),
                               translation_error_m(result.T_camera_lidar, T_true))
    assert errors[True][0] <= 0.2 and errors[True][1] <= 0.05, errors
    assert errors[False][1] > 0.15, errors  # the sweep's motion matters: the test would not see a regression


# Open yard (painted ground, a few cars, terraces whose creases are edges of surface orientation with
# continuous range), 640x360 x 512 columns, 10 frames, from 5 deg / 0.5 m, default settings:
# intensity 0.132 deg / 1.5 cm; range 4.42 deg / 81 cm; normals 4.61 deg / 36 cm (lidar viewpoint, lsq:
# normals 4.53 / 36, range 4.99 / 40). The issue expected normals to work where range fails; on this
# yard they do not: the image's edges are mostly paint and ground patches that normals cannot see, and
# both geometric features score higher (0.68-0.88) at poses several degrees off than at the truth.
# Also measured, not adopted: frames spread over 50 m of drive (1 Hz) with 60 instead of 24 earthworks
# give normals 0.28-1.2 deg / 16-19 cm over 3 scene seeds (range 2.3-6.0 deg / 77-104 cm), always ~15 cm
# too far forward; started at the truth, normals still drift to 0.86 deg / 29 cm. Normals from 8
# neighbours on the lidar's sphere (1.4 deg / 18 cm) and a feature of the normal alone (its tilt from
# the lidar's z axis, constant on flat ground: 2.5-9 deg) did not fix it. The ground's texture is what
# defeats normals: the same yard with bare uniform ground (no paint, no patches; terraces and cars kept,
# an ad hoc scene) gives normals 0.50 deg / 9.8 cm at scene seed 1, but at seeds 2-4 the translation runs
# to the box's edge (0.48-1.04 deg / 83-113 cm, all flagged suspect); patches without paint: 4.05 deg.
# Why, measured (/tmp ad hoc scripts; the returned pose vs the truth, GOM split by point class): the paper's
# normals feature (the normal's angle to the ray) is, on flat ground, the incidence angle atan(r / h): a
# monotone function of range, so on a yard that is mostly ground it behaves like range. Ground points score
# 0.722 at the returned pose (5785 in view) vs 0.656 at the truth (19182), the rest 0.677 vs 0.755: the
# swarm trades the near ground out of view. Normals as a vector field instead (the structure tensor of the
# sphere gradients of the three normal components, no equalisation, so flat ground carries only noise): 6.1
# deg (k-d tree normals) and 9.6 deg (range-image normals); keeping the top 5-20 % of its magnitudes or
# cutting at 2-8x the median magnitude: 5.2-10 deg. In every variant the returned pose scores above the
# truth (e.g. 0.680 vs 0.544): the objective is wrong, not the search. Few creases are in view (a frame
# sees one or two terraces near the horizon), and paint edges are everywhere to align them with.
def test_open_scene_intensity_recovers_extrinsic(sim_dir: Path) -> None:
    """From the log's 5 deg / 0.5 m start in a box that holds it (10 deg / 1 m): measured 0.195 deg /
    2.3 cm. The default 5 deg / 0.5 m box puts that start's truth on its edge: 3.64 deg / 36 cm,
    ``suspect``; from two starts 2 deg / 12 cm off, default box: 0.21 / 2.5 and 0.20 / 2.9. The lidar's
    sphere keeps a 0.2 deg bias here, from the scan's 512 columns (from the truth 0.212 deg, with 1024
    columns 0.104: ``test_lidar_sphere_from_the_truth_stays_there_when_columns_are_dense``); the camera's
    (``gradient_viewpoint = camera``) gave 0.13 deg / 1.4 cm from this start, 0.05 / 1.1 and 1.77 / 18.7 from the
    other two."""
    frames, T_init, T_true = simulated_frames(sim_dir, "open", "intensity", 10)
    result = calibrate(frames, T_init, SolverConfig(search_deg=10.0, search_m=1.0, repeats=2))
    rot = rotation_error_deg(result.T_camera_lidar, T_true)
    trans = translation_error_m(result.T_camera_lidar, T_true)
    assert rot <= 0.3, f"rotation error {rot:.3f} deg"
    assert trans <= 0.04, f"translation error {trans:.3f} m"
    assert result.verdict == "recalibrated", result.verdict_reason


@pytest.mark.slow
def test_lidar_sphere_from_the_truth_stays_there_when_columns_are_dense(sim_dir: Path) -> None:
    """The lidar sphere's small bias on the simulator comes from the test scans' 512 columns (0.70 deg apart,
    sparser than the 64 rings' 0.42 deg; no spinning lidar common on vehicles samples its columns that
    coarsely but an Ouster in 512-column mode). From the truth, box 1 deg / 0.1 m, 6 DoF, street (intensity),
    scene seeds 1, 2, 3: 512 columns 0.244 / 0.230 / 0.266 deg, 3-4 cm; 1024 columns 0.042 / 0.073 / 0.089
    deg, 0.9-1.2 cm; 2048 columns 0.023 / 0.049 / 0.118 deg. Neither the image blur (2 -> 3, 4 px: worse),
    the gradient fit, K, the magnitude, the kept fraction nor the image-axis gradients removed it at 512."""
    frames, _, T_true = simulated_frames(sim_dir, "street", "intensity", 10, columns=1024)
    config = SolverConfig(search_deg=1.0, search_m=0.1, translation="estimate")
    result = calibrate(frames, T_true, config)
    assert rotation_error_deg(result.T_camera_lidar, T_true) <= 0.1
    assert translation_error_m(result.T_camera_lidar, T_true) <= 0.015


@pytest.mark.slow
@pytest.mark.parametrize("feature", ["range", "normals"])
def test_open_scene_geometric_features(sim_dir: Path, feature: str) -> None:
    """Range and normals on the open yard: the target is 0.5 deg / 10 cm; where that is missed (both,
    measured: range 4.43 deg / 81 cm, normals 7.32 deg / 106 cm (4.60 / 36 with the overlap limit at 0.5),
    each with components at the edge of the 5 deg / 0.5 m box) the estimate must carry the verdict
    ``suspect``, never a confident wrong one."""
    frames, T_init, T_true = simulated_frames(sim_dir, "open", feature, 10)
    result = calibrate(frames, T_init, SolverConfig())
    rot = rotation_error_deg(result.T_camera_lidar, T_true)
    trans = translation_error_m(result.T_camera_lidar, T_true)
    within = rot <= 0.5 and trans <= 0.1
    assert within or result.verdict == "suspect", f"{rot:.2f} deg / {trans:.3f} m but {result.verdict}"
    if not within:
        pytest.xfail(f"{feature}: {rot:.2f} deg / {100 * trans:.0f} cm, flagged suspect "
                     f"({result.verdict_reason}); the yard's image edges are mostly paint")


@pytest.mark.slow
def test_vlp16_like_scan_is_not_fooled_by_its_rings(sim_dir: Path) -> None:
    """16 rings 2 deg apart and 1800 columns (a VLP-16), street, from 2 deg / 10 cm off: on the sharp
    image GOM is aliased by the rings and every seeded start tried (5) ended one ring off in pitch, 1.9-2.0
    deg / 36-40 cm, ``recalibrated``. With the term smoothed across the rings (auto: sigma 4 px > the
    2 px image blur) 4 of 5 starts land at 0.13-0.16 deg (3 seeded runs each); their translation keeps an
    18 cm bias that the metric has at the truth (this start: 0.135 deg / 18.3 cm). The test runs the default
    2 seeded runs, the unsmoothed control one."""
    frames, _, T_true = simulated_frames(sim_dir, "street", "intensity", 10, beams=16, columns=1800)
    T_init = perturb(T_true, 2.0, 0.1, seed=8)
    result = calibrate(frames, T_init, SolverConfig())
    assert result.ring_smoothing_px == pytest.approx(4.0, rel=0.1)
    assert rotation_error_deg(result.T_camera_lidar, T_true) <= 0.3
    assert translation_error_m(result.T_camera_lidar, T_true) <= 0.25
    aliased = calibrate(frames, T_init, SolverConfig(repeats=1, ring_smoothing="off"))  # every seed: a ring off
    assert aliased.ring_smoothing_px == 0.0
    assert rotation_error_deg(aliased.T_camera_lidar, T_true) > 1.5  # one ring (2 deg) off in pitch


@pytest.mark.slow
def test_rosette_lidar_calibrates_and_names_the_axis_it_cannot_fix(sim_dir: Path) -> None:
    """A forward-looking non-repetitive lidar (``--lidar rosette``: 6 lines x 4000 samples, a Livox Avia's
    24k points per scan, 70.4 deg circular field of view), street, intensity, 3 runs, from 2 deg / 10 cm
    off (start seeds 7-11): rotation 0.29-0.40 deg, translation 8.5-24.6 cm, all of it along the camera's
    vertical axis, which every run names weak (profile 0.04-0.34); the other axes within 3.2 cm. GOM at
    the truth 0.660 vs 0.661 at this start's estimate: the scan's few lines (each dense along its curve)
    leave the vertical translation almost flat. With 16 lines x 1800 samples: 0.076 deg / 2.0 cm; not
    de-skewed at 15 m/s (point times used), same starts: 0.05-0.39 deg / 2.8-5.2 cm. This start ends 0.24
    deg / 15.2 cm off, all along y, whose deviation (7.8 cm) makes it ``suspect`` for ty: an estimate
    beyond 0.5 deg / 15 cm must never be ``recalibrated``, and a ``suspect`` one names the axis."""
    frames, _, T_true = simulated_frames(sim_dir, "street", "intensity", 10, beams=6, columns=4000, lidar="rosette")
    result = calibrate(frames, perturb(T_true, 2.0, 0.1, seed=7), SolverConfig(repeats=3))
    error_camera_m = (result.T_camera_lidar @ np.linalg.inv(T_true))[:3, 3]
    assert rotation_error_deg(result.T_camera_lidar, T_true) <= 0.5
    if np.linalg.norm(error_camera_m) > 0.15:
        assert result.verdict == "suspect" and "ty" in result.verdict_reason, result.verdict_reason
    else:
        assert result.verdict == "recalibrated", result.verdict_reason
    assert "y" in result.weak_translation_axes
    assert abs(error_camera_m[0]) <= 0.05 and abs(error_camera_m[2]) <= 0.05, error_camera_m
    assert np.linalg.norm(error_camera_m) <= 0.3


@pytest.mark.slow
def test_sparse_lidar_rolled_to_the_camera_searches_by_angle_and_is_suspect(sim_dir: Path) -> None:
    """32 beams (rings 1.33 deg apart) rolled 45 deg about the forward axis, street, intensity, 1024 columns,
    from 2 deg / 10 cm off (seed 7): the sphere's stretch of the polar angle assumes level rings and ended
    1.36 deg / 43 cm off, ``recalibrated``; searched by angle (auto, since the rings cross the image slanted
    44 deg) 0.21 deg / 21 cm. Neither is reliable on such rigs (35-45 deg rolls: 0.2-0.8 deg by angle), so the
    verdict is ``suspect`` and says why."""
    frames, _, T_true = simulated_frames(sim_dir, "street", "intensity", 10, beams=32, columns=1024,
                                         lidar_roll_deg=45.0)
    result = calibrate(frames, perturb(T_true, 2.0, 0.1, seed=7), SolverConfig(repeats=3))
    assert result.ring_slant_deg == pytest.approx(44.0, abs=1.0) and result.sparse_rings
    assert result.verdict == "suspect" and "by angle, auto" in result.verdict_reason, result.verdict_reason
    assert rotation_error_deg(result.T_camera_lidar, T_true) <= 0.4
    assert translation_error_m(result.T_camera_lidar, T_true) <= 0.3


@pytest.mark.slow
def test_sparse_lidar_estimate_is_within_bounds_or_flagged(sim_dir: Path) -> None:
    """A 16-beam lidar (rings 2 deg apart, columns 0.7 deg) leaves GOM's lidar gradients too coarse: from a
    drifted 2 deg / 10 cm start the best of 6 seeded 6-DoF runs (3 repeats, 3 more while unconfirmed) is
    5.28 deg / 80 cm off and no other run
    lands within 0.5 deg / 15 cm of it. With the translation held (``translation = "auto"``) the runs
    agree on 3.41 deg / 9.5 cm, 5.9 deg from that best: returned, but ``suspect``. The estimate must be
    within 0.5 deg / 15 cm or carry the verdict ``suspect``: never a confident wrong calibration (the
    default 2 repeats, up to 3 more while unconfirmed)."""
    frames, _, T_true = simulated_frames(sim_dir, "street", "intensity", 10, beams=16)
    T_init = perturb(T_true, 2.0, 0.1, seed=7)
    result = calibrate(frames, T_init, SolverConfig())
    rot = rotation_error_deg(result.T_camera_lidar, T_true)
    trans = translation_error_m(result.T_camera_lidar, T_true)
    within = rot <= 0.5 and trans <= 0.15
    assert within or result.verdict == "suspect", f"{rot:.2f} deg / {trans:.3f} m but {result.verdict}"
    assert result.verdict != "suspect" or result.verdict_reason


@pytest.mark.slow
def test_a_corridor_keeps_the_6dof_estimate_its_held_translation_scores_clearly_below(sim_dir: Path) -> None:
    """3 m corridors, 6 frames, 2 deg / 12 cm off (start seed 1001). No seeded 6-DoF run confirms another, and the
    runs with the translation held at the start's agree on 2.3 deg off: in a scene this near, a rotation makes up
    for the held 12 cm. The best 6-DoF run (0.35 deg / 2 cm) scores 0.792 against their 0.741, clearly higher over
    the image bands, so the log fixes the translation and the 6-DoF estimate stands (``suspect``: unconfirmed)."""
    frames, _, T_true = simulated_frames(sim_dir, "corridor", "auto", 6)
    result = calibrate(frames, perturb(T_true, 2.0, 0.12, seed=1001), solver_config(Config()))
    assert not result.translation_held
    assert rotation_error_deg(result.T_camera_lidar, T_true) < 0.5
    assert translation_error_m(result.T_camera_lidar, T_true) < 0.05
    assert result.verdict == "suspect"
