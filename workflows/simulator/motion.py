"""Vehicle motion along a scene's loop route: poses ``T_world_base`` as a function of time.

base_link: x forward, y left, z up, on the ground under the rear axle. The route is a counter-clockwise
rounded rectangle starting in the middle of its bottom side heading +x; the vehicle drives at a
constant speed and keeps going round the loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError
from fleetcal.workflows.simulator.scene import RouteSpec


@dataclass(frozen=True)
class LoopMotion:
    """Constant-speed motion round ``route``; ``speed_m_s`` metres per second."""

    route: RouteSpec
    speed_m_s: float

    def __post_init__(self) -> None:
        r = self.route
        if not np.isfinite(self.speed_m_s) or self.speed_m_s < 0:
            raise ConfigError(f"speed must be a non-negative number of m/s, got {self.speed_m_s}")
        if r.corner_radius_m <= 0 or r.corner_radius_m > min(r.half_x_m, r.half_y_m):
            raise ConfigError("route corner radius must be positive and fit in the loop")

    @property
    def loop_length_m(self) -> float:
        r = self.route
        return float(
            4 * (r.half_x_m - r.corner_radius_m) + 4 * (r.half_y_m - r.corner_radius_m) + 2 * np.pi * r.corner_radius_m
        )

    def planar(self, t_s: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(x, y, yaw) in the world frame (m, m, rad) at times ``t_s`` (s since the start)."""
        r = self.route
        a, b, rc = r.half_x_m, r.half_y_m, r.corner_radius_m
        sx, sy = 2 * (a - rc), 2 * (b - rc)
        arc = np.pi / 2 * rc
        # segments from the start: half bottom, corner, right, corner, top, corner, left, corner, half bottom
        lengths = np.array([sx / 2, arc, sy, arc, sx, arc, sy, arc, sx / 2])
        ends = np.cumsum(lengths)
        s = np.mod(np.asarray(t_s, dtype=np.float64) * self.speed_m_s, self.loop_length_m)
        seg = np.minimum(np.searchsorted(ends, s, side="right"), len(lengths) - 1)
        local = s - (ends[seg] - lengths[seg])
        x = np.empty_like(s)
        y = np.empty_like(s)
        yaw = np.empty_like(s)
        straights = {
            0: (0.0, -b, 0.0),
            2: (a, -b + rc, np.pi / 2),
            4: (a - rc, b, np.pi),
            6: (-a, b - rc, -np.pi / 2),
            8: (-a + rc, -b, 0.0),
        }
        for k, (x0, y0, heading) in straights.items():
            m = seg == k
            x[m] = x0 + np.cos(heading) * local[m]
            y[m] = y0 + np.sin(heading) * local[m]
            yaw[m] = heading
        centres = {
            1: (a - rc, -b + rc, -np.pi / 2),
            3: (a - rc, b - rc, 0.0),
            5: (-a + rc, b - rc, np.pi / 2),
            7: (-a + rc, -b + rc, np.pi),
        }
        for k, (cx, cy, ang0) in centres.items():
            m = seg == k
            ang = ang0 + local[m] / rc
            x[m] = cx + rc * np.cos(ang)
            y[m] = cy + rc * np.sin(ang)
            yaw[m] = ang + np.pi / 2
        return x, y, np.mod(yaw + np.pi, 2 * np.pi) - np.pi

    def T_world_base(self, t_s: float) -> NDArray[np.float64]:
        """4x4 ``T_world_base`` at time ``t_s`` (s since the start)."""
        return self.T_world_base_many(np.array([t_s]))[0]

    def T_world_base_many(self, t_s: NDArray[np.float64]) -> NDArray[np.float64]:
        """(N, 4, 4) ``T_world_base`` at times ``t_s``."""
        x, y, yaw = self.planar(np.atleast_1d(t_s))
        out = np.zeros((x.size, 4, 4))
        c, s = np.cos(yaw), np.sin(yaw)
        out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
        out[:, 2, 2] = out[:, 3, 3] = 1.0
        out[:, 0, 3], out[:, 1, 3] = x, y
        return out
