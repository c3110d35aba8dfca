"""The conversations a WC serves (thesis 6.3.2): SETUP_RUN, START_RUN, DNLD_ME, UPLD_ME, each checked
against the machine's status and done under the state lock (see gwc/wc/wc.py)."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
from collections.abc import Awaitable, Callable
from pathlib import Path

from gwc.errors import ConversationTimeout, DatabaseError, DatabaseUnavailable, QueueError
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode, MachineStatus
from gwc.ipc.mq import MeMessage, MessageId
from gwc.ipc.names import Conv, Msg
from gwc.quality.sheet import with_sheet
from gwc.servers.recipe import RECIPE_ID
from gwc.wc.base import ALL_OPERATIONS, SERVER_RESTART, SERVER_TIMEOUT, S
from gwc.wc.device import WCDevice
from gwc.wc.link import MeDied


class WCSteps(WCDevice):
    """The conversations served."""

    async def _refuse_now(self, conv: Conversation, ack: str, code: str, note: str) -> None:
        self.log.info("refused %s: %s (%s)", conv.cls, code, note)
        await conv.send(message(ack, ack_code=code, note=note[:500]))

    def _asking_entity(self, conv: Conversation) -> tuple[int | None, tuple[str, str] | None]:
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

    async def _not_reserved(self, conv: Conversation) -> tuple[str, str] | None:
        """START_RUN's check (see _asking_entity). The run this WC set up for the same asker was found
        reserved to it by that SETUP_RUN's read: not read again."""
        assert conv.first is not None
        req = conv.first.first
        entity, refusal = self._asking_entity(conv)
        set_up = req.machine_run_id == self.machine_run_id and (conv.initiator, req.machine_run_id) == self._set_up_for
        if entity is None or set_up:
            return refusal
        try:
            row = await self._read_when_up(
                "SELECT 1 FROM reserved_machines WHERE machine_id = %s AND machine_run_id = %s AND entity_id = %s",
                (self.machine_id, req.machine_run_id, entity),
            )
        except DatabaseError as e:
            return AckCode.DB_BADREA, str(e)
        if row is None:
            return (
                AckCode.NOT_RESERVED,
                f"run {req.machine_run_id} on {self.machine_id} is not reserved to lot:{entity}",
            )
        return None

    def _check(self, req: Message, allowed: tuple[MachineStatus, ...]) -> tuple[str, str] | None:
        """Why this request cannot be served now, as (ack code, note); None if it can."""
        if req.machine_id != self.machine_id:
            return AckCode.BAD_MESSAGE, f"this is the WC of {self.machine_id}, not of {req.machine_id}"
        if self.status not in allowed:
            return AckCode.NOTNOW, f"machine is {self.status}, not {' or '.join(allowed)}"
        return None

    async def _ask_me(self, msg: MeMessage) -> tuple[MeMessage | None, tuple[str, str] | None]:
        """One request to the ME within a step: its answer, or the refusal the step gives (a dead ME
        is declared dead on the way)."""
        try:
            return await self.me_request(msg), None
        except MeDied as e:
            await self.me_died(str(e))
            return None, (AckCode.START_FAIL, f"ME failed: {e}")
        except QueueError as e:
            return None, (AckCode.START_FAIL, str(e))

    async def _serve_step(
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
        async with self._state_lock:
            refusal = self._check(req, allowed)
            if refusal is None:
                refusal = await work(req)
        if refusal is not None:
            await self._refuse_now(conv, ack, *refusal)
            return False
        return True

    # ----------------------------------------------------------------- SETUP_RUN, START_RUN

    async def setup_run(self, conv: Conversation) -> None:
        """6.3.2.3: Idle only; reservation, recipe and op type checked; the approved recipe to the ME;
        status Setup (asked beside the ME's setup: docs/machine-interface.md, *The order of a run's steps*).
        A request that names no recipe gets this machine's for the op type (OP_MACHINE_RECIPE), named in
        the answer. One that says `start` is started as soon as it is set up, as START_RUN would, and
        answered once Running: the lot's START_RUN round trip saved (docs/lot-scripts.md)."""
        assert conv.first is not None
        req = conv.first.first
        self.log.info(
            "SETUP_RUN run %d recipe %s op %s%s",
            req.machine_run_id,
            req.recipe_id or "(ours)",
            req.op_type,
            " and start" if req.start else "",
        )
        entity, refusal = self._asking_entity(conv)
        if refusal is not None:
            await self._refuse_now(conv, Msg.SETUP_RUN_ACK, *refusal)
            return
        if not await self._serve_step(conv, Msg.SETUP_RUN_ACK, (S.IDLE,), lambda r: self._setup(r, entity)):
            return
        self._set_up_for = (conv.initiator, req.machine_run_id)
        self.log.info(
            "set up run %d with recipe %s%s", req.machine_run_id, self.recipe_id, ", started" if req.start else ""
        )
        await conv.send(message(Msg.SETUP_RUN_ACK, ack_code=AckCode.ACK_OK, recipe_id=self.recipe_id))

    async def _setup(self, req: Message, entity: int | None) -> tuple[str, str] | None:
        # The reservation (a lot's), the recipe (the one asked for, else the machine's first for the op
        # type), that OP_MACHINE_RECIPE allows it, and its approved version: one read.
        try:
            reserved, recipe, valid, version, checksum = await self._read_when_up(
                "SELECT %(e)s::bigint IS NULL OR EXISTS (SELECT 1 FROM reserved_machines WHERE machine_id = %(m)s "
                "AND machine_run_id = %(run)s AND entity_id = %(e)s), r.recipe, EXISTS (SELECT 1 FROM "
                "op_machine_recipe WHERE machine_id = %(m)s AND recipe_id = r.recipe AND op_type = %(op)s), "
                "v.version, v.checksum FROM (SELECT coalesce(%(r)s::text, (SELECT min(recipe_id) FROM "
                "op_machine_recipe WHERE machine_id = %(m)s AND op_type = %(op)s)) AS recipe) r "
                "LEFT JOIN recipe_versions v ON v.recipe_id = r.recipe AND v.approved",
                {"e": entity, "m": self.machine_id, "run": req.machine_run_id, "r": req.recipe_id, "op": req.op_type},
            ) or (False, None, False, None, None)
        except DatabaseUnavailable:
            raise  # the module answers DB_Badrea: the lot may ask again once the database is back
        except DatabaseError as e:
            return AckCode.DB_BADREA, str(e)
        if not reserved:
            return (
                AckCode.NOT_RESERVED,
                f"run {req.machine_run_id} on {self.machine_id} is not reserved to lot:{entity}",
            )
        if recipe is None:
            return AckCode.REC_INVAL, f"{self.machine_id} has no recipe for op type {req.op_type}"
        if not valid:
            return AckCode.REC_INVAL, f"recipe {recipe} is not for op type {req.op_type} on {self.machine_id}"
        # Listing 3: a machine set up for a run accepts no other operation until the run is over. That and
        # the status Setup are asked now, beside the recipe's setup on the ME, which depends on neither. The
        # lot is not kept waiting for MSCHED's answer to the accept types: while the run is reserved
        # MSCHED binds the machine to nobody else anyway, so what the accepts-nothing protects is the
        # run's end, and the run's Run_Complete waits for it (docs/machine-interface.md 4.1). Both are on
        # the wire before the ME is asked: the Machine Server's change, a durable commit, takes longer
        # than the ME's setup, and the answer to the lot waits for it.
        status = asyncio.ensure_future(
            self.change_status(S.SETUP, expect=[S.IDLE], recipe_id=recipe, machine_run_id=req.machine_run_id)
        )
        accept = asyncio.ensure_future(self.set_accept_types([]))
        await asyncio.sleep(0)  # each sends its request in its first step
        try:
            fetch = self._recipe(recipe, version, checksum)
            if req.sheet is not None:  # the run's offsets after the approved recipe (gwc/quality/sheet.py)
                fetch = with_sheet(fetch, req.sheet, req.machine_run_id)
            refusal = await self._set_up_on_me(recipe, fetch)
        finally:
            set_up = await status
        if refusal is None and not set_up:
            refusal = AckCode.DB_BADUPD, "the Machine Server refused the change to Setup"
        if refusal is not None:
            note = f"setup of run {req.machine_run_id} failed"
            if set_up and not await self.change_status(S.IDLE, expect=[S.SETUP], note=note) and self.status == S.SETUP:
                # Left in Setup: given up by the abandoned-setup watch once the lot has unreserved the run.
                self.machine_run_id, self.recipe_id = req.machine_run_id, recipe
            if await accept and self.status == S.IDLE:  # (not on a machine that went down meanwhile)
                await self.set_accept_types(ALL_OPERATIONS)
            return refusal
        self.machine_run_id, self.recipe_id = req.machine_run_id, recipe
        self._accepting_none = accept
        # A start refused leaves the run set up, as a refused START_RUN does: its lot gives it up.
        return await self._run_on_me(req) if req.start else None

    async def _set_up_on_me(self, recipe_id: str, fetch: Awaitable[tuple[Path | None, str]]) -> tuple[str, str] | None:
        """The approved recipe (`fetch`) to the ME, which sets up with it; the refusal, or None."""
        path, why = await fetch
        if path is None:
            await self.raise_alarm("REC_INVAL", f"{self.machine_id}: recipe {recipe_id} refused: {why}", wait=False)
            return AckCode.REC_INVAL, why
        answer, refusal = await self._ask_me(MeMessage(MessageId.SETUP_RUN, file_name=str(path), recipe_id=recipe_id))
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
            path = self._recipe_file(recipe_id, version)
            with contextlib.suppress(OSError):
                if hashlib.sha256(path.read_bytes()).hexdigest() == checksum:
                    return path, ""
        return await self.fetch_recipe(recipe_id)

    def _recipe_file(self, recipe_id: str, version: int) -> Path:
        return self.recipe_dir / f"{recipe_id}.v{version}"

    async def fetch_recipe(self, recipe_id: str) -> tuple[Path | None, str]:
        """The approved version from the ERS, checksum verified, written where the ME can read it."""
        try:
            reply = await self.ask(
                Conv.RECIPE_GET,
                message(Msg.RECIPE_FETCH, recipe_id=recipe_id, machine_id=self.machine_id),
                "ers",
                SERVER_TIMEOUT,
                within=SERVER_RESTART,
            )
        except ConversationTimeout:
            return None, "the Equipment Recipe Server did not answer"
        if reply.ack_code != AckCode.ACK_OK or reply.content is None:
            return None, reply.note or f"recipe {recipe_id} refused by the ERS ({reply.ack_code})"
        digest = hashlib.sha256(reply.content.encode()).hexdigest()
        if digest != reply.checksum:
            return None, f"recipe {recipe_id} v{reply.version} checksum mismatch: the recipe was modified"
        path = self._recipe_file(recipe_id, reply.version)
        with contextlib.suppress(OSError, UnicodeDecodeError):
            if path.read_text() == reply.content:  # written by an earlier setup, as approved: a read, not a write
                return path, ""
        # Written whole, then renamed: the ME never reads half a recipe. Every fetch runs under the state
        # lock (SETUP_RUN, DNLD_ME), so one temporary name serves.
        tmp = path.with_name(f"{path.name}.tmp")
        try:
            self.recipe_dir.mkdir(parents=True, exist_ok=True)
            tmp.write_text(reply.content)
            tmp.replace(path)
        except OSError as e:
            with contextlib.suppress(OSError):
                tmp.unlink()
            return None, f"recipe {recipe_id} v{reply.version} not written to {path}: {e}"
        return path, ""

    async def start_run(self, conv: Conversation) -> None:
        """6.3.2.4: Setup or Setup_Shut only; the ME starts; Running (or Run_Shut)."""
        assert conv.first is not None
        req = conv.first.first
        self.log.info("START_RUN run %d", req.machine_run_id)
        refusal = await self._not_reserved(conv)
        if refusal is not None:
            await self._refuse_now(conv, Msg.START_RUN_ACK, *refusal)
            return
        if not await self._serve_step(conv, Msg.START_RUN_ACK, (S.SETUP, S.SETUP_SHUT), self._run_on_me):
            return
        self.log.info("run %d started", req.machine_run_id)
        await conv.send(message(Msg.START_RUN_ACK, ack_code=AckCode.ACK_OK))

    async def _run_on_me(self, req: Message) -> tuple[str, str] | None:
        if req.machine_run_id != self.machine_run_id:
            return AckCode.START_FAIL, f"set up for run {self.machine_run_id}, not {req.machine_run_id}"
        results = self._results_path(req.machine_run_id)
        answer, refusal = await self._ask_me(
            MeMessage(MessageId.START_RUN, file_name=str(results), recipe_id=self.recipe_id or "")
        )
        if answer is None:
            return refusal
        if answer.ack_code != AckCode.ACK_OK:
            return AckCode.START_FAIL, f"ME refused to start: {answer.ack_code} {answer.alarm_text}"
        # The status now, not at the check: a shutdown may have come while the ME was starting.
        target = S.RUN_SHUT if self.status == S.SETUP_SHUT else S.RUNNING
        if not await self.change_status(
            target, expect=[self.status], machine_run_id=req.machine_run_id, recipe_id=self.recipe_id
        ):
            return AckCode.DB_BADUPD, f"the Machine Server refused the change to {target}"
        return None

    # ----------------------------------------------------------------- DNLD_ME, UPLD_ME

    async def _not_held(self, conv: Conversation) -> tuple[str, str] | None:
        """DNLD_ME and UPLD_ME's check (Listing 1's ers_download / ers_upload from a lot script): a lot
        entity lot:E may download to and upload from only a machine RESERVED_MACHINES gives to E (any
        of its runs), else Not_Auth; a recipe id must be a recipe id (it names the machine's file)."""
        assert conv.first is not None
        req = conv.first.first
        if not RECIPE_ID.match(req.recipe_id):
            return AckCode.BAD_MESSAGE, f"recipe id {req.recipe_id!r}: letters, digits, _ . - only (64 at most)"
        entity, refusal = self._asking_entity(conv)
        if entity is None:
            return refusal
        try:
            row = await self._read_when_up(
                "SELECT 1 FROM reserved_machines WHERE machine_id = %s AND entity_id = %s LIMIT 1",
                (self.machine_id, entity),
            )
        except DatabaseError as e:
            return AckCode.DB_BADREA, str(e)
        if row is None:
            return AckCode.NOT_AUTH, f"{self.machine_id} is not reserved to lot:{entity}"
        return None

    async def download(self, conv: Conversation) -> None:
        """DNLD_ME (5.1.3): a recipe from the cell to the machine. Idle only."""
        assert conv.first is not None
        req = conv.first.first
        refusal = await self._not_held(conv)
        if refusal is not None:
            return await self._refuse_now(conv, Msg.DOWNLOAD_ACK, *refusal)
        if not await self._serve_step(conv, Msg.DOWNLOAD_ACK, (S.IDLE,), self._download):
            return
        self.log.info("recipe %s downloaded to %s", req.recipe_id, self.machine_id)
        await conv.send(message(Msg.DOWNLOAD_ACK, ack_code=AckCode.ACK_OK))

    async def _download(self, req: Message) -> tuple[str, str] | None:
        path, why = await self.fetch_recipe(req.recipe_id)
        if path is None:
            return AckCode.REC_INVAL, why
        answer, refusal = await self._ask_me(MeMessage(MessageId.DNLD_ME, file_name=str(path), recipe_id=req.recipe_id))
        if answer is None:
            return refusal
        if answer.ack_code != AckCode.ACK_OK:
            return answer.ack_code or AckCode.START_FAIL, f"ME refused the download: {answer.alarm_text}"
        return None

    async def upload(self, conv: Conversation) -> None:
        """UPLD_ME (5.1.3): the machine's recipe back to the cell, stored by the ERS as a new version."""
        assert conv.first is not None
        req = conv.first.first
        refusal = await self._not_held(conv)
        if refusal is not None:
            return await self._refuse_now(conv, Msg.UPLOAD_ACK, *refusal)
        async with self._state_lock:
            refusal = self._check(req, (S.IDLE,))
            content: str | None = None
            if refusal is None:
                refusal, content = await self._upload(req)
        if refusal is not None:
            return await self._refuse_now(conv, Msg.UPLOAD_ACK, *refusal)
        assert content is not None
        try:
            stored = await self.ask(
                Conv.RECIPE_PUT,
                message(
                    Msg.RECIPE_STORE,
                    recipe_id=req.recipe_id,
                    content=content,
                    by=conv.initiator if conv.initiator.startswith("lot:") else self.name,
                    description=None,
                ),
                "ers",
                SERVER_TIMEOUT,
            )
        except ConversationTimeout:
            return await self._refuse_now(
                conv, Msg.UPLOAD_ACK, AckCode.TIMEOUT, "the Equipment Recipe Server did not answer"
            )
        self.log.info(
            "recipe %s uploaded from %s: ERS says %s, version %s",
            req.recipe_id,
            self.machine_id,
            stored.ack_code,
            stored.version,
        )
        await conv.send(message(Msg.UPLOAD_ACK, ack_code=stored.ack_code, version=stored.version, note=stored.note))

    async def _upload(self, req: Message) -> tuple[tuple[str, str] | None, str | None]:
        answer, refusal = await self._ask_me(MeMessage(MessageId.UPLD_ME, recipe_id=req.recipe_id))
        if answer is None:
            return refusal, None
        if answer.ack_code != AckCode.ACK_OK or not answer.file_name:
            return (answer.ack_code or AckCode.START_FAIL, f"the ME returned no recipe: {answer.alarm_text}"), None
        try:
            return None, Path(answer.file_name).read_text()
        except (OSError, UnicodeDecodeError) as e:
            return (AckCode.REC_INVAL, f"the ME's recipe file {answer.file_name} is unreadable: {e}"), None
