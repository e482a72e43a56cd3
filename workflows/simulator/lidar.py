"""Lidar models (spinning multi-beam, or a non-repetitive rosette): ray layout, ray casting, range noise,
intensity, dropouts.

Lidar frame: x forward, y left, z up. Column ``c`` fires at ``c / columns`` of the scan period after the
scan stamp. Spinning: column ``c`` points at azimuth ``2 pi c / columns`` (counter-clockwise from +x);
ring 0 is the lowest beam; the grid has one row per ring (row = ring) and one column per firing.
Rosette (a forward-looking Risley-prism lidar such as a Livox Mid-70 / Avia): each row is one laser
line tracing the sum of two counter-rotating prism deflections, a flower of petals that precess from
scan to scan and so fill the circular field of view over time; rows are lines, not rings.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError
from fleetcal.workflows.simulator.raycast import TriangleGrid, cast_rays
from fleetcal.workflows.simulator.scene import Scene, surface_properties

SUPPORTED_BEAMS = (16, 32, 64, 128)
LidarPattern = Literal["spinning", "rosette"]
LIDAR_PATTERNS: tuple[str, ...] = ("spinning", "rosette")
MAX_ROSETTE_LINES = 16
DEFAULT_LAYOUT: dict[str, tuple[int, int]] = {"spinning": (64, 1024), "rosette": (6, 4000)}
"""Rings (lines) and columns (samples per scan) of each pattern when not given: a 64-beam spinning lidar; a
rosette of 6 lines x 4000, the 24k points per 0.1 s scan of a Livox Avia."""
ROSETTE_HALF_ANGLE_DEG = 35.2
"""Half the circular field of view of the rosette (a Livox Mid-70's 70.4 deg)."""
ROSETTE_PRISM_HZ = (97.3, 63.1)
"""Rotation rates of the two prisms (opposite senses): each line passes the centre 16 times per 0.1 s scan,
in 5 lobes (the ratio is near 3/2) that turn from scan to scan, so the pattern fills the field of view
over about a second instead of repeating."""


def beam_elevations_deg(beams: int) -> NDArray[np.float64]:
    """Vertical beam angles (degrees, ascending) of a real-sensor-like layout.

    16: VLP-16 (-15..15, 2 deg). 32: HDL-32E (-30.67..10.67, 1.33 deg). 64: HDL-64E (-24.8..2: upper
    block at 1/3 deg down to -8.33, lower block at 1/2 deg). 128: VLS-128-like (-25..15, dense near 0).
    """
    if beams == 16:
        return np.linspace(-15.0, 15.0, 16)
    if beams == 32:
        return np.linspace(-30.67, 10.67, 32)
    if beams == 64:
        upper = np.linspace(2.0, -8.33, 32)
        lower = np.linspace(-8.83, -24.8, 32)
        return np.sort(np.concatenate([upper, lower]))
    if beams == 128:
        u = np.linspace(-1.0, 1.0, 128)
        return np.sort(np.where(u < 0, -25.0, 15.0) * np.abs(u) ** 1.6)
    raise ConfigError(f"unsupported beam count {beams} (choose from {', '.join(map(str, SUPPORTED_BEAMS))})")


@dataclass(frozen=True)
class LidarModel:
    """Sensor parameters.

    Attributes:
        beams, columns: rings and firings per revolution (``rosette``: laser lines, 1..16, and samples per
            line and scan).
        period_s: one revolution (0.1 s for 10 Hz); one scan of the rosette.
        range_noise_m: standard deviation of the range noise.
        max_range_m, min_range_m: no return beyond / before these.
        dropout: probability that a valid return is lost at random.
        gain_spread: standard deviation of the per-beam intensity gain (relative).
        seed: seeds the per-beam gains.
    """

    beams: int = 64
    columns: int = 1024
    period_s: float = 0.1
    range_noise_m: float = 0.015
    max_range_m: float = 100.0
    min_range_m: float = 0.5
    dropout: float = 0.01
    gain_spread: float = 0.08
    seed: int = 0
    pattern: LidarPattern = "spinning"

    def __post_init__(self) -> None:
        if self.pattern == "rosette":
            if not 1 <= self.beams <= MAX_ROSETTE_LINES:
                raise ConfigError(f"a rosette lidar has 1..{MAX_ROSETTE_LINES} lines, got {self.beams}")
        elif self.pattern == "spinning":
            beam_elevations_deg(self.beams)
        else:
            raise ConfigError(f"unknown lidar pattern {self.pattern!r} (choose from {', '.join(LIDAR_PATTERNS)})")
        if not 64 <= self.columns <= 4096:
            raise ConfigError(f"lidar columns must be in 64..4096, got {self.columns}")

    @property
    def elevations_deg(self) -> NDArray[np.float64]:
        return beam_elevations_deg(self.beams)

    @property
    def beam_gains(self) -> NDArray[np.float64]:
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, self.beams, 0x6A1]))
        return np.clip(1.0 + self.gain_spread * rng.standard_normal(self.beams), 0.6, 1.4)

    def directions(self, scan_start_s: float = 0.0) -> NDArray[np.float64]:
        """(beams, columns, 3) unit ray directions in the lidar frame of the scan that starts at
        ``scan_start_s`` (seconds on the sensor's clock; only the rosette, whose prisms keep turning
        from scan to scan, depends on it)."""
        if self.pattern == "rosette":
            return self._rosette_directions(scan_start_s)
        el = np.radians(self.elevations_deg)[:, None]
        az = 2 * np.pi * np.arange(self.columns)[None, :] / self.columns
        return np.stack(
            np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)),
            axis=-1,
        )

    def _rosette_directions(self, scan_start_s: float) -> NDArray[np.float64]:
        """Two counter-rotating prisms, each deflecting by half the field of view: the deflection (angle
        from +x, direction in the y-z plane) is the sum of two unit phasors; line ``l`` starts both at
        its own phase (golden-ratio steps), so the lines interleave."""
        t = scan_start_s + self.column_times_s()[None, :]
        line = np.arange(self.beams)[:, None]
        f1, f2 = ROSETTE_PRISM_HZ
        phase1 = 2 * np.pi * ((line * 0.618034) % 1.0)
        phase2 = 2 * np.pi * ((line * 0.414214) % 1.0)
        half = np.radians(ROSETTE_HALF_ANGLE_DEG)
        z = 0.5 * half * (np.exp(1j * (2 * np.pi * f1 * t + phase1)) + np.exp(-1j * (2 * np.pi * f2 * t + phase2)))
        off_axis, around = np.abs(z), np.angle(z)
        return np.stack(
            np.broadcast_arrays(np.cos(off_axis), np.sin(off_axis) * np.cos(around), np.sin(off_axis) * np.sin(around)),
            axis=-1,
        )

    def column_times_s(self) -> NDArray[np.float64]:
        """(columns,) firing time of each column after the scan stamp, s."""
        return self.period_s * np.arange(self.columns) / self.columns


@dataclass
class LidarScan:
    """One simulated scan, organised: (beams, columns) grids, NaN / invalid where there is no return.

    Attributes:
        points_xyz: (beams, columns, 3) float32, lidar frame at the scan stamp (or at each column's
            firing time when the scan is not de-skewed), m; NaN for no return.
        intensity: (beams, columns) float32, 0..255.
        ring: (beams, columns) uint16.
        time_s: (beams, columns) float32, firing time after the scan stamp, s; 0 in a de-skewed scan,
            whose every point is where it was at the stamp (a nonzero time would tell a reader to
            move the point from that time).
        valid: (beams, columns) bool.
        reflectivity: (beams, columns) float64 surface reflectivity at the hit (truth, for tests).
    """

    points_xyz: NDArray[np.float32]
    intensity: NDArray[np.float32]
    ring: NDArray[np.uint16]
    time_s: NDArray[np.float32]
    valid: NDArray[np.bool_]
    reflectivity: NDArray[np.float64]

    def unorganized(self) -> tuple[NDArray[np.float32], dict[str, NDArray[np.generic]]]:
        """(N, 3) valid points (row-major order) and their channels intensity, ring, time."""
        v = self.valid
        return self.points_xyz[v], {
            "intensity": self.intensity[v],
            "ring": self.ring[v],
            "time": self.time_s[v],
        }


def simulate_scan(
    scene: Scene,
    grid: TriangleGrid,
    model: LidarModel,
    T_world_lidar: NDArray[np.float64],
    rng: np.random.Generator,
    scan_start_s: float = 0.0,
) -> LidarScan:
    """Cast one revolution from ``T_world_lidar``: (4, 4) for a de-skewed scan (every ray from the stamp
    pose), or (columns, 4, 4) poses at each column's firing time (points then stay in each column's frame,
    as a moving real sensor reports them). ``scan_start_s``: the scan's stamp on the sensor's clock, s
    (where a rosette's prisms stand)."""
    B, C = model.beams, model.columns
    T = np.asarray(T_world_lidar, dtype=np.float64)
    deskewed = T.shape == (4, 4)
    if deskewed:
        T = np.broadcast_to(T, (C, 4, 4))
    if T.shape != (C, 4, 4):
        raise ConfigError(f"T_world_lidar must be (4, 4) or ({C}, 4, 4), got {T.shape}")
    dirs_l = model.directions(scan_start_s)
    dirs_w = np.einsum("cij,bcj->bci", T[:, :3, :3], dirs_l)
    origins = np.broadcast_to(T[:, :3, 3][None], (B, C, 3))
    t, tri = cast_rays(grid, origins.reshape(-1, 3), dirs_w.reshape(-1, 3), t_max=model.max_range_m)
    t = t.reshape(B, C)
    tri = tri.reshape(B, C)
    hit = tri >= 0
    refl = np.zeros((B, C))
    cos_inc = np.zeros((B, C))
    if np.any(hit):
        idx = np.nonzero(hit)
        p_world = origins[idx] + dirs_w[idx] * t[idx][:, None]
        _, refl[idx] = surface_properties(scene, tri[idx], p_world)
        cos_inc[idx] = np.abs(np.einsum("ij,ij->i", scene.normals[tri[idx]], dirs_w[idx]))
    gains = model.beam_gains[:, None]
    signal = refl * cos_inc
    noise_r = rng.standard_normal((B, C)) * model.range_noise_m
    u_drop = rng.random((B, C))
    noise_i = rng.standard_normal((B, C))
    rng_m = np.where(hit, t + noise_r, np.nan)
    weak = signal < 0.02
    valid = hit & (rng_m >= model.min_range_m) & (rng_m <= model.max_range_m) & (u_drop >= model.dropout)
    valid &= ~(weak & (u_drop < 0.7))
    intensity = np.clip(255.0 * signal * gains + 1.5 * noise_i, 0.0, 255.0)
    points = np.where(valid[..., None], dirs_l * rng_m[..., None], np.nan).astype(np.float32)
    ring = np.broadcast_to(np.arange(B, dtype=np.uint16)[:, None], (B, C)).copy()
    column_times = np.zeros(C, dtype=np.float32) if deskewed else model.column_times_s().astype(np.float32)
    time_s = np.broadcast_to(column_times[None, :], (B, C)).copy()
    return LidarScan(
        points_xyz=points,
        intensity=np.where(valid, intensity, np.nan).astype(np.float32),
        ring=ring,
        time_s=time_s,
        valid=valid,
        reflectivity=np.where(valid, refl, np.nan),
    )
