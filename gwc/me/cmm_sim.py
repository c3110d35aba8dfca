"""The CMM simulator: the CMM's end of Listing 9's serial line, so the whole CMM path runs anywhere.

It plays what Listing 9 did on the CMM's computer: it reads records ending in `!`, keeps the part
programs downloaded to it, takes the part named after `SETUP RUN !` `1!`, and answers
`START RUN !` with `PASS!` or `FAIL!` once the part is measured. While it measures it reads nothing
(Listing 9 loops waiting for the RESULTS file), so what the ME sends meanwhile waits on the line.
Records it does not know go "to SUP" as in Listing 9: it logs them.

Where: by default a pseudo-terminal pair, the slave end published as var/run/cmm-<id>.pty (the
port of an ME with `serial.port = "sim"`); with `sim.listen = "host:port"` a TCP server (the ME's
port is then `socket://host:port`, a serial device server); with `sim.port` any pyserial URL.

What it speaks follows the machine's `transfer`: "line" (ours: length-prefixed recipes, `OK!`,
and `STATUS <n>!` answered `READY <n>!`) or "kermit" (Listing 9: G-Kermit after ` DOWNLD !` and
` UPLD !`; STATUS is passed to SUP like any unknown record). `sim.bang = false` sends the verdict
as Listing 9's output() does, without its `!`. Options, in the machine's `sim` table:

    sim = { measure_time = 0.3, pattern = "PPF", bang = true, listen = "127.0.0.1:7001" }

Faults, so tests can make it misbehave like a real CMM on a shop floor: written as JSON to
var/run/cmm-<id>.fault (fault_file; `inject_fault` does it), taken within IDLE_WAIT:

    {"fault": "silent", "for": 5}        reads and throws away everything, answers nothing (hung)
    {"fault": "garbage", "kind": K}      the next verdict is replaced by garbage: K = text (a record
                                         outside the grammar), binary, long (no `!`), half (never ended)
    {"fault": "hangup", "for": 30}       the line goes (pty closed / connection and listener closed),
                                         and comes back after `for` s (a new pty, the link republished)
    {"fault": "power_cycle", "for": 2}   a hang-up that also forgets the programs, the part and a
                                         measurement in progress
    {"fault": "delay", "for": 12}        the next verdict comes `for` s after START RUN (slow or late)
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import shutil
import socket
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

import serial
from serial.rfc2217 import PortManager

from gwc.agent.control import notify_ready
from gwc.config import Config, MachineSpec
from gwc.errors import ConfigError, LineError
from gwc.me.line import LineLost, RecordStream, escaped, kermit, open_serial, serial_stream
from gwc.me.parts import PartError, is_tar, part_tar, program_from
from gwc.quality.process import measure, read_part
from gwc.quality.recipe import features_of
from gwc.quality.sheet import read_sheet

ANSWER_TIMEOUT = 5.0  # longest wait for the rest of a multi-record command
IDLE_WAIT = 0.2
KERMIT_TIMEOUT = 60.0
FAULTS = ("silent", "garbage", "hangup", "power_cycle", "delay")
GARBAGE = {
    "text": b"XYZZY 42!",
    "binary": b"\x00\xfe\x13PA\x81SS!",
    "long": b"A" * 200,
    "half": b"PAS",
}


def sim_link(cfg: Config, machine_id: str) -> Path:
    """Where the CMM simulator publishes its pseudo-terminal for machine_id."""
    return cfg.run_dir / f"cmm-{machine_id}.pty"


def fault_file(cfg: Config, machine_id: str) -> Path:
    """Where a fault for the simulator of machine_id is written (inject_fault)."""
    return cfg.run_dir / f"cmm-{machine_id}.fault"


def inject_fault(cfg: Config, machine_id: str, fault: str, **params: Any) -> None:
    """Tell the running simulator of machine_id to misbehave (see the module docstring)."""
    if fault not in FAULTS:
        raise ConfigError(f"unknown simulator fault {fault!r}: one of {', '.join(FAULTS)}")
    path = fault_file(cfg, machine_id)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps({"fault": fault, **params}))
    os.replace(tmp, path)


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


class TcpEnd:
    """A serial device server's end: one ME connection at a time on a listening socket; raw bytes
    (the ME's `socket://`) or, with `rfc2217`, Telnet with RFC 2217's port settings (`rfc2217://`)."""

    def __init__(self, listen: str, rfc2217: bool = False) -> None:
        host, _, port = listen.rpartition(":")
        self.address = (host or "127.0.0.1", int(port))
        self.rfc2217 = rfc2217
        self._server: socket.socket | None = None
        self._conn: socket.socket | None = None
        self._telnet: PortManager | None = None  # RFC 2217's Telnet state of the connection

    def _listen(self) -> socket.socket:
        if self._server is None:
            server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                server.bind(self.address)
                server.listen(1)
            except OSError:
                server.close()
                raise
            self._server = server
        return self._server

    def read_some(self, timeout: float) -> bytes:
        if self._conn is None:
            server = self._listen()
            ready, _, _ = select.select([server], [], [], max(0.0, timeout))
            if not ready:
                return b""
            self._conn, _ = server.accept()
            if self.rfc2217:
                # pyserial's server side of RFC 2217; the port settings the ME sets land on a loop://
                # port (a simulator has no UART to set) and are acknowledged as a device server does.
                self._telnet = PortManager(serial.serial_for_url("loop://"), _Sender(self._conn))
            return b""
        ready, _, _ = select.select([self._conn], [], [], max(0.0, timeout))
        if not ready:
            return b""
        try:
            data = self._conn.recv(4096)
        except OSError:
            data = b""
        if data and self._telnet is not None:
            try:
                data = b"".join(self._telnet.filter(data))  # negotiation answered, IAC unescaped
            except OSError:  # answering the negotiation failed: the connection broke
                self._drop()
                return b""
            return data
        if not data:
            self._drop()
        return data

    def _drop(self) -> None:
        """The ME hung up: wait for its next connection."""
        if self._conn is not None:
            self._conn.close()
        self._conn, self._telnet = None, None

    def write(self, data: bytes) -> None:
        if self._conn is None:
            raise LineLost("no ME connected")
        if self._telnet is not None:
            data = b"".join(self._telnet.escape(data))  # a data byte 0xFF doubled, as Telnet wants
        try:
            self._conn.sendall(data)
        except OSError as e:
            self._drop()
            raise LineLost(f"the ME's connection broke: {e}") from e

    def close(self) -> None:
        for s in (self._conn, self._server):
            if s is not None:
                with contextlib.suppress(OSError):
                    s.close()
        self._conn = self._server = None
        self._telnet = None


class _Sender:
    """The connection as RFC 2217's PortManager writes to it (its negotiation answers)."""

    def __init__(self, conn: socket.socket) -> None:
        self.write = conn.sendall


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
        self.listen = sim.get("listen")
        serial_port = spec.options.get("serial", {})
        # A device server speaks what the ME's URL says: raw bytes (socket://) or RFC 2217 (rfc2217://).
        self.rfc2217 = isinstance(serial_port, dict) and str(serial_port.get("port", "")).startswith("rfc2217://")
        self.bang = bool(sim.get("bang", True))
        try:  # measuring a part program's FEATUREs: the gauge's own noise, seeded
            self.gauge_sigma = float(sim.get("gauge_sigma", 0.0005))
            self.seed = int(sim.get("seed", 1))
        except (TypeError, ValueError):
            raise ConfigError(f"machine {spec.id}: sim.gauge_sigma and sim.seed must be numbers") from None
        self._measures: list[str] = []
        self.kermit = spec.options.get("transfer", "line") == "kermit"
        self.store = cfg.var / "cmmsim" / spec.id  # the CMM's /usr/avail/part (Kermit files land here)
        self.programs: dict[str, bytes] = {}
        self.part: str | None = None
        self.measured = 0
        self._verdict: str | None = None
        self._verdict_at = 0.0
        self._silent_until = 0.0
        self._garbage: bytes | None = None
        self._delay: float | None = None
        self._down_until = 0.0

    # ----------------------------------------------------------------- the line's end

    def _open(self) -> tuple[RecordStream, Callable[[], None]]:
        if self.listen:
            end = TcpEnd(str(self.listen), rfc2217=self.rfc2217)
            end._listen()  # bound now, so an ME that connects early is queued, not refused
            self.log.info("CMM simulator of %s listening on %s:%d", self.spec.id, *end.address)
            return RecordStream(end.read_some, end.write, f"tcp {self.listen}"), end.close
        if self.port:
            ser = open_serial(self.spec.options.get("serial", {}), str(self.port))
            self.log.info("CMM simulator of %s on %s", self.spec.id, self.port)
            return serial_stream(ser, f"port {self.port}"), ser.close
        pty = PtyEnd()
        self._publish(sim_link(self.cfg, self.spec.id), pty.slave_name)
        return RecordStream(pty.read_some, pty.write, f"pty {pty.slave_name}"), pty.close

    def _unpublish(self) -> None:
        with contextlib.suppress(OSError):
            sim_link(self.cfg, self.spec.id).unlink()

    def serve(self, stop: threading.Event) -> int:
        line, closer = self._open()
        self.store.mkdir(parents=True, exist_ok=True)
        self.log.info(
            "CMM simulator ready: %.2fs per part, verdicts %s%s, %s transfer",
            self.measure_time,
            self.pattern,
            "" if self.bang else " (without '!', as Listing 9's output())",
            "Kermit" if self.kermit else "line",
        )
        notify_ready()
        try:
            while not stop.is_set():
                fault = self._take_fault()
                if fault in ("hangup", "power_cycle"):
                    closer()
                    self._unpublish()
                    self.log.warning("line down (%s) for %.1fs", fault, self._down_until - time.monotonic())
                    while not stop.is_set() and time.monotonic() < self._down_until:
                        stop.wait(min(IDLE_WAIT, max(0.0, self._down_until - time.monotonic())))
                    reopened = self._reopen(stop)
                    if reopened is None:
                        break
                    line, closer = reopened
                    self.log.warning("line up again after %s", fault)
                    continue
                self._step(line)
        finally:
            if not self.listen and not self.port:
                self._unpublish()
            closer()
        return 0

    def _reopen(self, stop: threading.Event) -> tuple[RecordStream, Callable[[], None]] | None:
        """The line back after a hang-up; a port still taken (its TCP address held a moment) is tried
        again until it opens, or None once the simulator is stopping."""
        while not stop.is_set():
            try:
                return self._open()
            except (OSError, LineError) as e:
                self.log.warning("cannot open the line again (%s): retrying", e)
                stop.wait(IDLE_WAIT)
        return None

    def _step(self, line: RecordStream) -> None:
        now = time.monotonic()
        try:
            if now < self._silent_until:  # hung: the line is read and nothing done with it
                junk = line.drain(IDLE_WAIT, IDLE_WAIT)
                if junk:
                    self.log.info("silent: ignored %s", escaped(junk))
                return
            if self._verdict is not None:  # measuring: Listing 9 reads nothing until the part is done
                time.sleep(min(IDLE_WAIT, max(0.0, self._verdict_at - now)))
                self._answer_due(line)
                return
            rec = line.next_record(IDLE_WAIT)
            if rec is not None:
                self.handle(rec, line)
        except LineLost as e:
            self.log.warning("%s: waiting for the ME", e)
            time.sleep(IDLE_WAIT)
        except LineError as e:
            self.log.warning("%s: dropped", e)
            line.drain(0.05, 1.0)

    def _publish(self, link: Path, target: str) -> None:
        link.parent.mkdir(parents=True, exist_ok=True)
        tmp = link.with_name(link.name + ".tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(target, tmp)
        os.replace(tmp, link)
        self.log.info("serial end published: %s -> %s", link, target)

    # ----------------------------------------------------------------- faults

    def _take_fault(self) -> str | None:
        path = fault_file(self.cfg, self.spec.id)
        try:
            raw = path.read_text()
            path.unlink()
        except FileNotFoundError:
            return None
        try:
            fault = json.loads(raw)
            kind = fault["fault"]
            span = float(fault.get("for", 0.0))
        except (ValueError, KeyError, TypeError) as e:
            self.log.error("fault file %s unreadable (%s): %r", path, e, raw[:200])
            return None
        self.log.warning("fault injected: %s", raw)
        now = time.monotonic()
        if kind == "silent":
            self._silent_until, self._verdict = now + span, None
        elif kind == "garbage":
            self._garbage = GARBAGE.get(str(fault.get("kind", "text")), GARBAGE["text"])
        elif kind == "delay":
            self._delay = span
        elif kind in ("hangup", "power_cycle"):
            self._down_until = now + span
            if kind == "power_cycle":
                self.programs, self.part, self._verdict = {}, None, None
                shutil.rmtree(self.store, ignore_errors=True)
        else:
            self.log.error("unknown fault %r ignored", kind)
            return None
        return str(kind)

    # ----------------------------------------------------------------- Listing 9

    def _answer_due(self, line: RecordStream) -> None:
        if self._verdict is not None and time.monotonic() >= self._verdict_at:
            verdict, self._verdict = self._verdict, None
            self.log.info("part %s measured: %s", self.part, verdict)
            if self._garbage is not None:
                junk, self._garbage = self._garbage, None
                self.log.warning("sending garbage instead of %s: %s", verdict, escaped(junk))
                line.write_bytes(junk)
                return
            for rec in self._measures:  # each feature's value, then the verdict (docs/quality.md)
                line.write_record(rec)
            line.write_bytes(verdict.encode("ascii") if self.bang else verdict[:-1].encode("ascii"))

    def _measure(self, program: bytes) -> tuple[list[str], bool] | None:
        """The features of the part program measured on the part its run sheet names (the simulated mill
        left it in var/sim/parts), or on a nominal part: `MEAS <feature> <value>!` records and the verdict."""
        text = program.decode("utf-8", "replace")
        feats = features_of(text)
        if not feats:
            return None
        sheet = read_sheet(text)
        part = read_part(self.cfg.var, sheet.workpiece) if sheet is not None and sheet.workpiece else None
        values = measure(feats, part, f"{self.seed}:{self.measured}", self.gauge_sigma)
        records = [f"MEAS {name} {value:.6f}!" for name, value in values.items()]
        return records, all(f.passes(values[f.name]) for f in feats)

    def handle(self, rec: str, line: RecordStream) -> None:
        """One command from the ME (the branches of Listing 9's listen())."""
        self.log.info("read: %r", rec)
        if rec == " DOWNLD !":
            self._receive_program(line)
        elif rec == " UPLD !":
            self._send_program(line)
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
            self._measures = []
            measured = self._measure(self.programs.get(self.part, b""))
            if measured is not None:  # a part program with FEATUREs: measured, the verdict from the tolerances
                self._measures, passed = measured
                self._verdict = "PASS!" if passed else "FAIL!"
            wait, self._delay = (self.measure_time if self._delay is None else self._delay), None
            self._verdict_at = time.monotonic() + wait
            self.log.info("measuring part %s (%d): %.1fs", self.part, self.measured, wait)
        elif rec.startswith("STATUS ") and not self.kermit:
            line.write_record(f"READY {rec[len('STATUS ') : -1].strip()}".rstrip() + "!")
        else:
            self.log.info("passed to SUP: %r", rec)

    def _receive_program(self, line: RecordStream) -> None:
        if self.kermit:  # Listing 9: system("kermit ilbr /dev/tty2a 9600")
            self.store.mkdir(parents=True, exist_ok=True)
            before = {p.name for p in self.store.iterdir()}
            kermit(line, ["-r"], self.store, KERMIT_TIMEOUT)
            got = [p for p in self.store.iterdir() if p.name not in before] or sorted(
                self.store.iterdir(), key=lambda p: p.stat().st_mtime
            )[-1:]
            for path in got:
                # Listing 9 untars the part directory; a plain file (an older ME's) is the program itself.
                data, name = path.read_bytes(), path.name
                if name.endswith(".tar") and is_tar(data):
                    name = name[: -len(".tar")]
                    try:
                        data = program_from(name, data)
                    except PartError as e:
                        self.log.error("part directory %s refused: %s", path.name, e)
                        continue
                self.programs[name] = data
                self.log.info("part program %s received by Kermit (%d bytes, as %s)", name, len(data), path.name)
            return
        name = line.read_record(ANSWER_TIMEOUT)[:-1]
        content = line.read_bytes(line.read_length(ANSWER_TIMEOUT), ANSWER_TIMEOUT)
        self.programs[name] = content
        self.log.info("part program %s received (%d bytes)", name, len(content))
        line.write_record("OK!")

    def _send_program(self, line: RecordStream) -> None:
        name = line.read_record(ANSWER_TIMEOUT)[:-1]
        content = self.programs.get(name)
        if self.kermit:  # Listing 9: kermit ilbs /dev/tty2a 9600 <part>.tar; nothing to send: no transfer
            if content is None:
                self.log.warning("upload of unknown part program %s: nothing sent", name)
                return
            (self.store / f"{name}.tar").write_bytes(part_tar(name, content))
            kermit(line, ["-s", f"{name}.tar"], self.store, KERMIT_TIMEOUT)
            return
        if content is None:
            self.log.warning("upload of unknown part program %s", name)
            line.write_record("NONE!")
        else:
            line.write_record(f"{len(content)}!")
            line.write_bytes(content)


def simulated(spec: MachineSpec) -> bool:
    """Is this machine's CMM the simulator (started with the machine: on a pty, or as its TCP server)?"""
    sim = spec.options.get("sim", {})
    serial = spec.options.get("serial", {})
    return spec.kind == "cmm" and (
        (isinstance(serial, dict) and serial.get("port") == "sim")
        or (isinstance(sim, dict) and bool(sim.get("listen")))
    )


def main(cfg: Config, machine_id: str, log: logging.Logger, stop: threading.Event) -> int:
    """Run the CMM simulator of `machine_id` until `stop` is set."""
    return CmmSimulator(cfg, cfg.machine(machine_id), log).serve(stop)
