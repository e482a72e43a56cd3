"""What a log holds: topics, counts, rates, frame ids, lidar/camera topics, tf edges, what the
first scan of each lidar topic carries (its channels and per-point times), and every problem the
other commands will meet in it.

``inspect_log`` makes one streaming pass over the raw messages. It deserialises the first message of
each topic (for its ``header.frame_id``; a lidar's first scan is also decoded), every tf message (the
edges, with the same checks ``readers.frames.load_tf_tree`` makes), and every PointCloud2, Image,
CompressedImage and CameraInfo message, whose sizes and fields are checked against their data without
decoding points or pixels (``check_pointcloud2``, ``check_image``, ``check_compressed_image``), so
inspecting a log costs about one read of its bytes.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from typing import Any

from fleetcal.pipeline.errors import DecodeError
from fleetcal.pipeline.msgtypes import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, IMAGE_TYPES, POINTCLOUD2, TF_MESSAGE
from fleetcal.pipeline.point_times import PointTimeKind, classify_point_times
from fleetcal.pipeline.transforms import TransformTree
from fleetcal.readers.base import LogReader, RawMessage, TopicInfo
from fleetcal.readers.decode.camera_info import decode_camera_info
from fleetcal.readers.decode.image import check_compressed_image, check_image
from fleetcal.readers.decode.pointcloud2 import MAX_RANGE_M, check_pointcloud2, decode_pointcloud2
from fleetcal.readers.frames import (
    TfCheck,
    add_tf_message,
    camera_info_topic_for,
    is_static_tf_topic,
    tf_structure_problems,
)
from fleetcal.readers.mcap_reader import TruncationInfo
from fleetcal.readers.open import truncation_of

CHECKS: dict[str, Any] = {
    POINTCLOUD2: check_pointcloud2,
    IMAGE: check_image,
    COMPRESSED_IMAGE: check_compressed_image,
    CAMERA_INFO: decode_camera_info,
}
"""Message type -> a check of one deserialised message that raises DecodeError as the commands would."""


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
        dropped: points dropped at decode: NaN or infinite, all zero (no return), or beyond ``max_range_m``.
        beyond_range: of those, finite points beyond ``max_range_m``.
        max_range_m: the range limit used, metres (``io.max_range_m``).
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
    dropped: int = 0
    beyond_range: int = 0
    max_range_m: float = MAX_RANGE_M

    def describe(self) -> str:
        if self.time_range_s is None:
            times = "no per-point times"
        else:
            t0, t1 = self.time_range_s
            meaning = {"constant": "one capture time (a de-skewed scan): used as stamped",
                       "sweep": "used to move each point by its firing time",
                       "foreign": "not a sweep (another clock?): not used"}[self.point_times]  # fmt: skip
            times = f"point times {t0:.6g}..{t1:.6g} s from the stamp, {meaning}"
        dropped = ""
        if self.dropped:
            far = f", {self.beyond_range} of them beyond {self.max_range_m:g} m" if self.beyond_range else ""
            dropped = f" ({self.dropped} dropped: NaN, zero{far})"
        return f"{self.points} points{dropped}; channels {', '.join(self.channels) or 'none'}; {times}"

    def problem(self, topic: str) -> str | None:
        """The problem the first scan shows to the other commands, or None."""
        if self.beyond_range:
            return (f"{topic}: the first scan has {self.beyond_range} points beyond io.max_range_m = "
                    f"{self.max_range_m:g} m (corrupt coordinates?): they are dropped")
        if self.points == 0:
            return f"{topic}: the first scan has no valid point ({self.dropped} NaN, infinite or zero)"
        return None


def lidar_summary(msg: Any, topic: str, max_range_m: float = MAX_RANGE_M) -> LidarSummary:
    """``LidarSummary`` of a decoded PointCloud2 message (DecodeError when it cannot be decoded)."""
    frame = decode_pointcloud2(msg, topic, max_range_m=max_range_m)
    times = classify_point_times(frame.channels.get("time"))
    span = None if times.kind == "none" else (times.first_s, times.last_s)
    beyond = 0
    if frame.dropped_points:
        beyond = decode_pointcloud2(msg, topic, max_range_m=float("inf")).n_points - frame.n_points
    return LidarSummary(frame.n_points, tuple(frame.channels), span, times.kind, frame.dropped_points, beyond,
                        max_range_m)  # fmt: skip


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
        problems: what ``calibrate``, ``map`` and ``process`` will meet, one line each: messages that
            cannot be decoded (per topic: how many, the first reason), bad tf entries, tf edges that
            are not a tree, a first scan with no valid point or with points beyond the range limit, an
            image topic without CameraInfo.
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
    problems: list[str] = field(default_factory=list)

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
            "problems": list(self.problems),
        }


@dataclass
class _TopicStats:
    count: int = 0
    first_ns: int = 0
    last_ns: int = 0
    frame_id: str | None = None
    decode_failed: bool = False
    bad_messages: int = 0
    first_bad: str | None = None


def _frame_id(msg: Any) -> str | None:
    header = getattr(msg, "header", None)
    frame_id = getattr(header, "frame_id", None)
    return frame_id if isinstance(frame_id, str) else None


def inspect_log(reader: LogReader, max_range_m: float = MAX_RANGE_M) -> InspectReport:
    """Summarise ``reader``'s log in one streaming pass (see module docstring); lidar points beyond
    ``max_range_m`` (metres, ``io.max_range_m``) count as problems."""
    infos = reader.topics
    seen = _Seen({name: _TopicStats() for name in infos}, TfCheck(TransformTree()))
    for raw in reader.messages():
        _check_message(reader, raw, infos, seen, max_range_m)
    seen.tf.structure = tf_structure_problems(seen.tf.tree)
    stats, scans = seen.stats, seen.scans
    summaries = [_topic_summary(name, stats[name], infos.get(name)) for name in sorted(stats)]
    names = [t.name for t in summaries]
    types = {t.name: t.type for t in summaries}
    camera_info = {name: info_topic for name in names if types[name] in IMAGE_TYPES
                   and (info_topic := camera_info_topic_for(name, infos)) is not None}
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
        tf=sorted((TfEdge(*edge) for edge in seen.tf.tree.edges()),
                  key=lambda e: (not e.static, e.parent, e.child)),
        undecodable_topics=[t.name for t in summaries if not t.decodable],
        truncation=truncation_of(reader),
        message_count=seen.total,
        lidar_scans=scans,
        problems=_problems(stats, scans, seen.tf) + [
            f"{name}: image topic without a CameraInfo topic beside it: calibrate and process cannot use it"
            for name in names if types[name] in IMAGE_TYPES and name not in camera_info and stats[name].count
        ],
    )


@dataclass
class _Seen:
    """What the pass over a log has seen so far: per-topic counts, the tf tree, each lidar topic's first scan."""

    stats: dict[str, _TopicStats]
    tf: TfCheck
    scans: dict[str, LidarSummary] = field(default_factory=dict)
    total: int = 0


def _check_message(reader: LogReader, raw: RawMessage, infos: dict[str, TopicInfo], seen: _Seen,
                   max_range_m: float) -> None:
    """Count one message and check its content: every message of a checked type or of tf, the first of the
    others (its frame id); a message that does not decode is counted as bad (a whole topic of an unchecked
    type: undecodable)."""
    seen.total += 1
    topic = seen.stats.setdefault(raw.topic, _TopicStats())
    if topic.count == 0:
        topic.first_ns = raw.log_time_ns
    topic.count += 1
    topic.last_ns = max(topic.last_ns, raw.log_time_ns)
    info = infos.get(raw.topic)
    decodable = _decodable(info, topic)
    msgtype = info.msgtype if info is not None else ""
    if not decodable or (topic.count > 1 and msgtype not in CHECKS and msgtype != TF_MESSAGE):
        return
    try:
        msg = reader.deserialize(raw)
    except DecodeError as err:
        if msgtype == TF_MESSAGE:
            seen.tf.bad_entries[raw.topic] = seen.tf.bad_entries.get(raw.topic, 0) + 1
            seen.tf.first_bad = seen.tf.first_bad or str(err)
        elif msgtype in CHECKS:
            _bad_message(topic, err)
        else:
            topic.decode_failed = True
        return
    if topic.count == 1:
        topic.frame_id = _frame_id(msg)
    if msgtype == TF_MESSAGE:
        add_tf_message(seen.tf, raw.topic, getattr(msg, "transforms", []), is_static_tf_topic(raw.topic))
    elif msgtype in CHECKS:
        try:
            CHECKS[msgtype](msg)
            if msgtype == POINTCLOUD2 and raw.topic not in seen.scans:
                seen.scans[raw.topic] = lidar_summary(msg, raw.topic, max_range_m)
        except DecodeError as err:
            _bad_message(topic, err)


def _decodable(info: TopicInfo | None, topic: _TopicStats) -> bool:
    """Whether the topic's messages can be decoded: a known type, and none of its messages failed to."""
    return info is not None and info.decodable and not topic.decode_failed


def _topic_summary(name: str, topic: _TopicStats, info: TopicInfo | None) -> TopicSummary:
    """One topic's line of the report: its type, count, mean rate (Hz) and frame id."""
    span_s = (topic.last_ns - topic.first_ns) / 1e9
    rate = (topic.count - 1) / span_s if topic.count >= 2 and span_s > 0 else None
    return TopicSummary(name=name, type=info.msgtype if info is not None else "", count=topic.count, rate_hz=rate,
                        frame_id=topic.frame_id,
                        decodable=_decodable(info, topic))


def _bad_message(topic: _TopicStats, err: DecodeError) -> None:
    topic.bad_messages += 1
    topic.first_bad = topic.first_bad or str(err)


def _problems(stats: dict[str, _TopicStats], scans: dict[str, LidarSummary], tf: TfCheck) -> list[str]:
    """The report's problem lines (see ``InspectReport.problems``)."""
    problems = [
        f"{name}: {t.bad_messages} of {t.count} messages cannot be decoded (skipped by the other commands); "
        f"first: {t.first_bad}"
        for name, t in sorted(stats.items())
        if t.bad_messages
    ]
    problems.extend(p for topic, scan in sorted(scans.items()) if (p := scan.problem(topic)))
    bad_tf = tf.bad_entries_text()
    if bad_tf:
        problems.append(f"tf: {bad_tf} (not used by the other commands)")
    problems.extend(f"tf: {line}: calibrate then needs --initial, process fails, map ignores the tf"
                    for line in tf.structure)
    return problems


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
    if report.problems:
        lines.append("problems:")
        lines.extend(f"  {p}" for p in report.problems)
    else:
        lines.append("problems: none")
    return "\n".join(lines) + "\n"
