"""Work orders and lots: Work Order Entry (the order, CREATE_LOT, one lot script per entity), the
operator's decisions (IMPORT_LOT, EXPORT_LOT), and the reads behind Work Order Status and the Dispatch
List; the customers, products and lot scripts an order names."""

from __future__ import annotations

import logging
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import psycopg

from gwc import db
from gwc.cell import read_pid
from gwc.client.session import ask, hi_conn, need_server, rows_of
from gwc.config import PROJECT_ROOT, Config
from gwc.errors import GwcError, MessageError, Refused
from gwc.ipc import BlockingBus
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode, LotState
from gwc.ipc.names import Conv, Msg
from gwc.lot.admission import LotQueue
from gwc.lot.entity import create_lot, read_traveller
from gwc.lot.run import load_script, spawn_lot_script, spawn_lot_scripts
from gwc.servers.lot import MAX_QUANTITY

__all__ = [
    "add_customer",
    "create_lot",
    "decide",
    "enter_order",
    "list_customers",
    "list_lots",
    "list_orders",
    "list_products",
    "list_scripts",
    "order_status",
    "parse_due",
    "parse_items",
    "read_rows",
    "read_traveller",
    "register_script",
    "rows_of",
    "script_alive",
    "spawn_lot_script",
    "spawn_lot_scripts",
]


def parse_due(text: str | None, now: datetime | None = None) -> datetime | None:
    """A work order's due date (Figure 6.3's Date Due): `YYYY-MM-DD`, `YYYY-MM-DD HH:MM`, `now`, or from
    now: `+3d`, `+12h`, `+30m`; local time. None for None."""
    if text is None:
        return None
    now = now or datetime.now().astimezone()
    t = text.strip()
    if t == "now":
        return now
    if t.startswith("+") and t[1:-1].isdigit() and t[-1] in "dhm":
        return now + timedelta(**{{"d": "days", "h": "hours", "m": "minutes"}[t[-1]]: int(t[1:-1])})
    try:
        due = datetime.fromisoformat(t)
    except ValueError:
        raise GwcError(f"bad due date {text!r}: write YYYY-MM-DD, 'YYYY-MM-DD HH:MM', now, or +3d / +12h") from None
    return due if due.tzinfo else due.astimezone()


def parse_items(items: tuple[str, ...]) -> list[tuple[str, int]]:
    """PRODUCT=QTY arguments (QTY defaults to 1), each product once."""
    out: dict[str, int] = {}
    for item in items:
        product, sep, qty = item.partition("=")
        product = product.strip()
        try:
            n = int(qty) if sep else 1
        except ValueError:
            raise GwcError(f"bad order item {item!r}: write PRODUCT=QUANTITY, e.g. alum_chess_set=2") from None
        if not product or n <= 0:
            raise GwcError(f"bad order item {item!r}: write PRODUCT=QUANTITY with a quantity of 1 or more")
        out[product] = out.get(product, 0) + n
    if not out:
        raise GwcError("an order needs at least one PRODUCT=QUANTITY")
    return list(out.items())


INT4 = range(-(2**31), 2**31)  # what the lots table's int columns hold (priority)


def check_order(customer: str, items: list[tuple[str, int]], note: str | None, priority: int | None) -> None:
    """What the Lot Server and the tables will refuse, refused before the order is written: an order
    saved and then refused its lots would be left behind with none (GwcError naming what is wrong)."""
    if priority is not None and priority not in INT4:
        raise GwcError(f"priority {priority} is out of range ({INT4.start}..{INT4.stop - 1}; default 20)")
    for product, qty in items:
        if not 0 < qty <= MAX_QUANTITY:
            raise GwcError(f"{qty} x {product}: a lot holds 1..{MAX_QUANTITY} units; split the order")
        try:  # each lot's request, as it will be sent: its fields checked by the catalogue now
            message(Msg.CREATE_LOT_ENTITY, product_id=product, quantity=qty, work_order_id=1, owner=customer,
                    priority=priority, request_id="check")  # fmt: skip
        except MessageError as e:
            raise GwcError(f"{product}: {e}") from None
    if note is not None and "\0" in note:
        raise GwcError("the order's note holds a NUL byte")


def enter_order(
    cfg: Config,
    log: logging.Logger,
    bus: BlockingBus,
    customer: str,
    items: list[tuple[str, int]],
    note: str | None = None,
    priority: int | None = None,
    start_scripts: bool = True,
    due: datetime | None = None,
) -> dict[str, Any]:
    """Work Order Entry: checks the customer and products, writes the order (as gwc_hi, the owner of
    WORK_ORDERS), asks the Lot Server for each product's lot (CREATE_LOT, asked again while it is away),
    and starts one lot script process per entity. Returns the order, its lots, entities and pids.
    Everything is checked before the order is written (check_order, the customer, the products)."""
    check_order(customer, items, note, priority)
    with hi_conn(cfg, log) as conn:
        if not conn.execute("SELECT 1 FROM customers WHERE customer_id = %s", (customer,)).fetchone():
            known = ", ".join(r[0] for r in conn.execute("SELECT customer_id FROM customers ORDER BY 1")) or "none"
            raise GwcError(f"unknown customer {customer!r} (known: {known}; add one with `gwc customer add`)")
        for product, _ in items:
            row = conn.execute("SELECT script_id FROM products WHERE product_id = %s", (product,)).fetchone()
            if row is None:
                known = ", ".join(r[0] for r in conn.execute("SELECT product_id FROM products ORDER BY 1"))
                raise GwcError(f"unknown product {product!r} (known: {known})")
            if row[0] is None:
                raise GwcError(f"product {product!r} has no lot script: `gwc script register ... --product {product}`")
        conn.rollback()
        need_server(bus, "ls", "Lot Server")

        def write(cur: psycopg.Cursor[Any]) -> int:
            wo = db.get_new_max_value(cur, "WORK_ORDER")
            cur.execute(
                "INSERT INTO work_orders (work_order_id, customer_id, note, due_at) VALUES (%s, %s, %s, %s)",
                (wo, customer, note, due),
            )
            for product, qty in items:
                cur.execute(
                    "INSERT INTO work_order_items (work_order_id, product_id, quantity) VALUES (%s, %s, %s)",
                    (wo, product, qty),
                )
            return wo

        wo = db.transaction(conn, write, log=log)
    log.info("work order %d for %s: %s", wo, customer, ", ".join(f"{q} x {p}" for p, q in items))
    lots = []
    for product, qty in items:
        try:
            lot_id, entities = create_lot(bus, product, qty, work_order_id=wo, owner=customer, priority=priority)
        except GwcError as e:
            raise GwcError(f"work order {wo} was saved, but its lot of {product} was not created: {e}") from e
        pids: dict[int, int | None] = {}
        if start_scripts:
            pids = spawn_lot_scripts(cfg, entities)
            started = [e for e, pid in pids.items() if pid is not None]
            log.info(
                "lot %d: %d lot scripts started, %d queued (they start as others end)",
                lot_id,
                len(started),
                len(entities) - len(started),
            )
        lots.append(
            {"lot_id": lot_id, "product_id": product, "quantity": qty, "entities": entities, "script_pids": pids}
        )
    return {"work_order_id": wo, "customer_id": customer, "lots": lots}


def decide(bus: BlockingBus, entity_id: int, action: str, by: str) -> int | None:
    """IMPORT_LOT / EXPORT_LOT to the Lot Server: the operator lets an entity in or out; RELEASE_LOT
    (action retry, reroute or fail): a held entity goes on or fails (the Lot Server then tells the
    entity with LOT_MOVED). Returns its lot; Refused if the Lot Server says no."""
    cls = {"import": Conv.IMPORT_LOT, "export": Conv.EXPORT_LOT}.get(action, Conv.RELEASE_LOT)
    ack = ask(bus, cls, message(Msg.LOT_DECISION, entity_id=entity_id, action=action, by=by), "ls", None)
    if ack.ack_code == AckCode.UNKNOWN:
        raise GwcError(f"unknown lot entity {entity_id} (see `gwc lots`)")
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or f"cannot {action} entity {entity_id}")
    return ack.lot_id


ORDER_STATUS_SQL = """
SELECT w.work_order_id AS work_order, w.customer_id AS customer, c.name AS customer_name,
       to_char(w.created_at, 'YYYY-MM-DD HH24:MI:SS') AS created,
       to_char(w.due_at, 'YYYY-MM-DD HH24:MI:SS') AS due, w.due_at < now() AS overdue,
       (SELECT string_agg(i.quantity || ' x ' || i.product_id, ', ' ORDER BY i.product_id)
          FROM work_order_items i WHERE i.work_order_id = w.work_order_id) AS items,
       (SELECT json_object_agg(state, n) FROM (
            SELECT s.state, count(*) AS n FROM lots l JOIN lot_status s USING (lot_id)
            JOIN lot_entities e USING (entity_id)
            WHERE l.work_order_id = w.work_order_id AND e.destroyed_at IS NULL GROUP BY s.state) x) AS states,
       w.note
  FROM work_orders w LEFT JOIN customers c USING (customer_id)
"""


def order_status(states: dict[str, int] | None) -> str:
    """One word for an order (Figure 6.6's Status), from where its entities are."""
    states = states or {}
    total = sum(states.values())
    if not total:
        return "NEW"
    if states.get(LotState.CREATED, 0) == total:
        return "NEW"
    done = states.get(LotState.EXPORTED, 0) + states.get(LotState.FAILED, 0)
    if done == total:
        return "DONE" if not states.get(LotState.FAILED) else "DONE (with failures)"
    if states.get(LotState.WAITING_IMPORT, 0) + states.get(LotState.CREATED, 0) == total:
        return "WAITING IMPORT"
    return "RUNNING"


def read_rows(
    cfg: Config, log: logging.Logger, conn: psycopg.Connection[Any] | None, sql: str, *params: Any
) -> list[dict[str, Any]]:
    """rows_of on the caller's connection (a screen that stays open keeps one), or on a new one."""
    if conn is not None:
        return rows_of(conn, sql, *params)
    with hi_conn(cfg, log) as own:
        return rows_of(own, sql, *params)


def list_orders(
    cfg: Config, log: logging.Logger, work_order: int | None = None, conn: psycopg.Connection[Any] | None = None
) -> list[dict[str, Any]]:
    """Work Order Status (WOSU): every order (or one), its items, status and where its lots are."""
    where = " WHERE w.work_order_id = %s" if work_order is not None else ""
    rows = read_rows(
        cfg,
        log,
        conn,
        ORDER_STATUS_SQL + where + " ORDER BY w.work_order_id",
        *([work_order] if work_order is not None else []),
    )
    for r in rows:
        r["status"] = order_status(r["states"])
        if r.pop("overdue") and not r["status"].startswith("DONE"):
            r["status"] += " (LATE)"
        r["lots"] = ", ".join(f"{n} {s}" for s, n in sorted((r.pop("states") or {}).items()))
    return rows


LOTS_SQL = """
SELECT s.entity_id AS entity, s.lot_id AS lot, e.parent_entity_id AS parent, l.work_order_id AS work_order,
       l.product_id AS product,
       l.owner, l.priority, s.state, s.reason AS result, s.script_pid,
       to_char(s.updated_at, 'HH24:MI:SS') AS since
  FROM lot_status s JOIN lots l USING (lot_id) JOIN lot_entities e USING (entity_id)
 WHERE e.destroyed_at IS NULL
"""


def script_alive(cfg: Config, entity_id: int, pid: int | None) -> str:
    """The entity's lot script pid, and whether that process still runs; "queued" while it waits for a
    place (gwc/lot/admission.py)."""
    if entity_id in LotQueue(cfg.run_dir):
        return "queued"
    if pid is None:
        return "-"
    st = read_pid(cfg, f"lot:{entity_id}")
    alive = st.alive and st.pid == pid
    return f"{pid}" if alive else f"{pid} (ended)"


def list_lots(
    cfg: Config,
    log: logging.Logger,
    work_order: int | None = None,
    state: str | None = None,
    entity: int | None = None,
    conn: psycopg.Connection[Any] | None = None,
    changed_since: datetime | None = None,
) -> list[dict[str, Any]]:
    """The Dispatch List (DISP): every lot entity (or those of an order, a state, one entity, or changed
    since a time: a screen that stays open reads only what changed) and its script."""
    sql, params = LOTS_SQL, []
    for cond, value in (
        ("l.work_order_id = %s", work_order),
        ("s.state = %s", state),
        ("s.entity_id = %s", entity),
        ("s.updated_at >= %s", changed_since),
    ):
        if value is not None:
            sql += f" AND {cond}"
            params.append(value)
    rows = read_rows(cfg, log, conn, sql + " ORDER BY s.entity_id", *params)
    for r in rows:
        r["script"] = script_alive(cfg, r["entity"], r.pop("script_pid"))
    return rows


CUSTOMER_FIELDS = ("name", "address", "city", "state", "zip")  # Figures 6.2, 6.3


def add_customer(cfg: Config, log: logging.Logger, customer_id: str, name: str | None, **address: str | None) -> None:
    """Add a customer, or change one (CUSTOMERS, owned by the HI): its name and address (address, city,
    state, zip: Figure 6.3); a field not given is left as it is."""
    unknown = set(address) - set(CUSTOMER_FIELDS)
    if unknown:
        raise GwcError(f"unknown customer field(s): {', '.join(sorted(unknown))}")
    values = {"name": name, **{f: address.get(f) for f in CUSTOMER_FIELDS[1:]}}
    cols = ", ".join(values)
    with hi_conn(cfg, log) as conn:
        db.transaction(
            conn,
            lambda cur: cur.execute(
                f"INSERT INTO customers (customer_id, {cols}) VALUES (%s, {', '.join(['%s'] * len(values))}) "
                "ON CONFLICT (customer_id) DO UPDATE SET "
                + ", ".join(f"{c} = coalesce(excluded.{c}, customers.{c})" for c in values),
                (customer_id, *values.values()),
            ),
            log=log,
        )


def list_customers(cfg: Config, log: logging.Logger) -> list[dict[str, Any]]:
    """Every customer, with its address."""
    with hi_conn(cfg, log) as conn:
        return rows_of(
            conn, "SELECT customer_id AS customer, name, address, city, state, zip FROM customers ORDER BY 1"
        )


def list_products(cfg: Config, log: logging.Logger) -> list[dict[str, Any]]:
    """Every product and its lot script."""
    with hi_conn(cfg, log) as conn:
        return rows_of(
            conn,
            "SELECT p.product_id AS product, p.description, p.script_id AS script, s.path "
            "FROM products p LEFT JOIN lot_scripts s USING (script_id) ORDER BY 1",
        )


def register_script(
    cfg: Config, log: logging.Logger, script_id: str, path: Path, products: tuple[str, ...], description: str | None
) -> str:
    """Register a lot script file (it must import and define main(entity)) and the products it makes.
    Returns the path as stored: relative to the checkout when inside it, else absolute."""
    full = path if path.is_absolute() else (Path.cwd() / path)
    full = full.resolve()
    load_script(full)  # it exists, imports, and has main(entity)
    try:
        stored = str(full.relative_to(PROJECT_ROOT))
    except ValueError:
        stored = str(full)

    def write(cur: psycopg.Cursor[Any]) -> None:
        cur.execute(
            "INSERT INTO lot_scripts (script_id, path, description) VALUES (%s, %s, %s) "
            "ON CONFLICT (script_id) DO UPDATE SET path = excluded.path, "
            "description = coalesce(excluded.description, lot_scripts.description)",
            (script_id, stored, description),
        )
        for p in products:
            cur.execute(
                "INSERT INTO products (product_id, description, script_id) VALUES (%s, %s, %s) "
                "ON CONFLICT (product_id) DO UPDATE SET script_id = excluded.script_id",
                (p, description, script_id),
            )

    with hi_conn(cfg, log) as conn:
        db.transaction(conn, write, log=log)
    return stored


def list_scripts(cfg: Config, log: logging.Logger) -> list[dict[str, Any]]:
    """Every registered lot script and the products it makes."""
    with hi_conn(cfg, log) as conn:
        return rows_of(
            conn,
            "SELECT s.script_id AS script, s.path, s.description, "
            "(SELECT string_agg(product_id, ', ' ORDER BY product_id) FROM products p "
            "WHERE p.script_id = s.script_id) AS products FROM lot_scripts s ORDER BY 1",
        )
