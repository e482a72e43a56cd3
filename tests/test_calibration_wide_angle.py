"""A VLP-16-like lidar (16 rings 2 deg apart, 1800 columns) with a real wide-angle lens (plumb_bob
D = -0.4398 0.2329 -0.0011 0.00021 -0.073, fx = 0.70 x width, ``fleetcal simulate --beams 16
--wide-angle``): the lens model folds over 50 deg off axis, inside the image's corners, so the projection
must cull points beyond that before distorting (it used to overflow and see no point at all).

Cheap settings (3 frames of a 640x360 image, 60 particles, 40 iterations, one run and no confirmation),
from the log's tf, 2 deg / 12 cm off. Measured: 0.365 deg / 22.0 cm, ``recalibrated`` (the accuracy target
is 0.2 deg / 3 cm): the rotation comes within 0.4 deg, the translation keeps the decimetre bias that GOM has
at the truth on 16 rings 2 deg apart with any lens (the pinhole VLP-16 test in test_calibration_sim.py:
18 cm), and one cut-down run cannot be checked against another, so nothing makes it ``suspect`` here. The
bounds below are what the lens part guarantees: points in view, the rotation pulled in from 2 deg.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.transforms import rotation_error_deg, translation_error_m
from fleetcal.readers.frames import load_tf_tree
from fleetcal.readers.open import open_log
from fleetcal.stages.calibration import SolverConfig, calibrate
from fleetcal.workflows.calibrate import collect_frames, initial_guess
from fleetcal.workflows.simulator.truth import load_truth, truth_path_for
from fleetcal.workflows.simulator.write import SimulationOptions, simulate_log

CHEAP = SolverConfig(n_particles=60, max_iterations=40, repeats=1, confirm_repeats=0)


@pytest.fixture(scope="module")
def wide_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    log = tmp_path_factory.mktemp("wide") / "vlp16_wide.mcap"
    simulate_log(log, SimulationOptions(frames=3, beams=16, columns=1800, wide_angle=True, width=640, height=360,
                                        perturb_deg=2.0, perturb_m=0.12, seed=1), quiet=True)
    return log


def test_vlp16_with_a_wide_angle_lens_calibrates(wide_log: Path) -> None:
    truth = load_truth(truth_path_for(wide_log))
    pair = truth["pairs"][0]
    config = Config()
    config.calibration.feature = "intensity"
    config.calibration.frames = 3
    with open_log(wide_log) as reader:
        tree = load_tf_tree(reader)
        col = collect_frames(reader, truth["lidar_topic"], pair["camera_topic"], config, tree)
        T_init = initial_guess(tree, col.lidar_frame, col.camera_frame, None)
    T_true = np.asarray(pair["T_camera_lidar"], dtype=np.float64)
    camera = col.frames[0].camera
    assert camera.max_undistorted_radius == pytest.approx(1.196, abs=1e-3)
    assert rotation_error_deg(T_init, T_true) == pytest.approx(2.0, abs=1e-6)
    result = calibrate(col.frames, T_init, CHEAP)
    rot = rotation_error_deg(result.T_camera_lidar, T_true)
    trans = translation_error_m(result.T_camera_lidar, T_true)
    print(f"wide-angle VLP-16: {rot:.3f} deg / {100 * trans:.1f} cm, {result.verdict}: {result.verdict_reason}")
    assert min(result.points_used) > 1000  # the camera sees the scan (it used to see no point)
    assert rot <= 0.6, f"{rot:.2f} deg from a 2 deg start"
    assert trans <= 0.3, f"{100 * trans:.1f} cm from a 12 cm start"
