"""Orders and lots: the thesis's WOEN, WOSU, DISP, IMPL screens (and CUST, PROD), as gwc commands.

`gwc order new` is Work Order Entry: it writes the order (as role gwc_hi, the owner of
WORK_ORDERS), asks the Lot Server to create the lots (CREATE_LOT), and starts one lot script
process per entity, detached with a pid file (the thesis's HI fork/exec'd the script), so
`gwc stop` stops them too. `gwc order list/show` is Work Order Status; `gwc lots` the Dispatch
List; `gwc import` / `gwc export` the operator's decisions (IMPORT_LOT / EXPORT_LOT to the Lot
Server, which tells the entity with LOT_MOVED). `gwc customer`, `gwc product` and `gwc script`
keep the tables an order names; `gwc script register` is how a new lot script joins the cell.
What they do with the cell is gwc.client.orders'; this module parses and prints.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from gwc.client.orders import (
    add_customer,
    decide,
    enter_order,
    list_customers,
    list_lots,
    list_orders,
    list_products,
    list_scripts,
    parse_due,
    parse_items,
    read_traveller,
    register_script,
)
from gwc.client.session import hi_bus, need_server, operator
from gwc.errors import GwcError
from gwc.hi import context, json_option, table
from gwc.ipc.codes import LotState
from gwc.lot.model import RELEASES

# ----------------------------------------------------------------------------- work orders (WOEN, WOSU)


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
@click.option("--due", help="Date due (Fig. 6.3): YYYY-MM-DD, 'YYYY-MM-DD HH:MM', now, +3d, +12h.")
@click.argument("items", nargs=-1, required=True, metavar="PRODUCT=QTY...")
@json_option
def order_new(
    customer: str,
    note: str | None,
    priority: int | None,
    no_scripts: bool,
    due: str | None,
    items: tuple[str, ...],
    as_json: bool,
) -> None:
    """Enter a work order: one lot per product, one entity (and lot script process) per unit.

    Example: gwc order new --customer NJIT alum_chess_set=2 milled_pawn=3
    """
    cfg, log = context()
    parsed = parse_items(items)
    with hi_bus(cfg, log) as bus:
        result = enter_order(
            cfg, log, bus, customer, parsed, note, priority, start_scripts=not no_scripts, due=parse_due(due)
        )
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    click.echo(f"work order {result['work_order_id']} for {customer}")
    for lot in result["lots"]:
        ents = ", ".join(str(e) for e in lot["entities"])
        click.echo(f"  lot {lot['lot_id']}: {lot['quantity']} x {lot['product_id']} (entities {ents})")
        queued = [str(e) for e, pid in lot["script_pids"].items() if pid is None]
        for e, pid in lot["script_pids"].items():
            if pid is not None:
                click.echo(f"    entity {e}: lot script started (pid {pid})")
        if queued:
            click.echo(f"    entities {_span(queued)}: lot scripts queued (each starts as another ends)")
    click.echo("the lots will ask to be imported: see `gwc lots`, then `gwc import ENTITY` (or --all)")


def _span(ids: list[str]) -> str:
    """A list of entity ids, shortened: 7, 8, 9 ... 200 (194 in all)."""
    return ", ".join(ids) if len(ids) <= 6 else f"{', '.join(ids[:3])} ... {ids[-1]} ({len(ids)} in all)"


@order.command("list")
@json_option
def order_list(as_json: bool) -> None:
    """Work Order Status (WOSU): every order, its customer, items and where its lots are."""
    cfg, log = context()
    columns = ["work_order", "customer", "customer_name", "created", "due", "items", "status", "lots"]
    table(list_orders(cfg, log), columns, as_json)


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
        f"entered {o['created']}, due {o['due'] or '-'}: {o['status']}"
    )
    click.echo(f"items: {o['items']}" + (f"; note: {o['note']}" if o["note"] else ""))
    table(entities, ["entity", "lot", "product", "state", "script", "result"])


# ----------------------------------------------------------------------------- lots (DISP, IMPL)


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
        table(rows, ["entity", "lot", "parent", "work_order", "product", "state", "since", "script", "result"], as_json)
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


def _decide_command(action: str, entities: tuple[int, ...], all_waiting: bool) -> None:
    cfg, log = context()
    waiting = LotState.WAITING_IMPORT if action == "import" else LotState.WAITING_EXPORT
    if all_waiting:
        entities = tuple(r["entity"] for r in list_lots(cfg, log, state=waiting))
        if action == "import":  # and those whose scripts have not asked yet (queued): imported ahead
            entities += tuple(r["entity"] for r in list_lots(cfg, log, state=LotState.CREATED))
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
@click.option(
    "--all",
    "all_waiting",
    is_flag=True,
    help="Import every entity waiting to be imported, and ahead every one whose script has not asked yet.",
)
def import_lot(entities: tuple[int, ...], all_waiting: bool) -> None:
    """Import lot entities into the cell (IMPL): each waiting_import, or created (imported ahead of its
    script's request: a queued script finds its entity imported when it starts)."""
    _decide_command("import", entities, all_waiting)


@click.command("export")
@click.argument("entities", type=int, nargs=-1)
@click.option("--all", "all_waiting", is_flag=True, help="Export every entity waiting to be exported.")
def export_lot(entities: tuple[int, ...], all_waiting: bool) -> None:
    """Export finished lot entities from the cell: each must be waiting_export."""
    _decide_command("export", entities, all_waiting)


@click.command("release")
@click.argument("entities", type=int, nargs=-1, required=True)
@click.option(
    "--decision",
    type=click.Choice(RELEASES),
    required=True,
    help="retry or reroute: the entity asks for its operation again (its script's alternatives); "
    "fail: the entity fails, its machines freed.",
)
def release_lot(entities: tuple[int, ...], decision: str) -> None:
    """Release held lot entities (state held: a run in doubt past its bound; `gwc lots --state held`,
    `gwc lots E` for why): retry, reroute or fail. Look at the part on the machine first."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        need_server(bus, "ls", "Lot Server")
        for e in entities:
            lot_id = decide(bus, e, decision, operator())
            click.echo(f"entity {e} (lot {lot_id}) released: {decision}")


# ----------------------------------------------------------------------------- customers, products, scripts


@click.group("customer")
def customer() -> None:
    """Customers an order is for (CUST)."""


@customer.command("add")
@click.argument("customer_id")
@click.option("--name", help="The customer's name.")
@click.option("--address", help="Street address (Fig. 6.3).")
@click.option("--city")
@click.option("--state")
@click.option("--zip", "zip_code")
def customer_add(
    customer_id: str, name: str | None, address: str | None, city: str | None, state: str | None, zip_code: str | None
) -> None:
    """Add a customer, or change its name or address (fields not given stay as they are)."""
    cfg, log = context()
    add_customer(cfg, log, customer_id, name, address=address, city=city, state=state, zip=zip_code)
    click.echo(f"customer {customer_id} saved")


@customer.command("list")
@json_option
def customer_list(as_json: bool) -> None:
    """Every customer."""
    cfg, log = context()
    table(list_customers(cfg, log), ["customer", "name", "address", "city", "state", "zip"], as_json)


@click.group("product")
def product() -> None:
    """Products an order can name, and the lot script that makes each (PROD)."""


@product.command("list")
@json_option
def product_list(as_json: bool) -> None:
    """Every product and its lot script."""
    cfg, log = context()
    table(list_products(cfg, log), ["product", "script", "path", "description"], as_json)


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
    stored = register_script(cfg, log, script_id, path, products, description)
    click.echo(f"lot script {script_id} registered ({stored})" + (f" for {', '.join(products)}" if products else ""))


@script.command("list")
@json_option
def script_list(as_json: bool) -> None:
    """Every registered lot script and the products it makes."""
    cfg, log = context()
    table(list_scripts(cfg, log), ["script", "path", "products", "description"], as_json)


commands = [order, lots, import_lot, export_lot, release_lot, customer, product, script]
