"""MFGNet runtime: numpy + onnxruntime registration pipeline, HTTP API and CLI (no torch)."""

__version__ = "0.1.0"

import os as _os

# ONNX Runtime's Linux build sends telemetry (DNS lookups of mobile.events.data.microsoft.com) and writes a device id
# under $XDG_CACHE_HOME/Microsoft (by default $HOME/.cache/Microsoft) when it is imported, unless this is set; set
# here, before any module of the service imports it. An ORT_DISABLE_TELEMETRY the environment names is kept.
_os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
