"""Numba kernels for ``stages.image_gradients`` (private; call the public wrappers there).

Inputs are C-contiguous arrays and scalars; outputs are written into preallocated arrays.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from pipeline.numba_flags import NJIT_FLAGS


@njit(**NJIT_FLAGS)
def gradient_magnitude(
    gx: np.ndarray,
    gy: np.ndarray,
    valid: np.ndarray,
    use_valid: bool,
    magnitude: np.ndarray,
) -> None:
    """Gradient magnitude, zeroing the 1-px image border and invalid pixels.

    Args:
        gx, gy: (H, W) float32 gradient along x (columns) and y (rows); zeroed in place on the border
            and where invalid, so that ``atan2(gy, gx)`` is 0 there.
        valid: (H, W) uint8, non-zero where the gradient is valid; read only when ``use_valid``.
        use_valid: whether ``valid`` applies.
        magnitude: (H, W) float32 output, ``sqrt(gx**2 + gy**2)``.
    """
    height, width = gx.shape
    for r in range(height):
        if r == 0 or r == height - 1:
            for c in range(width):
                gx[r, c] = 0.0
                gy[r, c] = 0.0
                magnitude[r, c] = 0.0
            continue
        if use_valid:
            for c in range(width):
                if valid[r, c] == 0:
                    gx[r, c] = 0.0
                    gy[r, c] = 0.0
        gx[r, 0] = 0.0
        gy[r, 0] = 0.0
        gx[r, width - 1] = 0.0
        gy[r, width - 1] = 0.0
        for c in range(width):
            x = gx[r, c]
            y = gy[r, c]
            magnitude[r, c] = math.sqrt(x * x + y * y)


def warm_up() -> None:
    """Compile (or load from the cache) every kernel of this module on tiny inputs."""
    a = np.zeros((3, 3), np.float32)
    gradient_magnitude(a, a.copy(), np.ones((3, 3), np.uint8), True, a.copy())
