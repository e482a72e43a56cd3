"""Camera clock offset and rolling-shutter readout, estimated together with the extrinsic.

Clocks (``DESIGN.md``): an image stamped ``t`` was exposed at lidar time ``t - offset``, its row r at
``t - offset + readout * r / (H - 1)``. A scan's points, already moved to the camera stamp by the frame's
ego-motion, move on to their row's exposure time by the lidar's twist at the camera stamp (velocity ``v``,
angular rate ``w``, lidar frame): ``p + tau * (v + w x p)`` with ``tau = offset - readout * row / (H - 1)``
(first order of ``pipeline.transforms.screw_apply``).

A shift common to every frame is the extrinsic: at a steady velocity ``v``, an offset moves every point
by ``offset * v``, which a translation reproduces exactly. So the search splits ``tau`` into its mean ``m``
(over all points of all frames) and the rest: the points move by ``m`` times the twist's deviation from the
twist most frames share (the median over the frames), plus the rest times the full twist. The extrinsic
searched then absorbs the shared motion, and ``extrinsic_correction`` takes it back out. The median, not
the mean: GOM follows the majority of frames, so a drive with two turning frames of ten ends at the
straight frames' optimum, which is what the median describes (with the mean, an intensity-only search of a
simulated 30 ms offset found 1 ms). What fixes the offset is how the motion differs
between frames (turns against straights, speed changes); what fixes the readout is how the motion shears
the image from its first row to its last. A log whose frames all move alike (or not at all) does not
constrain the offset: ``profile`` then finds every candidate scoring alike and says it is unobservable.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.transforms import Mat4, apply
from fleetcal.stages.calibration.problem import CalibrationProblem, Scorer
from fleetcal.stages.calibration.uncertainty import BANDS_PER_FRAME, band_scores, scores_alike

Fractions = list[list[list[NDArray[np.float64]]]]
"""Row fractions per group of scorers, frame and scorer (``TimeShiftField.row_fractions``)."""

PROFILE_STEPS = 21
"""Candidates of a profile over a time parameter's search range."""


@dataclass(frozen=True)
class TimeShift:
    """Camera timing relative to the lidar: ``offset_s`` (camera clock minus lidar clock) and ``readout_s``
    (first to last row), seconds; ``readout_s`` None: each frame's own (``CalibrationFrame.readout_s``)."""

    offset_s: float = 0.0
    readout_s: float | None = None


@dataclass(frozen=True)
class TimingEstimate:
    """Timing found with the extrinsic.

    Attributes:
        shift: the timing the returned extrinsic was refined under.
        offset_std_s, readout_std_s: standard deviations, seconds; NaN where not estimated, inf where the
            log's motion does not constrain it (unobservable).
        x: the extrinsic's parameters refined under ``shift``.
        score: mean score at ``x``.
    """

    shift: TimeShift
    offset_std_s: float
    readout_std_s: float
    x: NDArray[np.float64]
    score: float


@dataclass(frozen=True)
class TimeProfile:
    """A time parameter profiled over a grid at a fixed extrinsic.

    Attributes:
        value_s: the best candidate (refined by a parabola through its neighbours), seconds.
        std_s: standard deviation, seconds: half the reach of the candidates that score alike
            (``uncertainty.scores_alike``), at least the grid's step / sqrt(12).
        observable: False where candidates at both ends of the range score as well as the best.
        score: mean score at ``value_s``'s grid candidate.
    """

    value_s: float
    std_s: float
    observable: bool
    score: float


class TimeShiftField:
    """Moves the scored points of a ``CalibrationProblem`` in time (see the module's docstring).

    Built once from the problem's unshifted scorers; ``apply`` replaces the scorers' points, so the problem
    scores candidate extrinsics under that timing until the next ``apply``.
    """

    def __init__(self, problem: CalibrationProblem, twists_lidar: list[NDArray[np.floating] | None],
                 readouts_s: list[float]) -> None:
        """Per frame of the problem: ``twists_lidar``, the lidar twist (6,) at the camera stamp (v m/s, w rad/s,
        lidar frame), or None where the frame's motion is unknown (its points are then not moved);
        ``readouts_s``, its camera's known readout, seconds."""
        self.problem = problem
        self.readouts = [float(r) for r in readouts_s]
        self.twists = [None if tw is None else np.asarray(tw, dtype=np.float64).reshape(6) for tw in twists_lidar]
        known = [tw for tw in self.twists if tw is not None]
        # the motion most frames share: what a search at the stamps' timing absorbs into the extrinsic
        self.shared_twist = np.median(known, axis=0) if known else np.zeros(6)
        # the scorers (per frame, per channel and twin), with their unshifted points; the views the swarm
        # scores are rebuilt from them (``CalibrationProblem.points_moved``)
        self.groups = [problem.scorers]
        self.base_points = [[[s.points for s in scorers] for scorers in group] for group in self.groups]

    @property
    def moving(self) -> bool:
        """Whether any frame has a known, non-zero twist."""
        return any(tw is not None and np.any(tw != 0.0) for tw in self.twists)

    def row_fractions(self, x: NDArray[np.float64]) -> Fractions:
        """Per group (scorers, exploration twins), frame and scorer, each unshifted point's image row over the
        last row (N,) at parameters x (D,); 0.5 where it does not project."""
        T_c0 = self.problem.T_camera_lidar(x)
        out: Fractions = []
        for group in self.base_points:
            per_frame = []
            for k, points in enumerate(group):
                camera = self.problem.frames[k].camera
                T = self.problem.T_camera_camera0[k] @ T_c0
                fractions = []
                for p in points:
                    uv, valid = camera.project(apply(T, p))
                    rows = np.where(valid, np.clip(uv[:, 1] / max(camera.height - 1, 1), 0.0, 1.0), 0.5)
                    fractions.append(np.nan_to_num(rows, nan=0.5))
                per_frame.append(fractions)
            out.append(per_frame)
        return out

    @staticmethod
    def mean_fraction(fractions: Fractions) -> float:
        """Mean row fraction over the scored points of every frame (first channel of each)."""
        values = [frame[0] for frame in fractions[0] if frame]
        return float(np.mean(np.concatenate(values))) if values else 0.5

    def apply(self, shift: TimeShift, fractions: Fractions) -> None:
        """Move every scorer's points to the rows' exposure times under ``shift`` (``fractions``:
        ``row_fractions`` at the extrinsic the rows are taken at)."""
        mean_row = self.mean_fraction(fractions)
        m = self.mean_shift_s(shift, fractions)
        changed = False
        for group, base, group_fractions in zip(self.groups, self.base_points, fractions, strict=True):
            for k, (scorers, points) in enumerate(zip(group, base, strict=True)):
                tw = self.twists[k]
                readout = self.readouts[k] if shift.readout_s is None else shift.readout_s
                for j, p in enumerate(points):
                    rest = readout * (group_fractions[k][j] - mean_row)
                    # no shift (no motion, or none under this timing): the unshifted points themselves
                    moved = p if tw is None or (m == 0.0 and not np.any(rest)) else self._moved(p, tw, m, rest)
                    if scorers[j].points is not moved:
                        scorers[j] = _with_points(scorers[j], moved)
                        changed = True
        if changed:
            self.problem.points_moved()

    def mean_shift_s(self, shift: TimeShift, fractions: Fractions) -> float:
        """The mean of the points' time shifts ``tau`` over the frames, seconds."""
        readout = float(np.mean(self.readouts)) if shift.readout_s is None else shift.readout_s
        return shift.offset_s - readout * self.mean_fraction(fractions)

    def _moved(self, p: NDArray[np.float64], twist: NDArray[np.float64], m: float,
               rest: NDArray[np.float64]) -> NDArray[np.float64]:
        """Points p (N, 3) moved by ``m`` times the twist's deviation from the shared one and by ``-rest`` (N,)
        times the full twist."""
        v, w = twist[:3], twist[3:]
        dv, dw = v - self.shared_twist[:3], w - self.shared_twist[3:]
        velocity = v[None, :] + np.cross(w[None, :], p)
        deviation = dv[None, :] + np.cross(dw[None, :], p)
        return np.ascontiguousarray(p + m * deviation - np.asarray(rest)[:, None] * velocity)

    def extrinsic_correction(self, shift: TimeShift, fractions: Fractions) -> Mat4:
        """``C`` with ``T_camera_lidar = T_searched @ C``: undoes the shared motion the searched extrinsic
        absorbed (the inverse of ``exp(m w_shared)``, ``m v_shared``)."""
        m = self.mean_shift_s(shift, fractions)
        absorbed = np.eye(4)
        absorbed[:3, :3] = Rotation.from_rotvec(m * self.shared_twist[3:]).as_matrix()
        absorbed[:3, 3] = m * self.shared_twist[:3]
        return np.asarray(np.linalg.inv(absorbed))


def _with_points(scorer: Scorer, points: NDArray[np.float64]) -> Scorer:
    """A shallow copy of ``scorer`` scoring ``points`` (N, 3) instead of its own."""
    twin = copy.copy(scorer)
    twin.points = points
    return twin


def profile(field: TimeShiftField, x: NDArray[np.float64], fractions: Fractions,
            shifts: list[TimeShift], values_s: NDArray[np.float64]) -> TimeProfile:
    """Score the extrinsic x (D,) under each of ``shifts`` (one per candidate value ``values_s``, evenly
    spaced) and summarise (``TimeProfile``). Leaves the problem's points under the best shift."""
    per_band = []
    for shift in shifts:
        field.apply(shift, fractions)
        per_band.append(band_scores(field.problem, x[None], BANDS_PER_FRAME)[0])
    scores = np.vstack(per_band)
    means = scores.mean(axis=1)
    best = int(np.argmax(means))
    alike = np.array([scores_alike(scores[best] - scores[i]) for i in range(len(shifts))])
    step = float(values_s[1] - values_s[0]) if len(values_s) > 1 else 0.0
    value = float(values_s[best]) + _parabola_peak(means, best) * step
    reach = float(np.max(np.abs(values_s[alike] - value)))
    field.apply(shifts[best], fractions)
    return TimeProfile(value_s=value, std_s=max(reach / 2.0, step / np.sqrt(12.0)),
                       observable=not (bool(alike[0]) and bool(alike[-1])), score=float(means[best]))


def _parabola_peak(values: NDArray[np.float64], i: int) -> float:
    """Offset in grid steps, within +-0.5, of the peak of the parabola through ``values[i-1:i+2]``; 0 at an
    end of the grid or where the three do not bend down."""
    if i <= 0 or i >= len(values) - 1:
        return 0.0
    a, b, c = values[i - 1], values[i], values[i + 1]
    bend = a - 2.0 * b + c
    return float(np.clip(0.5 * (a - c) / bend, -0.5, 0.5)) if bend < 0 else 0.0


def estimate_timing(field: TimeShiftField, x: NDArray[np.float64], known: TimeShift, offset: bool, readout: bool,
                    range_s: float, refine: Callable[[NDArray[np.float64]], tuple[NDArray[np.float64], float]],
                    max_rounds: int = 4) -> TimingEstimate:
    """Alternate profiles of the offset (``offset``: over +-``range_s``) and the readout (``readout``: over
    0..2 ``range_s``) at the extrinsic x (D,), starting from ``known``, with ``refine``-ing the extrinsic under
    what they found (``refine(x) -> (x, score)``), until neither moves by more than half a grid step (at most
    ``max_rounds``); then profile each again on a grid four times finer about its value, which gives the
    reported value and deviation. A profile whose ends score as well as its best leaves its parameter at
    ``known``'s value with an infinite deviation."""
    shift = known
    offset_std = readout_std = float("nan")
    offsets = np.linspace(-range_s, range_s, PROFILE_STEPS)
    readouts = np.linspace(0.0, 2.0 * range_s, PROFILE_STEPS // 2 + 1)
    step = float(offsets[1] - offsets[0])
    score = float("nan")
    for _ in range(max_rounds):
        before = shift
        fractions = field.row_fractions(x)
        if offset:
            found = profile(field, x, fractions, [TimeShift(v, shift.readout_s) for v in offsets], offsets)
            offset_std = found.std_s if found.observable else float("inf")
            shift = replace(shift, offset_s=found.value_s if found.observable else known.offset_s)
        if readout:
            found = profile(field, x, fractions, [TimeShift(shift.offset_s, v) for v in readouts], readouts)
            readout_std = found.std_s if found.observable else float("inf")
            shift = replace(shift, readout_s=found.value_s if found.observable else known.readout_s)
        field.apply(shift, fractions)
        x, score = refine(x)
        moved = abs(shift.offset_s - before.offset_s) + abs((shift.readout_s or 0.0) - (before.readout_s or 0.0))
        if moved < step / 2 or not (np.isfinite(offset_std) or np.isfinite(readout_std)):
            break
    fractions = field.row_fractions(x)
    if offset and np.isfinite(offset_std):
        values = np.asarray(shift.offset_s + step / 4.0 * np.arange(-8, 9), dtype=np.float64)
        found = profile(field, x, fractions, [TimeShift(v, shift.readout_s) for v in values], values)
        offset_std = found.std_s if found.observable else offset_std  # else the fine grid is too short
        shift = replace(shift, offset_s=found.value_s)
    if readout and np.isfinite(readout_std) and shift.readout_s is not None:
        values = np.asarray(shift.readout_s + step / 4.0 * np.arange(-8, 9), dtype=np.float64)
        values = values[values >= 0.0]
        found = profile(field, x, fractions, [TimeShift(shift.offset_s, v) for v in values], values)
        readout_std = found.std_s if found.observable else readout_std
        shift = replace(shift, readout_s=found.value_s)
    field.apply(shift, fractions)
    score = float(field.problem.evaluate(x[None])[0])
    return TimingEstimate(shift, offset_std, readout_std, x, score)


def extrinsic_deviation(field: TimeShiftField, std_s: float, range_s: float,
                        R_camera_lidar: NDArray[np.float64]) -> NDArray[np.float64]:
    """(6,) deviations of the extrinsic (rotation degrees, translation metres, camera axes) that a mean time
    shift known to ``std_s`` seconds leaves (the correction ``extrinsic_correction`` moves by it); an
    unobservable one (``std_s`` inf) counts as uniform over +-``range_s``."""
    std = range_s / np.sqrt(3.0) if not np.isfinite(std_s) else std_s
    rotation = np.degrees(np.abs(R_camera_lidar @ field.shared_twist[3:])) * std
    translation = np.abs(R_camera_lidar @ field.shared_twist[:3]) * std
    return np.concatenate([rotation, translation])
