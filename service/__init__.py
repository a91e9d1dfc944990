"""MFGNet runtime: numpy + onnxruntime registration pipeline, HTTP API and CLI (no torch)."""

__version__ = "0.1.0"
