"""Log output of every v2v process (server, workers): text lines or one JSON object per line.

A module of its own so that any process sets up logging without importing the server.
"""
from __future__ import annotations

import json
import logging
import sys
import time


class JsonFormatter(logging.Formatter):
    """One JSON object per log line (``--log-format json``): ``time`` (ISO 8601 UTC),
    ``level``, ``logger``, ``message``, and ``exception`` when there is one."""

    def format(self, record: logging.LogRecord) -> str:
        d = {"time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
             "level": record.levelname, "logger": record.name, "message": record.getMessage()}
        if record.exc_info:
            d["exception"] = self.formatException(record.exc_info)
        return json.dumps(d)


#: The logging levels a command accepts by name.
LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


def setup_logging(level: str, fmt: str, name: str) -> None:
    """Log to stderr at ``level`` (a name of :data:`LEVELS`, any case), as text lines prefixed
    by ``name`` or as JSON objects.

    Raises:
        ValueError: ``level`` is not a level's name.
    """
    if str(level).upper() not in LEVELS:
        raise ValueError(f"log level {level!r} is not one of {', '.join(LEVELS)}")
    handler = logging.StreamHandler(sys.stderr)
    if fmt == "json":
        handler.setFormatter(JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter(f"%(asctime)s {name} %(levelname)s %(message)s"))
    logging.basicConfig(level=str(level).upper(), handlers=[handler], force=True)
