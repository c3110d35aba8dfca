"""The ME loop every machine side shares: Listing 7's read-act-answer, and what Listing 7 left out.

Listing 7 read a request from the queue, slept, and answered it, forking a child for the run. Here
one loop serves the WC's requests one at a time and, between them, watches the run in progress, so
the WC's pings (NO_MESSAGE) are answered while the machine works and a dead ME is told from a busy
one. What a machine actually does (home, load a recipe, run, report) is in the subclass: the dummy
machine (gwc.me.dummy) or the CMM over RS-232 (gwc.me.cmm).

The ME's own state (MeState) mirrors what the machine is doing, not MACHINE_STATUS: the WC keeps the
cell's view. A request that does not fit the ME's state is refused with Notnow; a refusal's reason
goes in alarm_text (cut to its 80-byte slot by `brief`, the whole of it in the log).

Answers the WC could not take (its queue full while it was down) wait in an outbox and are sent
again each turn of the loop, so a restarted WC still gets its RUN_COMPL.

A machine that can be lost while the ME runs (the CMM at the end of its serial line) reports it:
`device_lost(why)` sends ME_LOST (the WC raises an alarm and shuts the machine down), the ME
refuses work (Notnow) and looks for the machine in `watch()`, and `device_back()` sends ME_BACK
once it answers again (the WC clears the alarm and brings the machine back).

RUN_NO counts the runs of the machine, not of the ME process: it is kept in var/me/<id>/run_no.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

from gwc.agent.control import notify_ready
from gwc.config import Config, MachineSpec
from gwc.errors import ConfigError, GwcError, QueueError, QueueFull, QueueTimeout
from gwc.files import rewrite
from gwc.ipc.codes import AckCode
from gwc.ipc.mq import ALARM_TEXT_SIZE, Channel, MeMessage, MessageId
from gwc.me.results import write_results

RUN_NO_FILE = "run_no"  # in the machine's memory directory: the last run number given

IDLE_POLL = 0.25  # wait this long for a request when nothing runs
RUN_POLL = 0.02  # ... and this long while a run is in progress, to notice its end soon
OUTBOX_POLL = 1.0  # ... and at most this long while answers wait for the WC to read again (send())


class MeState(StrEnum):
    SHUTDOWN = "shutdown"
    HOMING = "homing"  # ME_START received, waiting for the operator to clear the homing alarm
    IDLE = "idle"
    SETUP = "setup"
    RUNNING = "running"


class Refusal(GwcError):
    """A request the machine cannot do now: answered with `ack_code`, not an error of the ME."""

    def __init__(self, ack_code: AckCode, reason: str) -> None:
        super().__init__(reason)
        self.ack_code = ack_code
        self.reason = reason


@dataclass
class RunOutcome:
    """How a run ended: ACK_OK (results valid) or Run_Fail, and the machine's own results."""

    ack_code: AckCode
    results: dict[str, str] = field(default_factory=dict)
    note: str = ""


def brief(text: str, size: int = ALARM_TEXT_SIZE) -> str:
    """Shorten an explanation to fit a queue slot on purpose (the channel itself never truncates)."""
    data = text.encode("utf-8")
    if len(data) <= size:
        return text
    return data[: size - 3].decode("utf-8", "ignore") + "..."


class Options:
    """Typed access to a machine's options in etc/cell.toml; a wrong type is a ConfigError naming it."""

    def __init__(self, spec: MachineSpec, where: str = "") -> None:
        self.spec = spec
        self.values = spec.options
        self.where = where or f"machine {spec.id}"

    def get(self, name: str, kind: type | tuple[type, ...], default: Any) -> Any:
        value = self.values.get(name, default)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if value is not None and not isinstance(value, kind):
            raise ConfigError(f"{self.where}: option {name} = {value!r} has the wrong type")
        if isinstance(value, float) and value < 0:
            raise ConfigError(f"{self.where}: option {name} must not be negative")
        return value


class MachineSide:
    """Base of every ME. Subclasses implement the machine: home, load, begin, progress, ..."""

    kind = "machine"
    default_homing_alarm: str | None = None
    # How long the loop waits for a request when nothing runs: what watch() needs (a real machine's line).
    idle_poll = IDLE_POLL

    def __init__(self, cfg: Config, spec: MachineSpec, log: logging.Logger) -> None:
        self.cfg = cfg
        self.spec = spec
        self.log = log
        self.options = Options(spec)
        alarm = self.options.get("homing_alarm", (bool, str), self.default_homing_alarm is not None)
        self.homing_alarm = (self.default_homing_alarm or "HOME_CMM") if alarm is True else (alarm or None)
        self.channel = Channel(cfg.ipc_prefix, spec.id, "me", log)
        self.state = MeState.SHUTDOWN
        self.recipe_id = ""
        self.results_path: Path | None = None
        self.memory = cfg.var / "me" / spec.id  # the machine's own recipe store (download/upload)
        self.run_no = self._last_run_no()  # runs of this machine, across ME restarts
        self.run_started = 0.0
        self.lost: str | None = None  # why the machine itself stopped answering, while it does not
        self._start_req: MeMessage | None = None
        self._outbox: deque[MeMessage] = deque()
        self._blocked = False  # the WC's queue was full at the last try
        self._handlers: dict[MessageId, Callable[[MeMessage], None]] = {
            MessageId.NO_MESSAGE: self._ping,
            MessageId.ME_START: self._me_start,
            MessageId.ME_START_WAIT: self._alarm_cleared,
            MessageId.ME_SHUT: self._me_shut,
            MessageId.SETUP_RUN: self._setup_run,
            MessageId.START_RUN: self._start_run,
            MessageId.DNLD_ME: self._download,
            MessageId.UPLD_ME: self._upload,
        }

    # ----------------------------------------------------------------- what a machine does

    def home(self) -> None:
        """Get the machine ready after ME_START (and its homing alarm, if any). Raise Refusal if it cannot."""

    def load(self, recipe_id: str, path: Path) -> None:
        """Set the machine up with this recipe (SETUP_RUN)."""

    def begin(self) -> None:
        """Start the run set up (START_RUN); its end is found by progress()."""

    def progress(self) -> RunOutcome | None:
        """Called often while running: the outcome once the run has ended, else None."""
        return RunOutcome(AckCode.ACK_OK)

    def abort(self, why: str) -> None:
        """Stop a run that will not be reported (ME_SHUT during a run, or the ME stopping)."""

    def download(self, recipe_id: str, path: Path) -> None:
        """DNLD_ME: keep this recipe on the machine."""
        self.memory.mkdir(parents=True, exist_ok=True)
        (self.memory / recipe_id).write_bytes(path.read_bytes())

    def upload(self, recipe_id: str) -> Path:
        """UPLD_ME: a file holding the machine's copy of this recipe."""
        path = self.memory / recipe_id
        if not path.is_file():
            raise Refusal(AckCode.REC_INVAL, f"the machine holds no recipe {recipe_id}")
        return path

    def close(self) -> None:
        """Release the machine (serial port, ...) when the ME stops."""

    def watch(self) -> None:
        """Called every turn of the loop while the machine is started and not running: look after it
        (a line that hung up, a lost machine that may answer again)."""

    # ----------------------------------------------------------------- a machine lost and found

    def device_lost(self, why: str) -> None:
        """The machine stopped answering: tell the WC (ME_LOST) once; work is refused until device_back."""
        if self.lost is not None:
            return
        self.lost = why
        self.log.error("the machine is lost: %s; the WC shuts it down, the ME looks for it", why)
        self.send(MeMessage(MessageId.ME_LOST, alarm_text=brief(why)))

    def device_back(self) -> None:
        """The lost machine answers again: tell the WC (ME_BACK), serve again."""
        if self.lost is None:
            return
        self.log.warning("the machine answers again (it was lost: %s)", self.lost)
        self.lost = None
        self.send(MeMessage(MessageId.ME_BACK))

    def _last_run_no(self) -> int:
        try:
            return int((self.memory / RUN_NO_FILE).read_text().strip() or 0)
        except FileNotFoundError:
            return 0
        except (OSError, ValueError) as e:
            raise ConfigError(f"machine {self.spec.id}: {self.memory / RUN_NO_FILE} unreadable: {e}") from e

    def _next_run_no(self) -> int:
        """The next run number, written before the run starts, so no two runs of a machine share one."""
        n = self.run_no + 1
        rewrite(self.memory / RUN_NO_FILE, f"{n}\n".encode())  # on a run's start: no file made or replaced
        return n

    # ----------------------------------------------------------------- the loop

    def serve(self, stop: threading.Event) -> int:
        """Serve the WC until `stop` is set; returns the process exit code."""
        # What the WC sent while no ME was running waits in the queue and is served now: the queues
        # outlive either half so that nothing is lost across a restart (a request this new ME cannot
        # serve yet is refused Notnow, and an answer the WC no longer waits for is dropped by its seq).
        self.channel.open()
        self.log.info(
            "%s ME of %s ready on %s (homing alarm: %s)",
            self.kind,
            self.spec.id,
            self.channel.in_name,
            self.homing_alarm or "none",
        )
        notify_ready()
        try:
            while not stop.is_set():
                self._flush()
                try:
                    msg = self.channel.receive(self._poll())
                except QueueTimeout:
                    msg = None
                except QueueError as e:
                    self.log.warning("garbled record from the WC dropped: %s", e)
                    msg = None
                if msg is not None:
                    self.handle(msg)
                if self.state == MeState.RUNNING:
                    self._watch_run()
                elif self.state in (MeState.IDLE, MeState.SETUP):
                    self.watch()
        finally:
            if self.state == MeState.RUNNING:
                self.abort("the ME is stopping")
            self.close()
            self.channel.close()
        return 0

    def _poll(self) -> float:
        """How long this turn of the loop waits for a request."""
        if self.state == MeState.RUNNING:
            return RUN_POLL
        return min(self.idle_poll, OUTBOX_POLL) if self._outbox else self.idle_poll

    def handle(self, msg: MeMessage) -> None:
        """One request from the WC: act and answer. Nothing the WC sends can stop the loop."""
        if msg.message_id != MessageId.NO_MESSAGE:
            self.log.info("WC asks %s (state %s)", msg.describe(), self.state)
        handler = self._handlers.get(msg.message_id)
        try:
            if handler is None:
                raise Refusal(AckCode.BAD_MESSAGE, f"{msg.message_id.name} is not a request an ME serves")
            handler(msg)
        except Refusal as r:
            self.log.warning("refused %s: %s (%s)", msg.message_id.name, r.ack_code, r.reason)
            self.answer(msg, r.ack_code, alarm_text=brief(r.reason))
        except Exception as e:  # a bug or a machine fault must not kill the ME: the WC gets an answer
            self.log.exception("%s failed", msg.message_id.name)
            self.answer(msg, AckCode.BAD_MESSAGE, alarm_text=brief(f"ME error: {e}"))

    def answer(self, req: MeMessage, ack_code: AckCode, message_id: MessageId | None = None, **fields: str) -> None:
        self.send(req.reply(ack_code, message_id=message_id, **fields))

    def send(self, msg: MeMessage) -> None:
        """Send to the WC, or keep it for later if its queue is full (the WC is down)."""
        self._outbox.append(msg)
        self._flush()

    def _flush(self) -> None:
        while self._outbox:
            try:
                self.channel.send(self._outbox[0])
            except QueueFull as e:
                if not self._blocked:
                    self.log.error("%s: keeping %d answer(s) until the WC reads again", e, len(self._outbox))
                    self._blocked = True
                return
            except QueueError as e:
                self.log.error("answer dropped, it can never be sent: %s", e)
            else:
                if self._blocked:
                    self.log.info("the WC reads again: answers delivered")
                    self._blocked = False
            self._outbox.popleft()

    @property
    def waiting(self) -> int:
        """Answers kept for the WC because its queue was full."""
        return len(self._outbox)

    def _need(self, *states: MeState, what: str) -> None:
        if self.state not in states:
            raise Refusal(AckCode.NOTNOW, f"cannot {what}: the machine is {self.state}")
        if self.lost is not None and self.state != MeState.SHUTDOWN:
            raise Refusal(AckCode.NOTNOW, f"cannot {what}: the machine does not answer ({self.lost})")

    # ----------------------------------------------------------------- the requests

    def _ping(self, msg: MeMessage) -> None:
        # A shut-down ME says so: a WC that believes its machine is up learns the ME was restarted.
        if self.state == MeState.SHUTDOWN:
            self.answer(msg, AckCode.NOTNOW, alarm_text="the machine is shut down")
            return
        # A started ME tells its state, and while running the results file of its run: a restarted
        # WC learns whether the run it resumes is still going (gwc.wc.me_side.MeSide._resume).
        running = self.state == MeState.RUNNING and self.results_path is not None
        self.answer(
            msg,
            AckCode.ACK_OK,
            alarm_text=self.state.value,
            recipe_id=self.recipe_id,
            file_name=str(self.results_path) if running else "",
        )

    def _me_start(self, msg: MeMessage) -> None:
        if self.state == MeState.RUNNING:
            raise Refusal(AckCode.NOTNOW, f"run {self.run_no} is in progress: start again when it is over")
        self.recipe_id, self.lost = "", None
        if self.homing_alarm:
            # Listing 3: the first answer to ME_START is the alarm asking the operator to home the machine.
            self.state = MeState.HOMING
            self._start_req = msg
            self.log.info("homing: alarm %s to the WC, waiting for the operator", self.homing_alarm)
            self.send(MeMessage(MessageId.CELL_ALAR, alarm_text=self.homing_alarm, seq=msg.seq))
            return
        self._homed(msg)

    def _homed(self, req: MeMessage) -> None:
        self._start_req = None
        try:
            self.home()
        except Refusal:
            self.state = MeState.SHUTDOWN
            raise
        self.state = MeState.IDLE
        self.log.info("machine ready (Idle)")
        self.answer(req, AckCode.ACK_OK)

    def _alarm_cleared(self, msg: MeMessage) -> None:
        req = self._start_req
        if self.state != MeState.HOMING or req is None:
            self.log.info("alarm %s cleared: nothing was waiting for it", msg.alarm_text or "?")
            return
        if msg.ack_code == AckCode.REQ_CANCEL:  # a stop came while the operator had not homed the machine
            self.state, self._start_req = MeState.SHUTDOWN, None
            self.log.info("start cancelled by the cell while waiting for homing: the machine stays shut down")
            self.answer(req, AckCode.REQ_CANCEL, alarm_text="start cancelled before the machine was homed")
            return
        if msg.ack_code != AckCode.ACK_OK:
            self.state, self._start_req = MeState.SHUTDOWN, None
            self.answer(req, AckCode.START_FAIL, alarm_text="the homing alarm could not be raised")
            return
        self.log.info("homing alarm cleared by the operator")
        try:
            self._homed(req)
        except Refusal as r:
            self.log.warning("refused ME_START: %s (%s)", r.ack_code, r.reason)
            self.answer(req, r.ack_code, alarm_text=brief(r.reason))

    def _me_shut(self, msg: MeMessage) -> None:
        if self.state == MeState.RUNNING:
            self.log.warning("ME_SHUT during run %d: the run is abandoned", self.run_no)
            self.abort("ME_SHUT received")
        self.state, self._start_req, self.lost = MeState.SHUTDOWN, None, None
        self.recipe_id = ""
        self.log.info("machine shut down")
        self.answer(msg, AckCode.ACK_OK, message_id=MessageId.ME_SHUT_C)

    def _recipe_path(self, msg: MeMessage) -> Path:
        if not msg.recipe_id:
            raise Refusal(AckCode.REC_INVAL, "no recipe id")
        path = Path(msg.file_name)
        if not msg.file_name or not path.is_file():
            raise Refusal(AckCode.REC_INVAL, f"recipe file {msg.file_name or '(none)'} not found")
        return path

    def _setup_run(self, msg: MeMessage) -> None:
        self._need(MeState.IDLE, MeState.SETUP, what="set up a run")
        path = self._recipe_path(msg)
        self.load(msg.recipe_id, path)
        self.recipe_id = msg.recipe_id
        self.state = MeState.SETUP
        self.log.info("set up with recipe %s (%s)", msg.recipe_id, path)
        self.answer(msg, AckCode.ACK_OK)

    def _start_run(self, msg: MeMessage) -> None:
        self._need(MeState.SETUP, what="start a run")
        if not msg.file_name:
            raise Refusal(AckCode.BAD_MESSAGE, "START_RUN names no results file")
        self.results_path = Path(msg.file_name)
        self.run_no = self._next_run_no()
        self.begin()
        self.run_started = time.monotonic()
        self.state = MeState.RUNNING
        self.log.info("run %d started with recipe %s", self.run_no, self.recipe_id)
        self.answer(msg, AckCode.ACK_OK)

    def _watch_run(self) -> None:
        try:
            outcome = self.progress()
        except Exception as e:
            self.log.exception("run %d: the machine failed", self.run_no)
            outcome = RunOutcome(AckCode.RUN_FAIL, note=f"machine error: {e}")
        if outcome is not None:
            self.end_run(outcome)

    def end_run(self, outcome: RunOutcome) -> None:
        """The run in progress is over: results file, RUN_COMPL, Idle."""
        self.state = MeState.IDLE
        assert self.results_path is not None
        results = {
            "RECIPE": self.recipe_id,
            "RUN_NO": str(self.run_no),
            "RUN_TIME": f"{time.monotonic() - self.run_started:.3f}",
            **outcome.results,
        }
        if outcome.note:
            results.setdefault("NOTE", outcome.note)
        file_name = str(self.results_path)
        try:
            write_results(self.results_path, results, outcome=(outcome.ack_code, outcome.note))
        except (OSError, ValueError) as e:
            self.log.error("run %d: cannot write results file %s: %s", self.run_no, self.results_path, e)
            outcome, file_name = RunOutcome(AckCode.RUN_FAIL), ""
        level = logging.INFO if outcome.ack_code == AckCode.ACK_OK else logging.WARNING
        self.log.log(
            level,
            "run %d complete: %s, %d results in %s%s",
            self.run_no,
            outcome.ack_code,
            len(results),
            file_name or "(none)",
            f" ({outcome.note})" if outcome.note else "",
        )
        self.send(
            MeMessage(
                MessageId.RUN_COMPL,
                file_name=file_name,
                recipe_id=self.recipe_id,
                ack_code=outcome.ack_code,
                alarm_text=brief(outcome.note),
            )
        )

    def _download(self, msg: MeMessage) -> None:
        self._need(MeState.IDLE, MeState.SETUP, MeState.SHUTDOWN, what="download a recipe")
        self.download(msg.recipe_id, self._recipe_path(msg))
        self.log.info("recipe %s downloaded to the machine", msg.recipe_id)
        self.answer(msg, AckCode.ACK_OK)

    def _upload(self, msg: MeMessage) -> None:
        self._need(MeState.IDLE, MeState.SETUP, MeState.SHUTDOWN, what="upload a recipe")
        if not msg.recipe_id:
            raise Refusal(AckCode.REC_INVAL, "no recipe id")
        path = self.upload(msg.recipe_id)
        self.log.info("recipe %s uploaded from the machine to %s", msg.recipe_id, path)
        self.answer(msg, AckCode.ACK_OK, file_name=str(path))
