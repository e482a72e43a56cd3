"""Voxel-grid downsampling that averages positions and per-point channels, and sums of rows per key.

Rows are grouped by their int64 voxel key with a hash table (``voxel_kernels``) and the groups numbered
in ascending key order, so the output does not depend on the input order and each voxel's sum runs
over its rows in input order.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, InputError
from fleetcal.stages.registration.voxel_kernels import (
    accumulate_kernel,
    group_kernel,
    means_kernel,
    rehash_kernel,
    sum_rows_kernel,
    voxel_keys_kernel,
)

G = TypeVar("G", bound=np.generic)

KEY_BITS = 21
_KEY_OFFSET = 1 << (KEY_BITS - 1)
_KEY_MASK = (1 << KEY_BITS) - 1


_KEY_CHUNK = 1 << 20
"""Keys per chunk when coarsening them (temporaries stay ~25 MB whatever the cloud size)."""


def voxel_keys(
    points_xyz: NDArray[np.floating], voxel_size_m: float, valid: NDArray[np.bool_] | None = None
) -> NDArray[np.int64]:
    """One int64 key per point: the voxel's integer coordinates packed 21 bits each.

    One pass over the points in their own dtype (``voxel_kernels.voxel_keys_kernel``): the only
    full-size array made is the (N,) key vector.

    Args:
        points_xyz: (N, 3) points, metres.
        voxel_size_m: edge of a voxel, metres (> 0).
        valid: optional (N,) mask; points outside it (e.g. NaN) get the key ``-1`` (valid keys are >= 0).

    Returns:
        (N,) int64 keys; equal keys mean the same voxel.

    Raises:
        InputError: points farther than 2^20 voxels from the origin (keys would collide), or not finite
            outside ``valid``.
    """
    pts = np.asarray(points_xyz)
    if not np.issubdtype(pts.dtype, np.floating):
        pts = pts.astype(np.float64)
    keys = np.empty(pts.shape[0], dtype=np.int64)
    mask = np.ones(0, dtype=np.bool_) if valid is None else np.ascontiguousarray(valid, dtype=np.bool_)
    if not voxel_keys_kernel(pts, float(voxel_size_m), mask, _KEY_OFFSET, KEY_BITS, keys):
        raise InputError(
            f"points span more than {_KEY_OFFSET} voxels of {voxel_size_m} m from the origin; use a larger voxel size"
        )
    return keys


def coarsen_keys(keys: NDArray[np.int64], levels: int) -> NDArray[np.int64]:
    """Keys of the voxels ``2**levels`` times larger (grids aligned at the origin), in place.

    Each packed coordinate ``c + 2^20`` becomes ``(c + 2^20) >> levels`` = ``floor(c / 2^levels)`` plus
    a constant, so equal coarse keys mean the same coarse voxel. Negative (invalid) keys stay.
    """
    if levels <= 0:
        return keys
    for lo in range(0, keys.shape[0], _KEY_CHUNK):
        chunk = keys[lo : lo + _KEY_CHUNK]
        x = ((chunk >> (2 * KEY_BITS)) & _KEY_MASK) >> levels
        y = ((chunk >> KEY_BITS) & _KEY_MASK) >> levels
        z = (chunk & _KEY_MASK) >> levels
        chunk[:] = np.where(chunk >= 0, (x << (2 * KEY_BITS)) | (y << KEY_BITS) | z, chunk)
    return keys


def voxel_downsample(
    points_xyz: NDArray[np.floating],
    voxel_size_m: float,
    channels: NDArray[np.floating] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Average the points (and their channels) that fall into each voxel of a regular grid.

    Memory-lean (see ``voxel_downsample_capped``): float32 input is not copied to float64.

    Args:
        points_xyz: (N, 3) finite points, metres, any frame (float32 or float64).
        voxel_size_m: voxel edge, metres; ``0`` returns the input unchanged (as float64).
        channels: optional (N, n) per-point values averaged like the positions.

    Returns:
        (points (M, 3) float64, channels (M, n) float64 (n = 0 when none), counts (M,) int64 points
        per voxel), voxels in ascending key order (deterministic).

    Raises:
        ConfigError: negative or non-finite voxel size.
        InputError: shapes that do not match.
    """
    pts, ch, counts, _ = voxel_downsample_capped(points_xyz, voxel_size_m, channels)
    return pts, ch, counts


def voxel_downsample_capped(
    points_xyz: NDArray[np.floating],
    voxel_size_m: float,
    channels: NDArray[np.floating] | None = None,
    *,
    valid: NDArray[np.bool_] | None = None,
    max_voxels: int | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], float]:
    """``voxel_downsample`` with invalid points skipped in place and a cap on the voxels kept.

    When more than ``max_voxels`` voxels are occupied, the voxel edge is doubled (on the integer keys)
    until at most ``max_voxels`` remain, the grouping stopping as soon as the cap is passed (its hash
    table stays within 2 * ``max_voxels`` slots); the means are then taken once over the original
    points. Besides the input, the full-size arrays are the int64 key and the voxel number of each
    point (16 bytes a point); no float64 copy of the cloud and no filtered copy for ``valid`` are made.

    Args:
        points_xyz: (N, 3) points, metres (float32 or float64); finite where ``valid``.
        voxel_size_m: voxel edge, metres; ``0``: no downsampling (the valid points, as float64).
        channels: optional (N, n) per-point values averaged like the positions.
        valid: optional (N,) bool mask of the points to use (default: all).
        max_voxels: optional cap on the voxels kept (ignored when ``voxel_size_m`` is 0).

    Returns:
        (points (M, 3) float64, channels (M, n) float64, counts (M,) int64, voxel edge used in
        metres), voxels in ascending key order.

    Raises:
        ConfigError: negative or non-finite voxel size, max_voxels < 1.
        InputError: shapes that do not match.
    """
    if not np.isfinite(voxel_size_m) or voxel_size_m < 0:
        raise ConfigError(f"voxel size must be a finite number >= 0, got {voxel_size_m}")
    if max_voxels is not None and max_voxels < 1:
        raise ConfigError(f"max_voxels must be >= 1, got {max_voxels}")
    pts = np.asarray(points_xyz)
    if not np.issubdtype(pts.dtype, np.floating):
        pts = pts.astype(np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points_xyz must be (N, 3), got {pts.shape}")
    n = pts.shape[0]
    ch = np.zeros((n, 0)) if channels is None else np.asarray(channels)
    if ch.ndim == 1:
        ch = ch[:, None]
    if ch.shape[0] != n:
        raise InputError(f"channels have {ch.shape[0]} rows for {n} points")
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (n,):
            raise InputError(f"valid mask has shape {valid.shape} for {n} points")
        if valid.all():
            valid = None
    if voxel_size_m == 0 or n == 0 or (valid is not None and not valid.any()):
        if valid is not None:
            pts, ch = pts[valid], ch[valid]
        return (pts.astype(np.float64), ch.astype(np.float64), np.ones(pts.shape[0], dtype=np.int64),
                float(voxel_size_m))  # fmt: skip
    keys = voxel_keys(pts, voxel_size_m, valid)
    group = np.empty(n, dtype=np.int64)
    levels = 0
    while True:  # with a cap: coarser and coarser keys until the voxels fit
        last_try = max_voxels is None or levels == KEY_BITS - 1
        distinct, complete = group_kernel(keys, group, -1 if last_try else max_voxels)
        if complete:
            break
        coarsen_keys(keys, 1)
        levels += 1
    del keys
    rank = _ascending_rank(distinct)
    m = distinct.shape[0]
    out_pts = np.zeros((m, 3))
    out_ch = np.zeros((m, ch.shape[1]))
    counts = np.zeros(m, dtype=np.int64)
    sum_rows_kernel(group, rank, pts, out_pts, counts)
    sum_rows_kernel(group, rank, ch, out_ch, np.zeros(m, dtype=np.int64))
    out_pts /= counts[:, None]
    out_ch /= counts[:, None]
    return out_pts, out_ch, counts, float(voxel_size_m) * 2.0**levels


def _ascending_rank(distinct: NDArray[np.int64]) -> NDArray[np.int64]:
    """(M,) position of each of the distinct keys in ascending order."""
    rank = np.empty(distinct.shape[0], dtype=np.int64)
    rank[np.argsort(distinct)] = np.arange(distinct.shape[0])
    return rank


class VoxelSums:
    """Running sums of rows (c columns) and row counts per voxel key, to which rows are added and from
    which they are removed again (a sliding window of scans), in a hash table (``voxel_kernels``).

    Adding or removing N rows costs O(N), whatever the number of voxels held. Voxels emptied by
    removals keep their slot until they outnumber the occupied ones, then the table is compacted.
    """

    def __init__(self, n_columns: int) -> None:
        self.n_columns = n_columns
        self._n_groups = 0
        self._group_keys = np.zeros(0, dtype=np.int64)
        self._sums = np.zeros((0, n_columns + 1))  # the row count in the last column
        self._table = np.full((16, 2), -1, dtype=np.int64)

    @property
    def n_occupied(self) -> int:
        """Voxels holding at least one row."""
        return int(np.count_nonzero(self._sums[: self._n_groups, -1]))

    def add(self, keys: NDArray[np.int64], values: NDArray[np.floating]) -> None:
        """Add rows (N, c) under their keys (N,) (negative keys: skipped)."""
        self._accumulate(keys, values, 1)

    def remove(self, keys: NDArray[np.int64], values: NDArray[np.floating]) -> None:
        """Remove rows added before (the same keys and values)."""
        self._accumulate(keys, values, -1)
        if self._n_groups > 1024 and self._n_groups > 2 * self.n_occupied:
            self._compact()

    def means(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """(keys (M,), mean rows (M, c)) of the occupied voxels, in no particular order."""
        keys = np.empty(self._n_groups, dtype=np.int64)
        means = np.empty((self._n_groups, self.n_columns))
        m = means_kernel(self._sums, self._n_groups, self._group_keys, keys, means)
        return keys[:m], means[:m]

    def _accumulate(self, keys: NDArray[np.int64], values: NDArray[np.floating], sign: int) -> None:
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        vals = np.asarray(values)
        if vals.ndim != 2 or vals.shape != (keys.shape[0], self.n_columns):
            raise InputError(f"values must be ({keys.shape[0]}, {self.n_columns}), got {vals.shape}")
        need = self._n_groups + keys.shape[0]
        if need > self._sums.shape[0]:
            size = max(need, 2 * self._sums.shape[0])
            self._group_keys = _grown(self._group_keys, size)
            self._sums = _grown(self._sums, size)
        if 2 * need > self._table.shape[0]:
            self._rehash(need)
        self._n_groups = accumulate_kernel(self._table, self._group_keys, self._sums, self._n_groups, keys, vals,
                                           sign)  # fmt: skip

    def _rehash(self, groups: int) -> None:
        size = 16
        while size < 2 * groups:
            size *= 2
        self._table = np.full((size, 2), -1, dtype=np.int64)
        rehash_kernel(self._group_keys, self._n_groups, self._table)

    def _compact(self) -> None:
        keep = np.flatnonzero(self._sums[: self._n_groups, -1] > 0)
        self._n_groups = keep.shape[0]
        self._group_keys = np.ascontiguousarray(self._group_keys[keep])
        self._sums = np.ascontiguousarray(self._sums[keep])
        self._rehash(self._n_groups)


def _grown(values: NDArray[G], rows: int) -> NDArray[G]:
    """``values`` with zero rows appended up to ``rows``."""
    out = np.zeros((rows, *values.shape[1:]), dtype=values.dtype)
    out[: values.shape[0]] = values
    return out
