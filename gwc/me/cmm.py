"""The CMM's machine side: Listing 9's line protocol over RS-232 (or any pyserial URL), owned for the
CMM's whole life.

Listing 9 ran on the CMM's own computer and read records from the serial line, each ending in `!`.
The ME is the other end of that line. What it sends, and what the CMM answers (docs/machine-interface.md
section 6 has the grammar, both transfers and every timeout):

    ` DOWNLD !`  then the part program                         a recipe to the CMM
    ` UPLD !`  `<part>!`  then the part program back           a recipe back from the CMM
    `SETUP RUN !`  `1!`  `<part>!`                             set up the part program (no answer)
    `START RUN !`                                              measure -> `PASS!` / `FAIL!` (or without `!`)
    `STATUS <n>!`                                              are you there? -> `READY <n>!` (transfer "line")

The program moves as the machine's `transfer` says: "line" (ours: `<part>!` `<n>!` + n bytes,
answered `OK!`) or "kermit" (Listing 9's own: G-Kermit on both ends, the part directory as
`<part>.tar` both ways, a plain file still taken back: gwc/me/parts.py).

The line is the ME's from ME_START to ME_SHUT. Before each exchange it is resynchronised (STATUS <n>
answered READY <n>, everything before it logged and dropped; with Kermit, drained until quiet), so
nothing an earlier exchange left behind, a late verdict above all, is read as the answer to a later
one. An exchange that fails costs that exchange (Notnow for a request, Run_Fail for a run), then
the CMM is probed at once: if it does not answer, or the port is gone (EIO, hang-up, closed
socket), the machine is lost (ME_LOST: the WC raises CMM_LOST and shuts the machine down) and the
ME reopens and probes it with backoff (reprobe_min doubling to reprobe_max) until it answers (ME_BACK:
alarm cleared, the machine back in service).

A FAIL part is a run that worked and found the part out of tolerance: RUN_COMPL carries ACK_OK and
RESULT FAIL. Run_Fail is a run the CMM never measured (no verdict in time, garbage instead of one,
the line lost), and says which in its note.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import TypeVar

import serial

from gwc.config import Config, MachineSpec
from gwc.errors import ConfigError, LineError
from gwc.ipc.codes import AckCode
from gwc.me.cmm_sim import sim_link
from gwc.me.line import (
    Garbage,
    LineLost,
    LineTimeout,
    RecordStream,
    escaped,
    kermit,
    open_serial,
    serial_settings,
    serial_stream,
)
from gwc.me.machine import MachineSide, Refusal, RunOutcome
from gwc.me.parts import PartError, part_tar, program_from
from gwc.retry import Deadline

T = TypeVar("T")
VERDICTS = ("PASS!", "FAIL!")
TRANSFERS = ("line", "kermit")
KERMIT_TIMEOUT = 60.0  # longest one Kermit transfer may take
QUIET = 0.1  # resynchronising without STATUS (Kermit devices): the line must be quiet this long


def exchange_deadline(spec: MachineSpec) -> float:
    """The longest one exchange can take before the ME answers its request: the resync and the answer
    (the serial timeout each), the Kermit transfer, and a margin for the ME's own loop."""
    serial = spec.options.get("serial", {})
    timeout = float(serial.get("timeout", 5.0)) if isinstance(serial, dict) else 5.0
    kermit_time = float(spec.options.get("kermit_timeout", KERMIT_TIMEOUT)) if _is_kermit(spec) else 0.0
    return 2 * timeout + kermit_time + 2.0


def _is_kermit(spec: MachineSpec) -> bool:
    return spec.options.get("transfer", "line") == "kermit"


def check_name(name: str) -> str:
    """A part name as a record: ASCII, no `!`, no line ends, no path, short enough for one record."""
    if not name or "!" in name or "/" in name or not name.isascii() or not name.isprintable() or len(name) >= 100:
        raise Refusal(AckCode.REC_INVAL, f"part name {name!r} cannot be sent as a record")
    return name


class CmmMachine(MachineSide):
    kind = "cmm"
    default_homing_alarm = "HOME_CMM"  # Listing 3: the operator pushes the CMM's start button

    def __init__(self, cfg: Config, spec: MachineSpec, log: logging.Logger) -> None:
        super().__init__(cfg, spec, log)
        self.settings = serial_settings(self.options.get("serial", dict, {}), f"machine {spec.id}")
        self.answer_timeout = float(self.settings.get("timeout", 5.0))
        self.open_timeout = float(self.settings.get("open_timeout", self.answer_timeout))
        self.run_timeout = self.options.get("run_timeout", float, 120.0)
        self.transfer = self.options.get("transfer", str, "line")
        if self.transfer not in TRANSFERS:
            raise ConfigError(f"machine {spec.id}: transfer must be one of {', '.join(TRANSFERS)}")
        self.probe = self.options.get("probe", bool, self.transfer == "line")
        self.kermit_timeout = self.options.get("kermit_timeout", float, KERMIT_TIMEOUT)
        self.reprobe_min = self.options.get("reprobe_min", float, 0.5)
        self.reprobe_max = self.options.get("reprobe_max", float, 2.0)
        self._ser: serial.SerialBase | None = None
        self._line: RecordStream | None = None
        self._opening: tuple[str, Future[serial.SerialBase]] | None = None  # a probe's open (_probe_line)
        self._run_deadline = 0.0
        self._given_up = 0  # the last run given up without a verdict: its verdict may still come
        self._suspect: str | None = None  # an exchange failed: probe the CMM next
        self._probe_deadline: float | None = None  # a STATUS is out: its READY is due by then
        self._status_no = 0
        self._ready = ""  # the answer due to the STATUS out
        self._next_probe = 0.0
        self._backoff = self.reprobe_min

    # ----------------------------------------------------------------- the line

    def _port(self, wait: bool) -> str:
        port = str(self.settings["port"])
        if port != "sim":
            return port
        link = sim_link(self.cfg, self.spec.id)
        deadline = Deadline(self.open_timeout if wait else 0.0)
        while not link.exists():  # the simulator may still be starting, or its line is down
            if deadline.expired:
                raise LineLost(f"no CMM simulator: {link} does not exist (is `gwc run cmmsim` running?)")
            time.sleep(0.05)
        return os.path.realpath(link)

    def line(self) -> RecordStream:
        """The open line to the CMM, opened now if it is not (waiting for the simulator's pty to appear)."""
        if self._line is None:
            if self._opening is not None:  # a probe's open under way: its outcome first
                port, opening = self._opening
                self._opening = None
                self._adopt(port, opening.result())
            else:
                port = self._port(wait=True)
                self._adopt(port, open_serial(self.settings, port))
        assert self._line is not None
        return self._line

    def _probe_line(self) -> RecordStream | None:
        """The line for a probe, opened without holding the ME's loop: None while the open is under way.

        Opening a device server's port can take seconds: pyserial's TCP connect waits up to 5 s for a
        host that is off (its SYN unanswered), and rfc2217:// negotiates Telnet options for up to 3 s
        with a server that accepted but does not speak. The WC's pings (1.5 s) must be answered
        meanwhile, or the ME is taken for dead. LineLost if the open failed."""
        if self._line is not None:
            return self._line
        if self._opening is None:
            port = self._port(wait=False)
            self._opening = (port, self._open_in_background(port))
        port, opening = self._opening
        if not opening.done():
            return None
        self._opening = None
        self._adopt(port, opening.result())
        return self._line

    def _open_in_background(self, port: str) -> Future[serial.SerialBase]:
        """open_serial in a daemon thread (one at a time: _opening), so a stopping ME never waits for it."""
        opening: Future[serial.SerialBase] = Future()

        def run() -> None:
            try:
                opening.set_result(open_serial(self.settings, port))
            except Exception as e:  # handed to the ME's loop, which takes the outcome
                opening.set_exception(e)

        threading.Thread(target=run, name=f"open-{self.spec.id}", daemon=True).start()
        return opening

    def _adopt(self, port: str, ser: serial.SerialBase) -> None:
        self._ser = ser
        self._line = serial_stream(ser, f"CMM line {port}")
        self.log.info(
            "serial line to the CMM open: %s at %s %s%s%s (%s)",
            port,
            ser.baudrate,
            ser.bytesize,
            ser.parity,
            ser.stopbits,
            ", ".join(f"{k}={v}" for k, v in self.settings.items() if k != "port"),
        )

    def drop_line(self, why: str) -> None:
        if self._ser is not None:
            self.log.warning("closing the serial line to the CMM: %s", why)
            try:
                self._ser.close()
            except (OSError, serial.SerialException):
                pass
        self._ser, self._line = None, None

    def _stale(self, rec: str, when: str) -> None:
        """A record nobody asked for: a late verdict of a run given up, or garbage. Logged, dropped."""
        if rec.rstrip("!") in ("PASS", "FAIL") and self._given_up:
            self.log.warning("late verdict %s for run %d (given up) %s: dropped", rec, self._given_up, when)
        elif rec.startswith("READY "):
            self.log.info("answer %s to an earlier STATUS %s: dropped", rec, when)
        else:
            self.log.warning("unexpected record from the CMM %s: %r dropped", when, rec)

    def _resync(self, line: RecordStream) -> None:
        """Nothing from an earlier exchange may answer the next one: STATUS until READY!, or drain."""
        if not self.probe:
            junk = line.drain(QUIET, self.answer_timeout)
            if junk:
                self._stale(junk.decode("ascii", "backslashreplace"), "before the exchange")
            return
        ready = self._ask_status(line)
        deadline = Deadline(self.answer_timeout)
        while True:
            rec = line.next_record(deadline.left(), bare_verdict=True)
            if rec is None:
                raise LineTimeout(f"the CMM did not answer STATUS within {self.answer_timeout:.1f}s")
            if rec == ready:
                return
            self._stale(rec, f"before {ready}")

    def _ask_status(self, line: RecordStream) -> str:
        """`STATUS <n>!`, numbered so that an answer to an earlier one (a CMM that read several at once
        after a measurement) is not taken for this one's; returns the answer due, `READY <n>!`."""
        self._status_no = self._status_no % 99999 + 1
        line.write_record(f"STATUS {self._status_no}!")
        return f"READY {self._status_no}!"

    def _exchange(self, what: str, fn: Callable[[RecordStream], T]) -> T:
        """One exchange on a resynchronised line. Its failure is refused Notnow (the CMM cannot serve
        now: the lot asks again): a CMM that did not answer the resync, or whose line is gone, is lost
        at once; after any other failure it is probed next (watch)."""
        self._suspect, self._probe_deadline = None, None  # the resync probes as well
        try:
            line = self.line()
            try:
                self._resync(line)
            except LineTimeout as e:
                raise LineLost(str(e)) from e
            return fn(line)
        except LineError as e:
            self.log.warning("CMM exchange failed (%s): %s", what, e)
            if isinstance(e, LineLost):
                self._lose(str(e))
            else:
                self._suspect = str(e)
            state = f"lost: {self.lost}" if self.lost else "probed next"
            raise Refusal(AckCode.NOTNOW, f"{what} failed: {e} (the CMM is {state})") from e

    def _send_recipe(self, line: RecordStream, part: str, path: Path) -> None:
        line.write_record(" DOWNLD !")
        if self.transfer == "kermit":
            # The part directory as a tar, as Listing 9 extracts it into /usr/avail/part (gwc/me/parts.py).
            spool = self.memory / "kermit"
            shutil.rmtree(spool, ignore_errors=True)
            spool.mkdir(parents=True)
            (spool / f"{part}.tar").write_bytes(part_tar(part, path.read_bytes()))
            kermit(line, ["-s", f"{part}.tar"], spool, self.kermit_timeout)
            return
        content = path.read_bytes()
        line.write_record(f"{part}!")
        line.write_record(f"{len(content)}!")
        line.write_bytes(content)
        answer = line.read_record(self.answer_timeout)
        if answer != "OK!":
            raise Garbage(f"the CMM answered {answer!r} to the download of {part}, not OK!")

    # ----------------------------------------------------------------- the machine

    def home(self) -> None:
        self._suspect, self._probe_deadline = None, None
        try:
            self._resync(self.line())
        except LineError as e:
            self.drop_line(str(e))
            raise Refusal(AckCode.START_FAIL, f"the CMM does not answer: {e}") from e

    def load(self, recipe_id: str, path: Path) -> None:
        part = check_name(recipe_id)

        def setup(line: RecordStream) -> None:
            self._send_recipe(line, part, path)
            line.write_record("SETUP RUN !")
            line.write_record("1!")
            line.write_record(f"{part}!")

        self._exchange(f"setup of {recipe_id}", setup)

    def download(self, recipe_id: str, path: Path) -> None:
        part = check_name(recipe_id)
        self._exchange(f"download of {recipe_id}", lambda line: self._send_recipe(line, part, path))

    def upload(self, recipe_id: str) -> Path:
        part = check_name(recipe_id)
        target = self.memory / "upload"
        target.mkdir(parents=True, exist_ok=True)

        def fetch(line: RecordStream) -> bytes | None:
            line.write_record(" UPLD !")
            line.write_record(f"{part}!")
            if self.transfer == "kermit":
                # Received under a name the ME chooses (-a), in a folder of its own, emptied first: the far
                # end never chooses where a file lands (`../../x`, `/etc/x`: docs/security.md).
                inbox = self.memory / "kermit-in"
                shutil.rmtree(inbox, ignore_errors=True)
                inbox.mkdir(parents=True)
                kermit(line, ["-r", "-a", "upload"], inbox, self.kermit_timeout)
                landed = sorted(p.name for p in inbox.iterdir())
                if landed not in ([], ["upload"]):  # -a holds for every file gkermit writes: never seen
                    raise Garbage(f"the Kermit transfer left {landed} in {inbox}, not one file 'upload'")
                return (inbox / "upload").read_bytes() if landed else None
            first = line.read_record(self.answer_timeout)
            if first == "NONE!":
                return None
            return line.read_bytes(line.length_of(first), self.answer_timeout)

        content = self._exchange(f"upload of {recipe_id}", fetch)
        if content is None:
            raise Refusal(AckCode.REC_INVAL, f"the CMM holds no part program {recipe_id}")
        try:
            content = program_from(part, content)  # <part>.tar of the part directory, or the program alone
        except PartError as e:
            self.log.error("upload of %s refused: %s", recipe_id, e)
            raise Refusal(AckCode.REC_INVAL, str(e)) from e
        path = target / part
        path.write_bytes(content)
        return path

    def begin(self) -> None:
        self._exchange("start of the run", lambda line: line.write_record("START RUN !"))
        self._run_deadline = time.monotonic() + self.run_timeout

    def progress(self) -> RunOutcome | None:
        """The verdict, or why the run failed (the CMM is then probed by watch(), after RUN_COMPL)."""
        line = self.line()
        try:
            rec = line.poll_record(bare_verdict=True)
        except LineError as e:
            # The note leads with what came (RUN_COMPL carries 80 bytes of it; the port is in the ME's log).
            what = str(e).removeprefix(f"{line.name}: ")
            kind = "line lost" if isinstance(e, LineLost) else "garbage"
            return self._run_failed(e, f"{kind} during the run: {what}")
        if rec is None:
            if time.monotonic() > self._run_deadline:
                return self._run_failed(
                    LineTimeout("no verdict"), f"no verdict from the CMM within {self.run_timeout:g}s: run given up"
                )
            return None
        if rec in VERDICTS:
            self.log.info("the CMM answered %s", rec)
            return RunOutcome(AckCode.ACK_OK, {"PART": self.recipe_id, "RESULT": rec[:-1]})
        return self._run_failed(Garbage(rec), f"the CMM answered {escaped(rec.encode())} instead of a verdict")

    def _run_failed(self, error: LineError, note: str) -> RunOutcome:
        self._given_up = self.run_no
        self._suspect = note  # probed by watch() once RUN_COMPL is out (so ME_LOST follows it)
        if isinstance(error, LineLost):
            self.drop_line(note)
        self.log.warning("run %d failed, the part was not measured: %s", self.run_no, note)
        return RunOutcome(AckCode.RUN_FAIL, {"RESULT": "NONE"}, note=note)

    def abort(self, why: str) -> None:
        # Listing 9 has no way to stop a measurement: its late verdict is dropped at the next resync.
        self._given_up = self.run_no
        self.log.warning("run %d abandoned (%s): the CMM's verdict will be dropped", self.run_no, why)

    def watch(self) -> None:
        """Between runs, never blocking the loop (the WC's pings must be answered): a CMM whose last
        exchange failed, or which is lost, is probed (STATUS sent, READY! looked for on later turns);
        an open line is read for a hang-up (a power cycle while Idle) and for what nobody asked for."""
        if self._suspect is not None or self.lost is not None:
            self._probe_step()
            return
        if self._line is None:
            return
        try:
            rec = self._line.poll_record(bare_verdict=True)
        except Garbage as e:
            self.log.warning("garbage from the CMM between exchanges dropped: %s", e)
            return
        except LineError as e:
            self._lose(str(e))
            return
        if rec is not None:
            self._stale(rec, "between exchanges")

    def _probe_step(self) -> None:
        now = time.monotonic()
        if self._probe_deadline is None:
            if now < self._next_probe:
                return
            try:
                line = self._probe_line()
                if line is None:
                    return  # still opening: looked at again next turn
                if self.probe:
                    self._ready = self._ask_status(line)
                    self._probe_deadline = now + self.answer_timeout
                    return
                line.drain(QUIET, QUIET)  # a Kermit device: an open line that does not hang up is there
            except LineError as e:
                self._probe_failed(str(e), gone=True)
                return
            self._found()
            return
        try:
            rec = self.line().poll_record(bare_verdict=True)
        except Garbage as e:
            self.log.warning("garbage from the CMM while probing dropped: %s", e)
            return
        except LineError as e:
            self._probe_failed(str(e), gone=True)
            return
        if rec == self._ready:
            self._found()
        elif rec is not None:
            self._stale(rec, "while probing")
        elif now > self._probe_deadline:
            self._probe_failed(f"the CMM did not answer STATUS within {self.answer_timeout:.1f}s", gone=False)

    def _found(self) -> None:
        self._probe_deadline = None
        if self._suspect is not None:
            self.log.info("the CMM answers after the failed exchange (%s)", self._suspect)
            self._suspect = None
        self._backoff = self.reprobe_min
        self.device_back()

    def _probe_failed(self, why: str, gone: bool) -> None:
        """A probe failed: the CMM is lost (if it was not), and probed again after the backoff. The line
        is closed (and opened again) only when the port is `gone`: a silent CMM's line stays open, so
        that what it says when it wakes up (a late verdict) is read, logged and dropped."""
        self._probe_deadline = None
        if self.lost is None:
            self._lose(f"{self._suspect}; then {why}" if self._suspect else why, gone)
            return
        if gone:
            self.drop_line(why)
        self._backoff = min(self._backoff * 2, self.reprobe_max)
        self._next_probe = time.monotonic() + self._backoff
        self.log.info("the CMM still does not answer (%s): next try in %.1fs", why, self._backoff)

    def _lose(self, why: str, gone: bool = True) -> None:
        """The CMM is lost: the WC told, probes from now on with backoff (the line closed if `gone`)."""
        self._suspect, self._probe_deadline = None, None
        if gone:
            self.drop_line(why)
        self._backoff = self.reprobe_min
        self._next_probe = time.monotonic() + self._backoff
        self.device_lost(why)

    def close(self) -> None:
        if self._ser is not None:
            self.drop_line("the ME is stopping")
