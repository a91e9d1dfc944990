"""Benchmarks, profiling and selection tools (training side; never part of the runtime image)."""

import service  # noqa: F401  (sets ORT_DISABLE_TELEMETRY before a benchmark imports onnxruntime itself)
