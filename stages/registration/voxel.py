"""Voxel-grid downsampling that averages positions and per-point channels (sort-based, NumPy)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from pipeline.errors import ConfigError, InputError

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_KEY_MASK = (1 << _KEY_BITS) - 1


def voxel_keys(points_xyz: NDArray[np.floating], voxel_size_m: float) -> NDArray[np.int64]:
    """One int64 key per point: the voxel's integer coordinates packed 21 bits each.

    Args:
        points_xyz: (N, 3) points, metres.
        voxel_size_m: edge of a voxel, metres (> 0).

    Returns:
        (N,) int64 keys; equal keys mean the same voxel.

    Raises:
        InputError: points farther than 2^20 voxels from the origin (keys would collide).
    """
    cells = np.floor(np.asarray(points_xyz, dtype=np.float64) / voxel_size_m).astype(np.int64)
    if cells.size and (cells.min() < -_KEY_OFFSET or cells.max() >= _KEY_OFFSET):
        raise InputError(
            f"points span more than {_KEY_OFFSET} voxels of {voxel_size_m} m from the origin; "
            "use a larger voxel size"
        )
    shifted = (cells + _KEY_OFFSET) & _KEY_MASK
    return (shifted[:, 0] << (2 * _KEY_BITS)) | (shifted[:, 1] << _KEY_BITS) | shifted[:, 2]


def voxel_downsample(
    points_xyz: NDArray[np.floating],
    voxel_size_m: float,
    channels: NDArray[np.floating] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Average the points (and their channels) that fall into each voxel of a regular grid.

    Args:
        points_xyz: (N, 3) finite points, metres, any frame.
        voxel_size_m: voxel edge, metres; ``0`` returns the input unchanged (as float64).
        channels: optional (N, n) per-point values averaged like the positions.

    Returns:
        (points (M, 3) float64, channels (M, n) float64 (n = 0 when none), counts (M,) int64 points
        per voxel), voxels in ascending key order (deterministic).

    Raises:
        ConfigError: negative or non-finite voxel size.
        InputError: shapes that do not match.
    """
    if not np.isfinite(voxel_size_m) or voxel_size_m < 0:
        raise ConfigError(f"voxel size must be a finite number >= 0, got {voxel_size_m}")
    pts = np.asarray(points_xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points_xyz must be (N, 3), got {pts.shape}")
    ch = np.zeros((pts.shape[0], 0)) if channels is None else np.asarray(channels, dtype=np.float64)
    if ch.ndim == 1:
        ch = ch[:, None]
    if ch.shape[0] != pts.shape[0]:
        raise InputError(f"channels have {ch.shape[0]} rows for {pts.shape[0]} points")
    if voxel_size_m == 0 or pts.shape[0] == 0:
        return pts.copy(), ch.copy(), np.ones(pts.shape[0], dtype=np.int64)
    keys = voxel_keys(pts, voxel_size_m)
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    values = np.concatenate([pts, ch], axis=1)
    sums = np.zeros((counts.shape[0], values.shape[1]))
    for col in range(values.shape[1]):
        sums[:, col] = np.bincount(inverse, weights=values[:, col], minlength=counts.shape[0])
    means = sums / counts[:, None]
    return means[:, :3].copy(), means[:, 3:].copy(), counts.astype(np.int64)
