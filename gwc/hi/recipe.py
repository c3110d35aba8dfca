"""The recipe library: `gwc recipe add | list | show | approve` (Equipment Recipe Server, 1.4.1).

Listing and showing read the tables and the library files; adding and approving are asked of the
ERS (RECIPE_PUT, RECIPE_APPR), the only writer of recipes. `list` also says whether the approved
version's library file still is what was approved: a file edited since is "MODIFIED", and a
machine refuses it until someone approves again.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from gwc import db
from gwc.cell import hi_bus
from gwc.config import Config
from gwc.errors import GwcError, Refused
from gwc.hi import context, json_option, table
from gwc.hi.alarm import operator
from gwc.ipc.catalogue import Message, message
from gwc.ipc.codes import AckCode
from gwc.servers.recipe import sha256, version_path

TIMEOUT = 10.0


def _ask_ers(cls: str, msg: Message) -> Message:
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        conv, batch = bus.request(cls, msg, to="ers", timeout=TIMEOUT)
        conv.end()
    ack = batch.first
    if ack.ack_code != AckCode.ACK_OK:
        raise Refused(ack.ack_code, ack.note or "")
    return ack


def _note(ack: Message) -> str:
    return f": {ack.note}" if ack.note else ""


def file_state(cfg: Config, recipe_id: str, version: int, checksum: str) -> str:
    """ok, MODIFIED or missing: the library file of a version against its recorded checksum."""
    try:
        data = version_path(cfg, recipe_id, version).read_bytes()
    except FileNotFoundError:
        return "missing"
    return "ok" if sha256(data) == checksum else "MODIFIED"


@click.group("recipe")
def recipe_group() -> None:
    """The recipe library (Equipment Recipe Server)."""


@recipe_group.command("add")
@click.argument("recipe_id")
@click.argument("file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--description", help="What the recipe is (set or replaced).")
@click.option("--approve", is_flag=True, help="Approve the new version at once.")
def recipe_add(recipe_id: str, file: Path, description: str | None, approve: bool) -> None:
    """Store FILE as a new version of RECIPE_ID (a new recipe if it is unknown)."""
    try:
        content = file.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise GwcError(f"cannot read {file} as text: {e}") from e
    ack = _ask_ers(
        "RECIPE_PUT",
        message("Recipe_Store", recipe_id=recipe_id, content=content, by=operator(), description=description),
    )
    click.echo(f"{recipe_id} v{ack.version} stored (sha256 {ack.checksum[:12]})" + _note(ack))
    if approve:
        appr = _ask_ers(
            "RECIPE_APPR", message("Recipe_Approve", recipe_id=recipe_id, version=ack.version, by=operator())
        )
        click.echo(f"{recipe_id} v{appr.version} approved")


@recipe_group.command("approve")
@click.argument("recipe_id")
@click.argument("version", type=int, required=False)
def recipe_approve(recipe_id: str, version: int | None) -> None:
    """Approve VERSION (default: the latest). An edited library file is stored as a new version first."""
    ack = _ask_ers("RECIPE_APPR", message("Recipe_Approve", recipe_id=recipe_id, version=version, by=operator()))
    click.echo(f"{recipe_id} v{ack.version} approved (sha256 {ack.checksum[:12]})" + _note(ack))


def _rows(cfg: Config, sql: str, *params: Any) -> list[dict[str, Any]]:
    with db.connect(cfg, role="hi") as conn:
        cur = conn.execute(sql, params)
        names = [d.name for d in cur.description or []]
        return [dict(zip(names, r)) for r in cur.fetchall()]


@recipe_group.command("list")
@json_option
def recipe_list(as_json: bool) -> None:
    """Every recipe: its versions, the approved one, whether its file is intact, its machines."""
    cfg, _ = context()
    rows = _rows(
        cfg,
        """
        select r.recipe_id, r.description, count(v.version) as versions, a.version as approved, a.checksum,
               (select string_agg(distinct m.machine_id, ' ' order by m.machine_id) from op_machine_recipe m
                 where m.recipe_id = r.recipe_id) as machines
        from recipes r left join recipe_versions v using (recipe_id)
        left join recipe_versions a on a.recipe_id = r.recipe_id and a.approved
        group by r.recipe_id, r.description, a.version, a.checksum order by r.recipe_id""",
    )
    for r in rows:
        r["file"] = file_state(cfg, r["recipe_id"], r["approved"], r["checksum"]) if r["approved"] else None
        r["checksum"] = r["checksum"][:12] if r["checksum"] else None
    table(rows, ["recipe_id", "versions", "approved", "checksum", "file", "machines", "description"], as_json)


@recipe_group.command("show")
@click.argument("recipe_id")
@click.option("--version", type=int, help="Which version's content to print (default: the approved one).")
def recipe_show(recipe_id: str, version: int | None) -> None:
    """The versions of RECIPE_ID, then the content of one (as stored: the original)."""
    cfg, _ = context()
    rows = _rows(
        cfg,
        "select version, approved, checksum, created_by, created_at, note, content "
        "from recipe_versions where recipe_id = %s order by version",
        recipe_id,
    )
    if not rows:
        raise GwcError(f"no recipe {recipe_id!r} (see `gwc recipe list`)")
    for r in rows:
        r["file"] = file_state(cfg, recipe_id, r["version"], r["checksum"])
        r["created_at"] = r["created_at"].strftime("%Y-%m-%d %H:%M:%S")
    table(
        [{**r, "checksum": r["checksum"][:12], "approved": "yes" if r["approved"] else ""} for r in rows],
        ["version", "approved", "checksum", "file", "created_by", "created_at", "note"],
    )
    chosen = next((r for r in rows if (r["version"] == version if version else r["approved"])), None)
    if chosen is None:
        raise GwcError(f"recipe {recipe_id} has no " + (f"version {version}" if version else "approved version"))
    click.echo(f"--- {recipe_id} v{chosen['version']} ---")
    click.echo(bytes(chosen["content"]).decode(errors="replace"), nl=False)


commands = [recipe_group]
