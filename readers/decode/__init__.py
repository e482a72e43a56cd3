"""Decoders: deserialised ROS message objects (rosbags, ROS 1 or ROS 2) -> fleetcal frames and models."""

from __future__ import annotations

from fleetcal.readers.decode.camera_info import decode_camera_info, rectification_rotation, stereo_baseline_m
from fleetcal.readers.decode.common import stamp_to_ns
from fleetcal.readers.decode.image import SUPPORTED_ENCODINGS, decode_compressed_image, decode_image
from fleetcal.readers.decode.pointcloud2 import decode_pointcloud2
from fleetcal.readers.decode.tf import decode_tf, decode_transform

__all__ = [
    "SUPPORTED_ENCODINGS",
    "decode_camera_info",
    "decode_compressed_image",
    "decode_image",
    "decode_pointcloud2",
    "decode_tf",
    "decode_transform",
    "rectification_rotation",
    "stamp_to_ns",
    "stereo_baseline_m",
]
