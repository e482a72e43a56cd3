"""What a scan's per-point times (the ``time`` channel, s relative to the scan stamp) are: one rule for
calibration, mapping, ``process`` and ``inspect``.

- ``none``: no finite time.
- ``constant``: all within ``MIN_SWEEP_SPAN_S`` of one another: one capture time (a driver that de-skews,
  or zeroed times); the scan is used as stamped.
- ``sweep``: a spinning lidar's firing times, none further than ``max_offset_s`` from the stamp; each point
  can be moved by its own time.
- ``foreign``: times further from the stamp (another clock than the header's, e.g. PJLab rig1's points
  21.9 million s from their stamps, or a cloud merged over several sweeps); not used.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

PointTimeKind = Literal["none", "constant", "sweep", "foreign"]

MAX_SWEEP_S = 0.5
"""Per-point times further than this from the scan stamp are not one sweep's firing times (s): a lidar
spinning at 2 Hz or faster."""

MAX_SWEEP_INTERVALS = 2.0
"""Where the scan interval is known (mapping), times further than this many intervals from the stamp are
not one sweep's either."""

MIN_SWEEP_SPAN_S = 1e-3
"""Times spanning less than this are one capture time (s): a point moves under 1 cm in it at 10 m/s."""


@dataclass(frozen=True)
class PointTimes:
    """Classification of a scan's per-point times.

    Attributes:
        kind: ``none``, ``constant``, ``sweep`` or ``foreign`` (module docstring).
        first_s, last_s: first and last finite time, s from the scan stamp (NaN for ``none``).
        all_finite: every point has a finite time.
    """

    kind: PointTimeKind
    first_s: float = float("nan")
    last_s: float = float("nan")
    all_finite: bool = False

    @property
    def is_sweep(self) -> bool:
        return self.kind == "sweep"


def max_offset_s(interval_s: float | None = None) -> float:
    """The furthest a sweep's point time may lie from its stamp (s): ``MAX_SWEEP_S``, or less where the scan
    interval is known (``MAX_SWEEP_INTERVALS`` of it)."""
    if interval_s is None or not (np.isfinite(interval_s) and interval_s > 0):
        return MAX_SWEEP_S
    return min(MAX_SWEEP_S, MAX_SWEEP_INTERVALS * float(interval_s))


def classify_point_times(times_s: NDArray[np.generic] | None, interval_s: float | None = None) -> PointTimes:
    """``PointTimes`` of per-point times (s from the stamp); ``interval_s``: the scan interval where known."""
    if times_s is None:
        return PointTimes("none")
    t = np.asarray(times_s, dtype=np.float64).ravel()
    finite = np.isfinite(t)
    all_finite = bool(finite.all())
    if not all_finite:
        t = t[finite]
    if t.size == 0:
        return PointTimes("none")
    first, last = float(t.min()), float(t.max())
    if max(abs(first), abs(last)) > max_offset_s(interval_s):
        kind: PointTimeKind = "foreign"
    elif last - first < MIN_SWEEP_SPAN_S:
        kind = "constant"
    else:
        kind = "sweep"
    return PointTimes(kind, first, last, all_finite)


__all__ = ["MAX_SWEEP_INTERVALS", "MAX_SWEEP_S", "MIN_SWEEP_SPAN_S", "PointTimeKind", "PointTimes",
           "classify_point_times", "max_offset_s"]
