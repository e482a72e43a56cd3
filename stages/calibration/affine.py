"""Camera-camera mode (GOM paper 3.2.2): the 2-D affine map between two images that maximises GOM
between their gradients (translation, rotation, scale and shear), found with the same swarm."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, ProcessingError
from fleetcal.stages.calibration import metric_kernels as mk
from fleetcal.stages.calibration.metrics import ALL_VALID
from fleetcal.stages.calibration.pso import BatchObjective, particle_swarm, pattern_search


@dataclass
class AffineResult:
    """Outcome of ``calibrate_affine``.

    Attributes:
        A_base_moving: (2, 3) affine map taking moving-image pixels (u, v, 1) to base-image pixels.
        params: (6,) tx, ty (px), rotation (deg), scale x, scale y, shear, about the moving image centre.
        score, initial_score: GOM at the estimate and at the identity map.
        pixels_used: moving-image pixels in the objective (all pairs).
        runtime_s: optimisation wall time, seconds.
        pair_params: (pairs, 6) each pair's own optimum polished from ``params`` (one pair: ``params``).
    """

    A_base_moving: NDArray[np.float64]
    params: NDArray[np.float64]
    score: float
    initial_score: float
    pixels_used: int
    runtime_s: float
    pair_params: NDArray[np.float64]


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


GradientPair = tuple[NDArray[np.floating], NDArray[np.floating], NDArray[np.floating]]
"""One image pair's gradients: the base image's (H, W, 2) along u and v (``ImageGradients.gxy``: a C-contiguous
float32 array is shared, not copied), the moving image's along u and along v (H', W') each."""

AFFINE_SWARM_PIXELS = 60_000
"""Moving-image pixels the swarm scores over all pairs together: each pair's strongest pixels thinned evenly to
its share, so one swarm costs the same per pose for 3 pairs or 40; the polish scores every kept pixel."""


@dataclass
class _Pixels:
    """One pair's objective: the moving image's kept pixels (N, 2) (u, v), their gradient orientation as cos / sin
    of twice the angle and magnitude, and the base image's gradient planes (H, W, 2) with its valid mask."""

    uv: NDArray[np.float64]
    c2: NDArray[np.float64]
    s2: NDArray[np.float64]
    weight: NDArray[np.float64]
    planes: NDArray[np.float32]
    mask: NDArray[np.uint8]

    def thinned(self, keep: int) -> _Pixels:
        """Every s-th pixel (row-major order: spread over the image), at most ``keep`` of them."""
        stride = max(1, -(-self.uv.shape[0] // max(keep, 1)))
        return _Pixels(np.ascontiguousarray(self.uv[::stride]), np.ascontiguousarray(self.c2[::stride]),
                       np.ascontiguousarray(self.s2[::stride]), np.ascontiguousarray(self.weight[::stride]),
                       self.planes, self.mask)


def _pair_pixels(pair: GradientPair, keep_fraction: float) -> _Pixels:
    """The strongest ``keep_fraction`` of the moving image's gradient pixels against the base image's planes."""
    planes = np.ascontiguousarray(pair[0], dtype=np.float32)
    mgx, mgy = (np.asarray(a, dtype=np.float64) for a in pair[1:])
    if planes.ndim != 3 or planes.shape[2] != 2 or mgx.shape != mgy.shape or mgx.ndim != 2:
        raise ProcessingError("image gradients must be a base (H, W, 2) array and two equal moving (H, W) arrays")
    mag = np.hypot(mgx, mgy)
    strong = mag > 0
    if not np.any(strong):
        raise ProcessingError("the moving image has no gradients (blank image)")
    cut = np.quantile(mag[strong], 1.0 - keep_fraction)
    vv, uu = np.nonzero(strong & (mag >= cut))
    theta = np.arctan2(mgy[vv, uu], mgx[vv, uu])
    return _Pixels(np.ascontiguousarray(np.column_stack([uu, vv]), dtype=np.float64),
                   np.ascontiguousarray(np.cos(2 * theta)), np.ascontiguousarray(np.sin(2 * theta)),
                   np.ascontiguousarray(mag[vv, uu]), planes, ALL_VALID)


def _gom_objective(views: list[_Pixels], centre: tuple[float, float]) -> BatchObjective:
    """GOM of ``views`` together (sums over every pair's pixels) for a batch of parameters (P, 6)."""
    def objective(params: NDArray[np.float64]) -> NDArray[np.float64]:
        A = np.ascontiguousarray(affine_matrices(params, centre))
        num = np.zeros(A.shape[0])
        den = np.zeros(A.shape[0])
        for v in views:
            n, d, _count = mk.gom_affine_batch_kernel(v.uv, v.c2, v.s2, v.weight, v.planes, v.mask, A)
            num += n
            den += d
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.asarray(np.where(den > 0, num / (2 * den), 0.0))
    return objective


Box = tuple[NDArray[np.float64], NDArray[np.float64]]


def _pair_optima(views: list[_Pixels], centre: tuple[float, float], x: NDArray[np.float64],
                 step: NDArray[np.float64], box: Box) -> NDArray[np.float64]:
    """(pairs, 6) each pair's own optimum polished from ``x`` by steps ``step`` (x itself for one pair)."""
    if len(views) == 1:
        return x[None].copy()
    return np.stack([pattern_search(_gom_objective([v], centre), x, step, box[0], box[1],
                                    min_step_fraction=0.05).best_x for v in views])


def calibrate_affine(base_gx: NDArray[np.floating], base_gy: NDArray[np.floating],
                     moving_gx: NDArray[np.floating], moving_gy: NDArray[np.floating],
                     search_px: float = 20.0, search_deg: float = 5.0, search_scale: float = 0.05,
                     search_shear: float = 0.05, keep_fraction: float = 0.2, n_particles: int = 200,
                     max_iterations: int = 100, seed: int = 0) -> AffineResult:
    """Affine alignment of a moving image to a base image by GOM of their gradients (H, W each)
    (``calibrate_affine_pairs`` of the one pair)."""
    base_gxy = np.stack([np.asarray(base_gx), np.asarray(base_gy)], axis=2)
    return calibrate_affine_pairs([(base_gxy, moving_gx, moving_gy)], search_px, search_deg, search_scale,
                                  search_shear, keep_fraction, n_particles, max_iterations, seed)


def calibrate_affine_pairs(pairs: Sequence[GradientPair], search_px: float = 20.0, search_deg: float = 5.0,
                           search_scale: float = 0.05, search_shear: float = 0.05, keep_fraction: float = 0.2,
                           n_particles: int = 200, max_iterations: int = 100, seed: int = 0) -> AffineResult:
    """One affine map aligning every pair's moving image to its base image: GOM summed over the pairs.

    The strongest ``keep_fraction`` of each moving image's gradient pixels are mapped into its base image; their
    gradient directions are carried through the map's linear part. The swarm scores at most
    ``AFFINE_SWARM_PIXELS`` of them over all pairs, the polish every one. Each pair is then polished alone from
    the estimate: the spread of those optima is ``pair_params``.
    """
    if not pairs:
        raise ProcessingError("no image pairs to align")
    if not 0 < keep_fraction <= 1:
        raise ConfigError("keep_fraction must be in (0, 1]")
    views = [_pair_pixels(pair, keep_fraction) for pair in pairs]
    if len({(v.planes.shape, np.shape(p[1])) for v, p in zip(views, pairs, strict=True)}) != 1:
        raise ProcessingError("every image pair must have the same image sizes")
    height, width = np.shape(pairs[0][1])
    centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    total = sum(v.uv.shape[0] for v in views)
    share = AFFINE_SWARM_PIXELS * np.array([v.uv.shape[0] for v in views]) / total
    search = _gom_objective([v.thinned(int(k)) for v, k in zip(views, share, strict=True)], centre)
    everywhere = _gom_objective(views, centre)
    identity = np.array([0.0, 0.0, 0.0, 1.0, 1.0, 0.0])
    half = np.array([search_px, search_px, search_deg, search_scale, search_scale, search_shear])
    lower, upper = identity - half, identity + half
    start = time.perf_counter()
    swarm = particle_swarm(search, lower, upper, n_particles=n_particles, max_iterations=max_iterations,
                           stall_iterations=10, score_tolerance=1e-5, seed=seed, x_initial=identity)
    polish = pattern_search(everywhere, swarm.best_x, 0.05 * half, lower, upper, min_step_fraction=0.01)
    own = _pair_optima(views, centre, polish.best_x, 0.01 * half, (lower, upper))
    runtime = time.perf_counter() - start
    return AffineResult(affine_matrices(polish.best_x, centre)[0], polish.best_x, polish.best_score,
                        float(everywhere(identity[None])[0]), total, runtime, own)
