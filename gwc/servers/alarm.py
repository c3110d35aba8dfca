"""The Cell Alarm Server (thesis 1.4.5, 6.3.2.8): the one writer of the ALARMS history.

An alarm (ALARM_SEND) is checked against ALARM_DESCRIPTION, numbered (ALARM_NO), recorded with who
raised it and when, and is pending until the operator clears it. An alarm the description table
does not know is recorded and shown all the same, marked unknown: losing an alarm because its id
was misspelt would be worse. Every new alarm is handed to the Status Line Server (a Cell_Event).

The operator clears one (ALARM_CLR_REQ): the history gets who and when, and ALARM_CLEAR is
broadcast so the WC that waits on it (6.3.2.8) continues.
"""

from __future__ import annotations

from typing import Any

from gwc import db
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.module import Handler, Module
from gwc.servers.common import Server


class AlarmServer(Server, Module):
    role = "cas"

    def handlers(self) -> dict[str, Handler]:
        return {"ALARM_SEND": self.alarm_send, "ALARM_CLR_REQ": self.alarm_clear}

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
            return await self.answer(conv, "Alarm_Ack", AckCode.BAD_MESSAGE, "alarm_id and raised_by must be given")

        def record(cur: Any) -> tuple[int, bool, str]:
            row = cur.execute(
                "select alarm_text from alarm_description where alarm_id = %s", (req.alarm_id,)
            ).fetchone()
            known = row is not None
            text = req.alarm_text or (row[0] if known else f"unknown alarm {req.alarm_id}")
            no = db.get_new_max_value(cur, "ALARM_NO")
            cur.execute(
                "insert into alarms (alarm_no, alarm_id, known, machine_id, alarm_text, raised_by) "
                "values (%s, %s, %s, %s, %s, %s)",
                (no, req.alarm_id, known, req.machine_id, text, req.raised_by),
            )
            return no, known, text

        no, known, text = self.transaction(record)
        if known:
            self.log.info("alarm %d %s from %s pending: %s", no, req.alarm_id, req.raised_by, text)
        else:
            self.log.warning(
                "alarm %d %s from %s is not in ALARM_DESCRIPTION: recorded as unknown: %s",
                no,
                req.alarm_id,
                req.raised_by,
                text,
            )
        await self.answer(conv, "Alarm_Ack", AckCode.ACK_OK, alarm_no=no, known=known)
        await self.event(f"alarm {no} {req.alarm_id}{'' if known else ' (unknown)'}: {text}")

    async def alarm_clear(self, conv: Conversation) -> None:
        """ALARM_CLR_REQ: the operator clears a pending alarm; ALARM_CLEAR tells whoever waits on it."""
        req = self.request(conv)
        if not req.cleared_by.strip():
            return await self.answer(conv, "Alarm_Clear_Ack", AckCode.BAD_MESSAGE, "cleared_by must be given")

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
            return await self.answer(conv, "Alarm_Clear_Ack", AckCode.UNKNOWN, f"no alarm number {req.alarm_no}")
        alarm_id, machine_id, by, at = row
        if at is not None:
            return await self.answer(
                conv,
                "Alarm_Clear_Ack",
                AckCode.NOTNOW,
                f"alarm {req.alarm_no} was already cleared by {by} at {at:%Y-%m-%d %H:%M:%S}",
            )
        self.log.info("alarm %d %s cleared by %s", req.alarm_no, alarm_id, req.cleared_by)
        await self.answer(conv, "Alarm_Clear_Ack", AckCode.ACK_OK)
        await self.broadcast(
            "ALARM_CLE",
            message(
                "Alarm_Clear",
                alarm_no=req.alarm_no,
                alarm_id=alarm_id,
                machine_id=machine_id,
                cleared_by=req.cleared_by,
            ),
        )
        await self.event(f"alarm {req.alarm_no} {alarm_id} cleared by {req.cleared_by}")
