"""The start of a calibration whose log has no lidar-camera transform (or ``--initial auto``): the rig's
motion where it moves (each chosen image against the image next to it, paired with the lidar's motion over
the same interval, ``stages.calibration.hand_eye``), then a search of GOM around it or over every rotation
(``stages.calibration.initialisation``)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.config import Config
from fleetcal.pipeline.engine import Engine
from fleetcal.pipeline.frames import CameraFrame
from fleetcal.pipeline.progress import Progress
from fleetcal.pipeline.transforms import exp_se3
from fleetcal.readers.base import LogReader
from fleetcal.stages.calibration.config import SolverConfig
from fleetcal.stages.calibration.frame import CalibrationFrame, equalised_grey
from fleetcal.stages.calibration.hand_eye import CameraMotion, camera_motion, motion_rotation
from fleetcal.stages.calibration.initialisation import InitialGuess, search_initial_guess
from fleetcal.workflows.frame_sources import STAGE_WARMUPS, LogFrames
from fleetcal.workflows.pairing import ChosenPair

log = logging.getLogger(__name__)

SEARCH_FRAMES = 6
"""Frames (spread over those collected) that score the start's candidates."""


@dataclass(frozen=True)
class _GreyStage:
    """Engine stage: the equalised grey (uint8) of the images whose header stamp is in ``stamps_ns``, with the
    stamp (others: None)."""

    stamps_ns: frozenset[int]

    def __call__(self, camera: CameraFrame) -> tuple[int, NDArray[np.uint8]] | None:
        if camera.stamp_ns not in self.stamps_ns:
            return None
        return camera.stamp_ns, equalised_grey(camera.image)


def rig_motions(reader: LogReader, camera_topic: str, frames: list[CalibrationFrame], pairs: list[ChosenPair],
                config: Config, engine: Engine | None = None) -> tuple[list[CameraMotion], NDArray[np.float64]]:
    """The camera's motion between each frame's image and the image next to it (``camera_motion``) and the
    lidar's ``T_a_b`` (4, 4) over the same interval from the frame's twist, for the frames (of one camera,
    each with its ``pairs`` entry) that have both."""
    wanted = [(f, p) for f, p in zip(frames, pairs, strict=True)
              if p.camera_neighbour_log_ns >= 0 and f.twist_at_camera() is not None]
    if not wanted:
        return [], np.zeros((0, 4, 4))
    source = LogFrames(reader.paths, config.io.allow_truncated, config.io.max_range_m)
    own = engine is None
    engine = Engine(workers=0, quiet=True, warmups=STAGE_WARMUPS) if engine is None else engine
    try:
        greys = dict(engine.map_frames(source, camera_topic, _GreyStage(frozenset(
            [p.camera_neighbour_stamp_ns for _, p in wanted] + [p.camera_stamp_ns for _, p in wanted])),
            ordered=True, desc="initialisation images",
            log_times_ns=sorted({t for _, p in wanted for t in (p.camera_neighbour_log_ns, p.camera_log_ns)})))
    finally:
        if own:
            engine.close()
    motions, lidar = [], []
    for frame, pair in wanted:
        other, grey, twist = (greys.get(pair.camera_neighbour_stamp_ns), greys.get(pair.camera_stamp_ns),
                              frame.twist_at_camera())
        if other is None or grey is None or twist is None:
            continue
        earlier = pair.camera_neighbour_stamp_ns < frame.stamp_ns
        motion = camera_motion(other, grey, frame.camera) if earlier else camera_motion(grey, other, frame.camera)
        if motion is not None:
            motions.append(motion)
            dt_s = abs(frame.stamp_ns - pair.camera_neighbour_stamp_ns) * 1e-9
            lidar.append(exp_se3(np.concatenate([twist[3:], twist[:3]]) * dt_s))  # T_a_b, first order
    return motions, np.asarray(lidar).reshape(-1, 4, 4)


def find_start(reader: LogReader, camera_topic: str, camera_frames: list[CalibrationFrame],
               camera_pairs: list[ChosenPair], frames: list[CalibrationFrame], config: Config,
               solver: SolverConfig, engine: Engine | None = None, quiet: bool = True) -> InitialGuess:
    """A start without a guess: around the rotation the rig's motion gives (``motion_rotation``, from
    ``camera_topic``'s frames and their pairs), else over the whole rotation space (``search_initial_guess``),
    scored on at most ``SEARCH_FRAMES`` of ``frames`` (every camera's, for a joint rig)."""
    motions, lidar_T = rig_motions(reader, camera_topic, camera_frames, camera_pairs, config, engine)
    rotation = motion_rotation(motions, lidar_T) if motions else None
    index = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), SEARCH_FRAMES)).round().astype(int))
    with Progress(total=100, desc=f"start search ({'motion' if rotation is not None else 'all rotations'})",
                  quiet=quiet, unit="%", line_interval_s=1.0) as bar:
        guess = search_initial_guess([frames[i] for i in index], solver, rotation,
                                     progress=lambda done: bar.update(int(100 * done) - bar.done))
        bar.update(100 - bar.done)
    log.info("start from %s (%d camera motions%s): %d candidates, score %.4g, runner-up %.4g %.1f deg away%s",
             guess.source, len(motions), "" if rotation is None or rotation.free_axis_lidar is None else
             ", one axis free", guess.candidates, guess.score, guess.runner_up_score, guess.runner_up_deg,
             ", ambiguous" if guess.ambiguous else "")
    return guess
