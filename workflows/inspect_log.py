"""What a log holds: topics, counts, rates, frame ids, lidar/camera topics, tf edges, and what the
first scan of each lidar topic carries (its channels and per-point times).

``inspect_log`` makes one streaming pass over the raw messages (bytes only) and deserialises just
the first message of each topic (for its ``header.frame_id``; a lidar's is also decoded) and the
``/tf`` + ``/tf_static`` messages (for the tf edges), so inspecting a large log costs one read of its
bytes.
"""

from __future__ import annotations

import contextlib
import datetime as dt
from dataclasses import dataclass, field
from typing import Any

from fleetcal.pipeline.errors import DecodeError
from fleetcal.pipeline.msgtypes import IMAGE_TYPES, POINTCLOUD2
from fleetcal.pipeline.point_times import PointTimeKind, classify_point_times
from fleetcal.readers.base import LogReader
from fleetcal.readers.decode.pointcloud2 import decode_pointcloud2
from fleetcal.readers.frames import camera_info_topic_for
from fleetcal.readers.mcap_reader import TruncationInfo
from fleetcal.readers.open import truncation_of

TF_TOPICS = {"/tf": False, "/tf_static": True}


@dataclass(frozen=True)
class TopicSummary:
    """One topic of the log.

    Attributes:
        name: topic name.
        type: ROS 2 style message type.
        count: number of messages read.
        rate_hz: mean message rate over the topic's own span (log time); None below 2 messages.
        frame_id: ``header.frame_id`` of the first message; None when it has no header or cannot
            be decoded.
        decodable: False when the log carries no usable definition for the type.
    """

    name: str
    type: str
    count: int
    rate_hz: float | None
    frame_id: str | None
    decodable: bool


@dataclass(frozen=True)
class TfEdge:
    """A transform published in the log: ``parent -> child`` (``T_parent_child``)."""

    parent: str
    child: str
    static: bool


@dataclass(frozen=True)
class LidarSummary:
    """The first scan of a lidar topic.

    Attributes:
        points: valid points in it.
        channels: its per-point channels (decoder names, ``time`` normalised to s from the stamp).
        time_range_s: (first, last) per-point time minus the header stamp, s; None without a time field.
        point_times: ``none`` (no time field), ``constant`` (within 1 ms: a scan the driver de-skewed),
            ``sweep`` (within ``point_times.MAX_SWEEP_S`` of the stamp: calibration and mapping move each point by
            it) or ``foreign`` (further: another clock than the header's; not used); see
            ``pipeline.point_times``.
    """

    points: int
    channels: tuple[str, ...]
    time_range_s: tuple[float, float] | None
    point_times: PointTimeKind

    def describe(self) -> str:
        if self.time_range_s is None:
            times = "no per-point times"
        else:
            t0, t1 = self.time_range_s
            meaning = {"constant": "one capture time (a de-skewed scan): used as stamped",
                       "sweep": "used to move each point by its firing time",
                       "foreign": "not a sweep (another clock?): not used"}[self.point_times]  # fmt: skip
            times = f"point times {t0:.6g}..{t1:.6g} s from the stamp, {meaning}"
        return f"{self.points} points; channels {', '.join(self.channels) or 'none'}; {times}"


def lidar_summary(msg: Any, topic: str) -> LidarSummary:
    """``LidarSummary`` of a decoded PointCloud2 message (DecodeError when it cannot be decoded)."""
    frame = decode_pointcloud2(msg, topic)
    times = classify_point_times(frame.channels.get("time"))
    span = None if times.kind == "none" else (times.first_s, times.last_s)
    return LidarSummary(frame.n_points, tuple(frame.channels), span, times.kind)


@dataclass
class InspectReport:
    """The result of ``fleetcal inspect``.

    Attributes:
        paths: the log files.
        format: ``mcap``, ``ros1`` or ``ros2``.
        start_ns, end_ns: log time (ns) of the first and of the last message (0 when empty).
        topics: per-topic summaries, sorted by name.
        lidar_topics: ``PointCloud2`` topics.
        camera_topics: image topics (Image/CompressedImage) with a CameraInfo topic beside them.
        camera_info_topics: image topic -> its CameraInfo topic.
        tf: unique tf edges from ``/tf`` and ``/tf_static``.
        undecodable_topics: topics whose type the log cannot decode.
        truncation: what was lost when the log is damaged, else None.
        lidar_scans: lidar topic -> its first scan's ``LidarSummary`` (where it decodes).
    """

    paths: list[str]
    format: str
    start_ns: int
    end_ns: int
    topics: list[TopicSummary]
    lidar_topics: list[str]
    camera_topics: list[str]
    camera_info_topics: dict[str, str]
    tf: list[TfEdge]
    undecodable_topics: list[str]
    truncation: TruncationInfo | None = None
    message_count: int = field(default=0)
    lidar_scans: dict[str, LidarSummary] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        """Time span of the log in seconds."""
        return (self.end_ns - self.start_ns) / 1e9

    def to_json(self) -> dict[str, Any]:
        """The ``--json`` object (DESIGN.md contract)."""
        return {
            "paths": list(self.paths),
            "format": self.format,
            "start_ns": int(self.start_ns),
            "end_ns": int(self.end_ns),
            "topics": [
                {
                    "name": t.name,
                    "type": t.type,
                    "count": t.count,
                    "rate_hz": t.rate_hz,
                    "frame_id": t.frame_id,
                }
                for t in self.topics
            ],
            "lidar_topics": list(self.lidar_topics),
            "camera_topics": list(self.camera_topics),
            "tf": [{"parent": e.parent, "child": e.child, "static": e.static} for e in self.tf],
            "undecodable_topics": list(self.undecodable_topics),
            "lidar_scans": {
                topic: {"points": v.points, "channels": list(v.channels),
                        "time_range_s": None if v.time_range_s is None else list(v.time_range_s),
                        "point_times": v.point_times}  # fmt: skip
                for topic, v in self.lidar_scans.items()
            },
        }


@dataclass
class _TopicStats:
    count: int = 0
    first_ns: int = 0
    last_ns: int = 0
    frame_id: str | None = None
    decode_failed: bool = False


def _frame_id(msg: Any) -> str | None:
    header = getattr(msg, "header", None)
    frame_id = getattr(header, "frame_id", None)
    return frame_id if isinstance(frame_id, str) else None


def inspect_log(reader: LogReader) -> InspectReport:
    """Summarise ``reader``'s log in one streaming pass (see module docstring)."""
    infos = reader.topics
    stats = {name: _TopicStats() for name in infos}
    edges: dict[tuple[str, str, bool], None] = {}
    scans: dict[str, LidarSummary] = {}
    total = 0
    for raw in reader.messages():
        total += 1
        topic = stats.setdefault(raw.topic, _TopicStats())
        if topic.count == 0:
            topic.first_ns = raw.log_time_ns
        topic.count += 1
        topic.last_ns = max(topic.last_ns, raw.log_time_ns)
        info = infos.get(raw.topic)
        decodable = info is not None and info.decodable and not topic.decode_failed
        is_tf = raw.topic in TF_TOPICS
        if not decodable or (topic.count > 1 and not is_tf):
            continue
        try:
            msg = reader.deserialize(raw)
        except DecodeError:
            topic.decode_failed = True
            continue
        if topic.count == 1:
            topic.frame_id = _frame_id(msg)
            if info is not None and info.msgtype == POINTCLOUD2:
                with contextlib.suppress(DecodeError):  # listed anyway; calibrate / map say what is wrong
                    scans[raw.topic] = lidar_summary(msg, raw.topic)
        if is_tf:
            for transform in getattr(msg, "transforms", []):
                parent = transform.header.frame_id.lstrip("/")
                child = transform.child_frame_id.lstrip("/")
                edges[(parent, child, TF_TOPICS[raw.topic])] = None

    summaries: list[TopicSummary] = []
    for name in sorted(stats):
        topic = stats[name]
        info = infos.get(name)
        span_s = (topic.last_ns - topic.first_ns) / 1e9
        rate = (topic.count - 1) / span_s if topic.count >= 2 and span_s > 0 else None
        summaries.append(
            TopicSummary(
                name=name,
                type=info.msgtype if info is not None else "",
                count=topic.count,
                rate_hz=rate,
                frame_id=topic.frame_id,
                decodable=info is not None and info.decodable and not topic.decode_failed,
            )
        )
    names = [t.name for t in summaries]
    types = {t.name: t.type for t in summaries}
    camera_info: dict[str, str] = {}
    for name in names:
        if types[name] in IMAGE_TYPES:
            info_topic = camera_info_topic_for(name, infos)
            if info_topic is not None:
                camera_info[name] = info_topic
    counted = [t for t in summaries if t.count > 0]
    return InspectReport(
        paths=list(reader.paths),
        format=reader.format,
        start_ns=min((stats[t.name].first_ns for t in counted), default=0),
        end_ns=max((stats[t.name].last_ns for t in counted), default=0),
        topics=summaries,
        lidar_topics=[n for n in names if types[n] == POINTCLOUD2],
        camera_topics=sorted(camera_info),
        camera_info_topics=camera_info,
        tf=sorted((TfEdge(p, c, s) for p, c, s in edges), key=lambda e: (not e.static, e.parent, e.child)),
        undecodable_topics=[t.name for t in summaries if not t.decodable],
        truncation=truncation_of(reader),
        message_count=total,
        lidar_scans=scans,
    )


def _iso(stamp_ns: int) -> str:
    stamp = dt.datetime.fromtimestamp(stamp_ns / 1e9, tz=dt.timezone.utc)
    return stamp.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def format_report(report: InspectReport) -> str:
    """Human-readable text of ``report`` (what ``fleetcal inspect`` prints without ``--json``)."""
    lines = [f"log: {', '.join(report.paths)} ({report.format}, {report.message_count} messages)"]
    if report.message_count:
        lines.append(
            f"time span: {_iso(report.start_ns)} .. {_iso(report.end_ns)} ({report.duration_s:.3f} s; "
            f"{report.start_ns} .. {report.end_ns} ns)"
        )
    else:
        lines.append("time span: (no messages)")
    lines.append("")
    rows = [("topic", "type", "count", "rate Hz", "frame id")]
    for t in report.topics:
        rate = f"{t.rate_hz:.2f}" if t.rate_hz is not None else "-"
        frame_id = t.frame_id if t.frame_id is not None else "-"
        rows.append((t.name, t.type or "?", str(t.count), rate, frame_id))
    widths = [max(len(row[i]) for row in rows) for i in range(5)]
    for row in rows:
        cells = [row[0].ljust(widths[0]), row[1].ljust(widths[1]), row[2].rjust(widths[2]),
                 row[3].rjust(widths[3]), row[4]]
        lines.append("  ".join(cells).rstrip())
    lines.append("")
    lines.append(f"lidar topics: {', '.join(report.lidar_topics) or 'none'}")
    lines.extend(f"  {topic}: {scan.describe()}" for topic, scan in report.lidar_scans.items())
    cameras = [f"{c} (info: {report.camera_info_topics[c]})" for c in report.camera_topics]
    lines.append(f"camera topics: {', '.join(cameras) or 'none'}")
    if report.tf:
        lines.append("tf edges:")
        lines.extend(f"  {e.parent} -> {e.child}{' (static)' if e.static else ''}" for e in report.tf)
    else:
        lines.append("tf edges: none")
    if report.undecodable_topics:
        types = {t.name: t.type for t in report.topics}
        lines.append("undecodable topics (no usable definition in the log):")
        lines.extend(f"  {name} ({types.get(name) or '?'})" for name in report.undecodable_topics)
    else:
        lines.append("undecodable topics: none")
    return "\n".join(lines) + "\n"
