"""`gwc bench opcua`: the OPC UA gateway's change-to-notification latency, and its CPU, under load.

It runs `gwc bench cell` (its own private cell of dummy machines whose runs take no time, lots
going through as fast as the cell allows), attaches a gateway to that cell once its machines are up
(the bench cell's configuration plus an [opcua] section on a free port), and subscribes, as an OPC UA
client, to `--items` monitored items: ten variables of each machine (status, machine_run_id, the
Machinery states, counters, times, the last run). The latency of a change is from the Machine
Server's log entry of it ("wc3: Idle -> Setup", written as it commits the change and before it
broadcasts UPD_ME_ST) to the client's notification of the machine's new status, both on this host's
wall clock. (A listener on the bus in this process was tried first: under load its thread heard
changes seconds late, behind the client's, and gave negative latencies.) The gateway's CPU is its
utime + stime (/proc) over the window the lots run in.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import click
from asyncua import Client, Node, ua

from gwc.bench import brief, summary
from gwc.bench.logs import log_events
from gwc.client.session import bench_context
from gwc.config import load_config
from gwc.errors import GwcError
from gwc.ipc import BlockingBus
from gwc.ipc.names import Conv
from gwc.log import log_file_name
from gwc.module import module_name
from gwc.retry import Deadline
from gwc.soak.private_config import write_config

# Ten variables of each machine, the status first: what a dashboard of the cell would watch.
WATCHED = (
    "status",
    "machine_run_id",
    "MachineryItemState/CurrentState",
    "MachineryOperationMode/CurrentState",
    "runs",
    "runs_since_maintenance",
    "start_time",
    "end_time",
    "last_run/machine_run_id",
    "last_run/ack_code",
)
UP = 300.0  # the bench cell's start, the gateway's start, on a loaded machine


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _wait(predicate: Any, timeout: float, what: str, proc: subprocess.Popen[bytes]) -> Any:
    deadline = Deadline(timeout)
    while not (value := predicate()):
        if proc.poll() is not None:
            raise GwcError(f"gwc bench cell ended (exit {proc.returncode}) before {what}")
        if deadline.expired:
            raise GwcError(f"timed out after {timeout:.0f}s waiting for {what}")
        time.sleep(0.2)
    return value


class Notified:
    """asyncua subscription handler: each notification of a watched node, with when it came."""

    def __init__(self) -> None:
        self.seen: list[tuple[float, str, Any]] = []

    def datachange_notification(self, node: Node, val: Any, data: Any) -> None:
        self.seen.append((time.time(), str(node.nodeid.Identifier), val))


CHANGE = re.compile(r"^(\S+): (\S+) -> (\S+)")  # the Machine Server's entry of a status change


def changes(ms_log: Path) -> list[tuple[float, str, str]]:
    """(epoch, machine, status) of every status change the Machine Server logged."""
    return [(t, m.group(1), m.group(3)) for t, text in log_events(ms_log) if (m := CHANGE.match(text))]


EARLY = 0.01  # s a notification may precede its change's log entry (its time stamp has ms precision)


def latencies(
    heard: list[tuple[float, str, str]], seen: list[tuple[float, str, Any]]
) -> tuple[list[tuple[float, float]], int]:
    """For each status change, (when, time to its notification), and how many changes were never
    notified. Per machine, changes and notifications are walked in order: notifications older than
    the change are passed over (the initial values, a change seen already); the next one is the
    change's if it says the same status, else the change was never shown (a client may see two
    quick changes as one) and the notification is left to the change it belongs to."""
    notes: dict[str, list[tuple[float, Any]]] = {}
    for t, path, value in seen:
        if path.endswith("/status"):
            notes.setdefault(path.split("/")[1], []).append((t, value))
    out, missed = [], 0
    at = dict.fromkeys(notes, 0)
    for t, machine, status in sorted(heard):
        mine, j = notes.get(machine, []), at.get(machine, 0)
        while j < len(mine) and mine[j][0] < t - EARLY:
            j += 1
        at[machine] = j
        if j < len(mine) and mine[j][1] == status:
            out.append((t, mine[j][0] - t))
            at[machine] = j + 1
        else:
            missed += 1
    return out, missed


async def _client(endpoint: str, machines: list[str], items: int, interval: float, done: Any) -> Notified:
    client = Client(endpoint, timeout=30, watchdog_intervall=5.0)
    deadline = Deadline(UP)
    while True:
        try:
            await client.connect()
            break
        except (OSError, TimeoutError, ua.UaError):
            if deadline.expired:
                raise GwcError(f"the gateway did not listen at {endpoint} within {UP:.0f}s") from None
            await asyncio.sleep(0.5)
    try:
        ns = await client.get_namespace_index("urn:gwc:cell")
        paths = [f"machines/{m}/{v}" for v in WATCHED for m in machines][:items]
        note = Notified()
        sub = await client.create_subscription(interval * 1000, note)
        for i in range(0, len(paths), 50):
            await sub.subscribe_data_change(
                [client.get_node(ua.NodeId(ua.String(p), ua.Int16(ns))) for p in paths[i : i + 50]], queuesize=100
            )
        while not done():
            await asyncio.sleep(0.2)
        return note
    finally:
        await client.disconnect()


def run(log: logging.Logger, where: Path, machines: int, lots: int, items: int, interval: float) -> dict[str, Any]:
    if items > machines * len(WATCHED):
        raise GwcError(f"--items {items}: at most {len(WATCHED)} per machine ({machines * len(WATCHED)})")
    cell_var = where / "cell"
    shutil.rmtree(where, ignore_errors=True)
    where.mkdir(parents=True)
    bench_cmd = [sys.executable, "-m", "gwc", "bench", "cell", "--machines", str(machines), "--lots", str(lots)]
    bench_cmd += ["--solo", "0", "--deaths", "0", "--dir", str(cell_var), "--json"]
    with open(where / "bench-cell.out", "wb") as out:
        bench = subprocess.Popen(bench_cmd, stdout=out, stderr=subprocess.STDOUT, env=dict(os.environ))
    gateway: subprocess.Popen[bytes] | None = None
    bus: BlockingBus | None = None
    try:
        cell_toml = cell_var / "etc" / "cell.toml"
        _wait(cell_toml.exists, UP, "the bench cell's configuration", bench)
        cell = load_config(cell_toml)
        ids = [m.id for m in cell.machines]
        bus = BlockingBus(f"bench.opcua.{os.getpid()}", cell.bus, log)
        wcs = [module_name("wc", m) for m in ids]
        _wait(
            lambda: all(Conv.SETUP_RUN in (p.interest if (p := bus.peers().get(w)) else ()) for w in wcs),
            UP,
            "the bench cell's machines",
            bench,
        )
        endpoint = f"opc.tcp://127.0.0.1:{_free_port()}/gwc/"
        gw_cfg = write_config(where / "gateway.toml", {**cell.raw, "opcua": {"endpoint": endpoint}})
        env = dict(os.environ, GWC_CONFIG=str(gw_cfg.path), GWC_VAR=str(cell_var), PYTHONUNBUFFERED="1")
        with open(where / "gateway.out", "wb") as out:
            gateway = subprocess.Popen(
                [sys.executable, "-m", "gwc", "run", "opcua", "--start"], env=env, stdout=out, stderr=out
            )
        window: dict[str, float] = {}

        def done() -> bool:
            if "start" not in window:
                window.update(start=time.time(), cpu=_cpu_seconds(gateway.pid))
            if bench.poll() is None:
                return False
            window.update(end=time.time(), cpu=_cpu_seconds(gateway.pid) - window["cpu"])
            return True

        note = asyncio.run(_client(endpoint, ids, items, interval, done))
        ms_log = cell.log_dir / log_file_name("ms")
        heard = [h for h in changes(ms_log) if window["start"] <= h[0] <= window["end"]]
        lat, missed = latencies(heard, note.seen)
        seconds = window["end"] - window["start"]
        text = (where / "bench-cell.out").read_text()
        cell_result = json.loads(text[text.index("{") :]) if "{" in text else {}
        return {
            "machines": len(ids),
            "items": items,
            "publishing_interval_ms": interval * 1000,
            "seconds": seconds,
            "status_changes": len(heard),
            "notifications": len(note.seen),
            "missed": missed,
            "latency_ms": summary([x * 1000 for _, x in lat]),
            # the five slowest: seconds into the window, latency in ms (do they cluster?)
            "slowest": [
                (round(t - window["start"], 2), round(x * 1000, 1)) for t, x in sorted(lat, key=lambda p: -p[1])[:5]
            ],
            "gateway_cpu_s": window["cpu"],
            "gateway_cpu_pct": 100 * window["cpu"] / seconds if seconds else float("nan"),
            "lots_per_s": cell_result.get("lots_per_s"),
        }
    finally:
        if bus is not None:
            bus.close()
        if gateway is not None:
            gateway.terminate()
            try:
                gateway.wait(10)
            except subprocess.TimeoutExpired:
                gateway.kill()
        if bench.poll() is None:
            bench.terminate()
            bench.wait(60)


@click.command("opcua")
@click.option("--machines", type=int, default=10, show_default=True, help="Dummy machines of the bench cell.")
@click.option("--lots", type=int, default=300, show_default=True, help="Lots the bench cell runs meanwhile.")
@click.option("--items", type=int, default=100, show_default=True, help="Monitored items (10 per machine at most).")
@click.option("--interval", type=float, default=0.02, show_default=True, help="Publishing interval, seconds.")
@click.option("--where", type=click.Path(path_type=Path), help="State folder (default var/bench-opcua).")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
def command(machines: int, lots: int, items: int, interval: float, where: Path | None, as_json: bool) -> None:
    """The OPC UA gateway's change-to-notification latency (median, p99) for ITEMS monitored items,
    and its CPU, while `gwc bench cell` runs lots through a private cell."""
    cfg, log = bench_context()
    logging.getLogger("asyncua").setLevel(logging.ERROR)  # its notes on revised settings are not results
    result = run(log, (where or cfg.var / "bench-opcua").resolve(), machines, lots, items, interval)
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    click.echo(
        f"{result['items']} monitored items on {result['machines']} machines, publishing every "
        f"{result['publishing_interval_ms']:.0f} ms, {result['seconds']:.1f}s of `gwc bench cell` "
        f"({result['lots_per_s'] or 0:.2f} lots/s)"
    )
    click.echo(
        f"  status change (the Machine Server's log) to notification (ms): {brief(result['latency_ms'])}; "
        f"{result['status_changes']} changes, {result['missed']} not notified as such"
    )
    click.echo(f"  gateway CPU: {result['gateway_cpu_s']:.1f}s, {result['gateway_cpu_pct']:.0f}% of one core")
