"""Decoded frames from a ``LogReader``: lidar scans, camera images with their CameraInfo, the tf tree."""

from __future__ import annotations

import logging
import re
from collections.abc import Collection, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

from fleetcal.pipeline.camera_model import CameraModel
from fleetcal.pipeline.errors import DecodeError, InputError, TransformError
from fleetcal.pipeline.frames import CameraFrame, LidarFrame
from fleetcal.pipeline.msgtypes import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE_TYPES, POINTCLOUD2, TF_MESSAGE
from fleetcal.pipeline.transforms import TransformTree
from fleetcal.readers.base import LogReader, RawMessage, TopicInfo
from fleetcal.readers.decode import (
    decode_camera_info,
    decode_compressed_image,
    decode_image,
    decode_pointcloud2,
    rectification_rotation,
    stereo_baseline_m,
)
from fleetcal.readers.decode.pointcloud2 import MAX_RANGE_M
from fleetcal.readers.decode.tf import decode_transform

log = logging.getLogger(__name__)


def require_topic(reader: LogReader, topic: str, expected: tuple[str, ...]) -> str:
    """The message type of ``topic``; InputError when it is missing or not one of ``expected``."""
    info = reader.topics.get(topic)
    if info is None:
        raise InputError(f"topic {topic} is not in the log (topics: {', '.join(sorted(reader.topics))})")
    if info.msgtype not in expected:
        raise InputError(f"topic {topic} has type {info.msgtype}, expected {' or '.join(expected)}")
    return info.msgtype


def iter_lidar_frames(
    reader: LogReader, topic: str, start_ns: int | None = None, end_ns: int | None = None,
    max_range_m: float = MAX_RANGE_M,
) -> Iterator[LidarFrame]:
    """Decoded PointCloud2 frames of ``topic`` with ``start_ns <= log time < end_ns``, in log order; points
    beyond ``max_range_m`` (metres) dropped (``decode_pointcloud2``).

    Raises:
        InputError: the topic is missing or not a PointCloud2 topic.
        DecodeError: a message cannot be decoded.
    """
    require_topic(reader, topic, (POINTCLOUD2,))
    for raw in reader.messages(topics=[topic], start_ns=start_ns, end_ns=end_ns):
        yield decode_pointcloud2(reader.deserialize(raw), topic, raw.log_time_ns, max_range_m)


def camera_info_topic_for(image_topic: str, topics: Mapping[str, TopicInfo] | Iterable[str]) -> str | None:
    """The CameraInfo topic of an image topic: ``camera_info`` in the image's namespace or a parent one.

    ``/cam/image_raw`` and ``/cam/image/compressed`` both give ``/cam/camera_info``. With a mapping
    of TopicInfo only CameraInfo topics count. None when there is none.
    """
    if isinstance(topics, Mapping):
        candidates = {name for name, info in topics.items() if info.msgtype == CAMERA_INFO}
    else:
        candidates = set(topics)
    parts = image_topic.rstrip("/").split("/")
    for depth in range(len(parts) - 1, 0, -1):
        name = "/".join(parts[:depth]) + "/camera_info"
        if name in candidates:
            return name
    return None


_RECTIFIED_SEGMENT = re.compile(r"(^|_)rect(ified)?($|_)")


def is_rectified_topic(image_topic: str) -> bool:
    """True for an image topic named as rectified by ROS convention (a path segment ``image_rect``,
    ``image_rect_color``, ``image_rect_raw``, ``rect`` or ``rectified``)."""
    return any(_RECTIFIED_SEGMENT.search(part) for part in image_topic.strip("/").split("/"))


def decode_camera_image(msgtype: str, msg: Any, topic: str, log_time_ns: int = 0) -> CameraFrame:
    """Decode an Image or CompressedImage message object by its type name."""
    if msgtype == COMPRESSED_IMAGE:
        return decode_compressed_image(msg, topic, log_time_ns)
    return decode_image(msg, topic, log_time_ns)


class CameraInfoTracker:
    """The latest CameraModel of a CameraInfo topic, seeded with the topic's first message.

    Images that arrive before their first CameraInfo (in log order) still get a model. ``rectified``:
    the images are rectified (``decode_camera_info(rectified=True)``: P's intrinsics, no distortion,
    a stereo camera's rectification rotation R as ``R_rect``).
    """

    def __init__(self, reader: LogReader, info_topic: str | None, rectified: bool = False) -> None:
        self.topic = info_topic
        self.rectified = rectified
        self.model: CameraModel | None = None
        self._failed = False
        self._told_stereo = False
        if info_topic is not None:
            first = next(iter(reader.messages(topics=[info_topic])), None)
            if first is not None:
                self.update(reader, first)

    @classmethod
    def for_image(cls, reader: LogReader, image_topic: str,
                  rectified_topics: Collection[str] = ()) -> CameraInfoTracker:
        """Tracker of the CameraInfo of ``image_topic`` (``camera_info_topic_for``), rectified when the
        topic's name says so (``is_rectified_topic``) or it is one of ``rectified_topics``."""
        rectified = is_rectified_topic(image_topic) or image_topic in rectified_topics
        return cls(reader, camera_info_topic_for(image_topic, reader.topics), rectified)

    def update(self, reader: LogReader, raw: RawMessage) -> None:
        """Take a new CameraInfo; an undecodable one keeps the previous model (warned once)."""
        try:
            msg = reader.deserialize(raw)
            self.model = decode_camera_info(msg, rectified=self.rectified)
            if self.rectified and not self._told_stereo:
                self._told_stereo = True  # the first decoded CameraInfo tells; the rig does not change
                angle_deg = rectification_rotation(msg)
                if angle_deg > 0.01:
                    log.info("%s: rectified images turned by a rectification rotation R of %.2f deg "
                             "(stereo); points are turned by R before projecting", raw.topic, angle_deg)
                baseline_m = stereo_baseline_m(msg)
                if baseline_m != 0.0:
                    frame_id = getattr(getattr(msg, "header", None), "frame_id", "")
                    log.warning("%s: P holds a stereo baseline of %.3f m, not applied: the images are taken "
                                "to be in %r as this camera's own frame (if it is the left camera's, the "
                                "extrinsic found is off by the baseline)", raw.topic, baseline_m, frame_id)
        except DecodeError as err:
            if not self._failed:
                log.warning("ignoring CameraInfo on %s: %s", raw.topic, err)
            self._failed = True


def iter_camera_frames(
    reader: LogReader, topic: str, start_ns: int | None = None, end_ns: int | None = None
) -> Iterator[CameraFrame]:
    """Decoded Image / CompressedImage frames of ``topic`` with the latest CameraInfo attached.

    ``camera`` is None when the log has no CameraInfo for the topic (see ``camera_info_topic_for``).

    Raises:
        InputError: the topic is missing or not an image topic.
        DecodeError, UnsupportedEncodingError: an image cannot be decoded.
    """
    msgtype = require_topic(reader, topic, IMAGE_TYPES)
    info = CameraInfoTracker.for_image(reader, topic)
    wanted = [topic] if info.topic is None else [topic, info.topic]
    for raw in reader.messages(topics=wanted, start_ns=start_ns, end_ns=end_ns):
        if raw.topic == info.topic:
            info.update(reader, raw)
            continue
        frame = decode_camera_image(msgtype, reader.deserialize(raw), topic, raw.log_time_ns)
        frame.camera = info.model
        yield frame


@dataclass
class TfCheck:
    """What ``check_tf`` found in a log's ``/tf`` and ``/tf_static``.

    Attributes:
        tree: the edges that decoded (bad entries left out).
        bad_entries: entries skipped, per topic (NaN or infinite values, a quaternion that is not a
            rotation, a frame to itself, an empty frame name, an undecodable message).
        first_bad: the first bad entry's reason, for messages.
        structure: why the edges do not form a tree (a frame with two parents, a loop), one line each.
    """

    tree: TransformTree
    bad_entries: dict[str, int] = field(default_factory=dict)
    first_bad: str | None = None
    structure: list[str] = field(default_factory=list)

    def bad_entries_text(self) -> str | None:
        """One line about the skipped entries, or None when there is none."""
        if not self.bad_entries:
            return None
        counts = ", ".join(f"{n} on {topic}" for topic, n in sorted(self.bad_entries.items()))
        return f"skipped {sum(self.bad_entries.values())} bad tf entries ({counts}); first: {self.first_bad}"


def tf_structure_problems(tree: TransformTree) -> list[str]:
    """Why ``tree``'s edges are not a tf tree, one line each: a frame with more than one parent (tf gives
    each frame one), and loops of parent -> child edges (``velo -> camera`` and ``camera -> velo``)."""
    parents: dict[str, set[str]] = {}
    for parent, child, _ in tree.edges():
        parents.setdefault(child, set()).add(parent)
    problems = [
        f"frame {child!r} has {len(ps)} parents ({', '.join(repr(p) for p in sorted(ps))}); tf allows one"
        for child, ps in sorted(parents.items())
        if len(ps) > 1
    ]
    reported: set[frozenset[str]] = set()
    for start in sorted(parents):
        loop = _loop_through(start, parents)
        if loop and frozenset(loop) not in reported:
            reported.add(frozenset(loop))
            problems.append("tf edges form a loop: " + " -> ".join(repr(f) for f in [*loop, loop[0]]))
    return problems


def _loop_through(start: str, parents: Mapping[str, set[str]]) -> list[str] | None:
    """Frames of a parent -> child loop through ``start`` (parent first, from the smallest name), or None
    (depth-first search)."""
    stack: list[tuple[str, list[str]]] = [(start, [start])]
    seen: set[str] = set()
    while stack:
        node, path = stack.pop()
        for parent in sorted(parents.get(node, ())):
            if parent == start:
                loop = path[::-1]
                first = loop.index(min(loop))
                return loop[first:] + loop[:first]
            if parent not in seen:
                seen.add(parent)
                stack.append((parent, [*path, parent]))
    return None


def add_tf_message(check: TfCheck, topic: str, transforms: Iterable[Any], static: bool) -> None:
    """Add a TFMessage's transforms to ``check.tree``; bad entries are counted in ``check``."""
    for stamped in transforms:
        try:
            stamp_ns, parent, child, T_parent_child = decode_transform(stamped)
            check.tree.add(parent, child, T_parent_child, stamp_ns, static=static)
        except TransformError as err:
            check.bad_entries[topic] = check.bad_entries.get(topic, 0) + 1
            check.first_bad = check.first_bad or f"{err} (on {topic})"


def is_static_tf_topic(topic: str) -> bool:
    """True for a ``tf_static`` topic (``/tf_static``, ``/robot/tf_static``)."""
    return topic.rstrip("/").endswith("tf_static")


def check_tf(reader: LogReader, tolerance_ns: int = 100_000_000) -> TfCheck:
    """The log's ``/tf`` (dynamic) and ``/tf_static`` (static) edges as a TransformTree, with the bad
    entries skipped and counted and the problems of the tree's shape (``tf_structure_problems``)."""
    check = TfCheck(TransformTree(tolerance_ns=tolerance_ns))
    topics = [name for name, info in reader.topics.items() if info.msgtype == TF_MESSAGE]
    if not topics:
        return check
    for raw in reader.messages(topics=topics):
        try:
            transforms = reader.deserialize(raw).transforms
        except DecodeError as err:
            check.bad_entries[raw.topic] = check.bad_entries.get(raw.topic, 0) + 1
            check.first_bad = check.first_bad or str(err)
            continue
        add_tf_message(check, raw.topic, transforms, is_static_tf_topic(raw.topic))
    check.structure = tf_structure_problems(check.tree)
    return check


def load_tf(reader: LogReader, tolerance_ns: int = 100_000_000) -> tuple[TransformTree | None, str | None]:
    """TransformTree of the log's ``/tf`` (dynamic) and ``/tf_static`` (static) topics, and what is wrong
    with them (None: nothing).

    Bad entries (NaN, not a rotation, self-loops, undecodable messages) are skipped, counted and
    reported in one logged warning (and as the problem). Edges that are not a tree (a frame with two
    parents, a loop) give no tree: which of two disagreeing transforms is meant cannot be known, so none is
    used; the problem names the frames.
    """
    check = check_tf(reader, tolerance_ns)
    bad = check.bad_entries_text()
    if bad:
        log.warning("%s", bad)
    if check.structure:
        return None, f"the log's tf is not a tree: {'; '.join(check.structure)}"
    return check.tree, bad


def load_tf_tree(reader: LogReader, tolerance_ns: int = 100_000_000) -> TransformTree:
    """``load_tf``'s tree.

    Raises:
        TransformError: the edges are not a tree (the message names the frames).
    """
    tree, problem = load_tf(reader, tolerance_ns)
    if tree is None:
        raise TransformError(str(problem))
    return tree
