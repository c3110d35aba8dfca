"""The work of the conversations a WC serves (thesis 6.3.2: SETUP_RUN, START_RUN, DNLD_ME, UPLD_ME), each
checked against the machine's status and done under the state lock; and an abandoned setup given up
(see gwc/wc/wc.py, whose handlers call it)."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

from gwc.errors import DatabaseError, DatabaseUnavailable
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.mq import MeMessage, MessageId
from gwc.servers.recipe import RECIPE_ID
from gwc.wc.base import ABANDONED_S, ALL_OPERATIONS, SETUP_CHECK_S, MachineState, ServerCalls, WcHost
from gwc.wc.me_side import MeSide


class Steps:
    """What the WC's handlers do: the checks (status, reservation), the work under the state lock, the
    refusals answered."""

    def __init__(self, host: WcHost, state: MachineState, servers: ServerCalls, me: MeSide) -> None:
        self.host = host
        self.state = state
        self.servers = servers
        self.me = me
        self._setup_checked = 0.0  # when the run set up was last found reserved (or not) ...
        self._unreserved_since: float | None = None  # ... and since when it is not

    async def refuse_now(self, conv: Conversation, ack: str, code: str, note: str) -> None:
        self.host.log.info("refused %s: %s (%s)", conv.cls, code, note)
        await conv.send(message(ack, ack_code=code, note=note[:500]))

    def asking_entity(self, conv: Conversation) -> tuple[int | None, tuple[str, str] | None]:
        """Defence in depth (docs/security.md): a lot entity (lot:E) sets up and starts only a run that
        RESERVED_MACHINES gives to E on this machine. The entity to check (None: the asker holds the module
        key and is trusted: the operator's tools, tests driving a machine by hand), or why it may not ask."""
        assert conv.first is not None
        req = conv.first.first
        asker = conv.initiator
        if not asker.startswith("lot:"):
            return None, None
        entity, named = asker[4:], req.fields.get("entity_id")  # Setup_Run names its entity; Start_Run does not
        if not entity.isdigit() or (named is not None and str(named) != entity):
            return None, (AckCode.NOT_RESERVED, f"{asker} asks for entity {named}")
        return int(entity), None

    async def not_reserved(self, conv: Conversation) -> tuple[str, str] | None:
        """START_RUN's check (see _asking_entity). The run this WC set up for the same asker was found
        reserved to it by that SETUP_RUN's read: not read again."""
        assert conv.first is not None
        req = conv.first.first
        entity, refusal = self.asking_entity(conv)
        set_up = (
            req.machine_run_id == self.state.machine_run_id
            and (conv.initiator, req.machine_run_id) == self.state.set_up_for
        )
        if entity is None or set_up:
            return refusal
        try:
            row = await self.servers.read_when_up(
                "SELECT 1 FROM reserved_machines WHERE machine_id = %s AND machine_run_id = %s AND entity_id = %s",
                (self.state.machine_id, req.machine_run_id, entity),
            )
        except DatabaseError as e:
            return AckCode.DB_BADREA, str(e)
        if row is None:
            return (
                AckCode.NOT_RESERVED,
                f"run {req.machine_run_id} on {self.state.machine_id} is not reserved to lot:{entity}",
            )
        return None

    def check(self, req: Message, allowed: tuple[MachineStatus, ...]) -> tuple[str, str] | None:
        """Why this request cannot be served now, as (ack code, note); None if it can."""
        if req.machine_id != self.state.machine_id:
            return AckCode.BAD_MESSAGE, f"this is the WC of {self.state.machine_id}, not of {req.machine_id}"
        if self.state.status not in allowed:
            return AckCode.NOTNOW, f"machine is {self.state.status}, not {' or '.join(allowed)}"
        return None

    async def serve_step(
        self,
        conv: Conversation,
        ack: str,
        allowed: tuple[MachineStatus, ...],
        work: Callable[[Message], Awaitable[tuple[str, str] | None]],
    ) -> bool:
        """One of 6.3.2's steps: the state checked and the work done under the state lock, refusals
        answered with `ack`. True when it was done (the caller answers ACK_OK)."""
        assert conv.first is not None
        req = conv.first.first
        async with self.state.lock:
            refusal = self.check(req, allowed)
            if refusal is None:
                refusal = await work(req)
        if refusal is not None:
            await self.refuse_now(conv, ack, *refusal)
            return False
        return True

    # ----------------------------------------------------------------- SETUP_RUN, START_RUN

    async def setup(self, req: Message, entity: int | None) -> tuple[str, str] | None:
        # The reservation (a lot's), the recipe (the one asked for, else the machine's first for the op
        # type), that OP_MACHINE_RECIPE allows it, and its approved version: one read.
        try:
            reserved, recipe, valid, version, checksum = await self.servers.read_when_up(
                "SELECT %(e)s::bigint IS NULL OR EXISTS (SELECT 1 FROM reserved_machines WHERE machine_id = %(m)s "
                "AND machine_run_id = %(run)s AND entity_id = %(e)s), r.recipe, EXISTS (SELECT 1 FROM "
                "op_machine_recipe WHERE machine_id = %(m)s AND recipe_id = r.recipe AND op_type = %(op)s), "
                "v.version, v.checksum FROM (SELECT coalesce(%(r)s::text, (SELECT min(recipe_id) FROM "
                "op_machine_recipe WHERE machine_id = %(m)s AND op_type = %(op)s)) AS recipe) r "
                "LEFT JOIN recipe_versions v ON v.recipe_id = r.recipe AND v.approved",
                {
                    "e": entity,
                    "m": self.state.machine_id,
                    "run": req.machine_run_id,
                    "r": req.recipe_id,
                    "op": req.op_type,
                },
            ) or (False, None, False, None, None)
        except DatabaseUnavailable:
            raise  # the module answers DB_Badrea: the lot may ask again once the database is back
        except DatabaseError as e:
            return AckCode.DB_BADREA, str(e)
        if not reserved:
            return (
                AckCode.NOT_RESERVED,
                f"run {req.machine_run_id} on {self.state.machine_id} is not reserved to lot:{entity}",
            )
        if recipe is None:
            return AckCode.REC_INVAL, f"{self.state.machine_id} has no recipe for op type {req.op_type}"
        if not valid:
            return AckCode.REC_INVAL, f"recipe {recipe} is not for op type {req.op_type} on {self.state.machine_id}"
        # Listing 3: a machine set up for a run accepts no other operation until the run is over. That and
        # the status Setup are asked now, beside the recipe's setup on the ME, which depends on neither. The
        # lot is not kept waiting for MSCHED's answer to the accept types: while the run is reserved
        # MSCHED binds the machine to nobody else anyway, so what the accepts-nothing protects is the
        # run's end, and the run's Run_Complete waits for it (docs/machine-interface.md 4.1). Both are on
        # the wire before the ME is asked: the Machine Server's change, a durable commit, takes longer
        # than the ME's setup, and the answer to the lot waits for it.
        status = asyncio.ensure_future(
            self.servers.change_status(
                MachineStatus.SETUP, expect=[MachineStatus.IDLE], recipe_id=recipe, machine_run_id=req.machine_run_id
            )
        )
        accept = asyncio.ensure_future(self.servers.set_accept_types([]))
        await asyncio.sleep(0)  # each sends its request in its first step
        try:
            refusal = await self._set_up_on_me(recipe, self._recipe(recipe, version, checksum))
        finally:
            set_up = await status
        if refusal is None and not set_up:
            refusal = AckCode.DB_BADUPD, "the Machine Server refused the change to Setup"
        if refusal is not None:
            note = f"setup of run {req.machine_run_id} failed"
            if (
                set_up
                and not await self.servers.change_status(MachineStatus.IDLE, expect=[MachineStatus.SETUP], note=note)
                and self.state.status == MachineStatus.SETUP
            ):
                # Left in Setup: given up by the abandoned-setup watch once the lot has unreserved the run.
                self.state.machine_run_id, self.state.recipe_id = req.machine_run_id, recipe
            if await accept and self.state.status == MachineStatus.IDLE:  # (not on a machine that went down meanwhile)
                await self.servers.set_accept_types(ALL_OPERATIONS)
            return refusal
        self.state.machine_run_id, self.state.recipe_id = req.machine_run_id, recipe
        self.servers.accepting_none = accept
        # A start refused leaves the run set up, as a refused START_RUN does: its lot gives it up.
        return await self.run_on_me(req) if req.start else None

    async def _set_up_on_me(self, recipe_id: str, fetch: Awaitable[tuple[Path | None, str]]) -> tuple[str, str] | None:
        """The approved recipe (`fetch`) to the ME, which sets up with it; the refusal, or None."""
        path, why = await fetch
        if path is None:
            await self.servers.raise_alarm(
                "REC_INVAL", f"{self.state.machine_id}: recipe {recipe_id} refused: {why}", wait=False
            )
            return AckCode.REC_INVAL, why
        answer, refusal = await self.me.ask_me(MeMessage(MessageId.SETUP_RUN, file_name=str(path), recipe_id=recipe_id))
        if answer is None:
            return refusal
        if answer.ack_code != AckCode.ACK_OK:
            return answer.ack_code or AckCode.START_FAIL, f"ME refused the setup: {answer.alarm_text}"
        return None

    async def _recipe(self, recipe_id: str, version: int | None, checksum: str | None) -> tuple[Path | None, str]:
        """The approved recipe for the ME: the copy this machine holds when it is the approved version (its
        sha256 checked now), else fetched from the ERS (a new version, a machine's first setup with it, a
        copy changed on disk, or no approved version: the ERS says why)."""
        if version is not None and checksum is not None:
            path = self.state.recipe_file(recipe_id, version)
            with contextlib.suppress(OSError):
                if hashlib.sha256(path.read_bytes()).hexdigest() == checksum:
                    return path, ""
        return await self.servers.fetch_recipe(recipe_id)

    async def run_on_me(self, req: Message) -> tuple[str, str] | None:
        if req.machine_run_id != self.state.machine_run_id:
            return AckCode.START_FAIL, f"set up for run {self.state.machine_run_id}, not {req.machine_run_id}"
        results = self.state.results_path(req.machine_run_id)
        answer, refusal = await self.me.ask_me(
            MeMessage(MessageId.START_RUN, file_name=str(results), recipe_id=self.state.recipe_id or "")
        )
        if answer is None:
            return refusal
        if answer.ack_code != AckCode.ACK_OK:
            return AckCode.START_FAIL, f"ME refused to start: {answer.ack_code} {answer.alarm_text}"
        # The status now, not at the check: a shutdown may have come while the ME was starting.
        target = MachineStatus.RUN_SHUT if self.state.status == MachineStatus.SETUP_SHUT else MachineStatus.RUNNING
        if not await self.servers.change_status(
            target, expect=[self.state.status], machine_run_id=req.machine_run_id, recipe_id=self.state.recipe_id
        ):
            return AckCode.DB_BADUPD, f"the Machine Server refused the change to {target}"
        return None

    # ----------------------------------------------------------------- DNLD_ME, UPLD_ME

    async def not_held(self, conv: Conversation) -> tuple[str, str] | None:
        """DNLD_ME and UPLD_ME's check (Listing 1's ers_download / ers_upload from a lot script): a lot
        entity lot:E may download to and upload from only a machine RESERVED_MACHINES gives to E (any
        of its runs), else Not_Auth; a recipe id must be a recipe id (it names the machine's file)."""
        assert conv.first is not None
        req = conv.first.first
        if not RECIPE_ID.match(req.recipe_id):
            return AckCode.BAD_MESSAGE, f"recipe id {req.recipe_id!r}: letters, digits, _ . - only (64 at most)"
        entity, refusal = self.asking_entity(conv)
        if entity is None:
            return refusal
        try:
            row = await self.servers.read_when_up(
                "SELECT 1 FROM reserved_machines WHERE machine_id = %s AND entity_id = %s LIMIT 1",
                (self.state.machine_id, entity),
            )
        except DatabaseError as e:
            return AckCode.DB_BADREA, str(e)
        if row is None:
            return AckCode.NOT_AUTH, f"{self.state.machine_id} is not reserved to lot:{entity}"
        return None

    async def download(self, req: Message) -> tuple[str, str] | None:
        path, why = await self.servers.fetch_recipe(req.recipe_id)
        if path is None:
            return AckCode.REC_INVAL, why
        answer, refusal = await self.me.ask_me(
            MeMessage(MessageId.DNLD_ME, file_name=str(path), recipe_id=req.recipe_id)
        )
        if answer is None:
            return refusal
        if answer.ack_code != AckCode.ACK_OK:
            return answer.ack_code or AckCode.START_FAIL, f"ME refused the download: {answer.alarm_text}"
        return None

    async def upload(self, req: Message) -> tuple[tuple[str, str] | None, str | None]:
        answer, refusal = await self.me.ask_me(MeMessage(MessageId.UPLD_ME, recipe_id=req.recipe_id))
        if answer is None:
            return refusal, None
        if answer.ack_code != AckCode.ACK_OK or not answer.file_name:
            return (answer.ack_code or AckCode.START_FAIL, f"the ME returned no recipe: {answer.alarm_text}"), None
        try:
            return None, Path(answer.file_name).read_text()
        except (OSError, UnicodeDecodeError) as e:
            return (AckCode.REC_INVAL, f"the ME's recipe file {answer.file_name} is unreadable: {e}"), None

    # ----------------------------------------------------------------- an abandoned setup

    async def give_up_abandoned_setup(self) -> None:
        """A machine set up for a run that MSCHED no longer reserves for it goes Idle again.

        The lot that set it up gave up or died between SETUP_RUN and START_RUN, and was unreserved.
        Nobody will start that run, and the machine serves SETUP_RUN only when Idle: without this it
        would stay in Setup for good. The run must be missing from RESERVED_MACHINES for ABANDONED_S
        first, so a reservation is never raced.
        """
        run_id, now = self.state.machine_run_id, time.monotonic()
        if self.state.status not in (MachineStatus.SETUP, MachineStatus.SETUP_SHUT) or run_id is None:
            self._unreserved_since = None
            return
        if now - self._setup_checked < SETUP_CHECK_S:
            return
        self._setup_checked = now
        try:
            reserved = (
                self.servers.read(
                    "SELECT 1 FROM reserved_machines WHERE machine_id = %s AND machine_run_id = %s",
                    (self.state.machine_id, run_id),
                )
                is not None
            )
        except DatabaseUnavailable:
            raise
        except DatabaseError as e:
            self.host.log.warning("cannot check the reservation of run %d: %s", run_id, e)
            return
        if reserved or self._unreserved_since is None:
            self._unreserved_since = None if reserved else now
            return
        if now - self._unreserved_since < ABANDONED_S:
            return
        async with self.state.lock:
            if (
                self.state.status not in (MachineStatus.SETUP, MachineStatus.SETUP_SHUT)
                or self.state.machine_run_id != run_id
            ):
                return
            self.host.log.warning(
                "run %d is set up but not reserved any more (its lot gave up or died): giving it up", run_id
            )
            self.state.clear_run()
            self._unreserved_since = None
            if self.state.status == MachineStatus.SETUP_SHUT:
                await self.me.go_shutdown(f"shutdown after run {run_id} was given up")
            else:
                await self.servers.change_status(
                    MachineStatus.IDLE, expect=[MachineStatus.SETUP], note=f"run {run_id} given up: not reserved"
                )
                await self.servers.set_accept_types(ALL_OPERATIONS)
