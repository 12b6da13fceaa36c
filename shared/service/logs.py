"""Logs of the job service as JSON lines carrying the job and stage they are about.

``GRAYLIGHT_LOG_FORMAT=json`` (:func:`configure_logging`, called by ``graylight serve``,
``worker`` and ``beat``) makes every record one JSON object on one line::

    {"time": "2026-12-01T17:55:14.123Z", "level": "INFO", "logger": "workers.runner",
     "message": "...", "job": "9b1e...", "stage": "decode", "stage_id": 41, "process": 1234}

``job``, ``stage`` and ``stage_id`` come from :func:`log_context` (the runner holds one around
each stage it runs; a record's own ``extra={"job": ...}`` wins) and are left out when unknown.
An exception's traceback goes into ``"exc"`` as one string, so a line is still one line.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import logging
import time
from collections.abc import Iterator
from typing import Any

from shared.service.config import Settings

__all__ = ["CONTEXT_FIELDS", "JsonFormatter", "configure_logging", "log_context", "reset_log_context", "set_log_context"]

#: The ids a record carries when known.
CONTEXT_FIELDS = ("job", "stage", "stage_id")

_CONTEXT: contextvars.ContextVar[dict[str, Any] | None] = contextvars.ContextVar("graylight_log_context", default=None)


def set_log_context(**ids: Any) -> contextvars.Token:
    """From now on (in this thread or task) records carry ``ids``; undo with :func:`reset_log_context`."""
    return _CONTEXT.set({**(_CONTEXT.get() or {}), **{k: v for k, v in ids.items() if v is not None}})


def reset_log_context(token: contextvars.Token) -> None:
    _CONTEXT.reset(token)


@contextlib.contextmanager
def log_context(**ids: Any) -> Iterator[None]:
    """Records logged inside the block (in this thread or task) carry ``ids`` (job, stage, ...)."""
    token = set_log_context(**ids)
    try:
        yield
    finally:
        reset_log_context(token)


class JsonFormatter(logging.Formatter):
    """One JSON object a line: time (UTC, ISO 8601, ms), level, logger, message, the context ids."""

    def format(self, record: logging.LogRecord) -> str:
        # As logging.Formatter.format does: handlers and tests read record.message afterwards.
        record.message = record.getMessage()
        t = time.gmtime(record.created)
        doc: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", t) + f".{int(record.msecs):03d}Z",
            "level": record.levelname,
            "logger": record.name,
            "message": record.message,
        }
        context = _CONTEXT.get() or {}
        for k in CONTEXT_FIELDS:
            value = getattr(record, k, None)
            if value is None:
                value = context.get(k)
            if value is not None:
                doc[k] = value
        doc["process"] = record.process
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str, ensure_ascii=False)


def configure_logging(settings: Settings, level: int | str | None = None) -> None:
    """Switch the root logger's handlers to :class:`JsonFormatter` when the configuration says
    ``json`` (one stderr handler is added when there is none); ``text`` leaves logging alone."""
    if settings.log_format != "json":
        return
    root = logging.getLogger()
    if not root.handlers:
        root.addHandler(logging.StreamHandler())
    for handler in root.handlers:
        handler.setFormatter(JsonFormatter())
    if level is not None:
        root.setLevel(level)
