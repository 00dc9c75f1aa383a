"""Logs for operators: plain text for a terminal, or one JSON object a line (``ARCLOUD_LOG_FORMAT=json``)
for a log collector; either way with the context of the frame being processed.

``log_context(map_id=..., frame_id=...)`` (a ``with`` block) and ``bind_log_context`` (the rest of the
current task: an HTTP request) put fields in a ``contextvars`` context; ``LogContextFilter``, on the
handler, copies them onto every record logged meanwhile, so that a line logged deep in the step or a
store carries the frame's ids without its call site knowing of them. The context follows a request into
``run_in_threadpool`` (anyio copies it) but not into a new thread.

A JSON line::

    {"time": "2025-01-31T12:00:00.123Z", "level": "DEBUG", "logger": "arcloud.core.step", "message": "...",
     "process": "arcloud-worker-0", "pid": 4242, "thread": "MainThread", "worker": "host-4242",
     "map_id": "office", "device_id": "phone1", "frame_id": "f000012", "deliveries": 1}

plus the fields a call passed as ``extra=``, ``exception`` (the traceback, as one string) when there is
one, and ``client``, ``method``, ``path``, ``status`` on uvicorn's access lines (an upload's: its ids, and ``refused``, the
problem's detail, when it was refused).

No line carries a secret: ``SecretFilter``, on uvicorn's loggers and on the handler, rewrites each record
(message, arguments, fields, traceback) with ``scrub``: a ``token=`` value in a URL (the viewer's
``/viewer?map=M&token=T`` of before, written in clear by the access log then; now refused), an ``Authorization`` header's value and
an API token anywhere become ``***`` (a token keeps its key id, which names the key in ``keys list``).
"""

from __future__ import annotations

import contextvars
import json
import logging
import re
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from datetime import UTC, datetime
from types import MappingProxyType
from typing import Any, Literal, TextIO

LogFormat = Literal["text", "json"]

TEXT_FORMAT = "%(asctime)s %(levelname)s %(processName)s %(name)s: %(message)s"
#: uvicorn's loggers, which it gives handlers of its own; they go through the root's instead.
UVICORN_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access")

_NO_FIELDS: Mapping[str, object] = MappingProxyType({})
_log_context: contextvars.ContextVar[Mapping[str, object]] = contextvars.ContextVar("arcloud_log_context", default=_NO_FIELDS)

#: Attributes every ``LogRecord`` has; any other one came from ``extra=`` or the log context.
_RECORD_ATTRIBUTES = frozenset(logging.makeLogRecord({}).__dict__) | {"message", "asctime", "taskName"}
#: Extras that repeat a line in another form (uvicorn's coloured copy of the message).
_SKIPPED_EXTRAS = frozenset({"color_message"})


@contextmanager
def log_context(**fields: object) -> Iterator[None]:
    """Every line logged in this ``with`` block (in this thread or task) carries ``fields``."""
    token = _log_context.set(MappingProxyType({**_log_context.get(), **fields}))
    try:
        yield
    finally:
        _log_context.reset(token)


def bind_log_context(**fields: object) -> None:
    """Every line logged from now on in the current context carries ``fields``: for an HTTP request, its
    task (uvicorn runs each request in a task of its own, so the fields end with the response)."""
    _log_context.set(MappingProxyType({**_log_context.get(), **fields}))


class LogContextFilter(logging.Filter):
    """Copies the log context's fields onto each record (fields the call passed as ``extra=`` win)."""

    def filter(self, record: logging.LogRecord) -> bool:
        for name, value in _log_context.get().items():
            record.__dict__.setdefault(name, value)
        return True


#: (pattern, replacement) of each secret a log line must not carry (``scrub``).
_SECRETS = (
    (re.compile(r"(?i)(token=)[^&\s\"'#]+"), r"\1***"),  # ?token=..., access_token=...
    (re.compile(r"(?i)(authorization['\"]?\s*[:=,]\s*(?:b?['\"])?)((?:bearer|basic)\s+)?[^\s'\",}]+"), r"\1\2***"),
    (re.compile(r"\b(arc_[0-9a-f]{12})_[A-Za-z0-9_-]{43}"), r"\1_***"),  # an API token (``arcloud.access``)
)


def scrub(text: str) -> str:
    """``text`` without secrets: ``token=`` values, ``Authorization`` values and API tokens become ``***``."""
    for pattern, replacement in _SECRETS:
        text = pattern.sub(replacement, text)
    return text


class SecretFilter(logging.Filter):
    """Scrubs each record's message, string fields and traceback (``scrub``). A record whose message held a
    secret carries the scrubbed message with no arguments, but for uvicorn's access lines, which keep their five
    (client, method, path, HTTP version, status: the JSON lines' fields), the path scrubbed."""

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            message = record.getMessage()
        except Exception:  # noqa: BLE001 - arguments that do not fit the message: the handler reports it
            return True
        cleaned = scrub(message)
        if cleaned != message:
            if record.name == "uvicorn.access" and isinstance(record.args, tuple):
                record.args = tuple(scrub(arg) if isinstance(arg, str) else arg for arg in record.args)
            else:
                record.msg, record.args = cleaned, None
        for name, value in record_fields(record).items():
            if isinstance(value, str):
                record.__dict__[name] = scrub(value)
        if record.exc_info and not record.exc_text:
            record.exc_text = logging.Formatter().formatException(record.exc_info)
        if record.exc_text:
            record.exc_text = scrub(record.exc_text)
        return True


#: The one filter configure_logging puts on loggers (adding it again to a logger is a no-op).
SECRET_FILTER = SecretFilter()


def record_fields(record: logging.LogRecord) -> dict[str, Any]:
    """The fields a record carries beyond logging's own: the log context's and ``extra=``'s."""
    return {k: v for k, v in record.__dict__.items() if k not in _RECORD_ATTRIBUTES and k not in _SKIPPED_EXTRAS}


class TextFormatter(logging.Formatter):
    """``TEXT_FORMAT``, then the record's fields as ``[name=value ...]`` when it has any."""

    def __init__(self) -> None:
        super().__init__(TEXT_FORMAT)

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        fields = record_fields(record)
        if not fields:
            return text
        first, newline, rest = text.partition("\n")  # the fields on the message's line, before any traceback
        return f"{first} [{' '.join(f'{k}={v}' for k, v in fields.items())}]{newline}{rest}"


class JsonFormatter(logging.Formatter):
    """One JSON object a line (the module docstring lists its fields); values JSON cannot hold are written
    as their ``str``."""

    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
            "process": record.processName,
            "pid": record.process,
            "thread": record.threadName,
        }
        if record.name == "uvicorn.access" and isinstance(record.args, tuple) and len(record.args) == 5:
            client, method, path, _http_version, status = record.args
            line.update(client=client, method=method, path=path, status=status)
        for name, value in record_fields(record).items():
            line.setdefault(name, value)
        if record.exc_text:  # formatted already (and scrubbed: SecretFilter)
            line["exception"] = record.exc_text
        elif record.exc_info:
            line["exception"] = self.formatException(record.exc_info)
        if record.stack_info:
            line["stack"] = self.formatStack(record.stack_info)
        return json.dumps(line, default=str, ensure_ascii=False)


def make_formatter(log_format: LogFormat) -> logging.Formatter:
    if log_format == "json":
        return JsonFormatter()
    if log_format == "text":
        return TextFormatter()
    raise ValueError(f"log format: expected text or json, got {log_format!r}")


class StderrHandler(logging.StreamHandler):
    """A ``StreamHandler`` on ``sys.stderr`` as it is when each record is written, not when the handler was
    made: where stderr is replaced (a test's capture that later closes, a daemon's redirection), lines go
    to the current one instead of failing on a closed stream."""

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, _value: object) -> None:  # StreamHandler.__init__ sets it; the property ignores that
        pass


def configure_logging(level: str, log_format: LogFormat = "text") -> None:
    """This process's logging: one handler on the root logger, writing ``log_format`` to stderr with the
    log context; ``arcloud``'s loggers at ``level`` (the root's level, for other libraries, is left as it
    is). uvicorn's loggers that have handlers of their own write through the root's instead, so that every line
    of the process has one format, with its time and context (uvicorn's own text lines had neither). Every line is
    scrubbed of secrets (``SecretFilter`` on the handler and on uvicorn's loggers). Calling it again replaces what it
    did."""
    handler = StderrHandler()
    handler.setFormatter(make_formatter(log_format))
    handler.addFilter(LogContextFilter())
    handler.addFilter(SECRET_FILTER)  # after the context: its fields are scrubbed too
    root = logging.getLogger()
    for old in root.handlers[:]:
        root.removeHandler(old)
    root.addHandler(handler)
    logging.getLogger("arcloud").setLevel(level)
    for name in UVICORN_LOGGERS:  # their records, before any handler (uvicorn's own write text lines)
        logging.getLogger(name).addFilter(SECRET_FILTER)
    for name in UVICORN_LOGGERS:  # through the root's handler, in either format: time, level and context on every line
        logger = logging.getLogger(name)
        if logger.handlers:  # uvicorn's own (none when its access log is off: that stays off)
            logger.handlers.clear()
            logger.propagate = True


__all__ = [
    "JsonFormatter",
    "LogContextFilter",
    "LogFormat",
    "SecretFilter",
    "TextFormatter",
    "bind_log_context",
    "configure_logging",
    "log_context",
    "make_formatter",
    "record_fields",
    "scrub",
]
