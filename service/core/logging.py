"""Structured logs: one JSON object per line on stderr (request lines never carry point data)."""

from __future__ import annotations

import json
import logging
import sys
import time

ACCESS_LOGGER = "mfgnet.access"
APP_LOGGER = "mfgnet.api"

_RESERVED = set(logging.makeLogRecord({}).__dict__) | {"message", "asctime", "color_message"}


class JsonFormatter(logging.Formatter):
    """``{"ts", "level", "logger", "msg", **extra}``; a traceback goes into ``"exc"``."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        entry.update({k: v for k, v in record.__dict__.items() if k not in _RESERVED and not k.startswith("_")})
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


LIBRARY_LEVEL = "WARNING"  # other libraries' loggers (through the root logger): warnings and errors only


def configure_logging(level: str = "info") -> None:
    """Send ``mfgnet.*``, uvicorn's own loggers and Python warnings (``py.warnings``: a numerical warning
    would otherwise print a plain-text line among the JSON ones) to stderr as JSON lines at ``level``, and every
    other library's warnings and errors through the root logger the same way (python-multipart warns of a
    malformed upload; without a root handler Python's last resort printed it as a plain-text line)."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter())
    logging.captureWarnings(True)
    for name in ("mfgnet", "uvicorn", "uvicorn.error", "py.warnings"):
        logger = logging.getLogger(name)
        logger.handlers[:] = [handler]
        logger.setLevel(level.upper())
        logger.propagate = False
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(LIBRARY_LEVEL)
