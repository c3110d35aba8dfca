"""The module lifecycle: a startup that fails after Startup_Ack still ends its conversation."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from pathlib import Path

import pytest

from gwc.errors import DatabaseError, DatabaseUnavailable
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.module import Module
from gwc.retry import Deadline
from gwc.soak.private_config import private_bus
from tests.conftest import make_config


class FailingStartup(Module):
    async def on_startup(self) -> str:
        raise DatabaseError("the table is gone")


def test_startup_work_that_raises_is_answered_with_startup_complete_not_left_to_time_out(tmp_path: Path) -> None:
    cfg = make_config(tmp_path, None, bus=private_bus())
    log = logging.getLogger("test.module")

    async def scenario() -> tuple[str, str, bool]:
        module = FailingStartup(cfg, "failing", log)
        runner = asyncio.get_running_loop().create_task(module.run())
        starter = Bus("starter", cfg.bus, log)
        await starter.sign_on()
        try:
            conv, ack = await starter.request(
                "STARTUP", message("Startup_Request", module="failing"), to="failing", timeout=10
            )
            done = await conv.next_message(5)  # well before the 10 s a starter would otherwise wait
            conv.end()
            return ack.first.ack_code, done.first.ack_code, module.started
        finally:
            module.stop()
            await runner
            await starter.close()

    ack, complete, started = asyncio.run(asyncio.wait_for(scenario(), 30))
    assert ack == AckCode.ACK_OK
    assert complete == AckCode.DB_BADUPD
    assert not started


def test_ask_within_rides_out_a_server_that_is_not_up_yet(tmp_path: Path) -> None:
    """A question safe to ask twice is asked again while the server restarts, not failed at once."""
    cfg = make_config(tmp_path, None, bus=private_bus())
    log = logging.getLogger("test.module")

    async def server_appears_late() -> None:
        await asyncio.sleep(1.0)
        srv = Bus("srv", cfg.bus, log, interest=("GET_STATUS",))
        await srv.sign_on()
        try:
            while True:  # as a real server does, answer every question (earlier tries arrive too)
                conv = await srv.first_message()
                if conv is not None:
                    await conv.send(message("Status_Reply", machine_id="wc1", status="Idle", ack_code=AckCode.ACK_OK))
                    conv.end()
        finally:
            await srv.close()

    async def scenario() -> str:
        asker = Module(cfg, "asker", log)
        await asker.bus.sign_on()
        late = asyncio.get_running_loop().create_task(server_appears_late())
        try:
            answer = await asker.ask("GET_STATUS", message("Get_Status", machine_id="wc1"), "srv", 0.3, within=10)
            return answer.status
        finally:
            late.cancel()
            await asyncio.gather(late, return_exceptions=True)
            await asker.bus.close()

    assert asyncio.run(asyncio.wait_for(scenario(), 30)) == "Idle"


def test_a_module_whose_database_is_away_fails_fast_waits_for_it_and_carries_on_when_it_is_back(
    tmp_path: Path, database_url: str
) -> None:
    """No step waits for a database that is gone (DatabaseUnavailable at once, no new connect), a step
    that must not be lost waits for it, and the module reconnects by itself: it never exits."""
    dead = tmp_path / "nosocket"
    dead.mkdir()
    cfg = make_config(tmp_path, f"postgresql://gwc@/gwc?host={dead}&connect_timeout=1", bus=private_bus())
    log = logging.getLogger("test.module")

    async def scenario() -> None:
        module = Module(cfg, "dbless", log)
        module.database.role = "ms"
        with pytest.raises(DatabaseUnavailable):
            module.transaction(lambda cur: cur.execute("select 1"))
        assert module.database.down is not None
        started = time.monotonic()
        with pytest.raises(DatabaseUnavailable, match="away"):
            module.transaction(lambda cur: cur.execute("select 1"))
        assert time.monotonic() - started < 0.05  # refused at once: the reconnect task tries, not the step
        assert not await module.wait_database(Deadline(0.3))
        with pytest.raises(DatabaseUnavailable):
            await module.transaction_when_up(lambda cur: cur.execute("select 1"), within=0.3)
        # The database comes back (here: the module is pointed at one that answers).
        module.database.cfg = dataclasses.replace(cfg, database_url=database_url)
        row = await asyncio.wait_for(module.transaction_when_up(lambda cur: cur.execute("select 7").fetchone()), 10)
        assert row == (7,) and module.database.down is None
        module.db().close()
        await module.bus.close()
        for task in list(module._tasks):
            task.cancel()

    asyncio.run(scenario())
