"""How a person comes through a door and what the door does with each act (docs/users.md).

A `Person` is who acts: a cell user with a role, at a door (web, console, gwc, opcua), from an
address. Every door runs an act through `act`: the role table is consulted (gwc/users/roles.py); a
refusal is raised (`Forbidden`) after its audit row is written, and an allowed act is run and its
outcome (ok or failed, and why) appended to the audit trail. The audit row is written by the door,
in the person's name: the module that owns the action hears only the conversation, with `by` naming
the person as `door:user` (e.g. `web:alice`), which it records as it always has (alarm history, lot
decisions, recipe versions).

A `gwc` command (and `gwc console`) on a cell host is the unix login that ran it: `SUDO_USER` when
root runs it through sudo, else the process's own user, mapped to the cell user whose unix_user it
is (or of the same name). A cell with no users yet is open, as before users existed: every login
acts as admin, and is audited so.
"""

from __future__ import annotations

import logging
import os
import pwd
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import psycopg

from gwc.errors import Forbidden, GwcError, NotAuthenticated
from gwc.users import store
from gwc.users.roles import Action, Role, check


@dataclass(frozen=True)
class Person:
    name: str
    role: Role
    door: str
    address: str = ""
    managed: bool = True  # False: a cell with no users yet (everyone is admin)

    @property
    def by(self) -> str:
        """How the owning module records who acted (its `by`, `cleared_by`, ... fields)."""
        return f"{self.door}:{self.name}"


def unix_login() -> str:
    """The login behind this process: sudo's caller when root runs through sudo, else its own user."""
    uid = os.getuid()
    if uid == 0 and os.environ.get("SUDO_USER"):
        return os.environ["SUDO_USER"]
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return str(uid)


def identify_unix(conn: psycopg.Connection[Any], door: str) -> Person:
    """The person running this `gwc` command (or console): NotAuthenticated if the cell has users
    and none of them is this login."""
    login = unix_login()
    user = store.user_of_unix(conn, login)
    if user is not None:
        return Person(user.user_name, user.role, door, address=f"unix:{login}")
    if store.count_users(conn) == 0:
        return Person(login, Role.admin, door, address=f"unix:{login}", managed=False)
    raise NotAuthenticated(
        f"unix user {login} is no user of this cell: an admin adds one (gwc user add NAME --role ROLE --unix {login})"
    )


def audit(
    conn: psycopg.Connection[Any], who: Person, action: Action | str, target: str, outcome: str, note: str
) -> None:
    store.append(
        conn,
        store.AuditRow(
            user_name=who.name,
            role=who.role.name,
            door=who.door,
            address=who.address,
            action=str(action),
            target=target,
            outcome=outcome,
            note=note,
        ),
    )


def refuse_unless(
    conn: psycopg.Connection[Any], who: Person, action: Action, target: str = "", log: logging.Logger | None = None
) -> None:
    """The role table's answer for `who`: Forbidden (audited, logged) unless their role may."""
    try:
        check(who.name, who.role, action)
    except Forbidden as e:
        audit(conn, who, action, target, "refused", str(e))
        if log:
            log.warning("%s at the %s door refused: %s %s: %s", who.name, who.door, action, target, e)
        raise


@contextmanager
def act(
    conn: psycopg.Connection[Any], who: Person, action: Action, target: str = "", log: logging.Logger | None = None
) -> Iterator[list[str]]:
    """Check, run the body, audit its outcome. The body may append a note (what came of it) to the
    list it is given; a GwcError out of it is audited `failed` with its message and raised again."""
    refuse_unless(conn, who, action, target, log)
    notes: list[str] = []
    try:
        yield notes
    except GwcError as e:
        audit(conn, who, action, target, "failed", str(e))
        raise
    except BaseException as e:
        audit(conn, who, action, target, "failed", f"{type(e).__name__}: {e}")
        raise
    audit(conn, who, action, target, "ok", "; ".join(notes))


def login(conn: psycopg.Connection[Any], name: str, password: str, door: str, address: str) -> Person:
    """A person by name and password (the web's and OPC UA's doors). NotAuthenticated for either
    wrong, the same way (no telling which)."""
    from gwc.users.passwords import verify

    user = store.get_user(conn, name)
    if not verify(user.password_hash if user else None, password) or user is None:
        raise NotAuthenticated("wrong user name or password")
    return Person(user.user_name, user.role, door, address)
