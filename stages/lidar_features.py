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
    """Range-image window of the grid neighbour search (``search="grid"``).

    Attributes:
        half_rows: rings (or elevation bins) searched on each side of the point's own.
        half_cols: azimuth bins searched on each side; the azimuth bin is about one point wide
            (points per row / bins per row ~ 1), so this is about the points seen along the ring.
        max_range_jump: candidates whose range differs from the point's by more than this fraction
            of the point's range are rejected (depth edges).
        elevation_bin_deg: without a ring channel or organised grid the cells are square
            ``elevation_bin_deg`` x ``elevation_bin_deg`` bins of elevation and azimuth, and the
            window is ``elevation_half_rows`` x ``elevation_half_cols`` bins each side.
    """

    half_rows: int = 1
    half_cols: int = 5
    max_range_jump: float = 0.3
    elevation_bin_deg: float = 0.2
    elevation_half_rows: int = 3
    elevation_half_cols: int = 4


def grid_neighbours(
    points_xyz: ArrayLike,
    k: int = 8,
    sensor_xyz: ArrayLike = (0.0, 0.0, 0.0),
    *,
    rings: ArrayLike | None = None,
    organized: tuple[tuple[int, int], ArrayLike] | None = None,
    params: GridSearchParams | None = None,
) -> NDArray[np.int64]:
    """k nearest neighbours (indices, nearest first, -1 padded) from a spherical range-image window.

    Rows are the ``rings`` channel values, else the organised grid's rows (``organized`` =
    ``((height, width), organized_index)``), else elevation bins of ``elevation_bin_deg`` seen from
    ``sensor_xyz``; columns are azimuth bins (the organised grid's columns when organised). The
    candidates of a point are those of the cells within the window, range-gated; the k nearest in
    3D are returned. Equal to the exact k-NN wherever those lie in the window (on a spinning
    lidar: almost everywhere except sparse far ground and depth edges).

    Args:
        points_xyz: (N, 3) finite points, metres.
        k: neighbours per point (>= 1).
        sensor_xyz: sensor origin, same frame.
        rings: optional (N,) integer laser ring per point.
        organized: optional ((height, width), (N,) flat index into the organised grid).
        params: window settings.

    Returns:
        (N, k) int64 indices into ``points_xyz``; -1 where fewer than k candidates were found.

    Raises:
        InputError: bad shapes, non-finite points, k < 1, rings out of range.
    """
    pts = _check_points(points_xyz)
    if not np.isfinite(pts).all():
        raise InputError("grid_neighbours needs finite points (drop NaN points first)")
    if not isinstance(k, (int, np.integer)) or k < 1:
        raise InputError(f"k must be an integer >= 1, got {k!r}")
    n = pts.shape[0]
    ring_arr = None if rings is None else _check_channel(rings, n, "rings")
    org = None if organized is None else (organized[0], _check_channel(organized[1], n, "organized_index"))
    return _grid_neighbours(pts, int(k), _check_sensor(sensor_xyz), ring_arr, org, params or GridSearchParams())


def _grid_neighbours(
    pts: NDArray[np.float64],
    k: int,
    sensor: NDArray[np.float64],
    rings: NDArray[np.int64] | None,
    organized: tuple[tuple[int, int], NDArray[np.int64]] | None,
    params: GridSearchParams,
) -> NDArray[np.int64]:
    n = pts.shape[0]
    out = np.full((n, k), -1, dtype=np.int64)
    if n < 2:
        return out
    rel = pts - sensor
    if organized is not None and rings is None:
        (height, width), index = organized
        if index.min() < 0 or index.max() >= height * width:
            raise InputError(f"organized_index outside the {height}x{width} grid")
        rows, cols = index // width, index % width
        n_rows, n_cols = int(height), int(width)
        half_rows, half_cols = params.half_rows, params.half_cols
    else:
        if rings is not None:
            ring_min = int(rings.min())
            rows = rings - ring_min
            n_rows = int(rows.max()) + 1
            if n_rows > 65536:
                raise InputError(f"ring channel spans {n_rows} values; not laser rings")
        else:
            if not params.elevation_bin_deg > 0:
                raise InputError(f"elevation_bin_deg must be > 0, got {params.elevation_bin_deg}")
            elevation = np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1]))
            rows = np.floor((elevation - elevation.min()) / np.radians(params.elevation_bin_deg)).astype(np.int64)
            n_rows = int(rows.max()) + 1
        half_rows, half_cols = params.half_rows, params.half_cols
        if rings is not None:
            occupied = int(np.count_nonzero(np.bincount(rows, minlength=n_rows)))
            n_cols = max(1, round(n / occupied))
        else:
            n_cols = max(1, round(360.0 / params.elevation_bin_deg))
            half_rows, half_cols = params.elevation_half_rows, params.elevation_half_cols
        azimuth = np.arctan2(rel[:, 1], rel[:, 0])
        cols = np.floor((azimuth + np.pi) * (n_cols / (2.0 * np.pi))).astype(np.int64)
        np.clip(cols, 0, n_cols - 1, out=cols)
    lidar_feature_kernels.grid_neighbours(
        pts, np.ascontiguousarray(rows, dtype=np.int64), np.ascontiguousarray(cols, dtype=np.int64),
        n_rows, n_cols, k, int(half_rows), int(half_cols), float(params.max_range_jump),
        sensor, out,
    )  # fmt: skip
    return out


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
    ranks = rankdata(arr[finite], method="average")
    out[finite] = ((ranks - 1.0) / (n - 1.0)).astype(np.float32)
    return out


def normal_ray_angles(
    points_xyz: ArrayLike,
    k: int = 8,
    sensor_xyz: ArrayLike = (0.0, 0.0, 0.0),
    knn_workers: int = -1,
    *,
    rings: ArrayLike | None = None,
    organized: tuple[tuple[int, int], ArrayLike] | None = None,
    search: NeighbourSearch = "auto",
    grid: GridSearchParams | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """PCA normals of the k nearest neighbours and their angle to the sensor ray.

    Neighbours come from ``scipy.spatial.cKDTree`` over the finite points (``search="kdtree"``;
    query threads ``knn_workers``, -1 = all cores) or from a range-image window (``search="grid"``,
    see ``grid_neighbours``; the k nearest in 3D among the points of a few rings/azimuth bins around
    the point, about 5x faster). ``"auto"`` takes the grid when the scan has a ring channel or is
    organised, else the kd-tree. The covariance is centred at the point (GOM eq. 4) and its smallest
    eigenvector is the normal; where both searches find the same neighbours the outputs are equal.

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
    if search not in ("auto", "kdtree", "grid"):
        raise InputError(f"unknown neighbour search {search!r}; expected auto, kdtree or grid")
    use_grid = search == "grid" or (search == "auto" and (rings is not None or organized is not None))
    if use_grid:
        ring_good = None if rings is None else _check_channel(rings, n, "rings")[finite]
        org_good = None
        if organized is not None:
            org_good = (organized[0], _check_channel(organized[1], n, "organized_index")[finite])
        neighbours = _grid_neighbours(good, k_eff, sensor, ring_good, org_good, grid or GridSearchParams())
    else:
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
        rings, organized, search: neighbour search for ``normals`` (see ``normal_ray_angles``):
            with a ring channel or an organised grid ``"auto"`` uses the range-image window.

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
        _, values = normal_ray_angles(
            pts, k=k, sensor_xyz=sensor_xyz, knn_workers=knn_workers, rings=rings, organized=organized,
            search=search,
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

    For normals the scan's ``ring`` channel or organised grid, when it has one, feeds the grid
    neighbour search (``search="auto"``).

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
