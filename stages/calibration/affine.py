"""Camera-camera mode (GOM paper 3.2.2): the 2-D affine map between two images that maximises GOM
between their gradients (translation, rotation, scale and shear), found with the same swarm."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, ProcessingError
from fleetcal.stages.calibration import metric_kernels as mk
from fleetcal.stages.calibration.pso import particle_swarm, pattern_search


@dataclass
class AffineResult:
    """Outcome of ``calibrate_affine``.

    Attributes:
        A_base_moving: (2, 3) affine map taking moving-image pixels (u, v, 1) to base-image pixels.
        params: (6,) tx, ty (px), rotation (deg), scale x, scale y, shear, about the moving image centre.
        score, initial_score: GOM at the estimate and at the identity map.
        pixels_used: moving-image pixels in the objective.
        runtime_s: optimisation wall time.
    """

    A_base_moving: NDArray[np.float64]
    params: NDArray[np.float64]
    score: float
    initial_score: float
    pixels_used: int
    runtime_s: float


def affine_matrices(params: NDArray[np.floating], centre_uv: tuple[float, float]) -> NDArray[np.float64]:
    """(P, 2, 3) maps ``x' = R(rot) [[sx, shear], [0, sy]] (x - c) + c + t`` from params (P, 6)."""
    p = np.atleast_2d(np.asarray(params, dtype=np.float64))
    th = np.radians(p[:, 2])
    cos, sin = np.cos(th), np.sin(th)
    L = np.empty((p.shape[0], 2, 2))
    L[:, 0, 0] = cos * p[:, 3]
    L[:, 0, 1] = cos * p[:, 5] - sin * p[:, 4]
    L[:, 1, 0] = sin * p[:, 3]
    L[:, 1, 1] = sin * p[:, 5] + cos * p[:, 4]
    c = np.asarray(centre_uv, dtype=np.float64)
    A = np.empty((p.shape[0], 2, 3))
    A[:, :, :2] = L
    A[:, :, 2] = c - L @ c + p[:, :2]
    return A


def calibrate_affine(base_gx: NDArray[np.floating], base_gy: NDArray[np.floating],
                     moving_gx: NDArray[np.floating], moving_gy: NDArray[np.floating],
                     search_px: float = 20.0, search_deg: float = 5.0, search_scale: float = 0.05,
                     search_shear: float = 0.05, keep_fraction: float = 0.2, n_particles: int = 200,
                     max_iterations: int = 100, seed: int = 0) -> AffineResult:
    """Affine alignment of a moving image to a base image by GOM of their gradients (H, W each).

    The strongest ``keep_fraction`` of the moving image's gradient pixels are mapped into the base
    image; their gradient directions are carried through the map's linear part.
    """
    bgx, bgy = np.asarray(base_gx, dtype=np.float64), np.asarray(base_gy, dtype=np.float64)
    mgx, mgy = np.asarray(moving_gx, dtype=np.float64), np.asarray(moving_gy, dtype=np.float64)
    if bgx.shape != bgy.shape or mgx.shape != mgy.shape or bgx.ndim != 2 or mgx.ndim != 2:
        raise ProcessingError("image gradients must be pairs of equal (H, W) arrays")
    if not 0 < keep_fraction <= 1:
        raise ConfigError("keep_fraction must be in (0, 1]")
    mag = np.hypot(mgx, mgy)
    strong = mag > 0
    if not np.any(strong):
        raise ProcessingError("the moving image has no gradients (blank image)")
    cut = np.quantile(mag[strong], 1.0 - keep_fraction)
    vv, uu = np.nonzero(strong & (mag >= cut))
    pixels = np.ascontiguousarray(np.column_stack([uu, vv]), dtype=np.float64)
    theta = np.arctan2(mgy[vv, uu], mgx[vv, uu])
    c2, s2 = np.ascontiguousarray(np.cos(2 * theta)), np.ascontiguousarray(np.sin(2 * theta))
    weight = np.ascontiguousarray(mag[vv, uu])
    planes = np.ascontiguousarray(np.stack([bgx, bgy], axis=2))
    mask = np.ones(bgx.shape, dtype=np.uint8)
    centre = ((mgx.shape[1] - 1) / 2.0, (mgx.shape[0] - 1) / 2.0)

    def objective(params: NDArray[np.float64]) -> NDArray[np.float64]:
        A = np.ascontiguousarray(affine_matrices(params, centre))
        num, den, _count = mk.gom_affine_batch_kernel(pixels, c2, s2, weight, planes, mask, A)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.asarray(np.where(den > 0, num / (2 * den), 0.0))

    identity = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 0.0])
    half = np.array([search_px, search_px, search_deg, search_scale, search_scale, search_shear])
    start = time.perf_counter()
    swarm = particle_swarm(objective, identity - half, identity + half, n_particles=n_particles,
                           max_iterations=max_iterations, stall_iterations=10, score_tolerance=1e-5,
                           seed=seed, x_initial=identity)
    polish = pattern_search(objective, swarm.best_x, 0.05 * half, identity - half, identity + half,
                            min_step_fraction=0.01, score_at_x0=swarm.best_score)
    runtime = time.perf_counter() - start
    return AffineResult(affine_matrices(polish.best_x, centre)[0], polish.best_x, polish.best_score,
                        float(objective(identity[None])[0]), int(pixels.shape[0]), runtime)
