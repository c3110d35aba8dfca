"""What the web pages show, read from the tables with the Human Interface's own read functions
(gwc.client), on one connection of the web module's (role gwc_hi) used by one thread at a time, and
what they do, as conversations on the module's bus (as the OPC UA gateway holds them) or through the
HI's own client code in a thread (Work Order Entry)."""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable
from typing import Any, TypeVar

import psycopg

from gwc import db
from gwc.client.alarms import alarm_rows
from gwc.client.machines import machine_rows
from gwc.client.orders import LOTS_SQL, list_orders, script_alive
from gwc.client.requests import request_tables
from gwc.client.session import rows_of
from gwc.config import Config
from gwc.errors import DatabaseError, DatabaseUnavailable

T = TypeVar("T")
LOTS_SHOWN = 300  # the dispatch list shows the newest this many entities


class Reader:
    """One database connection (gwc_hi) for the web module, remade after a failure; every use runs in
    a worker thread under a lock, so the event loop serving pages never waits for PostgreSQL."""

    def __init__(self, cfg: Config, log: logging.Logger) -> None:
        self.cfg = cfg
        self.log = log
        self._conn: psycopg.Connection[Any] | None = None
        self._lock = threading.Lock()

    def _run(self, fn: Callable[[psycopg.Connection[Any]], T]) -> T:
        with self._lock:
            if self._conn is None or self._conn.closed:
                self._conn = db.connect(self.cfg, role="hi", log=self.log, attempts=1)
            try:
                return fn(self._conn)
            except psycopg.OperationalError as e:
                self._conn.close()
                self._conn = None
                raise DatabaseUnavailable(f"the cell database is away: {e}") from e
            except psycopg.Error as e:
                self._conn.rollback()
                raise DatabaseError(str(e)) from e

    async def run(self, fn: Callable[[psycopg.Connection[Any]], T]) -> T:
        return await asyncio.to_thread(self._run, fn)

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()


def plain(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows as JSON takes them (times as text)."""
    return [
        {k: (v if v is None or isinstance(v, (str, int, float, bool)) else str(v)) for k, v in r.items()} for r in rows
    ]


def read_view(cfg: Config, log: logging.Logger, conn: psycopg.Connection[Any], topic: str, peers: set[str]) -> Any:
    """One topic of the pages: machines, alarms, lots, orders, requests, order_form, record, spc."""
    if topic == "machines":
        return plain(machine_rows(conn, cfg, peers))
    if topic == "alarms":
        return plain(alarm_rows(conn))
    if topic == "lots":  # the dispatch list's newest LOTS_SHOWN entities (list_lots reads them all)
        rows = rows_of(conn, LOTS_SQL + " ORDER BY s.entity_id DESC LIMIT %s", LOTS_SHOWN)
        for r in rows:
            r["script"] = script_alive(cfg, r["entity"], r.pop("script_pid"))
        return plain(rows[::-1])
    if topic == "orders":
        return plain(list_orders(cfg, log, conn=conn))
    if topic == "requests":
        waiting, reserved, telling = request_tables(conn)
        return {"waiting": plain(waiting), "reserved": plain(reserved), "telling": plain(telling)}
    if topic == "order_form":
        customers = [r[0] for r in conn.execute("select customer_id from customers order by 1")]
        products = [
            r[0] for r in conn.execute("select product_id from products where script_id is not null order by 1")
        ]
        conn.rollback()
        return {"customers": customers, "products": products}
    if topic == "record":  # the OEE, timeline and downtime pages' live window (gwc.web.record)
        from gwc.web import record

        return record.record_view(cfg, conn, *record.window(cfg, None, None))
    if topic == "spc":
        from gwc.web import record

        return record.spc_view(cfg, conn)
    raise ValueError(f"no topic {topic!r}")


TOPICS = ("machines", "alarms", "lots", "orders", "requests")
# Topics dearer to read (an OEE over hours, every control chart): read when something touched them at
# most every first seconds, and at least every second seconds, while a page is open.
SLOW_TOPICS: dict[str, tuple[float, float]] = {"record": (5.0, 30.0), "spc": (5.0, 60.0)}
