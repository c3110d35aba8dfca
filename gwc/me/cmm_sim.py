"""The CMM simulator: the CMM's end of Listing 9's serial line, so the whole CMM path runs anywhere.

It plays what Listing 9 did on the CMM's computer: it reads records ending in `!`, keeps the part
programs downloaded to it, takes the part named after `SETUP RUN !` `1!`, and answers
`START RUN !` with `PASS!` or `FAIL!` once the part is measured. Records it does not know go "to
SUP" as in Listing 9: it logs them.

By default it opens a pseudo-terminal pair, keeps the master end and publishes the slave end as
var/run/cmm-<id>.pty, which the CMM's ME opens as its serial port when `serial.port = "sim"`. With
`sim.port` set it serves that port instead (any URL pyserial accepts). Its behaviour comes from the
machine's `sim` table in etc/cell.toml:

    sim = { measure_time = 0.3, pattern = "PPF" }   # seconds per part; verdicts cycled per part
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import threading
import time
import tty
from pathlib import Path

from gwc.agent.control import notify_ready
from gwc.config import Config, MachineSpec
from gwc.errors import ConfigError, LineError
from gwc.me.cmm import RecordStream, open_serial, serial_stream, sim_link

ANSWER_TIMEOUT = 5.0  # longest wait for the rest of a multi-record command
IDLE_WAIT = 0.2


class PtyEnd:
    """The master end of a pseudo-terminal pair; its slave is the port the ME opens."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo or line editing before the ME sets its end up
        self.slave_name = os.ttyname(self._slave)

    def read_some(self, timeout: float) -> bytes:
        ready, _, _ = select.select([self.master], [], [], max(0.0, timeout))
        return os.read(self.master, 4096) if ready else b""

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.master, view) :]

    def close(self) -> None:
        # The slave end stays open in here until now, so the master never sees a hang-up when
        # the ME closes and reopens its port.
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


class CmmSimulator:
    def __init__(self, cfg: Config, spec: MachineSpec, log: logging.Logger) -> None:
        if spec.kind != "cmm":
            raise ConfigError(f"machine {spec.id} is a {spec.kind} machine: the CMM simulator serves cmm machines")
        sim = spec.options.get("sim", {})
        if not isinstance(sim, dict):
            raise ConfigError(f"machine {spec.id}: sim must be a table")
        self.cfg, self.spec, self.log = cfg, spec, log
        try:
            self.measure_time = float(sim.get("measure_time", 1.0))
        except (TypeError, ValueError):
            raise ConfigError(f"machine {spec.id}: sim.measure_time must be a number of seconds") from None
        self.pattern = str(sim.get("pattern", "P")).upper()
        if self.measure_time < 0 or not self.pattern or set(self.pattern) - {"P", "F"}:
            raise ConfigError(f"machine {spec.id}: sim needs measure_time >= 0 and a pattern of P and F, got {sim!r}")
        self.port = sim.get("port")
        self.programs: dict[str, bytes] = {}
        self.part: str | None = None
        self.measured = 0
        self._verdict: str | None = None
        self._verdict_at = 0.0

    def serve(self, stop: threading.Event) -> int:
        pty: PtyEnd | None = None
        link = sim_link(self.cfg, self.spec.id)
        if self.port:
            ser = open_serial(self.spec.options.get("serial", {}), str(self.port))
            line = serial_stream(ser, f"port {self.port}")
            closer = ser.close
            self.log.info("CMM simulator of %s on %s", self.spec.id, self.port)
        else:
            pty = PtyEnd()
            line = RecordStream(pty.read_some, pty.write, f"pty {pty.slave_name}")
            closer = pty.close
            self._publish(link, pty.slave_name)
        self.log.info("CMM simulator ready: %.2fs per part, verdicts %s", self.measure_time, self.pattern)
        notify_ready()
        try:
            while not stop.is_set():
                self._answer_due(line)
                wait = IDLE_WAIT
                if self._verdict is not None:
                    wait = min(wait, max(0.001, self._verdict_at - time.monotonic()))
                try:
                    rec = line.next_record(wait)
                    if rec is not None:
                        self.handle(rec, line)
                except LineError as e:
                    self.log.warning("%s: dropped", e)
                    line.discard()
        finally:
            if pty is not None:
                with contextlib.suppress(OSError):
                    if os.readlink(link) == pty.slave_name:
                        link.unlink()
            closer()
        return 0

    def _publish(self, link: Path, target: str) -> None:
        link.parent.mkdir(parents=True, exist_ok=True)
        tmp = link.with_name(link.name + ".tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(target, tmp)
        os.replace(tmp, link)
        self.log.info("serial end published: %s -> %s", link, target)

    def _answer_due(self, line: RecordStream) -> None:
        if self._verdict is not None and time.monotonic() >= self._verdict_at:
            verdict, self._verdict = self._verdict, None
            self.log.info("part %s measured: %s", self.part, verdict)
            line.write_record(verdict)

    def handle(self, rec: str, line: RecordStream) -> None:
        """One command from the ME (the branches of Listing 9's listen())."""
        self.log.info("read: %r", rec)
        if rec == " DOWNLD !":
            name = line.read_record(ANSWER_TIMEOUT)[:-1]
            content = line.read_bytes(line.read_length(ANSWER_TIMEOUT), ANSWER_TIMEOUT)
            self.programs[name] = content
            self.log.info("part program %s received (%d bytes)", name, len(content))
            line.write_record("OK!")
        elif rec == " UPLD !":
            name = line.read_record(ANSWER_TIMEOUT)[:-1]
            content = self.programs.get(name)
            if content is None:
                self.log.warning("upload of unknown part program %s", name)
                line.write_record("NONE!")
            else:
                line.write_record(f"{len(content)}!")
                line.write_bytes(content)
        elif rec == "SETUP RUN !":
            one = line.read_record(ANSWER_TIMEOUT)
            if one != "1!":
                self.log.warning("unexpected input after SETUP RUN: %r", one)
            self.part = line.read_record(ANSWER_TIMEOUT)[:-1]
            self.log.info("part name: %s", self.part)
        elif rec == "START RUN !":
            if self.part is None:
                self.log.warning("START RUN with no part set up: FAIL")
                line.write_record("FAIL!")
                return
            letter = self.pattern[self.measured % len(self.pattern)]
            self.measured += 1
            self._verdict = "PASS!" if letter == "P" else "FAIL!"
            self._verdict_at = time.monotonic() + self.measure_time
            self.log.info("measuring part %s (%d)", self.part, self.measured)
        else:
            self.log.info("passed to SUP: %r", rec)


def main(cfg: Config, machine_id: str, log: logging.Logger, stop: threading.Event) -> int:
    """Run the CMM simulator of `machine_id` until `stop` is set."""
    return CmmSimulator(cfg, cfg.machine(machine_id), log).serve(stop)
