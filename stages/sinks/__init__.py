"""Sinks of results: Parquet tables, report PNGs, atomic outputs."""
