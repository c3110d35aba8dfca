"""What docs/protocol.md ("Refusals") promises a stranger's client, against real servers: a directed
opener of a class the module does not serve is answered Notnow, and an answerable class sent under
the lot key that the lot key does not allow is answered Not_Auth, never left to time out; both for
classes whose answer carries more than an ack code (Status_Reply, Status_Line, Pong) too."""

from __future__ import annotations

from typing import Any

import pytest

from gwc.ipc import BlockingBus
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from tests.harness import CellHarness

pytestmark = pytest.mark.e2e

MACHINES = [{"id": "wc1", "kind": "dummy", "run_time": 0.1}]


def ask(bus: BlockingBus, cls: str, msg: Message, to: str) -> Message:
    conv, batch = bus.request(cls, msg, to=to, timeout=10)  # ConversationTimeout: the promise broken
    conv.end()
    return batch.first


@pytest.fixture
def servers(make_cell: Any) -> CellHarness:
    cell: CellHarness = make_cell(machines=MACHINES)
    cell.start_servers("ms", "sls")
    return cell


def test_a_directed_opener_a_module_does_not_serve_is_answered_notnow(servers: CellHarness) -> None:
    bus = servers.bus
    status = ask(bus, "GET_STATUS", message("Get_Status", machine_id="wc1"), to="sls")
    assert (status.name, status.ack_code, status.machine_id) == ("Status_Reply", AckCode.NOTNOW, "wc1")
    assert status.note == "sls does not serve GET_STATUS"
    line = ask(bus, "STATUS_LN", message("Status_Line_Get"), to="ms")
    assert (line.name, line.ack_code) == ("Status_Line", AckCode.NOTNOW) and line.text.startswith("Notnow")
    action = ask(bus, "LOT_ACTION", message("Lot_Action", entity_id=1, action="hold", by="test"), to="ms")
    assert (action.name, action.ack_code) == ("Lot_Action_Ack", AckCode.NOTNOW)
    pong = ask(bus, "PING", message("Ping", n=3), to="sls")
    assert (pong.name, pong.n, pong.ack_code) == ("Pong", 3, AckCode.NOTNOW)
    # ... and the modules serve what they do serve, as before.
    served = ask(bus, "GET_STATUS", message("Get_Status", machine_id="wc1"), to="ms")
    assert served.ack_code == AckCode.ACK_OK and served.status == "Shutdown"
    assert ask(bus, "STATUS_LN", message("Status_Line_Get"), to="sls").ack_code is None


def test_every_answerable_class_the_lot_key_may_not_send_is_answered_not_auth(servers: CellHarness) -> None:
    with BlockingBus("lot:77", servers.cfg.bus, servers.log) as lot:  # holds the lot key: a lot entity's rights
        status = ask(lot, "GET_STATUS", message("Get_Status", machine_id="wc1"), to="ms")
        assert (status.name, status.ack_code, status.machine_id) == ("Status_Reply", AckCode.NOT_AUTH, "wc1")
        line = ask(lot, "STATUS_LN", message("Status_Line_Get"), to="sls")
        assert (line.name, line.ack_code) == ("Status_Line", AckCode.NOT_AUTH)
        pong = ask(lot, "PING", message("Ping", n=5), to="ms")
        assert (pong.name, pong.n, pong.ack_code) == ("Pong", 5, AckCode.NOT_AUTH)
        down = ask(lot, "CHG_STATUS", message("Change_Status", machine_id="wc1", status="Idle"), to="ms")
        assert down.ack_code == AckCode.NOT_AUTH
    assert servers.query("SELECT status FROM machine_status WHERE machine_id = 'wc1'") == [("Shutdown",)]
