"""Per-point model covariances for GICP (eq. 4-5) and Multi-Channel GICP (eq. 6-10).

Equation numbers refer to Servos & Waslander, "Multi Channel Generalized-ICP"
(``shared/papers/mc-gicp-servos-waslander.md``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, InputError
from fleetcal.stages.registration.covariance_kernels import (
    gicp_covariances_kernel,
    mcgicp_covariances_kernel,
    voxel_block_covariances_kernel,
)
from fleetcal.stages.registration.kdtree import KdTree
from fleetcal.stages.registration.voxel import KEY_BITS, voxel_keys

MIN_PLANE_VARIANCE_M2 = 1e-10
BLOCK_REACHES = (1, 2)
"""Half-widths, in voxels, of the blocks a voxel's plane is fitted to, nearest first (3 x 3 x 3, then 5 x 5 x 5)."""


def build_kdtree(points: NDArray[np.float64]) -> KdTree:
    """kd-tree over (N, d) points (``KdTree``: numba kernels, middle-of-extent splits)."""
    return KdTree(points)


def knn_indices(
    points_xyz: NDArray[np.float64], k: int, tree: KdTree | None = None, workers: int = -1
) -> NDArray[np.int64]:
    """(N, k) int64 indices of the k nearest neighbours of every point (itself included).

    Args:
        points_xyz: (N, 3) points.
        k: neighbours per point.
        tree: a kd-tree over exactly these points (built when None).
        workers: threads for the search (-1: one per core).

    Raises:
        InputError: fewer than k points, or a tree over another number of points.
    """
    n = points_xyz.shape[0]
    if k < 3:
        raise ConfigError(f"k must be at least 3 to fit a plane, got {k}")
    if n < k:
        raise InputError(f"scan has {n} points, fewer than the k={k} neighbours needed for covariances")
    tree = build_kdtree(points_xyz) if tree is None else tree
    if tree.n != n:
        raise InputError(f"the kd-tree holds {tree.n} points, not the {n} points asked about")
    return tree.self_knn(k, workers=workers)


def _validated_points(points_xyz: NDArray[np.floating]) -> NDArray[np.float64]:
    pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points_xyz must be (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise InputError("points_xyz contains NaN or infinite values; drop them first")
    return pts


def estimate_covariances(
    points_xyz: NDArray[np.floating],
    k: int = 20,
    epsilon: float = 1e-3,
    descriptors: NDArray[np.floating] | None = None,
    descriptor_covariance: NDArray[np.floating] | None = None,
    neighbors: NDArray[np.int64] | None = None,
    workers: int = -1,
) -> NDArray[np.float64]:
    """Model covariance of every point, in the points' frame.

    Without descriptors: the GICP plane model C = U diag(1, 1, eps) U^T (eq. 4-5), U from the SVD
    of the covariance of the k nearest neighbours. With descriptors (N, n) and their measurement
    covariance Lambda (n, n): the MC-GICP model of eq. 6-10, C = U [[Omega, 0], [0, eps]] U^T.

    Args:
        points_xyz: (N, 3) finite points, metres.
        k: neighbours per point (itself included), at least 3.
        epsilon: variance along the normal relative to the unit in-plane variance.
        descriptors: (N, n) descriptor channels, or None for plain GICP.
        descriptor_covariance: (n, n) symmetric positive definite Lambda; needed with descriptors.
        neighbors: precomputed (N, k) neighbour indices (from ``knn_indices``), optional.
        workers: threads for the kd-tree query (-1: all).

    Returns:
        (N, 3, 3) float64 symmetric positive definite covariances.

    Raises:
        InputError: fewer than k points, NaN points, mismatched shapes.
        ConfigError: epsilon <= 0, Lambda not positive definite.
    """
    pts = _validated_points(points_xyz)
    if not (epsilon > 0 and np.isfinite(epsilon)):
        raise ConfigError(f"epsilon must be > 0, got {epsilon}")
    nbrs = knn_indices(pts, k, workers=workers) if neighbors is None else np.ascontiguousarray(neighbors)
    if nbrs.shape != (pts.shape[0], nbrs.shape[1]) or nbrs.shape[1] < 3:
        raise InputError(f"neighbors must be (N, k>=3) for N={pts.shape[0]}, got {nbrs.shape}")
    out = np.empty((pts.shape[0], 3, 3))
    if descriptors is None or np.asarray(descriptors).shape[-1] == 0:
        gicp_covariances_kernel(pts, nbrs.astype(np.int64, copy=False), float(epsilon), out)
        return out
    desc = np.ascontiguousarray(descriptors, dtype=np.float64)
    if desc.ndim == 1:
        desc = desc[:, None]
    if desc.shape[0] != pts.shape[0]:
        raise InputError(f"descriptors have {desc.shape[0]} rows for {pts.shape[0]} points")
    if not np.all(np.isfinite(desc)):
        raise InputError("descriptors contain NaN or infinite values")
    if descriptor_covariance is None:
        raise ConfigError("MC-GICP covariances need the descriptor measurement covariance Lambda")
    lam = np.atleast_2d(np.asarray(descriptor_covariance, dtype=np.float64))
    n = desc.shape[1]
    if lam.shape != (n, n) or not np.allclose(lam, lam.T):
        raise ConfigError(f"descriptor covariance must be a symmetric ({n}, {n}) matrix, got {lam.shape}")
    try:
        np.linalg.cholesky(lam)
    except np.linalg.LinAlgError as err:
        raise ConfigError("descriptor covariance Lambda is not positive definite") from err
    precision = np.ascontiguousarray(np.linalg.inv(lam))
    mcgicp_covariances_kernel(
        pts, desc, nbrs.astype(np.int64, copy=False), precision, float(epsilon), MIN_PLANE_VARIANCE_M2, out
    )
    return out


def voxel_block_covariances(points_xyz: NDArray[np.float64], voxel_size_m: float, k: int, epsilon: float,
                            tree: KdTree, workers: int = 1) -> NDArray[np.float64]:
    """GICP plane covariances (eq. 4-5) of voxel means, each from the means in the smallest block of voxels around
    it (``BLOCK_REACHES``) that holds at least half of ``k`` of them.

    A voxel-downsampled scan holds one point per voxel, so a block's points are a point's neighbours within one
    or two voxel edges, found by walking the sorted voxel keys instead of a k-nearest search. Where no block
    holds k / 2 points (a lone ring far from the lidar, or the edge of the scan) the plane comes from the
    point's ``k`` nearest (``tree``), as in ``estimate_covariances``.

    Args:
        points_xyz: (N, 3) finite voxel means of a ``voxel_size_m`` grid, metres.
        voxel_size_m: the grid's voxel edge (> 0), metres.
        k: the neighbours a plane is fitted to where the blocks are sparse (itself included); a block needs
            k // 2 points.
        epsilon: variance along the normal relative to the unit in-plane variance.
        tree: kd-tree over ``points_xyz``.
        workers: threads for the k-nearest search of the points whose blocks are sparse.

    Returns:
        (N, 3, 3) float64 symmetric positive definite covariances.
    """
    pts = np.ascontiguousarray(points_xyz, dtype=np.float64)
    keys = voxel_keys(pts, voxel_size_m)
    order = None if np.all(keys[1:] > keys[:-1]) else np.argsort(keys, kind="stable")  # downsampled: ascending
    ordered = pts if order is None else np.ascontiguousarray(pts[order])
    ordered_keys = keys if order is None else np.ascontiguousarray(keys[order])
    out = np.empty((pts.shape[0], 3, 3))
    sparse = np.ones(pts.shape[0], dtype=np.bool_)
    for reach in BLOCK_REACHES:
        voxel_block_covariances_kernel(ordered, ordered_keys, KEY_BITS, reach, np.flatnonzero(sparse), float(epsilon),
                                       max(3, k // 2), out, sparse)
    if order is not None:
        out[order], sparse[order] = out.copy(), sparse.copy()
    rows = np.flatnonzero(sparse)
    if rows.size:
        _, nearest = tree.knn(pts[rows], min(k, pts.shape[0]), workers=workers)
        sparse_out = np.empty((rows.size, 3, 3))
        gicp_covariances_kernel(pts, nearest, float(epsilon), sparse_out)
        out[rows] = sparse_out
    return out
