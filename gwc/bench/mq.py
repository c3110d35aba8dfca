"""`gwc bench mq`: the WC<->ME round trip, beside a bare posix-ipc ping-pong in the same run.

Three measurements, each between this process and a real second process over a fresh queue pair:

* bare: raw 396-byte records bounced by a plain posix_ipc loop (`python -m gwc.bench.mq --serve`),
  no packing, no checks: the floor for two Python processes on POSIX queues;
* channel: gwc.ipc.mq records (packed, CRC-checked, seq) answered by the real dummy ME process
  (`gwc run me`), asked from a plain blocking loop;
* wc: the same ME asked the way the WC asks it (gwc.wc.link.MeLink: asyncio, the reader thread,
  answers matched by seq): the WC<->ME round trip the cell pays.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import click
import posix_ipc

from gwc.bench import pin_cpu, summary
from gwc.errors import GwcError, QueueTimeout
from gwc.ipc.codes import AckCode
from gwc.ipc.mq import LAYOUT_SIZE, Channel, MeMessage, MessageId, open_queue, queue_names, remove_queues
from gwc.soak.private_config import write_config
from gwc.wc.link import MeLink

WARMUP = 200
LOG = logging.getLogger("gwc.bench.mq")


def _serve_bare(prefix: str, machine: str) -> None:
    to_me, from_me = queue_names(prefix, machine)
    inq, outq = open_queue(to_me), open_queue(from_me)
    try:
        while True:
            data, _ = inq.receive(30)
            if data[:1] == b"X":
                return
            outq.send(data)
    finally:
        inq.close()
        outq.close()


def _bare(prefix: str, n: int) -> list[float]:
    machine = "bare"
    to_me, from_me = queue_names(prefix, machine)
    outq, inq = open_queue(to_me), open_queue(from_me)
    server = subprocess.Popen(
        [sys.executable, "-m", "gwc.bench.mq", "--serve", "--prefix", prefix, "--machine", machine],
        stdin=subprocess.DEVNULL,
        preexec_fn=_server_cpu,
    )
    try:
        record = bytes(LAYOUT_SIZE)
        rtt = []
        for i in range(WARMUP + n):
            t0 = time.perf_counter()
            outq.send(record)
            inq.receive(10)
            if i >= WARMUP:
                rtt.append((time.perf_counter() - t0) * 1e6)
        outq.send(b"X" + bytes(LAYOUT_SIZE - 1))
        server.wait(10)
        return rtt
    except posix_ipc.BusyError:
        raise GwcError("bare bench server did not answer within 10s") from None
    finally:
        if server.poll() is None:
            server.kill()
            server.wait()
        outq.close()
        inq.close()
        remove_queues(prefix, [machine])


def _channel(ch: Channel, n: int) -> list[float]:
    rtt = []
    for i in range(WARMUP + n):
        t0 = time.perf_counter()
        ch.send(MeMessage(MessageId.NO_MESSAGE, seq=i + 1))
        answer = ch.receive(10)
        if i >= WARMUP:
            rtt.append((time.perf_counter() - t0) * 1e6)
        if answer.seq != i + 1:
            raise GwcError(f"channel bench: answer {answer.seq} to request {i + 1}")
    return rtt


async def _wc(ch: Channel, n: int) -> list[float]:
    link = MeLink(ch, LOG)
    link.start(asyncio.get_running_loop())
    try:
        rtt = []
        for i in range(WARMUP + n):
            t0 = time.perf_counter()
            await link.request(MeMessage(MessageId.NO_MESSAGE), 10)
            if i >= WARMUP:
                rtt.append((time.perf_counter() - t0) * 1e6)
        return rtt
    finally:
        link.stop()


CPUS = sorted(os.sched_getaffinity(0))  # as started, before run() takes one of them for itself


def _server_cpu() -> None:
    pin_cpu(1, CPUS)  # in the server process, before it runs: every thread it starts stays there too


def run(n: int = 5000) -> dict[str, Any]:
    """The three measurements, this process on one CPU and the server on another; in microseconds."""
    prefix = f"/gwcbench.{os.getpid()}.{uuid.uuid4().hex[:6]}"
    pin_cpu(0, CPUS)
    try:
        return _run(prefix, n)
    finally:
        os.sched_setaffinity(0, CPUS)


def _run(prefix: str, n: int) -> dict[str, Any]:
    results: dict[str, Any] = {"bare": _bare(prefix, n)}
    var = Path(tempfile.mkdtemp(prefix="gwc-bench-mq-"))
    me: subprocess.Popen[bytes] | None = None
    prefix_me: str | None = None
    try:
        cfg_path = var / "etc" / "cell.toml"
        cfg = write_config(
            cfg_path,
            {
                "cell": {"name": "bench", "var": str(var)},
                "log": {"level": "warning"},
                "machine": [{"id": "bench", "kind": "dummy"}],
            },
        )
        prefix_me = cfg.ipc_prefix
        env = dict(os.environ, GWC_CONFIG=str(cfg_path), GWC_VAR=str(var))
        me = subprocess.Popen(
            [sys.executable, "-m", "gwc", "run", "me", "--machine", "bench"],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            preexec_fn=_server_cpu,
        )
        with Channel(cfg.ipc_prefix, "bench", "wc", LOG) as ch:
            ch.send(MeMessage(MessageId.ME_START, seq=2**31))
            try:
                started = ch.receive(30)
            except QueueTimeout:
                raise GwcError("the bench ME did not answer ME_START within 30s") from None
            if started.ack_code != AckCode.ACK_OK:
                raise GwcError(f"the bench ME refused ME_START: {started.describe()}")
            results["channel"] = _channel(ch, n)
        results["wc"] = asyncio.run(_wc(Channel(cfg.ipc_prefix, "bench", "wc", LOG), n))
    finally:
        if me is not None:
            me.terminate()
            try:
                me.wait(10)
            except subprocess.TimeoutExpired:
                me.kill()
                me.wait()
        if prefix_me is not None:
            remove_queues(prefix_me, ["bench"])
        shutil.rmtree(var, ignore_errors=True)
    out: dict[str, Any] = {}
    for name, rtt in results.items():
        s = summary(rtt)
        out[name] = {
            "median_us": round(s["median"], 1),
            "p99_us": round(s["p99"], 1),
            "mean_us": round(s["mean"], 1),
            "n": n,
        }
    out["ratio_median"] = round(out["wc"]["median_us"] / out["bare"]["median_us"], 2)
    out["ratio_p99"] = round(out["wc"]["p99_us"] / out["bare"]["p99_us"], 2)
    return out


@click.command("mq")
@click.option("-n", "count", default=5000, show_default=True, help="Round trips measured (after 200 warm-up).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON for machines.")
def command(count: int, as_json: bool) -> None:
    """WC<->ME round trip over the queue pair, beside a bare posix-ipc ping-pong."""
    import json

    r = run(count)
    if as_json:
        click.echo(json.dumps(r, indent=1))
        return
    click.echo(f"WC<->ME round trip, {count} requests, one at a time (microseconds)")
    click.echo(f"  {'':34} {'median':>8} {'p99':>8} {'mean':>8}")
    labels = {
        "bare": "bare posix_ipc ping-pong",
        "channel": "Channel -> dummy ME (blocking)",
        "wc": "WC (MeLink, asyncio) -> dummy ME",
    }
    for key, label in labels.items():
        row = r[key]
        click.echo(f"  {label:34} {row['median_us']:8.1f} {row['p99_us']:8.1f} {row['mean_us']:8.1f}")
    click.echo(f"  WC / bare: median x{r['ratio_median']}, p99 x{r['ratio_p99']}")


def _main() -> None:
    parser = argparse.ArgumentParser(description="gwc bench mq server side")
    parser.add_argument("--serve", action="store_true", required=True)
    parser.add_argument("--prefix", required=True)
    parser.add_argument("--machine", required=True)
    args = parser.parse_args()
    _serve_bare(args.prefix, args.machine)


if __name__ == "__main__":
    _main()
