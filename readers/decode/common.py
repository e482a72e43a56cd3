"""Helpers shared by the decoders."""

from __future__ import annotations

from typing import Any


def stamp_to_ns(stamp: Any) -> int:
    """Integer nanoseconds of a ROS time (``sec`` + ``nanosec``; ROS 1 and ROS 2 alike in rosbags)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)
