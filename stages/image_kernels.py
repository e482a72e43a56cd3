"""Numba kernels for ``stages.image_gradients`` (private; call the public wrappers there).

Inputs are C-contiguous arrays and scalars; outputs are written into preallocated arrays.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from fleetcal.pipeline.numba_flags import NJIT_FLAGS


@njit(**NJIT_FLAGS)
def zero_border_and_invalid(gxy: np.ndarray, valid: np.ndarray, use_valid: bool) -> None:
    """Zero the gradients on the 1-px image border and at invalid pixels, in place, so that their
    magnitude and ``atan2(gy, gx)`` are 0 there.

    Args:
        gxy: (H, W, 2) float32 gradient along x (columns) and y (rows).
        valid: (H, W) uint8, non-zero where the gradient is valid; read only when ``use_valid``.
        use_valid: whether ``valid`` applies.
    """
    height = gxy.shape[0]
    width = gxy.shape[1]
    for r in range(height):
        for c in range(width):
            if r == 0 or r == height - 1 or c == 0 or c == width - 1 or (use_valid and valid[r, c] == 0):
                gxy[r, c, 0] = 0.0
                gxy[r, c, 1] = 0.0


def warm_up() -> None:
    """Compile (or load from the cache) every kernel of this module on tiny inputs."""
    zero_border_and_invalid(np.zeros((3, 3, 2), np.float32), np.ones((3, 3), np.uint8), True)
