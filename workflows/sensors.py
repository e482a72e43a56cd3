"""Which topics of a log are lidars and cameras, from the topic list alone (no pass over the data)."""

from __future__ import annotations

from dataclasses import dataclass

from fleetcal.pipeline.errors import InputError, UsageError
from fleetcal.readers.base import LogReader
from fleetcal.readers.frames import IMAGE_TYPES, POINTCLOUD2, camera_info_topic_for


@dataclass(frozen=True)
class SensorTopics:
    """The lidar topic and the camera (image) topics a workflow works on."""

    lidar_topic: str
    camera_topics: list[str]


def lidar_topics(reader: LogReader) -> list[str]:
    return sorted(n for n, t in reader.topics.items() if t.msgtype == POINTCLOUD2 and t.count > 0)


def camera_topics(reader: LogReader) -> list[str]:
    """Image topics with a CameraInfo topic beside them."""
    return sorted(
        n
        for n, t in reader.topics.items()
        if t.msgtype in IMAGE_TYPES and t.count > 0 and camera_info_topic_for(n, reader.topics)
    )


def resolve_lidar(reader: LogReader, lidar_topic: str | None) -> str:
    """The given lidar topic, or the only one in the log.

    Raises:
        InputError: the given topic is not in the log, or the log has no lidar (content: exit 1).
        UsageError: the log has several lidars and none was named (exit 2).
    """
    if lidar_topic:
        if lidar_topic not in reader.topics:
            raise InputError(f"lidar topic {lidar_topic} is not in the log")
        return lidar_topic
    found = lidar_topics(reader)
    if not found:
        raise InputError("the log has no PointCloud2 topic with messages (no lidar to work on)")
    if len(found) > 1:
        raise UsageError(f"the log has {len(found)} PointCloud2 topics ({', '.join(found)}); name one with --lidar")
    return found[0]


def resolve_cameras(reader: LogReader, cameras: list[str] | None, require: bool = True) -> list[str]:
    """The given camera topics (each must have a CameraInfo), or every camera of the log."""
    if cameras:
        for topic in cameras:
            if topic not in reader.topics:
                raise InputError(f"camera topic {topic} is not in the log")
            if reader.topics[topic].msgtype not in IMAGE_TYPES:
                raise InputError(f"topic {topic} is not an image topic ({reader.topics[topic].msgtype})")
            if camera_info_topic_for(topic, reader.topics) is None:
                raise InputError(f"camera {topic} has no CameraInfo topic beside it in the log")
        return list(cameras)
    found = camera_topics(reader)
    if not found and require:
        images = [n for n, t in reader.topics.items() if t.msgtype in IMAGE_TYPES]
        if images:
            raise InputError(f"no CameraInfo for the image topics ({', '.join(sorted(images))})")
        raise InputError("the log has no camera (an image topic with a CameraInfo topic)")
    return found
