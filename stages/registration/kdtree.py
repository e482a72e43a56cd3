"""``KdTree``: nearest-neighbour searches over (N, D) points for registration (numba kernels).

The tree (``kdtree_kernels``) splits nodes at the middle of their longest side. Its arrays (``arrays``)
go straight into the registration kernels, which search it point by point without coming back to
Python (``gicp_kernels.match_linearize_kernel``). A search from a known nearby point climbs from that
point's leaf instead of descending from the root. Searches run on ``workers`` threads (the kernels
release the GIL), cut into slices of the queries.
"""

from __future__ import annotations

import functools
import itertools
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, InputError
from fleetcal.stages.registration.kdtree_kernels import build_kernel, knn_kernel, nearest_kernel, self_knn_kernel

T = TypeVar("T")

MIN_POINTS_PER_THREAD = 2048
"""Queries per thread at least: below that a thread costs more than it saves."""
LEAF_SIZE = 32
"""Points per leaf at most. KITTI HDL-64E scans at 0.25 m voxels (19k points; a 37-49k-point local map):
leaves of 8 to 32 points query within 5 % of each other, and a tree of 32-point leaves builds 17 % faster
than one of 16."""


class KdTree:
    """kd-tree over (N, D) finite float64 points, N >= 1.

    Attributes:
        n: number of points.
        dims: D.
        arrays: (tree_points (N, D), order (N,), leaf_of (N,), node_info (M, 5), node_split (M,),
            node_cell (M, 2, D)) as ``kdtree_kernels.build_kernel`` returns them; ``order[i]`` is the
            input row of tree position ``i``.
    """

    def __init__(self, points: NDArray[np.floating], leaf_size: int = LEAF_SIZE) -> None:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[0] < 1 or pts.shape[1] < 1:
            raise InputError(f"kd-tree points must be (N >= 1, D >= 1), got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise InputError("kd-tree points contain NaN or infinite values")
        if leaf_size < 1:
            raise ConfigError(f"leaf_size must be >= 1, got {leaf_size}")
        self.n, self.dims = pts.shape
        self.arrays: tuple[NDArray[np.generic], ...] = build_kernel(pts, int(leaf_size))

    @property
    def points(self) -> NDArray[np.float64]:
        """(N, D) the points in input order (a copy)."""
        tree_points, order = self.arrays[0], self.arrays[1]
        out = np.empty_like(tree_points)
        out[order] = tree_points
        return out

    def _queries(self, queries: NDArray[np.floating]) -> NDArray[np.float64]:
        q = np.ascontiguousarray(queries, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != self.dims:
            raise InputError(f"queries must be (Q, {self.dims}), got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise InputError("queries contain NaN or infinite values")
        return q

    def nearest(
        self, queries: NDArray[np.floating], max_distance: float = np.inf
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """(distance (Q,), index (Q,)) of the point nearest each query, closer than ``max_distance``;
        inf and -1 where none is."""
        q = self._queries(queries)
        if not max_distance > 0:
            raise ConfigError(f"max_distance must be > 0, got {max_distance}")
        index = np.empty(q.shape[0], dtype=np.int64)
        d2 = np.empty(q.shape[0])
        nearest_kernel(*self.arrays, q, float(max_distance) ** 2, index, d2)
        return np.sqrt(d2), index

    def knn(
        self, queries: NDArray[np.floating], k: int, workers: int = 1
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """(distances (Q, k), indices (Q, k)) of the k points nearest each query, nearest first
        (``workers`` threads, -1: one per core)."""
        q = self._queries(queries)
        self._check_k(k)
        index = np.empty((q.shape[0], k), dtype=np.int64)
        d2 = np.empty((q.shape[0], k))
        in_threads(lambda lo, hi: knn_kernel(*self.arrays, q[lo:hi], index[lo:hi], d2[lo:hi]),
                   split_range(q.shape[0], thread_count(workers)))  # fmt: skip
        return np.sqrt(d2), index

    def self_knn(self, k: int, workers: int = 1) -> NDArray[np.int64]:
        """(N, k) indices of the k points nearest each of the tree's own points (itself included), in no
        particular order within a row (``workers`` threads, -1: one per core)."""
        self._check_k(k)
        index = np.empty((self.n, k), dtype=np.int64)
        in_threads(lambda lo, hi: self_knn_kernel(*self.arrays, lo, hi, index),
                   split_range(self.n, thread_count(workers)))  # fmt: skip
        return index

    def _check_k(self, k: int) -> None:
        if not 1 <= k <= self.n:
            raise InputError(f"k must be between 1 and the {self.n} points of the tree, got {k}")


def thread_count(workers: int) -> int:
    """Threads for a ``workers`` setting (-1: one per core)."""
    return max(1, os.cpu_count() or 1) if workers < 0 else max(1, workers)


def split_range(n: int, threads: int) -> list[tuple[int, int]]:
    """[lo, hi) bounds cutting ``range(n)`` into at most ``threads`` slices of at least
    ``MIN_POINTS_PER_THREAD`` (one slice when n is smaller)."""
    count = max(1, min(threads, n // MIN_POINTS_PER_THREAD))
    edges = [n * k // count for k in range(count + 1)]
    return list(itertools.pairwise(edges))


def in_threads(run: Callable[[int, int], T], slices: list[tuple[int, int]]) -> list[T]:
    """``run(lo, hi)`` of every slice, the first on the calling thread and the others on a pool kept for the
    process (the kernels release the GIL): a registration calls this once per iteration, a few milliseconds
    apart, so starting threads each time would cost as much as the slices save."""
    if len(slices) == 1:
        return [run(*slices[0])]
    others = [_pool().submit(run, *bounds) for bounds in slices[1:]]
    first = run(*slices[0])
    return [first, *(future.result() for future in others)]


@functools.cache
def _pool() -> ThreadPoolExecutor:
    """The process's pool for ``in_threads`` (one thread per core)."""
    return ThreadPoolExecutor(thread_count(-1), thread_name_prefix="fleetcal-slices")
