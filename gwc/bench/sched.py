"""`gwc bench sched`: how fast MSCHED decides with a long queue, and how soon a freed machine is bound.

For each queue size a scratch database is made in the cell's PostgreSQL (the cell's own tables are
never touched), with 100 machines up and accepting, and a real MSCHED process runs on a private bus
group. This process plays the lot entities: 100 holders take every machine, then entities queue
the requested number of requests (a third of them with an alternative; a third of the
alternatives want two machines at once).

* Decisions per second: the holders free their machines; every entity bound acknowledges and frees
  its machines at once, so each binding frees the next; the first `--decisions` bindings are timed
  (at most half the queue, so the queue stays between its size and half of it).
* Free-to-bound latency: the cell at rest (every entity bound holds on), one holder at a time frees its
  machines; the time from sending Unreserve_Me to receiving the next entity's Machine_Req_Comp.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import click
import psycopg
from psycopg import sql

from gwc import db
from gwc.bench import cpu_s, summary
from gwc.client.session import bench_context
from gwc.config import Config
from gwc.errors import GwcError
from gwc.ipc import eventloop
from gwc.ipc.bus import Bus, Conversation
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode
from gwc.ipc.names import Conv, Msg
from gwc.log import open_log
from gwc.retry import Deadline
from gwc.soak.private_config import private_bus, write_config

OP = "dummy_op"
T = 60.0


@dataclass
class Result:
    queued: int
    machines: int
    decisions: int
    seconds: float
    policy: str
    cpu_s: float  # MSCHED's CPU time while the decisions were timed
    latencies_ms: list[float] = field(default_factory=list)

    @property
    def rate(self) -> float:
        return self.decisions / self.seconds if self.seconds else float("nan")

    def as_dict(self) -> dict[str, Any]:
        lat = summary(self.latencies_ms)
        return {
            "policy": self.policy,
            "queued": self.queued,
            "machines": self.machines,
            "decisions": self.decisions,
            "seconds": round(self.seconds, 3),
            "decisions_per_s": round(self.rate, 1),
            "msched_cpu_ms_per_decision": round(self.cpu_s * 1000 / self.decisions, 3) if self.decisions else None,
            "free_to_bound_median_ms": round(lat["median"], 3),
            "free_to_bound_p99_ms": round(lat["p99"], 3),
            "latency_samples": lat["n"],
        }


# ----------------------------------------------------------------------------- a scratch cell


def _scratch_url(url: str, dbname: str) -> str:
    info: dict[str, Any] = dict(psycopg.conninfo.conninfo_to_dict(url))
    info["dbname"] = dbname
    return psycopg.conninfo.make_conninfo(**info)


def _prepare(url: str, machines: list[str], entities: int) -> None:
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("insert into me_config (machine_id, kind) select unnest(%s::text[]), 'dummy'", (machines,))
        conn.execute("insert into machine_status (machine_id, status) select unnest(%s::text[]), 'Idle'", (machines,))
        conn.execute("insert into accept_types (machine_id, op_type) select unnest(%s::text[]), %s", (machines, OP))
        conn.execute("insert into lots (lot_id, product_id) values (1, 'alum_chess_set')")
        conn.execute(
            "insert into lot_entities (entity_id, lot_id) select g, 1 from generate_series(1, %s) g", (entities,)
        )
        conn.execute(
            "insert into lot_status (entity_id, lot_id, state) "
            "select g, 1, 'waiting_machine' from generate_series(1, %s) g",
            (entities,),
        )


def _bench_config(tmp: Path, url: str, level: str, policy: str) -> Config:
    cfg = write_config(
        tmp / "etc" / "cell.toml",
        {
            "cell": {"name": "bench", "var": str(tmp / "var"), "policy": policy},
            # The keys named, not left to var: GWC_VAR in the environment would put them elsewhere.
            "bus": private_bus(
                heartbeat=0.25,
                peer_timeout=3.0,
                key_file=str(tmp / "var" / "secrets" / "cell.key"),
                lot_key_file=str(tmp / "var" / "secrets" / "lot.key"),
            ),
            "database": {"url": url},
            "log": {"level": level},
        },
    )
    # The scratch cell's own var/ and database, whatever GWC_VAR / GWC_DATABASE_URL say.
    return dataclasses.replace(cfg, var=tmp / "var", database_url=url)


# ----------------------------------------------------------------------------- the entities


class Bench:
    """The lot entities, all played on one bus attachment."""

    def __init__(self, bus: Bus, machines: list[str], rng: random.Random) -> None:
        self.bus = bus
        self.machines = machines
        self.rng = rng
        self.looping = True
        self.decisions: list[float] = []
        self.target = 0
        self.enough = asyncio.Event()
        self.held: dict[int, list[str]] = {}
        self.watchers: list[tuple[set[str], asyncio.Future[float]]] = []
        self.sem = asyncio.Semaphore(100)
        self.last_comp = time.monotonic()
        self.acked = 0
        self.errors: list[str] = []

    def check(self, task: asyncio.Task[None]) -> None:
        """Done-callback of an entity: remember why it failed."""
        if not task.cancelled() and task.exception() is not None:
            self.errors.append(str(task.exception()))

    def alternatives(self) -> list[list[str]]:
        alts = 2 if self.rng.random() < 1 / 3 else 1
        return [self.rng.sample(self.machines, 2 if self.rng.random() < 1 / 3 else 1) for _ in range(alts)]

    async def ask(self, cls: str, first: Any) -> Any:
        conv, batch = await self.bus.request(cls, first, to="msched", timeout=T)
        conv.end()
        return batch.first

    async def request(self, entity: int, machines: list[str], priority: int) -> Conversation:
        async with self.sem:
            conv, batch = await self.bus.request(
                Conv.MACH_REQ,
                message(
                    Msg.MACHINE_REQUEST, entity_id=entity, op_type=OP, num_machines=len(machines), priority=priority
                ),
                *[message(Msg.MACHINE_ENTRY, machine_id=m) for m in machines],
                to="msched",
                timeout=T,
            )
        if batch.first.ack_code != AckCode.ACK_OK:
            raise GwcError(f"bench: request of entity {entity} refused: {batch.first.ack_code} {batch.first.note}")
        self.acked += 1
        return conv

    async def comp(self, entity: int, conv: Conversation) -> list[str]:
        batch = await conv.next_message(3600)
        now = time.monotonic()
        head = batch.first
        self.last_comp = now
        await conv.send(message(Msg.REQUEST_COMP_ACK, entity_id=entity, ack_code=AckCode.ACK_OK))
        conv.end()
        if head.ack_code != AckCode.ACK_OK:
            return []
        got = [m.machine_id for m in batch.messages[1:]]
        if self.looping:
            self.decisions.append(now)
            if len(self.decisions) >= self.target:
                self.enough.set()
        for watch, fut in self.watchers:
            if watch.intersection(got) and not fut.done():
                fut.set_result(now)
        return got

    async def life(self, entity: int, alts: list[list[str]], priority: int = 20) -> None:
        """Ask and get machines; while throughput is measured free them at once, else hold them."""
        convs = [await self.request(entity, a, priority) for a in alts]
        got = [m for ms in await asyncio.gather(*(self.comp(entity, c) for c in convs)) for m in ms]
        if self.looping:
            await self.ask(Conv.UNRESERVE, message(Msg.UNRESERVE_ME, entity_id=entity))
        else:
            self.held[entity] = got


async def _run(
    cfg: Config, url: str, queued: int, n_machines: int, decisions: int, samples: int, msched: int, log: Any
) -> Result:
    machines = [f"bm{i:03d}" for i in range(n_machines)]
    bus = Bus(f"bench.{os.getpid()}", cfg.bus, log)
    await bus.sign_on()
    bench = Bench(bus, machines, random.Random(5))
    tasks: list[asyncio.Task[None]] = []
    try:
        deadline = Deadline(T)
        while Conv.SHUTDOWN not in getattr(bus.peers().get("msched"), "interest", ()):
            if deadline.expired:
                raise GwcError("bench: msched did not start (see the bench's var/log)")
            await asyncio.sleep(0.05)
        # Holders take every machine.
        bench.looping = False
        holders = list(range(1, n_machines + 1))
        tasks += [asyncio.create_task(bench.life(e, [[m]])) for e, m in zip(holders, machines)]
        while len(bench.held) < n_machines:
            await asyncio.sleep(0.01)
        # The queue: entities with one or two alternatives, until `queued` requests wait.
        entity, n = n_machines, 0
        while n < queued:
            entity += 1
            alts = bench.alternatives()[: queued - n]
            n += len(alts)
            task = asyncio.create_task(bench.life(entity, alts, bench.rng.randint(1, 40)))
            task.add_done_callback(bench.check)
            tasks.append(task)
        deadline = Deadline(600)
        while bench.acked < queued + n_machines:
            if deadline.expired or bench.errors:
                raise GwcError(
                    f"bench: only {bench.acked - n_machines} of {queued} requests were queued "
                    f"({bench.errors[0] if bench.errors else 'too slow'})"
                )
            await asyncio.sleep(0.05)
        with psycopg.connect(url, autocommit=True) as conn:
            row = conn.execute("select count(distinct request_key) from request_machines").fetchone()
            in_queue = row[0] if row else 0
        # Throughput: free everything; every entity bound frees its machines at once.
        decisions = min(decisions, in_queue // 2)  # the queue stays at least half full while timed
        bench.looping = True
        bench.target = decisions
        cpu0 = cpu_s(msched)
        start = time.monotonic()
        for e in holders:
            del bench.held[e]
            tasks.append(asyncio.create_task(bench.ask(Conv.UNRESERVE, message(Msg.UNRESERVE_ME, entity_id=e))))
        await asyncio.wait_for(bench.enough.wait(), 600)
        took = bench.decisions[decisions - 1] - start
        cpu = cpu_s(msched) - cpu0
        bench.looping = False
        # Rest: wait until nothing has been bound for half a second (every entity bound holds on).
        while time.monotonic() - bench.last_comp < 0.5:
            await asyncio.sleep(0.1)
        # Latency: free one holder's machines at a time: the holder of the machine the oldest waiting
        # one-machine request wants, so that every sample frees a machine someone waits for.
        lat: list[float] = []
        with psycopg.connect(url, autocommit=True) as conn:
            for _ in range(samples):
                row = conn.execute(
                    "select r.entity_id from request_machines q "
                    "join reserved_machines r on r.machine_id = q.machine_id "
                    "where r.entity_id = any(%s) and not exists (select 1 from request_machines u "
                    "where u.request_key = q.request_key and u.machine_id <> q.machine_id) order by q.seq limit 1",
                    (sorted(bench.held),),
                ).fetchone()
                if row is None:
                    break
                lat += await _sample(bus, bench, int(row[0]))
        return Result(in_queue, n_machines, decisions, took, cfg.policy, cpu, lat)
    finally:
        for t in tasks:
            t.cancel()
        await bus.close(flush=0)


async def _sample(bus: Bus, bench: Bench, e: int) -> list[float]:
    """Free entity e's machines; the time until the next entity is told it has one, in ms."""
    freed = set(bench.held.pop(e))
    fut: asyncio.Future[float] = asyncio.get_running_loop().create_future()
    bench.watchers = [(freed, fut)]
    t0 = time.monotonic()
    conv = await bus.start(Conv.UNRESERVE, message(Msg.UNRESERVE_ME, entity_id=e), to="msched")
    try:
        t1 = await asyncio.wait_for(fut, T)
    finally:
        await conv.next_message(T)
        conv.end()
    return [(t1 - t0) * 1000]


def run_size(
    cfg: Config, log: Any, queued: int, n_machines: int, decisions: int, samples: int, level: str, policy: str = "fifo"
) -> Result:
    """One measurement on its own scratch database and MSCHED (the cell's server running)."""
    base_url = db.database_url(cfg)
    name = f"gwc_bench_{uuid.uuid4().hex[:10]}"
    url = _scratch_url(base_url, name)
    tmp = Path(tempfile.mkdtemp(prefix="gwc-bench-sched-"))
    proc: subprocess.Popen[bytes] | None = None
    with psycopg.connect(_scratch_url(base_url, "postgres"), autocommit=True) as admin:
        admin.execute(sql.SQL("create database {}").format(sql.Identifier(name)))
    try:
        bcfg = _bench_config(tmp, url, level, policy)
        db.init_schema(bcfg, log)
        _prepare(url, [f"bm{i:03d}" for i in range(n_machines)], n_machines + queued + 10)
        env = dict(
            os.environ, GWC_CONFIG=str(bcfg.path), GWC_VAR=str(bcfg.var), GWC_DATABASE_URL=url, PYTHONUNBUFFERED="1"
        )
        bcfg.var.mkdir(parents=True, exist_ok=True)
        with open(tmp / "msched.out", "wb") as out:
            proc = subprocess.Popen(
                [sys.executable, "-m", "gwc", "run", "msched", "--start"],
                env=env,
                stdout=out,
                stderr=out,
                stdin=subprocess.DEVNULL,
            )
        # On the cell's kind of loop (uvloop), as the lot scripts it plays run: on asyncio's own the
        # bench spent more CPU a decision than MSCHED, on the same two cores.
        return eventloop.run(
            _run(
                bcfg, url, queued, n_machines, decisions, samples, proc.pid, open_log("bench", bcfg.log_dir, "warning")
            )
        )
    finally:
        if proc is not None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        with psycopg.connect(_scratch_url(base_url, "postgres"), autocommit=True) as admin:
            admin.execute(sql.SQL("drop database if exists {} with (force)").format(sql.Identifier(name)))
        shutil.rmtree(tmp, ignore_errors=True)


@click.command("sched")
@click.option(
    "--queued", "sizes", default="1000,10000", show_default=True, help="Queue sizes to measure, comma-separated."
)
@click.option("--machines", "n_machines", default=100, show_default=True)
@click.option("--decisions", default=2000, show_default=True, help="Bindings timed per queue size.")
@click.option("--samples", default=200, show_default=True, help="Free-to-bound latency samples per size.")
@click.option("--level", default="note", show_default=True, help="MSCHED's log level during the run.")
@click.option("--policy", type=click.Choice(["fifo", "priority"]), default="fifo", show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print JSON for scripts.")
def command(sizes: str, n_machines: int, decisions: int, samples: int, level: str, policy: str, as_json: bool) -> None:
    """MSCHED: decisions per second and free-to-bound latency with 1,000 and 10,000 requests queued."""
    cfg, log = bench_context()
    try:
        qs = [int(s) for s in sizes.split(",") if s.strip()]
    except ValueError:
        raise click.BadParameter(f"--queued must be numbers, got {sizes!r}") from None
    # The embedded cluster is left as it was found: stopped again if this command started it.
    started = cfg.embedded and not db.cluster_running(cfg)
    if cfg.embedded:
        db.cluster_start(cfg, log)
    results = []
    try:
        for q in qs:
            if not as_json:
                click.echo(f"queue {q}: filling and measuring ...")
            results.append(run_size(cfg, log, q, n_machines, decisions, samples, level, policy).as_dict())
    finally:
        if started:
            db.cluster_stop(cfg, log)
    if as_json:
        click.echo(json.dumps(results, indent=1))
        return
    click.echo(
        f"{'queued':>8} {'machines':>8} {'decisions':>9} {'dec/s':>8} {'free->bound median ms':>22} "
        f"{'p99 ms':>8} {'samples':>7}"
    )
    for r in results:
        click.echo(
            f"{r['queued']:>8} {r['machines']:>8} {r['decisions']:>9} {r['decisions_per_s']:>8} "
            f"{r['free_to_bound_median_ms']:>22} {r['free_to_bound_p99_ms']:>8} {r['latency_samples']:>7}"
        )
