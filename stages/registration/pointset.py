"""``PointSet``: a scan prepared once for registration (downsampled, descriptors, covariances).

The same PointSet serves as source of one pair and target of the next; its kd-trees are built
lazily and cached.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, InputError
from fleetcal.pipeline.frames import LidarFrame
from fleetcal.stages.registration.config import CHANNEL_MODES, RegistrationConfig
from fleetcal.stages.registration.covariance_kernels import moved_rows_kernel
from fleetcal.stages.registration.covariances import (
    build_kdtree,
    estimate_covariances,
    knn_indices,
    voxel_block_covariances,
)
from fleetcal.stages.registration.kdtree import KdTree
from fleetcal.stages.registration.voxel import voxel_downsample_capped

log = logging.getLogger(__name__)

MAX_PREPARED_POINTS = 500_000
"""Most points a prepared scan keeps: a scan still larger after voxel downsampling is downsampled
again with the voxel doubled until it fits (bounds memory and time of the covariances, e.g. for
a 10M-point scan with little structure at the voxel size)."""

MIN_CHANNEL_VARIANCE = 1e-12
POINT_TO_POINT_VARIANCE = 0.5
"""Covariance 0.5 I on both sides gives W = I: Color-ICP's point-to-point cost."""


def channel_names_for(mode: str) -> tuple[str, ...]:
    """Descriptor channel names of a channel mode; ConfigError for an unknown mode."""
    try:
        return CHANNEL_MODES[mode]
    except KeyError as err:
        raise ConfigError(
            f"unknown channel mode {mode!r}; expected one of {', '.join(CHANNEL_MODES)}"
        ) from err


@dataclass
class PointSet:
    """A scan ready for registration.

    Attributes:
        points_xyz: (N, 3) float64 points, metres, scan frame.
        channels: (N, n) float64 descriptors in ``channel_names`` order (intensity as recorded,
            colour scaled to [0, 1]); n = 0 for plain GICP.
        covariances: (N, 3, 3) float64 model covariances (GICP eq. 4-5 or MC-GICP eq. 6-10).
        channel_names: names of the descriptor columns.
        descriptor_covariance: (n, n) Lambda used for the MC-GICP kernel weights (eq. 7).
        channel_variance: (n,) variance of each descriptor over the scan (sets kd-tree weights).
        dropped_points: non-finite points removed before downsampling.
        stamp_ns: scan time, ns (0 when unknown).
        frame_id: frame of ``points_xyz``.
        times_s: (N,) capture time of each point minus ``stamp_ns`` (the mean over its voxel), seconds;
            None when the scan has no per-point time (``deskew`` needs it).
    """

    points_xyz: NDArray[np.float64]
    channels: NDArray[np.float64]
    covariances: NDArray[np.float64]
    channel_names: tuple[str, ...] = ()
    descriptor_covariance: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 0)))
    channel_variance: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    dropped_points: int = 0
    stamp_ns: int = 0
    frame_id: str = ""
    times_s: NDArray[np.float64] | None = None
    _tree: KdTree | None = field(default=None, init=False, repr=False, compare=False)
    _feature_trees: dict[tuple[float, ...], KdTree] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    @property
    def n_points(self) -> int:
        return int(self.points_xyz.shape[0])

    @property
    def tree(self) -> KdTree:
        """kd-tree over ``points_xyz`` (built on first use)."""
        if self._tree is None:
            self._tree = build_kdtree(self.points_xyz)
        return self._tree

    def scaled_descriptors(self, channel_alpha: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, n) descriptors multiplied by sqrt(alpha) (the weighted kd-tree coordinates)."""
        return self.channels * np.sqrt(channel_alpha)[None, :]

    def feature_tree(self, channel_alpha: NDArray[np.float64]) -> KdTree:
        """kd-tree over (3 + n)-D points [xyz, sqrt(alpha) * descriptors] (cached per alpha)."""
        key = tuple(float(a) for a in channel_alpha)
        tree = self._feature_trees.get(key)
        if tree is None:
            features = np.concatenate([self.points_xyz, self.scaled_descriptors(channel_alpha)], axis=1)
            tree = build_kdtree(features)
            self._feature_trees[key] = tree
        return tree


def finite_rows(values: NDArray[np.floating]) -> NDArray[np.bool_]:
    """(N,) bool: whether each row of ``values`` (N, c) is finite. One check of the whole array comes
    first: when all of it is finite (the usual case) no reduction per row is made (NumPy's row-wise
    ``all`` over an (N, 3) array takes about 50 times as long)."""
    if np.isfinite(values).all():
        return np.ones(values.shape[0], dtype=bool)
    return np.asarray(np.isfinite(values).all(axis=1))


def _descriptor_columns(
    n_points: int, channels: Mapping[str, NDArray[np.generic]] | None, names: tuple[str, ...]
) -> NDArray[np.float64]:
    columns = []
    available = {} if channels is None else channels
    for name in names:
        if name not in available:
            have = ", ".join(sorted(available)) or "none"
            raise InputError(f"scan has no {name!r} channel (channels: {have})")
        values = np.asarray(available[name])
        if values.shape != (n_points,):
            raise InputError(f"channel {name!r} has shape {values.shape}, expected ({n_points},)")
        column = values.astype(np.float64)
        if name in ("r", "g", "b") and (
            np.issubdtype(values.dtype, np.integer) or column.max(initial=0) > 1.0
        ):
            column = column / 255.0
        columns.append(column)
    if not columns:
        return np.zeros((n_points, 0))
    return np.stack(columns, axis=1)


def _descriptor_covariance(
    descriptors: NDArray[np.float64], mode: str, scale: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(Lambda (n, n), per-channel variance (n,)) estimated from the scan (paper section IV).

    intensity: the variance of the intensities. color: equal independent RGB variances (their mean).
    combined: the full empirical covariance of (intensity, r, g, b), inter-channel terms included.
    """
    n = descriptors.shape[1]
    if n == 0:
        return np.zeros((0, 0)), np.zeros(0)
    variance = np.maximum(descriptors.var(axis=0), MIN_CHANNEL_VARIANCE)
    if mode == "color":
        lam = np.eye(3) * float(variance.mean())
    elif mode == "combined":
        lam = np.atleast_2d(np.cov(descriptors, rowvar=False, bias=True))
        lam = lam + np.eye(n) * MIN_CHANNEL_VARIANCE
    else:
        lam = np.diag(variance)
    return lam * scale, variance


def prepare_pointset(
    points_xyz: NDArray[np.floating],
    channels: Mapping[str, NDArray[np.generic]] | None,
    config: RegistrationConfig,
    *,
    stamp_ns: int = 0,
    frame_id: str = "",
    max_points: int | None = MAX_PREPARED_POINTS,
    times_s: NDArray[np.generic] | None = None,
) -> PointSet:
    """Drop non-finite points, voxel-downsample (averaging descriptors) and compute covariances.

    Voxel downsampling comes first and is memory-lean (float32 points stay float32 until the voxel
    means; see ``voxel_downsample``); covariances are computed on the downsampled points only. When
    more than ``max_points`` voxels are occupied (and the voxel size is > 0) the voxel size is doubled
    until at most ``max_points`` remain (``voxel_downsample_capped``; a warning is logged).

    Args:
        points_xyz: (N, 3) points, metres, scan frame.
        channels: per-point arrays by name (``intensity``, ``r``, ``g``, ``b``), as in LidarFrame.
        config: registration settings (method, channels, voxel size, k, epsilon, Lambda).
        max_points: cap on the prepared points (None: no cap).
        times_s: optional (N,) per-point time minus the stamp, seconds: averaged per voxel into
            ``PointSet.times_s`` (ignored unless finite at every kept point).

    Raises:
        InputError: wrong shapes, a missing channel, fewer than k points after downsampling.
        ConfigError: unknown channel mode.
    """
    names = channel_names_for(config.channels)
    pts = np.asarray(points_xyz)
    if not np.issubdtype(pts.dtype, np.floating):
        pts = pts.astype(np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points_xyz must be (N, 3), got {pts.shape}")
    desc = _descriptor_columns(pts.shape[0], channels, names)
    finite = finite_rows(pts)
    if desc.shape[1]:
        finite &= finite_rows(desc)
    dropped = int(pts.shape[0] - np.count_nonzero(finite))
    pts, desc, voxel_times, voxel_m = _downsampled(pts, desc, finite, _time_column(times_s, finite), config,
                                                   max_points, stamp_ns)
    if pts.shape[0] < config.k_neighbors:
        raise InputError(
            f"scan has {pts.shape[0]} points after dropping {dropped} non-finite ones and "
            f"{config.voxel_size_m} m voxel downsampling; at least k={config.k_neighbors} are needed"
        )
    if config.descriptor_covariance is not None and len(names) > 0:
        lam = np.atleast_2d(np.asarray(config.descriptor_covariance, dtype=np.float64))
        variance = np.maximum(desc.var(axis=0), MIN_CHANNEL_VARIANCE)
    else:
        lam, variance = _descriptor_covariance(desc, config.channels, config.descriptor_variance_scale)
    pts = np.ascontiguousarray(pts)
    tree = None
    if config.method == "color_icp":
        cov = np.broadcast_to(np.eye(3) * POINT_TO_POINT_VARIANCE, (pts.shape[0], 3, 3)).copy()
    else:
        tree = build_kdtree(pts)  # the neighbour search's tree is the registration target's tree too
        cov = _model_covariances(pts, desc, lam, voxel_m, tree, config)
    prepared = PointSet(
        points_xyz=np.ascontiguousarray(pts),
        channels=np.ascontiguousarray(desc),
        covariances=cov,
        channel_names=names,
        descriptor_covariance=lam,
        channel_variance=variance,
        dropped_points=dropped,
        stamp_ns=stamp_ns,
        frame_id=frame_id,
        times_s=voxel_times,
    )
    prepared._tree = tree
    return prepared


def _downsampled(pts: NDArray[np.floating], desc: NDArray[np.float64], finite: NDArray[np.bool_],
                 times: NDArray[np.float64] | None, config: RegistrationConfig, max_points: int | None,
                 stamp_ns: int) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None, float]:
    """The finite points voxel-downsampled (``voxel_downsample_capped``) with their descriptors and per-point
    times averaged per voxel: points, descriptors, times (None without) and the voxel edge used (m; a warning
    where the cap made it coarser than the settings')."""
    if times is not None:
        desc = np.concatenate([desc, times[:, None]], axis=1)
    pts, desc, _, voxel_m = voxel_downsample_capped(
        pts, config.voxel_size_m, desc, valid=finite, max_voxels=max_points
    )
    voxel_times = None
    if times is not None:
        voxel_times, desc = np.ascontiguousarray(desc[:, -1]), desc[:, :-1]
    if voxel_m != config.voxel_size_m:
        log.warning(
            "scan at %d keeps %d points only with %.3g m voxels (not %.3g m): more than max_points=%d",
            stamp_ns, pts.shape[0], voxel_m, config.voxel_size_m, max_points,
        )  # fmt: skip
    return pts, desc, voxel_times, voxel_m


def _model_covariances(pts: NDArray[np.float64], desc: NDArray[np.float64], lam: NDArray[np.float64], voxel_m: float,
                       tree: KdTree, config: RegistrationConfig) -> NDArray[np.float64]:
    """(M, 3, 3) model covariances of downsampled points ``pts`` (voxel edge ``voxel_m``, 0: not downsampled):
    GICP planes from each voxel's block of voxels (``voxel_block_covariances``), MC-GICP's from the k nearest
    with their descriptors ``desc`` and measurement covariance ``lam``."""
    if config.method == "gicp" and voxel_m > 0:
        return voxel_block_covariances(pts, voxel_m, config.k_neighbors, config.epsilon, tree, config.workers)
    nbrs = knn_indices(pts, config.k_neighbors, tree=tree, workers=config.workers)
    return estimate_covariances(pts, config.k_neighbors, config.epsilon, desc if config.method == "mcgicp" else None,
                                lam, neighbors=nbrs, workers=config.workers)


def transformed_pointset(scan: PointSet, T_new_scan: NDArray[np.float64]) -> PointSet:
    """``scan`` moved into another frame: points p' = R p + t, covariances R C R^T (descriptors kept)."""
    T = np.asarray(T_new_scan, dtype=np.float64)
    R = T[:3, :3]
    return dataclasses.replace(
        scan,
        points_xyz=np.ascontiguousarray(scan.points_xyz @ R.T + T[:3, 3]),
        covariances=np.ascontiguousarray(np.matmul(np.matmul(R, scan.covariances), R.T)),
    )


def moved_rows(scan: PointSet, T_new_scan: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 3 + n + 9) rows [R p + t, descriptors, R C R^T flattened] of ``scan`` moved into another frame
    (``transformed_pointset`` as one array: the columns that ``merge_pointsets`` averages)."""
    n = scan.channels.shape[1]
    rows = np.empty((scan.n_points, 12 + n))
    moved_rows_kernel(scan.points_xyz, np.ascontiguousarray(scan.covariances), np.ascontiguousarray(T_new_scan),
                      rows[:, :3], rows[:, 3 + n :])  # fmt: skip
    rows[:, 3 : 3 + n] = scan.channels
    return rows


def pointset_from_rows(
    rows: NDArray[np.float64], names: tuple[str, ...], config: RegistrationConfig, stamp_ns: int, frame_id: str
) -> PointSet:
    """PointSet of rows [position, descriptors, covariance flattened] (``moved_rows``, or their means per
    voxel); Lambda and the channel variances are those of these descriptors."""
    n = len(names)
    desc = np.ascontiguousarray(rows[:, 3 : 3 + n])
    if config.descriptor_covariance is not None and n > 0:
        lam = np.atleast_2d(np.asarray(config.descriptor_covariance, dtype=np.float64))
        variance = np.maximum(desc.var(axis=0), MIN_CHANNEL_VARIANCE)
    else:
        lam, variance = _descriptor_covariance(desc, config.channels, config.descriptor_variance_scale)
    return PointSet(
        points_xyz=np.ascontiguousarray(rows[:, :3]), channels=desc,
        covariances=np.ascontiguousarray(rows[:, 3 + n :]).reshape(-1, 3, 3), channel_names=names,
        descriptor_covariance=lam, channel_variance=variance, stamp_ns=stamp_ns, frame_id=frame_id,
    )  # fmt: skip


def merge_pointsets(scans: Sequence[PointSet], config: RegistrationConfig, frame_id: str = "map") -> PointSet:
    """One PointSet of several prepared scans already in a common frame, voxel-downsampled at the
    registration voxel size: positions, descriptors and covariances are averaged per voxel (a mean of
    positive definite covariances stays positive definite); Lambda and the channel variances are those
    of the merged descriptors. No neighbour search: the covariances are the scans' own.

    Raises:
        InputError: no scans, or scans prepared with different channels.
    """
    if not scans:
        raise InputError("no scans to merge")
    names = scans[0].channel_names
    if any(s.channel_names != names for s in scans):
        raise InputError("scans to merge were prepared with different channels")
    points = np.concatenate([s.points_xyz for s in scans])
    columns = np.concatenate(
        [np.concatenate([s.channels, s.covariances.reshape(-1, 9)], axis=1) for s in scans]
    )
    points, columns, _, _ = voxel_downsample_capped(points, config.voxel_size_m, columns)
    return pointset_from_rows(np.concatenate([points, columns], axis=1), names, config, scans[-1].stamp_ns, frame_id)


def _time_column(times_s: NDArray[np.generic] | None, valid: NDArray[np.bool_]) -> NDArray[np.float64] | None:
    """Per-point times as float64 (N,) (0 at invalid points), or None when absent, misshapen or not
    finite at every valid point."""
    if times_s is None:
        return None
    times = np.asarray(times_s, dtype=np.float64)
    if times.shape != valid.shape or not np.all(np.isfinite(times[valid])):
        return None
    return np.where(valid, times, 0.0)


def pointset_from_frame(
    frame: LidarFrame, config: RegistrationConfig, max_points: int | None = MAX_PREPARED_POINTS
) -> PointSet:
    """``prepare_pointset`` on a LidarFrame (its channels, stamp, frame id and per-point ``time``)."""
    pointset = prepare_pointset(
        frame.points_xyz, frame.channels, config, stamp_ns=frame.stamp_ns, frame_id=frame.frame_id,
        max_points=max_points, times_s=frame.channels.get("time"),
    )  # fmt: skip
    pointset.dropped_points += frame.dropped_points
    return pointset
