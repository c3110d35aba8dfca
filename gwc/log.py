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
import io
import logging
import logging.handlers
import os
import sys
from collections import Counter
from collections.abc import Callable, Iterator
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

# A process's .out file (what it writes outside its log: tracebacks before the log opens, a lot
# script's print()s, a crash of the interpreter) is bounded too: each process writes at most
# MAX_OUT_BYTES there in its life, and a start finding the file past that size moves it to .out.1.
MAX_OUT_BYTES = 1024 * 1024

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


# Every control character (C0, DEL, C1), \n and \r among them, as a visible escape: a field that
# came from outside (a conversation id, a sender's name, a note) can neither start a forged log line
# nor send a terminal its control sequences (docs/security.md).
_ESCAPES = {c: f"\\x{c:02x}" for c in (*range(0x20), *range(0x7F, 0xA0))} | {
    ord("\n"): "\\n",
    ord("\r"): "\\r",
    ord("\t"): "\\t",
}


def escape(text: str) -> str:
    """`text` with every control character escaped (see _ESCAPES); unchanged, and cheap, when it has none."""
    return text if text.isprintable() else text.translate(_ESCAPES)


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
        conv = escape(str(getattr(record, "conv", None) or _conversation.get()))
        message = escape(record.getMessage())
        if record.exc_info:  # a traceback's lines, each escaped, joined on one line
            message += " | " + " | ".join(escape(line) for line in self.formatException(record.exc_info).split("\n"))
        return (
            f"From {record.funcName} | Date {date} | User {escape(self.user)} | Term {escape(self.term)} | "
            f"PID {record.process} | Module {escape(self.module)} | Conv {conv} | {record.levelname}: {message}"
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


class FaultLog:
    """Failures of work that must go on (a heartbeat's steps, the receive path): each counted, and
    logged with its traceback the first time its kind (step and exception type) is seen, so that one
    bad datagram repeated a thousand times a second neither stops the work nor floods the log."""

    MAX_KINDS = 64  # kinds logged apart; past that, counted only

    def __init__(self, log: logging.Logger, stats: Counter[str]) -> None:
        self.log = log
        self.stats = stats
        self._seen: set[tuple[str, str]] = set()

    def run(self, step: str, work: Callable[[], object]) -> None:
        """Do one step of work that must go on; a failure is counted (and logged once per kind)."""
        try:
            work()
        except Exception as e:
            self.failed(step, e)

    def failed(self, step: str, error: BaseException) -> None:
        self.stats["failed_" + step] += 1
        kind = (step, type(error).__name__)
        if kind in self._seen or len(self._seen) >= self.MAX_KINDS:
            return
        self._seen.add(kind)
        self.log.error(
            "%s failed (%s): %s; it goes on, and further %s failures of %s are counted, not logged",
            step,
            kind[1],
            error,
            kind[1],
            step,
            exc_info=error,
        )


def open_out(path: Path) -> int:
    """The descriptor a starting process's stdout and stderr go to (its .out file): appended to,
    moved to <name>.out.1 first once past MAX_OUT_BYTES; never through a symbolic link."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        if path.lstat().st_size >= MAX_OUT_BYTES:
            path.replace(path.with_name(path.name + ".1"))
    except FileNotFoundError:
        pass
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_NOFOLLOW | os.O_CLOEXEC, 0o640)


class CappedStream(io.TextIOBase):
    """A text stream that passes on at most `limit` characters, then one line saying the rest was
    dropped: what a process prints outside its log cannot fill the disk."""

    def __init__(self, stream: io.TextIOBase, limit: int = MAX_OUT_BYTES) -> None:
        super().__init__()
        self.stream = stream
        self.left = limit

    def write(self, s: str) -> int:
        n = len(s)
        if self.left <= 0:
            return n
        if n > self.left:
            s = s[: self.left] + f"\n[gwc: output past {MAX_OUT_BYTES} characters dropped; see the log]\n"
        self.left -= n
        self.stream.write(s)
        return n

    def flush(self) -> None:
        self.stream.flush()

    def fileno(self) -> int:
        return self.stream.fileno()

    def isatty(self) -> bool:
        return self.stream.isatty()

    def writable(self) -> bool:
        return True


def cap_output(limit: int = MAX_OUT_BYTES) -> None:
    """Bound what this process writes to its stdout and stderr (its .out file) from Python."""
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if isinstance(stream, CappedStream):  # a fork of a capped process: a budget of its own
            stream.left = limit
        elif stream is not None:
            setattr(sys, name, CappedStream(stream, limit))
