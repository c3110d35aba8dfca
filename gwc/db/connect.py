"""Connections to the cell database: the URL a module's role uses, a connect retried with backoff
(thesis 3.2.2), every member of a multi-host URL tried at once, a failing-over database's standbys
watched for the one promoted (gwc.promotion), and the kernel's watch on a TCP link (TCP_WATCH)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import threading
import time
from typing import Any
from urllib.parse import quote, urlsplit, urlunsplit

import psycopg
from psycopg import sql
from psycopg.conninfo import conninfo_attempts, conninfo_attempts_async, conninfo_to_dict

from gwc.config import Config
from gwc.db.access import ca_file, lot_password, passwords_file, role_passwords, uses_tls
from gwc.db.names import DB_NAME, LOT_ROLE, SUPERUSER, db_port, socket_dir
from gwc.errors import DatabaseError, DatabaseUnavailable
from gwc.promotion import await_promotion, await_promotion_async, read_only_refusal
from gwc.retry import Backoff

_log = logging.getLogger("gwc.db")


def database_url(cfg: Config, role: str | None = None) -> str:
    """The URL the cell uses: GWC_DATABASE_URL / [database] url, else the embedded cluster's socket, or
    from another host of the cell its address, as the module's role (gwc_hi for the operator's tools)."""
    if cfg.database_url:
        return cfg.database_url
    port = db_port(cfg)
    host = cfg.database_host
    if (host is not None and host.name != cfg.host) or (role == LOT_ROLE and cfg.embedded):
        # From another host every role logs in as itself; on the database's host lot scripts do too,
        # so that their role's connection limit holds them to their share (limit_lot_connections).
        user = f"gwc_{role or 'hi'}"
        if host is None or host.name == cfg.host:
            return f"postgresql://{user}@/{DB_NAME}?host={quote(str(socket_dir(cfg)), safe='')}" + (
                f"&port={port}" if port != 5432 else ""
            )
        password = lot_password(cfg) if role == LOT_ROLE else None
        password = password or role_passwords(cfg).get(user)
        if password is None:
            raise DatabaseError(f"no password for {user} in {passwords_file(cfg)}: copy it from the database host")
        tls = f"?sslmode=verify-ca&sslrootcert={quote(str(ca_file(cfg)), safe='')}" if uses_tls(cfg) else ""
        return f"postgresql://{user}:{quote(password, safe='')}@{host.address}:{port}/{DB_NAME}{tls}"
    return f"postgresql://{SUPERUSER}@/{DB_NAME}?host={quote(str(socket_dir(cfg)), safe='')}" + (
        f"&port={port}" if port != 5432 else ""
    )


def _redact(url: str) -> str:
    """The URL without its password, for messages and logs."""
    with contextlib.suppress(ValueError):
        parts = urlsplit(url)
        if parts.password:
            netloc = parts.netloc.replace(f":{parts.password}@", ":***@")
            return urlunsplit(parts._replace(netloc=netloc))
    return re.sub(r"password=\S+", "password=***", url)


def one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


_ROLE = re.compile(r"^[a-z][a-z0-9_]*$")
# A TCP connection (from another host) is watched by the kernel, not by queries: probed after 3 s of
# silence, dead after 3 probes unanswered. Data unacknowledged for 8 s ends it: a query on a cut link
# fails instead of holding its module for TCP's ~15 min of retries. The socket then turns readable, as
# a resting module's watch sees without a round trip (gwc/module.py). libpq ignores it on a Unix socket.
_KEEPALIVE = {"keepalives": 1, "keepalives_idle": 3, "keepalives_interval": 1, "keepalives_count": 3}
# Data unacknowledged this long ends the connection (ms). The peer's kernel acknowledges, not its
# PostgreSQL, so a loaded server does not trip it; a dead host (a database failover's old primary)
# does, and a module's query on it fails after 4 s instead of holding its step (docs/reliability.md).
TCP_WATCH: dict[str, Any] = {**_KEEPALIVE, "tcp_user_timeout": 4000}
CONNECT_TIMEOUT_S = 5  # a connect's bound, unless the URL says (`connect_timeout`)
SLOW_MEMBER_S = 0.25  # s: how long a multi-host connect waits for a silent member once the others refused


def connect(
    cfg: Config,
    role: str | None = None,
    log: logging.Logger | None = None,
    attempts: int = 5,
    promotion_wait: float = 0.0,
) -> psycopg.Connection[Any]:
    """Connect (autocommit off) as role gwc_<role>, retrying with backoff (thesis 3.2.2).

    Raises DatabaseUnavailable after the last try; DatabaseError at once if the role is unknown
    (that is not transient: the schema has not been applied). `promotion_wait` (s): how long a try
    may watch the standbys of a database failing over for the one promoted (PROMOTION_POLL_S), for a
    caller in a thread of its own that would try again anyway.
    """
    log = log or _log
    if role is not None and not _ROLE.match(role):
        raise DatabaseError(f"bad database role name {role!r}")
    url = database_url(cfg, role)
    error: Exception | None = None
    backoff = Backoff(0.1, 2.0, attempts=attempts, jitter=0.2)
    while True:
        attempt = backoff.tries + 1
        try:
            conn = connect_any(url, f"gwc_{role}" if role else "gwc", promotion_wait)
        except psycopg.OperationalError as e:
            error = e
            pause = backoff.next()
            if pause is None:
                break  # the caller hears of it (DatabaseUnavailable)
            log.warning(
                "database connect failed (try %d of %d) to %s: %s", attempt, attempts, _redact(url), one_line(e)
            )
            time.sleep(pause)
            continue
        if role is not None:
            try:
                conn.execute(sql.SQL("set role {}").format(sql.Identifier(f"gwc_{role}")))
                conn.commit()
            except psycopg.OperationalError as e:  # the server went away meanwhile
                conn.close()
                raise DatabaseUnavailable(f"cell database connection lost at once: {one_line(e)}") from e
            except psycopg.Error as e:
                conn.close()
                raise DatabaseError(
                    f"cannot act as database role gwc_{role}: {one_line(e)} "
                    f"(has the schema been applied? try `gwc db init`)"
                ) from e
        return conn
    raise DatabaseUnavailable(
        f"cannot connect to the cell database at {_redact(url)} after {attempts} tries "
        f"({one_line(error) if error else 'no attempt'}): is the cell database running? try `gwc db start`"
    ) from error


def connect_any(url: str, application_name: str, promotion_wait: float = 0.0) -> psycopg.Connection[Any]:
    """psycopg.connect(url), but a multi-host URL's members are tried all at once, not in turn.

    libpq (and psycopg) try the members of `host=a,b,c` one after the other, each for up to
    `connect_timeout`: after a database failover whose old primary's host is dead (its packets lost,
    not refused) every connect paid that member's whole timeout before it tried the new primary. Here
    each member is tried in a thread of its own with the URL's options (target_session_attrs among
    them); the first that accepts wins and the others are closed. Once a member has refused and only
    silent ones are left, they are waited for at most SLOW_MEMBER_S: the caller's backoff tries again
    soon rather than waiting out a dead host's timeout. With `promotion_wait`, a member that refused
    for being a standby is watched until it is promoted (see PROMOTION_POLL_S), for that long."""
    given = conninfo_to_dict(url)
    options: dict[str, Any] = {"application_name": application_name, **TCP_WATCH}
    if "connect_timeout" not in given:
        options["connect_timeout"] = CONNECT_TIMEOUT_S
    attempts = conninfo_attempts({**given, **options})
    if len(attempts) < 2 and promotion_wait <= 0:
        return psycopg.connect(url, autocommit=False, **options)
    return _race(attempts, promotion_wait)


async def connect_async(cfg: Config, role: str, promotion_wait: float = 0.0) -> psycopg.AsyncConnection[Any]:
    """One try at a connection as role gwc_<role> (autocommit), for an event loop that must run no
    thread: the host agent, which forks lot scripts. Every member of a multi-host URL at once, as
    connect_any (and, with `promotion_wait`, its standbys watched for the one promoted);
    DatabaseUnavailable when none accepts, DatabaseError when the role cannot be taken."""
    if not _ROLE.match(role):
        raise DatabaseError(f"bad database role name {role!r}")
    url = database_url(cfg, role)
    given = conninfo_to_dict(url)
    options: dict[str, Any] = {"application_name": f"gwc_{role}", **TCP_WATCH}
    if "connect_timeout" not in given:
        options["connect_timeout"] = CONNECT_TIMEOUT_S
    attempts: list[dict[str, Any]] = await conninfo_attempts_async({**given, **options})
    loop = asyncio.get_running_loop()
    watch_until = loop.time() + promotion_wait
    watching = 0

    async def one(params: dict[str, Any]) -> psycopg.AsyncConnection[Any]:
        nonlocal watching
        try:
            return await psycopg.AsyncConnection.connect(**params, autocommit=True)
        except psycopg.Error as e:
            if promotion_wait <= 0 or not read_only_refusal(e):
                raise
            watching += 1
            try:
                promoted = await await_promotion_async(params, watch_until)
            finally:
                watching -= 1
            if promoted is None:
                raise
            return promoted

    pending = {asyncio.ensure_future(one(a)) for a in attempts}
    deadline = loop.time() + max(float(a.get("connect_timeout") or CONNECT_TIMEOUT_S) for a in attempts)
    errors: list[str] = []
    refused_at: float | None = None
    conn: psycopg.AsyncConnection[Any] | None = None
    try:
        while pending and conn is None:
            until = deadline if refused_at is None else min(deadline, refused_at + SLOW_MEMBER_S)
            if watching:
                until = max(until, watch_until)
            if until <= loop.time():
                break
            left = until - loop.time()
            done, pending = await asyncio.wait(pending, timeout=left, return_when=asyncio.FIRST_COMPLETED)
            for task in done:
                if (error := task.exception()) is not None:
                    errors.append(one_line(error))
                    refused_at = refused_at or loop.time()
                elif conn is None:
                    conn = task.result()
                else:
                    await task.result().close()
    finally:
        for task in pending:
            task.cancel()
    if conn is None:
        why = "; ".join(errors) or "no answer"
        raise DatabaseUnavailable(f"cannot connect to the cell database at {_redact(url)}: {why}")
    try:
        await conn.execute(sql.SQL("set role {}").format(sql.Identifier(f"gwc_{role}")))
    except psycopg.OperationalError as e:
        await conn.close()
        raise DatabaseUnavailable(f"cell database connection lost at once: {one_line(e)}") from e
    except psycopg.Error as e:
        await conn.close()
        raise DatabaseError(f"cannot act as database role gwc_{role}: {one_line(e)} (try `gwc db init`)") from e
    return conn


def _race(attempts: list[dict[str, Any]], promotion_wait: float = 0.0) -> psycopg.Connection[Any]:
    """The first of the members' connections to succeed (see connect_any); the others are closed."""
    done = threading.Condition()
    errors: list[str] = []
    won: list[psycopg.Connection[Any] | None] = []  # [conn] once one won, [None] once given up
    watching = [0]  # members being watched for a promotion
    start = time.monotonic()
    watch_until = start + promotion_wait

    def one(params: dict[str, Any]) -> None:
        try:
            conn = psycopg.connect(**params, autocommit=False)
        except psycopg.Error as e:
            promoted = None
            if promotion_wait > 0 and read_only_refusal(e):
                with done:
                    watching[0] += 1
                    done.notify_all()
                try:
                    promoted = await_promotion(params, watch_until, lambda: bool(won))
                finally:
                    with done:
                        watching[0] -= 1
            if promoted is None:
                with done:
                    errors.append(f"{params.get('host')}: {one_line(e)}")
                    done.notify_all()
                return
            conn = promoted
        with done:
            if not won:
                won.append(conn)
                done.notify_all()
                return
        conn.close()  # another member won, or the caller gave up

    for params in attempts:
        threading.Thread(target=one, args=(params,), name="gwc-db-connect", daemon=True).start()
    deadline = start + max(float(p.get("connect_timeout") or CONNECT_TIMEOUT_S) for p in attempts)
    refused_at: float | None = None
    with done:
        while not won and len(errors) < len(attempts):
            now = time.monotonic()
            if errors and refused_at is None:
                refused_at = now
            until = deadline if refused_at is None else min(deadline, refused_at + SLOW_MEMBER_S)
            if watching[0]:
                until = max(until, watch_until)
            if now >= until:
                break
            done.wait(until - now)
        if won:
            conn = won[0]
            assert conn is not None
            return conn
        won.append(None)
        silent = len(attempts) - len(errors)
        raise psycopg.OperationalError(
            "no member accepted: " + "; ".join(errors + ([f"{silent} silent"] if silent else []))
        )


def probe(cfg: Config) -> str | None:
    """Whether the cell database answers now: None if it does, else why not (for `gwc status`)."""
    try:
        with psycopg.connect(database_url(cfg), connect_timeout=3) as conn:
            conn.execute("select 1")
    except psycopg.Error as e:
        return one_line(e)
    return None
