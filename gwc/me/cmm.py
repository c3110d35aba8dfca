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
import re
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from gwc.config import Config, MachineSpec
from gwc.errors import ConfigError, LineError
from gwc.ipc.codes import AckCode
from gwc.me.cmm_line import QUIET, CmmLine
from gwc.me.line import (
    Garbage,
    LineLost,
    LineTimeout,
    RecordStream,
    escaped,
    kermit,
    serial_settings,
)
from gwc.me.machine import MachineSide, Refusal, RunOutcome
from gwc.me.parts import PartError, part_tar, program_from
from gwc.retry import Deadline

T = TypeVar("T")
VERDICTS = ("PASS!", "FAIL!")
TRANSFERS = ("line", "kermit")
KERMIT_TIMEOUT = 60.0  # longest one Kermit transfer may take
MEAS_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]{0,31}$")  # a measured feature's name (MEAS records)
MEAS_VALUE = re.compile(r"^[-+]?[0-9]+(\.[0-9]*)?$")


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
        self.run_timeout = self.options.get("run_timeout", float, 120.0)
        self.transfer = self.options.get("transfer", str, "line")
        if self.transfer not in TRANSFERS:
            raise ConfigError(f"machine {spec.id}: transfer must be one of {', '.join(TRANSFERS)}")
        self.probe = self.options.get("probe", bool, self.transfer == "line")
        self.kermit_timeout = self.options.get("kermit_timeout", float, KERMIT_TIMEOUT)
        self.reprobe_min = self.options.get("reprobe_min", float, 0.5)
        self.reprobe_max = self.options.get("reprobe_max", float, 2.0)
        self.link = CmmLine(cfg, spec.id, self.settings, log, self.probe)
        self._run_deadline = Deadline(0.0)
        self._suspect: str | None = None  # an exchange failed: probe the CMM next
        self._probe_deadline: float | None = None  # a STATUS is out: its READY is due by then
        self._ready = ""  # the answer due to the STATUS out
        self._next_probe = 0.0
        self._backoff = self.reprobe_min
        self._measured: dict[str, str] = {}  # MEAS records of the run in progress: feature -> value

    # ----------------------------------------------------------------- the line

    def _exchange(self, what: str, fn: Callable[[RecordStream], T]) -> T:
        """One exchange on a resynchronised line. Its failure is refused Notnow (the CMM cannot serve
        now: the lot asks again): a CMM that did not answer the resync, or whose line is gone, is lost
        at once; after any other failure it is probed next (watch)."""
        self._suspect, self._probe_deadline = None, None  # the resync probes as well
        try:
            line = self.link.open()
            try:
                self.link.resync(line)
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
            self.link.resync(self.link.open())
        except LineError as e:
            self.link.drop(str(e))
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
        self._measured = {}
        self._exchange("start of the run", lambda line: line.write_record("START RUN !"))
        self._run_deadline = Deadline(self.run_timeout)

    def progress(self) -> RunOutcome | None:
        """The verdict, or why the run failed (the CMM is then probed by watch(), after RUN_COMPL)."""
        line = self.link.open()
        try:
            rec = line.poll_record(bare_verdict=True)
        except LineError as e:
            # The note leads with what came (RUN_COMPL carries 80 bytes of it; the port is in the ME's log).
            what = str(e).removeprefix(f"{line.name}: ")
            kind = "line lost" if isinstance(e, LineLost) else "garbage"
            return self._run_failed(e, f"{kind} during the run: {what}")
        if rec is None:
            if self._run_deadline.expired:
                return self._run_failed(
                    LineTimeout("no verdict"), f"no verdict from the CMM within {self.run_timeout:g}s: run given up"
                )
            return None
        if rec.startswith("MEAS "):  # a feature's measured value, before the verdict (docs/quality.md)
            words = rec[:-1].split()
            if (
                len(words) == 3
                and MEAS_NAME.match(words[1])
                and MEAS_VALUE.match(words[2])
                and words[1] not in self._measured
            ):
                self._measured[words[1]] = words[2]
                return None
            return self._run_failed(Garbage(rec), f"the CMM sent a bad measurement {escaped(rec.encode())}")
        if rec in VERDICTS:
            self.log.info(
                "the CMM answered %s%s", rec, f" ({len(self._measured)} features measured)" if self._measured else ""
            )
            return RunOutcome(AckCode.ACK_OK, {**self._measured, "PART": self.recipe_id, "RESULT": rec[:-1]})
        return self._run_failed(Garbage(rec), f"the CMM answered {escaped(rec.encode())} instead of a verdict")

    def _run_failed(self, error: LineError, note: str) -> RunOutcome:
        self.link.given_up = self.run_no
        self._suspect = note  # probed by watch() once RUN_COMPL is out (so ME_LOST follows it)
        if isinstance(error, LineLost):
            self.link.drop(note)
        self.log.warning("run %d failed, the part was not measured: %s", self.run_no, note)
        return RunOutcome(AckCode.RUN_FAIL, {"RESULT": "NONE"}, note=note)

    def abort(self, why: str) -> None:
        # Listing 9 has no way to stop a measurement: its late verdict is dropped at the next resync.
        self.link.given_up = self.run_no
        self.log.warning("run %d abandoned (%s): the CMM's verdict will be dropped", self.run_no, why)

    def watch(self) -> None:
        """Between runs, never blocking the loop (the WC's pings must be answered): a CMM whose last
        exchange failed, or which is lost, is probed (STATUS sent, READY! looked for on later turns);
        an open line is read for a hang-up (a power cycle while Idle) and for what nobody asked for."""
        if self._suspect is not None or self.lost is not None:
            self._probe_step()
            return
        if self.link.stream is None:
            return
        try:
            rec = self.link.stream.poll_record(bare_verdict=True)
        except Garbage as e:
            self.log.warning("garbage from the CMM between exchanges dropped: %s", e)
            return
        except LineError as e:
            self._lose(str(e))
            return
        if rec is not None:
            self.link.stale(rec, "between exchanges")

    def _probe_step(self) -> None:
        now = time.monotonic()
        if self._probe_deadline is None:
            if now < self._next_probe:
                return
            try:
                line = self.link.open_for_probe()
                if line is None:
                    return  # still opening: looked at again next turn
                if self.probe:
                    self._ready = self.link.ask_status(line)
                    self._probe_deadline = now + self.answer_timeout
                    return
                line.drain(QUIET, QUIET)  # a Kermit device: an open line that does not hang up is there
            except LineError as e:
                self._probe_failed(str(e), gone=True)
                return
            self._found()
            return
        try:
            rec = self.link.open().poll_record(bare_verdict=True)
        except Garbage as e:
            self.log.warning("garbage from the CMM while probing dropped: %s", e)
            return
        except LineError as e:
            self._probe_failed(str(e), gone=True)
            return
        if rec == self._ready:
            self._found()
        elif rec is not None:
            self.link.stale(rec, "while probing")
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
            self.link.drop(why)
        self._backoff = min(self._backoff * 2, self.reprobe_max)
        self._next_probe = time.monotonic() + self._backoff
        self.log.info("the CMM still does not answer (%s): next try in %.1fs", why, self._backoff)

    def _lose(self, why: str, gone: bool = True) -> None:
        """The CMM is lost: the WC told, probes from now on with backoff (the line closed if `gone`)."""
        self._suspect, self._probe_deadline = None, None
        if gone:
            self.link.drop(why)
        self._backoff = self.reprobe_min
        self._next_probe = time.monotonic() + self._backoff
        self.device_lost(why)

    def close(self) -> None:
        if self.link.is_open:
            self.link.drop("the ME is stopping")
