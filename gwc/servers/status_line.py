"""The Status Line Server (thesis 7.4): the one line every operator screen shows.

The line says what waits for the operator: lot entities waiting to be imported or exported (the
Lot Server's LOT_STATUS), pending alarms (the Cell Alarm Server's ALARMS), and the last cell event
heard on the bus (a Cell_Event, a machine status change, an alarm cleared, a lot moved, a run
completed). The counts are read from the owners' tables at every STATUS_LN, so the line is never
stale; the server writes nothing (role gwc_sls reads only) and keeps only the last event in memory.
While the database is away the line says so (DATABASE DOWN), with the last event heard.
"""

from __future__ import annotations

import logging
import time

from gwc.config import Config
from gwc.errors import DatabaseUnavailable
from gwc.ipc.bus import Conversation
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.module import Handler, Module
from gwc.servers import status_line_store
from gwc.servers.common import NOT_LOTS, Server

SHOW = 5  # entity ids named on the line before "..."


def _ids(ids: list[int]) -> str:
    return ", ".join(map(str, ids[:SHOW])) + (", ..." if len(ids) > SHOW else "")


def _describe(cls: str, msg: Message) -> str:
    """A bus event in the words of the status line."""
    if cls == Conv.UPD_ME_ST:
        return f"{msg.machine_id} {msg.previous or '?'} -> {msg.status}" + (f" ({msg.note})" if msg.note else "")
    if cls == Conv.ALARM_CLE:
        return f"alarm {msg.alarm_no} {msg.alarm_id or ''} cleared by {msg.cleared_by}".replace("  ", " ")
    if cls == Conv.LOT_MOVED:
        return f"entity {msg.entity_id} (lot {msg.lot_id}) {msg.action}ed"
    if cls == Conv.RUN_COMPL:
        return f"{msg.machine_id} run {msg.machine_run_id} " + (
            "complete" if msg.ack_code == AckCode.ACK_OK else f"failed ({msg.ack_code})"
        )
    return str(msg.text)


def line(w: status_line_store.Waiting, last_event: str) -> str:
    """The status line's text: what waits, then the last event heard."""
    parts = []
    if w.imports:
        parts.append(f"IMPORT {len(w.imports)} waiting ({_ids(w.imports)})")
    if w.exports:
        parts.append(f"EXPORT {len(w.exports)} waiting ({_ids(w.exports)})")
    if w.newest is not None:
        a = w.newest
        parts.append(f"ALARMS {w.alarms} pending, newest #{a.alarm_no}{'' if a.known else ' (unknown)'}: {a.text}")
    parts.append(f"LAST {last_event}")
    return " | ".join(parts)[:500]


class StatusLineServer(Server, Module):
    role = "sls"
    ignored_peers = NOT_LOTS

    def __init__(self, cfg: Config, name: str, log: logging.Logger) -> None:
        super().__init__(cfg, name, log)
        self.last_event = "status line server started"

    def handlers(self) -> dict[str, Handler]:
        heard = (Conv.CELL_EVENT, Conv.UPD_ME_ST, Conv.ALARM_CLE, Conv.LOT_MOVED, Conv.RUN_COMPL)
        events: dict[str, Handler] = dict.fromkeys(heard, self.heard)
        return {Conv.STATUS_LN: self.status_line, **events}

    def refusal(self, cls: str, req: Message, code: str, note: str) -> Message | None:
        if cls == Conv.STATUS_LN:
            return message(Msg.STATUS_LINE, text=f"status line unavailable: {code} {note}"[:500])
        return None

    async def heard(self, conv: Conversation) -> None:
        self.last_event = f"{time.strftime('%H:%M:%S')} {_describe(conv.cls, self.request(conv))}"[:200]

    async def status_line(self, conv: Conversation) -> None:
        """STATUS_LN: the line, from the owners' tables now; while the database is away, DATABASE DOWN."""
        try:
            w = self.transaction(status_line_store.waiting)
        except DatabaseUnavailable:
            assert self.database.down is not None
            away = time.monotonic() - self.database.down
            text = f"DATABASE DOWN for {away:.0f}s: imports, exports and alarms unknown | LAST {self.last_event}"
            await conv.send(message(Msg.STATUS_LINE, text=text[:500], last_event=self.last_event))
            return
        await conv.send(
            message(
                Msg.STATUS_LINE,
                text=line(w, self.last_event),
                imports=len(w.imports),
                exports=len(w.exports),
                alarms=w.alarms,
                last_event=self.last_event,
            )
        )
