"""People: `gwc user add/remove/passwd/role/list` (docs/users.md). The users table is the Human
Interface's; only an admin may change it, except in a cell with no users yet (the first user is
added by whoever runs the cell). A password is read from standard input, never from the command line
(where `ps` and the shell's history would show it)."""

from __future__ import annotations

import sys

import click

from gwc.client.session import hi_conn
from gwc.errors import GwcError
from gwc.hi import context, json_option, table
from gwc.users import Action, Role, act, identify_unix, store
from gwc.users.passwords import hash_password

ROLES = click.Choice([r.name for r in Role])


def read_password(confirm: bool = True) -> str:
    """The new password: prompted twice on a terminal, else the first line of standard input."""
    if sys.stdin.isatty():
        return str(click.prompt("password", hide_input=True, confirmation_prompt=confirm))
    line = sys.stdin.readline().rstrip("\n")
    if not line:
        raise GwcError("no password on standard input (echo PASSWORD | gwc user ...)")
    return line


def hashed(password: str) -> str:
    try:
        return hash_password(password)
    except ValueError as e:
        raise GwcError(str(e)) from None


@click.group("user")
def user_group() -> None:
    """The cell's users and their roles (viewer, operator, engineer, admin)."""


@user_group.command("add")
@click.argument("name")
@click.option("--role", type=ROLES, required=True, help="What the user may do (docs/users.md).")
@click.option("--unix", "unix_user", default=None, help="The unix login whose `gwc` commands act as this user.")
def user_add(name: str, role: str, unix_user: str | None) -> None:
    """Add user NAME with a role; the password comes from standard input."""
    cfg, log = context()
    password = hashed(read_password())
    with hi_conn(cfg, log) as conn:
        who = identify_unix(conn, "gwc")
        with act(conn, who, Action.USER_MANAGE, f"add {name} {role}", log):
            store.add_user(conn, name, Role[role], password, unix_user, who.by)
    click.echo(f"user {name} added ({role})")


@user_group.command("remove")
@click.argument("name")
def user_remove(name: str) -> None:
    """Remove user NAME (the audit trail keeps their acts)."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        who = identify_unix(conn, "gwc")
        with act(conn, who, Action.USER_MANAGE, f"remove {name}", log):
            store.remove_user(conn, name)
    click.echo(f"user {name} removed")


@user_group.command("passwd")
@click.argument("name")
def user_passwd(name: str) -> None:
    """Set user NAME's password (from standard input). Anyone may set their own; an admin anyone's."""
    cfg, log = context()
    password = hashed(read_password())
    with hi_conn(cfg, log) as conn:
        who = identify_unix(conn, "gwc")
        own = who.managed and who.name == name
        with act(conn, who, Action.VIEW if own else Action.USER_MANAGE, f"passwd {name}", log):
            store.change_user(conn, name, password_hash=password)
    click.echo(f"password of {name} changed")


@user_group.command("role")
@click.argument("name")
@click.argument("role", type=ROLES)
def user_role(name: str, role: str) -> None:
    """Give user NAME another role."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        who = identify_unix(conn, "gwc")
        with act(conn, who, Action.USER_MANAGE, f"role {name} {role}", log):
            store.change_user(conn, name, role=Role[role])
    click.echo(f"user {name} is now {role}")


@user_group.command("list")
@json_option
def user_list(as_json: bool) -> None:
    """Every user, their role and unix login (never a hash)."""
    cfg, log = context()
    with hi_conn(cfg, log) as conn:
        rows = [
            {
                "user_name": u.user_name,
                "role": u.role.name,
                "unix_user": u.unix_user,
                "created_at": u.created_at.strftime("%Y-%m-%d %H:%M:%S"),
                "created_by": u.created_by,
            }
            for u in store.list_users(conn)
        ]
    table(rows, ["user_name", "role", "unix_user", "created_at", "created_by"], as_json)


commands = [user_group]
