"""Targetless lidar-camera calibration with the gradient orientation measure (GOM, Taylor et al.).

Lidar gradients on a camera-centred sphere, GOM / NMI / Levinson metrics evaluated for whole pose
batches in numba, a particle swarm plus pattern-search polish, and ``calibrate`` on top.
"""

from fleetcal.stages.calibration.affine import AffineResult, calibrate_affine
from fleetcal.stages.calibration.calibrator import CalibrationResult, calibrate
from fleetcal.stages.calibration.config import SolverConfig
from fleetcal.stages.calibration.frame import CalibrationFrame, compensate_ego_motion
from fleetcal.stages.calibration.landscape import ScoreLandscape, score_landscape
from fleetcal.stages.calibration.metrics import (
    METRICS,
    GomScorer,
    GradientPlanes,
    LevinsonScorer,
    MetricBatch,
    NmiScorer,
    levinson_edge_image,
)
from fleetcal.stages.calibration.problem import CalibrationProblem
from fleetcal.stages.calibration.pso import SwarmResult, particle_swarm, pattern_search
from fleetcal.stages.calibration.sphere_gradients import LidarGradients, compute_sphere_gradients

__all__ = [
    "METRICS",
    "AffineResult",
    "CalibrationFrame",
    "CalibrationProblem",
    "CalibrationResult",
    "GomScorer",
    "GradientPlanes",
    "LevinsonScorer",
    "LidarGradients",
    "MetricBatch",
    "NmiScorer",
    "ScoreLandscape",
    "SolverConfig",
    "SwarmResult",
    "calibrate",
    "calibrate_affine",
    "compensate_ego_motion",
    "compute_sphere_gradients",
    "levinson_edge_image",
    "particle_swarm",
    "pattern_search",
    "score_landscape",
]
