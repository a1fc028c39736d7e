"""Logging set-up: the entry point calls ``configure_logging`` once; modules only call
``structlog.get_logger()``.

JSON lines when stdout is not a terminal (journald under systemd), readable console
output when it is. Log lines about a frame carry ``seq`` (bind it: ``log.bind(seq=n)``).
"""

from __future__ import annotations

import logging
import sys
from typing import Literal

import structlog

LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}


class _CurrentStream:
    """Writes to whatever ``sys.stdout`` (or ``sys.stderr``) is at the time of writing, not
    at configuration: a caller that swaps it (pytest's capture, a CLI run in-process)
    never leaves the loggers holding a closed file."""

    def __init__(self, name: Literal["stdout", "stderr"]) -> None:
        self._name = name

    def _stream(self):
        return getattr(sys, self._name)

    def write(self, text: str) -> int:
        return self._stream().write(text)

    def flush(self) -> None:
        self._stream().flush()

    def isatty(self) -> bool:
        return self._stream().isatty()


def configure_logging(level: str = "info", fmt: Literal["auto", "json", "console"] = "auto", stream=None) -> None:
    if stream is None or stream is sys.stdout:
        stream = _CurrentStream("stdout")
    elif stream is sys.stderr:
        stream = _CurrentStream("stderr")
    use_json = fmt == "json" or (fmt == "auto" and not stream.isatty())
    renderer = structlog.processors.JSONRenderer() if use_json else structlog.dev.ConsoleRenderer(colors=False)
    processors = [
        structlog.contextvars.merge_contextvars,
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
        structlog.processors.StackInfoRenderer(),
        structlog.processors.format_exc_info,
        renderer,
    ]
    structlog.configure(
        processors=processors,
        wrapper_class=structlog.make_filtering_bound_logger(LEVELS[level]),
        logger_factory=structlog.PrintLoggerFactory(file=stream),
        cache_logger_on_first_use=False,
    )
