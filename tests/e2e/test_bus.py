"""The conversation bus between real processes on a real multicast group (loopback).

Peers are `python -m tests.buspeer` processes (see that module for what they answer); the test
process talks to them through its own Bus, so every conversation crosses a process boundary.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import os
import random
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from xprocess import ProcessStarter

from gwc.config import Config
from gwc.errors import ConversationTimeout
from gwc.ipc import BlockingBus, Bus, wire
from gwc.ipc.auth import Guard
from gwc.ipc.catalogue import message
from gwc.log import log_file_name, open_log
from tests.harness import wait_for, write_cell_config

ROOT = Path(__file__).resolve().parents[2]
FAULTS = {"drop": 0.2, "duplicate": 0.1, "reorder": 0.1}


class BusLab:
    """A private bus (own group and port) with peer processes and an observer bus in the test."""

    def __init__(self, xprocess: Any, var: Path, faults: dict[str, float] | None = None) -> None:
        self.xprocess = xprocess
        self.cfg: Config = write_cell_config(var, None, modules=(), faults=faults, bus={"reply_timeout": 15.0})
        self.tag = f"b{os.getpid()}-{random.randrange(1 << 30):x}"
        self.log = open_log("test", self.cfg.log_dir, "note")
        self.bus = BlockingBus(f"test.{self.tag}", self.cfg.bus, self.log, interest=())
        self.names: list[str] = []

    def start_peer(self, name: str, interest: str = "PING") -> None:
        lab = self
        env = dict(
            os.environ,
            GWC_CONFIG=str(self.cfg.path),
            PYTHONUNBUFFERED="1",
            PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        )

        class Starter(ProcessStarter):
            terminate_on_interrupt = True
            timeout = 20
            args = [sys.executable, "-m", "tests.buspeer", name, "--interest", interest]

            def __init__(self, control_dir: Any, process: Any) -> None:
                super().__init__(control_dir, process)
                self.env = env

            def startup_check(self) -> bool:
                return name in lab.bus.peers()

        self.xprocess.ensure(f"{self.tag}-{name}", Starter, restart=True)
        self.names.append(name)

    def report(self, name: str) -> dict[str, Any]:
        conv, batch = self.bus.request("PING", message("Ping", n=0, payload="report"), to=name, timeout=15)
        conv.end()
        return json.loads(batch.first.payload)

    def close(self) -> None:
        for name in self.names:
            try:
                self.xprocess.getinfo(f"{self.tag}-{name}").terminate(timeout=10)
            except Exception as e:  # keep cleaning the rest
                print(f"buslab: terminating {name} failed: {e}")
        self.bus.close()


@pytest.fixture
def make_lab(xprocess: Any, tmp_path: Path) -> Iterator[Any]:
    labs: list[BusLab] = []

    def make(**kw: Any) -> BusLab:
        lab = BusLab(xprocess, tmp_path / f"lab{len(labs)}", **kw)
        labs.append(lab)
        return lab

    yield make
    for lab in labs:
        lab.close()


def test_multi_message_conversation_arrives_whole_and_in_order(make_lab: Any) -> None:
    lab = make_lab()
    lab.start_peer("sched", interest="PING,MACH_REQ")
    ids = [f"m{i}" for i in range(12)]
    batch = [message("Machine_Request", entity_id=7, op_type="op", num_machines=len(ids))]
    batch += [message("Machine_Entry", machine_id=m) for m in ids]
    conv, answer = lab.bus.request("MACH_REQ", *batch, to="sched", timeout=15)
    conv.end()
    assert answer.first.name == "Machine_Req_Ack" and answer.first.note == ",".join(ids)
    pings = [message("Ping", n=i) for i in range(20)]
    conv, answer = lab.bus.request("PING", *pings, to="sched", timeout=15)
    conv.end()
    assert [m.n for m in answer.messages] == list(range(20))


def test_reply_reaches_only_the_initiators_conversation(make_lab: Any) -> None:
    lab = make_lab()
    lab.start_peer("echo")
    lab.start_peer("watcher", interest="PING")  # also answers broadcast Pings: two answers, both to us
    other = BlockingBus(f"other.{lab.tag}", lab.cfg.bus, lab.log, interest=("PING",))
    try:
        wait_for(lambda: {"echo", "watcher"} <= set(other.peers()), 10, "other to see the peers")
        a = lab.bus.start("PING", message("Ping", n=1))  # broadcast: echo and watcher both answer
        b = other.start("PING", message("Ping", n=2), to="echo")
        got_a = sorted((x.sender, x.first.n) for x in (a.next_message(15), a.next_message(15)))
        got_b = b.next_message(15)
        assert got_a == [("echo", 1), ("watcher", 1)]
        assert (got_b.sender, got_b.first.n) == ("echo", 2)
        a.end()
        b.end()
        # `other` listens to PING too: it got our broadcast Ping, but no Pong: replies are directed.
        heard = other.first_message(timeout=5)
        assert heard is not None and heard.first is not None and heard.first.first.name == "Ping"
        assert heard.first.sender == lab.bus.bus.name
        assert other.first_message(timeout=0.5) is None
        watcher = lab.report("watcher")
        assert [s[2] for s in watcher["seen"] if s[0] == "PING" and s[2] != [0]] == [
            [1]
        ]  # not n=2, which was sent to echo
    finally:
        other.close()


def test_interest_filters_hide_what_they_should_and_change_at_run_time(make_lab: Any) -> None:
    lab = make_lab()
    lab.start_peer("wc", interest="PING")
    lab.bus.start("UPD_ME_ST", message("Update_ME_Status", machine_id="x", status="Idle")).end()
    conv, _ = lab.bus.request("PING", message("Ping", n=1, payload="interest:+UPD_ME_ST"), to="wc", timeout=15)
    conv.end()
    wait_for(lambda: "UPD_ME_ST" in lab.bus.peers()["wc"].interest, 10, "wc to announce its new interest")
    lab.bus.start("UPD_ME_ST", message("Update_ME_Status", machine_id="y", status="Idle")).end()
    wait_for(lambda: any(s[0] == "UPD_ME_ST" for s in lab.report("wc")["seen"]), 10, "the second broadcast")
    seen = [s for s in lab.report("wc")["seen"] if s[0] == "UPD_ME_ST"]
    assert len(seen) == 1, "the broadcast sent before the interest changed was never seen"


def test_unanswered_conversation_times_out_and_is_logged(make_lab: Any) -> None:
    lab = make_lab()
    lab.start_peer("mute")
    with pytest.raises(ConversationTimeout, match="no answer from mute"):
        lab.bus.request("PING", message("Ping", n=1, payload="silent"), to="mute", timeout=0.5)
    text = (lab.cfg.log_dir / log_file_name("test")).read_text()
    assert "PING conversation" in text and "no answer from mute within 0.5s" in text


def test_peers_are_seen_to_join_and_to_leave_cleanly_or_by_silence(make_lab: Any) -> None:
    lab = make_lab()
    lab.start_peer("p1")
    lab.start_peer("p2")
    assert lab.bus.peers()["p1"].interest == frozenset({"PING"})
    left: list[str] = []
    # Registered, and waited for, on the bus thread before p1 goes (uvloop may handle a datagram
    # before a callback merely scheduled from another thread: the bye was once heard first).
    lab.bus.call(lambda: lab.bus.bus.peer_listeners.append(lambda name, peer: peer is None and left.append(name)))
    lab.xprocess.getinfo(f"{lab.tag}-p1").terminate(timeout=10)  # SIGTERM: a clean close says bye
    wait_for(lambda: "p1" not in lab.bus.peers(), 1.0, "p1 to leave at once (it said bye)")
    os.kill(lab.xprocess.getinfo(f"{lab.tag}-p2").pid, signal.SIGKILL)  # no bye: only silence tells
    wait_for(lambda: "p2" not in lab.bus.peers(), 10, "p2 to be dropped after peer_timeout of silence")
    assert left == ["p1", "p2"]


async def _thousand(lab: BusLab, n: int = 1000, window: int = 25) -> list[tuple[int, list[int]]]:
    bus = Bus(f"client.{lab.tag}", lab.cfg.bus, logging.getLogger("client"), ())
    await bus.sign_on()
    done: list[tuple[int, list[int]]] = []
    try:
        deadline = asyncio.get_running_loop().time() + 20
        while "srv" not in bus.peers():
            assert asyncio.get_running_loop().time() < deadline, "server not seen"
            await asyncio.sleep(0.02)
        todo = iter(range(n))

        async def worker() -> None:
            for i in todo:
                batch = [message("Ping", n=3 * i + k) for k in range(3)]
                conv, answer = await bus.request("PING", *batch, to="srv", timeout=20)
                conv.end()
                done.append((i, [m.n for m in answer.messages]))

        await asyncio.wait_for(asyncio.gather(*(worker() for _ in range(window))), 120)
    finally:
        await bus.close()
    return done


def test_thousand_conversations_complete_exactly_once_in_order_under_faults(make_lab: Any) -> None:
    lab = make_lab(faults=FAULTS)
    lab.start_peer("srv")
    done = asyncio.run(_thousand(lab))
    assert sorted(i for i, _ in done) == list(range(1000))
    assert all(ns == [3 * i, 3 * i + 1, 3 * i + 2] for i, ns in done)
    report = lab.report("srv")
    assert report["acted"] == 1000 and report["actions"] == 1000 and not report["acted_twice"], "each acted on once"
    stats = report["stats"]
    assert stats["injected_drop"] > 100 and stats["injected_duplicate"] > 50 and stats["injected_reorder"] > 50
    assert stats.get("duplicates", 0) > 0


def test_crossed_waits_with_new_conversations_arriving_never_deadlock(make_lab: Any) -> None:
    """A asks B, B asks A back before answering, both ways at once, 20 deep: all complete."""
    lab = make_lab()
    lab.start_peer("a")
    lab.start_peer("b")
    convs = []
    for i in range(20):
        # Each `nest` makes the receiver ask the other peer a question before it answers.
        convs.append(lab.bus.start("PING", message("Ping", n=i, payload="nest:" + "ba"[i % 2]), to="ab"[i % 2]))
    for i, conv in enumerate(convs):
        assert conv.next_message(20).first.n == i  # bounded: a deadlock fails here, it does not hang
        conv.end()
    for name in ("a", "b"):
        assert lab.report(name)["actions"] == 20  # 10 nests asked of it + 10 leaves asked by the other


def _mutations(valid: bytes, rnd: random.Random) -> Iterator[bytes]:
    yield b""
    yield b"GWC"
    yield b'GWC\x01{"k":"msg","s":"x","n":1}'  # an old (JSON) version
    yield b"XYZ" + valid[3:]
    yield wire.HEADER + b"\0" * 20  # truncated
    yield valid + b"[" * 50_000  # nesting bomb in the fields
    yield valid[:-1] + b',"x":' + b"9" * 5000 + b"}"  # huge integer in the fields
    yield wire.encode(
        wire.Envelope(kind="msg", src="x", inc=1, seq=1, conv="x.1.1", cls="NOPE", msg="Ping", to="fz")
    )  # unknown class
    yield wire.encode(
        wire.Envelope(
            kind="msg", src="x", inc=1, seq=2, conv="x.1.2", cls="PING", msg="Ping", fields={"n": "one"}, to="fz"
        )
    )  # wrong field type
    yield wire.encode(wire.Envelope(kind="hello", src="x", inc=1, interest=("\0", "é" * 100)))  # classes unknown
    yield valid + b" " * wire.MAX_DATAGRAM  # oversized
    for _ in range(400):
        data = bytearray(valid)
        for _ in range(rnd.randrange(1, 6)):
            data[rnd.randrange(len(data))] = rnd.randrange(256)
        yield bytes(data[: rnd.randrange(len(data) + 1)] if rnd.random() < 0.3 else data)
    for _ in range(100):
        yield bytes(rnd.randrange(256) for _ in range(rnd.randrange(1, 300)))


def test_the_kernel_keeps_from_a_module_what_is_not_meant_for_it(make_lab: Any) -> None:
    """Directed msgs, broadcasts of a class a module does not hear, and acks to others never wake it."""
    lab = make_lab()
    lab.start_peer("echo")
    lab.start_peer("deaf", interest="MACH_REQ")
    for i in range(50):
        for to in ("echo", None):
            conv, answer = lab.bus.request("PING", message("Ping", n=i), to=to, timeout=15)
            conv.end()
            assert answer.first.n == i
    deaf, echo = lab.report("deaf")["stats"], lab.report("echo")["stats"]
    assert echo["msg"] >= 100 and echo["hello"] > 0
    assert deaf.get("msg", 0) == 1 and deaf.get("ack", 0) <= 1, "only the report's own conversation reached it"
    # Membership still reaches everyone: by beats, read at each heartbeat.
    wait_for(lambda: lab.report("deaf")["stats"].get("beat", 0) > 0, 10, "deaf to read the others' beats")


def test_fuzzed_datagrams_are_dropped_and_the_module_keeps_answering(make_lab: Any) -> None:
    """Each mutation twice: as an outsider sends it (no seal: refused unread) and sealed with the
    cell's key (as from a buggy module: the decoder and the catalogue refuse it)."""
    lab = make_lab()
    lab.start_peer("fz")
    rnd = random.Random(1991)
    valid = wire.encode(
        wire.Envelope(
            kind="msg",
            src="fuzzer",
            inc=5,
            seq=1,
            conv="fuzzer.5.1",
            cls="PING",
            msg="Ping",
            to="fz",
            fields={"n": 1, "payload": "leaf"},
        )
    )
    guard = Guard(lab.cfg.bus, "fuzzer", lab.log, collections.Counter())
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(lab.cfg.bus.interface))
    try:
        for i, data in enumerate(_mutations(valid, rnd)):
            for datagram in (data, guard.seal(data)):
                try:
                    sock.sendto(datagram, (lab.cfg.bus.group, lab.cfg.bus.port))
                except OSError:
                    pass  # the kernel refused it (too large): fine, it never reached anyone
            if i % 50 == 0:
                conv, answer = lab.bus.request("PING", message("Ping", n=i), to="fz", timeout=15)
                conv.end()
                assert answer.first.n == i
    finally:
        sock.close()
    stats = lab.report("fz")["stats"]
    assert stats["malformed"] > 100 and stats.get("invalid", 0) >= 1
    assert stats.get("dropped_short", 0) + stats.get("dropped_other_cell", 0) > 100


def test_monitor_shows_and_records_conversations_decoded_with_filters(make_lab: Any, tmp_path: Path) -> None:
    lab = make_lab()
    lab.start_peer("sched", interest="PING,MACH_REQ")
    record = tmp_path / "monitor.jsonl"
    env = dict(os.environ, GWC_CONFIG=str(lab.cfg.path), GWC_VAR=str(lab.cfg.var))
    cmd = [sys.executable, "-m", "gwc", "monitor", "--duration", "20", "--count", "4"]
    popen = dict(env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    everything = subprocess.Popen([*cmd, "--record", str(record)], **popen)  # type: ignore[call-overload]
    only_ping = subprocess.Popen([*cmd[:-2], "--count", "2", "--class", "PING", "--json"], **popen)  # type: ignore[call-overload]
    machine = subprocess.Popen([*cmd[:-2], "--count", "2", "--machine", "wc7", "--json"], **popen)  # type: ignore[call-overload]
    keyless = subprocess.Popen([*cmd[:4], "--duration", "4", "--no-key", "--json"], **popen)  # type: ignore[call-overload]
    procs = (everything, only_ping, machine, keyless)
    try:
        for p in procs:  # each says so on stderr once it has joined the group
            assert p.stderr is not None and "monitoring bus" in p.stderr.readline()
        conv, _ = lab.bus.request("PING", message("Ping", n=99), to="sched", timeout=15)
        conv.end()
        conv, answer = lab.bus.request(
            "MACH_REQ",
            message("Machine_Request", entity_id=3, op_type="op", num_machines=1),
            message("Machine_Entry", machine_id="wc7"),
            to="sched",
            timeout=15,
        )
        conv.end()
        outs = [p.communicate(timeout=30)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    lines = [json.loads(x) for x in record.read_text().splitlines()]
    msgs = [x["message"] for x in lines]
    assert msgs[:2] == ["Ping", "Pong"] and msgs[-2:] == ["Machine_Request", "Machine_Entry"], msgs
    req = lines[-2]
    assert req["class"] == "MACH_REQ" and req["initiator"] == lab.bus.bus.name and req["to"] == "sched"
    assert req["fields"] == {"entity_id": 3, "op_type": "op", "num_machines": 1} and req["more"] == 1
    assert "Ping" in outs[0] and "MACH_REQ" in outs[0]
    assert {json.loads(x)["class"] for x in outs[1].splitlines()} == {"PING"}
    assert [json.loads(x)["message"] for x in outs[2].splitlines()] == ["Machine_Entry", "Machine_Req_Ack"]
    without_key = [json.loads(x) for x in outs[3].splitlines()]  # only that traffic exists, nothing decoded
    assert without_key and all(set(x) == {"time", "bus", "unauthenticated", "keyed"} for x in without_key)


def test_bench_bus_runs_and_reports_bus_and_floor(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, "-m", "gwc", "bench", "bus", "-n", "300", "--json"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    for mode in ("bare", "asyncio", "bus"):
        assert r[mode]["median_us"] > 0 and r[mode]["p99_us"] >= r[mode]["median_us"]
        assert r[mode]["conversations_per_s"] > 0
        assert r[mode]["client_cpu_us"] > 0 and r[mode]["server_cpu_us"] > 0
    assert r["ratio_median"] == round(r["bus"]["median_us"] / r["bare"]["median_us"], 2)
