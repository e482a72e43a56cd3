"""End-to-end recipes (inspect, simulate, demo, calibrate, map, process, batch) and the CLI."""
