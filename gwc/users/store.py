"""The SQL of users and the audit trail (sql/090_users.sql), returning dataclasses. The users table is
the Human Interface's (gwc_hi); every door appends to the audit trail, none changes it."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

import psycopg

from gwc.errors import GwcError
from gwc.users.roles import Role


@dataclass(frozen=True)
class User:
    user_name: str
    role: Role
    password_hash: str
    unix_user: str | None
    created_at: datetime
    created_by: str


@dataclass(frozen=True)
class AuditRow:
    """One act of a person (who, role, door, address, what, target, outcome, when)."""

    user_name: str
    role: str
    door: str
    action: str
    target: str = ""
    outcome: str = "ok"
    note: str = ""
    address: str = ""
    at: datetime | None = None
    audit_no: int | None = None


_USER_COLS = "user_name, role, password_hash, unix_user, created_at, created_by"


def _user(row: tuple[Any, ...]) -> User:
    name, role, hashed, unix, at, by = row
    return User(name, Role[role], hashed, unix, at, by)


def get_user(conn: psycopg.Connection[Any], name: str) -> User | None:
    row = conn.execute(f"select {_USER_COLS} from cell_users where user_name = %s", (name,)).fetchone()
    conn.rollback()
    return _user(row) if row else None


def user_of_unix(conn: psycopg.Connection[Any], unix_user: str) -> User | None:
    """The cell user a unix login is mapped to (its unix_user), else the cell user of the same name
    that has no other mapping."""
    row = conn.execute(
        f"select {_USER_COLS} from cell_users where unix_user = %s "
        "union all select " + _USER_COLS + " from cell_users where user_name = %s and unix_user is null limit 1",
        (unix_user, unix_user),
    ).fetchone()
    conn.rollback()
    return _user(row) if row else None


def count_users(conn: psycopg.Connection[Any]) -> int:
    (n,) = conn.execute("select count(*) from cell_users").fetchone() or (0,)
    conn.rollback()
    return int(n)


def list_users(conn: psycopg.Connection[Any]) -> list[User]:
    rows = conn.execute(f"select {_USER_COLS} from cell_users order by user_name").fetchall()
    conn.rollback()
    return [_user(r) for r in rows]


def add_user(
    conn: psycopg.Connection[Any], name: str, role: Role, password_hash: str, unix_user: str | None, by: str
) -> None:
    try:
        conn.execute(
            "insert into cell_users (user_name, role, password_hash, unix_user, created_by) "
            "values (%s, %s, %s, %s, %s)",
            (name, role.name, password_hash, unix_user, by),
        )
        conn.commit()
    except psycopg.errors.UniqueViolation:
        conn.rollback()
        raise GwcError(f"user {name!r} exists already, or unix user {unix_user!r} is another's") from None
    except psycopg.errors.CheckViolation:
        conn.rollback()
        raise GwcError(
            f"user name {name!r}: a lowercase letter, then up to 31 of a-z 0-9 _ . - (like a unix login)"
        ) from None


def change_user(
    conn: psycopg.Connection[Any],
    name: str,
    *,
    role: Role | None = None,
    password_hash: str | None = None,
) -> None:
    cur = conn.execute(
        "update cell_users set role = coalesce(%s, role), password_hash = coalesce(%s, password_hash), "
        "changed_at = now() where user_name = %s",
        (role.name if role else None, password_hash, name),
    )
    conn.commit()
    if cur.rowcount != 1:
        raise GwcError(f"no user {name!r} (gwc user list)")


def remove_user(conn: psycopg.Connection[Any], name: str) -> None:
    cur = conn.execute("delete from cell_users where user_name = %s", (name,))
    conn.commit()
    if cur.rowcount != 1:
        raise GwcError(f"no user {name!r} (gwc user list)")


def append(conn: psycopg.Connection[Any], row: AuditRow) -> None:
    """One row more in the audit trail, in its own transaction."""
    conn.execute(
        "insert into audit_trail (user_name, role, door, address, action, target, outcome, note) "
        "values (%s, %s, %s, %s, %s, %s, %s, %s)",
        (row.user_name, row.role, row.door, row.address, row.action, row.target, row.outcome, row.note[:2000]),
    )
    conn.commit()


def audit_rows(
    conn: psycopg.Connection[Any], since: datetime | None = None, user: str | None = None, limit: int = 1000
) -> list[AuditRow]:
    """The trail, newest last: since a time, of one user, at most `limit` rows (the newest)."""
    rows = conn.execute(
        "select * from (select user_name, role, door, action, target, outcome, note, address, at, audit_no "
        "from audit_trail where (%s::timestamptz is null or at >= %s) and (%s::text is null or user_name = %s) "
        "order by audit_no desc limit %s) t order by audit_no",
        (since, since, user, user, limit),
    ).fetchall()
    conn.rollback()
    return [AuditRow(*r) for r in rows]
