"""A bus peer for the bus's end-to-end tests, run as its own process: `python -m tests.buspeer NAME`.

It answers PING conversations (Ping -> Pong with the same n, one Pong per Ping of the batch, in
order) and MACH_REQ batches (Machine_Req_Ack whose note lists the Machine_Entry ids in the order they
came), records every conversation it is given, and obeys a few commands carried in a Ping's payload:

    report            answer with a JSON summary (last conversations seen, actions taken, bus stats)
    interest:+CLS     listen to CLS from now on (interest:-CLS: stop)
    silent            never answer (for timeout tests)
    nest:NAME         before answering, ask module NAME a `leaf` Ping and wait for its answer
    leaf              answer at once

Each conversation runs as its own task, as gwc.module does, so a peer waiting inside `nest` still
serves the other side's conversations.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import json
import signal
from typing import Any

from gwc.config import load_config
from gwc.ipc.bus import Bus, Conversation
from gwc.ipc.catalogue import message
from gwc.log import open_log


class Peer:
    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self.seen: list[tuple[str, str, list[Any]]] = []  # (class, initiator, [n or machine_id, ...])
        self.actions: collections.Counter[str] = collections.Counter()  # conv id -> times acted on

    async def serve(self, conv: Conversation) -> None:
        assert conv.first is not None
        msgs = conv.first.messages
        try:
            if conv.cls == "MACH_REQ":
                ids = [m.machine_id for m in msgs[1:]]
                self.seen.append((conv.cls, conv.initiator, ids))
                self.actions[conv.id] += 1
                await conv.send(message("Machine_Req_Ack", ack_code="ACK_OK", note=",".join(ids)))
                return
            payload = msgs[0].fields.get("payload") or ""
            self.seen.append((conv.cls, conv.initiator, [m.fields.get("n") for m in msgs]))
            if conv.cls != "PING":
                return
            if payload == "report":
                report = {
                    "seen": self.seen[-50:],
                    "acted": len(self.actions),
                    "actions": sum(self.actions.values()),
                    "acted_twice": [c for c, k in self.actions.items() if k > 1],
                    "stats": dict(self.bus.stats),
                    "interest": sorted(self.bus.interests),
                    "peers": sorted(self.bus.peers()),
                }
                await conv.send(message("Pong", n=msgs[0].n, payload=json.dumps(report)))
                return
            if payload == "silent":
                return
            if payload.startswith("interest:"):
                change = payload.split(":", 1)[1]
                (self.bus.interest if change[0] == "+" else self.bus.no_interest)(change[1:])
            elif payload.startswith("nest:"):
                inner, answer = await self.bus.request(
                    "PING", message("Ping", n=msgs[0].n, payload="leaf"), to=payload[5:], timeout=20
                )
                inner.end()
            self.actions[conv.id] += 1
            await conv.send(*[message("Pong", n=m.n, payload=m.payload) for m in msgs])
        finally:
            conv.end()


async def main(name: str, interest: list[str]) -> None:
    cfg = load_config()
    log = open_log(name, cfg.log_dir, "note")
    bus = Bus(name, cfg.bus, log, interest)
    peer = Peer(bus)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    await bus.sign_on()
    tasks: set[asyncio.Task[None]] = set()
    stopper = loop.create_task(stop.wait())
    while not stop.is_set():
        getter = loop.create_task(bus.first_message())
        done, _ = await asyncio.wait({getter, stopper}, return_when=asyncio.FIRST_COMPLETED)
        if getter not in done:
            getter.cancel()
            break
        conv = getter.result()
        if conv is not None:
            task = loop.create_task(peer.serve(conv))
            tasks.add(task)
            task.add_done_callback(tasks.discard)
    for t in tasks:
        t.cancel()
    await bus.close()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("name")
    ap.add_argument("--interest", default="PING")
    args = ap.parse_args()
    asyncio.run(main(args.name, [c for c in args.interest.split(",") if c]))
