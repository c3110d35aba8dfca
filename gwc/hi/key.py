"""`gwc key`: the cell's keys (gwc/ipc/keys.py; docs/security.md says how they reach other hosts)."""

from __future__ import annotations

import time
from datetime import datetime

import click

from gwc.hi import context, json_option, table
from gwc.ipc import keys


@click.group("key")
def key() -> None:
    """The cell key every module and `gwc` command signs with, and the lot key lot scripts hold."""


@key.command("new")
@click.option("--force", is_flag=True, help="Replace existing keys (stops a running cell from hearing itself).")
def new(force: bool) -> None:
    """Make the cell's keys (a new cell id, a module key and a lot key), mode 0600."""
    cfg, _ = context()
    keys.new(cfg.bus, force=force)
    click.echo(f"new cell keys in {cfg.bus.key_file} (lot scripts: {cfg.bus.lot_key_file})")


@key.command("rotate")
@click.option(
    "--overlap",
    default=keys.DEFAULT_OVERLAP,
    show_default=True,
    help="Seconds the old keys stay accepted (copy the new files to every host within it).",
)
@click.option(
    "--take-up",
    "take_up",
    default=keys.TAKE_UP,
    show_default=True,
    help="Seconds before senders use the new keys (on several hosts: time to copy the files to all).",
)
def rotate(overlap: float, take_up: float) -> None:
    """Change the keys of a running cell: new keys used after the take-up, old ones accepted for the overlap."""
    cfg, _ = context()
    keys.rotate(cfg.bus, overlap, take_up)
    click.echo(
        f"rotated: senders take the new keys in {take_up:.0f} s, the old ones are refused after "
        f"{overlap:.0f} s; copy {cfg.bus.key_file} and {cfg.bus.lot_key_file} to the cell's other hosts now"
    )


@key.command("show")
@json_option
def show(as_json: bool) -> None:
    """The keys in the cell key file, without their secrets."""
    cfg, _ = context()
    _, keyset = keys.load(cfg.bus, "module")

    def when(t: float | None) -> str:
        return "-" if not t else datetime.fromtimestamp(t).isoformat(" ", "seconds")

    rows = [
        {**k, "send_from": when(k["send_from"]), "until": when(k["until"]), "cell_id": keyset.cell_id.hex()}
        for k in keys.describe(keyset, time.time())
    ]
    table(rows, ["cell_id", "role", "id", "sending", "send_from", "until"], as_json)


@key.command("opcua-password")
@click.option("--password", prompt=True, hide_input=True, confirmation_prompt=True, help="(asked when not given)")
def opcua_password(password: str) -> None:
    """Print the salted hash of an OPC UA user's password, for cell.toml's [opcua] users."""
    from gwc.opcua.security import hash_password  # (asyncua: loaded only for this command)

    click.echo(hash_password(password))


commands = [key]
