"""What the operation entity works with: its deadlines, the steps' outcomes, a machine request's
alternatives, the traveller's file, and the constants of its waits (see gwc/lot/entity.py)."""

from __future__ import annotations

import asyncio
import contextlib
import json
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any, TypeVar

from gwc.config import Config
from gwc.errors import BusError, GwcError
from gwc.files import forget_previous, rewrite
from gwc.ipc.catalogue import Message
from gwc.ipc.codes import AckCode, LotState, MachineStatus
from gwc.ipc.names import Conv
from gwc.retry import Backoff

T = TypeVar("T")
# In the cell an entity hears every module's death (MOD_DIED), and the machines' news (UPD_ME_ST, RUN_COMPL)
# about the machines it is bound to only (ABOUT_MACHINES, narrowed to them at each binding and unreserve:
# docs/protocol.md, "Subjects"): another machine's run is no business of this lot, and with 50 machines
# at work every lot woke, checked and acknowledged every one of them.
LISTENS = (Conv.MOD_DIED,)
ABOUT_MACHINES = (Conv.RUN_COMPL, Conv.UPD_ME_ST)
# Until its lot is imported an entity listens to no broadcast: the cell's machine traffic is no
# business of a lot waiting at the door, and in a busy cell many wait there. Its own moves
# (LOT_MOVED) come addressed to it, not broadcast to every lot (gwc/servers/lot.py).
WAITING_LISTENS: tuple[str, ...] = ()
UP = (MachineStatus.IDLE.value, MachineStatus.SETUP.value, MachineStatus.RUNNING.value)
FINISHED = (LotState.COMPLETED, LotState.WAITING_EXPORT, LotState.EXPORTED, LotState.FAILED)
IMPORTED = (LotState.IMPORTED, LotState.WAITING_MACHINE, LotState.RUNNING, *FINISHED)
FOREVER = 10.0**7  # a conversation MSCHED answers when it can: its own deadline is the caller's
BOUND_AT_ONCE = 0.01  # s: a request granted within this after its Machine_Req_Ack never waited
POLL = 1.0  # fallback asks (the Lot Server) and reads (MACHINE_STATUS) while waiting for a broadcast
HISTORY = 32  # status changes remembered per machine
SHUT = (MachineStatus.SHUTDOWN.value,)
ENDED = (MachineStatus.SHUTDOWN.value, MachineStatus.IDLE.value)  # a machine in these runs nothing
# ENTITY_REQ actions whose repeat (its first answer was lost) may find the operator already moved the
# entity on: the Lot Server then answers Notnow with the state the first request led to.
ALREADY = {"import": (LotState.IMPORTED,), "export": (LotState.EXPORTED,)}
# What the operator may do with a held entity (RELEASE_LOT, `gwc release`): ask for the operation again
# (retry and reroute alike: the script's alternatives, whichever machine is up), or fail it.
RELEASES = ("retry", "reroute", "fail")


@dataclass(frozen=True)
class Timeouts:
    """Deadlines of the entity's steps, in seconds. Operator decisions get long ones."""

    answer: float = 10.0  # a server's answer to one conversation
    import_: float = 3600.0  # the operator imports the lot
    export: float = 3600.0  # the operator exports it
    machines: float = 600.0  # waiting in MSCHED's queue for machines
    setup: float = 300.0  # SETUP_RUN (the CMM waits for its start button to be pushed)
    run: float = 600.0  # from START_RUN to RUN_COMPL
    lost_grace: float = 3.0  # RUN_COMPL may still follow a machine's Shutdown (Run_Shut) or Idle
    # After an agent announced an ME's death: time for its WC to store a RUN_COMPL the ME had already
    # queued (it then completes the run as usual) before the run is counted lost.
    death_settle: float = 0.2
    # A run whose machine went Shutdown unheard (WC silent) is in doubt until its expected time
    # (the machine's `run_time` in cell.toml) plus this from its start; then the lot script decides.
    in_doubt: float = 30.0
    held: float = 3600.0  # the operator releases an entity held with a run in doubt
    cleanup: float = 5.0  # each cleanup conversation of a failing entity
    retry: float = 60.0  # asking a server (ls, msched) again while it is away, restarting or not started
    backoff: float = 0.2  # the first pause between those asks, doubling ...
    backoff_max: float = 2.0  # ... up to this
    pause: float = 1.0  # before an operation's next try after a machine was lost, doubling per try

    def asking(self, within: float | None = None) -> Backoff:
        """The pauses between asks of a server that cannot answer now: from `backoff`, doubling to
        `backoff_max`, for `within` seconds (`retry` by default)."""
        return Backoff(self.backoff, self.backoff_max, within=self.retry if within is None else within)


@dataclass
class Reservation:
    """Machines MSCHED bound to the entity for one operation (Machine_Req_Comp ACK_OK)."""

    op_type: str
    machine_run_id: int
    request_key: int | None
    machines: list[str]


@dataclass
class Run:
    """One run of one machine and its MACHINE_RUN_RESULT rows; a failed run's `note` says why it failed
    (MACHINE_RUN_OUTCOME's note: "no verdict from the CMM within 120s: run given up", ...)."""

    machine_id: str
    recipe_id: str
    machine_run_id: int
    ack_code: str
    results: dict[str, str]
    note: str = ""

    @property
    def ok(self) -> bool:
        return self.ack_code == AckCode.ACK_OK


@dataclass
class Operation:
    """One operation done: where it ran and what the machines reported."""

    op_type: str
    machine_run_id: int
    runs: list[Run]
    tries: int = 1

    @property
    def ok(self) -> bool:
        """Every run completed (ACK_OK). Whether the part is good is `passed`."""
        return all(r.ok for r in self.runs)

    @property
    def machines(self) -> list[str]:
        return [r.machine_id for r in self.runs]

    @property
    def results(self) -> dict[str, str]:
        """All runs' results in one dict (param -> value); with several machines, keys are machine.param."""
        if len(self.runs) == 1:
            return dict(self.runs[0].results)
        return {f"{r.machine_id}.{k}": v for r in self.runs for k, v in r.results.items()}

    @property
    def passed(self) -> bool:
        """The runs completed and the results say the part is within tolerance (see `verdict`)."""
        return self.ok and verdict(self.results)[0]


FAIL_WORDS = {"FAIL", "FAILED", "REJECT", "REJECTED", "NOK", "OUT_OF_TOLERANCE"}
PASS_WORDS = {"PASS", "PASSED", "OK", "ACCEPT", "ACCEPTED", "IN_TOLERANCE"}


def verdict(results: dict[str, str]) -> tuple[bool, str]:
    """Is a measured part within tolerance, from its run results (thesis 3.2.3)?

    Understands the two forms our machines report: PASS/FAIL values (the CMM, per feature or
    overall) and numeric measurements with a tolerance (`deviation` / `tolerance`, or
    `<name>` with `<name>_nominal` and `<name>_tol`). Any failing value fails the part; no
    verdict at all fails it too (a measurement that says nothing does not pass a part).
    """
    fails, passes, why = [], 0, []
    for param, value in sorted(results.items()):
        word = str(value).strip().upper()
        if word in FAIL_WORDS:
            fails.append(param)
        elif word in PASS_WORDS:
            passes += 1
    lowered = {k.lower(): v for k, v in results.items()}
    checks: list[tuple[str, float, float, float]] = []
    if "deviation" in lowered and "tolerance" in lowered:
        with contextlib.suppress(ValueError):
            checks.append(("deviation", float(lowered["deviation"]), 0.0, float(lowered["tolerance"])))
    for k, v in lowered.items():
        if f"{k}_nominal" in lowered and f"{k}_tol" in lowered:
            with contextlib.suppress(ValueError):
                checks.append((k, float(v), float(lowered[f"{k}_nominal"]), float(lowered[f"{k}_tol"])))
    for name, measured, nominal, tol in checks:
        if abs(measured - nominal) > abs(tol):
            fails.append(name)
            why.append(f"{name} {measured:g} off {nominal:g} by more than {abs(tol):g}")
        else:
            passes += 1
    if fails:
        return False, "out of tolerance: " + (", ".join(why) if why else ", ".join(fails))
    if passes:
        return True, "within tolerance"
    return False, "no verdict in the run results"


@dataclass
class Alternative:
    """One MACH_REQ conversation: one alternative (a set of machines, all needed) of a request."""

    op_type: str
    machines: list[str]
    ack: Message | None = None
    comp: Message | None = None
    reserved: list[str] = field(default_factory=list)
    error: str | None = None
    done: bool = False
    group: MachineRequest | None = None

    @property
    def key(self) -> int | None:
        return self.ack.request_key if self.ack is not None else None

    @property
    def sibling_cancelled(self) -> bool:
        """MSCHED ended it because another alternative of the entity was satisfied, or refused it for
        that reason (Machine_Req_Ack REQ_CANCEL: a sibling of its alt_group was bound before it came)."""
        if self.ack is not None and self.ack.ack_code == AckCode.REQ_CANCEL:
            return True
        c = self.comp
        return c is not None and c.ack_code == AckCode.REQ_CANCEL and "satisfied" in (c.note or "")

    def describe(self) -> str:
        return " AND ".join(self.machines)


class WcCall:
    """A conversation held on the bus thread for a step waiting in the script's thread (see _ask_wc)."""

    def __init__(self) -> None:
        self.answer: Message | None = None
        self.error: GwcError | None = None
        self.done = False
        self.task: asyncio.Task[None] | None = None
        self.abandoned = False


class MachineRequest:
    """The alternatives asked for one operation ((M1 AND M2) OR (M3)), as MSCHED answered them."""

    def __init__(self, op_type: str, alternatives: list[Alternative], alt_group: str | None = None) -> None:
        self.op_type = op_type
        self.alternatives = alternatives
        self.alt_group = alt_group  # sent with each alternative: MSCHED binds at most one of them
        self.winner: Alternative | None = None  # the alternative the entity took
        self.found: Reservation | None = None  # bound in a conversation the entity had given up (reserve.py)
        for a in alternatives:
            a.group = self

    def surplus(self, alt: Alternative) -> list[str]:
        """Machines of a second bound alternative that the winner does not use: to be given back."""
        keep = set(self.winner.reserved or self.winner.machines) if self.winner else set()
        return [m for m in (alt.reserved or alt.machines) if m not in keep]

    @property
    def keys(self) -> list[int]:
        return [a.key for a in self.alternatives if a.key is not None]

    def describe(self) -> str:
        return " OR ".join(f"({a.describe()})" for a in self.alternatives)


def traveller_path(cfg: Config, entity_id: int) -> Path:
    return cfg.var / "lots" / f"entity-{entity_id}.json"


def save_traveller(cfg: Config, entity_id: int, traveller: dict[str, Any]) -> None:
    """Write the traveller whole, never torn (gwc.files.rewrite)."""
    rewrite(traveller_path(cfg, entity_id), json.dumps(traveller, default=str, indent=1).encode())


def forget_previous_traveller(cfg: Config, entity_id: int) -> None:
    """The entity's script is ending: its traveller's previous version goes."""
    forget_previous(traveller_path(cfg, entity_id))


def read_traveller(cfg: Config, entity_id: int) -> dict[str, Any] | None:
    try:
        return json.loads(traveller_path(cfg, entity_id).read_text())
    except (OSError, ValueError):
        return None


def now_text() -> str:
    return datetime.now().isoformat(" ", "milliseconds")


def failure_reason(exc: BaseException) -> str:
    if isinstance(exc, (GwcError, BusError)):
        return str(exc)
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted"
    return f"lot script error: {type(exc).__name__}: {exc}"
