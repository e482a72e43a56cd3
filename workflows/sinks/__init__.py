"""Sinks that write logs: ROS message builders, log writers (MCAP / ROS 1 / ROS 2), write-back of raw records."""
