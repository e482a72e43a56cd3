"""Occlusion filter of the calibration preparation (``CalibrationConfig.occlusion_filter``)."""

from __future__ import annotations

import numpy as np

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.stages.calibration.problem import visible_points


def _grid(x_half: float, y_half: float, z: float, step: float) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(-x_half, x_half + 1e-9, step), np.arange(-y_half, y_half + 1e-9, step))
    return np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)])


def test_wall_behind_box_hidden_points_dropped_visible_kept() -> None:
    """Camera frame, f = 500 px: a 2 m x 2 m box face at 5 m in front of a 6 m x 4 m wall at 10 m.

    The box covers |x|, |y| < 2 m on the wall (|u - cx|, |v - cy| < 200 px); wall points well inside
    that shadow are dropped, wall points well outside it and every box point are kept.
    """
    camera = CameraModel(640, 480, np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), np.zeros(5), "plumb_bob")
    box = _grid(1.0, 1.0, 5.0, 0.02)  # 2 px spacing on the image
    wall = _grid(3.0, 2.3, 10.0, 0.04)  # 2 px spacing
    behind = _grid(0.5, 0.5, 100.0, 0.5)  # far outside the image: never tested, kept
    behind[:, 0] += 200.0
    points = np.vstack([box, wall, behind])
    keep = visible_points(points, camera, cell_px=4, rel_tol=0.1, abs_tol_m=0.1)

    n_box, n_wall = box.shape[0], wall.shape[0]
    wall_keep = keep[n_box : n_box + n_wall]
    shadow = np.max(np.abs(wall[:, :2]), axis=1)
    assert keep[:n_box].all()
    assert not wall_keep[shadow < 1.9].any()  # hidden behind the box (margin of ~2 cells)
    assert wall_keep[shadow > 2.1].all()  # beside the box
    assert np.count_nonzero(shadow < 1.9) > 5000 and np.count_nonzero(shadow > 2.1) > 3000
    assert keep[n_box + n_wall :].all()
