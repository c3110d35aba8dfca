"""The production record in the OPC UA address space (docs/record.md, docs/opcua.md): each machine's
OEE figures since midnight and its open downtime with its reason, in a `Monitoring` object (where OPC
40001-1 Machinery puts a machine's monitored values), and a `SetDowntimeReason` method.

Self-contained, so the gateway only calls `build` for each machine and `refresh` when it re-reads the
machines: the figures are read from the record's store (gwc.record.store) at most every REFRESH_S.
"""

from __future__ import annotations

import time
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from asyncua import ua

from gwc.client.record import parse_when
from gwc.ipc.catalogue import message
from gwc.ipc.names import Conv, Msg
from gwc.record import store

if TYPE_CHECKING:
    from gwc.opcua.gateway import Gateway

V = ua.VariantType
REFRESH_S = 2.0  # the figures are computed at most this often (each is a few reads per machine)
MONITORING = {
    "Availability": V.Double,
    "Performance": V.Double,
    "Quality": V.Double,
    "OEE": V.Double,
    "Parts": V.Int64,
    "GoodParts": V.Int64,
    "Since": V.DateTime,
    "DowntimeOpen": V.Boolean,
    "DowntimeEventId": V.Int64,
    "DowntimeCause": V.String,
    "DowntimeReason": V.String,
    "DowntimeE10State": V.String,
}
_last: dict[int, float] = {}  # id(gateway) -> when its figures were last computed


async def build(gw: Gateway, node: ua.NodeId, machine_id: str, out: list[tuple[str, ua.VariantType, str]]) -> None:
    """One machine's Monitoring object and its SetDowntimeReason method."""
    sp = gw.space
    assert sp is not None
    path = f"machines/{machine_id}"
    await sp.object(node, f"{path}/Monitoring", "Monitoring", MONITORING)
    await sp.set(f"{path}/Monitoring/DowntimeOpen", False)

    async def set_reason(reason: str) -> ua.CallMethodResult:
        first = message(Msg.DOWNTIME_REASON, machine_id=machine_id, reason=reason, by=gw.methods.by)
        return await gw.methods.converse(
            f"SetDowntimeReason({machine_id}, {reason})", lambda: gw.methods.ask(Conv.DOWNTIME_RSN, first, "ms")
        )

    await sp.method(
        node,
        f"{path}/SetDowntimeReason",
        "SetDowntimeReason",
        set_reason,
        [("reason", V.String, "the open downtime's reason, one of cell.toml's reason tree (gwc downtime reasons)")],
        out,
    )


async def refresh(gw: Gateway, force: bool = False) -> None:
    """Each machine's figures since midnight and its open downtime, written where they changed."""
    now = time.monotonic()
    if not force and now - _last.get(id(gw), 0.0) < REFRESH_S:
        return
    _last[id(gw)] = now
    rec = gw.cfg.record
    until = datetime.now(UTC)
    since = parse_when("today", rec.timezone, until)

    def read(cur: Any) -> tuple[dict[str, Any], list[store.DowntimeEvent]]:
        conn = cur.connection
        return store.oee(conn, rec, since, until, gw.machine_ids), store.downtime_events(conn, open_only=True)

    rep, events = await gw._read(read)
    sp = gw.space
    assert sp is not None
    open_of = {e.machine_id: e for e in events}
    for m in rep["machines"]:
        path = f"machines/{m['machine_id']}/Monitoring"
        ev = open_of.get(m["machine_id"])
        await sp.set_all(
            path,
            {
                "Availability": m["availability"],
                "Performance": m["performance"],
                "Quality": m["quality"],
                "OEE": m["oee"],
                "Parts": m["parts"],
                "GoodParts": m["good_parts"],
                "Since": since,
                "DowntimeOpen": ev is not None,
                "DowntimeEventId": ev.event_id if ev else None,
                "DowntimeCause": ev.cause if ev else None,
                "DowntimeReason": ev.reason if ev else None,
                "DowntimeE10State": ev.e10_state if ev else None,
            },
            MONITORING,
        )
