"""Recipe: targetless lidar-camera calibration of one log (GOM paper), from paired frames to tables.

Steps: resolve topics -> initial guess (log tf or ``--initial``) -> pick N paired frames spread over
the log -> per-frame features (lidar feature, image gradients), ego-motion from ``/tf`` -> particle
swarm + polish (``stages.calibration``) -> ``calibration.parquet``, ``frames.parquet``, report PNGs.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, NoReturn

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.camera_model import CameraModel, with_model
from fleetcal.pipeline.config import CalibrationConfig, Config
from fleetcal.pipeline.engine import Engine
from fleetcal.pipeline.errors import InputError, ProcessingError, UsageError
from fleetcal.pipeline.frames import CameraFrame, LidarFrame
from fleetcal.pipeline.progress import Progress
from fleetcal.pipeline.transforms import (
    Mat4,
    TransformTree,
    apply,
    from_xyz_rpy,
    rotation_error_deg,
    to_quat,
    to_rpy_deg,
    translation_error_m,
)
from fleetcal.readers.base import LogReader
from fleetcal.readers.frames import CameraInfoTracker, load_tf
from fleetcal.stages.calibration.calibrator import CalibrationResult, ProgressCallback, SearchProgress, calibrate
from fleetcal.stages.calibration.config import SolverConfig
from fleetcal.stages.calibration.frame import (
    AUTO_FEATURE_GROUPS,
    AUTO_FEATURES,
    CalibrationFrame,
    CameraFeatures,
    LidarFeatures,
    camera_feature_stage,
    join_frame,
    lidar_feature_stage,
    with_columns,
)
from fleetcal.stages.calibration.initialisation import InitialGuess
from fleetcal.stages.sinks import report
from fleetcal.stages.sinks.tables import CALIBRATION_SCHEMA, FRAMES_SCHEMA, STD_COLUMNS, write_rows
from fleetcal.workflows import mapping
from fleetcal.workflows.calibration_start import find_start
from fleetcal.workflows.ego_motion import camera_twist, has_odometry, scan_motion, sweep_motion, twist_motion
from fleetcal.workflows.frame_sources import STAGE_WARMUPS, LogFrames
from fleetcal.workflows.pairing import ChosenPair, PairingStats, choose_pairs

log = logging.getLogger(__name__)


@dataclass
class PairCalibration:
    """The calibration of one lidar/camera pair (in joint mode, one row per camera of the rig)."""

    lidar_topic: str
    camera_topic: str
    lidar_frame: str
    camera_frame: str
    result: CalibrationResult
    T_camera_lidar: Mat4
    T_camera_lidar_initial: Mat4
    frames: list[CalibrationFrame] = field(default_factory=list)
    overlay_image: NDArray[Any] | None = None  # the first frame's raw image, for overlays (only that one is kept)
    lidar_stamps_ns: list[int] = field(default_factory=list)
    n_points: list[int] = field(default_factory=list)
    motion_source: str = "none"  # tf (the log's odometry), odometry (fleetcal's own) or none
    estimate_frame: str = ""  # the camera frame whose axes the translation profile is along ("": camera_frame)
    initialisation: str = "tf"  # where the initial guess came from: tf, initial, motion or search
    initial_candidates: int = 0  # starting poses scored by a motion or search initialisation

    def axis_deviations(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(3,) rotation (degrees) and (3,) translation (metres) standard deviations along this camera's axes
        (the result's, in the reference camera's axes, turned into this one's; correlations left out)."""
        R = (self.T_camera_lidar @ np.linalg.inv(self.result.T_camera_lidar))[:3, :3]
        turned = [np.sqrt(np.abs(R) ** 2 @ (np.asarray(std, dtype=np.float64) ** 2))
                  for std in (self.result.std_rotation_deg, self.result.std_translation_m)]
        return turned[0], turned[1]

    def timing(self) -> dict[str, float]:
        """The camera's clock offset, readout and their deviations, seconds (``CalibrationResult``'s; NaN where
        not estimated, NaN with an infinite deviation where unobservable)."""
        r = self.result
        return {"time_offset_s": r.time_offset_s, "time_offset_std_s": r.time_offset_std_s,
                "readout_s": r.readout_s, "readout_std_s": r.readout_std_s}

    def summary(self) -> dict[str, Any]:
        t, q = to_quat(self.T_camera_lidar)
        return {
            "lidar_topic": self.lidar_topic,
            "camera_topic": self.camera_topic,
            "lidar_frame": self.lidar_frame,
            "camera_frame": self.camera_frame,
            "metric": self.result.metric,
            "T_camera_lidar": self.T_camera_lidar.tolist(),
            "T_camera_lidar_initial": self.T_camera_lidar_initial.tolist(),
            "translation_m": t.tolist(),
            "quaternion_xyzw": q.tolist(),
            "rpy_deg": to_rpy_deg(self.T_camera_lidar).tolist(),
            "score": self.result.score,
            "initial_score": self.result.initial_score,
            "verdict": self.result.verdict,
            "verdict_reason": self.result.verdict_reason,
            "change_deg": rotation_error_deg(self.T_camera_lidar, self.T_camera_lidar_initial),
            "change_m": translation_error_m(self.T_camera_lidar, self.T_camera_lidar_initial),
            "rotation_std_deg": _finite_or_none(self.result.rotation_std_deg),
            "translation_std_m": _finite_or_none(self.result.translation_std_m),
            "agreeing_repeats": self.result.agreeing_repeats,
            "translation_held": self.result.translation_held,
            "translation_profile": [_finite_or_none(float(v)) for v in self.result.translation_profile],
            "weak_translation_axes": list(self.result.weak_translation_axes),
            "translation_axes_frame": self.estimate_frame or self.camera_frame,
            "ring_spacing_deg": _finite_or_none(self.result.ring_spacing_deg),
            "sparse_rings": self.result.sparse_rings,
            "ring_slant_deg": _finite_or_none(self.result.ring_slant_deg),
            "frames_used": self.result.frames_used,
            "runtime_s": self.result.runtime_s,
            "motion_compensated": self.motion_source != "none",
            **{name: _finite_or_none(float(value)) for name, value in zip(STD_COLUMNS, np.concatenate(
                self.axis_deviations()), strict=True)},
            "alike_runs": self.result.alike_runs,
            "alike_aliases": self.result.alike_aliases,
            "initialisation": self.initialisation,
            "initial_candidates": self.initial_candidates,
            **_timing_json(self.timing()),
            "motion_source": self.motion_source,
        }


def _finite_or_none(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def _timing_json(timing: dict[str, float]) -> dict[str, float | str | None]:
    """``PairCalibration.timing`` for JSON: a time and its deviation are ``"unobservable"`` where the deviation
    is infinite, None where not estimated."""
    out: dict[str, float | str | None] = {}
    for name in ("time_offset", "readout"):
        value, std = timing[f"{name}_s"], timing[f"{name}_std_s"]
        out[f"{name}_s"] = "unobservable" if np.isinf(std) else _finite_or_none(value)
        out[f"{name}_std_s"] = "unobservable" if np.isinf(std) else _finite_or_none(std)
    return out


def parse_initial(text: str) -> Mat4:
    """``"x y z roll pitch yaw"`` (metres, degrees, xyz-extrinsic) -> ``T_camera_lidar``."""
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError as err:
        raise UsageError(f"--initial must be 6 numbers 'x y z roll pitch yaw', got {text!r}") from err
    if len(values) != 6 or not np.all(np.isfinite(values)):
        raise UsageError(f"--initial must be 6 finite numbers 'x y z roll pitch yaw', got {text!r}")
    return from_xyz_rpy(*values)


def lidar_feature_spec(c: CalibrationConfig) -> str:
    """What the lidar stage computes for ``c.feature``: ``auto`` is measured per log by GOM only
    (``SolverConfig.feature_groups``); the other metrics take ``range+normals``."""
    return "range+normals" if c.feature == "auto" and c.metric != "gom" else c.feature


def feature_used(spec: str, result: CalibrationResult) -> str:
    """The lidar feature the objective used: the lidar stage's ``spec`` (``lidar_feature_spec``), or for ``auto``
    the columns the calibration chose among."""
    if result.feature_columns is None:
        return spec
    return "+".join(AUTO_FEATURES[i] for i in result.feature_columns)


def solver_config(config: Config) -> SolverConfig:
    c = config.calibration
    return SolverConfig(
        feature_groups=AUTO_FEATURE_GROUPS if c.feature == "auto" and c.metric == "gom" else (),
        metric=c.metric,
        search_deg=c.search_deg,
        search_m=c.search_m,
        translation=c.translation,
        n_particles=c.particles,
        max_iterations=c.iterations,
        repeats=c.repeats,
        estimate_focal=c.estimate_focal,
        estimate_time_offset=c.time_offset == "estimate",
        estimate_readout=c.readout == "estimate",
        time_range_s=c.time_range_s,
    )


@dataclass
class _Collected:
    frames: list[CalibrationFrame]
    overlay_image: NDArray[Any] | None
    lidar_stamps: list[int]
    n_points: list[int]
    lidar_frame: str
    camera_frame: str
    motion_source: str = "none"  # of the ego-motion that moved the scans to the camera stamps: tf, odometry, none
    pairs: list[ChosenPair] = field(default_factory=list)  # the pair of each frame


@dataclass
class ScansSeen:
    """What the scans of one lidar gave to earlier cameras of the same run, so that each scan is decoded,
    featured and registered once for all the cameras that pair with it."""

    scans: dict[int, Any] = field(default_factory=dict)  # header stamp -> LidarFeatures or _SparseScan
    points_xyz: dict[int, NDArray[np.float64]] = field(default_factory=dict)  # header stamp -> float64 points
    twists: dict[tuple[int, int], NDArray[Any] | None] = field(default_factory=dict)  # (early, late) -> twist


@dataclass(frozen=True)
class _SparseScan:
    """What the lidar stage returns for a chosen scan with too few valid points (kept apart from decode
    failures, which the engine counts)."""

    stamp_ns: int
    n_points: int


@dataclass(frozen=True)
class _ChosenLidarStage:
    """Engine stage: lidar feature(s) of the scans whose header stamp is in ``stamps_ns`` (others: None)."""

    stamps_ns: frozenset[int]
    feature: str

    def __call__(self, lidar: LidarFrame) -> LidarFeatures | _SparseScan | None:
        if lidar.stamp_ns not in self.stamps_ns:
            return None
        if lidar.n_points < SolverConfig.min_points:
            return _SparseScan(lidar.stamp_ns, lidar.n_points)
        return lidar_feature_stage(lidar, self.feature)


@dataclass(frozen=True)
class _ChosenCameraStage:
    """Engine stage: gradients (and with ``grey`` the equalised grey) of the images whose header stamp is in
    ``stamps_ns`` (others: None), projected with the calibration's camera model (``model``: the client's
    CameraInfo model of a topic listed as rectified, else the frame's own); the image of ``first_ns`` is kept
    for overlays."""

    stamps_ns: frozenset[int]
    first_ns: int
    camera_model: str
    model: CameraModel | None
    grey: bool

    def __call__(self, camera: CameraFrame) -> CameraFeatures | None:
        if camera.stamp_ns not in self.stamps_ns:
            return None
        camera.camera = with_model(self.model if self.model is not None else camera.camera, self.camera_model)
        if camera.camera is None:
            raise InputError(f"camera {camera.topic} has no CameraInfo in the log (or its K is unusable)")
        return camera_feature_stage(camera, keep_image=camera.stamp_ns == self.first_ns, keep_grey=self.grey)


def calibration_engine(config: Config, quiet: bool = True,
                       warmups: Sequence[Callable[[], None]] = STAGE_WARMUPS) -> Engine:
    """The engine of a ``calibrate`` run: in process unless a scheduler or a worker count is configured (a
    handful of frames does not pay for starting a local cluster); ``warmups`` as ``Engine``'s (the lidar and
    image stages' kernels by default)."""
    configured = config.engine.scheduler is not None or config.engine.workers is not None
    return Engine(scheduler=config.engine.scheduler, workers=config.engine.workers if configured else 0,
                  quiet=quiet, warmups=warmups)


def collect_frames(
    reader: LogReader,
    lidar_topic: str,
    camera_topic: str,
    config: Config,
    tree: TransformTree | None,
    engine: Engine | None = None,
    seen: ScansSeen | None = None,
) -> _Collected:
    """Choose N pairs spread over the log by their header stamps, run the per-frame stages (decoding, lidar
    feature, image gradients) on ``engine`` for those messages only (None: in process), then join each
    pair with its ego-motion from ``tree``. Scans already in ``seen`` (earlier cameras of the run) are not
    decoded again; what this call decodes is added to it."""
    c = config.calibration
    stats = PairingStats()
    chosen = choose_pairs(reader, lidar_topic, camera_topic, config.io.pairing_tolerance_ns, c.frames, stats=stats)
    if not chosen:
        _raise_unpaired(lidar_topic, camera_topic, stats, config)
    info = CameraInfoTracker.for_image(reader, camera_topic, config.io.rectified_topics)
    if info.model is None:
        raise InputError(f"camera {camera_topic} has no CameraInfo in the log (or its K is unusable)")
    source = LogFrames(reader.paths, config.io.allow_truncated, config.io.max_range_m)
    own = engine is None
    engine = Engine(workers=0, quiet=True, warmups=STAGE_WARMUPS) if engine is None else engine
    seen = ScansSeen() if seen is None else seen
    try:
        new = [p for p in chosen if p.lidar_stamp_ns not in seen.scans]
        lidar_problems, blank_scans = [], 0
        if new:
            lidar_stage = _ChosenLidarStage(frozenset(p.lidar_stamp_ns for p in new), lidar_feature_spec(c))
            seen.scans.update({r.stamp_ns if isinstance(r, _SparseScan) else r.lidar.stamp_ns: r
                               for r in engine.map_frames(source, lidar_topic, lidar_stage, ordered=True,
                                                          desc="calibration scans",
                                                          log_times_ns=[p.lidar_log_ns for p in new])})
            lidar_problems, blank_scans = _problems(engine), engine.stats.skip_reasons.get("no valid points", 0)
        scans = {p.lidar_stamp_ns: seen.scans[p.lidar_stamp_ns] for p in chosen if p.lidar_stamp_ns in seen.scans}
        camera_stage = _ChosenCameraStage(frozenset(p.camera_stamp_ns for p in chosen), chosen[0].camera_stamp_ns,
                                          c.camera_model,
                                          info.model if camera_topic in config.io.rectified_topics else None,
                                          grey=c.metric == "nmi")
        images = {r.stamp_ns: r for r in engine.map_frames(
            source, camera_topic, camera_stage, ordered=True, desc="calibration images",
            log_times_ns=[p.camera_log_ns for p in chosen])}
        problems = lidar_problems + _problems(engine)
        twists = _odometry_twists(engine, source, lidar_topic, chosen, scans, config, tree, seen.twists)
    finally:
        if own:
            engine.close()
    for message in problems:
        log.warning("skipping an undecodable frame on %s", message)
    return _joined(chosen, scans, images, config, tree, lidar_topic, problems, blank_scans, twists, seen.points_xyz)


def _problems(engine: Engine) -> list[str]:
    """The skip messages of the engine's last run other than frames it was not asked for or that hold no
    valid point (those are counted apart)."""
    return [m for m in engine.stats.skip_examples if not m.endswith(("stage returned None", "no valid points"))]


def _odometry_twists(engine: Engine, source: LogFrames, lidar_topic: str, chosen: list[ChosenPair],
                     scans: dict[int, Any], config: Config, tree: TransformTree | None,
                     registered: dict[tuple[int, int], NDArray[Any] | None]) -> dict[int, NDArray[Any]]:
    """Lidar stamp -> the lidar's twist (6,) at each chosen scan from fleetcal's own odometry, for a log whose
    tf does not move the lidar (else, or with motion compensation off: empty): each chosen scan registered
    (plain GICP with the mapping settings) onto the scan next to it in the log, once per two scans
    (``registered``: (early, late) header stamps -> twist or None, filled here and reused)."""
    scan = next((s for s in scans.values() if isinstance(s, LidarFeatures)), None)
    if not config.calibration.motion_compensation or scan is None:
        return {}
    if has_odometry(tree, scan.lidar.frame_id.lstrip("/")):
        return {}
    wanted = [p for p in chosen if p.neighbour_log_ns >= 0 and isinstance(scans.get(p.lidar_stamp_ns), LidarFeatures)
              and _scan_pair(p) not in registered]
    reg = mapping.ego_motion_registration(config)
    times = sorted({p.lidar_log_ns for p in wanted} | {p.neighbour_log_ns for p in wanted})
    sets = ({ps.stamp_ns: ps for ps in engine.map_frames(source, lidar_topic, partial(mapping.prepare_scan, config=reg),
                                                          desc="calibration odometry", log_times_ns=times)}
            if times else {})
    for pair in wanted:
        key = _scan_pair(pair)
        early, late = sets.get(key[0]), sets.get(key[1])
        if early is None or late is None or key in registered:  # each other's neighbours: one registration
            continue
        registered[key] = mapping.scan_twist(early, late, reg)
        if registered[key] is None:
            log.warning("no odometry for the scans at %d and %d: their registration failed", *key)
    twists: dict[int, NDArray[Any]] = {}
    for pair in chosen:
        twist = registered.get(_scan_pair(pair))
        if twist is not None:
            twists[pair.lidar_stamp_ns] = twist
    return twists


def _scan_pair(pair: ChosenPair) -> tuple[int, int]:
    """(earlier, later) header stamps of a chosen scan and its neighbour: the key of their registration."""
    return min(pair.lidar_stamp_ns, pair.neighbour_stamp_ns), max(pair.lidar_stamp_ns, pair.neighbour_stamp_ns)


def _joined(chosen: list[ChosenPair], scans: dict[int, Any], images: dict[int, CameraFeatures], config: Config,
            tree: TransformTree | None, lidar_topic: str, skips: list[str], blank_scans: int,
            twists: dict[int, NDArray[Any]], points_xyz: dict[int, NDArray[np.float64]]) -> _Collected:
    """The chosen pairs whose scan and image came back, joined with their ego-motion from ``tree``, else
    from ``twists`` (fleetcal's odometry, ``_odometry_twists``) (``blank_scans``: chosen scans without a valid
    point, skipped by the engine)."""
    c = config.calibration
    out = _Collected([], None, [], [], "", "")
    sparse = blank_scans
    for pair in chosen:
        scan, image = scans.get(pair.lidar_stamp_ns), images.get(pair.camera_stamp_ns)
        if isinstance(scan, _SparseScan):
            log.warning("skipping scan at %d: %d points", scan.stamp_ns, scan.n_points)
            sparse += 1
            continue
        if scan is None or image is None:
            continue
        out.lidar_frame, out.camera_frame = scan.lidar.frame_id.lstrip("/"), image.frame_id.lstrip("/")
        sweep = (sweep_motion(tree, out.lidar_frame, scan.lidar, image.stamp_ns)
                 if c.motion_compensation and c.point_times else None)
        motion = (scan_motion(tree, out.lidar_frame, scan.lidar.stamp_ns, image.stamp_ns)
                  if c.motion_compensation and sweep is None else None)
        if sweep is None and motion is None and scan.lidar.stamp_ns in twists:
            sweep = twist_motion(scan.lidar, image.stamp_ns, twists[scan.lidar.stamp_ns], c.point_times)
            out.motion_source = "odometry"
        elif motion is not None or sweep is not None:
            out.motion_source = "tf"
        if pair.lidar_stamp_ns not in points_xyz:  # one float64 copy of a scan for all its cameras
            points_xyz[pair.lidar_stamp_ns] = np.asarray(scan.lidar.points_xyz, dtype=np.float64)
        twist_at_camera = camera_twist(tree, out.lidar_frame, image.stamp_ns) if motion is not None else None
        frame = replace(join_frame(scan, image, T_lidar_motion=motion, points_xyz=points_xyz[pair.lidar_stamp_ns]),
                        readout_s=c.readout_of(image.topic), camera_twist_lidar=twist_at_camera)
        if sweep is not None:
            frame = replace(frame, point_time_offsets_s=sweep[0], twist_lidar=sweep[1])
        out.frames.append(frame)
        if out.overlay_image is None:
            out.overlay_image = image.image  # the objective keeps gradients only: no image per frame
        out.lidar_stamps.append(scan.lidar.stamp_ns)
        out.pairs.append(pair)
        out.n_points.append(scan.lidar.n_points)
    if out.frames:
        return out
    if sparse:
        raise InputError(
            f"no valid points: all {sparse} paired scans on {lidar_topic} have fewer than "
            f"{SolverConfig.min_points} valid points (empty clouds, or NaN or beyond io.max_range_m "
            f"{config.io.max_range_m:g} m)"
        )
    if skips:
        raise InputError(f"no paired frame could be decoded: {skips[0]}")
    raise InputError(f"none of the {len(chosen)} paired frames on {lidar_topic} could be used")


def _raise_unpaired(lidar_topic: str, camera_topic: str, stats: PairingStats, config: Config) -> NoReturn:
    """The error of a log in which no scan has an image near it."""
    if stats.lidar_frames == 0 or stats.camera_frames == 0:
        raise InputError(f"no messages on {lidar_topic if stats.lidar_frames == 0 else camera_topic}")
    raise InputError(
        f"no lidar scan on {lidar_topic} has an image on {camera_topic} within "
        f"{config.io.pairing_tolerance_ns / 1e6:.0f} ms ({stats.lidar_frames} scans, "
        f"{stats.camera_frames} images)"
    )


AUTO = "auto"
"""``--initial auto``: search the start even where the log's tf has one."""


SEARCHED_START_M = 1.0
"""Half-width of the translation box (metres) around a searched start, whose translation is 0: the camera
within about a metre of the lidar on each axis. The box is then wide: the start is not trusted."""


def _box_for(solver: SolverConfig, guess: InitialGuess | None) -> SolverConfig:
    """The solver for a calibration from a searched start (``guess``): the translation box widened to
    ``SEARCHED_START_M``; from the tf or ``--initial``, ``solver`` itself."""
    if guess is None:
        return solver
    return replace(solver, search_m=max(solver.search_m, SEARCHED_START_M))


def _searched_start(pairs: list[PairCalibration], guess: InitialGuess) -> None:
    """Record a searched start on its pairs; an ambiguous one makes the verdict ``suspect``."""
    for pair in pairs:
        pair.initialisation, pair.initial_candidates = guess.source, guess.candidates
        if guess.ambiguous:
            pair.result = replace(pair.result, verdict="suspect", verdict_reason=(
                f"the start is ambiguous: two starting rotations {guess.runner_up_deg:.0f} deg apart matched the "
                "images alike; give a guess with --initial or calibrate from a log with more motion or structure"))


def _start(reader: LogReader, topic: str, col: _Collected, frames: list[CalibrationFrame],
           tf: tuple[TransformTree | None, str | None], initial: str | None, config: Config, solver: SolverConfig,
           engine: Engine | None, quiet: bool = True) -> tuple[Mat4, InitialGuess | None]:
    """The start: ``--initial``, else the log's tf, else (or with ``--initial auto``) one found by
    ``find_start``; a log whose tf is broken (``tf[1]``) and lacks the path fails instead of guessing."""
    tree, problem = tf
    if initial and initial != AUTO:
        return parse_initial(initial), None
    if initial != AUTO and tree is not None and tree.can_lookup(col.camera_frame, col.lidar_frame):
        return initial_guess(tree, col.lidar_frame, col.camera_frame, None), None
    if initial != AUTO and problem is not None:
        path = (problem if tree is None else
                f"the log's tf has no path from {col.lidar_frame!r} to {col.camera_frame!r} ({problem})")
        raise InputError(f'no initial guess: {path}; give one with --initial "x y z roll pitch yaw" or search one '
                         "with --initial auto")
    guess = find_start(reader, topic, col.frames, col.pairs, frames, config, solver, engine, quiet)
    return guess.T_camera_lidar, guess


def initial_guess(
    tree: TransformTree | None, lidar_frame: str, camera_frame: str, initial: str | None
) -> Mat4:
    """``--initial`` when given, else the log's tf (lidar -> camera); a clear error without either."""
    if initial:
        return parse_initial(initial)
    if tree is None or not tree.can_lookup(camera_frame, lidar_frame):
        raise InputError(
            f"no initial guess: the log's tf has no path from {lidar_frame!r} to {camera_frame!r}; "
            'give one with --initial "x y z roll pitch yaw"'
        )
    return tree.lookup(
        camera_frame, lidar_frame, None if tree.is_static_path(camera_frame, lidar_frame) else 0
    )


def _log_tf(reader: LogReader) -> tuple[TransformTree | None, str | None]:
    """``readers.frames.load_tf``, saying that a tf which is not a tree is ignored."""
    tree, problem = load_tf(reader)
    if tree is None:
        log.warning("ignoring the log's tf (no ego-motion from it): %s", problem)
    return tree, problem


def _collect_cameras(reader: LogReader, lidar_topic: str, camera_topics: list[str], config: Config,
                     tree: TransformTree | None, engine: Engine | None) -> dict[str, _Collected]:
    """``collect_frames`` of every camera, each scan decoded once for all of them; the decoded scans are let go
    once the frames are joined (the frames keep their points and features only)."""
    seen = ScansSeen()
    return {topic: collect_frames(reader, lidar_topic, topic, config, tree, engine, seen) for topic in camera_topics}


def run_calibration(
    reader: LogReader,
    lidar_topic: str,
    camera_topics: list[str],
    config: Config,
    initial: str | None = None,
    joint: bool = False,
    quiet: bool = False,
    engine: Engine | None = None,
) -> list[PairCalibration]:
    """Calibrate every camera against the lidar (pairwise) or the whole rig at once (``joint``); the per-frame
    work runs on ``engine`` (None: in process)."""
    tree, tf_problem = _log_tf(reader)
    solver = solver_config(config)
    for topic in config.io.rectified_topics:
        if topic not in reader.topics:
            log.warning("rectified topic %s is not in the log: ignored", topic)
    collected = _collect_cameras(reader, lidar_topic, camera_topics, config, tree, engine)
    if joint and len(camera_topics) > 1:
        return _calibrate_joint(reader, lidar_topic, camera_topics, collected, (tree, tf_problem), initial, config,
                                quiet, engine)
    results = []
    for topic in camera_topics:
        col = collected[topic]
        T_init, guess = _start(reader, topic, col, col.frames, (tree, tf_problem), initial, config, solver, engine,
                               quiet)
        _check_visible(col.frames, T_init, topic)
        with search_progress(quiet) as progress:
            result = calibrate(col.frames, T_init, _box_for(solver, guess), progress)
        results.append(_pair(lidar_topic, topic, col, result, result.T_camera_lidar, T_init))
        _initialised(results[-1:], initial, guess)
    return results


def _initialised(pairs: list[PairCalibration], initial: str | None, guess: InitialGuess | None) -> None:
    """Say where the pairs' start came from (``initialisation``)."""
    if guess is not None:
        _searched_start(pairs, guess)
        return
    for pair in pairs:
        pair.initialisation = "initial" if initial else "tf"


def _pair(
    lidar_topic: str, topic: str, col: _Collected, result: CalibrationResult, T_camera_lidar: Mat4, T_init: Mat4,
    estimate_frame: str = "",
) -> PairCalibration:
    frames = col.frames if result.feature_columns is None else with_columns(col.frames, result.feature_columns)
    return PairCalibration(
        lidar_topic, topic, col.lidar_frame, col.camera_frame, result, T_camera_lidar, T_init,
        frames, col.overlay_image, col.lidar_stamps, col.n_points, col.motion_source, estimate_frame,
    )  # fmt: skip


def _calibrate_joint(
    reader: LogReader,
    lidar_topic: str,
    camera_topics: list[str],
    collected: dict[str, _Collected],
    tf: tuple[TransformTree | None, str | None],
    initial: str | None,
    config: Config,
    quiet: bool = False,
    engine: Engine | None = None,
) -> list[PairCalibration]:
    """One unknown lidar pose for the whole rig: ``T_camera_k_lidar = T_camera_k_camera0 @ T_camera0_lidar``,
    the camera-to-camera transforms from the log's tf; camera0 is the first camera topic."""
    ref = collected[camera_topics[0]]
    solver = solver_config(config)
    tree = tf[0]
    frames: list[CalibrationFrame] = []
    T_cam_ref: dict[str, Mat4] = {}
    for topic in camera_topics:
        col = collected[topic]
        if tree is None or not tree.can_lookup(col.camera_frame, ref.camera_frame):
            raise InputError(f"--joint needs the tf between cameras {ref.camera_frame!r} and {col.camera_frame!r}")
        T_cam_ref[topic] = tree.lookup(col.camera_frame, ref.camera_frame)
        for f in col.frames:
            f.T_camera_camera0 = T_cam_ref[topic]
            frames.append(f)
    T_init, guess = _start(reader, camera_topics[0], ref, frames, tf, initial, config, solver, engine, quiet)
    with search_progress(quiet) as progress:
        result = calibrate(frames, T_init, _box_for(solver, guess), progress)
    pairs = [
        _pair(lidar_topic, topic, collected[topic], result, T_cam_ref[topic] @ result.T_camera_lidar,
              T_cam_ref[topic] @ T_init, ref.camera_frame)  # fmt: skip
        for topic in camera_topics
    ]
    _initialised(pairs, initial, guess)
    return pairs


@contextmanager
def search_progress(quiet: bool) -> Iterator[ProgressCallback]:
    """A ``calibrate`` progress callback that draws the search on stderr (``pipeline.progress.Progress``:
    percent done, run, iteration and best score so far, ETA; one line a second at most off a terminal)."""
    desc = "calibration search"
    with Progress(total=100, desc=desc, quiet=quiet, unit="%", line_interval_s=1.0) as bar:

        def report(p: SearchProgress) -> None:
            bar.desc = f"{desc} run {p.run}/{p.runs} iteration {p.iteration} best {p.best_score:.4f}"
            bar.update(int(100 * p.fraction) - bar.done)

        yield report


def _check_visible(frames: list[CalibrationFrame], T_camera_lidar: Mat4, topic: str) -> None:
    """Drop nothing, but fail clearly when the camera sees no lidar point at the initial guess."""
    seen = 0
    for f in frames:
        _, valid = f.camera.project(apply(T_camera_lidar, f.points_xyz))
        seen += int(valid.sum())
    if seen == 0:
        raise ProcessingError(
            f"camera {topic} sees no lidar points at the initial guess; check the tf or --initial"
        )


def calibration_rows(pairs: list[PairCalibration], feature: str) -> list[dict[str, Any]]:
    rows = []
    for p in pairs:
        t, q = to_quat(p.T_camera_lidar)
        roll, pitch, yaw = to_rpy_deg(p.T_camera_lidar)
        rows.append({
            "lidar_topic": p.lidar_topic, "camera_topic": p.camera_topic, "lidar_frame": p.lidar_frame,
            "camera_frame": p.camera_frame, "metric": p.result.metric, "feature": feature_used(feature, p.result),
            "tx_m": t[0], "ty_m": t[1], "tz_m": t[2], "qx": q[0], "qy": q[1], "qz": q[2], "qw": q[3],
            "roll_deg": roll, "pitch_deg": pitch, "yaw_deg": yaw, "score": p.result.score,
            "initial_score": p.result.initial_score, "frames_used": p.result.frames_used,
            "runtime_s": p.result.runtime_s, "verdict": p.result.verdict, "verdict_reason": p.result.verdict_reason,
            **dict(zip(STD_COLUMNS, np.concatenate(p.axis_deviations()).tolist(), strict=True)),
            "initialisation": p.initialisation, "initial_candidates": p.initial_candidates, **p.timing(),
            "motion_source": p.motion_source,
        })  # fmt: skip
    return rows


def frame_rows(pairs: list[PairCalibration]) -> list[dict[str, Any]]:
    """One row per lidar scan and per camera image used (scores of the image's pair)."""
    rows: list[dict[str, Any]] = []
    seen_scans: set[tuple[str, int]] = set()
    for p in pairs:
        offset = 0
        if len(pairs) > 1 and p.result.frames_used > len(p.frames):
            offset = sum(len(q.frames) for q in pairs[: pairs.index(p)])
        for i, f in enumerate(p.frames):
            key = (p.lidar_topic, p.lidar_stamps_ns[i])
            if key not in seen_scans:
                seen_scans.add(key)
                rows.append(
                    {"topic": p.lidar_topic, "stamp_ns": p.lidar_stamps_ns[i], "n_points": p.n_points[i]}
                )
            j = offset + i
            rows.append({
                "topic": p.camera_topic, "stamp_ns": f.stamp_ns, "width": f.camera.width, "height": f.camera.height,
                "camera_topic": p.camera_topic,
                "score_initial": float(p.result.frame_initial_scores[j]),
                "score_final": float(p.result.frame_scores[j]),
            })  # fmt: skip
    return rows


def write_calibration(pairs: list[PairCalibration], config: Config, out_dir: Path) -> list[Path]:
    """``calibration.parquet``, ``frames.parquet`` and the report PNGs."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [
        write_rows(calibration_rows(pairs, lidar_feature_spec(config.calibration)), CALIBRATION_SCHEMA,
                   out_dir / "calibration.parquet"),
        write_rows(frame_rows(pairs), FRAMES_SCHEMA, out_dir / "frames.parquet"),
    ]  # fmt: skip
    report_dir = out_dir / "report"
    for p in pairs:
        if not p.frames or p.overlay_image is None:
            continue
        name = p.camera_topic.strip("/").replace("/", "_")
        f, image = p.frames[0], p.overlay_image
        for label, T in (("before", p.T_camera_lidar_initial), ("after", p.T_camera_lidar)):
            points = f.points_at_camera_stamp()
            written.append(report.write_overlay(image, f.camera, apply(T, points),
                                                report_dir / f"overlay_{label}_{name}.png"))  # fmt: skip
    return written


def landscape(pair: PairCalibration, config: Config, out_dir: Path, steps: int = 21) -> Path | None:
    """Score slices around the optimum (rotation about camera x/y, translation along x/y) as one PNG."""
    from fleetcal.stages.calibration.landscape import score_landscape
    from fleetcal.stages.calibration.problem import CalibrationProblem

    if not pair.frames:
        return None
    # the objective that was optimised: the viewpoint calibrate() resolved, not re-derived here
    solver = replace(solver_config(config), gradient_viewpoint=pair.result.gradient_viewpoint)
    problem = CalibrationProblem(pair.frames, pair.result.T_camera_lidar, solver)
    centre = problem.x_of(pair.result.T_camera_lidar)
    if problem.dim > centre.size:
        centre = np.append(centre, pair.result.focal_scale)
    rotation = score_landscape(problem, centre, axes=(0, 1), half_width=(2.0, 2.0), steps=steps)
    translation = score_landscape(problem, centre, axes=(3, 4), half_width=(0.2, 0.2), steps=steps)
    grids = {"rot x/y +-2 deg": rotation.scores, "trans x/y +-0.2 m": translation.scores}
    name = pair.camera_topic.strip("/").replace("/", "_")
    return report.write_landscape(grids, out_dir / "report" / f"landscape_{name}.png")


def timed(fn: Any, *args: Any, **kwargs: Any) -> tuple[Any, float]:
    start = time.perf_counter()
    value = fn(*args, **kwargs)
    return value, time.perf_counter() - start
