"""The module runtime: one lifecycle for every cell module (GUIDE 3), written once.

A module signs on to the bus and listens only for its start class (STARTUP, or ME_START for a
machine's WC). On a Startup_Request it answers Startup_Ack, does its startup work, widens its
interest to the classes it serves, and sends Startup_Complete. On a Shutdown_Request it answers
Shutdown_Ack, does its shutdown work, narrows its interest back and sends Shutdown_Complete.

Subclasses declare only their handlers, `{"MACH_REQ": self.machine_request, ...}` (the switch of
Listing 2's main loop without its repetition), and the two hooks. Each incoming conversation runs
as its own asyncio task, so a handler waiting for an answer never stops other conversations from
being served. Rule for handlers: check and change shared state with no `await` in between.

The start class stays in the interest set while running, so a second Startup_Request is answered
Notnow rather than left to time out (6.3.2.1 has the WC answer a failed startup the same way).
"""

from __future__ import annotations

import asyncio
import gc
import importlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar

import psycopg

from gwc import db, schema
from gwc.agent.control import notify_ready
from gwc.config import Config, load_config
from gwc.errors import ConversationTimeout, DatabaseError, DatabaseUnavailable, GwcError, Refused
from gwc.ipc import catalogue, eventloop
from gwc.ipc.bus import Bus, Conversation
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.lease import EXIT_DEPOSED, Deposed, Lease
from gwc.log import cap_output, conversation, open_log
from gwc.moduledb import ModuleDatabase
from gwc.promotion import PROMOTION_WAIT_S
from gwc.retry import Backoff, Deadline

Handler = Callable[[Conversation], Awaitable[None]]
T = TypeVar("T")
# The note of the Notnow a module answers before its STARTUP (or after its SHUTDOWN): a passing state,
# so callers (the lot library) ask again after a pause rather than give up.
NOT_STARTED = "module not started"
# How long a module waits for its database at startup, and asks to other modules go on while
# their database is away: the outage the cell rides out without a step failing (docs/reliability.md).
DATABASE_OUTAGE_S = 60.0

# Bus modules: name -> "module:Class". Machine halves take --machine and are named kind:ID.
BUS_MODULES = {
    "msched": "gwc.msched.server:Msched",
    "ms": "gwc.servers.machine:MachineServer",
    "ls": "gwc.servers.lot:LotServer",
    "cas": "gwc.servers.alarm:AlarmServer",
    "ers": "gwc.servers.recipe:RecipeServer",
    "sls": "gwc.servers.status_line:StatusLineServer",
    "wc": "gwc.wc.wc:WC",
    "opcua": "gwc.opcua.gateway:Gateway",
    "web": "gwc.web.module:WebModule",
}
# Processes off the bus, each `main(cfg, machine_id, log, stop) -> int`.
MACHINE_PROCESSES = {
    "me": "gwc.me:main",
    "cmmsim": "gwc.me.cmm_sim:main",
}
MACHINE_KINDS = ("wc", "me", "cmmsim")


def ask_again(answer: catalogue.Message) -> bool:
    """Whether an answer means "not now, ask again": the module is not started (yet, or any more),
    or its database is away (DB_Badrea: nothing was done, thesis 3.2.2)."""
    return answer.ack_code == AckCode.DB_BADREA or (
        answer.ack_code == AckCode.NOTNOW and answer.fields.get("note") == NOT_STARTED
    )


def module_name(kind: str, machine: str | None = None) -> str:
    """The bus and log name of a module: 'msched', or 'wc:cmm_wc' for a machine half."""
    return f"{kind}:{machine}" if machine else kind


async def ask(
    bus: Bus,
    cls: str,
    first: catalogue.Message,
    to: str | None,
    timeout: float | None = None,
    *more: catalogue.Message,
    within: float = 0.0,
) -> catalogue.Message:
    """Hold a one-question conversation with another module and return its answer.

    Raises ConversationTimeout (logged) if nobody answers. The caller reads the answer's ack_code.
    With `within` > 0, a module that is restarting (no answer, or an answer that `ask_again`)
    is asked again in a new conversation, with backoff, for up to `within` seconds: only for
    questions that are safe to ask twice.
    """
    backoff = Backoff(0.2, 2.0, within=within)
    while True:
        try:
            conv, batch = await bus.request(cls, first, *more, to=to, timeout=timeout)
            conv.end()
            answer = batch.first
            if not ask_again(answer) or (pause := backoff.next()) is None:
                return answer
        except ConversationTimeout:
            if (pause := backoff.next()) is None:
                raise
        bus.log.warning("%s did not take %s (restarting?): asking again in %.1fs", to or "nobody", cls, pause)
        await asyncio.sleep(pause)


def _load(path: str) -> Any:
    mod, _, attr = path.partition(":")
    return getattr(importlib.import_module(mod), attr)


class Module:
    """Base of every bus module. Subclasses set `role` (their database role) and override hooks."""

    role: str | None = None  # database role (gwc_<role>), None if the module does not use the database
    start_class = Conv.STARTUP
    stop_class = Conv.SHUTDOWN
    always: tuple[str, ...] = ()  # classes listened to even when not started
    ignored_peers: tuple[str, ...] = ()  # name prefixes of modules this one does not track (gwc.ipc.bus.Bus)

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        self.cfg = cfg
        self.name = name
        self.log = log
        self.bus = Bus(
            name,
            cfg.bus,
            log,
            interest=self.idle_interest(),
            ignored_peers=self.ignored_peers,
        )
        self.started = False
        self.exit_code = 0
        self._stop = asyncio.Event()
        self._tasks: set[asyncio.Task[Any]] = set()
        # Redundancy (gwc/lease.py): the lease that makes this instance the active one, when cell.toml
        # runs the module with standbys; `fenced` once it lost it (it then serves nothing and exits).
        self.lease = Lease.of(cfg, name, log)
        self.fenced = False
        self.holding = LeaseHolding(self)

        def prepare(conn: psycopg.Connection) -> None:
            self.holding.on_connect(conn)
            self.on_connect(conn)

        self.database = ModuleDatabase(
            cfg, self.role, log, prepare, self.holding.deposed, self.on_database_back, self._tasks
        )
        self.lifecycle = Lifecycle(self)

    # ----------------------------------------------------------------- what subclasses declare

    def handlers(self) -> dict[str, Handler]:
        """The conversations served while started, by class."""
        return {}

    async def on_startup(self) -> str:
        """Startup work; return an ack code (ACK_OK to go on)."""
        return AckCode.ACK_OK

    async def on_shutdown(self) -> str | None:
        """Shutdown work: finish or refuse what is pending. May return a note for Shutdown_Complete."""
        return None

    def cancel_start(self) -> Awaitable[str] | None:
        """Asked on a stop request while not started: the work that cancels a start in progress (a WC
        whose machine waits to be homed), giving the note of the stop's completion; None when no start
        is in progress (the stop is then refused: not started)."""
        return None

    async def still_up(self) -> bool:
        """Asked on a start request while started: whether the cell still counts this module up (a start
        is then refused as already done). False lets the start run again."""
        return True

    async def on_bus(self) -> None:
        """Called once signed on to the bus, before the first conversation is served."""

    async def on_idle(self) -> None:
        """Called about every heartbeat while the module runs (timers, liveness checks)."""

    def serves(self, cls: str) -> bool:
        """Whether a conversation of this class is served now (started, or listened to always)."""
        return self.started or cls in self.always

    def startup_complete(self, code: str) -> catalogue.Message:
        return message(Msg.STARTUP_COMPLETE, ack_code=code)

    def shutdown_complete(self, note: str | None) -> catalogue.Message:
        return message(Msg.SHUTDOWN_COMPLETE, ack_code=AckCode.ACK_OK, note=note)

    async def ask(
        self,
        cls: str,
        first: catalogue.Message,
        to: str | None,
        timeout: float | None = None,
        *more: catalogue.Message,
        within: float = 0.0,
    ) -> catalogue.Message:
        """ask() on this module's bus."""
        return await ask(self.bus, cls, first, to, timeout, *more, within=within)

    def idle_interest(self) -> set[str]:
        return {self.start_class, *self.always}

    def spawn(self, coro: Coroutine[Any, Any, object]) -> None:
        """Run work in the background, owned by the module (cancelled when it stops); its result is dropped."""
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def busy_interest(self) -> set[str]:
        return {self.start_class, self.stop_class, *self.always, *self.handlers()}

    # ----------------------------------------------------------------- database

    def db(self) -> psycopg.Connection:
        """This module's connection, made on first use and remade after a failure (3.2.2).

        While the database is away this raises DatabaseUnavailable at once: a task of its own
        reconnects with backoff, so no step and no heartbeat ever waits for a database that is gone.
        """
        return self.database.connection()

    def transaction(self, fn: Callable[[psycopg.Cursor[Any]], T]) -> T:
        """Run one step's database work as one transaction, retried on transient failures."""
        return self.database.transaction(fn)

    async def transaction_when_up(self, fn: Callable[[psycopg.Cursor[Any]], T], within: float | None = None) -> T:
        """A step that must not be lost though nobody waits for it (a broadcast heard, a dead lot
        reaped, a run's results): run now, or as soon as the database is back, for up to `within`
        seconds (None: as long as the module runs); then DatabaseUnavailable."""
        deadline = Deadline(within)
        while True:
            try:
                return self.transaction(fn)
            except DatabaseUnavailable:
                if not await self.wait_database(deadline):
                    raise

    async def wait_database(self, deadline: Deadline) -> bool:
        """Wait until the database is back (True), or the deadline passes (False)."""
        return await self.database.wait_up(deadline)

    def on_connect(self, conn: psycopg.Connection) -> None:
        """Called with every new connection, before it is used (MSCHED takes its lock here).
        DatabaseUnavailable from it counts as no connection: the module reconnects later."""

    async def on_database_back(self, down_for: float) -> None:
        """Called once the database is back after an outage of `down_for` seconds."""

    # ----------------------------------------------------------------- running

    def stop(self, code: int = 0) -> None:
        self.exit_code = self.exit_code or code
        self._stop.set()

    async def run(self, start: bool = False) -> int:
        await schema.check_at_start(self.cfg, self.role, self.log)  # a schema it cannot run with: it exits
        if self.lease is not None:
            if not await until_stopped(self.holding.stand_by(), self._stop):
                self.log.info("Stopped while standing by")
                return self.exit_code
            start = True  # the active instance of a redundant module starts itself
        await self.bus.sign_on()
        await self.on_bus()
        self.log.info("Starting: listening for %s", ", ".join(sorted(self.bus.interests)))
        # What start-up made (modules, the catalogue, connections) lives as long as the process: out
        # of the collector's way, so that its full collections do not stall a step for milliseconds.
        gc.freeze()
        if start:
            await self.lifecycle.start()
            if self.lease is not None:
                notify_ready()
        loop = asyncio.get_running_loop()
        idle = loop.create_task(self._idle_loop())
        self.bus.accept(self._accept)
        try:
            await self._stop.wait()
        finally:
            self.bus.accept(None)
            idle.cancel()
            if self.started:
                await self.lifecycle.finish()
            for t in list(self._tasks):
                t.cancel()
            await self.bus.close(flush=0.0 if self.fenced else 1.0)
            self.database.close()
            self.log.info("Stopped (exit %d)", self.exit_code)
        return self.exit_code

    def _accept(self, conv: Conversation) -> None:
        """Every conversation opened with this module runs as a task of its own, started as its first
        batch arrives (Bus.accept): a handler waiting for an answer never keeps the next conversation
        waiting (docs/protocol.md, No collisions)."""
        task = asyncio.get_running_loop().create_task(self._serve(conv))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _idle_loop(self) -> None:
        """The module's periodic work, right after each of its bus heartbeats: one wake-up for both."""
        beat = asyncio.Event()
        self.bus.beat_listeners.append(beat.set)
        while True:
            await beat.wait()
            beat.clear()
            try:
                self.holding.keep()
                if self.fenced:
                    return
                self.database.probe()
                await self.on_idle()
            except DatabaseUnavailable:
                pass  # said once when it went; done again once it is back
            except Exception as e:
                self.bus.faults.failed("idle work", e)

    async def _serve(self, conv: Conversation) -> None:
        with conversation(conv.id, conv.cls):
            assert conv.first is not None
            head = conv.first.first
            opener = catalogue.CONVERSATION_CLASSES[conv.cls].messages[0]
            try:
                if self.fenced:
                    self.log.info("ignored %s from %s: deposed", head.name, conv.first.sender)
                elif head.name != opener:
                    self.log.info(
                        "ignored %s from %s: not the opening of a conversation here", head.name, conv.first.sender
                    )
                elif conv.cls == self.start_class:
                    await self.lifecycle.startup(conv)
                elif conv.cls == self.stop_class:
                    await self.lifecycle.shutdown(conv)
                else:
                    handler = self.handlers().get(conv.cls)
                    if handler is None or not self.serves(conv.cls):
                        self.log.info("ignored %s from %s: not served now", head.name, conv.first.sender)
                        why = NOT_STARTED if handler is not None else f"{self.name} does not serve {conv.cls}"
                        await self._refuse(conv, AckCode.NOTNOW, why)
                    else:
                        await handler(conv)
            except asyncio.CancelledError:
                raise
            except Refused as e:  # a handler's (or its store's) refusal: answered here, for every module
                self.log.info("refused %s from %s: %s (%s)", conv.cls, conv.first.sender, e.ack_code, e.detail or "-")
                await self._refuse(conv, e.ack_code, e.detail, **e.fields)
            except DatabaseUnavailable as e:
                self.log.warning("%s from %s not served now: %s", head.name, conv.first.sender, e)
                await self._refuse(conv, AckCode.DB_BADREA, str(e))
            except DatabaseError as e:
                self.log.error("%s failed: %s", head.name, e)
                await self._refuse(conv, AckCode.DB_BADUPD, str(e))
            except GwcError as e:
                self.log.error("%s failed: %s", head.name, e)
                await self._refuse(conv, AckCode.BAD_MESSAGE, str(e))
            except Exception as e:
                self.log.exception("%s failed unexpectedly", head.name)
                await self._refuse(conv, AckCode.BAD_MESSAGE, f"internal error: {e}")
            finally:
                conv.end()

    async def _refuse(self, conv: Conversation, code: str, note: str, **fields: Any) -> None:
        """Answer a conversation nobody answered yet with its class's refusal: `code`, `note`, `fields`."""
        if conv.sent or conv.first is None:
            return
        answer = catalogue.refusal(conv.cls, code, note, conv.first.first.fields)
        if answer is None:
            return
        try:
            await conv.send(message(answer.name, **answer.fields, **fields) if fields else answer)
        except GwcError as e:
            self.log.warning("could not refuse %s: %s", conv.cls, e)


def run_module(
    kind: str,
    machine: str | None = None,
    start: bool = False,
    cfg: Config | None = None,
    options: dict[str, Any] | None = None,
) -> int:
    """Run one module as this process until SIGTERM; returns the exit code (3 = database fatal)."""
    cfg = cfg or load_config()
    if kind in MACHINE_KINDS and not machine:
        raise GwcError(f"{kind} needs --machine ID (one of: {', '.join(m.id for m in cfg.machines)})")
    if machine:
        cfg.machine(machine)  # unknown machine: ConfigError before anything starts
    name = module_name(kind, machine)
    log = open_log(name, cfg.log_dir, cfg.level_of(name))
    cap_output()
    log.info("Starting %s (pid %d)", name, os.getpid())
    if kind in MACHINE_PROCESSES:
        stop = threading.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
        try:
            code = _load(MACHINE_PROCESSES[kind])(cfg, machine, log, stop)
        except GwcError as e:
            log.error("fatal: %s", e)
            code = e.exit_code
        log.info("Stopped %s (exit %d)", name, code)
        return int(code)
    if kind not in BUS_MODULES:
        known = ", ".join([*BUS_MODULES, *MACHINE_PROCESSES])
        raise GwcError(f"unknown module {kind!r} (known: {known})")
    cls = _load(BUS_MODULES[kind])

    async def main() -> int:
        module = (
            cls(cfg, name, log, **(options or {}))
            if machine is None
            else cls(cfg, name, log, machine, **(options or {}))
        )
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, module.stop)
        return await module.run(start=start)

    try:
        return eventloop.run(main())
    except GwcError as e:
        log.error("fatal: %s", e)
        print(f"gwc: {name}: {e}", file=sys.stderr)
        return e.exit_code


async def until_stopped(work: Awaitable[None], stop: asyncio.Event) -> bool:
    """Do `work` unless `stop` is set first (SIGTERM): whether it was done."""
    done = asyncio.ensure_future(work)
    stopping = asyncio.ensure_future(stop.wait())
    try:
        await asyncio.wait({done, stopping}, return_when=asyncio.FIRST_COMPLETED)
    finally:
        stopping.cancel()
    if not done.done():
        done.cancel()
        return False
    done.result()
    return True


class Lifecycle:
    """A module's STARTUP and SHUTDOWN (GUIDE 3), written once: answering the start and stop classes,
    doing the module's startup and shutdown work through its hooks, widening and narrowing its interest.
    A part the Module holds, as LeaseHolding is."""

    def __init__(self, module: Module) -> None:
        self.module = module

    async def start(self) -> str:
        """The module's startup work (waiting up to DATABASE_OUTAGE_S for its database), then its
        interest widened: the ack code of Startup_Complete."""
        m = self.module
        deadline = Deadline(DATABASE_OUTAGE_S)
        while True:
            try:
                code = await m.on_startup()
                break
            except DatabaseUnavailable:
                m.log.warning("startup waits for the cell database")
                if not await m.wait_database(deadline):
                    raise
        if code == AckCode.ACK_OK:
            m.started = True
            m.bus.set_interest(m.busy_interest())
            m.log.info("started: listening for %s", ", ".join(sorted(m.bus.interests)))
        return code

    async def startup(self, conv: Conversation) -> None:
        m = self.module
        assert conv.first is not None
        req = conv.first.first
        if req.module != m.name:
            m.log.info("ignored Startup_Request for %s", req.module)
            return
        if m.started and await m.still_up():
            await conv.send(message(Msg.STARTUP_ACK, ack_code=AckCode.NOTNOW, note=f"{m.name} is already started"))
            return
        await conv.send(message(Msg.STARTUP_ACK, ack_code=AckCode.ACK_OK))
        try:
            code = await self.start()
        except Exception as e:
            # The starter waits for Startup_Complete: tell it how the startup failed, then let
            # _serve log the error.
            failed = (
                AckCode.DB_BADREA
                if isinstance(e, DatabaseUnavailable)
                else AckCode.DB_BADUPD
                if isinstance(e, DatabaseError)
                else AckCode.START_FAIL
            )
            await conv.send(m.startup_complete(failed))
            raise
        await conv.send(m.startup_complete(code))

    async def shutdown(self, conv: Conversation) -> None:
        m = self.module
        assert conv.first is not None
        req = conv.first.first
        if req.module != m.name:
            m.log.info("ignored Shutdown_Request for %s", req.module)
            return
        if not m.started:
            cancel = m.cancel_start()
            if cancel is None:
                await conv.send(message(Msg.SHUTDOWN_ACK, ack_code=AckCode.NOTNOW, note=f"{m.name} is not started"))
                return
            await conv.send(message(Msg.SHUTDOWN_ACK, ack_code=AckCode.ACK_OK))
            await conv.send(m.shutdown_complete(await cancel))
            return
        await conv.send(message(Msg.SHUTDOWN_ACK, ack_code=AckCode.ACK_OK))
        note = await self.finish()
        await conv.send(m.shutdown_complete(note))

    async def finish(self) -> str | None:
        """The module's shutdown work, its interest narrowed back first: the note of Shutdown_Complete."""
        m = self.module
        m.started = False
        m.bus.set_interest(m.idle_interest())
        note = None
        try:
            note = await m.on_shutdown()
        except Exception:
            m.log.exception("shutdown work failed")
        m.log.info("shut down: listening for %s", ", ".join(sorted(m.bus.interests)))
        return note


class LeaseHolding:
    """A module's side of its lease (gwc/lease.py), when it runs with standbys: standing by off the bus
    until it holds the lease, taking it again on every new connection, renewing it at the heartbeat,
    and being deposed. A part the Module holds, so the lease adds no method to every module."""

    def __init__(self, module: Module) -> None:
        self.module = module

    def on_connect(self, conn: psycopg.Connection) -> None:
        """A new connection of the active instance takes its lease again (same epoch), or Deposed."""
        lease = self.module.lease
        if lease is not None and lease.epoch:
            lease.claim(conn)

    async def stand_by(self) -> None:
        """Off the bus until this instance holds its module's lease; then its connection is the one
        that holds it, and the module starts at once, carrying on from the tables."""
        m = self.module
        assert m.lease is not None
        m.log.info("redundant: waiting for the lease of %s", m.name)
        # Each try watches a database failing over for its promoted member (db.PROMOTION_POLL_S).
        conn = await m.lease.wait(lambda: db.connect(m.cfg, m.role, m.log, 1, PROMOTION_WAIT_S), notify_ready)
        m.database.adopt(conn)
        try:
            m.on_connect(conn)
        except DatabaseUnavailable as e:  # (MSCHED's own lock: its predecessor's session is going)
            m.log.warning("after taking the lease: %s", e)
            m.database.close()

    def keep(self) -> None:
        """At each heartbeat: renew the lease when due; depose this instance when it could not for
        the lease's deadline (a standby may fence it soon) or the lease is not its own any more."""
        m = self.module
        lease = m.lease
        if lease is None or not lease.active or m.fenced:
            return
        try:
            if lease.overdue():
                lease.depose(f"the lease of {m.name} was not renewed for {lease.settings.deadline:.1f}s")
            if lease.due():
                m.transaction(lease.renew)
        except Deposed as e:
            self.deposed(str(e))

    def deposed(self, why: str) -> None:
        """Fenced: serve nothing more, leave the bus and exit; the agent starts this a standby again."""
        m = self.module
        if m.fenced:
            return
        m.fenced = True
        m.started = False
        m.bus.set_interest(set())
        m.log.error("%s: no longer the active %s, leaving the bus to stand by again", why, m.name)
        m.database.close()
        m.stop(EXIT_DEPOSED)
