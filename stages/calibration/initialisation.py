"""A starting ``T_camera_lidar`` for a log that has none: the lidar's edges scored against the images' over
candidate rotations (around a rotation from the rig's motion, all along the axis motion leaves free, or over
every rotation), on blurred image gradients, then the best distinct candidates polished and compared.

The score is GOM's numerator above chance (``GomScorer.alignment``: lidar times image gradient magnitudes
times the cosine of twice their orientation difference), each frame's divided by the alignment all its lidar
gradients would have with a mean image gradient; unlike GOM it is not divided by the weight a pose sees, so
a pose that sees a few aligned edges does not beat one that sees many.

The rotation is what must be found: the camera is assumed within a few metres of the lidar, so at the
scene's ranges a translation error turns the view by a few degrees; the polish frees the translation within
the calibration's box so that the rotation does not make up for it, and the calibration's own search then
finds the translation (the start keeps ``translation_m``, zero by default).

Grid: optical-axis directions on a Fibonacci sphere ``CELL_DEG`` apart, around each tilts and rolls about
the optical axis ``STEP_DEG`` apart (or the motion candidates, ``_candidates``). The lidar gradients are
computed once per base rotation (``lidar_view_gradients``) and turned with each candidate's roll
(``GomScorer``), so all candidates of a base cost one kernel call per frame. The image blur is half a step's
footprint in pixels, so that a candidate within half a step of the truth lies in the blurred score's basin.

Two candidates are told apart by the image-band test of ``uncertainty.scores_alike``: where the best
polished candidate does not score clearly above a runner-up that the calibration's box around it does not
reach, the start is ``ambiguous``; where the best does not score clearly above zero, there is no start.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import ProcessingError
from fleetcal.pipeline.transforms import apply, rotation_error_deg
from fleetcal.stages.calibration.config import SolverConfig
from fleetcal.stages.calibration.frame import CalibrationFrame, Mat4, fold_rectification
from fleetcal.stages.calibration.hand_eye import HandEyeRotation, rotations_about
from fleetcal.stages.calibration.metrics import GomScorer, GradientPlanes
from fleetcal.stages.calibration.pso import pattern_search
from fleetcal.stages.calibration.sphere_gradients import camera_sphere_neighbours, lidar_view_gradients
from fleetcal.stages.calibration.uncertainty import BANDS_PER_FRAME, scores_alike

CELL_DEG = 30.0
"""Spacing of the optical-axis directions whose lidar gradients are computed."""
STEP_DEG = 7.5
"""Spacing of the candidate rotations (tilt and roll) scored around each direction."""
POINTS_PER_FRAME = 3000
"""Scored points per frame in the coarse search (every s-th of the strongest gradients)."""
POLISHED = 4
"""Distinct candidates polished and compared."""
MOTION_STEP_DEG = 1.5
"""Spacing of the candidates around a rotation found from motion (its error is a degree or two)."""
MOTION_HALF_DEG = 4.5
"""Half-width of the candidates around a whole rotation from motion: three times the largest deviation
``hand_eye.motion_rotation`` calls determined (1.5 deg)."""
MOTION_CELL_DEG = 15.0
"""Spacing along a free axis of the rotations whose lidar gradients are computed."""


@dataclass(frozen=True)
class InitialGuess:
    """A start found without a guess.

    Attributes:
        T_camera_lidar: 4x4, reference camera <- lidar.
        source: ``motion`` (around a rotation from the rig's motion, ``hand_eye``) or ``search`` (the whole
            rotation space).
        candidates: candidate poses scored.
        score: blurred GOM of the best polished candidate.
        runner_up_score: the same for the best candidate more than ``separation_deg`` from it (NaN: none).
        runner_up_deg: rotation between the two, degrees (NaN: none).
        ambiguous: the runner-up scores as well as the best (image-band test).
    """

    T_camera_lidar: Mat4
    source: str
    candidates: int
    score: float
    runner_up_score: float
    runner_up_deg: float
    ambiguous: bool


@dataclass
class _FramePrep:
    """One frame's inputs to the coarse scorers: points at the camera stamp and as captured (lidar frame),
    the feature, their lidar-sphere neighbours, the blurred image gradients."""

    frame: CalibrationFrame
    points: NDArray[np.float64]
    raw: NDArray[np.float64]
    feature: NDArray[np.float64]
    neighbours: NDArray[np.int64]
    planes: GradientPlanes
    T_camera_camera0: Mat4
    scale: float = 1.0  # alignment of all the frame's lidar gradients with a mean image gradient


def fibonacci_directions(n: int) -> NDArray[np.float64]:
    """(n, 3) unit vectors spread evenly over the sphere."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    azimuth = np.pi * (1.0 + np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z**2)
    return np.column_stack([r * np.cos(azimuth), r * np.sin(azimuth), z])


def looking_along(direction: NDArray[np.floating]) -> NDArray[np.float64]:
    """3x3 ``R_camera_lidar`` of a camera whose optical axis is ``direction`` (lidar frame), roll arbitrary."""
    z = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.vstack([x, np.cross(z, x), z])


def local_turns(half_deg: float, step_deg: float, full_roll: bool) -> NDArray[np.float64]:
    """(M, 3, 3) rotations in the camera frame: tilts of the optical axis within +-``half_deg`` and rolls
    about it (all around with ``full_roll``, else within +-``half_deg``), ``step_deg`` apart."""
    tilts = np.arange(-half_deg, half_deg + 1e-9, step_deg)
    rolls = (np.arange(0.0, 360.0, step_deg) if full_roll else tilts)
    tx, ty, rz = np.meshgrid(tilts, tilts, rolls, indexing="ij")
    roll = Rotation.from_euler("z", rz.ravel()[:, None], degrees=True)
    tilt = Rotation.from_rotvec(np.column_stack([tx.ravel(), ty.ravel(), np.zeros(tx.size)]), degrees=True)
    return np.asarray((roll * tilt).as_matrix())


def axis_turns(axis_camera: NDArray[np.floating], half_deg: float, step_deg: float) -> NDArray[np.float64]:
    """(M, 3, 3) rotations in the camera frame about ``axis_camera`` within +-``half_deg``, each with tilts of
    -1, 0, +1 ``step_deg`` about two axes perpendicular to it."""
    axis = np.asarray(axis_camera, dtype=np.float64) / np.linalg.norm(axis_camera)
    e1 = looking_along(axis)[0]
    e2 = np.cross(axis, e1)
    spins = np.arange(-half_deg, half_deg + 1e-9, step_deg)
    tilt = np.array([-step_deg, 0.0, step_deg])
    a, b, c = np.meshgrid(spins, tilt, tilt, indexing="ij")
    rotvecs = a.ravel()[:, None] * axis + b.ravel()[:, None] * e1 + c.ravel()[:, None] * e2
    return np.asarray(Rotation.from_rotvec(rotvecs, degrees=True).as_matrix())


def blur_for_step_px(camera: CameraModel, step_deg: float) -> float:
    """Gaussian sigma (pixels) of half a step's footprint at the principal point."""
    return 0.5 * float(np.radians(step_deg)) * 0.5 * (camera.fx + camera.fy)


def _prepare(frame: CalibrationFrame, step_deg: float, k: int) -> _FramePrep:
    """A frame's inputs (``_FramePrep``): finite points with a feature, their sphere neighbours by angle
    (rotation-free: computed once), the image gradients blurred for ``step_deg``."""
    f = fold_rectification(frame)
    raw = np.asarray(f.points_xyz, dtype=np.float64)
    feature = np.asarray(f.feature, dtype=np.float64)
    feature = feature if feature.ndim == 1 else feature[:, 0]
    points = f.points_at_camera_stamp()
    good = np.all(np.isfinite(points), axis=1) & np.isfinite(feature) & np.all(np.isfinite(raw), axis=1)
    raw, points, feature = raw[good], points[good], feature[good]
    if raw.shape[0] <= k:
        raise ProcessingError(f"frame {f.label!r}: {raw.shape[0]} valid lidar points, too few to search")
    neighbours = camera_sphere_neighbours(raw, np.eye(4), k, "angle")
    planes = GradientPlanes.of_stacked(f.gradients.gxy, f.camera, f.mask, f.gradients.stride).blurred(
        blur_for_step_px(f.camera, step_deg))
    prep = _FramePrep(f, points, raw, feature, neighbours, planes, np.asarray(f.T_camera_camera0, dtype=np.float64))
    lidar = lidar_view_gradients(raw, points, feature, np.eye(4), f.motion_rotation(), k=k, fit="lsq",
                                 neighbours=neighbours).magnitude
    image = float(np.mean(np.hypot(planes.planes[:, :, 0], planes.planes[:, :, 1])))
    prep.scale = max(float(np.sum(lidar)) * image, 1e-12)
    return prep


def _scorer(prep: _FramePrep, T_camera0_lidar: Mat4, reach_deg: float, keep_fraction: float) -> GomScorer | None:
    """A frame's GOM scorer with lidar gradients seen from ``T_camera0_lidar``, on at most
    ``POINTS_PER_FRAME`` of the strongest gradients within the view plus ``reach_deg`` (None: none there)."""
    T = prep.T_camera_camera0 @ T_camera0_lidar
    grads = lidar_view_gradients(prep.raw, prep.points, prep.feature, T, prep.frame.motion_rotation(), k=prep.
                                 neighbours.shape[1], fit="lsq", neighbours=prep.neighbours)
    camera = prep.frame.camera
    cam = apply(T, prep.points)
    keep = (grads.magnitude > 0) & _in_reach(cam, camera, np.radians(reach_deg))
    if keep_fraction < 1.0 and np.any(keep):
        keep &= grads.magnitude >= np.quantile(grads.magnitude[keep], 1.0 - keep_fraction)
    index = np.flatnonzero(keep)
    if index.size < 20:
        return None
    stride = max(1, index.size // POINTS_PER_FRAME)
    in_reach, index = index.size, index[::stride]
    uv, _ = camera.project(cam[index])
    order = np.lexsort((np.nan_to_num(uv[:, 0]), np.floor(np.nan_to_num(uv[:, 1]) / 4.0)))
    index = index[order]
    weight = grads.magnitude[index] * (in_reach / index.size)  # each scored point stands for those skipped
    return GomScorer(prep.points[index], grads.gx[index], grads.gy[index], weight, prep.planes, camera, T[:3, :3])


def _in_reach(points_cam: NDArray[np.float64], camera: CameraModel, reach_rad: float) -> NDArray[np.bool_]:
    """Points whose angle off the optical axis is within the image's largest plus ``reach_rad``."""
    off_axis = np.arctan2(np.hypot(points_cam[:, 0], points_cam[:, 1]), points_cam[:, 2])
    return np.asarray(off_axis < _half_view_rad(camera) + reach_rad)


def _half_view_rad(camera: CameraModel) -> float:
    """Largest angle off the optical axis that the image's corners and edge midpoints see."""
    if camera.distortion_model in ("equidistant", "cylindrical"):
        return float(min(camera.max_view_angle_rad, np.radians(100.0)))
    w, h = camera.width - 1.0, camera.height - 1.0
    uv = np.array([[0, 0], [w, 0], [0, h], [w, h], [camera.cx, 0], [camera.cx, h], [0, camera.cy], [w, camera.cy]])
    rays = camera.unproject(uv)
    return float(np.max(np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2])))


def _score(scorers: Sequence[GomScorer | None], T_batch: NDArray[np.float64],
           preps: Sequence[_FramePrep]) -> NDArray[np.float64]:
    """(P,) mean over frames of candidate extrinsics' (P, 4, 4) edge alignment (``GomScorer.alignment``),
    each frame's divided by its ``scale``."""
    total = np.zeros(T_batch.shape[0])
    for scorer, prep in zip(scorers, preps, strict=True):
        if scorer is not None:
            total += scorer.alignment(prep.T_camera_camera0 @ T_batch) / prep.scale
    return total / max(len(preps), 1)


def _poses(R: NDArray[np.float64], translation_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """(P, 4, 4) extrinsics of rotations (P, 3, 3) with one translation (camera frame)."""
    T = np.tile(np.eye(4), (R.shape[0], 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = translation_m
    return T


def _grid_scores(preps: list[_FramePrep], bases: NDArray[np.float64], turns: NDArray[np.float64],
                 translation_m: NDArray[np.float64], reach_deg: float, config: SolverConfig,
                 progress: Callable[[float], None] | None = None) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Rotations (B * M, 3, 3) ``turns @ base`` for every base rotation and their coarse scores; ``progress``
    is told the fraction of bases done."""
    rotations, scores = [], []
    for k, R_base in enumerate(bases):
        if progress is not None:
            progress(k / len(bases))
        T_base = _poses(R_base[None], translation_m)[0]
        scorers = [_scorer(p, T_base, reach_deg, config.keep_fraction) for p in preps]
        R = turns @ R_base
        rotations.append(R)
        scores.append(_score(scorers, _poses(R, translation_m), preps))
    return np.concatenate(rotations), np.concatenate(scores)


def _distinct(rotations: NDArray[np.float64], scores: NDArray[np.float64], separation_deg: float,
              count: int) -> list[int]:
    """Indices of the best-scoring rotations, each more than ``separation_deg`` from every better one."""
    chosen: list[int] = []
    for i in np.argsort(-scores):
        if scores[i] <= 0 or len(chosen) == count:
            break
        if all(rotation_error_deg(rotations[i], rotations[j]) > separation_deg for j in chosen):
            chosen.append(int(i))
    return chosen


def _outside_box(R: NDArray[np.float64], R_centre: NDArray[np.float64], half_deg: float) -> bool:
    """Whether ``R`` lies outside the calibration's rotation box (rotation vector components within
    +-``half_deg``, camera frame) around ``R_centre``."""
    turn = Rotation.from_matrix(R @ R_centre.T).as_rotvec(degrees=True)
    return bool(np.max(np.abs(turn)) > half_deg)


@dataclass(frozen=True)
class _Polished:
    R: NDArray[np.float64]
    score: float
    bands: NDArray[np.float64]


def _polish(preps: list[_FramePrep], R_start: NDArray[np.float64], translation_m: NDArray[np.float64],
            step_deg: float, config: SolverConfig) -> _Polished:
    """Compass search from ``R_start`` (gradients seen from there) of the rotation, with the translation free
    within the calibration's box (``config.search_m``) so that the rotation does not turn to make up for a
    near scene's parallax; the rotation is kept, at ``translation_m``, with its band scores."""
    T_start = _poses(R_start[None], translation_m)[0]
    scorers = [_scorer(p, T_start, step_deg, config.keep_fraction) for p in preps]

    def objective(z: NDArray[np.floating]) -> NDArray[np.float64]:
        z = np.atleast_2d(z)
        T = _poses(Rotation.from_rotvec(z[:, :3], degrees=True).as_matrix() @ R_start, translation_m)
        T[:, :3, 3] += z[:, 3:]
        return _score(scorers, T, preps)

    half = np.array([step_deg] * 3 + [config.search_m] * 3)
    result = pattern_search(objective, np.zeros(6), half / 2.0, -half, half, min_step_fraction=0.05)
    R = Rotation.from_rotvec(result.best_x[:3], degrees=True).as_matrix() @ R_start
    return _Polished(R, float(result.best_score), _band_scores(scorers, preps, _poses(R[None], translation_m)[0]))


def _band_scores(scorers: Sequence[GomScorer | None], preps: Sequence[_FramePrep], T: Mat4) -> NDArray[np.float64]:
    """Scores of one extrinsic on each frame's image bands (points in image order, ``BANDS_PER_FRAME``)."""
    out = []
    for scorer, prep in zip(scorers, preps, strict=True):
        if scorer is None:
            out.extend([0.0] * BANDS_PER_FRAME)
            continue
        for band in np.array_split(np.arange(scorer.points.shape[0]), BANDS_PER_FRAME):
            out.append(float(scorer.subset(band).alignment((prep.T_camera_camera0 @ T)[None])[0]) / prep.scale)
    return np.asarray(out)


def search_initial_guess(frames: list[CalibrationFrame], config: SolverConfig,
                         motion: HandEyeRotation | None = None,
                         translation_m: NDArray[np.floating] | None = None,
                         progress: Callable[[float], None] | None = None) -> InitialGuess:
    """Find a starting extrinsic (``progress``: told the fraction of candidates scored): score candidate
    rotations, polish the ``POLISHED`` best distinct ones and return the best. It is an error where even the
    best matches the images no better than chance (its alignment on the image bands within two standard
    errors of zero), and ambiguous where one outside the calibration's box around it (``config.search_deg``,
    which the search from the start covers) scores alike; around a whole rotation from motion, every
    candidate within the region it allows is the same answer. Candidates: around ``motion``'s rotation
    (``MOTION_STEP_DEG`` apart), all along its free axis if it has one; without it, the whole rotation space
    (``CELL_DEG`` / ``STEP_DEG``).

    Raises:
        ProcessingError: no candidate sees enough scene structure (no frame, no lidar gradient in view).
    """
    if not frames:
        raise ProcessingError("no paired lidar/camera frames to search a start from")
    t = np.zeros(3) if translation_m is None else np.asarray(translation_m, dtype=np.float64).reshape(3)
    bases, turns, step_deg, reach_deg = _candidates(motion)
    apart_deg = max(2.0 * step_deg, config.search_deg)  # beyond the calibration's box around the best
    if motion is not None and motion.free_axis_lidar is None:
        apart_deg = max(apart_deg, 2.0 * MOTION_HALF_DEG)  # the whole region motion allows is one answer
    preps = [_prepare(f, step_deg, config.sphere_k) for f in frames]
    R_all, scores = _grid_scores(preps, bases, turns, t, reach_deg, config, progress)
    best = _distinct(R_all, scores, 2.0 * step_deg, POLISHED)
    if not best:
        raise ProcessingError("no starting pose found: at no rotation do the lidar's edges meet image edges "
                              "(too little structure in view); give a guess with --initial")
    polished = sorted((_polish(preps, R_all[i], t, step_deg, config) for i in best), key=lambda p: -p.score)
    top = polished[0]
    if scores_alike(top.bands):
        raise ProcessingError("no starting pose found: at no rotation do the lidar's edges meet image edges "
                              "better than by chance (too little structure in view); give a guess with --initial")
    others = [p for p in polished[1:] if _outside_box(p.R, top.R, apart_deg)]
    runner = others[0] if others else None
    ambiguous = runner is not None and scores_alike(top.bands - runner.bands)
    return InitialGuess(
        _poses(top.R[None], t)[0], "search" if motion is None else "motion", int(R_all.shape[0]) + len(best),
        top.score, runner.score if runner else float("nan"),
        rotation_error_deg(runner.R, top.R) if runner else float("nan"), bool(ambiguous))


def _candidates(motion: HandEyeRotation | None) -> tuple[NDArray[np.float64], NDArray[np.float64], float, float]:
    """Base rotations (B, 3, 3), the turns (M, 3, 3) scored around each, their step and the reach beyond the
    view (degrees) within which a base's lidar gradients are computed."""
    if motion is None:
        n_directions = max(8, round(4.0 * np.pi / np.radians(CELL_DEG) ** 2))
        bases = np.stack([looking_along(d) for d in fibonacci_directions(n_directions)])
        return bases, local_turns(CELL_DEG / 2.0, STEP_DEG, full_roll=True), STEP_DEG, CELL_DEG / 2.0 + STEP_DEG
    R = np.asarray(motion.R_camera_lidar, dtype=np.float64)
    if motion.free_axis_lidar is None:
        turns = local_turns(MOTION_HALF_DEG, MOTION_STEP_DEG, full_roll=False)
        return R[None], turns, MOTION_STEP_DEG, MOTION_HALF_DEG + MOTION_STEP_DEG
    bases = rotations_about(R, motion.free_axis_lidar, round(360.0 / MOTION_CELL_DEG))
    turns = axis_turns(R @ motion.free_axis_lidar, MOTION_CELL_DEG / 2.0, MOTION_STEP_DEG)
    return bases, turns, MOTION_STEP_DEG, MOTION_CELL_DEG / 2.0 + MOTION_STEP_DEG
