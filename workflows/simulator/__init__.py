"""Synthetic world with exact ground truth: seeded scenes, a spinning lidar, cameras, vehicle motion, and
a log writer (``simulate_log``) that produces MCAP / ROS 1 / ROS 2 logs plus a ``<log>.truth.json``."""

from fleetcal.workflows.simulator.write import SimulationOptions, SimulationResult, simulate_log

__all__ = ["SimulationOptions", "SimulationResult", "simulate_log"]
