"""Per-point lidar features of the GOM paper, section 3.1: return intensity, range and normals, each
histogram-equalised to [0, 1].

Points are (N, 3) in the lidar frame, metres; the sensor sits at ``sensor_xyz`` (default the frame's
origin). Non-finite points (and non-finite intensities) are kept in place but get a NaN feature and
take no part in the neighbour search or the equalisation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree
from scipy.stats import rankdata

from pipeline.errors import InputError
from pipeline.frames import LidarFrame
from stages import lidar_feature_kernels

__all__ = [
    "FEATURE_KINDS",
    "FeatureKind",
    "LidarFeatureResult",
    "compute_lidar_feature",
    "equalize_rank",
    "lidar_frame_feature",
    "normal_ray_angles",
]

FeatureKind = Literal["intensity", "range", "normals"]
FEATURE_KINDS: tuple[str, ...] = get_args(FeatureKind)


def equalize_rank(values: ArrayLike) -> NDArray[np.float32]:
    """Rank-based histogram equalisation to [0, 1] (the empirical CDF, ties averaged).

    ``out = (average_rank - 1) / (n_finite - 1)``: the smallest value maps to 0, the largest to 1,
    equal values to the same number; a single value or a constant array maps to 0.5. Non-finite
    entries stay NaN and are not ranked.
    """
    arr = np.asarray(values, dtype=np.float64).ravel()
    out = np.full(arr.shape, np.nan, dtype=np.float32)
    finite = np.isfinite(arr)
    n = int(finite.sum())
    if n == 0:
        return out
    if n == 1:
        out[finite] = 0.5
        return out
    ranks = rankdata(arr[finite], method="average")
    out[finite] = ((ranks - 1.0) / (n - 1.0)).astype(np.float32)
    return out


def normal_ray_angles(
    points_xyz: ArrayLike, k: int = 8, sensor_xyz: ArrayLike = (0.0, 0.0, 0.0), knn_workers: int = -1
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """PCA normals of the k nearest neighbours and their angle to the sensor ray.

    Neighbours come from ``scipy.spatial.cKDTree`` over the finite points (query threads:
    ``knn_workers``, -1 = all cores); the covariance is centred at the point (GOM eq. 4) and its
    smallest eigenvector is the normal.

    Returns:
        normals: (N, 3) float64 unit normals (sign arbitrary), NaN where undefined.
        angles: (N,) float64 radians in [0, pi/2] between the normal line and the ray sensor->point;
            NaN for non-finite points, points with fewer than 2 neighbours, collinear neighbourhoods
            and points on the sensor.

    Raises:
        InputError: bad shape, k < 2.
    """
    pts = _check_points(points_xyz)
    if not isinstance(k, (int, np.integer)) or k < 2:
        raise InputError(f"k must be an integer >= 2, got {k!r}")
    sensor = _check_sensor(sensor_xyz)
    n = pts.shape[0]
    normals = np.full((n, 3), np.nan)
    angles = np.full(n, np.nan)
    finite = np.flatnonzero(np.isfinite(pts).all(axis=1))
    m = finite.size
    if m < 3:
        return normals, angles
    good = np.ascontiguousarray(pts[finite])
    k_eff = min(int(k), m - 1)
    tree = cKDTree(good, balanced_tree=False)
    order = tree.indices
    _, idx = tree.query(good[order], k=k_eff + 1, workers=knn_workers)
    neighbours = np.empty((m, k_eff + 1), dtype=np.int64)
    neighbours[order] = np.asarray(idx, dtype=np.int64).reshape(m, k_eff + 1)
    good_normals = np.empty((m, 3))
    good_angles = np.empty(m)
    lidar_feature_kernels.normal_ray_angles(good, neighbours, k_eff, sensor, good_normals, good_angles)
    normals[finite] = good_normals
    angles[finite] = good_angles
    return normals, angles


def compute_lidar_feature(
    points_xyz: ArrayLike,
    kind: FeatureKind,
    intensity: ArrayLike | None = None,
    k: int = 8,
    sensor_xyz: ArrayLike = (0.0, 0.0, 0.0),
    knn_workers: int = -1,
) -> NDArray[np.float32]:
    """One GOM section-3.1 feature per point, histogram-equalised to [0, 1] (``equalize_rank``).

    Args:
        points_xyz: (N, 3) float points, metres, lidar frame; N may be 0.
        kind: ``intensity`` (return intensity; needs ``intensity``), ``range`` (distance to the sensor)
            or ``normals`` (angle between the PCA normal of the k nearest neighbours and the ray to
            the sensor).
        intensity: (N,) return intensity, for ``kind="intensity"``.
        k: neighbours for ``normals``.
        sensor_xyz: sensor origin in the points' frame, metres.
        knn_workers: threads of the neighbour query for ``normals`` (-1: all cores).

    Returns:
        (N,) float32 in [0, 1]; NaN where the point (or its intensity, or its normal) is undefined.

    Raises:
        InputError: bad shapes or dtypes, unknown kind, missing intensity.
    """
    pts = _check_points(points_xyz)
    if kind not in FEATURE_KINDS:
        raise InputError(f"unknown lidar feature {kind!r}; expected one of {', '.join(FEATURE_KINDS)}")
    n = pts.shape[0]
    if kind == "intensity":
        if intensity is None:
            raise InputError("lidar feature 'intensity' needs the cloud's intensity channel")
        raw = np.asarray(intensity)
        if raw.shape != (n,) or not (np.issubdtype(raw.dtype, np.number) or raw.dtype == np.bool_):
            raise InputError(f"intensity must be a numeric ({n},) array, got {raw.dtype} {raw.shape}")
        values = raw.astype(np.float64)
        values[~np.isfinite(pts).all(axis=1)] = np.nan
    elif kind == "range":
        sensor = _check_sensor(sensor_xyz)
        values = np.linalg.norm(pts - sensor, axis=1)
    else:
        _, values = normal_ray_angles(pts, k=k, sensor_xyz=sensor_xyz, knn_workers=knn_workers)
    return equalize_rank(values)


@dataclass
class LidarFeatureResult:
    """Per-frame result of ``lidar_frame_feature``.

    Attributes:
        stamp_ns: the scan's sensor stamp.
        topic: lidar topic.
        kind: feature kind.
        n_points: points in the scan.
        n_valid: points with a defined (finite) feature.
        feature: (N,) float32 in [0, 1], NaN where undefined.
    """

    stamp_ns: int
    topic: str
    kind: str
    n_points: int
    n_valid: int
    feature: NDArray[np.float32]


def lidar_frame_feature(
    frame: LidarFrame, kind: FeatureKind = "normals", k: int = 8, knn_workers: int = 1
) -> LidarFeatureResult:
    """Engine stage: the ``kind`` feature of one scan.

    ``knn_workers`` defaults to 1 because the engine already runs one single-threaded worker
    process per core; more query threads would only oversubscribe the cores.

    Raises:
        InputError: the scan has no finite points, lacks the intensity channel, or bad data.
    """
    pts = _check_points(frame.points_xyz)
    if pts.shape[0] == 0 or not np.isfinite(pts).all(axis=1).any():
        raise InputError(f"no valid points in the scan at stamp {frame.stamp_ns}")
    feature = compute_lidar_feature(
        pts, kind, intensity=frame.channel("intensity"), k=k, knn_workers=knn_workers
    )
    return LidarFeatureResult(
        stamp_ns=frame.stamp_ns,
        topic=frame.topic,
        kind=kind,
        n_points=int(pts.shape[0]),
        n_valid=int(np.isfinite(feature).sum()),
        feature=feature,
    )


def _check_points(points_xyz: ArrayLike) -> NDArray[np.float64]:
    arr = np.asarray(points_xyz)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"points_xyz must be a float array, got dtype {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"points_xyz must have shape (N, 3), got {arr.shape}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def _check_sensor(sensor_xyz: ArrayLike) -> NDArray[np.float64]:
    sensor = np.asarray(sensor_xyz, dtype=np.float64).ravel()
    if sensor.shape != (3,) or not np.isfinite(sensor).all():
        raise InputError(f"sensor_xyz must be 3 finite numbers, got {sensor_xyz!r}")
    return np.ascontiguousarray(sensor)
