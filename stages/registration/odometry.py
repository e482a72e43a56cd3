"""Scan-to-scan odometry over a sequence of scans, and a voxel-grid map with averaged channels.

Poses are ``T_map_lidar`` with map = the first scan's lidar frame. Each new scan (source) is
registered to the previous one (target) starting from a constant-velocity guess (the previous
relative motion) or from externally given odometry poses.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from pipeline.errors import InputError
from pipeline.frames import LidarFrame
from pipeline.transforms import apply, invert
from stages.registration.gicp import RegistrationConfig, register
from stages.registration.pointset import PointSet, pointset_from_frame
from stages.registration.voxel import voxel_downsample, voxel_keys

MAP_CHANNELS = ("intensity", "r", "g", "b")
COLOR_CHANNELS = ("r", "g", "b")


@dataclass
class OdometryStep:
    """One scan of the trajectory.

    Attributes:
        index: position of the scan in the input sequence.
        stamp_ns: scan time, ns.
        T_map_lidar: (4, 4) pose of the scan, map = first scan's lidar frame.
        T_prev_curr: (4, 4) motion from the previous scan (identity for the first).
        fitness: registration fitness against the previous scan (1.0 for the first scan).
        rmse_m: registration RMSE, metres (0.0 for the first scan).
        iterations: optimiser iterations.
        converged: registration converged (True for the first scan).
        degenerate: Hessian eigenvalue ratio below the threshold.
        hessian_eigenvalues: (6,) ascending, zeros for the first scan.
        n_points: points used for registration after downsampling.
        dropped_points: non-finite points removed.
    """

    index: int
    stamp_ns: int
    T_map_lidar: NDArray[np.float64]
    T_prev_curr: NDArray[np.float64]
    fitness: float
    rmse_m: float
    iterations: int
    converged: bool
    degenerate: bool
    hessian_eigenvalues: NDArray[np.float64] = field(default_factory=lambda: np.zeros(6))
    n_points: int = 0
    dropped_points: int = 0


class VoxelMap:
    """A voxel grid accumulating points in the map frame; each voxel keeps the mean position and channels.

    Channels (``intensity`` float, ``r``, ``g``, ``b`` uint8) are averaged; ``channels()`` returns
    only those that every inserted scan carried.
    """

    def __init__(self, voxel_size_m: float) -> None:
        if not (np.isfinite(voxel_size_m) and voxel_size_m > 0):
            raise InputError(f"map voxel size must be > 0, got {voxel_size_m}")
        self.voxel_size_m = float(voxel_size_m)
        self._keys = np.zeros(0, dtype=np.int64)
        self._sums = np.zeros((0, 3 + len(MAP_CHANNELS)))
        self._counts = np.zeros(0, dtype=np.int64)
        self._present: set[str] | None = None

    @property
    def n_voxels(self) -> int:
        return int(self._keys.shape[0])

    def insert(
        self, points_map_xyz: NDArray[np.floating], channels: dict[str, NDArray[np.generic]] | None = None
    ) -> None:
        """Add (N, 3) points already in the map frame, with optional per-point channels."""
        pts = np.asarray(points_map_xyz, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise InputError(f"map points must be (N, 3), got {pts.shape}")
        channels = {} if channels is None else channels
        finite = np.all(np.isfinite(pts), axis=1)
        values = np.zeros((pts.shape[0], 3 + len(MAP_CHANNELS)))
        values[:, :3] = pts
        present = set()
        for col, name in enumerate(MAP_CHANNELS):
            if name in channels:
                values[:, 3 + col] = np.asarray(channels[name], dtype=np.float64)
                present.add(name)
        self._present = present if self._present is None else self._present & present
        values = values[finite & np.all(np.isfinite(values), axis=1)]
        if values.shape[0] == 0:
            return
        keys = np.concatenate([self._keys, voxel_keys(values[:, :3], self.voxel_size_m)])
        sums = np.concatenate([self._sums, values])
        counts = np.concatenate([self._counts, np.ones(values.shape[0], dtype=np.int64)])
        unique, inverse = np.unique(keys, return_inverse=True)
        self._keys = unique
        self._counts = np.bincount(inverse, weights=counts, minlength=unique.shape[0]).astype(np.int64)
        self._sums = np.stack(
            [
                np.bincount(inverse, weights=sums[:, c], minlength=unique.shape[0])
                for c in range(sums.shape[1])
            ],
            axis=1,
        )

    def points(self) -> NDArray[np.float64]:
        """(M, 3) mean position of each voxel, metres, map frame."""
        return self._sums[:, :3] / self._counts[:, None]

    def channels(self) -> dict[str, NDArray[np.generic]]:
        """Mean channels per voxel: ``intensity`` float32; ``r``, ``g``, ``b`` uint8."""
        out: dict[str, NDArray[np.generic]] = {}
        for col, name in enumerate(MAP_CHANNELS):
            if self._present is None or name not in self._present:
                continue
            mean = self._sums[:, 3 + col] / self._counts
            if name in COLOR_CHANNELS:
                out[name] = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
            else:
                out[name] = mean.astype(np.float32)
        return out


def _as_pointset(scan: PointSet | LidarFrame, config: RegistrationConfig) -> PointSet:
    if isinstance(scan, PointSet):
        return scan
    if isinstance(scan, LidarFrame):
        return pointset_from_frame(scan, config)
    raise InputError(f"run_odometry takes PointSet or LidarFrame scans, got {type(scan).__name__}")


def _map_points(
    scan: PointSet | LidarFrame, pointset: PointSet
) -> tuple[NDArray[np.float64], dict[str, NDArray[np.generic]]]:
    """Points and channels to insert into the map: the full frame when given, else the PointSet."""
    if isinstance(scan, LidarFrame):
        channels = {name: np.asarray(scan.channels[name]) for name in MAP_CHANNELS if name in scan.channels}
        return np.asarray(scan.points_xyz, dtype=np.float64), channels
    channels = {}
    for col, name in enumerate(pointset.channel_names):
        values = pointset.channels[:, col]
        channels[name] = values * 255.0 if name in COLOR_CHANNELS else values
    return pointset.points_xyz, channels


def run_odometry(
    scans: Iterable[PointSet | LidarFrame],
    config: RegistrationConfig | None = None,
    initial_motion: Sequence[NDArray[np.float64]] | None = None,
    voxel_map: VoxelMap | None = None,
) -> list[OdometryStep]:
    """Scan-to-scan odometry: register each scan to the previous one and chain the motions.

    Args:
        scans: LidarFrames (prepared with ``config``) or already prepared PointSets, in time order.
        config: registration settings (method, channels, voxel size...); default GICP.
        initial_motion: optional external odometry, one (4, 4) pose T_odom_lidar per scan; the guess
            for each pair is then inv(P[k-1]) @ P[k]. Without it: constant velocity.
        voxel_map: when given, every scan is inserted at its estimated pose (a failed pair keeps
            the guess and the map keeps going).

    Returns:
        One OdometryStep per scan.

    Raises:
        InputError: a scan cannot be prepared, or ``initial_motion`` is shorter than the scans.
    """
    config = RegistrationConfig() if config is None else config
    steps: list[OdometryStep] = []
    previous: PointSet | None = None
    T_map_prev = np.eye(4)
    velocity = np.eye(4)
    for index, scan in enumerate(scans):
        current = _as_pointset(scan, config)
        if previous is None:
            T_map_curr = np.eye(4)
            step = OdometryStep(
                index,
                current.stamp_ns,
                T_map_curr,
                np.eye(4),
                1.0,
                0.0,
                0,
                True,
                False,
                n_points=current.n_points,
                dropped_points=current.dropped_points,
            )
        else:
            if initial_motion is not None:
                if index >= len(initial_motion):
                    raise InputError(f"initial_motion has {len(initial_motion)} poses for more scans")
                guess = invert(np.asarray(initial_motion[index - 1])) @ np.asarray(initial_motion[index])
            else:
                guess = velocity
            result = register(current, previous, guess, config)
            T_prev_curr = result.T_target_source if result.n_correspondences > 0 else guess
            T_map_curr = T_map_prev @ T_prev_curr
            velocity = T_prev_curr
            step = OdometryStep(
                index,
                current.stamp_ns,
                T_map_curr,
                T_prev_curr,
                result.fitness,
                result.rmse_m,
                result.iterations,
                result.converged,
                result.degenerate,
                result.hessian_eigenvalues,
                current.n_points,
                current.dropped_points,
            )
        steps.append(step)
        if voxel_map is not None:
            points, channels = _map_points(scan, current)
            voxel_map.insert(apply(T_map_curr, points), channels)
        previous = current
        T_map_prev = T_map_curr
    return steps


__all__ = ["OdometryStep", "VoxelMap", "run_odometry", "voxel_downsample"]
