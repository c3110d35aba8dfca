"""`gwc bench bus`: request->reply round trips over the bus, beside the bare multicast floor.

Real processes: this one (the client) and one `python -m gwc.bench.bus --serve MODE ...` per mode
(the servers); the client interleaves the modes in rounds. `bus` mode holds PING conversations
through gwc.ipc.bus (one asyncio loop a side,
reliability, ordering, membership all on); `bare` mode bounces datagrams on a plain multicast
socket, blocking, nothing else: the floor no bus on this medium can beat; `asyncio` mode is the bare
ping-pong through one asyncio loop a side, to show what asyncio alone costs. All run in the same
invocation on private groups, so the ratios compare like with like on a shared, noisy machine.
Authentication is on in `bus` mode, as in the cell; what the seal costs alone is measured apart
(`mac`): sealing and checking one Ping datagram, in this process.

`--hosts` measures the same between two hosts: it builds two network namespaces joined by a veth
bridge (gwc/netns.py, root only), runs this client in one and the servers in the other, so every
datagram crosses a real interface pair, as between two computers of a cell (minus the wire).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import logging
import os
import random
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import click

from gwc import netns
from gwc.bench import cpu_s, pin_cpu, summary
from gwc.config import BusConfig
from gwc.errors import GwcError
from gwc.ipc import auth, eventloop, keys, wire
from gwc.ipc.auth import Guard
from gwc.ipc.bus import Bus
from gwc.ipc.catalogue import message
from gwc.ipc.conversation import Conversation
from gwc.ipc.names import Conv, Msg
from gwc.ipc.transport import open_socket
from gwc.retry import Deadline

SERVER = "bench.srv"
MODES = ("bare", "asyncio", "bus")  # the floor, the floor plus one asyncio loop a side, the bus


def _cfg(group: str, port: int, key_dir: str, interface: str = "127.0.0.1") -> BusConfig:
    where = Path(key_dir)
    return BusConfig(
        group=group,
        port=port,
        interface=interface,
        reply_timeout=10.0,
        key_file=str(where / "cell.key"),
        lot_key_file=str(where / "lot.key"),
    )


def mac_cost(n: int = 20_000) -> dict[str, float]:
    """Microseconds to seal one Ping datagram and to check one (median of batches), and its size."""
    cfg = _private_cfg(tempfile.mkdtemp(prefix="gwc-bench-keys-"))
    keys.new(cfg)
    log = logging.getLogger("gwc.bench")
    sender, receiver = (
        Guard(cfg, "bench.a", log, collections.Counter()),
        Guard(cfg, "bench.b", log, collections.Counter()),
    )
    body = wire.encode(
        wire.Envelope(
            kind="msg", src="bench.a", inc=7, seq=1, conv="bench.a.7.1", cls=Conv.PING, msg=Msg.PING, fields={"n": 1}
        )
    )
    batch = 500
    seal_us, check_us = [], []
    for _ in range(max(1, n // batch)):
        t0 = time.perf_counter()
        sealed = [sender.seal(body) for _ in range(batch)]
        t1 = time.perf_counter()
        for data in sealed:
            receiver.open(data, False, "bench")
        t2 = time.perf_counter()
        seal_us.append((t1 - t0) / batch * 1e6)
        check_us.append((t2 - t1) / batch * 1e6)
    shutil.rmtree(Path(cfg.key_file or "").parent, ignore_errors=True)
    assert not receiver.stats, f"the bench's own datagrams were refused: {dict(receiver.stats)}"
    return {
        "seal_us": round(statistics.median(seal_us), 2),
        "check_us": round(statistics.median(check_us), 2),
        "bytes": auth.SEAL_BYTES,
    }


def bytecodes(n: int = 1000, warm: int = 300) -> dict[str, Any]:
    """What a PING round trip costs the interpreter, counted, not timed: the Python bytecodes and calls
    it executes per function (`file:function` -> [bytecodes, calls] a round trip), both sides in this
    process over the in-memory transport (sys.settrace opcode events over `n` round trips after `warm`).
    The ack and retransmission timers are set long, so that only the round trip's own work is counted
    (acks ride on the msgs): deterministic, so a change can be read on a loaded machine."""
    from gwc.ipc.memory import MemoryTransport

    key_dir = tempfile.mkdtemp(prefix="gwc-bench-keys-")
    cfg = replace(_private_cfg(key_dir), ack_timeout=60.0, retry_deadline=120.0)
    keys.new(cfg)
    ops: collections.Counter[str] = collections.Counter()
    calls: collections.Counter[str] = collections.Counter()

    def tracer(frame: Any, event: str, arg: Any) -> Any:
        code = frame.f_code
        where = f"{code.co_filename.rsplit('/', 1)[-1]}:{code.co_name}"
        if event == "call":
            frame.f_trace_opcodes = True
            calls[where] += 1
        elif event == "opcode":
            ops[where] += 1
        return tracer

    async def main() -> None:
        log = logging.getLogger("gwc.bench")
        server = Bus(SERVER, cfg, log, [Conv.PING], transport=MemoryTransport(cfg))
        client = _BusClient(cfg)
        client.bus = Bus("bench.cli", cfg, log, [], transport=MemoryTransport(cfg))
        await server.sign_on(settle=0)
        stopped = asyncio.get_running_loop().create_future()
        server.accept(lambda conv: _answer(conv, stopped))
        try:
            await client.ready()
            for i in range(warm):
                await client.ping(i)
            sys.settrace(tracer)
            try:
                for i in range(n):
                    await client.ping(i)
            finally:
                sys.settrace(None)
        finally:
            await client.close()
            await server.close()

    try:
        eventloop.run(main())
    finally:
        shutil.rmtree(key_dir, ignore_errors=True)
    per = {k: [round(v / n, 1), round(calls[k] / n, 2)] for k, v in ops.most_common()}
    return {"bytecodes": round(sum(ops.values()) / n), "calls": round(sum(calls.values()) / n, 1), "per_function": per}


# ----------------------------------------------------------------------------- servers


async def _serve_bus(cfg: BusConfig) -> None:
    bus = Bus(SERVER, cfg, logging.getLogger("gwc.bench"), [Conv.PING])
    await bus.sign_on(settle=0)
    stopped = asyncio.get_running_loop().create_future()
    bus.accept(lambda conv: _answer(conv, stopped))
    await stopped
    await bus.close()


def _answer(conv: Conversation, stopped: asyncio.Future[None]) -> None:
    """A Ping answered at once, on the bus's loop, as a handler that needs no database answers
    (Bus.accept): no task, no loop turn between the Ping and its Pong."""
    assert conv.first is not None
    first = conv.first.first
    if first.fields.get("payload") == "stop":  # (not first.payload: an absent field's read raises inside)
        if not stopped.done():
            stopped.set_result(None)
    else:
        conv.reply(message(Msg.PONG, n=first.n))
    conv.end()


def _serve_bare(cfg: BusConfig) -> None:
    sock = open_socket(cfg)
    sock.setblocking(True)
    me = os.getpid().to_bytes(4, "big")
    while True:
        data = sock.recv(2048)
        if data[:1] == b"Q":  # a ping from the client: answer with R + the same payload
            sock.sendto(b"R" + me + data[5:], (cfg.group, cfg.port))
        elif data[:1] == b"X":
            return


class _Reader(asyncio.DatagramProtocol):
    """Hands each datagram the loop reads to on_datagram: the way the bus reads its socket
    (gwc/ipc/transport.py), so that this mode shows what the loop costs and nothing else."""

    def __init__(self, on_datagram: Any) -> None:
        self.on_datagram = on_datagram

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.on_datagram(data)


async def _endpoint(sock: socket.socket, on_datagram: Any) -> asyncio.DatagramTransport:
    """The loop reading `sock` (which it owns from here: closing the endpoint closes it)."""
    endpoint, _ = await asyncio.get_running_loop().create_datagram_endpoint(lambda: _Reader(on_datagram), sock=sock)
    return endpoint


async def _serve_asyncio(cfg: BusConfig) -> None:
    """The bare ping-pong with one asyncio loop a side and nothing else: what asyncio alone costs."""
    loop = asyncio.get_running_loop()
    done = loop.create_future()
    dest = (cfg.group, cfg.port)
    sock = open_socket(cfg)

    def on_datagram(data: bytes) -> None:
        if data[:1] == b"Q":
            sock.sendto(b"R" + data[1:], dest)
        elif data[:1] == b"X" and not done.done():
            done.set_result(None)

    endpoint = await _endpoint(sock, on_datagram)
    try:
        await done
    finally:
        endpoint.close()


# ----------------------------------------------------------------------------- clients
# Each client: ready() (wait for its server), ping(i) (one round trip), stop(), close(). The run
# interleaves them in rounds, so a load change on a shared machine hits all three alike.


class _BareClient:
    def __init__(self, cfg: BusConfig) -> None:
        self.sock = open_socket(cfg)
        self.sock.setblocking(True)
        self.sock.settimeout(2.0)
        self.dest = (cfg.group, cfg.port)

    def _ping(self, i: int) -> None:
        self.sock.sendto(b"Q\0\0\0\0" + i.to_bytes(8, "big"), self.dest)

    def _pong(self) -> int:
        while True:  # our own pings loop back to us: skip them
            data = self.sock.recv(2048)
            if data[:1] == b"R":
                return int.from_bytes(data[5:13], "big")

    async def ready(self) -> None:
        deadline = Deadline(20)
        while True:
            try:
                self._ping(0)
                self._pong()
                return
            except TimeoutError:
                if deadline.expired:
                    raise GwcError("bare bench server did not answer within 20s") from None

    async def ping(self, i: int) -> None:
        self._ping(i)
        got = self._pong()
        if got != i:
            raise GwcError(f"bare bench: answer {got} to ping {i} (a datagram was lost)")

    async def rate(self, n: int, window: int) -> float:
        t0 = time.perf_counter()
        sent = min(window, n)
        for i in range(sent):
            self._ping(i)
        for _ in range(n):
            self._pong()
            if sent < n:
                self._ping(sent)
                sent += 1
        return n / (time.perf_counter() - t0)

    async def stop(self) -> None:
        self.sock.sendto(b"X", self.dest)

    async def close(self) -> None:
        self.sock.close()


def _expire(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_exception(TimeoutError())


class _AsyncioClient:
    def __init__(self, cfg: BusConfig) -> None:
        self.cfg = cfg
        self.dest = (cfg.group, cfg.port)
        self.waiting: dict[int, asyncio.Future[None]] = {}
        self.sock: socket.socket | None = None
        self.endpoint: asyncio.DatagramTransport | None = None

    def _on_datagram(self, data: bytes) -> None:
        if data[:1] == b"R":
            fut = self.waiting.pop(int.from_bytes(data[5:13], "big"), None)
            if fut is not None and not fut.done():
                fut.set_result(None)

    async def ready(self) -> None:
        self.sock = open_socket(self.cfg)
        self.endpoint = await _endpoint(self.sock, self._on_datagram)
        deadline = Deadline(20)
        while True:
            try:
                await self.ping(0, 0.5)
                return
            except TimeoutError:
                if deadline.expired:
                    raise GwcError("asyncio bench server did not answer within 20s") from None

    async def ping(self, i: int, timeout: float = 2.0) -> None:
        loop = asyncio.get_running_loop()
        fut = self.waiting[i] = loop.create_future()
        assert self.sock is not None
        self.sock.sendto(b"Q\0\0\0\0" + i.to_bytes(8, "big"), self.dest)
        timer = loop.call_later(timeout, _expire, fut)  # one timer, as the bus has for its waits: no wait_for task
        try:
            await fut
        finally:
            timer.cancel()
            self.waiting.pop(i, None)

    async def rate(self, n: int, window: int) -> float:
        return await _windowed(self.ping, n, window)

    async def stop(self) -> None:
        if self.sock is not None:
            self.sock.sendto(b"X", self.dest)

    async def close(self) -> None:
        if self.endpoint is not None:
            self.endpoint.close()


class _BusClient:
    def __init__(self, cfg: BusConfig) -> None:
        self.bus = Bus(f"bench.cli.{os.getpid()}", cfg, logging.getLogger("gwc.bench"), [])

    async def ready(self) -> None:
        await self.bus.sign_on(settle=0)
        deadline = Deadline(20)
        while SERVER not in self.bus.peers():
            if deadline.expired:
                raise GwcError("bench server did not appear on the bus within 20s")
            await asyncio.sleep(0.01)

    async def ping(self, i: int) -> None:
        conv, batch = await self.bus.request(Conv.PING, message(Msg.PING, n=i), to=SERVER)
        conv.end()
        if batch.first.n != i:
            raise GwcError(f"bench: answer {batch.first.n} to request {i}")

    async def rate(self, n: int, window: int) -> float:
        return await _windowed(self.ping, n, window)

    def datagrams(self) -> tuple[int, int]:
        """Datagrams this side has sent (sealed) and read on the bus port so far."""
        s = self.bus.stats
        return self.bus.guard.sealed, s["msg"] + s["ack"] + s["hello"] + s["bye"]

    async def stop(self) -> None:
        await self.bus.start(Conv.PING, message(Msg.PING, n=0, payload="stop"), to=SERVER)

    async def close(self) -> None:
        await self.bus.close()


async def _windowed(ping: Any, n: int, window: int) -> float:
    """Conversations per second with `window` of them in flight."""
    todo = iter(range(n))

    async def worker() -> None:
        for i in todo:
            await ping(i)

    t0 = time.perf_counter()
    await asyncio.gather(*(worker() for _ in range(window)))
    return n / (time.perf_counter() - t0)


class _Client(Protocol):
    """What every client side of the benchmark does (the three modes measure the same round trip)."""

    async def ready(self) -> None: ...
    async def ping(self, i: int) -> None: ...
    async def rate(self, n: int, window: int) -> float: ...
    async def stop(self) -> None: ...
    async def close(self) -> None: ...


CLIENTS: dict[str, Callable[[BusConfig], _Client]] = {"bare": _BareClient, "asyncio": _AsyncioClient, "bus": _BusClient}
ROUNDS = 10


async def _measure(
    cfgs: dict[str, BusConfig], servers: dict[str, int], n: int, window: int
) -> dict[str, dict[str, Any]]:
    clients = {mode: CLIENTS[mode](cfgs[mode]) for mode in MODES}
    rtt: dict[str, list[float]] = {mode: [] for mode in MODES}
    # CPU each side spends per round trip, summed over the rounds: a round trip's time is both sides'
    # CPU plus the wakeups between them, so this shows where it goes.
    cpu = {mode: [0.0, 0.0] for mode in MODES}  # client, server
    rates: dict[str, float] = {}
    sent_read = [0, 0]  # bus mode: datagrams the client sent and read during the rounds
    me = os.getpid()
    per_round = max(1, n // ROUNDS)
    try:
        for c in clients.values():
            await c.ready()
            for i in range(200):  # warm up
                await c.ping(i)
        for r in range(ROUNDS):
            for mode, c in clients.items():
                d0 = c.datagrams() if isinstance(c, _BusClient) else (0, 0)
                c0, s0 = cpu_s(me), cpu_s(servers[mode])
                for i in range(r * per_round, (r + 1) * per_round):
                    t0 = time.perf_counter()
                    await c.ping(i)
                    rtt[mode].append((time.perf_counter() - t0) * 1e6)
                cpu[mode][0] += cpu_s(me) - c0
                cpu[mode][1] += cpu_s(servers[mode]) - s0
                if isinstance(c, _BusClient):
                    d1 = c.datagrams()
                    sent_read[0] += d1[0] - d0[0]
                    sent_read[1] += d1[1] - d0[1]
        for mode, c in clients.items():
            rates[mode] = await c.rate(n, window)
            await c.stop()
    finally:
        for c in clients.values():
            await c.close()
    return {
        mode: {
            "rtt": rtt[mode],
            "rate": rates.get(mode, 0.0),
            "cpu_us": [t / (per_round * ROUNDS) * 1e6 for t in cpu[mode]],
            "datagrams": [d / (per_round * ROUNDS) for d in sent_read] if mode == "bus" else None,
        }
        for mode in MODES
    }


def _spawn(mode: str, cfg: BusConfig, pin: bool, peer: tuple[str, str] | None) -> subprocess.Popen[bytes]:
    """One server; with `peer` (its namespace and address), on that other host."""
    where = ["ip", "netns", "exec", peer[0]] if peer else []
    return subprocess.Popen(
        [
            *where,
            sys.executable,
            "-m",
            "gwc.bench.bus",
            "--serve",
            mode,
            "--group",
            cfg.group,
            "--port",
            str(cfg.port),
            "--keys",
            str(Path(cfg.key_file or "").parent),
            "--interface",
            peer[1] if peer else cfg.interface,
            *(["--pin"] if pin else []),
        ],
        stdin=subprocess.DEVNULL,
    )


def _private_cfg(key_dir: str, interface: str = "127.0.0.1") -> BusConfig:
    rnd = random.Random()
    group = f"239.255.{rnd.randrange(1, 255)}.{rnd.randrange(1, 255)}"
    return _cfg(group, rnd.randrange(20000, 60000), key_dir, interface)


def run(
    n: int = 5000, window: int = 16, pin: bool = True, interface: str = "127.0.0.1", peer: tuple[str, str] | None = None
) -> dict[str, Any]:
    """All three measurements, each against its own server process; figures in microseconds.
    With `peer` (a namespace and its address), the servers run on that host and this client's bus is
    on `interface`."""
    key_dir = tempfile.mkdtemp(prefix="gwc-bench-keys-")
    cfgs = {mode: _private_cfg(key_dir, interface) for mode in MODES}
    keys.new(cfgs["bus"])
    mask = os.sched_getaffinity(0)
    servers = {mode: _spawn(mode, cfgs[mode], pin, peer) for mode in MODES}
    if pin:
        pin_cpu(0)
    try:
        raw = eventloop.run(_measure(cfgs, {mode: p.pid for mode, p in servers.items()}, n, window))
        for server in servers.values():
            server.wait(10)
    finally:
        shutil.rmtree(key_dir, ignore_errors=True)
        os.sched_setaffinity(0, mask)
        for server in servers.values():
            if server.poll() is None:
                server.kill()
                server.wait()
    results: dict[str, Any] = {}
    for mode in MODES:
        s = summary(raw[mode]["rtt"])
        results[mode] = {
            "median_us": round(s["median"], 1),
            "p99_us": round(s["p99"], 1),
            "mean_us": round(s["mean"], 1),
            "n": s["n"],
            "conversations_per_s": round(raw[mode]["rate"]),
            "window": window,
            "client_cpu_us": round(raw[mode]["cpu_us"][0], 1),
            "server_cpu_us": round(raw[mode]["cpu_us"][1], 1),
        }
    results["ratio_median"] = round(results["bus"]["median_us"] / results["bare"]["median_us"], 2)
    results["ratio_p99"] = round(results["bus"]["p99_us"] / results["bare"]["p99_us"], 2)
    results["asyncio_ratio_median"] = round(results["asyncio"]["median_us"] / results["bare"]["median_us"], 2)
    sent, read = raw["bus"]["datagrams"]
    # What the client sent is what the server read, and the other way round (the kernel keeps the rest away).
    results["bus"]["datagrams_per_round_trip"] = {"to_server": round(sent, 3), "to_client": round(read, 3)}
    results["mac"] = mac_cost()
    return results


@click.command("bus")
@click.option("-n", "count", default=5000, show_default=True, help="Round trips measured (after 200 warm-up).")
@click.option("--window", default=16, show_default=True, help="Conversations in flight for the rate measurement.")
@click.option(
    "--pin/--no-pin",
    default=True,
    show_default=True,
    help="Put client and server on different CPUs (both modes alike).",
)
@click.option("--hosts", is_flag=True, help="Between two namespace hosts over veth (root), not on loopback.")
@click.option(
    "--bytecodes", "count_bytecodes", is_flag=True, help="Count a round trip's Python bytecodes per function instead."
)
@click.option("--json", "as_json", is_flag=True, help="Print JSON for machines.")
def command(count: int, window: int, pin: bool, hosts: bool, count_bytecodes: bool, as_json: bool) -> None:
    """Bus request->reply round trip (median, p99) and conversations/s, beside bare multicast UDP."""
    if count_bytecodes:
        b = bytecodes(min(count, 2000))
        if as_json:
            click.echo(json.dumps(b, indent=1))
            return
        click.echo(f"a PING round trip, both sides: {b['bytecodes']} bytecodes, {b['calls']} Python calls")
        for where, (ops, calls) in list(b["per_function"].items())[:40]:
            click.echo(f"{ops:8.1f} {calls:6.2f}  {where}")
        return
    r = _between_hosts(count, window, pin) if hosts else run(count, window, pin)
    if as_json:
        click.echo(json.dumps(r, indent=1))
        return
    click.echo(f"{'':7} {'median us':>10} {'p99 us':>10} {'conv/s':>10} {'CPU us per round trip':>24}")
    click.echo(f"{'':7} {'':>10} {'':>10} {'':>10} {'client':>11} {'server':>12}")
    for mode in MODES:
        m = r[mode]
        click.echo(
            f"{mode:7} {m['median_us']:>10.1f} {m['p99_us']:>10.1f} {m['conversations_per_s']:>10} "
            f"{m['client_cpu_us']:>11.1f} {m['server_cpu_us']:>12.1f}"
        )
    click.echo(
        f"bus/bare: median x{r['ratio_median']}, p99 x{r['ratio_p99']} (target: median within x3); "
        f"asyncio alone/bare: median x{r['asyncio_ratio_median']}"
    )
    mac = r["mac"]
    dg = r["bus"]["datagrams_per_round_trip"]
    click.echo(
        f"authentication (on in bus mode): seal {mac['seal_us']:.2f} us, check {mac['check_us']:.2f} us per "
        f"datagram, {mac['bytes']} bytes; a round trip took {dg['to_server']:.2f} datagrams to the server and "
        f"{dg['to_client']:.2f} back (each sealed by its sender, checked by its addressee; acks ride on the msgs)"
    )


def _between_hosts(count: int, window: int, pin: bool) -> dict[str, Any]:
    """The measurement with the client on host h1 and the servers on h2: this command again, in h1."""
    why = netns.unavailable()
    if why:
        raise GwcError(f"gwc bench bus --hosts: {why}")
    with netns.Hosts(2) as hosts:
        h1, h2 = hosts.hosts
        argv = [sys.executable, "-m", "gwc.bench.bus", "--client", "-n", str(count), "--window", str(window)]
        argv += ["--interface", h1.address, "--peer", f"{h2.netns}:{h2.address}", *(["--pin"] if pin else [])]
        out = subprocess.run(h1.argv(argv), capture_output=True, text=True, timeout=600)
        if out.returncode != 0:
            raise GwcError(f"gwc bench bus --hosts: the client in {h1.netns} failed: {out.stderr.strip()[-400:]}")
    return {**json.loads(out.stdout), "between": f"{h1.name} {h1.address} -> {h2.name} {h2.address} (veth)"}


def _main() -> None:
    ap = argparse.ArgumentParser(description="gwc bench bus server process (or, with --client, the client)")
    ap.add_argument("--serve", choices=MODES)
    ap.add_argument("--client", action="store_true", help="run the measurement, print JSON (for --hosts)")
    ap.add_argument("-n", type=int, default=5000)
    ap.add_argument("--window", type=int, default=16)
    ap.add_argument("--peer", help="NETNS:ADDRESS of the servers' host")
    ap.add_argument("--group")
    ap.add_argument("--port", type=int)
    ap.add_argument("--interface", default="127.0.0.1")
    ap.add_argument("--pin", action="store_true")
    ap.add_argument("--keys", help="the folder holding the bench cell's key files")
    args = ap.parse_args()
    if args.client:
        ns, _, address = (args.peer or "").partition(":")
        result = run(args.n, args.window, args.pin, args.interface, (ns, address) if args.peer else None)
        sys.stdout.write(json.dumps(result) + "\n")
        return
    cfg = _cfg(args.group, args.port, args.keys, args.interface)
    if args.pin:
        pin_cpu(1)
    if args.serve == "bus":
        eventloop.run(_serve_bus(cfg))
    elif args.serve == "asyncio":
        eventloop.run(_serve_asyncio(cfg))
    else:
        _serve_bare(cfg)


if __name__ == "__main__":
    _main()
