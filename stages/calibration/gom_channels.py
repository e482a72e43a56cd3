"""A frame's GOM scorers scored in one pass (``metric_kernels.gom_channels_batch_kernel``).

With several lidar features (``range+normals``) every feature channel keeps its own strongest points of
the same cloud, and where the image gradients are also smoothed across the lidar's rings each channel has
a twin against those planes: four GOM sums over largely the same points and the same image. Scored one by
one, every point is projected once per scorer; here each point of the channels' union is projected once
per pose and each set of planes sampled once, and every channel's sums are those its own scorer gives.
"""

from __future__ import annotations

import copy

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ProcessingError
from fleetcal.stages.calibration import metric_kernels as mk
from fleetcal.stages.calibration.metrics import (
    GomScorer,
    GradientPlanes,
    MetricBatch,
    focal_batch,
    pose_batch,
    roll_turns,
)


class GomChannels:
    """The GOM scorers of one frame, scored together.

    Args:
        selections: (C, N) bool, which points of one cloud (N points, in the order the scorers keep them)
            each channel's scorer holds.
        channels: the C (1 or 2) channels' scorers (``GomScorer``), all against the same gradient planes,
            camera and gradient rotation.
        twin_planes: other gradient planes of the same camera the channels are also scored against (their
            ``GomScorer.against`` twins), kept at the same or wider strides (``GradientPlanes.blurred_along``
            thinned), or None.
    """

    def __init__(self, selections: NDArray[np.bool_], channels: list[GomScorer],
                 twin_planes: GradientPlanes | None = None) -> None:
        first = channels[0]
        if any(s.image is not first.image or not np.array_equal(s.cam, first.cam) for s in channels):
            raise ProcessingError("channels scored together must share their gradient planes and camera")
        chosen = np.asarray(selections, dtype=bool)
        if chosen.shape[0] != len(channels) or not 1 <= len(channels) <= 2:
            raise ProcessingError(f"one or two channels are scored together, got {len(channels)}")
        union = np.any(chosen, axis=0)
        member = np.zeros((int(union.sum()), 2), dtype=bool)  # a second column of none for one channel
        member[:, : len(channels)] = chosen[:, union].T
        m = member.shape[0]
        self.c2, self.s2, self.magnitude = np.zeros((m, 2)), np.zeros((m, 2)), np.zeros((m, 2))
        points = np.zeros((m, 3))
        for ch, scorer in enumerate(channels):
            rows = member[:, ch]
            if int(rows.sum()) != scorer.points.shape[0]:
                raise ProcessingError("a channel's selection does not match its scorer's points")
            points[rows] = scorer.points
            self.c2[rows, ch], self.s2[rows, ch], self.magnitude[rows, ch] = scorer.c2, scorer.s2, scorer.magnitude
        self.points = points
        self.member = member.astype(np.uint8)
        self.n_channels = len(channels)
        if twin_planes is not None:
            first.against(twin_planes)  # the twin's size checked against the camera at its strides
        self.planes = [first.image] + ([twin_planes] if twin_planes is not None else [])
        # the twin's pixel per pixel of the frame's planes, along u and v (twins kept at a wider stride)
        self.scale1 = np.array(first.image.strides, dtype=np.float64) / np.array(self.planes[-1].strides)
        self.cam = first.cam
        self.R_gradients = first.R_gradients

    def score(self, T_camera_lidar_batch: NDArray[np.floating],
              focal_scale: NDArray[np.floating] | None = None) -> list[MetricBatch]:
        """Each scorer's ``MetricBatch``: the channels against the frame's planes, then against the twin
        planes (the order of the frame's scorer list)."""
        poses = pose_batch(T_camera_lidar_batch)
        first, second = self.planes[0], self.planes[-1]
        num, den, count = mk.gom_pair_batch_kernel(
            self.points, self.c2, self.s2, self.magnitude, self.member, first.planes, second.planes,
            len(self.planes), first.mask, second.mask, self.scale1, self.cam, poses,
            focal_batch(focal_scale, poses.shape[0]), roll_turns(poses, self.R_gradients))  # fmt: skip
        return [MetricBatch.of_gom(np.ascontiguousarray(num[:, k, ch]), np.ascontiguousarray(den[:, k, ch]),
                                   np.ascontiguousarray(count[:, k, ch]))
                for k in range(len(self.planes)) for ch in range(self.n_channels)]

    def on_planes(self, replaced: dict[int, GradientPlanes]) -> GomChannels:
        """These channels against other planes of the same size in place of some of theirs (``replaced``: by
        the ``id`` of the planes they replace, e.g. the same values in float32)."""
        other = copy.copy(self)
        other.planes = [replaced.get(id(planes), planes) for planes in self.planes]
        return other

    def subset(self, index: NDArray[np.int64]) -> GomChannels:
        """These channels on the points ``index`` of their union only (same planes): every channel's sums over
        its own points among them."""
        part = copy.copy(self)
        part.points = np.ascontiguousarray(self.points[index])
        part.c2 = np.ascontiguousarray(self.c2[index])
        part.s2 = np.ascontiguousarray(self.s2[index])
        part.magnitude = np.ascontiguousarray(self.magnitude[index])
        part.member = np.ascontiguousarray(self.member[index])
        return part
