"""Registration: GICP, Multi-Channel GICP (Servos & Waslander), Color-ICP; lidar odometry (local map or scan-to-scan).

Typical use::

    config = RegistrationConfig(method="mcgicp", channels="intensity")
    target = prepare_pointset(points0, {"intensity": i0}, config)
    source = prepare_pointset(points1, {"intensity": i1}, config)
    result = register(source, target, np.eye(4), config)   # result.T_target_source
"""

from fleetcal.stages.registration.config import RegistrationConfig
from fleetcal.stages.registration.covariances import estimate_covariances, knn_indices
from fleetcal.stages.registration.gicp import RegistrationResult, register
from fleetcal.stages.registration.odometry import (
    ODOMETRY_MODES,
    LocalMap,
    OdometryStep,
    VoxelMap,
    relative_translation_drift,
    run_odometry,
)
from fleetcal.stages.registration.pointset import CHANNEL_MODES, PointSet, pointset_from_frame, prepare_pointset
from fleetcal.stages.registration.voxel import voxel_downsample

__all__ = [
    "CHANNEL_MODES",
    "ODOMETRY_MODES",
    "LocalMap",
    "OdometryStep",
    "PointSet",
    "RegistrationConfig",
    "RegistrationResult",
    "VoxelMap",
    "estimate_covariances",
    "knn_indices",
    "pointset_from_frame",
    "prepare_pointset",
    "register",
    "relative_translation_drift",
    "run_odometry",
    "voxel_downsample",
]
