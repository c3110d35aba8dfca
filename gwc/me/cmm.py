"""The CMM's machine side: Listing 9's line protocol over RS-232 with pyserial.

Listing 9 ran on the CMM's own computer and read records from the serial line, each ending in `!`.
The ME is the other end of that line. What it sends, and what the CMM answers:

    ` DOWNLD !`  `<part>!`  `<n>!`  <n bytes>    a recipe to the CMM            -> `OK!`
    ` UPLD !`  `<part>!`                          a recipe back from the CMM     -> `<n>!` <n bytes>, or `NONE!`
    `SETUP RUN !`  `1!`  `<part>!`                set up the part program        (no answer, as in Listing 9)
    `START RUN !`                                 measure the part               -> `PASS!` or `FAIL!`

Listing 9 moved recipe files with kermit after ` DOWNLD !` and ` UPLD !`; the length-prefixed
transfer above takes kermit's place on the same line. A FAIL part is a run that worked and found
the part out of tolerance: RUN_COMPL carries ACK_OK and RESULT FAIL. Run_Fail is kept for a run that
did not work (no answer in time, the line lost).

The port is opened when the machine starts (ME_START), not when the ME process starts, so the ME
may start before the CMM (or its simulator) and a line lost in a run is opened again at the next
start. Serial settings come from the machine's `serial` table in etc/cell.toml; `port = "sim"`
means the pseudo-terminal of the CMM simulator (gwc.me.cmm_sim), published as var/run/cmm-<id>.pty,
and any other port is handed to pyserial's serial_for_url (a device, or socket://, rfc2217://...).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import serial

from gwc.config import Config, MachineSpec
from gwc.errors import ConfigError, LineError
from gwc.ipc.codes import AckCode
from gwc.me.machine import MachineSide, Refusal, RunOutcome

END = b"!"
MAX_RECORD = 125  # Listing 9's BUF_SIZE: a longer record is garbage on the line
MAX_PAYLOAD = 1 << 20  # largest recipe file moved over the line
READ_SLICE = 0.05  # pyserial read timeout: the longest one read blocks
SERIAL_KEYS = ("port", "baudrate", "bytesize", "parity", "stopbits", "timeout", "xonxoff", "rtscts")


def sim_link(cfg: Config, machine_id: str) -> Path:
    """Where the CMM simulator publishes its pseudo-terminal for machine_id."""
    return cfg.run_dir / f"cmm-{machine_id}.pty"


def check_name(name: str) -> str:
    """A part name as a record: ASCII, no `!`, no line ends, short enough for one record."""
    if not name or "!" in name or not name.isascii() or not name.isprintable() or len(name) >= MAX_RECORD:
        raise LineError(f"part name {name!r} cannot be sent as a record")
    return name


class RecordStream:
    """Records ending in `!` over any byte line: `read_some(timeout)` and `write(bytes)`."""

    def __init__(self, read_some: Callable[[float], bytes], write: Callable[[bytes], object], name: str) -> None:
        self._read_some = read_some
        self._write = write
        self.name = name
        self._buf = bytearray()

    def write_record(self, text: str) -> None:
        data = text.encode("ascii")
        if not data.endswith(END) or len(data) > MAX_RECORD:
            raise LineError(f"bad record {text!r}: a record ends in '!' and is at most {MAX_RECORD} bytes")
        self.write_bytes(data)

    def write_bytes(self, data: bytes) -> None:
        try:
            self._write(data)
        except (OSError, serial.SerialException) as e:
            raise LineError(f"writing to {self.name} failed: {e}") from e

    def _fill(self, timeout: float) -> None:
        try:
            self._buf += self._read_some(timeout)
        except (OSError, serial.SerialException) as e:
            raise LineError(f"reading from {self.name} failed: {e}") from e

    def _take_record(self) -> str | None:
        end = self._buf.find(END)
        if end < 0:
            if len(self._buf) > MAX_RECORD:
                junk = bytes(self._buf[:40])
                self._buf.clear()
                raise LineError(f"garbled line {self.name}: {MAX_RECORD}+ bytes without '!' ({junk!r}...)")
            return None
        raw = bytes(self._buf[: end + 1])
        del self._buf[: end + 1]
        try:
            return raw.decode("ascii")
        except UnicodeDecodeError:
            raise LineError(f"garbled record on {self.name}: {raw[:40]!r}") from None

    def poll_record(self) -> str | None:
        """A complete record if one has arrived, without waiting."""
        rec = self._take_record()
        if rec is None:
            self._fill(0.0)
            rec = self._take_record()
        return rec

    def next_record(self, timeout: float) -> str | None:
        """The next record, waiting up to `timeout` s; None if none came."""
        deadline = time.monotonic() + timeout
        while True:
            rec = self._take_record()
            if rec is not None:
                return rec
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._fill(left)

    def read_record(self, timeout: float) -> str:
        """The next record; LineError if none came within `timeout` s (every wait has a deadline)."""
        rec = self.next_record(timeout)
        if rec is None:
            raise LineError(f"no record from {self.name} within {timeout:.1f}s")
        return rec

    def read_bytes(self, n: int, timeout: float) -> bytes:
        deadline = time.monotonic() + timeout
        while len(self._buf) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise LineError(f"{self.name}: {len(self._buf)} of {n} bytes within {timeout:.1f}s")
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
            raise LineError(f"{self.name}: expected a length record, got {rec!r}") from None
        if not 0 <= n <= MAX_PAYLOAD:
            raise LineError(f"{self.name}: length {n} out of range")
        return n

    def discard(self) -> None:
        """Forget what is buffered (a late answer of an abandoned exchange)."""
        self._buf.clear()


def serial_stream(ser: serial.SerialBase, name: str) -> RecordStream:
    """A RecordStream over an open pyserial port (its timeout must be short: READ_SLICE)."""

    def read_some(timeout: float) -> bytes:
        deadline = time.monotonic() + timeout
        while True:
            waiting = ser.in_waiting
            if waiting or timeout > 0:
                data = ser.read(waiting or 1)
                if data:
                    return bytes(data)
            if time.monotonic() >= deadline:
                return b""

    return RecordStream(read_some, ser.write, name)


def open_serial(settings: dict[str, object], port: str) -> serial.SerialBase:
    """Open a port with the machine's settings, as any URL pyserial accepts; LineError if it cannot."""
    kwargs = {k: v for k, v in settings.items() if k not in ("port", "timeout")}
    try:
        return serial.serial_for_url(port, timeout=READ_SLICE, write_timeout=5.0, **kwargs)
    except (serial.SerialException, OSError, ValueError) as e:
        raise LineError(f"cannot open serial port {port}: {e}") from e


class CmmMachine(MachineSide):
    kind = "cmm"
    default_homing_alarm = "HOME_CMM"  # Listing 3: the operator pushes the CMM's start button

    def __init__(self, cfg: Config, spec: MachineSpec, log: logging.Logger) -> None:
        super().__init__(cfg, spec, log)
        settings = dict(self.options.get("serial", dict, {}))
        unknown = set(settings) - set(SERIAL_KEYS)
        if unknown:
            raise ConfigError(f"machine {spec.id}: unknown serial setting(s) {', '.join(sorted(unknown))}")
        if not isinstance(settings.get("port"), str) or not settings["port"]:
            raise ConfigError(f'machine {spec.id}: serial.port is required (a device, a pyserial URL, or "sim")')
        self.settings = settings
        self.answer_timeout = float(settings.get("timeout", 5.0))  # type: ignore[arg-type]
        self.run_timeout = self.options.get("run_timeout", float, 120.0)
        self._ser: serial.SerialBase | None = None
        self._line: RecordStream | None = None
        self._run_deadline = 0.0

    # ----------------------------------------------------------------- the line

    def _port(self) -> str:
        port = str(self.settings["port"])
        if port != "sim":
            return port
        link = sim_link(self.cfg, self.spec.id)
        deadline = time.monotonic() + self.answer_timeout
        while not link.exists():  # the simulator may still be starting
            if time.monotonic() > deadline:
                raise LineError(f"no CMM simulator: {link} does not exist (is `gwc run cmmsim` running?)")
            time.sleep(0.05)
        return os.path.realpath(link)

    def line(self) -> RecordStream:
        """The open line to the CMM, opened now if it is not."""
        if self._line is None:
            port = self._port()
            self._ser = open_serial(self.settings, port)
            self._line = serial_stream(self._ser, f"CMM line {port}")
            self.log.info(
                "serial line to the CMM open: %s (%s)",
                port,
                ", ".join(f"{k}={v}" for k, v in self.settings.items() if k != "port"),
            )
        return self._line

    def drop_line(self, why: str) -> None:
        if self._ser is not None:
            self.log.warning("closing the serial line to the CMM: %s", why)
            try:
                self._ser.close()
            except (OSError, serial.SerialException):
                pass
        self._ser, self._line = None, None

    def _exchange(self, what: str, fn: Callable[[RecordStream], object]) -> object:
        """One exchange on the line; a line failure becomes a Refusal and a closed line (reopened later)."""
        try:
            line = self.line()
            if self._ser is not None:
                self._ser.reset_input_buffer()
            line.discard()
            return fn(line)
        except LineError as e:
            self.drop_line(str(e))
            raise Refusal(AckCode.START_FAIL, f"{what}: {e}") from e

    def _send_recipe(self, line: RecordStream, part: str, content: bytes) -> None:
        line.write_record(" DOWNLD !")
        line.write_record(f"{check_name(part)}!")
        line.write_record(f"{len(content)}!")
        line.write_bytes(content)
        answer = line.read_record(self.answer_timeout)
        if answer != "OK!":
            raise LineError(f"the CMM answered {answer!r} to the download of {part}")

    # ----------------------------------------------------------------- the machine

    def home(self) -> None:
        self._exchange("start", lambda line: None)

    def load(self, recipe_id: str, path: Path) -> None:
        content = path.read_bytes()

        def setup(line: RecordStream) -> None:
            self._send_recipe(line, recipe_id, content)
            line.write_record("SETUP RUN !")
            line.write_record("1!")
            line.write_record(f"{recipe_id}!")

        self._exchange(f"setup of {recipe_id}", setup)

    def download(self, recipe_id: str, path: Path) -> None:
        content = path.read_bytes()
        self._exchange(f"download of {recipe_id}", lambda line: self._send_recipe(line, recipe_id, content))

    def upload(self, recipe_id: str) -> Path:
        def fetch(line: RecordStream) -> bytes | None:
            line.write_record(" UPLD !")
            line.write_record(f"{check_name(recipe_id)}!")
            first = line.read_record(self.answer_timeout)
            if first == "NONE!":
                return None
            return line.read_bytes(line.length_of(first), self.answer_timeout)

        content = self._exchange(f"upload of {recipe_id}", fetch)
        if content is None:
            raise Refusal(AckCode.REC_INVAL, f"the CMM holds no part program {recipe_id}")
        assert isinstance(content, bytes)
        path = self.memory / "upload" / recipe_id
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content)
        return path

    def begin(self) -> None:
        self._exchange("start of the run", lambda line: line.write_record("START RUN !"))
        self._run_deadline = time.monotonic() + self.run_timeout

    def progress(self) -> RunOutcome | None:
        if self._line is None:
            return RunOutcome(AckCode.RUN_FAIL, {"RESULT": "NONE"}, note="serial line closed during the run")
        try:
            rec = self._line.poll_record()
        except LineError as e:
            self.drop_line(str(e))
            return RunOutcome(AckCode.RUN_FAIL, {"RESULT": "NONE"}, note=f"line lost: {e}")
        if rec is None:
            if time.monotonic() > self._run_deadline:
                return RunOutcome(
                    AckCode.RUN_FAIL,
                    {"RESULT": "NONE"},
                    note=f"no PASS!/FAIL! from the CMM within {self.run_timeout:.0f}s",
                )
            return None
        if rec in ("PASS!", "FAIL!"):
            self.log.info("the CMM answered %s", rec)
            return RunOutcome(AckCode.ACK_OK, {"PART": self.recipe_id, "RESULT": rec[:-1]})
        self.log.warning("unexpected record from the CMM during the run: %r", rec)
        return None

    def abort(self, why: str) -> None:
        # Listing 9 has no way to stop a measurement: its late answer is discarded before the next exchange.
        self.log.warning("run %d abandoned (%s): the CMM's answer will be ignored", self.run_no, why)

    def close(self) -> None:
        if self._ser is not None:
            self.drop_line("the ME is stopping")
