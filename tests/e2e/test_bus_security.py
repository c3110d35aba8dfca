"""The bus obeys only its own cell (issue 15), against real modules: forgeries and replays from an
outsider, a lot script outside its rights, a WC asked for a run not reserved to the asker, the
malformed kinds that once got through, a flood while lots run, two cells on one group and port."""

from __future__ import annotations

import collections
import contextlib
import functools
import logging
import os
import random
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from psycopg import sql

from gwc.config import BusConfig
from gwc.ipc import BlockingBus, keys, wire
from gwc.ipc.auth import Guard
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.log import log_file_name
from tests.e2e.lotkit import TWO_DUMMY_RUNS, cell_with_machines, gwc, import_export_all, ok, order
from tests.harness import CellHarness, wait_for

pytestmark = pytest.mark.e2e


class Outsider:
    """Someone on the network with the cell's group and port (a copied cell.toml) but not its key:
    datagrams written from docs/protocol.md, unsealed or sealed with a key of their own."""

    def __init__(self, cfg: BusConfig, tmp: Path) -> None:
        self.dest = (cfg.group, cfg.port)
        self.beat_dest = (cfg.group, cfg.beat_port)
        own = BusConfig(key_file=str(tmp / "k" / "cell.key"), lot_key_file=str(tmp / "k" / "lot.key"))
        keys.new(own)
        self.guard = Guard(own, "outsider", logging.getLogger("outsider"), collections.Counter())
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(cfg.interface))

    def send(self, data: bytes, beat: bool = False) -> None:
        """Both ways an outsider can: bare, and sealed under a key that is not the cell's."""
        for datagram in (data, self.guard.seal(data, beat=beat)):
            try:
                self.sock.sendto(datagram, self.beat_dest if beat else self.dest)
            except BlockingIOError:
                pass  # the flood outran the socket: lost like any datagram

    def close(self) -> None:
        self.sock.close()


def msg(src: str, inc: int, cls: str, name: str, to: str | None = None, seq: int = 1, **fields: Any) -> bytes:
    return wire.encode(
        wire.Envelope(
            kind="msg", src=src, inc=inc, seq=seq, conv=f"{src}.{inc:x}.{seq}", cls=cls, msg=name, to=to, fields=fields
        )
    )


def status(cell: CellHarness, machine: str) -> str:
    return str(cell.query("SELECT status FROM machine_status WHERE machine_id = %s", machine)[0][0])


def ask(cell: CellHarness, cls: str, m: Any, to: str, bus: BlockingBus | None = None) -> Any:
    conv, answer = (bus or cell.bus).request(cls, m, to=to, timeout=15)
    conv.end()
    return answer.first


@pytest.fixture
def outsider(tmp_path: Path) -> Iterator[Any]:
    made: list[Outsider] = []

    def make(cell: CellHarness) -> Outsider:
        made.append(Outsider(cell.cfg.bus, tmp_path / f"outsider{len(made)}"))
        return made[-1]

    yield make
    for o in made:
        o.close()


def test_the_bus_obeys_only_its_own_cell(lot_cell: Any, outsider: Any, tmp_path: Path) -> None:
    """One cell, four attacks in turn (a cell's start-up is the costly part of each)."""
    cell = cell_with_machines(lot_cell(machines=[{"id": "wc1", "kind": "dummy", "run_time": 0.2}]), "wc1")
    forgeries_and_replays_are_refused_and_change_nothing(cell, outsider(cell))
    the_wc_sets_up_only_what_is_reserved_and_malformed_kinds_stop_at_the_wire(cell)
    a_lot_script_outside_its_rights_is_refused_and_its_lot_goes_on(cell, tmp_path)
    control_characters_off_the_wire_are_escaped_in_the_log_and_the_monitor(cell)
    ok(gwc(cell, "check"))


FORGED = "\nFrom forged | Date 2026-01-01 | Module msched | Error: forged\r\x1b[2J\x9b31m"


def control_characters_off_the_wire_are_escaped_in_the_log_and_the_monitor(cell: CellHarness) -> None:
    """A lot key holder's conversation id and field carrying a newline, a carriage return and terminal
    control sequences: msched's log line stays one line, the monitor prints them escaped."""
    monitor = subprocess.Popen(
        [sys.executable, "-m", "gwc", "monitor", "--class", "CANCEL_RE", "--count", "1", "--duration", "20"],
        env=cell.env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert monitor.stderr is not None and select.select([monitor.stderr], [], [], 20)[0], "the monitor said nothing"
        assert "monitoring bus" in monitor.stderr.readline()  # it listens now
        guard = Guard(cell.cfg.bus, "lot:66", cell.log, collections.Counter())
        env = wire.Envelope(
            kind="msg", src="lot:66", inc=66, seq=1, conv="lot:66.42.1" + FORGED, cls="CANCEL_RE",
            msg="Cancel_Request", to="msched", fields={"request_key": 999, "by": "lot" + FORGED},
        )  # fmt: skip
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(cell.cfg.bus.interface))
        sock.sendto(guard.seal(wire.encode(env)), (cell.cfg.bus.group, cell.cfg.bus.port))
        sock.close()
        out, err = monitor.communicate(timeout=30)
    finally:
        monitor.kill()
        monitor.wait()
    wait_for(lambda: cell.log_has("msched", "cancel request 999 by lot"), 10, "msched to log the cancel")
    (line,) = [x for x in cell.log_text("msched").splitlines() if "cancel request 999" in x]
    assert "Conv lot:66.42.1\\nFrom forged" in line and "\\r\\x1b[2J\\x9b31m" in line, line
    assert not any(x.startswith("From forged") for x in cell.log_text("msched").splitlines())
    assert "lot:66.42.1\\nFrom forged" in out and "\x1b" not in out and "\r" not in out and "\x9b" not in out, out


def the_keys_change_on_the_running_cell(cell: CellHarness) -> None:
    """`gwc key rotate`: every module takes up the new keys; past the overlap only they are accepted,
    and nobody was refused on the way (no module left the bus, none seemed to restart)."""
    incs = {name: p.inc for name, p in cell.bus.peers().items()}
    ok(gwc(cell, "key", "rotate", "--take-up", "3", "--overlap", "5"))
    expired = time.time() + 5.5
    wait_for(lambda: time.time() > expired, 10, "the old keys to expire")
    answer = ask(cell, "CANCEL_RE", message("Cancel_Request", request_key=2, by="test"), "msched")
    assert answer.ack_code == AckCode.REQ_KEY_U
    assert {name: p.inc for name, p in cell.bus.peers().items() if name in incs} == incs
    assert status(cell, "wc1") == "Idle"
    assert cell.bus.bus.guard.key_ids == (2, 2)


def forgeries_and_replays_are_refused_and_change_nothing(cell: CellHarness, out: Outsider) -> None:
    raised = ask(cell, "ALARM_SEND", message("Alarm_Send", alarm_id="SPILT_COFFEE", raised_by="test"), "cas")
    alarm = raised.alarm_no
    wc_inc = cell.bus.peers()["wc:wc1"].inc
    ms_inc = cell.bus.peers()["ms"].inc
    for i in range(20):  # each forgery many times, as in the report
        out.send(msg("ms", ms_inc, "UPD_ME_ST", "Update_ME_Status", seq=100 + i, machine_id="wc1", status="Shutdown"))
        out.send(msg("hi.1", 1, "SHUTDOWN", "Shutdown_Request", to="msched", seq=i + 1, module="msched"))
        out.send(msg("cas", 1, "ALARM_CLE", "Alarm_Clear", seq=i + 1, alarm_no=alarm, cleared_by="intruder"))
        out.send(
            msg("hi.1", 1, "ALARM_CLR_REQ", "Alarm_Clear_Request", to="cas", seq=50 + i, alarm_no=alarm, cleared_by="x")
        )
        out.send(
            msg(
                "lot:1",
                1,
                "MACH_REQ",
                "Machine_Request",
                to="msched",
                seq=i + 1,
                entity_id=1,
                op_type="dummy_op",
                num_machines=0,
            )
        )
        out.send(wire.encode(wire.Envelope(kind="bye", src="wc:wc1", inc=wc_inc)))
        out.send(wire.encode(wire.Envelope(kind="hello", src="wc:wc1", inc=wc_inc + 1, query=True)))
        out.send(wire.encode(wire.Envelope(kind="hello", src="wc:wc9", inc=9)), beat=True)
    # A valid datagram captured off the wire and sent again byte for byte: a Machine_Request.
    captured: list[bytes] = []
    sniffer = BlockingBus(f"sniff.{cell.tag}", cell.cfg.bus, cell.log)
    transport = sniffer.bus.transport
    send = transport.send
    transport.send = lambda data: (captured.append(data), send(data))[1]  # type: ignore[method-assign]
    try:
        conv = sniffer.start("CANCEL_RE", message("Cancel_Request", request_key=424242, by="test"), to="msched")
        assert conv.next_message(15).first.ack_code == AckCode.REQ_KEY_U
        conv.end()
    finally:
        sniffer.close()
    replayer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a source of its own: its own report line
    replayer.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(cell.cfg.bus.interface))
    for _ in range(3):
        replayer.sendto(captured[0], out.dest)
    replayer.close()
    # Nothing changed: the machine is Idle, MSCHED serves, the alarm is raised, wc1 on the bus, no request.
    answer = ask(cell, "CANCEL_RE", message("Cancel_Request", request_key=1, by="test"), "msched")
    assert answer.ack_code == AckCode.REQ_KEY_U
    assert status(cell, "wc1") == "Idle"
    assert cell.query("SELECT cleared_at FROM alarms WHERE alarm_no = %s", alarm) == [(None,)]
    assert cell.query("SELECT count(*) FROM request_machines") == [(0,)]
    peers = cell.bus.peers()
    assert peers["wc:wc1"].inc == wc_inc and "wc:wc9" not in peers
    assert cell.alive("msched") and cell.alive("wc", "wc1")
    # Each module says so in one line per source and interval, naming the replay too.
    wait_for(lambda: cell.log_has("msched", "replay"), 15, "msched to report the replayed datagram")
    for module in ("msched", "ms", "cas"):  # each writes its first line at its next heartbeat
        wait_for(functools.partial(cell.log_has, module, "dropped from"), 15, f"{module} to report the drops")
        assert cell.log_text(module).count("dropped from") < 10, module


SCRIPT = '''"""A pawn whose script also tries what lot scripts may not: shut MSCHED down, announce a machine down."""

from gwc.ipc.catalogue import message
from gwc.lot import OperationEntity


def main(entity: OperationEntity) -> None:
    entity.wait_for_import()
    bus = entity._bus
    conv, answer = bus.request("SHUTDOWN", message("Shutdown_Request", module="msched"), to="msched", timeout=10)
    conv.end()
    entity.log.info("SHUTDOWN answered %s", answer.first.ack_code)
    assert answer.first.ack_code == "Not_Auth", answer.first
    bus.start("UPD_ME_ST", message("Update_ME_Status", machine_id="wc1", status="Shutdown")).end()
    op = entity.operate("dummy_op")
    entity.lot_completed(f"PASS: on {op.machines[0]}")
    entity.wait_for_export()
'''


def register_pawn(cell: CellHarness, tmp_path: Path) -> None:
    """A product of the dummy machines alone: `pawn`."""
    script = tmp_path / f"pawn_{cell.tag}.py"
    script.write_text(TWO_DUMMY_RUNS)
    ok(gwc(cell, "script", "register", "pawn", str(script), "--product", "pawn"))


def a_lot_script_outside_its_rights_is_refused_and_its_lot_goes_on(cell: CellHarness, tmp_path: Path) -> None:
    script = tmp_path / "rogue.py"
    script.write_text(SCRIPT)
    ok(gwc(cell, "script", "register", "rogue", str(script), "--product", "rogue_pawn"))
    (pawn,) = order(cell, "rogue_pawn=1")
    import_export_all(cell, [pawn], timeout=60)
    assert cell.alive("msched") and status(cell, "wc1") == "Idle"
    assert "SHUTDOWN answered Not_Auth" in cell.log_text(f"lot:{pawn}")
    for cls in ("SHUTDOWN", "UPD_ME_ST"):  # one line per source (entity and class) and interval
        wait_for(lambda: cell.log_has("msched", f"lot:{pawn} ({cls})"), 15, f"msched to log the refused {cls}")  # noqa: B023
        assert cell.log_text("msched").count(f"lot:{pawn} ({cls})") == 1


def the_wc_sets_up_only_what_is_reserved_and_malformed_kinds_stop_at_the_wire(cell: CellHarness) -> None:
    lot_key_cfg = cell.cfg.bus
    with BlockingBus("lot:77", lot_key_cfg, cell.log) as lot:  # holds the lot key: a lot entity's rights
        for cls, name in (("SETUP_RUN", "Setup_Run"), ("START_RUN", "Start_Run")):
            fields = {"machine_id": "wc1", "machine_run_id": 4242}
            if name == "Setup_Run":
                fields |= {"recipe_id": "dummy_recipe", "op_type": "dummy_op", "entity_id": 77}
            answer = ask(cell, cls, message(name, **fields), "wc:wc1", bus=lot)
            assert answer.ack_code == AckCode.NOT_RESERVED, answer
    assert status(cell, "wc1") == "Idle"
    # The two malformed kinds that leaked, sealed with the cell's key (a buggy module, not an outsider).
    guard = Guard(cell.cfg.bus, "buggy", cell.log, collections.Counter())
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(cell.cfg.bus.interface))
    hello = wire.encode(wire.Envelope(kind="hello", src="phantom", inc=3, interest=("X" * 200,)))
    sock.sendto(guard.seal(hello[:-201] + bytes([201]) + b"X" * 201), (cell.cfg.bus.group, cell.cfg.bus.port))
    nul = msg("buggy", 3, "CHG_STATUS", "Change_Status", to="ms", machine_id="wc1\0", status="Shutdown")
    sock.sendto(guard.seal(nul), (cell.cfg.bus.group, cell.cfg.bus.port))
    sock.close()
    wait_for(lambda: cell.log_has("ms", "dropped invalid"), 10, "ms to refuse the NUL")
    assert "phantom" not in cell.bus.peers() and status(cell, "wc1") == "Idle"
    assert "DB_Badupd" not in cell.log_text("ms") and "| Error:" not in cell.log_text("ms")


DOWN = "SELECT machine_id FROM machine_status WHERE machine_id = ANY(%s) AND status = 'Shutdown'"


@pytest.mark.soak  # ~60 s: a cell of two machines, a 3 s flood, two lots
def test_a_flood_on_both_ports_while_lots_run_shuts_nothing_down(lot_cell: Any, outsider: Any, tmp_path: Path) -> None:
    cell = cell_with_machines(
        lot_cell(machines=[{"id": m, "kind": "dummy", "run_time": 0.3, "liveness": 1.5} for m in ("wc1", "wc2")]),
        "wc1",
        "wc2",
    )
    sizes = {name: cell.log_path(name).stat().st_size for name in ("msched", "ms", "ls", "cas", "sls", "ers")}
    sizes |= {f"wc:{m}": cell.log_path(f"wc:{m}").stat().st_size for m in ("wc1", "wc2")}
    out = outsider(cell)
    rnd = random.Random(15)
    done = threading.Event()
    downs: list[str] = []
    took: list[float] = []

    def flood() -> None:  # 20,000 datagrams in 3 s to each port (half bare, half under a foreign key)
        start = time.monotonic()
        for i in range(10_000):
            junk = rnd.randbytes(rnd.randrange(16, 200))
            out.send(wire.HEADER + junk, beat=False)
            out.send(wire.HEADER + junk, beat=True)
            behind = start + 3.0 * i / 10_000 - time.monotonic()
            if behind > 0:
                time.sleep(behind)
        took.append(time.monotonic() - start)
        done.set()

    register_pawn(cell, tmp_path)
    entities = order(cell, "pawn=3")
    flooder = threading.Thread(target=flood)
    flooder.start()
    try:
        while not done.is_set():
            downs += [m for (m,) in cell.query(DOWN, ["wc1", "wc2"])]
            time.sleep(0.1)
    finally:
        flooder.join()
    import_export_all(cell, entities, timeout=90)
    assert not downs, f"machines shut down under the flood: {downs}"
    assert took[0] < 4.5, f"the flood took {took[0]:.1f}s, not about 3"
    ok(gwc(cell, "check"))
    for name, before in sizes.items():
        grown = cell.log_path(name).stat().st_size - before
        assert grown < 200_000, f"{log_file_name(name)} grew {grown} bytes"


@pytest.fixture
def second_database_url(pg_cluster: Any) -> Iterator[str]:
    name = f"gwc_t_{uuid.uuid4().hex[:12]}"
    with pg_cluster.admin() as conn:
        conn.execute(
            sql.SQL("create database {} template {}").format(sql.Identifier(name), sql.Identifier(pg_cluster.template))
        )
    yield pg_cluster.url(name)
    with pg_cluster.admin() as conn:
        conn.execute(sql.SQL("drop database if exists {} with (force)").format(sql.Identifier(name)))


@pytest.mark.soak  # ~80 s: two whole cells, then a key rotation
def test_two_cells_with_their_own_keys_share_a_group_and_port(
    lot_cell: Any, xprocess: Any, tmp_path: Path, second_database_url: str
) -> None:
    one = cell_with_machines(lot_cell(machines=[{"id": "wc1", "kind": "dummy", "run_time": 0.2}]), "wc1")
    same = {"group": one.cfg.bus.group, "port": one.cfg.bus.port}
    two = CellHarness(
        xprocess,
        tmp_path / "second",
        second_database_url,
        bus=same,
        machines=[{"id": "wc1", "kind": "dummy", "run_time": 0.2}],
    )
    try:
        assert (two.cfg.bus.group, two.cfg.bus.port) == (one.cfg.bus.group, one.cfg.bus.port)
        assert keys.load(two.cfg.bus, "module")[1].cell_id != keys.load(one.cfg.bus, "module")[1].cell_id
        cell_with_machines(two, "wc1")
        for c in (one, two):
            register_pawn(c, tmp_path)
        lots = {c: order(c, "pawn=1") for c in (one, two)}
        for c, entities in lots.items():
            import_export_all(c, entities, timeout=60)
        for c in (one, two):  # each heard only its own modules: none seemed to restart, none came or went twice
            assert "restarted (incarnation" not in c.log_text("msched")
            assert c.query("SELECT count(*) FROM lot_status") == [(1,)]
            ok(gwc(c, "check"))
        assert "other cell" in one.log_text("msched") and "other cell" in two.log_text("msched")
        the_keys_change_on_the_running_cell(one)
    finally:
        two.close()


class CounterJumper:
    """A holder of the lot key (a hostile lot script) sealing authentic datagrams whose replay
    counter jumps by 2^62 (then to the top of 64 bits), on both ports, under a new incarnation each
    round: every module's replay window for that sender meets the jump."""

    def __init__(self, cell: CellHarness) -> None:
        self.cfg = cell.cfg.bus
        self.guard = Guard(self.cfg, "lot:999", logging.getLogger("jumper"), collections.Counter())
        assert self.guard.role == "lot"
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(self.cfg.interface))
        self.stop = threading.Event()
        self.sent = 0
        self.thread = threading.Thread(target=self.run)

    def run(self) -> None:
        inc = 1000
        while not self.stop.is_set():
            inc += 1
            hello = wire.encode(wire.Envelope(kind="hello", src="lot:999", inc=inc))
            ask = msg(
                "lot:999", inc, "MACH_REQ", "Machine_Request", to="nobody", entity_id=9, op_type="x", num_machines=0
            )
            for counter in (0, 2**62, 2**63, 2**64 - 2):
                for beat, body, port in ((True, hello, self.cfg.beat_port), (False, ask, self.cfg.port)):
                    self.guard._counters[beat] = counter
                    with contextlib.suppress(BlockingIOError):
                        self.sock.sendto(self.guard.seal(body, beat=beat), (self.cfg.group, port))
                        self.sent += 1
            time.sleep(0.005)

    def __enter__(self) -> CounterJumper:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join()
        self.sock.close()


def test_a_lot_key_holders_counter_jumps_of_2_62_on_both_ports_blind_no_module(lot_cell: Any) -> None:
    """Issue 40: the jump once raised MemoryError in every module, a frozen WC stayed Idle for 30 s
    and tracebacks filled the .out files. Now: nothing raises, a frozen WC is shut down within its
    liveness while the jumps go on, and logs and outputs barely grow."""
    liveness = 1.5
    cell = cell_with_machines(
        lot_cell(machines=[{"id": "wc1", "kind": "dummy", "run_time": 0.2, "liveness": liveness}]), "wc1"
    )
    outs = {name: Path(cell.xprocess.getinfo(cell._xname(name)).logpath) for name in cell.started}  # their .out
    sizes = {name: (path.stat().st_size, cell.log_path(name).stat().st_size) for name, path in outs.items()}
    wc = cell.pid("wc", "wc1")
    assert wc is not None
    with CounterJumper(cell) as jumper:
        wait_for(lambda: jumper.sent > 2000, 20, "the first 2000 jumps")
        os.kill(wc, signal.SIGSTOP)  # frozen: silent, not dead
        frozen = time.monotonic()
        try:
            wait_for(lambda: status(cell, "wc1") == "Shutdown", 15, "the Machine Server to shut the frozen wc1 down")
            took = time.monotonic() - frozen
        finally:
            os.kill(wc, signal.SIGCONT)
        wait_for(lambda: jumper.sent > 6000, 20, "6000 jumps")
        ok(gwc(cell, "machine", "start", "wc1"))
        assert status(cell, "wc1") == "Idle"
        healthy_until = time.monotonic() + 2 * liveness  # a healthy machine is not shut down afterwards
        while time.monotonic() < healthy_until:
            assert status(cell, "wc1") == "Idle"
            time.sleep(0.2)
    print(f"frozen wc1 shut down {took:.2f}s after SIGSTOP under {jumper.sent} jumps (liveness {liveness}s)")
    assert took < liveness + 4, took  # its liveness, the watch's rounds, a busy machine (30 s before)
    ok(gwc(cell, "check"))
    for name, path in outs.items():
        out_grew = path.stat().st_size - sizes[name][0]
        log = cell.log_text(name)
        assert out_grew < 2000, f"{name}'s output grew {out_grew} bytes"
        assert cell.log_path(name).stat().st_size - sizes[name][1] < 50_000, name
        assert "MemoryError" not in log and " failed (" not in log, name
