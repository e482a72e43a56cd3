"""Simulate a drive and write it as a log (MCAP, ROS 1 bag or ROS 2 bag folder) plus its truth file.

Topics: ``/lidar/points`` (PointCloud2 x, y, z, intensity (float32), ring (uint16), time (float32 s after
the stamp); frame ``lidar``; 10 Hz), ``/camera_N/image_raw`` (Image rgb8) or
``/camera_N/image_raw/compressed`` (CompressedImage jpeg), ``/camera_N/camera_info``, ``/tf`` (odometry
``odom -> base_link`` at 50 Hz and at every sensor stamp) and ``/tf_static`` (``base_link -> lidar`` and
``lidar -> camera_N_optical`` from the PERTURBED calibration). Sensor time starts at a fixed epoch and
nothing depends on the wall clock, so the same options give byte-identical files. Cameras may run on a clock
offset from the lidar's and read their rows out as a rolling shutter (``SimulationOptions.time_offset_ms``,
``readout_ms``): an image is rendered from the vehicle poses at its rows' true (lidar-clock) times.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from fleetcal.pipeline.errors import ConfigError, ProcessingError
from fleetcal.pipeline.msgtypes import LogFormat
from fleetcal.pipeline.progress import Progress
from fleetcal.pipeline.transforms import invert
from fleetcal.workflows.simulator.camera import (
    SimCamera,
    fisheye_camera,
    panorama_camera,
    pinhole_camera,
    rectified_stereo_camera,
    render,
    row_times_s,
    wide_angle_camera,
)
from fleetcal.workflows.simulator.lidar import (
    DEFAULT_LAYOUT,
    LIDAR_PATTERNS,
    MAX_ROSETTE_LINES,
    SUPPORTED_BEAMS,
    LidarModel,
    LidarScan,
    simulate_scan,
)
from fleetcal.workflows.simulator.motion import LoopMotion
from fleetcal.workflows.simulator.raycast import TriangleGrid, build_grid
from fleetcal.workflows.simulator.scene import SCENES, Scene, build_scene
from fleetcal.workflows.simulator.truth import (
    BASE_FRAME,
    DRIFTS,
    LIDAR_FRAME,
    LIDAR_TOPIC,
    MAX_CAMERAS,
    ODOM_FRAME,
    Rig,
    build_rig,
    build_truth,
    camera_frame,
    camera_topics,
    truth_path_for,
    write_truth,
)
from fleetcal.workflows.sinks import ros_messages as rm
from fleetcal.workflows.sinks.log_writer import LogWriter

START_NS = 1_700_000_000_000_000_000
"""Sensor time of the first scan (fixed: no wall clock)."""
TF_PERIOD_NS = 20_000_000
PREFETCH_IMAGES = 2
DEFAULT_SPEED_M_S = {"street": 8.0, "corridor": 1.5, "open": 5.0}
MAX_TIME_OFFSET_MS = 1000.0
MAX_READOUT_MS = 1000.0


@dataclass(frozen=True)
class SimulationOptions:
    """What to simulate. ``speed_m_s`` None: the scene's default (street 8, corridor 1.5, open 5 m/s).

    ``max_range_m``: lidar returns beyond this range are lost (the corridor's ends are out of range for
    the first ~70 scans with 25 m or less, which leaves the along-wall motion to texture alone).
    ``deskew`` True (default): every point of a scan is cast from the vehicle pose at the scan stamp (no
    motion distortion); False: each column is cast from the pose at its firing time and reported in the
    lidar frame of that time, as a moving real sensor does (the ``time`` field then matters).
    ``lidar``: ``spinning`` (``beams`` rings x ``columns`` firings) or ``rosette`` (a forward-looking
    non-repetitive Livox-like lidar: ``beams`` laser lines, 1..16, x ``columns`` samples per scan;
    ``workflows.simulator.lidar``); a rosette scan has no organised form. ``lidar_roll_deg``: the lidar
    mounted rolled about its forward axis (its rings then cross the forward camera's image slanted).
    ``camera_yaw_deg`` / ``camera_roll_deg``: every camera turned left by that much / rolled about its optical
    axis. ``tf_static`` False: no ``/tf_static`` (neither the lidar's mount nor the cameras'; the truth file
    still has them). ``drift``: ``cameras`` (default) perturbs each camera's extrinsic on its own, ``lidar`` the
    lidar's mount once, so the tf between the cameras stays exact (``truth.build_rig``; ``calibrate --joint``).
    ``beams`` / ``columns`` 0 (default): the pattern's (``DEFAULT_LAYOUT``: 64 x 1024 spinning, 6 x 4000
    rosette), filled in on construction. ``odometry`` False: no ``/tf`` odometry is written (a raw sensor
    log; the truth file still has the trajectory).
    ``time_offset_ms``: every camera's clock minus the lidar clock, ms (an image stamped t was exposed at lidar
    time t - offset); ``readout_ms``: every camera's rolling-shutter readout, ms from the first image row to the
    last (0: global shutter; the stamp is the first row's time). Only what the images show depends on them:
    stamps, ``/tf`` odometry (lidar time) and scans do not.
    """

    fmt: LogFormat = "mcap"
    frames: int = 20
    scene: str = "street"
    beams: int = 0
    columns: int = 0
    cameras: int = 1
    fisheye: bool = False
    panorama: bool = False
    rectified: bool = False
    wide_angle: bool = False
    compressed: bool = False
    organized: bool = False
    speed_m_s: float | None = None
    perturb_deg: float = 2.0
    perturb_m: float = 0.1
    drift: str = "cameras"
    seed: int = 0
    width: int = 1280
    height: int = 720
    camera_rate_hz: float = 10.0
    lidar_rate_hz: float = 10.0
    deskew: bool = True
    max_range_m: float = 100.0
    lidar: str = "spinning"
    lidar_roll_deg: float = 0.0
    camera_yaw_deg: float = 0.0
    camera_roll_deg: float = 0.0
    odometry: bool = True
    tf_static: bool = True
    time_offset_ms: float = 0.0
    readout_ms: float = 0.0

    def __post_init__(self) -> None:
        beams, columns = DEFAULT_LAYOUT.get(self.lidar, (0, 0))
        if self.beams == 0:
            object.__setattr__(self, "beams", beams)
        if self.columns == 0:
            object.__setattr__(self, "columns", columns)

    def validate(self) -> None:
        """Raise ConfigError with a one-line message for any nonsense value."""
        checks = [
            (self.fisheye + self.panorama + self.rectified + self.wide_angle <= 1,
             "choose one of fisheye, panorama, rectified and wide-angle cameras"),
            (
                self.fmt in ("mcap", "ros1", "ros2"),
                f"unknown format {self.fmt!r} (choose from mcap, ros1, ros2)",
            ),
            (self.scene in SCENES, f"unknown scene {self.scene!r} (choose from {', '.join(SCENES)})"),
            (self.frames >= 1, f"frames must be at least 1, got {self.frames}"),
            (self.lidar in LIDAR_PATTERNS, f"unknown lidar {self.lidar!r} (choose from {', '.join(LIDAR_PATTERNS)})"),
            (
                self.lidar != "spinning" or self.beams in SUPPORTED_BEAMS,
                f"beams (--beams) must be one of {', '.join(map(str, SUPPORTED_BEAMS))}, got {self.beams}",
            ),
            (
                self.lidar != "rosette" or 1 <= self.beams <= MAX_ROSETTE_LINES,
                f"a rosette lidar has 1..{MAX_ROSETTE_LINES} lines (--beams), got {self.beams}",
            ),
            (self.lidar != "rosette" or not self.organized, "a rosette lidar's scans have no organised form"),
            (
                np.isfinite(self.lidar_roll_deg) and -180 <= self.lidar_roll_deg <= 180,
                f"lidar-roll must be in -180..180 degrees, got {self.lidar_roll_deg}",
            ),
            *[(np.isfinite(angle) and -180 <= angle <= 180, f"{name} must be in -180..180 degrees, got {angle}")
              for name, angle in (("camera-yaw", self.camera_yaw_deg), ("camera-roll", self.camera_roll_deg))],
            (64 <= self.columns <= 4096, f"columns must be in 64..4096, got {self.columns}"),
            (1 <= self.cameras <= MAX_CAMERAS, f"cameras must be in 1..{MAX_CAMERAS}, got {self.cameras}"),
            (
                self.speed_m_s is None or (np.isfinite(self.speed_m_s) and 0 <= self.speed_m_s <= 60),
                f"speed must be in 0..60 m/s, got {self.speed_m_s}",
            ),
            (
                np.isfinite(self.perturb_deg) and 0 <= self.perturb_deg <= 45,
                f"perturb-deg must be in 0..45, got {self.perturb_deg}",
            ),
            (
                np.isfinite(self.perturb_m) and 0 <= self.perturb_m <= 2,
                f"perturb-m must be in 0..2, got {self.perturb_m}",
            ),
            (self.drift in DRIFTS, f"drift must be one of {', '.join(DRIFTS)}, got {self.drift!r}"),
            (0 <= self.seed < 2**63, f"seed must be a non-negative integer, got {self.seed}"),
            (
                16 <= self.width <= 8192 and 16 <= self.height <= 8192,
                f"image size must be 16..8192 pixels a side, got {self.width}x{self.height}",
            ),
            (
                np.isfinite(self.max_range_m) and 1.0 <= self.max_range_m <= 1000.0,
                f"max-range must be in 1..1000 m, got {self.max_range_m}",
            ),
            (
                0.5 <= self.camera_rate_hz <= 100 and 1 <= self.lidar_rate_hz <= 50,
                "sensor rates out of range",
            ),
            (
                np.isfinite(self.time_offset_ms) and abs(self.time_offset_ms) <= MAX_TIME_OFFSET_MS,
                f"time-offset-ms must be in -{MAX_TIME_OFFSET_MS:g}..{MAX_TIME_OFFSET_MS:g} ms, "
                f"got {self.time_offset_ms}",
            ),
            (
                np.isfinite(self.readout_ms) and 0 <= self.readout_ms <= MAX_READOUT_MS,
                f"readout-ms must be in 0..{MAX_READOUT_MS:g} ms, got {self.readout_ms}",
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(message)

    @property
    def speed(self) -> float:
        return DEFAULT_SPEED_M_S[self.scene] if self.speed_m_s is None else float(self.speed_m_s)

    @property
    def time_offset_s(self) -> float:
        """Camera clock minus lidar clock, s."""
        return float(self.time_offset_ms) / 1e3

    @property
    def readout_s(self) -> float:
        """Rolling-shutter readout from the first to the last image row, s (0: global shutter)."""
        return float(self.readout_ms) / 1e3


@dataclass
class SimulationResult:
    """What ``simulate_log`` wrote."""

    log_path: str
    truth_path: str
    format: str
    scene: str
    seed: int
    lidar_scans: int
    camera_images: int
    messages: int
    duration_s: float
    distance_m: float
    runtime_s: float
    lidar_topic: str
    camera_topics: list[str]

    def to_json(self) -> dict[str, object]:
        return asdict(self)


def _event_times(opts: SimulationOptions) -> tuple[list[int], list[list[int]], list[float]]:
    """Scan stamps, per-camera image stamps and per-camera phases (ms after the scan stamps)."""
    scan_period = round(1e9 / opts.lidar_rate_hz)
    scans = [START_NS + k * scan_period for k in range(opts.frames)]
    end = START_NS + opts.frames * scan_period
    rng = np.random.default_rng(np.random.SeedSequence([opts.seed, 0xCA4]))
    phases_ms = [float(np.round(rng.uniform(10.0, 30.0), 3)) for _ in range(opts.cameras)]
    cam_period = round(1e9 / opts.camera_rate_hz)
    images = []
    for phase in phases_ms:
        first = START_NS + round(phase * 1e6)
        images.append(list(range(first, end, cam_period)))
    return scans, images, phases_ms


def camera_pose(
    motion: LoopMotion, T_base_camera: NDArray[np.float64], first_row_s: float, readout_s: float, height: int
) -> NDArray[np.float64]:
    """World pose of a camera's optical frame while it exposes an image whose first row is exposed at
    ``first_row_s`` (s since the start, lidar clock): (4, 4) for a global shutter (``readout_s`` 0), else
    (H, 4, 4) one pose per image row at its own time (``row_times_s``)."""
    if readout_s == 0:
        return motion.T_world_base(first_row_s) @ T_base_camera
    return motion.T_world_base_many(row_times_s(first_row_s, readout_s, height)) @ T_base_camera


Event = tuple[int, int, str, int, int]
"""(log time ns, order, kind, index, sub) of one message to write; ``order`` breaks ties deterministically.
Kinds: ``tf_static``; ``tf`` (index: the stamp, ns); ``lidar`` (index: the scan); ``camera`` (index: the camera,
sub: its image)."""


@dataclass
class _Drive:
    """What one simulation sees: the scene, the vehicle's motion, the rig, its sensors and their stamps (ns)."""

    opts: SimulationOptions
    scene: Scene
    grid: TriangleGrid
    motion: LoopMotion
    rig: Rig
    lidar: LidarModel
    cameras: list[SimCamera]
    scans: list[int]
    images: list[list[int]]
    phases_ms: list[float]

    @classmethod
    def of(cls, opts: SimulationOptions) -> _Drive:
        """The scene, rig, sensors and stamps ``opts`` describe, all seeded by ``opts.seed``."""
        scene = build_scene(opts.scene, opts.seed)
        rig = build_rig(opts.cameras, scene.lidar_height_m, opts.perturb_deg, opts.perturb_m, opts.seed,
                        lidar_roll_deg=opts.lidar_roll_deg, camera_yaw_deg=opts.camera_yaw_deg,
                        camera_roll_deg=opts.camera_roll_deg, drift=opts.drift)
        lidar = LidarModel(beams=opts.beams, columns=opts.columns, period_s=1.0 / opts.lidar_rate_hz,
                           max_range_m=opts.max_range_m, seed=opts.seed,
                           pattern="rosette" if opts.lidar == "rosette" else "spinning")
        make_model = (fisheye_camera if opts.fisheye else panorama_camera if opts.panorama
                      else rectified_stereo_camera if opts.rectified else wide_angle_camera if opts.wide_angle
                      else pinhole_camera)
        cameras = [SimCamera(make_model(opts.width, opts.height), spectral_mix=min(0.15 * i, 0.6))
                   for i in range(opts.cameras)]
        scans, images, phases_ms = _event_times(opts)
        return cls(opts, scene, build_grid(scene.triangles), LoopMotion(scene.route, opts.speed), rig, lidar,
                   cameras, scans, images, phases_ms)

    @staticmethod
    def t_s(stamp_ns: int) -> float:
        """Seconds since the first scan."""
        return (stamp_ns - START_NS) / 1e9

    def events(self) -> list[Event]:
        """Every message of the log, in log-time order."""
        opts = self.opts
        events: list[Event] = [(START_NS, 0, "tf_static", 0, 0)] if opts.tf_static else []
        tf_stamps = set(range(START_NS, self.scans[-1] + round(1e9 / opts.lidar_rate_hz) + 1, TF_PERIOD_NS))
        tf_stamps.update(self.scans)
        for cam_stamps in self.images:
            tf_stamps.update(cam_stamps)
        if opts.odometry:
            events += [(s + 1_000_000, 1, "tf", s, 0) for s in sorted(tf_stamps)]
        scan_latency = round(1e9 / opts.lidar_rate_hz) + 2_000_000
        events += [(s + scan_latency, 2, "lidar", k, 0) for k, s in enumerate(self.scans)]
        for i, cam_stamps in enumerate(self.images):
            events += [(s + 8_000_000, 3 + i, "camera", i, j) for j, s in enumerate(cam_stamps)]
        return sorted(events)

    def scan(self, k: int) -> LidarScan:
        """Scan ``k``, cast from the pose at its stamp (de-skewed) or each column's firing time."""
        rng = np.random.default_rng(np.random.SeedSequence([self.opts.seed, 0x11DA, k]))
        start_s = self.t_s(self.scans[k])
        if self.opts.deskew:
            T = self.motion.T_world_base(start_s) @ self.rig.T_base_lidar
        else:
            T = self.motion.T_world_base_many(start_s + self.lidar.column_times_s()) @ self.rig.T_base_lidar
        return simulate_scan(self.scene, self.grid, self.lidar, T, rng, scan_start_s=start_s)

    def image(self, index: int, sub: int) -> NDArray[np.uint8]:
        """Image ``sub`` of camera ``index``, exposed at its stamp less the camera clock's offset; its own seeded
        noise."""
        exposed_s = self.t_s(self.images[index][sub]) - self.opts.time_offset_s
        T_world_cam = camera_pose(self.motion, self.rig.T_base_cameras[index], exposed_s, self.opts.readout_s,
                                  self.opts.height)
        rng = np.random.default_rng(np.random.SeedSequence([self.opts.seed, 0xC0, index, sub]))
        exposure = 1.0 + 0.05 * np.sin(0.7 * exposed_s + index)
        return render(self.scene, self.grid, self.cameras[index], T_world_cam, rng, exposure_scale=exposure)

    def T_map_lidar(self) -> NDArray[np.float64]:
        """(S, 4, 4) the lidar's pose at each scan stamp in the first scan's lidar frame."""
        T_lidar0_world = invert(self.motion.T_world_base(0.0) @ self.rig.T_base_lidar)
        return np.stack([T_lidar0_world @ self.motion.T_world_base(self.t_s(s)) @ self.rig.T_base_lidar
                         for s in self.scans])


class _ImagesAhead:
    """Camera images rendered one or two events ahead on a helper thread (the kernels release the GIL), so
    rendering overlaps message building and compression."""

    def __init__(self, drive: _Drive, events: list[Event], pool: ThreadPoolExecutor) -> None:
        self.drive, self.pool = drive, pool
        self.jobs = [(index, sub) for _, _, kind, index, sub in events if kind == "camera"]
        self.pending: dict[int, Future[NDArray[np.uint8]]] = {}
        self.next_job = 0

    def next(self, index: int, sub: int) -> NDArray[np.uint8]:
        if self.jobs[self.next_job] != (index, sub):
            raise ProcessingError(f"camera event {(index, sub)} out of order (expected {self.jobs[self.next_job]})")
        for q in range(self.next_job, min(self.next_job + PREFETCH_IMAGES, len(self.jobs))):
            if q not in self.pending:
                self.pending[q] = self.pool.submit(self.drive.image, *self.jobs[q])
        self.next_job += 1
        return self.pending.pop(self.next_job - 1).result()


def _scan_message(drive: _Drive, index: int, profile: rm.Profile) -> Any:
    """Scan ``index`` as a PointCloud2 (organised B x C with ``organized``)."""
    scan = drive.scan(index)
    if not drive.opts.organized:
        points, chans = scan.unorganized()
        return rm.pointcloud2(drive.scans[index], LIDAR_FRAME, points, chans, profile=profile)
    channels: dict[str, NDArray[Any]] = {"intensity": np.nan_to_num(scan.intensity.ravel(), nan=0.0),
                                         "ring": scan.ring.ravel(), "time": scan.time_s.ravel()}
    return rm.pointcloud2(drive.scans[index], LIDAR_FRAME, scan.points_xyz.reshape(-1, 3), channels,
                          organized_shape=scan.valid.shape, profile=profile)


def _write_camera(writer: LogWriter, drive: _Drive, log_ns: int, index: int, sub: int, image: NDArray[np.uint8],
                  profile: rm.Profile) -> None:
    """Image ``sub`` of camera ``index`` and its CameraInfo (1 us before it)."""
    opts, stamp, frame = drive.opts, drive.images[index][sub], camera_frame(index)
    image_topic, info_topic = camera_topics(index, opts.compressed, opts.rectified)
    writer.write(info_topic, "sensor_msgs/msg/CameraInfo", log_ns - 1000,
                 rm.camera_info(stamp, frame, drive.cameras[index].model, profile))
    if opts.compressed:
        writer.write(image_topic, "sensor_msgs/msg/CompressedImage", log_ns,
                     rm.compressed_image(stamp, frame, image, "jpeg", 90, profile))
    else:
        writer.write(image_topic, "sensor_msgs/msg/Image", log_ns, rm.image(stamp, frame, image, "rgb8", profile))


def _write_events(writer: LogWriter, drive: _Drive, events: list[Event], progress: Progress,
                  pool: ThreadPoolExecutor) -> tuple[int, int]:
    """Write every event; (messages, camera images) written."""
    profile: rm.Profile = "ros1" if drive.opts.fmt == "ros1" else "ros2"
    T_odom_world = invert(drive.motion.T_world_base(0.0))
    ahead = _ImagesAhead(drive, events, pool)
    n_messages = n_images = 0
    for log_ns, _, kind, index, sub in events:
        if kind == "tf_static":
            transforms = [(START_NS, BASE_FRAME, LIDAR_FRAME, drive.rig.T_base_lidar)]
            transforms += [(START_NS, LIDAR_FRAME, camera_frame(i), invert(T))
                           for i, T in enumerate(drive.rig.T_camera_lidar_in_log)]
            writer.write("/tf_static", "tf2_msgs/msg/TFMessage", log_ns, rm.tf_message(transforms, profile))
        elif kind == "tf":
            T_odom_base = T_odom_world @ drive.motion.T_world_base(drive.t_s(index))
            writer.write("/tf", "tf2_msgs/msg/TFMessage", log_ns,
                         rm.tf_message([(index, ODOM_FRAME, BASE_FRAME, T_odom_base)], profile))
        elif kind == "lidar":
            writer.write(LIDAR_TOPIC, "sensor_msgs/msg/PointCloud2", log_ns, _scan_message(drive, index, profile))
            progress.update()
        else:
            _write_camera(writer, drive, log_ns, index, sub, ahead.next(index, sub), profile)
            n_messages += 1  # its CameraInfo
            n_images += 1
            progress.update()
        n_messages += 1
    return n_messages, n_images


def _truth_extra(drive: _Drive) -> dict[str, Any]:
    """What the truth file says of the drive beyond the rig and the stamps."""
    opts = drive.opts
    return {
        "frames": opts.frames,
        "lidar": {"pattern": opts.lidar, "roll_deg": opts.lidar_roll_deg, "beams": opts.beams,
                  "columns": opts.columns, "organized": opts.organized, "deskewed": opts.deskew,
                  "rate_hz": opts.lidar_rate_hz, "max_range_m": opts.max_range_m},
        "cameras": [{"camera_topic": camera_topics(i, opts.compressed, opts.rectified)[0],
                     "camera_info_topic": camera_topics(i, opts.compressed, opts.rectified)[1],
                     "phase_ms": drive.phases_ms[i], "model": drive.cameras[i].model.distortion_model,
                     "spectral_mix": drive.cameras[i].spectral_mix} for i in range(opts.cameras)],
        "speed_m_s": opts.speed,
        "note": "T_camera_lidar is exact; T_camera_lidar_in_log is it turned by perturb_deg about a random "
        "axis and moved by perturb_m in a random direction (drift 'lidar': the lidar's mount is, once for all "
        "cameras, so the tf between them is exact)",
        "drift": opts.drift,
        "perturb_deg": opts.perturb_deg,
        "perturb_m": opts.perturb_m,
    }


def simulate_log(out: str | os.PathLike[str], opts: SimulationOptions, *, quiet: bool = True) -> SimulationResult:
    """Simulate ``opts`` and write the log at ``out`` (file; folder for ``ros2``) and its truth file."""
    opts.validate()
    started = time.monotonic()
    out_path = Path(out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    drive = _Drive.of(opts)
    events = drive.events()
    progress = Progress(len(drive.scans) + sum(map(len, drive.images)), desc="simulate", quiet=quiet)
    with (
        ThreadPoolExecutor(max_workers=1, thread_name_prefix="fleetcal-render") as pool,
        LogWriter(out_path, opts.fmt) as writer,
    ):
        n_messages, n_images = _write_events(writer, drive, events, progress, pool)
    progress.close()
    truth = build_truth(rig=drive.rig, compressed=opts.compressed, rectified=opts.rectified,
                        scan_stamps_ns=drive.scans, T_map_lidar=drive.T_map_lidar(), scene=opts.scene,
                        seed=opts.seed, fmt=opts.fmt, extra=_truth_extra(drive), time_offset_s=opts.time_offset_s,
                        readout_s=opts.readout_s)
    truth_path = write_truth(truth_path_for(out_path), truth)
    duration_s = (drive.scans[-1] - START_NS) / 1e9
    topics = [camera_topics(i, opts.compressed, opts.rectified)[0] for i in range(opts.cameras)]
    return SimulationResult(log_path=str(out_path), truth_path=str(truth_path), format=opts.fmt, scene=opts.scene,
                            seed=opts.seed, lidar_scans=len(drive.scans), camera_images=n_images,
                            messages=n_messages, duration_s=duration_s, distance_m=opts.speed * duration_s,
                            runtime_s=time.monotonic() - started, lidar_topic=LIDAR_TOPIC, camera_topics=topics)
