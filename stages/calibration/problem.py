"""The calibration objective: frames prepared once (culled, ordered, lidar gradients, scorers per feature
channel and their smoothed twins) and scored for whole batches of candidate extrinsics."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import ProcessingError
from fleetcal.pipeline.transforms import apply
from fleetcal.stages.calibration.config import SolverConfig
from fleetcal.stages.calibration.frame import (
    CalibrationFrame,
    Mat4,
    compensate_ego_motion,
    default_blur_sigma_px,
    fold_rectification,
)
from fleetcal.stages.calibration.gom_channels import GomChannels
from fleetcal.stages.calibration.metrics import (
    GomScorer,
    GradientPlanes,
    LevinsonScorer,
    MetricBatch,
    NmiScorer,
    levinson_edge_image,
)
from fleetcal.stages.calibration.pso import SwarmResult, particle_swarm, pattern_search
from fleetcal.stages.calibration.sphere_gradients import (
    LidarGradients,
    camera_sphere_neighbours,
    compute_sphere_gradients,
    depth_discontinuities,
    lidar_view_gradients,
    ring_spacing_rad,
)


class Scorer(Protocol):
    points: NDArray[np.float64]  # (N, 3) lidar points scored, lidar frame, metres

    def score(self, T_camera_lidar_batch: NDArray[np.floating],
              focal_scale: NDArray[np.floating] | None = None) -> MetricBatch: ...


@dataclass
class SharedPreparation:
    """What the objectives of one log's frames share whatever lidar feature they score (the same frames, in the
    same order, initial guess and settings): measured by the first objective built with it and reused by the
    next (``CalibrationProblem``'s ``shared``), so that choosing a feature builds these once.

    Attributes:
        ring_spacing_rad: per frame, its scan's ring spacing (``sphere_gradients.ring_spacing_rad``), radians.
        polar_scales: frame index -> which of its points were scored (``np.packbits`` of an (N,) bool) and the
            polar-angle factor of their sphere neighbour search (``LidarGradients.polar_scale``): another
            feature whose values are not finite at other points measures it again.
        twin_planes: frame index -> its image gradients smoothed across the lidar's rings (``gom_twins``).
    """

    ring_spacing_rad: list[float] | None = None
    polar_scales: dict[int, tuple[bytes, float]] = dataclasses.field(default_factory=dict)
    twin_planes: dict[int, GradientPlanes] = dataclasses.field(default_factory=dict)

    def ring_spacings(self, frames: list[CalibrationFrame]) -> list[float]:
        """Per frame, its scan's ring spacing (NaN: untold); measured once per scan (a scan's cameras share
        its points array) and once per log."""
        if self.ring_spacing_rad is None:
            by_scan: dict[int, float] = {}
            for f in frames:
                if id(f.points_xyz) not in by_scan:
                    by_scan[id(f.points_xyz)] = ring_spacing_rad(f.points_xyz)
            self.ring_spacing_rad = [by_scan[id(f.points_xyz)] for f in frames]
        if len(self.ring_spacing_rad) != len(frames):
            raise ProcessingError("objectives sharing their preparation must score the same frames")
        return self.ring_spacing_rad

    def polar_scale(self, k: int, scored: bytes) -> float | None:
        """Frame ``k``'s polar-angle factor where it was measured on the same points (``scored``), else None."""
        known = self.polar_scales.get(k)
        return known[1] if known is not None and known[0] == scored else None

    def twins_of(self, k: int, image: GradientPlanes,
                 planes_of: Callable[[GradientPlanes], GradientPlanes]) -> GradientPlanes:
        """Frame ``k``'s twin planes, made from its ``image`` gradients by ``planes_of`` the first time."""
        if k not in self.twin_planes:
            self.twin_planes[k] = planes_of(image)
        return self.twin_planes[k]


def delta_transforms(x: NDArray[np.floating]) -> NDArray[np.float64]:
    """(P, 4, 4) ``T_delta`` from parameters (P, >=6): rotation vector (deg) and translation (m)."""
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    T = np.tile(np.eye(4), (x.shape[0], 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(x[:, :3], degrees=True).as_matrix()
    T[:, :3, 3] = x[:, 3:6]
    return T


def embed(z: NDArray[np.floating], base: NDArray[np.float64], free: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Full parameter vectors (P, D) from values (P, F) of the ``free`` parameters, the others at ``base``
    (D,): how a search over some parameters is scored by ``CalibrationProblem.evaluate``."""
    z = np.atleast_2d(np.asarray(z, dtype=np.float64))
    x = np.tile(base, (z.shape[0], 1))
    x[:, free] = z
    return x


def evaluate_embedded(problem: CalibrationProblem, z: NDArray[np.floating], base: NDArray[np.float64],
                      free: NDArray[np.bool_], view: ScoringView | None = None) -> NDArray[np.float64]:
    """``problem.evaluate`` of the free parameters z (P, F), the others at ``base`` (``embed``), on ``view``
    (None: every point). Picklable with ``functools.partial``, unlike a closure."""
    return problem.evaluate(embed(z, base, free), view)


def _view_cull(points_cam: NDArray[np.float64], camera: CameraModel, margin_rad: float,
               margin_m: float) -> NDArray[np.bool_]:
    """Points that could enter the image for any pose in the search box (conservative)."""
    x, y, z = points_cam[:, 0], points_cam[:, 1], points_cam[:, 2]
    rng = np.linalg.norm(points_cam, axis=1)
    slack = margin_rad + np.arctan2(margin_m, np.maximum(rng - margin_m, 1e-3)) + np.radians(2.0)
    if camera.distortion_model == "cylindrical":
        elev = np.abs(np.arctan2(y, np.hypot(x, z)))
        half_v = np.arctan(max(camera.cy, camera.height - camera.cy) / camera.fy)
        return np.asarray(elev < half_v + slack)
    if camera.distortion_model == "equidistant":
        return np.asarray(np.arctan2(np.hypot(x, y), z) < np.radians(90.0) + slack)
    uv_corners = np.array([[0, 0], [camera.width - 1, 0], [0, camera.height - 1],
                           [camera.width - 1, camera.height - 1], [camera.cx, 0],
                           [camera.cx, camera.height - 1],
                           [0, camera.cy], [camera.width - 1, camera.cy]], dtype=np.float64)
    rays = camera.unproject(uv_corners)
    half_u = float(np.max(np.abs(np.arctan2(rays[:, 0], rays[:, 2]))))
    half_v = float(np.max(np.abs(np.arctan2(rays[:, 1], rays[:, 2]))))
    az = np.abs(np.arctan2(x, z))
    el = np.abs(np.arctan2(y, z))
    front = z > 0
    return np.asarray(front & (az < half_u + slack) & (el < half_v + slack))


def _image_order(points_cam: NDArray[np.float64], camera: CameraModel) -> NDArray[np.int64]:
    """Order of points by image row band then column at the initial pose, so that the kernels read
    the image with cache locality (does not change any score)."""
    uv, _ = camera.project(points_cam)
    uv = np.nan_to_num(uv, nan=-1.0, posinf=-1.0, neginf=-1.0)
    return np.asarray(np.lexsort((uv[:, 0], np.floor(uv[:, 1] / 4.0))), dtype=np.int64)


def across_rings_uv(camera: CameraModel, T_camera_lidar: Mat4) -> NDArray[np.float64] | None:
    """Image direction (2,), in pixels, across a spinning lidar's rings near the principal point: the
    lidar's z axis as the camera sees it. None where the camera looks along that axis (the rings circle
    the image)."""
    up = np.asarray(T_camera_lidar, dtype=np.float64)[:3, :3] @ np.array([0.0, 0.0, 1.0])
    if np.hypot(up[0], up[1]) < 0.3:
        return None
    return np.array([camera.fx * up[0], camera.fy * up[1]])


def ring_slant_deg(camera: CameraModel, T_camera_lidar: Mat4) -> float:
    """How far a spinning lidar's rings cross the image slanted, degrees in [0, 90]: the angle between the
    image's vertical and ``across_rings_uv`` (0 for a lidar level with the camera; a lidar rolled about the
    camera's optical axis: its roll). NaN where the rings circle the image."""
    across = across_rings_uv(camera, T_camera_lidar)
    if across is None:
        return float("nan")
    return float(np.degrees(np.arctan2(abs(across[0]), abs(across[1]))))


MIN_SWARM_FRAMES = 2  # a single frame's scene can leave a direction unfixed that a second one fixes (KITTI)


def swarm_frame_subset(frame_points: Sequence[int], budget: int, seed: int) -> list[int] | None:
    """The frames a seeded run's swarm scores: all (None) while their points (``frame_points``, per frame) add up
    to at most ``budget`` (0: no limit), else as many frames of the mean size as fit in the budget (at least
    ``MIN_SWARM_FRAMES``): every s-th frame from an offset that the seed turns, so that a candidate costs at most
    about ``budget`` points however many frames the log has, and the runs' swarms see different frames of the
    log; the polish and every reported score use all frames."""
    total, n_frames = int(sum(frame_points)), len(frame_points)
    if budget <= 0 or total <= budget:
        return None
    fitting = max(budget * n_frames // total, MIN_SWARM_FRAMES)
    step = min(-(-n_frames // fitting), max(n_frames // MIN_SWARM_FRAMES, 1))
    return None if step == 1 else list(range(seed % step, n_frames, step))


@dataclass
class ScoringView:
    """What a pose is scored on: some of the problem's frames (``frames``, their indices) and for each its
    scorers (feature channels, then their ring-smoothed twins), the same scored in one pass (``GomChannels``,
    or None) and how many of them are feature channels; ``per_point``: how many of a frame's points one scored
    point stands for (the overlap limits count points, so a strided view's counts are scaled by it)."""

    frames: list[int]
    scorers: list[list[Scorer]]
    together: list[GomChannels | None]
    channels: list[int]
    per_point: int = 1
    share: float = 1.0  # of its frames' points it scores: a pose scored counts as this many evaluations

    def of_frames(self, chosen: Sequence[int]) -> ScoringView:
        """This view on the frames at positions ``chosen`` of its own."""
        return ScoringView([self.frames[k] for k in chosen], [self.scorers[k] for k in chosen],
                           [self.together[k] for k in chosen], [self.channels[k] for k in chosen], self.per_point,
                           self.share)

    def strided(self, stride: int) -> ScoringView:
        """Every ``stride``-th point of each frame's GOM scorers (points are in image order, so a stride thins
        a frame evenly), one by one; other metrics' scorers whole. ``self`` where stride is 1."""
        if stride <= 1:
            return self
        scorers = [[s.subset(np.arange(0, s.points.shape[0], stride)) if isinstance(s, GomScorer) else s
                    for s in frame] for frame in self.scorers]
        return ScoringView(self.frames, scorers, [None] * len(scorers), self.channels, self.per_point * stride)

    def split(self, stride: int) -> tuple[ScoringView, ScoringView]:
        """Every ``stride``-th point of each frame (points are in image order, so a stride thins a frame evenly)
        and the other points: two views whose GOM sums add up to this view's (``MetricBatch.plus``). A frame
        scored in one pass (``together``) keeps its scorer list, which that pass replaces.

        Raises:
            ProcessingError: a scorer is not GOM.
        """
        parts: tuple[list[list[Scorer]], list[list[Scorer]]] = ([], [])
        passes: tuple[list[GomChannels | None], list[GomChannels | None]] = ([], [])
        for frame, together in zip(self.scorers, self.together, strict=True):
            if together is not None:
                thinned, rest = _strides(together.points.shape[0], stride)
                passes[0].append(together.subset(thinned))
                passes[1].append(together.subset(rest))
                parts[0].append(frame)
                parts[1].append(frame)
                continue
            gom = [s for s in frame if isinstance(s, GomScorer)]
            if len(gom) != len(frame):
                raise ProcessingError("only GOM scorers split over point sets")
            halves = [_strides(s.points.shape[0], stride) for s in gom]
            parts[0].append([s.subset(h[0]) for s, h in zip(gom, halves, strict=True)])
            parts[1].append([s.subset(h[1]) for s, h in zip(gom, halves, strict=True)])
            passes[0].append(None)
            passes[1].append(None)
        return (ScoringView(self.frames, parts[0], passes[0], self.channels, self.per_point * stride,
                            self.share / stride),
                ScoringView(self.frames, parts[1], passes[1], self.channels, self.per_point,
                            self.share * (1.0 - 1.0 / stride)))

    def in_float32(self) -> ScoringView:
        """This view with its frames' int16 gradient planes (``image_gradients.quantised``) copied to float32,
        which the GOM kernel samples about a fifth faster; the scores are the same (int16 steps are exact in
        float32, and the kernel samples either in float32)."""
        scorers: list[list[Scorer]] = []
        together: list[GomChannels | None] = []
        for frame, t in zip(self.scorers, self.together, strict=True):
            floats = {id(s.image): s.image.as_float32() for s in frame
                      if isinstance(s, GomScorer) and s.image.planes.dtype == np.int16}
            scorers.append([s.against(floats[id(s.image)]) if isinstance(s, GomScorer) and id(s.image) in floats
                            else s for s in frame])
            together.append(None if t is None else t.on_planes(floats))
        return ScoringView(self.frames, scorers, together, self.channels, self.per_point, self.share)

    def against(self, planes_of: Callable[[GradientPlanes], GradientPlanes]) -> ScoringView:
        """The GOM feature channels of every frame against other gradient planes made once per frame from its
        own (``planes_of``: e.g. blurred for exploration); ring-smoothed twins sit it out, other metrics too."""
        scorers = [gom_twins(frame[:n], planes_of) for frame, n in zip(self.scorers, self.channels, strict=True)]
        return ScoringView(self.frames, scorers, [None] * len(scorers), [len(frame) for frame in scorers],
                           self.per_point)

    def batches(self, k: int, T: NDArray[np.float64], focal: NDArray[np.floating] | None) -> list[MetricBatch]:
        """Frame k's metric batches, a scorer's each, for its extrinsics ``T`` (P, 4, 4)."""
        together = self.together[k]
        if together is not None:
            return together.score(T, focal)
        return [scorer.score(T, focal) for scorer in self.scorers[k]]


def _strides(n: int, stride: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Indices of every ``stride``-th of n points, and of the others."""
    every = np.arange(n)
    thinned = every % stride == 0
    return every[thinned], every[~thinned]


def gom_twins(scorers: list[Scorer], planes_of: Callable[[GradientPlanes], GradientPlanes]) -> list[Scorer]:
    """Twins of a frame's GOM scorers against other gradient planes made once from the frame's (``planes_of``:
    e.g. smoothed across the rings, or blurred for exploration) and shared by the channels."""
    gom = [s for s in scorers if isinstance(s, GomScorer)]
    if not gom:
        return []
    planes = planes_of(gom[0].image)
    return [s.against(planes) for s in gom]


SCREEN_STRIDE = 4  # a screening pass scores every 4th point: most of a swarm's candidates are ruled out by it
SCREEN_SIGMAS = 3.0  # its error's standard deviations a candidate's thinned score is given before it is ruled out
POLISH_MIN_STEP = 0.005
"""A polish stops once its steps are this fraction of its first ones (a tenth of the box): 0.005 deg / 0.5 mm in
the workflow's box of +-5 deg / +-0.5 m."""


class ScreenedObjective:
    """A swarm's objective on ``view`` in two passes: the free parameters z (P, F) (the others at ``base``,
    ``embed``) are scored on every ``SCREEN_STRIDE``-th point first, and on the other points only where the thinned
    score plus ``SCREEN_SIGMAS`` standard deviations of its error reaches the row's ``floor`` (its particle's best
    score). Those rows get their exact score (the two passes' sums added), the others -inf: they cannot beat their
    floor but by a chance the thinned score's error puts at about 1 in 700. The error's deviation is measured
    on the rows scored in full (none yet: every row is)."""

    def __init__(self, problem: CalibrationProblem, view: ScoringView, base: NDArray[np.float64],
                 free: NDArray[np.bool_]) -> None:
        self.problem, self.view, self.base, self.free = problem, view, base, free
        self.thinned, self.rest = view.split(SCREEN_STRIDE)
        self.squared_error = 0.0
        self.compared = 0

    def __call__(self, z: NDArray[np.floating], floor: NDArray[np.floating] | None = None) -> NDArray[np.float64]:
        x = embed(z, self.base, self.free)
        first = self.problem.metric_batches(x, self.thinned)
        estimate = self.problem.scores_of(first, self.thinned)[0].mean(axis=1)
        deviation = np.sqrt(self.squared_error / self.compared) if self.compared > 1 else np.inf
        go = np.ones(x.shape[0], dtype=bool) if floor is None else estimate + SCREEN_SIGMAS * deviation >= floor
        scores = np.full(x.shape[0], -np.inf)
        if np.any(go):
            second = self.problem.metric_batches(x[go], self.rest)
            merged = [[a.rows(go).plus(b) for a, b in zip(fa, fb, strict=True)]
                      for fa, fb in zip(first, second, strict=True)]
            scores[go] = self.problem.scores_of(merged, self.view)[0].mean(axis=1)
            self.squared_error += float(np.sum((estimate[go] - scores[go]) ** 2))
            self.compared += int(np.sum(go))
        return scores


class CalibrationProblem:
    """Prepared frames and the batched objective ``evaluate(x (P, D)) -> (P,)`` of a calibration."""

    def __init__(self, frames: list[CalibrationFrame], T_camera_lidar_init: Mat4,
                 config: SolverConfig, shared: SharedPreparation | None = None) -> None:
        """``shared``: what an objective of the same frames with another lidar feature measured (filled here
        where empty); None: measured for this objective alone."""
        config.validate()
        if not frames:
            raise ProcessingError("no paired lidar/camera frames to calibrate from")
        T0 = np.asarray(T_camera_lidar_init, dtype=np.float64)
        if T0.shape != (4, 4) or not np.all(np.isfinite(T0)):
            raise ProcessingError("initial T_camera_lidar must be a finite 4x4 transform")
        self.config = config
        self.T_init = T0
        self.dim = 7 if config.estimate_focal else 6
        s_deg, s_m = config.search_deg, config.search_m
        half = [s_deg] * 3 + [s_m] * 3 + ([config.focal_search] if config.estimate_focal else [])
        centre = [0.0] * 6 + ([1.0] if config.estimate_focal else [])
        self.lower = np.asarray(centre) - np.asarray(half)
        self.upper = np.asarray(centre) + np.asarray(half)
        frames = [fold_rectification(f) for f in frames]
        self.frames = frames
        self.T_camera_camera0 = [np.asarray(f.T_camera_camera0, dtype=np.float64) for f in frames]
        self.points_used: list[int] = []
        self.ring_smoothing_px: list[float] = []  # per frame, 0: none
        shared = SharedPreparation() if shared is None else shared
        self.ring_spacing_rad = shared.ring_spacings(frames)  # per frame, NaN: untold
        self.ring_slant_deg = [ring_slant_deg(f.camera, T_c_c0 @ T0)  # per frame at the initial guess, NaN: untold
                               for f, T_c_c0 in zip(frames, self.T_camera_camera0, strict=True)]
        self.selections: list[NDArray[np.bool_] | None] = []  # per frame: which points each GOM channel keeps
        self.full = ScoringView(list(range(len(frames))), [], [], [])
        for k, (f, T_c_c0, ring) in enumerate(zip(frames, self.T_camera_camera0, self.ring_spacing_rad,
                                                  strict=True)):
            scorers, n, selections = self._prepare(f, T_c_c0 @ T0, k, shared)
            sigma_px, across = self._ring_smoothing(f, T_c_c0 @ T0, ring)
            smoothed = partial(GradientPlanes.blurred_along, direction_uv=across, sigma_px=sigma_px, thinned=True)
            twins = gom_twins(scorers, partial(shared.twins_of, k, planes_of=smoothed)) if sigma_px > 0 else []
            self.full.scorers.append(scorers + twins)
            self.full.channels.append(len(scorers))
            self.full.together.append(_together(scorers, selections, twins))
            self.selections.append(selections)
            self.points_used.append(n)
            self.ring_smoothing_px.append(sigma_px)
        self._explore_views: dict[tuple[int, ...], ScoringView] = {}  # by the frames they score
        self._search_view: tuple[tuple[int, ...], ScoringView] | None = None  # the last, by its frames
        self.evaluations = 0.0  # poses scored on every point of a view's frames
        self.on_iteration: Callable[[int, float], None] | None = None  # called after each swarm iteration
        init_counts = self._channel_counts(self.centre[None])
        self.min_counts = [np.maximum(config.min_points, np.floor(config.min_overlap_fraction * c)).astype(np.int64)
                           for c in init_counts]

    @property
    def centre(self) -> NDArray[np.float64]:
        """(D,) the box's centre: the initial guess's parameters."""
        return np.asarray(0.5 * (self.lower + self.upper))

    def _ring_smoothing(self, f: CalibrationFrame, T_cam_lidar: Mat4, ring: float) -> tuple[
            float, NDArray[np.float64]]:
        """Across-ring smoothing of a frame's image gradients (``SolverConfig.ring_smoothing``) for rings
        ``ring`` radians apart: its Gaussian sigma in pixels (0: none) and the image direction (2,) across the
        lidar's rings (its z axis seen by the camera near the principal point)."""
        cfg = self.config
        none = (0.0, np.zeros(2))
        if cfg.metric != "gom" or cfg.ring_smoothing == "off":
            return none
        across = across_rings_uv(f.camera, T_cam_lidar)
        if across is None or not np.isfinite(ring):
            return none
        up = np.asarray(T_cam_lidar, dtype=np.float64)[:3, :3] @ np.array([0.0, 0.0, 1.0])
        px_per_rad = float(np.linalg.norm(across) / np.hypot(up[0], up[1]))
        sigma_px = cfg.ring_smoothing_fraction * ring * px_per_rad
        if cfg.ring_smoothing == "auto" and sigma_px <= default_blur_sigma_px(f.camera.width):
            return none
        return sigma_px, across

    def _prepare(self, f: CalibrationFrame, T_cam_lidar: Mat4, k: int,
                 shared: SharedPreparation) -> tuple[list[Scorer], int, NDArray[np.bool_] | None]:
        """Scorers of frame ``k`` (one per feature channel; Levinson: one), its largest point count and, for
        GOM, which of the frame's points each channel keeps ((C, N) bool; other metrics: None)."""
        cfg = self.config
        pts = np.asarray(f.points_xyz, dtype=np.float64)
        feat = np.asarray(f.feature, dtype=np.float64)
        feat = feat[:, None] if feat.ndim == 1 else feat
        if pts.ndim != 2 or pts.shape[1] != 3 or feat.ndim != 2 or feat.shape[0] != pts.shape[0]:
            raise ProcessingError(
                f"frame {f.label!r}: points {pts.shape} and feature {feat.shape} do not match")
        raw = pts
        pts = compensate_ego_motion(pts, f.T_lidar_motion, f.point_time_offsets_s, f.twist_lidar)
        good = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(feat), axis=1)
        pts, feat, raw = pts[good], feat[good], raw[good]
        keep = _view_cull(apply(T_cam_lidar, pts), f.camera, np.radians(cfg.search_deg) * np.sqrt(3),
                          cfg.search_m * np.sqrt(3))
        pts, feat, raw = pts[keep], feat[keep], raw[keep]
        order = _image_order(apply(T_cam_lidar, pts), f.camera)
        pts, feat, raw = pts[order], feat[order], raw[order]
        if pts.shape[0] <= cfg.sphere_k:
            raise ProcessingError(f"frame {f.label!r}: only {pts.shape[0]} lidar points could be seen by the "
                                  "camera in the search box")
        if cfg.metric == "nmi":
            if f.intensity is None:
                raise ProcessingError(f"frame {f.label!r}: NMI needs the image intensity")
            return [NmiScorer(pts, feat[:, c], f.intensity, f.camera, f.mask, cfg.nmi_bins)
                    for c in range(feat.shape[1])], pts.shape[0], None
        if cfg.metric == "levinson":  # depth discontinuities: the feature does not enter
            around = camera_sphere_neighbours(pts, T_cam_lidar, cfg.sphere_k, cfg.neighbours_on("camera"))
            weight = depth_discontinuities(pts, around, cfg.levinson_min_jump_m)
            sel = weight > 0
            stride = f.gradients.stride
            edges = levinson_edge_image(f.gradients.magnitude, cfg.levinson_blur_px / stride)
            return [LevinsonScorer(pts[sel], weight[sel], edges, f.camera, f.mask, stride)], int(sel.sum()), None
        good[good] = keep
        scored = np.packbits(good).tobytes()  # which of the frame's points: the key of what is shared
        scorers: list[Scorer] = []
        selections: list[NDArray[np.bool_]] = []
        neighbours: NDArray[np.int64] | None = None  # one sphere search per frame, shared by the channels
        image = GradientPlanes.of_stacked(f.gradients.gxy, f.camera, f.mask, f.gradients.stride)  # shared too
        for c in range(feat.shape[1]):
            scorer, sel, grads = self._gom_scorer(f, raw, pts, feat[:, c], T_cam_lidar, image, neighbours,
                                                  shared.polar_scale(k, scored))
            if neighbours is None:
                neighbours = grads.neighbours
                shared.polar_scales[k] = (scored, grads.polar_scale)
            scorers.append(scorer)
            selections.append(sel)
        return scorers, max(int(sel.sum()) for sel in selections), np.array(selections)

    def _gom_scorer(self, f: CalibrationFrame, raw: NDArray[np.float64], pts: NDArray[np.float64],
                    feat: NDArray[np.float64], T_cam_lidar: Mat4, image: GradientPlanes,
                    neighbours: NDArray[np.int64] | None,
                    polar_scale: float | None) -> tuple[GomScorer, NDArray[np.bool_], LidarGradients]:
        """GOM scorer of one feature channel (lidar gradients, paper 3.3, and the point selection) against
        the frame's ``image`` gradients, which of ``pts`` it keeps ((N,) bool) and the lidar gradients it
        came from (sphere neighbours: ``neighbours``, another channel's, or searched with ``polar_scale``
        where known)."""
        cfg = self.config
        if cfg.viewpoint == "lidar":
            grads = lidar_view_gradients(raw, pts, feat, T_cam_lidar,
                                         f.motion_rotation(),
                                         k=cfg.sphere_k, fit=cfg.fit, neighbours_by=cfg.neighbours_on("lidar"),
                                         neighbours=neighbours, polar_scale=polar_scale)
        else:
            grads = compute_sphere_gradients(pts, feat, T_cam_lidar, k=cfg.sphere_k, fit=cfg.fit,
                                             neighbours_by=cfg.neighbours_on("camera"), neighbours=neighbours,
                                             polar_scale=polar_scale)
        magnitude = grads.magnitude  # the paper's weight (Algorithm 1: mean absolute difference to the neighbours)
        sel = magnitude > 0
        if cfg.keep_fraction < 1.0 and np.any(sel):
            cut = np.quantile(magnitude[sel], 1.0 - cfg.keep_fraction)
            sel &= magnitude >= cut
        gx, gy = grads.gx[sel], grads.gy[sel]
        scorer = GomScorer(pts[sel], gx, gy, magnitude[sel], image, f.camera,
                           T_cam_lidar[:3, :3])
        return scorer, sel, grads

    def T_camera_lidar_batch(self, x: NDArray[np.floating]) -> NDArray[np.float64]:
        """(P, 4, 4) extrinsics (reference camera <- lidar) of parameters x (P, D)."""
        return np.asarray(delta_transforms(x) @ self.T_init)

    def pixel_deg(self) -> float:
        """Median over the frames of one pixel's angle at the principal point, degrees."""
        return float(np.median([np.degrees(1.0 / f.camera.fx) for f in self.frames]))

    def typical_range_and_off_axis(self) -> tuple[float, float]:
        """Median range (metres) and median off-axis tangent (sqrt(x^2 + y^2) / z in each camera's frame) of
        the scored points at the initial guess; NaN where no scorer keeps points."""
        ranges, tangents = [], []
        for scorers, T_c_c0 in zip(self.scorers, self.T_camera_camera0, strict=True):
            points = getattr(scorers[0], "points", None) if scorers else None
            if points is None or len(points) == 0:
                continue
            cam = apply(T_c_c0 @ self.T_init, np.asarray(points, dtype=np.float64))
            ahead = cam[cam[:, 2] > 0]
            ranges.append(np.linalg.norm(cam, axis=1))
            tangents.append(np.hypot(ahead[:, 0], ahead[:, 1]) / ahead[:, 2])
        if not ranges:
            return float("nan"), float("nan")
        return float(np.median(np.concatenate(ranges))), float(np.median(np.concatenate(tangents)))

    def T_camera_lidar(self, x: NDArray[np.floating]) -> Mat4:
        """The extrinsic of parameters x (D,)."""
        return np.asarray(delta_transforms(np.asarray(x)[None])[0] @ self.T_init)

    def x_of(self, T_camera_lidar: Mat4) -> NDArray[np.float64]:
        """Parameters (6,) of an extrinsic (focal scale not included)."""
        T_delta = np.asarray(T_camera_lidar) @ np.linalg.inv(self.T_init)
        rv = Rotation.from_matrix(T_delta[:3, :3]).as_rotvec(degrees=True)
        return np.concatenate([rv, T_delta[:3, 3]])

    @property
    def scorers(self) -> list[list[Scorer]]:
        """Per frame, the scorers of every point (``full``): feature channels, then ring-smoothed twins."""
        return self.full.scorers

    @property
    def together(self) -> list[GomChannels | None]:
        """Per frame, its scorers in one pass (``full``), or None."""
        return self.full.together

    def points_moved(self) -> None:
        """Rebuild what is derived from the scorers' points after they were replaced (``timing``): the frames'
        one-pass scorers and the exploration's views."""
        for k, scorers in enumerate(self.full.scorers):
            n = self.full.channels[k]
            self.full.together[k] = _together(scorers[:n], self.selections[k], scorers[n:])
        self._explore_views.clear()
        self._search_view = None

    def points_scored(self) -> list[int]:
        """Per frame, the points a pose projects over all its scorers (the union of its channels' where they
        are scored in one pass)."""
        return [t.points.shape[0] if t is not None else sum(s.points.shape[0] for s in frame)
                for frame, t in zip(self.full.scorers, self.full.together, strict=True)]

    def search_view(self, seed: int) -> ScoringView:
        """What a seeded run's swarm scores: the frames ``swarm_frame_subset`` picks for the seed, within
        ``SolverConfig.swarm_points`` points, their gradient planes in float32 (``ScoringView.in_float32``: most
        evaluations score these frames, so they are copied while the run's frames are; the others stay int16)."""
        subset = swarm_frame_subset(self.points_scored(), self.config.swarm_points, seed)
        key = tuple(range(len(self.frames))) if subset is None else tuple(subset)
        if self._search_view is None or self._search_view[0] != key:
            self._search_view = None  # freed before the next one is made
            self._search_view = (key, (self.full if subset is None else self.full.of_frames(subset)).in_float32())
        return self._search_view[1]

    def explore_view(self, seed: int) -> ScoringView | None:
        """The search view's feature channels, on every ``explore_stride``-th point, against the image gradients
        blurred for exploration (``SolverConfig.explore``); None where the swarm does not explore."""
        if not self.config.explores:
            return None
        search = self.search_view(seed)
        key = tuple(search.frames)
        if key not in self._explore_views:
            factor = self.config.explore_blur_factor  # times the blur of the image's width
            blurred = search.against(
                lambda planes: planes.blurred(sigma_px=factor * default_blur_sigma_px(planes.width_px)))
            self._explore_views[key] = blurred.strided(self.config.explore_stride)
        return self._explore_views[key]

    def metric_batches(self, x: NDArray[np.floating], view: ScoringView) -> list[list[MetricBatch]]:
        """Metric batches per frame and scorer of ``view`` for parameters (P, D)."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        T_c0 = delta_transforms(x) @ self.T_init
        focal = x[:, 6] if x.shape[1] > 6 else None
        self.evaluations += x.shape[0] * view.share
        return [view.batches(k, self.T_camera_camera0[frame] @ T_c0, focal) for k, frame in enumerate(view.frames)]

    def _channel_counts(self, x: NDArray[np.floating]) -> list[NDArray[np.int64]]:
        """Projected points per frame and channel of the first candidate of x."""
        return [np.array([b.counts[0] for b in frame], dtype=np.int64) for frame in self.metric_batches(x, self.full)]

    def frame_scores(self, x: NDArray[np.floating],
                     view: ScoringView | None = None) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Per-frame scores (mean over the frame's scorers: feature channels and their ring-smoothed twins;
        a scorer projecting fewer points than its minimum scores 0) and projected-point counts (largest
        over scorers), each (P, F), of parameters (P, D) on ``view`` (None: every point, ``full``)."""
        view = self.full if view is None else view
        return self.scores_of(self.metric_batches(x, view), view)

    def scores_of(self, batches: list[list[MetricBatch]],
                  view: ScoringView) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """``frame_scores`` of the metric batches of ``view``'s frames and scorers (``metric_batches``)."""
        n = batches[0][0].scores.shape[0]
        scores = np.zeros((n, len(batches)))
        counts = np.zeros((n, len(batches)), dtype=np.int64)
        for k, frame in enumerate(batches):
            for c, batch in enumerate(frame):
                seen = batch.counts * view.per_point
                limit = self.min_counts[view.frames[k]][c]
                scores[:, k] += np.where(seen >= limit, batch.scores, 0.0) / len(frame)
                counts[:, k] = np.maximum(counts[:, k], seen)
        return scores, counts

    def overlap_limited(self, x: NDArray[np.floating], fraction: float) -> list[str]:
        """Frames whose feature channels project at most ``1 + fraction`` times their minimum count (the
        overlap limit, ``min_overlap_fraction`` of the count at the initial guess) at parameters x (D,),
        each described as ``"frame 2 (/cam): 5908 points, limit 5907"``: there the limit, not the
        metric, held the optimum."""
        limited = []
        for k, frame in enumerate(self.metric_batches(np.asarray(x)[None], self.full)):
            for c, batch in enumerate(frame):
                seen, limit = int(batch.counts[0]), int(self.min_counts[k][c])
                if limit <= seen <= (1.0 + fraction) * limit:
                    label = f" ({self.frames[k].label})" if self.frames[k].label else ""
                    limited.append(f"frame {k + 1}{label}: {seen} points, limit {limit}")
                    break
        return limited

    def evaluate(self, x: NDArray[np.floating], view: ScoringView | None = None) -> NDArray[np.float64]:
        """Mean score over frames for parameters (P, D) -> (P,), on ``view`` (None: every point)."""
        return np.asarray(self.frame_scores(x, view)[0].mean(axis=1))

    def free_parameters(self, hold_translation: bool = False) -> NDArray[np.bool_]:
        """(D,) which parameters the optimiser searches: those with a box of non-zero width, less the
        translation when ``hold_translation`` (it stays at the initial guess's)."""
        free = self.upper > self.lower
        if hold_translation:
            free[3:6] = False
        return np.asarray(free)

    def optimise(self, seed: int, hold_translation: bool = False) -> tuple[SwarmResult, SwarmResult | None]:
        """One seeded swarm (+ polish) run over the free parameters (``free_parameters``); the others stay
        at the box's centre (the initial guess). Results are given in all D parameters. The swarm and the
        polish score the seed's frames (``search_view``); where those are a subset of the frames, the
        polish's ``best_score`` is its pose's score over every frame, and ``polish_everywhere`` refines
        the chosen run's pose on every frame."""
        cfg = self.config
        free = self.free_parameters(hold_translation)
        centre = self.centre
        lower, upper = self.lower[free], self.upper[free]
        search, explore = self.search_view(seed), self.explore_view(seed)
        screened = ScreenedObjective(self, search, centre, free) if cfg.metric == "gom" else None
        swarm = particle_swarm(screened or partial(evaluate_embedded, self, base=centre, free=free, view=search),
                               lower, upper,
                               n_particles=cfg.n_particles,
                               max_iterations=cfg.max_iterations, stall_iterations=cfg.stall_iterations,
                               min_iterations=cfg.min_iterations, score_tolerance=cfg.swarm_tolerance,
                               seed=seed, x_initial=centre[free],
                               explore_objective=(partial(evaluate_embedded, self, base=centre, free=free,
                                                          view=explore) if explore is not None else None),
                               explore_iterations=cfg.explore_phase_iterations, on_iteration=self.on_iteration,
                               screened=screened)
        swarm = dataclasses.replace(swarm, best_x=embed(swarm.best_x, centre, free)[0])
        if not cfg.polish:
            return swarm, None
        polish = self._polish(swarm.best_x, free, search, swarm.best_score)
        if search is not self.full:
            polish = dataclasses.replace(polish, best_score=float(self.evaluate(polish.best_x[None])[0]))
        return swarm, polish

    def polish_everywhere(self, x: NDArray[np.floating], hold_translation: bool, score: float) -> SwarmResult:
        """The polish (``pattern_search``) from parameters x (D,) over every frame; ``score``: x's score there."""
        return self._polish(np.asarray(x, dtype=np.float64), self.free_parameters(hold_translation), self.full,
                            score)

    def polish_on_view(self, x: NDArray[np.floating], hold_translation: bool, seed: int,
                       min_step_fraction: float = POLISH_MIN_STEP) -> SwarmResult:
        """The polish (``pattern_search``) from parameters x (D,) on the seed's swarm frames (``search_view``),
        down to ``min_step_fraction`` of its first steps; its ``best_score`` is scored there."""
        start = np.asarray(x, dtype=np.float64)
        view = self.search_view(seed)
        return self._polish(start, self.free_parameters(hold_translation), view,
                            float(self.evaluate(start[None], view)[0]), min_step_fraction)

    def _polish(self, x: NDArray[np.float64], free: NDArray[np.bool_], view: ScoringView, score: float,
                min_step_fraction: float = POLISH_MIN_STEP) -> SwarmResult:
        """Compass search over the free parameters from x (D,) on ``view`` (x scores ``score`` there), the others
        at the box's centre, from steps of a tenth of the box down to ``min_step_fraction`` of them; the result in
        all D parameters."""
        centre = self.centre
        lower, upper = self.lower[free], self.upper[free]
        result = pattern_search(partial(evaluate_embedded, self, base=centre, free=free, view=view), x[free],
                                0.1 * (upper - lower), lower, upper, min_step_fraction=min_step_fraction,
                                score_at_x0=score)
        return dataclasses.replace(result, best_x=embed(result.best_x, centre, free)[0])


def _together(channels: list[Scorer], selections: NDArray[np.bool_] | None, twins: list[Scorer]) -> GomChannels | None:
    """The frame's GOM scorers in one pass (``GomChannels``) where there are several (one or two channels and
    their ring-smoothed twins); None for a single scorer, more than two channels or another metric."""
    gom = [s for s in channels if isinstance(s, GomScorer)]
    if selections is None or len(gom) != len(channels) or len(gom) > 2 or len(channels) + len(twins) < 2:
        return None
    twin_planes = twins[0].image if twins and isinstance(twins[0], GomScorer) else None
    return GomChannels(selections, gom, twin_planes)
