"""Generators of bad inputs: tiny synthetic logs (written with ``workflows.sinks.log_writer``), damaged
copies of them (byte-level MCAP / bag / sqlite damage) and mutated message objects.

Shared by ``tests/test_bad_inputs.py`` (the corpus), ``tests/test_fuzz_decoders.py`` and
``benchmarks/fuzz_long.py``. Nothing here is committed as binary: every input is made on the fly.

The synthetic scene: a lidar (frame ``lidar``, x forward) sees three textured planes in front of a
camera (frame ``camera``, optical: z forward) mounted at ``T_CAMERA_LIDAR``; ``/tf_static`` holds
``lidar -> camera`` (``T_lidar_camera``).
"""

from __future__ import annotations

import copy
import shutil
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.transforms import apply, invert, make_T, to_rpy_deg
from fleetcal.workflows.sinks import ros_messages
from fleetcal.workflows.sinks.log_writer import LogWriter

LIDAR_TOPIC = "/lidar/points"
CAMERA_TOPIC = "/camera/image_raw"
INFO_TOPIC = "/camera/camera_info"
TF_STATIC = "/tf_static"
TF = "/tf"
PC2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
INFO = "sensor_msgs/msg/CameraInfo"
TFMSG = "tf2_msgs/msg/TFMessage"

T_CAMERA_LIDAR = make_T(
    Rotation.from_euler("x", -5, degrees=True).as_matrix() @ np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]]),
    [0.0, -0.08, -0.27],
)
"""Lidar points (x forward, z up) into the camera optical frame (z forward, y down)."""
INITIAL_TEXT = " ".join(f"{v:g}" for v in [0.0, -0.08, -0.27, *to_rpy_deg(T_CAMERA_LIDAR)])
"""``--initial`` equal to ``T_CAMERA_LIDAR``."""
INITIAL_BEHIND = "0 0 0 90 0 90"
"""``--initial`` that turns the camera to look backwards: it sees no lidar point."""

WIDTH, HEIGHT = 160, 120
CAMERA = CameraModel(WIDTH, HEIGHT, np.array([[110.0, 0, 80], [0, 110.0, 60], [0, 0, 1]]), np.zeros(5), "plumb_bob")
STEP_NS = 100_000_000
START_NS = 1_700_000_000_000_000_000

Mutator = Callable[[Any, int], Any]
"""(message object, frame index) -> message object to write (may be the same, modified)."""


def scene_points(rng: np.random.Generator, n: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """(points_xyz (n, 3) float32 in the lidar frame, metres; intensity (n,) float32): three planes."""
    which = rng.integers(0, 3, n)
    u = rng.uniform(-3, 3, n)
    v = rng.uniform(-1.5, 1.5, n)
    x = np.where(which == 0, 8.0, np.where(which == 1, 5.0 + u, 4.0 + 0.5 * u))
    y = np.where(which == 0, u, np.where(which == 1, -2.5, 2.5))
    z = v
    points = np.stack([x, y, z], axis=1).astype(np.float32)
    intensity = ((np.floor(u * 2) + np.floor(v * 2)) % 2 * 0.8 + 0.1).astype(np.float32)
    return points, intensity


def scene_image(points: NDArray[np.float32], intensity: NDArray[np.float32]) -> NDArray[np.uint8]:
    """mono8 (HEIGHT, WIDTH) image of the points' intensity as the camera sees them, plus texture."""
    uv, valid = CAMERA.project(apply(T_CAMERA_LIDAR, points.astype(np.float64)))
    img = np.full((HEIGHT, WIDTH), 40, dtype=np.uint8)
    cols = np.clip(uv[valid, 0].astype(int), 0, WIDTH - 1)
    rows = np.clip(uv[valid, 1].astype(int), 0, HEIGHT - 1)
    img[rows, cols] = (intensity[valid] * 255).astype(np.uint8)
    return img


@dataclass
class SceneSpec:
    """What ``write_scene`` writes; each field changes one thing of a healthy tiny log."""

    frames: int = 3
    n_points: int = 3000
    fmt: Literal["mcap", "ros1", "ros2"] = "mcap"
    compressed: bool = False
    with_tf: bool = True
    with_info: bool = True
    camera_offset_ns: int = 0
    seed: int = 0
    mutate_cloud: Mutator | None = None
    mutate_image: Mutator | None = None
    mutate_info: Mutator | None = None
    mutate_tf: Mutator | None = None
    log_time_ns: Callable[[int], int] | None = None
    """frame index -> log time (default: increasing by ``STEP_NS``)."""
    odometry: Callable[[int], NDArray[np.float64]] | None = None
    """frame index -> ``T_odom_lidar`` written on ``/tf`` (``odom -> lidar``) at the scan's stamp (None: no /tf)."""
    stamp_ns: Callable[[int], int] | None = None
    """frame index -> header stamp of the scan and its image (default: increasing by ``STEP_NS``)."""
    chunk_size: int = 4 * 1024 * 1024
    compression: str | None = "zstd"


def write_scene(path: Path, spec: SceneSpec | None = None) -> Path:
    """Write a tiny lidar + camera log described by ``spec`` at ``path``; returns ``path``."""
    spec = spec or SceneSpec()
    rng = np.random.default_rng(spec.seed)
    profile: Literal["ros1", "ros2"] = "ros1" if spec.fmt == "ros1" else "ros2"
    keep = lambda msg, i: msg  # noqa: E731
    mutate_cloud = spec.mutate_cloud or keep
    mutate_image = spec.mutate_image or keep
    mutate_info = spec.mutate_info or keep
    mutate_tf = spec.mutate_tf or keep
    with LogWriter(path, spec.fmt, compression=spec.compression, chunk_size=spec.chunk_size) as writer:
        if spec.with_tf:
            tf = ros_messages.tf_message([(START_NS, "lidar", "camera", invert(T_CAMERA_LIDAR))], profile)
            writer.write(TF_STATIC, TFMSG, START_NS, mutate_tf(tf, 0))
        for i in range(spec.frames):
            stamp = spec.stamp_ns(i) if spec.stamp_ns else START_NS + i * STEP_NS
            log_time = spec.log_time_ns(i) if spec.log_time_ns else START_NS + i * STEP_NS + 1_000_000
            if spec.odometry is not None:
                odom = ros_messages.tf_message([(stamp, "odom", "lidar", spec.odometry(i))], profile)
                writer.write(TF, TFMSG, log_time - 1000, odom)
            points, intensity = scene_points(rng, spec.n_points)
            cloud = ros_messages.pointcloud2(stamp, "lidar", points, {"intensity": intensity}, profile=profile)
            writer.write(LIDAR_TOPIC, PC2, log_time, mutate_cloud(cloud, i))
            cam_stamp = stamp + spec.camera_offset_ns
            img = scene_image(points, intensity)
            if spec.compressed:
                msg = ros_messages.compressed_image(cam_stamp, "camera", img, "jpeg", profile=profile)
                writer.write(CAMERA_TOPIC, COMPRESSED, log_time + 1000, mutate_image(msg, i))
            else:
                msg = ros_messages.image(cam_stamp, "camera", img, "mono8", profile=profile)
                writer.write(CAMERA_TOPIC, IMAGE, log_time + 1000, mutate_image(msg, i))
            if spec.with_info:
                info = ros_messages.camera_info(cam_stamp, "camera", CAMERA, profile)
                writer.write(INFO_TOPIC, INFO, log_time + 2000, mutate_info(info, i))
    return path


# --- message mutators ---------------------------------------------------------------------------


def set_attrs(**values: Any) -> Mutator:
    """Mutator setting attributes of every message (e.g. ``point_step=4``)."""

    def mutate(msg: Any, i: int) -> Any:
        for key, value in values.items():
            setattr(msg, key, value)
        return msg

    return mutate


def only_frame(index: int, mutate: Mutator) -> Mutator:
    """Apply ``mutate`` to frame ``index`` only."""
    return lambda msg, i: mutate(msg, i) if i == index else msg


def cut_data(keep_fraction: float) -> Mutator:
    """Mutator keeping the first ``keep_fraction`` of ``msg.data`` (size fields unchanged)."""

    def mutate(msg: Any, i: int) -> Any:
        data = np.asarray(msg.data, dtype=np.uint8)
        msg.data = data[: int(data.size * keep_fraction)].copy()
        return msg

    return mutate


def field_attr(name: str, **values: Any) -> Mutator:
    """Mutator setting attributes of the PointField called ``name``."""

    def mutate(msg: Any, i: int) -> Any:
        for field in msg.fields:
            if field.name == name:
                for key, value in values.items():
                    setattr(field, key, value)
        return msg

    return mutate


def cloud_of(points_fn: Callable[[int], NDArray[np.float32]], profile: str = "ros2") -> Mutator:
    """Mutator replacing the cloud by ``points_fn(frame index)`` (x, y, z float32, no channels)."""

    def mutate(msg: Any, i: int) -> Any:
        stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(getattr(msg.header.stamp, "nanosec", 0))
        return ros_messages.pointcloud2(stamp, str(msg.header.frame_id), points_fn(i), profile=profile)  # type: ignore[arg-type]

    return mutate


def tf_translation(x: float, y: float, z: float) -> Mutator:
    """Mutator writing the translation (x, y, z) into every transform of a TFMessage."""

    def mutate(msg: Any, i: int) -> Any:
        for stamped in msg.transforms:
            t = stamped.transform.translation
            t.x, t.y, t.z = x, y, z
        return msg

    return mutate


def tf_extra_edge(parent: str, child: str, x_m: float = 0.0) -> Mutator:
    """Mutator adding a copy of the first transform as ``parent -> child`` (translation x = ``x_m``):
    with ``camera -> lidar`` beside ``lidar -> camera`` a loop, with ``base -> camera`` a second parent."""

    def mutate(msg: Any, i: int) -> Any:
        extra = copy.deepcopy(msg.transforms[0])
        extra.header.frame_id = parent
        extra.child_frame_id = child
        extra.transform.translation.x = x_m
        msg.transforms = [*msg.transforms, extra]
        return msg

    return mutate


def odometry_jump(at_index: int, jump_m: float, step_m: float = 0.5) -> Callable[[int], NDArray[np.float64]]:
    """``T_odom_lidar`` moving ``step_m`` forward per scan, plus ``jump_m`` along y from scan ``at_index`` on."""
    return lambda i: make_T(np.eye(3), [step_m * i, jump_m if i >= at_index else 0.0, 0.0])


def tf_rotation(x: float, y: float, z: float, w: float) -> Mutator:
    """Mutator writing the quaternion (x, y, z, w) into every transform of a TFMessage."""

    def mutate(msg: Any, i: int) -> Any:
        for stamped in msg.transforms:
            q = stamped.transform.rotation
            q.x, q.y, q.z, q.w = x, y, z, w
        return msg

    return mutate


# --- byte-level damage of containers ------------------------------------------------------------

MCAP_MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_CHUNK, OP_DATA_END = 0x01, 0x02, 0x06, 0x0F


@dataclass(frozen=True)
class Record:
    """One MCAP record: opcode and byte range [start, end) in the file (start at the opcode)."""

    opcode: int
    start: int
    end: int

    @property
    def content_start(self) -> int:
        return self.start + 9


def mcap_records(data: bytes) -> list[Record]:
    """The top-level records of an intact MCAP file, in file order (parses opcode + u64 length)."""
    assert data.startswith(MCAP_MAGIC), "not an MCAP file"
    records = []
    pos = len(MCAP_MAGIC)
    while pos + 9 <= len(data) - len(MCAP_MAGIC):
        opcode = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        records.append(Record(opcode, pos, pos + 9 + length))
        pos += 9 + length
        if opcode == OP_FOOTER:
            break
    return records


def first(records: list[Record], opcode: int) -> Record:
    return next(r for r in records if r.opcode == opcode)


def mcap_truncated_in(src: Path, dst: Path, where: Literal["header", "chunk", "summary"]) -> Path:
    """Copy of ``src`` cut inside its header record, its first chunk, or its summary section."""
    data = src.read_bytes()
    records = mcap_records(data)
    if where == "header":
        cut = first(records, OP_HEADER).start + 5
    elif where == "chunk":
        chunk = first(records, OP_CHUNK)
        cut = (chunk.start + chunk.end) // 2
    else:
        data_end = first(records, OP_DATA_END)
        cut = data_end.end + (len(data) - data_end.end) // 2
    dst.write_bytes(data[:cut])
    return dst


def mcap_flip_in_chunk(src: Path, dst: Path, n_bytes: int = 8) -> Path:
    """Copy of ``src`` with ``n_bytes`` bytes inverted in the middle of its first chunk's records."""
    data = bytearray(src.read_bytes())
    chunk = first(mcap_records(bytes(data)), OP_CHUNK)
    mid = (chunk.start + chunk.end) // 2
    for k in range(mid, mid + n_bytes):
        data[k] ^= 0xFF
    dst.write_bytes(bytes(data))
    return dst


def mcap_lying_chunk_length(src: Path, dst: Path, length: int = 1 << 40) -> Path:
    """Copy of ``src`` whose first chunk record claims ``length`` bytes (far past the file end)."""
    data = bytearray(src.read_bytes())
    chunk = first(mcap_records(bytes(data)), OP_CHUNK)
    struct.pack_into("<Q", data, chunk.start + 1, length)
    dst.write_bytes(bytes(data))
    return dst


def mcap_without_summary(src: Path, dst: Path) -> Path:
    """Copy of ``src`` with the summary (and its indexes) removed: data section, then a footer with
    ``summary_start = 0``, then the magic (a valid MCAP a reader must stream)."""
    data = src.read_bytes()
    records = mcap_records(data)
    data_end = first(records, OP_DATA_END)
    body = bytearray(data[: data_end.end])
    body += bytes([OP_FOOTER]) + struct.pack("<QQQI", 20, 0, 0, 0)
    body += MCAP_MAGIC
    dst.write_bytes(bytes(body))
    return dst


def bag_without_index(src: Path, dst: Path) -> Path:
    """Copy of a ROS 1 bag whose bag-header record says ``index_pos = 0`` (unindexed, as after a crash)."""
    data = bytearray(src.read_bytes())
    key = b"index_pos="
    pos = data.find(key)
    assert pos > 0, "no index_pos in the bag header"
    struct.pack_into("<Q", data, pos + len(key), 0)
    dst.write_bytes(bytes(data))
    return dst


def ros2_folder_copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def db3_of(folder: Path) -> Path:
    return next(folder.glob("*.db3"))


def flip_bytes(data: bytes, rng: np.random.Generator, n_flips: int) -> bytes:
    """``data`` with ``n_flips`` random bytes replaced by random values."""
    out = bytearray(data)
    if not out:
        return bytes(out)
    for pos in rng.integers(0, len(out), n_flips):
        out[int(pos)] = int(rng.integers(0, 256))
    return bytes(out)
