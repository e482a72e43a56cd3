"""Settings of a registration and of the scan preparation it needs (``RegistrationConfig``), and the
names they accept. Pure Python: imported by the point-set preparation and the registration alike.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass

import numpy as np

from fleetcal.pipeline.errors import ConfigError

CHANNEL_MODES: dict[str, tuple[str, ...]] = {
    "none": (),
    "intensity": ("intensity",),
    "color": ("r", "g", "b"),
    "combined": ("intensity", "r", "g", "b"),
}
"""Descriptor channels of each channel mode, in column order."""

METHODS = ("gicp", "mcgicp", "color_icp")
ROBUST_KERNEL_NAMES = ("none", "huber", "cauchy")
OPTIMIZERS = ("gauss_newton", "levenberg_marquardt")


@dataclass
class RegistrationConfig:
    """Settings of one registration (and of the scan preparation it needs).

    Attributes:
        method: ``gicp``, ``mcgicp`` or ``color_icp``.
        channels: descriptor channels, ``none`` | ``intensity`` | ``color`` | ``combined``.
        voxel_size_m: voxel-grid downsampling before covariances (0: none).
        k_neighbors: neighbours for each covariance (itself included).
        epsilon: variance along the surface normal (plane model, eq. 4).
        max_correspondence_distance_m: correspondences farther apart (in the search space) are ignored.
        max_iterations: Gauss-Newton iterations (one correspondence search each) at most.
        rotation_eps_deg: converged when the update rotates less than this...
        translation_eps_m: ...and translates less than this.
        robust_kernel: ``none``, ``huber`` or ``cauchy`` on the Mahalanobis distance.
        robust_scale: kernel width (Mahalanobis units).
        optimizer: ``gauss_newton`` or ``levenberg_marquardt``.
        lm_initial_lambda: Levenberg-Marquardt damping at the start.
        channel_weight_m: kd-tree weight alpha_d = channel_weight_m^2 / var_d: one standard deviation
            of a descriptor counts as this many metres in the (3 + n)-D correspondence search.
        channel_alpha: explicit alpha per descriptor channel (overrides ``channel_weight_m``).
        descriptor_variance_scale: Lambda = scale * (descriptor covariance of the scan), eq. 7.
        descriptor_covariance: explicit Lambda (n x n), overrides the estimate.
        degeneracy_threshold: flag a registration degenerate when the Hessian's ``gicp.conditioning`` is below
            it: 0.01, a direction fixed ten times less precisely than the best one (the simulated poster
            corridor's GICP 0.0035, KITTI odometry 00 scan-to-map 0.05-0.26).
        workers: threads for kd-tree queries (-1: all cores).
    """

    method: str = "gicp"
    channels: str = "none"
    voxel_size_m: float = 0.25
    k_neighbors: int = 20
    epsilon: float = 1e-3
    max_correspondence_distance_m: float = 1.0
    max_iterations: int = 64
    rotation_eps_deg: float = 0.1
    translation_eps_m: float = 1e-3
    robust_kernel: str = "none"
    robust_scale: float = 1.0
    optimizer: str = "gauss_newton"
    lm_initial_lambda: float = 1e-4
    channel_weight_m: float = 0.1
    channel_alpha: tuple[float, ...] | None = None
    descriptor_variance_scale: float = 1.0
    descriptor_covariance: tuple[tuple[float, ...], ...] | None = None
    degeneracy_threshold: float = 1e-2
    workers: int = -1

    def __post_init__(self) -> None:
        _one_of("registration method", self.method, METHODS)
        _one_of("channel mode", self.channels, CHANNEL_MODES)
        if self.method in ("mcgicp", "color_icp") and self.channels == "none":
            raise ConfigError(
                f"method {self.method!r} needs descriptor channels (intensity, color or combined)"
            )
        _one_of("robust kernel", self.robust_kernel, ROBUST_KERNEL_NAMES)
        _one_of("optimizer", self.optimizer, OPTIMIZERS)
        positive = {
            "epsilon": self.epsilon,
            "max_correspondence_distance_m": self.max_correspondence_distance_m,
            "robust_scale": self.robust_scale,
            "channel_weight_m": self.channel_weight_m,
            "descriptor_variance_scale": self.descriptor_variance_scale,
        }
        for name, value in positive.items():
            if not (np.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a finite number > 0, got {value}")
        if self.k_neighbors < 3:
            raise ConfigError(f"k_neighbors must be >= 3, got {self.k_neighbors}")
        if self.max_iterations < 1:
            raise ConfigError(f"max_iterations must be >= 1, got {self.max_iterations}")
        if self.voxel_size_m < 0:
            raise ConfigError(f"voxel_size_m must be >= 0, got {self.voxel_size_m}")
        n = len(CHANNEL_MODES[self.channels])
        if self.channel_alpha is not None and len(self.channel_alpha) != n:
            raise ConfigError(f"channel_alpha needs {n} values for channels {self.channels!r}")


def _one_of(what: str, value: str, allowed: Collection[str]) -> None:
    """ConfigError naming ``what`` unless ``value`` is one of ``allowed``."""
    if value not in allowed:
        raise ConfigError(f"unknown {what} {value!r}; expected one of {', '.join(allowed)}")
