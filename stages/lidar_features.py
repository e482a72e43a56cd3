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

from fleetcal.pipeline.errors import InputError
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.stages import lidar_feature_kernels

__all__ = [
    "FEATURE_KINDS",
    "FeatureKind",
    "GridSearchParams",
    "LidarFeatureResult",
    "NeighbourSearch",
    "compute_lidar_feature",
    "equalize_rank",
    "grid_neighbours",
    "lidar_frame_feature",
    "normal_ray_angles",
]

FeatureKind = Literal["intensity", "range", "normals"]
FEATURE_KINDS: tuple[str, ...] = get_args(FeatureKind)


NeighbourSearch = Literal["auto", "kdtree", "grid"]


@dataclass(frozen=True)
class GridSearchParams:
    """Window cap of the range-image neighbour search (``search="grid"``).

    Attributes:
        max_half_rows: rows (rings or elevation bins) searched at most on each side of the point's.
        max_half_cols: azimuth bins searched at most on each side; within the cap the search stops
            as soon as nothing farther out can be nearer than the current k-th neighbour.
        elevation_bin_deg: row height (and azimuth bin width) when the scan has no ring channel.
    """

    max_half_rows: int = 6
    max_half_cols: int = 24
    elevation_bin_deg: float = 0.4


@dataclass
class GridNeighbours:
    """Result of ``grid_neighbours``.

    Attributes:
        neighbours: (N, k) int64 indices, nearest first, -1 where fewer than k were found.
        exact: (N,) bool, True where the k are proven to be the k nearest of the whole cloud.
    """

    neighbours: NDArray[np.int64]
    exact: NDArray[np.bool_]


def grid_neighbours(
    points_xyz: ArrayLike,
    k: int = 8,
    sensor_xyz: ArrayLike = (0.0, 0.0, 0.0),
    *,
    rings: ArrayLike | None = None,
    params: GridSearchParams | None = None,
) -> GridNeighbours:
    """k nearest neighbours from a spherical range image, with a proof of exactness per point.

    Rows are the laser rings (``rings``, ordered by their mean elevation), else elevation bins of
    ``elevation_bin_deg`` seen from ``sensor_xyz``; columns are azimuth bins (one point wide per
    ring, or ``elevation_bin_deg`` wide). The search runs outward from the point's cell and skips
    every row or column run whose least possible distance (range x sine of the least angle to it)
    is already beyond the k-th neighbour, so the k found are the exact Euclidean k nearest wherever
    the search ends inside the window cap (``exact``); 87-99% of the real spinning-lidar scans tried.

    Args:
        points_xyz: (N, 3) finite points, metres.
        k: neighbours per point (>= 1).
        sensor_xyz: sensor origin, same frame.
        rings: optional (N,) integer laser ring per point.
        params: window cap and bin size.

    Raises:
        InputError: bad shapes, non-finite points, k < 1.
    """
    pts = _check_points(points_xyz)
    if not np.isfinite(pts).all():
        raise InputError("grid_neighbours needs finite points (drop NaN points first)")
    if not isinstance(k, (int, np.integer)) or k < 1:
        raise InputError(f"k must be an integer >= 1, got {k!r}")
    n = pts.shape[0]
    ring_arr = None if rings is None else _check_channel(rings, n, "rings")
    return _grid_neighbours(pts, int(k), _check_sensor(sensor_xyz), ring_arr, params or GridSearchParams())


def _grid_neighbours(
    pts: NDArray[np.float64],
    k: int,
    sensor: NDArray[np.float64],
    rings: NDArray[np.int64] | None,
    params: GridSearchParams,
) -> GridNeighbours:
    n = pts.shape[0]
    out = np.full((n, k), -1, dtype=np.int64)
    exact = np.zeros(n, dtype=bool)
    if n < 2:
        return GridNeighbours(out, exact)
    if not params.elevation_bin_deg > 0 or params.max_half_rows < 0 or params.max_half_cols < 0:
        raise InputError(f"bad grid search parameters {params}")
    rel = pts - sensor
    elevation = np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1]))
    azimuth = np.arctan2(rel[:, 1], rel[:, 0])
    if rings is not None:
        # rows = rings in order of mean elevation (ring ids need not follow elevation)
        ring_ids, ring_of_point = np.unique(rings, return_inverse=True)
        mean_el = np.bincount(ring_of_point, weights=elevation) / np.bincount(ring_of_point)
        rank = np.empty(ring_ids.shape[0], dtype=np.int64)
        rank[np.argsort(mean_el, kind="stable")] = np.arange(ring_ids.shape[0])
        rows = rank[ring_of_point.ravel()]
        n_rows = int(ring_ids.shape[0])
        n_cols = max(1, round(n / n_rows))
    else:
        bin_rad = np.radians(params.elevation_bin_deg)
        rows = np.floor((elevation - elevation.min()) / bin_rad).astype(np.int64)
        n_rows = int(rows.max()) + 1
        n_cols = max(1, round(360.0 / params.elevation_bin_deg))
    cols = np.floor((azimuth + np.pi) * (n_cols / (2.0 * np.pi))).astype(np.int64)
    np.clip(cols, 0, n_cols - 1, out=cols)
    lidar_feature_kernels.grid_neighbours(
        pts, np.ascontiguousarray(rows), cols, elevation, azimuth, n_rows, n_cols, k,
        int(params.max_half_rows), int(params.max_half_cols), True, sensor, out, exact,
    )  # fmt: skip
    return GridNeighbours(out, exact)


def _check_channel(values: ArrayLike, n: int, name: str) -> NDArray[np.int64]:
    arr = np.asarray(values)
    if arr.shape != (n,) or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise InputError(f"{name} must be a numeric ({n},) array, got {arr.dtype} {arr.shape}")
    if n and not np.isfinite(arr).all():
        raise InputError(f"{name} has non-finite values")
    return np.ascontiguousarray(arr, dtype=np.int64)


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
    _, distinct_of, counts = np.unique(arr[finite], return_inverse=True, return_counts=True)
    below = np.cumsum(counts) - counts  # values smaller than each distinct value
    out[finite] = ((below + (counts - 1) / 2.0) / (n - 1.0))[distinct_of.ravel()].astype(np.float32)
    return out


def normal_ray_angles(
    points_xyz: ArrayLike,
    k: int = 8,
    sensor_xyz: ArrayLike = (0.0, 0.0, 0.0),
    knn_workers: int = -1,
    *,
    rings: ArrayLike | None = None,
    search: NeighbourSearch = "auto",
    grid: GridSearchParams | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """PCA normals of the k nearest neighbours and their angle to the sensor ray.

    Neighbours are the exact Euclidean k nearest among the finite points, from
    ``scipy.spatial.cKDTree`` (``search="kdtree"``; query threads ``knn_workers``, -1 = all cores)
    or from the range-image search (``search="grid"``, see ``grid_neighbours``: exact where it can
    prove it, typically 87-99% of a spinning-lidar scan, the rest queried on the kd-tree;
    single-threaded; ``rings`` order its rows). ``"auto"`` is the kd-tree: on the real scans of
    ../shared/data the grid search is not yet faster (see benchmarks/bench_engine.py). Both give the
    same neighbours (up to distance ties), hence the same normals. The covariance is centred at the
    point (GOM eq. 4) and its smallest eigenvector is the normal.

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
    if search not in ("auto", "kdtree", "grid"):
        raise InputError(f"unknown neighbour search {search!r}; expected auto, kdtree or grid")
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
    use_grid = search == "grid"
    neighbours = np.full((m, k_eff + 1), -1, dtype=np.int64)
    todo = np.arange(m)
    if use_grid:
        ring_good = None if rings is None else _check_channel(rings, n, "rings")[finite]
        found = _grid_neighbours(good, k_eff, sensor, ring_good, grid or GridSearchParams())
        neighbours[:, :k_eff] = found.neighbours
        todo = np.flatnonzero(~found.exact)
    if todo.size:
        # the kd-tree for the points the grid could not prove (all of them without the grid)
        tree = cKDTree(good, balanced_tree=False)
        if todo.size == m:
            todo = tree.indices  # the tree's own order: faster queries
        _, idx = tree.query(good[todo], k=k_eff + 1, workers=knn_workers)
        neighbours[todo] = np.asarray(idx, dtype=np.int64).reshape(todo.size, k_eff + 1)
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
    *,
    rings: ArrayLike | None = None,
    organized: tuple[tuple[int, int], ArrayLike] | None = None,
    search: NeighbourSearch = "auto",
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
        knn_workers: threads of the kd-tree neighbour query for ``normals`` (-1: all cores).
        rings: optional (N,) laser ring per point, for the ``normals`` grid search.
        organized: optional ((height, width), (N,) flat index) of an organised cloud: its rows
            serve as rings when ``rings`` is not given.
        search: neighbour search for ``normals`` (see ``normal_ray_angles``; ``"auto"``: kd-tree).

    Returns:
        (N,) float32 in [0, 1]; NaN where the point (or its intensity, or its normal) is undefined.

    Raises:
        InputError: bad shapes or dtypes, unknown kind, missing intensity.
    """
    pts = _check_points(points_xyz)
    if rings is None and organized is not None:
        (_, width), index = organized
        rings = _check_channel(index, pts.shape[0], "organized_index") // max(1, int(width))
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
        _, values = normal_ray_angles(
            pts, k=k, sensor_xyz=sensor_xyz, knn_workers=knn_workers, rings=rings, search=search,
        )  # fmt: skip
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
    frame: LidarFrame,
    kind: FeatureKind = "normals",
    k: int = 8,
    knn_workers: int = 1,
    search: NeighbourSearch = "auto",
) -> LidarFeatureResult:
    """Engine stage: the ``kind`` feature of one scan.

    For normals with ``search="grid"`` the scan's ``ring`` channel or organised grid, when it has
    one, gives the rows of the range-image search.

    ``knn_workers`` defaults to 1 because the engine already runs one single-threaded worker
    process per core; more query threads would only oversubscribe the cores.

    Raises:
        InputError: the scan has no finite points, lacks the intensity channel, or bad data.
    """
    pts = _check_points(frame.points_xyz)
    if pts.shape[0] == 0 or not np.isfinite(pts).all(axis=1).any():
        raise InputError(f"no valid points in the scan at stamp {frame.stamp_ns}")
    organized = None
    if frame.organized_shape is not None and frame.organized_index is not None:
        organized = (frame.organized_shape, frame.organized_index)
    feature = compute_lidar_feature(
        pts, kind, intensity=frame.channel("intensity"), k=k, knn_workers=knn_workers,
        rings=frame.channel("ring"), organized=organized, search=search,
    )  # fmt: skip
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
