"""Names every layer shares: the ROS message types fleetcal reads and writes, and log container formats.

Type names are ROS 2 style (``sensor_msgs/msg/PointCloud2``) for logs of every format; readers
normalise ROS 1 names to them.
"""

from __future__ import annotations

from typing import Literal

__all__ = [
    "CAMERA_INFO",
    "CAMERA_TYPES",
    "COMPRESSED_IMAGE",
    "IMAGE",
    "IMAGE_TYPES",
    "LIDAR_TYPES",
    "PATH",
    "POINTCLOUD2",
    "TF_MESSAGE",
    "LogFormat",
]

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
PATH = "nav_msgs/msg/Path"

IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
LIDAR_TYPES = frozenset({POINTCLOUD2})
CAMERA_TYPES = frozenset(IMAGE_TYPES)

LogFormat = Literal["mcap", "ros1", "ros2"]
"""Container format of a log: MCAP file, ROS 1 ``.bag``, ROS 2 bag folder."""
