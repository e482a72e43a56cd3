"""End-to-end recipes (inspect, simulate, demo, calibrate, map, process, batch), the CLI, the frame sources
that open and decode logs for the engine, pairing of lidar and camera frames, and log write-back."""
