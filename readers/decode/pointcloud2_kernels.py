"""Numba kernel for ``readers.decode.pointcloud2`` (private; call ``decode_pointcloud2``).

One pass over a PointCloud2 payload viewed as float32 words: gather x, y, z of the valid points
(finite, not all zero, within the maximum range) and mark which grid cells they came from.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetcal.pipeline.numba_flags import NJIT_FLAGS


@njit(**NJIT_FLAGS)
def gather_xyz_f32(
    words: np.ndarray,
    height: int,
    width: int,
    row_words: int,
    step_words: int,
    x_word: int,
    y_word: int,
    z_word: int,
    points_out: np.ndarray,
    valid_out: np.ndarray,
    max_range_m: float,
) -> int:
    """Copy valid points' x, y, z into ``points_out`` (N, 3) float32 in grid order; returns how many.

    ``words``: the payload as float32 (native order); point (r, c) starts at word
    ``r * row_words + c * step_words``; its x, y, z are ``x_word``/``y_word``/``z_word`` words in.
    ``valid_out`` (height * width,) bool is set per grid cell. Valid: x*x + y*y + z*z (float64) at most
    ``max_range_m`` squared (false for NaN and infinity) and not x = y = z = 0.
    """
    max_r2 = max_range_m * max_range_m
    kept = 0
    for r in range(height):
        row = r * row_words
        for c in range(width):
            base = row + c * step_words
            x = words[base + x_word]
            y = words[base + y_word]
            z = words[base + z_word]
            xd, yd, zd = np.float64(x), np.float64(y), np.float64(z)
            ok = xd * xd + yd * yd + zd * zd <= max_r2 and (x != 0.0 or y != 0.0 or z != 0.0)
            valid_out[r * width + c] = ok
            if ok:
                points_out[kept, 0] = x
                points_out[kept, 1] = y
                points_out[kept, 2] = z
                kept += 1
    return kept
