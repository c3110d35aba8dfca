"""Orders and lots: the thesis's WOEN, WOSU, DISP, IMPL screens (and CUST, PROD), as gwc commands.

`gwc order new` is Work Order Entry: it writes the order (as role gwc_hi, the owner of
WORK_ORDERS), asks the Lot Server to create the lots (CREATE_LOT), and starts one lot script
process per entity, detached with a pid file (the thesis's HI fork/exec'd the script), so
`gwc stop` stops them too. `gwc order list/show` is Work Order Status; `gwc lots` the Dispatch
List; `gwc import` / `gwc export` the operator's decisions (IMPORT_LOT / EXPORT_LOT to the Lot
Server, which tells the entity with LOT_MOVED). `gwc customer`, `gwc product` and `gwc script`
keep the tables an order names; `gwc script register` is how a new lot script joins the cell.
"""

from __future__ import annotations

import getpass
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import click
import psycopg

from gwc import db
from gwc.cell import hi_bus, read_pid
from gwc.config import PROJECT_ROOT, Config
from gwc.errors import GwcError, Refused
from gwc.hi import context, json_option, table
from gwc.ipc.bus import BlockingBus
from gwc.ipc.catalogue import message
from gwc.ipc.codes import AckCode, LotState
from gwc.lot.entity import create_lot, read_traveller
from gwc.lot.run import load_script, spawn_lot_script

ON_BUS_WAIT = 3.0  # how long a command waits to see a server on the bus before saying it is not running


# ----------------------------------------------------------------------------- helpers


def hi_conn(cfg: Config, log: logging.Logger) -> psycopg.Connection[Any]:
    """The Human Interface's connection, as role gwc_hi (it owns orders, customers, products, scripts)."""
    return db.connect(cfg, role="hi", log=log)


def rows_of(conn: psycopg.Connection[Any], sql: str, *params: Any) -> list[dict[str, Any]]:
    cur = conn.execute(sql, params)
    cols = [d.name for d in cur.description or []]
    rows = [dict(zip(cols, r)) for r in cur.fetchall()]
    conn.rollback()
    return rows


def need_server(bus: BlockingBus, name: str, what: str) -> None:
    """Fail in one line unless server `name` is on the bus (the cell is started)."""
    deadline = time.monotonic() + ON_BUS_WAIT
    while name not in bus.peers():
        if time.monotonic() > deadline:
            raise GwcError(f"the {what} ({name}) is not on the bus: start the cell with `gwc start`")
        time.sleep(0.05)


def operator() -> str:
    try:
        return f"hi:{getpass.getuser()}"
    except (KeyError, OSError):
        return f"hi:{os.getuid()}"


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


def script_alive(cfg: Config, entity_id: int, pid: int | None) -> str:
    if pid is None:
        return "-"
    st = read_pid(cfg, f"lot:{entity_id}")
    alive = st.alive and st.pid == pid
    return f"{pid}" if alive else f"{pid} (ended)"


# ----------------------------------------------------------------------------- work orders (WOEN, WOSU)


def enter_order(
    cfg: Config,
    log: logging.Logger,
    bus: BlockingBus,
    customer: str,
    items: list[tuple[str, int]],
    note: str | None = None,
    priority: int | None = None,
    start_scripts: bool = True,
) -> dict[str, Any]:
    """Work Order Entry: the order, its lots (CREATE_LOT), one lot script process per entity."""
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
                "INSERT INTO work_orders (work_order_id, customer_id, note) VALUES (%s, %s, %s)", (wo, customer, note)
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
        pids = {}
        if start_scripts:
            for e in entities:
                pids[e] = spawn_lot_script(cfg, e)
                log.info("entity %d: lot script started (pid %d)", e, pids[e])
        lots.append(
            {"lot_id": lot_id, "product_id": product, "quantity": qty, "entities": entities, "script_pids": pids}
        )
    return {"work_order_id": wo, "customer_id": customer, "lots": lots}


@click.group("order")
def order() -> None:
    """Work orders: enter one (WOEN), list them and their status (WOSU)."""


@order.command("new")
@click.option("--customer", "-c", required=True, help="Customer id (see `gwc customer list`).")
@click.option("--note", help="A note kept with the order.")
@click.option("--priority", type=int, help="Priority of its lots (default 20; used by the priority policy).")
@click.option(
    "--no-scripts",
    is_flag=True,
    help="Create the lots but start no lot scripts (start them by hand with `python -m gwc.lot.run --entity E`).",
)
@click.argument("items", nargs=-1, required=True, metavar="PRODUCT=QTY...")
@json_option
def order_new(
    customer: str, note: str | None, priority: int | None, no_scripts: bool, items: tuple[str, ...], as_json: bool
) -> None:
    """Enter a work order: one lot per product, one entity (and lot script process) per unit.

    Example: gwc order new --customer NJIT alum_chess_set=2 milled_pawn=3
    """
    cfg, log = context()
    parsed = parse_items(items)
    with hi_bus(cfg, log) as bus:
        result = enter_order(cfg, log, bus, customer, parsed, note, priority, start_scripts=not no_scripts)
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    click.echo(f"work order {result['work_order_id']} for {customer}")
    for lot in result["lots"]:
        ents = ", ".join(str(e) for e in lot["entities"])
        click.echo(f"  lot {lot['lot_id']}: {lot['quantity']} x {lot['product_id']} (entities {ents})")
        for e, pid in lot["script_pids"].items():
            click.echo(f"    entity {e}: lot script started (pid {pid})")
    click.echo("the lots will ask to be imported: see `gwc lots`, then `gwc import ENTITY` (or --all)")


ORDER_STATUS_SQL = """
SELECT w.work_order_id AS work_order, w.customer_id AS customer, c.name AS customer_name,
       to_char(w.created_at, 'YYYY-MM-DD HH24:MI:SS') AS created,
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
        r["lots"] = ", ".join(f"{n} {s}" for s, n in sorted((r.pop("states") or {}).items()))
    return rows


@order.command("list")
@json_option
def order_list(as_json: bool) -> None:
    """Work Order Status (WOSU): every order, its customer, items and where its lots are."""
    cfg, log = context()
    table(list_orders(cfg, log), ["work_order", "customer", "created", "items", "status", "lots"], as_json)


@order.command("show")
@click.argument("work_order", type=int)
@json_option
def order_show(work_order: int, as_json: bool) -> None:
    """One work order: its items and each of its lot entities."""
    cfg, log = context()
    orders = list_orders(cfg, log, work_order)
    if not orders:
        raise GwcError(f"unknown work order {work_order} (see `gwc order list`)")
    entities = list_lots(cfg, log, work_order=work_order)
    if as_json:
        click.echo(json.dumps({**orders[0], "entities": entities}, default=str, indent=1))
        return
    o = orders[0]
    click.echo(
        f"work order {o['work_order']} for {o['customer']} ({o['customer_name'] or '-'}), "
        f"entered {o['created']}: {o['status']}"
    )
    click.echo(f"items: {o['items']}" + (f"; note: {o['note']}" if o["note"] else ""))
    table(entities, ["entity", "lot", "product", "state", "script", "result"])


# ----------------------------------------------------------------------------- lots (DISP, IMPL)


LOTS_SQL = """
SELECT s.entity_id AS entity, s.lot_id AS lot, l.work_order_id AS work_order, l.product_id AS product,
       l.owner, l.priority, s.state, s.reason AS result, s.script_pid,
       to_char(s.updated_at, 'HH24:MI:SS') AS since
  FROM lot_status s JOIN lots l USING (lot_id) JOIN lot_entities e USING (entity_id)
 WHERE e.destroyed_at IS NULL
"""


def list_lots(
    cfg: Config,
    log: logging.Logger,
    work_order: int | None = None,
    state: str | None = None,
    entity: int | None = None,
    conn: psycopg.Connection[Any] | None = None,
) -> list[dict[str, Any]]:
    sql, params = LOTS_SQL, []
    for col, value in (("l.work_order_id", work_order), ("s.state", state), ("s.entity_id", entity)):
        if value is not None:
            sql += f" AND {col} = %s"
            params.append(value)
    rows = read_rows(cfg, log, conn, sql + " ORDER BY s.entity_id", *params)
    for r in rows:
        r["script"] = script_alive(cfg, r["entity"], r.pop("script_pid"))
    return rows


@click.command("lots")
@click.argument("entity", type=int, required=False)
@click.option("--order", "work_order", type=int, help="Only the lots of this work order.")
@click.option("--state", type=click.Choice([s.value for s in LotState]), help="Only entities in this state.")
@json_option
def lots(entity: int | None, work_order: int | None, state: str | None, as_json: bool) -> None:
    """The Dispatch List (DISP): every lot entity, where it is, its script and its result.

    With ENTITY, that entity in detail: its runs, machines and decisions (its traveller).
    """
    cfg, log = context()
    rows = list_lots(cfg, log, work_order, state, entity)
    if entity is None:
        table(rows, ["entity", "lot", "work_order", "product", "state", "since", "script", "result"], as_json)
        return
    if not rows:
        raise GwcError(f"unknown lot entity {entity} (see `gwc lots`)")
    trav = read_traveller(cfg, entity) or {}
    if as_json:
        click.echo(json.dumps({**rows[0], "steps": trav.get("steps", [])}, default=str, indent=1))
        return
    r = rows[0]
    click.echo(
        f"entity {entity}: lot {r['lot']}, work order {r['work_order']}, {r['product']} for {r['owner']}: "
        f"{r['state']} since {r['since']}"
    )
    click.echo(f"lot script: {trav.get('script_id', '-')} (pid {r['script']}); log {cfg.log_dir}/lot-{entity}.log")
    if r["result"]:
        click.echo(f"result: {r['result']}")
    for step in trav.get("steps", []):
        click.echo(
            f"  {step['at']}  {step['op_type']} on {', '.join(step['machines'])} "
            f"(run {step['machine_run_id']}): {step['note']}"
        )
        for run in step.get("runs", []):
            res = ", ".join(f"{k}={v}" for k, v in run["results"].items()) or "no results"
            click.echo(f"      {run['machine_id']} {run['recipe_id']} {run['ack_code']}: {res}")


def decide(bus: BlockingBus, entity_id: int, action: str, by: str) -> int | None:
    """IMPORT_LOT / EXPORT_LOT to the Lot Server: the operator lets an entity in or out. Returns its lot."""
    cls = "IMPORT_LOT" if action == "import" else "EXPORT_LOT"
    conv, batch = bus.request(cls, message("Lot_Decision", entity_id=entity_id, action=action, by=by), to="ls")
    conv.end()
    ack = batch.first
    if ack.ack_code == AckCode.UNKNOWN:
        raise GwcError(f"unknown lot entity {entity_id} (see `gwc lots`)")
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or f"cannot {action} entity {entity_id}")
    return ack.lot_id


def _decide_command(action: str, entities: tuple[int, ...], all_waiting: bool) -> None:
    cfg, log = context()
    waiting = LotState.WAITING_IMPORT if action == "import" else LotState.WAITING_EXPORT
    if all_waiting:
        entities = tuple(r["entity"] for r in list_lots(cfg, log, state=waiting))
        if not entities:
            click.echo(f"no entity is {waiting}")
            return
    if not entities:
        raise GwcError(f"name the entities to {action} (see `gwc lots --state {waiting}`), or use --all")
    with hi_bus(cfg, log) as bus:
        need_server(bus, "ls", "Lot Server")
        for e in entities:
            lot_id = decide(bus, e, action, operator())
            click.echo(f"entity {e} (lot {lot_id}) {action}ed")


@click.command("import")
@click.argument("entities", type=int, nargs=-1)
@click.option("--all", "all_waiting", is_flag=True, help="Import every entity waiting to be imported.")
def import_lot(entities: tuple[int, ...], all_waiting: bool) -> None:
    """Import lot entities into the cell (IMPL): each must be waiting_import."""
    _decide_command("import", entities, all_waiting)


@click.command("export")
@click.argument("entities", type=int, nargs=-1)
@click.option("--all", "all_waiting", is_flag=True, help="Export every entity waiting to be exported.")
def export_lot(entities: tuple[int, ...], all_waiting: bool) -> None:
    """Export finished lot entities from the cell: each must be waiting_export."""
    _decide_command("export", entities, all_waiting)


# ----------------------------------------------------------------------------- customers, products, scripts


@click.group("customer")
def customer() -> None:
    """Customers an order is for (CUST)."""


@customer.command("add")
@click.argument("customer_id")
@click.option("--name", help="The customer's name.")
def customer_add(customer_id: str, name: str | None) -> None:
    """Add a customer, or rename one."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        db.transaction(
            conn,
            lambda cur: cur.execute(
                "INSERT INTO customers (customer_id, name) VALUES (%s, %s) "
                "ON CONFLICT (customer_id) DO UPDATE SET name = coalesce(excluded.name, customers.name)",
                (customer_id, name),
            ),
            log=log,
        )
    click.echo(f"customer {customer_id} saved")


@customer.command("list")
@json_option
def customer_list(as_json: bool) -> None:
    """Every customer."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        rows = rows_of(conn, "SELECT customer_id AS customer, name FROM customers ORDER BY 1")
    table(rows, ["customer", "name"], as_json)


@click.group("product")
def product() -> None:
    """Products an order can name, and the lot script that makes each (PROD)."""


@product.command("list")
@json_option
def product_list(as_json: bool) -> None:
    """Every product and its lot script."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        rows = rows_of(
            conn,
            "SELECT p.product_id AS product, p.description, p.script_id AS script, s.path "
            "FROM products p LEFT JOIN lot_scripts s USING (script_id) ORDER BY 1",
        )
    table(rows, ["product", "script", "path", "description"], as_json)


@click.group("script")
def script() -> None:
    """Lot scripts: the programs that make products (see docs/lot-scripts.md)."""


@script.command("register")
@click.argument("script_id")
@click.argument("path", type=click.Path(dir_okay=False, path_type=Path))
@click.option(
    "--product", "products", multiple=True, help="Product made by this script (created if new; repeat for several)."
)
@click.option("--description", help="What the script does.")
def script_register(script_id: str, path: Path, products: tuple[str, ...], description: str | None) -> None:
    """Register a lot script file (it must define main(entity)) and the products it makes."""
    cfg, log = context()
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
    click.echo(f"lot script {script_id} registered ({stored})" + (f" for {', '.join(products)}" if products else ""))


@script.command("list")
@json_option
def script_list(as_json: bool) -> None:
    """Every registered lot script and the products it makes."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        rows = rows_of(
            conn,
            "SELECT s.script_id AS script, s.path, s.description, "
            "(SELECT string_agg(product_id, ', ' ORDER BY product_id) FROM products p "
            "WHERE p.script_id = s.script_id) AS products FROM lot_scripts s ORDER BY 1",
        )
    table(rows, ["script", "path", "products", "description"], as_json)


commands = [order, lots, import_lot, export_lot, customer, product, script]
