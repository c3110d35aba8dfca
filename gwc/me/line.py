"""Listing 9's serial line, both ends: records ending in `!`, the port settings, and Kermit transfers.

A record is at most 125 bytes (Listing 9's BUF_SIZE) of printable ASCII ending in `!`. What is not
(binary bytes, 125 bytes without a `!`) is refused here as Garbage, its bytes shown escaped, and
costs only the exchange it came in. Listing 9's `output()` writes strlen-1 bytes, so a CMM built
from the listing sends its verdict as `PASS` or `FAIL` with no `!`: where a verdict is expected a
bare one is taken once the line has been quiet for VERDICT_QUIET, or at once when the next byte
shows the record is over (see RecordStream.next_record).

The port is any URL pyserial's serial_for_url opens: a device, a pty, `socket://host:port`,
`rfc2217://host:port`. The failures are told apart because the ME answers them differently:
LineLost (the port is gone: EIO, hang-up, refused connection), LineTimeout (nothing came in time)
and Garbage (something came, but not a record).
"""

from __future__ import annotations

import os
import select
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import serial

from gwc.errors import ConfigError, LineError
from gwc.retry import Deadline

END = b"!"
MAX_RECORD = 125  # Listing 9's BUF_SIZE: a longer record is garbage on the line
MAX_PAYLOAD = 1 << 20  # largest recipe file moved over the line
READ_SLICE = 0.05  # pyserial read timeout: the longest one read blocks
VERDICT_QUIET = 0.3  # a bare PASS/FAIL (no `!`, as Listing 9 writes it) is taken after this much quiet
BARE_VERDICTS = (b"PASS", b"FAIL")
SERIAL_KEYS: dict[str, type | tuple[type, ...]] = {
    "port": str,
    "baudrate": int,
    "bytesize": int,
    "parity": str,
    "stopbits": (int, float),
    "xonxoff": bool,
    "rtscts": bool,
    "dsrdtr": bool,
    "timeout": (int, float),  # longest wait for an answer record
    "write_timeout": (int, float),  # longest a write may block (flow control holding us)
    "open_timeout": (int, float),  # longest wait for the port to open (the simulator's pty to appear)
}


class LineLost(LineError):
    """The port is gone (EIO, hang-up, connection refused or closed): the device must be found again."""


class LineTimeout(LineError):
    """No record within the deadline."""


class Garbage(LineError):
    """Bytes that are not a record of Listing 9's grammar."""


def escaped(data: bytes | bytearray, limit: int = 60) -> str:
    """Bytes as a log line shows them: printable ASCII as is, everything else escaped, long runs cut."""
    text = repr(bytes(data[:limit]))[2:-1]
    return text + (f"...({len(data)} bytes)" if len(data) > limit else "")


def serial_settings(raw: object, where: str) -> dict[str, Any]:
    """A machine's `serial` table checked: known keys, right types; ConfigError naming what is wrong."""
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: serial must be a table")
    settings = dict(raw)
    unknown = set(settings) - set(SERIAL_KEYS)
    if unknown:
        raise ConfigError(f"{where}: unknown serial setting(s) {', '.join(sorted(unknown))}")
    for key, value in settings.items():
        kind = SERIAL_KEYS[key]
        if (isinstance(value, bool) and kind is not bool) or not isinstance(value, kind):
            raise ConfigError(f"{where}: serial.{key} = {value!r} has the wrong type")
    if not settings.get("port"):
        raise ConfigError(f'{where}: serial.port is required (a device, a pyserial URL, or "sim")')
    return settings


def open_serial(settings: dict[str, Any], port: str) -> serial.SerialBase:
    """Open a port with the machine's settings, as any URL pyserial accepts; LineLost if it cannot."""
    kwargs = {k: v for k, v in settings.items() if k not in ("port", "timeout", "open_timeout", "write_timeout")}
    # pyserial's RFC 2217 client refuses any write timeout (NotImplementedError at open): its writes go
    # to a socket, bounded by the network and the device server's buffer, not by flow control.
    write_timeout = None if port.startswith("rfc2217://") else float(settings.get("write_timeout", 5.0))
    try:
        return serial.serial_for_url(port, timeout=READ_SLICE, write_timeout=write_timeout, **kwargs)
    except (serial.SerialException, OSError, ValueError) as e:
        raise LineLost(f"cannot open serial port {port}: {e}") from e


class RecordStream:
    """Records ending in `!` over any byte line: `read_some(timeout)` and `write(bytes)`.

    `read_some` returns b"" when nothing came in time and raises (OSError, SerialException, or
    LineLost itself) when the line is gone; all of those become LineLost here.
    """

    def __init__(self, read_some: Callable[[float], bytes], write: Callable[[bytes], object], name: str) -> None:
        self._read_some = read_some
        self._write = write
        self.name = name
        self._buf = bytearray()
        self._last_byte = time.monotonic()

    def write_record(self, text: str) -> None:
        data = text.encode("ascii")
        if not data.endswith(END) or len(data) > MAX_RECORD:
            raise LineError(f"bad record {text!r}: a record ends in '!' and is at most {MAX_RECORD} bytes")
        self.write_bytes(data)

    def write_bytes(self, data: bytes) -> None:
        try:
            self._write(data)
        except LineError:
            raise
        except (OSError, serial.SerialException) as e:
            raise LineLost(f"writing to {self.name} failed: {e}") from e

    def read_raw(self, timeout: float) -> bytes:
        """What is buffered, else what the line gives within `timeout` (for a Kermit transfer)."""
        if self._buf:
            data = bytes(self._buf)
            self._buf.clear()
            return data
        return self._read(timeout)

    def _read(self, timeout: float) -> bytes:
        try:
            data = self._read_some(timeout)
        except LineError:
            raise
        except (OSError, serial.SerialException) as e:
            raise LineLost(f"reading from {self.name} failed: {e}") from e
        if data:
            self._last_byte = time.monotonic()
        return data

    def _fill(self, timeout: float) -> None:
        self._buf += self._read(timeout)

    def _take_record(self, bare_verdict: bool) -> str | None:
        end = self._buf.find(END)
        if bare_verdict and self._buf[:4] in BARE_VERDICTS and end != 4:
            # Listing 9's verdict has no `!`: unambiguous once more bytes follow it, or the line is quiet.
            if len(self._buf) > 4 or time.monotonic() - self._last_byte >= VERDICT_QUIET:
                word = bytes(self._buf[:4]).decode("ascii")
                del self._buf[:4]
                return word + "!"
            return None
        if end < 0:
            if len(self._buf) >= MAX_RECORD:
                junk = bytes(self._buf)
                self._buf.clear()
                raise Garbage(f"{self.name}: {len(junk)} bytes without '!': {escaped(junk)}")
            return None
        raw = bytes(self._buf[: end + 1])
        del self._buf[: end + 1]
        if len(raw) > MAX_RECORD or not all(32 <= b < 127 for b in raw):
            raise Garbage(f"{self.name}: not a record: {escaped(raw)}")
        return raw.decode("ascii")

    def next_record(self, timeout: float, bare_verdict: bool = False) -> str | None:
        """The next record, waiting up to `timeout` s; None if none came.

        `bare_verdict`: a verdict is expected, so `PASS`/`FAIL` without `!` is one.
        """
        deadline = Deadline(timeout)
        while True:
            rec = self._take_record(bare_verdict)
            if rec is not None:
                return rec
            left = deadline.left()
            if left <= 0:
                return None
            self._fill(min(left, VERDICT_QUIET) if bare_verdict else left)

    def poll_record(self, bare_verdict: bool = False) -> str | None:
        """A complete record if one has arrived (one short read of the line), without waiting longer."""
        rec = self._take_record(bare_verdict)
        if rec is None:
            self._fill(0.0)
            rec = self._take_record(bare_verdict)
        return rec

    def read_record(self, timeout: float) -> str:
        """The next record; LineTimeout if none came within `timeout` s (every wait has a deadline)."""
        rec = self.next_record(timeout)
        if rec is None:
            raise LineTimeout(f"no record from {self.name} within {timeout:.1f}s")
        return rec

    def read_bytes(self, n: int, timeout: float) -> bytes:
        deadline = Deadline(timeout)
        while len(self._buf) < n:
            left = deadline.left()
            if left <= 0:
                raise LineTimeout(f"{self.name}: {len(self._buf)} of {n} bytes within {timeout:.1f}s")
            self._fill(left)
        data = bytes(self._buf[:n])
        del self._buf[:n]
        return data

    def read_length(self, timeout: float) -> int:
        """A `<n>!` record: the length of the bytes that follow."""
        return self.length_of(self.read_record(timeout))

    def length_of(self, rec: str) -> int:
        try:
            n = int(rec[:-1])
        except ValueError:
            raise Garbage(f"{self.name}: expected a length record, got {rec!r}") from None
        if not 0 <= n <= MAX_PAYLOAD:
            raise Garbage(f"{self.name}: length {n} out of range")
        return n

    def drain(self, quiet: float, limit: float) -> bytes:
        """Read until the line has been quiet for `quiet` s (at most `limit` s): what an earlier
        exchange left on the line, thrown away before the next."""
        junk = bytearray(self._buf)
        self._buf.clear()
        deadline = Deadline(limit)
        while not deadline.expired:
            data = self._read(quiet)
            if not data:
                break
            junk += data
        return bytes(junk)


def serial_stream(ser: serial.SerialBase, name: str) -> RecordStream:
    """A RecordStream over an open pyserial port (its timeout must be short: READ_SLICE).

    Every call reads at least once (up to READ_SLICE): a port whose device hung up (EIO on a pty,
    a closed socket) is found out by that read even when nothing is expected.
    """

    def read_some(timeout: float) -> bytes:
        deadline = Deadline(timeout)
        while True:
            data = ser.read(ser.in_waiting or 1)
            if data:
                # socket:// says only whether something waits, not how much: read on while it does
                while waiting := ser.in_waiting:
                    data += ser.read(waiting)
                return bytes(data)
            if deadline.expired:
                return b""

    return RecordStream(read_some, ser.write, name)


def kermit(line: RecordStream, args: Sequence[str], cwd: Path, timeout: float) -> None:
    """One Kermit transfer over `line` with G-Kermit (`gkermit -s FILE` or `-r`), as Listing 9 did after
    ` DOWNLD !` and ` UPLD !` with `kermit ilbr /dev/tty2a 9600`.

    gkermit talks on its standard input and output (-X); we carry its bytes to and from the line, so
    the transfer works over every port pyserial opens (a socket:// line has no tty to hand it).
    LineError if it fails or takes longer than `timeout`; LineLost if the line goes meanwhile.
    """
    argv = ["gkermit", "-X", "-q", "-i", "-P", "-w", "-b", "5", *args]
    try:
        proc = subprocess.Popen(argv, cwd=cwd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    except OSError as e:
        raise LineError(f"cannot run gkermit (is Debian's gkermit package installed?): {e}") from e
    assert proc.stdin is not None and proc.stdout is not None and proc.stderr is not None
    out = proc.stdout.fileno()
    os.set_blocking(out, False)
    deadline = Deadline(timeout)
    try:
        while True:
            ready, _, _ = select.select([out], [], [], 0)
            if ready:
                data = os.read(out, 65536)
                if data:
                    # gkermit says goodbye with CR LF, which Listing 9 would read into its next record
                    # (Kermit packets end in a bare CR, so this is never a packet's).
                    line.write_bytes(data[:-2] if data.endswith(b"\r\n") else data)
                    continue
                break  # gkermit closed its output: it is done
            if proc.poll() is not None:
                break
            if deadline.expired:
                raise LineTimeout(f"Kermit transfer ({' '.join(args)}) took longer than {timeout:.0f}s")
            data = line.read_raw(0.01)
            if data:
                try:
                    proc.stdin.write(data)
                    proc.stdin.flush()
                except BrokenPipeError:
                    pass
        code = proc.wait(timeout=max(0.1, deadline.left()))
    except subprocess.TimeoutExpired:
        raise LineTimeout(f"Kermit transfer ({' '.join(args)}) did not end within {timeout:.0f}s") from None
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        err = proc.stderr.read().decode("utf-8", "replace").strip()
        for f in (proc.stdin, proc.stdout, proc.stderr):
            try:
                f.close()
            except OSError:
                pass
    if code != 0:
        raise LineError(f"Kermit transfer ({' '.join(args)}) failed (exit {code}): {err or 'no message'}")
