"""The OPC UA gateway (issue 19) against a real cell, with asyncua's own client, as an MES would use it.

The gateway (`gwc run opcua`) and every server, WC, ME and the CMM simulator are real processes on
a private bus and database. The client runs in the test's event loop; what the test does as the
operator (`gwc ...`, waiting on the tables) runs in threads, so notifications are timed as they come.
"""

from __future__ import annotations

import asyncio
import json
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Node, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID

from gwc.config import write_config
from gwc.ipc.bus import BlockingBus
from gwc.opcua.security import hash_password
from tests.e2e.lotkit import cell_with_machines, gwc, ok, order, stop_lot_scripts
from tests.harness import CellHarness, wait_for

pytestmark = pytest.mark.e2e

NS = "urn:gwc:cell"
USER, PASSWORD = "operator", "cell-secret"
CMM = {
    "id": "cmm_wc",
    "kind": "cmm",
    "serial": {"port": "sim", "baudrate": 9600, "timeout": 5.0},
    "sim": {"measure_time": 0.3, "pattern": "P"},
}
WC1 = {"id": "wc1", "kind": "dummy", "run_time": 0.2}
LATENCY = 0.5  # from a status change on the bus to the subscriber's notification
# asyncua's client drops a connection whose server misses its 1 s probe; on a shared, loaded machine
# the test's clients allow 5 s (the gateway's own answers are held to well under 1 s: gateway.py).
WATCHDOG = 5.0
STARTUP = 60.0  # the gateway's start: asyncua builds its standard address space (2 s alone, 15 s on a loaded machine)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def with_gateway(cell: CellHarness) -> str:
    """Add an [opcua] section to the cell's configuration (a free port, one user); the endpoint."""
    endpoint = f"opc.tcp://127.0.0.1:{free_port()}/gwc/"
    raw = dict(cell.cfg.raw)
    users = {USER: hash_password(PASSWORD)}  # kept as a salted hash, never in clear
    raw["opcua"] = {"endpoint": endpoint, "anonymous": True, "users": users, "refresh": 1.0}
    cell.cfg = write_config(cell.cfg.path, raw)
    return endpoint


class Recorder:
    """asyncua subscription handler: every data change and event, with the monotonic time it came."""

    def __init__(self) -> None:
        self.changes: list[tuple[float, str, Any]] = []
        self.events: list[tuple[float, Any]] = []

    def datachange_notification(self, node: Node, val: Any, data: Any) -> None:
        self.changes.append((time.monotonic(), node.nodeid.to_string(), val))

    def event_notification(self, event: Any) -> None:
        self.events.append((time.monotonic(), event))

    def values(self, nodeid: ua.NodeId) -> list[Any]:
        return [v for _, n, v in self.changes if n == nodeid.to_string()]


class StatusEar:
    """The bus's UPD_ME_ST broadcasts as they come (a thread of the test's own): when each change was."""

    def __init__(self, cell: CellHarness) -> None:
        self.bus = BlockingBus(f"ear.{cell.tag}", cell.cfg.bus, cell.log, ("UPD_ME_ST",))
        self.heard: list[tuple[float, str, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, daemon=True)
        self._thread.start()

    def _listen(self) -> None:
        while not self._stop.is_set():
            conv = self.bus.first_message(timeout=0.2)
            if conv is not None and conv.first is not None:
                m = conv.first.first
                self.heard.append((time.monotonic(), m.machine_id, m.status))
                conv.end()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.bus.close()


async def until(predicate: Callable[[], Any], timeout: float, what: str) -> Any:
    """wait_for, without blocking the client's event loop."""
    return await asyncio.to_thread(wait_for, predicate, timeout, what)


async def read_until(node: Node, want: Any, timeout: float = 10.0) -> None:
    """Poll a node until it reads `want`; fail naming the node after the deadline."""
    deadline = time.monotonic() + timeout
    while (value := await node.read_value()) != want:
        assert time.monotonic() < deadline, f"{node.nodeid.to_string()} is {value!r}, not {want!r}"
        await asyncio.sleep(0.05)


async def secure_client(endpoint: str, certs: Path, user: str | None = USER) -> Client:
    """A client on a Basic256Sha256 SignAndEncrypt channel, with its own certificate made here."""
    cert, key = certs / "client-cert.der", certs / "client-key.pem"
    await setup_self_signed_certificate(
        key, cert, "urn:gwc:test:client", "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "test"}
    )
    client = Client(endpoint, timeout=30, watchdog_intervall=WATCHDOG)
    client.application_uri = "urn:gwc:test:client"
    await client.set_security(
        SecurityPolicyBasic256Sha256, str(cert), str(key), mode=ua.MessageSecurityMode.SignAndEncrypt
    )
    if user:
        client.set_user(user)
        client.set_password(PASSWORD)
    await client.connect()
    return client


@pytest.fixture
def opcua_cell(lot_cell: Any) -> Any:
    """A cell with every server, the machines given (processes up, Shutdown) and the gateway started."""
    ears: list[StatusEar] = []

    def make(*machines: dict[str, Any]) -> tuple[CellHarness, str, StatusEar]:
        cell = lot_cell(machines=list(machines))
        endpoint = with_gateway(cell)
        ears.append(StatusEar(cell))
        cell_with_machines(cell)
        cell.start("opcua", timeout=STARTUP)
        return cell, endpoint, ears[-1]

    yield make
    for e in ears:
        e.close()


def test_a_client_sees_machines_lots_and_alarms_live_and_commands_the_cell(opcua_cell: Any, tmp_path: Path) -> None:
    cell, endpoint, ear = opcua_cell(CMM, WC1)

    async def main() -> None:
        anonymous = Client(
            endpoint, timeout=30, watchdog_intervall=WATCHDOG, auto_reconnect=True, reconnect_max_delay=1.0
        )
        await anonymous.connect()
        unencrypted = Client(endpoint, timeout=30, watchdog_intervall=WATCHDOG)
        unencrypted.set_user(USER)
        unencrypted.set_password(PASSWORD)
        await unencrypted.connect()
        operator = await secure_client(endpoint, tmp_path)
        try:
            ns = await anonymous.get_namespace_index(NS)
            node = lambda path: anonymous.get_node(ua.NodeId(path, ns))
            call = lambda client, obj, method, *args: client.get_node(ua.NodeId(obj, ns)).call_method(
                ua.NodeId(f"{obj}/{method}" if obj.startswith("machines/") else f"cell/{method}", ns), *args
            )

            # Browse finds every configured machine, each with its identification and states.
            machines = await node("machines").get_children()
            assert sorted([(await m.read_browse_name()).Name for m in machines]) == ["cmm_wc", "wc1"]
            assert await node("machines/cmm_wc/Identification/Model").read_value() == "cmm"
            assert await node("machines/cmm_wc/status").read_value() == "Shutdown"

            rec = Recorder()
            sub = await anonymous.create_subscription(20, rec)
            status, wc1 = node("machines/cmm_wc/status"), node("machines/wc1/status")
            await sub.subscribe_data_change(
                [status, wc1, node("machines/cmm_wc/MachineryItemState/CurrentState")], queuesize=20
            )
            await sub.subscribe_events(anonymous.nodes.server, ua.ObjectIds.AlarmConditionType, queuesize=20)

            # Without a user, or without an encrypted channel, a method is refused.
            for refused in (anonymous, unencrypted):
                with pytest.raises(ua.UaStatusCodeError, match="BadUserAccessDenied"):
                    await call(refused, "machines/wc1", "Start")
            await unencrypted.disconnect()

            # The CMM's homing alarm arrives as an event; clearing it by the method clears it in the cell.
            starting = asyncio.create_task(call(operator, "machines/cmm_wc", "Start"))
            ev = await until(
                lambda: [e for _, e in rec.events if e.ConditionName == "HOME_CMM"], 30, "the homing alarm"
            )
            alarm = ev[0]
            assert alarm.Retain and alarm.SourceName == "cmm_wc" and alarm.Message.Text
            alarm_no = int(str(alarm.NodeId.Identifier).removeprefix("alarms/"))
            pending = json.loads(ok(await asyncio.to_thread(gwc, cell, "alarm", "list", "--json")))
            assert [a["alarm_no"] for a in pending] == [alarm_no]
            # The CMM waits to be homed: the start answers that it completes later (the client is not held).
            assert (await starting)[0] == "GoodCompletesAsynchronously"
            # The standard Acknowledge of the condition clears the cell's alarm; ClearAlarm then finds it
            # cleared already (the cell's Notnow, BadInvalidState).
            condition = operator.get_node(alarm.NodeId)
            acknowledge = ua.NodeId(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge)
            code, _ = await condition.call_method(acknowledge, alarm.EventId, ua.LocalizedText("homed"))
            assert code == "ACK_OK"
            assert json.loads(ok(await asyncio.to_thread(gwc, cell, "alarm", "list", "--json"))) == []
            with pytest.raises(ua.UaStatusCodeError, match="BadInvalidState"):
                await call(operator, "alarms", "ClearAlarm", ua.Variant(alarm_no, ua.VariantType.Int64))
            await until(lambda: [e for _, e in rec.events if e.NodeId == alarm.NodeId and not e.Retain], 10, "cleared")
            await until(lambda: "Idle" in rec.values(status.nodeid), 10, "the CMM Idle")
            assert rec.values(node("machines/cmm_wc/MachineryItemState/CurrentState").nodeid)[-1].Text == "NotExecuting"

            # A lot: the work order and the import by method; the CMM's status seen at every change.
            entities = await asyncio.to_thread(order, cell, "alum_chess_set=1")
            await until(
                lambda: (
                    cell.query("select state from lot_status where entity_id = %s", entities[0])[0][0]
                    == "waiting_import"
                ),
                20,
                "the lot to ask for import",
            )
            entity = f"lots/{cell.query('select lot_id from lot_status')[0][0]}/{entities[0]}"
            await read_until(node(f"{entity}/state"), "waiting_import")
            code, _ = await call(operator, "cell", "ImportLot", ua.Variant(entities[0], ua.VariantType.Int64))
            assert code == "ACK_OK"
            await until(
                lambda: rec.values(status.nodeid)[-4:] == ["Idle", "Setup", "Running", "Idle"],
                30,
                f"a run (seen so far: {rec.values(status.nodeid)})",
            )
            changes = [(t, v) for t, n, v in rec.changes if n == status.nodeid.to_string()]
            for value in ("Setup", "Running"):
                heard = next(t for t, m, s in ear.heard if m == "cmm_wc" and s == value)
                seen = next(t for t, v in changes if v == value)
                assert 0 <= seen - heard < LATENCY, f"{value} seen {seen - heard:.3f}s after the bus said it"
            await until(
                lambda: cell.query("select state from lot_status")[0][0] == "waiting_export", 20, "the lot done"
            )
            code, _ = await call(operator, "cell", "ExportLot", ua.Variant(entities[0], ua.VariantType.Int64))
            assert code == "ACK_OK"
            await until(lambda: cell.query("select state from lot_status")[0][0] == "exported", 10, "exported")
            last = json.loads(await node("machines/cmm_wc/last_run/results").read_value())
            assert last.get("RESULT") == "PASS", last

            # The operator's `gwc machine stop` is seen as Shutdown.
            ok(await asyncio.to_thread(gwc, cell, "machine", "stop", "cmm_wc"))
            await until(lambda: rec.values(status.nodeid)[-1] == "Shutdown", 10, "Shutdown")

            # With the user, methods stop and start a machine.
            for method, want in (("Start", "Idle"), ("Stop", "Shutdown"), ("Start", "Idle")):
                code, note = await call(operator, "machines/wc1", method)
                assert code in ("ACK_OK", "GoodCompletesAsynchronously"), note
                await read_until(wc1, want)
                assert cell.query("select status from machine_status where machine_id = 'wc1'")[0][0] == want
            await operator.disconnect()
            # The subscription's notifications trail the reads above: wait for its Idle before the kill.
            await until(lambda: rec.values(wc1.nodeid)[-1] == "Idle", 10, "the subscription's Idle")

            # The gateway killed while the client is subscribed; the machine stops meanwhile. asyncua's own
            # reconnect brings the subscription back, and it shows the status now, not the one before.
            await asyncio.to_thread(cell.kill, "opcua")
            ok(await asyncio.to_thread(gwc, cell, "machine", "stop", "wc1"))
            assert rec.values(wc1.nodeid)[-1] == "Idle"
            await asyncio.to_thread(cell.start, "opcua", timeout=STARTUP)
            await until(lambda: rec.values(wc1.nodeid)[-1] == "Shutdown", 20, "the restarted gateway's Shutdown")
            assert await wc1.read_value() == "Shutdown"
        finally:
            await anonymous.disconnect()

    loop = asyncio.new_event_loop()
    try:
        loop.run_until_complete(main())
    finally:
        loop.close()
        stop_lot_scripts(cell)
