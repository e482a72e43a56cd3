"""Voxel-grid downsampling that averages positions and per-point channels (sort-based, NumPy)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, InputError

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_KEY_MASK = (1 << _KEY_BITS) - 1


_KEY_CHUNK = 1 << 20
"""Points per chunk when computing keys: float64 temporaries stay ~25 MB whatever the cloud size."""


def voxel_keys(
    points_xyz: NDArray[np.floating], voxel_size_m: float, valid: NDArray[np.bool_] | None = None
) -> NDArray[np.int64]:
    """One int64 key per point: the voxel's integer coordinates packed 21 bits each.

    Computed in chunks of ``_KEY_CHUNK`` points (float64 per chunk, the input's dtype is kept), so the
    only full-size array made is the (N,) key vector.

    Args:
        points_xyz: (N, 3) points, metres.
        voxel_size_m: edge of a voxel, metres (> 0).
        valid: optional (N,) mask; points outside it (e.g. NaN) get the key ``-1`` (valid keys are >= 0).

    Returns:
        (N,) int64 keys; equal keys mean the same voxel.

    Raises:
        InputError: points farther than 2^20 voxels from the origin (keys would collide).
    """
    pts = np.asarray(points_xyz)
    keys = np.empty(pts.shape[0], dtype=np.int64)
    for lo in range(0, pts.shape[0], _KEY_CHUNK):
        scaled = pts[lo : lo + _KEY_CHUNK].astype(np.float64) / voxel_size_m
        ok = None if valid is None else valid[lo : lo + _KEY_CHUNK]
        if ok is not None:
            scaled[~ok] = 0.0
        cells = np.floor(scaled).astype(np.int64)
        if cells.size and (cells.min() < -_KEY_OFFSET or cells.max() >= _KEY_OFFSET):
            raise InputError(
                f"points span more than {_KEY_OFFSET} voxels of {voxel_size_m} m from the origin; "
                "use a larger voxel size"
            )
        cells += _KEY_OFFSET
        cells &= _KEY_MASK
        chunk = (cells[:, 0] << (2 * _KEY_BITS)) | (cells[:, 1] << _KEY_BITS) | cells[:, 2]
        if ok is not None:
            chunk[~ok] = -1
        keys[lo : lo + _KEY_CHUNK] = chunk
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
        x = ((chunk >> (2 * _KEY_BITS)) & _KEY_MASK) >> levels
        y = ((chunk >> _KEY_BITS) & _KEY_MASK) >> levels
        z = (chunk & _KEY_MASK) >> levels
        chunk[:] = np.where(chunk >= 0, (x << (2 * _KEY_BITS)) | (y << _KEY_BITS) | z, chunk)
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

    When more than ``max_voxels`` voxels are occupied, the voxel edge is doubled (on the integer
    keys, no pass over the points) until at most ``max_voxels`` remain; the means are then taken
    once over the original points. Besides the input, the full-size arrays are the int64 keys, one
    sort permutation and the voxel index of each point (about 24 bytes a point) and one float64
    column at a time; no float64 copy of the cloud and no filtered copy for ``valid`` are made.

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
    # the sort only numbers the voxels (ascending key); the sums run in point order (bincount).
    # Buffers are reused: the sorted keys become the voxel numbers, the keys the per-point index.
    order = np.argsort(keys)
    voxel_ids = keys[order]
    levels = 0
    if max_voxels is not None:
        occupied = _unique_sorted(voxel_ids)
        while occupied.shape[0] > max_voxels and levels < _KEY_BITS - 1:
            levels += 1
            occupied = _unique_sorted(np.sort(coarsen_keys(occupied, 1)))
        del occupied
        if levels:  # sort again on the coarser keys (only for scans over the cap)
            coarsen_keys(keys, levels)
            order = np.argsort(keys)
            voxel_ids = keys[order]
    starts = np.empty(n, dtype=bool)
    starts[0] = True
    np.not_equal(voxel_ids[1:], voxel_ids[:-1], out=starts[1:])
    skip = 1 if valid is not None else 0  # the invalid points (key -1) sort first: group 0
    np.cumsum(starts, out=voxel_ids)
    del starts
    voxel_ids -= 1
    m = int(voxel_ids[-1]) + 1
    inverse = keys
    inverse[order] = voxel_ids
    del order, voxel_ids, keys
    counts = np.bincount(inverse, minlength=m)[skip:]
    out_pts = np.empty((m - skip, 3))
    out_ch = np.empty((m - skip, ch.shape[1]))
    for out, values in [(out_pts, pts), (out_ch, ch)]:
        for col in range(values.shape[1]):
            out[:, col] = np.bincount(inverse, weights=values[:, col], minlength=m)[skip:]
            out[:, col] /= counts
    return out_pts, out_ch, counts.astype(np.int64), float(voxel_size_m) * 2.0**levels


def _unique_sorted(sorted_keys: NDArray[np.int64]) -> NDArray[np.int64]:
    """Distinct non-negative (valid) values of a sorted key array."""
    keep = np.empty(sorted_keys.shape[0], dtype=bool)
    if keep.size:
        keep[0] = True
        np.not_equal(sorted_keys[1:], sorted_keys[:-1], out=keep[1:])
        keep &= sorted_keys >= 0
    return sorted_keys[keep]
