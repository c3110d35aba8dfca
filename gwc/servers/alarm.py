"""The Cell Alarm Server (thesis 1.4.5, 6.3.2.8): the one writer of the ALARMS history.

An alarm (ALARM_SEND) is checked against ALARM_DESCRIPTION, numbered (ALARM_NO), recorded with who
raised it and when, and is pending until the operator clears it. An alarm the description table
does not know is recorded and shown all the same, marked unknown: losing an alarm because its id
was misspelt would be worse. Every new alarm is handed to the Status Line Server (a Cell_Event).

The operator clears one (ALARM_CLR_REQ): the history gets who and when, and ALARM_CLEAR is
broadcast so the WC that waits on it (6.3.2.8) continues.

1.4.5's last function, "taking the appropriate actions necessary for the given alarm": each alarm's
description (ALARM_DESCRIPTION.actions, set with `gwc alarm describe`) says what the CAS does as it
records one: `shutdown` (ME_SHUT to the alarm's machine: a machine in a run shuts down when the run
is over) and `page` (the operator paged: a cell event, and `[alarms] page_command` run with the
alarm's text when cell.toml names one). What was done is logged and kept in ALARMS.actions_taken.

The CAS also watches the database itself (every module notices an outage within a second): one
that lasts longer than `[database] outage_alarm_s` is told as a cell event while it lasts, and
recorded as alarm DB_DOWN as soon as the database is back, since an alarm cannot be written before.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time

from gwc.config import Config
from gwc.errors import GwcError, Refused
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import DATABASE_OUTAGE_S, Handler, Module
from gwc.servers import alarm_store
from gwc.servers.common import NOT_LOTS, SERVER_TIMEOUT, Server

ACTIONS = ("shutdown", "page")  # what an alarm's description may ask of the CAS (060_thesis.sql)
SEVERITIES = ("note", "warning", "error")
PAGE_TIMEOUT = 10.0  # s: the longest a page command may take before it is killed
OUTAGE_ALARM = "DB_DOWN"
OUTAGE_ALARM_S = 10.0  # a database away longer than this is an alarm ([database] outage_alarm_s)


LOT_ALARMS = ("SPC_RULE", "TOOL_CHANGE")  # what a lot script may raise (gwc/quality/lot.py)


class AlarmServer(Server, Module):
    role = "cas"
    ignored_peers = NOT_LOTS

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        super().__init__(cfg, name, log)
        self.outage_alarm_s = float(cfg.raw.get("database", {}).get("outage_alarm_s", OUTAGE_ALARM_S))
        self._outage_told = False
        page = cfg.raw.get("alarms", {}).get("page_command")
        self.page_command: list[str] = [page] if isinstance(page, str) else [str(a) for a in page or []]

    def handlers(self) -> dict[str, Handler]:
        return {
            Conv.ALARM_SEND: self.alarm_send,
            Conv.ALARM_CLR_REQ: self.alarm_clear,
            Conv.ALARM_DESC: self.alarm_describe,
        }

    async def on_startup(self) -> str:
        n = self.transaction(alarm_store.pending())
        self.log.info("%d alarm(s) pending from before", n)
        return AckCode.ACK_OK

    async def alarm_send(self, conv: Conversation) -> None:
        """ALARM_SEND: record the alarm (known or not), answer its number, tell the status line."""
        req = self.request(conv)
        if not req.alarm_id.strip() or not req.raised_by.strip():
            raise Refused(AckCode.BAD_MESSAGE, "alarm_id and raised_by must be given")
        if conv.initiator.startswith("lot:") and (req.alarm_id not in LOT_ALARMS or req.raised_by != conv.initiator):
            # A lot script raises quality's alarms only, in its own name (docs/quality.md).
            raise Refused(AckCode.NOT_AUTH, f"a lot raises only {', '.join(LOT_ALARMS)}, in its own name")

        no, known = await self.record(req.alarm_id, req.alarm_text, req.machine_id, req.raised_by)
        await self.answer(conv, Msg.ALARM_ACK, AckCode.ACK_OK, alarm_no=no, known=known)

    async def record(self, alarm_id: str, text: str | None, machine_id: str | None, raised_by: str) -> tuple[int, bool]:
        """Record an alarm (known or not) and tell the status line; its number, and whether it is known."""

        got = self.transaction(lambda cur: alarm_store.record(cur, alarm_id, text, machine_id, raised_by))
        no, known, full = got.alarm_no, got.known, got.text
        if known:
            self.log.info("alarm %d %s from %s pending: %s", no, alarm_id, raised_by, full)
        else:
            self.log.warning("alarm %d %s from %s is not in ALARM_DESCRIPTION: %s", no, alarm_id, raised_by, full)
        await self.event(f"alarm {no} {alarm_id}{'' if known else ' (unknown)'}: {full}")
        if got.actions:  # after the answer: the raiser (a WC in a step) is not held up by a shutdown
            self.spawn(self.act(no, alarm_id, machine_id, full, list(got.actions)))
        return no, known

    # ----------------------------------------------------------------- the alarm's actions (1.4.5)

    async def act(self, no: int, alarm_id: str, machine_id: str | None, text: str, actions: list[str]) -> None:
        """Do what the alarm's description asks, in its order; each outcome logged, all kept in ALARMS."""
        done = []
        for action in actions:
            if action == "shutdown":
                outcome = await self._shut_down(machine_id)
            elif action == "page":
                outcome = await self._page(no, alarm_id, machine_id, text)
            else:  # the table's check allows no other; a newer schema might
                outcome = f"{action}: not an action this CAS knows"
            self.log.warning("alarm %d %s: %s", no, alarm_id, outcome)
            done.append(outcome)
        taken = "; ".join(done)
        await self.transaction_when_up(alarm_store.actions_taken(no, taken), within=DATABASE_OUTAGE_S)

    async def _shut_down(self, machine_id: str | None) -> str:
        """ME_SHUT to the machine's WC, as `gwc machine stop` does."""
        if not machine_id:
            return "shutdown: the alarm names no machine"
        wc = f"wc:{machine_id}"
        try:
            conv, batch = await self.bus.request(
                Conv.ME_SHUT, message(Msg.SHUTDOWN_REQUEST, module=wc), to=wc, timeout=SERVER_TIMEOUT
            )
        except GwcError as e:
            return f"shutdown of {machine_id} not done: {e}"
        try:
            ack = batch.first
            if ack.ack_code == AckCode.NOTNOW:
                return f"shutdown of {machine_id}: it is shut down already"
            if ack.ack_code != AckCode.ACK_OK:
                return f"shutdown of {machine_id} refused: {ack.ack_code} {ack.note or ''}".strip()
            with contextlib.suppress(GwcError):  # pending: the run ends first (its note says so)
                done = (await conv.expect(Msg.SHUTDOWN_COMPLETE, Msg.ME_STOPPED, timeout=SERVER_TIMEOUT)).first
                return f"machine {machine_id} shut down" + (f" ({done.note})" if done.note else "")
            return f"machine {machine_id} shutting down" + (f" ({ack.note})" if ack.note else "")
        finally:
            conv.end()

    async def _page(self, no: int, alarm_id: str, machine_id: str | None, text: str) -> str:
        """Page the operator: a cell event on every screen, and the page command if cell.toml names one."""
        await self.event(f"PAGE: alarm {no} {alarm_id}" + (f" on {machine_id}" if machine_id else "") + f": {text}")
        if not self.page_command:
            return "paged on the status line"
        env = {
            **os.environ,
            "GWC_ALARM_NO": str(no),
            "GWC_ALARM_ID": alarm_id,
            "GWC_MACHINE": machine_id or "",
        }
        try:
            proc = await asyncio.create_subprocess_exec(
                *self.page_command, text, env=env, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE
            )
        except OSError as e:
            return f"paged on the status line; page command {self.page_command[0]} not run: {e}"
        try:
            _, err = await asyncio.wait_for(proc.communicate(), PAGE_TIMEOUT)
        except TimeoutError:
            proc.kill()
            await proc.wait()
            return f"paged on the status line; page command killed after {PAGE_TIMEOUT:g}s"
        if proc.returncode != 0:
            why = err.decode(errors="replace").strip()[-200:]
            return f"paged on the status line; page command exit {proc.returncode}: {why}"
        return "paged (status line and page command)"

    async def alarm_describe(self, conv: Conversation) -> None:
        """ALARM_DESC: the operator adds or changes an alarm's description: text, severity, actions."""
        req = self.request(conv)
        actions = None if req.actions is None else [str(a) for a in req.actions]
        wrong = [a for a in actions or [] if a not in ACTIONS]
        if not req.alarm_id.strip() or wrong or (req.severity is not None and req.severity not in SEVERITIES):
            why = f"unknown action(s) {', '.join(wrong)} (known: {', '.join(ACTIONS)})" if wrong else ""
            why = why or f"an alarm id, and a severity of {', '.join(SEVERITIES)}"
            raise Refused(AckCode.BAD_MESSAGE, why)
        got = self.transaction(alarm_store.describe(req.alarm_id, req.alarm_text, req.severity, actions))
        now = f"{got.alarm_text!r}, {got.severity}, actions {','.join(got.actions) or 'none'}"
        self.log.info("alarm %s described by %s: %s", req.alarm_id, req.by or conv.peer, now)
        await self.answer(conv, Msg.ALARM_CLEAR_ACK, AckCode.ACK_OK, now)

    # ----------------------------------------------------------------- the database's own outages

    async def on_idle(self) -> None:
        """A database away past the bound is told at once as a cell event (the alarm waits for it)."""
        if self.started and self.database.down is not None and not self._outage_told:
            away = time.monotonic() - self.database.down
            if away >= self.outage_alarm_s:
                self._outage_told = True
                self.log.error("the cell database has been away for %.0fs", away)
                await self.event(f"DATABASE DOWN for {away:.0f}s: alarm {OUTAGE_ALARM} follows when it is back")

    async def on_database_back(self, down_for: float) -> None:
        """An outage past the bound becomes alarm DB_DOWN, written now that it can be."""
        self._outage_told = False
        if down_for < self.outage_alarm_s:
            return
        since = time.strftime("%H:%M:%S", time.localtime(time.time() - down_for))
        text = f"the cell database was away for {down_for:.0f}s (from {since}; bound {self.outage_alarm_s:g}s)"
        await self.record(OUTAGE_ALARM, text, None, self.name)

    async def alarm_clear(self, conv: Conversation) -> None:
        """ALARM_CLR_REQ: the operator clears a pending alarm; ALARM_CLEAR tells whoever waits on it."""
        req = self.request(conv)
        if not req.cleared_by.strip():
            raise Refused(AckCode.BAD_MESSAGE, "cleared_by must be given")
        cleared = self.transaction(lambda cur: alarm_store.clear(cur, req.alarm_no, req.cleared_by))
        alarm_id = cleared.alarm_id
        self.log.info("alarm %d %s cleared by %s", req.alarm_no, alarm_id, req.cleared_by)
        await self.answer(conv, Msg.ALARM_CLEAR_ACK, AckCode.ACK_OK)
        await self.broadcast(
            Conv.ALARM_CLE,
            message(
                Msg.ALARM_CLEAR,
                alarm_no=req.alarm_no,
                alarm_id=alarm_id,
                machine_id=cleared.machine_id,
                cleared_by=req.cleared_by,
            ),
        )
        await self.event(f"alarm {req.alarm_no} {alarm_id} cleared by {req.cleared_by}")
