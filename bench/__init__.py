"""Benchmarks, profiling and selection tools (training side; never part of the runtime image)."""
