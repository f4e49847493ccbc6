"""Structured logging: one JSON object per line on stderr (or ``key=value`` text when a TTY).

Usage::

    log = get_logger("rce.robot")
    log.info("robot connected", robot="r1", user="u")
"""
from __future__ import annotations

import json
import logging
import os
import sys
import time


class _Formatter(logging.Formatter):
    def __init__(self, as_json: bool):
        super().__init__()
        self.as_json = as_json

    def format(self, record: logging.LogRecord) -> str:
        fields = getattr(record, "fields", {})
        if self.as_json:
            d = {"ts": round(record.created, 3), "level": record.levelname.lower(), "logger": record.name,
                 "msg": record.getMessage(), **fields}
            if record.exc_info:
                d["exc"] = self.formatException(record.exc_info)
            return json.dumps(d, default=str)
        stamp = time.strftime("%H:%M:%S", time.localtime(record.created))
        kv = " ".join(f"{k}={v}" for k, v in fields.items())
        line = f"{stamp} {record.levelname[0]} {record.name}: {record.getMessage()} {kv}".rstrip()
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


class StructLogger:
    """Thin wrapper: ``log.info(msg, **fields)`` attaches ``fields`` to the record."""

    def __init__(self, logger: logging.Logger):
        self._l = logger

    def _log(self, level: int, msg: str, exc_info=None, **fields) -> None:
        if self._l.isEnabledFor(level):
            self._l.log(level, msg, exc_info=exc_info, extra={"fields": fields}, stacklevel=3)

    def debug(self, msg: str, **fields) -> None:
        self._log(logging.DEBUG, msg, **fields)

    def info(self, msg: str, **fields) -> None:
        self._log(logging.INFO, msg, **fields)

    def warning(self, msg: str, **fields) -> None:
        self._log(logging.WARNING, msg, **fields)

    def error(self, msg: str, **fields) -> None:
        self._log(logging.ERROR, msg, **fields)

    def exception(self, msg: str, **fields) -> None:
        self._log(logging.ERROR, msg, exc_info=True, **fields)


def get_logger(name: str) -> StructLogger:
    """A structured logger named ``name`` (dotted, e.g. ``rce.master``)."""
    return StructLogger(logging.getLogger(name))


def setup_logging(level: str | None = None, as_json: bool | None = None) -> None:
    """Configure the root logger once per process: level from ``RCE_LOG_LEVEL`` (default INFO),
    JSON lines unless stderr is a TTY (override with ``RCE_LOG_JSON=0/1``)."""
    level = (level or os.environ.get("RCE_LOG_LEVEL", "INFO")).upper()
    if as_json is None:
        env = os.environ.get("RCE_LOG_JSON")
        as_json = (env == "1") if env is not None else not sys.stderr.isatty()
    h = logging.StreamHandler(sys.stderr)
    h.setFormatter(_Formatter(as_json))
    root = logging.getLogger()
    root.handlers[:] = [h]
    root.setLevel(level)
    logging.getLogger("websockets").setLevel(logging.WARNING)
    logging.getLogger("picows").setLevel(logging.WARNING)
    logging.getLogger("aiohttp.access").setLevel(logging.WARNING)
