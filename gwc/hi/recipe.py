"""The recipe library: `gwc recipe add | list | show | approve` (Equipment Recipe Server, 1.4.1).

Listing and showing read the tables and the library files; adding and approving are asked of the
ERS (RECIPE_PUT, RECIPE_APPR), the only writer of recipes. `list` also says whether the approved
version's library file still is what was approved: a file edited since is "MODIFIED", and a
machine refuses it until someone approves again. The conversations are gwc.client.recipes'.
"""

from __future__ import annotations

from pathlib import Path

import click

from gwc.client.recipes import approve_recipe, list_recipes, recipe_versions, store_recipe
from gwc.client.session import hi_bus
from gwc.errors import GwcError
from gwc.hi import context, json_option, table
from gwc.ipc.catalogue import Message


def _note(ack: Message) -> str:
    return f": {ack.note}" if ack.note else ""


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
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        ack = store_recipe(bus, recipe_id, content, description)
        click.echo(f"{recipe_id} v{ack.version} stored (sha256 {ack.checksum[:12]})" + _note(ack))
        if approve:
            appr = approve_recipe(bus, recipe_id, ack.version)
            click.echo(f"{recipe_id} v{appr.version} approved")


@recipe_group.command("approve")
@click.argument("recipe_id")
@click.argument("version", type=int, required=False)
def recipe_approve(recipe_id: str, version: int | None) -> None:
    """Approve VERSION (default: the latest). An edited library file is stored as a new version first."""
    cfg, log = context()
    with hi_bus(cfg, log) as bus:
        ack = approve_recipe(bus, recipe_id, version)
    click.echo(f"{recipe_id} v{ack.version} approved (sha256 {ack.checksum[:12]})" + _note(ack))


@recipe_group.command("list")
@json_option
def recipe_list(as_json: bool) -> None:
    """Every recipe: its versions, the approved one, whether its file is intact, its machines."""
    cfg, _ = context()
    rows = list_recipes(cfg)
    table(rows, ["recipe_id", "versions", "approved", "checksum", "file", "machines", "description"], as_json)


@recipe_group.command("show")
@click.argument("recipe_id")
@click.option("--version", type=int, help="Which version's content to print (default: the approved one).")
def recipe_show(recipe_id: str, version: int | None) -> None:
    """The versions of RECIPE_ID, then the content of one (as stored: the original)."""
    cfg, _ = context()
    rows = recipe_versions(cfg, recipe_id)
    if not rows:
        raise GwcError(f"no recipe {recipe_id!r} (see `gwc recipe list`)")
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
