"""Per-module log files in the thesis's Figure 2 form, one line per event.

Figure 2 gives each entry the procedure it came from, the date, the user, the terminal, the pid and
a level-tagged message. We keep those, one entry per line so it greps, and add the module and the
conversation the entry belongs to, so a fault can be followed from module to module:

    From machine_request | Date 2026-11-22 12:01:02.345 | User root | Term /dev/pts/0 | PID 812 | Module msched | Conv msched.5f3a.7 MACH_REQ | Note: request 12 queued for entity 4

The conversation comes from a context variable, so it follows an asyncio task without being passed
around: wrap a handler in `conversation(conv_id, cls)`.
"""

from __future__ import annotations

import contextlib
import contextvars
import getpass
import logging
import logging.handlers
import os
import sys
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

TRACE = 5
logging.addLevelName(TRACE, "Trace")
logging.addLevelName(logging.INFO, "Note")
logging.addLevelName(logging.WARNING, "Warning")
logging.addLevelName(logging.ERROR, "Error")

# Each log file is rotated at this size, keeping this many older files (<name>.log.1, ...): no flood
# or loop of errors can fill the disk (docs/operating.md, Logs).
MAX_LOG_BYTES = 8 * 1024 * 1024
LOG_BACKUPS = 3

LEVELS = {"trace": TRACE, "note": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}

_conversation: contextvars.ContextVar[str] = contextvars.ContextVar("gwc_conversation", default="-")


@contextlib.contextmanager
def conversation(conv_id: str, cls: str = "") -> Iterator[None]:
    """Tag every entry logged inside the block (and in tasks it starts) with this conversation."""
    token = _conversation.set(f"{conv_id} {cls}".strip())
    try:
        yield
    finally:
        _conversation.reset(token)


def current_conversation() -> str:
    return _conversation.get()


def _terminal() -> str:
    for fd in (0, 1, 2):
        try:
            return os.ttyname(fd)
        except OSError:
            continue
    return "none"


class Figure2Formatter(logging.Formatter):
    """Formats a record as one Figure 2 entry."""

    def __init__(self, module: str) -> None:
        super().__init__()
        self.module = module
        try:
            self.user = getpass.getuser()
        except (KeyError, OSError):
            self.user = str(os.getuid())
        self.term = _terminal()

    def format(self, record: logging.LogRecord) -> str:
        date = datetime.fromtimestamp(record.created).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]
        conv = getattr(record, "conv", None) or _conversation.get()
        message = record.getMessage().replace("\n", " | ")
        if record.exc_info:
            message += " | " + self.formatException(record.exc_info).replace("\n", " | ")
        return (
            f"From {record.funcName} | Date {date} | User {self.user} | Term {self.term} | "
            f"PID {record.process} | Module {self.module} | Conv {conv} | {record.levelname}: {message}"
        )


class CappedFileHandler(logging.handlers.RotatingFileHandler):
    """A RotatingFileHandler that rotates by the size the file has reached, told by the stream. The
    standard one checks every record before writing it: two stat()s (is it a regular file?), a
    second formatting of the record, a seek; a fifth of a lot script's logging went there. A file
    may pass the cap by one record."""

    def shouldRollover(self, record: logging.LogRecord) -> bool:
        if self.stream is None:
            self.stream = self._open()
        try:
            return self.maxBytes > 0 and self.stream.tell() >= self.maxBytes
        except OSError:  # not a regular file (a pipe): nothing to rotate
            return False


def log_file_name(module: str) -> str:
    """wc:cmm_wc logs to wc-cmm_wc.log: a module name is safe as a file name this way."""
    return module.replace(":", "-").replace("/", "_") + ".log"


def open_log(module: str, log_dir: Path | None, level: str = "note", echo: bool = False) -> logging.Logger:
    """Give a module its logger writing var/log/<module>.log (and stderr too when echo is set)."""
    logger = logging.getLogger(f"gwc.{module}")
    logger.setLevel(LEVELS.get(level, logging.INFO))
    logger.propagate = False
    for h in list(logger.handlers):
        logger.removeHandler(h)
        h.close()
    fmt = Figure2Formatter(module)
    if log_dir is not None:
        log_dir.mkdir(parents=True, exist_ok=True)
        fh = CappedFileHandler(
            log_dir / log_file_name(module), maxBytes=MAX_LOG_BYTES, backupCount=LOG_BACKUPS, encoding="utf-8"
        )
        fh.setFormatter(fmt)
        logger.addHandler(fh)
    if echo or log_dir is None:
        sh = logging.StreamHandler(sys.stderr)
        sh.setFormatter(fmt)
        logger.addHandler(sh)
    return logger
