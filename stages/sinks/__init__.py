"""Sinks: ROS message builders, log writers (MCAP / ROS 1 / ROS 2), Parquet tables, reports."""
