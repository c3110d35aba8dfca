"""The Cell Alarm Server (thesis 1.4.5, 6.3.2.8): the one writer of the ALARMS history.

An alarm (ALARM_SEND) is checked against ALARM_DESCRIPTION, numbered (ALARM_NO), recorded with who
raised it and when, and is pending until the operator clears it. An alarm the description table
does not know is recorded and shown all the same, marked unknown: losing an alarm because its id
was misspelt would be worse. Every new alarm is handed to the Status Line Server (a Cell_Event).

The operator clears one (ALARM_CLR_REQ): the history gets who and when, and ALARM_CLEAR is
broadcast so the WC that waits on it (6.3.2.8) continues.

The CAS also watches the database itself (every module notices an outage within a second): one
that lasts longer than `[database] outage_alarm_s` is told as a cell event while it lasts, and
recorded as alarm DB_DOWN as soon as the database is back, since an alarm cannot be written before.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from gwc import db
from gwc.config import Config
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import Handler, Module
from gwc.servers.common import NOT_LOTS, Server

OUTAGE_ALARM = "DB_DOWN"
OUTAGE_ALARM_S = 10.0  # a database away longer than this is an alarm ([database] outage_alarm_s)


class AlarmServer(Server, Module):
    role = "cas"
    ignored_peers = NOT_LOTS

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        super().__init__(cfg, name, log)
        self.outage_alarm_s = float(cfg.raw.get("database", {}).get("outage_alarm_s", OUTAGE_ALARM_S))
        self._outage_told = False

    def handlers(self) -> dict[str, Handler]:
        return {Conv.ALARM_SEND: self.alarm_send, Conv.ALARM_CLR_REQ: self.alarm_clear}

    async def on_startup(self) -> str:
        def pending(cur: Any) -> int:
            return int(cur.execute("select count(*) from alarms where cleared_at is null").fetchone()[0])

        n = self.transaction(pending)
        self.log.info("%d alarm(s) pending from before", n)
        return AckCode.ACK_OK

    async def alarm_send(self, conv: Conversation) -> None:
        """ALARM_SEND: record the alarm (known or not), answer its number, tell the status line."""
        req = self.request(conv)
        if not req.alarm_id.strip() or not req.raised_by.strip():
            return await self.answer(conv, Msg.ALARM_ACK, AckCode.BAD_MESSAGE, "alarm_id and raised_by must be given")

        no, known = await self.record(req.alarm_id, req.alarm_text, req.machine_id, req.raised_by)
        await self.answer(conv, Msg.ALARM_ACK, AckCode.ACK_OK, alarm_no=no, known=known)

    async def record(self, alarm_id: str, text: str | None, machine_id: str | None, raised_by: str) -> tuple[int, bool]:
        """Record an alarm (known or not) and tell the status line; its number, and whether it is known."""

        def insert(cur: Any) -> tuple[int, bool, str]:
            row = cur.execute("select alarm_text from alarm_description where alarm_id = %s", (alarm_id,)).fetchone()
            known = row is not None
            full = text or (row[0] if known else f"unknown alarm {alarm_id}")
            no = db.get_new_max_value(cur, "ALARM_NO")
            cur.execute(
                "insert into alarms (alarm_no, alarm_id, known, machine_id, alarm_text, raised_by) "
                "values (%s, %s, %s, %s, %s, %s)",
                (no, alarm_id, known, machine_id, full, raised_by),
            )
            return no, known, full

        no, known, full = self.transaction(insert)
        if known:
            self.log.info("alarm %d %s from %s pending: %s", no, alarm_id, raised_by, full)
        else:
            self.log.warning("alarm %d %s from %s is not in ALARM_DESCRIPTION: %s", no, alarm_id, raised_by, full)
        await self.event(f"alarm {no} {alarm_id}{'' if known else ' (unknown)'}: {full}")
        return no, known

    # ----------------------------------------------------------------- the database's own outages

    async def on_idle(self) -> None:
        """A database away past the bound is told at once as a cell event (the alarm waits for it)."""
        if self.started and self.database_down is not None and not self._outage_told:
            away = time.monotonic() - self.database_down
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
            return await self.answer(conv, Msg.ALARM_CLEAR_ACK, AckCode.BAD_MESSAGE, "cleared_by must be given")

        def clear(cur: Any) -> tuple[Any, ...] | None:
            row = cur.execute(
                "select alarm_id, machine_id, cleared_by, cleared_at from alarms where alarm_no = %s for update",
                (req.alarm_no,),
            ).fetchone()
            if row is None or row[3] is not None:
                return row
            cur.execute(
                "update alarms set cleared_by = %s, cleared_at = now() where alarm_no = %s",
                (req.cleared_by, req.alarm_no),
            )
            return row

        row = self.transaction(clear)
        if row is None:
            return await self.answer(conv, Msg.ALARM_CLEAR_ACK, AckCode.UNKNOWN, f"no alarm number {req.alarm_no}")
        alarm_id, machine_id, by, at = row
        if at is not None:
            return await self.answer(
                conv,
                Msg.ALARM_CLEAR_ACK,
                AckCode.NOTNOW,
                f"alarm {req.alarm_no} was already cleared by {by} at {at:%Y-%m-%d %H:%M:%S}",
            )
        self.log.info("alarm %d %s cleared by %s", req.alarm_no, alarm_id, req.cleared_by)
        await self.answer(conv, Msg.ALARM_CLEAR_ACK, AckCode.ACK_OK)
        await self.broadcast(
            Conv.ALARM_CLE,
            message(
                Msg.ALARM_CLEAR,
                alarm_no=req.alarm_no,
                alarm_id=alarm_id,
                machine_id=machine_id,
                cleared_by=req.cleared_by,
            ),
        )
        await self.event(f"alarm {req.alarm_no} {alarm_id} cleared by {req.cleared_by}")
